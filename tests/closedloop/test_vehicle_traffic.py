"""The ego's bicycle model, the pure-pursuit tracker and the other agents (replayed, or braking by IDM), without
rendering: hand-made scenarios whose answers are known."""
from __future__ import annotations

import math

import numpy as np
import pytest

from omniscs.closedloop.scenario import ClosedLoopScenario, interpolate_pose
from omniscs.closedloop.traffic import IDMConfig, Traffic, idm_accel
from omniscs.closedloop.vehicle import (Controls, PurePursuitConfig, VehicleLimits, VehicleState, advance,
                                        plan_to_ego, pure_pursuit)
from omniscs.errors import ValidationError

LIMITS = VehicleLimits()


def test_zero_controls_drive_straight_at_constant_speed():
    s = advance(VehicleState(0.0, 0.0, 0.3, 5.0, 0.0), Controls(0.0, 0.0), 2.0)
    assert s.x == pytest.approx(10 * math.cos(0.3)) and s.y == pytest.approx(10 * math.sin(0.3))
    assert s.speed == pytest.approx(5.0) and s.yaw == pytest.approx(0.3)


def test_constant_steer_turns_at_the_bicycle_models_yaw_rate_on_a_circle():
    steer, v, t = 0.2, 4.0, 3.0
    s = advance(VehicleState(0.0, 0.0, 0.0, v, steer), Controls(0.0, 0.0), t)
    yaw = v * math.tan(steer) / LIMITS.wheelbase_m * t
    radius = LIMITS.wheelbase_m / math.tan(steer)
    assert s.yaw == pytest.approx(yaw, rel=1e-6)
    assert s.x == pytest.approx(radius * math.sin(yaw), abs=1e-3)
    assert s.y == pytest.approx(radius * (1 - math.cos(yaw)), abs=1e-3)


def test_braking_stops_without_reversing_and_controls_are_clipped_to_the_limits():
    s = advance(VehicleState(0.0, 0.0, 0.0, 2.0, 0.0), Controls(-100.0, 50.0), 1.0)
    assert s.speed == 0.0 and s.accel == -LIMITS.max_decel and s.steer_rate == LIMITS.max_steer_rate
    assert math.hypot(s.x, s.y) == pytest.approx(2.0 ** 2 / (2 * LIMITS.max_decel), abs=2e-3)  # v²/2a
    assert abs(s.steer) <= LIMITS.max_steer_rad
    fast = advance(VehicleState(0.0, 0.0, 0.0, LIMITS.max_speed, 0.0), Controls(100.0, 0.0), 1.0)
    assert fast.speed == LIMITS.max_speed


@pytest.mark.parametrize("bad", [(math.nan, 0.0), (0.0, math.inf)])
def test_non_finite_controls_are_refused(bad):
    with pytest.raises(ValidationError):
        Controls(*bad)


def _straight_plan(v, lateral=0.0):  # planning frame x right, y forward
    return np.array([[lateral * k / 6, v * 0.5 * k] for k in range(1, 7)])


def test_pure_pursuit_holds_a_straight_plan_at_its_speed():
    c = pure_pursuit(VehicleState(0, 0, 0, 8.0, 0.0), plan_to_ego(_straight_plan(8.0), 0.8), 0.5, origin_ahead_m=0.8)
    assert abs(c.accel) < 1e-6 and abs(c.steer_rate) < 1e-6


def test_pure_pursuit_steers_toward_a_plan_on_the_left_and_slows_for_a_shorter_one():
    left = pure_pursuit(VehicleState(0, 0, 0, 8.0, 0.0), plan_to_ego(_straight_plan(8.0, lateral=-3.0), 0.8), 0.5,
                        origin_ahead_m=0.8)
    assert left.steer_rate > 0  # planning x is to the right: negative x is left
    slow = pure_pursuit(VehicleState(0, 0, 0, 8.0, 0.0), plan_to_ego(_straight_plan(4.0), 0.8), 0.5,
                        origin_ahead_m=0.8)
    assert slow.accel < -1.0


def test_a_stationary_plan_brakes_hard_and_keeps_the_wheel():
    c = pure_pursuit(VehicleState(0, 0, 0, 5.0, 0.1), plan_to_ego(np.zeros((6, 2)), 0.8), 0.5, origin_ahead_m=0.8)
    assert c.accel == -LIMITS.max_decel and c.steer_rate == 0.0


def test_tracking_a_curved_plan_in_closed_loop_follows_it_within_half_a_metre():
    R, v, dt = 30.0, 6.0, 0.1  # a left circle of radius 30 m, driven at 6 m/s
    circle = lambda s: np.array([R * math.sin(s / R), R * (1 - math.cos(s / R))])  # noqa: E731
    L = LIMITS.wheelbase_m
    state = VehicleState(0.0, 0.0, 0.0, v, math.atan(L / R))
    errors = []
    for k in range(60):
        s0 = v * k * dt
        pts = np.array([circle(s0 + v * 0.5 * i) for i in range(1, 7)])
        c, s_ = math.cos(state.yaw), math.sin(state.yaw)
        local = (pts - [state.x, state.y]) @ np.array([[c, -s_], [s_, c]])  # ego frame x forward, y left
        plan = np.stack([-local[:, 1], local[:, 0]], 1)  # planning frame (origin at the rear axle here)
        state = advance(state, pure_pursuit(state, plan_to_ego(plan, 0.0), 0.5, LIMITS, PurePursuitConfig()), dt)
        errors.append(abs(math.hypot(state.x, state.y - R) - R))
    assert max(errors) < 0.5


def _scenario(agent_xy_yaw, ego_speed=6.0, n=40, dt=0.1, sizes=((4.5, 1.9, 1.6),), categories=("car",)):
    t = np.arange(n) * dt
    ego = np.stack([1.3 + ego_speed * t, np.zeros(n), np.zeros(n)], 1)
    agents = np.asarray(agent_xy_yaw, np.float64).reshape(-1, n, 3)
    return ClosedLoopScenario("test/log", "test", "log", dt, (t * 1e6).astype(np.int64), np.arange(n), ego,
                              np.zeros(n), 4.6, 1.9, 1.3, np.arange(1, len(agents) + 1), tuple(categories),
                              np.asarray(sizes, np.float64).reshape(-1, 3), agents,
                              np.full(agents.shape[:2], 0.8))


def test_replayed_agents_are_where_their_trajectory_puts_them_at_each_instant():
    n = 40
    t = np.arange(n) * 0.1
    sc = _scenario(np.stack([20 + 3 * t, np.full(n, 3.5), np.zeros(n)], 1))
    traffic = Traffic(sc)
    for _ in range(7):
        traffic.step(0.1, np.array([0.0, 0.0, 0.0]), 6.0, (4.6, 1.9))
    assert traffic.poses()[0] == pytest.approx([20 + 3 * 0.7, 3.5, 0.0])
    assert traffic.velocities(0.1)[0] == pytest.approx([3.0, 0.0])


def test_a_reactive_agent_behind_the_ego_brakes_instead_of_driving_into_it():
    n = 60
    t = np.arange(n) * 0.1
    follower = np.stack([-15 + 10 * t, np.zeros(n), np.zeros(n)], 1)  # 10 m/s, behind a 3 m/s ego
    sc = _scenario(follower, ego_speed=3.0, n=n)
    for reactive, should_hit in ((False, True), (True, False)):
        traffic = Traffic(sc, reactive=reactive)
        gaps = []
        for k in range(1, n):
            ego = np.array([1.3 + 3.0 * k * 0.1, 0.0, 0.0])
            traffic.step(0.1, ego, 3.0, (4.6, 1.9))
            gaps.append(ego[0] - traffic.poses()[0, 0] - 4.55)
        assert (min(gaps) < 0) == should_hit
    assert min(gaps) > 1.0  # IDM keeps some room


def test_reactive_agents_ignore_an_ego_beside_them_and_never_outrun_their_log():
    n = 40
    t = np.arange(n) * 0.1
    sc = _scenario(np.stack([-10 + 8 * t, np.full(n, 3.5), np.zeros(n)], 1), ego_speed=2.0, n=n)
    traffic = Traffic(sc, reactive=True)
    for k in range(1, n):
        traffic.step(0.1, np.array([1.3 + 0.2 * k, 0.0, 0.0]), 2.0, (4.6, 1.9))
    assert traffic.poses()[0, 0] == pytest.approx(sc.agents[0, n - 1, 0], abs=1e-6)  # next lane: replayed as logged


def test_idm_stays_finite_at_the_extremes():
    cfg = IDMConfig()
    for speed, desired, gap, closing in ((0.0, 0.0, 0.0, 0.0), (30.0, 1e-9, 1e-9, 1e6), (1e6, 10.0, math.inf, -1e6),
                                         (5.0, 10.0, -3.0, 5.0)):
        a = idm_accel(speed, desired, gap, closing, cfg)
        assert math.isfinite(a) and -cfg.max_decel <= a <= cfg.max_accel


def test_pose_interpolation_takes_the_short_way_round_the_angle_seam_and_keeps_absence():
    poses = np.array([[0.0, 0.0, math.pi - 0.1], [1.0, 0.0, -math.pi + 0.1], [np.nan, np.nan, np.nan]])
    mid = interpolate_pose(poses, 0.5)
    assert abs(abs(mid[2]) - math.pi) < 1e-9 and mid[0] == pytest.approx(0.5)
    assert np.isnan(interpolate_pose(poses, 1.5)).all()


def test_a_reference_that_never_moves_still_has_a_route():
    sc = _scenario(np.zeros((40, 3)) + [50.0, 10.0, 0.0], ego_speed=0.0)
    route = sc.route
    assert np.linalg.norm(route[-1] - route[0]) == pytest.approx(1.0)
