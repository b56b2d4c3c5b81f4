"""Geometry: quaternions, SE(3), boxes and cameras stay exact and finite at the extremes."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from omniscs.errors import OmniscsError
from omniscs.geometry import (box_corners, box_corners_from_pose, clip_segment_to_near, compose,
                              ego_from_camera_mount, intrinsics_from_fov, invert_transform, is_rigid,
                              make_transform, points_in_box, pose_from_xyz_yaw, project, quat_from_axis_angle,
                              quat_multiply, quat_normalize, quat_to_rotmat, rotmat_from_euler, rotmat_to_quat,
                              transform_points, unproject, wrap_angle, yaw_of)

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3)


@given(quats)
def test_q_and_minus_q_give_the_same_rotation(q):
    q = np.array(q)
    np.testing.assert_allclose(quat_to_rotmat(q), quat_to_rotmat(-q), atol=1e-12)


@given(quats)
def test_rotmat_quat_round_trip_is_orthonormal_and_exact(q):
    R = quat_to_rotmat(np.array(q))
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(quat_to_rotmat(rotmat_to_quat(R)), R, atol=1e-12)


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
@pytest.mark.parametrize("angle", [np.pi, np.pi - 1e-9, 1e-12, 0.0])
def test_rotations_near_identity_and_at_180_degrees_round_trip(axis, angle):
    q = quat_from_axis_angle(np.array(axis, float), angle)
    R = quat_to_rotmat(q)
    q2 = rotmat_to_quat(R)
    assert np.all(np.isfinite(q2))
    np.testing.assert_allclose(quat_to_rotmat(q2), R, atol=1e-9)
    assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-6


def test_zero_norm_quaternion_is_a_clear_error():
    with pytest.raises(OmniscsError, match="zero norm"):
        quat_to_rotmat(np.zeros(4))
    with pytest.raises(OmniscsError):
        quat_normalize(np.array([np.nan, 0, 0, 1]))


def test_unnormalised_quaternion_gives_the_normalised_rotation():
    q = np.array([2.0, 0.0, 0.0, 2.0])
    np.testing.assert_allclose(quat_to_rotmat(q), rotmat_from_euler(yaw=np.pi / 2), atol=1e-12)


@given(quats, quats)
def test_quaternion_product_matches_matrix_product(a, b):
    a, b = np.array(a), np.array(b)
    np.testing.assert_allclose(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-9)


@given(finite, finite, finite, st.floats(-10, 10))
def test_inverse_transform_composes_to_identity(x, y, z, yaw):
    T = pose_from_xyz_yaw(x, y, z, yaw)
    np.testing.assert_allclose(compose(T, invert_transform(T)), np.eye(4), atol=1e-9)
    assert is_rigid(invert_transform(T))


def test_is_rigid_rejects_scaling_reflection_and_nan():
    assert not is_rigid(make_transform(2 * np.eye(3), np.zeros(3)))
    assert not is_rigid(make_transform(np.diag([1.0, 1.0, -1.0]), np.zeros(3)))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    assert not is_rigid(bad)


@given(st.floats(-20, 20))
def test_yaw_round_trips_through_rotation(yaw):
    assert abs(wrap_angle(yaw_of(rotmat_from_euler(yaw=yaw)) - yaw)) < 1e-9


def test_box_corners_front_face_is_ahead_and_points_in_box():
    corners = box_corners(np.array([10.0, 5.0, 1.0]), np.array([4.0, 2.0, 1.5]), np.pi / 2)
    assert np.allclose(corners[:4, 1], 7.0)  # heading +y: the front face is at y = 5 + 2
    assert points_in_box(np.array([[10.0, 6.9, 1.0]]), [10, 5, 1], [4, 2, 1.5], np.pi / 2).all()
    assert not points_in_box(np.array([[11.5, 5.0, 1.0]]), [10, 5, 1], [4, 2, 1.5], np.pi / 2).any()


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
