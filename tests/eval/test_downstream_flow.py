"""The downstream flows on a dataset in a workspace: the proxy planner fine-tuned and evaluated (base vs
fine-tuned, behaviour-SCS and original examples) into the catalog, reused on a rerun; datasets found from the
generate run that made them; an external job's metrics read back, a crash recorded as a failed model.

The dataset is laid out as the dataset stage lays it out (card, one store per variant with variant.json), but its
variant stores are copies of the source store: the downstream code reads only their boxes' categories and map,
so the test spares rendering them. ``fake_uniad.py`` stands in for an external UniAD process."""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

from omniscs import catalog
from omniscs.errors import OmniscsError, ValidationError
from omniscs.pipeline import downstream as d
from omniscs.pipeline import layout

FAKE = str(Path(__file__).with_name("fake_uniad.py"))


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    from omniscs.pipeline.request import SceneRequest
    from omniscs.pipeline.stages import behavior_stage, ingest_stage, load_plan, plan_stage
    from omniscs.scene import SyntheticSource, load_scene
    from omniscs.scs.behavior import traffic_from_scene
    from omniscs.scs.behavior.solution import solve_ego

    ws = tmp_path_factory.mktemp("downstream") / "ws"
    scene_rec = ingest_stage(SyntheticSource(template="t_junction", seed=320_000, n_frames=50, n_cameras=1,
                                             width=32, height=18), ws)
    request = SceneRequest(behavior_variants=3, behavior_preset="fast", previews=False)
    plan = load_plan(plan_stage(scene_rec.path, request, ws))
    behaved = behavior_stage(scene_rec.path, plan, 3, ws, "fast")
    scene = load_scene(scene_rec.path)
    traffic = traffic_from_scene(scene)
    root = layout.dataset_folder(ws, "ds-test")
    variants = []
    for spec in json.loads(Path(behaved.path).read_text()):
        store_id = f"{scene.scene_id}-{spec['variant_id']}"
        shutil.copytree(scene_rec.path, root / "scenes" / store_id)
        solution = solve_ego(spec, traffic).to_dict()
        (root / "scenes" / store_id / "variant.json").write_text(json.dumps({"variant": spec,
                                                                            "ego_solution": solution}))
        variants.append({"scene_id": scene.scene_id, "store_id": store_id, "variant_id": spec["variant_id"],
                         "ego_solved": solution["solved"]})
    (root / "dataset.json").write_text(json.dumps({"dataset_id": "ds-test", "variants": variants,
                                                   "counts": {"variants": len(variants)}}))
    return ws


def _two_base_logs(monkeypatch, tmp_path):
    """The base planner's rehearsal remade from a record naming two of its training logs instead of 40 (time)."""
    real = d.base_planner_logs
    from omniscs.eval.planner import DEFAULT_PLANNER

    record = json.loads((DEFAULT_PLANNER / "training.json").read_text())
    seeds = record["data"]["train_seeds"]
    (tmp_path / "training.json").write_text(json.dumps({"data": {**record["data"],
                                                                 "train_seeds": [seeds[0], seeds[0] + 1]}}))
    monkeypatch.setattr(d, "base_planner_logs", lambda base_path, progress=None: real(tmp_path))


@pytest.mark.slow
def test_finetune_evaluate_catalogues_base_and_fine_tuned_on_both_splits_and_reuses_the_model(prefect_harness,
                                                                                            workspace, monkeypatch,
                                                                                            tmp_path):
    from flows.downstream import finetune_evaluate

    _two_base_logs(monkeypatch, tmp_path)
    first = finetune_evaluate(["ds-test"], workspace=str(workspace), run_id="ft1")
    second = finetune_evaluate(["ds-test"], workspace=str(workspace), run_id="ft2")
    tuned = first["models"][0]["model_id"]
    assert tuned.startswith("proxy-planner-") and second["models"][0]["model_id"] == tuned
    # rehearsal: the logs mixed in are the base's own training logs (two here), not the dataset's source log
    training = json.loads((layout.downstream_folder(workspace, tuned) / "planner" / "training.json").read_text())
    assert training["log_source"] == "base's training logs (rehearsal)"
    assert training["log_examples"] == len(d.base_planner_logs(None)) > 0
    root = catalog.catalog_root(workspace)
    models = catalog.query(root, "SELECT model_id, status, n_examples FROM downstream_models").to_pylist()
    assert models == [{"model_id": tuned, "status": "trained", "n_examples": models[0]["n_examples"]}]
    assert models[0]["n_examples"] > 0
    rows = catalog.query(root, "SELECT model_id, split, metric, horizon, convention, value, status "
                               "FROM evaluations_by_run WHERE run_id = 'ft1'").to_pylist()
    got = {(r["model_id"], r["split"], r["metric"], r["horizon"], r["convention"]) for r in rows}
    for model in (d.BASE_MODEL_ID, tuned):
        for split in ("behaviour-SCS", "original"):
            for metric in ("L2", "collision"):
                assert (model, split, metric, "3s", "uniad") in got
    assert all(r["status"] == "ok" and r["value"] is not None and r["value"] >= 0 for r in rows)
    run = catalog.query(root, "SELECT status, flow_run_id FROM runs WHERE run_id = 'ft1'").to_pylist()[0]
    assert run["status"] == "completed" and run["flow_run_id"]
    # the run's comparison plot: base against fine-tuned
    assert first["plot"] == str(layout.evaluation_folder(workspace, "ft1") / "comparison.png")
    assert _png_shape(first["plot"])[0] > 200


def _png_shape(path) -> tuple:
    import cv2

    image = cv2.imread(str(path))
    assert image is not None, f"{path} is not an image"
    return image.shape


@pytest.mark.slow
def test_datasets_are_found_from_the_generate_run_that_made_them(workspace):
    root = catalog.catalog_root(workspace)
    catalog.write_rows(root, "datasets", "gen-1", [{
        "dataset_id": "ds-test", "path": str(layout.dataset_folder(workspace, "ds-test")), "content_hash": "x" * 12,
        "reused": False, "scene_ids": ["s"], "n_scenes": 1, "n_variants": 3, "n_frames": 50, "n_samples": 0,
        "n_annotations": 0, "n_ego_solved": 3, "fidelity_psnr": None, "fidelity_ssim": None,
        "fidelity_masked_psnr": None, "feature_drift": None, "card_path": "c", "preview_path": "p",
        "config_json": "{}"}])
    from omniscs.pipeline.stages import catalog_run_stage

    catalog_run_stage("gen-1", workspace, "generate_dataset", "completed", 0, 1, 1, {},
                      flow_run_id="7c0e6f3a-0000-4000-8000-000000000001")
    assert d.datasets_of_flow_run(workspace, "prefect.flow-run.7c0e6f3a-0000-4000-8000-000000000001") == ["ds-test"]
    with pytest.raises(OmniscsError, match="made no dataset"):
        d.datasets_of_flow_run(workspace, "prefect.flow-run.00000000-0000-4000-8000-000000000000")
    with pytest.raises(ValidationError, match="not a flow run id"):
        d.datasets_of_flow_run(workspace, "x' OR '1'='1")


@pytest.mark.slow
def test_an_external_job_is_read_back_and_a_crash_is_a_failed_model(prefect_harness, workspace):
    from flows.downstream import finetune_evaluate

    template = "{python} " + FAKE + " {config} {dataset_root}"
    out = finetune_evaluate(["ds-test"], model="external", workspace=str(workspace), run_id="ext1",
                            external_template=template, external_values={"python": sys.executable, "config": "ok"},
                            external_export=None)
    model = out["models"][0]["model_id"]
    root = catalog.catalog_root(workspace)
    rows = catalog.query(root, "SELECT task, metric, class_name, horizon, value FROM evaluations "
                               f"WHERE model_id = '{model}'").to_pylist()
    by = {(r["task"], r["metric"], r["class_name"], r["horizon"]): r["value"] for r in rows}
    assert by[("detection", "NDS", "", "")] == 0.4976 and by[("detection", "AP", "car", "")] == 0.573
    assert by[("planning", "L2", "", "3.0s")] == 1.8131
    assert _png_shape(out["plot"])[0] > 200  # what the job printed, drawn
    with pytest.raises(Exception, match="exit code 3"):
        finetune_evaluate(["ds-test"], model="external", workspace=str(workspace), run_id="ext2",
                          external_template=template, external_values={"python": sys.executable, "config": "crash"},
                          external_export=None)
    failed = catalog.query(root, "SELECT m.status, m.error, r.status AS run_status FROM downstream_models_by_run m "
                                 "JOIN runs r USING (run_id) WHERE m.run_id = 'ext2'").to_pylist()
    assert failed and failed[0]["status"] == "failed" and "CUDA out of memory" in failed[0]["error"]
    assert failed[0]["run_status"] == "failed"


@pytest.mark.slow
def test_the_evaluate_flow_and_bad_requests(prefect_harness, workspace):
    from flows.downstream import evaluate, finetune_evaluate

    out = evaluate(d.BASE_MODEL_ID, ["ds-test"], workspace=str(workspace), run_id="ev1")
    assert out["model_id"] == d.BASE_MODEL_ID and _png_shape(out["plot"])[0] > 200
    with pytest.raises(ValidationError, match="no downstream model"):
        evaluate("proxy-planner-000000000000", ["ds-test"], workspace=str(workspace), run_id="ev2")
    with pytest.raises(ValidationError, match="not in workspace"):
        finetune_evaluate(["ds-missing"], workspace=str(workspace), run_id="ev3")
    with pytest.raises(ValidationError, match="model must be one of"):
        finetune_evaluate(["ds-test"], model="uniad", workspace=str(workspace), run_id="ev4")
    with pytest.raises(ValidationError, match="name the datasets"):
        finetune_evaluate(None, workspace=str(workspace), run_id="ev5")


@pytest.mark.slow
def test_the_finetune_command_refuses_unknown_datasets_and_options_in_one_line(workspace):
    import subprocess

    base = [sys.executable, "-c", "from omniscs.cli import main; main()", "finetune"]
    for args, message in ((["ds-missing", "--workspace", str(workspace)], "not in workspace"),
                          (["ds-test", "--model", "uniad", "--workspace", str(workspace)], "proxy or external"),
                          (["ds-test", "--model", "external", "--workspace", str(workspace)], "--external-template")):
        proc = subprocess.run(base + args, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and message in proc.stderr and proc.stderr.strip().count("\n") == 0, proc.stderr


def test_the_base_planners_training_logs_are_remade_from_its_record_and_a_base_without_one_has_none(tmp_path):
    (tmp_path / "training.json").write_text(json.dumps({"data": {"templates": ["straight", "t_junction"],
                                                                 "train_seeds": [5000, 5002], "n_frames": 60}}))
    examples = d.base_planner_logs(tmp_path)
    scenes = sorted({e.scenario.scenario_id.split("/")[0] for e in examples})
    assert scenes == ["syn-straight-s5000", "syn-straight-s5002", "syn-t_junction-s5001"]  # templates in turn
    assert examples and all(e.sample.trajectory.shape == (6, 2) and e.sample.mask.all() for e in examples)  # logs: known
    (tmp_path / "training.json").write_text(json.dumps({"command": "someone's own planner"}))
    assert d.base_planner_logs(tmp_path) == []
    assert d.base_planner_logs(tmp_path / "missing") == []
