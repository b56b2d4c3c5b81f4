"""``omniscs generate`` (the ``generate_dataset`` flow, every parameter) and ``omniscs demo``."""
from __future__ import annotations

import contextlib
import inspect
import os
import signal
import sys
import threading
import time
import types
from pathlib import Path
from typing import Iterator, Optional

import typer

from omniscs.cli.common import console, print_error, print_table, read_edits, run_progress, show_dataset

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


def run_generate(request) -> dict:
    """Check the run once (a bad input fails here, before Prefect starts and before anything is written), then run
    the flow against a Prefect API that stops with this process; SIGINT / SIGTERM stop the run cleanly. The stages'
    progress shows as bars on a terminal and plain lines in a log, whichever task runner runs them.
    ``request``: a ``RunRequest`` or its fields as a dict."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from omniscs.pipeline.records import new_run_id
    from omniscs.pipeline.request import RunRequest
    from omniscs.pipeline.validate import check_run
    from omniscs.storage import usable_workspace, workspace_path

    request = RunRequest.parse(request)
    if request.run_id is None:  # named now, so that a stop can record the run as cancelled
        request = request.model_copy(update={"run_id": new_run_id()})
    checked = check_run(request, hand_on=True)  # the flow below takes this check, not a second one
    usable_workspace(request.workspace)  # not a file, nor under one
    short = planning_frames_warning(request)
    if short is not None:
        print_error(short, label="warning", style="yellow")
    from flows.generate import generate_dataset
    from omniscs.cli.prefect_api import prefect_api

    ws = workspace_path(request.workspace)
    with stops_cleanly(request.run_id, ws, request.to_dict(), len(checked.scenes)), prefect_api(), \
            run_progress(ws, request.run_id):
        return generate_dataset(request)


def planning_frames_warning(request) -> str | None:
    """What to say before a dataset run whose synthetic logs are too short for ``omniscs eval planning`` (a keyframe
    needs 3 s of future at 2 Hz); None when they are long enough, or when the run makes no dataset. A warning, not an
    error: the variants and detection evaluation do not need the future."""
    from omniscs.eval.planning import STEP_S, STEPS, frames_for_planning
    from omniscs.world.model import FRAME_PERIOD_US

    if not request.annotate or not any(str(s).startswith("syn:") for s in request.sources):
        return None
    rate_hz = 1e6 / FRAME_PERIOD_US
    needed = frames_for_planning(rate_hz)
    if request.n_frames >= needed:
        return None
    return (f"--frames {request.n_frames} is too few for planning evaluation (omniscs eval planning): a keyframe "
            f"needs {STEPS * STEP_S:g} s of future, so a synthetic log needs at least {needed} frames at "
            f"{rate_hz:g} Hz for one evaluated keyframe (and {round(STEP_S * rate_hz)} more for each further one); "
            "use e.g. --frames 40")


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


#: ``omniscs generate`` spellings of ``RunRequest`` fields whose option name is not the field's.
CLI_NAMES = {"n_frames": "--frames", "n_cameras": "--cameras", "edits": "--edit",
             "appearance_objects": "--appearance-object"}
#: How a field's help says what it takes, where its type alone does not.
CLI_VALUES = {"edits": "JSON or @file", "fit_preset": "fast|balanced|accurate",
              "behavior_preset": "fast|balanced|accurate", "task_runner": "threads|dask"}


def option_name(field: str) -> str:
    """The ``omniscs generate`` option of a ``RunRequest`` field."""
    return CLI_NAMES.get(field, "--" + field.replace("_", "-"))


def _request_parameters() -> list[inspect.Parameter]:
    """``omniscs generate``'s arguments, one per ``RunRequest`` field, help text from the field's docstring."""
    import typing

    from omniscs.pipeline.request import RunRequest

    params = []
    for name, field in RunRequest.model_fields.items():
        doc = " ".join((field.description or "").split())
        if name == "sources":
            params.insert(0, inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                               default=typer.Argument(..., help=doc), annotation=list[str]))
            continue
        kind = field.annotation
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        base = args[0] if typing.get_origin(kind) in (typing.Union, types.UnionType) and len(args) == 1 else kind
        default = field.get_default(call_default_factory=True)
        if name == "edits":
            annotation, default = Optional[str], None
        elif typing.get_origin(base) is list:
            annotation, default = Optional[list[str]], None
        elif base is bool:
            annotation = bool
        elif base is int:
            annotation = Optional[int] if default is None else int
        elif base is float:
            annotation = Optional[float] if default is None else float
        else:  # text, a path, or one of a few words (Literal)
            annotation = Optional[str] if default is None else str
        if name in CLI_VALUES:
            doc = f"{doc} [{CLI_VALUES[name]}]"
        if name == "appearance_objects":
            doc += " Repeat the option for several."
        flag = option_name(name)
        decls = [f"{flag}/--no-{flag[2:]}"] if base is bool else [flag]
        params.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=annotation,
                                        default=typer.Option(default, *decls, help=doc)))
    return params


def generate(**fields) -> None:
    """Run the generate_dataset flow: per scene ingest, plan, preview, fit, agents, background, behaviour and
    appearance variants, render + annotate, catalog; with --annotate, the run's dataset. Every option is a field
    of the run's request (omniscs.pipeline.request.RunRequest)."""
    from omniscs.edits import edit_to_dict

    fields["edits"] = [edit_to_dict(e) for e in read_edits(fields.get("edits"))]
    fields["appearance_objects"] = list(fields.get("appearance_objects") or ())
    from omniscs.errors import OmniscsError
    from omniscs.pipeline.request import RunRequest

    try:
        request = RunRequest.parse(fields)
    except OmniscsError as exc:  # name the option, not only the field
        field = str(exc).split(":", 1)[0]
        if field in fields and field != "sources":
            raise OmniscsError(f"{option_name(field)} ({exc})") from None
        raise
    result = run_generate(request)
    rows = [{"scene_id": s["scene_id"], **{stage: _state(r) for stage, r in s["stages"].items()}}
            for s in result["scenes"]]
    print_table(rows, title=f"run {result['run_id']}")
    console.print(f"run {result['run_id']}: {len(result['scenes'])} scene(s) in {result['workspace']}")
    if result.get("dataset_path"):
        from omniscs.annotate.dataset import gate_counts

        counts = gate_counts(result["dataset_gates"]) if result.get("dataset_gates") else ""
        console.print(f"dataset {result['dataset_id']}: {result['dataset_path']}  (omniscs dataset info "
                      f"{result['dataset_id']})" + (f"\n  variants: {counts}" if counts else ""))
        for warning in result.get("dataset_warnings") or []:
            print_error(warning, label="warning", style="yellow")


generate.__signature__ = inspect.Signature(_request_parameters())


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
    where = {"workspace": str(workspace)} if workspace is not None else {}
    result = run_generate({"sources": list(DEMO_SOURCES), "n_frames": DEMO_FRAMES, "previews": True, **where})
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
    built = run_generate({"sources": [DEMO_DATASET_SOURCE], "n_frames": DEMO_FRAMES, "previews": False,
                          "fit_preset": "fast", "behavior_variants": DEMO_DATASET_VARIANTS, "behavior_preset": "fast",
                          "annotate": True, "pool": str(pool), "appearance_variants": DEMO_APPEARANCE_VARIANTS,
                          **where})
    show_dataset(Path(built["dataset_path"]))
    console.print(f"demo finished in {time.perf_counter() - started:.1f} s")
