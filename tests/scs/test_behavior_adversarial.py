"""Adversarial latent optimisation: collisions are found plausibly, numerical extremes stay finite, plausibility
checks catch what they must, and L_app joins the loss only when a renderer exists."""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.pipeline.procedural import traffic_from_world
from omniscs.scs.behavior.adversarial_config import adversarial_preset
from omniscs.scs.behavior.render_consistency import RenderConsistencyTerm
from omniscs.scs.behavior.checkpoint import load_traffic_model
from omniscs.scs.behavior.collision import footprints, overlapping
from omniscs.scs.behavior.evaluation import evaluate
from omniscs.scs.behavior.generation import distinct_variants, generate_variants, variant_schedule
from omniscs.scs.behavior.losses import box_gap
from omniscs.scs.behavior.optimisation import intercept, optimise, warm_start
from omniscs.scs.behavior.planner import PlannerConfig, rule_based_plan
from omniscs.scs.behavior.problem import BehaviorProblem
from omniscs.scs.behavior.variants import variant_spec
from tests.behavior_fixtures import straight_world
from tests.scs.test_behavior_render_consistency import blob_renderer

FAST = adversarial_preset("fast")


@pytest.fixture(scope="module")
def model():
    return load_traffic_model()


def test_a_car_in_the_next_lane_is_steered_into_the_ego_plausibly(model):
    traffic = traffic_from_world(straight_world([{"x": 8.0, "y": 3.3, "speed": 8.0}]))
    (v,) = generate_variants(traffic, model, 1, FAST)
    assert v.success and v.plausible, v.evaluation.violations
    assert v.kind in ("cut_in", "rear_end") and v.adversary == 1
    assert v.losses["L_app"] is None and v.losses["L_beh"] < 10.0


def test_progress_moves_with_the_optimiser_steps_and_never_goes_back(model):
    traffic = traffic_from_world(straight_world([{"x": 8.0, "y": 3.3, "speed": 8.0},
                                                 {"x": -12.0, "y": 3.3, "speed": 9.0}]))
    seen: list[tuple[int, int]] = []
    variants = generate_variants(traffic, model, 2, FAST, progress=lambda k, n: seen.append((k, n)))
    assert len(variants) == 2
    total = 2 * (FAST.iterations + 1)
    assert {n for _, n in seen} == {total} and seen[-1][0] == total
    done = [k for k, _ in seen]
    assert done == sorted(done) and len(set(done)) == len(done)
    assert len(done) > 4  # within each variant, not once per variant


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
    assert evaluate(problem, states, lon, lat, plan, 1).plausible
    harsh = lon.copy()
    harsh[1, 5] = -6.0
    assert any("braking 6.00 > 4.05" in v for v in evaluate(problem, states, harsh, lat, plan, 1).violations)
    crash = states.copy()
    crash[2, 15:, :3] = crash[1, 15:, :3]
    assert any(v.startswith("collision of track 1 and track 2") for v in
               evaluate(problem, crash, lon, lat, plan, 1).violations)
    off = states.copy()
    off[1, 20:, 1] += 14.0  # scene frame y: onto the sidewalk
    assert any("leaves the drivable area" in v for v in evaluate(problem, off, lon, lat, plan, 1).violations)


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
    assert optimise(plain, 1, (0, plain.horizon), "v", True).losses["L_app"] is None

    render = blob_renderer(size=24, extent_m=60.0)
    original = render(plain.world_trajectories(plain.fitted.states)).detach()
    appearance = RenderConsistencyTerm(render, original)
    seen = []
    wrapped = RenderConsistencyTerm(lambda traj: seen.append(traj.poses.requires_grad) or render(traj), original)
    with_app = BehaviorProblem(traffic, model, FAST, render_consistency=wrapped)
    result = optimise(with_app, 1, (0, with_app.horizon), "v", True)
    assert result.losses["L_app"] is not None and np.isfinite(result.losses["L_app"])
    assert seen and all(seen)  # the renderer received differentiable trajectories every step
    assert appearance(plain.world_trajectories(plain.fitted.states)).item() == pytest.approx(0.0, abs=1e-8)


def test_a_parked_car_pulls_out_into_the_ego_only_with_the_warm_start(model):
    traffic = traffic_from_world(straight_world([{"x": 18.0, "y": 3.3, "speed": 0.0}]))
    (stays,) = generate_variants(traffic, model, 1, replace(FAST, restarts=0))
    assert not stays.success  # from the log its braking controls saturate: L_beh cannot make it move
    (v,) = generate_variants(traffic, model, 1, FAST)
    assert v.success and v.plausible, v.evaluation.violations
    assert v.kind == "cut_in" and v.adversary == 1


def test_warm_starts_are_deterministic_for_a_fixed_seed_and_differ_between_restarts(model):
    traffic = traffic_from_world(straight_world([{"x": 18.0, "y": 3.3, "speed": 0.0},
                                                 {"x": 30.0, "y": 6.6, "yaw": np.pi, "speed": 8.0}]))
    problem = BehaviorProblem(traffic, model, FAST)
    window = (0, problem.horizon)
    first = warm_start(problem, 1, window, restart=0)
    assert torch.equal(first, warm_start(problem, 1, window, restart=0))
    assert not torch.equal(first, warm_start(problem, 1, window, restart=1))
    assert torch.equal(first[2:], problem.z_fit[2:]) and torch.equal(first[0], problem.z_fit[0])  # only node 1 moves
    problem.config = replace(FAST, seed=1)
    assert not torch.equal(first, warm_start(problem, 1, window, restart=0))
    problem.config = FAST
    a, b = (optimise(problem, 1, window, "v", True, z_start=first) for _ in range(2))
    assert np.array_equal(a.agents[1], b.agents[1], equal_nan=True) and a.iterations == b.iterations


def test_the_interception_search_finds_a_comfortable_path_of_a_parked_car_into_the_ego(model):
    traffic = traffic_from_world(straight_world([{"x": 18.0, "y": 3.3, "speed": 0.0}]))
    problem = BehaviorProblem(traffic, model, FAST)
    states, gap = intercept(problem, 1, (0, problem.horizon), problem.logged_plan, torch.Generator().manual_seed(0))
    assert gap < 0.0 and states[-1, 3] > 1.0  # it pulls out and its box overlaps the ego's
    lon, lat = np.diff(np.r_[0.0, states[:, 3].numpy()]) / traffic.dt, (states[:, 3] * states[:, 4]).numpy()
    cb = FAST.comfort
    assert lon.max() <= cb.max_lon_accel and lon.min() >= cb.min_lon_accel and np.abs(lat).max() <= cb.max_abs_lat_accel


def test_box_gap_is_negative_exactly_when_the_boxes_overlap_and_finite_far_away():
    rng = np.random.default_rng(0)
    n = 400
    plan = np.stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(-np.pi, np.pi, n)], -1)
    agent = np.stack([rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), rng.uniform(-np.pi, np.pi, n)], -1)
    gap = box_gap(torch.from_numpy(agent)[None], (4.5, 1.9), torch.from_numpy(plan), (4.8, 2.0))[0].numpy()
    overlap = overlapping(footprints(agent[:, :2], agent[:, 2], 4.5, 1.9),
                          footprints(plan[:, :2], plan[:, 2], 4.8, 2.0))
    margin = np.abs(gap) > 1e-6  # exactly touching counts either way
    assert overlap.any() and (~overlap).any()
    assert np.array_equal((gap < 0)[margin], overlap[margin])
    agent_10km = torch.tensor([[[1e4, 0.0, np.pi / 2]]], dtype=torch.float32, requires_grad=True)
    far = box_gap(agent_10km, (4.5, 1.9), torch.zeros(1, 3), (4.8, 2.0))
    far.sum().backward()
    assert far.item() == pytest.approx(1e4 - 2.4 - 0.95, rel=1e-5) and torch.isfinite(agent_10km.grad).all()


def test_agents_whose_reconstruction_collides_replay_their_log_and_are_never_adversaries(model):
    # In this procedural intersection two cars turn past each other 3.7 m apart, tighter than the comfort yaw rate
    # (1 rad/s): comfort decoding runs both wide and their reconstructions overlap, which the log never does.
    from omniscs.world import generate_world

    traffic = traffic_from_world(generate_world("intersection", 2100, n_frames=40, n_cameras=1, width=64, height=36))
    base = adversarial_preset("balanced")
    unpinned = BehaviorProblem(traffic, model, replace(base, pin_colliding_reconstructions=False))
    fit = unpinned.fitted
    ev = evaluate(unpinned, fit.states.numpy(), fit.longitudinal_accel.numpy(), fit.lateral_accel.numpy(),
                  unpinned.logged_plan, 1)
    assert any(v.startswith("collision of track 10 and track 11") for v in ev.violations)

    p = BehaviorProblem(traffic, model, base)
    pinned = [int(traffic.track_ids[p.node_tracks[k]]) for k in np.flatnonzero(p.pinned)]
    assert pinned == [10, 11]
    fit = p.fitted
    ev = evaluate(p, fit.states.numpy(), fit.longitudinal_accel.numpy(), fit.lateral_accel.numpy(), p.logged_plan, 1)
    assert not any(v.startswith("collision") for v in ev.violations), ev.violations
    mask = p.batch.future_mask[0].numpy()
    for k in np.flatnonzero(p.pinned):  # exactly the log, whatever the latents
        assert np.allclose(fit.states[k, mask[k], :3].numpy(), p.batch.future[0, k, mask[k]].numpy(), atol=1e-5)
        moved = p.decode(p.z_fit + 1.0).states
        assert torch.equal(moved[k], fit.states[k])
    assert not set(np.flatnonzero(p.pinned)) & {c[0] for c in p.candidates()}
    assert torch.isfinite(fit.states).all()


@pytest.mark.slow
def test_the_knot_fallback_keeps_a_plausible_interception_the_latent_cannot_express(model):
    # A left turn across this procedural intersection into the ego: the interception search over the decoder's
    # control knots finds it, comfortably and on the road; the latent refitted to it and optimised does not.
    from omniscs.world import generate_world

    traffic = traffic_from_world(generate_world("intersection", 2200, n_frames=40, n_cameras=1, width=64, height=36))
    base = adversarial_preset("balanced")
    p = BehaviorProblem(traffic, model, replace(base, knot_fallback=False))
    (latent,) = distinct_variants(p, p.candidates(), 1)
    assert latent.source == "latent" and not latent.success
    p.config = base
    (v,) = distinct_variants(p, p.candidates(), 1)
    assert v.source == "knots" and v.success and v.plausible and v.adversary == latent.adversary
    spec = json.loads(json.dumps(variant_spec(v)))
    assert spec["source"] == "knots" and spec["losses"]["L_restore"] == 0.0
    cb = base.comfort
    assert cb.min_lon_accel <= spec["adversary_accel_mps2"][0] and spec["adversary_accel_mps2"][1] <= cb.max_lon_accel
    assert spec["adversary_max_lateral_accel_mps2"] <= cb.max_abs_lat_accel
    assert all(np.isfinite(x) for x in v.losses.values() if x is not None)


@pytest.mark.skipif(torch.cuda.is_available(), reason="tests the message shown where CUDA is missing")
def test_asking_for_cuda_without_it_is_a_clear_error_before_any_work(model):
    from omniscs.scs.behavior.train import TrainConfig, train_model

    traffic = traffic_from_world(straight_world([{"x": 8.0, "y": 3.3, "speed": 8.0}]))
    with pytest.raises(OmniscsError, match="no CUDA device"):
        generate_variants(traffic, model, 1, replace(FAST, device="cuda"))
    never = lambda *args: pytest.fail("no procedural log may be made before the device is checked")  # noqa: E731
    with pytest.raises(OmniscsError, match="no CUDA device"):
        train_model(TrainConfig(device="cuda"), never)
    with pytest.raises(OmniscsError, match="unknown device"):
        generate_variants(traffic, model, 1, replace(FAST, device="gpu0"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_variant_made_on_cuda_steers_the_car_into_the_ego_as_on_the_cpu(model):
    traffic = traffic_from_world(straight_world([{"x": 8.0, "y": 3.3, "speed": 8.0}]))
    (v,) = generate_variants(traffic, model, 1, replace(FAST, device="cuda"))
    (cpu,) = generate_variants(traffic, model, 1, FAST)
    assert v.success and v.plausible, v.evaluation.violations
    assert v.adversary == cpu.adversary and v.kind == cpu.kind
    assert all(np.isfinite(x) for x in v.losses.values() if x is not None)
    assert next(model.parameters()).device.type == "cpu"  # the caller's model stays where it was


def test_with_gates_further_candidates_are_tried_until_enough_pass_or_the_budget_is_spent(monkeypatch):
    # The schedule and its bookkeeping, with the optimisation replaced by outcomes given in order.
    from types import SimpleNamespace

    from omniscs.scs.behavior import generation

    def run(outcomes, n, accept, budget):
        it = iter(outcomes)

        def fake(problem, candidates, node, window, reachable, index, used, on_step=None):
            used.add((node, tuple(window)))
            return SimpleNamespace(success=next(it), node=node, window=window)
        monkeypatch.setattr(generation, "optimise_with_fallback", fake)
        problem = SimpleNamespace(config=SimpleNamespace(time_windows=((0.0, 0.5), (0.5, 1.0)), iterations=60),
                                  horizon=20,
                                  traffic=SimpleNamespace(scene_id="s"))
        candidates = [(1, True, 3.0), (2, True, 5.0), (3, False, 9.0)]
        return generation.distinct_variants(problem, candidates, n, accept=accept, budget=budget)

    def passes(v):
        return v.success

    tried = run([False, False, True, True], 2, passes, 6)
    assert [v.success for v in tried] == [False, False, True, True]
    assert [(v.node, v.window) for v in tried] == [(1, (0, 10)), (2, (0, 10)), (1, (10, 20)), (2, (10, 20))]
    assert len(run([False] * 9, 2, passes, 3)) == 3  # the budget ends it
    assert len(run([False] * 9, 1, passes, 9)) == 4  # so do the distinct (adversary, window) pairs: 2 x 2
    assert len(run([False] * 9, 2, None, 6)) == 2  # without gates: n variants, as before

    def unreachable(outcomes, n, budget):
        it = iter(outcomes)
        monkeypatch.setattr(generation, "optimise_with_fallback", lambda *a, **k: SimpleNamespace(success=next(it)))
        problem = SimpleNamespace(config=SimpleNamespace(time_windows=((0.0, 1.0),), iterations=60), horizon=20,
                                  traffic=SimpleNamespace(scene_id="s"))
        return generation.distinct_variants(problem, [(1, False, 40.0), (2, False, 50.0)], n, accept=passes,
                                            budget=budget)
    assert len(unreachable([False] * 9, 1, 6)) == 1  # no vehicle can reach the ego: the budget is not spent
