"""The downstream benchmark end to end on a few scenes (slow: it generates variants and solves the ego)."""
from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.mark.slow
def test_the_quick_protocol_writes_its_report_with_both_test_sets(tmp_path):
    from omniscs.bench.downstream import quick_config, run_downstream_benchmark

    result = run_downstream_benchmark(tmp_path / "reports", tmp_path / "ws", quick_config())
    report = json.loads((tmp_path / "reports" / "downstream" / "report.json").read_text())
    assert (tmp_path / "reports" / "downstream" / "report.png").stat().st_size > 10_000
    assert set(report["rows"]) == {"behaviour-SCS test", "original test"}
    assert all(set(models) == {"straight on", "base", "fine-tuned", "logs-only control"}
               for models in report["rows"].values())
    orig = report["intervals"]["original test"]  # two test scenes: an interval over them
    assert orig["l2_change_3s"][0] <= orig["l2_change_3s"][1] and orig["n_scenes"] == 2
    for models in result["rows"].values():
        for m in models.values():
            assert m["n"] > 0 and all(np.isfinite(v) for v in (*m["L2"].values(), *m["collision"].values()))
    assert "proxy" in (tmp_path / "reports" / "downstream" / "report.md").read_text()
    # the fine-tuning settings are chosen on the validation scenes, one row per candidate
    grid = report["finetune_selection"]
    assert len(grid) == 2 and all(np.isfinite(g["l2_change_3s"]) for g in grid)
    assert (report["config"]["finetune"]["lr"], report["config"]["scs_share"],
            report["config"]["finetune"]["collision_weight"]) in {(g["lr"], g["scs_share"], g["collision_weight"])
                                                                  for g in grid}
    assert report["data"]["val"]["log_examples"] > 0


def test_rehearsal_keeps_only_the_logs_base_was_trained_on():
    from types import SimpleNamespace

    from omniscs.bench.downstream import _base_logs
    from omniscs.errors import ValidationError

    def example(scene_id):
        return SimpleNamespace(scenario=SimpleNamespace(scenario_id=scene_id))

    logs = [example("syn-straight-s300000"), example("syn-t_junction-s300039/v1"), example("syn-straight-s300040")]
    kept = _base_logs(logs, {"data": {"train_seeds": [300000, 300039]}})
    assert [e.scenario.scenario_id for e in kept] == ["syn-straight-s300000", "syn-t_junction-s300039/v1"]
    with pytest.raises(ValidationError, match="train seeds"):
        _base_logs(logs, {"data": {}})
