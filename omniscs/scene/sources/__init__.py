"""Readers of recorded driving datasets (nuScenes v1.0, KITTI tracking, Waymo Open Dataset v2) into the scene store."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable

from omniscs.errors import OmniscsError, ValidationError
from omniscs.scene.sources.common import (ATTRIBUTES, FORMATS, UNEXPECTED_READ_ERRORS, BadFrame, DatasetSource,
                                          SkippedFramesWarning, check_frame_files, fingerprint, load_attributes,
                                          reader_failure, write_log)


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
    """A reader opened on the source's scene (tables parsed, frames planned; no image read yet).

    Data that is not in the format's layout is one ValidationError naming the file (and field where known)."""
    module = _module(source.format)
    cls = {"nuscenes": "NuScenesReader", "kitti": "KittiReader", "waymo-v2": "WaymoV2Reader"}[source.format]
    try:
        return getattr(module, cls)(source)
    except BadFrame as bad:  # a file the reader needed up front (e.g. an image to learn a camera's size)
        raise ValidationError(str(bad)) from None
    except UNEXPECTED_READ_ERRORS as exc:
        raise reader_failure(source, exc, "the tables") from None


def resolve(source: DatasetSource) -> DatasetSource:
    """The source with an absolute dataroot and its scene named (the only scene when none was given), after
    checking that the scene exists and its defining files are there and readable: a source that cannot be read
    fails here, before anything is written (the pipeline resolves every source before work starts)."""
    if not isinstance(source, DatasetSource):
        raise OmniscsError(f"not a dataset source: {source!r}")
    module = _module(source.format)
    root = Path(source.dataroot).expanduser()
    if not root.is_dir():
        raise OmniscsError(f"{source.format} dataroot {root} does not exist")
    source = replace(source, dataroot=str(root.resolve()))
    try:
        if source.scene is None:
            scenes = list_scenes(source.format, source.dataroot, source.version)
            if len(scenes) != 1:
                example = scenes[0] if scenes else "SCENE"
                raise OmniscsError(f"{root} holds {len(scenes)} scenes; name one, e.g. "
                                   f"{source.format}:{root}:{example}")
            source = replace(source, scene=scenes[0])
        module.check_scene(source)
    except UNEXPECTED_READ_ERRORS as exc:
        raise reader_failure(source, exc, "the scene list") from None
    return source


def validate_source(source: DatasetSource) -> DatasetSource:
    """``resolve`` plus opening the reader (every table parsed, cameras and frames checked) and, unless bad frames
    are to be skipped, a stat of every per-frame file: what can be known about a source without decoding images,
    for a pipeline that checks all its sources before any work starts. Returns the resolved source."""
    source = resolve(source)
    reader = open_reader(source)
    if not source.skip_bad_frames:
        check_frame_files(reader)
    return source


def read_dataset_scene(source: DatasetSource, out_dir: str | Path, overwrite: bool = False,
                       progress: Callable[[int, int], None] | None = None) -> Path:
    """Read one scene of a dataset into a validated scene store at ``out_dir`` (atomically)."""
    source = resolve(source)
    return write_log(open_reader(source), Path(out_dir), overwrite=overwrite, progress=progress)


def current_fingerprint(source: DatasetSource) -> list:
    """The dataset files' sizes and times now, to compare with a stored scene's ``dataset_fingerprint``."""
    source = resolve(source)
    return fingerprint(_module(source.format).dataset_files(source), Path(source.dataroot))


__all__ = ["ATTRIBUTES", "FORMATS", "DatasetSource", "SkippedFramesWarning", "current_fingerprint", "list_scenes",
           "load_attributes", "open_reader", "read_dataset_scene", "resolve", "validate_source"]
