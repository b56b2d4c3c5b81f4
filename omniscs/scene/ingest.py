"""Scene sources and ingest: turn what a user points at into a validated scene store in the workspace."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Union

from omniscs.errors import OmniscsError
from omniscs.scene.sources.common import FORMATS, DatasetSource
from omniscs.scene.synthetic import SyntheticSource, write_synthetic_scene


@dataclass(frozen=True)
class StoreSource:
    """An existing scene store on disk; ingest validates it and uses it in place."""

    path: str

    def to_dict(self) -> dict:
        return {"kind": "store", "path": self.path}


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
        if len(parts) not in (3, 4) or not parts[2].lstrip("-").isdigit():
            raise OmniscsError(f"bad synthetic source {text!r}; write syn:TEMPLATE:SEED[:LIGHTING], e.g. syn:straight:0:night")
        fields = dict(template=parts[1], seed=int(parts[2]), **synthetic_defaults)
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
    kind = d.get("kind")
    fields = {k: v for k, v in d.items() if k != "kind"}
    if kind == "synthetic":
        return SyntheticSource(**fields)
    if kind == "store":
        return StoreSource(**fields)
    if kind in FORMATS:
        return DatasetSource.from_dict(d)
    raise OmniscsError(f"unknown source kind {kind!r}; use 'synthetic', 'store' or one of {list(FORMATS)}")


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


def check_synthetic(source: SyntheticSource) -> None:
    from omniscs.world import LIGHTINGS, TEMPLATES

    if source.template not in TEMPLATES:
        raise OmniscsError(f"unknown template {source.template!r}; use one of {list(TEMPLATES)}")
    if source.lighting not in LIGHTINGS:
        raise OmniscsError(f"unknown lighting {source.lighting!r}; use one of {list(LIGHTINGS)}")
    if not 1 <= source.n_cameras <= 6:
        raise OmniscsError(f"n_cameras must be 1..6; got {source.n_cameras}")
    if source.n_frames < 1 or source.width < 8 or source.height < 8:
        raise OmniscsError("need at least 1 frame and images of at least 8x8 pixels")
