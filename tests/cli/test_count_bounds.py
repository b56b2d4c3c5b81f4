"""Counts that can take a machine down are bounded where they are given: threads, optimiser steps and seeds are
refused by the option itself (exit 2, one line) before any work."""
from __future__ import annotations

import pytest
from typer.testing import CliRunner

from omniscs.checks import MAX_ITERATIONS, MAX_SEED, MAX_THREADS
from omniscs.cli import app

runner = CliRunner()


@pytest.mark.parametrize("argv, option", [
    (["fit", "/nowhere", "--threads", str(MAX_THREADS + 1)], "--threads"),
    (["fit", "/nowhere", "--threads", "0"], "--threads"),
    (["fit", "/nowhere", "--iterations", str(MAX_ITERATIONS + 1)], "--iterations"),
    (["world", "make", "--out", "/nowhere", "--seed", str(MAX_SEED + 1)], "--seed"),
    (["world", "make", "--out", "/nowhere", "--seed", "-1"], "--seed"),
    (["bench", "behavior", "--threads", str(MAX_THREADS + 1)], "--threads"),
    (["bench", "behavior", "--seed-offset", str(MAX_SEED + 1)], "--seed-offset"),
    (["bench", "reliability", "--seed", str(MAX_SEED + 1)], "--seed"),
])
def test_a_count_beyond_its_bound_is_refused_by_the_option(argv, option, tmp_path):
    result = runner.invoke(app, argv)
    assert result.exit_code == 2 and option in result.output, result.output


@pytest.mark.parametrize("given", [str(MAX_SEED + 1), "\u0665", "1,-2", "1e3"])
def test_bench_seed_lists_take_ascii_seeds_in_range_only(given):
    from omniscs.cli.common import seeds
    from omniscs.errors import OmniscsError

    with pytest.raises(OmniscsError, match="--seeds"):
        seeds(given)
    assert seeds("0, 7,4294967295") == (0, 7, MAX_SEED)
