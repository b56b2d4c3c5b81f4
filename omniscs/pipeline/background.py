"""The background stage (Prefect-free): after the fit (and the agents stage), the background behind every large
static object the plan's edits move, remove or replace by a smaller object is repaired
(``omniscs.background.repair``) and the repaired scene graph is written as a checkpoint the later stages render
(``repaired/<scene_id>/background-<key>/``), with the objects' nodes still in it, so whichever edit moves or removes
them shows the repaired background. Beside it, ``repair/``: per hole view the hole mask, the filled image and the
depth map, a preview sheet and ``repair.json``; one ``background_repairs`` catalog row per repaired object.

The ``uncovered`` stage (after the variant stages) does the same repair, keyed the same way, for the large static
objects that the drawn variants uncover and the plan could not know of: an appearance variant that replaces a parked
trailer by a sedan (its target is chosen only when the variants are drawn) leaves the rest of the trailer's
footprint empty. The annotate stage composes those variants on the graph this stage repaired, and every other variant
on the graph it was given (the repair's refit also touches the background around the objects, which variants that keep
them show)."""
from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from omniscs.background.depth import SHIPPED, load_depth_model
from omniscs.background.depthnet import WEIGHTS_FILE
from omniscs.background.inpaint import load_inpainter
from omniscs.background.inpaintnet import SHIPPED as INPAINT_SHIPPED, WEIGHTS_FILE as INPAINT_WEIGHTS
from omniscs.background.repair import RepairConfig, repair_background
from omniscs.edits import parse_edits
from omniscs.errors import OmniscsError
from omniscs.nsg.checkpoint import load_graph, load_metrics, read_checkpoint_meta, write_checkpoint_files
from omniscs.nsg.config import FitConfig
from omniscs.nsg.observations import Observations
from omniscs.pipeline import layout
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.plan import PlanConfig, ScenePlan, repair_objects
from omniscs.progress import Progress, no_progress
from omniscs.scene import load_scene
from omniscs.scene.summary import agent_rows
from omniscs.storage import atomic_write_json
from omniscs.untrusted import read_own_json

#: Bumped when the background stage changes what it writes.
BACKGROUND_VERSION = 1

REPAIR_DIR = "repair"
CATALOG_ROWS = "catalog_rows.json"

#: Hole views drawn in the preview sheet.
PREVIEW_VIEWS = 6


def background_stage(scene_path: str | Path, plan: ScenePlan, model: StageRecord | None,
                     workspace: str | Path | None = None, progress: Progress = no_progress,
                     out_dir: str | Path | None = None, config=None, reuse: bool = True) -> StageRecord:
    """The graph of ``model`` (the fit's or the agents stage's record) with the background behind the plan's
    ``background_repair`` objects repaired. Skipped (the record is handed on unchanged by the callers) when there
    is no fitted graph or nothing to repair."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if model is None or model.info.get("status") != "fitted":
        return StageRecord.skip("background", scene.scene_id, "no fitted scene graph to repair")
    if not plan.stages.get("background_repair"):
        return StageRecord.skip("background", scene.scene_id,
                                "no edit moves, removes or shrinks a large static object: nothing to repair")
    return _repaired_record("background", scene, plan, model, plan.background_repair, workspace, progress, out_dir,
                            config, reuse, started)


def uncovered_stage(scene_path: str | Path, plan: ScenePlan, model: StageRecord | None,
                    variants: Sequence[StageRecord | None], workspace: str | Path | None = None,
                    progress: Progress = no_progress, out_dir: str | Path | None = None, config=None,
                    plan_config: PlanConfig = PlanConfig(), reuse: bool = True) -> StageRecord:
    """The graph of ``model`` (the latest graph stage's record) with the background repaired behind the large static
    objects that the edits of the drawn ``variants`` (variant stages' records; their ``variants.json``) uncover, as
    the plan decides for a request's edits (``omniscs.plan.repair_objects``; ``plan_config``: its thresholds), less
    those the background stage already repaired. Keyed like the background stage (the same objects on the same graph
    are one repair), so a rerun reuses it. Skipped when there is no fitted graph or nothing is uncovered."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    if model is None or model.info.get("status") != "fitted":
        return StageRecord.skip("uncovered", scene.scene_id, "no fitted scene graph to repair")
    objects = tuple(t for t in uncovered_objects(scene, variants, plan_config) if t not in plan.background_repair)
    if not objects:
        return StageRecord.skip("uncovered", scene.scene_id,
                                "no variant uncovers what a large static object hid: nothing to repair")
    return _repaired_record("uncovered", scene, plan, model, objects, workspace, progress, out_dir, config, reuse,
                            started)


def variant_edits(variants: Sequence[StageRecord | None]) -> list:
    """Every edit of the variants that ``variants`` (stage records whose path is a ``variants.json``; skipped or
    None ones are passed over) drew, up to the number each was asked for; variants without edits (behaviour
    variants are trajectories) add none."""
    edits = []
    for record in variants:
        if record is None or record.skipped:
            continue
        drawn = read_own_json(record.path, "the stage's variants file is damaged; remove its folder and run again",
                              expect=list)
        # spare candidates (drawn beyond the request, for the quality gates) are not repaired for: the annotate
        # stage leaves out a spare that would uncover an unrepaired object
        drawn = drawn[:int(record.info["n_requested"])] if record.info.get("n_requested") else drawn
        for v in drawn:
            edits += parse_edits(v.get("edits") or [])
    return edits


def uncovered_objects(scene, variants: Sequence[StageRecord | None],
                      plan_config: PlanConfig = PlanConfig()) -> tuple[int, ...]:
    """Track ids of ``scene``'s large static objects whose footprint some edit of ``variants`` uncovers (moved,
    removed, replaced by a smaller object)."""
    agents = {a["track_id"]: a for a in agent_rows(scene)}
    return repair_objects(agents, variant_edits(variants), plan_config)


def variant_uncovers(scene, variant: dict, plan_config: PlanConfig = PlanConfig()) -> tuple[int, ...]:
    """Track ids of ``scene``'s large static objects whose footprint one variant spec's edits uncover."""
    agents = {a["track_id"]: a for a in agent_rows(scene)}
    return repair_objects(agents, parse_edits(variant.get("edits") or []), plan_config)


def _repaired_record(stage: str, scene, plan: ScenePlan, model: StageRecord, objects: tuple[int, ...], workspace,
                     progress: Progress, out_dir, config, reuse: bool, started: float) -> StageRecord:
    """The repair of ``objects`` on ``model``'s graph as ``stage``'s record (made, or reused by its key)."""
    config = config or RepairConfig()
    key = StageKey.of("background", BACKGROUND_VERSION,
                      {"scene": scene.content_hash, "graph": model.key, "objects": list(objects)},
                      {"repair": config.to_dict(), "models": _model_ids(config)})
    name = f"background-{key.short}"
    if out_dir is None:
        if workspace is None:
            raise OmniscsError(f"{stage}_stage needs a workspace or an out_dir")
        out_dir = layout.stage_folder(workspace, "background", scene.scene_id, name)
    out_dir = Path(out_dir)
    manifest = reusable(out_dir, key) if reuse else None
    if manifest is None:
        def make(tmp: Path) -> dict:
            rows = _repair(scene, plan, objects, model, config, tmp, name, progress)
            atomic_write_json(tmp / CATALOG_ROWS, rows)
            return {"checkpoint": ".", "repair": REPAIR_DIR, "catalog_rows": CATALOG_ROWS}

        produce(out_dir, key, make)
    rows = read_own_json(out_dir / CATALOG_ROWS, f"the stage folder {out_dir} is damaged; remove it and run again",
                         expect=list)
    return StageRecord(stage, scene.scene_id, str(out_dir), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest, rows={"background_repairs": rows},
                       info={"status": "fitted", "metrics": model.info.get("metrics"), "fit_path": model.path,
                             "repaired": [r["track_id"] for r in rows]})


def _model_ids(config) -> dict:
    """Which inpainter and depth model the repair uses (their weights decide its output)."""
    depth = load_depth_model(config.depth_model)
    weights = None
    if depth.name == "embedded":  # retrained shipped weights change the repair

        weights = hashlib.sha256((SHIPPED / WEIGHTS_FILE).read_bytes()).hexdigest()
    ids = {"inpainter": load_inpainter(config.inpainter).name, "depth_model": depth.name, "depth_weights": weights}
    if ids["inpainter"] == "embedded":  # so do retrained inpainting weights

        ids["inpaint_weights"] = hashlib.sha256((INPAINT_SHIPPED / INPAINT_WEIGHTS).read_bytes()).hexdigest()
    return ids


def _repair(scene, plan: ScenePlan, objects: tuple[int, ...], model: StageRecord, config, out: Path, name: str,
            progress: Progress) -> list[dict]:
    graph = load_graph(model.path, scene)
    meta_config = read_checkpoint_meta(model.path).get("config")
    fit_config = FitConfig.from_dict(meta_config) if meta_config else FitConfig()
    views = [(c, int(f)) for f in plan.train_frames for c in plan.cameras]
    result = repair_background(graph, Observations(scene, plan.cameras), objects, views, fit_config,
                               config, progress=progress)
    metrics = {**load_metrics(model.path), "background_repair": result.facts}
    write_checkpoint_files(result.graph, out, plan, meta_config, metrics)
    write_repair_files(result, out / REPAIR_DIR, config)
    fit_id = Path(model.path).name
    seconds = float(sum(result.seconds.values()))
    f = result.facts
    return [{"scene_id": scene.scene_id, "model_id": name, "fit_model_id": fit_id, "track_id": int(t),
             "hole_views": f["hole_views"], "hole_pixels": f["hole_pixels"], "observed_pixels": f["observed_pixels"],
             "plane_pixels": f["plane_filled_pixels"], "carried_pixels": f["carried_pixels"],
             "inpainted_pixels": f["inpainted_pixels"],
             "unfilled_pixels": f["unfilled_pixels"], "seeds": f["seeds"], "dropped_gaussians": f["dropped_gaussians"],
             "depth_method": config.depth_method, "refit": config.refit, "seconds": seconds,
             "repair_path": str((out / REPAIR_DIR).name)}
            for t in objects]


def write_repair_files(result, folder: Path, config) -> None:
    """Per hole view: ``<camera>-<frame>-mask.png``, ``-filled.png``, ``-depth.png`` (16-bit, centimetres from the
    camera centre, 0 = unknown); ``preview.png`` (logged | filled | depth of a few views); ``repair.json``."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    views = []
    for hv in result.views:
        stem = f"{hv.camera}-{hv.frame:04d}"
        Image.fromarray((hv.mask * 255).astype(np.uint8)).save(folder / f"{stem}-mask.png")
        Image.fromarray(hv.filled).save(folder / f"{stem}-filled.png")
        cm = np.where(np.isfinite(hv.filled_depth), np.clip(hv.filled_depth * 100.0, 0, 65535), 0).astype(np.uint16)
        Image.fromarray(cm).save(folder / f"{stem}-depth.png")
        views.append({"camera": hv.camera, "frame": hv.frame, "hole_share": hv.hole_share, "observed": hv.observed,
                      "planes": hv.plane_filled, "carried": hv.carried, "inpainted": hv.inpainted,
                      "unfilled": int(hv.unfilled.sum()),
                      "files": [f"{stem}-mask.png", f"{stem}-filled.png", f"{stem}-depth.png"]})
    Image.fromarray(preview_sheet(result.views)).save(folder / "preview.png")
    atomic_write_json(folder / "repair.json", {
        "config": dataclasses.asdict(config), "facts": result.facts, "seconds": result.seconds, "views": views,
        "drnet": None if result.drnet is None else {"depth_scale": result.drnet.depth_scale,
                                                     "history": result.drnet.history}})


def preview_sheet(views) -> np.ndarray:  # [rows * h, 3 * w, 3] uint8
    """Logged image, filled image (hole outlined) and filled depth for up to PREVIEW_VIEWS hole views with the
    largest holes."""
    import cv2

    picked = sorted(views, key=lambda v: -v.hole_share)[:PREVIEW_VIEWS]
    rows = []
    for hv in picked:
        edge = cv2.morphologyEx(hv.mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        filled = hv.filled.copy()
        filled[edge] = (255, 0, 0)
        d = hv.filled_depth
        fin = np.isfinite(d)
        inv = np.zeros(d.shape)
        inv[fin] = 1.0 / np.maximum(d[fin], 0.5)
        scale = np.percentile(inv[fin], 99) if fin.any() else 1.0
        colour = cv2.applyColorMap((np.clip(inv / max(scale, 1e-6), 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        colour = colour[..., ::-1].copy()
        colour[~fin] = 0
        rows.append(np.concatenate([hv.image, filled, colour], 1))
    h = max(r.shape[0] for r in rows)
    return np.concatenate([np.pad(r, ((0, h - r.shape[0]), (0, 0), (0, 0))) for r in rows], 0)
