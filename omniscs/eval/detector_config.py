"""The proxy camera detector's configuration (``omniscs.eval.detector``): the network's shape and classes, how
it is trained and how its outputs are decoded, and the constants of those outputs (stride, regression channels,
typical class sizes)."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from omniscs.errors import ValidationError
from omniscs.eval.detection import DETECTION_NAMES

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


def config_dict(config: DetectorConfig) -> dict:
    """The network config as JSON values (tuples as lists), as a checkpoint stores it."""
    d = asdict(config)
    d["widths"], d["classes"] = list(config.widths), list(config.classes)
    return d
