"""Scene-graph checkpoints: a round trip renders bit-identically; other scenes and versions are refused."""
from __future__ import annotations

import json

import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.nsg import fit_scene
from omniscs.nsg.checkpoint import GRAPH_JSON, load_graph, load_metrics, load_plan, save_checkpoint
from omniscs.nsg.edit import apply_graph_edits
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from tests.conftest import write_tiny_scene
from tests.nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("nsg-ckpt")
    scene = load_scene(write_nsg_scene(root / "scene", nsg_world(n_frames=5)))
    config = tiny_fit_config(20)
    result = fit_scene(scene, config, make_plan(scene, None, config.plan), checkpoint_dir=root / "ckpt")
    return scene, result, root / "ckpt"


def test_round_trip_renders_bit_identically_without_refitting(fitted):
    scene, result, ckpt = fitted
    loaded = load_graph(ckpt, scene)
    for f in (0, 3):
        a = result.graph.render(result.graph.view("CAM_FRONT", f))
        b = loaded.render(loaded.view("CAM_FRONT", f))
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)
    assert load_plan(ckpt) == result.plan
    assert load_metrics(ckpt)["status"] == "fitted"
    assert load_metrics(ckpt)["n_gaussians"] == loaded.n_gaussians


def test_an_edited_graph_with_shared_tensors_saves_and_loads(fitted, tmp_path):
    scene, result, _ = fitted
    edited = apply_graph_edits(result.graph, [{"op": "replace_model", "track_id": 1, "asset_id": "nsg:2"}])
    loaded = load_graph(save_checkpoint(edited, tmp_path / "edited"))
    assert torch.equal(loaded.agent(1).gaussians.means, edited.agent(1).gaussians.means)


def test_a_checkpoint_of_another_scene_is_refused(fitted, tmp_path):
    _, _, ckpt = fitted
    other = load_scene(write_tiny_scene(tmp_path / "other"))
    with pytest.raises(OmniscsError, match="fitted to scene nsg-test"):
        load_graph(ckpt, other)


def test_a_checkpoint_of_another_version_is_refused(fitted, tmp_path):
    import shutil

    _, _, ckpt = fitted
    old = tmp_path / "old"
    shutil.copytree(ckpt, old)
    meta = json.loads((old / GRAPH_JSON).read_text())
    meta["version"] = 0
    (old / GRAPH_JSON).write_text(json.dumps(meta))
    with pytest.raises(OmniscsError, match="version 0 scene-graph checkpoint"):
        load_graph(old)
    with pytest.raises(OmniscsError, match="not a scene-graph checkpoint"):
        load_graph(tmp_path)


def test_saving_over_an_existing_checkpoint_needs_overwrite(fitted):
    _, result, ckpt = fitted
    with pytest.raises(OmniscsError, match="already exists"):
        save_checkpoint(result.graph, ckpt)
