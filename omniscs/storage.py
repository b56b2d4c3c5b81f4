"""Workspace root, atomic writes and content hashes: how artifacts reach disk whole or not at all."""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import uuid
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np

from omniscs.errors import OmniscsError

#: Environment variable naming the workspace root; default ``./omniscs-data``.
HOME_ENV = "OMNISCS_HOME"
DEFAULT_HOME = "omniscs-data"


#: Characters a name needs beyond its own for the temporary sibling written beside it
#: (``.<name>.tmp-<pid>-<12 hex>``; pids have at most 7 digits on Linux).
TEMP_NAME_ROOM = 27


def check_link(path: Path, what: str) -> None:
    """Refuse ``path`` when it, or a folder above it, is a symbolic link to nothing: writing through it would
    create its target somewhere the user did not name."""
    for candidate in (path, *path.parents):
        if candidate.is_symlink() and not candidate.exists():
            target = os.readlink(candidate)
            where = "is" if candidate == path else f"lies under {candidate}, which is"
            raise OmniscsError(f"{what} {path} {where} a symbolic link to {target}, which does not exist; create "
                               "the target or give a real path")


def check_names(path: Path, what: str) -> None:
    """Refuse names the file system cannot hold (with room for a temporary sibling's) and paths past its limit,
    before any work."""
    anchor = Path(path.anchor or "/")  # the deepest existing folder, found from the top: a name too long for
    for part in path.parts[1:]:          # the file system makes every call on the path below it fail
        try:
            if not (anchor / part).is_dir():
                break
        except OSError:
            break
        anchor = anchor / part
    try:
        name_max = os.pathconf(anchor, "PC_NAME_MAX")
        path_max = os.pathconf(anchor, "PC_PATH_MAX")
    except (OSError, ValueError):
        name_max, path_max = 255, 4096
    for part in path.parts[1:]:
        if len(os.fsencode(part)) + TEMP_NAME_ROOM > name_max:
            raise OmniscsError(f"{what} {path}: the name {part[:40]}... is {len(os.fsencode(part))} bytes; names "
                               f"here hold at most {name_max - TEMP_NAME_ROOM} (with room for a temporary's)")
    if len(os.fsencode(str(path))) + TEMP_NAME_ROOM >= path_max:
        raise OmniscsError(f"{what} {str(path)[:60]}... is {len(os.fsencode(str(path)))} bytes long; paths here "
                           f"hold at most {path_max - TEMP_NAME_ROOM - 1}")


def check_writable(path: Path, what: str, inside: bool = False) -> None:
    """Refuse ``path`` when the nearest existing folder above it (with ``inside``: it, when it exists: a folder
    that is added to) cannot take a new file: read-only, not permitted, or a virtual file system such as /proc. A
    probe file is made there and removed (the only test that holds for root and on every file system); an output
    that will replace ``path`` never has its own folder touched."""
    anchor = next((p for p in ((path,) if inside else ()) + tuple(path.parents) if p.exists()), None)
    if anchor is None:
        return
    if not anchor.is_dir():
        raise OmniscsError(f"{what} {path} lies under {anchor}, which is a file, not a folder")
    probe = anchor / f".omniscs-probe-{os.getpid()}-{uuid.uuid4().hex[:12]}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise OmniscsError(f"{what} {path}: cannot write in {anchor} ({exc.strerror or exc}); choose a folder you "
                           "can write") from None
    os.close(fd)
    probe.unlink(missing_ok=True)


def check_output(path: str | os.PathLike, what: str = "--out", follow: bool = False) -> Path:
    """The path policy for outputs, applied before any work: ``path`` (made absolute) must not be a symbolic link
    (a dangling one would send the output elsewhere, a live one would be replaced as a whole; give the link's
    target instead) nor lie under a dangling one; its names must fit the file system; the nearest existing folder
    above it (or it, when it is one) must be writable. ``follow``: an output folder that is added to (scene
    stores, a pool) may be a link to an existing folder, and is returned resolved."""
    path = Path(path).expanduser().absolute()
    check_names(path, what)
    if path.is_symlink() and not (follow and path.is_dir()):
        raise OmniscsError(f"{what} {path} is a symbolic link (to {os.readlink(path)}); give the real path")
    check_link(path, what)
    path = path.resolve() if follow else path
    check_writable(path, what, inside=follow)
    return path


def workspace_path(root: str | os.PathLike | None = None) -> Path:
    """The workspace root's absolute path (``root`` if given, else $OMNISCS_HOME, else ./omniscs-data), not
    created. A workspace may be a symbolic link to a folder (followed: the workspace is its target); one that
    points nowhere is refused rather than created elsewhere."""
    given = Path(root or os.environ.get(HOME_ENV) or DEFAULT_HOME).expanduser().absolute()
    check_names(given, "workspace")
    check_link(given, "workspace")
    return given.resolve()


def inside(path: str | os.PathLike, root: str | os.PathLike, what: str) -> Path:
    """``path`` resolved, refused unless it stays under ``root`` (resolved): a folder of the workspace (catalog
    table, pool models) that is a symbolic link out of it would let a reader read, or a writer write, elsewhere."""
    resolved, top = Path(path).resolve(), Path(root).resolve()
    if resolved != top and top not in resolved.parents:
        raise OmniscsError(f"{what} {path} leads out of {root} (to {resolved}): a symbolic link; the project "
                           "follows links only inside its folders")
    return resolved


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


def usable_workspace(root: str | os.PathLike | None = None) -> Path:
    """The workspace root a command will write into, checked but not created (stages create what they write,
    so a command refused later leaves no empty workspace behind): an error when it, or a folder above it, is a
    file."""
    path = workspace_path(root)
    for candidate in (path, *path.parents):
        if candidate.exists():
            if not candidate.is_dir():
                where = "is a file" if candidate == path else f"lies under {candidate}, which is a file"
                raise OmniscsError(f"workspace {path} {where}; choose another --workspace")
            break
    check_names(path, "workspace")
    check_writable(path, "workspace", inside=True)
    return path


def existing_workspace(root: str | os.PathLike | None = None) -> Path:
    """The workspace root for commands that only read it: an error when it does not exist (nothing is
    created)."""
    path = workspace_path(root)
    if not path.is_dir():
        raise OmniscsError(f"no workspace at {path}; run `omniscs generate` first or pass --workspace "
                           f"(or set ${HOME_ENV})")
    return path


#: File in every folder ``atomic_directory`` makes: proof that omniscs wrote it, so ``overwrite`` may replace it.
OWNER_MARKER = ".omniscs"
#: Files whose presence also proves a folder is the project's (the pipeline's stage manifest, in outputs
#: written before the marker existed).
OWNED_IF_HOLDS = (OWNER_MARKER, "stage.json")

# Temporary siblings are named ``.<name>.tmp-<pid>-<12 hex>``: the pid says whose they are, so the temporaries of
# a writer that died (killed, crashed machine) can be told from those of a live one and removed.
_TEMP_NAME = re.compile(r"^\..+\.tmp-(\d+)-[0-9a-f]{12}$")


def _temp_sibling(path: Path) -> Path:
    return path.parent / f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:12]}"


def temp_sibling(path: str | os.PathLike) -> Path:
    """A fresh name for a temporary of this process beside ``path`` (``clean_stale_temps`` removes it once this
    process is gone)."""
    return _temp_sibling(Path(path))


def temp_siblings(path: str | os.PathLike) -> list[Path]:
    """The temporaries beside ``path`` that are named after it, whoever wrote them."""
    path = Path(path)
    return [p for p in path.parent.glob(f".{glob_escape(path.name)}.tmp-*") if temp_owner(p) is not None]


def temp_owner(path: str | os.PathLike) -> int | None:
    """The pid of the writer a temporary file or folder belongs to (None: not a temporary)."""
    m = _TEMP_NAME.match(Path(path).name)
    return int(m.group(1)) if m else None


def pid_alive(pid: int) -> bool:
    """Whether a process with this pid runs on this machine (a pid of another user's process counts)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def is_owned(folder: str | os.PathLike) -> bool:
    """True when ``folder`` was written by omniscs (it holds the owner marker or a stage manifest) or is empty:
    the only folders ``overwrite`` may replace."""
    folder = Path(folder)
    if not folder.is_dir():
        return False
    return any((folder / name).is_file() for name in OWNED_IF_HOLDS) or not any(folder.iterdir())


def check_replaceable(path: str | os.PathLike) -> None:
    """Refuse to replace ``path`` unless it is a folder omniscs wrote (see ``is_owned``)."""
    path = Path(path)
    if path.exists() and not is_owned(path):
        what = "a file" if not path.is_dir() else "a folder omniscs did not write (no .omniscs marker)"
        raise OmniscsError(f"refusing to overwrite {path}: it is {what}; move it away or choose another --out")


def make_parents(path: Path) -> list[Path]:
    """Create ``path``'s missing parent folders; returns those created (outermost first)."""
    missing = []
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise OmniscsError(f"cannot write {path}: {parent} is a file, not a folder")
            break
        missing.append(parent)
    for parent in reversed(missing):
        try:
            parent.mkdir()
        except FileExistsError:
            pass
        except OSError as exc:
            raise OmniscsError(f"cannot create {parent}: {exc.strerror or exc}") from None
    return list(reversed(missing))


def remove_empty(folders: list[Path]) -> None:
    for folder in reversed(folders):  # innermost first
        try:
            folder.rmdir()
        except OSError:
            break


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to a temporary sibling, fsync, then rename over ``path``."""
    path = Path(path)
    make_parents(path)
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

    On any exception the temporary directory (and any parent folder made for it) is deleted and ``final`` is
    left as it was. ``overwrite`` replaces an existing ``final`` only when omniscs wrote it (``is_owned``); the
    new folder holds the owner marker. Temporary siblings of ``final`` left by dead writers are removed first.
    """
    final = Path(final)
    if final.is_symlink():
        raise OmniscsError(f"{final} is a symbolic link (to {os.readlink(final)}); give the real path")
    if final.exists() and not overwrite:
        raise OmniscsError(f"{final} already exists; choose another --out or pass --overwrite")
    if overwrite:
        check_replaceable(final)
    created = make_parents(final)
    for stale in final.parent.glob(f".{glob_escape(final.name)}.tmp-*"):
        pid = temp_owner(stale)
        if pid is not None and not pid_alive(pid):
            shutil.rmtree(stale, ignore_errors=True) if stale.is_dir() else stale.unlink(missing_ok=True)
    tmp = _temp_sibling(final)
    tmp.mkdir()
    finished = False
    try:
        (tmp / OWNER_MARKER).write_text("written by omniscs\n")
        yield tmp
        if final.exists():
            if not overwrite:
                raise OmniscsError(f"{final} already exists; choose another --out or pass --overwrite")
            check_replaceable(final)
            trash = _temp_sibling(final)
            os.replace(final, trash)
            os.replace(tmp, final)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, final)
        finished = True
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if not finished:
            remove_empty(created)


def glob_escape(name: str) -> str:
    """``name`` with glob's special characters made literal."""
    return "".join(f"[{c}]" if c in "*?[" else c for c in name)


def file_sha256(path: str | os.PathLike) -> str:
    """sha256 of a file's bytes (hex), read in chunks."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


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
