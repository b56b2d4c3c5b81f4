"""What a run asks of each scene (``SceneRequest``) and what each stage hands to the next (``StageRecord``):
small, JSON-able values (ids, paths, catalog rows), never tensors, so Prefect can pass them between tasks."""
from __future__ import annotations

import uuid
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone

from omniscs.errors import OmniscsError

def new_run_id() -> str:
    """A fresh run id: UTC time stamp and 6 random hex digits (sortable, unique, a safe id)."""
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ") + "-" + uuid.uuid4().hex[:6]


#: Named quality presets of the scene-graph fit and the behaviour optimisation.
PRESET_NAMES = ("fast", "balanced", "accurate")


@dataclass(frozen=True)
class SceneRequest:
    """The variants and quality a run asks for; the same for every scene of the run. The plan stage turns it
    into what each scene needs modelled."""

    fit_preset: str | None = None
    """Scene-graph preset (fast, balanced, accurate); None: no scene graph is fitted."""
    behavior_variants: int = 0
    """Behaviour-level SCS variants per scene (0: none). With a scene graph, L_app is rendered by it."""
    behavior_preset: str = "balanced"
    """Adversarial-optimisation preset (fast, balanced, accurate)."""
    behavior_checkpoint: str | None = None
    """Traffic-model checkpoint folder; None: the shipped one."""
    edits: tuple[dict, ...] = ()
    """Edits the variants will apply (JSON dicts, see README); their tracks become nodes in the plan."""
    previews: bool = True
    """Contact sheet and BEV picture of every scene."""
    device: str = "cpu"
    """Compute device of the scene graph and the behaviour optimisation ("cpu" or "cuda")."""
    annotate: bool = False
    """Render and annotate every variant through the scene graph (a dataset's frames and ground truth); needs
    ``fit_preset`` and ``behavior_variants`` > 0."""
    pool: str | None = None
    """Model pool folder for the agents stage (360-degree models of tracks the edits turn); None: such tracks
    get their online model (the fitted node, mirrored) only. Appearance variants take their objects from it."""
    appearance_variants: int = 0
    """Appearance-level SCS variants per scene (0: none): pool objects replacing a vehicle's model or inserted at
    valid poses (upright, on its side, overturned); needs ``fit_preset`` and ``pool``."""
    appearance_objects: tuple[str, ...] = ()
    """Pool model ids the appearance variants composite (e.g. what ``omniscs scs mine`` found missed); empty: every
    model of the pool."""

    def __post_init__(self) -> None:
        if self.fit_preset is not None and self.fit_preset not in PRESET_NAMES:
            raise OmniscsError(f"unknown fit preset {self.fit_preset!r}; use one of {list(PRESET_NAMES)} or none")
        n = self.behavior_variants
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise OmniscsError(f"behavior_variants must be a non-negative integer; got {n!r}")
        if self.behavior_preset not in PRESET_NAMES:
            raise OmniscsError(f"unknown behavior preset {self.behavior_preset!r}; use one of {list(PRESET_NAMES)}")
        if not isinstance(self.annotate, bool):
            raise OmniscsError(f"annotate must be true or false; got {self.annotate!r}")
        n = self.appearance_variants
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise OmniscsError(f"appearance_variants must be a non-negative integer; got {n!r}")
        if n and (self.fit_preset is None or self.pool is None):
            raise OmniscsError("appearance variants composite pool objects into a scene graph: give a fit preset "
                               "and a model pool")
        if isinstance(self.appearance_objects, (str, bytes)) or \
                not all(isinstance(m, str) and m for m in self.appearance_objects):
            raise OmniscsError(f"appearance_objects must be a list of pool model ids; got {self.appearance_objects!r}")
        object.__setattr__(self, "appearance_objects", tuple(self.appearance_objects))
        if self.annotate and (self.fit_preset is None or self.behavior_variants + self.appearance_variants < 1):
            raise OmniscsError("a dataset renders variants through a scene graph: give a fit preset and "
                               "behavior_variants >= 1 or appearance_variants >= 1")
        if self.device not in ("cpu", "cuda") and not str(self.device).startswith("cuda:"):
            raise OmniscsError(f"unknown device {self.device!r}; use cpu or cuda")
        if isinstance(self.edits, (str, bytes, dict)) or not all(isinstance(e, dict) for e in self.edits):
            raise OmniscsError(f"edits must be a list of edit objects (JSON dicts, see README); got {self.edits!r}")
        if self.pool is not None and not isinstance(self.pool, str):
            object.__setattr__(self, "pool", str(self.pool))
        if self.behavior_checkpoint is not None and not isinstance(self.behavior_checkpoint, str):
            object.__setattr__(self, "behavior_checkpoint", str(self.behavior_checkpoint))
        object.__setattr__(self, "edits", tuple(dict(e) for e in self.edits))

    def parsed_edits(self) -> list:
        """The edits as the project's edit types (a malformed one is an OmniscsError)."""
        from omniscs.edits import edit_from_dict

        return [edit_from_dict(e) for e in self.edits]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["edits"] = [dict(e) for e in self.edits]
        d["appearance_objects"] = list(self.appearance_objects)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SceneRequest":
        d = dict(d)
        d["edits"] = tuple(d.get("edits") or ())
        d["appearance_objects"] = tuple(d.get("appearance_objects") or ())
        return cls(**d)


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
