"""The ``generate_dataset`` flow: scenes in, catalogued scene stores (and, later, SCS variants) out.

Pipeline per scene: ingest → preview → fit NSG (when a preset is given) → behaviour variants (when asked
for) → catalog. Later stages (agents, background, appearance variants, export) slot in before catalog.
"""
from __future__ import annotations

import json
import time
import uuid
from datetime import datetime, timezone

from prefect import flow, unmapped
from prefect.task_runners import ThreadPoolTaskRunner

from omniscs.errors import OmniscsError
from omniscs.nsg.config import PRESETS as FIT_PRESETS
from omniscs.scene import parse_source
from omniscs.scs.behavior import PRESETS as BEHAVIOR_PRESETS
from omniscs.storage import workspace_root
from tasks.behavior import behavior_variants as behavior_variants_task
from tasks.ingest import catalog_run, catalog_scene, ingest_scene, preview_scene
from tasks.nsg import fit_nsg

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
                     previews: bool = True, behavior_variants: int = 0,
                     behavior_checkpoint: str | None = None, behavior_preset: str = "balanced",
                     fit_preset: str | None = None) -> dict:
    """Ingest every source (``syn:TEMPLATE:SEED[:LIGHTING]`` or a scene-store path) and catalogue it.

    ``behavior_variants`` > 0 makes that many behaviour-level SCS variants per scene (``variants`` table;
    ``behavior_checkpoint`` defaults to the shipped traffic model, ``behavior_preset`` is fast, balanced or
    accurate). ``fit_preset`` (fast, balanced or accurate) fits each scene's Gaussian scene graph after
    ingest (``models`` table; checkpoints under ``models/<scene_id>/``); with both, every vehicle is a node
    and the behaviour optimisation adds L_app rendered by that graph. Returns the run id, workspace, the
    scene ids and paths, the variant files and the fitted models.
    """
    if isinstance(behavior_variants, bool) or not isinstance(behavior_variants, int) or behavior_variants < 0:
        raise OmniscsError(f"behavior_variants must be a non-negative integer; got {behavior_variants!r}")
    if behavior_variants and behavior_preset not in BEHAVIOR_PRESETS:
        raise OmniscsError(f"unknown behavior_preset {behavior_preset!r}; use one of {list(BEHAVIOR_PRESETS)}")
    if fit_preset is not None and fit_preset not in FIT_PRESETS:
        raise OmniscsError(f"unknown fit_preset {fit_preset!r}; use one of {list(FIT_PRESETS)} or None")
    ws = str(workspace_root(workspace))
    run_id = run_id or new_run_id()
    started = _now_us()
    config = {"sources": list(sources), "n_frames": n_frames, "n_cameras": n_cameras, "width": width,
              "height": height, "previews": previews, "behavior_variants": behavior_variants,
              "behavior_checkpoint": behavior_checkpoint, "behavior_preset": behavior_preset,
              "fit_preset": fit_preset}
    specs = [parse_source(s, n_frames=n_frames, n_cameras=n_cameras, width=width, height=height).to_dict()
             for s in sources]
    try:
        ingested = ingest_scene.map(specs, workspace=unmapped(ws))
        preview_dirs = (preview_scene.map(ingested, workspace=unmapped(ws)) if previews
                        else [None] * len(specs))
        models = []
        if fit_preset is not None:
            models = fit_nsg.map(ingested, workspace=unmapped(ws), run_id=unmapped(run_id),
                                 preset=unmapped(fit_preset), behavior_variants=unmapped(behavior_variants))
        behaviour = []
        if behavior_variants > 0:
            # after fit-nsg when there is one: its scene graph renders L_app
            behaviour = behavior_variants_task.map(ingested, workspace=unmapped(ws), run_id=unmapped(run_id),
                                                   n_variants=unmapped(behavior_variants),
                                                   checkpoint=unmapped(behavior_checkpoint),
                                                   preset=unmapped(behavior_preset),
                                                   model=models if fit_preset is not None else unmapped(None))
        scene_ids = catalog_scene.map(ingested, preview_dirs, run_id=unmapped(run_id), workspace=unmapped(ws),
                                      wait_for=list(behaviour) + list(models) or None)
        scene_ids = scene_ids.result()
        behaviour = behaviour.result() if behavior_variants > 0 else []
        models = models.result() if fit_preset is not None else []
        ingested = ingested.result()
    except Exception as exc:
        catalog_run(run_id, ws, "generate_dataset", "failed", started, _now_us(), len(specs),
                    json.dumps(config), error=str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        raise
    catalog_run(run_id, ws, "generate_dataset", "completed", started, _now_us(), len(specs), json.dumps(config))
    return {"run_id": run_id, "workspace": ws,
            "scenes": [{"scene_id": i["scene_id"], "path": i["path"], "reused": i["reused"]} for i in ingested],
            "previews": [p.result() if hasattr(p, "result") else p for p in preview_dirs],
            "behavior_variants": behaviour, "models": models}
