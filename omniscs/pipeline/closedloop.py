"""The closed-loop stage: one scenario of the workspace (a scene's log, or one of its behaviour variants) driven by
one policy inside the scene's fitted graph; its run folder under ``closedloop/<eval id>/`` and one
``closed_loop_runs`` catalog row. The ``closed_loop_eval`` flow, the CLI and the benchmark all call it.

Scenario references: ``SCENE_ID`` or ``SCENE_ID/log`` (the log), ``SCENE_ID/VARIANT_ID`` (a variant from the
newest ``variants/SCENE_ID/*/variants.json`` that has it). The graph is the newest checkpoint of the scene among the
fit, agents and background stages (the most complete model), unless one is named."""
from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from omniscs.closedloop.policies import make_policy
from omniscs.closedloop.run import run_episode
from omniscs.closedloop.scenario import log_scenario, variant_scenario
from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator
from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.downstream import content_id
from omniscs.ids import check_id
from omniscs.nsg.checkpoint import load_graph
from omniscs.pipeline import layout
from omniscs.pipeline.records import StageRecord
from omniscs.progress import Progress, no_progress
from omniscs.scene import load_scene
from omniscs.untrusted import read_own_json

log = logging.getLogger(__name__)

#: Stages whose outputs are scene-graph checkpoints, the most complete last.
MODEL_STAGES = ("fit", "agents", "background")


@dataclass(frozen=True)
class ScenarioRef:
    scenario_id: str
    scene_id: str
    variant_id: str | None  # None = the log
    scene_path: Path
    checkpoint: Path
    variants_path: Path | None
    variant: dict | None = None  # the variants.json entry (None = the log)


def parse_ref(ref: str) -> tuple[str, str | None]:
    """``SCENE_ID[/log|/VARIANT_ID]`` -> (scene id, variant id or None)."""
    parts = str(ref).strip().split("/")
    if len(parts) > 2 or not parts[0]:
        raise ValidationError(f"scenario {ref!r}: write SCENE_ID, SCENE_ID/log or SCENE_ID/VARIANT_ID")
    scene_id = check_id("scene id", parts[0])
    variant = None if len(parts) == 1 or parts[1] == "log" else check_id("variant id", parts[1])
    return scene_id, variant


def newest_checkpoint(workspace: str | Path, scene_id: str) -> Path:
    found = [p.parent for stage in MODEL_STAGES
             for p in layout.scene_folder(workspace, stage, scene_id).glob("*/graph.json")]
    if not found:
        raise OmniscsError(f"scene {scene_id} has no fitted scene graph in {workspace}; fit it first "
                           "(omniscs generate, or omniscs fit --out and --checkpoint)")
    return max(found, key=lambda p: (p / "graph.json").stat().st_mtime)


def find_variant(workspace: str | Path, scene_id: str, variant_id: str) -> tuple[Path, dict]:
    files = sorted(layout.scene_folder(workspace, "behavior", scene_id).glob("*/variants.json"),
                   key=lambda p: p.stat().st_mtime, reverse=True)
    for path in files:
        for v in read_own_json(path, "the workspace is damaged; run the behaviour stage again", expect=list):
            if str(v.get("variant_id")) == variant_id:
                return path, v
    raise OmniscsError(f"scene {scene_id} has no behaviour variant {variant_id} in {workspace} "
                       f"({len(files)} variants.json searched); list them in the variants catalog table")


def resolve(workspace: str | Path, ref: str, checkpoint: str | Path | None = None) -> ScenarioRef:
    """Where the scene, its graph and (for a variant) its trajectories are; a clear error for anything missing."""
    scene_id, variant_id = parse_ref(ref)
    scene_path = layout.scene_folder(workspace, "ingest", scene_id)
    if not (scene_path / "manifest.json").is_file():
        raise OmniscsError(f"scene {scene_id} is not in {workspace} (no scenes/{scene_id}); ingest or generate it")
    ckpt = Path(checkpoint) if checkpoint is not None else newest_checkpoint(workspace, scene_id)
    if not (ckpt / "graph.json").is_file():
        raise OmniscsError(f"{ckpt} is not a scene-graph checkpoint (no graph.json)")
    variants_path, variant = find_variant(workspace, scene_id, variant_id) if variant_id else (None, None)
    return ScenarioRef(f"{scene_id}/{variant_id or 'log'}", scene_id, variant_id, scene_path, ckpt, variants_path,
                       variant)


def load_world(ref: ScenarioRef, device: str = "cpu"):
    """(scene, graph, scenario) of a resolved reference."""
    scene = load_scene(ref.scene_path)
    graph = load_graph(ref.checkpoint, scene, device=device)
    dt = _scene_period(scene)
    log_sc = log_scenario(scene, dt=dt)
    if ref.variant is None:
        return scene, graph, log_sc
    return scene, graph, variant_scenario(scene, ref.variant, log_sc)


def _scene_period(scene) -> float:
    ts = scene.frames["timestamp_us"].to_numpy(np.int64)
    return round(float(np.median(np.diff(ts))) / 1e6, 6) if len(ts) > 1 else 0.1


def eval_id_of(policy: str, scenarios: list[str], settings: dict) -> str:
    return content_id("cl", {"policy": policy, "scenarios": sorted(scenarios), "settings": settings})


def run_folder(workspace: str | Path, eval_id: str, scenario_id: str) -> Path:
    return layout.closedloop_folder(workspace, eval_id) / scenario_id.replace("/", "__")


def closed_loop_stage(workspace: str | Path, ref: str, policy: str, eval_id: str, config=None,
                      max_steps: int | None = None, checkpoint: str | Path | None = None,
                      out_dir: str | Path | None = None, progress: Progress = no_progress,
                      epdms=None) -> StageRecord:
    """Drive scenario ``ref`` with ``policy`` (``omniscs.closedloop.policies.make_policy``) and score it; the run
    folder goes under ``out_dir`` when given, else under the workspace's ``closedloop/<eval_id>/``. A user error in
    this scenario (missing scene, graph or variant; a policy that fails) is recorded as a failed row and does not
    stop the evaluation's other scenarios."""
    started = time.perf_counter()
    config = config or ClosedLoopConfig()
    row = {"eval_id": eval_id, "scenario_id": str(ref), "scene_id": str(ref).split("/")[0], "kind": "log",
           "model_id": "-", "policy": policy, "reactive": bool(config.reactive)}
    try:
        resolved = resolve(workspace, ref, checkpoint)
        row.update(scenario_id=resolved.scenario_id, kind="log" if resolved.variant_id is None else "behavior",
                   model_id=resolved.checkpoint.name)
        scene, graph, scenario = load_world(resolved)
        sim = Simulator(graph, scene, config)
        pol = make_policy(policy)
        row["policy"] = getattr(pol, "name", policy)
        out = (Path(out_dir) / resolved.scenario_id.replace("/", "__") if out_dir is not None
               else run_folder(workspace, eval_id, resolved.scenario_id))
        result = run_episode(sim, pol, scenario, max_steps=max_steps, out_dir=out, overwrite=True,
                             progress=progress, epdms=epdms)
    except OmniscsError as exc:
        log.error("closed-loop %s with %s failed: %s", ref, policy, exc)
        row.update(status="failed", error=str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        return StageRecord("closedloop", row["scene_id"], None, seconds=time.perf_counter() - started,
                           rows={"closed_loop_runs": [row]}, info={"status": "failed", "error": row["error"]})
    s = result.summary
    sc = s["scores"]
    row.update(status="ok", reason=s["reason"], steps=int(s["steps"]), simulated_s=float(s["simulated_s"]),
               pdms=sc.get("pdms"), epdms=sc.get("epdms"), hd_score=sc.get("hd_score"),
               route_completion=sc.get("route_completion"),
               no_collision=sc.get("nc_mean"), drivable_compliance=sc.get("dac_mean"),
               time_to_collision=sc.get("ttc_mean"), comfort=sc.get("comfort_mean"), ego_progress=sc.get("ep_mean"),
               collision=bool(sc.get("any_collision")), steps_per_s=float(s["steps_per_s"]),
               run_path=str(result.folder), error=None)
    return StageRecord("closedloop", resolved.scene_id, str(result.folder), seconds=time.perf_counter() - started,
                       rows={"closed_loop_runs": [row]},
                       info={"status": "ok", "scenario_id": resolved.scenario_id, "pdms": row["pdms"],
                             "epdms": row["epdms"],
                             "hd_score": row["hd_score"], "route_completion": row["route_completion"],
                             "reason": row["reason"], "run_path": row["run_path"]})


def settings_of(config, max_steps: int | None) -> dict:
    return {"config": json.loads(json.dumps(asdict(config), default=str)), "max_steps": max_steps}
