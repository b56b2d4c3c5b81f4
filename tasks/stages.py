"""Prefect tasks: one line each over the pipeline's stage functions; they pass records (ids, paths, rows)."""
from __future__ import annotations

from prefect import task

from omniscs.pipeline import stages
from omniscs.pipeline.agents import agents_stage
from omniscs.pipeline.appearance import appearance_stage
from omniscs.pipeline.background import background_stage
from omniscs.pipeline.records import SceneRequest, StageRecord
from tasks.progress import artifact_progress
from tasks.retries import STAGE_TASK_OPTIONS


@task(name="ingest", task_run_name="ingest-{label}", **STAGE_TASK_OPTIONS)
def ingest(source: dict, workspace: str, label: str) -> StageRecord:
    return stages.ingest_stage(source, workspace, progress=artifact_progress(f"ingest {label}"))


@task(name="plan", task_run_name="plan-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def plan(scene: StageRecord, request: SceneRequest, workspace: str) -> StageRecord:
    return stages.plan_stage(scene.path, request, workspace)


@task(name="preview", task_run_name="preview-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def preview(scene: StageRecord, workspace: str) -> StageRecord:
    return stages.preview_stage(scene.path, workspace)


@task(name="fit", task_run_name="fit-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def fit(scene: StageRecord, plan: StageRecord, request: SceneRequest, workspace: str) -> StageRecord:
    return stages.fit_stage(scene.path, stages.load_plan(plan), request.fit_preset, workspace,
                            progress=artifact_progress(f"fit scene graph of {scene.scene_id} ({request.fit_preset})"),
                            **stages.device_overrides(request))


@task(name="agents", task_run_name="agents-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def agents(scene: StageRecord, plan: StageRecord, model: StageRecord, request: SceneRequest,
           workspace: str) -> StageRecord:
    return agents_stage(scene.path, stages.load_plan(plan), model, workspace, request.pool,
                        progress=artifact_progress(f"360-degree agents of {scene.scene_id}"))


@task(name="background", task_run_name="background-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def background(scene: StageRecord, plan: StageRecord, model: StageRecord, workspace: str) -> StageRecord:
    return background_stage(scene.path, stages.load_plan(plan), model, workspace,
                            progress=artifact_progress(f"background repair of {scene.scene_id}"))


@task(name="behavior", task_run_name="behavior-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def behavior(scene: StageRecord, plan: StageRecord, model: StageRecord | None, request: SceneRequest,
             workspace: str) -> StageRecord:
    return stages.behavior_stage(scene.path, stages.load_plan(plan), request.behavior_variants, workspace,
                                 request.behavior_preset, request.behavior_checkpoint, model,
                                 progress=artifact_progress(f"behaviour variants of {scene.scene_id}"),
                                 adversarial_overrides=stages.device_overrides(request))


@task(name="appearance", task_run_name="appearance-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def appearance(scene: StageRecord, plan: StageRecord, model: StageRecord | None, request: SceneRequest,
               workspace: str) -> StageRecord:
    return appearance_stage(scene.path, stages.load_plan(plan), model, request.appearance_variants, request.pool,
                            workspace, request.appearance_objects,
                            progress=artifact_progress(f"appearance variants of {scene.scene_id}"))


@task(name="annotate", task_run_name="annotate-{scene.scene_id}", **STAGE_TASK_OPTIONS)
def annotate(scene: StageRecord, plan: StageRecord, model: StageRecord | None, behavior: StageRecord | None,
             workspace: str, appearance: StageRecord | None = None) -> StageRecord:
    return stages.annotate_stage(scene.path, stages.load_plan(plan), model, behavior, workspace,
                                 progress=artifact_progress(f"render + annotate variants of {scene.scene_id}"),
                                 appearance=appearance)


@task(name="dataset", **STAGE_TASK_OPTIONS)
def dataset(annotated: list[StageRecord], workspace: str, dataset_id: str | None, facts: dict) -> StageRecord:
    return stages.dataset_stage(annotated, workspace, dataset_id, facts)


@task(name="catalog-dataset", task_run_name="catalog-{record.scene_id}", **STAGE_TASK_OPTIONS)
def catalog_dataset(run_id: str, workspace: str, record: StageRecord) -> list[str]:
    return stages.catalog_dataset_stage(run_id, workspace, record)


@task(name="catalog-scene", task_run_name="catalog-{scene_id}", **STAGE_TASK_OPTIONS)
def catalog_scene(run_id: str, workspace: str, scene_id: str, records: list[StageRecord]) -> list[str]:
    return stages.catalog_scene_stage(run_id, workspace, records)


@task(name="catalog-run", **STAGE_TASK_OPTIONS)
def catalog_run(run_id: str, workspace: str, flow: str, status: str, started_at_us: int, finished_at_us: int,
                n_scenes: int, config: dict, error: str | None = None) -> str:
    from prefect.runtime import flow_run

    return stages.catalog_run_stage(run_id, workspace, flow, status, started_at_us, finished_at_us, n_scenes, config,
                                    error, flow_run_id=flow_run.get_id())
