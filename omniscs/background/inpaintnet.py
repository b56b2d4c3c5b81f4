"""The embedded inpainting network: a U-Net with a dilated context bottleneck that fills a hole in an RGB image from
the pixels around it, its training loop on repair pairs (arrays and tensors only) and its weights on disk.

Training pairs are camera images of procedural worlds with a large agent, the agent's hole, and the same view of
the world without the agent (omniscs.training.inpaint). Half of each batch are those pairs; the other half are
self-supervised: a clean image (a pair's target) with another pair's hole laid over it at a random place, the way
LaMa trains on random masks, so the network sees many more holes than pairs. The loss is the mean absolute error
inside the hole plus ``context_weight`` times the one outside it (where the inpainter's output is discarded anyway:
it keeps the network's colours calibrated).
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from omniscs.background.inpaint_base import HoleFiller, unit_float_to_uint8
from omniscs.errors import OmniscsError, ValidationError
from omniscs.pretrained.registry import folder as shipped_folder, verified_folder
from omniscs.progress import Progress, no_progress
from omniscs.storage import atomic_directory
from omniscs.untrusted import read_own_json

#: The shipped weights (registry entry ``inpaint``; ``omniscs pretrained train inpaint --install`` writes them).
SHIPPED = shipped_folder("inpaint")
WEIGHTS_FILE = "inpaint.safetensors"
INFO_FILE = "training.json"

#: RGB normalisation of the network's input (after scaling to 0..1); hole pixels enter as 0 after it.
RGB_MEAN = 0.45
RGB_STD = 0.25

#: Images whose longer side exceeds this multiple of the working long side are shrunk to it; smaller ones are
#: filled at their own resolution (no resampling blur).
NATIVE_LIMIT = 1.5


@dataclass(frozen=True)
class InpaintNetConfig:
    """The architecture (stored in ``training.json`` beside the weights)."""

    widths: tuple[int, ...] = (32, 64, 96, 128, 192)
    """Channels of the U-Net's levels, full resolution first; each further level halves the resolution."""
    dilations: tuple[int, ...] = (2, 4, 8)
    """Residual blocks of dilated 3x3 convolutions at the lowest level, one per entry: at 1/16 of a 256 x 144 image
    their receptive field spans the whole image, so a large hole is filled from all of its surroundings."""
    long_side: int = 256
    """Working resolution of large images (see NATIVE_LIMIT)."""

    @property
    def multiple(self) -> int:
        return 2 ** (len(self.widths) - 1)

    @classmethod
    def from_dict(cls, d: dict) -> "InpaintNetConfig":
        return cls(tuple(int(w) for w in d["widths"]), tuple(int(x) for x in d["dilations"]), int(d["long_side"]))


def _block(c_in: int, c_out: int, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=dilation, dilation=dilation),
                         nn.GroupNorm(math.gcd(8, c_out), c_out), nn.LeakyReLU(0.2, inplace=True))


class _Residual(nn.Module):
    def __init__(self, c: int, dilation: int) -> None:
        super().__init__()
        self.body = nn.Sequential(_block(c, c, dilation), _block(c, c, 1))

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


class InpaintNet(nn.Module):
    """Encoder (two 3x3 blocks per level, stride-2 convolution between levels), dilated residual context blocks at
    the lowest level, decoder (bilinear upsampling, two blocks over [upsampled, skip]), a 3x3 head with a sigmoid.
    Input: the image with its hole blanked and the hole itself; output: a full image in 0..1."""

    def __init__(self, config: InpaintNetConfig = InpaintNetConfig()) -> None:
        super().__init__()
        if len(config.widths) < 2 or min(config.widths) < 1 or min(config.dilations, default=1) < 1:
            raise OmniscsError(f"InpaintNet needs at least two levels of positive widths and positive dilations; "
                               f"got {config}")
        w = config.widths
        self.config = config
        self.encoder = nn.ModuleList([nn.Sequential(_block(4, w[0]), _block(w[0], w[0]))] + [
            nn.Sequential(nn.Conv2d(w[i - 1], w[i], 3, stride=2, padding=1), _block(w[i], w[i]), _block(w[i], w[i]))
            for i in range(1, len(w))])
        self.context = nn.Sequential(*[_Residual(w[-1], d) for d in config.dilations])
        self.decoder = nn.ModuleList([nn.Sequential(_block(w[i + 1] + w[i], w[i]), _block(w[i], w[i]))
                                      for i in reversed(range(len(w) - 1))])
        self.head = nn.Conv2d(w[0], 3, 3, padding=1)

    def forward(self, rgb: Tensor,   # [B, 3, H, W] in 0..1, H and W multiples of config.multiple
                hole: Tensor,        # [B, 1, H, W] 1 = fill
                ) -> Tensor:         # [B, 3, H, W] in 0..1
        x = torch.cat([(rgb - RGB_MEAN) / RGB_STD * (1.0 - hole), hole], 1)
        skips = []
        for block in self.encoder:
            x = block(x)
            skips.append(x)
        x = self.context(x)
        for block, skip in zip(self.decoder, reversed(skips[:-1])):
            x = nn.functional.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], 1))
        return torch.sigmoid(self.head(x))


class NetInpainter(HoleFiller):
    """An InpaintNet as an Inpainter (omniscs.background.inpaint): the image (shrunk to the working resolution
    when it is much larger, see NATIVE_LIMIT) is padded by reflection to a multiple of the network's levels."""

    def __init__(self, net: InpaintNet, name: str = "embedded", device: str = "cpu") -> None:
        self.net = net.eval().to(device)
        self._name = name
        self.device = device

    @property
    def name(self) -> str:
        return self._name

    @torch.no_grad()
    def _fill(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        height, width = mask.shape
        cfg = self.net.config
        image, hole = rgb, mask
        if max(height, width) > NATIVE_LIMIT * cfg.long_side:
            scale = cfg.long_side / max(height, width)
            w, h = max(1, round(width * scale)), max(1, round(height * scale))
            image = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            hole = cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.0
        h, w = hole.shape
        m = cfg.multiple
        pad = ((0, -h % m), (0, -w % m))
        mode = "reflect" if h > 1 and w > 1 and -h % m < h and -w % m < w else "edge"
        image = np.pad(image, pad + ((0, 0),), mode=mode)
        hole_p = np.pad(hole, pad, mode=mode)
        x = torch.from_numpy(np.ascontiguousarray(image)).to(self.device).permute(2, 0, 1)[None].float() / 255.0
        k = torch.from_numpy(np.ascontiguousarray(hole_p)).to(self.device)[None, None].float()
        out = self.net(x, k)[0, :, :h, :w].permute(1, 2, 0).float().cpu().numpy()
        if out.shape[:2] != (height, width):
            out = cv2.resize(out, (width, height), interpolation=cv2.INTER_LINEAR)
        return unit_float_to_uint8(out, f"inpainting network {self._name!r}")


# ----------------------------------------------------------------------------- training
@dataclass(frozen=True)
class InpaintTrainConfig:
    """Training of the embedded inpainting network (AdamW, one-cycle learning rate, L1 loss)."""

    steps: int = 12_000
    """Optimiser steps."""
    batch: int = 16
    """Samples per step (half repair pairs, half self-supervised holes; see the module docstring)."""
    lr: float = 1e-3
    """Peak learning rate of the one-cycle schedule."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    context_weight: float = 0.1
    """Weight of the mean absolute error outside the hole."""
    self_supervised: float = 0.5
    """Share of each batch made of a clean image with another pair's hole laid over it."""
    jitter: float = 0.15
    """Brightness and contrast of a sample (image and target alike) are scaled by 1 +- up to this."""
    seed: int = 0
    """Seed of the initialisation, the sampling and the augmentations."""
    architecture: InpaintNetConfig = InpaintNetConfig()
    """The network trained."""
    log_every: int = 50
    """Steps per entry of the loss curve kept in the history."""
    workers: int = 0
    """Processes that make batches ahead of the optimiser (0: in this process); each step's batch is drawn from its
    own seed (``seed``, step), so the weights do not depend on this number."""

    @classmethod
    def from_dict(cls, d: dict) -> "InpaintTrainConfig":
        d = dict(d)
        arch = d.pop("architecture", None)
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValidationError(f"unknown inpainting training settings {sorted(unknown)}")
        out = cls(**d)
        return out if arch is None else dataclasses.replace(out, architecture=InpaintNetConfig.from_dict(arch))


def check_pairs(images: np.ndarray, holes: np.ndarray, targets: np.ndarray, multiple: int) -> None:
    """Raise an OmniscsError unless images and targets are uint8 [N, H, W, 3] and holes bool [N, H, W], every hole
    non-empty and not the whole image, the sides multiples of ``multiple``."""
    if not isinstance(images, np.ndarray) or images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise OmniscsError(f"training images must be a uint8 array [N, H, W, 3]; got "
                           f"{getattr(images, 'dtype', type(images))} {getattr(images, 'shape', '')}")
    n, h, w = images.shape[:3]
    if n < 2:
        raise OmniscsError(f"inpainting training needs at least two pairs; got {n}")
    if not isinstance(targets, np.ndarray) or targets.shape != images.shape or targets.dtype != np.uint8:
        raise OmniscsError(f"training targets must be uint8 {list(images.shape)} like the images; got "
                           f"{getattr(targets, 'dtype', type(targets))} {getattr(targets, 'shape', '')}")
    if not isinstance(holes, np.ndarray) or holes.shape != (n, h, w) or holes.dtype != np.bool_:
        raise OmniscsError(f"training holes must be a bool array [N, H, W] = {[n, h, w]}; got "
                           f"{getattr(holes, 'dtype', type(holes))} {getattr(holes, 'shape', '')}")
    share = holes.reshape(n, -1).mean(1)
    if (share == 0).any() or (share == 1).any():
        raise OmniscsError("every training hole must cover some pixels but not the whole image")
    if h % multiple or w % multiple:
        raise OmniscsError(f"training images must have sides that are multiples of {multiple}; got {h}x{w}")


class _PairBatches(torch.utils.data.Dataset):
    """Item ``step``: that step's batch (images [B, H, W, 3] uint8, holes [B, H, W] bool, targets [B, H, W, 3]
    uint8), drawn and augmented from a generator seeded by (``config.seed``, step)."""

    def __init__(self, images: np.ndarray, holes: np.ndarray, targets: np.ndarray, config: InpaintTrainConfig):
        self.images, self.holes, self.targets, self.config = images, holes, targets, config

    def __len__(self) -> int:
        return self.config.steps

    def _sample(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, h, w = self.holes.shape
        i = int(rng.integers(n))
        image, hole, target = self.images[i], self.holes[i], self.targets[i]
        if rng.random() < self.config.self_supervised:
            k = int(rng.integers(n))
            moved = np.zeros_like(hole)
            dx = int(rng.integers(-w // 2, w // 2 + 1))
            src = self.holes[k][:, max(0, -dx):w - max(0, dx)]
            moved[:, max(0, dx):max(0, dx) + src.shape[1]] = src
            if moved.any() and not moved.all():
                image = target
                hole = moved
        if rng.random() < 0.5:
            image, hole, target = image[:, ::-1], hole[:, ::-1], target[:, ::-1]
        j = self.config.jitter
        gain, contrast = rng.uniform(1 - j, 1 + j), rng.uniform(1 - j, 1 + j)

        def tone(x: np.ndarray) -> np.ndarray:
            y = (x.astype(np.float32) - 128.0) * contrast + 128.0
            return np.clip(y * gain, 0, 255).round().astype(np.uint8)

        return tone(image), np.ascontiguousarray(hole), tone(target)

    def __getitem__(self, step: int) -> tuple[Tensor, Tensor, Tensor]:
        rng = np.random.default_rng([self.config.seed, int(step)])
        batch = [self._sample(rng) for _ in range(self.config.batch)]
        return tuple(torch.from_numpy(np.stack([b[k] for b in batch])) for k in range(3))


def inpaint_loss(pred: Tensor, target: Tensor, hole: Tensor, context_weight: float) -> Tensor:
    """Mean absolute error over the hole pixels plus ``context_weight`` times the one over the others
    (pred, target [B, 3, H, W]; hole [B, 1, H, W] in {0, 1})."""
    err = (pred - target).abs().mean(1, keepdim=True)
    inside = (err * hole).sum() / hole.sum().clamp_min(1.0)
    outside = (err * (1 - hole)).sum() / (1 - hole).sum().clamp_min(1.0)
    return inside + context_weight * outside


def train_inpaint_net(images: np.ndarray,   # [N, H, W, 3] uint8, with the object
                      holes: np.ndarray,    # [N, H, W] bool
                      targets: np.ndarray,  # [N, H, W, 3] uint8, without it
                      config: InpaintTrainConfig = InpaintTrainConfig(),
                      progress: Progress = no_progress,
                      device: str = "cpu",
                      init: dict[str, Tensor] | None = None,  # weights to start from (default: a fresh network)
                      ) -> tuple[dict[str, Tensor], dict]:
    """Train an InpaintNet, from scratch or on from ``init`` (a state dict of the same architecture: a second
    phase of training). Raises an OmniscsError when the loss stops being finite."""
    arch = config.architecture
    check_pairs(images, holes, targets, arch.multiple)
    if config.steps < 1 or config.batch < 1:
        raise OmniscsError(f"steps and batch must be positive; got steps={config.steps}, batch={config.batch}")
    torch.manual_seed(config.seed)
    net = InpaintNet(arch)
    if init is not None:
        try:
            net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in init.items()})
        except RuntimeError as e:
            raise OmniscsError(f"the initial weights do not fit the architecture {arch} ({str(e).splitlines()[0]})") \
                from None
    net = net.to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=config.steps)
    batches = torch.utils.data.DataLoader(_PairBatches(images, holes, targets, config), batch_size=None,
                                          num_workers=config.workers, shuffle=False,
                                          prefetch_factor=4 if config.workers else None)
    started, losses = time.perf_counter(), []
    net.train()
    for step, (x, k, y) in enumerate(batches):
        x = x.to(device, non_blocking=True).permute(0, 3, 1, 2).float() / 255.0
        y = y.to(device, non_blocking=True).permute(0, 3, 1, 2).float() / 255.0
        k = k.to(device, non_blocking=True)[:, None].float()
        loss = inpaint_loss(net(x, k), y, k, config.context_weight)
        if not torch.isfinite(loss):
            raise OmniscsError(f"inpainting training diverged at step {step} (the loss is not finite); check the "
                               "training images for NaN/Inf, or lower the learning rate")
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        progress(step + 1, config.steps, f"L1 {np.mean(losses[-20:]):.4f}")
    net.eval()
    window = max(1, min(50, len(losses) // 4))
    history = {"config": asdict(config), "loss_first": float(np.mean(losses[:window])),
               "loss_last": float(np.mean(losses[-window:])),
               "loss_curve": [[s, float(np.mean(losses[max(0, s - config.log_every):s + 1]))]
                              for s in range(0, config.steps, config.log_every)],
               "seconds": time.perf_counter() - started, "n_pairs": int(len(images)), "device": str(device),
               "initialised_from_weights": init is not None,
               "n_parameters": int(sum(p.numel() for p in net.parameters()))}
    return {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}, history


# ----------------------------------------------------------------------------- weights on disk
def save_inpaint_net(state_dict: dict[str, Tensor], architecture: InpaintNetConfig, folder: str | Path,
                     info: dict) -> None:
    """Weights (safetensors; floating tensors stored as float16, which halves the file and changes fills by less
    than a grey level) and ``training.json``, written whole into ``folder``."""
    with atomic_directory(Path(folder), overwrite=True) as tmp:
        save_file({k: v.detach().half().contiguous() if v.is_floating_point() else v.contiguous()
                   for k, v in state_dict.items()}, str(tmp / WEIGHTS_FILE))
        (tmp / INFO_FILE).write_text(json.dumps({"architecture": asdict(architecture), **info}, indent=1,
                                                default=str))


def load_inpaint_net(folder: str | Path = SHIPPED) -> InpaintNet:
    """The InpaintNet saved in ``folder`` by ``save_inpaint_net`` (float32, eval mode)."""
    folder = verified_folder(folder)
    make = ("train them with `omniscs pretrained train inpaint --export-data PACK`, infra/inpaint_gpu/train.py and "
            "`omniscs pretrained train inpaint --install OUT`")
    try:
        info = read_own_json(folder / INFO_FILE, f"{folder} holds no inpainting weights this version reads; {make}",
                             expect=dict, error=ValidationError)
        arch = InpaintNetConfig.from_dict(info["architecture"])
        net = InpaintNet(arch)
        net.load_state_dict({k: v.float() if v.is_floating_point() else v
                             for k, v in load_file(str(folder / WEIGHTS_FILE)).items()})
    except (OSError, KeyError, TypeError, ValueError, RuntimeError) as e:
        raise ValidationError(f"{folder} holds no inpainting weights this version reads ({type(e).__name__}: {e}); "
                              f"{make}") from e
    return net.eval()
