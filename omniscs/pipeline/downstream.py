"""The downstream stages (Prefect-free, like the per-scene stage modules beside it): fine-tune the proxy planner on
generated datasets, evaluate a planner on datasets, run an external job (UniAD or any stack) and read its metrics
back. Each returns a ``StageRecord`` whose rows go to the ``downstream_models`` and ``evaluations`` tables; a failure
of the model (a crash, a timeout, a dataset with nothing to learn from) is a ``failed`` row with its reason, not a
lost run.

Folders: ``downstream/<model_id>/`` (a fine-tuned checkpoint, reused by the one reuse contract: the same datasets,
base and config give the same model) and ``downstream/<model_id>/`` for an external job (its log and work dir)."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

from omniscs import catalog
from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.comparison import write_comparison
from omniscs.eval.detector import (
    DEFAULT_DETECTOR,
    DetectorTrainConfig,
    evaluate_detector,
    load_detector,
    save_detector,
    score_detections,
    train_detector,
)
from omniscs.eval.downstream import (
    CAMERA_VIEW,
    CARD_JSON,
    content_id,
    dataset_card,
    detection_rows,
    external_rows,
    failed_row,
    log_examples,
    planner_rows,
    variant_examples,
)
from omniscs.eval.external import job_argv, parse_uniad_output, run_job
from omniscs.eval.planner import (
    DEFAULT_PLANNER,
    TrainConfig,
    load_planner,
    mixed_examples,
    plan,
    save_planner,
    train_planner,
)
from omniscs.eval.planning import evaluate_planning
from omniscs.eval.scenarios import planning_examples, scenario_from_traffic
from omniscs.export import export_scenes
from omniscs.locks import output_lock
from omniscs.pipeline import layout
from omniscs.pipeline.procedural import procedural_scene_id, procedural_scenes, procedural_traffic
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.progress import Progress, no_progress
from omniscs.untrusted import read_own_json

log = logging.getLogger(__name__)

FINETUNE_VERSION = 3  # 2: behaviour-SCS keyframes after the now step (variant_keyframes), masked loss; 3: the logs
#                       repeated when the SCS examples outnumber them (mix_repeats)
#: Share of the fine-tuning examples that are behaviour-SCS (``planner.mix_repeats``: the short kind is repeated).
SCS_SHARE = 0.5
BASE_MODEL_ID = "proxy-planner-base"


def dataset_paths(workspace: str | Path, dataset_ids: list[str]) -> list[Path]:
    """The folders of ``dataset_ids`` in the workspace; a clear error for an unknown one."""
    if not dataset_ids:
        raise ValidationError("no dataset ids given")
    out = []
    for d in dataset_ids:
        path = layout.dataset_folder(workspace, d)
        if not (path / CARD_JSON).is_file():
            raise ValidationError(f"dataset {d} is not in workspace {workspace} (no {path / CARD_JSON})")
        out.append(path)
    return out


def _source_scenes(workspace: str | Path, datasets: list[Path]) -> list[Path]:
    ids = sorted({v["scene_id"] for d in datasets for v in dataset_card(d).get("variants", [])})
    paths = [layout.scene_store(workspace, sid) for sid in ids]  # ingested, or used in place
    return [p for p in paths if p is not None]


def _planner(model: StageRecord | None):
    return load_planner(None if model is None else model.path)


def _model_row(model_id: str, kind: str, base_model_id: str, dataset_ids: list[str], out: Path, settings: dict) -> dict:
    """The ``downstream_models`` row of a proxy fine-tune, less its outcome (status, counts, seconds, error)."""
    return {"model_id": model_id, "kind": kind, "base_model_id": base_model_id, "dataset_ids": list(dataset_ids),
            "path": str(out), "command": None, "log_path": None, "config_json": json.dumps(settings, sort_keys=True)}


def base_planner_logs(base_path: str | Path, progress: Progress = no_progress) -> list:
    """Planning examples of the procedural logs a base planner was trained on, remade from the ``data`` its training
    record names (``templates`` in turn over the ``train_seeds`` range, ``n_frames`` each, as ``omniscs pretrained
    train planner`` trains the shipped one); [] for a base whose record names none."""
    path = Path(base_path) / "training.json"
    data = (read_own_json(path, "name a planner folder a training wrote", expect=dict).get("data") or {}) \
        if path.exists() else {}
    seeds, templates, n_frames = data.get("train_seeds"), data.get("templates"), data.get("n_frames")
    if not (seeds and templates and n_frames):
        return []
    scenes = procedural_scenes(templates, int(seeds[0]), int(seeds[-1]) - int(seeds[0]) + 1)
    out = []
    for i, (template, seed) in enumerate(scenes):
        progress(i, len(scenes), f"the base planner's training log {template}:{seed} (rehearsal)")
        traffic = procedural_traffic(template, seed, int(n_frames), scene_id=procedural_scene_id(template, seed))
        out += planning_examples(scenario_from_traffic(traffic))
    return out


def finetune_stage(dataset_ids: list[str], workspace: str | Path, config=None, base: str | Path | None = None,
                   progress: Progress = no_progress, reuse: bool = True, rehearse: bool = True) -> StageRecord:
    """The proxy planner fine-tuned from ``base`` (default: the shipped one) on the datasets' behaviour-SCS
    examples mixed with log examples (SCS_SHARE of them SCS). ``rehearse``: the logs are those base was trained on
    (``base_planner_logs``), as the planning protocol fine-tunes (reports/downstream/report.md: no log base has not
    seen, so it keeps what it knew); otherwise, or for a base whose record names no logs, the datasets' source
    logs."""
    started = time.perf_counter()
    config = config or TrainConfig(epochs=15, lr=1e-3, seed=1)  # the setting the planning protocol kept (its bench)
    datasets = dataset_paths(workspace, dataset_ids)
    base_path = Path(base) if base is not None else DEFAULT_PLANNER
    base_hash = _folder_hash(base_path)
    inputs = {"datasets": {d.name: dataset_card(d).get("counts") for d in datasets}, "base": base_hash}
    settings = {"train": dataclasses.asdict(config), "scs_share": SCS_SHARE, "rehearse": bool(rehearse)}
    key = StageKey.of("finetune", FINETUNE_VERSION, inputs, settings)
    model_id = content_id("proxy-planner", {"key": key.digest})
    out = layout.downstream_folder(workspace, model_id)
    row = _model_row(model_id, "proxy_planner", BASE_MODEL_ID if base is None else str(base), dataset_ids, out,
                     settings)
    with output_lock(out):
        manifest = reusable(out, key) if reuse else None
        reused = manifest is not None
        if manifest is None:
            logs = base_planner_logs(base_path, progress) if rehearse else []
            log_source = "base's training logs (rehearsal)" if logs else "the datasets' source logs"
            if not logs:
                logs = log_examples(_source_scenes(workspace, datasets))
            scs, counts = [], []
            for d in datasets:
                got, c = variant_examples(d)
                scs += got
                counts.append(c)
            if not scs:
                return StageRecord("finetune", "-", None, seconds=time.perf_counter() - started, key=key.digest,
                                   rows={"downstream_models": [dict(row, status="failed", n_examples=0,
                                                                    train_seconds=None, path=None,
                                                                    error="the datasets hold no solved variant with a "
                                                                          "1 s future to learn from")]},
                                   info={"status": "failed", "model_id": model_id})
            examples, mix = mixed_examples(scs, logs, SCS_SHARE)
            base_model = load_planner(base_path)

            def make(tmp: Path) -> dict:
                model, record = train_planner(examples, config, init=base_model, progress=progress)
                record.update(datasets=list(dataset_ids), scs_examples=len(scs), log_examples=len(logs),
                              log_source=log_source, base=str(base_path), counts=counts, **mix)
                save_planner(model, tmp / "planner", record)
                return {"n_examples": record["n_examples"], "train_seconds": record["seconds"]}

            manifest = produce(out, key, make)
    outputs = manifest.get("outputs", {})
    return StageRecord("finetune", "-", str(out / "planner"), reused=reused,
                       seconds=time.perf_counter() - started, key=key.digest,
                       rows={"downstream_models": [dict(row, status="trained", n_examples=outputs.get("n_examples"),
                                                        train_seconds=outputs.get("train_seconds"), error=None)]},
                       info={"status": "trained", "model_id": model_id})


DETECTOR_BASE_ID = "proxy-detector-base"
#: Fine-tuning of the proxy detector in the flows (``DetectorTrainConfig`` fields): the setting the detection
#: protocol kept on its validation sets (reports/downstream/detection.md).
DETECTOR_FINETUNE = {"steps": 1200, "lr": 1e-3, "seed": 1, "class_balance": 0.0}
DETECTOR_VERSION = "v1.0-trainval"


def _dataset_stores(dataset: Path) -> list[str]:
    return sorted(str(p) for p in (dataset / "scenes").iterdir() if (p / "manifest.json").is_file())


def dataroot_version(root: str | Path) -> tuple[str, str]:
    """(root, version) of a nuScenes dataroot holding exactly one ``v1.0-*`` table folder; a clear error otherwise."""
    root = Path(root)
    versions = sorted(p.name for p in root.glob("v1.0-*") if (p / "sample.json").is_file()) if root.is_dir() else []
    if len(versions) != 1:
        raise ValidationError(f"{root} is not a nuScenes dataroot with one version folder (found "
                              f"{versions or 'none'}); name a dataroot such as the one the base detector was "
                              "trained on")
    return str(root), versions[0]


def export_dataroot(stores: list[str], out: Path, keyframe_every: int | None) -> Path:
    """Scene stores as one nuScenes dataroot (DETECTOR_VERSION) at ``out``, replacing what is there."""
    return export_scenes(stores, "nuscenes", out, overwrite=True, version=DETECTOR_VERSION,
                         keyframe_every=keyframe_every)


def finetune_detector_stage(dataset_ids: list[str], workspace: str | Path, config=None, base: str | Path | None = None,
                            progress: Progress = no_progress, reuse: bool = True,
                            rehearsal: list[str] | None = None) -> StageRecord:
    """The proxy camera detector fine-tuned from ``base`` (default: the shipped one) on the datasets' variant stores
    (appearance variants above all) and their source logs, every frame, exported as nuScenes dataroots for the
    training only (``downstream/<model_id>/detector/`` keeps the weights). ``rehearsal``: nuScenes dataroots the
    base was trained on, mixed into the fine-tuning so that it does not forget them (the shipped detector's are
    made under ``<workspace>/bench-detector/`` by ``omniscs pretrained train detector``; without them, a
    fine-tuning on a few logs costs the detector much of what it knew: reports/downstream/detection.md)."""
    started = time.perf_counter()
    config = config or DetectorTrainConfig(**DETECTOR_FINETUNE)
    datasets = dataset_paths(workspace, dataset_ids)
    base_path = Path(base) if base is not None else DEFAULT_DETECTOR
    replay = [dataroot_version(r) for r in rehearsal or []]
    inputs = {"datasets": {d.name: dataset_card(d).get("counts") for d in datasets}, "base": _folder_hash(base_path),
              "rehearsal": [f"{r} {v}" for r, v in replay]}
    settings = {"train": dataclasses.asdict(config)}
    key = StageKey.of("finetune-detector", FINETUNE_VERSION, inputs, settings)
    model_id = content_id("proxy-detector", {"key": key.digest})
    out = layout.downstream_folder(workspace, model_id)
    row = _model_row(model_id, "proxy_detector", DETECTOR_BASE_ID if base is None else str(base), dataset_ids, out,
                     settings)
    with output_lock(out):
        manifest = reusable(out, key) if reuse else None
        reused = manifest is not None
        if manifest is None:
            stores = [s for d in datasets for s in _dataset_stores(d)]
            logs = [str(p) for p in _source_scenes(workspace, datasets)]
            base_model = load_detector(base_path)
            if not replay:
                log.warning("fine-tuning the detector without the data it was trained on (no rehearsal dataroot): "
                            "on a few logs and their variants alone it forgets much of what it knew")

            def make(tmp: Path) -> dict:
                data = Path(tempfile.mkdtemp(prefix=".detector-data-", dir=tmp))
                try:
                    roots = [(export_dataroot(stores, data / "variants", 1), DETECTOR_VERSION)]
                    if logs:
                        roots.append((export_dataroot(logs, data / "logs", 1), DETECTOR_VERSION))
                    model, record = train_detector(roots + replay, config, init=base_model, progress=progress)
                finally:
                    shutil.rmtree(data, ignore_errors=True)
                record.update(datasets=list(dataset_ids), base=str(base_path), variant_stores=len(stores),
                              log_stores=len(logs), rehearsal=[list(r) for r in replay])
                save_detector(model, tmp / "detector", record)
                return {"n_examples": record.get("n_images"), "train_seconds": record.get("seconds")}

            manifest = produce(out, key, make)
    outputs = manifest.get("outputs", {})
    return StageRecord("finetune", "-", str(out / "detector"), reused=reused, seconds=time.perf_counter() - started,
                       key=key.digest,
                       rows={"downstream_models": [dict(row, status="trained", n_examples=outputs.get("n_examples"),
                                                        train_seconds=outputs.get("train_seconds"), error=None)]},
                       info={"status": "trained", "model_id": model_id, "task": "detection"})


def evaluate_detector_stage(model: StageRecord | None, dataset_ids: list[str], workspace: str | Path,
                            eval_id: str | None = None) -> StageRecord:
    """A proxy detector (``model``: a detector fine-tune's record; None: the shipped base) on each dataset's variant
    stores and on its source logs ("original"), 2 Hz keyframes, by nuScenes mAP / NDS / AP per class over the classes
    each set holds, scored all round (nuScenes' protocol) and in the cameras' view (convention ``camera_view``);
    rows for ``evaluations``."""
    started = time.perf_counter()
    model_id = DETECTOR_BASE_ID if model is None else model.info["model_id"]
    eval_id = eval_id or content_id("eval", {"model": model_id, "datasets": sorted(dataset_ids), "task": "detection"})
    detector = load_detector(None if model is None else model.path)
    rows = []
    for path in dataset_paths(workspace, dataset_ids):
        did = path.name
        sets = (("variants", _dataset_stores(path)), ("original", [str(p) for p in _source_scenes(workspace, [path])]))
        data = Path(tempfile.mkdtemp(prefix=".detector-eval-"))
        try:
            for split, stores in sets:
                if not stores:
                    rows.append(failed_row(eval_id, model_id, did, "detection", split,
                                           f"dataset {did} has no {split} scene store in this workspace"))
                    continue
                root, results = export_dataroot(stores, data / split, None), data / f"{split}-results.json"
                try:
                    metrics = evaluate_detector(detector, root, DETECTOR_VERSION, results)
                except ValidationError as exc:  # e.g. no evaluated box: recorded, not a lost run
                    rows.append(failed_row(eval_id, model_id, did, "detection", split, str(exc)))
                    continue
                rows += detection_rows(eval_id, model_id, did, split, metrics)
                try:  # the same detections, only the boxes a camera sees
                    rows += detection_rows(eval_id, model_id, did, split,
                                           score_detections(root, DETECTOR_VERSION, results, camera_view=True))
                except ValidationError as exc:
                    rows.append(failed_row(eval_id, model_id, did, "detection", split, str(exc), CAMERA_VIEW))
        finally:
            shutil.rmtree(data, ignore_errors=True)
    return StageRecord("evaluate", "-", None, seconds=time.perf_counter() - started,
                       rows={"evaluations": rows}, info={"eval_id": eval_id, "model_id": model_id,
                                                         "failed": sum(r["status"] == "failed" for r in rows)})


def _folder_hash(path: Path) -> str:
    h = hashlib.sha256()
    for f in sorted(p for p in Path(path).glob("*") if p.is_file()):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def evaluate_stage(model: StageRecord | None, dataset_ids: list[str], workspace: str | Path,
                   eval_id: str | None = None) -> StageRecord:
    """A planner (``model``: a fine-tune stage's record; None: the shipped base) on each dataset's behaviour-SCS
    examples and on its source logs ("original"), by UniAD's planning metrics; rows for ``evaluations``."""
    started = time.perf_counter()
    model_id = BASE_MODEL_ID if model is None else model.info["model_id"]
    eval_id = eval_id or content_id("eval", {"model": model_id, "datasets": sorted(dataset_ids)})
    planner = _planner(model)
    rows = []
    for path in dataset_paths(workspace, dataset_ids):
        did = path.name
        scs, _ = variant_examples(path)
        logs = log_examples(_source_scenes(workspace, [path]))
        for split, examples in (("behaviour-SCS", scs), ("original", logs)):
            if not examples:
                rows.append(failed_row(eval_id, model_id, did, "planning", split,
                                       f"dataset {did} has no {split} example with "
                                       + ("1 s of known future" if split == "behaviour-SCS" else "a whole 3 s future")))
                continue
            rows += planner_rows(eval_id, model_id, did, split,
                                 evaluate_planning([e.sample for e in examples], plan(planner, examples)))
    return StageRecord("evaluate", "-", None, seconds=time.perf_counter() - started,
                       rows={"evaluations": rows}, info={"eval_id": eval_id, "model_id": model_id,
                                                         "failed": sum(r["status"] == "failed" for r in rows)})


def external_stage(template: str, dataset_ids: list[str], workspace: str | Path, values: dict | None = None,
                   timeout_s: float = 6 * 3600.0, export: str | None = "uniad",
                   on_line=None) -> StageRecord:
    """An external job on the datasets: exported (``export``: uniad or nuscenes, or None) into the job's folder,
    the template filled (``{dataset_root}``, ``{info_train}``, ``{info_val}``, ``{work_dir}`` and ``values``), run
    to its end or its timeout, its printed metrics read back. Without export, ``{dataset_root}`` is the dataset's
    own folder (one dataset only). A crash or timeout is a failed model row."""
    started = time.perf_counter()
    datasets = dataset_paths(workspace, dataset_ids)
    model_id = content_id("external", {"template": template, "datasets": sorted(dataset_ids), "values": values,
                                       "at": time.time_ns()})
    out = layout.downstream_folder(workspace, model_id)
    out.mkdir(parents=True, exist_ok=True)
    filled = {"work_dir": str(out / "work"), **(values or {})}
    if export is None and len(datasets) == 1:
        filled.setdefault("dataset_root", str(datasets[0]))
    elif export is None:
        raise ValidationError("several datasets go to an external job only exported into one dataroot (export)")
    else:
        stores = [s for d in datasets for s in sorted((d / "scenes").iterdir()) if s.is_dir()]
        root = export_scenes(stores, export, out / "data")
        filled.update(dataset_root=str(root), info_train=str(root / "infos" / "nuscenes_infos_temporal_train.pkl"),
                      info_val=str(root / "infos" / "nuscenes_infos_temporal_val.pkl"))
    argv = job_argv(template, filled)  # a bad template is the user's error: raised, not a failed row
    result = run_job(argv, out / "job.log", timeout_s, on_line=on_line)
    eval_id = content_id("eval", {"model": model_id})
    row = {"model_id": model_id, "kind": "external", "base_model_id": None, "dataset_ids": list(dataset_ids),
           "path": str(out), "n_examples": None, "train_seconds": result.seconds,
           "command": " ".join(argv), "log_path": result.log_path, "config_json": json.dumps(
               {"template": template, "values": values, "timeout_s": timeout_s, "export": export}, sort_keys=True)}
    if not result.ok:
        return StageRecord("external", "-", str(out), seconds=time.perf_counter() - started,
                           rows={"downstream_models": [dict(row, status="failed", error=result.reason)],
                                 "evaluations": [failed_row(eval_id, model_id, None, "external", "external",
                                                            result.reason)]},
                           info={"status": "failed", "model_id": model_id, "error": result.reason})

    rows = external_rows(eval_id, model_id, None, parse_uniad_output(Path(result.log_path).read_text()))
    if not rows:
        rows = [failed_row(eval_id, model_id, None, "external", "external",
                           "the job ended well but printed no metrics UniAD's evaluation prints")]
    return StageRecord("external", "-", str(out), seconds=time.perf_counter() - started,
                       rows={"downstream_models": [dict(row, status="trained", error=None)], "evaluations": rows},
                       info={"status": "trained", "model_id": model_id, "eval_id": eval_id})


def datasets_of_flow_run(workspace: str | Path, flow_run_id: str) -> list[str]:
    """The datasets a ``generate_dataset`` run made, found by the orchestrator's flow run id (what a
    ``prefect.flow-run.Completed`` event names: ``prefect.flow-run.<id>`` or the bare id)."""
    fid = str(flow_run_id).removeprefix("prefect.flow-run.")
    if not fid or "'" in fid:
        raise ValidationError(f"not a flow run id: {flow_run_id!r}")
    rows = catalog.query(layout.catalog_root(workspace),
                         "SELECT DISTINCT d.dataset_id FROM datasets_by_run d JOIN runs r ON r.run_id = d.run_id "
                         f"WHERE r.flow_run_id = '{fid}' ORDER BY 1").to_pylist()
    if not rows:
        raise OmniscsError(f"flow run {fid} made no dataset in workspace {workspace} (a run without --annotate, "
                           "or another workspace)")
    return [r["dataset_id"] for r in rows]


def comparison_plot_stage(run_id: str, workspace: str | Path, records: list[StageRecord]) -> str | None:
    """The run's comparison plot (``omniscs.eval.comparison``) of the evaluation rows of ``records``, written to
    ``<workspace>/evaluations/<run_id>/comparison.png``; None when no row can be drawn (every evaluation failed)."""
    rows = [row for r in records for row in r.rows.get("evaluations", [])]
    if not any(row["status"] == "ok" for row in rows):
        return None
    try:
        out = write_comparison(rows, layout.evaluation_folder(workspace, run_id) / "comparison.png", f"run {run_id}")
    except ValidationError:  # only rows the plot does not draw (e.g. an external job's TP errors)
        return None
    return str(out)


def catalog_records_stage(run_id: str, workspace: str | Path, records: list[StageRecord], writer: str) -> list[str]:
    """One Parquet file per table for the rows of ``records`` (downstream models, evaluations)."""
    tables: dict[str, list[dict]] = {}
    for r in records:
        for table, rows in r.rows.items():
            tables.setdefault(table, []).extend(rows)
    root = layout.catalog_root(workspace)
    written = [catalog.write_rows(root, table, run_id, rows, writer=writer) for table, rows in tables.items() if rows]
    return [str(p) for p in written if p is not None]
