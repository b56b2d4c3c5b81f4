"""The simulated LiDAR of rendered variants, and the count of its points in each box.

The default sensor is LIDAR_TOP-like: a spinning LiDAR at the ego's LiDAR mount (32 beams between +10.67° and
-30.67°, 360° of azimuth, 70 m), whose beams are looked up in depth the scene graph renders in a ring of level
pinhole views around the mount, so a box behind the ego gets points as it would in a log. The older sampling of the
dataset cameras' own depth (``lidar_from_depth``) stays for runs that want no extra render."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omniscs.annotate.config import AnnotateConfig
from omniscs.errors import OmniscsError
from omniscs.geometry import (intrinsics_matrix, make_transform, points_in_box, spinning_beam_directions,
                              transform_points, unproject)

#: Pixels added on every side of a ring view beyond what its beams need: a beam on the sector's edge still lands
#: inside the image, whatever the rounding.
RING_MARGIN_PX = 1
#: A beam counts as in front of a view when the cosine of its angle to the view's axis exceeds this.
MIN_AXIS_COS = 1e-6


@dataclass(frozen=True)
class RingView:
    """One pinhole view of the LiDAR ring: an OpenCV camera at the LiDAR's origin, level, looking along one azimuth."""

    K: np.ndarray                # [3, 3] float64 intrinsics (square pixels; the principal point sits off-centre
                                 # vertically: the beams reach further down than up)
    lidar_from_view: np.ndarray  # [4, 4] float64, no translation
    width: int
    height: int


def beam_directions(config: AnnotateConfig) -> np.ndarray:  # -> [beams * azimuth steps, 3] unit, LiDAR frame
    """The ring sensor's beams: ``lidar_beams`` elevations, 360° / ``lidar_horizontal_step_deg`` azimuths."""
    steps = max(1, int(round(360.0 / float(config.lidar_horizontal_step_deg))))
    return spinning_beam_directions(int(config.lidar_beams), float(config.lidar_min_elevation_deg),
                                    float(config.lidar_max_elevation_deg), steps)


def ring_views(config: AnnotateConfig) -> list[RingView]:
    """``lidar_ring_views`` level views at the LiDAR's origin, view i looking along azimuth 360° i / n (LiDAR frame:
    x forward, y left, z up), each wide enough for its sector of azimuth and tall enough for every beam elevation in
    it; pixels of ``lidar_ring_pixel_deg`` at the view's centre."""
    n = int(config.lidar_ring_views)
    half = math.pi / n  # half the sector of azimuth a view answers for
    f = 1.0 / math.tan(math.radians(float(config.lidar_ring_pixel_deg)))
    # A beam at elevation e and azimuth a off the view's axis lands at slope tan(e) / cos(a) above the axis: the
    # steepest slopes are at the sector's edge for beams pointing away from the horizon, at its centre otherwise.
    top_e, bottom_e = (math.tan(math.radians(float(e))) for e in (config.lidar_max_elevation_deg,
                                                                  config.lidar_min_elevation_deg))
    top = top_e / math.cos(half) if top_e >= 0 else top_e
    bottom = bottom_e / math.cos(half) if bottom_e < 0 else bottom_e
    half_width = math.ceil(f * math.tan(half)) + RING_MARGIN_PX
    width = 2 * half_width
    cy = math.ceil(f * top) + RING_MARGIN_PX
    height = cy + math.ceil(-f * bottom) + RING_MARGIN_PX
    K = intrinsics_matrix(f, f, float(half_width), float(cy))
    views = []
    for i in range(n):
        a = 2.0 * math.pi * i / n
        forward = np.array([math.cos(a), math.sin(a), 0.0])  # the view's z axis
        right = np.array([math.sin(a), -math.cos(a), 0.0])   # its x axis
        down = np.array([0.0, 0.0, -1.0])                    # its y axis
        views.append(RingView(K.copy(), make_transform(np.stack([right, down, forward], 1), np.zeros(3)),
                              width, height))
    return views


def lidar_from_views(views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],  # (depth [H, W], K, lidar_from_view)
                     directions: np.ndarray,      # [R, 3] unit beam directions, LiDAR frame
                     ego_from_lidar: np.ndarray,  # [4, 4]
                     max_range_m: float,
                     min_range_m: float = 0.0) -> np.ndarray:  # -> float32 [N, 4] ego frame, intensity 0
    """The returns of a spinning LiDAR whose beams are looked up in rendered depth: each beam takes the view it
    points most squarely into among those whose image holds it, the depth (metres along that view's axis; 0 = no
    surface) of the pixel it crosses, and ends at range depth / cos(angle to the axis). Every view's camera sits at
    the LiDAR's origin. A beam no view holds, over a pixel without a surface (the sky), with a depth that is not
    finite or a range outside (``min_range_m``, ``max_range_m``] gives no return. Intensity is 0: the scene graph
    knows no reflectivity."""
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    n = len(directions)
    best_cos = np.full(n, MIN_AXIS_COS)
    chosen = np.full(n, -1, dtype=np.int64)
    row = np.zeros(n, dtype=np.int64)
    col = np.zeros(n, dtype=np.int64)
    for i, (depth, K, lidar_from_view) in enumerate(views):
        lidar_from_view = np.asarray(lidar_from_view, dtype=np.float64)
        if not np.allclose(lidar_from_view[:3, 3], 0.0, atol=1e-9):
            raise OmniscsError(f"LiDAR view {i} is not at the LiDAR's origin (offset {lidar_from_view[:3, 3]} m): "
                               "a beam's depth can only be looked up from its own origin")
        h, w = depth.shape
        d_view = directions @ lidar_from_view[:3, :3]  # [R, 3] the beams in the view's frame
        z = d_view[:, 2]
        ahead = z > best_cos
        safe = np.where(ahead, z, 1.0)
        u = np.floor(K[0, 0] * d_view[:, 0] / safe + K[0, 2])  # pixel i spans [i, i + 1)
        v = np.floor(K[1, 1] * d_view[:, 1] / safe + K[1, 2])
        take = ahead & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        best_cos[take], chosen[take] = z[take], i
        col[take], row[take] = u[take].astype(np.int64), v[take].astype(np.int64)
    ranges = np.zeros(n)
    for i, (depth, _, _) in enumerate(views):
        mine = np.flatnonzero(chosen == i)
        ranges[mine] = np.asarray(depth, dtype=np.float64)[row[mine], col[mine]] / best_cos[mine]
    keep = (chosen >= 0) & np.isfinite(ranges) & (ranges > max(0.0, float(min_range_m))) \
        & (ranges <= float(max_range_m))
    xyz = transform_points(np.asarray(ego_from_lidar, dtype=np.float64), directions[keep] * ranges[keep, None])
    out = np.zeros((len(xyz), 4), np.float32)
    out[:, :3] = xyz
    return out


def lidar_from_depth(views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],  # (depth [H,W], K, ego_from_camera)
                     config: AnnotateConfig) -> np.ndarray:  # -> float32 [N, 4] ego frame, intensity 0
    """Points sampled from the dataset cameras' rendered depth like a spinning LiDAR's beams (rows and columns at
    the configured angular steps) over the cameras' fields of view only (``lidar_source`` cameras)."""
    points = []
    for depth, K, ego_from_camera in views:
        h, w = depth.shape
        du = max(1, int(round(K[0, 0] * np.tan(np.radians(config.lidar_horizontal_step_deg)))))
        dv = max(1, int(round(K[1, 1] * np.tan(np.radians(config.lidar_vertical_step_deg)))))
        v, u = np.mgrid[dv // 2:h:dv, du // 2:w:du]
        z = depth[v, u].astype(np.float64)
        uv = np.stack([u + 0.5, v + 0.5], -1).reshape(-1, 2)
        cam = unproject(uv, z.reshape(-1), K)
        keep = (z.reshape(-1) > 0) & (np.linalg.norm(cam, axis=1) <= config.lidar_max_range_m)
        points.append(transform_points(ego_from_camera, cam[keep]))
    xyz = np.concatenate(points) if points else np.zeros((0, 3))
    out = np.zeros((len(xyz), 4), np.float32)
    out[:, :3] = xyz
    return out


def points_in_boxes(points_ego: np.ndarray,      # [N, 3+] ego frame
                    ego_from_boxes: np.ndarray,  # [B, 4, 4]
                    sizes: np.ndarray,           # [B, 3] length, width, height
                    margin: float = 0.0) -> np.ndarray:  # -> [B] int64
    """How many points lie in each box grown by ``margin`` metres on every side."""
    counts = np.zeros(len(sizes), dtype=np.int64)
    order = np.argsort(points_ego[:, 0], kind="stable")
    xyz = points_ego[order, :3].astype(np.float64)  # sorted by x: a box's candidates are one slice
    for i, (T, size) in enumerate(zip(ego_from_boxes, sizes)):
        reach = 0.5 * float(np.linalg.norm(size)) + margin  # the box's bounding cube
        lo = int(np.searchsorted(xyz[:, 0], T[0, 3] - reach, side="left"))
        hi = int(np.searchsorted(xyz[:, 0], T[0, 3] + reach, side="right"))
        cand = xyz[lo:hi]
        near = np.abs(cand[:, 1:] - T[1:3, 3]).max(1) <= reach if len(cand) else np.zeros(0, bool)
        counts[i] = int(points_in_box(cand[near], T, size, margin).sum())
    return counts
