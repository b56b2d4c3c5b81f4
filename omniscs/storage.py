"""Workspace root, atomic writes and content hashes: how artifacts reach disk whole or not at all."""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import uuid
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np

from omniscs.errors import OmniscsError

#: Environment variable naming the workspace root; default ``./omniscs-data``.
HOME_ENV = "OMNISCS_HOME"
DEFAULT_HOME = "omniscs-data"


def workspace_path(root: str | os.PathLike | None = None) -> Path:
    """The workspace root's absolute path (``root`` if given, else $OMNISCS_HOME, else ./omniscs-data), not
    created."""
    return Path(root or os.environ.get(HOME_ENV) or DEFAULT_HOME).expanduser().resolve()


def workspace_root(root: str | os.PathLike | None = None) -> Path:
    """The workspace root (see ``workspace_path``), created when missing: for commands that write into it."""
    path = workspace_path(root)
    if path.exists() and not path.is_dir():
        raise OmniscsError(f"workspace {path} is a file, not a folder; choose another --workspace")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OmniscsError(f"cannot create workspace {path}: {exc.strerror or exc}") from None
    return path


def existing_workspace(root: str | os.PathLike | None = None) -> Path:
    """The workspace root for commands that only read it: an error when it does not exist (nothing is
    created)."""
    path = workspace_path(root)
    if not path.is_dir():
        raise OmniscsError(f"no workspace at {path}; run `omniscs generate` first or pass --workspace "
                           f"(or set ${HOME_ENV})")
    return path


def _temp_sibling(path: Path) -> Path:
    return path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:12]}"


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to a temporary sibling, fsync, then rename over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_sibling(path)
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_write_with(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> Path:
    """Let ``write`` serialise into a buffer (e.g. ``fig.savefig(buf, format="png")``), then write it atomically."""
    buf = io.BytesIO()
    write(buf)
    return atomic_write_bytes(path, buf.getvalue())


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


@contextlib.contextmanager
def atomic_directory(final: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary directory that becomes ``final`` only if the block finishes without error.

    On any exception the temporary directory is deleted and ``final`` is left as it was.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_sibling(final)
    tmp.mkdir()
    try:
        yield tmp
        if final.exists():
            if not overwrite:
                raise FileExistsError(f"{final} already exists")
            trash = _temp_sibling(final)
            os.replace(final, trash)
            os.replace(tmp, final)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def content_hash(*parts) -> str:
    """Stable sha256 over JSON-able values and numpy arrays (dtype, shape and bytes)."""
    h = hashlib.sha256()
    for part in parts:
        _feed(h, part)
    return h.hexdigest()


def _feed(h, x) -> None:
    if isinstance(x, np.ndarray):
        arr = np.ascontiguousarray(x)
        h.update(f"nd:{arr.dtype.str}:{arr.shape}".encode())
        h.update(arr.tobytes())
    elif isinstance(x, (list, tuple)):
        h.update(f"seq:{len(x)}".encode())
        for v in x:
            _feed(h, v)
    elif isinstance(x, dict):
        h.update(f"map:{len(x)}".encode())
        for k in sorted(x):
            h.update(str(k).encode())
            _feed(h, x[k])
    else:
        h.update(json.dumps(x, sort_keys=True, default=str).encode())
