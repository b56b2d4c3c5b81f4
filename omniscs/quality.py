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
import torch.nn.functional as F
from kornia.filters import get_gaussian_kernel1d
from kornia.metrics import ssim as kornia_ssim
from torch import Tensor

from omniscs._ssim import FusedSSIMLoss
from omniscs.errors import OmniscsError

#: PSNR (dB) reported for identical images instead of +inf.
MAX_PSNR_DB = 100.0

#: SSIM window (pixels), the usual 11x11 Gaussian window.
SSIM_WINDOW = 11

#: Standard deviation (pixels) of the SSIM window's Gaussian, kornia's and the SSIM paper's.
SSIM_SIGMA = 1.5
#: SSIM's stabilising constants, as fractions of the data range (SSIM paper: K1, K2).
SSIM_K1, SSIM_K2 = 0.01, 0.03
#: Added to SSIM's denominator (kornia's default), so two flat black images score 1, not NaN.
SSIM_EPS = 1e-12

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


def ssim_loss(rendered: Tensor,  # [B, C, H, W], differentiable
              target: Tensor,    # [B, C, H, W]
              window: int,       # odd, less than twice the smaller side
              data_range: float = 1.0) -> Tensor:  # -> [] mean of clamp((1 - SSIM) / 2, 0, 1)
    """The structural dissimilarity a fit trains with: kornia's ``ssim_loss`` (reflect padding, a Gaussian window
    of sigma ``SSIM_SIGMA``), the same value, with gradients equal to rounding. kornia pads and filters each of the
    five moments (x, y, x², y², xy) on its own; here each image is padded once and the five moments are filtered
    by one grouped separable convolution: a fit step's SSIM forward+backward is 1.6x (120x68) to 2.4x (240x135)
    faster on the CPU. A single float32 CPU image pair (a fit step) goes through ``omniscs._ssim``'s fused passes
    instead, which accumulate in float64."""
    if window < 1 or window % 2 == 0:
        raise OmniscsError(f"ssim_loss: the window must be a positive odd number of pixels, got {window}")
    if (rendered.device.type == "cpu" and rendered.dtype == torch.float32 and rendered.dim() == 4
            and rendered.shape[0] == 1 and target.shape == rendered.shape and window // 2 < min(rendered.shape[2:])):
        # a fit step's case: the fused Numba passes (omniscs._ssim), held to the code below by the tests
        kernel = get_gaussian_kernel1d(window, SSIM_SIGMA, dtype=torch.float64)[0].numpy()
        return FusedSSIMLoss.apply(rendered, target.to(torch.float32), kernel, (SSIM_K1 * data_range) ** 2,
                                   (SSIM_K2 * data_range) ** 2, SSIM_EPS)
    return _ssim_loss_torch(rendered, target, window, data_range)


def _ssim_loss_torch(rendered: Tensor, target: Tensor, window: int, data_range: float = 1.0) -> Tensor:
    """``ssim_loss`` in PyTorch operations: its definition, and its code for other devices and types."""
    channels = rendered.shape[1]
    kernel = get_gaussian_kernel1d(window, SSIM_SIGMA, device=rendered.device, dtype=rendered.dtype)[0]  # [k]
    pad = window // 2
    x = F.pad(rendered, (pad, pad, pad, pad), mode="reflect")
    y = F.pad(target.to(rendered.dtype), (pad, pad, pad, pad), mode="reflect")
    moments = torch.cat([x, y, x * x, y * y, x * y], 1)                 # [B, 5C, H + 2 pad, W + 2 pad]
    n = moments.shape[1]
    filtered = F.conv2d(moments, kernel.view(1, 1, 1, window).expand(n, 1, 1, window), groups=n)
    filtered = F.conv2d(filtered, kernel.view(1, 1, window, 1).expand(n, 1, window, 1), groups=n)
    mu_x, mu_y, e_xx, e_yy, e_xy = filtered.split(channels, 1)          # [B, C, H, W] each
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    numerator = (2.0 * mu_xy + c1) * (2.0 * (e_xy - mu_xy) + c2)
    denominator = (mu_xx + mu_yy + c1) * ((e_xx - mu_xx) + (e_yy - mu_yy) + c2)
    similarity = numerator / (denominator + SSIM_EPS)
    return torch.clamp((1.0 - similarity) / 2.0, 0.0, 1.0).mean()


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
