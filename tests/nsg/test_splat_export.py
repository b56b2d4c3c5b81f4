"""A fitted scene graph at one frame as 3DGS PLY: the file reads back to the same Gaussians (float32), and our
renderer draws the same image from the file as from the graph; bad input is one clear error."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from annotate_fixtures import fitted_scene
from omniscs.agents.ply import read_gaussian_ply
from omniscs.cli import app
from omniscs.errors import OmniscsError
from omniscs.gaussians import concat_params
from omniscs.nsg.graph import BACKGROUND, render_view
from omniscs.nsg.splat_export import frame_gaussians, write_scene_ply

runner = CliRunner()


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """(scene, graph, the graph's checkpoint folder)."""
    root = tmp_path_factory.mktemp("splat")
    return (*fitted_scene(root, n_frames=6, n_cameras=1, iterations=60), root / "graph")


def test_a_frame_reads_back_as_the_same_gaussians_and_renders_the_same_image(fitted, tmp_path):
    scene, graph, ckpt = fitted
    frame = 4
    nodes = frame_gaussians(graph, frame)
    assert len(nodes) == 1 + sum(bool(a.present[frame]) for a in graph.agents if len(a.gaussians))
    (path,) = write_scene_ply(graph, frame, tmp_path / "scene.ply")
    back = read_gaussian_ply(path)
    whole = concat_params(list(nodes.values()))
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(back, name).numpy(), getattr(whole, name).float().numpy(), err_msg=name)
    # the file's Gaussians as a graph's background, no agents: the same picture as the graph at that frame
    flat = graph.replace(background=back, agents=())
    view = graph.view(scene.camera_names[0], frame)
    with torch.no_grad():
        a = render_view(graph, view).rgb.numpy()
        b = render_view(flat, view).rgb.numpy()
    assert np.abs(a - b).max() < 2e-3, np.abs(a - b).max()  # float32 sums in another order; SH turned with agents
    moved_agent = [k for k in nodes if k != BACKGROUND][0]
    assert not torch.equal(nodes[moved_agent].means, graph.agent(int(moved_agent.split(".")[1])).gaussians.means)


def test_split_writes_a_file_per_node_and_the_cli_checks_before_writing(fitted, tmp_path):
    scene, graph, ckpt = fitted
    files = write_scene_ply(graph, 2, tmp_path / "split", split=True)
    assert files[0].name == "background.ply" and all(f.is_file() for f in files)
    assert sum(len(read_gaussian_ply(f)) for f in files) == sum(len(p) for p in frame_gaussians(graph, 2).values())
    with pytest.raises(OmniscsError, match="out of range"):
        frame_gaussians(graph, graph.n_frames)
    for argv, message in [(["--frame", "99"], "out of range"), (["--edit", "{not json"], "edit"),
                          (["--out", str(tmp_path / "x.png")], "must end in .ply")]:
        args = ["export", "ply", str(ckpt), "--out", str(tmp_path / "bad.ply"), *argv]
        result = runner.invoke(app, args)
        assert isinstance(result.exception, OmniscsError) and message in str(result.exception), result.output
    assert not (tmp_path / "bad.ply").exists() and not (tmp_path / "x.png").exists()
    ok = runner.invoke(app, ["export", "ply", str(ckpt), "--out", str(tmp_path / "ok.ply"), "--frame", "1",
                             "--edit", '[{"op": "remove", "track_id": 1}]'])
    assert ok.exit_code == 0, ok.output
    assert len(read_gaussian_ply(tmp_path / "ok.ply")) < sum(len(p) for p in frame_gaussians(graph, 1).values())

