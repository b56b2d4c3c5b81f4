"""Fitting a scene graph to a driving log: L1 + SSIM + LiDAR depth, per-camera exposure, Adam, densification."""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import OmniscsError
from omniscs.nsg.checkpoint import save_checkpoint
from omniscs.nsg.config import FitConfig
from omniscs.gaussians import GaussianParams, concat_params
from omniscs.nsg.graph import BACKGROUND, SceneGraph, agent_key, render_view
from omniscs.nsg.init import agent_scene_scale, background_scene_scale, initial_graph, node_budgets
from omniscs.quality import psnr, ssim, ssim_loss
from omniscs.nsg.observations import Observations, View
from omniscs.nsg.sky import SkyParams
from omniscs.nsg.strategy import (OptimisedGaussians, SharedAdam, add_screen_gradients, all_finite, refine,
                                  reset_opacities, screen_gradient_norms)
from omniscs.plan import ScenePlan
from omniscs.progress import Progress
from omniscs.scene.store import Scene

log = logging.getLogger(__name__)

#: Smoothing of the loss for the divergence test and of the PSNR shown while fitting.
LOSS_EMA = 0.9

#: A progress callback: (iteration, total iterations, smoothed loss, smoothed training PSNR in dB).


class FitDiverged(OmniscsError):
    """The fit blew up (non-finite or exploding loss or parameters); nothing was saved as a result."""

    def __init__(self, step: int, reason: str) -> None:
        super().__init__(f"scene-graph fit diverged at iteration {step}: {reason}; lower the learning rates "
                         "or use another preset")
        self.step = step
        self.reason = reason


@dataclass
class DivergenceMonitor:
    """Flags a non-finite loss at once, and a smoothed loss above ``max_ratio`` x its best after warm-up."""

    max_ratio: float
    warmup: int
    ema: float | None = None
    best: float = math.inf
    seen: int = 0

    def update(self, loss: float) -> str | None:
        if not math.isfinite(loss):
            return f"loss is {loss}"
        self.seen += 1
        self.ema = loss if self.ema is None else LOSS_EMA * self.ema + (1 - LOSS_EMA) * loss
        self.best = min(self.best, self.ema)
        if self.seen >= self.warmup and self.ema > self.max_ratio * self.best:
            return f"smoothed loss {self.ema:.4g} exceeds {self.max_ratio:g} x its best {self.best:.4g}"
        return None

    def restart(self) -> None:
        """Forget the history: after an opacity reset the loss jumps on purpose."""
        self.ema, self.best, self.seen = None, math.inf, 0


@dataclass(frozen=True)
class FitResult:
    graph: SceneGraph
    plan: ScenePlan
    config: FitConfig
    metrics: dict
    history: list[dict] = field(default_factory=list)


def photometric_loss(rendered: Tensor, target: Tensor,  # [H, W, 3]
                     config: FitConfig) -> Tensor:
    l1 = (rendered - target).abs().mean()
    if config.loss.ssim_weight == 0:
        return l1
    a, b = rendered.permute(2, 0, 1)[None].contiguous(), target.permute(2, 0, 1)[None].contiguous()
    window = min(config.loss.ssim_window, 2 * (min(target.shape[:2]) // 2) - 1)
    dssim = 2.0 * ssim_loss(a, b, max(window, 1))  # (1 - SSIM) / 2, as kornia's
    return (1 - config.loss.ssim_weight) * l1 + config.loss.ssim_weight * dssim


def lidar_depth_loss(depth: Tensor, alpha: Tensor,  # [h, w] expected depth and coverage
                     uv: np.ndarray, z: np.ndarray,  # [M, 2] full-resolution pixels, [M] LiDAR depths
                     factor: int, min_alpha: float) -> Tensor:
    """Mean relative error |D - z| / z of the expected depth at the LiDAR returns' pixels that are covered."""
    if len(z) == 0:
        return depth.sum() * 0.0
    h, w = depth.shape
    px = torch.from_numpy(np.clip((uv[:, 0] / factor).astype(np.int64), 0, w - 1)).to(depth.device)
    py = torch.from_numpy(np.clip((uv[:, 1] / factor).astype(np.int64), 0, h - 1)).to(depth.device)
    target = torch.from_numpy(z.astype(np.float32)).to(depth.device)
    d, a = depth[py, px], alpha[py, px].detach()
    covered = a > min_alpha
    if not bool(covered.any()):
        return depth.sum() * 0.0
    return ((d[covered] - target[covered]).abs() / target[covered]).mean()


def evaluate_graph(graph: SceneGraph, obs: Observations, frames, cameras=None) -> dict:
    """Full-resolution PSNR and SSIM of ``graph`` against the logged images of ``frames`` x ``cameras`` (None when
    there is no such view: a scene too short to hold frames out has no held-out score, not a NaN)."""
    cameras = tuple(cameras or [c.name for c in graph.cameras])
    rows = []
    for f in frames:
        for cam in cameras:
            out = graph.render(obs.view(cam, f))
            target = obs.image(cam, f)
            rows.append({"frame": int(f), "camera": cam, "psnr": psnr(out.rgb, target), "ssim": ssim(out.rgb, target)})
    if not rows:
        return {"psnr": None, "ssim": None, "n_views": 0, "views": []}
    return {"psnr": float(np.mean([r["psnr"] for r in rows])), "ssim": float(np.mean([r["ssim"] for r in rows])),
            "n_views": len(rows), "views": rows}


class _Trainer:
    """Live parameters of every node, their optimisers and the training loop's bookkeeping.

    ``trainable`` ({node key: [n] bool}) limits optimisation to some rows of a node: the others are held fixed
    (no gradients, no optimiser state, never densified or pruned) and rendered before the trainable ones. A
    node without an entry is wholly trainable; ``aux`` says whether the sky and exposures are optimised too.
    """

    def __init__(self, template: SceneGraph, config: FitConfig, budgets: Mapping[str, int],
                 scene_scale: Mapping[str, float], trainable: Mapping[str, Tensor] | None = None,
                 aux: bool = True) -> None:
        self.config, self.template = config, template
        self.generator = torch.Generator().manual_seed(config.seed)  # host generator: same splits on any device
        self.adam = SharedAdam()  # every node's Gaussians, stepped once a step
        self.nodes: dict[str, OptimisedGaussians] = {}
        self.fixed: dict[str, GaussianParams] = {}
        self.scene_scale: dict[str, float] = {}
        self.budget: dict[str, int] = {}
        self.base_means_lr: dict[str, float] = {}
        trainable = dict(trainable or {})
        unknown = sorted(set(trainable) - {BACKGROUND} - {agent_key(a.track_id) for a in template.agents})
        if unknown:
            raise OmniscsError(f"trainable rows name node(s) {unknown} that the scene graph does not have")
        for key, params in [(BACKGROUND, template.background)] + [(agent_key(a.track_id), a.gaussians)
                                                                  for a in template.agents]:
            rows = trainable.get(key)
            if rows is not None:
                rows = rows.to(params.device)
                self.fixed[key] = params.select(torch.nonzero(~rows).squeeze(1)).detached()
                params = params.select(torch.nonzero(rows).squeeze(1))
            self._add_node(key, params, scene_scale[key], budgets[key])
        self.sky = template.sky.texture.clone().requires_grad_(aux)
        self.exposure = {c: t.clone().requires_grad_(aux) for c, t in template.exposure.items()}
        self.aux_optimizer = None
        if aux:
            self.aux_optimizer = torch.optim.Adam(
                [{"params": [self.sky], "lr": config.lr.sky},
                 {"params": list(self.exposure.values()), "lr": config.lr.exposure}], eps=1e-15, fused=True)

    @classmethod
    def for_scene(cls, scene: Scene, plan: ScenePlan, config: FitConfig, obs: Observations) -> "_Trainer":
        """A fresh fit: nodes seeded from the scene as the plan says."""
        template = initial_graph(scene, plan, config, obs)  # on config.device
        budgets = node_budgets(plan, config)
        sizes = {agent_key(a.track_id): budgets.per_agent for a in template.agents}
        scales = {agent_key(a.track_id): agent_scene_scale(a.size) for a in template.agents}
        return cls(template, config, {BACKGROUND: budgets.background, **sizes},
                   {BACKGROUND: background_scene_scale(scene, plan.cameras), **scales})

    def _add_node(self, key: str, params, scene_scale: float, budget: int) -> None:
        lr = self.config.lr
        rates = {"means": lr.means * scene_scale, "quats": lr.quats, "log_scales": lr.log_scales,
                 "opacity_logits": lr.opacity_logits, "sh_dc": lr.sh_dc, "sh_rest": lr.sh_rest}
        self.nodes[key] = OptimisedGaussians(params, rates, self.adam)
        self.scene_scale[key] = scene_scale
        self.budget[key] = max(budget, len(params))
        self.base_means_lr[key] = rates["means"]

    def graph(self, frozen: bool = False) -> SceneGraph:
        def get(key: str) -> GaussianParams:
            node = self.nodes[key].frozen() if frozen else self.nodes[key].current()
            return node if key not in self.fixed else concat_params([self.fixed[key], node])

        agents = tuple(dataclasses.replace(a, gaussians=get(agent_key(a.track_id))) for a in self.template.agents)
        sky = self.sky.detach().clone() if frozen else self.sky
        exposure = {c: (t.detach().clone() if frozen else t) for c, t in self.exposure.items()}
        return self.template.replace(background=get(BACKGROUND), agents=agents, sky=SkyParams(sky), exposure=exposure)

    def finite(self) -> bool:
        # one test over every node's tensors (per node, the tests' own overhead was 2.5 ms of a step with 40 nodes)
        return all_finite([t for n in self.nodes.values() for t in n.params.values()] + [self.sky,
                                                                                          *self.exposure.values()])

    @property
    def n_gaussians(self) -> int:
        return sum(len(n) for n in self.nodes.values()) + sum(len(p) for p in self.fixed.values())

    def step(self, step: int, view: View, target: Tensor, factor: int,
             depth_targets: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float]:
        """One optimiser step on one view; ``depth_targets`` (full-resolution pixels uv [M, 2], depths [M]) adds
        the depth loss (LiDAR returns in a fit)."""
        cfg = self.config
        active_sh = min(cfg.sh_degree, step // max(1, cfg.sh_degree_interval))
        out = render_view(self.graph(), view, sh_degree=active_sh, absgrad=cfg.strategy.absgrad)
        means2d = out.meta.get("means2d")
        if means2d is not None and means2d.requires_grad:
            means2d.retain_grad()
        unknown = torch.isnan(target)
        if bool(unknown.any()):  # pixels a target leaves NaN are not supervised: the render stands in for them
            target = torch.where(unknown, out.rgb.detach(), target)
        loss = photometric_loss(out.rgb, target, cfg)
        if cfg.loss.depth_weight > 0 and depth_targets is not None:
            uv, z = depth_targets
            loss = loss + cfg.loss.depth_weight * lidar_depth_loss(out.depth, out.alpha, uv, z, factor,
                                                                   cfg.loss.depth_min_alpha)
        loss_value = float(loss.detach())
        if not math.isfinite(loss_value):
            return loss_value, float("nan")
        loss.backward()
        refining = step < cfg.strategy.refine_stop_iter
        if refining and means2d is not None and means2d.grad is not None:
            grads = means2d.absgrad if cfg.strategy.absgrad else means2d.grad
            norms, visible = screen_gradient_norms(grads[0], out.meta["radii"][0], view.width, view.height)
            for key, sl in out.node_slices.items():
                sl = slice(sl.start + len(self.fixed.get(key, ())), sl.stop)  # fixed rows come first
                if sl.stop > sl.start:
                    add_screen_gradients(self.nodes[key], norms[sl], visible[sl])
        progress = step / max(1, cfg.iterations - 1)
        decay = cfg.lr.means_final_ratio ** progress
        for key, node in self.nodes.items():
            node.set_lr("means", self.base_means_lr[key] * decay)
        self.adam.step()
        if self.aux_optimizer is not None:
            self.aux_optimizer.step()
            self.aux_optimizer.zero_grad(set_to_none=True)
        if cfg.strategy.is_refine_step(step):
            for key, node in self.nodes.items():
                if len(node):
                    refine(cfg.strategy, node, step, self.scene_scale[key], self.budget[key], self.generator)
        if cfg.strategy.is_reset_step(step):
            for node in self.nodes.values():
                reset_opacities(cfg.strategy, node)
        return loss_value, psnr(out.rgb.detach(), target)


def fit_scene(scene: Scene, config: FitConfig, plan: ScenePlan, progress: Progress | None = None,
              evaluate: bool = True, checkpoint_dir: str | Path | None = None, overwrite: bool = False) -> FitResult:
    """Fit a scene graph to ``scene``: nodes from ``plan`` (the plan stage decides what is modelled; the fit
    never re-plans), trained on its training frames, evaluated on its held-out frames, saved to
    ``checkpoint_dir`` when given. Raises FitDiverged (and saves nothing) when the fit blows up."""
    if not isinstance(plan, ScenePlan):
        raise OmniscsError(f"fit_scene needs the scene's plan (omniscs.plan.make_plan), got {type(plan).__name__}")
    if plan.content_hash != scene.content_hash:
        raise OmniscsError(f"plan is for scene content {plan.content_hash[:12]}, not {scene.scene_id} "
                           f"({scene.content_hash[:12]}); re-plan")
    if not plan.train_frames:
        raise OmniscsError(f"scene {scene.scene_id} has no training frames (it has {scene.n_frames} frame(s)); "
                           "set holdout_every=0 or use a longer log")
    if checkpoint_dir is not None and Path(checkpoint_dir).exists() and not overwrite:
        raise OmniscsError(f"{checkpoint_dir} already exists; choose another checkpoint folder or overwrite it")
    threads = torch.get_num_threads()
    torch.set_num_threads(config.torch_threads)
    try:
        result = _fit(scene, plan, config, progress, evaluate)
    finally:
        torch.set_num_threads(threads)
    if checkpoint_dir is not None:
        save_checkpoint(result.graph, checkpoint_dir, plan, config.to_dict(), {"status": "fitted", **result.metrics},
                        overwrite=overwrite)
    return result


#: One training sample: the view at the step's resolution, its target image [h, w, 3], the downscale factor and
#: the depth targets (full-resolution pixels uv [M, 2], depths [M]) or None.
Sample = tuple[View, Tensor, int, "tuple[np.ndarray, np.ndarray] | None"]


#: Per-view divergence compares with at least this loss: a crop that is almost perfectly fitted varies by more
#: than the ratio in noise alone.
PER_VIEW_LOSS_FLOOR = 0.02


@dataclass
class PerViewDivergence:
    """For samples whose losses differ by orders of magnitude (a refit's crops): a non-finite loss at once, and a
    view's loss above ``max_ratio`` x the lowest that same view had, once it was seen before."""

    max_ratio: float
    best: dict = field(default_factory=dict)

    def update(self, loss: float, view: int) -> str | None:
        if not math.isfinite(loss):
            return f"loss is {loss}"
        best = self.best.get(view)
        if best is not None and loss > self.max_ratio * max(best, PER_VIEW_LOSS_FLOOR):
            return f"loss {loss:.4g} of view {view} exceeds {self.max_ratio:g} x its best {best:.4g}"
        self.best[view] = loss if best is None else min(best, loss)
        return None


def train_loop(trainer: _Trainer, n_views: int, sample: Callable[[int, int], Sample], label: str,
               progress: Progress | None, per_view: bool = False) -> tuple[list[dict], float | None, float | None]:
    """The training loop every fit and refit runs: ``trainer.config.iterations`` steps over ``n_views`` views in
    seeded random order (``sample(view_index, step)`` makes each step's sample), divergence detection (raises
    FitDiverged; ``per_view`` compares each view's loss with its own best, for samples of very unequal loss), smoothed loss and PSNR, history every 50 steps. Returns (history, loss EMA, PSNR EMA)."""
    config = trainer.config
    started = time.perf_counter()
    monitor = DivergenceMonitor(config.max_loss_ratio, config.divergence_warmup)
    views = PerViewDivergence(config.max_loss_ratio) if per_view else None
    rng = np.random.default_rng(config.seed)
    order: list[int] = []
    history: list[dict] = []
    psnr_ema = loss_ema = None
    last_factor = None
    for step in range(config.iterations):
        if not order:
            order = list(rng.permutation(n_views))
        index = order.pop()
        view, target, factor, depth = sample(index, step)
        if last_factor is not None and factor != last_factor:
            # A finer image has detail the coarser one lacked: the loss rises on purpose (a 3-frame 160x90 fit's
            # smoothed loss went from 0.008 to 0.044 at the 1/4 -> 1/2 step), so the test starts again.
            monitor.restart()
            if views is not None:
                views.best.clear()
        last_factor = factor
        loss, train_psnr = trainer.step(step, view, target, factor, depth)
        reason = views.update(loss, index) if views is not None else monitor.update(loss)
        if reason is None and not trainer.finite():
            reason = "parameters became NaN or infinite"
        if reason is not None:
            log.warning("%s diverged at iteration %d: %s", label, step, reason)
            raise FitDiverged(step, reason)
        if config.strategy.is_reset_step(step):
            monitor.restart()
        psnr_ema = train_psnr if psnr_ema is None else LOSS_EMA * psnr_ema + (1 - LOSS_EMA) * train_psnr
        loss_ema = loss if loss_ema is None else LOSS_EMA * loss_ema + (1 - LOSS_EMA) * loss
        if step % 50 == 0 or step == config.iterations - 1:
            history.append({"iteration": step, "loss": loss_ema, "train_psnr": psnr_ema, "factor": factor,
                            "n_gaussians": trainer.n_gaussians, "seconds": time.perf_counter() - started})
        if progress is not None:
            progress(step + 1, config.iterations, f"loss {loss_ema:.4f}  PSNR {psnr_ema:.2f} dB")
    return history, loss_ema, psnr_ema


def _fit(scene: Scene, plan: ScenePlan, config: FitConfig, progress: Progress | None, evaluate: bool) -> FitResult:
    started = time.perf_counter()
    obs = Observations(scene, plan.cameras, config.torch_device)
    trainer = _Trainer.for_scene(scene, plan, config, obs)
    n_init = trainer.template.n_gaussians
    init_seconds = time.perf_counter() - started
    views = [(c, f) for f in plan.train_frames for c in plan.cameras]
    with_depth = config.loss.depth_weight > 0

    def sample(i: int, step: int) -> Sample:
        cam, f = views[i]
        factor = config.downscale_at(step)
        return (obs.view(cam, f).downscaled(factor), obs.image(cam, f, factor), factor,
                obs.lidar_depth_targets(cam, f) if with_depth else None)

    history, loss_ema, psnr_ema = train_loop(trainer, len(views), sample, f"fit of {scene.scene_id}", progress)
    graph = trainer.graph(frozen=True)
    train_seconds = time.perf_counter() - started
    metrics = {"iterations": config.iterations, "fit_seconds": train_seconds, "init_seconds": init_seconds,
               "n_gaussians_init": n_init, "n_gaussians": graph.n_gaussians,
               "n_agent_nodes": len(graph.agents), "final_loss": loss_ema, "train_psnr": psnr_ema}
    if evaluate:
        held = evaluate_graph(graph, obs, plan.heldout_frames, plan.cameras)
        metrics.update({"heldout_psnr": held["psnr"], "heldout_ssim": held["ssim"], "heldout_views": held["n_views"],
                        "eval_seconds": time.perf_counter() - started - train_seconds})
    return FitResult(graph, plan, config, metrics, history)


def refit(graph: SceneGraph, config: FitConfig, n_views: int, sample: Callable[[int, int], Sample],
          trainable: Mapping[str, Tensor] | None = None, scene_scale: Mapping[str, float] | None = None,
          budgets: Mapping[str, int] | None = None, label: str = "refit",
          progress: Progress | None = None) -> tuple[SceneGraph, list[dict]]:
    """Optimise an already fitted ``graph`` further with the fit's own step and loop: ``config.iterations``
    steps over ``n_views`` samples (``sample(view_index, step)``: the targets need not be the log's images),
    only the ``trainable`` rows of each named node changing (the RoI-guided background refit; no entry: the
    whole node), the sky and exposures held. ``budgets`` caps each node's trainable rows (default: as many as
    it starts with, so densification only replaces); ``scene_scale`` sizes the means' learning rate and the
    densification thresholds (default 10 m). Raises FitDiverged (nothing returned) when it blows up."""
    keys = [BACKGROUND] + [agent_key(a.track_id) for a in graph.agents]
    sizes = {BACKGROUND: len(graph.background), **{agent_key(a.track_id): len(a.gaussians) for a in graph.agents}}
    rows = {k: int(trainable[k].sum()) if trainable and k in trainable else sizes[k] for k in keys}
    budgets = {k: max(rows[k], (budgets or {}).get(k, rows[k])) for k in keys}
    scales = {k: (scene_scale or {}).get(k, 10.0) for k in keys}
    threads = torch.get_num_threads()
    torch.set_num_threads(config.torch_threads)
    try:
        trainer = _Trainer(graph, config, budgets, scales, trainable, aux=False)
        history, _, _ = train_loop(trainer, n_views, sample, label, progress, per_view=True)
        return trainer.graph(frozen=True), history
    finally:
        torch.set_num_threads(threads)
