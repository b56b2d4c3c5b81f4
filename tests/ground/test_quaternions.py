"""Quaternions (one home, numpy and torch): exact round trips, Hamilton products, q and -q, and the extremes
(identity, 180°, zero norm) never give NaN or Inf."""
import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from omniscs.errors import OmniscsError
from omniscs.geometry import rotmat_from_euler, wrap_angle, yaw_from_matrix
from omniscs.quaternions import (normalize_quats, quat_from_axis_angle, quat_multiply, quat_normalize, quat_to_rotmat,
                                 rotmat_to_quat, rotmats_from_quats, rotmats_from_unit_quats, yaw_from_quaternion,
                                 yaw_to_quat)

quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3)

#: Rotations that stress the formulas: identity, a tiny turn, and half turns about each axis and a diagonal.
EXTREMES = {
    "identity": [1.0, 0.0, 0.0, 0.0],
    "tiny turn": quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), 1e-12).tolist(),
    "180 about x": [0.0, 1.0, 0.0, 0.0],
    "180 about y": [0.0, 0.0, 1.0, 0.0],
    "180 about z": [0.0, 0.0, 0.0, 1.0],
    "180 about a diagonal": quat_from_axis_angle(np.array([1.0, 1.0, 1.0]), np.pi).tolist(),
    "just short of 180": quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), np.pi - 1e-9).tolist(),
}


# ----------------------------------------------------------------------------- numpy float64 (data)
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


def test_zero_norm_quaternion_in_data_is_a_clear_error():
    with pytest.raises(OmniscsError, match="zero norm"):
        quat_to_rotmat(np.zeros(4))
    with pytest.raises(OmniscsError):
        quat_normalize(np.array([np.nan, 0, 0, 1]))
    with pytest.raises(OmniscsError, match="zero length"):
        quat_from_axis_angle(np.zeros(3), 1.0)


def test_unnormalised_quaternion_gives_the_normalised_rotation():
    q = np.array([2.0, 0.0, 0.0, 2.0])
    np.testing.assert_allclose(quat_to_rotmat(q), rotmat_from_euler(yaw=np.pi / 2), atol=1e-12)


@given(quats, quats)
def test_quaternion_product_matches_matrix_product(a, b):
    a, b = np.array(a), np.array(b)
    np.testing.assert_allclose(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-9)


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.0, np.pi, -np.pi])
def test_yaw_quaternion_is_the_turn_about_z(yaw):
    np.testing.assert_allclose(quat_to_rotmat(yaw_to_quat(yaw)), rotmat_from_euler(yaw=yaw), atol=1e-12)
    np.testing.assert_allclose(yaw_to_quat(yaw), quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), yaw), atol=0)


# ----------------------------------------------------------------------------- torch (learnable orientations)
@pytest.mark.parametrize("name", EXTREMES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_rotation_matches_numpy_at_the_extremes_for_q_and_minus_q(name, dtype):
    q = np.array(EXTREMES[name])
    expected = quat_to_rotmat(q)
    for sign in (1.0, -1.0):
        R = rotmats_from_quats(torch.tensor(sign * 3.0 * q, dtype=dtype))  # any norm
        assert torch.isfinite(R).all()
        np.testing.assert_allclose(R.double().numpy(), expected, atol=1e-6 if dtype == torch.float32 else 1e-12)


@given(quats, quats)
def test_torch_and_numpy_hamilton_products_agree(a, b):
    expected = quat_multiply(np.array(a), np.array(b))
    got = quat_multiply(torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64))
    np.testing.assert_array_equal(got.numpy(), expected)  # one formula: bit-identical


def test_product_with_the_identity_and_with_minus_q():
    q = torch.tensor([[0.3, -0.5, 0.1, 0.8]], dtype=torch.float64)
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.equal(quat_multiply(identity, q), q) and torch.equal(quat_multiply(q, identity), q)
    torch.testing.assert_close(rotmats_from_quats(quat_multiply(q, q)), rotmats_from_quats(quat_multiply(-q, q)))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_norm_torch_quaternion_is_the_identity_with_zero_gradient(dtype):
    q = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1e-30, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0]], dtype=dtype,
                     requires_grad=True)
    unit = normalize_quats(q)
    R = rotmats_from_quats(q)
    assert torch.equal(unit[0].detach(), torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype))
    assert torch.equal(R[:2].detach(), torch.eye(3, dtype=dtype).expand(2, 3, 3))
    (unit.sum() + (R * torch.arange(9, dtype=dtype).reshape(3, 3)).sum()).backward()
    assert torch.isfinite(q.grad).all()
    assert torch.equal(q.grad[:2], torch.zeros(2, 4, dtype=dtype))
    assert q.grad[2].abs().sum() > 0  # a usable quaternion does learn


def test_zero_norm_numpy_copy_of_a_learnt_quaternion_is_the_identity():
    q = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, -5.0]])
    np.testing.assert_array_equal(normalize_quats(q), [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, -1.0]])


@given(quats)
def test_unit_rotation_of_a_normalised_quaternion_is_the_rotation_of_the_raw_one(q):
    raw = torch.tensor(q, dtype=torch.float64)
    assert torch.equal(rotmats_from_unit_quats(normalize_quats(raw)), rotmats_from_quats(raw))
    assert torch.allclose(normalize_quats(raw).norm(), torch.tensor(1.0, dtype=torch.float64))


@given(quats)
def test_the_yaw_of_a_quaternion_is_the_yaw_of_its_matrix_and_the_same_for_minus_q(q):
    q = np.array(q)
    yaw = yaw_from_quaternion(q)
    assert np.isfinite(yaw)
    R = quat_to_rotmat(q)
    if np.hypot(R[0, 0], R[1, 0]) > 1e-6:  # x axis not straight up or down, where the heading is undefined
        assert abs(wrap_angle(yaw - yaw_from_matrix(R))) < 1e-9
    assert abs(wrap_angle(yaw - yaw_from_quaternion(-q))) < 1e-12


def test_yaw_from_quaternion_inverts_yaw_to_quat_over_a_batch():
    yaws = np.linspace(-3.0, 3.0, 7)
    assert np.allclose(yaw_from_quaternion(3.0 * yaw_to_quat(yaws)), yaws)  # any non-zero norm


def test_a_batch_of_rotations_gives_each_the_quaternion_it_gets_alone_on_every_branch():
    rng = np.random.default_rng(12)
    q = rng.normal(size=(400, 4))
    q[:4] = np.eye(4)  # 0 and 180 degree turns: each of Shepperd's four branches
    q[4:8] = np.eye(4) + 1e-9 * rng.normal(size=(4, 4))
    R = quat_to_rotmat(q)
    R[8:40] = R[8:40].round(2)  # not quite orthonormal
    alone = np.stack([rotmat_to_quat(r) for r in R])
    picked = np.argmax(np.concatenate([np.trace(R, axis1=1, axis2=2)[:, None],
                                       np.diagonal(R, axis1=1, axis2=2)], 1), 1)
    assert set(picked.tolist()) == {0, 1, 2, 3}
    assert np.array_equal(rotmat_to_quat(R), alone)  # bit for bit: a fit's nodes are converted together
    assert np.array_equal(rotmat_to_quat(R.reshape(20, 20, 3, 3)).reshape(-1, 4), alone)
