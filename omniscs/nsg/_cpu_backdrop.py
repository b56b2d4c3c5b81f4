"""Numba kernels of a view's backdrop (CPU): the sky where the Gaussians leave a pixel uncovered, then the camera's
exposure correction, fused per pixel with a hand-derived backward.

The PyTorch code in ``omniscs.nsg.backdrop`` (``pixel_directions``, ``sky_colors``: ``grid_sample`` bilinear,
``align_corners=False``, border padding; the [3, 4] affine) is the definition; tests hold these kernels to it in
values and gradients, at the texture's borders and seam, and at alpha 0 and 1. Pixel arithmetic is float64, images
float32. Reductions (the texture's and the affine's gradients) sum fixed runs of rows and then the runs in order,
so the results do not depend on the thread count.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

#: Runs of image rows whose texture and affine gradients are summed separately, then in order.
ROW_RUNS = 8


@nb.njit(cache=True, parallel=True)
def sky_grid(
    width, height,
    K,         # [3, 3] float64 intrinsics
    rotation,  # [3, 3] float64 world_from_camera rotation
    grid,      # out [H * W, 2] float32: (azimuth / pi, -elevation / (pi / 2)), grid_sample's (x, y)
):
    """Where each pixel centre's viewing direction falls on the latitude-longitude sky texture."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for row in nb.prange(height):
        dy = (row + 0.5 - cy) / fy
        for col in range(width):
            dx = (col + 0.5 - cx) / fx
            inv = 1.0 / math.sqrt(dx * dx + dy * dy + 1.0)
            x, y, z = dx * inv, dy * inv, inv
            wx = rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2] * z
            wy = rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2] * z
            wz = rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2] * z
            p = row * width + col
            grid[p, 0] = math.atan2(np.float32(wy), np.float32(wx)) * np.float32(1.0 / math.pi)
            grid[p, 1] = -math.asin(np.float32(min(1.0, max(-1.0, wz)))) * np.float32(2.0 / math.pi)


@nb.njit(cache=True, inline="always")
def _corners(gx, gy, tex_w, tex_h):
    """grid_sample's bilinear corners at a grid point (align_corners=False, border padding): the top-left texel
    (x0, y0), always inside the texture, and the weights of the column and row after it (0 where those lie
    past the texture's edge: grid_sample's border clamps the point to the last texel centre)."""
    ix = min(tex_w - 1.0, max(0.0, ((gx + 1.0) * tex_w - 1.0) * 0.5))
    iy = min(tex_h - 1.0, max(0.0, ((gy + 1.0) * tex_h - 1.0) * 0.5))
    x0 = int(math.floor(ix))
    y0 = int(math.floor(iy))
    return x0, y0, ix - x0, iy - y0


@nb.njit(cache=True, parallel=True)
def backdrop_forward(
    colour,    # [H, W, 3] float32: what the Gaussians composited
    alpha,     # [H, W] float32: how much of each pixel they cover
    texture,   # [3, h, w] float32: the sky's colours (activated)
    grid,      # [H * W, 2] float32 (sky_grid)
    affine,    # [3, 4] float32 exposure [A | b]
    out,       # out [H, W, 3] float32: A (colour + (1 - alpha) sky) + b
):
    height, width = alpha.shape
    tex_h, tex_w = texture.shape[1], texture.shape[2]
    for row in nb.prange(height):
        for col in range(width):
            p = row * width + col
            x0, y0, wx, wy = _corners(np.float64(grid[p, 0]), np.float64(grid[p, 1]), tex_w, tex_h)
            uncovered = 1.0 - np.float64(alpha[row, col])
            x1 = min(x0 + 1, tex_w - 1)
            y1 = min(y0 + 1, tex_h - 1)
            w00, w01, w10, w11 = (1.0 - wx) * (1.0 - wy), wx * (1.0 - wy), (1.0 - wx) * wy, wx * wy
            c0 = c1 = c2 = 0.0
            for k in range(3):
                sky = (w00 * texture[k, y0, x0] + w01 * texture[k, y0, x1] + w10 * texture[k, y1, x0]
                       + w11 * texture[k, y1, x1])
                c = np.float64(colour[row, col, k]) + uncovered * sky
                if k == 0:
                    c0 = c
                elif k == 1:
                    c1 = c
                else:
                    c2 = c
            for k in range(3):
                out[row, col, k] = affine[k, 0] * c0 + affine[k, 1] * c1 + affine[k, 2] * c2 + affine[k, 3]


@nb.njit(cache=True, parallel=True)
def backdrop_backward(
    colour, alpha, texture, grid, affine,  # as in backdrop_forward
    upstream,      # [H, W, 3] float32: d loss / d out
    grad_colour,   # out [H, W, 3] float32
    grad_alpha,    # out [H, W] float32
    grad_texture,  # out [3, h, w] float64
    grad_affine,   # out [3, 4] float64
):
    height, width = alpha.shape
    tex_h, tex_w = texture.shape[1], texture.shape[2]
    runs = min(ROW_RUNS, height)
    run_texture = np.empty((runs, 3, tex_h, tex_w))
    run_affine = np.empty((runs, 3, 4))
    for r in nb.prange(runs):
        run_texture[r] = 0.0
        run_affine[r] = 0.0
        for row in range(r * height // runs, (r + 1) * height // runs):
            a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = b0 = b1 = b2 = 0.0
            for col in range(width):
                p = row * width + col
                x0, y0, wx, wy = _corners(np.float64(grid[p, 0]), np.float64(grid[p, 1]), tex_w, tex_h)
                x1 = min(x0 + 1, tex_w - 1)  # a corner past the edge has weight 0: any texel will do
                y1 = min(y0 + 1, tex_h - 1)
                w00, w01, w10, w11 = (1.0 - wx) * (1.0 - wy), wx * (1.0 - wy), (1.0 - wx) * wy, wx * wy
                uncovered = 1.0 - np.float64(alpha[row, col])
                u0 = np.float64(upstream[row, col, 0])
                u1 = np.float64(upstream[row, col, 1])
                u2 = np.float64(upstream[row, col, 2])
                b0 += u0
                b1 += u1
                b2 += u2
                g_alpha = 0.0
                for k in range(3):
                    # d out / d c = A: the gradient reaching the composited colour is A^T upstream
                    g = affine[0, k] * u0 + affine[1, k] * u1 + affine[2, k] * u2
                    sky = (w00 * texture[k, y0, x0] + w01 * texture[k, y0, x1] + w10 * texture[k, y1, x0]
                           + w11 * texture[k, y1, x1])
                    c = np.float64(colour[row, col, k]) + uncovered * sky
                    if k == 0:
                        a00 += u0 * c
                        a10 += u1 * c
                        a20 += u2 * c
                    elif k == 1:
                        a01 += u0 * c
                        a11 += u1 * c
                        a21 += u2 * c
                    else:
                        a02 += u0 * c
                        a12 += u1 * c
                        a22 += u2 * c
                    grad_colour[row, col, k] = g
                    g_alpha -= g * sky
                    g_sky = g * uncovered
                    run_texture[r, k, y0, x0] += w00 * g_sky
                    run_texture[r, k, y0, x1] += w01 * g_sky
                    run_texture[r, k, y1, x0] += w10 * g_sky
                    run_texture[r, k, y1, x1] += w11 * g_sky
                grad_alpha[row, col] = g_alpha
            run_affine[r, 0, 0] += a00
            run_affine[r, 0, 1] += a01
            run_affine[r, 0, 2] += a02
            run_affine[r, 1, 0] += a10
            run_affine[r, 1, 1] += a11
            run_affine[r, 1, 2] += a12
            run_affine[r, 2, 0] += a20
            run_affine[r, 2, 1] += a21
            run_affine[r, 2, 2] += a22
            run_affine[r, 0, 3] += b0
            run_affine[r, 1, 3] += b1
            run_affine[r, 2, 3] += b2
    # the runs summed in order by plain loops: an array expression here would be a parallel region of its own,
    # launched 2 x ROW_RUNS times a call, which cost more than the whole kernel at fit resolutions (measured)
    for k in range(3):
        for ty in range(tex_h):
            for tx in range(tex_w):
                total = 0.0
                for r in range(runs):
                    total += run_texture[r, k, ty, tx]
                grad_texture[k, ty, tx] = total
        for j in range(4):
            total = 0.0
            for r in range(runs):
                total += run_affine[r, k, j]
            grad_affine[k, j] = total
