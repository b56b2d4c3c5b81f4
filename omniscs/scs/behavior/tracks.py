"""Traffic of one log on a regular time grid (world frame, float64): the behaviour model's view of a scene.

Built from a scene store (any source) or from a log's arrays (``traffic_from_log``: e.g. a procedural log that
was never rendered). Positions are box centres; the ego's box centre lies ``ego_centre_ahead_m`` ahead of its
frame origin. The map comes from the log's road map when it has one, else it is derived from the traffic.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import wrap_angle, yaw_from_matrix
from omniscs.roadmap import RoadMap
from omniscs.scs.behavior.maps import MapConfig, SceneMap, map_from_road_map, map_from_tracks
from omniscs.taxonomy import VEHICLE_CATEGORIES

#: Relative tolerance on a log's frame period before it is resampled to the model's time step.
DT_TOLERANCE = 0.02
#: When resampling, a gap longer than this many source periods ends a track's presence.
MAX_GAP_PERIODS = 2.5


@dataclass(frozen=True)
class EgoBox:
    """The ego vehicle's footprint (scene stores do not record it; these are the synthetic ego's values)."""

    length: float = 4.6
    """Ego box length, metres."""
    width: float = 1.9
    """Ego box width, metres."""
    centre_ahead_m: float = 1.3
    """How far the box centre lies ahead of the ego frame origin (rear axle), metres."""


@dataclass(frozen=True)
class TrafficScene:
    """Ego and every track of a log on steps of ``dt`` seconds, world frame, box centres."""

    scene_id: str
    dt: float
    timestamps_us: np.ndarray  # [S] int64
    ego_xy: np.ndarray  # [S, 2] ego box centre
    ego_yaw: np.ndarray  # [S]
    ego_z: np.ndarray  # [S] ego frame origin height
    ego_box: EgoBox
    track_ids: np.ndarray  # [N] int64
    categories: tuple[str, ...]  # [N]
    sizes: np.ndarray  # [N, 3] length, width, height
    xy: np.ndarray  # [N, S, 2] (0 where absent)
    yaw: np.ndarray  # [N, S]
    z: np.ndarray  # [N, S] box centre height
    present: np.ndarray  # [N, S] bool
    map: SceneMap
    source_frames: np.ndarray | None = None  # [S] scene frame of each step; None when the log was resampled

    @property
    def n_steps(self) -> int:
        return len(self.timestamps_us)

    @property
    def n_tracks(self) -> int:
        return len(self.track_ids)

    def is_vehicle(self) -> np.ndarray:  # [N] bool
        return np.array([c in VEHICLE_CATEGORIES for c in self.categories], dtype=bool)

    def index_of(self, track_id: int) -> int:
        hits = np.flatnonzero(self.track_ids == int(track_id))
        if not len(hits):
            raise OmniscsError(f"scene {self.scene_id} has no track {track_id}; tracks: {self.track_ids.tolist()}")
        return int(hits[0])


def _ego_centre(world_from_ego: np.ndarray, ego_box: EgoBox) -> tuple[np.ndarray, np.ndarray]:  # [S,4,4] -> [S,2], [S]
    yaw = yaw_from_matrix(world_from_ego[:, :3, :3])
    xy = world_from_ego[:, :2, 3] + ego_box.centre_ahead_m * np.stack([np.cos(yaw), np.sin(yaw)], -1)
    return xy, yaw


def _moving_paths_and_parked(xy, yaw, present, sizes, vehicle, moving_path_m) -> tuple[list, np.ndarray]:
    paths, parked = [], []
    for i in np.flatnonzero(vehicle):
        pts = xy[i, present[i]]
        if not len(pts):
            continue
        travelled = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
        if travelled > moving_path_m:
            paths.append(pts)
        else:
            k = int(np.flatnonzero(present[i])[0])
            parked.append([xy[i, k, 0], xy[i, k, 1], yaw[i, k], sizes[i, 0], sizes[i, 1]])
    return paths, np.asarray(parked, dtype=np.float64).reshape(-1, 5)


def scene_map(road_map: RoadMap | None,
              ego_xy: np.ndarray,      # [S, 2] ego box centres
              xy: np.ndarray,          # [N, S, 2] track box centres (0 where absent)
              yaw: np.ndarray,         # [N, S]
              present: np.ndarray,     # [N, S] bool
              sizes: np.ndarray,       # [N, 3] length, width, height
              categories: tuple[str, ...] | list[str],  # [N]
              config: MapConfig = MapConfig()) -> SceneMap:
    """The raster map of a log: its road map's when it brings one, else derived from the ego path, the paths of
    moving vehicles and the footprints of standing ones."""
    if road_map is not None:
        return map_from_road_map(road_map, ego_xy, config)
    vehicle = np.array([c in VEHICLE_CATEGORIES for c in categories], dtype=bool)
    paths, parked = _moving_paths_and_parked(xy, yaw, present, sizes, vehicle, config.moving_path_m)
    return map_from_tracks(ego_xy, paths, parked, config)


def traffic_from_log(scene_id: str,
                     timestamps_us: np.ndarray,     # [S] int64, one per step
                     world_from_ego: np.ndarray,    # [S, 4, 4] float64
                     track_ids: np.ndarray,         # [N] int64
                     categories: tuple[str, ...] | list[str],  # [N]
                     sizes: np.ndarray,             # [N, 3] length, width, height
                     world_from_agent: np.ndarray,  # [N, S, 4, 4] float64, box centre, x = heading
                     present: np.ndarray,           # [N, S] bool
                     dt: float,
                     road_map: RoadMap | None = None, ego_box: EgoBox = EgoBox(),
                     map_config: MapConfig = MapConfig()) -> TrafficScene:
    """The traffic of a log already on a regular grid of ``dt`` seconds (each step is the log's frame of that
    index), e.g. a procedural log that was never rendered; the map as ``scene_map`` makes it."""
    world_from_ego = np.asarray(world_from_ego, dtype=np.float64)
    ego_xy, ego_yaw = _ego_centre(world_from_ego, ego_box)
    n, s = len(track_ids), len(timestamps_us)
    poses = np.asarray(world_from_agent, dtype=np.float64).reshape(n, s, 4, 4)
    present = np.asarray(present, dtype=bool).reshape(n, s)
    xy = poses[..., :2, 3].copy()
    yaw = yaw_from_matrix(poses[..., :3, :3])
    z = poses[..., 2, 3].copy()
    xy[~present] = 0.0
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    categories = tuple(categories)
    return TrafficScene(
        scene_id=scene_id, dt=float(dt), timestamps_us=np.asarray(timestamps_us, dtype=np.int64),
        ego_xy=ego_xy, ego_yaw=ego_yaw, ego_z=world_from_ego[:, 2, 3].copy(), ego_box=ego_box,
        track_ids=np.asarray(track_ids, dtype=np.int64), categories=categories, sizes=sizes,
        xy=xy, yaw=yaw, z=z, present=present,
        map=scene_map(road_map, ego_xy, xy, yaw, present, sizes, categories, map_config), source_frames=np.arange(s),
    )


def traffic_from_scene(scene, dt: float = 0.1, ego_box: EgoBox = EgoBox(),
                       map_config: MapConfig = MapConfig()) -> TrafficScene:
    """The traffic of a scene store on a ``dt`` grid (resampled when the log's period differs). The map is
    the store's road map when it has one (synthetic scenes), else derived from the ego path and boxes."""
    ts_us = scene.frames["timestamp_us"].to_numpy().astype(np.int64)
    times = (ts_us - ts_us[0]) * 1e-6
    periods = np.diff(times)
    native = len(times) == 1 or bool(np.all(np.abs(periods - dt) <= DT_TOLERANCE * dt))
    if native:
        grid = times
        grid_us = ts_us
    else:
        grid = np.arange(0.0, times[-1] + 1e-9, dt)
        grid_us = ts_us[0] + np.round(grid * 1e6).astype(np.int64)
    ego_xy_src, ego_yaw_src = _ego_centre(scene.world_from_ego_all, ego_box)
    ego_z_src = scene.world_from_ego_all[:, 2, 3]
    ego_xy = np.stack([np.interp(grid, times, ego_xy_src[:, k]) for k in range(2)], -1)
    ego_yaw = wrap_angle(np.interp(grid, times, np.unwrap(ego_yaw_src)))
    ego_z = np.interp(grid, times, ego_z_src)

    boxes = scene.boxes
    track_ids = np.array(sorted(boxes.track_id.unique()), dtype=np.int64)
    n, s = len(track_ids), len(grid)
    xy, yaw, z = np.zeros((n, s, 2)), np.zeros((n, s)), np.zeros((n, s))
    present = np.zeros((n, s), dtype=bool)
    sizes = np.zeros((n, 3))
    categories = []
    src_period = float(np.median(periods)) if len(periods) else dt
    for i, (tid, g) in enumerate(boxes.groupby("track_id", sort=True)):
        g = g.sort_values("frame_idx")
        f = g.frame_idx.to_numpy()
        categories.append(str(g.category.iloc[0]))
        sizes[i] = g[["length", "width", "height"]].median().to_numpy()
        if native:
            xy[i, f] = g[["cx", "cy"]].to_numpy()
            yaw[i, f] = g.yaw.to_numpy()
            z[i, f] = g.cz.to_numpy()
            present[i, f] = True
            continue
        t = times[f]
        k = np.searchsorted(t, grid, side="right") - 1  # last sample at or before each grid time
        ok = (k >= 0) & (grid <= t[-1] + 1e-9)
        k = np.clip(k, 0, len(t) - 1)
        nxt = np.minimum(k + 1, len(t) - 1)
        gap_ok = (t[nxt] - t[k]) <= MAX_GAP_PERIODS * src_period
        present[i] = ok & (gap_ok | np.isclose(grid, t[k]))
        xy[i, :, 0] = np.interp(grid, t, g.cx.to_numpy())
        xy[i, :, 1] = np.interp(grid, t, g.cy.to_numpy())
        yaw[i] = wrap_angle(np.interp(grid, t, np.unwrap(g.yaw.to_numpy())))
        z[i] = np.interp(grid, t, g.cz.to_numpy())
    xy[~present] = 0.0
    return TrafficScene(
        scene_id=scene.scene_id,
        dt=float(dt if not native or len(times) == 1 else round(float(np.median(np.diff(ts_us))) / 1e6, 6)),
        timestamps_us=grid_us, ego_xy=ego_xy, ego_yaw=ego_yaw, ego_z=ego_z, ego_box=ego_box, track_ids=track_ids,
        categories=tuple(categories), sizes=sizes, xy=xy, yaw=yaw, z=z, present=present,
        map=scene_map(scene.road_map, ego_xy, xy, yaw, present, sizes, categories, map_config),
        source_frames=np.arange(s) if native else None,
    )
