"""Planning examples from scenarios (UniAD's frame, command, what the planner sees) and the embedded proxy planner:
it learns (better than driving straight on, on held-out scenarios), fine-tunes from its weights, saves and loads."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.errors import ValidationError
from omniscs.eval.planner import (CHANNELS, TrainConfig, features, load_planner, mix_repeats, mixed_examples, plan,
                                  save_planner, train_planner)
from omniscs.eval.planning import EGO_SHIFT, evaluate_planning
from omniscs.eval.scenarios import Scenario, command_of, planning_examples


def _scenario(seed: int, steps: int = 60, dt: float = 0.1, turn: float = 0.0, lead_gap: float | None = None,
              heading: float = 0.7) -> Scenario:
    """The ego driving at a random speed (turning at ``turn`` rad/s), optionally with a slower car ahead in its
    lane that makes it brake; a parked car beside the road."""
    rng = np.random.default_rng(seed)
    v0 = rng.uniform(4.0, 12.0)
    t = np.arange(steps) * dt
    speed = np.full(steps, v0)
    agents, ids, cats, sizes = [], [], [], []
    if lead_gap is not None:  # a car ahead going slower: the ego closes in, then follows at its speed
        lead_v = v0 * 0.4
        closing = np.clip(t - 1.0, 0.0, None)
        speed = np.maximum(lead_v, v0 - 3.0 * closing)
    yaw = heading + turn * t
    dist = np.concatenate([[0.0], np.cumsum(speed[:-1] * dt)])
    if abs(turn) > 1e-9:
        radius = v0 / turn
        ang = turn * dist / v0
        x = radius * np.sin(ang)
        y = radius * (1 - np.cos(ang))
    else:
        x, y = dist, np.zeros(steps)
    c, s = np.cos(heading), np.sin(heading)
    ego = np.stack([x * c - y * s + 3.0, x * s + y * c - 2.0, yaw], 1)
    if lead_gap is not None:
        lead = dist[0] + lead_gap + lead_v * t
        agents.append(np.stack([lead * c + 3.0, lead * s - 2.0, np.full(steps, heading)], 1))
        ids.append(1)
        cats.append("car")
        sizes.append([4.5, 1.9])
    parked = np.tile([15.0 * c - 4.0 * s + 3.0, 15.0 * s + 4.0 * c - 2.0, heading], (steps, 1))
    agents.append(parked)
    ids.append(2)
    cats.append("car")
    sizes.append([4.5, 1.9])
    return Scenario(f"s{seed}", dt, ego, np.array(ids), tuple(cats), np.array(sizes, float), np.stack(agents))


def test_examples_are_in_uniads_frame_with_the_command_and_what_lies_ahead():
    sc = _scenario(0)
    examples = planning_examples(sc)
    assert len(examples) == len(range(5, 60 - 30, 5))
    ex = examples[0]
    traj = ex.sample.trajectory
    speed = np.linalg.norm(sc.ego[6, :2] - sc.ego[5, :2]) / 0.1
    np.testing.assert_allclose(traj[:, 0], 0.0, atol=1e-9)  # straight ahead: along +y
    np.testing.assert_allclose(traj[:, 1], speed * 0.5 * np.arange(1, 7), rtol=1e-9)
    assert ex.inputs.command == "forward" and ex.inputs.speed == pytest.approx(speed)
    parked = ex.inputs.boxes_now[0]  # 4 m to the ego's left, ahead, aligned with it
    assert parked[0] == pytest.approx(-4.0, abs=1e-6) and parked[4] == pytest.approx(np.pi / 2)
    assert parked[1] == pytest.approx(15.0 - np.linalg.norm(sc.ego[5, :2] - sc.ego[0, :2]) + EGO_SHIFT, abs=1e-6)
    left = planning_examples(_scenario(1, turn=0.35))[0]
    right = planning_examples(_scenario(1, turn=-0.35))[0]
    assert (left.inputs.command, right.inputs.command) == ("left", "right")
    assert left.sample.trajectory[-1, 0] < -2.0 < 2.0 < right.sample.trajectory[-1, 0]
    assert command_of(np.array([[0.0, 1.0], [1.9, 9.0]])) == "forward"
    with pytest.raises(ValidationError, match="does not divide"):
        planning_examples(_scenario(2, dt=0.3))


def test_features_draw_vehicles_now_and_before_and_no_map_channel_without_a_map():
    ex = planning_examples(_scenario(3, lead_gap=12.0))[0]
    raster, state, base = features(ex)
    assert raster.shape[0] == len(CHANNELS) and raster[0].sum() > 0 and raster[1].sum() > 0
    assert not np.array_equal(raster[0], raster[1])  # the lead car moved in half a second
    assert raster[2].sum() == 0 and raster[3].sum() == 0 and state[-1] == 0.0
    assert base[-1, 1] == pytest.approx(ex.inputs.speed * 3.0) and np.all(base[:, 0] == 0)


def _examples(seeds, **kw):
    return [e for s in seeds for e in planning_examples(_scenario(s, turn=[0.0, 0.2, -0.2][s % 3],
                                                                  lead_gap=12.0 if s % 2 else None, **kw))]


def test_the_planner_learns_braking_and_turning_better_than_driving_straight_on(tmp_path):
    train, held = _examples(range(0, 24)), _examples(range(100, 112))
    model, record = train_planner(train, TrainConfig(epochs=25, batch_size=32, lr=3e-3, seed=0))
    assert record["epoch_loss_m"][-1] < 0.5 * record["epoch_loss_m"][0]
    samples = [e.sample for e in held]
    straight = evaluate_planning(samples, {e.sample.token: features(e)[2] for e in held})
    learned = evaluate_planning(samples, plan(model, held))
    assert learned["uniad"]["L2"]["3s"] < 0.6 * straight["uniad"]["L2"]["3s"]
    path = save_planner(model, tmp_path / "planner", record)
    again = load_planner(path)
    a, b = plan(model, held[:3]), plan(again, held[:3])
    assert all(np.array_equal(a[k], b[k]) for k in a)
    tuned, rec = train_planner(train[:10], TrainConfig(epochs=2, seed=1), init=model)
    assert rec["fine_tuned"] and not np.array_equal(plan(tuned, held[:1])[held[0].sample.token],
                                                    a[held[0].sample.token])
    with pytest.raises(ValidationError, match="not a proxy planner"):
        load_planner(tmp_path / "nowhere")
    with pytest.raises(ValidationError, match="no planning examples"):
        train_planner([])


def test_a_variant_with_absent_steps_reads_them_as_nan():
    from omniscs.eval.scenarios import scenario_from_variant

    ego = [[float(i), 0.0, 0.0] for i in range(40)]
    variant = {"variant_id": "v0", "scene_id": "s", "dt": 0.1, "now_step": 9, "ego": ego,
               "agents": {"3": [None] * 5 + [[float(i), 3.5, 0.0] for i in range(5, 40)]},
               "sizes": {"3": [4.5, 1.9, 1.6], "ego": [4.6, 1.9, 1.6]}}
    sc = scenario_from_variant(variant, {3: "car"})
    assert np.isnan(sc.agents[0, :5]).all() and np.isfinite(sc.agents[0, 5:]).all()
    with pytest.raises(ValidationError, match="no category"):
        scenario_from_variant(variant, {})


def test_the_shipped_planner_loads_and_says_how_it_was_made():
    import json

    from omniscs.eval.planner import DEFAULT_PLANNER

    model = load_planner()
    record = json.loads((DEFAULT_PLANNER / "training.json").read_text())
    assert record["command"] == "omniscs bench downstream --train-base" and not record["fine_tuned"]
    assert record["data"]["train_seeds"][0] == 300_000 and record["n_examples"] > 100
    assert record["epoch_loss_m"][-1] < record["epoch_loss_m"][0]
    held = planning_examples(_scenario(7, lead_gap=12.0))
    assert all(np.isfinite(p).all() for p in plan(model, held).values())


def test_variant_keyframes_run_past_the_now_step_with_the_unknown_future_masked():
    from omniscs.eval.scenarios import SCS_MIN_KNOWN, variant_keyframes

    sc = _scenario(4, steps=40, lead_gap=12.0)  # a variant's span: 1 s history and 3 s future at 0.1 s
    full = planning_examples(sc, start=9)
    assert [e.step for e in full] == [9]  # only the now step has all six waypoints
    keys = variant_keyframes(sc, 9)
    assert [e.step for e in keys] == [9, 14, 19, 24, 29]
    assert [int(e.sample.mask.sum()) for e in keys] == [6, 5, 4, 3, 2]
    assert SCS_MIN_KNOWN == 2
    last = keys[-1].sample
    assert np.all(last.trajectory[2:] == 0) and all(len(v) == 0 for v in last.vehicles[2:])
    assert len(last.vehicles[0]) == 2  # the lead car and the parked car, where the truth is known
    np.testing.assert_allclose(keys[0].sample.trajectory, full[0].sample.trajectory)
    with pytest.raises(ValidationError, match="min_known"):
        planning_examples(sc, min_known=0)


def test_masked_steps_add_nothing_and_collisions_are_also_read_per_known_step():
    sc = _scenario(5, steps=40, lead_gap=6.0)
    from omniscs.eval.scenarios import variant_keyframes

    keys = variant_keyframes(sc, 9)
    samples = [e.sample for e in keys]
    truth = {s.token: s.trajectory for s in samples}
    out = evaluate_planning(samples, truth)
    assert out["known_per_step"] == [5, 5, 4, 3, 2, 1]
    assert out["per_step"]["L2"] == pytest.approx([0.0] * 6)
    def onto_the_lead(s):  # each known waypoint on the lead car (the box nearest ahead)
        out = s.trajectory.copy()
        for i, boxes in enumerate(s.vehicles):
            if len(boxes):
                lead = boxes[np.argmin(np.abs(boxes[:, 0]))]
                out[i] = lead[:2] - np.array([0.0, EGO_SHIFT])
        return out

    got = evaluate_planning(samples, {s.token: onto_the_lead(s) for s in samples})
    col, known = np.array(got["per_step"]["obj_box_col"]), np.array(got["known_per_step"])
    np.testing.assert_allclose(got["per_step"]["obj_box_col_known"], col * len(samples) / known)
    assert col.max() > 0


def test_collision_loss_is_zero_when_clear_and_pushes_the_plan_out_of_a_box():
    import torch

    from omniscs.eval.planner import collision_loss, collision_penetration, future_boxes

    box = torch.zeros(1, 6, 1, 6)
    box[0, :, 0] = torch.tensor([0.0, 8.0, 4.0, 2.0, np.pi / 2, 1.0])  # a car ahead, along +y
    clear = torch.zeros(1, 6, 2)
    clear[0, :, 1] = -5.0
    assert collision_penetration(clear, box, 0.0).abs().max() == 0
    into = clear.clone()
    into[0, :, 1] = 6.0  # the ego box's front reaches into the car
    reach = collision_penetration(into, box, 0.0)
    assert (reach > 0).all() and (collision_penetration(into, box, 1.0) > reach).all()
    plan_ = into.clone().requires_grad_(True)
    mask = torch.ones(1, 6)
    loss = collision_loss(plan_, clear, mask, box)
    loss.backward()
    assert loss.item() > 0 and (plan_.grad[0, :, 1] > 0).all()  # moving back (-y) lowers it
    assert collision_loss(into, into, mask, box).item() == 0  # where the truth itself collides: left out
    ex = planning_examples(_scenario(6, lead_gap=12.0))[0]
    boxes = future_boxes(ex)
    assert boxes.shape[0] == 6 and boxes[..., 5].sum() > 0 and np.isfinite(boxes).all()


def test_training_with_the_collision_loss_learns_and_mirrors_its_boxes():
    import torch

    from omniscs.eval.planner import _mirror, _tensors

    train = _examples(range(0, 6))
    data = _tensors(train[:4], with_boxes=True)
    m = _mirror(*data)
    assert torch.equal(m[5][..., 0], -data[5][..., 0]) and torch.allclose(m[5][..., 4], np.pi - data[5][..., 4])
    model, record = train_planner(train, TrainConfig(epochs=6, batch_size=16, lr=3e-3, collision_weight=1.0))
    assert np.isfinite(record["epoch_loss_m"]).all() and record["epoch_loss_m"][-1] < record["epoch_loss_m"][0]
    with pytest.raises(ValidationError, match="collision_weight"):
        TrainConfig(collision_weight=-1.0)


@pytest.mark.parametrize("n_scs, n_logs, share, repeats, reached", [
    (100, 520, 0.5, (5, 1), 500 / 1020),   # few SCS examples: they are repeated
    (855, 520, 0.5, (1, 2), 855 / 1895),   # more SCS examples than logs: the logs are repeated, not the SCS ones
    (855, 520, 0.3, (1, 4), 855 / 2935),   # a lower share repeats the logs more
    (300, 100, 0.75, (1, 1), 0.75),        # already at the share
    (0, 50, 0.5, (1, 1), 0.0),             # one kind missing: nothing to mix
    (50, 0, 0.5, (1, 1), 1.0),
])
def test_the_fine_tuning_mix_repeats_the_short_kind_to_come_near_the_share(n_scs, n_logs, share, repeats, reached):
    assert mix_repeats(n_scs, n_logs, share) == repeats
    examples, mix = mixed_examples(["s"] * n_scs, ["l"] * n_logs, share)
    assert (mix["scs_repeat"], mix["log_repeat"]) == repeats
    assert examples.count("s") == repeats[0] * n_scs and examples.count("l") == repeats[1] * n_logs
    assert mix["scs_share"] == pytest.approx(reached)
    if n_scs and n_logs:  # one more or one fewer repeat of the repeated kind comes no nearer the share
        step = (1, 0) if repeats[1] == 1 else (0, 1)
        for sign in (1, -1):
            rs, rl = repeats[0] + sign * step[0], repeats[1] + sign * step[1]
            if rs >= 1 and rl >= 1:
                assert abs(rs * n_scs / (rs * n_scs + rl * n_logs) - share) >= abs(reached - share) - 1e-12


@pytest.mark.parametrize("share", [-0.1, 1.5, float("nan")])
def test_a_share_outside_zero_to_one_is_refused(share):
    with pytest.raises(ValidationError, match="share"):
        mix_repeats(10, 10, share)
