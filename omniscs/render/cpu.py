"""CPU backend: gsplat's tile rasteriser as Numba kernels behind torch.autograd.Functions.

Why Numba rather than a C++ extension: it compiles plain Python loops to native, multi-threaded
code (``prange`` over 16x16 tiles) with no build step, so ``make test`` works on a fresh machine;
``cache=True`` keeps the machine code beside the module, so the compile (about 20-40 s, once per
machine; the benchmark reports it as "first call") is not paid again. LLVM vectorises the pixel
loops for AVX-512 once they are written as fixed 16-lane, branch-free rows with a polynomial exp
(libm's exp does not vectorise); measured against straightforward per-pixel loops that was about
2x on the forward pass, which is what a hand-written C++ extension would also have to do.

Two Functions, as in gsplat: ``CpuProjection`` (EWA projection fused per Gaussian, float64,
hand-derived backward; ``projection.py`` is its definition and the tests hold it to it) and
``TileRasterizer`` (depth sort, binning into tiles, front-to-back compositing, and a back-to-front
backward pass that rebuilds transmittance by division). SH colours stay in PyTorch (``sh.py``,
shared with the reference). Each intersection writes its gradient into its own slot and every
Gaussian sums its slots in tile order, so forward and backward are bitwise deterministic (no
atomics, no dependence on thread scheduling). Camera parameters (viewmats, Ks) get no gradient.

Screen-space gradients: ``meta["means2d"]`` is the [C, N, 2] tensor the rasteriser consumed. Call
``meta["means2d"].retain_grad()`` before ``backward()`` to read ``meta["means2d"].grad`` (gsplat's
densification signal); with ``absgrad=True`` the per-pixel absolute gradients are summed into
``meta["means2d"].absgrad`` as well.

Shared machines: OpenMP threads (PyTorch's and Numba's) spin while they wait, which steals the
cores from the threads doing work when other processes are busy (measured here: a quarter of a
forward+backward, two thirds of the gradcheck tests). ``OMP_WAIT_POLICY=PASSIVE`` avoids it.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from omniscs.devices import keeps_torch_threads
from omniscs.render import _cpu_kernels as kernels
from omniscs.render import _cpu_projection as projection_kernels
from omniscs.render.projection import ScreenGaussians

def _as_real(t: Tensor, shape: tuple[int, ...], real: type) -> np.ndarray:
    return np.ascontiguousarray(t.detach().reshape(shape).numpy(), dtype=real)


def _pixel_type(*tensors: Tensor) -> type:
    """The arithmetic type of the pixel loops: float64 when any input is float64, else float32."""
    return np.float64 if any(t.dtype == torch.float64 for t in tensors) else np.float32


def _as_float64(t: Tensor) -> np.ndarray:
    # NumPy casts on one thread: a PyTorch cast is a parallel op that stalls on a busy machine
    return np.ascontiguousarray(t.detach().numpy(), dtype=np.float64)


def _from_float64(a: np.ndarray, dtype: torch.dtype) -> Tensor:
    return torch.from_numpy(a if dtype == torch.float64 else a.astype(np.float32))


def _as_array(t: Tensor) -> np.ndarray:  # in its own type: the projection kernels read values as float64
    return np.ascontiguousarray(t.detach().numpy())


class CpuProjection(torch.autograd.Function):
    """``projection.project_gaussians`` as fused Numba kernels; differentiable in means, quats, scales, opacities.

    Computes in float64 whatever the input dtype (geometry wants it; the kernels read every value as float64,
    so float32 inputs are not copied) and returns the dtype of ``means``.
    """

    @staticmethod
    @keeps_torch_threads
    def forward(ctx, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmats: Tensor, Ks: Tensor,
                width: int, height: int, near_plane: float, far_plane: float, eps2d: float, antialiased: bool,
                ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:  # ScreenGaussians' fields, float64 depths
        real = _pixel_type(means)  # the outputs' type, as means'
        inputs = (*(_as_array(t) for t in (means, quats, scales, opacities)), _as_float64(viewmats), _as_float64(Ks))
        settings = (width, height, float(near_plane), float(far_plane), float(eps2d), bool(antialiased))
        n_cams, n_gauss = viewmats.shape[0], means.shape[0]
        means2d = np.empty((n_cams, n_gauss, 2), dtype=real)
        conics = np.empty((n_cams, n_gauss, 3), dtype=real)
        depths = np.empty((n_cams, n_gauss))
        opacities_c = np.empty((n_cams, n_gauss), dtype=real)
        radii = np.empty((n_cams, n_gauss, 2), dtype=np.int32)
        projection_kernels.project_forward(*inputs, *settings, projection_kernels.norms2(inputs[4]), means2d, conics,
                                           depths, opacities_c, radii)
        ctx.inputs, ctx.settings, ctx.radii = inputs, settings, radii
        radii_t, sort_depths = torch.from_numpy(radii), torch.from_numpy(depths)
        ctx.mark_non_differentiable(radii_t, sort_depths)
        dtype = means.dtype
        return (torch.from_numpy(means2d), torch.from_numpy(conics), _from_float64(depths, dtype),
                torch.from_numpy(opacities_c), radii_t, sort_depths)

    @staticmethod
    @keeps_torch_threads
    def backward(ctx, v_means2d, v_conics, v_depths, v_opacities, _v_radii, _v_sort_depths):
        means, quats, scales, opacities, viewmats, Ks = ctx.inputs
        n_cams, n_gauss = viewmats.shape[0], means.shape[0]
        upstream = [
            np.zeros(shape, dtype=means.dtype) if grad is None else _as_array(grad)
            for grad, shape in ((v_means2d, (n_cams, n_gauss, 2)), (v_conics, (n_cams, n_gauss, 3)),
                                (v_depths, (n_cams, n_gauss)), (v_opacities, (n_cams, n_gauss)))
        ]
        grads = (np.empty_like(means), np.empty_like(quats), np.empty_like(scales), np.empty_like(opacities))
        projection_kernels.project_backward(*ctx.inputs, *ctx.settings, ctx.radii, *upstream, *grads)
        return (*(torch.from_numpy(g) for g in grads),
                None, None, None, None, None, None, None, None)


def project_cpu(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,  # [N, 3], [N, 4], [N, 3], [N]
    viewmats: Tensor, Ks: Tensor,                                     # [C, 4, 4], [C, 3, 3]
    width: int, height: int, near_plane: float, far_plane: float, eps2d: float, antialiased: bool = False,
) -> tuple[ScreenGaussians, Tensor]:  # screen Gaussians, float64 depths [C, N] to sort by
    """Same result as ``projection.project_gaussians`` (to rounding), from the fused kernels.

    The float64 depths keep the compositing order of float32 inputs equal to the float64 reference's.
    """
    *fields, sort_depths = CpuProjection.apply(means, quats, scales, opacities, viewmats.detach(), Ks.detach(),
                                               width, height, near_plane, far_plane, eps2d, antialiased)
    return ScreenGaussians(*fields), sort_depths


def _depth_bits(depths: Tensor) -> np.ndarray:  # [C, N] float -> [C, N] uint64, same order for positive depths
    values = np.ascontiguousarray(depths.detach().numpy())
    if values.dtype == np.float64:
        return values.view(np.uint64)
    return values.astype(np.float32).view(np.uint32).astype(np.uint64)


class TileRasterizer(torch.autograd.Function):
    """Composite screen-space Gaussians over 16x16 tiles.

    Differentiable in means2d, conics, colours, opacities and backgrounds.
    """

    @staticmethod
    @keeps_torch_threads
    def forward(
        ctx,
        means2d: Tensor,      # [C, N, 2]
        conics: Tensor,       # [C, N, 3]
        colors: Tensor,       # [C, N, D]
        opacities: Tensor,    # [C, N]
        backgrounds: Tensor,  # [C, D]
        sort_depths: Tensor,  # [C, N] sort key only (depth gradients flow through colour channels)
        radii: Tensor,        # [C, N, 2] int32, 0 where culled
        width: int,
        height: int,
        absgrad: bool,
    ) -> tuple[Tensor, Tensor]:  # colours [C, H, W, D], alphas [C, H, W, 1]
        n_cams, n_gauss, n_channels = colors.shape
        flat = n_cams * n_gauss
        real = _pixel_type(means2d, conics, colors, opacities)
        radii_np = radii.numpy()
        depth_order, n_visible = kernels.depth_order(_depth_bits(sort_depths), radii_np)
        threads = numba.get_num_threads()  # how the kernels split their work (results do not depend on it)
        bins = kernels.bin_gaussians(
            _as_real(means2d, (flat, 2), real), _as_real(conics, (flat, 3), real), _as_real(opacities, (flat,), real),
            _as_real(colors, (flat, n_channels), real), radii_np.reshape(flat, 2), depth_order, n_visible, width,
            height, threads,
        )
        tile_offsets, isect_packed, _, packed_records, packed_colors, _, _ = bins
        backgrounds_np = _as_real(backgrounds, (n_cams, n_channels), real)
        out_colors = np.empty((n_cams, height, width, n_channels), dtype=real)
        out_alphas = np.empty((n_cams, height, width, 1), dtype=real)
        transmittance = np.empty((n_cams, height, width), dtype=real)
        counts = np.empty((n_cams, height, width), dtype=np.int32)
        row_masks = np.empty(isect_packed.shape[0], dtype=np.int32)
        tile_order = kernels.spread_order(tile_offsets.shape[0] - 1, threads)
        kernels.rasterize_forward(tile_offsets, isect_packed, packed_records, packed_colors,
                                  backgrounds_np, out_colors, out_alphas, transmittance, counts, row_masks, tile_order)
        ctx.bins = bins
        ctx.image = (width, height, transmittance, counts, row_masks, backgrounds_np, tile_order)
        ctx.n_flat = flat
        ctx.absgrad = absgrad
        ctx.dtypes = (colors.dtype, backgrounds.dtype)
        ctx.save_for_backward(means2d)
        dtype = colors.dtype
        return torch.from_numpy(out_colors).to(dtype), torch.from_numpy(out_alphas).to(dtype)

    @staticmethod
    @keeps_torch_threads
    def backward(ctx, grad_colors: Tensor | None, grad_alphas: Tensor | None):
        (means2d,) = ctx.saved_tensors
        width, height, transmittance, counts, row_masks, backgrounds, tile_order = ctx.image
        tile_offsets, isect_packed, packed_ids, packed_records, packed_colors, packed_offsets, packed_isects = ctx.bins
        n_cams, n_channels = backgrounds.shape
        real = backgrounds.dtype.type  # the forward pass's pixel type
        grad_colors_np = (np.zeros((n_cams, height, width, n_channels), dtype=real) if grad_colors is None
                          else _as_real(grad_colors, (n_cams, height, width, n_channels), real))
        grad_alphas_np = (np.zeros((n_cams, height, width, 1), dtype=real) if grad_alphas is None
                          else _as_real(grad_alphas, (n_cams, height, width, 1), real))
        slots = np.empty((isect_packed.shape[0], kernels.N_GEOMETRY_SLOTS + n_channels), dtype=real)
        kernels.rasterize_backward(tile_offsets, isect_packed, packed_records, packed_colors, backgrounds,
                                   transmittance, counts, row_masks, grad_colors_np, grad_alphas_np, slots, tile_order)
        dt_colors, dt_backgrounds = ctx.dtypes
        per_gaussian = tuple(np.zeros((ctx.n_flat,) + shape, dtype=_pixel_type(means2d))
                             for shape in ((2,), (3,), (), (2,), (n_channels,)))
        kernels.reduce_slots(packed_ids, packed_offsets, packed_isects, slots, *per_gaussian, numba.get_num_threads())
        g_means2d, g_conics, g_opacities, g_absgrad, g_colors = (
            torch.from_numpy(a).reshape((n_cams, -1) + a.shape[1:]) for a in per_gaussian)
        if ctx.absgrad:
            means2d.absgrad = g_absgrad
        grad_backgrounds = None
        if ctx.needs_input_grad[4]:
            seen = transmittance[..., None].astype(np.float64) * grad_colors_np
            grad_backgrounds = torch.from_numpy(seen.sum(axis=(1, 2))).to(dt_backgrounds)
        return (g_means2d, g_conics, g_colors.to(dt_colors), g_opacities, grad_backgrounds,
                None, None, None, None, None)


def rasterize_cpu(
    screen: ScreenGaussians,
    colors: Tensor,       # [C, N, D]
    backgrounds: Tensor,  # [C, D]
    width: int,
    height: int,
    absgrad: bool = False,
    sort_depths: Tensor | None = None,  # [C, N] depths to order by (default: screen.depths)
) -> tuple[Tensor, Tensor]:  # colors [C, H, W, D], alphas [C, H, W, 1]
    return TileRasterizer.apply(screen.means2d, screen.conics, colors, screen.opacities, backgrounds,
                                screen.depths if sort_depths is None else sort_depths, screen.radii,
                                width, height, absgrad)
