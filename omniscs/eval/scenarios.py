"""Driving scenarios as planning examples: a recorded or procedural log (its traffic) or a behaviour-SCS variant
(its agents, with the ego on its solution), cut into keyframes with 6 future waypoints at 0.5 s, each in UniAD's
planning frame (``omniscs.eval.planning``).

The waypoint of a step is the point ``EGO_SHIFT`` (0.5 m) behind the centre of the ego's box, so UniAD's ego box
(centred 0.5 m ahead of the waypoint) lands on the ego's own box; the frame has x to the ego's right and y along its
heading. What a planner may see at a keyframe (``PlanningInput``): the agents' boxes now and ``HISTORY_S`` before,
the drivable area when the scene has a map, the ego's speed and yaw rate, and UniAD's driving command (from the
true future: right / left when its last waypoint is 2 m or more to the side)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omniscs.errors import ValidationError
from omniscs.eval.planning import EGO_SHIFT, STEP_S, STEPS, PlanningSample
from omniscs.taxonomy import VEHICLE_CATEGORIES

#: How far back the planner sees the agents (s).
HISTORY_S = 0.5
COMMANDS = ("right", "left", "forward")


@dataclass(frozen=True)
class Scenario:
    """The ego and the agents of one log or variant on steps of ``dt`` seconds (world frame, box centres)."""

    scenario_id: str
    dt: float
    ego: np.ndarray          # [S, 3] x, y, yaw of the ego box centre
    track_ids: np.ndarray    # [N]
    categories: tuple[str, ...]
    sizes: np.ndarray        # [N, 2] length, width
    agents: np.ndarray       # [N, S, 3] x, y, yaw (NaN where absent)
    drivable: object | None = None  # a map with ``is_drivable(points [K, 2]) -> bool [K]`` (world frame), or None

    def __post_init__(self):
        S = len(self.ego)
        if self.agents.shape != (len(self.track_ids), S, 3) or self.sizes.shape != (len(self.track_ids), 2):
            raise ValidationError(f"scenario {self.scenario_id}: agents must be [N, {S}, 3] and sizes [N, 2]")
        if not np.isfinite(self.ego).all() or not (self.dt > 0):
            raise ValidationError(f"scenario {self.scenario_id}: the ego needs a finite pose at every step, dt > 0")

    @property
    def vehicle(self) -> np.ndarray:  # [N] bool
        return np.array([c in VEHICLE_CATEGORIES for c in self.categories], bool)


def scenario_from_traffic(traffic) -> Scenario:
    """A log's traffic (``omniscs.scs.behavior.TrafficScene``) as a scenario: the ego as logged."""
    agents = np.concatenate([traffic.xy, traffic.yaw[..., None]], -1).astype(np.float64)
    agents[~traffic.present] = np.nan
    ego = np.concatenate([traffic.ego_xy, traffic.ego_yaw[:, None]], -1)
    return Scenario(traffic.scene_id, float(traffic.dt), ego, np.asarray(traffic.track_ids), tuple(traffic.categories),
                    np.asarray(traffic.sizes, np.float64)[:, :2], agents, traffic.map)


def scenario_from_variant(variant: dict, categories: dict[int, str], ego: np.ndarray | None = None,
                          drivable=None) -> Scenario:
    """A behaviour variant (a ``variants.json`` entry) as a scenario; ``ego`` ([S, 3] box centre, e.g. the ego's
    solution) replaces the variant's ego plan; ``categories`` names each track's class (from its scene)."""
    plan = np.asarray(ego if ego is not None else variant["ego"], np.float64)
    ids = sorted(int(k) for k in variant["agents"])
    agents = np.stack([_poses(variant["agents"][str(k)], len(plan)) for k in ids]) if ids \
        else np.zeros((0, len(plan), 3))
    sizes = np.array([variant["sizes"][str(k)][:2] for k in ids], np.float64).reshape(-1, 2)
    unknown = [k for k in ids if k not in categories]
    if unknown:
        raise ValidationError(f"variant {variant.get('variant_id')}: no category for track(s) {unknown}")
    return Scenario(f"{variant.get('scene_id')}/{variant.get('variant_id')}", float(variant["dt"]), plan,
                    np.array(ids, np.int64), tuple(categories[k] for k in ids), sizes, agents, drivable)


def _poses(rows: list, n: int) -> np.ndarray:  # [n, 3], NaN where a step is null (the agent is absent)
    out = np.full((n, 3), np.nan)
    for i, r in enumerate(rows[:n]):
        if r is not None and len(r) >= 3 and all(v is not None for v in r[:3]):
            out[i] = np.asarray(r[:3], np.float64)
    return out


def waypoint_frames(ego: np.ndarray) -> np.ndarray:  # [S, 3] box centres -> [S, 3, 3] world_from_planning (2D)
    """Each step's planning frame: origin EGO_SHIFT behind the box centre, x to the right, y along the heading."""
    c, s = np.cos(ego[:, 2]), np.sin(ego[:, 2])
    T = np.zeros((len(ego), 3, 3))
    T[:, 0, 0], T[:, 1, 0] = s, -c        # x axis: the ego's right
    T[:, 0, 1], T[:, 1, 1] = c, s         # y axis: heading
    T[:, 0, 2] = ego[:, 0] - EGO_SHIFT * c
    T[:, 1, 2] = ego[:, 1] - EGO_SHIFT * s
    T[:, 2, 2] = 1.0
    return T


def to_frame(world_from_frame: np.ndarray, xy: np.ndarray) -> np.ndarray:  # [3, 3], [..., 2] -> [..., 2]
    R, t = world_from_frame[:2, :2], world_from_frame[:2, 2]
    return (np.asarray(xy) - t) @ R


def command_of(trajectory: np.ndarray) -> str:
    """UniAD's driving command from the last waypoint's lateral offset (x >= 2 m right, <= -2 m left)."""
    x = float(trajectory[-1, 0])
    return "right" if x >= 2.0 else "left" if x <= -2.0 else "forward"


@dataclass(frozen=True)
class PlanningInput:
    """What a planner sees at one keyframe (planning frame)."""

    boxes_now: np.ndarray    # [B, 6] x, y, length, width, yaw, is_vehicle
    boxes_past: np.ndarray   # [B', 6] the same HISTORY_S before
    speed: float             # m/s
    yaw_rate: float          # rad/s
    command: str
    world_from_frame: np.ndarray  # [3, 3]


@dataclass(frozen=True)
class PlanningExample:
    """One keyframe: the input, and the truth the metrics need."""

    sample: PlanningSample
    inputs: PlanningInput
    scenario: Scenario
    step: int


def _boxes(scenario: Scenario, step: int, frame: np.ndarray, vehicles_only: bool) -> np.ndarray:
    """[B, 6] boxes present at ``step`` in ``frame`` (x, y, length, width, yaw, is_vehicle)."""
    keep = scenario.vehicle if vehicles_only else np.ones(len(scenario.track_ids), bool)
    return boxes_in_frame(scenario.agents[keep, step], scenario.sizes[keep], scenario.vehicle[keep], frame)


def boxes_in_frame(pose: np.ndarray,     # [N, 3] world x, y, yaw (NaN rows = absent)
                   sizes: np.ndarray,    # [N, 2] length, width
                   vehicle: np.ndarray,  # [N] bool
                   frame: np.ndarray,    # [3, 3] world_from_planning
                   ) -> np.ndarray:      # [B, 6] x, y, length, width, yaw (from the frame's x axis), is_vehicle
    """The present boxes in a planning frame."""
    keep = np.isfinite(pose).all(-1)
    if not keep.any():
        return np.zeros((0, 6))
    xy = to_frame(frame, pose[keep, :2])
    heading = np.arctan2(frame[1, 1], frame[0, 1])  # the frame's y axis (the ego's heading) in the world
    yaw = pose[keep, 2] - heading + np.pi / 2  # yaw measured from the frame's x axis
    return np.column_stack([xy, np.asarray(sizes)[keep], yaw, np.asarray(vehicle)[keep].astype(np.float64)])


def planning_examples(scenario: Scenario, start: int = 0, stride_s: float = STEP_S,
                      min_known: int = STEPS) -> list[PlanningExample]:
    """Every keyframe from ``start`` (one each ``stride_s``) that has the HISTORY_S before it and at least
    ``min_known`` of its STEPS future waypoints at STEP_S. Waypoints past the scenario's end are masked out (UniAD's
    ``sdc_planning_mask``): zero, with no vehicles at those steps, so they add nothing to L2 or collisions; the
    command then reads the last known waypoint."""
    per_step = STEP_S / scenario.dt
    k = int(round(per_step))
    if abs(per_step - k) > 1e-6 or k < 1:
        raise ValidationError(f"scenario {scenario.scenario_id}: dt {scenario.dt} s does not divide {STEP_S} s")
    if not 1 <= min_known <= STEPS:
        raise ValidationError(f"min_known must be 1..{STEPS} future waypoints; got {min_known}")
    back = int(round(HISTORY_S / scenario.dt))
    stride = max(1, int(round(stride_s / scenario.dt)))
    frames = waypoint_frames(scenario.ego)
    S = len(scenario.ego)
    out = []
    for t in range(max(start, back), S - min_known * k, stride):
        frame = frames[t]
        future = [t + k * (i + 1) for i in range(STEPS)]
        known = np.array([f < S for f in future])
        trajectory = np.zeros((STEPS, 2))
        trajectory[known] = to_frame(frame, frames[[f for f in future if f < S], :2, 2])
        vehicles = tuple(_boxes(scenario, f, frame, vehicles_only=True)[:, :5] if f < S else np.zeros((0, 5))
                         for f in future)
        now = _boxes(scenario, t, frame, vehicles_only=False)
        past = _boxes(scenario, t - back, frame, vehicles_only=False)
        moved = to_frame(frame, frames[t - back, :2, 2])
        speed = float(np.linalg.norm(moved) / (back * scenario.dt)) if back else 0.0
        yaw_rate = float(np.angle(np.exp(1j * (scenario.ego[t, 2] - scenario.ego[t - back, 2]))) / (back * scenario.dt)) \
            if back else 0.0
        command = command_of(trajectory[known])
        sample = PlanningSample(f"{scenario.scenario_id}@{t}", trajectory, known, vehicles, command)
        out.append(PlanningExample(sample, PlanningInput(now, past, speed, yaw_rate, command, frame),
                                   scenario, t))
    return out


#: Behaviour-SCS keyframes need at least this many known future waypoints (1 s).
SCS_MIN_KNOWN = 2


def variant_keyframes(scenario: Scenario, now_step: int) -> list[PlanningExample]:
    """The planning examples of a behaviour variant (ego on its solution): its now step and every 0.5 s after it
    while at least ``SCS_MIN_KNOWN`` future waypoints are known. A variant spans the traffic model's 3 s future,
    so only the now step has all six; the later keyframes are the ones that see the adversary leave its logged path
    (the cut-in itself), with their future masked past the variant's end."""
    return planning_examples(scenario, start=now_step, min_known=SCS_MIN_KNOWN)
