"""The detection half of the paper's downstream protocol (its Tables 3 and 6) on this machine, with the embedded
proxy camera detector (``omniscs.eval.detector``) standing in for UniAD's perception.

Data (procedural, rendered, all through the factory's own stages):
  - train: procedural logs (``train_scenes``) and their appearance-SCS variants: objects of a pool built from the
    library's pool split (``object_kinds``, indices ``train_objects``) replacing vehicles or inserted upright, on their
    side and overturned (the ``appearance`` and ``annotate`` stages, fast scene graphs), as the dataset
    ``det-scs-train-<size>-<digest of its logs>``;
  - test: held-out logs (``test_scenes``) with held-out objects (indices ``test_objects`` of the same kinds, none in
    the training pool): the appearance-SCS test set ``det-scs-test-...``, and the original test set (the logs themselves).
  - validation: other held-out logs (``val_scenes``) with other held-out objects (``val_objects``): the fine-tuning
    setting is chosen there among ``candidates``, never on a test set;
  - earlier test (``earlier_test_scenes``): the test logs of the protocol's first version, on which it was shaped;
    reported apart from the fresh test set.
Each set is exported as a nuScenes dataroot. *Base* is the shipped proxy detector (trained on other procedural logs
without SCS); *fine-tuned* starts from base and trains on the train logs and their appearance-SCS variants, together
with base's own training logs (``rehearse``). Both are
evaluated on both test sets with nuScenes' mAP and NDS over the classes each test set holds."""
from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from omniscs.annotate.dataset import CARD_JSON
from omniscs.bench.detector_logs import VERSION as SHIPPED_VERSION, ShippedDetectorConfig, procedural_dataroot
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.errors import ValidationError
from omniscs.eval.detection import DetectionConfig, bootstrap_map_difference, filter_boxes
from omniscs.eval.detector import (
    DEFAULT_DETECTOR,
    WEIGHTS,
    DetectorTrainConfig,
    evaluate_detector,
    load_detector,
    save_detector,
    score_detections,
    train_detector,
    training_set,
)
from omniscs.eval.nuscenes_io import NuScenesTables, evaluated_classes, evaluated_ground_truth, load_results
from omniscs.pipeline import layout
from omniscs.pipeline.downstream import DETECTOR_VERSION, export_dataroot
from omniscs.pipeline.pool import pool_asset_stage
from omniscs.pipeline.request import SceneRequest
from omniscs.pipeline.stages import dataset_stage, run_scene
from omniscs.progress import Progress, no_progress
from omniscs.scene import SyntheticSource
from omniscs.storage import workspace_root
from omniscs.world.assets import list_asset_ids

log = logging.getLogger(__name__)

VERSION = DETECTOR_VERSION  # the dataroots the protocol exports and reads
#: Split -> the names of its appearance-SCS set and of its logs' set.
SET_NAMES = {"val": ("validation appearance-SCS", "validation logs"),
             "test": ("appearance-SCS test", "original test"),
             "earlier test": ("earlier appearance-SCS test", "earlier original test")}


@dataclass(frozen=True)
class DetectionProtocolConfig:
    train_scenes: tuple[str, ...] = ("straight:7201", "t_junction:7202", "intersection:7203", "straight:7204")
    """Training logs (template:seed); no other benchmark uses these seeds."""
    val_scenes: tuple[str, ...] = ("straight:7401", "t_junction:7402", "intersection:7403")
    """Validation logs: the fine-tuning setting is chosen on them and their variants (empty: the first candidate)."""
    test_scenes: tuple[str, ...] = ("straight:7601", "t_junction:7602", "intersection:7603", "straight:7604",
                                    "t_junction:7605", "intersection:7606")
    """Held-out logs of both test sets (fresh: never looked at while the protocol was shaped)."""
    earlier_test_scenes: tuple[str, ...] = ("straight:7301", "t_junction:7302", "intersection:7303", "straight:7501",
                                            "t_junction:7502", "intersection:7503", "straight:7504", "t_junction:7505",
                                            "intersection:7506")
    """The test logs of the protocol's earlier versions (7301-7303 its first, 7501-7506 its second), looked at while
    it was shaped: reported apart (empty: none)."""
    n_frames: int = 30
    preset: str = "fast"
    """Fit preset of the scene graphs the variants are rendered through."""
    appearance_variants: int = 16
    """Appearance variants per training scene (8 with objects 0-6 alone gained less on validation:
    reports/detection_4x8_train_data)."""
    test_variants: int = 4
    """Appearance variants per test scene (the appearance-SCS test set)."""
    object_kinds: tuple[str, ...] = ("box_truck", "bus", "excavator", "wheel_loader", "trailer", "sedan", "suv")
    """Library kinds the SCS objects come from (pool split)."""
    train_objects: tuple = ((0, 6), (10, 16))
    """Pool-split index range per kind of the training objects ((start, stop), or several such ranges)."""
    test_objects: tuple[int, int] = (6, 8)
    """... and of the held-out test objects (disjoint from the training ones)."""
    val_objects: tuple[int, int] = (8, 10)
    """... and of the validation objects (disjoint from both)."""
    finetune: DetectorTrainConfig = field(default_factory=lambda: DetectorTrainConfig(steps=1200, lr=1e-3, seed=1))
    """Fine-tuning from the shipped weights: the settings every candidate shares."""
    candidates: tuple[dict, ...] = field(default_factory=lambda: (
        {}, {"class_balance": 0.5}, {"class_balance": 1.0}, {"class_balance": 0.5, "lr": 5e-4}))
    """Fine-tuning candidates (``DetectorTrainConfig`` fields over ``finetune``). The one kept gains most mAP on the
    validation appearance-SCS set among those losing at most ``map_regression_limit`` on the validation logs (none
    such: the one losing least)."""
    rehearse: bool = True
    """Fine-tune on the base detector's own training images too (the shipped detector's procedural logs,
    ``omniscs.training.detector``), as the paper fine-tunes on the original training set plus the SCS data: trained
    on a few logs and their variants alone, a detector forgets what it knew."""
    map_gain_target: float = 0.05
    """Fine-tuned must gain this much mAP (0.05 = 5 points) on the appearance-SCS test set ..."""
    map_regression_limit: float = 0.01
    """... and lose at most this much on the original test set."""
    camera_view: bool = True
    """Score only the boxes a camera sees (``nuscenes_io.in_camera_view``): the rig's three front cameras leave about
    half of the boxes nuScenes' filter keeps (within range, with LiDAR points) behind the ego, where no camera
    detector can find them. The all-round scores (nuScenes' filter alone) are reported beside them."""

    def __post_init__(self):
        ranges = {k: _spans(getattr(self, f"{k}_objects")) for k in ("train", "val", "test")}
        for k, spans in ranges.items():
            if any(not 0 <= a < b for a, b in spans):
                raise ValidationError(f"{k}_objects must be index ranges (start, stop) with 0 <= start < stop; "
                                      f"got {getattr(self, f'{k}_objects')}")
        used = {k: {i for a, b in spans for i in range(a, b)} for k, spans in ranges.items()}
        for a, b in (("train", "val"), ("train", "test"), ("val", "test")):
            if used[a] & used[b]:
                raise ValidationError(f"{a}_objects and {b}_objects share pool indices {sorted(used[a] & used[b])}: "
                                      "held-out objects must not be trained on")
        if not self.candidates:
            raise ValidationError("name at least one fine-tuning candidate")


def quick_config() -> DetectionProtocolConfig:
    """A smoke run: one train and one test scene, two variants, a few steps (not a measurement)."""
    return DetectionProtocolConfig(train_scenes=("straight:7201",), val_scenes=(), test_scenes=("straight:7301",),
                                   earlier_test_scenes=(), n_frames=12, appearance_variants=2, test_variants=2,
                                   object_kinds=("box_truck", "sedan"), train_objects=(0, 3),
                                   finetune=DetectorTrainConfig(steps=5, batch_size=4, seed=1),
                                   candidates=({}, {"class_balance": 1.0}), rehearse=False)


def _spans(spans) -> tuple[tuple[int, int], ...]:
    """Index ranges as a tuple of (start, stop) pairs; one (start, stop) pair is one range."""
    spans = tuple(spans)
    return (tuple(spans),) if len(spans) == 2 and all(isinstance(x, int) for x in spans) else \
        tuple(tuple(x) for x in spans)


def _pool(workspace: Path, name: str, kinds, spans) -> tuple[Path, list[str]]:
    """The pool ``pool-<name>`` of the library's pool-split assets of ``kinds`` at the index ranges ``spans``."""
    root = workspace / "bench-downstream" / f"pool-{name}"
    ids = [a for k in kinds for start, stop in _spans(spans) for a in list_asset_ids(k, "pool")[start:stop]]
    return root, [pool_asset_stage(a, root).info["model_id"] for a in ids]


def split_dataset_id(split: str, scenes, n_variants: int) -> str:
    """The appearance-SCS dataset of a split, named by the split, its size and a digest of its logs
    (``det-scs-test-6x4-<digest>``): a split with other logs is another dataset, and never replaces one that
    results were made from."""
    digest = hashlib.sha1(json.dumps(list(scenes)).encode()).hexdigest()[:8]
    return f"det-scs-{split}-{len(scenes)}x{n_variants}-{digest}"


def check_dataset_free(workspace: Path, dataset_id: str, scene_ids: set[str]) -> None:
    """A clear error when the workspace's dataset ``dataset_id`` holds other scenes than ``scene_ids`` (the ids
    name the logs, so only a changed scene id of the same log gets here): replacing that dataset would leave every
    result made from it unreproducible."""
    card = layout.dataset_folder(workspace, dataset_id) / CARD_JSON
    if not card.is_file():
        return
    held = {v["scene_id"] for v in json.loads(card.read_text()).get("variants", [])}
    if held and held != set(scene_ids):
        raise ValidationError(f"dataset {dataset_id} in {workspace} already holds other scenes ({len(held)}: "
                              f"{sorted(held)[0]}, ...); this split ({len(scene_ids)} scenes) would replace it. "
                              "Use another workspace, or give the split a different size")


def build_split(split: str, scenes, pool: Path, objects: list[str], config: DetectionProtocolConfig, workspace: Path,
                progress: Progress = no_progress) -> dict:
    """The split's logs (scene store paths) and its appearance-SCS dataset (the factory's stages; reused)."""
    n_variants = config.appearance_variants if split == "train" else config.test_variants
    request = SceneRequest(fit_preset=config.preset, previews=False, appearance_variants=n_variants,
                           pool=str(pool), appearance_objects=tuple(objects), annotate=True)
    logs, annotated = [], []
    for i, item in enumerate(scenes):
        progress(i, len(scenes), f"{split} scene {item}: fit, appearance variants, render + annotate")
        template, _, seed = item.partition(":")
        records = run_scene(SyntheticSource(template, int(seed), "day", config.n_frames, 3, 480, 270), request,
                            workspace)
        logs.append(records[0].path)
        annotated.append(next(r for r in records if r.stage == "annotate"))
    dataset_id = split_dataset_id(split, scenes, n_variants)
    check_dataset_free(workspace, dataset_id, {r.scene_id for r in annotated})
    dataset = dataset_stage(annotated, workspace, dataset_id, {"protocol": "detection", "split": split})
    stores = sorted(str(p) for p in (Path(dataset.path) / "scenes").iterdir() if p.is_dir())
    return {"logs": logs, "scs": stores, "dataset": dataset.path}


def _export(stores: list[str], root: Path, name: str, keyframe_every: int | None = None) -> Path:
    """The stores as one nuScenes dataroot ``root/name-<digest of the stores>`` (``keyframe_every`` None: the 2 Hz
    keyframes the protocol evaluates; training sets take every frame, as the shipped detector's training did); made
    once, reused by later runs."""
    digest = hashlib.sha1(json.dumps([sorted(stores), keyframe_every]).encode()).hexdigest()[:10]
    out = root / f"{name}-{digest}"
    if not (out / VERSION / "sample.json").is_file():
        export_dataroot(stores, out, keyframe_every)
    return out


def _fine_tuned(root: Path, tuning_set: list, train_config, base, images, progress: Progress):
    """``base`` fine-tuned on ``tuning_set`` with ``train_config`` (``images``: a callable giving the read images),
    kept under ``root/tuned-<digest>`` and loaded from there by a later run with the same data, settings and base."""
    key = json.dumps([[str(r), v] for r, v in tuning_set] + [asdict(train_config)], sort_keys=True)
    key += hashlib.sha1((DEFAULT_DETECTOR / WEIGHTS).read_bytes()).hexdigest()
    folder = root / f"tuned-{hashlib.sha1(key.encode()).hexdigest()[:12]}"
    if (folder / "training.json").is_file():
        return load_detector(folder), json.loads((folder / "training.json").read_text())
    model, record = train_detector(tuning_set, train_config, init=base, data=images(), progress=progress)
    save_detector(model, folder, record, overwrite=True)
    return model, record


def choose_candidate(val: list[dict], regression_limit: float) -> int:
    """Index of the kept fine-tuning candidate among ``val`` (per candidate its validation ``scs_gain`` and
    ``logs_change`` in mAP): the largest gain among those losing at most ``regression_limit`` on the logs; when none
    does, the one losing least."""
    if not val:
        raise ValueError("no candidate to choose from")
    within = [i for i, v in enumerate(val) if v["logs_change"] >= -regression_limit]
    if within:
        return max(within, key=lambda i: (val[i]["scs_gain"], val[i]["logs_change"]))
    return max(range(len(val)), key=lambda i: val[i]["logs_change"])


def gain_interval(dataroot: Path, base_results: Path, tuned_results: Path, n: int = 200, seed: int = 0,
                  camera_view: bool = False) -> dict | None:
    """The mAP gain of fine-tuned over base on one test set with its 95 % interval from resampling the set's scenes
    (``omniscs.eval.detection.bootstrap_map_difference``), over the classes the set holds (``camera_view``: only the
    boxes a camera sees, as ``score_detections``); None for a set of one scene."""
    tables = NuScenesTables.load(dataroot, VERSION)
    if len(tables["scene"]) < 2:
        return None
    groups = {t: scene["name"] for scene in tables["scene"].values() for t in tables.scene_samples([scene["name"]])}
    samples = tables.scene_samples()
    gt, racks = evaluated_ground_truth(tables, samples, camera_view)
    config = DetectionConfig(class_names=evaluated_classes(gt, racks))
    preds = [filter_boxes(load_results(p, tables, samples, config, camera_view)[0], config, racks)
             for p in (base_results, tuned_results)]
    return bootstrap_map_difference(filter_boxes(gt, config, racks), *preds, groups, config, n, seed)


def _data(config: DetectionProtocolConfig, ws: Path, root: Path, progress: Progress) -> tuple[dict, dict, dict]:
    """(pools, splits, dataroots): each split's pool, logs and appearance-SCS dataset (the factory's stages), and the
    sets the protocol trains and evaluates on, exported as nuScenes dataroots (all reused when made before)."""
    objects = {"train": config.train_objects, "val": config.val_objects, "test": config.test_objects}
    scenes = {"train": config.train_scenes, "val": config.val_scenes, "test": config.test_scenes,
              "earlier test": config.earlier_test_scenes}
    pool_of = {"train": "train", "val": "val", "test": "test", "earlier test": "test"}
    pools = {s: _pool(ws, s, config.object_kinds, objects[s]) for s in sorted({pool_of[k] for k in scenes if scenes[k]})}
    splits = {k: build_split("test" if k == "earlier test" else k, scenes[k], *pools[pool_of[k]], config, ws, progress)
              for k in scenes if scenes[k]}
    roots = {"train logs": _export(splits["train"]["logs"], root, "train-logs", 1),
             "train appearance-SCS": _export(splits["train"]["scs"], root, "train-scs", 1)}
    for k, (scs_name, logs_name) in SET_NAMES.items():
        if k in splits:
            roots[scs_name] = _export(splits[k]["scs"], root, f"{k.replace(' ', '-')}-scs")
            roots[logs_name] = _export(splits[k]["logs"], root, f"{k.replace(' ', '-')}-logs")
    if config.rehearse:
        shipped = ShippedDetectorConfig()
        progress(0, None, "the base detector's training logs (for rehearsal)")
        roots["base training logs"] = procedural_dataroot(ws, "train", shipped, shipped.train_keyframe_every, progress)
    return pools, splits, roots


def _results_path(root: Path, roots: dict, model: str, name: str) -> Path:
    return root / f"results-{model}-{name.replace(' ', '_')}-{roots[name].name}.json"


def _choose_fine_tuning(config: DetectionProtocolConfig, root: Path, roots: dict, base, tuning_set: list,
                        progress: Progress) -> tuple[list[dict], int, object, dict]:
    """(candidates' validation rows, the kept one's index, its model, its training record): each candidate of
    ``config.candidates`` fine-tuned from ``base`` (or reused) and scored on the validation sets; without validation
    sets the first candidate is kept."""
    read: dict[tuple, object] = {}  # the fine-tuning images, read once per annotation filter the candidates use

    def images_for(train_config) -> object:
        key = tuple(getattr(train_config, f) for f in ("max_depth_m", "near_m", "min_visibility", "require_points"))
        if key not in read:
            progress(0, None, "reading the fine-tuning images")
            read.clear()
            read[key] = training_set(tuning_set, base.config, train_config)
        return read[key]

    scs_set, logs_set = SET_NAMES["val"]
    base_val = {n: evaluate_detector(base, roots[n], VERSION, _results_path(root, roots, "base", n),
                                     camera_view=config.camera_view)["mAP"]
                for n in (scs_set, logs_set) if n in roots}
    candidates, best = [], None
    for i, overrides in enumerate(config.candidates):
        train_config = replace(config.finetune, **overrides)
        progress(i, len(config.candidates), f"fine-tuning candidate {i + 1} of {len(config.candidates)}: {overrides}")
        model, record = _fine_tuned(root, tuning_set, train_config, base, lambda: images_for(train_config), progress)
        row = {"overrides": dict(overrides), "seconds": float(record["seconds"])}  # the training's, also when reused
        if not base_val:  # nothing to choose on: the first candidate is kept
            return [row], 0, model, record
        val = {n: evaluate_detector(model, roots[n], VERSION, _results_path(root, roots, f"candidate{i}", n),
                                    camera_view=config.camera_view)["mAP"]
               for n in (scs_set, logs_set)}
        row.update(scs_base=base_val[scs_set], scs_tuned=val[scs_set], scs_gain=val[scs_set] - base_val[scs_set],
                   logs_base=base_val[logs_set], logs_tuned=val[logs_set],
                   logs_change=val[logs_set] - base_val[logs_set])
        candidates.append(row)
        if choose_candidate(candidates, config.map_regression_limit) == i:  # keep only the best so far in memory
            best = (model, record)
    return candidates, choose_candidate(candidates, config.map_regression_limit), *best


def run_detection_protocol(out_dir: str | Path, workspace: str | Path | None = None,
                           config: DetectionProtocolConfig = DetectionProtocolConfig(),
                           progress: Progress = no_progress) -> dict:
    machine = machine_info()
    ws = workspace_root(workspace)
    root = ws / "bench-downstream" / "detection"
    started = time.perf_counter()
    pools, splits, roots = _data(config, ws, root, progress)
    data_s = time.perf_counter() - started
    base = load_detector()
    base_record = json.loads((DEFAULT_DETECTOR / "training.json").read_text())
    tuning_set = [(roots["train logs"], VERSION), (roots["train appearance-SCS"], VERSION)]
    if config.rehearse:
        tuning_set.append((roots["base training logs"], SHIPPED_VERSION))
    candidates, kept, tuned, tune_record = _choose_fine_tuning(config, root, roots, base, tuning_set, progress)
    rows, intervals, all_round, all_round_intervals = {}, {}, {}, {}
    for name in [n for n in SET_NAMES["test"] + SET_NAMES["earlier test"] if n in roots]:
        paths = {m: _results_path(root, roots, m, name) for m in ("base", "fine-tuned")}
        rows[name] = {m: evaluate_detector(model, roots[name], VERSION, paths[m], camera_view=config.camera_view)
                      for m, model in (("base", base), ("fine-tuned", tuned))}
        progress(0, None, f"{name}: resampling its scenes for the gain's interval")
        intervals[name] = gain_interval(roots[name], paths["base"], paths["fine-tuned"],
                                        camera_view=config.camera_view)
        if config.camera_view:  # the same detections scored all round (nuScenes' filter alone)
            all_round[name] = {m: score_detections(roots[name], VERSION, paths[m]) for m in paths}
            all_round_intervals[name] = gain_interval(roots[name], paths["base"], paths["fine-tuned"])
    summary = {**_summary(rows, config), "intervals": intervals}
    if all_round:
        summary["all_round"] = {**_summary(all_round, config), "intervals": all_round_intervals}
    report = {"config": asdict(config), "machine": finish(machine), "rows": rows, "all_round_rows": all_round,
              "summary": summary,
              "candidates": candidates, "kept": kept,
              "pools": {s: {"path": str(p), "models": m} for s, (p, m) in pools.items()},
              "datasets": {s: splits[s]["dataset"] for s in splits}, "dataroots": {k: str(v) for k, v in roots.items()},
              "seconds": {"data": data_s, "finetune": candidates[kept]["seconds"],
                          "all": time.perf_counter() - started},
              "base_training": {k: base_record.get(k) for k in ("command", "data", "seconds", "train_config")},
              "finetune_training": {k: tune_record.get(k) for k in ("n_images", "n_boxes", "seconds", "train_config",
                                                                     "draws_showing_class")}}
    write_report(out_dir, "downstream", report, markdown(report), {"": lambda f: _plot(report, f)}, part="detection")
    return report


def _summary(rows: dict, config: DetectionProtocolConfig) -> dict:
    """The gain on the appearance-SCS test set and the change on the original one, against the targets."""
    scs, orig = rows["appearance-SCS test"], rows["original test"]
    gain = scs["fine-tuned"]["mAP"] - scs["base"]["mAP"]
    change = orig["fine-tuned"]["mAP"] - orig["base"]["mAP"]
    return {"scs_map_gain": gain, "original_map_change": change, "meets_gain_target": gain >= config.map_gain_target,
            "meets_regression_limit": change >= -config.map_regression_limit}


def markdown(r: dict) -> str:
    c, s, ft = r["config"], r["summary"], r["finetune_training"]
    lines = ["# Downstream benchmark: the detection protocol with the proxy camera detector", "", load_line(r["machine"]),
             "", "The detector is the embedded **proxy** (`omniscs.eval.detector`: a small CenterNet-style camera network "
             "trained here), not UniAD's perception: these numbers show the protocol running end to end on this "
             "machine, not what UniAD would do.", "",
             f"Data: {len(c['train_scenes'])} train logs ({', '.join(c['train_scenes'])}), "
             f"{len(c['val_scenes'])} validation logs ({', '.join(c['val_scenes']) or 'none'}) and "
             f"{len(c['test_scenes'])} held-out test logs ({', '.join(c['test_scenes'])}), {c['n_frames']} frames, "
             f"3 cameras; {c['appearance_variants']} appearance variants per train log and {c['test_variants']} per "
             f"validation or test log (objects of kinds {', '.join(c['object_kinds'])} from the library's pool split: "
             f"train indices {c['train_objects']}, validation objects {c['val_objects']}, held-out test objects "
             f"{c['test_objects']}), fast scene graphs. Base: the shipped proxy detector "
             f"(`{r['base_training'].get('command')}`); fine-tuned: from base, {ft['train_config']['steps']} steps "
             f"(class balance {ft['train_config'].get('class_balance', 0)}) on the train logs and their "
             "appearance-SCS variants"
             + (" together with the base detector's own training logs (rehearsal, as the paper fine-tunes on the "
                "original training set plus SCS data)" if c.get("rehearse") else "")
             + f" ({ft.get('n_images')} images). mAP and NDS over the classes each test set holds."
             + (" The test logs are fresh: the protocol was shaped on the earlier test logs "
                f"({', '.join(c['earlier_test_scenes'])}), reported below apart." if c['earlier_test_scenes'] else ""),
             ""]
    camera = c.get("camera_view", False)
    if camera:
        lines += ["Scored on the boxes a camera sees (a point of the box in front of a camera and inside its image; "
                  "`nuscenes_io.in_camera_view`): the rig's three front cameras leave about half of the boxes "
                  "nuScenes' filter keeps (within range, with LiDAR points) behind the ego, where no camera detector "
                  "can find them; nuScenes' six cameras look all round, so its protocol needs no such filter. The "
                  "same detections scored all round (nuScenes' filter alone) follow.", ""]
    lines += [_headline(r["rows"], s, c, "in the cameras' view" if camera else ""), ""]
    if r.get("all_round_rows"):
        lines += [_headline(r["all_round_rows"], s["all_round"], c, "all round"), ""]
    classes = sorted({k for rows in r["rows"].values() for m in rows.values() for k in m["AP"]})
    lines += _rows_table(r["rows"], classes)
    scs = r["rows"]["appearance-SCS test"]
    if "AP_by_threshold" in scs["base"]:
        thresholds = list(next(iter(scs["base"]["AP_by_threshold"].values())))
        lines += ["", "AP on the appearance-SCS test set at each centre-distance threshold (m), base -> fine-tuned: "
                  "where a class gains only at the wide thresholds, the detector finds the objects but places them "
                  "that far off.", "", "| class | boxes | " + " | ".join(f"AP {t} m" for t in thresholds) + " |",
                  "|---|---:|" + "---:|" * len(thresholds)]
        for k in scs["base"]["classes"]:
            b, f = scs["base"]["AP_by_threshold"][k], scs["fine-tuned"]["AP_by_threshold"][k]
            lines.append(f"| {k} | {scs['base']['gt_boxes'][k]} | " + " | ".join(
                f"{100 * b[t]:.1f} -> {100 * f[t]:.1f}" for t in thresholds) + " |")
    if s.get("intervals"):
        lines += ["", "How far the changes can be trusted: each test set's scenes (a log or one of its variants) drawn "
                  "with replacement 200 times and the change recomputed (whole scenes, since the frames of one scene "
                  "are nearly the same picture):", "",
                  "| test set | scored | mAP change (points) | 95 % interval | fine-tuned better in | scenes |",
                  "|---|---|---:|---|---:|---:|"]
        scored = [("in view" if camera else "all round", s["intervals"])]
        scored += [("all round", s["all_round"]["intervals"])] if s.get("all_round") else []
        for name in s["intervals"]:
            for how, intervals in scored:
                iv = intervals.get(name)
                if iv is None:
                    lines.append(f"| {name} | {how} | | one scene: nothing to resample | | 1 |")
                    continue
                lines.append(f"| {name} | {how} | {100 * iv['difference']:+.1f} | [{100 * iv['low']:+.1f}, "
                             f"{100 * iv['high']:+.1f}] | {100 * iv['share_b_better']:.0f} % of draws | "
                             f"{iv['n_groups']} |")
    if r.get("all_round_rows"):
        lines += ["", "The same detections scored all round (nuScenes' filter alone: boxes no camera sees count as "
                  "missed):", ""] + _rows_table(r["all_round_rows"], classes)
    if r.get("candidates") and "scs_gain" in r["candidates"][0]:
        lines += ["", "Fine-tuning setting chosen on the validation sets (never on a test set): the candidate gaining "
                  "most mAP on the validation appearance-SCS set among those losing at most "
                  f"{100 * c['map_regression_limit']:.0f} point on the validation logs. Class balance: images drawn "
                  "with weight sum over their classes of n_c^-b (0: every image equally often).", "",
                  "| candidate | val appearance-SCS mAP base | tuned | gain | val logs mAP base | tuned | change | "
                  "seconds |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for i, v in enumerate(r["candidates"]):
            settings = {**{k: c["finetune"][k] for k in ("steps", "lr", "class_balance")}, **v["overrides"]}
            lines.append(f"| {'**kept** ' if i == r['kept'] else ''}" + ", ".join(f"{k} {x}" for k, x in settings.items())
                         + f" | {100 * v['scs_base']:.1f} | {100 * v['scs_tuned']:.1f} | {100 * v['scs_gain']:+.1f} | "
                         f"{100 * v['logs_base']:.1f} | {100 * v['logs_tuned']:.1f} | {100 * v['logs_change']:+.1f} | "
                         f"{v['seconds']:.0f} |")
    if ft.get("draws_showing_class"):
        lines += ["", "Share of the kept fine-tuning's drawn images that show each class: " + ", ".join(
            f"{k} {100 * v:.0f} %" for k, v in ft["draws_showing_class"].items() if v > 0) + "."]
    lines += ["", f"Ground-truth boxes evaluated{' in view' if camera else ''}: " + "; ".join(
        f"{name}: " + ", ".join(f"{k} {n}" for k, n in models["base"]["gt_boxes"].items())
        for name, models in r["rows"].items()), ""]
    if r.get("all_round_rows"):
        lines += ["Ground-truth boxes evaluated all round: " + "; ".join(
            f"{name}: " + ", ".join(f"{k} {n}" for k, n in models["base"]["gt_boxes"].items())
            for name, models in r["all_round_rows"].items()), ""]
    lines += [
        f"Time: data {r['seconds']['data']:.0f} s (the factory's stages, reused when made before), fine-tuning "
        f"{r['seconds']['finetune']:.0f} s."]
    return "\n".join(lines) + "\n"


def _headline(rows: dict, s: dict, c: dict, scored: str) -> str:
    scs = rows["appearance-SCS test"]
    return (f"**{'Scored ' + scored + ': ' if scored else ''}appearance-SCS test set: mAP {100 * scs['base']['mAP']:.1f} "
            f"base, {100 * scs['fine-tuned']['mAP']:.1f} fine-tuned: {100 * s['scs_map_gain']:+.1f} points (target "
            f"+{100 * c['map_gain_target']:.0f}: {'met' if s['meets_gain_target'] else 'not met'}); original test set: "
            f"{100 * s['original_map_change']:+.1f} points (limit -{100 * c['map_regression_limit']:.0f}: "
            f"{'met' if s['meets_regression_limit'] else 'not met'}).**")


def _rows_table(rows: dict, classes: list[str]) -> list[str]:
    lines = ["| test set | detector | mAP | NDS | " + " | ".join(f"AP {k}" for k in classes) + " |",
             "|---|---|---:|---:|" + "---:|" * len(classes)]
    for name, models in rows.items():
        for model, m in models.items():
            lines.append(f"| {name} | {model} | {100 * m['mAP']:.1f} | {100 * m['NDS']:.1f} | " + " | ".join(
                f"{100 * m['AP'][k]:.1f}" if k in m["AP"] else "" for k in classes) + " |")
    return lines


def _plot(r: dict, f) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(r["rows"])
    classes = sorted({k for rows in r["rows"].values() for m in rows.values() for k in m["AP"]})
    cols = min(len(names), 2)
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(7 * cols, 4 * rows), squeeze=False)
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    for ax, name in zip(axes.flat, names):
        x = np.arange(len(classes) + 1)
        for j, (model, colour) in enumerate((("base", "#4c72b0"), ("fine-tuned", "#dd8452"))):
            m = r["rows"][name][model]
            vals = [100 * m["mAP"]] + [100 * m["AP"].get(k, np.nan) for k in classes]
            ax.bar(x + (j - 0.5) * 0.38, vals, 0.38, label=model, color=colour)
        present = r["rows"][name]["base"]["AP"]
        for i, k in enumerate(classes, start=1):  # an empty slot is a class the set does not hold, not an AP of 0
            ax.text(i, 0, "0" if k in present and max(r["rows"][name][m]["AP"][k] for m in ("base", "fine-tuned")) == 0
                    else "none" if k not in present else "", ha="center", va="bottom", fontsize=7, color="#555555")
        ax.set_xticks(x, ["mAP"] + classes, rotation=30, ha="right", fontsize=8)
        ax.set_ylabel("AP, %")
        ax.set_title(name + (" (boxes in the cameras' view)" if r["config"].get("camera_view") else ""))
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(f, format="png", dpi=90)
    plt.close(fig)
