"""``bench agents``' report: Table 4's summary, the targets and the Markdown, from hand-made rows; matching ranks
queries against a pool."""
import numpy as np
import pytest
import torch

from omniscs.bench.agents import ARMS, MATCH_LEVELS, TABLE4_EDITS, _targets, agents_markdown, run_matching, table4_summary


def _rows():
    rows = []
    for name, _ in TABLE4_EDITS:
        for arm, psnr in zip(ARMS, (15.0, 18.5, 17.0, 18.5, 19.0)):
            for track, shift in ((1, -0.5), (2, 0.5)):
                rows.append({"scene_id": "s", "track_id": track, "edit": name, "arm": arm, "n_views": 3,
                             "masked_psnr": psnr + shift, "masked_ssim": 0.5})
    rows.append({"scene_id": "s", "track_id": 3, "edit": "rotate 90°", "arm": "naive", "n_views": 0,
                 "masked_psnr": None, "masked_ssim": None})  # no view shows it: left out, not a zero
    return rows


def test_the_summary_and_targets_follow_the_rows():
    summary = table4_summary(_rows())
    cell = next(s for s in summary if s["edit"] == "rotate 90°" and s["arm"] == "dual")
    assert cell["agents"] == 2 and cell["masked_psnr"] == 18.5
    naive = next(s for s in summary if s["edit"] == "rotate 90°" and s["arm"] == "naive")
    assert naive["agents"] == 2 and naive["masked_psnr"] == 15.0
    matching = [{"embedder": "e", "cue": "appearance", "level": lv, "top1": 0.5, "top5": 0.9, "queries": 4}
                for lv, _ in MATCH_LEVELS]
    targets = _targets(matching, summary, [{"seconds": 2.0}, {"seconds": 4.0}])
    assert targets["dual_gain_db"]["gains"] == {"rotate 90°": 3.5, "rotate 180°": 3.5, "rotate 270°": 3.5}
    assert targets["dual_gain_db"]["met"] and not targets["matching_top1_at_target_level"]["met"]
    assert targets["build_seconds"]["median"] == 3.0 and targets["build_seconds"]["met"]
    report = {"machine": {"cpus": 2, "platform": "x", "load_average_start": [1.0, 1, 1],
                          "load_average_end": [2.0, 2, 2]},
              "config": {"preset": "fast", "scenes": ["straight:1"]}, "targets": targets, "table4": summary,
              "matching": matching, "decisions": [],
              "pool": {"size": 3, "by_category": {"car": 3}, "quality_db_median": 18.0,
                       "build_seconds_per_model": [2.0, 4.0], "growth": []}}
    text = agents_markdown(report)
    assert "| rotate 90° | 15.00 / 0.500 | 18.50 / 0.500 | 17.00 / 0.500 | 18.50 / 0.500 | 19.00 / 0.500 |" in text
    assert "goal 3 dB each: met" in text and "goal 95 %: NOT met" in text


def test_matching_ranks_keyframe_queries_first_within_their_category(tmp_path):
    from omniscs.agents.matching import ColourHistogram, crop_square
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.agents.pool import Pool
    from omniscs.world.assets import build_asset

    pool = Pool(tmp_path / "pool")
    for aid in ("sedan-0050", "suv-0040", "bus-0013"):
        a = build_asset(aid)
        params, _ = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, 1000, 0)
        pool.add(params, a.category, "mesh", aid)
    table = pool.table()
    queries = []
    for m in table.itertuples():
        k = pool.keyframes(m.model_id)[7]
        queries.append((crop_square(np.ascontiguousarray(k[..., :3]), k[..., 3] / 255.0), m.category, m.model_id,
                        np.array([m.length, m.width, m.height])))
    rows = run_matching(queries, pool, [ColourHistogram()])
    assert len(rows) == 3 * len(MATCH_LEVELS)  # appearance, + box shape, + box shape with full-resolution keyframes
    clean = [r for r in rows if r["level"] == "clean"]
    assert all(r["top1"] == 1.0 and r["top5"] == 1.0 for r in clean)
    assert all(0.0 <= r["top1"] <= r["top5"] <= 1.0 for r in rows)


def test_swapping_a_worlds_vehicles_keeps_them_on_the_same_ground():
    from omniscs.bench.agents import swap_vehicles
    from omniscs.taxonomy import VEHICLE_CATEGORIES
    from omniscs.world import build_asset, generate_world
    from omniscs.world.assets import list_asset_ids

    world = generate_world("straight", 81)
    cars = list_asset_ids("sedan", "pool")[:2]
    new, swapped = swap_vehicles(world, {"car": list(cars)})
    before = {a.track_id: a for a in world.agents}
    assert sorted(swapped.values()) == sorted(cars) and len(new.agents) == len(world.agents)
    for track in new.agents:
        old = before[track.track_id]
        if track.track_id not in swapped:  # the rest of the world is untouched
            assert track.asset_id == old.asset_id and np.array_equal(track.poses, old.poses)
            continue
        assert old.category == "car" and old.category in VEHICLE_CATEGORIES
        assert np.allclose(track.size, build_asset(swapped[track.track_id]).size)
        bottom = lambda t: t.poses[:, :3, 3] - 0.5 * t.size[2] * t.poses[:, :3, 2]  # noqa: E731
        assert np.allclose(bottom(track), bottom(old))


def test_msnet_learns_only_from_pool_assets_no_benchmark_uses():
    from omniscs.bench.agents import POOL_QUOTA, pool_ids
    from omniscs.training.msnet import unbenched_pool_assets
    from omniscs.world.assets import asset_split, list_asset_ids

    quota = tuple(POOL_QUOTA.items())
    extra, bench = set(unbenched_pool_assets(quota)), set(pool_ids(quota))
    assert extra and not extra & bench and all(asset_split(a) == "pool" for a in extra)
    assert extra | bench == {a for kind, _ in quota for a in list_asset_ids(kind, "pool")}


@pytest.mark.slow
def test_the_matching_only_benchmark_writes_its_report(tmp_path):
    import json

    from omniscs.bench.agents import quick_config, run_matching_benchmark

    report = run_matching_benchmark(tmp_path / "out", tmp_path / "ws", quick_config())
    written = json.loads((tmp_path / "out" / "agents" / "matching.json").read_text())
    assert written["target"] == report["target"] and 0 <= report["target"]["top1"] <= 1
    levels = {r["level"] for r in report["matching"]}
    assert levels == {lv for lv, _ in MATCH_LEVELS} and report["pool_size"] == 12
    assert "## Matching" in (tmp_path / "out" / "agents" / "matching.md").read_text()


def test_multi_view_matching_scores_a_query_as_the_dual_strategy_scores_a_track(tmp_path):
    from omniscs.agents.matching import ColourHistogram, crop_square, match_scores
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.agents.pool import Pool
    from omniscs.bench.agents import _matching_lines
    from omniscs.world.assets import build_asset

    pool = Pool(tmp_path / "pool")
    for aid in ("sedan-0050", "sedan-0051", "sedan-0052", "suv-0040"):
        a = build_asset(aid)
        params, _ = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, 1000, 0)
        pool.add(params, a.category, "mesh", aid)
    table = pool.table()

    def crop(model_id, k):
        key = pool.keyframes(model_id)[k]
        return crop_square(np.ascontiguousarray(key[..., :3]), key[..., 3] / 255.0)

    # each query: its model's keyframe first, then zero to two keyframes of the next model of its category (views
    # that disagree, so the mean over views decides), views of unequal count
    rows_ = list(table.itertuples())
    queries = []
    for i, m in enumerate(rows_):
        same = [r for r in rows_ if r.category == m.category]
        other = same[(same.index(m) + 1) % len(same)].model_id
        more = np.stack([crop(other, k) for k in (3, 20)[:i % 3]]) if i % 3 else np.zeros((0, 64, 64, 3), np.uint8)
        queries.append((crop(m.model_id, 7), m.category, m.model_id, np.array([m.length, m.width, m.height]), more))
    embedder = ColourHistogram()
    rows = run_matching(queries, pool, [embedder], size_noise=0.0)
    multi = [r for r in rows if "views" in r["cue"]]
    assert len(rows) == 4 * len(MATCH_LEVELS) and len(multi) == len(MATCH_LEVELS)
    assert multi[0]["cue"] == "appearance + box shape, up to 3 views"
    assert multi[0]["queries_by_views"] == {"3": 1, "2": 1, "1": 2}
    # undegraded, the ranking is the pipeline's (match_scores over the same crops), gated by category
    tracks, models, scores, cats = match_scores({i: np.concatenate([q[0][None], q[4]]) for i, q in enumerate(queries)},
                                                {i: q[3] for i, q in enumerate(queries)}, pool, embedder)
    top1 = [models[np.argmax(np.where(cats == q[1], scores[i], -np.inf))] == q[2] for i, q in enumerate(queries)]
    clean = next(r for r in multi if r["level"] == "clean")
    assert clean["top1"] == pytest.approx(np.mean(top1))
    assert clean["top1"] < next(r for r in rows if r["level"] == "clean" and r["cue"] == "appearance")["top1"] == 1.0
    text = "\n".join(_matching_lines(rows))
    assert "| colour histogram + box shape, up to 3 views |" in text and "2 with 1" in text


# ----------------------------------------------------------------------------- what limits the pool arm
def test_the_limits_table_averages_the_agents_that_have_every_arm():
    from omniscs.bench.agents import LIMIT_EDITS, LIMITS, _limits_lines, limits_summary

    rows, limits = [], []
    for tid, base in ((1, 12.0), (2, 14.0), (3, 10.0)):
        for arm, add in (("naive", 0.0), ("pool", 1.0), ("pool in-pool", 1.5)):
            rows.append({"scene_id": "s", "track_id": tid, "edit": "rotate 90°", "arm": arm, "masked_psnr": base + add})
        for k, arm in enumerate(LIMITS):
            if tid == 3 and k == 2:
                continue  # an agent missing one ceiling is left out of every column, not averaged unevenly
            limits.append({"scene_id": "s", "track_id": tid, "edit": "rotate 90°", "arm": arm,
                           "masked_psnr": base + 2.0 + k})
    summary = limits_summary(limits, rows)
    assert [r["edit"] for r in summary] == list(LIMIT_EDITS)
    r90 = summary[0]
    assert r90["agents"] == 2 and r90["naive"] == 13.0 and r90["pool in-pool"] == 14.5
    assert r90[LIMITS[0]] == 15.0 and r90[LIMITS[2]] == 17.0
    assert summary[1]["agents"] == 0 and summary[1]["naive"] is None
    decisions = [{"scene_id": "s", "track_id": 1, "arm": "own model", "model_id": "pm-a"},
                 {"scene_id": "s", "track_id": 2, "arm": "own model", "model_id": "pm-b"},
                 {"scene_id": "s", "track_id": 1, "arm": "pool in-pool", "strategy": "pool", "model_id": "pm-a"},
                 {"scene_id": "s", "track_id": 2, "arm": "pool in-pool", "strategy": "pool", "model_id": "pm-c"}]
    text = "\n".join(_limits_lines({"limits": summary, "decisions": decisions}))
    assert "| rotate 90° | 2 | 13.00 | 14.00 | 14.50 | 15.00 | 16.00 | 17.00 |" in text
    assert "| rotate 180° | 0 | n/a |" in text
    assert "picked the own model for 1 of 2 agents" in text
    assert _limits_lines({"decisions": []}) == []  # a report made before the table


@pytest.fixture(scope="module")
def tiny_graph(tmp_path_factory):
    from omniscs.nsg.init import initial_graph
    from omniscs.nsg.observations import Observations
    from omniscs.plan import make_plan
    from omniscs.scene import load_scene
    from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene

    scene = load_scene(write_nsg_scene(tmp_path_factory.mktemp("limits") / "scene", nsg_world(n_frames=4)))
    config = tiny_fit_config()
    return initial_graph(scene, make_plan(scene, None, config.plan), config, Observations(scene))


def test_the_oracle_colour_fit_moves_the_vehicle_towards_the_truth(tiny_graph):
    from types import SimpleNamespace

    from omniscs.bench.agents import truth_fitted
    from omniscs.quality import psnr
    from omniscs.render.sh import rgb_to_sh_dc

    node = tiny_graph.agents[0]
    f = int(np.flatnonzero(node.present)[0])
    cam = tiny_graph.cameras[0].name
    red = node.gaussians
    red = type(red)(red.means, red.quats, red.log_scales, red.opacity_logits,
                    rgb_to_sh_dc(torch.tensor([[0.9, 0.1, 0.1]]).expand(len(red), 3)), torch.zeros_like(red.sh_rest))
    truth_graph = tiny_graph.replace(agents=tuple(a.with_changes(gaussians=red) if a.track_id == node.track_id else a
                                                  for a in tiny_graph.agents))
    alone = truth_graph.replace(agents=(truth_graph.agent(node.track_id),))
    mask = alone.render(alone.view(cam, f)).alpha.reshape(-1).numpy() > 0.5
    view = truth_graph.view(cam, f)
    rgb = (truth_graph.render(view).rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    gt = SimpleNamespace(rgb=rgb, instance=np.where(mask.reshape(rgb.shape[:2]), node.track_id, -1))
    assert mask.sum() > 20
    target, m = torch.from_numpy(rgb.astype(np.float32) / 255), torch.from_numpy(gt.instance == node.track_id)
    before = psnr(tiny_graph.render(view).rgb, target, m)
    fitted = truth_fitted(tiny_graph, node.track_id, [(f, cam, gt)], steps=60)
    after = psnr(fitted.render(view).rgb, target, m)
    assert np.isfinite(after) and after > before + 5.0, (before, after)
    assert fitted.background is tiny_graph.background  # only the vehicle's colours change


def test_the_dual_arm_models_360_degrees_only_where_the_plan_of_the_edit_alone_does(tmp_path):
    """Table 4's dual arm is what the product renders for a request with one edit: the plan turns the agents stage
    on for a turn of more than 45 degrees and the overturn, not for the translations (the fitted node renders
    those)."""
    from omniscs.bench.agents import dual_needs_360
    from omniscs.edits import edit_from_dict
    from omniscs.scene import load_scene
    from tests.conftest import write_tiny_scene

    scene = load_scene(write_tiny_scene(tmp_path / "s", n_frames=4, n_tracks=2))
    planned = {name: dual_needs_360(scene, edit_from_dict({**spec, "track_id": 1})) for name, spec in TABLE4_EDITS}
    assert planned == {"translate 2.0 m": False, "translate 3.5 m": False, "rotate 90°": True, "rotate 180°": True,
                       "rotate 270°": True, "overturned": True}
    assert dual_needs_360(scene, edit_from_dict({"op": "rotate", "track_id": 1, "yaw_deg": 30.0})) is False
