"""Tasks that bring scenes into the workspace and describe them in the catalog."""
from __future__ import annotations

import time
from pathlib import Path

from prefect import task
from prefect.artifacts import create_progress_artifact, update_progress_artifact
from prefect.runtime import task_run

from omniscs import catalog
from omniscs.preview import write_previews
from omniscs.scene import ingest, load_scene, source_from_dict
from omniscs.scene.summary import agent_rows, frame_rows, scene_row


def _ingest_run_name() -> str:
    src = task_run.parameters["source"]
    kind = src.get("kind")
    if kind == "synthetic":
        return f"ingest-{src['template']}-{src['lighting']}-s{src['seed']}"
    if kind == "store":
        return f"ingest-{Path(src['path']).name}"
    return f"ingest-{kind}-{src.get('scene') or Path(src.get('dataroot', 'scene')).name}"


@task(name="ingest", task_run_name=_ingest_run_name)
def ingest_scene(source: dict, workspace: str) -> dict:
    """Validate or render one scene store; returns its id, path, whether it was reused, and seconds."""
    started = time.perf_counter()
    artifact = create_progress_artifact(0.0, description=f"ingest {source}")
    last = [0.0]

    def progress(done: int, total: int) -> None:
        pct = 100.0 * done / total
        if pct - last[0] >= 10.0 or done == total:
            update_progress_artifact(artifact, pct)
            last[0] = pct

    result = ingest(source_from_dict(source), Path(workspace), progress=progress)
    update_progress_artifact(artifact, 100.0)
    return {"scene_id": result.scene_id, "path": str(result.path), "reused": result.reused,
            "seconds": time.perf_counter() - started}


@task(name="preview")
def preview_scene(ingested: dict, workspace: str) -> str:
    """Contact sheet and BEV plot of a scene; returns the preview folder."""
    out = Path(workspace) / "previews" / ingested["scene_id"]
    write_previews(load_scene(ingested["path"]), out)
    return str(out)


@task(name="catalog-scene")
def catalog_scene(ingested: dict, preview_dir: str | None, run_id: str, workspace: str) -> str:
    """One new Parquet file each in the scenes, agents and frames tables for this scene."""
    scene = load_scene(ingested["path"])
    root = catalog.catalog_root(Path(workspace))
    agents = agent_rows(scene)
    writer = f"scene-{scene.scene_id}"
    catalog.write_rows(root, "agents", run_id, agents, writer=writer)
    catalog.write_rows(root, "frames", run_id, frame_rows(scene), writer=writer)
    catalog.write_rows(root, "scenes", run_id,
                       [scene_row(scene, agents, ingested["reused"], ingested["seconds"], preview_dir)],
                       writer=writer)
    return scene.scene_id


@task(name="catalog-run")
def catalog_run(run_id: str, workspace: str, flow: str, status: str, started_at_us: int, finished_at_us: int,
                n_scenes: int, config_json: str, error: str | None = None) -> str:
    import omniscs

    catalog.write_rows(catalog.catalog_root(Path(workspace)), "runs", run_id, [{
        "flow": flow, "status": status, "started_at_us": started_at_us, "finished_at_us": finished_at_us,
        "n_scenes": n_scenes, "config_json": config_json, "omniscs_version": omniscs.__version__, "error": error,
    }], writer="run")
    return run_id
