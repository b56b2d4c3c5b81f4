"""The ego's solution to a behaviour variant: collision-free where the plan collides, within the comfort bounds,
on the plan when nothing is in the way, an honest "not solved" when a collision cannot be avoided, finite always."""
from __future__ import annotations

import numpy as np
import pytest

from behavior_fixtures import straight_world
from omniscs.errors import OmniscsError
from omniscs.pipeline.procedural import traffic_from_world
from omniscs.scs.behavior.collision import box_iou, footprints
from omniscs.scs.behavior.solution import SolutionConfig, solve_ego

N, DT, NOW = 40, 0.1, 10
SIZES = {"ego": [4.6, 1.9], "1": [4.5, 1.9]}
FAST = SolutionConfig(starts=16, steps=80)


@pytest.fixture(scope="module")
def traffic():
    return traffic_from_world(straight_world([{"x": 25.0, "y": 3.3, "speed": 3.0}], ego_speed=8.0, n_frames=N))


def _ego(traffic, speed_scale: float = 1.0) -> list:
    x0 = float(traffic.ego_xy[0, 0])
    return [[x0 + speed_scale * (float(traffic.ego_xy[i, 0]) - x0), float(traffic.ego_xy[i, 1]),
             float(traffic.ego_yaw[i])] for i in range(N)]


def _cut_in(start_x: float = 22.0, speed: float = 2.0) -> list:
    rows = []
    for i in range(N):
        y = 3.3 if i < NOW else max(0.0, 3.3 - 0.25 * (i - NOW))
        rows.append([start_x + speed * i * DT, y, 0.0 if i < NOW or y == 0 else -0.3])
    return rows


def _variant(traffic, adversary_rows, **changes) -> dict:
    v = {"variant_id": "v000", "scene_id": traffic.scene_id, "ego": _ego(traffic), "agents": {"1": adversary_rows},
         "sizes": dict(SIZES), "now_step": NOW, "dt": DT, "adversary": 1}
    v.update(changes)
    return v


def _max_iou(solution, rows) -> float:
    adv = np.array([r if r is not None else [np.nan] * 3 for r in rows], dtype=np.float64)
    on = ~np.isnan(adv[:, 0])
    fe = footprints(solution.trajectory[on, :2], solution.trajectory[on, 2], *SIZES["ego"])
    fa = footprints(adv[on, :2], adv[on, 2], *SIZES["1"])
    return float(box_iou(fe, fa).max())


def test_the_solution_avoids_a_cut_in_that_the_plan_hits(traffic):
    variant = _variant(traffic, _cut_in())
    plan_hit = _max_iou(type("P", (), {"trajectory": np.array(variant["ego"])})(), variant["agents"]["1"])
    assert plan_hit > 0.1  # the plan drives into the adversary
    solution = solve_ego(variant, traffic, FAST)
    assert solution.solved and solution.reason is None
    assert _max_iou(solution, variant["agents"]["1"]) == 0.0 and solution.min_gap_m > 0.0
    cb = FAST.comfort
    assert solution.max_decel_mps2 <= -cb.min_lon_accel * FAST.comfort_tolerance
    assert solution.max_accel_mps2 <= cb.max_lon_accel * FAST.comfort_tolerance
    assert solution.max_yaw_rate_radps <= cb.max_abs_yaw_rate * FAST.comfort_tolerance
    np.testing.assert_array_equal(solution.trajectory[:NOW + 1], np.array(variant["ego"])[:NOW + 1])


def test_the_solution_keeps_to_the_plan_when_nothing_is_in_the_way(traffic):
    far = [[300.0 + 3.0 * i * DT, 10.0, np.pi] for i in range(N)]
    solution = solve_ego(_variant(traffic, far), traffic, FAST)
    assert solution.solved and solution.mean_deviation_m < 0.1


def test_an_overlap_at_the_first_step_is_reported_unsolved_with_finite_numbers(traffic):
    ego = _ego(traffic)
    on_top = [list(r) for r in ego]  # the adversary sits on the ego from now on
    for i in range(NOW):
        on_top[i] = [ego[i][0], 3.3, 0.0]
    solution = solve_ego(_variant(traffic, on_top), traffic, FAST)
    assert not solution.solved and "collision" in solution.reason
    d = solution.to_dict()
    assert all(v is None or np.isfinite(v) for v in d.values() if isinstance(v, float))
    assert np.isfinite(solution.trajectory).all() and solution.min_gap_m < 0


def test_a_standing_ego_absent_agents_and_a_one_step_horizon_stay_finite(traffic):
    standing = [[1.3, 0.0, 0.0]] * N
    absent = [None] * N
    s1 = solve_ego(_variant(traffic, absent, ego=standing), traffic, FAST)
    assert s1.solved and np.isfinite(s1.trajectory).all() and s1.max_deviation_m < 1e-6
    s2 = solve_ego(_variant(traffic, _cut_in(), now_step=N - 2), traffic, FAST)
    assert np.isfinite(s2.trajectory).all() and len(s2.trajectory) == N
    s3 = solve_ego(_variant(traffic, _cut_in(), now_step=N - 1), traffic, FAST)  # nothing after now
    assert np.isfinite(s3.trajectory).all()
    far = [[10_000.0, 10_000.0, 0.0]] * N
    assert solve_ego(_variant(traffic, far), traffic, FAST).solved


def test_the_same_variant_gives_the_same_solution(traffic):
    a = solve_ego(_variant(traffic, _cut_in()), traffic, FAST)
    b = solve_ego(_variant(traffic, _cut_in()), traffic, FAST)
    np.testing.assert_array_equal(a.trajectory, b.trajectory)


@pytest.mark.parametrize("change, message", [
    ({"ego": None}, "ego"), ({"now_step": 99}, "now_step"), ({"dt": 0.0}, "dt"), ({"sizes": {"ego": [4.6, 1.9]}}, "sizes"),
    ({"agents": {"1": [[0.0, 0.0, float("nan")]] * N}}, "NaN"), ({"agents": {"1": [[0.0, 0.0, 0.0]] * 3}}, "list of"),
])
def test_a_malformed_variant_is_one_clear_error(traffic, change, message):
    with pytest.raises(OmniscsError, match=message):
        solve_ego(_variant(traffic, _cut_in(), **change), traffic, FAST)


def test_agents_far_from_the_plans_path_do_not_change_the_search_but_are_still_checked(traffic):
    far_rows = [[float(r[0]) + 5.0, 40.0, 0.0] for r in _ego(traffic)]  # a parallel road 40 m to the side
    base = _variant(traffic, _cut_in())
    with_far = _variant(traffic, _cut_in(), agents={"1": _cut_in(), "2": far_rows},
                        sizes={**SIZES, "2": [4.5, 1.9]})
    a, b = solve_ego(base, traffic, FAST), solve_ego(with_far, traffic, FAST)
    np.testing.assert_array_equal(a.trajectory, b.trajectory)
    assert b.solved and b.min_gap_m == pytest.approx(a.min_gap_m)
    # 30 m behind the ego on its own path: an ego that brakes could meet it, so it stays in the search
    from omniscs.scs.behavior.solution import _near_plan

    plan = np.array(_ego(traffic))[NOW + 1:]
    follower = np.array([[float(r[0]) - 30.0, float(r[1]), float(r[2])] for r in _ego(traffic)])[None, NOW + 1:]
    sideways = np.array(far_rows)[None, NOW + 1:]
    sizes = {"2": (4.5, 1.9)}
    assert _near_plan(plan, (4.6, 1.9), follower, np.ones(follower.shape[:2], bool), ["2"], sizes, 10.0) == [True]
    assert _near_plan(plan, (4.6, 1.9), sideways, np.ones(sideways.shape[:2], bool), ["2"], sizes, 10.0) == [False]
