"""Dataset sources in the factory: text forms, idempotent ingest, catalog rows, the flow, the CLI, and exports
that are written whole or not at all."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from omniscs.pipeline.request import RunRequest
from omniscs import catalog
from omniscs.cli import app
from omniscs.errors import OmniscsError
from omniscs.export import export_scenes
from omniscs.pipeline.stages import ingest_stage
from omniscs.scene import DatasetSource, StoreSource, load_scene, parse_source, source_from_dict
from omniscs.scene.summary import agent_rows, scene_row
from tests.conftest import write_tiny_scene
from tests.dataset_fixtures import leftovers

runner = CliRunner()


@pytest.fixture
def kitti_root(tmp_path):
    """A tiny scene (5 frames, one 64x36 camera, 2 cars) written as KITTI tracking sequence 0000."""
    return export_scenes([write_tiny_scene(tmp_path / "tiny")], "kitti", tmp_path / "kitti")


@pytest.fixture
def nuscenes_root(tmp_path):
    store = write_tiny_scene(tmp_path / "tiny_nus", scene_id="tiny-nus")
    return export_scenes([store], "nuscenes", tmp_path / "nuscenes", version="v1.0-mini", keyframe_every=2)


def test_text_sources_name_a_format_a_dataroot_and_optionally_a_scene(kitti_root, nuscenes_root):
    src = parse_source(f"kitti:{kitti_root}:0000")
    assert src == DatasetSource("kitti", str(kitti_root.resolve()), "0000")
    assert parse_source(f"kitti:{kitti_root}").scene is None
    nus = parse_source(f"nuscenes:{nuscenes_root}/v1.0-mini:scene-0001", n_frames=9)  # synthetic defaults ignored
    assert (nus.dataroot, nus.version, nus.scene) == (str(nuscenes_root.resolve()), "v1.0-mini", "scene-0001")
    assert source_from_dict(json.loads(json.dumps(nus.to_dict()))) == nus
    assert isinstance(parse_source(str(kitti_root)), StoreSource)  # a bare path is still a scene store
    with pytest.raises(OmniscsError, match="is not a directory"):
        parse_source("waymo-v2:/no/such/root:segment")
    with pytest.raises(OmniscsError, match="write kitti:DATAROOT"):
        parse_source("kitti:")


def test_ingest_reuses_an_up_to_date_store_and_rereads_when_the_dataset_changes(kitti_root, tmp_path):
    source = parse_source(f"kitti:{kitti_root}")
    first = ingest_stage(source, tmp_path / "ws")
    second = ingest_stage(source, tmp_path / "ws")
    assert (first.reused, second.reused) == (False, True) and first.path == second.path
    assert Path(first.path).parent == tmp_path / "ws" / "scenes" and first.scene_id.startswith("kitti-0000-")
    n_boxes = len(load_scene(first.path).boxes)
    labels = kitti_root / "training" / "label_02" / "0000.txt"
    lines = labels.read_text().splitlines()
    labels.write_text("\n".join(lines[:-1]) + "\n")  # one label fewer
    third = ingest_stage(source, tmp_path / "ws")
    assert not third.reused and third.path == first.path and len(load_scene(third.path).boxes) == n_boxes - 1


def test_catalog_scene_rows_record_the_dataset_its_scene_id_and_location(nuscenes_root, tmp_path):
    result = ingest_stage(parse_source(f"nuscenes:{nuscenes_root}"), tmp_path / "ws")
    scene = load_scene(result.path)
    row = scene_row(scene, agent_rows(scene), reused=False, ingest_seconds=0.1)
    assert row["source_kind"] == "nuscenes" and row["source_scene_id"] == "scene-0001"
    assert row["dataroot"] == str(nuscenes_root.resolve()) and row["location"] == "boston-seaport"
    assert catalog.validated_table("scenes", [row]).num_rows == 1


def test_a_dataroot_with_several_scenes_needs_a_scene_name(tmp_path):
    stores = [write_tiny_scene(tmp_path / n, scene_id=n) for n in ("a", "b")]
    root = export_scenes(stores, "kitti", tmp_path / "kitti")
    with pytest.raises(OmniscsError, match="holds 2 scenes; name one, e.g. kitti:.*:0000"):
        ingest_stage(parse_source(f"kitti:{root}"), tmp_path / "ws")
    assert ingest_stage(parse_source(f"kitti:{root}:0001"), tmp_path / "ws").scene_id.startswith("kitti-0001-")


def test_generate_dataset_accepts_dataset_sources(prefect_harness, kitti_root, tmp_path):
    from flows.generate import generate_dataset

    ws = tmp_path / "ws"
    result = generate_dataset(RunRequest(sources=[f"kitti:{kitti_root}:0000"], workspace=str(ws), run_id="real", previews=False))
    rows = catalog.query(catalog.catalog_root(ws), "SELECT source_kind, source_scene_id, dataroot, n_frames "
                                                   "FROM scenes").to_pylist()
    assert rows == [{"source_kind": "kitti", "source_scene_id": "0000", "dataroot": str(kitti_root.resolve()),
                     "n_frames": 5}]
    assert load_scene(result["scenes"][0]["path"]).manifest["dataset"] == "kitti"


def test_cli_exports_a_scene_and_ingests_it_back(tmp_path):
    store = write_tiny_scene(tmp_path / "tiny")
    out = tmp_path / "waymo"
    result = runner.invoke(app, ["world", "export", str(store), "--format", "waymo-v2", "--out", str(out)])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["ingest", "--source", "waymo-v2", "--dataroot", str(out), "--out", str(tmp_path / "s")])
    assert result.exit_code == 0, result.output
    (path,) = (tmp_path / "s").iterdir()
    scene = load_scene(path)
    assert scene.n_frames == 5 and scene.camera_names == ["CAM_FRONT"] and scene.manifest["source_scene_id"] == "tiny"


def test_cli_reports_a_bad_format_in_one_line_with_exit_code_2(tmp_path):
    env = {**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    proc = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", "world", "export",
                           str(tmp_path), "--format", "carla", "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "unknown --format 'carla'" in proc.stderr


def test_an_export_that_fails_leaves_nothing_and_an_existing_one_is_kept(tmp_path):
    store = write_tiny_scene(tmp_path / "tiny")
    with pytest.raises(OmniscsError, match="unknown camera 'CAM_BACK'"):
        export_scenes([store], "kitti", tmp_path / "out", camera="CAM_BACK")
    assert not (tmp_path / "out").exists() and not leftovers(tmp_path)
    export_scenes([store], "nuscenes", tmp_path / "nus", version="v1.0-mini")
    with pytest.raises(OmniscsError, match="already exists"):
        export_scenes([store], "nuscenes", tmp_path / "nus", version="v1.0-mini")
    assert (tmp_path / "nus" / "v1.0-mini" / "scene.json").is_file()
