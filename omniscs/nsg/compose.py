"""Eq. 1 of the paper, the one place a node's Gaussians are carried into the world: G_A = T_A ⊗ G_A-loc."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from omniscs.gaussians import Gaussians
from omniscs.geometry import rotmat_to_quat


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:  # [..., 4] x [..., 4] -> [..., 4]
    """Hamilton product a ⊗ b (rotate by b, then by a), (w, x, y, z)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def place_gaussians(local: Gaussians,
                    world_from_node: np.ndarray,  # [4, 4] float64 rigid
                    ) -> Gaussians:
    """``T ⊗ G = (R μ + t, Rot(R, q), s, c, α)``: means and orientations move; scales, colours and
    opacities do not (SH colours stay in the node frame; the renderer evaluates them there)."""
    T = np.asarray(world_from_node, dtype=np.float64)
    dtype = local.means.dtype
    R = torch.from_numpy(T[:3, :3].copy()).to(dtype)
    t = torch.from_numpy(T[:3, 3].copy()).to(dtype)
    q_R = torch.from_numpy(rotmat_to_quat(T[:3, :3])).to(dtype)
    means = local.means @ R.T + t
    quats = quat_multiply(q_R.expand_as(local.quats), local.quats)
    return Gaussians(means, quats, local.scales, local.opacities, local.sh)
