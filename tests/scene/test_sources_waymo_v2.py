"""Waymo Open Dataset v2: a synthetic scene written as Parquet components reads back within tolerance (pyarrow
only), LiDAR round-trips through range images, and broken segments fail clearly."""
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy.spatial import cKDTree

from omniscs.errors import OmniscsError, ValidationError
from omniscs.export import export_scenes
from omniscs.geometry import make_transform, rotmat_from_euler
from omniscs.scene import load_scene
from omniscs.scene.sources import DatasetSource, SkippedFramesWarning, load_attributes, read_dataset_scene
from omniscs.export.waymo_v2 import points_to_range_image
from omniscs.scene.sources.waymo_v2 import CAMERA_NAME, LIDAR, LIDAR_BOX, range_image_to_points
from tests.dataset_fixtures import (
    box_errors,
    copy_tree,
    image_psnr,
    leftovers,
    match_tracks,
    pose_error,
    synthetic_store,
)

GEOMETRY_TOL = 1e-9  # poses, calibration and boxes are float64 columns
JPEG_MIN_PSNR_DB = 32.0
#: Waymo's classes: vehicles, pedestrians, cyclists; cones, barriers and debris have no type.
WAYMO_CLASS = {"car": "car", "truck": "car", "bus": "car", "trailer": "car", "construction_vehicle": "car",
               "motorcycle": "car", "pedestrian": "pedestrian", "bicycle": "bicycle"}


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    return load_scene(synthetic_store(tmp_path_factory))


@pytest.fixture(scope="module")
def dataroot(original, tmp_path_factory):
    return export_scenes([original.path], "waymo-v2", tmp_path_factory.mktemp("waymo") / "training")


@pytest.fixture(scope="module")
def read(dataroot, tmp_path_factory):
    return load_scene(read_dataset_scene(DatasetSource("waymo-v2", str(dataroot)), tmp_path_factory.mktemp("r") / "s"))


def _segment(root):
    return next((root / "vehicle_pose").glob("*.parquet")).stem


def test_the_writer_follows_the_published_v2_schema(dataroot):
    seg = _segment(dataroot)
    schema = pq.read_schema(dataroot / "lidar_box" / f"{seg}.parquet")
    assert schema.field("key.segment_context_name").type == pa.string()
    assert schema.field("key.frame_timestamp_micros").type == pa.int64()
    assert schema.field("key.laser_object_id").type == pa.string()
    assert schema.field("[LiDARBoxComponent].box.heading").type == pa.float64()
    assert schema.field("[LiDARBoxComponent].type").type == pa.int8()
    pose = pq.read_schema(dataroot / "vehicle_pose" / f"{seg}.parquet")
    assert pose.field("[VehiclePoseComponent].world_from_vehicle.transform").type == pa.list_(pa.float64(), 16)
    image = pq.read_schema(dataroot / "camera_image" / f"{seg}.parquet")
    assert image.field("key.camera_name").type == pa.int8() and image.field("[CameraImageComponent].image").type == pa.binary()
    calib = pq.read_schema(dataroot / "camera_calibration" / f"{seg}.parquet")
    assert {f"[CameraCalibrationComponent].intrinsic.{k}" for k in ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2",
                                                                     "k3")} <= set(calib.names)
    lidar = pq.read_schema(dataroot / "lidar" / f"{seg}.parquet")
    assert lidar.field("[LiDARComponent].range_image_return1.shape").type == pa.list_(pa.int32(), 3)
    assert (dataroot / ".omniscs").is_file()  # the marker that lets --overwrite replace this export later
    assert {p.name for p in dataroot.iterdir() if p.name != ".omniscs"} == {"vehicle_pose", "camera_calibration", "camera_image", "lidar_box",
                                                   "camera_box", "lidar", "lidar_calibration", "stats"}


def test_round_trip_keeps_poses_cameras_boxes_timestamps_and_images(original, read):
    frame_map = {f: f for f in range(original.n_frames)}
    assert read.frames.timestamp_us.tolist() == original.frames.timestamp_us.tolist()
    assert pose_error(original, read, frame_map) < GEOMETRY_TOL
    assert read.camera_names == ["CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT"]  # Waymo has no rear cameras
    for cam in read.camera_names:
        assert np.abs(read.intrinsics(cam) - original.intrinsics(cam)).max() < GEOMETRY_TOL
        assert np.abs(read.ego_from_camera(cam) - original.ego_from_camera(cam)).max() < GEOMETRY_TOL
        for f in range(original.n_frames):
            assert image_psnr(original.image(cam, f), read.image(cam, f)) > JPEG_MIN_PSNR_DB
    expected = original.boxes[original.boxes.category.isin(WAYMO_CLASS)]
    assert len(read.boxes) == len(expected)
    tracks = match_tracks(expected, read.boxes, frame_map)
    err = box_errors(original.boxes, read.boxes, frame_map, tracks)
    assert err["centre"] < GEOMETRY_TOL and err["size"] < GEOMETRY_TOL and err["yaw"] < GEOMETRY_TOL, err
    orig_cat = original.boxes.drop_duplicates("track_id").set_index("track_id").category
    for tid, g in read.boxes.groupby("track_id"):
        assert set(g.category) == {WAYMO_CLASS[orig_cat[tracks[tid]]]}
    dropped = original.boxes.category.isin(WAYMO_CLASS).eq(False).sum()
    assert read.manifest["dropped_boxes"] == {"TYPE_UNKNOWN": int(dropped)}
    assert set(load_attributes(read).name) >= {"laser_object_id", "speed", "difficulty_level", "camera_box"}


def test_lidar_round_trips_through_range_images_within_half_a_column(original, read):
    """Points are binned to Waymo's fixed column grid: each moves at most range * sin(pi / columns), none is lost."""
    spec = original.world.lidar
    origin = spec.ego_from_lidar[:3, 3]
    for f in range(original.n_frames):
        a, b = original.lidar(f), read.lidar(f)
        assert len(b) == len(a)
        dist, _ = cKDTree(a[:, :3]).query(b[:, :3])
        rng_a, rng_b = (np.linalg.norm(p[:, :3] - origin, axis=1) for p in (a, b))
        assert np.all(dist <= rng_b * np.sin(np.pi / spec.azimuth_steps) + 1e-4)
        assert np.abs(np.sort(rng_a) - np.sort(rng_b)).max() < 1e-4  # ranges are kept exactly
        assert np.abs(np.sort(a[:, 3]) - np.sort(b[:, 3])).max() < 0.01  # intensity 0..255 stored as 0..1


def test_range_image_conversion_is_exact_for_points_on_the_column_grid():
    extrinsic = make_transform(rotmat_from_euler(yaw=0.3), [1.0, 0.2, 2.0])
    width, incl = 64, np.radians(np.linspace(-20.0, 5.0, 8))
    cols = np.arange(0, width, 3)
    az_vehicle = np.pi - 2 * np.pi * (cols + 0.5) / width
    az_sensor = az_vehicle - 0.3
    e = np.repeat(incl[::2], len(cols))
    a = np.tile(az_sensor, len(incl[::2]))
    r = np.linspace(5.0, 40.0, len(e))
    p_sensor = np.stack([np.cos(a) * np.cos(e) * r, np.sin(a) * np.cos(e) * r, np.sin(e) * r], -1)
    p_vehicle = p_sensor @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    points = np.concatenate([p_vehicle, np.full((len(r), 1), 127.5)], 1).astype(np.float32)
    back = range_image_to_points(points_to_range_image(points, extrinsic, incl, width), extrinsic, incl)
    dist, _ = cKDTree(points[:, :3]).query(back[:, :3])
    assert len(back) == len(points) and dist.max() < 1e-4 and np.allclose(back[:, 3], 127.5, atol=1e-3)


# ----------------------------------------------------------------------------- bad input
def _rewrite(root, component, edit):
    path = next((root / component).glob("*.parquet"))
    table = edit(pq.read_table(path))
    pq.write_table(table, path)


def _drop_first_image(table):
    return table.slice(1)


def _set_column(name, value, row=0):
    def edit(table):
        col = table.column(name).to_pylist()
        col[row] = value(col[row]) if callable(value) else value
        i = table.column_names.index(name)
        return table.set_column(i, table.schema.field(i), pa.array(col, type=table.schema.field(i).type))
    return edit


BREAKAGES = {
    "missing table": (lambda root: next((root / "camera_calibration").glob("*.parquet")).unlink(),
                      "Waymo v2 component 'camera_calibration' is missing", False),
    "missing column": (lambda root: _rewrite(root, "lidar_box", lambda t: t.drop(["[LiDARBoxComponent].box.heading"])),
                       r"missing column\(s\) \['\[LiDARBoxComponent\].box.heading'\]", False),
    "missing image": (lambda root: _rewrite(root, "camera_image", _drop_first_image), "has no image for camera", True),
    "truncated lidar": (lambda root: _rewrite(root, "lidar", _set_column(f"{LIDAR}.range_image_return1.values",
                                                                         lambda v: v[:-9])),
                        "range_image_return1 has .* values for shape", True),
    "zero-size box": (lambda root: _rewrite(root, "lidar_box", _set_column(f"{LIDAR_BOX}.box.size.x", 0.0)),
                      r"box.size \[0.0, .*\] must be positive", True),
    "uncalibrated camera": (lambda root: _rewrite(root, "camera_image", _set_column(CAMERA_NAME, 5)),
                            "image of camera 5 which camera_calibration does not list", True),
}


@pytest.mark.parametrize("case", list(BREAKAGES))
def test_a_broken_segment_fails_with_one_clear_error_and_writes_nothing(case, dataroot, tmp_path):
    root = copy_tree(dataroot, tmp_path / "training")
    BREAKAGES[case][0](root)
    with pytest.raises(ValidationError, match=BREAKAGES[case][1]):
        read_dataset_scene(DatasetSource("waymo-v2", str(root)), tmp_path / "out" / "store")
    assert not (tmp_path / "out" / "store").exists()
    assert not (tmp_path / "out").exists() or not leftovers(tmp_path / "out")


@pytest.mark.parametrize("case", [c for c, (_, _, per_frame) in BREAKAGES.items() if per_frame])
def test_skip_bad_frames_leaves_the_bad_frame_out_with_a_warning_and_a_count(case, dataroot, original, tmp_path):
    root = copy_tree(dataroot, tmp_path / "training")
    BREAKAGES[case][0](root)
    with pytest.warns(SkippedFramesWarning, match=f"skipped 1 of {original.n_frames} frames"):
        out = read_dataset_scene(DatasetSource("waymo-v2", str(root), skip_bad_frames=True), tmp_path / "store")
    store = load_scene(out)
    assert store.n_frames == original.n_frames - 1
    assert store.manifest["skipped_frames"][0]["frame"] == str(original.frames.timestamp_us.iloc[0])


def test_an_unknown_camera_is_refused_by_name(dataroot, tmp_path):
    with pytest.raises(OmniscsError, match=r"unknown camera\(s\) \['CAM_BACK'\]"):
        read_dataset_scene(DatasetSource("waymo-v2", str(dataroot), cameras=("CAM_BACK",)), tmp_path / "s")


def test_a_segment_without_lidar_or_boxes_still_reads(dataroot, tmp_path):
    root = copy_tree(dataroot, tmp_path / "training")
    for component in ("lidar", "lidar_calibration", "lidar_box", "camera_box", "stats"):
        for p in (root / component).glob("*.parquet"):
            p.unlink()
    store = load_scene(read_dataset_scene(DatasetSource("waymo-v2", str(root)), tmp_path / "s"))
    assert not store.has_lidar and len(store.boxes) == 0 and store.n_frames == 6  # frames come from vehicle_pose


def test_per_pixel_lidar_poses_move_points_into_the_frame_pose():
    """A pixel fired 1 m further along x (world) than the frame pose lands 1 m further along the vehicle's x."""
    extrinsic = make_transform(np.eye(3), [0.0, 0.0, 2.0])
    incl = np.radians(np.linspace(-10.0, 5.0, 4))
    image = np.full((4, 16, 4), -1.0, np.float32)
    image[1, 3] = [20.0, 0.5, 0.0, -1.0]
    world_from_vehicle = make_transform(rotmat_from_euler(yaw=0.5), [100.0, 50.0, 0.0])
    still = range_image_to_points(image, extrinsic, incl)
    pixel_pose = np.zeros((4, 16, 6))
    pixel_pose[..., 2] = 0.5  # yaw
    pixel_pose[..., 3:] = [100.0 + np.cos(0.5), 50.0 + np.sin(0.5), 0.0]  # 1 m ahead along the heading
    moved = range_image_to_points(image, extrinsic, incl, pixel_pose, world_from_vehicle)
    assert np.allclose(moved[:, :3] - still[:, :3], [[1.0, 0.0, 0.0]], atol=1e-5)


def test_lens_distortion_is_removed_from_images_and_recorded(dataroot, original, tmp_path):
    root = copy_tree(dataroot, tmp_path / "training")
    _rewrite(root, "camera_calibration", _set_column("[CameraCalibrationComponent].intrinsic.k1", -0.2))
    store = load_scene(read_dataset_scene(DatasetSource("waymo-v2", str(root)), tmp_path / "s"))
    assert store.manifest["distortion"] == {"CAM_FRONT": [-0.2, 0.0, 0.0, 0.0, 0.0]}
    assert store.image_size("CAM_FRONT") == original.image_size("CAM_FRONT")
    assert image_psnr(original.image("CAM_FRONT", 0), store.image("CAM_FRONT", 0)) < JPEG_MIN_PSNR_DB  # remapped
    assert image_psnr(original.image("CAM_FRONT_LEFT", 0), store.image("CAM_FRONT_LEFT", 0)) > JPEG_MIN_PSNR_DB
