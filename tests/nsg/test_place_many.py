"""Several nodes placed at once (omniscs.nsg.compose.place_many, and render_view's batched node path) against Eq. 1
node by node: values and gradients, for fixed, world-frame and differentiable poses, a zero quaternion among them,
and a behaviour-style render whose agent poses carry gradients."""
from __future__ import annotations

import torch

from omniscs.gaussians import Gaussians, activate
from omniscs.geometry import pose_from_xyz_yaw
from omniscs.nsg.compose import NodePose, place_gaussians, place_many
from omniscs.nsg.graph import _centre_in_node, render_view
from omniscs.render.sh import colors_from_sh

from tests.nsg.test_nsg_model import _graph, _random_params
from tests.nsg.test_prepare import _pose


def _locals(sizes, seed):
    g = torch.Generator().manual_seed(seed)
    return [Gaussians(torch.randn(n, 3, generator=g, dtype=torch.float64) * 2,
                      torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1),
                      torch.rand(n, 3, generator=g, dtype=torch.float64), torch.rand(n, generator=g, dtype=torch.float64),
                      torch.randn(n, 4, 3, generator=g, dtype=torch.float64)) for n in sizes]


def _node_poses():
    return [None, _pose(1),
            NodePose(torch.tensor([0.3, -0.2, 0.5, 0.9], dtype=torch.float64, requires_grad=True),
                     torch.tensor([4.0, -1.0, 0.5], dtype=torch.float64, requires_grad=True)),
            NodePose(torch.zeros(4, dtype=torch.float64, requires_grad=True),  # reads as the identity
                     torch.tensor([-2.0, 3.0, 0.0], dtype=torch.float64, requires_grad=True))]


def test_place_many_is_place_gaussians_node_by_node_in_values_and_gradients():
    sizes = (5, 7, 3, 4)
    results = []
    for batched in (True, False):
        locals_ = [Gaussians(*(t.clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)))
                   for g in _locals(sizes, seed=2)]
        poses = _node_poses()
        if batched:
            local = Gaussians(*(torch.cat([getattr(g, k) for g in locals_])
                                for k in ("means", "quats", "scales", "opacities", "sh")))
            node_of = torch.repeat_interleave(torch.arange(4), torch.tensor(sizes))
            placed, _, _ = place_many(local, node_of, poses)
            means, quats = placed.means, placed.quats
        else:
            placed = [place_gaussians(g, p) if p is not None else g for g, p in zip(locals_, poses)]
            means, quats = torch.cat([p.means for p in placed]), torch.cat([p.quats for p in placed])
        w = torch.Generator().manual_seed(3)
        loss = (means * torch.randn(means.shape, generator=w, dtype=torch.float64)).sum() + \
            (quats * torch.randn(quats.shape, generator=w, dtype=torch.float64)).sum()
        loss.backward()
        grads = [g.means.grad for g in locals_] + [g.quats.grad for g in locals_] + \
            [t.grad for p in poses[2:] for t in (p.quat, p.translation)]
        results.append((means.detach(), quats.detach(), grads))
    (m1, q1, g1), (m2, q2, g2) = results
    assert torch.allclose(m1, m2, atol=1e-12) and torch.allclose(q1, q2, atol=1e-12)
    for a, b in zip(g1, g2):
        assert torch.isfinite(a).all() and torch.allclose(a, b, atol=1e-10)
    assert float(g1[-1].abs().sum()) > 0  # the zero quaternion's translation still learns


def test_a_render_with_moved_agents_matches_the_node_by_node_render(monkeypatch):
    import omniscs.nsg.graph as graph_module

    graph = _graph(pose_from_xyz_yaw(9.0, 0.0, 1.0, 0.3), _random_params(60, spread=0.8),
                   background=_random_params(80, seed=1, spread=4.0))
    view = graph.view("CAM_FRONT", 1)

    def node_by_node(nodes, camera_centre, degree, activated):  # render_view's loop, as the definition
        placed, colours = [], []
        for _, pose, params, _ in nodes:
            local = activate(params)
            dirs = local.means - _centre_in_node(camera_centre, pose).to(local.means.dtype)
            colours.append(colors_from_sh(degree, local.sh, dirs[None])[0])
            placed.append(local if pose is None else place_gaussians(local, pose))
        return Gaussians(*(torch.cat([getattr(p, k) for p in placed])
                           for k in ("means", "quats", "scales", "opacities", "sh"))), torch.cat(colours)

    def render():
        x, y, yaw = (torch.tensor(v, requires_grad=True) for v in (9.2, 0.3, 0.25))
        out = render_view(graph, view, agent_poses={7: NodePose.from_xy_yaw(x, y, yaw, 1.0)})
        (out.rgb.square().sum() + out.depth.sum()).backward()
        return out, (x.grad, y.grad, yaw.grad)

    batched, batched_grads = render()
    monkeypatch.setattr(graph_module, "_place_and_colour", node_by_node)
    plain, plain_grads = render()
    assert plain.alpha.sum() > 1.0
    assert torch.allclose(batched.rgb, plain.rgb, atol=2e-5) and torch.allclose(batched.alpha, plain.alpha, atol=2e-5)
    assert torch.allclose(batched.depth, plain.depth, rtol=1e-4, atol=1e-4)
    for a, b in zip(batched_grads, plain_grads):
        assert torch.isfinite(a) and abs(float(b)) > 0
        assert torch.allclose(a, b, rtol=1e-3, atol=1e-4 * abs(float(b)))
