"""The behaviour model's view of a log: tracks on a time grid, maps (from a road map or derived), per-agent
features; a recorded log and a procedural one go through the same code."""
import numpy as np
import pytest
import torch

from omniscs.geometry import pose_from_xyz_yaw
from omniscs.scene import CameraRecord, SceneWriter, load_scene
from omniscs.geometry import ego_from_camera_mount, intrinsics_from_fov
from omniscs.pipeline.procedural import traffic_from_world
from omniscs.scs.behavior.features import build_sample, collate, dequantise_crops
from omniscs.roadmap import RoadMap
from omniscs.scs.behavior.maps import CropSpec, map_from_road_map
from omniscs.scs.behavior.tracks import traffic_from_log, traffic_from_scene
from omniscs.world import road_map_for
from tests.behavior_fixtures import straight_world


def test_ego_positions_are_box_centres_ahead_of_the_rear_axle():
    traffic = traffic_from_world(straight_world([], ego_speed=5.0))
    assert np.allclose(traffic.ego_xy[0], [1.3, 0.0]) and np.allclose(traffic.ego_xy[10], [6.3, 0.0])


def test_road_map_knows_lanes_road_and_kerb():
    traffic = traffic_from_world(straight_world([]))
    m = traffic.map
    assert m.source == "road_map"
    assert m.is_drivable(np.array([[20.0, 0.0], [20.0, 9.9], [20.0, 16.0], [20.0, -4.0]])).tolist() == \
        [True, True, False, False]
    d = m.outside_distance(torch.tensor([[20.0, 0.0], [20.0, -5.66]])).numpy()
    assert d[0] == 0.0 and d[1] == pytest.approx(4.0, abs=0.6)


def test_map_patch_is_in_the_agents_frame_with_lane_direction_relative_to_its_heading():
    traffic = traffic_from_world(straight_world([]))
    spec = CropSpec()
    east = traffic.map.crops(np.array([[20.0, 0.0]]), np.array([0.0]), spec)[0]
    west = traffic.map.crops(np.array([[20.0, 0.0]]), np.array([np.pi]), spec)[0]
    rows, cols = spec.shape
    ahead = int((10.0 - spec.x_min) / spec.resolution_m)

    def row(lateral_m: float) -> slice:  # the two patch rows around a lateral offset (the band is 1.5 m wide)
        r = int((lateral_m + spec.half_width) / spec.resolution_m - 0.5)
        return slice(r, r + 2)

    assert east[0, row(0.0), ahead].min() > 0.9  # drivable ahead
    assert east[2, row(0.0), ahead].max() == pytest.approx(1.0, abs=1e-3)  # own lane runs along +x
    assert west[2, row(0.0), ahead].min() == pytest.approx(-1.0, abs=1e-3)  # facing the wrong way
    assert east[2, row(6.64), ahead].min() == pytest.approx(-1.0, abs=1e-3)  # oncoming lane on its left
    assert east[0, row(-8.0), ahead].max() < 0.1  # the sidewalk on its right is not drivable


def test_agents_that_appear_after_the_now_step_are_not_nodes_but_stay_in_the_traffic():
    world = straight_world([{"x": 20.0, "y": 3.3, "speed": 8.0},
                            {"x": 40.0, "y": 3.3, "speed": 5.0, "first": 20}])
    traffic = traffic_from_world(world)
    sample = build_sample(traffic, 9, 10, 30)
    assert sample.track_ids.tolist() == [-1, 1]
    assert traffic.present[1, 20:].all() and not traffic.present[1, :20].any()


def test_history_of_a_late_agent_is_masked_and_features_are_finite():
    world = straight_world([{"x": 20.0, "y": 3.3, "speed": 8.0, "first": 8}])
    sample = build_sample(traffic_from_world(world), 9, 10, 30)
    valid = sample.history[1, :, -1]
    assert valid.tolist() == [0.0] * 8 + [1.0, 1.0]
    assert torch.isfinite(sample.history).all() and torch.isfinite(sample.state0).all()
    assert sample.state0[1, 3] == pytest.approx(8.0, abs=1e-3)  # speed from the two observed frames


def test_far_agents_get_empty_map_patches_and_finite_features():
    world = straight_world([{"x": 10_000.0, "y": 3.3, "speed": 8.0}])
    sample = build_sample(traffic_from_world(world), 9, 10, 30)
    patch = dequantise_crops(sample.crops[1])
    assert torch.isfinite(sample.state0).all() and patch.abs().max() < 0.01


def test_collate_pads_scenes_and_masks_the_padding():
    a = build_sample(traffic_from_world(straight_world([{"x": 20.0, "y": 3.3, "speed": 8.0}])), 9, 10, 30)
    b = build_sample(traffic_from_world(straight_world([])), 9, 10, 30)
    batch = collate([a, b])
    assert batch.node_mask.tolist() == [[True, True], [True, False]]
    assert batch.crops[1, 1].abs().sum() == 0 and not batch.future_mask[1, 1].any()


def _store(tmp_path, period_us: int, n_frames: int):
    out = tmp_path / f"log{period_us}"
    with SceneWriter(out, "log", {"kind": "test"}) as w:
        ts = np.arange(n_frames, dtype=np.int64) * period_us
        w.set_frames(ts, np.stack([pose_from_xyz_yaw(6.0 * t * 1e-6, 0.0, 0.0, 0.0) for t in ts]))
        w.set_cameras([CameraRecord("CAM_FRONT", 32, 18, intrinsics_from_fov(32, 18, np.radians(70)),
                                    ego_from_camera_mount(1.5, 0.0, 1.6, 0.0))])
        rows = []
        for f in range(n_frames):
            t = f * period_us * 1e-6
            rows.append(dict(frame_idx=f, track_id=7, category="car", cx=15.0 + 4.0 * t, cy=3.5, cz=0.8,
                             length=4.5, width=1.9, height=1.6, yaw=0.0))
            if f < n_frames - 2:
                rows.append(dict(frame_idx=f, track_id=9, category="car", cx=-20.0, cy=-3.5, cz=0.8,
                                 length=4.5, width=1.9, height=1.6, yaw=0.0))
        w.set_boxes(rows)
        for f in range(n_frames):
            w.write_image("CAM_FRONT", f, np.zeros((18, 32, 3), np.uint8))
    return load_scene(out)


def test_a_2hz_log_is_resampled_to_the_model_step_and_keeps_presence(tmp_path):
    traffic = traffic_from_scene(_store(tmp_path, 500_000, 9), dt=0.1)
    assert traffic.n_steps == 41 and traffic.source_frames is None
    moving = traffic.index_of(7)
    assert np.allclose(traffic.xy[moving, 5], [17.0, 3.5]) and traffic.present[moving].all()
    parked = traffic.index_of(9)
    assert traffic.present[parked, :31].all() and not traffic.present[parked, 31:].any()


def test_logs_without_a_map_derive_the_drivable_area_from_driven_paths_and_parked_cars(tmp_path):
    traffic = traffic_from_scene(_store(tmp_path, 100_000, 30), dt=0.1)
    m = traffic.map
    assert m.source == "derived" and traffic.source_frames is not None
    assert m.is_drivable(np.array([[3.0, 0.0], [16.0, 3.5], [-20.0, -3.5], [3.0, 30.0]])).tolist() == \
        [True, True, True, False]


def test_a_road_map_survives_json_and_rasterises_to_the_same_map():
    world = straight_world([])
    road = road_map_for(world)
    again = RoadMap.from_json(road.to_json())
    assert again.to_dict() == road.to_dict()
    ego_xy = traffic_from_world(world).ego_xy
    a, b = map_from_road_map(road, ego_xy), map_from_road_map(again, ego_xy)
    assert np.array_equal(a.layers, b.layers) and np.array_equal(a.extent, b.extent)
    probe = np.random.default_rng(0).uniform(-40.0, 120.0, (500, 2))
    assert np.array_equal(a.is_drivable(probe), road.is_drivable(probe))


def test_a_recorded_log_and_the_same_log_as_arrays_give_the_same_traffic_and_derived_map(tmp_path):
    scene = _store(tmp_path, 100_000, 30)
    from_store = traffic_from_scene(scene, dt=0.1)
    n, s = from_store.n_tracks, from_store.n_steps
    poses = np.zeros((n, s, 4, 4))
    poses[:] = np.eye(4)
    for row in scene.boxes.itertuples():
        poses[from_store.index_of(row.track_id), row.frame_idx] = pose_from_xyz_yaw(row.cx, row.cy, row.cz, row.yaw)
    from_arrays = traffic_from_log("log", from_store.timestamps_us, scene.world_from_ego_all, from_store.track_ids,
                                   from_store.categories, from_store.sizes, poses, from_store.present, dt=0.1)
    assert from_arrays.map.source == from_store.map.source == "derived"
    assert np.array_equal(from_arrays.map.layers, from_store.map.layers)
    for name in ("ego_xy", "ego_yaw", "xy", "yaw", "present", "source_frames"):
        assert np.allclose(getattr(from_arrays, name), getattr(from_store, name)), name
