"""``omniscs bench background``: removing a large static object, measured against the world re-rendered without it.

Procedural logs with a large parked truck or trailer (a fresh seed set, none used while building the repair) are
fitted with the object as a node (the plan of a 'remove' edit), then the object is removed and the background it
hid is left as fitted (naive), inpainted in 2D per rendered frame (no 3D), or repaired in 3D with seeds at depths
from least-squares-aligned relative depth or from DRNet, without and with the RoI-guided refit. Every arm is
compared with the procedural world re-rendered without the object at held-out logged views and at novel views
(the ego shifted sideways): hole-region PSNR/SSIM, depth AbsRel and delta < 1.25 in the hole, full-image PSNR and
seconds. The depth maps themselves (DRNet vs least squares) are scored at the training views' holes, and the RoI
refit is compared with refitting the whole background (time and quality) and with carrying inpainted pixels
between views.
"""
from __future__ import annotations

import copy
import dataclasses
import logging
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from omniscs.background.depth import load_depth_model
from omniscs.background.holes import hole_mask, ray_norms
from omniscs.background.inpaint import load_inpainter
from omniscs.background.repair import (
    RepairConfig,
    cleaned_graph,
    fill_views,
    plane_fill,
    prepare_views,
    refit_background,
    removed_objects,
    seeded_graph,
)
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.errors import OmniscsError
from omniscs.nsg.checkpoint import load_graph, read_checkpoint_meta
from omniscs.nsg.config import FitConfig
from omniscs.nsg.observations import Observations
from omniscs.pipeline.request import SceneRequest
from omniscs.pipeline.stages import fit_stage, ingest_stage, load_plan, plan_stage
from omniscs.progress import Progress, no_progress
from omniscs.quality import psnr, psnr_from_mse, ssim
from omniscs.scene import SyntheticSource, load_scene
from omniscs.scene.summary import agent_rows
from omniscs.storage import workspace_root
from omniscs.taxonomy import SEMANTIC_CLASSES
from omniscs.world import WorldRenderer, apply_edits
from omniscs.world.model import CameraSpec

log = logging.getLogger(__name__)

PLANES_ARM = "planes + DRNet + RoI refit"
PLANES_SEEDED_ARM = "planes + DRNet + RoI refit, inpainted pixels seeded"
PLANES_AGREE_ARM = ("planes + DRNet + RoI refit, previous textures (depth agreement, nearest view, "
                    "no free-space check)")
PLANES_FIRST_ARM = "planes + DRNet + RoI refit, planes first where the cleaned background covers"
PLANES_INPAINT_ARM = "planes + DRNet + RoI refit, unobserved texels inpainted (no street fill)"
PLANES_PERIODIC_ARM = "planes + DRNet + RoI refit, unobserved texels copied whole periods along the street"
PLANES_SLOW_REFIT_ARM = "planes + DRNet + RoI refit, refit at the fit's learning rates"
ARMS = ("naive", "hidden Gaussians removed", "2D inpainting only", "least squares", "DRNet", "DRNet + RoI refit",
        PLANES_ARM)
"""The issue's rows and the starting point of every 3D repair (the object's node and the background Gaussians only
it hid removed), then the factory's default repair: planes found around the object give depth and a texture
inpainted on the plane where their rays meet one (omniscs.background.planes), Gaussians are seeded there only, and
the RoI refit fits the rest of the hole to the 2D inpainter's fill at DRNet's depth."""
EXTRA_ARMS = ("least squares + RoI refit", "DRNet + full refit", PLANES_SEEDED_ARM,
              "DRNet + RoI refit, carrying between views", "2D inpainting only, embedded inpainter",
              "DRNet + RoI refit, embedded inpainter", "DRNet + RoI refit, embedded inpainter, whole hole",
              PLANES_AGREE_ARM, PLANES_FIRST_ARM, PLANES_INPAINT_ARM, PLANES_PERIODIC_ARM, PLANES_SLOW_REFIT_ARM)
"""The comparisons: the planes arm seeding the inpainted pixels too, at DRNet's depth (the default before
2026-11-27); three that use the embedded inpainting network instead of the configured inpainter, the last one
inpainting every hole pixel (the cleaned background's render of the hole is not kept); the planes arm with the plane
textures it had until the eighth session of 2026-11-27 (a view gave a texel its colour only where its render's solid
depth agreed with the texel's, the nearest view won, and rays took planes where the views see through them); and
planes filling every hole pixel they reach (planes_first; reports/background_bench_planes_first holds a run in
which that was the default arm: it was worse); and the planes arm whose unobserved texels the inpainter fills
without the street fill (PlaneConfig.unobserved='inpaint', the default until the ninth session of 2026-11-27), or
copying the seen texels whole periods away where the texture repeats ('periodic': reports/background_bench_periodic
holds a run in which that was the default arm: it was worse); and the planes arm refitting at the fit's own learning
rates (RepairConfig.refit_lr_scale=1, the default until the fifteenth session of 2026-11-28)."""
STRIP_ARMS = ("naive", "DRNet + RoI refit", PLANES_ARM)
"""The arms shown in the PNG strips, after the ground truth."""


@dataclass(frozen=True)
class BackgroundBenchConfig:
    scenes: tuple[str, ...] = ("straight_parked_truck:101", "straight_parked_truck:102", "straight_parked_truck:103",
                               "straight_parked_truck:104", "straight_parked_truck:105")
    """Held-out procedural logs (template:seed) with a large parked object; seeds 90 and 91 were used while
    building the repair."""
    preset: str = "fast"
    """Fit preset of the scene graphs."""
    offsets_m: tuple[float, ...] = (-1.5, 1.5)
    """Novel views: the ego shifted this far sideways (+ = left) at the held-out frames."""
    views_per_kind: int = 12
    """At most this many evaluated views per scene and kind (logged, each novel offset): every held-out view that
    shows the object, or this many spread evenly over them."""
    min_hole_pixels: int = 400
    """An evaluated view shows at least this many pixels of the object (full resolution)."""
    repair: RepairConfig = field(default_factory=RepairConfig)
    """The repair's settings (the planes arm; the paper's arms turn the planes off); the other arms change one
    field of it."""
    full_comparison: bool = True
    """Also run the ablations (EXTRA_ARMS): least squares + RoI refit, the full background refit, the planes arm
    seeding inpainted pixels, carrying inpainted pixels between views, the embedded inpainter."""
    ablations: tuple[str, ...] | None = None
    """With ``full_comparison``, only these of EXTRA_ARMS (None: all of them)."""

    def __post_init__(self) -> None:
        unknown = sorted(set(self.ablations or ()) - set(EXTRA_ARMS))
        if unknown:
            raise OmniscsError(f"unknown ablation(s) {unknown}; choose from {list(EXTRA_ARMS)}")

    def extra_arms(self) -> tuple[str, ...]:
        """The ablations this run makes, in EXTRA_ARMS' order."""
        if not self.full_comparison:
            return ()
        return tuple(a for a in EXTRA_ARMS if self.ablations is None or a in self.ablations)


def quick_config() -> BackgroundBenchConfig:
    """A smoke run: one scene, few views and steps (not a measurement)."""
    r = RepairConfig(roi_iterations=40, full_iterations=60, drnet=dataclasses.replace(RepairConfig().drnet, steps=60))
    return BackgroundBenchConfig(scenes=("straight_parked_truck:90",), views_per_kind=1, offsets_m=(1.5,),
                                 repair=r)


def _source(item: str, n_frames: int = 40):
    template, _, seed = item.partition(":")
    return SyntheticSource(template, int(seed), "day", n_frames, 3, 480, 270)


def large_static_object(scene) -> int:
    """The track id of the scene's largest static truck, trailer, bus or construction vehicle."""
    rows = [a for a in agent_rows(scene)
            if not a["moving"] and a["category"] in ("truck", "trailer", "bus", "construction_vehicle")]
    if not rows:
        raise OmniscsError(f"scene {scene.scene_id} has no large static object")
    return int(max(rows, key=lambda a: a["length"] * a["width"] * a["height"])["track_id"])


def prepare_scene(item: str, preset: str, workspace: Path, progress: Progress = no_progress, n_frames: int = 40,
                  pick=large_static_object):
    """Ingest (``n_frames`` frames), plan the removal of the object ``pick(scene)`` names (so it becomes a node) and
    fit (reused when fitted before)."""
    ingested = ingest_stage(_source(item, n_frames), workspace)
    scene = load_scene(ingested.path)
    track = pick(scene)
    request = SceneRequest(fit_preset=preset, edits=({"op": "remove", "track_id": track},), previews=False)
    plan = load_plan(plan_stage(ingested.path, request, workspace))
    fitted = fit_stage(ingested.path, plan, preset, workspace, progress=progress)
    if fitted.info["status"] != "fitted":
        raise RuntimeError(f"the fit of {scene.scene_id} diverged: {fitted.info['error']}")
    return scene, plan, fitted, track


@dataclass
class EvalView:
    kind: str              # "logged" or "novel +1.5 m"
    camera: str
    frame: int
    world_from_ego: np.ndarray
    gt_rgb: np.ndarray     # [H, W, 3] uint8, the world without the object
    gt_depth: np.ndarray   # [H, W] z-depth (0 = sky)
    hole: np.ndarray       # [H, W] bool: the object's pixels in the world with it
    lit_rgb: np.ndarray | None = None  # [H, W, 3] uint8, the world without the object but with its shadow and
    #                                    ambient occlusion (what the other views observed behind it)
    gt_semantic: np.ndarray | None = None  # [H, W] uint8 semantic ids of the world without the object (0 = sky)


def _shifted(world, offset_m: float):
    shift = np.eye(4)
    shift[1, 3] = offset_m
    return world.replace(ego_poses=world.ego_poses @ shift)


def evaluation_views(scene, frames, track: int, config: BackgroundBenchConfig) -> list[EvalView]:
    """Held-out logged views and novel views that show the object most (ground truth from the world)."""
    out = []
    for offset in (0.0,) + tuple(config.offsets_m):
        world = scene.world if offset == 0 else _shifted(scene.world, offset)
        removed = apply_edits(world, [{"op": "remove", "track_id": track}])
        with_obj, without = WorldRenderer(world), WorldRenderer(removed)
        # the object invisible to the cameras but still shading its surroundings
        kept_light = WorldRenderer(removed, shadow_casters=[a for a in world.agents if a.track_id == track])
        cands = []
        for f in frames:
            for cam in scene.camera_names:
                hole = with_obj.render_camera(int(f), cam).instance == track
                if hole.sum() >= config.min_hole_pixels:
                    cands.append((int(hole.sum()), int(f), cam, hole))
        if len(cands) > config.views_per_kind:  # evenly over the frames, not the easiest or hardest views
            cands = [cands[int(i)] for i in np.linspace(0, len(cands) - 1, config.views_per_kind).round()]
        picked = [(f, cam, hole) for _, f, cam, hole in cands]
        kind = "logged" if offset == 0 else f"novel {offset:+.1f} m"
        for f, cam, hole in picked:
            gt = without.render_camera(f, cam)
            out.append(EvalView(kind, cam, f, world.ego_poses[f], gt.rgb, gt.depth, hole,
                                kept_light.render_camera(f, cam).rgb, gt.semantic))
    return out


def depth_errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float | None, float | None]:
    """AbsRel and the share with max(pred/gt, gt/pred) < 1.25 over ``mask`` pixels where both are positive."""
    ok = mask & (gt > 0) & np.isfinite(pred) & (pred > 0)
    if not ok.any():
        return None, None
    p, g = pred[ok].astype(np.float64), gt[ok].astype(np.float64)
    return float(np.mean(np.abs(p - g) / g)), float(np.mean(np.maximum(p / g, g / p) < 1.25))


def score_view(rgb: np.ndarray, depth: np.ndarray | None, ev: EvalView) -> dict:
    out = torch.from_numpy(rgb.astype(np.float32) / 255.0)
    gt = torch.from_numpy(ev.gt_rgb.astype(np.float32) / 255.0)
    hole = torch.from_numpy(ev.hole)
    absrel, delta = (None, None) if depth is None else depth_errors(depth, ev.gt_depth, ev.hole)
    lit = None if ev.lit_rgb is None else psnr(out, torch.from_numpy(ev.lit_rgb.astype(np.float32) / 255.0), hole)
    return {"hole_psnr": psnr(out, gt, hole), "hole_ssim": ssim(out, gt, hole), "full_psnr": psnr(out, gt),
            "depth_absrel": absrel, "depth_delta": delta, "hole_psnr_lit": lit}


def object_light_cost(evs: list[EvalView]) -> dict:
    """What the removed object's own light (its sun shadow and ambient occlusion on what lies behind it) costs in
    the hole, per kind of view: the hole PSNR, pooled over the views' hole pixels, of an exact repair that keeps
    that light (the world without the object, shaded as if it were there) against the world without it, and the
    share of hole pixels that light changes by more than 8 grey levels. A repair that reproduces what the other
    views observed behind the object is bounded by it."""
    out = {}
    for kind in ("logged", "novel"):
        sel = [ev for ev in evs if ev.kind.startswith(kind) and ev.lit_rgb is not None]
        if not sel:
            continue
        lit = np.concatenate([ev.lit_rgb[ev.hole] for ev in sel]).astype(np.float64)
        gt = np.concatenate([ev.gt_rgb[ev.hole] for ev in sel]).astype(np.float64)
        out[kind] = {"pooled_hole_psnr": psnr(torch.from_numpy(lit[None] / 255.0), torch.from_numpy(gt[None] / 255.0)),
                     "changed_share": float(np.mean(np.abs(lit - gt).max(1) > 8)), "views": len(sel)}
    return out


CLASS_ARMS = ("naive", "hidden Gaussians removed", PLANES_ARM)
"""The arms whose hole error the report splits by what truly lies in the hole."""


def class_errors(rgb: np.ndarray, ev: EvalView) -> dict[str, list[float]]:
    """Per semantic class of the world without the object (omniscs.taxonomy), over the hole: [pixels, summed
    squared error] (per pixel the mean over channels of the error in 0..1), to pool over views and scenes."""
    if ev.gt_semantic is None or not ev.hole.any():
        return {}
    err = ((rgb.astype(np.float64) - ev.gt_rgb.astype(np.float64)) / 255.0) ** 2
    err = err.mean(-1)[ev.hole]
    sem = ev.gt_semantic[ev.hole]
    out = {}
    for c in np.unique(sem):
        sel = sem == c
        out[SEMANTIC_CLASSES.get(int(c), str(int(c)))] = [int(sel.sum()), float(err[sel].sum())]
    return out


def pooled_class_errors(per_view: list[dict[str, list[float]]]) -> dict[str, list[float]]:
    """class_errors of several views (and scenes) added up."""
    out: dict[str, list[float]] = {}
    for d in per_view:
        for name, (n, sse) in d.items():
            acc = out.setdefault(name, [0, 0.0])
            acc[0] += int(n)
            acc[1] += float(sse)
    return out


def render_eval(graph, ev: EvalView) -> tuple[np.ndarray, np.ndarray]:
    out = graph.render(graph.view(ev.camera, ev.frame, ev.world_from_ego))
    return ((out.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8),
            np.where(out.alpha.numpy() > 0.5, out.depth.numpy(), 0.0))


def inpaint_render(graph, obj, inpainter, ev: EvalView) -> np.ndarray:
    """The 2D-only arm: the naive render with the object's projected box (dilated) inpainted in the image."""
    rgb, _ = render_eval(graph, ev)
    mask = hole_mask(graph.view(ev.camera, ev.frame, ev.world_from_ego), [obj])
    if mask.all():
        return rgb  # nothing to inpaint from: the 2D method leaves the frame as it is
    return inpainter.inpaint(rgb, mask)


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(statistics.fmean(vals)) if vals else None


def map_errors(hole_views, scene, track: int, factor: int) -> dict:
    """DRNet / least-squares depth maps against the world without the object at the training views' holes."""
    world = apply_edits(scene.world, [{"op": "remove", "track_id": track}])
    cams = []
    for c in world.cameras:
        K = c.K.copy()
        K[:2] /= factor
        cams.append(CameraSpec(c.name, c.width // factor, c.height // factor, K, c.ego_from_camera))
    renderer = WorldRenderer(world.replace(cameras=tuple(cams)))

    errs, deltas, n = [], [], 0
    for hv in hole_views:
        gt = renderer.render_camera(hv.frame, hv.camera).depth
        gt_range = np.where(gt > 0, gt * ray_norms(hv.view), 0.0)
        pred = hv.filled_depth
        ok = hv.mask & np.isfinite(pred) & (gt_range > 0)
        if not ok.any():
            continue
        p, g = pred[ok].astype(np.float64), gt_range[ok]
        errs.append(np.abs(p - g) / g)
        deltas.append(np.maximum(p / g, g / p) < 1.25)
        n += int(ok.sum())
    if not n:
        return {"absrel": None, "delta": None, "pixels": 0}
    return {"absrel": float(np.concatenate(errs).mean()), "delta": float(np.concatenate(deltas).mean()), "pixels": n}


def run_scene(item: str, config: BackgroundBenchConfig, workspace: Path, inpainter, depth_model,
              progress: Progress = no_progress) -> dict:
    scene, plan, fitted, track = prepare_scene(item, config.preset, workspace, progress)
    graph = load_graph(fitted.path, scene)
    fit_config = FitConfig.from_dict(read_checkpoint_meta(fitted.path)["config"])
    obs = Observations(scene, plan.cameras)
    train_views = [(c, int(f)) for f in plan.train_frames for c in plan.cameras]
    objects = removed_objects(graph, [track])
    naive = graph.replace(agents=tuple(a for a in graph.agents if a.track_id != track))
    evs = evaluation_views(scene, plan.heldout_frames, track, config)
    # the paper's method (no planes, Gaussians seeded at every inpainted pixel); the planes arms turn them on
    rc = dataclasses.replace(config.repair, planes=False, seed_inpainted=True)

    t0 = time.perf_counter()
    holes = prepare_views(graph, obs, objects, train_views, rc, progress)
    base_views = holes.views
    cleaned, dropped = cleaned_graph(graph, objects, holes.hidden)
    hole_seconds = time.perf_counter() - t0
    arms: dict[str, dict] = {}  # arm -> {"graph" | "render", "seconds"}
    maps = {}
    fills = {}
    for method in ("lsq", "drnet"):
        cfg = dataclasses.replace(rc, depth_method=method)
        views = copy.deepcopy(base_views)
        t0 = time.perf_counter()
        fill_views(views, cleaned, cfg, inpainter, depth_model, progress)
        seeded, n_seeds = seeded_graph(cleaned, views, cfg)
        fills[method] = (views, seeded, n_seeds, hole_seconds + time.perf_counter() - t0)
        maps[method] = map_errors(views, scene, track, rc.factor)
    extras = config.extra_arms()
    refits = [("DRNet + RoI refit", "drnet", dataclasses.replace(rc, refit="roi")),
              ("least squares + RoI refit", "lsq", dataclasses.replace(rc, refit="roi", depth_method="lsq")),
              ("DRNet + full refit", "drnet", dataclasses.replace(rc, refit="full"))]
    for name, method, cfg in refits:
        if name != "DRNet + RoI refit" and name not in extras:
            continue
        views, seeded, n_seeds, seconds = fills[method]
        t0 = time.perf_counter()
        g, info = refit_background(seeded, n_seeds, objects, views, obs, train_views, fit_config, cfg, progress)
        arms[name] = {"graph": g, "seconds": seconds + time.perf_counter() - t0, "refit_seconds": info["refit_seconds"],
                      "trainable": info["trainable"]}
    def refit_arm(cfg, filler) -> dict:
        views = copy.deepcopy(base_views)
        t0 = time.perf_counter()
        facts = plane_fill(views, cleaned, obs, objects, train_views, cfg, filler, progress) if cfg.planes else {}
        fill_views(views, cleaned, cfg, filler, depth_model, progress)
        seeded, n_seeds = seeded_graph(cleaned, views, cfg)
        g, info = refit_background(seeded, n_seeds, objects, views, obs, train_views, fit_config, cfg, progress)
        return {"graph": g, "seconds": hole_seconds + time.perf_counter() - t0, "views": views, "facts": facts}

    planes_cfg = dataclasses.replace(config.repair, planes=True)
    arms[PLANES_ARM] = refit_arm(planes_cfg, inpainter)
    maps["planes"] = map_errors(arms[PLANES_ARM]["views"], scene, track, rc.factor)

    network = load_inpainter("embedded") if any("embedded" in a for a in extras) else None
    ablations = {
        PLANES_SEEDED_ARM: lambda: refit_arm(dataclasses.replace(planes_cfg, seed_inpainted=True), inpainter),
        "DRNet + RoI refit, carrying between views": lambda: refit_arm(dataclasses.replace(rc, carry=True), inpainter),
        "DRNet + RoI refit, embedded inpainter": lambda: refit_arm(rc, network),
        "DRNet + RoI refit, embedded inpainter, whole hole": lambda: refit_arm(
            dataclasses.replace(rc, keep_observed=False), network),
        PLANES_AGREE_ARM: lambda: refit_arm(dataclasses.replace(planes_cfg, plane=dataclasses.replace(
            planes_cfg.plane, texel_visibility="agree", free_space=False, texel_colour="nearest",
            unobserved="inpaint"), planes_first=False), inpainter),
        PLANES_FIRST_ARM: lambda: refit_arm(dataclasses.replace(planes_cfg, planes_first=True), inpainter),
        PLANES_INPAINT_ARM: lambda: refit_arm(dataclasses.replace(planes_cfg, plane=dataclasses.replace(
            planes_cfg.plane, unobserved="inpaint")), inpainter),
        PLANES_PERIODIC_ARM: lambda: refit_arm(dataclasses.replace(planes_cfg, plane=dataclasses.replace(
            planes_cfg.plane, unobserved="periodic")), inpainter),
        PLANES_SLOW_REFIT_ARM: lambda: refit_arm(dataclasses.replace(planes_cfg, refit_lr_scale=1.0), inpainter)}
    for name, make in ablations.items():
        if name in extras:
            arms[name] = make()
    if PLANES_AGREE_ARM in arms:
        maps["planes, depth agreement"] = map_errors(arms[PLANES_AGREE_ARM]["views"], scene, track, rc.factor)
    arms["naive"] = {"graph": naive, "seconds": 0.0}
    arms["hidden Gaussians removed"] = {"graph": cleaned, "seconds": hole_seconds}
    arms["least squares"] = {"graph": fills["lsq"][1], "seconds": fills["lsq"][3]}
    arms["DRNet"] = {"graph": fills["drnet"][1], "seconds": fills["drnet"][3]}

    rows, strip = [], None
    by_class: dict[str, dict[str, list]] = {}
    strip_view = max((ev for ev in evs if ev.kind != "logged"), key=lambda ev: ev.hole.sum(), default=None)
    for name in ARMS + extras:
        per_view = []
        t_inpaint = 0.0
        for ev in evs:
            if name.startswith("2D inpainting only"):
                t0 = time.perf_counter()
                rgb, depth = inpaint_render(naive, objects[0], network if "embedded" in name else inpainter, ev), None
                t_inpaint += time.perf_counter() - t0
            else:
                rgb, depth = render_eval(arms[name]["graph"], ev)
            per_view.append({"kind": ev.kind, **score_view(rgb, depth, ev)})
            if name in CLASS_ARMS:
                by_class.setdefault(name, {}).setdefault("novel" if ev.kind.startswith("novel") else "logged",
                                                        []).append(class_errors(rgb, ev))
            if ev is strip_view and name in STRIP_ARMS:
                strip = (strip or {"gt": ev.gt_rgb, "hole": ev.hole, "label": f"{ev.camera} frame {ev.frame} {ev.kind}"})
                strip[name] = rgb
        seconds = t_inpaint if name.startswith("2D inpainting only") else arms[name]["seconds"]
        for kind in ("logged", "novel"):
            sel = [v for v in per_view if v["kind"].startswith(kind)]
            rows.append({"scene_id": scene.scene_id, "track_id": track, "arm": name, "views": kind, "n_views": len(sel),
                         **{k: _mean([v[k] for v in sel]) for k in ("hole_psnr", "hole_ssim", "full_psnr",
                                                                     "depth_absrel", "depth_delta", "hole_psnr_lit")},
                         "seconds": seconds})
    views, _, n_seeds, _ = fills["drnet"]
    facts = {"scene_id": scene.scene_id, "source": item, "track_id": track,
             "category": graph.agent(track).category, "size": [float(x) for x in graph.agent(track).size],
             "heldout_psnr": fitted.info["metrics"]["heldout_psnr"], "hole_views": len(views), "seeds": n_seeds,
             "dropped_gaussians": dropped, "observed_pixels": sum(h.observed for h in views),
             "carried_pixels": sum(h.carried for h in views), "inpainted_pixels": sum(h.inpainted for h in views),
             "unfilled_pixels": sum(int(h.unfilled.sum()) for h in views),
             "hole_pixels": sum(int(h.mask.sum()) for h in views),
             "depth_maps": maps, "object_light": object_light_cost(evs), "planes": arms[PLANES_ARM]["facts"],
             "eval_views": {k: sum(ev.kind.startswith(k) for ev in evs) for k in ("logged", "novel")},
             "classes": {arm: {kind: pooled_class_errors(v) for kind, v in kinds.items()}
                         for arm, kinds in by_class.items()}}
    for name in ("DRNet + RoI refit", "DRNet + full refit"):
        if name in arms:
            facts[name] = {"refit_seconds": arms[name]["refit_seconds"], "trainable": arms[name]["trainable"]}
    return {"rows": rows, "facts": facts, "strip": strip}


def summary(rows: list[dict]) -> list[dict]:
    out = []
    arms = list(dict.fromkeys(r["arm"] for r in rows))
    for arm in arms:
        for kind in ("logged", "novel"):
            sel = [r for r in rows if r["arm"] == arm and r["views"] == kind]
            out.append({"arm": arm, "views": kind, "scenes": len(sel),
                        **{k: _mean([r[k] for r in sel]) for k in ("hole_psnr", "hole_ssim", "depth_absrel",
                                                                    "depth_delta", "full_psnr", "hole_psnr_lit",
                                                                    "seconds")}})
    return out


def run_background_benchmark(out_dir: Path, workspace: Path | None = None,
                             config: BackgroundBenchConfig = BackgroundBenchConfig(),
                             progress: Progress = no_progress) -> dict:
    workspace = Path(workspace) if workspace else workspace_root()
    machine = machine_info()
    inpainter = load_inpainter(config.repair.inpainter)
    depth_model = load_depth_model(config.repair.depth_model)
    rows, facts, strips = [], [], []
    started = time.perf_counter()
    for item in config.scenes:
        result = run_scene(item, config, workspace, inpainter, depth_model, progress)
        rows += result["rows"]
        facts.append(result["facts"])
        if result["strip"] is not None:
            strips.append(result["strip"])
    summ = summary(rows)
    report = {"config": _config_dict(config), "machine": finish(machine), "seconds": time.perf_counter() - started,
              "rows": rows, "scenes": facts, "summary": summ, "targets": targets(summ, facts),
              "inpainter": getattr(inpainter, "name", str(inpainter)),
              "depth_model": getattr(depth_model, "name", str(depth_model))}
    write_report(out_dir, "background", report, background_markdown(report),
                 {"": lambda buf: _strip_png(strips, buf)} if strips else None)
    return report


def _config_dict(config: BackgroundBenchConfig) -> dict:
    return asdict(config)


def targets(summ: list[dict], facts: list[dict]) -> dict:
    def get(arm, kind, key):
        for r in summ:
            if r["arm"] == arm and r["views"] == kind:
                return r[key]
        return None

    dr = _mean([f["depth_maps"]["drnet"]["absrel"] for f in facts])
    ls = _mean([f["depth_maps"]["lsq"]["absrel"] for f in facts])
    naive, repaired = get("naive", "novel", "hole_psnr"), get("DRNet + RoI refit", "novel", "hole_psnr")
    planes = get(PLANES_ARM, "novel", "hole_psnr")
    pl = _mean([f["depth_maps"].get("planes", {}).get("absrel") for f in facts])
    roi = _mean([f.get("DRNet + RoI refit", {}).get("refit_seconds") for f in facts])
    full = _mean([f.get("DRNet + full refit", {}).get("refit_seconds") for f in facts])
    out = {"drnet_absrel": dr, "lsq_absrel": ls,
           "drnet_absrel_met": dr is not None and dr <= 0.05,
           "drnet_vs_lsq": None if dr is None or not ls else 1.0 - dr / ls,
           "novel_gain_db": None if naive is None or repaired is None else repaired - naive,
           "planes_novel_gain_db": None if naive is None or planes is None else planes - naive, "planes_absrel": pl,
           "roi_over_full_time": None if not roi or not full else roi / full}
    out["drnet_vs_lsq_met"] = out["drnet_vs_lsq"] is not None and out["drnet_vs_lsq"] >= 0.30
    out["novel_gain_met"] = any(v is not None and v >= 6.0 for v in (out["novel_gain_db"], out["planes_novel_gain_db"]))
    out["roi_time_met"] = out["roi_over_full_time"] is not None and out["roi_over_full_time"] <= 0.20
    return out


def class_table(scenes: list[dict], kind: str = "novel") -> list[str]:
    """Markdown rows: per class of what truly lies in the hole, pooled over the scenes' ``kind`` views, its share
    of the hole pixels, each CLASS_ARMS arm's PSNR there and the share of the last arm's squared error it holds
    (classes by that share, largest first)."""
    pooled = {arm: pooled_class_errors([s.get("classes", {}).get(arm, {}).get(kind, {}) for s in scenes])
              for arm in CLASS_ARMS}
    last = pooled[CLASS_ARMS[-1]]
    pixels = sum(n for n, _ in last.values())
    total = sum(e for _, e in last.values())
    if not pixels:
        return []

    def db(n, sse):
        return psnr_from_mse(sse / n)

    out = ["| what lies there | hole pixels | " + " | ".join(f"{a}: PSNR (dB)" for a in CLASS_ARMS)
           + f" | share of the {CLASS_ARMS[-1]} arm's squared error |", "|---" * (len(CLASS_ARMS) + 3) + "|"]
    for name, (n, sse) in sorted(last.items(), key=lambda kv: -kv[1][1]):
        cells = [f"{db(*pooled[a][name]):.2f}" if name in pooled[a] else "—" for a in CLASS_ARMS]
        share = f"{100 * sse / total:.0f} %" if total > 0 else "—"
        out.append(f"| {name} | {100 * n / pixels:.1f} % | " + " | ".join(cells) + f" | {share} |")
    return out


def background_markdown(report: dict) -> str:
    def f(v, d=2):
        return "—" if v is None else f"{v:.{d}f}"

    t = report["targets"]
    lower = "—" if t["drnet_vs_lsq"] is None else f"{100 * t['drnet_vs_lsq']:.0f} %"
    lines = [
        "# Background repair after removing a large static object (`omniscs bench background`)", "",
        f"Held-out procedural logs {', '.join(report['config']['scenes'])} (40 frames x 3 cameras at 480x270, "
        f"fit preset {report['config']['preset']}); each scene's largest parked truck/trailer is removed and every "
        "arm is compared with the world re-rendered without it: held-out logged views and novel views (ego shifted "
        f"{', '.join(f'{o:+.1f}' for o in report['config']['offsets_m'])} m sideways). Hole = the object's pixels in "
        "the world with it. Inpainter: " + report["inpainter"] + "; relative depth: " + report["depth_model"] + ". "
        + load_line(report["machine"]) + f" Total {report['seconds'] / 60:.1f} min.", "",
        "| arm | views | hole PSNR (dB) | hole SSIM | depth AbsRel | δ<1.25 | full PSNR (dB) | seconds | "
        "hole PSNR against the world keeping the object's shadow (dB) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["summary"]:
        lines.append(f"| {r['arm']} | {r['views']} | {f(r['hole_psnr'])} | {f(r['hole_ssim'], 3)} | "
                     f"{f(r['depth_absrel'], 3)} | {f(r['depth_delta'], 3)} | {f(r['full_psnr'])} | {f(r['seconds'], 1)} | "
                     f"{f(r['hole_psnr_lit'])} |")
    lines += ["", "The object's own light: the world without the object but shaded as if it were there (its sun shadow "
              "and ambient occlusion kept) against the world without it, in the hole. What the other views observed "
              "behind the object carries that light, so a repair that reproduces it exactly scores this (pooled over "
              "the views' hole pixels):", "",
              "| scene | logged: hole PSNR | changed pixels | novel: hole PSNR | changed pixels |", "|---|---|---|---|---|"]
    for s in report["scenes"]:
        lt = s["object_light"]
        cells = [f"{f(lt[k]['pooled_hole_psnr'])} | {100 * lt[k]['changed_share']:.0f} %" if k in lt else "— | —"
                 for k in ("logged", "novel")]
        lines.append(f"| {s['scene_id']} | {cells[0]} | {cells[1]} |")
    rows = class_table(report["scenes"], "novel")
    if rows:
        lines += ["", "Where the error lies: the hole pixels of the novel views, pooled over the scenes, by what the "
                  "world without the object shows there (its semantic class):", ""] + rows
    lines += ["", "Depth maps in the training views' holes (before any refit) against the world without the object:", "",
              "| scene | least squares AbsRel | δ<1.25 | DRNet AbsRel | δ<1.25 | pixels | planes + DRNet AbsRel | δ<1.25 "
              "| pixels | hole pixels on a plane |", "|---|---|---|---|---|---|---|---|---|---|"]
    for s in report["scenes"]:
        m, pm, pf = s["depth_maps"], s["depth_maps"].get("planes", {}), s.get("planes", {})
        share = f"{100 * pf['plane_pixels'] / s['hole_pixels']:.0f} %" if pf and s["hole_pixels"] else "—"
        lines.append(f"| {s['scene_id']} | {f(m['lsq']['absrel'], 3)} | {f(m['lsq']['delta'], 3)} | "
                     f"{f(m['drnet']['absrel'], 3)} | {f(m['drnet']['delta'], 3)} | {m['drnet']['pixels']:,} | "
                     f"{f(pm.get('absrel'), 3)} | {f(pm.get('delta'), 3)} | {pm.get('pixels', 0):,} | {share} |")
    lines += ["", "RoI refit against refitting the whole background (same seeds, same targets):", "",
              "| scene | RoI refit (s) | trainable | full refit (s) | trainable | ratio |", "|---|---|---|---|---|---|"]
    for s in report["scenes"]:
        roi, full = s.get("DRNet + RoI refit", {}), s.get("DRNet + full refit", {})
        ratio = roi.get("refit_seconds") / full["refit_seconds"] if full.get("refit_seconds") else None
        lines.append(f"| {s['scene_id']} | {f(roi.get('refit_seconds'), 1)} | {roi.get('trainable', '—'):,} | "
                     f"{f(full.get('refit_seconds'), 1)} | {full.get('trainable', '—'):,} | {f(ratio, 3)} |"
                     if full else f"| {s['scene_id']} | {f(roi.get('refit_seconds'), 1)} | — | — | — | — |")
    lines += ["", "Scenes:", "", "| scene | object | size (m) | held-out PSNR | hole views | hole px | carried | "
              "inpainted | unfilled | seeds |", "|---|---|---|---|---|---|---|---|---|---|"]
    for s in report["scenes"]:
        lines.append(f"| {s['scene_id']} | {s['category']} {s['track_id']} | {' x '.join(f'{x:.1f}' for x in s['size'])} | "
                     f"{f(s['heldout_psnr'])} | {s['hole_views']} | {s['hole_pixels']:,} | {s['carried_pixels']:,} | "
                     f"{s['inpainted_pixels']:,} | {s['unfilled_pixels']:,} | {s['seeds']:,} |")
    roi_verdict = ("not measured: the full refit is an ablation" if t["roi_over_full_time"] is None
                   else "met" if t["roi_time_met"] else "NOT met")
    lines += ["", "Targets:", "",
              f"- DRNet depth AbsRel ≤ 0.05: {f(t['drnet_absrel'], 3)} ({'met' if t['drnet_absrel_met'] else 'NOT met'})",
              f"- DRNet ≥ 30 % lower AbsRel than least squares ({f(t['lsq_absrel'], 3)}): {lower} "
              f"({'met' if t['drnet_vs_lsq_met'] else 'NOT met'})",
              f"- repaired hole PSNR ≥ 6 dB above naive at novel views: DRNet + RoI refit {f(t['novel_gain_db'])} dB, "
              f"{PLANES_ARM} {f(t.get('planes_novel_gain_db'))} dB ({'met' if t['novel_gain_met'] else 'NOT met'})",
              f"- RoI refit ≤ 20 % of a full refit's time: {f(t['roi_over_full_time'], 3)} "
              f"({roi_verdict})", "",
              "![strips](report.png)", "",
              f"Strips (one novel view per scene): ground truth without the object, naive removal, DRNet + RoI refit "
              f"and {PLANES_ARM}; the object's outline in red. Depth AbsRel of the planes arm (hole pixels where "
              "a plane is met take its depth, the rest DRNet's): "
              f"{f(t.get('planes_absrel'), 3)}.", ""]
    return "\n".join(lines)


def _strip_png(strips: list[dict], buf) -> None:
    import cv2
    from PIL import Image

    rows = []
    for s in strips:
        tiles = []
        for key in ("gt",) + STRIP_ARMS:
            if key not in s:
                continue
            img = s[key].copy()
            edge = cv2.morphologyEx(s["hole"].astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
            img[edge] = (255, 0, 0)
            tiles.append(img)
        rows.append(np.concatenate(tiles, 1))
    sheet = Image.fromarray(np.concatenate(rows, 0))
    sheet = sheet.resize((sheet.width // 2, sheet.height // 2), Image.LANCZOS)  # a readable overview, small in git
    sheet.save(buf, format="PNG", optimize=True)
