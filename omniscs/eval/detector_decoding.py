"""Decoding the proxy detector's outputs into nuScenes detection results (``omniscs.eval.detector``): peaks,
centres from regressed depth and from the ground contact fused by their expected errors, attributes, a centre
NMS across cameras, and the results file."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from omniscs.errors import ValidationError
from omniscs.eval.detection import CLASS_ATTRIBUTES
from omniscs.eval.detector_config import (CLASS_SIZE, CYCLES, MOVING_SPEED_MPS, STRIDE, VELOCITY_SCALE, DetectConfig,
                                         DetectorConfig)
from omniscs.eval.detector_network import ProxyDetector
from omniscs.eval.detector_views import (CameraView, back_project, camera_views, global_yaw, load_image,
                                        quaternion_from_yaw, ray_azimuth, view_with_image_size)
from omniscs.eval.nuscenes_io import NuScenesTables
from omniscs.progress import Progress, no_progress
from omniscs.storage import atomic_write_text


# ----------------------------------------------------------------------------- inference
def regressed_depth(output: np.ndarray, focal_input: float, config: DetectorConfig) -> np.ndarray:
    """Depth (m, optical axis) of the depth channel's output for a camera of ``focal_input`` px at the input size
    (the inverse of the target ``targets`` writes)."""
    return np.exp(np.clip(output, -10, 10)) * focal_input / config.reference_focal


def _decode_view(heat_logits: torch.Tensor, regression: torch.Tensor, view: CameraView, config: DetectorConfig,
                 detect_config: DetectConfig) -> list[dict]:
    """Boxes (global frame, no sample token yet) of one view's outputs ([C, h, w], [REGRESSION, h, w])."""
    heat = torch.sigmoid(heat_logits)
    peaks = heat * (F.max_pool2d(heat[None], 3, 1, 1)[0] == heat).float()
    k = min(detect_config.top_k, peaks.numel())
    scores, flat = peaks.flatten().topk(k)
    keep = scores >= max(detect_config.score_threshold, 1e-12)
    scores, flat = scores[keep].double().numpy(), flat[keep].numpy()
    if not len(flat):
        return []
    oh, ow = heat.shape[-2:]
    label, cell = flat // (oh * ow), flat % (oh * ow)
    cy, cx = cell // ow, cell % ow
    r = regression[:, cy, cx].double().numpy()  # [REGRESSION, K]
    sx, sy = config.input_width / view.width, config.input_height / view.height
    uv = np.stack([(cx + r[0]) * STRIDE / sx, (cy + r[1]) * STRIDE / sy], 1)
    depth = regressed_depth(r[2], view.intrinsics[1, 1] * sy, config)
    prior = np.array([CLASS_SIZE[config.classes[i]] for i in label], np.float64)
    size = prior * np.exp(np.clip(r[3:6].T, -3, 3))
    contact = np.stack([(cx + r[10]) * STRIDE / sx, (cy + r[11]) * STRIDE / sy], 1)
    centres = fused_centres(uv, depth, contact, size[:, 2], view, config, sy)
    yaw = global_yaw(np.arctan2(r[6], r[7]), centres, view.global_from_camera)
    azimuth = ray_azimuth(centres, view.global_from_camera)
    along, across = r[8] * VELOCITY_SCALE, r[9] * VELOCITY_SCALE
    vel = np.stack([along * np.cos(azimuth) - across * np.sin(azimuth),
                    along * np.sin(azimuth) + across * np.cos(azimuth)], 1)
    rotation = quaternion_from_yaw(yaw)
    out = []
    for j in range(len(flat)):
        name = config.classes[int(label[j])]
        out.append({"translation": centres[j].tolist(), "size": size[j].tolist(), "rotation": rotation[j].tolist(),
                    "velocity": vel[j].tolist(), "detection_name": name, "detection_score": float(scores[j]),
                    "attribute_name": attribute_for(name, float(np.hypot(*vel[j])))})
    return out


def _ground_plane(view: CameraView) -> tuple[np.ndarray, float]:
    """The ground's normal (the ego's z axis, global frame) and the camera's height above the ego's z = 0 plane."""
    n = view.global_from_ego[:3, 2]
    return n, float(n @ (view.global_from_camera[:3, 3] - view.global_from_ego[:3, 3]))


def ground_contact_centres(contact: np.ndarray,  # [N, 2] px: where each box's bottom centre projects
                           height: np.ndarray,   # [N] box heights (m)
                           view: CameraView,
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box centres read from the ground: the ray through each contact pixel meets the ego's z = 0 plane at the
    bottom centre, the centre is half the height above it. Returns (centres [N, 3] global, their depths [N] along
    the optical axis, valid [N]: the ray meets the ground in front of the camera, which stands above it)."""
    n, above = _ground_plane(view)
    origin = view.global_from_camera[:3, 3]
    uv1 = np.concatenate([np.asarray(contact, np.float64), np.ones((len(contact), 1))], 1)
    rays = (uv1 @ np.linalg.inv(np.asarray(view.intrinsics, np.float64)).T) @ view.global_from_camera[:3, :3].T
    down = rays @ n
    valid = (down < -1e-6) & (above > 1e-3)
    s = np.where(valid, -above / np.where(valid, down, -1.0), 0.0)
    centres = origin + s[:, None] * rays + np.asarray(height, np.float64)[:, None] / 2 * n
    camera = (centres - origin) @ view.global_from_camera[:3, :3]
    valid &= camera[:, 2] > 0.1
    return centres, camera[:, 2], valid


def fused_centres(uv: np.ndarray,       # [N, 2] px: projected centres
                  depth: np.ndarray,    # [N] regressed depths (m, optical axis)
                  contact: np.ndarray,  # [N, 2] px: regressed ground contacts
                  height: np.ndarray,   # [N] box heights (m)
                  view: CameraView, config: DetectorConfig, input_scale: float,
                  ) -> np.ndarray:      # [N, 3] global
    """Box centres from the regressed depth and, where the detector's errors were measured, the ground contact,
    weighed by their expected errors at that distance (inverse variances): the regressed depth errs by about
    ``depth_error`` * z, the ground contact by ``contact_error_px`` times how far the ground point moves per input
    pixel of row, z^2 / (f * camera height). Near boxes are read from the ground, far ones from the regressed
    depth. ``input_scale``: input pixels per image pixel (rows)."""
    direct = back_project(uv, depth, view.intrinsics, view.global_from_camera)
    if config.depth_error is None or config.contact_error_px is None or not len(uv):
        return direct
    ground, z_ground, valid = ground_contact_centres(contact, height, view)
    if not valid.any():
        return direct
    above = max(_ground_plane(view)[1], 1e-3)
    focal = float(view.intrinsics[1, 1]) * input_scale
    z = np.clip(np.where(valid, z_ground, depth), 0.1, None)
    var_direct = (config.depth_error * np.clip(depth, 0.1, None)) ** 2
    var_ground = (config.contact_error_px * z * z / (focal * above)) ** 2
    w = np.where(valid, var_direct / (var_direct + var_ground + 1e-12), 0.0)
    return w[:, None] * np.where(valid[:, None], ground, direct) + (1 - w[:, None]) * direct


def attribute_for(name: str, speed: float) -> str:
    """The class's attribute for a predicted speed (m/s): moving / parked (vehicles), moving / standing
    (pedestrians), with / without rider (cycles), none (cones, barriers)."""
    allowed = CLASS_ATTRIBUTES[name]
    if not allowed:
        return ""
    moving = speed >= MOVING_SPEED_MPS
    if name in CYCLES:
        return "cycle.with_rider" if moving else "cycle.without_rider"
    if name == "pedestrian":
        return "pedestrian.moving" if moving else "pedestrian.standing"
    return "vehicle.moving" if moving else "vehicle.parked"


def centre_nms(boxes: list[dict], radius_m: float) -> list[dict]:
    """Boxes by falling score, less any within ``radius_m`` (ground plane) of a kept box of its class."""
    kept: list[dict] = []
    for box in sorted(boxes, key=lambda b: -b["detection_score"]):
        if all(k["detection_name"] != box["detection_name"] or
               math.hypot(k["translation"][0] - box["translation"][0],
                          k["translation"][1] - box["translation"][1]) >= radius_m for k in kept):
            kept.append(box)
    return kept


@torch.no_grad()
def detect(model: ProxyDetector, dataroot: str | Path, version: str, scenes: list[str] | None = None,
           config: DetectConfig = DetectConfig(), progress: Progress = no_progress) -> dict:
    """nuScenes detection results of the keyframes of ``scenes`` (names or tokens; all when None): every sample
    present (an empty list where nothing is found), boxes in the global frame."""
    tables = NuScenesTables.load(dataroot, version)
    samples = tables.scene_samples(scenes)
    if not samples:
        raise ValidationError(f"{Path(dataroot) / version} has no samples to detect in")
    by_sample = camera_views(tables, samples)
    views = [view_with_image_size(v) for t in samples for v in by_sample[t]]
    threads = torch.get_num_threads()
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    model.eval()
    found: dict[str, list[dict]] = {t: [] for t in samples}
    try:
        mc = model.config
        for start in range(0, len(views), config.batch_size):
            chunk = views[start:start + config.batch_size]
            images = torch.from_numpy(np.stack([load_image(v, mc.input_width, mc.input_height) for v in chunk]))
            heat_logits, regression = model(images)
            for view, h, r in zip(chunk, heat_logits, regression):
                found[view.sample_token] += _decode_view(h, r, view, mc, config)
            progress(min(start + config.batch_size, len(views)), len(views), "detecting")
    finally:
        torch.set_num_threads(threads)
    results = {}
    for token, boxes in found.items():
        kept = centre_nms(boxes, config.nms_radius_m)[:config.max_boxes_per_sample]
        results[token] = [{"sample_token": token, **b} for b in kept]
    meta = {"use_camera": True, "use_lidar": False, "use_radar": False, "use_map": False, "use_external": False,
            "method": "omniscs proxy camera detector (CenterNet-style, trained from scratch)"}
    return {"meta": meta, "results": results}


def write_results(results: dict, path: str | Path) -> Path:
    """The results as JSON, written atomically."""
    path = Path(path)
    atomic_write_text(path, json.dumps(results))
    return path
