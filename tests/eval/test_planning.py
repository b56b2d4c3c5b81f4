"""UniAD's planning metrics on hand-made cases with known answers, and on an exported dataroot (its frame: x right,
y forward; keyframes at 2 Hz), with clear errors for bad results."""
from __future__ import annotations

import json

import numpy as np
import pytest

from omniscs.errors import ValidationError
from omniscs.eval.planning import (GRID, PlanningSample, box_collisions, ego_cells, evaluate_planning, horizons,
                                   occupancy)


def test_the_ego_box_is_uniads_32_cells_half_a_metre_ahead_of_the_waypoint():
    cells = ego_cells()
    assert len(cells) == 32
    assert (cells[:, 0].min(), cells[:, 0].max()) == (97, 104)  # along y: -1.542 .. 2.542 m
    assert (cells[:, 1].min(), cells[:, 1].max()) == (98, 101)  # along x: -0.925 .. 0.925 m


def test_occupancy_fills_the_cells_whose_centres_lie_in_the_footprint():
    along_y = occupancy(np.array([[0.0, 10.0, 4.0, 2.0, np.pi / 2]]))
    rows, cols = np.nonzero(along_y)
    assert along_y.sum() == 8 * 4 and set(cols) == {98, 99, 100, 101} and (rows.min(), rows.max()) == (116, 123)
    turned = occupancy(np.array([[0.0, 10.0, 4.0, 2.0, 0.0]]))
    assert turned.sum() == 4 * 8 and np.nonzero(turned)[1].min() == 96
    assert not occupancy(np.array([[80.0, 0.0, 4.0, 2.0, 0.0]])).any() and occupancy(np.zeros((0, 5))).shape == (GRID, GRID)


def _straight(n: int = 6, speed: float = 4.0) -> np.ndarray:
    return np.stack([np.zeros(n), speed * 0.5 * np.arange(1, n + 1)], 1)


def test_collision_only_where_the_ego_box_meets_a_vehicle():
    traj = _straight()  # y = 2, 4, ..., 12
    occupied = np.zeros((6, GRID, GRID), bool)
    occupied[2] = occupancy(np.array([[0.0, 8.0, 4.0, 2.0, np.pi / 2]]))  # 6..10 m ahead at step 2 (ego at 6 m)
    occupied[4] = occupancy(np.array([[4.0, 10.0, 4.0, 2.0, np.pi / 2]]))  # beside the path
    assert box_collisions(traj, occupied).tolist() == [False, False, True, False, False, False]


def test_l2_and_collision_rates_with_masks_and_true_collisions_left_out():
    gt = _straight()
    cars = [np.zeros((0, 5))] * 6
    a_cars = list(cars)
    a_cars[2] = np.array([[3.0, 10.0, 4.0, 2.0, np.pi / 2]])  # where the plan goes (3, 10), not the truth (0, 6)
    b_cars = list(cars)
    b_cars[4] = np.array([[0.0, 10.0, 4.0, 2.0, np.pi / 2]])  # the truth itself hits it: left out
    mask_b = np.array([1, 1, 1, 1, 1, 0], bool)
    samples = [PlanningSample("a", gt, np.ones(6, bool), tuple(a_cars)), PlanningSample("b", gt, mask_b, tuple(b_cars))]
    plan = gt + np.array([3.0, 4.0])  # 5 m off at every step
    out = evaluate_planning(samples, {"a": plan, "b": plan})
    assert out["per_step"]["L2"] == pytest.approx([5, 5, 5, 5, 5, 2.5])
    assert out["per_step"]["obj_box_col"] == pytest.approx([0, 0, 0.5, 0, 0, 0])
    assert out["gt_collision_steps"] == [0, 0, 0, 0, 1, 0]
    assert out["uniad"]["L2"] == pytest.approx({"1s": 5.0, "2s": 5.0, "3s": 2.5})
    assert out["stp3"]["L2"] == pytest.approx({"1s": 5.0, "2s": 5.0, "3s": 27.5 / 6})
    assert out["stp3"]["obj_box_col"] == pytest.approx({"1s": 0.0, "2s": 0.125, "3s": 0.5 / 6})


def test_horizons_under_both_conventions():
    v = np.arange(6.0)
    assert horizons(v, "uniad") == {"1s": 1.0, "2s": 3.0, "3s": 5.0}
    assert horizons(v, "stp3") == {"1s": 0.5, "2s": 1.5, "3s": 2.5}
    with pytest.raises(ValidationError, match="convention"):
        horizons(v, "vad")


@pytest.mark.parametrize("plan, message", [(None, "no planned trajectory"), (np.zeros((5, 2)), "6 finite"),
                                           (np.full((6, 2), np.nan), "6 finite")])
def test_bad_plans_are_clear_errors(plan, message):
    sample = PlanningSample("a", _straight(), np.ones(6, bool), tuple([np.zeros((0, 5))] * 6))
    with pytest.raises(ValidationError, match=message):
        evaluate_planning([sample], {} if plan is None else {"a": plan})


# ----------------------------------------------------------------------------- on an exported dataroot
@pytest.fixture(scope="module")
def dataroot(tmp_path_factory):
    from omniscs.export import export_scenes
    from omniscs.scene import SyntheticSource, write_synthetic_scene

    root = tmp_path_factory.mktemp("planroot")
    store = write_synthetic_scene(SyntheticSource(template="straight", seed=4, n_frames=45, n_cameras=1, width=64,
                                                  height=36), root / "store")
    return export_scenes([store], "nuscenes", root / "nuscenes", version="v1.0-mini")


def test_true_futures_point_forward_and_the_truth_as_plan_scores_zero(dataroot, tmp_path):
    from omniscs.eval.nuscenes_io import NuScenesTables, evaluate_planning_results, load_planning_samples

    tables = NuScenesTables.load(dataroot, "v1.0-mini")
    keyframes = tables.scene_samples()
    samples, short = load_planning_samples(tables, keyframes)
    assert len(samples) >= 2 and short == 6 and len(keyframes) == len(samples) + short
    for s in samples:  # the ego drives ahead along its lane: y grows, x stays small
        assert np.all(np.diff(np.r_[0.0, s.trajectory[:, 1]]) > 0) and np.abs(s.trajectory[:, 0]).max() < 1.0
    results = {t: {"trajectory": [[0.0, 0.0]] * 6} for t in keyframes}  # the last keyframes too: allowed
    results.update({s.token: {"trajectory": s.trajectory.tolist()} for s in samples})
    path = tmp_path / "plan.json"
    path.write_text(json.dumps({"meta": {}, "results": results}))
    out = evaluate_planning_results(dataroot, "v1.0-mini", path)
    assert out["n_samples"] == len(samples) and out["n_short_future"] == 6
    assert out["uniad"]["L2"] == {"1s": 0.0, "2s": 0.0, "3s": 0.0}
    assert out["uniad"]["obj_box_col"] == {"1s": 0.0, "2s": 0.0, "3s": 0.0}
    standing = dict(results)
    standing.update({s.token: {"trajectory": [[0.0, 0.0]] * 6} for s in samples})  # the ego does not move
    path.write_text(json.dumps({"meta": {}, "results": standing}))
    still = evaluate_planning_results(dataroot, "v1.0-mini", path)
    want = np.mean([np.linalg.norm(s.trajectory[5]) for s in samples])
    assert still["uniad"]["L2"]["3s"] == pytest.approx(want) and want > 5.0


def test_bad_planning_results_are_clear_errors(dataroot, tmp_path):
    from omniscs.eval.nuscenes_io import evaluate_planning_results

    path = tmp_path / "plan.json"
    path.write_text(json.dumps({"results": {"nope": [[0, 0]] * 6}}))
    with pytest.raises(ValidationError, match="not evaluated here"):
        evaluate_planning_results(dataroot, "v1.0-mini", path)
    path.write_text(json.dumps({"results": {}}))
    with pytest.raises(ValidationError, match="lack sample"):
        evaluate_planning_results(dataroot, "v1.0-mini", path)
    path.write_text("[1, 2]")
    with pytest.raises(ValidationError, match="'results' object"):
        evaluate_planning_results(dataroot, "v1.0-mini", path)


@pytest.mark.slow
def test_the_eval_planning_command_prints_both_conventions(dataroot, tmp_path):
    import subprocess
    import sys

    from omniscs.eval.nuscenes_io import NuScenesTables, load_planning_samples

    tables = NuScenesTables.load(dataroot, "v1.0-mini")
    samples, _ = load_planning_samples(tables, tables.scene_samples())
    path = tmp_path / "plan.json"
    path.write_text(json.dumps({"results": {s.token: {"trajectory": (s.trajectory + [0.3, 0.4]).tolist()}
                                            for s in samples}}))
    args = [sys.executable, "-c", "from omniscs.cli import main; main()", "eval", "planning", "--dataroot",
            str(dataroot), "--results", str(path)]
    proc = subprocess.run([*args, "--json"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["uniad"]["L2"] == pytest.approx({"1s": 0.5, "2s": 0.5, "3s": 0.5})
    table = subprocess.run([*args, "--convention", "stp3"], capture_output=True, text=True, timeout=120)
    assert table.returncode == 0 and "stp3" in table.stdout and "uniad" not in table.stdout
    bad = subprocess.run([*args, "--convention", "vad"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--convention" in bad.stderr


def test_a_scene_bootstrap_resamples_whole_groups_and_pairs_the_two_planners():
    from omniscs.eval.planning import aggregate_planning, bootstrap_planning, per_sample_planning

    gt = _straight()
    empty = tuple([np.zeros((0, 5))] * 6)
    car = list(empty)
    car[3] = np.array([[3.0, 8.0, 4.0, 2.0, np.pi / 2]])
    samples = [PlanningSample(f"s{i}", gt, np.ones(6, bool), tuple(car) if i % 2 else empty) for i in range(8)]
    straight = {s.token: gt for s in samples}
    aside = {s.token: gt + np.array([3.0, 0.0]) for s in samples}  # 3 m right: into the car where there is one
    per_a, per_b = per_sample_planning(samples, straight), per_sample_planning(samples, aside)
    whole = aggregate_planning(per_b)
    assert whole["per_step"]["obj_box_col"][3] == pytest.approx(0.5)
    groups = [f"scene{i // 2}" for i in range(8)]  # each scene: one keyframe with the car, one without
    col = lambda o: o["per_step"]["obj_box_col"][3]  # noqa: E731
    a, b = bootstrap_planning(per_a, per_b, groups, col, n=50)
    assert np.all(a == 0) and np.allclose(b, 0.5)  # whole scenes drawn: always half the keyframes have the car
    l2a, l2b = bootstrap_planning(per_a, per_b, groups, lambda o: o["uniad"]["L2"]["3s"], n=5)
    assert np.all(l2a == 0) and np.allclose(l2b, 3.0)
    with pytest.raises(ValidationError, match="two groups"):
        bootstrap_planning(per_a, per_b, ["one"] * 8, col)


def test_catalog_rows_leave_a_horizon_no_keyframe_knows_empty_not_zero():
    from omniscs.eval.downstream import planner_rows

    gt = _straight()
    mask = np.array([1, 1, 1, 0, 0, 0], bool)  # only 1.5 s of the future known
    sample = PlanningSample("a", gt * mask[:, None], mask, tuple([np.zeros((0, 5))] * 6))
    out = evaluate_planning([sample], {"a": gt + 1.0})
    rows = planner_rows("e", "m", "d", "behaviour-SCS", out)
    value = {(r["convention"], r["metric"], r["horizon"]): r["value"] for r in rows}
    assert value[("uniad", "L2", "1s")] == pytest.approx(np.sqrt(2))
    assert all(value[(c, m, h)] is None for c in ("uniad", "stp3") for m in ("L2", "collision", "collision_known")
               for h in ("2s", "3s"))
    assert value[("uniad", "collision_known", "1s")] == 0.0
