"""Shared pieces of the export tests: two small rendered synthetic scenes (a straight road and a 4-way
intersection), rendered once per test process, and the devkit objects read from an export."""
from __future__ import annotations

from pathlib import Path

from omniscs.scene import SyntheticSource, write_synthetic_scene
from tests.dataset_fixtures import FIXTURE_SOURCE, synthetic_store

#: A 4-way intersection (junction, connectors, crossings, stop lines) with the fixture's rig and length.
INTERSECTION_SOURCE = SyntheticSource(template="intersection", seed=1, n_frames=FIXTURE_SOURCE.n_frames,
                                      n_cameras=6, width=FIXTURE_SOURCE.width, height=FIXTURE_SOURCE.height)

_CACHE: dict[str, Path] = {}


def two_stores(tmp_path_factory) -> list[Path]:
    """The straight-road fixture store and an intersection store."""
    if "intersection" not in _CACHE:
        _CACHE["intersection"] = write_synthetic_scene(INTERSECTION_SOURCE,
                                                       tmp_path_factory.mktemp("intersection") / "store")
    return [synthetic_store(tmp_path_factory), _CACHE["intersection"]]
