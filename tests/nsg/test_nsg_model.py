"""Scene-graph model: activation, Eq. 1 composition, rendering of nodes, sky and arbitrary views."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from omniscs.gaussians import GaussianParams, activate, params_from_values
from omniscs.geometry import (ego_from_camera_mount, intrinsics_from_fov, make_transform, pose_from_xyz_yaw,
                              rotmat_from_euler)
from omniscs.nsg.agent import AgentNode, box_surface_points
from omniscs.nsg.backdrop import identity_exposure
from omniscs.nsg.compose import place_gaussians
from omniscs.nsg.graph import SceneGraph
from omniscs.nsg.observations import View
from omniscs.nsg.sky import init_sky
from omniscs.quaternions import quat_to_rotmat
from omniscs.render.sh import colors_from_sh
from omniscs.scene.store import CameraRecord

W, H = 64, 40


def _camera() -> CameraRecord:
    return CameraRecord("CAM_FRONT", W, H, intrinsics_from_fov(W, H, np.radians(70)),
                        ego_from_camera_mount(0.0, 0.0, 1.5, 0.0))


def _random_params(n: int, seed: int = 0, sh_degree: int = 1, spread: float = 1.0) -> GaussianParams:
    g = torch.Generator().manual_seed(seed)
    p = params_from_values(torch.randn(n, 3, generator=g) * spread, torch.full((n, 3), 0.15),
                           torch.full((n,), 0.8), torch.rand(n, 3, generator=g), sh_degree,
                           quats=torch.randn(n, 4, generator=g))
    return GaussianParams(p.means, p.quats, p.log_scales + 0.3 * torch.randn(n, 3, generator=g), p.opacity_logits,
                          p.sh_dc, 0.3 * torch.randn(p.sh_rest.shape, generator=g))


def _graph(agent_pose: np.ndarray, agent_params: GaussianParams, n_frames: int = 2,
           background: GaussianParams | None = None) -> SceneGraph:
    poses = np.repeat(agent_pose[None], n_frames, 0)
    agent = AgentNode(7, "car", np.array([4.5, 1.9, 1.6]), poses, np.ones(n_frames, bool), agent_params)
    bg = background if background is not None else _random_params(0)
    return SceneGraph("s", "h" * 64, bg, (agent,), init_sky(torch.tensor([0.4, 0.6, 0.9]), 8, 16),
                      {"CAM_FRONT": identity_exposure()}, (_camera(),),
                      np.repeat(np.eye(4)[None], n_frames, 0), sh_degree=agent_params.sh_degree)


def test_activation_inverts_params_from_values():
    means, scales = torch.randn(5, 3), torch.rand(5, 3) + 0.01
    opac, rgb = torch.rand(5) * 0.9 + 0.05, torch.rand(5, 3)
    g = activate(params_from_values(means, scales, opac, rgb, 2))
    assert torch.allclose(g.means, means) and torch.allclose(g.scales, scales, rtol=1e-5)
    assert torch.allclose(g.opacities, opac, atol=1e-6)
    colours = colors_from_sh(2, g.sh, torch.randn(1, 5, 3))[0]
    assert torch.allclose(colours, rgb, atol=1e-6)  # higher bands start at zero: colour is view-independent


def test_activation_of_degenerate_raw_values_is_finite():
    p = GaussianParams(torch.zeros(3, 3), torch.zeros(3, 4), torch.tensor([[-1e9] * 3, [1e9] * 3, [0.0] * 3]),
                       torch.tensor([-1e9, 1e9, 0.0]), torch.zeros(3, 3), torch.zeros(3, 0, 3))
    g = activate(p)
    for t in (g.quats, g.scales, g.opacities):
        assert torch.isfinite(t).all()
    assert torch.equal(g.quats[0], torch.tensor([1.0, 0, 0, 0]))
    assert (g.scales > 0).all()


def test_place_gaussians_is_eq1_rigid_motion_of_means_and_covariances():
    local = activate(_random_params(20))
    T = make_transform(rotmat_from_euler(0.3, -0.2, 1.1), [5.0, -2.0, 0.7])
    placed = place_gaussians(local, T)
    R = T[:3, :3]
    assert np.allclose(placed.means.numpy(), local.means.double().numpy() @ R.T + T[:3, 3], atol=1e-5)

    def cov(g):
        Rg = quat_to_rotmat(g.quats.double().numpy())
        s2 = g.scales.double().numpy() ** 2
        return np.einsum("nij,nj,nkj->nik", Rg, s2, Rg)
    assert np.allclose(cov(placed), R @ cov(local) @ R.T, atol=1e-5)
    assert placed.scales is local.scales and placed.opacities is local.opacities and placed.sh is local.sh


def test_rotation_by_q_and_minus_q_renders_identically():
    q = np.array([0.8, 0.1, -0.3, 0.5])
    q /= np.linalg.norm(q)
    params = _random_params(60, spread=0.8)
    flipped = GaussianParams(params.means, -params.quats, params.log_scales, params.opacity_logits, params.sh_dc,
                             params.sh_rest)
    view = View(0, pose_from_xyz_yaw(0, 0, 1.0, 0) @ _camera().ego_from_camera, _camera().K, W, H, "CAM_FRONT")
    pose = make_transform(quat_to_rotmat(q), [9.0, 0.5, 1.0])
    pose_neg = make_transform(quat_to_rotmat(-q), [9.0, 0.5, 1.0])
    a = _graph(pose, params).render(view)
    b = _graph(pose_neg, flipped).render(view)
    assert a.alpha.max() > 0.2
    assert torch.allclose(a.rgb, b.rgb, atol=1e-5) and torch.allclose(a.depth, b.depth, atol=1e-4)


def test_view_dependent_colour_is_evaluated_in_the_agent_frame():
    """Turning an agent and the camera together about the agent leaves the image unchanged (SH degree 1)."""
    params = _random_params(80, seed=3, spread=0.8)
    empty_bg = params.select(torch.zeros(len(params), dtype=torch.bool))
    pose = pose_from_xyz_yaw(10.0, 0.0, 1.0, 0.0)
    cam = pose_from_xyz_yaw(0.0, 0.0, 1.0, 0.0) @ _camera().ego_from_camera
    turn = make_transform(rotmat_from_euler(yaw=np.radians(70)), [0, 0, 0])
    about_agent = pose @ turn @ np.linalg.inv(pose)
    a = _graph(pose, params, background=empty_bg).render(View(0, cam, _camera().K, W, H, None))
    b = _graph(about_agent @ pose, params, background=empty_bg).render(View(0, about_agent @ cam, _camera().K, W, H,
                                                                           None))
    colour = a.rgb * a.alpha[..., None]
    assert a.alpha.max() > 0.2
    assert torch.allclose(colour, b.rgb * b.alpha[..., None], atol=2e-4)


def test_sky_fills_pixels_no_gaussian_covers():
    params = _random_params(30)
    empty = params.select(torch.zeros(len(params), dtype=torch.bool))
    graph = _graph(pose_from_xyz_yaw(1e4, 0, 0, 0), empty, background=empty)  # agent node with no Gaussians
    out = graph.render(graph.view("CAM_FRONT", 0))
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0)
    assert out.rgb.std(dim=(0, 1)).max() < 0.05 and torch.allclose(out.rgb.mean((0, 1)),
                                                                     torch.tensor([0.4, 0.6, 0.9]), atol=0.02)


def test_render_at_another_ego_pose_and_an_unlogged_camera():
    params = _random_params(60, spread=0.8)
    graph = _graph(pose_from_xyz_yaw(9.0, 0.0, 1.0, 0.0), params)
    logged = graph.render(graph.view("CAM_FRONT", 0))
    moved = graph.render(graph.view("CAM_FRONT", 0, world_from_ego=pose_from_xyz_yaw(0.0, 1.5, 0.0, 0.1)))
    K = intrinsics_from_fov(32, 20, np.radians(90))
    novel = graph.render(View(1, pose_from_xyz_yaw(2.0, 0, 1.0, 0) @ _camera().ego_from_camera, K, 32, 20, None))
    assert novel.rgb.shape == (20, 32, 3)
    for out in (logged, moved, novel):
        assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    assert not torch.allclose(logged.rgb, moved.rgb, atol=1e-3)


def test_box_surface_points_lie_on_the_box_faces():
    size = np.array([4.0, 2.0, 1.5])
    pts = box_surface_points(size, 500, np.random.default_rng(0))
    on_face = np.isclose(np.abs(pts), size / 2).any(axis=1)
    assert on_face.all() and np.all(np.abs(pts) <= size / 2 + 1e-9)


def test_graph_is_a_value():
    graph = _graph(pose_from_xyz_yaw(9.0, 0.0, 1.0, 0.0), _random_params(10))
    with pytest.raises(ValueError):
        graph.agents[0].world_from_agent[0, 0, 3] = 1.0
    with pytest.raises(TypeError):
        graph.exposure["CAM_FRONT"] = identity_exposure()


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 1e-3),
       st.sampled_from([np.array([1.0, 0, 0, 0]), np.array([0.0, 1, 0, 0]), np.array([0.0, 0, 0, 1]),
                        np.array([1e-9, 1, 0, 0])]))
def test_eq1_is_exact_for_any_pose_rotation_including_half_turns(q_pose, q_special):
    """Identity, 180° about x (overturned) and z, and near-180° turns: no NaN, covariance = R Σ R^T."""
    params = _random_params(12, seed=1)
    local = activate(params)
    for q in (np.asarray(q_pose), q_special):
        T = make_transform(quat_to_rotmat(q), [3.0, -1.0, 0.5])
        placed = place_gaussians(local, T)
        assert torch.isfinite(placed.means).all() and torch.isfinite(placed.quats).all()
        Rl = quat_to_rotmat(local.quats.double().numpy())
        Rp = quat_to_rotmat(placed.quats.double().numpy())
        s2 = local.scales.double().numpy() ** 2
        cov_l = np.einsum("nij,nj,nkj->nik", Rl, s2, Rl)
        cov_p = np.einsum("nij,nj,nkj->nik", Rp, s2, Rp)
        R = T[:3, :3]
        assert np.allclose(cov_p, R @ cov_l @ R.T, atol=1e-5)


def test_pixel_directions_are_the_unit_rays_through_pixel_centres_turned_into_the_world():
    from omniscs.nsg.backdrop import pixel_directions

    rng = np.random.default_rng(5)
    K = intrinsics_from_fov(37, 23, np.radians(70.0))
    K[0, 2] += 3.0  # an off-centre principal point
    for _ in range(3):
        q = rng.normal(size=4)
        T = make_transform(quat_to_rotmat(q / np.linalg.norm(q)), rng.normal(size=3) * 10)
        d = pixel_directions(View(0, T, K, 37, 23)).numpy()
        u, v = np.meshgrid(np.arange(37) + 0.5, np.arange(23) + 0.5)
        want = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T[:3, :3].T
        want /= np.linalg.norm(want, axis=-1, keepdims=True)
        assert d.shape == (23, 37, 3) and d.dtype == np.float32
        np.testing.assert_allclose(d, want, atol=1e-6)


def test_render_with_nodes_activated_beforehand_is_the_same_image():
    from omniscs.nsg.graph import BACKGROUND, agent_key, render_view

    graph = _graph(pose_from_xyz_yaw(9.0, 0.0, 1.0, 0.0), _random_params(60, spread=0.8),
                   background=_random_params(80, seed=1, spread=4.0))
    activated = {BACKGROUND: activate(graph.background.detached()),
                 agent_key(7): activate(graph.agent(7).gaussians.detached())}
    view = graph.view("CAM_FRONT", 1)
    plain, ready = render_view(graph, view), render_view(graph, view, activated=activated)
    assert plain.alpha.sum() > 1.0
    for a, b in ((plain.rgb, ready.rgb), (plain.depth, ready.depth), (plain.alpha, ready.alpha)):
        assert torch.equal(a, b)
    stale = {BACKGROUND: activate(_random_params(10, seed=2))}  # not this node's size: ignored
    assert torch.equal(render_view(graph, view, activated=stale).rgb, plain.rgb)
