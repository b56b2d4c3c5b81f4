"""The per-scene pipeline, written once as a table: ``STAGES`` says, in pipeline order, each stage's name, the
function that runs it, what it reads and when it runs. Three walkers go through it with ``walk_scene``: ``run_scene``
(benchmarks, tests), the ``scene-pipeline`` Prefect sub-flow (each stage a task) and ``omniscs fit --until STAGE``.

ingest → plan → preview → fit → agents → background → behavior → appearance → uncovered → annotate (then, per run,
dataset and catalog). Each stage function lives in its own module of this package, is Prefect-free, follows the one
reuse contract (``reuse.py``) and the one progress contract (``omniscs.progress``) and returns a ``StageRecord``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Collection

from omniscs.errors import OmniscsError
from omniscs.pipeline.agents import agents_stage
from omniscs.pipeline.annotate import annotate_stage, replay_stage
from omniscs.pipeline.appearance import appearance_stage
from omniscs.pipeline.background import background_stage, uncovered_stage
from omniscs.pipeline.behavior import behavior_stage
from omniscs.pipeline.catalog import catalog_run_stage, catalog_scene_stage
from omniscs.pipeline.common import device_overrides
from omniscs.pipeline.dataset import catalog_dataset_stage, dataset_stage
from omniscs.pipeline.fit import fit_stage
from omniscs.pipeline.ingest import ingest_stage
from omniscs.pipeline.plan import load_plan, plan_config_for, plan_stage
from omniscs.pipeline.preview import preview_stage
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.request import SceneRequest
from omniscs.plan import ScenePlan
from omniscs.progress import Progress, no_progress

#: The stage functions, importable from here as one index (their homes are this package's modules).
__all__ = ["STAGES", "STAGE_NAMES", "SceneState", "Stage", "agents_stage", "annotate_stage", "appearance_stage",
           "background_stage", "behavior_stage", "catalog_dataset_stage", "catalog_run_stage", "catalog_scene_stage",
           "dataset_stage", "fit_stage", "ingest_stage", "load_plan", "plan_stage", "preview_stage", "replay_stage",
           "run_directly", "run_scene", "stage", "start_scene", "uncovered_stage", "walk_scene"]

@dataclass(frozen=True)
class SceneState:
    """Where one scene's walk through the table stands: what it was given and every record made so far. Small and
    JSON-able (paths, ids, rows), so Prefect passes it to each stage's task."""

    source: dict | str
    """What the ingest stage reads: a source's dict or text, or a scene-store path."""
    request: SceneRequest
    """What the run asks of every scene."""
    workspace: str
    """The workspace root."""
    label: str = ""
    """How the scene is named before it is ingested (the source as the user wrote it)."""
    records: tuple[StageRecord, ...] = ()
    """The records of the stages that ran, in order."""
    model: StageRecord | None = None
    """The scene graph later stages build on: the fit's record, replaced by agents' and background's when they
    made one."""
    options: dict = field(default_factory=dict)
    """Keyword arguments for single stages, by stage name (the CLI's ``--out`` and fit overrides)."""

    def record(self, stage: str) -> StageRecord | None:
        """The record of ``stage`` when it ran, else None."""
        return next((r for r in self.records if r.stage == stage), None)

    @property
    def scene_path(self) -> str:
        return self.record("ingest").path

    @property
    def scene_id(self) -> str:
        ingested = self.record("ingest")
        return ingested.scene_id if ingested is not None else self.label

    @property
    def plan(self) -> ScenePlan:
        return load_plan(self.record("plan"))

    def planned(self, stage: str) -> bool:
        """The scene's plan turns on ``stage`` (a key of ``ScenePlan.stages``)."""
        return bool(self.plan.stages.get(stage))

    def ran(self, stage: str) -> StageRecord | None:
        """The record of ``stage`` when it ran and did something (not skipped), else None."""
        record = self.record(stage)
        return record if record is not None and not record.skipped else None

    def with_record(self, record: StageRecord, makes_model: bool) -> "SceneState":
        model = record if makes_model and not record.skipped else self.model
        return dataclasses.replace(self, records=self.records + (record,), model=model)


@dataclass(frozen=True)
class Stage:
    """One row of the pipeline's table."""

    name: str
    """The stage's name: its record's ``stage``, its Prefect task's name, a value of ``fit --until``."""
    run: Callable[[SceneState, Progress], StageRecord]
    """Runs the stage for one scene (its function, given what it reads from the state)."""
    reads: tuple[str, ...]
    """What it reads from earlier stages ('model': the current scene graph); for readers and the docs."""
    when: Callable[[SceneState], bool]
    """Whether it runs for this scene (ingest and plan always; the others as the plan and request say)."""
    doing: str
    """What it does, for progress lines: '<doing> of <scene>'."""
    makes_model: bool = False
    """Its record is the scene graph the later stages build on."""


def _options(state: SceneState, stage: str) -> dict:
    return dict(state.options.get(stage, {}))


def _ingest(s: SceneState, progress: Progress) -> StageRecord:
    return ingest_stage(s.source, s.workspace, progress=progress, **_options(s, "ingest"))


def _plan(s: SceneState, progress: Progress) -> StageRecord:
    return plan_stage(s.scene_path, s.request, s.workspace, **_options(s, "plan"))


def _preview(s: SceneState, progress: Progress) -> StageRecord:
    return preview_stage(s.scene_path, s.workspace)


def _fit(s: SceneState, progress: Progress) -> StageRecord:
    record = fit_stage(s.scene_path, s.plan, s.request.fit_preset, s.workspace, progress=progress,
                       **{**device_overrides(s.request), **_options(s, "fit")})
    if record.info.get("status") == "diverged":  # nothing after it can use the scene: the scene fails, saying why
        raise OmniscsError(f"scene {record.scene_id}: {record.info['error']}")
    return record


def _agents(s: SceneState, progress: Progress) -> StageRecord:
    return agents_stage(s.scene_path, s.plan, s.model, s.workspace, s.request.pool, progress=progress,
                        **_options(s, "agents"))


def _background(s: SceneState, progress: Progress) -> StageRecord:
    return background_stage(s.scene_path, s.plan, s.model, s.workspace, progress=progress,
                            **_options(s, "background"))


def _behavior(s: SceneState, progress: Progress) -> StageRecord:
    return behavior_stage(s.scene_path, s.plan, s.request.behavior_variants, s.workspace, s.request.behavior_preset,
                          s.request.behavior_checkpoint, s.model, progress=progress,
                          adversarial_overrides=device_overrides(s.request), gates=s.request.gates(),
                          budget=s.request.variant_budget, **_options(s, "behavior"))


def _appearance(s: SceneState, progress: Progress) -> StageRecord:
    return appearance_stage(s.scene_path, s.plan, s.model, s.request.appearance_variants, s.request.pool,
                            s.workspace, s.request.appearance_objects, progress=progress,
                            budget=s.request.variant_budget, **_options(s, "appearance"))


def _uncovered(s: SceneState, progress: Progress) -> StageRecord:
    return uncovered_stage(s.scene_path, s.plan, s.model, (s.ran("appearance"),), s.workspace, progress=progress,
                           plan_config=plan_config_for(s.request), **_options(s, "uncovered"))


def _annotate(s: SceneState, progress: Progress) -> StageRecord:
    return annotate_stage(s.scene_path, s.plan, s.model, s.ran("behavior"), s.workspace, progress=progress,
                          appearance=s.ran("appearance"), uncovered=s.ran("uncovered"), gates=s.request.gates(),
                          keep_failed=s.request.keep_failed, designed=s.request.edits, pool=s.request.pool,
                          **_options(s, "annotate"))


def _always(s: SceneState) -> bool:
    return True


#: The per-scene pipeline, in order.
STAGES: tuple[Stage, ...] = (
    Stage("ingest", _ingest, ("source",), _always, "ingest"),
    Stage("plan", _plan, ("ingest", "request"), _always, "plan"),
    Stage("preview", _preview, ("ingest",), lambda s: s.request.previews, "previews"),
    Stage("fit", _fit, ("ingest", "plan"), lambda s: s.planned("fit_nsg"), "fit scene graph", makes_model=True),
    Stage("agents", _agents, ("ingest", "plan", "model"),
          lambda s: s.model is not None and s.planned("agent_models"), "360-degree agents", makes_model=True),
    Stage("background", _background, ("ingest", "plan", "model"),
          lambda s: s.model is not None and s.planned("background_repair"), "background repair", makes_model=True),
    Stage("behavior", _behavior, ("ingest", "plan", "model"), lambda s: s.planned("behavior_variants"),
          "behaviour variants"),
    Stage("appearance", _appearance, ("ingest", "plan", "model"), lambda s: s.planned("appearance_variants"),
          "appearance variants"),
    Stage("uncovered", _uncovered, ("ingest", "plan", "model", "appearance"),
          lambda s: s.model is not None and s.ran("appearance") is not None and s.planned("render_annotate"),
          "background repair behind replaced objects"),
    Stage("annotate", _annotate, ("ingest", "plan", "model", "behavior", "appearance", "uncovered"),
          lambda s: s.planned("render_annotate"), "render + annotate variants"),
)
STAGE_NAMES = tuple(s.name for s in STAGES)
_BY_NAME = {s.name: s for s in STAGES}


def stage(name: str) -> Stage:
    """The table's row of ``name``."""
    if name not in _BY_NAME:
        raise OmniscsError(f"unknown stage {name!r}; the stages are {', '.join(STAGE_NAMES)}")
    return _BY_NAME[name]


#: How a walker runs one stage: directly, or as a Prefect task.
RunStage = Callable[[Stage, SceneState], StageRecord]


def run_directly(progress_for: Callable[[str], Progress] | None = None) -> RunStage:
    """A walker's runner that calls each stage's function in this process (``progress_for(stage) -> Progress``
    gives each stage its progress sink)."""
    def call(row: Stage, state: SceneState) -> StageRecord:
        return row.run(state, progress_for(row.name) if progress_for is not None else no_progress)
    return call


def walk_scene(state: SceneState, call: RunStage, until: str | None = None,
               skip: Collection[str] = ()) -> SceneState:
    """Run every stage of the table that this scene needs, in order, from where ``state`` stands (stages with a
    record are not run again), up to and including ``until``; stages in ``skip`` do not run."""
    for name in ([until] if until is not None else []) + list(skip):
        stage(name)  # an unknown name is an error, not a silent no-op
    for row in STAGES:
        if state.record(row.name) is None and row.name not in skip and row.when(state):
            state = state.with_record(call(row, state), row.makes_model)
        if row.name == until:
            break
    return state


def start_scene(source, request: SceneRequest, workspace: str | Path, label: str = "",
                options: dict | None = None) -> SceneState:
    """A scene's state before its first stage."""
    return SceneState(source=source, request=request, workspace=str(workspace), label=label or str(source),
                      options=dict(options or {}))


def run_scene(source, request: SceneRequest, workspace: str | Path, run_id: str | None = None,
              progress_for: Callable[[str], Progress] | None = None) -> list[StageRecord]:
    """Every stage for one scene, in pipeline order, without an orchestrator (benchmarks and tests; the
    ``generate_dataset`` flow walks the same table with Prefect tasks). With ``run_id`` the scene is catalogued."""
    state = walk_scene(start_scene(source, request, workspace), run_directly(progress_for))
    if run_id is not None:
        catalog_scene_stage(run_id, workspace, list(state.records))
    return list(state.records)
