"""The viewer tests share one small fitted scene per test process (the fit takes a few seconds): two cars, the
second absent in frame 0, two cameras."""
from __future__ import annotations

import socket

import pytest

#: The car 11 m ahead in the ego lane, and one in the next lane that appears in frame 1.
AGENTS = ({"x": 11.0, "y": 0.0, "speed": 6.0, "asset": "sedan-0003"},
          {"x": 6.0, "y": 3.3, "speed": 9.0, "asset": "sedan-0011", "first": 1})


@pytest.fixture(scope="session")
def fitted(tmp_path_factory):
    """(scene, graph) of the fitted log; the store is at ``<root>/scene`` and the checkpoint at ``<root>/graph``."""
    from annotate_fixtures import fitted_scene

    root = tmp_path_factory.mktemp("viewer-world")
    return fitted_scene(root, agents=AGENTS, n_frames=4, n_cameras=2, iterations=100)


@pytest.fixture(scope="session")
def checkpoint(fitted):
    return fitted[0].path.parent / "graph"


@pytest.fixture
def port() -> int:
    """A port free on the loopback now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
