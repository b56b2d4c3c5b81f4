"""Which task failures are worth another try: transient ones (a lost Dask worker, a closed connection, a timeout),
retried with exponential backoff; never a user error (``OmniscsError``) or a bug."""
from __future__ import annotations

from prefect.cache_policies import NO_CACHE
from prefect.tasks import exponential_backoff

from omniscs.errors import OmniscsError

#: Retries of a task after a transient failure, and the first backoff (doubling each time, with jitter).
RETRIES = 2
BACKOFF_S = 5.0


def _transient_types() -> tuple[type, ...]:
    types: list[type] = [ConnectionError, TimeoutError, BrokenPipeError]
    try:
        from distributed import KilledWorker
        from distributed.comm.core import CommClosedError

        types += [KilledWorker, CommClosedError]
    except ImportError:
        pass
    return tuple(types)


def is_transient(exc: BaseException | None) -> bool:
    """A failure another try may not meet: a lost worker or connection, a timeout; never a user error."""
    return exc is not None and not isinstance(exc, OmniscsError) and isinstance(exc, _transient_types())


def retry_transient(task, task_run, state) -> bool:
    """Prefect's ``retry_condition_fn``: retry only what ``is_transient`` calls transient."""
    try:
        exc = state.result(raise_on_failure=False)
    except Exception as e:  # the result itself could not be read back: treat that as what failed
        exc = e
    return is_transient(exc if isinstance(exc, BaseException) else None)


#: Task options for stages: retried on transient failures only, with backoff; no Prefect cache, because each stage's
#: own content-hash reuse decides what is made again (flows/runners.py says why).
STAGE_TASK_OPTIONS = {"retries": RETRIES, "retry_delay_seconds": exponential_backoff(backoff_factor=BACKOFF_S),
                      "retry_jitter_factor": 0.5, "retry_condition_fn": retry_transient, "cache_policy": NO_CACHE}
