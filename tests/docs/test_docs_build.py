"""`mkdocs build --strict` builds the site (no broken links, no warnings), with Results pages from the reports."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from docs_helpers import REPO, load_generator


def test_site_builds_strict_with_generated_results(tmp_path: Path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "WARNING" not in run.stderr, run.stderr
    site = tmp_path / "site"
    assert (site / "results" / "fit" / "index.html").is_file()
    assert (site / "formats" / "catalog-columns" / "index.html").is_file()
    assert not any(p.name == "gen_results.py" for p in site.rglob("*")), "the generator was copied into the site"


def test_results_table_carries_the_figure_of_its_json():
    report = json.loads((REPO / "reports" / "fit" / "report.json").read_text())
    page = load_generator().generate()["results/fit.md"]
    for row in report["summary"]:
        assert f"{row['median_heldout_psnr']:.4g}" in page, f"{row['preset']}'s held-out PSNR is not on the page"


def test_readme_stays_short():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; details belong in docs/"
