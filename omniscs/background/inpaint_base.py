"""What every 2D inpainter shares (``omniscs.background.inpaint``'s adapters and the embedded network of
``omniscs.background.inpaintnet``): checking the image and mask, compositing the fill into the hole only, and
turning a model's float output into pixels without passing NaN on."""
from __future__ import annotations

import numpy as np

from omniscs.errors import OmniscsError


def check_image_and_mask(rgb: np.ndarray, mask: np.ndarray) -> None:
    """Raise an OmniscsError unless rgb is an [H, W, 3] uint8 array and mask an [H, W] bool array of the same size."""
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        shape = getattr(rgb, "shape", type(rgb).__name__)
        raise OmniscsError(f"the image to inpaint must be an [H, W, 3] RGB numpy array; got {shape}")
    if rgb.dtype != np.uint8:
        raise OmniscsError(f"the image to inpaint must be uint8 (0..255); got {rgb.dtype}: convert it first")
    if not isinstance(mask, np.ndarray) or mask.ndim != 2:
        shape = getattr(mask, "shape", type(mask).__name__)
        raise OmniscsError(f"the inpainting mask must be an [H, W] numpy array; got {shape}")
    if mask.dtype != np.bool_:
        raise OmniscsError(f"the inpainting mask must be bool (True = fill this pixel); got {mask.dtype}: "
                           "pass mask.astype(bool) or a comparison such as mask > 0")
    if mask.shape != rgb.shape[:2]:
        raise OmniscsError(f"the inpainting mask is {mask.shape[0]}x{mask.shape[1]} (HxW) but the image is "
                           f"{rgb.shape[0]}x{rgb.shape[1]}: they must be the same size")


class HoleFiller:
    """Shared inpaint(): validate, skip empty masks, refuse full ones, let the subclass fill, composite."""

    def _fill(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:  # [H, W, 3] uint8 (contiguous), [H, W] bool
        """The method's full-frame result, [H, W, 3] uint8; only its pixels inside the mask are kept."""
        raise NotImplementedError

    def inpaint(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """rgb [H, W, 3] uint8 with the pixels where mask [H, W] bool is True filled; all others exactly rgb."""
        check_image_and_mask(rgb, mask)
        if not mask.any():
            return rgb.copy()
        if mask.all():
            raise OmniscsError(f"the inpainting mask covers all {mask.size} pixels: there is nothing to inpaint "
                               "from; mark only the pixels to fill (True) and keep some known pixels (False)")
        filled = self._fill(np.ascontiguousarray(rgb), mask)
        if filled.shape != rgb.shape or filled.dtype != np.uint8:
            raise OmniscsError(f"inpainter {self.name!r} returned {filled.shape} {filled.dtype}, expected "
                               f"{rgb.shape} uint8: the model or export does not fit this adapter")
        out = rgb.copy()
        out[mask] = filled[mask]
        return out

    @property
    def name(self) -> str:  # overridden by every inpainter
        raise NotImplementedError


def unit_float_to_uint8(image: np.ndarray, what: str) -> np.ndarray:
    """[..., 3] float in [0, 1] (a model's output) as uint8; a non-finite value is an error, never passed on."""
    if not np.isfinite(image).all():
        raise OmniscsError(f"{what} returned NaN or Inf pixels: the weights are broken or do not fit this "
                           "adapter; check the model file")
    return np.rint(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
