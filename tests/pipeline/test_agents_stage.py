"""The agents stage: after the fit, tracks an edit turns get 360-degree models; the completed graph is what later
stages render; decisions reach the catalog; the stage reuses by key and runs inside the generate flow."""
import json
from pathlib import Path

import numpy as np
import pytest

from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.agents.pool import Pool
from omniscs.nsg.config import PRESETS
from omniscs.pipeline import stages
from omniscs.pipeline.agents import agents_stage
from omniscs.pipeline.request import SceneRequest
from tests.nsg_fixtures import tiny_fit_config, write_nsg_scene

TURN = {"op": "rotate", "track_id": 1, "yaw_deg": 180.0}


@pytest.fixture(scope="module")
def small_pool(tmp_path_factory) -> Path:
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.world.assets import build_asset

    pool = Pool(tmp_path_factory.mktemp("pool") / "pool")
    for aid in ("sedan-0046", "suv-0036"):
        a = build_asset(aid)
        params, _ = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, 1200, 0)
        pool.add(params, a.category, "mesh", aid)
    return pool.root


def _fitted(tmp_path, edits):
    store = write_nsg_scene(tmp_path / "in")
    plan = stages.load_plan(stages.plan_stage(store, SceneRequest(fit_preset="fast", edits=edits), tmp_path / "ws"))
    return store, plan, stages.fit_stage(store, plan, "fast", tmp_path / "ws")


def test_the_agents_stage_writes_a_completed_graph_and_its_decisions(tmp_path, monkeypatch, small_pool):
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.edit import apply_graph_edits

    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(10))
    store, plan, fitted = _fitted(tmp_path, (TURN,))
    assert plan.needs_360 == (1,) and plan.stages["agent_models"]
    record = agents_stage(store, plan, fitted, tmp_path / "ws", small_pool)
    assert not record.reused and record.info["status"] == "fitted" and record.info["strategies"] == {"1": "pool"}
    assert Path(record.path).parent.parent == tmp_path / "ws" / "agent_models"
    graph = load_graph(record.path)  # a checkpoint like any other: later stages render it
    decisions = json.loads((Path(record.path) / "decisions.json").read_text())["tracks"]
    assert {d["track_id"]: d["strategy"] for d in decisions} == {1: "pool", 2: "fitted"}
    rows = record.rows["agent_models"]
    assert catalog.validated_table("agent_models", rows).num_rows == 2
    row = next(r for r in rows if r["track_id"] == 1)
    assert row["pool_model_id"] in set(Pool(small_pool).table().model_id) and row["needs_360"]
    assert np.isfinite(row["distance"]) and 0 <= row["clarity"] <= 1
    naive = load_graph(fitted.path)
    a = apply_graph_edits(naive, [TURN]).render(naive.view("CAM_FRONT", 3)).rgb
    b = apply_graph_edits(graph, [TURN]).render(graph.view("CAM_FRONT", 3)).rgb
    assert float((a - b).abs().mean()) > 1e-3 and bool(b.isfinite().all())
    again = agents_stage(store, plan, fitted, tmp_path / "ws", small_pool)
    assert again.reused and again.path == record.path and again.rows == record.rows
    # without a pool: the online model; another key, another folder
    alone = agents_stage(store, plan, fitted, tmp_path / "ws", None)
    assert alone.path != record.path and alone.info["strategies"] == {"1": "online"}


def test_the_stage_is_skipped_when_no_edit_turns_an_agent(tmp_path, monkeypatch, small_pool):
    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(5))
    store, plan, fitted = _fitted(tmp_path, ({"op": "translate", "track_id": 1, "lateral": 1.0},))
    assert not plan.stages["agent_models"]
    assert agents_stage(store, plan, fitted, tmp_path / "ws", small_pool).skipped
    assert agents_stage(store, plan, None, tmp_path / "ws", small_pool).skipped


def test_generate_runs_the_agents_stage_between_fit_and_the_catalog(prefect_harness, tmp_path, monkeypatch,
                                                                    small_pool):
    from flows.generate import generate_dataset

    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(10))
    store = write_nsg_scene(tmp_path / "in")
    ws = tmp_path / "ws"
    result = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), run_id="turn", previews=False, fit_preset="fast",
                              edits=[TURN], pool=str(small_pool)))
    (scene,) = result["scenes"]
    assert list(scene["stages"]) == ["ingest", "plan", "fit", "agents"]
    rows = catalog.query(catalog.catalog_root(ws), "SELECT track_id, strategy, needs_360 FROM agent_models "
                                                   "ORDER BY track_id").to_pylist()
    assert rows == [{"track_id": 1, "strategy": "pool", "needs_360": True},
                    {"track_id": 2, "strategy": "fitted", "needs_360": False}]
    with pytest.raises(Exception, match="not a folder"):
        generate_dataset(dict(sources=[str(store)], workspace=str(ws), fit_preset="fast", edits=[TURN],
                         pool=str(tmp_path / "missing")))
