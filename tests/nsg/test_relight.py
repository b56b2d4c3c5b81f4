"""Relightable agent nodes: colours from albedo, normals turned by the node's pose and the scene's light, in
rendering, edits and checkpoints (issue 13)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams
from omniscs.nsg.relight import (LIGHTING_ROWS, RELIGHT_TENSORS, Relight, camera_response, inverse_camera_response,
                                  matte, neutral_lighting)
from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET


def _yaw(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _light(sun=0.0, direction=(1.0, 0.0, 0.0), sky=0.0, ground=0.0, zenith=0.0, horizon=0.0, below=0.0):
    rows = [sun, direction, sky, ground, zenith, horizon, below]
    return torch.stack([torch.as_tensor(r, dtype=torch.float32).expand(3) for r in rows])


def test_a_side_lit_by_the_sun_goes_dark_when_the_node_turns_away():
    # sun 0.8 from +x, sky and ground 0.1 each; matte albedo 0.5; each Gaussian seen head-on
    normals = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    r = matte(torch.full((3, 3), 0.5), normals, _light(sun=0.8, sky=0.1, ground=0.1))
    facing = r.colours(np.eye(3))
    assert torch.allclose(facing[0], camera_response(torch.tensor(0.45)).expand(3), atol=1e-6)  # 0.5 (0.8 + 0.1)
    assert torch.allclose(facing[1], camera_response(torch.tensor(0.05)).expand(3), atol=1e-6)  # side: sky + ground
    turned = r.colours(_yaw(180.0))
    assert torch.allclose(turned[0], facing[1], atol=1e-6)  # faces away from the sun: sky and ground alone
    assert torch.allclose(turned[2], facing[2])  # the roof does not care about a turn
    # the light from above and from below: a roof sees the sky only, a floor the ground only
    up_down = matte(torch.full((2, 3), 1.0), torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]),
                    _light(sky=0.3, ground=0.1)).colours(np.eye(3))
    assert torch.allclose(inverse_camera_response(up_down), torch.tensor([[0.3] * 3, [0.1] * 3]), atol=1e-4)


def test_glass_mirrors_the_sky_at_grazing_angles_and_shows_its_colour_head_on():
    # one vertical pane facing +x, dark red albedo, reflectance 0.09; a blue sky; light from the sky only
    pane = Relight(torch.tensor([[0.3, 0.02, 0.02]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([0.09]),
                   torch.tensor([400.0]), _light(sky=0.6, ground=0.3, zenith=(0.1, 0.2, 0.9), horizon=(0.1, 0.2, 0.9),
                                                 below=0.05))
    head_on = pane.colours(np.eye(3), torch.tensor([[-1.0, 0.0, 0.0]]))[0]
    grazing = pane.colours(np.eye(3), torch.tensor([[-0.05, 1.0, 0.1]]))[0]  # seen along the pane, from below
    assert head_on[0] > head_on[2] and grazing[2] > grazing[0] + 0.3
    # the sun's highlight shows where it is mirrored towards the camera, and only there
    light = _light(sun=1.0, direction=(1.0, 0.0, 0.0), sky=0.2)
    shiny = Relight(torch.tensor([[0.1, 0.1, 0.1]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([0.09]),
                    torch.tensor([200.0]), light)
    mirrored = shiny.colours(np.eye(3), torch.tensor([[-1.0, 0.0, 0.0]]))[0]
    aside = shiny.colours(np.eye(3), torch.tensor([[-1.0, 0.6, 0.0]]))[0]
    assert float(mirrored.mean()) > float(aside.mean()) + 0.2
    # matte: no mirror term at all, however grazing
    flat = matte(torch.tensor([[0.3, 0.02, 0.02]]), torch.tensor([[1.0, 0.0, 0.0]]), pane.lighting)
    assert torch.allclose(flat.colours(np.eye(3), torch.tensor([[-0.05, 1.0, 0.1]])), flat.colours(np.eye(3)),
                          atol=1e-6)


def test_the_camera_response_inverts_and_stays_finite_at_the_extremes():
    x = torch.tensor([0.0, 1e-4, 0.1, 1.0, 5.0])
    assert torch.allclose(inverse_camera_response(camera_response(x)), x, atol=1e-3)
    ends = camera_response(torch.tensor([-1e30, 0.0, 1e30, float("inf")]))
    assert bool(torch.isfinite(ends).all()) and float(ends.min()) == 0.0 and abs(float(ends.max()) - 1.0) < 1e-6
    assert bool(torch.isfinite(inverse_camera_response(torch.tensor([0.0, 1.0]))).all())


def test_bad_relight_data_is_refused():
    with pytest.raises(OmniscsError, match="albedo"):
        matte(torch.zeros(3, 3), torch.zeros(2, 3))
    with pytest.raises(OmniscsError, match="lighting"):
        Relight(torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2), torch.ones(2), torch.zeros(5, 3))
    with pytest.raises(OmniscsError, match="NaN"):
        matte(torch.full((2, 3), float("nan")), torch.zeros(2, 3))
    # extreme light, zero normals, a sun direction of zero length, grazing and zero-length views: finite, 0..1
    gen = torch.Generator().manual_seed(0)
    normals = torch.nn.functional.normalize(torch.randn(5, 3, generator=gen), dim=1)
    normals[0] = 0.0
    for light in (neutral_lighting() * 1e30, torch.zeros(LIGHTING_ROWS, 3), neutral_lighting()):
        r = Relight(torch.rand(5, 3, generator=gen), normals, torch.tensor([0.0, 0.05, 0.5, 1.0, 0.09]),
                    torch.tensor([1.0, 10.0, 400.0, 2000.0, 90.0]), light)
        views = torch.randn(5, 3, generator=gen)
        views[1] = 0.0
        for c in (r.colours(np.eye(3)), r.colours(_yaw(77.0), views)):
            assert bool(torch.isfinite(c).all()) and float(c.min()) >= 0 and float(c.max()) <= 1


def relit_graph(scene):
    """The fitted-graph skeleton of ``scene`` with node 1 opaque, degree-0 and relit (what the agents stage leaves);
    also built from a carried scene on GPU machines that lack the world's packages (infra/gpu_check)."""
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import make_plan
    from tests.nsg_fixtures import tiny_fit_config

    config = tiny_fit_config()
    g = initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))
    node = g.agent(1)
    p = node.gaussians
    p = GaussianParams(p.means, p.quats, p.log_scales + 0.5, p.opacity_logits + 6.0, p.sh_dc,
                       torch.zeros_like(p.sh_rest))
    gen = torch.Generator().manual_seed(0)
    relight = Relight(torch.rand(len(p), 3, generator=gen),
                      torch.nn.functional.normalize(torch.randn(len(p), 3, generator=gen), dim=1),
                      torch.rand(len(p), generator=gen) * 0.1, 1.0 + 200.0 * torch.rand(len(p), generator=gen), LIGHT)
    return g.replace(agents=tuple(a.with_changes(gaussians=p, relight=relight) if a.track_id == 1 else a
                                  for a in g.agents))


LIGHT = torch.tensor([[1.2, 1.1, 1.0], [0.5, 0.45, 0.6], [0.4, 0.45, 0.5], [0.15, 0.14, 0.12], [0.3, 0.4, 0.7],
                      [0.6, 0.65, 0.7], [0.2, 0.2, 0.2]])


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    from omniscs.scene import load_scene
    from tests.nsg_fixtures import nsg_world, write_nsg_scene

    return relit_graph(load_scene(write_nsg_scene(tmp_path_factory.mktemp("relight") / "scene", nsg_world(n_frames=4))))


def _baked(graph, frame: int, extra=np.eye(3)):
    """The graph with node 1's relit colours at ``frame`` written into its Gaussians, relight data dropped."""
    node = graph.agent(1)
    R = node.world_from_agent[frame][:3, :3] @ extra
    view = graph.view(graph.cameras[0].name, frame)
    means = node.gaussians.means.detach()
    centre = (view.world_from_camera[:3, 3] - node.world_from_agent[frame][:3, 3]) @ R  # the camera in the node
    dirs = means - torch.from_numpy(centre).to(means.device, means.dtype)
    dc = (node.relight.colours(R, dirs) - SH_COLOR_OFFSET) / SH_C0
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
    import shutil

    from omniscs.nsg.checkpoint import GRAPH_JSON, load_graph, save_checkpoint

    folder = save_checkpoint(graph, tmp_path / "ckpt")
    back = load_graph(folder)
    r, s = graph.agent(1).relight, back.agent(1).relight
    assert all(torch.equal(getattr(r, k), getattr(s, k)) for k in RELIGHT_TENSORS)
    assert back.agent(2).relight is None
    view = graph.view(graph.cameras[0].name, 1)
    assert torch.allclose(back.render(view).rgb, graph.render(view).rgb, atol=1e-6)
    # a checkpoint relit by the earlier light model (five lighting rows, no materials): a clear error
    from safetensors.torch import load_file, save_file

    from omniscs.nsg.checkpoint import TENSORS, TENSORS_RECORD
    from omniscs.storage import file_sha256

    old = tmp_path / "old"
    shutil.copytree(folder, old)
    t = load_file(str(old / TENSORS))
    key = [k for k in t if k.endswith(".relight.lighting")][0]
    t[key] = t[key][:5].clone()
    t = {k: v for k, v in t.items() if not k.endswith((".relight.specular", ".relight.shininess"))}
    save_file(t, str(old / TENSORS))
    record = json.loads((old / GRAPH_JSON).read_text())  # a whole file of that time, not a damaged one
    record[TENSORS_RECORD] = {"bytes": (old / TENSORS).stat().st_size, "sha256": file_sha256(old / TENSORS)}
    (old / GRAPH_JSON).write_text(json.dumps(record))
    with pytest.raises(OmniscsError, match="earlier light model"):
        load_graph(old)
    meta = json.loads((folder / GRAPH_JSON).read_text())
    meta["agents"][[a["track_id"] for a in meta["agents"]].index(1)]["relight"] = "yes"
    (folder / GRAPH_JSON).write_text(json.dumps(meta))
    with pytest.raises(OmniscsError, match="relight"):
        load_graph(folder)


def relit_node_checks(graph, device: str) -> dict:
    """A relit graph moved to ``device`` (CUDA: rendered by gsplat) renders node 1 in the colours its relight data
    give at each frame's pose and after a turn (against the same colours baked by hand, on that device, and against
    the CPU render), and its light fits back through that device's rasterizer (agents.relight.fit_lighting, as the
    dual strategy calls it), and the dual strategy's colour correction and refinement run there (they read the
    renders back to the CPU). Asserts; returns the figures (infra/gpu_check/relight_cuda.py prints them)."""
    from omniscs.agents.relight import fit_lighting
    from omniscs.agents.track_pixels import track_alone
    from omniscs.nsg.edit import apply_graph_edits
    from omniscs.nsg.graph import render_view
    from omniscs.nsg.relight import neutral_lighting

    moved = graph.to(device)
    r = moved.agent(1).relight
    assert all(getattr(r, k).device.type == torch.device(device).type for k in RELIGHT_TENSORS)
    cam = graph.cameras[0].name
    turn = [{"op": "rotate", "track_id": 1, "yaw_deg": 90.0}]
    figures = {"backend": None, "baked_max_diff": 0.0, "cpu_mean_diff": 0.0}
    for frame, edits, extra in ((0, [], np.eye(3)), (3, [], np.eye(3)), (2, turn, _yaw(90.0))):
        g = apply_graph_edits(moved, edits) if edits else moved
        assert g.agent(1).relight is not None
        view = g.view(cam, frame)
        out = g.render(view)
        baked = _baked(moved, frame, extra)
        baked = apply_graph_edits(baked, edits) if edits else baked
        figures["backend"] = out.meta["backend"]
        figures["baked_max_diff"] = max(figures["baked_max_diff"],
                                        float((out.rgb - baked.render(view).rgb).abs().max()))
        on_cpu = (apply_graph_edits(graph, edits) if edits else graph).render(graph.view(cam, frame)).rgb
        figures["cpu_mean_diff"] = max(figures["cpu_mean_diff"], float((out.rgb.cpu() - on_cpu).abs().mean()))
        assert bool(torch.isfinite(out.rgb).all())
    assert figures["baked_max_diff"] < 1e-4 and figures["cpu_mean_diff"] < 2e-3, figures
    # the light, fitted back from renders made with it, starting from an even light
    node = moved.agent(1)
    alone = track_alone(moved, 1, node.gaussians).replace(agents=(node,))
    samples = []
    for f in range(graph.n_frames):
        out = render_view(alone, moved.view(cam, f))
        if (out.alpha > 0.9).sum() > 50:
            samples.append((moved.view(cam, f), out.rgb.detach().cpu(), out.alpha.detach().cpu()))
    assert samples
    even = node.relight.with_lighting(neutral_lighting().to(device))
    fitted, info = fit_lighting(moved, 1, node.gaussians, even, samples, steps=100, render_steps=150, render_lr=0.05)
    assert fitted.lighting.device.type == torch.device(device).type
    assert info["views"] == len(samples) and info["loss_last"] < 0.3 * info["loss_first"], info
    figures["light_fit"] = info
    # the dual strategy's colour helpers on the same device: the colour map of a node against renders of itself
    # is the identity, and colours put off by a shift are refined back
    from omniscs.agents.dual import fit_colour_correction, refine_colours

    plain = alone.replace(agents=(node.with_changes(gaussians=node.gaussians),))  # stored colours, no relight
    targets = [(v, render_view(plain, v).rgb.detach().cpu(), w) for v, _, w in samples]
    affine = fit_colour_correction(moved, 1, node.gaussians, targets)
    assert np.allclose(affine, np.hstack([np.eye(3), np.zeros((3, 1))]), atol=1e-3), affine
    p = node.gaussians
    off = GaussianParams(p.means, p.quats, p.log_scales, p.opacity_logits, p.sh_dc + 0.3, p.sh_rest)

    def error(params):
        g = alone.replace(agents=(node.with_changes(gaussians=params),))
        with torch.no_grad():
            return float(np.mean([(render_view(g, v).rgb.cpu() - t)[w > 0.9].abs().mean() for v, t, w in targets]))

    refined = refine_colours(moved, 1, off, targets, steps=60)
    assert refined.sh_dc.device.type == torch.device(device).type
    figures["colour_refine"] = {"error_off": error(off), "error_refined": error(refined)}
    assert figures["colour_refine"]["error_refined"] < 0.5 * figures["colour_refine"]["error_off"], figures
    return figures


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA GPU"))])
def test_a_relit_node_renders_and_fits_its_light_on_the_graphs_device(graph, device):
    relit_node_checks(graph, device)
