"""``omniscs predict`` then ``omniscs eval``: results made by the embedded proxies (or a user's external job) on a
dataroot are the files the evaluation reads; bad inputs around them are one clear error and leave nothing written."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from omniscs.errors import OmniscsError, ValidationError
from tests.conftest import write_tiny_scene


@pytest.fixture(scope="module")
def dataroot(tmp_path_factory):
    """A 36-frame straight drive (10 Hz) exported at 2 Hz: 8 keyframes, the first 2 with the whole 3 s future."""
    from omniscs.export import export_scenes

    root = tmp_path_factory.mktemp("predictroot")
    store = write_tiny_scene(root / "store", n_frames=36, n_tracks=3, scene_id="drive36")
    return export_scenes([store], "nuscenes", root / "nuscenes")


def run_cli(*args):
    return subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_predict_then_eval_is_two_commands_for_planning_and_detection(dataroot, tmp_path):
    plan = tmp_path / "plan.json"
    made = run_cli("predict", "planning", "--dataroot", dataroot, "--out", plan)
    assert made.returncode == 0, made.stderr
    assert "8 trajectories" in made.stdout and "then: omniscs eval planning" in made.stdout
    scored = run_cli("eval", "planning", "--dataroot", dataroot, "--results", plan, "--json")
    assert scored.returncode == 0, scored.stderr
    assert "version v1.0-trainval (the only one" in scored.stderr
    assert "2 of 8 keyframes have the 3 s of future" in scored.stderr
    out = json.loads(scored.stdout)
    assert out["n_samples"] == 2 and out["n_short_future"] == 6
    assert all(math.isfinite(v) and v >= 0 for v in out["uniad"]["L2"].values())

    det = tmp_path / "det.json"
    made = run_cli("predict", "detection", "--dataroot", dataroot, "--version", "v1.0-trainval", "--out", det)
    assert made.returncode == 0, made.stderr
    results = json.loads(det.read_text())
    assert results["meta"]["use_camera"] is True and len(results["results"]) == 8
    scored = run_cli("eval", "detection", "--dataroot", dataroot, "--results", det, "--json")
    assert scored.returncode == 0, scored.stderr
    assert json.loads(scored.stdout)["n_samples"] == 8

    before = plan.read_bytes()
    again = run_cli("predict", "planning", "--dataroot", dataroot, "--out", plan)
    assert again.returncode == 2 and "already exists" in again.stderr and "--overwrite" in again.stderr
    assert plan.read_bytes() == before
    assert run_cli("predict", "planning", "--dataroot", dataroot, "--out", plan, "--overwrite").returncode == 0


def test_planning_predictions_cover_every_keyframe_in_the_frame_eval_reads(dataroot):
    from omniscs.eval.nuscenes_io import NuScenesTables, load_planning_results, load_planning_samples
    from omniscs.eval.planner import load_planner
    from omniscs.eval.predict import predict_planning

    out = predict_planning(load_planner(), dataroot, None)
    tables = NuScenesTables.load(dataroot, None)
    keyframes = tables.scene_samples()
    assert sorted(out["results"]) == sorted(keyframes) and out["meta"]["version"] == "v1.0-trainval"
    evaluated, _ = load_planning_samples(tables, keyframes)
    plans = load_planning_results_from(out, evaluated, keyframes, load_planning_results)
    for sample in evaluated:  # the ego drives straight ahead at 10 m/s: so do the plans, give or take
        assert np.abs(plans[sample.token][:, 0]).max() < 2.0
        assert plans[sample.token][-1, 1] == pytest.approx(sample.trajectory[-1, 1], rel=0.3)


def load_planning_results_from(out, evaluated, keyframes, reader):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "plan.json"
        path.write_text(json.dumps(out))
        return reader(path, [s.token for s in evaluated], allowed=keyframes)


def test_the_ego_moves_as_its_poses_say_over_the_half_second_before_or_the_next_pose():
    from omniscs.eval.predict import ego_motion_at

    def frame(x, heading):  # planning frame at (x, 0): x right, y along the heading
        return np.array([[math.sin(heading), math.cos(heading), x], [-math.cos(heading), math.sin(heading), 0.0],
                         [0, 0, 1.0]])

    poses = [(0.1 * i, frame(2.0 * i, 0.05 * i)) for i in range(12)]  # 20 m/s, 0.5 rad/s
    speed, yaw_rate = ego_motion_at(poses, 1.0)
    assert speed == pytest.approx(20.0, rel=0.02) and yaw_rate == pytest.approx(0.5)
    assert ego_motion_at(poses, 0.0) == pytest.approx((20.0, 0.5), rel=0.02)  # the first: over the next pose
    assert ego_motion_at(poses[:1], 0.0) == (0.0, 0.0)


def test_the_drivable_area_of_a_map_expansion_has_its_holes_cut_out(tmp_path):
    from omniscs.eval.predict import DrivableArea

    nodes = {"a": (0, 0), "b": (10, 0), "c": (10, 10), "d": (0, 10), "e": (4, 4), "f": (6, 4), "g": (6, 6),
             "h": (4, 6)}
    expansion = {"node": [{"token": k, "x": x, "y": y} for k, (x, y) in nodes.items()],
                 "polygon": [{"token": "p", "exterior_node_tokens": list("abcd"),
                              "holes": [{"node_tokens": list("efgh")}]}],
                 "drivable_area": [{"token": "da", "polygon_tokens": ["p"]}]}
    path = tmp_path / "boston-seaport.json"
    path.write_text(json.dumps(expansion))
    area = DrivableArea.from_expansion(path)
    assert area.is_drivable(np.array([[1.0, 1.0], [5.0, 5.0], [11.0, 1.0], [9.0, 9.0]])).tolist() == \
        [True, False, False, True]
    path.write_text(json.dumps({"node": []}))
    with pytest.raises(ValidationError, match="not a nuScenes map expansion"):
        DrivableArea.from_expansion(path)


#: A stand-in for a user's model: writes planning results for N keyframes of the dataroot.
MODEL_SCRIPT = """import json, sys
samples = json.load(open(f"{sys.argv[1]}/{sys.argv[2]}/sample.json"))
plans = {s["token"]: {"trajectory": [[0.0, 5.0 * (i + 1)] for i in range(6)]} for s in samples[:int(sys.argv[4])]}
json.dump({"results": plans}, open(sys.argv[3], "w"))
"""


def test_an_external_model_runs_through_the_job_template_and_its_results_are_checked(dataroot, tmp_path):
    from omniscs.pipeline.predict import predict_external

    script = tmp_path / "model.py"
    script.write_text(MODEL_SCRIPT)
    out = tmp_path / "plan.json"
    template = f"{sys.executable} {script} {{dataset_root}} {{version}} {{results}} 8"
    summary = predict_external("planning", template, dataroot, None, out)
    assert summary["samples"] == 8 and len(json.loads(out.read_text())["results"]) == 8
    assert (tmp_path / "plan.json.job.log").is_file()

    bad = tmp_path / "bad.json"
    short = f"{sys.executable} {script} {{dataset_root}} {{version}} {{results}} 1"  # misses keyframes
    with pytest.raises(OmniscsError, match="results would not evaluate: .*lack sample"):
        predict_external("planning", short, dataroot, None, bad)
    with pytest.raises(OmniscsError, match="external planning job failed .*exit code 3"):
        predict_external("planning", f'{sys.executable} -c "raise SystemExit(3)"', dataroot, None, bad)
    with pytest.raises(OmniscsError, match="wrote no results"):
        predict_external("planning", f'{sys.executable} -c "pass"', dataroot, None, bad)
    with pytest.raises(ValidationError, match="unknown placeholder"):
        predict_external("planning", "echo {checkpint}", dataroot, None, bad)
    assert not bad.exists()


@pytest.mark.parametrize("args, message", [
    (["planning", "--out", "{tmp}/p.json"], "name exactly one of --dataroot"),
    (["planning", "--dataroot", "{root}", "--dataset", "ds-x", "--out", "{tmp}/p.json"], "name exactly one of"),
    (["planning", "--dataroot", "{root}", "--out", "{tmp}/p.txt"], "--out must end in .json"),
    (["planning", "--dataroot", "{root}", "--out", "{tmp}/p.json", "--model", "external"],
     "needs --external-template"),
    (["planning", "--dataroot", "{root}", "--out", "{tmp}/p.json", "--model", "uniad"], "--model is proxy or"),
    (["detection", "--dataroot", "{root}", "--out", "{tmp}/p.json", "--weights", "{tmp}"],
     "is not a proxy detector checkpoint"),
    (["planning", "--dataroot", "{root}", "--version", "v1.0-mini", "--out", "{tmp}/p.json"],
     r"has no nuScenes table folder 'v1.0-mini'; it has \['v1.0-trainval'\]"),
    (["planning", "--dataset", "ds-nothing", "--out", "{tmp}/p.json"], "ds-nothing is not a dataset"),
])
def test_bad_predict_inputs_are_one_error_line_and_write_nothing(args, message, dataroot, tmp_path):
    from typer.testing import CliRunner

    from omniscs.cli import app

    filled = [a.format(tmp=tmp_path, root=dataroot) for a in args]
    result = CliRunner().invoke(app, ["predict", *filled])
    assert result.exit_code != 0
    assert isinstance(result.exception, OmniscsError), result.output
    assert __import__("re").search(message, str(result.exception)) and "\n" not in str(result.exception)
    assert not (tmp_path / "p.json").exists() and not (tmp_path / "p.txt").exists()


def test_eval_planning_without_any_keyframe_with_a_future_says_how_long_a_scene_must_be(tmp_path):
    from omniscs.eval.nuscenes_io import evaluate_planning_results
    from omniscs.eval.planning import frames_for_planning
    from omniscs.export import export_scenes

    assert frames_for_planning(10.0) == 31 and frames_for_planning(2.0) == 7
    store = write_tiny_scene(tmp_path / "store", n_frames=20, scene_id="short20")
    root = export_scenes([store], "nuscenes", tmp_path / "nus")
    (tmp_path / "plan.json").write_text(json.dumps({"results": {}}))
    heard = []
    with pytest.raises(ValidationError, match=r"needs at least 7 keyframes at 2 Hz \(31 frames at 10 Hz\) and the "
                                              r"longest here has 4"):
        evaluate_planning_results(root, None, tmp_path / "plan.json", on_coverage=lambda *a: heard.append(a))
    assert heard == [(0, 4)]


@pytest.mark.slow  # importing the procedural world's constants takes seconds
def test_a_dataset_run_with_too_few_frames_for_planning_is_warned_before_it_starts():
    from omniscs.cli.generate import planning_frames_warning
    from omniscs.pipeline.request import RunRequest

    def request(frames, annotate=True):
        return RunRequest.parse({"sources": ["syn:straight:0"], "n_frames": frames, "annotate": annotate,
                                 "fit_preset": "fast", "behavior_variants": 1})

    said = planning_frames_warning(request(20))
    assert "--frames 20 is too few for planning evaluation" in said and "at least 31 frames" in said
    assert planning_frames_warning(request(31)) is None and planning_frames_warning(request(20, False)) is None


@pytest.fixture(scope="module")
def world_export(tmp_path_factory):
    """A 36-frame procedural log (it has roads: the export writes their map expansion) and its nuScenes export."""
    from omniscs.export import export_scenes
    from omniscs.scene import SyntheticSource, write_synthetic_scene

    root = tmp_path_factory.mktemp("predictworld")
    store = write_synthetic_scene(SyntheticSource(template="straight", seed=4, n_frames=36, n_cameras=1, width=64,
                                                  height=36), root / "store")
    return store, export_scenes([store], "nuscenes", root / "nuscenes")


@pytest.mark.slow  # a procedural log is made and exported (about 15 s)
def test_a_keyframe_of_an_export_looks_to_the_planner_as_its_log_did(world_export):
    """The planner's input at a keyframe read from the dataroot (boxes, history, speed, command, the map expansion's
    drivable area) is the one the planner was trained on for that instant of the log."""
    from omniscs.eval.downstream import log_examples
    from omniscs.eval.nuscenes_io import NuScenesTables
    from omniscs.eval.planner import features, features_of
    from omniscs.eval.predict import dataroot_planning_inputs

    store, root = world_export
    examples = log_examples([store])
    tables = NuScenesTables.load(root, None)
    inputs = dataroot_planning_inputs(tables, tables.scene_samples())
    assert examples and all(drivable is not None for _, _, drivable in inputs)
    for example in examples:
        raster, state, base = features(example)
        _, seen, drivable = inputs[example.step // 5]  # keyframes every 5 frames
        raster_read, state_read, base_read = features_of(seen, drivable)
        assert np.allclose(state_read, state, atol=1e-3) and np.allclose(base_read, base, atol=1e-3)
        for channel in range(len(raster)):  # box edges move by the offset between the LiDAR and the waypoint
            assert np.abs(raster_read[channel] - raster[channel]).sum() <= 0.1 * raster[channel].sum() + 4
        assert raster[3].sum() > 0


@pytest.mark.slow  # three exports and two evaluations in process (about 6 s)
def test_a_dataset_is_predicted_and_evaluated_under_the_tokens_of_its_export(tmp_path):
    """--dataset exports the dataset's variant stores for the run as `dataset export` does: the results made on it
    score against that export and against --dataset alike."""
    from typer.testing import CliRunner

    from omniscs.annotate.dataset import CARD_JSON, SCENES
    from omniscs.cli import app
    from omniscs.export import export_scenes

    dataset = tmp_path / "ds-tiny"
    write_tiny_scene(dataset / SCENES / "drive36", n_frames=36, n_tracks=2, scene_id="drive36")
    (dataset / CARD_JSON).write_text("{}")
    plan = tmp_path / "plan.json"
    runner = CliRunner()
    made = runner.invoke(app, ["predict", "planning", "--dataset", str(dataset), "--out", str(plan)])
    assert made.exit_code == 0, made.output
    for where in (["--dataset", str(dataset)],
                  ["--dataroot", str(export_scenes([dataset / SCENES / "drive36"], "nuscenes", tmp_path / "nus"))]):
        scored = runner.invoke(app, ["eval", "planning", *where, "--results", str(plan), "--json"])
        assert scored.exit_code == 0, scored.output
        assert json.loads(scored.stdout.strip().splitlines()[-1])["n_samples"] == 2
    bad = runner.invoke(app, ["eval", "planning", "--dataset", str(dataset), "--version", "v1.0-mini", "--results",
                              str(plan)])
    assert isinstance(bad.exception, OmniscsError) and "--version applies to --dataroot" in str(bad.exception)


@pytest.mark.slow  # an export and the CLI in process (about 5 s on a busy machine)
def test_eval_planning_of_a_dataset_too_short_for_it_names_the_dataset_not_its_temporary_export(tmp_path):
    from typer.testing import CliRunner

    from omniscs.annotate.dataset import CARD_JSON, SCENES
    from omniscs.cli import app

    dataset = tmp_path / "ds-short"
    write_tiny_scene(dataset / SCENES / "drive20", n_frames=20, scene_id="drive20")
    (dataset / CARD_JSON).write_text("{}")
    (tmp_path / "plan.json").write_text(json.dumps({"results": {}}))
    result = CliRunner().invoke(app, ["eval", "planning", "--dataset", str(dataset), "--results",
                                      str(tmp_path / "plan.json")])
    message = str(result.exception)
    assert isinstance(result.exception, ValidationError), result.output
    assert message.startswith("no keyframe of dataset ds-short has the 3 s of future") and "omniscs-predict" not in message
    assert "31 frames at 10 Hz" in message and "--frames 40" in message
