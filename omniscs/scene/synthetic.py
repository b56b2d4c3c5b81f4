"""Synthetic sources: render a procedural world into a scene store with exact ground truth."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.geometry import invert_transform, transform_points, yaw_from_matrix
from omniscs.quaternions import rotmat_to_quat
from omniscs.scene.store import CameraRecord
from omniscs.scene.writer import SceneWriter
from omniscs.storage import content_hash


@dataclass(frozen=True)
class SyntheticSource:
    """A procedural driving log to generate: which layout, seed, lighting and sensor rig."""

    template: str = "straight"
    """Road layout template (see ``omniscs.world.TEMPLATES``)."""
    seed: int = 0
    """Seed for layout, assets and traffic; the same seed gives the same log."""
    lighting: str = "day"
    """One of ``omniscs.world.LIGHTINGS`` (day, dusk, night, fog)."""
    n_frames: int = 40
    """Number of frames at 10 Hz."""
    n_cameras: int = 3
    """Cameras in nuScenes-like placement, 1 to 6 (3 = front, front-left, front-right)."""
    width: int = 480
    """Image width in pixels."""
    height: int = 270
    """Image height in pixels."""

    def to_dict(self) -> dict:
        return {"kind": "synthetic", **asdict(self)}

    def scene_id(self) -> str:
        from omniscs.world.model import LAYOUT_VERSION
        digest = content_hash(asdict(self), LAYOUT_VERSION)[:8]
        return f"syn-{self.template}-{self.lighting}-s{self.seed}-{digest}"


def boxes_from_world(world, lidar_world: list[np.ndarray] | None = None,
                     visible_pixels: dict[tuple[int, int], int] | None = None) -> list[dict]:
    """One box row per present agent and frame, world frame; LiDAR points ([N,3] world per frame)
    and visible pixel counts ({(frame, track): count}) fill the visibility fields when given."""
    rows = []
    for agent in world.agents:
        for f in np.flatnonzero(agent.present):
            pose = agent.poses[f]
            centre = pose[:3, 3]
            q = rotmat_to_quat(pose[:3, :3])
            n_pts = -1 if lidar_world is None else _points_in_posed_box(lidar_world[f], pose, agent.size)
            rows.append({
                "frame_idx": int(f), "track_id": int(agent.track_id), "category": agent.category,
                "source_category": agent.asset_id.split("-")[0],
                "cx": centre[0], "cy": centre[1], "cz": centre[2],
                "length": agent.size[0], "width": agent.size[1], "height": agent.size[2],
                "yaw": float(yaw_from_matrix(pose[:3, :3])), "qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3],
                "num_lidar_points": n_pts,
                "visible_pixels": -1 if visible_pixels is None else int(visible_pixels.get((int(f), agent.track_id), 0)),
            })
    return rows


#: Slack around a box when counting the LiDAR points that hit it (points lie on the surface).
BOX_POINT_MARGIN = 0.05


def _points_in_posed_box(points: np.ndarray, pose: np.ndarray, size: np.ndarray,
                         margin: float = BOX_POINT_MARGIN) -> int:  # [N, 3] world, [4, 4], [3]
    local = transform_points(invert_transform(pose), points)
    return int(np.all(np.abs(local) <= 0.5 * np.asarray(size) + margin, axis=1).sum())


def write_world_scene(world, out_dir: Path, scene_id: str, source: dict, overwrite: bool = False,
                      progress: Callable[[int, int], None] | None = None) -> Path:
    """Render every camera and frame of ``world`` plus LiDAR into a scene store at ``out_dir``."""
    from omniscs.world import WorldRenderer

    renderer = WorldRenderer(world)
    total = world.n_frames * (len(world.cameras) + 1)
    done = 0
    visible: dict[tuple[int, int], int] = {}
    lidar_world: list[np.ndarray] = []
    with SceneWriter(out_dir, scene_id, source, overwrite=overwrite) as writer:
        writer.set_frames(world.timestamps_us(), world.ego_poses)
        writer.set_cameras([CameraRecord(c.name, c.width, c.height, c.K, c.ego_from_camera) for c in world.cameras])
        writer.write_world_json(world.to_json())
        writer.set_extra(template=world.template, lighting=world.lighting, seed=world.seed)
        for f in range(world.n_frames):
            for cam in world.cameras:
                r = renderer.render_camera(f, cam.name)
                writer.write_image(cam.name, f, r.rgb)
                writer.write_gt(cam.name, f, r.depth, r.instance, r.semantic)
                ids, counts = np.unique(r.instance[r.instance >= 0], return_counts=True)
                for tid, n in zip(ids.tolist(), counts.tolist()):
                    visible[(f, tid)] = visible.get((f, tid), 0) + n
                done += 1
                if progress:
                    progress(done, total)
            points = renderer.lidar_scan(f)
            writer.write_lidar(f, points)
            lidar_world.append(transform_points(world.ego_poses[f], points[:, :3]))
            done += 1
            if progress:
                progress(done, total)
        writer.set_boxes(boxes_from_world(world, lidar_world, visible))
    return Path(out_dir)


def write_synthetic_scene(source: SyntheticSource, out_dir: Path, overwrite: bool = False,
                          progress: Callable[[int, int], None] | None = None) -> Path:
    """Generate the world for ``source`` and write it as a scene store."""
    from omniscs.world import generate_world

    world = generate_world(source.template, source.seed, n_frames=source.n_frames, n_cameras=source.n_cameras,
                           width=source.width, height=source.height, lighting=source.lighting)
    return write_world_scene(world, out_dir, source.scene_id(), source.to_dict(), overwrite, progress)
