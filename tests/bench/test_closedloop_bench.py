"""The closed-loop benchmark end to end on one tiny scene (slow: it fits a graph and makes a behaviour variant)."""
from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_the_quick_benchmark_reports_speed_scores_with_epdms_and_load(tmp_path):
    from omniscs.bench.closedloop import quick_config, run_closedloop_benchmark

    result = run_closedloop_benchmark(tmp_path / "reports", tmp_path / "ws", quick_config())
    report = json.loads((tmp_path / "reports" / "closedloop" / "report.json").read_text(), parse_constant=float)
    assert (tmp_path / "reports" / "closedloop" / "report.png").stat().st_size > 10_000
    assert {(r["cameras"], r["outputs"]) for r in report["speed"]} == {
        (1, "rgb+depth"), (1, "rgb+depth+instance+semantic"), (2, "rgb+depth"), (2, "rgb+depth+instance+semantic")}
    assert all(r["steps_per_s"] > 0 and 0 < r["render_share"] <= 1 for r in report["speed"])
    kinds = {(r["policy"], r["kind"]) for r in result["scores"]}
    assert kinds == {(p, k) for p in ("replay", "rule", "proxy") for k in ("log", "behavior")}
    assert result["load"]["errors"] == 0 and result["load"]["steps"] > 0
    assert result["load"]["latency_ms"]["p50"] <= result["load"]["latency_ms"]["p99"]
    md = (tmp_path / "reports" / "closedloop" / "report.md").read_text()
    assert "Closed-loop testing benchmark" in md and "EPDMS (NAVSIM TTC)" in md and "| LK |" in md
    assert all(0.0 <= r["epdms"] <= 1.0 and 0.0 <= r["epdms_navsim_ttc"] <= 1.0 for r in result["scores"])
    for policy in ("replay", "rule", "proxy"):
        for kind in ("log", "behavior"):
            assert report["summary"][policy][kind]["epdms"] is not None
            s = report["epdms_sub_scores"][policy][kind]
            assert s["tlc"] == 1.0 and s["with_lanes"] == s["n"] and 0.0 <= s["lk"] <= 1.0
