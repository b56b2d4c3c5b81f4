"""Where an inserted object may go: the placement checks on hand-made contexts (a straight road |y| < 5, a truck,
the ego driving down +x with one forward camera), the sampler, and one rendered synthetic scene."""
from __future__ import annotations

import math

import numpy as np
import pytest

from omniscs.errors import OmniscsError
from omniscs.geometry import ego_from_camera_mount, intrinsics_from_fov, pose_from_xyz_yaw
from omniscs.scs.appearance.placement import (EGO_TRACK_ID, OVERLAPS_ACCEPTED, Cameras, GroundHeight, ObjectPoses,
                                              Obstacles, PlacementConfig, PlacementContext, PlacementError,
                                              boxes_overlap, check_placement, in_range, no_overlap, on_road,
                                              placement_context, require_valid, sample_placements, visible)

N_FRAMES = 10
EGO_SPEED = 1.0  # metres per frame, along +x from the origin
EGO_BOX = (4.6, 1.9, 1.6)
EGO_AHEAD = 1.3
#: The truck: track 4, parked at (20, 2) in every frame.
TRUCK = dict(track=4, centre=(20.0, 2.0, 1.5), size=(8.0, 2.5, 3.0), yaw=0.0)
SMALL = (2.0, 2.0, 2.0)


def tiny_context(boxes=(TRUCK,), with_ego: bool = True, road_length: float = 200.0) -> PlacementContext:
    """Road |y| < 5 for 0 < x < road_length on flat ground; boxes: dicts (track, centre, size, yaw, frames)."""
    rows = []
    for b in boxes:
        for f in b.get("frames", range(N_FRAMES)):
            rows.append((f, b["track"], b["centre"], b["size"], b["yaw"]))
    if with_ego:
        for f in range(N_FRAMES):
            x = EGO_SPEED * f
            rows.append((f, EGO_TRACK_ID, (x + EGO_AHEAD, 0.0, EGO_BOX[2] / 2), EGO_BOX, 0.0))
    obstacles = Obstacles.from_arrays(*([r[k] for r in rows] for k in range(5)))
    width, height = 640, 360
    mount = ego_from_camera_mount(1.5, 0.0, 1.5, 0.0)
    cameras = Cameras(names=("CAM_FRONT",),
                      world_from_camera=np.stack([pose_from_xyz_yaw(EGO_SPEED * f, 0.0, 0.0, 0.0) @ mount
                                                  for f in range(N_FRAMES)])[:, None],
                      K=intrinsics_from_fov(width, height, math.radians(70.0))[None],
                      width=np.array([width]), height=np.array([height]))
    return PlacementContext(obstacles=obstacles, cameras=cameras,
                            drivable=lambda xy: (np.abs(xy[:, 1]) < 5.0) & (xy[:, 0] > 0.0) & (xy[:, 0] < road_length),
                            ground_z=lambda xy: np.zeros(len(xy)))


@pytest.fixture(scope="module")
def ctx() -> PlacementContext:
    return tiny_context()


def single(ctx, x, y, yaw=0.0, size=SMALL) -> ObjectPoses:
    return ObjectPoses.at(ctx, size, [[x, y, yaw]])


# ----------------------------------------------------------------------------- overlap geometry
def overlap(a, b, clearance=0.0, size_a=SMALL, size_b=SMALL) -> bool:
    """a, b: (x, y, z, yaw)."""
    return bool(boxes_overlap(np.array(a[:3]), np.array(size_a), a[3], np.array(b[:3]), np.array(size_b), b[3],
                              clearance))


def test_touching_boxes_overlap_and_separated_ones_do_not():
    assert overlap((0, 0, 0, 0), (2.0, 0, 0, 0))
    assert not overlap((0, 0, 0, 0), (2.01, 0, 0, 0))
    assert overlap((0, 0, 0, 0), (2.2, 0, 0, 0), clearance=0.3)
    assert not overlap((0, 0, 0, 0), (2.2, 0, 0, 0), clearance=0.1)


def test_rotated_boxes_use_the_separating_axis_test_not_bounding_boxes():
    q = math.radians(45.0)
    # their axis-aligned bounding boxes overlap, the squares do not (corner (1, 1) is 1.41 m from the centre,
    # the rotated square's edge 1 m)
    assert not overlap((0, 0, 0, 0), (2.0, 2.0, 0, q))
    assert overlap((0, 0, 0, 0), (1.6, 1.6, 0, q))
    # a rotated corner poking into the side
    assert overlap((0, 0, 0, 0), (2.3, 0, 0, q))
    assert not overlap((0, 0, 0, 0), (2.5, 0, 0, q))
    # the same pair in a rotated frame gives the same answer
    r = math.radians(30.0)
    rot = np.array([[math.cos(r), -math.sin(r)], [math.sin(r), math.cos(r)]])
    for bx, by, expect in ((2.0, 2.0, False), (1.6, 1.6, True)):
        x, y = rot @ [bx, by]
        assert overlap((0, 0, 0, r), (x, y, 0, q + r)) == expect


def test_boxes_separated_in_height_do_not_overlap():
    assert not overlap((0, 0, 0, 0), (0, 0, 2.5, 0), clearance=0.3)
    assert overlap((0, 0, 0, 0), (0, 0, 2.2, 0), clearance=0.3)


# ----------------------------------------------------------------------------- checks on user poses
def test_a_placement_on_the_egos_path_is_rejected(ctx):
    # the ego box reaches x = 6 around frame 2; nothing else is near
    assert not no_overlap(ctx, single(ctx, 6.0, 0.0))[0] and no_overlap(ctx, single(ctx, 6.0, -3.5))[0]
    result = check_placement(ctx, SMALL, (6.0, 0.0, 0.0))
    assert not result.passed["no_overlap"]
    assert any("ego's path" in line for line in result.failures)
    no_ego = tiny_context(with_ego=False)
    assert check_placement(no_ego, SMALL, (6.0, 0.0, 0.0)).passed["no_overlap"]
    with pytest.raises(OmniscsError,
                       match=r"placement \(6.0, 0.0, yaw 0°\) overlaps the ego's path at frames .*--sample"):
        require_valid(ctx, SMALL, (6.0, 0.0, 0.0))


def test_an_overlap_names_the_track_and_the_frames_where_both_exist():
    ctx = tiny_context(boxes=(TRUCK, dict(track=7, centre=(15.0, -3.0, 0.8), size=(4.5, 1.9, 1.6), yaw=0.0,
                                          frames=range(3, 7))))
    result = check_placement(ctx, SMALL, (15.0, -3.0, 0.0))
    overlaps = [line for line in result.failures if "overlaps" in line]
    assert overlaps == ["overlaps track 7 at frames 3-6 (clearance 0.3 m)"]
    # a moving object that is there only before track 7 arrives does not overlap it
    poses = np.array([[15.0, -3.0, 0.0]] * 3)
    assert check_placement(ctx, SMALL, poses, frames=[0, 1, 2]).passed["no_overlap"]
    assert not check_placement(ctx, SMALL, poses, frames=[1, 2, 3]).passed["no_overlap"]


def test_a_moving_object_is_checked_at_each_of_its_frames(ctx):
    # drives along y = -2.5 ... then swerves into the truck at frames 5-7
    poses = np.array([[30.0, -3.0, 0.0]] * N_FRAMES)
    poses[5:8] = [20.0, 2.0, 0.0]
    result = check_placement(ctx, SMALL, poses)
    assert any(line.startswith("overlaps track 4 at frames 5-7") for line in result.failures)
    assert not on_road(ctx, ObjectPoses.moving(ctx, (2.0, 2.0, 2.0), [[30.0, 4.5, 0.0]] * N_FRAMES))[0]


def test_off_road_placements_are_rejected_and_the_margin_counts(ctx):
    assert on_road(ctx, single(ctx, 30.0, -3.0))[0]
    assert not on_road(ctx, single(ctx, 30.0, 8.0))[0]
    assert not on_road(ctx, single(ctx, 30.0, 4.5))[0]  # centre on the road, a side off it
    assert on_road(ctx, single(ctx, 30.0, 3.5))[0]
    assert not on_road(ctx, single(ctx, 30.0, 3.5), PlacementConfig(road_margin_m=1.0))[0]
    # a 45° yaw swings the corners out (to 3.8 + 1.41 m)
    assert on_road(ctx, single(ctx, 30.0, 3.8))[0]
    assert not on_road(ctx, single(ctx, 30.0, 3.8, yaw=math.radians(45.0)))[0]
    result = check_placement(ctx, SMALL, (30.0, 8.0, 0.0))
    assert not result.passed["on_road"] and "drivable area" in result.message()


def test_behind_the_camera_and_beyond_range_are_not_visible(ctx):
    assert visible(ctx, single(ctx, 25.0, -3.0))[0]
    behind = check_placement(ctx, SMALL, (-20.0, 0.0, 0.0))
    assert not behind.passed["visible"] and "behind the camera" in behind.message()
    far = single(ctx, 100.0, 0.0)
    assert not visible(ctx, far)[0]
    assert visible(ctx, far, PlacementConfig(max_distance_m=120.0))[0]
    assert "beyond 60 m" in check_placement(ctx, SMALL, (100.0, 0.0, 0.0)).message()
    # far to the side: in front of the camera but outside its image
    side = check_placement(ctx, SMALL, (20.0, -30.0, 0.0))
    assert not side.passed["visible"] and "inside the image" in side.message()


def test_a_box_on_the_sight_line_hides_the_object(ctx):
    hidden = single(ctx, 40.0, 4.0)
    assert not visible(ctx, hidden)[0]
    assert visible(tiny_context(boxes=()), hidden)[0]
    assert "hidden behind track 4" in check_placement(ctx, SMALL, (40.0, 4.0, 0.0)).message()


def test_visibility_needs_k_frames(ctx):
    # in view only while the object exists (frames 0-1), not enough for k = 3, enough for k = 2
    objects = ObjectPoses.moving(ctx, SMALL, [[25.0, -3.0, 0.0]] * 2)
    assert not visible(ctx, objects)[0]
    assert visible(ctx, objects, PlacementConfig(min_visible_frames=2))[0]


def test_in_range_measures_the_distance_from_the_camera_at_the_frame(ctx):
    objects = ObjectPoses.at(ctx, SMALL, [[20.0, -3.0, 0.0], [45.0, -3.0, 0.0], [5.0, -3.0, 0.0]])
    assert in_range(ctx, objects, np.zeros(3, dtype=int), np.zeros(3, dtype=int)).tolist() == [True, False, False]
    # at frame 9 the camera is at x = 10.5: 34.5 m to the second one
    assert not in_range(ctx, objects, np.full(3, 9), None)[1]
    assert in_range(ctx, objects, np.full(3, 9), None, PlacementConfig(distance_m=(8.0, 35.0)))[1]
    result = check_placement(ctx, SMALL, (45.0, -3.0, 0.0), frame=0)
    assert not result.passed["in_range"] and "outside the requested 8.0-30.0 m" in result.message()
    assert "in_range" not in check_placement(ctx, SMALL, (45.0, -3.0, 0.0)).passed


def test_a_valid_placement_passes_every_check(ctx):
    result = require_valid(ctx, SMALL, (25.0, -3.0, 0.3), frame=0)
    assert result.ok and result.failures == ()
    assert set(result.passed) == {"on_road", "no_overlap", "visible", "in_range"}


def test_nan_and_non_positive_inputs_are_refused(ctx):
    for pose in ((math.nan, 0.0, 0.0), (20.0, math.inf, 0.0), (20.0, 0.0, math.nan)):
        with pytest.raises(OmniscsError, match="NaN or infinite"):
            check_placement(ctx, SMALL, pose)
    for size in ((math.nan, 1.0, 1.0), (0.0, 1.0, 1.0), (-1.0, 1.0, 1.0), (1.0, 1.0)):
        with pytest.raises(OmniscsError, match="object size"):
            check_placement(ctx, size, (20.0, 0.0, 0.0))
        with pytest.raises(OmniscsError, match="object size"):
            sample_placements(ctx, size, 1)
    with pytest.raises(OmniscsError, match="finite"):
        PlacementConfig(distance_m=(8.0, math.nan))
    with pytest.raises(OmniscsError, match="min <= max"):
        PlacementConfig(distance_m=(30.0, 8.0))
    poses = np.zeros((N_FRAMES, 3))
    poses[4, 1] = math.nan
    with pytest.raises(OmniscsError, match=r"pose \[0.0, nan, 0.0\] has a NaN"):
        check_placement(ctx, SMALL, poses)
    with pytest.raises(OmniscsError, match="NaN or infinite"):
        Obstacles.from_arrays([0], [1], [[0.0, math.nan, 0.0]], [[1.0, 1.0, 1.0]], [0.0])


# ----------------------------------------------------------------------------- sampler
SAMPLE_CONFIG = PlacementConfig(camera="CAM_FRONT")


@pytest.fixture(scope="module")
def sampled(ctx):
    return sample_placements(ctx, (4.0, 2.0, 1.5), 6, SAMPLE_CONFIG, rng_seed=3)


def test_sampled_placements_pass_every_check_when_checked_again(ctx, sampled):
    assert sampled.n_accepted == 6
    for (x, y, z, yaw), frame in zip(sampled.placements, sampled.frames):
        assert z == pytest.approx(0.75)
        result = check_placement(ctx, (4.0, 2.0, 1.5), (x, y, yaw), SAMPLE_CONFIG, frame=int(frame))
        assert result.ok, result.message()
    assert set(sampled.cameras) == {"CAM_FRONT"}


def test_rejection_counts_add_up(sampled):
    r = sampled.rejected
    assert set(r) == {"on_road", "no_overlap", "visible", "in_range", OVERLAPS_ACCEPTED}
    assert sampled.n_accepted + sum(r.values()) >= sampled.n_proposals  # each rejected proposal counts at least once
    assert all(0 <= v <= sampled.n_proposals - sampled.n_accepted for v in r.values())
    assert r["on_road"] > 0  # the camera sees far more than the 10 m wide road
    assert r["in_range"] == 0  # proposals are drawn at the requested distances
    assert sampled.acceptance == pytest.approx(sampled.n_accepted / sampled.n_proposals)
    d = sampled.to_dict()
    assert d["n_accepted"] == 6 and len(d["placements"]) == 6 and d["rejected"] == r


def test_placements_sampled_in_a_small_area_never_overlap_each_other(ctx):
    config = PlacementConfig(camera="CAM_FRONT", distance_m=(12.0, 16.0), yaw_mode="fixed", max_proposals=4000)
    size = (3.0, 1.5, 1.5)
    result = sample_placements(ctx, size, 6, config, rng_seed=1)
    p = result.placements
    for i in range(len(p)):
        for j in range(i + 1, len(p)):
            assert not overlap(p[i], p[j], config.clearance_m, size, size)
    assert result.rejected[OVERLAPS_ACCEPTED] > 0  # the mutual check was exercised
    assert np.allclose(p[:, 3], 0.0)


def test_the_same_seed_gives_the_same_placements(ctx, sampled):
    again = sample_placements(ctx, (4.0, 2.0, 1.5), 6, SAMPLE_CONFIG, rng_seed=3)
    assert np.array_equal(again.placements, sampled.placements) and again.to_dict() == sampled.to_dict()
    other = sample_placements(ctx, (4.0, 2.0, 1.5), 6, SAMPLE_CONFIG, rng_seed=4)
    assert not np.array_equal(other.placements, sampled.placements)


def test_an_object_wider_than_the_road_is_refused_naming_the_road_check(ctx):
    with pytest.raises(PlacementError, match=r"found 0 of 1 placements in 300 proposals .*on_road 300.*does not "
                                             r"fit on this road") as err:
        sample_placements(ctx, (12.0, 11.0, 2.0), 1, PlacementConfig(camera="CAM_FRONT", max_proposals=300))
    assert err.value.result.rejected["on_road"] == 300 and err.value.result.n_accepted == 0


def test_distances_beyond_the_map_are_refused_naming_the_check(ctx):
    with pytest.raises(OmniscsError, match=r"on_road 200.*visible 200.*none of the 200 proposals landed on the "
                                           r"drivable area"):
        sample_placements(ctx, SMALL, 2, PlacementConfig(distance_m=(300.0, 400.0), max_proposals=200))


def test_an_unreachable_visibility_request_names_the_visible_check(ctx):
    with pytest.raises(OmniscsError, match=r"visible 100.*fewer than 11 frames.*only 10 frames"):
        sample_placements(ctx, SMALL, 1, PlacementConfig(min_visible_frames=11, max_proposals=100))
    with pytest.raises(OmniscsError, match=r"visible 100.*within 60 m"):
        sample_placements(ctx, SMALL, 1, PlacementConfig(distance_m=(70.0, 80.0), max_proposals=100,
                                                         road_margin_m=0.0))


def test_yaw_modes(ctx):
    fixed = sample_placements(ctx, SMALL, 3, PlacementConfig(yaw_mode="fixed", yaw=0.5), rng_seed=0)
    assert np.allclose(fixed.placements[:, 3], 0.5)
    with pytest.raises(OmniscsError, match="lane directions"):
        sample_placements(ctx, SMALL, 1, PlacementConfig(yaw_mode="lane"))
    with pytest.raises(OmniscsError, match="yaw mode"):
        PlacementConfig(yaw_mode="random")


def test_ground_height_interpolates_nearby_samples_and_falls_back_to_the_nearest():
    ground = GroundHeight(np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 3.0]]), radius_m=8.0)
    z = ground(np.array([[5.0, 0.0], [3.0, 0.0], [1.0, 0.0], [100.0, 0.0], [-50.0, 0.0]]))
    assert z[0] == pytest.approx(2.0) and 1.2 < z[1] < 1.5  # both samples within 8 m, the nearer weighs more
    assert z[2] == pytest.approx(1.0)  # only one within 8 m
    assert z[3] == pytest.approx(3.0) and z[4] == pytest.approx(1.0)  # none: the nearest
    assert np.isfinite(ground(np.array([[0.0, 0.0]]))).all()


# ----------------------------------------------------------------------------- a rendered synthetic scene
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from nsg_fixtures import write_nsg_scene

    from omniscs.scene import load_scene

    return load_scene(write_nsg_scene(tmp_path_factory.mktemp("placement") / "scene"))


@pytest.fixture(scope="module")
def scene_ctx(scene):
    return placement_context(scene)


def test_the_scene_context_holds_the_logged_boxes_and_the_ego(scene, scene_ctx):
    obs = scene_ctx.obstacles
    ego = obs.track_id == EGO_TRACK_ID
    assert ego.sum() == scene.n_frames and len(obs) == len(scene.boxes) + scene.n_frames
    T = scene.world_from_ego_all
    assert np.allclose(obs.centre[ego, 0], T[:, 0, 3] + 1.3) and np.allclose(obs.centre[ego, 2], T[:, 2, 3] + 0.8)
    assert np.allclose(obs.size[ego], [4.6, 1.9, 1.6])
    assert scene_ctx.cameras.names == tuple(scene.camera_names)
    assert np.allclose(scene_ctx.ground_z(np.array([[20.0, 0.0]])), 0.0, atol=0.05)


def test_the_scene_rejects_logged_cars_and_off_road_poses_and_excluding_a_track_frees_its_place(scene, scene_ctx):
    car = scene.boxes[scene.boxes.track_id == 1].sort_values("frame_idx")
    poses = car[["cx", "cy", "yaw"]].to_numpy()
    size = car[["length", "width", "height"]].to_numpy()[0]
    assert not check_placement(scene_ctx, size, poses).passed["no_overlap"]
    replaced = placement_context(scene, exclude=(1,))
    assert check_placement(replaced, size, poses).passed["no_overlap"]
    assert not check_placement(scene_ctx, SMALL, (20.0, 40.0, 0.0)).passed["on_road"]


def test_the_scene_sampler_places_valid_lane_aligned_objects(scene_ctx):
    config = PlacementConfig(camera="CAM_FRONT", yaw_mode="lane", lane_yaw_jitter=0.0)
    result = sample_placements(scene_ctx, (4.0, 2.0, 1.6), 3, config, rng_seed=0)
    for (x, y, _, yaw), frame in zip(result.placements, result.frames):
        assert check_placement(scene_ctx, (4.0, 2.0, 1.6), (x, y, yaw), config, frame=int(frame)).ok
    assert np.all(np.abs(np.sin(result.placements[:, 3])) < 0.05)  # the straight road's lanes run along x
    with pytest.raises(OmniscsError, match="on_road"):
        sample_placements(scene_ctx, (4.0, 2.0, 1.6), 1, PlacementConfig(distance_m=(2_000.0, 2_100.0),
                                                                          max_proposals=100))
    with pytest.raises(OmniscsError, match="does not fit on this road"):
        sample_placements(scene_ctx, (20.0, 20.0, 2.0), 1, PlacementConfig(max_proposals=200))
