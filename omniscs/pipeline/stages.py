"""The pipeline's stages, each written once and Prefect-free: ingest → plan → preview → fit → behavior → catalog.

Every stage takes the scene (its store path), the recorded plan where it needs one and its config, follows the
one reuse contract (``reuse.py``: content hash of inputs + config + stage version), reports through the one
progress contract (``progress.py``) and returns a ``StageRecord``. The flow, the CLI and the benchmarks call
these functions; none of them wires a stage of its own.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

from omniscs import catalog
from omniscs.errors import OmniscsError
from omniscs.ids import check_id
from omniscs.locks import output_lock
from omniscs.pipeline import layout
from omniscs.progress import Progress, no_progress
from omniscs.pipeline.records import SceneRequest, StageRecord
from omniscs.pipeline.reuse import StageKey, mark_done, produce, reusable
from omniscs.plan import PlanConfig, ScenePlan, make_plan
from omniscs.scene import (DatasetSource, StoreSource, SyntheticSource, load_scene, parse_source, source_from_dict,
                           write_source_scene)
from omniscs.storage import atomic_write_json, atomic_write_text

log = logging.getLogger(__name__)

#: Stage versions: bump one when its code changes what it writes (older outputs are then not reused).
INGEST_VERSION = 1
PLAN_VERSION = 1
PREVIEW_VERSION = 1
FIT_VERSION = 1
BEHAVIOR_VERSION = 1
ANNOTATE_VERSION = 1
REPLAY_VERSION = 1
DATASET_VERSION = 1

#: The plan file in a plan stage's folder.
PLAN_JSON = "plan.json"


def _waiting(progress: Progress, out: Path):
    """What a stage reports while another writer (another run, or the same scene twice) holds its output."""
    return lambda who: progress(0, None, f"waiting for {who or 'another writer'} to finish {Path(out).name}")


def _source(source) -> SyntheticSource | StoreSource | DatasetSource:
    if isinstance(source, (SyntheticSource, StoreSource, DatasetSource)):
        return source
    if isinstance(source, dict):
        return source_from_dict(source)
    return parse_source(str(source))


# ----------------------------------------------------------------------------- ingest
def ingest_stage(source, workspace: str | Path, progress: Progress = no_progress,
                 scenes_root: str | Path | None = None, reuse: bool = True) -> StageRecord:
    """One source (a parsed source, its dict, or its text) as a validated scene store under
    ``scenes_root`` (default ``<workspace>/scenes``). A store made from the same source (and, for recorded
    datasets, unchanged dataset files) is reused unless ``reuse`` is False; an existing scene-store path is
    used in place."""
    started = time.perf_counter()
    src = _source(source)
    if isinstance(src, StoreSource):
        scene = src.verify()  # used in place: every file checked against the sizes and hashes it was written with
        return StageRecord("ingest", scene.scene_id, str(scene.path), reused=True,
                           seconds=time.perf_counter() - started, info={"source": src.to_dict()})
    fingerprint = None
    if isinstance(src, DatasetSource):
        from omniscs.scene.sources import current_fingerprint, resolve

        src = resolve(src)
        fingerprint = current_fingerprint(src)
    from omniscs.scene.store import SCHEMA_VERSION

    key = StageKey.of("ingest", INGEST_VERSION, src.to_dict(), {"dataset_files": fingerprint,
                                                                "schema": SCHEMA_VERSION})
    out = Path(scenes_root) if scenes_root is not None else layout.scenes_dir(workspace)
    out = out / check_id("scene id", src.scene_id())
    with output_lock(out, _waiting(progress, out)):
        reused = reuse and reusable(out, key) is not None
        if not reused:
            write_source_scene(src, out, progress=progress)
            mark_done(out, key, {"scene_store": "."}, time.perf_counter() - started)
    scene = load_scene(out)  # validates a reused store as well
    return StageRecord("ingest", scene.scene_id, str(out), reused=reused, seconds=time.perf_counter() - started,
                       key=key.digest, info={"source": src.to_dict()})


# ----------------------------------------------------------------------------- plan
def plan_config_for(request: SceneRequest) -> PlanConfig:
    """The plan's thresholds and Gaussian budget: the fit preset's when a graph is fitted, else the defaults."""
    if request.fit_preset is None:
        return PlanConfig()
    from omniscs.nsg.config import fit_preset

    return fit_preset(request.fit_preset).plan


def plan_stage(scene_path: str | Path, request: SceneRequest, workspace: str | Path,
               plan_config: PlanConfig | None = None) -> StageRecord:
    """What this scene needs modelled for the request (``plan.make_plan``), computed once, written to
    ``plans/<scene_id>/plan-<key>/plan.json``, catalogued in ``plans`` and passed to every later stage."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    config = plan_config or plan_config_for(request)
    edits = request.parsed_edits()
    if request.behavior_variants > 0:
        check_behavior_request(scene, request)
    plan = make_plan(scene, edits, config, behavior_variants=request.behavior_variants,
                     fit_nsg=request.fit_preset is not None, annotate=request.annotate,
                     appearance_variants=request.appearance_variants)
    key = StageKey.of("plan", PLAN_VERSION, scene.content_hash, plan.to_dict())
    out = layout.stage_folder(workspace, "plan", scene.scene_id, f"plan-{key.short}")
    with output_lock(out):
        reused = reusable(out, key) is not None
        if not reused:
            produce(out, key, lambda tmp: (atomic_write_text(tmp / PLAN_JSON, plan.to_json() + "\n"),
                                           {"plan": PLAN_JSON})[1])
    row = plan_row(plan, key.short, out / PLAN_JSON, reused)
    return StageRecord("plan", scene.scene_id, str(out / PLAN_JSON), reused=reused,
                       seconds=time.perf_counter() - started, key=key.digest, rows={"plans": [row]},
                       info={"summary": plan.summary(), "stages": dict(plan.stages)})


def check_behavior_request(scene, request: SceneRequest) -> None:
    """A log too short for behaviour variants fails at its plan, before any fitting (the checks the behavior
    stage would make first: the checkpoint loads, the preset exists, the log covers the model's horizon)."""
    from omniscs.scs.behavior import adversarial_preset, traffic_from_scene
    from omniscs.scs.behavior.checkpoint import load_checkpoint
    from omniscs.scs.behavior.problem import now_and_horizon

    now_and_horizon(traffic_from_scene(scene), load_checkpoint(request.behavior_checkpoint).config,
                    adversarial_preset(request.behavior_preset))


def load_plan(record_or_path: StageRecord | str | Path) -> ScenePlan:
    """The plan a plan stage recorded."""
    path = record_or_path.path if isinstance(record_or_path, StageRecord) else record_or_path
    return ScenePlan.from_dict(json.loads(Path(path).read_text()))


def plan_row(plan: ScenePlan, plan_id: str, path: Path, reused: bool) -> dict:
    """The plan's row of the ``plans`` catalog table."""
    return {"scene_id": plan.scene_id, "plan_id": plan_id, "content_hash": plan.content_hash,
            "agent_nodes": list(plan.agent_nodes), "n_agent_nodes": len(plan.agent_nodes),
            "node_reasons_json": json.dumps({str(k): v for k, v in plan.node_reasons.items()}, sort_keys=True),
            "n_background_tracks": len(plan.background_tracks), "needs_360": list(plan.needs_360),
            "background_repair": list(plan.background_repair), "inserted": list(plan.inserted),
            "cameras": list(plan.cameras), "n_train_frames": len(plan.train_frames),
            "n_heldout_frames": len(plan.heldout_frames), "modelled_area_m2": float(plan.modelled_area_m2),
            "gaussian_budget": int(plan.gaussian_budget),
            "stages": sorted(s for s, on in plan.stages.items() if on), "plan_path": str(path), "reused": reused}


# ----------------------------------------------------------------------------- preview
def preview_stage(scene_path: str | Path, workspace: str | Path) -> StageRecord:
    """Contact sheet (boxes projected) and BEV plot under ``previews/<scene_id>/``."""
    from omniscs.preview import write_previews

    started = time.perf_counter()
    scene = load_scene(scene_path)
    key = StageKey.of("preview", PREVIEW_VERSION, scene.content_hash, {})
    out = layout.scene_folder(workspace, "preview", scene.scene_id)
    with output_lock(out):
        reused = reusable(out, key) is not None
        if not reused:
            produce(out, key, lambda tmp: {k: p.name for k, p in write_previews(scene, tmp).items()})
    return StageRecord("preview", scene.scene_id, str(out), reused=reused, seconds=time.perf_counter() - started,
                       key=key.digest)


# ----------------------------------------------------------------------------- fit
def fit_stage(scene_path: str | Path, plan: ScenePlan, preset: str, workspace: str | Path | None = None,
              progress: Progress = no_progress, out_dir: str | Path | None = None, reuse: bool = True,
              replace: bool = True, **overrides) -> StageRecord:
    """Fit (or reuse) the scene graph the plan asks for with a preset (``overrides`` replace preset fields);
    checkpoint in ``out_dir`` (default ``models/<scene_id>/nsg-<preset>-<key>/``) and one ``models`` row. A
    diverged fit is a row with status 'diverged' and nothing on disk, so the rest of a run goes on.
    ``reuse=False`` fits again even when an identical fit exists (benchmarks time the fit itself);
    ``replace=False`` refuses an ``out_dir`` that holds something else (a user's folder)."""
    from omniscs.nsg.checkpoint import load_metrics
    from omniscs.nsg.config import fit_preset
    from omniscs.nsg.train import FitDiverged, fit_scene

    started = time.perf_counter()
    scene = load_scene(scene_path)
    if not plan.stages.get("fit_nsg", True):
        return StageRecord.skip("fit", scene.scene_id, "the request fits no scene graph")
    config = fit_preset(preset, **overrides)
    key = StageKey.of("fit", FIT_VERSION, {"scene": scene.content_hash, "plan": plan.to_dict()},
                      _result_config(config.to_dict()))
    name = f"nsg-{preset}-{key.short}"
    if out_dir is None:
        if workspace is None:
            raise OmniscsError("fit_stage needs a workspace or an out_dir")
        out_dir = layout.stage_folder(workspace, "fit", scene.scene_id, name)
    out_dir = Path(out_dir)
    row = {"scene_id": scene.scene_id, "model_id": name, "kind": "nsg", "preset": preset,
           "n_agent_nodes": len(plan.agent_nodes), "agent_nodes": list(plan.agent_nodes),
           "iterations": config.iterations}
    with output_lock(out_dir, _waiting(progress, out_dir)):
        found = reusable(out_dir, key)
        if out_dir.exists() and not replace and (found is None or not reuse):
            raise OmniscsError(f"{out_dir} already exists and holds another fit; choose another folder or "
                               "overwrite it")
        if reuse and found is not None:
            metrics = load_metrics(out_dir)
            row.update(_metric_fields(metrics), status="fitted", checkpoint_path=str(out_dir), reused=True)
            return StageRecord("fit", scene.scene_id, str(out_dir), reused=True,
                               seconds=time.perf_counter() - started, key=key.digest, rows={"models": [row]},
                               info={"status": "fitted", "metrics": metrics})
        try:
            result = fit_scene(scene, config, plan, progress=progress, checkpoint_dir=out_dir, overwrite=True)
        except FitDiverged as exc:
            row.update(status="diverged", checkpoint_path=None, reused=False, error=str(exc))
            return StageRecord("fit", scene.scene_id, None, seconds=time.perf_counter() - started, key=key.digest,
                               rows={"models": [row]}, info={"status": "diverged", "error": str(exc)})
        mark_done(out_dir, key, {"checkpoint": "."}, time.perf_counter() - started)
    row.update(_metric_fields(result.metrics), status="fitted", checkpoint_path=str(out_dir), reused=False)
    return StageRecord("fit", scene.scene_id, str(out_dir), seconds=time.perf_counter() - started, key=key.digest,
                       rows={"models": [row]}, info={"status": "fitted", "metrics": result.metrics})


def _metric_fields(metrics: dict) -> dict:
    return {k: metrics.get(k) for k in ("n_gaussians", "fit_seconds", "train_psnr", "heldout_psnr", "heldout_ssim")}


#: Config fields that change how fast a stage runs, not what it makes: left out of stage keys.
EXECUTION_FIELDS = ("device", "torch_threads")


def _result_config(config: dict) -> dict:
    return {k: v for k, v in config.items() if k not in EXECUTION_FIELDS}


# ----------------------------------------------------------------------------- behaviour variants
def behavior_stage(scene_path: str | Path, plan: ScenePlan, n_variants: int, workspace: str | Path | None = None,
                   preset: str = "balanced", checkpoint: str | Path | None = None, model: StageRecord | None = None,
                   progress: Progress = no_progress, out_dir: str | Path | None = None,
                   adversarial_overrides: dict | None = None, appearance_render=None,
                   reuse: bool = True) -> StageRecord:
    """``n_variants`` behaviour-level SCS variants of the scene (variants.json, one BEV PNG each, ``variants``
    rows) in ``out_dir`` (default ``variants/<scene_id>/behavior-<key>/``). With the scene's fitted graph
    (``model``, the fit stage's record) the optimisation adds L_app rendered by it; that graph's key is part
    of this stage's key, so variants with L_app are reused like any other (unless ``reuse`` is False)."""
    from omniscs.scs.behavior import adversarial_preset, traffic_from_scene
    from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT, checkpoint_hash
    from omniscs.scs.behavior.scene_render import AppearanceRenderConfig, appearance_from_checkpoint
    from omniscs.scs.behavior.variants import write_scene_variants

    started = time.perf_counter()
    scene = load_scene(scene_path)
    if not plan.stages.get("behavior_variants") or n_variants < 1:
        return StageRecord.skip("behavior", scene.scene_id, "the request asks for no behaviour variants")
    config = adversarial_preset(preset, **(adversarial_overrides or {}))
    ckpt = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
    graph = model if model is not None and model.info.get("status") == "fitted" else None
    render = appearance_render or AppearanceRenderConfig()
    key = StageKey.of("behavior", BEHAVIOR_VERSION,
                      {"scene": scene.content_hash, "plan": plan.to_dict(), "graph": graph.key if graph else None},
                      {"adversarial": _result_config(dataclasses.asdict(config)), "checkpoint": checkpoint_hash(ckpt),
                       "n_variants": int(n_variants),
                       "appearance": dataclasses.asdict(render) if graph else None})
    if out_dir is None:
        if workspace is None:
            raise OmniscsError("behavior_stage needs a workspace or an out_dir")
        out_dir = layout.stage_folder(workspace, "behavior", scene.scene_id, f"behavior-{key.short}")
    out_dir = Path(out_dir)
    with output_lock(out_dir, _waiting(progress, out_dir)):
        manifest = reusable(out_dir, key) if reuse else None
        if manifest is None:
            traffic = traffic_from_scene(scene)
            appearance = (appearance_from_checkpoint(graph.path, scene, traffic, ckpt, config, render)
                          if graph is not None else None)

            def make(tmp: Path) -> dict:
                result = write_scene_variants(traffic, tmp, n_variants, ckpt, config, appearance,
                                              progress=progress, published_dir=out_dir)
                if not result.rows:
                    raise OmniscsError(f"scene {scene.scene_id} has no vehicle besides the ego at the now step; "
                                       "no behaviour variant can be made")
                return {"variants": result.variants_json.name, "catalog_rows": "catalog_rows.json",
                        "bev": [p.name for p in result.bev_pngs]}

            produce(out_dir, key, make)
    rows = json.loads((out_dir / "catalog_rows.json").read_text())
    return StageRecord("behavior", scene.scene_id, str(out_dir / "variants.json"), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest, rows={"variants": rows},
                       info={"n_variants": len(rows), "n_success": sum(bool(r["success"]) for r in rows),
                             "appearance_term": graph is not None})


# ----------------------------------------------------------------------------- render + annotate
def replay_stage(scene_path: str | Path, model: StageRecord, workspace: str | Path, progress: Progress = no_progress,
                 reuse: bool = True) -> StageRecord:
    """Every logged view of the scene rendered through its fitted graph, unedited, with its PSNR against the logged
    image (``omniscs.annotate.replay``), in ``replays/<scene_id>/replay-<key>/``: made once per graph, read by
    every annotate run on it for the fidelity proxies."""
    from omniscs.annotate.scene import replay_scene
    from omniscs.nsg.checkpoint import load_checkpoint

    started = time.perf_counter()
    scene = load_scene(scene_path)
    if model is None or model.info.get("status") != "fitted":
        return StageRecord.skip("replay", scene.scene_id, "no fitted scene graph")
    key = StageKey.of("replay", REPLAY_VERSION, {"scene": scene.content_hash, "graph": model.key}, {})
    out = layout.stage_folder(workspace, "replay", scene.scene_id, f"replay-{key.short}")
    with output_lock(out, _waiting(progress, out)):
        manifest = reusable(out, key) if reuse else None
        if manifest is None:
            graph = load_checkpoint(model.path, scene)
            manifest = produce(out, key, lambda tmp: replay_scene(graph, scene, tmp, progress))
            reused = False
        else:
            reused = True
    return StageRecord("replay", scene.scene_id, str(out), reused=reused, seconds=time.perf_counter() - started,
                       key=key.digest, info={k: manifest.get("outputs", {}).get(k)
                                             for k in ("n_views", "mean_logged_psnr")})


def annotate_stage(scene_path: str | Path, plan: ScenePlan, model: StageRecord | None, behavior: StageRecord | None,
                   workspace: str | Path, config=None, progress: Progress = no_progress,
                   reuse: bool = True, appearance: StageRecord | None = None) -> StageRecord:
    """Every behaviour variant of the scene rendered through its fitted graph and annotated (``omniscs.annotate``),
    the ego on its solution: one scene store per variant, ``rows.json`` and a BEV per variant, in
    ``annotated/<scene_id>/annotate-<key>/``. Procedural scenes are compared with the world's exact render (unless
    ``config.exact_fidelity`` is off). ``appearance`` (the appearance stage's record) adds its variants, composed
    from their pool's models; with procedural scenes their exact reference inserts the library asset each pool
    model was built from."""
    from omniscs.annotate import AnnotateConfig
    from omniscs.annotate.replay import Replay
    from omniscs.annotate.scene import annotate_variants
    from omniscs.nsg.checkpoint import load_checkpoint
    from omniscs.pipeline.procedural import world_description, world_reference
    from omniscs.scs.behavior import traffic_from_scene
    from omniscs.scs.behavior.solution import SolutionConfig, solve_ego, solution_bev_picture

    started = time.perf_counter()
    scene = load_scene(scene_path)
    if not plan.stages.get("render_annotate"):
        return StageRecord.skip("annotate", scene.scene_id, "the request builds no dataset")
    behavior = behavior if behavior is not None and not behavior.skipped else None
    appearance = appearance if appearance is not None and not appearance.skipped else None
    if model is None or model.info.get("status") != "fitted" or (behavior is None and appearance is None):
        return StageRecord.skip("annotate", scene.scene_id, "no fitted scene graph or no variants to render")
    config = config or AnnotateConfig()
    solution_config = SolutionConfig()
    inputs = {"scene": scene.content_hash, "graph": model.key, "variants": None if behavior is None else behavior.key}
    if appearance is not None:
        inputs["appearance"] = appearance.key
    key = StageKey.of("annotate", ANNOTATE_VERSION, inputs,
                      {"annotate": config.to_dict(), "solution": dataclasses.asdict(solution_config)})
    out = layout.stage_folder(workspace, "annotate", scene.scene_id, f"annotate-{key.short}")
    with output_lock(out, _waiting(progress, out)):
        manifest = reusable(out, key) if reuse else None
        if manifest is None:
            variants = json.loads(Path(behavior.path).read_text()) if behavior is not None else []
            if appearance is not None:
                variants += json.loads(Path(appearance.path).read_text())
            traffic = traffic_from_scene(scene)
            replay = None
            if config.fidelity_every:  # the proxies compare with the unedited logged views: rendered once per graph
                replayed = replay_stage(scene_path, model, workspace, progress=progress)
                replay = Replay.open(replayed.path)
            graph = load_checkpoint(model.path, scene)

            def make(tmp: Path) -> dict:
                results = annotate_variants(
                    graph, scene, variants, tmp, solve=lambda v: solve_ego(v, traffic, solution_config),
                    reference=world_reference(scene) if config.exact_fidelity else None,
                    describe=world_description(scene), config=config,
                    progress=progress, replay=replay,
                    picture=lambda v, sol, png: solution_bev_picture(v, sol, traffic, png),
                    compose=appearance_composer(graph), reference_for=appearance_references(scene, variants)
                    if config.exact_fidelity else None)
                return {"stores": [r.store.name for r in results], "rows": "rows.json"}

            produce(out, key, make)
    from omniscs.annotate.scene import read_rows

    rows = read_rows(out)
    summaries = rows["variants"]
    return StageRecord("annotate", scene.scene_id, str(out), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest,
                       info={"n_variants": len(summaries), "n_images": len(rows["samples"]),
                             "n_annotations": len(rows["annotations"]),
                             "n_ego_solved": sum(bool(v.get("ego_solved")) for v in summaries)})


def appearance_composer(graph):
    """``variant -> Composite`` of appearance variants over ``graph``: objects from the variant's pool (or the graph's
    own ``nsg:`` nodes), colours through its colour transform (``omniscs.scs.appearance.compose``)."""
    from omniscs.agents.pool import model_resolver
    from omniscs.nsg.edit import node_model_resolver
    from omniscs.scs.appearance.compose import compose_variant

    def compose(variant: dict):
        pool = variant.get("pool")
        resolve = model_resolver(pool, node_model_resolver(graph)) if pool else node_model_resolver(graph)
        return compose_variant(graph, variant, resolve)
    return compose


def appearance_references(scene, variants: list[dict]):
    """``variant -> Reference`` (exact images) of a procedural scene's appearance variants, else None."""
    from omniscs.agents.pool import Pool
    from omniscs.pipeline.procedural import appearance_reference, pool_asset_of

    pools = {v["pool"] for v in variants if v.get("kind") == "appearance" and v.get("pool")}
    if scene.world is None or not pools:
        return None
    by_pool = {p: appearance_reference(scene, pool_asset_of(Pool(p))) for p in pools}
    return lambda variant: by_pool[variant["pool"]](variant) if variant.get("pool") in by_pool else None


# ----------------------------------------------------------------------------- dataset
def dataset_stage(annotated: list[StageRecord], workspace: str | Path, dataset_id: str | None = None,
                  facts: dict | None = None, reuse: bool = True) -> StageRecord:
    """Gather the annotate stages' outputs of a run into ``datasets/<dataset_id>/`` (variant stores, BEVs,
    preview, card; ``omniscs.annotate.dataset``) with its ``datasets``, ``samples`` and ``annotations`` rows.
    ``dataset_id`` defaults to ``ds-<key>``: the same annotated inputs give the same dataset, reused."""
    from omniscs.annotate.dataset import CARD_JSON, PREVIEW_PNG

    started = time.perf_counter()
    done = [r for r in annotated if r is not None and not r.skipped and r.path]
    if not done:
        raise OmniscsError("no scene of this run has annotated variants; a dataset needs at least one")
    facts = dict(facts or {})
    key = StageKey.of("dataset", DATASET_VERSION, sorted(r.key for r in done), facts)
    dataset_id = check_id("dataset id", dataset_id or f"ds-{key.short}")
    out = layout.dataset_folder(workspace, dataset_id)
    with output_lock(out):
        manifest = reusable(out, key) if reuse else None
        if manifest is None:
            produce(out, key, lambda tmp: _assemble(tmp, out, done, dataset_id, facts))
    rows = json.loads((out / "rows.json").read_text())
    card = json.loads((out / CARD_JSON).read_text())
    c, fid = card["counts"], card["fidelity"]

    def mean(stat):
        return None if stat is None else stat["mean"]

    dataset_row = {"dataset_id": dataset_id, "path": str(out), "content_hash": key.digest,
                   "reused": manifest is not None, "scene_ids": sorted({r.scene_id for r in done}),
                   "n_scenes": c["scenes"], "n_variants": c["variants"], "n_frames": c["frames"],
                   "n_samples": c["images"], "n_annotations": c["annotations"], "n_ego_solved": c["ego_solved"],
                   "fidelity_psnr": mean(fid["variant_psnr"]), "fidelity_ssim": mean(fid["variant_ssim"]),
                   "fidelity_masked_psnr": mean(fid["variant_masked_psnr"]),
                   "feature_drift": mean(fid.get("variant_feature_drift")), "card_path": str(out / CARD_JSON),
                   "preview_path": str(out / PREVIEW_PNG),
                   "config_json": json.dumps(facts.get("config"), sort_keys=True, default=str)}
    return StageRecord("dataset", dataset_id, str(out), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest,
                       rows={"datasets": [dataset_row], "samples": rows["samples"],
                             "annotations": rows["annotations"]},
                       info={"dataset_id": dataset_id, "counts": c})


def _assemble(tmp: Path, final: Path, annotated: list[StageRecord], dataset_id: str, facts: dict) -> dict:
    from omniscs.annotate.dataset import CARD_JSON, CARD_MD, PREVIEW_PNG, assemble_dataset

    made = assemble_dataset([r.path for r in annotated], tmp, final, dataset_id, facts)
    atomic_write_json(tmp / "rows.json", {"samples": made["samples"], "annotations": made["annotations"]})
    return {"card": CARD_JSON, "readme": CARD_MD, "preview": PREVIEW_PNG, "rows": "rows.json"}


def catalog_dataset_stage(run_id: str, workspace: str | Path, record: StageRecord) -> list[str]:
    """The dataset's rows (``datasets``, ``samples``, ``annotations``), one new Parquet file per table."""
    root = layout.catalog_root(workspace)
    writer = f"dataset-{record.scene_id}"
    written = [catalog.write_rows(root, table, run_id, rows, writer=writer) for table, rows in record.rows.items()]
    return [str(p) for p in written if p is not None]


# ----------------------------------------------------------------------------- catalog
def catalog_scene_stage(run_id: str, workspace: str | Path, records: list[StageRecord]) -> list[str]:
    """One new Parquet file per catalog table for this scene: its scene, agent and frame rows (from the
    ingested store) and every row the scene's stages produced; returns the files written."""
    from omniscs.scene.summary import agent_rows, frame_rows, scene_row

    by_stage = {r.stage: r for r in records}
    ingest = by_stage["ingest"]
    scene = load_scene(ingest.path)
    preview = by_stage.get("preview")
    root = layout.catalog_root(workspace)
    writer = f"scene-{scene.scene_id}"
    agents = agent_rows(scene)
    tables: dict[str, list[dict]] = {
        "agents": agents, "frames": frame_rows(scene),
        "scenes": [scene_row(scene, agents, ingest.reused, ingest.seconds,
                             preview.path if preview is not None and not preview.skipped else None)]}
    for r in records:
        for table, rows in r.rows.items():
            tables.setdefault(table, []).extend(rows)
    written = [catalog.write_rows(root, table, run_id, rows, writer=writer) for table, rows in tables.items()]
    return [str(p) for p in written if p is not None]


def catalog_run_stage(run_id: str, workspace: str | Path, flow: str, status: str, started_at_us: int,
                      finished_at_us: int, n_scenes: int, config: dict, error: str | None = None,
                      flow_run_id: str | None = None) -> str:
    """The run's row in ``runs`` (written last, so a run row means the run ended, well or not); ``flow_run_id``:
    the orchestrator's id of the run (what its events name), when there is one."""
    import omniscs

    path = catalog.write_rows(layout.catalog_root(workspace), "runs", run_id, [{
        "flow": flow, "status": status, "started_at_us": started_at_us, "finished_at_us": finished_at_us,
        "n_scenes": n_scenes, "config_json": json.dumps(config, sort_keys=True, default=str),
        "omniscs_version": omniscs.__version__, "error": error, "flow_run_id": flow_run_id}], writer="run")
    return str(path)


def device_overrides(request: SceneRequest) -> dict:
    """The request's device as a config override (nothing for the CPU, every config's default)."""
    return {} if request.device == "cpu" else {"device": request.device}


# ----------------------------------------------------------------------------- one scene, start to end
def run_scene(source, request: SceneRequest, workspace: str | Path, run_id: str | None = None,
              progress_for=None) -> list[StageRecord]:
    """Every stage for one scene, in pipeline order, without an orchestrator (benchmarks and tests; the
    ``generate_dataset`` flow runs the same stages as Prefect tasks). ``progress_for(stage) -> Progress``
    gives each long stage its progress sink. With ``run_id`` the scene is catalogued."""
    def sink(stage: str) -> Progress:
        return progress_for(stage) if progress_for is not None else no_progress

    ingested = ingest_stage(source, workspace, progress=sink("ingest"))
    planned = plan_stage(ingested.path, request, workspace)
    plan = load_plan(planned)
    records = [ingested, planned]
    if request.previews:
        records.append(preview_stage(ingested.path, workspace))
    fitted = None
    if plan.stages.get("fit_nsg"):
        fitted = fit_stage(ingested.path, plan, request.fit_preset, workspace, progress=sink("fit"),
                           **device_overrides(request))
        records.append(fitted)
        if plan.stages.get("agent_models"):
            from omniscs.pipeline.agents import agents_stage

            completed = agents_stage(ingested.path, plan, fitted, workspace, request.pool, progress=sink("agents"))
            records.append(completed)
            fitted = completed if not completed.skipped else fitted
        if plan.stages.get("background_repair"):
            from omniscs.pipeline.background import background_stage

            repaired = background_stage(ingested.path, plan, fitted, workspace, progress=sink("background"))
            records.append(repaired)
            fitted = repaired if not repaired.skipped else fitted
    behaved = None
    if plan.stages.get("behavior_variants"):
        behaved = behavior_stage(ingested.path, plan, request.behavior_variants, workspace,
                                 request.behavior_preset, request.behavior_checkpoint, fitted,
                                 progress=sink("behavior"), adversarial_overrides=device_overrides(request))
        records.append(behaved)
    composed = None
    if plan.stages.get("appearance_variants"):
        from omniscs.pipeline.appearance import appearance_stage

        composed = appearance_stage(ingested.path, plan, fitted, request.appearance_variants, request.pool, workspace,
                                    request.appearance_objects, progress=sink("appearance"))
        records.append(composed)
    if plan.stages.get("render_annotate"):
        records.append(annotate_stage(ingested.path, plan, fitted, behaved, workspace, progress=sink("annotate"),
                                      appearance=composed))
    if run_id is not None:
        catalog_scene_stage(run_id, workspace, records)
    return records
