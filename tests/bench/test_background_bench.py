"""The background bench's second reference: what the removed object's own light costs in the hole."""
from __future__ import annotations

import numpy as np

from omniscs.bench.background import EvalView, object_light_cost, score_view
from omniscs.quality import MAX_PSNR_DB


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


def test_the_hole_error_is_split_by_what_truly_lies_there_and_pooled():
    from omniscs.bench.background import class_errors, pooled_class_errors
    from omniscs.taxonomy import SEMANTIC_IDS

    gt = np.full((4, 4, 3), 100, np.uint8)
    hole = np.zeros((4, 4), bool)
    hole[:2] = True
    sem = np.full((4, 4), SEMANTIC_IDS["building"], np.uint8)
    sem[0, :3] = SEMANTIC_IDS["vegetation"]
    sem[3] = SEMANTIC_IDS["sky"]  # outside the hole: not counted
    view = EvalView("novel +1.5 m", "CAM_FRONT", 0, np.eye(4), gt, np.ones((4, 4), np.float32), hole, None, sem)
    rgb = gt.copy()
    rgb[0, 0] = (151, 100, 100)  # one vegetation pixel off by 51 levels in one channel
    got = class_errors(rgb, view)
    assert set(got) == {"vegetation", "building"}
    assert got["building"] == [5, 0.0]
    assert got["vegetation"][0] == 3 and np.isclose(got["vegetation"][1], (51 / 255) ** 2 / 3)
    pooled = pooled_class_errors([got, got, {}])
    assert pooled["vegetation"][0] == 6 and np.isclose(pooled["vegetation"][1], 2 * got["vegetation"][1])
    # a view without the semantic render is left out
    bare = EvalView("novel +1.5 m", "CAM_FRONT", 0, np.eye(4), gt, np.ones((4, 4), np.float32), hole, None)
    assert class_errors(rgb, bare) == {}


def test_the_report_table_pools_scenes_and_ranks_classes_by_their_share_of_the_error():
    from omniscs.bench.background import CLASS_ARMS, class_table

    naive, cleaned, default = CLASS_ARMS
    scenes = [{"classes": {naive: {"novel": {"sky": [10, 1.0], "road": [30, 3.0]}},
                           cleaned: {"novel": {"sky": [10, 0.1], "road": [30, 0.3]}},
                           default: {"novel": {"sky": [10, 0.1], "road": [30, 0.03]}}}},
              {"classes": {default: {"novel": {"sky": [10, 0.1]}}}}]
    rows = class_table(scenes)
    assert len(rows) == 4  # header, rule, two classes
    sky, road = rows[2].split(" | "), rows[3].split(" | ")
    assert sky[0] == "| sky" and road[0] == "| road"  # sky holds 0.2 of the default's 0.23
    assert sky[1] == "40.0 %" and road[1] == "60.0 %"  # 20 + 30 of 50 pixels, pooled over both scenes
    assert float(road[4]) == 30.0  # 10 log10(30 / 0.03)
    assert float(sky[2]) == 10.0  # naive: only the first scene has it, 10 px with 1.0
    assert sky[-1] == "87 % |"
    assert class_table([{"classes": {}}]) == []
