"""The closed-loop simulator in a fitted scene graph of a small procedural log (ego at 6 m/s, a car 11 m ahead
keeping pace, one overtaking in the next lane): tracking, rendering, endings, refusals, the policies, the gymnasium
environment and the run folder."""
from __future__ import annotations

import json
import logging

import gymnasium
import numpy as np
import pytest
from PIL import Image

from closedloop_fixtures import N_FRAMES, stopping_variant
from omniscs.closedloop.env import ENV_ID
from omniscs.closedloop.policies import ProxyPolicy, make_policy
from omniscs.closedloop.run import BEV_PNG, FRAMES_PNG, REPLAY_GIF, RUN_JSON, STEPS_JSON, run_episode
from omniscs.closedloop.scenario import variant_scenario
from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator
from omniscs.closedloop.vehicle import Controls
from omniscs.errors import OmniscsError, ValidationError




def test_replaying_the_log_tracks_the_logged_ego_exactly_and_scores_full_marks(world):
    scene, graph, log = world
    sim = Simulator(graph, scene)
    result = run_episode(sim, make_policy("replay"), log)
    ego = np.array(sim.episode.ego)
    assert np.abs(ego - log.ego[:len(ego)]).max() < 0.02
    assert result.summary["reason"] in ("route_completed", "scenario_end")
    assert result.scores.pdms_mean == pytest.approx(1.0, abs=0.01) and not result.scores.any_collision
    assert result.scores.route_completion > 0.98


def test_an_observation_holds_every_camera_output_and_labels_the_car_ahead(world):
    scene, graph, log = world
    sim = Simulator(graph, scene)
    obs = sim.reset(log).observation
    cam = graph.cameras[0]
    assert obs.rgb[cam.name].shape == (cam.height, cam.width, 3) and obs.rgb[cam.name].dtype == np.uint8
    depth = obs.depth[cam.name]
    assert np.isfinite(depth).all() and (depth >= 0).all() and (depth > 0).mean() > 0.3
    assert 1 in set(np.unique(obs.instance[cam.name]))  # the car 11 m ahead
    assert set(np.unique(obs.instance[cam.name])) <= {-1, 1, 2}


def test_renders_follow_the_simulated_ego_not_the_log(world):
    scene, graph, log = world
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",), stop_on_collision=False))
    first = sim.reset(log).observation.rgb[graph.cameras[0].name].astype(float)
    for _ in range(8):
        res = sim.step(Controls(-8.0, 0.0))  # brake: the log drives on, the ego stops
    stopped = sim.ego_centre()[0]
    assert stopped < log.ego[8, 0] - 2.0
    assert res.info["ego_velo"] == 0.0 and res.info["timestamp"] == pytest.approx(0.8)
    moved = res.observation.rgb[graph.cameras[0].name].astype(float)
    assert np.abs(moved - first).mean() > 1.0  # the car ahead has pulled away in the image


def test_a_nan_or_absurd_plan_is_refused_and_the_episode_does_not_advance(world):
    scene, graph, log = world
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",)))
    sim.reset(log)
    for bad in (np.full((6, 2), np.nan), np.array([[0.0, 1e4]] * 6), np.zeros((6,)), [["a", "b"]],
                np.array([[0.0, 100.0]] * 6)):  # 100 m in 0.5 s: 200 m/s
        with pytest.raises(ValidationError):
            sim.step(bad)
    assert sim.episode.step == 0 and sim.episode.t == 0.0


def test_driving_out_of_the_fitted_area_ends_the_episode_with_a_warning(world, caplog):
    scene, graph, log = world
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",), max_offset_m=1.5, stop_on_collision=False))
    sim.reset(log)
    with caplog.at_level(logging.WARNING):
        for _ in range(N_FRAMES):
            res = sim.step(Controls(0.0, 1.0))  # full left lock
            if res.done:
                break
    assert res.done and res.reason == "left_fitted_area" and res.info["fitted_area_offset_m"] > 1.5
    assert "seen nothing there" in caplog.text
    assert res.observation is not None  # the last picture inside the area
    with pytest.raises(OmniscsError, match="reset"):
        sim.step(Controls(0.0, 0.0))


def test_replay_drives_into_a_car_that_stops_ahead_while_the_rule_policy_stops_behind_it(world):
    scene, graph, log = world
    sc = variant_scenario(scene, stopping_variant(scene), log)
    assert sc.kind == "behavior" and sc.adversary == 1
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",)))
    hit = run_episode(sim, make_policy("replay"), sc)
    assert hit.summary["reason"] == "collision" and hit.summary["collided_with"] == [1]
    assert hit.scores.pdms_mean < 0.5 and min(hit.scores.nc) == 0.0
    safe = run_episode(sim, make_policy("rule"), sc)
    assert not safe.scores.any_collision and safe.summary["reason"] != "collision"
    assert sim.episode.state.speed < 3.0  # it braked
    assert safe.scores.pdms_mean > hit.scores.pdms_mean


def test_the_proxy_planner_drives_the_log_without_collision(world):
    scene, graph, log = world
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",)))
    policy = ProxyPolicy()
    sim.reset(log)
    plan = policy.act(sim)
    assert plan.shape == (6, 2) and np.isfinite(plan).all()
    result = run_episode(sim, policy, log)
    assert not result.scores.any_collision and result.scores.route_completion > 0.8


def test_the_gymnasium_environment_steps_plans_and_controls_and_scores_at_the_end(world):
    scene, graph, log = world
    env = gymnasium.make(ENV_ID, graph=graph, scene=scene, scenario=log,
                         config=ClosedLoopConfig(outputs=("rgb", "depth")))
    obs, info = env.reset()
    cam = graph.cameras[0].name
    assert obs["rgb"][cam].shape == env.observation_space["rgb"][cam].shape
    assert set(info) >= {"ego_pos", "ego_box", "obj_boxes", "cam_params", "command", "rc", "collision"}
    obs, reward, terminated, truncated, info = env.step({"accel": 0.0, "steer_rate": 0.0})
    assert reward > 0.3  # 6 m/s for 0.1 s along the route
    replay = make_policy("replay")
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(replay.act(env.unwrapped.sim))
    assert "scores" in info and info["scores"]["pdms"] is not None
    assert json.dumps(info["scores"], allow_nan=False)


def test_a_run_folder_holds_its_scores_steps_and_pictures(world, tmp_path):
    scene, graph, log = world
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",)))
    result = run_episode(sim, make_policy("rule"), log, max_steps=8, out_dir=tmp_path / "run")
    folder = result.folder
    summary = json.loads((folder / RUN_JSON).read_text())
    assert summary["steps"] == 8 and summary["reason"] == "max_steps" and summary["policy"] == "rule"
    steps = json.loads((folder / STEPS_JSON).read_text())
    assert len(steps) == 9 and steps[0]["t"] == 0.0 and steps[-1]["t"] == pytest.approx(0.8)
    bev = Image.open(folder / BEV_PNG)
    assert bev.size[0] > 300
    assert Image.open(folder / FRAMES_PNG).size[0] >= graph.cameras[0].width
    gif = Image.open(folder / REPLAY_GIF)
    assert gif.n_frames == 9
    with pytest.raises(OmniscsError):
        run_episode(sim, make_policy("rule"), log, max_steps=2, out_dir=tmp_path / "run")  # no silent overwrite


def test_a_run_folder_keeps_every_steps_agent_boxes_contacts_and_camera_frame(world, tmp_path):
    from omniscs.closedloop.run import FRAMES_DIR, REPLAY_JSON
    from omniscs.closedloop.simulator import agent_heights

    scene, graph, log = world
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",)))
    sc = variant_scenario(scene, stopping_variant(scene), log)
    run_episode(sim, make_policy("replay"), sc, out_dir=tmp_path / "run")  # drives into the stopped car
    ep = sim.episode
    replay = json.loads((tmp_path / "run" / REPLAY_JSON).read_text())
    steps = json.loads((tmp_path / "run" / STEPS_JSON).read_text())
    assert len(replay["agents"]) == len(replay["frames"]) == len(replay["contacts"]) == len(steps) == ep.step + 1
    tracks = replay["tracks"]
    assert [t["track_id"] for t in tracks] == [int(t) for t in sc.track_ids]
    for k, rows in enumerate(replay["agents"]):
        present = np.flatnonzero(np.isfinite(ep.agents[k]).all(1))
        assert [r[0] for r in rows] == list(present)
        got = np.array(rows, float).reshape(-1, 5)
        np.testing.assert_allclose(got[:, [1, 2, 4]], ep.agents[k][present], atol=1e-4)
        np.testing.assert_allclose(got[:, 3], agent_heights(sc, k)[present], atol=1e-4)
        assert bool(replay["contacts"][k]) == steps[k]["collision"]
    assert replay["contacts"][-1] == [1] and not any(replay["contacts"][:-1])  # the stopped car, at the end only
    assert replay["camera"] == graph.cameras[0].name and replay["frame_size"] == [graph.cameras[0].width,
                                                                                 graph.cameras[0].height]
    files = sorted((tmp_path / "run" / FRAMES_DIR).iterdir())
    assert [f"{FRAMES_DIR}/{f.name}" for f in files] == replay["frames"]
    last = np.asarray(Image.open(files[-1]).convert("RGB"), float)
    seen = ep.last_observation.rgb[graph.cameras[0].name].astype(float)
    assert last.shape == seen.shape and np.abs(last - seen).mean() < 4.0  # the JPEG of what the policy saw last


def test_unknown_policies_cameras_and_sizes_are_refused(world):
    scene, graph, log = world
    for spec in ("greedy", "ftp://x", ""):
        with pytest.raises(ValidationError):
            make_policy(spec)
    with pytest.raises(ValidationError):
        Simulator(graph, scene, ClosedLoopConfig(cameras=("CAM_NOPE",)))
    with pytest.raises(ValidationError):
        ClosedLoopConfig(width=4)
    with pytest.raises(ValidationError):
        ClosedLoopConfig(outputs=("lidar",))
