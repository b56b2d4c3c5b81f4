"""Readers of recorded driving datasets (nuScenes v1.0, KITTI tracking, Waymo Open Dataset v2) into the scene store."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable

from omniscs.errors import OmniscsError
from omniscs.scene.sources.common import (
    ATTRIBUTES,
    FORMATS,
    DatasetSource,
    SkippedFramesWarning,
    load_attributes,
    write_log,
)


def _module(fmt: str):
    if fmt == "nuscenes":
        from omniscs.scene.sources import nuscenes as module
    elif fmt == "kitti":
        from omniscs.scene.sources import kitti as module
    elif fmt == "waymo-v2":
        from omniscs.scene.sources import waymo_v2 as module
    else:
        raise OmniscsError(f"unknown dataset format {fmt!r}; use one of {list(FORMATS)}")
    return module


def list_scenes(fmt: str, dataroot: str | Path, version: str | None = None) -> list[str]:
    """The scene names (nuScenes), sequences (KITTI) or segments (Waymo v2) under ``dataroot``."""
    return _module(fmt).list_scenes(dataroot, version)


def open_reader(source: DatasetSource):
    """A reader opened on the source's scene (tables parsed, frames planned; no image read yet)."""
    module = _module(source.format)
    cls = {"nuscenes": "NuScenesReader", "kitti": "KittiReader", "waymo-v2": "WaymoV2Reader"}[source.format]
    return getattr(module, cls)(source)


def resolve(source: DatasetSource) -> DatasetSource:
    """The source with an absolute dataroot and its scene named (the only scene when none was given)."""
    root = Path(source.dataroot).expanduser()
    if not root.is_dir():
        raise OmniscsError(f"{source.format} dataroot {root} does not exist")
    source = replace(source, dataroot=str(root.resolve()))
    if source.scene is None:
        scenes = list_scenes(source.format, source.dataroot, source.version)
        if len(scenes) != 1:
            example = scenes[0] if scenes else "SCENE"
            raise OmniscsError(f"{root} holds {len(scenes)} scenes; name one, e.g. "
                               f"{source.format}:{root}:{example}")
        source = replace(source, scene=scenes[0])
    return source


def read_dataset_scene(source: DatasetSource, out_dir: str | Path, overwrite: bool = False,
                       progress: Callable[[int, int], None] | None = None) -> Path:
    """Read one scene of a dataset into a validated scene store at ``out_dir`` (atomically)."""
    source = resolve(source)
    return write_log(open_reader(source), Path(out_dir), overwrite=overwrite, progress=progress)


def current_fingerprint(source: DatasetSource) -> list:
    """The dataset files' sizes and times now, to compare with a stored scene's ``dataset_fingerprint``."""
    from omniscs.scene.sources.common import fingerprint

    source = resolve(source)
    return fingerprint(_module(source.format).dataset_files(source), Path(source.dataroot))


__all__ = ["ATTRIBUTES", "FORMATS", "DatasetSource", "SkippedFramesWarning", "current_fingerprint", "list_scenes",
           "load_attributes", "open_reader", "read_dataset_scene", "resolve"]
