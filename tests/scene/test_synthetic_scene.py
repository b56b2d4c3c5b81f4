"""Synthetic scenes through the scene store: LiDAR, depth, masks, boxes and poses tie together."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.geometry import (box_corners_from_pose, invert_transform, make_transform, project, transform_points,
                              unproject)
from omniscs.pipeline.stages import ingest_stage
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene import SyntheticSource, load_scene, write_synthetic_scene

SOURCE = SyntheticSource(template="straight_parked_truck", seed=3, n_frames=6, n_cameras=3, width=160, height=90)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return load_scene(write_synthetic_scene(SOURCE, tmp_path_factory.mktemp("syn") / "scene"))


def _box_pose(row) -> np.ndarray:
    return make_transform(quat_to_rotmat(np.array([row.qw, row.qx, row.qy, row.qz])), [row.cx, row.cy, row.cz])


def test_a_synthetic_scene_exposes_its_worlds_road_map(scene):
    from omniscs.world import road_map_for

    expected, road = road_map_for(scene.world), scene.road_map
    assert road is not None and road.to_dict() == expected.to_dict()
    assert road.is_drivable(scene.world_from_ego_all[:, :2, 3]).all()  # the ego drives on the road


def test_synthetic_scene_has_ground_truth_and_the_world_it_came_from(scene):
    assert scene.has_gt and scene.has_lidar and scene.world is not None
    assert scene.world.n_frames == scene.n_frames == 6
    depth = scene.depth("CAM_FRONT", 0)
    assert depth.dtype == np.float32 and depth.shape == (90, 160) and np.all(np.isfinite(depth))
    assert scene.instance_mask("CAM_FRONT", 0).dtype == np.int32


def test_lidar_points_and_gt_depth_agree_after_projection(scene):
    rel_errors = []
    for f in range(scene.n_frames):
        pts_ego = scene.lidar(f)[:, :3].astype(np.float64)
        for cam in scene.camera_names:
            K = scene.intrinsics(cam)
            pts_cam = transform_points(invert_transform(scene.ego_from_camera(cam)), pts_ego)
            uv, z, ok = project(pts_cam, K, near=0.5)
            w, h = scene.image_size(cam)
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            px = np.floor(uv[ok]).astype(int)
            gt = scene.depth(cam, f)[px[:, 1], px[:, 0]]
            hit = gt > 0
            rel_errors.append(np.abs(gt[hit] - z[ok][hit]) / z[ok][hit])
    rel = np.concatenate(rel_errors)
    assert len(rel) > 1000
    assert np.median(rel) < 0.02          # pixel quantisation and depth edges make the tail
    assert np.mean(rel < 0.05) > 0.85


def test_visible_agent_box_centre_lands_on_its_own_instance_id(scene):
    checked = hits = 0
    for f in range(scene.n_frames):
        for cam in scene.camera_names:
            inst = scene.instance_mask(cam, f)
            depth = scene.depth(cam, f)
            cam_from_world = invert_transform(scene.world_from_camera(cam, f))
            w, h = scene.image_size(cam)
            for row in scene.boxes_at(f).itertuples():
                if (inst == row.track_id).sum() < 150:
                    continue
                c = transform_points(cam_from_world, np.array([[row.cx, row.cy, row.cz]]))
                uv, z, ok = project(c, scene.intrinsics(cam), near=0.5)
                u, v = np.floor(uv[0]).astype(int)
                if not (ok[0] and 0 <= u < w and 0 <= v < h):
                    continue
                checked += 1
                if inst[v, u] == row.track_id:
                    hits += 1
                else:  # only something nearer than the box's near face may cover its centre
                    assert depth[v, u] < z[0] - 0.4 * min(row.length, row.width), (f, cam, row.track_id)
    assert checked >= 10 and hits / checked > 0.8


def test_instance_pixels_unproject_into_their_own_box_through_the_recorded_poses(scene):
    inside = total = 0
    for f in (0, scene.n_frames - 1):
        boxes = {r.track_id: r for r in scene.boxes_at(f).itertuples()}
        for cam in scene.camera_names:
            inst, depth = scene.instance_mask(cam, f), scene.depth(cam, f)
            v, u = np.nonzero(inst >= 0)
            pts_cam = unproject(np.stack([u + 0.5, v + 0.5], 1), depth[v, u], scene.intrinsics(cam))
            pts_world = transform_points(scene.world_from_camera(cam, f), pts_cam)
            for tid in np.unique(inst[v, u]):
                r = boxes[int(tid)]
                local = transform_points(invert_transform(_box_pose(r)), pts_world[inst[v, u] == tid])
                within = np.all(np.abs(local) <= 0.5 * np.array([r.length, r.width, r.height]) + 0.05, axis=1)
                inside += within.sum()
                total += len(within)
    assert total > 5000 and inside / total > 0.99


def test_lidar_counts_and_visible_pixels_in_boxes_match_the_raw_data(scene):
    f = 0
    pts_world = transform_points(scene.world_from_ego(f), scene.lidar(f)[:, :3])
    counts = {}
    for cam in scene.camera_names:
        ids, n = np.unique(scene.instance_mask(cam, f), return_counts=True)
        for i, c in zip(ids, n):
            counts[int(i)] = counts.get(int(i), 0) + int(c)
    for row in scene.boxes_at(f).itertuples():
        assert row.visible_pixels == counts.get(row.track_id, 0)
        local = transform_points(invert_transform(_box_pose(row)), pts_world)
        n_in = np.all(np.abs(local) <= 0.5 * np.array([row.length, row.width, row.height]) + 0.05, axis=1).sum()
        assert row.num_lidar_points == n_in
    truck = scene.boxes_at(f).sort_values("visible_pixels").iloc[-1]
    assert truck.num_lidar_points > 50  # the large parked object right beside the ego is well sampled


def test_boxes_follow_the_world_agents_and_move_with_their_recorded_poses(scene):
    world = scene.world
    for agent in world.agents:
        rows = scene.boxes[scene.boxes.track_id == agent.track_id].sort_values("frame_idx")
        np.testing.assert_array_equal(rows.frame_idx.to_numpy(), np.flatnonzero(agent.present))
        np.testing.assert_allclose(rows[["cx", "cy", "cz"]].to_numpy(), agent.poses[agent.present, :3, 3], atol=1e-9)
        for r, pose in zip(rows.itertuples(), agent.poses[agent.present]):
            np.testing.assert_allclose(box_corners_from_pose(_box_pose(r), agent.size),
                                       box_corners_from_pose(pose, agent.size), atol=1e-9)
    # a static agent seen from the moving ego shifts back by exactly the ego's own motion
    static = scene.boxes.groupby("track_id").filter(lambda g: np.ptp(g.cx) == 0 and len(g) == scene.n_frames)
    row0 = static[static.frame_idx == 0].iloc[0]
    p = np.array([[row0.cx, row0.cy, row0.cz]])
    in_ego = [transform_points(invert_transform(scene.world_from_ego(f)), p)[0] for f in range(scene.n_frames)]
    ego_step = [scene.world_from_ego(f)[:3, 3] - scene.world_from_ego(f - 1)[:3, 3] for f in range(1, scene.n_frames)]
    assert np.linalg.norm(ego_step[0]) > 0.3
    np.testing.assert_allclose(np.diff(in_ego, axis=0)[:, 0], -np.array(ego_step)[:, 0], atol=1e-6)


def test_ingest_reuses_an_identical_synthetic_scene_and_renders_a_new_one(tmp_path):
    small = SyntheticSource(template="straight", seed=1, n_frames=2, n_cameras=1, width=48, height=27)
    first = ingest_stage(small, tmp_path)
    again = ingest_stage(small, tmp_path)
    other = ingest_stage(SyntheticSource(template="straight", seed=2, n_frames=2, n_cameras=1, width=48, height=27), tmp_path)
    assert not first.reused and again.reused and again.path == first.path
    assert other.scene_id != first.scene_id and not other.reused
    assert len(list((tmp_path / "scenes").iterdir())) == 2
