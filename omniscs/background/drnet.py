"""DRNet: relative depth -> absolute depth, trained per scene on the depths the fitted scene graph (or LiDAR) knows.

The architecture is the paper's table (depth refinement network): Conv3-32 LeakyReLU+BN, Conv3-64 LeakyReLU+BN,
spatial attention (CBAM's: channel mean and max -> Conv7 -> sigmoid, multiplying the 64 features),
Conv3-32 LeakyReLU+BN, Conv3-1. Input: the relative depth map of an image (affine-invariant inverse depth, as
Depth Anything gives) with its affine ambiguity fixed per image by the least-squares scale and shift to the known
depths outside the hole (``aligned_inverse``; the least-squares baseline stops there), times the scene's depth
scale (the median training target) so it is dimensionless. Output: absolute depth as the Euclidean distance from
the camera centre (the paper's psi(pos(G)): the distance to the ego's camera) divided by that scale, trained with
the mean squared error over the pixels that have a target. DRNet so learns, per scene, what the per-image affine
map cannot: the non-linear, local relation between the network's relative depth and the scene's metric depth.

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

#: Inputs (aligned depth / depth scale) are capped at this ratio; training targets beyond it are not used.
MAX_INPUT_RATIO = 4.0

#: Batches of crops whose average BatchNorm statistics DRNet keeps for inference.
RECALIBRATION_BATCHES = 50

#: Absolute depths are clamped into this range at inference (metres).
DEPTH_RANGE_M = (0.2, 1000.0)


class DRNetDiverged(OmniscsError):
    """DRNet training blew up; nothing was kept."""


@dataclass(frozen=True)
class DRNetConfig:
    """Per-scene DRNet training."""

    steps: int = 300
    """Adam steps."""
    batch: int = 8
    """Crops per step."""
    crop: int = 64
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


def _network_input(inverse: np.ndarray, depth_scale: float) -> np.ndarray:  # [H, W] -> [H, W] float32
    """The aligned map as depth in units of the scene's depth scale, capped at MAX_INPUT_RATIO (sky, far)."""
    ratio = 1.0 / np.maximum(np.asarray(inverse, np.float64) * depth_scale, 1.0 / MAX_INPUT_RATIO)
    return np.ascontiguousarray(ratio, dtype=np.float32)


@dataclass
class FittedDRNet:
    """A DRNet trained for one scene and the depth scale its outputs are in."""

    net: DRNet
    depth_scale: float
    history: list[dict]

    @torch.no_grad()
    def predict(self, inverse: np.ndarray) -> np.ndarray:  # [H, W] aligned inverse depth (1/m) -> [H, W] metres
        self.net.eval()
        x = torch.from_numpy(_network_input(inverse, self.depth_scale))[None, None]
        out = self.net(x)[0, 0].numpy() * self.depth_scale
        return np.clip(np.nan_to_num(out, nan=DEPTH_RANGE_M[1]), *DEPTH_RANGE_M).astype(np.float32)


def train_drnet(inputs: list[np.ndarray],   # per view [H, W] aligned inverse depth (1/m, ``aligned_inverse``)
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
    valid = [v & (np.nan_to_num(t, nan=0.0) <= MAX_INPUT_RATIO * depth_scale) for t, v in zip(targets, valid)]
    gen = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    net = DRNet(config.negative_slope)
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    usable = [i for i in range(len(inputs)) if valid[i].any()]
    xs = [torch.from_numpy(_network_input(inputs[i], depth_scale)) for i in usable]
    ts = [torch.from_numpy(np.where(valid[i], targets[i] / depth_scale, 0.0).astype(np.float32)) for i in usable]
    ms = [torch.from_numpy(valid[i]) for i in usable]
    history: list[dict] = []
    first = None
    net.train()
    for step in range(config.steps):
        x, t, m = _crops([xs, ts, ms], max(2, config.batch), config.crop, gen)  # BatchNorm needs two or more
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
    _recalibrate_batchnorm(net, xs, RECALIBRATION_BATCHES, max(2, config.batch), config.crop, gen)
    if not all(math.isfinite(float(p.detach().abs().max())) for p in net.parameters()):
        raise DRNetDiverged("DRNet weights became NaN or infinite; nothing was kept")
    last = float(np.mean([h["mse"] for h in history[-3:]])) if history else math.inf
    if first is None or (config.steps > 50 and last > first):
        raise DRNetDiverged(f"DRNet training did not converge (final mse {last:.4g} above the first {first:.4g}); "
                            "nothing was kept")
    return FittedDRNet(net, depth_scale, history)


def aligned_inverse(rel: np.ndarray,     # [H, W] relative inverse depth of the image
                    target: np.ndarray,  # [H, W] absolute depth (m), NaN where unknown
                    ) -> np.ndarray:     # [H, W] float32 inverse depth (1/m), >= 0
    """The scale and shift s, b minimising sum (s rel + b - 1/target)^2 over the pixels with a target (relative
    depth is inverse depth up to an affine map), applied to every pixel; clamped at 0 (infinitely far)."""
    valid = np.isfinite(target) & (target > 0)
    if not valid.any():
        raise OmniscsError("no pixel outside the hole has a depth: the least-squares alignment has nothing to fit")
    r = np.nan_to_num(np.asarray(rel, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    A = np.stack([r[valid], np.ones(int(valid.sum()))], 1)
    s, b = np.linalg.lstsq(A, 1.0 / target[valid].astype(np.float64), rcond=None)[0]
    inv = s * r + b
    return np.clip(np.where(np.isfinite(inv), inv, 0.0), 0.0, 1.0 / DEPTH_RANGE_M[0]).astype(np.float32)


def _crops(maps: list[list[Tensor]], n: int, crop: int, gen: torch.Generator) -> list[Tensor]:
    """``n`` random square crops (the same windows in each list of [H, W] maps), stacked as [n, 1, c, c]."""
    h = min(crop, min(x.shape[0] for x in maps[0]))
    w = min(crop, min(x.shape[1] for x in maps[0]))
    picks = []
    for _ in range(n):
        i = int(torch.randint(len(maps[0]), (1,), generator=gen))
        y0 = int(torch.randint(maps[0][i].shape[0] - h + 1, (1,), generator=gen))
        x0 = int(torch.randint(maps[0][i].shape[1] - w + 1, (1,), generator=gen))
        picks.append((i, y0, x0))
    return [torch.stack([m[i][y0:y0 + h, x0:x0 + w] for i, y0, x0 in picks])[:, None] for m in maps]


@torch.no_grad()
def _recalibrate_batchnorm(net: DRNet, xs: list[Tensor], batches: int, n: int, crop: int,
                           gen: torch.Generator) -> None:
    """Replace the BatchNorm running statistics (an exponential average of the last noisy batches) by their
    plain average over ``batches`` fresh batches of crops, so evaluation normalises as training did."""
    norms = [m for m in net.modules() if isinstance(m, nn.BatchNorm2d)]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average
    net.train()
    for _ in range(batches):
        net(_crops([xs], n, crop, gen)[0])
    for m in norms:
        m.momentum = 0.1
    net.eval()


def least_squares_depth(rel: np.ndarray, target: np.ndarray) -> np.ndarray:  # -> [H, W] float32 metres
    """The baseline: depth = 1 / ``aligned_inverse``, clamped to DEPTH_RANGE_M."""
    inv = aligned_inverse(rel, target).astype(np.float64)
    lo, hi = DEPTH_RANGE_M
    return np.clip(1.0 / np.maximum(inv, 1.0 / hi), lo, hi).astype(np.float32)
