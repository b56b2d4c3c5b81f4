"""External jobs: a command template filled without a shell, output streamed to a log, exit code and timeout
honoured (the process group stopped), UniAD's printed metrics parsed. ``fake_uniad.py`` stands in for the external
UniAD process: it prints UniAD's output format, crashes or hangs on request, and computes nothing."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from omniscs.errors import ValidationError
from omniscs.eval.external import job_argv, parse_uniad_output, run_job

FAKE = str(Path(__file__).with_name("fake_uniad.py"))
TEMPLATE = "{python} " + FAKE + " {config} '{checkpoint}'"


def test_a_template_is_filled_argument_by_argument_never_through_a_shell():
    argv = job_argv(TEMPLATE, {"python": sys.executable, "config": "ok", "checkpoint": "a b; rm -rf /"})
    assert argv == [sys.executable, FAKE, "ok", "a b; rm -rf /"]
    with pytest.raises(ValidationError, match="unknown placeholder"):
        job_argv("train {gpus}", {})
    with pytest.raises(ValidationError, match="needs a value"):
        job_argv("train {work_dir}", {})
    with pytest.raises(ValidationError, match="does not parse"):
        job_argv("train 'unclosed", {})


def test_a_finished_job_streams_its_log_and_its_metrics_are_parsed(tmp_path):
    lines = []
    argv = job_argv(TEMPLATE, {"python": sys.executable, "config": "ok", "checkpoint": "ckpt.pth"})
    result = run_job(argv, tmp_path / "logs" / "job.log", timeout_s=60, on_line=lines.append)
    assert result.ok and result.exit_code == 0 and result.reason is None
    log = Path(result.log_path).read_text()
    assert "ckpt.pth" in lines[0] and "NDS: 0.4976" in log and lines[-1] == result.tail[-1]
    metrics = parse_uniad_output(log)
    det, plan = metrics["detection"], metrics["planning"]
    assert det["mAP"] == 0.3823 and det["NDS"] == 0.4976 and det["mAVE"] == 0.3925
    assert det["classes"]["car"] == {"AP": 0.573, "ATE": 0.479, "ASE": 0.150, "AOE": 0.087, "AVE": 0.383, "AAE": 0.190}
    assert set(det["classes"]) == {"car", "pedestrian", "traffic_cone"}
    assert plan["convention"] == "uniad" and plan["steps"] == ["0.5s", "1.0s", "1.5s", "2.0s", "2.5s", "3.0s"]
    assert plan["per_step"]["L2"][5] == 1.8131 and plan["per_step"]["obj_box_col"][1] == 0.0010


def test_a_crash_is_its_exit_code_and_last_line(tmp_path):
    argv = job_argv(TEMPLATE, {"python": sys.executable, "config": "crash", "checkpoint": "x"})
    result = run_job(argv, tmp_path / "job.log", timeout_s=60)
    assert not result.ok and result.exit_code == 3 and "CUDA out of memory" in result.reason
    assert parse_uniad_output(Path(result.log_path).read_text()) == {}


def test_a_hanging_job_is_stopped_at_its_timeout(tmp_path):
    argv = job_argv(TEMPLATE, {"python": sys.executable, "config": "hang", "checkpoint": "x"})
    result = run_job(argv, tmp_path / "job.log", timeout_s=2)
    assert result.timed_out and result.exit_code is None and "timeout" in result.reason and result.seconds < 20
    assert "evaluating" in Path(result.log_path).read_text()


def test_a_missing_program_is_exit_code_127_not_a_traceback(tmp_path):
    result = run_job(["/nonexistent/uniad"], tmp_path / "job.log", timeout_s=5)
    assert result.exit_code == 127 and not result.ok and "could not start" in Path(result.log_path).read_text()
