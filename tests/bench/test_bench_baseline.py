"""``--baseline REF``: a git revision of the project is extracted once and its package imported by probes in fresh
interpreters, beside the current code; a revision that does not exist is one clear error."""
from __future__ import annotations

import pytest

from omniscs.bench.baseline import CURRENT_PACKAGE, baseline_tree, resolve_commit, run_probe
from omniscs.errors import OmniscsError

WHICH_PACKAGE = "import json, omniscs; print(json.dumps({'file': omniscs.__file__}))"


def test_a_revision_is_extracted_once_and_its_probe_imports_that_revision(tmp_path):
    commit, tree = baseline_tree("HEAD", tmp_path)
    assert commit == resolve_commit("HEAD") and len(commit) == 40
    assert (tree / "omniscs" / "render" / "_cpu_kernels.py").is_file()
    assert baseline_tree("HEAD", tmp_path) == (commit, tree)          # reused, not extracted again
    assert [p.name for p in (tmp_path / "baseline").iterdir()] == [commit]  # no staging folder left behind
    assert run_probe(tree, WHICH_PACKAGE, [])["file"].startswith(str(tree))
    assert run_probe(CURRENT_PACKAGE.parent, WHICH_PACKAGE, [])["file"].startswith(str(CURRENT_PACKAGE))


def test_an_unknown_revision_or_a_failing_probe_is_one_clear_error(tmp_path):
    with pytest.raises(OmniscsError, match="is not a commit"):
        baseline_tree("no-such-branch-anywhere", tmp_path)
    assert not (tmp_path / "baseline").exists()
    with pytest.raises(OmniscsError, match="probe .* failed: .*ZeroDivisionError"):
        run_probe(CURRENT_PACKAGE.parent, "1 / 0", [])


@pytest.mark.slow
def test_render_against_a_baseline_reports_both_sides_and_their_ratios(tmp_path):
    from omniscs.bench.render import compare_with_baseline, render_markdown

    commit, tree = baseline_tree("HEAD", tmp_path)
    got = compare_with_baseline(("HEAD", commit, tree), ((64, 36),), (500,), repeats=2, rounds=2)
    (cell,) = got["cells"]
    for key in ("forward_s", "forward_backward_s", "forward_cpu_s", "forward_backward_cpu_s"):
        assert cell[f"baseline_{key}"] > 0 and cell[f"current_{key}"] > 0
        assert cell[f"speedup_{key}"] == pytest.approx(cell[f"baseline_{key}"] / cell[f"current_{key}"])
    results = {"machine": {"cpus": 2, "numba_threads": 2, "numba_threading_layer": "omp", "OMP_WAIT_POLICY": "PASSIVE",
                           "load_average_start": [1.0], "load_average_end": [1.0]},
               "settings": {"repeats": 2}, "first_call_s": 0.1, "rows": [], "speedups": [],
               "peak_memory_at_max_count": {}, "targets": {"measured": False}, "baseline": got}
    assert f"Against HEAD ({commit[:12]})" in render_markdown(results)
