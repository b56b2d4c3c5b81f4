"""The behaviour benchmark (``omniscs bench behavior``): the ground truth of a variant re-rendered from the world,
the feasible-scene denominator, the report's honesty about L_app, and a small run end to end."""
import numpy as np
import pytest

from omniscs.bench.behavior import _summary, configurations, mark_feasible, markdown
from omniscs.scs.behavior.adversarial_config import adversarial_preset
from omniscs.quality import MAX_PSNR_DB
from omniscs.scs.behavior.render_consistency import masked_psnr


def test_ground_truth_of_a_variant_re_renders_the_adversary_on_its_new_path():
    from omniscs.bench.behavior import variant_ground_truth
    from tests.behavior_fixtures import straight_world

    world = straight_world([{"x": 14.0, "y": 3.3, "speed": 8.0}])
    steps = list(range(world.n_frames))
    logged = [[14.0 + 0.8 * f, 3.3, 0.0] for f in steps]
    moved = [[x, y - 3.3 if f >= 10 else y, yaw] for f, (x, y, yaw) in zip(steps, logged)]  # into the ego lane
    ego = [[1.3 + 0.8 * f, 0.0, 0.0] for f in steps]
    variant = {"agents": {"1": moved}, "adversary": 1, "source_frames": steps, "ego": ego,
               "ego_centre_ahead_of_origin_m": 1.3}
    rgb, mask = variant_ground_truth(world, variant, "CAM_FRONT", [5, 30])
    original_rgb, original_mask = variant_ground_truth(world, {**variant, "agents": {"1": logged}}, "CAM_FRONT",
                                                       [5, 30])
    assert rgb.shape == (2, 36, 64, 3) and mask.any()
    assert np.array_equal(mask[0], original_mask[0])  # before the edit nothing differs
    cols = np.nonzero(mask[1])[1].mean()
    original_cols = np.nonzero(original_mask[1])[1].mean()
    assert cols > original_cols + 5  # the adversary now sits straight ahead, right of where it was
    assert masked_psnr(rgb, rgb, mask) == MAX_PSNR_DB  # identical frames score the cap


def _row(scene, success, plausible):
    return {"scene_id": scene, "success": success, "plausible": plausible, "seconds": 1.0, "iterations": 10,
            "attempts": 1, "kind": "cut_in", "violations": [] if plausible else ["lateral acceleration 6 > 4.9"],
            "adversary_accel": [-1.0, 1.0], "adversary_max_lateral": 2.0}


def test_the_benchmark_counts_a_scene_feasible_by_search_or_by_a_plausible_success():
    scenes = [{"scene_id": "a", "reachable": True, "feasible_search": True},
              {"scene_id": "b", "reachable": True, "feasible_search": False},   # nobody can: excluded
              {"scene_id": "c", "reachable": False, "feasible_search": False},  # the search missed it
              {"scene_id": "d", "reachable": True, "feasible_search": True}]    # feasible, but the method fails
    rows = {"x": [_row("a", True, True), _row("b", True, False), _row("c", True, True), _row("d", False, True)],
            "rule": [_row("d", True, True)]}  # another plan: no proof for the replay plan
    mark_feasible(scenes, rows, ["x"])
    assert [s["feasible"] for s in scenes] == [True, False, True, True]
    assert [s["search_missed"] for s in scenes] == [False, False, True, False]
    s = _summary(rows["x"], scenes)
    assert s["feasible_scenes"] == 3 and s["scene_success_rate_feasible"] == pytest.approx(2 / 3)
    assert s["failed_feasible_scenes"] == ["d"]
    assert s["reachable_scenes"] == 3 and s["scene_success_rate_any_variant"] == pytest.approx(2 / 3)
    result = {"scenes": scenes, "bench": {"variants_per_scene": 1, "preset": "fast",
                                          "feasibility": {"starts": 64, "steps": 200}},
              "checkpoint_hash": "abc", "configurations": ["x"], "summary": {"x": s}, "rows": {"x": rows["x"]},
              "appearance": None}
    text = markdown(result)
    assert "3 scene(s) are **feasible**" in text and "the search missed 1: c" in text
    assert "| x | 67% (of 3) | 67% (of 3) |" in text and "Feasible scenes a configuration failed: x: d." in text


def _summary_row(**extra) -> dict:
    return {"scene_success_rate_any_variant": 1.0, "scene_success_rate_first_variant": 1.0,
            "scene_success_rate_feasible": 1.0, "feasible_scenes": 1, "reachable_scenes": 1,
            "variant_success_rate": 1.0, "successful_variants": 1, "variants": 1,
            "violation_rate_successful": 0.0, "violation_rate_all": 0.0,
            "adversary_abs_long_accel_mean": 1.0, "adversary_abs_long_accel_max": 2.0,
            "adversary_lateral_accel_mean": 1.0, "adversary_lateral_accel_max": 2.0,
            "seconds_per_variant_median": 1.0, "kinds": {"cut_in": 1}, **extra}


def test_benchmark_markdown_has_the_l_app_comparison_with_drift():
    from omniscs.bench.behavior import appearance_configs

    configs = configurations(adversarial_preset("fast"), rule_planner=False)
    assert len(configs) == 3
    study = {"scenes": [{"reachable": True}], "fits": [{"status": "fitted", "heldout_psnr": 27.5}],
             "fit_preset": "fast", "render": {"frames": 3, "downscale": 4},
             "summary": {name: _summary_row(appearance_drift_psnr_db_mean=21.25 if w is None else 23.5,
                                            appearance_drift_measured_variants=2)
                         for name, w in appearance_configs((1.0,))}}
    result = {"scenes": [{"reachable": True}], "bench": {"variants_per_scene": 1, "preset": "fast"},
              "checkpoint_hash": "abc", "summary": {name: _summary_row() for name in configs}, "appearance": study}
    text = markdown(result)
    assert "| default + L_app (weight 1) | 100% (of 1) | 100% (of 1) | 100% (1/1) | 0% | 1.00 | 23.50 | 2 |" in text
    assert "held-out PSNR 27.5 dB" in text
    assert "Not run" in markdown({**result, "appearance": None})


@pytest.mark.slow
def test_benchmark_runs_on_a_small_scene_set(tmp_path):
    from omniscs.bench.behavior import BenchConfig, run_behavior_benchmark

    result = run_behavior_benchmark(tmp_path, BenchConfig(scenes_per_template=1, variants_per_scene=1,
                                                          preset="fast", rule_planner=False, appearance_scenes=1,
                                                          app_weights=(1.0,)),
                                    workspace=tmp_path / "ws")
    assert (tmp_path / "behavior" / "report.md").is_file() and (tmp_path / "behavior" / "report.png").is_file()
    with_app = result["appearance"]["rows"]["default + L_app (weight 1)"]
    assert with_app and all(r["losses"]["L_app"] is not None for r in with_app)
