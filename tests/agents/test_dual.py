"""The dual strategy: mirror symmetry, colour correction, clarity and coverage, matching to the pool, and the graph it
completes (issue 13)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omniscs.agents.dual import (DualConfig, azimuth_coverage, choose, clarity, colour_corrected, complete_agents,
                                 cropped_to_box, mirror_completed, mirrored, track_views)
from omniscs.agents.matching import match_tracks
from omniscs.agents.pool import Pool
from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams
from omniscs.quaternions import quat_to_rotmat
from omniscs.render.sh import colors_from_sh
from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene


def _random_params(n: int, degree: int = 3, seed: int = 0) -> GaussianParams:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return GaussianParams(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g),
                          torch.randn(n, generator=g), torch.randn(n, 3, generator=g),
                          torch.randn(n, k - 1, 3, generator=g))


def _unit(q):
    q = q.double().numpy()
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_mirror_reflects_positions_orientations_and_view_dependent_colours():
    p = _random_params(50)
    m = mirrored(p)
    M = np.diag([1.0, -1.0, 1.0])
    assert torch.allclose(m.means, p.means * torch.tensor([1.0, -1.0, 1.0]))
    R, R2 = quat_to_rotmat(_unit(p.quats)), quat_to_rotmat(_unit(m.quats))
    assert np.allclose(M @ R @ M, R2, atol=1e-6)
    assert np.allclose(np.linalg.det(R2), 1.0, atol=1e-6)  # still a rotation: the renderer takes it as is
    dirs = torch.randn(4, 50, 3, generator=torch.Generator().manual_seed(1))
    seen = colors_from_sh(3, p.sh, dirs)
    seen_in_mirror = colors_from_sh(3, m.sh, dirs * torch.tensor([1.0, -1.0, 1.0]))
    assert torch.allclose(seen, seen_in_mirror, atol=1e-4)
    assert torch.allclose(mirrored(m).means, p.means)


def test_mirror_completion_keeps_the_seen_half_and_replaces_the_other_by_its_image():
    p = _random_params(200)
    left = mirror_completed(p, +1.0)
    n_left = int((p.means[:, 1] >= 0).sum())
    assert len(left) == n_left + int((p.means[:, 1] > 0).sum())
    kept = left.means[:n_left]
    assert bool((kept[:, 1] >= 0).all()) and bool((left.means[n_left:, 1] < 0).all())
    right = mirror_completed(p, -1.0)
    assert bool((right.means[: int((p.means[:, 1] <= 0).sum()), 1] <= 0).all())


def test_colour_correction_is_the_exact_affine_map_of_every_view_dependent_colour():
    p = _random_params(30, seed=2)
    p = GaussianParams(p.means, p.quats, p.log_scales, p.opacity_logits, p.sh_dc * 0.1 + 0.5, p.sh_rest * 0.02)
    affine = np.array([[0.8, 0.1, 0.0, 0.05], [0.0, 1.2, 0.0, -0.02], [0.05, 0.0, 0.9, 0.1]])
    out = colour_corrected(p, affine)
    dirs = torch.randn(3, 30, 3, generator=torch.Generator().manual_seed(3))
    before, after = colors_from_sh(3, p.sh, dirs), colors_from_sh(3, out.sh, dirs)
    assert bool((before > 0).all())  # no clamping in the way of the comparison
    expect = before @ torch.as_tensor(affine[:, :3], dtype=torch.float32).T + torch.as_tensor(affine[:, 3],
                                                                                              dtype=torch.float32)
    assert torch.allclose(after, expect.clamp_min(0), atol=1e-5)


def test_strays_far_from_the_box_are_cut_but_an_empty_cut_keeps_the_node():
    p = _random_params(100)
    means = p.means.clone()
    means[:5] = torch.tensor([25.0, 0.0, 0.0])  # strays 25 m away (what fast fits leave)
    p = GaussianParams(means, p.quats, p.log_scales, p.opacity_logits, p.sh_dc, p.sh_rest)
    size = np.array([4.5, 1.9, 1.6])
    cut = cropped_to_box(p, size, 0.3)
    assert len(cut) < len(p) and float(cut.means.abs().max(0).values[0]) <= 2.25 + 0.3
    assert len(cropped_to_box(p.select(torch.arange(5)), size, 0.3)) == 5


def test_azimuth_coverage_counts_sectors_and_their_mirror_images():
    assert azimuth_coverage([], 12, True) == 0.0
    assert azimuth_coverage([5.0, 7.0], 12, False) == pytest.approx(1 / 12)
    assert azimuth_coverage([45.0], 12, True) == pytest.approx(2 / 12)  # 45 and its mirror 315
    assert azimuth_coverage(np.arange(0, 360, 30) + 1.0, 12, False) == 1.0


def _clarity(score, coverage, category="car", pixels=4000.0):
    from omniscs.agents.dual import Clarity

    return Clarity(1, category, 10, pixels, 0.9, 80.0, coverage / 2, coverage, score)


def test_the_choice_follows_clarity_coverage_and_what_the_pool_holds():
    config = DualConfig(pool_categories=())
    assert choose(_clarity(0.9, 0.9), False, True, config)[0] == "fitted"
    assert choose(_clarity(0.9, 0.9), True, True, config)[0] == "online"
    # a car takes the relit pool model however well it was seen (default), a bus keeps the rule; none without a car
    strategy, reason = choose(_clarity(0.9, 0.9, pixels=30000.0), True, True, DualConfig())
    assert strategy == "pool" and reason.startswith("a car: the relit pool model")
    assert choose(_clarity(0.9, 0.9, "bus", pixels=30000.0), True, True, DualConfig())[0] == "online"
    assert choose(_clarity(0.9, 0.9, pixels=30000.0), True, False, DualConfig())[0] == "online"
    strategy, reason = choose(_clarity(0.9, 0.2), True, True, config)
    assert strategy == "pool" and "too few sides" in reason
    strategy, reason = choose(_clarity(0.2, 0.9), True, True, config)
    assert strategy == "pool" and reason.startswith("unclear")
    strategy, reason = choose(_clarity(0.2, 0.2, "bus"), True, False, config)
    assert strategy == "online" and "no bus model" in reason
    with pytest.raises(OmniscsError):
        DualConfig(min_coverage=1.5)


# ----------------------------------------------------------------------------- with a scene and a pool
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from omniscs.scene import load_scene

    return load_scene(write_nsg_scene(tmp_path_factory.mktemp("dual") / "scene", nsg_world(n_frames=6)))


@pytest.fixture(scope="module")
def graph(scene):
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import make_plan

    config = tiny_fit_config()
    return initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    """Three small models from the library's pool split: two cars and a truck."""
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.world.assets import build_asset

    from omniscs.world.render import F0, SHININESS

    p = Pool(tmp_path_factory.mktemp("pool") / "pool")
    for aid in ("sedan-0045", "suv-0035", "box_truck-0020"):
        s = build_asset(aid).surface
        params, info = model_from_mesh(s.vertices, s.faces, s.face_colour, 1500, 0,
                                       face_specular=F0[s.face_material], face_shininess=SHININESS[s.face_material])
        p.add(params, build_asset(aid).category, "mesh", aid, info["quality_psnr"], material=info["material"])
    return p


@pytest.fixture(scope="module")
def splat_pool(pool, tmp_path_factory):
    """The same models without their materials (as imported splats come)."""
    p = Pool(tmp_path_factory.mktemp("splats") / "pool")
    for mid in pool.table().model_id:
        m = pool.get(mid)
        p.add(m.params, m.meta["category"], "mesh", m.meta["source"], m.meta["quality"])
    return p


def test_clarity_of_tracks_seen_and_unseen_is_finite(scene):
    frames = range(scene.n_frames)
    c = clarity(scene, 1, frames)
    assert c.n_views > 0 and 0 < c.score <= 1 and 0 < c.coverage <= c.coverage_mirrored <= 1
    assert all(np.isfinite(v) for v in (c.score, c.pixels, c.coverage, c.coverage_mirrored, c.sharpness))
    # the car ahead is seen from behind only: the front and sides are not covered
    assert c.coverage_mirrored < DualConfig().min_coverage
    none = clarity(scene, 1, [])  # no frames at all: zero, never NaN
    assert none.n_views == 0 and none.score == 0.0 and none.coverage == 0.0
    with pytest.raises(OmniscsError, match="no boxes"):
        clarity(scene, 99, frames)
    far = track_views(scene, 1, frames, min_pixels=10**9)
    assert far == []


def test_matching_picks_the_model_a_query_was_made_from_within_its_category(pool):
    from omniscs.agents.matching import crop_square

    table = pool.table().set_index("source")
    queries, sizes, cats = {}, {}, {}
    for t, aid in ((1, "suv-0035"), (2, "sedan-0045"), (3, "box_truck-0020")):
        mid = table.loc[aid, "model_id"]
        rgba = pool.keyframes(mid)[::5]
        queries[t] = np.stack([crop_square(np.ascontiguousarray(k[..., :3]), k[..., 3] / 255.0) for k in rgba])
        sizes[t] = table.loc[aid, ["length", "width", "height"]].to_numpy(np.float64)
        cats[t] = table.loc[aid, "category"]
    got = match_tracks(queries, sizes, cats, pool)
    assert {t: m for t, (m, _) in got.items()} == {1: table.loc["suv-0035", "model_id"],
                                                   2: table.loc["sedan-0045", "model_id"],
                                                   3: table.loc["box_truck-0020", "model_id"]}
    assert all(np.isfinite(d) for _, d in got.values())
    # a category the pool lacks, a track without crops, an empty pool: left out, no error
    got = match_tracks({4: queries[1], 5: queries[2][:0]}, {4: sizes[1], 5: sizes[2]}, {4: "bus", 5: "car"}, pool)
    assert got == {}
    assert match_tracks(queries, sizes, cats, Pool(pool.root.parent / "empty")) == {}


def test_the_dual_strategy_completes_only_the_tracks_that_need_it(scene, graph, pool):
    frames = range(scene.n_frames)
    before = {a.track_id: a.gaussians.means.clone() for a in graph.agents}
    large = DualConfig(min_online_pixels=0.0)  # the tiny log's car counts as seen large enough for its fit to serve
    completed, decisions = complete_agents(graph, scene, [1], frames, pool, large)
    by = {d.track_id: d for d in decisions}
    assert by[2].strategy == "fitted" and by[1].strategy == "pool"
    assert by[1].model_id in set(pool.table().model_id) and np.isfinite(by[1].distance)
    # clear but seen from behind only: a pool model with a material replaces the node whole, relit
    assert "relit" in by[1].reason and completed.agent(1).relight is not None
    assert len(completed.agent(1).gaussians) == len(pool.get(by[1].model_id).params)
    assert completed.agent(1).gaussians.is_finite()
    out = completed.render(completed.view(scene.camera_names[0], 2))
    assert bool(torch.isfinite(out.rgb).all())
    # without a pool the track gets the online model: the fitted node, its unseen side mirrored
    online, decisions = complete_agents(graph, scene, [1], frames, None)
    d = {d.track_id: d for d in decisions}[1]
    assert d.strategy == "online" and d.mirrored and "pool has no car model" in d.reason
    assert len(online.agent(1).gaussians) > 0 and online.agent(1).gaussians.is_finite()
    # forced arms, bad input
    assert {x.track_id: x.strategy for x in complete_agents(graph, scene, [1], frames, pool, force="online")[1]}[1] \
        == "online"
    with pytest.raises(OmniscsError, match="not agent nodes"):
        complete_agents(graph, scene, [7], frames, pool)
    with pytest.raises(OmniscsError, match="force"):
        complete_agents(graph, scene, [1], frames, pool, force="both")
    # the source graph is a value: unchanged
    assert all(torch.equal(graph.agent(t).gaussians.means, m) for t, m in before.items())


def test_a_pool_of_one_model_of_another_category_falls_back_to_online(scene, graph, tmp_path, pool):
    single = Pool(tmp_path / "single")
    truck = pool.table().set_index("source").loc["box_truck-0020", "model_id"]
    m = pool.get(truck)
    single.add(m.params, "truck", "mesh", "box_truck-0020")
    _, decisions = complete_agents(graph, scene, [1], range(scene.n_frames), single)
    d = {d.track_id: d for d in decisions}[1]
    assert d.strategy == "online" and "no car model" in d.reason


def test_pool_model_ids_are_valid_assets_of_replace_and_insert_edits(graph, pool):
    from omniscs.agents.pool import model_resolver
    from omniscs.nsg.edit import apply_graph_edits, node_model_resolver

    mid = pool.table().model_id.iloc[0]
    resolve = model_resolver(pool.root, node_model_resolver(graph))
    edited = apply_graph_edits(graph, [{"op": "replace_model", "track_id": 2, "asset_id": mid},
                                       {"op": "insert", "track_id": 40, "asset_id": mid, "category": "car",
                                        "pose": [20.0, -3.0, 0.8, 0.0]},
                                       {"op": "replace_model", "track_id": 1, "asset_id": "nsg:2"}], resolve)
    assert edited.agent(2).gaussians.sh_degree == graph.sh_degree  # the pool's degree-0 model padded
    assert np.allclose(edited.agent(40).size, pool.get(mid).meta["size"], atol=1e-3)
    with pytest.raises(Exception, match="no model"):
        apply_graph_edits(graph, [{"op": "replace_model", "track_id": 2, "asset_id": "pm-000000000000"}], resolve)


def test_clear_well_covered_tracks_grow_the_pool_only_above_the_quality_gate(scene, graph, tmp_path):
    from omniscs.agents.dual import grow_pool

    frames = list(range(scene.n_frames))
    # opaque nodes, as a fit leaves them (the initial graph's are faint)
    graph = graph.replace(agents=tuple(a.with_changes(gaussians=GaussianParams(
        a.gaussians.means, a.gaussians.quats, a.gaussians.log_scales + 0.5, a.gaussians.opacity_logits + 6.0,
        a.gaussians.sh_dc, a.gaussians.sh_rest)) for a in graph.agents))
    grown_pool = Pool(tmp_path / "grown")
    loose = DualConfig(min_clarity=0.1, min_coverage=0.1, min_online_pixels=0.0)  # the tiny log's cars: few sides
    assert grow_pool(graph, scene, frames[:4], frames[4:], grown_pool, 1e9, loose)  # candidates, none good enough
    assert grown_pool.table().empty
    got = grow_pool(graph, scene, frames[:4], frames[4:], grown_pool, -1e9, loose)
    added = {t: m for t, (m, q) in got.items() if m}
    assert added and all(q is None or np.isfinite(q) for _, q in got.values())
    table = grown_pool.table().set_index("model_id")
    for t, m in added.items():
        assert table.loc[m, "provenance"] == "scene_track" and table.loc[m, "source"] == f"{scene.scene_id}/track-{t}"
    # a track seen too small is no candidate: its fit does not serve as its model
    small = DualConfig(min_clarity=0.1, min_coverage=0.1, min_online_pixels=1e9)
    assert grow_pool(graph, scene, frames[:4], frames[4:], Pool(tmp_path / "small"), -1e9, small) == {}
    # the default gates: nothing in this log is clear and covered enough
    assert grow_pool(graph, scene, frames[:4], frames[4:], Pool(tmp_path / "strict"), 24.0) == {}


def test_rendering_the_candidates_into_the_scene_finds_the_vehicle_a_track_was_made_from(scene, tmp_path):
    """The log's car ahead is sedan-0003; with its own model among cars of other shapes (a van and a pickup, both
    category car), the render check picks it. (Another sedan scores within about 1 % of it on this small, briefly
    fitted scene: the check tells shapes apart here, not one sedan from the next.)"""
    from omniscs.agents.dual import verified_matches
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.nsg.train import fit_scene
    from omniscs.plan import make_plan
    from omniscs.world.assets import build_asset

    own = Pool(tmp_path / "own")
    for aid in ("van-0025", "pickup-0020", "sedan-0003"):
        a = build_asset(aid)
        params, _ = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, 1500, 0)
        own_id = own.add(params, "car", "mesh", aid)  # the last one: sedan-0003
    config = tiny_fit_config(40)
    graph = fit_scene(scene, config, make_plan(scene, None, config.plan), evaluate=False).graph
    frames = range(scene.n_frames)
    views = {1: track_views(scene, 1, frames, 100)}
    from omniscs.agents.dual import scene_query_views

    queries = {1: scene_query_views(scene, 1, views[1], 4)[0]}
    got = verified_matches(graph, scene, [1], views, own, queries, DualConfig(verify_top_k=3, min_view_pixels=100))
    model_id, distance, error, affine = got[1]
    assert model_id == own_id and np.isfinite(distance) and 0 <= error < 1 and np.isfinite(affine).all()


def test_a_track_no_view_shows_falls_back_to_its_fitted_node_mirrored(scene, graph, pool):
    """Seen in no training view (absent, 80 m away, fully hidden): no crops to match, so the online model, finite."""
    completed, decisions = complete_agents(graph, scene, [1], [], pool)
    d = {d.track_id: d for d in decisions}[1]
    assert d.strategy == "online" and d.clarity.n_views == 0 and d.clarity.score == 0.0
    assert "no pool model matched" in d.reason
    assert completed.agent(1).gaussians.is_finite() and len(completed.agent(1).gaussians) > 0


# ----------------------------------------------------------------------------- relit pool models
def test_a_track_seen_small_gets_the_whole_pool_model_however_well_covered():
    config = DualConfig(min_online_pixels=3000.0, pool_categories=())
    strategy, reason = choose(_clarity(0.9, 0.9, pixels=1500.0), True, True, config)
    assert strategy == "pool" and "seen too small" in reason and "1500 pixels (min 3000)" in reason
    assert choose(_clarity(0.9, 0.9, pixels=5000.0), True, True, config)[0] == "online"
    with pytest.raises(OmniscsError):
        DualConfig(min_online_pixels=-1.0)


def test_normals_point_out_of_the_model_and_the_mesh_builds_light_comes_off():
    from omniscs.agents.mesh import gaussians_from_mesh
    from omniscs.agents.relight import outward_normals, relight_base
    from omniscs.nsg.relight import srgb_decode

    # a 4 x 2 x 1.5 m box, one albedo (linear 0.4, 0.2, 0.1) on every face
    import trimesh

    box = trimesh.creation.box((4.0, 2.0, 1.5))
    albedo = np.array([0.4, 0.2, 0.1])
    params = gaussians_from_mesh(box.vertices, box.faces, np.tile(albedo, (len(box.faces), 1)), n=3000)
    n = outward_normals(params).numpy()
    m = params.means.numpy()
    on_face = np.abs(np.abs(m) / [2.0, 1.0, 0.75] - 1.0) < 1e-4  # which face each Gaussian lies on
    axis = on_face.argmax(1)
    expected = np.zeros_like(n)
    expected[np.arange(len(m)), axis] = np.sign(m[np.arange(len(m)), axis])
    assert np.allclose(n, expected, atol=1e-4)
    base = relight_base(params, mesh_light=True)
    assert torch.allclose(base.albedo, torch.as_tensor(albedo, dtype=torch.float32).expand_as(base.albedo), atol=2e-3)
    # without the mesh light (an imported model) the colour counts as the albedo itself
    plain = relight_base(params, mesh_light=False)
    colour = (0.5 + 0.28209479177387814 * params.sh_dc).clamp(0, 1)
    assert torch.allclose(plain.albedo, srgb_decode(colour), atol=1e-6)


@pytest.mark.slow
def test_the_light_fit_recovers_a_known_light_from_the_views(scene, graph, pool):
    """Images of a pool model (its own material) lit by a known sun and sky: fitted from the neutral light, the
    renders match them far better than the neutral light does."""
    from omniscs.agents.dual import placed_candidate
    from omniscs.agents.track_pixels import track_alone
    from omniscs.agents.relight import fit_lighting, relight_base
    from omniscs.nsg.graph import render_view

    mid = pool.table().set_index("source").loc["sedan-0045", "model_id"]
    node = graph.agent(1)
    g = placed_candidate(pool, mid, node.size, graph.sh_degree, graph.device)
    base = relight_base(g, mesh_light=True, material=pool.get(mid).material)
    assert float(base.specular.max()) > 0  # glass and paint mirror the sky
    truth = torch.tensor([[2.0, 1.8, 1.5], [-0.6, 0.3, 0.7], [0.5, 0.6, 0.8], [0.2, 0.18, 0.15], [0.3, 0.45, 0.9],
                          [0.7, 0.75, 0.8], [0.25, 0.25, 0.25]])
    lit = track_alone(graph, 1, g).replace(agents=(node.with_changes(gaussians=g, relight=base.with_lighting(truth)),))
    samples = []
    for f in range(scene.n_frames):
        view = graph.view(scene.camera_names[0], f)
        out = render_view(lit, view)
        if (out.alpha > 0.9).sum() > 200:
            samples.append((view, out.rgb.detach(), out.alpha.detach()))
    assert samples
    fitted, info = fit_lighting(graph, 1, g, base, samples, steps=100, render_steps=40)
    assert info["views"] == len(samples) and info["pairs"] > 100 and info["loss_last"] < 0.3 * info["loss_first"]

    def error(relight):
        alone = lit.replace(agents=(node.with_changes(gaussians=g, relight=relight),))
        return float(np.mean([(render_view(alone, v).rgb - t).abs()[w > 0.9].mean() for v, t, w in samples]))

    assert error(fitted) < 0.3 * error(base) and error(fitted) < 0.03
    assert bool(torch.isfinite(fitted.lighting).all()) and float(fitted.lighting[[0, 2, 3, 4, 5, 6]].min()) >= 0
    # nothing to fit: the neutral light back, unchanged
    same, info = fit_lighting(graph, 1, g, base, [], steps=10)
    assert same is base and info["views"] == 0


def test_a_relit_pool_model_completes_a_small_track_and_follows_the_light_when_turned(scene, graph, pool, tmp_path):
    from omniscs.nsg.checkpoint import load_graph, save_checkpoint
    from omniscs.nsg.edit import apply_graph_edits

    frames = range(scene.n_frames)
    config = DualConfig(min_online_pixels=1e9, relight=True, relight_steps=20, pool_categories=())
    completed, decisions = complete_agents(graph, scene, [1], frames, pool, config)
    d = {d.track_id: d for d in decisions}[1]
    assert d.strategy == "pool" and "seen too small" in d.reason and "relit" in d.reason
    node = completed.agent(1)
    assert node.relight is not None and len(node.relight) == len(node.gaussians) == len(pool.get(d.model_id).params)
    assert np.isfinite(np.asarray(d.lighting)).all() and np.asarray(d.lighting).shape == (7, 3)
    assert torch.equal(node.relight.specular.cpu(), pool.get(d.model_id).material.specular)
    turned = apply_graph_edits(completed, [{"op": "rotate", "track_id": 1, "yaw_deg": 180.0}])
    view = turned.view(scene.camera_names[0], 2)
    out = turned.render(view)
    assert bool(torch.isfinite(out.rgb).all())
    back = load_graph(save_checkpoint(completed, tmp_path / "ckpt"))
    assert torch.allclose(back.render(view).rgb, completed.render(view).rgb, atol=1e-6)
    # a track seen large enough: a model with a material is relit whole; one without keeps the track's fitted
    # Gaussians on the seen sides, with no relight data
    whole, _ = complete_agents(graph, scene, [1], frames, pool, DualConfig(relight=True, min_online_pixels=0.0))
    assert whole.agent(1).relight is not None


def test_a_pool_model_without_a_material_keeps_the_seen_sides_of_a_large_track(scene, graph, splat_pool):
    frames = range(scene.n_frames)
    kept, ds = complete_agents(graph, scene, [1], frames, splat_pool, DualConfig(relight=True, min_online_pixels=0.0))
    d = {d.track_id: d for d in ds}[1]
    assert kept.agent(1).relight is None and "kept on the seen sides" in d.reason
    assert splat_pool.get(d.model_id).material is None
    assert len(kept.agent(1).gaussians) > len(graph.agent(1).gaussians)  # the pool model completes the fit


def test_a_pool_model_takes_the_background_in_its_box_with_it_but_not_the_road(scene, graph, pool):
    """Background Gaussians planted in track 1's box at one of its logged poses go with the pool model; one just
    above the box's bottom (the road) and one beyond the margin stay; off, nothing goes."""
    from omniscs.agents.dual import background_in_boxes
    from omniscs.gaussians import activate, concat_params, params_from_values

    node = graph.agent(1)
    f = int(np.flatnonzero(node.present)[-1])
    pose = np.asarray(node.world_from_agent[f])
    h = float(node.size[2])
    local = np.array([[0.0, 0.0, 0.0], [0.3, 0.1, 0.5 * h + 0.2],  # in the box; above its top, within the margin
                      [0.0, 0.0, -0.5 * h + 0.05],                  # on the road under the vehicle
                      [0.0, 0.5 * float(node.size[1]) + 0.6, 0.0]])  # beside it, beyond the margin
    planted = params_from_values(torch.as_tensor(local @ pose[:3, :3].T + pose[:3, 3], dtype=torch.float32),
                                 torch.full((4, 3), 0.05), torch.full((4,), 0.9), torch.full((4, 3), 0.5),
                                 graph.sh_degree)
    g = graph.replace(background=concat_params([graph.background, planted]))
    inside = background_in_boxes(g, [1], 0.3, 0.15)
    assert inside[-4:].tolist() == [True, True, False, False]
    assert not background_in_boxes(g, [], 0.3, 0.15).any()
    frames = range(scene.n_frames)
    done, ds = complete_agents(g, scene, [1], frames, pool, DualConfig(relight_steps=5, relight_render_steps=0),
                               force="pool")
    d = {d.track_id: d for d in ds}[1]
    assert len(done.background) == len(g.background) - int(inside.sum())
    assert f"{int(inside.sum())} background Gaussians" in d.reason
    kept = activate(done.background.detached()).means.numpy()
    assert np.isclose(kept, local[2] @ pose[:3, :3].T + pose[:3, 3], atol=1e-4).all(1).any()
    off, _ = complete_agents(g, scene, [1], frames, pool, DualConfig(clear_box=False, relight_steps=5,
                                                                     relight_render_steps=0), force="pool")
    assert len(off.background) == len(g.background)
    with pytest.raises(OmniscsError):
        DualConfig(clear_floor_m=-0.1)
