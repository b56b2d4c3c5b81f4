"""Real spherical harmonics up to degree 3 (gsplat's constants and basis order): the one home of SH colour,
used by every rasterizer backend and by the scene graph."""
from __future__ import annotations

import torch
from torch import Tensor

#: Highest supported SH degree (16 coefficients per channel).
MAX_SH_DEGREE = 3

#: Viewing directions shorter than this (a camera sitting on a Gaussian's centre) have no direction: they
#: are read as +z, so the colour is still a colour seen from somewhere (finite, and no gradient flows).
MIN_DIRECTION_NORM = 1e-12

#: Colours are SH(view) + this offset (so a zero DC coefficient is mid grey), clamped below at 0, as in gsplat.
SH_COLOR_OFFSET = 0.5

#: Real spherical-harmonic normalisation constants, band 0..3, signs folded in (the usual 3DGS basis order).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:  # dirs [..., 3] unit -> [..., (degree+1)^2]
    """Real SH basis functions evaluated at unit directions, in gsplat's coefficient order."""
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                  SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(basis, -1)


def unit_directions(dirs: Tensor) -> Tensor:  # [..., 3] any length -> [..., 3] unit
    """``dirs`` normalised; one shorter than MIN_DIRECTION_NORM reads as +z and passes no gradient back."""
    # the mask is taken on detached values and the division never sees a zero length: no 0/0 anywhere
    usable = torch.linalg.vector_norm(dirs.detach(), dim=-1, keepdim=True) >= MIN_DIRECTION_NORM
    forward = torch.zeros_like(dirs)
    forward[..., 2] = 1.0
    safe = torch.where(usable, dirs, forward)
    return safe / torch.linalg.vector_norm(safe, dim=-1, keepdim=True)


def colors_from_sh(degree: int,
                   coeffs: Tensor,  # [N, K, 3] SH coefficients, K >= (degree+1)^2
                   dirs: Tensor,    # [C, N, 3] viewing directions (camera -> Gaussian), any length
                   ) -> Tensor:     # [C, N, 3] colours >= 0
    """View-dependent colour up to ``degree`` (<= the degree ``coeffs`` holds); degree 0 ignores ``dirs``."""
    if degree == 0:
        return (SH_C0 * coeffs[None, :, 0] + SH_COLOR_OFFSET).clamp_min(0.0).expand(dirs.shape[0], -1, -1)
    basis = sh_basis(degree, unit_directions(dirs))  # [C, N, B]
    return (torch.einsum("cnb,nbk->cnk", basis, coeffs[:, :num_sh_bases(degree)]) + SH_COLOR_OFFSET).clamp_min(0.0)


def colors_from_sh_at_cameras(degree: int,
                              coeffs: Tensor,    # [N, K, 3] SH coefficients, K >= (degree+1)^2
                              means: Tensor,     # [N, 3] world
                              viewmats: Tensor,  # [C, 4, 4] cam_from_world
                              ) -> Tensor:       # [C, N, 3] colours >= 0
    """Colours as gsplat computes them inside ``rasterization``: direction = mean - camera centre."""
    rotation, translation = viewmats[:, :3, :3], viewmats[:, :3, 3]
    camera_centres = -torch.einsum("cji,cj->ci", rotation, translation)  # [C, 3] = -R^T t
    return colors_from_sh(degree, coeffs, means[None, :, :] - camera_centres[:, None, :])


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:  # [..., 3] in [0, 1] -> [..., 3] band-0 coefficient
    """The DC coefficient whose view-independent colour is ``rgb`` (inverse of the degree-0 colour)."""
    return (rgb - SH_COLOR_OFFSET) / SH_C0


def sh_rotation(degree: int, R) -> Tensor:  # [3, 3] rotation -> [K, K] float64, K = (degree+1)^2
    """The matrix M that turns coefficients with a rigid rotation: the function f'(d) = f(R^T d) has coefficients
    M @ c. Each band is closed under rotation, so fitting M on more directions than coefficients is exact."""
    k = num_sh_bases(degree)
    n = max(4 * k, 64)
    i = torch.arange(n, dtype=torch.float64) + 0.5  # a Fibonacci sphere: well-spread directions
    z = 1.0 - 2.0 * i / n
    phi = torch.pi * (1.0 + 5.0 ** 0.5) * i
    r = torch.sqrt(1.0 - z * z)
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    R = torch.as_tensor(R, dtype=torch.float64)
    Y = sh_basis(degree, dirs)            # [n, K]
    Y_turned = sh_basis(degree, dirs @ R)  # rows: R^T d
    return torch.linalg.lstsq(Y, Y_turned).solution  # [K, K]


def rotate_sh(coeffs: Tensor, R) -> Tensor:  # [N, K, 3], [3, 3] -> [N, K, 3]
    """SH coefficients of Gaussians turned by ``R`` (their colour seen from R d equals the old one seen from d)."""
    degree = int(round(coeffs.shape[1] ** 0.5)) - 1
    M = sh_rotation(degree, R).to(coeffs.dtype).to(coeffs.device)
    return torch.einsum("kj,njc->nkc", M, coeffs)
