"""``omniscs generate`` (the ``generate_dataset`` flow, every parameter) and ``omniscs demo``."""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Iterator, Optional

import typer

from omniscs.cli.common import console, print_error, print_table, read_edits, show_dataset

#: Sources of the demo run: every road template, the parked-truck scene, and low-light variants.
DEMO_SOURCES = ("syn:straight_parked_truck:3:day", "syn:t_junction:1:dusk", "syn:intersection:2:day",
                "syn:straight:0:night")
DEMO_FRAMES = 20
#: The demo's dataset: one scene (its variants hit the ego head-on with the fast presets), fitted and annotated.
DEMO_DATASET_SOURCE = "syn:straight_parked_truck:3:day"
DEMO_DATASET_VARIANTS = 2
#: The demo dataset's appearance variants and the pool-split assets they take their objects from (none is in a
#: procedural world): an overturned truck, a bus on its side, a car replacing a vehicle.
DEMO_APPEARANCE_VARIANTS = 2
DEMO_POOL_ASSETS = ("pool:box_truck", "pool:bus", "pool:sedan")


def run_generate(sources: list[str], workspace: Optional[Path] = None, **parameters) -> dict:
    """Check every input (a bad one fails here, before Prefect starts and before anything is written), then run
    the flow against a Prefect API that stops with this process; SIGINT / SIGTERM stop the run cleanly."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from omniscs.pipeline.records import new_run_id
    from omniscs.pipeline.validate import RIG_DEFAULTS, check_request, check_run_id, check_sources, run_config
    from omniscs.storage import usable_workspace, workspace_path

    rig = {k: parameters[k] for k in ("n_frames", "n_cameras", "width", "height") if k in parameters}
    request = check_request({k: parameters[k] for k in ("fit_preset", "behavior_variants", "behavior_preset",
                                                          "behavior_checkpoint", "edits", "previews", "device",
                                                          "annotate", "pool", "appearance_variants",
                                                          "appearance_objects")
                             if k in parameters})
    scenes, _ = check_sources(list(sources), **rig)
    from flows.runners import check_runner

    check_runner(parameters.get("task_runner", "threads"), parameters.get("workers"), parameters.get("dask_address"))
    run_id = check_run_id(parameters.pop("run_id", None)) or new_run_id()
    usable_workspace(workspace)  # not a file, nor under one
    from flows.generate import generate_dataset
    from omniscs.cli.prefect_api import prefect_api

    config = run_config(sources, **{**RIG_DEFAULTS, **rig}, **request.to_dict())
    with stops_cleanly(run_id, workspace_path(workspace), config, len(scenes)), prefect_api():
        return generate_dataset(sources=list(sources), workspace=str(workspace) if workspace else None,
                                run_id=run_id, **parameters)


@contextlib.contextmanager
def stops_cleanly(run_id: str, workspace: Path, config: dict, n_scenes: int) -> Iterator[None]:
    """On SIGINT or SIGTERM during the block: record the run as cancelled (unless it already has its ``runs``
    row), stop the temporary Prefect server, remove this process's temporary folders, print one line and exit
    (128 + signal number) without waiting for running stages. Finished stages stay and are reused by a rerun."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    from omniscs import catalog
    from omniscs.cli.prefect_api import stop_server
    from omniscs.pipeline.stages import catalog_run_stage
    from omniscs.locks import clean_stale_temps

    started = int(time.time() * 1e6)

    def stop(signum, frame) -> None:
        for s in STOP_SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        name = signal.Signals(signum).name
        try:
            if not any((catalog.catalog_root(workspace) / "runs" / f"run_id={run_id}").glob("*.parquet")):
                catalog_run_stage(run_id, workspace, "generate_dataset", "cancelled", started,
                                  int(time.time() * 1e6), n_scenes, config, error=f"stopped by {name}")
            stop_server()
            clean_stale_temps(workspace, include_own=True)
        finally:
            print_error(f"run {run_id} stopped by {name} and recorded as cancelled; run the same command again to "
                        "go on (finished stages are reused)")
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(128 + signum)

    previous = {s: signal.signal(s, stop) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


#: Signals that stop a run cleanly.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def generate(
    sources: list[str] = typer.Argument(..., help="syn:TEMPLATE:SEED[:LIGHTING], FORMAT:DATAROOT[:SCENE] "
                                                  "(nuscenes, kitti, waymo-v2) or scene-store paths."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data)."),
    run_id: Optional[str] = typer.Option(None, help="Run id (default: time-stamped)."),
    frames: int = typer.Option(40, help="Synthetic sources: frames at 10 Hz."),
    cameras: int = typer.Option(3, help="Synthetic sources: cameras, 1 to 6."),
    width: int = typer.Option(480, help="Synthetic sources: image width."),
    height: int = typer.Option(270, help="Synthetic sources: image height."),
    previews: bool = typer.Option(True, help="Write contact sheets and BEV plots."),
    fit_preset: Optional[str] = typer.Option(None, help="Fit each scene's Gaussian scene graph: fast, balanced or "
                                                        "accurate (default: no fit)."),
    behavior_variants: int = typer.Option(0, help="Behaviour-level SCS variants per scene (0: none)."),
    behavior_preset: str = typer.Option("balanced", help="Behaviour optimisation preset: fast, balanced or accurate."),
    behavior_checkpoint: Optional[Path] = typer.Option(None, help="Traffic-model checkpoint (default: the shipped "
                                                                  "one)."),
    edit: Optional[str] = typer.Option(None, help="Edits the variants will apply (JSON or @file, see README); "
                                                  "their tracks become nodes in every scene's plan."),
    device: str = typer.Option("cpu", help="Compute device of the scene graph and behaviour optimisation."),
    annotate: bool = typer.Option(False, help="Render and annotate every variant and gather them as a dataset "
                                              "(needs --fit-preset and behaviour or appearance variants)."),
    dataset_id: Optional[str] = typer.Option(None, help="With --annotate: the dataset's id (default ds-<hash>)."),
    pool: Optional[Path] = typer.Option(None, help="Model pool for the agents stage: tracks the edits turn off their "
                                                   "observed views get a 360-degree model from it or online."),
    task_runner: str = typer.Option("threads", help="Where scenes run: threads (this process) or dask (a local "
                                                    "cluster of --workers processes, or --dask-address)."),
    workers: Optional[int] = typer.Option(None, help="Scenes at once: threads, or local Dask worker processes "
                                                     "(default 2; each gets the cores divided among them)."),
    dask_address: Optional[str] = typer.Option(None, help="tcp://HOST:PORT of an existing Dask scheduler (many "
                                                          "machines sharing the workspace path)."),
    appearance_variants: int = typer.Option(0, help="Appearance-level SCS variants per scene (0: none): objects of "
                                                    "--pool replacing a vehicle or inserted upright, on the side or "
                                                    "overturned at valid poses (needs --fit-preset and --pool)."),
    appearance_object: Optional[list[str]] = typer.Option(None, "--appearance-object", help="Pool model ids the "
                                                          "appearance variants use (repeat; default: the whole pool), "
                                                          "e.g. what `omniscs scs mine` found missed."),
) -> None:
    """Run the generate_dataset flow: per scene ingest, plan, preview, fit, agents, background, behaviour and
    appearance variants, render + annotate, catalog; with --annotate, the run's dataset."""
    from omniscs.edits import edit_to_dict

    result = run_generate(list(sources), workspace, run_id=run_id, n_frames=frames, n_cameras=cameras, width=width,
                          height=height, previews=previews, fit_preset=fit_preset,
                          behavior_variants=behavior_variants, behavior_preset=behavior_preset,
                          behavior_checkpoint=str(behavior_checkpoint) if behavior_checkpoint else None,
                          edits=[edit_to_dict(e) for e in read_edits(edit)], device=device, annotate=annotate,
                          dataset_id=dataset_id, pool=str(pool) if pool is not None else None,
                          task_runner=task_runner, workers=workers, dask_address=dask_address,
                          appearance_variants=appearance_variants, appearance_objects=list(appearance_object or ()))
    rows = [{"scene_id": s["scene_id"], **{stage: _state(r) for stage, r in s["stages"].items()}}
            for s in result["scenes"]]
    print_table(rows, title=f"run {result['run_id']}")
    console.print(f"run {result['run_id']}: {len(result['scenes'])} scene(s) in {result['workspace']}")
    if result.get("dataset_path"):
        console.print(f"dataset {result['dataset_id']}: {result['dataset_path']}  (omniscs dataset info "
                      f"{result['dataset_id']})")


def demo_pool(ws: Path) -> Path:
    """The demo's model pool (``<workspace>/pools/demo``): the first model of each kind in DEMO_POOL_ASSETS, built
    once from the asset library's meshes (a few seconds each) and reused."""
    from omniscs.pipeline.pool import asset_ids, pool_asset_stage

    pool = ws / "pools" / "demo"
    for item in DEMO_POOL_ASSETS:
        pool_asset_stage(asset_ids([item])[0], pool)
    return pool


def _state(record: dict) -> str:
    if record["skipped"]:
        return "skipped"
    status = record["info"].get("status")
    return ("reused" if record["reused"] else f"{record['seconds']:.1f} s") + (f" ({status})" if status else "")


def demo(workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or "
                                                             "./omniscs-data).")) -> None:
    """A small multi-scene run on the embedded synthetic world; prints where everything went."""
    from omniscs import catalog
    from omniscs.storage import workspace_root

    started = time.perf_counter()
    result = run_generate(list(DEMO_SOURCES), workspace, n_frames=DEMO_FRAMES, n_cameras=3, width=480, height=270,
                          previews=True)
    ws = workspace_root(result["workspace"])
    root = catalog.catalog_root(ws)
    rows = catalog.query(root, f"""
        SELECT s.scene_id, s.n_frames, s.n_tracks, s.n_moving, s.reused,
               round(s.ingest_seconds, 1) AS ingest_s,
               (SELECT count(*) FROM agents_by_run a WHERE a.run_id = s.run_id AND a.scene_id = s.scene_id
                AND a.max_visible_pixels > 0) AS visible_tracks
        FROM scenes_by_run s WHERE s.run_id = '{result['run_id']}' ORDER BY s.scene_id""").to_pylist()
    print_table(rows, title=f"run {result['run_id']}")
    console.print(f"scene stores: {ws / 'scenes'}")
    for s in result["scenes"]:
        console.print(f"  {s['path']}")
    console.print(f"previews:     {ws / 'previews'}")
    for s in result["scenes"]:
        p = s["stages"]["preview"]["path"]
        console.print(f"  {p}/contact_sheet.png  {p}/bev.png")
    console.print(f"plans:        {ws / 'plans'}  (SELECT scene_id, n_agent_nodes, gaussian_budget FROM plans)")
    console.print(f"catalog:      {root}  (try: omniscs catalog query \"SELECT category, count(*) FROM agents GROUP BY 1\""
                  + (f" --workspace {ws}" if workspace else "") + ")")
    pool = demo_pool(ws)
    console.print(f"then a small dataset: {DEMO_DATASET_SOURCE}, fast scene graph, {DEMO_DATASET_VARIANTS} behaviour "
                  f"and {DEMO_APPEARANCE_VARIANTS} appearance variants (objects of the pool {pool}) rendered and "
                  "annotated (a few minutes)")
    built = run_generate([DEMO_DATASET_SOURCE], workspace, n_frames=DEMO_FRAMES, n_cameras=3, width=480, height=270,
                         previews=False, fit_preset="fast", behavior_variants=DEMO_DATASET_VARIANTS,
                         behavior_preset="fast", annotate=True, pool=str(pool),
                         appearance_variants=DEMO_APPEARANCE_VARIANTS)
    show_dataset(Path(built["dataset_path"]))
    console.print(f"demo finished in {time.perf_counter() - started:.1f} s")
