"""Behaviour variants end to end: the CLI's variants.json format, user errors, the plan flag, the flow task and
catalog rows, and the benchmark report's honesty about L_app."""
import json
from pathlib import Path
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from omniscs import catalog
from omniscs.cli import app
from omniscs.errors import OmniscsError
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from omniscs.scs.behavior.adversarial_config import adversarial_preset
from omniscs.bench.behavior import configurations, markdown
from tests.conftest import write_tiny_scene

ISSUE_KEYS = {"variant_id", "dt", "ego", "agents", "sizes", "adversary", "collision_step", "success", "plausible",
              "losses"}


def test_scs_behavior_writes_variants_json_in_the_issue_format_and_a_picture_each(tmp_path):
    out = tmp_path / "v"
    result = CliRunner().invoke(app, ["scs", "behavior", "syn:t_junction:5", "--variants", "2", "--out", str(out),
                                      "--preset", "fast"])
    assert result.exit_code == 0, result.output
    variants = json.loads((out / "variants.json").read_text())
    assert len(variants) == 2
    for v in variants:
        assert ISSUE_KEYS <= set(v)
        assert v["dt"] == pytest.approx(0.1) and len(v["ego"]) == 40
        assert all(len(p) == 3 for p in v["ego"])
        assert str(v["adversary"]) in v["agents"] and "ego" in v["sizes"]
        assert set(v["agents"]) <= set(v["sizes"]) | {"ego"}
        assert all(len(traj) == 40 for traj in v["agents"].values())
        assert set(v["losses"]) == {"L_adv", "L_beh", "L_app", "L_restore", "L_plaus"} and v["losses"]["L_app"] is None
        assert v["collision_step"] is None or 10 <= v["collision_step"] < 40
        assert v["success"] == (v["collision_step"] is not None)
        assert (out / f"{v['variant_id']}.png").stat().st_size > 20_000


def _cli(*args):
    return subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", *args],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args, message", [
    (["syn:roundabout:1", "--variants", "1"], "unknown template"),
    (["syn:straight:1", "--variants", "0"], "--variants must be at least 1"),
    (["syn:straight:1", "--frames", "8", "--variants", "1"], "behaviour variants need at least"),
    (["syn:straight:1:8", "--variants", "1"], "unknown lighting"),  # one syn: grammar: the 4th part is lighting
    (["syn:straight:1", "--planner", "magic"], "unknown planner"),
    (["syn:straight:1", "--checkpoint", "/nonexistent"], "train-behavior"),
])
def test_scs_behavior_user_errors_are_domain_errors_that_write_nothing(tmp_path, args, message):
    result = CliRunner().invoke(app, ["scs", "behavior", *args, "--out", str(tmp_path / "o")])
    assert isinstance(result.exception, OmniscsError) and message in str(result.exception)
    assert not (tmp_path / "o").exists()


def test_scs_behavior_user_error_exits_2_with_one_line_and_no_traceback(tmp_path):
    proc = _cli("scs", "behavior", "syn:straight:1", "--frames", "8", "--out", str(tmp_path / "o"))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "behaviour variants need at least 11 steps" in proc.stderr and proc.stderr.strip().count("\n") == 0


def test_the_device_never_changes_which_behavior_variants_are_reused():
    from dataclasses import asdict, replace

    from omniscs.pipeline.stages import _result_config

    fast = adversarial_preset("fast")
    assert _result_config(asdict(replace(fast, device="cuda"))) == _result_config(asdict(fast))
    assert _result_config(asdict(replace(fast, seed=1))) != _result_config(asdict(fast))


def test_the_plan_runs_the_behavior_stage_only_when_variants_are_requested(tiny_scene):
    scene = load_scene(tiny_scene)
    assert not make_plan(scene).stages["behavior_variants"]
    assert make_plan(scene, behavior_variants=3).stages["behavior_variants"]
    with pytest.raises(OmniscsError, match="non-negative"):
        make_plan(scene, behavior_variants=-1)


def test_generate_dataset_makes_and_catalogues_behavior_variants(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    store = write_tiny_scene(tmp_path / "in" / "road", n_frames=30, n_tracks=3, scene_id="road", with_lidar=False)
    ws = tmp_path / "ws"
    result = generate_dataset([str(store)], workspace=str(ws), run_id="beh", previews=False, behavior_variants=2,
                              behavior_preset="fast")
    made = result["scenes"][0]["stages"]["behavior"]
    assert made["info"]["n_variants"] == 2 and Path(made["path"]).is_file()
    assert Path(made["path"]).parent.parent == ws / "variants" / "road"
    again = generate_dataset([str(store)], workspace=str(ws), run_id="beh2", previews=False, behavior_variants=2,
                             behavior_preset="fast")
    assert again["scenes"][0]["stages"]["behavior"]["reused"]
    root = catalog.catalog_root(ws)
    rows = catalog.query(root, "SELECT scene_id, variant_id, kind, adversary, success, plausible, loss_app, "
                               "run_id FROM variants_by_run ORDER BY variant_id").to_pylist()
    assert [r["scene_id"] for r in rows if r["run_id"] == "beh"] == ["road", "road"]
    assert all(r["loss_app"] is None and r["adversary"] in (0, 1, 2) for r in rows)
    assert catalog.query(root, "SELECT count(*) n FROM scenes_by_run").to_pylist() == [{"n": 2}]  # one per run


def test_generate_dataset_refuses_a_negative_variant_count(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    with pytest.raises(OmniscsError, match="non-negative"):
        generate_dataset(["syn:straight:0"], workspace=str(tmp_path), behavior_variants=-2)


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
