"""The logged views replayed through a fitted scene graph: every camera of every frame rendered at its logged pose,
unedited, and compared with the logged image. A product of the graph alone, made once per fit (the pipeline's
``replay`` output, reused by every annotate run on that graph: new variants, another annotate config), so the
fidelity proxies of a recorded log (``omniscs.annotate.fidelity``: ``logged_psnr`` and the feature drift against
the unedited render) cost a PNG read per view instead of a rendering. The PNGs hold exactly the uint8 image the
annotator would render (lossless), so annotations are the same with and without a replay.

Layout: ``views.parquet`` (camera, frame_idx, logged_psnr: the render against the logged image, how well the graph
reproduces that view) and ``images/<camera>/<frame:06d>.png``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np
import pandas as pd

from omniscs.errors import OmniscsError, ValidationError
from omniscs.progress import Progress, no_progress

VIEWS_PARQUET = "views.parquet"
IMAGES = "images"


def _png(root: Path, camera: str, frame: int) -> Path:
    return root / IMAGES / camera / f"{frame:06d}.png"


def write_replay(out_dir: str | Path, views: Iterable[tuple[str, int, np.ndarray, float | None]],
                 total: int | None = None, progress: Progress = no_progress) -> dict:
    """Write ``views`` ((camera, frame, uint8 [H, W, 3] unedited render, logged PSNR or None) each) into
    ``out_dir`` (layout above); returns {n_views, mean logged PSNR}. ``annotate.scene.replay_scene`` renders them."""
    out = Path(out_dir)
    rows = []
    for i, (cam, frame, rgb, logged_psnr) in enumerate(views):
        path = _png(out, cam, frame)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OmniscsError(f"could not write {path}")
        rows.append({"camera": cam, "frame_idx": int(frame),
                     "logged_psnr": None if logged_psnr is None or not np.isfinite(logged_psnr) else logged_psnr})
        progress(i + 1, total, "logged views replayed")
    table = pd.DataFrame(rows, columns=["camera", "frame_idx", "logged_psnr"]).astype(
        {"camera": str, "frame_idx": "int64", "logged_psnr": "float64"})
    table.to_parquet(out / VIEWS_PARQUET, index=False)
    psnrs = table.logged_psnr.dropna()
    return {"n_views": len(table), "mean_logged_psnr": float(psnrs.mean()) if len(psnrs) else None}


@dataclass
class Replay:
    """A replay folder read back: the unedited render and logged PSNR of each logged view."""

    folder: Path
    _psnr: dict[tuple[str, int], float | None] = field(default_factory=dict, repr=False)

    @classmethod
    def open(cls, folder: str | Path) -> "Replay":
        folder = Path(folder)
        try:
            table = pd.read_parquet(folder / VIEWS_PARQUET)
        except (OSError, ValueError) as e:
            raise ValidationError(f"{folder} is not a readable replay ({VIEWS_PARQUET}: {e})") from e
        psnr = {(str(c), int(f)): (None if pd.isna(p) else float(p))
                for c, f, p in zip(table.camera, table.frame_idx, table.logged_psnr)}
        return cls(folder, psnr)

    def __contains__(self, view: tuple[str, int]) -> bool:
        return view in self._psnr

    def __len__(self) -> int:
        return len(self._psnr)

    def view(self, camera: str, frame: int) -> tuple[np.ndarray, float | None]:
        """(uint8 [H, W, 3] RGB, logged PSNR or None) of the logged view; a clear error when it is missing."""
        if (camera, frame) not in self._psnr:
            raise OmniscsError(f"replay {self.folder} has no view {camera} frame {frame}")
        path = _png(self.folder, camera, frame)
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValidationError(f"replay image {path} is missing or unreadable")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), self._psnr[(camera, frame)]
