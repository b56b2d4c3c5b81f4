"""Gaussian sets: raw (trainable) parameters and their activation (the one place it happens).

Raw parameters are what the optimiser sees: unnormalised quaternions, log-scales, opacity logits and
SH coefficients; ``activate`` turns them into what the rasterizer takes (SH colours: ``omniscs.render.sh``).
Learning is float32.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from omniscs.quaternions import normalize_quats, quat_multiply, rotmat_to_quat
from omniscs.render.sh import num_sh_bases, rgb_to_sh_dc, rotate_sh

#: Opacities are kept inside (eps, 1 - eps) when turned into logits, so logits stay finite.
OPACITY_EPS = 1e-6

#: Scales are floored at this (metres) when turned into log-scales.
MIN_SCALE = 1e-7

#: Log-scales are clamped to this range on activation: exp() never overflows or underflows to 0.
LOG_SCALE_RANGE = (-16.0, 8.0)

#: Order of the raw parameter tensors (checkpoint keys, optimiser groups).
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


@dataclass(frozen=True)
class GaussianParams:
    """Raw parameters of N Gaussians in their node's frame; the form that is optimised and stored."""

    means: Tensor           # [N, 3] node frame, metres
    quats: Tensor           # [N, 4] (w, x, y, z), unnormalised
    log_scales: Tensor      # [N, 3] log of metres
    opacity_logits: Tensor  # [N]
    sh_dc: Tensor           # [N, 3] band-0 SH coefficient (the view-independent colour)
    sh_rest: Tensor         # [N, K - 1, 3] higher bands, K = (degree + 1)^2

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(math.sqrt(self.sh_rest.shape[1] + 1))) - 1

    @property
    def sh(self) -> Tensor:  # [N, K, 3]
        return torch.cat([self.sh_dc[:, None], self.sh_rest], 1)

    def as_dict(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Tensor]) -> "GaussianParams":
        return cls(**{name: d[name] for name in PARAM_NAMES})

    def select(self, index: Tensor) -> "GaussianParams":
        """The Gaussians picked by ``index`` ([N] bool mask or [M] int64 indices)."""
        return GaussianParams(**{k: v[index] for k, v in self.as_dict().items()})

    def detached(self) -> "GaussianParams":
        return GaussianParams(**{k: v.detach().clone() for k, v in self.as_dict().items()})

    def to(self, device: torch.device | str) -> "GaussianParams":
        """The same parameters on ``device`` (these very tensors when they are there already)."""
        return GaussianParams(**{k: v.to(device) for k, v in self.as_dict().items()})

    @property
    def device(self) -> torch.device:
        return self.means.device

    def is_finite(self) -> bool:
        return all(bool(torch.isfinite(v).all()) for v in self.as_dict().values())


def empty_params(sh_degree: int, dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu") -> GaussianParams:
    def zeros(*shape: int) -> Tensor:
        return torch.zeros(*shape, dtype=dtype, device=device)

    return GaussianParams(zeros(0, 3), zeros(0, 4), zeros(0, 3), zeros(0), zeros(0, 3),
                          zeros(0, num_sh_bases(sh_degree) - 1, 3))


def concat_params(parts: list[GaussianParams]) -> GaussianParams:
    """All Gaussians of ``parts`` in one set (SH degrees must agree)."""
    return GaussianParams(**{name: torch.cat([getattr(p, name) for p in parts]) for name in PARAM_NAMES})


@dataclass(frozen=True)
class Gaussians:
    """Activated Gaussians: what the rasterizer takes (plus SH coefficients, evaluated per view)."""

    means: Tensor      # [N, 3] metres, in the frame named by whoever holds them
    quats: Tensor      # [N, 4] unit (w, x, y, z)
    scales: Tensor     # [N, 3] metres, positive
    opacities: Tensor  # [N] in (0, 1)
    sh: Tensor         # [N, K, 3]

    def __len__(self) -> int:
        return self.means.shape[0]


def activate(params: GaussianParams) -> Gaussians:
    """The one place raw parameters become rasterizer inputs: normalise, exponentiate, squash."""
    quats = normalize_quats(params.quats)  # a zero quaternion is the identity rotation, with zero gradient
    scales = torch.exp(params.log_scales.clamp(*LOG_SCALE_RANGE))
    opacities = torch.sigmoid(params.opacity_logits)
    return Gaussians(params.means, quats, scales, opacities, params.sh)


def params_from_values(means: Tensor,     # [N, 3]
                       scales: Tensor,    # [N, 3] metres
                       opacities: Tensor,  # [N] in [0, 1]
                       rgb: Tensor,       # [N, 3] in [0, 1]
                       sh_degree: int,
                       quats: Tensor | None = None,  # [N, 4]; identity when None
                       ) -> GaussianParams:
    """Raw parameters that activate to the given values (inverse activations; view-independent colour)."""
    n = means.shape[0]
    dtype = torch.float32
    if quats is None:
        quats = torch.zeros(n, 4, dtype=dtype, device=means.device)
        quats[:, 0] = 1.0
    o = opacities.to(dtype).clamp(OPACITY_EPS, 1.0 - OPACITY_EPS)
    return GaussianParams(means.to(dtype).contiguous(), quats.to(dtype).contiguous(),
                          torch.log(scales.to(dtype).clamp_min(MIN_SCALE)).contiguous(),
                          torch.log(o / (1.0 - o)).contiguous(), rgb_to_sh_dc(rgb.to(dtype)).contiguous(),
                          torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, dtype=dtype, device=means.device))


def rigidly_moved(params: GaussianParams, rotation, translation) -> GaussianParams:
    """``params`` moved by p -> R p + t: means and orientations turn, and so do the view-dependent colours (every SH
    band turned with the rotation: the Gaussians look from R d as they looked from d); scales and opacities stay."""
    R = torch.as_tensor(rotation, dtype=torch.float64)
    t = torch.as_tensor(translation, dtype=torch.float64)
    dtype = params.means.dtype
    q = torch.as_tensor(rotmat_to_quat(R.numpy()), dtype=dtype)
    sh = rotate_sh(params.sh.double(), R).to(dtype)
    return GaussianParams((params.means.double() @ R.T + t).to(dtype), quat_multiply(q.expand_as(params.quats),
                                                                                     params.quats),
                          params.log_scales.clone(), params.opacity_logits.clone(), sh[:, 0].contiguous(),
                          sh[:, 1:].contiguous())


def with_sh_degree(params: GaussianParams, degree: int) -> GaussianParams:
    """The same colours with ``degree`` bands (missing bands are zero; extra bands are dropped)."""
    k = num_sh_bases(degree) - 1
    rest = params.sh_rest
    if rest.shape[1] < k:
        rest = torch.cat([rest, rest.new_zeros(len(params), k - rest.shape[1], 3)], 1)
    return GaussianParams(params.means, params.quats, params.log_scales, params.opacity_logits, params.sh_dc,
                          rest[:, :k].contiguous())
