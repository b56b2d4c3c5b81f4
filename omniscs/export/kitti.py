"""KITTI tracking writer: scene stores as sequences ``<split>/{image_02,velodyne,calib,label_02,oxts}`` of one root.

One camera (``camera``, default CAM_FRONT) becomes image_02 and defines the rectified reference frame
(R_rect = I, P0..P3 = [K | 0]); other cameras are not written (KITTI tracking has one left colour camera; image_03
would need a true stereo partner). The IMU/OXTS frame is the store's ego frame; the velodyne frame is the scene's
LiDAR mount. Poses are written as OXTS lat/lon/alt/roll/pitch/yaw by inverting the devkit's Mercator projection:
scenes read from KITTI keep their Mercator frame, others are placed with their first pose at ``DEFAULT_GEO_ORIGIN``.
OXTS velocities come from pose differences; accelerations and angular rates are written as 0. KITTI tracking has
no timestamps, so a reader assumes 10 Hz. Labels: boxes whose image rectangle in the camera is non-empty (KITTI
labels what the camera sees), classes KITTI has under its names (Car, Van, Truck, Pedestrian, Person_sitting,
Cyclist, Tram, Misc), the others under the project's class name (as nuScenes' own KITTI export does); boxes are
upright in the rectified frame (rotation_y only). Truncation and occlusion levels are estimates.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.export.common import (
    box_poses,
    ego_from_lidar,
    encode_png,
    projected_rect,
    visible_fraction,
    write_bytes,
)
from omniscs.geometry import invert_transform, make_transform, wrap_angle
from omniscs.scene.sources.common import global_from_world_of, load_attributes
from omniscs.scene.sources.kitti import (
    DONT_CARE,
    INTENSITY_SCALE,
    KITTI_OBJECT_FROM_BOX,
    TYPE_TO_CATEGORY,
    mercator_scale,
    oxts_to_pose,
    pose_to_oxts_geo,
)
from omniscs.scene.store import Scene
from omniscs.untrusted import loads_json

#: Where scenes without a KITTI pose frame are placed: latitude, longitude (degrees), altitude (m) of Karlsruhe.
DEFAULT_GEO_ORIGIN = (49.011, 8.4165, 115.0)
#: Project classes KITTI has its own name for (others are written under the project's name).
KITTI_TYPES = {"car": "Car", "truck": "Truck", "pedestrian": "Pedestrian", "bicycle": "Cyclist"}
#: OXTS status fields written: pos_accuracy (m), vel_accuracy (m/s), navstat, numsats, posmode, velmode, orimode.
OXTS_STATUS = (0.05, 0.05, 4, 10, 4, 4, 4)
#: Fraction of a box's image rectangle outside the image above which it counts as heavily truncated (level 2).
HEAVY_TRUNCATION = 0.5
#: Visible fractions for occlusion levels 0 (fully visible) and 1 (partly occluded); below: 2 (largely occluded).
OCCLUSION_BOUNDS = (0.8, 0.4)
OCCLUSION_UNKNOWN = 3


def kitti_type(category: str, source_category: str | None) -> str:
    """The KITTI type of a store box; it always maps back to the same project class."""
    if source_category in TYPE_TO_CATEGORY and TYPE_TO_CATEGORY[source_category] == category:
        return source_category
    if category == "car" and source_category == "van":
        return "Van"
    return KITTI_TYPES.get(category, category)


def _fmt(values) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(values, dtype=np.float64).ravel())


def write_kitti(scenes: list[Scene], root: Path, camera: str = "CAM_FRONT", split: str = "training",
                progress: Callable[[int, int], None] | None = None) -> Path:
    """Write ``scenes`` as KITTI tracking sequences 0000, 0001, ... under ``root/split``."""
    base = root / split
    total = sum(s.n_frames for s in scenes)
    done = 0
    for i, scene in enumerate(scenes):
        for _ in _write_sequence(scene, base, f"{i:04d}", camera):
            done += 1
            if progress:
                progress(done, total)
    return root


def mercator_from_world(scene: Scene) -> tuple[np.ndarray, float]:  # -> [4, 4], Mercator scale
    """The scene's KITTI Mercator frame: kept from a KITTI source, else first pose at DEFAULT_GEO_ORIGIN."""
    global_from_world = global_from_world_of(scene)
    kept = scene.manifest.get("kitti_mercator_scale")
    if scene.manifest.get("dataset") == "kitti" and kept:
        return global_from_world, float(kept)
    lat, lon, alt = DEFAULT_GEO_ORIGIN
    scale = mercator_scale(lat)
    ref = oxts_to_pose(np.array([lat, lon, alt, 0.0, 0.0, 0.0]), scale)[:3, 3]
    first = (global_from_world @ scene.world_from_ego(0))[:3, 3]
    return make_transform(np.eye(3), ref - first) @ global_from_world, scale


def _write_sequence(scene: Scene, base: Path, seq: str, camera: str):
    cam = scene.camera(camera)
    ego_from_velo = ego_from_lidar(scene)
    velo_from_ego = invert_transform(ego_from_velo)
    cam_from_ego = invert_transform(cam.ego_from_camera)
    P = np.hstack([cam.K, np.zeros((3, 1))])
    calib = [f"P{k}: {_fmt(P)}" for k in range(4)]
    calib += [f"R_rect {_fmt(np.eye(3))}", f"Tr_velo_cam {_fmt((cam_from_ego @ ego_from_velo)[:3])}",
              f"Tr_imu_velo {_fmt(velo_from_ego[:3])}"]
    write_bytes(base / "calib" / f"{seq}.txt", ("\n".join(calib) + "\n").encode())
    write_bytes(base / "oxts" / f"{seq}.txt", _oxts_lines(scene).encode())

    boxes = scene.boxes.reset_index(drop=True)
    world_from_box = box_poses(boxes)
    by_frame = {int(f): g.index.to_numpy() for f, g in boxes.groupby("frame_idx")}
    dont_care = _dont_care(scene, camera)
    labels = []
    for f in range(scene.n_frames):
        write_bytes(base / "image_02" / seq / f"{f:06d}.png", encode_png(scene.image(camera, f)))
        if scene.has_lidar:
            pts = scene.lidar(f)
            out = np.empty((len(pts), 4), np.float32)
            out[:, :3] = pts[:, :3].astype(np.float64) @ velo_from_ego[:3, :3].T + velo_from_ego[:3, 3]
            out[:, 3] = np.clip(pts[:, 3] / INTENSITY_SCALE, 0.0, 1.0)
            (base / "velodyne" / seq).mkdir(parents=True, exist_ok=True)
            out.tofile(base / "velodyne" / seq / f"{f:06d}.bin")
        rect_from_world = cam_from_ego @ invert_transform(scene.world_from_ego(f))
        for i in by_frame.get(f, []):
            line = _label(f, boxes.iloc[i], rect_from_world @ world_from_box[i], cam, scene, world_from_box[i])
            if line:
                labels.append(line)
        labels += [f"{f} -1 {DONT_CARE} -1 -1 -10 {' '.join(f'{v:.6f}' for v in bbox)} -1 -1 -1 -1000 -1000 -1000 -10"
                   for bbox in dont_care.get(f, [])]
        yield f
    write_bytes(base / "label_02" / f"{seq}.txt", ("\n".join(labels) + ("\n" if labels else "")).encode())


def _dont_care(scene: Scene, camera: str) -> dict[int, list[list[float]]]:
    attrs = load_attributes(scene)
    attrs = attrs[(attrs["name"] == "dont_care_bbox") & (attrs["camera"] == camera)]
    out: dict[int, list[list[float]]] = {}
    for f, value in zip(attrs["frame_idx"], attrs["value"]):
        out.setdefault(int(f), []).append(loads_json(value, f"a dont_care_bbox attribute of {scene.path}",
                                                     "re-ingest the source", expect=list))
    return out


def _label(f: int, row, rect_from_box: np.ndarray, cam, scene: Scene, world_from_box: np.ndarray) -> str | None:
    size = np.array([row.length, row.width, row.height])
    rect = projected_rect(rect_from_box, size, cam.K, cam.width, cam.height)
    if rect is None:
        return None
    bbox, outside, all_in_front = rect
    R = rect_from_box[:3, :3]
    heading = (R @ KITTI_OBJECT_FROM_BOX.T)[:, 0]
    ry = float(np.arctan2(-heading[2], heading[0]))
    x, y, z = rect_from_box[:3, 3] + R @ np.array([0.0, 0.0, -0.5 * row.height])
    alpha = float(wrap_angle(ry - np.arctan2(x, z)))
    truncated = 0 if outside <= 0 and all_in_front else (1 if outside <= HEAVY_TRUNCATION else 2)
    fraction = visible_fraction(scene, row, world_from_box)
    occluded = (OCCLUSION_UNKNOWN if fraction is None else
                0 if fraction >= OCCLUSION_BOUNDS[0] else 1 if fraction >= OCCLUSION_BOUNDS[1] else 2)
    kind = kitti_type(row.category, row.source_category)
    values = [alpha, *bbox, row.height, row.width, row.length, x, y, z, ry]
    return f"{f} {int(row.track_id)} {kind} {truncated} {occluded} " + " ".join(f"{v:.6f}" for v in values)


def _oxts_lines(scene: Scene) -> str:
    mercator_from_world_, scale = mercator_from_world(scene)
    poses = mercator_from_world_ @ scene.world_from_ego_all
    t = scene.frames["timestamp_us"].to_numpy(np.int64) * 1e-6
    velocity = np.gradient(poses[:, :3, 3], t, axis=0) if len(t) > 1 else np.zeros((1, 3))
    lines = []
    for pose, v in zip(poses, velocity):
        geo = pose_to_oxts_geo(pose, scale)
        v_vehicle = pose[:3, :3].T @ v
        motion = [v[1], v[0], *v_vehicle] + [0.0] * 12  # vn ve vf vl vu, then ax..wu
        lines.append(" ".join([*(repr(g) for g in geo), *(f"{m:.9g}" for m in motion),
                               *(str(s) for s in OXTS_STATUS)]))
    return "\n".join(lines) + "\n"
