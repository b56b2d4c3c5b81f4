"""Prefect tasks of the downstream flows: one line each over ``omniscs.pipeline.downstream``."""
from __future__ import annotations

from prefect import task

from omniscs.pipeline import downstream as d
from omniscs.pipeline.records import StageRecord
from tasks.progress import artifact_progress
from tasks.retries import STAGE_TASK_OPTIONS


@task(name="finetune-proxy-planner", **STAGE_TASK_OPTIONS)
def finetune(dataset_ids: list[str], workspace: str, rehearse: bool = True) -> StageRecord:
    return d.finetune_stage(dataset_ids, workspace, rehearse=rehearse,
                            progress=artifact_progress("fine-tune the proxy planner"))


@task(name="evaluate-planner", task_run_name="evaluate-{label}", **STAGE_TASK_OPTIONS)
def evaluate(model: StageRecord | None, dataset_ids: list[str], workspace: str, label: str) -> StageRecord:
    return d.evaluate_stage(model, dataset_ids, workspace)


@task(name="finetune-proxy-detector", **STAGE_TASK_OPTIONS)
def finetune_detector(dataset_ids: list[str], workspace: str, rehearsal: list[str] | None = None) -> StageRecord:
    return d.finetune_detector_stage(dataset_ids, workspace, rehearsal=rehearsal,
                                     progress=artifact_progress("fine-tune the proxy camera detector"))


@task(name="evaluate-detector", task_run_name="evaluate-detector-{label}", **STAGE_TASK_OPTIONS)
def evaluate_detector(model: StageRecord | None, dataset_ids: list[str], workspace: str, label: str) -> StageRecord:
    return d.evaluate_detector_stage(model, dataset_ids, workspace)


@task(name="external-job", **STAGE_TASK_OPTIONS)
def external(template: str, dataset_ids: list[str], workspace: str, values: dict, timeout_s: float,
             export: str | None) -> StageRecord:
    return d.external_stage(template, dataset_ids, workspace, values, timeout_s, export)


@task(name="catalog-records", task_run_name="catalog-{writer}", **STAGE_TASK_OPTIONS)
def catalog(run_id: str, workspace: str, records: list[StageRecord], writer: str = "downstream") -> list[str]:
    return d.catalog_records_stage(run_id, workspace, records, writer=writer)


@task(name="comparison-plot", **STAGE_TASK_OPTIONS)
def comparison_plot(run_id: str, workspace: str, records: list[StageRecord]) -> str | None:
    return d.comparison_plot_stage(run_id, workspace, records)
