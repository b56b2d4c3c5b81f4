"""Numba kernels of the CPU backend: tile binning, front-to-back forward, back-to-front backward, reduction.

Arrays are float32 in memory; arithmetic is float64 in registers (free in scalar code, and it keeps
the float32 path close to the float64 reference). Every parallel loop writes disjoint memory, and
per-Gaussian gradients are summed in a fixed order, so results are bitwise reproducible.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from omniscs.render.constants import ALPHA_THRESHOLD, MAX_ALPHA, TRANSMITTANCE_STOP

#: Slack on the per-Gaussian Mahalanobis cut-off (which only skips exp for pixels whose alpha is
#: below ALPHA_THRESHOLD anyway); rounding can never move a visible pixel past it.
SIGMA_CUT_SLACK = 1e-6

#: Gradient slots per intersection before the colour channels: means2d (2), conic (3), opacity (1), |means2d| (2).
N_GEOMETRY_SLOTS = 8


@nb.njit(cache=True, inline="always")
def _sigma_cut(opacity):
    """Mahalanobis half-distance beyond which alpha < ALPHA_THRESHOLD."""
    return math.log(max(opacity, ALPHA_THRESHOLD) / ALPHA_THRESHOLD) + SIGMA_CUT_SLACK


@nb.njit(cache=True)
def bin_gaussians(
    means2d,       # [C*N, 2] float32
    radii,         # [C*N, 2] int32, 0 where culled
    depth_order,   # [C, N] int64 per-camera indices sorted by depth (stable), visible ones first
    n_visible,     # [C] int64
    width, height, tile,
):
    """Assign Gaussians to the tiles their pixel box touches, each tile's list sorted front to back.

    Returns tile_offsets [C*T + 1], isect_gaussians [M] (flat Gaussian c*N + g per intersection),
    pixel_boxes [C*N, 4] (x_lo, x_hi, y_lo, y_hi inclusive; x_lo > x_hi when empty),
    gaussian_offsets [C*N + 1] and gaussian_isects [M] (each Gaussian's intersections, tile order).
    """
    n_cams, n_gauss = depth_order.shape
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n_tiles = tiles_x * tiles_y
    pixel_boxes = np.empty((n_cams * n_gauss, 4), dtype=np.int32)
    per_gaussian = np.zeros(n_cams * n_gauss + 1, dtype=np.int64)
    for g in range(n_cams * n_gauss):
        pixel_boxes[g, 0] = 1
        pixel_boxes[g, 1] = 0
        pixel_boxes[g, 2] = 1
        pixel_boxes[g, 3] = 0
        if radii[g, 0] <= 0:
            continue
        mx = np.float64(means2d[g, 0])
        my = np.float64(means2d[g, 1])
        # pixel px is inside when |px + 0.5 - mx| <= rx; clip in float before converting to int
        x_lo = max(0.0, math.ceil(min(mx - radii[g, 0] - 0.5, width)))
        x_hi = min(width - 1.0, math.floor(max(mx + radii[g, 0] - 0.5, -1.0)))
        y_lo = max(0.0, math.ceil(min(my - radii[g, 1] - 0.5, height)))
        y_hi = min(height - 1.0, math.floor(max(my + radii[g, 1] - 0.5, -1.0)))
        if x_lo > x_hi or y_lo > y_hi:
            continue
        pixel_boxes[g, 0] = np.int32(x_lo)
        pixel_boxes[g, 1] = np.int32(x_hi)
        pixel_boxes[g, 2] = np.int32(y_lo)
        pixel_boxes[g, 3] = np.int32(y_hi)
        per_gaussian[g + 1] = (pixel_boxes[g, 1] // tile - pixel_boxes[g, 0] // tile + 1) * (
            pixel_boxes[g, 3] // tile - pixel_boxes[g, 2] // tile + 1)
    gaussian_offsets = np.cumsum(per_gaussian)
    n_isects = gaussian_offsets[-1]

    tile_counts = np.zeros(n_cams * n_tiles + 1, dtype=np.int64)
    for g in range(n_cams * n_gauss):
        if per_gaussian[g + 1] == 0:
            continue
        base = (g // n_gauss) * n_tiles
        for ty in range(pixel_boxes[g, 2] // tile, pixel_boxes[g, 3] // tile + 1):
            for tx in range(pixel_boxes[g, 0] // tile, pixel_boxes[g, 1] // tile + 1):
                tile_counts[base + ty * tiles_x + tx + 1] += 1
    tile_offsets = np.cumsum(tile_counts)

    cursor = tile_offsets[:-1].copy()
    isect_gaussians = np.empty(n_isects, dtype=np.int32)
    gaussian_isects = np.empty(n_isects, dtype=np.int64)
    for cam in range(n_cams):
        base = cam * n_tiles
        for rank in range(n_visible[cam]):
            g = cam * n_gauss + depth_order[cam, rank]
            k = gaussian_offsets[g]
            for ty in range(pixel_boxes[g, 2] // tile, pixel_boxes[g, 3] // tile + 1):
                for tx in range(pixel_boxes[g, 0] // tile, pixel_boxes[g, 1] // tile + 1):
                    t = base + ty * tiles_x + tx
                    isect_gaussians[cursor[t]] = g
                    gaussian_isects[k] = cursor[t]
                    cursor[t] += 1
                    k += 1
    return tile_offsets, isect_gaussians, pixel_boxes, gaussian_offsets, gaussian_isects


@nb.njit(cache=True, parallel=True)
def rasterize_forward(
    tile_offsets, isect_gaussians, pixel_boxes,
    means2d,    # [C*N, 2] float32
    conics,     # [C*N, 3] float32
    colors,     # [C*N, D] float32
    opacities,  # [C*N] float32
    width, height, tile,
    out_colors,         # [C, H, W, D] float32
    out_transmittance,  # [C, H, W] float32
    out_counts,         # [C, H, W] int32: list entries up to and including the last one composited
):
    n_cams = out_colors.shape[0]
    n_channels = colors.shape[1]
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n_tiles = tiles_x * tiles_y
    for job in nb.prange(n_cams * n_tiles):
        cam = job // n_tiles
        ty = (job % n_tiles) // tiles_x
        tx = (job % n_tiles) % tiles_x
        x0 = tx * tile
        y0 = ty * tile
        x1 = min(x0 + tile, width)
        y1 = min(y0 + tile, height)
        tw = x1 - x0
        th = y1 - y0
        transmittance = np.ones((th, tw), dtype=np.float64)
        accumulated = np.zeros((th, tw, n_channels), dtype=np.float64)
        counts = np.zeros((th, tw), dtype=np.int32)
        done = np.zeros((th, tw), dtype=np.bool_)
        n_done = 0
        start = tile_offsets[job]
        end = tile_offsets[job + 1]
        for p in range(start, end):
            g = isect_gaussians[p]
            bx0 = max(pixel_boxes[g, 0], x0)
            bx1 = min(pixel_boxes[g, 1], x1 - 1)
            by0 = max(pixel_boxes[g, 2], y0)
            by1 = min(pixel_boxes[g, 3], y1 - 1)
            mx = np.float64(means2d[g, 0])
            my = np.float64(means2d[g, 1])
            ca = np.float64(conics[g, 0])
            cb = np.float64(conics[g, 1])
            cc = np.float64(conics[g, 2])
            opacity = np.float64(opacities[g])
            cut = _sigma_cut(opacity)
            for py in range(by0, by1 + 1):
                dy = my - (py + 0.5)
                ly = py - y0
                for px in range(bx0, bx1 + 1):
                    lx = px - x0
                    if done[ly, lx]:
                        continue
                    dx = mx - (px + 0.5)
                    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if sigma < 0.0 or sigma > cut:
                        continue
                    alpha = min(MAX_ALPHA, opacity * math.exp(-sigma))
                    if alpha < ALPHA_THRESHOLD:
                        continue
                    t_before = transmittance[ly, lx]
                    t_after = t_before * (1.0 - alpha)
                    if t_after <= TRANSMITTANCE_STOP:
                        done[ly, lx] = True
                        n_done += 1
                        continue
                    weight = alpha * t_before
                    for k in range(n_channels):
                        accumulated[ly, lx, k] += weight * colors[g, k]
                    transmittance[ly, lx] = t_after
                    counts[ly, lx] = p - start + 1
            if n_done == tw * th:
                break
        for ly in range(th):
            for lx in range(tw):
                out_transmittance[cam, y0 + ly, x0 + lx] = transmittance[ly, lx]
                out_counts[cam, y0 + ly, x0 + lx] = counts[ly, lx]
                for k in range(n_channels):
                    out_colors[cam, y0 + ly, x0 + lx, k] = accumulated[ly, lx, k]


@nb.njit(cache=True, parallel=True)
def rasterize_backward(
    tile_offsets, isect_gaussians, pixel_boxes,
    means2d, conics, colors, opacities,   # as in rasterize_forward
    width, height, tile,
    transmittance_final,  # [C, H, W] float32 from the forward pass
    counts,               # [C, H, W] int32 from the forward pass
    grad_colors,          # [C, H, W, D] float32, dL/d(render colours without background)
    grad_transmittance,   # [C, H, W] float32, dL/d(final transmittance)
    slots,                # [M, N_GEOMETRY_SLOTS + D] float32 out: this intersection's gradient terms
):
    """Walk each tile's list back to front, rebuilding transmittance by division (as gsplat)."""
    n_cams = transmittance_final.shape[0]
    n_channels = colors.shape[1]
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n_tiles = tiles_x * tiles_y
    for job in nb.prange(n_cams * n_tiles):
        cam = job // n_tiles
        ty = (job % n_tiles) // tiles_x
        tx = (job % n_tiles) % tiles_x
        x0 = tx * tile
        y0 = ty * tile
        x1 = min(x0 + tile, width)
        y1 = min(y0 + tile, height)
        tw = x1 - x0
        th = y1 - y0
        start = tile_offsets[job]
        end = tile_offsets[job + 1]
        for p in range(start, end):
            for k in range(slots.shape[1]):
                slots[p, k] = 0.0
        transmittance = np.empty((th, tw), dtype=np.float64)
        behind = np.zeros((th, tw, n_channels), dtype=np.float64)  # colour composited behind the current Gaussian
        max_count = 0
        for ly in range(th):
            for lx in range(tw):
                transmittance[ly, lx] = transmittance_final[cam, y0 + ly, x0 + lx]
                max_count = max(max_count, counts[cam, y0 + ly, x0 + lx])
        grad_color_local = np.empty(n_channels, dtype=np.float64)
        for rank in range(max_count - 1, -1, -1):
            p = start + rank
            g = isect_gaussians[p]
            bx0 = max(pixel_boxes[g, 0], x0)
            bx1 = min(pixel_boxes[g, 1], x1 - 1)
            by0 = max(pixel_boxes[g, 2], y0)
            by1 = min(pixel_boxes[g, 3], y1 - 1)
            mx = np.float64(means2d[g, 0])
            my = np.float64(means2d[g, 1])
            ca = np.float64(conics[g, 0])
            cb = np.float64(conics[g, 1])
            cc = np.float64(conics[g, 2])
            opacity = np.float64(opacities[g])
            cut = _sigma_cut(opacity)
            g_mx = 0.0
            g_my = 0.0
            g_ca = 0.0
            g_cb = 0.0
            g_cc = 0.0
            g_opacity = 0.0
            g_abs_x = 0.0
            g_abs_y = 0.0
            for k in range(n_channels):
                grad_color_local[k] = 0.0
            for py in range(by0, by1 + 1):
                dy = my - (py + 0.5)
                ly = py - y0
                for px in range(bx0, bx1 + 1):
                    if rank >= counts[cam, py, px]:
                        continue
                    lx = px - x0
                    dx = mx - (px + 0.5)
                    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if sigma < 0.0 or sigma > cut:
                        continue
                    gaussian = math.exp(-sigma)
                    raw_alpha = opacity * gaussian
                    alpha = min(MAX_ALPHA, raw_alpha)
                    if alpha < ALPHA_THRESHOLD:
                        continue
                    inv_keep = 1.0 / (1.0 - alpha)
                    t_before = transmittance[ly, lx] * inv_keep
                    transmittance[ly, lx] = t_before
                    weight = alpha * t_before
                    grad_alpha = 0.0
                    for k in range(n_channels):
                        g_out = np.float64(grad_colors[cam, py, px, k])
                        grad_color_local[k] += weight * g_out
                        grad_alpha += (colors[g, k] * t_before - behind[ly, lx, k] * inv_keep) * g_out
                        behind[ly, lx, k] += colors[g, k] * weight
                    t_final = np.float64(transmittance_final[cam, py, px])
                    grad_alpha -= t_final * inv_keep * grad_transmittance[cam, py, px]
                    if raw_alpha <= MAX_ALPHA:
                        grad_sigma = -raw_alpha * grad_alpha
                        g_ca += 0.5 * grad_sigma * dx * dx
                        g_cb += grad_sigma * dx * dy
                        g_cc += 0.5 * grad_sigma * dy * dy
                        gx = grad_sigma * (ca * dx + cb * dy)
                        gy = grad_sigma * (cb * dx + cc * dy)
                        g_mx += gx
                        g_my += gy
                        g_abs_x += abs(gx)
                        g_abs_y += abs(gy)
                        g_opacity += gaussian * grad_alpha
            slots[p, 0] = g_mx
            slots[p, 1] = g_my
            slots[p, 2] = g_ca
            slots[p, 3] = g_cb
            slots[p, 4] = g_cc
            slots[p, 5] = g_opacity
            slots[p, 6] = g_abs_x
            slots[p, 7] = g_abs_y
            for k in range(n_channels):
                slots[p, N_GEOMETRY_SLOTS + k] = grad_color_local[k]


@nb.njit(cache=True, parallel=True)
def reduce_slots(
    gaussian_offsets,  # [C*N + 1]
    gaussian_isects,   # [M]
    slots,             # [M, S] float32
    out,               # [C*N, S] float32: per-Gaussian sums, in tile order
):
    for g in nb.prange(out.shape[0]):
        for k in range(slots.shape[1]):
            total = 0.0
            for i in range(gaussian_offsets[g], gaussian_offsets[g + 1]):
                total += slots[gaussian_isects[i], k]
            out[g, k] = total
