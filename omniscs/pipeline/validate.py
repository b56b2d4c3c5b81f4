"""Everything a run is given, checked once before any work starts: the sources (they exist and parse), the
request's outside-world parts (the pool, the traffic-model checkpoint, the device, the edits) and the task runner.
A bad input is one OmniscsError line; the CLI refuses it before Prefect starts, and the flow records it in its
``runs`` row before any task runs. The CLI and the flow share one check per run (``check_run``)."""
from __future__ import annotations

import json
import socket
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlparse

from omniscs.devices import resolve_device
from omniscs.errors import OmniscsError, ValidationError
from omniscs.ids import check_id
from omniscs.pipeline.appearance import pool_objects
from omniscs.pipeline.request import MAX_WORKERS, RunRequest, SceneRequest
from omniscs.scene import DatasetSource, StoreSource, SyntheticSource, check_synthetic, parse_source
from omniscs.scene.sources import resolve
from omniscs.scs.behavior.checkpoint import load_traffic_model

#: Task runners a run can use (flows/runners.py builds them).
TASK_RUNNERS = ("threads", "dask")
#: How long a Dask scheduler may take to answer before the run is refused (seconds).
SCHEDULER_TIMEOUT_S = 5.0



@dataclass(frozen=True)
class CheckedSource:
    """A source as the user wrote it, parsed (a recorded scene resolved to its dataset scene), and the id of the
    scene store it becomes."""

    text: str
    source: dict
    scene_id: str


def check_source(text: str, n_frames: int = 40, n_cameras: int = 3, width: int = 480,
                 height: int = 270) -> CheckedSource:
    """One source, parsed and checked as far as it can be without rendering or reading it: a synthetic
    source's template, seed and lighting; a recorded dataset's root and scene; a scene store's manifest."""
    if not isinstance(text, str) or not text.strip():
        raise OmniscsError(f"empty source {text!r}; give syn:TEMPLATE:SEED[:LIGHTING], FORMAT:DATAROOT[:SCENE] or "
                           "a scene-store path")
    src = parse_source(text, n_frames=n_frames, n_cameras=n_cameras, width=width, height=height)
    if isinstance(src, SyntheticSource):
        if not 0 <= src.seed < 2 ** 32:
            raise OmniscsError(f"bad seed {src.seed} in {text!r}; seeds are integers from 0 to {2 ** 32 - 1}")
        check_synthetic(src)
        scene_id = src.scene_id()
    elif isinstance(src, DatasetSource):
        src = resolve(src)  # the dataset's scene exists and its defining files are readable
        scene_id = src.scene_id()
    elif isinstance(src, StoreSource):
        scene_id = src.verify().scene_id  # every file checked, so a damaged store fails before any work
    else:  # pragma: no cover - parse_source returns one of the above
        raise OmniscsError(f"cannot use source {text!r}")
    return CheckedSource(text, src.to_dict(), check_id("scene id", scene_id))


def check_sources(sources, n_frames: int = 40, n_cameras: int = 3, width: int = 480,
                  height: int = 270) -> tuple[list[CheckedSource], list[str]]:
    """Every source checked (the first bad one is the error); a scene named twice (the same text twice, or a
    synthetic source and the store it was rendered into) is kept once. Returns the scenes to run and the
    sources that were dropped as repeats."""
    if isinstance(sources, str) or not sources:
        raise OmniscsError("give at least one source (a list of syn:TEMPLATE:SEED[:LIGHTING], "
                           "FORMAT:DATAROOT[:SCENE] or scene-store paths)")
    kept: dict[str, CheckedSource] = {}
    repeats = []
    for text in sources:
        checked = check_source(text, n_frames, n_cameras, width, height)
        if checked.scene_id in kept:
            repeats.append(text)
        else:
            kept[checked.scene_id] = checked
    return list(kept.values()), repeats


def check_request(request: SceneRequest | dict) -> SceneRequest:
    """The request's outside-world parts: its edits parse, its pool is a folder holding the appearance objects,
    its traffic-model checkpoint loads and its device exists here (its fields were checked when it was made)."""
    request = SceneRequest.parse(request) if isinstance(request, dict) else request
    request.parsed_edits()
    if request.pool is not None and not Path(request.pool).is_dir():
        raise ValidationError(f"pool {request.pool} is not a folder (make one with omniscs pool build or import)")
    if request.appearance_variants > 0:  # the objects must be in the pool before any scene starts

        pool_objects(request.pool, request.appearance_objects)
    if request.behavior_variants > 0 or request.behavior_checkpoint is not None:
        load_traffic_model(request.behavior_checkpoint)
    resolve_device(request.device)
    return request


@dataclass(frozen=True)
class CheckedRun:
    """A run's request after its one check: the scenes to run (each source parsed, a repeat dropped) and the
    sources dropped as repeats."""

    request: RunRequest
    scenes: tuple[CheckedSource, ...]
    repeats: tuple[str, ...]


#: Runs the CLI checked before starting the flow in this process, by their request's JSON: the flow takes its
#: check from here once (a deployment's run, or a direct call, is checked by the flow itself).
_CHECKED: dict[str, CheckedRun] = {}


def check_run(request: RunRequest | dict, hand_on: bool = False) -> CheckedRun:
    """Every input of a run, checked once per run: the request's fields, its outside-world parts, the sources with
    the synthetic rig, and the task runner (a Dask scheduler must answer now). ``hand_on``: the caller starts the
    flow next in this process (the CLI), which then takes this check instead of making it again."""
    request = RunRequest.parse(request)
    key = json.dumps(request.to_dict(), sort_keys=True)
    if not hand_on and key in _CHECKED:
        return _CHECKED.pop(key)
    check_request(request.scene_request())
    scenes, repeats = check_sources(request.sources, request.n_frames, request.n_cameras, request.width,
                                    request.height)
    check_runner(request.task_runner, request.workers, request.dask_address)
    checked = CheckedRun(request, tuple(scenes), tuple(repeats))
    if hand_on:
        _CHECKED[key] = checked
    return checked


def check_run_id(run_id: str | None) -> str | None:
    """A run id given by the user must be a safe id (it names a catalog partition)."""
    return None if run_id is None else check_id("run id", run_id)


def check_runner(task_runner: str, workers: int | None, dask_address: str | None) -> None:
    """One clear error for a bad choice, before any scene starts (the scheduler must answer now)."""
    if task_runner not in TASK_RUNNERS:
        raise ValidationError(f"task_runner must be one of {TASK_RUNNERS}; got {task_runner!r}")
    if workers is not None and not 1 <= int(workers) <= MAX_WORKERS:
        raise ValidationError(f"workers must be between 1 and {MAX_WORKERS}; got {workers}")
    if dask_address is not None:
        if task_runner != "dask":
            raise ValidationError("dask_address needs task_runner='dask'")
        if workers is not None:
            raise ValidationError("workers is for a local Dask cluster; an existing scheduler has its own workers")
        _reach_scheduler(dask_address)


def _reach_scheduler(address: str) -> None:
    url = urlparse(address if "://" in address else f"tcp://{address}")
    if url.scheme not in ("tcp", "tls") or not url.hostname or not url.port:
        raise ValidationError(f"Dask scheduler address {address!r} must look like tcp://HOST:PORT")
    try:
        with socket.create_connection((url.hostname, url.port), timeout=SCHEDULER_TIMEOUT_S):
            pass
    except OSError as e:
        raise OmniscsError(f"the Dask scheduler at {address} is unreachable ({e}); start it (dask scheduler) "
                           "or leave dask_address out for a local cluster") from None
