"""Detection evaluation of a results file against an exported dataroot: the same mAP, errors and NDS as the
nuScenes devkit's own loading, filtering and metrics on the same files, and clear errors for bad results."""
from __future__ import annotations

import json

import numpy as np
import pytest

from omniscs.errors import ValidationError
from omniscs.eval.detection import TP_METRICS, DetectionConfig
from omniscs.eval.nuscenes_io import NuScenesTables, evaluate_detection_results
from omniscs.export import export_scenes
from tests.dataset_fixtures import synthetic_store

VERSION = "v1.0-mini"


@pytest.fixture(scope="module")
def dataroot(tmp_path_factory):
    store = synthetic_store(tmp_path_factory)
    return export_scenes([store], "nuscenes", tmp_path_factory.mktemp("evalroot") / "nuscenes", version=VERSION)


def _noisy_results(dataroot, path, seed: int = 0, drop: float = 0.25) -> dict:
    """Predictions made from the ground truth with errors of every kind, misses and false positives."""
    from omniscs.eval.nuscenes_io import CATEGORY_TO_DETECTION

    rng = np.random.default_rng(seed)
    tables = NuScenesTables.load(dataroot, VERSION)
    results = {t: [] for t in tables.scene_samples()}
    for ann in tables["sample_annotation"].values():
        cat = tables["category"][tables["instance"][ann["instance_token"]]["category_token"]]["name"]
        name = CATEGORY_TO_DETECTION.get(cat)
        if name is None or rng.random() < drop:
            continue
        attrs = [tables["attribute"][a]["name"] for a in ann["attribute_tokens"]]
        yaw = rng.normal(0, 0.3)
        q = np.array(ann["rotation"])
        turn = np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
        w1, x1, y1, z1 = q
        w2, x2, y2, z2 = turn
        rot = [w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
               w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2]
        results[ann["sample_token"]].append({
            "sample_token": ann["sample_token"], "translation": list(np.array(ann["translation"]) + rng.normal(0, 0.6, 3)),
            "size": list(np.array(ann["size"]) * rng.uniform(0.8, 1.2, 3)), "rotation": rot,
            "velocity": list(rng.normal(0, 1.0, 2)), "detection_name": name,
            "detection_score": float(np.round(rng.uniform(0.05, 1.0), 2)),
            "attribute_name": attrs[0] if attrs and rng.random() < 0.8 else ""})
    for token, boxes in results.items():  # a false positive per sample
        boxes.append({"sample_token": token, "translation": [*rng.uniform(-20, 20, 2) + tables.reference_pose(token)
                      ["translation"][:2], 0.8], "size": [1.8, 4.4, 1.5], "rotation": [1, 0, 0, 0],
                      "velocity": [0, 0], "detection_name": "car", "detection_score": 0.3,
                      "attribute_name": "vehicle.parked"})
    data = {"meta": {"use_camera": True, "use_lidar": False, "use_radar": False, "use_map": False,
                     "use_external": False}, "results": results}
    path.write_text(json.dumps(data))
    return data


def _devkit_metrics(dataroot, results_path):
    """The devkit's load_gt steps (without its official split names), its loaders' filters and its metrics."""
    from nuscenes.eval.common.data_classes import EvalBoxes
    from nuscenes.eval.common.loaders import add_center_dist, filter_eval_boxes, load_prediction
    from nuscenes.eval.common.utils import center_distance
    from nuscenes.eval.detection import algo
    from nuscenes.eval.detection.config import config_factory
    from nuscenes.eval.detection.data_classes import DetectionBox, DetectionMetrics
    from nuscenes.eval.detection.utils import category_to_detection_name
    from nuscenes.nuscenes import NuScenes

    cfg = config_factory("detection_cvpr_2019")
    nusc = NuScenes(version=VERSION, dataroot=str(dataroot), verbose=False)
    gt = EvalBoxes()
    for sample in nusc.sample:
        boxes = []
        for token in sample["anns"]:
            ann = nusc.get("sample_annotation", token)
            name = category_to_detection_name(ann["category_name"])
            if name is None:
                continue
            attrs = ann["attribute_tokens"]
            boxes.append(DetectionBox(sample_token=sample["token"], translation=ann["translation"], size=ann["size"],
                                      rotation=ann["rotation"], velocity=nusc.box_velocity(token)[:2],
                                      num_pts=ann["num_lidar_pts"] + ann["num_radar_pts"], detection_name=name,
                                      detection_score=-1.0,
                                      attribute_name=nusc.get("attribute", attrs[0])["name"] if attrs else ""))
        gt.add_boxes(sample["token"], boxes)
    pred, _ = load_prediction(str(results_path), cfg.max_boxes_per_sample, DetectionBox, verbose=False)
    gt = filter_eval_boxes(nusc, add_center_dist(nusc, gt), cfg.class_range)
    pred = filter_eval_boxes(nusc, add_center_dist(nusc, pred), cfg.class_range)
    metrics = DetectionMetrics(cfg)
    for name in cfg.class_names:
        for th in cfg.dist_ths:
            metrics.add_label_ap(name, th, algo.calc_ap(algo.accumulate(gt, pred, name, center_distance, th),
                                                        cfg.min_recall, cfg.min_precision))
        md = algo.accumulate(gt, pred, name, center_distance, cfg.dist_th_tp)
        for m in TP_METRICS:
            undefined = (name == "traffic_cone" and m in ("attr_err", "vel_err", "orient_err")) or \
                        (name == "barrier" and m in ("attr_err", "vel_err"))
            metrics.add_label_tp(name, m, np.nan if undefined else algo.calc_tp(md, cfg.min_recall, m))
    return metrics


def test_map_errors_and_nds_agree_with_the_devkit_on_an_exported_dataroot(dataroot, tmp_path):
    path = tmp_path / "results.json"
    _noisy_results(dataroot, path)
    ours, info = evaluate_detection_results(dataroot, VERSION, path)
    want = _devkit_metrics(dataroot, path)
    assert info["n_samples"] > 0 and sum(ours.n_gt.values()) >= 10
    assert ours.mean_ap == pytest.approx(want.mean_ap, abs=1e-6) and 0.05 < ours.mean_dist_aps["car"] < 1.0
    assert ours.nd_score == pytest.approx(want.nd_score, abs=1e-6)
    for name in ours.config.class_names:
        for th in ours.config.dist_ths:
            assert ours.label_aps[name][th] == pytest.approx(want.get_label_ap(name, th), abs=1e-6)
    for m in TP_METRICS:
        assert ours.tp_errors[m] == pytest.approx(want.tp_errors[m], abs=1e-6)


def test_ground_truth_as_predictions_scores_one_on_the_classes_present(dataroot, tmp_path):
    path = tmp_path / "perfect.json"
    _noisy_results(dataroot, path, drop=0.0)
    data = json.loads(path.read_text())
    tables = NuScenesTables.load(dataroot, VERSION)
    from omniscs.eval.detection import filter_boxes
    from omniscs.eval.nuscenes_io import load_ground_truth

    gt, racks = load_ground_truth(tables, tables.scene_samples())
    gt = filter_boxes(gt, DetectionConfig(), racks)  # what is evaluated (boxes without points would be false positives)
    present = tuple(sorted(set(gt.name.tolist())))
    perfect = {t: [] for t in data["results"]}
    for i in range(len(gt)):
        perfect[gt.sample_token[i]].append({
            "sample_token": gt.sample_token[i], "translation": gt.translation[i].tolist(), "size": gt.size[i].tolist(),
            "rotation": gt.rotation[i].tolist(), "velocity": np.nan_to_num(gt.velocity[i]).tolist(),
            "detection_name": gt.name[i], "detection_score": 0.5, "attribute_name": gt.attribute[i]})
    path.write_text(json.dumps({"meta": {}, "results": perfect}))
    m, _ = evaluate_detection_results(dataroot, VERSION, path, config=DetectionConfig(class_names=present))
    assert m.mean_ap == pytest.approx(1.0)
    assert all(m.tp_errors[k] == pytest.approx(0.0, abs=1e-9) for k in ("trans_err", "scale_err", "orient_err"))


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["results"].update({"not-a-token": []}), "unknown to the dataroot"),
    (lambda d: d["results"].pop(next(iter(d["results"]))), "lack 1 of the"),
    (lambda d: next(b for v in d["results"].values() for b in v).update(detection_score=float("nan")), "finite"),
    (lambda d: next(b for v in d["results"].values() for b in v).update(detection_name="ufo"), "unknown detection_name"),
    (lambda d: next(b for v in d["results"].values() for b in v).update(size=[0, 1, 1]), "positive"),
    (lambda d: next(b for v in d["results"].values() for b in v).pop("translation"), "not a nuScenes detection box"),
    (lambda d: d.pop("results"), "must be an object with a 'results'"),
])
def test_bad_results_are_one_clear_error(dataroot, tmp_path, edit, message):
    path = tmp_path / "results.json"
    data = _noisy_results(dataroot, path)
    edit(data)
    path.write_text(json.dumps(data))
    with pytest.raises(ValidationError, match=message):
        evaluate_detection_results(dataroot, VERSION, path)


def test_unknown_scene_or_missing_tables_are_clear_errors(dataroot, tmp_path):
    path = tmp_path / "results.json"
    _noisy_results(dataroot, path)
    with pytest.raises(ValidationError, match="unknown scene"):
        evaluate_detection_results(dataroot, VERSION, path, scenes=["nope"])
    with pytest.raises(ValidationError, match="has no nuScenes table folder 'v1.0-mini'; it has none"):
        evaluate_detection_results(tmp_path, VERSION, path)


@pytest.mark.slow
def test_the_eval_detection_command_prints_the_protocols_json_and_refuses_bad_results_in_one_line(dataroot, tmp_path):
    import subprocess
    import sys

    path = tmp_path / "results.json"
    _noisy_results(dataroot, path)
    args = [sys.executable, "-c", "from omniscs.cli import main; main()", "eval", "detection", "--dataroot",
            str(dataroot), "--version", VERSION, "--results", str(path)]
    proc = subprocess.run([*args, "--json"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    ours, _ = evaluate_detection_results(dataroot, VERSION, path)
    assert out["mAP"] == pytest.approx(ours.mean_ap) and out["NDS"] == pytest.approx(ours.nd_score)
    assert set(out["classes"]["car"]["AP"]) == {"0.5", "1", "2", "4"} and "mean_AP" in out["classes"]["car"]
    table = subprocess.run([*args, "--class", "car"], capture_output=True, text=True, timeout=120)
    assert table.returncode == 0 and "NDS" in table.stdout and "car" in table.stdout
    path.write_text(json.dumps({"results": {"unknown-token": []}}))
    bad = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "unknown to the dataroot" in bad.stderr


# ----------------------------------------------------------------------------- boxes a camera sees
def _front_camera() -> tuple:
    """A 100 x 100 px camera at the origin looking along global +x (camera x right = global -y, y down = -z)."""
    camera_from_global = np.eye(4)
    camera_from_global[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    return camera_from_global, np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]]), 100, 100


def test_a_box_is_in_view_when_a_point_of_it_is_in_front_of_a_camera_and_inside_its_image():
    from omniscs.eval.detection import Boxes
    from omniscs.eval.nuscenes_io import in_camera_view

    def box(token, x, y, w=2.0, length=4.0):
        return {"sample_token": token, "translation": [x, y, 0.0], "size": [w, length, 1.5],
                "rotation": [1.0, 0.0, 0.0, 0.0], "velocity": [0.0, 0.0], "detection_name": "car",
                "detection_score": -1.0, "attribute_name": ""}

    boxes = Boxes.from_records([
        box("s", 10.0, 0.0),                  # ahead: seen
        box("s", -10.0, 0.0),                 # behind the camera
        box("s", 10.0, 30.0),                 # ahead but far off to the left, outside the image
        box("s", 2.0, 0.0, w=40.0, length=1.0),  # a wall across the view: every corner outside, its middle inside
        box("other", 10.0, 0.0),              # a sample with no camera sees nothing
    ])
    assert in_camera_view(boxes, {"s": [_front_camera()], "other": []}).tolist() == [True, False, False, True, False]


def test_scoring_in_the_cameras_view_leaves_out_the_boxes_no_camera_sees(dataroot, tmp_path):
    import shutil

    from omniscs.eval.nuscenes_io import (camera_frustums, evaluated_classes, evaluated_ground_truth, in_camera_view,
                                          load_ground_truth)

    # the fixture's cameras see every box: a copy whose odd samples lost their camera images sees half of them
    dataroot = shutil.copytree(dataroot, tmp_path / "root")
    tables = NuScenesTables.load(dataroot, VERSION)
    samples = tables.scene_samples()
    blind = set(samples[1::2])
    cameras = {t for t, c in tables["calibrated_sensor"].items()
               if tables["sensor"][c["sensor_token"]]["channel"].startswith("CAM_")}
    rows = [sd for sd in tables["sample_data"].values()
            if not (sd["sample_token"] in blind and sd["calibrated_sensor_token"] in cameras)]
    (dataroot / VERSION / "sample_data.json").write_text(json.dumps(rows))
    tables = NuScenesTables.load(dataroot, VERSION)
    everything, _ = load_ground_truth(tables, samples)
    seen = in_camera_view(everything, camera_frustums(tables, samples))
    assert seen.any() and not seen[np.isin(everything.sample_token, list(blind))].any()
    in_view, racks = evaluated_ground_truth(tables, samples, camera_view=True)
    assert len(in_view) == int(seen.sum())
    # predictions exactly on the boxes a camera sees: perfect in view, missed ones all round
    results = {t: [] for t in samples}
    for i in np.flatnonzero(seen):
        results[everything.sample_token[i]].append({
            "sample_token": everything.sample_token[i], "translation": everything.translation[i].tolist(),
            "size": everything.size[i].tolist(), "rotation": everything.rotation[i].tolist(),
            "velocity": np.nan_to_num(everything.velocity[i]).tolist(), "detection_name": everything.name[i],
            "detection_score": 0.9, "attribute_name": everything.attribute[i]})
    path = tmp_path / "seen.json"
    path.write_text(json.dumps({"meta": {"use_camera": True}, "results": results}))
    config = DetectionConfig(class_names=evaluated_classes(in_view, racks))
    viewed, info = evaluate_detection_results(dataroot, VERSION, path, config=config, camera_view=True)
    round_, _ = evaluate_detection_results(dataroot, VERSION, path, config=config)
    assert info["camera_view"] and viewed.mean_ap == pytest.approx(1.0)
    assert round_.mean_ap < viewed.mean_ap
    # the command line's --camera-view scores the same
    import subprocess
    import sys

    args = [sys.executable, "-c", "from omniscs.cli import main; main()", "eval", "detection", "--dataroot",
            str(dataroot), "--version", VERSION, "--results", str(path), "--json", "--camera-view",
            *(x for c in config.class_names for x in ("--class", c))]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["camera_view"] and out["mAP"] == pytest.approx(1.0)


# ----------------------------------------------------------------------------- hostile results and tables
@pytest.mark.parametrize("content, message", [
    (b"[" * 100_000, "nested more than 256 deep"),
    (b'{"results": {}, "meta": {"n": ' + b"1" * 5000 + b"}}", "integer of 5000 digits"),
    (b'{"results": {"t": [{"velocity": [Infinity, 0]}]}}', "holds Infinity"),
    (b'{"results": {"t": [{"size": [1e400, 1, 1]}]}}', "too large for a float"),
    (b'{"results": {"\xff": []}}', "not UTF-8 text (byte 14 is 0xff)"),
])
def test_hostile_results_files_are_one_clear_error(dataroot, tmp_path, content, message):
    path = tmp_path / "results.json"
    path.write_bytes(content)
    with pytest.raises(ValidationError) as info:
        evaluate_detection_results(dataroot, VERSION, path)
    assert message in str(info.value) and str(path) in str(info.value) and "\n" not in str(info.value)


def test_an_endless_stream_or_a_fifo_as_results_is_refused_without_reading_it(dataroot, tmp_path):
    import os

    with pytest.raises(ValidationError, match="results file /dev/zero is a device, not a regular file"):
        evaluate_detection_results(dataroot, VERSION, "/dev/zero")
    fifo = tmp_path / "results.json"
    os.mkfifo(fifo)
    with pytest.raises(ValidationError, match="is a FIFO"):  # opened without blocking: no writer is needed
        evaluate_detection_results(dataroot, VERSION, fifo)


@pytest.mark.parametrize("chain", ["sample", "annotation"])
def test_a_next_chain_that_loops_or_dangles_is_one_error_not_a_hang(dataroot, tmp_path, chain):
    import shutil

    root = shutil.copytree(dataroot, tmp_path / "nus")
    table = root / VERSION / ("sample.json" if chain == "sample" else "sample_annotation.json")
    rows = json.loads(table.read_text())
    if chain == "sample":
        rows[-1]["next"] = rows[0]["token"]  # the scene's last keyframe leads back to its first
        expected = "loops at"
    else:
        rows[0]["next"] = "f" * 32
        expected = "names a neighbour"
    table.write_text(json.dumps(rows))
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"results": {}}))
    with pytest.raises(ValidationError, match=expected) as info:
        evaluate_detection_results(root, VERSION, path)
    assert str(table) in str(info.value)
