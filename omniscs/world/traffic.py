"""Traffic and sensor rig: turns a layout and a seed into a complete ``World`` (ego log, agents, cameras)."""
from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import ego_from_camera_mount, intrinsics_from_fov, pose_from_xyz_yaw
from omniscs.world.assets import asset_category, build_asset, list_asset_ids
from omniscs.world.layouts import TEMPLATES, Layout, Path, build_layout
from omniscs.world.model import FRAME_PERIOD_US, AgentTrack, CameraSpec, LidarSpec, World

log = logging.getLogger(__name__)

# Agents follow lane paths with curvature-limited speed profiles, park in kerbside slots, or stand still
# (cones, barriers, debris, construction plant). A candidate that would overlap the ego or an accepted
# agent in any frame is rejected, so logs are collision-free. Traffic does not depend on lighting, so
# the lighting variants of a (template, seed) are pixel-aligned re-renders of one scene.
#
# Large static object: ``straight_parked_truck`` always parks a box truck or container trailer in the
# kerbside slots 10-22 m ahead of the ego (up to 40 m when nearer placements collide; it hides the
# background behind it); every other
# template gets one with probability LARGE_OBJECT_CHANCE when it has a kerbside parking lane.

LIGHTINGS: tuple[str, ...] = ("day", "dusk", "night", "fog")

#: nuScenes-like camera placement in the ego frame (rear axle, x forward, y left, z up): name, x, y, z, yaw.
CAMERA_RIG: tuple[tuple[str, float, float, float, float], ...] = (
    ("CAM_FRONT", 1.70, 0.00, 1.51, 0.0),
    ("CAM_FRONT_LEFT", 1.52, 0.49, 1.51, np.radians(55.0)),
    ("CAM_FRONT_RIGHT", 1.52, -0.49, 1.51, np.radians(-55.0)),
    ("CAM_BACK_LEFT", 1.03, 0.48, 1.56, np.radians(110.0)),
    ("CAM_BACK_RIGHT", 1.03, -0.48, 1.56, np.radians(-110.0)),
    ("CAM_BACK", 0.03, 0.00, 1.57, np.pi),
)
CAMERA_HFOV_DEG = 70.0
MIN_IMAGE_SIDE = 8

EGO_LENGTH, EGO_WIDTH = 4.6, 1.9
EGO_CENTRE_AHEAD_OF_ORIGIN = 1.3  # the ego frame sits on the rear axle; its box centre is ahead of it
LATERAL_ACCEL = 2.5  # m/s^2 comfortable cornering limit that caps speed on curves
ACCEL, DECEL = 1.5, 3.0  # m/s^2
COLLISION_MARGIN = 0.6  # metres added to every footprint when checking overlaps
SPAWN_TRIES = 40
LARGE_OBJECT_CHANCE = 0.35
LARGE_OBJECT_AHEAD = (10.0, 22.0)  # world x range of the first kerbside slot the large object takes
LARGE_OBJECT_AHEAD_FALLBACK = (10.0, 40.0)  # tried last, when no placement in LARGE_OBJECT_AHEAD is free
KERB_NUDGE_STEP_M, KERB_NUDGE_MAX_M = 0.05, 0.3  # a required large object that fits nowhere moves towards the kerb
CONSTRUCTION_CHANCE = 0.3
DEBRIS_CHANCE = 0.35
PARKED_OCCUPANCY = (0.35, 0.7)  # range of the fraction of visible kerbside slots that are taken
PARKING_WINDOW = (-40.0, 170.0)  # world x range where parked cars are placed
NEAR_RANGE = (14.0, 75.0)  # metres from the ego's start for ordinary traffic
FAR_RANGE = (85.0, 190.0)  # small, distant agents

#: Kinds that drive, with how often they appear.
MOVING_KINDS = {"sedan": 40, "suv": 25, "van": 10, "pickup": 9, "box_truck": 8, "bus": 5}
PARKED_KINDS = {"sedan": 45, "suv": 25, "van": 15, "pickup": 10}


@dataclass
class _Candidate:
    asset_id: str
    poses: np.ndarray  # [F, 4, 4]
    present: np.ndarray  # [F] bool
    size: np.ndarray  # [3]


def camera_rig(n_cameras: int, width: int, height: int) -> tuple[CameraSpec, ...]:
    """The first ``n_cameras`` of the nuScenes-like rig, ~70° horizontal field of view each."""
    if not isinstance(n_cameras, (int, np.integer)) or not 1 <= n_cameras <= len(CAMERA_RIG):
        raise OmniscsError(f"n_cameras must be an integer from 1 to {len(CAMERA_RIG)}; got {n_cameras!r}")
    K = intrinsics_from_fov(width, height, np.radians(CAMERA_HFOV_DEG))
    return tuple(CameraSpec(name, int(width), int(height), K.copy(), ego_from_camera_mount(x, y, z, yaw))
                 for name, x, y, z, yaw in CAMERA_RIG[:n_cameras])


def drive_profile(path: Path, s0: float, v_desired: float, n_frames: int, dt: float) -> np.ndarray:
    """Arc length per frame [F] for a driver who wants ``v_desired`` m/s, slows for curves ahead and
    stops at the end of the path."""
    s, out = float(s0), np.empty(n_frames)
    v = v_desired
    for f in range(n_frames):
        out[f] = s
        look = np.linspace(s, s + max(6.0, 2.5 * v), 8)
        kappa = np.max(np.abs(path.curvature(look)))
        v_lim = min(v_desired, np.sqrt(LATERAL_ACCEL / max(kappa, 1e-6)))
        v_lim = min(v_lim, np.sqrt(2 * DECEL * max(path.length - s, 0.0)))
        v = float(np.clip(v_lim, v - DECEL * dt, v + ACCEL * dt))
        v = max(v, 0.0)
        s += v * dt
    return out


def _poses_on_path(path: Path, s: np.ndarray, z: float) -> np.ndarray:  # [F] -> [F, 4, 4]
    xy, yaw = path.at(s)
    return np.stack([pose_from_xyz_yaw(x, y, z, a) for (x, y), a in zip(xy, yaw)])


def _footprints(poses: np.ndarray, length: float, width: float,
                centre_offset: float = 0.0) -> np.ndarray:  # [F,4,4] -> [F, 4, 2] corners
    hx, hy = length / 2 + COLLISION_MARGIN / 2, width / 2 + COLLISION_MARGIN / 2
    local = np.array([[hx, hy], [hx, -hy], [-hx, -hy], [-hx, hy]]) + [centre_offset, 0.0]
    R = poses[:, :2, :2]
    return np.einsum("fij,kj->fki", R, local) + poses[:, None, :2, 3]


def _overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # [F,4,2] x [F,4,2] -> [F] bool (SAT)
    sep = np.zeros(len(a), dtype=bool)
    for poly in (a, b):
        for i in range(2):
            edge = poly[:, i + 1] - poly[:, i]
            axis = np.stack([-edge[:, 1], edge[:, 0]], -1)  # [F, 2]
            pa = np.einsum("fkj,fj->fk", a, axis)
            pb = np.einsum("fkj,fj->fk", b, axis)
            sep |= (pa.max(1) < pb.min(1)) | (pb.max(1) < pa.min(1))
    return ~sep


class _TrafficBuilder:
    """Spawns agents one by one and keeps only those that never overlap anything already accepted."""

    def __init__(self, layout: Layout, template: str, seed: int, n_frames: int) -> None:
        self.layout, self.template, self.n_frames = layout, template, n_frames
        self.rng = np.random.default_rng([zlib.crc32(b"traffic"), zlib.crc32(template.encode()), int(seed)])
        self.dt = FRAME_PERIOD_US * 1e-6
        self.accepted: list[_Candidate] = []
        self.footprints: list[tuple[np.ndarray, np.ndarray]] = []  # (corners [F,4,2], present [F])
        self.used_assets: set[str] = set()
        self.used_slots: set[int] = set()

    # -- ego ------------------------------------------------------------------------------------
    def ego(self) -> np.ndarray:  # -> [F, 4, 4]
        path = self.layout.route_path(self.layout.ego_route)
        self.ego_speed = float(self.rng.uniform(7.0, 11.0))
        s = drive_profile(path, self.layout.ego_start_s, self.ego_speed, self.n_frames, self.dt)
        poses = _poses_on_path(path, s, 0.0)
        if not np.allclose(poses[0], np.eye(4), atol=1e-9):
            raise OmniscsError("internal: the layout's world frame does not start at the ego pose")
        poses[0] = np.eye(4)
        self.ego_poses = poses
        self.ego_path, self.ego_s = path, s
        self.footprints.append((_footprints(poses, EGO_LENGTH, EGO_WIDTH, EGO_CENTRE_AHEAD_OF_ORIGIN),
                                np.ones(self.n_frames, dtype=bool)))
        return poses

    # -- candidates ----------------------------------------------------------------------------
    def pick_asset(self, kinds: dict[str, int]) -> str:
        names = list(kinds)
        w = np.array([kinds[k] for k in names], dtype=np.float64)
        for _ in range(SPAWN_TRIES):
            kind = names[int(self.rng.choice(len(names), p=w / w.sum()))]
            ids = list_asset_ids(kind)
            aid = ids[int(self.rng.integers(0, len(ids)))]
            if aid not in self.used_assets:
                return aid
        return aid

    def try_accept(self, cand: _Candidate) -> bool:
        corners = _footprints(cand.poses, cand.size[0], cand.size[1])
        for other, present in self.footprints:
            both = cand.present & present
            if np.any(_overlap(corners, other) & both):
                return False
        self.accepted.append(cand)
        self.footprints.append((corners, cand.present))
        self.used_assets.add(cand.asset_id)
        return True

    def static(self, asset_id: str, x: float, y: float, yaw: float) -> _Candidate:
        size = build_asset(asset_id).size
        pose = pose_from_xyz_yaw(x, y, size[2] / 2, yaw)
        return _Candidate(asset_id, np.repeat(pose[None], self.n_frames, 0), np.ones(self.n_frames, bool), size)

    def random_route(self, first: str) -> list[str]:
        route = [first]
        while self.layout.lanes[route[-1]].successors and len(route) < 8:
            nxt = self.layout.lanes[route[-1]].successors
            route.append(nxt[int(self.rng.integers(0, len(nxt)))])
        return route

    def moving(self, distance_range: tuple[float, float], kinds: dict[str, int] = MOVING_KINDS,
               first_lanes: list[str] | None = None) -> bool:
        """A lane follower that starts within ``distance_range`` of the ego's start, on one of
        ``first_lanes`` (default: any road lane)."""
        lanes = first_lanes or [lid for lid, lane in self.layout.lanes.items() if lane.kind == "lane"]
        for _ in range(SPAWN_TRIES):
            route = self.random_route(lanes[int(self.rng.integers(0, len(lanes)))])
            path = self.layout.route_path(route)
            s_grid = np.arange(0.0, path.length, 2.0)
            xy, _ = path.at(s_grid)
            d = np.linalg.norm(xy, axis=1)
            ok = np.flatnonzero((d >= distance_range[0]) & (d <= distance_range[1]))
            if not len(ok):
                continue
            s0 = float(s_grid[ok[int(self.rng.integers(0, len(ok)))]])
            aid = self.pick_asset(kinds)
            size = build_asset(aid).size
            # Followers of the ego's own lanes keep about its pace; others drive their own speed.
            same_route = route[0] in self.layout.ego_route
            v = self.ego_speed * self.rng.uniform(0.95, 1.2) if same_route else self.rng.uniform(6.0, 13.0)
            if asset_category(aid) in ("bus", "truck"):
                v *= 0.85
            s = drive_profile(path, s0, v, self.n_frames, self.dt)
            present = s < path.length - 0.5
            if not present[0]:
                continue
            cand = _Candidate(aid, _poses_on_path(path, s, size[2] / 2), present, size)
            if self.try_accept(cand):
                return True
        return False

    def parked(self) -> None:
        slots = [(i, sl) for i, sl in enumerate(self.layout.parking_slots)
                 if PARKING_WINDOW[0] <= sl.x <= PARKING_WINDOW[1] and i not in self.used_slots]
        occupancy = self.rng.uniform(*PARKED_OCCUPANCY)
        for i, sl in slots:
            if self.rng.uniform() > occupancy:
                continue
            aid = self.pick_asset(PARKED_KINDS)
            jitter = self.rng.uniform(-1, 1, 3) * [0.4, 0.12, 0.04]
            cand = self.static(aid, sl.x + jitter[0], sl.y + jitter[1], sl.yaw + jitter[2])
            if self.try_accept(cand):
                self.used_slots.add(i)

    def slot_runs(self, length: float, x_range: tuple[float, float], side: int) -> list[list[int]]:
        """Every run of consecutive free kerbside slots on ``side`` that holds ``length`` metres and starts in
        x_range, in a seeded random order."""
        slots = self.layout.parking_slots
        idx = [i for i, sl in enumerate(slots) if sl.side == side]
        starts = [j for j, i in enumerate(idx) if x_range[0] <= slots[i].x <= x_range[1]]
        self.rng.shuffle(starts)
        need = int(np.ceil(length / 6.5))
        runs = []
        for j in starts:
            run = idx[j:j + need]
            if len(run) < need or any(r in self.used_slots for r in run):
                continue
            if abs(slots[run[-1]].x - slots[run[0]].x) > 6.5 * (need - 1) + 1e-6:
                continue  # the run is broken by a junction
            runs.append(run)
        return runs

    def large_static_object(self, required: bool) -> bool:
        if not required and self.rng.uniform() > LARGE_OBJECT_CHANCE:
            return False
        kinds = {"box_truck": 1, "trailer": 1}
        first = self.pick_asset(kinds)
        # The drawn asset first; if no kerbside run takes it (every placement collides), the other kind,
        # drawn only then so that worlds which never need it keep their random stream.
        tried = []
        for attempt in range(3):
            aid = first if attempt == 0 else self.pick_asset({k: 1 for k in kinds if not first.startswith(k)})
            tried.append(aid)
            x_range = LARGE_OBJECT_AHEAD if attempt < 2 else LARGE_OBJECT_AHEAD_FALLBACK
            if self._park_large(aid, x_range, 0.0):
                return True
        if required:
            # Last resort, reached only where the placements above all collide (so every world that had its object
            # before is unchanged): in a layout whose kerbside lane lies close to the ego's lane, the object hugs
            # the kerb, moved outwards in steps until it clears the collision margin.
            for nudge in np.arange(KERB_NUDGE_STEP_M, KERB_NUDGE_MAX_M + 1e-9, KERB_NUDGE_STEP_M):
                for aid in tried:
                    if self._park_large(aid, LARGE_OBJECT_AHEAD_FALLBACK, float(nudge)):
                        return True
            raise OmniscsError(f"internal: no kerbside room for the large static object in {self.template!r}")
        return False

    def _park_large(self, aid: str, x_range: tuple[float, float], nudge: float) -> bool:
        """``aid`` parked over a free kerbside run starting in ``x_range`` (either side), ``nudge`` metres
        further from the lanes than the slots' centre line; True once one placement is accepted."""
        size = build_asset(aid).size
        for side in (-1, 1):
            for run in self.slot_runs(size[0], x_range, side):
                slots = [self.layout.parking_slots[i] for i in run]
                x = 0.5 * (slots[0].x + slots[-1].x)
                cand = self.static(aid, x, slots[0].y + side * nudge, slots[0].yaw)
                if self.try_accept(cand):
                    # Keep the slot on the ego's side of it free, so nothing parked hides the object itself.
                    near_end = min(run, key=lambda i: abs(self.layout.parking_slots[i].x))
                    self.used_slots.update(run + [near_end - 1, near_end + 1])
                    return True
        return False

    def construction_zone(self) -> None:
        if self.rng.uniform() > CONSTRUCTION_CHANCE:
            return
        side = int(self.rng.choice([-1, 1]))
        plant = self.pick_asset({"excavator": 1, "wheel_loader": 1})
        size = build_asset(plant).size
        runs = self.slot_runs(size[0] + 4.0, (40.0, 90.0), side)
        run = runs[0] if runs else None
        if run is None:
            return
        slots = [self.layout.parking_slots[i] for i in run]
        x0, x1 = min(s.x for s in slots) - 3.0, max(s.x for s in slots) + 3.0
        y = slots[0].y
        if not self.try_accept(self.static(plant, 0.5 * (x0 + x1), y, slots[0].yaw + self.rng.uniform(-0.3, 0.3))):
            return
        self.used_slots.update(run)
        road_side = y - side * 1.5  # cones along the lane edge, between the works and the traffic
        for x in np.arange(x0, x1 + 0.1, 3.0):
            self.try_accept(self.static(self.pick_asset({"traffic_cone": 1}), x, road_side, 0.0))
        self.try_accept(self.static(self.pick_asset({"barrier": 1}), x0 - 1.5, y, np.pi / 2))

    def debris(self) -> None:
        if self.rng.uniform() > DEBRIS_CHANCE:
            return
        lanes = [lane for lane in self.layout.lanes.values() if lane.kind == "lane"]
        for _ in range(SPAWN_TRIES):
            lane = lanes[int(self.rng.integers(0, len(lanes)))]
            path = lane.path
            s = self.rng.uniform(0, path.length)
            (xy,), (yaw,) = path.at(np.array([s]))
            if not 20.0 <= np.linalg.norm(xy) <= 80.0:
                continue
            lateral = self.rng.uniform(-0.8, 0.8)
            xy = xy + lateral * np.array([-np.sin(yaw), np.cos(yaw)])
            if self.try_accept(self.static(self.pick_asset({"debris": 1}), xy[0], xy[1], self.rng.uniform(-np.pi, np.pi))):
                return

    def agents(self) -> list[AgentTrack]:
        required = self.template == "straight_parked_truck"
        self.large_static_object(required)
        self.construction_zone()
        self.parked()
        n_near = int(self.rng.integers(5, 10))
        for _ in range(n_near):
            self.moving(NEAR_RANGE)
        for _ in range(int(self.rng.integers(1, 4))):
            self.moving(FAR_RANGE)
        # Junctions get traffic entering from the side roads and from ahead, which crosses or turns.
        crossing = [lid for lid in self.layout.lanes if lid.startswith(("north_in", "south_in", "east_in"))]
        if crossing:
            for _ in range(int(self.rng.integers(2, 5))):
                self.moving(NEAR_RANGE, first_lanes=crossing)
        self.debris()
        return [AgentTrack(track_id=i + 1, category=asset_category(c.asset_id), asset_id=c.asset_id,
                           size=np.asarray(c.size, dtype=np.float64).copy(), poses=c.poses, present=c.present)
                for i, c in enumerate(self.accepted)]


def generate_world(template: str, seed: int, n_frames: int = 40, n_cameras: int = 3, width: int = 480,
                   height: int = 270, lighting: str = "day") -> World:
    """A complete procedural log: ego on its lane at 10 Hz, traffic, parked and static objects, camera
    rig and LiDAR. Deterministic in (template, seed); lighting changes only how it is rendered.

    template: one of TEMPLATES (``straight_parked_truck`` always has a large parked truck or container
    ahead-right of the ego; the others get one by chance). lighting: one of LIGHTINGS. n_cameras: 1..6
    of CAMERA_RIG in order (3 = front, front-left, front-right).
    """
    if template not in TEMPLATES:
        raise OmniscsError(f"unknown template {template!r}; use one of {list(TEMPLATES)}")
    if lighting not in LIGHTINGS:
        raise OmniscsError(f"unknown lighting {lighting!r}; use one of {list(LIGHTINGS)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise OmniscsError(f"seed must be a non-negative integer; got {seed!r}")
    if not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise OmniscsError(f"n_frames must be a positive integer; got {n_frames!r}")
    if not all(isinstance(v, (int, np.integer)) and v >= MIN_IMAGE_SIDE for v in (width, height)):
        raise OmniscsError(f"image width and height must be integers >= {MIN_IMAGE_SIDE}; got {width}x{height}")
    cameras = camera_rig(n_cameras, width, height)
    layout = build_layout(template, int(seed))
    builder = _TrafficBuilder(layout, template, int(seed), int(n_frames))
    ego_poses = builder.ego()
    agents = builder.agents()
    log.debug("world %s seed %d: %d agents", template, seed, len(agents))
    return World(template=template, seed=int(seed), lighting=lighting, n_frames=int(n_frames), ego_poses=ego_poses,
                 cameras=cameras, lidar=LidarSpec(), agents=tuple(agents))
