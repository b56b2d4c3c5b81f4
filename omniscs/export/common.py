"""What every dataset writer shares: global poses, box poses and velocities, LiDAR mount, visibility estimates,
deterministic tokens and the atomic output folder."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from omniscs.errors import OmniscsError
from omniscs.geometry import box_corners_from_pose, invert_transform, make_transform, project
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene.sources.common import ego_from_lidar_of, global_from_world_of, load_attributes
from omniscs.scene.store import Scene, load_scene
from omniscs.storage import atomic_directory

#: LiDAR mount used when a scene records none (nuScenes-like LIDAR_TOP position, axes as the ego's).
DEFAULT_EGO_FROM_LIDAR = make_transform(np.eye(3), [0.94, 0.0, 1.84])
#: A box whose centre speed is below this counts as standing still (m/s).
STILL_SPEED_MPS = 0.5
#: Boxes closer to a camera than this along its axis are not labelled in it (metres).
MIN_LABEL_DEPTH_M = 0.5
#: JPEG quality of written camera images (the formats ship JPEGs; high quality keeps round trips close).
JPEG_QUALITY = 95
#: Slack around a box when counting the LiDAR points inside it (points lie on the surface).
BOX_POINT_MARGIN_M = 0.05


def token(*parts) -> str:
    """A deterministic 32-hex-digit token (nuScenes style) from the parts that identify a record."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def global_poses(scene: Scene) -> np.ndarray:  # -> [F, 4, 4] global_from_ego
    return global_from_world_of(scene) @ scene.world_from_ego_all


def ego_from_lidar(scene: Scene) -> np.ndarray:  # -> [4, 4]
    mount = ego_from_lidar_of(scene)
    return DEFAULT_EGO_FROM_LIDAR.copy() if mount is None else mount


def box_poses(boxes: pd.DataFrame) -> np.ndarray:  # [N] rows -> [N, 4, 4] world_from_box
    if len(boxes) == 0:
        return np.zeros((0, 4, 4))
    q = boxes[["qw", "qx", "qy", "qz"]].to_numpy(np.float64)
    return make_transform(quat_to_rotmat(q), boxes[["cx", "cy", "cz"]].to_numpy(np.float64))


def box_velocities(scene: Scene) -> np.ndarray:  # -> [N, 3] world-frame velocity of each row of scene.boxes (m/s)
    """Finite differences of each track's centre: central where both neighbours exist, else one-sided."""
    boxes = scene.boxes
    ts = scene.frames["timestamp_us"].to_numpy(np.int64) * 1e-6
    vel = np.zeros((len(boxes), 3))
    for _, g in boxes.groupby("track_id", sort=False):
        g = g.sort_values("frame_idx")
        idx = g.index.to_numpy()
        if len(idx) < 2:
            continue
        xyz = g[["cx", "cy", "cz"]].to_numpy(np.float64)
        t = ts[g["frame_idx"].to_numpy()]
        grad = np.gradient(xyz, t, axis=0)
        vel[boxes.index.get_indexer(idx)] = grad
    return vel


def projected_rect(camera_from_box: np.ndarray, size: np.ndarray, K: np.ndarray, width: int, height: int
                   ) -> tuple[np.ndarray, float, bool] | None:
    """The image rectangle of a box: ([x1, y1, x2, y2] clipped to the image, fraction of the unclipped rectangle
    outside the image, whether all corners are in front of the camera), or None when the box centre is nearer
    than MIN_LABEL_DEPTH_M or the rectangle is empty. Corners behind the camera are left out of the rectangle.
    """
    if camera_from_box[2, 3] < MIN_LABEL_DEPTH_M:
        return None
    corners = box_corners_from_pose(camera_from_box, size)
    uv, _, front = project(corners, K, near=MIN_LABEL_DEPTH_M)
    if not front.any():
        return None
    uv = uv[front]
    full = np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])
    clipped = np.array([np.clip(full[0], 0, width), np.clip(full[1], 0, height),
                        np.clip(full[2], 0, width), np.clip(full[3], 0, height)])
    area = (clipped[2] - clipped[0]) * (clipped[3] - clipped[1])
    if area <= 0:
        return None
    full_area = max((full[2] - full[0]) * (full[3] - full[1]), area)
    return clipped, float(1.0 - area / full_area), bool(front.all())


def visible_fraction(scene: Scene, row, world_from_box: np.ndarray) -> float | None:
    """Estimated visible fraction of a box: its visible pixels over the area of its rectangles in all cameras.

    None when the scene does not know visible pixels. Rough: rectangles over-count a box's silhouette.
    """
    if row.visible_pixels < 0:
        return None
    size = np.array([row.length, row.width, row.height])
    area = 0.0
    for cam in scene.camera_names:
        c = scene.camera(cam)
        camera_from_box = invert_transform(scene.world_from_camera(cam, int(row.frame_idx))) @ world_from_box
        rect = projected_rect(camera_from_box, size, c.K, c.width, c.height)
        if rect is not None:
            r = rect[0]
            area += (r[2] - r[0]) * (r[3] - r[1])
    if area <= 0:
        return 0.0
    return float(min(1.0, row.visible_pixels / area))


def attribute_lookup(scene: Scene, name: str) -> dict[tuple[int, int], str]:
    """{(frame_idx, track_id): value} of one attribute of a scene read from a dataset (empty otherwise)."""
    attrs = load_attributes(scene)
    attrs = attrs[attrs["name"] == name]
    return {(int(f), int(t)): v for f, t, v in zip(attrs["frame_idx"], attrs["track_id"], attrs["value"])}


def encode_jpeg(rgb: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:  # uint8 [H, W, 3] RGB -> JPEG bytes
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise OmniscsError("could not encode a JPEG image")
    return buf.tobytes()


def encode_png(rgb: np.ndarray) -> bytes:  # uint8 [H, W, 3] RGB -> PNG bytes
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OmniscsError("could not encode a PNG image")
    return buf.tobytes()


def encode_mask_png(mask: np.ndarray) -> bytes:  # uint8 [H, W] -> PNG bytes, one channel
    """A single-channel 8-bit PNG (a binary mask: 0 background, 255 foreground, as the devkit's MapMask reads it)."""
    import cv2

    if mask.dtype != np.uint8 or mask.ndim != 2:
        raise OmniscsError(f"a mask PNG is uint8 [H, W]; got {mask.dtype} {mask.shape}")
    ok, buf = cv2.imencode(".png", mask)
    if not ok:
        raise OmniscsError("could not encode a PNG mask")
    return buf.tobytes()


def write_bytes(path: Path, data: bytes) -> None:
    """Write a file inside an export's temporary folder (the folder as a whole is renamed when complete)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def export_scenes(scene_paths: list[str | os.PathLike], fmt: str, out: str | os.PathLike, overwrite: bool = False,
                  progress: Callable[[int, int], None] | None = None, **options) -> Path:
    """Write scene stores as one dataset of format ``fmt`` at ``out``; nothing is left at ``out`` on failure.

    ``options`` go to the format's writer (nuScenes: version, keyframe_every, location, scene_spacing_m; UniAD: those
    and the UniADConfig fields, e.g. box_convention, val_scenes; KITTI: camera, split; OpenSCENARIO: config,
    nuscenes_maps).
    """
    from omniscs.export import WRITERS

    if fmt not in WRITERS:
        raise OmniscsError(f"unknown export format {fmt!r}; use one of {list(WRITERS)}")
    if not scene_paths:
        raise OmniscsError("name at least one scene store to export")
    out = Path(out)
    if out.exists() and not overwrite:
        raise OmniscsError(f"{out} already exists; choose another --out or pass --overwrite")
    scenes = [load_scene(p) for p in scene_paths]
    ids = [s.scene_id for s in scenes]
    if len(set(ids)) != len(ids):
        raise OmniscsError(f"the same scene is named twice: {sorted({i for i in ids if ids.count(i) > 1})}")
    with atomic_directory(out, overwrite=overwrite) as tmp:
        WRITERS[fmt](scenes, tmp, progress=progress, **options)
    return out
