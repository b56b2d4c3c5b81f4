"""The fit's SSIM loss on the CPU as two Numba passes: ``quality.ssim_loss``'s maths (reflect padding, a separable
Gaussian window, kornia's constants, the mean of clamp((1 - SSIM) / 2, 0, 1)) with a hand-derived backward.

A fit step computes the loss of one rendered image against its target. In PyTorch that is two grouped
convolutions over fifteen moment planes and some thirty elementwise operations each way, about a fifth of a
full-resolution fit step on two cores; here it is one pass forward (which also keeps the three per-pixel
gradient maps) and one adjoint-filter pass backward, parallel over colour planes and rows, accumulating in
float64. ``quality.ssim_loss`` is the definition; tests hold this one to it in value and gradient.
"""
from __future__ import annotations

import numba as nb
import numpy as np
import torch
from torch import Tensor

from omniscs.devices import keeps_torch_threads


@nb.njit(cache=True, inline="always")
def _reflect(i, n):
    """Index of padded position i - pad in a length-n axis under reflect padding (the edge is not repeated)."""
    if i < 0:
        return -i
    if i > n - 1:
        return 2 * (n - 1) - i
    return i


@nb.njit(cache=True, parallel=True)
def ssim_forward(x, y,       # [P, H, W] float32 rendered and target planes
                 kernel,     # [k] float64 normalised 1D window, k odd
                 c1, c2, eps,
                 grad_maps,  # [3, P, H, W] float64 out: d(sum of per-pixel loss)/d(mu_x, e_xx, e_xy)
                 ):          # -> sum over planes and pixels of clamp((1 - SSIM) / 2, 0, 1)
    planes, height, width = x.shape
    k = kernel.shape[0]
    pad = k // 2
    rows = height + 2 * pad
    # horizontal pass over every padded row: the five moments filtered along x (taps outer, columns inner: the
    # column loops vectorise)
    horizontal = np.empty((planes, 5, rows, width))
    for job in nb.prange(planes * rows):
        p, r = job // rows, job % rows
        src = _reflect(r - pad, height)
        bx = np.empty(width + 2 * pad)  # the padded row, read once
        by = np.empty(width + 2 * pad)
        for c in range(width + 2 * pad):
            col = _reflect(c - pad, width)
            bx[c] = x[p, src, col]
            by[c] = y[p, src, col]
        acc = np.zeros((5, width))
        for b in range(k):
            w = kernel[b]
            for j in range(width):
                vx = bx[j + b]
                vy = by[j + b]
                acc[0, j] += w * vx
                acc[1, j] += w * vy
                acc[2, j] += w * vx * vx
                acc[3, j] += w * vy * vy
                acc[4, j] += w * vx * vy
        for q in range(5):
            for j in range(width):
                horizontal[p, q, r, j] = acc[q, j]
    row_sums = np.empty(planes * height)
    for job in nb.prange(planes * height):
        p, i = job // height, job % height
        m = np.zeros((5, width))
        for a in range(k):
            w = kernel[a]
            for q in range(5):
                for j in range(width):
                    m[q, j] += w * horizontal[p, q, i + a, j]
        total = 0.0
        for j in range(width):
            mu_x, mu_y, e_xx, e_yy, e_xy = m[0, j], m[1, j], m[2, j], m[3, j], m[4, j]
            mu_xy = mu_x * mu_y
            a1 = 2.0 * mu_xy + c1
            a2 = 2.0 * (e_xy - mu_xy) + c2
            b1 = mu_x * mu_x + mu_y * mu_y + c1
            b2 = (e_xx - mu_x * mu_x) + (e_yy - mu_y * mu_y) + c2
            den = b1 * b2 + eps
            similarity = a1 * a2 / den
            loss = (1.0 - similarity) / 2.0
            inside = (loss >= 0.0) & (loss <= 1.0)  # torch.clamp passes the gradient at its bounds
            total += min(max(loss, 0.0), 1.0)
            g = -0.5 if inside else 0.0
            d_num = g / den
            d_den = -g * similarity / den
            grad_maps[0, p, i, j] = d_num * 2.0 * mu_y * (a2 - a1) + d_den * 2.0 * mu_x * (b2 - b1)
            grad_maps[1, p, i, j] = d_den * b1
            grad_maps[2, p, i, j] = d_num * 2.0 * a1
        row_sums[job] = total
    # summed in order by a plain loop: row_sums.sum() would be a parallel reduction, a region of its own whose
    # order depends on the thread count
    total = 0.0
    for job in range(planes * height):
        total += row_sums[job]
    return total


@nb.njit(cache=True, parallel=True)
def ssim_backward(x, y, kernel, grad_maps,  # as in ssim_forward
                  scale,                    # d loss / d (sum of per-pixel losses)
                  out,                      # [P, H, W] float32: d loss / d x
                  ):
    """The adjoint of the forward's filtering: each gradient map filtered back onto the padded planes (vertical,
    then horizontal), then the padded positions folded onto the pixels they copy."""
    planes, height, width = x.shape
    k = kernel.shape[0]
    pad = k // 2
    rows, cols = height + 2 * pad, width + 2 * pad
    vertical = np.empty((planes, 3, rows, width))
    for job in nb.prange(planes * rows):
        p, r = job // rows, job % rows
        a_lo, a_hi = max(0, r - height + 1), min(k - 1, r)  # window taps whose output row i = r - a exists
        acc = np.zeros((3, width))
        for a in range(a_lo, a_hi + 1):
            w = kernel[a]
            for m in range(3):
                for j in range(width):
                    acc[m, j] += w * grad_maps[m, p, r - a, j]
        for m in range(3):
            for j in range(width):
                vertical[p, m, r, j] = acc[m, j]
    for p in nb.prange(planes):
        for i in range(height):
            for j in range(width):
                out[p, i, j] = 0.0
        acc = np.empty((3, cols))
        for r in range(rows):
            src = _reflect(r - pad, height)
            acc[:] = 0.0
            for b in range(k):  # taps outer: the column loop vectorises
                w = kernel[b]
                for m in range(3):
                    for j in range(width):
                        acc[m, j + b] += w * vertical[p, m, r, j]
            for c in range(cols):
                col = _reflect(c - pad, width)
                vx = np.float64(x[p, src, col])
                vy = np.float64(y[p, src, col])
                out[p, src, col] += scale * (acc[0, c] + 2.0 * vx * acc[1, c] + vy * acc[2, c])


class FusedSSIMLoss(torch.autograd.Function):
    """mean(clamp((1 - SSIM) / 2, 0, 1)) of [1, C, H, W] float32 CPU images; differentiable in ``rendered``."""

    @staticmethod
    @keeps_torch_threads
    def forward(ctx, rendered: Tensor, target: Tensor, kernel: np.ndarray, c1: float, c2: float,
                eps: float) -> Tensor:
        x = np.ascontiguousarray(rendered.detach()[0].numpy(), dtype=np.float32)
        y = np.ascontiguousarray(target.detach()[0].numpy(), dtype=np.float32)
        grad_maps = np.empty((3,) + x.shape)
        total = ssim_forward(x, y, kernel, c1, c2, eps, grad_maps)
        ctx.saved = (x, y, kernel, grad_maps)
        return torch.tensor(total / x.size, dtype=rendered.dtype)

    @staticmethod
    @keeps_torch_threads
    def backward(ctx, grad: Tensor):
        x, y, kernel, grad_maps = ctx.saved
        out = np.empty(x.shape, dtype=np.float32)
        ssim_backward(x, y, kernel, grad_maps, float(grad) / x.size, out)
        return torch.from_numpy(out)[None], None, None, None, None, None
