"""Can any agent reach the ego's path? A search over free, comfort-bounded controls, independent of the traffic model.

The behaviour benchmark's target is a success rate "over scenes where some agent can reach the ego path".
``BehaviorProblem.reachable`` answers that cheaply with a kinematic envelope (0.5·a·t² along and across the fitted
path, boxes touching), which is looser than the bicycle model and than the success test (footprint IoU > 0.02):
a car one lane over whose envelope touches the ego may still have no comfortable trajectory that overlaps it.

This module answers the question directly. For each candidate it optimises per-step controls (acceleration, yaw
acceleration; one free pair per step, no traffic model, no latent) from many random starts, rolled through the same
bicycle model with the plausibility bounds as hard limits (longitudinal +2.4 / -4.05 m/s², lateral 4.9 m/s², yaw
rate 1 rad/s), toward overlapping the ego's box, and measures the result with the exact footprint IoU. An agent
that starts on the drivable area must stay on it (the plausibility check's own test, on every step); other agents
are ignored. So "feasible" is necessary for a plausible success, not sufficient: it bounds what any adversarial
method could achieve. A search can miss a trajectory that exists; the benchmark therefore also counts a scene as
feasible wherever a method produced a successful, plausible variant (``bench.mark_feasible``).

Candidates whose reach ball (speed·t + ½·a_max·t² plus both boxes' half diagonals) never meets the ego's path are
ruled out without a search: that test is exact, not heuristic.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from omniscs.errors import OmniscsError
from omniscs.scs.behavior.collision import box_iou, footprints
from omniscs.scs.behavior.kinematics import bound_controls, rollout, soft_clip_accel
from omniscs.scs.behavior.losses import INTERCEPT_SOFTMIN_M, box_gap


@dataclass(frozen=True)
class FeasibilityConfig:
    """How hard the search tries (more starts and steps: fewer misses, more time)."""

    starts: int = 192
    """Random starting control sequences per candidate, optimised together as one batch."""
    steps: int = 300
    """Adam steps at most."""
    lr: float = 0.1
    """Adam learning rate on the raw (pre-squash) controls."""
    init_std: tuple[float, ...] = (0.3, 1.0, 2.0)
    """Standard deviations of the random raw controls; the starts are split evenly between them."""
    depth_m: float = 1.5
    """Penetration rewarded up to this depth, metres (deeper overlap is more IoU; beyond it nothing more)."""
    offroad_weight: float = 10.0
    """Weight of the squared distance off the drivable area in the search's loss (agents that start on it)."""
    road: bool = True
    """Require agents that start on the drivable area to stay on it; False ignores the road (a looser bound)."""
    check_every: int = 50
    """Measure IoU every this many steps and stop once a start exceeds the threshold."""
    seed: int = 0
    """Seed of the random starts (the search is deterministic per seed)."""


@dataclass
class Reach:
    """The search's answer for one candidate adversary."""

    node: int
    track: int  # index into the scene's tracks
    feasible: bool
    best_iou: float
    best_gap_m: float  # smallest separating-axis gap reached by a trajectory that stays on the road (negative: depth)
    searched: bool  # False when ruled out by the reach ball
    steps: int
    states: np.ndarray | None  # [T, 5] the best trajectory (scene frame), None when not searched


def comfort_kinematics(problem):
    """The model's physical limits tightened to the plausibility bounds (lateral acceleration and yaw rate)."""
    cb = problem.config.comfort
    lim = problem.model.config.limits
    return replace(lim, max_lateral_accel=min(lim.max_lateral_accel, cb.max_abs_lat_accel),
                   max_yaw_rate=min(lim.max_yaw_rate, cb.max_abs_yaw_rate))


def out_of_reach(state0: np.ndarray,          # [5] x, y, yaw, v, yaw_rate at the now step
                 size: tuple[float, float],   # agent length, width
                 plan: np.ndarray,            # [T, 3] ego box centre and heading
                 ego_size: tuple[float, float],
                 dt: float, max_accel: float, max_speed: float) -> bool:
    """True when the agent provably cannot touch the ego box at any step: at step t its centre is within
    v0·t + ½·a·t² (speed capped) of where it starts, and two boxes touch only if their centres are within the sum of
    their half diagonals."""
    t = np.arange(1, len(plan) + 1) * dt
    v0 = float(np.clip(state0[3], 0.0, max_speed))
    t_cap = max((max_speed - v0) / max(max_accel, 1e-9), 0.0)
    ta = np.minimum(t, t_cap)
    reach = v0 * ta + 0.5 * max_accel * ta ** 2 + max_speed * (t - ta)
    radius = 0.5 * (np.hypot(*size) + np.hypot(*ego_size))
    dist = np.linalg.norm(plan[:, :2] - state0[None, :2], axis=1)
    return bool(np.all(dist > reach + radius))


def search_reach(problem, node: int, plan: np.ndarray | None = None,
                 config: FeasibilityConfig = FeasibilityConfig()) -> Reach:
    """Search comfort-bounded controls of ``node`` for a trajectory whose box overlaps the ego plan's box with
    footprint IoU above the problem's collision threshold (see the module docstring)."""
    if not 1 <= node < problem.n_nodes:
        raise OmniscsError(f"node {node} is not a non-ego node of scene {problem.traffic.scene_id} "
                           f"(1..{problem.n_nodes - 1})")
    if config.starts < 1 or config.steps < 1 or config.check_every < 1 or not config.init_std:
        raise OmniscsError("feasibility search needs starts, steps and check_every >= 1 and some init_std")
    cfg, cb = problem.config, problem.config.comfort
    if plan is None:
        plan = problem.plan(problem.fitted_np)
    plan = np.asarray(plan, dtype=np.float64)
    track = int(problem.node_tracks[node])
    state0_t = problem.sample.state0[node].to(torch.float32)
    state0 = state0_t.numpy().astype(np.float64)
    size = tuple(float(x) for x in problem.node_sizes_np[node])
    lim = comfort_kinematics(problem)
    threshold = cfg.collision_iou
    if out_of_reach(state0, size, plan, problem.ego_size, problem.traffic.dt, cb.max_lon_accel, lim.max_speed):
        return Reach(node, track, False, 0.0, float("inf"), False, 0, None)

    on_road = bool(config.road and problem.onroad_now[node])
    road_map, frame = problem.traffic.map, problem.frame
    gen = torch.Generator().manual_seed(config.seed)
    groups = np.array_split(np.arange(config.starts), len(config.init_std))
    raw0 = torch.zeros(config.starts, problem.horizon, 2)
    for std, idx in zip(config.init_std, groups):
        raw0[idx] = torch.randn(len(idx), problem.horizon, 2, generator=gen) * float(std)
    raw = raw0.requires_grad_(True)
    opt = torch.optim.Adam([raw], lr=config.lr)
    plan_t = torch.tensor(plan, dtype=torch.float32)
    fe = footprints(plan[:, :2], plan[:, 2], problem.ego_size[0], problem.ego_size[1])  # [T, 4, 2]
    best_iou, best_gap, best_states, steps = 0.0, float("inf"), None, 0

    def roll(r: torch.Tensor) -> torch.Tensor:
        c = bound_controls(r, lim)
        c = torch.stack([soft_clip_accel(c[..., 0], cb.max_lon_accel, -cb.min_lon_accel), c[..., 1]], -1)
        return rollout(state0_t.expand(r.shape[0], 5), c, problem.traffic.dt, lim, cfg.standstill_gradient)

    def offroad(states: torch.Tensor) -> torch.Tensor:  # [S, T] metres off the drivable area
        return road_map.outside_distance(frame.to_world(states[..., :3])[..., :2])

    def stays_on_road(states: np.ndarray) -> np.ndarray:  # [S, T, 5] -> [S] bool, as evaluation.evaluate tests
        if not on_road:
            return np.ones(len(states), dtype=bool)
        xy = frame.to_world_np(states[..., :3])[..., :2].reshape(-1, 2)
        off = (~road_map.is_drivable(xy) & road_map.covers(xy)).reshape(states.shape[:2])
        return ~off.any(-1)

    def measure(states: torch.Tensor, gap: torch.Tensor) -> None:
        nonlocal best_iou, best_gap, best_states
        st = states.detach().numpy().astype(np.float64)
        g = torch.where(torch.from_numpy(stays_on_road(st))[:, None], gap.detach(), torch.full_like(gap, float("inf")))
        best_gap = min(best_gap, float(g.min()))
        hits = torch.nonzero(g < 0).numpy()  # only overlapping (start, step) pairs on the road need the exact IoU
        if len(hits) == 0:
            return
        fa = footprints(st[hits[:, 0], hits[:, 1], :2], st[hits[:, 0], hits[:, 1], 2], size[0], size[1])
        iou = box_iou(fe[hits[:, 1]], fa)
        k = int(np.argmax(iou))
        if iou[k] > best_iou:
            best_iou, best_states = float(iou[k]), st[hits[k, 0]].copy()

    for step in range(1, config.steps + 1):
        states = roll(raw)
        gap = box_gap(states[..., :3], size, plan_t, problem.ego_size).clamp_min(-config.depth_m)  # [S, T]
        loss = (-INTERCEPT_SOFTMIN_M * torch.logsumexp(-gap / INTERCEPT_SOFTMIN_M, -1)).sum()
        if on_road:
            loss = loss + config.offroad_weight * (torch.relu(offroad(states)) ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        steps = step
        if step % config.check_every == 0 or step == config.steps:
            with torch.no_grad():
                states = roll(raw)
                gap = box_gap(states[..., :3], size, plan_t, problem.ego_size)
            measure(states, gap)
            if best_iou > threshold:
                break
    if best_states is None:  # no overlap at all: keep the closest approach for the record
        with torch.no_grad():
            states = roll(raw)
            gap = box_gap(states[..., :3], size, plan_t, problem.ego_size)
        best_states = states[int(gap.min(-1).values.argmin())].numpy().astype(np.float64)
    return Reach(node, track, best_iou > threshold, best_iou, best_gap, True, steps, best_states)


def search_scene(problem, config: FeasibilityConfig = FeasibilityConfig(), stop_at_first: bool = False
                 ) -> list[Reach]:
    """``search_reach`` for every candidate adversary of the scene (``problem.candidates()``, heuristic reachable
    ones first); with ``stop_at_first`` it stops at the first feasible one."""
    plan = problem.plan(problem.fitted_np)
    out = []
    for node, _, _ in problem.candidates():
        out.append(search_reach(problem, node, plan, config))
        if stop_at_first and out[-1].feasible:
            break
    return out
