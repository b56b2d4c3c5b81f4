"""KITTI tracking: a synthetic scene written as a sequence reads back within tolerance (poses through OXTS and the
Mercator projection, boxes through the rectified camera frame), and broken sequences fail clearly."""
import numpy as np
import pytest

from omniscs.errors import OmniscsError, ValidationError
from omniscs.export import export_scenes
from omniscs.geometry import invert_transform, project
from omniscs.scene import load_scene
from omniscs.scene.sources import DatasetSource, SkippedFramesWarning, load_attributes, read_dataset_scene
from omniscs.scene.sources.kitti import mercator_scale, oxts_to_pose, pose_to_oxts_geo
from tests.dataset_fixtures import box_errors, copy_tree, leftovers, pose_error, synthetic_store

#: Tolerances: poses go through lat/lon (full precision) and the Mercator projection; labels have 6 decimals.
POSE_TOL = 1e-6
CALIB_TOL = 1e-9  # calibration is written with 13 significant digits
BOX_CENTRE_TOL_M = 1e-5
BOX_ANGLE_TOL_RAD = 1e-5
LIDAR_TOL_M = 1e-4
#: Every box at least this far in front of CAM_FRONT whose centre projects into the image must be labelled.
SURELY_VISIBLE_DEPTH_M = 2.0


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    return load_scene(synthetic_store(tmp_path_factory))


@pytest.fixture(scope="module")
def dataroot(original, tmp_path_factory):
    return export_scenes([original.path], "kitti", tmp_path_factory.mktemp("kitti") / "kitti")


@pytest.fixture(scope="module")
def read(dataroot, tmp_path_factory):
    return load_scene(read_dataset_scene(DatasetSource("kitti", str(dataroot)), tmp_path_factory.mktemp("r") / "s"))


def test_the_writer_lays_out_a_kitti_tracking_sequence(dataroot, original):
    base = dataroot / "training"
    assert sorted(p.name for p in base.iterdir()) == ["calib", "image_02", "label_02", "oxts", "velodyne"]
    assert len(list((base / "image_02" / "0000").glob("*.png"))) == original.n_frames
    assert (base / "velodyne" / "0000" / "000005.bin").stat().st_size % 16 == 0
    oxts = (base / "oxts" / "0000.txt").read_text().splitlines()
    assert len(oxts) == original.n_frames and all(len(line.split()) == 30 for line in oxts)
    calib = dict(line.split(" ", 1) for line in (base / "calib" / "0000.txt").read_text().splitlines())
    assert set(calib) == {"P0:", "P1:", "P2:", "P3:", "R_rect", "Tr_velo_cam", "Tr_imu_velo"}
    labels = [line.split() for line in (base / "label_02" / "0000.txt").read_text().splitlines()]
    assert labels and all(len(fields) == 17 for fields in labels)
    assert {fields[2] for fields in labels} <= {"Car", "Van", "Truck", "construction_vehicle", "traffic_cone",
                                                "barrier", "debris"}


def test_mercator_projection_inverts_exactly():
    scale = mercator_scale(49.0)
    oxts = np.array([49.0123, 8.4321, 117.5, 0.01, -0.02, 2.9] + [0.0] * 24)
    geo = pose_to_oxts_geo(oxts_to_pose(oxts, scale), scale)
    assert np.allclose(geo, oxts[:6], atol=1e-12)


def test_round_trip_keeps_poses_cameras_boxes_timestamps_and_images(original, read):
    frame_map = {f: f for f in range(original.n_frames)}
    assert read.frames.timestamp_us.tolist() == original.frames.timestamp_us.tolist()  # 10 Hz from 0
    assert pose_error(original, read, frame_map) < POSE_TOL
    assert read.camera_names == ["CAM_FRONT"]
    assert np.abs(read.intrinsics("CAM_FRONT") - original.intrinsics("CAM_FRONT")).max() < CALIB_TOL
    assert np.abs(read.ego_from_camera("CAM_FRONT") - original.ego_from_camera("CAM_FRONT")).max() < CALIB_TOL
    for f in range(original.n_frames):
        assert np.array_equal(read.image("CAM_FRONT", f), original.image("CAM_FRONT", f))  # PNG: lossless
        a, b = original.lidar(f), read.lidar(f)
        assert a.shape == b.shape and np.abs(a - b).max() < LIDAR_TOL_M * 255
        assert np.abs(a[:, :3] - b[:, :3]).max() < LIDAR_TOL_M
    # KITTI keeps track ids and labels what CAM_FRONT sees
    tracks = {t: t for t in read.boxes.track_id.unique()}
    err = box_errors(original.boxes, read.boxes, frame_map, tracks)
    assert err["centre"] < BOX_CENTRE_TOL_M and err["size"] < BOX_CENTRE_TOL_M and err["yaw"] < BOX_ANGLE_TOL_RAD, err
    merged = read.boxes.merge(original.boxes, on=["frame_idx", "track_id"], suffixes=("", "_orig"))
    assert (merged.category == merged.category_orig).all()
    cam = original.camera("CAM_FRONT")
    read_keys = set(zip(read.boxes.frame_idx, read.boxes.track_id))
    surely_visible = 0
    for row in original.boxes.itertuples():
        centre = invert_transform(original.world_from_camera("CAM_FRONT", row.frame_idx)) @ [row.cx, row.cy, row.cz, 1]
        uv, _, _ = project(centre[None, :3], cam.K)
        if centre[2] > SURELY_VISIBLE_DEPTH_M and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height:
            surely_visible += 1
            assert (row.frame_idx, row.track_id) in read_keys
    assert surely_visible > 10 and len(read.boxes) < len(original.boxes)  # boxes behind the camera are not labels
    attrs = load_attributes(read)
    assert {"truncated", "occluded", "alpha", "bbox_2d"} <= set(attrs.name)


def test_dont_care_regions_and_flags_are_kept_as_attributes(dataroot, tmp_path):
    root = copy_tree(dataroot, tmp_path / "kitti")
    labels = root / "training" / "label_02" / "0000.txt"
    labels.write_text(labels.read_text() + "2 -1 DontCare -1 -1 -10 10.0 20.0 30.0 40.0 -1 -1 -1 -1000 -1000 -1000 -10\n")
    store = load_scene(read_dataset_scene(DatasetSource("kitti", str(root)), tmp_path / "s"))
    attrs = load_attributes(store)
    dont_care = attrs[attrs.name == "dont_care_bbox"]
    assert dont_care.frame_idx.tolist() == [2] and dont_care.track_id.tolist() == [-1]
    assert dont_care.value.tolist() == ["[10.0,20.0,30.0,40.0]"] and dont_care.camera.tolist() == ["CAM_FRONT"]
    out = export_scenes([store.path], "kitti", tmp_path / "again")  # and written back
    assert "2 -1 DontCare" in (out / "training" / "label_02" / "0000.txt").read_text()


# ----------------------------------------------------------------------------- bad input
def _base(root):
    return root / "training"


def _truncate(path):
    path.write_bytes(path.read_bytes()[:-5])


def _short_p2(path):
    lines = [("P2: 1 2 3" if line.startswith("P2:") else line) for line in path.read_text().splitlines()]
    path.write_text("\n".join(lines) + "\n")


def _zero_dimensions(root):
    path = _base(root) / "label_02" / "0000.txt"
    lines = path.read_text().splitlines()
    fields = lines[0].split()
    fields[10:13] = ["0.0", "1.8", "4.2"]
    path.write_text("\n".join([" ".join(fields)] + lines[1:]) + "\n")
    return int(fields[0])


BREAKAGES = {
    "missing calibration": (lambda root: (_base(root) / "calib" / "0000.txt").unlink(),
                            "calib/0000.txt: KITTI calibration file is missing", False),
    "missing oxts": (lambda root: (_base(root) / "oxts" / "0000.txt").unlink(), "OXTS pose file is missing", False),
    "missing labels": (lambda root: (_base(root) / "label_02" / "0000.txt").unlink(), "KITTI label file is missing",
                       False),
    "missing image": (lambda root: (_base(root) / "image_02" / "0000" / "000003.png").unlink(),
                      "000003.png: image file is missing", True),
    "truncated lidar": (lambda root: _truncate(_base(root) / "velodyne" / "0000" / "000004.bin"),
                        "000004.bin: LiDAR file is truncated", True),
    "zero-size box": (_zero_dimensions, "has zero or negative dimensions", True),
    "broken calibration": (lambda root: _short_p2(_base(root) / "calib" / "0000.txt"), "field P2 has 3 values", False),
}


@pytest.mark.parametrize("case", list(BREAKAGES))
def test_a_broken_sequence_fails_with_one_clear_error_and_writes_nothing(case, dataroot, tmp_path):
    root = copy_tree(dataroot, tmp_path / "kitti")
    BREAKAGES[case][0](root)
    with pytest.raises(ValidationError, match=BREAKAGES[case][1]):
        read_dataset_scene(DatasetSource("kitti", str(root)), tmp_path / "out" / "store")
    assert not (tmp_path / "out" / "store").exists()
    assert not (tmp_path / "out").exists() or not leftovers(tmp_path / "out")


@pytest.mark.parametrize("case", [c for c, (_, _, per_frame) in BREAKAGES.items() if per_frame])
def test_skip_bad_frames_leaves_the_bad_frame_out_with_a_warning_and_a_count(case, dataroot, original, tmp_path):
    root = copy_tree(dataroot, tmp_path / "kitti")
    BREAKAGES[case][0](root)
    with pytest.warns(SkippedFramesWarning, match=f"skipped 1 of {original.n_frames} frames"):
        out = read_dataset_scene(DatasetSource("kitti", str(root), skip_bad_frames=True), tmp_path / "store")
    store = load_scene(out)
    assert store.n_frames == original.n_frames - 1
    skipped = int(store.manifest["skipped_frames"][0]["frame"])
    kept = [f for f in range(original.n_frames) if f != skipped]
    assert store.frames.timestamp_us.tolist() == original.frames.timestamp_us.iloc[kept].tolist()


def test_an_unknown_camera_is_refused_by_name(dataroot, tmp_path):
    with pytest.raises(OmniscsError, match=r"unknown camera\(s\) \['CAM_FRONT_RIGHT_STEREO'\]"):
        read_dataset_scene(DatasetSource("kitti", str(dataroot), cameras=("image_03",)), tmp_path / "s")
    assert not (tmp_path / "s").exists()
