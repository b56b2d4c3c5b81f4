"""What the proxy detector reads from a nuScenes dataroot (``omniscs.eval.detector``): per keyframe sample and camera
the view (image, intrinsics, poses) and its annotated boxes projected into it, and the camera geometry (projection,
back-projection, observation angle) that training and decoding share."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omniscs.errors import ValidationError
from omniscs.eval.detector_config import DetectorTrainConfig
from omniscs.eval.nuscenes_io import CATEGORY_TO_DETECTION, NuScenesTables
from omniscs.geometry import invert_transform, make_transform
from omniscs.quaternions import quat_to_rotmat, yaw_from_quaternion


# ----------------------------------------------------------------------------- geometry
def transform_of(record: dict) -> np.ndarray:  # {translation [3], rotation [4] w, x, y, z} -> [4, 4]

    return make_transform(quat_to_rotmat(np.asarray(record["rotation"], np.float64)),
                          np.asarray(record["translation"], np.float64))


def project_to_camera(points_global: np.ndarray,      # [N, 3] global
                      intrinsics: np.ndarray,         # [3, 3]
                      global_from_camera: np.ndarray,  # [4, 4]
                      ) -> tuple[np.ndarray, np.ndarray]:  # uv [N, 2] px, depth [N] m along the optical axis
    """Pixels and depths of global points (uv is meaningless where depth <= 0)."""
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


def view_with_image_size(view: CameraView) -> CameraView:
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
