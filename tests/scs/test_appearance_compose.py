"""Appearance-level SCS composition: objects replace an agent's model (own size, its motion) or stand at a user pose
(upright, on the side, overturned) resting on the road; the annotation box is the box of the turned model; the world
and the graph read the same edit specs; shadow and colour transform; 1-to-N variants that pass every check; clear
errors for impossible requests (issue 16)."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from appearance_fixtures import small_pool
from nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene
from omniscs.errors import OmniscsError
from omniscs.geometry import pose_from_xyz_yaw, rotmat_from_euler
from omniscs.scs.appearance.compose import (SHADOW_ID_OFFSET, CompositeConfig, check_variant, compose_variant,
                                            contact_shadow, heading_and_tilt, insert_variant, model_upright_box,
                                            new_track_id, node_boxes, replace_variant)

AGENTS = ({"x": 11.0, "y": 0.0, "speed": 6.0, "asset": "sedan-0003"},
          {"x": 6.0, "y": 3.3, "speed": 9.0, "asset": "sedan-0011"})


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from omniscs.scene import load_scene

    world = nsg_world(agents=AGENTS, n_frames=8, n_cameras=2, width=128, height=72)
    return load_scene(write_nsg_scene(tmp_path_factory.mktemp("app") / "scene", world))


@pytest.fixture(scope="module")
def graph(scene):
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import make_plan

    config = tiny_fit_config()
    return initial_graph(scene, make_plan(scene, None, config.plan, appearance_variants=1), config,
                         Observations(scene))


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    """Two pool-split models: a box truck and a sedan (never in the test world)."""
    return small_pool(tmp_path_factory.mktemp("pool") / "pool")


@pytest.fixture(scope="module")
def resolve(pool, graph):
    from omniscs.agents.pool import model_resolver
    from omniscs.nsg.edit import node_model_resolver

    return model_resolver(pool.root, node_model_resolver(graph))


def _ids(pool):
    t = pool.table().set_index("source")
    return t.loc["box_truck-0020", "model_id"], t.loc["sedan-0045", "model_id"]


# ----------------------------------------------------------------------------- boxes of turned models
@pytest.mark.parametrize("roll,pitch,expect", [(0, 0, (0, 1, 2)), (180, 0, (0, 1, 2)), (90, 0, (0, 2, 1)),
                                               (-90, 0, (0, 2, 1)), (0, 90, (2, 1, 0)), (0, 180, (0, 1, 2))])
def test_the_annotation_box_of_a_turned_model_is_the_upright_box_it_fills(roll, pitch, expect):
    from omniscs.nsg.agent import AgentNode
    from omniscs.gaussians import empty_params

    size = np.array([4.0, 2.0, 1.5])
    yaw = 0.7
    T = pose_from_xyz_yaw(3.0, -2.0, 0.9, yaw)
    T[:3, :3] = T[:3, :3] @ rotmat_from_euler(np.radians(roll), np.radians(pitch), 0.0)
    node = AgentNode(5, "car", size, T[None], np.array([True]), empty_params(0))
    box = node_boxes(node)[0]
    assert np.allclose([box["length"], box["width"], box["height"]], size[list(expect)], atol=1e-9)
    assert np.allclose([box["cx"], box["cy"], box["cz"]], [3.0, -2.0, 0.9])
    heading = yaw + np.pi if pitch == 180 else yaw  # pitched over backwards, the nose points the other way
    assert np.isclose(np.cos(box["yaw"] - heading), 1.0, atol=1e-9)  # pitch 90: read from the y axis
    assert np.isclose(box["qw"] ** 2 + box["qz"] ** 2, 1.0) and box["qx"] == 0.0 and box["qy"] == 0.0


def test_heading_and_tilt_recompose_every_rotation_even_at_gimbal_lock():
    rng = np.random.default_rng(0)
    cases = [rotmat_from_euler(*rng.uniform(-np.pi, np.pi, 3)) for _ in range(50)]
    cases += [rotmat_from_euler(0.3, np.pi / 2, 1.1), rotmat_from_euler(-2.0, -np.pi / 2, -0.4)]
    for R in cases:
        yaw, tilt = heading_and_tilt(R)
        c, s = np.cos(yaw), np.sin(yaw)
        assert np.allclose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ tilt, R, atol=1e-9)
        assert np.isfinite(yaw) and np.all(np.isfinite(tilt))


# ----------------------------------------------------------------------------- replace and insert
def test_replace_keeps_the_agents_motion_and_takes_the_objects_own_size_on_the_same_ground(graph, resolve, pool):
    truck, _ = _ids(pool)
    model = resolve(truck)
    v = replace_variant(graph.scene_id, "a000", 1, model, truck)
    comp = compose_variant(graph, v, resolve, CompositeConfig(shadow=False))
    before, after = graph.agent(1), comp.graph.agent(1)
    assert np.allclose(after.size, model.size) and after.category == model.category
    assert np.allclose(after.world_from_agent[:, :2, 3], before.world_from_agent[:, :2, 3])  # the same motion
    bottom_before = before.world_from_agent[:, 2, 3] - before.size[2] / 2
    bottom_after = after.world_from_agent[:, 2, 3] - after.size[2] / 2
    assert np.allclose(bottom_before, bottom_after)  # resting where the car stood
    boxes = comp.boxes[1]
    assert sorted(boxes) == list(np.flatnonzero(before.present)) and comp.objects == (1,)
    assert np.isclose(boxes[0]["height"], model.size[2]) and boxes[0]["category"] == model.category


@pytest.mark.parametrize("roll", [0.0, 90.0, 180.0])
def test_an_inserted_object_rests_on_the_road_and_the_world_places_it_identically(scene, graph, resolve, pool, roll):
    from omniscs.world import apply_edits

    truck, _ = _ids(pool)
    model = resolve(truck)
    tid = new_track_id(scene, graph)
    v = insert_variant(scene.scene_id, "a001", tid, model, truck, 25.0, -3.3, 0.0, 0.4, roll_deg=roll)
    comp = compose_variant(graph, v, resolve, CompositeConfig(shadow=False))
    node = comp.graph.agent(tid)
    box = comp.boxes[tid][0]
    assert np.isclose(box["cz"] - box["height"] / 2, 0.0, atol=1e-9)  # the turned box's floor on the road
    assert np.allclose([box["length"], box["width"], box["height"]], model_upright_box(model, roll))
    # the turned model's lowest Gaussian lies near the road (Gaussians sit on the surface of the calibrated model)
    R, t = node.world_from_agent[0, :3, :3], node.world_from_agent[0, :3, 3]
    lowest = float((node.gaussians.means.double().numpy() @ R.T + t)[:, 2].min())
    assert -0.15 < lowest < 0.2
    # the same spec applied to the world (with a library asset of that size) puts its box exactly there
    edits = [dict(e, asset_id="box_truck-0020") for e in v["edits"]]
    track = apply_edits(scene.world, edits).agent(tid)
    assert np.allclose(track.poses, node.world_from_agent, atol=1e-9) and np.allclose(track.size, node.size)


def test_a_replaced_agent_in_the_world_takes_the_same_size_and_ground(scene, graph, resolve, pool):
    from omniscs.world import apply_edits

    truck, _ = _ids(pool)
    v = replace_variant(graph.scene_id, "a000", 2, resolve(truck), truck)
    node = compose_variant(graph, v, resolve, CompositeConfig(shadow=False)).graph.agent(2)
    track = apply_edits(scene.world, [dict(e, asset_id="box_truck-0020") for e in v["edits"]]).agent(2)
    assert np.allclose(track.size, node.size)
    assert np.allclose(track.poses[:, 2, 3] - track.size[2] / 2, scene.world.agent(2).poses[:, 2, 3]
                       - scene.world.agent(2).size[2] / 2)


# ----------------------------------------------------------------------------- shadow and colour
def test_the_contact_shadow_is_an_unannotated_node_that_darkens_the_road_around_the_object(scene, graph, resolve,
                                                                                          pool, tmp_path):
    from omniscs.annotate.scene import annotate_variants

    truck, _ = _ids(pool)
    tid = new_track_id(scene, graph)
    v = insert_variant(scene.scene_id, "a002", tid, resolve(truck), truck, 18.0, -3.3, 0.0, 0.0)
    lit = compose_variant(graph, v, resolve, CompositeConfig(shadow=False, colour_fit=False))
    shaded = compose_variant(graph, v, resolve, CompositeConfig(shadow=True, colour_fit=False))
    assert tid + SHADOW_ID_OFFSET in shaded.graph.agent_ids and tid + SHADOW_ID_OFFSET not in shaded.boxes
    view = graph.view(scene.camera_names[0], 0)
    a, b = lit.graph.render(view), shaded.graph.render(view)
    darker = (a.rgb - b.rgb).sum(-1)
    assert float(darker.max()) > 0.1 and float(darker.min()) > -1e-4  # only ever darker
    results = annotate_variants(graph, scene, [v], tmp_path / "ann",
                                compose=lambda x: compose_variant(graph, x, resolve, CompositeConfig(shadow=True)))
    rows = json.loads((tmp_path / "ann" / "rows.json").read_text())
    assert {a["track_id"] for a in rows["annotations"]} & {tid} == {tid}
    assert all(a["track_id"] < SHADOW_ID_OFFSET for a in rows["annotations"])
    assert results[0].summary["level"] == "appearance"


def test_the_contact_shadow_stays_finite_and_bounded_at_extreme_footprints():
    for footprint in ([0.01, 0.01], [40.0, 3.0], [1e-6, 1e-6]):
        s = contact_shadow(np.array(footprint), CompositeConfig(), 3)
        assert len(s) > 0 and s.is_finite()
        alpha = torch.sigmoid(s.opacity_logits)
        assert float(alpha.max()) <= CompositeConfig().shadow_opacity + 1e-6


def test_the_scene_colour_transform_is_identity_without_a_pool_and_finite_with_one(scene, graph, pool, tmp_path):
    from omniscs.agents.pool import Pool
    from omniscs.scs.appearance.colour import IDENTITY, ColourFitConfig, scene_colour_transform

    none = scene_colour_transform(graph, scene, None)
    assert np.allclose(none.affine, IDENTITY) and "no model pool" in none.reason
    empty = scene_colour_transform(graph, scene, Pool(tmp_path / "empty"))
    assert np.allclose(empty.affine, IDENTITY) and "empty" in empty.reason
    got = scene_colour_transform(graph, scene, pool, config=ColourFitConfig(min_view_pixels=50))
    assert np.all(np.isfinite(got.affine)) and got.vehicles
    lo, hi = ColourFitConfig().gain_range
    assert np.all((np.diag(got.affine[:, :3]) >= lo) & (np.diag(got.affine[:, :3]) <= hi))


def test_a_variants_colour_transform_maps_the_objects_colours_exactly(graph, resolve, pool):
    from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET

    truck, _ = _ids(pool)
    v = replace_variant(graph.scene_id, "a000", 1, resolve(truck), truck)
    affine = np.array([[0.5, 0, 0, 0.2], [0, 0.6, 0, 0.1], [0, 0, 0.7, 0.0]])
    plain = compose_variant(graph, v, resolve, CompositeConfig(shadow=False, colour_fit=False))
    mapped = compose_variant(graph, dict(v, colour=affine.tolist()), resolve, CompositeConfig(shadow=False))
    c0 = SH_COLOR_OFFSET + SH_C0 * plain.graph.agent(1).gaussians.sh_dc.double().numpy()
    c1 = SH_COLOR_OFFSET + SH_C0 * mapped.graph.agent(1).gaussians.sh_dc.double().numpy()
    assert np.allclose(c1, c0 @ affine[:, :3].T + affine[:, 3], atol=1e-5)
    with pytest.raises(OmniscsError, match="colour must be a finite 3 x 4"):
        compose_variant(graph, dict(v, colour=[[float("nan")] * 4] * 3), resolve)


# ----------------------------------------------------------------------------- 1-to-N and bad requests
def test_variants_drawn_one_to_n_pass_every_placement_check_and_repeat_by_seed(scene, graph, resolve, pool):
    from omniscs.scs.appearance.placement import PlacementConfig, check_placement, placement_context
    from omniscs.scs.appearance.variants import AppearanceConfig, make_appearance_variants

    config = AppearanceConfig(placement=PlacementConfig(distance_m=(10.0, 30.0), min_visible_frames=2), seed=3)
    ids = list(_ids(pool))
    drawn = make_appearance_variants(graph, scene, resolve, ids, 4, config)
    assert [v["variant_id"] for v in drawn.variants] == ["a000", "a001", "a002", "a003"]
    assert {v["placement"] for v in drawn.variants} <= {"insert", "replace"}
    context = placement_context(scene)
    for v in drawn.variants:
        check_variant(v)
        if v["placement"] != "insert":
            continue
        e = v["edits"][0]
        box = model_upright_box(resolve(v["object_id"]), e["roll_deg"], e["pitch_deg"])
        x, y, z, yaw = e["pose"]
        z += box[2] / 2 - resolve(v["object_id"]).size[2] / 2  # the resting lift of the turned box
        assert check_placement(context, box, (x, y, z, yaw), config.placement).ok
    again = make_appearance_variants(graph, scene, resolve, ids, 4, config)
    assert [v["edits"] for v in again.variants] == [v["edits"] for v in drawn.variants]
    poses = [v["pose"]["name"] for v in drawn.variants if v["placement"] == "insert"]
    assert poses[:2] == ["overturned", "on_side"]


def test_impossible_and_malformed_requests_are_clear_errors(scene, graph, resolve, pool):
    from omniscs.nsg.edit import AgentModel
    from omniscs.pipeline.appearance import parse_pose, user_variants
    from omniscs.scs.appearance.variants import make_appearance_variants

    truck, car = _ids(pool)
    with pytest.raises(OmniscsError, match="overlaps"):  # on top of the car ahead of the ego
        user_variants(scene, graph, resolve, insert=car, pose="11,0,0")
    with pytest.raises(OmniscsError, match="drivable"):  # off the road
        user_variants(scene, graph, resolve, insert=car, pose="20,40,0")
    with pytest.raises(OmniscsError, match="--pose must be"):
        parse_pose("1,2")
    with pytest.raises(OmniscsError, match="--pose must be"):
        parse_pose("1,nan,3")
    with pytest.raises(OmniscsError, match="give one of"):
        user_variants(scene, graph, resolve)
    huge = resolve(truck)
    giant = AgentModel(huge.gaussians, np.array([60.0, 30.0, 5.0]), huge.category)
    with pytest.raises(OmniscsError, match="found 0 of 1"):
        make_appearance_variants(graph, scene, lambda _: giant, ["pm-giant"], 1)
    v = replace_variant(graph.scene_id, "a000", 1, huge, truck)
    with pytest.raises(OmniscsError, match="not an appearance or designed variant"):
        check_variant(dict(v, kind="cut_in"))
    with pytest.raises(OmniscsError, match="placement must be"):
        check_variant(dict(v, placement="teleport"))
    bad = dataclasses.replace(huge.gaussians, means=huge.gaussians.means * float("nan"))
    with pytest.raises(OmniscsError, match="non-finite"):
        compose_variant(graph, v, lambda _: AgentModel(bad, huge.size, huge.category))
    with pytest.raises(Exception, match="has no model"):
        compose_variant(graph, dict(v, edits=[dict(v["edits"][0], asset_id="pm-000000000000")]), resolve)


def test_a_pool_model_without_keyframes_is_refused_before_any_scene_and_the_colour_fit_falls_back(
        scene, graph, pool, tmp_path):
    import shutil

    from omniscs.agents.pool import Pool
    from omniscs.pipeline.appearance import pool_objects
    from omniscs.scs.appearance.colour import IDENTITY, ColourFitConfig, scene_colour_transform

    broken = Pool(tmp_path / "broken")
    shutil.copytree(pool.root, broken.root, ignore=shutil.ignore_patterns("embeddings"))
    truck, car = _ids(pool)
    (broken.root / "models" / car / "keyframes.npz").unlink()
    with pytest.raises(OmniscsError, match="has no readable keyframes"):
        pool_objects(broken.root, (car,))
    assert pool_objects(broken.root, (truck,)) == [truck]
    got = scene_colour_transform(graph, scene, broken, config=ColourFitConfig(min_view_pixels=50))
    assert np.allclose(got.affine, IDENTITY) and "could not be matched" in got.reason


def test_an_object_that_fits_nowhere_gives_way_to_the_next_and_is_recorded(scene, graph, resolve, pool):
    from omniscs.nsg.edit import AgentModel
    from omniscs.scs.appearance.placement import PlacementConfig
    from omniscs.scs.appearance.variants import AppearanceConfig, make_appearance_variants

    truck, car = _ids(pool)
    real = resolve(car)
    giant = AgentModel(real.gaussians, np.array([60.0, 30.0, 5.0]), real.category)
    models = {"pm-giant": giant, car: real}
    config = AppearanceConfig(placements=("insert",), placement=PlacementConfig(distance_m=(10.0, 30.0),
                                                                                min_visible_frames=2), seed=1)
    drawn = make_appearance_variants(graph, scene, lambda m: models[m], ["pm-giant", car], 2, config)
    assert [v["object_id"] for v in drawn.variants] == [car, car]
    assert sum(len(r["objects_that_fit_nowhere"]) for r in drawn.placements) == 1
    assert drawn.placements[[len(r["objects_that_fit_nowhere"]) > 0 for r in drawn.placements].index(True)][
        "objects_that_fit_nowhere"][0]["object_id"] == "pm-giant"
