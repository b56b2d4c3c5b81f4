"""Relightable agent nodes: a 360-degree model whose colours follow the scene's light when the agent turns.

A model with a baked look keeps its light on its own sides: turn a car whose sunlit back the cameras saw, and the
sunlit colour goes with the back, while in the scene that side now faces away from the sun. A relightable node
keeps, per Gaussian, a linear albedo and an outward normal in the node frame, and one light for the scene in the
world frame:

    linear colour = albedo * max(E(n), 0) + A,   E(n) = L0 + L1 n_x + L2 n_y + L3 n_z   (per channel)

with n the Gaussian's normal turned into the world by the node's pose in the rendered frame: the irradiance E is
the first two spherical-harmonic bands (the ambient level and the main light's direction); A is light the surface
reflects whatever its albedo (the sky on paint and glass). The colour is then encoded with the sRGB curve. Since
the normal is turned by the pose of each frame, every edit (turn, overturn, new trajectory) is relit, with no
step of its own.

``lighting`` rows: 0-3 the irradiance coefficients L0..L3, 4 the additive term A; columns R, G, B.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import OmniscsError

#: Rows of ``Relight.lighting``: four irradiance coefficients (1, n_x, n_y, n_z) and the additive term.
LIGHTING_ROWS = 5


def srgb_encode(linear: Tensor) -> Tensor:
    """Linear 0..1 -> display 0..1 (the sRGB curve); differentiable, finite at 0."""
    x = linear.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def srgb_decode(display: Tensor) -> Tensor:
    """Display 0..1 -> linear 0..1 (inverse of ``srgb_encode``)."""
    c = display.clamp(0.0, 1.0)
    return torch.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def irradiance_basis(normals: Tensor) -> Tensor:  # [N, 3] -> [N, 4]
    return torch.cat([torch.ones_like(normals[:, :1]), normals], 1)


@dataclass(frozen=True)
class Relight:
    """Per-Gaussian linear albedo [N, 3] and unit outward normals [N, 3] (node frame), and the scene's light
    [LIGHTING_ROWS, 3] (world frame); see the module docstring."""

    albedo: Tensor
    normals: Tensor
    lighting: Tensor

    def __post_init__(self) -> None:
        n = self.albedo.shape[0]
        if self.albedo.shape != (n, 3) or self.normals.shape != (n, 3) \
                or self.lighting.shape != (LIGHTING_ROWS, 3):
            raise OmniscsError(f"relight data must be albedo [N, 3], normals [N, 3] and lighting [{LIGHTING_ROWS}, 3]; "
                               f"got {tuple(self.albedo.shape)}, {tuple(self.normals.shape)}, "
                               f"{tuple(self.lighting.shape)}")
        if not all(bool(torch.isfinite(t).all()) for t in (self.albedo, self.normals, self.lighting)):
            raise OmniscsError("relight data holds NaN or Inf values")

    def __len__(self) -> int:
        return int(self.albedo.shape[0])

    def to(self, device) -> "Relight":
        return Relight(self.albedo.to(device), self.normals.to(device), self.lighting.to(device))

    def with_lighting(self, lighting: Tensor) -> "Relight":
        return Relight(self.albedo, self.normals, lighting)

    def colours(self, world_from_node_rotation) -> Tensor:
        """Display colours [N, 3] of the Gaussians with the node turned by ``world_from_node_rotation`` ([3, 3]
        tensor or array); differentiable in the lighting."""
        R = torch.as_tensor(np.array(world_from_node_rotation) if not torch.is_tensor(world_from_node_rotation)
                            else world_from_node_rotation, dtype=self.normals.dtype, device=self.normals.device)
        n = self.normals @ R.T
        L = self.lighting.to(self.normals.dtype)
        linear = self.albedo * (irradiance_basis(n) @ L[:4]).clamp_min(0.0) + L[4]
        return srgb_encode(linear)


def flat_lighting(level: float = 1.0, dtype=torch.float32) -> Tensor:
    """A light that gives every side the same irradiance ``level`` and reflects nothing."""
    L = torch.zeros(LIGHTING_ROWS, 3, dtype=dtype)
    L[0] = float(level)
    return L
