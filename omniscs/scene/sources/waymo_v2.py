"""Waymo Open Dataset v2 reader: one segment's Parquet component tables into the scene store (pyarrow, no TensorFlow).

Layout: ``<dataroot>/<component>/<segment_context_name>.parquet`` (dataroot is a split folder such as
``training/``). Components and the columns read (names as the v2 schema flattens them):

* ``vehicle_pose`` (required; one row per frame, defines the frames): ``key.segment_context_name``,
  ``key.frame_timestamp_micros``, ``[VehiclePoseComponent].world_from_vehicle.transform`` (16 float64, row-major).
* ``camera_calibration`` (required): ``key.camera_name`` (1 FRONT .. 5 SIDE_RIGHT),
  ``[CameraCalibrationComponent].intrinsic.{f_u,f_v,c_u,c_v,k1,k2,p1,p2,k3}``, ``.extrinsic.transform``
  (vehicle_from_camera, camera axes x forward, y left, z up; converted to OpenCV), ``.width``, ``.height``.
* ``camera_image`` (required): ``key.frame_timestamp_micros``, ``key.camera_name``, ``[CameraImageComponent].image``
  (JPEG). Images with lens distortion are undistorted to the calibration's pinhole K.
* ``lidar_box`` (optional; without it the scene has no boxes): ``key.laser_object_id``,
  ``[LiDARBoxComponent].box.center.{x,y,z}``, ``.box.size.{x,y,z}`` (length, width, height), ``.box.heading``,
  ``.type``, ``.num_lidar_points_in_box``; when present ``.speed.{x,y,z}`` and ``.difficulty_level.detection``
  go to ``attributes.parquet``. Boxes are in the vehicle frame of their frame.
* ``camera_box`` (optional, to ``attributes.parquet``): ``key.camera_object_id``,
  ``[CameraBoxComponent].box.center.{x,y}``, ``.box.size.{x,y}``, ``.type``.
* ``lidar`` + ``lidar_calibration`` (optional): ``key.laser_name``, ``[LiDARComponent].range_image_return1/2.values``
  and ``.shape`` ([H, W, 4]: range, intensity, elongation, no-label-zone), ``[LiDARCalibrationComponent].extrinsic
  .transform`` and ``.beam_inclination.{min,max,values}``. Range images become points as the Waymo devkit does
  (column azimuth from +pi down, corrected by the extrinsic's yaw; rows from the highest inclination).
  ``lidar_pose`` (per-pixel vehicle poses of the TOP LiDAR), when present, compensates ego motion within a sweep.
* ``stats`` (optional): ``[StatsComponent].location``, ``.time_of_day``, ``.weather`` go to the manifest.

Not read: ``camera_segmentation``, ``lidar_segmentation``, ``lidar_camera_projection``, ``projected_lidar_box``,
``lidar_camera_synced_box``, ``camera_to_lidar_box_association``, keypoints, hkp and object assets.
Types map TYPE_VEHICLE -> car, TYPE_PEDESTRIAN -> pedestrian, TYPE_CYCLIST -> bicycle; TYPE_SIGN and
TYPE_UNKNOWN have no project class and are left out (counted in the manifest).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import CAMERA_FROM_FORWARD_RIG, invert_transform, make_transform, rotmat_from_euler
from omniscs.scene.sources.common import (
    BadFrame,
    DatasetSource,
    FrameData,
    FramePlan,
    RawBox,
    check_camera,
    decode_image_bytes,
    fingerprint,
    json_value,
    pick_scene,
    select_cameras,
)
from omniscs.scene.store import CameraRecord

SEGMENT = "key.segment_context_name"
TIMESTAMP = "key.frame_timestamp_micros"
CAMERA_NAME = "key.camera_name"
LASER_NAME = "key.laser_name"
LASER_OBJECT_ID = "key.laser_object_id"
CAMERA_OBJECT_ID = "key.camera_object_id"
POSE = "[VehiclePoseComponent].world_from_vehicle.transform"
CALIB = "[CameraCalibrationComponent]"
IMAGE = "[CameraImageComponent]"
LIDAR_BOX = "[LiDARBoxComponent]"
CAMERA_BOX = "[CameraBoxComponent]"
LIDAR = "[LiDARComponent]"
LIDAR_CALIB = "[LiDARCalibrationComponent]"
LIDAR_POSE = "[LiDARPoseComponent]"
STATS = "[StatsComponent]"

#: Waymo CameraName enum -> store camera name.
CAMERAS: dict[int, str] = {1: "CAM_FRONT", 2: "CAM_FRONT_LEFT", 3: "CAM_FRONT_RIGHT", 4: "CAM_SIDE_LEFT",
                           5: "CAM_SIDE_RIGHT"}
#: Waymo LaserName enum.
LASERS: dict[int, str] = {1: "TOP", 2: "FRONT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT", 5: "REAR"}
TOP_LASER = 1
#: Waymo BoxType enum -> (name, project class or None).
BOX_TYPES: dict[int, tuple[str, str | None]] = {
    0: ("TYPE_UNKNOWN", None), 1: ("TYPE_VEHICLE", "car"), 2: ("TYPE_PEDESTRIAN", "pedestrian"),
    3: ("TYPE_SIGN", None), 4: ("TYPE_CYCLIST", "bicycle"),
}
DISTORTION = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
#: Waymo LiDAR intensity is about 0..1; the store's is nuScenes-like 0..255.
INTENSITY_SCALE = 255.0
RANGE_IMAGE_CHANNELS = 4

#: OpenCV camera axes (x right, y down, z forward) expressed in Waymo's camera axes (x forward, y left, z up).
WAYMO_CAMERA_FROM_OPENCV = invert_transform(CAMERA_FROM_FORWARD_RIG)

REQUIRED = ("vehicle_pose", "camera_calibration", "camera_image")


def component_path(root: Path, component: str, segment: str) -> Path:
    return root / component / f"{segment}.parquet"


#: Every component the reader may read (their files define whether a stored copy is stale).
COMPONENTS = ("vehicle_pose", "camera_calibration", "camera_image", "lidar_box", "camera_box", "lidar",
              "lidar_calibration", "lidar_pose", "stats")


def dataset_files(source: DatasetSource) -> list[Path]:
    return [component_path(Path(source.dataroot), c, source.scene) for c in COMPONENTS]


def list_scenes(dataroot: str | Path, version: str | None = None) -> list[str]:
    root = Path(dataroot)
    if not root.is_dir():
        raise OmniscsError(f"Waymo v2 dataroot {root} does not exist")
    folder = root / "vehicle_pose"
    if not folder.is_dir():
        raise OmniscsError(f"{root} is not a Waymo v2 split folder: it has no vehicle_pose/ component folder")
    return sorted(p.stem for p in folder.glob("*.parquet"))


def expected_kind(column: str) -> str:
    """What the v2 schema stores in a column this reader reads: string, integer, number, binary or a list."""
    if column in (SEGMENT, LASER_OBJECT_ID, CAMERA_OBJECT_ID) or column.startswith(STATS):
        return "string"
    if column in (TIMESTAMP, CAMERA_NAME, LASER_NAME) or column.endswith(
            (".type", ".width", ".height", ".num_lidar_points_in_box", ".difficulty_level.detection")):
        return "integer"
    if column.endswith(".image"):
        return "binary"
    if column.endswith(".shape"):
        return "list of integers"
    if column.endswith((".transform", ".values")):
        return "list of numbers"
    return "number"


def _has_kind(t: pa.DataType, kind: str) -> bool:
    if pa.types.is_dictionary(t):
        t = t.value_type
    if kind == "string":
        return pa.types.is_string(t) or pa.types.is_large_string(t)
    if kind == "integer":
        return pa.types.is_integer(t)
    if kind == "number":
        return pa.types.is_integer(t) or pa.types.is_floating(t)
    if kind == "binary":
        return pa.types.is_binary(t) or pa.types.is_large_binary(t)
    if pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t):
        return _has_kind(t.value_type, "integer" if kind == "list of integers" else "number")
    return False


def check_component_schema(path: Path, schema: pa.Schema, columns: list[str], optional: tuple[str, ...] = ()) -> None:
    """Required ``columns`` exist, and every column read has the v2 schema's kind; else one ValidationError."""
    missing = [c for c in columns if c not in schema.names]
    if missing:
        raise ValidationError(f"{path}: missing column(s) {missing}")
    for name in [*columns, *(c for c in optional if c in schema.names)]:
        t = schema.field(name).type
        if not _has_kind(t, expected_kind(name)):
            raise ValidationError(f"{path}: column {name} has type {t}, expected {expected_kind(name)} "
                                  "(Waymo Open Dataset v2 schema)")


def read_component(root: Path, component: str, segment: str, columns: list[str], optional: tuple[str, ...] = (),
                   filters=None) -> pa.Table:
    """Columns of one component of a segment; a missing file or column, a column of the wrong type or a null in a
    required column is a ValidationError naming it. ``optional`` columns are read when present.
    """
    path = component_path(root, component, segment)
    if not path.is_file():
        raise ValidationError(f"{path}: Waymo v2 component {component!r} is missing")
    try:
        schema = pq.read_schema(path)
        check_component_schema(path, schema, columns, optional)
        table = pq.read_table(path, columns=columns + [c for c in optional if c in schema.names], filters=filters)
    except (pa.ArrowException, OSError) as exc:
        raise ValidationError(f"{path}: unreadable Parquet ({str(exc).strip().splitlines()[0][:200]})") from None
    for name in columns:
        if table.column(name).null_count:
            raise ValidationError(f"{path}: column {name} has {table.column(name).null_count} null value(s)")
    if SEGMENT in table.column_names:
        seg = table.column(SEGMENT).to_numpy(zero_copy_only=False)
        if len(seg) and np.any(seg != segment):
            table = table.filter(pa.array(seg == segment))
    return table


#: Columns each component must have, and optional ones read when present (checked when a source is resolved).
def _schema_plan() -> dict[str, tuple[list[str], tuple[str, ...]]]:
    lb, cb = LIDAR_BOX, CAMERA_BOX
    return {
        "vehicle_pose": ([SEGMENT, TIMESTAMP, POSE], ()),
        "camera_calibration": ([SEGMENT, CAMERA_NAME, *(f"{CALIB}.intrinsic.{k}" for k in ("f_u", "f_v", "c_u", "c_v")),
                                f"{CALIB}.extrinsic.transform", f"{CALIB}.width", f"{CALIB}.height"],
                               tuple(f"{CALIB}.intrinsic.{k}" for k in DISTORTION)),
        "camera_image": ([SEGMENT, TIMESTAMP, CAMERA_NAME, f"{IMAGE}.image"], ()),
        "lidar_box": ([SEGMENT, TIMESTAMP, LASER_OBJECT_ID, *(f"{lb}.box.center.{a}" for a in "xyz"),
                       *(f"{lb}.box.size.{a}" for a in "xyz"), f"{lb}.box.heading", f"{lb}.type"],
                      (f"{lb}.num_lidar_points_in_box", *(f"{lb}.speed.{a}" for a in "xyz"),
                       f"{lb}.difficulty_level.detection")),
        "camera_box": ([SEGMENT, TIMESTAMP, CAMERA_NAME, CAMERA_OBJECT_ID, f"{cb}.box.center.x", f"{cb}.box.center.y",
                        f"{cb}.box.size.x", f"{cb}.box.size.y", f"{cb}.type"], ()),
        "lidar": ([SEGMENT, TIMESTAMP, LASER_NAME, f"{LIDAR}.range_image_return1.values",
                   f"{LIDAR}.range_image_return1.shape"],
                  (f"{LIDAR}.range_image_return2.values", f"{LIDAR}.range_image_return2.shape")),
        "lidar_calibration": ([SEGMENT, LASER_NAME, f"{LIDAR_CALIB}.extrinsic.transform",
                               f"{LIDAR_CALIB}.beam_inclination.min", f"{LIDAR_CALIB}.beam_inclination.max"],
                              (f"{LIDAR_CALIB}.beam_inclination.values",)),
        "lidar_pose": ([SEGMENT, TIMESTAMP, LASER_NAME, f"{LIDAR_POSE}.range_image_return1.values",
                        f"{LIDAR_POSE}.range_image_return1.shape"], ()),
        "stats": ([SEGMENT], (f"{STATS}.location", f"{STATS}.time_of_day", f"{STATS}.weather")),
    }


def check_scene(source: DatasetSource) -> None:
    """The segment exists, has the required components, and every component present has the v2 schema (only the
    Parquet footers are read); else one error naming the file and column."""
    root = Path(source.dataroot)
    segments = list_scenes(root)
    if source.scene not in segments:
        raise OmniscsError(f"{root} has no segment {source.scene!r}; it has {segments[:20]}")
    for component, (columns, optional) in _schema_plan().items():
        path = component_path(root, component, source.scene)
        if not path.is_file():
            if component in REQUIRED:
                raise ValidationError(f"{path}: Waymo v2 component {component!r} is missing")
            continue
        try:
            schema = pq.read_schema(path)
        except (pa.ArrowException, OSError) as exc:
            raise ValidationError(f"{path}: unreadable Parquet ({str(exc).strip().splitlines()[0][:200]})") from None
        check_component_schema(path, schema, columns, optional)
    if component_path(root, "lidar", source.scene).is_file() and \
            not component_path(root, "lidar_calibration", source.scene).is_file():
        raise ValidationError(f"{component_path(root, 'lidar_calibration', source.scene)}: Waymo v2 component "
                              "'lidar_calibration' is missing (the segment has range images)")


def _matrix(values, where: str) -> np.ndarray:  # 16 values -> [4, 4]
    m = np.asarray(values, dtype=np.float64)
    if m.size != 16 or not np.all(np.isfinite(m)):
        raise ValidationError(f"{where}: transform is not 16 finite numbers")
    return m.reshape(4, 4)


def inclinations(calib: dict, height: int) -> np.ndarray:  # -> [H] ascending radians
    values = calib.get("values")
    if values is not None and len(values) == height:
        return np.asarray(values, dtype=np.float64)
    lo, hi = float(calib["min"]), float(calib["max"])
    return lo + (0.5 + np.arange(height)) / height * (hi - lo)


def column_azimuths(width: int, vehicle_from_lidar: np.ndarray) -> np.ndarray:  # -> [W] sensor-frame azimuth
    """Waymo's column azimuths: from +pi down to -pi in the vehicle frame, expressed in the sensor frame."""
    az_correction = np.arctan2(vehicle_from_lidar[1, 0], vehicle_from_lidar[0, 0])
    ratios = (np.arange(width, 0, -1) - 0.5) / width
    return (ratios * 2.0 - 1.0) * np.pi - az_correction


def range_image_to_points(range_image: np.ndarray, vehicle_from_lidar: np.ndarray, inclination: np.ndarray,
                          pixel_pose: np.ndarray | None = None, world_from_vehicle: np.ndarray | None = None
                          ) -> np.ndarray:
    """range_image [H, W, 4], extrinsic [4, 4], inclination [H] ascending -> float32 [N, 4] vehicle x, y, z, intensity.

    ``pixel_pose`` [H, W, 6] (roll, pitch, yaw, x, y, z of world_from_vehicle per pixel) moves each point through
    the vehicle pose at its own firing time back to the frame's ``world_from_vehicle``.
    """
    H, W = range_image.shape[:2]
    incl = inclination[::-1]  # row 0 is the highest beam
    az = column_azimuths(W, vehicle_from_lidar)
    rng = range_image[..., 0].astype(np.float64)
    rows, cols = np.nonzero(rng > 0)
    r = rng[rows, cols]
    ci, si = np.cos(incl[rows]), np.sin(incl[rows])
    p = np.stack([np.cos(az[cols]) * ci * r, np.sin(az[cols]) * ci * r, si * r], -1)
    p = p @ vehicle_from_lidar[:3, :3].T + vehicle_from_lidar[:3, 3]
    if pixel_pose is not None and world_from_vehicle is not None:
        pp = pixel_pose[rows, cols].astype(np.float64)
        if np.any(pp != 0):
            R = _euler_zyx(pp[:, 0], pp[:, 1], pp[:, 2])
            world = np.einsum("nij,nj->ni", R, p) + pp[:, 3:6]
            vehicle_from_world = invert_transform(world_from_vehicle)
            p = world @ vehicle_from_world[:3, :3].T + vehicle_from_world[:3, 3]
    intensity = range_image[rows, cols, 1].astype(np.float64) * INTENSITY_SCALE
    return np.concatenate([p, intensity[:, None]], axis=1).astype(np.float32)


def _euler_zyx(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:  # [N] x3 -> [N, 3, 3]
    """R = Rz(yaw) Ry(pitch) Rx(roll), vectorised."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


class WaymoV2Reader:
    """Opened on one Waymo v2 segment; see the module docstring for components and conventions."""

    def __init__(self, source: DatasetSource):
        self.source = source
        self.root = Path(source.dataroot)
        segments = list_scenes(self.root)
        segment = pick_scene(segments, source.scene, self.root, "segment",
                             f"waymo-v2:{self.root}:{segments[0] if segments else 'SEGMENT'}")
        self.segment = segment
        poses = read_component(self.root, "vehicle_pose", segment, [SEGMENT, TIMESTAMP, POSE])
        where = str(component_path(self.root, "vehicle_pose", segment))
        ts = poses.column(TIMESTAMP).to_numpy()
        order = np.argsort(ts, kind="stable")
        pose_values = poses.column(POSE).to_pylist()
        self.frames = [FramePlan(str(int(ts[i])), int(ts[i]), _matrix(pose_values[i], f"{where}: frame {ts[i]}"))
                       for i in order]
        if len(set(ts.tolist())) != len(ts):
            raise ValidationError(f"{where}: field {TIMESTAMP} has duplicate frames")
        self._pose_by_ts = {p.timestamp_us: p.global_from_ego for p in self.frames}
        self.cameras, self.distortion = self._cameras()
        self._camera_by_enum = {enum: name for enum, name in CAMERAS.items() if name in {c.name for c in self.cameras}}
        self._calibrated = set(self._calib_enums)
        self._boxes = self._read_boxes()
        self._camera_boxes = self._read_camera_boxes()
        self._lidar_calib = self._read_lidar_calibration()
        self.has_lidar = self._lidar_calib is not None
        self.extra = {
            "source_scene_id": segment, "location": None,
            "ego_from_lidar": (self._lidar_calib[TOP_LASER]["extrinsic"].reshape(16).tolist()
                               if self.has_lidar and TOP_LASER in self._lidar_calib else None),
            "distortion": self.distortion,
            "dataset_fingerprint": fingerprint(dataset_files(replace(source, scene=segment)), self.root),
        }
        self.extra.update(self._stats())

    # ------------------------------------------------------------------ segment-level tables
    def _cameras(self) -> tuple[list[CameraRecord], dict[str, list[float]]]:
        intr = [f"{CALIB}.intrinsic.{k}" for k in ("f_u", "f_v", "c_u", "c_v")]
        dist = [f"{CALIB}.intrinsic.{k}" for k in DISTORTION]
        cols = [SEGMENT, CAMERA_NAME, *intr, f"{CALIB}.extrinsic.transform", f"{CALIB}.width", f"{CALIB}.height"]
        table = read_component(self.root, "camera_calibration", self.segment, cols, optional=tuple(dist)).to_pydict()
        where = component_path(self.root, "camera_calibration", self.segment)
        records: dict[str, CameraRecord] = {}
        distortion: dict[str, list[float]] = {}
        self._calib_enums = []
        for i, enum in enumerate(table[CAMERA_NAME]):
            if int(enum) not in CAMERAS:
                raise ValidationError(f"{where}: field {CAMERA_NAME} has unknown camera {enum} "
                                      f"(Waymo cameras are {sorted(CAMERAS)})")
            name = CAMERAS[int(enum)]
            self._calib_enums.append(int(enum))
            fu, fv, cu, cv = (float(table[c][i]) for c in intr)
            K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
            vehicle_from_cam = _matrix(table[f"{CALIB}.extrinsic.transform"][i], f"{where}: camera {name} extrinsic")
            coeffs = [float(table[c][i] or 0.0) if c in table else 0.0 for c in dist]
            if any(coeffs):
                distortion[name] = coeffs
            if name in records:
                raise ValidationError(f"{where}: camera {name} is calibrated twice")
            records[name] = check_camera(CameraRecord(name, int(table[f"{CALIB}.width"][i]),
                                                      int(table[f"{CALIB}.height"][i]), K,
                                                      vehicle_from_cam @ WAYMO_CAMERA_FROM_OPENCV), where)
        order = [CAMERAS[e] for e in sorted(set(self._calib_enums))]
        keep = select_cameras(order, self.source.cameras, f"Waymo segment {self.segment}")
        return [records[n] for n in keep], {n: c for n, c in distortion.items() if n in keep}

    def _read_boxes(self) -> dict[int, list[dict]]:
        if not component_path(self.root, "lidar_box", self.segment).is_file():
            return {}
        cols = [TIMESTAMP, LASER_OBJECT_ID, *(f"{LIDAR_BOX}.box.center.{a}" for a in "xyz"),
                *(f"{LIDAR_BOX}.box.size.{a}" for a in "xyz"), f"{LIDAR_BOX}.box.heading", f"{LIDAR_BOX}.type"]
        optional = (f"{LIDAR_BOX}.num_lidar_points_in_box", *(f"{LIDAR_BOX}.speed.{a}" for a in "xyz"),
                    f"{LIDAR_BOX}.difficulty_level.detection")
        rows = read_component(self.root, "lidar_box", self.segment, [SEGMENT] + cols, optional).to_pylist()
        by_ts: dict[int, list[dict]] = {}
        for row in rows:
            by_ts.setdefault(int(row[TIMESTAMP]), []).append(row)
        return by_ts

    def _read_camera_boxes(self) -> dict[int, list[dict]]:
        if not component_path(self.root, "camera_box", self.segment).is_file():
            return {}
        cols = [SEGMENT, TIMESTAMP, CAMERA_NAME, CAMERA_OBJECT_ID, f"{CAMERA_BOX}.box.center.x",
                f"{CAMERA_BOX}.box.center.y", f"{CAMERA_BOX}.box.size.x", f"{CAMERA_BOX}.box.size.y", f"{CAMERA_BOX}.type"]
        by_ts: dict[int, list[dict]] = {}
        for row in read_component(self.root, "camera_box", self.segment, cols).to_pylist():
            by_ts.setdefault(int(row[TIMESTAMP]), []).append(row)
        return by_ts

    def _read_lidar_calibration(self) -> dict[int, dict] | None:
        if not component_path(self.root, "lidar", self.segment).is_file():
            return None
        cols = [SEGMENT, LASER_NAME, f"{LIDAR_CALIB}.extrinsic.transform", f"{LIDAR_CALIB}.beam_inclination.min",
                f"{LIDAR_CALIB}.beam_inclination.max"]
        table = read_component(self.root, "lidar_calibration", self.segment, cols,
                               optional=(f"{LIDAR_CALIB}.beam_inclination.values",)).to_pylist()
        where = component_path(self.root, "lidar_calibration", self.segment)
        return {int(r[LASER_NAME]): {
            "extrinsic": _matrix(r[f"{LIDAR_CALIB}.extrinsic.transform"], f"{where}: laser {r[LASER_NAME]}"),
            "min": r[f"{LIDAR_CALIB}.beam_inclination.min"], "max": r[f"{LIDAR_CALIB}.beam_inclination.max"],
            "values": r.get(f"{LIDAR_CALIB}.beam_inclination.values")} for r in table}

    def _stats(self) -> dict:
        if not component_path(self.root, "stats", self.segment).is_file():
            return {}
        cols = [f"{STATS}.location", f"{STATS}.time_of_day", f"{STATS}.weather"]
        rows = read_component(self.root, "stats", self.segment, [SEGMENT], optional=tuple(cols)).to_pylist()
        if not rows:
            return {}
        return {"location": rows[0].get(f"{STATS}.location"), "time_of_day": rows[0].get(f"{STATS}.time_of_day"),
                "weather": rows[0].get(f"{STATS}.weather")}

    # ------------------------------------------------------------------ frames
    def load_frame(self, i: int) -> FrameData:
        plan = self.frames[i]
        t = plan.timestamp_us
        images = self._images(t)
        lidar = self._lidar(t, plan.global_from_ego) if self.has_lidar else None
        boxes = [self._box(row, plan.global_from_ego, t) for row in self._boxes.get(t, [])]
        attrs = []
        for row in self._camera_boxes.get(t, []):
            cam = CAMERAS.get(int(row[CAMERA_NAME]))
            if cam not in self._camera_by_enum.values():
                continue
            attrs.append({"track_id": -1, "camera": cam, "name": "camera_box", "value": json_value({
                "object_id": row[CAMERA_OBJECT_ID],
                "center": [row[f"{CAMERA_BOX}.box.center.x"], row[f"{CAMERA_BOX}.box.center.y"]],
                "size": [row[f"{CAMERA_BOX}.box.size.x"], row[f"{CAMERA_BOX}.box.size.y"]],
                "type": BOX_TYPES.get(int(row[f"{CAMERA_BOX}.type"]), ("TYPE_UNKNOWN", None))[0]})})
        return FrameData(images=images, lidar=lidar, boxes=boxes, attributes=attrs)

    def _images(self, t: int) -> dict[str, np.ndarray]:
        import cv2

        path = component_path(self.root, "camera_image", self.segment)
        table = read_component(self.root, "camera_image", self.segment, [SEGMENT, TIMESTAMP, CAMERA_NAME, f"{IMAGE}.image"],
                               filters=[(TIMESTAMP, "=", t)])
        images = {}
        for enum, data in zip(table.column(CAMERA_NAME).to_pylist(), table.column(f"{IMAGE}.image").to_pylist()):
            if int(enum) not in self._calibrated:
                raise BadFrame(f"{path}: frame {t}: image of camera {enum} which camera_calibration does not list")
            name = CAMERAS[int(enum)]
            if name not in self._camera_by_enum.values():
                continue
            cam = next(c for c in self.cameras if c.name == name)
            rgb = decode_image_bytes(data, f"{path}: frame {t} camera {name}", (cam.width, cam.height))
            if name in self.distortion:
                rgb = cv2.undistort(rgb, cam.K, np.asarray(self.distortion[name]))
            images[name] = rgb
        missing = [c.name for c in self.cameras if c.name not in images]
        if missing:
            raise BadFrame(f"{path}: frame {t} has no image for camera(s) {missing}")
        return images

    def _lidar(self, t: int, world_from_vehicle: np.ndarray) -> np.ndarray:
        path = component_path(self.root, "lidar", self.segment)
        cols = [SEGMENT, TIMESTAMP, LASER_NAME]
        returns = [f"{LIDAR}.range_image_return{k}" for k in (1, 2)]
        table = read_component(self.root, "lidar", self.segment, cols + [f"{returns[0]}.values", f"{returns[0]}.shape"],
                               optional=(f"{returns[1]}.values", f"{returns[1]}.shape"), filters=[(TIMESTAMP, "=", t)])
        if table.num_rows == 0:
            raise BadFrame(f"{path}: frame {t} has no range image")
        pixel_poses = self._pixel_poses(t)
        parts = []
        for row in table.to_pylist():
            laser = int(row[LASER_NAME])
            if laser not in self._lidar_calib:
                raise BadFrame(f"{path}: frame {t}: laser {laser} has no lidar_calibration row")
            calib = self._lidar_calib[laser]
            for ret in returns:
                values, shape = row.get(f"{ret}.values"), row.get(f"{ret}.shape")
                if values is None or shape is None:
                    continue
                shape = [int(s) for s in shape]
                if len(shape) != 3 or shape[2] != RANGE_IMAGE_CHANNELS or len(values) != int(np.prod(shape)):
                    raise BadFrame(f"{path}: frame {t} laser {LASERS.get(laser, laser)}: {ret} has "
                                   f"{len(values)} values for shape {shape}")
                ri = np.asarray(values, dtype=np.float32).reshape(shape)
                # the second return has the first's per-pixel poses (Waymo stores them once)
                parts.append(range_image_to_points(ri, calib["extrinsic"], inclinations(calib, shape[0]),
                                                   pixel_poses.get(laser), world_from_vehicle))
        return np.concatenate(parts) if parts else np.zeros((0, 4), np.float32)

    def _pixel_poses(self, t: int) -> dict[int, np.ndarray]:
        if not component_path(self.root, "lidar_pose", self.segment).is_file():
            return {}
        cols = [SEGMENT, TIMESTAMP, LASER_NAME, f"{LIDAR_POSE}.range_image_return1.values",
                f"{LIDAR_POSE}.range_image_return1.shape"]
        out = {}
        for row in read_component(self.root, "lidar_pose", self.segment, cols, filters=[(TIMESTAMP, "=", t)]).to_pylist():
            shape = [int(s) for s in row[cols[4]]]
            out[int(row[LASER_NAME])] = np.asarray(row[cols[3]], dtype=np.float64).reshape(shape)
        return out

    def _box(self, row: dict, world_from_vehicle: np.ndarray, t: int) -> RawBox:
        where = f"{component_path(self.root, 'lidar_box', self.segment)}: frame {t} object {row[LASER_OBJECT_ID]}"
        size = np.array([row[f"{LIDAR_BOX}.box.size.{a}"] for a in "xyz"], dtype=np.float64)
        if not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise BadFrame(f"{where}: field {LIDAR_BOX}.box.size {size.tolist()} must be positive")
        centre = [row[f"{LIDAR_BOX}.box.center.{a}"] for a in "xyz"]
        heading = float(row[f"{LIDAR_BOX}.box.heading"])
        type_name, category = BOX_TYPES.get(int(row[f"{LIDAR_BOX}.type"]), (f"TYPE_{row[f'{LIDAR_BOX}.type']}", None))
        attrs = {"laser_object_id": str(row[LASER_OBJECT_ID])}
        speed = [row.get(f"{LIDAR_BOX}.speed.{a}") for a in "xyz"]
        if all(v is not None for v in speed):
            attrs["speed"] = json_value(speed)
        if row.get(f"{LIDAR_BOX}.difficulty_level.detection") is not None:
            attrs["difficulty_level"] = str(row[f"{LIDAR_BOX}.difficulty_level.detection"])
        n_points = row.get(f"{LIDAR_BOX}.num_lidar_points_in_box")
        return RawBox(track_key=str(row[LASER_OBJECT_ID]), category=category, source_category=type_name,
                      global_from_box=world_from_vehicle @ make_transform(rotmat_from_euler(yaw=heading), centre),
                      size=size, num_lidar_points=-1 if n_points is None else int(n_points), attributes=attrs)
