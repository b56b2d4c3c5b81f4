"""Per-output locks, so two writers (two runs, or one source given twice) never produce the same folder at once.

A lock is the hidden file ``.<name>.lock`` beside the output, held with ``flock``: the kernel releases it when its
holder dies, however it dies (SIGKILL included), so a lock can never outlive its writer — that is how stale locks
are detected. The file names the holder (pid, host, start time) for the message a waiting writer prints, and the
holder removes it when done. Locks are for one machine's file system (local disks; not NFS).

``clean_stale_temps`` removes what dead writers left behind: their temporary siblings (``omniscs.storage``) and
their lock files.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import socket
import time
from pathlib import Path
from typing import Callable, Iterator

from omniscs.storage import make_parents, pid_alive, remove_empty, temp_owner

#: How often a waiting writer retries (seconds).
POLL_SECONDS = 0.2


def lock_path(target: str | os.PathLike) -> Path:
    target = Path(target)
    return target.parent / f".{target.name}.lock"


def holder(target: str | os.PathLike) -> str:
    """Who holds ``target``'s lock, as its lock file says ('' when nobody or unknown)."""
    try:
        return lock_path(target).read_text().strip()
    except OSError:
        return ""


@contextlib.contextmanager
def output_lock(target: str | os.PathLike, waiting: Callable[[str], None] | None = None) -> Iterator[None]:
    """Hold ``target``'s lock for the block; wait (calling ``waiting(holder)`` once) while another writer has
    it. Inside the block, check again whether the output is already there: the other writer may have made it."""
    path = lock_path(target)
    created: list[Path] = []
    told = False
    while True:
        created += make_parents(path)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except FileNotFoundError:  # another writer removed the empty parent folder just now: make it again
            continue
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if not told and waiting is not None:
                        waiting(holder(target))
                        told = True
                    time.sleep(POLL_SECONDS)
            # the previous holder may have removed the file between our open and our lock: lock the live one
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()} since {time.strftime('%H:%M:%S')}\n".encode())
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        os.close(fd)
        remove_empty(created)  # a folder made only for the lock (the output failed) is not left behind


def holder_pid(lock_file: str | os.PathLike) -> int | None:
    """The pid a lock file names (None when it names none)."""
    try:
        words = Path(lock_file).read_text().split()
    except OSError:
        return None
    return int(words[1]) if len(words) > 1 and words[0] == "pid" and words[1].isdigit() else None


def remove_if_stale(path: str | os.PathLike) -> bool:
    """Remove a lock file nobody holds (its holder died before removing it); True when removed."""
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError:
        return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        try:
            if os.stat(path).st_ino != os.fstat(fd).st_ino:
                return False
        except FileNotFoundError:
            return False
        os.unlink(path)
        return True
    finally:
        os.close(fd)


def clean_stale_temps(root: str | os.PathLike, max_depth: int = 4, include_own: bool = False) -> list[Path]:
    """Remove the temporary files and folders (and stale lock files) under ``root``, down to ``max_depth``
    levels, whose writer is no longer running (``include_own``: this process's too, when it is being stopped).
    Returns what was removed."""
    root = Path(root)
    removed: list[Path] = []
    if not root.is_dir():
        return removed
    own = os.getpid()
    for dirpath, dirnames, filenames in os.walk(root):
        depth = len(Path(dirpath).relative_to(root).parts)
        for name in list(dirnames) + filenames:
            path = Path(dirpath) / name
            pid = temp_owner(path)
            if pid is not None and (not pid_alive(pid) or (include_own and pid == own)):
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)
                removed.append(path)
            elif pid is None and name.endswith(".lock") and name.startswith("."):
                if remove_if_stale(path) or (include_own and holder_pid(path) == own and _unlink(path)):
                    removed.append(path)
        dirnames[:] = [d for d in dirnames if temp_owner(d) is None and depth + 1 < max_depth
                       and (Path(dirpath) / d).exists() and not (Path(dirpath) / d).is_symlink()]
    return removed


def _unlink(path: Path) -> bool:
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    return True
