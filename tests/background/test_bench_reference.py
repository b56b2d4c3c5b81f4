"""The background bench's second reference: what the removed object's own light costs in the hole."""
from __future__ import annotations

import numpy as np

from omniscs.bench.background import EvalView, object_light_cost, score_view
from omniscs.nsg.metrics import MAX_PSNR_DB


def _view(kind: str, gt: np.ndarray, lit: np.ndarray | None, hole: np.ndarray) -> EvalView:
    return EvalView(kind, "CAM_FRONT", 0, np.eye(4), gt, np.ones(gt.shape[:2], np.float32), hole, lit)


def test_the_cost_is_pooled_over_hole_pixels_and_counts_what_the_shadow_changes():
    gt = np.full((4, 4, 3), 200, np.uint8)
    hole = np.zeros((4, 4), bool)
    hole[:2] = True  # 8 hole pixels per view
    shaded = gt.copy()
    shaded[0, :2] = 100  # a shadow on 2 of them
    shaded[3] = 0  # outside the hole: not counted
    views = [_view("logged", gt, gt.copy(), hole), _view("novel +1.5 m", gt, shaded, hole),
             _view("novel -1.5 m", gt, gt.copy(), hole)]
    cost = object_light_cost(views)
    assert cost["logged"] == {"pooled_hole_psnr": MAX_PSNR_DB, "changed_share": 0.0, "views": 1}
    # 2 of 16 novel hole pixels are off by 100 levels in every channel
    mse = 2 * (100 / 255) ** 2 / 16
    assert np.isclose(cost["novel"]["pooled_hole_psnr"], -10 * np.log10(mse))
    assert cost["novel"]["changed_share"] == 2 / 16 and cost["novel"]["views"] == 2


def test_views_without_the_second_reference_are_left_out_and_score_none():
    gt = np.full((16, 16, 3), 50, np.uint8)  # SSIM's window needs more than 11 pixels a side
    hole = np.ones((16, 16), bool)
    view = _view("logged", gt, None, hole)
    assert object_light_cost([view]) == {}
    assert score_view(gt, None, view)["hole_psnr_lit"] is None
    lit = _view("logged", gt, gt.copy(), hole)
    assert score_view(gt, None, lit)["hole_psnr_lit"] == MAX_PSNR_DB


def test_the_ablations_can_be_picked_and_an_unknown_one_is_refused():
    import dataclasses

    import pytest

    from omniscs.bench.background import EXTRA_ARMS, PLANES_AGREE_ARM, BackgroundBenchConfig
    from omniscs.errors import OmniscsError

    assert BackgroundBenchConfig().extra_arms() == EXTRA_ARMS
    picked = BackgroundBenchConfig(ablations=(PLANES_AGREE_ARM, EXTRA_ARMS[0]))
    assert picked.extra_arms() == (EXTRA_ARMS[0], PLANES_AGREE_ARM)  # in the report's order
    assert dataclasses.replace(picked, full_comparison=False).extra_arms() == ()
    with pytest.raises(OmniscsError, match="unknown ablation"):
        BackgroundBenchConfig(ablations=("planes, but better",))
