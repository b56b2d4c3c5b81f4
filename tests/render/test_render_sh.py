"""Spherical-harmonic colour has one home (omniscs.render.sh): the scene graph and the rasterizer agree, both
earlier formulations are reproduced, and a zero-length viewing direction gives finite colours and gradients."""
import math

import pytest
import torch

from omniscs.render import rasterize
from omniscs.render.sh import (SH_C0, colors_from_sh, colors_from_sh_at_cameras, num_sh_bases, rgb_to_sh_dc,
                               unit_directions)

F64 = torch.float64


def gsplat_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:  # [..., 3] unit -> [..., B]
    """gsplat's CUDA kernel form of the real SH basis (its constants, written as it writes them): the form
    the rasterizer used before SH had one home."""
    x, y, z = dirs.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    out = [torch.full_like(x, 0.2820947917738781), -0.48860251190292 * y, 0.4886025119029199 * z,
           -0.4886025119029199 * x]
    if degree >= 2:
        out += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.9461746957575601 * zz - 0.3153915652525201,
                -1.0925484305920792 * x * z, 0.5462742152960395 * (xx - yy)]
    if degree >= 3:
        radial = -2.285228997322329 * zz + 0.4570457994644658
        out += [-0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * x * y * z, radial * y,
                z * (1.865881662950577 * zz - 1.119528997770346), radial * x, 1.445305721320277 * z * (xx - yy),
                -0.5900435899266435 * x * (xx - 3 * yy)]
    return torch.stack(out[:num_sh_bases(degree)], -1)


def random_sh(n: int, k: int = 16, seed: int = 0, dtype=F64) -> torch.Tensor:
    return 0.4 * torch.randn(n, k, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def random_dirs(c: int, n: int, seed: int = 1, dtype=F64) -> torch.Tensor:
    return 3.0 * torch.randn(c, n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_colours_match_gsplats_formulation_for_ordinary_directions(degree):
    coeffs, dirs = random_sh(40), random_dirs(2, 40)
    unit = dirs / dirs.norm(dim=-1, keepdim=True)
    basis = gsplat_basis(degree, unit)
    expected = ((basis[..., None] * coeffs[None, :, :num_sh_bases(degree)]).sum(-2) + 0.5).clamp_min(0.0)
    torch.testing.assert_close(colors_from_sh(degree, coeffs, dirs), expected, atol=1e-12, rtol=0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_colours_match_the_scene_graphs_formulation_bit_for_bit(degree):
    """The scene graph fitted with the 3DGS polynomial form and an einsum; fits must not move by one ulp."""
    coeffs, dirs = random_sh(40, dtype=torch.float32), random_dirs(1, 40, dtype=torch.float32)
    if degree == 0:
        expected = (SH_C0 * coeffs[None, :, 0] + 0.5).clamp_min(0.0)
    else:
        x, y, z = (dirs / dirs.norm(dim=-1, keepdim=True)).unbind(-1)
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        c1 = 0.4886025119029199
        b = [torch.full_like(x, SH_C0), -c1 * y, c1 * z, -c1 * x]
        b += [1.0925484305920792 * xy, -1.0925484305920792 * yz, 0.31539156525252005 * (2 * zz - xx - yy),
              -1.0925484305920792 * xz, 0.5462742152960396 * (xx - yy)]
        b += [-0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * xy * z,
              -0.4570457994644658 * y * (4 * zz - xx - yy), 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
              -0.4570457994644658 * x * (4 * zz - xx - yy), 1.445305721320277 * z * (xx - yy),
              -0.5900435899266435 * x * (xx - 3 * yy)]
        bases = num_sh_bases(degree)
        basis = torch.stack(b[:bases], -1)
        expected = (torch.einsum("cnb,nbk->cnk", basis, coeffs[:, :bases]) + 0.5).clamp_min(0.0)
    assert torch.equal(colors_from_sh(degree, coeffs, dirs), expected)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_length_direction_gives_finite_colours_and_gradients(degree, dtype):
    coeffs = random_sh(3, dtype=dtype).requires_grad_(True)
    dirs = torch.tensor([[[0.0, 0.0, 0.0], [1e-30, 0.0, 0.0], [0.0, 0.0, 2.5]]], dtype=dtype, requires_grad=True)
    colours = colors_from_sh(degree, coeffs, dirs)
    assert torch.isfinite(colours).all()
    colours.sum().backward()
    assert torch.isfinite(coeffs.grad).all()
    if degree > 0:  # degree 0 is view-independent: the directions get no gradient at all
        assert torch.isfinite(dirs.grad).all()
        assert torch.equal(dirs.grad[0, :2], torch.zeros(2, 3, dtype=dtype))  # no direction, nothing to learn
    # a zero direction is read as +z: the colour is the one seen looking along +z
    along_z = colors_from_sh(degree, coeffs.detach(), torch.tensor([[[0.0, 0.0, 1.0]] * 3], dtype=dtype))
    torch.testing.assert_close(colours[0, :2].detach(), along_z[0, :2])


def test_unit_directions_are_unit_and_zero_reads_as_plus_z():
    dirs = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [1e4, -1e4, 0.0]], dtype=F64)  # 10 km away
    unit = unit_directions(dirs)
    assert torch.isfinite(unit).all()
    torch.testing.assert_close(unit, torch.tensor([[0.6, 0.8, 0.0], [0.0, 0.0, 1.0],
                                                   [1 / math.sqrt(2), -1 / math.sqrt(2), 0.0]], dtype=F64))


def test_rasterizer_sh_colours_are_the_scene_graphs_colours_seen_from_the_camera_centre():
    coeffs = random_sh(25)
    means = torch.randn(25, 3, generator=torch.Generator().manual_seed(2), dtype=F64) + torch.tensor([0.0, 0.0, 6.0],
                                                                                                   dtype=F64)
    angle = 0.4
    R = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0],
                      [-math.sin(angle), 0.0, math.cos(angle)]], dtype=F64)
    centre = torch.tensor([0.5, -0.2, 1.0], dtype=F64)
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3], viewmat[:3, 3] = R.T, -R.T @ centre  # cam_from_world of a camera at ``centre``
    at_cameras = colors_from_sh_at_cameras(3, coeffs, means, viewmat[None])
    torch.testing.assert_close(at_cameras, colors_from_sh(3, coeffs, (means - centre)[None]), atol=1e-12, rtol=0)


def test_rasterize_with_sh_degree_equals_rasterize_with_the_evaluated_colours():
    means = torch.tensor([[0.0, 0.0, 4.0], [0.3, -0.2, 5.0]], dtype=F64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=F64)
    scales = torch.full((2, 3), 0.3, dtype=F64)
    opacities = torch.tensor([0.7, 0.9], dtype=F64)
    coeffs = random_sh(2)
    viewmats = torch.eye(4, dtype=F64)[None]
    Ks = torch.tensor([[[20.0, 0.0, 8.0], [0.0, 20.0, 8.0], [0.0, 0.0, 1.0]]], dtype=F64)
    with_sh, _, _ = rasterize(means, quats, scales, opacities, coeffs, viewmats, Ks, 16, 16, sh_degree=2,
                              backend="reference")
    colours = colors_from_sh_at_cameras(2, coeffs, means, viewmats)
    direct, _, _ = rasterize(means, quats, scales, opacities, colours, viewmats, Ks, 16, 16, backend="reference")
    assert torch.equal(with_sh, direct)


def test_rgb_to_sh_dc_inverts_the_degree_zero_colour():
    rgb = torch.rand(10, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    dc = rgb_to_sh_dc(rgb)
    coeffs = torch.cat([dc[:, None], torch.zeros(10, 15, 3, dtype=F64)], 1)
    for degree in (0, 3):
        torch.testing.assert_close(colors_from_sh(degree, coeffs, random_dirs(1, 10))[0], rgb, atol=1e-12, rtol=0)
