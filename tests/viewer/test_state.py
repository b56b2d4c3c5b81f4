"""The viewer's state: which Gaussians, boxes, frustums, paths and points it draws at a frame, and its camera view."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from omniscs.errors import OmniscsError
from omniscs.gaussians import activate, concat_params
from omniscs.nsg.graph import BACKGROUND, agent_key
from omniscs.nsg.splat_export import frame_gaussians
from omniscs.quaternions import quat_to_rotmat
from omniscs.viewer.state import (CATEGORY_COLOURS, ViewerConfig, graph_camera_image, graph_frame, graph_trajectories,
                                  rendered_image, splat_layers, store_camera_image, store_frame, store_trajectories)


def placed(layers, state):
    """The splats of ``state``'s nodes carried into the world: (centres [N, 3], covariances [N, 3, 3]), node order."""
    centres, covariances = [], []
    for node in state.nodes:
        s, T = layers[node.key], node.world_from_node
        R = T[:3, :3]
        centres.append(s.centers.astype(np.float64) @ R.T + T[:3, 3])
        covariances.append(R @ s.covariances.astype(np.float64) @ R.T)
    return np.concatenate(centres), np.concatenate(covariances)


def test_a_frame_shows_the_background_and_only_the_agents_present_at_their_poses(fitted):
    _, graph = fitted
    first, later = graph_frame(graph, 0), graph_frame(graph, 2)
    assert [n.key for n in first.nodes] == [BACKGROUND, agent_key(1)]          # car 2 appears in frame 1
    assert [n.key for n in later.nodes] == [BACKGROUND, agent_key(1), agent_key(2)]
    assert np.array_equal(later.nodes[0].world_from_node, np.eye(4))
    for node, box in zip(later.nodes[1:], later.boxes):
        agent = graph.agent(box.track_id)
        assert np.array_equal(node.world_from_node, agent.world_from_agent[2])
        assert np.array_equal(box.world_from_box, agent.world_from_agent[2]) and np.array_equal(box.size, agent.size)
        assert box.label == f"car {box.track_id}" and box.colour == CATEGORY_COLOURS["car"]


def test_frustums_are_the_logged_rig_on_the_logged_ego_pose(fitted):
    _, graph = fitted
    state = graph_frame(graph, 3)
    assert [f.camera for f in state.frustums] == [c.name for c in graph.cameras]
    for f, cam in zip(state.frustums, graph.cameras):
        assert np.allclose(f.world_from_camera, graph.world_from_ego[3] @ cam.ego_from_camera)
        # the half-height of the image seen at depth fy subtends half the vertical field of view
        assert np.isclose(np.tan(f.fov_y / 2) * cam.K[1, 1], cam.height / 2) and f.aspect == cam.width / cam.height


def test_placed_splats_are_the_graphs_gaussians_in_the_world_at_that_frame(fitted):
    _, graph = fitted
    layers = splat_layers(graph, budget=10**9)
    for frame in (0, 3):
        centres, covariances = placed(layers, graph_frame(graph, frame))
        truth = activate(concat_params(list(frame_gaussians(graph, frame).values())))  # the PLY export's world
        R = quat_to_rotmat(truth.quats.double().numpy())
        truth_cov = np.einsum("nij,nj,nkj->nik", R, truth.scales.double().numpy() ** 2, R)
        assert np.allclose(centres, truth.means.double().numpy(), atol=1e-4)
        assert np.allclose(covariances, truth_cov, atol=1e-6, rtol=1e-3)
    bg = layers[BACKGROUND]
    expected_rgb = (0.28209479177387814 * graph.background.sh_dc + 0.5).clamp(0, 1).numpy()
    assert np.allclose(bg.rgbs, expected_rgb, atol=1e-6)
    assert np.allclose(bg.opacities[:, 0], torch.sigmoid(graph.background.opacity_logits).numpy())


def test_the_splat_budget_keeps_the_most_opaque_gaussians_over_all_nodes(fitted):
    _, graph = fitted
    opacity = {k: v.opacities[:, 0] for k, v in splat_layers(graph, budget=10**9).items()}
    budget = graph.n_gaussians // 3
    kept = splat_layers(graph, budget)
    assert sum(len(s) for s in kept.values()) == budget
    kept_min = min(float(s.opacities.min()) for s in kept.values() if len(s))
    every = np.sort(np.concatenate(list(opacity.values())))[::-1]
    assert kept_min == pytest.approx(every[budget - 1]) and every[budget] <= kept_min
    assert all(len(kept[k]) <= len(opacity[k]) for k in kept)


def test_trajectories_are_the_ego_path_and_each_agent_over_its_present_frames(fitted):
    _, graph = fitted
    ego, *agents = graph_trajectories(graph)
    assert ego.track_id is None and np.array_equal(ego.positions, graph.world_from_ego[:, :3, 3])
    assert [t.track_id for t in agents] == [1, 2]
    late = agents[1]
    assert list(late.frames) == [1, 2, 3]
    assert np.array_equal(late.positions, graph.agent(2).world_from_agent[1:, :3, 3])


def test_a_scene_store_shows_its_lidar_in_the_world_and_its_logged_boxes(fitted):
    scene, _ = fitted
    sweep = scene.lidar(2)[:, :3].astype(np.float64)
    ego = scene.world_from_ego(2)
    state = store_frame(scene, 2, lidar_budget=10**9)
    assert np.allclose(state.points, sweep @ ego[:3, :3].T + ego[:3, 3], atol=1e-4)
    budget = len(sweep) // 4
    thin = store_frame(scene, 2, lidar_budget=budget)
    stride = -(-len(sweep) // budget)  # the smallest stride that fits the budget
    assert len(thin.points) <= budget and np.array_equal(thin.points, state.points[::stride])
    logged = scene.boxes_at(2).sort_values("track_id")
    assert [b.track_id for b in state.boxes] == list(logged.track_id)
    assert np.allclose([b.world_from_box[:3, 3] for b in state.boxes], logged[["cx", "cy", "cz"]].to_numpy())
    assert state.nodes == () and len(state.frustums) == 2
    assert [t.track_id for t in store_trajectories(scene)] == [None, 1, 2]


def test_the_camera_view_is_what_omniscs_render_writes_with_the_boxes_drawn_over_it(fitted, checkpoint, tmp_path):
    from PIL import Image

    from omniscs.cli import app

    _, graph = fitted
    out = tmp_path / "render.png"
    result = CliRunner().invoke(app, ["render", str(checkpoint), "--camera", "CAM_FRONT", "--frame", "2",
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    plain = graph_camera_image(graph, "CAM_FRONT", 2, boxes=False)
    assert np.array_equal(plain, np.asarray(Image.open(out).convert("RGB")))
    assert np.array_equal(plain, rendered_image(graph, "CAM_FRONT", 2))
    boxed = graph_camera_image(graph, "CAM_FRONT", 2)
    changed = np.any(boxed != plain, axis=2)
    assert 0.005 < changed.mean() < 0.5  # wireframes and labels, not a repaint
    car = np.array(CATEGORY_COLOURS["car"])
    assert np.any(np.all(np.abs(boxed[changed].astype(int) - car) <= 40, axis=1))


def test_a_stores_camera_view_is_its_logged_image_with_its_boxes(fitted):
    scene, _ = fitted
    plain = store_camera_image(scene, "CAM_FRONT", 1, boxes=False)
    assert np.array_equal(plain, scene.image("CAM_FRONT", 1))
    assert np.any(store_camera_image(scene, "CAM_FRONT", 1) != plain)


@pytest.mark.parametrize("field,value", [("splat_budget", 0), ("lidar_budget", 1.5), ("play_fps", float("nan")),
                                         ("frustum_scale_m", -1.0)])
def test_a_bad_viewer_setting_is_one_error(field, value):
    with pytest.raises(OmniscsError, match=field):
        ViewerConfig(**{field: value})


def test_the_road_map_is_drawn_as_lane_centrelines_and_drivable_outlines_on_the_ground():
    from omniscs.roadmap import RoadMap
    from omniscs.viewer.state import DRIVABLE_COLOUR, LANE_COLOUR, road_lines

    square = np.array([[0.0, -4.0], [50.0, -4.0], [50.0, 4.0], [0.0, 4.0]])
    road = RoadMap((square,), (np.array([[0.0, 0.0], [25.0, 0.0], [50.0, 0.0]]),), np.array([0.0, -4.0]),
                   np.array([50.0, 4.0]))
    segments, colours = road_lines(road, ground_z=-0.3)
    assert segments.shape == (2 + 4, 2, 3) and np.all(segments[..., 2] == -0.3)
    assert np.array_equal(segments[1], [[25.0, 0.0, -0.3], [50.0, 0.0, -0.3]])
    assert np.array_equal(segments[-1, 1, :2], square[0])  # the outline closes
    assert [tuple(c[0]) for c in colours] == [LANE_COLOUR] * 2 + [DRIVABLE_COLOUR] * 4


def test_with_its_scene_the_camera_view_puts_the_logged_image_left_of_the_rendered_one(fitted):
    scene, graph = fitted
    both = graph_camera_image(graph, "CAM_FRONT", 1, scene=scene)
    width = graph.camera("CAM_FRONT").width
    assert both.shape[1] == 2 * width
    assert np.array_equal(both[:, :width], store_camera_image(scene, "CAM_FRONT", 1))
    assert np.array_equal(both[:, width:], graph_camera_image(graph, "CAM_FRONT", 1))
