"""NAVSIM v2's EPDMS beside PDMS on hand-made runs whose answers are known: each sub-score, the human-agent filter,
the formula, NAVSIM's TTC, and the extremes (empty runs, far agents, degenerate routes and lanes)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from omniscs.closedloop import epdms as e
from omniscs.closedloop.epdms import EPDMSConfig
from omniscs.closedloop.epdms import score_with_epdms as score_run
from omniscs.errors import ValidationError
from test_metrics import DT, Rectangle, agent_track, make_trace, straight, uniad_plans

LANE_Y = -1.75  # the ego's lane (eastbound, +x); the oncoming lane runs westbound at +1.75
LANES = (np.array([[-100.0, LANE_Y], [1000.0, LANE_Y]]), np.array([[1000.0, -LANE_Y], [-100.0, -LANE_Y]]))
ROUTE = np.array([[0.0, LANE_Y], [1000.0, LANE_Y]])


def lane_trace(ego, speed, tracks=(), **kw):
    """A run on a two-lane road (one lane per direction) whose route follows the eastbound lane."""
    kw.setdefault("route", ROUTE)
    kw.setdefault("lane_centrelines", LANES)
    return make_trace(ego, speed, tracks, **kw)


def at(ego, y):
    out = ego.copy()
    out[:, 1] = y
    return out


def epdms_of(trace, **config):
    return score_run(trace, config=EPDMSConfig(**config)).epdms


def assert_clean(scores):
    text = json.dumps(scores.to_dict(), allow_nan=False)  # raises on NaN / Inf
    assert "NaN" not in text and "Infinity" not in text


# ----------------------------------------------------------------------------- DDC
@pytest.mark.parametrize("speed, expected", [(5.0, 0.5), (10.0, 0.0), (1.0, 1.0)])
def test_driving_against_the_lane_direction_gives_ddc_by_the_distance_driven_over_one_second(speed, expected):
    # 11 increments of speed * 0.1 s in NAVSIM's trailing 1 s window: 5.5 m (>= 2, < 6), 11 m (>= 6), 1.1 m (< 2)
    ego, v = straight(speed, 41)
    s = epdms_of(lane_trace(at(ego, -LANE_Y), v))
    assert s.values["ddc"][0] == expected and s.policy["ddc"][0] == expected


def test_driving_with_the_lane_direction_in_either_lane_keeps_ddc_one():
    ego, v = straight(10.0, 41)
    assert np.all(epdms_of(lane_trace(at(ego, LANE_Y), v)).values["ddc"] == 1.0)
    westbound = at(ego, -LANE_Y)
    westbound[:, 0] = 500.0 - westbound[:, 0]
    westbound[:, 2] = np.pi
    assert np.all(epdms_of(lane_trace(westbound, v)).values["ddc"] == 1.0)


# ----------------------------------------------------------------------------- LK
def test_leaving_the_lane_centre_for_longer_than_the_window_zeroes_lk():
    ego, v = straight(10.0, 41)
    off = at(ego, LANE_Y + 0.8)  # 0.8 m from the centreline (> 0.5 m), still inside the lane
    s = epdms_of(lane_trace(off, v))
    assert s.lane_keeping_scored and s.values["lk"][0] == 0.0
    assert s.values["ddc"][0] == 1.0  # in its own lane: not oncoming
    # the last windows hold fewer than 20 poses: too short to fail
    assert s.values["lk"][21] == 0.0 and s.values["lk"][22] == 1.0 and s.values["lk"][-1] == 1.0


def test_a_deviation_shorter_than_the_window_or_within_the_limit_keeps_lk_one():
    ego, v = straight(10.0, 41)
    brief = at(ego, LANE_Y)
    brief[5:24, 1] = LANE_Y + 0.8  # 19 poses (1.9 s) beyond the limit: under 20
    assert np.all(epdms_of(lane_trace(brief, v)).values["lk"] == 1.0)
    brief[5:25, 1] = LANE_Y + 0.8  # 20 poses: fails every window that holds them all
    lk = epdms_of(lane_trace(brief, v)).values["lk"]
    assert lk[0] == 0.0 and lk[5] == 0.0 and lk[6] == 1.0
    assert np.all(epdms_of(lane_trace(at(ego, LANE_Y + 0.3), v)).values["lk"] == 1.0)


def test_without_a_lane_map_ddc_and_lk_are_one_and_the_report_says_so():
    ego, v = straight(10.0, 41)
    s = epdms_of(make_trace(at(ego, -LANE_Y), v))
    assert not s.has_lanes and not s.lane_keeping_scored
    assert np.all(s.values["ddc"] == 1.0) and np.all(s.values["lk"] == 1.0)
    assert e.NO_LANES_NOTE in s.to_dict()["notes"]


def test_lk_is_not_scored_when_no_lane_carries_the_route():
    ego, v = straight(10.0, 41)
    far_lanes = tuple(line + 5_000.0 for line in LANES)
    s = epdms_of(lane_trace(at(ego, LANE_Y + 0.8), v, lane_centrelines=far_lanes))
    assert s.has_lanes and not s.lane_keeping_scored and np.all(s.values["lk"] == 1.0)
    assert e.NO_ROUTE_LANE_NOTE in s.to_dict()["notes"]


# ----------------------------------------------------------------------------- HC, EC, TLC
def braking_run():
    """10 m/s, a brake at -8 m/s² from 1.0 s down to 4 m/s (0.75 s), then 4 m/s."""
    speed = np.array([10.0 if k < 10 else max(4.0, 10.0 - 8.0 * (k - 9) * DT) for k in range(61)])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * DT)])
    return np.stack([x, np.full(61, LANE_Y), np.zeros(61)], 1), speed


def test_a_hard_brake_fails_history_comfort_also_in_windows_that_start_after_it():
    ego, v = braking_run()
    scores = score_run(lane_trace(ego, v))
    s = scores.epdms
    assert s.values["hc"][0] == 0.0 and scores.comfort[0] == 0.0
    later = 25  # its window starts 1 s after the brake ended: PDMS's comfort passes, its 1.5 s history does not
    assert scores.comfort[later] == 1.0 and s.values["hc"][later] == 0.0
    assert s.values["hc"][45] == 1.0  # history 3.0 .. 4.5 s: smooth again
    smooth_ego, smooth_v = straight(10.0, 61)
    assert np.all(epdms_of(lane_trace(at(smooth_ego, LANE_Y), smooth_v)).values["hc"] == 1.0)


def test_plans_that_change_their_mind_every_half_second_fail_extended_comfort():
    ego, v = straight(10.0, 41)
    ego = at(ego, LANE_Y)
    steady = uniad_plans(ego, v)
    s = epdms_of(lane_trace(ego, v, plans=steady))
    assert np.all(s.values["ec"] == 1.0) and s.ec_compared[5:].all() and not s.ec_compared[:5].any()
    k = np.arange(1, 7) * 0.5
    jerky = [p if (t // 5) % 2 == 0 else np.stack([e_[0] + 10.0 * k - 0.5 * 4.0 * k ** 2, p[:, 1]], 1)
             for t, (p, e_) in enumerate(zip(steady, ego))]  # every other half second: a 4 m/s² brake planned
    s = epdms_of(lane_trace(ego, v, plans=jerky))
    assert s.values["ec"][5] == 0.0 and s.values["ec"][10] == 0.0 and s.values["ec"][0] == 1.0


def test_without_plans_ec_compares_nothing_and_is_one():
    ego, v = braking_run()
    s = epdms_of(lane_trace(ego, v))
    assert np.all(s.values["ec"] == 1.0) and not s.ec_compared.any()
    assert s.to_dict()["ec_compared_steps"] == 0


def test_tlc_is_one_because_the_world_has_no_traffic_lights():
    ego, v = straight(10.0, 41)
    s = epdms_of(lane_trace(at(ego, -LANE_Y), v))
    assert np.all(s.values["tlc"] == 1.0) and s.to_dict()["traffic_lights"] == e.TLC_NOTE


# ----------------------------------------------------------------------------- human-agent filter
def test_a_sub_score_the_logged_ego_also_fails_is_not_held_against_the_policy():
    ego, v = straight(10.0, 41)
    wrong_way = at(ego, -LANE_Y)
    both = epdms_of(lane_trace(wrong_way, v, reference_ego=wrong_way))
    assert both.policy["ddc"][0] == 0.0 and both.filtered["ddc"][0] and both.values["ddc"][0] == 1.0
    alone = epdms_of(lane_trace(wrong_way, v, reference_ego=at(ego, LANE_Y)))
    assert not alone.filtered["ddc"].any() and alone.values["ddc"][0] == 0.0
    none = epdms_of(lane_trace(wrong_way, v))
    assert not none.human_filter and none.values["ddc"][0] == 0.0


def test_the_filter_uses_the_logged_ego_over_the_same_window_for_the_drivable_area():
    ego, v = straight(10.0, 41)
    road = Rectangle(-100.0, 1000.0, -3.0, 3.0)
    offroad = at(ego, 4.0)
    scores = score_run(make_trace(offroad, v, drivable=road, reference_ego=offroad))
    assert scores.dac[0] == 0.0  # PDMS is unchanged by the filter
    assert scores.epdms.values["dac"][0] == 1.0 and scores.epdms.filtered["dac"].all()
    long_ego, long_v = straight(10.0, 61)
    logged_late = at(long_ego, 0.0)
    logged_late[50:, 1] = 4.0  # the log leaves the road at 5 s: only windows that reach 5 s are filtered
    s = epdms_of(make_trace(at(long_ego, 4.0), long_v, drivable=road, reference_ego=logged_late))
    assert not s.filtered["dac"][:10].any() and s.values["dac"][9] == 0.0
    assert s.filtered["dac"][10:].all() and np.all(s.values["dac"][10:] == 1.0)
    clean = epdms_of(make_trace(offroad, v, drivable=road, reference_ego=at(ego, 0.0)))
    assert np.all(clean.values["dac"] == 0.0)


def test_the_logged_ego_meets_the_logged_agents_not_the_run_s():
    steps = 41
    ego, v = straight(10.0, steps)
    parked = agent_track(20.0, 0.0, steps) + ("vehicle", (4.5, 2.0))
    gone = np.full((1, steps, 3), np.nan)  # in the log the car was not there
    trace = make_trace(ego, v, [parked], reference_ego=ego, reference_agents=parked[0][None])
    s = epdms_of(trace)
    assert s.policy["nc"][0] == 0.0 and s.filtered["nc"][0] and s.values["nc"][0] == 1.0
    empty_road = make_trace(ego, v, [parked], reference_ego=ego, reference_agents=gone)
    assert not epdms_of(empty_road).filtered["nc"].any()


# ----------------------------------------------------------------------------- the formula
def test_epdms_multiplies_the_multipliers_into_the_weighted_mean_of_the_rest():
    ego, v = straight(10.0, 41)
    s = epdms_of(lane_trace(at(ego, LANE_Y + 0.8), v))  # LK 0, everything else 1
    assert s.values["lk"][0] == 0.0 and s.epdms[0] == pytest.approx((5 + 5 + 0 + 2 + 2) / 16)
    ego5, v5 = straight(5.0, 41)
    s = epdms_of(lane_trace(at(ego5, -LANE_Y), v5))  # DDC 0.5 (5.5 m oncoming), LK 0 (far from the route's lane)
    assert s.values["ddc"][0] == 0.5 and s.values["lk"][0] == 0.0
    assert s.epdms[0] == pytest.approx(0.5 * 14 / 16)
    for t in range(len(s.epdms)):
        mult = np.prod([s.values[n][t] for n in e.MULTIPLIERS])
        w = EPDMSConfig().weights()
        assert s.epdms[t] == pytest.approx(mult * sum(w[n] * s.values[n][t] for n in e.WEIGHTED) / 16)
    assert s.epdms_mean == pytest.approx(np.mean(s.epdms))


def test_epdms_and_its_sub_scores_reach_to_dict_beside_an_unchanged_pdms():
    ego, v = straight(10.0, 41)
    d = score_run(lane_trace(at(ego, LANE_Y + 0.8), v)).to_dict()
    assert d["pdms"] == 1.0 and d["epdms"] == pytest.approx((22 * 14 / 16 + 19) / 41)  # LK 0 in steps 0 .. 21
    sub = d["epdms_scores"]
    assert sub["lk_min"] == 0.0 and sub["ttc_mode"] == "ours" and sub["has_lanes"]
    assert set(d["per_step"]) >= {"epdms", "ddc", "tlc", "lk", "hc", "ec", "epdms_nc", "epdms_ttc"}
    assert json.loads(json.dumps(d, allow_nan=False)) == d


# ----------------------------------------------------------------------------- NAVSIM's TTC
def test_navsim_ttc_checks_a_creeping_ego_that_ours_counts_as_stopped():
    steps = 21
    ego, v = straight(0.02, steps)  # 0.02 m/s: over NAVSIM's 0.005, under our 0.05
    oncoming = agent_track(9.25, -10.0, steps) + ("vehicle", (4.5, 2.0))  # reaches the ego's front at 0.5 s
    trace = make_trace(ego, v, [oncoming], reference=np.zeros(steps))
    ours, navsim = score_run(trace), score_run(trace, config=EPDMSConfig(ttc="navsim"))
    assert ours.epdms.values["ttc"][0] == 1.0 and navsim.epdms.values["ttc"][0] == 0.0
    assert np.array_equal(ours.ttc, navsim.ttc) and ours.pdms_mean == navsim.pdms_mean  # PDMS keeps its own TTC
    assert navsim.to_dict()["epdms_scores"]["ttc_mode"] == "navsim"


def test_navsim_ttc_looks_at_the_agents_recorded_positions_at_its_look_ahead_times():
    steps = 10
    ego, v = straight(10.0, steps)
    parked = agent_track(11.0, 0.0, steps) + ("vehicle", (4.5, 2.0))  # 6.5 m gap: reached at 0.9 s, not 0.6 s
    s = epdms_of(make_trace(ego, v, [parked]), ttc="navsim")
    assert s.values["ttc"][0] == 0.0
    assert np.all(s.values["ttc"][1:] == 1.0)  # later windows are too short for the 0.9 s look-ahead (NAVSIM)
    far = agent_track(16.0, 0.0, steps) + ("vehicle", (4.5, 2.0))  # 11.5 m: beyond 0.9 s at 10 m/s
    assert epdms_of(make_trace(ego, v, [far]), ttc="navsim").values["ttc"][0] == 1.0


def test_navsim_ttc_ignores_agents_already_touching_at_the_window_s_start():
    steps = 21
    ego, v = straight(10.0, steps)
    glued = agent_track(4.0, 10.0, steps) + ("vehicle", (4.5, 2.0))  # overlaps the ego's front throughout
    s_ours, s_navsim = epdms_of(make_trace(ego, v, [glued])), epdms_of(make_trace(ego, v, [glued]), ttc="navsim")
    assert s_ours.policy["ttc"][0] == 0.0 and s_navsim.policy["ttc"][0] == 1.0


# ----------------------------------------------------------------------------- extremes
def test_an_empty_run_scores_no_epdms_and_stays_plain_json():
    empty = make_trace(np.zeros((0, 3)), np.zeros(0), reference=np.zeros(0), reference_ego=np.zeros((0, 3)),
                       lane_centrelines=LANES)
    scores = score_run(empty, config=EPDMSConfig(ttc="navsim"))
    d = scores.to_dict()
    assert d["epdms"] is None and d["epdms_scores"]["lk_mean"] is None and d["per_step"]["epdms"] == []
    assert_clean(scores)


def test_far_agents_far_lanes_and_degenerate_routes_and_lanes_never_give_nan_or_inf():
    steps = 41
    ego, v = straight(10.0, steps, x0=1e4)
    far = agent_track(1e4, -30.0, steps, y=1e4) + ("vehicle", (4.5, 2.0))
    route = np.array([[0.0, 0.0], [0.0, 0.0], [2e4, 0.0], [2e4, 0.0]])  # zero-length segments at both ends
    lanes = (np.array([[0.0, 0.0], [0.0, 0.0], [2e4, 0.0]]),  # a zero-length segment
             np.array([[5.0, 5.0], [5.0, 5.0]]),              # no length at all: ignored
             np.array([[1e7, 1e7], [1e7 + 1.0, 1e7]]))        # 10 000 km away
    for mode in ("ours", "navsim"):
        scores = score_run(make_trace(ego, v, [far], route=route, lane_centrelines=lanes, reference_ego=ego,
                                      reference_agents=far[0][None], plans=uniad_plans(ego, v)),
                           config=EPDMSConfig(ttc=mode))
        s = scores.epdms
        assert_clean(scores)
        assert np.all(np.isfinite(s.epdms)) and s.epdms.min() == pytest.approx(1.0) and s.lane_keeping_scored
    huge, hv = straight(1e6, 21, x0=1e7)
    scores = score_run(make_trace(huge, hv, plans=uniad_plans(huge, hv), lane_centrelines=LANES,
                                  reference_ego=huge, drivable=Rectangle(-1e12, 1e12, -10.0, 10.0)),
                       config=EPDMSConfig(ttc="navsim"))
    assert_clean(scores)
    assert np.all(np.isfinite(scores.epdms.epdms))


def test_bad_configs_and_references_raise_one_domain_error():
    with pytest.raises(ValidationError, match="TTC mode"):
        EPDMSConfig(ttc="carla")
    with pytest.raises(ValidationError, match="human_filter"):
        EPDMSConfig(human_filter=("nc", "comfort"))
    with pytest.raises(ValidationError):
        EPDMSConfig(lane_keeping_window_s=0.0)
    ego, v = straight(10.0, 5)
    with pytest.raises(ValidationError, match="reference_ego"):
        make_trace(ego, v, reference_ego=ego[:-1])
    with pytest.raises(ValidationError, match="reference_agents"):
        make_trace(ego, v, reference_agents=np.zeros((2, 5, 3)))
    with pytest.raises(ValidationError, match="lane_centrelines"):
        make_trace(ego, v, lane_centrelines=(np.array([[0.0, np.nan], [1.0, 0.0]]),))


def test_track_velocity_differences_forward_then_backward_where_the_next_step_is_absent():
    poses = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [np.nan] * 3]])
    vel = e.track_velocity(poses, 0.1)
    assert vel[0, :3, 0] == pytest.approx([10.0, 20.0, 20.0]) and np.isnan(vel[0, 3]).all()
    assert e.path_speed(poses[0, :3], 0.1) == pytest.approx([10.0, 15.0, 20.0])


# ----------------------------------------------------------------------------- catalog
def test_closed_loop_runs_written_before_epdms_still_read_with_a_null_epdms(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from omniscs import catalog

    row = dict(eval_id="cl-1", scenario_id="s/log", scene_id="s", kind="log", model_id="m", policy="rule",
               reactive=False, status="ok", pdms=0.9, hd_score=0.5)
    catalog.write_rows(tmp_path, "runs", "old", [dict(flow="closed_loop_eval", status="completed", started_at_us=0,
                                                      finished_at_us=1, n_scenes=1, config_json="{}",
                                                      omniscs_version="test")], writer="run")
    old_schema = pa.schema([f for f in catalog.SCHEMAS["closed_loop_runs"] if f.name != "epdms"])
    folder = tmp_path / "closed_loop_runs" / "run_id=old"
    folder.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist([row], schema=old_schema),
                   folder / "task-0000000000000001-000000000001.parquet")
    catalog.write_rows(tmp_path, "closed_loop_runs", "new", [dict(row, eval_id="cl-2", epdms=0.8)])
    got = catalog.query(tmp_path, "SELECT eval_id, pdms, epdms FROM closed_loop_runs_raw ORDER BY eval_id").to_pylist()
    assert got == [{"eval_id": "cl-1", "pdms": 0.9, "epdms": None}, {"eval_id": "cl-2", "pdms": 0.9, "epdms": 0.8}]


# ----------------------------------------------------------------------------- closed-loop runs
def test_a_run_scores_epdms_with_the_log_as_human_reference_and_a_variant_without_one(world, tmp_path):
    from closedloop_fixtures import stopping_variant
    from omniscs.closedloop.policies import make_policy
    from omniscs.closedloop.run import RUN_JSON, STEPS_JSON, run_episode
    from omniscs.closedloop.scenario import variant_scenario
    from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator

    scene, graph, log = world
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",)))
    replay = run_episode(sim, make_policy("replay"), log, out_dir=tmp_path / "log")
    assert replay.trace.reference_ego is not None and len(replay.trace.lane_centrelines) > 0
    s = replay.scores.epdms
    assert s.has_lanes and s.human_filter and s.epdms_mean == pytest.approx(1.0, abs=0.02)
    summary = json.loads((replay.folder / RUN_JSON).read_text())
    assert summary["scores"]["epdms"] == pytest.approx(s.epdms_mean)
    assert "epdms" in json.loads((replay.folder / STEPS_JSON).read_text())[0]
    hit = run_episode(sim, make_policy("replay"), variant_scenario(scene, stopping_variant(scene), log))
    assert hit.trace.reference_ego is None and not hit.scores.epdms.human_filter  # a synthetic world: no filter
    assert hit.scores.epdms.values["nc"].min() == 0.0 and hit.scores.epdms.epdms_mean < 0.5
