"""Parametric asset library: vehicles, cones, barriers and debris as triangle meshes with per-face materials.

Every asset has a stable id ``"<kind>-<index>"``; its parameters come from a seeded generator, so the
same id gives the identical mesh on every run and machine. Meshes live in the agent local frame.
"""
from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import trimesh

from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, rotmat_from_euler, transform_points
from omniscs.taxonomy import SEMANTIC_IDS


class Material(IntEnum):
    """Surface materials; the renderer turns (material, face colour, face params, hit point) into shading."""

    ASPHALT = 0
    LANE_PAINT = 1
    CONCRETE = 2
    KERB = 3
    FACADE = 4
    ROOF = 5
    METAL = 6
    FOLIAGE = 7
    BARK = 8
    GRASS = 9
    CAR_PAINT = 10
    GLASS = 11
    TYRE = 12
    HEADLIGHT = 13
    TAILLIGHT = 14
    PLASTIC = 15
    CHROME = 16
    LAMP = 17
    PLATE = 18
    CONTAINER = 19
    REFLECTIVE = 20
    SIGN_LIGHT = 21
    ROCK = 22
    WOOD = 23
    SIGNAL = 24


#: Number of float parameters stored per face (meaning depends on the material; see the renderer).
FACE_PARAMS = 4

VEHICLE_SEMANTIC = SEMANTIC_IDS["vehicle"]
OBSTACLE_SEMANTIC = SEMANTIC_IDS["obstacle"]


def srgb(r: float, g: float, b: float) -> np.ndarray:  # 0..255 sRGB -> [3] linear float64
    """Linear-light colour from 8-bit sRGB (the renderer shades in linear light)."""
    c = np.array([r, g, b], dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# ----------------------------------------------------------------------------- mesh kit
@dataclass(frozen=True)
class SurfaceMesh:
    """Triangles with per-face appearance: what both assets and layouts hand to the renderer."""

    vertices: np.ndarray  # [V, 3] float64
    faces: np.ndarray  # [F, 3] int64
    face_colour: np.ndarray  # [F, 3] float32 linear RGB albedo
    face_material: np.ndarray  # [F] uint8 Material
    face_semantic: np.ndarray  # [F] uint8 omniscs.taxonomy semantic id
    face_params: np.ndarray  # [F, FACE_PARAMS] float32 material parameters


class MeshBuilder:
    """Accumulates primitive parts (boxes, prisms, cylinders, blobs) with their appearance."""

    def __init__(self) -> None:
        self._vertices: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self._colour: list[np.ndarray] = []
        self._material: list[np.ndarray] = []
        self._semantic: list[np.ndarray] = []
        self._params: list[np.ndarray] = []
        self._n_vertices = 0

    def add(self, vertices: np.ndarray, faces: np.ndarray, colour, material, semantic,
            params=None) -> None:
        """vertices [V, 3], faces [F, 3]; colour [3] or [F, 3]; material and semantic int or [F];
        params [FACE_PARAMS] or [F, FACE_PARAMS]."""
        vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        n = len(faces)
        self._vertices.append(vertices)
        self._faces.append(faces + self._n_vertices)
        self._n_vertices += len(vertices)
        self._colour.append(np.broadcast_to(np.asarray(colour, dtype=np.float32), (n, 3)))
        self._material.append(np.broadcast_to(np.asarray(material, dtype=np.uint8), (n,)))
        self._semantic.append(np.broadcast_to(np.asarray(semantic, dtype=np.uint8), (n,)))
        p = np.zeros(FACE_PARAMS, dtype=np.float32) if params is None else np.asarray(params, dtype=np.float32)
        self._params.append(np.broadcast_to(p, (n, FACE_PARAMS)))

    def extend(self, mesh: SurfaceMesh) -> None:
        self.add(mesh.vertices, mesh.faces, mesh.face_colour, mesh.face_material, mesh.face_semantic,
                 mesh.face_params)

    def box(self, centre, size, colour, material, semantic: int, R: np.ndarray | None = None,
            side_material: dict[str, int] | None = None, side_colour: dict[str, np.ndarray] | None = None,
            side_semantic: dict[str, int] | None = None, params=None) -> None:
        """Axis-aligned box (then rotated by R about its centre); sides named +x -x +y -y +z -z."""
        h = 0.5 * np.asarray(size, dtype=np.float64)
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
        quads = {"-x": (0, 1, 3, 2), "+x": (4, 6, 7, 5), "-y": (0, 4, 5, 1),
                 "+y": (2, 3, 7, 6), "-z": (0, 2, 6, 4), "+z": (1, 5, 7, 3)}
        faces, mats, cols, sems = [], [], [], []
        for name, (a, b, c, d) in quads.items():
            faces += [(a, b, c), (a, c, d)]
            m = (side_material or {}).get(name, material)
            col = (side_colour or {}).get(name, colour)
            sem = (side_semantic or {}).get(name, semantic)
            mats += [m, m]
            cols += [col, col]
            sems += [sem, sem]
        rot = np.eye(3) if R is None else R
        verts = corners @ rot.T + np.asarray(centre, dtype=np.float64)
        self.add(verts, faces, np.array(cols), np.array(mats), np.array(sems), params)

    def prism(self, profile, lo: float, hi: float, colour, material, semantic: int, axis: int = 1,
              edge_material: list[int] | None = None, edge_colour: list | None = None,
              cap_material: int | None = None, cap_colour=None, params=None) -> None:
        """Extrude a convex polygon (profile [K, 2], in the plane of the two other axes, counter-clockwise)
        from ``lo`` to ``hi`` along ``axis``; edge i joins profile points i and i+1."""
        profile = np.asarray(profile, dtype=np.float64)
        k = len(profile)
        other = [a for a in range(3) if a != axis]
        verts = np.zeros((2 * k, 3))
        verts[:k, other[0]], verts[:k, other[1]], verts[:k, axis] = profile[:, 0], profile[:, 1], lo
        verts[k:, other[0]], verts[k:, other[1]], verts[k:, axis] = profile[:, 0], profile[:, 1], hi
        faces, mats, cols = [], [], []
        cap_m = material if cap_material is None else cap_material
        cap_c = colour if cap_colour is None else cap_colour
        for i in range(1, k - 1):  # fan caps: fine for convex profiles
            faces += [(0, i, i + 1), (k, k + i + 1, k + i)]
            mats += [cap_m, cap_m]
            cols += [cap_c, cap_c]
        for i in range(k):
            j = (i + 1) % k
            faces += [(i, j, k + j), (i, k + j, k + i)]
            m = material if edge_material is None else edge_material[i]
            c = colour if edge_colour is None else edge_colour[i]
            mats += [m, m]
            cols += [c, c]
        self.add(verts, faces, np.array(cols), np.array(mats), semantic, params)

    def cylinder(self, p0, p1, radius: float, colour, material, semantic: int, sections: int = 12,
                 radius1: float | None = None, cap_material: int | None = None, cap_colour=None,
                 params=None) -> None:
        """Capped cylinder (or frustum when ``radius1`` is given) from point p0 to p1."""
        p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
        axis = p1 - p0
        length = np.linalg.norm(axis)
        z = axis / length
        helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        ang = np.linspace(0, 2 * np.pi, sections, endpoint=False)
        r1 = radius if radius1 is None else radius1
        ring = np.cos(ang)[:, None] * x + np.sin(ang)[:, None] * y  # [S, 3]
        verts = np.concatenate([p0 + radius * ring, p1 + r1 * ring, [p0, p1]])
        s = sections
        faces, mats, cols = [], [], []
        cap_m = material if cap_material is None else cap_material
        cap_c = colour if cap_colour is None else cap_colour
        for i in range(s):
            j = (i + 1) % s
            faces += [(i, j, s + j), (i, s + j, s + i), (2 * s, j, i), (2 * s + 1, s + i, s + j)]
            mats += [material, material, cap_m, cap_m]
            cols += [colour, colour, cap_c, cap_c]
        self.add(verts, faces, np.array(cols), np.array(mats), semantic, params)

    def blob(self, centre, radii, rng: np.random.Generator, colour, material, semantic: int,
             subdivisions: int = 1, roughness: float = 0.15, params=None) -> None:
        """A lumpy ellipsoid (rocks, foliage): an icosphere with seeded radial noise."""
        sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
        v = np.asarray(sphere.vertices, dtype=np.float64)
        v = v * (1.0 + roughness * rng.uniform(-1.0, 1.0, size=(len(v), 1)))
        self.add(v * np.asarray(radii, dtype=np.float64) + np.asarray(centre, dtype=np.float64),
                 np.asarray(sphere.faces), colour, material, semantic, params)

    def build(self) -> SurfaceMesh:
        if not self._faces:
            return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32),
                               np.zeros(0, np.uint8), np.zeros(0, np.uint8), np.zeros((0, FACE_PARAMS), np.float32))
        return SurfaceMesh(
            vertices=np.concatenate(self._vertices),
            faces=np.concatenate(self._faces),
            face_colour=np.ascontiguousarray(np.concatenate(self._colour)),
            face_material=np.ascontiguousarray(np.concatenate(self._material)),
            face_semantic=np.ascontiguousarray(np.concatenate(self._semantic)),
            face_params=np.ascontiguousarray(np.concatenate(self._params)),
        )


def oriented_box_between(b: MeshBuilder, start, end, width: float, thickness: float, colour, material,
                         semantic: int) -> None:
    """A beam from ``start`` to ``end`` (points in the x-z plane at some y), width along y."""
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    d = end - start
    length = float(np.linalg.norm(d))
    pitch = -np.arctan2(d[2], d[0])  # positive pitch tilts +x downwards
    b.box(0.5 * (start + end), (length, width, thickness), colour, material, semantic,
          R=rotmat_from_euler(pitch=pitch))


# ----------------------------------------------------------------------------- palettes
CAR_PAINTS = [srgb(*c) for c in (
    (236, 236, 232), (22, 22, 24), (172, 174, 178), (96, 99, 104), (28, 42, 88), (158, 22, 28),
    (34, 62, 44), (192, 178, 148), (44, 92, 172), (226, 186, 34), (206, 98, 28), (92, 58, 38),
    (120, 20, 40), (60, 110, 140), (210, 210, 200),
)]
#: Paint popularity (white, black, silver and grey dominate real traffic).
CAR_PAINT_WEIGHTS = np.array([18, 16, 14, 12, 6, 6, 3, 3, 5, 2, 2, 2, 3, 3, 5], dtype=np.float64)
WORK_PAINTS = [srgb(*c) for c in ((236, 178, 20), (232, 132, 20), (214, 190, 40), (200, 60, 30))]
CONTAINER_PAINTS = [srgb(*c) for c in (
    (150, 52, 36), (36, 70, 130), (40, 110, 70), (130, 130, 128), (210, 110, 30), (220, 220, 214),
    (160, 30, 30), (60, 60, 64),
)]
GLASS_TINTS = [srgb(*c) for c in ((30, 38, 46), (22, 26, 30), (40, 52, 58))]
TYRE_BLACK = srgb(24, 24, 24)
TRIM_BLACK = srgb(30, 30, 32)
RIM_SILVER = srgb(180, 182, 186)
RIM_DARK = srgb(60, 60, 64)
HEADLIGHT_WHITE = srgb(235, 235, 225)
TAILLIGHT_RED = srgb(170, 16, 16)
PLATE_WHITE = srgb(230, 230, 220)
CONE_ORANGE = srgb(240, 90, 20)
REFLECTIVE_WHITE = srgb(240, 240, 240)
CONCRETE_GREY = srgb(170, 168, 160)
WOOD_BROWN = srgb(150, 110, 70)
ROCK_GREY = srgb(110, 106, 100)
LEAF_GREEN = srgb(70, 100, 40)
SIGN_AMBER = srgb(250, 170, 40)


def _pick(rng: np.random.Generator, options: list, weights: np.ndarray | None = None) -> np.ndarray:
    p = None if weights is None else weights / weights.sum()
    return options[int(rng.choice(len(options), p=p))]


def _jitter(rng: np.random.Generator, colour: np.ndarray, amount: float = 0.06) -> np.ndarray:
    return np.clip(colour * (1.0 + amount * rng.uniform(-1, 1, 3)), 0.0, 1.0)


# ----------------------------------------------------------------------------- builders
def _wheels(b: MeshBuilder, axles_x: list[float], half_width: float, radius: float, tyre_width: float,
            rim_colour: np.ndarray, sections: int = 14) -> None:
    """Wheels just outboard of the body sides (so their discs show), resting on z = 0."""
    for x in axles_x:
        for side in (1.0, -1.0):
            outer = side * (half_width + 0.01)
            inner = side * (half_width + 0.01 - tyre_width)
            b.cylinder((x, inner, radius), (x, outer, radius), radius, TYRE_BLACK, Material.TYRE,
                       VEHICLE_SEMANTIC, sections=sections)
            b.cylinder((x, outer, radius), (x, outer + side * 0.012, radius), 0.58 * radius, rim_colour,
                       Material.CHROME, VEHICLE_SEMANTIC, sections=sections)


def _lights(b: MeshBuilder, x_front: float, x_rear: float, half_width: float, z_head: float,
            z_tail: float, head_size: tuple, tail_size: tuple, plate: bool = True) -> None:
    for side in (1.0, -1.0):
        y_h = side * (half_width - 0.06 - head_size[1] / 2)
        b.box((x_front - head_size[0] / 2 + 0.02, y_h, z_head), head_size, HEADLIGHT_WHITE,
              Material.HEADLIGHT, VEHICLE_SEMANTIC)
        y_t = side * (half_width - 0.04 - tail_size[1] / 2)
        b.box((x_rear + tail_size[0] / 2 - 0.02, y_t, z_tail), tail_size, TAILLIGHT_RED,
              Material.TAILLIGHT, VEHICLE_SEMANTIC)
    if plate:
        b.box((x_rear - 0.005, 0.0, z_tail - 0.12), (0.03, 0.52, 0.12), PLATE_WHITE, Material.PLATE,
              VEHICLE_SEMANTIC)
        b.box((x_front + 0.005, 0.0, z_head - 0.16), (0.03, 0.52, 0.12), PLATE_WHITE, Material.PLATE,
              VEHICLE_SEMANTIC)


def _car_params(rng: np.random.Generator, kind: str) -> dict:
    """Dimensions (metres) and styling of the four car-like kinds."""
    u = rng.uniform
    if kind == "sedan":
        p = dict(length=u(4.1, 5.0), width=u(1.72, 1.90), height=u(1.38, 1.52), clearance=u(0.13, 0.19),
                 wheel_r=u(0.30, 0.34), belt=u(0.80, 0.92), hood=u(0.95, 1.35), screen=u(0.60, 0.85))
        hatch = rng.uniform() < 0.35
        p.update(deck=u(0.10, 0.25) if hatch else u(0.55, 0.90), rear=u(0.25, 0.40) if hatch else u(0.45, 0.70))
    elif kind == "suv":
        p = dict(length=u(4.3, 5.1), width=u(1.80, 2.00), height=u(1.62, 1.90), clearance=u(0.18, 0.26),
                 wheel_r=u(0.34, 0.40), belt=u(0.95, 1.10), hood=u(0.95, 1.25), screen=u(0.45, 0.65),
                 deck=u(0.05, 0.15), rear=u(0.10, 0.22))
    elif kind == "van":
        p = dict(length=u(4.8, 6.2), width=u(1.90, 2.05), height=u(1.95, 2.60), clearance=u(0.16, 0.22),
                 wheel_r=u(0.32, 0.37), belt=u(0.95, 1.10), hood=u(0.45, 0.85), screen=u(0.55, 0.85),
                 deck=u(0.02, 0.06), rear=u(0.0, 0.05))
    elif kind == "pickup":
        p = dict(length=u(5.0, 5.9), width=u(1.85, 2.05), height=u(1.75, 1.95), clearance=u(0.22, 0.30),
                 wheel_r=u(0.37, 0.42), belt=u(1.05, 1.20), hood=u(1.30, 1.60), screen=u(0.40, 0.55),
                 deck=u(1.55, 2.10), rear=u(0.05, 0.12))
    else:
        raise OmniscsError(f"internal: {kind!r} is not a car-like kind")
    p.update(
        paint=_jitter(rng, _pick(rng, CAR_PAINTS, CAR_PAINT_WEIGHTS)),
        glass=_pick(rng, GLASS_TINTS),
        rim=RIM_SILVER if rng.uniform() < 0.7 else RIM_DARK,
        nose=u(0.10, 0.22),
        tumble=u(0.06, 0.14),
        front_overhang=u(0.80, 1.00),
        rear_overhang=u(0.75, 1.05),
        head_w=u(0.28, 0.45),
        head_h=u(0.07, 0.14),
        roof_rack=bool(kind in ("suv", "van") and rng.uniform() < 0.35),
        two_tone=bool(rng.uniform() < 0.12),
        cargo_panel=bool(kind == "van" and rng.uniform() < 0.6),
        trim=bool(rng.uniform() < 0.5),
    )
    return p


def _build_car(b: MeshBuilder, p: dict, kind: str) -> None:
    L, W, H = p["length"], p["width"], p["height"]
    c, hb, nose = p["clearance"], p["belt"], p["nose"]
    xf, xr = L / 2, -L / 2
    paint, glass = p["paint"], p["glass"]
    sem = VEHICLE_SEMANTIC
    lower = [(xr + 0.10, c), (xf - 0.15, c), (xf, c + 0.15), (xf, hb - nose),
             (xf - 0.35, hb - 0.02), (xr + 0.12, hb), (xr, hb - 0.08), (xr, c + 0.12)]
    b.prism(lower, -W / 2, W / 2, paint, Material.CAR_PAINT, sem)
    # Greenhouse: windscreen (edge 1) and rear window (edge 3) are glass, the roof (edge 2) is paint.
    base_front = xf - p["hood"]
    base_rear = xr + p["deck"]
    top_front = base_front - p["screen"]
    top_rear = min(base_rear + p["rear"], top_front - 0.4)
    cabin = [(base_rear, hb - 0.03), (base_front, hb - 0.03), (top_front, H), (top_rear, H)]
    cw = W - 2 * p["tumble"]
    roof = srgb(235, 235, 232) if p["two_tone"] else paint
    b.prism(cabin, -cw / 2, cw / 2, paint, Material.CAR_PAINT, sem,
            edge_material=[Material.CAR_PAINT, Material.GLASS, Material.CAR_PAINT, Material.GLASS],
            edge_colour=[paint, glass, roof, glass], cap_material=Material.GLASS, cap_colour=glass)
    # Pillars poke through the side glass so windows read as separate panes.
    frac = np.linspace(0.0, 1.0, 5)[1:-1] if p["length"] > 5.2 else [0.5]
    for f in frac:
        xb = base_rear + f * (base_front - base_rear)
        z_top = H - 0.03
        b.box((xb, 0, 0.5 * (hb + z_top)), (0.10, cw + 0.012, z_top - hb), paint, Material.CAR_PAINT, sem)
    if p["cargo_panel"]:  # panel van: no rear side windows
        x0, x1 = base_rear, base_rear + 0.62 * (base_front - base_rear)
        b.box((0.5 * (x0 + x1), 0, 0.5 * (hb + H - 0.05)), (x1 - x0, cw + 0.014, H - 0.05 - hb), paint,
              Material.CAR_PAINT, sem)
    if kind == "pickup":  # open bed walls on top of the lower body
        bed_top = hb + 0.42
        for side in (1.0, -1.0):
            b.box((0.5 * (xr + base_rear), side * (W / 2 - 0.04), 0.5 * (hb + bed_top)),
                  (base_rear - xr, 0.08, bed_top - hb), paint, Material.CAR_PAINT, sem)
        b.box((xr + 0.04, 0, 0.5 * (hb + bed_top)), (0.08, W - 0.02, bed_top - hb), paint, Material.CAR_PAINT, sem)
    if p["roof_rack"]:
        for side in (1.0, -1.0):
            b.box((0.5 * (top_front + top_rear), side * (cw / 2 - 0.08), H + 0.04),
                  (top_front - top_rear - 0.1, 0.04, 0.08), TRIM_BLACK, Material.PLASTIC, sem)
    if p["trim"]:  # dark bumpers
        b.box((xf - 0.06, 0, c + 0.12), (0.14, W - 0.06, 0.14), TRIM_BLACK, Material.PLASTIC, sem)
        b.box((xr + 0.06, 0, c + 0.14), (0.14, W - 0.06, 0.14), TRIM_BLACK, Material.PLASTIC, sem)
    b.box((xf - 0.01, 0, hb - nose - 0.10), (0.04, 0.40 * W, 0.12), TRIM_BLACK, Material.PLASTIC, sem)  # grille
    _lights(b, xf, xr, W / 2, hb - nose - 0.07, hb - 0.14, (0.08, p["head_w"], p["head_h"]), (0.08, 0.30, 0.12))
    _wheels(b, [xf - p["front_overhang"], xr + p["rear_overhang"]], W / 2, p["wheel_r"], 0.22, p["rim"])


def _box_truck_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    return dict(length=u(6.5, 9.5), width=u(2.30, 2.50), cab_len=u(1.8, 2.3), cab_h=u(2.6, 3.1),
                box_h=u(3.2, 3.9), wheel_r=u(0.45, 0.52), cab_paint=_jitter(rng, _pick(rng, CAR_PAINTS, CAR_PAINT_WEIGHTS)),
                box_paint=_jitter(rng, srgb(232, 232, 228) if u() < 0.6 else _pick(rng, CAR_PAINTS)),
                stripe=_pick(rng, CAR_PAINTS) if u() < 0.5 else None, tandem=bool(u() < 0.4),
                glass=_pick(rng, GLASS_TINTS), stripe_h=u(0.3, 0.8))


def _build_box_truck(b: MeshBuilder, p: dict) -> None:
    L, W = p["length"], p["width"]
    xf, xr = L / 2, -L / 2
    sem, r = VEHICLE_SEMANTIC, p["wheel_r"]
    cab_x0 = xf - p["cab_len"]
    chassis_top = 1.0
    b.box((0, 0, 0.75), (L - 0.4, W - 0.7, 0.5), TRIM_BLACK, Material.METAL, sem)  # chassis rails
    cab = [(cab_x0, 0.55), (xf, 0.55), (xf, p["cab_h"] - 0.35), (xf - 0.25, p["cab_h"]), (cab_x0, p["cab_h"])]
    b.prism(cab, -W / 2, W / 2, p["cab_paint"], Material.CAR_PAINT, sem)
    zg0, zg1 = 0.55 * p["cab_h"], p["cab_h"] - 0.38
    b.box((xf + 0.005, 0, 0.5 * (zg0 + zg1)), (0.02, W - 0.30, zg1 - zg0), p["glass"], Material.GLASS, sem)
    for side in (1.0, -1.0):
        b.box((xf - 0.6 * p["cab_len"] / 2 - 0.1, side * (W / 2 + 0.004), 0.5 * (zg0 + zg1)),
              (0.55 * p["cab_len"], 0.012, zg1 - zg0), p["glass"], Material.GLASS, sem)
    box_x1 = cab_x0 - 0.12
    bw = W - 0.02
    b.box((0.5 * (xr + box_x1), 0, 0.5 * (chassis_top + p["box_h"])), (box_x1 - xr, bw, p["box_h"] - chassis_top),
          p["box_paint"], Material.CAR_PAINT, sem)
    if p["stripe"] is not None:
        z0 = chassis_top + 0.4
        for side in (1.0, -1.0):
            b.box((0.5 * (xr + box_x1), side * (bw / 2 + 0.004), z0 + p["stripe_h"] / 2),
                  (box_x1 - xr - 0.4, 0.01, p["stripe_h"]), p["stripe"], Material.CAR_PAINT, sem)
    b.box((xr - 0.004, 0, 0.5 * (chassis_top + p["box_h"])), (0.012, 0.04, p["box_h"] - chassis_top - 0.2),
          TRIM_BLACK, Material.METAL, sem)  # rear door seam
    b.box((xf - 0.05, 0, 0.70), (0.14, W - 0.04, 0.28), TRIM_BLACK, Material.PLASTIC, sem)  # bumper
    b.box((xr + 0.08, 0, 0.55), (0.10, W - 0.3, 0.10), TRIM_BLACK, Material.METAL, sem)  # underride guard
    _lights(b, xf, xr, W / 2, 1.0, 0.85, (0.08, 0.30, 0.16), (0.08, 0.22, 0.16))
    rear = [xr + 1.6] if not p["tandem"] else [xr + 1.3, xr + 2.4]
    _wheels(b, [xf - 1.1] + rear, W / 2 - 0.03, r, 0.30, RIM_SILVER)


def _bus_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    liveries = [srgb(*c) for c in ((220, 40, 30), (240, 240, 236), (30, 90, 170), (240, 200, 30),
                                   (40, 140, 80), (120, 120, 124))]
    return dict(length=u(10.0, 13.2), width=u(2.48, 2.56), height=u(2.95, 3.40), wheel_r=u(0.48, 0.53),
                paint=_jitter(rng, _pick(rng, liveries)), stripe=_pick(rng, liveries), glass=_pick(rng, GLASS_TINTS),
                window_bottom=u(1.15, 1.40), ac_len=u(1.5, 3.0), doors=int(rng.integers(2, 4)))


def _build_bus(b: MeshBuilder, p: dict) -> None:
    L, W, H = p["length"], p["width"], p["height"]
    xf, xr = L / 2, -L / 2
    sem = VEHICLE_SEMANTIC
    body = [(xr, 0.32), (xf, 0.32), (xf, H - 0.25), (xf - 0.2, H), (xr + 0.1, H), (xr, H - 0.15)]
    b.prism(body, -W / 2, W / 2, p["paint"], Material.CAR_PAINT, sem)
    z0, z1 = p["window_bottom"], H - 0.35
    for side in (1.0, -1.0):
        b.box((0.5 * (xr + 0.6 + xf - 0.5), side * (W / 2 + 0.004), 0.5 * (z0 + z1)),
              (xf - 0.5 - xr - 0.6, 0.012, z1 - z0), p["glass"], Material.GLASS, sem)
        b.box((0, side * (W / 2 + 0.004), 0.55), (L - 0.3, 0.012, 0.25), p["stripe"], Material.CAR_PAINT, sem)
    b.box((xf + 0.004, 0, 0.5 * (0.95 + H - 0.45)), (0.012, W - 0.2, H - 0.45 - 0.95), p["glass"], Material.GLASS, sem)
    b.box((xf + 0.006, 0, H - 0.33), (0.012, W - 0.5, 0.22), SIGN_AMBER, Material.SIGN_LIGHT, sem)
    b.box((xr - 0.004, 0, 0.5 * (z0 + 0.3 + z1)), (0.012, W - 0.5, z1 - z0 - 0.3), p["glass"], Material.GLASS, sem)
    door_x = np.linspace(xf - 1.2, xr + 3.5, p["doors"])
    for x in door_x:  # doors on the kerb (right, -y) side
        b.box((x, -(W / 2 + 0.008), 0.5 * (0.35 + z1)), (1.1, 0.012, z1 - 0.35), p["glass"], Material.GLASS, sem)
    b.box((xr + 0.3 + p["ac_len"] / 2 + 2.0, 0, H + 0.15), (p["ac_len"], 1.6, 0.3), srgb(200, 200, 200),
          Material.METAL, sem)
    _lights(b, xf, xr, W / 2, 0.75, 0.9, (0.08, 0.35, 0.18), (0.08, 0.22, 0.35))
    _wheels(b, [xf - 2.5, xr + 3.0], W / 2 - 0.06, p["wheel_r"], 0.32, RIM_SILVER)


def _trailer_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    container = bool(u() < 0.6)
    return dict(length=u(6.0, 13.6), width=u(2.44, 2.55), box_h=u(2.59, 2.90), deck=u(1.15, 1.35),
                wheel_r=u(0.47, 0.52), axles=int(rng.integers(1, 4)), container=container,
                paint=_jitter(rng, _pick(rng, CONTAINER_PAINTS) if container else srgb(236, 236, 232)),
                rib=u(0.25, 0.35))


def _build_trailer(b: MeshBuilder, p: dict) -> None:
    L, W = p["length"], p["width"]
    xf, xr = L / 2, -L / 2
    sem, deck = VEHICLE_SEMANTIC, p["deck"]
    top = deck + p["box_h"]
    mat = Material.CONTAINER if p["container"] else Material.CAR_PAINT
    b.box((0, 0, 0.5 * (deck + top)), (L, W, p["box_h"]), p["paint"], mat, sem, params=(p["rib"], 0, 0, 0))
    b.box((0, 0, deck - 0.15), (L - 0.1, W - 0.5, 0.3), TRIM_BLACK, Material.METAL, sem)  # chassis
    if p["container"]:
        for y in (-0.45, -0.15, 0.15, 0.45):  # door locking bars
            b.box((xr - 0.01, y * W, 0.5 * (deck + top)), (0.03, 0.05, p["box_h"] - 0.2), RIM_DARK, Material.METAL, sem)
    for side in (1.0, -1.0):  # landing gear near the front
        b.box((xf - 2.0, side * (W / 2 - 0.5), 0.5 * (deck - 0.3)), (0.14, 0.14, deck - 0.3), RIM_DARK, Material.METAL, sem)
    b.box((xr + 0.1, 0, 0.55), (0.12, W - 0.3, 0.12), TRIM_BLACK, Material.METAL, sem)  # underride guard
    for side in (1.0, -1.0):
        b.box((xr - 0.02, side * (W / 2 - 0.2), 0.8), (0.06, 0.25, 0.14), TAILLIGHT_RED, Material.TAILLIGHT, sem)
    axles = [xr + 1.2 + 1.3 * i for i in range(p["axles"])]
    _wheels(b, axles, W / 2 - 0.06, p["wheel_r"], 0.32, RIM_SILVER)


def _excavator_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    return dict(track_len=u(3.4, 4.6), width=u(2.5, 3.2), house_len=u(2.8, 3.6), house_h=u(1.0, 1.3),
                boom_len=u(4.0, 5.6), boom_deg=u(25, 50), arm_len=u(2.2, 3.0), arm_deg=u(40, 75),
                paint=_jitter(rng, _pick(rng, WORK_PAINTS)), glass=_pick(rng, GLASS_TINTS))


def _build_excavator(b: MeshBuilder, p: dict) -> None:
    W, sem, paint = p["width"], VEHICLE_SEMANTIC, p["paint"]
    tl = p["track_len"]
    for side in (1.0, -1.0):
        b.box((0, side * (W / 2 - 0.3), 0.42), (tl, 0.6, 0.84), TYRE_BLACK, Material.TYRE, sem)
    b.box((0, 0, 0.9), (tl * 0.5, W - 1.1, 0.3), RIM_DARK, Material.METAL, sem)
    hz0 = 1.05
    hz1 = hz0 + p["house_h"]
    hl = p["house_len"]
    b.box((-0.4, 0, 0.5 * (hz0 + hz1)), (hl, W * 0.92, hz1 - hz0), paint, Material.CAR_PAINT, sem)
    b.box((-0.4 - hl / 2 + 0.35, 0, hz1 + 0.25), (0.7, W * 0.9, 0.5), RIM_DARK, Material.METAL, sem)  # counterweight
    cab_x = -0.4 + hl / 2 - 0.6
    cab_y = W * 0.46 - 0.5
    cab_top = hz1 + 1.55
    b.box((cab_x, cab_y, 0.5 * (hz1 + cab_top)), (1.1, 0.95, cab_top - hz1), paint, Material.CAR_PAINT, sem)
    b.box((cab_x + 0.56, cab_y, hz1 + 0.9), (0.012, 0.8, 1.1), p["glass"], Material.GLASS, sem)
    b.box((cab_x, cab_y + 0.48, hz1 + 0.9), (0.9, 0.012, 1.0), p["glass"], Material.GLASS, sem)
    pivot = np.array([-0.4 + hl / 2 - 0.2, -0.25, hz1 - 0.1])
    boom_dir = np.array([np.cos(np.radians(p["boom_deg"])), 0.0, np.sin(np.radians(p["boom_deg"]))])
    boom_tip = pivot + p["boom_len"] * boom_dir
    arm_dir = np.array([np.cos(np.radians(p["arm_deg"])), 0.0, -np.sin(np.radians(p["arm_deg"]))])
    arm_tip = boom_tip + p["arm_len"] * arm_dir
    arm_tip[2] = max(arm_tip[2], 0.9)  # the bucket stays above ground
    oriented_box_between(b, pivot, boom_tip, 0.45, 0.55, paint, Material.CAR_PAINT, sem)
    oriented_box_between(b, boom_tip, arm_tip, 0.35, 0.40, paint, Material.CAR_PAINT, sem)
    b.box((arm_tip[0] + 0.2, pivot[1], arm_tip[2] - 0.4), (0.8, 0.95, 0.8), RIM_DARK, Material.METAL, sem,
          R=rotmat_from_euler(pitch=np.radians(-20)))


def _loader_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    return dict(length=u(6.0, 8.0), width=u(2.4, 2.9), wheel_r=u(0.70, 0.85), cab_h=u(3.1, 3.5),
                bucket_z=u(0.05, 1.2), paint=_jitter(rng, _pick(rng, WORK_PAINTS)), glass=_pick(rng, GLASS_TINTS))


def _build_wheel_loader(b: MeshBuilder, p: dict) -> None:
    L, W, r = p["length"], p["width"], p["wheel_r"]
    xf, xr = L / 2, -L / 2
    sem, paint = VEHICLE_SEMANTIC, p["paint"]
    body_w = W - 0.75
    b.box((xr + 1.4, 0, 1.35), (2.6, body_w, 1.3), paint, Material.CAR_PAINT, sem)  # engine / rear body
    b.box((xr + 3.2, 0, 1.0), (1.4, body_w * 0.7, 0.9), RIM_DARK, Material.METAL, sem)  # articulation
    b.box((xr + 4.3, 0, 1.15), (1.5, body_w, 0.9), paint, Material.CAR_PAINT, sem)  # front frame
    cab_x = xr + 2.9
    b.box((cab_x, 0, 0.5 * (2.0 + p["cab_h"])), (1.3, 1.2, p["cab_h"] - 2.0), paint, Material.CAR_PAINT, sem)
    for sx in (1.0, -1.0):
        b.box((cab_x + sx * 0.656, 0, 0.5 * (2.2 + p["cab_h"] - 0.1)), (0.012, 1.0, p["cab_h"] - 2.4),
              p["glass"], Material.GLASS, sem)
        b.box((cab_x, sx * 0.606, 0.5 * (2.2 + p["cab_h"] - 0.1)), (1.1, 0.012, p["cab_h"] - 2.4),
              p["glass"], Material.GLASS, sem)
    bucket_x = xf - 0.55
    bz = p["bucket_z"]
    for side in (1.0, -1.0):
        oriented_box_between(b, (xr + 4.0, side * 0.55, 1.6), (bucket_x - 0.3, side * 0.55, bz + 0.6),
                             0.2, 0.3, paint, Material.CAR_PAINT, sem)
    b.box((bucket_x, 0, bz + 0.5), (1.1, W - 0.04, 1.0), RIM_DARK, Material.METAL, sem)
    _wheels(b, [xr + 1.3, xr + 4.4], body_w / 2 + 0.33, r, 0.55, paint, sections=16)


def _cone_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    return dict(height=u(0.45, 1.0), base=u(0.32, 0.50), radius=u(0.12, 0.20), bands=int(rng.integers(1, 3)),
                colour=_jitter(rng, CONE_ORANGE if u() < 0.8 else srgb(220, 40, 30)))


def _build_cone(b: MeshBuilder, p: dict) -> None:
    sem, h, r = OBSTACLE_SEMANTIC, p["height"], p["radius"]
    b.box((0, 0, 0.02), (p["base"], p["base"], 0.04), p["colour"], Material.PLASTIC, sem)
    top_r = 0.025
    b.cylinder((0, 0, 0.04), (0, 0, h), r, p["colour"], Material.PLASTIC, sem, sections=12, radius1=top_r)
    for i in range(p["bands"]):
        z0 = 0.04 + (0.45 + 0.2 * i) * (h - 0.04)
        z1 = z0 + 0.12 * (h - 0.04)
        ra = r + (top_r - r) * (z0 - 0.04) / (h - 0.04) + 0.004
        rb = r + (top_r - r) * (z1 - 0.04) / (h - 0.04) + 0.004
        b.cylinder((0, 0, z0), (0, 0, z1), ra, REFLECTIVE_WHITE, Material.REFLECTIVE, sem, sections=12, radius1=rb)


def _barrier_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    style = ["jersey", "plastic", "aframe"][int(rng.integers(0, 3))]
    return dict(style=style, length=u(1.2, 4.0), height=u(0.8, 1.1), base=u(0.45, 0.7), stripes=int(rng.integers(3, 7)),
                colour=_jitter(rng, CONCRETE_GREY if style == "jersey" else
                               (srgb(200, 30, 30) if u() < 0.6 else srgb(236, 236, 236))))


def _build_barrier(b: MeshBuilder, p: dict) -> None:
    sem, L, H, base = OBSTACLE_SEMANTIC, p["length"], p["height"], p["base"]
    if p["style"] in ("jersey", "plastic"):
        top = 0.3 * base
        profile = [(-base / 2, 0), (base / 2, 0), (base / 2, 0.08), (top / 2 + 0.08, 0.3), (top / 2, H),
                   (-top / 2, H), (-top / 2 - 0.08, 0.3), (-base / 2, 0.08)]
        mat = Material.CONCRETE if p["style"] == "jersey" else Material.PLASTIC
        b.prism(profile, -L / 2, L / 2, p["colour"], mat, sem, axis=0)
        if p["style"] == "jersey":
            b.box((0, base / 2 - 0.01, 0.18), (L * 0.9, 0.02, 0.1), REFLECTIVE_WHITE, Material.REFLECTIVE, sem)
        return
    for x in (-L / 2 + 0.1, L / 2 - 0.1):  # A-frame legs and striped boards
        for side in (1.0, -1.0):
            oriented = rotmat_from_euler(roll=side * np.radians(15))
            b.box((x, side * 0.12, H / 2), (0.06, 0.05, H), RIM_DARK, Material.METAL, sem, R=oriented)
    n = p["stripes"]
    seg = (L - 0.05) / n
    for board_z in (H - 0.15, H - 0.5):
        for i in range(n):
            col = p["colour"] if i % 2 == 0 else REFLECTIVE_WHITE
            mat = Material.PLASTIC if i % 2 == 0 else Material.REFLECTIVE
            b.box((-L / 2 + 0.025 + seg * (i + 0.5), 0, board_z), (seg, 0.04, 0.22), col, mat, sem)
    b.box((0, 0, 0.02), (L, base, 0.04), RIM_DARK, Material.METAL, sem)


def _debris_params(rng: np.random.Generator) -> dict:
    u = rng.uniform
    style = ["rocks", "tyre", "crates", "branch", "bags"][int(rng.integers(0, 5))]
    return dict(style=style, scale=u(0.5, 1.4), count=int(rng.integers(1, 5)), sub_seed=int(rng.integers(0, 2**31)))


def _build_debris(b: MeshBuilder, p: dict) -> None:
    sem, s = OBSTACLE_SEMANTIC, p["scale"]
    rng = np.random.default_rng(p["sub_seed"])
    style = p["style"]
    if style == "rocks":
        for _ in range(p["count"]):
            rad = s * rng.uniform(0.15, 0.45, 3) * np.array([1.0, 1.0, 0.7])
            c = (rng.uniform(-0.6, 0.6) * s, rng.uniform(-0.4, 0.4) * s, rad[2] * 0.8)
            b.blob(c, rad, rng, _jitter(rng, ROCK_GREY, 0.2), Material.ROCK, sem, subdivisions=1, roughness=0.25)
    elif style == "tyre":
        r = 0.3 + 0.15 * s
        b.cylinder((0, 0, 0), (0, 0, 0.22), r, TYRE_BLACK, Material.TYRE, sem, sections=16)
        b.cylinder((0, 0, 0.22), (0, 0, 0.225), 0.55 * r, RIM_DARK, Material.METAL, sem, sections=16)
    elif style == "crates":
        z = 0.0
        for i in range(p["count"]):
            size = s * rng.uniform(0.35, 0.8, 3)
            yaw = rng.uniform(-0.5, 0.5)
            off = rng.uniform(-0.3, 0.3, 2) * s if i else np.zeros(2)
            colour = _jitter(rng, WOOD_BROWN if rng.uniform() < 0.6 else srgb(170, 140, 100), 0.15)
            b.box((off[0], off[1], z + size[2] / 2), size, colour, Material.WOOD, sem, R=rotmat_from_euler(yaw=yaw))
            z += size[2] if rng.uniform() < 0.5 else 0.0
    elif style == "branch":
        length = 1.2 + 1.5 * s
        b.cylinder((-length / 2, 0, 0.08), (length / 2, 0.1, 0.12), 0.07 * s + 0.03, srgb(90, 65, 45), Material.BARK,
                   sem, sections=8)
        for _ in range(p["count"]):
            x = rng.uniform(-length / 3, length / 2)
            b.blob((x, rng.uniform(-0.3, 0.3), 0.3 * s), (0.5 * s, 0.4 * s, 0.3 * s), rng,
                   _jitter(rng, LEAF_GREEN, 0.2), Material.FOLIAGE, sem, subdivisions=1, roughness=0.3)
    else:  # bags / a dumped bin
        for _ in range(p["count"]):
            rad = s * rng.uniform(0.2, 0.35, 3)
            c = (rng.uniform(-0.5, 0.5) * s, rng.uniform(-0.3, 0.3) * s, rad[2])
            b.blob(c, rad, rng, srgb(30, 30, 34) if rng.uniform() < 0.6 else srgb(40, 70, 140),
                   Material.PLASTIC, sem, subdivisions=1, roughness=0.2)


# ----------------------------------------------------------------------------- library
@dataclass(frozen=True)
class AssetKind:
    """One family of assets: how many instances, which taxonomy category, how to make them.

    Instances ``0 .. count-1`` are the *world* split (what procedural worlds place); the next ``pool_count``
    are the *pool* split, made only into pool models, so that benchmark worlds hold vehicles no pool model
    was built from. The world split is the library as it was before the pool split existed: every world is
    unchanged by it."""

    count: int
    category: str
    make_params: object  # Callable[[np.random.Generator], dict]
    build: object  # Callable[[MeshBuilder, dict], None]
    pool_count: int = 0


def _car_kind(kind: str, count: int, pool_count: int) -> AssetKind:
    return AssetKind(count, "car", lambda rng: _car_params(rng, kind), lambda b, p: _build_car(b, p, kind), pool_count)


#: The asset families and their instance counts (world ids run from ``<kind>-0000`` to ``<kind>-<count-1>``,
#: pool ids on from there: ``<kind>-<count>`` to ``<kind>-<count+pool_count-1>``).
ASSET_KINDS: dict[str, AssetKind] = {
    "sedan": _car_kind("sedan", 45, 250),
    "suv": _car_kind("suv", 35, 200),
    "van": _car_kind("van", 25, 120),
    "pickup": _car_kind("pickup", 20, 100),
    "box_truck": AssetKind(20, "truck", _box_truck_params, _build_box_truck, 60),
    "bus": AssetKind(12, "bus", _bus_params, _build_bus, 40),
    "trailer": AssetKind(15, "trailer", _trailer_params, _build_trailer, 40),
    "excavator": AssetKind(8, "construction_vehicle", _excavator_params, _build_excavator, 12),
    "wheel_loader": AssetKind(8, "construction_vehicle", _loader_params, _build_wheel_loader, 12),
    "traffic_cone": AssetKind(12, "traffic_cone", _cone_params, _build_cone),
    "barrier": AssetKind(12, "barrier", _barrier_params, _build_barrier),
    "debris": AssetKind(18, "debris", _debris_params, _build_debris),
}


@dataclass(frozen=True)
class Asset:
    """A built asset in the agent local frame (x forward, y left, z up; origin at the box centre).

    The mesh exactly fills its box: its bounds are ``[-size/2, size/2]``. Arrays are shared through a
    cache: treat them as read-only.
    """

    asset_id: str
    kind: str
    category: str
    size: np.ndarray  # [3] float64 (length, width, height)
    surface: SurfaceMesh  # per-face appearance for the renderer
    params: dict  # the generator parameters (dimensions, colours, style flags)

    @property
    def mesh(self) -> trimesh.Trimesh:
        """The geometry as a trimesh (faces in the same order as ``surface``)."""
        return trimesh.Trimesh(self.surface.vertices, self.surface.faces, process=False)


def _parse_id(asset_id: str) -> tuple[str, int]:
    if not isinstance(asset_id, str) or "-" not in asset_id:
        raise OmniscsError(f"bad asset id {asset_id!r}; ids look like 'sedan-0007' (see list_asset_ids())")
    kind, _, index = asset_id.rpartition("-")
    if kind not in ASSET_KINDS or not index.isdigit() or len(index) != 4:
        raise OmniscsError(f"unknown asset id {asset_id!r}; kinds are {sorted(ASSET_KINDS)}, ids look like 'sedan-0007'")
    i = int(index)
    total = ASSET_KINDS[kind].count + ASSET_KINDS[kind].pool_count
    if i >= total:
        raise OmniscsError(f"asset id {asset_id!r} is out of range; {kind} has {total} "
                           f"instances ({kind}-0000..{kind}-{total - 1:04d})")
    return kind, i


#: The library's splits: 'world' (what procedural worlds place), 'pool' (only ever made into pool models), 'all'.
SPLITS = ("world", "pool", "all")


def list_asset_ids(kind: str | None = None, split: str = "world") -> list[str]:
    """Every asset id of a split (or those of one kind), in a stable order."""
    if kind is not None and kind not in ASSET_KINDS:
        raise OmniscsError(f"unknown asset kind {kind!r}; use one of {sorted(ASSET_KINDS)}")
    if split not in SPLITS:
        raise OmniscsError(f"unknown asset split {split!r}; use one of {list(SPLITS)}")
    kinds = [kind] if kind else list(ASSET_KINDS)
    ids = []
    for k in kinds:
        world, pool = ASSET_KINDS[k].count, ASSET_KINDS[k].pool_count
        lo = world if split == "pool" else 0
        hi = world if split == "world" else world + pool
        ids += [f"{k}-{i:04d}" for i in range(lo, hi)]
    return ids


def asset_split(asset_id: str) -> str:
    """'world' or 'pool': which split of the library an asset id belongs to."""
    kind, index = _parse_id(asset_id)
    return "world" if index < ASSET_KINDS[kind].count else "pool"


def asset_category(asset_id: str) -> str:
    """The taxonomy category (omniscs.taxonomy.CATEGORIES) of an asset id."""
    kind, _ = _parse_id(asset_id)
    return ASSET_KINDS[kind].category


def asset_kind(asset_id: str) -> str:
    return _parse_id(asset_id)[0]


def _stable_seed(kind: str, index: int) -> list[int]:
    """Seed material independent of Python's hash randomisation, so ids mean the same everywhere."""
    return [zlib.crc32(kind.encode("utf-8")), index]


def asset_params(asset_id: str) -> dict:
    """The generator parameters of an asset (cheap: builds no mesh)."""
    kind, index = _parse_id(asset_id)
    return ASSET_KINDS[kind].make_params(np.random.default_rng(_stable_seed(kind, index)))


@functools.lru_cache(maxsize=None)
def build_asset(asset_id: str) -> Asset:
    """Build (once per process) the mesh of an asset id, centred on its box."""
    kind, _ = _parse_id(asset_id)
    params = asset_params(asset_id)
    builder = MeshBuilder()
    ASSET_KINDS[kind].build(builder, params)
    surface = builder.build()
    lo, hi = surface.vertices.min(axis=0), surface.vertices.max(axis=0)
    centred = transform_points(make_transform(np.eye(3), -0.5 * (lo + hi)), surface.vertices)
    surface = SurfaceMesh(centred, surface.faces, surface.face_colour, surface.face_material,
                          surface.face_semantic, surface.face_params)
    for arr in (surface.vertices, surface.faces, surface.face_colour, surface.face_material,
                surface.face_semantic, surface.face_params):
        arr.flags.writeable = False
    return Asset(asset_id=asset_id, kind=kind, category=ASSET_KINDS[kind].category, size=hi - lo,
                 surface=surface, params=params)
