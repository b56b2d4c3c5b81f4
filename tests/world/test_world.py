"""Procedural world: deterministic generation, exact ground truth in renders and LiDAR, lighting, errors."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform, project, transform_points, unproject
from omniscs.taxonomy import CATEGORIES, SEMANTIC_IDS
from omniscs.world import (LIGHTINGS, TEMPLATES, World, WorldRenderer, build_asset, camera_rig, generate_world,
                           layout_for)

W, H = 96, 54


@pytest.fixture(scope="module")
def world() -> World:
    return generate_world("intersection", 3, n_frames=3, n_cameras=3, width=W, height=H)


@pytest.fixture(scope="module")
def renderer(world) -> WorldRenderer:
    return WorldRenderer(world)


@pytest.fixture(scope="module")
def front(renderer):
    return renderer.render_camera(0, "CAM_FRONT")


# ----------------------------------------------------------------------------- generation
def test_same_seed_generates_the_same_world_and_another_seed_does_not():
    a = generate_world("t_junction", 5, n_frames=4, width=W, height=H)
    b = generate_world("t_junction", 5, n_frames=4, width=W, height=H)
    c = generate_world("t_junction", 6, n_frames=4, width=W, height=H)
    assert a.to_json() == b.to_json()
    assert a.to_json() != c.to_json()


def test_ego_starts_at_the_world_origin_and_drives_forward_at_10_hz(world):
    np.testing.assert_array_equal(world.ego_poses[0], np.eye(4))
    step = np.linalg.norm(np.diff(world.ego_poses[:, :2, 3], axis=0), axis=1)
    assert np.all(step > 0.3) and np.all(step < 2.0)  # 3..20 m/s at 0.1 s per frame
    assert world.ego_poses[1, 0, 3] > 0
    np.testing.assert_array_equal(world.timestamps_us(), [0, 100_000, 200_000])


def test_agents_have_asset_sized_boxes_resting_on_the_ground(world):
    assert len(world.agents) >= 5
    for a in world.agents:
        assert a.category in CATEGORIES
        np.testing.assert_allclose(a.size, build_asset(a.asset_id).size)
        assert np.all(a.size > 0)
        np.testing.assert_allclose(a.poses[a.present, 2, 3], a.size[2] / 2, atol=1e-9)


def test_traffic_is_collision_free_with_the_ego(world):
    ego_xy = world.ego_poses[:, :2, 3] + 1.3 * world.ego_poses[:, :2, 0]  # ego box centre
    for a in world.agents:
        d = np.linalg.norm(a.poses[:, :2, 3] - ego_xy, axis=1)[a.present]
        assert np.all(d > 0.5 * (a.size[1] + 1.9)), a.track_id


def test_every_template_generates_and_parked_truck_template_has_a_large_static_object_ahead():
    for template in TEMPLATES:
        w = generate_world(template, 1, n_frames=2, n_cameras=1, width=W, height=H)
        assert w.template == template and len(w.agents) > 0
    w = generate_world("straight_parked_truck", 4, n_frames=5, n_cameras=1, width=W, height=H)
    big = [a for a in w.agents if a.category in ("truck", "trailer")
           and np.allclose(a.poses[0], a.poses[-1]) and 10 < a.poses[0, 0, 3] < 45]
    assert big, "expected a parked box truck or container ahead of the ego"


def test_world_survives_a_json_round_trip(world):
    again = World.from_json(world.to_json())
    assert again.to_json() == world.to_json()


def test_layout_map_marks_lanes_drivable_and_sidewalks_not(world):
    layout = layout_for(world)
    for lane in layout.lanes.values():
        assert layout.is_drivable(lane.centreline).all(), lane.lane_id
    for poly in layout.sidewalk_polygons:
        assert not layout.is_drivable(poly.mean(0, keepdims=True)).any()
    assert layout.is_drivable(np.zeros((1, 2)))[0]  # the ego starts on the road
    grid = layout.rasterize_drivable((-20, 60), (-30, 30), 1.0)
    assert grid.shape == (60, 80) and 0.1 < grid.mean() < 0.9


def test_camera_rig_is_nuscenes_like_and_validates_count():
    rig = camera_rig(6, W, H)
    assert [c.name for c in rig] == ["CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT",
                                     "CAM_BACK_RIGHT", "CAM_BACK"]
    forward = np.array([r.ego_from_camera[:3, 2] for r in rig])  # camera z axis in the ego frame
    assert forward[0, 0] > 0.99 and forward[5, 0] < -0.99 and forward[1, 1] > 0.5 and forward[2, 1] < -0.5
    hfov = np.degrees(2 * np.arctan(0.5 * W / rig[0].K[0, 0]))
    assert 65 < hfov < 75


@pytest.mark.parametrize("kwargs", [
    dict(template="roundabout"), dict(lighting="sunset"), dict(n_cameras=0), dict(n_cameras=7),
    dict(n_frames=0), dict(width=4), dict(seed=-1), dict(seed="7"),
])
def test_bad_generation_inputs_raise_a_domain_error(kwargs):
    args = dict(template="straight", seed=0, n_frames=2, n_cameras=1, width=W, height=H, lighting="day")
    args.update(kwargs)
    with pytest.raises(OmniscsError):
        generate_world(**args)


def test_bad_render_requests_raise_a_domain_error(renderer):
    with pytest.raises(OmniscsError):
        renderer.render_camera(99, "CAM_FRONT")
    with pytest.raises(OmniscsError):
        renderer.render_camera(0, "CAM_NOPE")
    with pytest.raises(OmniscsError):
        renderer.lidar_scan(-1)


# ----------------------------------------------------------------------------- rendering
def test_same_seed_renders_identical_images():
    w1 = generate_world("straight", 2, n_frames=2, n_cameras=1, width=W, height=H, lighting="dusk")
    w2 = generate_world("straight", 2, n_frames=2, n_cameras=1, width=W, height=H, lighting="dusk")
    a, b = WorldRenderer(w1).render_camera(1, "CAM_FRONT"), WorldRenderer(w2).render_camera(1, "CAM_FRONT")
    for name in ("rgb", "depth", "instance", "semantic"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_outputs_have_the_documented_shapes_and_types(front):
    assert front.rgb.shape == (H, W, 3) and front.rgb.dtype == np.uint8
    assert front.depth.shape == (H, W) and front.depth.dtype == np.float32
    assert front.instance.shape == (H, W) and front.instance.dtype == np.int32
    assert front.semantic.shape == (H, W) and front.semantic.dtype == np.uint8


def test_depth_is_finite_and_zero_exactly_on_sky(front):
    assert np.all(np.isfinite(front.depth)) and np.all(front.depth >= 0)
    sky = front.semantic == SEMANTIC_IDS["sky"]
    assert sky.any() and (~sky).any()
    np.testing.assert_array_equal(front.depth == 0, sky)
    assert np.all(front.instance[sky] == -1)


def test_scene_contains_a_plausible_street(front):
    classes = set(np.unique(front.semantic).tolist())
    for name in ("sky", "road", "lane_marking", "building", "vehicle"):
        assert SEMANTIC_IDS[name] in classes, name
    # Sky above, road below.
    assert np.mean(front.semantic[0] == SEMANTIC_IDS["sky"]) > 0.2
    assert np.mean(np.isin(front.semantic[-1], [SEMANTIC_IDS["road"], SEMANTIC_IDS["lane_marking"]])) > 0.5


def test_road_pixels_unproject_onto_the_ground_plane(world, front):
    cam = world.camera("CAM_FRONT")
    road = front.semantic == SEMANTIC_IDS["road"]
    v, u = np.nonzero(road)
    pts_cam = unproject(np.stack([u + 0.5, v + 0.5], -1), front.depth[v, u], cam.K)
    pts_world = transform_points(world.ego_poses[0] @ cam.ego_from_camera, pts_cam)
    np.testing.assert_allclose(pts_world[:, 2], 0.0, atol=2e-3)


def test_lidar_points_agree_with_camera_depth_where_both_see():
    w = generate_world("straight", 0, n_frames=1, n_cameras=1, width=480, height=270)
    r = WorldRenderer(w)
    cam = w.cameras[0]
    depth = r.render_camera(0, cam.name).depth
    points = r.lidar_scan(0)
    uv, z, in_front = project(transform_points(invert_transform(cam.ego_from_camera), points[:, :3]), cam.K)
    px = np.floor(uv).astype(int)
    ok = in_front & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    assert ok.sum() > 1000
    d_img = depth[px[ok, 1], px[ok, 0]]
    rel = np.abs(d_img - z[ok]) / z[ok]
    assert np.median(rel) < 0.02


def test_lidar_is_in_the_ego_frame_within_range_with_track_ids_on_agent_boxes(world, renderer):
    points, tracks = renderer.lidar_scan(0, return_track_ids=True)
    assert points.dtype == np.float32 and points.shape[1] == 4 and len(points) == len(tracks) > 5000
    dist = np.linalg.norm(points[:, :3] - world.lidar.ego_from_lidar[:3, 3], axis=1)
    assert dist.max() <= world.lidar.max_range + 1e-3
    assert np.all((points[:, 3] >= 0) & (points[:, 3] <= 255))
    ground = np.abs(points[:, 2]) < 0.05  # flat road in the ego frame: ego origin sits on the ground
    assert ground.mean() > 0.2
    hit_ids = set(np.unique(tracks[tracks >= 0]).tolist())
    assert hit_ids
    for tid in hit_ids:
        agent = world.agent(tid)
        local = transform_points(invert_transform(agent.poses[0]), transform_points(world.ego_poses[0], points[tracks == tid, :3]))
        assert np.all(np.abs(local) <= agent.size / 2 + 1e-3)


def test_visible_car_box_centre_lands_on_its_own_instance(world, renderer):
    best = None
    for cam in world.cameras:
        out = renderer.render_camera(0, cam.name)
        ids, counts = np.unique(out.instance[out.instance >= 0], return_counts=True)
        for tid, n in zip(ids, counts):
            if world.agent(int(tid)).category == "car" and (best is None or n > best[0]):
                best = (n, int(tid), cam, out)
    assert best is not None, "expected a visible car"
    _, tid, cam, out = best
    centre = world.agent(tid).poses[0, :3, 3]
    cam_from_world = invert_transform(world.ego_poses[0] @ cam.ego_from_camera)
    uv, _, in_front = project(transform_points(cam_from_world, centre[None]), cam.K)
    assert in_front[0]
    u, v = np.floor(uv[0]).astype(int)
    assert out.instance[v, u] == tid


def test_absent_agents_are_not_rendered(world, renderer):
    out = renderer.render_camera(0, "CAM_FRONT")
    ids = np.unique(out.instance[out.instance >= 0])
    assert len(ids)
    tid = int(ids[0])
    agents = tuple(a if a.track_id != tid else type(a)(a.track_id, a.category, a.asset_id, a.size, a.poses,
                                                        np.zeros_like(a.present)) for a in world.agents)
    hidden = WorldRenderer(world.replace(agents=agents))
    assert tid not in hidden.render_camera(0, "CAM_FRONT").instance
    _, tracks = hidden.lidar_scan(0, return_track_ids=True)
    assert tid not in tracks


def test_lighting_changes_pixels_but_not_ground_truth():
    renders = {}
    for lighting in LIGHTINGS:
        w = generate_world("straight", 7, n_frames=1, n_cameras=1, width=W, height=H, lighting=lighting)
        renders[lighting] = WorldRenderer(w).render_camera(0, "CAM_FRONT")
    day = renders["day"]
    for lighting in ("dusk", "night", "fog"):
        other = renders[lighting]
        np.testing.assert_array_equal(other.depth, day.depth)
        np.testing.assert_array_equal(other.instance, day.instance)
        np.testing.assert_array_equal(other.semantic, day.semantic)
        assert np.mean(np.abs(other.rgb.astype(float) - day.rgb)) > 10, lighting
    assert renders["night"].rgb.mean() < 0.6 * day.rgb.mean()
    # Fog washes out contrast between near and far.
    assert renders["fog"].rgb.astype(float).std() < day.rgb.astype(float).std()


def test_sun_casts_shadows_on_the_road():
    """Rendering with the sun's shadow rays must darken some road pixels relative to the same view without them."""
    import dataclasses

    w = generate_world("straight_parked_truck", 0, n_frames=1, n_cameras=1, width=W, height=H)
    r = WorldRenderer(w)
    with_shadows = r.render_camera(0, "CAM_FRONT")
    r.light = dataclasses.replace(r.light, shadows=False)  # same seeded sensor noise, no shadow rays
    no_shadows = r.render_camera(0, "CAM_FRONT")
    road = with_shadows.semantic == SEMANTIC_IDS["road"]
    darker = (no_shadows.rgb.astype(int).sum(-1) - with_shadows.rgb.astype(int).sum(-1))[road]
    assert np.mean(darker > 60) > 0.02


def test_world_without_agents_renders_only_background(world):
    empty = WorldRenderer(world.replace(agents=()))
    out = empty.render_camera(0, "CAM_FRONT")
    assert np.all(out.instance == -1)
    assert SEMANTIC_IDS["vehicle"] not in out.semantic
    assert np.all(np.isfinite(out.depth))
    _, tracks = empty.lidar_scan(0, return_track_ids=True)
    assert np.all(tracks == -1)


@pytest.mark.parametrize("seed", [136, 100443, 100507])
def test_parked_truck_template_places_its_large_object_even_when_the_first_kerbside_spots_collide(seed):
    world = generate_world("straight_parked_truck", seed, n_frames=40, width=W, height=H)
    big = [a for a in world.agents if a.category in ("truck", "trailer") and a.size[0] > 6
           and np.ptp(a.poses[:, :3, 3], axis=0).max() < 0.1]
    assert len(big) == 1


def test_parked_truck_template_moves_its_large_object_towards_the_kerb_when_the_kerbside_lane_is_too_close():
    """Seed 340027: the ego drives the lane next to the kerbside lane, whose slots leave less room beside it than
    the collision margin asks. The object moves outwards (at most KERB_NUDGE_MAX_M) instead of failing; it still
    clears the ego's path by the margin and stands on the ego's right, beyond its lane."""
    from omniscs.world.layouts import build_layout
    from omniscs.world.traffic import COLLISION_MARGIN, EGO_WIDTH, KERB_NUDGE_MAX_M

    world = generate_world("straight_parked_truck", 340027, n_frames=40, width=W, height=H)
    layout = build_layout("straight_parked_truck", 340027)
    big = [a for a in world.agents if a.category in ("truck", "trailer") and a.size[0] > 6
           and np.ptp(a.poses[:, :3, 3], axis=0).max() < 0.1]
    assert len(big) == 1
    y = big[0].poses[0, 1, 3]
    slot_ys = {round(s.y, 6) for s in layout.parking_slots if s.side == -1}
    nearest = min(slot_ys, key=lambda s: abs(s - y))
    assert 0.0 < nearest - y <= KERB_NUDGE_MAX_M + 1e-9  # moved outwards, by no more than the limit
    ego_y = world.ego_poses[:, 1, 3]
    assert np.ptp(ego_y) < 1e-6
    gap = (ego_y[0] - EGO_WIDTH / 2) - (y + big[0].size[1] / 2)
    assert gap >= COLLISION_MARGIN - 1e-9
