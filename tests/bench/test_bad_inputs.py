"""Every bad input in the table (``omniscs.bench.bad_inputs.CASES``: sources, options, ids, paths, damaged stores,
checkpoints, edit specs, catalog queries, over every command) ends as one clear line: exit code 2, one
``error:`` line on stderr, no traceback, nothing new on disk."""
from __future__ import annotations

import pytest

from omniscs.bench.bad_inputs import CASES, Fixtures, invoke, run_case


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory):
    return Fixtures(tmp_path_factory.mktemp("bad-input-fixtures"))


def test_the_table_covers_every_command_with_at_least_120_cases():
    assert len(CASES) >= 120 and len({c.id for c in CASES}) == len(CASES)
    commands = {" ".join(a for a in c.argv[:2] if not a.startswith(("-", "{", "syn:", "/"))) for c in CASES}
    for command in ("generate", "demo", "ingest", "fit", "render", "world make", "world render", "world export",
                    "scs train-behavior", "scs behavior", "scene info", "scene preview", "catalog query",
                    "catalog views", "bench world", "bench plan", "bench reliability"):
        assert any(c == command or c.startswith(command + " ") for c in commands), command


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_one_clear_line(case, fixtures, tmp_path):
    outcome = run_case(case, fixtures, tmp_path / "case")
    assert outcome.outcome == "one clear line", outcome


@pytest.mark.parametrize("argv, verbatim", [
    (["generate", "syn:[bold]x[/]:1"], "[bold]x[/]"),
    (["generate", "syn:straight:0:got [1,2] :x:"], "got [1,2] :x:"),
])
def test_markup_in_an_error_is_printed_verbatim(tmp_path, argv, verbatim):
    code, _, err, escaped = invoke(argv, tmp_path, {"OMNISCS_HOME": str(tmp_path / "ws")})
    assert code == 2 and not escaped and verbatim in err


def test_markup_in_query_results_is_printed_verbatim(fixtures, tmp_path):
    ws = fixtures.make("ws", tmp_path)
    code, out, err, _ = invoke(["catalog", "query", "SELECT '[bold]x[/] :x: [red]' AS a", "--workspace", str(ws)],
                               tmp_path, {})
    assert code == 0 and "[bold]x[/] :x: [red]" in out, err
