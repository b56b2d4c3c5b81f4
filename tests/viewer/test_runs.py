"""A closed-loop run folder in the viewer: each step's boxes as the simulator had them, the agent the ego hit red
from the contact on, the frames the policy saw, the scores; older folders show the ego's path; damaged ones are one
error."""
from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from PIL import Image

from omniscs.errors import OmniscsError
from omniscs.viewer.runs import CONTACT_COLOUR, EGO_TRACK, ClosedLoopRunTarget
from omniscs.viewer.state import category_colour
from omniscs.viewer.targets import open_target

#: The car ahead (track 1) jumps back onto the ego at this step, then drives on: the contact lasts one step.
CONTACT_STEP = 2


@pytest.fixture(scope="module")
def run(fitted, tmp_path_factory):
    """(run folder, simulator after the run, its scenario): the log of the viewer's scene with the car ahead put on
    the ego at CONTACT_STEP, driven through (no stop on collision) by the replay policy."""
    from omniscs.closedloop.policies import make_policy
    from omniscs.closedloop.run import run_episode
    from omniscs.closedloop.scenario import log_scenario
    from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator

    scene, graph = fitted
    log = log_scenario(scene)
    agents = log.agents.copy()
    ahead = int(np.flatnonzero(log.track_ids == 1)[0])
    agents[ahead, CONTACT_STEP, :2] = log.ego[CONTACT_STEP, :2] + [1.0, 0.0]
    scenario = dataclasses.replace(log, agents=agents)
    sim = Simulator(graph, scene, ClosedLoopConfig(outputs=("rgb",), stop_on_collision=False))
    folder = tmp_path_factory.mktemp("viewer-run") / "run"
    run_episode(sim, make_policy("replay"), scenario, out_dir=folder)
    return folder, sim, scenario


def test_a_run_folder_opens_as_a_closed_loop_run_with_one_frame_per_step(run):
    folder, sim, _ = run
    target = open_target(folder)
    assert isinstance(target, ClosedLoopRunTarget) and not target.editable
    assert target.n_frames == sim.episode.step + 1 == 4
    assert target.camera_names == [sim.rig[0].name]
    summary = target.summary()
    scores = json.loads((folder / "run.json").read_text())["scores"]
    epdms = scores["epdms_scores"]
    assert f"| PDMS | {scores['pdms']:.3f} | NC {scores['nc_mean']:.2f} / {scores['nc_min']:.2f}, " in summary
    assert f"| EPDMS | {scores['epdms']:.3f} | NC {epdms['nc_mean']:.2f} / {epdms['nc_min']:.2f}, " in summary
    assert scores["nc_min"] == 0.0 and "touched 1 (red)" in summary


def test_each_steps_boxes_are_the_simulators_agents_and_ego_at_that_step(run):
    from omniscs.closedloop.simulator import agent_heights
    from omniscs.geometry import yaw_from_matrix

    folder, sim, scenario = run
    target = open_target(folder)
    ep = sim.episode
    for k in range(target.n_frames):
        state = target.frame_state(k)
        ego_box = next(b for b in state.boxes if b.track_id == EGO_TRACK)
        np.testing.assert_allclose(ego_box.world_from_box[:2, 3], ep.ego[k][:2], atol=1e-9)
        boxes = {b.track_id: b for b in state.boxes if b.track_id != EGO_TRACK}
        present = np.flatnonzero(np.isfinite(ep.agents[k]).all(1))
        assert sorted(boxes) == sorted(int(scenario.track_ids[i]) for i in present)
        z = agent_heights(scenario, k)
        for i in present:
            box = boxes[int(scenario.track_ids[i])]
            np.testing.assert_allclose(box.world_from_box[:3, 3], [*ep.agents[k][i, :2], z[i]], atol=1e-4)
            assert yaw_from_matrix(box.world_from_box[:3, :3]) == pytest.approx(ep.agents[k][i, 2], abs=1e-4)
            np.testing.assert_array_equal(box.size, scenario.sizes[i])
    last = {b["track_id"]: b for b in sim.boxes()}  # what the simulator itself reports at the last step
    for box in target.frame_state(target.n_frames - 1).boxes:
        if box.track_id != EGO_TRACK:
            np.testing.assert_allclose(box.world_from_box[:3, 3], last[box.track_id]["center"], atol=1e-4)
    np.testing.assert_allclose(target.frame_state(ep.step).world_from_ego, sim.world_from_ego(), atol=1e-4)


def test_the_agent_the_ego_hit_is_red_from_the_contact_on_and_the_others_keep_their_colour(run):
    folder, sim, _ = run
    target = open_target(folder)
    assert [bool(c) for c in sim.episode.contacts] == [k == CONTACT_STEP for k in range(4)]
    for k in range(target.n_frames):
        boxes = {b.track_id: b for b in target.frame_state(k).boxes}
        assert boxes[1].colour == (CONTACT_COLOUR if k >= CONTACT_STEP else category_colour("car"))
        assert (boxes[EGO_TRACK].colour == CONTACT_COLOUR) == (k == CONTACT_STEP)
        if 2 in boxes:
            assert boxes[2].colour == category_colour("car")
    assert "collision yes (track 1)" in target.step_summary(CONTACT_STEP)
    assert "collision no" in target.step_summary(CONTACT_STEP + 1)


def test_the_camera_view_at_a_step_is_the_frame_the_policy_saw(run):
    folder, sim, _ = run
    target = open_target(folder)
    camera = target.camera_names[0]
    for k in range(target.n_frames):
        saved = np.asarray(Image.open(folder / "frames" / f"{k:06d}.jpg").convert("RGB"))
        np.testing.assert_array_equal(target.camera_image(camera, k, boxes=False), saved)
    seen = sim.episode.last_observation.rgb[camera].astype(float)
    assert np.abs(target.camera_image(camera, 3, boxes=False).astype(float) - seen).mean() < 4.0
    drawn = target.camera_image(camera, 0, boxes=True)  # the car ahead's box projected onto the frame
    assert drawn.shape == seen.shape and (drawn != target.camera_image(camera, 0, boxes=False)).any()


def test_the_paths_are_the_driven_ego_the_reference_and_each_agents(run):
    folder, sim, scenario = run
    paths = open_target(folder).trajectories()
    ego = next(t for t in paths if t.category == "ego")
    np.testing.assert_allclose(ego.positions[:, :2], np.array(sim.episode.ego)[:, :2], atol=1e-9)
    reference = next(t for t in paths if t.category == "reference")
    np.testing.assert_allclose(reference.positions[:, :2], scenario.ego[:, :2], atol=1e-4)
    assert {t.track_id for t in paths if t.track_id is not None} == {int(t) for t in scenario.track_ids}


def test_a_run_folder_written_before_replays_were_kept_opens_with_the_ego_path(run, tmp_path):
    folder, sim, _ = run
    old = tmp_path / "old-run"
    shutil.copytree(folder, old)
    (old / "replay.json").unlink()
    shutil.rmtree(old / "frames")
    target = open_target(old)
    state = target.frame_state(2)
    assert state.boxes == () and state.frustums == ()
    np.testing.assert_allclose(state.world_from_ego[:2, 3], sim.episode.ego[2][:2], atol=1e-9)
    ego = target.trajectories()[0]
    np.testing.assert_allclose(ego.positions[:, :2], np.array(sim.episode.ego)[:, :2], atol=1e-9)
    notice = target.camera_image(target.camera_names[0], 1, boxes=True)
    assert notice.ndim == 3 and notice.dtype == np.uint8
    assert "kept no camera frames" in target.step_summary(1) and "ego's path only" in target.summary()


@pytest.mark.parametrize("damage", ["missing", "not json", "not a list", "a step without x"])
def test_a_run_folder_with_missing_or_damaged_steps_is_one_error(run, tmp_path, damage):
    folder, _, _ = run
    bad = tmp_path / "bad-run"
    shutil.copytree(folder, bad)
    steps = bad / "steps.json"
    if damage == "missing":
        steps.unlink()
    elif damage == "not json":
        steps.write_text('[{"step": 0, "x": ')
    elif damage == "not a list":
        steps.write_text('{"x": 1}')
    else:
        rows = json.loads(steps.read_text())
        del rows[1]["x"]
        steps.write_text(json.dumps(rows))
    with pytest.raises(OmniscsError, match="steps.json") as caught:
        open_target(bad)
    assert len(str(caught.value).splitlines()) == 1 and "omniscs closedloop run" in str(caught.value)


def test_a_damaged_replay_or_a_scene_option_is_one_error(run, tmp_path):
    folder, _, _ = run
    bad = tmp_path / "bad-replay"
    shutil.copytree(folder, bad)
    record = json.loads((bad / "replay.json").read_text())
    record["frames"][0] = "../../etc/passwd"
    (bad / "replay.json").write_text(json.dumps(record))
    with pytest.raises(OmniscsError, match="outside the run folder"):
        open_target(bad)
    record["frames"] = record["frames"][:2]
    (bad / "replay.json").write_text(json.dumps(record))
    with pytest.raises(OmniscsError, match="one per step"):
        open_target(bad)
    with pytest.raises(OmniscsError, match="closed-loop run"):
        open_target(folder, scene=folder)
