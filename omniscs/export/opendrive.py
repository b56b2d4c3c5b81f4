"""OpenDRIVE road networks (``.xodr``) of scenes, written with ``scenariogeneration``, and the area an exported
scenario's entities must stay in.

**Frames.** OpenDRIVE's inertial frame is right-handed with z up and headings counter-clockwise from +x, exactly
our world frame, so coordinates are written unchanged (metres, radians; no geo reference: the world origin is the
first ego pose).

**Procedural worlds: exact.** The layout (``omniscs.world.layouts``) is built from straight roads and Bezier junction
paths, both of which OpenDRIVE represents exactly:

- the main road, and each cross arm, is a road whose reference line (a ``line``) is the road's centre line between
  the two directions. Right lanes (ids -1, -2, ...) drive along the reference line, left lanes (1, 2, ...) against it
  (right-hand traffic). Outwards of the driving lanes come a ``parking`` lane where the layout parks cars and a
  ``sidewalk`` lane: the cross-section of the layout, lane by lane, with its widths.
- with a junction the main road is split at the junction box into a west and an east road; the arms start at the
  box's edge. Every junction path of the layout (a cubic Bezier curve) is a connecting road whose reference line is
  that curve written as a ``paramPoly3`` (a cubic is a cubic: exact) and whose one driving lane (-1) is centred on it
  (``laneOffset`` of half a lane). Lane links name the layout's lane successors; the junction's connections say
  which incoming lane feeds which path.

Sidewalk lanes carry the kerb height as their lane ``height`` (the roads themselves lie at z = 0, as the world's).
Road marks: the centre line as the world paints it (main road: double solid, dashed or solid; arms: dashed; yellow
or white), broken lines between lanes of one direction, a solid edge line. Not modelled: where the world breaks its
marks (junction mouths, crosswalks), crosswalks and stop lines. A T-junction's sidewalk runs on across the junction
mouth on the side without an arm, as a sidewalk connecting road in the junction.

**Road maps (scenes that carry a RoadMap but no procedural world).** Each lane centreline becomes a road of one
driving lane (``DEFAULT_LANE_WIDTH_M`` wide, centred on the line) whose reference line runs through every vertex of
the centreline as G1-continuous circular arcs and straight pieces (``nuscenes_map.arcline_paths``): exact at the
vertices, approximate between them. Lanes are not linked (a RoadMap records no topology).

**Recorded nuScenes logs: from the map expansion.** A store whose manifest names a nuScenes location gets its roads
from that location's map expansion (``<dataroot>/maps/expansion/<location>.json``: the log's own dataroot, which its
manifest records, or one given as ``nuscenes_maps``, which a variant store needs). Every lane and lane connector
whose path (the chords of its arcline pieces) comes within ``EXPANSION_MARGIN_M`` of the box around the scene's ego
poses and boxes becomes a road of one driving
lane: its reference line is the lane's ``arcline_path_3`` (circular arcs and straight pieces, which OpenDRIVE states
exactly, moved from the global frame into the scene's world frame by the log's ``global_from_world``: its heading
about z; the expansion is flat), its width the lane polygon's area over its length. The area entities must stay in
is the expansion's drivable area. Lanes are not linked (no junctions are built from the connectivity table).

A scene with none of these raises an OmniscsError naming what to give.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.export.nuscenes_map import DEFAULT_LANE_WIDTH_M, arcline_paths
from omniscs.roadmap import RoadMap
from omniscs.scene.store import Scene

#: OpenDRIVE version written (1.7: ASAM's checker applies all its rules but one, which starts at 1.8, to it).
ODR_MAJOR, ODR_MINOR = 1, 7
#: The header's date: fixed, so the same scene always gives the same file.
HEADER_DATE = "2000-01-01T00:00:00"
#: Gauss-Legendre nodes per piece and pieces of a connecting road when its arc length is integrated.
ARC_LENGTH_NODES, ARC_LENGTH_PIECES = 32, 64
#: Largest distance between the layout's junction path samples and the Bezier fitted through them (metres); more
#: means the layout's paths are no longer cubic Beziers and the export would not be exact.
BEZIER_FIT_TOLERANCE_M = 1e-6
#: Width of painted lines (metres; the world paints 13 cm lines).
MARK_WIDTH_M = 0.13
#: Map-expansion lanes within this of the scene's ego poses and boxes are exported (metres).
EXPANSION_MARGIN_M = 50.0
#: Largest map-expansion file read (the largest nuScenes expansion is about 150 MB).
MAX_EXPANSION_BYTES = 512 * 2**20
#: Lane widths estimated from a map-expansion lane polygon are clamped to this range (metres).
LANE_WIDTH_RANGE_M = (2.0, 6.0)


@dataclass(frozen=True)
class RoadNetwork:
    """A scene's road network: the OpenDRIVE document and the area entities of its scenarios may occupy."""

    xodr: bytes
    """The ``.xodr`` document (UTF-8)."""
    area: object
    """Where the network's lanes are (drivable area and sidewalks): a shapely geometry in world xy (metres)."""
    source: str
    """"procedural" (exact, from the world's layout), "nuscenes_expansion" (a recorded nuScenes log's map expansion)
    or "road_map" (from a RoadMap's lane centrelines)."""


def road_source_id(scene: Scene) -> str:
    """The scene whose roads a store drives on: a variant's source scene, else the store's own id."""
    return str(scene.manifest.get("source_scene_id") or scene.scene_id)


def road_network_of(scene: Scene, nuscenes_maps: str | Path | None = None) -> RoadNetwork:
    """The road network of a scene (named after its source scene, so the variants of one scene share it): exact for
    procedural worlds, from the nuScenes map expansion for recorded nuScenes logs (``nuscenes_maps``: a dataroot
    holding ``maps/expansion``; default the log's own), from the RoadMap otherwise; an OmniscsError for a scene that
    has none of these."""
    world = scene.world
    if world is not None:
        from omniscs.world.layouts import layout_for

        return procedural_network(layout_for(world), name=road_source_id(scene))
    expansion = expansion_path(scene, nuscenes_maps)
    if expansion is not None:
        return expansion_network(expansion, scene, name=road_source_id(scene))
    road_map = scene.road_map
    if road_map is None:
        where = f" in {nuscenes_maps}" if nuscenes_maps is not None else ""
        raise OmniscsError(f"scene {scene.scene_id} has no road map (no procedural world, no nuScenes map "
                           f"expansion{where} for its location {scene.manifest.get('location')!r}), so no OpenDRIVE "
                           "road network can be written for it; for a recorded nuScenes log give its dataroot's maps "
                           "(--nuscenes-maps DATAROOT), else export procedural scenes")
    return road_map_network(road_map, name=road_source_id(scene))


def expansion_path(scene: Scene, nuscenes_maps: str | Path | None = None) -> Path | None:
    """The nuScenes map expansion of a store's location: under ``nuscenes_maps`` when given, else under the dataroot
    the store was read from; None when the store names no location or the file is not there."""
    location = scene.manifest.get("location")
    if not isinstance(location, str) or scene.manifest.get("global_from_world") is None:
        return None
    source = scene.manifest.get("source") or {}
    root = nuscenes_maps if nuscenes_maps is not None else (
        source.get("dataroot") if source.get("kind") == "nuscenes" else None)
    if root is None:
        return None
    path = Path(root) / "maps" / "expansion" / f"{location}.json"
    return path if path.is_file() else None


# ----------------------------------------------------------------------------- procedural layouts
@dataclass(frozen=True)
class _Road:
    """One straight road of a layout: its reference line and its cross-section (lane widths outwards)."""

    road_id: int
    start: np.ndarray  # [2] world xy
    heading: float  # radians
    length: float  # metres
    left: tuple[tuple[str, float], ...]  # (lane type, width) for lanes 1, 2, ...
    right: tuple[tuple[str, float], ...]  # (lane type, width) for lanes -1, -2, ...

    def local(self, xy: np.ndarray) -> tuple[float, float]:  # [2] world -> (s along, t left of) the reference line
        d = np.asarray(xy, np.float64) - self.start
        c, s = math.cos(self.heading), math.sin(self.heading)
        return float(c * d[0] + s * d[1]), float(-s * d[0] + c * d[1])


def _cross_section(n_driving: int, lane_width: float, parking: float, sidewalk: float) -> tuple:
    lanes = [("driving", lane_width)] * n_driving
    if parking > 0:
        lanes.append(("parking", parking))
    lanes.append(("sidewalk", sidewalk))
    return tuple(lanes)


def _layout_roads(layout) -> list[_Road]:
    """The straight roads of a procedural layout, in the world frame (see the module docstring)."""
    from omniscs.world.layouts import X_MAX, X_MIN, Y_ARM_MAX

    p = layout.params
    lw, n, nc, sw = p["lane_width"], p["lanes_per_dir"], p["cross_lanes_per_dir"], p["sidewalk_width"]
    park_left = p["parking_width"] if p["parking_left"] else 0.0
    park_right = p["parking_width"] if p["parking_right"] else 0.0
    oy = float(layout.world_from_map[1, 3])  # the world frame is the map frame moved along y
    left = _cross_section(n, lw, park_left, sw)
    right = _cross_section(n, lw, park_right, sw)
    arms = tuple(p["arms"])
    if not arms:
        return [_Road(1, np.array([X_MIN, oy]), 0.0, X_MAX - X_MIN, left, right)]
    xj, wc = p["junction_x"], nc * lw
    w_left, w_right = n * lw + park_left, n * lw + park_right
    roads = [_Road(1, np.array([X_MIN, oy]), 0.0, (xj - wc) - X_MIN, left, right),
             _Road(2, np.array([xj + wc, oy]), 0.0, X_MAX - (xj + wc), left, right)]
    arm_section = _cross_section(nc, lw, 0.0, sw)
    if 1 in arms:  # north arm: from the junction box's edge towards +y
        roads.append(_Road(3, np.array([xj, oy + w_left]), math.pi / 2, Y_ARM_MAX - w_left, arm_section, arm_section))
    if -1 in arms:  # south arm: from the junction box's edge towards -y
        roads.append(_Road(4, np.array([xj, oy - w_right]), -math.pi / 2, Y_ARM_MAX - w_right, arm_section,
                           arm_section))
    return roads


def _lane_place(roads: list[_Road], centreline: np.ndarray) -> tuple[_Road, int]:
    """The road and OpenDRIVE lane id a layout lane lies on (its middle point), checking its driving direction."""
    mid = centreline[len(centreline) // 2] if len(centreline) > 2 else centreline.mean(0)
    direction = centreline[-1] - centreline[0]
    for road in roads:
        s, t = road.local(mid)
        if not 0.0 <= s <= road.length:
            continue
        offsets = np.cumsum([0.0] + [w for _, w in (road.left if t > 0 else road.right)])
        k = int(np.searchsorted(offsets, abs(t)))  # 1-based lane number outwards
        if 1 <= k <= len(offsets) - 1:
            along = math.cos(road.heading) * direction[0] + math.sin(road.heading) * direction[1]
            lane_id = k if t > 0 else -k
            if (lane_id < 0) != (along > 0):
                raise OmniscsError(f"layout lane at {mid.round(2).tolist()} drives against the right-hand traffic "
                                   f"of road {road.road_id}; the layout and the OpenDRIVE export disagree")
            return road, lane_id
    raise OmniscsError(f"layout lane at {mid.round(2).tolist()} lies on no road of the layout; the layout and the "
                       "OpenDRIVE export disagree")


def bezier_controls(samples: np.ndarray) -> np.ndarray:  # [N, 2] samples at t = linspace(0, 1, N) -> [4, 2]
    """The control points of the cubic Bezier curve through evenly parameterised samples (least squares; exact for
    samples of a cubic Bezier, as the layout's junction paths are)."""
    t = np.linspace(0.0, 1.0, len(samples))[:, None]
    basis = np.concatenate([(1 - t) ** 3, 3 * (1 - t) ** 2 * t, 3 * (1 - t) * t ** 2, t ** 3], axis=1)
    controls, *_ = np.linalg.lstsq(basis, samples, rcond=None)
    error = float(np.abs(basis @ controls - samples).max())
    if error > BEZIER_FIT_TOLERANCE_M:
        raise OmniscsError(f"a junction path is not a cubic Bezier curve (fit error {error:.2g} m); the OpenDRIVE "
                           "export of this layout would not be exact")
    return controls


def bezier_poly3(controls: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """A cubic Bezier [4, 2] as OpenDRIVE's ``paramPoly3`` (pRange normalized): (start xy [2], heading, coefficients
    [2, 4]: aU..dU, aV..dV in the frame at the start point whose u axis points along the heading)."""
    p0, c0, c1, p1 = controls
    power = np.stack([p0 * 0.0, 3 * (c0 - p0), 3 * (p0 - 2 * c0 + c1), p1 - 3 * c1 + 3 * c0 - p0])  # [4, 2]
    heading = math.atan2(*(c0 - p0)[::-1])
    c, s = math.cos(heading), math.sin(heading)
    u = power @ np.array([c, s])
    v = power @ np.array([-s, c])
    return p0.copy(), heading, np.stack([u, v])


def bezier_length(controls: np.ndarray) -> float:
    """Arc length of a cubic Bezier [4, 2] (piecewise Gauss-Legendre quadrature of its speed)."""
    nodes, weights = np.polynomial.legendre.leggauss(ARC_LENGTH_NODES)
    edges = np.linspace(0.0, 1.0, ARC_LENGTH_PIECES + 1)
    half = 0.5 * (edges[1:] - edges[:-1])
    t = ((edges[:-1] + edges[1:]) / 2)[:, None] + half[:, None] * nodes[None]  # [P, Q]
    p0, c0, c1, p1 = controls
    d = (3 * (1 - t[..., None]) ** 2 * (c0 - p0) + 6 * (1 - t[..., None]) * t[..., None] * (c1 - c0)
         + 3 * t[..., None] ** 2 * (p1 - c1))
    speed = np.linalg.norm(d, axis=-1)
    return float((speed * weights[None] * half[:, None]).sum())


def procedural_network(layout, name: str = "omniscs") -> RoadNetwork:
    """The exact OpenDRIVE network of a procedural layout (see the module docstring)."""
    from scenariogeneration import xodr

    roads = _layout_roads(layout)
    kerb = layout.params["kerb_height"]
    centre_mark = {"double_solid": xodr.RoadMarkType.solid_solid, "dashed": xodr.RoadMarkType.broken,
                   "solid": xodr.RoadMarkType.solid}[layout.params["centre_line"]]
    centre_colour = xodr.RoadMarkColor.yellow if layout.params["centre_yellow"] else xodr.RoadMarkColor.white
    odr = xodr.OpenDrive(name, revMajor=str(ODR_MAJOR), revMinor=str(ODR_MINOR))
    built = {}
    for road in roads:
        plan = xodr.PlanView()
        plan.add_fixed_geometry(xodr.Line(road.length), float(road.start[0]), float(road.start[1]), road.heading)
        centre = xodr.Lane(lane_type=xodr.LaneType.none)
        arm = road.road_id > 2  # the world dashes the cross arms' centre lines
        centre.add_roadmark(xodr.RoadMark(xodr.RoadMarkType.broken if arm else centre_mark, MARK_WIDTH_M,
                                          color=centre_colour))
        section = xodr.LaneSection(0, centre)
        for side, lanes in ((1, road.left), (-1, road.right)):
            for k, (kind, width) in enumerate(lanes):
                lane = xodr.Lane(lane_type=getattr(xodr.LaneType, kind), a=float(width))
                if kind == "sidewalk":  # the slab stands on its kerb
                    lane.add_height(float(kerb), float(kerb))
                next_kind = lanes[k + 1][0] if k + 1 < len(lanes) else None
                if kind == "driving":
                    mark = xodr.RoadMarkType.broken if next_kind == "driving" else xodr.RoadMarkType.solid
                    lane.add_roadmark(xodr.RoadMark(mark, MARK_WIDTH_M, color=xodr.RoadMarkColor.white))
                (section.add_left_lane if side > 0 else section.add_right_lane)(lane)
        lanes = xodr.Lanes()
        lanes.add_lanesection(section)
        built[road.road_id] = xodr.Road(road.road_id, plan, lanes, name=f"road {road.road_id}")
    connectors = [lane for lane in layout.lanes.values() if lane.kind == "connector"]
    if connectors:
        junction_id = 100
        junction = xodr.Junction("junction", junction_id)
        places = {lane.lane_id: _lane_place(roads, np.asarray(lane.centreline, np.float64))
                  for lane in layout.lanes.values() if lane.kind == "lane"}
        for road in roads:
            if road.road_id == 1:  # the west road ends at the junction, every other road starts there
                built[1].add_successor(xodr.ElementType.junction, junction_id)
            else:
                built[road.road_id].add_predecessor(xodr.ElementType.junction, junction_id)
        sources = {succ: lane.lane_id for lane in layout.lanes.values() for succ in lane.successors}
        for i, lane in enumerate(sorted(connectors, key=lambda c: c.lane_id)):
            road_id = 101 + i
            controls = bezier_controls(np.asarray(lane.centreline, np.float64))
            start, heading, (u, v) = bezier_poly3(controls)
            length = bezier_length(controls)
            plan = xodr.PlanView()
            plan.add_fixed_geometry(xodr.ParamPoly3(*u, *v, "normalized", length), float(start[0]),
                                    float(start[1]), heading)
            width = float(lane.width)
            path_lane = xodr.Lane(lane_type=xodr.LaneType.driving, a=width)
            (src_road, src_lane), (dst_road, dst_lane) = places[sources[lane.lane_id]], places[lane.successors[0]]
            path_lane.add_link("predecessor", src_lane)
            path_lane.add_link("successor", dst_lane)
            path = xodr.Road(road_id, plan, _centred_lane(path_lane, width), road_type=junction_id, name=lane.lane_id)
            # incoming lanes of the west road (ids < 0) leave at its end; every other road's at its start
            src_contact = xodr.ContactPoint.end if src_road.road_id == 1 and src_lane < 0 else xodr.ContactPoint.start
            dst_contact = xodr.ContactPoint.end if dst_road.road_id == 1 and dst_lane > 0 else xodr.ContactPoint.start
            path.add_predecessor(xodr.ElementType.road, src_road.road_id, src_contact)
            path.add_successor(xodr.ElementType.road, dst_road.road_id, dst_contact)
            built[road_id] = path
            connection = xodr.Connection(src_road.road_id, road_id, xodr.ContactPoint.start)
            connection.add_lanelink(src_lane, -1)
            junction.add_connection(connection)
        west, east = roads[0], roads[1]
        for side in (1, -1):  # a side without an arm keeps its sidewalk across the junction mouth
            if side in layout.params["arms"]:
                continue
            section = west.left if side > 0 else west.right
            kind, width = section[-1]
            offset = sum(w for _, w in section[:-1]) + width / 2  # from the reference line to the sidewalk's middle
            start = west.start + np.array([west.length, side * offset])
            road_id = 101 + len(connectors) + (0 if side > 0 else 1)
            plan = xodr.PlanView()
            plan.add_fixed_geometry(xodr.Line(float(east.start[0] - start[0])), float(start[0]), float(start[1]),
                                    0.0)
            walk = xodr.Lane(lane_type=xodr.LaneType.sidewalk, a=float(width))
            walk.add_height(float(kerb), float(kerb))
            lane_id = side * len(section)
            walk.add_link("predecessor", lane_id)
            walk.add_link("successor", lane_id)
            path = xodr.Road(road_id, plan, _centred_lane(walk, float(width)), road_type=junction_id,
                             name=f"sidewalk {'left' if side > 0 else 'right'}")
            path.add_predecessor(xodr.ElementType.road, west.road_id, xodr.ContactPoint.end)
            path.add_successor(xodr.ElementType.road, east.road_id, xodr.ContactPoint.start)
            built[road_id] = path
            connection = xodr.Connection(west.road_id, road_id, xodr.ContactPoint.start)
            connection.add_lanelink(lane_id, -1)
            junction.add_connection(connection)
        odr.add_junction(junction)
    for road_id in sorted(built):
        odr.add_road(built[road_id])
    return RoadNetwork(_document(odr), _union([*layout.drivable_polygons, *layout.sidewalk_polygons]), "procedural")


# ----------------------------------------------------------------------------- road maps
def road_map_network(road_map: RoadMap, name: str = "omniscs") -> RoadNetwork:
    """An OpenDRIVE network from a RoadMap's lane centrelines (see the module docstring)."""
    from scenariogeneration import xodr

    odr = xodr.OpenDrive(name, revMajor=str(ODR_MAJOR), revMinor=str(ODR_MINOR))
    road_id = 0
    for line in road_map.lane_centrelines:
        pieces = arcline_paths(np.asarray(line, np.float64))
        if not pieces:
            continue
        road_id += 1
        plan = xodr.PlanView()
        s = 0.0
        for piece in pieces:
            x, y, heading = piece["start_pose"]
            if piece["segment_length"][1] > 0:  # a straight piece
                geometry = xodr.Line(piece["segment_length"][1])
            else:
                curvature = (1.0 if piece["shape"] == "LSL" else -1.0) / piece["radius"]
                geometry = xodr.Arc(curvature, length=piece["segment_length"][0])
            plan.add_fixed_geometry(geometry, x, y, heading, s=s)
            s += sum(piece["segment_length"])
        lanes = _centred_lane(xodr.Lane(lane_type=xodr.LaneType.driving, a=DEFAULT_LANE_WIDTH_M), DEFAULT_LANE_WIDTH_M)
        odr.add_road(xodr.Road(road_id, plan, lanes, name=f"lane {road_id}"))
    if road_id == 0:
        raise OmniscsError("the scene's road map has no lane centreline, so no OpenDRIVE road can be written; "
                           "export scenes whose road map has lanes")
    return RoadNetwork(_document(odr), _union(road_map.drivable_polygons), "road_map")


# ----------------------------------------------------------------------------- nuScenes map expansions
def _expansion_xy(expansion: dict, world_from_global: np.ndarray):
    """(node token -> world xy [2]) of a map expansion, moved by the planar part of ``world_from_global``."""
    nodes = {n["token"]: (float(n["x"]), float(n["y"])) for n in expansion.get("node", [])}
    R, t = world_from_global[:2, :2], world_from_global[:2, 3]
    return lambda token: R @ np.asarray(nodes[token]) + t


def _arcline_segments(path: dict) -> list[tuple[float, float]]:  # -> [(curvature 1/m, length m)] of one record
    radius = float(path["radius"])
    out = []
    for letter, length in zip(path["shape"], path["segment_length"]):
        if float(length) > 1e-9:
            out.append((0.0 if letter == "S" else (1.0 if letter == "L" else -1.0) / radius, float(length)))
    return out


def expansion_network(path: str | Path, scene: Scene, name: str = "omniscs") -> RoadNetwork:
    """An OpenDRIVE network from a nuScenes map expansion, around ``scene`` (see the module docstring)."""
    from scenariogeneration import xodr
    from shapely.geometry import LineString, Polygon
    from shapely.geometry import box as shapely_box

    from omniscs.geometry import invert_transform
    from omniscs.scene.sources.common import global_from_world_of
    from omniscs.untrusted import read_json

    expansion = read_json(path, "give the map expansion of the log's nuScenes dataroot", expect=dict,
                          max_bytes=MAX_EXPANSION_BYTES, what="nuScenes map expansion")
    world_from_global = invert_transform(global_from_world_of(scene))
    turn = math.atan2(world_from_global[1, 0], world_from_global[0, 0])
    def to_world(xy) -> np.ndarray:  # global xy [2] -> world xy [2]
        return world_from_global[:2, :2] @ np.asarray(xy, np.float64) + world_from_global[:2, 3]

    try:
        xy_of = _expansion_xy(expansion, world_from_global)
        polygons = {p["token"]: p for p in expansion.get("polygon", [])}

        def ring(token: str) -> Polygon:
            record = polygons[token]
            return Polygon([xy_of(n) for n in record["exterior_node_tokens"]],
                           [[xy_of(n) for n in hole["node_tokens"]] for hole in record.get("holes", [])])

        reach = [scene.world_from_ego_all[:, :2, 3]]
        if len(scene.boxes):
            reach.append(scene.boxes[["cx", "cy"]].to_numpy(np.float64))
        reach = np.concatenate(reach)
        region = shapely_box(*(reach.min(0) - EXPANSION_MARGIN_M), *(reach.max(0) + EXPANSION_MARGIN_M))
        odr = xodr.OpenDrive(name, revMajor=str(ODR_MAJOR), revMinor=str(ODR_MINOR))
        lanes_by_token = {r["token"]: r for r in [*expansion.get("lane", []), *expansion.get("lane_connector", [])]}
        road_id = 0
        for token, paths in sorted(expansion.get("arcline_path_3", {}).items()):
            chords = [LineString([to_world(p["start_pose"][:2]), to_world(p["end_pose"][:2])]) for p in paths]
            if not any(chord.intersects(region) for chord in chords):
                continue
            plan, s_total = xodr.PlanView(), 0.0
            for p in paths:
                x, y = to_world(p["start_pose"][:2])
                heading = float(p["start_pose"][2]) + turn
                for curvature, length in _arcline_segments(p):
                    geometry = xodr.Line(length) if curvature == 0.0 else xodr.Arc(curvature, length=length)
                    plan.add_fixed_geometry(geometry, float(x), float(y), heading, s=s_total)
                    s_total += length
                    if curvature == 0.0:
                        x, y = x + length * math.cos(heading), y + length * math.sin(heading)
                    else:
                        end = heading + curvature * length
                        x += (math.sin(end) - math.sin(heading)) / curvature
                        y += (math.cos(heading) - math.cos(end)) / curvature
                        heading = end
            if s_total <= 0.0:
                continue
            width = DEFAULT_LANE_WIDTH_M
            lane = lanes_by_token.get(token)
            if lane is not None and lane.get("polygon_token") in polygons:
                width = float(np.clip(ring(lane["polygon_token"]).area / s_total, *LANE_WIDTH_RANGE_M))
            road_id += 1
            lanes = _centred_lane(xodr.Lane(lane_type=xodr.LaneType.driving, a=width), width)
            odr.add_road(xodr.Road(road_id, plan, lanes, name=f"nuScenes lane {token}"))
        area = [ring(token) for record in expansion.get("drivable_area", [])
                for token in record.get("polygon_tokens", [])]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise OmniscsError(f"{path} is not a readable nuScenes map expansion ({type(exc).__name__}: {exc}); give "
                           "the map expansion of the log's nuScenes dataroot") from None
    if road_id == 0:
        raise OmniscsError(f"the map expansion {path} has no lane within {EXPANSION_MARGIN_M:g} m of scene "
                           f"{scene.scene_id}; give the expansion of the location the log was recorded in")
    return RoadNetwork(_document(odr), _union(area), "nuscenes_expansion")


def _centred_lane(lane, width: float):  # xodr.Lane, metres -> xodr.Lanes
    """The lanes of a road that is one lane centred on its reference line (a junction path, a sidewalk across a
    junction mouth, a road-map or map-expansion centreline): an empty centre lane, ``lane`` on its right, the
    reference line moved half the lane's width to the left."""
    from scenariogeneration import xodr

    section = xodr.LaneSection(0, xodr.Lane(lane_type=xodr.LaneType.none))
    section.add_right_lane(lane)
    lanes = xodr.Lanes()
    lanes.add_laneoffset(xodr.LaneOffset(0, width / 2))
    lanes.add_lanesection(section)
    return lanes


def _union(polygons) -> object:  # [[K, 2] arrays or shapely polygons] -> one shapely geometry
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    return unary_union([p if hasattr(p, "geom_type") else Polygon(np.asarray(p, np.float64)) for p in polygons])


def _document(odr) -> bytes:
    """The OpenDRIVE document as bytes, its header date fixed (scenariogeneration writes the current time)."""
    import xml.etree.ElementTree as ET

    root = odr.get_element()
    header = root.find("header")
    if header is not None:
        header.set("date", HEADER_DATE)
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)
