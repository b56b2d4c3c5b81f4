"""generate_dataset on Dask: a local cluster of worker processes catalogues every scene once, a worker killed in
the middle of a fit has its scene rerun elsewhere without duplicates, an unreachable scheduler is one clear error;
transient failures are retried and user errors are not; concurrent writers lose no catalog rows."""
from __future__ import annotations

import glob
import json
import multiprocessing
import os
import re
import signal
import threading
import time

import pytest
from prefect import flow, task

from flows.runners import check_runner, local_cluster, scene_task_runner, worker_threads
from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.errors import OmniscsError, ValidationError
from omniscs.pipeline import layout
from tasks.retries import STAGE_TASK_OPTIONS, is_transient

TINY = dict(n_frames=4, n_cameras=1, width=64, height=36, previews=False)


def test_bad_runner_choices_are_refused_before_anything_runs():
    for args in (("processes", None, None), ("threads", 0, None), ("threads", None, "tcp://127.0.0.1:8786"),
                 ("dask", 2, "tcp://127.0.0.1:8786"), ("dask", None, "http://x"), ("dask", None, "tcp://host")):
        with pytest.raises(ValidationError):
            check_runner(*args)


def test_an_unreachable_scheduler_is_one_clear_error():
    with pytest.raises(OmniscsError, match="unreachable"):
        check_runner("dask", None, "tcp://127.0.0.1:1")


def test_local_workers_share_the_cores_without_oversubscribing():
    assert worker_threads(1, cores=2) == 2 and worker_threads(2, cores=2) == 1 and worker_threads(4, cores=2) == 1
    runner = scene_task_runner("dask", workers=2)
    env = runner.cluster_kwargs["env"]
    assert runner.cluster_kwargs["n_workers"] == 2 and runner.cluster_kwargs["threads_per_worker"] == 1
    assert env["NUMBA_NUM_THREADS"] == env["OMP_NUM_THREADS"] == str(worker_threads(2))


#: A user's script that imports the flows (and numba) at its top, as scripts do: a spawned worker process imports
#: it again before the nanny's environment reaches the worker.
_SCRIPT = """
import json, os, sys
import numba  # noqa: F401
from flows.runners import local_cluster, scene_task_runner


def settings(dask_worker):
    import numba
    return {"numba": numba.config.NUMBA_NUM_THREADS, "malloc": os.environ.get("MALLOC_TRIM_THRESHOLD_"),
            "profiling": "profile" in dask_worker.periodic_callbacks}


if __name__ == "__main__":
    from distributed import Client
    runner = scene_task_runner("dask", workers=int(sys.argv[1]))
    assert runner.cluster_class is local_cluster
    with local_cluster(**{**runner.cluster_kwargs, "n_workers": 1}) as cluster, Client(cluster) as client:
        found = list(client.run(settings).values())
    print(json.dumps({"workers": found, "wanted": runner.cluster_kwargs["env"]["NUMBA_NUM_THREADS"],
                      "here": {k: os.environ.get(k) for k in ("NUMBA_NUM_THREADS", "MALLOC_TRIM_THRESHOLD_")}}))
"""


@pytest.mark.skipif(any(k in os.environ for k in ("MALLOC_TRIM_THRESHOLD_", "NUMBA_NUM_THREADS")),
                    reason="this shell sets the variables itself")
@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: a worker's thread count is numba's default")
@pytest.mark.slow  # starts a Dask worker process (11 s): make test's five minutes
def test_local_workers_start_with_their_threads_and_malloc_tuning_and_no_profiler(tmp_path):
    import subprocess
    import sys

    script = tmp_path / "user_script.py"
    script.write_text(_SCRIPT)
    done = subprocess.run([sys.executable, str(script), "2"], capture_output=True, text=True, timeout=300,
                          cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    wanted = int(out["wanted"])
    assert wanted < os.cpu_count()  # numba's default (all cores) would differ
    # numba's thread count as the nanny asked, although the script had imported numba before the worker ran;
    # glibc's malloc tuning (dask's own default would be "65536"); no stack sampling of the running task
    assert out["workers"] == [{"numba": wanted, "malloc": None, "profiling": False}]
    # the nanny sets the variables in the parent process to spawn a worker: put back once the workers are up
    assert out["here"] == {"NUMBA_NUM_THREADS": None, "MALLOC_TRIM_THRESHOLD_": None}


def test_only_transient_failures_count_as_transient():
    from distributed import KilledWorker

    assert is_transient(ConnectionError("reset")) and is_transient(TimeoutError())
    assert is_transient(KilledWorker("t", "w", 3))
    assert not is_transient(OmniscsError("bad source")) and not is_transient(ValueError("bug"))
    assert not is_transient(None)


def test_a_task_is_retried_after_a_lost_connection_but_never_after_a_user_error(prefect_harness):
    calls = {"transient": 0, "user": 0}

    @task(**{**STAGE_TASK_OPTIONS, "retry_delay_seconds": 0})
    def flaky(kind: str) -> str:
        calls[kind] += 1
        if calls[kind] == 1:
            raise ConnectionError("worker lost") if kind == "transient" else OmniscsError("bad input")
        return "ok"

    @flow
    def run(kind: str) -> str:
        return flaky(kind)

    assert run("transient") == "ok" and calls["transient"] == 2
    with pytest.raises(OmniscsError):
        run("user")
    assert calls["user"] == 1


@pytest.mark.slow
def test_generate_dataset_on_a_local_dask_cluster_catalogues_every_scene_once(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    out = generate_dataset(RunRequest(sources=["syn:straight:11", "syn:t_junction:12", "syn:intersection:13"], workspace=str(ws),
                           run_id="dask1", task_runner="dask", workers=2, **TINY))
    assert len(out["scenes"]) == 3 and not out["failed"]
    rows = catalog.query(layout.catalog_root(ws), "SELECT scene_id FROM scenes_by_run WHERE run_id = 'dask1'")
    assert sorted(rows.column("scene_id").to_pylist()) == sorted(s["scene_id"] for s in out["scenes"])
    run = catalog.query(layout.catalog_root(ws), "SELECT status FROM runs WHERE run_id = 'dask1'").to_pylist()
    assert run == [{"status": "completed"}]
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    with get_client(sync_client=True) as client:
        summaries = client.read_artifacts(artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=["run-summary"])))
    tables = [json.loads(a.data) if isinstance(a.data, str) else a.data for a in summaries
              if "dask1" in (a.description or "")]
    assert tables and sorted(r["scene"] for r in tables[0]) == sorted(s["scene_id"] for s in out["scenes"])
    assert all(r["status"] == "done" and "ingest" in r["made"] for r in tables[0])


def test_a_scheduler_that_does_not_answer_fails_the_run_in_one_line(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    with pytest.raises(OmniscsError, match="unreachable"):
        generate_dataset(dict(sources=["syn:straight:11"], workspace=str(ws), run_id="dask2", task_runner="dask",
                         dask_address="tcp://127.0.0.1:1", **TINY))
    run = catalog.query(layout.catalog_root(ws), "SELECT status, error FROM runs WHERE run_id = 'dask2'").to_pylist()
    assert run[0]["status"] == "failed" and "unreachable" in run[0]["error"]
    assert not (ws / "scenes").exists()  # no scene started


def _kill_the_fitting_worker(ws, killed: list) -> None:
    """SIGKILL the process holding a scene-graph fit's lock (its file names the holder's pid) once it has worked
    for a moment: a Dask worker dying in the middle of a task."""
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        for lock in glob.glob(f"{ws}/models/*/.nsg-*.lock"):
            try:
                m = re.search(r"pid (\d+)", open(lock).read())
            except OSError:
                continue
            if m and int(m.group(1)) != os.getpid():
                time.sleep(3.0)
                os.kill(int(m.group(1)), signal.SIGKILL)
                killed.append(int(m.group(1)))
                return
        time.sleep(0.2)


@pytest.mark.slow  # about 2 minutes (a fit, a killed worker, the rerun); `make test-slow` runs it
def test_a_worker_killed_mid_fit_has_its_scene_rerun_elsewhere_and_nothing_duplicated(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    killed: list[int] = []
    watcher = threading.Thread(target=_kill_the_fitting_worker, args=(ws, killed), daemon=True)
    watcher.start()
    out = generate_dataset(RunRequest(sources=["syn:straight:14", "syn:t_junction:15"], workspace=str(ws), run_id="dask3",
                           fit_preset="fast", task_runner="dask", workers=2, **{**TINY, "n_frames": 6}))
    watcher.join(timeout=5)
    assert killed, "no fit was seen running"
    assert len(out["scenes"]) == 2 and not out["failed"]
    root = layout.catalog_root(ws)
    models = catalog.query(root, "SELECT scene_id, status FROM models WHERE run_id = 'dask3'").to_pylist()
    assert sorted(m["scene_id"] for m in models) == sorted(s["scene_id"] for s in out["scenes"])
    assert all(m["status"] == "fitted" for m in models)
    raw = catalog.query(root, "SELECT count(*) AS n FROM scenes_raw WHERE run_id = 'dask3'").to_pylist()
    assert raw == [{"n": 2}]  # the rerun scene was catalogued once: its first try died before its catalog task


def _write_many(root: str, writer: str, n: int) -> None:
    for i in range(n):
        catalog.write_rows(root, "runs", "shared", [{
            "flow": f"{writer}-{i}", "status": "completed", "started_at_us": i, "finished_at_us": i, "n_scenes": 0,
            "config_json": "{}", "omniscs_version": "test", "error": None, "flow_run_id": None}], writer=writer)


@pytest.mark.slow
def test_two_writers_on_the_same_catalog_table_lose_nothing(tmp_path):
    root = str(tmp_path / "catalog")
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_write_many, args=(root, f"w{k}", 40)) for k in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    assert all(p.exitcode == 0 for p in procs)
    rows = catalog.query(tmp_path / "catalog", "SELECT flow FROM runs_raw").column("flow").to_pylist()
    assert sorted(rows) == sorted(f"w{k}-{i}" for k in range(2) for i in range(40))


@pytest.mark.slow
def test_generate_dataset_runs_on_an_existing_scheduler_given_by_address(prefect_harness, tmp_path):
    from distributed import LocalCluster

    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        out = generate_dataset(RunRequest(sources=["syn:straight:16"], workspace=str(ws), run_id="dask4", task_runner="dask",
                               dask_address=cluster.scheduler_address, **TINY))
    assert len(out["scenes"]) == 1 and not out["failed"]
    run = catalog.query(layout.catalog_root(ws), "SELECT status FROM runs WHERE run_id = 'dask4'").to_pylist()
    assert run == [{"status": "completed"}]
