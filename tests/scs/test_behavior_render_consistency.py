"""L_app: the feature net (fixed random init or a user's local weights) and the render-consistency term's interface."""
import numpy as np
import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.scs.behavior.render_consistency import (AgentTrajectories, FeatureNet, FeatureNetConfig,
                                                    RenderConsistencyTerm, build_feature_net, masked_psnr)


def blob_renderer(size: int = 32, extent_m: float = 40.0):
    """A toy differentiable renderer for the interface tests (not a scene graph): each agent is a Gaussian
    blob in a top-down image, one frame per step."""
    coords = (torch.arange(size, dtype=torch.float32) + 0.5) * extent_m / size

    def render(traj: AgentTrajectories) -> torch.Tensor:  # -> [T, 3, H, W]
        x, y = traj.poses[..., 0], traj.poses[..., 1]  # [N, T]
        gx = torch.exp(-0.5 * ((coords[None, None, :] - x[..., None]) / 2.0) ** 2)  # [N, T, W]
        gy = torch.exp(-0.5 * ((coords[None, None, :] - y[..., None]) / 2.0) ** 2)  # [N, T, H]
        img = (gy[..., :, None] * gx[..., None, :]).sum(0).clamp(0, 1)  # [T, H, W]
        return torch.stack([img, 0.5 * img, 1.0 - img], 1)

    return render


def _trajectories(offset: float = 0.0, requires_grad: bool = False) -> AgentTrajectories:
    t = torch.arange(4, dtype=torch.float32)
    poses = torch.stack([torch.stack([10 + 2 * t + offset, torch.full_like(t, 20.0), torch.zeros_like(t)], -1),
                         torch.stack([30 - 2 * t, torch.full_like(t, 12.0), torch.zeros_like(t)], -1)])
    poses.requires_grad_(requires_grad)
    return AgentTrajectories([1, 2], poses, np.arange(10, 14), np.arange(10, 14) * 100_000)


def test_random_feature_net_is_fixed_by_its_seed_and_leaves_the_global_rng_alone():
    x = torch.rand(2, 3, 32, 32)
    state = torch.random.get_rng_state()
    a, b = build_feature_net(FeatureNetConfig(seed=3)), build_feature_net(FeatureNetConfig(seed=3))
    assert torch.equal(torch.random.get_rng_state(), state)
    assert all(torch.equal(fa, fb) for fa, fb in zip(a(x), b(x)))
    c = build_feature_net(FeatureNetConfig(seed=4))
    assert not torch.equal(a(x)[0], c(x)[0])
    assert not any(p.requires_grad for p in a.parameters())


@pytest.mark.parametrize("kind", ["state_dict", "export", "torchscript"])
def test_missing_user_weights_are_a_clear_error(kind, tmp_path):
    with pytest.raises(OmniscsError, match="feature-net weights not found.*use kind 'random'"):
        build_feature_net(FeatureNetConfig(kind=kind, weights_path=str(tmp_path / "vgg.pt")))


def test_a_users_network_plugs_in_from_a_state_dict(tmp_path):
    torch.manual_seed(0)
    trained = FeatureNet()
    torch.save(trained.state_dict(), tmp_path / "net.pt")
    x = torch.rand(1, 3, 16, 16)
    from_state = build_feature_net(FeatureNetConfig(kind="state_dict", weights_path=str(tmp_path / "net.pt")))
    assert torch.allclose(from_state(x)[-1], trained(x)[-1])
    torch.save({"not": "weights"}, tmp_path / "bad.pt")
    with pytest.raises(OmniscsError, match="do not load"):
        build_feature_net(FeatureNetConfig(kind="state_dict", weights_path=str(tmp_path / "bad.pt")))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("kind", ["export", "torchscript"])
def test_any_users_cnn_plugs_in_as_an_exported_program_or_torchscript(kind, tmp_path):
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3), torch.nn.ReLU())
    path = tmp_path / f"net.{kind}"
    if kind == "export":
        auto = torch.export.Dim.AUTO
        torch.export.save(torch.export.export(net, (torch.rand(2, 3, 16, 16),),
                                              dynamic_shapes=({0: auto, 2: auto, 3: auto},)), path)
    else:
        torch.jit.save(torch.jit.script(net), path)
    loaded = build_feature_net(FeatureNetConfig(kind=kind, weights_path=str(path)))
    render = blob_renderer()
    term = RenderConsistencyTerm(render, render(_trajectories()).detach(), feature_net=loaded)
    assert term(_trajectories()).item() == pytest.approx(0.0, abs=1e-9)
    moved = _trajectories(2.0, requires_grad=True)
    term(moved).backward()
    assert moved.poses.grad.abs().sum() > 0


def test_render_consistency_term_is_zero_for_the_original_grows_with_the_edit_and_reaches_the_poses():
    render = blob_renderer()
    term = RenderConsistencyTerm(render, render(_trajectories()).detach())
    assert term(_trajectories()).item() == pytest.approx(0.0, abs=1e-9)
    near, far = term(_trajectories(1.0)).item(), term(_trajectories(6.0)).item()
    assert 0 < near < far
    moved = _trajectories(3.0, requires_grad=True)
    term(moved).backward()
    assert torch.isfinite(moved.poses.grad).all() and moved.poses.grad[0, :, 0].abs().sum() > 0


def test_render_consistency_term_refuses_mismatched_frames():
    render = blob_renderer()
    term = RenderConsistencyTerm(render, render(_trajectories()).detach()[:2])
    with pytest.raises(OmniscsError, match="returned 4 frames"):
        term(_trajectories())


def test_masked_psnr_counts_only_the_adversarys_pixels():
    gt = np.zeros((2, 4, 4, 3))
    rendered = gt.copy()
    rendered[:, 0, 0] = 0.1  # error inside the mask
    rendered[:, 3, 3] = 1.0  # error outside it is ignored
    mask = np.zeros((2, 4, 4), bool)
    mask[:, 0, :2] = True
    assert masked_psnr(rendered, gt, mask) == pytest.approx(10 * np.log10(1 / (0.01 / 2)))
    assert masked_psnr(rendered, gt, np.zeros_like(mask)) is None
