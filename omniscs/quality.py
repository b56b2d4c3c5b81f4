"""Image quality, written once: PSNR and SSIM of a rendered image against a reference, over the whole image or a
mask, for numpy or torch images on a float ([0, 1]) or 8-bit ([0, 255]) scale.

The edge cases, the same for every caller:
- identical (or nearly identical) images: PSNR is ``MAX_PSNR_DB`` (100 dB), never +inf: a mean squared error
  at or below ``data_range² · 10^(-MAX_PSNR_DB / 10)`` reports the cap;
- an empty mask: None (nothing was seen, so there is nothing to score), never NaN or a zero;
- the rendered image is clipped to ``[0, data_range]`` first (a render's colour can leave the displayable range,
  the picture it stands for cannot); the reference is taken as it is;
- non-finite pixel values: an OmniscsError (a NaN or Inf score would poison every mean it enters).
Figures are computed in the inputs' floating precision (float32 renders stay float32 until the mean squared
error, 8-bit images are read as float64), so a stage's reported figures do not depend on where it was scored.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from kornia.metrics import ssim as kornia_ssim
from torch import Tensor

from omniscs.errors import OmniscsError

#: PSNR (dB) reported for identical images instead of +inf.
MAX_PSNR_DB = 100.0

#: SSIM window (pixels), the usual 11x11 Gaussian window.
SSIM_WINDOW = 11

#: The scale of 8-bit images, to pass as ``data_range``.
UINT8_RANGE = 255.0

Image = Tensor | np.ndarray


def _image(img: Image) -> Tensor:
    """A floating tensor of the image; integer images (8-bit) are read as float64 so differences cannot wrap."""
    t = img if isinstance(img, Tensor) else torch.from_numpy(np.asarray(img))
    return t if t.is_floating_point() else t.to(torch.float64)


def _mask(mask: Image, shape: torch.Size) -> Tensor:
    m = mask if isinstance(mask, Tensor) else torch.from_numpy(np.asarray(mask))
    m = m.to(torch.bool)
    if m.shape != shape:
        raise OmniscsError(f"mask of shape {tuple(m.shape)} does not cover images of {tuple(shape)} pixels; "
                           "pass one boolean per pixel")
    return m


def _pair(rendered: Image, target: Image) -> tuple[Tensor, Tensor]:
    r, g = _image(rendered), _image(target)
    if r.shape != g.shape:
        raise OmniscsError(f"rendered {tuple(r.shape)} and reference {tuple(g.shape)} images differ in shape")
    return r, g


def psnr_from_mse(mse: float, data_range: float = 1.0) -> float:
    """PSNR (dB) of a mean squared error on a ``data_range`` scale, capped at ``MAX_PSNR_DB``: the one place the
    rule is written (callers that pool errors over many views pass their pooled mean here)."""
    mse = float(mse)
    if not math.isfinite(mse) or mse < 0:
        raise OmniscsError(f"mean squared error {mse} is not a finite non-negative number: the images hold NaN or "
                           "Inf pixels; check the render before scoring it")
    if mse <= data_range ** 2 * 10 ** (-MAX_PSNR_DB / 10):
        return MAX_PSNR_DB
    return 10.0 * (2.0 * math.log10(data_range) - math.log10(mse))


def psnr(rendered: Image,  # [..., H, W, C] (C colour channels last), float or uint8
         target: Image,    # same shape
         mask: Image | None = None,  # [..., H, W] bool: the pixels to score; None scores all
         data_range: float = 1.0,    # 1.0 for [0, 1] images, UINT8_RANGE for 8-bit ones
         ) -> float | None:
    """Peak signal-to-noise ratio (dB) over all pixels or over ``mask``; None when the mask is empty. The mean
    runs over pixels, each pixel's squared error averaged over its channels (see the module's edge cases)."""
    r, g = _pair(rendered, target)
    err = (r.clamp(0, data_range) - g).pow(2).mean(-1)
    if mask is not None:
        m = _mask(mask, err.shape)
        if not bool(m.any()):
            return None
        err = err[m]
    return psnr_from_mse(float(err.mean()), data_range)


def _chw(img: Tensor) -> Tensor:  # [H, W, 3] -> [1, 3, H, W]
    return img.permute(2, 0, 1)[None].to(torch.float32)


def ssim_map(rendered: Image, target: Image,  # [H, W, 3] float or uint8
             data_range: float = 1.0) -> Tensor:  # -> [H, W]
    """The SSIM of every pixel's window (kornia, ``SSIM_WINDOW``), averaged over the colour channels; the rendered
    image clipped to ``[0, data_range]`` as for PSNR."""
    r, g = _pair(rendered, target)
    return kornia_ssim(_chw(r.clamp(0, data_range)), _chw(g), SSIM_WINDOW, max_val=data_range)[0].mean(0)


def ssim(rendered: Image, target: Image,  # [H, W, 3] float or uint8
         mask: Image | None = None,       # [H, W] bool
         smap: Tensor | None = None,      # [H, W] ssim_map of the two, when already computed
         data_range: float = 1.0) -> float | None:
    """Mean SSIM over all pixels, or the mean of the SSIM map over ``mask``; None when the mask is empty."""
    smap = ssim_map(rendered, target, data_range) if smap is None else smap
    if mask is not None:
        m = _mask(mask, smap.shape)
        if not bool(m.any()):
            return None
        return float(smap[m].mean())
    return float(smap.mean())
