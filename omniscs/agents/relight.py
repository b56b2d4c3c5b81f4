"""Pool models made relightable in a scene (``omniscs.nsg.relight``): their material and normals, and the scene's
light (a sun and a sky) fitted to what the cameras saw of the track.

- Normals: each Gaussian's thinnest axis (pool models from meshes are flat Gaussians lying in the surface), turned
  to point away from the box centre. Round Gaussians have no such axis; they take the direction from the centre.
- Material: a model built from a mesh brings its own (``agents.material``: albedo, specular reflectance, shininess
  per Gaussian, from its faces). A model without one (imported splats, scene tracks, mesh builds before version 3)
  counts as matte, its albedo its colours with the light they were made under taken off: the mesh build's fixed
  light (``omniscs.agents.mesh.shade``: ambient plus one direction, two-sided) for mesh models, an even light for
  the others.
- Light: ``fit_lighting`` takes, in each of the track's views, the Gaussians whose centre is the surface the
  camera sees there (the model rendered alone in the track's node at the logged pose: the centre's depth within a
  few centimetres of the rendered depth, inside the pixels both the fitted track and the model cover), pairs each
  with the logged colour under it and fits the light's rows to those pairs (Adam, L1 on display colours). The sun's
  direction is the hard part: the fit starts from SUN_STARTS directions around the sky and keeps the best.
"""
from __future__ import annotations

import numpy as np
import torch

from omniscs.agents.mesh import AMBIENT, LIGHT_DIRECTION
from omniscs.agents.track_pixels import shared_masks, track_alone
from omniscs.gaussians import GaussianParams, activate
from omniscs.nsg.graph import SceneGraph, render_view
from omniscs.nsg.relight import Relight, matte, neutral_lighting, shade, srgb_decode
from omniscs.quaternions import normalize_quats, quat_to_rotmat
from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET

#: A Gaussian counts as flat (its thinnest axis is the surface normal) when its thinnest scale is below this share
#: of its middle one.
FLAT_RATIO = 0.5
#: Starting directions of the sun in the light's fit: azimuths (every 45 degrees) at each elevation (degrees).
SUN_AZIMUTHS = 8
SUN_ELEVATIONS_DEG = (30.0, 60.0)
SUN_STARTS = SUN_AZIMUTHS * len(SUN_ELEVATIONS_DEG)
#: Colour pairs each start of the fit sees (a fixed random subset); the best start then goes on with all of them.
START_SAMPLES = 6000
#: A Gaussian's centre is the surface a camera sees when it lies within this many metres (plus 1 % of the distance)
#: of the depth rendered at its pixel.
DEPTH_TOLERANCE_M = 0.05
#: Weight of the pull of the light's rows towards the start's (per step, on the L1 loss).
LIGHT_RIDGE = 0.002


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
    """[N, 3] linear albedo of a model without a material: its colours (view-independent band) with the mesh
    build's light taken off when ``mesh_light``. ``scale``: per-axis stretch from the model's own box to the one
    ``params`` fill (normals and the build's light direction are turned by the inverse stretch)."""
    colour = (SH_COLOR_OFFSET + SH_C0 * params.sh_dc.detach()).clamp(0.0, 1.0)
    linear = srgb_decode(colour)
    if not mesh_light:
        return linear
    light = LIGHT_DIRECTION / (np.ones(3) if scale is None else np.asarray(scale, dtype=np.float64))
    light = torch.as_tensor(light / np.linalg.norm(light), dtype=normals.dtype, device=normals.device)
    shading = AMBIENT + (1.0 - AMBIENT) * (normals @ light).abs()
    return (linear / shading[:, None]).clamp(0.0, 1.0)


def relight_base(params: GaussianParams, mesh_light: bool, scale: np.ndarray | None = None,
                 material=None) -> Relight:
    """The model's relight data under a neutral light (``fit_lighting`` fits the scene's): its ``material``
    (``agents.material.GaussianMaterial``) when it has one, else a matte albedo from its colours."""
    normals = outward_normals(params)
    dtype, device = normals.dtype, normals.device
    if material is not None:
        if len(material) != len(params):
            raise ValueError(f"material for {len(material)} Gaussians, model of {len(params)}")
        return Relight(material.albedo.to(device, dtype), normals, material.specular.to(device, dtype),
                       material.shininess.to(device, dtype), neutral_lighting(dtype).to(device))
    return matte(model_albedo(params, normals, mesh_light, scale), normals)


def light_samples(graph: SceneGraph, track_id: int, candidate: GaussianParams, masked: list[tuple]) -> dict | None:
    """The colour pairs of the light's fit (module docstring): per pair the Gaussian's index, its node's rotation
    at that frame [3, 3], the view direction (world, camera to centre) and the logged colour; None without any.
    ``masked``: (view, target, mask) from ``track_pixels.shared_masks``."""
    node = graph.agent(track_id)
    alone = track_alone(graph, track_id, candidate)
    means = activate(candidate.detached()).means.cpu().double().numpy()
    index, rotation, view_dir, colour = [], [], [], []
    with torch.no_grad():
        for view, target, mask in masked:
            depth = render_view(alone, view).depth.cpu().numpy()
            T = np.asarray(node.world_from_agent[view.frame_idx], dtype=np.float64)
            world = means @ T[:3, :3].T + T[:3, 3]
            cam = np.linalg.inv(view.world_from_camera)
            p = world @ cam[:3, :3].T + cam[:3, 3]
            z = p[:, 2]
            front = z > 0.1
            uv = p[:, :2] / np.where(front, z, 1.0)[:, None] @ view.K[:2, :2].T + view.K[:2, 2]
            u, w = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            inside = front & (u >= 0) & (u < view.width) & (w >= 0) & (w < view.height)
            i = np.flatnonzero(inside)
            m = mask.cpu().numpy()[w[i], u[i]] & (np.abs(depth[w[i], u[i]] - z[i]) < DEPTH_TOLERANCE_M + 0.01 * z[i])
            i = i[m]
            if not len(i):
                continue
            index.append(i)
            rotation.append(np.broadcast_to(T[:3, :3], (len(i), 3, 3)))
            view_dir.append(world[i] - view.world_from_camera[:3, 3])
            colour.append(target.cpu().numpy()[w[i], u[i]])
    if not index:
        return None
    return {"index": torch.from_numpy(np.concatenate(index)),
            "rotation": torch.from_numpy(np.concatenate(rotation)).float(),
            "view": torch.from_numpy(np.concatenate(view_dir)).float(),
            "colour": torch.from_numpy(np.concatenate(colour)).float()}


def _sample_colours(relight: Relight, pairs: dict, lighting: torch.Tensor, subset: torch.Tensor | None = None):
    idx, rot, view = pairs["index"], pairs["rotation"], pairs["view"]
    if subset is not None:
        idx, rot, view = idx[subset], rot[subset], view[subset]
    dev = lighting.device
    normals = torch.einsum("nij,nj->ni", rot.to(dev), relight.normals[idx.to(dev)].float())
    return shade(relight.albedo[idx.to(dev)].float(), normals, view.to(dev), relight.specular[idx.to(dev)].float(),
                 relight.shininess[idx.to(dev)].float(), lighting)


def _no_negative_light(light: torch.Tensor) -> None:
    """In place, between optimiser steps: no light row goes below zero (the sun's direction row keeps its sign)."""
    with torch.no_grad():
        light[[0, 2, 3, 4, 5, 6]] = light[[0, 2, 3, 4, 5, 6]].clamp_min(0.0)


def _fit(relight: Relight, pairs: dict, start: torch.Tensor, steps: int, lr: float,
         subset: torch.Tensor | None) -> tuple[torch.Tensor, float]:
    target = pairs["colour"].to(start.device)
    if subset is not None:
        target = target[subset.to(start.device)]
    light = start.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([light], lr=lr)
    loss = None
    for _ in range(steps):
        loss = (_sample_colours(relight, pairs, light, subset) - target).abs().sum(1).mean()
        ridge = LIGHT_RIDGE * ((light - start) ** 2).sum()
        opt.zero_grad()
        (loss + ridge).backward()
        opt.step()
        _no_negative_light(light)
    with torch.no_grad():
        final = float((_sample_colours(relight, pairs, light, subset) - target).abs().sum(1).mean())
    return light.detach(), final


def sun_starts(base: torch.Tensor) -> list[torch.Tensor]:
    """``base`` with its sun direction set to each of SUN_STARTS directions spread over the sky."""
    out = []
    for el in SUN_ELEVATIONS_DEG:
        for k in range(SUN_AZIMUTHS):
            az, e = 2 * np.pi * k / SUN_AZIMUTHS, np.radians(el)
            light = base.clone()
            light[1] = torch.tensor([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)], dtype=base.dtype,
                                    device=base.device)
            out.append(light)
    return out


def _render_loss(alone: SceneGraph, node, relight: Relight, light: torch.Tensor, view, target, mask):
    lit = node.with_changes(relight=relight.with_lighting(light))
    out = render_view(alone.replace(agents=(lit,)), view)
    return (out.rgb - target.to(out.rgb.device)).abs().sum(-1)[mask.to(out.rgb.device)].mean()


def fit_lighting(graph: SceneGraph, track_id: int, candidate: GaussianParams, relight: Relight,
                 samples: list[tuple], steps: int = 200, lr: float = 0.03, render_steps: int = 60,
                 render_lr: float = 0.01) -> tuple[Relight, dict]:
    """``relight`` with the light fitted so that ``candidate`` (in the track's node) looks like the logged images
    (``dual.colour_samples``); returns it and {views, pairs, loss_first, loss_last, pair_loss}.

    First on the colour pairs (module docstring): each of the given light and SUN_STARTS sun directions runs
    ``steps`` steps on START_SAMPLES pairs, the best runs ``steps`` more on all of them. Then ``render_steps`` steps
    on the renders themselves (the model alone at the logged poses, L1 over the pixels the fitted track and the model
    share), where Gaussians blend as they do in the image. loss_first / loss_last: that render loss over every view
    with the given light / the light returned, which is the better of the two stages' by it. With no usable view, or
    a fit that does not stay finite, ``relight`` comes back unchanged."""
    alone = track_alone(graph, track_id, candidate)
    masked = shared_masks(alone, samples)
    info = {"views": len(masked), "pairs": 0, "loss_first": None, "loss_last": None, "pair_loss": None}
    if not masked or steps + render_steps <= 0:
        return relight, info
    node = alone.agent(track_id).with_changes(gaussians=candidate, relight=relight)
    alone = alone.replace(agents=(node,))

    def render_loss(light: torch.Tensor) -> float:
        with torch.no_grad():
            return float(np.mean([float(_render_loss(alone, node, relight, light, *m)) for m in masked]))

    given = relight.lighting.detach()
    info["loss_first"] = render_loss(given)
    light = given
    pairs = light_samples(graph, track_id, candidate, masked) if steps > 0 else None
    if pairs is not None:
        info["pairs"] = int(len(pairs["index"]))
        n = len(pairs["index"])
        subset = torch.randperm(n, generator=torch.Generator().manual_seed(0))[:START_SAMPLES] \
            if n > START_SAMPLES else None
        fits = [_fit(relight, pairs, s, steps, lr, subset) for s in [given] + sun_starts(given)]
        light, info["pair_loss"] = _fit(relight, pairs, min(fits, key=lambda f: f[1])[0], steps, lr, None)
    candidates = [(render_loss(light), light)] if bool(torch.isfinite(light).all()) else []
    if render_steps > 0:
        start = light if candidates else given
        x = start.detach().clone().requires_grad_(True)
        opt = torch.optim.Adam([x], lr=render_lr)
        for step in range(render_steps):
            loss = _render_loss(alone, node, relight, x, *masked[step % len(masked)])
            opt.zero_grad()
            (loss + LIGHT_RIDGE * ((x - start) ** 2).sum()).backward()
            opt.step()
            _no_negative_light(x)
        if bool(torch.isfinite(x).all()):
            candidates.append((render_loss(x.detach()), x.detach()))
    candidates = [c for c in candidates if np.isfinite(c[0])]
    if not candidates:
        return relight, info
    info["loss_last"], light = min(candidates, key=lambda c: c[0])
    if info["loss_last"] >= info["loss_first"]:  # nothing better than the light given
        info["loss_last"] = info["loss_first"]
        return relight, info
    return relight.with_lighting(light.to(relight.lighting.dtype)), info
