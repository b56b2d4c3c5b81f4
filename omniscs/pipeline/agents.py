"""The agents stage (Prefect-free): after the fit, the dual strategy gives each agent node the plan says needs a
360-degree model one (``omniscs.agents.dual``), cuts every node to its box, grows the pool from clear, well-covered
tracks, and writes the completed scene graph as a checkpoint the later stages render (``agent_models/<scene_id>/
agents-<key>/``: the checkpoint, ``decisions.json``) with one ``agent_models`` catalog row per node."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from omniscs.agents.dual import DualConfig, complete_agents, grow_pool, write_decisions
from omniscs.agents.pool import Pool
from omniscs.errors import OmniscsError
from omniscs.nsg.checkpoint import load_graph, load_metrics, read_checkpoint_meta, write_checkpoint_files
from omniscs.pipeline import layout
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.plan import ScenePlan
from omniscs.progress import Progress, no_progress
from omniscs.scene import load_scene
from omniscs.storage import atomic_write_json
from omniscs.untrusted import read_own_json

#: Bumped when the agents stage changes what it writes (2: relit pool models, the size rule; 3: matching compares a
#: crop seen small with keyframes as small, ``matching.GALLERY_SCALES``).
AGENTS_VERSION = 3

DECISIONS = "decisions.json"

#: Held-out masked PSNR (dB) a scene track needs to join the pool.
GROWTH_MIN_PSNR = 24.0


def _pool_state(pool: str | Path | None, scene_id: str) -> dict | None:
    """What of the pool decides the stage's output: its path and the ids it holds, less what this very scene added
    (so that the pool growing from the scene does not make the scene's own output stale)."""
    if pool is None:
        return None

    table = Pool(pool).table()
    return {"path": str(Path(pool).resolve()), "models": sorted(table.model_id[~table.source.str.startswith(
        f"{scene_id}/")]) if len(table) else []}


def agents_stage(scene_path: str | Path, plan: ScenePlan, model: StageRecord | None,
                 workspace: str | Path | None = None,
                 pool: str | Path | None = None, progress: Progress = no_progress, out_dir: str | Path | None = None,
                 config=None, grow: bool = True, reuse: bool = True) -> StageRecord:
    """The fitted graph (``model``, the fit stage's record) completed by the dual strategy; without ``pool`` every
    track that needs a 360-degree model gets the online one. A skipped stage (no fit, or nothing needs a model)
    hands the fit's record on unchanged."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if model is None or model.info.get("status") != "fitted":
        return StageRecord.skip("agents", scene.scene_id, "no fitted scene graph to complete")
    if not plan.stages.get("agent_models"):
        return StageRecord.skip("agents", scene.scene_id, "no edit turns or inserts an agent: the fit's nodes serve")
    config = config or DualConfig()
    state = _pool_state(pool, scene.scene_id)
    key = StageKey.of("agents", AGENTS_VERSION, {"scene": scene.content_hash, "graph": model.key,
                                                 "needs_360": list(plan.needs_360), "pool": state},
                      {"dual": dataclasses.asdict(config), "grow": bool(grow and pool is not None)})
    name = f"agents-{key.short}"
    if out_dir is None:
        if workspace is None:
            raise OmniscsError("agents_stage needs a workspace or an out_dir")
        out_dir = layout.stage_folder(workspace, "agents", scene.scene_id, name)
    out_dir = Path(out_dir)
    manifest = reusable(out_dir, key) if reuse else None
    if manifest is None:
        def make(tmp: Path) -> dict:
            rows = _complete(scene, plan, model, pool, config, grow, tmp, name, progress)
            atomic_write_json(tmp / "catalog_rows.json", rows)
            return {"checkpoint": ".", "decisions": DECISIONS, "catalog_rows": "catalog_rows.json"}

        produce(out_dir, key, make)

    rows = read_own_json(out_dir / "catalog_rows.json",
                         f"the stage folder {out_dir} is damaged; remove it and run again",
                         expect=list)
    return StageRecord("agents", scene.scene_id, str(out_dir), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest, rows={"agent_models": rows},
                       info={"status": "fitted", "metrics": model.info.get("metrics"), "fit_path": model.path,
                             "strategies": {str(r["track_id"]): r["strategy"] for r in rows if r["needs_360"]},
                             "grew_pool": [r["added_to_pool"] for r in rows if r["added_to_pool"]]})


def _complete(scene, plan: ScenePlan, model: StageRecord, pool, config, grow: bool, out: Path, name: str,
              progress: Progress) -> list[dict]:
    progress(0, 3, f"agents of {scene.scene_id}: dual strategy for {list(plan.needs_360)}")
    graph = load_graph(model.path, scene)
    p = Pool(pool) if pool is not None else None
    completed, decisions = complete_agents(graph, scene, plan.needs_360, plan.train_frames, p, config)
    progress(1, 3, f"agents of {scene.scene_id}: pool growth")
    grown = grow_pool(completed, scene, plan.train_frames, plan.heldout_frames, p, GROWTH_MIN_PSNR, config) \
        if grow and p is not None else {}
    progress(2, 3, f"agents of {scene.scene_id}: checkpoint")
    write_checkpoint_files(completed, out, plan, read_checkpoint_meta(model.path).get("config"),
                           load_metrics(model.path))
    write_decisions(out / DECISIONS, decisions)
    fit_id = Path(model.path).name
    rows = []
    for d in decisions:
        added, _ = grown.get(d.track_id, (None, None))
        rows.append({"scene_id": scene.scene_id, "model_id": name, "fit_model_id": fit_id, "track_id": d.track_id,
                     "strategy": d.strategy, "reason": d.reason, "needs_360": d.track_id in plan.needs_360,
                     "pool_path": None if pool is None else str(Path(pool).resolve()), "pool_model_id": d.model_id,
                     "distance": d.distance, "clarity": None if d.clarity is None else d.clarity.score,
                     "coverage": None if d.clarity is None else d.clarity.coverage_mirrored,
                     "mirrored": d.mirrored, "added_to_pool": added,
                     "n_gaussians": len(completed.agent(d.track_id).gaussians)})
    progress(3, 3, f"agents of {scene.scene_id}: done")
    return rows
