"""The share of boxes near the ego that consumers keep (LiDAR points for nuScenes' evaluation, valid_flag for
UniAD), counted from hand-written tables and pickles whose answer is known."""
from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from omniscs.errors import OmniscsError
from omniscs.export.coverage import nuscenes_point_coverage, uniad_valid_coverage

VERSION = "v1.0-mini"


def _write_tables(root, annotations, ego_xy=(100.0, 200.0)):
    """One keyframe sample with a LiDAR (ego at ``ego_xy``) and a camera sample_data whose ego pose is elsewhere
    (the LiDAR's pose decides); ``annotations``: (x, y offset from the ego, num_lidar_pts, num_radar_pts)."""
    tables = root / VERSION
    tables.mkdir(parents=True)
    rows = {
        "sensor": [{"token": "s-lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
                   {"token": "s-cam", "channel": "CAM_FRONT", "modality": "camera"}],
        "calibrated_sensor": [{"token": "c-lidar", "sensor_token": "s-lidar"},
                              {"token": "c-cam", "sensor_token": "s-cam"}],
        "ego_pose": [{"token": "e-lidar", "translation": [ego_xy[0], ego_xy[1], 0.0]},
                     {"token": "e-cam", "translation": [ego_xy[0] + 30.0, ego_xy[1], 0.0]}],
        "sample_data": [{"token": "sd-cam", "sample_token": "k0", "ego_pose_token": "e-cam",
                         "calibrated_sensor_token": "c-cam", "is_key_frame": True},
                        {"token": "sd-lidar", "sample_token": "k0", "ego_pose_token": "e-lidar",
                         "calibrated_sensor_token": "c-lidar", "is_key_frame": True}],
        "sample_annotation": [{"token": f"a{i}", "sample_token": "k0",
                               "translation": [ego_xy[0] + dx, ego_xy[1] + dy, 1.0],
                               "num_lidar_pts": lidar, "num_radar_pts": radar}
                              for i, (dx, dy, lidar, radar) in enumerate(annotations)],
    }
    for name, table in rows.items():
        (tables / f"{name}.json").write_text(json.dumps(table))
    return root


def test_nuscenes_coverage_counts_boxes_near_the_lidar_ego_pose_with_points(tmp_path):
    root = _write_tables(tmp_path, [(10.0, 0.0, 5, 0), (-30.0, 30.0, 0, 0), (0.0, -49.9, 0, 2), (40.0, 40.0, 9, 0),
                                    (-5.0, 0.0, 0, 0), (60.0, 0.0, 3, 0)])
    coverage = nuscenes_point_coverage(root, VERSION)
    # within 50 m: 10 m, 42.4 m, 49.9 m, 5 m (56.6 m and 60 m are not); with points: 10 m (lidar), 49.9 m (radar)
    assert (coverage.within, coverage.kept) == (4, 2) and coverage.share == 0.5
    assert nuscenes_point_coverage(root, VERSION, max_distance_m=70.0).within == 6
    assert nuscenes_point_coverage(root, VERSION, max_distance_m=1.0).share is None


def test_uniad_coverage_counts_valid_flags_near_the_ego_through_the_lidar_mount(tmp_path):
    yaw = np.pi / 2  # the LiDAR turned 90° about z: ego (x, y) = (-y, x) + the mount's offset
    q = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
    boxes = np.array([[0.0, -49.5, 0.0, 2, 4, 1.5, 0.0],   # ego (50.5, 0): out
                      [0.0, 48.0, 0.0, 2, 4, 1.5, 0.0],    # ego (-47, 0): in
                      [3.0, 4.0, 0.0, 2, 4, 1.5, 0.0]])    # ego (-3, 3): in
    infos = [{"gt_boxes": boxes, "valid_flag": np.array([True, True, False]), "lidar2ego_rotation": q,
              "lidar2ego_translation": [1.0, 0.0, 1.84]}]
    (tmp_path / "infos").mkdir()
    for split in ("train", "val"):
        with open(tmp_path / "infos" / f"nuscenes_infos_temporal_{split}.pkl", "wb") as f:
            pickle.dump({"infos": infos if split == "train" else [], "metadata": {}}, f)
    coverage = uniad_valid_coverage(tmp_path / "infos")
    assert (coverage.within, coverage.kept) == (2, 1)
    assert uniad_valid_coverage(tmp_path / "infos" / "nuscenes_infos_temporal_train.pkl", 60.0).to_dict() == {
        "max_distance_m": 60.0, "within": 3, "kept": 2, "share": 2 / 3}


def test_a_folder_that_is_not_an_export_is_one_clear_error(tmp_path):
    with pytest.raises(OmniscsError, match="nuScenes table"):
        nuscenes_point_coverage(tmp_path, VERSION)
    with pytest.raises(OmniscsError, match="UniAD info pickle"):
        uniad_valid_coverage(tmp_path)
