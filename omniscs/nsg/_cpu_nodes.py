"""Numba kernels of a fit step's node preparation: raw parameters of every node -> world-frame rasterizer inputs.

For each Gaussian, fused: activation (``omniscs.gaussians.activate``: unit quaternion, exp of the clamped
log-scales, sigmoid of the opacity logit), its colour seen from the camera (``omniscs.render.sh.colors_from_sh``,
the direction taken in the node's frame) and Eq. 1's placement (``omniscs.nsg.compose.place_gaussians``).
Forward and a hand-derived backward, parallel over Gaussians, computing in float64 and writing float32. The
PyTorch code those functions hold is the definition; tests hold this one to it, in values and gradients, at the
zero-length rules (a zero quaternion, a camera on a Gaussian's centre) and at the clamps.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from omniscs.quaternions import MIN_QUAT_NORM
from omniscs.render.sh import MIN_DIRECTION_NORM, SH_C0, SH_C1, SH_C2, SH_C3, SH_COLOR_OFFSET

#: Coefficients of the SH basis the kernels evaluate (degree 3).
MAX_BASES = 16


@nb.njit(cache=True, inline="always")
def _basis(x, y, z, degree, out):
    """Real SH basis at the unit direction (x, y, z), gsplat's order (``omniscs.render.sh.sh_basis``)."""
    out[0] = SH_C0
    if degree >= 1:
        out[1] = -SH_C1 * y
        out[2] = SH_C1 * z
        out[3] = -SH_C1 * x
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out[4] = SH_C2[0] * xy
        out[5] = SH_C2[1] * yz
        out[6] = SH_C2[2] * (2 * zz - xx - yy)
        out[7] = SH_C2[3] * xz
        out[8] = SH_C2[4] * (xx - yy)
    if degree >= 3:
        xx, yy, zz, xy = x * x, y * y, z * z, x * y
        out[9] = SH_C3[0] * y * (3 * xx - yy)
        out[10] = SH_C3[1] * xy * z
        out[11] = SH_C3[2] * y * (4 * zz - xx - yy)
        out[12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
        out[13] = SH_C3[4] * x * (4 * zz - xx - yy)
        out[14] = SH_C3[5] * z * (xx - yy)
        out[15] = SH_C3[6] * x * (xx - 3 * yy)


@nb.njit(cache=True, inline="always")
def _basis_vjp(x, y, z, degree, g):
    """d(sum_b g[b] basis_b) / d(x, y, z) at a unit direction (the basis's chain rule, band by band)."""
    dx = dy = dz = 0.0
    if degree >= 1:
        dx -= SH_C1 * g[3]
        dy -= SH_C1 * g[1]
        dz += SH_C1 * g[2]
    if degree >= 2:
        dx += SH_C2[0] * y * g[4] - 2 * SH_C2[2] * x * g[6] + SH_C2[3] * z * g[7] + 2 * SH_C2[4] * x * g[8]
        dy += SH_C2[0] * x * g[4] + SH_C2[1] * z * g[5] - 2 * SH_C2[2] * y * g[6] - 2 * SH_C2[4] * y * g[8]
        dz += SH_C2[1] * y * g[5] + 4 * SH_C2[2] * z * g[6] + SH_C2[3] * x * g[7]
    if degree >= 3:
        xx, yy, zz = x * x, y * y, z * z
        dx += (SH_C3[0] * 6 * x * y * g[9] + SH_C3[1] * y * z * g[10] - SH_C3[2] * 2 * x * y * g[11]
               - SH_C3[3] * 6 * x * z * g[12] + SH_C3[4] * (4 * zz - 3 * xx - yy) * g[13]
               + SH_C3[5] * 2 * x * z * g[14] + SH_C3[6] * 3 * (xx - yy) * g[15])
        dy += (SH_C3[0] * 3 * (xx - yy) * g[9] + SH_C3[1] * x * z * g[10] + SH_C3[2] * (4 * zz - xx - 3 * yy) * g[11]
               - SH_C3[3] * 6 * y * z * g[12] - SH_C3[4] * 2 * x * y * g[13] - SH_C3[5] * 2 * y * z * g[14]
               - SH_C3[6] * 6 * x * y * g[15])
        dz += (SH_C3[1] * x * y * g[10] + SH_C3[2] * 8 * y * z * g[11] + SH_C3[3] * (6 * zz - 3 * xx - 3 * yy) * g[12]
               + SH_C3[4] * 8 * x * z * g[13] + SH_C3[5] * (xx - yy) * g[14])
    return dx, dy, dz


@nb.njit(cache=True, inline="always")
def _unit(a, b, c, d, floor):
    """(a, b, c, d) / norm and the norm; (0, 0, 0, 0) and norm 0 when the norm is below ``floor`` (or NaN)."""
    norm = math.sqrt(a * a + b * b + c * c + d * d)
    if not norm >= floor:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    return a / norm, b / norm, c / norm, d / norm, norm


@nb.njit(cache=True, inline="always")
def _direction(means, centres, i, k):
    """Unit viewing direction of Gaussian i in its node's frame and its length (+z and 0 when it has none)."""
    ux, uy, uz, _, norm = _unit(means[i, 0] - centres[k, 0], means[i, 1] - centres[k, 1],
                                means[i, 2] - centres[k, 2], 0.0, MIN_DIRECTION_NORM)
    if norm == 0.0:
        return 0.0, 0.0, 1.0, 0.0
    return ux, uy, uz, norm


@nb.njit(cache=True, parallel=True)
def prepare_forward(
    means, quats, log_scales, logits, sh_dc, sh_rest,  # [N, 3], [N, 4], [N, 3], [N], [N, 3], [N, R, 3] float32 raw
    node_of,        # [N] int64: the node of each Gaussian
    rotations,      # [K, 3, 3] float64 world_from_node rotation
    translations,   # [K, 3] float64
    rotation_quats,  # [K, 4] float64 unit quaternion of the rotation
    centres,        # [K, 3] float64 camera centre in the node's frame
    degree, log_scale_lo, log_scale_hi,
    out_means, out_quats, out_scales, out_opacities, out_colours,  # [N, 3], [N, 4], [N, 3], [N], [N, 3] float32
):
    for i in nb.prange(means.shape[0]):
        k = node_of[i]
        b = np.empty(MAX_BASES)  # private to the iteration (prange's bodies run on several threads)
        for r in range(3):
            out_means[i, r] = (rotations[k, r, 0] * means[i, 0] + rotations[k, r, 1] * means[i, 1]
                               + rotations[k, r, 2] * means[i, 2] + translations[k, r])
        qw, qx, qy, qz, qnorm = _unit(np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                                      np.float64(quats[i, 3]), MIN_QUAT_NORM)
        if qnorm == 0.0:
            qw = 1.0
        aw, ax, ay, az = rotation_quats[k, 0], rotation_quats[k, 1], rotation_quats[k, 2], rotation_quats[k, 3]
        out_quats[i, 0] = aw * qw - ax * qx - ay * qy - az * qz
        out_quats[i, 1] = aw * qx + ax * qw + ay * qz - az * qy
        out_quats[i, 2] = aw * qy - ax * qz + ay * qw + az * qx
        out_quats[i, 3] = aw * qz + ax * qy - ay * qx + az * qw
        for r in range(3):
            out_scales[i, r] = math.exp(min(max(np.float64(log_scales[i, r]), log_scale_lo), log_scale_hi))
        out_opacities[i] = 1.0 / (1.0 + math.exp(-np.float64(logits[i])))
        ux, uy, uz = 0.0, 0.0, 1.0  # degree 0 has no direction
        if degree > 0:
            ux, uy, uz, _ = _direction(means, centres, i, k)
        _basis(ux, uy, uz, degree, b)
        for ch in range(3):
            value = b[0] * sh_dc[i, ch]
            for j in range(1, (degree + 1) * (degree + 1)):
                value += b[j] * sh_rest[i, j - 1, ch]
            out_colours[i, ch] = max(value + SH_COLOR_OFFSET, 0.0)


@nb.njit(cache=True, inline="always")
def _no_gradient(v_means, v_quats, v_scales, v_opacities, v_colours, i):
    """Whether every upstream gradient of Gaussian i is 0."""
    nonzero = v_opacities[i] != 0.0
    for r in range(3):
        nonzero |= (v_means[i, r] != 0.0) | (v_scales[i, r] != 0.0) | (v_colours[i, r] != 0.0)
    for r in range(4):
        nonzero |= v_quats[i, r] != 0.0
    return not nonzero


@nb.njit(cache=True, inline="always")
def _zero_row(g_means, g_quats, g_log_scales, g_logits, g_sh_dc, g_sh_rest, i):
    for r in range(3):
        g_means[i, r] = 0.0
        g_log_scales[i, r] = 0.0
        g_sh_dc[i, r] = 0.0
    for r in range(4):
        g_quats[i, r] = 0.0
    g_logits[i] = 0.0
    for j in range(g_sh_rest.shape[1]):
        for ch in range(3):
            g_sh_rest[i, j, ch] = 0.0


@nb.njit(cache=True, parallel=True)
def prepare_backward(
    means, quats, log_scales, logits, sh_dc, sh_rest, node_of, rotations, translations, rotation_quats, centres,
    degree, log_scale_lo, log_scale_hi,  # as in prepare_forward
    v_means, v_quats, v_scales, v_opacities, v_colours,  # upstream gradients of its outputs, float32
    g_means, g_quats, g_log_scales, g_logits, g_sh_dc, g_sh_rest,  # out: gradients of the raw parameters, float32
):
    n_bases = (degree + 1) * (degree + 1)
    for i in nb.prange(means.shape[0]):
        if _no_gradient(v_means, v_quats, v_scales, v_opacities, v_colours, i):
            _zero_row(g_means, g_quats, g_log_scales, g_logits, g_sh_dc, g_sh_rest, i)
            continue  # a Gaussian the view did not see (most of them): every gradient is 0
        k = node_of[i]
        b = np.empty(MAX_BASES)  # private to the iteration
        gb = np.zeros(MAX_BASES)
        # means: R^T of the placed means' gradient (the colour's share is added below)
        gmx = gmy = gmz = 0.0
        for r in range(3):
            gmx += rotations[k, r, 0] * v_means[i, r]
            gmy += rotations[k, r, 1] * v_means[i, r]
            gmz += rotations[k, r, 2] * v_means[i, r]
        # quaternions: through a (x) q_unit (a fixed), then the normalisation
        qw, qx, qy, qz, qnorm = _unit(np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                                      np.float64(quats[i, 3]), MIN_QUAT_NORM)
        if qnorm == 0.0:
            for r in range(4):
                g_quats[i, r] = 0.0
        else:
            aw, ax, ay, az = rotation_quats[k, 0], rotation_quats[k, 1], rotation_quats[k, 2], rotation_quats[k, 3]
            gw, gx, gy, gz = v_quats[i, 0], v_quats[i, 1], v_quats[i, 2], v_quats[i, 3]
            uw = aw * gw + ax * gx + ay * gy + az * gz
            ux = -ax * gw + aw * gx + az * gy - ay * gz
            uy = -ay * gw - az * gx + aw * gy + ax * gz
            uz = -az * gw + ay * gx - ax * gy + aw * gz
            along = qw * uw + qx * ux + qy * uy + qz * uz
            g_quats[i, 0] = (uw - qw * along) / qnorm
            g_quats[i, 1] = (ux - qx * along) / qnorm
            g_quats[i, 2] = (uy - qy * along) / qnorm
            g_quats[i, 3] = (uz - qz * along) / qnorm
        for r in range(3):
            raw = np.float64(log_scales[i, r])
            inside = raw >= log_scale_lo and raw <= log_scale_hi
            g_log_scales[i, r] = v_scales[i, r] * math.exp(raw) if inside else 0.0
        opacity = 1.0 / (1.0 + math.exp(-np.float64(logits[i])))
        g_logits[i] = v_opacities[i] * opacity * (1.0 - opacity)
        # colours: clamp_min's mask, the coefficients' gradient, then the direction's
        dx, dy, dz, dnorm = 0.0, 0.0, 1.0, 0.0
        if degree > 0:
            dx, dy, dz, dnorm = _direction(means, centres, i, k)
        _basis(dx, dy, dz, degree, b)
        for ch in range(3):
            value = b[0] * sh_dc[i, ch]
            for j in range(1, n_bases):
                value += b[j] * sh_rest[i, j - 1, ch]
            v = v_colours[i, ch] if value + SH_COLOR_OFFSET >= 0.0 else 0.0
            g_sh_dc[i, ch] = b[0] * v
            gb[0] += sh_dc[i, ch] * v
            for j in range(1, sh_rest.shape[1] + 1):
                if j < n_bases:
                    g_sh_rest[i, j - 1, ch] = b[j] * v
                    gb[j] += sh_rest[i, j - 1, ch] * v
                else:
                    g_sh_rest[i, j - 1, ch] = 0.0
        if degree >= 1 and dnorm > 0.0:
            gux, guy, guz = _basis_vjp(dx, dy, dz, degree, gb)
            along = dx * gux + dy * guy + dz * guz
            gmx += (gux - dx * along) / dnorm
            gmy += (guy - dy * along) / dnorm
            gmz += (guz - dz * along) / dnorm
        g_means[i, 0] = gmx
        g_means[i, 1] = gmy
        g_means[i, 2] = gmz
