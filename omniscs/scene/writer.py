"""Writing a scene store: ``SceneWriter`` fills a temporary folder (tables, images, LiDAR, ground truth) that
becomes the store only when whole, with every file's size and sha256 recorded in the manifest; ``store.py``
reads and checks what it writes."""
from __future__ import annotations

import io
import os
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.errors import OmniscsError
from omniscs.ids import check_id
from omniscs.scene.store import (BOX_COLUMNS, BOX_SCHEMA, BOXES, CAMERA_SCHEMA, CAMERAS, FILES, FRAME_SCHEMA, FRAMES,
                                 MANIFEST, MANIFEST_FIELDS, SCHEMA_VERSION, WORLD, CameraRecord, _short, file_sha256,
                                 gt_path, image_path, lidar_path, read_manifest, validate_files, validate_tables)
from omniscs.storage import OWNER_MARKER, atomic_directory, atomic_write_json, content_hash


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
    The manifest records every written file's size and sha256 (``FILES``), so damage is found later.
    """

    def __init__(self, out_dir: str | os.PathLike, scene_id: str, source: dict, overwrite: bool = False):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not overwrite:
            raise OmniscsError(f"{self.out_dir} already exists; choose another --out or pass overwrite")
        self.scene_id = check_id("scene id", scene_id)
        if not isinstance(source, dict):
            raise OmniscsError(f"a scene's source must be a dict; got {_short(source)}")
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
                if isinstance(err, OmniscsError):  # name the store, not its temporary folder
                    raise type(err)(str(err).replace(str(self.tmp), str(self.out_dir))) from None
                raise
        return self._ctx.__exit__(exc_type, exc, tb)

    def _root(self) -> Path:
        if self.tmp is None:
            raise OmniscsError("SceneWriter writes files only inside `with SceneWriter(...) as writer:`")
        return self.tmp

    @staticmethod
    def _target(path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def _write(self, path: Path, data: bytes) -> None:
        try:
            path.write_bytes(data)
        except OSError as exc:
            raise OmniscsError(f"cannot write {self.out_dir / path.relative_to(self.tmp)}: "
                               f"{exc.strerror or exc}") from None

    def set_frames(self, timestamps_us: np.ndarray, world_from_ego: np.ndarray) -> None:
        ts = np.asarray(timestamps_us, dtype=np.int64)
        poses = np.asarray(world_from_ego, dtype=np.float64).reshape(-1, 4, 4)
        if len(ts) != len(poses):
            raise OmniscsError(f"{len(ts)} timestamps but {len(poses)} poses")
        self._frames = pd.DataFrame({"frame_idx": np.arange(len(ts), dtype=np.int32), "timestamp_us": ts,
                                     "world_from_ego": list(poses.reshape(-1, 16))})

    def set_cameras(self, cameras: list[CameraRecord]) -> None:
        names = [c.name for c in cameras]
        for name in names:
            check_id("camera name", name)
        if len(set(names)) != len(names):
            raise OmniscsError(f"camera names must be unique; got {names}")
        self._cameras = {c.name: c for c in cameras}

    def set_boxes(self, boxes: list[dict] | pd.DataFrame) -> None:
        self._boxes = boxes_frame(boxes)

    def set_extra(self, **fields) -> None:
        """Extra manifest fields (e.g. the world's template and lighting)."""
        reserved = [k for k in fields if k in MANIFEST_FIELDS or k == FILES]
        if reserved:
            raise OmniscsError(f"extra manifest fields {reserved} would replace the store's own")
        self._extra.update(fields)

    def write_image(self, camera: str, frame_idx: int, rgb: np.ndarray) -> None:
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise OmniscsError(f"image for {camera}/{frame_idx} must be uint8 [H, W, 3]; got {rgb.dtype} {rgb.shape}")
        cam = self._cameras.get(camera)
        if cam is not None and rgb.shape[:2] != (cam.height, cam.width):
            raise OmniscsError(f"image for {camera}/{frame_idx} is {rgb.shape[1]}x{rgb.shape[0]} but the camera is "
                               f"{cam.width}x{cam.height}")
        path = self._target(image_path(self._root(), check_id("camera name", camera), frame_idx))
        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if not ok:
            raise OmniscsError(f"could not encode the image for {camera}/{frame_idx} as PNG")
        self._write(path, png.tobytes())

    def write_lidar(self, frame_idx: int, points: np.ndarray) -> None:
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 4)
        if not np.all(np.isfinite(pts)):
            raise OmniscsError(f"LiDAR points of frame {frame_idx} have NaN or Inf values")
        path = self._target(lidar_path(self._root(), frame_idx))
        buf = io.BytesIO()
        np.save(buf, pts)
        self._write(path, buf.getvalue())
        self._has_lidar = True

    def write_gt(self, camera: str, frame_idx: int, depth: np.ndarray, instance: np.ndarray,
                 semantic: np.ndarray) -> None:
        path = self._target(gt_path(self._root(), check_id("camera name", camera), frame_idx))
        buf = io.BytesIO()
        np.savez_compressed(buf, depth=depth.astype(np.float32), instance=instance.astype(np.int32),
                            semantic=semantic.astype(np.uint8))
        self._write(path, buf.getvalue())
        self._has_gt = True

    def write_world_json(self, text: str) -> None:
        self._write(self._target(self._root() / WORLD), text.encode("utf-8"))

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
            **self._extra,
            "schema_version": SCHEMA_VERSION,
            "scene_id": self.scene_id,
            "source": self.source,
            "cameras": list(self._cameras),
            "n_frames": len(self._frames),
            "has_lidar": self._has_lidar,
            "has_gt": self._has_gt,
            "content_hash": table_hash(self._frames, self._cameras, boxes, self.source),
        }
        validate_tables(self.tmp, manifest, self._frames, self._cameras, boxes)
        validate_files(self.tmp, manifest, len(self._frames), list(self._cameras))
        manifest[FILES] = record_files(self.tmp)
        atomic_write_json(self.tmp / MANIFEST, manifest)
        read_manifest(self.tmp)  # what is written must read back (e.g. extra fields of the wrong type)


def record_files(root: Path) -> dict[str, list]:
    """{relative posix path: [size, sha256]} of every file under ``root`` but the manifest and the owner marker."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in sorted(filenames):
            path = Path(dirpath) / name
            rel = path.relative_to(root).as_posix()
            if rel in (MANIFEST, OWNER_MARKER):
                continue
            out[rel] = [path.stat().st_size, file_sha256(path)]
    return out


def table_hash(frames: pd.DataFrame, cameras: dict[str, CameraRecord], boxes: pd.DataFrame, source: dict) -> str:
    """Content hash of what defines a scene's geometry: poses, timestamps, cameras, boxes, source."""
    poses = np.stack([np.asarray(m, dtype=np.float64) for m in frames["world_from_ego"]])
    cams = [(c.name, c.width, c.height, np.asarray(c.K, np.float64), np.asarray(c.ego_from_camera, np.float64))
            for c in cameras.values()]
    box_geom = boxes[["frame_idx", "track_id", "cx", "cy", "cz", "length", "width", "height", "yaw"]].to_numpy(np.float64)
    return content_hash(frames["timestamp_us"].to_numpy(np.int64), poses, cams, box_geom,
                        list(boxes["category"]), source)
