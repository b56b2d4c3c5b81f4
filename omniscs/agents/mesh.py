"""Pool models from meshes (the world's asset library, or any mesh trimesh reads): flat Gaussians on the surface,
and the views that check and refine them.

- ``gaussians_from_mesh``: ``n`` points sampled by area on the part of the surface seen from outside (meshes built
  from overlapping parts, as the asset library's are, hold faces inside other parts: their points are dropped, see
  ``outside_visible``); each becomes a flat Gaussian lying in its triangle (two in-plane scales from the area each
  point stands for, a thin one along the normal), coloured with the triangle's colour under a fixed light
  (``shade``: ambient + one direction, the look of the keyframes). ``model_from_mesh`` also gives each Gaussian its
  face's material (``agents.material``: the colour as albedo, and the specular reflectance and shininess when the
  mesh has them), which a scene relights (``agents.relight``).
- ``raycast_views``: the mesh itself seen by pinhole cameras (open3d ray casting; colour, alpha), the reference a
  model is scored and refined against.
- ``orbit_cameras`` / ``keyframes``: views around the model at a fixed elevation and distance (the pool's 30
  keyframes at 12 degrees of azimuth).
- ``refine``: a short fit of the Gaussians' colours, opacities and scales to ray-cast views with the project's
  rasterizer (positions and orientations stay on the surface).
Colours are display values in 0..1 (the mesh colours are taken as linear albedo and encoded with the sRGB curve).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from omniscs.agents.material import GaussianMaterial
from omniscs.errors import ValidationError
from omniscs.quality import psnr
from omniscs.gaussians import GaussianParams, activate, params_from_values
from omniscs.geometry import intrinsics_from_fov
from omniscs.quaternions import rotmat_to_quat
from omniscs.render import rasterize
from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET

#: Light for shading the mesh colours: a direction (towards the light) and the ambient share.
LIGHT_DIRECTION = np.array([0.35, 0.45, 0.82])
AMBIENT = 0.45
#: Thickness of the flat Gaussians along their normal (metres).
THICKNESS_M = 0.004
KEYFRAMES = 30
KEYFRAME_ELEVATION_DEG = 15.0
KEYFRAME_SIZE = 96
#: Version of the mesh-to-Gaussians build, recorded with every model it makes (``model.json`` "build"): 1 sampled
#: the whole surface, buried faces included; 2 keeps only the surface seen from outside (``outside_visible``); 3 also
#: keeps each Gaussian's material (``agents.material``: albedo, specular reflectance, shininess) from its face.
MESH_BUILD_VERSION = 3
#: Surface points are drawn this many times over before those not seen from outside are dropped.
OVERSAMPLE = 3
#: Directions tried per surface point when testing whether it is seen from outside the mesh.
VISIBILITY_DIRECTIONS = 48
#: Rays testing a surface point start this far off its face (metres), so they do not hit it again.
SURFACE_OFFSET_M = 1e-3


def _srgb(linear: np.ndarray) -> np.ndarray:
    c = np.clip(linear, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def shade(albedo: np.ndarray, normals: np.ndarray) -> np.ndarray:  # linear [N, 3], unit [N, 3] -> display [N, 3]
    light = LIGHT_DIRECTION / np.linalg.norm(LIGHT_DIRECTION)
    lambert = np.abs(normals @ light)  # two-sided: mesh winding is not trusted
    return _srgb(albedo * (AMBIENT + (1.0 - AMBIENT) * lambert)[:, None])


def _check_mesh(vertices, faces, face_colours):
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    c = np.asarray(face_colours, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValidationError("a mesh needs vertices [V, 3] and at least one triangle [F, 3]")
    if c.shape != (len(f), 3) or not np.isfinite(v).all() or not np.isfinite(c).all():
        raise ValidationError("a mesh needs finite vertices and one finite colour [F, 3] per triangle")
    if f.min() < 0 or f.max() >= len(v):
        raise ValidationError("mesh faces index vertices that do not exist")
    return v, f, c


def _raycaster(vertices: np.ndarray, faces: np.ndarray):
    """An open3d ray-casting scene of the triangles."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    return scene


def _sphere_directions(n: int) -> np.ndarray:  # [n, 3] unit vectors spread evenly (Fibonacci sphere)
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def outside_visible(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray,
                    directions: int = VISIBILITY_DIRECTIONS) -> np.ndarray:  # -> [N] bool
    """Which surface ``points`` can be seen from outside the mesh: a ray from the point (lifted off its face by
    SURFACE_OFFSET_M on the side it leaves from) along at least one of ``directions`` directions spread over the
    sphere meets no triangle. Points on faces buried inside other parts (the top of a car's body under its cabin,
    the body's side inside a wheel) see none."""
    import open3d as o3d

    scene = _raycaster(vertices, faces)
    seen = np.zeros(len(points), bool)
    for d in _sphere_directions(directions):
        todo = np.flatnonzero(~seen)  # only points no earlier direction has seen out
        if not len(todo):
            break
        side = np.sign(normals[todo] @ d)[:, None]
        side[side == 0] = 1.0
        origin = points[todo] + side * SURFACE_OFFSET_M * normals[todo] + SURFACE_OFFSET_M * d
        rays = np.concatenate([origin, np.broadcast_to(d, origin.shape)], 1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        seen[todo[~np.isfinite(hit)]] = True
    return seen


def gaussians_from_mesh(vertices, faces, face_colours, n: int = 20_000, seed: int = 0, with_faces: bool = False):
    """Flat, oriented Gaussians on the outside of the mesh surface (degree-0 colours), ``n`` of them: points are
    drawn by area, those ``outside_visible`` does not see are dropped (up to OVERSAMPLE draws in all), so the
    Gaussians stand for the surface a camera can see and none shows through it from inside. With ``with_faces``:
    (the Gaussians, the index of the face each lies on)."""
    import trimesh


    v, f, c = _check_mesh(vertices, faces, face_colours)
    mesh = trimesh.Trimesh(v, f, process=False)
    area = float(mesh.area)
    if not area > 0:
        raise ValidationError("the mesh has no surface area")
    points, face = trimesh.sample.sample_surface(mesh, OVERSAMPLE * int(n), seed=int(seed))
    tri = v[f[face]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    visible = outside_visible(v, f, points, normal)
    if not visible.any():  # a degenerate mesh (e.g. one flat sheet seen edge-on everywhere): keep what there is
        visible[:] = True
    outside_area = area * float(visible.mean())
    keep = np.flatnonzero(visible)[:int(n)]
    points, face, tri, normal = points[keep], face[keep], tri[keep], normal[keep]
    t1 = tri[:, 1] - tri[:, 0]
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    t2 = np.cross(normal, t1)
    rot = np.stack([t1, t2, normal], -1)  # columns: the Gaussian's axes
    in_plane = 0.75 * np.sqrt(outside_area / len(points))
    scales = np.tile([in_plane, in_plane, THICKNESS_M], (len(points), 1))
    colours = shade(c[face], normal)
    params = params_from_values(torch.as_tensor(points, dtype=torch.float32),
                                torch.as_tensor(scales, dtype=torch.float32), torch.full((len(points),), 0.95),
                                torch.as_tensor(colours, dtype=torch.float32), 0,
                                quats=torch.as_tensor(rotmat_to_quat(rot), dtype=torch.float32))
    return (params, face) if with_faces else params


@dataclass(frozen=True)
class Camera:
    world_from_camera: np.ndarray  # [4, 4] OpenCV axes (x right, y down, z forward)
    K: np.ndarray                  # [3, 3]
    width: int
    height: int


def orbit_cameras(size: np.ndarray, n: int = KEYFRAMES, elevation_deg: float = KEYFRAME_ELEVATION_DEG,
                  image: int = KEYFRAME_SIZE, fov_deg: float = 40.0) -> list[Camera]:
    """``n`` cameras around the origin at equal azimuth steps (the first in front of the model, looking back at
    it), all at one elevation, far enough that the whole box fits the image."""
    radius = 0.5 * float(np.linalg.norm(size))
    distance = 1.15 * radius / np.sin(np.radians(fov_deg) / 2)
    K = intrinsics_from_fov(image, image, np.radians(fov_deg))
    el = np.radians(elevation_deg)
    out = []
    for k in range(n):
        az = 2 * np.pi * k / n
        eye = distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        forward = -eye / np.linalg.norm(eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, forward, eye
        out.append(Camera(T, K, image, image))
    return out


def raycast_views(vertices, faces, face_colours, cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """The mesh seen by ``cameras``: colour [C, H, W, 3] (display 0..1, black where nothing) and alpha [C, H, W]."""
    import open3d as o3d

    v, f, c = _check_mesh(vertices, faces, face_colours)
    scene = _raycaster(v, f)
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    face_rgb = shade(c, normals)
    rgbs, alphas = [], []
    for cam in cameras:
        u, w = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        d = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (w - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
        d = d @ cam.world_from_camera[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        origin = np.broadcast_to(cam.world_from_camera[:3, 3], d.shape)
        rays = o3d.core.Tensor(np.concatenate([origin, d], -1).reshape(-1, 6).astype(np.float32))
        hit = scene.cast_rays(rays)
        ids = hit["primitive_ids"].numpy().astype(np.int64).reshape(cam.height, cam.width)
        found = np.isfinite(hit["t_hit"].numpy()).reshape(cam.height, cam.width)
        rgb = np.zeros((cam.height, cam.width, 3))
        rgb[found] = face_rgb[ids[found]]
        rgbs.append(rgb)
        alphas.append(found.astype(np.float64))
    return np.stack(rgbs), np.stack(alphas)


def _render(params: GaussianParams, cameras: list[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
    """[C, H, W, 3] colour on black and [C, H, W] alpha of the Gaussians alone."""
    g = activate(params)
    view = torch.stack([torch.as_tensor(np.linalg.inv(c.world_from_camera), dtype=torch.float32) for c in cameras])
    K = torch.stack([torch.as_tensor(c.K, dtype=torch.float32) for c in cameras])
    colours = (SH_COLOR_OFFSET + SH_C0 * g.sh[:, 0]).clamp(0.0, 1.0)
    rgb, alpha, _ = rasterize(g.means, g.quats, g.scales, g.opacities, colours, view, K, cameras[0].width,
                              cameras[0].height)
    return rgb, alpha[..., 0]


def keyframes(params: GaussianParams, size: np.ndarray, n: int = KEYFRAMES) -> np.ndarray:
    """uint8 [n, H, W, 4] RGBA views of a model around it (``orbit_cameras``)."""
    with torch.no_grad():
        rgb, alpha = _render(params, orbit_cameras(size, n))
    rgba = torch.cat([rgb, alpha[..., None]], -1).clamp(0, 1)
    return (rgba.numpy() * 255.0 + 0.5).astype(np.uint8)


def view_psnr(params: GaussianParams, rgb: np.ndarray, alpha: np.ndarray, cameras: list[Camera]) -> float | None:
    """PSNR (dB, ``omniscs.quality.psnr``) of the model's renders against reference views over the pixels either
    covers; None when neither covers any."""
    with torch.no_grad():
        got, got_alpha = _render(params, cameras)
    mask = (torch.as_tensor(alpha) > 0.5) | (got_alpha > 0.5)
    return psnr(got, torch.as_tensor(rgb, dtype=torch.float32), mask)


def refine(params: GaussianParams, rgb: np.ndarray, alpha: np.ndarray, cameras: list[Camera], steps: int = 100,
           lr: float = 0.02, seed: int = 0) -> tuple[GaussianParams, dict]:
    """A short fit of colours, opacities and scales to reference views (``raycast_views``); returns the model and
    {seconds, loss before, loss after}."""
    started = time.perf_counter()
    torch.manual_seed(seed)
    dc = params.sh_dc.detach().clone().requires_grad_(True)
    op = params.opacity_logits.detach().clone().requires_grad_(True)
    sc = params.log_scales.detach().clone().requires_grad_(True)
    target = torch.as_tensor(rgb, dtype=torch.float32)
    target_alpha = torch.as_tensor(alpha, dtype=torch.float32)
    opt = torch.optim.Adam([dc, op, sc], lr=lr)
    losses = []
    for step in range(steps):
        idx = [(step * 7 + j) % len(cameras) for j in range(2)]
        cams = [cameras[i] for i in idx]
        p = GaussianParams(params.means, params.quats, sc, op, dc, params.sh_rest)
        got, got_alpha = _render(p, cams)
        loss = (got - target[idx]).abs().mean() + 0.5 * (got_alpha - target_alpha[idx]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    out = GaussianParams(params.means, params.quats, sc.detach(), op.detach(), dc.detach(), params.sh_rest)
    return out, {"seconds": time.perf_counter() - started, "loss_first": losses[0] if losses else None,
                 "loss_last": losses[-1] if losses else None}


def model_from_mesh(vertices, faces, face_colours, n: int = 20_000, refine_steps: int = 100,
                    seed: int = 0, face_specular=None, face_shininess=None,
                    face_albedo=None) -> tuple[GaussianParams, dict]:
    """A pool model from a mesh already in its vehicle frame: Gaussians on the surface, refined against 12 ray-cast
    views around it; scored (PSNR, dB) on 6 other views at another elevation. Returns it and {quality, seconds,
    material, ...}: "material" is each Gaussian's ``GaussianMaterial`` from its face (the face colour as albedo;
    ``face_specular`` [F] and ``face_shininess`` [F] when the mesh has them, else matte; ``face_albedo`` [F, 3]
    linear when the diffuse reflectance differs from the colour the surface shows, as a metal's does)."""
    started = time.perf_counter()
    v, f, c = _check_mesh(vertices, faces, face_colours)
    size = v.max(0) - v.min(0)
    for name, a, shape in (("face_specular", face_specular, (len(f),)), ("face_shininess", face_shininess, (len(f),)),
                           ("face_albedo", face_albedo, (len(f), 3))):
        if a is not None and (np.shape(a) != shape or not np.isfinite(np.asarray(a, np.float64)).all()):
            raise ValidationError(f"{name} must hold one finite value per face and channel, shape {shape}; got "
                                  f"shape {np.shape(a)}")
    params, face = gaussians_from_mesh(v, f, c, n, seed, with_faces=True)
    material = GaussianMaterial.from_faces(face, c if face_albedo is None else face_albedo, face_specular,
                                           face_shininess)
    train = orbit_cameras(size, 12, elevation_deg=KEYFRAME_ELEVATION_DEG)
    held = orbit_cameras(size, 12, elevation_deg=30.0)[1::2]
    info = {}
    if refine_steps > 0:
        rgb, alpha = raycast_views(v, f, c, train)
        params, info = refine(params, rgb, alpha, train, steps=refine_steps, seed=seed)
    hrgb, halpha = raycast_views(v, f, c, held)
    return params, {"quality_psnr": view_psnr(params, hrgb, halpha, held), "seconds": time.perf_counter() - started,
                    "n_gaussians": len(params), "refine": info, "material": material,
                    "build": {"method": "mesh", "version": MESH_BUILD_VERSION, "gaussians": int(n),
                              "refine_steps": int(refine_steps), "seed": int(seed)}}
