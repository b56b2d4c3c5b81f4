"""The degradations a scene's road users suffer in the logged images, for training MSNet and benchmarking matching:
downsampling (distance), an illumination gain and gamma, an occluding block, blur, noise and JPEG compression."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from omniscs.errors import ValidationError


@dataclass(frozen=True)
class Degradation:
    """How badly a crop is seen: downsampling factor, illumination gain and gamma, occluded share of the crop,
    blur sigma (px), noise sigma (0..255), JPEG quality (None: no compression)."""

    downsample: float = 1.0
    gain: float = 1.0
    gamma: float = 1.0
    occlusion: float = 0.0
    blur: float = 0.0
    noise: float = 0.0
    jpeg: int | None = None

    def __post_init__(self):
        if not (self.downsample >= 1 and self.gain > 0 and self.gamma > 0 and 0 <= self.occlusion < 1
                and self.blur >= 0 and self.noise >= 0 and (self.jpeg is None or 1 <= self.jpeg <= 100)):
            raise ValidationError(f"bad degradation {self}")


def degrade(rgb: np.ndarray, d: Degradation, rng: np.random.Generator) -> np.ndarray:  # uint8 [H, W, 3] -> same
    """``rgb`` as a distant, badly lit, partly hidden, blurred, noisy, compressed observation (same size)."""
    h, w = rgb.shape[:2]
    img = rgb.astype(np.float32) / 255.0
    if d.downsample > 1:
        small = cv2.resize(img, (max(1, round(w / d.downsample)), max(1, round(h / d.downsample))),
                           interpolation=cv2.INTER_AREA)
        img = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    img = np.clip(d.gain * np.power(np.clip(img, 0, 1), d.gamma), 0, 1)
    if d.blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), d.blur)
    if d.occlusion > 0:  # a block of another colour over one side (what a parked car in front hides)
        side = rng.integers(4)
        frac = d.occlusion
        fill = rng.uniform(0.1, 0.6, 3).astype(np.float32)
        if side == 0:
            img[:, :round(w * frac)] = fill
        elif side == 1:
            img[:, w - round(w * frac):] = fill
        elif side == 2:
            img[h - round(h * frac):] = fill
        else:
            img[:round(h * frac)] = fill
    if d.noise > 0:
        img = img + rng.normal(0, d.noise / 255.0, img.shape).astype(np.float32)
    out = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    if d.jpeg is not None:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(d.jpeg)])
        out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if ok else out
    return out
