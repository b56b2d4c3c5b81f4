"""Where a flow's scenes run, and which failures are worth another try.

Task runners: ``threads`` (this process, today's default), ``dask`` with a local cluster of N worker processes
(prefect-dask's ``DaskTaskRunner``), or ``dask`` with the address of an existing scheduler (many machines sharing one
workspace path). Stages pass paths and ids between tasks, never tensors, so a scene's stages can run on any worker.
Each local worker gets ``cores // N`` threads for torch, numba and OpenMP (set in its environment before it imports
them), so N workers never oversubscribe the cores.

Caching: a stage's own content-hash reuse (``omniscs.pipeline.reuse``: the hash of its inputs' content, its config and
its version, checked under a per-output lock) stays the one source of truth, on every worker and across runs: it
looks at what is on disk, so it also reuses what another run, the CLI or a benchmark made. Prefect's cache policies
would add a second, weaker key (``INPUTS`` hashes the records passed in, i.e. paths, not the files' content; a
changed scene store at the same path would hit) and need persisted results on storage every worker shares. So the
stage tasks carry no Prefect cache (``NO_CACHE``), on purpose.

Retries (``tasks.retries``): a stage task is retried with exponential backoff only for transient failures (a lost Dask
worker, a closed connection, a timeout); a user error (``OmniscsError``) or a bug is never retried. A Dask worker
that dies mid-task has its task rescheduled on another worker by Dask itself; the stage's reuse and the catalog's
per-key views keep the rerun from duplicating anything."""
from __future__ import annotations

import os

from prefect.task_runners import ThreadPoolTaskRunner

from omniscs.pipeline.validate import TASK_RUNNERS, check_runner  # noqa: F401  (checked with the run's inputs)
from omniscs.progress import clear_stop, request_stop

#: Scenes processed at once by the thread runner; the machines this runs on have 2 cores.
MAX_PARALLEL_SCENES = 2


def worker_threads(workers: int, cores: int | None = None) -> int:
    """Threads each of ``workers`` local processes may use on this machine's cores (at least 1)."""
    return max(1, (cores or os.cpu_count() or 1) // max(int(workers), 1))


class StoppableThreadPoolTaskRunner(ThreadPoolTaskRunner):
    """Prefect's thread runner, except that a stopped run (SIGTERM turned into Prefect's TerminationSignal, or
    SIGINT's KeyboardInterrupt) leaves without waiting for the running stages: Prefect's runner would wait for the
    running fit to end (minutes) before the stop reached the CLI. The CLI's process exits right after, taking the
    threads with it, records the run as cancelled and removes its temporaries; any other process (a deployment's
    flow process, Python calling the flow) waits for its threads at exit, so the running stages are also asked to
    stop at their next progress report (``omniscs.progress.request_stop``)."""

    def __enter__(self):
        clear_stop()
        return super().__enter__()

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        if exc_type is not None and not issubclass(exc_type, Exception):
            request_stop()  # running stages end at their next progress report (a process waits for its threads)
        if exc_type is not None and not issubclass(exc_type, Exception) and self._executor is not None:
            for event in getattr(self, "_cancel_events", {}).values():
                event.set()
            self._executor.shutdown(wait=False, cancel_futures=True)  # cancel_all() would wait for them
            self._executor = None
        super().__exit__(exc_type, exc_value, traceback)


def scene_task_runner(task_runner: str = "threads", workers: int | None = None, dask_address: str | None = None):
    """The task runner that runs a flow's scenes (its choice checked with the run's inputs: ``check_runner``)."""
    if task_runner == "threads":
        return StoppableThreadPoolTaskRunner(max_workers=int(workers or MAX_PARALLEL_SCENES))
    from prefect_dask import DaskTaskRunner

    if dask_address is not None:
        return DaskTaskRunner(address=dask_address)
    n = int(workers or MAX_PARALLEL_SCENES)
    threads = str(worker_threads(n))
    env = {"OMP_NUM_THREADS": threads, "NUMBA_NUM_THREADS": threads, "MKL_NUM_THREADS": threads,
           "OPENBLAS_NUM_THREADS": threads, "OMP_WAIT_POLICY": "PASSIVE"}
    return DaskTaskRunner(cluster_class=local_cluster,
                          cluster_kwargs={"n_workers": n, "threads_per_worker": 1, "processes": True, "env": env,
                                          "dashboard_address": None})


def local_cluster(**cluster_kwargs):
    """``distributed.LocalCluster`` whose worker processes start with their thread settings, keep glibc's own malloc
    tuning and run no statistical profiler.

    - Threads: the ``env`` variables (``scene_task_runner``'s thread counts) are also set before each worker
      process starts (Dask's ``pre-spawn-environ``), not only once it runs: a spawned worker first imports the
      parent's main module, so a script that imports the flows (and with them numba) at its top fixed numba's
      thread count before the nanny's ``env`` arrived. Measured on this 2-core machine with 2 workers: numba ran two
      threads in each worker, 4 on 2 cores. The variables are put back in this process once the workers are up
      (the nanny sets them here to spawn; a worker Dask restarts later sets them here again).
    - Malloc: Dask's nannies start workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (its default ``pre-spawn-environ``),
      which hands freed memory back to the system at once and, being set explicitly, also stops glibc from raising its
      mmap threshold: every large array a fit step allocates is then fresh pages from the kernel. Measured (fast
      fit, one 160x90 camera, 20 frames): 41 s in a plain process, 64-71 s with that variable, a third of it system
      time. A variable the user's own environment sets is still passed on.
    - Profiler: a Dask worker samples its running task's Python stack every 10 ms (for the dashboard's profile
      page, which these clusters do not serve), from its event loop thread, which takes the interpreter lock from
      the task each time. Measured with 2 workers on 2 cores (two dev scenes, fast fits at the scale-out setting):
      fits of 45 and 63 s with it, 38 and 54 s without."""
    import dask
    from distributed import LocalCluster

    env = {k: str(v) for k, v in (cluster_kwargs.get("env") or {}).items()}
    before = {k: os.environ.get(k) for k in env}
    spawn = {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in env.items()}
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                              "distributed.worker.profile.enabled": False, **spawn}):
            return LocalCluster(**cluster_kwargs)
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
