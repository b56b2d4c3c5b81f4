"""The annotate stage: every variant of one scene rendered through its scene graph (behaviour variants with the ego
on its avoiding solution, appearance variants with their pool objects composed) with its automatic ground truth;
and the replay it compares with (the unedited logged views, rendered once per graph)."""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

from omniscs.agents.pool import Pool, model_resolver
from omniscs.annotate import AnnotateConfig
from omniscs.annotate.replay import Replay
from omniscs.annotate.scene import annotate_variants, read_rows, replay_scene
from omniscs.annotate.variant import COMPOSED
from omniscs.gates import GateConfig
from omniscs.locks import output_lock
from omniscs.nsg.checkpoint import load_graph
from omniscs.nsg.edit import node_model_resolver
from omniscs.pipeline import layout
from omniscs.pipeline.background import variant_uncovers
from omniscs.pipeline.common import waiting
from omniscs.pipeline.procedural import (appearance_lidar, appearance_reference, appearance_renderer, pool_asset_of,
                                        variant_renderer, world_description, world_lidar, world_reference)
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.plan import ScenePlan
from omniscs.progress import Progress, no_progress
from omniscs.scene import load_scene
from omniscs.scs.appearance.colour import scene_colour_transform
from omniscs.scs.appearance.compose import compose_variant
from omniscs.scs.appearance.variants import designed_catalog_row, designed_variant
from omniscs.scs.behavior import traffic_from_scene
from omniscs.scs.behavior.solution import SolutionConfig, solution_bev_picture, solve_ego
from omniscs.storage import atomic_write_json
from omniscs.untrusted import read_own_json

log = logging.getLogger(__name__)

#: Bump when the code changes what the stages write (older outputs are then not reused).
REPLAY_VERSION = 1
ANNOTATE_VERSION = 2  # 2: the 360° ring LiDAR (num_lidar_points of every box around the ego)
#: The designed variant's spec in an annotate stage folder (a ``variants.json`` of one entry).
DESIGNED_JSON = "designed.json"


def replay_stage(scene_path: str | Path, model: StageRecord, workspace: str | Path, progress: Progress = no_progress,
                 reuse: bool = True) -> StageRecord:
    """Every logged view of the scene rendered through its fitted graph, unedited, with its PSNR against the logged
    image (``omniscs.annotate.replay``), in ``replays/<scene_id>/replay-<key>/``: made once per graph, read by
    every annotate run on it for the fidelity proxies."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if model is None or model.info.get("status") != "fitted":
        return StageRecord.skip("replay", scene.scene_id, "no fitted scene graph")
    key = StageKey.of("replay", REPLAY_VERSION, {"scene": scene.content_hash, "graph": model.key}, {})
    out = layout.stage_folder(workspace, "replay", scene.scene_id, f"replay-{key.short}")
    with output_lock(out, waiting(progress, out)):
        manifest = reusable(out, key) if reuse else None
        if manifest is None:
            graph = load_graph(model.path, scene)
            manifest = produce(out, key, lambda tmp: replay_scene(graph, scene, tmp, progress))
            reused = False
        else:
            reused = True
    return StageRecord("replay", scene.scene_id, str(out), reused=reused, seconds=time.perf_counter() - started,
                       key=key.digest, info={k: manifest.get("outputs", {}).get(k)
                                             for k in ("n_views", "mean_logged_psnr")})


def annotate_stage(scene_path: str | Path, plan: ScenePlan, model: StageRecord | None, behavior: StageRecord | None,
                   workspace: str | Path, config=None, progress: Progress = no_progress,
                   reuse: bool = True, appearance: StageRecord | None = None,
                   uncovered: StageRecord | None = None, gates: GateConfig | None = None,
                   keep_failed: bool = False, designed: list[dict] | None = None,
                   pool: str | Path | None = None) -> StageRecord:
    """Every behaviour variant of the scene rendered through its fitted graph and annotated (``omniscs.annotate``),
    the ego on its solution: one scene store per variant, ``rows.json`` and a BEV per variant, in
    ``annotated/<scene_id>/annotate-<key>/``. Procedural scenes are compared with the world's exact render (unless
    ``config.exact_fidelity`` is off). ``appearance`` (the appearance stage's record) adds its variants, composed
    from their pool's models; with procedural scenes their exact reference inserts the library asset each pool
    model was built from. ``uncovered`` (the uncovered stage's record: ``model``'s graph repaired behind the objects
    some appearance variants uncover) is the graph those variants are composed on; every other variant keeps
    ``model``'s. With ``gates`` each variant gets its quality verdict; those failed before rendering are rendered
    only with ``keep_failed``, and spare candidates only until each level has as many passing variants as its
    stage was asked for (``omniscs.annotate.scene.annotate_variants``). ``designed`` (the request's edit objects)
    adds one designed variant (``d000``: those edits, models from ``pool``), rendered after the others, written as
    ``designed.json`` and catalogued in ``variants``."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if not plan.stages.get("render_annotate"):
        return StageRecord.skip("annotate", scene.scene_id, "the request builds no dataset")
    behavior = behavior if behavior is not None and not behavior.skipped else None
    appearance = appearance if appearance is not None and not appearance.skipped else None
    uncovered = uncovered if appearance is not None and uncovered is not None and not uncovered.skipped else None
    if model is None or model.info.get("status") != "fitted" or (behavior is None and appearance is None
                                                                  and not designed):
        return StageRecord.skip("annotate", scene.scene_id, "no fitted scene graph or no variants to render")
    config = config or AnnotateConfig()
    solution_config = SolutionConfig()
    inputs = {"scene": scene.content_hash, "graph": model.key, "variants": None if behavior is None else behavior.key}
    if appearance is not None:
        inputs["appearance"] = appearance.key
    if uncovered is not None:  # absent otherwise: runs without a repair for their variants keep their keys
        inputs["uncovered"] = uncovered.key
    if designed:  # likewise
        inputs["designed"] = {"edits": list(designed), "pool": None if pool is None else str(Path(pool).resolve())}
    wanted = {level: int(r.info.get("n_requested", r.info.get("n_variants", 0)))
              for level, r in (("behaviour", behavior), ("appearance", appearance)) if r is not None}
    if designed:
        wanted["designed"] = 1
    gated = {"gates": gates.to_dict(), "keep_failed": bool(keep_failed), "wanted": wanted} if gates else {}
    key = StageKey.of("annotate", ANNOTATE_VERSION, inputs,
                      {"annotate": config.to_dict(), "solution": dataclasses.asdict(solution_config), **gated})
    out = layout.stage_folder(workspace, "annotate", scene.scene_id, f"annotate-{key.short}")
    with output_lock(out, waiting(progress, out)):
        manifest = reusable(out, key) if reuse else None
        if manifest is None:
            variants = read_own_json(behavior.path, "run the behavior stage again", expect=list) \
                if behavior is not None else []
            if appearance is not None:
                variants += read_own_json(appearance.path, "run the appearance stage again", expect=list)
            traffic = traffic_from_scene(scene)
            replay = None
            if config.fidelity_every:  # the proxies compare with the unedited logged views: rendered once per graph
                replayed = replay_stage(scene_path, model, workspace, progress=progress)
                replay = Replay.open(replayed.path)
            graph = load_graph(model.path, scene)
            repaired = None
            objects = set(uncovered.info["repaired"]) if uncovered is not None else set()
            if uncovered is not None:
                repaired = (load_graph(uncovered.path, scene),
                            {v["variant_id"] for v in variants if objects & set(variant_uncovers(scene, v))})
            if appearance is not None and appearance.info.get("n_requested"):
                variants = without_unrepaired_spares(scene, variants, int(appearance.info["n_requested"]), objects)
            if designed:
                variants.append(designed_spec(graph, scene, plan, designed, pool, progress))

            def make(tmp: Path) -> dict:
                if designed:
                    atomic_write_json(tmp / DESIGNED_JSON, [variants[-1]])
                results = annotate_variants(
                    graph, scene, variants, tmp, solve=lambda v: solve_ego(v, traffic, solution_config),
                    describe=world_description(scene), config=config,
                    progress=progress, replay=replay,
                    picture=lambda v, sol, png: solution_bev_picture(v, sol, traffic, png),
                    compose=appearance_composer(graph, repaired), gates=gates, wanted=wanted if gates else None,
                    keep_failed=keep_failed, **exact_sensors(scene, variants, config))
                return {"stores": [r.store.name for r in results], "rows": "rows.json",
                        **({"designed": DESIGNED_JSON} if designed else {})}

            produce(out, key, make)
    rows = read_rows(out)
    summaries = rows["variants"]
    catalogued = {}
    if designed:
        spec = read_own_json(out / DESIGNED_JSON, f"the stage folder {out} is damaged; remove it and run again",
                             expect=list)
        catalogued = {"variants": [designed_catalog_row(v, out / DESIGNED_JSON) for v in spec]}
    return StageRecord("annotate", scene.scene_id, str(out), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest, rows=catalogued,
                       info={"n_variants": len(summaries), "n_images": len(rows["samples"]),
                             "n_annotations": len(rows["annotations"]),
                             "n_ego_solved": sum(bool(v.get("ego_solved")) for v in summaries),
                             "verdicts": variant_verdicts(rows)})


def designed_spec(graph, scene, plan: ScenePlan, edits: list[dict], pool: str | Path | None,
                  progress: Progress = no_progress) -> dict:
    """The designed variant of ``edits`` on ``scene`` (``designed_variant``): when they bring models of ``pool``
    (insert, replace_model of pm-... ids), its objects take the scene's colour transform, estimated as the
    appearance stage does."""
    spec = designed_variant(scene.scene_id, edits, None if pool is None else str(pool))
    if pool is not None and spec["object_id"] is not None:
        progress(0, 1, f"colour transform of {scene.scene_id} for the designed variant")
        spec["colour"] = scene_colour_transform(graph, scene, Pool(pool), plan.train_frames).to_dict()["affine"]
    return spec


def exact_sensors(scene, variants: list[dict], config: AnnotateConfig) -> dict:
    """``annotate_variants``' exact sensors of a procedural scene, empty for a recorded log: ``reference`` and
    ``reference_for`` (the exact images of behaviour and appearance variants, with ``config.exact_fidelity``) and
    ``lidar`` and ``lidar_for`` (their exact sweeps, with ``lidar_source`` world; else the sweeps come from the
    graph's depth). A variant's images and sweep share one ray-cast world; each pool's table is read once."""
    if scene.world is None:
        return {}
    worlds = variant_renderer(scene)
    pools = {v.get("pool") for v in variants if v.get("kind") in COMPOSED}
    placed = {p: appearance_renderer(scene, pool_asset_of(Pool(p) if p else None)) for p in pools}

    def per_pool(make):
        by_pool = {p: make(scene, None, renderer) for p, renderer in placed.items()}
        return lambda v: by_pool[v.get("pool")](v) if v.get("kind") in COMPOSED and v.get("pool") in by_pool \
            else None

    out = {}
    if config.exact_fidelity:
        out.update(reference=world_reference(scene, worlds), reference_for=per_pool(appearance_reference))
    if config.lidar_source == "world":
        out.update(lidar=world_lidar(scene, worlds), lidar_for=per_pool(appearance_lidar))
    return out


def variant_verdicts(rows: dict) -> dict[str, dict]:
    """{variant id: its quality verdict} of an annotate stage's ``rows.json``: rendered variants and those rejected
    before rendering (spare candidates that were not needed have none)."""
    out = {str(v["variant_id"]): v["gate"] for v in rows["variants"] if v.get("gate") is not None}
    out.update({str(r["variant_id"]): {"passed": r["passed"], "reasons": r["reasons"]}
                for r in rows.get("rejected") or []})
    return out


def without_unrepaired_spares(scene, variants: list[dict], n_requested: int, repaired: set[int]) -> list[dict]:
    """``variants`` less the spare appearance candidates (beyond the first ``n_requested``) that would uncover a
    large object no repair covers: rendered, they would show its ghost."""
    kept, seen = [], 0
    for v in variants:
        if v.get("kind") == "appearance":
            seen += 1
            if seen > n_requested and set(variant_uncovers(scene, v)) - repaired:
                log.info("spare appearance candidate %s is not rendered: it uncovers an object no repair covers",
                         v.get("variant_id"))
                continue
        kept.append(v)
    return kept


def appearance_composer(graph, repaired: tuple | None = None):
    """``variant -> Composite`` of appearance variants over ``graph``: objects from the variant's pool (or the graph's
    own ``nsg:`` nodes), colours through its colour transform (``omniscs.scs.appearance.compose``). ``repaired``:
    (a graph repaired behind the objects some variants uncover, the ids of those variants), composed over it
    instead."""
    def compose(variant: dict):
        base = repaired[0] if repaired is not None and variant.get("variant_id") in repaired[1] else graph
        pool = variant.get("pool")
        resolve = model_resolver(pool, node_model_resolver(base)) if pool else node_model_resolver(base)
        return compose_variant(base, variant, resolve)
    return compose


