"""Kinematic bicycle model: bounded controls (acceleration, yaw acceleration) rolled out into feasible states.

State per agent: (x, y, yaw, v, yaw_rate) at the box centre. The bicycle constraint ties the yaw rate to
the speed (``|yaw_rate| <= max_curvature * v``), so a standing vehicle cannot turn on the spot.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

#: Speeds below this (m/s) are treated as this when dividing (lateral-acceleration bound).
MIN_SPEED_FOR_DIVISION = 1e-3


@dataclass(frozen=True)
class KinematicLimits:
    """Physical bounds every decoded trajectory obeys (above the comfort bounds that plausibility checks)."""

    max_speed: float = 50.0
    """Speed is clamped to [0, max_speed] m/s."""
    max_accel: float = 4.0
    """Largest forward acceleration, m/s²."""
    max_decel: float = 8.0
    """Largest braking deceleration (positive number), m/s²."""
    max_yaw_accel: float = 3.0
    """Largest yaw acceleration, rad/s²."""
    max_yaw_rate: float = 1.2
    """Largest yaw rate at any speed, rad/s."""
    max_curvature: float = 0.2
    """Tightest turn, 1/m (steering lock: about a 5 m radius); caps the yaw rate at max_curvature * v."""
    max_lateral_accel: float = 8.0
    """Largest lateral acceleration v * yaw_rate, m/s² (tyre grip)."""


def bound_controls(raw: Tensor,  # [..., T, 2] unbounded network outputs
                   limits: KinematicLimits) -> Tensor:  # [..., T, 2] (accel m/s², yaw accel rad/s²)
    """Squash raw outputs into the physical control bounds (asymmetric for braking and accelerating)."""
    a = torch.tanh(raw[..., 0])
    accel = torch.where(a >= 0, a * limits.max_accel, a * limits.max_decel)
    yaw_accel = torch.tanh(raw[..., 1]) * limits.max_yaw_accel
    return torch.stack([accel, yaw_accel], dim=-1)


def soft_clip_accel(accel: Tensor, max_accel: float, max_decel: float) -> Tensor:  # [...] -> [...]
    """Smoothly saturate accelerations into (-max_decel, max_accel): identity to first order near 0 (1 m/s²
    changes by about 5% at the comfort bounds), never beyond the bounds, gradient never exactly 0."""
    return torch.where(accel >= 0, max_accel * torch.tanh(accel / max_accel), max_decel * torch.tanh(accel / max_decel))


def yaw_rate_bound(speed: Tensor, limits: KinematicLimits) -> Tensor:  # [...] m/s -> [...] rad/s
    """Largest |yaw rate| at ``speed``: steering lock, grip and the absolute cap, whichever is least."""
    grip = limits.max_lateral_accel / speed.clamp_min(MIN_SPEED_FOR_DIVISION)
    steer = limits.max_curvature * speed
    return torch.minimum(torch.minimum(steer, grip), torch.full_like(speed, limits.max_yaw_rate))


def rollout(state0: Tensor,    # [..., 5] (x, y, yaw, v, yaw_rate) at step 0
            controls: Tensor,  # [..., T, 2] bounded (accel, yaw accel), see bound_controls
            dt: float,
            limits: KinematicLimits,
            standstill_gradient: float = 0.0,
            ) -> Tensor:       # [..., T, 5] states at steps 1..T
    """Integrate the bicycle model in closed form (cumulative sums, no Python loop over steps).

    Speed is the integrated acceleration reflected at 0 (``v_t = S_t - min(0, min_k<=t S_k)``, exactly what
    clamping at 0 after every step gives) and capped at max_speed. The integrated yaw acceleration is
    saturated smoothly into the speed-dependent bound (``b * tanh(W / b)``), so the yaw rate never leaves
    it and a standing vehicle (b = 0) cannot turn. Heading and position follow by the trapezoid rule.

    ``standstill_gradient`` > 0 leaves the values unchanged but lets that fraction of the gradient through
    the stop at v = 0 (a surrogate gradient): a vehicle held at standstill by braking commands otherwise gives
    no gradient at all, and an optimiser could never make a parked car pull out.
    """
    x0, y0, yaw0, v0, w0 = state0.unbind(-1)
    accel, yaw_accel = controls[..., 0], controls[..., 1]
    integrated = v0.clamp(0.0, limits.max_speed)[..., None] + torch.cumsum(accel * dt, dim=-1)
    floor = torch.cummin(integrated, dim=-1).values.clamp_max(0.0)
    if standstill_gradient:
        floor = floor - standstill_gradient * (floor - floor.detach())
    v = (integrated - floor).clamp_max(limits.max_speed)  # [..., T]
    v_prev = torch.cat([v0.clamp(0.0, limits.max_speed)[..., None], v[..., :-1]], -1)
    bound = yaw_rate_bound(v, limits)
    w_cmd = w0[..., None] + torch.cumsum(yaw_accel * dt, dim=-1)
    w = bound * torch.tanh(w_cmd / bound.clamp_min(1e-4))
    bound0 = yaw_rate_bound(v0.clamp(0.0, limits.max_speed), limits)
    w_start = bound0 * torch.tanh(w0 / bound0.clamp_min(1e-4))
    w_prev = torch.cat([w_start[..., None], w[..., :-1]], -1)
    yaw = yaw0[..., None] + torch.cumsum(0.5 * (w_prev + w) * dt, dim=-1)
    yaw_prev = torch.cat([yaw0[..., None], yaw[..., :-1]], -1)
    v_mid, yaw_mid = 0.5 * (v_prev + v), 0.5 * (yaw_prev + yaw)
    x = x0[..., None] + torch.cumsum(v_mid * torch.cos(yaw_mid) * dt, dim=-1)
    y = y0[..., None] + torch.cumsum(v_mid * torch.sin(yaw_mid) * dt, dim=-1)
    return torch.stack([x, y, yaw, v, w], dim=-1)


def accelerations(state0: Tensor,  # [..., 5]
                  states: Tensor,  # [..., T, 5] from rollout
                  dt: float,
                  ) -> tuple[Tensor, Tensor]:  # longitudinal [..., T], lateral [..., T] m/s²
    """Longitudinal (dv/dt) and lateral (v * yaw_rate) accelerations along a rolled-out trajectory."""
    v = torch.cat([state0[..., None, 3], states[..., 3]], dim=-1)
    longitudinal = (v[..., 1:] - v[..., :-1]) / dt
    lateral = states[..., 3] * states[..., 4]
    return longitudinal, lateral
