"""NAVSIM v2's extended PDM score (EPDMS) of a closed-loop run, scored beside PDMS on the same executed windows: the
multipliers NC, DAC, DDC, TLC and the weighted EP, TTC, LK, HC, EC, with NAVSIM's human-agent filter. Weights and
thresholds live in one config (``EPDMSConfig``, NAVSIM's values)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from omniscs.closedloop import metrics
from omniscs.comfort import NAVSIM_COMFORT
from omniscs.errors import ValidationError
from omniscs.geometry import wrap_angle
from omniscs.scs.behavior.collision import footprints, overlapping

#: How TTC may be scored: "ours" (PDMS's check, ``metrics.ttc_violated_at``) or "navsim" (NAVSIM's).
TTC_MODES = ("ours", "navsim")
#: The sub-scores, the multipliers among them and the weighted ones (NAVSIM v2's EPDMS).
SUB_SCORES = ("nc", "dac", "ddc", "tlc", "ep", "ttc", "lk", "hc", "ec")
MULTIPLIERS = ("nc", "dac", "ddc", "tlc")
WEIGHTED = ("ep", "ttc", "lk", "hc", "ec")
#: What the report says about what cannot be scored here.
TLC_NOTE = "no traffic lights in the world: TLC is 1"
NO_LANES_NOTE = "no lane map: DDC and LK are 1"
NO_ROUTE_LANE_NOTE = "no lane carries the route: LK is 1"


@dataclass(frozen=True)
class EPDMSConfig:
    """Weights and thresholds of EPDMS. Defaults are NAVSIM v2's (its ``pdm_scorer.yaml`` and
    ``pdm_comfort_metrics.py``) except where a field says "ours": what NAVSIM reads from a map we do not have."""

    ep_weight: float = 5.0
    """Weight of ego progress (EP)."""
    ttc_weight: float = 5.0
    """Weight of time to collision within bound (TTC)."""
    lk_weight: float = 2.0
    """Weight of lane keeping (LK)."""
    hc_weight: float = 2.0
    """Weight of history comfort (HC)."""
    ec_weight: float = 2.0
    """Weight of extended (two-frame) comfort (EC)."""
    ttc: str = "ours"
    """How TTC is scored: "ours" (the PDMS check: ego and every agent move at constant velocity in 0.1 s steps up to
    0.9 s, 0.05 m/s stopped threshold) or "navsim" (only the ego moves, along its heading at its speed; agents stand
    at their recorded future positions 0 / 0.3 / 0.6 / 0.9 s on; 0.005 m/s stopped threshold)."""
    driving_direction_horizon_s: float = 1.0
    """DDC sums the distance driven in oncoming traffic over trailing windows of this length (s)."""
    driving_direction_compliance_m: float = 2.0
    """Oncoming distance (m) below which DDC is 1."""
    driving_direction_violation_m: float = 6.0
    """Oncoming distance (m) below which DDC is 0.5 (0 at or above it)."""
    lane_keeping_deviation_m: float = 0.5
    """LK: lateral distance (m) from the route's lane centreline beyond which a pose deviates."""
    lane_keeping_window_s: float = 2.0
    """LK is 0 when the ego deviates continuously for at least this long (s)."""
    lane_half_width_m: float = 1.75
    """(Ours.) A pose lies in a lane when within this distance (m) of its centreline: our road maps carry centrelines
    without widths (the procedural world's lanes are 3.2 to 3.7 m wide); NAVSIM tests its lane polygons."""
    history_s: float = 1.5
    """HC: seconds of the ego's own past prepended to each window (NAVSIM: 1.5 s of the human's past)."""
    ec_interval_s: float = 0.5
    """EC compares the plan issued at a step with the one issued this long before (NAVSIM's frame interval, s)."""
    ec_max_rms_accel: float = 0.7
    """EC: largest RMS difference of acceleration magnitude between the two plans (m/s²)."""
    ec_max_rms_jerk: float = 0.5
    """EC: largest RMS difference of jerk (m/s³)."""
    ec_max_rms_yaw_rate: float = 0.1
    """EC: largest RMS difference of yaw rate (rad/s)."""
    ec_max_rms_yaw_accel: float = 0.1
    """EC: largest RMS difference of yaw acceleration (rad/s²)."""
    navsim_stopped_speed: float = 5e-3
    """NAVSIM's TTC: an ego slower than this (m/s) is not checked."""
    navsim_ttc_times_s: tuple[float, ...] = (0.0, 0.3, 0.6, 0.9)
    """NAVSIM's TTC: look-ahead times (s) at which the projected ego meets the agents' recorded positions."""
    ahead_deg: float = 30.0
    """NAVSIM's TTC (nuPlan's ``is_agent_ahead``): an agent is ahead when the angle between the ego's heading and the
    ego-to-agent direction is below this (degrees)."""
    behind_deg: float = 150.0
    """... and behind when that angle is above this (degrees)."""
    human_filter: tuple[str, ...] = ("nc", "dac", "ddc", "tlc", "ttc", "lk")
    """Sub-scores the human-agent filter applies to: where the reference (logged) ego scores 0 over the same window,
    the policy scores 1. NAVSIM's filter covers every sub-score of its scorer, but there the human's EP is 1 by
    construction (normalised by itself), its HC is 1 (scored without history) and EC is computed after the filter,
    so these three never change; this default says so."""

    def __post_init__(self):
        if self.ttc not in TTC_MODES:
            raise ValidationError(f"EPDMS TTC mode {self.ttc!r} is unknown; choose one of {', '.join(TTC_MODES)}")
        unknown = [n for n in self.human_filter if n not in SUB_SCORES]
        if unknown:
            raise ValidationError(f"human_filter names {unknown}; choose among {', '.join(SUB_SCORES)}")
        positive = {name: getattr(self, name) for name in (
            "driving_direction_horizon_s", "lane_keeping_window_s", "lane_half_width_m", "ec_interval_s")}
        weights = [self.ep_weight, self.ttc_weight, self.lk_weight, self.hc_weight, self.ec_weight]
        if any(not (np.isfinite(v) and v > 0) for v in positive.values()) or \
                any(not (np.isfinite(w) and w >= 0) for w in weights) or sum(weights) <= 0:
            raise ValidationError("EPDMS config: windows and lane width must be positive, weights >= 0 with a "
                                  "positive sum")
        if any(not (np.isfinite(t) and t >= 0) for t in self.navsim_ttc_times_s) or not self.navsim_ttc_times_s:
            raise ValidationError("EPDMS config: navsim_ttc_times_s must be finite look-ahead times >= 0 s")

    def weights(self) -> dict[str, float]:
        """Weight of each weighted sub-score, by name."""
        return {"ep": self.ep_weight, "ttc": self.ttc_weight, "lk": self.lk_weight, "hc": self.hc_weight,
                "ec": self.ec_weight}


@dataclass(frozen=True, eq=False)
class EPDMSScores:
    """EPDMS of one run: per-step sub-scores after the human-agent filter (arrays [T]) and the run's mean."""

    values: dict
    """Sub-score name (``SUB_SCORES``) -> [T] value of each step's window after the human filter."""
    policy: dict
    """Sub-score name -> [T] the policy's own value, before the filter."""
    filtered: dict
    """Sub-score name -> [T] bool: the reference ego failed it (0) over the same window, so the policy scores 1."""
    epdms: np.ndarray
    """EPDMS of each step: NC DAC DDC TLC (5 EP + 5 TTC + 2 LK + 2 HC + 2 EC) / 16."""
    epdms_mean: float | None
    """Mean EPDMS over the steps (the run's EPDMS); None for an empty run."""
    ttc_mode: str
    """"ours" or "navsim" (``EPDMSConfig.ttc``)."""
    has_lanes: bool
    """Whether a lane map was there (without one, DDC and LK are 1)."""
    lane_keeping_scored: bool
    """Whether LK was scored (a lane map with a lane that carries the route)."""
    human_filter: bool
    """Whether the trace had a reference ego (without one nothing is filtered)."""
    ec_compared: np.ndarray
    """[T] bool: the step's EC compared two plans (no plan at the step or 0.5 s before: EC is 1)."""

    def to_dict(self) -> dict:
        """Plain JSON-able values (never NaN or Inf): the run's EPDMS, the mean and minimum of each sub-score, the
        fraction of steps each was filtered, what could not be scored, and the per-step values."""
        steps = len(self.epdms)
        out = {"epdms": _json_float(self.epdms_mean), "ttc_mode": self.ttc_mode, "has_lanes": bool(self.has_lanes),
               "lane_keeping_scored": bool(self.lane_keeping_scored), "human_filter": bool(self.human_filter),
               "traffic_lights": TLC_NOTE, "ec_compared_steps": int(np.sum(self.ec_compared)), "steps": steps}
        notes = [TLC_NOTE]
        if not self.has_lanes:
            notes.append(NO_LANES_NOTE)
        elif not self.lane_keeping_scored:
            notes.append(NO_ROUTE_LANE_NOTE)
        if not self.human_filter:
            notes.append("no reference ego: no human-agent filter")
        out["notes"] = notes
        for name in SUB_SCORES:
            v = self.values[name]
            out[f"{name}_mean"] = _json_float(np.mean(v)) if steps else None
            out[f"{name}_min"] = _json_float(np.min(v)) if steps else None
        out["filtered_fraction"] = {name: (_json_float(np.mean(self.filtered[name])) if steps else None)
                                    for name in SUB_SCORES}
        out["per_step"] = {name: [_json_float(v) for v in self.values[name]] for name in SUB_SCORES}
        out["per_step"]["epdms"] = [_json_float(v) for v in self.epdms]
        out["per_step"]["filtered"] = {name: [bool(f) for f in self.filtered[name]] for name in SUB_SCORES
                                       if self.filtered[name].any()}
        return out


def _json_float(value) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


# ----------------------------------------------------------------------------- scoring
def score_with_epdms(trace: "metrics.RunTrace", horizon_s: float = 4.0,
                     config: EPDMSConfig | None = None) -> "metrics.RunScores":
    """PDMS and HD-Score (``metrics.score_run``) with NAVSIM v2's EPDMS on the same windows in ``.epdms``
    (config default ``EPDMSConfig()``); the EPDMS does not change any PDMS or HD-Score figure."""
    scores = metrics.score_run(trace, horizon_s)
    return replace(scores, epdms=score_epdms(trace, scores, config if config is not None else EPDMSConfig()))


def score_epdms(trace: "metrics.RunTrace", pdms: "metrics.RunScores",
                config: EPDMSConfig = EPDMSConfig()) -> EPDMSScores:
    """EPDMS of a run over the same per-step windows as its PDMS (``pdms``, from ``metrics.score_run``).

    Per step t, over the executed window t .. t + horizon_s / dt:
    - NC, DAC, EP: PDMS's values of the window.
    - DDC: per pose, the distance driven since the previous pose counts as oncoming when the ego centre lies in a lane
      (within ``lane_half_width_m`` of its centreline) and every lane it lies in runs against the ego's heading; the
      most oncoming distance over trailing 1 s sums (NAVSIM: 11 increments at 0.1 s) gives 1 below 2 m, 0.5 below
      6 m, else 0. NAVSIM counts a centre outside every on-route lane polygon and skips intersections; our maps
      carry centrelines only, so a junction, where connectors run in all directions, rarely counts as oncoming.
    - TLC: 1. Our procedural intersections have no traffic lights (nothing is invented).
    - TTC: PDMS's window value (``ttc="ours"``), or ``navsim_ttc`` (``ttc="navsim"``).
    - LK: the lateral distance from the ego centre to the nearest centreline of the route's lanes (the lanes that carry
      the route in its direction); 0 when it exceeds 0.5 m on at least ceil(2 s / dt) consecutive poses. NAVSIM skips
      poses in intersections (we have no junction polygons: the route's junction connectors count as its lanes).
    - HC: nuPlan's comfort (``metrics.comfortable``, NAVSIM's bounds) on the window with up to 1.5 s of the ego's own
      past prepended (NAVSIM prepends the human's 1.5 s past to the planned trajectory).
    - EC: the plan issued at t against the plan issued ``ec_interval_s`` earlier, on their common times: RMS
      differences of acceleration magnitude, jerk, yaw rate and yaw acceleration within 0.7, 0.5, 0.1, 0.1; 1 when
      either step issued no plan (direct controls) or they share fewer than 4 waypoints. Derivatives are finite
      differences at the plan's spacing (NAVSIM: Savitzky-Golay on its 0.1 s simulated states).
    - Human-agent filter: each sub-score in ``config.human_filter`` that the reference ego (``trace.reference_ego``,
      against ``trace.reference_agents``) scores 0 over the same window is 1 for the policy (NAVSIM's rule: only 0,
      not 0.5, is filtered). Without a reference ego nothing is filtered.
    - EPDMS_t = NC DAC DDC TLC (5 EP + 5 TTC + 2 LK + 2 HC + 2 EC) / 16; the run's EPDMS is the mean over steps.
    """
    steps = trace.steps
    window = int(round(pdms.horizon_s / trace.dt))
    lanes = usable_lanes(trace.lane_centrelines)
    policy = {"nc": np.asarray(pdms.nc, dtype=np.float64), "dac": np.asarray(pdms.dac, dtype=np.float64),
              "ep": np.asarray(pdms.ep, dtype=np.float64), "tlc": np.ones(steps)}
    if config.ttc == "ours":
        policy["ttc"] = np.asarray(pdms.ttc, dtype=np.float64)
    else:
        policy["ttc"] = navsim_ttc(trace.ego, trace.ego_speed, trace.ego_size, trace.agents, trace.agent_sizes,
                                   np.asarray(pdms.offroad, dtype=bool), trace.dt, window, config)
    policy["ddc"] = driving_direction_compliance(trace.ego, lanes, trace.dt, window, config)
    policy["lk"], lk_scored = lane_keeping(trace.ego, lanes, trace.route, trace.dt, window, config)
    policy["hc"] = history_comfort(trace.ego, trace.dt, window, config)
    policy["ec"], ec_compared = extended_comfort(trace.ego, trace.plans, trace.plan_dt, trace.dt, config)

    filtered = {name: np.zeros(steps, dtype=bool) for name in SUB_SCORES}
    if trace.reference_ego is not None and steps:
        human = reference_scores(trace, lanes, window, config)
        for name, value in human.items():
            filtered[name] = value == 0.0
    values = {name: np.where(filtered[name], 1.0, policy[name]) for name in SUB_SCORES}
    weights = config.weights()
    multiplier = np.prod([values[name] for name in MULTIPLIERS], axis=0) if steps else np.zeros(0)
    weighted = sum(weights[name] * values[name] for name in WEIGHTED) / sum(weights.values())
    epdms = multiplier * weighted if steps else np.zeros(0)
    return EPDMSScores(values=values, policy=policy, filtered=filtered, epdms=epdms,
                       epdms_mean=float(np.mean(epdms)) if steps else None, ttc_mode=config.ttc,
                       has_lanes=bool(lanes), lane_keeping_scored=lk_scored,
                       human_filter=trace.reference_ego is not None, ec_compared=ec_compared)


def reference_scores(trace: "metrics.RunTrace", lanes: tuple, window: int, config: EPDMSConfig
                     ) -> dict[str, np.ndarray]:
    """The reference ego's own sub-scores (those in ``config.human_filter`` that it can fail) over each step's
    window: it drives ``trace.reference_ego`` among ``trace.reference_agents`` (or the run's agents), its speed
    from its positions. Name -> [T]."""
    ego = trace.reference_ego
    steps, (length, width) = len(ego), trace.ego_size
    speed = path_speed(ego, trace.dt)
    if trace.reference_agents is not None:
        agents, velocity = trace.reference_agents, track_velocity(trace.reference_agents, trace.dt)
    else:
        agents, velocity = trace.agents, trace.agent_velocity
    velocity = np.where(np.isfinite(velocity), velocity, 0.0)
    wanted = set(config.human_filter)
    out: dict[str, np.ndarray] = {}
    if "nc" in wanted:
        now = np.array([metrics.contact_nc(metrics.collisions_at(
            ego[t], trace.ego_size, speed[t], agents[:, t], trace.agent_sizes, trace.agent_kinds, velocity[:, t]))
            for t in range(steps)])
        out["nc"] = _window_reduce(now, window, np.min)
    offroad = np.zeros(steps, dtype=bool)
    if trace.drivable is not None:
        corners = footprints(ego[:, :2], ego[:, 2], length, width)
        offroad = ~metrics._drivable_mask(trace.drivable, corners.reshape(-1, 2)).reshape(steps, 4).all(-1)
    if "dac" in wanted:
        out["dac"] = 1.0 - _window_reduce(offroad.astype(np.float64), window, np.max)
    if "ttc" in wanted:
        if config.ttc == "ours":
            now = np.array([metrics.ttc_violated_at(ego[t], trace.ego_size, speed[t], agents[:, t],
                                                    trace.agent_sizes, velocity[:, t]) for t in range(steps)])
            out["ttc"] = 1.0 - _window_reduce(now.astype(np.float64), window, np.max)
        else:
            out["ttc"] = navsim_ttc(ego, speed, trace.ego_size, agents, trace.agent_sizes, offroad, trace.dt,
                                    window, config)
    if "ddc" in wanted:
        out["ddc"] = driving_direction_compliance(ego, lanes, trace.dt, window, config)
    if "lk" in wanted:
        out["lk"] = lane_keeping(ego, lanes, trace.route, trace.dt, window, config)[0]
    if "hc" in wanted:
        out["hc"] = history_comfort(ego, trace.dt, window, config)
    if "tlc" in wanted:
        out["tlc"] = np.ones(steps)
    # EP: the reference is what the policy's progress is measured against (its own EP is 1); EC: it issues no plans
    for name in ("ep", "ec"):
        if name in wanted:
            out[name] = np.ones(steps)
    return out


def _window_reduce(now: np.ndarray, window: int, reduce) -> np.ndarray:  # [T] -> [T] over t .. t + window
    steps = len(now)
    return np.array([reduce(now[t:min(steps - 1, t + window) + 1]) for t in range(steps)], dtype=np.float64)


def path_speed(poses: np.ndarray,  # [T, 3] x, y, yaw world
               dt: float) -> np.ndarray:  # [T] m/s
    """Speed along a logged path: the mean of the distances to the neighbouring poses over dt (one-sided at the
    ends); 0 for fewer than two poses."""
    if len(poses) < 2:
        return np.zeros(len(poses))
    d = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1) / dt
    return np.concatenate([d[:1], 0.5 * (d[1:] + d[:-1]), d[-1:]])


def track_velocity(agents: np.ndarray,  # [N, T, 3] x, y, yaw world, NaN where absent
                   dt: float) -> np.ndarray:  # [N, T, 2] world m/s, NaN where no neighbour step is present
    """Velocity of recorded tracks: the forward difference, else the backward one where the next step is absent."""
    out = np.full(agents.shape[:2] + (2,), np.nan)
    if agents.shape[1] < 2:
        return out
    forward = (agents[:, 1:, :2] - agents[:, :-1, :2]) / dt        # [N, T-1, 2], NaN where either is absent
    out[:, :-1] = forward
    back = np.isnan(out[:, 1:]).any(-1) & np.isfinite(forward).all(-1)
    out[:, 1:][back] = forward[back]
    return out


# ----------------------------------------------------------------------------- lanes
def usable_lanes(lanes) -> tuple:
    """The lane centrelines with at least two points and a positive length (others cannot give a direction)."""
    if not lanes:
        return ()
    keep = []
    for line in lanes:
        line = np.asarray(line, dtype=np.float64).reshape(-1, 2)
        if len(line) >= 2 and np.isfinite(line).all() and (np.diff(line, axis=0) ** 2).sum(-1).max() > 0:
            keep.append(line)
    return tuple(keep)


def lane_geometry(xy: np.ndarray,  # [K, 2] world
                  lanes: tuple,    # of [S + 1, 2] world centrelines in driving order
                  ) -> tuple[np.ndarray, np.ndarray]:  # distance [K, L] m, unit driving direction [K, L, 2]
    """Distance from each point to each centreline and the lane's driving direction at the nearest point (its nearest
    segment's; zero-length segments are skipped)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    dist = np.full((len(xy), len(lanes)), np.inf)
    direction = np.zeros((len(xy), len(lanes), 2))
    if len(xy) == 0:
        return dist, direction
    rows = np.arange(len(xy))
    for j, line in enumerate(lanes):
        seg = np.diff(line, axis=0)
        length2 = (seg ** 2).sum(-1)
        keep = length2 > 0
        start, seg, length2 = line[:-1][keep], seg[keep], length2[keep]
        if len(seg) == 0:
            continue
        rel = xy[:, None, :] - start[None]                                      # [K, S, 2]
        t = np.clip((rel * seg).sum(-1) / length2, 0.0, 1.0)
        d2 = ((rel - t[..., None] * seg) ** 2).sum(-1)
        nearest = np.argmin(d2, axis=1)
        dist[:, j] = np.sqrt(d2[rows, nearest])
        direction[:, j] = seg[nearest] / np.sqrt(length2[nearest])[:, None]
    return dist, direction


def oncoming(ego: np.ndarray,  # [T, 3] x, y, yaw world box centres
             lanes: tuple, half_width: float) -> np.ndarray:  # [T] bool
    """Whether the ego centre lies in at least one lane and every lane it lies in runs against its heading."""
    dist, direction = lane_geometry(ego[:, :2], lanes)
    heading = np.stack([np.cos(ego[:, 2]), np.sin(ego[:, 2])], -1)             # [T, 2]
    inside = dist <= half_width
    along = (direction * heading[:, None]).sum(-1) > 0
    return inside.any(1) & ~(inside & along).any(1)


def driving_direction_compliance(ego: np.ndarray,  # [T, 3] x, y, yaw world box centres
                                 lanes: tuple, dt: float, window: int, config: EPDMSConfig) -> np.ndarray:  # [T]
    """DDC of each step's window (see ``score_epdms``): 1, 0.5 or 0; 1 throughout without lanes."""
    steps = len(ego)
    out = np.ones(steps)
    if not lanes or steps == 0:
        return out
    moved = np.zeros(steps)
    moved[1:] = np.linalg.norm(np.diff(ego[:, :2], axis=0), axis=1)
    moved = np.where(oncoming(ego, lanes, config.lane_half_width_m), moved, 0.0)
    horizon = int(round(config.driving_direction_horizon_s / dt))
    for t in range(steps):
        end = min(steps - 1, t + window)
        step = moved[t:end + 1].copy()
        step[0] = 0.0                                   # the window's first pose has moved nowhere yet (NAVSIM)
        if not step.any():
            continue
        k = np.arange(len(step))
        trailing = np.array([step[max(0, i - horizon):i + 1].sum() for i in k])
        worst = float(trailing.max())
        if worst >= config.driving_direction_violation_m:
            out[t] = 0.0
        elif worst >= config.driving_direction_compliance_m:
            out[t] = 0.5
    return out


def route_lanes(route: np.ndarray,  # [R, 2] world polyline
                lanes: tuple, half_width: float) -> tuple:
    """The lanes that carry the route: some point of the route (sampled at most 1 m apart) lies in the lane and the
    route runs along the lane's direction there."""
    seg = np.diff(route, axis=0)
    length = np.linalg.norm(seg, axis=1)
    points, heading = [], []
    spacing = max(1.0, float(length.sum()) / 5000.0)    # at most about 5000 samples on very long routes
    for a, d, n in zip(route[:-1], seg, length):
        if n <= 0:
            continue
        k = max(1, int(math.ceil(n / spacing)))
        s = (np.arange(k) + 0.5) / k
        points.append(a + s[:, None] * d)
        heading.append(np.repeat((d / n)[None], k, 0))
    if not points:
        return ()
    points, heading = np.concatenate(points), np.concatenate(heading)
    dist, direction = lane_geometry(points, lanes)
    carried = ((dist <= half_width) & ((direction * heading[:, None]).sum(-1) > 0)).any(0)
    return tuple(line for line, c in zip(lanes, carried) if c)


def lane_keeping(ego: np.ndarray,    # [T, 3] x, y, yaw world box centres
                 lanes: tuple,
                 route: np.ndarray,  # [R, 2] world polyline
                 dt: float, window: int, config: EPDMSConfig) -> tuple[np.ndarray, bool]:  # [T], scored
    """LK of each step's window (see ``score_epdms``): 0 or 1; 1 throughout (and not scored) without lanes or when no
    lane carries the route."""
    steps = len(ego)
    out = np.ones(steps)
    if not lanes:
        return out, False
    carried = route_lanes(route, lanes, config.lane_half_width_m)
    if not carried:
        return out, False
    if steps == 0:
        return out, True
    deviation = lane_geometry(ego[:, :2], carried)[0].min(1)
    exceeds = deviation > config.lane_keeping_deviation_m
    need = max(1, int(math.ceil(config.lane_keeping_window_s / dt - 1e-9)))
    # run[k]: consecutive deviating poses ending at k; a window fails when a run inside it reaches ``need``
    run = np.zeros(steps, dtype=np.int64)
    for k in range(steps):
        run[k] = (run[k - 1] + 1 if k else 1) if exceeds[k] else 0
    for t in range(steps):
        end = min(steps - 1, t + window)
        inside = np.minimum(run[t:end + 1], np.arange(1, end - t + 2))  # runs are counted from the window's start
        if inside.max(initial=0) >= need:
            out[t] = 0.0
    return out, True


# ----------------------------------------------------------------------------- comfort
def history_comfort(ego: np.ndarray,  # [T, 3] x, y, yaw world box centres
                    dt: float, window: int, config: EPDMSConfig) -> np.ndarray:  # [T]
    """HC of each step's window: nuPlan's comfort on the window with up to ``history_s`` of the ego's past before
    it (NAVSIM's bounds, Savitzky-Golay derivatives)."""
    steps = len(ego)
    history = int(round(config.history_s / dt))
    out = np.ones(steps)
    for t in range(steps):
        start, end = max(0, t - history), min(steps - 1, t + window)
        span = slice(start, end + 1)
        out[t] = 1.0 if metrics.comfortable(ego[span, :2], ego[span, 2], dt, NAVSIM_COMFORT) else 0.0
    return out


def extended_comfort(ego: np.ndarray,  # [T, 3] x, y, yaw world box centres
                     plans: tuple,     # [T] of ([P, 2] world) | None
                     plan_dt: float, dt: float, config: EPDMSConfig) -> tuple[np.ndarray, np.ndarray]:
    """EC of each step (see ``score_epdms``): 0 or 1, and whether two plans were compared ([T] each)."""
    steps = len(ego)
    out, compared = np.ones(steps), np.zeros(steps, dtype=bool)
    lag = int(round(config.ec_interval_s / dt))
    if lag < 1:
        return out, compared
    for t in range(lag, steps):
        now_plan, prev_plan = plans[t], plans[t - lag]
        if now_plan is None or prev_plan is None:
            continue
        now = np.concatenate([ego[t, None, :2], now_plan], 0)                  # [P + 1, 2]
        prev = np.concatenate([ego[t - lag, None, :2], prev_plan], 0)
        now_times = t * dt + np.arange(len(now)) * plan_dt
        prev_times = (t - lag) * dt + np.arange(len(prev)) * plan_dt
        common = now_times <= prev_times[-1] + 1e-9
        n = int(common.sum())
        if n < 4:
            continue
        times = now_times[:n]
        now_heading = metrics.plan_headings(now, ego[t, 2])[:n]
        prev_heading = metrics.plan_headings(prev, ego[t - lag, 2])
        prev_heading = prev_heading[0] + np.concatenate([[0.0], np.cumsum(wrap_angle(np.diff(prev_heading)))])
        prev_xy = np.stack([np.interp(times, prev_times, prev[:, 0]), np.interp(times, prev_times, prev[:, 1])], -1)
        a = metrics.kinematics(now[:n], now_heading, plan_dt, smooth=False)
        b = metrics.kinematics(prev_xy, np.interp(times, prev_times, prev_heading), plan_dt, smooth=False)
        with np.errstate(over="ignore", invalid="ignore"):
            rms = {key: float(np.sqrt(np.mean((a[key] - b[key]) ** 2)))
                   for key in ("accel", "jerk", "yaw_rate", "yaw_accel")}
        ok = (rms["accel"] <= config.ec_max_rms_accel and rms["jerk"] <= config.ec_max_rms_jerk
              and rms["yaw_rate"] <= config.ec_max_rms_yaw_rate and rms["yaw_accel"] <= config.ec_max_rms_yaw_accel)
        out[t] = 1.0 if ok else 0.0                     # a NaN difference compares False: not comfortable
        compared[t] = True
    return out, compared


# ----------------------------------------------------------------------------- NAVSIM's TTC
def navsim_ttc(ego: np.ndarray,            # [T, 3] x, y, yaw world box centres
               speed: np.ndarray,          # [T] m/s
               ego_size: tuple[float, float],
               agents: np.ndarray,         # [N, T, 3] x, y, yaw world; non-finite where absent
               agent_sizes: np.ndarray,    # [N, 2] length, width
               offroad: np.ndarray,        # [T] bool: the ego box has a non-drivable corner
               dt: float, window: int, config: EPDMSConfig) -> np.ndarray:  # [T] 0 or 1
    """NAVSIM's time-to-collision within bound of each step's window (its ``_calculate_ttc``).

    For each pose k of the window whose look-ahead stays inside it (k + the largest offset <= the window's end) and
    each look-ahead time tau in ``navsim_ttc_times_s``: the ego box moved along its heading by speed_k tau meets the
    agents at their recorded positions at step k + round(tau / dt). A touched agent is skipped when it already
    touched the ego at the window's first pose, or was skipped before in this window, or the ego is slower than
    0.005 m/s; otherwise TTC is 0 when the agent is ahead (angle from the ego's heading to the agent under 30
    degrees) or the ego is off the drivable area and the agent is not behind (angle over 150 degrees), else the
    agent is skipped from then on. Angles are measured from the ego's box centre (NAVSIM: its rear axle); an agent
    centre on the ego's is neither ahead nor behind (nuPlan's angle is undefined there). NAVSIM also blames an ego
    in several lanes or in an intersection: we have no lane polygons, so only off-road counts.
    """
    steps, count = len(ego), len(agents)
    out = np.ones(steps)
    if steps == 0 or count == 0:
        return out
    length, width = ego_size
    offsets = np.array([int(round(tau / dt)) for tau in config.navsim_ttc_times_s])
    reach = int(offsets.max())
    present = np.isfinite(agents).all(-1)                                         # [N, T]
    safe = np.where(present[..., None], agents, 0.0)
    heading = np.stack([np.cos(ego[:, 2]), np.sin(ego[:, 2])], -1)              # [T, 2]
    sizes = np.asarray(agent_sizes, dtype=np.float64)
    agent_boxes = footprints(safe[..., :2], safe[..., 2], sizes[:, None, 0], sizes[:, None, 1])  # [N, T, 4, 2]
    ok_boxes = present & np.isfinite(agent_boxes).all((-1, -2))
    ahead_cos, behind_cos = np.cos(np.deg2rad(config.ahead_deg)), np.cos(np.deg2rad(config.behind_deg))

    def touching(k: int, offset: int) -> np.ndarray:  # [N] bool: projected ego at k meets the agents at k + offset
        with np.errstate(over="ignore", invalid="ignore"):
            centre = ego[k, :2] + heading[k] * speed[k] * offset * dt
        box = footprints(centre, ego[k, 2], length, width)
        return overlapping(box[None], agent_boxes[:, k + offset]) & ok_boxes[:, k + offset]

    def relation(k: int, offset: int, n: int) -> tuple[bool, bool]:  # (ahead, behind) of agent n
        d = safe[n, k + offset, :2] - ego[k, :2]
        norm = float(np.hypot(d[0], d[1]))
        if not norm > 0 or not np.isfinite(norm):
            return False, False
        c = float(heading[k] @ d) / norm
        return c > ahead_cos, c < behind_cos

    cache: dict[tuple[int, int], np.ndarray] = {}
    for t in range(steps):
        end = min(steps - 1, t + window)
        ignored = set(np.flatnonzero(cache.setdefault((t, 0), touching(t, 0))).tolist())
        violated = False
        for k in range(t, end - reach + 1):
            for offset in offsets:
                hit = cache.get((k, int(offset)))
                if hit is None:
                    hit = cache[(k, int(offset))] = touching(k, int(offset))
                for n in np.flatnonzero(hit):
                    if n in ignored or speed[k] < config.navsim_stopped_speed:
                        continue
                    ahead, behind = relation(k, int(offset), int(n))
                    if ahead or (offroad[k] and not behind):
                        violated = True
                        break
                    ignored.add(int(n))
                if violated:
                    break
            if violated:
                break
        out[t] = 0.0 if violated else 1.0
    return out
