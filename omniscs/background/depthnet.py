"""The embedded relative-depth network: a compact U-Net from an RGB image to affine-invariant inverse depth, the
scale-and-shift-invariant loss it learns with, its augmentations and its training loop (arrays and tensors only).

Output convention (as Depth Anything's): inverse depth up to an unknown scale > 0 and shift, larger = nearer.

Loss (Ranftl et al. 2020, "Towards Robust Monocular Depth Estimation", MiDaS): per image the target inverse depth is
normalised (minus its median, over its mean absolute deviation), the prediction is aligned to it by the
least-squares scale (its magnitude: the convention larger = nearer is part of what is learned) and shift over the
valid pixels, and the loss is the mean absolute residual plus
``grad_weight`` times the multi-scale gradient-matching term (L1 of the residual's finite differences at
``grad_scales`` power-of-two subsamplings). Sky pixels are kept as targets with inverse depth 0 (infinitely far),
so the network learns that sky is the farthest thing in the image; only pixels marked invalid (padding, the
unknowable inside of a randomly inpainted patch) are left out of the loss.
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from omniscs.errors import OmniscsError, ValidationError
from omniscs.pretrained.registry import verified_folder
from omniscs.progress import Progress, no_progress
from omniscs.storage import atomic_directory
from omniscs.untrusted import read_own_json

#: RGB normalisation of the network's input (after scaling to 0..1): mean and spread of road scenes, roughly.
RGB_MEAN = 0.45
RGB_STD = 0.25

#: Guards of the per-image normalisation and alignment against flat targets and constant predictions.
MIN_TARGET_SPREAD = 1e-6
MIN_PREDICTION_VARIANCE = 1e-8


@dataclass(frozen=True)
class DepthNetConfig:
    """The architecture of the embedded relative-depth network (stored in ``training.json`` beside its weights)."""

    widths: tuple[int, ...] = (32, 64, 96, 128, 192)
    """Channels of the U-Net's levels, full resolution first; each further level halves the resolution (the shipped
    network: 1.69 M parameters; the first one, (16, 24, 32, 40, 56) with 0.17 M trained for 800 steps, reached a
    held-out AbsRel of 0.218 against 0.072)."""
    long_side: int = 256
    """Working resolution: an image is resized so that its longer side has this many pixels (then padded)."""

    @property
    def multiple(self) -> int:
        """The working image's sides are padded up to a multiple of this (one halving per level below the first)."""
        return 2 ** (len(self.widths) - 1)


def _conv_block(c_in: int, c_out: int, n: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(n):
        layers += [nn.Conv2d(c_in if i == 0 else c_out, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out),
                   nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class DepthNet(nn.Module):
    """U-Net: one 3x3 block at full resolution, two per lower level (max-pool between levels), bilinear upsampling
    and one 3x3 block per decoder level over [upsampled, skip], a 3x3 head to one channel. The input gets a fourth
    channel, the image row from -1 (top of the content) to +1 (its bottom row), because in a road scene the row
    says much about depth and zero padding alone hides it from a small network."""

    def __init__(self, config: DepthNetConfig = DepthNetConfig()) -> None:
        super().__init__()
        if len(config.widths) < 2 or min(config.widths) < 1:
            raise OmniscsError(f"DepthNet needs at least two levels of positive widths; got {config.widths}")
        w = config.widths
        self.config = config
        self.encoder = nn.ModuleList([_conv_block(4 if i == 0 else w[i - 1], w[i], 1 if i == 0 else 2)
                                      for i in range(len(w))])
        self.decoder = nn.ModuleList([_conv_block(w[i + 1] + w[i], w[i], 1) for i in reversed(range(len(w) - 1))])
        self.head = nn.Conv2d(w[0], 1, 3, padding=1)

    def forward(self, rgb: Tensor,  # [B, 3, H, W] in 0..1, H and W multiples of config.multiple
                content_height: int | None = None,  # rows of real image content (the rest is padding)
                ) -> Tensor:  # [B, H, W] relative inverse depth
        b, _, h, w = rgb.shape
        rows = h if content_height is None else int(content_height)
        row = torch.arange(h, dtype=rgb.dtype, device=rgb.device) * (2.0 / max(rows - 1, 1)) - 1.0
        x = torch.cat([(rgb - RGB_MEAN) / RGB_STD, row.view(1, 1, h, 1).expand(b, 1, h, w)], 1)
        skips = []
        for i, block in enumerate(self.encoder):
            if i:
                x = nn.functional.max_pool2d(x, 2)
            x = block(x)
            skips.append(x)
        for block, skip in zip(self.decoder, reversed(skips[:-1])):
            x = nn.functional.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], 1))
        return self.head(x)[:, 0]


def working_size(height: int, width: int, long_side: int) -> tuple[int, int]:
    """(h, w) of an image of ``height`` x ``width`` resized so that its longer side is ``long_side`` (each >= 1)."""
    scale = long_side / max(height, width)
    return max(1, round(height * scale)), max(1, round(width * scale))


def network_input(rgb: np.ndarray,  # [H, W, 3] uint8
                  config: DepthNetConfig,
                  ) -> tuple[Tensor, tuple[int, int]]:  # [1, 3, Hp, Wp] in 0..1, (h, w) of the content in it
    """The image at the working resolution (area-averaged when shrinking, bilinear when growing), padded at the
    bottom and right by repeating the border up to a multiple of ``config.multiple``."""
    height, width = rgb.shape[:2]
    h, w = working_size(height, width, config.long_side)
    shrink = h * w < height * width
    image = cv2.resize(np.ascontiguousarray(rgb), (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    if image.ndim == 2:  # cv2 drops the channel axis of 1-pixel-wide results in some versions
        image = image[..., None].repeat(3, -1)
    m = config.multiple
    pad_h, pad_w = -h % m, -w % m
    image = np.pad(image, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    return torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0, (h, w)


@torch.no_grad()
def predict_inverse_depth(net: DepthNet, rgb: np.ndarray,  # [H, W, 3] uint8
                          ) -> np.ndarray:  # [H, W] float32 relative inverse depth
    """Run ``net`` (in eval mode) at its working resolution and resize the result back to the image (bilinear)."""
    height, width = rgb.shape[:2]
    x, (h, w) = network_input(rgb, net.config)
    device = next(net.parameters()).device
    out = net.eval()(x.to(device), content_height=h)[0, :h, :w].float().cpu().numpy()
    out = cv2.resize(out, (width, height), interpolation=cv2.INTER_LINEAR)
    if out.ndim == 1 or out.shape != (height, width):
        out = out.reshape(height, width)
    if not np.isfinite(out).all():
        raise OmniscsError("the relative-depth network produced non-finite values; its weights are damaged: "
                           "retrain them with `omniscs pretrained train reldepth`")
    return out.astype(np.float32)


# ----------------------------------------------------------------------------- loss
def scale_shift_align(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Least-squares (scale, shift) with ``scale * pred + shift ~ target`` over ``mask`` (arrays of one shape;
    float64 arithmetic). A constant prediction gets scale 0 and the target's mean as shift."""
    p = np.asarray(pred, np.float64)[mask]
    t = np.asarray(target, np.float64)[mask]
    if p.size == 0:
        raise OmniscsError("cannot align relative depth: no valid pixel; pass a mask that selects some pixels")
    pm, tm = p.mean(), t.mean()
    var = float(np.mean((p - pm) ** 2))
    scale = float(np.mean((p - pm) * (t - tm)) / var) if var > MIN_PREDICTION_VARIANCE else 0.0
    return scale, float(tm - scale * pm)


def normalise_target(target: Tensor, valid: Tensor) -> Tensor:  # [B, H, W], [B, H, W] bool -> [B, H, W]
    """Per image: minus the median over valid pixels, divided by the mean absolute deviation from it."""
    out = []
    for t, v in zip(target, valid):
        tv = t[v]
        if tv.numel() == 0:
            out.append(torch.zeros_like(t))
            continue
        med = tv.median()
        spread = (tv - med).abs().mean().clamp_min(MIN_TARGET_SPREAD)
        out.append((t - med) / spread)
    return torch.stack(out)


def ssi_loss(pred: Tensor,    # [B, H, W] raw network output
             target: Tensor,  # [B, H, W] ground-truth inverse depth (0 = sky)
             valid: Tensor,   # [B, H, W] bool: pixels that count
             grad_weight: float = 0.5, grad_scales: int = 4) -> Tensor:  # scalar
    """The scale-and-shift-invariant loss of the module docstring (mean over images that have valid pixels)."""
    target = normalise_target(target, valid)
    m = valid.to(pred.dtype)
    n = m.sum((1, 2)).clamp_min(1.0)
    pm = (pred * m).sum((1, 2)) / n
    tm = (target * m).sum((1, 2)) / n
    pc, tc = (pred - pm[:, None, None]) * m, (target - tm[:, None, None]) * m
    var = (pc * pc).sum((1, 2)) / n
    # |scale|: the least-squares scale may come out negative (an output that is depth rather than inverse depth fits
    # as well with the sign flipped); taking its magnitude makes such an output cost more than a constant one, so
    # the network learns the convention (larger = nearer) and the gradient never vanishes as it would at a clamp.
    scale = ((pc * tc).sum((1, 2)) / n / (var + MIN_PREDICTION_VARIANCE)).abs()
    shift = tm - scale * pm
    residual = (scale[:, None, None] * pred + shift[:, None, None] - target) * m
    loss = residual.abs().sum((1, 2)) / n
    for k in range(grad_scales if grad_weight > 0 else 0):
        step = 2 ** k
        r, mk = residual[:, ::step, ::step], m[:, ::step, ::step]
        gx = (r[:, :, 1:] - r[:, :, :-1]).abs() * mk[:, :, 1:] * mk[:, :, :-1]
        gy = (r[:, 1:] - r[:, :-1]).abs() * mk[:, 1:] * mk[:, :-1]
        loss = loss + grad_weight * (gx.sum((1, 2)) + gy.sum((1, 2))) / mk.sum((1, 2)).clamp_min(1.0)
    has = valid.flatten(1).any(1)
    return loss[has].mean() if has.any() else pred.sum() * 0.0


# ----------------------------------------------------------------------------- augmentation
@dataclass(frozen=True)
class DepthAugmentConfig:
    """Random changes of a training image so that the network copes with other cameras, light and, above all,
    images whose hole was filled by a classical inpainter (smooth, blurry patches)."""

    flip_prob: float = 0.5
    """Probability of a horizontal flip (image and target)."""
    crop_prob: float = 0.3
    """Probability of a random crop scaled back to the full canvas (a zoom)."""
    crop_min_scale: float = 0.75
    """Smallest side of such a crop, as a fraction of the canvas side."""
    brightness: float = 0.3
    """Gain factor drawn from [1 - brightness, 1 + brightness]."""
    contrast: float = 0.3
    """Contrast factor (about the image mean) from [1 - contrast, 1 + contrast]."""
    saturation: float = 0.4
    """Saturation factor (about the grey value) from [1 - saturation, 1 + saturation]."""
    channel_gain: float = 0.08
    """Per-channel gain (white balance) from [1 - channel_gain, 1 + channel_gain]."""
    gamma: float = 0.3
    """Gamma exponent from [1 - gamma, 1 + gamma]."""
    noise_std: float = 4.0
    """Largest standard deviation of additive Gaussian pixel noise (8-bit levels)."""
    blur_prob: float = 0.15
    """Probability of blurring the whole image (a soft or small camera)."""
    patch_prob: float = 0.5
    """Probability of adding one to three smoothed patches (blurred, or inpainted with their inside left out of the
    loss), each an ellipse or a rectangle."""
    patch_max_fraction: float = 0.2
    """Largest area of one patch as a fraction of the image."""


def _patch_mask(h: int, w: int, max_fraction: float, rng: np.random.Generator) -> np.ndarray:  # [h, w] uint8 0/1
    area = rng.uniform(0.01, max_fraction) * h * w
    aspect = rng.uniform(0.5, 2.0)
    ph = int(np.clip(np.sqrt(area / aspect), 2, h - 1))
    pw = int(np.clip(area / ph, 2, w - 1))
    y0, x0 = int(rng.integers(0, h - ph + 1)), int(rng.integers(0, w - pw + 1))
    mask = np.zeros((h, w), np.uint8)
    if rng.random() < 0.5:
        mask[y0:y0 + ph, x0:x0 + pw] = 1
    else:
        cv2.ellipse(mask, (x0 + pw // 2, y0 + ph // 2), (max(1, pw // 2), max(1, ph // 2)), 0.0, 0.0, 360.0, 1, -1)
    return mask


def augment(rgb: np.ndarray,    # [H, W, 3] uint8
            inv: np.ndarray,    # [H, W] float32 target inverse depth
            valid: np.ndarray,  # [H, W] bool
            config: DepthAugmentConfig, rng: np.random.Generator,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # same shapes and dtypes
    """One random augmentation of a training sample (see DepthAugmentConfig)."""
    h, w = inv.shape
    if rng.random() < config.crop_prob:
        s = rng.uniform(config.crop_min_scale, 1.0)
        ch, cw = max(2, int(round(h * s))), max(2, int(round(w * s)))
        y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        rgb = cv2.resize(rgb[y0:y0 + ch, x0:x0 + cw], (w, h), interpolation=cv2.INTER_LINEAR)
        inv = cv2.resize(inv[y0:y0 + ch, x0:x0 + cw], (w, h), interpolation=cv2.INTER_LINEAR)
        valid = cv2.resize(valid[y0:y0 + ch, x0:x0 + cw].astype(np.uint8), (w, h),
                           interpolation=cv2.INTER_NEAREST).astype(bool)
    if rng.random() < config.flip_prob:
        rgb, inv, valid = rgb[:, ::-1], inv[:, ::-1], valid[:, ::-1]
    rgb, inv, valid = np.ascontiguousarray(rgb), np.ascontiguousarray(inv), np.ascontiguousarray(valid)
    if rng.random() < config.patch_prob:
        for _ in range(int(rng.integers(1, 4))):
            mask = _patch_mask(h, w, config.patch_max_fraction, rng)
            if rng.random() < 0.5:
                sigma = rng.uniform(1.5, 5.0)
                blurred = cv2.GaussianBlur(rgb, (0, 0), sigma)
                rgb = np.where(mask[..., None] > 0, blurred, rgb)
            else:
                flags = cv2.INPAINT_TELEA if rng.random() < 0.5 else cv2.INPAINT_NS
                rgb = cv2.inpaint(rgb, mask, 3, flags)
                valid = valid & (mask == 0)
    if rng.random() < config.blur_prob:
        rgb = cv2.GaussianBlur(rgb, (0, 0), rng.uniform(0.5, 1.5))
    x = rgb.astype(np.float32) / 255.0
    x = x ** rng.uniform(1.0 - config.gamma, 1.0 + config.gamma)
    x = x * rng.uniform(1.0 - config.brightness, 1.0 + config.brightness)
    x = x * rng.uniform(1.0 - config.channel_gain, 1.0 + config.channel_gain, 3).astype(np.float32)
    mean = x.mean()
    x = (x - mean) * rng.uniform(1.0 - config.contrast, 1.0 + config.contrast) + mean
    grey = x.mean(-1, keepdims=True)
    x = (x - grey) * rng.uniform(1.0 - config.saturation, 1.0 + config.saturation) + grey
    x = x * 255.0 + rng.normal(0.0, rng.uniform(0.0, config.noise_std), x.shape).astype(np.float32)
    return np.clip(x, 0.0, 255.0).round().astype(np.uint8), inv.astype(np.float32), valid


# ----------------------------------------------------------------------------- training
@dataclass(frozen=True)
class DepthTrainConfig:
    """Training of the embedded relative-depth network (AdamW, one-cycle learning rate, the SSI loss)."""

    steps: int = 12_000
    """Optimiser steps (the shipped weights: 6.3 min on one H100 with 14 augmenting workers; on 2 CPUs the same
    training takes many hours)."""
    batch: int = 16
    """Images per step."""
    lr: float = 2e-3
    """Peak learning rate of the one-cycle schedule."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    grad_weight: float = 0.5
    """Weight of the multi-scale gradient-matching term (MiDaS uses 0.5)."""
    grad_scales: int = 4
    """Scales of the gradient-matching term (power-of-two subsamplings of the residual)."""
    seed: int = 0
    """Seed of the weights' initialisation, the sampling and the augmentations."""
    architecture: DepthNetConfig = DepthNetConfig()
    """The network trained."""
    augment: DepthAugmentConfig = DepthAugmentConfig()
    """Augmentations applied to every training sample."""
    log_every: int = 50
    """Steps per entry of the loss curve kept in the history."""
    workers: int = 0
    """Processes that augment batches ahead of the optimiser (0: augment in this process). Each step's batch is
    drawn and augmented from its own seed (``seed``, step), so the weights do not depend on this number."""

    @classmethod
    def from_dict(cls, d: dict) -> "DepthTrainConfig":
        """The configuration ``asdict`` gave (as training.json keeps it); fields it lacks take their defaults."""
        d = dict(d)
        arch = d.pop("architecture", None)
        aug = d.pop("augment", None)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValidationError(f"unknown relative-depth training settings {sorted(unknown)}")
        out = cls(**d)
        if arch is not None:
            out = dataclasses.replace(out, architecture=DepthNetConfig(tuple(int(w) for w in arch["widths"]),
                                                                       int(arch["long_side"])))
        if aug is not None:
            out = dataclasses.replace(out, augment=DepthAugmentConfig(**aug))
        return out


def _check_training_arrays(images: np.ndarray, inv_depths: np.ndarray, valid: np.ndarray | None,
                           multiple: int) -> None:
    if not isinstance(images, np.ndarray) or images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise OmniscsError(f"training images must be a uint8 array [N, H, W, 3]; got "
                           f"{getattr(images, 'dtype', type(images))} {getattr(images, 'shape', '')}")
    n, h, w = images.shape[:3]
    if n < 1 or h < 1 or w < 1:
        raise OmniscsError(f"training needs at least one non-empty image; got images of shape {images.shape}")
    if not isinstance(inv_depths, np.ndarray) or inv_depths.shape != (n, h, w):
        raise OmniscsError(f"training inverse depths must be an array [N, H, W] = {[n, h, w]} (one per image); got "
                           f"{getattr(inv_depths, 'shape', type(inv_depths))}")
    if valid is not None and (not isinstance(valid, np.ndarray) or valid.shape != (n, h, w)):
        raise OmniscsError(f"training valid masks must be a bool array [N, H, W] = {[n, h, w]}; got "
                           f"{getattr(valid, 'shape', type(valid))}")
    if h % multiple or w % multiple:
        raise OmniscsError(f"training images must have sides that are multiples of {multiple} (the network's "
                           f"levels); got {h}x{w}: resize or crop them first")


def train_depth_net(images: np.ndarray,      # [N, H, W, 3] uint8 at the working resolution
                    inv_depths: np.ndarray,  # [N, H, W] float32 ground-truth inverse depth (1/m, 0 = sky)
                    config: DepthTrainConfig = DepthTrainConfig(),
                    progress: Progress = no_progress,
                    valid: np.ndarray | None = None,  # [N, H, W] bool: pixels that count (all when None)
                    device: str = "cpu",
                    ) -> tuple[dict[str, Tensor], dict]:  # state dict of a DepthNet, history
    """Train a DepthNet from scratch with the SSI loss; every sample is augmented afresh. Raises an OmniscsError
    when the loss stops being finite (divergence, or NaN/Inf in the data)."""
    arch = config.architecture
    _check_training_arrays(images, inv_depths, valid, arch.multiple)
    if config.steps < 1 or config.batch < 1:
        raise OmniscsError(f"steps and batch must be positive; got steps={config.steps}, batch={config.batch}")
    torch.manual_seed(config.seed)
    net = DepthNet(arch).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=config.steps)
    batches = torch.utils.data.DataLoader(_AugmentedBatches(images, inv_depths, valid, config), batch_size=None,
                                          num_workers=config.workers, shuffle=False,
                                          persistent_workers=False, prefetch_factor=4 if config.workers else None)
    started, losses = time.perf_counter(), []
    net.train()
    for step, (x, target, mask) in enumerate(batches):
        x = x.to(device, non_blocking=True).permute(0, 3, 1, 2).float() / 255.0
        loss = ssi_loss(net(x), target.to(device, non_blocking=True), mask.to(device, non_blocking=True),
                        config.grad_weight, config.grad_scales)
        if not torch.isfinite(loss):
            raise OmniscsError(f"relative-depth training diverged at step {step} (the loss is not finite); check the "
                               "training images and inverse depths for NaN/Inf, or lower the learning rate")
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        progress(step + 1, config.steps, f"SSI loss {np.mean(losses[-20:]):.3f}")
    net.eval()
    window = max(1, min(50, len(losses) // 4))  # loss_first / loss_last: means over the first and last window
    history = {"config": asdict(config), "loss_first": float(np.mean(losses[:window])),
               "loss_last": float(np.mean(losses[-window:])),
               "loss_curve": [[s, float(np.mean(losses[max(0, s - config.log_every):s + 1]))]
                              for s in range(0, config.steps, config.log_every)],
               "seconds": time.perf_counter() - started, "n_images": int(len(images)), "device": str(device),
               "n_parameters": int(sum(p.numel() for p in net.parameters()))}
    return {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}, history


class _AugmentedBatches(torch.utils.data.Dataset):
    """Item ``step``: that step's batch (images [B, H, W, 3] uint8, inverse depths [B, H, W], valid [B, H, W]),
    its samples and augmentations drawn from a generator seeded by (``config.seed``, step)."""

    def __init__(self, images: np.ndarray, inv_depths: np.ndarray, valid: np.ndarray | None,
                 config: DepthTrainConfig) -> None:
        self.images, self.inv_depths, self.valid, self.config = images, inv_depths, valid, config
        self.all_valid = np.ones(inv_depths.shape[1:], bool)

    def __len__(self) -> int:
        return self.config.steps

    def __getitem__(self, step: int) -> tuple[Tensor, Tensor, Tensor]:
        rng = np.random.default_rng([self.config.seed, int(step)])
        batch = [augment(self.images[i], self.inv_depths[i], self.all_valid if self.valid is None else self.valid[i],
                         self.config.augment, rng) for i in rng.integers(0, len(self.images), self.config.batch)]
        return tuple(torch.from_numpy(np.stack([b[k] for b in batch])) for k in range(3))


# ----------------------------------------------------------------------------- weights on disk
WEIGHTS_FILE = "reldepth.safetensors"
INFO_FILE = "training.json"


def save_depth_net(state_dict: dict[str, Tensor], architecture: DepthNetConfig, folder: str | Path,
                   info: dict) -> None:
    """Weights (safetensors, float32) and how they were made (``training.json``, with the architecture), written
    whole into ``folder`` (replacing an earlier one written by omniscs)."""
    with atomic_directory(Path(folder), overwrite=True) as tmp:
        save_file({k: v.detach().float().contiguous() if v.is_floating_point() else v.contiguous()
                   for k, v in state_dict.items()}, str(tmp / WEIGHTS_FILE))
        (tmp / INFO_FILE).write_text(json.dumps({"architecture": asdict(architecture), **info}, indent=1,
                                                default=str))


def load_depth_net(folder: str | Path) -> DepthNet:
    """The DepthNet saved in ``folder`` by ``save_depth_net``, in eval mode."""
    folder = verified_folder(folder)
    try:
        arch = read_own_json(folder / INFO_FILE, f"{folder} holds no relative-depth weights this version reads; "
                             "retrain them with `omniscs pretrained train reldepth`", expect=dict,
                             error=ValidationError)["architecture"]
        net = DepthNet(DepthNetConfig(tuple(int(c) for c in arch["widths"]), int(arch["long_side"])))
        net.load_state_dict(load_file(str(folder / WEIGHTS_FILE)))
    except (OSError, KeyError, TypeError, ValueError, RuntimeError) as e:
        raise ValidationError(f"{folder} holds no relative-depth weights this version reads "
                              f"({type(e).__name__}: {e}); retrain them with "
                              "`omniscs pretrained train reldepth`") from e
    return net.eval()
