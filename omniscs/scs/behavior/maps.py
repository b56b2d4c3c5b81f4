"""Rasterised scene maps for the behaviour model: drivable area and lane centrelines (with direction).

Logs that bring a road map (``omniscs.roadmap.RoadMap``; synthetic scenes do) are rasterised from it; recorded
logs without one get a map derived from where vehicles were seen driving: corridors around the ego path and
moving tracks, plus the footprints of parked vehicles.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from omniscs.errors import OmniscsError
from omniscs.roadmap import RoadMap

#: Layers of SceneMap.layers, in order.
MAP_LAYERS = ("drivable", "centreline", "lane_dir_cos", "lane_dir_sin")


@dataclass(frozen=True)
class MapConfig:
    """How scene maps are rasterised (world-aligned grid around the ego path)."""

    resolution_m: float = 0.5
    """Raster cell size, metres."""
    margin_m: float = 100.0
    """The raster covers the ego path's bounding box grown by this many metres on every side."""
    lane_line_width_m: float = 1.5
    """Width of the painted lane-centreline band, metres (at least the map patches' cell size)."""
    corridor_half_width_m: float = 2.5
    """Logs without a map: box centres within this distance of a driven path count as drivable."""
    moving_path_m: float = 1.0
    """Logs without a map: a vehicle track that travels further than this contributes its path as a lane."""


@dataclass(frozen=True)
class CropSpec:
    """The map patch each agent sees, in its own frame (x forward, y left)."""

    x_min: float = -9.0
    """Rear edge of the patch, metres behind the agent's centre."""
    x_max: float = 39.0
    """Front edge of the patch, metres ahead."""
    half_width: float = 15.0
    """Half of the patch's lateral extent, metres."""
    resolution_m: float = 1.5
    """Cell size of the patch, metres."""

    @property
    def shape(self) -> tuple[int, int]:  # (rows = lateral, columns = longitudinal)
        return (int(round(2 * self.half_width / self.resolution_m)),
                int(round((self.x_max - self.x_min) / self.resolution_m)))


class SceneMap:
    """World-aligned raster of one scene: layers [C, H, W] (see MAP_LAYERS), row i at y0 + (i + 0.5) * res,
    column j at x0 + (j + 0.5) * res, and the distance (metres) from each cell to the drivable area.
    Its tensors are copied to the device of the points they are sampled at (once per device)."""

    def __init__(self, origin: np.ndarray, resolution: float, layers: np.ndarray, source: str,
                 road_map: RoadMap | None = None, extent: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.origin = np.asarray(origin, dtype=np.float64)  # [2] world xy of the raster's lower-left corner
        self.resolution = float(resolution)
        self.layers = np.ascontiguousarray(layers, dtype=np.float32)  # [C, H, W]
        self.source = source  # "road_map" or "derived"
        self.road_map = road_map  # exact drivable test when the map came from a RoadMap
        if extent is None:
            h, w = self.layers.shape[1:]
            extent = (self.origin.copy(), self.origin + np.array([w, h]) * self.resolution)
        self.extent = (np.asarray(extent[0], dtype=np.float64), np.asarray(extent[1], dtype=np.float64))
        outside = (self.layers[0] < 0.5).astype(np.uint8)
        self.outside_m = (cv2.distanceTransform(outside, cv2.DIST_L2, 5) * self.resolution).astype(np.float32)
        self._tensors: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}

    @property
    def shape(self) -> tuple[int, int]:
        return self.layers.shape[1], self.layers.shape[2]

    def tensors(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """layers [1, C, H, W] and distance outside the drivable area [1, 1, H, W] (float32) on ``device``."""
        device = torch.device(device)
        if device not in self._tensors:
            self._tensors[device] = (torch.from_numpy(self.layers)[None].to(device),
                                     torch.from_numpy(self.outside_m)[None, None].to(device))
        return self._tensors[device]

    def _pixel(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # [N, 2] -> rows [N], cols [N] (int)
        ij = np.floor((np.asarray(xy, dtype=np.float64) - self.origin) / self.resolution).astype(np.int64)
        return ij[:, 1], ij[:, 0]

    def is_drivable(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] world -> [N] bool
        """Whether each point lies on the drivable area (exact polygons when the map came from a RoadMap)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.road_map is not None:
            return self.road_map.is_drivable(xy)
        rows, cols = self._pixel(xy)
        h, w = self.shape
        ok = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        out = np.zeros(len(xy), dtype=bool)
        out[ok] = self.layers[0, rows[ok], cols[ok]] > 0.5
        return out

    def covers(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] world -> [N] bool
        """Whether the map knows what is at each point (``extent``: a RoadMap's known extent, e.g. the bounding box
        of a procedural layout's roads and sidewalks, since that world stops at its road ends; the raster for
        derived maps)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.all((xy >= self.extent[0]) & (xy <= self.extent[1]), axis=1)

    def _normalised(self, xy: torch.Tensor) -> torch.Tensor:  # [..., 2] world -> grid_sample coordinates
        h, w = self.shape
        size = torch.tensor([w * self.resolution, h * self.resolution], dtype=xy.dtype, device=xy.device)
        return 2.0 * (xy - torch.as_tensor(self.origin, dtype=xy.dtype, device=xy.device)) / size - 1.0

    def outside_distance(self, xy: torch.Tensor) -> torch.Tensor:  # [..., 2] world (float) -> [...] metres
        """Bilinear distance to the drivable area (0 inside); differentiable in ``xy``; border value outside."""
        shape = xy.shape[:-1]
        grid = self._normalised(xy.reshape(1, -1, 1, 2).to(torch.float32))
        d = torch.nn.functional.grid_sample(self.tensors(xy.device)[1], grid, mode="bilinear", padding_mode="border",
                                            align_corners=False)
        return d.reshape(shape)

    def crops(self, xy: np.ndarray,    # [N, 2] world centres
              yaw: np.ndarray,          # [N] world headings
              spec: CropSpec,
              extra: np.ndarray | None = None,  # [H, W] an extra world layer (obstacles), same grid
              ) -> torch.Tensor:        # [N, C(+1), Hc, Wc] float32 in each agent's frame
        """The map patch around each agent, rotated into its frame; lane directions become relative to its heading.
        Cells outside the raster read 0 (unknown)."""
        n = len(xy)
        rows, cols = spec.shape
        lx = spec.x_min + (np.arange(cols) + 0.5) * spec.resolution_m
        ly = -spec.half_width + (np.arange(rows) + 0.5) * spec.resolution_m
        gx, gy = np.meshgrid(lx, ly)  # [rows, cols]
        c, s = np.cos(yaw)[:, None, None], np.sin(yaw)[:, None, None]
        wx = xy[:, 0, None, None] + c * gx - s * gy
        wy = xy[:, 1, None, None] + s * gx + c * gy
        grid = self._normalised(torch.from_numpy(np.stack([wx, wy], -1)).to(torch.float64)).to(torch.float32)
        layers = self.tensors()[0]
        if extra is not None:
            layers = torch.cat([layers, torch.from_numpy(np.asarray(extra, np.float32))[None, None]], dim=1)
        out = torch.nn.functional.grid_sample(layers, grid.reshape(1, n * rows, cols, 2), mode="bilinear",
                                              padding_mode="zeros", align_corners=False)
        out = out.reshape(layers.shape[1], n, rows, cols).permute(1, 0, 2, 3).contiguous()
        cos_w, sin_w = out[:, 2].clone(), out[:, 3].clone()
        ct, st = torch.from_numpy(np.cos(yaw)).float()[:, None, None], torch.from_numpy(np.sin(yaw)).float()[:, None, None]
        out[:, 2] = cos_w * ct + sin_w * st
        out[:, 3] = sin_w * ct - cos_w * st
        return out

    def footprint_layer(self, boxes: np.ndarray) -> np.ndarray:  # [K, 5] (x, y, yaw, length, width) -> [H, W]
        """A layer on this map's grid with the given box footprints filled with 1."""
        layer = np.zeros(self.shape, dtype=np.uint8)
        for x, y, yaw, length, width in np.asarray(boxes, dtype=np.float64).reshape(-1, 5):
            _fill_box(layer, self.origin, self.resolution, x, y, yaw, length, width)
        return layer.astype(np.float32)


def _grid(bounds_min: np.ndarray, bounds_max: np.ndarray, config: MapConfig) -> tuple[np.ndarray, int, int]:
    lo = np.floor((bounds_min - config.margin_m) / config.resolution_m) * config.resolution_m
    hi = np.ceil((bounds_max + config.margin_m) / config.resolution_m) * config.resolution_m
    w, h = (np.round((hi - lo) / config.resolution_m)).astype(int)
    return lo, int(h), int(w)


#: Fractional bits of the fixed-point coordinates handed to cv2 drawing (1/16 pixel).
_SHIFT = 4


def _to_px(xy: np.ndarray, origin: np.ndarray, res: float) -> np.ndarray:  # [N, 2] -> [N, 2] int32 (col, row)
    """Fixed-point pixel coordinates (``_SHIFT`` fractional bits) for cv2: pixel (j, i) covers
    [x0 + j res, x0 + (j + 1) res), so its centre is at j + 0.5 cells. Far points are clipped (cv2 clips lines)."""
    px = ((np.asarray(xy, dtype=np.float64) - origin) / res - 0.5) * (1 << _SHIFT)
    return np.round(np.clip(px, -2e8, 2e8)).astype(np.int32)


def _line_thickness(width_m: float, res: float) -> int:
    """cv2's thickness for a band ``width_m`` wide: cv2 draws thick lines about a pixel wider than asked."""
    return max(1, int(round(width_m / res)) - 1)


def _fill_box(layer: np.ndarray, origin, res, x, y, yaw, length, width) -> None:
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[length / 2, width / 2], [length / 2, -width / 2], [-length / 2, -width / 2],
                      [-length / 2, width / 2]])
    corners = local @ np.array([[c, s], [-s, c]]) + [x, y]
    cv2.fillPoly(layer, [_to_px(corners, origin, res)], 1, shift=_SHIFT)


def _paint_lanes(layers: np.ndarray, origin: np.ndarray, res: float, polylines: list[np.ndarray],
                 line_width_m: float) -> None:
    """Centreline band and its direction (world cos/sin) for every polyline ([K, 2] in driving order)."""
    thickness = _line_thickness(line_width_m, res)
    segment_of_cell = np.zeros(layers.shape[1:], dtype=np.int32)  # 1 + index of the segment drawn there
    directions = [np.zeros(2)]
    for pts in polylines:
        pts = np.asarray(pts, dtype=np.float64)
        px = _to_px(pts, origin, res)
        for a, b, pa, pb in zip(pts[:-1], pts[1:], px[:-1], px[1:]):
            d = b - a
            norm = np.hypot(*d)
            if norm < 1e-9:
                continue
            directions.append(d / norm)
            cv2.line(segment_of_cell, tuple(int(v) for v in pa), tuple(int(v) for v in pb), len(directions) - 1,
                     thickness, cv2.LINE_8, _SHIFT)
    directions = np.asarray(directions)
    on = segment_of_cell > 0
    layers[1][on] = 1.0
    layers[2][on] = directions[segment_of_cell[on], 0]
    layers[3][on] = directions[segment_of_cell[on], 1]


def map_from_road_map(road_map: RoadMap, ego_xy: np.ndarray,  # [S, 2] ego path (box centres)
                      config: MapConfig = MapConfig()) -> SceneMap:
    """Raster of a road map's drivable polygons and lane centrelines around the ego path."""
    origin, h, w = _grid(ego_xy.min(0), ego_xy.max(0), config)
    res = config.resolution_m
    xs = origin[0] + (np.arange(w) + 0.5) * res
    ys = origin[1] + (np.arange(h) + 0.5) * res
    gx, gy = np.meshgrid(xs, ys)
    layers = np.zeros((len(MAP_LAYERS), h, w), dtype=np.float32)
    layers[0] = road_map.is_drivable(np.stack([gx.ravel(), gy.ravel()], -1)).reshape(h, w)
    _paint_lanes(layers, origin, res, list(road_map.lane_centrelines), config.lane_line_width_m)
    return SceneMap(origin, res, layers, "road_map", road_map=road_map,
                    extent=(road_map.extent_min, road_map.extent_max))


def map_from_tracks(ego_xy: np.ndarray,          # [S, 2] ego path (box centres)
                    paths: list[np.ndarray],      # moving vehicles' paths, each [K, 2] in driving order
                    parked: np.ndarray,           # [P, 5] (x, y, yaw, length, width) of standing vehicles
                    config: MapConfig = MapConfig()) -> SceneMap:
    """A map for logs that bring none: drivable = corridors around driven paths plus parked footprints;
    lanes = the driven paths themselves."""
    if len(ego_xy) == 0:
        raise OmniscsError("cannot derive a map: the log has no ego poses")
    origin, h, w = _grid(ego_xy.min(0), ego_xy.max(0), config)
    res = config.resolution_m
    layers = np.zeros((len(MAP_LAYERS), h, w), dtype=np.float32)
    drivable = np.zeros((h, w), dtype=np.uint8)
    thickness = _line_thickness(2 * config.corridor_half_width_m, res)
    for pts in [ego_xy, *paths]:
        px = _to_px(pts, origin, res)
        if len(px) == 1:
            cv2.circle(drivable, tuple(int(v) for v in px[0]), (thickness // 2) << _SHIFT, 1, -1, cv2.LINE_8, _SHIFT)
        else:
            cv2.polylines(drivable, [px.reshape(-1, 1, 2)], False, 1, thickness, cv2.LINE_8, _SHIFT)
    for x, y, yaw, length, width in np.asarray(parked, dtype=np.float64).reshape(-1, 5):
        _fill_box(drivable, origin, res, x, y, yaw, length, width)
    layers[0] = drivable
    _paint_lanes(layers, origin, res, [ego_xy, *paths], config.lane_line_width_m)
    return SceneMap(origin, res, layers, "derived")
