"""The viewer benchmark: its densifying rule and the agents it edits on a small initial graph, and the quick run end
to end in Debian's headless chromium (slow: a short fit, two splat counts in the browser, three edits)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    """The initial (unfitted) scene graph of a thumbnail log, a few thousand Gaussians: cars 20 m and 11 m ahead of
    the ego (the second half a lane to the left) and one 8 m behind it, all keeping pace."""
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import make_plan
    from omniscs.scene import load_scene

    agents = ({"x": 20.0, "y": 0.0, "speed": 6.0}, {"x": 11.0, "y": 1.5, "speed": 6.0},
              {"x": -8.0, "y": 0.0, "speed": 6.0})
    world = nsg_world(agents, n_frames=4)
    scene = load_scene(write_nsg_scene(tmp_path_factory.mktemp("view-bench") / "scene", world))
    config = tiny_fit_config()
    return initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))


def test_densifying_adds_exactly_the_missing_gaussians_as_fainter_nearby_copies_the_same_every_time(graph):
    from omniscs.bench.view import densified

    count = graph.n_gaussians * 3 + 7
    dense = densified(graph, count, seed=0, opacity_share=0.5)
    assert dense.n_gaussians == count and dense.agents == graph.agents
    bg, n = graph.background, len(graph.background)
    extra = count - graph.n_gaussians
    copies = dense.background.select(torch.arange(n, n + extra))
    source = torch.arange(extra) % n
    assert torch.equal(dense.background.means[:n], bg.means)
    assert torch.allclose(torch.sigmoid(copies.opacity_logits), 0.5 * torch.sigmoid(bg.opacity_logits[source]),
                          atol=1e-5)
    assert torch.equal(copies.sh_dc, bg.sh_dc[source]) and torch.equal(copies.log_scales, bg.log_scales[source])
    offset = (copies.means - bg.means[source]).norm(dim=1) / bg.log_scales[source].exp().max(dim=1).values
    assert 0.5 < float(offset.median()) < 3.0  # about one of its own scales away, never on top of it
    again = densified(graph, count, seed=0, opacity_share=0.5)
    assert torch.equal(again.background.means, dense.background.means)
    assert densified(graph, graph.n_gaussians - 1) is graph  # fewer: the viewer's budget keeps the most opaque


def test_the_edited_agents_are_those_in_front_of_the_camera_nearest_first(graph):
    from omniscs.bench.view import busiest_frame, resized_cameras, seen_agents

    assert graph.agent_ids == (1, 2, 3)
    assert seen_agents(graph, 0) == [2, 1]  # the car 11 m ahead, then the one 20 m ahead; not the one behind
    turned = graph.replace(world_from_ego=np.stack([e @ np.diag([-1.0, -1.0, 1.0, 1.0]) for e in graph.world_from_ego]))
    assert seen_agents(turned, 0) == [3]  # the ego turned round: only the car that was behind
    assert busiest_frame(graph) in range(graph.n_frames)
    big = resized_cameras(graph, 640, 360)
    assert (big.cameras[0].width, big.cameras[0].height) == (640, 360)
    assert seen_agents(big, 0) == seen_agents(graph, 0)  # the same viewpoint, more pixels


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed (make system-deps)")
def test_the_quick_benchmark_times_the_splat_view_and_edits_and_writes_a_screenshot(tmp_path):
    pytest.importorskip("playwright.sync_api")
    from omniscs.bench.view import quick_config, run_view_benchmark

    config = quick_config()
    run_view_benchmark(tmp_path / "reports", tmp_path / "ws", config)
    folder = tmp_path / "reports" / "view"
    report = json.loads((folder / "report.json").read_text())
    rows = report["splat_view"]
    assert [r["gaussians"] for r in rows] == list(config.counts)
    for r in rows:
        assert r["drawn_splats"] == r["gaussians"]
        assert not r["blank"] and r["changed_vs_empty"] > 0.05, "the splats were not drawn"
        assert 0 <= r["first_frame_after_s"] < r["first_frame_s"] <= r["settled_s"] + 1.0
        assert r["orbit_frames"] > 0 and r["orbit_changed_view"] > 0.02, "the orbit did not move the view"
    e = report["edit_latency"]
    assert e["accepted"] == config.edits and e["timed"] == config.edits
    assert 0 < e["handler"]["median_s"] <= e["shown"]["median_s"] and e["handler_no_browser"]["median_s"] > 0
    assert all(r["frames_drawn_until_shown"] >= 0 for r in report["edits"] if r["browser"])
    assert all(r["image_size"] == "160x90" for r in report["edits"])
    assert report["machine"]["load_average_end"] and report["browser"]
    md = (folder / "report.md").read_text()
    assert "SwiftShader" in md and "first frame (s)" in md and "![the viewer](viewer.png)" in md
    for picture in ("viewer.png", "report.png"):
        assert 10_000 < (folder / picture).stat().st_size < 600_000
