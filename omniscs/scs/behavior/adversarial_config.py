"""Configuration of behaviour-variant synthesis: AdversarialConfig and its named presets."""
from __future__ import annotations

from dataclasses import dataclass, field

from omniscs.comfort import VARIANT_COMFORT, ComfortBounds
from omniscs.errors import OmniscsError
from omniscs.overrides import replace_checked
from omniscs.scs.behavior.planner import PlannerConfig

#: Kinds of collision a variant is labelled with (``none`` when no collision was reached).
COLLISION_KINDS = ("cut_in", "head_on", "rear_end", "t_bone", "none")
#: Tracks of these categories never become adversaries (they cannot drive on their own).
NON_ADVERSARY_CATEGORIES = frozenset({"trailer"})
#: The collision penalty watches pairs that come within this much of touching during the horizon (metres).
NEAR_PAIR_MARGIN_M = 6.0


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
    """Weight of L_app (used only when an RenderConsistencyTerm is supplied)."""
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
    comfort: ComfortBounds = VARIANT_COMFORT
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
    """Reachability: extra forward acceleration an adversary may use, m/s² (braking uses comfort.min_lon_accel)."""
    moving_speed: float = 0.5
    """Candidates at least this fast (m/s) at the now step are tried as adversaries before standing ones."""
    cut_in_offset_m: float = 1.75
    """A same-direction collision is a cut-in when the adversary started at least this far to the side."""
    attempts_per_variant: int = 3
    """A variant whose adversary fails (no collision, or implausible) retries with the next reachable
    candidates, up to this many adversaries in all; the best attempt is kept and all attempts are timed."""
    restarts: int = 1
    """An adversary that finds no collision is optimised again this many times before the next candidate is tried,
    each time from a warm start: its latent refitted to an interception path (optimisation.intercept). 0 = off."""
    knot_fallback: bool = True
    """When every latent optimisation of an adversary (fitted start and warm starts) fails, take its interception
    path itself (the decoder's control knots found by ``optimisation.intercept``, through the same comfort
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
    device: str = "cpu"
    """Where the traffic model, map lookups, losses and the optimisation run: "cpu" or "cuda" ("cuda:N"); read when
    a BehaviorProblem is built. An execution setting: it never changes which stored variants are reused."""

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
    """The preset ``name`` with ``overrides`` (AdversarialConfig fields) applied."""
    if name not in PRESETS:
        raise OmniscsError(f"unknown preset {name!r}; use one of {list(PRESETS)}")
    return replace_checked("behaviour optimisation", PRESETS[name], overrides)
