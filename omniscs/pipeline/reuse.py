"""The one reuse contract: a stage's output folder holds ``stage.json`` with the key it was made from (content
hash of the stage's name and version, its inputs and its config); a folder whose key matches is reused as is."""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from omniscs.errors import OmniscsError
from omniscs.storage import atomic_directory, atomic_write_json, content_hash
from omniscs.untrusted import read_own_json

#: The file in every stage output folder that says what it was made from; written last.
STAGE_MANIFEST = "stage.json"


@dataclass(frozen=True)
class StageKey:
    """What decides a stage's output: same key, same output."""

    stage: str
    """The stage's name (``fit``, ``behavior``, ...)."""
    version: int
    """The stage's version: bumped when its code changes what it writes."""
    digest: str
    """sha256 over stage, version, inputs and config."""

    @classmethod
    def of(cls, stage: str, version: int, inputs, config) -> "StageKey":
        """``inputs`` and ``config``: JSON-able values or numpy arrays (see ``storage.content_hash``). Leave
        out what does not change the result (the compute device, thread counts, progress callbacks)."""
        return cls(stage, int(version), content_hash(stage, int(version), inputs, config))

    @property
    def short(self) -> str:
        """The first 12 hex digits: enough to name a folder."""
        return self.digest[:12]


def reusable(out_dir: str | Path, key: StageKey) -> dict | None:
    """The stage manifest of ``out_dir`` when it was made from ``key`` (None when absent, damaged or another
    key): the caller may reuse the folder as is."""
    path = Path(out_dir) / STAGE_MANIFEST
    try:  # a damaged or replaced manifest (any of the reader's refusals) only means: not reusable
        manifest = read_own_json(path, "not reusable")
    except OmniscsError:
        return None
    if not isinstance(manifest, dict) or manifest.get("key") != key.digest or manifest.get("stage") != key.stage:
        return None
    return manifest


def mark_done(out_dir: str | Path, key: StageKey, outputs: dict, seconds: float) -> dict:
    """Write the stage manifest into a finished ``out_dir`` (for stages whose writer is atomic on its own,
    e.g. a scene store or a checkpoint). A crash before this leaves a folder that is not reused."""
    manifest = {"stage": key.stage, "version": key.version, "key": key.digest, "outputs": outputs,
                "seconds": float(seconds), "finished_at_us": int(time.time() * 1e6)}
    atomic_write_json(Path(out_dir) / STAGE_MANIFEST, manifest)
    return manifest


def produce(out_dir: str | Path, key: StageKey, make: Callable[[Path], dict]) -> dict:
    """Run ``make(tmp_dir) -> outputs`` into a temporary sibling of ``out_dir`` that replaces ``out_dir`` only
    when it finished, manifest included; on any error nothing of it is left."""
    started = time.perf_counter()
    with atomic_directory(out_dir, overwrite=True) as tmp:
        outputs = make(tmp)
        mark_done(tmp, key, outputs, time.perf_counter() - started)
    return reusable(out_dir, key) or {}
