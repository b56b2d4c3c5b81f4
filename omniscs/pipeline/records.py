"""What each stage hands to the next (``StageRecord``) and a run's id: small, JSON-able values (ids, paths,
catalog rows), never tensors, so Prefect can pass them between tasks."""
from __future__ import annotations

import uuid
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone


def new_run_id() -> str:
    """A fresh run id: UTC time stamp and 6 random hex digits (sortable, unique, a safe id)."""
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ") + "-" + uuid.uuid4().hex[:6]


@dataclass(frozen=True)
class StageRecord:
    """What one stage did for one scene: where its output is, whether it was reused or skipped, how long it
    took, and the catalog rows it produced (table name -> rows) for the scene's catalog stage to write."""

    stage: str
    """Stage name: ingest, plan, preview, fit, behavior, ..."""
    scene_id: str
    """The scene the stage worked on."""
    path: str | None = None
    """Its output folder or file (None when it wrote nothing)."""
    reused: bool = False
    """An output made from the same inputs, config and stage version was already there."""
    skipped: bool = False
    """The scene's plan does not need this stage: it did nothing."""
    seconds: float = 0.0
    """Wall time of this call (near 0 when reused or skipped)."""
    key: str | None = None
    """The stage key (content hash) the output was made from."""
    rows: dict[str, list[dict]] = field(default_factory=dict)
    """Catalog rows by table."""
    info: dict = field(default_factory=dict)
    """Small facts for the caller (status, counts, ids)."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "StageRecord":
        return cls(**d)

    @classmethod
    def skip(cls, stage: str, scene_id: str, why: str) -> "StageRecord":
        return cls(stage, scene_id, skipped=True, info={"why": why})
