"""Kinematic bicycle decoding: every rolled-out trajectory is feasible, whatever the controls."""
import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from omniscs.scs.behavior.kinematics import (KinematicLimits, accelerations, bound_controls, rollout,
                                             yaw_rate_bound)

LIMITS = KinematicLimits()
DT = 0.1


def _state(x=0.0, y=0.0, yaw=0.0, v=0.0, w=0.0):
    return torch.tensor([[x, y, yaw, v, w]], dtype=torch.float32)


@settings(max_examples=40, deadline=None)
@given(raw_scale=st.sampled_from([0.0, 1.0, 10.0, 1e3, 1e6]), v0=st.floats(0.0, 60.0), w0=st.floats(-5.0, 5.0),
       seed=st.integers(0, 2**16))
def test_speed_and_yaw_rate_stay_within_their_bounds_for_any_controls(raw_scale, v0, w0, seed):
    g = torch.Generator().manual_seed(seed)
    raw = torch.randn(4, 30, 2, generator=g) * raw_scale
    states = rollout(_state(v=v0, w=w0).expand(4, 5), bound_controls(raw, LIMITS), DT, LIMITS)
    assert torch.isfinite(states).all()
    v, w = states[..., 3], states[..., 4]
    assert (v >= 0).all() and (v <= LIMITS.max_speed + 1e-4).all()
    assert (w.abs() <= yaw_rate_bound(v, LIMITS) + 1e-5).all()
    lon, lat = accelerations(_state(v=min(v0, LIMITS.max_speed)).expand(4, 5), states, DT)
    assert (lon <= LIMITS.max_accel + 1e-3).all() and (lon >= -LIMITS.max_decel - 1e-3).all()
    assert (lat.abs() <= LIMITS.max_lateral_accel + 1e-3).all()


def test_zero_controls_drive_at_constant_velocity():
    states = rollout(_state(x=1.0, yaw=np.pi / 2, v=5.0), torch.zeros(1, 20, 2), DT, LIMITS)
    assert torch.allclose(states[0, -1, :2], torch.tensor([1.0, 10.0]), atol=1e-4)
    assert torch.allclose(states[0, :, 3], torch.full((20,), 5.0))


def test_a_standing_vehicle_cannot_turn_on_the_spot():
    controls = torch.zeros(1, 30, 2)
    controls[..., 1] = LIMITS.max_yaw_accel  # full steering, no throttle
    states = rollout(_state(v=0.0, w=0.8), controls, DT, LIMITS)
    assert torch.equal(states[0, :, :3], torch.zeros(30, 3))


def test_braking_stops_without_reversing_and_pulls_away_again():
    controls = torch.zeros(1, 30, 2)
    controls[0, :15, 0] = -LIMITS.max_decel
    controls[0, 15:, 0] = 2.0
    states = rollout(_state(v=3.0), controls, DT, LIMITS)
    x, v = states[0, :, 0], states[0, :, 3]
    assert (torch.diff(x) >= -1e-6).all()
    assert v[14] == 0.0 and torch.isclose(v[15], torch.tensor(2.0 * DT))


def test_gradients_are_finite_for_stopped_and_fast_agents():
    raw = torch.zeros(3, 30, 2, requires_grad=True)
    state0 = torch.tensor([[0, 0, 0, 0.0, 0], [0, 0, 0, 49.9, 0.5], [0, 0, 0, 1e-7, 0]], dtype=torch.float32)
    rollout(state0, bound_controls(raw, LIMITS), DT, LIMITS)[..., :3].sum().backward()
    assert torch.isfinite(raw.grad).all() and raw.grad.abs().sum() > 0
