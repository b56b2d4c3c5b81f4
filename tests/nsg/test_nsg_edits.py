"""Editing a scene graph: the world's edit specs applied as values, pose for pose the same as the ground truth."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omniscs.edits import Insert, Remove, ReplaceModel, Rotate, SetTrajectory, Translate
from omniscs.errors import OmniscsError
from omniscs.gaussians import activate
from omniscs.geometry import transform_points
from omniscs.nsg import Observations
from omniscs.nsg.compose import place_gaussians
from omniscs.nsg.edit import apply_graph_edits, scale_to_box
from omniscs.nsg.init import initial_graph
from omniscs.plan import make_plan
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene import load_scene
from omniscs.world import apply_edits
from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return load_scene(write_nsg_scene(tmp_path_factory.mktemp("nsg-edit") / "scene", nsg_world(n_frames=6)))


@pytest.fixture(scope="module")
def graph(scene):
    config = tiny_fit_config()
    return initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))


def _snapshot(graph):
    return ([a.world_from_agent.copy() for a in graph.agents], [a.present.copy() for a in graph.agents],
            [a.gaussians.means.clone() for a in graph.agents], graph.agent_ids, graph.background.means.clone())


EVERY_KIND = [
    {"op": "translate", "track_id": 1, "lateral": 2.0},
    {"op": "rotate", "track_id": 1, "yaw_deg": 90, "roll_deg": 180},
    {"op": "replace_model", "track_id": 2, "asset_id": "nsg:1"},
    {"op": "set_trajectory", "track_id": 2, "waypoints": [[20.0, 3.3, 0.8, 0.1]] * 5 + [None]},
    {"op": "insert", "track_id": 50, "asset_id": "nsg:2", "category": "car", "pose": [25.0, -3.0, 0.8, 0.0],
     "roll_deg": 180},
    {"op": "remove", "track_id": 1},
]


def test_edits_leave_the_source_graph_unchanged(graph):
    before = _snapshot(graph)
    edited = apply_graph_edits(graph, EVERY_KIND)
    after = _snapshot(graph)
    for x, y in zip(before[:3], after[:3]):
        for a, b in zip(x, y):
            assert (np.array_equal(a, b) if isinstance(a, np.ndarray) else torch.equal(a, b))
    assert before[3] == after[3] and torch.equal(before[4], after[4])
    assert edited.agent_ids == (2, 50)


def test_pose_edits_match_the_ground_truth_world_pose_for_pose(scene, graph):
    edits = [Translate(track_id=1, lateral=3.5), Rotate(track_id=1, yaw_deg=270), Rotate(track_id=2, roll_deg=180),
             Translate(track_id=2, longitudinal=-1.0, vertical=0.2)]
    edited = apply_graph_edits(graph, edits)
    world = apply_edits(scene.world, edits)
    for tid in (1, 2):
        assert np.allclose(edited.agent(tid).world_from_agent, world.agent(tid).poses, atol=1e-9)


def test_roll_180_moves_agent_gaussians_to_their_mirrored_positions(graph):
    agent = graph.agent(1)
    f = 3
    rolled = apply_graph_edits(graph, [Rotate(track_id=1, roll_deg=180)]).agent(1)
    local = activate(agent.gaussians)
    world = place_gaussians(local, rolled.world_from_agent[f]).means.double().numpy()
    mirrored = local.means.double().numpy() * np.array([1.0, -1.0, -1.0])  # (x, y, z) -> (x, -y, -z) in the box
    assert np.allclose(world, transform_points(agent.world_from_agent[f], mirrored), atol=1e-4)


def test_remove_takes_the_agent_out_of_the_rendered_image(graph):
    view = graph.view("CAM_FRONT", 2)
    before = graph.render(view)
    after = apply_graph_edits(graph, [Remove(track_id=1)]).render(view)
    assert 1 not in apply_graph_edits(graph, [Remove(track_id=1)]).agent_ids
    assert (before.alpha - after.alpha).abs().max() > 0.05  # seeds are faint (opacity 0.1) before fitting
    assert (before.rgb - after.rgb).abs().max() > 0.02


def test_replace_model_scales_the_other_model_exactly_to_the_box(graph):
    source = graph.agent(2).gaussians
    small, big = np.array([4.5, 1.9, 1.6]), np.array([9.0, 2.85, 3.2])
    scaled = scale_to_box(source, small, big)
    D = big / small
    assert np.allclose(scaled.means.double().numpy(), source.means.double().numpy() * D, atol=1e-5)

    def cov(p):
        g = activate(p)
        R = quat_to_rotmat(g.quats.double().numpy())
        return np.einsum("nij,nj,nkj->nik", R, g.scales.double().numpy() ** 2, R)
    assert np.allclose(cov(scaled), D[None, :, None] * cov(source) * D[None, None, :], rtol=1e-4, atol=1e-9)
    edited = apply_graph_edits(graph, [ReplaceModel(track_id=1, asset_id="nsg:2")])
    assert len(edited.agent(1).gaussians) == len(source)
    assert np.array_equal(edited.agent(1).world_from_agent, graph.agent(1).world_from_agent)  # motion is kept


def test_set_trajectory_and_insert_pose_nodes_like_the_world(scene, graph):
    waypoints = tuple((20.0 + f, 3.3, 0.8, 0.05 * f) if f != 4 else None for f in range(scene.n_frames))
    insert = Insert(track_id=50, asset_id="nsg:2", category="car", pose=(25.0, -3.0, 0.8, 0.3), roll_deg=180,
                    size=(4.5, 1.9, 1.6))
    edited = apply_graph_edits(graph, [SetTrajectory(track_id=2, waypoints=waypoints), insert])
    world_insert = Insert(track_id=50, asset_id="sedan-0000", category="car", pose=(25.0, -3.0, 0.8, 0.3),
                          roll_deg=180, size=(4.5, 1.9, 1.6))
    world = apply_edits(scene.world, [SetTrajectory(track_id=2, waypoints=waypoints), world_insert])
    for tid in (2, 50):
        node, track = edited.agent(tid), world.agent(tid)
        assert np.array_equal(node.present, track.present)
        assert np.allclose(node.world_from_agent[node.present], track.poses[track.present], atol=1e-9)
    out = edited.render(edited.view("CAM_FRONT", 4))
    assert torch.isfinite(out.rgb).all()


def test_edits_of_tracks_that_are_not_nodes_are_refused_with_a_clear_error(graph):
    with pytest.raises(OmniscsError, match="not an agent node"):
        apply_graph_edits(graph, [Translate(track_id=99, lateral=1.0)])
    with pytest.raises(OmniscsError, match="already has a node"):
        apply_graph_edits(graph, [Insert(track_id=1, asset_id="nsg:2", category="car", pose=(0, 0, 0, 0))])
    with pytest.raises(OmniscsError, match="pool model"):
        apply_graph_edits(graph, [ReplaceModel(track_id=1, asset_id="excavator-0002")])


def test_scaling_flat_and_tiny_gaussians_to_a_box_stays_finite(graph):
    from omniscs.gaussians import GaussianParams

    g = graph.agent(1).gaussians
    flat = GaussianParams(g.means, g.quats, torch.tensor([[0.0, -16.0, -16.0]]).expand_as(g.log_scales).clone(),
                          g.opacity_logits, g.sh_dc, g.sh_rest)
    for size in ([9.0, 0.1, 3.0], [1e-3, 1e-3, 1e-3], [100.0, 50.0, 20.0]):
        scaled = scale_to_box(flat, np.array([4.5, 1.9, 1.6]), np.array(size))
        assert scaled.is_finite()
    with pytest.raises(OmniscsError):
        scale_to_box(flat, np.array([4.5, 1.9, 1.6]), np.array([0.0, 1.0, 1.0]))
