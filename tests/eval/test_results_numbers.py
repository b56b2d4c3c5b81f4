"""Results files whose numbers are JSON but wrong are refused with the entry named: strings or booleans for numbers,
sizes and coordinates beyond any real box or place, a near-zero quaternion, a score outside [0, 1], a speed
beyond 200 m/s; planning waypoints alike. Good entries pass."""
from __future__ import annotations

import math

import pytest

from omniscs.errors import ValidationError
from omniscs.eval.nuscenes_io import _checked_box, load_planning_results

GOOD = {"sample_token": "s", "translation": [1.0, 2.0, 0.5], "size": [1.8, 4.5, 1.6], "rotation": [1, 0, 0, 0],
        "velocity": [0.5, 0.0], "detection_name": "car", "detection_score": 0.5, "attribute_name": ""}


@pytest.mark.parametrize("change, message", [
    ({"size": ["1.8", "4.5", "1.6"]}, "not strings or booleans"),
    ({"translation": [1.0, True, 0.5]}, "not strings or booleans"),
    ({"detection_score": "0.9"}, "not strings or booleans"),
    ({"size": [1.8, 1e300, 1.6]}, "at most 100 m"),
    ({"size": [1.8, 0.0, 1.6]}, "positive"),
    ({"translation": [1e7, 0.0, 0.0]}, "beyond"),
    ({"rotation": [1e-30, 0.0, 0.0, 0.0]}, "not a quaternion"),
    ({"detection_score": 1.5}, r"\[0, 1\]"),
    ({"velocity": [1e5, 0.0]}, "200 m/s"),
    ({"velocity": [math.inf, 0.0]}, "finite"),
    ({"size": [1.8, 4.5]}, "needs 3 numbers"),
])
def test_a_detection_box_with_wrong_numbers_is_refused(change, message):
    with pytest.raises(ValidationError, match=message):
        _checked_box({**GOOD, **change}, "results['s'][0]")


def test_good_boxes_pass_and_an_unknown_velocity_is_nan():
    assert _checked_box(GOOD, "b")["size"] == [1.8, 4.5, 1.6]
    box = dict(GOOD)
    del box["velocity"]
    assert all(math.isnan(v) for v in _checked_box(box, "b")["velocity"])


@pytest.mark.parametrize("trajectory", [[["1", "2"]] * 6, [[True, 0.0]] * 6, [[1e7, 0.0]] * 6])
def test_planning_waypoints_must_be_numbers_near_the_ego(trajectory, tmp_path):
    data = {"results": {"k": {"trajectory": trajectory}}}
    with pytest.raises(ValidationError, match="waypoint"):
        load_planning_results(tmp_path / "r.json", ["k"], data=data)
    ok = load_planning_results(tmp_path / "r.json", ["k"], data={"results": {"k": [[0.0, float(i)] for i in range(6)]}})
    assert ok["k"].shape == (6, 2)
