"""Prefect tasks over the pipeline's stage table: one task per stage (named after it), each a call of its row's
function; plus the per-run dataset and catalog tasks. They pass records (ids, paths, rows), never tensors."""
from __future__ import annotations

from prefect import task

from omniscs.pipeline import stages
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.stages import STAGES, SceneState, Stage
from tasks.progress import task_progress
from tasks.retries import STAGE_TASK_OPTIONS


def _run(stage: str, state: SceneState, run_id: str | None = None) -> StageRecord:
    row = stages.stage(stage)
    with task_progress(f"{row.doing} of {state.scene_id}", state.workspace, run_id,
                       f"{state.scene_id} {stage}") as progress:
        return row.run(state, progress)


#: One Prefect task per row of the stage table, named after its stage.
STAGE_TASKS = {row.name: task(_run, name=row.name, task_run_name=f"{row.name}-{{state.scene_id}}",
                              **STAGE_TASK_OPTIONS) for row in STAGES}


def run_stage(row: Stage, state: SceneState, run_id: str | None = None) -> StageRecord:
    """The walker's runner inside a flow: the stage as its Prefect task (of run ``run_id``, whose watcher, if any,
    hears its progress)."""
    return STAGE_TASKS[row.name](row.name, state, run_id)


@task(name="dataset", **STAGE_TASK_OPTIONS)
def dataset(annotated: list[StageRecord], workspace: str, dataset_id: str | None, facts: dict,
            keep_failed: bool = False, run_id: str | None = None) -> StageRecord:
    # The stage reports no steps of its own (it gathers finished variants): its start and end are its progress.
    with task_progress("dataset of the run", workspace, run_id, "dataset") as progress:
        record = stages.dataset_stage(annotated, workspace, dataset_id, facts, keep_failed=keep_failed)
        progress(1, 1, record.info["dataset_id"])
    return record


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
