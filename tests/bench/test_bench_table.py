"""``omniscs bench`` is one table: every benchmark's options come from its options dataclass (help from the field
docs), every report lands in ``reports/<name>/`` and a rerun replaces its files; flows and the library's own tests
never import the benchmarks."""
import dataclasses
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from omniscs.bench.harness import write_report
from omniscs.cli import app
from omniscs.cli.bench import BENCHMARKS, field_docs
from tests.test_layering import imported_modules

ROOT = Path(__file__).resolve().parents[2]
NAMES = ("world", "sources", "behavior", "fit", "edits", "render", "plan", "dataset", "agents", "scaleout",
         "closedloop", "view", "appearance", "background", "downstream", "reliability", "bad-inputs")
runner = CliRunner()


def test_the_table_holds_every_benchmark_once():
    assert tuple(b.name for b in BENCHMARKS) == NAMES


@pytest.mark.parametrize("bench", BENCHMARKS, ids=lambda b: b.name)
def test_every_option_is_a_documented_field_and_shows_in_help(bench):
    docs = field_docs(bench.options)
    assert set(docs) == {f.name for f in dataclasses.fields(bench.options)}, "a field without a docstring"
    result = runner.invoke(app, ["bench", bench.name, "--help"], env={"COLUMNS": "400"})
    assert result.exit_code == 0, result.output
    help_text = " ".join(result.output.split())
    assert "--out" in help_text
    for f in dataclasses.fields(bench.options):
        flag = f.metadata.get("flag", "--" + f.name.replace("_", "-"))
        assert flag in help_text, (bench.name, flag)
        assert docs[f.name][:40] in help_text, (bench.name, f.name)


def test_a_bad_option_value_is_one_error_before_any_work(tmp_path):
    result = runner.invoke(app, ["bench", "world", "--seeds", "abc", "--out", str(tmp_path / "r")])
    assert result.exit_code != 0 and not (tmp_path / "r").exists()


def test_reports_go_to_one_folder_per_benchmark_and_a_rerun_replaces_them(tmp_path):
    def picture(buf):
        buf.write(b"png")

    for value in (1, 2):
        write_report(tmp_path, "downstream", {"x": value}, f"# run {value}\n", {"": picture})
        write_report(tmp_path, "downstream", {"y": value}, f"# detection {value}\n", {"": picture},
                     part="detection")
        write_report(tmp_path, "world", {"x": value}, "# world\n", {"": picture, "preview": picture})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["downstream", "world"]
    assert sorted(p.name for p in (tmp_path / "downstream").iterdir()) == \
        ["detection.json", "detection.md", "detection.png", "report.json", "report.md", "report.png"]
    assert sorted(p.name for p in (tmp_path / "world").iterdir()) == \
        ["preview.png", "report.json", "report.md", "report.png"]
    assert json.loads((tmp_path / "downstream" / "report.json").read_text()) == {"x": 2}
    write_report(tmp_path, "downstream", {"x": 3}, "# run 3\n")  # a run without its picture drops the old one
    assert not (tmp_path / "downstream" / "report.png").exists()
    assert (tmp_path / "downstream" / "detection.md").read_text() == "# detection 2\n"


def test_flows_never_import_the_benchmarks():
    files = sorted((ROOT / "flows").rglob("*.py"))
    assert files
    assert [f"{f.name}:{line} {name}" for f in files for line, name in imported_modules(f)
            if name == "omniscs.bench" or name.startswith("omniscs.bench.")] == []


def test_only_the_benchmarks_own_tests_import_them():
    tests = ROOT / "tests"
    offenders = [f"{f.relative_to(ROOT)}:{line}" for f in sorted(tests.rglob("*.py"))
                 if tests / "bench" not in f.parents
                 for line, name in imported_modules(f) if name == "omniscs.bench" or name.startswith("omniscs.bench.")]
    assert offenders == []
