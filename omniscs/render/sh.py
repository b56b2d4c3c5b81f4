"""Real spherical harmonics up to degree 3 with gsplat's constants and basis order, shared by all backends."""
from __future__ import annotations

import torch
from torch import Tensor

#: Highest supported SH degree (16 coefficients per channel).
MAX_SH_DEGREE = 3

#: Directions shorter than this are not normalised (a camera sitting on a Gaussian's centre).
MIN_DIRECTION_NORM = 1e-12

#: gsplat adds this to SH colours (the DC term then encodes colour - 0.5) and clamps below at 0.
SH_COLOR_OFFSET = 0.5

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, 0.9461746957575601, 0.31539156525252005, 0.5462742152960396)
SH_C3 = (0.5900435899266435, 2.890611442640554, 2.285228997322329, 0.4570457994644658,
         1.865881662950577, 1.119528997770346, 1.445305721320277)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:  # dirs [..., 3] unit -> [..., (degree+1)^2]
    """Real SH basis functions evaluated at unit directions, in gsplat's coefficient order."""
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [
            SH_C2[0] * x * y,
            -SH_C2[0] * y * z,
            SH_C2[1] * zz - SH_C2[2],
            -SH_C2[0] * x * z,
            SH_C2[3] * (xx - yy),
        ]
    if degree >= 3:
        radial = -SH_C3[2] * zz + SH_C3[3]
        basis += [
            -SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            radial * y,
            z * (SH_C3[4] * zz - SH_C3[5]),
            radial * x,
            SH_C3[6] * z * (xx - yy),
            -SH_C3[0] * x * (xx - 3 * yy),
        ]
    return torch.stack(basis, -1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:  # [..., K, 3], [..., 3] -> [..., 3]
    """Raw SH colour (no offset, no clamp) seen along ``dirs`` (any length; zero length is allowed)."""
    usable = torch.linalg.vector_norm(dirs.detach(), dim=-1, keepdim=True) >= MIN_DIRECTION_NORM
    safe = torch.where(usable, dirs, torch.ones_like(dirs))
    unit = torch.where(usable, safe / torch.linalg.vector_norm(safe, dim=-1, keepdim=True), 0.0)
    basis = sh_basis(degree, unit)  # [..., B]
    return (basis[..., None] * coeffs[..., : basis.shape[-1], :]).sum(-2)


def colors_from_sh(
    degree: int,
    coeffs: Tensor,    # [N, K, 3] SH coefficients, K >= (degree+1)^2
    means: Tensor,     # [N, 3] world
    viewmats: Tensor,  # [C, 4, 4] cam_from_world
) -> Tensor:  # [C, N, 3] colours, clamped at 0
    """View-dependent colours as gsplat computes them: direction = mean - camera centre, +0.5, max(., 0)."""
    rotation, translation = viewmats[:, :3, :3], viewmats[:, :3, 3]
    camera_centres = -torch.einsum("cji,cj->ci", rotation, translation)  # [C, 3] = -R^T t
    dirs = means[None, :, :] - camera_centres[:, None, :]  # [C, N, 3]
    rgb = eval_sh(degree, coeffs[None].expand(dirs.shape[0], -1, -1, -1), dirs)
    return torch.clamp_min(rgb + SH_COLOR_OFFSET, 0.0)
