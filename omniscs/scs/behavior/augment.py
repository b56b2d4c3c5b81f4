"""Manoeuvre augmentation of training futures: lane changes, swerves and speed changes of moving vehicles, and
standing vehicles pulling out.

Procedural traffic keeps its lane at a planned speed, so its future is nearly determined by its past and a
latent variable trained on it alone would carry no information (the decoder learns to ignore it, and
latent-space optimisation then cannot move anyone). Replacing some agents' logged futures by plausible
alternatives (on the drivable area, within comfort bounds, overlapping nobody's logged future) makes the
latent span manoeuvres. Only the future after the now step changes; the past stays as logged.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omniscs.geometry import wrap_angle
from omniscs.scs.behavior.collision import overlapping
from omniscs.scs.behavior.tracks import TrafficScene

#: Below this speed (m/s) an augmented trajectory keeps its logged heading (no direction from positions).
MIN_SPEED_FOR_HEADING = 0.5


@dataclass(frozen=True)
class AugmentConfig:
    """Which futures are replaced by manoeuvres, and their ranges."""

    probability: float = 0.5
    """Chance that a moving vehicle's future is replaced (when a valid manoeuvre is found)."""
    tries: int = 6
    """Random manoeuvres tried per chosen agent before keeping its logged future."""
    lane_change_offset_m: tuple[float, float] = (0.8, 3.8)
    """Lateral shift of a lane change or swerve, metres (either side)."""
    lane_change_duration_s: tuple[float, float] = (1.2, 3.2)
    """Duration of a lane change or swerve, seconds."""
    pull_out_probability: float = 0.15
    """Chance that a standing vehicle's future is replaced by pulling out (accelerating with a sideways shift)."""
    pull_out_accel_mps2: tuple[float, float] = (1.0, 2.4)
    """Acceleration of a pull-out, m/s²."""
    speed_change_mps2: tuple[float, float] = (-3.5, 2.0)
    """Extra acceleration (negative = braking) of a speed change, m/s²."""
    speed_change_duration_s: tuple[float, float] = (0.8, 3.0)
    """How long the extra acceleration lasts, seconds."""
    max_lateral_accel: float = 4.5
    """Comfort bound on the manoeuvre's lateral acceleration, m/s²."""
    max_long_accel: float = 2.4
    """Bound on forward acceleration, m/s²."""
    max_long_decel: float = 4.0
    """Bound on braking deceleration, m/s²."""
    max_curvature: float = 0.2
    """Tightest turn a manoeuvre may take, 1/m (the bicycle model's steering lock)."""
    clearance_m: float = 0.3
    """Footprints grown by this much when checking overlaps with other agents' logged futures."""


def _extend(path: np.ndarray, extra: float) -> np.ndarray:  # [K, 2] -> [K+1, 2] prolonged along the last heading
    if len(path) < 2:
        return path
    d = path[-1] - path[-2]
    n = np.linalg.norm(d)
    if n < 1e-6:
        return path
    return np.vstack([path, path[-1] + d / n * extra])


def _corners(xy: np.ndarray, yaw: np.ndarray, length: float, width: float) -> np.ndarray:  # [T,2],[T] -> [T,4,2]
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length / 2, width / 2]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([xy[:, None, 0] + c * local[:, 0] - s * local[:, 1],
                     xy[:, None, 1] + s * local[:, 0] + c * local[:, 1]], -1)


def manoeuvre(xy: np.ndarray, yaw: np.ndarray, speed0: float, dt: float, lateral: float, t_start: float,
              duration: float, extra_accel: float, accel_time: float, path_speed: float | None = None,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # -> xy [T, 2], yaw [T], speed [T+1]
    """A new future along the path ``xy`` [T+1, 2] (now step first): the logged speed profile (or a constant
    ``path_speed``) changed by ``extra_accel`` for ``accel_time`` s, and a smooth lateral shift of ``lateral`` m
    over ``duration`` s."""
    t_steps = len(xy) - 1
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    v_log = np.concatenate([[speed0], seg / dt]) if path_speed is None else np.full(t_steps + 1, path_speed)
    tau = np.arange(t_steps + 1) * dt
    v_new = np.maximum(v_log + extra_accel * np.minimum(tau, accel_time), 0.0)
    s_new = np.concatenate([[0.0], np.cumsum(0.5 * (v_new[1:] + v_new[:-1]) * dt)])
    path = _extend(xy, max(0.0, s_new[-1] - seg.sum()) + 5.0)
    s_path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    px = np.interp(s_new, s_path, path[:, 0])
    py = np.interp(s_new, s_path, path[:, 1])
    # path direction at each new arc length, for the lateral shift
    ahead = np.stack([np.interp(s_new + 0.5, s_path, path[:, 0]), np.interp(s_new + 0.5, s_path, path[:, 1])], -1)
    behind = np.stack([np.interp(s_new - 0.5, s_path, path[:, 0]), np.interp(s_new - 0.5, s_path, path[:, 1])], -1)
    d = ahead - behind
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    fallback = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    direction = np.where(norm > 1e-6, d / np.maximum(norm, 1e-9), fallback)
    normal = np.stack([-direction[:, 1], direction[:, 0]], -1)
    u = np.clip((tau - t_start) / max(duration, 1e-6), 0.0, 1.0)
    offset = lateral * (3 * u ** 2 - 2 * u ** 3)
    new_xy = np.stack([px, py], -1) + offset[:, None] * normal
    step = np.diff(new_xy, axis=0)
    heading = np.arctan2(step[:, 1], step[:, 0])
    moving = np.linalg.norm(step, axis=1) / dt > MIN_SPEED_FOR_HEADING
    new_yaw = np.empty(t_steps)
    last = yaw[0]
    for k in range(t_steps):  # standing still keeps the last heading
        last = heading[k] if moving[k] else last
        new_yaw[k] = last
    new_yaw = yaw[0] + np.unwrap(np.concatenate([[0.0], wrap_angle(new_yaw - yaw[0])]))[1:]
    return new_xy[1:], wrap_angle(new_yaw), v_new


def augment_traffic(traffic: TrafficScene, now_step: int, future_steps: int, rng: np.random.Generator,
                    config: AugmentConfig = AugmentConfig()) -> TrafficScene:
    """A copy of ``traffic`` whose moving vehicles' futures (after ``now_step``) are, with probability
    ``config.probability`` each, replaced by a valid lane change and/or speed change."""
    s = traffic.n_steps
    end = min(s, now_step + 1 + future_steps)
    if end - now_step < 3:
        return traffic
    xy, yaw, present = traffic.xy.copy(), traffic.yaw.copy(), traffic.present
    dt = traffic.dt
    window = slice(now_step + 1, end)
    vehicle = traffic.is_vehicle()
    others = [(traffic.ego_xy[window], traffic.ego_yaw[window], np.ones(end - now_step - 1, bool),
               traffic.ego_box.length, traffic.ego_box.width, -1)]
    for j in range(traffic.n_tracks):
        if present[j, window].any():
            others.append((xy[j, window], yaw[j, window], present[j, window], traffic.sizes[j, 0],
                           traffic.sizes[j, 1], j))
    for i in np.flatnonzero(vehicle & present[:, now_step]):
        if not present[i, now_step:end].all():
            continue
        path = xy[i, now_step:end]
        standing = np.linalg.norm(path[-1] - path[0]) < 1.0
        if rng.uniform() > (config.pull_out_probability if standing else config.probability):
            continue
        if standing:  # a straight path along its heading to pull out along
            heading = np.array([np.cos(yaw[i, now_step]), np.sin(yaw[i, now_step])])
            path = path[0] + np.linspace(0.0, 60.0, len(path))[:, None] * heading
        speed0 = float(np.linalg.norm(xy[i, now_step] - xy[i, max(now_step - 1, 0)]) / dt) if now_step else 0.0
        length, width = traffic.sizes[i, 0], traffic.sizes[i, 1]
        for _ in range(config.tries):
            kind = rng.integers(0, 3)  # 0 lane change, 1 speed change, 2 both
            lateral = 0.0
            extra, accel_time = 0.0, 0.0
            t_start, duration = 0.0, 1.0
            if kind in (0, 2):
                lateral = rng.uniform(*config.lane_change_offset_m) * rng.choice([-1.0, 1.0])
                duration = rng.uniform(*config.lane_change_duration_s)
                t_start = rng.uniform(0.0, max(0.0, (end - now_step - 1) * dt - duration))
            if kind in (1, 2):
                extra = rng.uniform(*config.speed_change_mps2)
                accel_time = rng.uniform(*config.speed_change_duration_s)
            if standing:
                extra, accel_time = rng.uniform(*config.pull_out_accel_mps2), (end - now_step) * dt
                lateral = lateral or rng.uniform(*config.lane_change_offset_m) * rng.choice([-1.0, 1.0])
            new_xy, new_yaw, v = manoeuvre(path, yaw[i, now_step:end], 0.0 if standing else speed0, dt, lateral,
                                           t_start, duration, extra, accel_time,
                                           path_speed=0.0 if standing else None)
            if not _plausible(new_xy, new_yaw, v, dt, config) or not traffic.map.is_drivable(new_xy).all():
                continue
            mine = _corners(new_xy, new_yaw, length + config.clearance_m, width + config.clearance_m)
            clash = False
            for oxy, oyaw, opres, ol, ow, j in others:
                if j == i:
                    continue
                both = opres
                if both.any() and (overlapping(mine, _corners(oxy, oyaw, ol, ow)) & both).any():
                    clash = True
                    break
            if clash:
                continue
            xy[i, window], yaw[i, window] = new_xy, new_yaw
            break
    return replace(traffic, xy=xy, yaw=yaw)


def _plausible(xy: np.ndarray, yaw: np.ndarray, v: np.ndarray, dt: float, config: AugmentConfig) -> bool:
    accel = np.diff(v) / dt
    if accel.max(initial=0.0) > config.max_long_accel + 1e-6 or accel.min(initial=0.0) < -config.max_long_decel - 1e-6:
        return False
    if len(xy) < 3:
        return True
    vel = np.diff(xy, axis=0) / dt
    acc = np.diff(vel, axis=0) / dt
    speed = np.linalg.norm(vel[1:], axis=1)
    lateral = np.abs(vel[1:, 0] * acc[:, 1] - vel[1:, 1] * acc[:, 0]) / np.maximum(speed, 1e-3)
    curvature = lateral / np.maximum(speed, 1e-3) ** 2
    fast = speed > MIN_SPEED_FOR_HEADING
    return bool(np.all(lateral[fast] <= config.max_lateral_accel) and np.all(curvature[fast] <= config.max_curvature))
