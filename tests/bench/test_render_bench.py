"""The rasteriser benchmark writes its JSON, Markdown and plot and compares backends in one run."""
from __future__ import annotations

import json

from omniscs.render import rasterize
from omniscs.bench.render import run_render_benchmark
from omniscs.render.scenes import street_scene


def test_benchmark_writes_reports_and_speedups(tmp_path):
    # the reference's predicted cost for 50k Gaussians is ~500x that for 100: a 2 s budget splits them robustly
    results = run_render_benchmark(tmp_path, resolutions=((48, 27),), counts=(100, 50_000), repeats=1,
                                   reference_budget_s=2.0, calibration_size=((32, 18), 300))
    for name in ("report.json", "report.md", "report.png", "sample.png"):
        assert (tmp_path / "render" / name).stat().st_size > 0
    assert json.loads((tmp_path / "render" / "report.json").read_text())["rows"] == results["rows"]
    by_key = {(row["count"], row["backend"]): row for row in results["rows"]}
    assert not by_key[(100, "cpu")]["skipped"] and not by_key[(100, "reference")]["skipped"]
    assert by_key[(50_000, "reference")]["skipped"]  # over budget
    assert [s["source"] for s in results["speedups"]] == ["calibration", "grid"]
    assert all(s["forward"] > 0 and s["forward_backward"] > 0 for s in results["speedups"])
    assert results["peak_memory_at_max_count"]["48x27"]["peak_rss_bytes"] > 0


def test_street_scene_puts_gaussians_in_view():
    s = street_scene(2000, 64, 36)
    _, alphas, meta = rasterize(**s.as_kwargs(), backend="cpu")
    assert (meta["radii"][..., 0] > 0).float().mean() > 0.5
    assert alphas.mean() > 0.2
