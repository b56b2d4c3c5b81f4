"""The project at another git revision, beside the current code: a benchmark measures both in the same run, in
turns, and reports ratios (``--baseline REF``), so a speed-up is measured on one machine under one load."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import omniscs
from omniscs.errors import OmniscsError
from omniscs.storage import atomic_directory

#: The package folder of the code that is running (its parent goes on PYTHONPATH for the current side).
CURRENT_PACKAGE = Path(omniscs.__file__).resolve().parent


def repository_root() -> Path:
    """The git work tree the running package belongs to (a baseline is a revision of it)."""
    try:
        out = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=CURRENT_PACKAGE, capture_output=True,
                             text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        raise OmniscsError(f"--baseline needs the project as a git checkout; {CURRENT_PACKAGE} is not in one") \
            from None
    return Path(out.stdout.strip())


def resolve_commit(ref: str) -> str:
    """The full commit hash of ``ref`` (a branch, tag, hash or expression such as HEAD~3)."""
    try:
        out = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}"],
                             cwd=repository_root(), capture_output=True, text=True, check=True)
    except subprocess.CalledProcessError:
        raise OmniscsError(f"--baseline {ref!r} is not a commit of {repository_root()}; name a branch, tag or "
                           "hash (git log shows them)") from None
    return out.stdout.strip()


def baseline_tree(ref: str, cache_root: Path) -> tuple[str, Path]:
    """(commit, folder holding that commit's ``omniscs`` package), extracted once under ``cache_root`` and reused.

    Only the package is extracted: the benchmarks' probes import it and nothing else of the project. Its Numba
    kernels compile on first use and cache beside it, like the current code's."""
    commit = resolve_commit(ref)
    dest = Path(cache_root) / "baseline" / commit
    if (dest / "omniscs" / "__init__.py").is_file():
        return commit, dest
    try:
        archive = subprocess.run(["git", "archive", "--format=tar", commit, "omniscs"], cwd=repository_root(),
                                 capture_output=True, check=True)
        with atomic_directory(dest) as staging:
            subprocess.run(["tar", "-x", "-C", str(staging)], input=archive.stdout, check=True)
    except subprocess.CalledProcessError as e:
        raise OmniscsError(f"could not extract {commit[:12]}'s omniscs package: "
                           f"{(e.stderr or b'').decode(errors='replace').strip()[:200]}") from None
    return commit, dest


def run_probe(package_parent: Path, script: str, args: list[str], timeout_s: float = 1800.0) -> dict[str, Any]:
    """Run ``script`` (Python source that prints one JSON object on its last line) in a fresh interpreter that
    imports ``omniscs`` from ``package_parent``. The working folder is a neutral one, so that neither side picks
    up the other's package from the current folder."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(package_parent), os.environ.get("PYTHONPATH", "")]))
    with tempfile.TemporaryDirectory(prefix="omniscs-probe-") as cwd:
        try:
            done = subprocess.run([sys.executable, "-c", script, *args], cwd=cwd, env=env, capture_output=True,
                                  text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise OmniscsError(f"a benchmark probe of {package_parent} ran past {timeout_s:.0f} s") from None
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        raise OmniscsError(f"a benchmark probe of {package_parent} failed: {last[-300:]}")
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    return json.loads(lines[-1])
