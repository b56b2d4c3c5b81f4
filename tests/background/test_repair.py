"""The repair on a small fitted log with a parked box truck beside the road: holes against the world's own masks,
what the repair returns and keeps, the background stage (checkpoint, files, catalog rows, reuse, skip), and the
clear errors when nothing pins the depth."""
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.background.drnet import DRNetConfig
from omniscs.background.repair import (HoleView, RepairConfig, fill_views, prepare_views, removed_objects,
                                       repair_background)
from omniscs.errors import OmniscsError
from omniscs.nsg.config import PRESETS
from omniscs.pipeline import stages
from omniscs.pipeline.background import background_stage
from omniscs.pipeline.request import SceneRequest
from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene

TRUCK = 1
REMOVE = {"op": "remove", "track_id": TRUCK}
SMALL = RepairConfig(factor=1, roi_iterations=15, full_iterations=15, drnet=DRNetConfig(steps=30, crop=24))


def _truck_world():
    # a box truck parked 12 m ahead on the right, a car passing on the left
    agents = ({"x": 14.0, "y": -4.0, "speed": 0.0, "asset": "box_truck-0000", "size": (8.3, 2.3, 3.6)},
              {"x": 6.0, "y": 3.3, "speed": 9.0, "asset": "sedan-0011"})
    return nsg_world(agents=agents, n_frames=8, n_cameras=2, width=96, height=54)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bg")
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(PRESETS, "fast", tiny_fit_config(60))
        store = write_nsg_scene(tmp / "in", _truck_world(), "bg-test")
        plan = stages.load_plan(stages.plan_stage(store, SceneRequest(fit_preset="fast", edits=(REMOVE,)), tmp / "ws"))
        record = stages.fit_stage(store, plan, "fast", tmp / "ws")
    return store, plan, record, tmp


@pytest.mark.slow  # the module's fit (24 s) is shared with the slow tests: all of them in make test-slow
def test_the_plan_asks_for_repair_and_the_holes_cover_the_trucks_pixels(fitted):
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.observations import Observations
    from omniscs.scene import load_scene
    from omniscs.world import WorldRenderer

    store, plan, record, _ = fitted
    assert plan.background_repair == (TRUCK,) and plan.stages["background_repair"]
    scene = load_scene(store)
    graph = load_graph(record.path, scene)
    views = [(c, int(f)) for f in plan.train_frames for c in plan.cameras]
    holes = prepare_views(graph, Observations(scene, plan.cameras), removed_objects(graph, [TRUCK]), views,
                          RepairConfig(factor=1))
    assert holes.views and holes.hidden.shape == (len(graph.background),)
    renderer = WorldRenderer(scene.world)
    covered = []
    for hv in holes.views:
        truth = renderer.render_camera(hv.frame, hv.camera).instance == TRUCK
        covered.append((hv.mask & truth).sum() / max(1, truth.sum()))
        assert np.all(np.isfinite(hv.target_depth[~np.isnan(hv.target_depth)]))
        assert np.isnan(hv.target_depth[hv.mask]).all()  # no depth target inside the hole
    assert np.mean(covered) > 0.9


@pytest.mark.slow
def test_repair_keeps_the_truck_node_seeds_the_hole_and_the_counts_add_up(fitted):
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.edit import apply_graph_edits
    from omniscs.nsg.observations import Observations
    from omniscs.scene import load_scene

    store, plan, record, _ = fitted
    scene = load_scene(store)
    graph = load_graph(record.path, scene)
    views = [(c, int(f)) for f in plan.train_frames for c in plan.cameras]
    result = repair_background(graph, Observations(scene, plan.cameras), [TRUCK], views,
                               tiny_fit_config(60), SMALL)
    g = result.graph
    assert g.agent_ids == graph.agent_ids  # the truck is back where it was: edits move or remove it
    assert np.array_equal(g.agent(TRUCK).world_from_agent, graph.agent(TRUCK).world_from_agent)
    f = result.facts
    assert f["seeds"] > 0 and f["hole_views"] == len(result.views)
    assert (f["observed_pixels"] + f["plane_filled_pixels"] + f["carried_pixels"] + f["inpainted_pixels"]
            + f["unfilled_pixels"]) == f["hole_pixels"]
    assert g.background.is_finite() and result.drnet is not None and f["refit"]["iterations"] == 15
    # the road and the sidewalk around the truck are planes: they fill part of the hole, at their depth
    assert f["planes"] >= 1 and f["plane_filled_pixels"] > 0
    for hv in result.views:
        planar = hv.mask & hv.planar & ~np.isnan(hv.filled_depth)
        assert np.array_equal(hv.filled_depth[planar & hv.new], hv.plane_dist[planar & hv.new])
    seeds_only = repair_background(graph, Observations(scene, plan.cameras), [TRUCK], views, tiny_fit_config(60),
                                   RepairConfig(factor=1, refit="none", depth_method="lsq"))
    s = seeds_only.facts
    assert len(seeds_only.graph.background) == len(graph.background) - s["dropped_gaussians"] + s["seeds"]
    assert seeds_only.drnet is None and "refit" not in s
    # planes_first: the planes fill every hole pixel they reach; by default what the cleaned background covers wins
    first = repair_background(graph, Observations(scene, plan.cameras), [TRUCK], views, tiny_fit_config(60),
                              RepairConfig(factor=1, refit="none", depth_method="lsq", planes_first=True))
    for hv in first.views:
        on = hv.mask & hv.planar
        assert np.array_equal(hv.filled_depth[on], hv.plane_dist[on])
    p1 = first.facts
    assert p1["plane_filled_pixels"] >= s["plane_filled_pixels"] and p1["observed_pixels"] <= s["observed_pixels"]
    assert p1["plane_filled_pixels"] + p1["observed_pixels"] == s["plane_filled_pixels"] + s["observed_pixels"]
    # the default seeds the planes' pixels only; the paper's way also seeds every inpainted pixel
    paper = repair_background(graph, Observations(scene, plan.cameras), [TRUCK], views, tiny_fit_config(60),
                              RepairConfig(factor=1, refit="none", depth_method="lsq", seed_inpainted=True)).facts
    assert 0 < s["seeds"] < paper["seeds"] and paper["inpainted_pixels"] > 0
    removed = apply_graph_edits(g, [REMOVE])
    out = removed.render(removed.view(plan.cameras[0], plan.train_frames[0]))
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()


@pytest.mark.slow
def test_the_refit_runs_at_the_fits_learning_rates_times_refit_lr_scale(fitted, monkeypatch):
    import omniscs.background.repair as repair
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.observations import Observations
    from omniscs.scene import load_scene

    store, plan, record, _ = fitted
    scene = load_scene(store)
    graph = load_graph(record.path, scene)
    views = [(c, int(f)) for f in plan.train_frames for c in plan.cameras]
    rates = []

    def refit(graph, config, *args, **kwargs):
        rates.append(config.lr)
        return graph, []

    monkeypatch.setattr(repair, "refit", refit)
    fit = tiny_fit_config(60)
    for k in (1.0, 2.0):
        repair_background(graph, Observations(scene, plan.cameras), [TRUCK], views, fit,
                          dataclasses.replace(SMALL, depth_method="lsq", refit_lr_scale=k))
    same, doubled = rates
    assert same == fit.lr
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        assert getattr(doubled, name) == pytest.approx(2.0 * getattr(fit.lr, name))
    # the sky and the exposures are held in the refit; their rates and the means' decay stay the fit's
    assert (doubled.sky, doubled.exposure, doubled.means_final_ratio) == (fit.lr.sky, fit.lr.exposure,
                                                                          fit.lr.means_final_ratio)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(OmniscsError, match="refit_lr_scale"):
            RepairConfig(refit_lr_scale=bad)


@pytest.mark.slow  # the module's fit (24 s) is shared with the slow tests: all of them in make test-slow
def test_inpainting_the_whole_hole_with_the_embedded_network_keeps_no_observed_pixel(fitted):
    from omniscs.background.inpaintnet import SHIPPED
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.observations import Observations
    from omniscs.scene import load_scene

    if not (SHIPPED / "inpaint.safetensors").is_file():
        pytest.skip("no shipped inpainting weights")
    store, plan, record, _ = fitted
    scene = load_scene(store)
    graph = load_graph(record.path, scene)
    views = [(c, int(f)) for f in plan.train_frames for c in plan.cameras]
    config = dataclasses.replace(SMALL, inpainter="embedded", keep_observed=False, refit="none", planes=False,
                                 seed_inpainted=True)
    result = repair_background(graph, Observations(scene, plan.cameras), [TRUCK], views, tiny_fit_config(60), config)
    f = result.facts
    assert f["observed_pixels"] == 0 and f["inpainted_pixels"] > 0 and f["seeds"] > 0
    assert f["inpainted_pixels"] + f["unfilled_pixels"] == f["hole_pixels"]
    for hv in result.views:  # a view is inpainted whole or (too little context) left unsupervised whole
        assert np.array_equal(hv.new | hv.unfilled, hv.mask)
        assert np.array_equal(hv.filled[~hv.mask], hv.image[~hv.mask])


def test_fill_views_refuses_when_no_view_knows_any_depth():
    from omniscs.nsg.observations import View

    view = View(0, np.eye(4), np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), 16, 12, "CAM_FRONT")
    mask = np.zeros((12, 16), bool)
    mask[3:9, 4:12] = True
    hv = HoleView("CAM_FRONT", 0, view, np.full((12, 16, 3), 128, np.uint8), mask, np.full((12, 16), np.nan, np.float32))

    class Flat:
        name = "flat"

        def predict(self, rgb):
            return np.ones(rgb.shape[:2], np.float32)

    class Same:
        name = "same"

        def inpaint(self, rgb, mask):
            return rgb.copy()

    graph = type("G", (), {"render": None})
    with pytest.raises(OmniscsError, match="known depth"):
        fill_views([hv], graph, RepairConfig(), Same(), Flat())


@pytest.mark.slow
def test_the_background_stage_writes_a_repaired_checkpoint_its_files_and_rows_and_reuses_them(fitted):
    from omniscs.nsg.checkpoint import load_graph

    store, plan, record, tmp = fitted
    ws = tmp / "ws"
    first = background_stage(store, plan, record, ws, config=SMALL)
    assert not first.reused and first.info["repaired"] == [TRUCK]
    assert Path(first.path).parent.parent == ws / "repaired"
    graph = load_graph(first.path)
    assert TRUCK in graph.agent_ids
    repair = Path(first.path) / "repair"
    info = json.loads((repair / "repair.json").read_text())
    assert (repair / "preview.png").is_file() and info["views"]
    for v in info["views"]:
        assert all((repair / name).is_file() for name in v["files"])
    rows = first.rows["background_repairs"]
    assert catalog.validated_table("background_repairs", rows).num_rows == 1 and rows[0]["track_id"] == TRUCK
    again = background_stage(store, plan, record, ws, config=SMALL)
    assert again.reused and again.path == first.path


@pytest.mark.slow  # the module's fit (24 s) is shared with the slow tests: all of them in make test-slow
def test_the_background_stage_skips_scenes_that_need_no_repair(fitted, tmp_path):
    store, _, record, _ = fitted
    plan = stages.load_plan(stages.plan_stage(store, SceneRequest(fit_preset="fast"), tmp_path / "ws"))
    skipped = background_stage(store, plan, record, tmp_path / "ws")
    assert skipped.skipped and "nothing to repair" in skipped.info["why"]
    assert background_stage(store, plan, None, tmp_path / "ws").skipped


@pytest.mark.slow
def test_omniscs_fit_repairs_the_background_of_a_removed_truck_unless_told_not_to(fitted, tmp_path):
    from typer.testing import CliRunner

    from omniscs.cli import app

    store, _, _, _ = fitted
    runner = CliRunner()
    edit = json.dumps([REMOVE])
    base = ["fit", str(store), "--preset", "fast", "--iterations", "20", "--edit", edit, "--workspace",
            str(tmp_path / "ws")]
    on = runner.invoke(app, base + ["--out", str(tmp_path / "on")])
    assert on.exit_code == 0, on.output
    assert "background repaired" in on.output and (tmp_path / "on" / "repair" / "repair.json").is_file()
    off = runner.invoke(app, base + ["--out", str(tmp_path / "off"), "--background-repair", "off"])
    assert off.exit_code == 0, off.output
    assert "background repair off" in off.output and not (tmp_path / "off" / "repair").exists()
    bad = runner.invoke(app, base + ["--out", str(tmp_path / "bad"), "--background-repair", "maybe"])
    assert isinstance(bad.exception, OmniscsError) and "on or off" in str(bad.exception)  # main() exits 2 on it
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow
def test_generate_runs_the_background_stage_after_the_fit_and_catalogues_it(prefect_harness, tmp_path, monkeypatch):
    from flows.generate import generate_dataset

    monkeypatch.setitem(PRESETS, "fast", tiny_fit_config(20))
    store = write_nsg_scene(tmp_path / "in", _truck_world(), "bg-flow")
    ws = tmp_path / "ws"
    result = generate_dataset(RunRequest(sources=[str(store)], workspace=str(ws), run_id="repair", previews=False, fit_preset="fast",
                              edits=[REMOVE]))
    (scene,) = result["scenes"]
    assert list(scene["stages"]) == ["ingest", "plan", "fit", "background"]
    rows = catalog.query(catalog.catalog_root(ws), "SELECT track_id, depth_method, refit, seeds > 0 AS seeded "
                                                   "FROM background_repairs").to_pylist()
    assert rows == [{"track_id": TRUCK, "depth_method": "drnet", "refit": "roi", "seeded": True}]


def test_seeds_in_front_of_observed_background_are_dropped_and_the_others_kept():
    from omniscs.background.repair import consistent_seeds
    from omniscs.nsg.observations import View

    # camera at the origin looking along world +x; a solid wall 10 m away except an inpainted patch
    cam = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
    view = View(0, cam, np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), 16, 12, "CAM_FRONT")
    hv = HoleView("CAM_FRONT", 0, view, np.zeros((12, 16, 3), np.uint8), np.zeros((12, 16), bool),
                  np.full((12, 16), np.nan, np.float32))
    hv.solid_z = np.full((12, 16), 10.0)
    hv.new = np.zeros((12, 16), bool)
    hv.new[6, 8] = True  # the pixel the ray along +x meets
    points = np.array([[5.0, 0.0, 0.0],     # in front of the wall, at the inpainted pixel: kept
                       [5.0, 0.2, 0.0],     # in front of the wall where it was observed: dropped
                       [12.0, 0.2, 0.0],    # behind the wall: hidden, kept
                       [-5.0, 0.0, 0.0]])   # behind the camera: no view says anything, kept
    kept, colours = consistent_seeds(points, np.arange(4)[:, None].repeat(3, 1), [hv])
    assert colours[:, 0].tolist() == [0, 2, 3]


def _appearance_record(folder: Path, variants: list[dict]):
    """A stand-in for the appearance stage's record: its variants.json."""
    from omniscs.pipeline.records import StageRecord

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "variants.json").write_text(json.dumps(variants))
    return StageRecord("appearance", "bg-test", str(folder / "variants.json"))


def _replacing(track: int, size) -> dict:
    from omniscs.scs.appearance.compose import replace_variant
    from omniscs.nsg.edit import AgentModel

    model = AgentModel(None, np.asarray(size, dtype=np.float64), "car")
    return replace_variant("bg-test", "a000", track, model, "pm-smaller")


@pytest.mark.slow
def test_the_uncovered_stage_repairs_what_a_smaller_replacement_uncovers_as_the_background_stage_would(fitted,
                                                                                                      tmp_path):
    from omniscs.pipeline.background import uncovered_stage

    store, plan, record, tmp = fitted
    ws = tmp / "ws"
    unplanned = dataclasses.replace(plan, background_repair=(), stages={**plan.stages, "background_repair": False})
    sedan = _appearance_record(tmp_path / "a", [_replacing(TRUCK, (4.4, 1.8, 1.5))])
    repaired = uncovered_stage(store, unplanned, record, [sedan], ws, config=SMALL)
    assert repaired.stage == "uncovered" and not repaired.skipped and repaired.info["repaired"] == [TRUCK]
    assert repaired.rows["background_repairs"][0]["track_id"] == TRUCK
    # the same objects on the same graph are one repair, whichever stage asks for it
    planned = background_stage(store, plan, record, ws, config=SMALL)
    assert planned.reused and planned.path == repaired.path and planned.key == repaired.key
    # nothing uncovered: a covering replacement (a bus over the truck), an insert, no variants, or what the
    # background stage already repaired
    bus = _appearance_record(tmp_path / "b", [_replacing(TRUCK, (11.0, 2.5, 3.6))])
    assert uncovered_stage(store, unplanned, record, [bus], ws, config=SMALL).skipped
    assert uncovered_stage(store, unplanned, record, [None], ws, config=SMALL).skipped
    done = uncovered_stage(store, plan, planned, [sedan], ws, config=SMALL)
    assert done.skipped and "nothing to repair" in done.info["why"]


def test_only_edits_that_uncover_a_large_static_object_name_it_for_repair(tmp_path):
    from omniscs.pipeline.background import uncovered_objects
    from omniscs.scene import load_scene
    from omniscs.scs.appearance.compose import insert_variant
    from omniscs.nsg.edit import AgentModel

    scene = load_scene(write_nsg_scene(tmp_path / "in", _truck_world(), "bg-test"))
    car = AgentModel(None, np.array([4.4, 1.8, 1.5]), "car")
    insert = insert_variant("bg-test", "a001", 9, car, "pm-smaller", 20.0, 3.0, 0.0, 0.0)
    moving_car = _replacing(2, (2.0, 1.0, 1.0))  # track 2 passes by: its background was seen
    record = _appearance_record(tmp_path / "a", [insert, moving_car, _replacing(TRUCK, (4.4, 1.8, 1.5))])
    assert uncovered_objects(scene, [record]) == (TRUCK,)
    assert uncovered_objects(scene, [_appearance_record(tmp_path / "b", [insert, moving_car])]) == ()



def test_annotate_composes_only_the_variants_that_uncover_on_the_repaired_graph(monkeypatch, tmp_path):
    from omniscs.pipeline import annotate
    from omniscs.scene import load_scene

    monkeypatch.setattr(annotate, "compose_variant", lambda graph, variant, resolve: graph)
    monkeypatch.setattr(annotate, "node_model_resolver", lambda graph: None)
    scene = load_scene(write_nsg_scene(tmp_path / "in", _truck_world(), "bg-test"))
    variants = [dict(_replacing(TRUCK, (4.4, 1.8, 1.5)), variant_id="a001"),
                dict(_replacing(TRUCK, (11.0, 2.5, 3.6)), variant_id="a002")]
    uncovering = {v["variant_id"] for v in variants if TRUCK in annotate.variant_uncovers(scene, v)}
    assert uncovering == {"a001"}
    compose = annotate.appearance_composer("fitted graph", ("repaired graph", uncovering))
    assert [compose(v) for v in variants] == ["repaired graph", "fitted graph"]
    assert annotate.appearance_composer("fitted graph")(variants[0]) == "fitted graph"
