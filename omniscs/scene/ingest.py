"""Scene sources and ingest: turn what a user points at into a validated scene store in the workspace."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Union

from omniscs.errors import OmniscsError, ValidationError
from omniscs.scene.sources.common import FORMATS, DatasetSource
from omniscs.scene.store import load_scene
from omniscs.scene.synthetic import SyntheticSource, write_synthetic_scene


@dataclass(frozen=True)
class StoreSource:
    """An existing scene store on disk; ingest validates it and uses it in place."""

    path: str

    def to_dict(self) -> dict:
        return {"kind": "store", "path": self.path}


Source = Union[SyntheticSource, StoreSource, DatasetSource]


@dataclass(frozen=True)
class IngestResult:
    scene_id: str
    path: Path
    reused: bool
    """True when an identical scene store already existed and was reused instead of re-rendered."""


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


def scenes_dir(workspace: Path) -> Path:
    return Path(workspace) / "scenes"


def ingest(source: Source, workspace: Path, overwrite: bool = False,
           progress: Callable[[int, int], None] | None = None) -> IngestResult:
    """Validate or generate one scene store. Synthetic scenes already present with the same source are reused."""
    if isinstance(source, StoreSource):
        scene = load_scene(source.path)
        return IngestResult(scene.scene_id, scene.path, reused=True)
    if isinstance(source, DatasetSource):
        return ingest_dataset(source, scenes_dir(workspace), overwrite=overwrite, progress=progress)
    if not isinstance(source, SyntheticSource):
        raise OmniscsError(f"cannot ingest {source!r}")
    _check_synthetic(source)
    out = scenes_dir(workspace) / source.scene_id()
    if out.exists() and not overwrite:
        try:
            scene = load_scene(out)
            if scene.source == source.to_dict():
                return IngestResult(scene.scene_id, out, reused=True)
        except ValidationError:
            pass  # a damaged earlier result is regenerated below
        overwrite = True
    write_synthetic_scene(source, out, overwrite=overwrite, progress=progress)
    return IngestResult(source.scene_id(), out, reused=False)


def _check_synthetic(source: SyntheticSource) -> None:
    from omniscs.world import LIGHTINGS, TEMPLATES

    if source.template not in TEMPLATES:
        raise OmniscsError(f"unknown template {source.template!r}; use one of {list(TEMPLATES)}")
    if source.lighting not in LIGHTINGS:
        raise OmniscsError(f"unknown lighting {source.lighting!r}; use one of {list(LIGHTINGS)}")
    if not 1 <= source.n_cameras <= 6:
        raise OmniscsError(f"n_cameras must be 1..6; got {source.n_cameras}")
    if source.n_frames < 1 or source.width < 8 or source.height < 8:
        raise OmniscsError("need at least 1 frame and images of at least 8x8 pixels")


def ingest_dataset(source: DatasetSource, out_root: Path, overwrite: bool = False,
                   progress: Callable[[int, int], None] | None = None) -> IngestResult:
    """Read one dataset scene into ``out_root/<scene_id>``; a store already there from the same source and
    unchanged dataset files is reused."""
    from omniscs.scene.sources import current_fingerprint, read_dataset_scene, resolve

    source = resolve(source)
    out = Path(out_root) / source.scene_id()
    if out.exists() and not overwrite:
        try:
            scene = load_scene(out)
            if (scene.source == source.to_dict()
                    and scene.manifest.get("dataset_fingerprint") == current_fingerprint(source)):
                return IngestResult(scene.scene_id, out, reused=True)
        except ValidationError:
            pass  # a damaged earlier result is read again below
        overwrite = True
    read_dataset_scene(source, out, overwrite=overwrite, progress=progress)
    return IngestResult(source.scene_id(), out, reused=False)
