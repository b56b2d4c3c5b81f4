"""nuScenes map expansion v1.3 (``maps/expansion/<location>.json``) from scenes' road layouts, and where each scene
is placed in a location's global frame so that several procedural scenes share one map without overlapping.

**Placement.** A scene *keeps its frame* when its manifest has a ``global_from_world`` and a nuScenes location
(a recorded nuScenes log, or a store that says where it is): its poses stay in that global frame and no map file
is written for it (the real map expansion belongs to it). Every other scene (procedural worlds, hand-made stores,
logs of other datasets) is *placed*: it is exported under one of the four nuScenes location names (UniAD opens only
those), and the k-th placed scene of a location (0-based, in export order) gets

    global_from_world = translation((k % GRID_COLUMNS) * spacing, (k // GRID_COLUMNS) * spacing, 0)

so its world origin (its first ego pose) sits at the centre of its own square grid cell of side ``spacing``
(default ``SCENE_SPACING_M``); scene 0 keeps the identity. A placed scene's roads, ego poses and boxes must lie
within ``spacing / 2 - MAP_MARGIN_M`` of its origin along x and y (else an error asks for a larger spacing), so
the maps of two scenes never overlap. Placed scenes of one location are also moved in time when needed so that
each starts ``SCENE_TIME_GAP_US`` after the previous one ends (UniAD sorts samples by timestamp).

**Map records** (world frame moved by ``global_from_world``): ``drivable_area`` (one record per scene: its drivable
polygons), ``road_segment`` (drivable polygons cut at the junction, which is a segment of its own with
``is_intersection``), ``lane`` (kind "lane": polygon from the centreline and width, from/to edge lines, left/right
boundary nodes as divider segments of type NIL), ``lane_connector`` (kind "connector": paths through a junction),
``arcline_path_3`` (each centreline as G1-continuous circular arcs and straight pieces through its vertices),
``connectivity`` (incoming/outgoing from the lanes' successors, or from end points that meet for a RoadMap),
``road_divider`` / ``lane_divider`` (the mid line between two neighbouring lanes of opposite / the same
direction), ``ped_crossing``, ``stop_line`` (type TRAFFIC_LIGHT: the procedural junctions are signalised) and
``walkway`` from the procedural layout. Left empty (the sources do not model them): ``road_block``,
``carpark_area``, ``traffic_light``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.export.common import token
from omniscs.geometry import make_transform, wrap_angle
from omniscs.roadmap import in_convex_polygon
from omniscs.scene.sources.common import global_from_world_of
from omniscs.scene.store import Scene

#: The nuScenes map locations (the only map names the devkit's NuScenesMap and UniAD open).
NUSCENES_LOCATIONS: tuple[str, ...] = ("boston-seaport", "singapore-onenorth", "singapore-hollandvillage",
                                       "singapore-queenstown")
DEFAULT_LOCATION = "boston-seaport"
MAP_VERSION = "1.3"
#: Side of a placed scene's square grid cell (metres); procedural worlds span about 520 m.
SCENE_SPACING_M = 1_000.0
#: Placed scenes per grid row.
GRID_COLUMNS = 10
#: Clearance kept between a scene's extent and the edge of its grid cell (metres).
MAP_MARGIN_M = 20.0
#: Time between the end of one placed scene and the start of the next (microseconds).
SCENE_TIME_GAP_US = 60_000_000
#: Lane width assumed for lanes of a RoadMap, which records centrelines only (metres).
DEFAULT_LANE_WIDTH_M = 3.5
#: Two lanes whose ends are closer than this continue into each other (RoadMap lanes; metres).
SUCCESSOR_GAP_M = 0.5
#: Spacing of the samples that find where two lanes run side by side (metres).
DIVIDER_SAMPLE_STEP_M = 2.0
#: Divider polylines keep only the vertices needed to stay within this of the sampled mid line (metres).
DIVIDER_SIMPLIFY_M = 0.01
#: Two lanes are neighbours where their centrelines are this close to the sum of their half widths (metres).
NEIGHBOUR_TOLERANCE_M = 0.3
#: Radius written for straight arcline paths (the devkit needs a non-zero one; straight pieces never use it).
STRAIGHT_RADIUS_M = 1_000.0
#: A chord within this angle of the heading is written as a straight piece (radians).
STRAIGHT_ANGLE_RAD = 1e-9
#: Margin added to the largest coordinate for ``canvas_edge`` (metres).
CANVAS_MARGIN_M = 10.0


def check_location(location: str) -> str:
    if location not in NUSCENES_LOCATIONS:
        raise OmniscsError(f"unknown nuScenes location {location!r}; UniAD and the devkit open only "
                           f"{list(NUSCENES_LOCATIONS)}: choose one of them")
    return location


# ----------------------------------------------------------------------------- a scene's roads
@dataclass(frozen=True)
class RoadLane:
    """One lane or junction connector: its centreline in driving order and the lanes it continues into."""

    lane_id: str
    """Unique within its scene."""
    centreline: np.ndarray
    """[N, 2] xy, the first point where traffic enters."""
    width: float
    """Metres."""
    successors: tuple[str, ...]
    """lane_ids a vehicle may continue into at the end."""
    kind: str
    """"lane" (a road lane) or "connector" (a path through a junction)."""


@dataclass(frozen=True)
class RoadLayout:
    """A scene's roads as far as its source knows them, in one frame (polygons [K, 2], counter-clockwise)."""

    drivable: tuple[np.ndarray, ...]
    """Polygons whose union is the drivable area."""
    lanes: tuple[RoadLane, ...]
    """Lanes and connectors."""
    walkways: tuple[np.ndarray, ...] = ()
    """Sidewalk polygons."""
    crossings: tuple[np.ndarray, ...] = ()
    """Pedestrian crossing polygons."""
    stop_lines: tuple[np.ndarray, ...] = ()
    """Painted stop line polygons."""
    junctions: tuple[np.ndarray, ...] = ()
    """Junction boxes (road segments of their own, marked as intersections)."""

    def points(self) -> np.ndarray:  # -> [M, 2] every vertex
        parts = [*self.drivable, *self.walkways, *self.crossings, *self.stop_lines, *self.junctions,
                 *(lane.centreline for lane in self.lanes)]
        return np.concatenate(parts) if parts else np.zeros((0, 2))

    def moved(self, a_from_b: np.ndarray) -> "RoadLayout":  # [4, 4]: this layout's frame b -> frame a
        def xy(p):
            return np.asarray(p, np.float64) @ a_from_b[:2, :2].T + a_from_b[:2, 3]

        return RoadLayout(drivable=tuple(xy(p) for p in self.drivable),
                          lanes=tuple(replace(lane, centreline=xy(lane.centreline)) for lane in self.lanes),
                          walkways=tuple(xy(p) for p in self.walkways),
                          crossings=tuple(xy(p) for p in self.crossings),
                          stop_lines=tuple(xy(p) for p in self.stop_lines),
                          junctions=tuple(xy(p) for p in self.junctions))


def road_layout_of(scene: Scene) -> RoadLayout | None:
    """A scene's roads in its world frame: the procedural layout (lanes with widths and successors, sidewalks,
    crossings, stop lines, junction) for synthetic scenes, else its RoadMap, else None."""
    world = scene.world
    if world is not None:
        from omniscs.world.layouts import layout_for

        layout = layout_for(world)
        lanes = tuple(RoadLane(lane.lane_id, np.asarray(lane.centreline, np.float64), float(lane.width),
                               tuple(lane.successors), lane.kind) for lane in layout.lanes.values())
        junctions = () if layout.junction_polygon is None else (np.asarray(layout.junction_polygon, np.float64),)
        return RoadLayout(drivable=tuple(layout.drivable_polygons), lanes=lanes,
                          walkways=tuple(layout.sidewalk_polygons), crossings=tuple(layout.crosswalk_polygons),
                          stop_lines=tuple(layout.stop_line_polygons), junctions=junctions)
    road_map = scene.road_map
    if road_map is None:
        return None
    centrelines = [np.asarray(c, np.float64) for c in road_map.lane_centrelines]
    lanes = []
    for i, line in enumerate(centrelines):
        successors = tuple(f"lane_{j}" for j, other in enumerate(centrelines)
                           if j != i and np.linalg.norm(other[0] - line[-1]) <= SUCCESSOR_GAP_M)
        lanes.append(RoadLane(f"lane_{i}", line, DEFAULT_LANE_WIDTH_M, successors, "lane"))
    return RoadLayout(drivable=tuple(road_map.drivable_polygons), lanes=tuple(lanes))


# ----------------------------------------------------------------------------- placement
@dataclass(frozen=True)
class ScenePlacement:
    """Where one exported scene lives: its location, global frame, time shift and (placed scenes) its roads."""

    location: str
    """nuScenes location name written to the log."""
    global_from_world: np.ndarray
    """[4, 4] used for every ego pose, annotation and map record of the scene."""
    time_offset_us: int
    """Added to every timestamp of the scene."""
    placed: bool
    """True: moved to a grid cell of ``location`` (its map goes into that location's expansion file)."""
    roads: RoadLayout | None
    """The scene's roads in the global frame (placed scenes that have a map), else None."""


def keeps_its_frame(scene: Scene) -> bool:
    """Whether a scene keeps its recorded global frame and location (see the module docstring)."""
    return scene.manifest.get("global_from_world") is not None and scene.manifest.get("location") in NUSCENES_LOCATIONS


def grid_offset(k: int, spacing: float) -> np.ndarray:  # -> [4, 4] global_from_world of the k-th placed scene
    return make_transform(np.eye(3), [(k % GRID_COLUMNS) * spacing, (k // GRID_COLUMNS) * spacing, 0.0])


def place_scenes(scenes: list[Scene], location: str = DEFAULT_LOCATION, spacing: float = SCENE_SPACING_M
                 ) -> list[ScenePlacement]:
    """The placement of every scene of one export (see the module docstring)."""
    check_location(location)
    if isinstance(spacing, bool) or not isinstance(spacing, (int, float)) or not np.isfinite(spacing) or \
            spacing <= 2 * MAP_MARGIN_M:
        raise OmniscsError(f"scene spacing must be a number of metres above {2 * MAP_MARGIN_M:g}; got {spacing!r}")
    kept_locations = {s.manifest["location"]: s.scene_id for s in scenes if keeps_its_frame(s)}
    placed_count = sum(not keeps_its_frame(s) for s in scenes)
    if placed_count and location in kept_locations:
        raise OmniscsError(f"scene {kept_locations[location]} is a recorded log in {location}, whose map file "
                           f"procedural scenes would replace; export the procedural scenes under another location")
    out, k, previous_end = [], 0, None
    for scene in scenes:
        ts = scene.frames["timestamp_us"].to_numpy(np.int64)
        if keeps_its_frame(scene):
            out.append(ScenePlacement(scene.manifest["location"], global_from_world_of(scene), 0, False, None))
            continue
        roads = road_layout_of(scene)
        _check_fits(scene, roads, spacing)
        global_from_world = grid_offset(k, spacing)
        shift = 0 if previous_end is None else max(0, previous_end + SCENE_TIME_GAP_US - int(ts[0]))
        previous_end = int(ts[-1]) + shift
        out.append(ScenePlacement(location, global_from_world, shift, True,
                                  None if roads is None else roads.moved(global_from_world)))
        k += 1
    return out


def _check_fits(scene: Scene, roads: RoadLayout | None, spacing: float) -> None:
    xy = [scene.world_from_ego_all[:, :2, 3]]
    if len(scene.boxes):
        xy.append(scene.boxes[["cx", "cy"]].to_numpy(np.float64))
    if roads is not None:
        xy.append(roads.points())
    reach = float(np.abs(np.concatenate(xy)).max())
    if reach > spacing / 2 - MAP_MARGIN_M:
        needed = 2 * (reach + MAP_MARGIN_M)
        raise OmniscsError(f"scene {scene.scene_id} reaches {reach:.0f} m from its first ego pose, more than a "
                           f"{spacing:g} m grid cell holds; pass a scene spacing above {needed:.0f} m")


# ----------------------------------------------------------------------------- geometry helpers
def _normals(line: np.ndarray) -> np.ndarray:  # [N, 2] -> [N, 2] unit left normals at the vertices
    seg = np.diff(line, axis=0)
    seg /= np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-12)
    tangent = np.concatenate([seg[:1], seg[:-1] + seg[1:], seg[-1:]])
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)


def lane_boundaries(lane: RoadLane) -> tuple[np.ndarray, np.ndarray]:  # -> left [N, 2], right [N, 2]
    offset = 0.5 * lane.width * _normals(lane.centreline)
    return lane.centreline + offset, lane.centreline - offset


def arcline_paths(line: np.ndarray) -> list[dict]:  # [N, 2] -> arcline path records
    """A polyline as G1-continuous pieces through its vertices: each piece leaves a vertex along the current heading
    and reaches the next vertex on a circular arc (or straight, when the chord is along the heading). The first
    heading is the tangent of the circle through the first three vertices, so evenly sampled circles come out
    exact."""
    pts = np.asarray(line, np.float64)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
    pts = pts[keep]
    if len(pts) < 2:
        return []
    chord0 = pts[1] - pts[0]
    heading = float(np.arctan2(chord0[1], chord0[0]))
    if len(pts) >= 3:
        turn = wrap_angle(np.arctan2(*(pts[2] - pts[1])[::-1]) - heading)
        # The tangent at p0 of the circle through p0, p1, p2 is the first chord turned back by half the turn
        # between the chords, scaled by the chords' lengths (inscribed-angle theorem).
        a, b = np.linalg.norm(pts[1] - pts[0]), np.linalg.norm(pts[2] - pts[1])
        heading -= float(turn) * a / (a + b)
    paths = []
    for p0, p1 in zip(pts[:-1], pts[1:]):
        chord = p1 - p0
        d = float(np.linalg.norm(chord))
        alpha = float(wrap_angle(np.arctan2(chord[1], chord[0]) - heading))
        end_heading = float(wrap_angle(heading + 2 * alpha))
        if abs(alpha) < STRAIGHT_ANGLE_RAD:
            shape, radius, lengths = "LSL", STRAIGHT_RADIUS_M, [0.0, d, 0.0]
        else:
            radius = d / (2 * abs(np.sin(alpha)))
            shape, lengths = ("LSL" if alpha > 0 else "RSR"), [2 * abs(alpha) * radius, 0.0, 0.0]
        paths.append({"start_pose": [float(p0[0]), float(p0[1]), heading],
                      "end_pose": [float(p1[0]), float(p1[1]), end_heading],
                      "shape": shape, "radius": float(radius), "segment_length": lengths})
        heading = end_heading
    return paths


def _nearest_on_polyline(points: np.ndarray, line: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point [M, 2]: nearest point on the polyline [N, 2], distance, and whether it is an inner point (not
    clamped to an end of the polyline)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.einsum("msk,sk->ms", points[:, None, :] - a[None], ab) / np.maximum(np.einsum("sk,sk->s", ab, ab), 1e-12)
    t = np.clip(t, 0.0, 1.0)
    nearest = a[None] + t[..., None] * ab[None]
    dist = np.linalg.norm(points[:, None, :] - nearest, axis=2)
    i = np.argmin(dist, axis=1)
    rows = np.arange(len(points))
    ti = t[rows, i]
    inner = ~(((i == 0) & (ti <= 0.0)) | ((i == len(a) - 1) & (ti >= 1.0)))
    return nearest[rows, i], dist[rows, i], inner


def _resample(line: np.ndarray, step: float) -> np.ndarray:  # [N, 2] -> [M, 2] every ``step`` metres, ends kept
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    samples = np.unique(np.concatenate([np.arange(0.0, s[-1], step), [s[-1]]]))
    return np.stack([np.interp(samples, s, line[:, 0]), np.interp(samples, s, line[:, 1])], axis=1)


def lane_dividers(lanes: tuple[RoadLane, ...]) -> list[tuple[np.ndarray, bool]]:
    """Mid lines between neighbouring road lanes: (polyline [M, 2], same direction?) per side-by-side run."""
    road = [lane for lane in lanes if lane.kind == "lane" and len(lane.centreline) >= 2]
    out = []
    for i, a in enumerate(road):
        lo_a, hi_a = a.centreline.min(0), a.centreline.max(0)
        for b in road[i + 1:]:
            gap = 0.5 * (a.width + b.width)
            if np.any(b.centreline.min(0) > hi_a + gap + NEIGHBOUR_TOLERANCE_M) or \
                    np.any(b.centreline.max(0) < lo_a - gap - NEIGHBOUR_TOLERANCE_M):
                continue
            samples = _resample(a.centreline, DIVIDER_SAMPLE_STEP_M)
            nearest, dist, inner = _nearest_on_polyline(samples, b.centreline)
            side_by_side = inner & (np.abs(dist - gap) <= NEIGHBOUR_TOLERANCE_M)
            if side_by_side.sum() < 2:
                continue
            dir_a = a.centreline[-1] - a.centreline[0]
            dir_b = b.centreline[-1] - b.centreline[0]
            same = bool(np.dot(dir_a, dir_b) > 0)
            mid = 0.5 * (samples + nearest)
            # Split into runs of consecutive side-by-side samples.
            edges = np.flatnonzero(np.diff(np.concatenate([[0], side_by_side.astype(int), [0]])))
            for start, stop in zip(edges[::2], edges[1::2]):
                if stop - start >= 2:
                    out.append((_simplified(mid[start:stop]), same))
    return out


def _simplified(line: np.ndarray) -> np.ndarray:  # [M, 2] -> [K, 2], ends kept, within DIVIDER_SIMPLIFY_M
    from shapely.geometry import LineString

    return np.asarray(LineString(line).simplify(DIVIDER_SIMPLIFY_M).coords, np.float64)


def _junction_cut(polygon: np.ndarray, junctions: tuple[np.ndarray, ...]) -> list[np.ndarray]:
    """The parts of a drivable polygon outside every junction box."""
    from shapely.geometry import Polygon

    shape = Polygon(polygon)
    for junction in junctions:
        shape = shape.difference(Polygon(junction))
    parts = getattr(shape, "geoms", [shape])
    return [np.asarray(p.exterior.coords[:-1], np.float64) for p in parts if not p.is_empty and p.area > 1e-6]


# ----------------------------------------------------------------------------- the expansion file
class MapExpansion:
    """The records of one location's map expansion, gathered scene by scene (coordinates in the global frame)."""

    LAYERS = ("polygon", "line", "node", "drivable_area", "road_segment", "road_block", "lane", "ped_crossing",
              "walkway", "stop_line", "carpark_area", "road_divider", "lane_divider", "traffic_light",
              "lane_connector")

    def __init__(self, location: str):
        self.location = check_location(location)
        self.layers: dict[str, list[dict]] = {name: [] for name in self.LAYERS}
        self.arcline_path_3: dict[str, list[dict]] = {}
        self.connectivity: dict[str, dict[str, list[str]]] = {}

    # -- geometric records
    def _node(self, key: tuple, xy) -> str:
        tok = token("map-node", self.location, *key)
        self.layers["node"].append({"token": tok, "x": float(xy[0]), "y": float(xy[1])})
        return tok

    def _nodes(self, key: tuple, points: np.ndarray) -> list[str]:
        return [self._node((*key, i), p) for i, p in enumerate(points)]

    def _line(self, key: tuple, points: np.ndarray) -> str:
        tok = token("map-line", self.location, *key)
        self.layers["line"].append({"token": tok, "node_tokens": self._nodes(("line", *key), points)})
        return tok

    def _polygon(self, key: tuple, ring: np.ndarray) -> str:
        tok = token("map-polygon", self.location, *key)
        self.layers["polygon"].append({"token": tok, "exterior_node_tokens": self._nodes(("polygon", *key), ring),
                                       "holes": []})
        return tok

    # -- one scene
    def add(self, scene_key: str, roads: RoadLayout) -> None:
        """Add one scene's roads (already in the global frame); ``scene_key`` keeps its tokens apart."""
        k = scene_key
        drivable_token = token("map-drivable_area", self.location, k)
        self.layers["drivable_area"].append({"token": drivable_token, "polygon_tokens": [
            self._polygon((k, "drivable", i), p) for i, p in enumerate(roads.drivable)]})
        segments = []  # (token, ring) for ped crossings to name their segment
        pieces = [(part, False) for poly in roads.drivable for part in _junction_cut(poly, roads.junctions)]
        pieces += [(junction, True) for junction in roads.junctions]
        for i, (ring, is_intersection) in enumerate(pieces):
            seg = token("map-road_segment", self.location, k, i)
            self.layers["road_segment"].append({"token": seg, "polygon_token": self._polygon((k, "segment", i), ring),
                                                "is_intersection": is_intersection,
                                                "drivable_area_token": drivable_token})
            segments.append((seg, ring))
        lane_tokens = {lane.lane_id: token("map-lane", self.location, k, lane.lane_id) for lane in roads.lanes}
        for lane in roads.lanes:
            self._add_lane(k, lane, lane_tokens[lane.lane_id])
        incoming: dict[str, list[str]] = {t: [] for t in lane_tokens.values()}
        for lane in roads.lanes:
            for nxt in lane.successors:
                if nxt in lane_tokens:
                    incoming[lane_tokens[nxt]].append(lane_tokens[lane.lane_id])
        for lane in roads.lanes:
            tok = lane_tokens[lane.lane_id]
            self.connectivity[tok] = {"incoming": incoming[tok],
                                      "outgoing": [lane_tokens[n] for n in lane.successors if n in lane_tokens]}
        for i, (line, same) in enumerate(lane_dividers(roads.lanes)):
            line_token = self._line((k, "divider", i), line)
            if same:
                self.layers["lane_divider"].append({
                    "token": token("map-lane_divider", self.location, k, i), "line_token": line_token,
                    "lane_divider_segments": [{"node_token": n, "segment_type": "NIL"}
                                              for n in self.layers["line"][-1]["node_tokens"]]})
            else:
                self.layers["road_divider"].append({"token": token("map-road_divider", self.location, k, i),
                                                    "line_token": line_token,
                                                    "road_segment_token": _segment_of(line.mean(0), segments)})
        crossing_tokens = []
        for i, ring in enumerate(roads.crossings):
            tok = token("map-ped_crossing", self.location, k, i)
            crossing_tokens.append(tok)
            self.layers["ped_crossing"].append({"token": tok, "polygon_token": self._polygon((k, "crossing", i), ring),
                                                "road_segment_token": _segment_of(ring.mean(0), segments)})
        for i, ring in enumerate(roads.walkways):
            self.layers["walkway"].append({"token": token("map-walkway", self.location, k, i),
                                           "polygon_token": self._polygon((k, "walkway", i), ring)})
        for i, ring in enumerate(roads.stop_lines):
            self.layers["stop_line"].append({"token": token("map-stop_line", self.location, k, i),
                                             "polygon_token": self._polygon((k, "stop", i), ring),
                                             "stop_line_type": "TRAFFIC_LIGHT", "ped_crossing_tokens": [],
                                             "traffic_light_tokens": [], "road_block_token": ""})

    def _add_lane(self, k: str, lane: RoadLane, tok: str) -> None:
        left, right = lane_boundaries(lane)
        ring = np.concatenate([right, left[::-1]])
        polygon_token = self._polygon((k, "lane", lane.lane_id), ring)
        self.arcline_path_3[tok] = arcline_paths(lane.centreline)
        if lane.kind == "connector":
            self.layers["lane_connector"].append({"token": tok, "polygon_token": polygon_token})
            return
        self.layers["lane"].append({
            "token": tok, "polygon_token": polygon_token, "lane_type": "CAR",
            "from_edge_line_token": self._line((k, "lane-from", lane.lane_id), np.stack([right[0], left[0]])),
            "to_edge_line_token": self._line((k, "lane-to", lane.lane_id), np.stack([right[-1], left[-1]])),
            "left_lane_divider_segments": [{"node_token": n, "segment_type": "NIL"}
                                           for n in self._nodes((k, "lane-left", lane.lane_id), left)],
            "right_lane_divider_segments": [{"node_token": n, "segment_type": "NIL"}
                                            for n in self._nodes((k, "lane-right", lane.lane_id), right)]})

    def to_json(self) -> dict:
        xy = np.array([[n["x"], n["y"]] for n in self.layers["node"]]).reshape(-1, 2)
        edge = (np.maximum(xy.max(0), 0.0) + CANVAS_MARGIN_M) if len(xy) else np.full(2, CANVAS_MARGIN_M)
        return {"version": MAP_VERSION, "canvas_edge": [float(edge[0]), float(edge[1])], **self.layers,
                "arcline_path_3": self.arcline_path_3, "connectivity": self.connectivity}


def _segment_of(xy: np.ndarray, segments: list[tuple[str, np.ndarray]]) -> str:
    for seg, ring in segments:
        if in_convex_polygon(np.asarray(xy).reshape(1, 2), _ccw(ring))[0]:
            return seg
    return ""


def _ccw(ring: np.ndarray) -> np.ndarray:
    x, y = ring[:, 0], ring[:, 1]
    area = 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    return ring if area >= 0 else ring[::-1]


def map_expansions(placements: list[ScenePlacement], scene_keys: list[str]) -> dict[str, dict]:
    """{location: expansion JSON} for every location that has placed scenes."""
    maps: dict[str, MapExpansion] = {}
    for placement, key in zip(placements, scene_keys):
        if not placement.placed:
            continue
        expansion = maps.setdefault(placement.location, MapExpansion(placement.location))
        if placement.roads is not None:
            expansion.add(key, placement.roads)
    return {location: expansion.to_json() for location, expansion in maps.items()}
