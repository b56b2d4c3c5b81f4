"""Pool models made relightable in a scene (``omniscs.nsg.relight``): their albedo and normals, and the scene's light
fitted to what the cameras saw of the track.

- Normals: each Gaussian's thinnest axis (pool models from meshes are flat Gaussians lying in the surface), turned
  to point away from the box centre. Round Gaussians have no such axis; they take the direction from the centre.
- Albedo: the model's colours with the light they were made under taken off. Models built from meshes carry the
  build's fixed light (``omniscs.agents.mesh.shade``: ambient plus one direction, two-sided), so their linear
  colour is divided by it; other models (imported splats, scene tracks) count as evenly lit.
- Light: ``fit_lighting`` renders the model alone in the track's node at the logged poses and fits the light's
  coefficients (Adam, L1) to the logged pixels the fitted track covers, as ``dual.refine_colours`` fits colours.
"""
from __future__ import annotations

import numpy as np
import torch

from omniscs.agents.mesh import AMBIENT, LIGHT_DIRECTION
from omniscs.gaussians import GaussianParams
from omniscs.nsg.graph import SceneGraph, render_view
from omniscs.nsg.relight import Relight, flat_lighting, srgb_decode
from omniscs.quaternions import normalize_quats, quat_to_rotmat
from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET

#: A Gaussian counts as flat (its thinnest axis is the surface normal) when its thinnest scale is below this share
#: of its middle one.
FLAT_RATIO = 0.5
#: Weight of the pull of the light's direction and additive terms towards none (per step, on the L1 loss).
LIGHT_RIDGE = 0.01


def outward_normals(params: GaussianParams) -> torch.Tensor:
    """[N, 3] unit normals in the model frame (see the module docstring)."""
    means = params.means.detach()
    R = torch.as_tensor(quat_to_rotmat(normalize_quats(params.quats.detach().double().cpu().numpy())),
                        dtype=means.dtype, device=means.device)
    scales = params.log_scales.detach()
    order = scales.argsort(1)
    thin = R[torch.arange(len(means), device=means.device), :, order[:, 0]]
    flat = (scales.gather(1, order[:, :1]) - scales.gather(1, order[:, 1:2]))[:, 0] < float(np.log(FLAT_RATIO))
    radial = means / means.norm(dim=1, keepdim=True).clamp_min(1e-9)
    radial[means.norm(dim=1) < 1e-9] = torch.tensor([0.0, 0.0, 1.0], dtype=means.dtype, device=means.device)
    side = torch.sign((thin * means).sum(1, keepdim=True))
    side[side == 0] = 1.0
    n = torch.where(flat[:, None], thin * side, radial)
    return n / n.norm(dim=1, keepdim=True).clamp_min(1e-9)


def model_albedo(params: GaussianParams, normals: torch.Tensor, mesh_light: bool,
                 scale: np.ndarray | None = None) -> torch.Tensor:
    """[N, 3] linear albedo: the model's colours (view-independent band) with the mesh build's light taken off when
    ``mesh_light``. ``scale``: per-axis stretch from the model's own box to the one ``params`` fill (normals and the
    build's light direction are turned by the inverse stretch)."""
    colour = (SH_COLOR_OFFSET + SH_C0 * params.sh_dc.detach()).clamp(0.0, 1.0)
    linear = srgb_decode(colour)
    if not mesh_light:
        return linear
    light = LIGHT_DIRECTION / (np.ones(3) if scale is None else np.asarray(scale, dtype=np.float64))
    light = torch.as_tensor(light / np.linalg.norm(light), dtype=normals.dtype, device=normals.device)
    shading = AMBIENT + (1.0 - AMBIENT) * (normals @ light).abs()
    return (linear / shading[:, None]).clamp(0.0, 1.0)


def relight_base(params: GaussianParams, mesh_light: bool, scale: np.ndarray | None = None) -> Relight:
    """The model's albedo and normals under an even light (``fit_lighting`` fits the scene's)."""
    normals = outward_normals(params)
    albedo = model_albedo(params, normals, mesh_light, scale)
    return Relight(albedo, normals, flat_lighting(dtype=normals.dtype).to(normals.device))


def fit_lighting(graph: SceneGraph, track_id: int, candidate: GaussianParams, relight: Relight,
                 samples: list[tuple], steps: int = 200, lr: float = 0.03) -> tuple[Relight, dict]:
    """``relight`` with the light fitted so that ``candidate`` (in the track's node, alone) looks like the logged
    images (``dual.colour_samples``); returns it and {loss_first, loss_last, views}. With no usable view, or a fit
    that does not stay finite, the even light comes back unchanged."""
    from omniscs.agents.dual import _alone, shared_masks

    node = graph.agent(track_id).with_changes(gaussians=candidate, relight=relight)
    alone = _alone(graph, track_id, candidate).replace(agents=(node,))
    masked = shared_masks(alone, samples)
    info = {"views": len(masked), "loss_first": None, "loss_last": None}
    if not masked or steps <= 0:
        return relight, info
    light = relight.lighting.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([light], lr=lr)
    for step in range(steps):
        view, target, mask = masked[step % len(masked)]
        lit = node.with_changes(relight=relight.with_lighting(light))
        out = render_view(alone.replace(agents=(lit,)), view)
        loss = (out.rgb - target.to(out.rgb.device)).abs().sum(-1)[mask.to(out.rgb.device)].mean()
        ridge = LIGHT_RIDGE * (light[1:] ** 2).sum()
        opt.zero_grad()
        (loss + ridge).backward()
        opt.step()
        info["loss_first"] = info["loss_first"] if info["loss_first"] is not None else float(loss.detach())
        info["loss_last"] = float(loss.detach())
    light = light.detach()
    if not bool(torch.isfinite(light).all()):
        return relight, info
    return relight.with_lighting(light), info
