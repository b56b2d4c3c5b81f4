"""Geometry: rotations, SE(3), boxes and cameras stay exact and finite at the extremes (quaternions:
test_quaternions.py)."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from omniscs.geometry import (box_corners, box_corners_from_pose, clip_segment_to_near, compose,
                              ego_from_camera_mount, euler_from_rotmat, intrinsics_from_fov, invert_transform, is_rigid,
                              make_transform, points_in_box, pose_from_xyz_yaw, project, rotmat_from_euler,
                              transform_points, unproject, world_from_box, wrap_angle, yaw_from_matrix)

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@given(finite, finite, finite, st.floats(-10, 10))
def test_inverse_transform_composes_to_identity(x, y, z, yaw):
    T = pose_from_xyz_yaw(x, y, z, yaw)
    np.testing.assert_allclose(compose(T, invert_transform(T)), np.eye(4), atol=1e-9)
    assert is_rigid(invert_transform(T))


@given(st.floats(-np.pi, np.pi), st.floats(-np.pi / 2, np.pi / 2), st.floats(-np.pi, np.pi))
def test_euler_from_rotmat_gives_angles_that_rebuild_the_rotation(roll, pitch, yaw):
    R = rotmat_from_euler(roll, pitch, yaw)
    angles = euler_from_rotmat(R)
    np.testing.assert_allclose(rotmat_from_euler(*angles), R, atol=1e-9)
    assert abs(angles[1]) <= np.pi / 2 and all(np.isfinite(angles))


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2])
def test_euler_from_rotmat_at_gimbal_lock_puts_the_whole_turn_in_yaw(pitch):
    R = rotmat_from_euler(0.4, pitch, 1.1)
    roll, found_pitch, yaw = euler_from_rotmat(R)
    assert roll == 0.0 and found_pitch == pytest.approx(pitch)
    np.testing.assert_allclose(rotmat_from_euler(roll, found_pitch, yaw), R, atol=1e-9)


def test_is_rigid_rejects_scaling_reflection_and_nan():
    assert not is_rigid(make_transform(2 * np.eye(3), np.zeros(3)))
    assert not is_rigid(make_transform(np.diag([1.0, 1.0, -1.0]), np.zeros(3)))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    assert not is_rigid(bad)


@given(st.floats(-20, 20))
def test_yaw_round_trips_through_rotation(yaw):
    assert abs(wrap_angle(yaw_from_matrix(rotmat_from_euler(yaw=yaw)) - yaw)) < 1e-9


def test_box_corners_front_face_is_ahead_and_points_in_box():
    corners = box_corners(np.array([10.0, 5.0, 1.0]), np.array([4.0, 2.0, 1.5]), np.pi / 2)
    assert np.allclose(corners[:4, 1], 7.0)  # heading +y: the front face is at y = 5 + 2
    box = world_from_box([10, 5, 1], np.pi / 2)
    assert points_in_box(np.array([[10.0, 6.9, 1.0]]), box, [4, 2, 1.5]).all()
    assert not points_in_box(np.array([[11.5, 5.0, 1.0]]), box, [4, 2, 1.5]).any()
    assert points_in_box(np.array([[11.5, 5.0, 1.0]]), box, [4, 2, 1.5], margin=0.6).all()  # grown on every side
    assert points_in_box(np.array([[10.0, 7.0, 1.0, 0.3]]), box, [4, 2, 1.5]).all()  # faces count; extra columns not


def test_overturned_box_corners_match_the_upright_box_set():
    size = np.array([4.0, 2.0, 1.5])
    upright = box_corners_from_pose(pose_from_xyz_yaw(0, 0, 0.75, 0.3), size)
    flipped = box_corners_from_pose(make_transform(rotmat_from_euler(np.pi, 0, 0.3), [0, 0, 0.75]), size)
    d = np.linalg.norm(upright[:, None] - flipped[None], axis=-1).min(axis=1)
    assert d.max() < 1e-9  # rolling 180° maps the box onto itself, with corners relabelled


@given(st.floats(-0.6, 0.6), st.floats(-0.3, 0.3), st.floats(0.5, 1e4))
def test_project_then_unproject_recovers_points_up_to_10_km(u_tan, v_tan, z):
    K = intrinsics_from_fov(480, 270, np.radians(70))
    p = np.array([[u_tan * z, v_tan * z, z]])
    uv, depth, ok = project(p, K)
    assert ok.all()
    np.testing.assert_allclose(unproject(uv, depth, K), p, rtol=1e-9, atol=1e-9)


def test_points_at_and_behind_the_near_plane_do_not_project_and_stay_finite():
    K = intrinsics_from_fov(480, 270, np.radians(70))
    pts = np.array([[1.0, 1.0, 0.01], [1.0, 1.0, 0.0], [1.0, 1.0, -5.0], [0.0, 0.0, 1e-300], [3.0, 0.0, 1e4]])
    uv, depth, ok = project(pts, K, near=0.01)
    assert ok.tolist() == [False, False, False, False, True]
    assert np.all(np.isfinite(uv)) and np.all(np.isfinite(depth))


def test_segment_clipping_to_the_near_plane():
    a, b = np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 3.0])
    ca, cb = clip_segment_to_near(a, b, near=1.0)
    assert ca[2] == pytest.approx(1.0) and cb[2] == 3.0
    assert clip_segment_to_near(a, np.array([0, 0, -2.0]), near=0.1) is None


def test_forward_camera_looks_along_ego_x():
    ego_from_cam = ego_from_camera_mount(1.5, 0.0, 1.6, yaw=0.0)
    ahead = transform_points(invert_transform(ego_from_cam), np.array([[20.0, 0.0, 1.6], [20.0, 2.0, 1.6],
                                                                        [20.0, 0.0, 3.0]]))
    assert ahead[0, 2] == pytest.approx(18.5)   # z forward
    assert ahead[1, 0] < 0                       # ego +y (left) is image -x
    assert ahead[2, 1] < 0                       # ego +z (up) is image -y
    left = transform_points(invert_transform(ego_from_camera_mount(0, 0, 1.6, yaw=np.pi / 2)), np.array([[0, 10.0, 1.6]]))
    assert left[0, 2] == pytest.approx(10.0)
