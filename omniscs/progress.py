"""The one progress contract: every long stage reports ``progress(done, total, note)``; one throttle decides
when a sink (a Prefect progress artifact, a rich bar, plain lines in a log) hears about it. A run's feed carries the
progress of stages that run elsewhere (a Prefect task, a Dask worker) to the command that started the run."""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import sys
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Protocol, TextIO


class Progress(Protocol):
    """What every stage calls while it works: ``done`` of ``total`` units (``total`` None when unknown),
    with a short ``note`` (e.g. the current loss) that sinks may show."""

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None: ...


def no_progress(done: int, total: int | None = None, note: str = "") -> None:
    """The progress callback of a caller that does not watch."""


class Stopped(BaseException):
    """Raised from a stage's progress callback once the run is being stopped (``request_stop``): the stage unwinds
    at its next report (its temporary output goes with it) instead of running to its end. Like KeyboardInterrupt it
    is not an ``Exception``: no handler of errors takes it for a failure to record or retry, and Prefect reports
    the task as crashed (one line), not as failed with a traceback."""


#: Set while the run this process works for is being stopped (SIGTERM or SIGINT reached its flow, or the run was
#: cancelled): a process that ends only when its threads end (a deployment's flow process) then ends within one
#: progress report of each running stage, not after the stage.
_STOP = threading.Event()


def request_stop() -> None:
    """Ask every stage of this process to stop at its next progress report."""
    _STOP.set()


def clear_stop() -> None:
    """Forget an earlier stop request (a new run starts in this process)."""
    _STOP.clear()


def stoppable(progress: "Progress") -> "Progress":
    """``progress`` that raises ``Stopped`` instead of reporting once a stop was requested."""
    def report(done: int, total: int | None = None, note: str = "") -> None:
        if _STOP.is_set():
            raise Stopped("the run is being stopped")
        progress(done, total, note)
    return report


class Throttled:
    """Forwards a progress stream to ``sink`` only when it moved at least ``step_pct`` percent, or
    ``min_interval_s`` passed with any movement, or the work finished, or a new phase began (its total changed or
    its count went back, as when a stage moves from one kind of step to the next): Prefect artifacts and log lines
    stay few however many steps a stage takes, while the first and last report of each phase always get through."""

    def __init__(self, sink: Callable[[int, int | None, str], None], step_pct: float = 5.0,
                 min_interval_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.sink = sink
        self.step_pct = float(step_pct)
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._last_pct: float | None = None
        self._last_done: int | None = None
        self._last_total: int | None = None
        self._last_time = -float("inf")
        self._latest: tuple[int, int | None, str] | None = None

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        now = self._clock()
        self._latest = (done, total, note)
        pct = 100.0 * done / total if total else None
        finished = total is not None and done >= total
        first = self._last_done is None
        moved = done != self._last_done
        phase = not first and (total != self._last_total or done < self._last_done)
        far = pct is not None and self._last_pct is not None and pct - self._last_pct >= self.step_pct
        late = moved and now - self._last_time >= self.min_interval_s
        if first or finished or phase or far or late:
            self._last_pct, self._last_done, self._last_total, self._last_time = pct, done, total, now
            self.sink(done, total, note)

    def remind(self, note: str) -> bool:
        """When the sink heard nothing for ``min_interval_s``: forward the latest report if the work moved since
        the last one it heard (the interval rule, for reports that come too seldom to trigger it themselves), else
        the latest report again with ``note`` instead of its own (a long step that reports nothing still shows that
        it runs). True when it forwarded anything."""
        now = self._clock()
        if self._latest is None or now - self._last_time < self.min_interval_s:
            return False
        done, total, own = self._latest
        moved = done != self._last_done
        if moved:
            self._last_pct, self._last_done, self._last_total = (100.0 * done / total if total else None), done, total
        self._last_time = now
        self.sink(done, total, own if moved else note)
        return True


class LineProgress:
    """Plain periodic lines (``label: 40/100 (40%)  note``) for logs and pipes, where a bar would be noise; a
    report of nothing done of an unknown total shows only its note (``label: started``)."""

    def __init__(self, label: str, stream: TextIO | None = None) -> None:
        self.label = label
        self.stream = stream

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        stream = self.stream or sys.stderr
        amount = f"{done}/{total} ({100.0 * done / total:.0f}%)" if total else (f"{done}" if done or not note else "")
        stream.write(f"{self.label}: {'  '.join(part for part in (amount, note) if part)}\n")
        stream.flush()


def percent(done: int, total: int | None) -> float:
    """Progress as a percentage in [0, 100] (0 while the total is unknown)."""
    if not total:
        return 0.0
    return float(min(100.0, max(0.0, 100.0 * done / total)))


def tee(*sinks: Progress) -> Progress:
    """One progress callback that tells every one of ``sinks`` (each keeps its own throttle)."""
    def both(done: int, total: int | None = None, note: str = "") -> None:
        for sink in sinks:
            sink(done, total, note)
    return both


# ----------------------------------------------------------------------------- a run's feed
# The stages of a ``generate_dataset`` run execute as Prefect tasks, in this process (thread runner) or in Dask worker
# processes, on this machine or on others that share the workspace. Their progress reaches the command that started
# the run through a feed: a folder of the workspace that the command creates while it watches, into which every
# stage run appends its start, its (throttled) progress and its end as JSON lines, in a file of its own, and which
# the command reads every FEED_POLL_S. Files in the workspace, rather than Dask's pub/sub or Prefect's log API,
# because they work the same for every task runner (threads, a local cluster, a remote scheduler: the Dask runner
# already requires a shared workspace), need no client handle or server round trip, survive a worker that dies (its
# lines stay; the retry writes a new file), and cost nothing when nobody watches (no folder, no writes: a
# deployment's runs are unchanged). The folder is a temporary of the watching process (``omniscs.storage`` naming):
# removed when the command ends, and by ``clean_stale_temps`` if the command was killed.

#: Folder of the workspace that holds the feeds of watched runs.
FEED_ROOT = "progress"
#: Seconds between two reads of a feed by the command that watches it.
FEED_POLL_S = 0.5
#: A stage writes into the feed when it moved this many percent ...
FEED_STEP_PCT = 1.0
#: ... or this many seconds passed with any movement: fine enough for a terminal bar, few enough writes to cost nothing.
FEED_MIN_INTERVAL_S = 2.0


def _feed_name(workspace: str | os.PathLike, run_id: str) -> Path:
    return Path(workspace) / FEED_ROOT / run_id


@contextlib.contextmanager
def watched_run(workspace: str | os.PathLike, run_id: str) -> Iterator[Path]:
    """Open the feed of run ``run_id`` for the block (its folder, which stages that start meanwhile write into);
    the folder is removed afterwards."""
    from omniscs.storage import temp_sibling

    folder = temp_sibling(_feed_name(workspace, run_id))
    folder.mkdir(parents=True)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        with contextlib.suppress(OSError):  # the feeds' root goes once no run is watched
            folder.parent.rmdir()


@dataclass(frozen=True)
class FeedReport:
    """One line of a run's feed."""

    label: str
    """Whose progress: ``<scene> <stage>`` (``dataset`` for the run's dataset)."""
    done: int
    """Units done so far."""
    total: int | None
    """Units in all (None while unknown)."""
    note: str = ""
    """What the stage says about where it is (e.g. the current loss)."""
    event: str = "progress"
    """``start`` and ``end`` bracket one run of the stage (written whatever its own reports); ``progress`` is one of
    its reports, throttled by the writer."""
    at: float = 0.0
    """When it was written (seconds since the epoch): orders the reports of stage runs that one read finds."""


@contextlib.contextmanager
def stage_feed(workspace: str | os.PathLike, run_id: str | None, label: str) -> Iterator[Progress]:
    """For the block (one run of a stage of run ``run_id``): where the stage reports so that the command watching
    the run hears it (``label``, e.g. ``syn-straight-s3 fit``, names its lines), with its start and end marked; or
    ``no_progress`` when no command watches the run."""
    from omniscs.storage import temp_siblings

    folders = temp_siblings(_feed_name(workspace, run_id)) if run_id else []
    if not folders:
        yield no_progress
        return
    writer = FeedWriter(folders[0], label)
    writer.write(FeedReport(label, 0, None, "started", "start", time.time()))
    try:
        yield Throttled(writer, step_pct=FEED_STEP_PCT, min_interval_s=FEED_MIN_INTERVAL_S)
    finally:
        writer.write(FeedReport(label, 0, None, "", "end", time.time()))


class FeedWriter:
    """Appends one stage run's progress to a file of its own in a feed folder, one JSON line per report."""

    def __init__(self, folder: str | os.PathLike, label: str) -> None:
        self.path = Path(folder) / f"{uuid.uuid4().hex}.jsonl"
        self.label = label
        self._gone = False

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        self.write(FeedReport(self.label, int(done), None if total is None else int(total), str(note),
                              at=time.time()))

    def write(self, report: FeedReport) -> None:
        if self._gone:
            return
        try:  # one small write per line: a reader never sees half of a line unless the writer died inside it
            with open(self.path, "a", encoding="utf-8") as stream:
                stream.write(json.dumps(dataclasses.asdict(report)) + "\n")
        except OSError:  # the watcher ended (its folder is gone): the stage goes on, unwatched
            self._gone = True


class FeedReader:
    """Reads a feed folder incrementally: each ``read()`` returns the reports appended since the last one, in the
    order they were written."""

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self._offsets: dict[Path, int] = {}

    def read(self) -> list[FeedReport]:
        reports = []
        for path in sorted(self.folder.glob("*.jsonl")):
            start = self._offsets.get(path, 0)
            try:
                with open(path, "rb") as stream:
                    stream.seek(start)
                    chunk = stream.read()
            except OSError:
                continue
            end = chunk.rfind(b"\n") + 1  # a line still being written waits for the next read
            self._offsets[path] = start + end
            for raw in chunk[:end].splitlines():
                try:
                    r = json.loads(raw)
                    reports.append(FeedReport(str(r["label"]), int(r["done"]),
                                              None if r["total"] is None else int(r["total"]), str(r["note"]),
                                              str(r["event"]), float(r["at"])))
                except (ValueError, KeyError, TypeError):
                    continue  # the tail of a writer killed mid-line
        return sorted(reports, key=lambda r: r.at)  # stable: a stage's own reports keep their order


@contextlib.contextmanager
def following(folder: str | os.PathLike, deliver: Callable[[FeedReport], None],
              tick: Callable[[], None] | None = None, poll_s: float = FEED_POLL_S) -> Iterator[None]:
    """Pass every report of the feed in ``folder`` to ``deliver`` while the block runs (from one background thread,
    which also calls ``tick()`` after each read), and what is left once it ends."""
    reader, stop = FeedReader(folder), threading.Event()

    def drain() -> None:
        for report in reader.read():
            deliver(report)

    def loop() -> None:
        while not stop.wait(poll_s):
            drain()
            if tick is not None:
                tick()

    thread = threading.Thread(target=loop, name="omniscs-progress-feed", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        drain()  # the last reports (a stage's 100 %) written just before the run ended
