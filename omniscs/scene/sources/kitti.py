"""KITTI tracking reader: one sequence (image_02/03, velodyne, calib, label_02, oxts) into the scene store.

Frames: ego = the OXTS/IMU frame (x forward, y left, z up); poses from the OXTS lat/lon/alt/roll/pitch/yaw by the
KITTI devkit's Mercator projection (scale from the first frame's latitude), so the dataset's global frame is
Mercator metres east/north/up. KITTI tracking has no timestamps: frame ``n`` is at ``n * 0.1 s`` (10 Hz).
Cameras: image_02 (left colour) is ``CAM_FRONT``, image_03 (right colour, when present) ``CAM_FRONT_RIGHT_STEREO``;
their intrinsics and offsets come from P2/P3 in the rectified reference frame (R_rect). Labels are boxes in that
rectified frame (bottom centre, h w l, rotation_y about the camera's y axis) moved to the world through
R_rect, Tr_velo_cam, Tr_imu_velo and the OXTS pose. DontCare regions, truncation, occlusion, alpha and the 2D box
are kept in ``attributes.parquet``. Velodyne points (x, y, z, reflectance 0..1) go to the ego frame, reflectance
scaled to the store's 0..255.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import invert_transform, make_transform, rotmat_from_euler
from omniscs.scene.sources.common import (
    BadFrame,
    DatasetSource,
    FrameData,
    FramePlan,
    RawBox,
    check_camera,
    fingerprint,
    json_value,
    pick_scene,
    read_float32_records,
    read_image_file,
    read_text_file,
    require_file,
    select_cameras,
)
from omniscs.scene.store import CameraRecord

#: KITTI tracking frames come at 10 Hz and carry no timestamps.
FRAME_PERIOD_US = 100_000
#: Earth radius the KITTI devkit uses for the Mercator projection of OXTS positions (metres).
EARTH_RADIUS_M = 6_378_137.0
#: Values per OXTS line: lat lon alt roll pitch yaw vn ve vf vl vu ax ay az af al au wx wy wz wf wl wu
#: pos_accuracy vel_accuracy navstat numsats posmode velmode orimode.
OXTS_VALUES = 30
#: Floats per velodyne point: x, y, z, reflectance.
VELODYNE_VALUES_PER_POINT = 4
#: KITTI reflectance is 0..1; the store's intensity is nuScenes-like 0..255.
INTENSITY_SCALE = 255.0
#: Label line fields: frame track_id type truncated occluded alpha bbox(4) h w l x y z rotation_y [score].
LABEL_FIELDS = 17
DONT_CARE = "DontCare"

#: Image folders and projection matrices of the two colour cameras, and their store names.
CAMERAS: dict[str, tuple[str, str]] = {"image_02": ("CAM_FRONT", "P2"), "image_03": ("CAM_FRONT_RIGHT_STEREO", "P3")}

#: KITTI object types to the project taxonomy (Misc: unusual road objects; Tram: the nearest class is bus).
#: The project's own class names (as written by nuScenes' KITTI export and by omniscs' writer for classes KITTI
#: lacks) are accepted too.
TYPE_TO_CATEGORY: dict[str, str] = {
    "Car": "car", "Van": "car", "Truck": "truck", "Pedestrian": "pedestrian", "Person_sitting": "pedestrian",
    "Cyclist": "bicycle", "Tram": "bus", "Misc": "debris",
}
PROJECT_CLASSES = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian", "motorcycle", "bicycle",
                   "traffic_cone", "barrier", "debris")

#: Rotation from our box frame (x forward, y left, z up) to KITTI's object frame (x forward, y down, z left).
KITTI_OBJECT_FROM_BOX = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

#: How far a calibration rotation may be from orthonormal before it is refused (it is re-orthonormalised).
MAX_ROTATION_ERROR = 1e-3


def category_of(kitti_type: str) -> str | None:
    if kitti_type in TYPE_TO_CATEGORY:
        return TYPE_TO_CATEGORY[kitti_type]
    lowered = kitti_type.lower()
    return lowered if lowered in PROJECT_CLASSES else None


def rotation_about_camera_y(ry: float) -> np.ndarray:  # -> [3, 3]; maps object x (length) to (cos, 0, -sin)
    c, s = np.cos(ry), np.sin(ry)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def mercator_scale(lat0_deg: float) -> float:
    return float(np.cos(np.radians(lat0_deg)))


def oxts_to_pose(oxts: np.ndarray, scale: float) -> np.ndarray:  # [30] -> [4, 4] mercator_from_imu
    """KITTI devkit pose: Mercator position (x east, y north, z up) and R = Rz(yaw) Ry(pitch) Rx(roll)."""
    lat, lon, alt, roll, pitch, yaw = (float(v) for v in oxts[:6])
    x = scale * np.radians(lon) * EARTH_RADIUS_M
    y = scale * EARTH_RADIUS_M * np.log(np.tan(np.radians(90.0 + lat) / 2.0))
    return make_transform(rotmat_from_euler(roll, pitch, yaw), [x, y, alt])


def pose_to_oxts_geo(pose: np.ndarray, scale: float) -> tuple[float, float, float, float, float, float]:
    """Inverse of ``oxts_to_pose``: (lat, lon, alt, roll, pitch, yaw) of a Mercator-frame pose [4, 4]."""
    x, y, alt = pose[:3, 3]
    lon = np.degrees(x / (scale * EARTH_RADIUS_M))
    lat = np.degrees(2.0 * np.arctan(np.exp(y / (scale * EARTH_RADIUS_M)))) - 90.0
    R = pose[:3, :3]
    yaw = np.arctan2(R[1, 0], R[0, 0])
    pitch = np.arctan2(-R[2, 0], np.hypot(R[2, 1], R[2, 2]))
    roll = np.arctan2(R[2, 1], R[2, 2])
    return float(lat), float(lon), float(alt), float(roll), float(pitch), float(yaw)


def split_dir(root: Path, split: str | None) -> Path:
    """The folder holding image_02/, calib/, ...: ``root`` itself or ``root/<split>`` (default training)."""
    if not root.is_dir():
        raise OmniscsError(f"KITTI dataroot {root} does not exist")
    if (root / "image_02").is_dir():
        return root
    path = root / (split or "training")
    if not (path / "image_02").is_dir():
        raise OmniscsError(f"{root} is not a KITTI tracking root: no image_02/ in it or in {path}")
    return path


def list_scenes(dataroot: str | Path, version: str | None = None) -> list[str]:
    base = split_dir(Path(dataroot), version)
    return sorted(p.name for p in (base / "image_02").iterdir() if p.is_dir())


def check_scene(source: DatasetSource) -> None:
    """The sequence exists and has its calibration, poses and (outside ``testing``) labels; else one error."""
    base = split_dir(Path(source.dataroot), source.version)
    seqs = list_scenes(source.dataroot, source.version)
    if source.scene not in seqs:
        raise OmniscsError(f"{base} has no sequence {source.scene!r}; it has {seqs[:20]}")
    require_file(base / "calib" / f"{source.scene}.txt", "KITTI calibration file")
    require_file(base / "oxts" / f"{source.scene}.txt", "OXTS pose file")
    if base.name != "testing":
        require_file(base / "label_02" / f"{source.scene}.txt", "KITTI label file")


def dataset_files(source: DatasetSource) -> list[Path]:
    """The files whose change makes a stored copy of the sequence stale (calibration, poses, labels)."""
    base = split_dir(Path(source.dataroot), source.version)
    return [base / "calib" / f"{source.scene}.txt", base / "oxts" / f"{source.scene}.txt",
            base / "label_02" / f"{source.scene}.txt"]


def parse_calib(path: Path) -> dict[str, np.ndarray]:
    """``KEY[:] v1 v2 ...`` lines as float arrays (tracking spells R_rect, Tr_velo_cam, Tr_imu_velo)."""
    out = {}
    for n, line in enumerate(read_text_file(path, "KITTI calibration file").splitlines(), 1):
        if not line.strip():
            continue
        key, _, rest = line.strip().partition(" ")
        try:
            values = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise ValidationError(f"{path}: line {n} ({key}) has a value that is not a number") from None
        if not np.all(np.isfinite(values)):
            raise ValidationError(f"{path}: line {n} ({key}) has a NaN or Inf value")
        out[key.rstrip(":")] = values
    return out


def _calib_field(calib: dict, path: Path, names: tuple[str, ...], n: int) -> np.ndarray:
    for name in names:
        if name in calib:
            if calib[name].size != n:
                raise ValidationError(f"{path}: field {name} has {calib[name].size} values, expected {n}")
            return calib[name]
    raise ValidationError(f"{path}: field {names[0]} is missing")


def _rigid_from_3x4(values: np.ndarray, path: Path, name: str) -> np.ndarray:  # [12] -> [4, 4]
    T = np.eye(4)
    T[:3, :] = values.reshape(3, 4)
    T[:3, :3] = _orthonormal(T[:3, :3], path, name)
    return T


def _orthonormal(R: np.ndarray, path: Path, name: str) -> np.ndarray:
    u, _, vt = np.linalg.svd(R)
    fixed = u @ vt
    if np.linalg.det(fixed) < 0 or np.abs(fixed - R).max() > MAX_ROTATION_ERROR:
        raise ValidationError(f"{path}: field {name} is not a rotation")
    return fixed


class KittiReader:
    """Opened on one KITTI tracking sequence; see the module docstring for frames and conventions."""

    def __init__(self, source: DatasetSource):
        self.source = source
        self.root = Path(source.dataroot)
        self.base = split_dir(self.root, source.version)
        seqs = list_scenes(self.root, source.version)
        seq = pick_scene(seqs, source.scene, self.base, "sequence",
                         f"kitti:{self.root}:{seqs[0] if seqs else '0000'}")
        self.seq = seq
        self.calib_path = self.base / "calib" / f"{seq}.txt"
        self.oxts_path = require_file(self.base / "oxts" / f"{seq}.txt", "OXTS pose file")
        self.label_path = self.base / "label_02" / f"{seq}.txt"
        self.velo_dir = self.base / "velodyne" / seq
        self.has_lidar = self.velo_dir.is_dir()
        calib = parse_calib(self.calib_path)
        r_rect = np.eye(4)
        r_rect[:3, :3] = _orthonormal(_calib_field(calib, self.calib_path, ("R_rect", "R0_rect"), 9).reshape(3, 3),
                                      self.calib_path, "R_rect")
        velo_cam = _rigid_from_3x4(_calib_field(calib, self.calib_path, ("Tr_velo_cam", "Tr_velo_to_cam"), 12),
                                   self.calib_path, "Tr_velo_cam")
        self.imu_velo = _rigid_from_3x4(_calib_field(calib, self.calib_path, ("Tr_imu_velo", "Tr_imu_to_velo"), 12),
                                        self.calib_path, "Tr_imu_velo")  # velo_from_imu
        self.rect_from_ego = r_rect @ velo_cam @ self.imu_velo
        self.ego_from_rect = invert_transform(self.rect_from_ego)
        available = {folder: name for folder, (name, _) in CAMERAS.items() if (self.base / folder / seq).is_dir()}
        wanted = None
        if source.cameras is not None:
            wanted = tuple(available.get(c, CAMERAS[c][0] if c in CAMERAS else c) for c in source.cameras)
        keep = select_cameras(list(available.values()), wanted, f"KITTI sequence {seq}")
        self.oxts = self._read_oxts()
        n_frames = len(self.oxts)
        self.image_dirs = {}
        self.cameras = []
        for folder, (name, proj) in CAMERAS.items():
            if name not in keep:
                continue
            P = _calib_field(calib, self.calib_path, (proj,), 12).reshape(3, 4)
            K = P[:, :3].copy()
            if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise ValidationError(f"{self.calib_path}: field {proj} is not a rectified projection [K | K t]")
            cam_from_rect = make_transform(np.eye(3), np.linalg.solve(K, P[:, 3]))
            self.image_dirs[name] = self.base / folder / seq
            width, height = self._image_size(self.image_dirs[name], n_frames)
            self.cameras.append(check_camera(CameraRecord(name, width, height, K,
                                                          invert_transform(cam_from_rect @ self.rect_from_ego)),
                                             self.calib_path))
        scale = next((mercator_scale(o[0]) for o in self.oxts if o is not None), None)
        if scale is None:
            raise ValidationError(f"{self.oxts_path}: no readable pose line")
        self.scale = scale
        self.frames = [FramePlan(str(f), f * FRAME_PERIOD_US,
                                 oxts_to_pose(o, scale) if o is not None else np.full((4, 4), np.nan))
                       for f, o in enumerate(self.oxts)]
        self.labels, self.label_errors = self._read_labels()
        self.extra = {
            "source_scene_id": seq, "location": None, "split": self.base.name,
            "geo_origin": next([float(v) for v in o[:3]] for o in self.oxts if o is not None),
            "ego_from_lidar": invert_transform(self.imu_velo).reshape(16).tolist() if self.has_lidar else None,
            "kitti_mercator_scale": scale,
            "dataset_fingerprint": fingerprint(dataset_files(replace(source, scene=seq)), self.root),
        }

    def _read_oxts(self) -> list[np.ndarray | None]:
        rows: list[np.ndarray | None] = []
        for line in read_text_file(self.oxts_path, "OXTS pose file").splitlines():
            if not line.strip():
                continue
            try:
                values = np.array([float(v) for v in line.split()])
            except ValueError:
                values = None
            rows.append(values if values is not None and values.size == OXTS_VALUES and
                        np.all(np.isfinite(values[:6])) else None)
        if not rows:
            raise ValidationError(f"{self.oxts_path}: no pose lines")
        return rows

    def _image_size(self, folder: Path, n_frames: int) -> tuple[int, int]:
        for f in range(n_frames):
            path = folder / f"{f:06d}.png"
            if path.is_file():
                try:
                    rgb = read_image_file(path)
                except BadFrame:
                    continue
                return rgb.shape[1], rgb.shape[0]
        raise ValidationError(f"{folder}: no readable image")

    def _read_labels(self) -> tuple[dict[int, list[list[str]]], dict[int, str]]:
        labels: dict[int, list[list[str]]] = {}
        errors: dict[int, str] = {}
        if not self.label_path.is_file():
            if self.base.name == "testing":
                return labels, errors
            require_file(self.label_path, "KITTI label file")
        for n, line in enumerate(read_text_file(self.label_path, "KITTI label file").splitlines(), 1):
            fields = line.split()
            if not fields:
                continue
            try:
                frame = int(fields[0])
            except ValueError:
                raise ValidationError(f"{self.label_path}: line {n}: field frame {fields[0]!r} is not an integer") from None
            if len(fields) not in (LABEL_FIELDS, LABEL_FIELDS + 1):
                errors.setdefault(frame, f"{self.label_path}: line {n} has {len(fields)} fields, expected "
                                         f"{LABEL_FIELDS} (or {LABEL_FIELDS + 1} with a score)")
                continue
            labels.setdefault(frame, []).append(fields + [str(n)])
        return labels, errors

    def frame_files(self, i: int) -> list[tuple[Path, str, int | None]]:
        """The image and velodyne files frame ``i`` reads: (path, what, bytes per point or None)."""
        out = [(self.image_dirs[cam.name] / f"{i:06d}.png", "image file", None) for cam in self.cameras]
        if self.has_lidar:
            out.append((self.velo_dir / f"{i:06d}.bin", "LiDAR file", 4 * VELODYNE_VALUES_PER_POINT))
        return out

    def load_frame(self, i: int) -> FrameData:
        if not np.all(np.isfinite(self.frames[i].global_from_ego)):
            raise BadFrame(f"{self.oxts_path}: line {i + 1} is not {OXTS_VALUES} numbers")
        if i in self.label_errors:
            raise BadFrame(self.label_errors[i])
        images = {cam.name: read_image_file(self.image_dirs[cam.name] / f"{i:06d}.png", (cam.width, cam.height))
                  for cam in self.cameras}
        lidar = None
        if self.has_lidar:
            raw = read_float32_records(self.velo_dir / f"{i:06d}.bin", VELODYNE_VALUES_PER_POINT)
            ego_from_velo = invert_transform(self.imu_velo)
            xyz = raw[:, :3].astype(np.float64) @ ego_from_velo[:3, :3].T + ego_from_velo[:3, 3]
            lidar = np.concatenate([xyz, raw[:, 3:4] * INTENSITY_SCALE], axis=1).astype(np.float32)
        global_from_rect = self.frames[i].global_from_ego @ self.ego_from_rect
        boxes, attrs = [], []
        for fields in self.labels.get(i, []):
            box, extra = self._label(fields, global_from_rect)
            if box is not None:
                boxes.append(box)
            attrs += extra
        return FrameData(images=images, lidar=lidar, boxes=boxes, attributes=attrs)

    def _label(self, fields: list[str], global_from_rect: np.ndarray) -> tuple[RawBox | None, list[dict]]:
        line = fields[-1]
        where = f"{self.label_path}: line {line}"
        try:
            track, kitti_type = int(fields[1]), fields[2]
            truncated, occluded, alpha = float(fields[3]), int(float(fields[4])), float(fields[5])
            bbox = [float(v) for v in fields[6:10]]
            h, w, l, x, y, z, ry = (float(v) for v in fields[10:17])
            score = float(fields[17]) if len(fields) == LABEL_FIELDS + 2 else None
        except ValueError:
            raise BadFrame(f"{where}: a field is not a number") from None
        cam = self.cameras[0].name if self.cameras else None
        if kitti_type == DONT_CARE:
            return None, [{"track_id": -1, "camera": cam, "name": "dont_care_bbox", "value": json_value(bbox)}]
        if not all(np.isfinite(v) and v > 0 for v in (h, w, l)):
            raise BadFrame(f"{where}: track {track} ({kitti_type}) has zero or negative dimensions h={h} w={w} l={l}")
        R = rotation_about_camera_y(ry) @ KITTI_OBJECT_FROM_BOX
        rect_from_box = make_transform(R, [x, y - 0.5 * h, z])  # bottom centre -> centre (camera y points down)
        attrs = {"truncated": repr(truncated), "occluded": str(occluded), "alpha": repr(alpha),
                 "bbox_2d": json_value(bbox)}
        if score is not None:
            attrs["score"] = repr(score)
        box = RawBox(track_key=str(track), category=category_of(kitti_type), source_category=kitti_type,
                     global_from_box=global_from_rect @ rect_from_box, size=np.array([l, w, h]),
                     track_id=track, attributes=attrs)
        return box, []
