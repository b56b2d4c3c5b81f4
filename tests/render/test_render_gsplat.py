"""The gsplat backend: parity with the CPU backend on CUDA, a clear error everywhere else."""
from __future__ import annotations

import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.render import rasterize
from omniscs.render.gsplat_backend import gsplat_available
from omniscs.render.scenes import StreetScene, random_scene

HAS_CUDA_GSPLAT = torch.cuda.is_available() and gsplat_available()


def test_gsplat_backend_on_cpu_tensors_raises_a_clear_error():
    s = random_scene(10, 16, 12, dtype=torch.float32)
    with pytest.raises(OmniscsError, match="CUDA"):
        rasterize(**s.as_kwargs(), backend="gsplat")


@pytest.mark.skipif(not HAS_CUDA_GSPLAT, reason="needs a CUDA device and the gsplat package")
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
def test_gsplat_matches_cpu_backend(render_mode):
    s = random_scene(2000, 128, 96, n_cameras=2, seed=21, dtype=torch.float32)
    cuda = StreetScene(**{k: getattr(s, k).cuda() for k in ("means", "quats", "scales", "opacities", "colors",
                                                             "viewmats", "Ks")}, width=s.width, height=s.height)
    gs_colors, gs_alphas, gs_meta = rasterize(**cuda.as_kwargs(), render_mode=render_mode)  # auto -> gsplat
    assert gs_meta["backend"] == "gsplat"
    cpu_colors, cpu_alphas, _ = rasterize(**s.as_kwargs(), render_mode=render_mode, backend="cpu")
    error = (gs_colors.cpu()[..., :3] - cpu_colors[..., :3]).abs()
    assert error.mean().item() < 1e-3 and (gs_alphas.cpu() - cpu_alphas).abs().mean().item() < 1e-3


@pytest.mark.skipif(not HAS_CUDA_GSPLAT, reason="needs a CUDA device and the gsplat package")
def test_gsplat_gradients_match_cpu_backend():
    """The same loss differentiated through gsplat's kernels and through ours: the gradients agree (the fit trains
    through either backend)."""
    s = random_scene(1500, 96, 72, n_cameras=2, seed=22, dtype=torch.float32)
    target = torch.rand(2, 72, 96, 3, generator=torch.Generator().manual_seed(5))
    names = ("means", "quats", "scales", "opacities", "colors")
    grads = {}
    for device, backend in (("cuda", "gsplat"), ("cpu", "cpu")):
        leaves = {k: getattr(s, k).to(device).clone().requires_grad_(True) for k in names}
        colors, alphas, _ = rasterize(**leaves, viewmats=s.viewmats.to(device), Ks=s.Ks.to(device), width=s.width,
                                      height=s.height, backend=backend)
        loss = ((colors[..., :3] - target.to(device)) ** 2).mean() + alphas.mean()
        loss.backward()
        grads[backend] = {k: leaves[k].grad.detach().cpu() for k in names}
    for k in names:
        g, c = grads["gsplat"][k], grads["cpu"][k]
        assert torch.isfinite(g).all() and torch.isfinite(c).all()
        rel = (g - c).norm() / c.norm().clamp(min=1e-12)
        assert rel.item() < 2e-2, f"{k}: relative gradient difference {rel.item():.3g}"
