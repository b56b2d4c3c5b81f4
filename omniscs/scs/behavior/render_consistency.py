"""The render-consistency term (the paper's appearance term)
L_app = sum_t || F(Re(NSG_perturbed))_t - F(Re(NSG))_t ||^2 and its feature net F.

``RenderConsistencyTerm`` takes any differentiable renderer ``render(trajectories) -> images [T, 3, H, W]`` (the
Gaussian scene graph's: ``scene_render.GraphTrajectoryRenderer``) and the images of the unperturbed scene. The
feature net defaults to a *fixed, seeded random-init* CNN: no pretrained ImageNet weights exist here, a random
multi-scale filter bank of this kind still responds to edges, colour and texture placement (the "random-weight
features as a perceptual metric" observation), it needs no file and no training data, and it cannot bake the look of
the procedural world into the metric (a net self-trained on our renders would). A user's pretrained network plugs in
from local weights: a state dict for this architecture, or a torch.export / TorchScript file of any CNN.

Also here: the drift metric of the benchmark (PSNR of rendered perturbed frames against ground
truth, masked to the adversary) and the ego's poses under a variant's plan.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor, nn

from omniscs.errors import OmniscsError
from omniscs.geometry import pose_from_xyz_yaw
from omniscs.quality import psnr

FEATURE_NET_KINDS = ("random", "state_dict", "export", "torchscript")


@dataclass(frozen=True)
class FeatureNetConfig:
    """Which feature extractor F the render-consistency term compares renders with."""

    kind: str = "random"
    """"random" (fixed seeded init), "state_dict" (this architecture, weights from ``weights_path``), "export"
    (any network saved with torch.export.save, mapping [B, 3, H, W] in [0, 1] to features; export it with
    dynamic batch, height and width) or "torchscript" (the same, saved with torch.jit.save)."""
    weights_path: str | None = None
    """Local weights file for "state_dict" / "torchscript"."""
    seed: int = 0
    """Seed of the random initialisation ("random")."""
    widths: tuple[int, ...] = (16, 32, 64)
    """Channels of the three stride-2 stages (this architecture)."""


@dataclass
class AgentTrajectories:
    """What a renderer needs to place the agents: world-frame poses per future step (differentiable)."""

    track_ids: list[int]  # [N]
    poses: Tensor  # [N, T, 3] x, y, yaw (world frame)
    steps: np.ndarray  # [T] step indices of the log (scene frames when the log was not resampled)
    timestamps_us: np.ndarray  # [T] int64


Renderer = Callable[[AgentTrajectories], Tensor]  # -> images [T, 3, H, W] in [0, 1]


class FeatureNet(nn.Module):
    """Three stride-2 conv stages (3x3, ReLU); returns every stage's features (multi-scale, like LPIPS)."""

    def __init__(self, widths: tuple[int, ...] = (16, 32, 64)) -> None:
        super().__init__()
        stages, c_in = [], 3
        for c in widths:
            stages.append(nn.Sequential(nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.ReLU(),
                                        nn.Conv2d(c, c, 3, padding=1), nn.ReLU()))
            c_in = c
        self.stages = nn.ModuleList(stages)

    def forward(self, images: Tensor) -> list[Tensor]:  # [B, 3, H, W] in [0, 1] -> [[B, C_k, H_k, W_k]]
        x = (images - 0.5) / 0.25
        out = []
        for stage in self.stages:
            x = stage(x)
            out.append(x)
        return out


def build_feature_net(config: FeatureNetConfig = FeatureNetConfig()) -> nn.Module:
    """The feature net, frozen and in eval mode; a missing or mismatching weights file is a one-line error."""
    if config.kind not in FEATURE_NET_KINDS:
        raise OmniscsError(f"unknown feature-net kind {config.kind!r}; use one of {list(FEATURE_NET_KINDS)}")
    if config.kind == "random":
        generator_state = torch.random.get_rng_state()
        torch.manual_seed(config.seed)
        try:
            net = FeatureNet(config.widths)
            for m in net.modules():
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                    nn.init.zeros_(m.bias)
        finally:
            torch.random.set_rng_state(generator_state)
    else:
        path = Path(config.weights_path) if config.weights_path else None
        if path is None or not path.is_file():
            what = {"state_dict": "a state dict of omniscs.scs.behavior.render_consistency.FeatureNet "
                                  "(torch.save(net.state_dict(), PATH))",
                    "export": "a CNN saved with torch.export.save(torch.export.export(net, ...), PATH) mapping "
                              "[B,3,H,W] to features",
                    "torchscript": "a TorchScript CNN (torch.jit.save(torch.jit.script(net), PATH)) mapping "
                                   "[B,3,H,W] to features"}[config.kind]
            raise OmniscsError(f"feature-net weights not found at {config.weights_path!r}; supply {what}, "
                               "or use kind 'random'")
        try:
            if config.kind == "state_dict":
                net = FeatureNet(config.widths)
                with warnings.catch_warnings():  # torch warns when handed a TorchScript file; we report it below
                    warnings.simplefilter("ignore", UserWarning)
                    state = torch.load(path, map_location="cpu", weights_only=True)
                if not isinstance(state, dict):
                    raise ValueError(f"expected a state dict, found {type(state).__name__}")
                net.load_state_dict(state)
            elif config.kind == "export":
                net = torch.export.load(str(path)).module()
            else:
                net = torch.jit.load(str(path), map_location="cpu")
        except (RuntimeError, ValueError, KeyError) as exc:
            raise OmniscsError(f"feature-net weights {path} do not load as {config.kind} "
                               f"({str(exc).splitlines()[0]})") from None
    if config.kind == "export":  # an exported program's module has no eval(); its parameters still need freezing
        for p in net.parameters():
            p.requires_grad_(False)
        return net
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net


def _as_list(features) -> list[Tensor]:
    if isinstance(features, Tensor):
        return [features]
    if isinstance(features, dict):
        return list(features.values())
    return list(features)


def feature_distance(net: nn.Module, images: Tensor, reference_features: list[Tensor]) -> Tensor:
    """sum_t of the squared feature difference, averaged over each stage's elements and summed over stages."""
    feats = _as_list(net(images))
    if len(feats) != len(reference_features):
        raise OmniscsError("feature net returned a different number of feature maps for the two renders")
    total = images.new_zeros(())
    for f, r in zip(feats, reference_features):
        total = total + ((f - r) ** 2).reshape(f.shape[0], -1).mean(-1).sum()
    return total


class RenderConsistencyTerm:
    """L_app for a differentiable renderer: features of the perturbed render against the original's."""

    def __init__(self, render: Renderer, original_images: Tensor,  # [T, 3, H, W] in [0, 1]
                 feature_net: nn.Module | None = None, weight: float = 1.0) -> None:
        if original_images.dim() != 4 or original_images.shape[1] != 3:
            raise OmniscsError(f"original images must be [T, 3, H, W]; got {tuple(original_images.shape)}")
        self.render = render
        self.net = feature_net if feature_net is not None else build_feature_net()
        self.weight = float(weight)
        with torch.no_grad():
            self.reference = [f.detach() for f in _as_list(self.net(original_images.to(torch.float32)))]
        self.n_frames = original_images.shape[0]

    def __call__(self, trajectories: AgentTrajectories) -> Tensor:  # scalar, differentiable in the poses
        images = self.render(trajectories)
        if images.shape[0] != self.n_frames:
            raise OmniscsError(f"renderer returned {images.shape[0]} frames; the original has {self.n_frames}")
        return self.weight * feature_distance(self.net, images.to(torch.float32), self.reference)


# ----------------------------------------------------------------------------- render drift (benchmark)
def masked_psnr(rendered: np.ndarray,      # [T, H, W, 3] or [T, 3, H, W] float in [0, 1]
                ground_truth: np.ndarray,  # same shape
                mask: np.ndarray,          # [T, H, W] bool: the adversary's pixels
                ) -> float | None:
    """PSNR (dB, ``omniscs.quality.psnr``) over masked pixels of frames in either layout; None when the mask is
    empty (the adversary is never seen)."""
    r, g = np.asarray(rendered, np.float64), np.asarray(ground_truth, np.float64)
    if r.shape != g.shape:
        raise OmniscsError(f"rendered {r.shape} and ground-truth {g.shape} frames differ in shape")
    if r.shape[1] == 3 and r.shape[-1] != 3:
        r, g = np.moveaxis(r, 1, -1), np.moveaxis(g, 1, -1)
    return psnr(r, g, mask)


def variant_ego_poses(variant: dict, logged: np.ndarray) -> np.ndarray:  # [F, 4, 4] -> [F, 4, 4]
    """The ego's poses under a variant's plan (the box centre lies ahead of the ego origin; heights logged)."""
    poses = np.array(logged, dtype=np.float64, copy=True)
    ahead = float(variant.get("ego_centre_ahead_of_origin_m", 0.0))
    for step, pose in zip(variant["source_frames"], variant["ego"]):
        if 0 <= step < len(poses):
            x, y, yaw = pose
            poses[step] = pose_from_xyz_yaw(x - ahead * np.cos(yaw), y - ahead * np.sin(yaw),
                                            float(poses[step, 2, 3]), yaw)
    return poses
