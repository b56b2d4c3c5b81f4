"""gsplat backend: hands the call to ``gsplat.rasterization`` for CUDA tensors (gsplat imported lazily)."""
from __future__ import annotations

from typing import Any

from torch import Tensor

from omniscs.errors import OmniscsError


def gsplat_available() -> bool:
    """True when gsplat imports (it still needs CUDA tensors to run)."""
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def rasterize_gsplat(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmats: Tensor, Ks: Tensor, width: int, height: int, *,
    near_plane: float, far_plane: float, eps2d: float, sh_degree: int | None,
    backgrounds: Tensor | None, render_mode: str, antialiased: bool, absgrad: bool,
) -> tuple[Tensor, Tensor, dict[str, Any]]:  # colors [C, H, W, D(+1)], alphas [C, H, W, 1], meta
    """gsplat's own rasteriser (non-packed, 16-pixel tiles); meta keeps gsplat's full dict under "gsplat"."""
    if not means.is_cuda:
        raise OmniscsError("backend 'gsplat' needs CUDA tensors; move them to a GPU or use backend='cpu'")
    try:
        from gsplat import rasterization
    except ImportError as err:
        raise OmniscsError(
            f"backend 'gsplat' needs the gsplat package ({err}); install it (pip install gsplat) "
            "or use backend='cpu'"
        ) from err
    render_colors, render_alphas, meta = rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
        backgrounds=backgrounds, render_mode=render_mode, packed=False, tile_size=16,
        rasterize_mode="antialiased" if antialiased else "classic", absgrad=absgrad,
    )
    ours = {key: meta[key] for key in ("means2d", "radii", "depths", "conics", "opacities") if key in meta}
    ours.update(backend="gsplat", width=width, height=height, gsplat=meta)
    return render_colors, render_alphas, ours
