"""The fit and edits benchmarks (``omniscs bench fit``, ``omniscs bench edits``): reports that label reduced sizes
and hold every number, and both run end to end at thumbnail size."""
from __future__ import annotations

import dataclasses
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


def test_a_compressed_schedule_scales_every_step_count_and_keeps_never_as_never():
    from omniscs.bench.fit import schedule_scaled
    from omniscs.nsg.config import fit_preset
    from omniscs.nsg.strategy import DensifyStrategy

    got = schedule_scaled(fit_preset("balanced"), 750)  # balanced: 3,000 iterations, refine 300-2,500 every 100
    assert got == {"iterations": 750, "sh_degree_interval": 250, "strategy": {
        "refine_start_iter": 75, "refine_stop_iter": 625, "refine_every": 25, "reset_every": 375}}
    config = fit_preset("balanced", **{**got, "strategy": DensifyStrategy(**{
        **dataclasses.asdict(fit_preset("balanced").strategy), **got["strategy"]})})
    assert config.iterations == 750 and config.resolution_schedule == fit_preset("balanced").resolution_schedule
    assert schedule_scaled(fit_preset("fast"), 15)["strategy"]["reset_every"] == 0     # fast never resets
    assert schedule_scaled(fit_preset("fast"), 15)["strategy"]["refine_every"] == 1    # an interval stays >= 1


def test_a_store_the_baseline_cannot_read_is_one_error_naming_both_schema_versions(tmp_path):
    from omniscs.bench.baseline import CURRENT_PACKAGE, run_probe
    from omniscs.bench.fit import _FIT_PROBE
    from omniscs.errors import OmniscsError
    from omniscs.scene import SCHEMA_VERSION

    (tmp_path / "manifest.json").write_text(json.dumps({"schema_version": SCHEMA_VERSION + 98}))
    with pytest.raises(OmniscsError, match=f"schema_version {SCHEMA_VERSION + 98} but this revision reads "
                                           f"{SCHEMA_VERSION}; choose a baseline"):
        run_probe(CURRENT_PACKAGE.parent, _FIT_PROBE, [str(tmp_path), "fast", "{}"])


def test_the_report_against_a_baseline_shows_both_sides_ratios_and_targets():
    small = BenchScenes(seeds=(0,), n_frames=8, n_cameras=1, width=96, height=54)
    machine = {"cpus": 2, "platform": "x", "load_average_start": [1.0, 1, 1], "load_average_end": [2.0, 2, 2]}
    comparison = {"preset": "balanced", "baseline_iterations": 3000, "current_iterations": 2000,
                  "baseline_wall_s": 573.0, "current_wall_s": 250.0, "speedup": 573 / 250,
                  "baseline_heldout_psnr": 31.33, "current_heldout_psnr": 31.1, "psnr_difference_db": -0.23,
                  "baseline_heldout_ssim": 0.9, "current_heldout_ssim": 0.899, "ssim_difference": -0.001,
                  "baseline_gaussians": 98615, "current_gaussians": 90000, "baseline_peak_rss_bytes": 2 * 2**30,
                  "current_peak_rss_bytes": 2**30, "memory_ratio": 0.5}
    from omniscs.bench.fit import _throughput_targets

    targets = _throughput_targets({"balanced": comparison})
    assert targets["balanced_met"] is True and targets["balanced_memory_met"] is True and targets["fast_met"] is None
    text = fit_markdown({"label": small.label(), "machine": machine, "summary": [], "rows": [],
                         "baseline": {"ref": "main~3", "commit": "a" * 40, "rounds": 2, "comparison": [comparison],
                                      "targets": targets},
                         "curve": [{"side": "current", "point": "balanced at 750 iterations", "preset": "balanced",
                                    "iterations": 750, "median_wall_s": 80.0, "median_heldout_psnr": 29.0}]})
    assert "Against main~3 (aaaaaaaaaaaa)" in text and "2 turn(s)" in text
    assert "| balanced | 3000 / 2000 | 573 / 250 | 2.29x | 31.33 / 31.10 | -0.23 | 0.900 / 0.899 | 98,615 / 90,000 " \
           "| 2,048 / 1,024 |" in text
    assert "in <= 5 min: met" in text and "faster than the baseline at its held-out PSNR (within 0.05 dB): not " \
                                          "measured" in text
    assert "| current | balanced at 750 iterations | 750 | 80 | 29.00 |" in text


@pytest.mark.slow
def test_quick_fit_against_the_same_revision_gives_identical_fits_ratios_and_the_curve(tmp_path):
    from typer.testing import CliRunner

    from omniscs.bench.baseline import resolve_commit
    from omniscs.cli import app

    result = CliRunner().invoke(app, ["bench", "fit", "--quick", "--baseline", "HEAD", "--presets", "fast,balanced",
                                      "--curve-iterations", "15", "--workspace", str(tmp_path / "ws"),
                                      "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    folder = tmp_path / "r" / "fit"
    report = json.loads((folder / "report.json").read_text())
    base = report["baseline"]
    assert base["ref"] == "HEAD" and base["commit"] == resolve_commit("HEAD") and base["rounds"] == 1
    assert [r["side"] for r in report["rows"]] == ["baseline", "current", "current", "baseline", "current"]
    by_preset = {c["preset"]: c for c in base["comparison"]}
    assert list(by_preset) == ["fast", "balanced"]
    for c in by_preset.values():
        # the same code on the same store with the same seed: the fits agree to the last digit
        assert c["current_heldout_psnr"] == c["baseline_heldout_psnr"] and c["psnr_difference_db"] == 0.0
        assert c["current_heldout_ssim"] == c["baseline_heldout_ssim"]
        assert c["current_gaussians"] == c["baseline_gaussians"] and c["current_iterations"] == 30
        assert c["speedup"] == pytest.approx(c["baseline_wall_s"] / c["current_wall_s"])
        assert c["memory_ratio"] == pytest.approx(c["current_peak_rss_bytes"] / c["baseline_peak_rss_bytes"])
    assert all(r["peak_rss_bytes"] >= r["rss_before_fit_bytes"] > 0 for r in report["rows"])
    assert {(p["side"], p["point"], p["iterations"]) for p in report["curve"]} == {
        ("baseline", "fast", 30), ("baseline", "balanced", 30), ("current", "fast", 30), ("current", "balanced", 30),
        ("current", "balanced at 15 iterations", 15)}
    assert [s["preset"] for s in report["summary"]] == ["fast", "balanced"]
    text = (folder / "report.md").read_text()
    assert "Against HEAD (" in text and "| fast | 30 / 30 |" in text and "+0.00 |" in text
    assert (folder / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (folder / "report.partial.json").exists()
