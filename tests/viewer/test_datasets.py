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
    assert np.array_equal(target.camera_image("CAM_FRONT", 2, boxes=True), store_camera_image(scene, "CAM_FRONT", 2))
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
