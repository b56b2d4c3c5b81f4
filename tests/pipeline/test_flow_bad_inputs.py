"""Bad parameters of the generate_dataset flow, called directly (Python, a deployment): each fails before any
scene starts with one OmniscsError line, recorded in the run's ``runs`` row, and no scene output is written.
The request (``RunRequest``) checks its fields' types and ranges itself, so a deployment's bad JSON is refused the
same way."""
from __future__ import annotations

import pytest

from omniscs import catalog
from omniscs.errors import OmniscsError

GOOD = {"sources": ["syn:straight:0"], "n_frames": 2, "n_cameras": 1, "width": 16, "height": 16}

CASES = [
    ("no sources", {"sources": []}, "at least one source"),
    ("unknown template", {"sources": ["syn:nope:1"]}, "unknown template"),
    ("negative seed", {"sources": ["syn:straight:-1"]}, "bad synthetic source 'syn:straight:-1'"),
    ("a seed in another script's digits", {"sources": ["syn:straight:\u0665"]}, "in ASCII digits"),
    ("a seed beyond 32 bits", {"sources": ["syn:straight:18446744073709551616"]}, "from 0 to 4294967295"),
    ("unknown lighting", {"sources": ["syn:straight:0:purple"]}, "unknown lighting"),
    ("bad synthetic form", {"sources": ["syn:straight"]}, "bad synthetic source"),
    ("missing store", {"sources": ["/nonexistent/store"]}, "neither syn:TEMPLATE:SEED"),
    ("one bad among good", {"sources": ["syn:straight:0", "syn:straight:0:purple"]}, "unknown lighting"),
    ("zero frames", {"n_frames": 0}, "n_frames"),
    ("too many frames", {"n_frames": 10 ** 7}, "n_frames"),
    ("seven cameras", {"n_cameras": 7}, "n_cameras"),
    ("width 1", {"width": 1}, "width"),
    ("height huge", {"height": 100_000}, "height"),
    ("unknown fit preset", {"fit_preset": "best"}, "fit_preset: Input should be 'fast', 'balanced' or 'accurate'"),
    ("negative variants", {"behavior_variants": -1}, "behavior_variants"),
    ("a million variants", {"behavior_variants": 10 ** 6}, "less than or equal to 1000"),
    ("unknown behaviour preset", {"behavior_preset": "ultra"}, "behavior_preset"),
    ("missing checkpoint", {"behavior_variants": 1, "behavior_checkpoint": "/nonexistent/ckpt"}, "checkpoint"),
    ("edit track id a bool", {"edits": [{"op": "remove", "track_id": True}]}, "track_id"),
    ("edit amount a string", {"edits": [{"op": "translate", "track_id": 1, "longitudinal": "3"}]}, "longitudinal"),
    ("edit of unknown kind", {"edits": [{"op": "explode", "track_id": 1}]}, "edit"),
    ("unknown device", {"device": "tpu"}, "device"),
    ("cuda without a GPU", {"device": "cuda:7"}, "cuda"),
    ("a count given as text", {"behavior_variants": "3"}, "behavior_variants: Input should be a valid integer"),
    ("a count given as a boolean", {"appearance_variants": True}, "appearance_variants: Input should be a valid integer"),
    ("frames given as a float", {"n_frames": 2.0}, "n_frames: Input should be a valid integer"),
    ("edits not a list", {"edits": {"op": "remove", "track_id": 1}}, "edits: Input should be a valid list"),
    ("an unknown field", {"fit_presets": "fast"}, "fit_presets: Extra inputs are not permitted"),
    ("unknown task runner", {"task_runner": "processes"}, "task_runner"),
    ("a dataset id that escapes", {"dataset_id": "../up"}, "dataset id '../up' is not a safe id"),
]


@pytest.mark.parametrize("name, change, message", CASES, ids=[c[0] for c in CASES])
def test_bad_flow_parameter_fails_before_any_scene_with_one_recorded_line(prefect_harness, tmp_path, name, change,
                                                                          message):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    with pytest.raises(OmniscsError, match=message) as info:
        generate_dataset(dict(**{**GOOD, **change}, workspace=str(ws), run_id="bad"))
    line = str(info.value)
    assert len(line.splitlines()) == 1
    assert sorted(p.name for p in ws.iterdir()) == ["catalog"]  # no scene, plan or preview started
    rows = catalog.query(catalog.catalog_root(ws), "SELECT status, n_scenes, error FROM runs").to_pylist()
    assert rows == [{"status": "failed", "n_scenes": 0, "error": " ".join(line.split())}]


def test_unsafe_run_id_is_refused_before_anything_is_written(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    with pytest.raises(OmniscsError, match="run id '../x' is not a safe id"):
        generate_dataset(dict(**GOOD, workspace=str(tmp_path / "ws"), run_id="../x"))
    assert not (tmp_path / "x").exists() and not any((tmp_path / "ws").rglob("*.parquet"))
