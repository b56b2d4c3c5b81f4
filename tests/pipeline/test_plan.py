"""The scene plan models only what a scene requires."""
import pytest

from omniscs.edits import parse_edits
from omniscs.errors import OmniscsError
from omniscs.edits import ReplaceModel
from omniscs.plan import UNCOVERED_MARGIN_M, PlanConfig, ScenePlan, make_plan, uncovered_margin
from omniscs.scene import load_scene
from tests.conftest import write_tiny_scene


@pytest.fixture
def scene(tmp_path):
    # track 0 static, track 1 moves 3.5 m, track 2 moves 7 m over 8 frames
    return load_scene(write_tiny_scene(tmp_path / "s", n_frames=8, n_tracks=3))


def test_only_moving_tracks_become_nodes_without_edits(scene):
    plan = make_plan(scene)
    assert plan.agent_nodes == (1, 2) and plan.background_tracks == (0,)
    assert plan.node_reasons == {1: "moving", 2: "moving"}
    assert not plan.stages["agent_models"] and not plan.stages["background_repair"]


def test_an_edited_static_track_becomes_a_node_and_a_large_turn_needs_a_360_model(scene):
    plan = make_plan(scene, parse_edits('[{"op": "rotate", "track_id": 0, "yaw_deg": 180},'
                                        ' {"op": "translate", "track_id": 1, "lateral": 2.0}]'))
    assert plan.agent_nodes == (0, 1, 2) and plan.background_tracks == ()
    assert plan.node_reasons[0] == "edited" and plan.node_reasons[1] == "moving+edited"
    assert plan.needs_360 == (0,) and plan.stages["agent_models"]


def test_small_turns_need_no_360_model(scene):
    plan = make_plan(scene, parse_edits('[{"op": "rotate", "track_id": 0, "yaw_deg": 20}]'))
    assert plan.needs_360 == ()


def test_moving_a_large_static_object_asks_for_background_repair(scene):
    small = make_plan(scene, parse_edits('[{"op": "remove", "track_id": 0}]'))
    assert small.background_repair == ()  # a 4.5 x 1.9 x 1.6 m car is under the volume threshold
    big = make_plan(scene, parse_edits('[{"op": "remove", "track_id": 0}]'), PlanConfig(large_object_volume_m3=10.0))
    assert big.background_repair == (0,) and big.stages["background_repair"]


def _replace(track: int, size) -> list:
    return [ReplaceModel(track, "pm-other", size=None if size is None else tuple(size))]


def test_replacing_a_large_static_object_by_a_smaller_one_asks_for_background_repair(scene):
    big = PlanConfig(large_object_volume_m3=10.0)  # track 0: a static 4.5 x 1.9 x 1.6 m car
    shrunk = make_plan(scene, _replace(0, (3.0, 1.5, 1.2)), big)
    assert shrunk.background_repair == (0,) and shrunk.stages["background_repair"]
    # an object whose box covers the old one (larger, scaled to the old box, or smaller by less than the margin on
    # every side) uncovers nothing
    for size in ((5.0, 2.0, 1.8), None, (4.2, 1.8, 1.5)):
        covered = make_plan(scene, _replace(0, size), big)
        assert covered.background_repair == () and not covered.stages["background_repair"], size
    # a smaller object uncovers one side only: longer and wider but lower still leaves the top of the old box empty
    assert make_plan(scene, _replace(0, (6.0, 2.5, 1.0)), big).background_repair == (0,)
    # under the volume threshold, or moving (the background behind it was seen): no repair
    assert make_plan(scene, _replace(0, (3.0, 1.5, 1.2))).background_repair == ()
    assert make_plan(scene, _replace(1, (1.0, 1.0, 1.0)), PlanConfig(large_object_volume_m3=0.1)).background_repair \
        == ()


def test_the_uncovered_margin_is_the_old_boxs_worst_overhang():
    old = (13.0, 2.5, 4.0)  # a trailer replaced by a sedan resting on the same ground, centred where it stood
    assert uncovered_margin(old, ReplaceModel(1, "pm", size=(4.6, 1.9, 1.5))) == pytest.approx(4.2)
    assert uncovered_margin(old, ReplaceModel(1, "pm", size=(13.0, 2.5, 3.0))) == pytest.approx(1.0)  # the top
    assert uncovered_margin(old, ReplaceModel(1, "pm", size=(14.0, 3.0, 4.5))) == 0.0
    assert uncovered_margin(old, ReplaceModel(1, "pm")) == 0.0  # scaled to the old box
    assert 0 < UNCOVERED_MARGIN_M < 0.5


def test_every_fourth_frame_is_held_out(scene):
    plan = make_plan(scene)
    assert plan.heldout_frames == (3, 7) and plan.train_frames == (0, 1, 2, 4, 5, 6)
    assert make_plan(scene, config=PlanConfig(holdout_every=0)).heldout_frames == ()


def test_budget_grows_with_nodes_and_stays_within_bounds(scene):
    cfg = PlanConfig(min_gaussians=1, max_gaussians=10**9)
    base = make_plan(scene, config=cfg).gaussian_budget
    more = make_plan(scene, parse_edits('[{"op": "remove", "track_id": 0}]'), cfg).gaussian_budget
    assert more == base + cfg.gaussians_per_agent
    assert make_plan(scene, config=PlanConfig(max_gaussians=5_000, min_gaussians=1)).gaussian_budget == 5_000


def test_edits_naming_unknown_tracks_or_reusing_ids_are_refused(scene):
    with pytest.raises(OmniscsError, match=r"track id\(s\) \[9\]"):
        make_plan(scene, parse_edits('[{"op": "remove", "track_id": 9}]'))
    with pytest.raises(OmniscsError, match="reuse track id"):
        make_plan(scene, parse_edits('[{"op": "insert", "track_id": 1, "asset_id": "sedan-0001", '
                                     '"category": "car", "pose": [0, 0, 0.7, 0]}]'))


def test_plan_round_trips_through_json(scene):
    plan = make_plan(scene, parse_edits('[{"op": "insert", "track_id": 50, "asset_id": "sedan-0001", '
                                        '"category": "car", "pose": [0, 0, 0.7, 0]}]'))
    assert plan.inserted == (50,) and plan.stages["agent_models"]
    assert ScenePlan.from_dict(__import__("json").loads(plan.to_json())) == plan


def test_empty_scene_plans_without_nodes(tmp_path):
    plan = make_plan(load_scene(write_tiny_scene(tmp_path / "e", n_tracks=0)))
    assert plan.agent_nodes == () and plan.background_tracks == () and plan.gaussian_budget > 0
