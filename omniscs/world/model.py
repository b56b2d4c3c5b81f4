"""The data model of a procedural driving world: what is in it and how it moves, JSON round-trippable.

Static geometry (roads, buildings, poles) is regenerated from (template, seed, LAYOUT_VERSION) and
agent meshes from their asset ids, so a ``World`` stays small and an edited copy re-renders exactly.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

import numpy as np

from omniscs.errors import OmniscsError

#: Bump when procedural layout or asset generation changes, so stale scenes are not re-rendered wrongly.
LAYOUT_VERSION = 1

#: Frame period of the synthetic logs (10 Hz), int64 microseconds.
FRAME_PERIOD_US = 100_000


@dataclass(frozen=True)
class CameraSpec:
    """One pinhole camera (OpenCV convention) rigidly mounted on the ego vehicle."""

    name: str
    width: int
    height: int
    K: np.ndarray  # [3, 3] float64 intrinsics
    ego_from_camera: np.ndarray  # [4, 4] float64


@dataclass(frozen=True)
class LidarSpec:
    """A spinning LiDAR: ``beams`` rows between the elevation limits, ``azimuth_steps`` columns."""

    beams: int = 32
    max_range: float = 70.0
    azimuth_steps: int = 1_080
    min_elevation_deg: float = -30.67  # HDL-32E-like vertical field of view (nuScenes LIDAR_TOP)
    max_elevation_deg: float = 10.67
    ego_from_lidar: np.ndarray = field(
        default_factory=lambda: np.array(
            [[1.0, 0, 0, 0.94], [0, 1.0, 0, 0.0], [0, 0, 1.0, 1.84], [0, 0, 0, 1.0]]
        )
    )  # [4, 4] float64


@dataclass(frozen=True)
class AgentTrack:
    """One rigid agent: an asset from the library, its box size and its pose per frame."""

    track_id: int
    category: str  # one of omniscs.taxonomy.CATEGORIES
    asset_id: str  # stable id; the asset library rebuilds the mesh from it
    size: np.ndarray  # [3] float64 (length, width, height) of the box, metres
    poses: np.ndarray  # [F, 4, 4] float64 world_from_agent; origin at the box centre, x = heading
    present: np.ndarray  # [F] bool: whether the agent exists in each frame


@dataclass(frozen=True)
class World:
    """A complete procedural driving log: layout, lighting, ego motion, sensors and agents."""

    template: str  # "straight", "t_junction", "intersection", ...
    seed: int
    lighting: str  # "day", "dusk", "night", "fog"
    n_frames: int
    ego_poses: np.ndarray  # [F, 4, 4] float64 world_from_ego
    cameras: tuple[CameraSpec, ...]
    lidar: LidarSpec
    agents: tuple[AgentTrack, ...]
    frame_period_us: int = FRAME_PERIOD_US
    layout_version: int = LAYOUT_VERSION

    def timestamps_us(self) -> np.ndarray:  # [F] int64
        return np.arange(self.n_frames, dtype=np.int64) * self.frame_period_us

    def agent(self, track_id: int) -> AgentTrack:
        for a in self.agents:
            if a.track_id == track_id:
                return a
        raise OmniscsError(f"no agent with track id {track_id}; known ids: {[a.track_id for a in self.agents]}")

    def camera(self, name: str) -> CameraSpec:
        for c in self.cameras:
            if c.name == name:
                return c
        raise OmniscsError(f"unknown camera {name!r}; this world has {[c.name for c in self.cameras]}")

    def replace(self, **changes) -> "World":
        return dataclasses.replace(self, **changes)

    # -- JSON ---------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return _to_jsonable(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, d: dict) -> "World":
        d = dict(d)
        d["ego_poses"] = np.asarray(d["ego_poses"], dtype=np.float64)
        d["cameras"] = tuple(
            CameraSpec(name=c["name"], width=int(c["width"]), height=int(c["height"]),
                       K=np.asarray(c["K"], dtype=np.float64),
                       ego_from_camera=np.asarray(c["ego_from_camera"], dtype=np.float64))
            for c in d["cameras"]
        )
        lid = dict(d["lidar"])
        lid["ego_from_lidar"] = np.asarray(lid["ego_from_lidar"], dtype=np.float64)
        d["lidar"] = LidarSpec(**lid)
        d["agents"] = tuple(
            AgentTrack(track_id=int(a["track_id"]), category=a["category"], asset_id=a["asset_id"],
                       size=np.asarray(a["size"], dtype=np.float64),
                       poses=np.asarray(a["poses"], dtype=np.float64).reshape(-1, 4, 4),
                       present=np.asarray(a["present"], dtype=bool))
            for a in d["agents"]
        )
        return cls(**d)

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> "World":
        return cls.from_dict(json.loads(text))


def _to_jsonable(x):
    if isinstance(x, dict):
        return {k: _to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x
