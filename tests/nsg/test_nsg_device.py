"""Where a scene graph lives: FitConfig.device (CPU by default, CUDA only where there is one), checkpoints
loaded onto a chosen device, and CUDA fits that render through gsplat."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.nsg import FitConfig, fit_preset, fit_scene, load_graph
from omniscs.nsg.config import resolve_device
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene


@pytest.fixture
def no_cuda(monkeypatch):
    """This machine as one without a GPU, whatever it really has."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return load_scene(write_nsg_scene(tmp_path_factory.mktemp("nsg-device") / "scene", nsg_world(n_frames=4)))


def test_the_default_device_is_the_cpu():
    assert FitConfig().device == "cpu" and FitConfig().torch_device == torch.device("cpu")
    assert all(preset.device == "cpu" for preset in (fit_preset(n) for n in ("fast", "balanced", "accurate")))


@pytest.mark.parametrize("device", ["cuda", "cuda:0"])
def test_asking_for_cuda_without_cuda_is_a_clear_error(no_cuda, device):
    with pytest.raises(OmniscsError, match="no CUDA GPU.*device='cpu'"):
        FitConfig(device=device)
    with pytest.raises(OmniscsError, match="no CUDA GPU"):
        fit_preset("fast", device=device)


@pytest.mark.parametrize("device", ["gpu", "cuda:x", "mps", 3.5])
def test_an_unknown_or_unsupported_device_is_a_clear_error(device):
    with pytest.raises(OmniscsError, match="device"):
        resolve_device(device)


def test_the_device_is_not_part_of_what_a_fit_means():
    """``to_dict`` is recorded in checkpoints and hashed into the fit stage's key: it must not name the device,
    so existing CPU fits keep their fingerprint and a GPU fit of the same settings reuses as the same."""
    config = tiny_fit_config(10)
    d = config.to_dict()
    assert "device" not in d
    assert set(d) == {f.name for f in dataclasses.fields(FitConfig)} - {"device"}
    assert FitConfig.from_dict(d) == config
    assert FitConfig.from_dict({**d, "device": "cpu"}) == config


def test_a_checkpoint_loads_onto_the_chosen_device_and_cuda_without_cuda_is_refused(scene, tmp_path, monkeypatch):
    config = tiny_fit_config(5)
    fit_scene(scene, config, make_plan(scene, None, config.plan), evaluate=False, checkpoint_dir=tmp_path / "ckpt")
    graph = load_graph(tmp_path / "ckpt", device="cpu")
    assert graph.device == torch.device("cpu")
    assert all(a.gaussians.device == torch.device("cpu") for a in graph.agents)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(OmniscsError, match="no CUDA GPU"):
        load_graph(tmp_path / "ckpt", device="cuda")


def test_moving_a_graph_to_where_it_is_shares_its_tensors(scene):
    config = tiny_fit_config(3)
    graph = fit_scene(scene, config, make_plan(scene, None, config.plan), evaluate=False).graph
    same = graph.to("cpu")
    assert same.background.means is graph.background.means and same.sky.texture is graph.sky.texture
    view = graph.view("CAM_FRONT", 1)
    assert torch.equal(same.render(view).rgb, graph.render(view).rgb)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_tiny_cuda_fit_trains_and_renders_through_gsplat(scene, tmp_path):
    pytest.importorskip("gsplat")
    config = tiny_fit_config(20, device="cuda")
    result = fit_scene(scene, config, make_plan(scene, None, config.plan), checkpoint_dir=tmp_path / "ckpt")
    graph = result.graph
    assert graph.device.type == "cuda" and all(a.gaussians.device.type == "cuda" for a in graph.agents)
    assert graph.sky.texture.is_cuda and all(t.is_cuda for t in graph.exposure.values())
    out = graph.render(graph.view("CAM_FRONT", 2))
    assert out.rgb.is_cuda and out.meta["backend"] == "gsplat"
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    assert result.metrics["heldout_psnr"] > 10.0
    on_cpu = load_graph(tmp_path / "ckpt", device="cpu")  # fitted on a GPU, inspected anywhere
    assert on_cpu.device.type == "cpu" and on_cpu.render(on_cpu.view("CAM_FRONT", 2)).meta["backend"] == "cpu"
