"""The comparison plot of an evaluation run: a panel per task, split and scoring, each model's bars, and a value a
model lacks shown as missing, never as a zero."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from omniscs.errors import ValidationError
from omniscs.eval.comparison import _panels, comparison_png, write_comparison


def _row(model, task, split, metric, value, class_name="", horizon="", convention="", status="ok"):
    return {"eval_id": "e", "model_id": model, "dataset_id": "ds", "task": task, "split": split, "metric": metric,
            "class_name": class_name, "horizon": horizon, "convention": convention, "value": value, "n": 10,
            "status": status, "error": None if status == "ok" else "boom"}


ROWS = [
    _row("base", "detection", "variants", "mAP", 0.10), _row("tuned", "detection", "variants", "mAP", 0.15),
    _row("base", "detection", "variants", "AP", 0.30, "car"), _row("tuned", "detection", "variants", "AP", None, "car"),
    _row("base", "detection", "variants", "mAP", 0.20, convention="camera_view"),
    _row("tuned", "detection", "variants", "mAP", 0.25, convention="camera_view"),
    _row("base", "planning", "original", "L2", 0.7, horizon="3s", convention="uniad"),
    _row("tuned", "planning", "original", "L2", 0.6, horizon="3s", convention="uniad"),
    _row("base", "planning", "original", "L2", 0.5, horizon="3s", convention="stp3"),    # not drawn
    _row("base", "planning", "original", "collision", 0.05, horizon="3s", convention="uniad"),
    _row("tuned", "detection", "original", "run", None, status="failed"),                 # not drawn
]


def test_panels_split_task_split_and_scoring_and_keep_a_missing_value_missing():
    panels = _panels(ROWS)
    assert list(panels) == [("detection", "variants", "all round"), ("detection", "variants", "in the cameras' view"),
                            ("planning", "original", "uniad: L2 (m)"), ("planning", "original", "uniad: collision (%)")]
    variants = panels[("detection", "variants", "all round")]
    assert variants["mAP"] == {"base": pytest.approx(10.0), "tuned": pytest.approx(15.0)}  # in points
    assert variants["AP car"] == {"base": pytest.approx(30.0), "tuned": None}
    assert panels[("planning", "original", "uniad: L2 (m)")]["3s"] == {"base": 0.7, "tuned": 0.6}
    assert panels[("planning", "original", "uniad: collision (%)")]["3s"] == {"base": pytest.approx(5.0)}


def test_the_plot_is_a_picture_and_a_run_with_nothing_to_draw_is_a_clear_error(tmp_path):
    out = write_comparison(ROWS, tmp_path / "runs" / "comparison.png", "run r1")
    image = cv2.imread(str(out))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 600
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 10  # bars in colour, not a blank canvas
    with pytest.raises(ValidationError, match="no evaluation row to draw"):
        comparison_png([ROWS[-1]])
