"""Numba kernels of the CPU backend: tile binning, front-to-back forward, back-to-front backward, reduction.

Arrays are float32 in memory; arithmetic is float64 in registers (free in scalar code, and it keeps
the float32 path close to the float64 reference). Every parallel loop writes disjoint memory, and
per-Gaussian gradients are summed in a fixed order, so results are bitwise reproducible.
A pixel is skipped, in forward and backward alike, by the same tests in the same order.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from omniscs.render.constants import ALPHA_THRESHOLD, MAX_ALPHA, TILE_SIZE, TRANSMITTANCE_STOP

#: Slack on the per-Gaussian cut-off of the Mahalanobis half-distance sigma beyond which alpha is
#: below ALPHA_THRESHOLD anyway; only saves exp() calls, never removes a visible pixel.
SIGMA_CUT_SLACK = 1e-6

#: Extra slack (in sigma) of the test that skips tile rows missing the cut-off ellipse entirely, so
#: rounding never skips a row holding a pixel that passes the per-pixel sigma test.
ROW_SPAN_SLACK = 1e-4

#: Columns of a Gaussian record: centre x, y; conic a, b, c; opacity; sigma cut-off; then for the
#: row test: 2 a (cut-off + ROW_SPAN_SLACK), a c - b^2, 1 / a.
N_RECORD = 10

#: exp(-sigma) is evaluated as (Taylor polynomial at sigma / 2^EXP_SQUARINGS)^(2^EXP_SQUARINGS): plain
#: arithmetic that vectorises (libm exp does not), relative error < 1e-7 for sigma up to ln(255).
EXP_SQUARINGS = 6

#: Gradient slots per intersection before the colour channels: means2d (2), conic (3), opacity (1), |means2d| (2).
N_GEOMETRY_SLOTS = 8


@nb.njit(cache=True, parallel=True)
def make_records(means2d, conics, opacities, radii):  # [G, 2], [G, 3], [G], [G, 2] -> [G, N_RECORD] float64, [G] bool
    """Pack what the pixel loops read per Gaussian into one row; flag Gaussians that can be drawn."""
    n = means2d.shape[0]
    records = np.empty((n, N_RECORD), dtype=np.float64)
    drawable = np.empty(n, dtype=np.bool_)
    for g in nb.prange(n):
        opacity = np.float64(opacities[g])
        records[g, 0] = means2d[g, 0]
        records[g, 1] = means2d[g, 1]
        records[g, 2] = conics[g, 0]
        records[g, 3] = conics[g, 1]
        records[g, 4] = conics[g, 2]
        records[g, 5] = opacity
        records[g, 6] = math.log(max(opacity, ALPHA_THRESHOLD) / ALPHA_THRESHOLD) + SIGMA_CUT_SLACK
        records[g, 7] = 2.0 * records[g, 2] * (records[g, 6] + ROW_SPAN_SLACK)
        records[g, 8] = records[g, 2] * records[g, 4] - records[g, 3] * records[g, 3]
        records[g, 9] = 1.0 / records[g, 2] if records[g, 2] > 0.0 else 0.0
        finite = True
        for k in range(N_RECORD):
            finite = finite and math.isfinite(records[g, k])
        positive = records[g, 2] > 0.0 and records[g, 8] > 0.0
        drawable[g] = radii[g, 0] > 0 and radii[g, 1] > 0 and finite and positive
    return records, drawable


@nb.njit(cache=True)
def bin_gaussians(
    records,       # [C*N, N_RECORD]
    drawable,      # [C*N] bool
    radii,         # [C*N, 2] int32
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
        if not drawable[g]:
            continue
        mx = records[g, 0]
        my = records[g, 1]
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


@nb.njit(cache=True, inline="always")
def _exp_neg(sigma):
    """exp(-sigma) for 0 <= sigma <= ~6 by scaled Taylor series and repeated squaring."""
    t = sigma * (1.0 / (1 << EXP_SQUARINGS))
    p = 1.0 - t * (1.0 - t * (0.5 - t * (1.0 / 6.0 - t * (1.0 / 24.0 - t * (1.0 / 120.0)))))
    # EXP_SQUARINGS squarings, written out: a loop here would stop LLVM vectorising the caller
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    return p


@nb.njit(cache=True, inline="always")
def _row_alphas(records, g, dy, x0, first, last, gaussian_row, alpha_row):
    """exp(-sigma) and alpha of Gaussian g over the TILE_SIZE pixels of one tile row (alpha 0 = skipped).

    Lanes first..last (tile-relative columns) are the Gaussian's pixel box; the loop has a fixed
    trip count and no branches so that LLVM vectorises it. Forward and backward both call it, so
    they take identical decisions.
    """
    mx = records[g, 0]
    ca = records[g, 2]
    cb_dy = records[g, 3] * dy
    cc_dy2 = records[g, 4] * dy * dy
    opacity = records[g, 5]
    cut = records[g, 6]
    for i in range(TILE_SIZE):
        dx = mx - (x0 + i + 0.5)
        sigma = 0.5 * (ca * dx * dx + cc_dy2) + cb_dy * dx
        inside = (i >= first) & (i <= last) & (sigma >= 0.0) & (sigma <= cut)
        gaussian = _exp_neg(min(max(sigma, 0.0), cut))
        alpha = min(MAX_ALPHA, opacity * gaussian)
        gaussian_row[i] = gaussian
        alpha_row[i] = alpha if inside & (alpha >= ALPHA_THRESHOLD) else 0.0


@nb.njit(cache=True, inline="always")
def _tile_of(job, width, height):
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = tiles_x * tiles_y
    cam = job // n_tiles
    x0 = ((job % n_tiles) % tiles_x) * TILE_SIZE
    y0 = ((job % n_tiles) // tiles_x) * TILE_SIZE
    return cam, x0, y0, min(TILE_SIZE, width - x0), min(TILE_SIZE, height - y0)


@nb.njit(cache=True, parallel=True)
def rasterize_forward(
    tile_offsets, isect_gaussians, pixel_boxes, records,
    colors,             # [C*N, D] float32
    out_colors,         # [C, H, W, D] float32
    out_transmittance,  # [C, H, W] float32
    out_counts,         # [C, H, W] int32: list entries up to and including the last one composited
):
    n_cams, height, width, n_channels = out_colors.shape
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    for job in nb.prange(n_cams * tiles_x * tiles_y):
        cam, x0, y0, tw, th = _tile_of(job, width, height)
        transmittance = np.ones((TILE_SIZE, TILE_SIZE), dtype=np.float64)
        active = np.ones((TILE_SIZE, TILE_SIZE), dtype=np.float64)  # 1 until the pixel stops
        counts = np.zeros((TILE_SIZE, TILE_SIZE), dtype=np.int64)
        accumulated = np.zeros((n_channels, TILE_SIZE, TILE_SIZE), dtype=np.float64)
        gaussian_row = np.empty(TILE_SIZE, dtype=np.float64)
        alpha_row = np.empty(TILE_SIZE, dtype=np.float64)
        weight_row = np.empty(TILE_SIZE, dtype=np.float64)
        live_in_row = np.zeros(TILE_SIZE, dtype=np.int64)  # pixels of each row still compositing
        live_in_row[:th] = tw
        n_done = 0
        start = tile_offsets[job]
        for p in range(start, tile_offsets[job + 1]):
            g = isect_gaussians[p]
            first = max(pixel_boxes[g, 0], x0) - x0
            last = min(pixel_boxes[g, 1], x0 + tw - 1) - x0
            for py in range(max(pixel_boxes[g, 2], y0), min(pixel_boxes[g, 3], y0 + th - 1) + 1):
                ly = py - y0
                dy = records[g, 1] - (py + 0.5)
                if live_in_row[ly] == 0 or records[g, 7] < dy * dy * records[g, 8]:
                    continue  # the row is finished or misses the cut-off ellipse
                _row_alphas(records, g, dy, x0, first, last, gaussian_row, alpha_row)
                stopped = 0
                composited = 0
                for i in range(TILE_SIZE):
                    alpha = alpha_row[i]
                    t_before = transmittance[ly, i]
                    t_after = t_before * (1.0 - alpha)
                    live = (alpha > 0.0) & (active[ly, i] > 0.0)
                    go = live & (t_after > TRANSMITTANCE_STOP)
                    stop = live & (t_after <= TRANSMITTANCE_STOP)
                    weight_row[i] = alpha * t_before if go else 0.0
                    transmittance[ly, i] = t_after if go else t_before
                    counts[ly, i] = p - start + 1 if go else counts[ly, i]
                    active[ly, i] = 0.0 if stop else active[ly, i]
                    stopped += 1 if stop else 0
                    composited += 1 if go else 0
                if composited > 0:
                    for k in range(n_channels):
                        color = np.float64(colors[g, k])
                        for i in range(TILE_SIZE):
                            accumulated[k, ly, i] += weight_row[i] * color
                live_in_row[ly] -= stopped
                n_done += stopped
            if n_done == tw * th:
                break
        for ly in range(th):
            for lx in range(tw):
                out_transmittance[cam, y0 + ly, x0 + lx] = transmittance[ly, lx]
                out_counts[cam, y0 + ly, x0 + lx] = counts[ly, lx]
                for k in range(n_channels):
                    out_colors[cam, y0 + ly, x0 + lx, k] = accumulated[k, ly, lx]


@nb.njit(cache=True, parallel=True)
def rasterize_backward(
    tile_offsets, isect_gaussians, pixel_boxes, records, colors,   # as in rasterize_forward
    transmittance_final,  # [C, H, W] float32 from the forward pass
    counts,               # [C, H, W] int32 from the forward pass
    grad_colors,          # [C, H, W, D] float32, dL/d(render colours without background)
    grad_transmittance,   # [C, H, W] float32, dL/d(final transmittance)
    slots,                # [M, N_GEOMETRY_SLOTS + D] float32 out: this intersection's gradient terms
):
    """Walk each tile's list back to front, rebuilding transmittance by division (as gsplat).

    Per-Gaussian sums are kept per lane (pixel column) and added across lanes in a fixed order at
    the end, which vectorises without reassociating floating-point sums.
    """
    n_cams, height, width, n_channels = grad_colors.shape
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_slots = N_GEOMETRY_SLOTS + n_channels
    for job in nb.prange(n_cams * tiles_x * tiles_y):
        cam, x0, y0, tw, th = _tile_of(job, width, height)
        start = tile_offsets[job]
        for p in range(start, tile_offsets[job + 1]):
            for k in range(n_slots):
                slots[p, k] = 0.0
        transmittance = np.ones((TILE_SIZE, TILE_SIZE), dtype=np.float64)
        final = np.ones((TILE_SIZE, TILE_SIZE), dtype=np.float64)
        grad_final = np.zeros((TILE_SIZE, TILE_SIZE), dtype=np.float64)
        tile_counts = np.zeros((TILE_SIZE, TILE_SIZE), dtype=np.int64)
        grad_out = np.zeros((n_channels, TILE_SIZE, TILE_SIZE), dtype=np.float64)
        behind = np.zeros((n_channels, TILE_SIZE, TILE_SIZE), dtype=np.float64)  # colour composited behind
        max_count = 0
        row_max_count = np.zeros(TILE_SIZE, dtype=np.int64)  # no pixel of the row composited beyond this
        for ly in range(th):
            for lx in range(tw):
                final[ly, lx] = transmittance_final[cam, y0 + ly, x0 + lx]
                transmittance[ly, lx] = final[ly, lx]
                grad_final[ly, lx] = grad_transmittance[cam, y0 + ly, x0 + lx]
                tile_counts[ly, lx] = counts[cam, y0 + ly, x0 + lx]
                max_count = max(max_count, counts[cam, y0 + ly, x0 + lx])
                row_max_count[ly] = max(row_max_count[ly], counts[cam, y0 + ly, x0 + lx])
                for k in range(n_channels):
                    grad_out[k, ly, lx] = grad_colors[cam, y0 + ly, x0 + lx, k]
        gaussian_row = np.empty(TILE_SIZE, dtype=np.float64)
        alpha_row = np.empty(TILE_SIZE, dtype=np.float64)
        t_before_row = np.empty(TILE_SIZE, dtype=np.float64)
        inv_keep_row = np.empty(TILE_SIZE, dtype=np.float64)
        weight_row = np.empty(TILE_SIZE, dtype=np.float64)
        grad_alpha_row = np.empty(TILE_SIZE, dtype=np.float64)
        lanes = np.zeros((n_slots, TILE_SIZE), dtype=np.float64)  # back to 0 after each Gaussian
        for rank in range(max_count - 1, -1, -1):
            p = start + rank
            g = isect_gaussians[p]
            mx = records[g, 0]
            ca = records[g, 2]
            cb = records[g, 3]
            cc = records[g, 4]
            opacity = records[g, 5]
            first = max(pixel_boxes[g, 0], x0) - x0
            last = min(pixel_boxes[g, 1], x0 + tw - 1) - x0
            touched = 0
            for py in range(max(pixel_boxes[g, 2], y0), min(pixel_boxes[g, 3], y0 + th - 1) + 1):
                ly = py - y0
                dy = records[g, 1] - (py + 0.5)
                if rank >= row_max_count[ly] or records[g, 7] < dy * dy * records[g, 8]:
                    continue
                _row_alphas(records, g, dy, x0, first, last, gaussian_row, alpha_row)
                valid_lanes = 0
                for i in range(TILE_SIZE):
                    alpha = alpha_row[i]
                    valid = (alpha > 0.0) & (rank < tile_counts[ly, i])
                    inv_keep = 1.0 / (1.0 - alpha)
                    t_before = transmittance[ly, i] * inv_keep
                    transmittance[ly, i] = t_before if valid else transmittance[ly, i]
                    t_before_row[i] = t_before
                    inv_keep_row[i] = inv_keep
                    weight_row[i] = alpha * t_before if valid else 0.0
                    grad_alpha_row[i] = -final[ly, i] * inv_keep * grad_final[ly, i] if valid else 0.0
                    valid_lanes += 1 if valid else 0
                if valid_lanes == 0:
                    continue
                touched += valid_lanes
                for k in range(n_channels):
                    color = np.float64(colors[g, k])
                    for i in range(TILE_SIZE):
                        g_out = grad_out[k, ly, i]
                        weight = weight_row[i]
                        lanes[N_GEOMETRY_SLOTS + k, i] += weight * g_out
                        term = (color * t_before_row[i] - behind[k, ly, i] * inv_keep_row[i]) * g_out
                        grad_alpha_row[i] += term if weight > 0.0 else 0.0
                        behind[k, ly, i] += color * weight
                for i in range(TILE_SIZE):
                    dx = mx - (x0 + i + 0.5)
                    raw_alpha = opacity * gaussian_row[i]
                    unclamped = (weight_row[i] > 0.0) & (raw_alpha <= MAX_ALPHA)
                    grad_alpha = grad_alpha_row[i] if unclamped else 0.0
                    grad_sigma = -raw_alpha * grad_alpha
                    gx = grad_sigma * (ca * dx + cb * dy)
                    gy = grad_sigma * (cb * dx + cc * dy)
                    lanes[0, i] += gx
                    lanes[1, i] += gy
                    lanes[2, i] += 0.5 * grad_sigma * dx * dx
                    lanes[3, i] += grad_sigma * dx * dy
                    lanes[4, i] += 0.5 * grad_sigma * dy * dy
                    lanes[5, i] += gaussian_row[i] * grad_alpha
                    lanes[6, i] += abs(gx)
                    lanes[7, i] += abs(gy)
            if touched == 0:
                continue  # lanes were only ever incremented by zero
            for k in range(n_slots):
                total = 0.0
                for i in range(first, last + 1):
                    total += lanes[k, i]
                    lanes[k, i] = 0.0
                slots[p, k] = total


@nb.njit(cache=True, parallel=True)
def reduce_slots(
    gaussian_offsets,  # [C*N + 1]
    gaussian_isects,   # [M]
    slots,             # [M, S] float32
    out,               # [C*N, S] float64: per-Gaussian sums, in tile order
):
    n_slots = slots.shape[1]
    for g in nb.prange(out.shape[0]):
        for k in range(n_slots):
            out[g, k] = 0.0
        for i in range(gaussian_offsets[g], gaussian_offsets[g + 1]):
            row = gaussian_isects[i]
            for k in range(n_slots):
                out[g, k] += slots[row, k]
