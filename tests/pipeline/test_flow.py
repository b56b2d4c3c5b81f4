"""The generate_dataset flow: ingests scenes, writes previews and one catalog file per task, records the run."""
from pathlib import Path

import pytest

from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.errors import OmniscsError
from tests.conftest import write_tiny_scene


@pytest.fixture
def two_stores(tmp_path):
    return [write_tiny_scene(tmp_path / "in" / "a", scene_id="a"),
            write_tiny_scene(tmp_path / "in" / "b", scene_id="b", n_tracks=3)]


def test_generate_dataset_catalogues_every_scene_and_the_run(prefect_harness, tmp_path, two_stores):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    result = generate_dataset(RunRequest(sources=[str(p) for p in two_stores], workspace=str(ws), run_id="run-1"))
    assert [s["scene_id"] for s in result["scenes"]] == ["a", "b"]
    root = catalog.catalog_root(ws)
    scenes = catalog.query(root, "SELECT scene_id, n_tracks, source_kind, run_id FROM scenes ORDER BY 1").to_pylist()
    assert scenes == [{"scene_id": "a", "n_tracks": 2, "source_kind": "test", "run_id": "run-1"},
                      {"scene_id": "b", "n_tracks": 3, "source_kind": "test", "run_id": "run-1"}]
    assert catalog.query(root, "SELECT count(*) n FROM agents").to_pylist() == [{"n": 5}]
    assert catalog.query(root, "SELECT count(*) n FROM frames").to_pylist() == [{"n": 10}]
    runs = catalog.query(root, "SELECT status, n_scenes FROM runs").to_pylist()
    assert runs == [{"status": "completed", "n_scenes": 2}]
    # one file per scene and table: two scenes wrote two files in each scene table
    assert len(list((root / "agents" / "run_id=run-1").glob("*.parquet"))) == 2
    for s in result["scenes"]:
        assert Path(s["stages"]["preview"]["path"], "bev.png").stat().st_size > 0


def test_rerun_appends_a_new_partition_and_never_edits_the_first(prefect_harness, tmp_path, two_stores):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    generate_dataset(RunRequest(sources=[str(two_stores[0])], workspace=str(ws), run_id="first", previews=False))
    first = sorted((catalog.catalog_root(ws) / "scenes").rglob("*.parquet"))
    mtimes = [p.stat().st_mtime_ns for p in first]
    generate_dataset(RunRequest(sources=[str(two_stores[0])], workspace=str(ws), run_id="second", previews=False))
    assert [p.stat().st_mtime_ns for p in first] == mtimes
    rows = catalog.query(catalog.catalog_root(ws), "SELECT run_id FROM scenes_by_run ORDER BY 1").to_pylist()
    assert rows == [{"run_id": "first"}, {"run_id": "second"}]


def test_bad_source_fails_before_any_scene_starts_and_the_run_row_says_why(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    with pytest.raises(OmniscsError, match="neither syn:TEMPLATE:SEED nor an existing scene-store"):
        generate_dataset(dict(sources=["syn:straight:0", str(tmp_path / "missing")], workspace=str(ws), run_id="bad"))
    assert not (ws / "scenes").exists()  # the good source did not start either
    written = sorted(p.relative_to(ws).parts[:2] for p in ws.rglob("*.parquet"))
    assert written == [("catalog", "runs")]
    row = catalog.query(catalog.catalog_root(ws), "SELECT * FROM runs").to_pylist()[0]
    assert row["status"] == "failed" and row["n_scenes"] == 0
    assert "neither syn:TEMPLATE:SEED" in row["error"] and "\n" not in row["error"]


def test_synthetic_source_is_rendered_once_and_reused_by_the_next_run(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    kwargs = dict(workspace=str(ws), n_frames=2, n_cameras=1, width=64, height=36)
    first = generate_dataset(RunRequest(sources=["syn:straight_parked_truck:0:night"], run_id="r1", **kwargs))
    second = generate_dataset(RunRequest(sources=["syn:straight_parked_truck:0:night"], run_id="r2", previews=False, **kwargs))
    assert first["scenes"][0]["scene_id"] == second["scenes"][0]["scene_id"]
    assert [first["scenes"][0]["reused"], second["scenes"][0]["reused"]] == [False, True]
    root = catalog.catalog_root(ws)
    rows = catalog.query(root, "SELECT run_id, template, lighting, has_gt, reused FROM scenes_by_run ORDER BY run_id").to_pylist()
    assert rows == [{"run_id": "r1", "template": "straight_parked_truck", "lighting": "night", "has_gt": True, "reused": False},
                    {"run_id": "r2", "template": "straight_parked_truck", "lighting": "night", "has_gt": True, "reused": True}]
    big = catalog.query(root, "SELECT category FROM agents_by_run WHERE run_id = 'r1' AND category IN ('truck', 'trailer') "
                              "AND NOT moving").to_pylist()
    assert big, "the parked-truck template must catalogue its large static object"


def test_a_scene_named_twice_runs_and_is_catalogued_once(prefect_harness, tmp_path, two_stores):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    a = str(two_stores[0])
    result = generate_dataset(RunRequest(sources=[a, a, str(Path(a) / ".." / "a")], workspace=str(ws), run_id="twice", previews=False))
    assert [s["scene_id"] for s in result["scenes"]] == ["a"] and len(result["repeats"]) == 2
    raw = catalog.query(catalog.catalog_root(ws), "SELECT scene_id FROM scenes_raw").to_pylist()
    assert raw == [{"scene_id": "a"}]
    assert catalog.query(catalog.catalog_root(ws), "SELECT n_scenes FROM runs").to_pylist() == [{"n_scenes": 1}]
