"""Repairing the background behind removed or moved large static objects (the paper's depth-refinement
background reconstruction), on a fitted scene graph:

1. holes: per training view (at a working resolution), the pixels where the object is the first surface
   (omniscs.background.holes), dilated;
2. known depth outside the holes: LiDAR returns and the background's Gaussian centres that are visible (their
   depth agrees with the rendered depth), as the distance to the camera centre;
3. relative depth of each original image; DRNet trained per scene to map it to that absolute depth;
4. hole pixels the cleaned background covers keep what other views observed there; the 2D inpainter fills the
   rest of each view (views with too little context are left unsupervised), and the inpainted pixels' relative
   depth goes through DRNet (or the least-squares baseline); optionally (``carry``) views go in order of growing
   hole share and what earlier views filled is carried into later ones through its 3D points first; with
   ``planes`` (the default), hole pixels the cleaned background does not cover and whose ray meets a plane found
   around the object take that plane's depth and texture first (omniscs.background.planes), and only the rest
   goes to the inpainter and DRNet;
5. the background loses its Gaussians inside the object's box and the hidden ones, and gains seeds at the lifted
   inpainted pixels, less those some view would see in front of background it observed (a wrong depth);
6. RoI-guided refit: only background Gaussians inside the enlarged box (and the seeds) are optimised, on crops
   around each view's hole, with the fit's own loop (omniscs.nsg.train.refit); or a full refit of the
   background for comparison, or none.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from omniscs.background.depth import load_depth_model
from omniscs.background.drnet import DRNetConfig, FittedDRNet, aligned_inverse, least_squares_depth, train_drnet
from omniscs.background.planes import (Donor, FreeSpace, PlaneConfig, build_textures, fit_planes, plane_hits,
                                       region_points, texture_colours)
from omniscs.background.holes import (RemovedObject, box_entry_distance, crop_view, dilate, hole_bbox, hole_mask,
                                      lift_pixels, ray_norms)
from omniscs.background.inpaint import load_inpainter
from omniscs.errors import OmniscsError
from omniscs.gaussians import activate, concat_params, with_sh_degree
from omniscs.geometry import points_in_box
from omniscs.nsg.background import init_background, voxel_subsample
from omniscs.nsg.config import FitConfig
from omniscs.nsg.graph import BACKGROUND, SceneGraph, agent_key
from omniscs.nsg.observations import Observations, View, project_points
from omniscs.nsg.train import refit
from omniscs.progress import Progress, no_progress

log = logging.getLogger(__name__)

#: The repair's output version (recorded next to the checkpoint; part of the stage key).
REPAIR_VERSION = 1

DEPTH_METHODS = ("drnet", "lsq")

#: Something is in front of the removed object where the rest of the graph renders nearer than this share of the
#: distance at which the pixel's ray enters the object's box.
OCCLUDER_SHARE = 0.9

#: A refit is declared diverged when a view's loss exceeds this multiple of that view's best.
REFIT_MAX_LOSS_RATIO = 10.0

#: A seed nearer than this share below the solid background's depth at a pixel counts as in front of it.
SEED_DEPTH_SLACK = 0.05

#: DRNet trains on the known depths inside each hole's bounding box grown by this many times its size per side.
NEAR_HOLE_GROW = 0.5

#: A hole pixel that the cleaned background covers at least this much shows what other views observed there.
OBSERVED_ALPHA = 0.95

#: A view shows nothing at all (the sky) where the cleaned background covers less than this of the pixel.
EMPTY_ALPHA = 0.05
REFIT_MODES = ("roi", "full", "none")

#: The learning rates RepairConfig.refit_lr_scale multiplies (the sky and the exposures are held in the refit).
REFIT_SCALED_RATES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


@dataclass(frozen=True)
class RepairConfig:
    """How the background behind removed objects is repaired. The paper's method is planes=False,
    seed_inpainted=True; the defaults add the planes and seed only their pixels."""

    factor: int = 2
    """Views are repaired at 1/factor of the logged resolution (holes, inpainting, depth, refit)."""
    inpainter: str | None = None
    """2D inpainter (omniscs.background.inpaint.load_inpainter spec); None: OpenCV's FSR, no weights needed."""
    depth_model: str | None = None
    """Relative depth model (omniscs.background.depth.load_depth_model spec); None: the shipped network."""
    depth_method: str = "drnet"
    """'drnet' (the paper) or 'lsq' (least-squares scale and shift of the relative depth: the baseline)."""
    carry: bool = False
    """Carry pixels filled in earlier views into later ones through their 3D points (one texture for all views);
    False (the default: better on the development logs, where carried pixels sat at their source view's depth
    errors) inpaints every view on its own and lets the refit reconcile them."""
    keep_observed: bool = True
    """Hole pixels the cleaned background covers keep its render (what other views observed there); False
    inpaints every hole pixel from the image around the hole."""
    min_context: float = 0.2
    """A view is inpainted only if at least this share of its pixels is known (outside the hole, or carried);
    otherwise only carried pixels fill it and the rest is not supervised."""
    visible_tolerance: float = 0.05
    """A Gaussian centre is a depth target where its depth is within this fraction of the rendered depth."""
    seed_voxel_m: float = 0.1
    """Lifted hole pixels are thinned to one per voxel of this size before seeding Gaussians."""
    seed_opacity: float = 0.8
    """Opacity of the seeded Gaussians (high: without a refit they must already cover the hole)."""
    seed_check: bool = True
    """Drop seeds that some view would see in front of background it observed (a wrong depth; see
    consistent_seeds)."""
    seed_max_scale_m: float = 0.3
    """Largest initial size of a seeded Gaussian."""
    seed_inpainted: bool = False
    """Seed Gaussians also at the pixels the 2D inpainter filled, at their DRNet (or least-squares) depth, as the
    paper does (True: the paper's method); False (the default) seeds only the pixels the planes fill, at their exact
    depth, and leaves the inpainted pixels to the refit's existing Gaussians (they stay targets of its colour and
    depth losses). Without planes, False seeds nothing. Chosen on the development logs 90-95 (hole PSNR at novel
    views 16.36 against 16.06 dB); on the held-out logs 101-105 18.46 against 18.31
    (docs/design-notes.md, background repair)."""
    refit: str = "roi"
    """'roi' (optimise only background Gaussians in the enlarged box, on crops around the holes), 'full'
    (every background Gaussian on whole images: the comparison) or 'none' (seeds only)."""
    roi_iterations: int = 300
    """Steps of the RoI refit."""
    full_iterations: int = 1_500
    """Steps of the full background refit (the fast fit preset's count)."""
    refit_lr_scale: float = 2.0
    """The refit's learning rates (means, rotations, sizes, opacities, colours) are the fit's times this (the sky
    and the exposures are held): the hole's Gaussians start far from what the filled views show, and the refit has
    few steps. 2 is the default since the fifteenth session of 2026-11-28, chosen on the development logs 90, 91, 93
    and 94 (with PlaneConfig.unobserved='periodic'): hole PSNR at novel views 18.20 -> 18.51, 20.86 -> 20.89,
    17.98 -> 18.27, 18.05 -> 18.31 dB, at no extra time; on the held-out logs 101-105, with the default street fill,
    19.97 against 19.82 dB (reports/background/report.md; docs/design-notes.md). On the development logs three times
    as many steps at the fit's rates gained about as much (17.29 -> 17.61, 20.79 -> 20.97 dB) but would cost the RoI
    refit its time target, and faster colours alone nothing (17.27, 20.83)."""
    crop_margin_px: int = 12
    """Pixels around a hole's bounding box in the RoI refit's crops (at the working resolution)."""
    depth_weight: float = 0.1
    """Weight of the refined-depth loss on the filled hole pixels during the refit."""
    drnet: DRNetConfig = field(default_factory=DRNetConfig)
    """DRNet training."""
    planes: bool = True
    """Hole pixels that the cleaned background does not cover and whose ray meets a plane found around the object
    (road, sidewalk, facade: see omniscs.background.planes) take that plane's depth and its texture, gathered from
    every view and inpainted on the plane; DRNet and the 2D inpainter fill only the rest. False (with
    seed_inpainted=True): the paper's method. Chosen on the development logs 90/91 (+0.8 / +0.4 dB hole PSNR at
    novel views, depth AbsRel 0.09 / 0.12 against 0.32 / 0.21); on the held-out logs 101-105 +0.14 dB (18.31
    against 18.17, 1.6 dB worse on one log whose views saw 4 % of the texture), depth AbsRel 0.184 against 0.269
    (reports/background/ablations.md). With the plane textures of PlaneConfig.texel_visibility / texel_colour /
    free_space: 19.59 dB at novel views, +4.82 over naive (docs/design-notes.md); with the texels no view
    saw filled along the street (PlaneConfig.unobserved): 19.82 dB, +5.05 (docs/design-notes.md); with
    the refit at twice the fit's learning rates (refit_lr_scale): 19.97 dB, +5.20 (reports/background/report.md,
    the default's run)."""
    plane: PlaneConfig = field(default_factory=PlaneConfig)
    """Finding and texturing the planes."""
    planes_first: bool = False
    """True: planes fill the hole pixels they meet even where the cleaned background covers them; False (the
    default): the cleaned background's render, what other views observed there, wins. Tried in the eighth session
    of 2026-11-27: chosen on the development logs 90 and 91 (17.99 -> 17.94 and 20.09 -> 21.00 dB at novel views),
    it scored 19.35 against 19.59 dB on the held-out logs 101-105 (docs/design-notes.md, background repair; 1.6 dB
    worse on log 102), so it is not the default."""

    def __post_init__(self) -> None:
        if self.depth_method not in DEPTH_METHODS:
            raise OmniscsError(f"unknown depth method {self.depth_method!r}; use one of {list(DEPTH_METHODS)}")
        if self.refit not in REFIT_MODES:
            raise OmniscsError(f"unknown refit mode {self.refit!r}; use one of {list(REFIT_MODES)}")
        if not (np.isfinite(self.refit_lr_scale) and self.refit_lr_scale > 0):
            raise OmniscsError(f"refit_lr_scale must be a positive number; got {self.refit_lr_scale!r}")
        if not isinstance(self.factor, int) or self.factor < 1:
            raise OmniscsError(f"factor must be a positive integer; got {self.factor!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class HoleView:
    """One training view being repaired (at the working resolution)."""

    camera: str
    frame: int
    view: View
    image: np.ndarray           # [h, w, 3] uint8 logged image
    mask: np.ndarray            # [h, w] bool hole
    target_depth: np.ndarray    # [h, w] float32 known distance to the camera (m), NaN where unknown
    relative: np.ndarray | None = None      # [h, w] relative depth of the logged image
    filled: np.ndarray | None = None        # [h, w, 3] uint8 image with the hole filled where it could be
    filled_depth: np.ndarray | None = None  # [h, w] float32 distance (m) of hole pixels, NaN elsewhere / unfilled
    unfilled: np.ndarray | None = None      # [h, w] bool hole pixels nothing filled
    new: np.ndarray | None = None           # [h, w] bool hole pixels the 2D inpainter filled
    solid_z: np.ndarray | None = None       # [h, w] z-depth of the cleaned background where it is solid, else inf
    plane_dist: np.ndarray | None = None    # [h, w] float32 distance (m) to the plane a hole pixel meets, NaN: none
    plane_rgb: np.ndarray | None = None     # [h, w, 3] uint8 that plane's texture
    planar: np.ndarray | None = None        # [h, w] bool hole pixels the planes fill
    observed: int = 0
    plane_filled: int = 0
    carried: int = 0
    inpainted: int = 0

    @property
    def hole_share(self) -> float:
        return float(self.mask.mean())


@dataclass
class RepairResult:
    graph: SceneGraph
    views: list[HoleView]
    drnet: FittedDRNet | None
    seconds: dict[str, float]
    facts: dict


def removed_objects(graph: SceneGraph, track_ids) -> list[RemovedObject]:
    """The agent nodes ``track_ids`` of ``graph`` as objects to repair behind (their logged boxes)."""
    return [RemovedObject.from_node(graph.agent(int(t))) for t in track_ids]


def _uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.detach().clamp(0, 1).cpu().numpy() * 255.0).round().astype(np.uint8)


@dataclass
class Holes:
    """What the removed objects hid: the training views they show in, and the background Gaussians that every
    training view sees only behind them (never constrained by an image: the stain a naive removal shows)."""

    views: list[HoleView]
    hidden: np.ndarray  # [N] bool over the graph's background rows


def prepare_views(graph: SceneGraph, obs: Observations, objects: list[RemovedObject], views: list[tuple[str, int]],
                  config: RepairConfig, progress: Progress = no_progress) -> Holes:
    """Holes and known depth of every ``views`` (camera, frame) where an object shows, and the hidden background
    Gaussians: behind an object in some view (deeper than where its pixel's ray enters the box) and at or in
    front of the rendered surface in none (``visible_tolerance``)."""
    ids = {o.track_id for o in objects}
    without = graph.replace(agents=tuple(a for a in graph.agents if a.track_id not in ids))
    centres = activate(graph.background.detached()).means.cpu().numpy().astype(np.float64)
    seen = np.zeros(len(centres), bool)
    behind = np.zeros(len(centres), bool)
    out: list[HoleView] = []
    for i, (cam, f) in enumerate(views):
        progress(i, len(views), f"holes {cam} frame {f}")
        view = obs.view(cam, f).downscaled(config.factor)
        rendered = graph.render(view)
        depth, alpha = rendered.depth.cpu().numpy(), rendered.alpha.cpu().numpy()
        uv, z, inside = project_points(view, centres)
        idx = np.flatnonzero(inside)
        px = np.floor(uv[idx]).astype(np.int64)
        surface = np.where(alpha > 0.5, depth, np.inf)[px[:, 1], px[:, 0]]
        seen[idx[z[idx] <= surface * (1.0 + config.visible_tolerance)]] = True
        box_hit = hole_mask(view, objects, 0)
        if not box_hit.any():
            continue
        entry = np.full(box_hit.shape, np.inf)
        for o in objects:
            if o.present[f]:
                entry = np.minimum(entry, box_entry_distance(view, o.pose(f), o.size))
        behind[idx[z[idx] > entry[px[:, 1], px[:, 0]]]] = True
        # the object is the first surface, except where the rest of the graph puts something clearly nearer (a
        # passing car, a tree, a lamp post) in front of its box
        rest = without.render(view)
        nearer = (rest.alpha.cpu().numpy() > 0.5) & (rest.depth.cpu().numpy() < OCCLUDER_SHARE * entry)
        first = box_hit & ~nearer
        if not first.any():
            continue
        dilation = max(1, int(round(4 / config.factor)))
        mask = dilate(first, dilation)
        target = _known_depth(rest, view, obs, cam, f, centres, mask, config)
        image = _uint8(obs.image(cam, f, config.factor))
        out.append(HoleView(cam, f, view, image, mask, target))
    return Holes(out, behind & ~seen)


def cleaned_graph(graph: SceneGraph, objects: list[RemovedObject], hidden: np.ndarray) -> tuple[SceneGraph, int]:
    """The graph without the objects' nodes, the hidden background Gaussians and those inside the objects' boxes;
    returns it and how many background Gaussians went."""
    ids = {o.track_id for o in objects}
    bg = graph.background
    means = activate(bg.detached()).means.cpu().numpy().astype(np.float64)
    drop = np.asarray(hidden, bool).copy()
    for o in objects:
        for f in np.flatnonzero(o.present)[:1]:
            drop |= points_in_box(means, o.pose(int(f)), o.size)
    kept = bg.select(torch.from_numpy(np.flatnonzero(~drop)).to(bg.device))
    return graph.replace(background=kept, agents=tuple(a for a in graph.agents if a.track_id not in ids)), int(drop.sum())


def _known_depth(rendered, view: View, obs: Observations, cam: str, f: int, centres: np.ndarray,
                 mask: np.ndarray, config: RepairConfig) -> np.ndarray:
    """Distance to the camera at pixels outside ``mask`` that LiDAR or a visible Gaussian centre pins down
    (visible: within ``visible_tolerance`` of ``rendered``, the view's render of the graph without the objects)."""
    h, w = mask.shape
    norms = ray_norms(view)
    target = np.full((h, w), np.nan, dtype=np.float32)
    rdepth, ralpha = rendered.depth.cpu().numpy(), rendered.alpha.cpu().numpy()
    uv, z, inside = project_points(view, centres)
    px = np.floor(uv[inside]).astype(np.int64)
    z = z[inside]
    ok = (ralpha[px[:, 1], px[:, 0]] > 0.9) & (np.abs(z - rdepth[px[:, 1], px[:, 0]]) <= config.visible_tolerance * z)
    px, z = px[ok], z[ok]
    order = np.argsort(-z)  # nearest written last
    target[px[order, 1], px[order, 0]] = z[order]
    luv, lz = obs.lidar_depth_targets(cam, f)
    if len(lz):
        lpx = np.clip(np.floor(luv / config.factor).astype(np.int64), 0, [w - 1, h - 1])
        order = np.argsort(-lz)
        target[lpx[order, 1], lpx[order, 0]] = lz[order]  # LiDAR wins over centres
    target[mask] = np.nan
    return (target * norms).astype(np.float32)


def _splat(view: View, points: np.ndarray, colours: np.ndarray, where: np.ndarray,
           radius: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-buffered splat of world points into the ``where`` pixels of ``view``: colour [h, w, 3] uint8, distance
    [h, w] (NaN where nothing landed), hit [h, w] bool."""
    h, w = where.shape
    colour = np.zeros((h, w, 3), np.uint8)
    dist = np.full((h, w), np.nan, np.float32)
    if len(points) == 0:
        return colour, dist, np.zeros((h, w), bool)
    uv, z, inside = project_points(view, points)
    uv, z, cols = uv[inside], z[inside], colours[inside]
    rng = np.linalg.norm(points[inside] - view.world_from_camera[:3, 3], axis=1)
    order = np.argsort(-z)
    best = np.full((h, w), np.inf)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            x = np.floor(uv[order, 0]).astype(np.int64) + dx
            y = np.floor(uv[order, 1]).astype(np.int64) + dy
            ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            x, y, zz, o = x[ok], y[ok], z[order][ok], order[ok]
            sel = where[y, x]
            x, y, zz, o = x[sel], y[sel], zz[sel], o[sel]
            # later writes (nearer points) win within this offset; keep the nearest over offsets
            tmp = np.full((h, w), np.inf)
            idx = np.full((h, w), -1)
            tmp[y, x] = zz
            idx[y, x] = o
            better = tmp < best
            best[better] = tmp[better]
            colour[better] = cols[idx[better]]
            dist[better] = rng[idx[better]]
    return colour, dist, np.isfinite(best)


def plane_points(obs: Observations, cleaned: SceneGraph, frames) -> np.ndarray:
    """World points that can carry the planes: the LiDAR returns of ``frames``, or where the log has no LiDAR the
    cleaned background's opaque Gaussian centres."""
    lidar = [obs.lidar_world(int(f)) for f in frames]
    points = np.concatenate(lidar) if lidar else np.zeros((0, 3))
    if len(points):
        return points
    g = activate(cleaned.background.detached())
    opaque = g.opacities.reshape(-1).cpu().numpy() > 0.5
    return g.means.cpu().numpy().astype(np.float64)[opaque]


def plane_fill(hole_views: list[HoleView], cleaned: SceneGraph, obs: Observations, objects: list[RemovedObject],
               train_views: list[tuple[str, int]], config: RepairConfig, inpainter,
               progress: Progress = no_progress) -> dict:
    """Planes around the objects, their textures from every training view (inpainted on the plane where no view
    saw them), and per hole view the pixels they fill (``plane_dist``, ``plane_rgb``, ``planar``), in place.
    Returns what was found."""
    frames = sorted({int(f) for _, f in train_views})
    points = plane_points(obs, cleaned, frames)
    planes = []
    for o in objects:
        planes += fit_planes(region_points(points, o), config.plane, street=o.roi()[0][:3, 0])
    by_key = {(hv.camera, hv.frame): hv for hv in hole_views}
    donors = []
    for i, (cam, f) in enumerate(train_views):
        progress(i, len(train_views), f"plane texture views {cam} frame {f}")
        view = obs.view(cam, f).downscaled(config.factor)
        rendered = cleaned.render(view)
        alpha, depth = rendered.alpha.cpu().numpy(), rendered.depth.cpu().numpy()
        solid = np.where(alpha > OBSERVED_ALPHA, depth, np.inf)
        near = np.where(alpha > 0.5, depth, np.inf)
        nothing = alpha < EMPTY_ALPHA
        hv = by_key.get((cam, f))
        if hv is not None:
            solid[hv.mask] = np.inf  # the logged pixel shows the object
            near[hv.mask] = 0.0
            nothing[hv.mask] = False
            image = hv.image
        else:
            image = _uint8(obs.image(cam, f, config.factor))
        donors.append(Donor(view, image, solid, nothing, near))
    free = FreeSpace(planes, donors, config.plane) if config.plane.free_space else None
    hits = []
    for hv in hole_views:
        entry = np.full(hv.mask.shape, np.inf)
        for o in objects:
            if o.present[hv.frame]:
                entry = np.minimum(entry, box_entry_distance(hv.view, o.pose(hv.frame), o.size))
        hv.plane_dist, which = plane_hits(hv.view, hv.mask, planes, entry, empty=None if free is None else free.empty)
        hits.append((hv.view, hv.plane_dist, which))
    textures = build_textures(planes, hits, donors, inpainter, config.plane)
    for hv, (_, dist, which) in zip(hole_views, hits):
        hv.plane_rgb, hv.planar = texture_colours(hv.view, dist, which, textures)
    used = [t for t in textures if t is not None]
    return {"planes": len(planes), "textured_planes": len(used),
            "plane_pixels": sum(int(hv.planar.sum()) for hv in hole_views),
            "texels_observed": int(sum(int((t.observed & t.needed).sum()) for t in used)),
            "texels_needed": int(sum(int(t.needed.sum()) for t in used))}


def fill_views(hole_views: list[HoleView], cleaned: SceneGraph, config: RepairConfig, inpainter, depth_model,
               progress: Progress = no_progress) -> FittedDRNet | None:
    """Steps 3-4 of the module docstring, in place on ``hole_views``; returns the trained DRNet (None for lsq).
    Hole pixels that the ``cleaned`` graph (objects and hidden Gaussians gone) covers (coverage above
    OBSERVED_ALPHA) keep its render: other views observed what lies there."""
    for i, hv in enumerate(hole_views):
        progress(i, len(hole_views), f"relative depth {hv.camera} frame {hv.frame}")
        hv.relative = np.asarray(depth_model.predict(hv.image), dtype=np.float32)
    drnet = None
    if config.depth_method == "drnet":
        usable = [hv for hv in hole_views if np.isfinite(hv.target_depth).any()]
        if not usable:
            raise OmniscsError("no training view has a known depth outside the hole (no visible Gaussian centre, no "
                               "LiDAR return): DRNet cannot be trained")
        inputs = [aligned_inverse(hv.relative, hv.target_depth) for hv in usable]
        drnet = train_drnet(inputs, [near_hole(hv.target_depth, hv.mask) for hv in usable], config.drnet, progress)
    points = np.zeros((0, 3))
    colours = np.zeros((0, 3), np.uint8)
    for i, hv in enumerate(sorted(hole_views, key=lambda v: v.hole_share)):
        progress(i, len(hole_views), f"filling {hv.camera} frame {hv.frame}")
        image = hv.image.copy()
        depth = np.full(hv.mask.shape, np.nan, np.float32)
        todo = hv.mask.copy()
        rendered = cleaned.render(hv.view)
        # where the cleaned background is solid, and how far (z): seeds must not end up in front of it
        hv.solid_z = np.where(rendered.alpha.cpu().numpy() > OBSERVED_ALPHA, rendered.depth.cpu().numpy(), np.inf)
        seen = todo & (rendered.alpha.cpu().numpy() > OBSERVED_ALPHA) & config.keep_observed
        if config.planes_first and hv.planar is not None:
            seen &= ~hv.planar
        image[seen] = _uint8(rendered.rgb)[seen]
        depth[seen] = (rendered.depth.cpu().numpy() * ray_norms(hv.view))[seen]
        todo &= ~seen
        hv.observed = int(seen.sum())
        planar = np.zeros_like(todo)
        if hv.planar is not None:
            planar = hv.planar & todo
            image[planar], depth[planar] = hv.plane_rgb[planar], hv.plane_dist[planar]
            todo &= ~planar
            hv.plane_filled = int(planar.sum())
        if config.carry and len(points):
            c, d, hit = _splat(hv.view, points, colours, todo)
            image[hit], depth[hit] = c[hit], d[hit]
            todo &= ~hit
            hv.carried = int(hit.sum())
        new = np.zeros_like(todo)
        if todo.any() and 1.0 - todo.mean() >= config.min_context:
            image = inpainter.inpaint(image, todo)
            rel = np.asarray(depth_model.predict(image), dtype=np.float32)
            # depths outside the hole, and the carried and observed pixels' inside it
            known = np.where(np.isfinite(hv.target_depth), hv.target_depth, depth)
            if drnet is not None:
                est = drnet.predict(aligned_inverse(rel, known))
            else:
                est = least_squares_depth(rel, known)
            depth[todo] = est[todo]
            new, todo = todo, np.zeros_like(todo)
            hv.inpainted = int(new.sum())
        new = new | planar
        hv.filled, hv.filled_depth, hv.unfilled, hv.new = (image, np.where(hv.mask, depth, np.nan).astype(np.float32),
                                                           todo, new)
        if new.any():
            points = np.concatenate([points, lift_pixels(hv.view, new, depth)])
            colours = np.concatenate([colours, image[new]])
    return drnet


def near_hole(target: np.ndarray, mask: np.ndarray, grow: float = NEAR_HOLE_GROW) -> np.ndarray:
    """``target`` kept only inside the hole's bounding box grown by ``grow`` times its size on every side (NaN
    elsewhere): DRNet learns the mapping where it will be used, not on the far side of the image."""
    box = hole_bbox(mask, 0)
    if box is None:
        return target
    x0, y0, x1, y1 = box
    gx, gy = int(grow * (x1 - x0)), int(grow * (y1 - y0))
    out = np.full_like(target, np.nan)
    sl = (slice(max(0, y0 - gy), y1 + gy), slice(max(0, x0 - gx), x1 + gx))
    out[sl] = target[sl]
    return out


def consistent_seeds(points: np.ndarray, colours: np.ndarray,
                     hole_views: list[HoleView]) -> tuple[np.ndarray, np.ndarray]:
    """Drop lifted points that some view would see in front of the solid cleaned background at a pixel its
    inpainter did not fill (outside the hole, or observed inside it): a point there is at a wrong depth, and
    would cover what that view saw. Points behind solid background stay hidden and are harmless."""
    bad = np.zeros(len(points), bool)
    for hv in hole_views:
        if hv.solid_z is None:
            continue
        uv, z, inside = project_points(hv.view, points)
        idx = np.flatnonzero(inside)
        px = np.floor(uv[idx]).astype(np.int64)
        solid = hv.solid_z[px[:, 1], px[:, 0]]
        free = ~hv.new[px[:, 1], px[:, 0]] if hv.new is not None else np.ones(len(idx), bool)
        bad[idx[free & (z[idx] < (1.0 - SEED_DEPTH_SLACK) * solid)]] = True
    return points[~bad], colours[~bad]


def seeded_graph(cleaned: SceneGraph, hole_views: list[HoleView], config: RepairConfig) -> tuple[SceneGraph, int]:
    """``cleaned`` plus Gaussians seeded at the inpainted hole pixels (coloured, at their estimated depth),
    thinned per voxel; returns it and the count of seeds (appended last to the background)."""
    bg = cleaned.background
    pts, cols = [], []
    for hv in hole_views:
        ok = hv.new & np.isfinite(hv.filled_depth)
        if not config.seed_inpainted:
            ok &= hv.planar if hv.planar is not None else np.zeros_like(ok)
        if not ok.any():
            continue
        pts.append(lift_pixels(hv.view, ok, hv.filled_depth))
        cols.append(hv.filled[ok].astype(np.float64) / 255.0)
    if not pts:
        return cleaned, 0
    p, c = np.concatenate(pts), np.concatenate(cols)
    if config.seed_check:
        p, c = consistent_seeds(p, c, hole_views)
    if not len(p):
        return cleaned, 0
    keep = voxel_subsample(p, config.seed_voxel_m, len(p), np.random.default_rng(0))
    seeds = with_sh_degree(init_background(p[keep], c[keep], 0, config.seed_opacity, config.seed_max_scale_m),
                           cleaned.sh_degree).to(bg.device)
    return cleaned.replace(background=concat_params([bg, seeds])), len(keep)


def refit_background(graph: SceneGraph, n_seeds: int, objects: list[RemovedObject], hole_views: list[HoleView],
                     obs: Observations, train_views: list[tuple[str, int]], fit_config: FitConfig,
                     config: RepairConfig, progress: Progress = no_progress) -> tuple[SceneGraph, dict]:
    """Step 6: the RoI-guided refit (``config.refit == 'roi'``) or the full background refit ('full')."""
    means = activate(graph.background.detached()).means.cpu().numpy().astype(np.float64)
    n = len(means)
    if config.refit == "roi":
        rows = np.zeros(n, bool)
        for o in objects:
            rows |= points_in_box(means, *o.roi())
        rows[n - n_seeds:] = True
        samples = [_roi_sample(hv, config) for hv in hole_views if not hv.unfilled.all()]
        iterations = config.roi_iterations
    else:
        rows = np.ones(n, bool)
        by_key = {(hv.camera, hv.frame): hv for hv in hole_views}
        samples = [_roi_sample(by_key[k], config, crop=False) if k in by_key else _plain_sample(obs, k, config)
                   for k in train_views]
        iterations = config.full_iterations
    if not samples:
        raise OmniscsError("no view has a filled hole pixel to refit on (every hole view lacks context and "
                           "nothing could be carried into it)")
    trainable = {BACKGROUND: torch.from_numpy(rows).to(graph.device)}
    for a in graph.agents:
        trainable[agent_key(a.track_id)] = torch.zeros(len(a.gaussians), dtype=torch.bool, device=graph.device)
    strategy = dataclasses.replace(fit_config.strategy, refine_start_iter=max(50, iterations // 6),
                                   refine_stop_iter=int(0.8 * iterations), refine_every=50, reset_every=0)
    loss = dataclasses.replace(fit_config.loss, depth_weight=config.depth_weight)
    # the views' losses differ by orders of magnitude (small and large holes, inpainted and well-fitted views): the
    # refit compares each view's loss with that view's own best
    lr = dataclasses.replace(fit_config.lr, **{name: getattr(fit_config.lr, name) * config.refit_lr_scale
                                               for name in REFIT_SCALED_RATES})
    cfg = dataclasses.replace(fit_config, iterations=iterations, strategy=strategy, loss=loss, sh_degree_interval=1,
                              max_loss_ratio=max(fit_config.max_loss_ratio, REFIT_MAX_LOSS_RATIO), lr=lr)
    budgets = {BACKGROUND: int(rows.sum() * 1.3)}
    scale = {BACKGROUND: float(max(10.0, np.ptp(means[rows], axis=0).max() if rows.any() else 10.0))}
    device = graph.device

    def sample(i: int, step: int):
        view, target, depth = samples[i]
        return view, target.to(device), 1, depth

    started = time.perf_counter()
    graph, history = refit(graph, cfg, len(samples), sample, trainable, scale, budgets,
                           label=f"{config.refit} background refit", progress=progress)
    return graph, {"iterations": iterations, "views": len(samples), "trainable": int(rows.sum()),
                   "refit_seconds": time.perf_counter() - started, "history": history}


def _roi_sample(hv: HoleView, config: RepairConfig, crop: bool = True):
    """(view, target [h, w, 3] float with NaN where not supervised, depth targets) of a hole view, cropped to
    its hole's bounding box (+ margin) when ``crop``."""
    target = hv.filled.astype(np.float32) / 255.0
    target[hv.unfilled] = np.nan
    view = hv.view
    ok = hv.mask & np.isfinite(hv.filled_depth)
    ys, xs = np.nonzero(ok)
    z = hv.filled_depth[ok] / ray_norms(view)[ok]
    if crop:
        box = hole_bbox(hv.mask, config.crop_margin_px)
        x0, y0, x1, y1 = box
        view = crop_view(view, box)
        target = target[y0:y1, x0:x1]
        xs, ys = xs - x0, ys - y0
    step = 2  # every other pixel is plenty of depth supervision
    uv = np.stack([xs[::step] + 0.5, ys[::step] + 0.5], 1).astype(np.float64)
    return view, torch.from_numpy(np.ascontiguousarray(target)), (uv, z[::step].astype(np.float64))


def _plain_sample(obs: Observations, key: tuple[str, int], config: RepairConfig):
    cam, f = key
    return obs.view(cam, f).downscaled(config.factor), obs.image(cam, f, config.factor).cpu(), None


def repair_background(graph: SceneGraph, obs: Observations, track_ids, train_views: list[tuple[str, int]],
                      fit_config: FitConfig, config: RepairConfig = RepairConfig(), inpainter=None, depth_model=None,
                      progress: Progress = no_progress) -> RepairResult:
    """Remove the agent nodes ``track_ids`` (large static objects) from ``graph`` and repair the background they
    hid, from the ``train_views`` (camera, frame) the graph was fitted on. Returns the repaired graph, with those
    nodes back where they were (an edit that removes or moves them shows the repaired background), and what was
    done."""
    inpainter = inpainter or load_inpainter(config.inpainter)
    depth_model = depth_model or load_depth_model(config.depth_model)
    objects = removed_objects(graph, track_ids)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    holes = prepare_views(graph, obs, objects, train_views, config, progress)
    hole_views = holes.views
    if not hole_views:
        raise OmniscsError(f"track(s) {sorted(track_ids)} cover no pixel of any training view: nothing to repair")
    cleaned, dropped = cleaned_graph(graph, objects, holes.hidden)
    seconds["holes"] = time.perf_counter() - t0
    plane_facts = {}
    if config.planes:
        t0 = time.perf_counter()
        plane_facts = plane_fill(hole_views, cleaned, obs, objects, train_views, config, inpainter, progress)
        seconds["planes"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    drnet = fill_views(hole_views, cleaned, config, inpainter, depth_model, progress)
    seconds["fill"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    seeded, n_seeds = seeded_graph(cleaned, hole_views, config)
    seconds["seed"] = time.perf_counter() - t0
    facts = {"hole_views": len(hole_views), "seeds": n_seeds, "dropped_gaussians": dropped,
             "observed_pixels": sum(h.observed for h in hole_views),
             "plane_filled_pixels": sum(h.plane_filled for h in hole_views),
             "carried_pixels": sum(h.carried for h in hole_views),
             "inpainted_pixels": sum(h.inpainted for h in hole_views),
             "unfilled_pixels": sum(int(h.unfilled.sum()) for h in hole_views),
             "hole_pixels": sum(int(h.mask.sum()) for h in hole_views), **plane_facts}
    if config.refit != "none":
        seeded, info = refit_background(seeded, n_seeds, objects, hole_views, obs, train_views, fit_config, config,
                                        progress)
        seconds["refit"] = info.pop("refit_seconds")
        facts["refit"] = {k: v for k, v in info.items() if k != "history"}
    ids = {o.track_id for o in objects}
    restored = seeded.replace(agents=seeded.agents + tuple(a for a in graph.agents if a.track_id in ids))
    return RepairResult(restored, hole_views, drnet, seconds, facts)
