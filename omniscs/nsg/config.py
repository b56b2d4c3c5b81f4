"""Fit configuration of the scene graph (frozen, documented dataclasses) and the fast/balanced/accurate presets."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from omniscs.devices import resolve_device
from omniscs.errors import OmniscsError
from omniscs.overrides import replace_checked
from omniscs.nsg.graph import RenderSettings
from omniscs.nsg.strategy import DensifyStrategy
from omniscs.plan import PlanConfig


#: FitConfig fields that say where a fit runs, not what it means: left out of ``FitConfig.to_dict`` (which
#: checkpoints record and stage keys hash), so the same fit on another device reuses and compares as the same.
EXECUTION_ONLY_FIELDS = ("device",)


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates per parameter group (gsplat's defaults, scaled for short fits)."""

    means: float = 1.6e-4
    """Means, times the node's scene scale (metres); decays exponentially to ``means_final_ratio`` of it."""
    means_final_ratio: float = 0.01
    """Means learning rate at the last iteration, as a fraction of the first."""
    quats: float = 1e-3
    """Unnormalised quaternions."""
    log_scales: float = 5e-3
    """Log-scales."""
    opacity_logits: float = 5e-2
    """Opacity logits."""
    sh_dc: float = 2.5e-3
    """Band-0 (view-independent) colour coefficients."""
    sh_rest: float = 2.5e-3 / 20
    """Higher SH bands (view-dependent colour)."""
    sky: float = 2e-2
    """Sky texture logits."""
    exposure: float = 5e-4
    """Per-camera affine colour correction."""


@dataclass(frozen=True)
class LossConfig:
    """Photometric and LiDAR terms of the fitting loss."""

    ssim_weight: float = 0.2
    """Weight of (1 - SSIM) against L1 (3DGS's lambda)."""
    ssim_window: int = 11
    """SSIM window size in pixels."""
    depth_weight: float = 0.1
    """Weight of the LiDAR term: mean |expected depth - LiDAR depth| / LiDAR depth at projected returns."""
    depth_min_alpha: float = 0.5
    """LiDAR returns only supervise pixels that Gaussians already cover at least this much."""


@dataclass(frozen=True)
class InitConfig:
    """How the first Gaussians are placed: on LiDAR returns, box surfaces and camera rays."""

    opacity: float = 0.1
    """Initial opacity of every seed Gaussian."""
    voxel_m: float = 0.15
    """LiDAR returns are thinned to one per voxel of this size before the budget draw."""
    max_seed_scale_m: float = 1.0
    """Largest initial Gaussian size, metres."""
    ray_seed_fraction: float = 0.25
    """Share of the background budget seeded along random camera rays (what LiDAR never hits: tall
    facades, far geometry), at depths uniform in inverse depth between the two limits below."""
    ray_seed_near_m: float = 3.0
    """Nearest depth of ray seeds, metres."""
    ray_seed_far_m: float = 150.0
    """Farthest depth of ray seeds, metres."""
    agent_box_margin_m: float = 0.15
    """LiDAR returns up to this far outside an agent's box belong to it (box fits are loose)."""
    agent_ground_clearance_m: float = 0.08
    """Returns lower than this above an agent's box floor are road, not agent."""
    agent_surface_seeds: int = 600
    """Seeds on the box surface for an agent that no LiDAR return hit."""


@dataclass(frozen=True)
class FitConfig:
    """Everything that decides a scene-graph fit; see ``PRESETS`` for the named trade-offs."""

    iterations: int = 3_000
    """Optimiser steps; each renders one training image."""
    resolution_schedule: tuple[tuple[float, int], ...] = ((0.0, 4), (0.3, 2), (0.7, 1))
    """(fraction of iterations, downscale factor): from that point on, images are fitted at 1/factor size."""
    sh_degree: int = 1
    """Spherical-harmonic degree of colours (0 = view-independent)."""
    sh_degree_interval: int = 1_000
    """The active SH degree goes up by one every this many iterations."""
    plan: PlanConfig = field(default_factory=PlanConfig)
    """Scene plan settings (which tracks become nodes, Gaussian budget, held-out frames)."""
    init_budget_fraction: float = 0.6
    """Seeds fill this share of each node's part of the plan's Gaussian budget; densification may grow
    the node up to its full part."""
    strategy: DensifyStrategy = field(default_factory=DensifyStrategy)
    """Densify / prune / opacity-reset schedule."""
    lr: LearningRates = field(default_factory=LearningRates)
    """Learning rates."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Loss terms."""
    init: InitConfig = field(default_factory=InitConfig)
    """Initialisation."""
    render: RenderSettings = field(default_factory=RenderSettings)
    """Rasterizer settings (stored with the graph, used again when rendering it)."""
    sky_height: int = 32
    """Rows of the sky texture (latitude)."""
    sky_width: int = 128
    """Columns of the sky texture (longitude)."""
    max_loss_ratio: float = 5.0
    """The fit is declared diverged when the smoothed loss exceeds this multiple of its best value."""
    divergence_warmup: int = 50
    """Iterations before the loss-ratio test starts (the first losses are noisy)."""
    seed: int = 0
    """Seed of view order, ray seeds and splits."""
    torch_threads: int = 1
    """torch CPU threads; the rasterizer's Numba kernels have their own pool, and on a 2-core machine one
    torch thread is faster than two for the small per-node tensor operations."""
    device: str = "cpu"
    """Torch device the graph is fitted on: 'cpu' (the Numba rasterizer) or 'cuda' / 'cuda:<index>' (gsplat).
    Where a fit runs, not what it means: not in ``to_dict``. Asking for CUDA where there is none is an error."""

    def __post_init__(self) -> None:
        resolve_device(self.device)

    @property
    def torch_device(self) -> torch.device:
        return resolve_device(self.device)

    def to_dict(self) -> dict:
        """The settings that decide what the fit is (recorded in checkpoints, hashed into stage keys); the
        device is left out, so moving a fit between CPU and GPU keeps its fingerprint."""
        d = dataclasses.asdict(self)
        for name in EXECUTION_ONLY_FIELDS:
            del d[name]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "FitConfig":
        """The config of ``to_dict`` (the device is the default unless ``d`` names one)."""
        d = dict(d)
        nested = {"plan": PlanConfig, "strategy": DensifyStrategy, "lr": LearningRates, "loss": LossConfig,
                  "init": InitConfig, "render": RenderSettings}
        for key, kind in nested.items():
            if key in d:
                d[key] = kind(**d[key])
        if "resolution_schedule" in d:
            d["resolution_schedule"] = tuple(tuple(x) for x in d["resolution_schedule"])
        return cls(**d)

    def downscale_at(self, step: int) -> int:
        factor = 1
        for start, f in self.resolution_schedule:
            if step >= start * self.iterations:
                factor = f
        return factor


#: Measured on 40-frame, 3-camera 480x270 procedural logs on 2 shared cores: see ``omniscs bench fit``.
PRESETS: dict[str, FitConfig] = {
    "fast": FitConfig(
        iterations=1_500, resolution_schedule=((0.0, 4), (0.4, 2)), sh_degree=0,
        plan=PlanConfig(gaussians_per_m2=1.5, gaussians_per_agent=1_000, max_gaussians=60_000),
        strategy=DensifyStrategy(refine_start_iter=200, refine_stop_iter=1_300, refine_every=100, reset_every=0),
    ),
    "balanced": FitConfig(
        iterations=3_000, resolution_schedule=((0.0, 4), (0.25, 2), (0.6, 1)), sh_degree=1,
        plan=PlanConfig(gaussians_per_m2=3.0, gaussians_per_agent=2_000, max_gaussians=150_000),
        strategy=DensifyStrategy(refine_start_iter=300, refine_stop_iter=2_500, refine_every=100, reset_every=1_500),
    ),
    "accurate": FitConfig(
        iterations=5_000, resolution_schedule=((0.0, 4), (0.2, 2), (0.5, 1)), sh_degree=2,
        plan=PlanConfig(gaussians_per_m2=5.0, gaussians_per_agent=3_000, max_gaussians=250_000),
        strategy=DensifyStrategy(refine_start_iter=500, refine_stop_iter=4_200, refine_every=100, reset_every=2_000),
    ),
}


def fit_preset(name: str, **overrides) -> FitConfig:
    """A named preset with some fields replaced (e.g. ``iterations=50`` for a smoke test)."""
    if name not in PRESETS:
        raise OmniscsError(f"unknown preset {name!r}; use one of {list(PRESETS)}")
    return replace_checked("fit", PRESETS[name], overrides)
