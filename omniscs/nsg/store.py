"""Fitted scene graphs in the workspace: ``models/<scene_id>/nsg-<preset>-<key>/``, reused when inputs match."""
from __future__ import annotations

from pathlib import Path

from omniscs.edits import Edit, edit_to_dict
from omniscs.errors import OmniscsError
from omniscs.nsg.checkpoint import CHECKPOINT_VERSION, load_metrics, read_checkpoint_meta
from omniscs.nsg.config import fit_preset
from omniscs.nsg.train import FitDiverged, Progress, fit_scene
from omniscs.plan import make_plan
from omniscs.scene.store import load_scene
from omniscs.storage import content_hash

#: Folder of fitted models under the workspace root.
MODELS_DIR = "models"


def model_id(scene_content_hash: str, preset: str, config: dict, edits: list[dict],
             agent_nodes: tuple[int, ...] = ()) -> str:
    """Names a fit by what decides it: scene content, configuration, the edits and nodes of the plan,
    checkpoint version."""
    key = content_hash(scene_content_hash, config, edits, list(agent_nodes), CHECKPOINT_VERSION)
    return f"nsg-{preset}-{key[:12]}"


def fit_into_workspace(scene_path: str | Path, workspace: str | Path, preset: str,
                       edits: list[Edit] | None = None, progress: Progress | None = None,
                       behavior_variants: int = 0) -> dict:
    """Fit (or reuse) the scene graph of one scene store; returns its ``models`` catalog row.

    A diverged fit is reported in the row (status 'diverged', no checkpoint) rather than raised, so the
    rest of a flow run goes on; nothing of it is left on disk. ``behavior_variants`` > 0 plans every vehicle
    as a node (behaviour-level variants move them in the render).
    """
    scene = load_scene(scene_path)
    config = fit_preset(preset)
    edits = list(edits or [])
    plan = make_plan(scene, edits, config.plan, behavior_variants=behavior_variants)
    ident = model_id(scene.content_hash, preset, config.to_dict(), [edit_to_dict(e) for e in edits],
                     plan.agent_nodes)
    out = Path(workspace) / MODELS_DIR / scene.scene_id / ident
    row = {"scene_id": scene.scene_id, "model_id": ident, "kind": "nsg", "preset": preset,
           "n_agent_nodes": len(plan.agent_nodes), "agent_nodes": list(plan.agent_nodes),
           "iterations": config.iterations}
    if out.exists():
        try:
            read_checkpoint_meta(out)
            metrics = load_metrics(out)
        except OmniscsError:
            metrics = None
        if metrics and metrics.get("status") == "fitted":
            return {**row, **_metric_fields(metrics), "status": "fitted", "checkpoint_path": str(out), "reused": True}
    try:
        result = fit_scene(scene, config, plan, progress=progress, checkpoint_dir=out, overwrite=True)
    except FitDiverged as exc:
        return {**row, "status": "diverged", "checkpoint_path": None, "reused": False, "error": str(exc)}
    return {**row, **_metric_fields(result.metrics), "status": "fitted", "checkpoint_path": str(out),
            "reused": False}


def _metric_fields(metrics: dict) -> dict:
    return {k: metrics.get(k) for k in ("n_gaussians", "fit_seconds", "train_psnr", "heldout_psnr", "heldout_ssim")}
