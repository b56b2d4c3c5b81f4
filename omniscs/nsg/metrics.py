"""Image quality: PSNR and SSIM (kornia), over the whole image or a mask."""
from __future__ import annotations

import math

import torch
from kornia.metrics import ssim as kornia_ssim
from torch import Tensor

#: SSIM window (pixels), the usual 11x11 Gaussian window.
SSIM_WINDOW = 11

#: PSNR is reported as this when the images are identical (instead of +inf).
MAX_PSNR_DB = 100.0


def _chw(img: Tensor) -> Tensor:  # [H, W, 3] -> [1, 3, H, W]
    return img.permute(2, 0, 1)[None].to(torch.float32)


def psnr(rendered: Tensor, target: Tensor,  # [H, W, 3] in [0, 1]
         mask: Tensor | None = None) -> float:  # [H, W] bool
    """Peak signal-to-noise ratio in dB over all pixels, or over ``mask`` (NaN when the mask is empty)."""
    err = (rendered.clamp(0, 1) - target).pow(2).mean(-1)
    if mask is not None:
        if not bool(mask.any()):
            return float("nan")
        err = err[mask]
    mse = float(err.mean())
    return MAX_PSNR_DB if mse <= 10 ** (-MAX_PSNR_DB / 10) else -10.0 * math.log10(mse)


def ssim_map(rendered: Tensor, target: Tensor) -> Tensor:  # [H, W, 3] in [0, 1] -> [H, W]
    """The SSIM of every pixel's window, averaged over the colour channels."""
    return kornia_ssim(_chw(rendered.clamp(0, 1)), _chw(target), SSIM_WINDOW)[0].mean(0)


def ssim(rendered: Tensor, target: Tensor,  # [H, W, 3] in [0, 1]
         mask: Tensor | None = None,  # [H, W] bool
         smap: Tensor | None = None) -> float:  # [H, W] ssim_map of the two, when already computed
    """Mean SSIM over all pixels, or the mean of the SSIM map over ``mask`` (NaN when it is empty)."""
    smap = ssim_map(rendered, target) if smap is None else smap
    if mask is not None:
        if not bool(mask.any()):
            return float("nan")
        return float(smap[mask].mean())
    return float(smap.mean())
