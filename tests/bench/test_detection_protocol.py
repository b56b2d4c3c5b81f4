"""The detection protocol end to end on one train and one test scene (slow: it fits two scene graphs and renders
their appearance variants)."""
from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.mark.slow
def test_the_quick_detection_protocol_reports_both_test_sets_for_base_and_fine_tuned(tmp_path):
    from omniscs.bench.detection_protocol import quick_config, run_detection_protocol

    run_detection_protocol(tmp_path / "reports", tmp_path / "ws", quick_config())
    report = json.loads((tmp_path / "reports" / "downstream" / "detection.json").read_text())
    assert set(report["rows"]) == {"appearance-SCS test", "original test"}
    for models in report["rows"].values():
        assert set(models) == {"base", "fine-tuned"}
        for m in models.values():
            assert m["n_samples"] > 0 and 0.0 <= m["mAP"] <= 1.0 and np.isfinite(m["NDS"]) and m["classes"]
            for k in m["classes"]:  # the class's AP is the mean of its APs at the four distance thresholds
                assert list(m["AP_by_threshold"][k]) == ["0.5", "1", "2", "4"]
                assert np.mean(list(m["AP_by_threshold"][k].values())) == pytest.approx(m["AP"][k])
    # the appearance-SCS test set holds the composited objects' classes besides the log's own
    scs_boxes = report["rows"]["appearance-SCS test"]["base"]["gt_boxes"]
    assert sum(scs_boxes.values()) > sum(report["rows"]["original test"]["base"]["gt_boxes"].values())
    assert (tmp_path / "reports" / "downstream" / "detection.png").stat().st_size > 5_000
    assert "proxy" in (tmp_path / "reports" / "downstream" / "detection.md").read_text()
    # the gain's interval: the appearance-SCS test set (the log's variants) has scenes to resample, the one log not
    intervals = report["summary"]["intervals"]
    scs = intervals["appearance-SCS test"]
    assert scs["n_groups"] >= 2 and scs["low"] <= scs["difference"] <= scs["high"]
    assert intervals["original test"] is None
    # scored in the cameras' view, and the same detections all round: a box in view is counted all round too
    assert report["config"]["camera_view"] and set(report["all_round_rows"]) == set(report["rows"])
    for name, models in report["rows"].items():
        for k, n in models["base"]["gt_boxes"].items():
            assert n <= report["all_round_rows"][name]["base"]["gt_boxes"][k]
    assert set(report["summary"]["all_round"]) >= {"scs_map_gain", "original_map_change", "intervals"}
    assert "all round" in (tmp_path / "reports" / "downstream" / "detection.md").read_text()


def test_the_kept_candidate_gains_most_within_the_regression_limit_else_loses_least():
    from omniscs.bench.detection_protocol import choose_candidate

    val = [{"scs_gain": 0.02, "logs_change": 0.0}, {"scs_gain": 0.08, "logs_change": -0.03},
           {"scs_gain": 0.05, "logs_change": -0.005}]
    assert choose_candidate(val, 0.01) == 2  # the largest gain (0.08) loses 3 points on the logs
    assert choose_candidate(val, 0.05) == 1
    worse = [{"scs_gain": 0.1, "logs_change": -0.04}, {"scs_gain": 0.0, "logs_change": -0.02}]
    assert choose_candidate(worse, 0.01) == 1  # none within: the one losing least
    with pytest.raises(ValueError):
        choose_candidate([], 0.01)


def test_object_ranges_that_overlap_between_train_validation_and_test_are_refused():
    from omniscs.bench.detection_protocol import DetectionProtocolConfig
    from omniscs.errors import ValidationError

    DetectionProtocolConfig(train_objects=((0, 6), (10, 16)), val_objects=(8, 10), test_objects=(6, 8))
    with pytest.raises(ValidationError, match="train_objects and test_objects share pool indices \\[6\\]"):
        DetectionProtocolConfig(train_objects=(0, 7))
    with pytest.raises(ValidationError, match="val_objects and test_objects"):
        DetectionProtocolConfig(val_objects=(5, 7), train_objects=(0, 5))
    with pytest.raises(ValidationError, match="start < stop"):
        DetectionProtocolConfig(val_objects=(9, 8))
    with pytest.raises(ValidationError, match="candidate"):
        DetectionProtocolConfig(candidates=())


def test_a_split_whose_dataset_name_holds_other_scenes_is_refused_not_overwritten(tmp_path):
    import json

    from omniscs.bench.detection_protocol import check_dataset_free
    from omniscs.errors import ValidationError
    from omniscs.pipeline import layout

    check_dataset_free(tmp_path, "det-scs-test-2x4", {"a", "b"})  # no such dataset yet: free
    folder = layout.dataset_folder(tmp_path, "det-scs-test-2x4")
    folder.mkdir(parents=True)
    (folder / "dataset.json").write_text(json.dumps({"variants": [{"scene_id": "a"}, {"scene_id": "b"}]}))
    check_dataset_free(tmp_path, "det-scs-test-2x4", {"a", "b"})  # the same scenes: reused
    with pytest.raises(ValidationError, match="already holds other scenes"):
        check_dataset_free(tmp_path, "det-scs-test-2x4", {"a", "c"})
    assert json.loads((folder / "dataset.json").read_text())["variants"][1]["scene_id"] == "b"  # untouched


def test_a_split_with_other_logs_gets_another_dataset_name():
    from omniscs.bench.detection_protocol import split_dataset_id

    a = split_dataset_id("test", ("straight:7501", "t_junction:7502"), 4)
    assert a == split_dataset_id("test", ("straight:7501", "t_junction:7502"), 4)  # the same split: the same dataset
    assert a.startswith("det-scs-test-2x4-")
    others = {split_dataset_id("test", ("straight:7601", "t_junction:7602"), 4),
              split_dataset_id("val", ("straight:7501", "t_junction:7502"), 4),
              split_dataset_id("test", ("straight:7501", "t_junction:7502"), 2)}
    assert a not in others and len(others) == 3
