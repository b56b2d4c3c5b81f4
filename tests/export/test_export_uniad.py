"""UniAD export: the info pickles hold every key UniAD's converter writes, with the right shapes and finite numbers,
loadable without numpy 2; the boxes decode back onto the scene store's boxes under UniAD v1's loader (and show how
v2's differs); the devkit and PredictHelper read the dataroot; anchors are finite; bad options are one clear error."""
import pickle

import numpy as np
import pytest

from omniscs.errors import OmniscsError
from omniscs.export import export_scenes
from omniscs.export.common import ego_from_lidar, token
from omniscs.export.nuscenes import nuscenes_lidar_mount
from omniscs.export.nuscenes_map import NUSCENES_LOCATIONS
from omniscs.export.uniad import (
    ANCHOR_FILE,
    DETECTION_CLASSES,
    NAME_MAPPING,
    UNIAD_CAMERAS,
    UniADConfig,
    motion_anchors,
    ego_motion,
    uniad_infos,
)
from omniscs.geometry import box_corners_from_pose, invert_transform, make_transform, pose_from_xyz_yaw
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene import load_scene
from tests.conftest import write_tiny_scene
from tests.export.export_fixtures import two_stores

VERSION = "v1.0-mini"
INFO_KEYS = {"token", "prev", "next", "can_bus", "frame_idx", "sweeps", "cams", "scene_token", "lidar_path",
             "lidar2ego_translation", "lidar2ego_rotation", "ego2global_translation", "ego2global_rotation",
             "timestamp", "gt_boxes", "gt_names", "gt_velocity", "num_lidar_pts", "num_radar_pts", "valid_flag",
             "gt_inds", "gt_ins_tokens", "fut_traj", "fut_traj_valid_mask", "visibility_tokens"}
SENSOR_KEYS = {"data_path", "type", "sample_data_token", "sensor2ego_translation", "sensor2ego_rotation",
               "ego2global_translation", "ego2global_rotation", "timestamp", "sensor2lidar_rotation",
               "sensor2lidar_translation"}
#: Corner agreement of a correctly decoded box with the store's box (metres; JSON keeps full float precision).
CORNER_TOL_M = 1e-6


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    return two_stores(tmp_path_factory)


@pytest.fixture(scope="module")
def out(stores, tmp_path_factory):
    # every box of the stores (also those no sensor captures, e.g. the intersection's trucks): the format is
    # checked on all of them; which boxes an export labels is tests/export/test_unseen_boxes.py's subject
    return export_scenes(stores, "uniad", tmp_path_factory.mktemp("uniad") / "data", version=VERSION,
                         val_scenes=["scene-0002"], keep_unseen=True)


def _load(path):
    with open(path, "rb") as fh:
        return pickle.load(fh)


@pytest.fixture(scope="module")
def pickles(out):
    return {split: _load(out / "infos" / f"nuscenes_infos_temporal_{split}.pkl") for split in ("train", "val")}


@pytest.fixture(scope="module")
def nusc(out):
    from nuscenes.nuscenes import NuScenes

    return NuScenes(version=VERSION, dataroot=str(out / "nuscenes"), verbose=False)


def _finite(x):
    return np.all(np.isfinite(np.asarray(x, np.float64)))


def test_the_info_pickles_have_every_key_with_the_right_shapes_and_finite_numbers(pickles, out, stores):
    assert pickles["train"]["metadata"] == pickles["val"]["metadata"] == {"version": VERSION}
    train, val = pickles["train"]["infos"], pickles["val"]["infos"]
    assert len(train) == len(val) == 2  # one scene each, 2 keyframes (10 Hz log, 2 Hz samples)
    assert {i["scene_token"] for i in train}.isdisjoint({i["scene_token"] for i in val})
    for infos in (train, val):
        assert [i["frame_idx"] for i in infos] == [0, 1]
        assert infos[0]["next"] == infos[1]["token"] and infos[1]["prev"] == infos[0]["token"]
        for info in infos:
            assert set(info) == INFO_KEYS
            n = len(info["gt_boxes"])
            assert n > 0 and info["gt_boxes"].shape == (n, 7) and _finite(info["gt_boxes"])
            assert info["gt_velocity"].shape == (n, 2) and _finite(info["gt_velocity"])
            assert info["fut_traj"].shape == info["fut_traj_valid_mask"].shape == (n, 16, 2)
            assert _finite(info["fut_traj"]) and set(np.unique(info["fut_traj_valid_mask"])) <= {0.0, 1.0}
            for key in ("gt_names", "num_lidar_pts", "num_radar_pts", "valid_flag", "gt_inds", "gt_ins_tokens",
                        "visibility_tokens"):
                assert info[key].shape == (n,), key
            assert set(info["visibility_tokens"]) <= {1, 2, 3, 4} and info["valid_flag"].dtype == bool
            assert info["can_bus"].shape == (18,) and _finite(info["can_bus"]) and not info["can_bus"][-2:].any()
            assert info["can_bus"][:7].tolist() == [*info["ego2global_translation"], *info["ego2global_rotation"]]
            assert tuple(info["cams"]) == UNIAD_CAMERAS
            for cam in info["cams"].values():
                assert set(cam) == SENSOR_KEYS | {"cam_intrinsic"} and cam["type"] in UNIAD_CAMERAS
                assert cam["cam_intrinsic"].shape == (3, 3) and cam["sensor2lidar_rotation"].shape == (3, 3)
                assert (out / "nuscenes" / cam["data_path"].removeprefix("./data/nuscenes/")).is_file()
            assert info["lidar_path"].startswith("./data/nuscenes/samples/LIDAR_TOP/")
            assert all(set(s) == SENSOR_KEYS and s["type"] == "lidar" for s in info["sweeps"])
    assert len(train[1]["sweeps"]) == 5 and len(train[0]["sweeps"]) == 0  # frames 4..0 precede keyframe 5
    anchors = _load(out / "others" / ANCHOR_FILE)
    assert len(anchors["anchors_all"]) == 4
    assert all(a.shape == (6, 12, 2) and a.dtype == np.float32 and _finite(a) for a in anchors["anchors_all"])
    assert len(anchors["sample_counts"]) == len(anchors["fallback"]) == 4


class _RecordingUnpickler(pickle.Unpickler):
    """Records every global a pickle names."""

    def find_class(self, module, name):
        self.names.add(f"{module}.{name}")
        return super().find_class(module, name)


def test_pickles_name_only_numpy_ndarray_and_bytearray_so_numpy_1_loads_them(out):
    for path in [*(out / "infos").iterdir(), out / "others" / ANCHOR_FILE]:
        with open(path, "rb") as fh:
            reader = _RecordingUnpickler(fh)
            reader.names = set()
            reader.load()
        assert reader.names == {"numpy.ndarray", "builtins.bytearray"}  # never numpy 2's numpy._core
    info = _load(out / "infos" / "nuscenes_infos_temporal_train.pkl")["infos"][0]  # a copy of its own
    info["gt_velocity"][0] = [1.0, 2.0]  # UniAD's loader zeroes NaN velocities in place
    assert not any(isinstance(v, np.generic) for v in info.values())


def test_gt_names_are_the_detection_classes_mapped_from_the_nuscenes_categories(pickles, nusc):
    seen = set()
    for info in pickles["train"]["infos"] + pickles["val"]["infos"]:
        sample = nusc.get("sample", info["token"])
        categories = [nusc.get("sample_annotation", a)["category_name"] for a in sample["anns"]]
        for name, category in zip(info["gt_names"], categories):
            assert name == NAME_MAPPING.get(category, category)
            assert name in DETECTION_CLASSES or category not in NAME_MAPPING
            seen.add(name)
    assert {"car", "truck", "traffic_cone"} <= seen


def test_the_devkit_loads_the_dataroot_and_predict_helper_futures_match_the_infos(nusc, pickles, out):
    from nuscenes.map_expansion.map_api import NuScenesMap
    from nuscenes.prediction import PredictHelper

    helper = PredictHelper(nusc)
    maps = {loc: NuScenesMap(dataroot=str(out / "nuscenes"), map_name=loc) for loc in NUSCENES_LOCATIONS}  # UniAD
    assert {loc for loc, m in maps.items() if m.drivable_area} == {log["location"] for log in nusc.log}  # opens all 4
    moving = 0
    for info in pickles["train"]["infos"] + pickles["val"]["infos"]:
        for i, instance in enumerate(info["gt_ins_tokens"]):
            future = np.reshape(helper.get_future_for_agent(instance, info["token"], seconds=8, in_agent_frame=True),
                                (-1, 2))
            k = len(future)
            assert info["fut_traj_valid_mask"][i, :, 0].sum() == k
            assert np.allclose(info["fut_traj"][i, :k], future) and not info["fut_traj"][i, k:].any()
            moving += k > 0 and np.linalg.norm(future[-1]) > 0.5
    assert moving > 0  # some agents move between the two keyframes


def test_can_bus_motion_is_the_finite_difference_of_the_ego_poses(pickles, stores):
    store = load_scene(stores[0])
    info = pickles["train"]["infos"][1]  # keyframe 5: frames 4 and (the last) 5 around it
    poses, t = store.world_from_ego_all, store.frames.timestamp_us.to_numpy() * 1e-6
    v_world = (poses[5, :3, 3] - poses[4, :3, 3]) / (t[5] - t[4])
    assert np.allclose(info["can_bus"][13:16], poses[5, :3, :3].T @ v_world, atol=1e-9)
    assert np.linalg.norm(info["can_bus"][13:16]) > 1.0  # the fixture's ego drives


def test_can_bus_motion_on_a_circle_is_speed_yaw_rate_and_centripetal_acceleration():
    speed, yaw_rate, dt = 10.0, 0.2, 0.1  # a left turn of radius 50 m at 10 Hz
    t = np.arange(12) * dt
    radius = speed / yaw_rate
    poses = np.stack([pose_from_xyz_yaw(radius * np.sin(yaw_rate * s), radius * (1 - np.cos(yaw_rate * s)), 0.0,
                                        yaw_rate * s) for s in t])
    acc, omega, vel = ego_motion(poses, (t * 1e6).round().astype(np.int64))
    inner = slice(2, -2)  # central differences
    assert np.allclose(omega[:, 2], yaw_rate) and np.allclose(omega[:, :2], 0.0)
    assert np.allclose(vel[inner], [speed, 0.0, 0.0], atol=0.01)
    assert np.allclose(acc[inner], [0.0, speed * yaw_rate, 0.0], atol=0.01)  # towards the turn's centre (left)
    acc, omega, vel = ego_motion(poses[:1], np.zeros(1, np.int64))
    assert not (acc.any() or omega.any() or vel.any())  # one pose: no motion, never NaN


def _corners_mmdet3d_lidar_box(box, counter_clockwise):  # [7] -> [8, 3]
    """Corners of ``LiDARInstance3DBoxes([box], origin=(0.5, 0.5, 0.5)).corners``: the box is given by its gravity
    centre and moved to its bottom centre; local corners are sizes * (unit cube - (0.5, 0.5, 0)); mmdet3d 0.17 turns
    them clockwise by the yaw (``points @ [[c, -s], [s, c]]``), 1.0.0rc6 counter-clockwise (``@ [[c, s], [-s, c]]``)."""
    x, y, z, dx, dy, dz, r = box
    unit = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 1], [0, 1, 0], [1, 0, 0], [1, 0, 1], [1, 1, 1], [1, 1, 0]], float)
    local = (unit - [0.5, 0.5, 0.0]) * [dx, dy, dz]
    c, s = np.cos(r), np.sin(r)
    rot_t = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) if counter_clockwise else \
        np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return local @ rot_t + [x, y, z - dz / 2]


def _corners_v1_loader(box):  # UniAD main (mmdet3d 0.17)
    return _corners_mmdet3d_lidar_box(box, counter_clockwise=False)


def _corners_v2_loader(box):  # UniAD v2.0 (mmdet3d 1.0.0rc6)
    return _corners_mmdet3d_lidar_box(box, counter_clockwise=True)


def _corners_v2_eval(box):  # UniAD v2.0 output_to_nusc_box: nuScenes Box(centre, sizes as w, l, h, yaw quaternion)
    from nuscenes.utils.data_classes import Box
    from pyquaternion import Quaternion

    return Box(box[:3], box[3:6], Quaternion(axis=[0, 0, 1], radians=box[6])).corners().T


def _corner_gap(a, b):  # [8, 3] x2 -> largest distance from a corner of one set to the nearest of the other
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    return max(d.min(0).max(), d.min(1).max())


def test_box_conventions_v1_decodes_onto_the_store_boxes_and_v2_only_through_its_eval_path(nusc, stores):
    gaps = {}
    for convention in ("v1", "v2"):
        infos = uniad_infos(nusc, UniADConfig(box_convention=convention))
        gaps[convention] = {"v1 loader": [], "v2 loader": [], "v2 eval": []}
        for store_path in stores:
            store = load_scene(store_path)
            scene_token = token("scene", store.scene_id)
            ours = [i for i in infos if i["scene_token"] == scene_token]
            for keyframe, info in zip((0, 5), ours):
                mount = nuscenes_lidar_mount(ego_from_lidar(store))  # what the export wrote
                lidar_from_world = invert_transform(store.world_from_ego(keyframe) @ mount)
                rows = {token("instance", store.scene_id, int(r.track_id)): r
                        for r in store.boxes_at(keyframe).itertuples()}
                for box, instance in zip(info["gt_boxes"], info["gt_ins_tokens"]):
                    r = rows[instance]
                    pose = make_transform(quat_to_rotmat(np.array([r.qw, r.qx, r.qy, r.qz])), [r.cx, r.cy, r.cz])
                    truth = box_corners_from_pose(lidar_from_world @ pose, [r.length, r.width, r.height])
                    if abs(r.length - r.width) < 0.2:
                        continue  # near-square footprints cannot tell the conventions apart
                    gaps[convention]["v1 loader"].append(_corner_gap(_corners_v1_loader(box), truth))
                    gaps[convention]["v2 loader"].append(_corner_gap(_corners_v2_loader(box), truth))
                    gaps[convention]["v2 eval"].append(_corner_gap(_corners_v2_eval(box), truth))
    assert len(gaps["v1"]["v1 loader"]) > 20
    assert max(gaps["v1"]["v1 loader"]) < CORNER_TOL_M  # v1 boxes under UniAD main's loader: exact
    assert min(gaps["v2"]["v2 loader"]) > 0.2  # v2 boxes under UniAD v2.0's loader: turned by 90 degrees
    assert max(gaps["v2"]["v2 eval"]) < CORNER_TOL_M  # ... but exact through v2.0's nuScenes-Box evaluation path


def test_a_scene_with_zero_boxes_gives_empty_arrays(tmp_path):
    store = write_tiny_scene(tmp_path / "empty", n_frames=11, n_tracks=0, scene_id="no-boxes")
    out = export_scenes([store], "uniad", tmp_path / "data", version=VERSION, keyframe_every=5)
    infos = _load(out / "infos" / "nuscenes_infos_temporal_train.pkl")["infos"]
    assert len(infos) == 3 and not _load(out / "infos" / "nuscenes_infos_temporal_val.pkl")["infos"]
    for info in infos:
        assert info["gt_boxes"].shape == (0, 7) and info["gt_velocity"].shape == (0, 2)
        assert info["fut_traj"].shape == info["fut_traj_valid_mask"].shape == (0, 16, 2)
        assert all(info[k].shape == (0,) for k in ("gt_names", "gt_inds", "gt_ins_tokens", "visibility_tokens",
                                                   "valid_flag", "num_lidar_pts", "num_radar_pts"))
        assert tuple(info["cams"]) == ("CAM_FRONT",) and _finite(info["can_bus"])
    anchors = _load(out / "others" / ANCHOR_FILE)
    assert anchors["fallback"] == [True] * 4 and anchors["sample_counts"] == [0] * 4
    assert all(_finite(a) and a.shape == (6, 12, 2) for a in anchors["anchors_all"])


def _fake_infos(rng, names, speeds):
    """Infos with straight 12-step futures along +y (agent frame) at the given speeds."""
    steps = np.arange(1, 17) * 0.5
    fut = np.stack([np.stack([np.zeros(16), v * steps], axis=1) for v in speeds])
    fut += rng.normal(0, 0.01, fut.shape)
    return [{"gt_names": np.array(names), "gt_velocity": np.stack([np.zeros(len(speeds)), speeds], 1),
             "fut_traj": fut, "fut_traj_valid_mask": np.ones_like(fut)}]


def test_anchors_cluster_each_group_and_fall_back_to_straight_lines_at_the_median_speed():
    rng = np.random.default_rng(0)
    speeds = np.concatenate([rng.uniform(1, 12, 40), [1.0, 1.5, 2.0]])
    names = ["car"] * 20 + ["bus"] * 20 + ["pedestrian"] * 3
    anchors = motion_anchors(_fake_infos(rng, names, speeds))
    assert anchors["sample_counts"] == [40, 0, 3, 0] and anchors["fallback"] == [False, True, True, True]
    vehicle = anchors["anchors_all"][0]
    assert vehicle.shape == (6, 12, 2) and _finite(vehicle)
    ends = np.sort(vehicle[:, -1, 1])
    assert ends[0] < 6 * 3 and ends[-1] > 6 * 10 and np.abs(vehicle[:, :, 0]).max() < 0.1  # speeds spread, along +y
    pedestrian = anchors["anchors_all"][2]
    assert np.allclose(np.linalg.norm(pedestrian[:, -1], axis=1), 1.5 * 6.0, atol=1e-5)  # median speed for 6 s
    assert np.allclose(anchors["anchors_all"][3], 0.0)  # no barriers or cones: their default speed is 0


@pytest.mark.parametrize("options, message", [
    ({"box_convention": "v3"}, r"unknown box convention 'v3'; use 'v1' \(UniAD main\) or 'v2'"),
    ({"location": "paris"}, r"unknown nuScenes location 'paris'"),
    ({"val_scenes": ["scene-9999"]}, r"val scene\(s\) \['scene-9999'\] are not in this export"),
    ({"anchor_modes": 0}, r"anchor_modes must be an integer >= 1"),
    ({"colour": "red"}, r"unknown UniAD option\(s\) \['colour'\]"),
])
def test_bad_uniad_options_are_one_clear_error_and_write_nothing(options, message, tmp_path):
    store = write_tiny_scene(tmp_path / "tiny")
    with pytest.raises(OmniscsError, match=message) as info:
        export_scenes([store], "uniad", tmp_path / "data", version=VERSION, **options)
    assert "\n" not in str(info.value)
    assert not (tmp_path / "data").exists()


def test_a_scene_without_lidar_is_refused_with_what_to_do(tmp_path):
    store = write_tiny_scene(tmp_path / "tiny", with_lidar=False)
    with pytest.raises(OmniscsError, match=r"has no LiDAR; UniAD infos live in the LIDAR_TOP frame"):
        export_scenes([store], "uniad", tmp_path / "data", version=VERSION)
    assert not (tmp_path / "data").exists()


def test_lidar_top_has_nuscenes_axes_so_uniads_planning_targets_point_forward(nusc):
    """UniAD's planning target is the next LiDAR origin in the current LIDAR_TOP frame, and its command the x
    (lateral) offset of the last target; with nuScenes' axes the ego driving on moves along +y."""
    def world_from_lidar(sample):
        sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        cs, pose = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"]), nusc.get("ego_pose", sd["ego_pose_token"])
        as_T = lambda r: make_transform(quat_to_rotmat(np.array(r["rotation"])), r["translation"])  # noqa: E731
        return as_T(pose) @ as_T(cs)

    checked = 0
    for sample in nusc.sample:
        if not sample["next"]:
            continue
        target = invert_transform(world_from_lidar(sample)) @ world_from_lidar(nusc.get("sample", sample["next"]))
        x, y = target[:2, 3]
        assert y > 1.0 and abs(x) < y, (x, y)  # forward along +y; UniAD's command (x >= 2: right) is not fooled
        checked += 1
    assert checked >= 2


def test_a_store_lidar_mount_is_kept_when_it_already_has_nuscenes_axes():
    tilted = make_transform(quat_to_rotmat(np.array([np.cos(-np.pi / 4), 0.01, 0.0, np.sin(-np.pi / 4)])),
                            [0.9, 0.0, 1.8])  # nuScenes' mount: x right, a small tilt
    np.testing.assert_array_equal(nuscenes_lidar_mount(tilted), tilted)
    forward = make_transform(np.eye(3), [0.94, 0.0, 1.84])  # x forward: turned to nuScenes' axes, same position
    out = nuscenes_lidar_mount(forward)
    np.testing.assert_allclose(out[:3, 3], [0.94, 0.0, 1.84])
    np.testing.assert_allclose(out[:3, :3] @ [1, 0, 0], [0, -1, 0], atol=1e-12)  # x: the ego's right
    np.testing.assert_allclose(out[:3, :3] @ [0, 1, 0], [1, 0, 0], atol=1e-12)   # y: forward
