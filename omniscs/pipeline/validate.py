"""Everything a run is given, checked before any work starts: the sources, the synthetic sensor rig, the request
(presets, variants, checkpoint, edits, device) and the run id. A bad input is one OmniscsError line; the CLI
refuses it before Prefect starts, and the flow records it in its ``runs`` row before any task runs."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from omniscs.checks import is_int
from omniscs.errors import OmniscsError, ValidationError
from omniscs.ids import check_id
from omniscs.pipeline.records import SceneRequest

#: Bounds of the synthetic sensor rig (frames at 10 Hz, cameras in nuScenes placement, image size in pixels).
FRAMES = (1, 10_000)
CAMERAS = (1, 6)
IMAGE_SIDE = (8, 4096)
#: The synthetic rig when a caller names none (the defaults of ``generate_dataset`` and ``omniscs generate``).
RIG_DEFAULTS = {"n_frames": 40, "n_cameras": 3, "width": 480, "height": 270}
#: Most behaviour variants one scene may ask for.
MAX_BEHAVIOR_VARIANTS = 1000


@dataclass(frozen=True)
class CheckedSource:
    """A source as the user wrote it, parsed (a recorded scene resolved to its dataset scene), and the id of the
    scene store it becomes."""

    text: str
    source: dict
    scene_id: str


def _int_in(name: str, value, bounds: tuple[int, int]) -> int:
    lo, hi = bounds
    if not is_int(value) or not lo <= value <= hi:
        raise OmniscsError(f"{name} must be an integer from {lo} to {hi}; got {value!r}")
    return value


def check_rig(n_frames: int, n_cameras: int, width: int, height: int) -> None:
    """The synthetic sensor rig's numbers."""
    _int_in("--frames (n_frames)", n_frames, FRAMES)
    _int_in("--cameras (n_cameras)", n_cameras, CAMERAS)
    _int_in("--width", width, IMAGE_SIDE)
    _int_in("--height", height, IMAGE_SIDE)


def check_source(text: str, n_frames: int = 40, n_cameras: int = 3, width: int = 480,
                 height: int = 270) -> CheckedSource:
    """One source, parsed and checked as far as it can be without rendering or reading it: a synthetic
    source's template, seed and lighting; a recorded dataset's root and scene; a scene store's manifest."""
    from omniscs.scene import DatasetSource, StoreSource, SyntheticSource, check_synthetic, parse_source

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
        from omniscs.scene.sources import resolve

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
    check_rig(n_frames, n_cameras, width, height)
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
    """The request's presets and counts (``SceneRequest`` checks them), its edits, its traffic-model checkpoint
    (it must load) and its device (it must exist here)."""
    from omniscs.devices import resolve_device

    if isinstance(request, dict):
        try:
            request = SceneRequest.from_dict(request)
        except TypeError as exc:
            raise OmniscsError(f"bad request: {exc}") from None
    if request.behavior_variants > MAX_BEHAVIOR_VARIANTS:
        raise OmniscsError(f"behavior_variants must be at most {MAX_BEHAVIOR_VARIANTS}; got "
                           f"{request.behavior_variants}")
    if request.appearance_variants > MAX_BEHAVIOR_VARIANTS:
        raise OmniscsError(f"appearance_variants must be at most {MAX_BEHAVIOR_VARIANTS}; got "
                           f"{request.appearance_variants}")
    request.parsed_edits()
    if request.pool is not None and not Path(request.pool).is_dir():
        raise ValidationError(f"pool {request.pool} is not a folder (make one with omniscs pool build or import)")
    if request.appearance_variants > 0:  # the objects must be in the pool before any scene starts
        from omniscs.pipeline.appearance import pool_objects

        pool_objects(request.pool, request.appearance_objects)
    if request.behavior_variants > 0 or request.behavior_checkpoint is not None:
        from omniscs.scs.behavior.checkpoint import load_checkpoint

        load_checkpoint(request.behavior_checkpoint)
    resolve_device(request.device)
    return request


def check_run_id(run_id: str | None) -> str | None:
    """A run id given by the user must be a safe id (it names a catalog partition)."""
    return None if run_id is None else check_id("run id", run_id)


def run_config(sources, n_frames: int, n_cameras: int, width: int, height: int, **request_fields) -> dict:
    """The run's configuration as given (before checking), as its ``runs`` row records it: the sources, the
    synthetic rig and the request's fields (``SceneRequest``'s names)."""
    return {"sources": [sources] if isinstance(sources, str) else list(sources), "n_frames": n_frames,
            "n_cameras": n_cameras, "width": width, "height": height,
            **{k: list(v) if k == "edits" else v for k, v in request_fields.items()}}
