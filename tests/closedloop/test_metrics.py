"""Closed-loop scores (NAVSIM PDMS, HUGSIM HD-Score) on hand-made runs whose answers are known."""
from __future__ import annotations

import json

import numpy as np
import pytest

from omniscs.closedloop import metrics
from omniscs.closedloop.metrics import RunTrace, score_run
from omniscs.errors import ValidationError

DT = 0.1
EGO_SIZE = (4.5, 2.0)


class Rectangle:
    """Drivable inside an axis-aligned rectangle."""

    def __init__(self, x0, x1, y0, y1):
        self.bounds = (x0, x1, y0, y1)

    def is_drivable(self, xy):
        x0, x1, y0, y1 = self.bounds
        xy = np.asarray(xy)
        return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)


class HalfPlane:
    """Drivable where x <= limit (and, optionally, y <= y_limit)."""

    def __init__(self, limit, y_limit=np.inf):
        self.limit, self.y_limit = limit, y_limit

    def is_drivable(self, xy):
        xy = np.asarray(xy)
        return (xy[:, 0] <= self.limit) & (xy[:, 1] <= self.y_limit)


WIDE_ROAD = Rectangle(-100.0, 1000.0, -10.0, 10.0)


def straight(speed, steps, x0=0.0, accel=0.0):  # -> ego [T, 3], speed [T]
    t = np.arange(steps) * DT
    v = np.maximum(speed + accel * t, 0.0)
    x = x0 + speed * t + 0.5 * accel * t ** 2
    return np.stack([x, np.zeros(steps), np.zeros(steps)], 1), v


def agent_track(x0, vx, steps, y=0.0):  # -> poses [T, 3], velocity [T, 2]
    t = np.arange(steps) * DT
    poses = np.stack([x0 + vx * t, np.full(steps, y), np.zeros(steps)], 1)
    return poses, np.tile([vx, 0.0], (steps, 1))


def make_trace(ego, speed, tracks=(), plans=None, route=None, reference=None, drivable=WIDE_ROAD, **overrides):
    """tracks: (poses [T, 3], velocity [T, 2], kind, (length, width)) per agent."""
    steps = len(ego)
    n = len(tracks)
    fields = dict(
        dt=DT, ego=ego, ego_speed=speed, ego_size=EGO_SIZE,
        agents=np.stack([p for p, _, _, _ in tracks]) if n else np.zeros((0, steps, 3)),
        agent_sizes=np.array([s for _, _, _, s in tracks]) if n else np.zeros((0, 2)),
        agent_kinds=tuple(k for _, _, k, _ in tracks),
        agent_velocity=np.stack([v for _, v, _, _ in tracks]) if n else np.zeros((0, steps, 2)),
        plans=tuple(plans) if plans is not None else (None,) * steps, plan_dt=0.5,
        route=np.array([[0.0, 0.0], [100.0, 0.0]]) if route is None else route,
        reference_progress=ego[:, 0] - ego[0, 0] if reference is None else reference,
        drivable=drivable)
    fields.update(overrides)
    return RunTrace(**fields)


def uniad_plans(ego, speed):
    """A plan per step continuing at the current speed: 6 waypoints at 0.5 s."""
    k = np.arange(1, 7)[:, None] * 0.5
    return [np.stack([e[0] + s * k[:, 0], np.full(6, e[1])], 1) for e, s in zip(ego, speed)]


def assert_json_clean(scores):
    text = json.dumps(scores.to_dict(), allow_nan=False)  # raises on NaN / Inf
    assert "NaN" not in text and "Infinity" not in text


# ----------------------------------------------------------------------------- whole runs
def test_straight_drive_on_an_empty_road_scores_pdms_one_and_hd_score_equal_to_route_completion():
    ego, speed = straight(10.0, 31)
    scores = score_run(make_trace(ego, speed, plans=uniad_plans(ego, speed)))
    assert scores.pdms_mean == pytest.approx(1.0)
    assert np.all(scores.pdms == 1.0) and np.all(scores.hd_step == 1.0)
    assert scores.route_completion == pytest.approx(0.30)
    assert scores.hd_score == pytest.approx(scores.route_completion)
    assert not scores.any_collision and scores.at_fault_collisions == 0 and scores.offroad_fraction == 0.0
    assert_json_clean(scores)


def test_steps_without_a_plan_are_scored_on_the_executed_path():
    ego, speed = straight(10.0, 31)
    scores = score_run(make_trace(ego, speed))
    assert np.all(scores.hd_step == 1.0)
    assert scores.hd_score == pytest.approx(0.30)


def test_head_on_agent_zeroes_nc_and_pdms_at_steps_whose_window_holds_the_contact():
    steps = 21
    ego, speed = straight(10.0, steps)
    oncoming = agent_track(30.0, -10.0, steps) + ("vehicle", (4.5, 2.0))
    scores = score_run(make_trace(ego, speed, [oncoming]))
    first = next(k for k, c in enumerate(scores.contacts) if c)
    assert first == 13  # centres 30 - 20 t apart touch when closer than 4.5 m: t = 1.275 s
    hit = scores.contacts[first][0]
    assert hit.kind_of_contact == "active_front" and hit.at_fault and hit.kind == "vehicle"
    blamed = [k for k, c in enumerate(scores.contacts) if any(x.at_fault for x in c)]
    window = int(round(4.0 / DT))
    for t in range(steps):
        holds_blamed = any(t <= k <= t + window for k in blamed)
        assert scores.nc[t] == (0.0 if holds_blamed else 1.0)
        if holds_blamed:
            assert scores.pdms[t] == 0.0
    assert scores.at_fault_collisions == len(blamed) >= 1 and scores.any_collision
    assert scores.hd_nc[0] == 0.0  # the plan-less step 0 path (executed) runs into the agent too


def test_stopped_ego_hit_from_behind_is_not_at_fault():
    steps = 21
    ego, speed = straight(0.0, steps)
    chaser = agent_track(-10.0, 5.0, steps) + ("vehicle", (4.5, 2.0))
    scores = score_run(make_trace(ego, speed, [chaser], reference=np.zeros(steps)))
    kinds = {c.kind_of_contact for found in scores.contacts for c in found}
    assert kinds == {"stopped_ego"} and scores.any_collision
    assert np.all(scores.nc == 1.0) and scores.at_fault_collisions == 0


def test_moving_ego_rear_ended_is_not_at_fault():
    steps = 13  # the chaser (10 m behind, 5 m/s faster) touches at 1.1 s; stop before it passes through
    ego, speed = straight(5.0, steps)
    chaser = agent_track(-10.0, 10.0, steps) + ("vehicle", (4.5, 2.0))
    scores = score_run(make_trace(ego, speed, [chaser]))
    found = [c for cs in scores.contacts for c in cs]
    assert found and all(c.kind_of_contact == "active_rear" and not c.at_fault for c in found)
    assert np.all(scores.nc == 1.0) and np.all(scores.ttc == 1.0)


def test_hitting_a_static_cone_gives_nc_one_half():
    steps = 21
    ego, speed = straight(10.0, steps)
    cone = agent_track(15.0, 0.0, steps) + ("static", (0.4, 0.4))
    scores = score_run(make_trace(ego, speed, [cone]))
    found = [c for cs in scores.contacts for c in cs]
    assert found and all(c.kind_of_contact == "stopped_track" and c.at_fault for c in found)
    assert scores.nc[0] == 0.5 and scores.nc.min() == 0.5
    assert scores.pdms[0] == pytest.approx(0.5 * (5 * 1 + 5 * scores.ttc[0] + 2 * 1) / 12)


def test_a_parked_vehicle_hit_is_a_full_collision():
    steps = 21
    ego, speed = straight(10.0, steps)
    parked = agent_track(15.0, 0.0, steps) + ("vehicle", (4.5, 2.0))
    assert score_run(make_trace(ego, speed, [parked])).nc[0] == 0.0


def test_side_contact_is_active_lateral_and_at_fault():
    contacts = metrics.collisions_at(np.array([0.0, 0.0, 0.0]), EGO_SIZE, 5.0, np.array([[0.0, 1.8, 0.0]]),
                                     np.array([[4.5, 2.0]]), ("vehicle",), np.array([[5.0, 0.0]]))
    assert [(c.kind_of_contact, c.at_fault) for c in contacts] == [("active_lateral", True)]


def test_driving_off_the_drivable_area_gives_dac_zero():
    steps = 21
    ego, speed = straight(10.0, steps)
    road = Rectangle(-10.0, 15.0, -5.0, 5.0)  # the front corners leave it once x > 12.75
    scores = score_run(make_trace(ego, speed, drivable=road))
    assert scores.dac[0] == 0.0 and scores.has_map
    assert scores.offroad.tolist() == [x + 2.25 > 15.0 for x in ego[:, 0]]
    assert scores.offroad_fraction == pytest.approx(np.mean(ego[:, 0] + 2.25 > 15.0))
    on_road = score_run(make_trace(ego, speed, drivable=WIDE_ROAD))
    assert np.all(on_road.dac == 1.0)


def test_no_map_means_dac_one_and_has_map_false():
    ego, speed = straight(10.0, 11)
    scores = score_run(make_trace(ego, speed, drivable=None))
    assert not scores.has_map and np.all(scores.dac == 1.0) and np.all(scores.hd_dac == 1.0)


def test_hard_brake_fails_comfort_and_a_gentle_one_passes():
    ego, speed = straight(20.0, 21, accel=-8.0)
    assert score_run(make_trace(ego, speed)).comfort[0] == 0.0
    ego, speed = straight(20.0, 21, accel=-2.0)
    assert np.all(score_run(make_trace(ego, speed)).comfort == 1.0)


def test_a_steady_turn_across_the_yaw_seam_is_comfortable_and_a_sharp_one_is_not():
    t = np.arange(41) * DT

    def arc(radius, speed):
        yaw = np.pi - 0.5 + speed / radius * t  # passes +pi, where yaw wraps
        centre = np.array([0.0, 0.0])
        xy = centre + radius * np.stack([np.cos(yaw - np.pi / 2), np.sin(yaw - np.pi / 2)], 1)
        return xy, metrics.wrap_angle(yaw)

    xy, yaw = arc(20.0, 5.0)  # yaw rate 0.25 rad/s, lateral accel 1.25 m/s^2
    assert metrics.comfortable(xy, yaw, DT)
    xy, yaw = arc(5.0, 10.0)  # yaw rate 2 rad/s
    assert not metrics.comfortable(xy, yaw, DT)


def test_savitzky_golay_smoothing_absorbs_centimetre_jitter_that_raw_differences_flag():
    t = np.arange(41) * DT
    xy = np.stack([10.0 * t, np.zeros_like(t)], 1)
    xy[20, 0] += 0.02
    assert metrics.comfortable(xy, np.zeros_like(t), DT, smooth=True)
    assert not metrics.comfortable(xy, np.zeros_like(t), DT, smooth=False)


def test_agent_closing_fast_five_metres_ahead_fails_ttc_and_one_fifty_metres_ahead_passes():
    ego = np.array([0.0, 0.0, 0.0])

    def violated(gap):
        ahead = np.array([[gap + 4.5, 0.0, 0.0]])  # centre distance = gap + half lengths
        return metrics.ttc_violated_at(ego, EGO_SIZE, 5.0, ahead, np.array([[4.5, 2.0]]), np.array([[-5.0, 0.0]]))

    assert violated(5.0) and not violated(50.0)
    steps = 11
    e, s = straight(5.0, steps)
    for gap, expected in ((5.0, 0.0), (50.0, 1.0)):
        track = agent_track(gap + 4.5, -5.0, steps) + ("vehicle", (4.5, 2.0))
        assert score_run(make_trace(e, s, [track])).ttc[0] == expected


def test_ttc_ignores_agents_behind_and_a_stopped_ego():
    behind = np.array([[-6.0, 0.0, 0.0]])
    args = (EGO_SIZE,)
    assert not metrics.ttc_violated_at(np.zeros(3), *args, 5.0, behind, np.array([[4.5, 2.0]]), np.array([[20.0, 0]]))
    ahead = np.array([[6.0, 0.0, 0.0]])
    assert not metrics.ttc_violated_at(np.zeros(3), *args, 0.0, ahead, np.array([[4.5, 2.0]]), np.array([[-9.0, 0]]))


def test_ep_is_one_half_when_the_ego_covers_half_the_reference_progress():
    ego, speed = straight(5.0, 41)
    scores = score_run(make_trace(ego, speed, reference=np.arange(41) * DT * 10.0))
    assert scores.ep[0] == pytest.approx(0.5)


def test_ep_is_one_under_five_metres_of_reference_progress_and_zero_above_for_a_stopped_ego():
    ego, speed = straight(0.0, 41)
    slow = score_run(make_trace(ego, speed, reference=np.arange(41) * DT * 1.0))  # 4 m in 4 s
    assert np.all(slow.ep == 1.0)
    fast = score_run(make_trace(ego, speed, reference=np.arange(41) * DT * 2.0))  # 8 m in 4 s
    assert fast.ep[0] == 0.0


def test_hd_ttc_fails_when_the_plan_stops_just_short_of_a_parked_car():
    steps = 11
    ego, speed = straight(0.0, steps)
    plan = np.stack([np.linspace(2.0, 12.0, 6), np.zeros(6)], 1)  # ends 1.25 m short of the parked car's rear
    parked = agent_track(17.5, 0.0, steps) + ("vehicle", (4.5, 2.0))
    scores = score_run(make_trace(ego, speed, [parked], plans=[plan] + [None] * (steps - 1),
                                  reference=np.zeros(steps)))
    assert scores.hd_nc[0] == 1.0 and scores.hd_ttc[0] == 0.0
    assert scores.hd_step[0] == pytest.approx(2.0 / 7.0 * scores.hd_comfort[0])
    through = np.stack([np.linspace(4.0, 24.0, 6), np.zeros(6)], 1)
    scores = score_run(make_trace(ego, speed, [parked], plans=[through] + [None] * (steps - 1),
                                  reference=np.zeros(steps)))
    assert scores.hd_nc[0] == 0.0 and scores.hd_step[0] == 0.0


def test_hugsim_dac_counts_drivable_cells_of_the_footprint():
    path, headings, size = np.zeros((1, 2)), np.zeros(1), (4.0, 2.0)  # 2 x 2 cell centres at (+-1, +-0.5)
    dac = metrics.hd_drivable_compliance
    assert dac(path, headings, size, HalfPlane(10.0)) == 1.0
    # HUGSIM's strict thresholds on a 2 x 2 grid: half the cells off the road (r = 0.5) still pass ...
    assert dac(path, headings, size, HalfPlane(0.0)) == 1.0
    # ... and one drivable cell of four (r = 0.25) fails
    assert dac(path, headings, size, HalfPlane(0.0, y_limit=0.0)) == 0.0
    # the 0.5 tier: on a 3 x 3 grid, the rear third drivable (r = 1/3)
    assert dac(path, headings, size, HalfPlane(-0.5), cells=(3, 3)) == 0.5
    assert dac(path, headings, size, None) == 1.0


def test_hugsim_dac_in_a_run_passes_half_the_cells_off_road_and_fails_three_of_four():
    steps = 11
    ego, speed = straight(0.0, steps)
    scores = score_run(make_trace(ego, speed, drivable=HalfPlane(-0.5), reference=np.zeros(steps)))
    assert np.all(scores.hd_dac == 1.0)  # rear two cells drivable: r = 0.5 passes under HUGSIM's rule
    scores = score_run(make_trace(ego, speed, drivable=HalfPlane(-0.5, y_limit=0.0), reference=np.zeros(steps)))
    assert np.all(scores.hd_dac == 0.0) and np.all(scores.hd_step == 0.0)


def test_plan_headings_keep_the_current_yaw_for_a_short_plan():
    short = np.array([[0.0, 0.0], [0.3, 0.3], [0.5, 0.6]])
    assert np.all(metrics.plan_headings(short, 0.7) == 0.7)
    long = np.array([[0.0, 0.0], [0.0, 2.0], [0.0, 2.0], [2.0, 2.0]])
    assert np.allclose(metrics.plan_headings(long, 0.1), [0.1, np.pi / 2, np.pi / 2, 0.0])


# ----------------------------------------------------------------------------- route completion
def test_route_completion_is_monotone_and_within_zero_and_one():
    route = np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 50.0]])  # 100 m
    xs = np.concatenate([np.linspace(-20, 50, 30), np.linspace(50, 10, 10)])
    xy = np.stack([xs, np.zeros_like(xs)], 1)
    assert metrics.route_completion(xy, route) == pytest.approx(0.5)
    assert metrics.route_completion(np.array([50.0, 80.0]), route) == 1.0
    assert metrics.route_completion(np.array([-30.0, 5.0]), route) == 0.0
    assert np.allclose(metrics.progress_along(np.array([[25.0, 3.0], [52.0, 20.0]]), route), [25.0, 70.0])
    ego = np.concatenate([xy, np.zeros((len(xy), 1))], 1)
    scores = score_run(make_trace(ego, np.zeros(len(xy)), route=route, reference=np.zeros(len(xy)), drivable=None))
    assert np.all(np.diff(scores.rc) >= 0) and scores.rc.min() >= 0.0 and scores.rc.max() <= 1.0
    assert scores.route_completion == pytest.approx(0.5)


def test_zero_length_route_raises():
    with pytest.raises(ValidationError):
        metrics.route_completion(np.zeros(2), np.array([[1.0, 1.0], [1.0, 1.0]]))
    ego, speed = straight(1.0, 3)
    with pytest.raises(ValidationError):
        make_trace(ego, speed, route=np.array([[2.0, 0.0], [2.0, 0.0], [2.0, 0.0]]))


# ----------------------------------------------------------------------------- validation and extremes
def test_malformed_ego_raises_validation_errors():
    ego, speed = straight(1.0, 5)
    bad = ego.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ValidationError):
        make_trace(bad, speed)
    with pytest.raises(ValidationError):
        make_trace(ego[:, :2], speed)
    with pytest.raises(ValidationError):
        make_trace(ego, speed[:-1])
    with pytest.raises(ValidationError):
        make_trace(ego, speed, plans=[np.full((6, 2), np.inf)] + [None] * 4)
    with pytest.raises(ValidationError):
        make_trace(ego, speed, [agent_track(5.0, 0.0, 5) + ("truck", (4.5, 2.0))])


def test_a_single_step_and_an_empty_run_still_score():
    ego, speed = straight(3.0, 1)
    one = score_run(make_trace(ego, speed, plans=[np.array([[1.5, 0.0]])]))
    assert one.pdms.tolist() == [1.0] and one.hd_step.tolist() == [1.0]
    assert_json_clean(one)
    empty = score_run(make_trace(np.zeros((0, 3)), np.zeros(0), reference=np.zeros(0)))
    d = empty.to_dict()
    assert d["pdms"] is None and d["hd_score"] is None and d["route_completion"] == 0.0 and d["steps"] == 0
    assert_json_clean(empty)


def test_far_absent_and_missing_agents_change_nothing():
    steps = 21
    ego, speed = straight(10.0, steps)
    far = agent_track(10_000.0, -30.0, steps, y=10_000.0) + ("vehicle", (4.5, 2.0))
    ghost = agent_track(15.0, 0.0, steps) + ("vehicle", (4.5, 2.0))
    ghost[0][:] = np.nan  # absent at every step: would be hit if present
    ghost[1][:] = np.nan
    partly = agent_track(15.0, 0.0, steps) + ("vehicle", (4.5, 2.0))
    partly[0][:, 0] = np.nan  # one non-finite component: absent
    base = score_run(make_trace(ego, speed)).to_dict()
    for tracks in ([far], [ghost], [partly], [far, ghost, partly]):
        got = score_run(make_trace(ego, speed, tracks)).to_dict()
        assert got["per_step"] == base["per_step"] and got["pdms"] == base["pdms"] and not got["any_collision"]


def test_huge_speeds_and_coordinates_never_give_nan_or_inf():
    steps = 21
    ego, speed = straight(1e6, steps, x0=1e7)
    rocket = agent_track(1e7 + 50.0, -1e6, steps) + ("vru", (0.5, 0.5))
    plans = [p * 1.0 for p in uniad_plans(ego, speed)]
    scores = score_run(make_trace(ego, speed, [rocket], plans=plans, reference=np.arange(steps) * 1e5,
                                  drivable=Rectangle(-1e12, 1e12, -10.0, 10.0)))
    assert_json_clean(scores)
    for name in scores.SUB_SCORES:
        values = getattr(scores, name)
        assert np.all(np.isfinite(values)) and values.min() >= 0.0 and values.max() <= 1.0
    assert scores.comfort.min() == 1.0  # constant speed, however large, is comfortable


def test_to_dict_is_plain_json_with_stats_and_contacts():
    steps = 21
    ego, speed = straight(10.0, steps)
    cone = agent_track(15.0, 0.0, steps) + ("static", (0.4, 0.4))
    d = score_run(make_trace(ego, speed, [cone])).to_dict()
    assert json.loads(json.dumps(d, allow_nan=False)) == d
    assert d["nc_min"] == 0.5 and d["contacts"][0]["kind_of_contact"] == "stopped_track"
    assert set(d["per_step"]) >= {"pdms", "hd_step", "nc", "ep", "rc", "offroad"}
    assert all(isinstance(v, float) for v in d["per_step"]["pdms"])
