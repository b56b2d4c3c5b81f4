"""The ingest stage: one source (synthetic, a recorded dataset's scene, or a scene store) as a validated scene
store, reused when the same source (and unchanged dataset files) was ingested before."""
from __future__ import annotations

import time
from pathlib import Path

from omniscs.ids import check_id
from omniscs.locks import output_lock
from omniscs.pipeline import layout
from omniscs.pipeline.common import waiting
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, mark_done, reusable
from omniscs.progress import Progress, no_progress
from omniscs.scene import (DatasetSource, StoreSource, SyntheticSource, load_scene, parse_source, source_from_dict,
                           write_source_scene)
from omniscs.scene.sources import current_fingerprint, resolve
from omniscs.scene.store import SCHEMA_VERSION

#: Bump when the code changes what the stage writes (older outputs are then not reused).
INGEST_VERSION = 1


def as_source(source) -> SyntheticSource | StoreSource | DatasetSource:
    """A source given parsed, as its dict, or as its text."""
    if isinstance(source, (SyntheticSource, StoreSource, DatasetSource)):
        return source
    if isinstance(source, dict):
        return source_from_dict(source)
    return parse_source(str(source))


def ingest_stage(source, workspace: str | Path, progress: Progress = no_progress,
                 scenes_root: str | Path | None = None, reuse: bool = True) -> StageRecord:
    """One source (a parsed source, its dict, or its text) as a validated scene store under
    ``scenes_root`` (default ``<workspace>/scenes``). A store made from the same source (and, for recorded
    datasets, unchanged dataset files) is reused unless ``reuse`` is False; an existing scene-store path is
    used in place."""
    started = time.perf_counter()
    src = as_source(source)
    if isinstance(src, StoreSource):
        scene = src.verify()  # used in place: every file checked against the sizes and hashes it was written with
        return StageRecord("ingest", scene.scene_id, str(scene.path), reused=True,
                           seconds=time.perf_counter() - started, info={"source": src.to_dict()})
    fingerprint = None
    if isinstance(src, DatasetSource):
        src = resolve(src)
        fingerprint = current_fingerprint(src)
    key = StageKey.of("ingest", INGEST_VERSION, src.to_dict(), {"dataset_files": fingerprint,
                                                                "schema": SCHEMA_VERSION})
    out = Path(scenes_root) if scenes_root is not None else layout.scenes_dir(workspace)
    out = out / check_id("scene id", src.scene_id())
    with output_lock(out, waiting(progress, out)):
        reused = reuse and reusable(out, key) is not None
        if not reused:
            write_source_scene(src, out, progress=progress)
            mark_done(out, key, {"scene_store": "."}, time.perf_counter() - started)
    scene = load_scene(out)  # validates a reused store as well
    return StageRecord("ingest", scene.scene_id, str(out), reused=reused, seconds=time.perf_counter() - started,
                       key=key.digest, info={"source": src.to_dict()})


