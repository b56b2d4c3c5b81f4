"""Quaternion maths, the one home: (w, x, y, z), Hamilton product, q and -q the same rotation.

Two zero-norm rules, one per use. Quaternions read from logs, boxes and edits (numpy float64) must name a
rotation, so a zero or non-finite one is a data error (OmniscsError). Learnable orientations (torch, and
their numpy copies) can shrink to zero while fitting: such a quaternion reads as the identity and, in
torch, passes no gradient back. Neither rule ever yields NaN or Inf.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import OmniscsError

#: Quaternions (and rotation axes) shorter than this have no direction: an error for data, the identity
#: for learnable orientations.
MIN_QUAT_NORM = 1e-12

#: The identity rotation, (w, x, y, z).
IDENTITY_QUAT = (1.0, 0.0, 0.0, 0.0)


def _hamilton(aw, ax, ay, az, bw, bx, by, bz) -> list:  # components of a ⊗ b, for numpy or torch operands
    return [aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw]


def _rotation_rows(w, x, y, z) -> list[list]:  # rows of the rotation matrix of a unit quaternion
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]


def quat_multiply(a, b):  # [..., 4] x [..., 4] -> [..., 4]; numpy (as float64) or torch (its dtype)
    """Hamilton product a ⊗ b (rotate by b first, then by a); no normalisation, so no zero-norm rule."""
    if isinstance(a, Tensor) or isinstance(b, Tensor):
        return torch.stack(_hamilton(*a.unbind(-1), *b.unbind(-1)), -1)
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.stack(_hamilton(*np.moveaxis(a, -1, 0), *np.moveaxis(b, -1, 0)), -1)


# ----------------------------------------------------------------------------- numpy float64: data
def quat_normalize(q: np.ndarray) -> np.ndarray:  # [..., 4] -> [..., 4]
    """Unit quaternion with non-negative w (q and -q are the same rotation; this picks one).
    Raises OmniscsError for a zero-norm or non-finite quaternion (it names no rotation)."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(q)) or np.any(norm < MIN_QUAT_NORM):
        raise OmniscsError("quaternion has zero norm or is not finite; give a non-zero (w, x, y, z)")
    q = q / norm
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:  # [..., 4] (w, x, y, z), any non-zero norm -> [..., 3, 3]
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    return np.stack([np.stack(row, -1) for row in _rotation_rows(w, x, y, z)], -2)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:  # [..., 3, 3] -> [..., 4] (w >= 0)
    """Shepperd's method: picks the largest of w, x, y, z to divide by, so 180° turns stay exact."""
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    pick = np.argmax(diag, -1)
    q = np.empty((m.shape[0], 4))
    for k in range(4):  # each branch over all the matrices that pick it (elementwise: the same values one by one)
        rows = np.flatnonzero(pick == k)
        if not len(rows):
            continue
        r = m[rows]
        if k == 0:
            s = 2.0 * np.sqrt(np.maximum(1.0 + tr[rows], 0.0))
            parts = (0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s)
        elif k == 1:
            s = 2.0 * np.sqrt(np.maximum(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2], 0.0))
            parts = ((r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s)
        elif k == 2:
            s = 2.0 * np.sqrt(np.maximum(1.0 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2], 0.0))
            parts = ((r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s)
        else:
            s = 2.0 * np.sqrt(np.maximum(1.0 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2], 0.0))
            parts = ((r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s)
        q[rows] = np.stack(parts, -1)
    return quat_normalize(q).reshape(*batch, 4)


def quat_from_axis_angle(axis: np.ndarray, angle: float | np.ndarray) -> np.ndarray:  # [3], [...] -> [..., 4]
    axis = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(axis, axis=-1, keepdims=True)
    if np.any(n < MIN_QUAT_NORM):
        raise OmniscsError("rotation axis has zero length; give a non-zero axis")
    half = 0.5 * np.asarray(angle, dtype=np.float64)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axis / n], -1)


def yaw_to_quat(yaw: float | np.ndarray) -> np.ndarray:  # [...] radians about +z -> [..., 4]
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zero = np.zeros_like(half)
    return np.stack([np.cos(half), zero, zero, np.sin(half)], -1)


def yaw_from_quaternion(q: np.ndarray) -> np.ndarray:  # [..., 4] (w, x, y, z), any non-zero norm -> [...] rad
    """Heading of the rotated +x axis in the ground plane (``geometry.yaw_from_matrix`` for matrices)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:  # [4], [4], scalar -> [4] (w, x, y, z)
    """Spherical interpolation along the shorter arc (q and -q are the same rotation)."""
    q0, q1 = quat_normalize(q0), quat_normalize(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 1.0 - 1e-12:  # nearly the same rotation: linear interpolation is exact to rounding
        return quat_normalize(q0 + t * (q1 - q0))
    theta = np.arccos(dot)
    return quat_normalize((np.sin((1 - t) * theta) * q0 + np.sin(t * theta) * q1) / np.sin(theta))


# ----------------------------------------------------------------------------- learnable orientations
def normalize_quats(quats):  # [..., 4] (w, x, y, z), any norm -> [..., 4] unit; torch or numpy
    """Unit quaternions; one shorter than MIN_QUAT_NORM reads as the identity (as gsplat's normalisation
    effectively does). In torch that one passes no gradient back, so neither value nor gradient is NaN."""
    if isinstance(quats, Tensor):
        # the mask is taken on detached values, and the division never sees a zero norm: no 0/0 anywhere
        usable = torch.linalg.vector_norm(quats.detach(), dim=-1, keepdim=True) >= MIN_QUAT_NORM
        identity = torch.zeros_like(quats)
        identity[..., 0] = 1.0
        q = torch.where(usable, quats, identity)
        return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    q = np.asarray(quats, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(norm >= MIN_QUAT_NORM, q / np.maximum(norm, MIN_QUAT_NORM), np.array(IDENTITY_QUAT))


def rotmats_from_unit_quats(quats: Tensor) -> Tensor:  # [..., 4] unit (w, x, y, z) -> [..., 3, 3]
    """Rotation matrices of quaternions that are already unit (activated ones); no normalisation here."""
    rows = _rotation_rows(*quats.unbind(-1))
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def rotmats_from_quats(quats: Tensor) -> Tensor:  # [..., 4] (w, x, y, z), any norm -> [..., 3, 3]
    """Rotation matrices of unnormalised quaternions; q and -q give the same matrix; zero norm: identity."""
    return rotmats_from_unit_quats(normalize_quats(quats))
