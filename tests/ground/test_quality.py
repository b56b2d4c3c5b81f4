"""One PSNR / SSIM: the same figures as the formulas it replaced on ordinary images, and one rule for the edge
cases (identical images, empty masks, 8-bit images, extremes)."""
import math

import numpy as np
import pytest
import torch
from kornia.metrics import ssim as kornia_ssim

from omniscs.errors import OmniscsError
from omniscs.quality import MAX_PSNR_DB, UINT8_RANGE, psnr, psnr_from_mse, ssim, ssim_loss, ssim_map


def _images(seed: int, shape=(24, 32, 3)):
    rng = np.random.default_rng(seed)
    target = rng.random(shape, dtype=np.float32)
    rendered = np.clip(target + rng.normal(0, 0.1, shape).astype(np.float32), -0.2, 1.2)  # leaves [0, 1]
    mask = rng.random(shape[:-1]) < 0.4
    return rendered, target, mask


# The formulas the library held before it had one home, written out as they were, to check the figures.
def _old_nsg_psnr(rendered, target, mask=None):  # omniscs/nsg/metrics.py
    err = (rendered.clamp(0, 1) - target).pow(2).mean(-1)
    if mask is not None:
        err = err[mask]
    mse = float(err.mean())
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def _old_mesh_view_psnr(got, rgb, mask):  # omniscs/agents/mesh.py view_psnr (renders already in [0, 1])
    err = ((got - torch.as_tensor(rgb, dtype=torch.float32)) ** 2).mean(-1)[mask]
    return float(10 * torch.log10(1.0 / err.mean().clamp_min(1e-10)))


def _old_masked_psnr(r, g, m):  # omniscs/scs/behavior/appearance.py masked_psnr (float64 frames in [0, 1])
    return float(10.0 * np.log10(1.0 / max(float(((r - g) ** 2)[m].mean()), 1e-12)))


def _old_heldout_psnr(views):  # omniscs/agents/dual.py heldout_psnr: pooled over views
    errors = sum(float(((np.clip(r[m], 0, 1) - g[m]) ** 2).sum()) for r, g, m in views)
    weights = sum(3.0 * m.sum() for _, _, m in views)
    return float(10.0 * np.log10(1.0 / max(errors / weights, 1e-10)))


@pytest.mark.parametrize("seed", range(5))
def test_psnr_gives_the_old_figures_on_ordinary_images(seed):
    rendered, target, mask = _images(seed)
    r, g, m = torch.from_numpy(rendered), torch.from_numpy(target), torch.from_numpy(mask)
    assert psnr(r, g) == _old_nsg_psnr(r, g)
    assert psnr(r, g, m) == _old_nsg_psnr(r, g, m)
    inside = r.clamp(0, 1)  # the agent renders were drawn with clamped colours
    assert psnr(inside, g, m) == pytest.approx(_old_mesh_view_psnr(inside, target, m), abs=1e-4)
    r64, g64 = np.clip(rendered, 0, 1).astype(np.float64), target.astype(np.float64)
    assert psnr(r64, g64, mask) == pytest.approx(_old_masked_psnr(r64, g64, mask), abs=1e-12)
    views = [(r64, g64, mask), (r64[::-1].copy(), g64, ~mask)]
    pooled = sum(float(((x[k] - y[k]) ** 2).sum()) for x, y, k in views) / sum(3.0 * k.sum() for *_, k in views)
    assert psnr_from_mse(pooled) == pytest.approx(_old_heldout_psnr(views), abs=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_ssim_gives_the_old_figures_on_ordinary_images(seed):
    rendered, target, mask = _images(seed)
    r, g = torch.from_numpy(rendered), torch.from_numpy(target)
    chw = lambda x: x.permute(2, 0, 1)[None].to(torch.float32)  # noqa: E731
    old_map = kornia_ssim(chw(r.clamp(0, 1)), chw(g), 11)[0].mean(0)
    assert torch.equal(ssim_map(r, g), old_map)
    assert ssim(r, g) == float(old_map.mean())
    assert ssim(r, g, torch.from_numpy(mask)) == float(old_map[torch.from_numpy(mask)].mean())


def test_identical_images_score_the_finite_cap_not_infinity():
    _, target, mask = _images(0)
    assert psnr(target, target) == MAX_PSNR_DB
    assert psnr(target, target, mask) == MAX_PSNR_DB
    assert psnr(target, target + 1e-7) == MAX_PSNR_DB  # within the cap's error floor
    assert ssim(target, target) == pytest.approx(1.0)


def test_an_empty_mask_scores_none_and_an_all_true_mask_scores_the_whole_image():
    rendered, target, _ = _images(1)
    empty = np.zeros(target.shape[:-1], bool)
    assert psnr(rendered, target, empty) is None and ssim(rendered, target, empty) is None
    full = np.ones(target.shape[:-1], bool)
    assert psnr(rendered, target, full) == psnr(rendered, target)
    assert ssim(rendered, target, full) == pytest.approx(ssim(rendered, target))


def test_8_bit_images_on_their_own_scale_score_as_the_same_images_in_0_1():
    rendered, target, mask = _images(2)
    r8 = (np.clip(rendered, 0, 1) * 255).round().astype(np.uint8)
    g8 = (target * 255).round().astype(np.uint8)
    as_float = psnr(r8.astype(np.float64) / 255.0, g8.astype(np.float64) / 255.0, mask)
    assert psnr(r8, g8, mask, data_range=UINT8_RANGE) == pytest.approx(as_float, abs=1e-9)
    assert psnr(g8, g8, data_range=UINT8_RANGE) == MAX_PSNR_DB
    assert ssim(r8, g8, data_range=UINT8_RANGE) == pytest.approx(
        ssim(r8.astype(np.float32) / 255.0, g8.astype(np.float32) / 255.0), abs=1e-5)


def test_psnr_stays_finite_at_the_extremes_and_refuses_non_finite_pixels():
    black, white = np.zeros((8, 8, 3)), np.ones((8, 8, 3))
    assert psnr(black, white) == 0.0 and psnr(white * 1e6, black) == 0.0  # the render is clipped to the range
    assert np.isfinite(psnr(black, white * 1e3))  # a reference far outside the range: a large error, not Inf
    with pytest.raises(OmniscsError, match="NaN or Inf"):
        psnr(black, np.full((8, 8, 3), np.nan))
    with pytest.raises(OmniscsError, match="differ in shape"):
        psnr(black, np.zeros((8, 9, 3)))
    with pytest.raises(OmniscsError, match="mask"):
        psnr(black, white, np.ones((8, 9), bool))


@pytest.mark.parametrize("size, window, dtype", [((68, 120), 11, torch.float32), ((135, 240), 11, torch.float32),
                                                 ((7, 9), 5, torch.float32), ((3, 5), 3, torch.float64),
                                                 ((40, 30), 11, torch.float64)])
def test_the_fits_ssim_loss_is_kornias_value_and_gradient(size, window, dtype):
    from kornia.losses import ssim_loss as kornia_ssim_loss

    g = torch.Generator().manual_seed(sum(size))
    rendered = torch.rand(1, 3, *size, generator=g, dtype=dtype)
    target = (0.7 * rendered + 0.3 * torch.rand(1, 3, *size, generator=g, dtype=dtype)).clamp(0, 1)
    ours_in, theirs_in = rendered.clone().requires_grad_(True), rendered.clone().requires_grad_(True)
    ours, theirs = ssim_loss(ours_in, target, window), kornia_ssim_loss(theirs_in, target, window)
    ours.backward()
    theirs.backward()
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert abs(ours.item() - theirs.item()) <= tol
    scale = theirs_in.grad.abs().max().item()
    assert scale > 0 and (ours_in.grad - theirs_in.grad).abs().max().item() <= tol * scale * 10


def test_the_ssim_loss_of_identical_flat_black_images_is_zero_not_nan_and_even_windows_are_refused():
    black = torch.zeros(1, 3, 16, 16, requires_grad=True)
    loss = ssim_loss(black, torch.zeros(1, 3, 16, 16), 11)
    loss.backward()
    # SSIM_EPS in the denominator leaves 1e-12 / (c1 c2) / 2 = 5.6e-6 for flat black images, as kornia does
    assert loss.item() == pytest.approx(1e-12 / (1e-4 * 9e-4) / 2, rel=1e-2) and torch.isfinite(black.grad).all()
    with pytest.raises(OmniscsError, match="odd"):
        ssim_loss(black, black.detach(), 4)


@pytest.mark.parametrize("size, window", [((68, 120), 11), ((6, 6), 11), ((9, 7), 5), ((1, 3), 1)])
def test_the_fused_cpu_ssim_loss_is_its_float64_definition_in_value_and_gradient(size, window):
    from omniscs.quality import _ssim_loss_torch

    g = torch.Generator().manual_seed(7)
    rendered = torch.rand(1, 3, *size, generator=g) * 1.4 - 0.2  # a render may leave [0, 1]
    target = torch.rand(1, 3, *size, generator=g)
    rendered[0, 1] = 0.0  # a flat black plane against a flat black target
    target[0, 1] = 0.0
    fused_in = rendered.clone().requires_grad_(True)
    reference_in = rendered.double().requires_grad_(True)
    fused = ssim_loss(fused_in, target, window)
    reference = _ssim_loss_torch(reference_in, target.double(), window)
    fused.backward()
    reference.backward()
    assert fused.dtype == torch.float32 and bool(torch.isfinite(fused_in.grad).all())
    assert abs(fused.item() - reference.item()) <= 1e-7
    scale = reference_in.grad.abs().max().item()
    assert scale > 0 and (fused_in.grad.double() - reference_in.grad).abs().max().item() <= 1e-5 * scale
