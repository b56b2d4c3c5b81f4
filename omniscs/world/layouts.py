"""Procedural street layouts (straight road, T-junction, 4-way intersection): static geometry and the map.

A layout is a pure function of (template, seed, LAYOUT_VERSION). It is built in a map frame (main road
along +x, centred on y = 0) and moved into the world frame, whose origin is the ego's first pose.
"""
from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, transform_points
from omniscs.roadmap import RoadMap, in_any_convex_polygon
from omniscs.taxonomy import SEMANTIC_IDS
from omniscs.world.assets import FACE_PARAMS, Material, MeshBuilder, SurfaceMesh, srgb
from omniscs.world.model import LAYOUT_VERSION

#: Layout templates. ``straight_parked_truck`` is ``straight`` that always gets a large parked
#: truck/container ahead of the ego on the right (see omniscs.world.traffic); the others get one by chance.
TEMPLATES: tuple[str, ...] = ("straight", "t_junction", "intersection", "straight_parked_truck")

#: Which cross-road arms each template has (+1 = left of the ego's road, -1 = right).
_CROSS_ARMS: dict[str, tuple[int, ...]] = {
    "straight": (), "straight_parked_truck": (), "t_junction": (1,), "intersection": (1, -1),
}

# Extent of the built world in the map frame (metres). The ego starts at map x = 0.
X_MIN, X_MAX = -160.0, 360.0
Y_ARM_MAX = 260.0
TERRAIN_HALF_EXTENT = 1_500.0
TERRAIN_Z = -0.03  # below the road so the road wins where both exist
MARKING_Z = 0.004  # paint floats just above the asphalt
MARKING_WIDTH = 0.13
STOP_LINE_WIDTH = 0.40
CROSSWALK_LENGTH = 3.0
CROSSWALK_STRIPE = 0.5
CROSSWALK_GAP_TO_JUNCTION = 1.0
KERB_STONE_WIDTH = 0.25
PARKING_SLOT_LENGTH = 6.5
PARKING_CLEARANCE_FROM_JUNCTION = 14.0
CONNECTOR_SAMPLES = 16
TREE_LAMP_CLEARANCE = 3.0  # metres between a tree trunk and a lamp post

SEM = SEMANTIC_IDS
ASPHALT_GREY = srgb(78, 78, 80)
PAINT_WHITE = srgb(225, 225, 220)
PAINT_YELLOW = srgb(226, 180, 40)
SIDEWALK_GREY = srgb(165, 162, 155)
KERB_GREY = srgb(195, 193, 188)
GRASS_GREEN = srgb(82, 112, 52)
POLE_GREY = srgb(100, 102, 106)
LAMP_WARM = srgb(255, 220, 160)
BARK_BROWN = srgb(84, 62, 44)
FACADES = [srgb(*c) for c in (
    (176, 92, 70), (150, 80, 60), (205, 190, 160), (190, 186, 178), (225, 222, 212), (120, 124, 130),
    (160, 150, 130), (96, 110, 130), (210, 200, 185), (140, 90, 80),
)]
ROOF_GREY = srgb(90, 90, 92)


# ----------------------------------------------------------------------------- paths
class Path:
    """A polyline followed by its centre: arc length -> position, heading and curvature."""

    #: Half-width (metres) of the finite difference that gives headings; smooths the polyline's corners.
    HEADING_BASELINE = 0.5

    def __init__(self, points: np.ndarray) -> None:  # [N, 2]
        pts = np.asarray(points, dtype=np.float64)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
        self.points = pts[keep]  # [N, 2]
        seg = np.diff(self.points, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg_len)])  # [N]
        self.length = float(self.s[-1])
        seg_yaw = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
        # Curvature at inner vertices: turn angle over the mean length of the two segments it joins.
        turn = np.diff(seg_yaw) / np.maximum(0.5 * (seg_len[:-1] + seg_len[1:]), 1e-9)
        self.vertex_curvature = np.concatenate([[0.0], turn, [0.0]])  # [N]

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # [M] -> xy [M, 2], yaw [M]
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        xy = self._xy(s)
        ahead = self._xy(np.minimum(s + self.HEADING_BASELINE, self.length))
        behind = self._xy(np.maximum(s - self.HEADING_BASELINE, 0.0))
        d = ahead - behind
        return xy, np.arctan2(d[:, 1], d[:, 0])

    def _xy(self, s: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(s, self.s, self.points[:, 0]), np.interp(s, self.s, self.points[:, 1])], -1)

    def curvature(self, s: np.ndarray) -> np.ndarray:  # [M] -> [M] 1/metres (signed, + = left)
        return np.interp(np.clip(s, 0.0, self.length), self.s, self.vertex_curvature)

    def project(self, xy: np.ndarray) -> float:  # [2] -> arc length of the nearest point
        a, b = self.points[:-1], self.points[1:]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", np.asarray(xy) - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12),
                    0.0, 1.0)
        nearest = a + t[:, None] * ab
        i = int(np.argmin(np.linalg.norm(nearest - xy, axis=1)))
        return float(self.s[i] + t[i] * (self.s[i + 1] - self.s[i]))


@dataclass(frozen=True)
class Lane:
    """A lane centreline in driving order (world frame) and the lanes a vehicle may continue into."""

    lane_id: str
    centreline: np.ndarray  # [N, 2] world xy, first point = where traffic enters
    width: float
    successors: tuple[str, ...]
    kind: str  # "lane" (a road lane) or "connector" (a path through a junction)

    @property
    def path(self) -> Path:
        return Path(self.centreline)


@dataclass(frozen=True)
class ParkingSlot:
    """A kerbside slot: box centre (x, y) in the world frame and the heading a parked car faces."""

    x: float
    y: float
    yaw: float
    side: int  # -1 right of the ego's road, +1 left


@dataclass(frozen=True)
class Layout:
    """Static world: geometry for the renderer, and the map (lanes, drivable area) for traffic and later stages."""

    template: str
    seed: int
    surface: SurfaceMesh  # world-frame static geometry with per-face appearance
    lanes: dict  # lane_id -> Lane
    drivable_polygons: tuple  # of [K, 2] world xy (convex, counter-clockwise)
    sidewalk_polygons: tuple  # of [K, 2] world xy
    parking_slots: tuple  # of ParkingSlot
    street_lamps: np.ndarray  # [L, 3] world positions of lamp heads (night lights)
    ego_route: tuple  # lane ids the ego drives, in order
    ego_start_s: float  # arc length along the ego route of the first ego pose
    junction_polygon: np.ndarray | None  # [4, 2] world xy of the junction box, None on straight roads
    world_from_map: np.ndarray  # [4, 4]
    params: dict  # the seeded road parameters
    crosswalk_polygons: tuple = ()  # of [4, 2] world xy (counter-clockwise): the striped pedestrian crossings
    stop_line_polygons: tuple = ()  # of [4, 2] world xy (counter-clockwise): painted stop lines

    def route_path(self, lane_ids) -> Path:
        """One path along consecutive lanes."""
        pts = [self.lanes[lane_ids[0]].centreline]
        for lid in lane_ids[1:]:
            pts.append(self.lanes[lid].centreline[1:])
        return Path(np.concatenate(pts))

    def is_drivable(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] world -> [N] bool
        return in_any_convex_polygon(xy, self.drivable_polygons)

    def road_map(self) -> RoadMap:
        """The layout's map in neutral form: drivable polygons, every lane's centreline (in ``lanes`` order) and,
        as the known extent, the bounding box of roads and sidewalks (the procedural world stops at its road ends)."""
        known = np.concatenate([*self.drivable_polygons, *self.sidewalk_polygons])
        return RoadMap(drivable_polygons=tuple(self.drivable_polygons),
                       lane_centrelines=tuple(lane.centreline for lane in self.lanes.values()),
                       extent_min=known.min(0), extent_max=known.max(0))

    def rasterize_drivable(self, x_range: tuple[float, float], y_range: tuple[float, float],
                           resolution: float) -> np.ndarray:
        """Drivable mask on a world-aligned grid: [H, W] bool, row i at y_min + (i + 0.5) * resolution,
        column j at x_min + (j + 0.5) * resolution."""
        if resolution <= 0:
            raise OmniscsError(f"raster resolution must be > 0 metres; got {resolution}")
        xs = np.arange(x_range[0] + 0.5 * resolution, x_range[1], resolution)
        ys = np.arange(y_range[0] + 0.5 * resolution, y_range[1], resolution)
        gx, gy = np.meshgrid(xs, ys)
        return self.is_drivable(np.stack([gx.ravel(), gy.ravel()], -1)).reshape(gy.shape)


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:  # -> [4, 2] ccw
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


# ----------------------------------------------------------------------------- parameters
def road_params(template: str, seed: int) -> dict:
    """The seeded road parameters of a template (what the geometry and the map are built from)."""
    if template not in TEMPLATES:
        raise OmniscsError(f"unknown template {template!r}; use one of {list(TEMPLATES)}")
    if int(seed) < 0:
        raise OmniscsError(f"seed must be a non-negative integer; got {seed!r}")
    rng = np.random.default_rng([zlib.crc32(template.encode("utf-8")), int(seed), LAYOUT_VERSION])
    arms = _CROSS_ARMS[template]
    lanes = int(rng.integers(1, 4)) if not arms else int(rng.integers(1, 3))
    district = ["suburban", "urban", "downtown"][int(rng.integers(0, 3))]
    parking_right = bool(template == "straight_parked_truck" or rng.uniform() < 0.7)
    ego_lane = int(rng.integers(0, lanes))
    if template == "straight_parked_truck":
        ego_lane = lanes - 1  # the truck parks beside the ego's lane
    turn = "straight"
    if arms and rng.uniform() < 0.35:
        options = (["left"] if (1 in arms and ego_lane == 0) else []) + \
                  (["right"] if (-1 in arms and ego_lane == lanes - 1) else [])
        if options:
            turn = options[int(rng.integers(0, len(options)))]
    return dict(
        lane_width=float(rng.uniform(3.2, 3.7)),
        lanes_per_dir=lanes,
        cross_lanes_per_dir=int(rng.integers(1, 3)),
        parking_right=parking_right,
        parking_left=bool(rng.uniform() < 0.6),
        parking_width=float(rng.uniform(2.2, 2.6)),
        sidewalk_width=float(rng.uniform(2.8, 5.0)),
        kerb_height=float(rng.uniform(0.12, 0.18)),
        junction_x=float(rng.uniform(34.0, 52.0)),
        centre_line=["double_solid", "dashed", "solid"][int(rng.integers(0, 3))],
        centre_yellow=bool(rng.uniform() < 0.4),
        dash_length=float(rng.uniform(2.5, 4.0)),
        dash_gap=float(rng.uniform(5.0, 9.0)),
        district=district,
        ego_lane=ego_lane,
        ego_turn=turn,
        arms=arms,
        asphalt_tone=float(rng.uniform(0.85, 1.15)),
        geometry_seed=int(rng.integers(0, 2**31)),
    )


# ----------------------------------------------------------------------------- geometry
def _quad(b: MeshBuilder, corners_xy: np.ndarray, z: float, colour, material, semantic: int, params=None) -> None:
    v = np.column_stack([corners_xy, np.full(4, z)])
    b.add(v, [(0, 1, 2), (0, 2, 3)], colour, material, semantic, params)


def _strip_x(b: MeshBuilder, x0: float, x1: float, y: float, width: float, colour, material=Material.LANE_PAINT,
             semantic: int = SEM["lane_marking"]) -> None:
    _quad(b, _rect(x0, x1, y - width / 2, y + width / 2), MARKING_Z, colour, material, semantic)


def _strip_y(b: MeshBuilder, y0: float, y1: float, x: float, width: float, colour, material=Material.LANE_PAINT,
             semantic: int = SEM["lane_marking"]) -> None:
    _quad(b, _rect(x - width / 2, x + width / 2, y0, y1), MARKING_Z, colour, material, semantic)


def _dashes(lo: float, hi: float, dash: float, gap: float) -> list[tuple[float, float]]:
    out, a = [], lo
    while a + dash <= hi:
        out.append((a, a + dash))
        a += dash + gap
    return out


def _intervals_minus(lo: float, hi: float, holes: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """[lo, hi] with the hole intervals cut out."""
    parts = [(lo, hi)]
    for h0, h1 in holes:
        nxt = []
        for a, c in parts:
            if h1 <= a or h0 >= c:
                nxt.append((a, c))
                continue
            if h0 > a:
                nxt.append((a, h0))
            if h1 < c:
                nxt.append((h1, c))
        parts = nxt
    return [(a, c) for a, c in parts if c - a > 1e-6]


class _LayoutBuilder:
    """Builds one layout in the map frame; ``finish`` moves it to the world frame."""

    def __init__(self, template: str, seed: int) -> None:
        self.template, self.seed = template, seed
        self.p = road_params(template, seed)
        self.rng = np.random.default_rng(self.p["geometry_seed"])
        self.b = MeshBuilder()
        p = self.p
        self.lw = p["lane_width"]
        self.n = p["lanes_per_dir"]
        self.nc = p["cross_lanes_per_dir"]
        self.half_lanes = self.n * self.lw  # main road: edge of the driving lanes
        self.w_left = self.half_lanes + (p["parking_width"] if p["parking_left"] else 0.0)
        self.w_right = self.half_lanes + (p["parking_width"] if p["parking_right"] else 0.0)
        self.wc = self.nc * self.lw  # cross road half width
        self.arms = p["arms"]
        self.xj = p["junction_x"]
        self.lamps: list[np.ndarray] = []
        self.drivable: list[np.ndarray] = []
        self.sidewalks: list[np.ndarray] = []
        self.crosswalks: list[np.ndarray] = []
        self.stop_lines: list[np.ndarray] = []
        self.lanes: dict[str, dict] = {}

    # -- roads ---------------------------------------------------------------------------
    def road_width(self, side: int) -> float:
        return self.w_left if side > 0 else self.w_right

    def roads(self) -> None:
        tone = self.p["asphalt_tone"]
        asphalt = np.clip(ASPHALT_GREY * tone, 0, 1)
        main = _rect(X_MIN, X_MAX, -self.w_right, self.w_left)
        self.drivable.append(main)
        _quad(self.b, main, 0.0, asphalt, Material.ASPHALT, SEM["road"])
        for side in self.arms:
            y0, y1 = (self.w_left, Y_ARM_MAX) if side > 0 else (-Y_ARM_MAX, -self.w_right)
            arm = _rect(self.xj - self.wc, self.xj + self.wc, y0, y1)
            self.drivable.append(arm)
            _quad(self.b, arm, 0.0, asphalt * 0.97, Material.ASPHALT, SEM["road"])
        _quad(self.b, _rect(-TERRAIN_HALF_EXTENT, TERRAIN_HALF_EXTENT, -TERRAIN_HALF_EXTENT, TERRAIN_HALF_EXTENT),
              TERRAIN_Z, GRASS_GREEN, Material.GRASS, SEM["terrain"])

    def junction_hole(self) -> tuple[float, float]:
        """x interval of the main road without lane markings (junction box plus crosswalks)."""
        margin = CROSSWALK_GAP_TO_JUNCTION + CROSSWALK_LENGTH + 1.2
        return self.xj - self.wc - margin, self.xj + self.wc + margin

    def markings(self) -> None:
        p, b = self.p, self.b
        centre_colour = PAINT_YELLOW if p["centre_yellow"] else PAINT_WHITE
        holes = [self.junction_hole()] if self.arms else []
        for x0, x1 in _intervals_minus(X_MIN, X_MAX, holes):
            if p["centre_line"] == "double_solid":
                for dy in (-0.12, 0.12):
                    _strip_x(b, x0, x1, dy, MARKING_WIDTH, centre_colour)
            elif p["centre_line"] == "solid":
                _strip_x(b, x0, x1, 0.0, MARKING_WIDTH, centre_colour)
            else:
                for a, c in _dashes(x0, x1, p["dash_length"], p["dash_gap"]):
                    _strip_x(b, a, c, 0.0, MARKING_WIDTH, centre_colour)
            for k in range(1, self.n):  # lane separators, both directions
                for sign in (1, -1):
                    for a, c in _dashes(x0, x1, p["dash_length"], p["dash_gap"]):
                        _strip_x(b, a, c, sign * k * self.lw, MARKING_WIDTH, PAINT_WHITE)
        for side in (1, -1):  # edge lines; broken only where a cross arm joins on that side
            side_holes = [self.junction_hole()] if side in self.arms else []
            for x0, x1 in _intervals_minus(X_MIN, X_MAX, side_holes):
                _strip_x(b, x0, x1, side * (self.half_lanes - 0.15), MARKING_WIDTH, PAINT_WHITE)
        if not self.arms:
            return
        for side in self.arms:  # cross-road markings
            y_in = self.w_left if side > 0 else self.w_right
            margin = CROSSWALK_GAP_TO_JUNCTION + CROSSWALK_LENGTH + 1.2
            lo, hi = (y_in + margin, Y_ARM_MAX) if side > 0 else (-Y_ARM_MAX, -y_in - margin)
            for a, c in _dashes(lo, hi, p["dash_length"], p["dash_gap"]):
                _strip_y(b, a, c, self.xj, MARKING_WIDTH, centre_colour)
            for k in range(1, self.nc):
                for sgn in (1, -1):
                    for a, c in _dashes(lo, hi, p["dash_length"], p["dash_gap"]):
                        _strip_y(b, a, c, self.xj + sgn * k * self.lw, MARKING_WIDTH, PAINT_WHITE)
        self.crosswalks_and_stop_lines()

    def crosswalks_and_stop_lines(self) -> None:
        b = self.b
        gap = CROSSWALK_GAP_TO_JUNCTION
        stripe_pitch = 2 * CROSSWALK_STRIPE
        # Main road arms (west = the ego's approach, east = beyond the junction).
        for sign in (-1, 1):
            x_near = self.xj + sign * (self.wc + gap)
            x_far = x_near + sign * CROSSWALK_LENGTH
            xa, xb = min(x_near, x_far), max(x_near, x_far)
            self.crosswalks.append(_rect(xa, xb, -self.w_right, self.w_left))
            y = -self.w_right + 0.4
            while y + CROSSWALK_STRIPE <= self.w_left - 0.4:
                _quad(b, _rect(xa, xb, y, y + CROSSWALK_STRIPE), MARKING_Z, PAINT_WHITE, Material.LANE_PAINT,
                      SEM["lane_marking"])
                y += stripe_pitch
            if len(self.arms) == 2:  # signalised 4-way: stop lines on the main road too
                x_stop = x_far + sign * 0.8
                y0, y1 = (-self.half_lanes, 0.0) if sign < 0 else (0.0, self.half_lanes)
                stop = _rect(x_stop - STOP_LINE_WIDTH / 2, x_stop + STOP_LINE_WIDTH / 2, y0, y1)
                self.stop_lines.append(stop)
                _quad(b, stop, MARKING_Z, PAINT_WHITE, Material.LANE_PAINT, SEM["lane_marking"])
        for side in self.arms:
            edge = self.w_left if side > 0 else self.w_right
            y_near = side * (edge + gap)
            y_far = y_near + side * CROSSWALK_LENGTH
            ya, yb = min(y_near, y_far), max(y_near, y_far)
            self.crosswalks.append(_rect(self.xj - self.wc, self.xj + self.wc, ya, yb))
            x = self.xj - self.wc + 0.4
            while x + CROSSWALK_STRIPE <= self.xj + self.wc - 0.4:
                _quad(b, _rect(x, x + CROSSWALK_STRIPE, ya, yb), MARKING_Z, PAINT_WHITE, Material.LANE_PAINT,
                      SEM["lane_marking"])
                x += stripe_pitch
            y_stop = y_far + side * 0.8
            # Traffic entering from the left arm drives -y on the -x half; from the right arm +y on +x.
            x0, x1 = (self.xj - self.wc, self.xj) if side > 0 else (self.xj, self.xj + self.wc)
            stop = _rect(x0, x1, y_stop - STOP_LINE_WIDTH / 2, y_stop + STOP_LINE_WIDTH / 2)
            self.stop_lines.append(stop)
            _quad(b, stop, MARKING_Z, PAINT_WHITE, Material.LANE_PAINT, SEM["lane_marking"])

    # -- sidewalks and kerbs -----------------------------------------------------------------
    def sidewalk_rects(self) -> list[tuple[np.ndarray, list[str]]]:
        """Sidewalk rectangles (map frame) and which of their edges face a road ('x0','x1','y0','y1')."""
        s = self.p["sidewalk_width"]
        out = []
        for side in (1, -1):
            edge = self.road_width(side)
            y0, y1 = (edge, edge + s) if side > 0 else (-edge - s, -edge)
            road_edge = "y0" if side > 0 else "y1"
            if side in self.arms:
                out.append((_rect(X_MIN, self.xj - self.wc, y0, y1), [road_edge, "x1"]))
                out.append((_rect(self.xj + self.wc, X_MAX, y0, y1), [road_edge, "x0"]))
                ya, yb = (edge + s, Y_ARM_MAX) if side > 0 else (-Y_ARM_MAX, -edge - s)
                out.append((_rect(self.xj - self.wc - s, self.xj - self.wc, ya, yb), ["x1"]))
                out.append((_rect(self.xj + self.wc, self.xj + self.wc + s, ya, yb), ["x0"]))
            else:
                out.append((_rect(X_MIN, X_MAX, y0, y1), [road_edge]))
        return out

    def sidewalks_and_kerbs(self) -> None:
        h = self.p["kerb_height"]
        for rect, road_edges in self.sidewalk_rects():
            self.sidewalks.append(rect)
            (x0, y0), (x1, y1) = rect[0], rect[2]
            self.b.box(((x0 + x1) / 2, (y0 + y1) / 2, (h - 0.05) / 2), (x1 - x0, y1 - y0, h + 0.05),
                       KERB_GREY, Material.KERB, SEM["kerb"], side_material={"+z": Material.CONCRETE},
                       side_colour={"+z": SIDEWALK_GREY}, side_semantic={"+z": SEM["sidewalk"]})
            top = h + 0.006
            w = KERB_STONE_WIDTH
            for e in road_edges:  # kerb stones stand slightly proud of the slab into the road
                if e == "y0":
                    r = (x0, x1, y0 - 0.01, y0 + w)
                elif e == "y1":
                    r = (x0, x1, y1 - w, y1 + 0.01)
                elif e == "x0":
                    r = (x0 - 0.01, x0 + w, y0, y1)
                else:
                    r = (x1 - w, x1 + 0.01, y0, y1)
                self.b.box(((r[0] + r[1]) / 2, (r[2] + r[3]) / 2, (top - 0.05) / 2),
                           (r[1] - r[0], r[3] - r[2], top + 0.05), KERB_GREY, Material.KERB, SEM["kerb"])

    # -- buildings, lamps, trees -----------------------------------------------------------------
    def building_heights(self) -> tuple[float, float]:
        return {"suburban": (5.0, 11.0), "urban": (9.0, 24.0), "downtown": (16.0, 48.0)}[self.p["district"]]

    def frontage(self) -> list[tuple[str, float, float, float, int]]:
        """Building frontage runs: (axis along which the run goes, start, end, offset line, facing)."""
        s = self.p["sidewalk_width"]
        runs = []
        for side in (1, -1):
            line = side * (self.road_width(side) + s)
            if side in self.arms:
                runs.append(("x", X_MIN, self.xj - self.wc - s, line, side))
                runs.append(("x", self.xj + self.wc + s, X_MAX, line, side))
                y_start = side * (self.road_width(side) + s)
                for sx in (-1, 1):
                    xline = self.xj + sx * (self.wc + s)
                    lo, hi = sorted((y_start, side * Y_ARM_MAX * 0.8))
                    runs.append(("y", lo, hi, xline, sx))
            else:
                runs.append(("x", X_MIN, X_MAX, line, side))
        return runs

    def buildings(self) -> None:
        rng, (h_lo, h_hi) = self.rng, self.building_heights()
        for axis, lo, hi, line, facing in self.frontage():
            cursor = lo + rng.uniform(0, 6)
            while cursor < hi - 6.0:
                width = min(rng.uniform(9, 26), hi - cursor)
                gap = rng.uniform(0.0, 3.0) if rng.uniform() < 0.7 else rng.uniform(6.0, 14.0)
                if width < 6.0:
                    break
                setback = rng.uniform(0.0, 4.0)
                depth = rng.uniform(10.0, 22.0)
                height = rng.uniform(h_lo, h_hi)
                near = line + facing * setback  # facade line nearest the road
                far = near + facing * depth
                a0, a1 = cursor, cursor + width
                if axis == "x":
                    centre = ((a0 + a1) / 2, (near + far) / 2, height / 2 - 0.05)
                    size = (width, depth, height + 0.1)
                else:
                    centre = ((near + far) / 2, (a0 + a1) / 2, height / 2 - 0.05)
                    size = (depth, width, height + 0.1)
                self.building(centre, size)
                cursor = a1 + gap

    def building(self, centre, size) -> None:
        rng = self.rng
        glassy = self.p["district"] == "downtown" and rng.uniform() < 0.35
        colour = srgb(70, 90, 110) if glassy else FACADES[int(rng.integers(0, len(FACADES)))]
        colour = np.clip(colour * rng.uniform(0.85, 1.15), 0, 1)
        window_period = rng.uniform(1.6, 3.2) if not glassy else rng.uniform(1.2, 1.8)
        floor_h = rng.uniform(2.9, 3.6)
        win_w = rng.uniform(0.35, 0.65) if not glassy else 0.9
        win_h = rng.uniform(0.40, 0.60) if not glassy else 0.85
        params = (window_period, floor_h, win_w, win_h)
        self.b.box(centre, size, colour, Material.FACADE, SEM["building"], side_material={"+z": Material.ROOF},
                   side_colour={"+z": ROOF_GREY}, params=params)
        if rng.uniform() < 0.5:  # rooftop plant room
            top = centre[2] + size[2] / 2
            plant = (min(size[0], size[1]) * rng.uniform(0.2, 0.4),) * 2 + (rng.uniform(1.5, 3.0),)
            self.b.box((centre[0], centre[1], top + plant[2] / 2), plant, ROOF_GREY, Material.ROOF, SEM["building"])

    def street_furniture(self) -> None:
        rng = self.rng
        spacing = rng.uniform(24.0, 34.0)
        for side in (1, -1):
            edge = self.road_width(side)
            lamp_xs = []
            x = X_MIN + rng.uniform(0, spacing)
            while x < X_MAX:
                if not self.near_junction(x, 4.0):
                    self.street_lamp(x, side * (edge + 0.55), side)
                    lamp_xs.append(x)
                x += spacing
            tree_gap = rng.uniform(9.0, 16.0)
            x = X_MIN + rng.uniform(0, tree_gap)
            while x < X_MAX:
                clear_of_lamps = not lamp_xs or np.min(np.abs(np.asarray(lamp_xs) - x)) > TREE_LAMP_CLEARANCE
                if clear_of_lamps and not self.near_junction(x, 6.0) and rng.uniform() < 0.75:
                    self.tree(x, side * (edge + 1.3 + rng.uniform(0.0, 0.6)))
                x += tree_gap * rng.uniform(0.8, 1.25)
        if self.arms:
            self.traffic_lights()

    def near_junction(self, x: float, margin: float) -> bool:
        return bool(self.arms) and abs(x - self.xj) < self.wc + self.p["sidewalk_width"] + margin

    def street_lamp(self, x: float, y: float, side: int) -> None:
        b, h = self.b, self.rng.uniform(7.0, 9.0)
        base = self.p["kerb_height"]
        b.cylinder((x, y, base - 0.02), (x, y, base + h), 0.09, POLE_GREY, Material.METAL, SEM["pole"], sections=8)
        arm_len = 1.6
        b.box((x, y - side * arm_len / 2, base + h - 0.05), (0.08, arm_len, 0.08), POLE_GREY, Material.METAL, SEM["pole"])
        head = np.array([x, y - side * arm_len, base + h - 0.12])
        b.box(head, (0.6, 0.3, 0.14), POLE_GREY, Material.METAL, SEM["pole"], side_material={"-z": Material.LAMP},
              side_colour={"-z": LAMP_WARM})
        self.lamps.append(head - np.array([0.0, 0.0, 0.1]))

    def tree(self, x: float, y: float) -> None:
        rng, b = self.rng, self.b
        base = self.p["kerb_height"]
        trunk_h = rng.uniform(2.0, 3.5)
        b.cylinder((x, y, base - 0.02), (x, y, base + trunk_h + 0.5), rng.uniform(0.12, 0.2), BARK_BROWN,
                   Material.BARK, SEM["vegetation"], sections=7)
        crown = rng.uniform(1.6, 2.8)
        green = np.clip(srgb(60, 96, 40) * rng.uniform(0.75, 1.25, 3), 0, 1)
        for _ in range(int(rng.integers(2, 4))):
            off = rng.uniform(-0.6, 0.6, 3) * crown * np.array([1, 1, 0.5])
            c = np.array([x, y, base + trunk_h + crown * 0.8]) + off
            b.blob(c, crown * rng.uniform(0.7, 1.0, 3), rng, green, Material.FOLIAGE, SEM["vegetation"],
                   subdivisions=1, roughness=0.22)

    def traffic_lights(self) -> None:
        b = self.b
        base = self.p["kerb_height"]
        corners = []
        for sx in (-1, 1):
            for side in (1, -1):
                if side not in self.arms and sx > 0 and len(self.arms) == 1:
                    continue
                corners.append((self.xj + sx * (self.wc + 0.6), side * (self.road_width(side) + 0.6)))
        for cx, cy in corners:
            b.cylinder((cx, cy, base - 0.02), (cx, cy, base + 3.6), 0.07, POLE_GREY, Material.METAL, SEM["pole"], sections=8)
            b.box((cx, cy, base + 3.1), (0.3, 0.3, 0.95), srgb(30, 30, 30), Material.PLASTIC, SEM["pole"])
            for i, col in enumerate((srgb(200, 20, 20), srgb(230, 160, 20), srgb(20, 200, 60))):
                for dx in (-1, 1):
                    b.box((cx + dx * 0.16, cy, base + 3.4 - 0.3 * i), (0.02, 0.18, 0.18), col,
                          Material.SIGNAL, SEM["pole"], params=(1.0 if i == (0 if dx < 0 else 2) else 0.0, 0, 0, 0))

    # -- lanes ---------------------------------------------------------------------------------------------
    def add_lane(self, lane_id: str, points, successors=(), kind: str = "lane") -> None:
        self.lanes[lane_id] = dict(points=np.asarray(points, dtype=np.float64), successors=list(successors), kind=kind)

    def build_lanes(self) -> None:
        lw = self.lw
        if not self.arms:
            for k in range(self.n):
                y = (k + 0.5) * lw
                self.add_lane(f"east_{k}", [(X_MIN, -y), (X_MAX, -y)])
                self.add_lane(f"west_{k}", [(X_MAX, y), (X_MIN, y)])
            return
        x_in, x_out = self.xj - self.wc, self.xj + self.wc
        for k in range(self.n):
            y = (k + 0.5) * lw
            self.add_lane(f"west_in_{k}", [(X_MIN, -y), (x_in, -y)])  # the ego's approach (from the west)
            self.add_lane(f"east_out_{k}", [(x_out, -y), (X_MAX, -y)])
            self.add_lane(f"east_in_{k}", [(X_MAX, y), (x_out, y)])
            self.add_lane(f"west_out_{k}", [(x_in, y), (X_MIN, y)])
        for side in self.arms:
            name = "north" if side > 0 else "south"
            edge = self.road_width(side)
            for k in range(self.nc):
                off = (k + 0.5) * lw
                if side > 0:  # northern arm: inbound drives -y on the -x half
                    self.add_lane(f"{name}_in_{k}", [(self.xj - off, Y_ARM_MAX), (self.xj - off, edge)])
                    self.add_lane(f"{name}_out_{k}", [(self.xj + off, edge), (self.xj + off, Y_ARM_MAX)])
                else:
                    self.add_lane(f"{name}_in_{k}", [(self.xj + off, -Y_ARM_MAX), (self.xj + off, -edge)])
                    self.add_lane(f"{name}_out_{k}", [(self.xj - off, -edge), (self.xj - off, -Y_ARM_MAX)])
        self.connectors()

    def connectors(self) -> None:
        """Paths through the junction: straight on, right turns from the outer lane, left from the inner."""
        arms = ["west", "east"] + [("north" if s > 0 else "south") for s in self.arms]
        n_lanes = {"west": self.n, "east": self.n, "north": self.nc, "south": self.nc}
        # For traffic entering from arm A: which arm is straight / left / right.
        turns = {"west": {"straight": "east", "left": "north", "right": "south"},
                 "east": {"straight": "west", "left": "south", "right": "north"},
                 "north": {"straight": "south", "left": "east", "right": "west"},
                 "south": {"straight": "north", "left": "west", "right": "east"}}
        for a in arms:
            for turn, b in turns[a].items():
                if b not in arms:
                    continue
                pairs = []
                if turn == "straight":
                    pairs = [(k, k) for k in range(min(n_lanes[a], n_lanes[b]))]
                elif turn == "right":
                    pairs = [(n_lanes[a] - 1, n_lanes[b] - 1)]
                else:
                    pairs = [(0, 0)]
                for ka, kb in pairs:
                    src, dst = f"{a}_in_{ka}", f"{b}_out_{kb}"
                    p0, p1 = self.lanes[src]["points"][-1], self.lanes[dst]["points"][0]
                    d0 = p0 - self.lanes[src]["points"][-2]
                    d1 = self.lanes[dst]["points"][1] - p1
                    cid = f"{src}->{dst}"
                    self.add_lane(cid, _bezier(p0, d0 / np.linalg.norm(d0), p1, d1 / np.linalg.norm(d1)),
                                  successors=[dst], kind="connector")
                    self.lanes[src]["successors"].append(cid)

    def ego_route(self) -> tuple[list[str], float]:
        k = self.p["ego_lane"]
        if not self.arms:
            return [f"east_{k}"], -X_MIN
        first = f"west_in_{k}"
        turn = self.p["ego_turn"]
        if turn == "straight":
            dst = f"east_out_{min(k, self.n - 1)}"
        elif turn == "left":
            dst = "north_out_0"
        else:
            dst = f"south_out_{self.nc - 1}"
        return [first, f"{first}->{dst}", dst], -X_MIN

    def parking_slots(self) -> list[tuple[float, float, float, int]]:
        slots = []
        for side, enabled in ((-1, self.p["parking_right"]), (1, self.p["parking_left"])):
            if not enabled:
                continue
            y = side * (self.half_lanes + self.p["parking_width"] / 2)
            yaw = 0.0 if side < 0 else np.pi  # parked with the traffic on that side
            x = X_MIN + 2.0
            while x + PARKING_SLOT_LENGTH < X_MAX:
                xc = x + PARKING_SLOT_LENGTH / 2
                if not (self.arms and abs(xc - self.xj) < self.wc + PARKING_CLEARANCE_FROM_JUNCTION):
                    slots.append((xc, y, yaw, side))
                x += PARKING_SLOT_LENGTH
        return slots

    # -- finish ---------------------------------------------------------------------------------
    def finish(self) -> Layout:
        self.roads()
        self.markings()
        self.sidewalks_and_kerbs()
        self.buildings()
        self.street_furniture()
        self.build_lanes()
        route, s0 = self.ego_route()
        ego_y = -(self.p["ego_lane"] + 0.5) * self.lw
        world_from_map = make_transform(np.eye(3), [0.0, -ego_y, 0.0])

        def to_world_xy(xy: np.ndarray) -> np.ndarray:
            return np.asarray(xy, dtype=np.float64) + world_from_map[:2, 3]

        surf = self.b.build()
        surf = SurfaceMesh(transform_points(world_from_map, surf.vertices), surf.faces, surf.face_colour,
                           surf.face_material, surf.face_semantic, surf.face_params)
        assert surf.face_params.shape[1] == FACE_PARAMS
        lanes = {lid: Lane(lid, to_world_xy(d["points"]), self.lw, tuple(d["successors"]), d["kind"])
                 for lid, d in self.lanes.items()}
        slots = tuple(ParkingSlot(float(x + world_from_map[0, 3]), float(y + world_from_map[1, 3]), float(yaw), side)
                      for x, y, yaw, side in self.parking_slots())
        junction = None
        if self.arms:
            junction = to_world_xy(_rect(self.xj - self.wc, self.xj + self.wc, -self.w_right, self.w_left))
        lamps = transform_points(world_from_map, np.array(self.lamps).reshape(-1, 3))
        return Layout(
            template=self.template, seed=self.seed, surface=surf, lanes=lanes,
            drivable_polygons=tuple(to_world_xy(r) for r in self.drivable),
            sidewalk_polygons=tuple(to_world_xy(r) for r in self.sidewalks),
            parking_slots=slots, street_lamps=lamps, ego_route=tuple(route), ego_start_s=float(s0),
            junction_polygon=junction, world_from_map=world_from_map, params=dict(self.p),
            crosswalk_polygons=tuple(to_world_xy(r) for r in self.crosswalks),
            stop_line_polygons=tuple(to_world_xy(r) for r in self.stop_lines),
        )


def _bezier(p0: np.ndarray, d0: np.ndarray, p1: np.ndarray, d1: np.ndarray,
            n: int = CONNECTOR_SAMPLES) -> np.ndarray:  # -> [n, 2]
    """Cubic Bezier from p0 leaving along d0 to p1 arriving along d1 (unit directions)."""
    reach = 0.5 * np.linalg.norm(p1 - p0)
    c0, c1 = p0 + reach * d0, p1 - reach * d1
    t = np.linspace(0.0, 1.0, n)[:, None]
    return ((1 - t) ** 3) * p0 + 3 * ((1 - t) ** 2) * t * c0 + 3 * (1 - t) * t * t * c1 + (t ** 3) * p1


@functools.lru_cache(maxsize=16)
def build_layout(template: str, seed: int) -> Layout:
    """The static layout of (template, seed) in the world frame of a log whose ego starts on its route."""
    if template not in TEMPLATES:
        raise OmniscsError(f"unknown template {template!r}; use one of {list(TEMPLATES)}")
    return _LayoutBuilder(template, int(seed)).finish()


def layout_for(world) -> Layout:
    """The layout (static geometry and map) a World was generated on."""
    if world.layout_version != LAYOUT_VERSION:
        raise OmniscsError(f"world was made with layout version {world.layout_version}, this code builds version "
                           f"{LAYOUT_VERSION}; regenerate the world with this version")
    return build_layout(world.template, world.seed)


def road_map_for(world) -> RoadMap:
    """The road map of a World (from the layout it was generated on)."""
    return layout_for(world).road_map()
