"""What every dataset reader shares: the source description, frame plans, skipping bad frames, re-origin,
box conversion, the attribute side table and writing the result through the scene store's validation.

Frame convention for recorded logs: the store's world frame is the dataset's global frame re-origined at the
first kept ego pose, turned by that pose's yaw only (so world z stays the dataset's up). The transform back,
``global_from_world`` (16 floats, row-major), is kept in the manifest so writers can restore global coordinates.

Side table ``attributes.parquet`` (one row per fact; the box schema of the store is fixed, so facts a format
keeps beside its boxes live here): ``frame_idx`` int32, ``track_id`` int64 (-1 for frame-level regions such as
KITTI DontCare), ``camera`` string (null unless the fact belongs to one image), ``name`` string, ``value`` string
(plain text or JSON). Names used by the readers: ``instance_token``, ``annotation_token``, ``attribute``,
``visibility`` (nuScenes); ``truncated``, ``occluded``, ``alpha``, ``bbox_2d``, ``dont_care_bbox`` (KITTI);
``laser_object_id``, ``speed``, ``difficulty_level``, ``camera_box`` (Waymo v2).
"""
from __future__ import annotations

import json
import os
import re
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Protocol

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import invert_transform, is_rigid, make_transform, rotmat_from_euler, yaw_from_matrix
from omniscs.ids import is_safe_id
from omniscs.quaternions import quat_to_rotmat, rotmat_to_quat, slerp
from omniscs.scene.store import CameraRecord, Scene
from omniscs.scene.writer import SceneWriter
from omniscs.storage import content_hash

#: Dataset formats a ``DatasetSource`` can name (also the ``kind`` in its dict form).
FORMATS: tuple[str, ...] = ("nuscenes", "kitti", "waymo-v2")

ATTRIBUTES = "attributes.parquet"
ATTRIBUTE_SCHEMA = pa.schema([
    ("frame_idx", pa.int32()),
    ("track_id", pa.int64()),
    ("camera", pa.string()),
    ("name", pa.string()),
    ("value", pa.string()),
])

#: How many skipped frames a warning or error message lists by name.
REASONS_SHOWN = 3

_UNSAFE_ID_CHARS = re.compile(r"[^A-Za-z0-9._-]+")


class SkippedFramesWarning(UserWarning):
    """Some frames of a log were unreadable and were left out (the user asked to skip bad frames)."""


class BadFrame(Exception):
    """One frame of a log cannot be read; the message names the file and field at fault."""


@dataclass(frozen=True)
class DatasetSource:
    """A scene of a recorded dataset on disk: which format, where, which scene, and how to read it."""

    format: str
    """One of FORMATS: ``nuscenes``, ``kitti`` or ``waymo-v2``."""
    dataroot: str
    """nuScenes: the folder holding ``v1.0-*/`` and ``samples/``; KITTI tracking: the folder holding ``training/``
    (or the split folder itself); Waymo v2: the split folder holding one sub-folder per component."""
    scene: str | None = None
    """nuScenes scene name (``scene-0061``) or token; KITTI sequence (``0003``); Waymo segment context name.
    None: the dataroot must hold exactly one scene."""
    version: str | None = None
    """nuScenes table version (``v1.0-mini``; None: the only ``v1.0-*`` folder); KITTI split (None: training)."""
    cameras: tuple[str, ...] | None = None
    """Store camera names to keep (e.g. ``CAM_FRONT``); None keeps every camera the log has."""
    sweeps: bool = False
    """nuScenes: every LIDAR_TOP sweep between the first and last keyframe (annotations interpolated) instead
    of the 2 Hz keyframes only."""
    skip_bad_frames: bool = False
    """Leave unreadable frames out with a warning and a count, instead of failing on the first one."""

    def __post_init__(self):
        if self.format not in FORMATS:
            raise OmniscsError(f"unknown dataset format {self.format!r}; use one of {list(FORMATS)}")
        if isinstance(self.dataroot, os.PathLike):
            object.__setattr__(self, "dataroot", os.fspath(self.dataroot))
        if not isinstance(self.dataroot, str) or not self.dataroot:
            raise OmniscsError(f"{self.format} source: dataroot must be a folder path; got {self.dataroot!r}")
        for name in ("scene", "version"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, str) or not value):
                raise OmniscsError(f"{self.format} source: {name} must be a non-empty string or null; got {value!r}")
        if self.cameras is not None:
            if isinstance(self.cameras, str) or not isinstance(self.cameras, (list, tuple)) or not all(
                    isinstance(c, str) and c for c in self.cameras):
                raise OmniscsError(f"{self.format} source: cameras must be a list of camera names or null; "
                                   f"got {self.cameras!r}")
            object.__setattr__(self, "cameras", tuple(self.cameras))
        for name in ("sweeps", "skip_bad_frames"):
            if not isinstance(getattr(self, name), bool):
                raise OmniscsError(f"{self.format} source: {name} must be true or false; got {getattr(self, name)!r}")

    def to_dict(self) -> dict:
        d = asdict(self)
        fmt = d.pop("format")
        d["cameras"] = list(self.cameras) if self.cameras is not None else None
        return {"kind": fmt, **d}

    @classmethod
    def from_dict(cls, d: dict) -> "DatasetSource":
        if not isinstance(d, dict):
            raise OmniscsError(f"a dataset source must be a JSON object with a 'kind'; got {d!r}")
        fields = {k: v for k, v in d.items() if k != "kind"}
        unknown = sorted(set(fields) - set(cls.__dataclass_fields__) - {"format"})
        if unknown or "format" in fields:
            raise OmniscsError(f"unknown field(s) {unknown or ['format']} for a {d.get('kind')} source; it takes "
                               f"{[f for f in cls.__dataclass_fields__ if f != 'format']}")
        if "dataroot" not in fields:
            raise OmniscsError(f"a {d.get('kind')} source needs a 'dataroot'")
        return cls(format=d.get("kind"), **fields)

    def scene_id(self) -> str:
        if self.scene is None:
            raise OmniscsError(f"{self.format} source {self.dataroot} names no scene; resolve it first")
        name = _UNSAFE_ID_CHARS.sub("-", self.scene).strip("-.") or "scene"
        mode = "-sweeps" if self.sweeps else ""
        return f"{self.format}-{name}{mode}-{content_hash(self.to_dict())[:8]}"


# ----------------------------------------------------------------------------- what readers hand over
@dataclass
class FramePlan:
    """One frame a reader intends to load: its dataset key (for messages), time and ego pose."""

    key: str
    timestamp_us: int
    global_from_ego: np.ndarray  # [4, 4] float64


@dataclass
class RawBox:
    """A box as a reader found it, in the dataset's global frame."""

    track_key: str
    """The dataset's object id (nuScenes instance token, KITTI track id, Waymo laser object id)."""
    category: str | None
    """Project taxonomy (omniscs.taxonomy.CATEGORIES); None when the label has no project class (dropped)."""
    source_category: str
    global_from_box: np.ndarray  # [4, 4] float64, box frame x forward, y left, z up, origin at the centre
    size: np.ndarray  # [3] length, width, height (metres)
    num_lidar_points: int = -1
    track_id: int | None = None
    """Keep this integer id (KITTI); None: ids are assigned in order of first appearance."""
    attributes: dict[str, str] = field(default_factory=dict)


@dataclass
class FrameData:
    """Everything of one frame: images per camera, LiDAR in the ego frame, boxes, frame-level attributes."""

    images: dict[str, np.ndarray]  # camera -> uint8 [H, W, 3] RGB
    lidar: np.ndarray | None  # float32 [N, 4] x, y, z, intensity (0..255) in the ego frame
    boxes: list[RawBox]
    attributes: list[dict] = field(default_factory=list)
    """Extra side-table rows of this frame: track_id, camera, name, value (frame_idx is filled in)."""


class LogReader(Protocol):
    """A reader opened on one scene: cameras and frame plans known up front, frames loaded one at a time."""

    source: DatasetSource
    cameras: list[CameraRecord]
    frames: list[FramePlan]
    has_lidar: bool
    extra: dict
    """Manifest fields: source_scene_id, location, ego_from_lidar, format-specific facts."""

    def load_frame(self, i: int) -> FrameData:
        """Frame ``i`` of ``frames``; raises BadFrame when a file or field of this frame is unusable."""
        ...


# ----------------------------------------------------------------------------- frames and poses
def world_from_global_at(global_from_ego: np.ndarray) -> np.ndarray:  # [4, 4] -> [4, 4]
    """Re-origin at an ego pose keeping the global up axis: the inverse of (its translation, its yaw)."""
    yaw = float(yaw_from_matrix(global_from_ego[:3, :3]))
    return invert_transform(make_transform(rotmat_from_euler(yaw=yaw), global_from_ego[:3, 3]))


def global_from_world_of(scene: Scene) -> np.ndarray:  # -> [4, 4]
    """The dataset global frame of a scene store (identity for synthetic scenes)."""
    values = scene.manifest.get("global_from_world")
    return np.eye(4) if values is None else np.asarray(values, dtype=np.float64).reshape(4, 4)


def ego_from_lidar_of(scene: Scene) -> np.ndarray | None:  # -> [4, 4] or None
    """The LiDAR mount a reader recorded, or the synthetic world's, or None when unknown."""
    values = scene.manifest.get("ego_from_lidar")
    if values is not None:
        return np.asarray(values, dtype=np.float64).reshape(4, 4)
    world = scene.world
    return None if world is None else np.asarray(world.lidar.ego_from_lidar, dtype=np.float64)


def interpolate_pose(a_from_b0: np.ndarray, a_from_b1: np.ndarray, t: float) -> np.ndarray:  # [4,4] x2 -> [4,4]
    """Linear centre, slerped rotation, at fraction ``t`` from the first pose to the second."""
    q = slerp(rotmat_to_quat(a_from_b0[:3, :3]), rotmat_to_quat(a_from_b1[:3, :3]), t)
    return make_transform(quat_to_rotmat(q), (1 - t) * a_from_b0[:3, 3] + t * a_from_b1[:3, 3])


# ----------------------------------------------------------------------------- files
def require_file(path: Path, what: str) -> Path:
    """``path`` when it is a regular file; otherwise a ValidationError naming it (a FIFO or a device, which would
    block or never end, is refused as not a file)."""
    if not path.is_file():
        if path.exists():
            raise ValidationError(f"{path}: {what} is not a regular file (a folder, a FIFO or a device); give a file")
        raise ValidationError(f"{path}: {what} is missing")
    return path


def read_text_file(path: Path, what: str) -> str:
    """A text file's contents; ValidationError naming it when missing, unreadable or not UTF-8 text."""
    require_file(path, what)
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValidationError(f"{path}: {what} is not text (binary or damaged)") from None
    except OSError as exc:
        raise ValidationError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None


def check_camera(camera: CameraRecord, where) -> CameraRecord:
    """A camera a reader built from calibration: positive size, pinhole K, rigid finite mount; else one
    ValidationError naming ``where`` (the calibration file and record) before anything is written."""
    K = np.asarray(camera.K, dtype=np.float64)
    if not is_safe_id(camera.name):
        raise ValidationError(f"{where}: camera name {camera.name!r} cannot name a folder")
    if not (isinstance(camera.width, (int, np.integer)) and isinstance(camera.height, (int, np.integer))
            and 0 < camera.width <= MAX_IMAGE_SIDE and 0 < camera.height <= MAX_IMAGE_SIDE):
        raise ValidationError(f"{where}: camera {camera.name} has image size {camera.width}x{camera.height}; "
                              f"width and height must be 1..{MAX_IMAGE_SIDE}")
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or \
            not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise ValidationError(f"{where}: camera {camera.name} intrinsics are not a pinhole matrix with positive "
                              f"focal lengths ({K.ravel().tolist()})")
    T = np.asarray(camera.ego_from_camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not is_rigid(T):
        raise ValidationError(f"{where}: camera {camera.name} mount (ego_from_camera) is not a finite rigid transform")
    return camera


#: Largest image side a reader accepts from calibration (pixels): larger values are damage, not cameras.
MAX_IMAGE_SIDE = 16384


def read_image_file(path: Path, expected_size: tuple[int, int] | None = None) -> np.ndarray:  # -> uint8 [H, W, 3]
    """Decode a PNG/JPEG as RGB; BadFrame when missing, undecodable or of the wrong (width, height)."""
    import cv2

    if not path.is_file():
        raise BadFrame(f"{path}: image file is missing")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise BadFrame(f"{path}: image is unreadable")
    return check_image_size(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), path, expected_size)


def decode_image_bytes(data: bytes, where: str, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Decode JPEG/PNG bytes as RGB uint8 [H, W, 3]; BadFrame naming ``where`` when they are not an image."""
    import cv2

    bgr = cv2.imdecode(np.frombuffer(data or b"", dtype=np.uint8), cv2.IMREAD_COLOR) if data else None
    if bgr is None:
        raise BadFrame(f"{where}: image bytes are empty or not an image")
    return check_image_size(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), where, expected_size)


def check_image_size(rgb: np.ndarray, where, expected_size: tuple[int, int] | None) -> np.ndarray:
    if expected_size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(expected_size):
        raise BadFrame(f"{where}: image is {rgb.shape[1]}x{rgb.shape[0]} but its calibration says "
                       f"{expected_size[0]}x{expected_size[1]}")
    return rgb


def read_float32_records(path: Path, values_per_point: int) -> np.ndarray:  # -> float32 [N, values_per_point]
    """A flat float32 point file (KITTI .bin, nuScenes .pcd.bin); BadFrame when missing or truncated."""
    if not path.is_file():
        raise BadFrame(f"{path}: LiDAR file is missing")
    size = path.stat().st_size
    record = 4 * values_per_point
    if size % record:
        raise BadFrame(f"{path}: LiDAR file is truncated ({size} bytes is not a whole number of "
                       f"{values_per_point}-float points)")
    try:
        points = np.fromfile(path, dtype=np.float32).reshape(-1, values_per_point)
    except OSError as exc:
        raise BadFrame(f"{path}: LiDAR file cannot be read ({exc.strerror or exc})") from None
    if not np.all(np.isfinite(points)):
        raise BadFrame(f"{path}: LiDAR file has NaN or Inf values")
    return points


def fingerprint(paths: Iterable[Path], root: Path) -> list:
    """Size and modification time of the files that define a scene, to tell when a reused store is stale."""
    out = []
    for p in sorted(set(paths)):
        if p.is_file():
            st = p.stat()
            out.append([os.path.relpath(p, root), st.st_size, st.st_mtime_ns])
    return out


def pick_scene(available: list[str], named: str | None, where, kind: str, example: str) -> str:
    """The ``named`` scene (a nuScenes scene, a KITTI sequence, a Waymo segment: ``kind``) of the ``available`` ones
    in ``where``, or the only one when none is named; a user mistake otherwise (``example``: a source that names one).
    """
    if named is None:
        if len(available) != 1:
            raise OmniscsError(f"{where} holds {len(available)} {kind}s; name one, e.g. {example}")
        return available[0]
    if named not in available:
        raise OmniscsError(f"{where} has no {kind} {named!r}; it has {available[:20]}")
    return named


def select_cameras(available: list[str], wanted: tuple[str, ...] | None, where: str) -> list[str]:
    """The cameras to keep, in the log's order; an unknown requested camera is a user mistake."""
    if wanted is None:
        return list(available)
    unknown = [c for c in wanted if c not in available]
    if unknown:
        raise OmniscsError(f"unknown camera(s) {unknown} for {where}; it has {available}")
    return [c for c in available if c in wanted]


# ----------------------------------------------------------------------------- writing a log into a store
def write_log(reader: LogReader, out_dir: Path, overwrite: bool = False,
              progress: Callable[[int, int], None] | None = None) -> Path:
    """Load every frame of ``reader`` and write a validated scene store at ``out_dir`` (atomically).

    Bad frames raise ValidationError, or with ``skip_bad_frames`` are left out with one SkippedFramesWarning.
    """
    source = reader.source
    total = len(reader.frames)
    if total == 0:
        raise ValidationError(f"{source.dataroot}: scene {source.scene} has no frames")
    if not source.skip_bad_frames:
        check_frame_files(reader)  # a missing or truncated file fails here, before anything is written
    skipped: list[dict] = []
    dropped: dict[str, int] = {}
    timestamps, poses, box_rows, attr_rows = [], [], [], []
    track_ids: dict[str, int] = {}
    used_ids: set[int] = set()
    world_from_global = None
    with SceneWriter(out_dir, source.scene_id(), source.to_dict(), overwrite=overwrite) as writer:
        writer.set_cameras(reader.cameras)
        for i, plan in enumerate(reader.frames):
            try:
                try:
                    data = reader.load_frame(i)
                except UNEXPECTED_READ_ERRORS as exc:
                    raise reader_failure(reader.source, exc, f"frame {plan.key}") from None
                _check_frame(data, plan, reader)
            except BadFrame as bad:
                if not source.skip_bad_frames:
                    raise ValidationError(f"{bad} (frame {plan.key}; pass skip_bad_frames / --skip-bad-frames "
                                          "to leave such frames out)") from None
                skipped.append({"frame": plan.key, "reason": str(bad)})
                if progress:
                    progress(i + 1, total)
                continue
            f = len(timestamps)
            if world_from_global is None:
                world_from_global = world_from_global_at(plan.global_from_ego)
            timestamps.append(int(plan.timestamp_us))
            poses.append(world_from_global @ plan.global_from_ego)
            for cam, rgb in data.images.items():
                writer.write_image(cam, f, rgb)
            if reader.has_lidar:
                writer.write_lidar(f, data.lidar)
            for box in data.boxes:
                if box.category is None:
                    dropped[box.source_category] = dropped.get(box.source_category, 0) + 1
                    continue
                tid = _track_id(box, track_ids, used_ids)
                box_rows.append(_box_row(f, tid, box, world_from_global))
                attr_rows += [{"frame_idx": f, "track_id": tid, "camera": None, "name": k, "value": v}
                              for k, v in box.attributes.items()]
            attr_rows += [{**row, "frame_idx": f} for row in data.attributes]
            if progress:
                progress(i + 1, total)
        if not timestamps:
            raise ValidationError(f"{source.dataroot}: no readable frame in scene {source.scene} "
                                  f"({len(skipped)} skipped; first: {skipped[0]['reason']})")
        writer.set_frames(np.asarray(timestamps, dtype=np.int64), np.stack(poses))
        writer.set_boxes(box_rows)
        extra = dict(reader.extra)
        extra.update(dataset=source.format, global_from_world=invert_transform(world_from_global).reshape(16).tolist(),
                     skipped_frames=skipped, dropped_boxes=dropped)
        writer.set_extra(**extra)
        _write_attributes(writer.tmp / ATTRIBUTES, attr_rows)
    if skipped:
        reasons = "; ".join(s["reason"] for s in skipped[:REASONS_SHOWN])
        warnings.warn(f"{source.format} scene {source.scene}: skipped {len(skipped)} of {total} frames "
                      f"({reasons})", SkippedFramesWarning, stacklevel=2)
    return Path(out_dir)


#: What a reader may raise on data that is not in the layout it expects (a field of the wrong type, a record that
#: is not an object, a Parquet column it cannot filter): turned into one ValidationError by ``reader_failure``.
UNEXPECTED_READ_ERRORS = (KeyError, TypeError, ValueError, IndexError, AttributeError, ArithmeticError, OSError,
                          pa.ArrowException)


def reader_failure(source: DatasetSource, exc: BaseException, what: str) -> ValidationError:
    """One ValidationError for an unexpected failure while reading ``what`` of ``source``: the format's own
    diagnosis (e.g. which nuScenes table and field is malformed) when it finds one, else the error's first line."""
    from omniscs.scene.sources import _module

    diagnose = getattr(_module(source.format), "diagnose", None)
    found = diagnose(source) if diagnose is not None else None
    if found:
        return ValidationError(found)
    text = str(exc).strip().splitlines()
    detail = f"{type(exc).__name__}: {text[0][:200] if text else ''}".rstrip(": ")
    return ValidationError(f"{source.dataroot}: cannot read {what} of {source.format} scene {source.scene} "
                           f"({detail}); the dataset is damaged or not in the {source.format} layout")


def check_frame_files(reader: LogReader) -> None:
    """Every per-frame file a reader will open exists (and, for flat float32 point files, is a whole number of
    points): a stat per file, so a broken dataset fails before the first frame is read or anything is written."""
    files_of = getattr(reader, "frame_files", None)
    if files_of is None:
        return
    for i, plan in enumerate(reader.frames):
        try:
            files = files_of(i)
        except UNEXPECTED_READ_ERRORS as exc:
            raise reader_failure(reader.source, exc, f"frame {plan.key}") from None
        for path, what, record_bytes in files:
            problem = None
            if not path.is_file():
                problem = f"{what} is missing"
            elif record_bytes and path.stat().st_size % record_bytes:
                problem = (f"{what} is truncated ({path.stat().st_size} bytes is not a whole number of "
                           f"{record_bytes}-byte points)")
            if problem:
                raise ValidationError(f"{path}: {problem} (frame {plan.key}; pass skip_bad_frames / "
                                      "--skip-bad-frames to leave such frames out)")


def _check_frame(data: FrameData, plan: FramePlan, reader: LogReader) -> None:
    """Frame-level checks every format shares: all cameras present, boxes of positive finite size."""
    missing = [c.name for c in reader.cameras if c.name not in data.images]
    if missing:
        raise BadFrame(f"{reader.source.dataroot}: frame {plan.key} has no image for camera(s) {missing}")
    if reader.has_lidar and data.lidar is None:
        raise BadFrame(f"{reader.source.dataroot}: frame {plan.key} has no LiDAR sweep")
    if not np.all(np.isfinite(plan.global_from_ego)):
        raise BadFrame(f"{reader.source.dataroot}: frame {plan.key}: ego pose has NaN or Inf")
    for box in data.boxes:
        if box.category is None:
            continue
        size = np.asarray(box.size, dtype=np.float64)
        if not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise BadFrame(f"{reader.source.dataroot}: frame {plan.key}: box {box.track_key} "
                           f"({box.source_category}) has zero or negative size {size.tolist()}")
        if not np.all(np.isfinite(box.global_from_box)):
            raise BadFrame(f"{reader.source.dataroot}: frame {plan.key}: box {box.track_key} has NaN or Inf pose")


def _track_id(box: RawBox, track_ids: dict[str, int], used: set[int]) -> int:
    if box.track_key not in track_ids:
        if box.track_id is not None:
            tid = int(box.track_id)
        else:
            tid = len(track_ids)
            while tid in used:
                tid += 1
        track_ids[box.track_key] = tid
        used.add(tid)
    return track_ids[box.track_key]


def _box_row(frame_idx: int, track_id: int, box: RawBox, world_from_global: np.ndarray) -> dict:
    pose = world_from_global @ box.global_from_box
    q = rotmat_to_quat(pose[:3, :3])
    return {"frame_idx": frame_idx, "track_id": track_id, "category": box.category,
            "source_category": box.source_category,
            "cx": pose[0, 3], "cy": pose[1, 3], "cz": pose[2, 3],
            "length": float(box.size[0]), "width": float(box.size[1]), "height": float(box.size[2]),
            "yaw": float(yaw_from_matrix(pose[:3, :3])), "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3],
            "num_lidar_points": int(box.num_lidar_points), "visible_pixels": -1}


def _write_attributes(path: Path, rows: list[dict]) -> None:
    df = pd.DataFrame(rows, columns=ATTRIBUTE_SCHEMA.names)
    pq.write_table(pa.Table.from_pandas(df, schema=ATTRIBUTE_SCHEMA, preserve_index=False), path)


def load_attributes(scene: Scene) -> pd.DataFrame:
    """The side table of a scene read from a dataset (empty for other scenes); see the module docstring."""
    path = scene.path / ATTRIBUTES
    if not path.is_file():
        return ATTRIBUTE_SCHEMA.empty_table().to_pandas()
    try:
        return pq.read_table(path).select(ATTRIBUTE_SCHEMA.names).to_pandas()
    except (pa.ArrowInvalid, KeyError, OSError) as exc:
        raise ValidationError(f"{path}: unreadable attribute table ({exc})") from None


def json_value(value) -> str:
    """A side-table value as compact JSON."""
    return json.dumps(value, separators=(",", ":"))
