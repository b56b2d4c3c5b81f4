"""One camera view of a variant, rendered with its ground truth from the same rasterisation: colour, depth, and a
label channel per instance that may show, blended with the colours' own weights. An instance's channel at a pixel
is how much of that pixel it covers once everything in front of it is taken off, so the instance mask (front-most
instance where that share is high), the unoccluded share of its alpha (visibility) and its tight 2D box all come
from what was drawn, not from a separate geometric guess."""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from omniscs.annotate.config import AnnotateConfig
from omniscs.annotate.replay import Replay
from omniscs.errors import OmniscsError
from omniscs.gaussians import Gaussians, activate
from omniscs.geometry import (BOX_EDGES, box_corners_from_pose, clip_segment_to_near, invert_transform,
                              make_transform)
from omniscs.nsg.compose import NodePose, place_gaussians
from omniscs.nsg.graph import BACKGROUND, SceneGraph, agent_key, agent_may_show, node_radius, render_view
from omniscs.quality import psnr
from omniscs.nsg.observations import View
from omniscs.quaternions import quat_to_rotmat, rotmat_to_quat
from omniscs.render import rasterize
from omniscs.taxonomy import SEMANTIC_IDS, VEHICLE_CATEGORIES

#: Semantic id of pixels the Gaussians cover but no instance claims: the scene graph does not know what the
#: background is made of (road, building, ...), only that something is there.
SEMANTIC_UNKNOWN = 255
#: Background Gaussians within this margin of a background track's box belong to that track (metres).
MEMBER_MARGIN_M = 0.15
#: ... unless they lie this close above the box floor (road surface under the object).
MEMBER_GROUND_CLEARANCE_M = 0.1


#: Padding of the projected boxes that decide which instances share an own-alpha rendering: (fraction of the
#: box's size, pixels) on every side.
OWN_ALPHA_PAD = (0.1, 4.0)
#: Unedited renders kept by one annotator for the feature drift of its variants (bytes).
UNEDITED_CACHE_BYTES = 256 * 2 ** 20


@dataclass(frozen=True)
class Instance:
    """A box that may be drawn in a view, and which Gaussians draw it."""

    track_id: int
    category: str
    world_from_box: np.ndarray  # [4, 4]
    size: np.ndarray            # [3] length, width, height
    members: Tensor | None = None  # background Gaussian indices of a track left in the background; None = a node


@dataclass(frozen=True)
class InstanceLabel:
    """What one instance looks like in one view."""

    track_id: int
    mask_pixels: int
    visible_alpha: float     # sum over pixels of the instance's unoccluded share
    own_alpha: float         # sum over pixels of its alpha rendered alone (0 when not rendered: nothing visible)
    in_image_fraction: float  # of its projected box rectangle (1 - truncation)
    visibility: float        # in_image_fraction * visible_alpha / own_alpha, in [0, 1]
    box2d: tuple[float, float, float, float] | None        # projected 3D box, clipped to the image (x1, y1, x2, y2)
    box2d_tight: tuple[float, float, float, float] | None  # around its instance-mask pixels
    camera_from_box: np.ndarray  # [4, 4]


@dataclass(frozen=True)
class ViewAnnotation:
    """One rendered, labelled view."""

    rgb: np.ndarray        # uint8 [H, W, 3]
    depth: np.ndarray      # float32 [H, W] metres along the camera axis; 0 = no surface
    instance: np.ndarray   # int32 [H, W] track id; -1 = none
    semantic: np.ndarray   # uint8 [H, W]: 0 sky, vehicle / obstacle for instances, SEMANTIC_UNKNOWN elsewhere
    labels: tuple[InstanceLabel, ...]  # every instance whose projected box meets the image


def background_members(graph: SceneGraph, tracks: dict[int, tuple[np.ndarray, np.ndarray]]  # id -> (pose, size)
                       ) -> dict[int, Tensor]:
    """The background Gaussians inside each background track's box (grown by MEMBER_MARGIN_M, above its floor
    plus MEMBER_GROUND_CLEARANCE_M): the Gaussians that draw that object (it never moves, so once per graph)."""
    means = graph.background.means.detach().to(torch.float64).cpu().numpy()
    out = {}
    for tid, (world_from_box, size) in tracks.items():
        local = (means - world_from_box[:3, 3]) @ world_from_box[:3, :3]
        half = 0.5 * np.asarray(size, dtype=np.float64)
        inside = np.all(np.abs(local[:, :2]) <= half[:2] + MEMBER_MARGIN_M, axis=1)
        inside &= (local[:, 2] <= half[2] + MEMBER_MARGIN_M) & (local[:, 2] >= -half[2] + MEMBER_GROUND_CLEARANCE_M)
        out[int(tid)] = torch.from_numpy(np.flatnonzero(inside))
    return out


class ViewAnnotator:
    """Renders and labels views of one scene graph (background activated once, node radii once)."""

    def __init__(self, graph: SceneGraph, config: AnnotateConfig = AnnotateConfig(),
                 replay: Replay | None = None) -> None:
        self.graph = graph
        self.config = config
        self.replay = replay
        self.background = activate(graph.background.detached())
        self.radii = {a.track_id: node_radius(a.gaussians) for a in graph.agents}
        self.local = {a.track_id: activate(a.gaussians.detached()) for a in graph.agents}
        self.activated = {BACKGROUND: self.background, **{agent_key(t): p for t, p in self.local.items()}}
        self._unedited: dict[tuple[str, int], tuple[np.ndarray, float | None]] = {}  # rgb, logged PSNR
        self._unedited_bytes = 0
        self._logged_rects: dict[tuple[str, int], dict[int, tuple[float, float, float, float]]] = {}
        self._clear_cache: tuple | None = None  # (key, graph, activated) of the last cleared sensor position
        self.last_render_seconds = 0.0
        """Seconds the last ``annotate`` spent in the rasterisation of colour, depth and labels (the rest is
        annotation: masks, boxes, the instances' own alpha)."""

    @torch.no_grad()
    def annotate(self, view: View, node_poses: dict[int, np.ndarray],  # moved agent nodes: world_from_agent
                 instances: list[Instance], hidden: frozenset[int] = frozenset(),
                 boxes: bool = True) -> ViewAnnotation:
        """Colour, depth, instance and semantic masks of ``view`` and (``boxes``) each instance's label; agent nodes
        in ``hidden`` are not drawn (a closed-loop scenario has them absent where their log has them)."""
        graph, cfg = self.graph, self.config
        f = graph.check_frame(view.frame_idx)
        camera_from_world = invert_transform(view.world_from_camera)
        showing: list[Instance] = []
        for inst in instances:
            radius = (self.radii.get(inst.track_id, 0.0) if inst.members is None else 0.0)
            radius = max(radius, 0.5 * float(np.linalg.norm(inst.size)))
            if agent_may_show(view, inst.world_from_box[:3, 3], radius, graph.settings.near_plane):
                showing.append(inst)
        labels = None
        if showing:
            n_bg = len(graph.background)
            bg = torch.zeros(n_bg, len(showing))
            labels = {BACKGROUND: bg}
            for e, inst in enumerate(showing):
                if inst.members is not None:
                    bg[inst.members, e] = 1.0
                else:
                    labels[agent_key(inst.track_id)] = torch.ones(len(graph.agent(inst.track_id).gaussians), 1) \
                        * torch.nn.functional.one_hot(torch.tensor(e), len(showing)).to(torch.float32)
        tick = time.perf_counter()
        out = render_view(graph, view, agent_poses=self._poses(node_poses, f), labels=labels,
                          only_agents=[t for t in self._may_show(view, node_poses) if t not in hidden],
                          activated=self.activated)
        self.last_render_seconds = time.perf_counter() - tick
        rgb = (out.rgb.clamp(0.0, 1.0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
        alpha = out.alpha.cpu().numpy()
        depth = self._surface_depth(out.depth.cpu().numpy(), alpha)
        instance = np.full(alpha.shape, -1, dtype=np.int32)
        semantic = np.where(alpha >= cfg.depth_alpha, SEMANTIC_UNKNOWN, SEMANTIC_IDS["sky"]).astype(np.uint8)
        results = []
        if showing:
            top, best = out.labels.max(-1)  # [H, W]: the largest share and whose it is
            best = best.cpu().numpy()
            claimed = top.cpu().numpy() >= cfg.mask_weight
            totals = out.labels.sum((0, 1)).double().cpu().numpy()  # [E] visible alpha per instance
            ids = np.array([inst.track_id for inst in showing], dtype=np.int32)
            kinds = np.array([SEMANTIC_IDS["vehicle" if inst.category in VEHICLE_CATEGORIES else "obstacle"]
                              for inst in showing], dtype=np.uint8)
            instance = np.where(claimed, ids[best], instance).astype(np.int32)
            semantic = np.where(claimed, kinds[best], semantic).astype(np.uint8)
            seen = [inst for e, inst in enumerate(showing) if totals[e] > 0.0]
            own = self._own_alphas(view, seen, node_poses) if boxes else {}
            for e, inst in enumerate(showing if boxes else ()):
                label = self._label(view, camera_from_world, inst, float(totals[e]), instance,
                                    own.get(inst.track_id, 0.0))
                if label is not None:
                    results.append(label)
        return ViewAnnotation(rgb, depth, instance, semantic, tuple(results))

    @torch.no_grad()
    def depth(self, view: View, node_poses: dict[int, np.ndarray],  # moved agent nodes: world_from_agent
              hidden: frozenset[int] = frozenset(), min_alpha: float | None = None,
              background_clearance_m: float = 0.0) -> np.ndarray:  # -> float32 [H, W] metres along the axis
        """The depth ``annotate`` would give ``view`` (0 where the Gaussians cover less than ``min_alpha``, by
        default ``depth_alpha``, of a pixel), without colour worth keeping or labels: what a simulated sensor needs
        (``omniscs.annotate.lidar``). Background Gaussians whose centres lie within ``background_clearance_m`` of
        the view's centre are left out (agent nodes never are). The view need not be a camera the fit saw (depth
        needs no exposure)."""
        graph, activated = self._cleared(view.world_from_camera[:3, 3], background_clearance_m)
        f = graph.check_frame(view.frame_idx)
        out = render_view(graph, view, sh_degree=0, agent_poses=self._poses(node_poses, f),
                          only_agents=[t for t in self._may_show(view, node_poses) if t not in hidden],
                          activated=activated)
        return self._surface_depth(out.depth.cpu().numpy(), out.alpha.cpu().numpy(), min_alpha)

    def _cleared(self, centre_world: np.ndarray,  # [3]
                 radius_m: float) -> tuple[SceneGraph, dict[str, Gaussians]]:
        """The graph and its activated nodes without the background Gaussians centred within ``radius_m`` of
        ``centre_world``; the last one is kept, as the views of one sensor position share it."""
        if radius_m <= 0.0:
            return self.graph, self.activated
        key = (tuple(np.asarray(centre_world, dtype=np.float64).round(9).tolist()), float(radius_m))
        if self._clear_cache is None or self._clear_cache[0] != key:
            bg = self.background
            centre = torch.as_tensor(np.asarray(centre_world), dtype=bg.means.dtype, device=bg.means.device)
            keep = torch.linalg.vector_norm(bg.means - centre, dim=1) >= radius_m
            graph = dataclasses.replace(self.graph, background=self.graph.background.select(keep))
            activated = {**self.activated, BACKGROUND: Gaussians(bg.means[keep], bg.quats[keep], bg.scales[keep],
                                                                 bg.opacities[keep], bg.sh[keep])}
            self._clear_cache = (key, graph, activated)
        return self._clear_cache[1], self._clear_cache[2]

    def _surface_depth(self, depth: np.ndarray, alpha: np.ndarray,  # [H, W] x2 -> float32 [H, W]
                       min_alpha: float | None = None) -> np.ndarray:
        """Depth where the Gaussians cover at least ``min_alpha`` (default ``depth_alpha``) of the pixel, else 0;
        never NaN or infinite."""
        min_alpha = self.config.depth_alpha if min_alpha is None else min_alpha
        out = np.where(alpha >= min_alpha, depth, 0.0).astype(np.float32)
        return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)

    @torch.no_grad()
    def unedited(self, camera: str, frame: int, logged_image: Callable[[], np.ndarray] | None = None,
                 keep: bool = True) -> tuple[View, np.ndarray, float | None]:
        """The logged view of ``camera`` at ``frame``, the graph's unedited render of it (uint8 [H, W, 3]) and,
        when ``logged_image()`` gives the logged image, that render's PSNR against it: read from the graph's replay
        when it has the view (``omniscs.annotate.replay``), else rendered; made once for all the variants this
        annotator labels (while UNEDITED_CACHE_BYTES has room; ``keep=False`` keeps nothing)."""
        view = self.graph.view(camera, frame)
        key = (camera, view.frame_idx)
        rgb, logged_psnr = self._unedited.get(key, (None, None))
        fresh = rgb is None
        if fresh and self.replay is not None and key in self.replay:
            rgb, logged_psnr = self.replay.view(*key)
            if rgb.shape != (view.height, view.width, 3):
                raise OmniscsError(f"replay {self.replay.folder} view {key} is {rgb.shape[1]}x{rgb.shape[0]}, "
                                   f"not the camera's {view.width}x{view.height}")
        elif fresh:
            out = render_view(self.graph, view, only_agents=self._may_show(view, {}), activated=self.activated)
            rgb = (out.rgb.clamp(0.0, 1.0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
        if logged_psnr is None and logged_image is not None:
            logged_psnr = psnr(torch.from_numpy(rgb.astype(np.float32) / 255.0),
                               torch.from_numpy(logged_image().astype(np.float32) / 255.0))
        if keep and (not fresh or self._unedited_bytes + rgb.nbytes <= UNEDITED_CACHE_BYTES):
            self._unedited_bytes += rgb.nbytes if fresh else 0
            self._unedited[key] = (rgb, logged_psnr)
        return view, rgb, logged_psnr

    def logged_rects(self, camera: str, frame: int, boxes: Callable[[], pd.DataFrame]
                     ) -> dict[int, tuple[float, float, float, float]]:
        """{track id: image rectangle} of the logged boxes (``boxes()``: the frame's rows of the scene's box
        table) in the logged view of ``camera`` at ``frame``, boxes off the image left out; made once per view."""
        view = self.graph.view(camera, frame)
        key = (camera, view.frame_idx)
        if key not in self._logged_rects:
            rows = boxes()
            camera_from_world = invert_transform(view.world_from_camera)
            world_from_box = make_transform(quat_to_rotmat(rows[["qw", "qx", "qy", "qz"]].to_numpy(np.float64)),
                                            rows[["cx", "cy", "cz"]].to_numpy(np.float64))
            sizes = rows[["length", "width", "height"]].to_numpy(np.float64)
            rects = {}
            for tid, T, size in zip(rows.track_id.to_numpy(), world_from_box, sizes):
                rect = projected_box(camera_from_world @ T, size, view.K, view.width, view.height,
                                     self.graph.settings.near_plane)
                if rect is not None:
                    rects[int(tid)] = rect[0]
            self._logged_rects[key] = rects
        return self._logged_rects[key]

    def _may_show(self, view: View, node_poses: dict[int, np.ndarray]) -> list[int]:
        """The agent nodes present in the view's frame that may reach its image where ``node_poses`` (or the log)
        puts them; the others are not placed, coloured or projected at all."""
        f, near = view.frame_idx, self.graph.settings.near_plane
        out = []
        for a in self.graph.agents:
            if a.present[f]:
                T = node_poses.get(a.track_id, a.world_from_agent[f])
                if agent_may_show(view, np.asarray(T)[:3, 3], self.radii[a.track_id], near):
                    out.append(a.track_id)
        return out

    def _poses(self, node_poses: dict[int, np.ndarray], frame: int) -> dict[int, NodePose]:
        """The moved agent nodes present in ``frame`` as the renderer's node poses."""
        return {tid: NodePose(torch.from_numpy(rotmat_to_quat(T[:3, :3])), torch.from_numpy(T[:3, 3].copy()))
                for tid, T in node_poses.items() if tid in self.radii and self.graph.agent(tid).present[frame]}

    def _label(self, view: View, camera_from_world: np.ndarray, inst: Instance, visible: float,
               instance: np.ndarray, own: float) -> InstanceLabel | None:
        camera_from_box = camera_from_world @ inst.world_from_box
        rect = projected_box(camera_from_box, inst.size, view.K, view.width, view.height,
                             self.config.min_label_depth_m)
        if rect is None:
            return None
        box2d, in_image = rect
        mask = instance == inst.track_id
        n_mask = int(np.count_nonzero(mask))
        tight = None
        if n_mask >= self.config.min_mask_pixels:
            ys, xs = np.nonzero(mask)
            tight = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
        own = own if visible > 0.0 else 0.0
        fraction = 0.0 if own <= 0.0 else float(np.clip(in_image * min(visible / own, 1.0), 0.0, 1.0))
        return InstanceLabel(inst.track_id, n_mask, visible, own, in_image, fraction, box2d, tight, camera_from_box)

    def _alone(self, view: View, inst: Instance, node_poses: dict[int, np.ndarray]) -> tuple[Tensor, ...]:
        """The instance's activated Gaussians in the world: means, quats, scales, opacities."""
        if inst.members is not None:
            g, idx = self.background, inst.members
            return g.means[idx], g.quats[idx], g.scales[idx], g.opacities[idx]
        node = self.graph.agent(inst.track_id)
        placed = place_gaussians(self.local[inst.track_id],
                                 node_poses.get(inst.track_id, node.world_from_agent[view.frame_idx]))
        return placed.means, placed.quats, placed.scales, placed.opacities

    def _own_alphas(self, view: View, instances: list[Instance],
                    node_poses: dict[int, np.ndarray]) -> dict[int, float]:
        """Per instance, the sum of its alpha over the image when it is rendered alone (nothing in front of it).

        Instances whose projected boxes (padded by OWN_ALPHA_PAD) do not meet are rendered together, one label
        channel each. Where a pixel gets a share from one instance only, no other instance touched it, so the
        share is exactly that instance's alpha alone there; an instance that shares a pixel with another of its
        group (a Gaussian outside its box) is rendered again alone. Exact either way; fewer rasterisations."""
        if not instances:
            return {}
        parts = [self._alone(view, inst, node_poses) for inst in instances]
        camera_from_world = invert_transform(view.world_from_camera)
        rects = []
        for inst in instances:
            rect = projected_box(camera_from_world @ inst.world_from_box, inst.size, view.K, view.width, view.height,
                                 self.graph.settings.near_plane)
            if rect is not None:
                x1, y1, x2, y2 = rect[0]
                px, py = OWN_ALPHA_PAD[0] * (x2 - x1) + OWN_ALPHA_PAD[1], OWN_ALPHA_PAD[0] * (y2 - y1) + OWN_ALPHA_PAD[1]
                rect = (x1 - px, y1 - py, x2 + px, y2 + py)
            rects.append(rect)
        groups: list[list[int]] = []
        for e in sorted(range(len(instances)), key=lambda i: rects[i] is None):
            home = None
            if rects[e] is not None:
                home = next((g for g in groups if all(rects[o] is not None and not _meet(rects[e], rects[o])
                                                      for o in g)), None)
            if home is None:
                groups.append([e])
            else:
                home.append(e)
        own = {}
        for group in groups:
            shares = self._alpha_channels(view, [parts[e] for e in group])  # [H, W, len(group)] or None
            alone = []
            if shares is None:
                own.update({instances[e].track_id: 0.0 for e in group})
            elif len(group) == 1:
                own[instances[group[0]].track_id] = float(shares.sum(dtype=np.float64))
            else:
                planes = np.ascontiguousarray(np.moveaxis(shares, -1, 0)).reshape(len(group), -1)  # [G, H*W]
                touched = planes > 0.0
                multi = np.add.reduce(touched, axis=0, dtype=np.uint8) >= 2
                clash = set(np.nonzero(touched[:, multi].any(1))[0].tolist()) if multi.any() else set()
                sums = planes.sum(1, dtype=np.float64)
                for i, e in enumerate(group):
                    if i in clash:
                        alone.append(e)
                    else:
                        own[instances[e].track_id] = float(sums[i])
            for e in alone:
                single = self._alpha_channels(view, [parts[e]])
                own[instances[e].track_id] = 0.0 if single is None else float(single.sum(dtype=np.float64))
        return own

    def _alpha_channels(self, view: View, parts: list[tuple[Tensor, ...]]) -> np.ndarray | None:  # [H, W, E]
        """Rasterise the Gaussians of ``parts`` together, channel e one for part e's Gaussians and 0 elsewhere."""
        sizes = [len(p[0]) for p in parts]
        if sum(sizes) == 0:
            return None
        means, quats, scales, opacities = (torch.cat([p[i] for p in parts]) for i in range(4))
        on = dict(device=means.device, dtype=means.dtype)
        channels = torch.repeat_interleave(torch.eye(len(parts), **on), torch.tensor(sizes, device=means.device), 0)
        s = self.graph.settings
        viewmat = torch.from_numpy(invert_transform(view.world_from_camera)).to(**on)[None]
        K = torch.from_numpy(view.K).to(**on)[None]
        out, _, _ = rasterize(means, quats, scales, opacities, channels, viewmat, K, view.width, view.height,
                              near_plane=s.near_plane, far_plane=s.far_plane, eps2d=s.eps2d, render_mode="RGB",
                              backend=s.backend, rasterize_mode=s.rasterize_mode)
        return out[0].cpu().numpy()


def _meet(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def projected_box(camera_from_box: np.ndarray, size: np.ndarray, K: np.ndarray, width: int, height: int,
                  near: float) -> tuple[tuple[float, float, float, float], float] | None:
    """The image rectangle of a 3D box clipped to the image, and the fraction of its unclipped rectangle inside
    the image; the box's edges are first cut at the plane ``near`` in front of the camera, so a box beside or
    partly behind the camera still gets its true rectangle. None when no part of it is in front or it misses
    the image."""
    corners = box_corners_from_pose(camera_from_box, size)
    points = []
    for a, b in BOX_EDGES:
        seg = clip_segment_to_near(corners[a], corners[b], near)
        if seg is not None:
            points.extend(seg)
    if not points:
        return None
    p = np.asarray(points)
    uv = (p[:, :2] / p[:, 2:3]) @ K[:2, :2].T + K[:2, 2]
    x1, y1 = uv.min(0)
    x2, y2 = uv.max(0)
    cx1, cy1 = float(np.clip(x1, 0, width)), float(np.clip(y1, 0, height))
    cx2, cy2 = float(np.clip(x2, 0, width)), float(np.clip(y2, 0, height))
    area = (cx2 - cx1) * (cy2 - cy1)
    if not area > 0.0:
        return None
    full = max(float((x2 - x1) * (y2 - y1)), area)
    return (cx1, cy1, cx2, cy2), float(area / full) if np.isfinite(full) else 0.0
