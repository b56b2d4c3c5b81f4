"""Ray-cast renderer of a procedural world: RGB, z-depth, instance and semantic masks, and LiDAR scans."""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform, transform_points
from omniscs.world import lidar as lidar_model
from omniscs.world.assets import Material, build_asset, srgb
from omniscs.world.layouts import layout_for
from omniscs.world.model import World

# Ray caster: open3d ``RaycastingScene`` (Embree inside, multi-threaded). On the idle 2-core dev machine
# one 480x270 image (130k rays, 96k triangles) cast in 10 ms with open3d against 18 ms with
# trimesh/embreex (single-threaded); with the other core busy both took ~17 ms, and
# ``omniscs.bench.world`` re-measures the ratio each run. Static geometry lives in one scene built once;
# agents go into a small scene rebuilt per frame, and each ray keeps the nearer hit. Shading (numpy)
# costs more than casting: about 0.55 s per frame for three 480x270 cameras on 2 cores.

M = Material
N_MATERIALS = max(Material) + 1


@dataclass(frozen=True)
class CameraRender:
    """One rendered camera image with exact ground truth."""

    rgb: np.ndarray  # [H, W, 3] uint8 sRGB
    depth: np.ndarray  # [H, W] float32 z-depth in the camera frame, metres; 0.0 where nothing is hit (sky)
    instance: np.ndarray  # [H, W] int32 agent track_id, -1 for background and sky
    semantic: np.ndarray  # [H, W] uint8 omniscs.taxonomy.SEMANTIC_CLASSES id (0 = sky)


@dataclass(frozen=True)
class Lighting:
    """How one lighting condition looks: sun, sky, fog, artificial lights and camera exposure."""

    sun_elevation_deg: float
    sun_colour: np.ndarray  # [3] linear irradiance of the sun (or moon) on a surface facing it
    sky_zenith: np.ndarray  # [3] linear radiance of the sky straight up
    sky_horizon: np.ndarray  # [3] linear radiance of the sky at the horizon
    ambient: float  # scale of the sky light that reaches surfaces (hemisphere ambient)
    fog_density: float  # 1/metres; transmittance exp(-density * distance)
    fog_colour: np.ndarray  # [3] linear in-scattered colour
    exposure: float  # camera gain before the tone curve
    emissive_gain: float  # how bright lamps, lights and lit windows appear
    street_lamp_power: float  # radiant intensity of a street lamp (0 = off)
    headlight_power: float  # radiant intensity of each ego headlight (0 = off)
    lit_window_fraction: float  # fraction of facade windows lit from inside
    shadows: bool  # trace sun shadow rays
    noise_sigma: float  # sensor noise std on the [0, 1] output scale


LIGHTING_MODELS: dict[str, Lighting] = {
    "day": Lighting(52.0, srgb(255, 247, 235) * 2.6, srgb(90, 140, 215), srgb(190, 212, 235), 1.0,
                    0.0015, srgb(200, 210, 225), 1.15, 0.25, 0.0, 0.0, 0.0, True, 0.004),
    "dusk": Lighting(7.0, srgb(255, 150, 80) * 1.7, srgb(60, 70, 130), srgb(240, 150, 100), 0.8,
                     0.003, srgb(180, 130, 120), 1.9, 0.7, 6.0, 18.0, 0.2, True, 0.008),
    "night": Lighting(35.0, srgb(150, 170, 255) * 0.05, srgb(4, 6, 14), srgb(22, 20, 30), 0.6,
                      0.002, srgb(20, 20, 28), 5.0, 1.0, 22.0, 30.0, 0.35, False, 0.015),
    "fog": Lighting(40.0, srgb(255, 250, 245) * 0.5, srgb(175, 178, 182), srgb(195, 197, 200), 1.6,
                    0.028, srgb(190, 192, 195), 1.35, 0.6, 4.0, 12.0, 0.1, True, 0.006),
}

# Per-material optics (indexed by Material): specular reflectance at normal incidence, Phong exponent,
# and how strongly the face colour glows when lights are on.
F0 = np.zeros(N_MATERIALS, np.float32)
SHININESS = np.full(N_MATERIALS, 8.0, np.float32)
EMISSION = np.zeros(N_MATERIALS, np.float32)
for _m, _f0, _sh in ((M.CAR_PAINT, 0.05, 90), (M.GLASS, 0.09, 400), (M.CHROME, 0.55, 120), (M.METAL, 0.08, 30),
                     (M.PLASTIC, 0.04, 30), (M.HEADLIGHT, 0.12, 200), (M.TAILLIGHT, 0.08, 120),
                     (M.LANE_PAINT, 0.02, 10), (M.CONTAINER, 0.04, 20), (M.PLATE, 0.04, 40),
                     (M.SIGNAL, 0.05, 60), (M.REFLECTIVE, 0.05, 20)):
    F0[_m], SHININESS[_m] = _f0, _sh
for _m, _e in ((M.HEADLIGHT, 7.0), (M.TAILLIGHT, 3.0), (M.LAMP, 10.0), (M.SIGN_LIGHT, 3.0), (M.SIGNAL, 5.0)):
    EMISSION[_m] = _e

SHADOW_RAY_LENGTH = 600.0  # metres; farther occluders do not shade
AO_RAY_LENGTH = 2.5  # metres; short rays that darken ambient light under cars and in corners
AO_STRENGTH = 0.55
SURFACE_OFFSET = 0.02  # metres along the normal before tracing secondary rays
SURFACE_OFFSET_PER_METRE = 1e-3  # grows with distance to beat float32 error
STREET_LAMP_RANGE = 45.0
HEADLIGHT_MOUNTS = ((3.6, 0.65, 0.7), (3.6, -0.65, 0.7))  # ego frame
HEADLIGHT_COS_INNER, HEADLIGHT_COS_OUTER = 0.985, 0.90
HEADLIGHT_PITCH = np.radians(-1.5)
HEADLIGHT_NEAR_CUT, HEADLIGHT_NEAR_RAMP = 3.0, 9.0  # metres
WINDOW_GLASS = srgb(38, 48, 60)
WINDOW_LIT = srgb(255, 210, 150)
DIRT_BROWN = srgb(110, 90, 60)
GROUND_BOUNCE = srgb(120, 115, 105)
SUN_GLOW_MIN_COS = 0.5  # sky directions farther than 60° from the sun get no glow
TONE_KNEE = 1.0  # tone curve y = 1 - exp(-x / knee)
SKY_NOISE_FREE = True  # the sky stays clean; only lit surfaces get sensor noise


# ----------------------------------------------------------------------------- procedural noise
def _hash(ix: np.ndarray, iy: np.ndarray, salt: int = 0) -> np.ndarray:  # int lattice -> [0, 1)
    h = ix.astype(np.int64).astype(np.uint32) * np.uint32(374761393)
    h = h + iy.astype(np.int64).astype(np.uint32) * np.uint32(668265263) + np.uint32(salt * 2246822519 % 2**32)
    h = (h ^ (h >> np.uint32(13))) * np.uint32(1274126177)
    h = h ^ (h >> np.uint32(16))
    return h.astype(np.float32) * np.float32(1.0 / 2**32)


def value_noise(x: np.ndarray, y: np.ndarray, salt: int = 0) -> np.ndarray:  # [N], [N] -> [N] in [0, 1)
    """Smooth lattice value noise (deterministic, position-anchored so textures do not swim)."""
    xf, yf = np.floor(x), np.floor(y)
    fx, fy = (x - xf).astype(np.float32), (y - yf).astype(np.float32)
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    xi, yi = xf.astype(np.int64), yf.astype(np.int64)
    a, b = _hash(xi, yi, salt), _hash(xi + 1, yi, salt)
    c, d = _hash(xi, yi + 1, salt), _hash(xi + 1, yi + 1, salt)
    return (a + (b - a) * fx) + ((c + (d - c) * fx) - (a + (b - a) * fx)) * fy


def fbm(x: np.ndarray, y: np.ndarray, octaves: int = 3, salt: int = 0) -> np.ndarray:  # -> [N] ~[0, 1)
    total, amp, norm = np.zeros(x.shape, np.float32), 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(x * (2 ** o), y * (2 ** o), salt + o)
        norm += amp
        amp *= 0.5
    return total / norm


# ----------------------------------------------------------------------------- geometry tables
@dataclass
class _FaceTable:
    """Per-face attributes of one ray-casting scene (row = primitive id)."""

    colour: np.ndarray  # [F, 3] float32
    material: np.ndarray  # [F] uint8
    semantic: np.ndarray  # [F] uint8
    params: np.ndarray  # [F, 4] float32 (assets.FACE_PARAMS)
    track: np.ndarray  # [F] int32 track id, -1 for static
    agent: np.ndarray  # [F] int32 index into the frame's agent list, -1 for static


def _o3d_scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))
    return scene


@dataclass
class _Frame:
    index: int
    scene: o3d.t.geometry.RaycastingScene | None  # agents only; None when no agent is present
    table: _FaceTable  # static faces, then the present agents' faces
    agent_from_world: np.ndarray  # [A, 4, 4] per present agent (unscaled local frame)
    agent_scale: np.ndarray  # [A, 3] mesh scale that fits the asset into the track's box
    casters: o3d.t.geometry.RaycastingScene | None = None  # shadow casters present (not seen by camera or LiDAR)


@dataclass
class _Hits:
    t: np.ndarray  # [N] float32, inf on miss
    normal: np.ndarray  # [N, 3] float32 unit geometric normal (unoriented)
    dynamic: np.ndarray  # [N] bool: the hit is on an agent
    face: np.ndarray  # [N] int64 row in the frame's face table (agent faces follow the static ones)


def _placed_mesh(track, frame_idx: int):
    """A track's asset, the scale that fits its mesh into the track's box, and the mesh's vertices in the world at
    ``frame_idx``."""
    asset = build_asset(track.asset_id)
    scale = np.asarray(track.size, dtype=np.float64) / asset.size
    return asset, scale, transform_points(track.poses[frame_idx], asset.surface.vertices * scale)


class WorldRenderer:
    """Renders a World frame by frame: static geometry is built once, agents are placed per frame."""

    def __init__(self, world: World, shadow_casters=()) -> None:
        """``shadow_casters``: agent tracks (of this or another world: e.g. removed ones) that shade this world (sun
        shadows, ambient occlusion) without being seen by camera or LiDAR rays; a removed object's light stays."""
        self.world = world
        self.shadow_casters = tuple(shadow_casters)
        self.layout = layout_for(world)
        if world.lighting not in LIGHTING_MODELS:
            raise OmniscsError(f"unknown lighting {world.lighting!r}; use one of {list(LIGHTING_MODELS)}")
        self.light = LIGHTING_MODELS[world.lighting]
        sun_rng = np.random.default_rng([zlib.crc32(b"sun"), world.seed])
        azimuth = sun_rng.uniform(-np.pi, np.pi)
        el = np.radians(self.light.sun_elevation_deg)
        self.sun_dir = np.array([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)])
        surf = self.layout.surface
        self.static_scene = _o3d_scene(surf.vertices, surf.faces)
        n = self.n_static_faces = len(surf.faces)
        self.static_table = _FaceTable(surf.face_colour.astype(np.float32), surf.face_material.astype(np.uint8),
                                       surf.face_semantic.astype(np.uint8), surf.face_params.astype(np.float32),
                                       np.full(n, -1, np.int32), np.full(n, -1, np.int32))
        self._frame: _Frame | None = None
        self._ray_cache: dict = {}
        self._lidar_dirs = lidar_model.beam_directions(world.lidar)  # [R, 3] lidar frame
        for track in world.agents + self.shadow_casters:
            if track.poses.shape[0] != world.n_frames:
                raise OmniscsError(f"track {track.track_id} has {track.poses.shape[0]} poses; this world has "
                                   f"{world.n_frames} frames")
            build_asset(track.asset_id)  # fail early on unknown assets

    # -- per-frame agent scene ---------------------------------------------------------------
    def _check_frame(self, frame_idx: int) -> None:
        if not isinstance(frame_idx, (int, np.integer)) or not 0 <= frame_idx < self.world.n_frames:
            raise OmniscsError(f"frame index {frame_idx!r} is out of range; this world has frames "
                               f"0..{self.world.n_frames - 1}")

    def frame(self, frame_idx: int) -> _Frame:
        self._check_frame(frame_idx)
        if self._frame is not None and self._frame.index == frame_idx:
            return self._frame
        verts, faces, cols, mats, sems, pars, tracks, agents = [], [], [], [], [], [], [], []
        inv_poses, scales = [], []
        offset = 0
        for track in self.world.agents:
            if not track.present[frame_idx]:
                continue
            asset, scale, placed = _placed_mesh(track, frame_idx)
            pose = track.poses[frame_idx]
            s = asset.surface
            verts.append(placed)
            faces.append(s.faces + offset)
            offset += len(s.vertices)
            nf = len(s.faces)
            cols.append(s.face_colour)
            mats.append(s.face_material)
            sems.append(s.face_semantic)
            pars.append(s.face_params)
            tracks.append(np.full(nf, track.track_id, np.int32))
            agents.append(np.full(nf, len(inv_poses), np.int32))
            inv_poses.append(invert_transform(pose))
            scales.append(scale)
        scene = _o3d_scene(np.concatenate(verts), np.concatenate(faces)) if verts else None
        casters = self._caster_scene(frame_idx)
        st = self.static_table
        # One table per frame, static faces first, so a hit's attributes are a single gather.
        table = _FaceTable(np.concatenate([st.colour] + cols), np.concatenate([st.material] + mats),
                           np.concatenate([st.semantic] + sems), np.concatenate([st.params] + pars),
                           np.concatenate([st.track] + tracks), np.concatenate([st.agent] + agents))
        self._frame = _Frame(frame_idx, scene, table, np.array(inv_poses).reshape(-1, 4, 4),
                             np.array(scales).reshape(-1, 3), casters)
        return self._frame

    def _caster_scene(self, frame_idx: int) -> o3d.t.geometry.RaycastingScene | None:
        verts, faces, offset = [], [], 0
        for track in self.shadow_casters:
            if not track.present[frame_idx]:
                continue
            asset, _, placed = _placed_mesh(track, frame_idx)
            verts.append(placed)
            faces.append(asset.surface.faces + offset)
            offset += len(asset.surface.vertices)
        return _o3d_scene(np.concatenate(verts), np.concatenate(faces)) if verts else None

    # -- ray casting -------------------------------------------------------------------------
    def _cast(self, fr: _Frame, rays: np.ndarray) -> _Hits:  # rays [N, 6] float32
        tensor = o3d.core.Tensor(rays)
        hit = self.static_scene.cast_rays(tensor)
        t = hit["t_hit"].numpy()
        normal = hit["primitive_normals"].numpy()
        face = hit["primitive_ids"].numpy().astype(np.int64)
        dynamic = np.zeros(len(t), dtype=bool)
        if fr.scene is not None:
            dh = fr.scene.cast_rays(tensor)
            td = dh["t_hit"].numpy()
            dynamic = td < t
            t = np.where(dynamic, td, t)
            normal = np.where(dynamic[:, None], dh["primitive_normals"].numpy(), normal)
            face = np.where(dynamic, dh["primitive_ids"].numpy().astype(np.int64) + self.n_static_faces, face)
        return _Hits(t, normal, dynamic, face)

    def _occluded(self, fr: _Frame, rays: np.ndarray) -> np.ndarray:  # [N, 6], hit within |d| -> [N] bool
        if len(rays) == 0:
            return np.zeros(0, dtype=bool)
        tensor = o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32))
        occ = self.static_scene.test_occlusions(tensor, tnear=0.0, tfar=1.0).numpy().astype(bool)
        for scene in (fr.scene, fr.casters):
            if scene is not None:
                occ |= scene.test_occlusions(tensor, tnear=0.0, tfar=1.0).numpy().astype(bool)
        return occ

    def _attr(self, fr: _Frame, hits: _Hits, sel: np.ndarray, name: str) -> np.ndarray:
        """A face attribute of the hit rays ``sel`` (indices) from the frame's table."""
        return getattr(fr.table, name)[hits.face[sel]]

    # -- camera ------------------------------------------------------------------------------
    def render_camera(self, frame_idx: int, camera_name: str) -> CameraRender:
        """Render one camera of one frame: sRGB image, z-depth (0 = sky), instance ids, semantic ids."""
        cam = self.world.camera(camera_name)
        fr = self.frame(frame_idx)
        world_from_camera = self.world.ego_poses[frame_idx] @ cam.ego_from_camera
        H, W = cam.height, cam.width
        d_cam, d_len = self._camera_rays(cam)
        d_world = d_cam @ world_from_camera[:3, :3].T.astype(np.float32)  # [N, 3], |d| = d_len
        origin = world_from_camera[:3, 3]
        rays = np.empty((len(d_cam), 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = d_world
        hits = self._cast(fr, rays)
        hit = np.isfinite(hits.t)
        depth = np.where(hit, hits.t, 0.0).astype(np.float32)
        sel = np.flatnonzero(hit)
        miss = np.flatnonzero(~hit)
        semantic = np.zeros(H * W, np.uint8)
        instance = np.full(H * W, -1, np.int32)
        semantic[sel] = self._attr(fr, hits, sel, "semantic")
        instance[sel] = self._attr(fr, hits, sel, "track")
        radiance = np.empty((H * W, 3), np.float32)
        radiance[miss] = self._sky(d_world[miss] / d_len[miss, None])
        if len(sel):
            dist = hits.t[sel] * d_len[sel]
            view = d_world[sel] / d_len[sel, None]
            radiance[sel] = self._fog(self._shade(fr, hits, sel, origin, view, dist, frame_idx), dist)
        rgb = self._to_srgb(radiance, hit, frame_idx, camera_name)
        return CameraRender(rgb.reshape(H, W, 3), depth.reshape(H, W), instance.reshape(H, W),
                            semantic.reshape(H, W))

    def _camera_rays(self, cam) -> tuple[np.ndarray, np.ndarray]:  # -> d_cam [H*W, 3] float32, |d| [H*W]
        """Camera-frame ray directions through pixel centres (u + 0.5, v + 0.5), scaled to z = 1 so the
        ray parameter t is the z-depth."""
        key = (cam.name, cam.width, cam.height, cam.K.tobytes())
        cached = self._ray_cache.get(key)
        if cached is None:
            u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
            K = cam.K
            d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
            cached = (d.astype(np.float32), np.linalg.norm(d, axis=1).astype(np.float32))
            self._ray_cache[key] = cached
        return cached

    def render_frame(self, frame_idx: int) -> dict[str, CameraRender]:
        return {cam.name: self.render_camera(frame_idx, cam.name) for cam in self.world.cameras}

    # -- shading -------------------------------------------------------------------------------
    def _sky(self, d: np.ndarray) -> np.ndarray:  # [N, 3] unit -> [N, 3] linear radiance
        L = self.light
        d = d.astype(np.float32, copy=False)
        e = np.sqrt(np.clip(d[:, 2], 0.0, 1.0))[:, None]
        sky = L.sky_horizon.astype(np.float32) + (L.sky_zenith - L.sky_horizon).astype(np.float32) * e
        cos_sun = np.clip(d @ self.sun_dir.astype(np.float32), 0.0, 1.0)
        near_sun = cos_sun > SUN_GLOW_MIN_COS
        if near_sun.any():
            c = cos_sun[near_sun]
            c8 = (c * c) ** 4
            glow = 0.25 * c8 + 4.0 * np.power(c, 800.0)
            tint = (L.sun_colour / max(np.max(L.sun_colour), 1e-6) * np.max(L.sky_horizon) * 2.0).astype(np.float32)
            sky[near_sun] += glow[:, None] * tint
        sky[d[:, 2] < 0] = L.sky_horizon * 0.8
        if L.fog_density > 0.01:  # thick fog: the sky is the fog
            sky = 0.3 * sky + 0.7 * L.fog_colour.astype(np.float32)
        return sky

    def _fog(self, colour: np.ndarray, dist: np.ndarray) -> np.ndarray:
        transmit = np.exp(-self.light.fog_density * dist)[:, None].astype(np.float32)
        return colour * transmit + self.light.fog_colour * (1.0 - transmit)

    def _shade(self, fr: _Frame, hits: _Hits, sel: np.ndarray, origin: np.ndarray, view: np.ndarray,
               dist: np.ndarray, frame_idx: int) -> np.ndarray:  # -> [M, 3] linear radiance
        L = self.light
        p = (origin + view * dist[:, None]).astype(np.float64)  # [M, 3] world hit points
        n = hits.normal[sel].astype(np.float32)
        flip = np.einsum("ij,ij->i", n, view) > 0
        n[flip] = -n[flip]  # normals face the viewer
        mat = self._attr(fr, hits, sel, "material")
        colour = self._attr(fr, hits, sel, "colour")
        params = self._attr(fr, hits, sel, "params")
        albedo, f0, shininess, emission = self._materials(fr, hits, sel, p, n, mat, colour, params)

        # Secondary rays: sun shadows and short ambient-occlusion probes, one occlusion query.
        offset = (SURFACE_OFFSET + SURFACE_OFFSET_PER_METRE * dist)[:, None]
        start = p + n * offset
        ndl = np.clip(n @ self.sun_dir, 0.0, 1.0).astype(np.float32)
        ao_dir = n + np.array([0.0, 0.0, 1.0], np.float32)
        ao_dir /= np.maximum(np.linalg.norm(ao_dir, axis=1, keepdims=True), 1e-6)
        probes = [np.concatenate([start, ao_dir * AO_RAY_LENGTH], 1)]
        lit = np.flatnonzero(ndl > 0) if L.shadows else np.zeros(0, np.int64)
        if len(lit):
            probes.append(np.concatenate([start[lit], np.broadcast_to(self.sun_dir * SHADOW_RAY_LENGTH, (len(lit), 3))], 1))
        occ = self._occluded(fr, np.concatenate(probes))
        ao = 1.0 - AO_STRENGTH * occ[: len(p)].astype(np.float32)
        sun_vis = np.ones(len(p), np.float32)
        if len(lit):
            sun_vis[lit] = 1.0 - occ[len(p):].astype(np.float32)
        direct = (ndl * sun_vis)[:, None] * L.sun_colour.astype(np.float32)

        hemi = (0.5 + 0.5 * n[:, 2])[:, None]
        sky_avg = 0.5 * (L.sky_zenith + L.sky_horizon)
        ambient = L.ambient * ao[:, None] * (hemi * sky_avg + (1 - hemi) * GROUND_BOUNCE * np.mean(sky_avg) * 2.0)
        artificial = self._artificial_light(p, n, frame_idx)
        diffuse_light = direct + ambient.astype(np.float32) + artificial

        # Specular: Fresnel-weighted sky reflection plus a sun highlight.
        cos_v = np.clip(-np.einsum("ij,ij->i", n, view), 0.0, 1.0)
        fresnel = (f0 + (1 - f0) * (1 - cos_v) ** 5) * (f0 > 0)
        shiny = np.flatnonzero(f0 > 0)
        env = np.zeros_like(albedo)
        refl = view[shiny] - 2 * np.einsum("ij,ij->i", view[shiny], n[shiny])[:, None] * n[shiny]
        env[shiny] = self._sky(refl) * ao[shiny, None]
        half = self.sun_dir - view
        half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-6)
        ndh = np.clip(np.einsum("ij,ij->i", n, half.astype(np.float32)), 0.0, 1.0)
        spec = (f0 > 0) * sun_vis * (ndh ** shininess) * (shininess + 8) / (8 * np.pi) * 4 * f0
        colour_out = albedo * (1 - fresnel)[:, None] * diffuse_light + fresnel[:, None] * env \
            + spec[:, None] * L.sun_colour + emission
        return colour_out.astype(np.float32)

    def _artificial_light(self, p: np.ndarray, n: np.ndarray, frame_idx: int) -> np.ndarray:  # -> [M, 3]
        L = self.light
        out = np.zeros(p.shape, np.float32)
        if L.street_lamp_power > 0 and len(self.layout.street_lamps):
            lamps = self.layout.street_lamps
            centre = p.mean(axis=0)
            near = lamps[np.linalg.norm(lamps[:, :2] - centre[:2], axis=1) < 3 * STREET_LAMP_RANGE]
            warm = srgb(255, 205, 150).astype(np.float32)
            for lamp in near:
                to = (lamp - p).astype(np.float32)
                d2 = np.einsum("ij,ij->i", to, to)
                d = np.sqrt(d2)
                cos_n = np.clip(np.einsum("ij,ij->i", n, to) / np.maximum(d, 1e-6), 0.0, 1.0)
                down = np.clip(to[:, 2] / np.maximum(d, 1e-6), 0.0, 1.0)  # lamps shine downwards
                fall = np.clip(1.0 - d / STREET_LAMP_RANGE, 0.0, 1.0)
                out += (L.street_lamp_power * cos_n * down * fall / (d2 + 1.0))[:, None] * warm
        if L.headlight_power > 0:
            ego = self.world.ego_poses[frame_idx]
            c, s = np.cos(HEADLIGHT_PITCH), np.sin(HEADLIGHT_PITCH)
            axis = ego[:3, :3] @ np.array([c, 0.0, s])
            white = srgb(255, 245, 225).astype(np.float32)
            for mount in HEADLIGHT_MOUNTS:
                src = transform_points(ego, np.array([mount]))[0]
                to = (src - p).astype(np.float32)
                d2 = np.einsum("ij,ij->i", to, to)
                d = np.sqrt(d2)
                unit = to / np.maximum(d, 1e-6)[:, None]
                cos_n = np.clip(np.einsum("ij,ij->i", n, unit), 0.0, 1.0)
                cos_axis = -unit @ axis.astype(np.float32)
                cone = np.clip((cos_axis - HEADLIGHT_COS_OUTER) / (HEADLIGHT_COS_INNER - HEADLIGHT_COS_OUTER), 0, 1)
                # Low beams are aimed so the road lights up from a few metres ahead, not under the bumper.
                reach = np.clip((d - HEADLIGHT_NEAR_CUT) / HEADLIGHT_NEAR_RAMP, 0.0, 1.0)
                out += (L.headlight_power * cos_n * cone * reach / (d2 + 1.0))[:, None] * white
        return out

    def _materials(self, fr: _Frame, hits: _Hits, sel: np.ndarray, p: np.ndarray, n: np.ndarray,
                   mat: np.ndarray, colour: np.ndarray, params: np.ndarray):
        """Procedural textures -> albedo [M, 3], f0 [M], shininess [M], emission [M, 3]."""
        L = self.light
        albedo = colour.copy()
        f0 = F0[mat].copy()
        shininess = SHININESS[mat].copy()
        emission = (EMISSION[mat] * L.emissive_gain)[:, None] * colour
        x, y, z = p[:, 0], p[:, 1], p[:, 2]

        def scale(mask: np.ndarray, factor: np.ndarray) -> None:
            albedo[mask] *= np.asarray(factor, np.float32).reshape(-1, 1) if np.ndim(factor) else factor

        m = mat == M.ASPHALT
        if m.any():
            g = 0.78 + 0.35 * fbm(x[m] * 0.8, y[m] * 0.8, 3, 1) + 0.18 * (value_noise(x[m] * 25, y[m] * 25, 2) - 0.5)
            scale(m, g)
        m = mat == M.LANE_PAINT
        if m.any():
            scale(m, 0.8 + 0.25 * value_noise(x[m] * 6, y[m] * 6, 3))
        m = (mat == M.CONCRETE) & (n[:, 2] > 0.5)
        if m.any():  # paving slabs with joints
            fx, fy = np.mod(x[m], 1.2), np.mod(y[m], 1.2)
            joint = (fx < 0.03) | (fy < 0.03)
            scale(m, np.where(joint, 0.72, 1.0) * (0.9 + 0.2 * value_noise(x[m] * 3, y[m] * 3, 4)))
        m = mat == M.KERB
        if m.any():
            scale(m, 0.85 + 0.25 * value_noise(x[m] * 4 + z[m] * 9, y[m] * 4, 5))
        m = mat == M.GRASS
        if m.any():
            patch = fbm(x[m] * 0.15, y[m] * 0.15, 3, 6)[:, None]
            base = albedo[m] * (0.75 + 0.5 * value_noise(x[m] * 2, y[m] * 2, 7))[:, None]
            albedo[m] = base * (1 - 0.5 * patch) + DIRT_BROWN.astype(np.float32) * 0.5 * patch
        m = mat == M.FOLIAGE
        if m.any():
            scale(m, 0.55 + 0.7 * value_noise(x[m] * 2.5 + z[m] * 1.7, y[m] * 2.5 - z[m] * 1.3, 8))
        m = (mat == M.BARK) | (mat == M.ROCK) | (mat == M.ROOF)
        if m.any():
            scale(m, 0.8 + 0.4 * value_noise(x[m] * 3 + z[m] * 5, y[m] * 3 - z[m] * 2, 9))
        m = mat == M.WOOD
        if m.any():
            scale(m, 0.8 + 0.3 * value_noise(x[m] * 1.5 + z[m] * 20, y[m] * 1.5, 10))
        m = np.flatnonzero(mat == M.FACADE)
        if len(m):
            self._facades(m, p, n, params, albedo, f0, shininess, emission)
        m = np.flatnonzero(mat == M.CONTAINER)
        if len(m):  # corrugated steel: ribs along the container's length, in its own frame
            local = self._agent_local(fr, hits, sel[m], p[m])
            rib = np.maximum(params[m, 0], 0.05)
            ribs = 0.82 + 0.18 * np.cos(2 * np.pi * local[:, 0] / rib)
            albedo[m] *= ribs[:, None].astype(np.float32)
        m = mat == M.SIGNAL
        if m.any():  # only the lit lamp of a traffic light glows
            emission[m] *= params[m, 0:1]
            albedo[m] *= np.where(params[m, 0:1] > 0, 1.0, 0.25)
        m = (mat == M.HEADLIGHT) | (mat == M.TAILLIGHT) | (mat == M.LAMP) | (mat == M.SIGN_LIGHT)
        if m.any() and L.emissive_gain < 0.5:  # daylight: lamps are dim, their covers look like plastic
            albedo[m] *= 0.6
        return albedo, f0, shininess, emission

    def _facades(self, idx: np.ndarray, p: np.ndarray, n: np.ndarray, params: np.ndarray, albedo: np.ndarray,
                 f0: np.ndarray, shininess: np.ndarray, emission: np.ndarray) -> None:
        """Window grid on building walls: the horizontal facade coordinate runs along the wall."""
        pp, nn, par = p[idx], n[idx], params[idx]
        wall = np.abs(nn[:, 2]) < 0.5
        u = pp[:, 0] * -nn[:, 1] + pp[:, 1] * nn[:, 0]
        period, floor_h, win_w, win_h = (np.maximum(par[:, 0], 0.5), np.maximum(par[:, 1], 2.0), par[:, 2], par[:, 3])
        cu, cv = u / period, pp[:, 2] / floor_h
        fu, fv = cu - np.floor(cu), cv - np.floor(cv)
        window = wall & (np.abs(fu - 0.5) < win_w / 2) & (np.abs(fv - 0.55) < win_h / 2) & (pp[:, 2] > 1.0)
        frame = wall & ~window & (np.abs(fu - 0.5) < win_w / 2 + 0.04) & (np.abs(fv - 0.55) < win_h / 2 + 0.03) \
            & (pp[:, 2] > 1.0)
        grime = (0.85 + 0.25 * value_noise(pp[:, 0] * 0.7 + pp[:, 2] * 0.3, pp[:, 1] * 0.7, 11)).astype(np.float32)
        albedo[idx] *= grime[:, None]
        w = idx[window]
        albedo[w] = WINDOW_GLASS.astype(np.float32)
        f0[w], shininess[w] = F0[M.GLASS], SHININESS[M.GLASS]
        albedo[idx[frame]] *= 0.6
        if self.light.lit_window_fraction > 0:
            cell = _hash(np.floor(cu[window]).astype(np.int64) + 7919 * np.round(nn[window, 0]).astype(np.int64),
                         np.floor(cv[window]).astype(np.int64) + 104729 * np.round(nn[window, 1]).astype(np.int64), 12)
            lit = cell < self.light.lit_window_fraction
            emission[w[lit]] = WINDOW_LIT.astype(np.float32) * 1.2 * self.light.emissive_gain

    def _agent_local(self, fr: _Frame, hits: _Hits, sel: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Hit points in their agent's asset frame (unscaled mesh coordinates) [M, 3]."""
        agent = fr.table.agent[hits.face[sel]]
        inv = fr.agent_from_world[agent]  # [M, 4, 4]
        local = np.einsum("mij,mj->mi", inv[:, :3, :3], p) + inv[:, :3, 3]
        return local / fr.agent_scale[agent]

    def _to_srgb(self, radiance: np.ndarray, hit: np.ndarray, frame_idx: int, camera_name: str) -> np.ndarray:
        L = self.light
        x = 1.0 - np.exp(-np.maximum(radiance, 0.0) * L.exposure / TONE_KNEE)
        if L.noise_sigma > 0:
            rng = np.random.default_rng([self.world.seed, frame_idx, zlib.crc32(camera_name.encode())])
            noise = rng.normal(0.0, L.noise_sigma, x.shape).astype(np.float32)
            if SKY_NOISE_FREE:
                noise *= hit[:, None]
            x = x + noise
        x = np.clip(x, 0.0, 1.0)
        srgb_out = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
        return np.clip(np.round(srgb_out * 255.0), 0, 255).astype(np.uint8)

    # -- LiDAR ---------------------------------------------------------------------------------
    def lidar_scan(self, frame_idx: int, return_track_ids: bool = False):
        """One sweep in the ego frame: points [N, 4] float32 (x, y, z, intensity 0..255), only returns
        within ``max_range``; with ``return_track_ids`` also [N] int32 track ids (-1 = background)."""
        fr = self.frame(frame_idx)
        spec = self.world.lidar
        world_from_lidar = self.world.ego_poses[frame_idx] @ spec.ego_from_lidar
        d_world = self._lidar_dirs @ world_from_lidar[:3, :3].T
        origin = world_from_lidar[:3, 3]
        rays = np.concatenate([np.broadcast_to(origin, d_world.shape), d_world], 1).astype(np.float32)
        hits = self._cast(fr, rays)
        keep = np.flatnonzero(np.isfinite(hits.t) & (hits.t <= spec.max_range))
        rng_m = hits.t[keep].astype(np.float64)
        p_lidar = self._lidar_dirs[keep] * rng_m[:, None]
        p_ego = transform_points(spec.ego_from_lidar, p_lidar)
        mat = self._attr(fr, hits, keep, "material")
        cos_inc = np.einsum("ij,ij->i", hits.normal[keep], d_world[keep])
        inten = lidar_model.intensity(mat, cos_inc, rng_m)
        points = np.concatenate([p_ego, inten[:, None]], 1).astype(np.float32)
        if return_track_ids:
            return points, self._attr(fr, hits, keep, "track").astype(np.int32)
        return points
