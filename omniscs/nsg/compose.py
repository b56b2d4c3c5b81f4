"""Eq. 1 of the paper, the one place a node's Gaussians are carried into the world: G_A = T_A ⊗ G_A-loc."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from omniscs.gaussians import Gaussians
from omniscs.quaternions import normalize_quats, quat_multiply, rotmat_to_quat, rotmats_from_quats


@dataclass(frozen=True)
class NodePose:
    """A node's world pose as tensors, for poses that must carry gradients (behaviour-level optimisation
    moves agents and renders them): rotation as a quaternion, translation in metres."""

    quat: Tensor         # [4] (w, x, y, z), any non-zero norm
    translation: Tensor  # [3]

    @classmethod
    def from_xy_yaw(cls, x: Tensor, y: Tensor, yaw: Tensor, z: float) -> "NodePose":
        """An upright pose on the ground plane (yaw about +z), differentiable in ``x``, ``y`` and ``yaw``."""
        half = 0.5 * yaw
        zero = torch.zeros_like(half)
        quat = torch.stack([torch.cos(half), zero, zero, torch.sin(half)])
        return cls(quat, torch.stack([x, y, torch.full_like(x, float(z))]))

    def unit_quat(self) -> Tensor:  # [4]; a zero quaternion reads as the identity
        return normalize_quats(self.quat)

    def rotmat(self) -> Tensor:  # [3, 3] world_from_node rotation
        return rotmats_from_quats(self.quat)


def place_gaussians(local: Gaussians,
                    world_from_node: np.ndarray | NodePose,  # [4, 4] float64 rigid, or a differentiable pose
                    ) -> Gaussians:
    """``T ⊗ G = (R μ + t, Rot(R, q), s, c, α)``: means and orientations move; scales, colours and
    opacities do not (SH colours stay in the node frame; the renderer evaluates them there)."""
    on = dict(device=local.means.device, dtype=local.means.dtype)  # the pose joins the Gaussians where they are
    if isinstance(world_from_node, NodePose):
        q_R = world_from_node.unit_quat().to(**on)
        R = world_from_node.rotmat().to(**on)
        t = world_from_node.translation.to(**on)
    else:
        T = np.asarray(world_from_node, dtype=np.float64)
        R = torch.from_numpy(T[:3, :3].copy()).to(**on)
        t = torch.from_numpy(T[:3, 3].copy()).to(**on)
        q_R = torch.from_numpy(rotmat_to_quat(T[:3, :3])).to(**on)
    means = local.means @ R.T + t
    quats = quat_multiply(q_R.expand_as(local.quats), local.quats)
    return Gaussians(means, quats, local.scales, local.opacities, local.sh)


def place_many(local: Gaussians,  # several nodes' Gaussians in their own frames, concatenated
               node_of: Tensor,  # [N] int64: which of ``poses`` each Gaussian belongs to
               poses: Sequence[np.ndarray | NodePose | None],  # as in place_gaussians; None: already in the world
               ) -> tuple[Gaussians, Tensor, Tensor]:  # placed, rotations [K, 3, 3], translations [K, 3]
    """``place_gaussians`` of several nodes in one go: the poses are stacked and gathered per Gaussian, so the number
    of tensor operations (and of autograd nodes behind them) does not grow with the number of nodes.
    Differentiable poses (NodePose) carry gradients. Also returns the stacked world_from_node rotations and
    translations."""
    on = dict(device=local.means.device, dtype=local.means.dtype)
    count = len(poses)
    fixed_rotations = np.tile(np.eye(3), (count, 1, 1))
    fixed_translations = np.zeros((count, 3))
    fixed_quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (count, 1))
    for k, pose in enumerate(poses):
        if pose is not None and not isinstance(pose, NodePose):
            T = np.asarray(pose, dtype=np.float64)
            fixed_rotations[k], fixed_translations[k], fixed_quats[k] = T[:3, :3], T[:3, 3], rotmat_to_quat(T[:3, :3])
    rotations = torch.from_numpy(fixed_rotations).to(**on)
    translations = torch.from_numpy(fixed_translations).to(**on)
    rotation_quats = torch.from_numpy(fixed_quats).to(**on)
    posed = [k for k, pose in enumerate(poses) if isinstance(pose, NodePose)]
    if posed:  # the differentiable poses, all together
        index = torch.tensor(posed, device=local.means.device)
        quats = torch.stack([poses[k].quat.to(**on) for k in posed])
        rotations = rotations.index_put((index,), rotmats_from_quats(quats))
        rotation_quats = rotation_quats.index_put((index,), normalize_quats(quats))
        translations = translations.index_put((index,), torch.stack([poses[k].translation.to(**on) for k in posed]))
    means = torch.einsum("nij,nj->ni", rotations[node_of], local.means) + translations[node_of]
    quats = quat_multiply(rotation_quats[node_of], local.quats)
    return Gaussians(means, quats, local.scales, local.opacities, local.sh), rotations, translations
