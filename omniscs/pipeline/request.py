"""What a run asks for, defined once: ``SceneRequest`` (the variants and quality asked of every scene) and
``RunRequest`` (the sources, the synthetic rig and where and how the run executes, plus every scene field).

These are the ``generate_dataset`` flow's one parameter (Prefect shows it as a form and records it), the fields the
``omniscs generate`` options are made from (help text from the field docstrings), and what deployments, benchmarks
and the ``runs`` catalog row build or record. Adding a setting means adding one field here.

Field values are checked for type and range when a request is made; what needs the outside world (the sources
exist, the pool and checkpoint load, the device is here) is checked once per run by ``validate.check_run``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import pydantic
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from omniscs.edits import edit_from_dict
from omniscs.errors import OmniscsError
from omniscs.gates import GateConfig
from omniscs.ids import check_id

#: Named quality presets of the scene-graph fit and the behaviour optimisation.
PRESET_NAMES = ("fast", "balanced", "accurate")
Preset = Literal["fast", "balanced", "accurate"]
#: Most variants of one kind one scene may ask for.
MAX_VARIANTS = 1000
#: Most candidates tried per requested variant.
MAX_BUDGET = 20
#: Bounds of the synthetic sensor rig (frames at 10 Hz, cameras in nuScenes placement, image side in pixels).
FRAMES = (1, 10_000)
CAMERAS = (1, 6)
IMAGE_SIDE = (8, 4096)
#: Where a run's scenes can run (flows/runners.py).
TaskRunner = Literal["threads", "dask"]
#: Most scenes at once (thread or Dask worker count) one machine is asked for.
MAX_WORKERS = 256

#: ``RunRequest`` fields that say where a run is written and how it executes, not what it makes.
EXECUTION_FIELDS = ("workspace", "run_id", "task_runner", "workers", "dask_address")

_CONFIG = ConfigDict(frozen=True, extra="forbid", strict=True, use_attribute_docstrings=True)


def _as_list(value):
    """Sequences arrive as lists (JSON, Prefect) or tuples (Python callers): both are taken."""
    return list(value) if isinstance(value, tuple) else value


def _as_text(value):
    """Paths are given as ``Path`` by Python callers and as text everywhere else."""
    return str(value) if isinstance(value, Path) else value


class SceneRequest(BaseModel):
    """The variants and quality a run asks for; the same for every scene of the run. The plan stage turns it into
    what each scene needs modelled."""

    model_config = _CONFIG

    fit_preset: Preset | None = None
    """Fit each scene's Gaussian scene graph with this preset (fast, balanced, accurate); none: no fit."""
    behavior_variants: int = Field(0, ge=0, le=MAX_VARIANTS)
    """Behaviour-level SCS variants per scene (0: none). With a scene graph, L_app is rendered by it."""
    behavior_preset: Preset = "balanced"
    """Adversarial-optimisation preset of the behaviour variants (fast, balanced, accurate)."""
    behavior_checkpoint: str | None = None
    """Traffic-model checkpoint folder of the behaviour variants; none: the shipped one."""
    edits: list[dict[str, Any]] = Field(default_factory=list)
    """Edits of a designed scenario (edit objects, see the edits guide; e.g. a spec saved in ``omniscs view``):
    their tracks become nodes in every scene's plan, and with annotate they are rendered and annotated as one
    designed variant (d000) of every scene, beside the drawn ones."""
    previews: bool = True
    """Write a contact sheet and a BEV picture of every scene."""
    device: str = "cpu"
    """Compute device of the scene graph and the behaviour optimisation: cpu, cuda or cuda:N."""
    annotate: bool = False
    """Render and annotate every variant through its scene graph and gather them as one dataset (needs a fit
    preset and behaviour or appearance variants, or edits)."""
    pool: str | None = None
    """Model pool folder: tracks the edits turn off their observed views get a 360-degree model from it (or
    online), and appearance variants take their objects from it."""
    appearance_variants: int = Field(0, ge=0, le=MAX_VARIANTS)
    """Appearance-level SCS variants per scene (0: none): pool objects replacing a vehicle's model or inserted
    upright, on the side or overturned at valid poses (needs a fit preset and a pool)."""
    appearance_objects: list[str] = Field(default_factory=list)
    """Pool model ids the appearance variants use (e.g. what ``omniscs scs mine`` found missed); empty: the whole
    pool."""
    keep_failed: bool = False
    """Put variants that fail the quality gates into the dataset too, marked (passed_gates false); by default they
    stay in the workspace and the catalog only, with their reasons."""
    variant_budget: int = Field(3, ge=1, le=MAX_BUDGET)
    """Candidates tried per requested variant (other adversaries and time windows; other objects and placements)
    until as many as requested pass the quality gates."""
    near_miss_m: float = Field(0.0, ge=0.0, le=50.0, allow_inf_nan=False)
    """Gate: a behaviour variant without contact passes when the ego's and the adversary's centres come this close
    (metres; 0: a collision is required)."""
    min_visible_frames: int = Field(3, ge=0, le=FRAMES[1])
    """Gate: frames in which an appearance variant's object must be visible (100 mask pixels in a camera, a
    quarter of it unoccluded)."""
    min_fidelity_psnr: float = Field(20.0, ge=0.0, le=100.0, allow_inf_nan=False)
    """Gate: the lowest mean PSNR (dB) a variant's render may have against the exact render (procedural scenes;
    recorded logs are judged by the logged-view PSNR and the feature drift)."""

    def __init__(self, **fields) -> None:
        """A bad field is one OmniscsError line naming it (not pydantic's multi-line report)."""
        try:
            super().__init__(**fields)
        except pydantic.ValidationError as exc:
            raise OmniscsError(request_error(exc)) from None

    _to_list = field_validator("edits", "appearance_objects", mode="before")(_as_list)
    _to_text = field_validator("pool", "behavior_checkpoint", mode="before")(_as_text)

    @field_validator("appearance_objects")
    @classmethod
    def _model_ids(cls, ids: list[str]) -> list[str]:
        if not all(ids):
            raise ValueError("pool model ids must not be empty")
        return ids

    @field_validator("device")
    @classmethod
    def _device(cls, device: str) -> str:
        if device not in ("cpu", "cuda") and not (device.startswith("cuda:") and device[5:].isdigit()):
            raise ValueError(f"unknown device {device!r}; use cpu, cuda or cuda:N")
        return device

    @model_validator(mode="after")
    def _consistent(self):
        if self.appearance_variants and (self.fit_preset is None or self.pool is None):
            raise ValueError("appearance variants composite pool objects into a scene graph: give a fit preset "
                             "and a model pool")
        if self.annotate and (self.fit_preset is None
                              or self.behavior_variants + self.appearance_variants < 1 and not self.edits):
            raise ValueError("a dataset renders variants through a scene graph: give a fit preset and "
                             "behavior_variants >= 1, appearance_variants >= 1 or edits (a designed variant)")
        return self

    @classmethod
    def parse(cls, value):
        """``value`` (an instance, or its dict as JSON or a deployment gives it) as this request; a bad field is
        one OmniscsError line naming it."""
        if isinstance(value, cls):
            return value
        if not isinstance(value, dict):
            raise OmniscsError(f"a {cls.__name__} must be an object of fields; got {type(value).__name__}")
        try:
            return cls.model_validate(value)
        except pydantic.ValidationError as exc:
            raise OmniscsError(request_error(exc)) from None

    def gates(self):
        """The quality gates every variant of the run must pass (``omniscs.gates``)."""
        return GateConfig(near_miss_m=self.near_miss_m, min_visible_frames=self.min_visible_frames,
                          min_psnr_db=self.min_fidelity_psnr)

    def parsed_edits(self) -> list:
        """The edits as the project's edit types (a malformed one is an OmniscsError)."""
        return [edit_from_dict(e) for e in self.edits]

    def scene_request(self) -> "SceneRequest":
        """The fields every scene of the run is asked for."""
        return SceneRequest(**{k: getattr(self, k) for k in SceneRequest.model_fields})

    def to_dict(self) -> dict:
        return self.model_dump(mode="json")

    @classmethod
    def from_dict(cls, d: dict):
        return cls.parse(dict(d))


class RunRequest(SceneRequest):
    """One run of the ``generate_dataset`` flow: its sources, the synthetic rig, where its outputs go and how its
    scenes run, and what every scene is asked for (the ``SceneRequest`` fields)."""

    sources: list[str]
    """syn:TEMPLATE:SEED[:LIGHTING], FORMAT:DATAROOT[:SCENE] (nuscenes, kitti, waymo-v2) or scene-store paths."""
    workspace: str | None = None
    """Workspace root (default $OMNISCS_HOME or ./omniscs-data)."""
    run_id: str | None = None
    """Run id, the name of its catalog partition (default: a time stamp and random digits)."""
    n_frames: int = Field(40, ge=FRAMES[0], le=FRAMES[1])
    """Synthetic sources: frames at 10 Hz."""
    n_cameras: int = Field(3, ge=CAMERAS[0], le=CAMERAS[1])
    """Synthetic sources: cameras, in nuScenes' placement."""
    width: int = Field(480, ge=IMAGE_SIDE[0], le=IMAGE_SIDE[1])
    """Synthetic sources: image width in pixels."""
    height: int = Field(270, ge=IMAGE_SIDE[0], le=IMAGE_SIDE[1])
    """Synthetic sources: image height in pixels."""
    dataset_id: str | None = None
    """With annotate: the dataset's id (default ds-<content hash>, so the same inputs give the same dataset)."""
    task_runner: TaskRunner = "threads"
    """Where scenes run: threads (this process) or dask (a local cluster of `workers` processes, or the scheduler
    at `dask_address`)."""
    workers: int | None = Field(None, ge=1, le=MAX_WORKERS)
    """Scenes at once: threads, or local Dask worker processes (default 2; each gets the cores divided among
    them)."""
    dask_address: str | None = None
    """tcp://HOST:PORT of an existing Dask scheduler (its workers must see the same workspace path)."""

    def product_fields(self) -> dict:
        """The fields that decide what the run makes (not where it is written or how it is executed): what a
        dataset made by the run records, so that the same inputs give the same dataset."""
        return {k: v for k, v in self.to_dict().items() if k not in EXECUTION_FIELDS}

    _run_to_list = field_validator("sources", mode="before")(_as_list)
    _run_to_text = field_validator("workspace", mode="before")(_as_text)

    @field_validator("run_id", "dataset_id")
    @classmethod
    def _safe_id(cls, value: str | None, info) -> str | None:
        if value is None:
            return None
        try:
            return check_id(info.field_name.replace("_", " "), value)
        except OmniscsError as exc:
            raise ValueError(str(exc)) from None


def request_error(exc: pydantic.ValidationError) -> str:
    """A request's first bad field as one line: which field, what is wrong, what was given."""
    err = exc.errors(include_url=False)[0]
    where = ".".join(str(p) for p in err["loc"])
    message = err["msg"].removeprefix("Value error, ")
    given = err.get("input")
    shown = "" if err["type"] == "missing" or isinstance(given, dict) or repr(given) in message else f"; got {given!r}"
    if len(shown) > 80:
        shown = shown[:77] + "..."
    return f"{where}: {message}{shown}" if where else f"{message}{shown}"


def scene_fields() -> tuple[str, ...]:
    """The ``SceneRequest`` field names (what a ``RunRequest`` hands to every scene)."""
    return tuple(SceneRequest.model_fields)
