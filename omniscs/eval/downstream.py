"""Driving models on generated datasets: planning examples from a dataset's variants (the ego on its solution) and
from the logs they came from, fine-tuning the proxy planner on them, evaluating a planner on them, and the rows of
the ``downstream_models`` and ``evaluations`` catalog tables.

A dataset (``datasets/<id>/``) holds one scene store per behaviour variant with ``variant.json`` (the variant and
the ego's solution). A solved variant gives one example at its now step (the 3 s after it are the variant's
future); an unsolved one is a test case without a planning target and gives none. The logs are the source scene
stores the dataset names (``scene_ids``), read from the workspace."""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from omniscs.annotate.dataset import CARD_JSON
from omniscs.annotate.variant import VARIANT_JSON
from omniscs.errors import ValidationError
from omniscs.eval.planning import HORIZONS
from omniscs.eval.scenarios import (PlanningExample, planning_examples, scenario_from_traffic, scenario_from_variant,
                                   variant_keyframes)
from omniscs.scene import load_scene
from omniscs.scs.behavior import traffic_from_scene
from omniscs.untrusted import read_own_json

log = logging.getLogger(__name__)


def dataset_card(dataset_path: str | Path) -> dict:
    path = Path(dataset_path) / CARD_JSON
    if not path.exists():
        raise ValidationError(f"{dataset_path} is not a dataset (it has no {CARD_JSON}); build one with omniscs "
                              "generate")
    return read_own_json(path, "the dataset card is damaged; build the dataset again", expect=dict,
                         error=ValidationError)


def variant_examples(dataset_path: str | Path) -> tuple[list[PlanningExample], dict]:
    """The behaviour-SCS examples of a dataset (``variant_keyframes`` of each solved variant: its now step and the
    keyframes after it with at least 1 s of known future) and counts."""
    root = Path(dataset_path)
    card = dataset_card(root)
    out, counts = [], {"variants": 0, "unsolved": 0, "too_short": 0}
    for v in card.get("variants", []):
        counts["variants"] += 1
        store_path = root / "scenes" / v["store_id"]
        meta = read_own_json(store_path / VARIANT_JSON, f"dataset {card.get('dataset_id')} is damaged; build it "
                             "again", expect=dict, error=ValidationError)
        solution = meta.get("ego_solution") or {}
        if not solution.get("solved"):
            counts["unsolved"] += 1
            continue
        store = load_scene(store_path)
        categories = {int(t): str(c) for t, c in store.boxes.groupby("track_id").category.first().items()}
        spec = meta["variant"]
        missing = [int(k) for k in spec["agents"] if int(k) not in categories]
        categories.update({k: "car" for k in missing})  # tracks the variant added without a box in the store
        scenario = scenario_from_variant(spec, categories, ego=np.asarray(solution["trajectory"], np.float64),
                                         drivable=traffic_from_scene(store).map)
        got = variant_keyframes(scenario, int(spec["now_step"]))
        counts["too_short"] += 0 if got else 1
        out += got
    return out, counts


def log_examples(scene_paths: list[str | Path]) -> list[PlanningExample]:
    """Planning examples of logs (scene stores), one every 0.5 s."""
    out = []
    for path in scene_paths:
        out += planning_examples(scenario_from_traffic(traffic_from_scene(load_scene(path))))
    return out


def planner_rows(eval_id: str, model_id: str, dataset_id: str | None, split: str, metrics: dict) -> list[dict]:
    """``evaluations`` rows of one planning evaluation (``omniscs.eval.planning.evaluate_planning``'s output)."""
    rows = []
    known = metrics.get("known_per_step")
    for convention in ("uniad", "stp3"):
        for metric, key in (("L2", "L2"), ("collision", "obj_box_col"), ("collision_known", "obj_box_col_known")):
            for horizon, value in metrics[convention][key].items():
                if known is not None and known[HORIZONS[horizon]] == 0:
                    value = np.nan  # no keyframe knows its truth that far ahead: no number, not a perfect 0
                rows.append({"eval_id": eval_id, "model_id": model_id, "dataset_id": dataset_id, "task": "planning",
                             "split": split, "metric": metric, "class_name": "", "horizon": horizon,
                             "convention": convention, "value": float(value) if np.isfinite(value) else None,
                             "n": int(metrics["n_samples"]), "status": "ok", "error": None})
    return rows


#: ``evaluations.convention`` of detection scores counting only the boxes a camera sees (``score_detections``);
#: nuScenes' own scoring (all round) has none.
CAMERA_VIEW = "camera_view"


def detection_rows(eval_id: str, model_id: str, dataset_id: str | None, split: str, metrics: dict) -> list[dict]:
    """``evaluations`` rows of one detection evaluation (``omniscs.eval.detector.evaluate_detector``'s output): mAP,
    NDS and the AP of every class the set holds; scored in the cameras' view, their convention is ``CAMERA_VIEW``."""
    convention = CAMERA_VIEW if metrics.get("camera_view") else ""

    def row(metric: str, value: float, class_name: str = "") -> dict:
        return {"eval_id": eval_id, "model_id": model_id, "dataset_id": dataset_id, "task": "detection",
                "split": split, "metric": metric, "class_name": class_name, "horizon": "", "convention": convention,
                "value": float(value) if np.isfinite(value) else None, "n": int(metrics["n_samples"]), "status": "ok",
                "error": None}

    return [row("mAP", metrics["mAP"]), row("NDS", metrics["NDS"])] + [row("AP", v, c)
                                                                       for c, v in sorted(metrics["AP"].items())]


def failed_row(eval_id: str, model_id: str, dataset_id: str | None, task: str, split: str, error: str,
               convention: str = "") -> dict:
    return {"eval_id": eval_id, "model_id": model_id, "dataset_id": dataset_id, "task": task, "split": split,
            "metric": "run", "class_name": "", "horizon": "", "convention": convention, "value": None, "n": None,
            "status": "failed", "error": error}


def external_rows(eval_id: str, model_id: str, dataset_id: str | None, parsed: dict) -> list[dict]:
    """``evaluations`` rows of what an external UniAD evaluation printed (``external.parse_uniad_output``)."""
    rows = []

    def row(task, split, metric, value, class_name="", horizon="", convention=""):
        rows.append({"eval_id": eval_id, "model_id": model_id, "dataset_id": dataset_id, "task": task, "split": split,
                     "metric": metric, "class_name": class_name, "horizon": horizon, "convention": convention,
                     "value": float(value) if value is not None and np.isfinite(value) else None, "n": None,
                     "status": "ok", "error": None})

    det = parsed.get("detection")
    if det:
        for name in ("mAP", "NDS", "mATE", "mASE", "mAOE", "mAVE", "mAAE"):
            if name in det:
                row("detection", "external", name, det[name])
        for cls, values in det.get("classes", {}).items():
            for name, value in values.items():
                row("detection", "external", name, value, class_name=cls)
    plan = parsed.get("planning")
    if plan:
        names = {"L2": "L2", "obj_box_col": "collision", "obj_col": "collision_point"}
        for key, values in plan["per_step"].items():
            for step, value in zip(plan["steps"], values):
                row("planning", "external", names.get(key, key), value, horizon=step,
                    convention=plan["convention"] or "")
    return rows


def content_id(prefix: str, parts: dict) -> str:
    """``<prefix>-<12 hex>`` of a JSON value: the same inputs name the same thing."""
    digest = hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()
    return f"{prefix}-{digest[:12]}"
