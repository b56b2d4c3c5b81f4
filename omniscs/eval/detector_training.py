"""Training the proxy detector (``omniscs.eval.detector``): the training set of a dataroot, heatmap and
regression targets, CenterNet's losses, augmentation, the training loop and the depth calibration that decoding
uses."""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from omniscs.errors import ValidationError
from omniscs.eval.detector_config import (CLASS_SIZE, REGRESSION, STRIDE, VELOCITY_SCALE, DetectorConfig,
                                         DetectorTrainConfig, config_dict)
from omniscs.eval.detector_decoding import regressed_depth
from omniscs.eval.detector_network import ProxyDetector, n_parameters, output_size
from omniscs.eval.detector_views import (ViewBoxes, annotations_by_sample, camera_views, gaussian_radius, load_image,
                                        view_boxes, view_with_image_size)
from omniscs.eval.nuscenes_io import NuScenesTables
from omniscs.progress import Progress, no_progress


# ----------------------------------------------------------------------------- training
@dataclass
class TrainingSet:
    """Resized images and their boxes in input pixels."""

    images: torch.Tensor          # uint8 [N, 3, H, W]
    boxes: list[ViewBoxes]        # per image, uv / extent in input pixels
    focal: np.ndarray             # [N] fy in input pixels
    sources: list[str] = field(default_factory=list)  # "dataroot version" per image

    def __len__(self) -> int:
        return len(self.boxes)


def _scaled(boxes: ViewBoxes, sx: float, sy: float) -> ViewBoxes:
    return ViewBoxes(boxes.uv * [sx, sy], boxes.depth, boxes.size, boxes.alpha, boxes.velocity, boxes.label,
                     boxes.extent * [sy, sx], boxes.contact * [sx, sy])


def training_set(dataroots: list[tuple[str | Path, str]], config: DetectorConfig = DetectorConfig(),
                 train: DetectorTrainConfig = DetectorTrainConfig(), progress: Progress = no_progress) -> TrainingSet:
    """Every keyframe camera image of the dataroots (all scenes) with the boxes it learns from."""
    images, boxes, focal, sources = [], [], [], []
    plan = []
    for root, version in dataroots:
        tables = NuScenesTables.load(root, version)
        samples = tables.scene_samples()
        anns = annotations_by_sample(tables)
        for token, views in camera_views(tables, samples).items():
            plan += [(view, anns.get(token, []), f"{root} {version}") for view in views]
    for i, (view, anns, source) in enumerate(plan):
        view = view_with_image_size(view)
        sx, sy = config.input_width / view.width, config.input_height / view.height
        images.append(torch.from_numpy(load_image(view, config.input_width, config.input_height)))
        boxes.append(_scaled(view_boxes(view, anns, config.classes, train), sx, sy))
        focal.append(view.intrinsics[1, 1] * sy)
        sources.append(source)
        progress(i + 1, len(plan), "reading images")
    return TrainingSet(torch.stack(images), boxes, np.array(focal, np.float64), sources)


def sampling_weights(boxes: list[ViewBoxes], n_classes: int, balance: float) -> np.ndarray:
    """Per image, the probability of drawing it under class-balanced sampling (``DetectorTrainConfig.class_balance``):
    the sum over the classes the image shows of n_c ** -balance, images without a box counting as one more class
    (index ``n_classes``); normalised to sum 1. ``balance`` 0 gives every image the same weight."""
    shown = [np.unique(b.label) if len(b) else np.array([n_classes]) for b in boxes]
    counts = np.bincount(np.concatenate(shown), minlength=n_classes + 1).astype(np.float64) if shown else np.ones(1)
    per_class = np.where(counts > 0, np.maximum(counts, 1.0) ** -float(balance), 0.0)
    weights = np.array([per_class[s].sum() for s in shown], np.float64)
    return weights / weights.sum() if weights.sum() > 0 else np.full(len(boxes), 1.0 / max(len(boxes), 1))


def _flipped(boxes: ViewBoxes, width: int) -> ViewBoxes:
    uv, contact = boxes.uv.copy(), boxes.contact.copy()
    uv[:, 0], contact[:, 0] = width - uv[:, 0], width - contact[:, 0]
    return ViewBoxes(uv, boxes.depth, boxes.size, -boxes.alpha, boxes.velocity * [1.0, -1.0], boxes.label,
                     boxes.extent, contact)


def _draw_gaussian(heat: np.ndarray, cx: int, cy: int, radius: int) -> None:  # heat [H, W], in place (max)
    sigma = (2 * radius + 1) / 6
    h, w = heat.shape
    ys, xs = np.arange(-radius, radius + 1), np.arange(-radius, radius + 1)
    g = np.exp(-(ys[:, None] ** 2 + xs[None, :] ** 2) / (2 * sigma * sigma))
    top, bottom, left, right = min(cy, radius), min(h - cy, radius + 1), min(cx, radius), min(w - cx, radius + 1)
    region = heat[cy - top:cy + bottom, cx - left:cx + right]
    np.maximum(region, g[radius - top:radius + bottom, radius - left:radius + right], out=region)


def targets(batch: list[ViewBoxes], focal: np.ndarray, config: DetectorConfig, train: DetectorTrainConfig
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(heatmaps [B, C, h, w], regression targets [B, REGRESSION, h, w], regression mask [B, REGRESSION, h, w]) of
    boxes in input pixels; where two centres fall in one cell the nearer box wins."""
    oh, ow = output_size(config)
    heat = np.zeros((len(batch), len(config.classes), oh, ow), np.float32)
    reg = np.zeros((len(batch), REGRESSION, oh, ow), np.float32)
    mask = np.zeros((len(batch), REGRESSION, oh, ow), np.float32)
    prior = np.log(np.array([CLASS_SIZE[c] for c in config.classes], np.float64))
    for b, boxes in enumerate(batch):
        for i in np.argsort(-boxes.depth):
            c = boxes.uv[i] / STRIDE
            cx, cy = int(min(max(c[0], 0), ow - 1e-6)), int(min(max(c[1], 0), oh - 1e-6))
            radius = max(0, int(gaussian_radius(*(boxes.extent[i] / STRIDE), train.min_overlap)))
            _draw_gaussian(heat[b, boxes.label[i]], cx, cy, radius)
            vel = boxes.velocity[i] / VELOCITY_SCALE
            reg[b, :, cy, cx] = [c[0] - cx, c[1] - cy, math.log(boxes.depth[i] * config.reference_focal / focal[b]),
                                 *(np.log(boxes.size[i]) - prior[boxes.label[i]]), math.sin(boxes.alpha[i]),
                                 math.cos(boxes.alpha[i]), *np.nan_to_num(vel),
                                 *(boxes.contact[i] / STRIDE - [cx, cy])]
            mask[b, :, cy, cx] = 1.0
            if not np.isfinite(vel).all():
                mask[b, 8:10, cy, cx] = 0.0
    return torch.from_numpy(heat), torch.from_numpy(reg), torch.from_numpy(mask)


def focal_loss(logits: torch.Tensor, heat: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4), summed and divided by the number of centres."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = heat.eq(1).float()
    pos_loss = -(torch.log(p) * (1 - p) ** 2 * pos).sum()
    neg_loss = -(torch.log(1 - p) * p ** 2 * (1 - heat) ** 4 * (1 - pos)).sum()
    return (pos_loss + neg_loss) / pos.sum().clamp(min=1.0)


def detection_losses(heat_logits: torch.Tensor, regression: torch.Tensor, heat: torch.Tensor, reg: torch.Tensor,
                     mask: torch.Tensor, train: DetectorTrainConfig) -> dict[str, torch.Tensor]:
    """The weighted loss terms and their sum (``total``)."""
    def l1(channels: slice) -> torch.Tensor:
        m = mask[:, channels]
        return (torch.abs(regression[:, channels] - reg[:, channels]) * m).sum() / m[:, :1].sum().clamp(min=1.0)

    terms = {"heatmap": focal_loss(heat_logits, heat), "offset": train.weight_offset * l1(slice(0, 2)),
             "depth": train.weight_depth * l1(slice(2, 3)), "size": train.weight_size * l1(slice(3, 6)),
             "rotation": train.weight_rotation * l1(slice(6, 8)), "velocity": train.weight_velocity * l1(slice(8, 10)),
             "contact": train.weight_contact * l1(slice(10, 12))}
    terms["total"] = sum(terms.values())
    return terms


def photometric_jitter(images: torch.Tensor, strength: float, gen: torch.Generator) -> torch.Tensor:
    """float [B, 3, H, W] (0..255) images with a random brightness, contrast (about each image's mean), per-channel
    gain and gamma each (factors exp(u), u uniform in [-strength, strength], the gains in half that range), drawn
    from ``gen``; clipped to 0..255."""
    b = len(images)
    u = (torch.rand(b, 6, generator=gen) * 2.0 - 1.0) * strength
    u[:, 2:5] *= 0.5
    x = images.float() / 255.0
    x = x.clamp_min(1e-6) ** torch.exp(u[:, 5]).view(b, 1, 1, 1)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * torch.exp(u[:, 1]).view(b, 1, 1, 1) + mean
    x = x * torch.exp(u[:, 0]).view(b, 1, 1, 1) * torch.exp(u[:, 2:5]).view(b, 3, 1, 1)
    return (x * 255.0).clamp(0.0, 255.0)


def train_detector(dataroots: list[tuple[str | Path, str]], config: DetectorTrainConfig = DetectorTrainConfig(),
                   detector_config: DetectorConfig = DetectorConfig(), init: ProxyDetector | None = None,
                   progress: Progress = no_progress, data: TrainingSet | None = None,
                   calibration_data: TrainingSet | None = None) -> tuple[ProxyDetector, dict]:
    """Fit a detector (from ``init``'s weights when given: fine-tuning) on every keyframe camera image of
    ``dataroots`` ((path, version) pairs; ``data``: their ``training_set`` when already read). Returns it and a
    record of the training (configs, image and box counts, loss curve, seconds). The same seed and thread count
    give the same weights. ``calibration_data``: images not trained on (read with the same network config) on which
    the depth errors that weigh the two depth readings are measured; None: the training images (errors on images
    the network has learned are smaller than on new ones)."""
    if not dataroots and data is None:
        raise ValidationError("name at least one (dataroot, version) to train the detector on")
    started = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        net_config = init.config if init is not None else detector_config
        data = data if data is not None else training_set(dataroots, net_config, config, progress)
        n_boxes = int(sum(len(b) for b in data.boxes))
        if n_boxes == 0:
            raise ValidationError("the training images show no annotation the detector learns from (of its classes, "
                                  f"within {config.max_depth_m} m, visible enough, with points)")
        read_s = time.perf_counter() - started
        torch.manual_seed(config.seed)
        model = ProxyDetector(net_config)
        if init is not None:
            model.load_state_dict(init.state_dict())
        opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=config.steps, pct_start=0.15)
        gen = torch.Generator().manual_seed(config.seed)
        weights = torch.from_numpy(sampling_weights(data.boxes, len(net_config.classes), config.class_balance))
        order = torch.randperm(len(data), generator=gen)
        cursor, curve, window = 0, [], []
        model.train()
        for step in range(config.steps):
            if config.class_balance > 0:  # drawn with replacement, rare classes' images more often
                idx = torch.multinomial(weights, config.batch_size, replacement=True, generator=gen)
            else:  # every image once per epoch (the shipped detector's training)
                if cursor + config.batch_size > len(order):
                    order, cursor = torch.randperm(len(data), generator=gen), 0
                idx = order[cursor:cursor + config.batch_size]
                cursor += config.batch_size
            flips = (torch.rand(len(idx), generator=gen) < 0.5).tolist() if config.flip else [False] * len(idx)
            images = data.images[idx]
            batch = []
            for k, (i, flip) in enumerate(zip(idx.tolist(), flips)):
                batch.append(_flipped(data.boxes[i], net_config.input_width) if flip else data.boxes[i])
                if flip:
                    images[k] = torch.flip(images[k], dims=[-1])
            if config.photometric > 0:
                images = photometric_jitter(images, config.photometric, gen)
            heat, reg, mask = targets(batch, data.focal[idx.numpy()], net_config, config)
            heat_logits, regression = model(images)
            losses = detection_losses(heat_logits, regression, heat, reg, mask, config)
            opt.zero_grad()
            losses["total"].backward()
            opt.step()
            sched.step()
            window.append({k: float(v.detach()) for k, v in losses.items()})
            if len(window) == config.log_every or step + 1 == config.steps:
                curve.append({"step": step + 1, **{k: float(np.mean([w[k] for w in window])) for k in window[0]}})
                window = []
            progress(step + 1, config.steps, f"loss {losses['total'].item():.3f}")
        model.eval()
        calibration = calibrate_depth(model, data if calibration_data is None else calibration_data,
                                      config.calibration_images)
        calibration["on"] = "training images" if calibration_data is None else "held-out calibration images"
        if calibration["depth_error"] is not None:
            model.config = replace(model.config, depth_error=calibration["depth_error"],
                                   contact_error_px=calibration["contact_error_px"])
    finally:
        torch.set_num_threads(threads)
    record = {"train_config": asdict(config), "detector_config": config_dict(model.config),
              "n_parameters": n_parameters(model), "n_images": len(data), "n_boxes": n_boxes,
              "boxes_per_class": {c: int(sum((b.label == i).sum() for b in data.boxes))
                                  for i, c in enumerate(model.config.classes)},
              "draws_showing_class": {c: float(sum(w for w, b in zip(weights.tolist(), data.boxes)
                                                   if (b.label == i).any()))
                                      for i, c in enumerate(model.config.classes)},
              "loss_curve": curve, "calibration": calibration, "read_seconds": read_s, "seconds": time.perf_counter() - started,
              "fine_tuned": init is not None}
    return model, record


@torch.no_grad()
def calibrate_depth(model: ProxyDetector, data: TrainingSet, n_images: int) -> dict:
    """The mean relative error of the regressed depth and the mean row error (input px) of the regressed ground
    contact at the ground-truth centres of up to ``n_images`` evenly spaced images of ``data``: the weights of
    ``fused_centres``. None for both where there are no images or no boxes."""
    picked = np.unique(np.linspace(0, len(data) - 1, min(n_images, len(data))).round().astype(int)) \
        if n_images > 0 and len(data) else np.zeros(0, int)
    rel, row = [], []
    for start in range(0, len(picked), 32):
        idx = picked[start:start + 32]
        _, regression = model(data.images[torch.from_numpy(idx)])
        oh, ow = regression.shape[-2:]
        for k, i in enumerate(idx):
            boxes = data.boxes[i]
            if not len(boxes):
                continue
            c = boxes.uv / STRIDE
            cx = np.clip(c[:, 0], 0, ow - 1e-6).astype(int)
            cy = np.clip(c[:, 1], 0, oh - 1e-6).astype(int)
            r = regression[k][:, cy, cx].double().numpy()
            depth = regressed_depth(r[2], data.focal[i], model.config)
            rel.append(np.abs(depth / boxes.depth - 1.0))
            row.append(np.abs((cy + r[11]) * STRIDE - boxes.contact[:, 1]))
    if not rel or not np.concatenate(rel).size:
        return {"depth_error": None, "contact_error_px": None, "n_boxes": 0, "n_images": int(len(picked))}
    rel_all, row_all = np.concatenate(rel), np.concatenate(row)
    return {"depth_error": float(max(np.mean(rel_all), 1e-4)), "contact_error_px": float(max(np.mean(row_all), 1e-3)),
            "n_boxes": int(rel_all.size), "n_images": int(len(picked))}
