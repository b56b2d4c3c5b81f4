"""What the placement checks read of a scene (``omniscs.scs.appearance.placement``): the logged obstacles and the ego
per frame, the cameras, the ground height and the lane direction, gathered once per scene in a ``PlacementContext``."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from omniscs.errors import OmniscsError
from omniscs.geometry import yaw_from_matrix
from omniscs.scs.appearance.placement.config import EGO_HEIGHT_M, EGO_TRACK_ID, positive_size


# ----------------------------------------------------------------------------- what the checks read
@dataclass(frozen=True)
class Obstacles:
    """Every box a placed object must keep clear of, per frame (world frame): logged agents, static objects and
    the ego (track_id ``EGO_TRACK_ID``)."""

    frame_idx: np.ndarray  # [M] int64
    track_id: np.ndarray   # [M] int64, EGO_TRACK_ID for the ego
    centre: np.ndarray     # [M, 3] box centres
    size: np.ndarray       # [M, 3] length, width, height
    yaw: np.ndarray        # [M]

    def __post_init__(self) -> None:
        m = len(self.frame_idx)
        shapes = (self.track_id.shape == (m,), self.centre.shape == (m, 3), self.size.shape == (m, 3),
                  self.yaw.shape == (m,))
        if not all(shapes):
            raise OmniscsError(f"obstacles: arrays disagree in shape (frame_idx [{m}], track_id "
                               f"{list(self.track_id.shape)}, centre {list(self.centre.shape)}, size "
                               f"{list(self.size.shape)}, yaw {list(self.yaw.shape)})")
        if not (np.isfinite(self.centre).all() and np.isfinite(self.size).all() and np.isfinite(self.yaw).all()):
            raise OmniscsError("obstacles: a box has a NaN or infinite centre, size or yaw; repair the log's boxes")

    @classmethod
    def from_arrays(cls, frame_idx, track_id, centre, size, yaw) -> Obstacles:
        return cls(frame_idx=np.asarray(frame_idx, dtype=np.int64).reshape(-1),
                   track_id=np.asarray(track_id, dtype=np.int64).reshape(-1),
                   centre=np.asarray(centre, dtype=np.float64).reshape(-1, 3),
                   size=np.asarray(size, dtype=np.float64).reshape(-1, 3),
                   yaw=np.asarray(yaw, dtype=np.float64).reshape(-1))

    @classmethod
    def from_scene(cls, scene, ego_size: tuple[float, float, float] | None = None,
                   ego_centre_ahead_m: float | None = None, exclude=()) -> Obstacles:
        """The boxes of a scene store (``scene.boxes``) plus the ego's at every frame. The ego's box defaults to
        the behaviour model's (``EgoBox``: length, width, centre ahead of the ego origin) with height
        ``EGO_HEIGHT_M``; its centre lies ``ego_centre_ahead_m`` ahead of the ego origin along the heading, at the
        origin's height + h/2 (the ego frame's origin is on the ground). ``exclude``: track ids left out (e.g.
        the agent the object replaces; ``EGO_TRACK_ID`` leaves out the ego)."""
        if ego_size is None or ego_centre_ahead_m is None:
            from omniscs.scs.behavior.tracks import EgoBox  # the behaviour package loads torch: only when needed

            box = EgoBox()
            ego_size = (box.length, box.width, EGO_HEIGHT_M) if ego_size is None else ego_size
            ego_centre_ahead_m = box.centre_ahead_m if ego_centre_ahead_m is None else ego_centre_ahead_m
        ego_size = positive_size(ego_size, "ego size")
        if not np.isfinite(ego_centre_ahead_m):
            raise OmniscsError(f"ego_centre_ahead_m {ego_centre_ahead_m} must be a finite number of metres")
        world_from_ego = np.asarray(scene.world_from_ego_all, dtype=np.float64).reshape(-1, 4, 4)
        n_frames = len(world_from_ego)
        ego_yaw = yaw_from_matrix(world_from_ego[:, :3, :3])
        ego_centre = world_from_ego[:, :3, 3].copy()
        ego_centre[:, 0] += ego_centre_ahead_m * np.cos(ego_yaw)
        ego_centre[:, 1] += ego_centre_ahead_m * np.sin(ego_yaw)
        ego_centre[:, 2] += ego_size[2] / 2
        excluded = {int(t) for t in exclude}
        b = scene.boxes
        b = b[~b.track_id.isin(excluded)] if len(b) else b
        frame_idx, track_id = [b.frame_idx.to_numpy(np.int64)], [b.track_id.to_numpy(np.int64)]
        centre = [b[["cx", "cy", "cz"]].to_numpy(np.float64)]
        size = [b[["length", "width", "height"]].to_numpy(np.float64)]
        yaw = [b.yaw.to_numpy(np.float64)]
        if EGO_TRACK_ID not in excluded:
            frame_idx.append(np.arange(n_frames))
            track_id.append(np.full(n_frames, EGO_TRACK_ID))
            centre.append(ego_centre)
            size.append(np.tile(ego_size, (n_frames, 1)))
            yaw.append(ego_yaw)
        return cls.from_arrays(*(np.concatenate(parts) for parts in (frame_idx, track_id, centre, size, yaw)))

    def __len__(self) -> int:
        return len(self.frame_idx)

    def without(self, track_ids) -> Obstacles:
        """These obstacles less the boxes of ``track_ids`` (e.g. the agent an object replaces)."""
        keep = ~np.isin(self.track_id, np.asarray(list(track_ids), dtype=np.int64))
        return Obstacles(self.frame_idx[keep], self.track_id[keep], self.centre[keep], self.size[keep], self.yaw[keep])


@dataclass(frozen=True)
class Cameras:
    """The log's cameras at every frame (OpenCV: x right, y down, z forward)."""

    names: tuple[str, ...]          # [C]
    world_from_camera: np.ndarray   # [F, C, 4, 4]
    K: np.ndarray                   # [C, 3, 3]
    width: np.ndarray               # [C] int, pixels
    height: np.ndarray              # [C] int, pixels

    def __post_init__(self) -> None:
        c = len(self.names)
        if (self.world_from_camera.ndim != 4 or self.world_from_camera.shape[1:] != (c, 4, 4)
                or self.K.shape != (c, 3, 3) or self.width.shape != (c,) or self.height.shape != (c,)):
            raise OmniscsError(f"cameras: {c} names but world_from_camera {list(self.world_from_camera.shape)}, "
                               f"K {list(self.K.shape)}, width {list(self.width.shape)}, "
                               f"height {list(self.height.shape)}")
        if c == 0 or self.world_from_camera.shape[0] == 0:
            raise OmniscsError("cameras: the log has no cameras or no frames; a placement needs both")
        if not (np.isfinite(self.world_from_camera).all() and np.isfinite(self.K).all()):
            raise OmniscsError("cameras: a camera pose or intrinsic matrix is not finite; repair the log")

    @classmethod
    def from_scene(cls, scene) -> Cameras:
        names = tuple(scene.camera_names)
        world_from_camera = np.stack([np.stack([scene.world_from_camera(c, f) for c in names])
                                      for f in range(scene.n_frames)]) if names else np.zeros((scene.n_frames, 0, 4, 4))
        sizes = [scene.image_size(c) for c in names]
        return cls(names=names, world_from_camera=np.asarray(world_from_camera, dtype=np.float64),
                   K=np.asarray([scene.intrinsics(c) for c in names], dtype=np.float64).reshape(-1, 3, 3),
                   width=np.array([s[0] for s in sizes], dtype=np.int64),
                   height=np.array([s[1] for s in sizes], dtype=np.int64))

    @property
    def n_frames(self) -> int:
        return self.world_from_camera.shape[0]

    def index_of(self, name: str) -> int:
        if name not in self.names:
            raise OmniscsError(f"unknown camera {name!r}; the log has {', '.join(self.names)}")
        return self.names.index(name)

    def hfov(self) -> np.ndarray:  # [C] radians
        """Horizontal field of view of each camera (pinhole, principal point anywhere)."""
        fx, cx = self.K[:, 0, 0], self.K[:, 0, 2]
        return np.arctan2(cx, fx) + np.arctan2(self.width - cx, fx)


class GroundHeight:
    """Road-surface height near points: inverse-distance weighting (power 2) of the ground samples within
    ``radius_m`` (at most ``neighbours`` of them), else the nearest sample's height. Samples are the bottoms
    (cz - h/2) of logged boxes and the ego origins (the ego frame's origin is on the ground), merged per cell of
    ``cell_m`` so a parked car seen in 200 frames counts once."""

    def __init__(self, points: np.ndarray,  # [K, 3] world ground samples
                 radius_m: float = 15.0, neighbours: int = 8, cell_m: float = 0.5) -> None:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        if not len(points):
            raise OmniscsError("no ground samples (no boxes and no ego poses): cannot tell the road's height")
        _, cell, counts = np.unique(np.floor(points[:, :2] / cell_m).astype(np.int64), axis=0, return_inverse=True,
                                    return_counts=True)
        cell = cell.reshape(-1)
        self.points = np.stack([np.bincount(cell, points[:, k]) / counts for k in range(3)], -1)  # [K', 3]
        self.radius_m, self.neighbours = float(radius_m), int(neighbours)
        self._tree = cKDTree(self.points[:, :2])

    @classmethod
    def from_obstacles(cls, obstacles: Obstacles, radius_m: float = 15.0) -> GroundHeight:
        """Box bottoms of every obstacle; the ego's box bottom is its origin's height."""
        return cls(np.concatenate([obstacles.centre[:, :2], obstacles.centre[:, 2:] - obstacles.size[:, 2:] / 2], 1),
                   radius_m=radius_m)

    def __call__(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] world -> [N] metres
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        k = min(self.neighbours, len(self.points))
        dist, idx = self._tree.query(xy, k=k)
        dist, idx = dist.reshape(len(xy), k), idx.reshape(len(xy), k)
        z = self.points[idx, 2]
        w = np.where(dist <= self.radius_m, 1.0 / np.maximum(dist, 1e-3) ** 2, 0.0)
        near = w.sum(1) > 0
        return np.where(near, (w * z).sum(1) / np.where(near, w.sum(1), 1.0), z[:, 0])


class LaneDirection:
    """Direction of travel of the lane nearest each point, from a scene map's centreline raster (cells of the
    ``centreline`` layer and their ``lane_dir_cos``/``lane_dir_sin``, see ``MAP_LAYERS``); accurate to one map
    cell. Points further than ``max_distance_m`` from every centreline cell have no lane."""

    def __init__(self, cells_xy: np.ndarray,  # [L, 2] world centres of centreline cells
                 yaw: np.ndarray,             # [L] lane direction there
                 max_distance_m: float = 5.0) -> None:
        self.cells_xy = np.asarray(cells_xy, dtype=np.float64).reshape(-1, 2)
        self.yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
        self.max_distance_m = float(max_distance_m)
        self._tree = cKDTree(self.cells_xy) if len(self.cells_xy) else None

    @classmethod
    def from_scene_map(cls, scene_map, max_distance_m: float = 5.0) -> LaneDirection:
        """From an ``omniscs.scs.behavior.maps.SceneMap`` (read through its numpy layers only)."""
        layers = np.asarray(scene_map.layers)
        rows, cols = np.nonzero(layers[1] > 0.5)
        res = float(scene_map.resolution)
        xy = np.asarray(scene_map.origin, dtype=np.float64) + (np.stack([cols, rows], -1) + 0.5) * res
        return cls(xy, np.arctan2(layers[3, rows, cols], layers[2, rows, cols]), max_distance_m)

    def __call__(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # [N, 2] -> yaw [N], found [N] bool
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self._tree is None:
            return np.zeros(len(xy)), np.zeros(len(xy), dtype=bool)
        dist, idx = self._tree.query(xy)
        found = dist <= self.max_distance_m
        return np.where(found, self.yaw[np.minimum(idx, len(self.yaw) - 1)], 0.0), found


@dataclass(frozen=True)
class PlacementContext:
    """Everything the checks read about one log."""

    obstacles: Obstacles
    cameras: Cameras
    drivable: Callable[[np.ndarray], np.ndarray]
    """xy [N, 2] world -> [N] bool: whether each point is on the drivable area."""
    ground_z: Callable[[np.ndarray], np.ndarray]
    """xy [N, 2] world -> [N]: road-surface height there, metres."""
    lane_direction: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    """xy [N, 2] -> (yaw [N], found [N] bool): the nearest lane's direction; None: yaw_mode 'lane' is unavailable."""

    def __post_init__(self) -> None:
        if len(self.obstacles) and (self.obstacles.frame_idx.min() < 0
                                    or self.obstacles.frame_idx.max() >= self.n_frames):
            raise OmniscsError(f"obstacles have frames outside 0..{self.n_frames - 1}, the frames the cameras have")

    @property
    def n_frames(self) -> int:
        return self.cameras.n_frames


def placement_context(scene, exclude=(), ground_radius_m: float = 15.0, lane_search_m: float = 5.0
                      ) -> PlacementContext:
    """The placement context of a scene store: its obstacles (``exclude``: track ids left out, e.g. the agent
    being replaced), cameras, drivable area and lanes (the behaviour model's scene map: the log's road map when
    it has one, else derived from where vehicles drove) and ground height (from every box and ego pose, the
    excluded ones included)."""
    from omniscs.scs.behavior.tracks import traffic_from_scene  # the behaviour package loads torch

    scene_map = traffic_from_scene(scene).map
    everything = Obstacles.from_scene(scene)
    obstacles = Obstacles.from_scene(scene, exclude=exclude) if len(exclude) else everything
    return PlacementContext(obstacles=obstacles, cameras=Cameras.from_scene(scene), drivable=scene_map.is_drivable,
                            ground_z=GroundHeight.from_obstacles(everything, ground_radius_m),
                            lane_direction=LaneDirection.from_scene_map(scene_map, lane_search_m))
