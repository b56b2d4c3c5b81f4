"""nuScenes detection metrics: the same numbers as the nuScenes devkit on the same boxes (accumulate, calc_ap,
calc_tp to 1e-6), known answers on hand-made cases, and the filters of the protocol."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.eval.detection import (TP_METRICS, Boxes, DetectionConfig, MetricData, accumulate, calc_ap, calc_tp,
                                    evaluate, filter_boxes)

CLASSES = ("car", "pedestrian", "barrier", "traffic_cone")
ATTRS = {"car": ("vehicle.moving", "vehicle.parked"), "pedestrian": ("pedestrian.moving", "pedestrian.standing"),
         "barrier": ("",), "traffic_cone": ("",)}


def _quat(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def _random_case(seed: int, n_samples: int = 6) -> tuple[list[dict], list[dict]]:
    """Ground truth and noisy predictions over a few samples: misses, false positives, equal scores, boxes of one
    sample close together, ground truth without attribute or velocity."""
    rng = np.random.default_rng(seed)
    gt, pred = [], []
    for s in range(n_samples):
        token = f"sample-{s}"
        for _ in range(rng.integers(0, 9)):
            name = CLASSES[rng.integers(len(CLASSES))]
            box = {"sample_token": token, "translation": [*rng.uniform(-30, 30, 2), 1.0],
                   "size": list(rng.uniform(0.5, 5.0, 3)), "rotation": _quat(rng.uniform(-np.pi, np.pi)),
                   "velocity": list(rng.normal(0, 3, 2)) if rng.random() > 0.15 else [np.nan, np.nan],
                   "detection_name": name, "attribute_name": ATTRS[name][rng.integers(len(ATTRS[name]))]}
            gt.append(box)
            if rng.random() < 0.8:  # detected, with errors of every kind
                pred.append(dict(box, translation=list(np.array(box["translation"]) + rng.normal(0, 0.8, 3)),
                                 size=list(np.array(box["size"]) * rng.uniform(0.7, 1.3, 3)),
                                 rotation=_quat(np.arctan2(box["rotation"][3], box["rotation"][0]) * 2
                                                + rng.normal(0, 0.5)),
                                 velocity=list(rng.normal(0, 3, 2)),
                                 attribute_name=ATTRS[name][rng.integers(len(ATTRS[name]))],
                                 detection_score=float(np.round(rng.uniform(0, 1), 1))))  # ties on purpose
        for _ in range(rng.integers(0, 4)):  # false positives
            name = CLASSES[rng.integers(len(CLASSES))]
            pred.append({"sample_token": token, "translation": [*rng.uniform(-30, 30, 2), 1.0],
                         "size": [1.5, 4.0, 1.6], "rotation": _quat(0.3), "velocity": [0.0, 0.0],
                         "detection_name": name, "attribute_name": ATTRS[name][0],
                         "detection_score": float(np.round(rng.uniform(0, 1), 1))})
    return gt, pred


def _devkit_boxes(records: list[dict]):
    from nuscenes.eval.common.data_classes import EvalBoxes
    from nuscenes.eval.detection.data_classes import DetectionBox

    boxes = EvalBoxes()
    by_sample: dict[str, list] = {}
    for r in records:
        by_sample.setdefault(r["sample_token"], []).append(DetectionBox(
            sample_token=r["sample_token"], translation=tuple(r["translation"]), size=tuple(r["size"]),
            rotation=tuple(r["rotation"]), velocity=tuple(r["velocity"]), detection_name=r["detection_name"],
            detection_score=r.get("detection_score", -1.0), attribute_name=r["attribute_name"]))
    for token, bs in by_sample.items():
        boxes.add_boxes(token, bs)
    return boxes


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_accumulate_calc_ap_and_calc_tp_agree_with_the_nuscenes_devkit(seed):
    from nuscenes.eval.common.utils import center_distance
    from nuscenes.eval.detection import algo

    gt, pred = _random_case(seed)
    ours_gt, ours_pred = Boxes.from_records(gt), Boxes.from_records(pred)
    dk_gt, dk_pred = _devkit_boxes(gt), _devkit_boxes(pred)
    compared = 0
    for name in CLASSES:
        for th in (0.5, 1.0, 2.0, 4.0):
            want = algo.accumulate(dk_gt, dk_pred, name, center_distance, th)
            got = accumulate(ours_gt, ours_pred, name, th)
            for field in ("recall", "precision", "confidence", *TP_METRICS):
                np.testing.assert_allclose(getattr(got, field), getattr(want, field), atol=1e-6, err_msg=field)
            assert calc_ap(got, 0.1, 0.1) == pytest.approx(algo.calc_ap(want, 0.1, 0.1), abs=1e-6)
            for metric in TP_METRICS:
                assert calc_tp(got, 0.1, metric) == pytest.approx(algo.calc_tp(want, 0.1, metric), abs=1e-6)
            compared += want.max_recall_ind > 0
    assert compared >= 8  # most classes and thresholds had matches: the comparison is not of empty curves


def test_perfect_predictions_score_one_and_a_half_right_set_scores_what_the_protocol_says():
    gt, _ = _random_case(7, n_samples=8)
    gt = [g for g in gt if g["detection_name"] == "car"]
    perfect = [dict(g, detection_score=0.9) for g in gt]
    config = DetectionConfig(class_names=("car",))
    m = evaluate(Boxes.from_records(gt), Boxes.from_records(perfect), config)
    assert m.mean_ap == pytest.approx(1.0) and m.label_tp_errors["car"]["trans_err"] == pytest.approx(0.0)
    # every other ground truth box found: precision 1 up to recall 0.5, then 0 -> AP = (0.5 - 0.1 ... ) by hand
    half = [dict(g, detection_score=0.9) for g in gt[::2]]
    recall = len(half) / len(gt)
    m = evaluate(Boxes.from_records(gt), Boxes.from_records(half), config)
    points = np.linspace(0, 1, 101)[11:]
    want = np.mean(np.where(points <= recall + 1e-12, 0.9, 0.0)) / 0.9
    assert m.label_aps["car"][2.0] == pytest.approx(want, abs=1e-9)


def test_nds_from_map_and_the_errors_by_its_formula():
    gt, pred = _random_case(11)
    m = evaluate(Boxes.from_records(gt), Boxes.from_records(pred), DetectionConfig(class_names=CLASSES))
    scores = [max(0.0, 1.0 - m.tp_errors[k]) for k in TP_METRICS]
    assert m.nd_score == pytest.approx((5 * m.mean_ap + sum(scores)) / 10)
    out = m.to_dict()
    assert set(out["classes"]) == set(CLASSES) and out["classes"]["traffic_cone"]["tp_errors"]["vel_err"] is None
    assert all(np.isfinite(v) for v in (out["mAP"], out["NDS"], *out["tp_errors"].values()))


def test_no_ground_truth_or_no_prediction_gives_ap_zero_and_errors_one():
    gt, pred = _random_case(3)
    empty = Boxes.from_records([])
    for a, b in ((Boxes.from_records(gt), empty), (empty, Boxes.from_records(pred))):
        md = accumulate(a, b, "car", 2.0)
        assert calc_ap(md, 0.1, 0.1) == 0.0 and calc_tp(md, 0.1, "trans_err") == 1.0
    assert isinstance(MetricData.no_predictions().max_recall_ind, int)


def test_filters_drop_far_boxes_ground_truth_without_points_and_bicycles_in_racks():
    config = DetectionConfig()
    base = {"sample_token": "s", "size": [1, 2, 1], "rotation": _quat(0), "velocity": [0, 0], "attribute_name": ""}
    records = [dict(base, translation=[10, 0, 0], detection_name="car"),       # kept
               dict(base, translation=[60, 0, 0], detection_name="car"),       # beyond 50 m
               dict(base, translation=[35, 0, 0], detection_name="barrier"),   # beyond 30 m
               dict(base, translation=[5, 0, 0], detection_name="pedestrian"),  # no point in it
               dict(base, translation=[3, 3, 0], detection_name="bicycle"),    # in the rack
               dict(base, translation=[3, -3, 0], detection_name="bicycle")]   # not in a rack
    boxes = Boxes.from_records(records, ego_dist=[10, 60, 35, 5, 4.2, 4.2], num_pts=[3, 3, 3, 0, 2, 2])
    rack = np.diag([4.0, 2.0, 2.0, 1.0])
    rack[:3, 3] = [3, 3, 0]
    kept = filter_boxes(boxes, config, racks={"s": rack[None]})
    assert kept.translation[:, :2].tolist() == [[10, 0], [3, -3]]


def test_the_scene_bootstrap_of_a_map_difference_brackets_what_it_measures():
    """The same predictions twice differ by exactly 0 in every draw; the ground truth itself against nothing differs
    by +1 on the whole set and by more than 0 in every draw (a perfect detector beats a blind one whichever scenes are
    drawn; a draw without a class's boxes scores that class 0 for both); noisy against perfect lies strictly between,
    and the interval holds the observed difference. One scene is no sample to draw from."""
    from omniscs.errors import ValidationError
    from omniscs.eval.detection import bootstrap_map_difference

    gt_rec, pred_rec = _random_case(5, n_samples=8)
    config = DetectionConfig(class_names=CLASSES)
    gt, noisy = Boxes.from_records(gt_rec), Boxes.from_records(pred_rec)
    perfect = Boxes.from_records([dict(r, detection_score=1.0) for r in gt_rec])
    nothing = Boxes.from_records([])
    groups = {f"sample-{s}": f"scene-{s // 2}" for s in range(8)}  # 4 scenes of 2 samples
    same = bootstrap_map_difference(gt, noisy, noisy, groups, config, n=20)
    assert same["difference"] == 0.0 and same["low"] == same["high"] == 0.0 and same["share_b_better"] == 0.0
    blind = bootstrap_map_difference(gt, nothing, perfect, groups, config, n=20)
    assert blind["difference"] == pytest.approx(1.0) and 0.0 < blind["low"] <= blind["high"] <= 1.0 + 1e-9
    assert blind["share_b_better"] == 1.0 and blind["n_groups"] == 4
    mixed = bootstrap_map_difference(gt, noisy, perfect, groups, config, n=50, seed=1)
    assert 0.0 < mixed["difference"] < 1.0 and mixed["low"] <= mixed["difference"] <= mixed["high"]
    again = bootstrap_map_difference(gt, noisy, perfect, groups, config, n=50, seed=1)
    assert again == mixed  # seeded
    with pytest.raises(ValidationError, match="at least two groups"):
        bootstrap_map_difference(gt, noisy, perfect, {t: "one" for t in groups}, config)
