"""Relightable agent nodes: a 360-degree model whose colours follow the scene's light when the agent turns.

A model with a baked look keeps its light on its own sides: turn a car whose sunlit back the cameras saw, and the
sunlit colour goes with the back, while in the scene that side now faces away from the sun; and the sky its windows
mirrored from one side is not what they mirror from another. A relightable node keeps, per Gaussian, its material
(linear albedo ``a``, specular reflectance at normal incidence ``f0``, shininess ``k``; ``omniscs.agents.material``)
and an outward normal in the node frame, and one light for the scene in the world frame: a sun and a sky.

With ``n`` the normal turned into the world by the node's pose in the rendered frame (and flipped towards the camera:
two-sided), ``v`` the direction from the camera to the Gaussian, ``s`` the sun's direction and ``r`` = v - 2 (v.n) n
the mirrored view:

    E      = sun max(n.s, 0) + sky (1 + n_z) / 2 + ground (1 - n_z) / 2         light reaching the surface
    F      = f0 + (1 - f0) (1 - max(-v.n, 0))^5          (0 where f0 = 0)      Schlick's Fresnel
    env(r) = horizon + (zenith - horizon) sqrt(r_z) above the horizon, below under it   the sky it mirrors
    spec   = f0 (k + 8) / (8 pi) max(n.h, 0)^k [n.s > 0] sun,  h = (s - v) / |s - v|   the sun's highlight
    linear = a (1 - F) E + F env(r) + spec
    colour = sRGB(1 - exp(-linear))                                              a film-like camera response

All light terms are in the camera's exposed units (the exposure is folded into them). Since the normal and the view
are turned by the pose of each frame, every edit (turn, overturn, new trajectory) is relit, with no step of its own.

``lighting`` rows (``LIGHT_ROWS``): sun (irradiance, RGB), sun direction (world x, y, z; any length), sky, ground
(the light from above and from below), zenith, horizon, below (the sky a surface mirrors straight up, at the horizon
and under it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import OmniscsError

#: Rows of ``Relight.lighting`` (see the module docstring).
LIGHT_ROWS = ("sun", "sun_direction", "sky", "ground", "zenith", "horizon", "below")
LIGHTING_ROWS = len(LIGHT_ROWS)
#: A neutral daylight: what a fit starts from (a white sun high in the sky, a grey sky).
NEUTRAL_LIGHT = ((1.5, 1.5, 1.5), (0.5, 0.5, 0.7), (0.4, 0.4, 0.4), (0.2, 0.2, 0.2), (0.4, 0.4, 0.4),
                 (0.7, 0.7, 0.7), (0.3, 0.3, 0.3))


def srgb_encode(linear: Tensor) -> Tensor:
    """Linear 0..1 -> display 0..1 (the sRGB curve); differentiable, finite at 0."""
    x = linear.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def srgb_decode(display: Tensor) -> Tensor:
    """Display 0..1 -> linear 0..1 (inverse of ``srgb_encode``)."""
    c = display.clamp(0.0, 1.0)
    return torch.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def camera_response(linear: Tensor) -> Tensor:
    """Exposed linear light (>= 0) -> display 0..1: 1 - exp(-x), then the sRGB curve."""
    return srgb_encode(-torch.expm1(-linear.clamp_min(0.0)))


def inverse_camera_response(display: Tensor) -> Tensor:
    """Display 0..1 -> exposed linear light (``camera_response`` inverted; display 1 gives a large finite value)."""
    return -torch.log1p(-srgb_decode(display).clamp(0.0, 1.0 - 1e-4))


def shade(albedo: Tensor, normals: Tensor, view: Tensor, specular: Tensor, shininess: Tensor,
          lighting: Tensor) -> Tensor:
    """Display colours [N, 3] (module docstring) of surfaces with world normals [N, 3], seen along world ``view``
    [N, 3] (camera to surface; any length); differentiable in every input."""
    L = lighting.to(albedo.dtype)
    v = view / view.norm(dim=1, keepdim=True).clamp_min(1e-9)
    n = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-9)
    n = torch.where((n * v).sum(1, keepdim=True) > 0, -n, n)  # two-sided: the side the camera sees
    sun, sky, ground, zenith, horizon, below = (L[i].clamp_min(0.0) for i in (0, 2, 3, 4, 5, 6))
    s = L[1] / L[1].norm().clamp_min(1e-9)
    ndl = (n @ s).clamp_min(0.0)[:, None]
    up = 0.5 + 0.5 * n[:, 2:3]
    irradiance = ndl * sun + up * sky + (1.0 - up) * ground
    f0 = specular[:, None]
    cos_v = (-(n * v).sum(1, keepdim=True)).clamp(0.0, 1.0)
    fresnel = torch.where(f0 > 0, f0 + (1.0 - f0) * (1.0 - cos_v) ** 5, torch.zeros_like(f0))
    r_z = (v - 2.0 * (v * n).sum(1, keepdim=True) * n)[:, 2:3]
    env = torch.where(r_z >= 0, horizon + (zenith - horizon) * torch.sqrt(r_z.clamp_min(0.0) + 1e-6), below)
    h = s - v
    h = h / h.norm(dim=1, keepdim=True).clamp_min(1e-9)
    k = shininess[:, None]
    ndh = (n * h).sum(1, keepdim=True).clamp(0.0, 1.0)
    highlight = f0 * (k + 8.0) / (8.0 * np.pi) * torch.exp(k * torch.log(ndh.clamp_min(1e-12))) * (ndl > 0) * sun
    linear = albedo * (1.0 - fresnel) * irradiance + fresnel * env + highlight
    return camera_response(linear)


@dataclass(frozen=True)
class Relight:
    """Per-Gaussian linear albedo [N, 3], unit outward normals [N, 3] (node frame), specular reflectance [N] and
    shininess [N], and the scene's light [LIGHTING_ROWS, 3] (world frame); see the module docstring."""

    albedo: Tensor
    normals: Tensor
    specular: Tensor
    shininess: Tensor
    lighting: Tensor

    def __post_init__(self) -> None:
        n = self.albedo.shape[0]
        if self.albedo.shape != (n, 3) or self.normals.shape != (n, 3) or self.specular.shape != (n,) \
                or self.shininess.shape != (n,) or self.lighting.shape != (LIGHTING_ROWS, 3):
            raise OmniscsError(f"relight data must be albedo [N, 3], normals [N, 3], specular [N], shininess [N] and "
                               f"lighting [{LIGHTING_ROWS}, 3]; got {tuple(self.albedo.shape)}, "
                               f"{tuple(self.normals.shape)}, {tuple(self.specular.shape)}, "
                               f"{tuple(self.shininess.shape)}, {tuple(self.lighting.shape)}")
        if not all(bool(torch.isfinite(getattr(self, k)).all()) for k in RELIGHT_TENSORS):
            raise OmniscsError("relight data holds NaN or Inf values")

    def __len__(self) -> int:
        return int(self.albedo.shape[0])

    def to(self, device) -> "Relight":
        return Relight(*(getattr(self, k).to(device) for k in RELIGHT_TENSORS))

    def with_lighting(self, lighting: Tensor) -> "Relight":
        return Relight(self.albedo, self.normals, self.specular, self.shininess, lighting)

    def colours(self, world_from_node_rotation, view_dirs: Tensor | None = None) -> Tensor:
        """Display colours [N, 3] of the Gaussians with the node turned by ``world_from_node_rotation`` ([3, 3]
        tensor or array), seen along ``view_dirs`` ([N, 3], node frame, camera to Gaussian); without them each is
        seen head-on (against its normal). Differentiable in the lighting."""
        R = torch.as_tensor(np.array(world_from_node_rotation) if not torch.is_tensor(world_from_node_rotation)
                            else world_from_node_rotation, dtype=self.normals.dtype, device=self.normals.device)
        n = self.normals @ R.T
        v = -n if view_dirs is None else view_dirs.to(self.normals.dtype) @ R.T
        return shade(self.albedo, n, v, self.specular, self.shininess, self.lighting)


RELIGHT_TENSORS = ("albedo", "normals", "specular", "shininess", "lighting")


def neutral_lighting(dtype=torch.float32) -> Tensor:
    """``NEUTRAL_LIGHT`` as a [LIGHTING_ROWS, 3] tensor."""
    return torch.tensor(NEUTRAL_LIGHT, dtype=dtype)


def matte(albedo: Tensor, normals: Tensor, lighting: Tensor | None = None) -> Relight:
    """Relight data of a matte surface (no mirror term, no highlight) under ``lighting`` (default neutral)."""
    n = albedo.shape[0]
    light = neutral_lighting(albedo.dtype).to(albedo.device) if lighting is None else lighting
    return Relight(albedo, normals, torch.zeros(n, dtype=albedo.dtype, device=albedo.device),
                   torch.ones(n, dtype=albedo.dtype, device=albedo.device), light)
