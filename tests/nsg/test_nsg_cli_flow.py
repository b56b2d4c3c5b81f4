"""Scene graph end to end: omniscs fit / render, the fit_nsg flow task and its catalog rows."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.cli import app
from omniscs.nsg.config import PRESETS, LearningRates
from omniscs.pipeline.stages import fit_stage
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_nsg_scene(tmp_path_factory.mktemp("nsg-cli") / "scene", nsg_world(n_frames=5))


def test_fit_then_render_an_edited_graph_from_the_command_line(store, tmp_path):
    ckpt = tmp_path / "ckpt"
    result = CliRunner().invoke(app, ["fit", str(store), "--out", str(ckpt), "--preset", "fast", "--iterations", "40"])
    assert result.exit_code == 0, result.output
    assert "agent node(s) [1, 2]" in result.output and (ckpt / "gaussians.safetensors").is_file()
    plain, edited = tmp_path / "plain.png", tmp_path / "edited.png"
    for out, extra in ((plain, []), (edited, ["--edit", '[{"op": "translate", "track_id": 1, "lateral": 3.5}]'])):
        result = CliRunner().invoke(app, ["render", str(ckpt), "--camera", "CAM_FRONT", "--frame", "2",
                                          "--out", str(out), *extra])
        assert result.exit_code == 0, result.output
    a, b = np.asarray(Image.open(plain)), np.asarray(Image.open(edited))
    assert a.shape == (54, 96, 3) and np.abs(a.astype(int) - b.astype(int)).max() > 5


def _cli(*args):
    return subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", *args],
                          capture_output=True, text=True, timeout=120)


def test_render_user_errors_exit_2_with_one_line(store, tmp_path):
    proc = _cli("render", str(store), "--out", str(tmp_path / "x.png"))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "not a scene-graph checkpoint" in proc.stderr and proc.stderr.strip().count("\n") == 0


def test_flow_fits_each_scene_once_and_catalogues_the_model(prefect_harness, store, tmp_path, monkeypatch):
    from flows.generate import generate_dataset

    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(10))
    ws = tmp_path / "ws"
    first = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), previews=False, fit_preset="fast", run_id="r1"))
    second = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), previews=False, fit_preset="fast", run_id="r2"))
    fit1, fit2 = (r["scenes"][0]["stages"]["fit"] for r in (first, second))
    assert fit1["info"]["status"] == "fitted" and not fit1["reused"]
    assert fit2["reused"] and fit2["path"] == fit1["path"]
    rows = catalog.query(catalog.catalog_root(ws), "SELECT * FROM models_by_run ORDER BY run_id").to_pylist()
    assert [r["run_id"] for r in rows] == ["r1", "r2"] and rows[0]["agent_nodes"] == [1, 2]
    assert rows[0]["heldout_psnr"] > 10 and rows[0]["preset"] == "fast"
    assert (ws / "models" / "nsg-test").is_dir()


def test_a_diverged_fit_is_catalogued_as_such_and_leaves_no_checkpoint(store, tmp_path, monkeypatch):
    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(20, lr=LearningRates(sh_dc=1e30), divergence_warmup=5))
    plan = make_plan(load_scene(store), config=PRESETS["fast"].plan)
    (row,) = fit_stage(store, plan, "fast", tmp_path).rows["models"]
    assert row["status"] == "diverged" and row["checkpoint_path"] is None and "diverged" in row["error"]
    catalog.validated_table("models", [row])
    assert not any((tmp_path / "models").rglob("graph.json"))


def test_runs_that_waited_for_a_fit_that_diverged_take_its_outcome_and_a_later_run_fits_again(store, tmp_path,
                                                                                               monkeypatch):
    import threading

    from omniscs.nsg.train import FitDiverged
    from omniscs.pipeline import fit as fit_module

    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(20))
    plan = make_plan(load_scene(store), config=PRESETS["fast"].plan)
    calls, started, release = [], threading.Event(), threading.Event()

    def diverging(*args, **kwargs):
        calls.append(1)
        started.set()
        release.wait(30)
        raise FitDiverged(604, "smoothed loss exploded")
    monkeypatch.setattr(fit_module, "fit_scene", diverging)
    results = {}
    first = threading.Thread(target=lambda: results.setdefault("first", fit_stage(store, plan, "fast", tmp_path)))
    first.start()
    started.wait(30)
    blocked = threading.Event()  # the waiter reports waiting for the lock the first fit holds
    waiter = threading.Thread(target=lambda: results.setdefault("waiter", fit_stage(
        store, plan, "fast", tmp_path, progress=lambda *a: blocked.set())))
    waiter.start()
    assert blocked.wait(30)
    release.set()
    first.join(60)
    waiter.join(60)
    assert len(calls) == 1  # one fit for both
    for name in ("first", "waiter"):
        assert results[name].info["status"] == "diverged" and "iteration 604" in results[name].info["error"]
    assert results["waiter"].reused
    later = fit_stage(store, plan, "fast", tmp_path)
    assert len(calls) == 2 and not later.reused


def test_a_diverged_fit_fails_its_scene_with_the_reason_instead_of_a_completed_run(store, tmp_path, monkeypatch):
    from omniscs.errors import OmniscsError
    from omniscs.pipeline.request import SceneRequest
    from omniscs.pipeline.stages import run_directly, start_scene, walk_scene

    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(20, lr=LearningRates(sh_dc=1e30), divergence_warmup=5))
    state = start_scene(str(store), SceneRequest(fit_preset="fast", previews=False), tmp_path)
    with pytest.raises(OmniscsError, match=r"scene nsg-test: scene-graph fit diverged at iteration \d+"):
        walk_scene(state, run_directly())
