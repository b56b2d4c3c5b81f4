"""generate_dataset with annotate: every stage from ingest to the dataset, catalogued; a rerun reuses everything
and gives the same dataset id; `omniscs dataset info` and `export` read what was built."""
from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene
from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.cli import app
from omniscs.errors import OmniscsError
from omniscs.nsg.config import PRESETS

AGENTS = ({"x": 14.0, "y": 0.0, "speed": 4.0, "asset": "sedan-0003"},
          {"x": 4.0, "y": 3.3, "speed": 9.0, "asset": "sedan-0011"})


@pytest.fixture(scope="module")
def built(prefect_harness, tmp_path_factory):
    from flows.generate import generate_dataset

    root = tmp_path_factory.mktemp("flow")
    store = write_nsg_scene(root / "in", nsg_world(agents=AGENTS, n_frames=20, n_cameras=1, width=96, height=54))
    mp = pytest.MonkeyPatch()
    mp.setitem(PRESETS, "fast", tiny_fit_config(40))
    try:
        # The tiny world's adversary does not reach the ego: its one variant fails the gates and is kept on request.
        kwargs = dict(workspace=str(root / "ws"), previews=False, fit_preset="fast", behavior_variants=1,
                      behavior_preset="fast", annotate=True, keep_failed=True, variant_budget=1)
        first = generate_dataset(RunRequest(sources=[str(store)], run_id="ds1", **kwargs))
        second = generate_dataset(RunRequest(sources=[str(store)], run_id="ds2", **kwargs))
    finally:
        mp.undo()
    return root / "ws", first, second


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_the_flow_builds_a_catalogued_dataset_of_every_variant(built):
    ws, first, _ = built
    assert first["dataset_id"].startswith("ds-") and Path(first["dataset_path"]).is_dir()
    stages = first["scenes"][0]["stages"]
    assert stages["annotate"]["info"]["n_variants"] == 1 and not stages["annotate"]["skipped"]
    root = catalog.catalog_root(ws)
    d = catalog.query(root, "SELECT dataset_id, n_variants, n_samples, n_annotations, fidelity_psnr FROM datasets_by_run "
                            "WHERE run_id = 'ds1'").to_pylist()
    assert d and d[0]["dataset_id"] == first["dataset_id"] and d[0]["n_samples"] > 0 and d[0]["fidelity_psnr"] > 10
    n = catalog.query(root, "SELECT count(*) AS n FROM samples s JOIN variants v USING (scene_id, variant_id)")
    assert n.to_pylist()[0]["n"] == d[0]["n_samples"]
    a = catalog.query(root, "SELECT count(*) AS n FROM annotations WHERE dataset_id = "
                            f"'{first['dataset_id']}'").to_pylist()[0]["n"]
    assert a == d[0]["n_annotations"] > 0


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_a_variant_that_fails_the_gates_is_catalogued_with_its_reasons_and_marked_in_the_card(built):
    ws, first, _ = built
    root = catalog.catalog_root(ws)
    (row,) = catalog.query(root, "SELECT passed_gates, gate_reasons FROM variants").to_pylist()
    assert row["passed_gates"] is False and row["gate_reasons"][0].startswith("no collision")
    (d,) = catalog.query(root, "SELECT n_requested, n_rejected, n_failed_kept, warnings FROM datasets").to_pylist()
    assert (d["n_requested"], d["n_rejected"], d["n_failed_kept"]) == (1, 1, 1)
    assert "0 of 1 requested behaviour variant(s) passed the quality gates (1 tried)" in d["warnings"]
    card = (Path(first["dataset_path"]) / "README.md").read_text()
    assert "**Warnings**" in card and "no collision within the horizon" in card
    info = CliRunner().invoke(app, ["dataset", "info", first["dataset_id"], "--workspace", str(ws)])
    assert "behaviour 0 of 1 requested passed, 1 rejected, 1 tried" in " ".join(info.output.split())


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_a_run_none_of_whose_variants_passes_writes_no_dataset_and_says_why(built):
    from flows.generate import generate_dataset

    ws, first, _ = built
    before = sorted(p.name for p in (ws / "datasets").iterdir())
    mp = pytest.MonkeyPatch()
    mp.setitem(PRESETS, "fast", tiny_fit_config(40))
    try:
        with pytest.raises(OmniscsError, match=r"no variant passed the quality gates \(1 rejected: .*no collision"):
            generate_dataset(RunRequest(sources=[first["scenes"][0]["stages"]["ingest"]["path"]], run_id="ds3",
                                        workspace=str(ws), previews=False,
                                        fit_preset="fast", behavior_variants=1, behavior_preset="fast",
                                        annotate=True, variant_budget=1))
    finally:
        mp.undo()
    assert sorted(p.name for p in (ws / "datasets").iterdir()) == before
    (run,) = catalog.query(catalog.catalog_root(ws), "SELECT status, error FROM runs_by_run WHERE run_id = 'ds3'"
                           ).to_pylist()
    assert run["status"] == "failed" and "quality gates" in run["error"]


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_a_rerun_reuses_every_stage_and_gives_the_same_dataset(built):
    _, first, second = built
    assert second["dataset_id"] == first["dataset_id"]
    assert all(r["reused"] for name, r in second["scenes"][0]["stages"].items() if not r["skipped"])


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_dataset_info_and_export_read_what_was_built(built, tmp_path):
    ws, first, _ = built
    info = CliRunner().invoke(app, ["dataset", "info", first["dataset_id"], "--workspace", str(ws)])
    assert info.exit_code == 0, info.output
    assert first["dataset_id"] in info.output and "preview.png" in info.output
    out = tmp_path / "nusc"
    exported = CliRunner().invoke(app, ["dataset", "export", first["dataset_path"], "--format", "nuscenes",
                                        "--out", str(out)])
    assert exported.exit_code == 0, exported.output
    assert (out / "v1.0-trainval" / "sample_annotation.json").is_file()


def test_a_dataset_is_refused_without_a_fit_or_variants(prefect_harness, tmp_path):
    from flows.generate import generate_dataset

    with pytest.raises(OmniscsError, match="fit preset"):
        generate_dataset(dict(sources=["syn:straight:0"], workspace=str(tmp_path), behavior_variants=1, annotate=True))
    result = CliRunner().invoke(app, ["dataset", "info", "no-such-set", "--workspace", str(tmp_path)])
    assert isinstance(result.exception, OmniscsError) and "is not a dataset" in str(result.exception)


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_dataset_export_for_uniad_takes_location_box_convention_and_val_scenes(built, tmp_path):
    import pickle

    _, first, _ = built
    stores = sorted(p.name for p in (Path(first["dataset_path"]) / "scenes").iterdir())
    out = tmp_path / "uniad"
    exported = CliRunner().invoke(app, ["dataset", "export", first["dataset_path"], "--format", "uniad",
                                        "--out", str(out), "--location", "singapore-onenorth",
                                        "--box-convention", "v2", "--val-scene", stores[0]])
    assert exported.exit_code == 0, exported.output
    assert (out / "nuscenes" / "maps" / "expansion" / "singapore-onenorth.json").is_file()
    with open(out / "infos" / "nuscenes_infos_temporal_val.pkl", "rb") as f:
        val = pickle.load(f)["infos"]
    with open(out / "infos" / "nuscenes_infos_temporal_train.pkl", "rb") as f:
        train = pickle.load(f)["infos"]
    assert val and len({i["scene_token"] for i in val}) == 1
    assert len({i["scene_token"] for i in train}) == len(stores) - 1
    wrong = CliRunner().invoke(app, ["dataset", "export", first["dataset_path"], "--format", "nuscenes",
                                     "--out", str(tmp_path / "n2"), "--box-convention", "v2"])
    assert isinstance(wrong.exception, OmniscsError) and "uniad only" in str(wrong.exception)
    assert not (tmp_path / "n2").exists()


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_the_logged_views_are_replayed_once_per_graph_and_read_by_every_annotate_run(built):
    from omniscs.annotate import AnnotateConfig
    from omniscs.annotate.scene import read_rows
    from omniscs.pipeline import stages
    from omniscs.pipeline.records import StageRecord

    ws, first, _ = built
    manifests = list((ws / "replays").glob("*/replay-*/stage.json"))
    assert len(manifests) == 1
    made = manifests[0].stat().st_mtime_ns
    rec = {name: StageRecord.from_dict(r) for name, r in first["scenes"][0]["stages"].items()}
    again = stages.annotate_stage(rec["ingest"].path, stages.load_plan(rec["plan"]), rec["fit"], rec["behavior"], ws,
                                  config=AnnotateConfig(exact_fidelity=False), reuse=False)
    replay = stages.replay_stage(rec["ingest"].path, rec["fit"], ws)
    assert replay.reused and replay.info["n_views"] == 20 and manifests[0].stat().st_mtime_ns == made
    samples = read_rows(again.path)["samples"]  # the proxies of a second annotate run come from the replay
    assert samples and all(s["logged_psnr"] > 10.0 and s["feature_drift"] is not None for s in samples)


@pytest.mark.slow  # shares the module's 30 s flow build: make test's five minutes
def test_dataset_export_as_openscenario_passes_asams_checkers_and_reads_back(built, tmp_path):
    from omniscs.export.asam_checks import check_file
    from omniscs.export.openscenario import read_scenario
    from omniscs.scene import load_scene

    _, first, _ = built
    stores = sorted((Path(first["dataset_path"]) / "scenes").iterdir())
    out = tmp_path / "xosc"
    exported = CliRunner().invoke(app, ["dataset", "export", first["dataset_path"], "--format", "openscenario",
                                        "--out", str(out)])
    assert exported.exit_code == 0, exported.output
    files = sorted(p for p in out.iterdir() if p.suffix in (".xosc", ".xodr"))
    assert len([p for p in files if p.suffix == ".xosc"]) == len(stores) and any(p.suffix == ".xodr" for p in files)
    for path in files:
        report = check_file(path)
        assert report.passed, report.to_dict()
    for store in stores:  # the annotated variant's agents, as rendered, are the scenario's
        scene = load_scene(store)
        read = read_scenario(out / f"{scene.scene_id}.xosc")
        assert len(read) == 1 + scene.boxes.track_id.nunique()
        ego_xy = scene.world_from_ego_all[:, :2, 3]
        assert abs(read["ego"].poses[:, :2] - ego_xy).max() < 0.01
