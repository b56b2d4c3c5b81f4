"""The devkit's own renderers run on our nuScenes export under the numpy the project installs, with the shim of
``omniscs.export.devkit`` (nuscenes-devkit 1.2.0 calls int() on a one-element array in its LIDAR_TOP map underlay,
which numpy 2 refuses); the shim leaves every other caller of the map mask as it was."""
from __future__ import annotations

import matplotlib
import numpy as np
import pytest
from PIL import Image

from omniscs.export import export_scenes
from omniscs.export.devkit import patch_nuscenes_devkit
from tests.dataset_fixtures import synthetic_store

VERSION = "v1.0-mini"


@pytest.fixture(scope="module")
def nusc(tmp_path_factory):
    from nuscenes.nuscenes import NuScenes

    root = export_scenes([synthetic_store(tmp_path_factory)], "nuscenes", tmp_path_factory.mktemp("devkit") / "nus",
                         version=VERSION)
    patch_nuscenes_devkit()
    return NuScenes(version=VERSION, dataroot=str(root), verbose=False)


@pytest.fixture(autouse=True)
def agg_backend():
    backend = matplotlib.get_backend()
    matplotlib.use("Agg")
    yield
    import matplotlib.pyplot as plt

    plt.close("all")
    matplotlib.use(backend)


def _is_picture(path) -> bool:
    image = np.asarray(Image.open(path).convert("L"))
    return image.shape[0] > 100 and image.shape[1] > 100 and image.min() < image.max()


@pytest.mark.slow
@pytest.mark.parametrize("channel, underlay", [("CAM_FRONT", False), ("LIDAR_TOP", True), ("LIDAR_TOP", False)])
def test_render_sample_data_writes_a_picture_of_a_camera_and_of_lidar_top_on_its_map(nusc, tmp_path, channel,
                                                                                       underlay):
    out = tmp_path / f"{channel}.png"
    nusc.render_sample_data(nusc.sample[0]["data"][channel], underlay_map=underlay, out_path=str(out), verbose=False)
    assert _is_picture(out)


@pytest.mark.slow
def test_render_sample_draws_every_sensor_of_a_keyframe(nusc, tmp_path):
    out = tmp_path / "sample.png"
    nusc.render_sample(nusc.sample[-1]["token"], out_path=str(out), verbose=False)
    assert _is_picture(out)


@pytest.mark.slow
def test_the_shim_is_applied_once_and_leaves_the_map_mask_answering_arrays(nusc, tmp_path):
    from nuscenes.nuscenes import NuScenesExplorer

    wrapped = NuScenesExplorer.render_ego_centric_map
    patch_nuscenes_devkit()
    assert NuScenesExplorer.render_ego_centric_map is wrapped
    nusc.render_sample_data(nusc.sample[0]["data"]["LIDAR_TOP"], underlay_map=True, out_path=str(tmp_path / "l.png"),
                            verbose=False)
    mask = nusc.map[0]["mask"]
    assert "to_pixel_coords" not in vars(mask)  # the one-call override is gone
    px, py = mask.to_pixel_coords(1.0, 2.0)
    assert isinstance(px, np.ndarray) and px.shape == (1,) and py.shape == (1,)
    assert mask.is_on_mask(np.array([1.0, 2.0]), np.array([1.0, 2.0])).shape == (2,)
