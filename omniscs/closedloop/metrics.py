"""Closed-loop driving scores of one run: NAVSIM's PDM score (PDMS), HUGSIM's HD-Score, and the instantaneous
checks (contacts, off-road, time to collision, route completion) the simulator runs each step. NAVSIM v2's EPDMS,
scored beside PDMS on the same windows, lives in ``omniscs.closedloop.epdms``."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_filter

from omniscs.comfort import HUGSIM_COMFORT, NAVSIM_COMFORT, ComfortBounds
from omniscs.errors import ValidationError
from omniscs.geometry import wrap_angle
from omniscs.scs.behavior.collision import footprints, overlapping

#: Agent kinds a trace may name: road users that move, vulnerable road users, and static objects.
AGENT_KINDS = ("vehicle", "vru", "static")
#: Below this speed (m/s) an ego or agent counts as stopped (nuPlan's ``stopped_speed_threshold``).
STOPPED_SPEED = 5e-2
#: Contact kinds of nuPlan's collision classification, and which of them put the ego at fault here.
CONTACT_KINDS = ("stopped_ego", "stopped_track", "active_front", "active_rear", "active_lateral")
AT_FAULT_CONTACTS = ("stopped_track", "active_front", "active_lateral")
#: NC of an at-fault contact with a static object (NAVSIM); a vehicle or VRU gives 0.
STATIC_CONTACT_NC = 0.5
#: Constant-velocity look-ahead of the TTC check (s): 0.0 .. 0.9 in 0.1 steps, under nuPlan's least TTC of 0.95 s.
LEAST_TTC_S = 0.95
TTC_STEP_S = 0.1
#: Below this reference progress (m) over a window, EP is 1 (NAVSIM's ``progress_distance_threshold``).
LOW_PROGRESS_M = 5.0
#: PDMS weights of EP, TTC and comfort (NAVSIM); HD-Score weights of TTC and comfort (HUGSIM).
PDMS_WEIGHTS = {"ep": 5.0, "ttc": 5.0, "comfort": 2.0}
HD_WEIGHTS = {"ttc": 5.0, "comfort": 2.0}
#: Savitzky-Golay smoothing of the executed trajectory before differentiation (nuPlan: window 15 at 10 Hz, order 2).
SAVGOL_WINDOW = 15
SAVGOL_ORDER = 2
#: HUGSIM: the ego footprint is split into this grid of cells (along length, along width) ...
HD_DAC_CELLS = (2, 2)
#: ... and a waypoint whose fraction of drivable cells is below the first value gives DAC 0, below the second 0.5.
HD_DAC_ZERO_BELOW, HD_DAC_HALF_BELOW = 0.3, 0.5
#: HUGSIM's TTC: the planned path displaced by its own velocity times each of these times (s).
HD_TTC_TIMES_S = (0.5, 1.0)
#: HUGSIM: a plan whose end lies less than this (m) from its start keeps the current yaw at every waypoint.
HD_MIN_PATH_M = 1.0
#: Waypoints of the executed-path stand-in for a step with no plan when the run has no plan at all (UniAD: 6).
DEFAULT_PLAN_POINTS = 6


@dataclass(frozen=True, eq=False)
class RunTrace:
    """One finished (or partial) closed-loop run. World frame, z up, yaw in radians from +x, metres, seconds.

    Arrays are converted to float64 and checked on construction; a malformed trace raises ValidationError.
    Agent poses that are not finite mean the agent is absent at that step.
    """

    dt: float
    """Simulator step (s), e.g. 0.1."""
    ego: np.ndarray  # [T, 3] x, y, yaw world
    """The ego BOX CENTRE at each step (T >= 0; an empty run still scores, with undefined means)."""
    ego_speed: np.ndarray  # [T] m/s
    """Ego speed at each step (>= 0)."""
    ego_size: tuple[float, float]
    """Ego (length, width) in metres."""
    agents: np.ndarray  # [N, T, 3] x, y, yaw world
    """Each agent's box centre per step; NaN where the agent is absent."""
    agent_sizes: np.ndarray  # [N, 2] length, width
    """Each agent's footprint size (m)."""
    agent_kinds: tuple[str, ...]  # [N]
    """Each agent's kind: "vehicle", "vru" (pedestrian, cyclist) or "static" (cone, barrier, debris, parked)."""
    agent_velocity: np.ndarray  # [N, T, 2] world m/s
    """Each agent's velocity per step; NaN where absent (a non-finite velocity of a present agent reads as 0)."""
    plans: tuple  # [T] of ([P, 2] world x, y) | None
    """The plan issued at each step: box-centre waypoints at ``plan_dt`` (P >= 1), or None for direct controls."""
    plan_dt: float
    """Time between plan waypoints (s); UniAD: 0.5."""
    route: np.ndarray  # [R, 2] world x, y
    """The reference path the ego should follow (R >= 2, positive length)."""
    reference_progress: np.ndarray  # [T] m
    """Metres the reference ego (the log) has travelled along ``route`` at each step time."""
    drivable: object | None
    """An object with ``is_drivable(xy [K, 2] world) -> bool [K]``, or None when the scene has no map."""
    reference_ego: np.ndarray | None = None  # [T, 3] x, y, yaw world
    """The reference (logged, human) ego's BOX CENTRE at each step's time, for EPDMS's human-agent filter; None: no
    filter (every sub-score is held against the policy)."""
    reference_agents: np.ndarray | None = None  # [N, T, 3] x, y, yaw world
    """The agents as the reference ego met them (the scenario's own trajectories; NaN where absent); None: the
    reference ego is checked against ``agents``, the agents of the run."""
    lane_centrelines: tuple | None = None  # of [K, 2] world x, y in driving order
    """The lane centrelines of the map, each in its driving direction (EPDMS's DDC and LK); None or empty: no lane map
    (DDC and LK score 1)."""

    def __post_init__(self):
        dt, plan_dt = _positive_scalar(self.dt, "dt"), _positive_scalar(self.plan_dt, "plan_dt")
        ego = np.asarray(self.ego, dtype=np.float64)
        if ego.ndim == 1 and ego.size == 0:
            ego = ego.reshape(0, 3)
        if ego.ndim != 2 or ego.shape[1] != 3:
            raise ValidationError(f"RunTrace.ego has shape {ego.shape}; pass [T, 3] x, y, yaw of the ego box "
                                  f"centre per step")
        if not np.isfinite(ego).all():
            raise ValidationError("RunTrace.ego holds NaN or Inf; every ego pose of the run must be finite")
        steps = len(ego)
        speed = np.asarray(self.ego_speed, dtype=np.float64).reshape(-1)
        if speed.shape != (steps,) or not np.isfinite(speed).all() or (speed < 0).any():
            raise ValidationError(f"RunTrace.ego_speed must be [T={steps}] finite speeds >= 0 m/s; "
                                  f"got shape {speed.shape}")
        size = _footprint_size(self.ego_size, "ego_size")
        sizes = np.asarray(self.agent_sizes, dtype=np.float64)
        count = len(sizes) if sizes.ndim >= 1 else 0
        if sizes.size == 0:
            sizes, count = sizes.reshape(0, 2), 0
        if sizes.ndim != 2 or sizes.shape[1] != 2 or not np.isfinite(sizes).all() or (sizes <= 0).any():
            raise ValidationError(f"RunTrace.agent_sizes must be [N, 2] positive length, width (m); "
                                  f"got shape {sizes.shape}")
        agents = np.asarray(self.agents, dtype=np.float64)
        if agents.size == 0 and count == 0:
            agents = agents.reshape(0, steps, 3)
        if agents.shape != (count, steps, 3):
            raise ValidationError(f"RunTrace.agents has shape {agents.shape}; pass [N={count}, T={steps}, 3] "
                                  f"x, y, yaw (NaN where absent)")
        velocity = np.asarray(self.agent_velocity, dtype=np.float64)
        if velocity.size == 0 and count == 0:
            velocity = velocity.reshape(0, steps, 2)
        if velocity.shape != (count, steps, 2):
            raise ValidationError(f"RunTrace.agent_velocity has shape {velocity.shape}; pass "
                                  f"[N={count}, T={steps}, 2] world m/s (NaN where absent)")
        kinds = tuple(str(k) for k in self.agent_kinds)
        if len(kinds) != count or any(k not in AGENT_KINDS for k in kinds):
            raise ValidationError(f"RunTrace.agent_kinds must name {count} kinds among {list(AGENT_KINDS)}; "
                                  f"got {list(kinds)[:5]}{'...' if len(kinds) > 5 else ''}")
        plans = tuple(self.plans)
        if len(plans) != steps:
            raise ValidationError(f"RunTrace.plans has {len(plans)} entries; pass one per step (T={steps}), "
                                  f"None where the policy gave direct controls")
        plans = tuple(None if p is None else _plan(p, k) for k, p in enumerate(plans))
        route = _route(self.route)
        reference = np.asarray(self.reference_progress, dtype=np.float64).reshape(-1)
        if reference.shape != (steps,) or not np.isfinite(reference).all():
            raise ValidationError(f"RunTrace.reference_progress must be [T={steps}] finite metres along the route; "
                                  f"got shape {reference.shape}")
        if self.drivable is not None and not callable(getattr(self.drivable, "is_drivable", None)):
            raise ValidationError("RunTrace.drivable must have is_drivable(xy [K, 2]) -> bool [K], or be None")
        reference_ego = None
        if self.reference_ego is not None:
            reference_ego = np.asarray(self.reference_ego, dtype=np.float64)
            if reference_ego.size == 0 and steps == 0:
                reference_ego = reference_ego.reshape(0, 3)
            if reference_ego.shape != (steps, 3) or not np.isfinite(reference_ego).all():
                raise ValidationError(f"RunTrace.reference_ego has shape {reference_ego.shape} or non-finite values; "
                                      f"pass [T={steps}, 3] finite x, y, yaw of the logged ego box centre, or None")
        reference_agents = None
        if self.reference_agents is not None:
            reference_agents = np.asarray(self.reference_agents, dtype=np.float64)
            if reference_agents.size == 0 and count == 0:
                reference_agents = reference_agents.reshape(0, steps, 3)
            if reference_agents.shape != (count, steps, 3):
                raise ValidationError(f"RunTrace.reference_agents has shape {reference_agents.shape}; pass "
                                      f"[N={count}, T={steps}, 3] logged x, y, yaw (NaN where absent), or None")
        lanes = None
        if self.lane_centrelines is not None:
            lanes = tuple(np.asarray(c, dtype=np.float64).reshape(-1, 2) for c in self.lane_centrelines)
            if any(not np.isfinite(c).all() for c in lanes):
                raise ValidationError("RunTrace.lane_centrelines holds NaN or Inf; pass finite [K, 2] world polylines")
        for name, value in (("dt", dt), ("plan_dt", plan_dt), ("ego", ego), ("ego_speed", speed),
                            ("ego_size", size), ("agents", agents), ("agent_sizes", sizes), ("agent_kinds", kinds),
                            ("agent_velocity", velocity), ("plans", plans), ("route", route),
                            ("reference_progress", reference), ("reference_ego", reference_ego),
                            ("reference_agents", reference_agents), ("lane_centrelines", lanes)):
            object.__setattr__(self, name, value)

    @property
    def steps(self) -> int:
        """Number of simulator steps T."""
        return len(self.ego)


@dataclass(frozen=True)
class Contact:
    """One overlap of the ego's footprint with an agent's at one step, classified as nuPlan does."""

    track: int
    """Index of the agent in the trace (axis N)."""
    kind: str
    """The agent's kind: "vehicle", "vru" or "static"."""
    kind_of_contact: str
    """One of CONTACT_KINDS: "stopped_ego", "stopped_track", "active_front", "active_rear", "active_lateral"."""
    at_fault: bool
    """Whether the contact counts against the ego (stopped_track, active_front, active_lateral)."""


# ----------------------------------------------------------------------------- validation helpers
def _positive_scalar(value, name: str) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0:
        raise ValidationError(f"RunTrace.{name} is {value}; pass a finite positive time in seconds")
    return value


def _footprint_size(size, name: str) -> tuple[float, float]:
    size = np.asarray(size, dtype=np.float64).reshape(-1)
    if size.shape != (2,) or not np.isfinite(size).all() or (size <= 0).any():
        raise ValidationError(f"{name} must be (length, width), both finite and positive metres; got {size.tolist()}")
    return float(size[0]), float(size[1])


def _plan(plan, step: int) -> np.ndarray:  # -> [P, 2]
    plan = np.asarray(plan, dtype=np.float64)
    if plan.ndim != 2 or plan.shape[1] != 2 or len(plan) < 1:
        raise ValidationError(f"RunTrace.plans[{step}] has shape {plan.shape}; pass [P, 2] world x, y waypoints "
                              f"(P >= 1) or None")
    if not np.isfinite(plan).all():
        raise ValidationError(f"RunTrace.plans[{step}] holds NaN or Inf; pass finite waypoints or None")
    return plan


def _route(route) -> np.ndarray:  # -> [R, 2]
    route = np.asarray(route, dtype=np.float64)
    if route.ndim != 2 or route.shape[1] != 2 or len(route) < 2 or not np.isfinite(route).all():
        raise ValidationError(f"route has shape {route.shape} or non-finite points; pass an [R, 2] world polyline "
                              f"with R >= 2 finite points")
    if not np.linalg.norm(np.diff(route, axis=0), axis=1).sum() > 0:
        raise ValidationError("route has zero length; pass a polyline whose points are not all the same")
    return route


def _drivable_mask(drivable, xy: np.ndarray) -> np.ndarray:  # [K, 2] world -> [K] bool
    if len(xy) == 0:
        return np.zeros(0, dtype=bool)
    mask = np.asarray(drivable.is_drivable(xy), dtype=bool).reshape(-1)
    if mask.shape != (len(xy),):
        raise ValidationError(f"drivable.is_drivable returned {mask.shape[0]} flags for {len(xy)} points; it must "
                              f"return one bool per point")
    return mask


def _present(poses: np.ndarray) -> np.ndarray:  # [..., 3] -> [...] bool
    return np.isfinite(poses).all(-1)


def _finite_or_zero(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return np.where(np.isfinite(a), a, 0.0)


# ----------------------------------------------------------------------------- instantaneous checks
def ego_footprint(pose: np.ndarray,        # [3] x, y, yaw world
                  size: tuple[float, float],  # (length, width) m
                  ) -> np.ndarray:         # [4, 2] corners, counter-clockwise from front-left
    """The ego's ground-plane box at a pose (the pose is the box centre)."""
    pose = np.asarray(pose, dtype=np.float64)
    return footprints(pose[:2], pose[2], size[0], size[1])


def _ego_local(ego_pose: np.ndarray, xy: np.ndarray) -> np.ndarray:  # [3], [..., 2] world -> [..., 2] ego frame
    c, s = np.cos(ego_pose[2]), np.sin(ego_pose[2])
    d = xy - ego_pose[:2]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def collisions_at(ego_pose: np.ndarray,            # [3] x, y, yaw world
                  ego_size: tuple[float, float],   # (length, width) m
                  ego_speed: float,                # m/s
                  agents_pose: np.ndarray,         # [N, 3] x, y, yaw world; non-finite where absent
                  agent_sizes: np.ndarray,         # [N, 2] length, width
                  agent_kinds: tuple[str, ...],    # [N]
                  agent_velocity: np.ndarray,      # [N, 2] world m/s
                  ) -> list[Contact]:
    """Agents whose footprint overlaps the ego's (touching counts), classified after nuPlan's collision metric.

    Rule, in order (nuPlan ``no_ego_at_fault_collisions``, as NAVSIM uses it):
    1. ego speed < 5e-2 m/s: ``stopped_ego``, not at fault;
    2. agent speed < 5e-2 m/s (a non-finite velocity reads as 0): ``stopped_track``, at fault;
    3. the agent's centre, in the ego frame (x ahead, y left), lies in the side wedges cut by the ego box's diagonals,
       |y| * length > |x| * width: ``active_lateral``, at fault. nuPlan blames a lateral contact only when the ego
       straddles lanes or is off its lane; without a lane association we always blame it;
    4. the agent's footprint overlaps the front half of the ego box (ahead of its centre): ``active_front``, at fault;
    5. otherwise (it touches the rear half only): ``active_rear``, not at fault.
    Absent agents (any non-finite pose value) are ignored.
    """
    ego_pose = np.asarray(ego_pose, dtype=np.float64)
    poses = np.asarray(agents_pose, dtype=np.float64).reshape(-1, 3)
    if len(poses) == 0:
        return []
    sizes = np.asarray(agent_sizes, dtype=np.float64).reshape(-1, 2)
    present = _present(poses)
    safe = np.where(present[:, None], poses, 0.0)
    length, width = ego_size
    agent_boxes = footprints(safe[:, :2], safe[:, 2], sizes[:, 0], sizes[:, 1])  # [N, 4, 2]
    hit = overlapping(ego_footprint(ego_pose, ego_size)[None], agent_boxes) & present
    if not hit.any():
        return []
    front_centre = ego_pose[:2] + 0.25 * length * np.array([np.cos(ego_pose[2]), np.sin(ego_pose[2])])
    front_half = footprints(front_centre, ego_pose[2], 0.5 * length, width)
    speeds = np.linalg.norm(_finite_or_zero(np.asarray(agent_velocity).reshape(-1, 2)), axis=-1)
    local = _ego_local(ego_pose, safe[:, :2])
    contacts = []
    for n in np.flatnonzero(hit):
        if ego_speed < STOPPED_SPEED:
            kind = "stopped_ego"
        elif speeds[n] < STOPPED_SPEED:
            kind = "stopped_track"
        elif abs(local[n, 1]) * length > abs(local[n, 0]) * width:
            kind = "active_lateral"
        elif overlapping(front_half, agent_boxes[n]):
            kind = "active_front"
        else:
            kind = "active_rear"
        contacts.append(Contact(track=int(n), kind=str(agent_kinds[n]), kind_of_contact=kind,
                                at_fault=kind in AT_FAULT_CONTACTS))
    return contacts


def contact_nc(contacts: list[Contact]) -> float:
    """NAVSIM's no-collision value of one step: 0 for an at-fault contact with a vehicle or VRU, 0.5 when the worst
    is an at-fault contact with a static object, else 1."""
    blamed = [c.kind for c in contacts if c.at_fault]
    if any(k != "static" for k in blamed):
        return 0.0
    return STATIC_CONTACT_NC if blamed else 1.0


def ttc_violated_at(ego_pose: np.ndarray,           # [3] x, y, yaw world
                    ego_size: tuple[float, float],  # (length, width) m
                    ego_speed: float,               # m/s
                    agents_pose: np.ndarray,        # [N, 3] x, y, yaw world; non-finite where absent
                    agent_sizes: np.ndarray,        # [N, 2] length, width
                    agent_velocity: np.ndarray,     # [N, 2] world m/s
                    ) -> bool:
    """nuPlan's time-to-collision check at one step: True when the ego would touch an agent within the least TTC.

    The ego moves along its heading at its speed and each agent at its velocity (yaws held), for look-ahead times
    0.0, 0.1, ..., 0.9 s (below nuPlan's least TTC, 0.95 s). Only a moving ego (speed >= 5e-2 m/s) is checked, and
    only agents whose centre is not behind the ego's rear (ego-frame x > -length / 2). An agent already overlapping
    at 0 s counts. Absent agents are ignored; a non-finite agent velocity reads as 0.
    """
    poses = np.asarray(agents_pose, dtype=np.float64).reshape(-1, 3)
    if ego_speed < STOPPED_SPEED or len(poses) == 0:
        return False
    ego_pose = np.asarray(ego_pose, dtype=np.float64)
    length, width = ego_size
    present = _present(poses)
    safe = np.where(present[:, None], poses, 0.0)
    ahead = present & (_ego_local(ego_pose, safe[:, :2])[:, 0] > -0.5 * length)
    if not ahead.any():
        return False
    sizes = np.asarray(agent_sizes, dtype=np.float64).reshape(-1, 2)[ahead]
    velocity = _finite_or_zero(np.asarray(agent_velocity).reshape(-1, 2))[ahead]
    taus = np.arange(int(np.ceil(LEAST_TTC_S / TTC_STEP_S))) * TTC_STEP_S  # [L]
    heading = np.array([np.cos(ego_pose[2]), np.sin(ego_pose[2])])
    with np.errstate(over="ignore", invalid="ignore"):
        ego_xy = ego_pose[:2] + ego_speed * taus[:, None] * heading  # [L, 2]
        agent_xy = safe[ahead, None, :2] + velocity[:, None] * taus[None, :, None]  # [M, L, 2]
    ego_boxes = footprints(ego_xy, np.full(len(taus), ego_pose[2]), length, width)  # [L, 4, 2]
    agent_boxes = footprints(agent_xy, np.broadcast_to(safe[ahead, None, 2], agent_xy.shape[:2]),
                             sizes[:, None, 0], sizes[:, None, 1])  # [M, L, 4, 2]
    touching = overlapping(ego_boxes[None], agent_boxes) & np.isfinite(agent_boxes).all((-1, -2))
    return bool(touching.any())


def offroad(ego_pose: np.ndarray,            # [3] x, y, yaw world
            ego_size: tuple[float, float],   # (length, width) m
            drivable,                        # is_drivable(xy [K, 2]) -> bool [K], or None
            ) -> bool:
    """True when any of the ego box's four corners is not drivable (nuPlan's drivable-area rule); False without a
    map."""
    if drivable is None:
        return False
    return not bool(_drivable_mask(drivable, ego_footprint(ego_pose, ego_size)).all())


def progress_along(xy: np.ndarray,     # [K, 2] world
                   route: np.ndarray,  # [R, 2] world polyline
                   ) -> np.ndarray:    # [K] m along the route
    """Arclength along the route of each point's projection: its nearest point on the polyline (first of equals)."""
    route = _route(route)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if not np.isfinite(xy).all():
        raise ValidationError("progress_along got non-finite points; pass finite world x, y")
    if len(xy) == 0:
        return np.zeros(0)
    start, seg = route[:-1], np.diff(route, axis=0)                        # [S, 2]
    seg_len2 = (seg ** 2).sum(-1)
    cum = np.concatenate([[0.0], np.cumsum(np.sqrt(seg_len2))])
    with np.errstate(over="ignore", invalid="ignore"):
        rel = xy[:, None, :] - start[None]                                 # [K, S, 2]
        t = np.where(seg_len2 > 0, (rel * seg).sum(-1) / np.where(seg_len2 > 0, seg_len2, 1.0), 0.0)
        t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
        dist2 = ((rel - t[..., None] * seg) ** 2).sum(-1)
    nearest = np.argmin(np.nan_to_num(dist2, nan=np.inf), axis=1)
    rows = np.arange(len(xy))
    return cum[nearest] + t[rows, nearest] * np.sqrt(seg_len2[nearest])


def route_completion(ego_xy: np.ndarray,  # [2] or [T, 2] world ego centre(s)
                     route: np.ndarray,   # [R, 2] world polyline
                     ) -> float:          # in [0, 1]
    """Fraction of the route covered: the projection's arclength over the route length, the largest over the given
    positions (so it never falls as a run goes on); 0 for no positions. A zero-length route raises ValidationError."""
    route = _route(route)
    xy = np.asarray(ego_xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return 0.0
    length = float(np.linalg.norm(np.diff(route, axis=0), axis=1).sum())
    return float(np.clip(progress_along(xy, route).max() / length, 0.0, 1.0))


# ----------------------------------------------------------------------------- comfort
def _derivative(series: np.ndarray, dt: float, smooth: bool) -> np.ndarray:  # [n] -> [n]
    """d/dt of a sampled series: a Savitzky-Golay derivative (window min(15, largest odd <= n), order 2) when
    ``smooth``, else finite differences (second-order at both ends, exact for quadratics)."""
    n = len(series)
    if smooth:
        window = min(SAVGOL_WINDOW, n if n % 2 else n - 1)
        if window > SAVGOL_ORDER:
            return savgol_filter(series, window, SAVGOL_ORDER, deriv=1, delta=dt, mode="interp")
    if n < 2:
        return np.zeros(n)
    return np.gradient(series, dt, edge_order=2 if n >= 3 else 1)


def kinematics(xy: np.ndarray,    # [n, 2] world box centres at a fixed spacing
               yaw: np.ndarray,   # [n] rad
               dt: float,         # s between samples
               smooth: bool = True,
               ) -> dict[str, np.ndarray]:  # name -> [n]
    """The ego's kinematics along a sampled trajectory, as nuPlan's comfort metrics define them (see ``comfortable``):
    lon_speed (m/s), lon_accel (m/s²), lon_jerk (m/s³), yaw_rate (rad/s), yaw_accel (rad/s²), lat_accel (m/s²),
    accel (|(lon_accel, lat_accel)|, m/s²) and jerk (its time derivative, m/s³). Non-finite where the input is."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    yaw = yaw[0] + np.concatenate([[0.0], np.cumsum(wrap_angle(np.diff(yaw)))]) if len(yaw) else yaw  # unwrapped
    with np.errstate(over="ignore", invalid="ignore"):
        vx, vy = _derivative(xy[:, 0], dt, smooth), _derivative(xy[:, 1], dt, smooth)
        lon_speed = vx * np.cos(yaw) + vy * np.sin(yaw)
        lon_accel = _derivative(lon_speed, dt, smooth)
        lon_jerk = _derivative(lon_accel, dt, smooth)
        yaw_rate = _derivative(yaw, dt, smooth)
        yaw_accel = _derivative(yaw_rate, dt, smooth)
        lat_accel = lon_speed * yaw_rate
        accel = np.hypot(lon_accel, lat_accel)
        jerk = _derivative(accel, dt, smooth)
    return {"lon_speed": lon_speed, "lon_accel": lon_accel, "lon_jerk": lon_jerk, "yaw_rate": yaw_rate,
            "yaw_accel": yaw_accel, "lat_accel": lat_accel, "accel": accel, "jerk": jerk}


def comfortable(xy: np.ndarray,     # [n, 2] world box centres at a fixed spacing
                yaw: np.ndarray,    # [n] rad
                dt: float,          # s between samples
                bounds: ComfortBounds = NAVSIM_COMFORT,
                smooth: bool = True,
                ) -> bool:
    """nuPlan's comfort test on a sampled trajectory (True with fewer than 4 samples).

    Velocity is the derivative of the positions; longitudinal speed is its component along the yaw, longitudinal
    acceleration and jerk its first and second derivatives; yaw rate and yaw acceleration are derivatives of the
    unwrapped yaw; lateral acceleration is longitudinal speed * yaw rate; the jerk magnitude is the derivative of
    the acceleration magnitude |(lon, lat)| (nuPlan's ``magnitude`` coordinate). Every sample must lie within
    ``bounds``; a non-finite value fails.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) < 4:
        return True
    k = kinematics(xy, yaw, dt, smooth)
    with np.errstate(over="ignore", invalid="ignore"):
        checks = [(k["lon_accel"] >= bounds.min_lon_accel) & (k["lon_accel"] <= bounds.max_lon_accel),
                  np.abs(k["lat_accel"]) <= bounds.max_abs_lat_accel,
                  np.abs(k["yaw_rate"]) <= bounds.max_abs_yaw_rate]
        optional = ((k["yaw_accel"], bounds.max_abs_yaw_accel), (k["lon_jerk"], bounds.max_abs_lon_jerk),
                    (k["jerk"], bounds.max_abs_jerk))
        checks += [np.abs(value) <= bound for value, bound in optional if bound is not None]
    # comparisons with NaN are False, so a non-finite kinematic value fails the test
    return bool(all(c.all() for c in checks))


# ----------------------------------------------------------------------------- HUGSIM's per-plan checks
def plan_headings(path: np.ndarray,  # [K, 2] world: the current ego centre, then the waypoints
                  current_yaw: float,
                  ) -> np.ndarray:   # [K] rad
    """Headings along a planned path (HUGSIM): the current yaw at the start; at each waypoint the direction of the
    segment arriving at it (a zero-length segment keeps the previous heading); the current yaw everywhere when the
    path's end lies less than 1 m from its start (a stopped ego's plan has no reliable direction)."""
    headings = np.full(len(path), float(current_yaw))
    if len(path) < 2 or np.linalg.norm(path[-1] - path[0]) < HD_MIN_PATH_M:
        return headings
    steps = np.diff(path, axis=0)
    for k, (dx, dy) in enumerate(steps, start=1):
        headings[k] = np.arctan2(dy, dx) if dx * dx + dy * dy > 0 else headings[k - 1]
    return headings


def hd_drivable_compliance(path: np.ndarray,              # [K, 2] world box centres
                           headings: np.ndarray,          # [K] rad
                           ego_size: tuple[float, float],  # (length, width) m
                           drivable,                      # is_drivable(xy [M, 2]) -> bool [M], or None
                           cells: tuple[int, int] = HD_DAC_CELLS,
                           ) -> float:                    # 0, 0.5 or 1
    """HUGSIM's drivable-area compliance of a path, with a drivable map standing in for its ground points.

    At each pose the footprint is split into ``cells`` (along length, along width; HUGSIM: 2 x 2) and a cell counts
    as drivable when its centre is (HUGSIM: when any ground point falls in it). With r the fraction of drivable
    cells, any pose with r < 0.3 gives 0, else any with r < 0.5 gives 0.5, else 1; 1 without a map. Note that on a
    2 x 2 grid r is a multiple of 1/4, so half the cells off the road (r = 0.5) still gives 1 and one cell of four
    gives 0, as in HUGSIM; the 0.5 tier needs a finer grid.
    """
    if drivable is None or len(path) == 0:
        return 1.0
    length, width = ego_size
    along, across = cells
    lx = (np.arange(along) + 0.5) / along * length - 0.5 * length
    ly = (np.arange(across) + 0.5) / across * width - 0.5 * width
    gx, gy = np.meshgrid(lx, ly, indexing="ij")
    local = np.stack([gx.ravel(), gy.ravel()], -1)                      # [C, 2] ego frame
    c, s = np.cos(headings)[:, None], np.sin(headings)[:, None]
    world = np.stack([path[:, :1] + c * local[:, 0] - s * local[:, 1],
                      path[:, 1:] + s * local[:, 0] + c * local[:, 1]], -1)  # [K, C, 2]
    ratio = _drivable_mask(drivable, world.reshape(-1, 2)).reshape(len(path), -1).mean(-1)
    if (ratio < HD_DAC_ZERO_BELOW).any():
        return 0.0
    return 0.5 if (ratio < HD_DAC_HALF_BELOW).any() else 1.0


def _path_collides(path: np.ndarray,         # [K, 2] world box centres
                   headings: np.ndarray,     # [K]
                   ego_size: tuple[float, float],
                   agent_poses: np.ndarray,  # [K, N, 3] the agents at each pose's time; non-finite where absent
                   agent_sizes: np.ndarray,  # [N, 2]
                   ) -> bool:
    if agent_poses.shape[1] == 0 or len(path) == 0:
        return False
    present = _present(agent_poses)                                     # [K, N]
    safe = np.where(present[..., None], agent_poses, 0.0)
    ego_boxes = footprints(path, headings, ego_size[0], ego_size[1])    # [K, 4, 2]
    agent_boxes = footprints(safe[..., :2], safe[..., 2], agent_sizes[None, :, 0], agent_sizes[None, :, 1])
    finite = np.isfinite(ego_boxes).all((-1, -2))[:, None]
    return bool((overlapping(ego_boxes[:, None], agent_boxes) & present & finite).any())


# ----------------------------------------------------------------------------- run scores
@dataclass(frozen=True, eq=False)
class RunScores:
    """PDMS and HD-Score of one run: per-step values (arrays [T]) and run aggregates. Means and minima are None
    for an empty run."""

    nc: np.ndarray
    """NAVSIM no at-fault collision over each step's window: 0, 0.5 (static object) or 1."""
    dac: np.ndarray
    """NAVSIM drivable-area compliance over each step's window: 0 or 1."""
    ttc: np.ndarray
    """NAVSIM time-to-collision over each step's window: 0 or 1."""
    comfort: np.ndarray
    """NAVSIM comfort over each step's window: 0 or 1."""
    ep: np.ndarray
    """NAVSIM ego progress over each step's window, in [0, 1]."""
    pdms: np.ndarray
    """PDMS of each step: nc * dac * (5 ep + 5 ttc + 2 comfort) / 12."""
    hd_nc: np.ndarray
    """HUGSIM no-collision of each step's plan: 0 or 1."""
    hd_dac: np.ndarray
    """HUGSIM drivable-area compliance of each step's plan: 0, 0.5 or 1."""
    hd_ttc: np.ndarray
    """HUGSIM time-to-collision of each step's plan: 0 or 1."""
    hd_comfort: np.ndarray
    """HUGSIM comfort of each step's plan: 0 or 1."""
    hd_step: np.ndarray
    """HUGSIM score of each step: hd_nc * hd_dac * (5 hd_ttc + 2 hd_comfort) / 7."""
    rc: np.ndarray
    """Route completion reached by each step (running maximum), in [0, 1]."""
    offroad: np.ndarray
    """Whether the ego box had a non-drivable corner at each step (all False without a map)."""
    contacts: tuple
    """Per step, the tuple of Contacts at that step."""
    pdms_mean: float | None
    """Mean PDMS over the steps (the run's PDMS)."""
    hd_score: float | None
    """HUGSIM HD-Score: mean of hd_step times the final route completion."""
    route_completion: float
    """Route completion at the end of the run (maximum over the run, capped at 1)."""
    any_collision: bool
    """Whether the ego touched any agent at any step, whoever was at fault."""
    at_fault_collisions: int
    """Number of steps with at least one at-fault contact."""
    offroad_fraction: float | None
    """Fraction of steps with the ego box partly off the drivable area (0 without a map)."""
    has_map: bool
    """Whether the trace had a drivable map (DAC is 1 throughout without one)."""
    horizon_s: float
    """Length of the executed window each PDMS step was scored on (s)."""
    epdms: object | None = None
    """NAVSIM v2's EPDMS on the same windows (``omniscs.closedloop.epdms.EPDMSScores``); None when not scored."""

    SUB_SCORES = ("nc", "dac", "ttc", "comfort", "ep", "pdms", "hd_nc", "hd_dac", "hd_ttc", "hd_comfort", "hd_step")

    def stats(self) -> dict[str, dict[str, float | None]]:
        """Mean and minimum of each per-step sub-score (None for an empty run)."""
        return {name: {"mean": _mean(getattr(self, name)), "min": _minimum(getattr(self, name))}
                for name in self.SUB_SCORES}

    def to_dict(self) -> dict:
        """Plain JSON-able values (floats, ints, bools, lists, None where undefined); never NaN or Inf."""
        out = {"pdms": _json_float(self.pdms_mean), "hd_score": _json_float(self.hd_score),
               "route_completion": _json_float(self.route_completion), "any_collision": bool(self.any_collision),
               "at_fault_collisions": int(self.at_fault_collisions),
               "offroad_fraction": _json_float(self.offroad_fraction), "has_map": bool(self.has_map),
               "horizon_s": _json_float(self.horizon_s), "steps": int(len(self.pdms))}
        for name, stat in self.stats().items():
            out[f"{name}_mean"], out[f"{name}_min"] = _json_float(stat["mean"]), _json_float(stat["min"])
        out["per_step"] = {name: [_json_float(v) for v in getattr(self, name)] for name in self.SUB_SCORES + ("rc",)}
        out["per_step"]["offroad"] = [bool(v) for v in self.offroad]
        out["contacts"] = [{"step": int(step), "track": c.track, "kind": c.kind, "kind_of_contact": c.kind_of_contact,
                            "at_fault": bool(c.at_fault)} for step, found in enumerate(self.contacts) for c in found]
        if self.epdms is not None:
            extended = self.epdms.to_dict()
            per_step = extended.pop("per_step")
            out["epdms"] = extended["epdms"]
            out["epdms_scores"] = extended
            out["per_step"]["epdms"] = per_step["epdms"]
            for name in ("ddc", "tlc", "lk", "hc", "ec"):
                out["per_step"][name] = per_step[name]
            for name in ("nc", "dac", "ep", "ttc"):  # EPDMS's values after the human filter (and --ttc navsim)
                out["per_step"][f"epdms_{name}"] = per_step[name]
            extended["filtered_steps"] = {name: [k for k, f in enumerate(flags) if f]
                                          for name, flags in per_step["filtered"].items()}
        return out


def _mean(a: np.ndarray) -> float | None:
    return float(np.mean(a)) if len(a) else None


def _minimum(a: np.ndarray) -> float | None:
    return float(np.min(a)) if len(a) else None


def _json_float(value) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


def _plan_points(trace: RunTrace) -> int:
    """Waypoints of the executed-path stand-in: the first issued plan's length, else UniAD's 6."""
    return next((len(p) for p in trace.plans if p is not None), DEFAULT_PLAN_POINTS)


def _planned_path(trace: RunTrace, step: int, points: int) -> tuple[np.ndarray, np.ndarray]:
    """The path HUGSIM scores at a step, [K, 2] world, and the simulator step whose agents each pose meets, [K] int.

    The current ego centre, then the plan's waypoints; for a step with no plan, the executed ego centres at
    plan_dt, 2 plan_dt, ... up to ``points`` waypoints, linearly interpolated between steps and cut at the run's end.
    A waypoint at time k plan_dt meets the agents of step round(step + k plan_dt / dt), or the last step (where
    ``_hd_scores`` moves them on at their last velocity).
    """
    ratio = trace.plan_dt / trace.dt
    plan = trace.plans[step]
    if plan is None:
        at = step + ratio * np.arange(1, points + 1)
        at = at[at <= trace.steps - 1 + 1e-9]
        grid = np.arange(trace.steps, dtype=np.float64)
        plan = np.stack([np.interp(at, grid, trace.ego[:, 0]), np.interp(at, grid, trace.ego[:, 1])], -1)
    path = np.concatenate([trace.ego[step, None, :2], plan.reshape(-1, 2)], 0)
    meet = np.minimum(np.rint(step + ratio * np.arange(len(path))).astype(np.int64), trace.steps - 1)
    return path, meet


def _hd_scores(trace: RunTrace, step: int, points: int) -> tuple[float, float, float, float]:
    """HUGSIM's NC, DAC, TTC and comfort of the plan issued at a step (see score_run)."""
    path, meet = _planned_path(trace, step, points)
    headings = plan_headings(path, trace.ego[step, 2])
    agents = np.transpose(trace.agents[:, meet], (1, 0, 2)).copy()      # [K, N, 3]
    # HUGSIM holds the agents at the last recorded frame for waypoints past the run's end (a lead car keeping pace
    # then stands still in the plan's way); here they go on at their last velocity, yaw held.
    beyond = np.maximum(step + trace.plan_dt / trace.dt * np.arange(len(path)) - (trace.steps - 1), 0.0) * trace.dt
    if trace.agents.shape[0] and beyond.any():
        last_velocity = _finite_or_zero(trace.agent_velocity[:, -1])      # [N, 2]
        agents[..., :2] += beyond[:, None, None] * last_velocity[None]
    nc = 0.0 if _path_collides(path, headings, trace.ego_size, agents, trace.agent_sizes) else 1.0
    dac = hd_drivable_compliance(path, headings, trace.ego_size, trace.drivable)
    if len(path) >= 2:
        velocity = np.diff(path, axis=0) / trace.plan_dt
        velocity = np.concatenate([velocity[:1], velocity], 0)
    else:
        velocity = np.zeros_like(path)
    ttc = 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        for t in HD_TTC_TIMES_S:
            if _path_collides(path + velocity * t, headings, trace.ego_size, agents, trace.agent_sizes):
                ttc = 0.0
                break
    comfort = 1.0 if comfortable(path, headings, trace.plan_dt, HUGSIM_COMFORT, smooth=False) else 0.0
    return nc, dac, ttc, comfort


def score_run(trace: RunTrace, horizon_s: float = 4.0) -> RunScores:
    """Score a closed-loop run with NAVSIM's PDMS and HUGSIM's HD-Score (``RunScores.epdms`` stays None:
    ``omniscs.closedloop.epdms.score_with_epdms`` adds NAVSIM v2's EPDMS beside them, on the same windows).

    PDMS (Dauner et al., NAVSIM, NeurIPS 2024), per step t, over the window of steps t .. t + horizon_s / dt (cut
    at the run's end). NAVSIM simulates the issued plan for 4 s (LQR tracking on a kinematic bicycle) against
    non-reactive log agents; here the window is what the closed loop actually executed, against the agents as
    they actually moved.
    - NC: the worst step value of the window (``contact_nc``: 0 vehicle/VRU at fault, 0.5 static at fault, 1).
    - DAC: 0 when the ego box has a non-drivable corner at any step of the window; 1 without a map.
    - TTC: 0 when ``ttc_violated_at`` holds at any step of the window.
    - C: ``comfortable`` on the window's ego poses with nuPlan's bounds and Savitzky-Golay derivatives.
    - EP: ego progress along the route over the window over the reference's (log's) progress over the same
      times, clipped to [0, 1]; 1 when the reference progresses less than 5 m (NAVSIM's low-progress threshold;
      NAVSIM's reference is the PDM-Closed planner's progress, ours the log's).
    - PDMS_t = NC * DAC * (5 EP + 5 TTC + 2 C) / 12; the run's PDMS is the mean over steps.

    HD-Score (Zhou et al., HUGSIM, 2024), per step, on the plan issued at that step (a step with no plan uses the
    executed ego path over the next P plan_dt seconds, P the first plan's length or 6, resampled at plan_dt):
    the path is the current ego centre then the waypoints, headed by ``plan_headings``; every pose meets the
    agents of its time (``_planned_path``), of every kind.
    - NC_h: 0 when the ego box at any pose of the path overlaps an agent, else 1.
    - DAC_h: ``hd_drivable_compliance`` (0 / 0.5 / 1).
    - TTC_h: the path displaced by its own velocity (differences / plan_dt, the first pose taking the second's)
      times 0.5 s and 1.0 s; 0 when either displaced path fails NC_h, else 1.
    - C_h: ``comfortable`` on the path at plan_dt with HUGSIM's bounds and plain finite differences.
    - score_t = NC_h * DAC_h * (5 TTC_h + 2 C_h) / 7; HD-Score = mean_t(score_t) * RC, RC the route completion
      at the end of the run (maximum over the run, capped at 1).
    """
    horizon_s = float(horizon_s)
    if not np.isfinite(horizon_s) or horizon_s < 0:
        raise ValidationError(f"horizon_s is {horizon_s}; pass a finite window length >= 0 seconds")
    steps, (length, width) = trace.steps, trace.ego_size
    window = int(round(horizon_s / trace.dt))
    poses = trace.agents                                                       # [N, T, 3], absent: non-finite
    velocity = _finite_or_zero(trace.agent_velocity)

    contacts, nc_now, ttc_now = [], np.ones(steps), np.zeros(steps, dtype=bool)
    for t in range(steps):
        found = collisions_at(trace.ego[t], trace.ego_size, trace.ego_speed[t], poses[:, t], trace.agent_sizes,
                              trace.agent_kinds, velocity[:, t])
        contacts.append(tuple(found))
        nc_now[t] = contact_nc(found)
        ttc_now[t] = ttc_violated_at(trace.ego[t], trace.ego_size, trace.ego_speed[t], poses[:, t],
                                     trace.agent_sizes, velocity[:, t])
    has_map = trace.drivable is not None
    if has_map and steps:
        corners = footprints(trace.ego[:, :2], trace.ego[:, 2], length, width)   # [T, 4, 2]
        off_now = ~_drivable_mask(trace.drivable, corners.reshape(-1, 2)).reshape(steps, 4).all(-1)
    else:
        off_now = np.zeros(steps, dtype=bool)
    progress = progress_along(trace.ego[:, :2], trace.route)                      # [T]
    route_length = float(np.linalg.norm(np.diff(trace.route, axis=0), axis=1).sum())
    rc = np.maximum.accumulate(np.clip(progress / route_length, 0.0, 1.0)) if steps else np.zeros(0)

    nc, dac, ttc, comfort, ep = (np.ones(steps) for _ in range(5))
    for t in range(steps):
        end = min(steps - 1, t + window)
        span = slice(t, end + 1)
        nc[t] = nc_now[span].min()
        dac[t] = 0.0 if off_now[span].any() else 1.0
        ttc[t] = 0.0 if ttc_now[span].any() else 1.0
        comfort[t] = 1.0 if comfortable(trace.ego[span, :2], trace.ego[span, 2], trace.dt, NAVSIM_COMFORT) else 0.0
        reference = trace.reference_progress[end] - trace.reference_progress[t]
        if reference >= LOW_PROGRESS_M:
            ratio = (progress[end] - progress[t]) / reference
            ep[t] = float(np.clip(ratio, 0.0, 1.0)) if np.isfinite(ratio) else 0.0
    w = PDMS_WEIGHTS
    pdms = nc * dac * (w["ep"] * ep + w["ttc"] * ttc + w["comfort"] * comfort) / sum(w.values())

    hd = np.ones((4, steps))
    points = _plan_points(trace)
    for t in range(steps):
        hd[:, t] = _hd_scores(trace, t, points)
    hd_nc, hd_dac, hd_ttc, hd_comfort = hd
    w = HD_WEIGHTS
    hd_step = hd_nc * hd_dac * (w["ttc"] * hd_ttc + w["comfort"] * hd_comfort) / sum(w.values())
    final_rc = float(rc[-1]) if steps else 0.0
    scores = RunScores(
        nc=nc, dac=dac, ttc=ttc, comfort=comfort, ep=ep, pdms=pdms, hd_nc=hd_nc, hd_dac=hd_dac, hd_ttc=hd_ttc,
        hd_comfort=hd_comfort, hd_step=hd_step, rc=rc, offroad=off_now, contacts=tuple(contacts),
        pdms_mean=_mean(pdms), hd_score=None if not steps else float(np.mean(hd_step)) * final_rc,
        route_completion=final_rc, any_collision=any(bool(c) for c in contacts),
        at_fault_collisions=int(sum(any(c.at_fault for c in found) for found in contacts)),
        offroad_fraction=_mean(off_now.astype(np.float64)), has_map=has_map, horizon_s=horizon_s)
    return scores
