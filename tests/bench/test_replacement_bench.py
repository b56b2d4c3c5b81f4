"""The replacement case of the background bench: what counts as ghost, and how scenes pool."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.bench.replacement import ghost_scores, replacement_markdown, summary


def test_ghost_pixels_are_region_pixels_off_by_more_than_the_threshold_on_some_channel():
    truth = np.full((4, 6, 3), 100, np.uint8)
    region = np.zeros((4, 6), bool)
    region[:, :3] = True  # 12 region pixels
    rgb = truth.copy()
    rgb[0, 0] = (100, 100, 130)  # off by 30 in one channel: ghost
    rgb[1, 0] = (120, 120, 120)  # off by 20: within the threshold
    rgb[2, 5] = 0  # outside the region: not counted
    s = ghost_scores(rgb, truth, region, 24)
    assert (s["region_pixels"], s["ghost_pixels"]) == (12, 1) and s["ghost_share"] == pytest.approx(1 / 12)
    mse = ((30 / 255) ** 2 / 3 + (20 / 255) ** 2) / 12
    assert s["hole_psnr"] == pytest.approx(-10 * np.log10(mse), rel=1e-5)
    empty = ghost_scores(rgb, truth, np.zeros((4, 6), bool), 24)
    assert empty["ghost_share"] is None and empty["hole_psnr"] is None


def test_the_summary_pools_ghost_pixels_over_scenes_and_the_page_shows_both_arms():
    rows = [{"scene_id": s, "track_id": 1, "arm": arm, "views": kind, "n_views": 2, "region_pixels": 1000,
             "ghost_pixels": ghost, "ghost_share": ghost / 1000, "hole_psnr": psnr}
            for s, factor in (("a", 1), ("b", 3))
            for arm, ghost, psnr in (("no repair", 400 * factor // 3, 14.0), ("repaired", 50 * factor, 20.0))
            for kind in ("logged", "novel")]
    out = {(r["arm"], r["views"]): r for r in summary(rows)}
    assert out["no repair", "novel"]["ghost_pixels"] == 133 + 400 and out["repaired", "novel"]["ghost_share"] == 0.1
    assert out["repaired", "logged"]["hole_psnr"] == 20.0 and out["repaired", "logged"]["n_views"] == 4
    report = {"config": {"scenes": ["a", "b"], "n_frames": 20, "preset": "fast", "object_kind": "sedan",
                         "offsets_m": [1.5], "ghost_threshold": 24},
              "machine": {}, "seconds": 60.0, "summary": summary(rows),
              "scenes": [{"scene_id": "a", "category": "trailer", "track_id": 1, "size": [13.0, 2.5, 4.0],
                          "object_id": "pm-x", "object_size": [4.6, 1.8, 1.4], "repair_seconds": 9.0,
                          "repair_reused": False}]}
    page = replacement_markdown(report)
    assert "| no repair | novel | 4 | 2,000 | 533 | 26.7 % | 14.00 |" in page
    assert "| repaired | novel | 4 | 2,000 | 200 | 10.0 % | 20.00 |" in page
