"""Edits in the viewer: a gizmo move and a removal through the handlers are the edit spec saved, and that spec is
what `omniscs render --edit` renders. Also: targets, bad targets and the serve loop."""
from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from omniscs.edits import Remove, Rotate, Translate, parse_edits
from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, rotmat_from_euler
from omniscs.nsg.edit import apply_graph_edits
from omniscs.viewer.app import NO_AGENT, ViewerApp, pose_args, pose_from_gizmo, serve
from omniscs.viewer.targets import GraphTarget, StoreTarget, open_target
from omniscs.viewer.session import EditSession
from omniscs.viewer.state import ViewerConfig, rendered_image, splat_layers

#: The gizmo drag of the tests: 2 m ahead, 1 m to the right, turned 30° left (in the car's own frame).
DRAG = make_transform(rotmat_from_euler(yaw=np.radians(30.0)), [2.0, -1.0, 0.0])


@pytest.fixture
def app(checkpoint, port, tmp_path):
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, open_target(checkpoint), frame=2, edits_out=tmp_path / "spec.json")
    yield app
    app.close()
    server.stop()


def test_a_gizmo_move_puts_the_agent_at_the_gizmo_pose_and_moves_its_whole_path_rigidly(fitted):
    _, graph = fitted
    session = EditSession(graph)
    before = graph.agent(2).world_from_agent
    edited = session.move(2, 2, before[2] @ DRAG)
    after = edited.agent(2).world_from_agent
    assert np.allclose(after[2], before[2] @ DRAG, atol=1e-6)
    assert np.allclose(after, before @ DRAG, atol=1e-6)  # every frame, in the car's own frame
    assert np.array_equal(edited.agent(1).world_from_agent, graph.agent(1).world_from_agent)
    assert session.edits() == [Translate(2, 2.0, -1.0, 0.0), Rotate(2, 30.0, 0.0, 0.0)]
    # a second drag composes with the first: one translate and one rotate still
    session.move(2, 0, session.graph.agent(2).world_from_agent[0] @ DRAG)
    # (the saved amounts are rounded to 0.1 mm and 0.001 degrees: 4.23205 m ahead is saved as 4.2321)
    assert np.allclose(session.graph.agent(2).world_from_agent, before @ DRAG @ DRAG, atol=2e-4)
    assert len(session.edits()) == 2 and session.edits()[1].yaw_deg == pytest.approx(60.0)


def test_edits_made_through_the_handlers_are_the_spec_saved(app, fitted, tmp_path):
    _, graph = fitted
    app.select(2)
    assert app.agent_list.value == "2 car" and app._gizmo is not None
    app.move_selected(graph.agent(2).world_from_agent[2] @ DRAG)  # what a gizmo release at frame 2 calls
    app.select(1)
    app.remove_selected()
    assert app.save() == tmp_path / "spec.json"
    assert json.loads((tmp_path / "spec.json").read_text()) == [
        {"op": "translate", "track_id": 2, "longitudinal": 2.0, "lateral": -1.0, "vertical": 0.0},
        {"op": "rotate", "track_id": 2, "yaw_deg": 30.0, "pitch_deg": 0.0, "roll_deg": 0.0},
        {"op": "remove", "track_id": 1}]
    assert "Saved 3 edit(s)" in app.status.content
    assert [b.track_id for b in app.target.frame_state(2).boxes] == [2]


def test_a_gizmo_release_moves_the_agent_as_the_gizmo_shows_it(app, fitted):
    _, graph = fitted
    app.select(2)
    target = graph.agent(2).world_from_agent[2] @ DRAG
    pose = pose_args(target)

    class Release:  # what viser hands the handler at the end of a drag
        phase = "end"

        class target:
            wxyz, position = pose["wxyz"].astype(np.float32), pose["position"].astype(np.float32)

    app._on_gizmo(Release)
    assert np.allclose(app.target.session.graph.agent(2).world_from_agent[2], target, atol=1e-4)
    assert np.allclose(pose_from_gizmo(app._gizmo.wxyz, app._gizmo.position), target, atol=1e-4)


def test_the_saved_spec_round_trips_and_renders_as_omniscs_render_does(app, fitted, checkpoint, tmp_path):
    from omniscs.cli import app as cli
    from omniscs.cli.common import read_edits

    _, graph = fitted
    app.select(2)
    app.move_selected(graph.agent(2).world_from_agent[2] @ DRAG)
    app.select(1)
    app.remove_selected()
    spec = app.save()
    assert read_edits(f"@{spec}") == parse_edits(app.target.session.spec()) == app.target.session.edits()
    out = tmp_path / "edited.png"
    result = CliRunner().invoke(cli, ["render", str(checkpoint), "--frame", "2", "--edit", f"@{spec}",
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    shown = rendered_image(app.target.session.graph, "CAM_FRONT", 2)
    assert np.array_equal(shown, np.asarray(Image.open(out).convert("RGB")))
    assert not np.array_equal(shown, rendered_image(graph, "CAM_FRONT", 2))  # the edit is visible


def test_a_move_past_the_edit_bounds_is_refused_and_the_session_is_unchanged(fitted):
    _, graph = fitted
    session = EditSession(graph)
    session.move(1, 0, graph.agent(1).world_from_agent[0] @ DRAG)
    kept = session.spec()
    with pytest.raises(OmniscsError, match="longitudinal"):
        session.move(1, 0, graph.agent(1).world_from_agent[0] @ make_transform(np.eye(3), [5_000.0, 0, 0]))
    with pytest.raises(OmniscsError, match="rigid"):
        session.move(1, 0, np.diag([2.0, 1.0, 1.0, 1.0]))
    assert session.spec() == kept


def test_removing_then_resetting_an_agent_brings_it_back_and_a_removed_agent_cannot_move(fitted):
    _, graph = fitted
    session = EditSession(graph)
    session.remove(1)
    assert session.graph.agent_ids == (2,) and session.edits() == [Remove(1)]
    with pytest.raises(OmniscsError, match="not an agent node"):
        session.move(1, 0, np.eye(4))
    session.reset(1)
    assert session.edits() == [] and session.graph.agent_ids == (1, 2)


def test_the_session_graph_is_what_apply_graph_edits_makes_of_its_spec(fitted):
    _, graph = fitted
    session = EditSession(graph)
    session.move(2, 3, graph.agent(2).world_from_agent[3] @ make_transform(rotmat_from_euler(roll=np.pi), [0, 0, 0.2]))
    again = apply_graph_edits(graph, json.loads(json.dumps(session.spec())))
    assert np.array_equal(again.agent(2).world_from_agent, session.graph.agent(2).world_from_agent)


def test_save_refuses_a_path_that_is_not_a_json_file(fitted, tmp_path):
    session = EditSession(fitted[1])
    with pytest.raises(OmniscsError, match=".json"):
        session.save(tmp_path / "spec.txt")


def test_targets_open_by_what_the_folder_holds_and_anything_else_is_one_error(fitted, checkpoint, tmp_path):
    scene, _ = fitted
    assert isinstance(open_target(checkpoint, ViewerConfig(splat_budget=100)), GraphTarget)
    assert isinstance(open_target(scene.path), StoreTarget)
    (tmp_path / "empty").mkdir()
    for bad, says in ((tmp_path / "nowhere", "does not exist"), (tmp_path / "empty", "neither a scene-graph"),
                      (checkpoint / "graph.json", "neither a scene-graph")):
        with pytest.raises(OmniscsError, match=says) as info:
            open_target(bad)
        assert "\n" not in str(info.value)


def test_a_checkpoint_opens_with_its_scene_store_and_a_store_refuses_one(fitted, checkpoint):
    scene, _ = fitted
    target = open_target(checkpoint, scene=scene.path)
    segments, _ = target.road()
    assert target.scene.scene_id == scene.scene_id and len(segments) > 0
    assert len(open_target(scene.path).road()[0]) == len(segments)  # the store's own map, the same lines
    assert open_target(checkpoint).road() is None
    with pytest.raises(OmniscsError, match="--scene, --pool and --variants go with a scene-graph"):
        open_target(scene.path, scene=scene.path)


def test_with_its_scene_a_move_is_checked_like_an_appearance_placement(fitted, checkpoint, port):
    import viser

    scene, graph = fitted
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, open_target(checkpoint, scene=scene.path), frame=2)
    try:
        app.select(2)
        app.move_selected(graph.agent(1).world_from_agent[2])  # onto car 1
        assert "overlaps track 1 at frames 1-3" in app.status.content
        app.move_selected(graph.agent(1).world_from_agent[2] @ make_transform(np.eye(3), [0.0, 40.0, 0.0]))
        assert "leaves the drivable area" in app.status.content
        app.reset_selected()
        app.select(1)
        app.remove_selected()
        app.select(2)
        app.move_selected(graph.agent(1).world_from_agent[2])  # where car 1 was: free now that it is removed
        assert "Placement of agent 2: on the road, clear of every box" in app.status.content
        app.model_list.value = "nsg:2 car"
        ego = graph.world_from_ego[2]
        tid = app.insert_at(ego[0, 3] + 11.0, ego[1, 3] + 0.0, 0.0)  # onto car 2, where it now stands
        assert f"Placement of agent {tid}: overlaps track 2" in app.status.content
    finally:
        app.close()
        server.stop()


@pytest.mark.slow  # about 10 s: kept out of make test's 5 minutes
def test_omniscs_view_of_a_bad_target_is_one_line_and_another_host_is_warned(tmp_path):
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", "view", str(tmp_path / "x"),
                           "--host", "0.0.0.0"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines[0].startswith("warning: serving on 0.0.0.0") and lines[-1].startswith("error: ")
    assert "does not exist" in lines[-1]


@pytest.mark.parametrize("host,says", [("10.255.255.1", "cannot listen on 10.255.255.1"),
                                       ("no-such-host.invalid", "does not resolve")])
def test_serving_on_an_address_this_machine_lacks_is_one_error_not_a_hang(checkpoint, host, says):
    with pytest.raises(OmniscsError, match=says):
        serve(open_target(checkpoint), host=host, port=8080)


def test_a_first_frame_out_of_range_is_one_error(checkpoint, port):
    with pytest.raises(OmniscsError, match="--frame 9 is out of range: nsg-test has frames 0 to 3"):
        serve(open_target(checkpoint), port=port, frame=9)


def test_serve_announces_its_url_and_stops_cleanly(checkpoint, port):
    import socket

    stop, urls = threading.Event(), []
    worker = threading.Thread(target=serve, args=(open_target(checkpoint),),
                              kwargs=dict(port=port, ready=urls.append, stop=stop))
    worker.start()
    try:
        for _ in range(100):
            if urls:
                break
            worker.join(0.1)
        # the port asked for, or the next free one when another process took it meanwhile
        assert len(urls) == 1 and urls[0].startswith("http://127.0.0.1:")
        served = int(urls[0].rsplit(":", 1)[1])
        assert port <= served < port + 10
    finally:
        stop.set()
        worker.join(10)
    assert not worker.is_alive()
    with socket.socket() as s:  # the port is free again
        s.bind(("127.0.0.1", served))


def test_a_click_ray_meets_the_road_in_front_of_the_camera_only():
    from omniscs.viewer.state import ray_ground_point

    assert np.allclose(ray_ground_point([0, 0, 10], [1, 0, -1], 0.5), [9.5, 0.0, 0.5])
    assert ray_ground_point([0, 0, 10], [1, 0, 0], 0.0) is None      # level: never
    assert ray_ground_point([0, 0, 10], [1, 0, 0.2], 0.0) is None    # above the horizon: behind the camera only


def test_an_inserted_overturned_model_is_the_spec_saved_and_renders_as_omniscs_render_does(app, fitted, checkpoint,
                                                                                          tmp_path):
    from omniscs.cli import app as cli

    _, graph = fitted
    app.model_list.value = "nsg:1 car"
    app.lie.value = "overturned"
    ego = graph.world_from_ego[2]
    tid = app.insert_at(ego[0, 3] + 16.0, ego[1, 3] - 3.0, 0.0)
    assert tid == 3 and app.selected == 3 and "agent.3" in app.target.layers and "agent.3" in app._splats
    assert [b.track_id for b in app.target.frame_state(0).boxes] == [1, 3]  # car 2 appears in frame 1
    spec = json.loads(app.save().read_text())
    assert len(spec) == 1 and spec[0]["op"] == "insert" and spec[0]["roll_deg"] == 180.0
    assert spec[0]["asset_id"] == "nsg:1" and spec[0]["category"] == "car"
    x, y, z, yaw = spec[0]["pose"]
    assert (x, y) == pytest.approx((ego[0, 3] + 16.0, ego[1, 3] - 3.0))
    assert z == pytest.approx(graph.agent(1).size[2] / 2)  # the upright box's centre; the insert rests it on its roof
    assert yaw == pytest.approx(0.0, abs=1e-6)  # the ego's heading: no scene, no lanes
    box = app.target.session.graph.agent(3).world_from_agent[2]
    assert box[2, 2] == pytest.approx(-1.0)  # on its roof
    out = tmp_path / "inserted.png"
    result = CliRunner().invoke(cli, ["render", str(checkpoint), "--frame", "2", "--edit", f"@{tmp_path / 'spec.json'}",
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    shown = rendered_image(app.target.session.graph, "CAM_FRONT", 2)
    assert np.array_equal(shown, np.asarray(Image.open(out).convert("RGB")))
    assert not np.array_equal(shown, rendered_image(graph, "CAM_FRONT", 2))
    app.remove_selected()  # an inserted agent removed is simply not inserted
    assert app.target.session.edits() == [] and "agent.3" not in app._splats


def test_giving_an_agent_another_model_swaps_its_splats_and_keeps_its_motion(app, fitted):
    _, graph = fitted
    app.select(1)
    app.model_list.value = "nsg:2 car"
    app.replace_selected()
    assert app.target.session.spec() == [{"op": "replace_model", "track_id": 1, "asset_id": "nsg:2", "size": None}]
    edited = app.target.session.graph.agent(1)
    assert np.array_equal(edited.world_from_agent, graph.agent(1).world_from_agent)  # same box, same motion
    assert len(app.target.layers["agent.1"]) == len(graph.agent(2).gaussians)


def test_a_pool_model_inserted_in_the_viewer_renders_with_the_same_pool(fitted, checkpoint, port, tmp_path):
    import viser
    from appearance_fixtures import small_pool

    from omniscs.cli import app as cli

    _, graph = fitted
    pool = small_pool(tmp_path / "pool", assets=("box_truck-0020",), gaussians=600)
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, open_target(checkpoint, pool=pool.root), frame=2, edits_out=tmp_path / "truck.json")
    try:
        truck = next(label for label in app._models if label.startswith("pm-") and label.endswith(" truck"))
        app.model_list.value = truck
        app.lie.value = "on its side"
        ego = graph.world_from_ego[2]
        app.insert_at(ego[0, 3] + 18.0, ego[1, 3] + 3.0, 0.0)
        spec = app.save()
        assert f"--pool {pool.root}" in app.status.content  # the render hint names the pool the spec needs
    finally:
        app.close()
        server.stop()
    assert json.loads(spec.read_text())[0]["asset_id"] == truck.split(" ")[0]
    out = tmp_path / "truck.png"
    result = CliRunner().invoke(cli, ["render", str(checkpoint), "--frame", "2", "--edit", f"@{spec}", "--pool",
                                      str(pool.root), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert np.array_equal(rendered_image(app.target.session.graph, "CAM_FRONT", 2),
                          np.asarray(Image.open(out).convert("RGB")))


def test_the_splat_share_control_redraws_the_most_opaque_part_of_the_graph(app, fitted):
    _, graph = fitted
    app.set_splat_share(25)
    kept = round(graph.n_gaussians * 0.25)
    assert sum(len(s) for s in app.target.layers.values()) == kept
    assert sum(len(s) for s in splat_layers(graph, kept).values()) == kept
    assert f"{kept:,} of {graph.n_gaussians:,} Gaussians drawn" in app.summary.content
    assert set(app._splats) == {k for k, s in app.target.layers.items() if len(s)}
    app.set_splat_share(100)
    assert sum(len(s) for s in app.target.layers.values()) == graph.n_gaussians


def test_a_graph_without_agent_nodes_opens_with_nothing_to_pick(tmp_path, port):
    import viser
    from annotate_fixtures import fitted_scene

    fitted_scene(tmp_path, agents=(), n_frames=2, n_cameras=1, iterations=20)
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, open_target(tmp_path / "graph"), frame=1, edits_out=tmp_path / "none.json")
    try:
        assert app.agent_list.options == (NO_AGENT,) and app._models == {}
        assert app.target.frame_state(1).boxes == () and app.image.image.shape[:2] == (54, 96)
        app.select(None)
        assert app.save() is not None and app.target.session.spec() == []
    finally:
        app.close()
        server.stop()
