"""Scene sources and ingest: turn what a user points at into a validated scene store in the workspace."""
from __future__ import annotations

import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Callable, Union

import numpy as np

from omniscs.checks import MAX_SEED, check_seed
from omniscs.errors import OmniscsError
from omniscs.scene.sources.common import FORMATS, DatasetSource
from omniscs.scene.store import verify_store
from omniscs.scene.synthetic import SyntheticSource, write_synthetic_scene


@dataclass(frozen=True)
class StoreSource:
    """An existing scene store on disk; ingest validates it and uses it in place."""

    path: str

    def __post_init__(self):
        if isinstance(self.path, os.PathLike):
            object.__setattr__(self, "path", os.fspath(self.path))
        if not isinstance(self.path, str) or not self.path:
            raise OmniscsError(f"a store source needs the path of a scene store; got {self.path!r}")

    def to_dict(self) -> dict:
        return {"kind": "store", "path": self.path}

    def verify(self, progress: Callable[[int, int], None] | None = None):
        """The store, fully checked (``omniscs.scene.store.verify_store``: every file's sha256, or a decode of
        every file for stores written before sizes and hashes were recorded): what ingest uses in place."""
        return verify_store(self.path, progress=progress)


Source = Union[SyntheticSource, StoreSource, DatasetSource]


def parse_source(text: str, **synthetic_defaults) -> Source:
    """``syn:TEMPLATE:SEED[:LIGHTING]`` for a procedural log, ``FORMAT:DATAROOT[:SCENE]`` for a scene of a
    recorded dataset (FORMAT: nuscenes, kitti, waymo-v2), or the path of a scene store.

    ``synthetic_defaults`` (n_frames, n_cameras, width, height) apply to synthetic sources only.
    """
    fmt, sep, rest = text.partition(":")
    if sep and fmt in FORMATS:
        return _parse_dataset_source(fmt, rest)
    if text.startswith("syn:"):
        parts = text.split(":")
        # ASCII digits only: str.isdigit and int() also take other scripts' digits ("٥" would become seed 5)
        if len(parts) not in (3, 4) or not (parts[2].isascii() and parts[2].isdigit()):
            raise OmniscsError(f"bad synthetic source {text!r}; write syn:TEMPLATE:SEED[:LIGHTING] with SEED a whole "
                               f"number from 0 to {MAX_SEED} in ASCII digits, e.g. syn:straight:0:night")
        fields = dict(template=parts[1], seed=check_seed(int(parts[2]), f"the seed of {text!r}"),
                      **synthetic_defaults)
        if len(parts) == 4:
            fields["lighting"] = parts[3]
        return SyntheticSource(**fields)
    path = Path(text)
    if not path.exists():
        raise OmniscsError(f"source {text!r} is neither syn:TEMPLATE:SEED nor an existing scene-store directory")
    return StoreSource(str(path.resolve()))


def _parse_dataset_source(fmt: str, rest: str) -> DatasetSource:
    """``DATAROOT[:SCENE]``; a nuScenes dataroot may end in its table folder (``/data/nuscenes/v1.0-mini``)."""
    if not rest:
        raise OmniscsError(f"bad {fmt} source; write {fmt}:DATAROOT[:SCENE], e.g. {fmt}:/data/{fmt}")
    root, scene = rest, None
    if not Path(rest).is_dir() and ":" in rest:
        root, _, scene = rest.rpartition(":")
    path = Path(root).expanduser()
    if not path.is_dir():
        raise OmniscsError(f"{fmt} dataroot {root!r} is not a directory")
    version = None
    if fmt == "nuscenes" and path.name.startswith("v1.0") and (path / "scene.json").is_file():
        path, version = path.parent, path.name
    return DatasetSource(fmt, str(path.resolve()), scene or None, version=version)


def source_from_dict(d: dict) -> Source:
    """A source from its dict form (``to_dict``); a wrong kind, an unknown or missing field or a value of the wrong
    type is one OmniscsError."""
    if not isinstance(d, dict):
        raise OmniscsError(f"a source must be a JSON object with a 'kind'; got {d!r}")
    kind = d.get("kind")
    if kind in FORMATS:
        return DatasetSource.from_dict(d)
    classes = {"synthetic": SyntheticSource, "store": StoreSource}
    if kind not in classes:
        raise OmniscsError(f"unknown source kind {kind!r}; use 'synthetic', 'store' or one of {list(FORMATS)}")
    cls = classes[kind]
    args = {k: v for k, v in d.items() if k != "kind"}
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(args) - set(names))
    if unknown:
        raise OmniscsError(f"unknown field(s) {unknown} for a {kind} source; it takes {names}")
    try:
        source = cls(**args)
    except TypeError as exc:
        raise OmniscsError(f"bad {kind} source {d!r}: {exc}") from None
    if isinstance(source, SyntheticSource):
        check_synthetic_fields(source)
    return source


def write_source_scene(source: Source, out: Path, progress: Callable[[int, int], None] | None = None) -> Path:
    """Render (synthetic) or read (recorded dataset) one source into the scene store ``out``, replacing what is
    there; returns ``out``. Whether an earlier store can be reused is the ingest stage's decision."""
    if isinstance(source, DatasetSource):
        from omniscs.scene.sources import read_dataset_scene

        read_dataset_scene(source, out, overwrite=True, progress=progress)
    elif isinstance(source, SyntheticSource):
        check_synthetic(source)
        write_synthetic_scene(source, out, overwrite=True, progress=progress)
    else:
        raise OmniscsError(f"cannot write a scene store from {source!r}")
    return Path(out)


#: Largest synthetic log and image a source may ask for (a typo such as 40000 frames is refused, not rendered).
MAX_SYNTHETIC_FRAMES = 10_000
MAX_SYNTHETIC_SIDE = 8192


def check_synthetic_fields(source: SyntheticSource) -> None:
    """The source's fields have the right types and sizes within bounds (templates are checked when rendering)."""
    for name in ("seed", "n_frames", "n_cameras", "width", "height"):
        value = getattr(source, name)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise OmniscsError(f"synthetic source field {name} must be an integer; got {value!r}")
    check_seed(source.seed, "synthetic source field seed")
    for name in ("template", "lighting"):
        if not isinstance(getattr(source, name), str):
            raise OmniscsError(f"synthetic source field {name} must be a string; got {getattr(source, name)!r}")
    if source.n_frames > MAX_SYNTHETIC_FRAMES or max(source.width, source.height) > MAX_SYNTHETIC_SIDE:
        raise OmniscsError(f"synthetic logs are limited to {MAX_SYNTHETIC_FRAMES} frames and images of "
                           f"{MAX_SYNTHETIC_SIDE} pixels a side; got {source.n_frames} frames of "
                           f"{source.width}x{source.height}")


def check_synthetic(source: SyntheticSource) -> None:
    from omniscs.world import LIGHTINGS, TEMPLATES

    check_synthetic_fields(source)
    if source.template not in TEMPLATES:
        raise OmniscsError(f"unknown template {source.template!r}; use one of {list(TEMPLATES)}")
    if source.lighting not in LIGHTINGS:
        raise OmniscsError(f"unknown lighting {source.lighting!r}; use one of {list(LIGHTINGS)}")
    if not 1 <= source.n_cameras <= 6:
        raise OmniscsError(f"n_cameras must be 1..6; got {source.n_cameras}")
    if source.n_frames < 1 or source.width < 8 or source.height < 8:
        raise OmniscsError("need at least 1 frame and images of at least 8x8 pixels")
