"""``omniscs bench agents``: the model pool and the dual strategy against the procedural world's exact ground truth.

Three parts, one report (reports/agents/):
- Pool: seconds per model built from meshes (fresh builds, not reuses) and the benchmark pool's size, built from
  the library's *pool* split only, so no vehicle of a benchmark world is in it.
- Matching: pool-split vehicles put into world scenes (the world's own renderer, lighting and camera), cropped by
  their ground-truth masks, degraded, and ranked against the pool's keyframes: top-1/top-5 per degradation level
  for each embedder.
- The paper's Table 4: edited-agent masked PSNR/SSIM after translate 2.0/3.5 m, rotate 90/180/270 degrees and
  overturn (roll 180 degrees), for the naive graph, online only, pool only and the dual strategy on held-out
  worlds, plus the pool arm with the edited vehicles' own models added to the pool (in-pool: matching may still
  pick another model), and at the turns what limits the pool arm (``LIMITS``: each vehicle's own model alone, with
  the background in its box kept, and its colours fitted to the truth as an oracle).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import statistics
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from omniscs.agents.degradation import Degradation, degrade
from omniscs.agents.dual import DualConfig, boxes_cleared, complete_agents, grow_pool
from omniscs.agents.matching import (
    GALLERY_SCALES,
    HOG,
    ColourHistogram,
    RawPixels,
    best_at_scales,
    crop_scale,
    crop_square,
    default_embedder,
    pool_gallery,
)
from omniscs.agents.mesh import MESH_BUILD_VERSION
from omniscs.agents.msnet import SHIPPED as MSNET_CHECKPOINT, MSNet, MSNetEmbedder, load_msnet
from omniscs.agents.pool import Pool
from omniscs.bench.fit import edited_agents, evaluation_views
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.edits import edit_from_dict, edit_to_dict
from omniscs.gaussians import GaussianParams
from omniscs.nsg.checkpoint import load_graph
from omniscs.nsg.edit import apply_graph_edits
from omniscs.nsg.graph import render_view
from omniscs.pipeline.agents import GROWTH_MIN_PSNR
from omniscs.pipeline.pool import pool_asset_stage
from omniscs.pipeline.request import SceneRequest
from omniscs.pipeline.stages import fit_stage, ingest_stage, load_plan, plan_stage
from omniscs.plan import make_plan
from omniscs.progress import Progress, no_progress
from omniscs.quality import psnr, ssim
from omniscs.scene import SyntheticSource, load_scene
from omniscs.storage import workspace_root
from omniscs.taxonomy import VEHICLE_CATEGORIES
from omniscs.world import WorldRenderer, apply_edits, build_asset, generate_world
from omniscs.world.assets import list_asset_ids

log = logging.getLogger(__name__)

#: How many models of each kind the benchmark pool takes from the library's pool split (320 in all).
POOL_QUOTA = {"sedan": 90, "suv": 70, "van": 45, "pickup": 40, "box_truck": 25, "bus": 15, "trailer": 15,
              "excavator": 10, "wheel_loader": 10}

#: Table 4's edits, each applied alone to each edited agent (agent frame).
TABLE4_EDITS: tuple[tuple[str, dict], ...] = (
    ("translate 2.0 m", {"op": "translate", "lateral": 2.0}),
    ("translate 3.5 m", {"op": "translate", "lateral": 3.5}),
    ("rotate 90°", {"op": "rotate", "yaw_deg": 90.0}),
    ("rotate 180°", {"op": "rotate", "yaw_deg": 180.0}),
    ("rotate 270°", {"op": "rotate", "yaw_deg": 270.0}),
    ("overturned", {"op": "rotate", "roll_deg": 180.0}),
)
ARMS = ("naive", "online", "pool", "dual", "pool in-pool")

#: What limits the pool arm at the turns: the edited vehicle's own model (its asset's exact shape and material, so
#: matching cannot fail; relit and its box cleared as the pool arm does), the same with the background Gaussians in
#: its box kept (what clearing them gives), and the own model's colours fitted to the evaluated views themselves (an
#: oracle that also absorbs the shape's misalignment in those views, so more than appearance alone could reach).
LIMIT_EDITS = ("rotate 90°", "rotate 180°", "rotate 270°")
LIMITS = ("own model", "own model, box kept", "colours fitted to the truth")
#: Adam steps of the oracle colour fit (L1 over the edited vehicle's ground-truth pixels of the evaluated views).
ORACLE_STEPS = 80

#: Matching's degradation levels (the issue's target level is 'x4 + 40 % occl. + illum.').
MATCH_LEVELS: tuple[tuple[str, dict], ...] = (
    ("clean", {}),
    ("x2", {"downsample": 2.0}),
    ("x4", {"downsample": 4.0}),
    ("x4 + 40 % occl. + illum.", {"downsample": 4.0, "occlusion": 0.4, "gain": 0.7, "gamma": 1.3}),
    ("x8 + blur + noise + JPEG", {"downsample": 8.0, "blur": 1.0, "noise": 6.0, "jpeg": 40}),
)


@dataclass(frozen=True)
class AgentsBenchConfig:
    scenes: tuple[str, ...] = ("straight:73", "t_junction:74")
    """Held-out procedural logs (template:seed) for Table 4; none was used while building the dual strategy
    (straight:71 and t_junction:72 were the first run's, before the coverage threshold and the render check
    changed; its numbers are in the issue's notes)."""
    preset: str = "balanced"
    """Fit preset of the scene graphs (the naive graph's baseline in reports/edits used balanced)."""
    agents_per_scene: int = 2
    """Edited agents per scene (the most visible vehicles)."""
    views_per_edit: int = 4
    """Evaluated views per agent and edit."""
    min_pixels: int = 200
    """An evaluated view shows at least this many ground-truth pixels of the edited agent."""
    match_scenes: tuple[str, ...] = ("straight:81", "t_junction:82", "intersection:83", "straight:84",
                                     "t_junction:85", "intersection:86", "straight:87", "t_junction:88")
    """Worlds whose vehicles are swapped for pool-split vehicles to make matching queries."""
    match_queries: int = 60
    """Matching queries (pool-split vehicles, each seen once)."""
    build_timing_models: int = 6
    """Models built afresh to time the mesh-to-pool path."""
    quota: tuple[tuple[str, int], ...] = tuple(POOL_QUOTA.items())


def quick_config() -> AgentsBenchConfig:
    """A smoke run: one small scene, the fast preset, few queries (not a measurement)."""
    return AgentsBenchConfig(scenes=("straight:71",), preset="fast", agents_per_scene=1, views_per_edit=2,
                             match_scenes=("straight:81",), match_queries=8, build_timing_models=2,
                             quota=(("sedan", 6), ("suv", 4), ("van", 2)))


def _source(item: str):
    template, _, seed = item.partition(":")
    return SyntheticSource(template, int(seed), "day", 40, 3, 480, 270)


def pool_ids(quota) -> list[str]:
    return [a for kind, n in quota for a in list_asset_ids(kind, "pool")[:n]]


def build_pool(pool: Path, ids: list[str], progress: Progress = no_progress) -> list[dict]:
    """The pool stage over ``ids``; assets the pool already holds a mesh model of are not looked at again."""
    table = Pool(pool).table()
    have = set(table.source[table.provenance == "mesh"]) if len(table) else set()
    rows = []
    for i, aid in enumerate(ids):
        if aid in have:
            continue
        progress(i, len(ids), f"pool model {aid}")
        rows.append(pool_asset_stage(aid, pool).rows["pool"][0])
    return rows


def table4_request(targets: list[int], preset: str):
    """The request whose plan makes the edited agents nodes that need 360-degree models."""
    edits = [{**spec, "track_id": int(t)} for t in targets for _, spec in TABLE4_EDITS]
    return SceneRequest(fit_preset=preset, edits=tuple(edits), previews=False)


def prepare_scene(item: str, config: AgentsBenchConfig, workspace: Path, progress: Progress = no_progress):
    """Ingest, pick the edited agents (vehicles, most visible), plan and fit (reused when fitted before)."""
    ingested = ingest_stage(_source(item), workspace)
    scene = load_scene(ingested.path)
    vehicles = set(scene.boxes[scene.boxes.category.isin(VEHICLE_CATEGORIES)].track_id)
    targets = [t for t in edited_agents(scene, (), 50, config.min_pixels) if t in vehicles][:config.agents_per_scene]
    request = table4_request(targets, config.preset)
    plan = load_plan(plan_stage(ingested.path, request, workspace))
    fitted = fit_stage(ingested.path, plan, config.preset, workspace, progress=progress)
    if fitted.info["status"] != "fitted":
        raise RuntimeError(f"the fit of {scene.scene_id} diverged: {fitted.info['error']}")
    return scene, plan, fitted, targets


# ----------------------------------------------------------------------------- matching
def swap_vehicles(world, options: dict[str, list[str]]):
    """``world`` with its vehicles replaced by assets popped from the end of ``options`` (category -> asset ids),
    each with its own box size, standing on the road where the world's vehicle stood; vehicles whose category has
    no asset left stay. Returns the new world and {track id: asset id} of the replaced ones."""
    tracks, swapped = [], {}
    for track in world.agents:
        choices = options.get(track.category)
        if track.category not in VEHICLE_CATEGORIES or not choices:
            tracks.append(track)
            continue
        asset = choices.pop()
        size = np.asarray(build_asset(asset).size, dtype=np.float64)
        poses = track.poses.copy()
        poses[:, :3, 3] += poses[:, :3, 2] * 0.5 * (size[2] - track.size[2])  # the new box on the same ground
        tracks.append(dataclasses.replace(track, asset_id=asset, size=size, poses=poses))
        swapped[track.track_id] = asset
    return world.replace(agents=tuple(tracks)), swapped


def matching_queries(config: AgentsBenchConfig, pool_table, progress: Progress = no_progress):
    """(crop uint8 [CROP, CROP, 3], category, true model id, box size [3], more crops uint8 [k, CROP, CROP, 3],
    ``crop_scale`` of each crop [1 + k]) per query: benchmark-pool vehicles put in the place of world vehicles
    (``swap_vehicles``), each seen whole (not cut by the image border) and cropped by its ground-truth mask (other
    pixels black, as in the keyframes). The first crop is the view that shows most of it; the others are its next
    largest views, up to ``DualConfig.match_views`` in all, as the dual strategy's matching takes a track's largest
    views."""
    by_category: dict[str, list[str]] = {}
    model_of = {}
    for row in pool_table.sort_values("model_id").itertuples():
        by_category.setdefault(row.category, []).append(row.source)
        model_of[row.source] = (row.model_id, row.category)
    rng = np.random.default_rng(20261125)
    for c in by_category.values():
        rng.shuffle(c)
    queries = []
    for item in config.match_scenes:
        template, _, seed = item.partition(":")
        world, swapped = swap_vehicles(generate_world(template, int(seed)), by_category)
        seen: dict[int, list[tuple[int, np.ndarray, float]]] = {}
        for tid, n, crop, scale in whole_views(world, swapped, 5, config.min_pixels * 2):
            seen.setdefault(tid, []).append((n, crop, scale))
        for tid, views in sorted(seen.items()):
            views = sorted(views, key=lambda v: -v[0])[:DualConfig().match_views]  # stable: the first largest leads
            model_id, category = model_of[swapped[tid]]
            more = np.stack([c for _, c, _ in views[1:]]) if len(views) > 1 else np.zeros((0, *views[0][1].shape),
                                                                                            np.uint8)
            queries.append((views[0][1], category, model_id, world.agent(tid).size, more,
                            np.array([s for _, _, s in views])))
        progress(len(queries), config.match_queries, f"matching queries from {item}")
        if len(queries) >= config.match_queries:
            break
    return queries[:config.match_queries]


def whole_views(world, track_ids, frame_step: int, min_pixels: int):
    """(track id, pixels, crop uint8 [CROP, CROP, 3], its ``crop_scale``) for every camera image of every
    ``frame_step``-th frame of ``world`` in which one of ``track_ids`` shows whole (not cut by the image border)
    over at least ``min_pixels``, cropped by its ground-truth mask (other pixels black, as in the pool's
    keyframes)."""
    renderer = WorldRenderer(world)
    for f in range(0, world.n_frames, frame_step):
        for cam in world.cameras:
            gt = renderer.render_camera(f, cam.name)
            for tid in track_ids:
                mask = gt.instance == tid
                n = int(mask.sum())
                if n < min_pixels or mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any():
                    continue
                masked = (gt.rgb * mask[..., None]).astype(np.uint8)
                yield tid, n, crop_square(masked, mask.astype(np.float32)), crop_scale(masked, mask.astype(np.float32))


def run_matching(queries, pool, embedders, size_weight: float = 1.0, size_noise: float = 0.05,
                 progress: Progress = no_progress) -> list[dict]:
    """Top-1/top-5 (within the query's category) per degradation level and embedder, on appearance alone and with
    the box-shape term the dual strategy adds (the query's size as a detector measures it: ``size_noise`` relative
    error per axis). Each crop is compared with the keyframes at the GALLERY_SCALES entry nearest to how small it
    is seen: its own ``crop_scale`` (a sixth item of the query, one per view; none: 1) times the level's
    downsampling, as the dual strategy does; one row per embedder compares with full-resolution keyframes instead.
    Where queries carry more views (a fifth item, ``matching_queries``), also as the dual strategy scores a track:
    the mean over its views, each degraded on its own, of the best keyframe similarity, with the box-shape term."""
    rows = []
    crops = np.stack([q[0] for q in queries])
    cats = np.array([q[1] for q in queries])
    truth = np.array([q[2] for q in queries])
    noise = np.random.default_rng(11).normal(0.0, size_noise, (len(queries), 3))
    sizes = np.stack([q[3] for q in queries]) * np.exp(noise)
    more = [q[4] if len(q) > 4 else np.zeros((0, *crops.shape[1:]), np.uint8) for q in queries]
    seen = [np.asarray(q[5], np.float64) if len(q) > 5 else np.ones(1 + len(m)) for q, m in zip(queries, more)]
    first_scale = np.array([s[0] for s in seen])
    more_scale = np.concatenate([s[1:] for s in seen])
    owner_of_more = np.concatenate([np.full(len(m), i) for i, m in enumerate(more)]).astype(np.int64)
    n_views = 1 + max(len(m) for m in more)
    view_counts = {str(k): sum(1 + len(m) == k for m in more) for k in range(n_views, 0, -1)}
    for embedder in embedders:
        galleries = {g: pool_gallery(pool, embedder, g) for g in GALLERY_SCALES}
        _, owner, table = galleries[1.0]
        models = np.array(sorted(table.model_id))
        indexed = table.set_index("model_id").loc[models]
        model_cat = indexed["category"].to_numpy()
        model_size = indexed[["length", "width", "height"]].to_numpy(np.float64)
        shape = np.abs(np.log(model_size[None] / sizes[:, None])).mean(-1)  # [Q, M]
        index = {m: j for j, m in enumerate(models)}
        cols = np.array([index[m] for m in owner])

        def scored(embeddings, scales):  # [n, M]: each embedding against the keyframes as small as it is seen
            return best_at_scales(embeddings, scales, lambda g: galleries[g][0], cols, len(models))

        for level, spec in MATCH_LEVELS:
            progress(len(rows), None, f"matching: {embedder.name}, {level}")
            down = spec.get("downsample", 1.0)
            rng = np.random.default_rng(7)
            embedded = embedder.embed(np.stack([degrade(c, Degradation(**spec), rng) for c in crops]))
            other = cats[:, None] != model_cat[None, :]  # category known from detection
            best = np.where(other, -np.inf, scored(embedded, first_scale * down))
            full = np.where(other, -np.inf, scored(embedded, np.ones(len(crops))))
            cues = [("appearance", best), ("appearance + box shape", best - size_weight * shape),
                    ("appearance + box shape, keyframes at full resolution", full - size_weight * shape)]
            if len(owner_of_more):  # the track's other views, degraded alike (their own draws), averaged in
                extra_rng = np.random.default_rng(8)
                extra = np.stack([degrade(c, Degradation(**spec), extra_rng) for m in more for c in m])
                total = best.copy()
                np.add.at(total, owner_of_more, scored(embedder.embed(extra), more_scale * down))
                counts = 1 + np.bincount(owner_of_more, minlength=len(crops))
                cues.append((f"appearance + box shape, up to {n_views} views",
                             total / counts[:, None] - size_weight * shape))
            for cue, scores in cues:
                ranked = models[np.argsort(-scores, axis=1)]
                rows.append({"embedder": embedder.name, "cue": cue, "level": level, "degradation": spec,
                             "queries": len(crops), "top1": float(np.mean(ranked[:, 0] == truth)),
                             "top5": float(np.mean([t in r[:5] for t, r in zip(truth, ranked)])),
                             **({"queries_by_views": view_counts} if "views" in cue else {})})
    return rows


# ----------------------------------------------------------------------------- Table 4
def _arm_graphs(graph, scene, plan, targets, pool, in_pool, progress: Progress):
    """The naive graph and the graph each arm makes (with its decisions)."""
    arms = {"naive": (graph, [])}
    for arm, force, p in (("online", "online", None), ("pool", "pool", pool), ("dual", None, pool),
                          ("pool in-pool", "pool", in_pool)):
        progress(0, None, f"{scene.scene_id}: {arm}")
        arms[arm] = complete_agents(graph, scene, targets, plan.train_frames, p, force=force)
    return arms


def run_table4(config: AgentsBenchConfig, workspace: Path, pool, progress: Progress = no_progress):
    rows, strips, decisions, fits, pool_growth, limits = [], [], [], [], [], []
    shutil.rmtree(workspace / "bench-agents" / "growth-pool", ignore_errors=True)
    for item in config.scenes:
        scene, plan, fitted, targets = prepare_scene(item, config, workspace, progress)
        graph = load_graph(fitted.path, scene)
        # in-pool: the benchmark pool plus the edited vehicles' own models (an upper bound on matching)
        in_pool = Pool(workspace / "bench-agents" / f"in-pool-{scene.scene_id}")
        shutil.rmtree(in_pool.root, ignore_errors=True)
        shutil.copytree(pool.root, in_pool.root, ignore=shutil.ignore_patterns("embeddings"))
        own_models = {t: pool_asset_stage(scene.world.agent(t).asset_id, in_pool.root).info["model_id"]
                      for t in targets}
        started = time.perf_counter()
        arms = _arm_graphs(graph, scene, plan, targets, pool, in_pool, progress)
        progress(0, None, f"{scene.scene_id}: own models")
        own, own_ids = own_model_graph(graph, scene, plan.train_frames, in_pool, own_models,
                                       workspace / "bench-agents" / f"own-{scene.scene_id}")
        # growth: the scene's clear, well-covered vehicles scored on held-out views join a copy of the pool
        growth = Pool(workspace / "bench-agents" / "growth-pool")
        if not growth.root.exists():
            shutil.copytree(pool.root, growth.root, ignore=shutil.ignore_patterns("embeddings"))
        grown = grow_pool(graph, scene, plan.train_frames, plan.heldout_frames, growth, GROWTH_MIN_PSNR)
        pool_growth.append({"scene_id": scene.scene_id, "candidates": len(grown),
                            "added": sorted(m for m, _ in grown.values() if m),
                            "heldout_psnr": {str(t): q for t, (_, q) in grown.items()},
                            "pool_size": len(growth.table())})
        fits.append({"scene_id": scene.scene_id, "source": item, "targets": targets,
                     "heldout_psnr": fitted.info["metrics"]["heldout_psnr"],
                     "arms_seconds": time.perf_counter() - started,
                     "assets": {str(t): scene.world.agent(t).asset_id for t in targets}})
        for arm, (_, ds) in arms.items():
            decisions += [{"scene_id": scene.scene_id, "arm": arm, **d.to_dict()} for d in ds if d.track_id in targets]
        decisions += [{"scene_id": scene.scene_id, "arm": "own model", "track_id": t, "strategy": "pool",
                       "model_id": m} for t, m in own_ids.items()]
        # the strip shows each scene's first edited agent and every agent the dual arm gave a pool model
        shown = {targets[0]} | {d.track_id for d in arms["dual"][1] if d.strategy == "pool"} if targets else set()
        for tid in targets:
            for name, spec in TABLE4_EDITS:
                edit = edit_from_dict({**spec, "track_id": tid})
                progress(len(rows), None, f"{scene.scene_id} track {tid}: {name}")
                renderer = WorldRenderer(apply_edits(scene.world, [edit]))
                views = evaluation_views(renderer, scene, tid, config.views_per_edit, config.min_pixels)
                strip = [] if tid not in shown or not views else [views[len(views) // 2][2].rgb]
                planned = dual_needs_360(scene, edit)
                scored: dict[int, tuple[list[dict], np.ndarray | None]] = {}  # by graph: the dual arm may be naive's
                for arm, (g, _) in arms.items():
                    if arm == "dual" and not planned:  # the product's plan keeps the fitted node for this edit
                        g = arms["naive"][0]
                    if id(g) not in scored:
                        scored[id(g)] = _scored_views(g, edit, tid, views, bool(strip))
                    per_view, shown_image = scored[id(g)]
                    if shown_image is not None:
                        strip.append(shown_image)
                    rows.append({"scene_id": scene.scene_id, "track_id": tid, "edit": name, "arm": arm,
                                 "spec": edit_to_dict(edit), "n_views": len(per_view),
                                 **({"needs_360": planned} if arm == "dual" else {}),
                                 "masked_psnr": _mean([v["psnr"] for v in per_view]),
                                 "masked_ssim": _mean([v["ssim"] for v in per_view])})
                if name in LIMIT_EDITS and views:
                    progress(len(rows), None, f"{scene.scene_id} track {tid}: {name}, what limits the pool arm")
                    limits += limit_rows(own, graph.background, tid, edit, views,
                                         {"scene_id": scene.scene_id, "track_id": tid, "edit": name})
                if strip:
                    f, cam, gt = views[len(views) // 2]
                    strips.append((f"{name} ({scene.scene_id} track {tid}, {cam} frame {f})", gt.instance == tid,
                                   strip))
    return rows, strips, decisions, fits, pool_growth, limits


def dual_needs_360(scene, edit) -> bool:
    """Whether the plan of a request with ``edit`` alone gives its track a 360-degree model (the agents stage runs
    for it); where it does not, the product renders the edit with the fitted node, and so does the dual arm."""
    return int(edit.track_id) in make_plan(scene, [edit]).needs_360


def _scored_views(graph, edit, track_id: int, views, keep_middle: bool) -> tuple[list[dict], np.ndarray | None]:
    """Masked PSNR / SSIM of ``graph`` with ``edit`` applied on each evaluation view (``evaluation_views``), and
    the middle view's render (uint8) when ``keep_middle`` (the report's strip)."""
    edited = apply_graph_edits(graph, [edit])
    per_view, middle = [], None
    for i, (f, cam, gt) in enumerate(views):
        out = edited.render(edited.view(cam, f))
        target = torch.from_numpy(gt.rgb.astype(np.float32) / 255.0)
        mask = torch.from_numpy(gt.instance == track_id)
        per_view.append({"psnr": psnr(out.rgb, target, mask), "ssim": ssim(out.rgb, target, mask)})
        if keep_middle and i == len(views) // 2:
            middle = (out.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    return per_view, middle


# ----------------------------------------------------------------------------- what limits the pool arm
def own_model_graph(graph, scene, train_frames, source, models: dict[int, str], root: Path):
    """The pool arm with each edited vehicle given its own model (``models``: track -> model id of the pool
    ``source``), from a pool of that one model per track, so matching cannot pick another: the graph and {track:
    model id}."""
    config = DualConfig()
    out, nodes, pooled, ids = None, {}, [], {}
    for t, model_id in models.items():
        pool = Pool(root / f"track-{t}")
        shutil.rmtree(pool.root, ignore_errors=True)
        model = source.get(model_id)
        pool.add(model.params, model.meta["category"], model.meta["provenance"], model.meta["source"],
                 model.meta["quality"], build=model.meta.get("build"), material=model.material)
        # the boxes are cleared below, all at once: each track's own run would clear only its own
        g, ds = complete_agents(graph, scene, [t], train_frames, pool, replace(config, clear_box=False), force="pool")
        d = next(d for d in ds if d.track_id == t)
        ids[t], nodes[t], out = d.model_id, g.agent(t), g if out is None else out
        pooled += [t] if d.strategy == "pool" else []
    if out is None:
        return graph, ids
    out = out.replace(agents=tuple(nodes.get(a.track_id, a) for a in out.agents))
    if config.clear_box and pooled:  # as complete_agents does for the tracks it gives pool models
        out = boxes_cleared(out, pooled, config)[0]
    return out, ids


def truth_fitted(edited, track_id: int, views, steps: int = ORACLE_STEPS):
    """``edited`` with the track's colours (SH, every band) fitted to the ground truth of ``views`` (an oracle)."""
    node = edited.agent(track_id)
    p = node.gaussians
    dc = p.sh_dc.detach().clone().requires_grad_(True)
    rest = p.sh_rest.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([dc, rest], lr=0.02)
    targets = [(edited.view(cam, f), torch.from_numpy(gt.rgb.astype(np.float32) / 255.0),
                torch.from_numpy(gt.instance == track_id)) for f, cam, gt in views]

    def with_colours(d, r):
        g = GaussianParams(p.means, p.quats, p.log_scales, p.opacity_logits, d, r)
        return edited.replace(agents=tuple(node.with_changes(gaussians=g, relight=None) if a.track_id == track_id
                                           else a for a in edited.agents))

    for step in range(steps):
        view, target, mask = targets[step % len(targets)]
        out = render_view(with_colours(dc, rest), view)
        loss = (out.rgb - target.to(out.rgb.device)).abs()[mask.to(out.rgb.device)].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return with_colours(dc.detach(), rest.detach())


def limit_rows(own, background, track_id: int, edit, views, key: dict) -> list[dict]:
    """Masked PSNR of each of LIMITS for one edited vehicle and edit; ``background``: the fitted graph's, before the
    pool arm cleared the box."""
    base = apply_graph_edits(own, [edit])
    graphs = {LIMITS[0]: base, LIMITS[1]: apply_graph_edits(own.replace(background=background), [edit]),
              LIMITS[2]: truth_fitted(base, track_id, views)}
    out = []
    for name, g in graphs.items():
        scores = [psnr(g.render(g.view(cam, f)).rgb, torch.from_numpy(gt.rgb.astype(np.float32) / 255.0),
                       torch.from_numpy(gt.instance == track_id)) for f, cam, gt in views]
        out.append({**key, "arm": name, "n_views": len(views), "masked_psnr": _mean(scores)})
    return out


def limits_summary(limits: list[dict], rows: list[dict]) -> list[dict]:
    """Per edit of LIMIT_EDITS, the mean masked PSNR of the naive, pool and pool in-pool arms and of each of LIMITS
    over the agents that have all of them."""
    out = []
    for name in LIMIT_EDITS:
        by = {}
        for r in rows + limits:
            if r["edit"] == name and r.get("masked_psnr") is not None:
                by.setdefault((r["scene_id"], r["track_id"]), {})[r["arm"]] = r["masked_psnr"]
        arms = ("naive", "pool", "pool in-pool") + LIMITS
        agents = [v for v in by.values() if all(a in v for a in arms)]
        out.append({"edit": name, "agents": len(agents),
                    **{a: (float(np.mean([v[a] for v in agents])) if agents else None) for a in arms}})
    return out


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def table4_summary(rows: list[dict]) -> list[dict]:
    out = []
    for name, _ in TABLE4_EDITS:
        for arm in ARMS:
            r = [x for x in rows if x["edit"] == name and x["arm"] == arm and x["n_views"]]
            out.append({"edit": name, "arm": arm, "agents": len(r),
                        "masked_psnr": _mean([x["masked_psnr"] for x in r]),
                        "masked_ssim": _mean([x["masked_ssim"] for x in r])})
    return out


# ----------------------------------------------------------------------------- the run
def run_agents_benchmark(out_dir: Path, workspace: Path | None = None, config: AgentsBenchConfig = AgentsBenchConfig(),
                         progress: Progress = no_progress) -> dict:
    machine = machine_info()
    ws = workspace_root(workspace)
    root = ws / "bench-agents"
    # pool: fresh builds timed, then the benchmark pool (reused when built before)
    timing_pool = root / "timing-pool"
    shutil.rmtree(timing_pool, ignore_errors=True)
    ids = pool_ids(config.quota)
    timing = build_pool(timing_pool, ids[:config.build_timing_models], progress)
    # one benchmark pool per mesh build version: a pool keeps the models it holds (pipeline.pool)
    pool = Pool(root / f"pool-mesh-v{MESH_BUILD_VERSION}")
    started = time.perf_counter()
    build_pool(pool.root, ids, progress)
    pool_seconds = time.perf_counter() - started
    table = pool.table()
    # matching
    queries = matching_queries(config, table, progress)
    matching = run_matching(queries, pool, _embedders(), progress=progress)
    # Table 4
    rows, strips, decisions, fits, growth, limits = run_table4(config, ws, pool, progress)
    summary = table4_summary(rows)
    report = {"config": asdict(config), "machine": finish(machine),
              "pool": {"size": len(table), "by_category": table.category.value_counts().to_dict(),
                       "split": "pool", "seconds_to_fill": pool_seconds,
                       "build_seconds_per_model": [r["seconds"] for r in timing],
                       "median_build_seconds": statistics.median(r["seconds"] for r in timing),
                       "quality_db_median": float(np.nanmedian(table.quality.astype(float))), "growth": growth},
              "matching": matching, "table4": summary, "pool_ranking_embedder": _default_name(), "rows": rows,
              "limits": limits_summary(limits, rows), "limit_rows": limits,
              "decisions": decisions, "fits": fits,
              "targets": _targets(matching, summary, timing)}
    write_report(out_dir, "agents", report, agents_markdown(report),
                 {"": lambda buf: _strip_png(strips, buf)} if strips else None)
    return report


def _embedders() -> list:
    """The baselines, the untrained network and the shipped MSNet (when the package holds its weights)."""
    torch.manual_seed(0)
    embedders = [ColourHistogram(), HOG(), RawPixels(), _Named(MSNetEmbedder(MSNet()), "MSNet (untrained)")]
    if (MSNET_CHECKPOINT / "msnet.safetensors").is_file():
        embedders.append(_Named(MSNetEmbedder(load_msnet(MSNET_CHECKPOINT)), "MSNet (shipped)"))
    return embedders


def run_matching_benchmark(out_dir: Path, workspace: Path | None = None,
                           config: AgentsBenchConfig = AgentsBenchConfig(), progress: Progress = no_progress) -> dict:
    """Matching alone (``agents/matching.json/.md``): the benchmark pool, its queries and every embedder, as in the
    whole benchmark, in minutes where Table 4's fits take hours; for a new MSNet."""
    machine = machine_info()
    pool = Pool(workspace_root(workspace) / "bench-agents" / f"pool-mesh-v{MESH_BUILD_VERSION}")
    build_pool(pool.root, pool_ids(config.quota), progress)
    matching = run_matching(matching_queries(config, pool.table(), progress), pool, _embedders(), progress=progress)
    training = MSNET_CHECKPOINT / "training.json"
    report = {"config": asdict(config), "machine": finish(machine), "pool_size": len(pool.table()),
              "msnet_training": json.loads(training.read_text()) if training.is_file() else None,
              "matching": matching, "target": _matching_target(matching)}
    write_report(out_dir, "agents", report, matching_markdown(report), part="matching")
    return report


def matching_markdown(report: dict) -> str:
    """reports/agents/matching.md from its JSON."""
    info = report["msnet_training"] or {}
    t = report["target"]
    lines = ["# Agents: matching alone (reports/agents/matching)", "", load_line(report["machine"]), "",
             f"The benchmark pool ({report['pool_size']} models) and queries of reports/agents "
             f"(worlds {', '.join(report['config']['match_scenes'])}). Shipped MSNet: {info.get('n_assets', '?')} "
             f"training identities, {info.get('n_keyframe_crops', '?')} keyframe and {info.get('n_camera_crops', '?')} "
             "camera crops (its training.json), none of a benchmark world or of the benchmark pool.", "",
             f"Top-1 at x4 + 40 % occlusion + illumination: {t['top1']:.1%} ({t['best']}); goal 95 %: "
             f"{'met' if t['met'] else 'NOT met'}.", "", *_matching_lines(report["matching"]), ""]
    return "\n".join(lines) + "\n"


def _default_name() -> str:
    return default_embedder().name


class _Named:
    """An embedder shown under another name in the report."""

    def __init__(self, inner, name: str) -> None:
        self.inner, self.name = inner, name
        self.cache_key = getattr(inner, "cache_key", name)

    def embed(self, crops):
        return self.inner.embed(crops)


def _matching_target(matching: list[dict]) -> dict:
    """The best top-1 at the issue's level (x4 + 40 % occlusion + illumination) against its 95 % goal."""
    best = max((r for r in matching if r["level"] == "x4 + 40 % occl. + illum."), key=lambda r: r["top1"])
    return {"best": f"{best['embedder']}, {best.get('cue', 'appearance')}", "top1": best["top1"], "goal": 0.95,
            "met": best["top1"] >= 0.95}


def _targets(matching, summary, timing) -> dict:
    psnr = {(s["edit"], s["arm"]): s["masked_psnr"] for s in summary}
    gains = {e: (psnr[(e, "dual")] - psnr[(e, "naive")]) if psnr[(e, "dual")] is not None
             and psnr[(e, "naive")] is not None else None for e in ("rotate 90°", "rotate 180°", "rotate 270°")}
    return {"matching_top1_at_target_level": _matching_target(matching),
            "dual_gain_db": {"gains": gains, "goal": 3.0,
                             "met": all(g is not None and g >= 3.0 for g in gains.values())},
            "build_seconds": {"median": statistics.median(r["seconds"] for r in timing), "goal": 30.0,
                              "met": statistics.median(r["seconds"] for r in timing) <= 30.0}}


def _views_note(matching: list[dict]) -> list[str]:
    """How many views the multi-view rows had per query (none when the report has no such rows)."""
    counts = next((r["queries_by_views"] for r in matching if "queries_by_views" in r), None)
    if not counts:
        return []
    spread = ", ".join(f"{n} with {k}" for k, n in counts.items() if n)
    return [f"The rows with views score each query over its largest whole views as the dual strategy scores a track "
            f"(the mean best keyframe similarity, each view degraded on its own): {spread}."]


def _matching_lines(matching: list[dict]) -> list[str]:
    lines = ["## Matching (top-1 / top-5 within the query's category)", "",
             f"{len(set(r['level'] for r in matching))} degradation levels, {matching[0]['queries']} queries: "
             "pool-split vehicles rendered into world scenes by the world's renderer (its lighting, not the "
             "keyframes'), each cropped by its ground-truth mask.", *_views_note(matching), "",
             "| embedder | " + " | ".join(lv for lv, _ in MATCH_LEVELS) + " |", "|---|" + "---|" * len(MATCH_LEVELS)]
    for name, cue in dict.fromkeys((r["embedder"], r.get("cue", "appearance")) for r in matching):
        cells = [next(f"{r['top1']:.0%} / {r['top5']:.0%}" for r in matching
                      if r["embedder"] == name and r.get("cue", "appearance") == cue and r["level"] == lv)
                 for lv, _ in MATCH_LEVELS]
        label = cue.replace("appearance", name, 1)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def agents_markdown(report: dict) -> str:
    def f(v, d=2):
        return "n/a" if v is None else f"{v:.{d}f}"

    m, p, t = report["machine"], report["pool"], report["targets"]
    lines = ["# Agents: model pool, matching and the dual strategy (reports/agents)", "",
             load_line(m), "",
             f"{report['config']['preset']} fits of held-out worlds {', '.join(report['config']['scenes'])} "
             "(40 frames x 3 cameras at 480x270). The pool holds only the asset library's pool split: no vehicle "
             "of a benchmark world is in it.", "",
             "## Targets", "",
             "- Matching top-1 at x4 + 40 % occlusion + illumination: "
             f"{t['matching_top1_at_target_level']['top1']:.1%} "
             f"({t['matching_top1_at_target_level']['best']}); goal 95 %: "
             f"{'met' if t['matching_top1_at_target_level']['met'] else 'NOT met'}.",
             "- Dual over naive, masked PSNR: "
             + ", ".join(f"{e} {f(g)} dB" for e, g in t["dual_gain_db"]["gains"].items())
             + f"; goal 3 dB each: {'met' if t['dual_gain_db']['met'] else 'NOT met'}.",
             f"- Seconds per pool model (fresh builds, median): {f(t['build_seconds']['median'], 1)}; goal 30: "
             f"{'met' if t['build_seconds']['met'] else 'NOT met'}.", "",
             "## Table 4: edited-agent masked PSNR (dB) / SSIM against the re-rendered world", "",
             "| edit | " + " | ".join(ARMS) + " |", "|---|" + "---|" * len(ARMS)]
    by = {(s["edit"], s["arm"]): s for s in report["table4"]}
    for name, _ in TABLE4_EDITS:
        cells = [f"{f(by[(name, a)]['masked_psnr'])} / {f(by[(name, a)]['masked_ssim'], 3)}" for a in ARMS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", f"Agents per edit: {by[(TABLE4_EDITS[0][0], 'naive')]['agents']}. Arms: naive = the fitted node "
              "as it is; online = the fitted node cut to its box, its unseen side filled by mirror symmetry; pool = "
              "the matched pool model, relit whole by the scene's sun and sky fitted to its views (its material from "
              "the mesh build), the background Gaussians in its box removed; dual = what the product renders for a "
              "request with that edit alone: where the plan gives the track a 360-degree model (a turn of more than "
              "45 degrees), a car the pool model, another vehicle the clarity/size/coverage choice between the two; "
              "where it does not (the translations), the fitted node as it is; pool in-pool = the "
              "pool arm with the edited vehicles' own models added to the pool (matching may still pick another "
              "model: not a bound; the own-model rows below are). "
              "Pool candidates are ranked by "
              f"{report.get('pool_ranking_embedder', 'colour histogram')} and box shape, the best five checked by "
              "rendering them into the scene.", "",
              *_limits_lines(report),
              *_matching_lines(report["matching"]),
              "", "## Pool", "",
              f"{p['size']} models ({', '.join(f'{k} {v}' for k, v in sorted(p['by_category'].items()))}); median "
              f"held-out quality {f(p['quality_db_median'], 1)} dB against ray-cast views; fresh builds "
              f"{', '.join(f(s, 1) for s in p['build_seconds_per_model'])} s per model.", "",
              "Growth from scene tracks (clear, seen large enough and from enough sides with mirror images, held-out "
              "masked PSNR at "
              "least the gate): " + "; ".join(f"after {g['scene_id']}: {g['candidates']} candidate(s), "
                                                f"{len(g['added'])} added, pool {g['pool_size']}" for g in p["growth"])
              + ".", "",
              "## Decisions (dual arm)", "", "| scene | track | strategy | clarity | coverage | model | reason |",
              "|---|---|---|---|---|---|---|"]
    for d in report["decisions"]:
        if d["arm"] != "dual":
            continue
        c = d["clarity"] or {}
        lines.append(f"| {d['scene_id']} | {d['track_id']} | {d['strategy']} | {f(c.get('score'))} | "
                     f"{f(c.get('coverage_mirrored'))} | {d['model_id'] or ''} | {d['reason']} |")
    return "\n".join(lines) + "\n"


def _limits_lines(report: dict) -> list[str]:
    """The 'what limits the pool arm' table (none for reports made before it)."""
    limits = report.get("limits")
    if not limits:
        return []
    own = {(d["scene_id"], d["track_id"]): d["model_id"] for d in report["decisions"] if d["arm"] == "own model"}
    inpool = {(d["scene_id"], d["track_id"]): d["model_id"] for d in report["decisions"]
              if d["arm"] == "pool in-pool" and d.get("strategy") == "pool" and (d["scene_id"], d["track_id"]) in own}
    hits = sum(own[k] == m for k, m in inpool.items())
    arms = ("naive", "pool", "pool in-pool") + LIMITS
    lines = ["## What limits the pool arm at the turns (masked PSNR, dB)", "",
             "| edit | agents | " + " | ".join(arms) + " |", "|---|---|" + "---|" * len(arms)]
    for r in limits:
        cells = ["n/a" if r[a] is None else f"{r[a]:.2f}" for a in arms]
        lines.append(f"| {r['edit']} | {r['agents']} | " + " | ".join(cells) + " |")
    lines += ["", "own model = the pool arm with each edited vehicle given its own asset's model (a pool of that one "
              "model: matching cannot fail; the in-pool arm picked the own model for "
              f"{hits} of {len(inpool)} agents), relit and its box cleared as the pool arm does; box kept = the same "
              "with the background Gaussians in the vehicle's box left in place; colours fitted to the truth = the "
              f"own model's colours (every SH band) fitted to the evaluated views' ground truth ({ORACLE_STEPS} Adam "
              "steps, L1 over the vehicle's pixels): an oracle fitted on the very views it is scored on, so it also "
              "makes up for the shape's misalignment there.", ""]
    return lines


def _strip_png(strips, buf) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 1 + len(ARMS)
    fig, axes = plt.subplots(len(strips), cols, figsize=(2.6 * cols, 1.9 * len(strips)), squeeze=False)
    for r, (title, mask, images) in enumerate(strips):
        ys, xs = np.nonzero(mask)
        y0, y1 = max(ys.min() - 25, 0), min(ys.max() + 25, mask.shape[0])
        x0, x1 = max(xs.min() - 35, 0), min(xs.max() + 35, mask.shape[1])
        for c, (label, img) in enumerate(zip(("ground truth",) + ARMS, images)):
            ax = axes[r, c]
            ax.imshow(img[y0:y1, x0:x1])
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(label, fontsize=9)
            if c == 0:
                ax.set_ylabel(title.split(" (")[0], fontsize=8)
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=70)  # photographic crops: at 110 dpi the strip passes 2 MB
    plt.close(fig)
