"""Hand-made procedural logs for behaviour tests: the layout of ``straight`` seed 0 (ego lane at y = 0, a second
eastbound lane at y = 3.3, westbound lanes at y = 6.6 and 10.0, drivable for y in [-1.66, 14.1]) with an ego and
agents that drive at constant speed along their heading."""
from __future__ import annotations

import functools

import numpy as np

from omniscs.geometry import pose_from_xyz_yaw
from omniscs.world import AgentTrack, generate_world

CAR = (4.5, 1.9, 1.6)


@functools.lru_cache(maxsize=1)
def _base(n_frames: int):
    return generate_world("straight", 0, n_frames=n_frames, n_cameras=1, width=64, height=36)


def straight_world(agents: list[dict], ego_speed: float = 8.0, n_frames: int = 40):
    """agents: dicts with x, y, yaw (world, at frame 0), speed (m/s), optional first/last frame, size, category."""
    base = _base(n_frames)
    t = np.arange(n_frames) * 0.1
    ego = np.stack([pose_from_xyz_yaw(ego_speed * ti, 0.0, 0.0, 0.0) for ti in t])
    tracks = []
    for k, a in enumerate(agents):
        size = np.array(a.get("size", CAR), dtype=np.float64)
        yaw = a.get("yaw", 0.0)
        xs = a["x"] + a.get("speed", 0.0) * t * np.cos(yaw)
        ys = a["y"] + a.get("speed", 0.0) * t * np.sin(yaw)
        poses = np.stack([pose_from_xyz_yaw(x, y, size[2] / 2, yaw) for x, y in zip(xs, ys)])
        present = np.zeros(n_frames, dtype=bool)
        present[a.get("first", 0): a.get("last", n_frames - 1) + 1] = True
        tracks.append(AgentTrack(track_id=k + 1, category=a.get("category", "car"), asset_id="sedan-0000",
                                 size=size, poses=poses, present=present))
    return base.replace(ego_poses=ego, agents=tuple(tracks))
