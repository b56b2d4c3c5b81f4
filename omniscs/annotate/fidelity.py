"""How far a rendered variant frame can be trusted.

Two measures, both per frame and camera and summarised per variant:

- ``image_fidelity``: PSNR / SSIM against an exact reference image of the same variant (procedural scenes,
  where the world renders the edited scene exactly), over the whole image and over the instances.
- ``feature_drift``: for recorded logs, where no reference of the edited scene exists, the rendered variant frame
  is compared with the scene graph's *unedited* render of the same source frame and camera at the logged pose
  (the render closest to what was observed). The pixels any moved agent covers in either image (its mask and
  projected box) are left out, so the drift reflects what the edit should not have changed: the background
  seen from the ego's new pose (the solution's novel viewpoint) and whatever a moved node dragged along or left
  behind. The descriptor is a coarse grid of cells, each holding a histogram of gradient orientations
  (magnitude-weighted, 8 unsigned bins, L2-normalised, as in HOG) and the cell's mean colour; the drift is the mean
  over cells valid in both images of (1 - cosine similarity) of the cell vectors, in [0, 1]: 0 for the same
  structure, growing with blur, holes, smears and viewpoint change. Coarse cells make a shift of a few pixels
  cost little. It is a hand-made proxy (no pretrained network is available offline), checked on procedural scenes
  against the exact PSNR (``omniscs bench dataset``).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from omniscs.quality import psnr, ssim, ssim_map

#: Descriptor grid (rows, columns) over the image.
DRIFT_CELLS = (6, 8)
#: Gradient orientation bins over [0, pi).
DRIFT_BINS = 8
#: A cell counts when at least this fraction of its pixels is kept in both images.
DRIFT_MIN_KEPT = 0.25
#: Weight of the cell's mean colour (0..1 per channel) beside its unit-length orientation histogram.
DRIFT_COLOUR_WEIGHT = 1.0
_EPS = 1e-9


def finite_or_none(x) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def image_fidelity(rendered: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> dict:
    """PSNR / SSIM of a rendered frame against its reference, over the image and over ``mask`` (None when empty)."""
    r = torch.from_numpy(rendered.astype(np.float32) / 255.0)
    g = torch.from_numpy(reference.astype(np.float32) / 255.0)
    m = torch.from_numpy(mask)
    smap = ssim_map(r, g)
    return {"psnr": psnr(r, g), "ssim": finite_or_none(ssim(r, g, smap=smap)),
            "masked_psnr": psnr(r, g, m), "masked_ssim": finite_or_none(ssim(r, g, m, smap=smap))}


def structure_descriptor(rgb: np.ndarray,  # uint8 [H, W, 3]
                         keep: np.ndarray,  # bool [H, W]
                         cells: tuple[int, int] = DRIFT_CELLS) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of a ``cells`` grid: [DRIFT_BINS + 3] (unit orientation histogram, mean colour) over the kept
    pixels, and the fraction of the cell's pixels kept. A cell with no pixel kept (or none at all) is zero.
    Gradients of the grey image (mean of the channels) by central differences, one-sided at the borders (as
    ``np.gradient``); one pass over the pixels (``_cell_sums``)."""
    rows, cols = cells
    hist, colour, kept_n, pixels = _cell_sums(np.ascontiguousarray(rgb, dtype=np.uint8),
                                              np.ascontiguousarray(keep, dtype=np.bool_), rows, cols, DRIFT_BINS)
    hist /= np.linalg.norm(hist, axis=1, keepdims=True) + _EPS
    colour /= np.maximum(kept_n, 1.0)[:, None]
    out = np.concatenate([hist, DRIFT_COLOUR_WEIGHT * colour], 1).reshape(rows, cols, DRIFT_BINS + 3)
    kept = np.where(pixels > 0, kept_n / np.maximum(pixels, 1.0), 0.0).reshape(rows, cols)
    return out, kept


@nb.njit(cache=True, nogil=True)
def _cell_sums(rgb, keep, rows, cols, bins):  # -> hist [C, bins], colour [C, 3], kept_n [C], pixels [C]
    """Per cell: magnitude-weighted orientation histogram and colour sums over the kept pixels, kept and total
    pixel counts."""
    h, w = keep.shape
    n_cells = rows * cols
    hist = np.zeros((n_cells, bins))
    colour = np.zeros((n_cells, 3))
    kept_n = np.zeros(n_cells)
    pixels = np.zeros(n_cells)
    grey = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            grey[y, x] = (float(rgb[y, x, 0]) + float(rgb[y, x, 1]) + float(rgb[y, x, 2])) / (3.0 * 255.0)
    col_of = np.empty(w, np.int64)
    for x in range(w):
        col_of[x] = min((x * cols) // w, cols - 1)
    for y in range(h):
        row = min((y * rows) // h, rows - 1)
        for x in range(w):
            c = row * cols + col_of[x]
            pixels[c] += 1.0
            if not keep[y, x]:
                continue
            kept_n[c] += 1.0
            for ch in range(3):
                colour[c, ch] += rgb[y, x, ch] / 255.0
            if h == 1:
                gy = 0.0
            elif y == 0:
                gy = grey[1, x] - grey[0, x]
            elif y == h - 1:
                gy = grey[h - 1, x] - grey[h - 2, x]
            else:
                gy = 0.5 * (grey[y + 1, x] - grey[y - 1, x])
            if w == 1:
                gx = 0.0
            elif x == 0:
                gx = grey[y, 1] - grey[y, 0]
            elif x == w - 1:
                gx = grey[y, w - 1] - grey[y, w - 2]
            else:
                gx = 0.5 * (grey[y, x + 1] - grey[y, x - 1])
            ang = math.atan2(gy, gx)
            if ang < 0.0:
                ang += math.pi
            if ang >= math.pi:  # atan2 gives pi for a gradient pointing to -x: unsigned, that is angle 0
                ang -= math.pi
            b = min(int(ang / math.pi * bins), bins - 1)
            hist[c, b] += math.sqrt(gx * gx + gy * gy)
    return hist, colour, kept_n, pixels


def feature_drift(rendered: np.ndarray, unedited: np.ndarray,  # uint8 [H, W, 3] each
                  keep: np.ndarray | None = None) -> float | None:  # bool [H, W]; None = every pixel
    """Mean over cells of (1 - cosine similarity) of the two images' structure descriptors, over the pixels in
    ``keep``; None when no cell has enough kept pixels. Finite, in [0, 1]."""
    if rendered.shape != unedited.shape:
        raise ValueError(f"images differ in size: {rendered.shape} vs {unedited.shape}")
    keep = np.ones(rendered.shape[:2], bool) if keep is None else np.asarray(keep, bool)
    a, ka = structure_descriptor(rendered, keep)
    b, kb = structure_descriptor(unedited, keep)
    valid = (ka >= DRIFT_MIN_KEPT) & (kb >= DRIFT_MIN_KEPT)
    if not valid.any():
        return None
    a, b = a[valid], b[valid]
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    cos = np.where((na > _EPS) & (nb > _EPS), (a * b).sum(1) / np.maximum(na * nb, _EPS),
                   np.where((na <= _EPS) & (nb <= _EPS), 1.0, 0.0))
    return float(np.clip(np.mean(1.0 - np.clip(cos, 0.0, 1.0)), 0.0, 1.0))


def box_mask(shape: tuple[int, int], boxes: list[tuple[float, float, float, float]]) -> np.ndarray:  # bool [H, W]
    """Pixels inside any of the image rectangles (x1, y1, x2, y2)."""
    mask = np.zeros(shape, bool)
    for x1, y1, x2, y2 in boxes:
        mask[int(np.floor(y1)):int(np.ceil(y2)), int(np.floor(x1)):int(np.ceil(x2))] = True
    return mask
