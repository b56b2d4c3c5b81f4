"""Small procedural logs for scene-graph tests: the ``straight`` layout with an ego at 6 m/s and hand-placed
agents, rendered (images, ground truth, LiDAR) at thumbnail size in about a second. The world's packages are imported
only to make a log, so that tiny_fit_config also serves GPU machines that lack them (infra/gpu_check)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from omniscs.geometry import pose_from_xyz_yaw

CAR = (4.5, 1.9, 1.6)

#: A car 11 m ahead in the ego lane keeping pace, and one in the next lane that overtakes it.
DEFAULT_AGENTS = (
    {"x": 11.0, "y": 0.0, "speed": 6.0, "asset": "sedan-0003"},
    {"x": 6.0, "y": 3.3, "speed": 9.0, "asset": "sedan-0011"},
)


def nsg_world(agents=DEFAULT_AGENTS, n_frames: int = 8, n_cameras: int = 1, width: int = 96, height: int = 54,
              ego_speed: float = 6.0):
    """agents: dicts with x, y (world, frame 0), speed (m/s, along +x), optional asset, first/last frame, size."""
    from omniscs.world import AgentTrack, camera_rig, generate_world

    base = generate_world("straight", 0, n_frames=n_frames, n_cameras=n_cameras, width=width, height=height)
    t = np.arange(n_frames) * 0.1
    ego = np.stack([pose_from_xyz_yaw(ego_speed * ti, 0.0, 0.0, 0.0) for ti in t])
    tracks = []
    for k, a in enumerate(agents):
        size = np.array(a.get("size", CAR), dtype=np.float64)
        poses = np.stack([pose_from_xyz_yaw(a["x"] + a.get("speed", 0.0) * ti, a["y"], size[2] / 2, 0.0) for ti in t])
        present = np.zeros(n_frames, dtype=bool)
        present[a.get("first", 0): a.get("last", n_frames - 1) + 1] = True
        tracks.append(AgentTrack(track_id=k + 1, category="car", asset_id=a.get("asset", "sedan-0000"), size=size,
                                 poses=poses, present=present))
    return base.replace(ego_poses=ego, agents=tuple(tracks), cameras=camera_rig(n_cameras, width, height))


def write_nsg_scene(out: Path, world=None, scene_id: str = "nsg-test") -> Path:
    from omniscs.scene.synthetic import write_world_scene

    world = world if world is not None else nsg_world()
    return write_world_scene(world, out, scene_id, {"kind": "test", "name": scene_id})


def tiny_fit_config(iterations: int = 60, **overrides):
    """The fast preset shrunk for thumbnails: full resolution, a few thousand Gaussians."""
    from omniscs.nsg import fit_preset
    from omniscs.plan import PlanConfig

    settings = dict(iterations=iterations, resolution_schedule=((0.0, 1),),
                    plan=PlanConfig(gaussians_per_m2=0.5, gaussians_per_agent=400, min_gaussians=3_000,
                                    max_gaussians=8_000))
    settings.update(overrides)
    return fit_preset("fast", **settings)
