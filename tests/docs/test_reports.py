"""reports/ holds one folder per benchmark, each with its report, and pictures sized for reading."""
from __future__ import annotations

import json

from docs_helpers import REPO, load_generator

REPORTS = REPO / "reports"
PICTURE_LIMIT_BYTES = 600_000
GEN = load_generator()


def test_every_report_folder_is_a_known_benchmark():
    names = {p.name for p in REPORTS.iterdir()}
    unknown = sorted(names - set(GEN.BENCHMARK_NAMES))
    assert not unknown, (f"reports/ holds {unknown}: one folder per benchmark (docs/gen_results.py BENCHMARKS); a "
                         "rerun replaces its folder, one-off experiments go to docs/design-notes.md")


def test_every_report_folder_has_its_json_and_markdown():
    for folder in sorted(p for p in REPORTS.iterdir() if p.is_dir()):
        assert (folder / "report.md").is_file(), f"{folder.name} lacks report.md"
        json.loads((folder / "report.json").read_text())  # present and valid JSON


def test_every_picture_is_under_600_kb():
    pictures = [p for p in REPORTS.rglob("*") if p.is_file() and p.suffix.lower() in GEN.PICTURE_SUFFIXES]
    assert pictures, "no pictures found: the check would not check anything"
    too_big = {str(p.relative_to(REPO)): p.stat().st_size // 1024 for p in pictures
               if p.stat().st_size >= PICTURE_LIMIT_BYTES}
    assert not too_big, f"pictures over 600 KB (KB): {too_big}; save them as 256-colour PNG, JPEG or smaller"


def test_every_benchmark_page_shows_a_table_from_its_json():
    files = GEN.generate()
    for bench in GEN.BENCHMARKS:
        if not (REPORTS / bench.name / "report.json").is_file():
            continue
        page = files[f"results/{bench.name}.md"]
        assert "\n|---|" in page, f"results/{bench.name}.md has no table: its sections name no key of its JSON"
