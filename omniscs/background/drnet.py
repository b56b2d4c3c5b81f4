"""DRNet: relative depth -> absolute depth, trained per scene on the depths the fitted scene graph (or LiDAR) knows.

The architecture is the paper's table (depth refinement network): Conv3-32 LeakyReLU+BN, Conv3-64 LeakyReLU+BN,
spatial attention (CBAM's: channel mean and max -> Conv7 -> sigmoid, multiplying the 64 features),
Conv3-32 LeakyReLU+BN, Conv3-1. Input: the relative depth map of an image (affine-invariant inverse depth, as
Depth Anything gives), normalised per image by the median and the mean absolute deviation over the pixels
outside the hole (the same pixels in the original and the inpainted image, so both maps get the same
normalisation). Output: absolute depth as the Euclidean distance from the camera centre (the paper's psi(pos(G)):
the distance to the ego's camera) divided by the scene's depth scale (the median training target), trained with
the mean squared error over the pixels that have a target.

Training that diverges (a non-finite loss, or a final loss above the first) raises DRNetDiverged: no model is
returned, nothing is saved.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from omniscs.errors import OmniscsError
from omniscs.progress import Progress, no_progress

#: Smallest depth scale (m) and the normalisation's smallest spread (guards flat maps).
MIN_DEPTH_SCALE_M = 0.5
MIN_SPREAD = 1e-6

#: Absolute depths are clamped into this range at inference (metres).
DEPTH_RANGE_M = (0.2, 1000.0)


class DRNetDiverged(OmniscsError):
    """DRNet training blew up; nothing was kept."""


@dataclass(frozen=True)
class DRNetConfig:
    """Per-scene DRNet training."""

    steps: int = 400
    """Adam steps."""
    batch: int = 8
    """Crops per step."""
    crop: int = 96
    """Side of the square crops trained on (pixels; whole views when smaller). The network sees 15 pixels
    around each output pixel, so crops lose nothing but time."""
    lr: float = 2e-3
    """Adam learning rate."""
    negative_slope: float = 0.1
    """LeakyReLU slope."""
    seed: int = 0
    """Seed of initial weights and batch order."""


class SpatialAttention(nn.Module):
    """CBAM spatial attention (Woo et al. 2018): a 7x7 convolution over the channel mean and max, sigmoid, times
    the input."""

    def __init__(self, kernel: int = 7) -> None:
        super().__init__()
        self.conv = nn.Conv2d(2, 1, kernel, padding=kernel // 2, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        pooled = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)
        return x * torch.sigmoid(self.conv(pooled))


class DRNet(nn.Module):
    """The paper's depth refinement network (see module docstring). [B, 1, H, W] -> [B, 1, H, W]."""

    def __init__(self, negative_slope: float = 0.1) -> None:
        super().__init__()

        def block(cin: int, cout: int) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(negative_slope), nn.BatchNorm2d(cout))

        self.body = nn.Sequential(block(1, 32), block(32, 64), SpatialAttention(7), block(64, 32),
                                  nn.Conv2d(32, 1, 3, padding=1))

    def forward(self, x: Tensor) -> Tensor:
        return self.body(x)


def normalise_relative(rel: np.ndarray, known: np.ndarray) -> np.ndarray:  # [H, W], [H, W] bool -> [H, W] float32
    """(rel - median) / mean absolute deviation, both over the ``known`` pixels (all pixels if none is known)."""
    rel = np.nan_to_num(np.asarray(rel, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    vals = rel[known] if known.any() else rel.ravel()
    med = float(np.median(vals))
    spread = max(float(np.mean(np.abs(vals - med))), MIN_SPREAD)
    return ((rel - med) / spread).astype(np.float32)


@dataclass
class FittedDRNet:
    """A DRNet trained for one scene and the depth scale its outputs are in."""

    net: DRNet
    depth_scale: float
    history: list[dict]

    @torch.no_grad()
    def predict(self, rel_normalised: np.ndarray) -> np.ndarray:  # [H, W] -> [H, W] float32 metres
        self.net.eval()
        x = torch.from_numpy(np.ascontiguousarray(rel_normalised, dtype=np.float32))[None, None]
        out = self.net(x)[0, 0].numpy() * self.depth_scale
        return np.clip(np.nan_to_num(out, nan=DEPTH_RANGE_M[1]), *DEPTH_RANGE_M).astype(np.float32)


def train_drnet(inputs: list[np.ndarray],   # per view [H, W] normalised relative depth
                targets: list[np.ndarray],  # per view [H, W] absolute depth (m), NaN where unknown
                config: DRNetConfig = DRNetConfig(), progress: Progress = no_progress) -> FittedDRNet:
    """Train DRNet on views whose pixels with a finite, positive target are supervised (MSE in depth-scale
    units). Views may differ in size (they are batched by size)."""
    if len(inputs) != len(targets) or not inputs:
        raise OmniscsError("DRNet needs at least one view, with one target map per input map")
    valid = [np.isfinite(t) & (t > 0) for t in targets]
    n_valid = sum(int(v.sum()) for v in valid)
    if n_valid == 0:
        raise OmniscsError("no pixel outside the hole has a depth (no projected Gaussian centre and no LiDAR "
                           "return): DRNet cannot be trained; fit the scene with LiDAR or more background")
    for x, t in zip(inputs, targets):
        if x.shape != t.shape or not np.all(np.isfinite(x)):
            raise OmniscsError("DRNet inputs must be finite and the size of their targets")
    depth_scale = max(MIN_DEPTH_SCALE_M, float(np.median(np.concatenate([t[v] for t, v in zip(targets, valid)]))))
    gen = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    net = DRNet(config.negative_slope)
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    usable = [i for i in range(len(inputs)) if valid[i].any()]
    xs = [torch.from_numpy(np.ascontiguousarray(inputs[i], np.float32)) for i in usable]
    ts = [torch.from_numpy(np.where(valid[i], targets[i] / depth_scale, 0.0).astype(np.float32)) for i in usable]
    ms = [torch.from_numpy(valid[i]) for i in usable]
    history: list[dict] = []
    first = None
    net.train()
    for step in range(config.steps):
        h = min(config.crop, min(x.shape[0] for x in xs))
        w = min(config.crop, min(x.shape[1] for x in xs))
        batch = []
        for _ in range(max(2, config.batch)):  # BatchNorm needs more than one sample
            i = int(torch.randint(len(xs), (1,), generator=gen))
            y0 = int(torch.randint(xs[i].shape[0] - h + 1, (1,), generator=gen))
            x0 = int(torch.randint(xs[i].shape[1] - w + 1, (1,), generator=gen))
            batch.append((xs[i][y0:y0 + h, x0:x0 + w], ts[i][y0:y0 + h, x0:x0 + w], ms[i][y0:y0 + h, x0:x0 + w]))
        x = torch.stack([b[0] for b in batch])[:, None]
        t = torch.stack([b[1] for b in batch])[:, None]
        m = torch.stack([b[2] for b in batch])[:, None]
        if not bool(m.any()):
            continue
        pred = net(x)
        loss = ((pred - t)[m] ** 2).mean()
        value = float(loss.detach())
        if not math.isfinite(value):
            raise DRNetDiverged(f"DRNet training diverged at step {step} (loss {value}); nothing was kept")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        first = value if first is None else first
        if step % 25 == 0 or step == config.steps - 1:
            history.append({"step": step, "mse": value})
            progress(step + 1, config.steps, f"DRNet mse {value:.4f}")
    if not all(math.isfinite(float(p.detach().abs().max())) for p in net.parameters()):
        raise DRNetDiverged("DRNet weights became NaN or infinite; nothing was kept")
    last = float(np.mean([h["mse"] for h in history[-3:]])) if history else math.inf
    if first is None or (config.steps > 50 and last > first):
        raise DRNetDiverged(f"DRNet training did not converge (final mse {last:.4g} above the first {first:.4g}); "
                            "nothing was kept")
    return FittedDRNet(net, depth_scale, history)


def least_squares_depth(rel: np.ndarray,     # [H, W] relative inverse depth of the image
                        target: np.ndarray,  # [H, W] absolute depth (m), NaN where unknown
                        ) -> np.ndarray:     # [H, W] float32 metres
    """The baseline: scale and shift s, b minimising sum (s rel + b - 1/target)^2 over the pixels with a target
    (relative depth is inverse depth up to an affine map), then depth = 1 / (s rel + b), clamped."""
    valid = np.isfinite(target) & (target > 0)
    if not valid.any():
        raise OmniscsError("no pixel outside the hole has a depth: the least-squares alignment has nothing to fit")
    r = np.asarray(rel, dtype=np.float64)
    A = np.stack([r[valid], np.ones(int(valid.sum()))], 1)
    s, b = np.linalg.lstsq(A, 1.0 / target[valid].astype(np.float64), rcond=None)[0]
    inv = s * r + b
    inv = np.where(np.isfinite(inv), inv, 0.0)
    lo, hi = DEPTH_RANGE_M
    return np.clip(1.0 / np.maximum(inv, 1.0 / hi), lo, hi).astype(np.float32)
