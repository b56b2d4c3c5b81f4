"""OpenSCENARIO + OpenDRIVE export: the trajectories, entities and boxes read back from the .xosc equal the variant
stores' (within 1 cm), the .xodr lanes lie exactly on the procedural layout's lanes, ASAM's checkers find no error
in either file, and bad input (an agent leaving the roads, a scene without roads, a damaged variant file) is one
clear error with nothing written."""
import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from omniscs.errors import OmniscsError
from omniscs.export import export_scenes
from omniscs.export.asam_checks import check_file, checker_versions
from omniscs.export.opendrive import bezier_controls, procedural_network, road_map_network
from omniscs.export.openscenario import (
    INDEX_JSON,
    OSC_CATEGORIES,
    OpenScenarioConfig,
    angle_error,
    hpr_from_matrix,
    read_scenario,
    road_file_of,
)
from omniscs.geometry import rotmat_from_euler, yaw_from_matrix
from omniscs.quaternions import quat_to_rotmat
from omniscs.roadmap import RoadMap
from omniscs.scene import load_scene
from omniscs.world.layouts import build_layout
from tests.conftest import write_tiny_scene
from tests.dataset_fixtures import leftovers
from tests.export.openscenario_fixtures import (INSERTED_TRACK, adversarial_boxes, moving_track, source_scene,
                                                variant_store, variant_stores)

#: The round trip's tolerance on positions (the issue's 1 cm) and on angles (radians).
ROUND_TRIP_M = 0.01
ROUND_TRIP_RAD = 1e-6


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return source_scene(tmp_path_factory)


@pytest.fixture(scope="module")
def variants(tmp_path_factory) -> list[Path]:
    return variant_stores(tmp_path_factory)


@pytest.fixture(scope="module")
def exported(variants, tmp_path_factory) -> Path:
    return export_scenes(variants, "openscenario", tmp_path_factory.mktemp("xosc-out") / "xosc")


def test_every_variant_gets_a_scenario_and_they_share_the_scene_road_network(exported, variants, scene):
    index = json.loads((exported / INDEX_JSON).read_text())
    assert [s["scene_id"] for s in index["scenarios"]] == ["beh-v000", "app-v000"]
    assert {road_file_of(exported / s["scenario"]) for s in index["scenarios"]} == {f"{scene.scene_id}.xodr"}
    assert (exported / f"{scene.scene_id}.xodr").is_file()
    assert all(s["roads"] == "procedural" for s in index["scenarios"])


def test_trajectories_read_back_equal_the_stores_within_a_centimetre(exported, variants):
    for store in variants:
        scene = load_scene(store)
        read = read_scenario(exported / f"{scene.scene_id}.xosc")
        times = (scene.frames["timestamp_us"].to_numpy(np.int64) - scene.frames["timestamp_us"].iloc[0]) / 1e6
        ego = read["ego"]
        assert ego.timing == "absolute"
        np.testing.assert_allclose(ego.times_s, times, atol=1e-9)
        poses = scene.world_from_ego_all
        assert np.abs(ego.poses[:, :3] - poses[:, :3, 3]).max() < ROUND_TRIP_M
        assert angle_error(ego.poses[:, 3], yaw_from_matrix(poses[:, :3, :3])).max() < ROUND_TRIP_RAD
        assert len(read) == 1 + scene.boxes.track_id.nunique()
        for track_id, rows in scene.boxes.groupby("track_id"):
            rows = rows.sort_values("frame_idx")
            entity = next(e for e in read.values() if e.name.endswith(f"_{track_id}"))
            size = rows[["length", "width", "height"]].to_numpy()[0]
            np.testing.assert_allclose(entity.size, size, atol=1e-9)
            centres = rows[["cx", "cy", "cz"]].to_numpy()
            R_store = quat_to_rotmat(rows[["qw", "qx", "qy", "qz"]].to_numpy())
            if len(entity.times_s):  # a moving entity: every vertex, at its frame's time
                np.testing.assert_allclose(entity.times_s, times[rows.frame_idx.to_numpy()], atol=1e-9)
                poses = entity.poses
            else:  # standing still: its initial position is every pose
                assert np.ptp(centres, axis=0).max() < 1e-6
                poses = np.repeat(entity.initial[None], len(rows), axis=0)
            R_read = np.stack([rotmat_from_euler(r, p, h) for h, p, r in poses[:, 3:]])
            centre_read = poses[:, :3] + R_read @ entity.centre  # the reference point and its box Center
            assert np.abs(centre_read - centres).max() < ROUND_TRIP_M, entity.name
            assert np.abs(R_read - R_store).max() < ROUND_TRIP_RAD, entity.name
            np.testing.assert_allclose(entity.initial, poses[0], atol=1e-9)


def test_entities_carry_their_opendrive_category_and_the_inserted_object_is_an_overturned_misc_object(exported):
    behaviour = read_scenario(exported / "beh-v000.xosc")
    for entity in behaviour.values():
        if entity.name == "ego":
            assert (entity.object_type, entity.category) == ("Vehicle", "car")
            continue
        category = entity.name.rsplit("_", 1)[0]
        assert (entity.object_type, entity.category) == OSC_CATEGORIES[category]
    appearance = read_scenario(exported / "app-v000.xosc")
    truck = appearance[f"object_{INSERTED_TRACK}"]
    assert (truck.object_type, truck.category) == ("MiscObject", "obstacle")
    assert len(truck.times_s) == 0  # standing still: placed once, no trajectory
    assert angle_error(truck.initial[5], math.pi) < 1e-9  # overturned: roll 180 degrees
    np.testing.assert_allclose(truck.size, [8.0, 2.5, 2.8])
    np.testing.assert_allclose(truck.centre, [0.0, 0.0, 1.4])


def test_every_category_of_the_taxonomy_has_an_openscenario_counterpart():
    from omniscs.taxonomy import CATEGORIES

    assert set(OSC_CATEGORIES) == set(CATEGORIES)


def test_the_ego_box_matches_the_behaviour_model_and_the_placement_ego():
    from omniscs.scs.appearance.placement.config import EGO_HEIGHT_M
    from omniscs.scs.behavior.tracks import EgoBox

    config, box = OpenScenarioConfig(), EgoBox()
    assert (config.ego_length, config.ego_width, config.ego_centre_ahead_m) == (box.length, box.width,
                                                                                box.centre_ahead_m)
    assert config.ego_height == EGO_HEIGHT_M


def test_asam_checkers_find_no_error_in_the_scenarios_or_the_road_network(exported):
    versions = checker_versions()
    assert set(versions) == {"asam-qc-openscenarioxml", "asam-qc-opendrive"}
    files = sorted(p for p in exported.iterdir() if p.suffix in (".xosc", ".xodr"))
    assert len(files) == 3
    for path in files:
        report = check_file(path)
        assert report.passed, (path.name, report.to_dict())
        assert report.issues["error"] == 0 and report.schema_checked
        assert report.checkers["completed"] >= 15  # the schema, reference and semantic rules ran, not skipped


def test_the_checkers_do_find_errors_in_a_broken_scenario(exported, tmp_path):
    text = (exported / "beh-v000.xosc").read_text()
    broken = tmp_path / "broken.xosc"
    broken.write_text(text.replace('entityRef="ego"', 'entityRef="nobody"', 1))
    (tmp_path / road_file_of(exported / "beh-v000.xosc")).write_bytes(
        (exported / road_file_of(exported / "beh-v000.xosc")).read_bytes())
    report = check_file(broken)
    assert not report.passed and report.issues["error"] >= 1
    bad_road = tmp_path / "bad.xodr"
    bad_road.write_text((exported / road_file_of(exported / "beh-v000.xosc")).read_text()
                        .replace('type="driving"', 'type="highway"', 1))
    assert not check_file(bad_road).passed


@pytest.mark.parametrize("template,seed", [("straight", 0), ("t_junction", 1), ("intersection", 3)])
def test_opendrive_lanes_lie_exactly_on_the_layout_lanes(template, seed):
    layout = build_layout(template, seed)
    root = ET.fromstring(procedural_network(layout).xodr)
    centre_lines = [line for road in root.iter("road") for line in _lane_centre_lines(road)]
    for lane in layout.lanes.values():
        samples = np.asarray(lane.centreline, np.float64)
        if lane.kind == "lane":  # straight: its end points and middle on a lane centre line of its road
            samples = np.stack([samples[0] + (samples[-1] - samples[0]) * f for f in (0.0, 0.37, 1.0)])
        best = min(np.abs(_distances(samples, line)).max() for line in centre_lines)
        assert best < 1e-6, (lane.lane_id, best)


def _reference_line(road: ET.Element, samples: int = 2001) -> np.ndarray:  # -> [K, 2] dense, world frame
    """A road's reference line from its planView (line, arc and paramPoly3 geometries, as OpenDRIVE defines them)."""
    points = []
    for geometry in road.findall("planView/geometry"):
        x0, y0, hdg, length = (float(geometry.get(k)) for k in ("x", "y", "hdg", "length"))
        p = np.linspace(0.0, 1.0, samples)
        poly, arc = geometry.find("paramPoly3"), geometry.find("arc")
        if poly is not None:
            c = {k: float(poly.get(k)) for k in ("aU", "bU", "cU", "dU", "aV", "bV", "cV", "dV")}
            u = c["aU"] + c["bU"] * p + c["cU"] * p ** 2 + c["dU"] * p ** 3
            v = c["aV"] + c["bV"] * p + c["cV"] * p ** 2 + c["dV"] * p ** 3
        elif arc is not None:
            k, s = float(arc.get("curvature")), p * length
            u, v = np.sin(k * s) / k, (1 - np.cos(k * s)) / k
        else:
            u, v = p * length, 0 * p
        points.append(np.stack([x0 + u * math.cos(hdg) - v * math.sin(hdg),
                                y0 + u * math.sin(hdg) + v * math.cos(hdg)], 1))
    return np.concatenate(points)


def _lane_centre_lines(road: ET.Element) -> list[np.ndarray]:
    """[K, 2] centre line samples of every driving lane of a road (dense, in the world frame)."""
    ref = _reference_line(road)
    tangent = np.gradient(ref, axis=0)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], 1) / np.linalg.norm(tangent, axis=1, keepdims=True)
    offset = road.find("lanes/laneOffset")
    base = 0.0 if offset is None else float(offset.get("a"))
    out = []
    for side, sign in (("left", 1.0), ("right", -1.0)):
        lanes = sorted(road.findall(f"lanes/laneSection/{side}/lane"), key=lambda e: abs(int(e.get("id"))))
        edge = 0.0
        for lane in lanes:
            width = float(lane.find("width").get("a"))
            if lane.get("type") == "driving":
                out.append(ref + normal * (base + sign * (edge + width / 2)))
            edge += width
    return out


def _distances(points: np.ndarray, line: np.ndarray) -> np.ndarray:  # [N, 2], dense [K, 2] -> [N] to the polyline
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.einsum("nkd,kd->nk", points[:, None] - a[None], ab) / np.maximum(np.einsum("kd,kd->k", ab, ab), 1e-18)
    t = np.clip(t, 0, 1)
    return np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(axis=1)


@pytest.mark.parametrize("template,seed", [("t_junction", 1), ("intersection", 3)])
def test_asams_own_geometry_code_puts_every_driving_lane_on_a_world_lane(template, seed, tmp_path):
    """The lane middle points that asam-qc-opendrive's geometry code computes from the .xodr (its reading of
    headings, paramPoly3, lane offsets and widths, not ours) lie on the world's lane centrelines."""
    from qc_opendrive.base import utils

    layout = build_layout(template, seed)
    path = tmp_path / "roads.xodr"
    path.write_bytes(procedural_network(layout).xodr)
    root = utils.get_root_without_default_namespace(str(path))
    dense = [_resampled(np.asarray(lane.centreline, np.float64)) for lane in layout.lanes.values()]
    checked = 0
    for road in utils.get_roads(root):
        length = utils.get_road_length(road)
        for section in utils.get_lane_sections(road):
            for lane in utils.get_left_and_right_lanes_from_lane_section(section):
                if lane.get("type") != "driving":
                    continue
                for s in np.linspace(0.0, length, 7)[1:-1]:
                    point = utils.get_middle_point_xyz_at_height_zero_from_lane_by_s(road, section, lane, s)
                    xy = np.array([[point.x, point.y]])
                    assert min(_distances(xy, line)[0] for line in dense) < 1e-4, (road.get("id"), lane.get("id"), s)
                    checked += 1
    assert checked > 20


def _resampled(line: np.ndarray) -> np.ndarray:  # [N, 2] -> dense [K, 2] along the world's lane
    """A straight lane as it is; a junction path (samples of a cubic Bezier) as the Bezier through them, densely."""
    if len(line) <= 2:
        return line
    p0, c0, c1, p1 = bezier_controls(line)
    t = np.linspace(0.0, 1.0, 4001)[:, None]
    return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c0 + 3 * (1 - t) * t ** 2 * c1 + t ** 3 * p1


@pytest.mark.parametrize("template,seed", [("straight", 0), ("t_junction", 1), ("intersection", 3)])
def test_opendrive_lanes_cover_exactly_the_layout_roads_and_sidewalks(template, seed):
    """Driving and parking lanes of the straight roads tile the drivable area outside the junction box; sidewalk
    lanes (the junction mouth's included) tile the sidewalks."""
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    layout = build_layout(template, seed)
    root = ET.fromstring(procedural_network(layout).xodr)
    pieces = {"road": [], "sidewalk": []}
    for road in root.iter("road"):
        geometries = road.findall("planView/geometry")
        if len(geometries) != 1 or geometries[0].find("line") is None:
            continue  # junction paths: curves, checked by the lane centre line test
        g = geometries[0]
        x0, y0, hdg, length = (float(g.get(k)) for k in ("x", "y", "hdg", "length"))
        along, left = np.array([math.cos(hdg), math.sin(hdg)]), np.array([-math.sin(hdg), math.cos(hdg)])
        offset = road.find("lanes/laneOffset")
        base = 0.0 if offset is None else float(offset.get("a"))
        for side, sign in (("left", 1.0), ("right", -1.0)):
            edge = base
            for lane in sorted(road.findall(f"lanes/laneSection/{side}/lane"), key=lambda e: abs(int(e.get("id")))):
                width = float(lane.find("width").get("a"))
                inner, outer = edge, edge + sign * width
                start = np.array([x0, y0])
                ring = [start + left * inner, start + along * length + left * inner,
                        start + along * length + left * outer, start + left * outer]
                pieces["sidewalk" if lane.get("type") == "sidewalk" else "road"].append(Polygon(ring))
                edge = outer
    drivable = unary_union([Polygon(p) for p in layout.drivable_polygons])
    if layout.junction_polygon is not None:
        drivable = drivable.difference(Polygon(layout.junction_polygon))
    sidewalks = unary_union([Polygon(p) for p in layout.sidewalk_polygons])
    for name, truth in (("road", drivable), ("sidewalk", sidewalks)):
        exported = unary_union(pieces[name])
        assert exported.symmetric_difference(truth).area < 1e-6, (name, exported.symmetric_difference(truth).area)


def test_junction_paths_are_refused_when_they_are_not_cubic_beziers():
    t = np.linspace(0, 1, 16)
    circle = np.stack([np.cos(t * np.pi / 2), np.sin(t * np.pi / 2)], 1) * 10.0
    with pytest.raises(OmniscsError, match="not a cubic Bezier"):
        bezier_controls(circle)


def test_a_road_map_becomes_one_checked_road_per_lane(tmp_path):
    arc = np.stack([30 * np.sin(np.linspace(0, 1, 12)), 30 * (1 - np.cos(np.linspace(0, 1, 12)))], 1)
    road_map = RoadMap(drivable_polygons=(np.array([[-5.0, -5], [40, -5], [40, 30], [-5, 30]]),),
                       lane_centrelines=(np.array([[0.0, 0.0], [20.0, 0.0]]), arc),
                       extent_min=np.array([-5.0, -5]), extent_max=np.array([40.0, 30]))
    network = road_map_network(road_map)
    path = tmp_path / "map.xodr"
    path.write_bytes(network.xodr)
    assert check_file(path).passed
    roads = ET.fromstring(network.xodr).findall("road")
    assert len(roads) == 2 and network.source == "road_map"
    lengths = [float(r.get("length")) for r in roads]
    assert lengths[0] == pytest.approx(20.0) and lengths[1] == pytest.approx(30.0, rel=1e-3)


@settings(max_examples=200, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-math.pi / 2, math.pi / 2), st.floats(-math.pi, math.pi))
@example(0.3, math.pi / 2, 0.7)  # gimbal lock: nose straight down / up
@example(0.3, -math.pi / 2, 0.7)
@example(2.0, 0.0, math.pi)  # overturned
def test_heading_pitch_roll_give_back_the_rotation(h, p, r):
    R = rotmat_from_euler(r, p, h)
    angles = hpr_from_matrix(R)
    assert np.isfinite(angles).all()
    back = rotmat_from_euler(angles[2], angles[1], angles[0])
    assert np.abs(back - R).max() < 1e-9


def test_an_agent_leaving_the_roads_is_refused_naming_it_and_the_time(scene, tmp_path):
    adversary = moving_track(scene)
    store = variant_store(scene, tmp_path / "scenes" / "off-v000", "off-v000",
                          adversarial_boxes(scene, adversary, 30.0), None)
    out = tmp_path / "xosc"
    category = str(scene.boxes[scene.boxes.track_id == adversary].category.iloc[0])
    with pytest.raises(OmniscsError, match=rf"{category}_{adversary} leaves the road network at t = 0\.[1-5]0 s"):
        export_scenes([store], "openscenario", out)
    assert not out.exists() and leftovers(tmp_path) == []


def test_a_scene_without_a_road_map_is_refused_and_nothing_is_written(tmp_path):
    store = write_tiny_scene(tmp_path / "tiny")
    out = tmp_path / "xosc"
    with pytest.raises(OmniscsError, match="has no road map"):
        export_scenes([store], "openscenario", out)
    assert not out.exists() and leftovers(tmp_path) == []


def test_a_damaged_variant_file_is_one_clear_error(scene, tmp_path):
    store = variant_store(scene, tmp_path / "bad-v000", "bad-v000", scene.boxes, None)
    variant = store / "variant.json"
    variant.write_text("{not json")
    out = tmp_path / "xosc"
    with pytest.raises(OmniscsError, match="variant.json"):
        export_scenes([store], "openscenario", out)
    assert not out.exists()


def run_cli(args: list[str]):
    from typer.testing import CliRunner

    from omniscs.cli import app

    return CliRunner().invoke(app, args)


def test_the_cli_exports_a_variants_folder_and_refuses_options_of_other_formats(variants, tmp_path):
    folder = variants[0].parent.parent
    out = tmp_path / "cli"
    result = run_cli(["dataset", "export", str(folder), "--format", "openscenario", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.glob("*.xosc")) == ["app-v000.xosc", "beh-v000.xosc"]
    bad = run_cli(["dataset", "export", str(folder), "--format", "openscenario", "--out", str(tmp_path / "x"),
                   "--keep-unseen"])
    assert isinstance(bad.exception, OmniscsError) and "apply to --format nuscenes and uniad only" in str(bad.exception)
    empty = tmp_path / "variants-only"
    empty.mkdir()
    (empty / "variants.json").write_text("[]")
    unrendered = run_cli(["dataset", "export", str(empty), "--format", "openscenario", "--out", str(tmp_path / "y")])
    assert isinstance(unrendered.exception, OmniscsError) and "never rendered" in str(unrendered.exception)
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()



@pytest.mark.slow  # about 10 s: kept out of make test's 5 minutes
def test_a_recorded_nuscenes_log_gets_its_roads_from_the_map_expansion(scene, tmp_path):
    """The intersection exported as nuScenes (with its map expansion), read back as a recorded log: the scenario's
    roads come from the expansion, the checkers pass, and every lane vertex of the world lies on a road."""
    from shapely.geometry import LineString
    from shapely.geometry import box as shapely_box

    from omniscs.export.opendrive import EXPANSION_MARGIN_M
    from omniscs.scene import parse_source, write_source_scene

    dataroot = export_scenes([scene.path], "nuscenes", tmp_path / "nusc", version="v1.0-mini")
    source = parse_source(f"nuscenes:{dataroot}/v1.0-mini")
    log = load_scene(write_source_scene(source, tmp_path / "log"))
    assert log.world is None and log.manifest["location"]
    out = export_scenes([log.path], "openscenario", tmp_path / "xosc")
    (entry,) = json.loads((out / INDEX_JSON).read_text())["scenarios"]
    assert entry["roads"] == "nuscenes_expansion"
    for path in sorted(out.glob("*.xo*")):
        assert check_file(path).passed, path.name
    road = ET.fromstring((out / entry["road_network"]).read_bytes())
    lines = [_reference_line(r) for r in road.iter("road")]
    layout = build_layout(scene.world.template, scene.world.seed)
    reach = np.concatenate([log.world_from_ego_all[:, :2, 3], log.boxes[["cx", "cy"]].to_numpy()])
    region = shapely_box(*(reach.min(0) - EXPANSION_MARGIN_M), *(reach.max(0) + EXPANSION_MARGIN_M))
    near = [lane for lane in layout.lanes.values() if LineString(lane.centreline).intersects(region)]
    assert near and len(lines) == len(near)  # every lane near the log, and only those, is a road
    for lane in near:  # arcs through the centreline vertices: exact at every vertex
        best = min(_distances(np.asarray(lane.centreline, np.float64), line).max() for line in lines)
        assert best < 1e-3, (lane.lane_id, best)
    moved = tmp_path / "elsewhere"
    (moved / "maps").mkdir(parents=True)
    with pytest.raises(OmniscsError, match="has no road map"):  # the variant of a log needs --nuscenes-maps
        export_scenes([log.path], "openscenario", tmp_path / "x2", nuscenes_maps=moved)


def behaviour_spec(scene, drift: float = 0.05) -> dict:
    """A variants.json entry as `omniscs scs behavior` writes it: the log replayed (box centres, yaws), the most moving
    track drifting sideways by ``drift`` metres a step."""
    adversary = moving_track(scene)
    frames = list(range(scene.n_frames))
    agents, sizes = {}, {}
    for tid, g in scene.boxes.groupby("track_id"):
        g = g.set_index("frame_idx")
        shift = drift if int(tid) == adversary else 0.0
        agents[str(tid)] = [[float(g.loc[f].cx) - shift * f * math.sin(g.loc[f].yaw),
                             float(g.loc[f].cy) + shift * f * math.cos(g.loc[f].yaw), float(g.loc[f].yaw)]
                            if f in g.index else None for f in frames]
        sizes[str(tid)] = [float(g.length.iloc[0]), float(g.width.iloc[0])]
    ego = scene.world_from_ego_all
    yaw = yaw_from_matrix(ego[:, :3, :3])
    rows = [[float(ego[f, 0, 3] + 1.3 * np.cos(yaw[f])), float(ego[f, 1, 3] + 1.3 * np.sin(yaw[f])), float(yaw[f])]
            for f in frames]
    return {"variant_id": "v000", "scene_id": scene.scene_id, "ego": rows, "agents": agents, "sizes": sizes,
            "adversary": adversary, "ego_centre_ahead_of_origin_m": 1.3, "dt": 0.1, "source_frames": frames,
            "timestamps_us": scene.frames["timestamp_us"].astype(int).tolist()}


def test_behaviour_variants_never_rendered_export_on_their_scene_store(scene, tmp_path):
    folder = tmp_path / "behavior"
    folder.mkdir()
    spec = behaviour_spec(scene)
    (folder / "variants.json").write_text(json.dumps([spec]))
    out = tmp_path / "xosc"
    unnamed = run_cli(["dataset", "export", str(folder), "--format", "openscenario", "--out", str(out)])
    assert isinstance(unnamed.exception, OmniscsError) and "--scene STORE" in str(unnamed.exception)
    result = run_cli(["dataset", "export", str(folder), "--format", "openscenario", "--out", str(out),
                      "--scene", str(scene.path)])
    assert result.exit_code == 0, result.output
    xosc = out / f"{scene.scene_id}-v000.xosc"
    for path in (xosc, out / road_file_of(xosc)):
        assert check_file(path).passed, path.name
    read = read_scenario(xosc)
    assert np.abs(read["ego"].poses[:, :2] - scene.world_from_ego_all[:, :2, 3]).max() < ROUND_TRIP_M
    for tid, rows in spec["agents"].items():
        track = scene.boxes[scene.boxes.track_id == int(tid)].sort_values("frame_idx")
        entity = read[f"{track.category.iloc[0]}_{tid}"]
        present = np.array([r for r in rows if r is not None])
        poses = entity.poses if len(entity.times_s) else entity.initial[None].repeat(len(present), 0)
        assert np.abs(poses[:, :2] - present[:, :2]).max() < ROUND_TRIP_M  # planar: centre = reference point
        assert np.abs(poses[:, 2] - (track.cz.to_numpy() - track.height.to_numpy() / 2)).max() < ROUND_TRIP_M
        assert angle_error(poses[:, 3], present[:, 2]).max() < ROUND_TRIP_RAD
    other = dict(spec, scene_id="syn-other")
    (folder / "variants.json").write_text(json.dumps([other]))
    wrong = run_cli(["dataset", "export", str(folder), "--format", "openscenario", "--out", str(tmp_path / "w"),
                     "--scene", str(scene.path)])
    assert isinstance(wrong.exception, OmniscsError) and "belongs to scene 'syn-other'" in str(wrong.exception)
    assert not (tmp_path / "w").exists() and leftovers(tmp_path) == []


def test_damaged_or_off_road_behaviour_variants_are_one_error_with_nothing_written(scene, tmp_path):
    from omniscs.export.openscenario import export_behaviour_variants

    variants_json = tmp_path / "variants.json"
    variants_json.write_text('[{"variant_id": "v000", ')
    with pytest.raises(OmniscsError, match="variants.json"):
        export_behaviour_variants(variants_json, scene.path, tmp_path / "a")
    spec = behaviour_spec(scene, drift=20.0)  # the adversary drifts 20 m a step: off the road at once
    variants_json.write_text(json.dumps([spec]))
    with pytest.raises(OmniscsError, match=r"leaves the road network at t = 0\.10 s"):
        export_behaviour_variants(variants_json, scene.path, tmp_path / "b")
    spec["ego"][2] = [1.0, 2.0]
    variants_json.write_text(json.dumps([spec]))
    with pytest.raises(OmniscsError, match=r"ego: step 2 is \[1\.0, 2\.0\], not \[x, y, yaw\]"):
        export_behaviour_variants(variants_json, scene.path, tmp_path / "c")
    assert not any((tmp_path / name).exists() for name in "abc") and leftovers(tmp_path) == []


def test_the_ego_is_marked_as_carlas_scenario_runner_finds_it(exported):
    root = ET.parse(exported / "beh-v000.xosc").getroot()
    marked = [obj.get("name") for obj in root.iter("ScenarioObject")
              if any(p.get("name") == "type" and p.get("value") == "ego_vehicle" for p in obj.iter("Property"))]
    assert marked == ["ego"]


def test_a_designed_variants_inserts_at_one_pose_are_its_static_objects(tmp_path):
    from types import SimpleNamespace

    from omniscs.export.openscenario import inserted_static_tracks

    edits = [{"op": "insert", "track_id": 9, "asset_id": "pm-0123456789ab", "category": "truck",
              "pose": [1.0, 2.0, 1.5, 0.0], "roll_deg": 180.0},
             {"op": "insert", "track_id": 10, "asset_id": "pm-0123456789ab", "category": "truck",
              "waypoints": [[1.0, 2.0, 1.5, 0.0], [2.0, 2.0, 1.5, 0.0]]},
             {"op": "set_trajectory", "track_id": 3, "waypoints": [[0.0, 0.0, 0.7, 0.0], None]}]
    (tmp_path / "variant.json").write_text(json.dumps({"variant": {"kind": "designed", "edits": edits}}))
    assert inserted_static_tracks(SimpleNamespace(path=tmp_path)) == {9}
    (tmp_path / "variant.json").write_text(json.dumps({"variant": {"kind": "designed", "edits": [{"op": "fly"}]}}))
    with pytest.raises(OmniscsError, match="designed variant's edits are damaged"):
        inserted_static_tracks(SimpleNamespace(path=tmp_path))
