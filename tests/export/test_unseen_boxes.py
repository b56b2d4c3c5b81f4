"""The nuScenes exporter labels an object from where a sensor first captures it to where one last does, like
nuScenes' annotators; an object no sensor captures is not labelled (``keep_unseen`` keeps every box)."""
from __future__ import annotations

import json

import pandas as pd
import pytest

from omniscs.export import export_scenes
from omniscs.export.nuscenes import seen_span
from omniscs.scene import load_scene
from tests.export.export_fixtures import two_stores


def _rows(spec: dict[int, list[tuple[int, int]]]) -> tuple[pd.DataFrame, dict[int, int]]:
    """{track id: [(LiDAR points, visible pixels) per keyframe]} -> keyframe box rows (sorted by frame) and the
    points per index label."""
    rows = [{"frame_idx": f, "track_id": tid, "visible_pixels": pixels, "points": points}
            for tid, boxes in spec.items() for f, (points, pixels) in enumerate(boxes)]
    frame = pd.DataFrame(rows).sort_values(["frame_idx", "track_id"]).reset_index(drop=True)
    frame.index = frame.index * 10 + 3  # labels that are not positions
    return frame, dict(zip(frame.index, frame.points))


def test_the_span_runs_from_the_first_to_the_last_capture_of_each_track():
    rows, points = _rows({
        1: [(0, 0), (0, 40), (0, 0), (0, 0), (5, 0), (0, 0)],   # seen at 1 (camera) and 4 (LiDAR): 1..4
        2: [(0, 0)] * 6,                                        # never seen: no box
        3: [(0, -1)] * 6,                                       # visible pixels unknown (a recorded log): all
        4: [(3, 0), (0, 0), (0, 0), (0, 0), (0, 0), (0, 0)],    # seen first only: frame 0
    })
    kept = rows.loc[seen_span(rows, points)]
    by_track = {t: sorted(g.frame_idx) for t, g in kept.groupby("track_id")}
    assert by_track == {1: [1, 2, 3, 4], 3: [0, 1, 2, 3, 4, 5], 4: [0]}
    assert list(kept.index) == [i for i in rows.index if i in set(kept.index)]  # the rows' order is kept


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    stores = two_stores(tmp_path_factory)
    out = tmp_path_factory.mktemp("unseen")
    seen = export_scenes(stores, "nuscenes", out / "seen", version="v1.0-mini")
    every = export_scenes(stores, "nuscenes", out / "every", version="v1.0-mini", keep_unseen=True)
    return stores, seen, every


def _table(root, name):
    return json.loads((root / "v1.0-mini" / f"{name}.json").read_text())


def test_an_export_leaves_out_only_boxes_no_sensor_captured_outside_their_span(exports):
    stores, seen, every = exports
    kept = {a["token"]: a for a in _table(seen, "sample_annotation")}
    allb = {a["token"]: a for a in _table(every, "sample_annotation")}
    assert set(kept) < set(allb), "the stores hold boxes no sensor captures"
    dropped = [allb[t] for t in set(allb) - set(kept)]
    assert all(a["num_lidar_pts"] == 0 for a in dropped)
    boxes = pd.concat([load_scene(s).boxes for s in stores])
    assert (boxes.visible_pixels >= 0).all(), "the synthetic stores know every box's visible pixels"
    # every instance left starts and ends with a box that has LiDAR points or was seen by a camera, and its chain
    # links only kept boxes
    instances = _table(seen, "instance")
    assert len(instances) < len(_table(every, "instance"))
    for inst in instances:
        chain, token = [], inst["first_annotation_token"]
        while token:
            chain.append(kept[token])
            token = kept[token]["next"]
        assert chain[-1]["token"] == inst["last_annotation_token"] and len(chain) == inst["nbr_annotations"]
    # within 50 m the share with points can only grow
    from omniscs.export.coverage import nuscenes_point_coverage
    before = nuscenes_point_coverage(every, "v1.0-mini")
    after = nuscenes_point_coverage(seen, "v1.0-mini")
    assert after.share >= before.share and after.within <= before.within
