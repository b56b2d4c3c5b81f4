"""The one progress contract: every long stage reports ``progress(done, total, note)``; one throttle decides
when a sink (a Prefect progress artifact, a rich bar, plain lines in a log) hears about it."""
from __future__ import annotations

import sys
import time
from typing import Callable, Protocol, TextIO


class Progress(Protocol):
    """What every stage calls while it works: ``done`` of ``total`` units (``total`` None when unknown),
    with a short ``note`` (e.g. the current loss) that sinks may show."""

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None: ...


def no_progress(done: int, total: int | None = None, note: str = "") -> None:
    """The progress callback of a caller that does not watch."""


class Throttled:
    """Forwards a progress stream to ``sink`` only when it moved at least ``step_pct`` percent, or
    ``min_interval_s`` passed with any movement, or the work finished: Prefect artifacts and log lines stay
    few however many steps a stage takes, while the first and last report always get through."""

    def __init__(self, sink: Callable[[int, int | None, str], None], step_pct: float = 5.0,
                 min_interval_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.sink = sink
        self.step_pct = float(step_pct)
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._last_pct: float | None = None
        self._last_done: int | None = None
        self._last_time = -float("inf")

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        now = self._clock()
        pct = 100.0 * done / total if total else None
        finished = total is not None and done >= total
        first = self._last_done is None
        moved = done != self._last_done
        far = pct is not None and self._last_pct is not None and pct - self._last_pct >= self.step_pct
        late = moved and now - self._last_time >= self.min_interval_s
        if first or finished or far or late:
            self._last_pct, self._last_done, self._last_time = pct, done, now
            self.sink(done, total, note)


class LineProgress:
    """Plain periodic lines (``label: 40/100 (40%) note``) for logs and pipes, where a bar would be noise."""

    def __init__(self, label: str, stream: TextIO | None = None) -> None:
        self.label = label
        self.stream = stream

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        stream = self.stream or sys.stderr
        amount = f"{done}/{total} ({100.0 * done / total:.0f}%)" if total else f"{done}"
        stream.write(f"{self.label}: {amount}{'  ' + note if note else ''}\n")
        stream.flush()


def percent(done: int, total: int | None) -> float:
    """Progress as a percentage in [0, 100] (0 while the total is unknown)."""
    if not total:
        return 0.0
    return float(min(100.0, max(0.0, 100.0 * done / total)))
