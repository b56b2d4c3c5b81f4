"""Variants in the viewer: a behaviour variant puts agents and the ego where the render-and-annotate stage puts them
(and the camera view is its image); an appearance variant is its edit list, and later edits add to it."""
from __future__ import annotations

import json

import numpy as np
import pytest

from omniscs.edits import parse_edits
from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform
from omniscs.viewer.state import ADVERSARY_COLOUR
from omniscs.viewer.targets import ORIGINAL_COLOUR, open_target
from omniscs.viewer.variants import read_variants, variant_summary


@pytest.fixture(scope="module")
def behaviour(fitted, tmp_path_factory):
    """(variants.json path, the variant): the log replayed with car 2 drifting 0.4 m per frame to its right."""
    from annotate_fixtures import logged_variant

    scene, _ = fitted
    variant = logged_variant(scene, shift={2: 0.4}, adversary=2)
    variant.update(success=True, plausible=True, collision_time_s=0.3, min_distance_m=0.0, kind="cut_in")
    path = tmp_path_factory.mktemp("behaviour") / "variants.json"
    path.write_text(json.dumps([variant]))
    return path, variant


def test_a_behaviour_variant_places_agents_and_ego_as_the_annotate_stage_does(fitted, checkpoint, behaviour):
    from omniscs.annotate.frames import variant_frames

    scene, graph = fitted
    path, variant = behaviour
    target = open_target(checkpoint, variants=path)
    target.pick_variant(0)
    frames = variant_frames(scene, variant, frozenset(graph.agent_ids))
    assert frames.n_frames == graph.n_frames
    for t, f in enumerate(frames.scene_frames):
        state = target.frame_state(int(f))
        assert np.allclose(state.world_from_ego, frames.world_from_ego[t], atol=1e-9)
        placed = {b.track_id: b.world_from_box for b in state.boxes}
        for tid, pose in frames.node_poses[t].items():
            assert np.allclose(placed[tid], pose, atol=1e-9), (f, tid)
    assert target.adversary == 2
    tinted = [t.track_id for t in target.trajectories() if t.tint == ORIGINAL_COLOUR]
    assert tinted == [2]  # the log's path of the car the variant moved, beneath its new one


def test_a_behaviour_variants_camera_view_is_the_image_the_annotate_stage_writes(fitted, checkpoint, behaviour,
                                                                                 tmp_path):
    from omniscs.annotate.variant import write_annotated_variant
    from omniscs.scene import load_scene

    scene, graph = fitted
    path, variant = behaviour
    write_annotated_variant(graph, scene, variant, tmp_path / "store", "nsg-test-v000")
    written = load_scene(tmp_path / "store")
    target = open_target(checkpoint, variants=path)
    target.pick_variant(0)
    for t in range(written.n_frames):
        shown = target.camera_image("CAM_FRONT", t, boxes=False)
        # the stage renders through its annotator (labels, culled nodes): the same image up to float rounding
        diff = np.abs(shown.astype(int) - written.image("CAM_FRONT", t).astype(int))
        assert diff.max() <= 1 and (diff > 0).mean() < 0.02, (t, diff.max(), (diff > 0).mean())


def test_an_appearance_variant_is_its_edits_and_later_edits_add_to_them(fitted, checkpoint, port, tmp_path):
    import viser

    from omniscs.viewer.app import ViewerApp

    scene, graph = fitted
    edits = [{"op": "replace_model", "track_id": 1, "asset_id": "nsg:2", "size": None}]
    variant = {"variant_id": "a000", "scene_id": scene.scene_id, "kind": "appearance", "placement": "replace",
               "track_id": 1, "adversary": 1, "object_id": "nsg:2", "category": "car", "edits": edits}
    (tmp_path / "appearance").mkdir()
    (tmp_path / "appearance" / "variants.json").write_text(json.dumps([variant]))
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, open_target(checkpoint, variants=tmp_path / "appearance"), frame=2,
                    edits_out=tmp_path / "more.json")
    try:
        app.pick_variant("a000")
        assert app.target.session.edits() == parse_edits(edits)
        assert len(app.target.layers["agent.1"]) == len(graph.agent(2).gaussians)  # its new model is drawn
        assert "a000" in app.variant_figures.content and "nsg:2" in app.variant_figures.content
        app.select(2)
        app.move_selected(graph.agent(2).world_from_agent[2] @ make_transform(np.eye(3), [1.0, 0.0, 0.0]))
        saved = json.loads(app.save().read_text())
        assert saved[0] == edits[0] and saved[1]["op"] == "translate" and len(saved) == 2
        app.pick_variant("(the log)")
        assert app.target.session.edits() == [] and app.target.adversary is None
    finally:
        app.close()
        server.stop()


def test_the_adversary_is_drawn_red_on_the_camera_view(fitted, checkpoint, behaviour):
    path, _ = behaviour
    target = open_target(checkpoint, variants=path)
    plain = target.camera_image("CAM_FRONT", 1, boxes=True)
    target.pick_variant(0)
    boxed = target.camera_image("CAM_FRONT", 1, boxes=True)
    red = np.all(np.abs(boxed.astype(int) - np.array(ADVERSARY_COLOUR)) <= 40, axis=2)
    assert red.sum() > 10 and not np.all(np.abs(plain.astype(int) - np.array(ADVERSARY_COLOUR)) <= 40, axis=2).any()


def test_variant_figures_read_like_the_catalog(behaviour):
    _, variant = behaviour
    text = variant_summary(variant)
    assert "adversary track 2" in text and "contact at 0.3 s" in text and "reaches the ego: yes" in text


def test_a_bad_variants_file_is_one_error(fitted, checkpoint, tmp_path):
    with pytest.raises(OmniscsError, match="does not exist"):
        read_variants(tmp_path / "nowhere.json")
    (tmp_path / "v.json").write_text('{"variant_id": "v0"}')
    with pytest.raises(OmniscsError, match="not a list of variants"):
        read_variants(tmp_path / "v.json")
    (tmp_path / "w.json").write_text('[{"variant_id": "v0", "scene_id": "elsewhere", "edits": []}]')
    with pytest.raises(OmniscsError, match="holds variants of \\['elsewhere'\\]"):
        open_target(checkpoint, variants=tmp_path / "w.json")


def test_a_variants_folder_of_a_workspace_opens_on_the_graph_it_was_drawn_on(fitted, checkpoint, behaviour,
                                                                            tmp_path):
    import os
    import shutil

    scene, graph = fitted
    _, variant = behaviour
    ws = tmp_path / "ws"
    old = shutil.copytree(checkpoint, ws / "models" / scene.scene_id / "nsg-fast-old")
    shutil.copytree(scene.path, ws / "scenes" / scene.scene_id)
    folder = ws / "variants" / scene.scene_id / "behavior-0123"
    folder.mkdir(parents=True)
    (folder / "variants.json").write_text(json.dumps([variant]))
    newer = shutil.copytree(checkpoint, ws / "models" / scene.scene_id / "nsg-fast-new")  # fitted after the draw
    t = (folder / "variants.json").stat().st_mtime
    os.utime(old / "graph.json", (t - 10, t - 10))
    os.utime(newer / "graph.json", (t + 10, t + 10))
    target = open_target(folder)
    assert target.path == old and target.scene is not None and target.scene.path == ws / "scenes" / scene.scene_id
    assert [v["variant_id"] for v in target.variants] == [variant["variant_id"]]
    target.pick_variant(0)
    assert target.adversary == 2
    with pytest.raises(OmniscsError, match="--variants goes with a scene-graph checkpoint"):
        open_target(folder, variants=folder)
    shutil.rmtree(ws / "models")
    with pytest.raises(OmniscsError, match=f"no fitted scene graph of {scene.scene_id}"):
        open_target(folder)
