"""The scene store: the canonical on-disk form of one driving log, whatever its source.

Layout of a scene directory::

    manifest.json            schema version, scene id, source, cameras, content hash, what is present, and
                             ``files``: size and sha256 of every other file the writer wrote (stores written before
                             that field existed lack it and stay readable)
    frames.parquet           frame_idx, timestamp_us, world_from_ego (16 float64, row-major)
    cameras.parquet          camera, width, height, K (9), ego_from_camera (16)
    boxes.parquet            one row per frame and track, world frame (see BOX_COLUMNS)
    images/<camera>/<frame:06d>.png
    lidar/<frame:06d>.npy    float32 [N, 4] x, y, z, intensity in the ego frame
    gt/<camera>/<frame:06d>.npz   depth float32, instance int32, semantic uint8 (synthetic sources)
    world.json               the procedural world description (synthetic sources; re-renders edits)

Stores are written by ``omniscs.scene.writer.SceneWriter``; this module reads and checks them.
"""
from __future__ import annotations

import os
import re
import zipfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path, PurePosixPath
from typing import Callable

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.checks import is_int, is_real
from omniscs.untrusted import read_json
from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import is_rigid
from omniscs.ids import check_id
from omniscs.roadmap import RoadMap
from omniscs.storage import OWNER_MARKER
from omniscs.storage import file_sha256 as storage_sha256

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
FRAMES = "frames.parquet"
CAMERAS = "cameras.parquet"
BOXES = "boxes.parquet"
WORLD = "world.json"
#: Manifest field: {relative path: [size in bytes, sha256 hex]} of every file the writer wrote besides the manifest.
FILES = "files"

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
        camera = self.camera(cam)
        path = image_path(self.path, camera.name, self.check_frame(frame_idx))
        return read_store_image(path, camera)

    def lidar(self, frame_idx: int) -> np.ndarray:  # float32 [N, 4] ego frame
        path = lidar_path(self.path, self.check_frame(frame_idx))
        if not self.has_lidar:
            raise OmniscsError(f"scene {self.scene_id} has no LiDAR")
        return read_store_lidar(path)

    def _gt(self, cam: str, frame_idx: int, key: str) -> np.ndarray | None:
        if not self.has_gt:
            return None
        camera = self.camera(cam)
        return read_store_gt(gt_path(self.path, camera.name, self.check_frame(frame_idx)), camera, (key,))[key]

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

        raw = read_json(path, "the store is damaged: write it again with `omniscs world make`", expect=dict,
                        what="world description", error=ValidationError)
        try:
            return World.from_dict(raw)
        except OmniscsError:
            raise
        except (ValueError, KeyError, TypeError, AttributeError, IndexError, OSError) as exc:
            raise ValidationError(f"{path}: not a readable world description ({_first_line(exc)}); the store is "
                                  "damaged: write it again with `omniscs world make`") from None

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
    """Open a scene store, validating it; raises ValidationError naming the file and field at fault.

    Checks the manifest's fields and types, the tables' columns, types and values, that every promised file is
    there and, where the manifest records sizes (stores written by this version on), that each file has the size
    it was written with: a truncated image or LiDAR file is caught here, in milliseconds. ``verify_store`` also
    compares contents (sha256) or, for older stores, decodes every file.
    """
    root = Path(path)
    if not root.is_dir():
        raise ValidationError(f"{root / MANIFEST}: not a scene store (manifest.json is missing)")
    try:
        manifest = read_manifest(root)
        frames = _read_table(root / FRAMES, FRAME_SCHEMA)
        cameras_df = _read_table(root / CAMERAS, CAMERA_SCHEMA)
        boxes = _read_table(root / BOXES, BOX_SCHEMA)
        cameras = _camera_records(root / CAMERAS, cameras_df)
        if manifest["n_frames"] != len(frames):
            raise ValidationError(f"{root / MANIFEST}: field n_frames is {manifest['n_frames']} but {FRAMES} has "
                                  f"{len(frames)} rows")
        validate_tables(root, manifest, frames, cameras, boxes)
        validate_files(root, manifest, len(frames), list(cameras))
        check_file_sizes(root, manifest)
    except OSError as exc:  # e.g. the store was replaced or removed while it was being read
        raise ValidationError(f"{root}: cannot read the store ({exc.strerror or exc}); it may have been replaced "
                              "or removed while it was read; open it again") from None
    return Scene(root, manifest, frames, cameras, boxes)


def verify_store(path: str | os.PathLike, progress: Callable[[int, int], None] | None = None) -> Scene:
    """``load_scene`` plus a full check of every data file: its sha256 against the manifest's record, or, for
    stores written before records existed, a decode of every image, LiDAR sweep, ground-truth file and side
    table. Ingest of an existing store path calls this: a damaged store is refused before anything uses it.
    About 0.05 s (hashes) or 0.6 s (decode) for 40 frames x 3 cameras of 480x270 on one core."""
    scene = load_scene(path)
    root = scene.path
    files = scene.manifest.get(FILES)
    if files is not None:
        for i, (rel, (size, digest)) in enumerate(sorted(files.items())):
            file = root / rel
            if file_sha256(file) != digest:
                raise ValidationError(f"{file}: content differs from the sha256 recorded in {MANIFEST} (the file "
                                      "is damaged or was changed); re-ingest the source or restore the file")
            if progress:
                progress(i + 1, len(files))
        # a hash vouches only for what was recorded: a file swapped together with its hash (a JPEG, another size,
        # a cut-off PNG) is caught by the images' structure, read from a few bytes at each end
        for cam in (scene.camera(c) for c in scene.camera_names):
            for f in range(scene.n_frames):
                check_png_structure(image_path(root, cam.name, f), cam)
        return scene
    cams = [scene.camera(c) for c in scene.camera_names]
    total = scene.n_frames * len(cams) * (2 if scene.has_gt else 1) + (scene.n_frames if scene.has_lidar else 0)
    done = 0
    for f in range(scene.n_frames):
        for cam in cams:
            read_store_image(image_path(root, cam.name, f), cam)
            done += 1
            if scene.has_gt:
                read_store_gt(gt_path(root, cam.name, f), cam)
                done += 1
        if scene.has_lidar:
            read_store_lidar(lidar_path(root, f))
            done += 1
        if progress:
            progress(done, total)
    side = root / "attributes.parquet"
    if side.is_file():
        try:
            pq.read_table(side)
        except (pa.ArrowException, OSError) as exc:
            raise ValidationError(f"{side}: unreadable Parquet ({_first_line(exc)}); re-ingest the source") from None
    world = root / WORLD
    if world.is_file():
        read_json(world, "not a readable world description; write the store again with `omniscs world make`",
                  expect=dict, what="world description", error=ValidationError)
    return scene


# ----------------------------------------------------------------------------- reading files
def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:200]


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _json_type(value) -> str:
    return {dict: "object", list: "list", str: "string", bool: "boolean", type(None): "null"}.get(
        type(value), "number" if isinstance(value, (int, float)) else type(value).__name__)


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes (hex); a missing or unreadable file is a ValidationError."""
    try:
        return storage_sha256(path)
    except FileNotFoundError:
        raise ValidationError(f"{path}: file is missing") from None
    except OSError as exc:
        raise ValidationError(f"{path}: cannot read ({exc.strerror or exc})") from None


#: A PNG file's first 8 bytes, and its last chunk (length 0, type IEND, its CRC).
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def check_png_structure(path: Path, camera: CameraRecord) -> None:
    """Without decoding: ``path`` is a whole PNG (signature, IHDR first, IEND last) of the camera's size;
    ValidationError otherwise (a JPEG under a .png name, another size, a file cut off)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
            fh.seek(0, os.SEEK_END)
            if fh.tell() < 24 + len(PNG_END):
                raise ValidationError(f"{path}: too short to be a PNG image; re-ingest the source")
            fh.seek(-len(PNG_END), os.SEEK_END)
            tail = fh.read(len(PNG_END))
    except FileNotFoundError:
        raise ValidationError(f"{path}: image file is missing") from None
    if head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValidationError(f"{path}: not a PNG image (a scene store keeps its images as PNG); re-ingest the source")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if (width, height) != (camera.width, camera.height):
        raise ValidationError(f"{path}: image is {width}x{height} but camera {camera.name} is "
                              f"{camera.width}x{camera.height} in {CAMERAS}")
    if tail != PNG_END:
        raise ValidationError(f"{path}: the PNG image is cut off (no IEND at its end); re-ingest the source")


def read_store_image(path: Path, camera: CameraRecord) -> np.ndarray:  # -> uint8 [H, W, 3] RGB
    """Decode one stored image; ValidationError when missing, undecodable or not the camera's size."""
    if not path.is_file():
        raise ValidationError(f"{path}: image file is missing")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValidationError(f"{path}: image is unreadable (damaged or not a PNG); re-ingest the source")
    if bgr.shape[:2] != (camera.height, camera.width):
        raise ValidationError(f"{path}: image is {bgr.shape[1]}x{bgr.shape[0]} but camera {camera.name} is "
                              f"{camera.width}x{camera.height} in {CAMERAS}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_store_lidar(path: Path) -> np.ndarray:  # -> float32 [N, 4]
    """Load one stored LiDAR sweep; ValidationError when missing, damaged, of the wrong shape or not finite."""
    if not path.is_file():
        raise ValidationError(f"{path}: LiDAR file is missing")
    try:
        points = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise ValidationError(f"{path}: LiDAR file is damaged ({_first_line(exc)}); re-ingest the source") from None
    if points.ndim != 2 or points.shape[1] != 4 or points.dtype.kind != "f":
        raise ValidationError(f"{path}: LiDAR points must be float [N, 4]; got {points.dtype} {list(points.shape)}")
    if not np.all(np.isfinite(points)):
        raise ValidationError(f"{path}: LiDAR points have NaN or Inf")
    return points.astype(np.float32, copy=False)


#: Arrays of a ground-truth file and their dtype kinds.
GT_ARRAYS = {"depth": "f", "instance": "i", "semantic": "u"}


def read_store_gt(path: Path, camera: CameraRecord, keys=tuple(GT_ARRAYS)) -> dict[str, np.ndarray]:
    """Load arrays ``keys`` of one ground-truth file (depth, instance, semantic); ValidationError when the file is
    missing or damaged or an array is absent or of the wrong size or type."""
    if not path.is_file():
        raise ValidationError(f"{path}: ground-truth file is missing")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in keys if key in data.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise ValidationError(f"{path}: ground-truth file is damaged ({_first_line(exc)}); re-ingest the "
                              "source") from None
    for key in keys:
        kind = GT_ARRAYS[key]
        if key not in arrays:
            raise ValidationError(f"{path}: ground-truth file has no {key!r} array")
        a = arrays[key]
        if a.shape != (camera.height, camera.width) or a.dtype.kind != kind:
            raise ValidationError(f"{path}: array {key} is {a.dtype} {list(a.shape)}; camera {camera.name} needs "
                                  f"[{camera.height}, {camera.width}]")
    return arrays


# ----------------------------------------------------------------------------- the manifest
#: Fields every manifest has, and their JSON types.
MANIFEST_FIELDS: dict[str, type] = {"schema_version": int, "scene_id": str, "source": dict, "cameras": list,
                                    "n_frames": int, "has_lidar": bool, "has_gt": bool, "content_hash": str}
#: Optional fields other code reads, and their JSON types (null allowed); "matrix" is 16 finite numbers.
OPTIONAL_FIELDS: dict[str, type | str] = {"template": str, "lighting": str, "seed": int, "location": str,
                                          "source_scene_id": str, "dataset": str, "global_from_world": "matrix",
                                          "ego_from_lidar": "matrix", FILES: dict}
_SHA256 = re.compile(r"[0-9a-f]{64}")


def _is_type(value, kind) -> bool:
    if kind is int:
        return is_int(value)
    if kind == "matrix":
        return (isinstance(value, list) and len(value) == 16 and all(is_real(v) for v in value)
                and bool(np.all(np.isfinite(np.asarray(value, dtype=np.float64)))))
    return isinstance(value, kind)


def read_manifest(root: str | os.PathLike) -> dict:
    """A store's manifest after checking it is a JSON object with every field of the right type."""
    path = Path(root) / MANIFEST
    if not path.exists():
        raise ValidationError(f"{path}: not a scene store (manifest.json is missing)")
    manifest = read_json(path, "the scene store's manifest is damaged; re-ingest the source", what="manifest",
                         error=ValidationError)
    if not isinstance(manifest, dict):
        raise ValidationError(f"{path}: must be a JSON object with the store's fields; got a {_json_type(manifest)}")
    version = manifest.get("schema_version")
    if not _is_type(version, int) or version != SCHEMA_VERSION:
        raise ValidationError(f"{path}: field schema_version is {_short(version)}; this omniscs reads "
                              f"{SCHEMA_VERSION}")
    missing = [k for k in MANIFEST_FIELDS if k not in manifest]
    if missing:
        raise ValidationError(f"{path}: missing field(s) {missing}; re-ingest the source")
    for key, kind in (*MANIFEST_FIELDS.items(), *OPTIONAL_FIELDS.items()):
        value = manifest.get(key)
        if key in OPTIONAL_FIELDS and value is None:
            continue
        if not _is_type(value, kind):
            what = {int: "an integer", str: "a string", dict: "a JSON object", list: "a JSON list",
                    bool: "true or false", "matrix": "16 finite numbers"}[kind]
            raise ValidationError(f"{path}: field {key} must be {what}; got {_short(value)}")
    try:
        check_id("scene id", manifest["scene_id"])
        for cam in manifest["cameras"]:
            check_id("camera name", cam)
    except OmniscsError as exc:
        field = "scene_id" if str(exc).startswith("scene id") else "cameras"
        raise ValidationError(f"{path}: field {field}: {exc}") from None
    if len(set(manifest["cameras"])) != len(manifest["cameras"]):
        raise ValidationError(f"{path}: field cameras lists a camera twice: {manifest['cameras']}")
    if manifest["n_frames"] < 1:
        raise ValidationError(f"{path}: field n_frames must be at least 1; got {manifest['n_frames']}")
    source = manifest["source"]
    for key in ("kind", "dataroot"):
        if source.get(key) is not None and not isinstance(source[key], str):
            raise ValidationError(f"{path}: field source.{key} must be a string; got {_short(source[key])}")
    for rel, record in (manifest.get(FILES) or {}).items():
        parts = PurePosixPath(rel).parts
        if (not rel or "\\" in rel or PurePosixPath(rel).is_absolute() or ".." in parts
                or rel in (MANIFEST, OWNER_MARKER)):
            raise ValidationError(f"{path}: field {FILES} names {_short(rel)}, not a file inside the store")
        if not (isinstance(record, list) and len(record) == 2 and _is_type(record[0], int) and record[0] >= 0
                and isinstance(record[1], str) and _SHA256.fullmatch(record[1])):
            raise ValidationError(f"{path}: field {FILES}[{rel!r}] must be [size in bytes, sha256 hex]; got "
                                  f"{_short(record)}")
    return manifest


def check_file_sizes(root: Path, manifest: dict) -> None:
    """Every file the manifest records exists with its recorded size (a stat per file; no reading)."""
    for rel, (size, _) in (manifest.get(FILES) or {}).items():
        file = root / rel
        try:
            actual = file.stat().st_size
        except FileNotFoundError:
            raise ValidationError(f"{file}: file is missing (the manifest records it)") from None
        except OSError as exc:
            raise ValidationError(f"{file}: cannot read ({exc.strerror or exc})") from None
        if actual != size:
            raise ValidationError(f"{file}: file is {actual} bytes but {MANIFEST} records {size} (truncated or "
                                  "damaged); re-ingest the source or restore the file")


# ----------------------------------------------------------------------------- the tables
def _read_table(path: Path, schema: pa.Schema) -> pd.DataFrame:
    """A store table with exactly ``schema``'s columns, each of its type (or one that converts without loss)."""
    if not path.is_file():
        raise ValidationError(f"{path}: file is missing")
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise ValidationError(f"{path}: unreadable Parquet ({_first_line(exc)}); re-ingest the source") from None
    missing = [n for n in schema.names if n not in table.column_names]
    if missing:
        raise ValidationError(f"{path}: missing column(s) {missing}")
    extra = [n for n in table.column_names if n not in schema.names]
    if extra:
        raise ValidationError(f"{path}: unexpected column(s) {extra}; a store's {path.name} has exactly "
                              f"{schema.names}")
    columns = []
    for fld in schema:
        col = table.column(fld.name)
        if not _convertible(col.type, fld.type):
            raise ValidationError(f"{path}: column {fld.name} has type {col.type}, expected {fld.type}")
        try:
            col = col.cast(fld.type, safe=True)
        except (pa.ArrowException, ValueError) as exc:
            raise ValidationError(f"{path}: column {fld.name} does not fit {fld.type} ({_first_line(exc)})") from None
        nulls = col.null_count  # a null float (pandas writes NaN so) reads back as NaN: the value checks name it
        if pa.types.is_floating(fld.type):
            nulls = 0
        elif pa.types.is_fixed_size_list(fld.type) and nulls == 0 and not pa.types.is_floating(fld.type.value_type):
            nulls = sum(c.flatten().null_count for c in col.chunks)
        if nulls and fld.name != "source_category":
            raise ValidationError(f"{path}: column {fld.name} has {nulls} null value(s)")
        columns.append(col)
    try:
        return pa.Table.from_arrays(columns, schema=schema).to_pandas()
    except (pa.ArrowException, ValueError, TypeError) as exc:
        raise ValidationError(f"{path}: unreadable table ({_first_line(exc)})") from None


def _convertible(actual: pa.DataType, expected: pa.DataType) -> bool:
    """Whether a column of type ``actual`` may stand for ``expected`` (same kind; the cast checks the values)."""
    if actual == expected:
        return True
    if pa.types.is_integer(expected):
        return pa.types.is_integer(actual)
    if pa.types.is_floating(expected):
        return pa.types.is_floating(actual) or pa.types.is_integer(actual)
    if pa.types.is_string(expected):
        return pa.types.is_string(actual) or pa.types.is_large_string(actual) or pa.types.is_null(actual)
    if pa.types.is_fixed_size_list(expected):
        is_list = (pa.types.is_list(actual) or pa.types.is_large_list(actual) or pa.types.is_fixed_size_list(actual))
        return is_list and _convertible(actual.value_type, expected.value_type)
    return False


def _camera_records(path: Path, cameras_df: pd.DataFrame) -> dict[str, CameraRecord]:
    cameras: dict[str, CameraRecord] = {}
    for r in cameras_df.itertuples():
        try:
            check_id("camera name", r.camera)
        except OmniscsError as exc:
            raise ValidationError(f"{path}: field camera: {exc}") from None
        if r.camera in cameras:
            raise ValidationError(f"{path}: camera {r.camera} is listed twice")
        cameras[r.camera] = CameraRecord(r.camera, int(r.width), int(r.height),
                                         np.asarray(r.K, dtype=np.float64).reshape(3, 3),
                                         np.asarray(r.ego_from_camera, dtype=np.float64).reshape(4, 4))
    return cameras


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
