"""EWA projection of 3D Gaussians to screen-space conics, in PyTorch for any float dtype.

This is the one home of the projection/covariance math: the reference backend differentiates it by
autograd, and it defines what the CPU backend's fused kernels (``_cpu_projection.py``) must compute.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from omniscs.quaternions import rotmats_from_quats
from omniscs.render.constants import ALPHA_THRESHOLD, FRUSTUM_MARGIN, MAX_RADIUS

#: Floor of det(Sigma2d) / det(Sigma2d + eps2d I) in antialiased mode; keeps the sqrt's gradient finite.
MIN_COMPENSATION_RATIO = 1e-12


@dataclass(frozen=True)
class ScreenGaussians:
    """Gaussians as C cameras see them. Entries of culled Gaussians are finite but carry no meaning."""

    means2d: Tensor    # [C, N, 2] projected centres, pixels (pixel (i, j) has its centre at (i+0.5, j+0.5))
    conics: Tensor     # [C, N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    depths: Tensor     # [C, N] camera-frame z of the centres, metres
    opacities: Tensor  # [C, N] opacity used for compositing (compensated in antialiased mode)
    radii: Tensor      # [C, N, 2] int32 half-extent in x and y, pixels; 0 where culled

    @property
    def visible(self) -> Tensor:  # [C, N] bool
        return self.radii[..., 0] > 0


def project_gaussians(
    means: Tensor,      # [N, 3] world
    quats: Tensor,      # [N, 4] (w, x, y, z), any norm
    scales: Tensor,     # [N, 3] activated (positive) scales, metres
    opacities: Tensor,  # [N] in [0, 1]
    viewmats: Tensor,   # [C, 4, 4] cam_from_world, OpenCV camera
    Ks: Tensor,         # [C, 3, 3]
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    antialiased: bool = False,
) -> ScreenGaussians:
    """Project Gaussians with the EWA local-affine approximation and cull what cannot be seen.

    Sigma = R S S^T R^T; Sigma2d = J W Sigma W^T J^T + eps2d I, with J the perspective Jacobian at
    the centre, x/z and y/z clamped to the frustum widened by FRUSTUM_MARGIN (as gsplat).
    The determinant is formed from the 2x2 minors of A = J W R S (Cauchy-Binet), so flat and
    edge-on Gaussians keep a non-negative, accurate determinant even in float32.
    Culled: centre outside [near_plane, far_plane]; singular or non-finite 2D covariance; opacity
    below ALPHA_THRESHOLD; screen box outside the image. The screen box half-extent is the
    opacity-aware one gsplat uses, sqrt(2 ln(opacity / ALPHA_THRESHOLD)) sigma (at most 3.33 sigma):
    exactly where alpha falls below ALPHA_THRESHOLD, so no pixel with a visible contribution
    lies outside it and tiling never truncates a Gaussian.
    """
    rotation = viewmats[:, :3, :3]  # [C, 3, 3]
    translation = viewmats[:, :3, 3]  # [C, 3]
    means_cam = torch.einsum("cij,nj->cni", rotation, means) + translation[:, None, :]  # [C, N, 3]
    x, y, z = means_cam.unbind(-1)
    in_depth = (z >= near_plane) & (z <= far_plane)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    inv_z = 1.0 / z_safe

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    u, v = x * inv_z, y * inv_z
    means2d = torch.stack([fx * u + cx, fy * v + cy], -1)  # [C, N, 2]

    margin_x = FRUSTUM_MARGIN * 0.5 * width / fx
    margin_y = FRUSTUM_MARGIN * 0.5 * height / fy
    u_clamped = torch.clamp(u, -(cx / fx + margin_x), (width - cx) / fx + margin_x)
    v_clamped = torch.clamp(v, -(cy / fy + margin_y), (height - cy) / fy + margin_y)
    zero = torch.zeros_like(inv_z)
    jacobian = torch.stack(  # [C, N, 2, 3]
        [
            torch.stack([fx * inv_z, zero, -fx * u_clamped * inv_z], -1),
            torch.stack([zero, fy * inv_z, -fy * v_clamped * inv_z], -1),
        ],
        -2,
    )
    scaled_rotations = rotmats_from_quats(quats) * scales[:, None, :]  # [N, 3, 3] = R diag(s)
    jacobian_world = torch.einsum("cnij,cjk->cnik", jacobian, rotation)  # [C, N, 2, 3]
    A = torch.einsum("cnij,njk->cnik", jacobian_world, scaled_rotations)  # [C, N, 2, 3]; Sigma2d = A A^T
    row0, row1 = A[..., 0, :], A[..., 1, :]
    a0 = (row0 * row0).sum(-1)
    b0 = (row0 * row1).sum(-1)
    c0 = (row1 * row1).sum(-1)
    minor01 = row0[..., 0] * row1[..., 1] - row0[..., 1] * row1[..., 0]
    minor02 = row0[..., 0] * row1[..., 2] - row0[..., 2] * row1[..., 0]
    minor12 = row0[..., 1] * row1[..., 2] - row0[..., 2] * row1[..., 1]
    det0 = minor01 * minor01 + minor02 * minor02 + minor12 * minor12
    a, c = a0 + eps2d, c0 + eps2d
    det = det0 + eps2d * (a0 + c0) + eps2d * eps2d

    finite = torch.isfinite(means2d).all(-1) & torch.isfinite(a) & torch.isfinite(c) & torch.isfinite(det)
    usable = in_depth & finite & (det > 0)
    inv_det = 1.0 / torch.where(usable, det, torch.ones_like(det))
    conics = torch.stack([c * inv_det, -b0 * inv_det, a * inv_det], -1)  # [C, N, 3]

    compositing_opacities = opacities[None, :].expand_as(z)
    if antialiased:  # Mip-Splatting's compensation keeps the blurred Gaussian's total mass
        ratio = torch.where(usable, det0 * inv_det, torch.zeros_like(det0))
        compositing_opacities = compositing_opacities * torch.sqrt(ratio.clamp(min=MIN_COMPENSATION_RATIO))

    with torch.no_grad():
        level = torch.log(compositing_opacities.clamp(min=ALPHA_THRESHOLD) / ALPHA_THRESHOLD)
        extent = torch.sqrt(2.0 * level)  # Mahalanobis radius where alpha reaches ALPHA_THRESHOLD
        radius_x = torch.ceil(extent * torch.sqrt(torch.where(usable, a, zero))).clamp(max=MAX_RADIUS)
        radius_y = torch.ceil(extent * torch.sqrt(torch.where(usable, c, zero))).clamp(max=MAX_RADIUS)
        on_screen = (
            (means2d[..., 0] + radius_x > 0) & (means2d[..., 0] - radius_x < width)
            & (means2d[..., 1] + radius_y > 0) & (means2d[..., 1] - radius_y < height)
        )
        kept = usable & on_screen & (radius_x > 0) & (radius_y > 0)
        radii = torch.where(kept[..., None], torch.stack([radius_x, radius_y], -1), 0.0).to(torch.int32)
    return ScreenGaussians(means2d, conics, z, compositing_opacities, radii)
