"""Edits on the ground-truth world: pose edits in the agent frame, remove, replace, trajectories, inserts."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.edits import Insert, Remove, ReplaceModel, Rotate, SetTrajectory, Translate
from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform, transform_points
from omniscs.taxonomy import SEMANTIC_IDS
from omniscs.world import World, WorldRenderer, apply_edits, build_asset, generate_world

W, H = 96, 54


@pytest.fixture(scope="module")
def world() -> World:
    return generate_world("straight", 11, n_frames=3, n_cameras=1, width=W, height=H)


@pytest.fixture(scope="module")
def front(world):
    return WorldRenderer(world).render_camera(0, "CAM_FRONT")


def _most_visible(front) -> int:
    ids, counts = np.unique(front.instance[front.instance >= 0], return_counts=True)
    assert len(ids), "the front camera should see at least one agent"
    return int(ids[np.argmax(counts)])


def test_remove_makes_the_instance_vanish_and_the_background_appear(world, front):
    tid = _most_visible(front)
    was = front.instance == tid
    after = WorldRenderer(apply_edits(world, [Remove(tid)])).render_camera(0, "CAM_FRONT")
    assert tid not in after.instance
    assert tid not in [a.track_id for a in apply_edits(world, [Remove(tid)]).agents]
    # What was behind the agent is farther away (or sky) everywhere it used to be.
    behind = after.depth[was]
    assert np.all((behind == 0) | (behind > front.depth[was]))
    assert np.any(after.rgb[was] != front.rgb[was])


def test_apply_edits_returns_a_new_world_and_leaves_the_input_untouched(world):
    before = world.to_json()
    tid = world.agents[0].track_id
    edited = apply_edits(world, [Translate(tid, longitudinal=2.0), Rotate(tid, yaw_deg=30)])
    assert world.to_json() == before
    assert edited.to_json() != before
    assert World.from_json(edited.to_json()).to_json() == edited.to_json()


def test_translate_moves_the_agent_along_its_own_axes(world):
    a = world.agents[0]
    edited = apply_edits(world, [Translate(a.track_id, longitudinal=2.0, lateral=-1.0, vertical=0.5)]).agent(a.track_id)
    expected = a.poses[:, :3, 3] + np.einsum("fij,j->fi", a.poses[:, :3, :3], [2.0, -1.0, 0.5])
    np.testing.assert_allclose(edited.poses[:, :3, 3], expected, atol=1e-12)
    np.testing.assert_allclose(edited.poses[:, :3, :3], a.poses[:, :3, :3], atol=1e-12)


def test_rotate_yaw_turns_the_heading_about_the_box_centre(world):
    a = world.agents[0]
    edited = apply_edits(world, [Rotate(a.track_id, yaw_deg=90)]).agent(a.track_id)
    np.testing.assert_allclose(edited.poses[:, :3, 3], a.poses[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(edited.poses[:, :3, 0], a.poses[:, :3, 1], atol=1e-12)  # new forward = old left


def test_replace_model_keeps_the_box_and_scales_the_new_mesh_into_it(world, front):
    tid = _most_visible(front)
    old = world.agent(tid)
    edited = apply_edits(world, [ReplaceModel(tid, "excavator-0001")])
    new = edited.agent(tid)
    np.testing.assert_array_equal(new.size, old.size)
    np.testing.assert_array_equal(new.poses, old.poses)
    assert new.asset_id == "excavator-0001" and new.category == "construction_vehicle"
    r = WorldRenderer(edited)
    out = r.render_camera(0, "CAM_FRONT")
    assert np.sum(out.instance == tid) > 0
    assert not np.array_equal(out.rgb, front.rgb)
    points, tracks = r.lidar_scan(0, return_track_ids=True)
    local = transform_points(invert_transform(new.poses[0]),
                             transform_points(edited.ego_poses[0], points[tracks == tid, :3]))
    assert len(local) and np.all(np.abs(local) <= new.size / 2 + 1e-3)


def test_overturned_insert_lies_on_its_roof_on_the_ground_and_renders(world):
    asset = build_asset("sedan-0003")
    edit = Insert(track_id=900, asset_id="sedan-0003", category="car", pose=(12.0, 0.0, asset.size[2] / 2, 0.3),
                  roll_deg=180.0)
    edited = apply_edits(world, [edit])
    agent = edited.agent(900)
    np.testing.assert_allclose(agent.size, asset.size)
    np.testing.assert_allclose(agent.poses[:, 2, 3], asset.size[2] / 2, atol=1e-9)
    np.testing.assert_allclose(agent.poses[:, :3, 2], np.tile([0, 0, -1.0], (3, 1)), atol=1e-9)  # roof down
    out = WorldRenderer(edited).render_camera(0, "CAM_FRONT")
    mask = out.instance == 900
    assert mask.sum() > 20
    assert np.all(out.semantic[mask] == SEMANTIC_IDS["vehicle"])


def test_insert_on_its_side_rests_on_the_ground():
    w = generate_world("straight", 11, n_frames=2, n_cameras=1, width=W, height=H)
    asset = build_asset("van-0002")
    edited = apply_edits(w, [Insert(track_id=901, asset_id="van-0002", category="car",
                                    pose=(15.0, 3.0, asset.size[2] / 2, 0.0), roll_deg=90.0)])
    np.testing.assert_allclose(edited.agent(901).poses[:, 2, 3], asset.size[1] / 2, atol=1e-9)


def test_inserted_box_size_scales_the_mesh(world):
    edited = apply_edits(world, [Insert(track_id=902, asset_id="traffic_cone-0000", category="traffic_cone",
                                        pose=(9.0, 0.0, 1.0, 0.0), size=(2.0, 2.0, 2.0))])
    np.testing.assert_allclose(edited.agent(902).size, [2.0, 2.0, 2.0])
    points, tracks = WorldRenderer(edited).lidar_scan(0, return_track_ids=True)
    local = transform_points(invert_transform(edited.agent(902).poses[0]),
                             transform_points(edited.ego_poses[0], points[tracks == 902, :3]))
    assert len(local) > 10 and np.all(np.abs(local) <= 1.0 + 1e-3)
    assert np.abs(local[:, 2]).max() > 0.5  # the cone is stretched to 2 m tall


def test_set_trajectory_replaces_poses_and_presence(world, front):
    tid = _most_visible(front)
    waypoints = (None, (20.0, 0.0, 0.8, 0.0), (21.0, 0.0, 0.8, 0.0))
    edited = apply_edits(world, [SetTrajectory(tid, waypoints)])
    agent = edited.agent(tid)
    np.testing.assert_array_equal(agent.present, [False, True, True])
    np.testing.assert_allclose(agent.poses[2, :3, 3], [21.0, 0.0, 0.8])
    r = WorldRenderer(edited)
    assert tid not in r.render_camera(0, "CAM_FRONT").instance
    assert tid in r.render_camera(1, "CAM_FRONT").instance


def test_edits_can_be_given_as_json(world):
    tid = world.agents[0].track_id
    edited = apply_edits(world, f'[{{"op": "remove", "track_id": {tid}}}]')
    assert tid not in [a.track_id for a in edited.agents]


@pytest.mark.parametrize("edits", [
    [Remove(123456)],
    [Translate(123456, longitudinal=1.0)],
    [ReplaceModel(1, "unicorn-0001")],
    [Insert(track_id=1, asset_id="sedan-0000", category="car", pose=(0, 0, 1, 0))],  # id already used
    [Insert(track_id=903, asset_id="sedan-0000", category="spaceship", pose=(0, 0, 1, 0))],
    [Insert(track_id=903, asset_id="sedan-0000", category="car")],  # neither pose nor waypoints
    [Insert(track_id=903, asset_id="sedan-0000", category="car", pose=(0, 0, 1, 0), size=(1, 0, 1))],
    [SetTrajectory(1, ((0, 0, 1, 0),))],  # wrong number of frames
    [Translate(1, longitudinal=float("nan"))],
])
def test_bad_edits_raise_a_domain_error(world, edits):
    assert world.agent(1)
    with pytest.raises(OmniscsError):
        apply_edits(world, edits)


def test_a_removed_agent_kept_as_a_shadow_caster_is_unseen_but_still_shades(world, front):
    """The bench's second reference: the world without an object, shaded as if it were there."""
    tid = _most_visible(front)
    removed = apply_edits(world, [Remove(tid)])
    plain = WorldRenderer(removed).render_camera(0, "CAM_FRONT")
    caster = [a for a in world.agents if a.track_id == tid]
    kept = WorldRenderer(removed, shadow_casters=caster).render_camera(0, "CAM_FRONT")
    assert tid not in kept.instance
    np.testing.assert_array_equal(kept.depth, plain.depth)  # not seen by camera rays
    np.testing.assert_array_equal(kept.instance, plain.instance)
    darker = kept.rgb.astype(int).sum(-1) < plain.rgb.astype(int).sum(-1) - 8
    assert darker.any()  # its shadow or ambient occlusion on what lies around it
    assert not (kept.rgb.astype(int).sum(-1) > plain.rgb.astype(int).sum(-1) + 8).any()  # light is only taken away
    np.testing.assert_array_equal(WorldRenderer(removed, shadow_casters=()).render_camera(0, "CAM_FRONT").rgb,
                                  plain.rgb)


def test_a_shadow_caster_from_a_log_of_another_length_is_refused(world):
    short = generate_world("straight", 12, n_frames=2, n_cameras=1, width=W, height=H)
    with pytest.raises(OmniscsError, match="poses"):
        WorldRenderer(world, shadow_casters=short.agents[:1])
