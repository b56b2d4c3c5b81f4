"""Where each stage's output lives under the workspace root (one place, so no caller builds a path of its own).
Every id that becomes a folder name here passes the one safe-id rule (``omniscs.ids``): nothing lands outside the
workspace."""
from __future__ import annotations

from pathlib import Path

from omniscs import catalog
from omniscs.catalog import catalog_root
from omniscs.ids import check_id

__all__ = ["catalog_root", "scenes_dir", "scene_folder", "stage_folder", "dataset_folder", "downstream_folder",
           "evaluation_folder", "closedloop_folder", "scene_store"]

#: Top-level folder of each stage's outputs.
FOLDERS = {"ingest": "scenes", "plan": "plans", "preview": "previews", "fit": "models", "agents": "agent_models",
           "background": "repaired",
           "behavior": "variants", "appearance": "variants", "replay": "replays", "annotate": "annotated", "dataset": "datasets",
           "downstream": "downstream", "evaluation": "evaluations", "closedloop": "closedloop"}


def scenes_dir(workspace: str | Path) -> Path:
    """Scene stores ingested into the workspace (``scenes/<scene_id>/``)."""
    return Path(workspace) / FOLDERS["ingest"]


def scene_folder(workspace: str | Path, stage: str, scene_id: str) -> Path:
    """``<workspace>/<stage folder>/<scene_id>``: all outputs of one stage for one scene."""
    return Path(workspace) / FOLDERS[stage] / check_id("scene id", scene_id)


def stage_folder(workspace: str | Path, stage: str, scene_id: str, name: str) -> Path:
    """One output of a stage for a scene, named by what made it (e.g. ``nsg-fast-<key>``)."""
    return scene_folder(workspace, stage, scene_id) / check_id(f"{stage} output name", name)


def dataset_folder(workspace: str | Path, dataset_id: str) -> Path:
    """``<workspace>/datasets/<dataset_id>``: one assembled dataset."""
    return Path(workspace) / FOLDERS["dataset"] / check_id("dataset id", dataset_id)


def downstream_folder(workspace: str | Path, model_id: str) -> Path:
    """``<workspace>/downstream/<model_id>``: one downstream model (a fine-tuned checkpoint, an external job)."""
    return Path(workspace) / FOLDERS["downstream"] / check_id("downstream model id", model_id)


def evaluation_folder(workspace: str | Path, run_id: str) -> Path:
    """``<workspace>/evaluations/<run_id>``: what one downstream run shows of its evaluations (the comparison plot)."""
    return Path(workspace) / FOLDERS["evaluation"] / check_id("run id", run_id)


def closedloop_folder(workspace: str | Path, eval_id: str) -> Path:
    """``<workspace>/closedloop/<eval_id>``: the run folders of one closed-loop evaluation."""
    return Path(workspace) / FOLDERS["closedloop"] / check_id("closed-loop evaluation id", eval_id)


def scene_store(workspace: str | Path, scene_id: str) -> Path | None:
    """Where a scene of the workspace is: ingested under ``scenes/``, or a scene store used in place (as the
    ``scenes`` catalog table recorded it); None when neither knows it."""
    here = scene_folder(workspace, "ingest", scene_id)
    if (here / "manifest.json").is_file():
        return here
    rows = catalog.query(catalog_root(Path(workspace)), "SELECT path FROM scenes WHERE scene_id = "
                         f"'{check_id('scene id', scene_id)}' ORDER BY run_id DESC LIMIT 1").to_pylist()
    path = Path(rows[0]["path"]) if rows else None
    return path if path is not None and (path / "manifest.json").is_file() else None
