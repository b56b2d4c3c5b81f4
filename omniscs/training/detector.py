"""Data and training of the shipped proxy camera detector (``omniscs.eval.detector``): procedural logs without any
SCS (ingested, then exported as nuScenes dataroots), the training run that wrote
``omniscs/pretrained/weights/detector/``, and its held-out evaluation by the nuScenes detection protocol.

Reproduce the shipped weights (about 25 minutes on 2 cores: 8 to make the logs, 10 to train, the rest evaluating)::

    omniscs pretrained train detector --workspace omniscs-data

Seeds: training logs from ``train_seed``, held-out logs from ``test_seed`` (templates in turn); no other benchmark or
test uses them. Training dataroots are exported with every frame a keyframe (10 Hz: more, if correlated, images);
held-out ones at the protocol's 2 Hz (and, for a steadier number on few logs, also at 10 Hz).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch

from omniscs.bench.detector_logs import VERSION, ShippedDetectorConfig, procedural_dataroot
from omniscs.eval.detector import (
    DEFAULT_DETECTOR,
    DetectConfig,
    ProxyDetector,
    detect,
    load_detector,
    save_detector,
    train_detector,
    training_set,
    write_results,
)
from omniscs.eval.nuscenes_io import evaluate_detection_results
from omniscs.progress import Progress, Throttled, no_progress
from omniscs.storage import workspace_root


def evaluate_on(model: ProxyDetector, dataroot: Path, detect_config: DetectConfig = DetectConfig()) -> dict:
    """mAP, NDS and the per-class numbers of ``model`` on every scene of a dataroot."""
    with tempfile.TemporaryDirectory() as tmp:
        path = write_results(detect(model, dataroot, VERSION, config=detect_config), Path(tmp) / "results.json")
        metrics, info = evaluate_detection_results(dataroot, VERSION, path)
    out = metrics.to_dict()
    out["n_samples"] = info["n_samples"]
    return out


def _summary(m: dict) -> dict:
    car = m["classes"]["car"]
    return {"mAP": m["mAP"], "NDS": m["NDS"], "car_AP": car["mean_AP"], "car_AP_by_threshold": car["AP"],
            "car_tp_errors": car["tp_errors"], "tp_errors": m["tp_errors"], "n_samples": m["n_samples"],
            "n_gt": {c: v["n_gt"] for c, v in m["classes"].items() if v["n_gt"]},
            "n_pred": {c: v["n_pred"] for c, v in m["classes"].items() if v["n_pred"]}}


def evaluate_heldout(model: ProxyDetector, workspace: str | Path,
                     config: ShippedDetectorConfig = ShippedDetectorConfig(), progress: Progress = no_progress
                     ) -> dict:
    """The model and an untrained one of the same network (seed 0) on the held-out logs, at 2 Hz (the protocol's
    keyframes) and at 10 Hz (every frame: more samples); and the model placing its boxes by the regressed depth
    alone, without the ground contact (what the fusion of ``omniscs.eval.detector.fused_centres`` adds)."""
    torch.manual_seed(0)
    untrained = ProxyDetector(model.config).eval()
    out = {"logs": [list(x) for x in config.logs("test")]}
    for name, every in (("2hz", None), ("10hz", 1)):
        root = procedural_dataroot(workspace, "test", config, every, progress)
        out[name] = {"trained": _summary(evaluate_on(model, root, config.detect)),
                     "untrained": _summary(evaluate_on(untrained, root, config.detect))}
        if model.config.depth_error is not None:
            alone = ProxyDetector(replace(model.config, depth_error=None, contact_error_px=None))
            alone.load_state_dict(model.state_dict())
            out[name]["regressed depth only"] = _summary(evaluate_on(alone.eval(), root, config.detect))
    return out


def _calibration_line(record: dict) -> str:
    cal, data = record.get("calibration") or {}, record["data"]
    if cal.get("depth_error") is None:
        return "- depth errors not measured: the regressed depth is used alone\n"
    where = (f"{len(data['calibration_logs'])} calibration logs not trained on (seeds {data['calibration_logs'][0][1]}-"
             f"{data['calibration_logs'][-1][1]})" if data.get("calibration_logs") else "training images")
    return (f"- errors that weigh the two depth readings, measured on {where}: regressed depth "
            f"{100 * cal['depth_error']:.1f} %, ground contact {cal['contact_error_px']:.2f} px\n")


def _validation_table(validation: dict | None) -> str:
    """The settings compared on the validation logs when these were chosen (``record['validation']``)."""
    if not validation:
        return ""
    rows = "".join(f"| {r['name']} | {r['settings']} | {r['mAP']:.4f} | {r['NDS']:.4f} | {r['car_AP']:.4f} |\n"
                   for r in validation["rows"])
    return (f"Settings chosen on the validation logs ({', '.join(f'{t}:{s}' for t, s in validation['logs'])}; "
            f"never on the held-out ones), every frame a sample:\n\n"
            "| detector | settings | mAP | NDS | car AP |\n|---|---|---|---|---|\n" + rows
            + f"\nKept: {validation['kept']}.\n\n")


def readme(record: dict) -> str:
    h = record.get("heldout", {})

    def row(split: str, which: str) -> str:
        s = h.get(split, {}).get(which)
        return "" if s is None else (f"| {split} | {which} | {s['n_samples']} | {s['mAP']:.4f} | {s['NDS']:.4f} | "
                                     f"{s['car_AP']:.4f} | {s['car_tp_errors']['trans_err']:.3f} |\n")

    data = record["data"]
    return (
        "# Shipped proxy camera 3D detector\n\n"
        "A small CenterNet-style network (`omniscs.eval.detector`), trained from scratch on this machine's CPUs on "
        "procedural logs without SCS. It is a proxy for UniAD's detection, far weaker than it: what matters is that "
        "it is a real learner, so fine-tuning with SCS data can move its numbers.\n\n"
        f"- command: `{record['command']}`\n"
        f"- training logs: {len(data['train_logs'])} (templates "
        f"{', '.join(dict.fromkeys(t for t, _ in data['train_logs']))} in turn, seeds {data['train_logs'][0][1]}-"
        f"{data['train_logs'][-1][1]}), "
        f"{data['n_frames']} frames, {data['n_cameras']} cameras at {data['image_size'][0]}x{data['image_size'][1]}, "
        f"every frame a keyframe: {record['n_images']} images, {record['n_boxes']} learned boxes\n"
        f"- network: {record['n_parameters']} parameters, input {record['detector_config']['input_width']}x"
        f"{record['detector_config']['input_height']}; {record['train_config']['steps']} steps of "
        f"{record['train_config']['batch_size']} images, seed {record['train_config']['seed']}, "
        f"{record['train_config']['threads']} threads, {record['seconds']:.0f} s"
        f"{'; photometric jitter ' + str(record['train_config']['photometric']) if record['train_config'].get('photometric') else ''}\n"
        + _calibration_line(record) + "\n"
        + _validation_table(record.get("validation"))
        + "Held-out logs (" + ", ".join(f"{t}:{s}" for t, s in h.get("logs", [])) + "), nuScenes detection protocol:\n\n"
        "| keyframes | model | samples | mAP | NDS | car AP | car translation error (m) |\n|---|---|---|---|---|---|---|\n"
        + "".join(row(split, which) for split in ("2hz", "10hz")
                  for which in ("trained", "regressed depth only", "untrained")))


def train_shipped_detector(workspace: str | Path | None = None,
                           config: ShippedDetectorConfig = ShippedDetectorConfig(),
                           out: str | Path | None = DEFAULT_DETECTOR, evaluate: bool = True,
                           progress: Progress = no_progress) -> tuple[ProxyDetector, dict]:
    """Make the training logs, train the detector, evaluate it on the held-out logs (``evaluate``) and write it
    with its record to ``out`` (replacing what is there; None: write nothing). Returns the model and the record."""
    workspace = workspace_root(workspace)
    started = time.perf_counter()
    root = procedural_dataroot(workspace, "train", config, config.train_keyframe_every, progress)
    calibration = None
    if config.calibration_logs > 0:
        calibration_root = procedural_dataroot(workspace, "calibration", config, 1, progress)
        calibration = training_set([(calibration_root, VERSION)], config.detector, config.train)
    data_s = time.perf_counter() - started
    model, record = train_detector([(root, VERSION)], config.train, config.detector, progress=progress,
                                   calibration_data=calibration)
    record = {"command": "omniscs pretrained train detector --workspace <workspace>",
              "python": "omniscs.training.detector.train_shipped_detector(workspace, "
                        "ShippedDetectorConfig())",
              "data": {"source": "procedural logs (SyntheticSource, ingest_stage), no SCS, exported as nuScenes "
                                 f"{VERSION}", "train_logs": [list(x) for x in config.logs("train")],
                       "calibration_logs": [list(x) for x in config.logs("calibration")],
                       "lighting": config.lighting, "n_frames": config.train_frames, "n_cameras": config.n_cameras,
                       "image_size": [config.width, config.height],
                       "keyframe_every": config.train_keyframe_every},
              "data_seconds": data_s, **record, "detect_config": asdict(config.detect)}
    if evaluate:
        record["heldout"] = evaluate_heldout(model, workspace, config, progress)
    if out is not None:
        save_detector(model, out, record, overwrite=True, readme=readme(record))
    return model, record


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workspace", default=None, help="workspace root (default: OMNISCS_HOME)")
    parser.add_argument("--out", default=str(DEFAULT_DETECTOR), help="checkpoint folder to write")
    parser.add_argument("--steps", type=int, default=None, help="training steps (default: the shipped run's)")
    parser.add_argument("--evaluate-only", action="store_true", help="evaluate the checkpoint at --out, write nothing")
    args = parser.parse_args(argv)

    config = ShippedDetectorConfig()
    if args.steps is not None:
        config = replace(config, train=replace(config.train, steps=args.steps))
    progress = Throttled(lambda d, t, n: print(f"{d}/{t} {n}", flush=True), step_pct=2.0)
    if args.evaluate_only:
        result = evaluate_heldout(load_detector(args.out), workspace_root(args.workspace), config, progress)
    else:
        _, record = train_shipped_detector(args.workspace, config, args.out, progress=progress)
        result = {k: record[k] for k in ("seconds", "n_images", "n_boxes", "heldout")}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

__all__ = ["ShippedDetectorConfig", "evaluate_heldout", "evaluate_on", "procedural_dataroot", "train_shipped_detector"]
