"""Shared reader geometry: re-origin keeps the global up axis, interpolation of box poses is stable at the extremes."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from omniscs.geometry import make_transform, rotmat_from_euler
from omniscs.quaternions import quat_from_axis_angle, quat_to_rotmat, slerp
from omniscs.scene.sources.common import interpolate_pose, world_from_global_at

angles = st.floats(-np.pi, np.pi, allow_nan=False)


@given(angles, st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(-1e4, 1e4))
@settings(max_examples=50, deadline=None)
def test_re_origin_puts_the_first_pose_at_the_origin_heading_x_and_keeps_z_up(yaw, pitch, roll, offset):
    global_from_ego = make_transform(rotmat_from_euler(roll, pitch, yaw), [offset, -offset / 3, 12.0])
    world_from_global = world_from_global_at(global_from_ego)
    first = world_from_global @ global_from_ego
    assert np.allclose(first[:3, 3], 0.0, atol=1e-9)
    assert np.allclose(world_from_global[:3, 2], [0.0, 0.0, 1.0], atol=1e-12)  # global up is world up
    assert abs(np.arctan2(first[1, 0], first[0, 0])) < 1e-9  # heading along world x


def test_slerp_takes_the_short_arc_and_treats_q_and_minus_q_alike():
    q = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), 0.4)
    assert np.allclose(slerp(q, -q, 0.3), q)
    half_turn = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi)
    mid = quat_to_rotmat(slerp(np.array([1.0, 0, 0, 0]), half_turn, 0.5))
    assert np.allclose(mid, rotmat_from_euler(yaw=np.pi / 2), atol=1e-12)
    near = quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), 1e-13)
    assert np.all(np.isfinite(slerp(np.array([1.0, 0, 0, 0]), near, 0.5)))


@given(angles, angles, st.floats(0.0, 1.0))
@settings(max_examples=50, deadline=None)
def test_interpolated_pose_moves_the_centre_linearly_and_turns_the_yaw_along_the_short_arc(yaw0, yaw1, t):
    a = make_transform(rotmat_from_euler(yaw=yaw0), [0.0, 0.0, 1.0])
    b = make_transform(rotmat_from_euler(yaw=yaw1), [10.0, -4.0, 1.0])
    pose = interpolate_pose(a, b, t)
    assert np.allclose(pose[:3, 3], [10.0 * t, -4.0 * t, 1.0])
    delta = (yaw1 - yaw0 + np.pi) % (2 * np.pi) - np.pi
    if abs(abs(delta) - np.pi) > 1e-6:  # exactly opposite headings have two short arcs
        expected = rotmat_from_euler(yaw=yaw0 + t * delta)
        assert np.allclose(pose[:3, :3], expected, atol=1e-9)
