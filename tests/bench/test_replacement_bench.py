"""The replacement case of the background bench: what counts as ghost, and how scenes pool."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.bench.replacement import ghost_scores, replacement_markdown, summary
from omniscs.pipeline.background import background_stage
from tests.background.test_repair import SMALL, TRUCK, fitted  # noqa: F401  (fitted: the module fixture)


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


@pytest.mark.slow
def test_a_smaller_replacement_shows_less_ghost_on_the_repaired_graph(fitted):
    """The truck replaced by the passing sedan's model, on the graph as fitted and on the repaired graph, against
    the world with the same replacement: the repaired graph leaves fewer wrong pixels where the truck stood."""
    from omniscs.bench.replacement import uncovered_region
    from omniscs.edits import ReplaceModel
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.edit import apply_graph_edits
    from omniscs.scene import load_scene
    from omniscs.world import WorldRenderer, apply_edits

    store, plan, record, tmp = fitted
    scene = load_scene(store)
    graph = load_graph(record.path, scene)
    repaired = load_graph(background_stage(store, plan, record, tmp / "ws", config=SMALL).path, scene)
    size = tuple(float(v) for v in graph.agent(2).size)
    truth = WorldRenderer(apply_edits(scene.world, [ReplaceModel(TRUCK, "sedan-0011", size=size)]))
    logged = WorldRenderer(scene.world)
    swap = [ReplaceModel(TRUCK, "nsg:2", size=size)]
    before_graph, after_graph = apply_graph_edits(graph, swap), apply_graph_edits(repaired, swap)
    before = after = region_pixels = 0
    for f in range(scene.n_frames):
        for cam in scene.camera_names:
            exact, region = uncovered_region(logged, truth, TRUCK, f, cam)
            if not region.any():
                continue
            scores = []
            for g in (before_graph, after_graph):
                rgb = (g.render(g.view(cam, f)).rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
                scores.append(ghost_scores(rgb, exact, region, 24))
            region_pixels += scores[0]["region_pixels"]
            before += scores[0]["ghost_pixels"]
            after += scores[1]["ghost_pixels"]
    assert region_pixels > 200
    assert after < 0.8 * before, (before, after, region_pixels)
