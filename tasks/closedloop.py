"""Prefect tasks of the closed-loop flow: one line each over ``omniscs.pipeline.closedloop``."""
from __future__ import annotations

from prefect import task

from omniscs.pipeline import closedloop as c
from omniscs.pipeline.records import StageRecord
from tasks.progress import artifact_progress
from tasks.retries import STAGE_TASK_OPTIONS


@task(name="closed-loop-run", task_run_name="closed-loop-{scenario}-{policy}", **STAGE_TASK_OPTIONS)
def run_scenario(workspace: str, scenario: str, policy: str, eval_id: str, config, max_steps: int | None,
                 out_dir: str | None, epdms=None) -> StageRecord:
    return c.closed_loop_stage(workspace, scenario, policy, eval_id, config, max_steps, out_dir=out_dir,
                               progress=artifact_progress(f"closed loop {scenario} ({policy})"), epdms=epdms)
