"""Adversarial latent optimisation: collisions are found plausibly, numerical extremes stay finite, plausibility
checks catch what they must, and L_app joins the loss only when a renderer exists."""
import json

import numpy as np
import pytest

from omniscs.scs.behavior.adversarial import (BehaviorProblem, adversarial_preset, generate_variants,
                                              variant_schedule)
from omniscs.scs.behavior.appearance import AppearanceTerm
from omniscs.scs.behavior.checkpoint import load_checkpoint
from omniscs.scs.behavior.planner import PlannerConfig, rule_based_plan
from omniscs.scs.behavior.tracks import traffic_from_world
from omniscs.scs.behavior.variants import variant_spec
from tests.behavior_fixtures import straight_world
from tests.test_behavior_appearance import blob_renderer

FAST = adversarial_preset("fast")


@pytest.fixture(scope="module")
def model():
    return load_checkpoint()


def test_a_car_in_the_next_lane_is_steered_into_the_ego_plausibly(model):
    traffic = traffic_from_world(straight_world([{"x": 8.0, "y": 3.3, "speed": 8.0}]))
    (v,) = generate_variants(traffic, model, 1, FAST)
    assert v.success and v.plausible, v.evaluation.violations
    assert v.kind in ("cut_in", "rear_end") and v.adversary == 1
    assert v.losses["L_app"] is None and v.losses["L_beh"] < 10.0


def test_numerical_extremes_far_standing_single_and_late_agents_and_a_standing_ego(model):
    world = straight_world([
        {"x": 500.0, "y": 3.3, "speed": 9.0},        # far
        {"x": 10_000.0, "y": 6.6, "speed": 9.0},     # very far
        {"x": 25.0, "y": 12.5, "speed": 0.0},        # standing (parked)
        {"x": -20.0, "y": 3.3, "speed": 9.0},        # passes the standing ego
        {"x": 30.0, "y": 3.3, "speed": 3.0, "first": 20},  # appears late
    ], ego_speed=0.0)
    traffic = traffic_from_world(world)
    results = generate_variants(traffic, model, 3, FAST)
    assert len(results) == 3
    for v in results:
        assert all(x is None or np.isfinite(x) for x in v.losses.values())
        spec = json.loads(json.dumps(variant_spec(v)))  # strict JSON: no NaN
        assert np.allclose([p[:2] for p in spec["ego"][10:]], [traffic.ego_xy[10]], atol=1e-6)  # ego stays put
        late = spec["agents"]["5"]
        assert all(p is None for p in late[:20]) and all(p is not None for p in late[20:])
        assert spec["agents"]["5"][25] == pytest.approx([30.0 + 3.0 * 2.5, 3.3, 0.0], abs=1e-3)  # replayed
    assert {v.adversary for v in results} <= {3, 4}  # the far agents cannot reach the ego: never chosen


def test_a_single_agent_scene_gives_one_adversary(model):
    traffic = traffic_from_world(straight_world([{"x": 30.0, "y": 6.6, "yaw": np.pi, "speed": 8.0}]))
    results = generate_variants(traffic, model, 2, FAST)
    assert [v.adversary for v in results] == [1, 1]
    assert results[0].window != results[1].window  # the second variant looks at another time window


def test_a_scene_with_no_other_vehicle_gives_no_variant(model):
    assert generate_variants(traffic_from_world(straight_world([])), model, 2, FAST) == []


def test_plausibility_catches_harsh_braking_collisions_between_agents_and_leaving_the_road(model):
    traffic = traffic_from_world(straight_world([{"x": 20.0, "y": 3.3, "speed": 8.0},
                                                 {"x": 40.0, "y": 3.3, "speed": 8.0}]))
    problem = BehaviorProblem(traffic, model, FAST)
    states = problem.fitted.states.numpy().astype(np.float64)
    lon = problem.fitted.longitudinal_accel.numpy().astype(np.float64)
    lat = problem.fitted.lateral_accel.numpy().astype(np.float64)
    plan = problem.plan(states)
    assert problem.evaluate(states, lon, lat, plan, 1).plausible
    harsh = lon.copy()
    harsh[1, 5] = -6.0
    assert any("braking 6.00 > 4.05" in v for v in problem.evaluate(states, harsh, lat, plan, 1).violations)
    crash = states.copy()
    crash[2, 15:, :3] = crash[1, 15:, :3]
    assert any(v.startswith("collision of track 1 and track 2") for v in
               problem.evaluate(crash, lon, lat, plan, 1).violations)
    off = states.copy()
    off[1, 20:, 1] += 14.0  # scene frame y: onto the sidewalk
    assert any("leaves the drivable area" in v for v in problem.evaluate(off, lon, lat, plan, 1).violations)


def test_rule_planner_keeps_speed_on_a_clear_road_and_stops_behind_a_standing_car():
    path = np.stack([np.linspace(0, 100, 50), np.zeros(50)], -1)
    clear = rule_based_plan(path, 8.0, np.zeros((0, 30, 3)), np.zeros((0, 30), bool), np.zeros((0, 2)),
                            (4.6, 1.9), 30, 0.1, PlannerConfig(kind="rule"), desired_speed=8.0)
    assert clear[-1, 0] == pytest.approx(24.0, abs=0.2)
    stopped = np.zeros((1, 30, 3))
    stopped[0, :, 0] = 15.0
    plan = rule_based_plan(path, 8.0, stopped, np.ones((1, 30), bool), np.array([[4.5, 1.9]]), (4.6, 1.9), 30,
                           0.1, PlannerConfig(kind="rule"), desired_speed=8.0)
    assert plan[-1, 0] < 15.0 - 4.55 and np.all(np.diff(plan[:, 0]) >= -1e-9)


def test_variants_take_adversaries_in_turn_then_other_time_windows():
    candidates = [(3, True, 2.0), (5, True, 4.0), (7, False, 1.0)]
    schedule = variant_schedule(candidates, 5, 30, ((0.0, 1.0), (0.0, 0.5), (0.5, 1.0)))
    assert [s[0] for s in schedule] == [3, 5, 3, 5, 3]
    assert [s[1] for s in schedule] == [(0, 30), (0, 30), (0, 15), (0, 15), (15, 30)]
    assert [s[0] for s in variant_schedule([(7, False, 1.0)], 2, 30, ((0.0, 1.0),))] == [7, 7]


def test_l_app_enters_the_loss_only_when_a_renderer_is_supplied(model):
    traffic = traffic_from_world(straight_world([{"x": 14.0, "y": 3.3, "speed": 8.0}]))
    plain = BehaviorProblem(traffic, model, FAST)
    assert plain.optimise(1, (0, plain.horizon), "v", True).losses["L_app"] is None

    render = blob_renderer(size=24, extent_m=60.0)
    original = render(plain.world_trajectories(plain.fitted.states)).detach()
    appearance = AppearanceTerm(render, original)
    seen = []
    wrapped = AppearanceTerm(lambda traj: seen.append(traj.poses.requires_grad) or render(traj), original)
    with_app = BehaviorProblem(traffic, model, FAST, appearance=wrapped)
    result = with_app.optimise(1, (0, with_app.horizon), "v", True)
    assert result.losses["L_app"] is not None and np.isfinite(result.losses["L_app"])
    assert seen and all(seen)  # the renderer received differentiable trajectories every step
    assert appearance(plain.world_trajectories(plain.fitted.states)).item() == pytest.approx(0.0, abs=1e-8)
