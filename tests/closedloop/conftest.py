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
