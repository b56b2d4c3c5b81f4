"""The reliability benchmark's checks (``omniscs bench reliability``), short forms: SIGTERM and SIGKILL of
`omniscs generate` and concurrent runs on one workspace, through the benchmark's process harness."""
from __future__ import annotations

import signal
import subprocess
import time

import pytest

from omniscs import catalog


def _wait_for(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return False


@pytest.mark.slow
def test_sigterm_stops_generate_records_the_run_and_leaves_no_server_or_temporaries(tmp_path):
    from omniscs.bench.reliability import children, cli_command, cli_env, running, workspace_state

    ws = tmp_path / "ws"
    proc = subprocess.Popen(cli_command() + ["generate", "syn:straight:45", "--frames", "40", "--cameras", "3",
                                             "--width", "160", "--height", "90", "--run-id", "stopped"],
                            env=cli_env(ws, tmp_path / "prefect"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert _wait_for(lambda: any(".tmp-" in p.name for p in (ws / "scenes").glob("*")), 240), \
            "rendering never started"
        server = children(proc.pid)
        assert server, "no temporary Prefect server was started"
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM
    assert err.strip().splitlines()[-1].startswith("error: run stopped stopped by SIGTERM")
    assert "Traceback" not in err
    assert _wait_for(lambda: not any(running(p) for p in server), 10)
    assert workspace_state(ws)["temporaries"] == []
    rows = catalog.query(catalog.catalog_root(ws), "SELECT status, error FROM runs").to_pylist()
    assert len(rows) == 1 and rows[0]["status"] == "cancelled"
    assert "stopped by SIGTERM" in rows[0]["error"]


@pytest.mark.slow
def test_sigkilled_runs_rerun_to_the_clean_result(tmp_path):
    """Fault injection, short form (one kill moment; the slow test below and `omniscs bench reliability` run 10):
    SIGKILL at a random moment, then the same command again; the rerun's catalog and files equal one clean
    run's."""
    from omniscs.bench.reliability import ReliabilityConfig, fault_injection

    config = ReliabilityConfig(sources=("syn:straight:46", "syn:t_junction:47:night"),
                               options=("--frames", "10", "--cameras", "1", "--width", "96", "--height", "54"),
                               kills=1, seed=7)
    result = fault_injection(config, tmp_path)
    assert len(result["kills"]) == 1
    assert result["clean_rows"]["scenes"] == 2 and result["clean_rows"]["agents"] > 0
    for kill in result["kills"]:
        assert kill["orphaned_processes"] == 0, kill
        assert kill["rerun_exit"] == 0, kill
        assert kill["catalog_equal"] and kill["files_equal"], kill
        assert kill["temporaries_after_rerun"] == 0, kill


@pytest.mark.slow
def test_four_concurrent_runs_with_overlapping_new_sources_all_succeed(tmp_path):
    from omniscs.bench.reliability import ReliabilityConfig, concurrency

    config = ReliabilityConfig(sources=("syn:straight:48", "syn:t_junction:49", "syn:intersection:50"),
                               options=("--frames", "6", "--cameras", "1", "--width", "96", "--height", "54"),
                               processes=4)
    result = concurrency(config, tmp_path)
    assert result["exit_codes"] == [0, 0, 0, 0], result["failed_output"]
    assert result["scene_stores"] == 3  # each new scene rendered once, whoever got there first
    assert sorted(r["status"] for r in result["runs"]) == ["completed"] * 4
    asked = {r["run_id"]: r["n_scenes"] for r in result["runs"]}
    assert {r["run_id"]: (r["rows"], r["scenes"]) for r in result["scenes_per_run"]} == \
        {run: (n, n) for run, n in asked.items()}
    assert result["scenes_twice_in_a_run"] == [] and result["temporaries_left"] == []


@pytest.mark.slow
def test_fault_injection_at_ten_moments(tmp_path):
    from omniscs.bench.reliability import ReliabilityConfig, fault_injection

    result = fault_injection(ReliabilityConfig(kills=10, seed=11), tmp_path)
    assert all(k["rerun_exit"] == 0 and k["catalog_equal"] and k["files_equal"] and not k["orphaned_processes"]
               and not k["temporaries_after_rerun"] for k in result["kills"]), result["kills"]


@pytest.mark.slow
@pytest.mark.parametrize("runner", [(), ("--task-runner", "dask", "--workers", "1")], ids=["threads", "dask"])
def test_sigterm_during_a_fit_ends_the_run_in_seconds_and_a_rerun_reuses_what_finished(runner, tmp_path):
    """With the thread runner and with a local Dask worker process (which must not outlive the run)."""
    from omniscs.bench.reliability import children, cli_command, cli_env, running, workspace_state

    ws = tmp_path / "ws"
    argv = cli_command() + ["generate", "syn:straight:51", "--frames", "6", "--cameras", "1", "--width", "160",
                            "--height", "90", "--fit-preset", "fast", "--no-previews", *runner, "--run-id", "fitstop"]
    proc = subprocess.Popen(argv, env=cli_env(ws, tmp_path / "prefect"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(lambda: any((ws / "models").glob("*/.tmp-*")) or any((ws / "models").glob("*/*/.tmp-*"))
                         or any((ws / "models").rglob("*.lock")), 300), "the fit never started"
        time.sleep(3)  # well inside the fit (tens of seconds here)
        helpers = children(proc.pid)  # the Prefect server, and the Dask worker processes with the dask runner
        sent = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert took < 10, f"the run took {took:.1f} s to stop"
    assert workspace_state(ws)["temporaries"] == []
    (row,) = catalog.query(catalog.catalog_root(ws), "SELECT status, error FROM runs").to_pylist()
    assert row["status"] == "cancelled" and "SIGTERM" in row["error"]
    assert _wait_for(lambda: not any(running(p) for p in helpers), 10), "a child process outlived the run"
    if runner:
        return  # the rerun's reuse does not depend on the runner (it is the stages' own)
    rerun = subprocess.run(argv[:-1] + ["fitagain"], env=cli_env(ws, tmp_path / "prefect"), capture_output=True,
                           text=True, timeout=900)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert "reused" in rerun.stdout.split("ingest", 1)[1]  # the ingested store is reused, not made again
