"""Prefect tasks of the pool flow: one line each over ``omniscs.pipeline.pool``."""
from __future__ import annotations

from prefect import task

from omniscs.pipeline import pool
from omniscs.pipeline.records import StageRecord
from tasks.retries import STAGE_TASK_OPTIONS


@task(name="pool-asset", task_run_name="pool-{asset_id}", **STAGE_TASK_OPTIONS)
def add_asset(asset_id: str, pool_path: str, gaussians: int, refine_steps: int) -> StageRecord:
    return pool.pool_asset_stage(asset_id, pool_path, gaussians, refine_steps)

