"""External jobs: fine-tuning or evaluating a real driving stack (UniAD, or any other) as a separate process that
a flow launches, watches and reads back.

A job is a command template with ``{placeholders}`` (``JOB_PLACEHOLDERS``: the exported dataset root, UniAD's info
files, a work dir, GPU ids, ...). The template is split into arguments first (shell-like quoting) and each argument
is then filled in, so a value never becomes more than one argument and nothing goes through a shell. The process
runs in its own process group with stdout and stderr streamed line by line into a log file (and to a callback);
a job that outlives its timeout is stopped (SIGTERM, then SIGKILL after ``KILL_GRACE_S``), the whole group with
it. What UniAD prints at the end of an evaluation is parsed into metrics (``parse_uniad_output``): the nuScenes
detection summary (``mAP:``, ``NDS:``, the mean errors and the per-class table of the devkit's report) and the
planning table (``metrics | 0.5s ... 3.0s`` rows ``obj_col``, ``obj_box_col``, ``L2``).

Example template for UniAD's evaluation on a GPU host (``tools/uniad_dist_eval.sh`` of OpenDriveLab/UniAD):
``./tools/uniad_dist_eval.sh {config} {checkpoint} {n_gpus}`` run with ``cwd`` at the UniAD checkout and
``CUDA_VISIBLE_DEVICES={gpu_ids}`` in the environment.
"""
from __future__ import annotations

import os
import re
import shlex
import signal
import string
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from omniscs.errors import ValidationError

#: Placeholders a job template may use (``version``, ``task`` and ``results``: the table version of the dataroot,
#: detection or planning, and the file an ``omniscs predict`` job writes its results to).
JOB_PLACEHOLDERS = ("dataset_root", "info_train", "info_val", "work_dir", "gpu_ids", "n_gpus", "config",
                    "checkpoint", "dataset_id", "python", "version", "task", "results")
#: Seconds between SIGTERM and SIGKILL when a job is stopped.
KILL_GRACE_S = 10.0
#: Lines of the log kept in memory for the result (the whole log is on disk).
TAIL_LINES = 200


def job_argv(template: str, values: dict[str, object]) -> list[str]:
    """The argument list of ``template`` with every ``{placeholder}`` filled from ``values``; unknown or missing
    placeholders and bad quoting are clear errors."""
    try:
        tokens = shlex.split(template)
    except ValueError as e:
        raise ValidationError(f"job template {template!r} does not parse ({e})") from e
    if not tokens:
        raise ValidationError("job template is empty")
    argv = []
    for token in tokens:
        try:
            names = [name for _, name, _, _ in string.Formatter().parse(token) if name is not None]
        except ValueError as e:
            raise ValidationError(f"job template argument {token!r}: {e}") from e
        unknown = [n for n in names if n not in JOB_PLACEHOLDERS]
        if unknown:
            raise ValidationError(f"job template names unknown placeholder(s) {unknown}; known: {list(JOB_PLACEHOLDERS)}")
        missing = [n for n in names if values.get(n) is None]
        if missing:
            raise ValidationError(f"job template needs a value for {missing}")
        argv.append(token.format(**{n: values[n] for n in names}))
    return argv


@dataclass
class JobResult:
    """How an external job ended."""

    argv: list[str]
    exit_code: int | None        # None when it was stopped after its timeout
    timed_out: bool
    seconds: float
    log_path: str
    tail: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.exit_code == 0 and not self.timed_out

    @property
    def reason(self) -> str | None:
        """Why it failed, in one line (None when it succeeded)."""
        if self.timed_out:
            return f"stopped after its timeout of {self.seconds:.0f} s"
        if self.exit_code != 0:
            last = next((line for line in reversed(self.tail) if line.strip()), "")
            return f"exit code {self.exit_code}" + (f": {last.strip()[:300]}" if last else "")
        return None


def run_job(argv: list[str], log_path: str | Path, timeout_s: float, cwd: str | Path | None = None,
            env: dict[str, str] | None = None, on_line: Callable[[str], None] | None = None) -> JobResult:
    """Run ``argv`` to its end or its timeout, its output streamed into ``log_path`` (and ``on_line``)."""
    if timeout_s <= 0:
        raise ValidationError(f"timeout_s must be positive; got {timeout_s}")
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    tail: list[str] = []
    try:
        proc = subprocess.Popen(argv, cwd=cwd, env=None if env is None else {**os.environ, **env},
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                text=True, errors="replace", bufsize=1, start_new_session=True)
    except OSError as e:
        log_path.write_text(f"could not start {argv[0]}: {e}\n")
        return JobResult(list(argv), 127, False, 0.0, str(log_path), [str(e)])

    def pump(log) -> None:
        for line in proc.stdout:
            log.write(line)
            log.flush()
            tail.append(line.rstrip("\n"))
            del tail[:-TAIL_LINES]
            if on_line is not None:
                on_line(line.rstrip("\n"))

    with open(log_path, "w", encoding="utf-8") as log:
        reader = threading.Thread(target=pump, args=(log,), daemon=True)
        reader.start()
        timed_out = False
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            _stop_group(proc)
        reader.join(timeout=KILL_GRACE_S)
    return JobResult(list(argv), None if timed_out else proc.returncode, timed_out,
                     time.perf_counter() - started, str(log_path), tail)


def _stop_group(proc: subprocess.Popen) -> None:
    for sig, wait in ((signal.SIGTERM, KILL_GRACE_S), (signal.SIGKILL, KILL_GRACE_S)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


_NUMBER = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|nan)"
_SUMMARY = re.compile(rf"^\s*(mAP|mATE|mASE|mAOE|mAVE|mAAE|NDS):\s*{_NUMBER}\s*$", re.MULTILINE)
_ERRORS = ("ATE", "ASE", "AOE", "AVE", "AAE")


def parse_uniad_output(text: str) -> dict:
    """Metrics from what a UniAD evaluation prints (the last report when there are several): ``detection`` (mAP,
    NDS, mean errors, per class AP and errors) and ``planning`` (per step at 0.5 s, per row: L2, obj_col,
    obj_box_col; ``convention`` when the table's title names it). Parts not printed are absent."""
    out: dict = {}
    summary = {name: float(value) for name, value in _SUMMARY.findall(text)}
    if summary:
        det = dict(summary)
        classes = {}
        header = text.rfind("Object Class")
        if header >= 0:
            for line in text[header:].splitlines()[1:]:
                parts = line.split()
                if len(parts) != 7:
                    break
                try:
                    values = [float(p) for p in parts[1:]]
                except ValueError:
                    break
                classes[parts[0]] = {"AP": values[0], **dict(zip(_ERRORS, values[1:]))}
        if classes:
            det["classes"] = classes
        out["detection"] = det
    table = _last_planning_table(text)
    if table is not None:
        out["planning"] = table
    return out


def _last_planning_table(text: str) -> dict | None:
    lines = text.splitlines()
    heads = [i for i, line in enumerate(lines) if re.match(r"^\|\s*metrics\s*\|", line)]
    if not heads:
        return None
    start = heads[-1]
    steps = [c.strip() for c in lines[start].strip().strip("|").split("|")][1:]
    title = next((lines[j] for j in range(start - 1, max(start - 4, -1), -1) if "definition" in lines[j]), "")
    convention = next((c for c in ("stp3", "uniad") if c in title), None)
    rows = {}
    for line in lines[start + 1:]:
        if line.startswith("+"):
            continue
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        try:
            rows[cells[0]] = [float(c.rstrip("%")) for c in cells[1:]]
        except ValueError:
            continue
    return {"steps": steps, "convention": convention, "per_step": rows} if rows else None
