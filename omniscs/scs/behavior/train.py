"""Training the traffic model on procedural traffic (unlimited, no rendering) and scene stores, and measuring
its reconstruction and prediction error (ADE/FDE) on held-out scenes against a constant-velocity baseline.

The procedural logs come from a ``ProceduralLogs`` source the caller injects (the CLI passes
``omniscs.pipeline.procedural.procedural_traffic``): model code never imports the procedural world."""
from __future__ import annotations

import logging
import math
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from omniscs.errors import OmniscsError
from omniscs.overrides import replace_checked
from omniscs.scs.behavior.augment import AugmentConfig, augment_traffic
from omniscs.devices import resolve_device
from omniscs.scs.behavior.checkpoint import save_checkpoint, set_threads
from omniscs.scs.behavior.features import SceneSample, build_sample, collate
from omniscs.scs.behavior.model import ModelConfig, TrafficModel
from omniscs.scs.behavior.tracks import TrafficScene, traffic_from_scene

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]  # (stage, done, total)
#: The traffic of one procedural log: (template, seed, frames) -> TrafficScene, never rendered; raises OmniscsError
#: for a seed of a template that cannot be built (training skips it).
ProceduralLogs = Callable[[str, int, int], TrafficScene]

#: Road templates that training draws procedural worlds from.
TRAIN_TEMPLATES = ("straight", "t_junction", "intersection", "straight_parked_truck")
#: Seeds of training worlds start here; held-out worlds and benchmark scenes use other ranges.
TRAIN_SEED_OFFSET = 100_000
HELDOUT_SEED_OFFSET = 900_000
#: A future counts as "moving" for the metrics when the agent travels further than this (metres).
MOVING_FUTURE_M = 1.0


@dataclass(frozen=True)
class TrainConfig:
    """How the traffic model is trained (see PRESETS for the speed/accuracy trade-off)."""

    seed: int = 0
    """Seed of the training worlds, the held-out worlds and the network initialisation."""
    n_worlds: int = 600
    """Procedural training worlds (each gives ``len(now_steps)`` samples)."""
    now_steps: tuple[int, ...] = (9, 19)
    """Now steps sampled from each training world (each needs ``future_steps`` more frames)."""
    heldout_worlds: int = 60
    """Procedural worlds (other seeds) kept out of training for ADE/FDE."""
    steps: int = 5_000
    """Optimiser steps."""
    batch_size: int = 16
    """Scenes per step."""
    lr: float = 2e-3
    """Adam learning rate (cosine-decayed to 5% over ``steps``)."""
    kl_weight: float = 0.05
    """Weight of the KL term (beta of the beta-VAE) after warm-up."""
    free_nats_per_dim: float = 0.1
    """KL below this many nats per latent dimension (batch mean) is not penalised (free bits)."""
    kl_warmup_steps: int = 500
    """Steps over which the KL weight rises linearly from 0."""
    grad_clip: float = 5.0
    """Gradient-norm clip."""
    eval_every: int = 1_000
    """Steps between held-out evaluations logged during training (0 = only at the end)."""
    prior_samples: int = 6
    """Samples from the prior for the min-of-K prediction metric."""
    torch_threads: int = 1
    """torch CPU threads (1: the development machines have 2 shared cores)."""
    device: str = "cpu"
    """Where the model trains and is evaluated: "cpu" or "cuda" ("cuda:N"); samples are built on the CPU."""
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    """Manoeuvre augmentation of training futures (lane and speed changes), so the latent carries manoeuvres."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Architecture of the model to train."""


#: Named presets: ``fast`` (a smoke test, seconds), ``balanced`` (the shipped checkpoint), ``accurate``.
PRESETS: dict[str, TrainConfig] = {
    "fast": TrainConfig(n_worlds=24, heldout_worlds=8, steps=60, batch_size=8, kl_warmup_steps=20, eval_every=0),
    "balanced": TrainConfig(),
    "accurate": TrainConfig(n_worlds=1_500, heldout_worlds=100, steps=12_000, kl_warmup_steps=1_000,
                            eval_every=2_000),
}


def train_preset(name: str, **overrides) -> TrainConfig:
    if name not in PRESETS:
        raise OmniscsError(f"unknown training preset {name!r}; use one of {list(PRESETS)}")
    return replace_checked("training", PRESETS[name], overrides)


def world_frames(model: ModelConfig, now_steps: tuple[int, ...]) -> int:
    return max(now_steps) + 1 + model.future_steps


def procedural_samples(logs: ProceduralLogs, n_worlds: int, seed_offset: int, now_steps: tuple[int, ...],
                       model: ModelConfig, progress: Progress | None = None, stage: str = "worlds",
                       augment: AugmentConfig | None = None) -> list[SceneSample]:
    """Samples from procedural logs ``seed_offset + i`` (templates in turn), without rendering anything;
    with ``augment``, some moving vehicles' futures become lane or speed changes (seeded per log)."""
    frames = world_frames(model, now_steps)
    out = []
    for i in range(n_worlds):
        template = TRAIN_TEMPLATES[i % len(TRAIN_TEMPLATES)]
        try:
            traffic = logs(template, seed_offset + i, frames)
        except OmniscsError as exc:  # a few seeds of some templates cannot be built; skip them
            log.warning("skipping procedural world %s seed %d: %s", template, seed_offset + i, exc)
            if progress:
                progress(stage, i + 1, n_worlds)
            continue
        rng = np.random.default_rng([seed_offset, i])
        for now in now_steps:
            scene = traffic if augment is None else augment_traffic(traffic, now, model.future_steps, rng, augment)
            out.append(build_sample(scene, now, model.history_steps, model.future_steps, model.crop))
        if progress:
            progress(stage, i + 1, n_worlds)
    return out


def scene_store_samples(paths: list[Path], model: ModelConfig) -> list[SceneSample]:
    """Samples from scene stores (recorded logs add real traffic): every now step with a full future."""
    from omniscs.scene import load_scene

    out = []
    for p in paths:
        traffic = traffic_from_scene(load_scene(p), dt=model.dt)
        last = traffic.n_steps - 1 - model.future_steps
        for now in range(model.history_steps - 1, last + 1, model.future_steps):
            out.append(build_sample(traffic, now, model.history_steps, model.future_steps, model.crop))
    return out


def train_model(config: TrainConfig, logs: ProceduralLogs, out_dir: Path | None = None, command: str = "",
                extra_scenes: list[Path] = (), progress: Progress | None = None,
                overwrite: bool = False) -> tuple[TrafficModel, dict]:
    """Train on procedural logs from ``logs`` (+ optional scene stores); evaluate on held-out procedural logs;
    save to ``out_dir``.

    Returns the model and the training record (also written beside the weights as training.json).
    """
    if out_dir is not None and Path(out_dir).exists() and not overwrite:
        raise OmniscsError(f"{out_dir} already exists; choose another --out or pass --overwrite")
    device = resolve_device(config.device)
    previous_threads = set_threads(config.torch_threads)
    started = time.perf_counter()
    try:
        torch.manual_seed(config.seed)
        rng = np.random.default_rng(config.seed)
        train = procedural_samples(logs, config.n_worlds, TRAIN_SEED_OFFSET + 10_000 * config.seed, config.now_steps,
                                   config.model, progress, "training worlds", config.augment)
        train += scene_store_samples([Path(p) for p in extra_scenes], config.model)
        heldout_seed = HELDOUT_SEED_OFFSET + 10_000 * config.seed
        heldout = procedural_samples(logs, config.heldout_worlds, heldout_seed, (9,), config.model, progress,
                                     "held-out worlds")
        heldout_manoeuvres = procedural_samples(logs, config.heldout_worlds, heldout_seed, (9,), config.model,
                                                progress, "held-out worlds (manoeuvres)", config.augment)
        data_seconds = time.perf_counter() - started
        model = TrafficModel(config.model).to(device)  # initialised on the CPU, so every device starts alike
        opt = torch.optim.Adam(model.parameters(), lr=config.lr)
        history = []
        t0 = time.perf_counter()
        for step in range(config.steps):
            frac = step / max(1, config.steps - 1)
            for g in opt.param_groups:
                g["lr"] = config.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))
            kl_w = config.kl_weight * min(1.0, (step + 1) / max(1, config.kl_warmup_steps))
            idx = rng.choice(len(train), size=min(config.batch_size, len(train)), replace=False)
            model.train()
            batch = collate([train[i] for i in idx]).to(device)
            out = model.losses(batch, kl_w, free_nats_per_dim=config.free_nats_per_dim)
            opt.zero_grad()
            out["loss"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            opt.step()
            if step % 50 == 0 or step == config.steps - 1:
                history.append({"step": step, **{k: round(float(v.detach()), 4) for k, v in out.items()}})
            if config.eval_every and step and step % config.eval_every == 0:
                m = evaluate(model, heldout[: max(8, len(heldout) // 4)], config.prior_samples)
                log.info("step %d: held-out moving ADE posterior %.2f m, prior %.2f m, CV %.2f m", step,
                         m["moving"]["posterior"]["ade"], m["moving"]["prior_mean"]["ade"],
                         m["moving"]["constant_velocity"]["ade"])
            if progress:
                progress("training", step + 1, config.steps)
        train_seconds = time.perf_counter() - t0
        model.eval()
        metrics = evaluate(model, heldout, config.prior_samples)
        metrics_manoeuvres = evaluate(model, heldout_manoeuvres, config.prior_samples)
        record = {
            "seed": config.seed, "command": command, "config": _jsonable(asdict(config)),
            "data": {"training_samples": len(train), "training_worlds": config.n_worlds,
                     "scene_stores": [str(p) for p in extra_scenes], "heldout_worlds": config.heldout_worlds,
                     "heldout_samples": len(heldout), "templates": list(TRAIN_TEMPLATES),
                     "train_seeds": [TRAIN_SEED_OFFSET + 10_000 * config.seed,
                                     TRAIN_SEED_OFFSET + 10_000 * config.seed + config.n_worlds - 1],
                     "heldout_seeds": [HELDOUT_SEED_OFFSET + 10_000 * config.seed,
                                       HELDOUT_SEED_OFFSET + 10_000 * config.seed + config.heldout_worlds - 1]},
            "heldout_metrics": metrics, "heldout_manoeuvre_metrics": metrics_manoeuvres,
            "loss_history": history,
            "seconds": {"data": round(data_seconds, 1), "training": round(train_seconds, 1)},
            "parameters": sum(p.numel() for p in model.parameters()),
            "torch": torch.__version__, "python": platform.python_version(), "threads": config.torch_threads,
        }
        if out_dir is not None:
            save_checkpoint(model, Path(out_dir), record, overwrite=overwrite)
        return model, record
    finally:
        set_threads(previous_threads)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def constant_velocity(state0: torch.Tensor, horizon: int, dt: float) -> torch.Tensor:  # [..., 5] -> [..., T, 2]
    """The baseline: keep the current speed and heading."""
    t = torch.arange(1, horizon + 1, dtype=state0.dtype, device=state0.device) * dt
    heading = torch.stack([torch.cos(state0[..., 2]), torch.sin(state0[..., 2])], -1)
    return state0[..., None, :2] + (state0[..., 3, None, None] * t[:, None]) * heading[..., None, :]


@torch.no_grad()
def evaluate(model: TrafficModel, samples: list[SceneSample], prior_samples: int = 6,
             batch_size: int = 16) -> dict:
    """ADE/FDE (metres) over non-ego agents with a complete logged future: posterior mean (reconstruction),
    prior mean and best of ``prior_samples`` prior samples (prediction), and constant velocity; for all
    such agents and for those that move more than MOVING_FUTURE_M."""
    sums: dict[str, dict[str, list[float]]] = {}
    device = next(model.parameters()).device
    for start in range(0, len(samples), batch_size):
        batch = collate(samples[start:start + batch_size]).to(device)
        context, edges, edge_mask = model.encode_past(batch)
        horizon = batch.future.shape[2]
        mu_q, _ = model.posterior(context, batch, edges, edge_mask)
        mu_p, logvar_p = model.prior(context)
        preds = {
            "posterior": model.decode(context, mu_q, batch, edges, edge_mask, horizon).states[..., :2],
            "prior_mean": model.decode(context, mu_p, batch, edges, edge_mask, horizon).states[..., :2],
            "constant_velocity": constant_velocity(batch.state0, horizon, model.config.dt),
        }
        draws = [model.decode(context, mu_p + torch.randn_like(mu_p) * torch.exp(0.5 * logvar_p), batch, edges,
                              edge_mask, horizon).states[..., :2] for _ in range(prior_samples)]
        target = batch.future[..., :2]
        full = batch.future_mask.all(-1) & batch.node_mask & ~batch.is_ego
        moving = full & ((target[..., -1, :] - batch.state0[..., :2]).norm(dim=-1) > MOVING_FUTURE_M)
        errs = {k: (v - target).norm(dim=-1) for k, v in preds.items()}
        draw_errs = torch.stack([(d - target).norm(dim=-1) for d in draws], 0)  # [K, B, N, T]
        best = draw_errs.mean(-1).argmin(0)  # [B, N]
        errs[f"prior_min_of_{prior_samples}"] = torch.gather(draw_errs, 0, best[None, ..., None].expand(
            1, *draw_errs.shape[1:]))[0]
        for group, mask in (("all", full), ("moving", moving)):
            g = sums.setdefault(group, {})
            for name, e in errs.items():
                g.setdefault(name + ":ade", []).extend(e.mean(-1)[mask].tolist())
                g.setdefault(name + ":fde", []).extend(e[..., -1][mask].tolist())
    out: dict = {}
    for group, g in sums.items():
        out[group] = {"agents": len(next(iter(g.values()))) if g else 0}
        for key, vals in g.items():
            name, metric = key.split(":")
            out[group].setdefault(name, {})[metric] = float(np.mean(vals)) if vals else float("nan")
    out["horizon_s"] = model.config.future_steps * model.config.dt
    return out
