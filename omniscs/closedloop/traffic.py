"""The other agents of a closed-loop run. By default they replay the scenario's trajectories in time, whatever the ego
does (non-reactive, as NAVSIM and HUGSIM's log agents). Reactive mode adds one behaviour: an agent that finds the ego
ahead of it in its path brakes by the Intelligent Driver Model (Treiber et al. 2000) instead of driving through it.
Each agent then moves along its own logged path at its own pace (a "path time" that runs slower while it brakes); it
never drives faster than its log, so an agent that fell behind stays behind."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omniscs.closedloop.scenario import ClosedLoopScenario, interpolate_pose
from omniscs.errors import ValidationError


@dataclass(frozen=True)
class IDMConfig:
    """Intelligent Driver Model parameters of reactive agents (Treiber's highway values, urban time gap)."""

    max_accel: float = 1.5
    """Largest acceleration back toward the logged speed, m/s²."""
    comfortable_decel: float = 2.0
    """Comfortable braking b, m/s²; IDM brakes harder when it must (capped by ``max_decel``)."""
    max_decel: float = 8.0
    """Hardest braking, m/s²."""
    time_gap_s: float = 1.5
    """Desired time gap T to the vehicle ahead, seconds."""
    min_gap_m: float = 2.0
    """Jam distance s0, metres."""
    exponent: float = 4.0
    """Free-road acceleration exponent delta."""
    lateral_margin_m: float = 0.5
    """The ego counts as in an agent's path when its centre lies within half their widths plus this margin of the
    agent's heading line, metres."""
    lookahead_m: float = 60.0
    """The ego is ignored when it is further ahead than this, metres."""

    def __post_init__(self):
        if not (self.max_accel > 0 and self.comfortable_decel > 0 and self.max_decel > 0 and self.time_gap_s >= 0
                and self.min_gap_m >= 0 and self.exponent > 0 and self.lookahead_m > 0):
            raise ValidationError("IDM parameters must be positive")


def idm_accel(speed: float, desired: float, gap: float, closing: float, cfg: IDMConfig) -> float:
    """IDM acceleration of a follower at ``speed`` wanting ``desired`` m/s, ``gap`` metres behind a leader it closes
    on at ``closing`` m/s (follower minus leader speed); ``gap`` = inf on a free road."""
    desired = max(desired, 0.1)
    free = 1.0 - (max(speed, 0.0) / desired) ** cfg.exponent
    if not math.isfinite(gap):
        return float(np.clip(cfg.max_accel * free, -cfg.max_decel, cfg.max_accel))
    s_star = cfg.min_gap_m + max(0.0, speed * cfg.time_gap_s
                                 + speed * closing / (2.0 * math.sqrt(cfg.max_accel * cfg.comfortable_decel)))
    a = cfg.max_accel * (free - (s_star / max(gap, 0.1)) ** 2)
    return float(np.clip(a, -cfg.max_decel, cfg.max_accel))


class Traffic:
    """Where the scenario's agents are as the run goes (world frame, box centres)."""

    def __init__(self, scenario: ClosedLoopScenario, reactive: bool = False, idm: IDMConfig = IDMConfig(),
                 movable: frozenset[int] | None = None) -> None:
        """``movable``: the track ids reactive mode may slow down (agent nodes: the others cannot be drawn
        anywhere but where they were logged); None = all."""
        self.scenario = scenario
        self.reactive = reactive
        self.idm = idm
        ids = [int(t) for t in scenario.track_ids]
        self.movable = np.array([movable is None or t in movable for t in ids], bool)
        steps = np.linalg.norm(np.diff(scenario.agents[..., :2], axis=1), axis=-1) / scenario.dt  # [N, S-1]
        self.logged_speed = np.nan_to_num(np.concatenate([steps, steps[:, -1:]], 1) if steps.shape[1] else
                                          np.zeros((len(ids), 1)), nan=0.0)  # [N, S]
        self.reset()

    def reset(self) -> None:
        self.t = 0.0
        self.path_time = np.zeros(len(self.scenario.track_ids))  # [N] s along each agent's own trajectory
        self.speed = self.logged_speed[:, 0].copy()
        self._previous = self.poses()

    def poses(self) -> np.ndarray:  # -> [N, 3] x, y, yaw (NaN where absent)
        sc = self.scenario
        if not len(sc.track_ids):
            return np.zeros((0, 3))
        if not self.reactive:
            return sc.agents_at(self.t)
        return np.stack([interpolate_pose(sc.agents[i], self.path_time[i] / sc.dt) for i in range(len(sc.track_ids))])

    def velocities(self, dt: float) -> np.ndarray:  # -> [N, 2] m/s over the last step (logged at the start)
        now = self.poses()
        if self.t == 0.0:
            later = self.scenario.agents_at(dt)
            v = (later[:, :2] - now[:, :2]) / dt
        else:
            v = (now[:, :2] - self._previous[:, :2]) / dt
        return np.nan_to_num(v, nan=0.0)

    def step(self, dt: float, ego_centre: np.ndarray,  # [3] x, y, yaw of the ego box centre after this step
             ego_speed: float, ego_size: tuple[float, float]) -> None:
        self._previous = self.poses()
        self.t += dt
        if not self.reactive:
            self.path_time[:] = self.t
            return
        sc, cfg = self.scenario, self.idm
        now = self._previous
        for i in range(len(sc.track_ids)):
            k = min(int(round(self.path_time[i] / sc.dt)), sc.n_steps - 1)
            v_log = float(self.logged_speed[i, k])
            if not self.movable[i] or not np.isfinite(now[i]).all() or v_log < 0.1:
                self.path_time[i] += dt
                self.speed[i] = v_log
                continue
            gap, closing = math.inf, 0.0
            c, s = math.cos(now[i, 2]), math.sin(now[i, 2])
            dx, dy = ego_centre[0] - now[i, 0], ego_centre[1] - now[i, 1]
            ahead, side = c * dx + s * dy, -s * dx + c * dy
            if 0.0 < ahead < cfg.lookahead_m \
                    and abs(side) < 0.5 * (sc.sizes[i, 1] + ego_size[1]) + cfg.lateral_margin_m:
                gap = ahead - 0.5 * (sc.sizes[i, 0] + ego_size[0])
                closing = self.speed[i] - ego_speed * math.cos(ego_centre[2] - now[i, 2])
            a = idm_accel(self.speed[i], v_log, gap, closing, cfg)
            self.speed[i] = float(np.clip(self.speed[i] + a * dt, 0.0, v_log))
            self.path_time[i] += dt * self.speed[i] / v_log
