"""Placement settings (``omniscs.scs.appearance.placement``): the names of the checks, the constants they share and
``PlacementConfig``."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from omniscs.errors import OmniscsError

#: track_id of the ego vehicle's box in ``Obstacles``.
EGO_TRACK_ID = -1
#: Height of the ego's box, metres: scene stores record only its footprint (``EgoBox`` in
#: ``omniscs.scs.behavior.tracks``); this is the value the closed-loop simulator reports for it.
EGO_HEIGHT_M = 1.6
#: Names of the checks, in the order they are reported.
CHECKS = ("on_road", "no_overlap", "visible", "in_range")
#: Rejections of proposals that passed every check but overlapped a placement accepted before them.
OVERLAPS_ACCEPTED = "overlaps_accepted"
YAW_MODES = ("lane", "uniform", "fixed")
#: Proposals drawn per batch by the sampler (part of what a seed reproduces: changing it changes the draws).
PROPOSAL_BATCH = 64


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class PlacementConfig:
    """What makes a placement valid and how the sampler proposes placements (world frame, metres, radians)."""

    distance_m: tuple[float, float] = (8.0, 30.0)
    """[min, max] horizontal distance from the camera (``in_range``; the sampler draws uniformly in it)."""
    min_visible_frames: int = 3
    """``visible``: the object must be in view in at least this many frames (k)."""
    min_in_image_fraction: float = 0.5
    """``visible``: share of the projected box's bounding rectangle that must lie inside the image."""
    clearance_m: float = 0.3
    """``no_overlap``: boxes closer than this (along some separating axis, or in height) count as overlapping."""
    road_margin_m: float = 0.0
    """``on_road``: the footprint grown by this much on every side must stay on the drivable area."""
    max_proposals: int = 2000
    """The sampler gives up after this many proposals."""
    max_distance_m: float = 60.0
    """``visible``: a box centre further than this from the camera (3D) does not count as visible."""
    near_plane_m: float = 0.5
    """``visible``: every box corner must lie at least this far in front of the camera (along its z)."""
    yaw_mode: str = "uniform"
    """Sampler: 'uniform' (yaw uniform in [-pi, pi)), 'fixed' (``yaw``) or 'lane' (the nearest lane's direction
    + ``yaw`` ± up to ``lane_yaw_jitter``; uniform where no lane is near)."""
    yaw: float = 0.0
    """'fixed': the world yaw of every placement; 'lane': an offset added to the lane direction (pi: against
    traffic, pi/2: across the lane)."""
    lane_yaw_jitter: float = math.radians(10.0)
    """'lane': the largest random offset from the lane direction, radians."""
    camera: str | None = None
    """Camera the object must be visible in and proposals are drawn in front of; None: any camera."""

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.distance_m)
        numbers = {f.name: getattr(self, f.name) for f in fields(self)
                   if f.name not in ("distance_m", "yaw_mode", "camera")}
        bad = [k for k, v in numbers.items() if not np.isfinite(v)] + (
            ["distance_m"] if not (np.isfinite(lo) and np.isfinite(hi)) else [])
        if bad:
            raise OmniscsError(f"placement config: {', '.join(bad)} must be finite numbers")
        if not 0.0 <= lo <= hi:
            raise OmniscsError(f"placement distance [{lo}, {hi}] m: need 0 <= min <= max")
        if self.min_visible_frames < 0 or not 0.0 <= self.min_in_image_fraction <= 1.0:
            raise OmniscsError("placement config: min_visible_frames must be >= 0 and min_in_image_fraction in [0, 1]")
        if self.clearance_m < 0 or self.road_margin_m < 0 or self.lane_yaw_jitter < 0:
            raise OmniscsError("placement config: clearance_m, road_margin_m and lane_yaw_jitter must be >= 0")
        if self.max_proposals < 1 or self.max_distance_m <= 0 or self.near_plane_m <= 0:
            raise OmniscsError("placement config: max_proposals must be >= 1, max_distance_m and near_plane_m > 0")
        if self.yaw_mode not in YAW_MODES:
            raise OmniscsError(f"placement yaw mode {self.yaw_mode!r} is unknown; use one of {', '.join(YAW_MODES)}")


def positive_size(size, what: str = "object size") -> np.ndarray:
    s = np.asarray(size, dtype=np.float64).reshape(-1)
    if s.shape != (3,) or not np.isfinite(s).all() or (s <= 0).any():
        raise OmniscsError(f"{what} {np.asarray(size).tolist()} must be three finite positive numbers "
                           "(length, width, height in metres)")
    return s
