"""Waymo Open Dataset v2 writer: scene stores as Parquet component tables ``<root>/<component>/<segment>.parquet``.

Components written (column names and Arrow types of the published v2 schema): ``vehicle_pose``,
``camera_calibration`` (no lens distortion; extrinsic converted to Waymo's camera axes x forward, y left, z up),
``camera_image`` (JPEG, frame pose; velocity and rolling-shutter fields are 0 / the frame time: the store has
no such data), ``lidar_box`` (upright boxes in the vehicle frame; speed from the track, acceleration 0,
difficulty level 2 for boxes with at most ``LEVEL_2_MAX_POINTS`` LiDAR points), ``camera_box`` (2D rectangles of the
projected 3D boxes; ``key.camera_object_id`` is the box's laser object id: ``camera_to_lidar_box_association`` is
not written), ``lidar_calibration`` and ``lidar`` (the scene's LiDAR as the TOP laser's first return), and
``stats``. Cameras map by name: CAM_FRONT, CAM_FRONT_LEFT, CAM_FRONT_RIGHT, CAM_SIDE_LEFT, CAM_SIDE_RIGHT; other
cameras (nuScenes' rear ones) have no Waymo slot and are not written.

LiDAR: points are binned into a range image of Waymo's layout (columns from azimuth +pi down in the vehicle
frame, rows from the highest inclination). Synthetic scenes give their exact beam inclinations and column count
(``beam_inclination.values``), so a round trip moves points only along the azimuth, by at most half a column;
other scenes get ``DEFAULT_ROWS`` x ``DEFAULT_COLUMNS`` spanning their points' inclinations. Two points in one
pixel keep the nearer. Classes: vehicles -> TYPE_VEHICLE, pedestrian -> TYPE_PEDESTRIAN, bicycle -> TYPE_CYCLIST;
traffic cones, barriers and debris have no Waymo type and are written as TYPE_UNKNOWN (a reader drops them).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.errors import OmniscsError
from omniscs.export.common import (
    BOX_POINT_MARGIN_M,
    attribute_lookup,
    box_poses,
    box_velocities,
    ego_from_lidar,
    encode_jpeg,
    global_poses,
    projected_rect,
    token,
)
from omniscs.geometry import invert_transform, points_in_box, yaw_from_matrix
from omniscs.scene.sources.waymo_v2 import (
    CALIB,
    CAMERA_BOX,
    CAMERA_NAME,
    CAMERA_OBJECT_ID,
    CAMERAS,
    DISTORTION,
    IMAGE,
    INTENSITY_SCALE,
    LASER_NAME,
    LASER_OBJECT_ID,
    LIDAR,
    LIDAR_BOX,
    LIDAR_CALIB,
    POSE,
    RANGE_IMAGE_CHANNELS,
    SEGMENT,
    STATS,
    TIMESTAMP,
    TOP_LASER,
    WAYMO_CAMERA_FROM_OPENCV,
)
from omniscs.scene.store import Scene

#: Range image size for scenes whose LiDAR pattern is unknown (Waymo's TOP LiDAR is 64 x 2650).
DEFAULT_ROWS = 64
DEFAULT_COLUMNS = 2650
#: Rounds azimuths that fall between two columns consistently to the same side (in columns; larger than the
#: float32 noise of stored points, which is ~2e-5 column at 70 m).
AZIMUTH_TIE_BIAS = 1e-3
#: Value of every channel of a range-image pixel without a return; no-label-zone value of a return.
EMPTY_PIXEL = -1.0
NOT_IN_NO_LABEL_ZONE = -1.0
#: Waymo's rule: boxes with at most this many LiDAR points are difficulty LEVEL_2, others LEVEL_1.
LEVEL_2_MAX_POINTS = 5
GLOBAL_SHUTTER = 5
TYPE_UNKNOWN, TYPE_VEHICLE, TYPE_PEDESTRIAN, TYPE_CYCLIST = 0, 1, 2, 4
#: Project classes as Waymo box types.
BOX_TYPE_OF: dict[str, int] = {
    "car": TYPE_VEHICLE, "truck": TYPE_VEHICLE, "bus": TYPE_VEHICLE, "trailer": TYPE_VEHICLE,
    "construction_vehicle": TYPE_VEHICLE, "motorcycle": TYPE_VEHICLE, "pedestrian": TYPE_PEDESTRIAN,
    "bicycle": TYPE_CYCLIST,
}
#: Store lighting presets as the stats component's time of day.
TIME_OF_DAY = {"day": "Day", "dusk": "Dawn/Dusk", "night": "Night", "fog": "Day"}

_CAMERA_ENUM = {name: enum for enum, name in CAMERAS.items()}
_TRANSFORM = pa.list_(pa.float64(), 16)


def segment_name(scene: Scene) -> str:
    own = scene.manifest.get("source_scene_id") if scene.manifest.get("dataset") == "waymo-v2" else None
    return own or scene.scene_id


def write_waymo_v2(scenes: list[Scene], root: Path, progress: Callable[[int, int], None] | None = None) -> Path:
    """Write each scene as one segment of v2 component tables under ``root``."""
    total = sum(s.n_frames for s in scenes)
    done = 0
    names = [segment_name(s) for s in scenes]
    if len(set(names)) != len(names):
        raise OmniscsError(f"two scenes would share a Waymo segment name: {names}")
    for scene, segment in zip(scenes, names):
        for _ in _write_segment(scene, segment, root):
            done += 1
            if progress:
                progress(done, total)
    return root


def _write(root: Path, component: str, segment: str, columns: dict[str, tuple[pa.DataType, list]]) -> None:
    table = pa.table({name: pa.array(values, type=dtype) for name, (dtype, values) in columns.items()})
    path = root / component / f"{segment}.parquet"
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)


def _write_segment(scene: Scene, segment: str, root: Path):
    cams = [c for c in scene.camera_names if c in _CAMERA_ENUM]
    if not cams:
        raise OmniscsError(f"scene {scene.scene_id} has no camera with a Waymo slot ({list(_CAMERA_ENUM)}); "
                           f"it has {scene.camera_names}")
    ts = scene.frames["timestamp_us"].to_numpy(np.int64)
    poses = global_poses(scene)
    F = len(ts)
    _write(root, "vehicle_pose", segment, {
        SEGMENT: (pa.string(), [segment] * F), TIMESTAMP: (pa.int64(), ts.tolist()),
        POSE: (_TRANSFORM, [p.reshape(16).tolist() for p in poses])})
    calib = {SEGMENT: (pa.string(), [segment] * len(cams)),
             CAMERA_NAME: (pa.int8(), [_CAMERA_ENUM[c] for c in cams])}
    for k, i, j in (("f_u", 0, 0), ("f_v", 1, 1), ("c_u", 0, 2), ("c_v", 1, 2)):
        calib[f"{CALIB}.intrinsic.{k}"] = (pa.float64(), [float(scene.intrinsics(c)[i, j]) for c in cams])
    for k in DISTORTION:
        calib[f"{CALIB}.intrinsic.{k}"] = (pa.float64(), [0.0] * len(cams))
    calib[f"{CALIB}.extrinsic.transform"] = (_TRANSFORM, [
        (scene.ego_from_camera(c) @ invert_transform(WAYMO_CAMERA_FROM_OPENCV)).reshape(16).tolist() for c in cams])
    calib[f"{CALIB}.width"] = (pa.int32(), [scene.image_size(c)[0] for c in cams])
    calib[f"{CALIB}.height"] = (pa.int32(), [scene.image_size(c)[1] for c in cams])
    calib[f"{CALIB}.rolling_shutter_direction"] = (pa.int8(), [GLOBAL_SHUTTER] * len(cams))
    _write(root, "camera_calibration", segment, calib)

    images = {k: [] for k in ("ts", "cam", "image", "pose")}
    lidar_rows = {k: [] for k in ("ts", "values", "shape")}
    mount = ego_from_lidar(scene)
    pattern = _lidar_pattern(scene, mount) if scene.has_lidar else None
    for f in range(F):
        for c in cams:
            images["ts"].append(int(ts[f]))
            images["cam"].append(_CAMERA_ENUM[c])
            images["image"].append(encode_jpeg(scene.image(c, f)))
            images["pose"].append(poses[f].reshape(16).tolist())
        if pattern is not None:
            ri = points_to_range_image(scene.lidar(f), mount, *pattern)
            lidar_rows["ts"].append(int(ts[f]))
            lidar_rows["values"].append(ri.reshape(-1))
            lidar_rows["shape"].append(list(ri.shape))
        yield f
    n = len(images["ts"])
    t_s = [t * 1e-6 for t in images["ts"]]
    _write(root, "camera_image", segment, {
        SEGMENT: (pa.string(), [segment] * n), TIMESTAMP: (pa.int64(), images["ts"]),
        CAMERA_NAME: (pa.int8(), images["cam"]), f"{IMAGE}.image": (pa.binary(), images["image"]),
        f"{IMAGE}.pose.transform": (_TRANSFORM, images["pose"]),
        **{f"{IMAGE}.velocity.linear_velocity.{a}": (pa.float32(), [0.0] * n) for a in "xyz"},
        **{f"{IMAGE}.velocity.angular_velocity.{a}": (pa.float64(), [0.0] * n) for a in "xyz"},
        f"{IMAGE}.pose_timestamp": (pa.float64(), t_s),
        f"{IMAGE}.rolling_shutter_params.shutter": (pa.float64(), [0.0] * n),
        f"{IMAGE}.rolling_shutter_params.camera_trigger_time": (pa.float64(), t_s),
        f"{IMAGE}.rolling_shutter_params.camera_readout_done_time": (pa.float64(), t_s)})
    if pattern is not None:
        inclination, _ = pattern
        _write(root, "lidar_calibration", segment, {
            SEGMENT: (pa.string(), [segment]), LASER_NAME: (pa.int8(), [TOP_LASER]),
            f"{LIDAR_CALIB}.extrinsic.transform": (_TRANSFORM, [mount.reshape(16).tolist()]),
            f"{LIDAR_CALIB}.beam_inclination.min": (pa.float64(), [float(inclination[0])]),
            f"{LIDAR_CALIB}.beam_inclination.max": (pa.float64(), [float(inclination[-1])]),
            f"{LIDAR_CALIB}.beam_inclination.values": (pa.list_(pa.float64()), [inclination.tolist()])})
        k = len(lidar_rows["ts"])
        _write(root, "lidar", segment, {
            SEGMENT: (pa.string(), [segment] * k), TIMESTAMP: (pa.int64(), lidar_rows["ts"]),
            LASER_NAME: (pa.int8(), [TOP_LASER] * k),
            f"{LIDAR}.range_image_return1.values": (pa.list_(pa.float32()), lidar_rows["values"]),
            f"{LIDAR}.range_image_return1.shape": (pa.list_(pa.int32(), 3), lidar_rows["shape"])})
    _write_boxes(scene, segment, root, cams, poses)
    _write(root, "stats", segment, {
        SEGMENT: (pa.string(), [segment] * F), TIMESTAMP: (pa.int64(), ts.tolist()),
        f"{STATS}.time_of_day": (pa.string(), [TIME_OF_DAY.get(scene.manifest.get("lighting"),
                                                               scene.manifest.get("time_of_day") or "Day")] * F),
        f"{STATS}.location": (pa.string(), [scene.manifest.get("location") or "location_omniscs"] * F),
        f"{STATS}.weather": (pa.string(), [scene.manifest.get("weather") or "sunny"] * F)})


def _object_ids(scene: Scene) -> dict[int, str]:
    kept = attribute_lookup(scene, "laser_object_id")
    ids = {tid: value for (_, tid), value in kept.items()}
    for tid in scene.boxes["track_id"].unique():
        ids.setdefault(int(tid), token("waymo-object", scene.scene_id, int(tid))[:22])
    return ids


def _write_boxes(scene: Scene, segment: str, root: Path, cams: list[str], poses: np.ndarray) -> None:
    boxes = scene.boxes.reset_index(drop=True)
    ts = scene.frames["timestamp_us"].to_numpy(np.int64)
    world_from_box = box_poses(boxes)
    velocity = box_velocities(scene)
    ids = _object_ids(scene)
    lidar: dict[int, np.ndarray] = {}
    cols = {k: [] for k in ("ts", "id", "center", "size", "heading", "type", "points", "speed", "level")}
    cam_cols = {k: [] for k in ("ts", "cam", "id", "center", "size", "type")}
    for i, row in enumerate(boxes.itertuples()):
        f = int(row.frame_idx)
        vehicle_from_world = invert_transform(scene.world_from_ego(f))
        vehicle_from_box = vehicle_from_world @ world_from_box[i]
        size = np.array([row.length, row.width, row.height])
        n_points = int(row.num_lidar_points)
        if n_points < 0 and scene.has_lidar:
            if f not in lidar:
                lidar = {f: scene.lidar(f)}
            n_points = int(points_in_box(lidar[f], vehicle_from_box, size, BOX_POINT_MARGIN_M).sum())
        box_type = BOX_TYPE_OF.get(row.category, TYPE_UNKNOWN)
        cols["ts"].append(int(ts[f]))
        cols["id"].append(ids[int(row.track_id)])
        cols["center"].append(vehicle_from_box[:3, 3])
        cols["size"].append(size)
        cols["heading"].append(float(yaw_from_matrix(vehicle_from_box[:3, :3])))
        cols["type"].append(box_type)
        cols["points"].append(max(n_points, 0))
        cols["speed"].append(vehicle_from_world[:3, :3] @ velocity[i])
        cols["level"].append(2 if max(n_points, 0) <= LEVEL_2_MAX_POINTS else 1)
        for c in cams:
            cam = scene.camera(c)
            camera_from_box = invert_transform(cam.ego_from_camera) @ vehicle_from_box
            rect = projected_rect(camera_from_box, size, cam.K, cam.width, cam.height)
            if rect is None:
                continue
            r = rect[0]
            cam_cols["ts"].append(int(ts[f]))
            cam_cols["cam"].append(_CAMERA_ENUM[c])
            cam_cols["id"].append(ids[int(row.track_id)])
            cam_cols["center"].append([(r[0] + r[2]) / 2, (r[1] + r[3]) / 2])
            cam_cols["size"].append([r[2] - r[0], r[3] - r[1]])
            cam_cols["type"].append(box_type)
    n = len(cols["ts"])
    center = np.reshape(cols["center"], (n, 3))
    size = np.reshape(cols["size"], (n, 3))
    speed = np.reshape(cols["speed"], (n, 3))
    _write(root, "lidar_box", segment, {
        SEGMENT: (pa.string(), [segment] * n), TIMESTAMP: (pa.int64(), cols["ts"]),
        LASER_OBJECT_ID: (pa.string(), cols["id"]),
        **{f"{LIDAR_BOX}.box.center.{a}": (pa.float64(), center[:, k].tolist()) for k, a in enumerate("xyz")},
        **{f"{LIDAR_BOX}.box.size.{a}": (pa.float64(), size[:, k].tolist()) for k, a in enumerate("xyz")},
        f"{LIDAR_BOX}.box.heading": (pa.float64(), cols["heading"]),
        f"{LIDAR_BOX}.type": (pa.int8(), cols["type"]),
        f"{LIDAR_BOX}.num_lidar_points_in_box": (pa.int64(), cols["points"]),
        f"{LIDAR_BOX}.num_top_lidar_points_in_box": (pa.int64(), cols["points"]),
        **{f"{LIDAR_BOX}.speed.{a}": (pa.float64(), speed[:, k].tolist()) for k, a in enumerate("xyz")},
        **{f"{LIDAR_BOX}.acceleration.{a}": (pa.float64(), [0.0] * n) for a in "xyz"},
        f"{LIDAR_BOX}.difficulty_level.detection": (pa.int8(), cols["level"]),
        f"{LIDAR_BOX}.difficulty_level.tracking": (pa.int8(), cols["level"])})
    m = len(cam_cols["ts"])
    c2 = np.reshape(cam_cols["center"], (m, 2))
    s2 = np.reshape(cam_cols["size"], (m, 2))
    _write(root, "camera_box", segment, {
        SEGMENT: (pa.string(), [segment] * m), TIMESTAMP: (pa.int64(), cam_cols["ts"]),
        CAMERA_NAME: (pa.int8(), cam_cols["cam"]), CAMERA_OBJECT_ID: (pa.string(), cam_cols["id"]),
        f"{CAMERA_BOX}.box.center.x": (pa.float64(), c2[:, 0].tolist()),
        f"{CAMERA_BOX}.box.center.y": (pa.float64(), c2[:, 1].tolist()),
        f"{CAMERA_BOX}.box.size.x": (pa.float64(), s2[:, 0].tolist()),
        f"{CAMERA_BOX}.box.size.y": (pa.float64(), s2[:, 1].tolist()),
        f"{CAMERA_BOX}.type": (pa.int8(), cam_cols["type"]),
        f"{CAMERA_BOX}.difficulty_level.detection": (pa.int8(), [1] * m),
        f"{CAMERA_BOX}.difficulty_level.tracking": (pa.int8(), [1] * m)})


def _lidar_pattern(scene: Scene, mount: np.ndarray) -> tuple[np.ndarray, int]:
    """Ascending beam inclinations [H] (radians) and column count of the range image."""
    world = scene.world
    if world is not None:
        spec = world.lidar
        incl = np.radians(np.linspace(spec.min_elevation_deg, spec.max_elevation_deg, spec.beams))
        return incl, int(spec.azimuth_steps)
    lidar_from_ego = invert_transform(mount)
    lo, hi = np.inf, -np.inf
    for f in range(scene.n_frames):
        p = scene.lidar(f)[:, :3].astype(np.float64) @ lidar_from_ego[:3, :3].T + lidar_from_ego[:3, 3]
        r = np.linalg.norm(p, axis=1)
        if np.any(r > 0):
            incl = np.arcsin(p[r > 0, 2] / r[r > 0])
            lo, hi = min(lo, incl.min()), max(hi, incl.max())
    if not np.isfinite(lo):
        lo, hi = -0.3, 0.05
    return np.linspace(lo, hi, DEFAULT_ROWS), DEFAULT_COLUMNS


def points_to_range_image(points_ego: np.ndarray, vehicle_from_lidar: np.ndarray, inclination: np.ndarray,
                          width: int) -> np.ndarray:
    """points [N, 4] ego x, y, z, intensity; extrinsic [4, 4]; inclination [H] ascending -> float32 [H, W, 4].

    The inverse of ``omniscs.scene.sources.waymo_v2.range_image_to_points`` up to the pixel grid.
    """
    H = len(inclination)
    lidar_from_vehicle = invert_transform(vehicle_from_lidar)
    p = points_ego[:, :3].astype(np.float64) @ lidar_from_vehicle[:3, :3].T + lidar_from_vehicle[:3, 3]
    r = np.linalg.norm(p, axis=1)
    keep = r > 0
    p, r, intensity = p[keep], r[keep], points_ego[keep, 3]
    az_correction = np.arctan2(vehicle_from_lidar[1, 0], vehicle_from_lidar[0, 0])
    az_vehicle = np.arctan2(p[:, 1], p[:, 0]) + az_correction
    column = (np.pi - az_vehicle) / (2 * np.pi) * width - 0.5  # column centres are integers
    col = np.floor(column + 0.5 + AZIMUTH_TIE_BIAS).astype(np.int64) % width
    incl = np.arcsin(np.clip(p[:, 2] / r, -1.0, 1.0))
    nearest = np.abs(incl[:, None] - inclination[None, :]).argmin(axis=1)
    row = H - 1 - nearest  # row 0 is the highest beam
    pixel = row * width + col
    order = np.lexsort((r, pixel))  # by pixel, nearest first
    first = np.ones(len(order), bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    sel = order[first]  # the nearest return of each pixel
    image = np.full((H, width, RANGE_IMAGE_CHANNELS), EMPTY_PIXEL, np.float32)
    image[row[sel], col[sel], 0] = r[sel]
    image[row[sel], col[sel], 1] = intensity[sel] / INTENSITY_SCALE
    image[row[sel], col[sel], 2] = 0.0
    image[row[sel], col[sel], 3] = NOT_IN_NO_LABEL_ZONE
    return image
