"""The ego vehicle of a closed-loop run: a kinematic bicycle model (state at the rear axle, which is the ego frame's
origin) and the pure-pursuit controller that turns a planned trajectory into its controls.

Why pure pursuit: a driving stack's plan is 6 waypoints at 0.5 s, often noisy and sometimes nearly stationary. Pure
pursuit steers toward one point of the plan at a speed-dependent look-ahead distance, needs no derivative of the plan
(an LQR tracker needs the plan's heading and curvature, which 6 noisy points give badly) and no linearisation, and
degrades gracefully when the plan is short. The longitudinal part fits the constant acceleration that best reaches
the plan's first two waypoints on time (least squares), so a plan that slows down is followed without a speed target
of its own."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omniscs.errors import ValidationError
from omniscs.geometry import wrap_angle


@dataclass(frozen=True)
class VehicleLimits:
    """The ego's kinematic bicycle model and what it can do (a mid-size car)."""

    wheelbase_m: float = 2.7
    """Distance from the rear axle (the ego frame's origin) to the front axle, metres."""
    max_steer_rad: float = 0.55
    """Largest front-wheel angle either side, radians."""
    max_steer_rate: float = 1.0
    """Fastest change of the wheel angle, rad/s."""
    max_accel: float = 3.0
    """Strongest acceleration, m/s²."""
    max_decel: float = 8.0
    """Strongest braking (positive number), m/s²."""
    max_speed: float = 30.0
    """Top speed, m/s; the model does not reverse (speed >= 0)."""
    substep_s: float = 0.02
    """Integration step: one simulator step is split into steps this long (midpoint rule)."""

    def __post_init__(self):
        if not (self.wheelbase_m > 0 and self.max_steer_rad > 0 and self.max_steer_rate > 0 and self.max_accel > 0
                and self.max_decel > 0 and self.max_speed > 0 and self.substep_s > 0):
            raise ValidationError("vehicle limits must all be positive")


@dataclass(frozen=True)
class VehicleState:
    """The ego at one instant (world frame, rear axle)."""

    x: float
    y: float
    yaw: float        # rad, heading of the ego's +x
    speed: float      # m/s along the heading, >= 0
    steer: float      # rad, front-wheel angle (left positive)
    accel: float = 0.0       # m/s², the last applied acceleration
    steer_rate: float = 0.0  # rad/s, the last applied steering rate


def yaw_rate_of(state: VehicleState, limits: VehicleLimits) -> float:  # rad/s
    return state.speed * math.tan(state.steer) / limits.wheelbase_m


@dataclass(frozen=True)
class Controls:
    """Direct controls for one simulator step."""

    accel: float       # m/s² (negative brakes)
    steer_rate: float  # rad/s (left positive)

    def __post_init__(self):
        if not (math.isfinite(self.accel) and math.isfinite(self.steer_rate)):
            raise ValidationError(f"controls must be finite numbers (got accel {self.accel}, steer_rate "
                                  f"{self.steer_rate})")


def advance(state: VehicleState, controls: Controls, dt: float, limits: VehicleLimits = VehicleLimits()
            ) -> VehicleState:
    """The state ``dt`` seconds later under ``controls`` (clipped to the limits), rear-axle kinematic bicycle:
    x' = v cos(yaw), y' = v sin(yaw), yaw' = v tan(steer) / L, v' = a, steer' = steer rate."""
    if not dt > 0:
        raise ValidationError(f"dt must be > 0 (got {dt})")
    a = float(np.clip(controls.accel, -limits.max_decel, limits.max_accel))
    rate = float(np.clip(controls.steer_rate, -limits.max_steer_rate, limits.max_steer_rate))
    n = max(1, int(math.ceil(dt / limits.substep_s - 1e-9)))
    h = dt / n
    x, y, yaw, v, steer = state.x, state.y, state.yaw, state.speed, state.steer
    for _ in range(n):
        v_next = min(max(v + a * h, 0.0), limits.max_speed)
        steer_next = float(np.clip(steer + rate * h, -limits.max_steer_rad, limits.max_steer_rad))
        v_mid, steer_mid = 0.5 * (v + v_next), 0.5 * (steer + steer_next)
        yaw_mid = yaw + 0.5 * h * v_mid * math.tan(steer_mid) / limits.wheelbase_m
        x += h * v_mid * math.cos(yaw_mid)
        y += h * v_mid * math.sin(yaw_mid)
        yaw += h * v_mid * math.tan(steer_mid) / limits.wheelbase_m
        v, steer = v_next, steer_next
    return VehicleState(x, y, float(wrap_angle(yaw)), v, steer, a, rate)


@dataclass(frozen=True)
class PurePursuitConfig:
    """Pure pursuit steering (Coulter 1992) with a least-squares longitudinal fit to the plan's first waypoints."""

    lookahead_s: float = 1.0
    """Look-ahead distance per m/s of speed (seconds)."""
    min_lookahead_m: float = 4.0
    """Shortest look-ahead distance, metres."""
    max_lookahead_m: float = 20.0
    """Longest look-ahead distance, metres."""
    steer_time_s: float = 0.2
    """The wheel angle is driven toward pure pursuit's angle over this time (steer rate = error / this)."""
    stationary_m: float = 0.5
    """A plan whose waypoints stay within this distance of the ego is a request to stop: brake, keep steering."""
    longitudinal_points: int = 2
    """How many leading waypoints the acceleration is fitted to."""


def plan_to_ego(plan_xy: np.ndarray,  # [K, 2] planning frame: x right, y forward, origin `origin_ahead_m` ahead
                origin_ahead_m: float) -> np.ndarray:  # -> [K, 2] ego (rear-axle) frame: x forward, y left
    """A plan in UniAD's planning frame as points in the ego frame."""
    plan_xy = np.asarray(plan_xy, dtype=np.float64)
    return np.stack([plan_xy[:, 1] + origin_ahead_m, -plan_xy[:, 0]], -1)


def pure_pursuit(state: VehicleState, plan_ego: np.ndarray,  # [K, 2] ego frame waypoints at plan_dt
                 plan_dt: float, limits: VehicleLimits = VehicleLimits(),
                 config: PurePursuitConfig = PurePursuitConfig(), origin_ahead_m: float = 0.0) -> Controls:
    """The controls that follow ``plan_ego`` (the polyline from the plan's origin, ``origin_ahead_m`` ahead of the
    rear axle, through the waypoints)."""
    pts = np.concatenate([[[origin_ahead_m, 0.0]], np.asarray(plan_ego, dtype=np.float64)], 0)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    v = state.speed
    if float(np.max(np.linalg.norm(pts - pts[0], axis=1))) < config.stationary_m:
        return Controls(-limits.max_decel if v > 0 else 0.0, 0.0)
    # longitudinal: the constant acceleration whose travel best matches the first waypoints' arc lengths on time
    k = min(config.longitudinal_points, len(arc) - 1)
    t = plan_dt * np.arange(1, k + 1)
    a = float(np.sum((arc[1:k + 1] - v * t) * 0.5 * t ** 2) / np.sum((0.5 * t ** 2) ** 2))
    # lateral: the point of the polyline at the look-ahead distance (extended along its last segment)
    ld = float(np.clip(config.lookahead_s * v, config.min_lookahead_m, config.max_lookahead_m))
    target = _point_at(pts, arc, ld)
    dist = float(np.hypot(*target))
    if dist < 1e-6:
        return Controls(a, 0.0)
    alpha = math.atan2(target[1], target[0])
    if target[0] < 0 and abs(alpha) > math.pi / 2:
        alpha = math.copysign(math.pi / 2, alpha)  # a point behind: turn as hard as the formula allows
    steer_goal = math.atan2(2.0 * limits.wheelbase_m * math.sin(alpha), dist)
    steer_goal = float(np.clip(steer_goal, -limits.max_steer_rad, limits.max_steer_rad))
    return Controls(a, (steer_goal - state.steer) / config.steer_time_s)


def _point_at(pts: np.ndarray, arc: np.ndarray, s: float) -> np.ndarray:  # polyline [K,2], arc [K] -> [2]
    if s >= arc[-1]:
        d = pts[-1] - pts[-2]
        n = float(np.linalg.norm(d))
        if n < 1e-9:
            return pts[-1]
        return pts[-1] + d / n * (s - arc[-1])
    i = int(np.searchsorted(arc, s, side="right")) - 1
    i = min(max(i, 0), len(pts) - 2)
    w = (s - arc[i]) / max(arc[i + 1] - arc[i], 1e-12)
    return pts[i] + w * (pts[i + 1] - pts[i])
