"""A neutral road map of one log (drivable polygons, lane centrelines, known extent; world frame), JSON round-trippable.

Sources that know their roads produce it (the procedural world from its layout); models read it without knowing
where it came from. Logs without one (recorded logs with no map) leave it None and models derive what they need.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from omniscs.errors import OmniscsError

#: Bump when the JSON layout of a RoadMap changes.
ROAD_MAP_VERSION = 1


def in_convex_polygon(xy: np.ndarray,    # [N, 2] points
                      poly: np.ndarray,  # [K, 2] convex polygon, counter-clockwise
                      ) -> np.ndarray:   # [N] bool, True on the boundary too
    inside = np.ones(len(xy), dtype=bool)
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        cross = (b[0] - a[0]) * (xy[:, 1] - a[1]) - (b[1] - a[1]) * (xy[:, 0] - a[0])
        inside &= cross >= -1e-9
    return inside


@dataclass(frozen=True)
class RoadMap:
    """Where vehicles may drive and along which lanes, in the world frame (metres)."""

    drivable_polygons: tuple[np.ndarray, ...]
    """Convex, counter-clockwise polygons [K, 2] whose union is the drivable area."""
    lane_centrelines: tuple[np.ndarray, ...]
    """One polyline [K, 2] per lane in driving order (the first point is where traffic enters): its direction."""
    extent_min: np.ndarray
    """[2] lower-left corner of the box the map knows (outside it nothing is known: the map stops, not the road)."""
    extent_max: np.ndarray
    """[2] upper-right corner of that box."""

    def is_drivable(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] world -> [N] bool
        return in_any_convex_polygon(xy, self.drivable_polygons)

    # -- JSON -----------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"version": ROAD_MAP_VERSION,
                "drivable_polygons": [np.asarray(p, dtype=np.float64).tolist() for p in self.drivable_polygons],
                "lane_centrelines": [np.asarray(c, dtype=np.float64).tolist() for c in self.lane_centrelines],
                "extent_min": np.asarray(self.extent_min, dtype=np.float64).tolist(),
                "extent_max": np.asarray(self.extent_max, dtype=np.float64).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "RoadMap":
        if d.get("version") != ROAD_MAP_VERSION:
            raise OmniscsError(f"road map version {d.get('version')!r} is not {ROAD_MAP_VERSION}, the one this "
                               "omniscs reads; write the map again with this version")
        return cls(drivable_polygons=tuple(np.asarray(p, dtype=np.float64).reshape(-1, 2)
                                           for p in d["drivable_polygons"]),
                   lane_centrelines=tuple(np.asarray(c, dtype=np.float64).reshape(-1, 2)
                                          for c in d["lane_centrelines"]),
                   extent_min=np.asarray(d["extent_min"], dtype=np.float64),
                   extent_max=np.asarray(d["extent_max"], dtype=np.float64))

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> "RoadMap":
        return cls.from_dict(json.loads(text))


def in_any_convex_polygon(xy: np.ndarray, polygons) -> np.ndarray:  # [N, 2], [[K, 2], ...] -> [N] bool
    """Whether each point lies in at least one of the convex polygons."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    inside = np.zeros(len(xy), dtype=bool)
    for poly in polygons:
        inside |= in_convex_polygon(xy, poly)
    return inside
