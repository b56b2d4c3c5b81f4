"""The plan stage: what one scene needs modelled for the request (``omniscs.plan.make_plan``), computed once,
recorded, catalogued, and read by every later stage."""
from __future__ import annotations

import json
import time
from pathlib import Path

from omniscs.locks import output_lock
from omniscs.nsg.config import fit_preset
from omniscs.pipeline import layout
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.request import SceneRequest
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.plan import PlanConfig, ScenePlan, make_plan
from omniscs.scene import load_scene
from omniscs.scs.behavior import adversarial_preset, traffic_from_scene
from omniscs.scs.behavior.checkpoint import load_traffic_model
from omniscs.scs.behavior.problem import now_and_horizon
from omniscs.storage import atomic_write_text
from omniscs.untrusted import read_own_json

#: Bump when the code changes what the stage writes (older outputs are then not reused).
PLAN_VERSION = 1
#: The plan file in a plan stage's folder.
PLAN_JSON = "plan.json"


def plan_config_for(request: SceneRequest) -> PlanConfig:
    """The plan's thresholds and Gaussian budget: the fit preset's when a graph is fitted, else the defaults."""
    if request.fit_preset is None:
        return PlanConfig()
    return fit_preset(request.fit_preset).plan


def plan_stage(scene_path: str | Path, request: SceneRequest, workspace: str | Path,
               plan_config: PlanConfig | None = None) -> StageRecord:
    """What this scene needs modelled for the request (``plan.make_plan``), computed once, written to
    ``plans/<scene_id>/plan-<key>/plan.json``, catalogued in ``plans`` and passed to every later stage."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    config = plan_config or plan_config_for(request)
    edits = request.parsed_edits()
    if request.behavior_variants > 0:
        check_behavior_request(scene, request)
    plan = make_plan(scene, edits, config, behavior_variants=request.behavior_variants,
                     fit_nsg=request.fit_preset is not None, annotate=request.annotate,
                     appearance_variants=request.appearance_variants)
    key = StageKey.of("plan", PLAN_VERSION, scene.content_hash, plan.to_dict())
    out = layout.stage_folder(workspace, "plan", scene.scene_id, f"plan-{key.short}")
    with output_lock(out):
        reused = reusable(out, key) is not None
        if not reused:
            produce(out, key, lambda tmp: (atomic_write_text(tmp / PLAN_JSON, plan.to_json() + "\n"),
                                           {"plan": PLAN_JSON})[1])
    row = plan_row(plan, key.short, out / PLAN_JSON, reused)
    return StageRecord("plan", scene.scene_id, str(out / PLAN_JSON), reused=reused,
                       seconds=time.perf_counter() - started, key=key.digest, rows={"plans": [row]},
                       info={"summary": plan.summary(), "stages": dict(plan.stages)})


def check_behavior_request(scene, request: SceneRequest) -> None:
    """A log too short for behaviour variants fails at its plan, before any fitting (the checks the behavior
    stage would make first: the checkpoint loads, the preset exists, the log covers the model's horizon)."""
    now_and_horizon(traffic_from_scene(scene), load_traffic_model(request.behavior_checkpoint).config,
                    adversarial_preset(request.behavior_preset))


def load_plan(record_or_path: StageRecord | str | Path) -> ScenePlan:
    """The plan a plan stage recorded."""
    path = record_or_path.path if isinstance(record_or_path, StageRecord) else record_or_path
    return ScenePlan.from_dict(read_own_json(path, "the workspace is damaged; plan the scene again", expect=dict))


def plan_row(plan: ScenePlan, plan_id: str, path: Path, reused: bool) -> dict:
    """The plan's row of the ``plans`` catalog table."""
    return {"scene_id": plan.scene_id, "plan_id": plan_id, "content_hash": plan.content_hash,
            "agent_nodes": list(plan.agent_nodes), "n_agent_nodes": len(plan.agent_nodes),
            "node_reasons_json": json.dumps({str(k): v for k, v in plan.node_reasons.items()}, sort_keys=True),
            "n_background_tracks": len(plan.background_tracks), "needs_360": list(plan.needs_360),
            "background_repair": list(plan.background_repair), "inserted": list(plan.inserted),
            "cameras": list(plan.cameras), "n_train_frames": len(plan.train_frames),
            "n_heldout_frames": len(plan.heldout_frames), "modelled_area_m2": float(plan.modelled_area_m2),
            "gaussian_budget": int(plan.gaussian_budget),
            "stages": sorted(s for s, on in plan.stages.items() if on), "plan_path": str(path), "reused": reused}


