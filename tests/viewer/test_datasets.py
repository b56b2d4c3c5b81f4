"""A dataset in the viewer: its variant stores one at a time, each with its images, boxes and frames."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from omniscs.errors import OmniscsError
from omniscs.viewer.state import store_camera_image
from omniscs.viewer.targets import DatasetTarget, open_target


@pytest.fixture
def dataset(fitted, tmp_path):
    """A dataset folder of two variant stores (copies of the test scene) and its card, which also lists a store the
    folder lacks (left out)."""
    scene, _ = fitted
    root = tmp_path / "ds-test"
    shutil.copytree(scene.path, root / "scenes" / "s-v000")
    shutil.copytree(scene.path, root / "scenes" / "s-v001")
    rows = [{"store_id": "s-v000", "scene_id": scene.scene_id, "variant_id": "v000", "level": "behaviour",
             "n_frames": 4, "n_images": 8, "n_annotations": 7, "passed_gates": True, "fidelity_psnr": 31.25},
            {"store_id": "s-v001", "scene_id": scene.scene_id, "variant_id": "v001", "level": "appearance",
             "n_frames": 4, "n_images": 8, "n_annotations": 6, "passed_gates": False, "fidelity_psnr": None},
            {"store_id": "s-missing", "scene_id": scene.scene_id, "variant_id": "v002"}]
    labels = [{"store_id": "s-v000", "frame_idx": 2, "camera": "CAM_FRONT", "track_id": 1, "visibility_level": 3,
               "is_adversary": True, "x1": 20.0, "y1": 10.0, "x2": 60.0, "y2": 40.0, "tight_x1": 24.0,
               "tight_y1": 12.0, "tight_x2": 50.0, "tight_y2": 36.0},
              {"store_id": "s-v000", "frame_idx": 2, "camera": "CAM_FRONT", "track_id": 2, "visibility_level": 1,
               "is_adversary": False, "x1": 70.0, "y1": 20.0, "x2": 90.0, "y2": 40.0, "tight_x1": None,
               "tight_y1": None, "tight_x2": None, "tight_y2": None}]
    (root / "rows.json").write_text(json.dumps({"samples": [], "annotations": labels}))
    (root / "dataset.json").write_text(json.dumps({"dataset_id": "ds-test", "counts": {"images": 16,
                                                                                      "annotations": 13},
                                                   "variants": rows}))
    return root


def test_a_dataset_opens_its_variant_stores_one_at_a_time(dataset, fitted):
    scene, _ = fitted
    target = open_target(dataset)
    assert isinstance(target, DatasetTarget) and [r["store_id"] for r in target.samples] == ["s-v000", "s-v001"]
    assert "31.2 dB PSNR" in target.sample_summary() and "gates passed" in target.sample_summary()
    target.pick(1)
    assert "gates FAILED" in target.sample_summary() and target.scene.path == dataset / "scenes" / "s-v001"
    # s-v001 has no annotation rows: its image is the store's, 3D boxes drawn
    assert np.array_equal(target.camera_image("CAM_FRONT", 2, boxes=True), store_camera_image(scene, "CAM_FRONT", 2))
    assert target.frame_summary(2) == "Frame 2 annotations: none listed"
    assert "**ds-test** (dataset): 2 variant stores, 16 images, 13 annotations" in target.summary()


def test_the_viewer_switches_samples_and_keeps_its_frame_in_range(dataset, port):
    import viser

    from omniscs.viewer.app import ViewerApp

    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, open_target(dataset), frame=3)
    try:
        app.pick_sample("s-v001")
        assert app.target.sample == 1 and "v001" in app.sample_figures.content
        assert int(app.frame_slider.value) == 3 and app.frame_slider.max == 3
        assert set(app._boxes) == {b.track_id for b in app.target.frame_state(3).boxes}
    finally:
        app.close()
        server.stop()


def test_a_dataset_without_stores_is_one_error(tmp_path):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "dataset.json").write_text('{"dataset_id": "ds", "variants": []}')
    with pytest.raises(OmniscsError, match="lists no variant store"):
        open_target(tmp_path / "ds")


def test_a_datasets_2d_boxes_are_drawn_tight_where_the_mask_gave_one_with_their_visibility(dataset, fitted):
    scene, _ = fitted
    target = open_target(dataset)
    plain = store_camera_image(scene, "CAM_FRONT", 2).astype(int)
    drawn = target.camera_image("CAM_FRONT", 2, boxes=True).astype(int)
    red = (drawn[..., 0] > 200) & (drawn[..., 1] < 60) & (drawn[..., 2] < 60)
    # the adversary's tight box (24..49 x 12..35) is red on its left edge, and the projected box's edge is not drawn
    assert red[14:34, 24].mean() > 0.9 and not red[14:34, 20].any()
    green = (np.abs(drawn - np.array([40, 220, 60])).sum(axis=2) < 30) & (np.abs(plain - drawn).sum(axis=2) > 0)
    assert green[22:38, 70].mean() > 0.9  # the other, without a tight box: its projected box
    # no rows at frame 1: nothing added
    assert np.array_equal(target.camera_image("CAM_FRONT", 1, boxes=True), store_camera_image(scene, "CAM_FRONT", 1))
    assert np.array_equal(target.camera_image("CAM_FRONT", 2, boxes=False), store_camera_image(scene, "CAM_FRONT", 2,
                                                                                                boxes=False))
    assert target.frame_summary(2) == "Frame 2 annotations: CAM_FRONT 2 (v1-v4: 1/0/1/0)"


def test_a_dataset_whose_rows_are_damaged_is_one_error(dataset):
    (dataset / "rows.json").write_text(json.dumps({"annotations": [{"frame_idx": 1}]}))
    with pytest.raises(OmniscsError, match="lacks store_id, frame_idx or camera"):
        open_target(dataset)
    (dataset / "rows.json").write_text("{not json")
    with pytest.raises(OmniscsError, match="rows.json"):
        open_target(dataset)
