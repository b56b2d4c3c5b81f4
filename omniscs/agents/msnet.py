"""MSNet: an omni-scale re-identification network (after OSNet, Zhou et al. 2019), written here and trained from
scratch on pool keyframes with degradations, that maps a crop of a road user to a unit vector; the same model
seen from near and far, lit differently, partly hidden, lands close.

Architecture (x0.25 widths, 64 x 64 input): a 3x3 stride-2 stem (16), then three stages of omni-scale bottlenecks
(``OSBlock``: 1x1 down to a quarter of the width, four streams of 1 to 4 stacked depthwise-separable 3x3 convolutions
(receptive fields 3 to 9), a shared channel gate (global pooling, two 1x1 convolutions, sigmoid) that weighs each
stream before they are summed, 1x1 back up, a residual connection) with 2x2 average pooling between stages (16,
32, 48, 64 channels), global average pooling, a linear layer to ``dim``, L2 normalisation.
Loss ``L_om``: batch-hard triplet loss with margin alpha: for each anchor the hardest positive (the farthest crop of
the same model) is pulled in and the hardest negative (the nearest crop of another model) pushed out,
mean(max(0, alpha + max_pos d - min_neg d)). (The paper's printed equation swaps max and min; this is the intended
form.)

Shipped weights (``SHIPPED``, made by ``omniscs pretrained train msnet``; ``training.json`` holds the seed,
data and losses): trained across domains on the asset library's world split, each vehicle's pool keyframes and its
camera crops from procedural logs as positives of one another, with an identity (softmax) loss beside L_om (the
triplet loss alone sat at the margin). On the agents benchmark (reports/agents/) it ranks pool-split vehicles seen
by the world's camera first for 18 % of clean queries and 20 % at 4x + 40 % occlusion + an illumination shift
(27.5 % with the box shape; colour histogram: 2 % and 6 %): far from the issue's 95 %."""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from omniscs.agents.degradation import degrade
from omniscs.errors import ValidationError
from omniscs.pretrained.registry import folder as shipped_folder, verified_folder
from omniscs.progress import Progress, no_progress
from omniscs.storage import atomic_directory
from omniscs.untrusted import read_own_json


class _Light3x3(nn.Module):  # depthwise-separable 3x3: 1x1 then depthwise 3x3, BN, ReLU
    def __init__(self, c: int) -> None:
        super().__init__()
        self.pw = nn.Conv2d(c, c, 1, bias=False)
        self.dw = nn.Conv2d(c, c, 3, padding=1, groups=c, bias=False)
        self.bn = nn.BatchNorm2d(c)

    def forward(self, x):
        return torch.relu(self.bn(self.dw(self.pw(x))))


class OSBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        mid = max(4, c_out // 4)
        self.down = nn.Sequential(nn.Conv2d(c_in, mid, 1, bias=False), nn.BatchNorm2d(mid), nn.ReLU())
        self.streams = nn.ModuleList([nn.Sequential(*[_Light3x3(mid) for _ in range(t)]) for t in range(1, 5)])
        self.gate = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(mid, max(2, mid // 4), 1), nn.ReLU(),
                                  nn.Conv2d(max(2, mid // 4), mid, 1), nn.Sigmoid())
        self.up = nn.Sequential(nn.Conv2d(mid, c_out, 1, bias=False), nn.BatchNorm2d(c_out))
        self.skip = nn.Identity() if c_in == c_out else nn.Sequential(nn.Conv2d(c_in, c_out, 1, bias=False),
                                                                       nn.BatchNorm2d(c_out))

    def forward(self, x):
        z = self.down(x)
        mixed = 0
        for stream in self.streams:  # each scale weighed by the shared gate, then summed
            y = stream(z)
            mixed = mixed + y * self.gate(y)
        return torch.relu(self.up(mixed) + self.skip(x))


@dataclass(frozen=True)
class MSNetConfig:
    widths: tuple[int, ...] = (16, 32, 48, 64)
    dim: int = 128


class MSNet(nn.Module):
    def __init__(self, config: MSNetConfig = MSNetConfig()) -> None:
        super().__init__()
        w = config.widths
        self.config = config
        layers = [nn.Conv2d(3, w[0], 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(w[0]), nn.ReLU()]
        for a, b in zip(w[:-1], w[1:]):
            layers += [OSBlock(a, b), OSBlock(b, b), nn.AvgPool2d(2)]
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(w[-1], config.dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, 3, H, W] in 0..1 -> [B, dim] unit
        z = self.features(x).mean((2, 3))
        return nn.functional.normalize(self.head(z), dim=1)


def batch_hard_triplet(emb: torch.Tensor, labels: torch.Tensor, margin: float) -> torch.Tensor:
    """mean over anchors of max(0, margin + farthest same-label distance - nearest other-label distance); anchors
    with no positive or no negative in the batch are left out."""
    d = torch.cdist(emb, emb)
    same = labels[:, None] == labels[None, :]
    eye = torch.eye(len(labels), dtype=torch.bool, device=emb.device)
    pos = torch.where(same & ~eye, d, torch.full_like(d, -1.0)).max(1).values
    neg = torch.where(~same, d, torch.full_like(d, float("inf"))).min(1).values
    ok = (pos >= 0) & torch.isfinite(neg)
    if not ok.any():
        return emb.sum() * 0.0
    return torch.relu(margin + pos[ok] - neg[ok]).mean()


@dataclass(frozen=True)
class MSNetTrainConfig:
    steps: int = 600
    models_per_batch: int = 16
    views_per_model: int = 4
    lr: float = 2e-3
    margin: float = 0.3
    seed: int = 0
    id_weight: float = 0.0
    """Weight of an identity (softmax) loss over the training models beside L_om, as OSNet trains: a cosine
    classifier on the embeddings keeps batch-hard triplets from collapsing every crop onto one point early on."""


def _tensor(crops: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(crops, dtype=torch.float32).permute(0, 3, 1, 2) / 255.0


def train_msnet(crops: np.ndarray, labels: np.ndarray, degradations, config: MSNetTrainConfig = MSNetTrainConfig(),
                net: MSNet | None = None, progress: Progress = no_progress,
                domains: np.ndarray | None = None) -> tuple[MSNet, dict]:
    """Train on ``crops`` (uint8 [N, 64, 64, 3]) of models ``labels`` [N]; each batch takes ``models_per_batch``
    models with ``views_per_model`` crops each, every crop degraded by one of ``degradations`` at random. With
    ``domains`` [N] (e.g. 0 = the pool's keyframes, 1 = camera images), a model's crops in a batch are drawn from
    each of its domains in turn, so that positives cross the domains a query and the gallery come from."""
    labels = np.unique(np.asarray(labels), return_inverse=True)[1].reshape(-1)  # any label type -> 0..M-1
    models = np.unique(labels)
    if len(models) < 2 or len(crops) != len(labels):
        raise ValidationError("MSNet needs crops of at least two models, one label per crop")
    rng = np.random.default_rng(config.seed)
    torch.manual_seed(config.seed)
    net = net or MSNet()
    classifier = nn.Linear(net.config.dim, len(models), bias=False) if config.id_weight > 0 else None
    params = list(net.parameters()) + (list(classifier.parameters()) if classifier is not None else [])
    opt = torch.optim.AdamW(params, lr=config.lr, weight_decay=5e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=config.steps)
    by_model = {m: np.flatnonzero(labels == m) for m in models}
    if domains is not None:
        domains = np.asarray(domains)
        if len(domains) != len(labels):
            raise ValidationError("MSNet domains need one entry per crop")
    by_domain = {m: [idx[domains[idx] == d] for d in np.unique(domains[idx])] for m, idx in by_model.items()} \
        if domains is not None else None

    def views_of(m) -> np.ndarray:
        if by_domain is None:
            return rng.choice(by_model[m], config.views_per_model)
        groups = by_domain[m]
        return np.array([rng.choice(groups[k % len(groups)]) for k in range(config.views_per_model)])

    started, losses = time.perf_counter(), []
    net.train()
    for step in range(config.steps):
        chosen = rng.choice(models, min(config.models_per_batch, len(models)), replace=False)
        idx = np.concatenate([views_of(m) for m in chosen])
        batch = np.stack([degrade(crops[i], degradations[rng.integers(len(degradations))], rng) for i in idx])
        emb = net(_tensor(batch))
        target = torch.as_tensor(labels[idx])
        loss = batch_hard_triplet(emb, target, config.margin)
        if classifier is not None:  # cosine logits at scale 16
            logits = 16.0 * emb @ nn.functional.normalize(classifier.weight, dim=1).T
            loss = loss + config.id_weight * nn.functional.cross_entropy(logits, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        progress(step + 1, config.steps, f"loss {np.mean(losses[-20:]):.3f}")
    net.eval()
    return net, {"config": asdict(config), "loss_first": float(np.mean(losses[:20])),
                 "loss_last": float(np.mean(losses[-20:])), "seconds": time.perf_counter() - started,
                 "n_crops": int(len(crops)), "n_models": int(len(models))}


class MSNetEmbedder:
    """The ``Embedder`` interface over a trained MSNet."""

    name = "MSNet"

    def __init__(self, net: MSNet) -> None:
        self.net = net.eval()
        h = hashlib.sha256()
        for k, v in sorted(net.state_dict().items()):
            h.update(k.encode())
            h.update(v.detach().cpu().numpy().tobytes())
        self.cache_key = f"msnet-{h.hexdigest()[:12]}"  # cached gallery embeddings belong to these very weights

    @torch.no_grad()
    def embed(self, crops: np.ndarray) -> np.ndarray:
        out = [self.net(_tensor(crops[i:i + 256])).numpy() for i in range(0, len(crops), 256)]
        return np.concatenate(out).astype(np.float32)


#: The shipped weights (registry entry ``msnet``; ``omniscs pretrained train msnet`` makes them).
SHIPPED = shipped_folder("msnet")


def shipped_embedder():
    """The shipped MSNet as an Embedder, or None when the package holds no weights."""
    if not (SHIPPED / "msnet.safetensors").is_file():
        return None
    return MSNetEmbedder(load_msnet(SHIPPED))


def save_msnet(net: MSNet, folder, info: dict) -> None:
    """Weights (safetensors), the architecture and how they were made (``training.json``), written whole."""
    with atomic_directory(Path(folder), overwrite=True) as tmp:
        save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(tmp / "msnet.safetensors"))
        (tmp / "training.json").write_text(json.dumps({"architecture": asdict(net.config), **info}, indent=1,
                                                      default=str))


def load_msnet(folder) -> MSNet:
    """An MSNet saved by ``save_msnet`` (a user's own weights of this architecture load the same way)."""
    folder = verified_folder(folder)
    try:
        arch = read_own_json(folder / "training.json", f"{folder} holds no MSNet weights this version reads",
                             expect=dict, error=ValidationError)["architecture"]
        net = MSNet(MSNetConfig(tuple(arch["widths"]), int(arch["dim"])))
        net.load_state_dict(load_file(str(folder / "msnet.safetensors")))
    except (OSError, KeyError, ValueError, RuntimeError) as e:
        raise ValidationError(f"{folder} holds no MSNet weights this version reads ({type(e).__name__}: {e})") from e
    return net.eval()
