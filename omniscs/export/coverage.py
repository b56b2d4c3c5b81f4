"""How many boxes near the ego an export's consumers keep: nuScenes' detection evaluation drops annotations without
LiDAR (or radar) points, UniAD's training drops boxes whose ``valid_flag`` is false. Read from the written files
only, so it measures what a consumer would see (the dataset card reports it)."""
from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.quaternions import quat_to_rotmat
from omniscs.untrusted import MAX_TABLE_BYTES, read_json

#: nuScenes' detection classes reach at most 50 m (car, truck, bus, ...): the boxes its evaluation can keep at all.
NEAR_EGO_M = 50.0


@dataclass(frozen=True)
class Coverage:
    """Boxes within ``max_distance_m`` of the ego (horizontal distance of the box centre from the ego origin) and how
    many of them a consumer keeps."""

    max_distance_m: float
    """The radius around the ego (metres)."""
    within: int
    """Boxes whose centre lies within the radius."""
    kept: int
    """Of them, those with at least one LiDAR or radar point (nuScenes) or ``valid_flag`` set (UniAD)."""

    @property
    def share(self) -> float | None:
        """kept / within; None when no box lies within the radius."""
        return self.kept / self.within if self.within else None

    def to_dict(self) -> dict:
        return {"max_distance_m": self.max_distance_m, "within": self.within, "kept": self.kept, "share": self.share}


def nuscenes_point_coverage(dataroot: str | Path, version: str, max_distance_m: float = NEAR_EGO_M) -> Coverage:
    """Keyframe annotations of a nuScenes dataroot within ``max_distance_m`` of the ego pose of their sample's LiDAR
    (a camera's where a sample has none), and how many have ``num_lidar_pts + num_radar_pts > 0``."""
    tables = Path(dataroot) / version
    names = ("sample_annotation", "sample_data", "ego_pose", "calibrated_sensor", "sensor")
    missing = [n for n in names if not (tables / f"{n}.json").exists()]
    if missing:
        raise OmniscsError(f"{tables} lacks the nuScenes table(s) {missing}; point at a dataroot and its version")
    rows = {n: read_json(tables / f"{n}.json", "give the dataroot's own table (a list of records)", expect=list,
                         max_bytes=MAX_TABLE_BYTES, what="nuScenes table") for n in names}
    modality = {s["token"]: s["modality"] for s in rows["sensor"]}
    sensor_of = {c["token"]: modality[c["sensor_token"]] for c in rows["calibrated_sensor"]}
    ego_xy = {e["token"]: np.asarray(e["translation"][:2], dtype=np.float64) for e in rows["ego_pose"]}
    pose_of_sample: dict[str, np.ndarray] = {}
    for sd in rows["sample_data"]:
        if not sd["is_key_frame"]:
            continue
        lidar = sensor_of[sd["calibrated_sensor_token"]] == "lidar"
        if lidar or sd["sample_token"] not in pose_of_sample:
            pose_of_sample[sd["sample_token"]] = ego_xy[sd["ego_pose_token"]]
    within = kept = 0
    for ann in rows["sample_annotation"]:
        ego = pose_of_sample.get(ann["sample_token"])
        if ego is None:
            continue
        if np.linalg.norm(np.asarray(ann["translation"][:2], dtype=np.float64) - ego) <= max_distance_m:
            within += 1
            kept += int(ann.get("num_lidar_pts", 0)) + int(ann.get("num_radar_pts", 0)) > 0
    return Coverage(float(max_distance_m), within, kept)


def uniad_valid_coverage(infos: str | Path, max_distance_m: float = NEAR_EGO_M) -> Coverage:
    """Boxes of UniAD info pickles (one ``.pkl`` or a folder of them, e.g. an export's ``infos/``) within
    ``max_distance_m`` of the ego (centres from the LiDAR frame into the ego's by each info's lidar2ego), and how
    many have ``valid_flag`` set."""
    path = Path(infos)
    files = sorted(path.glob("*.pkl")) if path.is_dir() else [path]
    if not files or not all(f.is_file() for f in files):
        raise OmniscsError(f"no UniAD info pickle at {path}; point at an export's infos/ folder or one .pkl")
    within = kept = 0
    for file in files:
        with open(file, "rb") as f:
            data = pickle.load(f)
        for info in data["infos"]:
            valid = np.asarray(info["valid_flag"], dtype=bool).reshape(-1)
            boxes = np.asarray(info["gt_boxes"], dtype=np.float64).reshape(len(valid), -1)  # centre x, y, z first
            R = quat_to_rotmat(np.asarray(info["lidar2ego_rotation"], dtype=np.float64))
            centres = boxes[:, :3] @ R.T + np.asarray(info["lidar2ego_translation"], dtype=np.float64)
            near = np.linalg.norm(centres[:, :2], axis=1) <= max_distance_m
            within += int(near.sum())
            kept += int(valid[near].sum())
    return Coverage(float(max_distance_m), within, kept)
