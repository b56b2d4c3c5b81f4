"""The fit stage: the Gaussian scene graph the plan asks for, fitted with a preset (or reused), with its
``models`` row; a fit that diverges is a record and a row with status 'diverged' and its reason (the pipeline then
fails the scene with that reason; benchmarks report it as a row)."""
from __future__ import annotations

import time
from pathlib import Path

from omniscs.errors import OmniscsError
from omniscs.locks import output_lock
from omniscs.nsg.checkpoint import load_metrics
from omniscs.nsg.config import fit_preset
from omniscs.nsg.train import FitDiverged, fit_scene
from omniscs.pipeline import layout
from omniscs.pipeline.common import result_config, waiting
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, mark_done, reusable
from omniscs.plan import ScenePlan
from omniscs.progress import Progress, no_progress
from omniscs.scene import load_scene
from omniscs.storage import atomic_write_json
from omniscs.untrusted import read_own_json

#: Bump when the code changes what the stage writes (older outputs are then not reused).
FIT_VERSION = 1


def fit_stage(scene_path: str | Path, plan: ScenePlan, preset: str, workspace: str | Path | None = None,
              progress: Progress = no_progress, out_dir: str | Path | None = None, reuse: bool = True,
              replace: bool = True, **overrides) -> StageRecord:
    """Fit (or reuse) the scene graph the plan asks for with a preset (``overrides`` replace preset fields);
    checkpoint in ``out_dir`` (default ``models/<scene_id>/nsg-<preset>-<key>/``) and one ``models`` row. A
    diverged fit is a record and a row with status 'diverged', no checkpoint, and a note beside ``out_dir``
    (``<name>.diverged.json``): a run that waited for the same fit meanwhile takes that outcome instead of
    fitting again; a later run fits again.
    ``reuse=False`` fits again even when an identical fit exists (benchmarks time the fit itself);
    ``replace=False`` refuses an ``out_dir`` that holds something else (a user's folder)."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if not plan.stages.get("fit_nsg", True):
        return StageRecord.skip("fit", scene.scene_id, "the request fits no scene graph")
    config = fit_preset(preset, **overrides)
    key = StageKey.of("fit", FIT_VERSION, {"scene": scene.content_hash, "plan": plan.to_dict()},
                      result_config(config.to_dict()))
    name = f"nsg-{preset}-{key.short}"
    if out_dir is None:
        if workspace is None:
            raise OmniscsError("fit_stage needs a workspace or an out_dir")
        out_dir = layout.stage_folder(workspace, "fit", scene.scene_id, name)
    out_dir = Path(out_dir)
    row = {"scene_id": scene.scene_id, "model_id": name, "kind": "nsg", "preset": preset,
           "n_agent_nodes": len(plan.agent_nodes), "agent_nodes": list(plan.agent_nodes),
           "iterations": config.iterations}
    asked_at = time.time()
    with output_lock(out_dir, waiting(progress, out_dir)):
        found = reusable(out_dir, key)
        failed = _diverged_meanwhile(out_dir, key, asked_at)
        if failed is not None and found is None:
            row.update(status="diverged", checkpoint_path=None, reused=True, error=failed)
            return StageRecord("fit", scene.scene_id, None, reused=True, seconds=time.perf_counter() - started,
                               key=key.digest, rows={"models": [row]}, info={"status": "diverged", "error": failed})
        if out_dir.exists() and not replace and (found is None or not reuse):
            raise OmniscsError(f"{out_dir} already exists and holds another fit; choose another folder or "
                               "overwrite it")
        if reuse and found is not None:
            metrics = load_metrics(out_dir)
            row.update(_metric_fields(metrics), status="fitted", checkpoint_path=str(out_dir), reused=True)
            return StageRecord("fit", scene.scene_id, str(out_dir), reused=True,
                               seconds=time.perf_counter() - started, key=key.digest, rows={"models": [row]},
                               info={"status": "fitted", "metrics": metrics})
        try:
            result = fit_scene(scene, config, plan, progress=progress, checkpoint_dir=out_dir, overwrite=True)
        except FitDiverged as exc:
            atomic_write_json(_diverged_note(out_dir), {"key": key.digest, "error": str(exc), "at": time.time()})
            row.update(status="diverged", checkpoint_path=None, reused=False, error=str(exc))
            return StageRecord("fit", scene.scene_id, None, seconds=time.perf_counter() - started, key=key.digest,
                               rows={"models": [row]}, info={"status": "diverged", "error": str(exc)})
        mark_done(out_dir, key, {"checkpoint": "."}, time.perf_counter() - started)
    row.update(_metric_fields(result.metrics), status="fitted", checkpoint_path=str(out_dir), reused=False)
    return StageRecord("fit", scene.scene_id, str(out_dir), seconds=time.perf_counter() - started, key=key.digest,
                       rows={"models": [row]}, info={"status": "fitted", "metrics": result.metrics})


def _diverged_note(out_dir: Path) -> Path:
    return out_dir.with_name(out_dir.name + ".diverged.json")


def _diverged_meanwhile(out_dir: Path, key: StageKey, since: float) -> str | None:
    """The reason of a fit of the same key that diverged after ``since`` (while this caller waited for the
    lock), else None."""
    note = _diverged_note(out_dir)
    try:
        d = read_own_json(note, "ignored")
    except OmniscsError:
        return None
    if isinstance(d, dict) and d.get("key") == key.digest and isinstance(d.get("at"), (int, float)) \
            and d["at"] >= since and isinstance(d.get("error"), str):
        return d["error"]
    return None


def _metric_fields(metrics: dict) -> dict:
    return {k: metrics.get(k) for k in ("n_gaussians", "fit_seconds", "train_psnr", "heldout_psnr", "heldout_ssim")}


