"""A run being stopped (SIGTERM or Ctrl-C reaching its flow) asks its running stages to stop at their next progress
report, so a process that waits for its threads (a notebook, a deployment's flow process) is not held until a fit
ends; the next run in the same process starts unstopped."""
from __future__ import annotations

import threading
import time

import pytest

from flows.runners import StoppableThreadPoolTaskRunner
from omniscs.progress import Stopped, clear_stop, no_progress, request_stop, stoppable


def test_a_stoppable_progress_raises_only_once_a_stop_is_requested():
    seen = []
    report = stoppable(lambda d, t=None, n="": seen.append(d))
    clear_stop()
    report(1, 10)
    request_stop()
    try:
        with pytest.raises(Stopped):
            report(2, 10)
    finally:
        clear_stop()
    report(3, 10)
    assert seen == [1, 3]


def test_leaving_the_runner_on_an_interrupt_stops_a_running_stage_at_its_next_report():
    """A stage thread reporting every 10 ms ends within a few reports of Ctrl-C leaving the runner (Prefect's own
    runner would have waited for it; here the thread itself ends)."""
    ended = threading.Event()
    report = stoppable(no_progress)

    def stage():
        try:
            for k in range(100_000):  # 1,000 s if never stopped
                report(k, 100_000)
                time.sleep(0.01)
        except Stopped:
            ended.set()

    runner = StoppableThreadPoolTaskRunner(max_workers=1)
    thread = threading.Thread(target=stage, daemon=True)
    try:
        with runner:
            thread.start()
            time.sleep(0.05)
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        pass
    assert ended.wait(2.0), "the stage went on after the run was stopped"
    with StoppableThreadPoolTaskRunner(max_workers=1):
        stoppable(no_progress)(1, 2)  # a new run in this process is not stopped
