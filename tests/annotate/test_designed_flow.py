"""A designed scenario (an edit spec such as `omniscs view` saves: a cut-in path and an overturned truck) given to
generate_dataset with annotate: rendered and annotated as one designed variant (d000) beside nothing else, judged by
the quality gates, catalogued as kind designed, and counted in the dataset card."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from appearance_fixtures import small_pool
from nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene
from omniscs import catalog
from omniscs.nsg.config import PRESETS
from omniscs.pipeline.request import RunRequest

AGENTS = ({"x": 14.0, "y": 0.0, "speed": 4.0, "asset": "sedan-0003"},
          {"x": 4.0, "y": 3.3, "speed": 9.0, "asset": "sedan-0011"})
N_FRAMES = 16
CAR_Z = 0.75  # nsg_fixtures' car: 1.5 m high, its box centre half that above the road
#: Two tiny fits and renders, about 50 s: in `make test-slow`.
pytestmark = pytest.mark.slow


def cut_in(track_id: int = 2) -> dict:
    """Track 2 (left lane, 9 m/s) steers into the ego's lane between frames 4 and 10."""
    waypoints = []
    for k in range(N_FRAMES):
        s = float(np.clip((k - 4) / 6.0, 0.0, 1.0))
        y = 3.3 * (1.0 - s)
        yaw = -0.3 if 0.0 < s < 1.0 else 0.0
        waypoints.append([4.0 + 0.9 * k, y, CAR_Z, yaw])
    return {"op": "set_trajectory", "track_id": track_id, "waypoints": waypoints}


def overturned(pool, track_id: int, x: float, y: float) -> dict:
    table = pool.table()
    row = table[table.category == "truck"].iloc[0]
    return {"op": "insert", "track_id": track_id, "asset_id": row.model_id, "category": "truck",
            "pose": [x, y, float(row.height) / 2, 0.0], "roll_deg": 180.0}


@pytest.fixture(scope="module")
def built(prefect_harness, tmp_path_factory):
    from flows.generate import generate_dataset

    root = tmp_path_factory.mktemp("designed")
    pool = small_pool(root / "pool", ("box_truck-0020",))
    store = write_nsg_scene(root / "in", nsg_world(agents=AGENTS, n_frames=N_FRAMES, n_cameras=1, width=128,
                                                   height=72))
    spec = [cut_in(), overturned(pool, 7, 24.0, 0.0)]
    (root / "saved.json").write_text(json.dumps(spec))
    mp = pytest.MonkeyPatch()
    mp.setitem(PRESETS, "fast", tiny_fit_config(40))
    try:
        # A 40-step fit renders at about 19.5 dB: the fidelity floor is lowered for it.
        result = generate_dataset(RunRequest(sources=[str(store)], workspace=str(root / "ws"), run_id="d1",
                                             previews=False, fit_preset="fast", annotate=True, edits=spec,
                                             pool=str(pool.root), min_fidelity_psnr=12.0))
    finally:
        mp.undo()
    return root, pool, spec, result


def test_a_designed_scenario_is_rendered_annotated_and_catalogued_as_one_variant(built):
    root, _, spec, result = built
    stages = result["scenes"][0]["stages"]
    assert "behavior" not in stages and "appearance" not in stages  # neither stage runs: only the design
    assert stages["annotate"]["info"]["n_variants"] == 1
    assert stages["annotate"]["info"]["verdicts"] == {"d000": {"passed": True, "reasons": []}}
    saved = json.loads((Path(stages["annotate"]["path"]) / "designed.json").read_text())
    assert saved[0]["edits"][0]["op"] == "set_trajectory" and saved[0]["adversary"] == 2
    assert saved[0]["tracks"] == [2, 7] and saved[0]["colour"] is not None
    cat = catalog.catalog_root(root / "ws")
    (v,) = catalog.query(cat, "SELECT kind, placement, adversary, object_id, passed_gates FROM variants").to_pylist()
    assert (v["kind"], v["placement"], v["adversary"], v["passed_gates"]) == ("designed", "designed", 2, True)
    assert v["object_id"] == spec[1]["asset_id"]
    # the annotations follow the design: the inserted truck is labelled upside down in its place, and track 2's
    # box ends in the ego's lane
    ann = catalog.query(cat, "SELECT frame_idx, track_id, category, cx AS x, cy AS y FROM annotations ORDER BY frame_idx"
                        ).to_pylist()
    truck = [a for a in ann if a["track_id"] == 7]
    assert truck and all(a["category"] == "truck" and abs(a["x"] - 24.0) < 0.05 for a in truck)
    late = [a for a in ann if a["track_id"] == 2 and a["frame_idx"] >= 11]
    assert late and all(abs(a["y"]) < 0.05 for a in late)
    card = json.loads((Path(result["dataset_path"]) / "dataset.json").read_text())
    assert card["counts"]["variants_by_level"]["designed"] == 1
    assert card["gates"]["requested"]["designed"] == card["gates"]["produced"]["designed"] == 1
    assert "1 designed" in (Path(result["dataset_path"]) / "README.md").read_text()


def test_a_designed_object_no_camera_sees_fails_the_visibility_gate_and_says_which(built, prefect_harness):
    from flows.generate import generate_dataset
    from omniscs.errors import OmniscsError

    root, pool, _, result = built
    hidden = [overturned(pool, 8, -40.0, 0.0)]  # 40 m behind the ego's start: the one front camera never sees it
    mp = pytest.MonkeyPatch()
    mp.setitem(PRESETS, "fast", tiny_fit_config(40))
    try:
        with pytest.raises(OmniscsError, match=r"no variant passed the quality gates .*edited track 8 is visible in "
                                               r"0 frame\(s\)"):
            generate_dataset(RunRequest(sources=[result["scenes"][0]["stages"]["ingest"]["path"]],
                                        workspace=str(root / "ws"), run_id="d2", previews=False, fit_preset="fast",
                                        annotate=True, edits=hidden, pool=str(pool.root), min_fidelity_psnr=12.0))
    finally:
        mp.undo()
