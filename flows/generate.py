"""The ``generate_dataset`` flow: scenes in, catalogued scene stores (and, later, SCS variants) out.

Pipeline per scene: ingest → preview → catalog. Later stages (plan, fit NSG, agents, background,
SCS variants, export) slot in between ingest and catalog.
"""
from __future__ import annotations

import json
import time
import uuid
from datetime import datetime, timezone

from prefect import flow, unmapped
from prefect.task_runners import ThreadPoolTaskRunner

from omniscs.scene import parse_source
from omniscs.storage import workspace_root
from tasks.ingest import catalog_run, catalog_scene, ingest_scene, preview_scene

#: Scenes processed at once; the machines this runs on have 2 cores.
MAX_PARALLEL_SCENES = 2


def new_run_id() -> str:
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ") + "-" + uuid.uuid4().hex[:6]


def _now_us() -> int:
    return int(time.time() * 1e6)


@flow(name="generate_dataset", task_runner=ThreadPoolTaskRunner(max_workers=MAX_PARALLEL_SCENES),
      log_prints=False)
def generate_dataset(sources: list[str], workspace: str | None = None, run_id: str | None = None,
                     n_frames: int = 40, n_cameras: int = 3, width: int = 480, height: int = 270,
                     previews: bool = True) -> dict:
    """Ingest every source (``syn:TEMPLATE:SEED[:LIGHTING]`` or a scene-store path) and catalogue it.

    Returns the run id, workspace and the scene ids and paths.
    """
    ws = str(workspace_root(workspace))
    run_id = run_id or new_run_id()
    started = _now_us()
    config = {"sources": list(sources), "n_frames": n_frames, "n_cameras": n_cameras, "width": width,
              "height": height, "previews": previews}
    specs = [parse_source(s, n_frames=n_frames, n_cameras=n_cameras, width=width, height=height).to_dict()
             for s in sources]
    try:
        ingested = ingest_scene.map(specs, workspace=unmapped(ws))
        preview_dirs = (preview_scene.map(ingested, workspace=unmapped(ws)) if previews
                        else [None] * len(specs))
        scene_ids = catalog_scene.map(ingested, preview_dirs, run_id=unmapped(run_id), workspace=unmapped(ws))
        scene_ids = scene_ids.result()
        ingested = ingested.result()
    except Exception as exc:
        catalog_run(run_id, ws, "generate_dataset", "failed", started, _now_us(), len(specs),
                    json.dumps(config), error=str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        raise
    catalog_run(run_id, ws, "generate_dataset", "completed", started, _now_us(), len(specs), json.dumps(config))
    return {"run_id": run_id, "workspace": ws,
            "scenes": [{"scene_id": i["scene_id"], "path": i["path"], "reused": i["reused"]} for i in ingested],
            "previews": [p.result() if hasattr(p, "result") else p for p in preview_dirs]}
