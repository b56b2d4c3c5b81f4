"""The appearance stage (Prefect-free): after the graph is complete (fit, agents, background), draw the scene's
appearance-level SCS variants: pool objects replacing a vehicle's model or inserted at valid poses
(``omniscs.scs.appearance``), with the scene's colour transform estimated once. Written to
``variants/<scene_id>/appearance-<key>/`` (``variants.json``, ``placements.json``) with ``variants`` rows
(kind ``appearance``); the annotate stage renders them."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from omniscs.agents.dual import DualConfig, cropped_to_box, mirror_completed, seen_side, track_views
from omniscs.agents.pool import Pool, model_resolver
from omniscs.annotate.dataset import PREVIEW_PNG, SCENES, write_preview
from omniscs.annotate.scene import annotate_variants
from omniscs.edits import edit_to_dict
from omniscs.errors import OmniscsError
from omniscs.locks import output_lock
from omniscs.nsg.checkpoint import load_graph
from omniscs.nsg.edit import node_model_resolver
from omniscs.pipeline import layout
from omniscs.pipeline.closedloop import newest_checkpoint
from omniscs.pipeline.procedural import (appearance_lidar, appearance_reference, appearance_renderer,
                                        pool_asset_of, world_description)
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.plan import ScenePlan
from omniscs.progress import Progress, no_progress
from omniscs.scene import load_scene
from omniscs.scs.appearance.colour import IDENTITY, scene_colour_transform
from omniscs.scs.appearance.compose import (
    CompositeConfig,
    compose_variant,
    insert_variant,
    model_upright_box,
    new_track_id,
    replace_variant,
)
from omniscs.scs.appearance.placement import PlacementConfig, check_placement, placement_context
from omniscs.scs.appearance.variants import (
    AppearanceConfig,
    designed_variant,
    make_appearance_variants,
    replacement_check,
    write_appearance_variants,
)
from omniscs.storage import atomic_directory, atomic_write_json, workspace_root
from omniscs.untrusted import read_json, read_own_json

#: Bumped when the appearance stage changes what it writes.
APPEARANCE_VERSION = 1


def pool_objects(pool, objects=(), categories=None) -> list[str]:
    """The model ids to composite: ``objects`` checked against the pool, or every model of the pool (of
    ``categories`` when given), by id."""
    table = Pool(pool).table()
    if table.empty:
        raise OmniscsError(f"model pool {pool} is empty; build it first (omniscs pool build --assets pool --out {pool})")
    known = set(table.model_id)
    if objects:
        missing = [m for m in objects if m not in known]
        if missing:
            raise OmniscsError(f"object(s) {missing} are not models of pool {pool}; see `omniscs pool list {pool}`")
        for m in objects:  # a model without its views cannot be checked or matched: refused before any scene
            Pool(pool).keyframes(m)
        return list(objects)
    if categories:
        table = table[table.category.isin(list(categories))]
        if table.empty:
            raise OmniscsError(f"pool {pool} has no model of the categories {list(categories)}")
    return sorted(table.model_id)


def appearance_stage(scene_path: str | Path, plan: ScenePlan, model: StageRecord | None, n_variants: int,
                     pool: str | Path | None, workspace: str | Path | None = None, objects=(), config=None,
                     progress: Progress = no_progress, out_dir: str | Path | None = None,
                     reuse: bool = True, budget: int = 1) -> StageRecord:
    """``n_variants`` appearance variants of the scene drawn on its complete graph (``model``: the latest graph
    stage's record) with objects from ``pool`` (``objects``: model ids; empty: the whole pool), followed by spare
    candidates up to ``budget`` per requested variant: the annotate stage renders them in order until
    ``n_variants`` pass the quality gates."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if n_variants < 1 or not plan.stages.get("appearance_variants"):
        return StageRecord.skip("appearance", scene.scene_id, "the request asks for no appearance variants")
    if model is None or model.info.get("status") != "fitted":
        return StageRecord.skip("appearance", scene.scene_id, "no fitted scene graph to composite objects into")
    if pool is None:
        raise OmniscsError("appearance variants take their objects from a model pool: give --pool")
    config = config or AppearanceConfig()
    ids = pool_objects(pool, tuple(objects))
    key = StageKey.of("appearance", APPEARANCE_VERSION,
                      {"scene": scene.content_hash, "graph": model.key, "pool": str(Path(pool).resolve()),
                       "objects": ids},
                      {"appearance": config.to_dict(), "n_variants": int(n_variants),
                       **({"budget": int(budget)} if budget > 1 else {})})
    if out_dir is None:
        if workspace is None:
            raise OmniscsError("appearance_stage needs a workspace or an out_dir")
        out_dir = layout.stage_folder(workspace, "appearance", scene.scene_id, f"appearance-{key.short}")
    out_dir = Path(out_dir)
    with output_lock(out_dir):
        manifest = reusable(out_dir, key) if reuse else None
        if manifest is None:
            spare = int(n_variants) * (max(1, int(budget)) - 1)
            produce(out_dir, key, lambda tmp: _draw(scene, plan, model, pool, ids, n_variants, config, progress,
                                                    tmp, out_dir, spare))
    rows = read_own_json(out_dir / "catalog_rows.json",
                         f"the stage folder {out_dir} is damaged; remove it and run again",
                         expect=list)
    return StageRecord("appearance", scene.scene_id, str(out_dir / "variants.json"), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest, rows={"variants": rows},
                       info={"n_variants": len(rows), "n_requested": int(n_variants),
                             "placements": {r["variant_id"]: r["placement"] for r in rows}})


def _draw(scene, plan, model, pool, ids, n_variants, config, progress, tmp: Path, out_dir: Path,
          spare: int = 0) -> dict:
    graph = load_graph(model.path, scene)
    p = Pool(pool)
    progress(0, n_variants + 1, f"colour transform of {scene.scene_id}")
    colour = scene_colour_transform(graph, scene, p, plan.train_frames)
    resolve = model_resolver(pool, node_model_resolver(graph))
    drawn = make_appearance_variants(graph, scene, resolve, ids, n_variants, config, colour.to_dict(),
                                     progress, spare)
    for v in drawn.variants:
        v["colour"] = colour.to_dict()["affine"]
        v["pool"] = str(Path(pool).resolve())
    return write_appearance_variants(drawn, tmp, out_dir)


# ----------------------------------------------------------------------------- one scene, by hand (omniscs scs appearance)
def parse_pose(text: str) -> tuple[float, float, float, float, float]:
    """``x,y,yaw[,roll,pitch]`` (metres, degrees) -> (x, y, yaw rad, roll deg, pitch deg)."""
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) not in (3, 5) or not all(math.isfinite(v) for v in values):
        raise OmniscsError(f"--pose must be x,y,yaw or x,y,yaw,roll,pitch (metres, degrees; e.g. 20,-3.5,90,180,0); "
                           f"got {text!r}")
    x, y, yaw = values[:3]
    roll, pitch = values[3:] if len(values) == 5 else (0.0, 0.0)
    return x, y, math.radians(yaw), roll, pitch


def user_variants(scene, graph, resolve, insert: str | None = None, pose: str | None = None,
                  replace: int | None = None, with_model: str | None = None, config=None) -> list[dict]:
    """One appearance variant from a user's request: ``insert`` (model id) at ``pose`` or ``replace`` (track id)
    ``with_model``; the placement checks run on it and a failure is one OmniscsError saying which and why (never a
    silent overlap)."""
    config = config or AppearanceConfig()
    if (insert is None) == (replace is None):
        raise OmniscsError("give one of --insert MODEL --pose x,y,yaw[,roll,pitch], --replace TRACK --with MODEL, "
                           "or --sample N")
    context = placement_context(scene)
    if insert is not None:
        if pose is None:
            raise OmniscsError("--insert needs --pose x,y,yaw[,roll,pitch] (metres, degrees)")
        x, y, yaw, roll, pitch = parse_pose(pose)
        model = resolve(insert)
        box = model_upright_box(model, roll, pitch)
        ground = float(context.ground_z(np.array([[x, y]]))[0])
        check = check_placement(context, box, (x, y, ground + 0.5 * float(box[2]), yaw), config.placement)
        if not check.ok:
            raise OmniscsError(check.message() + "; choose another pose or let the sampler pick one (--sample N)")
        return [insert_variant(scene.scene_id, "a000", new_track_id(scene, graph), model, insert, x, y, ground, yaw,
                               roll, pitch)]
    if with_model is None:
        raise OmniscsError("--replace TRACK needs --with MODEL (a pool model id)")
    node = graph.agent(int(replace))  # a clear error for a track that is not a node
    model = resolve(with_model)
    check = replacement_check(context, node, model.size, config.placement)
    if not check.ok:
        raise OmniscsError(f"track {replace} with {with_model} ({model.size[0]:.1f} x {model.size[1]:.1f} m) in its "
                           f"place: " + "; ".join(check.failures))
    return [replace_variant(scene.scene_id, "a000", int(replace), model, with_model)]


def render_appearance_set(scene, graph, variants: list[dict], out: Path, pool=None, composite=None,
                          progress: Progress = no_progress) -> dict:
    """Render and annotate appearance ``variants`` of ``scene`` through ``graph`` into ``out`` (``variants.json``,
    one scene store per variant under ``scenes/``, ``rows.json``, ``preview.png``); procedural scenes are compared
    with the world's exact images. Returns the variants' summaries."""
    composite = composite or CompositeConfig()
    resolve = model_resolver(pool, node_model_resolver(graph)) if pool is not None else node_model_resolver(graph)
    worlds = appearance_renderer(scene, pool_asset_of(Pool(pool) if pool is not None else None))
    atomic_write_json(out / "variants.json", variants)
    results = annotate_variants(graph, scene, variants, out / SCENES, describe=world_description(scene),
                                progress=progress, compose=lambda v: compose_variant(graph, v, resolve, composite),
                                reference_for=appearance_reference(scene, None, worlds),
                                lidar_for=appearance_lidar(scene, None, worlds))
    samples = [s for r in results for s in r.samples]
    annotations = [a for r in results for a in r.annotations]
    if samples:
        write_preview(out, samples, annotations, out / PREVIEW_PNG)
    return {"variants": [r.summary for r in results], "n_images": len(samples), "n_annotations": len(annotations)}


def appearance_scene_set(scene_path, out: Path, pool=None, checkpoint=None, insert=None, pose=None, replace=None,
                         with_model=None, sample=None, objects=(), camera=None, distance="8,30", seed=0,
                         colour: bool = True, shadow: bool = True, workspace=None, edits: list | None = None,
                         progress: Progress = no_progress) -> dict:
    """What ``omniscs scs appearance`` does: the scene and its graph, the variants asked for (one by hand, ``sample``
    drawn, or ``edits``: an edit spec such as ``omniscs view`` saves, as one designed variant), the scene's colour
    transform, then ``render_appearance_set`` into ``out`` (a temporary folder that
    becomes ``out`` only when everything is written). ``unrepaired`` in the result lists the large static objects
    whose footprint the variants uncover (``omniscs.plan.repair_objects``): rendered here without the background
    repair that ``omniscs generate`` runs for them (its uncovered stage), they leave a ghost."""
    try:
        lo, hi = (float(v) for v in str(distance).split(","))
    except ValueError:
        raise OmniscsError(f"--distance must be lo,hi metres (e.g. 8,30); got {distance!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise OmniscsError(f"--distance must be finite; got {distance!r}")
    if sample is not None and (insert is not None or replace is not None):
        raise OmniscsError("--sample draws its own placements: give it without --insert/--replace")
    if edits and (sample is not None or insert is not None or replace is not None):
        raise OmniscsError("--edit is a whole designed scenario: give it without --sample/--insert/--replace")
    if sample is not None and sample < 1:
        raise OmniscsError(f"--sample must be at least 1; got {sample}")
    if pool is not None and not Path(pool).is_dir():
        raise OmniscsError(f"--pool {pool} is not a folder (make one with omniscs pool build or import)")
    scene = load_scene(scene_path)
    ckpt = Path(checkpoint) if checkpoint is not None else newest_checkpoint(workspace_root(workspace), scene.scene_id)
    graph = load_graph(ckpt, scene)
    if camera is not None:
        scene.camera(camera)  # a clear error for an unknown camera
    config = AppearanceConfig(seed=seed, placement=PlacementConfig(distance_m=(lo, hi), camera=camera),
                              composite=CompositeConfig(colour_fit=colour, shadow=shadow))
    resolve = model_resolver(pool, node_model_resolver(graph)) if pool is not None else node_model_resolver(graph)
    p = Pool(pool) if pool is not None else None
    transform = scene_colour_transform(graph, scene, p) if colour else None
    if edits:
        specs = [designed_variant(scene.scene_id, [edit_to_dict(e) for e in edits])]
    elif sample is not None:
        if p is None and not objects:
            raise OmniscsError("--sample takes its objects from --pool (or give --object ids)")
        ids = pool_objects(pool, tuple(objects)) if p is not None else list(objects)
        specs = make_appearance_variants(graph, scene, resolve, ids, sample, config, progress=progress).variants
    else:
        specs = user_variants(scene, graph, resolve, insert, pose, replace, with_model, config)
    for v in specs:
        v["colour"] = (transform.affine if transform is not None else IDENTITY).tolist()
        if pool is not None:
            v["pool"] = str(Path(pool).resolve())
    from omniscs.pipeline.background import variant_uncovers  # the background stages import this module's users

    unrepaired = sorted({t for v in specs for t in variant_uncovers(scene, v)})
    with atomic_directory(Path(out), overwrite=True) as tmp:
        result = render_appearance_set(scene, graph, specs, tmp, pool, config.composite, progress)

        atomic_write_json(tmp / "colour.json", None if transform is None else transform.to_dict())
    return {"specs": specs, **result, "unrepaired": unrepaired}


# ----------------------------------------------------------------------------- models of what a detector missed
def _source_scene(workspace: Path, store_id: str) -> str | None:
    """The workspace scene a dataset's (or a log's) store id comes from: a variant store names its source scene in
    its manifest; a logged scene is its own source."""
    if (layout.scene_folder(workspace, "ingest", store_id) / "manifest.json").is_file():
        return store_id
    for manifest in sorted(Path(workspace).glob(f"{layout.FOLDERS['dataset']}/*/scenes/{store_id}/manifest.json")):
        source = read_json(manifest, "the dataset's scene store is damaged; build the dataset again", expect=dict,
                           what="manifest").get("source_scene_id")
        if source:
            return str(source)
    return None


def missed_object_models(missed_json: Path, workspace: Path, pool: Path, limit: int = 20,
                         progress: Progress = no_progress) -> list[dict]:
    """A pool model for each missed object of ``omniscs scs mine``'s picks (``missed.json``) that can be traced to a
    track of a fitted scene of ``workspace``: the track's node in the scene's newest graph, cut to its box and
    completed by mirror symmetry when one side was never seen (the pool's construction from a track's views), added
    to ``pool`` (provenance scene_track; the same model twice is one entry). Objects that cannot be traced, or whose
    track was left in the background, are listed with the reason. At most ``limit`` objects, in pick order."""
    payload = read_own_json(missed_json, "give a missed.json of `omniscs scs mine`", expect=dict)
    wanted, seen = [], set()
    for pick in payload.get("picks") or []:
        for box in pick.get("missed") or []:
            key = (box.get("scene_id"), box.get("track_id"))
            if key not in seen:
                seen.add(key)
                wanted.append(dict(box, pick=f"{pick.get('category')} / {pick.get('orientation')} / "
                                             f"{pick.get('pose')}"))
    if not wanted:
        raise OmniscsError(f"{missed_json} picks no missed object; nothing to model")
    config = DualConfig()
    p = Pool(pool)
    out, graphs = [], {}
    for i, box in enumerate(wanted[:limit]):
        progress(i, min(limit, len(wanted)), f"model of {box.get('scene_id')} track {box.get('track_id')}")
        row = {"store_id": box.get("scene_id"), "track_id": box.get("track_id"), "category": box.get("category"),
               "pick": box["pick"], "model_id": None}
        scene_id = _source_scene(workspace, str(box.get("scene_id"))) if box.get("scene_id") else None
        if scene_id is None or box.get("track_id") is None:
            out.append(dict(row, reason="not traced to a scene of this workspace"))
            continue
        if scene_id not in graphs:
            try:
                where = layout.scene_store(workspace, scene_id)
                if where is None:
                    raise OmniscsError(f"scene {scene_id} is neither ingested in {workspace} nor in its scenes "
                                       "catalog table")
                scene = load_scene(where)
                graphs[scene_id] = (scene, load_graph(newest_checkpoint(workspace, scene_id), scene))
            except OmniscsError as exc:
                graphs[scene_id] = (None, str(exc))
        scene, graph = graphs[scene_id]
        tid = int(box["track_id"])
        if scene is None:
            out.append(dict(row, scene_id=scene_id, reason=graph))
            continue
        if tid not in graph.agent_ids:
            out.append(dict(row, scene_id=scene_id, reason="the track was left in the background (not a node)"))
            continue
        node = graph.agent(tid)
        g = cropped_to_box(node.gaussians, node.size, config.box_margin_m)
        views = track_views(scene, tid, range(scene.n_frames), config.min_view_pixels)
        if views:
            g = mirror_completed(g, seen_side(views))
        model_id = p.add(g.detached().to("cpu"), node.category, "scene_track", f"{scene_id}/track-{tid}")
        out.append(dict(row, scene_id=scene_id, model_id=model_id, reason="the track's node, mirror-completed"))
    progress(len(out), len(out), "models of missed objects")
    return out
