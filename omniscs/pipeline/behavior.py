"""The behaviour stage: behaviour-level SCS variants of one scene (the traffic model's latents optimised toward
the ego, with L_app rendered by the scene graph when one is fitted)."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from omniscs.errors import OmniscsError
from omniscs.gates import GateConfig
from omniscs.locks import output_lock
from omniscs.pipeline import layout
from omniscs.pipeline.common import result_config, waiting
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.plan import ScenePlan
from omniscs.progress import Progress, no_progress
from omniscs.scene import load_scene
from omniscs.scs.behavior import adversarial_preset, traffic_from_scene
from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT, checkpoint_hash
from omniscs.scs.behavior.scene_render import RenderConsistencyConfig, render_consistency_from_checkpoint
from omniscs.scs.behavior.variants import write_scene_variants
from omniscs.untrusted import read_own_json

#: Bump when the code changes what the stage writes (older outputs are then not reused).
BEHAVIOR_VERSION = 1


def behavior_stage(scene_path: str | Path, plan: ScenePlan, n_variants: int, workspace: str | Path | None = None,
                   preset: str = "balanced", checkpoint: str | Path | None = None, model: StageRecord | None = None,
                   progress: Progress = no_progress, out_dir: str | Path | None = None,
                   adversarial_overrides: dict | None = None, appearance_render=None,
                   reuse: bool = True, gates: GateConfig | None = None, budget: int = 1) -> StageRecord:
    """``n_variants`` behaviour-level SCS variants of the scene (variants.json, one BEV PNG each, ``variants``
    rows) in ``out_dir`` (default ``variants/<scene_id>/behavior-<key>/``). With the scene's fitted graph
    (``model``, the fit stage's record) the optimisation adds L_app rendered by it; that graph's key is part
    of this stage's key, so variants with L_app are reused like any other (unless ``reuse`` is False).
    With ``gates`` (``omniscs.gates``) further adversaries and time windows are tried, up to ``budget`` candidates
    per requested variant, until ``n_variants`` reach their scenario; every candidate is kept with its verdict."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if not plan.stages.get("behavior_variants") or n_variants < 1:
        return StageRecord.skip("behavior", scene.scene_id, "the request asks for no behaviour variants")
    config = adversarial_preset(preset, **(adversarial_overrides or {}))
    ckpt = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
    graph = model if model is not None and model.info.get("status") == "fitted" else None
    render = appearance_render or RenderConsistencyConfig()
    key = StageKey.of("behavior", BEHAVIOR_VERSION,
                      {"scene": scene.content_hash, "plan": plan.to_dict(), "graph": graph.key if graph else None},
                      {"adversarial": result_config(dataclasses.asdict(config)), "checkpoint": checkpoint_hash(ckpt),
                       "n_variants": int(n_variants),
                       "appearance": dataclasses.asdict(render) if graph else None,
                       **({"gates": gates.to_dict(), "budget": int(budget)} if gates is not None else {})})
    if out_dir is None:
        if workspace is None:
            raise OmniscsError("behavior_stage needs a workspace or an out_dir")
        out_dir = layout.stage_folder(workspace, "behavior", scene.scene_id, f"behavior-{key.short}")
    out_dir = Path(out_dir)
    with output_lock(out_dir, waiting(progress, out_dir)):
        manifest = reusable(out_dir, key) if reuse else None
        if manifest is None:
            traffic = traffic_from_scene(scene)
            appearance = (render_consistency_from_checkpoint(graph.path, scene, traffic, ckpt, config, render)
                          if graph is not None else None)

            def make(tmp: Path) -> dict:
                result = write_scene_variants(traffic, tmp, n_variants, ckpt, config, appearance,
                                              progress=progress, published_dir=out_dir, gates=gates,
                                              budget=int(n_variants) * max(1, int(budget)))
                if not result.rows:
                    raise OmniscsError(f"scene {scene.scene_id} has no vehicle besides the ego at the now step; "
                                       "no behaviour variant can be made")
                return {"variants": result.variants_json.name, "catalog_rows": "catalog_rows.json",
                        "bev": [p.name for p in result.bev_pngs]}

            produce(out_dir, key, make)
    rows = read_own_json(out_dir / "catalog_rows.json",
                         f"the stage folder {out_dir} is damaged; remove it and run again",
                         expect=list)
    return StageRecord("behavior", scene.scene_id, str(out_dir / "variants.json"), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest, rows={"variants": rows},
                       info={"n_variants": len(rows), "n_success": sum(bool(r["success"]) for r in rows),
                             "n_requested": int(n_variants),
                             "n_passed": sum(r.get("passed_gates") is not False for r in rows),
                             "appearance_term": graph is not None})


