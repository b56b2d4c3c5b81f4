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

Not modelled: kerb heights (all lanes lie at z = 0; sidewalks are 12-18 cm higher in the world), road marks other
than the centre line and the lane separators, and the T-junction's sidewalk across the junction mouth on the side
without an arm (the junction holds driving paths only).

**Road maps (scenes that carry a RoadMap but no procedural world).** Each lane centreline becomes a road of one
driving lane (``DEFAULT_LANE_WIDTH_M`` wide, centred on the line) whose reference line runs through every vertex of
the centreline as G1-continuous circular arcs and straight pieces (``nuscenes_map.arcline_paths``): exact at the
vertices, approximate between them. Lanes are not linked (a RoadMap records no topology).

A scene with neither raises an OmniscsError: recorded logs carry no map in their stores.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

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


@dataclass(frozen=True)
class RoadNetwork:
    """A scene's road network: the OpenDRIVE document and the area entities of its scenarios may occupy."""

    xodr: bytes
    """The ``.xodr`` document (UTF-8)."""
    area: tuple[np.ndarray, ...]
    """Polygons [K, 2] (world xy) whose union is where the network's lanes are: drivable area and sidewalks."""
    source: str
    """"procedural" (exact, from the world's layout) or "road_map" (from a RoadMap's lane centrelines)."""


def road_source_id(scene: Scene) -> str:
    """The scene whose roads a store drives on: a variant's source scene, else the store's own id."""
    return str(scene.manifest.get("source_scene_id") or scene.scene_id)


def road_network_of(scene: Scene) -> RoadNetwork:
    """The road network of a scene (named after its source scene, so the variants of one scene share it): exact for
    procedural worlds, from the RoadMap otherwise; an OmniscsError for a scene that has neither."""
    world = scene.world
    if world is not None:
        from omniscs.world.layouts import layout_for

        return procedural_network(layout_for(world), name=road_source_id(scene))
    road_map = scene.road_map
    if road_map is None:
        raise OmniscsError(f"scene {scene.scene_id} has no road map (a recorded log's store carries none), so no "
                           "OpenDRIVE road network can be written for it; export procedural scenes or scenes whose "
                           "store has a road map")
    return road_map_network(road_map, name=road_source_id(scene))


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
    odr = xodr.OpenDrive(name, revMajor=str(ODR_MAJOR), revMinor=str(ODR_MINOR))
    built = {}
    for road in roads:
        plan = xodr.PlanView()
        plan.add_fixed_geometry(xodr.Line(road.length), float(road.start[0]), float(road.start[1]), road.heading)
        centre = xodr.Lane(lane_type=xodr.LaneType.none)
        centre.add_roadmark(xodr.RoadMark(xodr.RoadMarkType.solid, 0.13))
        section = xodr.LaneSection(0, centre)
        for side, lanes in ((1, road.left), (-1, road.right)):
            for k, (kind, width) in enumerate(lanes):
                lane = xodr.Lane(lane_type=getattr(xodr.LaneType, kind), a=float(width))
                next_kind = lanes[k + 1][0] if k + 1 < len(lanes) else None
                if kind == "driving":
                    mark = xodr.RoadMarkType.broken if next_kind == "driving" else xodr.RoadMarkType.solid
                    lane.add_roadmark(xodr.RoadMark(mark, 0.13))
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
            centre = xodr.Lane(lane_type=xodr.LaneType.none)
            path_lane = xodr.Lane(lane_type=xodr.LaneType.driving, a=width)
            (src_road, src_lane), (dst_road, dst_lane) = places[sources[lane.lane_id]], places[lane.successors[0]]
            path_lane.add_link("predecessor", src_lane)
            path_lane.add_link("successor", dst_lane)
            section = xodr.LaneSection(0, centre)
            section.add_right_lane(path_lane)
            lanes = xodr.Lanes()
            lanes.add_laneoffset(xodr.LaneOffset(0, width / 2))  # the lane is centred on the path
            lanes.add_lanesection(section)
            path = xodr.Road(road_id, plan, lanes, road_type=junction_id, name=lane.lane_id)
            # incoming lanes of the west road (ids < 0) leave at its end; every other road's at its start
            src_contact = xodr.ContactPoint.end if src_road.road_id == 1 and src_lane < 0 else xodr.ContactPoint.start
            dst_contact = xodr.ContactPoint.end if dst_road.road_id == 1 and dst_lane > 0 else xodr.ContactPoint.start
            path.add_predecessor(xodr.ElementType.road, src_road.road_id, src_contact)
            path.add_successor(xodr.ElementType.road, dst_road.road_id, dst_contact)
            built[road_id] = path
            connection = xodr.Connection(src_road.road_id, road_id, xodr.ContactPoint.start)
            connection.add_lanelink(src_lane, -1)
            junction.add_connection(connection)
        odr.add_junction(junction)
    for road_id in sorted(built):
        odr.add_road(built[road_id])
    area = tuple(np.asarray(p, np.float64) for p in (*layout.drivable_polygons, *layout.sidewalk_polygons))
    return RoadNetwork(_document(odr), area, "procedural")


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
        centre = xodr.Lane(lane_type=xodr.LaneType.none)
        section = xodr.LaneSection(0, centre)
        section.add_right_lane(xodr.Lane(lane_type=xodr.LaneType.driving, a=DEFAULT_LANE_WIDTH_M))
        lanes = xodr.Lanes()
        lanes.add_laneoffset(xodr.LaneOffset(0, DEFAULT_LANE_WIDTH_M / 2))
        lanes.add_lanesection(section)
        odr.add_road(xodr.Road(road_id, plan, lanes, name=f"lane {road_id}"))
    if road_id == 0:
        raise OmniscsError("the scene's road map has no lane centreline, so no OpenDRIVE road can be written; "
                           "export scenes whose road map has lanes")
    area = tuple(np.asarray(p, np.float64) for p in road_map.drivable_polygons)
    return RoadNetwork(_document(odr), area, "road_map")


def _document(odr) -> bytes:
    """The OpenDRIVE document as bytes, its header date fixed (scenariogeneration writes the current time)."""
    import xml.etree.ElementTree as ET

    root = odr.get_element()
    header = root.find("header")
    if header is not None:
        header.set("date", HEADER_DATE)
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)
