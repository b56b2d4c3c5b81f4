"""The ``generate_dataset`` flow: one ``scene-pipeline`` sub-flow per scene, scenes side by side.

Per scene (DESIGN.md): ingest → plan → preview → fit NSG → agents (360° models) → background (repair behind
moved or removed large static objects) → behaviour variants → appearance variants (pool objects composited) →
render + annotate → catalog;
then, once every scene is done, the run's annotated variants become one dataset (``datasets/<id>/``, catalogued).
Stages the scene's plan does not need are skipped.
A scene waits for nothing but its own stages: one slow or failed scene holds back no other.
"""
from __future__ import annotations

import signal
import time

from prefect import flow, get_run_logger, task, unmapped
from prefect.task_runners import ThreadPoolTaskRunner

from omniscs.errors import OmniscsError
from omniscs.ids import check_id
from omniscs.locks import clean_stale_temps
from omniscs.pipeline.records import SceneRequest, StageRecord, new_run_id
from omniscs.pipeline.validate import check_request, check_run_id, check_sources, run_config
from omniscs.storage import workspace_root
from flows.runners import MAX_PARALLEL_SCENES, check_runner, scene_task_runner
from tasks import stages as t
from tasks.progress import run_summary_artifact


def _now_us() -> int:
    return int(time.time() * 1e6)


@flow(name="scene-pipeline", flow_run_name="scene-{label}", log_prints=False)
def scene_pipeline(source: dict, label: str, request: SceneRequest, workspace: str, run_id: str) -> dict:
    """Every stage of one scene, in pipeline order; returns what the scene's stages produced."""
    scene = t.ingest(source, workspace, label)
    plan = t.plan(scene, request, workspace)
    stages = plan.info["stages"]
    records = [scene, plan]
    if request.previews:
        records.append(t.preview(scene, workspace))
    model = t.fit(scene, plan, request, workspace) if stages["fit_nsg"] else None
    if model is not None:
        records.append(model)
    if model is not None and stages["agent_models"]:
        completed = t.agents(scene, plan, model, request, workspace)
        records.append(completed)
        model = completed if not completed.skipped else model
    if model is not None and stages["background_repair"]:
        repaired = t.background(scene, plan, model, workspace)
        records.append(repaired)
        model = repaired if not repaired.skipped else model
    variants = t.behavior(scene, plan, model, request, workspace) if stages["behavior_variants"] else None
    if variants is not None:
        records.append(variants)
    composed = t.appearance(scene, plan, model, request, workspace) if stages.get("appearance_variants") else None
    if composed is not None:
        records.append(composed)
    if stages.get("render_annotate"):
        records.append(t.annotate(scene, plan, model, variants, workspace, composed))
    t.catalog_scene(run_id, workspace, scene.scene_id, records)
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


@flow(name="generate_dataset", task_runner=ThreadPoolTaskRunner(max_workers=MAX_PARALLEL_SCENES), log_prints=False)
def generate_dataset(sources: list[str], workspace: str | None = None, run_id: str | None = None,
                     n_frames: int = 40, n_cameras: int = 3, width: int = 480, height: int = 270,
                     previews: bool = True, fit_preset: str | None = None, behavior_variants: int = 0,
                     behavior_preset: str = "balanced", behavior_checkpoint: str | None = None,
                     edits: list[dict] | None = None, device: str = "cpu", annotate: bool = False,
                     dataset_id: str | None = None, pool: str | None = None, task_runner: str = "threads",
                     workers: int | None = None, dask_address: str | None = None, appearance_variants: int = 0,
                     appearance_objects: list[str] | None = None) -> dict:
    """Run the scene pipeline on every source and catalogue the run.

    Sources: ``syn:TEMPLATE:SEED[:LIGHTING]`` (procedural log of ``n_frames`` frames, ``n_cameras`` cameras at
    ``width`` x ``height``), ``FORMAT:DATAROOT[:SCENE]`` (nuscenes, kitti, waymo-v2) or a scene-store path.
    ``fit_preset`` (fast, balanced, accurate) fits each scene's Gaussian scene graph (``models`` table);
    ``behavior_variants`` > 0 makes that many behaviour-level SCS variants per scene (``variants`` table;
    ``behavior_checkpoint`` defaults to the shipped traffic model, ``behavior_preset`` is fast, balanced or
    accurate), with L_app rendered by the scene graph when one is fitted. ``edits`` (edit dicts, see README)
    are the edits the variants will apply: the plan makes their tracks nodes; tracks they turn off their observed
    views get 360-degree models in the ``agents`` stage (the dual strategy, with the model pool ``pool`` when given;
    ``agent_models`` table); large static objects they move or remove get the background behind them repaired in
    the ``background`` stage (``background_repairs`` table). ``appearance_variants`` > 0 makes that many
    appearance-level SCS variants per scene: objects of ``pool`` (``appearance_objects``, model ids; default the
    whole pool) replacing a vehicle's model or inserted at valid poses, upright, on the side or overturned
    (``variants`` rows of kind ``appearance``); with ``annotate`` they are rendered and annotated like the others. Each scene's plan is in the ``plans`` table. ``annotate`` renders and annotates every variant through its scene's graph, the ego on its
    avoiding solution, and gathers them into the dataset ``dataset_id`` (default ``ds-<content hash>``;
    ``datasets``, ``samples`` and ``annotations`` tables). Every input is checked before any scene starts (a bad one fails the run with one line in its
    ``runs`` row); a scene named twice runs once. Returns the run id, workspace, and per scene its id, path and
    stage records, and the dataset id (None without ``annotate``); scenes that failed are listed under ``failed``, and the run then ends failed after the others
    finished. An interrupted run (KeyboardInterrupt) is recorded as ``cancelled``.

    Scenes run on ``task_runner``: ``threads`` (``workers`` at once in this process, default 2) or ``dask``: a local
    cluster of ``workers`` processes (default 2; each gets this machine's cores divided among them for torch and
    numba), or the existing scheduler at ``dask_address`` (tcp://HOST:PORT; its workers must see the same workspace
    path). See flows/runners.py. A table artifact summarises the run (scenes, stages, variants, dataset, failures).
    """
    ws = str(workspace_root(workspace))
    run_id = check_run_id(run_id) or new_run_id()
    started = _now_us()
    config = run_config(sources, n_frames, n_cameras, width, height, fit_preset=fit_preset,
                        behavior_variants=behavior_variants, behavior_preset=behavior_preset,
                        behavior_checkpoint=behavior_checkpoint, edits=edits or (), previews=previews, device=device,
                        annotate=annotate, dataset_id=dataset_id, pool=pool,
                        appearance_variants=appearance_variants, appearance_objects=list(appearance_objects or ()))
    try:  # every input checked before any scene starts; a bad one is the run's one-line error
        request = check_request(SceneRequest(
            fit_preset=fit_preset, behavior_variants=behavior_variants, behavior_preset=behavior_preset,
            behavior_checkpoint=behavior_checkpoint, edits=tuple(edits or ()), previews=previews, device=device,
            annotate=annotate, pool=pool, appearance_variants=appearance_variants,
            appearance_objects=tuple(appearance_objects or ())))
        scenes, repeats = check_sources(sources, n_frames, n_cameras, width, height)
        dataset_id = check_id("dataset id", dataset_id) if dataset_id is not None else None
        check_runner(task_runner, workers, dask_address)
    except OmniscsError as exc:
        t.catalog_run(run_id, ws, "generate_dataset", "failed", started, _now_us(), 0, config, error=one_line(exc))
        raise
    logger = get_run_logger()
    if repeats:
        logger.warning("scene(s) given more than once, run once: %s", ", ".join(repeats))
    for stale in clean_stale_temps(ws):
        logger.info("removed %s, left by a writer that is no longer running", stale)
    try:
        with scene_task_runner(task_runner, workers, dask_address) as runner:
            futures = runner.map(scene_run, {"source": [c.source for c in scenes], "label": [c.text for c in scenes],
                                             "request": unmapped(request), "workspace": unmapped(ws),
                                             "run_id": unmapped(run_id)})
            results = [f.result() for f in futures]
        dataset = None
        done = [r for r in results if "error" not in r]
        if annotate and done:
            annotated = [StageRecord.from_dict(r["stages"]["annotate"]) for r in done if "annotate" in r["stages"]]
            dataset = t.dataset(annotated, ws, dataset_id, {"sources": [c.text for c in scenes], "config": config})
            t.catalog_dataset(run_id, ws, dataset)
    except BaseException as exc:  # recorded even when the run is interrupted (KeyboardInterrupt, SystemExit)
        status = "failed" if isinstance(exc, Exception) else "cancelled"
        t.catalog_run.fn(run_id, ws, "generate_dataset", status, started, _now_us(), len(scenes), config,
                         error=one_line(exc))
        raise
    failed = [r for r in results if "error" in r]
    error = "; ".join(f"{r['label']}: {r['error']}" for r in failed) or None
    run_summary_artifact(run_id, results, None if dataset is None else dataset.info["dataset_id"])
    t.catalog_run(run_id, ws, "generate_dataset", "failed" if failed else "completed", started, _now_us(),
                  len(scenes), config, error=error)
    if failed:
        raise OmniscsError(f"{len(failed)} of {len(scenes)} scene(s) failed in run {run_id}: {error}")
    return {"run_id": run_id, "workspace": ws, "scenes": done, "failed": failed, "repeats": repeats,
            "dataset_id": None if dataset is None else dataset.info["dataset_id"],
            "dataset_path": None if dataset is None else dataset.path}


def one_line(exc: BaseException) -> str:
    """An exception as the one line a ``runs`` row records."""
    text = " ".join(str(exc).split())
    if not isinstance(exc, Exception):  # KeyboardInterrupt, SystemExit, Prefect's TerminationSignal
        sig = getattr(exc, "signal", None)
        if isinstance(sig, int):
            return f"stopped by {signal.Signals(sig).name}"
        return f"stopped ({type(exc).__name__}{': ' + text if text else ''})"
    return text if isinstance(exc, OmniscsError) and text else f"{type(exc).__name__}: {text}".rstrip(": ")
