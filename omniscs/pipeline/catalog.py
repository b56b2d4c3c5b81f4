"""Cataloguing: a scene's rows (its store's scene, agent and frame rows and every row its stages produced) and a
run's ``runs`` row, each as new Parquet files of the workspace's catalog."""
from __future__ import annotations

import json
from pathlib import Path

import omniscs
from omniscs import catalog
from omniscs.pipeline import layout
from omniscs.pipeline.records import StageRecord
from omniscs.scene import load_scene
from omniscs.scene.summary import agent_rows, frame_rows, scene_row


def catalog_scene_stage(run_id: str, workspace: str | Path, records: list[StageRecord]) -> list[str]:
    """One new Parquet file per catalog table for this scene: its scene, agent and frame rows (from the
    ingested store) and every row the scene's stages produced; returns the files written."""
    by_stage = {r.stage: r for r in records}
    ingest = by_stage["ingest"]
    scene = load_scene(ingest.path)
    preview = by_stage.get("preview")
    root = layout.catalog_root(workspace)
    writer = f"scene-{scene.scene_id}"
    agents = agent_rows(scene)
    tables: dict[str, list[dict]] = {
        "agents": agents, "frames": frame_rows(scene),
        "scenes": [scene_row(scene, agents, ingest.reused, ingest.seconds,
                             preview.path if preview is not None and not preview.skipped else None)]}
    for r in records:
        for table, rows in r.rows.items():
            tables.setdefault(table, []).extend(rows)
    annotated = by_stage.get("annotate")
    verdicts = annotated.info.get("verdicts") or {} if annotated is not None and not annotated.skipped else {}
    for row in tables.get("variants", []):  # the render's verdict is the final one
        verdict = verdicts.get(str(row["variant_id"]))
        if verdict is not None:
            row.update(passed_gates=bool(verdict["passed"]), gate_reasons=list(verdict["reasons"]))
    written = [catalog.write_rows(root, table, run_id, rows, writer=writer) for table, rows in tables.items()]
    return [str(p) for p in written if p is not None]


def catalog_run_stage(run_id: str, workspace: str | Path, flow: str, status: str, started_at_us: int,
                      finished_at_us: int, n_scenes: int, config: dict, error: str | None = None,
                      flow_run_id: str | None = None) -> str:
    """The run's row in ``runs`` (written last, so a run row means the run ended, well or not); ``flow_run_id``:
    the orchestrator's id of the run (what its events name), when there is one."""
    path = catalog.write_rows(layout.catalog_root(workspace), "runs", run_id, [{
        "flow": flow, "status": status, "started_at_us": started_at_us, "finished_at_us": finished_at_us,
        "n_scenes": n_scenes, "config_json": json.dumps(config, sort_keys=True, default=str),
        "omniscs_version": omniscs.__version__, "error": error, "flow_run_id": flow_run_id}], writer="run")
    return str(path)
