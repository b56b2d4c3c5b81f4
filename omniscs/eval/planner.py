"""The embedded proxy planner: a small network, trained here on 2 cores, that plans 6 waypoints at 0.5 s from a
bird's-eye view. A stand-in for UniAD's planner (it sees boxes, not images), so that the paper's planning protocol
(base vs fine-tuned with behaviour-SCS data) runs end to end on this machine; real stacks run as external jobs.

Input (``features``), in UniAD's planning frame (x right, y forward; ``omniscs.eval.scenarios``):
  - a raster of ``GRID_W`` x ``GRID_H`` cells of ``CELL_M`` (x in [-20, 20) m, y in [-10, 30) m) with channels:
    vehicles now, vehicles ``HISTORY_S`` before (their motion), other road users now, drivable area (0 where the
    scene has no map);
  - a state vector: speed / 10, yaw rate, the driving command one-hot (right, left, forward), whether a map is there.
Output: 6 waypoints as offsets from driving on straight at the current speed.
Network: five stride-2 3x3 convolutions (16, 32, 64, 64, 64 channels, ReLU) over the raster, flattened, joined with the
state, two fully connected layers (256, ReLU) to 12 numbers. Loss: mean distance of the known waypoints (a keyframe
near a scenario's end has its later ones masked out), plus an optional collision loss (``TrainConfig.collision_weight``).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from omniscs.errors import ValidationError
from omniscs.pretrained.registry import folder as shipped_folder, network_with_weights, verified_folder
from omniscs.eval.planning import EGO_LENGTH, EGO_SHIFT, EGO_WIDTH, STEP_S, STEPS, footprints_on_grid
from omniscs.eval.scenarios import COMMANDS, PlanningExample, PlanningInput
from omniscs.progress import Progress, no_progress
from omniscs.storage import atomic_directory, atomic_write_json
from omniscs.untrusted import read_json

CELL_M = 0.5
X_RANGE = (-20.0, 20.0)
Y_RANGE = (-10.0, 30.0)
GRID_W = int(round((X_RANGE[1] - X_RANGE[0]) / CELL_M))
GRID_H = int(round((Y_RANGE[1] - Y_RANGE[0]) / CELL_M))
CHANNELS = ("vehicles", "vehicles_past", "others", "drivable")
STATE = ("speed_10", "yaw_rate", *(f"command_{c}" for c in COMMANDS), "has_map")
WEIGHTS = "planner.safetensors"
CONFIG = "planner_config.json"
TRAINING = "training.json"
#: The planner shipped with the package (registry entry ``planner``; ``omniscs pretrained train planner``).
DEFAULT_PLANNER = shipped_folder("planner")

#: The collision loss's margins (m) and weights, as UniAD configures its planner's three collision losses.
COLLISION_MARGINS = ((0.0, 2.5), (0.5, 1.0), (1.0, 0.25))
#: The future vehicles the collision loss looks at per step: the nearest to the true waypoint, within this reach.
COLLISION_BOXES, COLLISION_REACH_M = 8, 15.0
#: The ego box (as the metric places it: centred EGO_SHIFT ahead of the waypoint, not turned) as three circles of
#: its half width along its length.
_EGO_RADIUS = EGO_WIDTH / 2
_EGO_CIRCLES = EGO_SHIFT + np.array([-(EGO_LENGTH / 2 - _EGO_RADIUS), 0.0, EGO_LENGTH / 2 - _EGO_RADIUS])

_XS = X_RANGE[0] + (np.arange(GRID_W) + 0.5) * CELL_M
_YS = Y_RANGE[0] + (np.arange(GRID_H) + 0.5) * CELL_M


@dataclass(frozen=True)
class PlannerConfig:
    widths: tuple[int, ...] = (16, 32, 64, 64, 64)
    hidden: int = 256

    def __post_init__(self):
        if len(self.widths) < 1 or min(self.widths) < 1 or self.hidden < 1:
            raise ValidationError("planner widths and hidden size must be positive")
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 30
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0
    mirror: bool = True
    """Add every example mirrored left-right (x -> -x, commands swapped)."""
    collision_weight: float = 0.0
    """Weight of the collision loss (UniAD's planner trains with one): how far the ego box at each planned waypoint
    reaches into the true future vehicle boxes, with margins ``COLLISION_MARGINS``; 0 leaves it out."""

    def __post_init__(self):
        if self.epochs < 1 or self.batch_size < 1 or not (self.lr > 0) or self.weight_decay < 0 \
                or not (self.collision_weight >= 0):
            raise ValidationError("epochs and batch_size must be >= 1, lr > 0, weight_decay >= 0, "
                                  "collision_weight >= 0")


class ProxyPlanner(nn.Module):
    def __init__(self, config: PlannerConfig = PlannerConfig()) -> None:
        super().__init__()
        self.config = config
        layers, c = [], len(CHANNELS)
        for w in config.widths:
            layers += [nn.Conv2d(c, w, 3, stride=2, padding=1), nn.ReLU()]
            c = w
        self.encoder = nn.Sequential(*layers)
        h, w = GRID_H, GRID_W
        for _ in config.widths:
            h, w = (h + 1) // 2, (w + 1) // 2
        self.head = nn.Sequential(nn.Linear(c * h * w + len(STATE), config.hidden), nn.ReLU(),
                                  nn.Linear(config.hidden, config.hidden), nn.ReLU(),
                                  nn.Linear(config.hidden, STEPS * 2))

    def forward(self, raster: torch.Tensor, state: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        # [B, C, H, W], [B, S], [B, STEPS, 2] -> [B, STEPS, 2]
        z = self.encoder(raster).flatten(1)
        return base + self.head(torch.cat([z, state], 1)).view(-1, STEPS, 2)


def features(example: PlanningExample, with_map: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(raster float32 [C, H, W], state float32 [S], straight-ahead base [STEPS, 2]) of one example."""
    return features_of(example.inputs, example.scenario.drivable if with_map else None)


def features_of(inp: PlanningInput, drivable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``features`` of what a planner sees at one instant (``drivable``: the map's ``is_drivable`` or None)."""
    raster = np.zeros((len(CHANNELS), GRID_H, GRID_W), np.float32)
    now, past = inp.boxes_now, inp.boxes_past
    raster[0] = footprints_on_grid(now[now[:, 5] > 0, :5], _XS, _YS)
    raster[1] = footprints_on_grid(past[past[:, 5] > 0, :5], _XS, _YS)
    raster[2] = footprints_on_grid(now[now[:, 5] == 0, :5], _XS, _YS)
    if drivable is not None:
        gx, gy = np.meshgrid(_XS, _YS)
        frame = inp.world_from_frame
        world = np.stack([gx.ravel(), gy.ravel()], 1) @ frame[:2, :2].T + frame[:2, 2]
        raster[3] = np.asarray(drivable.is_drivable(world), np.float32).reshape(GRID_H, GRID_W)
    onehot = [1.0 if inp.command == c else 0.0 for c in COMMANDS]
    state = np.array([inp.speed / 10.0, inp.yaw_rate, *onehot, 1.0 if drivable is not None else 0.0], np.float32)
    base = np.stack([np.zeros(STEPS), inp.speed * STEP_S * np.arange(1, STEPS + 1)], 1).astype(np.float32)
    return raster, state, base


def future_boxes(example: PlanningExample) -> np.ndarray:  # [STEPS, COLLISION_BOXES, 6]
    """The future vehicles the collision loss sees: per known step the ``COLLISION_BOXES`` nearest to the true
    waypoint within ``COLLISION_REACH_M`` (x, y, length, width, yaw, valid; planning frame)."""
    out = np.zeros((STEPS, COLLISION_BOXES, 6), np.float32)
    sample = example.sample
    for i, boxes in enumerate(sample.vehicles):
        boxes = np.asarray(boxes, np.float64).reshape(-1, 5)
        if not sample.mask[i] or not len(boxes):
            continue
        d = np.hypot(boxes[:, 0] - sample.trajectory[i, 0], boxes[:, 1] - sample.trajectory[i, 1])
        keep = np.argsort(d)[:COLLISION_BOXES]
        keep = keep[d[keep] <= COLLISION_REACH_M]
        out[i, :len(keep), :5] = boxes[keep]
        out[i, :len(keep), 5] = 1.0
    return out


def collision_penetration(waypoints: torch.Tensor, boxes: torch.Tensor, margin: float) -> torch.Tensor:
    """[B, T, 2] waypoints, [B, T, K, 6] boxes -> [B, T]: how far (m) the ego's circles, grown by ``margin``, reach
    into the boxes, summed over boxes and circles (0 when clear)."""
    offsets = torch.zeros(len(_EGO_CIRCLES), 2, dtype=waypoints.dtype)
    offsets[:, 1] = torch.as_tensor(_EGO_CIRCLES, dtype=waypoints.dtype)
    centres = waypoints[:, :, None, None, :] + offsets  # [B, T, 1, 3, 2]
    rel = centres - boxes[..., None, :2]  # [B, T, K, 3, 2]
    c, s = torch.cos(boxes[..., 4:5]), torch.sin(boxes[..., 4:5])  # [B, T, K, 1]
    along = (c * rel[..., 0] + s * rel[..., 1]).abs() - boxes[..., 2:3] / 2
    across = (-s * rel[..., 0] + c * rel[..., 1]).abs() - boxes[..., 3:4] / 2
    outside = torch.sqrt(torch.relu(along) ** 2 + torch.relu(across) ** 2 + 1e-12)
    signed = outside + torch.clamp(torch.maximum(along, across), max=0.0)  # circle centre to box, < 0 inside
    reach = torch.relu(_EGO_RADIUS + margin - signed) * boxes[..., 5:6]
    return reach.sum((-1, -2))


def collision_loss(waypoints: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor,
                   boxes: torch.Tensor) -> torch.Tensor:
    """UniAD-style collision loss per example (mean over the batch): the margins' weighted penetrations of the
    planned waypoints at the known steps where the true waypoint itself is clear of every box."""
    clear = mask * (collision_penetration(truth, boxes, 0.0) <= 0).to(mask.dtype)
    total = sum(w * collision_penetration(waypoints, boxes, m) for m, w in COLLISION_MARGINS)
    return (total * clear).sum() / max(len(waypoints), 1)


def _tensors(examples: list[PlanningExample], progress: Progress = no_progress, with_boxes: bool = False):
    rasters, states, bases, targets, masks, boxes = [], [], [], [], [], []
    for i, ex in enumerate(examples):
        r, s, b = features(ex)
        rasters.append(r)
        states.append(s)
        bases.append(b)
        targets.append(ex.sample.trajectory.astype(np.float32))
        masks.append(ex.sample.mask.astype(np.float32))
        boxes.append(future_boxes(ex) if with_boxes else np.zeros((STEPS, 0, 6), np.float32))
        progress(i + 1, len(examples), "rasterising")
    return tuple(torch.from_numpy(np.stack(a)) for a in (rasters, states, bases, targets, masks, boxes))


def _mirror(raster, state, base, target, mask, boxes):
    r = torch.flip(raster, dims=[-1])  # x -> -x (columns run along x)
    s = state.clone()
    s[:, 2], s[:, 3] = state[:, 3], state[:, 2]  # right <-> left
    s[:, 1] = -state[:, 1]
    flip = torch.tensor([-1.0, 1.0])
    mirrored = boxes.clone()
    mirrored[..., 0] = -boxes[..., 0]
    mirrored[..., 4] = np.pi - boxes[..., 4]
    return r, s, base * flip, target * flip, mask, mirrored


def train_planner(examples: list[PlanningExample], config: TrainConfig = TrainConfig(),
                  init: ProxyPlanner | None = None, planner_config: PlannerConfig = PlannerConfig(),
                  progress: Progress = no_progress) -> tuple[ProxyPlanner, dict]:
    """Fit a planner (from ``init``'s weights when given: fine-tuning) on ``examples``; returns it and a record of
    the training (config, example count, loss per epoch, seconds)."""
    if not examples:
        raise ValidationError("no planning examples to train on")
    started = time.perf_counter()
    torch.manual_seed(config.seed)
    data = _tensors(examples, with_boxes=config.collision_weight > 0)
    if config.mirror:
        data = tuple(torch.cat([a, b]) for a, b in zip(data, _mirror(*data)))
    model = ProxyPlanner(init.config if init is not None else planner_config)
    if init is not None:
        model.load_state_dict(init.state_dict())
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    steps_per_epoch = max(1, (len(data[0]) + config.batch_size - 1) // config.batch_size)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=config.epochs * steps_per_epoch)
    gen = torch.Generator().manual_seed(config.seed)
    losses = []
    model.train()
    for epoch in range(config.epochs):
        order = torch.randperm(len(data[0]), generator=gen)
        total = 0.0
        for i in range(0, len(order), config.batch_size):
            idx = order[i:i + config.batch_size]
            raster, state, base, target, mask, boxes = (d[idx] for d in data)
            pred = model(raster, state, base)
            loss = ((pred - target).norm(dim=-1) * mask).sum() / mask.sum().clamp(min=1.0)
            if config.collision_weight > 0:
                loss = loss + config.collision_weight * collision_loss(pred, target, mask, boxes)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(idx)
        losses.append(total / len(order))
        progress(epoch + 1, config.epochs, f"epoch loss {losses[-1]:.3f} m")
    model.eval()
    record = {"train_config": asdict(config), "planner_config": asdict(model.config), "n_examples": len(examples),
              "n_trained": int(len(data[0])), "epoch_loss_m": losses, "seconds": time.perf_counter() - started,
              "fine_tuned": init is not None}
    return model, record


def mix_repeats(n_scs: int, n_logs: int, share: float) -> tuple[int, int]:
    """(SCS repeat, log repeat): whole-number repeats of the two kinds of example that bring the SCS share of the
    mix nearest ``share`` while repeating only the kind that is short (the other is used once). Without one kind,
    or with ``share`` at 0 or 1, nothing is repeated."""
    if not (math.isfinite(share) and 0.0 <= share <= 1.0):
        raise ValidationError(f"the SCS share must be in [0, 1]; got {share}")
    if n_scs <= 0 or n_logs <= 0 or share in (0.0, 1.0):
        return 1, 1
    wanted = share / (1.0 - share)  # SCS examples per log example
    if n_scs / n_logs <= wanted:
        return max(1, int(round(wanted * n_logs / n_scs))), 1
    return 1, max(1, int(round(n_scs / (wanted * n_logs))))


def mixed_examples(scs: list, logs: list, share: float) -> tuple[list, dict]:
    """The fine-tuning mix of behaviour-SCS and log examples at about ``share`` SCS (``mix_repeats``) and what it
    holds: {scs_repeat, log_repeat, scs_share} (the share reached)."""
    rs, rl = mix_repeats(len(scs), len(logs), share)
    n = rs * len(scs) + rl * len(logs)
    return list(scs) * rs + list(logs) * rl, {"scs_repeat": rs, "log_repeat": rl,
                                              "scs_share": rs * len(scs) / n if n else 0.0}


@torch.no_grad()
def plan(model: ProxyPlanner, examples: list[PlanningExample], batch_size: int = 256) -> dict[str, np.ndarray]:
    """{sample token: [STEPS, 2] planned waypoints} for ``examples``."""
    model.eval()
    out = {}
    for i in range(0, len(examples), batch_size):
        chunk = examples[i:i + batch_size]
        raster, state, base = _tensors(chunk)[:3]
        pred = model(raster, state, base).numpy().astype(np.float64)
        out.update({ex.sample.token: p for ex, p in zip(chunk, pred)})
    return out


@torch.no_grad()
def plan_inputs(model: ProxyPlanner, inputs: list[tuple[PlanningInput, object]], batch_size: int = 256,
                progress: Progress = no_progress) -> np.ndarray:  # -> [N, STEPS, 2] planning frame
    """Planned waypoints for what the planner sees at each of ``inputs`` ((input, drivable map or None) pairs: a
    keyframe of a dataroot rather than of a scenario, ``omniscs.eval.predict``)."""
    model.eval()
    out = []
    for i in range(0, len(inputs), batch_size):
        chunk = [features_of(inp, drivable) for inp, drivable in inputs[i:i + batch_size]]
        raster, state, base = (torch.from_numpy(np.stack(a)) for a in zip(*chunk))
        out.append(model(raster, state, base).numpy().astype(np.float64))
        progress(min(i + batch_size, len(inputs)), len(inputs), "planning")
    return np.concatenate(out) if out else np.zeros((0, STEPS, 2))


def save_planner(model: ProxyPlanner, out_dir: str | Path, training: dict, overwrite: bool = False) -> Path:
    """Weights (safetensors), network config and training record, written atomically."""
    with atomic_directory(Path(out_dir), overwrite=overwrite) as tmp:
        save_file({k: v.detach().contiguous() for k, v in model.state_dict().items()}, str(tmp / WEIGHTS))
        atomic_write_json(tmp / CONFIG, asdict(model.config))
        atomic_write_json(tmp / TRAINING, training)
    return Path(out_dir)


def load_planner(path: str | Path | None = None) -> ProxyPlanner:
    """A saved planner (default: the shipped one); a clear error when the folder is not one."""
    path = verified_folder(path if path is not None else DEFAULT_PLANNER)
    try:
        config = PlannerConfig(**read_json(path / CONFIG, f"{path} is not a proxy planner checkpoint; train one with "
                                           "`omniscs pretrained train planner` or name its folder", expect=dict,
                                           error=ValidationError))
        state = load_file(str(path / WEIGHTS))
    except (OSError, ValueError, TypeError) as e:
        raise ValidationError(f"{path} is not a proxy planner checkpoint ({e}); train one with "
                              "`omniscs pretrained train planner` or name its folder") from e
    return network_with_weights(ProxyPlanner(config), state, path, CONFIG)
