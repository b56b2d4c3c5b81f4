"""Crash safety and concurrency: per-output locks, temporaries of dead writers, overwrite only of what omniscs
wrote, the same source given twice (SIGTERM and SIGKILL of `omniscs generate` and concurrent runs: the reliability
benchmark's checks, tests/bench/test_reliability_bench.py)."""
from __future__ import annotations

import os
import subprocess
import threading
import time
from pathlib import Path

import pytest

from omniscs.errors import OmniscsError
from omniscs.locks import clean_stale_temps, holder, lock_path, output_lock
from omniscs.storage import OWNER_MARKER, atomic_directory, is_owned


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


# ----------------------------------------------------------------------------- locks
def test_a_second_writer_waits_for_the_first_and_sees_its_output(tmp_path):
    out = tmp_path / "out"
    order, told = [], []

    def first():
        with output_lock(out):
            order.append("first in")
            time.sleep(0.5)
            out.mkdir()
            order.append("first out")

    t = threading.Thread(target=first)
    t.start()
    time.sleep(0.1)
    with output_lock(out, waiting=told.append):
        order.append("second in")
        assert out.is_dir()  # made by the first writer while the second waited
    t.join()
    assert order == ["first in", "first out", "second in"]
    assert len(told) == 1 and f"pid {os.getpid()}" in told[0]
    assert not lock_path(out).exists()  # the holder removes its lock file


def test_a_lock_file_left_by_a_killed_writer_does_not_block_and_is_swept(tmp_path):
    out = tmp_path / "out"
    lock_path(out).write_text(f"pid {_dead_pid()} on somewhere\n")  # a writer died holding it: flock released
    with output_lock(out):
        assert "pid" in holder(out)
    lock_path(out).write_text("pid 1\n")
    assert clean_stale_temps(tmp_path) == [lock_path(out)] and not lock_path(out).exists()


# ----------------------------------------------------------------------------- temporaries
def test_temporaries_of_dead_writers_are_removed_and_live_ones_kept(tmp_path):
    dead = tmp_path / "scenes" / f".s1.tmp-{_dead_pid()}-0123456789ab"
    live = tmp_path / "scenes" / f".s2.tmp-{os.getpid()}-0123456789ab"
    dead_file = tmp_path / "catalog" / "runs" / "run_id=r" / f".x.parquet.tmp-{_dead_pid()}-ba9876543210"
    for p in (dead, live):
        (p / "images").mkdir(parents=True)
    dead_file.parent.mkdir(parents=True)
    dead_file.write_bytes(b"half")
    user_file = tmp_path / "scenes" / ".s3.tmp-notes"  # not ours: no pid, no hex tag
    user_file.write_text("keep")
    removed = clean_stale_temps(tmp_path)
    assert sorted(removed) == sorted([dead, dead_file])
    assert live.exists() and user_file.exists() and not dead.exists()
    assert clean_stale_temps(tmp_path, include_own=True) == [live]


def test_a_failed_atomic_directory_leaves_nothing_not_even_its_parents(tmp_path):
    final = tmp_path / "a" / "b" / "out"
    with pytest.raises(RuntimeError):
        with atomic_directory(final) as tmp:
            (tmp / "x").write_text("half")
            raise RuntimeError("writer failed")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- overwrite
def test_overwrite_replaces_only_folders_omniscs_wrote(tmp_path):
    ours = tmp_path / "ours"
    with atomic_directory(ours) as tmp:
        (tmp / "a").write_text("1")
    assert (ours / OWNER_MARKER).is_file() and is_owned(ours)
    with atomic_directory(ours, overwrite=True) as tmp:
        (tmp / "b").write_text("2")
    assert sorted(p.name for p in ours.iterdir()) == [OWNER_MARKER, "b"]

    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "thesis.tex").write_text("years of work")
    with pytest.raises(OmniscsError, match="refusing to overwrite .*did not write"):
        with atomic_directory(theirs, overwrite=True):
            pass
    assert (theirs / "thesis.tex").read_text() == "years of work"
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(OmniscsError, match="it is a file"):
        with atomic_directory(a_file, overwrite=True):
            pass
    assert a_file.read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["file", "ours", "theirs"]


# ----------------------------------------------------------------------------- the same scene twice at once
def test_the_same_new_source_ingested_twice_at_once_is_rendered_once(tmp_path):
    from omniscs.pipeline.stages import ingest_stage

    from omniscs.scene import SyntheticSource

    source = SyntheticSource("straight", 44, n_frames=3, n_cameras=1, width=32, height=18).to_dict()
    results, errors = [], []

    def ingest():
        try:
            results.append(ingest_stage(source, tmp_path))
        except Exception as exc:  # pragma: no cover - the failure this test guards against
            errors.append(exc)

    threads = [threading.Thread(target=ingest) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert sorted(r.reused for r in results) == [False, True]
    assert results[0].path == results[1].path
    assert [p.name for p in (tmp_path / "scenes").iterdir()] == [Path(results[0].path).name]
