"""The ego's planned trajectory T_plan: the logged future (replay) or a rule-based planner that reacts
(follows the logged path, keeps its speed, brakes for a vehicle in its corridor ahead: IDM)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omniscs.errors import OmniscsError

PLANNERS = ("replay", "rule")


@dataclass(frozen=True)
class PlannerConfig:
    """The ego planner and the parameters of the rule-based one (intelligent driver model along the path)."""

    kind: str = "replay"
    """"replay" (the logged ego future) or "rule" (lane following with braking for a lead vehicle)."""
    max_accel: float = 1.5
    """Rule planner: largest acceleration, m/s²."""
    comfortable_decel: float = 2.0
    """Rule planner: IDM comfortable deceleration b, m/s²."""
    max_brake: float = 6.0
    """Rule planner: emergency braking limit, m/s²."""
    min_gap_m: float = 2.0
    """Rule planner: standstill gap to the lead vehicle, metres."""
    headway_s: float = 1.2
    """Rule planner: desired time headway, seconds."""
    corridor_margin_m: float = 0.3
    """Rule planner: a vehicle leads when its centre is within half the two widths plus this of the path."""
    look_ahead_m: float = 100.0
    """Rule planner: vehicles further ahead along the path are ignored."""
    path_extension_m: float = 200.0
    """Rule planner: the logged path is prolonged straight by this much past its end."""


def _arc(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def rule_based_plan(ego_path: np.ndarray,   # [K, 2] the logged ego positions from the now step on (scene frame)
                    speed0: float,
                    agents: np.ndarray,     # [M, T, 3] x, y, yaw of the other vehicles (scene frame)
                    present: np.ndarray,    # [M, T] bool
                    agent_sizes: np.ndarray,  # [M, 2] length, width
                    ego_size: tuple[float, float],
                    horizon: int, dt: float, config: PlannerConfig = PlannerConfig(),
                    desired_speed: float | None = None,
                    ) -> np.ndarray:        # [T, 3] x, y, yaw (scene frame) at steps 1..T
    """Follow ``ego_path`` with IDM speed control behind the nearest vehicle in the ego's corridor."""
    path = np.asarray(ego_path, dtype=np.float64)
    if len(path) < 2 or np.linalg.norm(path[-1] - path[0]) < 1e-3:
        path = np.stack([path[0], path[0] + [1.0, 0.0]])
    d = path[-1] - path[-2]
    if np.linalg.norm(d) < 1e-6:
        d = path[-1] - path[0]
    path = np.vstack([path, path[-1] + d / np.linalg.norm(d) * config.path_extension_m])
    s_path = _arc(path)
    dense_s = np.arange(0.0, s_path[-1], 0.5)
    dense = np.stack([np.interp(dense_s, s_path, path[:, 0]), np.interp(dense_s, s_path, path[:, 1])], -1)
    tangent = np.gradient(dense, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    v0 = max(desired_speed if desired_speed is not None else speed0, 1.0)
    s, v = 0.0, max(speed0, 0.0)
    ego_len, ego_w = ego_size
    out = np.zeros((horizon, 3))
    prev_lead_s: dict[int, float] = {}
    for t in range(horizon):
        gap, lead_v = np.inf, v
        if len(agents):
            pos = agents[:, t - 1, :2] if t > 0 else agents[:, 0, :2]
            on = present[:, t - 1] if t > 0 else present[:, 0]
            dist = np.linalg.norm(pos[:, None, :] - dense[None], axis=-1)  # [M, D]
            nearest = dist.argmin(1)
            lateral = dist[np.arange(len(pos)), nearest]
            s_agent = dense_s[nearest]
            ahead = on & (s_agent > s) & (s_agent - s < config.look_ahead_m)
            ahead &= lateral < 0.5 * (ego_w + agent_sizes[:, 1]) + config.corridor_margin_m
            for m in np.flatnonzero(ahead):
                g = s_agent[m] - s - 0.5 * (ego_len + agent_sizes[m, 0])
                if g < gap:
                    gap = g
                    lead_v = (s_agent[m] - prev_lead_s[m]) / dt if m in prev_lead_s else v
            prev_lead_s = {int(m): float(s_agent[m]) for m in np.flatnonzero(on)}
        desired_gap = config.min_gap_m + v * config.headway_s + v * (v - lead_v) / (
            2.0 * np.sqrt(config.max_accel * config.comfortable_decel))
        interaction = (max(desired_gap, 0.0) / max(gap, 0.1)) ** 2 if np.isfinite(gap) else 0.0
        accel = config.max_accel * (1.0 - (v / v0) ** 4 - interaction)
        accel = float(np.clip(accel, -config.max_brake, config.max_accel))
        v_next = max(0.0, v + accel * dt)
        s += 0.5 * (v + v_next) * dt
        v = v_next
        k = min(int(np.searchsorted(dense_s, s)), len(dense) - 1)
        out[t, :2] = [np.interp(s, dense_s, dense[:, 0]), np.interp(s, dense_s, dense[:, 1])]
        out[t, 2] = np.arctan2(tangent[k, 1], tangent[k, 0])
    return out


def check_planner(kind: str) -> str:
    if kind not in PLANNERS:
        raise OmniscsError(f"unknown planner {kind!r}; use one of {list(PLANNERS)}")
    return kind
