"""Numba kernels of the CPU backend: tile binning, front-to-back forward, back-to-front backward, reduction.

Binning and packing compute in float64 (scalar code, where it is free). The pixel loops of the forward
and backward passes compute in the type of the arrays they are given (``records``): float32 for float32
inputs, where a 512-bit vector holds 16 lanes, a whole tile row, against 8 float64 ones, which halves
their instructions and the tile buffers' traffic (measured: ``omniscs bench render``); float64 for
float64 inputs, which stay as close to the float64 reference as they can. Every parallel loop writes disjoint memory, and
per-Gaussian gradients are summed in a fixed order, so results are bitwise reproducible.
A pixel is skipped, in forward and backward alike, by the same tests in the same order.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from omniscs.render.constants import ALPHA_THRESHOLD, MAX_ALPHA, TILE_SIZE, TRANSMITTANCE_STOP

#: Slack on the per-Gaussian cut-off of the Mahalanobis half-distance sigma beyond which alpha is
#: below ALPHA_THRESHOLD anyway; only saves exp() calls, never removes a visible pixel.
SIGMA_CUT_SLACK = 1e-5

#: Extra slack (in sigma) of the test that skips tile rows missing the cut-off ellipse entirely, so
#: rounding never skips a row holding a pixel that passes the per-pixel sigma test.
ROW_SPAN_SLACK = 1e-4

#: Margin (in pixels) of the test that skips a tile row whose chord of the cut-off ellipse lies left or
#: right of the Gaussian's columns in the tile; far above the float32 rounding of the pixel loops' sigma.
ROW_CHORD_SLACK = 1e-2

#: Columns of a packed Gaussian record (float32, one 64-byte cache line): centre x, y; conic a, b, c;
#: opacity; sigma cut-off; for the row tests 2 a (cut-off + ROW_SPAN_SLACK), a c - b^2, 1 / a and b / a;
#: the inclusive pixel box x_lo, x_hi, y_lo, y_hi (integers, exact in float32); 1 unused.
N_RECORD = 16
REC_X, REC_Y, REC_A, REC_B, REC_C, REC_OPACITY, REC_CUT, REC_ROW_SCALE, REC_CONIC_DET = range(9)
REC_X_LO, REC_X_HI, REC_Y_LO, REC_Y_HI = range(9, 13)
REC_INV_A, REC_B_OVER_A = 13, 14

#: exp(-sigma) is evaluated as (Taylor polynomial at sigma / 2^EXP_SQUARINGS)^(2^EXP_SQUARINGS): plain
#: arithmetic that vectorises (libm exp does not), relative error < 1e-7 for sigma up to ln(255).
EXP_SQUARINGS = 6

#: Colour channels composited inside the transmittance loop (the rest, if any, in a second pass):
#: enough for RGB, RGB+depth and depth alone.
FUSED_CHANNELS = 4

#: Gradient slots per intersection before the colour channels: means2d (2), conic (3), opacity (1), |means2d| (2).
N_GEOMETRY_SLOTS = 8


#: Constants of the pixel loops, as float32 so that they keep float32 rows in float32 (a float64 literal or
#: an int in an expression would promote the whole row to float64: Numba follows NumPy's promotion rules);
#: in float64 rows they promote to float64 (the values are exact or within 1e-8 of the float64 ones).
REAL = np.float32
_ZERO, _HALF, _ONE = REAL(0.0), REAL(0.5), REAL(1.0)
_MAX_ALPHA, _ALPHA_THRESHOLD, _TRANSMITTANCE_STOP = REAL(MAX_ALPHA), REAL(ALPHA_THRESHOLD), REAL(TRANSMITTANCE_STOP)
_EXP_SCALE = REAL(1.0 / (1 << EXP_SQUARINGS))
_TAYLOR = (REAL(1.0 / 2.0), REAL(1.0 / 6.0), REAL(1.0 / 24.0), REAL(1.0 / 120.0))

#: List entries ahead whose records and colours the pixel loops ask the CPU to fetch (a tile's list visits
#: records scattered over the packed array: without it a fifth of the forward kernel's time was spent
#: waiting for the first read of each record, measured by sampling).
PREFETCH_AHEAD = 4

#: Tile-list entries between two refreshes of the forward pass's per-row liveness.
LIVENESS_CHECK = 32

#: Bits per pass of the radix sort of depth keys (2^11 buckets fit in L1).
RADIX_BITS = 11


@intrinsic
def _prefetch_row(typingctx, array, row):
    """Ask the CPU to bring the cache line of array[row, 0] closer (LLVM's prefetch hint; no effect on results)."""
    def codegen(context, builder, signature, args):
        array_type, row_type = signature.args
        data = context.make_array(array_type)(context, builder, args[0])
        index = context.cast(builder, args[1], row_type, types.intp)
        pointer = cgutils.get_item_pointer(context, builder, array_type, data, [index, context.get_constant(types.intp, 0)])
        i32 = ir.IntType(32)
        prefetch = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [pointer.type, i32, i32, i32]), "llvm.prefetch.p0")
        # read, keep in all cache levels, data cache
        builder.call(prefetch, [pointer, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()
    return types.void(array, row), codegen


@nb.njit(cache=True)
def depth_order(
    depth_bits,  # [C, N] uint64: IEEE bits of the depths (order-preserving for positive depths)
    radii,       # [C, N, 2] int32, 0 where culled
):  # -> order [C, N] int64 (visible first, front to back, ties by index), n_visible [C] int64
    """Stable LSD radix sort of each camera's visible Gaussians by depth (ties keep index order).

    Keys travel with their indices (each pass reads memory in order), and one pass over the keys
    counts the digits of every pass, so a pass whose digit is the same for all keys is skipped.
    """
    n_cams, n_gauss = depth_bits.shape
    order = np.empty((n_cams, n_gauss), dtype=np.int64)
    n_visible = np.zeros(n_cams, dtype=np.int64)
    n_buckets = 1 << RADIX_BITS
    n_passes = (64 + RADIX_BITS - 1) // RADIX_BITS
    for cam in range(n_cams):
        n = 0
        for g in range(n_gauss):
            n += 1 if radii[cam, g, 0] > 0 else 0
        ids, keys = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.uint64)
        i, culled = 0, n
        for g in range(n_gauss):
            if radii[cam, g, 0] > 0:
                ids[i] = g
                keys[i] = depth_bits[cam, g]
                i += 1
            else:
                order[cam, culled] = g
                culled += 1
        counts = np.zeros((n_passes, n_buckets), dtype=np.int64)
        for i in range(n):
            for k in range(n_passes):
                counts[k, (keys[i] >> (k * RADIX_BITS)) & (n_buckets - 1)] += 1
        ids_out, keys_out = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.uint64)
        starts = np.empty(n_buckets, dtype=np.int64)
        for k in range(n_passes):
            if counts[k].max() == n:
                continue  # every key has the same digit here: the pass would not move anything
            total = 0
            for b in range(n_buckets):
                starts[b] = total
                total += counts[k, b]
            for i in range(n):
                digit = (keys[i] >> (k * RADIX_BITS)) & (n_buckets - 1)
                keys_out[starts[digit]] = keys[i]
                ids_out[starts[digit]] = ids[i]
                starts[digit] += 1
            ids, ids_out = ids_out, ids
            keys, keys_out = keys_out, keys
        order[cam, :n] = ids
        n_visible[cam] = n
    return order, n_visible


@nb.njit(cache=True, parallel=True)
def _pixel_boxes(means2d, conics, radii, width, height, tile):
    """Inclusive pixel box (x_lo, x_hi, y_lo, y_hi) of every Gaussian and how many tiles it touches.

    0 tiles for culled Gaussians, boxes holding no pixel centre, and screen parameters that are not
    finite or whose conic is not positive definite (possible after rounding to float32).
    """
    n = means2d.shape[0]
    # np.empty, and zeros written by the loop: a top-level np.zeros in a parallel function is a parallel region
    # of its own, and each region costs a wake-up of the threads
    boxes = np.empty((n, 4), dtype=np.int32)
    n_tiles = np.empty(n, dtype=np.int64)
    for g in nb.prange(n):
        boxes[g, 0] = boxes[g, 1] = boxes[g, 2] = boxes[g, 3] = 0
        n_tiles[g] = 0
        mx = np.float64(means2d[g, 0])
        my = np.float64(means2d[g, 1])
        ca = np.float64(conics[g, 0])
        cb = np.float64(conics[g, 1])
        cc = np.float64(conics[g, 2])
        finite = math.isfinite(mx) and math.isfinite(my) and math.isfinite(ca) and math.isfinite(cb) and math.isfinite(cc)
        if radii[g, 0] <= 0 or radii[g, 1] <= 0 or not finite or not (ca > 0.0 and ca * cc - cb * cb > 0.0):
            continue
        # pixel px is inside when |px + 0.5 - mx| <= rx; clip in float before converting to int
        x_lo = max(0.0, math.ceil(min(mx - radii[g, 0] - 0.5, width)))
        x_hi = min(width - 1.0, math.floor(max(mx + radii[g, 0] - 0.5, -1.0)))
        y_lo = max(0.0, math.ceil(min(my - radii[g, 1] - 0.5, height)))
        y_hi = min(height - 1.0, math.floor(max(my + radii[g, 1] - 0.5, -1.0)))
        if x_lo > x_hi or y_lo > y_hi:
            continue
        boxes[g, 0] = np.int32(x_lo)
        boxes[g, 1] = np.int32(x_hi)
        boxes[g, 2] = np.int32(y_lo)
        boxes[g, 3] = np.int32(y_hi)
        n_tiles[g] = (boxes[g, 1] // tile - boxes[g, 0] // tile + 1) * (boxes[g, 3] // tile - boxes[g, 2] // tile + 1)
    return boxes, n_tiles


@nb.njit(cache=True, parallel=True)
def _pack(packed_ids, means2d, conics, opacities, colors, boxes):
    """Rows of the drawn Gaussians in packed order: records (all the pixel loops read) and colours."""
    n = packed_ids.shape[0]
    records = np.empty((n, N_RECORD), dtype=means2d.dtype)
    packed_colors = np.empty((n, colors.shape[1]), dtype=colors.dtype)
    for s in nb.prange(n):
        g = packed_ids[s]
        records[s, N_RECORD - 1] = 0.0  # the unused column
        ca = np.float64(conics[g, 0])
        cb = np.float64(conics[g, 1])
        cc = np.float64(conics[g, 2])
        opacity = np.float64(opacities[g])
        cut = math.log(max(opacity, ALPHA_THRESHOLD) / ALPHA_THRESHOLD) + SIGMA_CUT_SLACK
        records[s, REC_X] = means2d[g, 0]
        records[s, REC_Y] = means2d[g, 1]
        records[s, REC_A] = ca
        records[s, REC_B] = cb
        records[s, REC_C] = cc
        records[s, REC_OPACITY] = opacity
        records[s, REC_CUT] = cut
        records[s, REC_ROW_SCALE] = 2.0 * ca * (cut + ROW_SPAN_SLACK)
        records[s, REC_CONIC_DET] = ca * cc - cb * cb
        records[s, REC_INV_A] = 1.0 / ca
        records[s, REC_B_OVER_A] = cb / ca
        records[s, REC_X_LO] = boxes[g, 0]
        records[s, REC_X_HI] = boxes[g, 1]
        records[s, REC_Y_LO] = boxes[g, 2]
        records[s, REC_Y_HI] = boxes[g, 3]
        for k in range(colors.shape[1]):
            packed_colors[s, k] = colors[g, k]
    return records, packed_colors


@nb.njit(cache=True)
def _balanced_runs(offsets, parts):
    """Bounds of ``parts`` contiguous runs of items 0 .. n-1 with about as many intersections each
    (offsets [n + 1] are the items' prefix sums); run r is bounds[r] .. bounds[r + 1] - 1."""
    n = offsets.shape[0] - 1
    bounds = np.searchsorted(offsets[:n], (np.arange(parts + 1) * offsets[n]) // parts)
    bounds[parts] = n
    return bounds


@nb.njit(cache=True, inline="always")
def _tile_box(records, s):
    """Inclusive tile columns and rows (tx_lo, tx_hi, ty_lo, ty_hi) of packed Gaussian s's pixel box."""
    return (int(records[s, REC_X_LO]) // TILE_SIZE, int(records[s, REC_X_HI]) // TILE_SIZE,
            int(records[s, REC_Y_LO]) // TILE_SIZE, int(records[s, REC_Y_HI]) // TILE_SIZE)


@nb.njit(cache=True, parallel=True)
def _tile_lists(packed_ids, records, n_gauss, n_cams, tiles_x, n_tiles, parts):
    """Per tile (n_tiles a camera), the packed Gaussians whose pixel box touches it, in packed order (a counting sort).

    The packed Gaussians are cut into ``parts`` runs of about as many Gaussians each; every run counts and
    scatters its own (in parallel), and a tile's slots are laid out run by run, so each tile's list is
    increasing exactly as a serial scatter makes it.
    """
    n_packed = packed_ids.shape[0]
    packed_offsets = np.empty(n_packed + 1, dtype=np.int64)
    packed_offsets[0] = 0
    # one pass over the records counts each Gaussian's tiles and each run's Gaussians per tile (runs of equal
    # Gaussian counts: their intersection counts are not known yet); 2.44 -> 1.99 ms at 640x360 with 100k
    # Gaussians on 2 threads against a first pass for the Gaussians' counts and runs of equal intersection counts
    run_bounds = np.empty(parts + 1, dtype=np.int64)
    for run in range(parts + 1):
        run_bounds[run] = (n_packed * run) // parts
    run_counts = np.empty((parts, n_cams * n_tiles), dtype=np.int64)
    for run in nb.prange(parts):
        run_counts[run] = 0
        for s in range(run_bounds[run], run_bounds[run + 1]):
            base = (packed_ids[s] // n_gauss) * n_tiles
            tx_lo, tx_hi, ty_lo, ty_hi = _tile_box(records, s)
            packed_offsets[s + 1] = (tx_hi - tx_lo + 1) * (ty_hi - ty_lo + 1)
            for ty in range(ty_lo, ty_hi + 1):
                for tx in range(tx_lo, tx_hi + 1):
                    run_counts[run, base + ty * tiles_x + tx] += 1
    for s in range(n_packed):
        packed_offsets[s + 1] += packed_offsets[s]
    n_isects = packed_offsets[n_packed]
    tile_offsets = np.empty(n_cams * n_tiles + 1, dtype=np.int64)
    cursors = np.empty((parts, n_cams * n_tiles), dtype=np.int64)
    k = 0
    for t in range(n_cams * n_tiles):
        tile_offsets[t] = k
        for run in range(parts):
            cursors[run, t] = k
            k += run_counts[run, t]
    tile_offsets[n_cams * n_tiles] = k
    isect_packed = np.empty(n_isects, dtype=np.int32)
    packed_isects = np.empty(n_isects, dtype=np.int64)
    for run in nb.prange(parts):
        for s in range(run_bounds[run], run_bounds[run + 1]):
            base = (packed_ids[s] // n_gauss) * n_tiles
            k = packed_offsets[s]
            tx_lo, tx_hi, ty_lo, ty_hi = _tile_box(records, s)
            for ty in range(ty_lo, ty_hi + 1):
                for tx in range(tx_lo, tx_hi + 1):
                    t = base + ty * tiles_x + tx
                    isect_packed[cursors[run, t]] = s
                    packed_isects[k] = cursors[run, t]
                    cursors[run, t] += 1
                    k += 1
    return tile_offsets, isect_packed, packed_offsets, packed_isects


@nb.njit(cache=True)
def bin_gaussians(
    means2d,       # [C*N, 2] float32
    conics,        # [C*N, 3] float32
    opacities,     # [C*N] float32
    colors,        # [C*N, D] float32
    radii,         # [C*N, 2] int32, 0 where culled
    depth_order,   # [C, N] int64 per-camera indices sorted by depth (stable), visible ones first
    n_visible,     # [C] int64
    width, height,
    parts,         # independent blocks of the tile-list scatter: the thread count
):
    """Pack the drawn Gaussians front to back and list, per tile, the ones whose pixel box touches it.

    Packing renumbers Gaussians camera by camera in depth order, so every tile's list is increasing
    and the pixel loops walk memory forwards. Returns
    tile_offsets [C*T + 1] and isect_packed [M] (packed index per intersection, each tile's run front to back);
    packed_ids [V] (flat c*N + g of each packed Gaussian), packed_records [V, N_RECORD], packed_colors [V, D];
    packed_offsets [V + 1] and packed_isects [M] (each packed Gaussian's intersections, in tile order).
    """
    n_cams, n_gauss = depth_order.shape
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = tiles_x * tiles_y
    boxes, tiles_touched = _pixel_boxes(means2d, conics, radii, width, height, TILE_SIZE)

    n_packed = 0
    for cam in range(n_cams):
        for rank in range(n_visible[cam]):
            n_packed += 1 if tiles_touched[cam * n_gauss + depth_order[cam, rank]] > 0 else 0
    packed_ids = np.empty(n_packed, dtype=np.int64)
    s = 0
    for cam in range(n_cams):
        for rank in range(n_visible[cam]):
            g = cam * n_gauss + depth_order[cam, rank]
            if tiles_touched[g] > 0:
                packed_ids[s] = g
                s += 1
    records, packed_colors = _pack(packed_ids, means2d, conics, opacities, colors, boxes)
    tile_offsets, isect_packed, packed_offsets, packed_isects = _tile_lists(
        packed_ids, records, n_gauss, n_cams, tiles_x, n_tiles, parts)
    return tile_offsets, isect_packed, packed_ids, records, packed_colors, packed_offsets, packed_isects


@nb.njit(cache=True, inline="always")
def _exp_neg(sigma):
    """exp(-sigma) for 0 <= sigma <= ~6 by scaled Taylor series and repeated squaring."""
    t = sigma * _EXP_SCALE
    p = _ONE - t * (_ONE - t * (_TAYLOR[0] - t * (_TAYLOR[1] - t * (_TAYLOR[2] - t * _TAYLOR[3]))))
    # EXP_SQUARINGS squarings, written out: a loop here would stop LLVM vectorising the caller
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    return p


@nb.njit(cache=True, inline="always")
def _lane_alpha(mx, ca, cb_dy, cc_dy2, opacity, cut, left, i, first, last):
    """exp(-sigma) and alpha of a Gaussian at lane i (tile-relative column) of one tile row (alpha 0 = skipped).

    Lanes first..last are the Gaussian's pixel box. Branch-free, so that LLVM vectorises the 16-lane
    loops that call it; forward and backward both call it, so they take identical decisions.
    """
    dx = mx - (left + REAL(i))
    sigma = _HALF * (ca * dx * dx + cc_dy2) + cb_dy * dx
    inside = (i >= first) & (i <= last) & (sigma >= _ZERO) & (sigma <= cut)
    gaussian = _exp_neg(min(max(sigma, _ZERO), cut))
    alpha = min(_MAX_ALPHA, opacity * gaussian)
    return gaussian, (alpha if inside & (alpha >= _ALPHA_THRESHOLD) else _ZERO)


@nb.njit(cache=True, inline="always")
def _sum_lanes(row):
    """Sum of a row's TILE_SIZE lanes in float64, in a fixed pairwise order."""
    s0 = (np.float64(row[0]) + np.float64(row[8])) + (np.float64(row[4]) + np.float64(row[12]))
    s1 = (np.float64(row[2]) + np.float64(row[10])) + (np.float64(row[6]) + np.float64(row[14]))
    s2 = (np.float64(row[1]) + np.float64(row[9])) + (np.float64(row[5]) + np.float64(row[13]))
    s3 = (np.float64(row[3]) + np.float64(row[11])) + (np.float64(row[7]) + np.float64(row[15]))
    return (s0 + s1) + (s2 + s3)


@nb.njit(cache=True)
def spread_order(n, parts):
    """0 .. n-1 dealt into ``parts`` contiguous blocks: block t holds t, t + parts, t + 2 parts, ...

    Numba's OpenMP layer splits a parallel loop into one contiguous block of iterations per thread
    (parallel_chunksize does not change that: measured), so a loop over tiles in image order gives
    one thread the sky and the other the street. Looping over this order with parts = the thread
    count, each thread gets every parts-th tile of the whole image, still in image order (a
    bit-reversed order balances as well but cost 8 % on one thread: tiles next to each other share
    their Gaussians' records in cache).
    """
    order = np.empty(n, dtype=np.int64)
    k = 0
    for t in range(parts):
        for j in range(t, n, parts):
            order[k] = j
            k += 1
    return order


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
    tile_offsets, isect_gaussians, records,  # from bin_gaussians: tile_offsets, isect_packed, packed_records
    colors,             # [V, D] float32 packed colours
    backgrounds,        # [C, D] float32, seen through the final transmittance
    out_colors,         # [C, H, W, D] float32
    out_alphas,         # [C, H, W, 1] float32: 1 - final transmittance
    out_transmittance,  # [C, H, W] float32: final transmittance (kept for the backward pass)
    out_counts,         # [C, H, W] int32: list entries up to and including the last one composited
    out_row_masks,      # [M] int32: per intersection, bit ly set where it composited a pixel of tile row ly
    tile_order,         # [C*T] int64: the order the parallel loop takes the tiles in (spread_order)
):
    """Composite each tile's list front to back.

    A pixel stops when its transmittance would fall to TRANSMITTANCE_STOP; the tile buffer then holds
    its transmittance negated (one buffer for both). Which rows still have a live pixel, and whether
    any has, is refreshed every LIVENESS_CHECK entries rather than counted per row (a per-row count
    is a horizontal sum that costs more than the rows it skips).
    """
    n_cams, height, width, n_channels = out_colors.shape
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    for j in nb.prange(n_cams * tiles_x * tiles_y):
        job = tile_order[j]
        cam, x0, y0, tw, th = _tile_of(job, width, height)
        # plane 0: transmittance; plane 1 + k: colour channel k composited so far (one array: fewer
        # arrays in a loop, fewer runtime alias checks between them, measured about 5 % faster)
        planes = np.zeros((1 + max(n_channels, FUSED_CHANNELS), TILE_SIZE, TILE_SIZE), dtype=records.dtype)
        for ly in range(TILE_SIZE):
            for lx in range(TILE_SIZE):
                planes[0, ly, lx] = _ONE if ly < th and lx < tw else -_ONE  # outside the image: never composited
        counts = np.zeros((TILE_SIZE, TILE_SIZE), dtype=np.int32)
        weight_row = np.empty(TILE_SIZE, dtype=records.dtype)
        row_live = np.zeros(TILE_SIZE, dtype=np.bool_)
        row_live[:th] = True
        left = REAL(x0) + _HALF
        start = tile_offsets[job]
        end = tile_offsets[job + 1]
        for p in range(start, end):
            out_row_masks[p] = 0
        for p in range(start, end):
            if (p - start) % LIVENESS_CHECK == LIVENESS_CHECK - 1:
                any_live = False
                for ly in range(th):
                    live = 0
                    for i in range(TILE_SIZE):
                        live += 1 if planes[0, ly, i] > _ZERO else 0
                    row_live[ly] = live > 0
                    any_live |= live > 0
                if not any_live:
                    break
            if p + PREFETCH_AHEAD < end:
                _prefetch_row(records, isect_gaussians[p + PREFETCH_AHEAD])
                _prefetch_row(colors, isect_gaussians[p + PREFETCH_AHEAD])
            g = isect_gaussians[p]
            first = max(int(records[g, REC_X_LO]), x0) - x0
            last = min(int(records[g, REC_X_HI]), x0 + tw - 1) - x0
            mx, ca, cb, cc = records[g, REC_X], records[g, REC_A], records[g, REC_B], records[g, REC_C]
            opacity, cut = records[g, REC_OPACITY], records[g, REC_CUT]
            row_scale, conic_det = records[g, REC_ROW_SCALE], records[g, REC_CONIC_DET]
            # the chord test in float64 (scalar, once per row): pixel centres left + i for i in first..last
            inv_a, b_over_a = np.float64(records[g, REC_INV_A]), np.float64(records[g, REC_B_OVER_A])
            chord_lo = np.float64(left) + first - ROW_CHORD_SLACK - np.float64(mx)
            chord_hi = np.float64(left) + last + ROW_CHORD_SLACK - np.float64(mx)
            c0 = colors[g, 0] if n_channels > 0 else _ZERO
            c1 = colors[g, 1] if n_channels > 1 else _ZERO
            c2 = colors[g, 2] if n_channels > 2 else _ZERO
            c3 = colors[g, 3] if n_channels > 3 else _ZERO
            row_mask = 0
            for py in range(max(int(records[g, REC_Y_LO]), y0), min(int(records[g, REC_Y_HI]), y0 + th - 1) + 1):
                ly = py - y0
                dy = records[g, REC_Y] - (REAL(py) + _HALF)
                if not row_live[ly] or row_scale < dy * dy * conic_det:
                    continue  # the row is finished or misses the cut-off ellipse
                # sigma <= cut on this row where |px - mx - (b / a) dy| <= sqrt(2 a cut - dy^2 (a c - b^2)) / a
                dy64 = np.float64(dy)
                chord_centre = b_over_a * dy64
                chord_half = math.sqrt(max(np.float64(row_scale) - dy64 * dy64 * np.float64(conic_det), 0.0)) * inv_a
                if chord_centre + chord_half < chord_lo or chord_centre - chord_half > chord_hi:
                    continue  # the chord lies beside the Gaussian's pixels in this tile row
                cb_dy = cb * dy
                cc_dy2 = cc * dy * dy
                any_go = False
                for i in range(TILE_SIZE):
                    _, alpha = _lane_alpha(mx, ca, cb_dy, cc_dy2, opacity, cut, left, i, first, last)
                    t_before = planes[0, ly, i]
                    t_after = t_before * (_ONE - alpha)
                    live = (alpha > _ZERO) & (t_before > _ZERO)
                    go = live & (t_after > _TRANSMITTANCE_STOP)
                    stop = live & (t_after <= _TRANSMITTANCE_STOP)
                    weight = alpha * t_before if go else _ZERO
                    weight_row[i] = weight
                    planes[1, ly, i] += weight * c0
                    planes[2, ly, i] += weight * c1
                    planes[3, ly, i] += weight * c2
                    planes[4, ly, i] += weight * c3
                    planes[0, ly, i] = t_after if go else (-t_before if stop else t_before)
                    counts[ly, i] = np.int32(p - start + 1) if go else counts[ly, i]
                    any_go |= go
                if not any_go:
                    continue
                row_mask |= 1 << ly
                for k in range(FUSED_CHANNELS, n_channels):
                    color = colors[g, k]
                    if color == _ZERO:
                        continue  # adds exactly nothing (weights are finite): sparse channels such as labels
                    for i in range(TILE_SIZE):
                        planes[1 + k, ly, i] += weight_row[i] * color
            out_row_masks[p] = row_mask
        for ly in range(th):
            for lx in range(tw):
                t_final = abs(planes[0, ly, lx])
                out_transmittance[cam, y0 + ly, x0 + lx] = t_final
                out_alphas[cam, y0 + ly, x0 + lx, 0] = _ONE - t_final
                out_counts[cam, y0 + ly, x0 + lx] = counts[ly, lx]
                for k in range(n_channels):
                    out_colors[cam, y0 + ly, x0 + lx, k] = planes[1 + k, ly, lx] + t_final * backgrounds[cam, k]


#: Planes of the backward pass's tile state (one array: fewer arrays in a loop, fewer runtime alias
#: checks between them): running transmittance, final transmittance, dL/d(final transmittance), the
#: first FUSED_CHANNELS colour gradients, and the colour composited behind, per fused channel.
_P_T, _P_FINAL, _P_GRAD_FINAL, _P_GRAD_OUT, _P_BEHIND = 0, 1, 2, 3, 3 + FUSED_CHANNELS
_N_PLANES = 3 + 2 * FUSED_CHANNELS

#: Rows of the backward pass's per-row scratch: exp(-sigma), transmittance before, 1 / (1 - alpha), weight, dL/dalpha.
_R_GAUSSIAN, _R_T_BEFORE, _R_INV_KEEP, _R_WEIGHT, _R_GRAD_ALPHA = range(5)


@nb.njit(cache=True, parallel=True)
def rasterize_backward(
    tile_offsets, isect_gaussians, records, colors, backgrounds,  # as in rasterize_forward
    transmittance_final,  # [C, H, W] float32 from the forward pass
    counts,               # [C, H, W] int32 from the forward pass
    row_masks,            # [M] int32 from the forward pass
    grad_colors,          # [C, H, W, D] float32, dL/d(rendered colours)
    grad_alphas,          # [C, H, W, 1] float32, dL/d(rendered alphas)
    slots,                # [M, N_GEOMETRY_SLOTS + D] float32 out: this intersection's gradient terms
    tile_order,           # as in rasterize_forward
):
    """Walk each tile's list back to front, rebuilding transmittance by division (as gsplat).

    Only the rows where the forward pass composited a pixel are visited (``row_masks``): a pixel
    gets a gradient from exactly the Gaussians that were composited there. Per-Gaussian sums are
    kept per lane (pixel column) and added across lanes in a fixed order at the end, which
    vectorises without reassociating floating-point sums.
    """
    n_cams, height, width, n_channels = grad_colors.shape
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_slots = N_GEOMETRY_SLOTS + n_channels
    n_extra = max(n_channels - FUSED_CHANNELS, 0)
    for j in nb.prange(n_cams * tiles_x * tiles_y):
        job = tile_order[j]
        cam, x0, y0, tw, th = _tile_of(job, width, height)
        start = tile_offsets[job]
        state = np.zeros((_N_PLANES, TILE_SIZE, TILE_SIZE), dtype=records.dtype)
        state[_P_T] = _ONE
        state[_P_FINAL] = _ONE
        tile_counts = np.zeros((TILE_SIZE, TILE_SIZE), dtype=np.int32)
        extra_grad_out = np.zeros((n_extra, TILE_SIZE, TILE_SIZE), dtype=records.dtype)
        extra_behind = np.zeros((n_extra, TILE_SIZE, TILE_SIZE), dtype=records.dtype)
        max_count = 0
        for ly in range(th):
            for lx in range(tw):
                t_final = transmittance_final[cam, y0 + ly, x0 + lx]
                state[_P_FINAL, ly, lx] = t_final
                state[_P_T, ly, lx] = t_final
                # colour = composited + T_final * background and alpha = 1 - T_final
                grad_t = -grad_alphas[cam, y0 + ly, x0 + lx, 0]
                for k in range(n_channels):
                    grad_t += backgrounds[cam, k] * grad_colors[cam, y0 + ly, x0 + lx, k]
                state[_P_GRAD_FINAL, ly, lx] = grad_t
                tile_counts[ly, lx] = counts[cam, y0 + ly, x0 + lx]
                max_count = max(max_count, counts[cam, y0 + ly, x0 + lx])
                for k in range(min(n_channels, FUSED_CHANNELS)):
                    state[_P_GRAD_OUT + k, ly, lx] = grad_colors[cam, y0 + ly, x0 + lx, k]
                for k in range(n_extra):
                    extra_grad_out[k, ly, lx] = grad_colors[cam, y0 + ly, x0 + lx, FUSED_CHANNELS + k]
        rows = np.empty((5, TILE_SIZE), dtype=records.dtype)
        lanes = np.zeros((N_GEOMETRY_SLOTS + max(n_channels, FUSED_CHANNELS), TILE_SIZE), dtype=records.dtype)
        left = REAL(x0) + _HALF
        for p in range(start + max_count, tile_offsets[job + 1]):
            slots[p, :] = 0.0  # beyond every pixel's last composited entry
        for rank in range(max_count - 1, -1, -1):
            p = start + rank
            row_mask = row_masks[p]
            if row_mask == 0:
                slots[p, :] = 0.0  # composited no pixel of this tile
                continue
            if rank >= PREFETCH_AHEAD:
                _prefetch_row(records, isect_gaussians[p - PREFETCH_AHEAD])
                _prefetch_row(colors, isect_gaussians[p - PREFETCH_AHEAD])
            g = isect_gaussians[p]
            mx, ca, cb, cc = records[g, REC_X], records[g, REC_A], records[g, REC_B], records[g, REC_C]
            opacity, cut = records[g, REC_OPACITY], records[g, REC_CUT]
            first = max(int(records[g, REC_X_LO]), x0) - x0
            last = min(int(records[g, REC_X_HI]), x0 + tw - 1) - x0
            c0 = colors[g, 0] if n_channels > 0 else _ZERO
            c1 = colors[g, 1] if n_channels > 1 else _ZERO
            c2 = colors[g, 2] if n_channels > 2 else _ZERO
            c3 = colors[g, 3] if n_channels > 3 else _ZERO
            for ly in range(th):
                if (row_mask >> ly) & 1 == 0:
                    continue
                dy = records[g, REC_Y] - (REAL(y0 + ly) + _HALF)
                cb_dy = cb * dy
                cc_dy2 = cc * dy * dy
                for i in range(TILE_SIZE):
                    gaussian, alpha = _lane_alpha(mx, ca, cb_dy, cc_dy2, opacity, cut, left, i, first, last)
                    valid = (alpha > _ZERO) & (rank < tile_counts[ly, i])
                    inv_keep = _ONE / (_ONE - alpha)
                    t_before = state[_P_T, ly, i] * inv_keep
                    state[_P_T, ly, i] = t_before if valid else state[_P_T, ly, i]
                    weight = alpha * t_before if valid else _ZERO
                    # the first FUSED_CHANNELS colour channels, written out so the loop stays vectorised
                    g0, g1 = state[_P_GRAD_OUT, ly, i], state[_P_GRAD_OUT + 1, ly, i]
                    g2, g3 = state[_P_GRAD_OUT + 2, ly, i], state[_P_GRAD_OUT + 3, ly, i]
                    lanes[N_GEOMETRY_SLOTS, i] += weight * g0
                    lanes[N_GEOMETRY_SLOTS + 1, i] += weight * g1
                    lanes[N_GEOMETRY_SLOTS + 2, i] += weight * g2
                    lanes[N_GEOMETRY_SLOTS + 3, i] += weight * g3
                    grad_alpha = -state[_P_FINAL, ly, i] * inv_keep * state[_P_GRAD_FINAL, ly, i]
                    grad_alpha += (c0 * t_before - state[_P_BEHIND, ly, i] * inv_keep) * g0
                    grad_alpha += (c1 * t_before - state[_P_BEHIND + 1, ly, i] * inv_keep) * g1
                    grad_alpha += (c2 * t_before - state[_P_BEHIND + 2, ly, i] * inv_keep) * g2
                    grad_alpha += (c3 * t_before - state[_P_BEHIND + 3, ly, i] * inv_keep) * g3
                    state[_P_BEHIND, ly, i] += c0 * weight
                    state[_P_BEHIND + 1, ly, i] += c1 * weight
                    state[_P_BEHIND + 2, ly, i] += c2 * weight
                    state[_P_BEHIND + 3, ly, i] += c3 * weight
                    rows[_R_GAUSSIAN, i] = gaussian
                    rows[_R_T_BEFORE, i] = t_before
                    rows[_R_INV_KEEP, i] = inv_keep
                    rows[_R_WEIGHT, i] = weight
                    rows[_R_GRAD_ALPHA, i] = grad_alpha if valid else _ZERO
                for k in range(n_extra):
                    color = colors[g, FUSED_CHANNELS + k]
                    for i in range(TILE_SIZE):
                        g_out = extra_grad_out[k, ly, i]
                        weight = rows[_R_WEIGHT, i]
                        lanes[N_GEOMETRY_SLOTS + FUSED_CHANNELS + k, i] += weight * g_out
                        term = (color * rows[_R_T_BEFORE, i] - extra_behind[k, ly, i] * rows[_R_INV_KEEP, i]) * g_out
                        rows[_R_GRAD_ALPHA, i] += term if weight > _ZERO else _ZERO
                        extra_behind[k, ly, i] += color * weight
                for i in range(TILE_SIZE):
                    dx = mx - (left + REAL(i))
                    raw_alpha = opacity * rows[_R_GAUSSIAN, i]
                    unclamped = (rows[_R_WEIGHT, i] > _ZERO) & (raw_alpha <= _MAX_ALPHA)
                    grad_alpha = rows[_R_GRAD_ALPHA, i] if unclamped else _ZERO
                    grad_sigma = -raw_alpha * grad_alpha
                    gx = grad_sigma * (ca * dx + cb * dy)
                    gy = grad_sigma * (cb * dx + cc * dy)
                    lanes[0, i] += gx
                    lanes[1, i] += gy
                    lanes[2, i] += _HALF * grad_sigma * dx * dx
                    lanes[3, i] += grad_sigma * dx * dy
                    lanes[4, i] += _HALF * grad_sigma * dy * dy
                    lanes[5, i] += rows[_R_GAUSSIAN, i] * grad_alpha
                    lanes[6, i] += abs(gx)
                    lanes[7, i] += abs(gy)
            # lanes outside first..last only ever added zeros
            for k in range(n_slots):
                slots[p, k] = _sum_lanes(lanes[k])
            lanes[:] = _ZERO


@nb.njit(cache=True, parallel=True)
def reduce_slots(
    packed_ids,      # [V] flat Gaussian of each packed one
    packed_offsets,  # [V + 1]
    packed_isects,   # [M]
    slots,           # [M, N_GEOMETRY_SLOTS + D] float32
    out_means2d,     # [C*N, 2] zeros (float32 or float64): per-Gaussian sums, in float64 in tile order, rounded
    out_conics,      # [C*N, 3]   once to the outputs' type; undrawn Gaussians stay 0. One array per
    out_opacities,   # [C*N]      gradient, so that the next backward reads each without a copy
    out_absgrad,     # [C*N, 2]
    out_colors,      # [C*N, D]
    parts,           # independent runs of packed Gaussians, balanced by intersections: the thread count
):
    n_slots = slots.shape[1]
    n_isects = packed_isects.shape[0]
    run_bounds = _balanced_runs(packed_offsets, parts)
    for run in nb.prange(parts):
        total = np.zeros(n_slots)
        for s in range(run_bounds[run], run_bounds[run + 1]):
            g = packed_ids[s]
            total[:] = 0.0
            for i in range(packed_offsets[s], packed_offsets[s + 1]):
                if i + PREFETCH_AHEAD < n_isects:
                    _prefetch_row(slots, packed_isects[i + PREFETCH_AHEAD])
                row = packed_isects[i]
                for k in range(n_slots):
                    total[k] += slots[row, k]
            out_means2d[g, 0], out_means2d[g, 1] = total[0], total[1]
            out_conics[g, 0], out_conics[g, 1], out_conics[g, 2] = total[2], total[3], total[4]
            out_opacities[g] = total[5]
            out_absgrad[g, 0], out_absgrad[g, 1] = total[6], total[7]
            for k in range(N_GEOMETRY_SLOTS, n_slots):
                out_colors[g, k - N_GEOMETRY_SLOTS] = total[k]
