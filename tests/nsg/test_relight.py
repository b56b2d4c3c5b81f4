"""Relightable agent nodes: colours from albedo, normals turned by the node's pose and the scene's light, in
rendering, edits and checkpoints (issue 13)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams
from omniscs.nsg.relight import Relight, flat_lighting, srgb_decode, srgb_encode
from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET
from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene


def _yaw(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_a_side_lit_by_the_sun_goes_dark_when_the_node_turns_away():
    # light from +x: ambient 0.2, direction term 0.8; nothing reflected; albedo 0.5 everywhere
    light = torch.zeros(5, 3)
    light[0], light[1] = 0.2, 0.8
    normals = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    r = Relight(torch.full((3, 3), 0.5), normals, light)
    facing = r.colours(np.eye(3))
    assert torch.allclose(facing[0], srgb_encode(torch.tensor(0.5)).expand(3), atol=1e-6)  # 0.5 * (0.2 + 0.8)
    assert torch.allclose(facing[1], srgb_encode(torch.tensor(0.1)).expand(3), atol=1e-6)  # side: ambient only
    turned = r.colours(_yaw(180.0))
    assert torch.allclose(turned[0], torch.zeros(3), atol=1e-6)  # faces away: 0.2 - 0.8 clamps to no light
    assert torch.allclose(turned[2], facing[2])  # the roof does not care about a turn
    # the additive term is added whatever the albedo; flat lighting gives back the albedo
    light[4] = 0.05
    assert torch.allclose(Relight(torch.zeros(3, 3), normals, light).colours(np.eye(3)),
                          srgb_encode(torch.tensor(0.05)).expand(3, 3), atol=1e-6)
    assert torch.allclose(srgb_decode(Relight(torch.full((3, 3), 0.3), normals, flat_lighting()).colours(_yaw(33))),
                          torch.full((3, 3), 0.3), atol=1e-5)


def test_bad_relight_data_is_refused():
    with pytest.raises(OmniscsError, match="albedo"):
        Relight(torch.zeros(3, 3), torch.zeros(2, 3), flat_lighting())
    with pytest.raises(OmniscsError, match="NaN"):
        Relight(torch.full((2, 3), float("nan")), torch.zeros(2, 3), flat_lighting())
    # extreme light: colours stay in 0..1, finite
    r = Relight(torch.rand(4, 3), torch.nn.functional.normalize(torch.randn(4, 3), dim=1), flat_lighting(1e30))
    c = r.colours(np.eye(3))
    assert bool(torch.isfinite(c).all()) and float(c.min()) >= 0 and float(c.max()) <= 1


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import make_plan
    from omniscs.scene import load_scene

    scene = load_scene(write_nsg_scene(tmp_path_factory.mktemp("relight") / "scene", nsg_world(n_frames=4)))
    config = tiny_fit_config()
    g = initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))
    # opaque node Gaussians, degree-0 colours: what the agents stage leaves
    node = g.agent(1)
    p = node.gaussians
    p = GaussianParams(p.means, p.quats, p.log_scales + 0.5, p.opacity_logits + 6.0, p.sh_dc, torch.zeros_like(p.sh_rest))
    gen = torch.Generator().manual_seed(0)
    light = torch.tensor([[0.4, 0.4, 0.45], [0.5, 0.45, 0.4], [0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [0.02, 0.03, 0.05]])
    relight = Relight(torch.rand(len(p), 3, generator=gen),
                      torch.nn.functional.normalize(torch.randn(len(p), 3, generator=gen), dim=1), light)
    return g.replace(agents=tuple(a.with_changes(gaussians=p, relight=relight) if a.track_id == 1 else a
                                  for a in g.agents))


def _baked(graph, frame: int, extra=np.eye(3)):
    """The graph with node 1's relit colours at ``frame`` written into its Gaussians, relight data dropped."""
    node = graph.agent(1)
    dc = (node.relight.colours(node.world_from_agent[frame][:3, :3] @ extra) - SH_COLOR_OFFSET) / SH_C0
    p = node.gaussians
    baked = node.with_changes(gaussians=GaussianParams(p.means, p.quats, p.log_scales, p.opacity_logits, dc, p.sh_rest))
    assert baked.relight is None  # new Gaussians without relight data drop it
    return graph.replace(agents=tuple(baked if a.track_id == 1 else a for a in graph.agents))


def test_a_relit_node_renders_its_colours_at_each_frames_pose_and_after_a_turn(graph):
    from omniscs.nsg.edit import apply_graph_edits

    cam = graph.cameras[0].name
    for frame in (0, 3):
        view = graph.view(cam, frame)
        assert torch.allclose(graph.render(view).rgb, _baked(graph, frame).render(view).rgb, atol=1e-6)
    turned = apply_graph_edits(graph, [{"op": "rotate", "track_id": 1, "yaw_deg": 90.0}])
    assert turned.agent(1).relight is not None
    view = turned.view(cam, 2)
    expected = apply_graph_edits(_baked(graph, 2, _yaw(90.0)), [{"op": "rotate", "track_id": 1, "yaw_deg": 90.0}])
    assert torch.allclose(turned.render(view).rgb, expected.render(view).rgb, atol=1e-6)
    # the turn changed what the lit node looks like, not only where it is
    plain = apply_graph_edits(_baked(graph, 2), [{"op": "rotate", "track_id": 1, "yaw_deg": 90.0}])
    assert not torch.allclose(turned.render(view).rgb, plain.render(view).rgb, atol=1e-3)


def test_relight_data_survives_a_checkpoint_and_a_damaged_flag_is_refused(graph, tmp_path):
    import json

    from omniscs.nsg.checkpoint import GRAPH_JSON, load_checkpoint, save_checkpoint

    folder = save_checkpoint(graph, tmp_path / "ckpt")
    back = load_checkpoint(folder)
    r, s = graph.agent(1).relight, back.agent(1).relight
    assert all(torch.equal(getattr(r, k), getattr(s, k)) for k in ("albedo", "normals", "lighting"))
    assert back.agent(2).relight is None
    view = graph.view(graph.cameras[0].name, 1)
    assert torch.allclose(back.render(view).rgb, graph.render(view).rgb, atol=1e-6)
    meta = json.loads((folder / GRAPH_JSON).read_text())
    meta["agents"][[a["track_id"] for a in meta["agents"]].index(1)]["relight"] = "yes"
    (folder / GRAPH_JSON).write_text(json.dumps(meta))
    with pytest.raises(OmniscsError, match="relight"):
        load_checkpoint(folder)
