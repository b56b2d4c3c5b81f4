"""Mining what a detector misses: nuScenes' centre-distance matching of a results file against the evaluated ground
truth of an exported dataroot, each box described (distance, visibility, orientation to the ego, pose, its source
scene and track), the miss-rate summaries, the SCS picks, and all-or-nothing outputs with one-line errors."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.detection import DETECTION_NAMES, Boxes, DetectionConfig, filter_boxes
from omniscs.eval.nuscenes_io import NuScenesTables, load_ground_truth
from omniscs.export import export_scenes
from omniscs.eval.mining import (
    MISSED_JSON,
    MISSED_MD,
    MISSED_PNG,
    MiningConfig,
    box_angles,
    build_report,
    distance_bins,
    ground_truth_annotations,
    match_ground_truth,
    mine,
    missed_box_records,
    orientation_bins,
    pick_scs_objects,
    pose_bins,
    recover_tracks,
    relative_heading_deg,
)
from tests.dataset_fixtures import leftovers, synthetic_store

VERSION = "v1.0-mini"
#: The fixture's trucks, cones, barriers and excavator stand 60-120 m away: evaluate every class out to 150 m.
WIDE = DetectionConfig(class_range={c: 150.0 for c in DETECTION_NAMES})


def _copy_tables(src: Path, dst: Path, edit=None) -> Path:
    """A dataroot holding only ``src``'s tables (all the mining reads), each list of rows passed through ``edit``."""
    (dst / VERSION).mkdir(parents=True)
    tables = {p.stem: json.loads(p.read_text()) for p in (src / VERSION).glob("*.json")}
    if edit is not None:
        edit(tables)
    for name, rows in tables.items():
        (dst / VERSION / f"{name}.json").write_text(json.dumps(rows))
    return dst


def _with_points(tables: dict) -> None:
    for ann in tables["sample_annotation"]:  # every class evaluated, not only those the LiDAR happened to hit
        ann["num_lidar_pts"] = max(1, ann["num_lidar_pts"])


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return synthetic_store(tmp_path_factory)


@pytest.fixture(scope="module")
def dataroot(store, tmp_path_factory):
    return export_scenes([store], "nuscenes", tmp_path_factory.mktemp("miningroot") / "nuscenes", version=VERSION)


@pytest.fixture(scope="module")
def all_classes_root(dataroot, tmp_path_factory):
    return _copy_tables(dataroot, tmp_path_factory.mktemp("allclasses") / "nuscenes", _with_points)


def _write_results(root: Path, path: Path, keep=lambda gt, i: True, shift=lambda gt, i: (0.0, 0.0), score=0.5
                   ) -> Path:
    """The ground truth of ``root`` as predictions (the boxes ``keep`` accepts, moved by ``shift`` in x, y)."""
    tables = NuScenesTables.load(root, VERSION)
    samples = tables.scene_samples()
    gt, _ = load_ground_truth(tables, samples)
    results = {t: [] for t in samples}
    for i in range(len(gt)):
        if keep(gt, i):
            results[gt.sample_token[i]].append({
                "sample_token": gt.sample_token[i], "translation": (gt.translation[i] + [*shift(gt, i), 0.0]).tolist(),
                "size": gt.size[i].tolist(), "rotation": gt.rotation[i].tolist(), "velocity": [0.0, 0.0],
                "detection_name": gt.name[i], "detection_score": score, "attribute_name": ""})
    path.write_text(json.dumps({"meta": {"use_camera": True}, "results": results}))
    return path


def _boxes(xy, names, scores=None, sample="s") -> Boxes:
    n = len(xy)
    return Boxes.from_records([{"sample_token": sample, "translation": [x, y, 0.5], "size": [2, 4, 1.5],
                                "rotation": [1, 0, 0, 0], "detection_name": name,
                                "detection_score": -1.0 if scores is None else scores[k]}
                               for k, ((x, y), name) in enumerate(zip(xy, names))], np.zeros(n), np.ones(n))


def _quat(axis, deg) -> list[float]:
    half = np.radians(deg) / 2
    return [float(np.cos(half)), *(np.sin(half) * np.asarray(axis, np.float64)).tolist()]


# ----------------------------------------------------------------------------- reading
def test_ground_truth_annotations_follow_load_ground_truth_box_for_box(all_classes_root):
    tables = NuScenesTables.load(all_classes_root, VERSION)
    samples = tables.scene_samples()
    gt, _ = load_ground_truth(tables, samples)
    annotations = ground_truth_annotations(tables, samples)
    assert len(annotations) == len(gt) > 20
    assert [a["sample_token"] for a, _ in annotations] == gt.sample_token.tolist()
    np.testing.assert_array_equal(np.array([a["translation"] for a, _ in annotations]), gt.translation)
    np.testing.assert_array_equal(np.array([a["size"] for a, _ in annotations]), gt.size)
    assert {c for _, c in annotations} >= {"vehicle.car", "movable_object.trafficcone", "movable_object.barrier"}


def test_results_equal_to_the_ground_truth_miss_nothing(dataroot, tmp_path):
    report = build_report(dataroot, VERSION, _write_results(dataroot, tmp_path / "r.json"))
    tables = NuScenesTables.load(dataroot, VERSION)
    gt, racks = load_ground_truth(tables, tables.scene_samples())
    assert report.n_gt == len(filter_boxes(gt, DetectionConfig(), racks)) > 10  # only the evaluated boxes count
    assert report.n_missed == 0 and report.miss_rate == 0.0
    assert (report.boxes["match_distance_m"] == 0.0).all() and (report.boxes["match_score"] == 0.5).all()
    for df in report.summaries.values():
        assert df["n_gt"].sum() == report.n_gt
        assert all(r is pd.NA or r == 0.0 for r in df["miss_rate"])


def test_dropping_every_car_misses_all_cars_and_nothing_else(all_classes_root, tmp_path):
    path = _write_results(all_classes_root, tmp_path / "r.json", keep=lambda gt, i: gt.name[i] != "car")
    report = build_report(all_classes_root, VERSION, path, MiningConfig(detection=WIDE))
    rates = dict(zip(report.by_category["category"], report.by_category["miss_rate"]))
    assert len(rates) >= 3 and rates["vehicle.car"] == 1.0
    assert all(rate == 0.0 for cat, rate in rates.items() if cat != "vehicle.car")
    assert report.boxes["missed"].to_numpy().tolist() == (report.boxes["detection_name"] == "car").tolist()


def test_a_prediction_3m_off_is_missed_at_2m_and_matched_at_4m(dataroot, tmp_path):
    gt = _boxes([(10.0, 0.0)], ["car"])
    pred = _boxes([(13.0, 0.0)], ["car"], scores=[0.9])
    assert match_ground_truth(gt, pred, 2.0).tolist() == [-1]
    assert match_ground_truth(gt, pred, 4.0).tolist() == [0]
    # end to end: one evaluated car, more than 8 m from any other box of its sample, predicted 3 m off
    tables = NuScenesTables.load(dataroot, VERSION)
    gt, racks = load_ground_truth(tables, tables.scene_samples())
    evaluated = filter_boxes(gt, DetectionConfig(), racks)

    def isolated(i: int) -> bool:
        same = gt.sample_token == gt.sample_token[i]
        d = np.hypot(*(gt.translation[same, :2] - gt.translation[i, :2]).T)
        return np.sort(d)[1] > 8.0 and any((evaluated.translation == gt.translation[i]).all(1))

    victim = next(i for i in range(len(gt)) if isolated(i))
    path = _write_results(dataroot, tmp_path / "r.json", shift=lambda gt, i: (3.0, 0.0) if i == victim else (0, 0))
    at_2 = build_report(dataroot, VERSION, path)
    at_4 = build_report(dataroot, VERSION, path, MiningConfig(match_distance_m=4.0))
    missed = at_2.boxes[at_2.boxes["missed"]]
    assert len(missed) == 1 and np.allclose(missed[["x", "y"]].to_numpy()[0], gt.translation[victim, :2])
    assert at_4.n_missed == 0 and at_4.boxes["match_distance_m"].max() == pytest.approx(3.0)
    # predictions are filtered as the protocol filters them: moved past the 50 m car range, they match nothing
    path = _write_results(dataroot, tmp_path / "r.json", shift=lambda gt, i: (3.0, 0.0))
    moved = build_report(dataroot, VERSION, path, MiningConfig(match_distance_m=4.0))
    pushed_out = moved.boxes["missed"] & (moved.boxes["ego_distance_m"] > 45.0)
    assert int(pushed_out.sum()) >= 1


def test_matching_is_greedy_by_score_within_class_and_sample_and_skips_low_scores():
    gt = _boxes([(0.0, 0.0), (1.5, 0.0)], ["car", "car"])
    # the best prediction sits nearest the second box and takes it; the other then takes the first
    pred = _boxes([(1.4, 0.0), (0.6, 0.0)], ["car", "car"], scores=[0.9, 0.3])
    assert match_ground_truth(gt, pred, 2.0).tolist() == [1, 0]
    assert match_ground_truth(gt, pred, 2.0, min_score=0.5).tolist() == [-1, 0]
    assert match_ground_truth(gt, _boxes([(0.0, 0.0)], ["truck"], [0.9]), 2.0).tolist() == [-1, -1]
    assert match_ground_truth(gt, _boxes([(0.0, 0.0)], ["car"], [0.9], sample="other"), 2.0).tolist() == [-1, -1]


def test_min_score_makes_low_scoring_detections_misses(dataroot, tmp_path):
    path = _write_results(dataroot, tmp_path / "r.json", score=0.2)
    assert build_report(dataroot, VERSION, path, MiningConfig(min_score=0.3)).miss_rate == 1.0
    assert build_report(dataroot, VERSION, path, MiningConfig(min_score=0.2)).n_missed == 0


# ----------------------------------------------------------------------------- describing a box
def test_orientation_bins_on_hand_made_boxes():
    ego = np.zeros((7, 2))
    box = np.array([[10, 0], [10, 0], [10, 0], [10, 0], [0, 10], [0, 10], [-5, -5]], np.float64)
    yaw = np.array([0.0, 180.0, 90.0, -90.0, 90.0, 0.0, 45.0])
    rel = relative_heading_deg(yaw, box, ego)
    np.testing.assert_allclose(rel, [0.0, -180.0, 90.0, -90.0, 0.0, -90.0, -180.0], atol=1e-9)
    # ahead heading away: its back; heading at us: its front; crossing to our left: its left flank faces us
    assert orientation_bins(rel).tolist() == ["away", "toward", "left side", "right side", "away", "right side",
                                              "toward"]
    assert orientation_bins(np.array([45.0, 45.1, 135.0, 134.9, -45.0, -135.0])).tolist() == \
        ["away", "left side", "toward", "left side", "away", "toward"]
    assert orientation_bins(np.array([60.0]), facing_deg=90.0).tolist() == ["away"]


def test_roll_and_pitch_make_on_its_side_and_overturned_and_q_equals_minus_q():
    quats = np.array([_quat([0, 0, 1], 30), _quat([1, 0, 0], 90), _quat([0, 1, 0], 90), _quat([1, 0, 0], 180),
                      _quat([0, 1, 0], 180), _quat([1, 0, 0], 40), _quat([1, 0, 0], 150)])
    angles = box_angles(quats)
    assert pose_bins(angles["tilt_deg"]).tolist() == ["upright", "on its side", "on its side", "overturned",
                                                      "overturned", "upright", "overturned"]
    np.testing.assert_allclose(angles["yaw_deg"][0], 30.0)
    np.testing.assert_allclose(abs(angles["roll_deg"][3]), 180.0)
    np.testing.assert_allclose(angles["pitch_deg"][2], 90.0)
    minus = box_angles(-quats)
    for k in angles:
        np.testing.assert_allclose(minus[k], angles[k], atol=1e-9)
    assert all(np.isfinite(v).all() for v in angles.values())
    with pytest.raises(ValidationError, match="non-zero"):
        box_angles(np.zeros((1, 4)))


def test_a_box_rolled_180_degrees_in_the_dataroot_is_overturned(dataroot, tmp_path):
    victim = {}

    def roll_one(tables):
        cars = [a for a in tables["sample_annotation"] if a["num_lidar_pts"] > 0 and a["size"][1] > 3.0]
        ann = cars[0]
        w, x, y, z = ann["rotation"]  # q ⊗ (0, 1, 0, 0): half a turn about the box's own x axis
        ann["rotation"] = [-x, w, z, -y]
        victim["token"] = ann["token"]

    root = _copy_tables(dataroot, tmp_path / "rolled", roll_one)
    report = build_report(root, VERSION, _write_results(root, tmp_path / "r.json"))
    row = report.boxes.set_index("annotation_token").loc[victim["token"]]
    assert row["pose"] == "overturned" and abs(row["roll_deg"]) == pytest.approx(180.0)
    assert (report.boxes["pose"] == "overturned").sum() == 1
    assert dict(zip(report.by_pose["pose"], report.by_pose["n_gt"]))["overturned"] == 1


def test_distance_bins_are_configurable_and_edges_go_to_the_farther_bin(dataroot, tmp_path):
    labels, names = distance_bins(np.array([0.0, 9.99, 10.0, 39.0, 40.0, 400.0]), (10.0, 20.0, 30.0, 40.0))
    assert names == ["0-10 m", "10-20 m", "20-30 m", "30-40 m", "40+ m"]
    assert labels.tolist() == ["0-10 m", "0-10 m", "10-20 m", "30-40 m", "40+ m", "40+ m"]
    report = build_report(dataroot, VERSION, _write_results(dataroot, tmp_path / "r.json"),
                          MiningConfig(distance_edges_m=(25.0,)))
    assert report.by_distance["distance"].tolist() == ["0-25 m", "25+ m"]
    near = int((report.boxes["ego_distance_m"] < 25.0).sum())
    assert report.by_distance["n_gt"].tolist() == [near, report.n_gt - near]
    with pytest.raises(OmniscsError, match="increasing"):
        MiningConfig(distance_edges_m=(20.0, 10.0))
    with pytest.raises(OmniscsError, match="match_distance_m"):
        MiningConfig(match_distance_m=0.0)


def test_scene_and_track_ids_are_recovered_for_an_export(store, dataroot, tmp_path):
    from omniscs.scene.store import load_scene

    scene = load_scene(store)
    report = build_report(dataroot, VERSION, _write_results(dataroot, tmp_path / "r.json"))
    assert report.boxes["track_id"].notna().all() and (report.boxes["scene_id"] == scene.scene_id).all()
    assert (report.boxes["scene_name"] == "scene-0001").all()
    sizes = scene.boxes.groupby("track_id")[["width", "length", "height"]].first()
    for row in report.boxes.itertuples():  # each recovered track is the store's box of that size
        np.testing.assert_allclose([row.width, row.length, row.height], sizes.loc[int(row.track_id)], rtol=1e-9)
    assert report.boxes["track_id"].nunique() == report.boxes["instance_token"].nunique()

    def anonymise(tables):  # not an OmniSCS export any more: nothing hashes to the scene's token
        for s in tables["scene"]:
            s["name"], s["description"] = "someone-elses-log", "recorded elsewhere"

    other = _copy_tables(dataroot, tmp_path / "other", anonymise)
    tables = NuScenesTables.load(other, VERSION)
    assert recover_tracks(tables, tables["instance"]) == {}
    report = build_report(other, VERSION, _write_results(other, tmp_path / "r2.json"))
    assert report.boxes["track_id"].isna().all() and report.boxes["scene_id"].isna().all()
    assert all(b["track_id"] is None and b["scene_id"] is None for b in missed_box_records(report.boxes))
    tables = NuScenesTables.load(dataroot, VERSION)
    assert recover_tracks(tables, tables["instance"], max_track_id=3) == \
        {t: v for t, v in recover_tracks(tables, tables["instance"]).items() if v[1] <= 3}


# ----------------------------------------------------------------------------- picks and outputs
def test_picks_rank_cells_by_miss_rate_then_misses_and_need_min_count(all_classes_root, tmp_path):
    path = _write_results(all_classes_root, tmp_path / "r.json", keep=lambda gt, i: gt.name[i] != "car")
    report = build_report(all_classes_root, VERSION, path, MiningConfig(detection=WIDE))
    picks = pick_scs_objects(report, top=10, min_count=1)
    assert picks and all(p.category == "vehicle.car" and p.miss_rate == 1.0 for p in picks)
    assert sum(p.n_missed for p in picks) == report.n_missed
    assert all(p.missed["missed"].all() and len(p.missed) == p.n_missed and p.missed["track_id"].notna().all()
               for p in picks)
    cells = [(c, o, "upright", n) for c, o, n in [("a", "toward", 4), ("b", "away", 8), ("c", "toward", 1),
                                                  ("d", "left side", 5)]]
    rows = []
    for category, orientation, pose, n in cells:
        misses = {"a": 2, "b": 4, "c": 1, "d": 0}[category]
        rows += [{"category": category, "orientation": orientation, "pose": pose, "missed": k < misses}
                 for k in range(n)]
    made = dataclasses.replace(report, boxes=pd.DataFrame(rows))
    ranked = pick_scs_objects(made, top=10, min_count=2)
    assert [(p.category, p.n_missed, p.n_gt) for p in ranked] == [("b", 4, 8), ("a", 2, 4)]
    assert [p.category for p in pick_scs_objects(made, top=1, min_count=1)] == ["c"]
    assert pick_scs_objects(made, top=0) == []


def test_mine_writes_json_markdown_and_a_readable_png(all_classes_root, tmp_path):
    import cv2

    path = _write_results(all_classes_root, tmp_path / "r.json", keep=lambda gt, i: i % 3 != 0)
    out = tmp_path / "mined"
    config = MiningConfig(pick_min_count=1, detection=WIDE)
    report = mine(all_classes_root, VERSION, path, out, config)
    assert 0 < report.n_missed < report.n_gt
    data = json.loads((out / MISSED_JSON).read_text(), parse_constant=lambda c: pytest.fail(f"{c} in missed.json"))
    assert data["report"]["n_missed"] == report.n_missed == len(data["missed"])
    assert data["report"]["summaries"]["distance"][0]["miss_rate"] is None or \
        isinstance(data["report"]["summaries"]["distance"][0]["miss_rate"], float)
    assert {b["annotation_token"] for b in data["missed"]} == set(report.missed_boxes["annotation_token"])
    first = data["missed"][0]
    assert len(first["translation"]) == 3 and len(first["rotation"]) == 4 and isinstance(first["track_id"], int)
    assert data["picks"] and all(p["missed"] for p in data["picks"])
    text = (out / MISSED_MD).read_text()
    assert "## By category" in text and "## SCS objects to composite" in text and "nan" not in text.lower()
    image = cv2.imread(str(out / MISSED_PNG))
    assert image is not None and image.shape[0] > 400 and image.shape[1] > 600 and image.std() > 10
    assert leftovers(tmp_path) == []
    with pytest.raises(OmniscsError, match="already exists"):
        mine(all_classes_root, VERSION, path, out, config)
    mine(all_classes_root, VERSION, path, out, config, overwrite=True)
    report.plot(tmp_path / "again.png")
    assert cv2.imread(str(tmp_path / "again.png")) is not None


def _no_points(tables):
    for ann in tables["sample_annotation"]:
        ann["num_lidar_pts"] = 0


@pytest.mark.parametrize("case, message", [
    ("unknown token", "unknown to the dataroot"),
    ("nan score", "finite"),
    ("missing dataroot", "does not exist"),
    ("nothing evaluated", "no evaluated ground-truth box"),
])
def test_errors_are_one_line_and_leave_nothing_in_out_dir(dataroot, tmp_path, case, message):
    root, path = dataroot, _write_results(dataroot, tmp_path / "r.json")
    data = json.loads(path.read_text())
    if case == "unknown token":
        data["results"]["not-a-sample"] = []
    elif case == "nan score":
        next(b for boxes in data["results"].values() for b in boxes)["detection_score"] = float("nan")
    elif case == "missing dataroot":
        root = tmp_path / "no-such-root"
    else:
        root = _copy_tables(dataroot, tmp_path / "pointless", _no_points)
    path.write_text(json.dumps(data))
    out = tmp_path / "out" / "mined"
    with pytest.raises(ValidationError, match=message) as info:
        mine(root, VERSION, path, out)
    assert "\n" not in str(info.value)
    assert not out.exists() and not (tmp_path / "out").exists() and leftovers(tmp_path) == []
