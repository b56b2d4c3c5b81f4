"""The ``generate_dataset`` flow: one ``scene-pipeline`` sub-flow per scene, scenes side by side.

Per scene, the stage table of ``omniscs.pipeline.stages`` (ingest → plan → preview → fit → agents → background →
behaviour variants → appearance variants → uncovered (repair) → render + annotate), each stage a task, then the
scene's catalog rows; then, once every scene is done, the run's annotated variants become one dataset
(``datasets/<id>/``, catalogued). Stages the scene's plan does not need are skipped. A scene waits for nothing but its
own stages: one slow or failed scene holds back no other. The run's one parameter is a ``RunRequest`` (a form in
Prefect's UI).
"""
from __future__ import annotations

import functools
import signal
import time

from prefect import flow, get_run_logger, task, unmapped

from omniscs.errors import OmniscsError
from omniscs.locks import clean_stale_temps
from omniscs.pipeline.records import StageRecord, new_run_id
from omniscs.pipeline.request import RunRequest, SceneRequest
from omniscs.pipeline.stages import start_scene, walk_scene
from omniscs.pipeline.validate import check_run, check_run_id
from omniscs.storage import workspace_root
from flows.runners import scene_task_runner
from tasks import stages as t
from tasks.progress import run_summary_artifact


def _now_us() -> int:
    return int(time.time() * 1e6)


@flow(name="scene-pipeline", flow_run_name="scene-{label}", validate_parameters=False, log_prints=False)
def scene_pipeline(source: dict, label: str, request: SceneRequest, workspace: str, run_id: str) -> dict:
    """Every stage of one scene that its plan needs, in the table's order; returns what they produced."""
    state = walk_scene(start_scene(source, request, workspace, label), functools.partial(t.run_stage, run_id=run_id))
    records = list(state.records)
    t.catalog_scene(run_id, workspace, state.scene_id, records)
    scene = state.record("ingest")
    return {"scene_id": scene.scene_id, "path": scene.path, "reused": scene.reused,
            "stages": {r.stage: r.to_dict() for r in records}}


@task(name="scene", task_run_name="scene-{label}")
def scene_run(source: dict, label: str, request: SceneRequest, workspace: str, run_id: str) -> dict:
    """The sub-flow of one scene, as a task so that the run's task runner runs scenes side by side; a failed
    scene is reported in the result instead of stopping the others."""
    try:
        return scene_pipeline(source, label, request, workspace, run_id)
    except Exception as exc:  # the scene failed; the run goes on and records it
        get_run_logger().exception("scene %s failed", label)
        return {"label": label, "error": one_line(exc)}


@flow(name="generate_dataset", validate_parameters=False, log_prints=False)
def generate_dataset(request: RunRequest) -> dict:
    """Run the scene pipeline on every source of ``request`` and catalogue the run (see ``RunRequest`` for every
    field: sources, synthetic rig, fit and variant settings, edits, pool, dataset, task runner).

    Every input is checked before any scene starts (a bad one fails the run with one line in its ``runs`` row);
    a scene named twice runs once. Returns the run id, workspace, and per scene its id, path and stage records, and
    the dataset id (None without ``annotate``); scenes that failed are listed under ``failed``, and the run then
    ends failed after the others finished. An interrupted run (KeyboardInterrupt) is recorded as ``cancelled``.
    Scenes run on the request's task runner (flows/runners.py). A table artifact summarises the run."""
    given = request.to_dict() if isinstance(request, RunRequest) else request
    raw = given if isinstance(given, dict) else {}
    ws = str(workspace_root(raw.get("workspace")))
    run_id = check_run_id(raw.get("run_id")) or new_run_id()  # an unsafe id: refused before anything is written
    started = _now_us()
    try:  # every input checked before any scene starts; a bad one is the run's one-line error
        checked = check_run(request)
    except OmniscsError as exc:
        t.catalog_run(run_id, ws, "generate_dataset", "failed", started, _now_us(), 0, raw, error=one_line(exc))
        raise
    request, scenes = checked.request, checked.scenes
    config = request.to_dict()
    logger = get_run_logger()
    if checked.repeats:
        logger.warning("scene(s) given more than once, run once: %s", ", ".join(checked.repeats))
    for stale in clean_stale_temps(ws):
        logger.info("removed %s, left by a writer that is no longer running", stale)
    try:
        with scene_task_runner(request.task_runner, request.workers, request.dask_address) as runner:
            futures = runner.map(scene_run, {"source": [c.source for c in scenes], "label": [c.text for c in scenes],
                                             "request": unmapped(request.scene_request()), "workspace": unmapped(ws),
                                             "run_id": unmapped(run_id)})
            results = [f.result() for f in futures]
        dataset = None
        done = [r for r in results if "error" not in r]
        if request.annotate and done:
            annotated = [StageRecord.from_dict(r["stages"]["annotate"]) for r in done if "annotate" in r["stages"]]
            facts = {"sources": [c.text for c in scenes], "config": request.product_fields()}
            failed_scenes = [{"scene": r["label"], "error": r["error"]} for r in results if "error" in r]
            if failed_scenes:  # the card says which scenes are missing and why
                facts["failed_scenes"] = failed_scenes
            dataset = t.dataset(annotated, ws, request.dataset_id, facts, keep_failed=request.keep_failed,
                                run_id=run_id)
            t.catalog_dataset(run_id, ws, dataset)
    except BaseException as exc:  # recorded even when the run is interrupted (KeyboardInterrupt, SystemExit)
        status = "failed" if isinstance(exc, Exception) else "cancelled"
        t.catalog_run.fn(run_id, ws, "generate_dataset", status, started, _now_us(), len(scenes), config,
                         error=one_line(exc))
        raise
    failed = [r for r in results if "error" in r]
    error = "; ".join(f"{r['label']}: {r['error']}" for r in failed) or None
    run_summary_artifact(run_id, results, None if dataset is None else dataset.info["dataset_id"],
                         [] if dataset is None else dataset.info.get("warnings", []))
    t.catalog_run(run_id, ws, "generate_dataset", "failed" if failed else "completed", started, _now_us(),
                  len(scenes), config, error=error)
    if failed:
        raise OmniscsError(f"{len(failed)} of {len(scenes)} scene(s) failed in run {run_id}: {error}")
    return {"run_id": run_id, "workspace": ws, "scenes": done, "failed": failed, "repeats": list(checked.repeats),
            "dataset_id": None if dataset is None else dataset.info["dataset_id"],
            "dataset_path": None if dataset is None else dataset.path,
            "dataset_gates": None if dataset is None else dataset.info.get("gates"),
            "dataset_warnings": [] if dataset is None else dataset.info.get("warnings", [])}


def one_line(exc: BaseException) -> str:
    """An exception as the one line a ``runs`` row records."""
    text = " ".join(str(exc).split())
    if not isinstance(exc, Exception):  # KeyboardInterrupt, SystemExit, Prefect's TerminationSignal
        sig = getattr(exc, "signal", None)
        if isinstance(sig, int):
            return f"stopped by {signal.Signals(sig).name}"
        return f"stopped ({type(exc).__name__}{': ' + text if text else ''})"
    return text if isinstance(exc, OmniscsError) and text else f"{type(exc).__name__}: {text}".rstrip(": ")
