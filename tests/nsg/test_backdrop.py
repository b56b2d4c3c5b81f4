"""The fused CPU backdrop (omniscs.nsg.backdrop: sky through 1 - alpha, then the exposure affine) against its
PyTorch definition, in values and gradients: views that look along the texture's seam, straight up and straight
down (its borders), alpha at 0 and 1, and the same result on one Numba thread as on two."""
from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from omniscs.geometry import make_transform, rotmat_from_euler
from omniscs.nsg.backdrop import backdrop_reference, with_backdrop
from omniscs.nsg.observations import View
from omniscs.nsg.sky import SkyParams

#: Camera frame (x right, y down, z forward) -> world axes for a camera looking along +x, level.
LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _view(rotation: np.ndarray, width: int = 41, height: int = 27, fov_px: float = 20.0) -> View:
    K = np.array([[fov_px, 0.0, width / 2 + 0.7], [0.0, fov_px, height / 2 - 0.4], [0.0, 0.0, 1.0]])
    return View(0, make_transform(rotation, np.array([1.0, -2.0, 0.5])), K, width, height, "CAM_FRONT")


def _inputs(view: View, seed: int):
    g = torch.Generator().manual_seed(seed)
    colour = torch.rand(view.height, view.width, 3, generator=g)
    alpha = torch.rand(view.height, view.width, generator=g)
    alpha[:3] = 0.0  # nothing in front of the sky
    alpha[-3:] = 1.0  # nothing of the sky shows
    texture = torch.randn(3, 6, 10, generator=g) * 2  # coarse, so neighbouring pixels share texels
    affine = torch.cat([torch.eye(3) + 0.2 * torch.randn(3, 3, generator=g), 0.1 * torch.randn(3, 1, generator=g)], 1)
    return colour, alpha, texture, affine


def _run(fn, view, inputs, upstream, with_affine=True):
    leaves = [t.clone().requires_grad_(True) for t in inputs]
    rgb = fn(leaves[0], leaves[1], SkyParams(leaves[2]), leaves[3] if with_affine else None, view)
    (rgb * upstream).sum().backward()
    return rgb.detach(), [t.grad for t in leaves]


VIEWS = {
    "level": LEVEL,
    "seam": rotmat_from_euler(0.0, 0.0, np.pi) @ LEVEL,  # looking along -x: azimuth +-pi, the texture's two ends
    "up": rotmat_from_euler(0.0, -np.pi / 2, 0.0) @ LEVEL,  # the top row of the texture and past it
    "down": rotmat_from_euler(0.0, np.pi / 2, 0.0) @ LEVEL,
    "tilted": rotmat_from_euler(0.4, -0.3, 2.0) @ LEVEL,
}


@pytest.mark.parametrize("name", sorted(VIEWS))
def test_values_and_gradients_match_the_definition(name):
    view = _view(VIEWS[name])
    inputs = _inputs(view, seed=len(name))
    upstream = torch.randn(view.height, view.width, 3, generator=torch.Generator().manual_seed(9))
    fused, fused_grads = _run(with_backdrop, view, inputs, upstream)
    want, want_grads = _run(backdrop_reference, view, inputs, upstream)
    assert torch.allclose(fused, want, atol=2e-5), float((fused - want).abs().max())
    for label, a, b in zip(("colour", "alpha", "texture", "affine"), fused_grads, want_grads):
        assert bool(torch.isfinite(a).all()), label
        scale = float(b.abs().max())
        assert scale > 0.0, label
        assert torch.allclose(a, b, rtol=1e-4, atol=2e-5 * scale), (label, float((a - b).abs().max()), scale)


def test_without_an_affine_it_is_the_sky_composite_alone():
    view = _view(VIEWS["tilted"])
    colour, alpha, texture, _ = _inputs(view, seed=3)
    upstream = torch.ones(view.height, view.width, 3)
    fused, grads = _run(with_backdrop, view, (colour, alpha, texture, torch.zeros(3, 4)), upstream, with_affine=False)
    want, want_grads = _run(backdrop_reference, view, (colour, alpha, texture, torch.zeros(3, 4)), upstream,
                            with_affine=False)
    assert torch.allclose(fused, want, atol=2e-5)
    assert grads[3] is None and want_grads[3] is None
    assert torch.allclose(grads[2], want_grads[2], atol=1e-4)
    # where alpha is 1 the colour is the Gaussians' own; where it is 0 it is colour + sky
    assert torch.allclose(fused[-3:], colour[-3:], atol=1e-6)


def test_thread_count_does_not_change_any_result():
    view = _view(VIEWS["tilted"], width=97, height=61)
    inputs = _inputs(view, seed=5)
    upstream = torch.randn(view.height, view.width, 3, generator=torch.Generator().manual_seed(2))
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = _run(with_backdrop, view, inputs, upstream)
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = _run(with_backdrop, view, inputs, upstream)
    finally:
        numba.set_num_threads(before)
    assert torch.equal(one[0], two[0])
    assert all(torch.equal(a, b) for a, b in zip(one[1], two[1]))


def test_extreme_inputs_stay_finite():
    view = _view(VIEWS["up"])
    colour, alpha, texture, affine = _inputs(view, seed=7)
    texture = torch.full_like(texture, 80.0)  # sigmoid saturates at 1
    texture[1] = -80.0                           # and at 0
    colour = colour * 1e4
    upstream = torch.full((view.height, view.width, 3), 1e3)
    rgb, grads = _run(with_backdrop, view, (colour, alpha, texture, affine), upstream)
    assert bool(torch.isfinite(rgb).all()) and all(bool(torch.isfinite(g).all()) for g in grads)
