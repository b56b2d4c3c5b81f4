"""Judging a variant: success and plausibility (``evaluate``), the differentiable plausibility penalty, the result."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from omniscs.geometry import wrap_angle
from omniscs.scs.behavior.adversarial_config import NEAR_PAIR_MARGIN_M, AdversarialConfig
from omniscs.scs.behavior.collision import box_iou, footprints, overlapping
from omniscs.scs.behavior.losses import disc_centres, disc_overlap
from omniscs.scs.behavior.model import Decoded
from omniscs.scs.behavior.problem import BehaviorProblem


@dataclass
class Evaluation:
    """Success and plausibility of one set of trajectories."""

    success: bool
    collision_step: int | None  # index into the horizon (0 = first future step)
    iou: np.ndarray  # [T] ego-adversary footprint IoU
    min_distance_m: float
    violations: list[str]
    adversary_accel: tuple[float, float]  # (most negative, largest) longitudinal, m/s²
    adversary_max_lateral: float
    adversary_max_yaw_rate: float
    agents_accel: tuple[float, float]  # over every decoded non-ego agent
    agents_max_lateral: float

    @property
    def plausible(self) -> bool:
        return not self.violations


@dataclass
class VariantResult:
    """One behaviour variant: trajectories of everyone (world frame, steps 0..now+horizon), adversary, outcome."""

    variant_id: str
    scene_id: str
    kind: str
    adversary: int
    window: tuple[int, int]  # horizon steps L_beh looked at
    reachable: bool
    evaluation: Evaluation
    losses: dict[str, float | None]
    iterations: int
    seconds: float
    dt: float
    now_step: int
    steps: np.ndarray  # [S] step indices
    timestamps_us: np.ndarray  # [S]
    source_frames: np.ndarray | None  # [S] scene frames, None when resampled
    ego: np.ndarray  # [S, 3] planned ego (box centre) x, y, yaw
    agents: dict[int, np.ndarray]  # track -> [S, 3], NaN rows where absent
    original_ego: np.ndarray  # [S, 3] logged
    original_agents: dict[int, np.ndarray]  # logged, NaN where absent
    sizes: dict[int, tuple[float, float]]
    ego_size: tuple[float, float]
    ego_centre_ahead_m: float
    planner: str
    collision_point: np.ndarray | None  # [2] world xy of the first contact (mean of the two centres)
    attempts: int = 1  # adversaries tried for this variant (see AdversarialConfig.attempts_per_variant)
    source: str = "latent"  # "latent": optimised latents; "knots": the interception path (knot_fallback)

    @property
    def success(self) -> bool:
        return self.evaluation.success

    @property
    def plausible(self) -> bool:
        return self.evaluation.plausible

    @property
    def collision_step(self) -> int | None:  # index into ``steps``
        c = self.evaluation.collision_step
        return None if c is None else self.now_step + 1 + c


def outcome(v: VariantResult) -> tuple:
    """How good a variant is, as a sort key: successful and plausible, successful, fewer violations, closer."""
    ev = v.evaluation
    return (ev.success and ev.plausible, ev.success, -len(ev.violations), -ev.min_distance_m)


# ----------------------------------------------------------------------------- success and plausibility
def evaluate(problem: BehaviorProblem,
             states: np.ndarray,  # [N, T, 5] decoded (scene frame)
             lon: np.ndarray, lat: np.ndarray,  # [N, T] longitudinal, lateral accelerations
             plan: np.ndarray,  # [T, 3] ego plan
             adversary: int) -> Evaluation:
    """Success (ego and adversary footprints overlap above collision_iou) and the plausibility violations: comfort
    bounds of decoded agents, collisions other than ego-adversary that the log does not have, leaving the road."""
    cfg, cb = problem.config, problem.config.comfort
    xyyaw, present, sizes, ids = problem.objects(states, plan, adversary)
    fp = footprints(xyyaw[..., :2], xyyaw[..., 2], sizes[:, 0, None], sizes[:, 1, None])  # [A, T, 4, 2]
    adv_obj = adversary  # node k >= 1 is object k
    iou = box_iou(fp[0], fp[adv_obj])
    hits = np.flatnonzero(iou > cfg.collision_iou)
    collision = int(hits[0]) if len(hits) else None
    violations: list[str] = []
    # comfort of every decoded non-ego agent
    for k in range(1, problem.n_nodes):
        track, on = ids[k], present[k]
        if not on.any() or problem.pinned[k]:  # pinned nodes replay the log, like tracks that are not nodes
            continue
        checks = ((lon[k, on].max(), cb.max_lon_accel, "longitudinal acceleration"),
                  (-lon[k, on].min(), -cb.min_lon_accel, "braking"),
                  (np.abs(lat[k, on]).max(), cb.max_abs_lat_accel, "lateral acceleration"),
                  (np.abs(states[k, on, 4]).max(), cb.max_abs_yaw_rate, "yaw rate"))
        for value, bound, what in checks:
            if value > bound + 1e-6:
                unit = "rad/s" if what == "yaw rate" else "m/s²"
                violations.append(f"track {track} {what} {value:.2f} > {bound:.2f} {unit}")
    # collisions other than ego-adversary that the log does not have (boxes near each other first)
    a_idx, b_idx, t_idx = problem.touching(xyyaw, present, sizes)
    hit = overlapping(fp[a_idx, t_idx], fp[b_idx, t_idx]) if len(a_idx) else np.zeros(0, bool)
    reported = set()
    for a, b, t in zip(a_idx[hit], b_idx[hit], t_idx[hit]):
        if (a, b) in reported or {a, b} == {0, adv_obj} or (a >= problem.n_nodes and b >= problem.n_nodes):
            continue
        if box_iou(fp[a, t], fp[b, t]) > cfg.collision_iou:
            reported.add((a, b))
            who = "ego" if a == 0 else f"track {ids[a]}"
            violations.append(f"collision of {who} and track {ids[b]} at horizon step {t}")
    # leaving the drivable area
    road = problem.traffic.map
    world = problem.frame.to_world_np(states[..., :3])
    for k in range(1, problem.n_nodes):
        if not problem.onroad_now[k] or problem.pinned[k]:
            continue
        xy = world[k, :, :2]
        off = np.flatnonzero(~road.is_drivable(xy) & road.covers(xy) & present[k])
        if len(off):
            violations.append(f"track {ids[k]} leaves the drivable area at horizon step {int(off[0])}")
    decoded = slice(1, problem.n_nodes)
    lon_seen = np.where(present[decoded], lon[decoded], 0.0)
    lat_seen = np.where(present[decoded], lat[decoded], 0.0)
    return Evaluation(
        success=collision is not None, collision_step=collision, iou=iou,
        min_distance_m=float(np.linalg.norm(xyyaw[0, :, :2] - xyyaw[adv_obj, :, :2], axis=1).min()),
        violations=violations,
        adversary_accel=(float(lon[adversary].min()), float(lon[adversary].max())),
        adversary_max_lateral=float(np.abs(lat[adversary]).max()),
        adversary_max_yaw_rate=float(np.abs(states[adversary, :, 4]).max()),
        agents_accel=(float(lon_seen.min(initial=0.0)), float(lon_seen.max(initial=0.0))),
        agents_max_lateral=float(np.abs(lat_seen).max(initial=0.0)),
    )


# ----------------------------------------------------------------------------- the plausibility penalty
def near_pairs(problem: BehaviorProblem,
               xyyaw: np.ndarray,  # [A, T, 3] everyone (ego, decoded nodes, replayed tracks)
               sizes: np.ndarray,  # [A, 2]
               adversary: int) -> tuple[np.ndarray, np.ndarray]:  # object indices a < b, [P] each
    """Pairs whose collision the penalty watches: close enough to touch soon (NEAR_PAIR_MARGIN_M), at least
    one of them decoded, and not the ego-adversary pair that the optimisation wants to collide."""
    reach = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1])
    d = np.linalg.norm(xyyaw[:, None, :, :2] - xyyaw[None, :, :, :2], axis=-1).min(-1)  # [A, A]
    near = d < reach[:, None] + reach[None, :] + NEAR_PAIR_MARGIN_M
    near &= np.triu(np.ones_like(near), 1)
    near[problem.n_nodes:, problem.n_nodes:] = False  # replayed tracks cannot move
    near[0, adversary] = False
    return np.nonzero(near)


def plausibility_penalty(problem: BehaviorProblem, dec: Decoded,
                         plan: Tensor,  # [T, 3] ego plan (scene frame)
                         adversary: int) -> dict[str, Tensor]:
    """Differentiable stand-ins for the plausibility checks (comfort, collisions, off-road), unweighted."""
    cfg, cb, m = problem.config, problem.config.comfort, problem.config.penalty_margin
    relu = torch.nn.functional.relu
    node_present = problem.node_present(adversary)
    seen = torch.from_numpy(node_present[1:] & ~problem.pinned[1:, None]).to(problem.device, dec.states.dtype)
    lon, lat, w = dec.longitudinal_accel[1:], dec.lateral_accel[1:], dec.states[1:, :, 4]
    comfort = ((relu(lon - m * cb.max_lon_accel) ** 2 + relu(-lon + m * cb.min_lon_accel) ** 2
                + relu(lat.abs() - m * cb.max_abs_lat_accel) ** 2 + relu(w.abs() - m * cb.max_abs_yaw_rate) ** 2)
               * seen).sum()
    zero = comfort * 0.0
    offroad = zero
    if cfg.offroad_weight:
        world = problem.frame.to_world(dec.states[1:, :, :3])
        outside = problem.traffic.map.outside_distance(world[..., :2])  # [N-1, T]
        onroad = torch.from_numpy(problem.onroad_now[1:]).to(problem.device, outside.dtype)
        offroad = ((relu(outside) ** 2) * onroad[:, None] * seen).sum()
    collision = collision_penalty(problem, dec, plan, adversary) if cfg.collision_weight else zero
    return {"comfort": comfort, "collision": collision, "offroad": offroad}


def weighted_penalty(config: AdversarialConfig, pen: dict[str, Tensor]) -> Tensor:
    """L_plaus: the plausibility penalty's terms with their configured weights."""
    return config.comfort_weight * pen["comfort"] + config.collision_weight * pen["collision"] \
        + config.offroad_weight * pen["offroad"]


def collision_penalty(problem: BehaviorProblem, dec: Decoded,
                      plan: Tensor,  # [T, 3] ego plan (scene frame)
                      adversary: int) -> Tensor:
    """Squared disc overlap (clearance_m apart) of pairs near each other, at least one decoded, except the
    ego-adversary pair and pairs that overlap in the log."""
    device = problem.device
    node_present = problem.node_present(adversary)
    replay = torch.from_numpy(problem.replay_xyyaw).to(device, torch.float32)
    xyyaw = torch.cat([plan[None], dec.states[1:, :, :3], replay], 0)  # [A, T, 3]
    sizes = torch.cat([torch.tensor([problem.ego_size], dtype=torch.float32, device=device), problem.node_sizes[1:],
                       torch.from_numpy(problem.replay_sizes).to(device, torch.float32)], 0)
    present = np.concatenate([node_present, problem.replay_present], 0)
    centres, radii = disc_centres(xyyaw, sizes)  # [A, 3, T, 2], [A]
    a_idx, b_idx = near_pairs(problem, xyyaw.detach().cpu().numpy(), sizes.cpu().numpy(), adversary)
    if not len(a_idx):
        return dec.states.sum() * 0.0
    overlap = disc_overlap(centres[a_idx], radii[a_idx], centres[b_idx], radii[b_idx], problem.config.clearance_m)
    valid = present[a_idx] & present[b_idx] & ~problem.log_overlaps[a_idx, b_idx]
    return (overlap * torch.from_numpy(valid).to(device)).sum()


# ----------------------------------------------------------------------------- the result
def classify(problem: BehaviorProblem, states: np.ndarray, plan: np.ndarray, adversary: int,
             collision: int | None) -> str:
    """cut_in, head_on, rear_end or t_bone from the geometry at the first contact; none without one."""
    if collision is None:
        return "none"
    t = collision
    rel_yaw = float(wrap_angle(states[adversary, t, 2] - plan[t, 2]))
    if abs(rel_yaw) > 0.75 * np.pi:
        return "head_on"
    if abs(rel_yaw) > 0.25 * np.pi:
        return "t_bone"
    ego0, adv0 = problem.state0_np[0], problem.state0_np[adversary]
    c, s = np.cos(ego0[2]), np.sin(ego0[2])
    d = adv0[:2] - ego0[:2]
    lateral0 = -s * d[0] + c * d[1]
    return "cut_in" if abs(lateral0) >= problem.config.cut_in_offset_m else "rear_end"


def variant_result(problem: BehaviorProblem, variant_id: str, adversary: int, window: tuple[int, int],
                   reachable: bool,
                   states: np.ndarray,  # [N, T, 5] the variant's node states (scene frame)
                   plan: np.ndarray,    # [T, 3] the ego plan against them
                   ev: Evaluation, losses: dict[str, float | None], iterations: int,
                   seconds: float) -> VariantResult:
    """The variant in the world frame over steps 0..now+horizon: logged where nothing changed, decoded after."""
    traffic = problem.traffic
    now = problem.now
    last = now + problem.horizon
    steps = np.arange(0, last + 1)
    nan = np.full((len(steps), 3), np.nan)

    def logged(i: int) -> np.ndarray:
        out = nan.copy()
        p = traffic.present[i, steps]
        out[p, :2] = traffic.xy[i, steps[p]]
        out[p, 2] = traffic.yaw[i, steps[p]]
        return out

    original_agents = {int(traffic.track_ids[i]): logged(i) for i in range(traffic.n_tracks)
                       if traffic.present[i, steps].any()}
    agents = {k: v.copy() for k, v in original_agents.items()}
    world_states = problem.frame.to_world_np(states[..., :3])  # [N, T, 3]
    present = problem.node_present(adversary)
    for k in range(1, problem.n_nodes):
        tid = int(traffic.track_ids[problem.node_tracks[k]])
        agents[tid][now + 1:] = np.where(present[k][:, None], world_states[k], np.nan)
    original_ego = np.concatenate([traffic.ego_xy[steps], traffic.ego_yaw[steps, None]], -1)
    ego = original_ego.copy()
    ego[now + 1:] = problem.frame.to_world_np(plan)
    adv_track = int(traffic.track_ids[problem.node_tracks[adversary]])
    point = None
    if ev.collision_step is not None:
        t = now + 1 + ev.collision_step
        point = 0.5 * (ego[t, :2] + agents[adv_track][t, :2])
    sizes = {int(traffic.track_ids[i]): (float(traffic.sizes[i, 0]), float(traffic.sizes[i, 1]))
             for i in range(traffic.n_tracks) if int(traffic.track_ids[i]) in agents}
    return VariantResult(
        variant_id=variant_id, scene_id=traffic.scene_id,
        kind=classify(problem, states, plan, adversary, ev.collision_step), adversary=adv_track,
        window=(int(window[0]), int(window[1])), reachable=reachable, evaluation=ev, losses=losses,
        iterations=int(iterations), seconds=float(seconds), dt=float(traffic.dt), now_step=now,
        steps=steps, timestamps_us=traffic.timestamps_us[steps],
        source_frames=None if traffic.source_frames is None else traffic.source_frames[steps],
        ego=ego, agents=agents, original_ego=original_ego, original_agents=original_agents, sizes=sizes,
        ego_size=problem.ego_size, ego_centre_ahead_m=float(traffic.ego_box.centre_ahead_m),
        planner=problem.config.planner.kind, collision_point=point,
    )
