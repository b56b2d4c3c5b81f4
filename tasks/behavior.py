"""Task that makes behaviour-level SCS variants of a scene and catalogues them."""
from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.artifacts import create_progress_artifact, update_progress_artifact

from omniscs import catalog
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from omniscs.scs.behavior import adversarial_preset, traffic_from_scene, write_scene_variants
from omniscs.scs.behavior.scene_render import appearance_from_checkpoint


@task(name="behavior-variants", task_run_name="behavior-{ingested[scene_id]}")
def behavior_variants(ingested: dict, workspace: str, run_id: str, n_variants: int,
                      checkpoint: str | None = None, preset: str = "balanced", model: dict | None = None) -> dict:
    """Variants of one scene under ``<workspace>/variants/<scene_id>/`` (variants.json + BEV PNGs) and one new
    file of rows in the ``variants`` table; skipped when the scene's plan does not ask for them. With the
    scene's fitted scene graph (``model``, the fit-nsg task's result) the optimisation includes L_app."""
    scene = load_scene(ingested["path"])
    plan = make_plan(scene, behavior_variants=n_variants)
    out_dir = Path(workspace) / "variants" / scene.scene_id
    if not plan.stages["behavior_variants"]:
        return {"scene_id": scene.scene_id, "path": None, "n_variants": 0, "n_success": 0, "skipped": True}
    artifact = create_progress_artifact(0.0, description=f"behaviour variants of {scene.scene_id}")
    traffic, config = traffic_from_scene(scene), adversarial_preset(preset)
    appearance = None
    if model is not None and model.get("status") == "fitted":
        appearance = appearance_from_checkpoint(model["checkpoint_path"], scene, traffic, checkpoint, config)
    result = write_scene_variants(
        traffic, out_dir, n_variants, checkpoint, config, appearance,
        progress=lambda done, total: update_progress_artifact(artifact, 100.0 * done / total))
    update_progress_artifact(artifact, 100.0)
    catalog.write_rows(catalog.catalog_root(Path(workspace)), "variants", run_id, result.rows,
                       writer=f"behavior-{scene.scene_id}")
    return {"scene_id": scene.scene_id, "path": str(result.variants_json), "n_variants": len(result.rows),
            "n_success": sum(r["success"] for r in result.rows), "skipped": False, "reused": result.reused,
            "appearance_term": appearance is not None}
