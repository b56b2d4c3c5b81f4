"""Rotated-box geometry in the ground plane: footprints, overlap tests and IoU (float64)."""
from __future__ import annotations

import numpy as np


def footprints(xy: np.ndarray,    # [..., 2] box centres
               yaw: np.ndarray,   # [...]
               length: np.ndarray | float,  # [...] or scalar
               width: np.ndarray | float,
               ) -> np.ndarray:   # [..., 4, 2] corners, counter-clockwise from front-left
    xy = np.asarray(xy, dtype=np.float64)
    hl = 0.5 * np.asarray(length, dtype=np.float64)[..., None]
    hw = 0.5 * np.asarray(width, dtype=np.float64)[..., None]
    lx = np.concatenate([hl, -hl, -hl, hl], -1) * np.ones(xy.shape[:-1] + (4,))
    ly = np.concatenate([hw, hw, -hw, -hw], -1) * np.ones(xy.shape[:-1] + (4,))
    c, s = np.cos(yaw)[..., None], np.sin(yaw)[..., None]
    return np.stack([xy[..., 0, None] + c * lx - s * ly, xy[..., 1, None] + s * lx + c * ly], -1)


def overlapping(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # [..., 4, 2] x [..., 4, 2] -> [...] bool
    """Whether two convex quadrilaterals overlap (separating-axis test; touching counts as overlap)."""
    a, b = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
    separated = np.zeros(a.shape[:-2], dtype=bool)
    for poly in (a, b):
        for i in range(2):
            edge = poly[..., i + 1, :] - poly[..., i, :]
            axis = np.stack([-edge[..., 1], edge[..., 0]], -1)
            pa = np.einsum("...kj,...j->...k", a, axis)
            pb = np.einsum("...kj,...j->...k", b, axis)
            separated |= (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~separated


def _area(poly: np.ndarray) -> float:  # [K, 2]
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _clip(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the part of convex ``subject`` inside convex counter-clockwise ``clipper``."""
    out = subject
    for i in range(len(clipper)):
        if len(out) == 0:
            break
        a, b = clipper[i], clipper[(i + 1) % len(clipper)]
        edge = b - a

        def inside(p):
            return edge[0] * (p[1] - a[1]) - edge[1] * (p[0] - a[0]) >= 0.0

        pts, new = out, []
        for j in range(len(pts)):
            p, q = pts[j], pts[(j + 1) % len(pts)]
            pin, qin = inside(p), inside(q)
            if pin:
                new.append(p)
            if pin != qin:
                d = q - p
                denom = edge[0] * d[1] - edge[1] * d[0]
                if abs(denom) > 1e-15:
                    t = (edge[1] * (p[0] - a[0]) - edge[0] * (p[1] - a[1])) / denom
                    new.append(p + t * d)
        out = np.array(new).reshape(-1, 2)
    return out


def _ccw(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    signed = float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    return poly if signed >= 0 else poly[::-1]


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # [..., 4, 2] x [..., 4, 2] -> [...] in [0, 1]
    """Intersection over union of footprints; exact polygon clipping where the separating-axis test overlaps."""
    a, b = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
    shape = a.shape[:-2]
    a2, b2 = a.reshape(-1, 4, 2), b.reshape(-1, 4, 2)
    out = np.zeros(len(a2))
    for k in np.flatnonzero(overlapping(a2, b2)):
        pa, pb = _ccw(a2[k]), _ccw(b2[k])
        inter = _area(_clip(pa, pb))
        union = _area(pa) + _area(pb) - inter
        out[k] = inter / union if union > 1e-12 else 0.0
    return np.clip(out, 0.0, 1.0).reshape(shape)
