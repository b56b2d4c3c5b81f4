"""The ``build_pool`` flow: assets of the world's library made into pool models, two at a time, catalogued
(``pool`` table: who added what, from which source)."""
from __future__ import annotations

from prefect import flow, unmapped
from prefect.task_runners import ThreadPoolTaskRunner

from omniscs.errors import ValidationError
from omniscs.pipeline.records import new_run_id
from omniscs.pipeline.validate import check_run_id
from omniscs.storage import workspace_root
from flows.generate import _now_us, one_line
from tasks import downstream as td
from tasks import pool as t
from tasks import stages as ts


@flow(name="build_pool", task_runner=ThreadPoolTaskRunner(max_workers=2), log_prints=False)
def build_pool(assets: list[str], pool: str, workspace: str | None = None, run_id: str | None = None,
               gaussians: int = 20_000, refine_steps: int = 100) -> dict:
    """Add ``assets`` (asset ids or kinds of the world's library) to the pool folder ``pool``; returns the run id
    and the model ids."""
    from omniscs.pipeline.pool import asset_ids

    ws = str(workspace_root(workspace))
    run_id = check_run_id(run_id) or new_run_id()
    started = _now_us()
    config = {"assets": assets, "pool": pool, "gaussians": gaussians, "refine_steps": refine_steps}
    try:
        ids = asset_ids(assets)
        if gaussians < 10 or refine_steps < 0:
            raise ValidationError("build_pool needs gaussians >= 10 and refine_steps >= 0")
        records = [f.result() for f in t.add_asset.map(ids, unmapped(pool), unmapped(gaussians),
                                                       unmapped(refine_steps))]
        td.catalog(run_id, ws, records, writer="pool")
    except BaseException as exc:
        ts.catalog_run.fn(run_id, ws, "build_pool", "failed" if isinstance(exc, Exception) else "cancelled",
                          started, _now_us(), 0, config, error=one_line(exc))
        raise
    ts.catalog_run(run_id, ws, "build_pool", "completed", started, _now_us(), 0, config)
    return {"run_id": run_id, "model_ids": [r.info["model_id"] for r in records]}
