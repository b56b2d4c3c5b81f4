"""nuScenes map expansion: the devkit's NuScenesMap opens the map of every location the logs name, every ego pose
lies on mapped drivable area next to a lane, lane arclines follow the centrelines, scenes exported together sit in
their own grid cells, recorded logs keep their frame, and bad options are one clear error."""
import json
from types import SimpleNamespace

import numpy as np
import pytest

from omniscs.errors import OmniscsError
from omniscs.export import export_scenes
from omniscs.export.nuscenes_map import (
    GRID_COLUMNS,
    SCENE_SPACING_M,
    MapExpansion,
    arcline_paths,
    road_layout_of,
)
from omniscs.geometry import make_transform, pose_from_xyz_yaw
from omniscs.roadmap import RoadMap
from omniscs.scene import CameraRecord, SceneWriter, load_scene
from omniscs.world.layouts import build_layout
from tests.export.export_fixtures import two_stores

VERSION = "v1.0-mini"
#: Largest distance between a lane's discretised arcline path and its centreline polyline (metres).
ARCLINE_TOL_M = 0.05


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    return two_stores(tmp_path_factory)


@pytest.fixture(scope="module")
def dataroot(stores, tmp_path_factory):
    return export_scenes(stores, "nuscenes", tmp_path_factory.mktemp("nusmap") / "nuscenes", version=VERSION)


@pytest.fixture(scope="module")
def nusc(dataroot):
    from nuscenes.nuscenes import NuScenes

    return NuScenes(version=VERSION, dataroot=str(dataroot), verbose=False)


@pytest.fixture(scope="module")
def nusc_map(dataroot):
    from nuscenes.map_expansion.map_api import NuScenesMap

    return NuScenesMap(dataroot=str(dataroot), map_name="boston-seaport")


def _scene_poses(nusc, scene):
    """Global xy of every ego pose of a scene (all sensors, all frames)."""
    sample = nusc.get("sample", scene["first_sample_token"])
    xy = []
    for channel in sample["data"]:
        sd = nusc.get("sample_data", sample["data"][channel])
        while sd["prev"]:
            sd = nusc.get("sample_data", sd["prev"])
        while True:
            xy.append(nusc.get("ego_pose", sd["ego_pose_token"])["translation"][:2])
            if not sd["next"]:
                break
            sd = nusc.get("sample_data", sd["next"])
    return np.array(xy)


def test_every_map_record_points_at_a_one_channel_mask_the_devkit_can_look_points_up_in(nusc):
    """The devkit's MapMask indexes its mask as a 2-D binary image (is_on_mask, the LIDAR_TOP map underlay)."""
    for record in nusc.map:
        mask = record["mask"]
        assert mask.mask().ndim == 2
        assert mask.is_on_mask(np.array([0.0, 1e4]), np.array([0.0, 1e4])).tolist() == [False, False]


def test_the_devkit_opens_the_map_of_every_location_the_logs_name(nusc, dataroot):
    from nuscenes.map_expansion.map_api import NuScenesMap

    locations = {log["location"] for log in nusc.log}
    assert locations == {"boston-seaport"}
    for location in locations:
        nusc_map = NuScenesMap(dataroot=str(dataroot), map_name=location)
        assert nusc_map.version == "1.3"
        for layer in ("drivable_area", "road_segment", "lane", "lane_connector", "ped_crossing", "walkway",
                      "stop_line", "road_divider", "lane_divider"):
            assert len(getattr(nusc_map, layer)) > 0, layer
        assert set(nusc_map.connectivity) == set(nusc_map.arcline_path_3) == \
            {r["token"] for r in nusc_map.lane + nusc_map.lane_connector}
        assert any(r["is_intersection"] for r in nusc_map.road_segment)


def test_every_ego_pose_lies_on_mapped_drivable_area_next_to_a_lane(nusc, nusc_map):
    checked = 0
    for scene in nusc.scene:
        for x, y in np.unique(_scene_poses(nusc, scene), axis=0):  # every frame's pose (sensors share it)
            assert nusc_map.record_on_point(x, y, "drivable_area"), (x, y)
            on = nusc_map.layers_on_point(x, y)
            assert on["drivable_area"] and on["road_segment"] and on["lane"] + on.get("lane_connector", ""), on
            near = nusc_map.get_records_in_radius(x, y, 10.0, ["lane", "lane_connector", "walkway"])
            assert near["lane"]
            lane = nusc_map.get_closest_lane(x, y, radius=5.0)
            poses = np.array(nusc_map.discretize_lanes([lane], 0.5)[lane])
            assert np.linalg.norm(poses[:, :2] - [x, y], axis=1).min() < 1.0  # the ego drives on the centreline
            checked += 1
    assert checked == 12  # two scenes of six frames


def test_lane_arclines_follow_the_centrelines_and_connectivity_is_symmetric(nusc_map, stores):
    from nuscenes.map_expansion.arcline_path_utils import discretize_lane

    layout = build_layout("intersection", 1)
    offset = np.array([SCENE_SPACING_M, 0.0])  # the intersection is the second placed scene
    centrelines = [lane.centreline + offset for lane in layout.lanes.values()]
    checked = 0
    for tok in nusc_map.arcline_path_3:
        pts = np.array(discretize_lane(nusc_map.get_arcline_path(tok), 0.25))[:, :2]
        if pts[0, 0] < SCENE_SPACING_M / 2:
            continue  # the straight road's lanes: two straight pieces
        gaps = [np.abs(pts[[0, -1]] - c[[0, -1]]).max() for c in centrelines]
        line = centrelines[int(np.argmin(gaps))]
        assert min(gaps) < 1e-6
        seg_a, seg_b = line[:-1], line[1:]
        ab = seg_b - seg_a
        t = np.clip(np.einsum("msk,sk->ms", pts[:, None] - seg_a, ab) / np.einsum("sk,sk->s", ab, ab), 0, 1)
        dist = np.linalg.norm(pts[:, None] - (seg_a + t[..., None] * ab), axis=2).min(1)
        assert dist.max() < ARCLINE_TOL_M
        checked += 1
    assert checked == len(centrelines)
    for tok, links in nusc_map.connectivity.items():
        for out in links["outgoing"]:
            assert tok in nusc_map.connectivity[out]["incoming"]
    connectors = {r["token"] for r in nusc_map.lane_connector}
    assert all(nusc_map.get_incoming_lane_ids(c) and nusc_map.get_outgoing_lane_ids(c) for c in connectors)


def test_evenly_sampled_circles_become_exact_arcs():
    from nuscenes.map_expansion.arcline_path_utils import discretize_lane

    theta = np.linspace(0.0, np.pi / 2, 9)
    for sign in (1, -1):  # left and right turns
        circle = np.stack([12.0 * np.cos(theta), sign * 12.0 * np.sin(theta)], axis=1)
        pts = np.array(discretize_lane(arcline_paths(circle), 0.1))[:, :2]
        assert np.abs(np.linalg.norm(pts, axis=1) - 12.0).max() < 1e-9


def test_two_scenes_exported_together_sit_in_their_own_grid_cells(nusc, nusc_map, stores):
    from shapely.geometry import MultiPolygon, Point

    by_scene = {}
    for area in nusc_map.drivable_area:
        by_scene[area["token"]] = MultiPolygon([nusc_map.extract_polygon(t) for t in area["polygon_tokens"]])
    assert len(by_scene) == 2
    a, b = by_scene.values()
    assert not a.intersects(b)
    spans = []
    for k, (scene, store) in enumerate(zip(sorted(nusc.scene, key=lambda s: s["name"]), stores)):
        poses = _scene_poses(nusc, scene)
        offset = np.array([(k % GRID_COLUMNS) * SCENE_SPACING_M, (k // GRID_COLUMNS) * SCENE_SPACING_M])
        first = nusc.get("ego_pose", nusc.get("sample_data", nusc.get("sample", scene["first_sample_token"])
                                              ["data"]["LIDAR_TOP"])["ego_pose_token"])
        assert np.allclose(first["translation"][:2], offset + load_scene(store).world_from_ego(0)[:2, 3])
        homes = {tok for tok, area in by_scene.items() if all(area.contains(Point(p)) for p in poses)}
        assert len(homes) == 1
        samples = [s["timestamp"] for s in nusc.sample if s["scene_token"] == scene["token"]]
        spans.append((min(samples), max(samples)))
    assert spans[0][1] < spans[1][0]  # the second scene was moved after the first in time


def _located_store(path, location, global_xy):
    global_from_world = make_transform(np.eye(3), [global_xy[0], global_xy[1], 0.0])
    with SceneWriter(path, f"rec-{location}", {"kind": "test"}) as w:
        w.set_frames(np.arange(3) * 500_000, np.stack([pose_from_xyz_yaw(2.0 * f, 0, 0, 0) for f in range(3)]))
        K = np.array([[50.0, 0, 32], [0, 50.0, 18], [0, 0, 1]])
        mount = np.array([[0, 0, 1, 1.5], [-1, 0, 0, 0], [0, -1, 0, 1.6], [0, 0, 0, 1.0]])
        w.set_cameras([CameraRecord("CAM_FRONT", 64, 36, K, mount)])
        w.set_boxes([])
        for f in range(3):
            w.write_image("CAM_FRONT", f, np.full((36, 64, 3), 90, np.uint8))
        w.set_extra(global_from_world=global_from_world.reshape(16).tolist(), location=location)
    return path


def test_a_recorded_log_keeps_its_frame_and_location_and_gets_no_map_file(stores, tmp_path):
    recorded = _located_store(tmp_path / "rec", "singapore-onenorth", (612.5, 1641.2))
    root = export_scenes([recorded, stores[0]], "nuscenes", tmp_path / "nus", version=VERSION, keyframe_every=1)
    logs = {r["logfile"]: r["location"] for r in json.loads((root / VERSION / "log.json").read_text())}
    assert sorted(logs.values()) == ["boston-seaport", "singapore-onenorth"]
    assert sorted(p.name for p in (root / "maps" / "expansion").iterdir()) == ["boston-seaport.json"]
    poses = json.loads((root / VERSION / "ego_pose.json").read_text())
    assert any(np.allclose(p["translation"], [612.5, 1641.2, 0.0]) for p in poses)
    assert any(np.allclose(p["translation"], [0.0, 0.0, 0.0]) for p in poses)  # the first placed scene: cell 0


def test_a_road_map_without_a_world_gives_lanes_with_inferred_successors(tmp_path):
    from nuscenes.map_expansion.map_api import NuScenesMap

    road_map = RoadMap(drivable_polygons=(np.array([[-5.0, -4.0], [60.0, -4.0], [60.0, 4.0], [-5.0, 4.0]]),),
                       lane_centrelines=(np.array([[0.0, -1.75], [30.0, -1.75]]),
                                         np.array([[30.0, -1.75], [55.0, -1.75]]),
                                         np.array([[55.0, 1.75], [0.0, 1.75]])),
                       extent_min=np.array([-5.0, -4.0]), extent_max=np.array([60.0, 4.0]))
    roads = road_layout_of(SimpleNamespace(world=None, road_map=road_map))
    assert [lane.successors for lane in roads.lanes] == [("lane_1",), (), ()]
    expansion = MapExpansion("singapore-queenstown")
    expansion.add("only", roads)
    path = tmp_path / "maps" / "expansion" / "singapore-queenstown.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(expansion.to_json()))
    nusc_map = NuScenesMap(dataroot=str(tmp_path), map_name="singapore-queenstown")
    first = nusc_map.get_closest_lane(10.0, -1.5)
    assert len(nusc_map.get_outgoing_lane_ids(first)) == 1
    assert nusc_map.record_on_point(20.0, 1.0, "drivable_area")
    assert len(nusc_map.road_divider) == 2 and not nusc_map.lane_divider  # opposite directions side by side


def test_recorded_log_and_procedural_scenes_in_one_location_is_one_clear_error(stores, tmp_path):
    recorded = _located_store(tmp_path / "rec", "boston-seaport", (100.0, 200.0))
    with pytest.raises(OmniscsError, match=r"recorded log in boston-seaport.*another location"):
        export_scenes([recorded, stores[0]], "nuscenes", tmp_path / "nus", version=VERSION)
    assert not (tmp_path / "nus").exists()


@pytest.mark.parametrize("options, message", [
    ({"location": "mars"}, r"unknown nuScenes location 'mars'.*boston-seaport"),
    ({"scene_spacing_m": 300.0}, r"reaches \d+ m from its first ego pose.*pass a scene spacing above"),
    ({"scene_spacing_m": float("nan")}, r"scene spacing must be a number of metres"),
    ({"scene_spacing_m": "wide"}, r"scene spacing must be a number of metres"),
    ({"location": None}, r"unknown nuScenes location None"),
])
def test_bad_map_options_are_one_clear_error_and_write_nothing(options, message, stores, tmp_path):
    with pytest.raises(OmniscsError, match=message) as info:
        export_scenes(stores[:1], "nuscenes", tmp_path / "nus", version=VERSION, **options)
    assert "\n" not in str(info.value)
    assert not (tmp_path / "nus").exists()
