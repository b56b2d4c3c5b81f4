"""Task that fits (or reuses) a scene's Gaussian scene graph and catalogues it in the ``models`` table."""
from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.artifacts import create_progress_artifact, update_progress_artifact

from omniscs import catalog
from omniscs.nsg.store import fit_into_workspace

#: The progress artifact is updated every this many percent.
PROGRESS_STEP_PCT = 5.0


@task(name="fit-nsg", task_run_name="fit-nsg-{ingested[scene_id]}")
def fit_nsg(ingested: dict, workspace: str, run_id: str, preset: str, behavior_variants: int = 0) -> dict:
    """Checkpoint under ``<workspace>/models/<scene_id>/`` and one row in the ``models`` table; with behaviour
    variants requested, every vehicle is a node (the variants move them in the render)."""
    artifact = create_progress_artifact(0.0, description=f"fit scene graph of {ingested['scene_id']} ({preset})")
    last = [0.0]

    def progress(done: int, total: int, loss: float, psnr: float) -> None:
        pct = 100.0 * done / total
        if pct - last[0] >= PROGRESS_STEP_PCT or done == total:
            update_progress_artifact(artifact, pct)
            last[0] = pct

    row = fit_into_workspace(ingested["path"], Path(workspace), preset, progress=progress,
                             behavior_variants=behavior_variants)
    update_progress_artifact(artifact, 100.0)
    catalog.write_rows(catalog.catalog_root(Path(workspace)), "models", run_id, [row],
                       writer=f"nsg-{ingested['scene_id']}")
    return {"scene_id": row["scene_id"], "model_id": row["model_id"], "status": row["status"],
            "checkpoint_path": row["checkpoint_path"], "reused": row["reused"]}
