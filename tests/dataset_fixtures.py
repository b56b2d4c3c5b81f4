"""Shared pieces of the dataset reader/writer tests: one small rendered synthetic scene per test process, and
comparisons of a scene read back from a dataset with the scene it was written from."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from omniscs.geometry import wrap_angle
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene import Scene, SyntheticSource, write_synthetic_scene

#: Six cameras (nuScenes rig), six frames at 10 Hz (two 2 Hz keyframes: 0 and 5), LiDAR; renders in ~3 s.
FIXTURE_SOURCE = SyntheticSource(template="straight", seed=0, n_frames=6, n_cameras=6, width=160, height=90)

_CACHE: dict[str, Path] = {}


def synthetic_store(tmp_path_factory) -> Path:
    """The fixture scene store, rendered once per test process."""
    if "store" not in _CACHE:
        _CACHE["store"] = write_synthetic_scene(FIXTURE_SOURCE, tmp_path_factory.mktemp("synthetic") / "store")
    return _CACHE["store"]


def copy_tree(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def leftovers(parent: Path) -> list[str]:
    """Temporary siblings an atomic write would leave behind if it were not atomic."""
    return sorted(p.name for p in parent.iterdir() if ".tmp-" in p.name)


def match_tracks(original: pd.DataFrame, read: pd.DataFrame, frame_map: dict[int, int], tol: float = 1e-3
                 ) -> dict[int, int]:
    """{read track id: original track id}, matching each read track's first box to the original box of the same
    frame with the nearest centre (readers number tracks in order of first appearance)."""
    mapping = {}
    for tid, g in read.groupby("track_id"):
        first = g.sort_values("frame_idx").iloc[0]
        cands = original[original.frame_idx == frame_map[int(first.frame_idx)]]
        d = np.linalg.norm(cands[["cx", "cy", "cz"]].to_numpy() - first[["cx", "cy", "cz"]].to_numpy(float), axis=1)
        assert len(d) and d.min() < tol, f"read track {tid} matches no original box (nearest {d.min() if len(d) else None} m)"
        mapping[int(tid)] = int(cands.iloc[int(np.argmin(d))].track_id)
    return mapping


def box_errors(original: pd.DataFrame, read: pd.DataFrame, frame_map: dict[int, int], track_map: dict[int, int]
               ) -> dict[str, float]:
    """Largest differences of centre, size, yaw and full orientation over every read box and its original."""
    orig = original.set_index(["frame_idx", "track_id"])
    err = {"centre": 0.0, "size": 0.0, "yaw": 0.0, "rotation": 0.0}
    for row in read.itertuples():
        o = orig.loc[(frame_map[int(row.frame_idx)], track_map[int(row.track_id)])]
        err["centre"] = max(err["centre"], float(np.linalg.norm([row.cx - o.cx, row.cy - o.cy, row.cz - o.cz])))
        err["size"] = max(err["size"], float(np.abs(np.subtract([row.length, row.width, row.height],
                                                                [o.length, o.width, o.height])).max()))
        err["yaw"] = max(err["yaw"], float(abs(wrap_angle(row.yaw - o.yaw))))
        Ra = quat_to_rotmat(np.array([row.qw, row.qx, row.qy, row.qz]))
        Rb = quat_to_rotmat(np.array([o.qw, o.qx, o.qy, o.qz]))
        err["rotation"] = max(err["rotation"], float(np.abs(Ra - Rb).max()))
    return err


def pose_error(a: Scene, b: Scene, frame_map: dict[int, int]) -> float:
    """Largest element difference of world_from_ego between read frames and their originals."""
    return max(float(np.abs(b.world_from_ego(j) - a.world_from_ego(f)).max()) for j, f in frame_map.items())


def image_psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)
