"""CPU backend: gsplat's tile rasteriser as Numba kernels behind a torch.autograd.Function.

Why Numba: it JIT-compiles plain Python loops to native, multi-threaded code (``prange`` over
16x16 tiles) with no build step; ``cache=True`` stores the machine code beside the module so the
one-off compile (measured by ``omniscs.render.bench``) is paid once per machine. A C++ extension
would need a compiler and a build on every fresh machine for the same scalar loops.

Two autograd Functions, as in gsplat: ``CpuProjection`` (EWA projection fused per Gaussian,
float64, hand-derived backward; ``projection.py`` is its definition) and ``TileRasterizer``
(binning into tiles, front-to-back compositing, and a back-to-front backward pass that rebuilds
transmittance by division). SH colours stay in PyTorch (``sh.py``, shared with the reference).
Each intersection writes its gradient into its own slot and every Gaussian sums its slots in
tile order, so forward and backward are deterministic (no atomics, no thread-order dependence).
Camera parameters (viewmats, Ks) get no gradient from this backend.

Screen-space gradients: ``meta["means2d"]`` is the [C, N, 2] tensor the rasteriser consumed. Call
``meta["means2d"].retain_grad()`` before ``backward()`` to read ``meta["means2d"].grad`` (gsplat's
densification signal); with ``absgrad=True`` the per-pixel absolute gradients are summed into
``meta["means2d"].absgrad`` as well.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from omniscs.render import _cpu_kernels as kernels
from omniscs.render import _cpu_projection as projection_kernels
from omniscs.render.constants import TILE_SIZE
from omniscs.render.projection import ScreenGaussians

#: Tiles handed to a thread at a time; small chunks balance the uneven cost of sky and street tiles.
TILES_PER_CHUNK = 4


def _as_float32(t: Tensor, shape: tuple[int, ...]) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float32).reshape(shape).numpy())


def _as_numpy(t: Tensor, dtype: torch.dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(dtype).numpy())


class CpuProjection(torch.autograd.Function):
    """``projection.project_gaussians`` as fused Numba kernels; differentiable in means, quats, scales, opacities.

    Works in the dtype of ``means`` (float32 or float64) in memory and in float64 in registers
    (cameras are always passed as float64).
    """

    @staticmethod
    def forward(ctx, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor, Ks: Tensor,
                width: int, height: int, near_plane: float, far_plane: float, eps2d: float, antialiased: bool,
                ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:  # see ScreenGaussians
        dtype = means.dtype
        inputs = (*(_as_numpy(t, dtype) for t in (means, quats, scales, opacities)),
                  _as_numpy(viewmats, torch.float64), _as_numpy(Ks, torch.float64))
        settings = (width, height, float(near_plane), float(far_plane), float(eps2d), bool(antialiased))
        n_cams, n_gauss = viewmats.shape[0], means.shape[0]
        np_dtype = inputs[0].dtype
        means2d = np.empty((n_cams, n_gauss, 2), dtype=np_dtype)
        conics = np.empty((n_cams, n_gauss, 3), dtype=np_dtype)
        depths = np.empty((n_cams, n_gauss), dtype=np_dtype)
        opacities_c = np.empty((n_cams, n_gauss), dtype=np_dtype)
        radii = np.empty((n_cams, n_gauss, 2), dtype=np.int32)
        projection_kernels.project_forward(*inputs, *settings, means2d, conics, depths, opacities_c, radii)
        ctx.inputs, ctx.settings, ctx.radii = inputs, settings, radii
        radii_t = torch.from_numpy(radii)
        ctx.mark_non_differentiable(radii_t)
        return (torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths),
                torch.from_numpy(opacities_c), radii_t)

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, v_opacities, _v_radii):
        means, quats, scales, opacities, viewmats, Ks = ctx.inputs
        n_cams, n_gauss = viewmats.shape[0], means.shape[0]
        dtype = torch.from_numpy(means[:0]).dtype
        upstream = [
            np.zeros(shape, dtype=means.dtype) if grad is None else _as_numpy(grad, dtype)
            for grad, shape in ((v_means2d, (n_cams, n_gauss, 2)), (v_conics, (n_cams, n_gauss, 3)),
                                (v_depths, (n_cams, n_gauss)), (v_opacities, (n_cams, n_gauss)))
        ]
        grads = (np.empty_like(means), np.empty_like(quats), np.empty_like(scales), np.empty_like(opacities))
        projection_kernels.project_backward(*ctx.inputs, *ctx.settings, ctx.radii, *upstream, *grads)
        return (*(torch.from_numpy(g) for g in grads), None, None, None, None, None, None, None, None)


def project_cpu(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,  # [N, 3], [N, 4], [N, 3], [N]
    viewmats: Tensor, Ks: Tensor,                                     # [C, 4, 4], [C, 3, 3]
    width: int, height: int, near_plane: float, far_plane: float, eps2d: float, antialiased: bool = False,
) -> ScreenGaussians:
    """Same result as ``projection.project_gaussians`` (to rounding), from the fused kernels."""
    return ScreenGaussians(*CpuProjection.apply(means, quats, scales, opacities, viewmats.detach(), Ks.detach(),
                                                width, height, near_plane, far_plane, eps2d, antialiased))


class TileRasterizer(torch.autograd.Function):
    """Composite screen-space Gaussians over 16x16 tiles; differentiable in means2d, conics, colours, opacities."""

    @staticmethod
    def forward(
        ctx,
        means2d: Tensor,    # [C, N, 2]
        conics: Tensor,     # [C, N, 3]
        colors: Tensor,     # [C, N, D]
        opacities: Tensor,  # [C, N]
        depths: Tensor,     # [C, N] sort key only (no gradient; depth gradients flow through colour channels)
        radii: Tensor,      # [C, N, 2] int32, 0 where culled
        width: int,
        height: int,
        absgrad: bool,
    ) -> tuple[Tensor, Tensor]:  # colours [C, H, W, D] without background, transmittance [C, H, W]
        n_cams, n_gauss, n_channels = colors.shape
        flat = n_cams * n_gauss
        visible = radii[..., 0] > 0
        sort_key = torch.where(visible, depths.detach(), torch.full_like(depths, float("inf")))
        depth_order = torch.sort(sort_key, dim=1, stable=True).indices
        means2d_np = _as_float32(means2d, (flat, 2))
        colors_np = _as_float32(colors, (flat, n_channels))
        radii_np = np.ascontiguousarray(radii.reshape(flat, 2).numpy())
        records, drawable = kernels.make_records(
            means2d_np, _as_float32(conics, (flat, 3)), _as_float32(opacities, (flat,)), radii_np)
        bins = kernels.bin_gaussians(records, drawable, radii_np, depth_order.numpy(), visible.sum(1).numpy(),
                                     width, height, TILE_SIZE)
        out_colors = np.empty((n_cams, height, width, n_channels), dtype=np.float32)
        out_transmittance = np.empty((n_cams, height, width), dtype=np.float32)
        out_counts = np.empty((n_cams, height, width), dtype=np.int32)
        with numba.parallel_chunksize(TILES_PER_CHUNK):
            kernels.rasterize_forward(bins[0], bins[1], bins[2], records, colors_np,
                                      out_colors, out_transmittance, out_counts)
        ctx.arrays = (records, colors_np)
        ctx.bins = bins
        ctx.image = (width, height, out_transmittance, out_counts)
        ctx.absgrad = absgrad
        ctx.dtypes = (means2d.dtype, conics.dtype, colors.dtype, opacities.dtype)
        ctx.save_for_backward(means2d)
        dtype = colors.dtype
        return torch.from_numpy(out_colors).to(dtype), torch.from_numpy(out_transmittance).to(dtype)

    @staticmethod
    def backward(ctx, grad_colors: Tensor | None, grad_transmittance: Tensor | None):
        (means2d,) = ctx.saved_tensors
        width, height, transmittance, counts = ctx.image
        records, colors_np = ctx.arrays
        tile_offsets, isect_gaussians, pixel_boxes, gaussian_offsets, gaussian_isects = ctx.bins
        n_cams = transmittance.shape[0]
        n_channels = colors_np.shape[1]
        if grad_colors is None:
            grad_colors = torch.zeros((n_cams, height, width, n_channels))
        if grad_transmittance is None:
            grad_transmittance = torch.zeros((n_cams, height, width))
        slots = np.empty((isect_gaussians.shape[0], kernels.N_GEOMETRY_SLOTS + n_channels), dtype=np.float32)
        with numba.parallel_chunksize(TILES_PER_CHUNK):
            kernels.rasterize_backward(
                tile_offsets, isect_gaussians, pixel_boxes, records, colors_np, transmittance, counts,
                _as_float32(grad_colors, tuple(grad_colors.shape)),
                _as_float32(grad_transmittance, tuple(grad_transmittance.shape)),
                slots,
            )
        per_gaussian = np.empty((records.shape[0], slots.shape[1]), dtype=np.float64)
        kernels.reduce_slots(gaussian_offsets, gaussian_isects, slots, per_gaussian)
        grads = torch.from_numpy(per_gaussian.astype(colors_np.dtype)).reshape(n_cams, -1, slots.shape[1])
        dt_means, dt_conics, dt_colors, dt_opacities = ctx.dtypes
        if ctx.absgrad:
            means2d.absgrad = grads[..., 6:8].to(dt_means)
        return (
            grads[..., 0:2].to(dt_means),
            grads[..., 2:5].to(dt_conics),
            grads[..., kernels.N_GEOMETRY_SLOTS:].to(dt_colors),
            grads[..., 5].to(dt_opacities),
            None, None, None, None, None,
        )


def rasterize_cpu(
    screen: ScreenGaussians,
    colors: Tensor,  # [C, N, D]
    width: int,
    height: int,
    absgrad: bool = False,
) -> tuple[Tensor, Tensor]:  # colors [C, H, W, D] (no background), alphas [C, H, W, 1]
    rendered, transmittance = TileRasterizer.apply(
        screen.means2d, screen.conics, colors, screen.opacities, screen.depths, screen.radii,
        width, height, absgrad,
    )
    return rendered, (1.0 - transmittance)[..., None]
