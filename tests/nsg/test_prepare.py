"""The fused node preparation of a fit step (omniscs.nsg.prepare) against its definition: activate, colors_from_sh
and place_gaussians node by node, in float64. Values and gradients, every SH degree, at the zero-length rules and
the clamps; and a fit step's render_view through it against the node-by-node render."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omniscs.gaussians import LOG_SCALE_RANGE, GaussianParams, activate
from omniscs.geometry import pose_from_xyz_yaw, rotmat_from_euler
from omniscs.nsg.compose import place_gaussians
from omniscs.nsg.graph import _centre_in_node, render_view
from omniscs.nsg.prepare import prepare_nodes
from omniscs.render.sh import colors_from_sh

from tests.nsg.test_nsg_model import _graph, _random_params

FIELDS = ("means", "quats", "scales", "opacities", "colours")


def _raw(n: int, degree: int, seed: int) -> GaussianParams:
    g = torch.Generator().manual_seed(seed)
    return GaussianParams(torch.randn(n, 3, generator=g) * 3, torch.randn(n, 4, generator=g),
                          torch.randn(n, 3, generator=g) * 3, torch.randn(n, generator=g) * 3,
                          torch.randn(n, 3, generator=g), torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g) * 0.3)


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = rotmat_from_euler(*rng.uniform(-np.pi, np.pi, 3))
    T[:3, 3] = rng.normal(size=3) * 5
    return T


def _definition(nodes, centre, degree):  # the node-by-node PyTorch code, concatenated
    outs = []
    for pose, params in nodes:
        local = activate(params)
        dirs = local.means - _centre_in_node(centre, pose).to(local.means.dtype)
        colours = colors_from_sh(degree, local.sh, dirs[None])[0]
        placed = local if pose is None else place_gaussians(local, pose)
        outs.append((placed.means, placed.quats, placed.scales, placed.opacities, colours))
    return [torch.cat(x) for x in zip(*outs)]


def _leaves(params: GaussianParams, dtype) -> GaussianParams:
    return GaussianParams(**{k: v.detach().to(dtype).clone().requires_grad_(True) for k, v in params.as_dict().items()})


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_values_and_gradients_match_the_node_by_node_definition_at_the_extremes(degree):
    centre = np.array([0.3, -0.2, 0.1])
    raws = [_raw(400, 3, 0), _raw(250, 3, 1), _raw(150, 3, 2)]
    with torch.no_grad():  # the rules' edges, all in the background node
        bg = raws[0]
        bg.quats[0] = 0.0                                             # zero quaternion: the identity, no gradient
        bg.quats[1] = torch.tensor([1e-30, 0.0, 0.0, 0.0])            # below MIN_QUAT_NORM
        bg.log_scales[2] = torch.tensor([-20.0, LOG_SCALE_RANGE[1], 9.0])  # below, at and above the clamp
        bg.opacity_logits[3], bg.opacity_logits[4] = 60.0, -60.0     # saturated sigmoid
        bg.means[5] = torch.tensor(centre, dtype=torch.float32)       # camera on the centre: +z, no gradient
        bg.sh_dc[6] = -10.0                                           # colour clamped at 0
    nodes = [None, _pose(1), _pose(2)]
    ref_leaves = [_leaves(p, torch.float64) for p in raws]
    got_leaves = [_leaves(p, torch.float32) for p in raws]
    ref = _definition(list(zip(nodes, ref_leaves)), centre, degree)
    got = prepare_nodes(list(zip(nodes, got_leaves)), centre, degree)
    weights = [torch.randn(r.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(i))
               for i, r in enumerate(ref)]
    sum((r * w).sum() for r, w in zip(ref, weights)).backward()
    sum((g.double() * w).sum() for g, w in zip(got, weights)).backward()
    for name, r, g in zip(FIELDS, ref, got):
        assert g.dtype == torch.float32 and g.shape == r.shape and bool(torch.isfinite(g).all()), name
        assert torch.allclose(g.double(), r.detach(), rtol=1e-6, atol=1e-6), name
    for key in GaussianParams.__dataclass_fields__:
        a = torch.cat([getattr(p, key).grad for p in ref_leaves])
        b = torch.cat([getattr(p, key).grad for p in got_leaves]).double()
        assert bool(torch.isfinite(b).all()), key
        assert torch.allclose(b, a, rtol=1e-5, atol=1e-5 * float(a.abs().max()) + 1e-12), key
    bg_grad = got_leaves[0]
    assert torch.equal(bg_grad.quats.grad[:2], torch.zeros(2, 4))
    assert bg_grad.log_scales.grad[2, 0] == 0.0 and bg_grad.log_scales.grad[2, 2] == 0.0
    assert bg_grad.log_scales.grad[2, 1] != 0.0  # the clamp passes gradient at its bound, as torch.clamp does
    assert torch.equal(bg_grad.sh_dc.grad[6], torch.zeros(3))
    if degree > 0:  # the other bands of the degenerate direction's colour still learn; its mean gets no colour share
        assert bool(bg_grad.sh_rest.grad[5, : (degree + 1) ** 2 - 1].abs().sum() > 0)
    if degree < 3:  # bands above the degree in use get zero gradient, not none
        assert torch.equal(bg_grad.sh_rest.grad[:, (degree + 1) ** 2 - 1:], torch.zeros_like(bg_grad.sh_rest[:, (degree + 1) ** 2 - 1:]))


def test_a_fit_step_render_matches_the_node_by_node_render_in_image_and_gradients(monkeypatch):
    import dataclasses

    import omniscs.nsg.graph as graph_module

    graph = _graph(pose_from_xyz_yaw(9.0, 0.0, 1.0, 0.3), _random_params(60, spread=0.8),
                   background=_random_params(80, seed=1, spread=4.0))
    view = graph.view("CAM_FRONT", 1)

    def step():  # a fit step's render of trainable copies of the nodes, and its gradients
        bg, agent = _leaves(graph.background, torch.float32), _leaves(graph.agent(7).gaussians, torch.float32)
        g = graph.replace(background=bg, agents=(dataclasses.replace(graph.agents[0], gaussians=agent),))
        out = render_view(g, view)
        (out.rgb.square().sum() + out.depth.sum()).backward()
        return out, (bg, agent)

    used = []
    real = graph_module.prepare_nodes
    monkeypatch.setattr(graph_module, "prepare_nodes", lambda *a: used.append(1) or real(*a))
    fused, fused_leaves = step()
    assert used, "a render with trainable float32 CPU nodes goes through prepare_nodes"
    monkeypatch.setattr(graph_module, "_fused_preparation", lambda *a: False)
    plain, plain_leaves = step()
    assert len(used) == 1 and plain.alpha.sum() > 1.0
    assert torch.allclose(fused.rgb, plain.rgb, atol=2e-5) and torch.allclose(fused.alpha, plain.alpha, atol=2e-5)
    assert torch.allclose(fused.depth, plain.depth, rtol=1e-4, atol=1e-4)
    for a, b in zip(fused_leaves, plain_leaves):
        for k in GaussianParams.__dataclass_fields__:
            ga, gb = getattr(a, k).grad, getattr(b, k).grad
            assert bool(torch.isfinite(ga).all()), k
            assert torch.allclose(ga, gb, rtol=1e-3, atol=1e-4 * float(gb.abs().max()) + 1e-8), k
        assert float(a.means.grad.abs().sum()) > 0
