"""L_app rendered by the Gaussian scene graph: differentiable agent poses, the plan for behaviour variants,
gradients that reach the trajectories, and finite values at the extremes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene
from omniscs.pipeline.request import RunRequest
from omniscs.errors import OmniscsError
from omniscs.gaussians import activate
from omniscs.geometry import pose_from_xyz_yaw
from omniscs.nsg.compose import NodePose, place_gaussians
from omniscs.nsg.graph import render_view
from omniscs.nsg.train import fit_scene
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from omniscs.scs.behavior import adversarial_preset, generate_variants, traffic_from_scene
from omniscs.scs.behavior.checkpoint import load_traffic_model
from omniscs.scs.behavior.scene_render import (RenderConsistencyConfig, GraphTrajectoryRenderer,
                                                scene_graph_render_consistency)

#: A car in the next lane ahead of the ego and an oncoming one: both can reach the ego path.
AGENTS = ({"x": 14.0, "y": 3.3, "speed": 5.0, "asset": "sedan-0003"},
          {"x": 30.0, "y": 6.6, "speed": -6.0, "asset": "sedan-0011"},
          {"x": 20.0, "y": -4.0, "speed": 0.0, "asset": "sedan-0020"})


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A 40-frame thumbnail log (the behaviour model needs 1 s of history and 1 s of future) and its graph."""
    world = nsg_world(AGENTS, n_frames=40, width=64, height=36)
    root = tmp_path_factory.mktemp("lapp")
    scene = load_scene(write_nsg_scene(root / "scene", world))
    config = tiny_fit_config(30)
    plan = make_plan(scene, [], config.plan, behavior_variants=2)
    return scene, plan, fit_scene(scene, config, plan, checkpoint_dir=root / "nsg").graph


def test_plan_for_behavior_variants_makes_every_vehicle_a_node(fitted):
    scene, plan, graph = fitted
    assert plan.agent_nodes == (1, 2, 3)
    assert plan.node_reasons[3] == "behavior"  # parked: a node only because variants may move it
    assert plan.node_reasons[1] == "moving+behavior"
    assert make_plan(scene, [], tiny_fit_config(30).plan).agent_nodes == (1, 2)  # no variants: parked car stays
    assert graph.agent_ids == (1, 2, 3)


def test_node_pose_places_gaussians_exactly_like_the_matrix():
    g = torch.Generator().manual_seed(0)
    from omniscs.gaussians import params_from_values
    local = activate(params_from_values(torch.randn(50, 3, generator=g, dtype=torch.float64),
                                        torch.rand(50, 3, generator=g, dtype=torch.float64) * 0.3 + 0.01,
                                        torch.full((50,), 0.5, dtype=torch.float64),
                                        torch.rand(50, 3, generator=g, dtype=torch.float64), 1))
    for yaw in (0.0, 0.7, math.pi, -2.5):
        T = pose_from_xyz_yaw(3.0, -2.0, 0.8, yaw)
        by_matrix = place_gaussians(local, T)
        pose = NodePose.from_xy_yaw(torch.tensor(3.0, dtype=torch.float64), torch.tensor(-2.0, dtype=torch.float64),
                                    torch.tensor(yaw, dtype=torch.float64), 0.8)
        by_pose = place_gaussians(local, pose)
        assert torch.allclose(by_pose.means, by_matrix.means, atol=1e-12)
        # same rotation up to the sign of the quaternion
        dots = (by_pose.quats * by_matrix.quats).sum(-1) / (by_pose.quats.norm(dim=-1) * by_matrix.quats.norm(dim=-1))
        assert torch.allclose(dots.abs(), torch.ones_like(dots), atol=1e-12)


def test_rendering_logged_poses_as_node_poses_changes_nothing(fitted):
    _, _, graph = fitted
    f = 20
    view = graph.view(graph.cameras[0].name, f)
    poses = {}
    for a in graph.agents:
        T = a.world_from_agent[f]
        yaw = math.atan2(T[1, 0], T[0, 0])
        poses[a.track_id] = NodePose.from_xy_yaw(torch.tensor(T[0, 3]), torch.tensor(T[1, 3]), torch.tensor(yaw),
                                                 T[2, 3])
    with torch.no_grad():
        plain = render_view(graph, view).rgb
        posed = render_view(graph, view, agent_poses=poses).rgb
    assert torch.allclose(plain, posed, atol=1e-5)
    with pytest.raises(OmniscsError, match="not agent nodes"):
        render_view(graph, view, agent_poses={99: poses[1]})


def test_a_static_layer_renders_the_same_image_and_gradients_with_fewer_gaussians(fitted):
    from omniscs.nsg.graph import static_layer

    _, _, graph = fitted
    for f, downscale in ((20, 1), (35, 2)):
        view = graph.view(graph.cameras[0].name, f).downscaled(downscale)
        layer = static_layer(graph, view)
        assert 0 < len(layer.means) < layer.kept_of == len(graph.background)  # culled, not emptied
        outs = []
        for static in (None, layer):
            T = graph.agent(1).world_from_agent[f]
            x = torch.tensor(T[0, 3] + 0.7, requires_grad=True)
            pose = NodePose.from_xy_yaw(x, torch.tensor(T[1, 3]), torch.tensor(math.atan2(T[1, 0], T[0, 0])), T[2, 3])
            out = render_view(graph, view, agent_poses={1: pose}, static=static)
            out.rgb.sum().backward()
            outs.append((out.rgb.detach(), float(x.grad)))
        assert torch.allclose(outs[0][0], outs[1][0], atol=1e-5)
        assert outs[0][1] != 0.0 and outs[1][1] == pytest.approx(outs[0][1], rel=1e-4, abs=1e-5)
    other = graph.view(graph.cameras[0].name, 21).downscaled(2)
    with pytest.raises(OmniscsError, match="static layer was made for frame 35"):
        render_view(graph, other, static=layer)


def test_agent_culling_leaves_the_image_unchanged_and_drops_agents_that_cannot_show(fitted):
    from omniscs.nsg.graph import agent_may_show
    from omniscs.nsg.observations import View

    _, _, graph = fitted
    view = graph.view(graph.cameras[0].name, 20).downscaled(2)
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    cam = View(0, np.eye(4), K, 100, 80)  # looking down +z
    assert agent_may_show(cam, [0, 0, 10], 1.0, 0.2)
    assert not agent_may_show(cam, [0, 0, -5], 1.0, 0.2)              # behind the camera
    assert agent_may_show(cam, [0, 0, -0.5], 1.0, 0.2)                # straddles the near plane
    assert not agent_may_show(cam, [40, 0, 10], 1.0, 0.2)             # far to the right (x/z = 4 > 1.0 with margin)
    assert agent_may_show(cam, [40, 0, 10], 30.0, 0.2)                # unless it is that large
    renderer = GraphTrajectoryRenderer(graph, np.arange(40), np.arange(10, 40),
                                       RenderConsistencyConfig(frames=3, downscale=2))
    g = torch.Generator().manual_seed(5)
    for trial in range(6):
        poses = {}
        for a in graph.agents:
            T = a.world_from_agent[20]
            dx, dy = (torch.randn(2, generator=g) * 6.0).tolist()
            if trial == 5 and a.track_id == 1:
                dx = -10_000.0  # ten kilometres behind
            poses[a.track_id] = NodePose.from_xy_yaw(torch.tensor(T[0, 3] + dx), torch.tensor(T[1, 3] + dy),
                                                     torch.tensor(float(torch.rand(1, generator=g)) * 6.0), T[2, 3])
        shown = renderer.showing(view, poses)
        with torch.no_grad():
            full = render_view(graph, view, agent_poses=poses).rgb
            culled = render_view(graph, view, agent_poses=poses, only_agents=shown).rgb
        assert torch.allclose(full, culled, atol=1e-6)
        if trial == 5:
            assert 1 not in shown and len(shown) == len(graph.agents) - 1


def _trajectories(fitted, shift: float = 0.0, far: float = 0.0):
    scene, _, graph = fitted
    traffic = traffic_from_scene(scene)
    model = load_traffic_model()
    config = adversarial_preset("fast")
    term = scene_graph_render_consistency(graph, traffic, model, config, RenderConsistencyConfig(downscale=1, frames=3))
    steps = np.arange(10, 40)
    ids = [int(t) for t in traffic.track_ids]
    poses = torch.from_numpy(np.stack([np.concatenate([traffic.xy[i, steps], traffic.yaw[i, steps, None]], -1)
                                       for i in range(len(ids))])).to(torch.float32)
    poses[0, :, 1] += shift
    poses[0, :, 0] += far
    poses.requires_grad_(True)
    from omniscs.scs.behavior.render_consistency import AgentTrajectories
    return term, AgentTrajectories(ids, poses, steps, traffic.timestamps_us[steps]), poses


def test_l_app_is_small_on_the_log_and_grows_and_has_gradients_when_an_agent_moves(fitted):
    term, logged, _ = _trajectories(fitted)
    at_log = float(term(logged).detach())
    term, moved, poses = _trajectories(fitted, shift=-2.0)
    value = term(moved)
    value.backward()
    assert math.isfinite(float(value.detach())) and float(value.detach()) > at_log + 1e-3
    grad = poses.grad
    assert torch.isfinite(grad).all()
    assert grad[0].abs().sum() > 0  # the moved car's trajectory receives a gradient


def test_l_app_stays_finite_for_an_agent_ten_kilometres_away(fitted):
    term, far, poses = _trajectories(fitted, far=10_000.0)
    value = term(far)
    value.backward()
    assert math.isfinite(float(value))
    assert torch.isfinite(poses.grad).all()


def test_variants_with_l_app_record_it_and_stay_finite(fitted):
    scene, _, graph = fitted
    traffic = traffic_from_scene(scene)
    model = load_traffic_model()
    config = adversarial_preset("fast")
    term = scene_graph_render_consistency(graph, traffic, model, config)
    (variant,) = generate_variants(traffic, model, 1, config, term)
    assert variant.losses["L_app"] is not None and math.isfinite(variant.losses["L_app"])
    assert all(math.isfinite(v) for v in variant.losses.values() if v is not None)


def test_renderer_refuses_resampled_logs_and_foreign_graphs(fitted):
    scene, _, graph = fitted
    with pytest.raises(OmniscsError, match="resampled"):
        GraphTrajectoryRenderer(graph, None, np.arange(10, 20))
    traffic = traffic_from_scene(scene)
    import dataclasses
    other = dataclasses.replace(traffic, scene_id="another-scene")
    with pytest.raises(OmniscsError, match="does not belong"):
        scene_graph_render_consistency(graph, other, load_traffic_model())


@pytest.mark.slow
def test_flow_feeds_the_fitted_graph_to_the_behavior_stage_and_reuses_variants_with_l_app(prefect_harness, tmp_path,
                                                                                         monkeypatch):
    from flows.generate import generate_dataset
    from omniscs import catalog
    from omniscs.nsg.config import PRESETS

    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(10))
    store = write_nsg_scene(tmp_path / "scene", nsg_world(AGENTS, n_frames=40, width=64, height=36))
    ws = tmp_path / "ws"
    out = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), previews=False, fit_preset="fast",
                           behavior_variants=1, behavior_preset="fast", run_id="r1"))
    stages = out["scenes"][0]["stages"]
    assert stages["fit"]["info"]["status"] == "fitted"
    assert stages["behavior"]["info"]["appearance_term"] is True and not stages["behavior"]["reused"]
    again = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), previews=False, fit_preset="fast",
                             behavior_variants=1, behavior_preset="fast", run_id="r2"))["scenes"][0]["stages"]
    assert again["fit"]["reused"] and again["behavior"]["reused"] and again["behavior"]["path"] == stages["behavior"]["path"]
    rows = catalog.query(catalog.catalog_root(ws), "SELECT run_id, loss_app FROM variants_by_run ORDER BY 1").to_pylist()
    assert [r["run_id"] for r in rows] == ["r1", "r2"] and rows[0]["loss_app"] == rows[1]["loss_app"] is not None
    models = catalog.query(catalog.catalog_root(ws), "SELECT agent_nodes FROM models").to_pylist()
    assert models[0]["agent_nodes"] == [1, 2, 3]  # the parked car too: variants may move it


def test_scs_behavior_with_nsg_reports_l_app(fitted, tmp_path):
    import json

    from typer.testing import CliRunner

    from omniscs.cli import app

    scene, _, _ = fitted
    out = tmp_path / "beh"
    result = CliRunner().invoke(app, ["scs", "behavior", str(scene.path), "--variants", "1", "--preset", "fast",
                                      "--nsg", str(scene.path.parent / "nsg"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    (variant,) = json.loads((out / "variants.json").read_text())
    assert variant["losses"]["L_app"] is not None and math.isfinite(variant["losses"]["L_app"])
    refused = CliRunner().invoke(app, ["scs", "behavior", "syn:straight:0", "--variants", "1", "--nsg",
                                       str(scene.path.parent / "nsg"), "--out", str(tmp_path / "x")])
    assert refused.exit_code != 0 and not (tmp_path / "x").exists()
