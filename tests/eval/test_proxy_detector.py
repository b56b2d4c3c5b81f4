"""The embedded proxy camera detector: exact camera geometry (projection, back-projection, observation angle),
results the nuScenes protocol accepts, deterministic training that lowers the loss, the shipped weights, and clear
errors for bad dataroots and checkpoints."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from omniscs.errors import ValidationError
from omniscs.eval.detection import DETECTION_NAMES
from omniscs.eval.detector import DEFAULT_DETECTOR, load_detector, save_detector
from omniscs.eval.detector_config import DetectConfig, DetectorConfig, DetectorTrainConfig
from omniscs.eval.detector_decoding import detect, write_results
from omniscs.eval.detector_network import ProxyDetector, output_size
from omniscs.eval.detector_training import photometric_jitter, targets, train_detector, training_set
from omniscs.eval.detector_views import (annotations_by_sample, back_project, camera_views, global_yaw,
                                        observation_angle, project_to_camera, view_boxes)
from omniscs.eval.nuscenes_io import NuScenesTables, evaluate_detection_results, load_results
from omniscs.export import export_scenes
from omniscs.quaternions import yaw_from_quaternion
from tests.dataset_fixtures import synthetic_store

VERSION = "v1.0-mini"
#: A network small enough to train a few steps in a second.
TINY = DetectorConfig(input_width=96, input_height=56, widths=(8, 16, 16, 16), head_width=16)


@pytest.fixture(scope="module")
def dataroot(tmp_path_factory):
    store = synthetic_store(tmp_path_factory)
    return export_scenes([store], "nuscenes", tmp_path_factory.mktemp("detroot") / "nuscenes", version=VERSION)


def _same_weights(a: ProxyDetector, b: ProxyDetector) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))


def _model(seed: int = 0, config: DetectorConfig = TINY) -> ProxyDetector:
    torch.manual_seed(seed)
    return ProxyDetector(config).eval()


def test_back_projecting_a_projected_ground_truth_centre_with_its_depth_recovers_it(dataroot):
    tables = NuScenesTables.load(dataroot, VERSION)
    anns = annotations_by_sample(tables)
    checked = 0
    for token, views in camera_views(tables, tables.scene_samples()).items():
        centres = np.array([a["translation"] for a in anns[token]], np.float64)
        yaws = yaw_from_quaternion(np.array([a["rotation"] for a in anns[token]]))
        for view in views:
            uv, depth = project_to_camera(centres, view.intrinsics, view.global_from_camera)
            front = depth > 0.5
            back = back_project(uv[front], depth[front], view.intrinsics, view.global_from_camera)
            np.testing.assert_allclose(back, centres[front], atol=1e-6, rtol=0)
            alpha = observation_angle(yaws[front], centres[front], view.global_from_camera)
            turn = np.angle(np.exp(1j * (global_yaw(alpha, back, view.global_from_camera) - yaws[front])))
            assert np.abs(turn).max(initial=0.0) < 1e-9
            checked += int(front.sum())
    assert checked >= 10


def test_a_box_straight_ahead_projects_to_the_principal_point_at_its_distance():
    K = np.array([[300.0, 0, 200.0], [0, 300.0, 100.0], [0, 0, 1]])
    global_from_camera = np.eye(4)
    global_from_camera[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera looking along global +x
    global_from_camera[:3, 3] = [500.0, 1200.0, 1.5]
    uv, depth = project_to_camera(np.array([[520.0, 1200.0, 1.5]]), K, global_from_camera)
    np.testing.assert_allclose(uv, [[200.0, 100.0]], atol=1e-9)
    np.testing.assert_allclose(depth, [20.0], atol=1e-9)
    # a box heading across the ray (global +y) is seen at alpha = +90 degrees from any camera looking at it
    assert observation_angle(np.array([np.pi / 2]), np.array([[520.0, 1200.0, 1.5]]), global_from_camera)[0] \
        == pytest.approx(np.pi / 2)


def test_detected_results_pass_the_protocols_checks_and_lie_in_the_global_frame(dataroot, tmp_path):
    results = detect(_model(), dataroot, VERSION, config=DetectConfig(score_threshold=0.0, top_k=5))
    tables = NuScenesTables.load(dataroot, VERSION)
    samples = tables.scene_samples()
    assert set(results["results"]) == set(samples) and results["meta"]["use_camera"] is True
    path = write_results(results, tmp_path / "results.json")
    boxes, meta = load_results(path, tables, samples)
    assert len(boxes) > 0 and meta["use_camera"] is True
    assert np.isfinite(boxes.translation).all() and np.isfinite(boxes.velocity).all() and (boxes.size > 0).all()
    metrics, info = evaluate_detection_results(dataroot, VERSION, path)
    assert info["n_samples"] == len(samples) and 0.0 <= metrics.mean_ap <= 1.0 and np.isfinite(metrics.nd_score)


def test_moving_the_global_frame_moves_the_detected_boxes_with_it(dataroot, tmp_path):
    """The same images with every ego pose moved by a rigid transform T: the boxes come out moved by T."""
    from omniscs.geometry import make_transform
    from omniscs.quaternions import quat_to_rotmat, rotmat_to_quat

    T = make_transform(quat_to_rotmat(np.array([np.cos(0.35), 0, 0, np.sin(0.35)])), np.array([1000.0, -500.0, 3.0]))
    moved = tmp_path / "moved"
    shutil.copytree(dataroot / VERSION, moved / VERSION)
    (moved / "samples").symlink_to(dataroot / "samples")
    poses = json.loads((moved / VERSION / "ego_pose.json").read_text())
    for p in poses:
        pose = T @ make_transform(quat_to_rotmat(np.array(p["rotation"])), np.array(p["translation"]))
        p["translation"], p["rotation"] = pose[:3, 3].tolist(), rotmat_to_quat(pose[:3, :3]).tolist()
    (moved / VERSION / "ego_pose.json").write_text(json.dumps(poses))
    config = DetectConfig(score_threshold=0.0, top_k=5, nms_radius_m=0.0)
    a, b = (detect(_model(), root, VERSION, config=config)["results"] for root in (dataroot, moved))
    for token, boxes in a.items():
        assert len(boxes) == len(b[token]) > 0
        for x, y in zip(boxes, b[token]):
            np.testing.assert_allclose(T[:3, :3] @ x["translation"] + T[:3, 3], y["translation"], atol=1e-6)
            np.testing.assert_allclose(x["size"], y["size"], atol=1e-9)
            turn = yaw_from_quaternion(np.array([y["rotation"]]))[0] - yaw_from_quaternion(np.array([x["rotation"]]))[0]
            assert np.angle(np.exp(1j * (turn - 0.7))) == pytest.approx(0.0, abs=1e-6)
            np.testing.assert_allclose(T[:2, :2] @ x["velocity"], y["velocity"], atol=1e-6)


@pytest.mark.parametrize("config", [TINY, replace(TINY, depth_error=0.1, contact_error_px=0.5)],
                         ids=["regressed depth", "fused with the ground contact"])
def test_decoding_the_training_targets_gives_back_the_ground_truth_boxes(dataroot, config):
    """A network that output exactly its targets would detect every learned box where it is, as large as it is and
    heading where it heads: encoding (targets) and decoding (back-projection, and the ground contact where the
    errors are measured) are inverse."""
    from omniscs.eval.detector_decoding import _decode_view
    from omniscs.eval.detector_training import _scaled

    tables = NuScenesTables.load(dataroot, VERSION)
    anns = annotations_by_sample(tables)
    train, found = DetectorTrainConfig(), 0
    for token, views in camera_views(tables, tables.scene_samples()).items():
        truth = {a["token"]: a for a in anns[token]}
        for view in views:
            boxes = view_boxes(view, anns[token], config.classes, train)
            sx, sy = config.input_width / view.width, config.input_height / view.height
            heat, reg, _ = targets([_scaled(boxes, sx, sy)], np.array([view.intrinsics[1, 1] * sy]), config, train)
            for box in _decode_view(torch.where(heat == 1, 20.0, -20.0)[0], reg[0], view, config, DetectConfig()):
                gt = min(truth.values(),
                         key=lambda a: np.linalg.norm(np.subtract(a["translation"], box["translation"])))
                np.testing.assert_allclose(box["translation"], gt["translation"], atol=1e-4)
                np.testing.assert_allclose(box["size"], gt["size"], rtol=1e-5)
                turn = yaw_from_quaternion(np.array([box["rotation"], gt["rotation"]]))
                assert np.angle(np.exp(1j * (turn[0] - turn[1]))) == pytest.approx(0.0, abs=1e-5)
                assert box["detection_name"] == gt["detection_name"]
                found += 1
    assert found >= 3


def test_boxes_of_one_object_seen_by_two_cameras_are_merged():
    from omniscs.eval.detector_decoding import centre_nms

    box = {"translation": [10.0, 5.0, 1.0], "detection_name": "car", "detection_score": 0.9}
    kept = centre_nms([box, {**box, "translation": [10.5, 5.0, 1.0], "detection_score": 0.8},
                       {**box, "detection_name": "truck", "detection_score": 0.7},
                       {**box, "translation": [14.0, 5.0, 1.0], "detection_score": 0.6}], radius_m=1.5)
    assert [(b["detection_name"], b["detection_score"]) for b in kept] == [("car", 0.9), ("truck", 0.7), ("car", 0.6)]


def test_flipping_an_image_mirrors_its_heatmap_targets(dataroot):
    from omniscs.eval.detector_training import _flipped

    data = training_set([(dataroot, VERSION)], TINY)
    i = int(np.argmax([len(b) for b in data.boxes]))
    assert len(data.boxes[i]) > 0
    heat, reg, mask = targets([data.boxes[i]], data.focal[[i]], TINY, DetectorTrainConfig())
    fheat, freg, fmask = targets([_flipped(data.boxes[i], TINY.input_width)], data.focal[[i]], TINY,
                                 DetectorTrainConfig())
    assert heat.shape == (1, len(DETECTION_NAMES), *output_size(TINY))
    # cells are STRIDE px wide and the input width is a multiple of it: mirrored pixels are mirrored cells
    torch.testing.assert_close(fheat, torch.flip(heat, dims=[-1]))
    on, fon = mask[0, 2] > 0, torch.flip(fmask[0, 2], dims=[-1]) > 0
    assert torch.equal(on, fon)
    torch.testing.assert_close(torch.flip(freg, dims=[-1])[0, 6][on], -reg[0, 6][on])  # sin(alpha) changes sign
    torch.testing.assert_close(torch.flip(freg, dims=[-1])[0, 2][on], reg[0, 2][on])  # depth does not


def test_a_few_training_steps_lower_the_loss_and_the_same_seed_gives_the_same_weights(dataroot):
    train = DetectorTrainConfig(steps=40, batch_size=4, lr=5e-3, log_every=10, seed=3, threads=1)
    data = training_set([(dataroot, VERSION)], TINY, train)
    assert sum(len(b) for b in data.boxes) > 0
    a, rec = train_detector([(dataroot, VERSION)], train, TINY, data=data)
    b, rec_b = train_detector([(dataroot, VERSION)], train, TINY, data=data)
    curve = [c["total"] for c in rec["loss_curve"]]
    assert len(curve) == 4 and curve[-1] < 0.7 * curve[0]
    assert curve == [c["total"] for c in rec_b["loss_curve"]]
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), name
    assert rec["n_images"] == len(data) and rec["n_boxes"] > 0


def test_the_ground_contact_reads_a_box_on_flat_ground_and_is_refused_above_the_horizon():
    """A car 12 m ahead of a camera 1.5 m above flat ground: the ray through the pixel of its bottom centre meets
    the ground at the bottom centre; a pixel above the horizon never meets it."""
    from omniscs.eval.detector_decoding import ground_contact_centres
    from omniscs.eval.detector_views import CameraView

    K = np.array([[200.0, 0, 160], [0, 200.0, 90], [0, 0, 1]])
    # OpenCV camera looking along ego +x: x_cam = -y_ego, y_cam = -z_ego, z_cam = x_ego
    R = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    global_from_ego = np.eye(4)
    global_from_ego[:3, 3] = [100.0, -20.0, 3.0]  # the ground under the car is at global z = 3
    ego_from_camera = np.eye(4)
    ego_from_camera[:3, :3], ego_from_camera[:3, 3] = R, [1.0, 0.0, 1.5]
    view = CameraView("s", "CAM_FRONT", None, 320, 180, K, global_from_ego @ ego_from_camera, global_from_ego)
    centre = np.array([[100.0 + 13.0, -20.0 + 0.5, 3.0 + 0.8]])
    uv, _ = project_to_camera(centre - [0, 0, 0.8], K, view.global_from_camera)
    centres, depth, valid = ground_contact_centres(np.vstack([uv, [[160.0, 60.0]]]), np.array([1.6, 1.6]), view)
    assert valid.tolist() == [True, False]
    np.testing.assert_allclose(centres[0], centre[0], atol=1e-9)
    assert depth[0] == pytest.approx(12.0)
    assert np.isfinite(centres).all() and np.isfinite(depth).all()


def test_training_measures_the_errors_that_weigh_the_two_depths(dataroot):
    train = DetectorTrainConfig(steps=3, batch_size=4, seed=3, threads=1, calibration_images=6)
    model, rec = train_detector([(dataroot, VERSION)], train, TINY)
    cal = rec["calibration"]
    assert cal["n_images"] == 6 and cal["n_boxes"] > 0
    assert model.config.depth_error == cal["depth_error"] > 0 and model.config.contact_error_px == cal["contact_error_px"] > 0
    off, _ = train_detector([(dataroot, VERSION)], replace(train, calibration_images=0), TINY)
    assert off.config.depth_error is None and off.config.contact_error_px is None
    assert cal["on"] == "training images"


def test_the_depth_errors_are_measured_on_the_calibration_images_when_given(dataroot):
    train = DetectorTrainConfig(steps=3, batch_size=4, seed=3, threads=1, calibration_images=6)
    data = training_set([(dataroot, VERSION)], TINY, train)
    own, rec = train_detector([(dataroot, VERSION)], train, TINY, data=data)
    # the same weights measured on other images: a darkened copy of the set reads the depths differently
    darker = replace(data, images=(data.images.float() * 0.4).to(torch.uint8))
    other, rec_other = train_detector([(dataroot, VERSION)], train, TINY, data=data, calibration_data=darker)
    assert _same_weights(own, other)
    assert rec_other["calibration"]["on"] == "held-out calibration images"
    assert rec_other["calibration"]["depth_error"] != rec["calibration"]["depth_error"]
    assert other.config.depth_error == rec_other["calibration"]["depth_error"] > 0


def test_photometric_jitter_changes_colours_within_range_and_repeats_with_the_seed():
    images = torch.stack([torch.zeros(3, 8, 10), torch.full((3, 8, 10), 255.0),
                          torch.linspace(0, 255, 240).reshape(3, 8, 10)]).to(torch.uint8)
    a = photometric_jitter(images, 0.3, torch.Generator().manual_seed(1))
    b = photometric_jitter(images, 0.3, torch.Generator().manual_seed(1))
    c = photometric_jitter(images, 0.3, torch.Generator().manual_seed(2))
    assert a.shape == images.shape and torch.isfinite(a).all() and a.min() >= 0 and a.max() <= 255
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert (a[2] - images[2].float()).abs().max() > 1.0  # the ramp changed
    assert a[0].max() <= 1e-3 * 255  # black stays (nearly) black under every change
    for strength in (1.0, 1e-6):  # the extremes stay finite and in range
        x = photometric_jitter(images, strength, torch.Generator().manual_seed(3))
        assert torch.isfinite(x).all() and x.min() >= 0 and x.max() <= 255


def test_training_with_photometric_jitter_is_deterministic(dataroot):
    train = DetectorTrainConfig(steps=3, batch_size=4, seed=3, threads=1, calibration_images=0, photometric=0.3)
    data = training_set([(dataroot, VERSION)], TINY, train)
    a, _ = train_detector([(dataroot, VERSION)], train, TINY, data=data)
    b, _ = train_detector([(dataroot, VERSION)], train, TINY, data=data)
    plain, _ = train_detector([(dataroot, VERSION)], replace(train, photometric=0.0), TINY, data=data)
    assert _same_weights(a, b)
    assert not _same_weights(a, plain)


def test_a_saved_detector_loads_with_the_same_outputs_and_a_bad_folder_is_a_clear_error(tmp_path):
    model = _model(seed=1)
    save_detector(model, tmp_path / "ckpt", {"note": "test"})
    again = load_detector(tmp_path / "ckpt")
    x = torch.randint(0, 255, (2, 3, TINY.input_height, TINY.input_width), dtype=torch.uint8)
    with torch.no_grad():
        for p, q in zip(model(x), again(x)):
            assert torch.equal(p, q)
    with pytest.raises(ValidationError, match="not a proxy detector checkpoint"):
        load_detector(tmp_path / "nothing")
    (tmp_path / "ckpt" / "detector_config.json").write_text(json.dumps({**json.loads(
        (tmp_path / "ckpt" / "detector_config.json").read_text()), "head_width": 24}))
    with pytest.raises(ValidationError, match="do not fit"):
        load_detector(tmp_path / "ckpt")


def test_the_shipped_detector_loads_and_gives_finite_outputs():
    model = load_detector()
    record = json.loads((DEFAULT_DETECTOR / "training.json").read_text())
    assert record["command"] and record["data"]["train_logs"] and record["seconds"] > 0
    assert (DEFAULT_DETECTOR / "detector.safetensors").stat().st_size < 5_000_000
    c = model.config
    x = torch.randint(0, 255, (1, 3, c.input_height, c.input_width), dtype=torch.uint8)
    with torch.no_grad():
        heat, reg = model(x)
    assert heat.shape[1] == len(c.classes) and torch.isfinite(heat).all() and torch.isfinite(reg).all()


def test_bad_dataroots_are_one_clear_error(dataroot, tmp_path):
    model = _model()
    with pytest.raises(ValidationError, match="nuScenes dataroot .*missing does not exist"):
        detect(model, tmp_path / "missing", VERSION)
    with pytest.raises(ValidationError, match="nuScenes dataroot .*missing does not exist"):
        train_detector([(tmp_path / "missing", VERSION)], DetectorTrainConfig(steps=1), TINY)
    no_cams = shutil.copytree(dataroot / VERSION, tmp_path / "nocam" / VERSION)
    tables = NuScenesTables.load(dataroot, VERSION)
    lidar = {t for t, c in tables["calibrated_sensor"].items()
             if not tables["sensor"][c["sensor_token"]]["channel"].startswith("CAM_")}
    rows = [r for r in json.loads((no_cams / "sample_data.json").read_text()) if r["calibrated_sensor_token"] in lidar]
    (no_cams / "sample_data.json").write_text(json.dumps(rows))
    with pytest.raises(ValidationError, match="no camera keyframes"):
        detect(model, tmp_path / "nocam", VERSION)
    with pytest.raises(ValidationError, match="no camera keyframes"):
        train_detector([(tmp_path / "nocam", VERSION)], DetectorTrainConfig(steps=1), TINY)
    no_images = shutil.copytree(dataroot / VERSION, tmp_path / "noimg" / VERSION)  # tables without the images
    with pytest.raises(ValidationError, match="missing or unreadable"):
        detect(model, no_images.parent, VERSION)
    with pytest.raises(ValidationError, match="unknown scene"):
        detect(model, dataroot, VERSION, scenes=["nope"])


def test_view_boxes_keep_only_annotations_in_front_within_range_and_in_the_image(dataroot):
    tables = NuScenesTables.load(dataroot, VERSION)
    anns = annotations_by_sample(tables)
    config = DetectorTrainConfig(max_depth_m=30.0)
    for token, views in camera_views(tables, tables.scene_samples()).items():
        for view in views:
            boxes = view_boxes(view, anns.get(token, []), DETECTION_NAMES, config)
            assert ((boxes.depth >= config.near_m) & (boxes.depth <= 30.0)).all()
            assert ((boxes.uv >= 0) & (boxes.uv < [view.width, view.height])).all()
            assert (boxes.extent > 0).all() and (boxes.size > 0).all()


def _boxes(labels: list[int]):
    from omniscs.eval.detector_views import ViewBoxes

    n = len(labels)
    return ViewBoxes(np.zeros((n, 2)), np.ones(n), np.ones((n, 3)), np.zeros(n), np.zeros((n, 2)),
                     np.asarray(labels, np.int64).reshape(n), np.ones((n, 2)), np.zeros((n, 2)))


def test_class_balanced_sampling_shows_each_class_about_equally_often_and_zero_balance_is_uniform():
    """Eight images show only class 0 (cars), one shows class 3 and one shows nothing: at balance 1 each of the three
    (class 0, class 3, no box) gets a third of the draws; at 0 every image a tenth; in between, in between."""
    from omniscs.eval.detector_training import sampling_weights

    boxes = [_boxes([0, 0])] * 8 + [_boxes([3])] + [_boxes([])]
    full = sampling_weights(boxes, 10, 1.0)
    np.testing.assert_allclose([full[:8].sum(), full[8], full[9]], [1 / 3] * 3)
    np.testing.assert_allclose(sampling_weights(boxes, 10, 0.0), np.full(10, 0.1))
    half = sampling_weights(boxes, 10, 0.5)
    assert 0.1 < half[8] < 1 / 3 and half.sum() == pytest.approx(1.0)
    # an image showing a car and the rare class is drawn more often than a car-only image
    mixed = sampling_weights([_boxes([0])] * 4 + [_boxes([0, 3])], 10, 1.0)
    assert mixed[4] > 4 * mixed[0]
    # finite at the extremes: no image, one empty image
    assert sampling_weights([], 10, 1.0).size == 0
    np.testing.assert_allclose(sampling_weights([_boxes([])], 10, 1.0), [1.0])


@pytest.mark.parametrize("field", ["class_balance", "photometric"])
@pytest.mark.parametrize("value", [-0.1, 1.5, float("nan")])
def test_a_share_outside_zero_to_one_is_a_clear_error(field, value):
    with pytest.raises(ValidationError, match=field):
        DetectorTrainConfig(**{field: value})


def test_class_balanced_training_is_deterministic_and_records_the_draws_per_class(dataroot):
    train = DetectorTrainConfig(steps=6, batch_size=4, seed=3, threads=1, class_balance=1.0, calibration_images=0)
    data = training_set([(dataroot, VERSION)], TINY, train)
    a, rec = train_detector([(dataroot, VERSION)], train, TINY, data=data)
    b, _ = train_detector([(dataroot, VERSION)], train, TINY, data=data)
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), name
    # the store's images show one class or none: balanced, each of those and "no box" get the same share of draws;
    # uniform, each class the share of images showing it
    shown = [set(b.label.tolist()) for b in data.boxes]
    classes = sorted(set().union(*shown))
    assert classes and all(len(s) <= 1 for s in shown)
    groups = len(classes) + any(not s for s in shown)
    _, uniform = train_detector([(dataroot, VERSION)], replace(train, class_balance=0.0), TINY, data=data)
    for i in classes:
        name = TINY.classes[i]
        assert rec["draws_showing_class"][name] == pytest.approx(1 / groups)
        assert uniform["draws_showing_class"][name] == pytest.approx(sum(i in s for s in shown) / len(shown))


def test_the_shipped_detectors_logs_of_each_split_are_disjoint():
    from omniscs.training.detector import ShippedDetectorConfig

    config = ShippedDetectorConfig(calibration_logs=12)
    splits = {s: {seed for _, seed in config.logs(s)} for s in ("train", "calibration", "validation", "test")}
    assert all(len(v) == n for v, n in zip(splits.values(), (config.train_logs, config.calibration_logs,
                                                             config.validation_logs, config.test_logs)))
    names = list(splits)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert not splits[a] & splits[b], (a, b)
    assert config.frames("calibration") == config.frames("train") and config.frames("validation") == config.n_frames


def test_shipped_detector_splits_that_share_a_log_are_a_clear_error():
    from omniscs.training.detector import ShippedDetectorConfig

    with pytest.raises(ValidationError, match="train and calibration logs"):
        ShippedDetectorConfig(train_logs=10, calibration_logs=12, calibration_seed=610_005)
