"""Numba kernels of the CPU backend's projection: the EWA math of ``projection.py``, fused per Gaussian.

Forward and a hand-derived backward, parallel over Gaussians with the cameras looped inside, in
float64 whatever the arrays' type: every value is read as float64 and rounded once when written, so
float32 Gaussians need no float64 copies in or out (one compiled version per type). Fusing matters on
shared machines: one parallel region instead of about a hundred small PyTorch ops, each of which waits
for every thread. The PyTorch version in ``projection.py`` is the
definition; tests hold this one to it.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from omniscs.quaternions import MIN_QUAT_NORM
from omniscs.render.constants import ALPHA_THRESHOLD, FRUSTUM_MARGIN, MAX_RADIUS
from omniscs.render.projection import MIN_COMPENSATION_RATIO


@nb.njit(cache=True, inline="always")
def _unit_quat(quats, n):
    """Normalised quaternion and its norm; the identity (norm 0) when too short to have a direction
    (the rule of ``omniscs.quaternions.normalize_quats``, fused here because Numba cannot call torch)."""
    w, x, y, z = np.float64(quats[n, 0]), np.float64(quats[n, 1]), np.float64(quats[n, 2]), np.float64(quats[n, 3])
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not norm >= MIN_QUAT_NORM:
        return 1.0, 0.0, 0.0, 0.0, 0.0
    return w / norm, x / norm, y / norm, z / norm, norm


@nb.njit(cache=True, inline="always")
def _rotation(w, x, y, z, R):
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@nb.njit(cache=True, inline="always")
def _rotated_scaled(viewmats, c, i, R, k):
    """Entry (i, k) of W R, W being camera c's rotation (scale it by s_k for W R S)."""
    return viewmats[c, i, 0] * R[0, k] + viewmats[c, i, 1] * R[1, k] + viewmats[c, i, 2] * R[2, k]


@nb.njit(cache=True, inline="always")
def _camera_frame(means, n, viewmats, Ks, c, width, height, near, far):
    """Camera-frame centre, the in-depth flag, 1/z, and the clamped and unclamped x/z, y/z with their clamp flags."""
    px, py, pz = np.float64(means[n, 0]), np.float64(means[n, 1]), np.float64(means[n, 2])
    x = viewmats[c, 0, 0] * px + viewmats[c, 0, 1] * py + viewmats[c, 0, 2] * pz + viewmats[c, 0, 3]
    y = viewmats[c, 1, 0] * px + viewmats[c, 1, 1] * py + viewmats[c, 1, 2] * pz + viewmats[c, 1, 3]
    z = viewmats[c, 2, 0] * px + viewmats[c, 2, 1] * py + viewmats[c, 2, 2] * pz + viewmats[c, 2, 3]
    in_depth = (z >= near) and (z <= far)
    inv_z = 1.0 / z if in_depth else 1.0
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    u = x * inv_z
    v = y * inv_z
    margin_x = FRUSTUM_MARGIN * 0.5 * width / fx
    margin_y = FRUSTUM_MARGIN * 0.5 * height / fy
    lo_u, hi_u = -(cx / fx + margin_x), (width - cx) / fx + margin_x
    lo_v, hi_v = -(cy / fy + margin_y), (height - cy) / fy + margin_y
    u_clamped = min(max(u, lo_u), hi_u)
    v_clamped = min(max(v, lo_v), hi_v)
    u_free = (u >= lo_u) and (u <= hi_u)
    v_free = (v >= lo_v) and (v <= hi_v)
    return x, y, z, in_depth, inv_z, u, v, u_clamped, v_clamped, u_free, v_free


#: 2 ln(1 / ALPHA_THRESHOLD): the squared cut-off extent (in sigmas) of an opacity of 1.
_EXTENT2_OPAQUE = 2.0 * math.log(1.0 / ALPHA_THRESHOLD)

#: Relative slack on the radii's bound (rounding of the bound's own arithmetic).
_BOUND_SLACK = 1.0 + 1e-9


def norms2(viewmats: np.ndarray) -> np.ndarray:  # [C, 4, 4] -> [C]
    """The square of each camera rotation's largest singular value (1 for a rotation), a little above."""
    return np.linalg.norm(viewmats[:, :3, :3], ord=2, axis=(1, 2)) ** 2 * (1.0 + 1e-12)


@nb.njit(cache=True, parallel=True)
def project_forward(
    means, quats, scales, opacities,  # [N, 3], [N, 4], [N, 3], [N] float32 or float64
    viewmats, Ks,                     # [C, 4, 4], [C, 3, 3] float64
    width, height, near, far, eps2d, antialiased,
    rotation_norms2,  # [C] float64, at least the square of each camera's largest singular value (``norms2``)
    out_means2d,    # [C, N, 2] the Gaussians' type
    out_conics,     # [C, N, 3] the Gaussians' type
    out_depths,     # [C, N] float64 (the sort key)
    out_opacities,  # [C, N] the Gaussians' type
    out_radii,      # [C, N, 2] int32
):
    """Culled pairs get radii 0 and finite values that mean nothing. Pairs outside [near, far], and those whose
    bound on the radii keeps them off the screen, skip the covariance (in a fit's view about two in five
    Gaussians are behind the camera and one in three is in front but off the screen)."""
    n_cams = viewmats.shape[0]
    for n in nb.prange(means.shape[0]):
        R = np.empty((3, 3))
        rotated = False
        opacity = np.float64(opacities[n])
        # extent^2 of the cut-off (as below) at the most opaque the compensation allows: the radii's bound
        extent2 = 2.0 * math.log(max(opacity, ALPHA_THRESHOLD) / ALPHA_THRESHOLD) if opacity > 1.0 else _EXTENT2_OPAQUE
        scales2 = 0.0
        for k in range(3):
            scales2 += np.float64(scales[n, k]) ** 2
        for c in range(n_cams):
            x, y, z, in_depth, inv_z, u, v, uc, vc, _, _ = _camera_frame(means, n, viewmats, Ks, c, width, height, near, far)
            fx, fy = Ks[c, 0, 0], Ks[c, 1, 1]
            mx = fx * u + Ks[c, 0, 2]
            my = fy * v + Ks[c, 1, 2]
            off_x = off_y = False
            if in_depth:
                # |row of J W R S|^2 <= (f / z)^2 (1 + clamped^2) |W|^2 sum_k s_k^2, and ceil(r) < r + 1
                spread = rotation_norms2[c] * scales2 * inv_z * inv_z
                bound_x = extent2 * (fx * fx * (1.0 + uc * uc) * spread + eps2d) * _BOUND_SLACK
                bound_y = extent2 * (fy * fy * (1.0 + vc * vc) * spread + eps2d) * _BOUND_SLACK
                off_x = (mx + 1.0 < 0.0 and bound_x <= (mx + 1.0) ** 2) or (
                    mx - 1.0 - width > 0.0 and bound_x <= (mx - 1.0 - width) ** 2)
                off_y = (my + 1.0 < 0.0 and bound_y <= (my + 1.0) ** 2) or (
                    my - 1.0 - height > 0.0 and bound_y <= (my - 1.0 - height) ** 2)
            if not in_depth or off_x or off_y:
                out_means2d[c, n, 0] = mx if math.isfinite(mx) else 0.0
                out_means2d[c, n, 1] = my if math.isfinite(my) else 0.0
                for k in range(3):
                    out_conics[c, n, k] = 0.0
                out_depths[c, n] = z if math.isfinite(z) else 0.0
                out_opacities[c, n] = opacity
                out_radii[c, n, 0] = 0
                out_radii[c, n, 1] = 0
                continue
            if not rotated:
                w, qx, qy, qz, _ = _unit_quat(quats, n)
                _rotation(w, qx, qy, qz, R)
                rotated = True
            # A = J W R S, row by row: J = [[fx/z, 0, -fx uc/z], [0, fy/z, -fy vc/z]]
            a00 = a01 = a02 = a10 = a11 = a12 = 0.0
            for k in range(3):
                b0 = _rotated_scaled(viewmats, c, 0, R, k) * np.float64(scales[n, k])
                b1 = _rotated_scaled(viewmats, c, 1, R, k) * np.float64(scales[n, k])
                b2 = _rotated_scaled(viewmats, c, 2, R, k) * np.float64(scales[n, k])
                row0 = fx * inv_z * b0 - fx * uc * inv_z * b2
                row1 = fy * inv_z * b1 - fy * vc * inv_z * b2
                if k == 0:
                    a00, a10 = row0, row1
                elif k == 1:
                    a01, a11 = row0, row1
                else:
                    a02, a12 = row0, row1
            ca0 = a00 * a00 + a01 * a01 + a02 * a02
            cb0 = a00 * a10 + a01 * a11 + a02 * a12
            cc0 = a10 * a10 + a11 * a11 + a12 * a12
            m01 = a00 * a11 - a01 * a10
            m02 = a00 * a12 - a02 * a10
            m12 = a01 * a12 - a02 * a11
            det0 = m01 * m01 + m02 * m02 + m12 * m12
            ca = ca0 + eps2d
            cc = cc0 + eps2d
            det = det0 + eps2d * (ca0 + cc0) + eps2d * eps2d
            finite = math.isfinite(mx) and math.isfinite(my) and math.isfinite(ca) and math.isfinite(cc) and math.isfinite(det)
            usable = in_depth and finite and det > 0.0
            inv_det = 1.0 / det if usable else 1.0
            opacity_c = opacity
            if antialiased:
                ratio = det0 * inv_det if usable else 0.0
                opacity_c = opacity * math.sqrt(max(ratio, MIN_COMPENSATION_RATIO))
            out_means2d[c, n, 0] = mx
            out_means2d[c, n, 1] = my
            out_conics[c, n, 0] = cc * inv_det
            out_conics[c, n, 1] = -cb0 * inv_det
            out_conics[c, n, 2] = ca * inv_det
            out_depths[c, n] = z
            out_opacities[c, n] = opacity_c
            extent = math.sqrt(2.0 * math.log(max(opacity_c, ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
            radius_x = min(math.ceil(extent * math.sqrt(ca if usable else 0.0)), MAX_RADIUS)
            radius_y = min(math.ceil(extent * math.sqrt(cc if usable else 0.0)), MAX_RADIUS)
            on_screen = (mx + radius_x > 0) and (mx - radius_x < width) and (my + radius_y > 0) and (my - radius_y < height)
            kept = usable and on_screen and radius_x > 0 and radius_y > 0
            out_radii[c, n, 0] = np.int32(radius_x) if kept else 0
            out_radii[c, n, 1] = np.int32(radius_y) if kept else 0


@nb.njit(cache=True, parallel=True)
def project_backward(
    means, quats, scales, opacities, viewmats, Ks,  # as in project_forward
    width, height, near, far, eps2d, antialiased,
    radii,          # [C, N, 2] int32 from the forward pass
    v_means2d,      # [C, N, 2] upstream gradients (float32 or float64)
    v_conics,       # [C, N, 3]
    v_depths,       # [C, N]
    v_opacities_c,  # [C, N]
    out_means,      # [N, 3] the Gaussians' type
    out_quats,      # [N, 4]
    out_scales,     # [N, 3]
    out_opacities,  # [N]
):
    """Chain rule through projection_forward; culled (Gaussian, camera) pairs contribute nothing."""
    n_cams = viewmats.shape[0]
    for n in nb.prange(means.shape[0]):
        seen = False
        for c in range(n_cams):
            seen |= radii[c, n, 0] > 0
        if not seen:  # culled by every camera: no gradient
            for i in range(3):
                out_means[n, i] = 0.0
                out_scales[n, i] = 0.0
            for i in range(4):
                out_quats[n, i] = 0.0
            out_opacities[n] = 0.0
            continue
        w, qx, qy, qz, qnorm = _unit_quat(quats, n)
        R = np.empty((3, 3))
        _rotation(w, qx, qy, qz, R)
        B = np.empty((3, 3))       # W R S for the current camera
        v_M = np.zeros((3, 3))     # gradient of R S, summed over cameras
        v_mean = np.zeros(3)
        v_opacity = 0.0
        for c in range(n_cams):
            if radii[c, n, 0] <= 0:
                continue
            x, y, z, _, inv_z, u, v, uc, vc, u_free, v_free = _camera_frame(means, n, viewmats, Ks, c, width, height, near, far)
            fx, fy = Ks[c, 0, 0], Ks[c, 1, 1]
            for i in range(3):
                for k in range(3):
                    B[i, k] = _rotated_scaled(viewmats, c, i, R, k) * np.float64(scales[n, k])
            j00 = fx * inv_z
            j02 = -fx * uc * inv_z
            j11 = fy * inv_z
            j12 = -fy * vc * inv_z
            r0 = np.empty(3)
            r1 = np.empty(3)
            for k in range(3):
                r0[k] = j00 * B[0, k] + j02 * B[2, k]
                r1[k] = j11 * B[1, k] + j12 * B[2, k]
            ca0 = r0[0] * r0[0] + r0[1] * r0[1] + r0[2] * r0[2]
            cb0 = r0[0] * r1[0] + r0[1] * r1[1] + r0[2] * r1[2]
            cc0 = r1[0] * r1[0] + r1[1] * r1[1] + r1[2] * r1[2]
            m01 = r0[0] * r1[1] - r0[1] * r1[0]
            m02 = r0[0] * r1[2] - r0[2] * r1[0]
            m12 = r0[1] * r1[2] - r0[2] * r1[1]
            det0 = m01 * m01 + m02 * m02 + m12 * m12
            ca = ca0 + eps2d
            cc = cc0 + eps2d
            det = det0 + eps2d * (ca0 + cc0) + eps2d * eps2d
            inv_det = 1.0 / det

            # conic = (cc, -cb0, ca) / det
            ka, kb, kc = np.float64(v_conics[c, n, 0]), np.float64(v_conics[c, n, 1]), np.float64(v_conics[c, n, 2])
            v_inv = ka * cc - kb * cb0 + kc * ca
            v_cc0 = ka * inv_det
            v_cb0 = -kb * inv_det
            v_ca0 = kc * inv_det
            v_det0 = 0.0
            if antialiased:
                ratio = det0 * inv_det
                compensation = math.sqrt(max(ratio, MIN_COMPENSATION_RATIO))
                v_opacity += np.float64(v_opacities_c[c, n]) * compensation
                if ratio > MIN_COMPENSATION_RATIO:
                    v_ratio = np.float64(v_opacities_c[c, n]) * np.float64(opacities[n]) * 0.5 / compensation
                    v_det0 += v_ratio * inv_det
                    v_inv += v_ratio * det0
            else:
                v_opacity += np.float64(v_opacities_c[c, n])
            v_det = -v_inv * inv_det * inv_det
            v_det0 += v_det
            v_ca0 += eps2d * v_det
            v_cc0 += eps2d * v_det

            # back to the rows of A
            v_r0 = np.empty(3)
            v_r1 = np.empty(3)
            for k in range(3):
                v_r0[k] = 2.0 * v_ca0 * r0[k] + v_cb0 * r1[k]
                v_r1[k] = 2.0 * v_cc0 * r1[k] + v_cb0 * r0[k]
            g01 = 2.0 * m01 * v_det0
            g02 = 2.0 * m02 * v_det0
            g12 = 2.0 * m12 * v_det0
            v_r0[0] += g01 * r1[1] + g02 * r1[2]
            v_r0[1] += -g01 * r1[0] + g12 * r1[2]
            v_r0[2] += -g02 * r1[0] - g12 * r1[1]
            v_r1[0] += -g01 * r0[1] - g02 * r0[2]
            v_r1[1] += g01 * r0[0] - g12 * r0[2]
            v_r1[2] += g02 * r0[0] + g12 * r0[1]

            # A = J B: gradients of J's entries and of B
            v_j00 = v_r0[0] * B[0, 0] + v_r0[1] * B[0, 1] + v_r0[2] * B[0, 2]
            v_j02 = v_r0[0] * B[2, 0] + v_r0[1] * B[2, 1] + v_r0[2] * B[2, 2]
            v_j11 = v_r1[0] * B[1, 0] + v_r1[1] * B[1, 1] + v_r1[2] * B[1, 2]
            v_j12 = v_r1[0] * B[2, 0] + v_r1[1] * B[2, 1] + v_r1[2] * B[2, 2]
            for k in range(3):
                v_b0 = j00 * v_r0[k]
                v_b1 = j11 * v_r1[k]
                v_b2 = j02 * v_r0[k] + j12 * v_r1[k]
                # B = W (R S): gradient of R S is W^T v_B
                for i in range(3):
                    v_M[i, k] += viewmats[c, 0, i] * v_b0 + viewmats[c, 1, i] * v_b1 + viewmats[c, 2, i] * v_b2

            # J and means2d through z, u, v
            v_z = -(j00 * v_j00 + j11 * v_j11) * inv_z - (j02 * v_j02 + j12 * v_j12) * inv_z
            v_u = fx * np.float64(v_means2d[c, n, 0]) + (-fx * inv_z * v_j02 if u_free else 0.0)
            v_v = fy * np.float64(v_means2d[c, n, 1]) + (-fy * inv_z * v_j12 if v_free else 0.0)
            v_x = v_u * inv_z
            v_y = v_v * inv_z
            v_z += -(v_u * x + v_v * y) * inv_z * inv_z + np.float64(v_depths[c, n])
            for i in range(3):
                v_mean[i] += viewmats[c, 0, i] * v_x + viewmats[c, 1, i] * v_y + viewmats[c, 2, i] * v_z

        for i in range(3):
            out_means[n, i] = v_mean[i]
        out_opacities[n] = v_opacity
        # M = R diag(s)
        G = np.empty((3, 3))
        for k in range(3):
            out_scales[n, k] = v_M[0, k] * R[0, k] + v_M[1, k] * R[1, k] + v_M[2, k] * R[2, k]
            for i in range(3):
                G[i, k] = v_M[i, k] * np.float64(scales[n, k])
        if qnorm == 0.0:
            for i in range(4):
                out_quats[n, i] = 0.0
            continue
        v_w = 2.0 * (-qz * G[0, 1] + qy * G[0, 2] + qz * G[1, 0] - qx * G[1, 2] - qy * G[2, 0] + qx * G[2, 1])
        v_x = 2.0 * (qy * G[0, 1] + qz * G[0, 2] + qy * G[1, 0] - 2 * qx * G[1, 1] - w * G[1, 2]
                     + qz * G[2, 0] + w * G[2, 1] - 2 * qx * G[2, 2])
        v_y = 2.0 * (-2 * qy * G[0, 0] + qx * G[0, 1] + w * G[0, 2] + qx * G[1, 0] + qz * G[1, 2]
                     - w * G[2, 0] + qz * G[2, 1] - 2 * qy * G[2, 2])
        v_zq = 2.0 * (-2 * qz * G[0, 0] - w * G[0, 1] + qx * G[0, 2] + w * G[1, 0] - 2 * qz * G[1, 1]
                      + qy * G[1, 2] + qx * G[2, 0] + qy * G[2, 1])
        # through q / |q|: remove the radial part, divide by the norm
        radial = w * v_w + qx * v_x + qy * v_y + qz * v_zq
        out_quats[n, 0] = (v_w - w * radial) / qnorm
        out_quats[n, 1] = (v_x - qx * radial) / qnorm
        out_quats[n, 2] = (v_y - qy * radial) / qnorm
        out_quats[n, 3] = (v_zq - qz * radial) / qnorm
