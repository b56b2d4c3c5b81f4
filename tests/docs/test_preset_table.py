"""The fit guide's preset table is generated from ``reports/fit/report.json``: the figures on the page are the
report's, in the format before ``--baseline`` and after it."""
from __future__ import annotations

import json
from pathlib import Path

from docs_helpers import REPO, load_generator


def test_the_guide_page_shows_the_reports_presets_instead_of_its_marker():
    generator = load_generator()
    page = generator.on_page_markdown((REPO / "docs" / "guide" / "fit.md").read_text(), None, None, None)
    report = json.loads((REPO / "reports" / "fit" / "report.json").read_text())
    assert "<!-- fit-presets -->" not in page and report["summary"]
    for s in report["summary"]:
        line = next(x for x in page.splitlines() if x.startswith(f"| `{s['preset']}` |"))
        assert f"| {s['median_heldout_psnr']:.2f} dB |" in line and f"| {s['median_wall_s']:,.0f} s |" in line
    assert "generated from `reports/fit/report.json`" in page


def test_a_report_against_a_baseline_gives_the_speed_up_and_psnr_difference_per_preset(tmp_path: Path):
    summary = {"preset": "balanced", "fits": 2, "diverged": 0, "iterations": 2000, "median_wall_s": 250.0,
               "median_gaussians": 90_000, "median_heldout_psnr": 31.1, "median_heldout_ssim": 0.899,
               "median_peak_rss_bytes": 3 * 2**28}
    report = {"label": "40 frames x 3 cameras at 480x270", "rounds": 2, "summary": [summary],
              "machine": {"cpus": 2, "load_average_start": [0.4, 0.5, 0.5]},
              "preset_settings": {"balanced": {"iterations": 2000, "resolution_schedule": [[0.0, 2], [0.5, 1]],
                                               "sh_degree": 1, "gaussians_per_m2": 3.0, "max_gaussians": 150_000}},
              "rows": [{"preset": "balanced", "side": "current", "point": "preset", "iterations": 2000}],
              "baseline": {"ref": "main~4", "commit": "b" * 40, "comparison": [
                  {"preset": "balanced", "speedup": 573.0 / 250.0, "psnr_difference_db": -0.23}]}}
    (tmp_path / "fit").mkdir()
    (tmp_path / "fit" / "report.json").write_text(json.dumps(report))
    table = load_generator().preset_table(tmp_path)
    assert "| `balanced` | 2,000 | 1/2, full from 50 % | 1 | 3 /m² (max 150k) | 250 s | 31.10 dB | 0.899 | 90,000 | " \
           "0.75 GiB | 2.29x | -0.23 dB |" in table
    assert "speed-up vs main~4" in table and "Against main~4 (bbbbbbbbbbbb)" in table and "settings as the report " \
                                                                                      "records them" in table
