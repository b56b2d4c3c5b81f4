"""Datasets: annotated variants gathered under datasets/<id>/ with a card, a preview and catalog rows; the same
inputs give the same dataset (reused), and the rows point at files that exist."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from annotate_fixtures import fitted_scene, logged_variant
from omniscs import catalog
from omniscs.annotate.dataset import CARD_JSON, CARD_MD, PREVIEW_PNG
from omniscs.annotate.scene import annotate_variants, read_rows
from omniscs.errors import OmniscsError
from omniscs.pipeline import stages
from omniscs.pipeline.records import StageRecord
from omniscs.scene import load_scene


@pytest.fixture(scope="module")
def annotated_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("dataset")
    scene, graph = fitted_scene(root, n_frames=4, n_cameras=2, iterations=80)
    variants = [logged_variant(scene, shift={2: 0.1}), dict(logged_variant(scene, shift={1: -0.1}), variant_id="v001")]
    out = root / "annotated"
    annotate_variants(graph, scene, variants, out)
    return scene, out


def _record(scene, path: Path) -> StageRecord:
    return StageRecord("annotate", scene.scene_id, str(path), key="k" * 64)


def test_a_dataset_holds_every_variant_store_with_card_preview_and_rows(annotated_dir, tmp_path):
    scene, out = annotated_dir
    record = stages.dataset_stage([_record(scene, out)], tmp_path / "ws", facts={"sources": ["test"], "config": {}})
    root = Path(record.path)
    card = json.loads((root / CARD_JSON).read_text())
    assert card["counts"]["variants"] == 2 and card["counts"]["images"] == 2 * 4 * 2
    assert (root / CARD_MD).read_text().startswith(f"# Dataset {record.info['dataset_id']}")
    preview = cv2.imread(str(root / PREVIEW_PNG))
    assert preview is not None and preview.shape[0] > 50
    for store_id in ("nsg-test-v000", "nsg-test-v001"):
        assert load_scene(root / "scenes" / store_id).n_frames == 4
    samples = record.rows["samples"]
    assert len(samples) == card["counts"]["images"] and all(Path(s["image_path"]).is_file() for s in samples)
    assert all(Path(s["gt_path"]).is_file() for s in samples)
    assert len(record.rows["annotations"]) == card["counts"]["annotations"] == len(read_rows(out)["annotations"])
    for table, rows in record.rows.items():
        assert catalog.validated_table(table, rows).num_rows == len(rows)


def test_the_same_inputs_give_the_same_dataset_reused(annotated_dir, tmp_path):
    scene, out = annotated_dir
    first = stages.dataset_stage([_record(scene, out)], tmp_path / "ws")
    second = stages.dataset_stage([_record(scene, out)], tmp_path / "ws")
    assert first.info["dataset_id"] == second.info["dataset_id"] and second.reused and not first.reused
    named = stages.dataset_stage([_record(scene, out)], tmp_path / "ws", dataset_id="my-set")
    assert Path(named.path).name == "my-set"


def test_catalogued_rows_are_queryable_with_duckdb(annotated_dir, tmp_path):
    scene, out = annotated_dir
    ws = tmp_path / "ws"
    record = stages.dataset_stage([_record(scene, out)], ws)
    stages.catalog_dataset_stage("run-1", ws, record)
    stages.catalog_run_stage("run-1", ws, "generate_dataset", "completed", 0, 1, 1, {})
    root = catalog.catalog_root(ws)
    n = catalog.query(root, "SELECT count(*) AS n FROM samples WHERE camera = 'CAM_FRONT'").to_pylist()[0]["n"]
    assert n == 2 * 4
    vis = catalog.query(root, "SELECT max(visibility_level) AS v FROM annotations").to_pylist()[0]["v"]
    assert 1 <= vis <= 4


def test_a_dataset_needs_an_annotated_scene_and_a_safe_id(annotated_dir, tmp_path):
    scene, out = annotated_dir
    with pytest.raises(OmniscsError, match="at least one"):
        stages.dataset_stage([StageRecord.skip("annotate", "s", "none")], tmp_path / "ws")
    with pytest.raises(OmniscsError, match="dataset id"):
        stages.dataset_stage([_record(scene, out)], tmp_path / "ws", dataset_id="../escape")
    assert not (tmp_path / "escape").exists()


def test_a_reader_during_a_rebuild_sees_the_dataset_or_a_clear_error(annotated_dir, tmp_path):
    import threading

    from omniscs.errors import OmniscsError as Error

    scene, out = annotated_dir
    ws = tmp_path / "ws"
    record = stages.dataset_stage([_record(scene, out)], ws)
    store = Path(record.path) / "scenes" / "nsg-test-v000"
    expected = load_scene(store).image("CAM_FRONT", 0)
    done, outcomes = threading.Event(), {"same": 0, "error": 0}
    failures = []

    def read_loop():
        while not done.is_set():
            try:
                image = load_scene(store).image("CAM_FRONT", 0)
                assert (image == expected).all()
                outcomes["same"] += 1
            except Error:
                outcomes["error"] += 1
            except Exception as exc:  # anything else is a failure of the guarantee
                failures.append(repr(exc))

    reader = threading.Thread(target=read_loop)
    reader.start()
    try:
        for _ in range(3):
            stages.dataset_stage([_record(scene, out)], ws, reuse=False)
    finally:
        done.set()
        reader.join()
    assert failures == [] and outcomes["same"] > 0
    assert (load_scene(store).image("CAM_FRONT", 0) == expected).all()
