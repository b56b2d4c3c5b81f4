"""The closed-loop tests share one fitted scene per test process (the fit takes about 7 s)."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def world(tmp_path_factory):
    """(scene, graph, log scenario) of ``closedloop_fixtures``' log; the scene store is at ``<root>/scene`` and the
    graph at ``<root>/graph`` (``world_root``)."""
    from annotate_fixtures import fitted_scene
    from closedloop_fixtures import N_FRAMES
    from omniscs.closedloop.scenario import log_scenario

    root = tmp_path_factory.mktemp("closedloop-world")
    scene, graph = fitted_scene(root, n_frames=N_FRAMES, n_cameras=1, iterations=150)
    return scene, graph, log_scenario(scene)


@pytest.fixture(scope="session")
def world_root(world):
    return world[0].path.parent


@pytest.fixture(scope="module")
def workspace(world, world_root, tmp_path_factory):
    """A workspace holding the log's scene store, its fitted graph and a behaviour variant (``stopping_variant``,
    variant id "stop"), as ingest, fit and scs behavior would leave them; one copy per test module."""
    import json
    import shutil

    from closedloop_fixtures import stopping_variant
    from omniscs.pipeline import layout

    scene = world[0]
    ws = tmp_path_factory.mktemp("closedloop-ws")
    shutil.copytree(world_root / "scene", layout.scene_folder(ws, "ingest", scene.scene_id))
    shutil.copytree(world_root / "graph", layout.stage_folder(ws, "fit", scene.scene_id, "nsg-test-graph"))
    variants = layout.stage_folder(ws, "behavior", scene.scene_id, "behavior-test") / "variants.json"
    variants.parent.mkdir(parents=True)
    variants.write_text(json.dumps([stopping_variant(scene)]))
    return ws
