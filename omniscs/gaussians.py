"""Gaussian sets: raw (trainable) parameters, their activation (the one place it happens), SH colours.

Raw parameters are what the optimiser sees: unnormalised quaternions, log-scales, opacity logits and
SH coefficients; ``activate`` turns them into what the rasterizer takes. Learning is float32.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

#: Highest SH degree supported (16 coefficients per channel).
MAX_SH_DEGREE = 3

#: Real spherical-harmonic normalisation constants, band 0..3 (the usual 3DGS basis order).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)

#: Colours are SH(view) + this offset (so DC = 0 means mid grey), clamped at 0.
SH_COLOUR_OFFSET = 0.5

#: Opacities are kept inside (eps, 1 - eps) when turned into logits, so logits stay finite.
OPACITY_EPS = 1e-6

#: Scales are floored at this (metres) when turned into log-scales.
MIN_SCALE = 1e-7

#: Log-scales are clamped to this range on activation: exp() never overflows or underflows to 0.
LOG_SCALE_RANGE = (-16.0, 8.0)

#: Direction vectors shorter than this are treated as "looking along +z" by the SH evaluation.
MIN_DIRECTION_NORM = 1e-12

#: Order of the raw parameter tensors (checkpoint keys, optimiser groups).
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


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

    def is_finite(self) -> bool:
        return all(bool(torch.isfinite(v).all()) for v in self.as_dict().values())


def empty_params(sh_degree: int, dtype: torch.dtype = torch.float32) -> GaussianParams:
    return GaussianParams(torch.zeros(0, 3, dtype=dtype), torch.zeros(0, 4, dtype=dtype),
                          torch.zeros(0, 3, dtype=dtype), torch.zeros(0, dtype=dtype), torch.zeros(0, 3, dtype=dtype),
                          torch.zeros(0, num_sh_bases(sh_degree) - 1, 3, dtype=dtype))


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
    norm = params.quats.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(params.quats)
    identity[:, 0] = 1.0
    # a zero quaternion is the identity rotation (no NaN); its gradient is then zero
    quats = torch.where(norm > MIN_DIRECTION_NORM, params.quats / norm.clamp_min(MIN_DIRECTION_NORM), identity)
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
        quats = torch.zeros(n, 4, dtype=dtype)
        quats[:, 0] = 1.0
    o = opacities.to(dtype).clamp(OPACITY_EPS, 1.0 - OPACITY_EPS)
    return GaussianParams(means.to(dtype).contiguous(), quats.to(dtype).contiguous(),
                          torch.log(scales.to(dtype).clamp_min(MIN_SCALE)).contiguous(),
                          torch.log(o / (1.0 - o)).contiguous(), rgb_to_sh_dc(rgb.to(dtype)).contiguous(),
                          torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, dtype=dtype))


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
    return (rgb - SH_COLOUR_OFFSET) / SH_C0


def sh_basis(degree: int, dirs: Tensor) -> Tensor:  # [..., 3] unit -> [..., (degree+1)^2]
    """Real SH basis functions evaluated at unit directions."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, -1)


def colors_from_sh(sh: Tensor,    # [N, K, 3]
                   dirs: Tensor,  # [C, N, 3] viewing directions (camera -> Gaussian), any length
                   degree: int,
                   ) -> Tensor:   # [C, N, 3] colours >= 0
    """View-dependent colour up to ``degree`` (<= the degree ``sh`` holds); degree 0 ignores ``dirs``."""
    if degree == 0:
        return (SH_C0 * sh[None, :, 0] + SH_COLOUR_OFFSET).clamp_min(0.0).expand(dirs.shape[0], -1, -1)
    length = dirs.norm(dim=-1, keepdim=True)
    forward = torch.zeros_like(dirs)
    forward[..., 2] = 1.0
    unit = torch.where(length > MIN_DIRECTION_NORM, dirs / length.clamp_min(MIN_DIRECTION_NORM), forward)
    basis = sh_basis(degree, unit)  # [C, N, B]
    bases = num_sh_bases(degree)
    return (torch.einsum("cnb,nbk->cnk", basis, sh[:, :bases]) + SH_COLOUR_OFFSET).clamp_min(0.0)
