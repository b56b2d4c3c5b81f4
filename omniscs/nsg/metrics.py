"""Old home of PSNR / SSIM, kept only for the benchmarks in omniscs/bench/ that still import it and count an empty
mask as NaN; new code imports omniscs.quality (where an empty mask gives None). Delete this module once bench/
imports omniscs.quality."""
from __future__ import annotations

from torch import Tensor

from omniscs import quality
from omniscs.quality import MAX_PSNR_DB, SSIM_WINDOW, ssim_map

__all__ = ["MAX_PSNR_DB", "SSIM_WINDOW", "psnr", "ssim", "ssim_map"]


def _nan_if_none(value: float | None) -> float:
    return float("nan") if value is None else value


def psnr(rendered: Tensor, target: Tensor, mask: Tensor | None = None) -> float:  # [H, W, 3], [H, W] bool
    """``omniscs.quality.psnr`` with NaN for an empty mask (the benchmarks' old contract)."""
    return _nan_if_none(quality.psnr(rendered, target, mask))


def ssim(rendered: Tensor, target: Tensor, mask: Tensor | None = None, smap: Tensor | None = None) -> float:
    """``omniscs.quality.ssim`` with NaN for an empty mask (the benchmarks' old contract)."""
    return _nan_if_none(quality.ssim(rendered, target, mask, smap))
