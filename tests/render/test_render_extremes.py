"""Numerical extremes and input errors: never NaN or Inf, one clear error for wrong inputs."""
from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from omniscs.errors import OmniscsError
from omniscs.render import rasterize
from omniscs.render.scenes import random_scene

BACKENDS = ("cpu", "reference")
PARAMS = ("means", "quats", "scales", "opacities", "colors")
WIDTH, HEIGHT = 24, 16


def camera(dtype=torch.float32, focal=20.0):
    K = torch.tensor([[[focal, 0.0, WIDTH / 2], [0.0, focal, HEIGHT / 2], [0.0, 0.0, 1.0]]], dtype=dtype)
    return torch.eye(4, dtype=dtype)[None], K


def render_with_grads(means, quats, scales, opacities, colors, backend, dtype=torch.float32, **kwargs):
    """Outputs and gradients of every Gaussian parameter for a weighted sum of all outputs."""
    leaves = [torch.as_tensor(x, dtype=dtype).clone().requires_grad_(True)
              for x in (means, quats, scales, opacities, colors)]
    viewmats, Ks = camera(dtype)
    out_colors, out_alphas, meta = rasterize(*leaves, viewmats, Ks, WIDTH, HEIGHT, backend=backend,
                                             render_mode="RGB+ED", **kwargs)
    meta["means2d"].retain_grad()
    (out_colors.sum() + 2 * out_alphas.sum()).backward()
    grads = [leaf.grad for leaf in leaves] + [meta["means2d"].grad]
    return out_colors, out_alphas, grads


def assert_all_finite(*tensors):
    for t in tensors:
        if t is not None:
            assert torch.isfinite(t).all(), t


def one(mean, scale=(0.2, 0.2, 0.2), quat=(1.0, 0.0, 0.0, 0.0), opacity=0.8, color=(0.3, 0.6, 0.9)):
    return [mean], [quat], [scale], [opacity], [color]


EXTREME_CASES = {
    "behind the camera": one((0.0, 0.0, -3.0)),
    "straddling the near plane": one((0.0, 0.0, 0.02), scale=(1.0, 1.0, 1.0)),
    "exactly at the near plane": one((0.0, 0.0, 0.01)),
    "10 km away": one((0.0, 0.0, 10_000.0), scale=(50.0, 50.0, 50.0)),
    "10 km away and tiny": one((3.0, -2.0, 10_000.0), scale=(1e-3, 1e-3, 1e-3)),
    "scale 1e-6": one((0.0, 0.0, 3.0), scale=(1e-6, 1e-6, 1e-6)),
    "scale 1e3": one((0.0, 0.0, 3.0), scale=(1e3, 1e3, 1e3)),
    "scales 1e-6 and 1e3 at once": one((0.0, 0.0, 3.0), scale=(1e3, 1e-6, 1e-6)),
    "flat covariance facing the camera": one((0.0, 0.0, 3.0), scale=(0.5, 0.5, 0.0)),
    "flat covariance edge-on": one((0.0, 0.0, 3.0), scale=(0.5, 0.0, 0.5)),
    "needle along the view ray": one((0.0, 0.0, 3.0), scale=(0.0, 0.0, 2.0)),
    "zero scale": one((0.0, 0.0, 3.0), scale=(0.0, 0.0, 0.0)),
    "opacity 0": one((0.0, 0.0, 3.0), opacity=0.0),
    "opacity 1": one((0.0, 0.0, 3.0), opacity=1.0),
    "zero-norm quaternion": one((0.0, 0.0, 3.0), scale=(0.5, 0.1, 0.1), quat=(0.0, 0.0, 0.0, 0.0)),
    "tiny unnormalised quaternion": one((0.0, 0.0, 3.0), scale=(0.5, 0.1, 0.1), quat=(1e-9, 2e-9, 0.0, 0.0)),
    "huge unnormalised quaternion": one((0.0, 0.0, 3.0), scale=(0.5, 0.1, 0.1), quat=(1e8, 3e8, -2e8, 0.5)),
    "far outside the view": one((1e4, 0.0, 1.0)),
    "covering the whole image": one((0.0, 0.0, 0.5), scale=(30.0, 30.0, 30.0), opacity=0.5),
}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", EXTREME_CASES)
def test_extreme_gaussians_render_and_differentiate_without_nan_or_inf(case, backend):
    colors, alphas, grads = render_with_grads(*EXTREME_CASES[case], backend=backend)
    assert_all_finite(colors, alphas, *grads)


def test_gaussian_covering_the_whole_image_touches_every_pixel_alike_in_both_backends():
    args = EXTREME_CASES["covering the whole image"]
    cpu_colors, cpu_alphas, _ = render_with_grads(*args, backend="cpu")
    ref_colors, ref_alphas, _ = render_with_grads(*args, backend="reference", dtype=torch.float64)
    assert (cpu_alphas > 0.4).all()
    torch.testing.assert_close(cpu_colors.double(), ref_colors, atol=1e-5, rtol=1e-5)


def test_gaussians_behind_or_beyond_the_planes_are_culled():
    means = [[0.0, 0.0, -3.0], [0.0, 0.0, 0.005], [0.0, 0.0, 50.0], [0.0, 0.0, 3.0]]
    n = len(means)
    viewmats, Ks = camera()
    for backend in BACKENDS:
        _, _, meta = rasterize(torch.tensor(means), torch.tensor([[1.0, 0, 0, 0]] * n), torch.full((n, 3), 0.3),
                               torch.full((n,), 0.9), torch.rand(n, 3), viewmats, Ks, WIDTH, HEIGHT,
                               far_plane=20.0, backend=backend)
        assert (meta["radii"][0, :, 0] > 0).tolist() == [False, False, False, True], backend


@pytest.mark.parametrize("backend", BACKENDS)
def test_rotation_by_q_and_minus_q_renders_identically(backend):
    s = random_scene(80, WIDTH, HEIGHT, seed=11, dtype=torch.float32)
    plus = rasterize(**s.as_kwargs(), backend=backend)[0]
    minus = rasterize(**{**s.as_kwargs(), "quats": -s.quats}, backend=backend)[0]
    if backend == "cpu":
        assert torch.equal(plus, minus)
    else:
        torch.testing.assert_close(plus, minus, atol=1e-6, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_norm_quaternion_renders_as_the_identity_rotation_and_gets_no_gradient(backend):
    scale = (0.6, 0.1, 0.1)  # anisotropic, so a wrong rotation would show
    zero = render_with_grads(*one((0.0, 0.0, 3.0), scale=scale, quat=(0.0, 0.0, 0.0, 0.0)), backend=backend)
    identity = render_with_grads(*one((0.0, 0.0, 3.0), scale=scale), backend=backend)
    torch.testing.assert_close(zero[0], identity[0])
    assert (zero[2][1] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_unnormalised_quaternions_render_like_their_normalised_versions(backend):
    s = random_scene(50, WIDTH, HEIGHT, seed=12, dtype=torch.float32)
    unit = rasterize(**{**s.as_kwargs(), "quats": s.quats / s.quats.norm(dim=-1, keepdim=True)}, backend=backend)[0]
    scaled = rasterize(**{**s.as_kwargs(), "quats": 7.5 * s.quats}, backend=backend)[0]
    torch.testing.assert_close(unit, scaled, atol=1e-5, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", ["RGB", "D", "ED", "RGB+D", "RGB+ED"])
def test_no_gaussians_renders_the_background_and_zero_depth(backend, mode):
    viewmats, Ks = camera()
    empty = [torch.zeros(0, 3, requires_grad=True), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0),
             torch.zeros(0, 3)]
    backgrounds = None if mode in ("D", "ED") else torch.tensor([[0.1, 0.2, 0.3]])
    colors, alphas, meta = rasterize(*empty, viewmats, Ks, WIDTH, HEIGHT, backgrounds=backgrounds,
                                     render_mode=mode, backend=backend)
    channels = {"RGB": 3, "D": 1, "ED": 1, "RGB+D": 4, "RGB+ED": 4}[mode]
    assert colors.shape == (1, HEIGHT, WIDTH, channels) and alphas.shape == (1, HEIGHT, WIDTH, 1)
    assert (alphas == 0).all()
    if backgrounds is not None:
        torch.testing.assert_close(colors[..., :3], backgrounds[:, None, None, :].expand(1, HEIGHT, WIDTH, 3))
    if "D" in mode:
        assert (colors[..., -1] == 0).all()
    colors.sum().backward()
    assert meta["radii"].shape == (1, 0, 2) and empty[0].grad.shape == (0, 3)


def test_equal_depths_composite_lower_index_first_in_both_backends():
    n = 6
    means = torch.tensor([[0.1 * i - 0.25, 0.05 * i, 4.0] for i in range(n)], dtype=torch.float64)
    args = (means, torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64), torch.full((n, 3), 0.4, dtype=torch.float64),
            torch.full((n,), 0.7, dtype=torch.float64), torch.eye(3, dtype=torch.float64)[torch.arange(n) % 3])
    viewmats, Ks = camera(torch.float64)
    cpu = rasterize(*args, viewmats, Ks, WIDTH, HEIGHT, backend="cpu")[0]
    ref = rasterize(*args, viewmats, Ks, WIDTH, HEIGHT, backend="reference")[0]
    torch.testing.assert_close(cpu, ref, atol=1e-6, rtol=0)
    flipped = rasterize(means.flip(0), *[a.flip(0) for a in args[1:]], viewmats, Ks, WIDTH, HEIGHT, backend="reference")[0]
    assert (flipped - ref).abs().max() > 1e-2  # the order matters, so the test above could fail


finite_float = st.floats(allow_nan=False, allow_infinity=False, width=32)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    depth=st.sampled_from([-5.0, 0.0, 0.01, 0.0100001, 0.3, 2.0, 1e2, 1e4]),
    offset=st.tuples(st.floats(-50, 50), st.floats(-50, 50)),
    log_scales=st.tuples(*[st.floats(-6, 3)] * 3),
    quat=st.tuples(*[st.floats(-1e3, 1e3)] * 4),
    opacity=st.floats(0.0, 1.0),
    eps2d=st.sampled_from([0.0, 0.3]),
    antialiased=st.booleans(),
)
def test_any_single_gaussian_gives_finite_images_and_gradients(depth, offset, log_scales, quat, opacity, eps2d,
                                                                antialiased):
    mean = (offset[0] * abs(depth) / 10, offset[1] * abs(depth) / 10, depth)
    scale = tuple(10.0 ** s for s in log_scales)
    args = one(mean, scale=scale, quat=quat, opacity=opacity)
    mode = "antialiased" if antialiased else "classic"
    colors, alphas, grads = render_with_grads(*args, backend="cpu", eps2d=eps2d, rasterize_mode=mode)
    assert_all_finite(colors, alphas, *grads)


BAD_INPUTS = {
    "means not [N, 3]": dict(means=torch.zeros(2, 2)),
    "quats of another length": dict(quats=torch.zeros(3, 4)),
    "scales [N]": dict(scales=torch.ones(2)),
    "opacities [N, 1]": dict(opacities=torch.ones(2, 1)),
    "colors for another N": dict(colors=torch.ones(5, 3)),
    "integer means": dict(means=torch.zeros(2, 3, dtype=torch.int64)),
    "float16 colours": dict(colors=torch.ones(2, 3, dtype=torch.float16)),
    "mixed float dtypes": dict(scales=torch.ones(2, 3, dtype=torch.float64)),
    "a list instead of a tensor": dict(opacities=[0.5, 0.5]),
    "viewmats [4, 4]": dict(viewmats=torch.eye(4)),
    "Ks for another C": dict(Ks=torch.eye(3).expand(2, 3, 3)),
    "zero width": dict(width=0),
    "float height": dict(height=16.0),
    "unknown render mode": dict(render_mode="RGBD"),
    "unknown backend": dict(backend="cuda"),
    "sh_degree 4": dict(sh_degree=4, colors=torch.ones(2, 25, 3)),
    "too few SH coefficients": dict(sh_degree=2, colors=torch.ones(2, 4, 3)),
    "backgrounds with wrong D": dict(backgrounds=torch.ones(1, 4)),
    "backgrounds in depth mode": dict(backgrounds=torch.ones(1, 3), render_mode="D"),
    "near plane at zero": dict(near_plane=0.0),
    "far plane before near": dict(near_plane=1.0, far_plane=0.5),
    "negative eps2d": dict(eps2d=-0.1),
    "unknown rasterize mode": dict(rasterize_mode="mip"),
    "absgrad on the reference": dict(absgrad=True, backend="reference"),
    "gsplat without CUDA": dict(backend="gsplat"),
}


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_wrong_inputs_raise_one_clear_domain_error(case):
    viewmats, Ks = camera()
    kwargs = dict(means=torch.zeros(2, 3), quats=torch.ones(2, 4), scales=torch.ones(2, 3), opacities=torch.ones(2),
                  colors=torch.ones(2, 3), viewmats=viewmats, Ks=Ks, width=WIDTH, height=HEIGHT)
    kwargs.update(BAD_INPUTS[case])
    with pytest.raises(OmniscsError) as info:
        rasterize(**kwargs)
    assert "\n" not in str(info.value) and len(str(info.value)) < 200
