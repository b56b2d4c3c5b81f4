"""The fit and edits benchmarks (``omniscs bench fit``, ``omniscs bench edits``): reports that label reduced sizes
and hold every number, and both run end to end at thumbnail size."""
from __future__ import annotations

import json

import pytest

from omniscs.bench.fit import BenchScenes, edits_markdown, fit_markdown


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
