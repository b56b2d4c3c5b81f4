"""Paths drawn in the viewer: control points to per-frame waypoints, and a cut-in drawn through the handlers is the
set_trajectory spec saved, rendered as `omniscs render --edit` renders it."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, pose_from_xyz_yaw, rotmat_from_euler
from omniscs.viewer.paths import control_frames, is_upright, path_waypoints
from omniscs.viewer.session import EditSession
from omniscs.viewer.state import rendered_image


def straight(n: int = 10, speed: float = 1.0) -> np.ndarray:  # [n, 4, 4] along +x at 1 m per frame, z 0.8
    return np.stack([pose_from_xyz_yaw(speed * f, 2.0, 0.8, 0.0) for f in range(n)])


def test_control_frames_spread_over_the_present_frames_with_both_ends():
    present = np.zeros(20, dtype=bool)
    present[3:17] = True
    frames = control_frames(present, n=4)
    assert list(frames) == [3, 7, 12, 16]
    assert list(control_frames(present[:6], n=4)) == [3, 4, 5]  # fewer present frames than points: all of them


def test_control_points_where_the_agent_is_give_back_its_path():
    poses, present = straight(), np.ones(10, dtype=bool)
    frames = control_frames(present, n=4)
    waypoints = path_waypoints(poses, present, frames, poses[frames, :2, 3])
    assert np.allclose(waypoints, [(float(f), 2.0, 0.8, 0.0) for f in range(10)])


def test_a_moved_control_point_bends_the_path_linearly_in_time_and_turns_the_heading():
    poses, present = straight(), np.ones(10, dtype=bool)
    frames = np.array([0, 5, 9])
    xy = poses[frames, :2, 3].copy()
    xy[2, 1] = -2.0  # the end 4 m to the right: a cut-in
    w = np.array(path_waypoints(poses, present, frames, xy))
    assert np.allclose(w[:6, 1], 2.0) and np.allclose(w[5:, 1], np.linspace(2.0, -2.0, 5))
    assert np.allclose(w[:, 0], np.arange(10)) and np.allclose(w[:, 2], 0.8)
    assert np.allclose(w[6:9, 3], np.arctan2(-1.0, 1.0))  # 1 m ahead and 1 m right per frame
    assert np.all(np.isfinite(w))


def test_an_agent_standing_still_keeps_its_heading_and_absent_frames_stay_absent():
    poses = np.stack([pose_from_xyz_yaw(5.0, 1.0, 0.8, 0.7)] * 6)
    present = np.array([False, True, True, True, True, False])
    w = path_waypoints(poses, present, np.array([1, 4]), [[5.0, 1.0], [5.0, 1.0]])
    assert w[0] is None and w[5] is None
    assert all(p[3] == pytest.approx(0.7) for p in w[1:5])


def test_bad_control_points_are_one_error():
    poses, present = straight(), np.ones(10, dtype=bool)
    with pytest.raises(OmniscsError, match="one control point per control frame"):
        path_waypoints(poses, present, np.array([0, 9]), [[0.0, 0.0]])
    with pytest.raises(OmniscsError, match="increase"):
        path_waypoints(poses, present, np.array([9, 0]), [[0.0, 0.0], [1.0, 1.0]])
    with pytest.raises(OmniscsError, match="finite"):
        path_waypoints(poses, present, np.array([0, 9]), [[0.0, np.nan], [1.0, 1.0]])


def test_only_an_upright_agent_counts_as_upright():
    poses, present = straight(), np.ones(10, dtype=bool)
    assert is_upright(poses, present)
    assert not is_upright(poses @ make_transform(rotmat_from_euler(np.pi, 0, 0), np.zeros(3)), present)


def test_a_cut_in_drawn_in_the_viewer_is_the_spec_saved_and_renders_as_omniscs_render_does(fitted, checkpoint, port,
                                                                                           tmp_path):
    import viser

    from omniscs.cli import app as cli
    from omniscs.viewer.app import ViewerApp
    from omniscs.viewer.targets import open_target

    _, graph = fitted
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, open_target(checkpoint), frame=2, edits_out=tmp_path / "cut-in.json")
    try:
        app.select(2)
        app.path_toggle.value = True
        assert len(app._path_handles) == len(app._path_frames) == 3  # car 2 is present in frames 1-3
        xy = np.array([h.position[:2] for h in app._path_handles])
        xy[-1, 1] = graph.agent(1).world_from_agent[3, 1, 3]  # its last point into the ego's lane
        app.draw_path(xy)  # what a control point's release calls
        spec = json.loads(app.save().read_text())
    finally:
        app.close()
        server.stop()
    assert [e["op"] for e in spec] == ["set_trajectory"] and spec[0]["track_id"] == 2
    waypoints = spec[0]["waypoints"]
    assert waypoints[0] is None and waypoints[3][1] == pytest.approx(xy[-1, 1], abs=1e-4)
    assert waypoints[3][3] < 0  # heading right, into the ego's lane
    out = tmp_path / "cut-in.png"
    result = CliRunner().invoke(cli, ["render", str(checkpoint), "--frame", "3", "--edit",
                                      f"@{tmp_path / 'cut-in.json'}", "--out", str(out)])
    assert result.exit_code == 0, result.output
    shown = rendered_image(app.target.session.graph, "CAM_FRONT", 3)
    assert np.array_equal(shown, np.asarray(Image.open(out).convert("RGB")))
    assert not np.array_equal(shown, rendered_image(graph, "CAM_FRONT", 3))


def test_a_tilted_agent_cannot_take_a_drawn_path_and_a_path_folds_earlier_moves(fitted):
    _, graph = fitted
    session = EditSession(graph)
    node = graph.agent(1)
    session.move(1, 0, node.world_from_agent[0] @ make_transform(rotmat_from_euler(np.pi, 0, 0), np.zeros(3)))
    with pytest.raises(OmniscsError, match="tilted"):
        session.set_path(1, [tuple(p[:3, 3]) + (0.0,) for p in node.world_from_agent])
    session.reset(1)
    session.move(1, 0, node.world_from_agent[0] @ make_transform(np.eye(3), [0.0, 1.0, 0.0]))
    moved = session.graph.agent(1)
    frames = control_frames(moved.present)
    session.set_path(1, path_waypoints(moved.world_from_agent, moved.present, frames,
                                       moved.world_from_agent[frames, :2, 3]))
    assert [e.op for e in session.edits()] == ["set_trajectory"]  # the move is in the path now
    assert np.allclose(session.graph.agent(1).world_from_agent, moved.world_from_agent, atol=1e-4)
