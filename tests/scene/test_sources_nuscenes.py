"""nuScenes: a synthetic scene written as a v1.0 dataroot loads in the devkit, reads back within tolerance,
and broken dataroots fail with one clear error (or, when asked, skip bad frames with a warning)."""
import json
import os

import numpy as np
import pytest

from omniscs.errors import OmniscsError, ValidationError
from omniscs.export import export_scenes
from omniscs.geometry import box_corners_from_pose, invert_transform, make_transform, project
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene import CameraRecord, SceneWriter, load_scene
from omniscs.scene.sources import DatasetSource, SkippedFramesWarning, load_attributes, read_dataset_scene
from tests.dataset_fixtures import (
    box_errors,
    copy_tree,
    image_psnr,
    leftovers,
    match_tracks,
    pose_error,
    synthetic_store,
)

VERSION = "v1.0-mini"
KEYFRAMES = [0, 5]  # 10 Hz log, 2 Hz keyframes
#: Tolerances: tables are JSON with full float precision, so geometry survives to rounding.
GEOMETRY_TOL = 1e-9
LIDAR_TOL_M = 1e-4  # float32 points moved to the sensor frame and back
JPEG_MIN_PSNR_DB = 32.0  # camera images are JPEG (quality 95)
JPEG_MAX_MEAN_ABS = 4.0


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    return load_scene(synthetic_store(tmp_path_factory))


@pytest.fixture(scope="module")
def dataroot(original, tmp_path_factory):
    # every box of the store, those no sensor captures too: the round trip is checked box for box
    return export_scenes([original.path], "nuscenes", tmp_path_factory.mktemp("nus") / "nuscenes", version=VERSION,
                         keep_unseen=True)


@pytest.fixture(scope="module")
def nusc(dataroot):
    from nuscenes.nuscenes import NuScenes

    return NuScenes(version=VERSION, dataroot=str(dataroot), verbose=False)


@pytest.fixture(scope="module")
def read(dataroot, tmp_path_factory):
    return load_scene(read_dataset_scene(DatasetSource("nuscenes", str(dataroot)), tmp_path_factory.mktemp("r") / "s"))


def test_devkit_loads_all_13_tables_with_consistent_tokens(nusc, original):
    n_sensors = len(original.camera_names) + 1
    assert len(nusc.scene) == 1 and len(nusc.log) == 1 and len(nusc.map) == 1
    assert len(nusc.sample) == len(KEYFRAMES)
    assert len(nusc.sample_data) == original.n_frames * n_sensors == len(nusc.ego_pose)
    assert len(nusc.calibrated_sensor) == n_sensors == len(nusc.sensor)
    on_keys = original.boxes[original.boxes.frame_idx.isin(KEYFRAMES)]
    assert len(nusc.sample_annotation) == len(on_keys)
    assert len(nusc.instance) == on_keys.track_id.nunique()
    assert len(nusc.category) == 23 and len(nusc.attribute) == 8 and len(nusc.visibility) == 4
    sample = nusc.get("sample", nusc.scene[0]["first_sample_token"])
    assert set(sample["data"]) == {*original.camera_names, "LIDAR_TOP"}
    sweeps = [sd for sd in nusc.sample_data if not sd["is_key_frame"]]
    assert len(sweeps) == (original.n_frames - len(KEYFRAMES)) * n_sensors
    assert all(sd["filename"].startswith("sweeps/") for sd in sweeps)
    for inst in nusc.instance:  # annotation chains run first -> last with nbr_annotations links
        token, n = inst["first_annotation_token"], 0
        while token:
            n += 1
            last, token = token, nusc.get("sample_annotation", token)["next"]
        assert n == inst["nbr_annotations"] and last == inst["last_annotation_token"]


def test_devkit_box_projections_agree_with_the_scene_store(nusc, original):
    from nuscenes.utils.geometry_utils import BoxVisibility, view_points

    checked = 0
    for f, sample in zip(KEYFRAMES, nusc.sample):
        for cam in original.camera_names:
            _, boxes, K = nusc.get_sample_data(sample["data"][cam], box_vis_level=BoxVisibility.ANY)
            cam_from_world = invert_transform(original.world_from_camera(cam, f))
            ours = original.boxes_at(f)
            for box in boxes:
                centres = []
                for row in ours.itertuples():
                    pose = make_transform(quat_to_rotmat(np.array([row.qw, row.qx, row.qy, row.qz])), [row.cx, row.cy, row.cz])
                    centres.append((np.linalg.norm((cam_from_world @ pose)[:3, 3] - box.center), pose, row))
                dist, pose, row = min(centres, key=lambda c: c[0])
                assert dist < 1e-6
                corners = box_corners_from_pose(cam_from_world @ pose, [row.length, row.width, row.height])
                devkit_corners = box.corners().T  # [8, 3] camera frame
                front = corners[:, 2] > 0.1
                uv, _, _ = project(corners[front], K)
                devkit_uv = view_points(devkit_corners[devkit_corners[:, 2] > 0.1].T, K, normalize=True)[:2].T
                assert len(uv) == len(devkit_uv)
                gap = np.abs(np.sort(uv, axis=0) - np.sort(devkit_uv, axis=0)).max()
                assert gap < 1e-6, f"{cam} frame {f}: devkit and store projections differ by {gap} px"
                checked += 1
    assert checked >= 10


def test_round_trip_keeps_poses_cameras_boxes_timestamps_and_images(original, read):
    frame_map = {j: f for j, f in enumerate(KEYFRAMES)}
    assert read.n_frames == len(KEYFRAMES)
    assert read.frames.timestamp_us.tolist() == original.frames.timestamp_us.iloc[KEYFRAMES].tolist()
    assert pose_error(original, read, frame_map) < GEOMETRY_TOL
    assert read.camera_names == ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                                 "CAM_BACK_RIGHT"]
    for cam in original.camera_names:
        assert np.abs(read.intrinsics(cam) - original.intrinsics(cam)).max() < GEOMETRY_TOL
        assert np.abs(read.ego_from_camera(cam) - original.ego_from_camera(cam)).max() < GEOMETRY_TOL
        assert read.image_size(cam) == original.image_size(cam)
        for j, f in frame_map.items():
            a, b = original.image(cam, f), read.image(cam, j)
            assert image_psnr(a, b) > JPEG_MIN_PSNR_DB
            assert np.abs(a.astype(float) - b.astype(float)).mean() < JPEG_MAX_MEAN_ABS
    expected = original.boxes[original.boxes.frame_idx.isin(KEYFRAMES)]
    assert len(read.boxes) == len(expected)
    tracks = match_tracks(original.boxes, read.boxes, frame_map)
    err = box_errors(original.boxes, read.boxes, frame_map, tracks)
    assert max(err.values()) < GEOMETRY_TOL, err
    cats = read.boxes.assign(orig=read.boxes.track_id.map(tracks)).drop_duplicates("track_id")
    orig_cat = original.boxes.drop_duplicates("track_id").set_index("track_id").category
    assert (cats.category.to_numpy() == orig_cat.loc[cats.orig].to_numpy()).all()
    assert set(read.boxes.source_category) <= {"vehicle.car", "vehicle.truck", "vehicle.construction",
                                               "movable_object.trafficcone", "movable_object.barrier",
                                               "movable_object.debris"}
    for j, f in frame_map.items():
        a, b = original.lidar(f), read.lidar(j)
        assert a.shape == b.shape and np.abs(a[:, :3] - b[:, :3]).max() < LIDAR_TOL_M
        assert np.array_equal(a[:, 3], b[:, 3])
    assert read.manifest["global_from_world"] == np.eye(4).reshape(16).tolist()
    attrs = load_attributes(read)
    assert {"instance_token", "annotation_token", "attribute", "visibility"} <= set(attrs.name)


def test_sweeps_mode_reads_every_frame_with_annotations_interpolated_like_the_devkit(dataroot, nusc, original, tmp_path):
    store = load_scene(read_dataset_scene(DatasetSource("nuscenes", str(dataroot), sweeps=True), tmp_path / "s"))
    assert store.n_frames == original.n_frames
    assert store.frames.timestamp_us.tolist() == original.frames.timestamp_us.tolist()
    frame_map = {f: f for f in range(original.n_frames)}
    assert pose_error(original, store, frame_map) < GEOMETRY_TOL
    tracks = match_tracks(original.boxes, store.boxes, frame_map)
    err = box_errors(original.boxes, store.boxes, frame_map, tracks)
    assert err["centre"] < 0.05 and err["yaw"] < 0.01, err  # the fixture's agents move nearly uniformly
    instance_of = load_attributes(store).query("name == 'instance_token'")
    instance_of = {(r.frame_idx, r.track_id): r.value for r in instance_of.itertuples()}
    sweep = next(sd for sd in nusc.sample_data if sd["channel"] == "LIDAR_TOP" and not sd["is_key_frame"]
                 and sd["timestamp"] == original.frames.timestamp_us.iloc[2])
    prev_instances = {nusc.get("sample_annotation", a)["instance_token"] for a in nusc.sample[0]["anns"]}
    ours = store.boxes_at(2)
    compared = 0
    for box in nusc.get_boxes(sweep["token"]):
        instance = nusc.get("sample_annotation", box.token)["instance_token"]
        if instance not in prev_instances:
            continue
        row = next(r for r in ours.itertuples() if instance_of[(2, r.track_id)] == instance)
        assert np.abs(np.array([row.cx, row.cy, row.cz]) - box.center).max() < 1e-9
        compared += 1
    assert compared > 5


def test_reading_re_origins_at_the_first_pose_and_keeps_the_global_frame_for_writers(tmp_path):
    """A log whose global frame is offset and turned reads back into the same world, and the offset is kept."""
    global_from_world = make_transform(quat_to_rotmat(np.array([np.cos(0.35), 0, 0, np.sin(0.35)])), [612.5, 1641.2, 3.0])
    with SceneWriter(tmp_path / "store", "offset", {"kind": "test"}) as w:
        w.set_frames(np.arange(3) * 500_000, np.stack([make_transform(np.eye(3), [2.0 * f, 0.0, 0.0]) for f in range(3)]))
        K = np.array([[50.0, 0, 32], [0, 50.0, 18], [0, 0, 1]])
        mount = np.array([[0, 0, 1, 1.5], [-1, 0, 0, 0], [0, -1, 0, 1.6], [0, 0, 0, 1.0]])
        w.set_cameras([CameraRecord("CAM_FRONT", 64, 36, K, mount)])
        w.set_boxes([dict(frame_idx=f, track_id=7, category="car", source_category="sedan", cx=10.0 + f, cy=2.0,
                          cz=0.8, length=4.5, width=1.9, height=1.5, yaw=0.3) for f in range(3)])
        for f in range(3):
            w.write_image("CAM_FRONT", f, np.full((36, 64, 3), 90, np.uint8))
        w.set_extra(global_from_world=global_from_world.reshape(16).tolist(), location="boston-seaport")
    root = export_scenes([tmp_path / "store"], "nuscenes", tmp_path / "nus", version=VERSION, keyframe_every=1)
    poses = json.loads((root / VERSION / "ego_pose.json").read_text())
    assert np.allclose(poses[0]["translation"], [612.5, 1641.2, 3.0])
    store = load_scene(read_dataset_scene(DatasetSource("nuscenes", str(root)), tmp_path / "read"))
    assert np.abs(store.world_from_ego_all - load_scene(tmp_path / "store").world_from_ego_all).max() < GEOMETRY_TOL
    assert np.allclose(np.reshape(store.manifest["global_from_world"], (4, 4)), global_from_world, atol=GEOMETRY_TOL)
    assert store.manifest["location"] == "boston-seaport" and not store.has_lidar
    assert np.allclose(store.boxes.cx, [10.0, 11.0, 12.0]) and np.allclose(store.boxes.yaw, 0.3)


# ----------------------------------------------------------------------------- bad input
def _break_table(root, table, edit):
    path = root / VERSION / f"{table}.json"
    rows = json.loads(path.read_text())
    edit(rows)
    path.write_text(json.dumps(rows))


def _keyframe_file(root, channel, frame_pos):
    rows = json.loads((root / VERSION / "sample_data.json").read_text())
    cs = {c["token"]: c["sensor_token"] for c in json.loads((root / VERSION / "calibrated_sensor.json").read_text())}
    sensors = {s["token"]: s["channel"] for s in json.loads((root / VERSION / "sensor.json").read_text())}
    keys = sorted((r for r in rows if r["is_key_frame"] and sensors[cs[r["calibrated_sensor_token"]]] == channel),
                  key=lambda r: r["timestamp"])
    return root / keys[frame_pos]["filename"]


def _zero_size(rows):
    rows[0]["size"] = [0.0, 4.0, 1.5]


BREAKAGES = {
    "missing table": (lambda root: (root / VERSION / "sample_annotation.json").unlink(),
                      "sample_annotation.json: nuScenes table 'sample_annotation' is missing", False),
    "missing image": (lambda root: _keyframe_file(root, "CAM_BACK", 1).unlink(), "image file is missing", True),
    "truncated lidar": (lambda root: _truncate(_keyframe_file(root, "LIDAR_TOP", 0)), "LiDAR file is truncated", True),
    "zero-size box": (lambda root: _break_table(root, "sample_annotation", _zero_size),
                      "field size .* must be three positive numbers", True),
    "corrupt table": (lambda root: (root / VERSION / "sample.json").write_text('[{"token": '),
                      "sample.json is not valid JSON", False),
    "table nested 100,000 deep": (lambda root: (root / VERSION / "sample.json").write_text("[" * 100_000),
                                  "sample.json is nested more than 256 deep", False),
    "table is a FIFO": (lambda root: _fifo(root / VERSION / "sample.json"),
                        "sample.json: nuScenes table 'sample' is not a regular file", False),
    "sample chain loops": (lambda root: _break_table(root, "sample", _loop_chain),
                           "sample chain of scene .* loops at", False),
    "dangling token": (lambda root: _break_table(root, "sample_annotation",
                                                 lambda rows: rows[0].update(instance_token="f" * 32)),
                       "tables are inconsistent", False),
}


def _fifo(path):
    path.unlink()
    os.mkfifo(path)


def _loop_chain(rows):
    """The last sample of the scene points back at its second one."""
    rows[-1]["next"] = rows[1]["token"]


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[:-7])


@pytest.mark.parametrize("case", list(BREAKAGES))
def test_a_broken_dataroot_fails_with_one_clear_error_and_writes_nothing(case, dataroot, tmp_path):
    root = copy_tree(dataroot, tmp_path / "nus")
    breakage, message, _ = BREAKAGES[case]
    breakage(root)
    with pytest.raises(ValidationError, match=message):
        read_dataset_scene(DatasetSource("nuscenes", str(root)), tmp_path / "out" / "store")
    assert not (tmp_path / "out" / "store").exists()
    assert not (tmp_path / "out").exists() or not leftovers(tmp_path / "out")


@pytest.mark.parametrize("case", [c for c, (_, _, per_frame) in BREAKAGES.items() if per_frame])
def test_skip_bad_frames_leaves_the_bad_frame_out_with_a_warning_and_a_count(case, dataroot, tmp_path):
    root = copy_tree(dataroot, tmp_path / "nus")
    BREAKAGES[case][0](root)
    with pytest.warns(SkippedFramesWarning, match="skipped 1 of 2 frames"):
        out = read_dataset_scene(DatasetSource("nuscenes", str(root), skip_bad_frames=True), tmp_path / "store")
    store = load_scene(out)
    assert store.n_frames == 1 and len(store.manifest["skipped_frames"]) == 1


def test_an_unknown_camera_is_refused_by_name(dataroot, tmp_path):
    with pytest.raises(OmniscsError, match=r"unknown camera\(s\) \['CAM_NOPE'\].*CAM_FRONT"):
        read_dataset_scene(DatasetSource("nuscenes", str(dataroot), cameras=("CAM_NOPE",)), tmp_path / "s")
    assert not (tmp_path / "s").exists()


def test_a_chosen_subset_of_cameras_is_read(dataroot, tmp_path):
    store = load_scene(read_dataset_scene(DatasetSource("nuscenes", str(dataroot), cameras=("CAM_BACK", "CAM_FRONT")),
                                          tmp_path / "s"))
    assert store.camera_names == ["CAM_FRONT", "CAM_BACK"]
