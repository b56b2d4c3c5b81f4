"""The scene store: the canonical on-disk form of one driving log, whatever its source.

Layout of a scene directory::

    manifest.json            schema version, scene id, source, cameras, content hash, what is present
    frames.parquet           frame_idx, timestamp_us, world_from_ego (16 float64, row-major)
    cameras.parquet          camera, width, height, K (9), ego_from_camera (16)
    boxes.parquet            one row per frame and track, world frame (see BOX_COLUMNS)
    images/<camera>/<frame:06d>.png
    lidar/<frame:06d>.npy    float32 [N, 4] x, y, z, intensity in the ego frame
    gt/<camera>/<frame:06d>.npz   depth float32, instance int32, semantic uint8 (synthetic sources)
    world.json               the procedural world description (synthetic sources; re-renders edits)
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import is_rigid
from omniscs.roadmap import RoadMap
from omniscs.storage import atomic_directory, atomic_write_json, content_hash

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
FRAMES = "frames.parquet"
CAMERAS = "cameras.parquet"
BOXES = "boxes.parquet"
WORLD = "world.json"

FRAME_SCHEMA = pa.schema([
    ("frame_idx", pa.int32()),
    ("timestamp_us", pa.int64()),
    ("world_from_ego", pa.list_(pa.float64(), 16)),
])
CAMERA_SCHEMA = pa.schema([
    ("camera", pa.string()),
    ("width", pa.int32()),
    ("height", pa.int32()),
    ("K", pa.list_(pa.float64(), 9)),
    ("ego_from_camera", pa.list_(pa.float64(), 16)),
])
BOX_SCHEMA = pa.schema([
    ("frame_idx", pa.int32()),
    ("track_id", pa.int64()),
    ("category", pa.string()),          # project taxonomy (omniscs.taxonomy.CATEGORIES)
    ("source_category", pa.string()),   # the label the source used
    ("cx", pa.float64()), ("cy", pa.float64()), ("cz", pa.float64()),
    ("length", pa.float64()), ("width", pa.float64()), ("height", pa.float64()),
    ("yaw", pa.float64()),
    ("qw", pa.float64()), ("qx", pa.float64()), ("qy", pa.float64()), ("qz", pa.float64()),
    ("num_lidar_points", pa.int32()),   # -1 when unknown
    ("visible_pixels", pa.int64()),     # instance-mask pixels over all cameras; -1 when unknown
])
BOX_COLUMNS = BOX_SCHEMA.names


@dataclass(frozen=True)
class CameraRecord:
    """One camera of a scene: its image size, intrinsics and mounting."""

    name: str
    width: int
    height: int
    K: np.ndarray  # [3, 3] float64
    ego_from_camera: np.ndarray  # [4, 4] float64


def image_path(root: Path, camera: str, frame_idx: int) -> Path:
    return root / "images" / camera / f"{frame_idx:06d}.png"


def lidar_path(root: Path, frame_idx: int) -> Path:
    return root / "lidar" / f"{frame_idx:06d}.npy"


def gt_path(root: Path, camera: str, frame_idx: int) -> Path:
    return root / "gt" / camera / f"{frame_idx:06d}.npz"


# ----------------------------------------------------------------------------- reading
class Scene:
    """Read access to a validated scene store (see module docstring for the layout)."""

    def __init__(self, path: Path, manifest: dict, frames: pd.DataFrame, cameras: dict[str, CameraRecord],
                 boxes: pd.DataFrame):
        self.path = path
        self.manifest = manifest
        self.frames = frames
        self._cameras = cameras
        self.boxes = boxes
        self._poses = np.stack([np.asarray(m, dtype=np.float64).reshape(4, 4)
                                for m in frames["world_from_ego"]]) if len(frames) else np.zeros((0, 4, 4))

    def __repr__(self) -> str:
        return f"Scene({self.scene_id!r}, frames={self.n_frames}, cameras={self.camera_names})"

    @property
    def scene_id(self) -> str:
        return self.manifest["scene_id"]

    @property
    def source(self) -> dict:
        return self.manifest["source"]

    @property
    def content_hash(self) -> str:
        return self.manifest["content_hash"]

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def camera_names(self) -> list[str]:
        return list(self._cameras)

    @property
    def has_lidar(self) -> bool:
        return bool(self.manifest.get("has_lidar"))

    @property
    def has_gt(self) -> bool:
        return bool(self.manifest.get("has_gt"))

    def camera(self, cam: str) -> CameraRecord:
        try:
            return self._cameras[cam]
        except KeyError:
            raise OmniscsError(f"unknown camera {cam!r} in scene {self.scene_id}; it has {self.camera_names}") from None

    def intrinsics(self, cam: str) -> np.ndarray:  # [3, 3]
        return self.camera(cam).K.copy()

    def ego_from_camera(self, cam: str) -> np.ndarray:  # [4, 4]
        return self.camera(cam).ego_from_camera.copy()

    def image_size(self, cam: str) -> tuple[int, int]:  # (width, height)
        c = self.camera(cam)
        return c.width, c.height

    def check_frame(self, frame_idx: int) -> int:
        """``frame_idx`` as an int, or an OmniscsError when the scene has no such frame."""
        if not 0 <= int(frame_idx) < self.n_frames:
            raise OmniscsError(f"frame {frame_idx} is out of range; scene {self.scene_id} has frames 0..{self.n_frames - 1}")
        return int(frame_idx)

    def world_from_ego(self, frame_idx: int) -> np.ndarray:  # [4, 4]
        return self._poses[self.check_frame(frame_idx)].copy()

    @property
    def world_from_ego_all(self) -> np.ndarray:  # [F, 4, 4]
        return self._poses.copy()

    def world_from_camera(self, cam: str, frame_idx: int) -> np.ndarray:  # [4, 4]
        return self.world_from_ego(frame_idx) @ self.camera(cam).ego_from_camera

    def image(self, cam: str, frame_idx: int) -> np.ndarray:  # uint8 [H, W, 3] RGB
        path = image_path(self.path, self.camera(cam).name, self.check_frame(frame_idx))
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValidationError(f"{path}: image is missing or unreadable")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def lidar(self, frame_idx: int) -> np.ndarray:  # float32 [N, 4] ego frame
        path = lidar_path(self.path, self.check_frame(frame_idx))
        if not self.has_lidar:
            raise OmniscsError(f"scene {self.scene_id} has no LiDAR")
        return np.load(path).astype(np.float32, copy=False)

    def _gt(self, cam: str, frame_idx: int, key: str) -> np.ndarray | None:
        if not self.has_gt:
            return None
        path = gt_path(self.path, self.camera(cam).name, self.check_frame(frame_idx))
        with np.load(path) as data:
            return data[key]

    def depth(self, cam: str, frame_idx: int) -> np.ndarray | None:  # float32 [H, W], 0 = no surface
        return self._gt(cam, frame_idx, "depth")

    def instance_mask(self, cam: str, frame_idx: int) -> np.ndarray | None:  # int32 [H, W], -1 = none
        return self._gt(cam, frame_idx, "instance")

    def semantic_mask(self, cam: str, frame_idx: int) -> np.ndarray | None:  # uint8 [H, W]
        return self._gt(cam, frame_idx, "semantic")

    def boxes_at(self, frame_idx: int) -> pd.DataFrame:
        return self.boxes[self.boxes.frame_idx == self.check_frame(frame_idx)]

    @cached_property
    def world(self):
        """The procedural world this scene was rendered from, or None for recorded logs."""
        path = self.path / WORLD
        if not path.exists():
            return None
        from omniscs.world.model import World  # the world package is heavy; only synthetic scenes need it
        return World.from_json(path.read_text())

    @cached_property
    def road_map(self) -> RoadMap | None:
        """The log's road map: the procedural world's for synthetic scenes, None for recorded logs (models then
        derive a map from the traffic)."""
        world = self.world
        if world is None:
            return None
        from omniscs.world.layouts import road_map_for

        return road_map_for(world)


def load_scene(path: str | os.PathLike) -> Scene:
    """Open a scene store, validating it; raises ValidationError naming the file and field at fault."""
    root = Path(path)
    manifest_path = root / MANIFEST
    if not manifest_path.is_file():
        raise ValidationError(f"{manifest_path}: not a scene store (manifest.json is missing)")
    try:
        manifest = json.loads(manifest_path.read_text())
    except json.JSONDecodeError as exc:
        raise ValidationError(f"{manifest_path}: invalid JSON ({exc})") from None
    version = manifest.get("schema_version")
    if version != SCHEMA_VERSION:
        raise ValidationError(f"{manifest_path}: field schema_version is {version!r}; this omniscs reads {SCHEMA_VERSION}")
    frames = _read_table(root / FRAMES, FRAME_SCHEMA)
    cameras_df = _read_table(root / CAMERAS, CAMERA_SCHEMA)
    boxes = _read_table(root / BOXES, BOX_SCHEMA)
    cameras = {
        r.camera: CameraRecord(r.camera, int(r.width), int(r.height),
                               np.asarray(r.K, dtype=np.float64).reshape(3, 3),
                               np.asarray(r.ego_from_camera, dtype=np.float64).reshape(4, 4))
        for r in cameras_df.itertuples()
    }
    validate_tables(root, manifest, frames, cameras, boxes)
    validate_files(root, manifest, len(frames), list(cameras))
    return Scene(root, manifest, frames, cameras, boxes)


def _read_table(path: Path, schema: pa.Schema) -> pd.DataFrame:
    if not path.is_file():
        raise ValidationError(f"{path}: file is missing")
    try:
        table = pq.read_table(path)
    except Exception as exc:  # pyarrow raises several types for corrupt files
        raise ValidationError(f"{path}: unreadable Parquet ({exc})") from None
    missing = [n for n in schema.names if n not in table.column_names]
    if missing:
        raise ValidationError(f"{path}: missing column(s) {missing}")
    return table.select(schema.names).to_pandas()


# ----------------------------------------------------------------------------- validation
def validate_tables(root: Path, manifest: dict, frames: pd.DataFrame, cameras: dict[str, CameraRecord],
                    boxes: pd.DataFrame) -> None:
    """Check poses, timestamps, cameras and boxes; the first problem found raises ValidationError."""
    fpath, cpath, bpath = root / FRAMES, root / CAMERAS, root / BOXES
    if len(frames) == 0:
        raise ValidationError(f"{fpath}: no frames")
    if not np.array_equal(frames["frame_idx"].to_numpy(), np.arange(len(frames))):
        raise ValidationError(f"{fpath}: field frame_idx must be 0..{len(frames) - 1} in order")
    ts = frames["timestamp_us"].to_numpy()
    if np.any(np.diff(ts) <= 0):
        bad = int(np.argmax(np.diff(ts) <= 0)) + 1
        raise ValidationError(f"{fpath}: field timestamp_us is not strictly increasing at frame {bad}")
    for i, m in enumerate(frames["world_from_ego"]):
        T = np.asarray(m, dtype=np.float64).reshape(4, 4)
        if not np.all(np.isfinite(T)):
            raise ValidationError(f"{fpath}: field world_from_ego of frame {i} has NaN or Inf")
        if not is_rigid(T):
            raise ValidationError(f"{fpath}: field world_from_ego of frame {i} is not a rigid transform")
    if not cameras:
        raise ValidationError(f"{cpath}: no cameras")
    for name, cam in cameras.items():
        if cam.width <= 0 or cam.height <= 0:
            raise ValidationError(f"{cpath}: camera {name}: fields width/height must be positive")
        K = cam.K
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
            raise ValidationError(f"{cpath}: camera {name}: field K is not a valid pinhole intrinsics matrix")
        if not is_rigid(cam.ego_from_camera):
            raise ValidationError(f"{cpath}: camera {name}: field ego_from_camera is not a rigid transform")
    listed = manifest.get("cameras", [])
    unknown = [c for c in listed if c not in cameras]
    if unknown or set(listed) != set(cameras):
        raise ValidationError(f"{root / MANIFEST}: field cameras lists {listed} but {cpath.name} has {list(cameras)}")
    if len(boxes):
        geom = boxes[["cx", "cy", "cz", "length", "width", "height", "yaw", "qw", "qx", "qy", "qz"]].to_numpy()
        if not np.all(np.isfinite(geom)):
            raise ValidationError(f"{bpath}: box fields have NaN or Inf")
        size = boxes[["length", "width", "height"]].to_numpy()
        if np.any(size <= 0):
            row = boxes.iloc[int(np.argmax(np.any(size <= 0, axis=1)))]
            raise ValidationError(
                f"{bpath}: field length/width/height must be > 0 (track {row.track_id}, frame {row.frame_idx})")
        fidx = boxes["frame_idx"].to_numpy()
        if fidx.min() < 0 or fidx.max() >= len(frames):
            raise ValidationError(f"{bpath}: field frame_idx outside 0..{len(frames) - 1}")
        if boxes.duplicated(["frame_idx", "track_id"]).any():
            raise ValidationError(f"{bpath}: duplicate (frame_idx, track_id) rows")


def validate_files(root: Path, manifest: dict, n_frames: int, cameras: list[str]) -> None:
    """Check that every image, LiDAR and GT file the manifest promises exists, and no unknown camera folder."""
    for folder in ("images", "gt"):
        base = root / folder
        if base.is_dir():
            extra = sorted(p.name for p in base.iterdir() if p.is_dir() and p.name not in cameras)
            if extra:
                raise ValidationError(f"{base}: folder for unknown camera(s) {extra} (not in {CAMERAS})")
    for cam in cameras:
        for f in range(n_frames):
            if not image_path(root, cam, f).is_file():
                raise ValidationError(f"{image_path(root, cam, f)}: image file is missing")
            if manifest.get("has_gt") and not gt_path(root, cam, f).is_file():
                raise ValidationError(f"{gt_path(root, cam, f)}: ground-truth file is missing")
    if manifest.get("has_lidar"):
        for f in range(n_frames):
            if not lidar_path(root, f).is_file():
                raise ValidationError(f"{lidar_path(root, f)}: LiDAR file is missing")


# ----------------------------------------------------------------------------- writing
def boxes_frame(rows: list[dict] | pd.DataFrame) -> pd.DataFrame:
    """Boxes as a DataFrame in the store's column order and dtypes (missing optional fields filled)."""
    df = pd.DataFrame(rows) if not isinstance(rows, pd.DataFrame) else rows.copy()
    defaults = {"source_category": None, "num_lidar_points": -1, "visible_pixels": -1}
    for col, default in defaults.items():
        if col not in df:
            df[col] = default
    if "qw" not in df and "yaw" in df:
        df["qw"], df["qx"], df["qy"], df["qz"] = np.cos(df.yaw / 2), 0.0, 0.0, np.sin(df.yaw / 2)
    if "source_category" in df:
        df["source_category"] = df["source_category"].fillna(df.get("category"))
    for name in BOX_COLUMNS:
        if name not in df:
            df[name] = pd.Series(dtype=object)
    table = pa.Table.from_pandas(df[BOX_COLUMNS], schema=BOX_SCHEMA, preserve_index=False)
    return table.to_pandas()


class SceneWriter:
    """Writes a scene store into a temporary directory that replaces ``out_dir`` only when complete.

    Use as a context manager; call ``set_frames``, ``set_cameras`` and ``set_boxes`` once and the
    per-frame writers as data arrives. Validation runs before the rename; on any error nothing is left.
    """

    def __init__(self, out_dir: str | os.PathLike, scene_id: str, source: dict, overwrite: bool = False):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not overwrite:
            raise OmniscsError(f"{self.out_dir} already exists; choose another --out or pass overwrite")
        self.scene_id = scene_id
        self.source = source
        self.overwrite = overwrite
        self._frames: pd.DataFrame | None = None
        self._cameras: dict[str, CameraRecord] = {}
        self._boxes: pd.DataFrame | None = None
        self._has_lidar = False
        self._has_gt = False
        self._extra: dict = {}
        self._ctx = None
        self.tmp: Path | None = None

    def __enter__(self) -> "SceneWriter":
        self._ctx = atomic_directory(self.out_dir, overwrite=self.overwrite)
        self.tmp = self._ctx.__enter__()
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                self._finish()
            except BaseException as err:
                self._ctx.__exit__(type(err), err, err.__traceback__)
                raise
        return self._ctx.__exit__(exc_type, exc, tb)

    def set_frames(self, timestamps_us: np.ndarray, world_from_ego: np.ndarray) -> None:
        ts = np.asarray(timestamps_us, dtype=np.int64)
        poses = np.asarray(world_from_ego, dtype=np.float64).reshape(-1, 4, 4)
        if len(ts) != len(poses):
            raise OmniscsError(f"{len(ts)} timestamps but {len(poses)} poses")
        self._frames = pd.DataFrame({"frame_idx": np.arange(len(ts), dtype=np.int32), "timestamp_us": ts,
                                     "world_from_ego": list(poses.reshape(-1, 16))})

    def set_cameras(self, cameras: list[CameraRecord]) -> None:
        self._cameras = {c.name: c for c in cameras}

    def set_boxes(self, boxes: list[dict] | pd.DataFrame) -> None:
        self._boxes = boxes_frame(boxes)

    def set_extra(self, **fields) -> None:
        """Extra manifest fields (e.g. the world's template and lighting)."""
        self._extra.update(fields)

    def write_image(self, camera: str, frame_idx: int, rgb: np.ndarray) -> None:
        path = image_path(self.tmp, camera, frame_idx)
        path.parent.mkdir(parents=True, exist_ok=True)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise OmniscsError(f"image for {camera}/{frame_idx} must be uint8 [H, W, 3]; got {rgb.dtype} {rgb.shape}")
        if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OmniscsError(f"could not write {path}")

    def write_lidar(self, frame_idx: int, points: np.ndarray) -> None:
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 4)
        path = lidar_path(self.tmp, frame_idx)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, pts)
        self._has_lidar = True

    def write_gt(self, camera: str, frame_idx: int, depth: np.ndarray, instance: np.ndarray,
                 semantic: np.ndarray) -> None:
        path = gt_path(self.tmp, camera, frame_idx)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, depth=depth.astype(np.float32), instance=instance.astype(np.int32),
                            semantic=semantic.astype(np.uint8))
        self._has_gt = True

    def write_world_json(self, text: str) -> None:
        (self.tmp / WORLD).write_text(text)

    def _finish(self) -> None:
        if self._frames is None or not self._cameras:
            raise OmniscsError("a scene needs frames and cameras before it is written")
        boxes = self._boxes if self._boxes is not None else boxes_frame([])
        boxes = boxes.sort_values(["frame_idx", "track_id"]).reset_index(drop=True)
        cams_df = pd.DataFrame([{"camera": c.name, "width": c.width, "height": c.height,
                                 "K": np.asarray(c.K, dtype=np.float64).reshape(9),
                                 "ego_from_camera": np.asarray(c.ego_from_camera, dtype=np.float64).reshape(16)}
                                for c in self._cameras.values()])
        pq.write_table(pa.Table.from_pandas(self._frames, schema=FRAME_SCHEMA, preserve_index=False), self.tmp / FRAMES)
        pq.write_table(pa.Table.from_pandas(cams_df, schema=CAMERA_SCHEMA, preserve_index=False), self.tmp / CAMERAS)
        pq.write_table(pa.Table.from_pandas(boxes, schema=BOX_SCHEMA, preserve_index=False), self.tmp / BOXES)
        manifest = {
            "schema_version": SCHEMA_VERSION,
            "scene_id": self.scene_id,
            "source": self.source,
            "cameras": list(self._cameras),
            "n_frames": len(self._frames),
            "has_lidar": self._has_lidar,
            "has_gt": self._has_gt,
            "content_hash": table_hash(self._frames, self._cameras, boxes, self.source),
            **self._extra,
        }
        validate_tables(self.tmp, manifest, self._frames, self._cameras, boxes)
        validate_files(self.tmp, manifest, len(self._frames), list(self._cameras))
        atomic_write_json(self.tmp / MANIFEST, manifest)


def table_hash(frames: pd.DataFrame, cameras: dict[str, CameraRecord], boxes: pd.DataFrame, source: dict) -> str:
    """Content hash of what defines a scene's geometry: poses, timestamps, cameras, boxes, source."""
    poses = np.stack([np.asarray(m, dtype=np.float64) for m in frames["world_from_ego"]])
    cams = [(c.name, c.width, c.height, np.asarray(c.K, np.float64), np.asarray(c.ego_from_camera, np.float64))
            for c in cameras.values()]
    box_geom = boxes[["frame_idx", "track_id", "cx", "cy", "cz", "length", "width", "height", "yaw"]].to_numpy(np.float64)
    return content_hash(frames["timestamp_us"].to_numpy(np.int64), poses, cams, box_geom,
                        list(boxes["category"]), source)
