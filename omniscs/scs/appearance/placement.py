"""Where an inserted object may go: the checks a placement (x, y, yaw of the object's box, world frame) must pass,
and a sampler that draws N valid placements for 1-to-N generation.

A placement must keep its footprint on the drivable area (``on_road``), stay clear of every logged agent, static
object and the ego at every frame both exist (``no_overlap``), be seen by the chosen camera in enough frames
(``visible``) and lie at the requested distance from it (``in_range``). All checks are geometry on boxes (numpy),
not renders: they are cheap enough to run on thousands of proposals. The object is static (one pose in every
frame) or follows given per-frame poses (e.g. it replaces a logged agent and inherits its motion).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform, wrap_angle, yaw_from_matrix

#: track_id of the ego vehicle's box in ``Obstacles``.
EGO_TRACK_ID = -1
#: Height of the ego's box, metres: scene stores record only its footprint (``EgoBox`` in
#: ``omniscs.scs.behavior.tracks``); this is the value the closed-loop simulator reports for it.
EGO_HEIGHT_M = 1.6
#: Names of the checks, in the order they are reported.
CHECKS = ("on_road", "no_overlap", "visible", "in_range")
#: Rejections of proposals that passed every check but overlapped a placement accepted before them.
OVERLAPS_ACCEPTED = "overlaps_accepted"
YAW_MODES = ("lane", "uniform", "fixed")
#: Proposals drawn per batch by the sampler (part of what a seed reproduces: changing it changes the draws).
PROPOSAL_BATCH = 64
#: Touching boxes (gap within this many metres of the clearance) count as overlapping despite rounding.
TOUCH_TOLERANCE_M = 1e-9

#: Box corners of a unit box (±0.5 on each axis) [8, 3], front-left-top first, as ``omniscs.geometry.box_corners``.
_UNIT_CORNERS = np.array([[sx, sy, sz] for sx in (0.5, -0.5) for sy in (0.5, -0.5) for sz in (0.5, -0.5)])
#: Footprint test points of a unit rectangle [9, 2]: corners, edge midpoints, centre.
_FOOTPRINT_POINTS = np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5],
                              [0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5], [0.0, 0.0]])

# visibility stages: how far a (frame, camera) view of the object got before it failed
_BEHIND, _TOO_FAR, _OUT_OF_IMAGE, _OCCLUDED, _VISIBLE = range(5)


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class PlacementConfig:
    """What makes a placement valid and how the sampler proposes placements (world frame, metres, radians)."""

    distance_m: tuple[float, float] = (8.0, 30.0)
    """[min, max] horizontal distance from the camera (``in_range``; the sampler draws uniformly in it)."""
    min_visible_frames: int = 3
    """``visible``: the object must be in view in at least this many frames (k)."""
    min_in_image_fraction: float = 0.5
    """``visible``: share of the projected box's bounding rectangle that must lie inside the image."""
    clearance_m: float = 0.3
    """``no_overlap``: boxes closer than this (along some separating axis, or in height) count as overlapping."""
    road_margin_m: float = 0.0
    """``on_road``: the footprint grown by this much on every side must stay on the drivable area."""
    max_proposals: int = 2000
    """The sampler gives up after this many proposals."""
    max_distance_m: float = 60.0
    """``visible``: a box centre further than this from the camera (3D) does not count as visible."""
    near_plane_m: float = 0.5
    """``visible``: every box corner must lie at least this far in front of the camera (along its z)."""
    yaw_mode: str = "uniform"
    """Sampler: 'uniform' (yaw uniform in [-pi, pi)), 'fixed' (``yaw``) or 'lane' (the nearest lane's direction
    + ``yaw`` ± up to ``lane_yaw_jitter``; uniform where no lane is near)."""
    yaw: float = 0.0
    """'fixed': the world yaw of every placement; 'lane': an offset added to the lane direction (pi: against
    traffic, pi/2: across the lane)."""
    lane_yaw_jitter: float = math.radians(10.0)
    """'lane': the largest random offset from the lane direction, radians."""
    camera: str | None = None
    """Camera the object must be visible in and proposals are drawn in front of; None: any camera."""

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.distance_m)
        numbers = {f.name: getattr(self, f.name) for f in fields(self)
                   if f.name not in ("distance_m", "yaw_mode", "camera")}
        bad = [k for k, v in numbers.items() if not np.isfinite(v)] + (
            ["distance_m"] if not (np.isfinite(lo) and np.isfinite(hi)) else [])
        if bad:
            raise OmniscsError(f"placement config: {', '.join(bad)} must be finite numbers")
        if not 0.0 <= lo <= hi:
            raise OmniscsError(f"placement distance [{lo}, {hi}] m: need 0 <= min <= max")
        if self.min_visible_frames < 0 or not 0.0 <= self.min_in_image_fraction <= 1.0:
            raise OmniscsError("placement config: min_visible_frames must be >= 0 and min_in_image_fraction in [0, 1]")
        if self.clearance_m < 0 or self.road_margin_m < 0 or self.lane_yaw_jitter < 0:
            raise OmniscsError("placement config: clearance_m, road_margin_m and lane_yaw_jitter must be >= 0")
        if self.max_proposals < 1 or self.max_distance_m <= 0 or self.near_plane_m <= 0:
            raise OmniscsError("placement config: max_proposals must be >= 1, max_distance_m and near_plane_m > 0")
        if self.yaw_mode not in YAW_MODES:
            raise OmniscsError(f"placement yaw mode {self.yaw_mode!r} is unknown; use one of {', '.join(YAW_MODES)}")


# ----------------------------------------------------------------------------- what the checks read
@dataclass(frozen=True)
class Obstacles:
    """Every box a placed object must keep clear of, per frame (world frame): logged agents, static objects and
    the ego (track_id ``EGO_TRACK_ID``)."""

    frame_idx: np.ndarray  # [M] int64
    track_id: np.ndarray   # [M] int64, EGO_TRACK_ID for the ego
    centre: np.ndarray     # [M, 3] box centres
    size: np.ndarray       # [M, 3] length, width, height
    yaw: np.ndarray        # [M]

    def __post_init__(self) -> None:
        m = len(self.frame_idx)
        shapes = (self.track_id.shape == (m,), self.centre.shape == (m, 3), self.size.shape == (m, 3),
                  self.yaw.shape == (m,))
        if not all(shapes):
            raise OmniscsError(f"obstacles: arrays disagree in shape (frame_idx [{m}], track_id "
                               f"{list(self.track_id.shape)}, centre {list(self.centre.shape)}, size "
                               f"{list(self.size.shape)}, yaw {list(self.yaw.shape)})")
        if not (np.isfinite(self.centre).all() and np.isfinite(self.size).all() and np.isfinite(self.yaw).all()):
            raise OmniscsError("obstacles: a box has a NaN or infinite centre, size or yaw; repair the log's boxes")

    @classmethod
    def from_arrays(cls, frame_idx, track_id, centre, size, yaw) -> Obstacles:
        return cls(frame_idx=np.asarray(frame_idx, dtype=np.int64).reshape(-1),
                   track_id=np.asarray(track_id, dtype=np.int64).reshape(-1),
                   centre=np.asarray(centre, dtype=np.float64).reshape(-1, 3),
                   size=np.asarray(size, dtype=np.float64).reshape(-1, 3),
                   yaw=np.asarray(yaw, dtype=np.float64).reshape(-1))

    @classmethod
    def from_scene(cls, scene, ego_size: tuple[float, float, float] | None = None,
                   ego_centre_ahead_m: float | None = None, exclude=()) -> Obstacles:
        """The boxes of a scene store (``scene.boxes``) plus the ego's at every frame. The ego's box defaults to
        the behaviour model's (``EgoBox``: length, width, centre ahead of the ego origin) with height
        ``EGO_HEIGHT_M``; its centre lies ``ego_centre_ahead_m`` ahead of the ego origin along the heading, at the
        origin's height + h/2 (the ego frame's origin is on the ground). ``exclude``: track ids left out (e.g.
        the agent the object replaces; ``EGO_TRACK_ID`` leaves out the ego)."""
        if ego_size is None or ego_centre_ahead_m is None:
            from omniscs.scs.behavior.tracks import EgoBox  # the behaviour package loads torch: only when needed

            box = EgoBox()
            ego_size = (box.length, box.width, EGO_HEIGHT_M) if ego_size is None else ego_size
            ego_centre_ahead_m = box.centre_ahead_m if ego_centre_ahead_m is None else ego_centre_ahead_m
        ego_size = _positive_size(ego_size, "ego size")
        if not np.isfinite(ego_centre_ahead_m):
            raise OmniscsError(f"ego_centre_ahead_m {ego_centre_ahead_m} must be a finite number of metres")
        world_from_ego = np.asarray(scene.world_from_ego_all, dtype=np.float64).reshape(-1, 4, 4)
        n_frames = len(world_from_ego)
        ego_yaw = yaw_from_matrix(world_from_ego[:, :3, :3])
        ego_centre = world_from_ego[:, :3, 3].copy()
        ego_centre[:, 0] += ego_centre_ahead_m * np.cos(ego_yaw)
        ego_centre[:, 1] += ego_centre_ahead_m * np.sin(ego_yaw)
        ego_centre[:, 2] += ego_size[2] / 2
        excluded = {int(t) for t in exclude}
        b = scene.boxes
        b = b[~b.track_id.isin(excluded)] if len(b) else b
        frame_idx, track_id = [b.frame_idx.to_numpy(np.int64)], [b.track_id.to_numpy(np.int64)]
        centre = [b[["cx", "cy", "cz"]].to_numpy(np.float64)]
        size = [b[["length", "width", "height"]].to_numpy(np.float64)]
        yaw = [b.yaw.to_numpy(np.float64)]
        if EGO_TRACK_ID not in excluded:
            frame_idx.append(np.arange(n_frames))
            track_id.append(np.full(n_frames, EGO_TRACK_ID))
            centre.append(ego_centre)
            size.append(np.tile(ego_size, (n_frames, 1)))
            yaw.append(ego_yaw)
        return cls.from_arrays(*(np.concatenate(parts) for parts in (frame_idx, track_id, centre, size, yaw)))

    def __len__(self) -> int:
        return len(self.frame_idx)

    def without(self, track_ids) -> Obstacles:
        """These obstacles less the boxes of ``track_ids`` (e.g. the agent an object replaces)."""
        keep = ~np.isin(self.track_id, np.asarray(list(track_ids), dtype=np.int64))
        return Obstacles(self.frame_idx[keep], self.track_id[keep], self.centre[keep], self.size[keep], self.yaw[keep])


@dataclass(frozen=True)
class Cameras:
    """The log's cameras at every frame (OpenCV: x right, y down, z forward)."""

    names: tuple[str, ...]          # [C]
    world_from_camera: np.ndarray   # [F, C, 4, 4]
    K: np.ndarray                   # [C, 3, 3]
    width: np.ndarray               # [C] int, pixels
    height: np.ndarray              # [C] int, pixels

    def __post_init__(self) -> None:
        c = len(self.names)
        if (self.world_from_camera.ndim != 4 or self.world_from_camera.shape[1:] != (c, 4, 4)
                or self.K.shape != (c, 3, 3) or self.width.shape != (c,) or self.height.shape != (c,)):
            raise OmniscsError(f"cameras: {c} names but world_from_camera {list(self.world_from_camera.shape)}, "
                               f"K {list(self.K.shape)}, width {list(self.width.shape)}, "
                               f"height {list(self.height.shape)}")
        if c == 0 or self.world_from_camera.shape[0] == 0:
            raise OmniscsError("cameras: the log has no cameras or no frames; a placement needs both")
        if not (np.isfinite(self.world_from_camera).all() and np.isfinite(self.K).all()):
            raise OmniscsError("cameras: a camera pose or intrinsic matrix is not finite; repair the log")

    @classmethod
    def from_scene(cls, scene) -> Cameras:
        names = tuple(scene.camera_names)
        world_from_camera = np.stack([np.stack([scene.world_from_camera(c, f) for c in names])
                                      for f in range(scene.n_frames)]) if names else np.zeros((scene.n_frames, 0, 4, 4))
        sizes = [scene.image_size(c) for c in names]
        return cls(names=names, world_from_camera=np.asarray(world_from_camera, dtype=np.float64),
                   K=np.asarray([scene.intrinsics(c) for c in names], dtype=np.float64).reshape(-1, 3, 3),
                   width=np.array([s[0] for s in sizes], dtype=np.int64),
                   height=np.array([s[1] for s in sizes], dtype=np.int64))

    @property
    def n_frames(self) -> int:
        return self.world_from_camera.shape[0]

    def index_of(self, name: str) -> int:
        if name not in self.names:
            raise OmniscsError(f"unknown camera {name!r}; the log has {', '.join(self.names)}")
        return self.names.index(name)

    def hfov(self) -> np.ndarray:  # [C] radians
        """Horizontal field of view of each camera (pinhole, principal point anywhere)."""
        fx, cx = self.K[:, 0, 0], self.K[:, 0, 2]
        return np.arctan2(cx, fx) + np.arctan2(self.width - cx, fx)


class GroundHeight:
    """Road-surface height near points: inverse-distance weighting (power 2) of the ground samples within
    ``radius_m`` (at most ``neighbours`` of them), else the nearest sample's height. Samples are the bottoms
    (cz - h/2) of logged boxes and the ego origins (the ego frame's origin is on the ground), merged per cell of
    ``cell_m`` so a parked car seen in 200 frames counts once."""

    def __init__(self, points: np.ndarray,  # [K, 3] world ground samples
                 radius_m: float = 15.0, neighbours: int = 8, cell_m: float = 0.5) -> None:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        if not len(points):
            raise OmniscsError("no ground samples (no boxes and no ego poses): cannot tell the road's height")
        _, cell, counts = np.unique(np.floor(points[:, :2] / cell_m).astype(np.int64), axis=0, return_inverse=True,
                                    return_counts=True)
        cell = cell.reshape(-1)
        self.points = np.stack([np.bincount(cell, points[:, k]) / counts for k in range(3)], -1)  # [K', 3]
        self.radius_m, self.neighbours = float(radius_m), int(neighbours)
        self._tree = cKDTree(self.points[:, :2])

    @classmethod
    def from_obstacles(cls, obstacles: Obstacles, radius_m: float = 15.0) -> GroundHeight:
        """Box bottoms of every obstacle; the ego's box bottom is its origin's height."""
        return cls(np.concatenate([obstacles.centre[:, :2], obstacles.centre[:, 2:] - obstacles.size[:, 2:] / 2], 1),
                   radius_m=radius_m)

    def __call__(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] world -> [N] metres
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        k = min(self.neighbours, len(self.points))
        dist, idx = self._tree.query(xy, k=k)
        dist, idx = dist.reshape(len(xy), k), idx.reshape(len(xy), k)
        z = self.points[idx, 2]
        w = np.where(dist <= self.radius_m, 1.0 / np.maximum(dist, 1e-3) ** 2, 0.0)
        near = w.sum(1) > 0
        return np.where(near, (w * z).sum(1) / np.where(near, w.sum(1), 1.0), z[:, 0])


class LaneDirection:
    """Direction of travel of the lane nearest each point, from a scene map's centreline raster (cells of the
    ``centreline`` layer and their ``lane_dir_cos``/``lane_dir_sin``, see ``MAP_LAYERS``); accurate to one map
    cell. Points further than ``max_distance_m`` from every centreline cell have no lane."""

    def __init__(self, cells_xy: np.ndarray,  # [L, 2] world centres of centreline cells
                 yaw: np.ndarray,             # [L] lane direction there
                 max_distance_m: float = 5.0) -> None:
        self.cells_xy = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
        self.yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
        self.max_distance_m = float(max_distance_m)
        self._tree = cKDTree(self.cells_xy) if len(self.cells_xy) else None

    @classmethod
    def from_scene_map(cls, scene_map, max_distance_m: float = 5.0) -> LaneDirection:
        """From an ``omniscs.scs.behavior.maps.SceneMap`` (read through its numpy layers only)."""
        layers = np.asarray(scene_map.layers)
        rows, cols = np.nonzero(layers[1] > 0.5)
        res = float(scene_map.resolution)
        xy = np.asarray(scene_map.origin, dtype=np.float64) + (np.stack([cols, rows], -1) + 0.5) * res
        return cls(xy, np.arctan2(layers[3, rows, cols], layers[2, rows, cols]), max_distance_m)

    def __call__(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # [N, 2] -> yaw [N], found [N] bool
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self._tree is None:
            return np.zeros(len(xy)), np.zeros(len(xy), dtype=bool)
        dist, idx = self._tree.query(xy)
        found = dist <= self.max_distance_m
        return np.where(found, self.yaw[np.minimum(idx, len(self.yaw) - 1)], 0.0), found


@dataclass(frozen=True)
class PlacementContext:
    """Everything the checks read about one log."""

    obstacles: Obstacles
    cameras: Cameras
    drivable: Callable[[np.ndarray], np.ndarray]
    """xy [N, 2] world -> [N] bool: whether each point is on the drivable area."""
    ground_z: Callable[[np.ndarray], np.ndarray]
    """xy [N, 2] world -> [N]: road-surface height there, metres."""
    lane_direction: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    """xy [N, 2] -> (yaw [N], found [N] bool): the nearest lane's direction; None: yaw_mode 'lane' is unavailable."""

    def __post_init__(self) -> None:
        if len(self.obstacles) and (self.obstacles.frame_idx.min() < 0
                                    or self.obstacles.frame_idx.max() >= self.n_frames):
            raise OmniscsError(f"obstacles have frames outside 0..{self.n_frames - 1}, the frames the cameras have")

    @property
    def n_frames(self) -> int:
        return self.cameras.n_frames


def placement_context(scene, exclude=(), ground_radius_m: float = 15.0, lane_search_m: float = 5.0
                      ) -> PlacementContext:
    """The placement context of a scene store: its obstacles (``exclude``: track ids left out, e.g. the agent
    being replaced), cameras, drivable area and lanes (the behaviour model's scene map: the log's road map when
    it has one, else derived from where vehicles drove) and ground height (from every box and ego pose, the
    excluded ones included)."""
    from omniscs.scs.behavior.tracks import traffic_from_scene  # the behaviour package loads torch

    scene_map = traffic_from_scene(scene).map
    everything = Obstacles.from_scene(scene)
    obstacles = Obstacles.from_scene(scene, exclude=exclude) if len(exclude) else everything
    return PlacementContext(obstacles=obstacles, cameras=Cameras.from_scene(scene), drivable=scene_map.is_drivable,
                            ground_z=GroundHeight.from_obstacles(everything, ground_radius_m),
                            lane_direction=LaneDirection.from_scene_map(scene_map, lane_search_m))


# ----------------------------------------------------------------------------- the object being placed
@dataclass(frozen=True)
class ObjectPoses:
    """N candidate placements of one object over the log's F frames (N = 1 for a single user pose)."""

    size: np.ndarray     # [3] length, width, height of the object's box (of the possibly tilted model)
    centre: np.ndarray   # [N, F, 3] world box centres
    yaw: np.ndarray      # [N, F]
    present: np.ndarray  # [N, F] bool: frames the object exists in
    static: bool         # the same pose in every frame

    @property
    def n(self) -> int:
        return self.centre.shape[0]

    @classmethod
    def at(cls, context: PlacementContext, size, placements) -> ObjectPoses:
        """Static placements [N, 3] (x, y, yaw; the box stands on ``ground_z``) or [N, 4] (x, y, z of the box
        centre, yaw), present in every frame."""
        size = _positive_size(size)
        p = _finite_poses(placements, "placement").reshape(-1, np.shape(placements)[-1])
        z = _box_centre_z(context, p, size)
        f = context.n_frames
        centre = np.repeat(np.stack([p[:, 0], p[:, 1], z], -1)[:, None], f, axis=1)
        return cls(size=size, centre=centre, yaw=np.repeat(wrap_angle(p[:, -1])[:, None], f, axis=1),
                   present=np.ones((len(p), f), dtype=bool), static=True)

    @classmethod
    def moving(cls, context: PlacementContext, size, poses, frames=None) -> ObjectPoses:
        """One object following per-frame poses [T, 3] (x, y, yaw) or [T, 4] (x, y, z, yaw) at ``frames`` [T]
        (default: every frame of the log, T = F); absent in the other frames."""
        size = _positive_size(size)
        p = _finite_poses(poses, "pose")
        if p.ndim != 2:
            raise OmniscsError(f"per-frame poses must be [T, 3] or [T, 4], got shape {list(p.shape)}")
        f = context.n_frames
        frames = np.arange(len(p)) if frames is None else np.asarray(frames, dtype=np.int64).reshape(-1)
        if len(frames) != len(p) or (len(frames) and (frames.min() < 0 or frames.max() >= f)):
            raise OmniscsError(f"{len(p)} per-frame poses need as many frames within 0..{f - 1} "
                               "(pass frames= when they do not start at frame 0)")
        if len(np.unique(frames)) != len(frames):
            raise OmniscsError("per-frame poses: a frame is given twice")
        centre, yaw = np.zeros((1, f, 3)), np.zeros((1, f))
        present = np.zeros((1, f), dtype=bool)
        centre[0, frames] = np.stack([p[:, 0], p[:, 1], _box_centre_z(context, p, size)], -1)
        yaw[0, frames] = wrap_angle(p[:, -1])
        present[0, frames] = True
        return cls(size=size, centre=centre, yaw=yaw, present=present, static=False)


def _positive_size(size, what: str = "object size") -> np.ndarray:
    s = np.asarray(size, dtype=np.float64).reshape(-1)
    if s.shape != (3,) or not np.isfinite(s).all() or (s <= 0).any():
        raise OmniscsError(f"{what} {np.asarray(size).tolist()} must be three finite positive numbers "
                           "(length, width, height in metres)")
    return s


def _finite_poses(poses, what: str) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim == 0 or p.shape[-1] not in (3, 4) or p.size == 0:
        raise OmniscsError(f"a {what} is (x, y, yaw) or (x, y, z, yaw); got shape {list(p.shape)}")
    if not np.isfinite(p).all():
        rows = p.reshape(-1, p.shape[-1])
        shown = rows[int(np.argmin(np.isfinite(rows).all(1)))]  # the first bad one
        raise OmniscsError(f"{what} {np.round(shown, 3).tolist()} has a NaN or infinite value; give finite metres "
                           "and radians")
    return p


def _box_centre_z(context: PlacementContext, p: np.ndarray, size: np.ndarray) -> np.ndarray:  # [N, 3|4] -> [N]
    if p.shape[-1] == 4:
        return p[:, 2]
    ground = np.asarray(context.ground_z(p[:, :2]), dtype=np.float64).reshape(-1)
    if not np.isfinite(ground).all():
        raise OmniscsError("the ground height is unknown (not finite) at the placement; give the box centre's z")
    return ground + size[2] / 2


# ----------------------------------------------------------------------------- geometry
def boxes_overlap(centre_a: np.ndarray,  # [..., 3]
                  size_a: np.ndarray,    # [..., 3] length, width, height
                  yaw_a: np.ndarray,     # [...]
                  centre_b: np.ndarray,  # [..., 3] (broadcast against a)
                  size_b: np.ndarray,    # [..., 3]
                  yaw_b: np.ndarray,     # [...]
                  clearance: float = 0.0) -> np.ndarray:  # [...] bool
    """Whether two yawed 3D boxes come closer than ``clearance``: the separating-axis test on their x-y
    rectangles (the four edge normals) plus their z-intervals. Touching counts as overlapping. With a clearance
    it is conservative: two rectangles clear of each other only diagonally (corner to corner) may be reported
    as overlapping; it never misses a real overlap."""
    d = np.asarray(centre_b, dtype=np.float64) - np.asarray(centre_a, dtype=np.float64)
    size_a, size_b = np.asarray(size_a, dtype=np.float64), np.asarray(size_b, dtype=np.float64)
    ca, sa, cb, sb = np.cos(yaw_a), np.sin(yaw_a), np.cos(yaw_b), np.sin(yaw_b)
    axes_a, axes_b = ((ca, sa), (-sa, ca)), ((cb, sb), (-sb, cb))
    ha, hb = size_a / 2, size_b / 2
    limit = clearance + TOUCH_TOLERANCE_M
    separated = np.abs(d[..., 2]) - ha[..., 2] - hb[..., 2] > limit
    for ux, uy in (*axes_a, *axes_b):
        ra = ha[..., 0] * np.abs(axes_a[0][0] * ux + axes_a[0][1] * uy) + ha[..., 1] * np.abs(
            axes_a[1][0] * ux + axes_a[1][1] * uy)
        rb = hb[..., 0] * np.abs(axes_b[0][0] * ux + axes_b[0][1] * uy) + hb[..., 1] * np.abs(
            axes_b[1][0] * ux + axes_b[1][1] * uy)
        separated = separated | (np.abs(d[..., 0] * ux + d[..., 1] * uy) - ra - rb > limit)
    return ~separated


def segment_hits_box(start: np.ndarray,   # [..., 3] world
                     end: np.ndarray,     # [..., 3]
                     centre: np.ndarray,  # [..., 3] box centre (broadcast)
                     size: np.ndarray,    # [..., 3]
                     yaw: np.ndarray,     # [...]
                     ) -> np.ndarray:     # [...] bool
    """Whether the segment start -> end passes through a yawed box (slab test in the box's frame; a segment
    grazing a face may count either way)."""
    c, s = np.cos(yaw), np.sin(yaw)
    q0 = np.asarray(start, dtype=np.float64) - centre
    q1 = np.asarray(end, dtype=np.float64) - centre
    half = np.asarray(size, dtype=np.float64) / 2
    local0 = (c * q0[..., 0] + s * q0[..., 1], -s * q0[..., 0] + c * q0[..., 1], q0[..., 2])
    local1 = (c * q1[..., 0] + s * q1[..., 1], -s * q1[..., 0] + c * q1[..., 1], q1[..., 2])
    t_in, t_out = 0.0, 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            # a segment parallel to a slab gets +-inf here (never inside the slab: an empty interval); NaN only
            # exactly on a face, which fmin/fmax ignore
            inv = 1.0 / (local1[k] - local0[k])
            t1, t2 = (-half[..., k] - local0[k]) * inv, (half[..., k] - local0[k]) * inv
            t_in = np.fmax(t_in, np.fmin(t1, t2))
            t_out = np.fmin(t_out, np.fmax(t1, t2))
    return t_in <= t_out


def _footprints(xy: np.ndarray, yaw: np.ndarray, length: float, width: float) -> np.ndarray:
    """Footprint test points [..., 9, 2] (corners, edge midpoints, centre) of rectangles at xy [..., 2]."""
    local = _FOOTPRINT_POINTS * np.array([length, width])
    c, s = np.cos(yaw)[..., None], np.sin(yaw)[..., None]
    return np.stack([xy[..., None, 0] + c * local[:, 0] - s * local[:, 1],
                     xy[..., None, 1] + s * local[:, 0] + c * local[:, 1]], -1)


def _rot_z(yaw: np.ndarray) -> np.ndarray:  # [...] -> [..., 3, 3]
    c, s = np.cos(yaw), np.sin(yaw)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)], -2)


def _camera_indices(context: PlacementContext, config: PlacementConfig) -> np.ndarray:  # [C'] int
    if config.camera is None:
        return np.arange(len(context.cameras.names))
    return np.array([context.cameras.index_of(config.camera)])


# ----------------------------------------------------------------------------- checks
def on_road_frames(context: PlacementContext, objects: ObjectPoses, config: PlacementConfig = PlacementConfig()
                   ) -> np.ndarray:  # [N, F] bool (True where absent)
    """Per frame: the footprint's corners, edge midpoints and centre (the footprint grown by ``road_margin_m``)
    all lie on the drivable area."""
    length, width = objects.size[:2] + 2 * config.road_margin_m
    if objects.static:
        pts = _footprints(objects.centre[:, 0, :2], objects.yaw[:, 0], length, width)  # [N, 9, 2]
        ok = np.asarray(context.drivable(pts.reshape(-1, 2)), dtype=bool).reshape(objects.n, -1).all(1)
        return np.repeat(ok[:, None], objects.present.shape[1], axis=1)
    out = np.ones(objects.present.shape, dtype=bool)
    n, f = np.nonzero(objects.present)
    pts = _footprints(objects.centre[n, f, :2], objects.yaw[n, f], length, width)
    out[n, f] = np.asarray(context.drivable(pts.reshape(-1, 2)), dtype=bool).reshape(len(n), -1).all(1)
    return out


def on_road(context: PlacementContext, objects: ObjectPoses, config: PlacementConfig = PlacementConfig()
            ) -> np.ndarray:  # [N] bool
    """The object's footprint stays on the drivable area (``road_margin_m`` inside its edge) in every frame."""
    return on_road_frames(context, objects, config).all(1)


def overlap_pairs(context: PlacementContext, objects: ObjectPoses, config: PlacementConfig = PlacementConfig()
                  ) -> np.ndarray:  # [N, M] bool: placement n overlaps obstacle box m (at m's frame)
    """Each obstacle box (one track at one frame) against the object's pose at that frame, with
    ``clearance_m``; False where the object is absent at that frame."""
    obs = context.obstacles
    if not len(obs):
        return np.zeros((objects.n, 0), dtype=bool)
    f = obs.frame_idx
    # bounding circles first: only pairs that close get the separating-axis test
    reach = np.hypot(*objects.size[:2]) / 2 + np.hypot(obs.size[:, 0], obs.size[:, 1]) / 2 + config.clearance_m
    gap = np.linalg.norm(objects.centre[:, f, :2] - obs.centre[None, :, :2], axis=-1)  # [N, M]
    n, m = np.nonzero((gap <= reach + TOUCH_TOLERANCE_M) & objects.present[:, f])
    hit = np.zeros(gap.shape, dtype=bool)
    hit[n, m] = boxes_overlap(objects.centre[n, f[m]], objects.size, objects.yaw[n, f[m]], obs.centre[m],
                              obs.size[m], obs.yaw[m], config.clearance_m)
    return hit


def no_overlap(context: PlacementContext, objects: ObjectPoses, config: PlacementConfig = PlacementConfig()
               ) -> np.ndarray:  # [N] bool
    """No 3D overlap (within ``clearance_m``) with any logged agent or static object at any frame where both
    exist (a static object exists in every frame), nor with the ego at any frame: the ego follows its logged
    path, so an object the ego drives through is an invalid placement (the edited log would show a collision
    that never happened)."""
    return ~overlap_pairs(context, objects, config).any(1)


@dataclass(frozen=True)
class Visibility:
    """How far each (placement, frame, camera) view got: stage [N, F, C'] (0 behind the near plane, 1 beyond
    ``max_distance_m``, 2 not enough inside the image, 3 occluded, 4 visible) and the occluding track
    [N, F, C'] (meaningful where stage == 3), for cameras ``cameras`` [C'] (indices)."""

    stage: np.ndarray     # [N, F, C'] int8
    occluder: np.ndarray  # [N, F, C'] int64
    cameras: np.ndarray   # [C'] int
    present: np.ndarray   # [N, F] bool

    def frames(self) -> np.ndarray:  # [N, F] bool
        return (self.stage == _VISIBLE).any(-1) & self.present


def visibility(context: PlacementContext, objects: ObjectPoses, config: PlacementConfig = PlacementConfig()
               ) -> Visibility:
    """Per frame and camera (the chosen one, or every camera): all 8 box corners in front of the near plane,
    the box centre within ``max_distance_m``, at least ``min_in_image_fraction`` of the projected corners'
    bounding rectangle inside the image, and the sight line from the camera to the box centre through no other
    obstacle's box (the ego, which carries the cameras, excepted). A geometric check, not a render: it ignores
    partial occlusion away from the sight line and occlusion by the static background."""
    cams = _camera_indices(context, config)
    n, f_count = objects.present.shape
    stage = np.zeros((n, f_count, len(cams)), dtype=np.int8)
    occluder = np.full((n, f_count, len(cams)), EGO_TRACK_ID, dtype=np.int64)
    obs = context.obstacles
    # obstacles that can hide the object (the ego carries the cameras), grouped by frame: frame f's are
    # blockers[bounds[f]:bounds[f + 1]]
    blockers = np.flatnonzero(obs.track_id != EGO_TRACK_ID)
    blockers = blockers[np.argsort(obs.frame_idx[blockers], kind="stable")]
    bounds = np.searchsorted(obs.frame_idx[blockers], np.arange(f_count + 1))
    corners_local = _UNIT_CORNERS * objects.size  # [8, 3]

    def _corners(centre, yaw):  # [R, 3], [R] -> [R, 8, 3] world
        return centre[:, None] + np.matmul(_rot_z(yaw)[:, None], corners_local[None, :, :, None])[..., 0]

    static_corners = _corners(objects.centre[:, 0], objects.yaw[:, 0]) if objects.static else None
    K = context.cameras.K[cams]  # [C', 3, 3]
    width, height = context.cameras.width[cams].astype(np.float64), context.cameras.height[cams].astype(np.float64)
    for f in range(f_count):
        rows = np.flatnonzero(objects.present[:, f])
        if not len(rows):
            continue
        centre = objects.centre[rows, f]  # [R, 3]
        corners = static_corners[rows] if objects.static else _corners(centre, objects.yaw[rows, f])
        world_from_camera = context.cameras.world_from_camera[f, cams]  # [C', 4, 4]
        camera_from_world = invert_transform(world_from_camera)
        pc = (np.matmul(corners.reshape(1, -1, 3), np.swapaxes(camera_from_world[:, :3, :3], 1, 2))
              + camera_from_world[:, None, :3, 3]).reshape(len(cams), len(rows), 8, 3)  # [C', R, 8, 3]
        in_front = (pc[..., 2] > config.near_plane_m).all(-1)  # [C', R]
        eye = world_from_camera[:, :3, 3]  # [C', 3]
        near_enough = np.linalg.norm(centre[None] - eye[:, None], axis=-1) <= config.max_distance_m
        z = np.where(in_front[..., None], pc[..., 2], 1.0)
        u = K[:, None, None, 0, 0] * pc[..., 0] / z + K[:, None, None, 0, 2]
        v = K[:, None, None, 1, 1] * pc[..., 1] / z + K[:, None, None, 1, 2]
        u0, u1, v0, v1 = u.min(-1), u.max(-1), v.min(-1), v.max(-1)  # [C', R]
        area = (u1 - u0) * (v1 - v0)
        inside = (np.clip(np.minimum(u1, width[:, None]) - np.maximum(u0, 0.0), 0.0, None)
                  * np.clip(np.minimum(v1, height[:, None]) - np.maximum(v0, 0.0), 0.0, None))
        fraction = np.where(area > 1e-12, inside / np.where(area > 1e-12, area, 1.0), 0.0)
        in_image = fraction >= config.min_in_image_fraction
        here = blockers[bounds[f]:bounds[f + 1]]
        occluded = np.zeros_like(in_front)
        ci, ri = np.nonzero(in_front & near_enough & in_image)  # only views that got this far can be occluded
        if len(here) and len(ci):
            hits = segment_hits_box(eye[ci, None], centre[ri, None], obs.centre[here], obs.size[here],
                                    obs.yaw[here])  # [P, M_f]
            occluded[ci, ri] = hits.any(-1)
            occluder[rows[ri], f, ci] = obs.track_id[here][np.argmax(hits, -1)]
        st = np.where(~in_front, _BEHIND, np.where(~near_enough, _TOO_FAR, np.where(
            ~in_image, _OUT_OF_IMAGE, np.where(occluded, _OCCLUDED, _VISIBLE))))
        stage[rows, f] = st.T
    return Visibility(stage=stage, occluder=occluder, cameras=cams, present=objects.present)


def visible(context: PlacementContext, objects: ObjectPoses, config: PlacementConfig = PlacementConfig()
            ) -> np.ndarray:  # [N] bool
    """In view of the chosen camera (or any camera) in at least ``min_visible_frames`` frames (see
    ``visibility``: geometry, not a render)."""
    return visibility(context, objects, config).frames().sum(1) >= config.min_visible_frames


def camera_distances(context: PlacementContext, objects: ObjectPoses, frame: np.ndarray,  # [N] int
                     camera: np.ndarray | None = None,  # [N] int camera index; None: the nearest allowed camera
                     config: PlacementConfig = PlacementConfig()) -> np.ndarray:  # [N] metres (inf where absent)
    """Horizontal (x-y) distance from the camera to the box centre at ``frame``."""
    frame = np.asarray(frame, dtype=np.int64).reshape(-1)
    rows = np.arange(objects.n)
    xy = objects.centre[rows, frame, :2]  # [N, 2]
    if camera is None:
        eye = context.cameras.world_from_camera[frame][:, _camera_indices(context, config), :2, 3]  # [N, C', 2]
        d = np.linalg.norm(eye - xy[:, None], axis=-1).min(1)
    else:
        eye = context.cameras.world_from_camera[frame, np.asarray(camera, dtype=np.int64).reshape(-1), :2, 3]
        d = np.linalg.norm(eye - xy, axis=-1)
    return np.where(objects.present[rows, frame], d, np.inf)


def in_range(context: PlacementContext, objects: ObjectPoses, frame: np.ndarray,  # [N] int
             camera: np.ndarray | None = None,  # [N] int; None: the nearest of the allowed cameras
             config: PlacementConfig = PlacementConfig()) -> np.ndarray:  # [N] bool
    """The horizontal distance from the camera at the proposing frame lies in ``distance_m``."""
    d = camera_distances(context, objects, frame, camera, config)
    lo, hi = config.distance_m
    return (d >= lo) & (d <= hi)


# ----------------------------------------------------------------------------- user-given placements
@dataclass(frozen=True)
class PlacementCheck:
    """Which checks a user-given placement passed, and one line for each it failed."""

    pose: str
    """The placement as people read it, e.g. "(12.0, 3.5, yaw 90°)"."""
    passed: dict[str, bool]
    """Check name -> passed (``in_range`` only when a frame was given)."""
    failures: tuple[str, ...]
    """One line per failed check, e.g. "overlaps track 4 at frames 3-9"."""

    @property
    def ok(self) -> bool:
        return all(self.passed.values())

    def message(self) -> str:
        return f"placement {self.pose} " + "; ".join(self.failures)

    def to_dict(self) -> dict:
        return {"pose": self.pose, "ok": self.ok, "passed": {k: bool(v) for k, v in self.passed.items()},
                "failures": list(self.failures)}


def check_placement(context: PlacementContext, size, pose, config: PlacementConfig = PlacementConfig(),
                    frame: int | None = None, frames=None) -> PlacementCheck:
    """Run every check on one user-given placement: ``pose`` is (x, y, yaw) or (x, y, z, yaw) for a static
    object, or per-frame poses [T, 3|4] at ``frames`` (default 0..T-1). ``in_range`` runs only when ``frame``
    (the frame the distance is measured at) is given. Failures are described, never raised: see
    ``require_valid``."""
    p = np.asarray(pose, dtype=np.float64)
    static = p.ndim == 1
    objects = (ObjectPoses.at(context, size, p[None]) if static
               else ObjectPoses.moving(context, size, p, frames))
    failures, passed = [], {}

    road = on_road_frames(context, objects, config)[0]
    passed["on_road"] = bool(road.all())
    if not passed["on_road"]:
        where = "" if static else f" at frames {_frame_ranges(np.flatnonzero(~road))}"
        margin = f" (with a {config.road_margin_m:.1f} m margin)" if config.road_margin_m > 0 else ""
        failures.append(f"leaves the drivable area{margin}{where}: its {objects.size[0]:.1f} x "
                        f"{objects.size[1]:.1f} m footprint must lie on the road")

    pairs = overlap_pairs(context, objects, config)[0]
    passed["no_overlap"] = not pairs.any()
    if not passed["no_overlap"]:
        obs = context.obstacles
        hit_ids = obs.track_id[pairs]
        parts = []
        for tid in sorted(set(hit_ids.tolist()), key=lambda t: (t != EGO_TRACK_ID, t)):
            who = "the ego's path" if tid == EGO_TRACK_ID else f"track {tid}"
            parts.append(f"{who} at frames {_frame_ranges(obs.frame_idx[pairs][hit_ids == tid])}")
        more = f" and {len(parts) - 3} more tracks" if len(parts) > 3 else ""
        failures.append(f"overlaps {', '.join(parts[:3])}{more} (clearance {config.clearance_m:.1f} m)")

    vis = visibility(context, objects, config)
    n_visible = int(vis.frames()[0].sum())
    passed["visible"] = n_visible >= config.min_visible_frames
    if not passed["visible"]:
        failures.append(_visibility_failure(vis, n_visible, config))

    if frame is not None:
        if not 0 <= int(frame) < context.n_frames:
            raise OmniscsError(f"frame {frame} is out of range; the log has frames 0..{context.n_frames - 1}")
        cam = None if config.camera is None else np.array([context.cameras.index_of(config.camera)])
        d = float(camera_distances(context, objects, np.array([frame]), cam, config)[0])
        lo, hi = config.distance_m
        passed["in_range"] = lo <= d <= hi
        if not passed["in_range"]:
            where = "absent" if not np.isfinite(d) else f"{d:.1f} m from {config.camera or 'the nearest camera'}"
            failures.append(f"is {where} at frame {int(frame)}, outside the requested {lo:.1f}-{hi:.1f} m")
    return PlacementCheck(pose=_describe_pose(p), passed=passed, failures=tuple(failures))


def require_valid(context: PlacementContext, size, pose, config: PlacementConfig = PlacementConfig(),
                  frame: int | None = None, frames=None) -> PlacementCheck:
    """``check_placement``, raising OmniscsError (one line naming each failed check) when any check fails."""
    result = check_placement(context, size, pose, config, frame, frames)
    if not result.ok:
        raise OmniscsError(result.message() + "; choose another pose or let the sampler pick one (--sample)")
    return result


def _visibility_failure(vis: Visibility, n_visible: int, config: PlacementConfig) -> str:
    best = vis.stage[0].max(-1)  # [F]: how far the best camera got in each frame
    best_cam = vis.stage[0].argmax(-1)
    reasons = []
    for code, text in ((_BEHIND, "behind the camera or nearer than its near plane"),
                       (_TOO_FAR, f"beyond {config.max_distance_m:.0f} m"),
                       (_OUT_OF_IMAGE, f"less than {config.min_in_image_fraction:.0%} inside the image")):
        frames = np.flatnonzero((best == code) & vis.present[0])
        if len(frames):
            reasons.append(f"{text} at frames {_frame_ranges(frames)}")
    hidden = np.flatnonzero((best == _OCCLUDED) & vis.present[0])
    if len(hidden):
        ids = sorted(set(vis.occluder[0, hidden, best_cam[hidden]].tolist()))
        reasons.append(f"hidden behind track {', '.join(map(str, ids))} at frames {_frame_ranges(hidden)}")
    camera = config.camera or "any camera"
    return (f"is visible in {n_visible} of {int(vis.present[0].sum())} frames of {camera} (needs "
            f"{config.min_visible_frames}): {'; '.join(reasons) or 'never in view'}")


def _describe_pose(p: np.ndarray) -> str:
    if p.ndim == 1:
        z = f", z {p[2]:.1f}" if len(p) == 4 else ""
        return f"({p[0]:.1f}, {p[1]:.1f}{z}, yaw {math.degrees(p[-1]):.0f}°)"
    return (f"(a {len(p)}-frame path from ({p[0, 0]:.1f}, {p[0, 1]:.1f}) to ({p[-1, 0]:.1f}, {p[-1, 1]:.1f}))")


def _frame_ranges(frames, limit: int = 4) -> str:
    """Sorted frames as ranges, e.g. "3-9, 12"."""
    frames = sorted({int(f) for f in np.asarray(frames).reshape(-1)})
    runs = []
    for f in frames:
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    text = [f"{a}-{b}" if b > a else f"{a}" for a, b in runs[:limit]]
    return ", ".join(text) + (", ..." if len(runs) > limit else "")


# ----------------------------------------------------------------------------- sampling
@dataclass(frozen=True)
class PlacementResult:
    """What the sampler found: accepted static placements and how the proposals fared."""

    placements: np.ndarray  # [K, 4] x, y, z (box centre), yaw; world
    frames: np.ndarray      # [K] int: the frame each was proposed at
    cameras: tuple[str, ...]  # [K] the camera each was proposed in
    size: np.ndarray        # [3] the object's length, width, height
    n_requested: int
    n_proposals: int
    rejected: dict[str, int] = field(default_factory=dict)
    """Check name (``CHECKS`` + ``OVERLAPS_ACCEPTED``) -> proposals it rejected (a proposal may fail several)."""

    @property
    def n_accepted(self) -> int:
        return len(self.placements)

    @property
    def acceptance(self) -> float:
        """Share of proposals accepted."""
        return self.n_accepted / self.n_proposals if self.n_proposals else 0.0

    def rejection_share(self) -> dict[str, float]:
        """Check name -> share of the proposals it rejected."""
        return {k: v / self.n_proposals if self.n_proposals else 0.0 for k, v in self.rejected.items()}

    def to_dict(self) -> dict:
        return {"placements": [[float(v) for v in p] for p in self.placements],
                "frames": [int(f) for f in self.frames], "cameras": list(self.cameras),
                "size": [float(v) for v in self.size], "n_requested": int(self.n_requested),
                "n_accepted": int(self.n_accepted), "n_proposals": int(self.n_proposals),
                "rejected": {k: int(v) for k, v in self.rejected.items()},
                "rejection_share": {k: float(v) for k, v in self.rejection_share().items()},
                "acceptance": float(self.acceptance)}


class PlacementError(OmniscsError):
    """The sampler found fewer valid placements than asked for; ``result`` holds what it found."""

    def __init__(self, message: str, result: PlacementResult) -> None:
        super().__init__(message)
        self.result = result


def sample_placements(context: PlacementContext, size, n: int, config: PlacementConfig = PlacementConfig(),
                      rng_seed: int = 0) -> PlacementResult:
    """Draw ``n`` valid static placements. Each proposal: a random frame and camera (``config.camera`` when
    set), a bearing uniform in the camera's horizontal field of view, a horizontal distance uniform in
    ``distance_m``, the box standing on ``ground_z``, a yaw by ``yaw_mode``. Every proposal goes through every
    check (rejections counted per check); one that passes them all is accepted unless it overlaps a placement
    accepted before it. Stops at ``n`` accepted or ``max_proposals``; raises ``PlacementError`` (an
    OmniscsError) naming the check that rejected most when fewer than ``n`` were found. Deterministic in
    ``rng_seed``."""
    size = _positive_size(size)
    if int(n) != n or n < 1:
        raise OmniscsError(f"asked for {n} placements; ask for at least 1")
    if config.yaw_mode == "lane" and context.lane_direction is None:
        raise OmniscsError("yaw mode 'lane' needs lane directions, and this context has none; use 'uniform' or "
                           "'fixed'")
    cams = _camera_indices(context, config)
    hfov = context.cameras.hfov()
    rng = np.random.default_rng(rng_seed)
    lo, hi = config.distance_m
    accepted, accepted_frames, accepted_cams = [], [], []
    rejected = {name: 0 for name in (*CHECKS, OVERLAPS_ACCEPTED)}
    n_proposals = 0
    road = {"centred": 0, "fitted": 0}  # proposals whose centre was on the road, and that passed on_road
    while len(accepted) < n and n_proposals < config.max_proposals:
        b = min(PROPOSAL_BATCH, config.max_proposals - n_proposals)
        # every draw happens in every batch whatever the mode, so a seed means the same proposals
        frame = rng.integers(0, context.n_frames, b)
        cam = cams[rng.integers(0, len(cams), b)]
        bearing = (rng.random(b) - 0.5) * hfov[cam]
        distance = lo + (hi - lo) * rng.random(b)
        uniform_yaw = rng.uniform(-np.pi, np.pi, b)
        jitter = rng.uniform(-1.0, 1.0, b) * config.lane_yaw_jitter

        world_from_camera = context.cameras.world_from_camera[frame, cam]  # [b, 4, 4]
        forward = world_from_camera[:, :2, 2]
        heading = np.arctan2(forward[:, 1], forward[:, 0]) + bearing
        xy = world_from_camera[:, :2, 3] + distance[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
        yaw = _proposal_yaw(context, config, xy, uniform_yaw, jitter)
        objects = ObjectPoses.at(context, size, np.concatenate([xy, yaw[:, None]], 1))
        centred = np.asarray(context.drivable(xy), dtype=bool).reshape(-1)
        ok = {"on_road": on_road(context, objects, config), "no_overlap": no_overlap(context, objects, config),
              "visible": visible(context, objects, config),
              "in_range": in_range(context, objects, frame, cam, config)}
        for i in range(b):
            n_proposals += 1
            road["centred"] += int(centred[i])
            road["fitted"] += int(ok["on_road"][i])
            failed = [name for name in CHECKS if not ok[name][i]]
            for name in failed:
                rejected[name] += 1
            if not failed:
                candidate = np.array([*objects.centre[i, 0], objects.yaw[i, 0]])
                if accepted and boxes_overlap(np.asarray(accepted)[:, :3], size, np.asarray(accepted)[:, 3],
                                              candidate[:3], size, candidate[3], config.clearance_m).any():
                    rejected[OVERLAPS_ACCEPTED] += 1
                else:
                    accepted.append(candidate)
                    accepted_frames.append(int(frame[i]))
                    accepted_cams.append(context.cameras.names[cam[i]])
            if len(accepted) == n:
                break
    result = PlacementResult(placements=np.asarray(accepted, dtype=np.float64).reshape(-1, 4),
                             frames=np.asarray(accepted_frames, dtype=np.int64), cameras=tuple(accepted_cams),
                             size=size, n_requested=int(n), n_proposals=n_proposals, rejected=rejected)
    if result.n_accepted < n:
        raise PlacementError(_shortfall_message(result, config, road, context.n_frames), result)
    return result


def _proposal_yaw(context: PlacementContext, config: PlacementConfig, xy: np.ndarray, uniform_yaw: np.ndarray,
                  jitter: np.ndarray) -> np.ndarray:  # [b]
    if config.yaw_mode == "fixed":
        return np.full(len(xy), wrap_angle(config.yaw))
    if config.yaw_mode == "uniform":
        return uniform_yaw
    lane_yaw, found = context.lane_direction(xy)
    return np.where(found, wrap_angle(np.asarray(lane_yaw, dtype=np.float64) + config.yaw + jitter), uniform_yaw)


def _shortfall_message(result: PlacementResult, config: PlacementConfig, road: dict[str, int], n_frames: int
                       ) -> str:
    worst = max((*CHECKS, OVERLAPS_ACCEPTED), key=lambda k: result.rejected[k])  # first of equals: CHECKS order
    k, total = result.rejected[worst], result.n_proposals
    length, width, _ = result.size
    lo, hi = config.distance_m
    counts = ", ".join(f"{name} {v}" for name, v in result.rejected.items() if v)
    advice = {
        "on_road": _road_advice(k, total, road, length, width, lo, hi, config),
        "no_overlap": (f"{k} of {total} proposals overlapped logged traffic or the ego's path; use a smaller "
                       f"object, a smaller clearance (now {config.clearance_m:.1f} m) or other distances"),
        "visible": (f"{k} of {total} proposals were visible in fewer than {config.min_visible_frames} frames of "
                    f"{config.camera or 'any camera'}; " + (
                        f"the log has only {n_frames} frames: lower min_visible_frames"
                        if config.min_visible_frames > n_frames else
                        f"bring --distance (now {lo:.0f}-{hi:.0f} m) within {config.max_distance_m:.0f} m, choose "
                        "another camera or lower min_visible_frames")),
        "in_range": (f"{k} of {total} proposals were outside {lo:.0f}-{hi:.0f} m of the camera; check "
                     f"--distance"),
        OVERLAPS_ACCEPTED: (f"{k} of {total} proposals overlapped objects placed before them; ask for fewer "
                            f"objects or widen --distance"),
    }[worst]
    return (f"found {result.n_accepted} of {result.n_requested} placements in {total} proposals "
            f"(rejected by {counts}): {advice}")


def _road_advice(k: int, total: int, road: dict[str, int], length: float, width: float, lo: float, hi: float,
                 config: PlacementConfig) -> str:
    if road["centred"] == 0:
        seen = f"{config.camera} sees no road" if config.camera else "no camera sees road"
        return (f"none of the {total} proposals landed on the drivable area: {seen} at {lo:.0f}-{hi:.0f} m (beyond "
                "the map?); choose other distances (--distance) or another camera")
    if road["fitted"] == 0:
        return (f"an object {length:.1f} m long and {width:.1f} m wide does not fit on this road: {k} of {total} "
                f"proposals left the drivable area (none of the {road['centred']} centred on it fit); use a smaller "
                f"object or widen --distance (now {lo:.0f}-{hi:.0f} m)")
    return (f"{k} of {total} proposals left the drivable area; use a smaller object, a smaller road margin (now "
            f"{config.road_margin_m:.1f} m) or other distances (--distance, now {lo:.0f}-{hi:.0f} m)")
