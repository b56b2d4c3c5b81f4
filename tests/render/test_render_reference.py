"""The reference rasteriser's semantics (the oracle for every backend) and its gradients."""
from __future__ import annotations

import math

import pytest
import torch

from omniscs.render import rasterize
from omniscs.render.constants import MAX_ALPHA
from omniscs.render.scenes import random_scene
from omniscs.render.sh import SH_C0, num_sh_bases, sh_basis

F64 = torch.float64


@pytest.fixture
def one_torch_thread():
    """gradcheck runs thousands of tiny ops: threads only add synchronisation (and stall on a busy machine)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def pinhole(width: int, height: int, focal: float = 20.0, dtype=F64) -> tuple[torch.Tensor, torch.Tensor]:
    """An identity-pose camera ([1, 4, 4], [1, 3, 3]) with its principal point at the image centre."""
    K = torch.tensor([[[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]]], dtype=dtype)
    return torch.eye(4, dtype=dtype)[None], K


def gaussians(means, scales, opacities, colors, quats=None, dtype=F64) -> dict[str, torch.Tensor]:
    means = torch.as_tensor(means, dtype=dtype)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype) if quats is None else torch.as_tensor(quats, dtype=dtype)
    return dict(means=means, quats=quats, scales=torch.as_tensor(scales, dtype=dtype),
                opacities=torch.as_tensor(opacities, dtype=dtype), colors=torch.as_tensor(colors, dtype=dtype))


def test_gaussian_centred_on_a_pixel_gives_that_pixel_its_opacity_and_colour():
    viewmats, Ks = pinhole(9, 9)
    # pixel (4, 4) has its centre at (4.5, 4.5) = the principal point, straight ahead
    g = gaussians([[0.0, 0.0, 5.0]], [[0.1, 0.1, 0.1]], [0.6], [[0.2, 0.4, 0.8]])
    colors, alphas, _ = rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, backend="reference")
    assert alphas[0, 4, 4, 0].item() == pytest.approx(0.6, rel=1e-12)
    assert colors[0, 4, 4].tolist() == pytest.approx([0.6 * 0.2, 0.6 * 0.4, 0.6 * 0.8], rel=1e-12)


def test_alpha_is_clamped_below_one_so_transmittance_stays_positive():
    viewmats, Ks = pinhole(9, 9)
    g = gaussians([[0.0, 0.0, 5.0]], [[0.1, 0.1, 0.1]], [1.0], [[1.0, 1.0, 1.0]])
    _, alphas, _ = rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, backend="reference")
    assert alphas[0, 4, 4, 0].item() == pytest.approx(MAX_ALPHA, rel=1e-12)


def test_nearer_gaussian_occludes_farther_one_whatever_the_input_order():
    viewmats, Ks = pinhole(9, 9)
    near_red = ([0.0, 0.0, 3.0], [0.3] * 3, 0.95, [1.0, 0.0, 0.0])
    far_blue = ([0.0, 0.0, 6.0], [0.6] * 3, 0.95, [0.0, 0.0, 1.0])
    images = []
    for order in ((near_red, far_blue), (far_blue, near_red)):
        g = gaussians(*[list(column) for column in zip(*order)])
        images.append(rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, backend="reference")[0])
    torch.testing.assert_close(images[0], images[1], rtol=0, atol=1e-14)
    centre = images[0][0, 4, 4]
    assert centre[0] > 0.9 and centre[2] < 0.05


def test_compositing_stops_before_transmittance_falls_to_threshold():
    viewmats, Ks = pinhole(9, 9)
    # two opaque layers: after the first T = 0.001; the second would take it to 1e-6 <= 1e-4, so it is skipped
    g = gaussians([[0.0, 0.0, 3.0], [0.0, 0.0, 4.0]], [[0.1] * 3] * 2, [1.0, 1.0], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    colors, alphas, _ = rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, backend="reference")
    assert alphas[0, 4, 4, 0].item() == pytest.approx(MAX_ALPHA, rel=1e-12)
    assert colors[0, 4, 4, 1].item() == 0.0


def test_background_shows_through_in_proportion_to_transmittance():
    viewmats, Ks = pinhole(9, 9)
    g = gaussians([[0.0, 0.0, 5.0]], [[0.1, 0.1, 0.1]], [0.6], [[1.0, 0.0, 0.0]])
    background = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    colors, _, _ = rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, backgrounds=background,
                             backend="reference")
    assert colors[0, 4, 4].tolist() == pytest.approx([0.6, 0.0, 0.4], rel=1e-12)
    assert colors[0, 0, 0].tolist() == pytest.approx([0.0, 0.0, 1.0], abs=1e-12)


def test_expected_depth_is_the_depth_of_a_single_layer_and_zero_where_nothing_is_drawn():
    viewmats, Ks = pinhole(9, 9)
    g = gaussians([[0.0, 0.0, 5.0]], [[0.1, 0.1, 0.1]], [0.6], [[1.0, 0.0, 0.0]])
    depth, alphas, _ = rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, render_mode="ED",
                                 backend="reference")
    accumulated, _, _ = rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, render_mode="D",
                                  backend="reference")
    assert depth[0, 4, 4, 0].item() == pytest.approx(5.0, rel=1e-12)
    assert accumulated[0, 4, 4, 0].item() == pytest.approx(0.6 * 5.0, rel=1e-12)
    assert alphas[0, 0, 0, 0].item() == 0.0 and depth[0, 0, 0, 0].item() == 0.0


def test_rgb_plus_depth_appends_the_depth_channel():
    s = random_scene(30, 24, 16)
    rgb, _, _ = rasterize(**s.as_kwargs(), backend="reference")
    rgbd, _, _ = rasterize(**s.as_kwargs(), render_mode="RGB+ED", backend="reference")
    ed, _, _ = rasterize(**s.as_kwargs(), render_mode="ED", backend="reference")
    torch.testing.assert_close(rgbd, torch.cat([rgb, ed], -1))


def test_sh_basis_is_orthonormal_on_the_sphere():
    # Fibonacci sphere quadrature: the mean of Y_i Y_j times 4 pi must be the identity
    n = 20_000
    k = torch.arange(n, dtype=F64) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5 ** 0.5) * k
    dirs = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], -1)
    basis = sh_basis(3, dirs)
    gram = 4 * math.pi * basis.T @ basis / n
    torch.testing.assert_close(gram, torch.eye(num_sh_bases(3), dtype=F64), atol=1e-3, rtol=0)


def test_sh_degree_zero_gives_the_dc_colour_plus_offset():
    viewmats, Ks = pinhole(9, 9)
    g = gaussians([[0.0, 0.0, 5.0]], [[0.1, 0.1, 0.1]], [0.6], [[0.0, 0.0, 0.0]])
    g["colors"] = torch.tensor([[[0.3, -0.2, 0.1]]], dtype=F64)
    colors, _, _ = rasterize(**g, viewmats=viewmats, Ks=Ks, width=9, height=9, sh_degree=0, backend="reference")
    expected = [0.6 * max(SH_C0 * c + 0.5, 0.0) for c in (0.3, -0.2, 0.1)]
    assert colors[0, 4, 4].tolist() == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_reference_gradients_match_finite_differences(mode, one_torch_thread):
    s = random_scene(4, 10, 8, seed=3, depth_range=(3.0, 5.0), scale_range=(0.3, 0.8))
    names = ("means", "quats", "scales", "opacities", "colors")
    leaves = tuple(getattr(s, name).clone().requires_grad_(True) for name in names)

    def render(*params):
        colors, alphas, _ = rasterize(*params, s.viewmats, s.Ks, s.width, s.height, render_mode="RGB+ED",
                                      backgrounds=torch.tensor([[0.1, 0.2, 0.3]], dtype=F64),
                                      rasterize_mode=mode, backend="reference")
        return colors, alphas

    assert torch.autograd.gradcheck(render, leaves, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_reference_sh_gradients_match_finite_differences(one_torch_thread):
    s = random_scene(3, 8, 6, seed=5, depth_range=(3.0, 5.0), scale_range=(0.3, 0.8))
    coeffs = (0.3 * torch.randn(3, 16, 3, dtype=F64, generator=torch.Generator().manual_seed(0))).requires_grad_(True)
    means = s.means.clone().requires_grad_(True)

    def render(means, coeffs):
        return rasterize(means, s.quats, s.scales, s.opacities, coeffs, s.viewmats, s.Ks, s.width, s.height,
                         sh_degree=3, backend="reference")[0]

    assert torch.autograd.gradcheck(render, (means, coeffs), eps=1e-6, atol=1e-5, rtol=1e-4)
