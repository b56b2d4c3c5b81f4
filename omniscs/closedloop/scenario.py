"""What a closed-loop run replays: the log of a scene, or a behaviour-SCS variant of it. The ego's reference
trajectory (the log's, or the variant's plan) gives the route, the start state and the progress to compare with; the
other agents follow their trajectories in time (optionally yielding to the ego: ``omniscs.closedloop.traffic``)."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import wrap_angle
from omniscs.taxonomy import VEHICLE_CATEGORIES

#: Categories that are vulnerable road users (they move but are not vehicles in the metrics' sense).
VRU_CATEGORIES = frozenset({"pedestrian", "bicycle", "motorcycle"})
#: Agents that never moved more than this (metres) over the scenario count as static objects in the metrics.
STATIC_M = 0.5
#: Shortest route a scenario has (metres; see ``ClosedLoopScenario.route``).
MIN_ROUTE_M = 1.0


@dataclass(frozen=True)
class ClosedLoopScenario:
    """One scenario on steps of ``dt`` seconds (world frame; box centres)."""

    scenario_id: str          # "<scene id>/log" or "<scene id>/<variant id>"
    scene_id: str
    kind: str                 # "log" | "behavior"
    dt: float
    timestamps_us: np.ndarray  # [S] int64
    scene_frames: np.ndarray   # [S] int: the scene frame each step shows (agent nodes' exposure, logged boxes)
    ego: np.ndarray            # [S, 3] x, y, yaw of the reference ego box centre
    ego_z: np.ndarray          # [S] height of the ego frame origin
    ego_length: float
    ego_width: float
    ego_centre_ahead_m: float  # the box centre lies this far ahead of the ego frame origin (rear axle)
    track_ids: np.ndarray      # [N] int64
    categories: tuple[str, ...]
    sizes: np.ndarray          # [N, 3] length, width, height
    agents: np.ndarray         # [N, S, 3] x, y, yaw (NaN where absent)
    agents_z: np.ndarray       # [N, S] box centre height (NaN where absent)
    drivable: object | None = None  # ``is_drivable(xy [K, 2]) -> bool [K]`` (world), or None
    adversary: int | None = None

    def __post_init__(self):
        S, N = len(self.ego), len(self.track_ids)
        if S < 2:
            raise ValidationError(f"scenario {self.scenario_id}: needs at least 2 steps (has {S})")
        if self.agents.shape != (N, S, 3) or self.sizes.shape != (N, 3) or self.agents_z.shape != (N, S):
            raise ValidationError(f"scenario {self.scenario_id}: agents must be [N, {S}, 3], sizes [N, 3]")
        if not (np.isfinite(self.ego).all() and np.isfinite(self.ego_z).all() and self.dt > 0):
            raise ValidationError(f"scenario {self.scenario_id}: the reference ego needs a finite pose at every step")

    @property
    def n_steps(self) -> int:
        return len(self.ego)

    @property
    def duration_s(self) -> float:
        return (self.n_steps - 1) * self.dt

    @functools.cached_property
    def kinds(self) -> tuple[str, ...]:
        """Each agent as the metrics see it: "vehicle", "vru" or "static" (a parked car counts as static); worked
        out once per scenario (every simulator step reads it)."""
        out = []
        for i, c in enumerate(self.categories):
            xy = self.agents[i, :, :2]
            xy = xy[np.isfinite(xy).all(-1)]
            moved = float(np.max(np.linalg.norm(xy - xy[0], axis=1))) if len(xy) else 0.0
            if moved < STATIC_M:
                out.append("static")
            elif c in VRU_CATEGORIES:
                out.append("vru")
            else:
                out.append("vehicle" if c in VEHICLE_CATEGORIES else "static")
        return tuple(out)

    @property
    def route(self) -> np.ndarray:  # -> [R, 2] the path the ego should follow (world)
        """The reference ego's path; a reference that never moves (under ``MIN_ROUTE_M``) gets a route of that
        length straight ahead of it, so route completion stays defined (and low for an ego that stays)."""
        xy = self.ego[:, :2]
        if float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))) >= MIN_ROUTE_M:
            return xy
        yaw = float(self.ego[0, 2])
        return np.stack([xy[0], xy[0] + MIN_ROUTE_M * np.array([np.cos(yaw), np.sin(yaw)])])

    def ego_at(self, t: float) -> np.ndarray:  # -> [3] reference ego box centre at time t (s), clamped
        return interpolate_pose(self.ego, t / self.dt)

    def agents_at(self, t: float) -> np.ndarray:  # -> [N, 3] (NaN where absent), time clamped to the scenario
        return interpolate_pose(self.agents, t / self.dt) if len(self.track_ids) else np.zeros((0, 3))

    def frame_at(self, t: float) -> int:
        """The scene frame shown at time ``t``: the nearest step's."""
        k = int(np.clip(round(t / self.dt), 0, self.n_steps - 1))
        return int(self.scene_frames[k])

    def reference_speed(self) -> np.ndarray:  # -> [S] m/s of the reference ego
        d = np.linalg.norm(np.diff(self.ego[:, :2], axis=0), axis=1) / self.dt
        return np.concatenate([d[:1], 0.5 * (d[1:] + d[:-1]), d[-1:]]) if len(d) > 1 else np.repeat(d, 2)


def interpolate_pose(poses: np.ndarray,  # [..., S, 3] x, y, yaw
                     k: float) -> np.ndarray:  # -> [..., 3] at fractional step k (clamped); NaN if either is absent
    S = poses.shape[-2]
    k = float(np.clip(k, 0.0, S - 1))
    i = min(int(np.floor(k)), S - 2)
    w = k - i
    a, b = poses[..., i, :], poses[..., i + 1, :]
    if w <= 1e-9:
        return a.copy()
    if w >= 1 - 1e-9:
        return b.copy()
    out = (1 - w) * a + w * b
    out[..., 2] = a[..., 2] + w * wrap_angle(b[..., 2] - a[..., 2])
    return out


def log_scenario(scene, dt: float = 0.1) -> ClosedLoopScenario:
    """The scene's own log (``omniscs.scene.Scene``) as a scenario; the scene must be on a ``dt`` grid."""
    from omniscs.scs.behavior.tracks import traffic_from_scene

    traffic = traffic_from_scene(scene, dt=dt)
    if traffic.source_frames is None:
        raise OmniscsError(f"scene {scene.scene_id} is not on a {dt} s grid (its frames would have to be resampled); "
                           "closed-loop runs replay logged frames: pass the scene's own period as dt")
    agents = np.concatenate([traffic.xy, traffic.yaw[..., None]], -1).astype(np.float64)
    agents[~traffic.present] = np.nan
    z = np.where(traffic.present, traffic.z, np.nan)
    ego = np.concatenate([traffic.ego_xy, traffic.ego_yaw[:, None]], -1)
    return ClosedLoopScenario(f"{scene.scene_id}/log", scene.scene_id, "log", float(traffic.dt),
                              np.asarray(traffic.timestamps_us, np.int64), np.asarray(traffic.source_frames, np.int64),
                              ego, np.asarray(traffic.ego_z, np.float64), traffic.ego_box.length,
                              traffic.ego_box.width, traffic.ego_box.centre_ahead_m, np.asarray(traffic.track_ids),
                              tuple(traffic.categories), np.asarray(traffic.sizes, np.float64), agents, z, traffic.map)


def variant_scenario(scene, variant: dict, log: ClosedLoopScenario | None = None) -> ClosedLoopScenario:
    """A behaviour variant (a ``variants.json`` entry of ``scene``) as a scenario: its agents' trajectories and its
    ego plan as the reference; heights, sizes, categories and the map from the log."""
    log = log or log_scenario(scene, dt=float(variant.get("dt", 0.1)))
    vid = str(variant.get("variant_id"))
    if variant.get("scene_id") not in (None, scene.scene_id):
        raise OmniscsError(f"variant {vid} belongs to scene {variant.get('scene_id')}, not {scene.scene_id}")
    frames = variant.get("source_frames")
    if frames is None:
        raise OmniscsError(f"variant {vid} has no scene frames (its log was resampled); it cannot be replayed")
    frames = np.asarray(frames, np.int64)
    if abs(float(variant.get("dt", log.dt)) - log.dt) > 1e-6:
        raise OmniscsError(f"variant {vid} steps {variant.get('dt')} s, its scene {log.dt} s")
    if len(frames) < 2 or frames.min() < 0 or frames.max() >= log.n_steps:
        raise OmniscsError(f"variant {vid} names frames outside its scene's 0..{log.n_steps - 1}")
    ego = np.asarray(variant.get("ego"), np.float64).reshape(-1, 3)
    if len(ego) != len(frames) or not np.isfinite(ego).all():
        raise OmniscsError(f"variant {vid}: its ego trajectory does not cover its {len(frames)} steps")
    agents = log.agents[:, frames].copy()
    z = log.agents_z[:, frames].copy()
    row = {int(t): i for i, t in enumerate(log.track_ids)}
    for key, traj in (variant.get("agents") or {}).items():
        i = row.get(int(key))
        if i is None:
            raise OmniscsError(f"variant {vid} moves track {key}, which its scene does not have")
        for k, pose in enumerate(traj[:len(frames)]):
            ok = pose is not None and len(pose) >= 3 and all(p is not None for p in pose[:3])
            agents[i, k] = np.asarray(pose[:3], np.float64) if ok else np.nan
    for i in range(len(z)):  # a variant may show an agent where its log had none: its typical height
        known = log.agents_z[i][np.isfinite(log.agents_z[i])]
        z[i] = np.where(np.isfinite(z[i]), z[i], float(np.median(known)) if len(known) else 0.5 * log.sizes[i, 2])
    z = np.where(np.isfinite(agents[..., 0]), z, np.nan)
    adversary = variant.get("adversary")
    return ClosedLoopScenario(f"{scene.scene_id}/{vid}", scene.scene_id, "behavior", log.dt,
                              log.timestamps_us[frames], frames, ego, log.ego_z[frames], log.ego_length, log.ego_width,
                              float(variant.get("ego_centre_ahead_of_origin_m", log.ego_centre_ahead_m)),
                              log.track_ids, log.categories, log.sizes, agents, z, log.drivable,
                              int(adversary) if adversary not in (None, "", -1, "-1") else None)
