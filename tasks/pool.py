"""Prefect tasks of the pool flow: one line each over ``omniscs.pipeline.pool``."""
from __future__ import annotations

from prefect import task

from omniscs.pipeline import pool
from omniscs.pipeline.records import StageRecord


@task(name="pool-asset", task_run_name="pool-{asset_id}")
def add_asset(asset_id: str, pool_path: str, gaussians: int, refine_steps: int) -> StageRecord:
    return pool.pool_asset_stage(asset_id, pool_path, gaussians, refine_steps)


@task(name="catalog-pool")
def catalog(run_id: str, workspace: str, records: list[StageRecord]) -> list[str]:
    from omniscs.pipeline.downstream import catalog_records_stage

    return catalog_records_stage(run_id, workspace, records, writer="pool")
