"""L_beh (log-sum-exp softmax over agents and steps) and the box geometry behind success and plausibility."""
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from omniscs.scs.behavior.collision import box_iou, footprints, overlapping
from omniscs.scs.behavior.losses import behavior_loss, disc_centres, restore_loss


def _naive(agent_xy, plan_xy):  # the paper's formula written directly (underflows far away)
    d = (agent_xy - plan_xy[None]).norm(dim=-1)
    delta = torch.exp(-d) / torch.exp(-d).sum()
    return (delta * d ** 2).sum()


def test_lbeh_is_the_papers_softmax_weighted_distance_for_near_agents():
    g = torch.Generator().manual_seed(0)
    agents, plan = torch.randn(3, 8, 2, generator=g) * 3, torch.randn(8, 2, generator=g)
    loss, delta = behavior_loss(agents, plan, torch.ones(3, 8, dtype=torch.bool))
    assert torch.isclose(loss, _naive(agents, plan), rtol=1e-5)
    assert torch.isclose(delta.sum(), torch.tensor(1.0)) and (delta >= 0).all()


@pytest.mark.parametrize("far_m", [300.0, 10_000.0, 1e6])
def test_lbeh_does_not_underflow_to_nan_when_every_agent_is_far(far_m):
    agents = torch.tensor([[[far_m, 0.0]] * 5, [[0.0, far_m * 1.5]] * 5], requires_grad=True)
    plan = torch.zeros(5, 2)
    assert torch.isnan(_naive(agents.detach(), plan)), "the naive formula is the failure this guards against"
    loss, delta = behavior_loss(agents, plan, torch.ones(2, 5, dtype=torch.bool))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(agents.grad).all()
    assert torch.isclose(delta.sum(), torch.tensor(1.0))
    assert torch.isclose(loss, torch.tensor(far_m ** 2), rtol=1e-4)  # all weight on the nearest agent
    assert (delta[1] == 0).all()


def test_lbeh_weights_only_participating_agents_and_steps():
    agents = torch.tensor([[[1.0, 0.0], [2.0, 0.0]], [[0.1, 0.0], [0.1, 0.0]]], requires_grad=True)
    mask = torch.tensor([[True, True], [False, False]])
    loss, delta = behavior_loss(agents, torch.zeros(2, 2), mask)
    loss.backward()
    assert (delta[1] == 0).all() and (agents.grad[1] == 0).all()
    assert delta[0, 0] > delta[0, 1]  # the closer step weighs more


def test_lbeh_without_participants_is_zero_with_zero_gradient():
    agents = torch.randn(2, 4, 2, requires_grad=True)
    loss, delta = behavior_loss(agents, torch.zeros(4, 2), torch.zeros(2, 4, dtype=torch.bool))
    loss.backward()
    assert loss.item() == 0.0 and (delta == 0).all() and (agents.grad == 0).all()


def test_lbeh_of_an_agent_on_the_plan_has_a_finite_gradient():
    agents = torch.zeros(1, 3, 2, requires_grad=True)
    loss, _ = behavior_loss(agents, torch.zeros(3, 2), torch.ones(1, 3, dtype=torch.bool))
    loss.backward()
    assert torch.isfinite(agents.grad).all() and loss.item() == pytest.approx(0.0, abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(distances=st.lists(st.floats(0.0, 1e7), min_size=1, max_size=12))
def test_lbeh_weights_form_a_distribution_at_any_scale(distances):
    agents = torch.tensor([[[d, 0.0]] for d in distances], dtype=torch.float32)
    loss, delta = behavior_loss(agents, torch.zeros(1, 2), torch.ones(len(distances), 1, dtype=torch.bool))
    assert torch.isfinite(loss) and torch.isfinite(delta).all()
    assert abs(float(delta.sum()) - 1.0) < 1e-5 and (delta >= 0).all()


def test_restore_loss_ignores_masked_agents():
    z0 = torch.zeros(3, 4)
    z = torch.ones(3, 4)
    assert restore_loss(z, z0, torch.tensor([0.0, 1.0, 1.0])).item() == 8.0


def test_identical_boxes_have_iou_one_and_separate_boxes_zero():
    a = footprints(np.zeros(2), 0.3, 4.0, 2.0)
    assert box_iou(a, a) == pytest.approx(1.0)
    assert box_iou(a, footprints(np.array([10.0, 0.0]), 0.3, 4.0, 2.0)) == 0.0


def test_boxes_shifted_by_half_their_length_overlap_by_one_third():
    a = footprints(np.zeros(2), 0.0, 4.0, 2.0)
    b = footprints(np.array([2.0, 0.0]), 0.0, 4.0, 2.0)
    assert box_iou(a, b) == pytest.approx(4.0 / 12.0)
    assert overlapping(a, b)


@settings(max_examples=40, deadline=None)
@given(dx=st.floats(-6, 6), dy=st.floats(-6, 6), yaw_a=st.floats(-4, 4), yaw_b=st.floats(-4, 4),
       turn=st.floats(-4, 4))
def test_iou_is_symmetric_bounded_and_unchanged_by_turning_the_whole_scene(dx, dy, yaw_a, yaw_b, turn):
    a = footprints(np.zeros(2), yaw_a, 4.5, 1.9)
    b = footprints(np.array([dx, dy]), yaw_b, 4.0, 1.8)
    iou = box_iou(a, b)
    assert 0.0 <= iou <= 1.0
    assert iou == pytest.approx(box_iou(b, a), abs=1e-9)
    c, s = np.cos(turn), np.sin(turn)
    R = np.array([[c, -s], [s, c]])
    assert iou == pytest.approx(box_iou(a @ R.T, b @ R.T), abs=1e-9)


def test_disc_stand_ins_cover_the_box_length():
    centres, radii = disc_centres(torch.tensor([[[0.0, 0.0, 0.0]]]), torch.tensor([[4.6, 1.9]]))
    xs = centres[0, :, 0, 0]
    assert torch.allclose(xs, torch.tensor([-1.35, 0.0, 1.35])) and radii.item() == pytest.approx(0.95)
