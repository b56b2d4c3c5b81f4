"""The feasibility search behind the behaviour benchmark's denominator: it finds comfortable collisions that exist,
rules out agents that cannot get there (soundly), stays finite far away, and the benchmark counts scenes with it."""
import numpy as np
import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.pipeline.procedural import traffic_from_world
from omniscs.scs.behavior.adversarial_config import adversarial_preset
from omniscs.scs.behavior.checkpoint import load_traffic_model
from omniscs.scs.behavior.collision import box_iou, footprints
from omniscs.scs.behavior.feasibility import (FeasibilityConfig, comfort_kinematics, out_of_reach, search_reach,
                                              search_scene)
from omniscs.scs.behavior.kinematics import accelerations, bound_controls, rollout, soft_clip_accel
from omniscs.scs.behavior.problem import BehaviorProblem
from tests.behavior_fixtures import straight_world

FAST = adversarial_preset("fast")
SEARCH = FeasibilityConfig(starts=64, steps=200)


@pytest.fixture(scope="module")
def model():
    return load_traffic_model()


def _problem(model, agents, ego_speed=8.0):
    return BehaviorProblem(traffic_from_world(straight_world(agents, ego_speed=ego_speed)), model, FAST)


def _node(problem, track_id):
    return next(k for k in range(1, problem.n_nodes)
                if int(problem.traffic.track_ids[int(problem.node_tracks[k])]) == track_id)


def test_a_car_in_the_next_lane_can_reach_the_ego_comfortably(model):
    p = _problem(model, [{"x": 6.0, "y": 3.3, "speed": 8.0}])
    r = search_reach(p, _node(p, 1), config=SEARCH)
    assert r.searched and r.feasible and r.best_iou > 0.02 and r.best_gap_m < 0
    plan = p.plan(p.fitted.states.numpy().astype(np.float64))
    ego = footprints(plan[:, :2], plan[:, 2], *p.ego_size)
    adv = footprints(r.states[:, :2], r.states[:, 2], *p.node_sizes[r.node].numpy())
    assert box_iou(ego, adv).max() == pytest.approx(r.best_iou)  # the reported trajectory is the one measured
    lon, lat = accelerations(p.sample.state0[r.node].double(), torch.tensor(r.states), p.traffic.dt)
    cb = p.config.comfort
    assert lon.max() <= cb.max_lon_accel and lon.min() >= cb.min_lon_accel
    assert lat.abs().max() <= cb.max_abs_lat_accel and np.abs(r.states[:, 4]).max() <= cb.max_abs_yaw_rate


def test_a_parked_car_reaches_a_standing_ego_only_when_it_faces_it(model):
    p = _problem(model, [{"x": 14.0, "y": 3.3, "yaw": np.pi, "speed": 0.0},  # facing the ego: pulls out into it
                         {"x": 8.0, "y": 3.3, "yaw": 0.0, "speed": 0.0}],    # facing away: would have to reverse
                 ego_speed=0.0)
    toward, away = (search_reach(p, _node(p, t), config=SEARCH) for t in (1, 2))
    assert toward.feasible and toward.searched
    assert not away.feasible and away.searched and away.best_iou == 0.0 and away.best_gap_m > 0


def test_far_agents_are_ruled_out_without_a_search_and_stay_finite(model):
    p = _problem(model, [{"x": 500.0, "y": 3.3, "speed": 9.0}, {"x": 10_000.0, "y": 6.6, "speed": 9.0},
                         {"x": 10.0, "y": 3.3, "speed": 8.0}])
    reaches = search_scene(p, SEARCH)
    by_track = {int(p.traffic.track_ids[r.track]): r for r in reaches}
    for far in (1, 2):
        assert not by_track[far].searched and not by_track[far].feasible and by_track[far].states is None
    assert by_track[3].feasible
    for r in reaches:
        assert np.isfinite(r.best_iou) and (r.states is None or np.isfinite(r.states).all())


def test_the_reach_ball_is_sound_for_any_comfortable_controls(model):
    p = _problem(model, [{"x": 20.0, "y": 3.3, "speed": 12.0}])
    node = _node(p, 1)
    lim, cb = comfort_kinematics(p), p.config.comfort
    state0 = p.sample.state0[node]
    gen = torch.Generator().manual_seed(3)
    raw = torch.randn(512, p.horizon, 2, generator=gen) * 3.0
    raw[:, :, 0] = raw[:, :, 0].abs() + 5.0  # flat out: the farthest any trajectory gets
    c = bound_controls(raw, lim)
    c = torch.stack([soft_clip_accel(c[..., 0], cb.max_lon_accel, -cb.min_lon_accel), c[..., 1]], -1)
    states = rollout(state0.expand(512, 5), c, p.traffic.dt, lim).numpy()
    travelled = np.linalg.norm(states[..., :2] - state0[:2].numpy(), axis=-1).max(0)  # [T]
    t = np.arange(1, p.horizon + 1) * p.traffic.dt
    v0 = float(state0[3])
    assert np.all(travelled <= v0 * t + 0.5 * cb.max_lon_accel * t ** 2 + 1e-3)
    assert travelled[-1] > v0 * t[-1] + 0.4 * cb.max_lon_accel * t[-1] ** 2  # and not loose: flat out gets close
    # a plan always one metre beyond the ball (plus both half diagonals) is out of reach; 2 m inside is not
    size = tuple(float(x) for x in p.node_sizes[node])
    radius = 0.5 * (np.hypot(*size) + np.hypot(*p.ego_size))
    yaw0 = float(state0[2])
    for extra, expected in ((1.0, True), (-2.0, False)):
        d = v0 * t + 0.5 * cb.max_lon_accel * t ** 2 + radius + extra
        plan = np.stack([float(state0[0]) + d * np.cos(yaw0), float(state0[1]) + d * np.sin(yaw0),
                         np.full_like(t, yaw0)], -1)
        assert out_of_reach(state0.numpy().astype(np.float64), size, plan, p.ego_size, p.traffic.dt,
                            cb.max_lon_accel, lim.max_speed) is expected


def test_the_search_is_deterministic_per_seed_and_rejects_bad_input(model):
    p = _problem(model, [{"x": 6.0, "y": 3.3, "speed": 8.0}])
    node = _node(p, 1)
    a, b = (search_reach(p, node, config=FeasibilityConfig(starts=16, steps=50, seed=4)) for _ in range(2))
    assert a.best_iou == b.best_iou and np.array_equal(a.states, b.states)
    with pytest.raises(OmniscsError, match="not a non-ego node"):
        search_reach(p, 0)
    with pytest.raises(OmniscsError, match="not a non-ego node"):
        search_reach(p, p.n_nodes)
    with pytest.raises(OmniscsError, match="starts"):
        search_reach(p, node, config=FeasibilityConfig(starts=0))
