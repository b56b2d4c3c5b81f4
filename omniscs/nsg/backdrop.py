"""A view's backdrop: the sky where the Gaussians leave a pixel uncovered, then the camera's exposure correction.

``rgb = A (colour + (1 - alpha) sky(direction)) + b``. The PyTorch code here (``pixel_directions``, ``sky_colors``,
the affine) is the definition and what CUDA tensors use; on the CPU the whole expression is one Numba pass each
way (``_cpu_backdrop``). As a dozen PyTorch operations (a [H*W, 3] x [3, 3] product each way, atan2, asin and
grid_sample over every pixel) it was about a tenth of a half-resolution fit step on a 2-core machine.
"""
from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from omniscs.devices import keeps_torch_threads
from omniscs.nsg import _cpu_backdrop as kernels
from omniscs.nsg.observations import View
from omniscs.nsg.sky import SkyParams, sky_colors


def pixel_directions(view: View, device: torch.device | str = "cpu") -> Tensor:  # [H, W, 3] float32 unit, world
    """Viewing direction through every pixel centre: the camera's unit rays (made once per intrinsics) turned into
    the world by the view's rotation."""
    rays = _camera_rays(view.width, view.height, tuple(np.asarray(view.K, np.float64).ravel().tolist()))
    rotation = torch.from_numpy(np.ascontiguousarray(view.world_from_camera[:3, :3], np.float32))
    return (rays @ rotation.T).to(device)


@functools.lru_cache(maxsize=32)
def _camera_rays(width: int, height: int, K: tuple[float, ...]) -> Tensor:  # [H, W, 3] float32 unit, camera frame
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d = np.stack([(u - K[2]) / K[0], (v - K[5]) / K[4], np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return torch.from_numpy(d.astype(np.float32))


def identity_exposure(device: torch.device | str = "cpu") -> Tensor:  # [3, 4]
    """The exposure correction that changes nothing: [I | 0]."""
    return torch.cat([torch.eye(3, device=device), torch.zeros(3, 1, device=device)], 1)


def backdrop_reference(colour: Tensor,  # [H, W, 3] what the Gaussians composited
                       alpha: Tensor,   # [H, W] how much of each pixel they cover
                       sky: SkyParams, affine: Tensor | None, view: View) -> Tensor:  # [H, W, 3]
    """The definition, in PyTorch (any device)."""
    rgb = colour + (1.0 - alpha)[..., None] * sky_colors(sky, pixel_directions(view, colour.device))
    return rgb if affine is None else rgb @ affine[:, :3].T + affine[:, 3]


def with_backdrop(colour: Tensor, alpha: Tensor, sky: SkyParams, affine: Tensor | None, view: View) -> Tensor:
    """``colour`` with the sky shown through ``1 - alpha`` and ``affine`` ([3, 4] [A | b]; None: none) applied:
    one fused pass each way for float32 CPU tensors, ``backdrop_reference`` otherwise."""
    tensors = (colour, alpha, sky.texture) + (() if affine is None else (affine,))
    if not all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors):
        return backdrop_reference(colour, alpha, sky, affine, view)
    grid = np.empty((view.height * view.width, 2), np.float32)
    kernels.sky_grid(view.width, view.height, np.asarray(view.K, np.float64),
                     np.ascontiguousarray(view.world_from_camera[:3, :3], np.float64), grid)
    return _Backdrop.apply(colour, alpha, torch.sigmoid(sky.texture), identity_exposure() if affine is None else affine,
                           grid)


class _Backdrop(torch.autograd.Function):
    """colour [H, W, 3], alpha [H, W], the sky's activated texture [3, h, w] and the affine [3, 4] -> rgb [H, W, 3];
    differentiable in all four (the sampling grid is fixed by the view)."""

    @staticmethod
    @keeps_torch_threads
    def forward(ctx, colour: Tensor, alpha: Tensor, texture: Tensor, affine: Tensor, grid: np.ndarray) -> Tensor:
        arrays = tuple(np.ascontiguousarray(t.detach().numpy(), dtype=np.float32) for t in (colour, alpha, texture, affine))
        out = np.empty(colour.shape, np.float32)
        kernels.backdrop_forward(*arrays[:3], grid, arrays[3], out)
        ctx.arrays, ctx.grid = arrays, grid
        return torch.from_numpy(out)

    @staticmethod
    @keeps_torch_threads
    def backward(ctx, upstream: Tensor):
        colour, alpha, texture, affine = ctx.arrays
        grad_colour = np.empty_like(colour)
        grad_alpha = np.empty_like(alpha)
        grad_texture = np.empty(texture.shape)
        grad_affine = np.empty((3, 4))
        kernels.backdrop_backward(colour, alpha, texture, ctx.grid, affine,
                                  np.ascontiguousarray(upstream.numpy(), dtype=np.float32),
                                  grad_colour, grad_alpha, grad_texture, grad_affine)
        return (torch.from_numpy(grad_colour), torch.from_numpy(grad_alpha),
                torch.from_numpy(grad_texture.astype(np.float32)), torch.from_numpy(grad_affine.astype(np.float32)), None)
