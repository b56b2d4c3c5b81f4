"""Adversarial optimisation in latent space: L_adv = L_beh + L_app + L_restore, success, plausibility, 1-to-N.

The traffic model first reproduces the log (posterior latents, refined by fitting them to the logged future);
then, per variant, every agent's latent is optimised so that the chosen adversary reaches the planner's
trajectory (L_beh, a log-sum-exp softmax over agents and steps), the rendered scene keeps its look (L_app,
only when a differentiable renderer is supplied) and the latents stay near where they started (L_restore).
A documented plausibility penalty (comfort, collisions with others, leaving the road) is added by default;
set its weights to 0 for the paper's three terms alone. An adversary that fails from the log's latents (and a
standing one from the outset) restarts from a warm start: a search over its control knots finds a comfortable
path into the ego (``BehaviorProblem.intercept``) and its latent is refitted to that path.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import OmniscsError
from omniscs.geometry import wrap_angle
from omniscs.scs.behavior.appearance import AgentTrajectories, AppearanceTerm
from omniscs.scs.behavior.checkpoint import set_threads
from omniscs.scs.behavior.collision import box_iou, footprints, overlapping
from omniscs.scs.behavior.features import SceneSample, build_sample, collate
from omniscs.scs.behavior.kinematics import accelerations
from omniscs.scs.behavior.model import ComfortLimits, Decoded, TrafficModel
from omniscs.scs.behavior.planner import PlannerConfig, check_planner, rule_based_plan
from omniscs.scs.behavior.tracks import TrafficScene

log = logging.getLogger(__name__)

#: Kinds of collision a variant is labelled with (``none`` when no collision was reached).
COLLISION_KINDS = ("cut_in", "head_on", "rear_end", "t_bone", "none")
#: Tracks of these categories never become adversaries (they cannot drive on their own).
NON_ADVERSARY_CATEGORIES = frozenset({"trailer"})
#: Small constant inside square roots so distances are differentiable at 0.
DIST_EPS = 1e-6
#: The collision penalty watches pairs that come within this much of touching during the horizon (metres).
NEAR_PAIR_MARGIN_M = 6.0
#: Temperature of the soft minimum over time of the box gap in the interception and feasibility searches (metres).
INTERCEPT_SOFTMIN_M = 0.3


@dataclass(frozen=True)
class ComfortBounds:
    """What a plausible trajectory stays within (the issue's comfort bounds)."""

    max_lateral_accel: float = 4.9
    """|lateral acceleration| bound, m/s²."""
    max_accel: float = 2.4
    """Forward acceleration bound, m/s²."""
    max_decel: float = 4.05
    """Braking bound (positive number), m/s²."""
    max_yaw_rate: float = 1.0
    """|yaw rate| bound, rad/s."""


@dataclass(frozen=True)
class AdversarialConfig:
    """Latent optimisation of behaviour variants (see PRESETS for the speed/quality trade-off)."""

    iterations: int = 150
    """Largest number of Adam steps per variant (it stops earlier once successful and plausible)."""
    lr: float = 0.05
    """Adam learning rate on the latents."""
    fit_iterations: int = 80
    """Adam steps fitting the latents to the logged future before any variant (reconstruction)."""
    fit_lr: float = 0.05
    """Learning rate of that fit."""
    fit_posterior_weight: float = 0.01
    """Pull toward the posterior mean during the fit (keeps agents with no logged future sensible)."""
    pin_colliding_reconstructions: bool = True
    """Agents whose reconstruction (the latents fitted to the log, before any variant) collides with another
    non-ego agent where the log does not replay their log instead, and are never adversaries: where comfort decoding
    cannot follow a logged manoeuvre (a turn tighter than the comfort yaw rate) the reconstruction runs wide into a
    neighbour the log passes cleanly, and every variant of the scene would start implausible. A collision penalty in
    the fit does not fix it (tried: the overlap stays while the fit error doubles)."""
    beh_weight: float = 1.0
    """Weight of L_beh."""
    restore_weight: float = 0.005
    """Weight of L_restore = sum ||z - z_init||² over non-ego agents."""
    app_weight: float = 1.0
    """Weight of L_app (used only when an AppearanceTerm is supplied)."""
    comfort_decoding: bool = True
    """Decode with accelerations and yaw rates saturated just inside the comfort bounds, so every agent's
    trajectory is comfortable by construction (the latent fit to the log uses the same decoder)."""
    comfort_decoding_margin: float = 0.97
    """Fraction of each comfort bound that comfort decoding saturates at."""
    standstill_gradient: float = 0.3
    """Surrogate gradient through the stop at v = 0 (values unchanged), so standing vehicles can be moved."""
    comfort_weight: float = 1.0
    """Plausibility penalty: weight of squared comfort-bound excess (m²/s⁴, rad²/s²). 0 = off."""
    collision_weight: float = 10.0
    """Plausibility penalty: weight of squared disc overlap with anyone but the ego-adversary pair. 0 = off."""
    offroad_weight: float = 10.0
    """Plausibility penalty: weight of squared distance off the drivable area. 0 = off."""
    penalty_margin: float = 0.9
    """Comfort penalties start at this fraction of each bound, so results stay inside the bounds."""
    clearance_m: float = 0.3
    """Discs of different agents are pushed apart until this gap remains."""
    collision_iou: float = 0.02
    """Boxes overlap (a collision) when their footprint IoU exceeds this."""
    comfort: ComfortBounds = field(default_factory=ComfortBounds)
    """The plausibility bounds."""
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    """The ego's planned trajectory: replay or rule-based."""
    replan_every: int = 10
    """Rule planner: re-plan against the current agent trajectories every this many steps."""
    check_every: int = 5
    """Evaluate success and plausibility every this many steps."""
    stop_on_success: bool = True
    """Stop a variant at the first check that is successful and plausible."""
    now_step: int | None = None
    """Step whose past conditions the model (default: history_steps - 1, the earliest with a full history)."""
    min_future_steps: int = 10
    """Shortest horizon after the now step that a log must offer, steps."""
    reach_accel_long: float = 2.4
    """Reachability: extra forward acceleration an adversary may use, m/s² (braking uses comfort.max_decel)."""
    moving_speed: float = 0.5
    """Candidates at least this fast (m/s) at the now step are tried as adversaries before standing ones."""
    cut_in_offset_m: float = 1.75
    """A same-direction collision is a cut-in when the adversary started at least this far to the side."""
    attempts_per_variant: int = 3
    """A variant whose adversary fails (no collision, or implausible) retries with the next reachable
    candidates, up to this many adversaries in all; the best attempt is kept and all attempts are timed."""
    restarts: int = 1
    """An adversary that finds no collision is optimised again this many times before the next candidate is tried,
    each time from a warm start: its latent refitted to an interception path (BehaviorProblem.intercept). 0 = off."""
    knot_fallback: bool = True
    """When every latent optimisation of an adversary (fitted start and warm starts) fails, take its interception
    path itself (the decoder's control knots found by ``BehaviorProblem.intercept``, through the same comfort
    bounds and bicycle rollout, everyone else on their reconstruction) if that is a successful, plausible
    variant. The traffic model's latent cannot express every comfortable manoeuvre (tight turns across an
    intersection, mostly); such variants are marked ``source: "knots"``. False: latent variants only."""
    warm_start_standing: bool = True
    """Standing candidates (slower than moving_speed) begin with the warm start instead of the fitted latents:
    from the log their braking controls saturate, so L_beh has almost no gradient and they stay parked."""
    intercept_samples: int = 16
    """Interception search: starting points (the adversary's fitted control knots, and random perturbations)."""
    intercept_noise: float = 1.0
    """Interception search: standard deviation of the perturbations of the raw control knots."""
    intercept_iterations: int = 100
    """Interception search: Adam steps on the control knots."""
    intercept_lr: float = 0.15
    """Interception search: Adam learning rate."""
    intercept_effort_weight: float = 0.01
    """Interception search: pull toward the fitted knots (the smallest change of the log that intercepts)."""
    intercept_depth_m: float = 1.0
    """Interception search: overlap with the ego is rewarded up to this penetration depth (about IoU 0.05 for a
    corner contact of two cars, over the success IoU even after the latent only approximates the path)."""
    warm_fit_iterations: int = 150
    """Adam steps fitting the adversary's latent to the interception path."""
    warm_fit_lr: float = 0.1
    """Learning rate of that fit."""
    seed: int = 0
    """Seed of the interception search's random starting points (variants are deterministic for a fixed seed)."""
    time_windows: tuple[tuple[float, float], ...] = ((0.0, 1.0), (0.0, 0.55), (0.45, 1.0))
    """Fractions of the horizon L_beh looks at; variants beyond the number of adversaries use the next window."""
    torch_threads: int = 1
    """torch CPU threads (1: the development machines have 2 shared cores)."""

    @property
    def uses_plausibility_penalty(self) -> bool:
        return bool(self.comfort_weight or self.collision_weight or self.offroad_weight)


#: Named presets: ``fast`` (tests, quick looks), ``balanced`` (default), ``accurate`` (more steps).
PRESETS: dict[str, AdversarialConfig] = {
    "fast": AdversarialConfig(iterations=60, fit_iterations=40, lr=0.08, check_every=4),
    "balanced": AdversarialConfig(),
    "accurate": AdversarialConfig(iterations=400, fit_iterations=200, lr=0.03, check_every=10),
}


def adversarial_preset(name: str, **overrides) -> AdversarialConfig:
    if name not in PRESETS:
        raise OmniscsError(f"unknown preset {name!r}; use one of {list(PRESETS)}")
    return replace(PRESETS[name], **overrides)


# ----------------------------------------------------------------------------- losses
def behaviour_loss(agent_xy: Tensor,  # [N, T, 2] agent box centres
                   plan_xy: Tensor,   # [T, 2] planner's box centre
                   mask: Tensor,      # [N, T] bool: which agents and steps take part
                   ) -> tuple[Tensor, Tensor]:  # L_beh (scalar), weights delta [N, T]
    """L_beh = sum_{i,t} delta_t^i ||T_t^i - T_t^plan||², delta = softmax over (i, t) of -||T_t^i - T_t^plan||.

    The softmax is taken in log space (log-sum-exp), so agents hundreds of metres or kilometres away give
    weights of exactly 0, never 0/0; with no participating entry the loss is 0.
    """
    d2 = ((agent_xy - plan_xy[None]) ** 2).sum(-1)
    if not bool(mask.any()):
        return d2.sum() * 0.0, torch.zeros_like(d2)
    d = torch.sqrt(d2 + DIST_EPS)
    logits = torch.where(mask, -d, torch.full_like(d, -float("inf")))
    # exp(logit - max) / sum(...): the log-sum-exp shift, normalised after the shift so that the weights sum
    # to 1 to float precision even when every distance is ~1e6 m (subtracting the full log-sum-exp would not)
    delta = torch.softmax(logits.reshape(-1), dim=0).reshape(d.shape)
    delta = torch.where(mask, delta, torch.zeros_like(d))
    return (delta * d2).sum(), delta


def restore_loss(z: Tensor, z_init: Tensor, mask: Tensor) -> Tensor:  # [N, Z], [N, Z], [N] bool -> scalar
    """L_restore = sum over masked agents of ||z - z_init||²."""
    return (((z - z_init) ** 2).sum(-1) * mask).sum()


def disc_centres(xyyaw: Tensor,  # [A, T, 3]
                 sizes: Tensor,  # [A, 2] length, width
                 ) -> tuple[Tensor, Tensor]:  # centres [A, 3, T, 2], radii [A]
    """Three discs of radius width/2 along each box's length (front, middle, back): a smooth stand-in for
    the box in the collision penalty."""
    length, width = sizes[:, 0], sizes[:, 1]
    reach = (0.5 * length - 0.5 * width).clamp_min(0.0)
    offsets = torch.stack([-reach, torch.zeros_like(reach), reach], 1)  # [A, 3]
    heading = torch.stack([torch.cos(xyyaw[..., 2]), torch.sin(xyyaw[..., 2])], -1)  # [A, T, 2]
    centres = xyyaw[:, None, :, :2] + offsets[:, :, None, None] * heading[:, None]
    return centres, 0.5 * width


def disc_overlap(centres_a: Tensor, radii_a: Tensor,  # [..., 3, T, 2], [...]
                 centres_b: Tensor, radii_b: Tensor,  # [..., 3, T, 2], [...] (leading dims broadcast)
                 clearance: float) -> Tensor:         # [..., T]
    """Squared overlap, summed over the 3 x 3 disc pairs, of discs a and b grown to keep ``clearance`` apart."""
    diff = centres_a[..., :, None, :, :] - centres_b[..., None, :, :, :]  # [..., 3, 3, T, 2]
    dist = torch.sqrt((diff ** 2).sum(-1) + DIST_EPS)
    need = (radii_a + radii_b + clearance)[..., None, None, None]
    return (torch.nn.functional.relu(need - dist) ** 2).sum((-3, -2))


def box_gap(xyyaw: Tensor,                  # [S, T, 3] agent box centres and headings
            size: tuple[float, float],      # agent length, width
            plan: Tensor,                   # [T, 3] ego box centre and heading
            ego_size: tuple[float, float],  # ego length, width
            ) -> Tensor:                    # [S, T] metres, negative when the boxes overlap
    """Separating-axis gap of two rotated boxes: the largest, over both boxes' axes, of the distance between the
    centres projected on the axis minus both boxes' projected half extents. Positive: apart (a lower bound of the
    distance); negative: overlapping, by minus the penetration depth."""
    d = xyyaw[..., :2] - plan[:, :2]
    rel = xyyaw[..., 2] - plan[:, 2]
    cos_rel, sin_rel = torch.cos(rel).abs(), torch.sin(rel).abs()
    ego_l, ego_w, l, w = 0.5 * ego_size[0], 0.5 * ego_size[1], 0.5 * size[0], 0.5 * size[1]
    ce, se = torch.cos(plan[:, 2]), torch.sin(plan[:, 2])
    ca, sa = torch.cos(xyyaw[..., 2]), torch.sin(xyyaw[..., 2])
    gaps = torch.stack([
        (ce * d[..., 0] + se * d[..., 1]).abs() - ego_l - (l * cos_rel + w * sin_rel),  # ego's heading
        (-se * d[..., 0] + ce * d[..., 1]).abs() - ego_w - (l * sin_rel + w * cos_rel),  # ego's side
        (ca * d[..., 0] + sa * d[..., 1]).abs() - l - (ego_l * cos_rel + ego_w * sin_rel),  # agent's heading
        (-sa * d[..., 0] + ca * d[..., 1]).abs() - w - (ego_l * sin_rel + ego_w * cos_rel),  # agent's side
    ], -1)
    return gaps.max(-1).values


def track_fit_loss(states: Tensor,  # [N, T, >=3] decoded x, y, yaw
                   target: Tensor,  # [N, T, >=3] x, y, yaw to reproduce
                   mask: Tensor,    # [N, T] bool: which entries count
                   ) -> Tensor:     # scalar: mean Huber position error (1 m knee) + (1 - cos) heading error
    err = torch.sqrt(((states[..., :2] - target[..., :2]) ** 2).sum(-1) + DIST_EPS)
    huber = torch.where(err < 1.0, 0.5 * err * err, err - 0.5)
    yaw = 1.0 - torch.cos(states[..., 2] - target[..., 2])
    return ((huber + yaw) * mask).sum() / mask.sum().clamp_min(1)


# ----------------------------------------------------------------------------- results
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


# ----------------------------------------------------------------------------- the problem
def now_and_horizon(traffic: TrafficScene, model_config, config: AdversarialConfig) -> tuple[int, int]:
    """The now step (the model's past ends there) and the horizon after it; a log too short is a user error."""
    s = traffic.n_steps
    now = model_config.history_steps - 1 if config.now_step is None else int(config.now_step)
    now = min(now, s - 1 - config.min_future_steps)
    if now < 0 or s - 1 - now < config.min_future_steps:
        raise OmniscsError(f"scene {traffic.scene_id} is {s} steps ({s * traffic.dt:.1f} s) long; behaviour "
                           f"variants need at least {config.min_future_steps + 1} steps "
                           f"({(config.min_future_steps + 1) * traffic.dt:.1f} s)")
    return now, min(model_config.future_steps, s - 1 - now)


class BehaviorProblem:
    """One scene prepared for adversarial optimisation: model context, fitted latents, planner, candidates."""

    def __init__(self, traffic: TrafficScene, model: TrafficModel, config: AdversarialConfig = AdversarialConfig(),
                 appearance: AppearanceTerm | None = None) -> None:
        check_planner(config.planner.kind)
        mc = model.config
        if abs(traffic.dt - mc.dt) > 1e-3 * mc.dt:
            raise OmniscsError(f"scene {traffic.scene_id} has {traffic.dt:.3f} s steps but the model expects "
                               f"{mc.dt:.3f} s; load it with traffic_from_scene(scene, dt={mc.dt})")
        self.traffic, self.model, self.config, self.appearance = traffic, model, config, appearance
        self.now, self.horizon = now_and_horizon(traffic, mc, config)
        now = self.now
        self.sample: SceneSample = build_sample(traffic, now, mc.history_steps, self.horizon, mc.crop)
        self.batch = collate([self.sample])
        with torch.no_grad():
            self.context, self.edges, self.edge_mask = model.encode_past(self.batch)
            self.z_post, _ = model.posterior(self.context, self.batch, self.edges, self.edge_mask)
        self.n_nodes = self.sample.n_nodes
        self.node_sizes = self.sample.sizes  # [N, 2]
        self.frame = self.sample.frame
        self.node_tracks = self.sample.track_index  # [N], -1 = ego
        node_set = set(int(i) for i in self.node_tracks[1:])
        window = slice(now + 1, now + 1 + self.horizon)
        # Tracks that are not nodes replay their log (static objects, pedestrians, agents that appear later).
        self.replay_tracks = [i for i in range(traffic.n_tracks)
                              if i not in node_set and traffic.present[i, window].any()]
        rxy, ryaw = self.frame.to_scene(traffic.xy[self.replay_tracks, window], traffic.yaw[self.replay_tracks, window])
        self.replay_xyyaw = np.concatenate([rxy, ryaw[..., None]], -1).reshape(len(self.replay_tracks), self.horizon, 3)
        self.replay_present = traffic.present[self.replay_tracks, window].reshape(len(self.replay_tracks), self.horizon)
        self.replay_sizes = traffic.sizes[self.replay_tracks, :2].reshape(-1, 2)
        exy, eyaw = self.frame.to_scene(traffic.ego_xy[window], traffic.ego_yaw[window])
        self.logged_plan = np.concatenate([exy, eyaw[:, None]], -1)  # [T, 3] scene frame
        self.ego_size = (traffic.ego_box.length, traffic.ego_box.width)
        state0 = self.sample.state0.numpy().astype(np.float64)
        self.onroad_now = traffic.map.is_drivable(self.frame.to_world_np(state0[:, :3])[:, :2])  # [N]
        self._log_overlaps = self._logged_overlaps()
        self._intercepts: dict[tuple, tuple[Tensor, float]] = {}
        self.pinned = np.zeros(self.n_nodes, dtype=bool)  # nodes that replay their log (see pin_colliding_...)
        self._pinned_states: Tensor | None = None
        self.z_fit, self.fit_ade = self._fit_latents()
        with torch.no_grad():
            self.fitted = self.decode(self.z_fit)
            self.fitted_knots = model.control_knots(self.context, self.z_fit[None], self.edges, self.edge_mask)[0]
        if config.pin_colliding_reconstructions:
            pinned = self._colliding_reconstructions()
            if pinned.any():
                self.pinned = pinned
                self._pinned_states = self._logged_states()
                with torch.no_grad():
                    self.fitted = self.decode(self.z_fit)

    # -- model ----------------------------------------------------------------------------------------
    @property
    def comfort_limits(self) -> ComfortLimits | None:
        """Decoding limits just inside the comfort bounds (None when comfort decoding is off)."""
        cfg = self.config
        if not cfg.comfort_decoding:
            return None
        cb, m = cfg.comfort, cfg.comfort_decoding_margin
        return ComfortLimits(m * cb.max_accel, m * cb.max_decel, m * cb.max_lateral_accel, m * cb.max_yaw_rate)

    def decode(self, z: Tensor) -> Decoded:  # z [N, Z] -> states [N, T, 5] (scene frame)
        dec = self.model.decode(self.context, z[None], self.batch, self.edges, self.edge_mask, self.horizon,
                                comfort=self.comfort_limits, standstill_gradient=self.config.standstill_gradient)
        states, lon, lat = dec.states[0], dec.longitudinal_accel[0], dec.lateral_accel[0]
        if self._pinned_states is not None:  # pinned nodes replay their log (no gradient, no accelerations)
            pin = torch.from_numpy(self.pinned)[:, None]
            states = torch.where(pin[..., None], self._pinned_states.to(states.dtype), states)
            lon = torch.where(pin, torch.zeros_like(lon), lon)
            lat = torch.where(pin, torch.zeros_like(lat), lat)
        return Decoded(states, lon, lat)

    def _logged_states(self) -> Tensor:  # [N, T, 5]: the log where present, the reconstruction elsewhere
        """Logged future states (speed and yaw rate by finite differences) of the nodes, for pinning."""
        states = self.fitted.states.detach().clone()
        future, mask = self.batch.future[0].to(states.dtype), self.batch.future_mask[0]
        prev = torch.cat([self.sample.state0[:, None, :3].to(states.dtype), future[:, :-1]], 1)
        dt = self.traffic.dt
        speed = torch.linalg.norm(future[..., :2] - prev[..., :2], dim=-1) / dt
        yaw_rate = torch.atan2(torch.sin(future[..., 2] - prev[..., 2]), torch.cos(future[..., 2] - prev[..., 2])) / dt
        logged = torch.cat([future, speed[..., None], yaw_rate[..., None]], -1)
        return torch.where(mask[..., None], logged, states)

    def _colliding_reconstructions(self) -> np.ndarray:  # [N] bool
        """Non-ego nodes whose fitted reconstruction overlaps (IoU > collision_iou) another non-ego agent at a step
        where the log has them apart. Overlaps with the ego are left alone: such an agent is a natural adversary."""
        states = self.fitted.states.numpy().astype(np.float64)
        xyyaw, present, sizes, _ = self._objects(states, self.logged_plan)
        fp = footprints(xyyaw[..., :2], xyyaw[..., 2], sizes[:, 0, None], sizes[:, 1, None])  # [A, T, 4, 2]
        pinned = np.zeros(self.n_nodes, dtype=bool)
        for a, b, t in zip(*self._touching(xyyaw, present, sizes)):
            if a == 0:
                continue
            decoded = [k for k in (a, b) if k < self.n_nodes]
            if decoded and not pinned[decoded].all() and box_iou(fp[a, t], fp[b, t]) > self.config.collision_iou:
                pinned[decoded] = True
        return pinned

    def _fit_latents(self) -> tuple[Tensor, float]:
        """Latents whose decoded trajectories reproduce the logged future (posterior mean, then refined)."""
        cfg = self.config
        target = self.batch.future[0]  # [N, T, 3]
        mask = self.batch.future_mask[0]
        z_post = self.z_post[0]
        z = z_post.clone().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=cfg.fit_lr)
        for _ in range(cfg.fit_iterations):
            loss = (track_fit_loss(self.decode(z).states, target, mask)
                    + cfg.fit_posterior_weight * ((z - z_post) ** 2).sum())
            opt.zero_grad()
            loss.backward()
            opt.step()
        z = z.detach()
        with torch.no_grad():
            states = self.decode(z).states
            err = torch.sqrt(((states[..., :2] - target[..., :2]) ** 2).sum(-1))
            non_ego = mask.clone()
            non_ego[0] = False
            ade = float((err * non_ego).sum() / non_ego.sum().clamp_min(1)) if bool(non_ego.any()) else 0.0
        return z, ade

    # -- warm start -----------------------------------------------------------------------------------
    def _obstacles(self, node: int) -> tuple[Tensor, Tensor, Tensor] | None:
        """Everyone but the ego and ``node`` that ``node`` could meet within the horizon, along their fitted or
        replayed trajectories: disc centres [A, 3, T, 2], radii [A], and where each counts [A, T] (present, and
        not already overlapping ``node`` in the log). None when nobody is near."""
        states = self.fitted.states.numpy().astype(np.float64)
        xyyaw, present, sizes, _ = self._objects(states, self.logged_plan, node)
        state0 = self.sample.state0[node].numpy().astype(np.float64)
        travel = state0[3] * self.horizon * self.traffic.dt + 0.5 * self.config.reach_accel_long * (
            self.horizon * self.traffic.dt) ** 2
        reach = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1])
        near = np.linalg.norm(xyyaw[..., :2] - state0[:2], axis=-1).min(-1) <= travel + reach + reach[node] \
            + NEAR_PAIR_MARGIN_M
        near[[0, node]] = False
        idx = np.flatnonzero(near)
        if not len(idx):
            return None
        centres, radii = disc_centres(torch.from_numpy(xyyaw[idx]).to(torch.float32),
                                      torch.from_numpy(sizes[idx]).to(torch.float32))
        valid = present[idx] & ~self._log_overlaps[node, idx]
        return centres, radii, torch.from_numpy(valid).to(torch.float32)

    def intercept(self, node: int, window: tuple[int, int], plan: np.ndarray,  # [T, 3] ego plan (scene frame)
                  generator: torch.Generator) -> tuple[Tensor, float]:  # states [T, 5], gap m
        """A trajectory of ``node`` that meets the ego plan within horizon steps ``window``, searched directly
        over the decoder's control knots (through the same bounds and bicycle rollout, so it is comfortable when
        decoding is). From the node's fitted knots and ``intercept_samples - 1`` random perturbations of them, Adam
        minimises the soft minimum over the window of the box gap (``box_gap``, down to minus
        ``intercept_depth_m``), a pull toward the fitted knots and, with the plausibility penalty's weights,
        overlap with the others' fitted trajectories and leaving the road. Returns the best sample's states and
        its smallest gap in the window (negative: overlap)."""
        cfg = self.config
        n_samples = cfg.intercept_samples
        base = self.fitted_knots[node]  # [K, 2]
        noise = torch.randn((n_samples, *base.shape), generator=generator) * cfg.intercept_noise
        noise[0] = 0.0
        knots = (base + noise).requires_grad_(True)
        opt = torch.optim.Adam([knots], lr=cfg.intercept_lr)
        state0 = self.sample.state0[node].expand(n_samples, 1, 5)
        target = torch.from_numpy(plan).to(torch.float32)
        in_window = torch.zeros(self.horizon, dtype=torch.bool)
        in_window[window[0]:window[1]] = True
        size = tuple(float(x) for x in self.node_sizes[node])
        obstacles = self._obstacles(node) if cfg.collision_weight else None
        offroad = bool(cfg.offroad_weight and self.onroad_now[node])
        relu = torch.nn.functional.relu
        for it in range(cfg.intercept_iterations + 1):
            states = self.model.roll_knots(knots[:, None], state0, self.horizon, self.comfort_limits,
                                           cfg.standstill_gradient).states[:, 0]  # [S, T, 5]
            gap = box_gap(states, size, target, self.ego_size).clamp_min(-cfg.intercept_depth_m)
            gap = torch.where(in_window, gap, torch.full_like(gap, float("inf")))
            soft = -INTERCEPT_SOFTMIN_M * torch.logsumexp(-gap / INTERCEPT_SOFTMIN_M, -1)  # [S]
            objective = soft + cfg.intercept_effort_weight * ((knots - base) ** 2).mean((1, 2))
            if obstacles is not None:
                centres, radii, valid = obstacles
                mine, my_radius = disc_centres(states[..., :3], self.node_sizes[node].expand(n_samples, 2))
                overlap = disc_overlap(mine[:, None], my_radius[:, None], centres[None], radii[None],
                                       cfg.clearance_m)  # [S, A, T]
                objective = objective + cfg.collision_weight * (overlap * valid).sum((1, 2))
            if offroad:
                outside = self.traffic.map.outside_distance(self.frame.to_world(states[..., :3])[..., :2])  # [S, T]
                objective = objective + cfg.offroad_weight * (relu(outside) ** 2).sum(-1)
            if it == cfg.intercept_iterations:
                break
            opt.zero_grad()
            objective.sum().backward()
            opt.step()
        best = int(torch.argmin(objective.detach()))
        return states[best].detach(), float(gap[best].min().detach())

    def interception_path(self, node: int, window: tuple[int, int], restart: int) -> tuple[Tensor, float]:
        """``intercept`` against the plan for the fitted trajectories, with random starts from a generator seeded
        by (seed, node, window, restart); cached per configuration (warm starts and the knot fallback share it)."""
        cfg = self.config
        key = (cfg, node, tuple(window), restart)
        if key not in self._intercepts:
            seed = np.random.SeedSequence([cfg.seed, node, window[0], window[1], restart]).generate_state(1)[0]
            plan = self.plan(self.fitted.states.numpy().astype(np.float64))
            states, gap = self.intercept(node, window, plan, torch.Generator().manual_seed(int(seed)))
            self._intercepts[key] = (states.detach(), gap)
        return self._intercepts[key]

    def knot_variant(self, node: int, window: tuple[int, int], restart: int, variant_id: str,
                     reachable: bool) -> VariantResult:
        """The variant in which ``node`` follows its interception path (restart ``restart``) and every other
        agent its reconstruction: evaluated, and its losses measured, exactly as an optimised variant."""
        cfg = self.config
        started = time.perf_counter()
        path, _ = self.interception_path(node, window, restart)
        states = self.fitted.states.detach().clone()
        lon, lat = self.fitted.longitudinal_accel.detach().clone(), self.fitted.lateral_accel.detach().clone()
        states[node] = path.to(states.dtype)
        lon[node], lat[node] = accelerations(self.sample.state0[node].to(states.dtype), states[node], self.traffic.dt)
        states_np = states.numpy().astype(np.float64)
        plan_np = self.plan(states_np)
        ev = self.evaluate(states_np, lon.numpy(), lat.numpy(), plan_np, node)
        plan = torch.from_numpy(plan_np).to(torch.float32)
        beh_mask = torch.zeros(self.n_nodes, self.horizon, dtype=torch.bool)
        beh_mask[node, window[0]:window[1]] = True
        with torch.no_grad():
            l_beh = float(behaviour_loss(states[..., :2], plan[:, :2], beh_mask)[0])
            pen = self.plausibility_penalty(Decoded(states, lon, lat), plan, node) \
                if cfg.uses_plausibility_penalty else {}
            l_plaus = float(self.weighted_penalty(pen)) if pen else 0.0
            l_app = None if self.appearance is None else float(self.appearance(self.world_trajectories(states)))
        total = cfg.beh_weight * l_beh + l_plaus + (0.0 if l_app is None else cfg.app_weight * l_app)
        losses = {"L_adv": total, "L_beh": l_beh, "L_app": l_app, "L_restore": 0.0, "L_plaus": l_plaus}
        result = self._result(variant_id, node, window, reachable, states_np, plan_np, ev, losses, 0,
                              time.perf_counter() - started)
        result.source = "knots"
        return result

    def warm_start(self, node: int, window: tuple[int, int], restart: int) -> Tensor:  # -> [N, Z]
        """The fitted latents with ``node``'s latent refitted to an interception path (``intercept``, against the
        plan for the fitted trajectories). The random starts of restart ``restart`` come from a generator seeded by
        (seed, node, window, restart)."""
        cfg = self.config
        target, _ = self.interception_path(node, window, restart)
        mask = torch.zeros(self.n_nodes, self.horizon, dtype=torch.bool)
        mask[node] = True
        full_target = torch.zeros(self.n_nodes, self.horizon, 3)
        full_target[node] = target[:, :3]
        z = self.z_fit.clone().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=cfg.warm_fit_lr)
        for _ in range(cfg.warm_fit_iterations):
            loss = track_fit_loss(self.decode(z).states, full_target, mask)
            opt.zero_grad()
            loss.backward()
            keep = z.grad[node].clone()
            z.grad.zero_()
            z.grad[node] = keep  # only the adversary's latent moves
            opt.step()
        return z.detach()

    # -- planner --------------------------------------------------------------------------------------
    def plan(self, node_states: np.ndarray) -> np.ndarray:  # [N, T, 5] scene frame -> [T, 3] ego plan
        if self.config.planner.kind == "replay":
            return self.logged_plan
        others = np.concatenate([node_states[1:, :, :3], self.replay_xyyaw], 0)
        present = np.concatenate([np.ones((self.n_nodes - 1, self.horizon), bool), self.replay_present], 0)
        sizes = np.concatenate([self.node_sizes[1:].numpy().astype(np.float64), self.replay_sizes], 0)
        ego_state = self.sample.state0[0].numpy().astype(np.float64)
        path = np.vstack([ego_state[None, :2], self.logged_plan[:, :2]])
        logged_speeds = np.linalg.norm(np.diff(path, axis=0), axis=1) / self.traffic.dt
        desired = float(max(logged_speeds.max(initial=0.0), ego_state[3]))
        if desired < 0.1:  # the ego stands still in the log: the planner keeps it there
            return np.repeat(np.array([[ego_state[0], ego_state[1], ego_state[2]]]), self.horizon, 0)
        return rule_based_plan(path, float(ego_state[3]), others, present, sizes, self.ego_size, self.horizon,
                               self.traffic.dt, self.config.planner, desired_speed=desired)

    # -- candidates -----------------------------------------------------------------------------------
    def candidates(self) -> list[tuple[int, bool, float]]:
        """(node, reachable, closest approach m) for every non-ego node that may be an adversary: reachable
        moving ones first, then reachable standing ones (they must pull out), then the rest; each group by how
        close its fitted trajectory comes to the ego plan."""
        plan = self.plan(self.fitted.states.numpy().astype(np.float64))
        state0 = self.sample.state0.numpy().astype(np.float64)
        fitted_all = self.fitted.states.numpy().astype(np.float64)
        out = []
        for k in range(1, self.n_nodes):
            track = int(self.node_tracks[k])
            if self.traffic.categories[track] in NON_ADVERSARY_CATEGORIES or self.pinned[k]:
                continue
            fitted = fitted_all[k]
            closest = float(np.linalg.norm(fitted[:, :2] - plan[:, :2], axis=1).min())
            out.append((k, self.reachable(k, plan), closest, state0[k, 3] >= self.config.moving_speed))
        out.sort(key=lambda c: (not c[1], not c[3], c[2]))
        return [c[:3] for c in out]

    def reachable(self, node: int, plan: np.ndarray) -> bool:
        """Whether ``node`` could touch the ego plan within comfort bounds: around its fitted trajectory, at
        time t it can be 0.5 * a * t² further or (braking, never reversing) shorter along its path, and offset
        sideways by at most min(0.5 * a_lat * t², 0.5 * curvature_max * s²) after travelling s metres (a standing
        car must roll before it can steer); the boxes touch when the ego's extent, seen along and across the
        adversary's heading, meets the adversary's half length or half width."""
        cb = self.config.comfort
        tau = np.arange(1, self.horizon + 1) * self.traffic.dt
        fitted = self.fitted.states[node].numpy().astype(np.float64)  # [T, 5]
        state0 = self.sample.state0[node].numpy().astype(np.float64)
        travelled = np.cumsum(np.linalg.norm(np.diff(np.vstack([state0[None, :2], fitted[:, :2]]), axis=0),
                                             axis=1))
        longer = 0.5 * self.config.reach_accel_long * tau ** 2
        shorter = np.minimum(0.5 * cb.max_decel * tau ** 2, travelled)
        s_max = travelled + longer
        side = np.minimum(0.5 * cb.max_lateral_accel * tau ** 2,
                          0.5 * self.model.config.limits.max_curvature * s_max ** 2)
        c, s = np.cos(fitted[:, 2]), np.sin(fitted[:, 2])
        d = plan[:, :2] - fitted[:, :2]
        along, across = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        length, width = self.node_sizes[node].numpy().astype(np.float64)
        rel = plan[:, 2] - fitted[:, 2]  # the ego's extent seen along / across the adversary
        reach_along = 0.5 * (length + np.abs(np.cos(rel)) * self.ego_size[0] + np.abs(np.sin(rel)) * self.ego_size[1])
        reach_across = 0.5 * (width + np.abs(np.sin(rel)) * self.ego_size[0] + np.abs(np.cos(rel)) * self.ego_size[1])
        ok = (along <= longer + reach_along) & (along >= -shorter - reach_along) & (np.abs(across) <= side + reach_across)
        return bool(ok.any())

    # -- evaluation -----------------------------------------------------------------------------------
    def node_present(self, adversary: int | None = None) -> np.ndarray:  # -> [N, T] bool
        """Where decoded nodes exist: the ego and the adversary always; other agents while their log has them
        (an agent that leaves the log, e.g. at the end of the road, leaves the variant too)."""
        present = self.batch.future_mask[0].numpy().copy()
        present[0] = True
        if adversary is not None:
            present[adversary] = True
        return present

    def _objects(self, node_states: np.ndarray, plan: np.ndarray, adversary: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
        """Everyone in the horizon: ego (0), decoded non-ego nodes, replayed tracks. xyyaw [A, T, 3],
        present [A, T], sizes [A, 2], and a track id per object (-1 = ego)."""
        xyyaw = np.concatenate([plan[None], node_states[1:, :, :3], self.replay_xyyaw], 0)
        present = np.concatenate([self.node_present(adversary), self.replay_present], 0)
        sizes = np.concatenate([np.array([self.ego_size]), self.node_sizes[1:].numpy().astype(np.float64),
                                self.replay_sizes], 0)
        ids = [-1] + [int(self.traffic.track_ids[t]) for t in self.node_tracks[1:]] + \
              [int(self.traffic.track_ids[t]) for t in self.replay_tracks]
        return xyyaw, present, sizes, ids

    def _touching(self, xyyaw: np.ndarray, present: np.ndarray, sizes: np.ndarray  # from _objects
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # object a < object b, step t
        """(a, b, t) where two present objects' centres are close enough for their boxes to touch (within the sum
        of their half diagonals) and the log does not already have them overlapping."""
        reach = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1])
        centre_d = np.linalg.norm(xyyaw[:, None, :, :2] - xyyaw[None, :, :, :2], axis=-1)  # [A, A, T]
        close = (centre_d <= (reach[:, None] + reach[None, :])[..., None]) & present[:, None] & present[None, :]
        close &= np.triu(np.ones(close.shape[:2], bool), 1)[..., None] & ~self._log_overlaps
        return np.nonzero(close)

    def _logged_overlaps(self) -> np.ndarray:  # [A, A, T] bool: pairs that already overlap in the log
        logged = np.zeros((self.n_nodes, self.horizon, 5))
        future = self.batch.future[0].numpy().astype(np.float64)
        logged[:, :, :3] = future
        xyyaw, present, sizes, _ = self._objects(logged, self.logged_plan)
        known = present.copy()
        known[: self.n_nodes] = self.batch.future_mask[0].numpy()
        known[0] = True
        fp = footprints(xyyaw[..., :2], xyyaw[..., 2], sizes[:, 0, None], sizes[:, 1, None])  # [A, T, 4, 2]
        over = overlapping(fp[:, None], fp[None, :])  # [A, A, T]
        return over & known[:, None] & known[None, :]

    def evaluate(self, states: np.ndarray,  # [N, T, 5] decoded (scene frame)
                 lon: np.ndarray, lat: np.ndarray,  # [N, T]
                 plan: np.ndarray,  # [T, 3]
                 adversary: int) -> Evaluation:
        cfg, cb = self.config, self.config.comfort
        xyyaw, present, sizes, ids = self._objects(states, plan, adversary)
        fp = footprints(xyyaw[..., :2], xyyaw[..., 2], sizes[:, 0, None], sizes[:, 1, None])  # [A, T, 4, 2]
        adv_obj = adversary  # node k >= 1 is object k
        iou = box_iou(fp[0], fp[adv_obj])
        hits = np.flatnonzero(iou > cfg.collision_iou)
        collision = int(hits[0]) if len(hits) else None
        violations: list[str] = []
        # comfort of every decoded non-ego agent
        for k in range(1, self.n_nodes):
            track, on = ids[k], present[k]
            if not on.any() or self.pinned[k]:  # pinned nodes replay the log, like tracks that are not nodes
                continue
            checks = ((lon[k, on].max(), cb.max_accel, "longitudinal acceleration"),
                      (-lon[k, on].min(), cb.max_decel, "braking"),
                      (np.abs(lat[k, on]).max(), cb.max_lateral_accel, "lateral acceleration"),
                      (np.abs(states[k, on, 4]).max(), cb.max_yaw_rate, "yaw rate"))
            for value, bound, what in checks:
                if value > bound + 1e-6:
                    unit = "rad/s" if what == "yaw rate" else "m/s²"
                    violations.append(f"track {track} {what} {value:.2f} > {bound:.2f} {unit}")
        # collisions other than ego-adversary that the log does not have (boxes near each other first)
        a_idx, b_idx, t_idx = self._touching(xyyaw, present, sizes)
        hit = overlapping(fp[a_idx, t_idx], fp[b_idx, t_idx]) if len(a_idx) else np.zeros(0, bool)
        reported = set()
        for a, b, t in zip(a_idx[hit], b_idx[hit], t_idx[hit]):
            if (a, b) in reported or {a, b} == {0, adv_obj} or (a >= self.n_nodes and b >= self.n_nodes):
                continue
            if box_iou(fp[a, t], fp[b, t]) > cfg.collision_iou:
                reported.add((a, b))
                who = "ego" if a == 0 else f"track {ids[a]}"
                violations.append(f"collision of {who} and track {ids[b]} at horizon step {t}")
        # leaving the drivable area
        world = self.frame.to_world_np(states[..., :3])
        for k in range(1, self.n_nodes):
            if not self.onroad_now[k] or self.pinned[k]:
                continue
            xy = world[k, :, :2]
            off = np.flatnonzero(~self.traffic.map.is_drivable(xy) & self.traffic.map.covers(xy) & present[k])
            if len(off):
                violations.append(f"track {ids[k]} leaves the drivable area at horizon step {int(off[0])}")
        decoded = slice(1, self.n_nodes)
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

    # -- penalty --------------------------------------------------------------------------------------
    def _near_pairs(self, xyyaw: np.ndarray,  # [A, T, 3] everyone (ego, decoded nodes, replayed tracks)
                    sizes: np.ndarray,        # [A, 2]
                    adversary: int) -> tuple[np.ndarray, np.ndarray]:  # object indices a < b, [P] each
        """Pairs whose collision the penalty watches: close enough to touch soon (NEAR_PAIR_MARGIN_M), at least
        one of them decoded, and not the ego-adversary pair that the optimisation wants to collide."""
        reach = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1])
        d = np.linalg.norm(xyyaw[:, None, :, :2] - xyyaw[None, :, :, :2], axis=-1).min(-1)  # [A, A]
        near = d < reach[:, None] + reach[None, :] + NEAR_PAIR_MARGIN_M
        near &= np.triu(np.ones_like(near), 1)
        near[self.n_nodes:, self.n_nodes:] = False  # replayed tracks cannot move
        near[0, adversary] = False
        return np.nonzero(near)

    def plausibility_penalty(self, dec: Decoded, plan: Tensor, adversary: int) -> dict[str, Tensor]:
        """Differentiable stand-ins for the plausibility checks (comfort, collisions, off-road), unweighted."""
        cfg, cb, m = self.config, self.config.comfort, self.config.penalty_margin
        relu = torch.nn.functional.relu
        node_present = self.node_present(adversary)
        seen = torch.from_numpy(node_present[1:] & ~self.pinned[1:, None]).to(dec.states.dtype)
        lon, lat, w = dec.longitudinal_accel[1:], dec.lateral_accel[1:], dec.states[1:, :, 4]
        comfort = ((relu(lon - m * cb.max_accel) ** 2 + relu(-lon - m * cb.max_decel) ** 2
                    + relu(lat.abs() - m * cb.max_lateral_accel) ** 2 + relu(w.abs() - m * cb.max_yaw_rate) ** 2)
                   * seen).sum()
        zero = comfort * 0.0
        offroad = zero
        if cfg.offroad_weight:
            world = self.frame.to_world(dec.states[1:, :, :3])
            outside = self.traffic.map.outside_distance(world[..., :2])  # [N-1, T]
            onroad = torch.from_numpy(self.onroad_now[1:]).to(outside.dtype)
            offroad = ((relu(outside) ** 2) * onroad[:, None] * seen).sum()
        collision = self.collision_penalty(dec, plan, adversary) if cfg.collision_weight else zero
        return {"comfort": comfort, "collision": collision, "offroad": offroad}

    def weighted_penalty(self, pen: dict[str, Tensor]) -> Tensor:
        """L_plaus: the plausibility penalty's terms with their configured weights."""
        cfg = self.config
        return cfg.comfort_weight * pen["comfort"] + cfg.collision_weight * pen["collision"] \
            + cfg.offroad_weight * pen["offroad"]

    def collision_penalty(self, dec: Decoded, plan: Tensor, adversary: int) -> Tensor:
        """Squared disc overlap (clearance_m apart) of pairs near each other, at least one decoded, except the
        ego-adversary pair and pairs that overlap in the log."""
        node_present = self.node_present(adversary)
        replay = torch.from_numpy(self.replay_xyyaw).to(torch.float32)
        xyyaw = torch.cat([plan[None], dec.states[1:, :, :3], replay], 0)  # [A, T, 3]
        sizes = torch.cat([torch.tensor([self.ego_size], dtype=torch.float32), self.node_sizes[1:],
                           torch.from_numpy(self.replay_sizes).to(torch.float32)], 0)
        present = np.concatenate([node_present, self.replay_present], 0)
        centres, radii = disc_centres(xyyaw, sizes)  # [A, 3, T, 2], [A]
        a_idx, b_idx = self._near_pairs(xyyaw.detach().numpy(), sizes.numpy(), adversary)
        if not len(a_idx):
            return dec.states.sum() * 0.0
        overlap = disc_overlap(centres[a_idx], radii[a_idx], centres[b_idx], radii[b_idx], self.config.clearance_m)
        valid = present[a_idx] & present[b_idx] & ~self._log_overlaps[a_idx, b_idx]
        return (overlap * torch.from_numpy(valid)).sum()

    # -- optimisation ---------------------------------------------------------------------------------
    def world_trajectories(self, states: Tensor) -> AgentTrajectories:
        """Non-ego node trajectories in the world frame, for a renderer (differentiable)."""
        steps = np.arange(self.now + 1, self.now + 1 + self.horizon)
        return AgentTrajectories(
            track_ids=[int(self.traffic.track_ids[t]) for t in self.node_tracks[1:]],
            poses=self.frame.to_world(states[1:, :, :3]), steps=steps,
            timestamps_us=self.traffic.timestamps_us[steps])

    def optimise(self, adversary: int, window: tuple[int, int], variant_id: str, reachable: bool,
                 on_step: Callable[[int], None] | None = None, z_start: Tensor | None = None) -> VariantResult:
        """Optimise all latents so that node ``adversary`` meets the ego plan within horizon steps ``window``,
        starting from ``z_start`` [N, Z] (a warm start) or the fitted latents; L_restore measures the distance to
        the fitted latents, i.e. to the log, either way."""
        cfg = self.config
        started = time.perf_counter()
        z_init = self.z_fit
        z = (z_init if z_start is None else z_start).clone().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=cfg.lr)
        beh_mask = torch.zeros(self.n_nodes, self.horizon, dtype=torch.bool)
        beh_mask[adversary, window[0]:window[1]] = True
        restore_mask = torch.ones(self.n_nodes)
        restore_mask[0] = 0.0  # the ego's latent stays: its trajectory is the planner's
        plan_np = self.plan(self.fitted.states.numpy().astype(np.float64))
        best: tuple | None = None
        it = 0
        for it in range(cfg.iterations + 1):
            final = it == cfg.iterations
            dec = self.decode(z)
            plan = torch.from_numpy(plan_np).to(torch.float32)
            l_beh, _ = behaviour_loss(dec.states[..., :2], plan[:, :2], beh_mask)
            l_restore = restore_loss(z, z_init, restore_mask)
            pen = self.plausibility_penalty(dec, plan, adversary) if cfg.uses_plausibility_penalty else {}
            l_plaus = self.weighted_penalty(pen) if pen else l_beh * 0.0
            l_app = self.appearance(self.world_trajectories(dec.states)) if self.appearance is not None else None
            total = cfg.beh_weight * l_beh + cfg.restore_weight * l_restore + l_plaus
            if l_app is not None:
                total = total + cfg.app_weight * l_app
            if it % cfg.check_every == 0 or final:
                states_np = dec.states.detach().numpy().astype(np.float64)
                eval_plan = self.plan(states_np)
                ev = self.evaluate(states_np, dec.longitudinal_accel.detach().numpy(),
                                   dec.lateral_accel.detach().numpy(), eval_plan, adversary)
                losses = {"L_adv": float(total.detach()), "L_beh": float(l_beh.detach()),
                          "L_app": None if l_app is None else float(l_app.detach()),
                          "L_restore": float(l_restore.detach()), "L_plaus": float(l_plaus.detach())}
                score = (ev.success and ev.plausible, ev.success, -len(ev.violations), -ev.min_distance_m)
                if best is None or score > best[0]:
                    best = (score, states_np, eval_plan, ev, losses, it)
                if cfg.stop_on_success and ev.success and ev.plausible:
                    break
            if final:
                break
            opt.zero_grad()
            total.backward()
            z.grad[0] = 0.0
            opt.step()
            if cfg.planner.kind == "rule" and it % cfg.replan_every == 0:
                plan_np = self.plan(dec.states.detach().numpy().astype(np.float64))
            if on_step:
                on_step(it)
        _, states_np, plan_np, ev, losses, best_it = best
        return self._result(variant_id, adversary, window, reachable, states_np, plan_np, ev, losses, best_it,
                            time.perf_counter() - started)

    # -- results --------------------------------------------------------------------------------------
    def classify(self, states: np.ndarray, plan: np.ndarray, adversary: int, collision: int | None) -> str:
        """cut_in, head_on, rear_end or t_bone from the geometry at the first contact; none without one."""
        if collision is None:
            return "none"
        t = collision
        rel_yaw = float(wrap_angle(states[adversary, t, 2] - plan[t, 2]))
        if abs(rel_yaw) > 0.75 * np.pi:
            return "head_on"
        if abs(rel_yaw) > 0.25 * np.pi:
            return "t_bone"
        state0 = self.sample.state0.numpy().astype(np.float64)
        ego0, adv0 = state0[0], state0[adversary]
        c, s = np.cos(ego0[2]), np.sin(ego0[2])
        d = adv0[:2] - ego0[:2]
        lateral0 = -s * d[0] + c * d[1]
        return "cut_in" if abs(lateral0) >= self.config.cut_in_offset_m else "rear_end"

    def _result(self, variant_id, adversary, window, reachable, states, plan, ev, losses, iterations,
                seconds) -> VariantResult:
        traffic = self.traffic
        last = self.now + self.horizon
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
        world_states = self.frame.to_world_np(states[..., :3])  # [N, T, 3]
        present = self.node_present(adversary)
        for k in range(1, self.n_nodes):
            tid = int(traffic.track_ids[self.node_tracks[k]])
            agents[tid][self.now + 1:] = np.where(present[k][:, None], world_states[k], np.nan)
        original_ego = np.concatenate([traffic.ego_xy[steps], traffic.ego_yaw[steps, None]], -1)
        ego = original_ego.copy()
        ego[self.now + 1:] = self.frame.to_world_np(plan)
        adv_track = int(traffic.track_ids[self.node_tracks[adversary]])
        point = None
        if ev.collision_step is not None:
            t = self.now + 1 + ev.collision_step
            point = 0.5 * (ego[t, :2] + agents[adv_track][t, :2])
        sizes = {int(traffic.track_ids[i]): (float(traffic.sizes[i, 0]), float(traffic.sizes[i, 1]))
                 for i in range(traffic.n_tracks) if int(traffic.track_ids[i]) in agents}
        return VariantResult(
            variant_id=variant_id, scene_id=traffic.scene_id,
            kind=self.classify(states, plan, adversary, ev.collision_step), adversary=adv_track,
            window=(int(window[0]), int(window[1])), reachable=reachable, evaluation=ev, losses=losses,
            iterations=int(iterations), seconds=float(seconds), dt=float(traffic.dt), now_step=self.now,
            steps=steps, timestamps_us=traffic.timestamps_us[steps],
            source_frames=None if traffic.source_frames is None else traffic.source_frames[steps],
            ego=ego, agents=agents, original_ego=original_ego, original_agents=original_agents, sizes=sizes,
            ego_size=self.ego_size, ego_centre_ahead_m=float(traffic.ego_box.centre_ahead_m),
            planner=self.config.planner.kind, collision_point=point,
        )


def variant_schedule(candidates: list[tuple[int, bool, float]], n_variants: int, horizon: int,
                     windows: tuple[tuple[float, float], ...]) -> list[tuple[int, tuple[int, int], bool]]:
    """(adversary node, horizon window, reachable) for each of ``n_variants``: reachable adversaries in
    turn (all adversaries when none is reachable), then again with the next time window."""
    reachable = [c for c in candidates if c[1]]
    pool = reachable or candidates
    out = []
    for k in range(n_variants):
        node, ok, _ = pool[k % len(pool)]
        lo, hi = windows[(k // len(pool)) % len(windows)]
        start, end = int(round(lo * horizon)), max(int(round(hi * horizon)), int(round(lo * horizon)) + 1)
        out.append((node, (start, min(end, horizon)), ok))
    return out


def _outcome(v: VariantResult) -> tuple:
    ev = v.evaluation
    return (ev.success and ev.plausible, ev.success, -len(ev.violations), -ev.min_distance_m)


def optimise_with_fallback(problem: BehaviorProblem, candidates: list[tuple[int, bool, float]], node: int,
                           window: tuple[int, int], reachable: bool, index: int,
                           used: set[tuple[int, tuple[int, int]]] | None = None) -> VariantResult:
    """Optimise variant ``index`` with adversary ``node``; while it finds no collision, restart it from warm starts
    (up to ``restarts``); while it fails (no collision, or implausible), try the next reachable candidates the
    same way (up to ``attempts_per_variant`` adversaries) that no earlier variant used with this window, so
    variants stay distinct. Standing candidates (with ``warm_start_standing``) begin with the warm starts and
    start from the fitted latents last. Keeps the best outcome; its time covers every attempt; records its
    (adversary, window) in ``used``."""
    cfg = problem.config
    used = set() if used is None else used
    others = [(c[0], c[1]) for c in candidates if c[1] and c[0] != node and (c[0], tuple(window)) not in used]
    tries = [(node, reachable)] + others[: max(0, cfg.attempts_per_variant - 1)]
    speed0 = problem.sample.state0[:, 3].numpy()
    best, seconds = None, 0.0
    for attempt, (n, ok) in enumerate(tries, start=1):
        track = int(problem.traffic.track_ids[problem.node_tracks[n]])
        standing = cfg.warm_start_standing and speed0[n] < cfg.moving_speed
        starts = [*range(cfg.restarts), None] if standing else [None, *range(cfg.restarts)]  # None: fitted latents
        for restart in starts:
            began = time.perf_counter()
            z_start = None if restart is None else problem.warm_start(n, window, restart)
            result = problem.optimise(n, window, f"v{index:02d}-track{track}", ok, z_start=z_start)
            seconds += time.perf_counter() - began
            if best is None or _outcome(result) > _outcome(best):
                best = result
            best.attempts = attempt
            if result.success:
                break
        if cfg.knot_fallback and not (best.success and best.plausible) and cfg.restarts > 0:
            began = time.perf_counter()
            fallback = problem.knot_variant(n, window, 0, f"v{index:02d}-track{track}", ok)
            seconds += time.perf_counter() - began
            if fallback.success and fallback.plausible:
                best = fallback
                best.attempts = attempt
        if best.success and best.plausible:
            break
    best.seconds = seconds
    adversary_node = int(np.flatnonzero(problem.traffic.track_ids[problem.node_tracks[1:]] == best.adversary)[0]) + 1
    used.add((adversary_node, tuple(window)))
    return best


def distinct_variants(problem: BehaviorProblem, candidates: list[tuple[int, bool, float]], n_variants: int,
                      progress: Callable[[int, int], None] | None = None) -> list[VariantResult]:
    """Up to ``n_variants`` variants, no two with the same (adversary, time window): the schedule's pairs in
    order, skipping pairs an earlier variant (or its fallback) already used. Fewer come back when the scene
    has fewer distinct pairs."""
    pool = [c for c in candidates if c[1]] or candidates
    windows = problem.config.time_windows
    queue = variant_schedule(candidates, len(pool) * len(windows), problem.horizon, windows)
    results: list[VariantResult] = []
    used: set[tuple[int, tuple[int, int]]] = set()
    while len(results) < n_variants:
        queue = [q for q in queue if (q[0], tuple(q[1])) not in used]
        if not queue:
            log.warning("scene %s: only %d distinct (adversary, window) variants", problem.traffic.scene_id,
                        len(results))
            break
        node, window, reachable = queue.pop(0)
        results.append(optimise_with_fallback(problem, candidates, node, window, reachable, len(results), used))
        if progress:
            progress(len(results), n_variants)
    return results


def generate_variants(traffic: TrafficScene, model: TrafficModel, n_variants: int,
                      config: AdversarialConfig = AdversarialConfig(), appearance: AppearanceTerm | None = None,
                      progress: Callable[[int, int], None] | None = None) -> list[VariantResult]:
    """``n_variants`` behaviour variants of one scene (different adversaries, then different time windows).

    Returns an empty list when no vehicle other than the ego is present at the now step.
    """
    if n_variants < 1:
        raise OmniscsError(f"the number of variants must be at least 1; got {n_variants}")
    previous = set_threads(config.torch_threads)
    try:
        problem = BehaviorProblem(traffic, model, config, appearance)
        candidates = problem.candidates()
        if not candidates:
            log.warning("scene %s: no vehicle besides the ego at step %d; no behaviour variant", traffic.scene_id,
                        problem.now)
            return []
        log.info("scene %s: %d candidate adversaries (%d reachable); latent fit ADE %.2f m", traffic.scene_id,
                 len(candidates), sum(c[1] for c in candidates), problem.fit_ade)
        return distinct_variants(problem, candidates, n_variants, progress)
    finally:
        set_threads(previous)
