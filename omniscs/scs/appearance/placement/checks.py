"""The placement checks (``omniscs.scs.appearance.placement``): the object being placed (``ObjectPoses``), box
geometry, the four checks (on the road, no overlap, visible, in range) and the verdict on a user-given placement."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform, wrap_angle
from omniscs.scs.appearance.placement.config import EGO_TRACK_ID, PlacementConfig, positive_size
from omniscs.scs.appearance.placement.context import PlacementContext

#: Touching boxes (gap within this many metres of the clearance) count as overlapping despite rounding.
TOUCH_TOLERANCE_M = 1e-9
#: Box corners of a unit box (±0.5 on each axis) [8, 3], front-left-top first, as ``omniscs.geometry.box_corners``.
_UNIT_CORNERS = np.array([[sx, sy, sz] for sx in (0.5, -0.5) for sy in (0.5, -0.5) for sz in (0.5, -0.5)])
#: Footprint test points of a unit rectangle [9, 2]: corners, edge midpoints, centre.
_FOOTPRINT_POINTS = np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5],
                              [0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5], [0.0, 0.0]])
# visibility stages: how far a (frame, camera) view of the object got before it failed
_BEHIND, _TOO_FAR, _OUT_OF_IMAGE, _OCCLUDED, _VISIBLE = range(5)


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
        size = positive_size(size)
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
        size = positive_size(size)
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


def camera_indices(context: PlacementContext, config: PlacementConfig) -> np.ndarray:  # [C'] int
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
    cams = camera_indices(context, config)
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
        eye = context.cameras.world_from_camera[frame][:, camera_indices(context, config), :2, 3]  # [N, C', 2]
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
