"""Which boxes an annotator labels: nuScenes' annotators label an object from where the LiDAR or a camera first
shows it to where they last do, through occlusions in between, and never an object no sensor shows. The exporters
and the dataset card count boxes by this one rule."""
from __future__ import annotations

from typing import Hashable, Iterable


def captured(lidar_points: int, visible_pixels: int) -> bool:
    """A box a sensor captured: it has LiDAR points, or visible pixels in some camera; visible pixels that are not
    known (-1, e.g. a recorded log's own annotation, which an annotator made) count as captured."""
    return int(lidar_points) > 0 or int(visible_pixels) != 0


def labelled(boxes: Iterable[tuple[Hashable, Hashable, int, bool]]) -> set:
    """The keys of the boxes an annotator labels, from (key, track, order, captured) per box: per track, those from
    its first captured box to its last (by ``order``, e.g. the frame index)."""
    tracks: dict = {}
    for key, track, order, hit in boxes:
        tracks.setdefault(track, []).append((order, key, hit))
    keep = set()
    for rows in tracks.values():
        rows.sort(key=lambda r: r[0])
        hits = [i for i, r in enumerate(rows) if r[2]]
        if hits:
            keep.update(r[1] for r in rows[hits[0]:hits[-1] + 1])
    return keep
