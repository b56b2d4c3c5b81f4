"""``rasterize``: gsplat's ``rasterization`` signature, input checks, render modes, backend dispatch."""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from omniscs.errors import OmniscsError
from omniscs.render.cpu import project_cpu, rasterize_cpu
from omniscs.render.gsplat_backend import rasterize_gsplat
from omniscs.render.projection import project_gaussians
from omniscs.render.reference import rasterize_reference
from omniscs.render.sh import MAX_SH_DEGREE, colors_from_sh_at_cameras, num_sh_bases

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
BACKENDS = ("auto", "reference", "cpu", "gsplat")

#: Where accumulated alpha is at most this, expected depth ("ED") is reported as 0 instead of D / alpha.
MIN_ALPHA_FOR_EXPECTED_DEPTH = 1e-10

_FLOAT_DTYPES = (torch.float32, torch.float64)


def rasterize(
    means: Tensor,      # [N, 3] world
    quats: Tensor,      # [N, 4] (w, x, y, z), need not be normalised
    scales: Tensor,     # [N, 3] activated (positive) scales, metres
    opacities: Tensor,  # [N] in [0, 1]
    colors: Tensor,     # [N, D] or [C, N, D] features; or [N, K, 3] SH coefficients with sh_degree
    viewmats: Tensor,   # [C, 4, 4] cam_from_world (OpenCV camera)
    Ks: Tensor,         # [C, 3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    backgrounds: Tensor | None = None,  # [C, D] for the colour channels (depth channels get 0)
    render_mode: str = "RGB",
    backend: str = "auto",
    rasterize_mode: str = "classic",
    absgrad: bool = False,
) -> tuple[Tensor, Tensor, dict[str, Any]]:  # colors [C, H, W, D(+1)], alphas [C, H, W, 1], meta
    """Render Gaussians into C cameras, as ``gsplat.rasterization`` does.

    render_mode: "RGB" colours; "D" accumulated depth sum(w_i z_i); "ED" that divided by alpha
    (0 where alpha is 0); "RGB+D"/"RGB+ED" append the depth channel to the colours.
    backend: "reference" (dense PyTorch oracle, any dtype/device, differentiable in everything),
    "cpu" (Numba kernels: projection in float64, 16x16-tile compositing with float32 storage; no
    gradient for viewmats/Ks), "gsplat" (CUDA), "auto" (gsplat for CUDA tensors, else cpu).
    rasterize_mode: "classic" adds eps2d to the 2D covariance; "antialiased" also scales opacity by
    sqrt(det(Sigma2d) / det(Sigma2d + eps2d I)) (Mip-Splatting).
    meta: means2d [C, N, 2] (call ``meta["means2d"].retain_grad()`` before backward for its
    gradient; cpu and gsplat fill ``.absgrad`` when absgrad=True), radii [C, N, 2] int32 (0 =
    culled), depths [C, N], conics [C, N, 3], opacities [C, N], backend, width, height.
    Outputs have the dtype of ``means``.
    """
    chosen = _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                           far_plane, eps2d, sh_degree, backgrounds, render_mode, backend, rasterize_mode, absgrad)
    dtype = means.dtype
    cameras = (viewmats, Ks)  # the cpu backend projects in float64 from the cameras as given
    viewmats, Ks = viewmats.to(dtype), Ks.to(dtype)
    backgrounds = None if backgrounds is None else backgrounds.to(dtype)
    antialiased = rasterize_mode == "antialiased"
    if chosen == "gsplat":
        return rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height,
            near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
            backgrounds=backgrounds, render_mode=render_mode, antialiased=antialiased, absgrad=absgrad,
        )

    if chosen == "cpu":
        screen, sort_depths = project_cpu(means, quats, scales, opacities, *cameras, width, height,
                                          near_plane, far_plane, eps2d, antialiased)
    else:
        screen = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height,
                                   near_plane, far_plane, eps2d, antialiased)
    n_cameras = viewmats.shape[0]
    if sh_degree is not None:
        features = colors_from_sh_at_cameras(sh_degree, colors, means, viewmats)
    elif colors.dim() == 2:
        features = colors[None].expand(n_cameras, -1, -1)
    else:
        features = colors
    depth_channel = screen.depths[..., None]
    if render_mode in ("D", "ED"):
        features = depth_channel
    elif render_mode in ("RGB+D", "RGB+ED"):
        features = torch.cat([features, depth_channel], -1)

    if backgrounds is None:
        backgrounds = features.new_zeros(n_cameras, features.shape[-1])
    elif render_mode in ("RGB+D", "RGB+ED"):
        backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(n_cameras, 1)], -1)
    if chosen == "cpu":
        render_colors, render_alphas = rasterize_cpu(screen, features, backgrounds, width, height, absgrad,
                                                     sort_depths)
    else:
        render_colors, render_alphas = rasterize_reference(screen, features, backgrounds, width, height)
    if render_mode in ("ED", "RGB+ED"):
        covered = render_alphas > MIN_ALPHA_FOR_EXPECTED_DEPTH
        safe_alphas = torch.where(covered, render_alphas, torch.ones_like(render_alphas))
        expected = torch.where(covered, render_colors[..., -1:] / safe_alphas, torch.zeros_like(safe_alphas))
        render_colors = torch.cat([render_colors[..., :-1], expected], -1)

    meta = {
        "means2d": screen.means2d, "radii": screen.radii, "depths": screen.depths, "conics": screen.conics,
        "opacities": screen.opacities, "backend": chosen, "width": width, "height": height,
    }
    return render_colors, render_alphas, meta


def _fail(message: str) -> None:
    raise OmniscsError(message)


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
                  eps2d, sh_degree, backgrounds, render_mode, backend, rasterize_mode, absgrad) -> str:
    """Raise OmniscsError naming the first wrong argument; return the backend that will run."""
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
             "viewmats": viewmats, "Ks": Ks}
    if backgrounds is not None:
        named["backgrounds"] = backgrounds
    for name, value in named.items():
        if not isinstance(value, Tensor):
            _fail(f"rasterize: {name} must be a torch.Tensor, got {type(value).__name__}")
        if value.dtype not in _FLOAT_DTYPES:
            _fail(f"rasterize: {name} must be float32 or float64, got {value.dtype}")
        if value.device != means.device:
            _fail(f"rasterize: {name} is on {value.device} but means is on {means.device}; put all inputs on one device")
    for name in ("quats", "scales", "opacities", "colors"):
        if named[name].dtype != means.dtype:
            _fail(f"rasterize: {name} is {named[name].dtype} but means is {means.dtype}; use one dtype for Gaussians")
    if means.dim() != 2 or means.shape[1] != 3:
        _fail(f"rasterize: means must be [N, 3], got {list(means.shape)}")
    n = means.shape[0]
    for name, shape in (("quats", (n, 4)), ("scales", (n, 3)), ("opacities", (n,))):
        if tuple(named[name].shape) != shape:
            _fail(f"rasterize: {name} must be {list(shape)} for N={n} Gaussians, got {list(named[name].shape)}")
    if viewmats.dim() != 3 or tuple(viewmats.shape[1:]) != (4, 4) or viewmats.shape[0] == 0:
        _fail(f"rasterize: viewmats must be [C, 4, 4] with C >= 1, got {list(viewmats.shape)}")
    n_cameras = viewmats.shape[0]
    if tuple(Ks.shape) != (n_cameras, 3, 3):
        _fail(f"rasterize: Ks must be [{n_cameras}, 3, 3] to match viewmats, got {list(Ks.shape)}")
    if sh_degree is not None:
        if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= MAX_SH_DEGREE:
            _fail(f"rasterize: sh_degree must be an int in 0..{MAX_SH_DEGREE} or None, got {sh_degree!r}")
        bases = num_sh_bases(sh_degree)
        if colors.dim() != 3 or colors.shape[0] != n or colors.shape[1] < bases or colors.shape[2] != 3:
            _fail(f"rasterize: with sh_degree={sh_degree} colors must be [N={n}, K>={bases}, 3], "
                  f"got {list(colors.shape)}")
        n_channels = 3
    else:
        if not ((colors.dim() == 2 and colors.shape[0] == n) or
                (colors.dim() == 3 and tuple(colors.shape[:2]) == (n_cameras, n))):
            _fail(f"rasterize: colors must be [N={n}, D] or [C={n_cameras}, N={n}, D] (or SH coefficients "
                  f"[N, K, 3] with sh_degree), got {list(colors.shape)}")
        n_channels = colors.shape[-1]
        if n_channels == 0:
            _fail("rasterize: colors need at least one channel")
    for name, size in (("width", width), ("height", height)):
        if isinstance(size, bool) or not isinstance(size, int) or size <= 0:
            _fail(f"rasterize: {name} must be a positive int, got {size!r}")
    if not 0.0 < near_plane < far_plane:
        _fail(f"rasterize: need 0 < near_plane < far_plane, got near_plane={near_plane}, far_plane={far_plane}")
    if not eps2d >= 0.0:
        _fail(f"rasterize: eps2d must be >= 0, got {eps2d}")
    if render_mode not in RENDER_MODES:
        _fail(f"rasterize: render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        _fail(f"rasterize: rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")
    if backgrounds is not None:
        if render_mode in ("D", "ED"):
            _fail(f"rasterize: backgrounds colour the RGB channels; render_mode {render_mode!r} has none, pass None")
        if tuple(backgrounds.shape) != (n_cameras, n_channels):
            _fail(f"rasterize: backgrounds must be [C={n_cameras}, D={n_channels}], got {list(backgrounds.shape)}")
    if backend not in BACKENDS:
        _fail(f"rasterize: backend must be one of {BACKENDS}, got {backend!r}")
    chosen = ("gsplat" if means.is_cuda else "cpu") if backend == "auto" else backend
    if chosen == "cpu" and means.device.type != "cpu":
        _fail(f"rasterize: backend 'cpu' needs CPU tensors, got {means.device}; use backend='gsplat' or move them")
    if chosen == "cpu" and (viewmats.requires_grad or Ks.requires_grad):
        _fail("rasterize: backend 'cpu' does not differentiate viewmats or Ks; detach them or use backend='reference'")
    if absgrad and chosen == "reference":
        _fail("rasterize: absgrad needs backend 'cpu' or 'gsplat' (the reference has no per-pixel gradient sums)")
    return chosen
