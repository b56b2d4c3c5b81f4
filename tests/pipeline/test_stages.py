"""The stage functions: the plan stage records one plan per scene and request, later stages follow it, stages
reuse by key, and one scene's failure in the flow stops no other scene."""
import json
from pathlib import Path

import pytest

from omniscs import catalog
from omniscs.errors import OmniscsError
from omniscs.nsg.config import PRESETS
from omniscs.pipeline import stages
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.request import SceneRequest
from tests.conftest import write_tiny_scene
from tests.nsg_fixtures import tiny_fit_config, write_nsg_scene


def test_the_plan_stage_writes_one_plan_per_scene_and_request_and_reuses_it(tmp_path):
    store = write_tiny_scene(tmp_path / "in", n_frames=30, n_tracks=3, scene_id="road", with_lidar=False)
    first = stages.plan_stage(store, SceneRequest(), tmp_path / "ws")
    again = stages.plan_stage(store, SceneRequest(), tmp_path / "ws")
    other = stages.plan_stage(store, SceneRequest(behavior_variants=2), tmp_path / "ws")
    assert not first.reused and again.reused and again.path == first.path
    assert other.path != first.path and Path(first.path).parent.parent == tmp_path / "ws" / "plans" / "road"
    plan = stages.load_plan(first)
    assert not plan.stages["fit_nsg"] and not plan.stages["behavior_variants"]  # nothing asked, nothing modelled
    assert stages.load_plan(other).stages["behavior_variants"]
    (row,) = first.rows["plans"]
    assert catalog.validated_table("plans", [row]).num_rows == 1 and row["stages"] == []
    assert json.loads(Path(first.path).read_text())["scene_id"] == "road"


def test_a_bad_edit_is_refused_by_the_request_or_the_plan_before_any_work(tmp_path):
    store = write_tiny_scene(tmp_path / "in", n_tracks=2)
    with pytest.raises(OmniscsError):
        SceneRequest(edits=({"op": "fly", "track_id": 0},)).parsed_edits()
    with pytest.raises(OmniscsError, match="does not have"):
        stages.plan_stage(store, SceneRequest(edits=({"op": "remove", "track_id": 9},)), tmp_path / "ws")
    with pytest.raises(OmniscsError, match="fit_preset: Input should be 'fast', 'balanced' or 'accurate'"):
        SceneRequest(fit_preset="fastest")
    assert not (tmp_path / "ws" / "plans").exists()


def test_stages_the_plan_does_not_need_are_skipped(tmp_path):
    store = write_tiny_scene(tmp_path / "in")
    plan = stages.load_plan(stages.plan_stage(store, SceneRequest(), tmp_path / "ws"))
    assert stages.fit_stage(store, plan, "fast", tmp_path / "ws").skipped
    assert stages.behavior_stage(store, plan, 2, tmp_path / "ws").skipped
    assert not (tmp_path / "ws" / "models").exists() and not (tmp_path / "ws" / "variants").exists()


def test_records_survive_a_round_trip_through_json():
    record = StageRecord("fit", "s", "/x", reused=True, seconds=1.5, key="k", rows={"models": [{"a": 1}]},
                         info={"status": "fitted"})
    assert StageRecord.from_dict(json.loads(json.dumps(record.to_dict()))) == record
    request = SceneRequest(fit_preset="fast", behavior_variants=2, edits=({"op": "remove", "track_id": 1},))
    assert SceneRequest.from_dict(json.loads(json.dumps(request.to_dict()))) == request


def test_run_scene_fits_once_then_reuses_and_catalogues_every_stage(tmp_path, monkeypatch):
    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(10))
    store = write_nsg_scene(tmp_path / "in")
    request = SceneRequest(fit_preset="fast", previews=False)
    first = {r.stage: r for r in stages.run_scene(str(store), request, tmp_path / "ws", run_id="r1")}
    second = {r.stage: r for r in stages.run_scene(str(store), request, tmp_path / "ws", run_id="r2")}
    assert list(first) == ["ingest", "plan", "fit"]
    assert not first["fit"].reused and second["fit"].reused and second["fit"].path == first["fit"].path
    assert stages.fit_stage(store, stages.load_plan(first["plan"]), "fast", tmp_path / "ws", reuse=False).reused is False
    root = catalog.catalog_root(tmp_path / "ws")
    rows = catalog.query(root, "SELECT p.run_id, p.n_agent_nodes, m.reused FROM plans_raw p JOIN models_raw m "
                               "USING (run_id, scene_id) ORDER BY 1").to_pylist()
    assert rows == [{"run_id": "r1", "n_agent_nodes": 2, "reused": False},
                    {"run_id": "r2", "n_agent_nodes": 2, "reused": True}]


def test_a_fit_into_a_user_folder_holding_something_else_is_refused(tmp_path, monkeypatch):
    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(5))
    store = write_nsg_scene(tmp_path / "in")
    plan = stages.load_plan(stages.plan_stage(store, SceneRequest(fit_preset="fast"), tmp_path / "ws"))
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(OmniscsError, match="already exists"):
        stages.fit_stage(store, plan, "fast", out_dir=mine, replace=False)
    assert (mine / "notes.txt").read_text() == "keep me"


def test_one_failing_scene_stops_no_other_and_the_run_is_recorded_failed(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    small = write_tiny_scene(tmp_path / "in" / "a", n_tracks=2, scene_id="a")
    big = write_tiny_scene(tmp_path / "in" / "b", n_tracks=3, scene_id="b")
    ws = tmp_path / "ws"
    # track 2 exists only in scene b: scene a's plan refuses the edit, scene b goes on
    with pytest.raises(OmniscsError, match="1 of 2 scene"):
        generate_dataset(dict(sources=[str(small), str(big)], workspace=str(ws), run_id="half", previews=False,
                         edits=[{"op": "remove", "track_id": 2}]))
    root = catalog.catalog_root(ws)
    assert catalog.query(root, "SELECT scene_id FROM scenes").to_pylist() == [{"scene_id": "b"}]
    assert catalog.query(root, "SELECT scene_id, agent_nodes FROM plans").to_pylist() == [
        {"scene_id": "b", "agent_nodes": [1, 2]}]
    (run,) = catalog.query(root, "SELECT status, error FROM runs").to_pylist()
    assert run["status"] == "failed" and "does not have" in run["error"]


def test_a_log_too_short_for_behavior_variants_fails_at_its_plan_before_any_fit(tmp_path):
    store = write_tiny_scene(tmp_path / "in", n_frames=5)
    with pytest.raises(OmniscsError, match="behaviour variants need at least"):
        stages.plan_stage(store, SceneRequest(fit_preset="fast", behavior_variants=1), tmp_path / "ws")
    assert not (tmp_path / "ws").exists()
