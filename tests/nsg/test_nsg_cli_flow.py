"""Scene graph end to end: omniscs fit / render, the fit_nsg flow task and its catalog rows, the benchmarks' reports."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from omniscs import catalog
from omniscs.bench.fit import BenchScenes, edits_markdown, fit_markdown
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
    first = generate_dataset([str(store)], workspace=str(ws), previews=False, fit_preset="fast", run_id="r1")
    second = generate_dataset([str(store)], workspace=str(ws), previews=False, fit_preset="fast", run_id="r2")
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


def test_benchmark_reports_label_reduced_sizes_and_hold_every_number():
    small = BenchScenes(seeds=(0,), n_frames=8, n_cameras=1, width=96, height=54)
    assert "REDUCED SIZE" in small.label() and "REDUCED" not in BenchScenes().label()
    machine = {"cpus": 2, "platform": "x", "load_average_start": [1.0, 1, 1], "load_average_end": [2.0, 2, 2]}
    row = {"scene_id": "s", "preset": "fast", "iterations": 10, "status": "fitted", "wall_s": 12.0, "fit_s": 11.0, "n_gaussians": 1000,
           "n_agent_nodes": 1, "heldout_psnr": 25.5, "heldout_ssim": 0.8, "train_psnr": 27.0,
           "load_1min_before": 1.0, "load_1min_after": 2.0}
    text = fit_markdown({"label": small.label(), "machine": machine, "summary": [
        {"preset": "fast", "fits": 1, "median_wall_s": 12.0, "median_gaussians": 1000, "median_heldout_psnr": 25.5,
         "median_heldout_ssim": 0.8}], "rows": [row]})
    assert "REDUCED SIZE" in text and "25.50" in text and "load average 1.0" in text
    text = edits_markdown({"label": small.label(), "preset": "fast", "machine": machine, "unedited_heldout_psnr": 24.0,
                           "summary": [{"edit": "rotate 180°", "agents": 1, "psnr": 20.0, "ssim": 0.7,
                                        "masked_psnr": None, "masked_ssim": None}], "fits": [], "rows": []})
    assert "| rotate 180° | 1 | 20.00 | 0.700 | n/a | n/a |" in text


@pytest.mark.slow
def test_both_benchmarks_run_end_to_end_at_thumbnail_size(tmp_path):
    from omniscs.bench.fit import run_edit_benchmark, run_fit_benchmark

    scenes = BenchScenes(seeds=(0,), n_frames=8, n_cameras=2, width=96, height=54)
    tiny = {"iterations": 30, "resolution_schedule": ((0.0, 1),)}
    fit = run_fit_benchmark(tmp_path / "r", scenes, ("fast", "balanced"), tmp_path / "ws", overrides=tiny)
    assert [s["preset"] for s in fit["summary"]] == ["fast", "balanced"]
    edits = run_edit_benchmark(tmp_path / "r", scenes, "fast", agents_per_scene=1, frames_per_edit=2, min_pixels=20,
                               workspace=tmp_path / "ws", overrides=tiny)
    assert [s["edit"] for s in edits["summary"]] == ["translate 2.0 m", "translate 3.5 m", "rotate 90°", "rotate 180°",
                                                     "rotate 270°"]
    assert all(s["agents"] == 1 and s["masked_psnr"] is not None for s in edits["summary"])
    for name in ("fit/report.json", "fit/report.md", "fit/report.png", "edits/report.json", "edits/report.md",
                 "edits/report.png"):
        assert (tmp_path / "r" / name).stat().st_size > 100
    assert json.loads((tmp_path / "r" / "edits" / "report.json").read_text())["unedited_heldout_psnr"] > 10
