"""The preview stage: a contact sheet (boxes projected into every camera) and a BEV plot of one scene."""
from __future__ import annotations

import time
from pathlib import Path

from omniscs.locks import output_lock
from omniscs.pipeline import layout
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.preview import write_previews
from omniscs.scene import load_scene

#: Bump when the code changes what the stage writes (older outputs are then not reused).
PREVIEW_VERSION = 1


def preview_stage(scene_path: str | Path, workspace: str | Path) -> StageRecord:
    """Contact sheet (boxes projected) and BEV plot under ``previews/<scene_id>/``."""
    started = time.perf_counter()
    scene = load_scene(scene_path)
    key = StageKey.of("preview", PREVIEW_VERSION, scene.content_hash, {})
    out = layout.scene_folder(workspace, "preview", scene.scene_id)
    with output_lock(out):
        reused = reusable(out, key) is not None
        if not reused:
            produce(out, key, lambda tmp: {k: p.name for k, p in write_previews(scene, tmp).items()})
    return StageRecord("preview", scene.scene_id, str(out), reused=reused, seconds=time.perf_counter() - started,
                       key=key.digest)


