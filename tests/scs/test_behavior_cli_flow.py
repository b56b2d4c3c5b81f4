"""Behaviour variants end to end: the CLI's variants.json format, user errors, the plan flag, the flow task and
catalog rows, and the benchmark report's honesty about L_app."""
import json
from pathlib import Path
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.cli import app
from omniscs.errors import OmniscsError
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from omniscs.scs.behavior.adversarial_config import adversarial_preset
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

    from omniscs.pipeline.common import result_config

    fast = adversarial_preset("fast")
    assert result_config(asdict(replace(fast, device="cuda"))) == result_config(asdict(fast))
    assert result_config(asdict(replace(fast, seed=1))) != result_config(asdict(fast))


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
    result = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), run_id="beh", previews=False, behavior_variants=2,
                              behavior_preset="fast"))
    made = result["scenes"][0]["stages"]["behavior"]
    assert made["info"]["n_variants"] == 2 and Path(made["path"]).is_file()
    assert Path(made["path"]).parent.parent == ws / "variants" / "road"
    again = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), run_id="beh2", previews=False, behavior_variants=2,
                             behavior_preset="fast"))
    assert again["scenes"][0]["stages"]["behavior"]["reused"]
    root = catalog.catalog_root(ws)
    rows = catalog.query(root, "SELECT scene_id, variant_id, kind, adversary, success, plausible, loss_app, "
                               "run_id FROM variants_by_run ORDER BY variant_id").to_pylist()
    assert [r["scene_id"] for r in rows if r["run_id"] == "beh"] == ["road", "road"]
    assert all(r["loss_app"] is None and r["adversary"] in (0, 1, 2) for r in rows)
    assert catalog.query(root, "SELECT count(*) n FROM scenes_by_run").to_pylist() == [{"n": 2}]  # one per run


def test_generate_dataset_refuses_a_negative_variant_count(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    with pytest.raises(OmniscsError, match="behavior_variants: Input should be greater than or equal to 0"):
        generate_dataset(dict(sources=["syn:straight:0"], workspace=str(tmp_path), behavior_variants=-2))
