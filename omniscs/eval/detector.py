"""The embedded proxy camera 3D detector: a small CenterNet-style network, trained here from scratch on 2 cores, that
finds the nuScenes detection classes in the cameras of a nuScenes dataroot and writes nuScenes detection results.
A stand-in for UniAD's detection head (a real learner, far weaker than UniAD), so that the paper's detection protocol
(base vs fine-tuned with appearance-SCS data; mAP, NDS) runs end to end on this machine; real stacks run as
external jobs.

Reads any nuScenes-format dataroot (the factory's exports or the real dataset): per keyframe sample and camera
(``sample_data`` of a ``CAM_*`` channel with ``is_key_frame``) the image, intrinsics and poses, and the sample's
annotations (global frame) projected into that camera.

Network (input: the image resized to ``DetectorConfig.input_width`` x ``input_height``, plus two coordinate channels
that let it read depth from the image row): four stride-2 blocks of two 3x3 convolutions (BN, ReLU; ``widths``), a
top-down path back to stride 4 (``STRIDE``) adding 1x1 lateral projections, then two 3x3 branches of ``head_width``:
  - heatmap: one logit per class of ``classes`` (all ten nuScenes detection classes by default) at each cell;
  - regression (``REGRESSION`` channels): sub-cell offset of the projected centre (2); log depth of the centre along
    the optical axis at ``reference_focal`` px (1: the depth is rescaled by the camera's focal length, so other
    intrinsics and input sizes read the same); log size (width, length, height: the nuScenes order) relative to the
    class's typical size (3); sin and cos of the *observation angle* alpha = global yaw - ground-plane azimuth of the
    ray from the camera to the centre (2: what an image shows of a box's heading; the same for every camera);
    velocity along and across that ray (m/s over ``VELOCITY_SCALE``: 2); the ground contact, where the box's bottom
    centre projects, relative to the cell (2).
Losses: CenterNet's penalty-reduced focal loss on the heatmaps (Gaussian peaks of the radius CenterNet derives from
the projected 2D box) and L1 on each regression at the object centres, each normalised by the number of centres.
Decoding: 3x3 max-pool peaks, the top ``DetectConfig.top_k`` per image above ``score_threshold``, each centre placed
twice: back-projected with the regressed depth, and read from the ground (the ray through the contact pixel meets the
ego's z = 0 plane, the centre is half the box height above it; a flat-ground assumption). The two are weighed by their
expected errors at that distance (inverse variances, from errors measured on the training images after training:
``calibrate_depth``): the ground reading is precise near the camera and loses a row's worth of precision
quadratically with distance, the regressed depth errs in proportion to it. Then camera -> ego -> global, and a
centre-distance NMS per class across the cameras of a sample.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from omniscs.errors import ValidationError
from omniscs.eval.detection import CLASS_ATTRIBUTES, DETECTION_NAMES
from omniscs.eval.nuscenes_io import CATEGORY_TO_DETECTION, NuScenesTables
from omniscs.progress import Progress, no_progress
from omniscs.quaternions import yaw_from_quaternion
from omniscs.storage import atomic_directory, atomic_write_json, atomic_write_text

#: Output stride of the heads (input pixels per heatmap cell).
STRIDE = 4
#: Regression channels: offset (2), log depth (1), log size (3: w, l, h), sin / cos of alpha (2), velocity (2),
#: ground contact (2: where the box's bottom centre projects, relative to the cell like the offset).
REGRESSION = 12
#: Velocities are regressed divided by this (m/s).
VELOCITY_SCALE = 10.0
#: Typical box size (width, length, height; m) per class: the sizes are regressed as log ratios to these.
CLASS_SIZE: dict[str, tuple[float, float, float]] = {
    "car": (1.95, 4.6, 1.7), "truck": (2.5, 7.0, 2.9), "bus": (2.9, 11.0, 3.5), "trailer": (2.9, 12.0, 3.9),
    "construction_vehicle": (2.8, 6.4, 3.2), "pedestrian": (0.67, 0.73, 1.77), "motorcycle": (0.77, 2.1, 1.47),
    "bicycle": (0.6, 1.7, 1.3), "traffic_cone": (0.41, 0.42, 1.07), "barrier": (2.5, 0.5, 0.98)}
#: Speed above which a box is given the class's moving attribute (m/s; the exporter's threshold).
MOVING_SPEED_MPS = 0.5
#: Classes whose attribute says whether they have a rider rather than whether they move.
CYCLES = ("bicycle", "motorcycle")
WEIGHTS = "detector.safetensors"
CONFIG = "detector_config.json"
TRAINING = "training.json"
README = "README.md"
#: The detector shipped with the package (``python -m omniscs.bench.detector_data``; see its training.json).
DEFAULT_DETECTOR = Path(__file__).parent / "checkpoints" / "detector"


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class DetectorConfig:
    """The network and its input (saved with the weights)."""

    input_width: int = 256
    """Width (px) the camera images are resized to."""
    input_height: int = 144
    """Height (px) the camera images are resized to."""
    widths: tuple[int, ...] = (16, 32, 64, 96)
    """Channels of the four stride-2 encoder blocks (strides 2, 4, 8, 16)."""
    head_width: int = 48
    """Channels of the top-down path and of the two head branches."""
    classes: tuple[str, ...] = DETECTION_NAMES
    """Detection classes the heatmap head has a channel for (nuScenes detection names)."""
    reference_focal: float = 128.0
    """Focal length (px) at which depth is regressed: depth = exp(output) * fy_input / reference_focal."""
    depth_prior_m: float = 20.0
    """Initial depth of the depth head (its bias)."""
    heatmap_prior: float = 0.1
    """Initial heatmap probability (CenterNet's bias of -2.19)."""
    depth_error: float | None = None
    """Mean relative error of the regressed depth (|z / z_true - 1|), measured on the training images after training
    (``calibrate_depth``); None: not measured, the regressed depth is used alone."""
    contact_error_px: float | None = None
    """Mean error (input px) of the regressed ground-contact point's row, measured with ``depth_error``."""

    def __post_init__(self):
        if len(self.widths) != 4 or min(self.widths) < 1 or self.head_width < 1:
            raise ValidationError("detector widths must be four positive channel counts and head_width positive")
        if self.input_width < 2 * STRIDE or self.input_height < 2 * STRIDE:
            raise ValidationError(f"detector input must be at least {2 * STRIDE} px each way")
        unknown = [c for c in self.classes if c not in DETECTION_NAMES]
        if unknown or not self.classes or len(set(self.classes)) != len(self.classes):
            raise ValidationError(f"detector classes must be distinct nuScenes detection names; got {self.classes}")
        if not (self.reference_focal > 0 and self.depth_prior_m > 0 and 0 < self.heatmap_prior < 1):
            raise ValidationError("reference_focal and depth_prior_m must be positive, heatmap_prior in (0, 1)")
        for name in ("depth_error", "contact_error_px"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValidationError(f"{name} must be a positive finite number or None; got {value}")
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        object.__setattr__(self, "classes", tuple(str(c) for c in self.classes))


@dataclass(frozen=True)
class DetectorTrainConfig:
    """How the detector is trained and which annotations it learns from."""

    steps: int = 2_000
    """Optimiser steps."""
    batch_size: int = 16
    """Camera images per step."""
    lr: float = 2e-3
    """Peak learning rate (one-cycle schedule, AdamW)."""
    weight_decay: float = 1e-4
    seed: int = 0
    """Seeds the weights, the order of the images and the flips."""
    threads: int = 2
    """Torch CPU threads while training (the same seed and thread count give the same weights)."""
    flip: bool = True
    """Mirror half of the images left-right (alpha and the cross-ray velocity change sign)."""
    max_depth_m: float = 60.0
    """Annotations farther along the optical axis are not learned."""
    near_m: float = 1.0
    """Annotations nearer along the optical axis (or behind the camera) are not learned."""
    min_visibility: int = 1
    """Lowest nuScenes visibility level (1: 0-40 %, 2: 40-60 %, 3: 60-80 %, 4: 80-100 %) of a learned annotation;
    annotations without a visibility token are kept. 1: all, as the protocol evaluates all (with a point)."""
    require_points: bool = True
    """Learn only annotations with a LiDAR or radar point (the protocol evaluates no others)."""
    min_overlap: float = 0.7
    """CenterNet's overlap for the heatmap Gaussian's radius."""
    weight_offset: float = 1.0
    weight_depth: float = 1.0
    weight_size: float = 1.0
    weight_rotation: float = 1.0
    weight_velocity: float = 0.5
    weight_contact: float = 1.0
    calibration_images: int = 512
    """Training images (evenly spaced) on which the errors that weigh regressed against ground-contact depth are
    measured after training (0: not measured; the regressed depth is then used alone)."""
    log_every: int = 50
    """Steps per entry of the recorded loss curve."""
    class_balance: float = 0.0
    """Class-balanced sampling of the images (CBGS's idea, Zhu et al. 2019, on camera images): 0 draws every image
    equally often, epoch by epoch; above 0 each image is drawn with replacement, with weight sum over the classes it
    shows of n_c ** -class_balance (n_c: the images that show class c), so at 1 every class is shown about equally
    often and the images of rare classes are repeated; images with no box weigh as one more class."""
    photometric: float = 0.0
    """Strength s of random photometric changes, drawn per training image: brightness, contrast about the image's
    mean, per-channel gain and gamma, each a factor exp(u) with u uniform in [-s, s] (the gains in [-s/2, s/2]).
    They leave every box where it is; 0: none (and no random numbers drawn)."""

    def __post_init__(self):
        if self.steps < 1 or self.batch_size < 1 or self.threads < 1 or self.log_every < 1 \
                or self.calibration_images < 0:
            raise ValidationError("steps, batch_size, threads and log_every must be >= 1, calibration_images >= 0")
        if not (math.isfinite(self.class_balance) and 0 <= self.class_balance <= 1):
            raise ValidationError(f"class_balance must be in [0, 1]; got {self.class_balance}")
        if not (math.isfinite(self.photometric) and 0 <= self.photometric <= 1):
            raise ValidationError(f"photometric must be in [0, 1]; got {self.photometric}")
        if not (self.lr > 0) or self.weight_decay < 0 or not 0 < self.near_m < self.max_depth_m:
            raise ValidationError("lr must be > 0, weight_decay >= 0 and 0 < near_m < max_depth_m")
        if self.min_visibility not in (1, 2, 3, 4) or not 0 < self.min_overlap < 1:
            raise ValidationError("min_visibility must be 1 to 4 and min_overlap in (0, 1)")


@dataclass(frozen=True)
class DetectConfig:
    """How network outputs become boxes."""

    score_threshold: float = 0.05
    """Lowest heatmap score of a kept peak."""
    top_k: int = 50
    """Most peaks kept per camera image."""
    nms_radius_m: float = 1.5
    """A box within this ground-plane distance of a higher-scoring box of its class (any camera) is dropped."""
    max_boxes_per_sample: int = 500
    """The protocol's limit."""
    batch_size: int = 16
    threads: int | None = None
    """Torch CPU threads while detecting (None: leave torch's setting)."""

    def __post_init__(self):
        if not 0 <= self.score_threshold < 1 or self.top_k < 1 or self.nms_radius_m < 0 \
                or not 1 <= self.max_boxes_per_sample <= 500 or self.batch_size < 1:
            raise ValidationError("score_threshold in [0, 1), top_k >= 1, nms_radius_m >= 0, "
                                  "max_boxes_per_sample in [1, 500], batch_size >= 1")


# ----------------------------------------------------------------------------- geometry
def transform_of(record: dict) -> np.ndarray:  # {translation [3], rotation [4] w, x, y, z} -> [4, 4]
    from omniscs.geometry import make_transform
    from omniscs.quaternions import quat_to_rotmat

    return make_transform(quat_to_rotmat(np.asarray(record["rotation"], np.float64)),
                          np.asarray(record["translation"], np.float64))


def project_to_camera(points_global: np.ndarray,      # [N, 3] global
                      intrinsics: np.ndarray,         # [3, 3]
                      global_from_camera: np.ndarray,  # [4, 4]
                      ) -> tuple[np.ndarray, np.ndarray]:  # uv [N, 2] px, depth [N] m along the optical axis
    """Pixels and depths of global points (uv is meaningless where depth <= 0)."""
    from omniscs.geometry import invert_transform

    cam = np.asarray(points_global, np.float64) @ invert_transform(global_from_camera)[:3, :3].T \
        + invert_transform(global_from_camera)[:3, 3]
    depth = cam[:, 2]
    safe = np.where(np.abs(depth) > 1e-9, depth, 1e-9)
    uvw = cam @ np.asarray(intrinsics, np.float64).T
    return uvw[:, :2] / safe[:, None], depth


def back_project(uv: np.ndarray,                 # [N, 2] px
                 depth: np.ndarray,              # [N] m along the optical axis
                 intrinsics: np.ndarray,         # [3, 3]
                 global_from_camera: np.ndarray,  # [4, 4]
                 ) -> np.ndarray:                # [N, 3] global
    """The global points that ``project_to_camera`` sends to (uv, depth)."""
    uv1 = np.concatenate([np.asarray(uv, np.float64), np.ones((len(uv), 1))], 1)
    cam = (uv1 @ np.linalg.inv(np.asarray(intrinsics, np.float64)).T) * np.asarray(depth, np.float64)[:, None]
    return cam @ global_from_camera[:3, :3].T + global_from_camera[:3, 3]


def ray_azimuth(centres_global: np.ndarray, global_from_camera: np.ndarray) -> np.ndarray:  # [N, 3] -> [N] rad
    """Ground-plane direction of the ray from the camera centre to each point (global frame)."""
    d = np.asarray(centres_global, np.float64)[:, :2] - global_from_camera[:2, 3]
    return np.arctan2(d[:, 1], d[:, 0])


def observation_angle(yaw_global: np.ndarray, centres_global: np.ndarray, global_from_camera: np.ndarray
                      ) -> np.ndarray:  # [N], [N, 3], [4, 4] -> [N] rad in (-pi, pi]
    """alpha = global yaw - the ray's azimuth: the heading as the camera sees it."""
    a = np.asarray(yaw_global, np.float64) - ray_azimuth(centres_global, global_from_camera)
    return np.arctan2(np.sin(a), np.cos(a))


def global_yaw(alpha: np.ndarray, centres_global: np.ndarray, global_from_camera: np.ndarray) -> np.ndarray:
    """Inverse of ``observation_angle``: [N] alpha, [N, 3] centres -> [N] global yaw in (-pi, pi]."""
    a = np.asarray(alpha, np.float64) + ray_azimuth(centres_global, global_from_camera)
    return np.arctan2(np.sin(a), np.cos(a))


def quaternion_from_yaw(yaw: np.ndarray) -> np.ndarray:  # [N] -> [N, 4] w, x, y, z about +z
    yaw = np.asarray(yaw, np.float64)
    return np.stack([np.cos(yaw / 2), np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2)], -1)


def box_corners_global(translation: np.ndarray, size_wlh: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """[3], [3] (w, l, h), [4] -> [8, 3]: corners of a nuScenes box."""
    from omniscs.quaternions import quat_to_rotmat

    w, length, h = np.asarray(size_wlh, np.float64)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    local = signs * np.array([length, w, h]) / 2
    return local @ quat_to_rotmat(np.asarray(rotation, np.float64)).T + np.asarray(translation, np.float64)


def gaussian_radius(height: float, width: float, min_overlap: float) -> float:
    """CenterNet's radius of a centre Gaussian for a 2D box of ``height`` x ``width`` cells."""
    b1, c1 = height + width, width * height * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1 ** 2 - 4 * c1)) / 2
    b2, c2 = 2 * (height + width), (1 - min_overlap) * width * height
    r2 = (b2 + math.sqrt(b2 ** 2 - 16 * c2)) / 2
    a3, b3, c3 = 4 * min_overlap, -2 * min_overlap * (height + width), (min_overlap - 1) * width * height
    r3 = (b3 + math.sqrt(b3 ** 2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


# ----------------------------------------------------------------------------- reading a dataroot
@dataclass(frozen=True)
class CameraView:
    """One keyframe image of one camera."""

    sample_token: str
    channel: str
    image_path: Path
    width: int
    height: int
    intrinsics: np.ndarray          # [3, 3] px
    global_from_camera: np.ndarray  # [4, 4] OpenCV camera (x right, y down, z forward) -> global
    global_from_ego: np.ndarray     # [4, 4] the ego frame (its z = 0 plane is the ground under the car) -> global


@dataclass(frozen=True)
class ViewBoxes:
    """Ground-truth boxes seen by one view, in its original pixels."""

    uv: np.ndarray        # [N, 2] projected centre, px
    depth: np.ndarray     # [N] m along the optical axis
    size: np.ndarray      # [N, 3] w, l, h (m)
    alpha: np.ndarray     # [N] observation angle (rad)
    velocity: np.ndarray  # [N, 2] m/s along and across the camera ray (NaN: unknown)
    label: np.ndarray     # [N] int, index into the detector's classes
    extent: np.ndarray    # [N, 2] height and width (px) of the projected box, clipped to the image
    contact: np.ndarray   # [N, 2] where the box's bottom centre (its ground contact) projects, px

    def __len__(self) -> int:
        return len(self.label)


def camera_views(tables: NuScenesTables, samples: list[str]) -> dict[str, list[CameraView]]:
    """{sample token: its keyframe camera views} for ``samples`` (channels in name order); a clear error when
    none of them has a camera keyframe."""
    channel = {t: tables["sensor"][c["sensor_token"]]["channel"] for t, c in tables["calibrated_sensor"].items()}
    wanted = set(samples)
    out: dict[str, list[CameraView]] = {t: [] for t in samples}
    for sd in tables["sample_data"].values():
        ch = channel.get(sd["calibrated_sensor_token"], "")
        if not (sd.get("is_key_frame") and ch.startswith("CAM_") and sd["sample_token"] in wanted):
            continue
        calib = tables["calibrated_sensor"][sd["calibrated_sensor_token"]]
        K = np.asarray(calib.get("camera_intrinsic") or [], np.float64)
        if K.shape != (3, 3):
            raise ValidationError(f"calibrated_sensor {calib['token']} ({ch}) has no 3x3 camera_intrinsic")
        global_from_ego = transform_of(tables["ego_pose"][sd["ego_pose_token"]])
        out[sd["sample_token"]].append(CameraView(sd["sample_token"], ch, tables.root / sd["filename"],
                                                  int(sd.get("width") or 0), int(sd.get("height") or 0), K,
                                                  global_from_ego @ transform_of(calib), global_from_ego))
    if not any(out.values()):
        raise ValidationError(f"{tables.root / tables.version} has no camera keyframes (sample_data of a CAM_* channel "
                              f"with is_key_frame) in the {len(samples)} chosen samples; the camera detector needs "
                              "images")
    for views in out.values():
        views.sort(key=lambda v: v.channel)
    return out


def annotations_by_sample(tables: NuScenesTables) -> dict[str, list[dict]]:
    """The detection-class annotations of each sample, each with its ``detection_name``, visibility level and
    global velocity."""
    out: dict[str, list[dict]] = {}
    for ann in tables["sample_annotation"].values():
        category = tables["category"][tables["instance"][ann["instance_token"]]["category_token"]]["name"]
        name = CATEGORY_TO_DETECTION.get(category)
        if name is None:
            continue
        vis = str(ann.get("visibility_token") or "")
        level = int(vis) if vis in ("1", "2", "3", "4") else None  # nuScenes' visibility tokens are the levels
        out.setdefault(ann["sample_token"], []).append(
            {**ann, "detection_name": name, "visibility_level": level, "velocity": tables.box_velocity(ann)[:2]})
    return out


def view_boxes(view: CameraView, annotations: list[dict], classes: tuple[str, ...],
               config: DetectorTrainConfig) -> ViewBoxes:
    """The annotations a view learns from: of the detector's classes, centre in front of the camera within
    [near_m, max_depth_m] and inside the image, visible enough and (``require_points``) with a point."""
    index = {c: i for i, c in enumerate(classes)}
    rows = []
    for ann in annotations:
        if ann["detection_name"] not in index:
            continue
        if config.require_points and int(ann.get("num_lidar_pts", 1)) + int(ann.get("num_radar_pts", 0)) <= 0:
            continue
        if ann["visibility_level"] is not None and ann["visibility_level"] < config.min_visibility:
            continue
        centre = np.asarray(ann["translation"], np.float64)[None]
        uv, depth = project_to_camera(centre, view.intrinsics, view.global_from_camera)
        u, v, z = float(uv[0, 0]), float(uv[0, 1]), float(depth[0])
        if not (config.near_m <= z <= config.max_depth_m and 0 <= u < view.width and 0 <= v < view.height):
            continue
        corners = box_corners_global(ann["translation"], ann["size"], ann["rotation"])
        cuv, cz = project_to_camera(corners, view.intrinsics, view.global_from_camera)
        cuv = cuv[cz > 0.1] if (cz > 0.1).any() else uv
        x0, y0 = np.clip(cuv.min(0), 0, [view.width, view.height])
        x1, y1 = np.clip(cuv.max(0), 0, [view.width, view.height])
        yaw = yaw_from_quaternion(np.asarray(ann["rotation"])[None])  # [1]
        azimuth = ray_azimuth(centre, view.global_from_camera)[0]
        bottom = centre - [0.0, 0.0, float(ann["size"][2]) / 2]  # nuScenes boxes turn about z only
        buv, bz = project_to_camera(bottom, view.intrinsics, view.global_from_camera)
        buv = buv[0] if bz[0] > 0.1 else uv[0]
        vel = np.asarray(ann["velocity"], np.float64)
        along = vel[0] * np.cos(azimuth) + vel[1] * np.sin(azimuth)
        across = -vel[0] * np.sin(azimuth) + vel[1] * np.cos(azimuth)
        rows.append((u, v, z, *ann["size"], float(observation_angle(yaw, centre, view.global_from_camera)[0]),
                     along, across, index[ann["detection_name"]], y1 - y0, x1 - x0, *buv))
    a = np.array(rows, np.float64).reshape(-1, 14)
    return ViewBoxes(a[:, 0:2], a[:, 2], a[:, 3:6], a[:, 6], a[:, 7:9], a[:, 9].astype(np.int64), a[:, 10:12],
                     a[:, 12:14])


def load_image(view: CameraView, width: int, height: int) -> np.ndarray:  # -> uint8 [3, height, width]
    """The view's image resized to the network input; a clear error naming a missing or unreadable file."""
    from PIL import Image

    try:
        with Image.open(view.image_path) as im:
            image = im.convert("RGB")
            size = image.size
            image = image.resize((width, height), Image.BILINEAR)
    except (OSError, ValueError) as e:
        raise ValidationError(f"camera image {view.image_path} of sample {view.sample_token} is missing or "
                              f"unreadable ({e})") from e
    if view.width and view.height and size != (view.width, view.height):
        raise ValidationError(f"camera image {view.image_path} is {size[0]}x{size[1]} px; its sample_data says "
                              f"{view.width}x{view.height}")
    return np.ascontiguousarray(np.asarray(image, np.uint8).transpose(2, 0, 1))


def _with_size(view: CameraView) -> CameraView:
    """The view with its image size read from the file when sample_data does not give it."""
    if view.width and view.height:
        return view
    from PIL import Image

    try:
        with Image.open(view.image_path) as im:
            w, h = im.size
    except OSError as e:
        raise ValidationError(f"camera image {view.image_path} of sample {view.sample_token} is missing or "
                              f"unreadable ({e})") from e
    return CameraView(view.sample_token, view.channel, view.image_path, w, h, view.intrinsics,
                      view.global_from_camera, view.global_from_ego)


# ----------------------------------------------------------------------------- network
def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 2, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def _conv_bn(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class ProxyDetector(nn.Module):
    def __init__(self, config: DetectorConfig = DetectorConfig()) -> None:
        super().__init__()
        self.config = config
        w, h = config.widths, config.head_width
        self.encoder = nn.ModuleList([_block(5, w[0]), _block(w[0], w[1]), _block(w[1], w[2]), _block(w[2], w[3])])
        self.lateral = nn.ModuleList([nn.Conv2d(c, h, 1) for c in (w[1], w[2], w[3])])
        self.fuse = nn.ModuleList([_conv_bn(h, h), _conv_bn(h, h)])
        self.heat_head = nn.Sequential(_conv_bn(h, h), nn.Conv2d(h, len(config.classes), 1))
        self.reg_head = nn.Sequential(_conv_bn(h, h), nn.Conv2d(h, REGRESSION, 1))
        nn.init.constant_(self.heat_head[-1].bias, math.log(config.heatmap_prior / (1 - config.heatmap_prior)))
        with torch.no_grad():
            self.reg_head[-1].bias.zero_()
            self.reg_head[-1].bias[2] = math.log(config.depth_prior_m)
            self.reg_head[-1].bias[7] = 1.0  # cos alpha

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # images uint8 or float [B, 3, H, W] (0..255) -> heatmap logits [B, C, H/4, W/4],
        # regression [B, REGRESSION, H/4, W/4]
        x = images.float() / 255.0 - 0.5
        b, _, hgt, wid = x.shape
        ys = torch.linspace(-1, 1, hgt, dtype=x.dtype).view(1, 1, hgt, 1).expand(b, 1, hgt, wid)
        xs = torch.linspace(-1, 1, wid, dtype=x.dtype).view(1, 1, 1, wid).expand(b, 1, hgt, wid)
        x = torch.cat([x, xs, ys], 1)
        feats = []
        for block in self.encoder:
            x = block(x)
            feats.append(x)
        top = self.lateral[2](feats[3])
        for level, fuse in ((1, self.fuse[0]), (0, self.fuse[1])):  # stride 8, then stride 4
            skip = feats[level + 1]
            top = fuse(self.lateral[level](skip) + F.interpolate(top, size=skip.shape[-2:], mode="nearest"))
        return self.heat_head(top), self.reg_head(top)


def output_size(config: DetectorConfig) -> tuple[int, int]:
    """(height, width) of the heads' maps."""
    h, w = config.input_height, config.input_width
    for _ in range(2):
        h, w = (h + 1) // 2, (w + 1) // 2
    return h, w


def n_parameters(model: nn.Module) -> int:
    return int(sum(p.numel() for p in model.parameters()))


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
        view = _with_size(view)
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
    record = {"train_config": asdict(config), "detector_config": _config_dict(model.config),
              "n_parameters": n_parameters(model), "n_images": len(data), "n_boxes": n_boxes,
              "boxes_per_class": {c: int(sum((b.label == i).sum() for b in data.boxes))
                                  for i, c in enumerate(model.config.classes)},
              "draws_showing_class": {c: float(sum(w for w, b in zip(weights.tolist(), data.boxes)
                                                   if (b.label == i).any()))
                                      for i, c in enumerate(model.config.classes)},
              "loss_curve": curve, "calibration": calibration, "read_seconds": read_s, "seconds": time.perf_counter() - started,
              "fine_tuned": init is not None}
    return model, record


def regressed_depth(output: np.ndarray, focal_input: float, config: DetectorConfig) -> np.ndarray:
    """Depth (m, optical axis) of the depth channel's output for a camera of ``focal_input`` px at the input size
    (the inverse of the target ``targets`` writes)."""
    return np.exp(np.clip(output, -10, 10)) * focal_input / config.reference_focal


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


# ----------------------------------------------------------------------------- inference
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
    views = [_with_size(v) for t in samples for v in by_sample[t]]
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


# ----------------------------------------------------------------------------- checkpoints
def _config_dict(config: DetectorConfig) -> dict:
    d = asdict(config)
    d["widths"], d["classes"] = list(config.widths), list(config.classes)
    return d


def save_detector(model: ProxyDetector, out_dir: str | Path, training: dict, overwrite: bool = False,
                  readme: str | None = None) -> Path:
    """Weights (safetensors), network config, training record (and a README when given), written atomically."""
    from safetensors.torch import save_file

    with atomic_directory(Path(out_dir), overwrite=overwrite) as tmp:
        save_file({k: v.detach().contiguous() for k, v in model.state_dict().items()}, str(tmp / WEIGHTS))
        atomic_write_json(tmp / CONFIG, _config_dict(model.config))
        atomic_write_json(tmp / TRAINING, training)
        if readme is not None:
            atomic_write_text(tmp / README, readme)
    return Path(out_dir)


def load_detector(path: str | Path | None = None) -> ProxyDetector:
    """A saved detector (default: the shipped one); a clear error when the folder is not one."""
    from safetensors.torch import load_file

    path = Path(path) if path is not None else DEFAULT_DETECTOR
    try:
        raw = json.loads((path / CONFIG).read_text())
        config = DetectorConfig(**{**raw, "widths": tuple(raw["widths"]), "classes": tuple(raw["classes"])})
        state = load_file(str(path / WEIGHTS))
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise ValidationError(f"{path} is not a proxy detector checkpoint ({e}); train one with "
                              "`python -m omniscs.bench.detector_data` or name its folder") from e
    model = ProxyDetector(config)
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        raise ValidationError(f"{path}: the weights do not fit the network of {CONFIG} ({e})") from e
    model.eval()
    return model


def evaluate_detector(model: ProxyDetector, dataroot: str | Path, version: str, results_path: str | Path,
                      config: DetectConfig = DetectConfig(), camera_view: bool = False) -> dict:
    """``model``'s detections of every keyframe of ``dataroot`` written to ``results_path`` and scored
    (``score_detections``)."""
    write_results(detect(model, dataroot, version, config=config), results_path)
    return score_detections(dataroot, version, results_path, camera_view)


def score_detections(dataroot: str | Path, version: str, results_path: str | Path, camera_view: bool = False) -> dict:
    """A results file scored by the nuScenes protocol over the classes the dataroot's evaluated ground truth holds (a
    class absent from a set would only add a zero): mAP, NDS, AP per class (the mean over the distance thresholds,
    and at each), evaluated boxes per class, samples. ``camera_view``: only the boxes a camera sees count
    (``nuscenes_io.in_camera_view``)."""
    from omniscs.eval.detection import DetectionConfig, filter_boxes
    from omniscs.eval.nuscenes_io import evaluate_detection_results, evaluated_classes, evaluated_ground_truth

    tables = NuScenesTables.load(dataroot, version)
    gt, racks = evaluated_ground_truth(tables, tables.scene_samples(), camera_view)
    names = filter_boxes(gt, DetectionConfig(), racks).name
    present = evaluated_classes(gt, racks)
    if not present:
        raise ValidationError(f"{Path(dataroot) / version} has no evaluated ground-truth box"
                              f"{' in a camera view' if camera_view else ''} to score detections on")
    metrics, info = evaluate_detection_results(dataroot, version, results_path,
                                               config=DetectionConfig(class_names=present), camera_view=camera_view)
    return {"mAP": float(metrics.mean_ap), "NDS": float(metrics.nd_score), "classes": list(present),
            "AP": {c: float(v) for c, v in metrics.mean_dist_aps.items()},
            "AP_by_threshold": {c: {f"{t:g}": float(a) for t, a in metrics.label_aps[c].items()} for c in present},
            "gt_boxes": {c: int((names == c).sum()) for c in present}, "n_samples": int(info["n_samples"]),
            "camera_view": bool(camera_view)}
