"""Reference backend: a dense PyTorch rasteriser, simple and obviously right; the oracle for every other backend.

Every pixel meets every visible Gaussian (no tiles); it runs in whatever float dtype it is given
(float64 for tests) and is differentiable by autograd. Memory is bounded by compositing
PAIRS_PER_CHUNK pixel-Gaussian pairs at a time and, under autograd, recomputing each chunk in
the backward pass (activation checkpointing).
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from omniscs.render.constants import ALPHA_THRESHOLD, MAX_ALPHA, TRANSMITTANCE_STOP
from omniscs.render.projection import ScreenGaussians

#: Pixel-Gaussian pairs composited in one step (about 32 MB per float64 temporary).
PAIRS_PER_CHUNK = 1 << 22


def pixel_centres(width: int, height: int, dtype: torch.dtype, device: torch.device) -> Tensor:  # -> [H*W, 2]
    """Centres (x + 0.5, y + 0.5) of all pixels in row-major order, as gsplat places them."""
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device) + 0.5,
        torch.arange(width, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)


def composite_chunk(
    pixels: Tensor,         # [P, 2] pixel centres
    means2d: Tensor,        # [B, 2] depth-sorted, front first
    conics: Tensor,         # [B, 3]
    opacities: Tensor,      # [B]
    colors: Tensor,         # [B, D]
    transmittance: Tensor,  # [P] before this chunk
    done: Tensor,           # [P] bool, pixel already stopped
    accumulated: Tensor,    # [P, D]
) -> tuple[Tensor, Tensor, Tensor]:  # transmittance [P], done [P], accumulated [P, D] after the chunk
    """Front-to-back alpha compositing of one depth-ordered chunk of Gaussians over all pixels."""
    delta = means2d[None, :, :] - pixels[:, None, :]  # [P, B, 2]
    dx, dy = delta[..., 0], delta[..., 1]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-sigma), max=MAX_ALPHA)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_THRESHOLD), alpha, torch.zeros_like(alpha))
    keep = 1.0 - alpha
    before = transmittance[:, None] * torch.cat([torch.ones_like(keep[:, :1]), torch.cumprod(keep, 1)[:, :-1]], 1)
    # A pixel stops at the first Gaussian that would take its transmittance to TRANSMITTANCE_STOP;
    # transmittance only falls, so every later Gaussian is excluded as well.
    included = (before * keep > TRANSMITTANCE_STOP) & ~done[:, None]
    weights = torch.where(included, alpha * before, torch.zeros_like(alpha))
    accumulated = accumulated + weights @ colors
    transmittance = transmittance * torch.where(included, keep, torch.ones_like(keep)).prod(1)
    done = done | (~included & (alpha > 0)).any(1)
    return transmittance, done, accumulated


def rasterize_reference(
    screen: ScreenGaussians,
    colors: Tensor,       # [C, N, D] per-camera colours/features
    backgrounds: Tensor,  # [C, D] seen through the final transmittance
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:  # colors [C, H, W, D], alphas [C, H, W, 1]
    """Composite the visible Gaussians of every camera, sorted by depth (ties: lower index first)."""
    n_cameras, _, n_channels = colors.shape
    dtype, device = colors.dtype, colors.device
    pixels = pixel_centres(width, height, dtype, device)
    n_pixels = pixels.shape[0]
    chunk = max(1, PAIRS_PER_CHUNK // n_pixels)
    images, alphas = [], []
    for cam in range(n_cameras):
        ids = torch.nonzero(screen.visible[cam]).squeeze(1)
        ids = ids[torch.sort(screen.depths[cam, ids].detach(), stable=True).indices]
        transmittance = torch.ones(n_pixels, dtype=dtype, device=device)
        done = torch.zeros(n_pixels, dtype=torch.bool, device=device)
        accumulated = torch.zeros(n_pixels, n_channels, dtype=dtype, device=device)
        for start in range(0, max(ids.numel(), 1), chunk):  # one empty chunk keeps outputs in the autograd graph
            sel = ids[start:start + chunk]
            args = (pixels, screen.means2d[cam, sel], screen.conics[cam, sel], screen.opacities[cam, sel],
                    colors[cam, sel], transmittance, done, accumulated)
            if torch.is_grad_enabled():
                transmittance, done, accumulated = checkpoint(composite_chunk, *args, use_reentrant=False)
            else:
                transmittance, done, accumulated = composite_chunk(*args)
        images.append((accumulated + transmittance[:, None] * backgrounds[cam]).reshape(height, width, n_channels))
        alphas.append((1.0 - transmittance).reshape(height, width, 1))
    return torch.stack(images), torch.stack(alphas)
