"""The predict stage (Prefect-free): a model's outputs on a nuScenes dataroot, or on a generated dataset exported as
one for the run, written as the results files ``omniscs eval detection / planning`` read. The model is the embedded
proxy (the shipped weights, or a user's local folder of them) or a user's external model run through the job
template of ``omniscs.eval.external`` with ``{results}`` to write; an external model's file is read as the
evaluation will read it before it is kept. Nothing is written at the results path unless the whole run succeeded.

A dataset's variant stores are exported the way ``omniscs dataset export --format nuscenes`` exports them (the same
sample tokens), so results made on a dataset score against that export of it."""
from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
from pathlib import Path
from typing import Iterator

from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.predict import TASKS, check_results
from omniscs.progress import Progress, no_progress
from omniscs.storage import atomic_write_bytes

def dataset_stores(dataset: Path) -> list[Path]:
    """The variant scene stores of a dataset folder, in the order ``dataset export`` writes them."""
    from omniscs.annotate.dataset import SCENES

    return sorted(p for p in (Path(dataset) / SCENES).iterdir() if p.is_dir())


@contextlib.contextmanager
def dataset_dataroot(dataset: Path, fmt: str = "nuscenes", progress: Progress = no_progress
                     ) -> Iterator[tuple[Path, str]]:
    """A dataset's variant stores exported for the duration of the block into a temporary folder: yields (nuScenes
    dataroot, version). ``fmt`` uniad also writes UniAD's infos (every scene in the val pickle: predictions are
    inference) beside the dataroot, under the folder's ``infos/``."""
    from omniscs.export import export_scenes
    from omniscs.export.nuscenes import DEFAULT_VERSION
    from omniscs.export.uniad import DATAROOT_DIR

    stores = dataset_stores(dataset)
    if not stores:
        raise OmniscsError(f"dataset {dataset} holds no variant scene store to predict on")
    tmp = Path(tempfile.mkdtemp(prefix=".omniscs-predict-"))
    try:
        options = {}
        if fmt == "uniad":
            from omniscs.scene.store import load_scene

            options["val_scenes"] = tuple(load_scene(s).scene_id for s in stores)
        root = export_scenes(stores, fmt, tmp / "export", progress=progress, **options)
        yield (root / DATAROOT_DIR if fmt == "uniad" else root), DEFAULT_VERSION
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def predict_proxy(task: str, dataroot: Path, version: str | None, out: Path, scenes: list[str] | None = None,
                  weights: Path | None = None, progress: Progress = no_progress) -> dict:
    """The embedded proxy of ``task`` (``weights``: a folder of its weights; default the shipped ones) on every
    keyframe of ``scenes`` of the dataroot, its results written atomically at ``out``; returns a summary."""
    import json

    started = time.perf_counter()
    if task == "detection":
        from omniscs.eval.detector import detect, load_detector

        model = load_detector(weights)  # a bad folder fails before any work
        results = detect(model, dataroot, version, scenes=scenes, progress=progress)
        count = {"boxes": sum(len(b) for b in results["results"].values())}
    elif task == "planning":
        from omniscs.eval.planner import load_planner
        from omniscs.eval.predict import predict_planning

        model = load_planner(weights)
        results = predict_planning(model, dataroot, version, scenes=scenes, progress=progress)
        count = {"trajectories": len(results["results"]), "keyframes_with_map": results["meta"]["has_map"]}
    else:
        raise ValidationError(f"unknown task {task!r}; one of {TASKS}")
    atomic_write_bytes(out, json.dumps(results).encode())
    return {"task": task, "model": "proxy", "weights": str(weights) if weights else "shipped",
            "samples": len(results["results"]), **count, "out": str(out), "seconds": time.perf_counter() - started}


def predict_external(task: str, template: str, dataroot: Path, version: str | None, out: Path,
                     scenes: list[str] | None = None, values: dict | None = None, timeout_s: float = 6 * 3600.0,
                     info_val: Path | None = None, on_line=None) -> dict:
    """A user's model run as an external job (``omniscs.eval.external``): the template filled with
    ``{dataset_root}``, ``{version}``, ``{task}``, ``{results}`` (where the job must write its results file),
    ``{work_dir}``, ``{info_val}`` (UniAD's infos of a dataset, when exported so) and ``values``; its log goes to
    ``<out>.job.log``. A failed job, or a results file the evaluation would refuse, is one error and ``out`` is left
    as it was."""
    from omniscs.eval.external import job_argv, run_job
    from omniscs.eval.nuscenes_io import resolve_version

    started = time.perf_counter()
    version = resolve_version(dataroot, version)
    work = Path(tempfile.mkdtemp(prefix=".omniscs-predict-job-"))
    try:
        results = work / f"{task}-results.json"
        filled = {**(values or {}), "dataset_root": str(dataroot), "version": version, "task": task,
                  "results": str(results), "work_dir": str(work / "work"),
                  "info_val": str(info_val) if info_val else None}
        argv = job_argv(template, filled)  # a bad template is an error before the job starts
        log_path = out.with_name(out.name + ".job.log")
        job = run_job(argv, log_path, timeout_s, on_line=on_line)
        if not job.ok:
            raise OmniscsError(f"the external {task} job failed ({job.reason}); its log: {log_path}")
        if not results.is_file():
            raise OmniscsError(f"the external {task} job ended well but wrote no results at the {{results}} path; "
                               f"its log: {log_path}")
        try:
            n = check_results(task, results, dataroot, version, scenes)
        except ValidationError as exc:
            raise OmniscsError(f"the external {task} job's results would not evaluate: {exc}") from exc
        atomic_write_bytes(out, results.read_bytes())
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {"task": task, "model": "external", "command": " ".join(argv), "samples": n, "out": str(out),
            "log": str(log_path), "seconds": time.perf_counter() - started}
