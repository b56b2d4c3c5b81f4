"""Agent nodes: Gaussians in the agent's own frame (x forward, y left, z up, box centre) plus a pose per frame."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams, params_from_values
from omniscs.geometry import invert_transform, make_transform, transform_points
from omniscs.nsg.background import neighbour_scales
from omniscs.nsg.relight import Relight
from omniscs.quaternions import quat_to_rotmat


@dataclass(frozen=True)
class AgentNode:
    """One agent: ``G_A-loc`` (local Gaussians) and ``T_A`` (world_from_agent per frame)."""

    track_id: int
    category: str
    size: np.ndarray              # [3] float64 box (length, width, height), metres
    world_from_agent: np.ndarray  # [F, 4, 4] float64; frames where the agent is absent hold any rigid pose
    present: np.ndarray           # [F] bool
    gaussians: GaussianParams     # agent frame
    relight: Relight | None = None
    """Albedo and normals of the Gaussians and the scene's light: their colours then follow the node's pose in
    each frame (``omniscs.nsg.relight``) instead of the colours the Gaussians hold."""

    def __post_init__(self) -> None:
        for array in (self.size, self.world_from_agent, self.present):
            array.flags.writeable = False  # a graph is a value: edits make new arrays
        if self.relight is not None and len(self.relight) != len(self.gaussians):
            raise OmniscsError(f"agent {self.track_id}: relight data for {len(self.relight)} Gaussians, "
                               f"the node has {len(self.gaussians)}")

    def with_changes(self, **changes) -> "AgentNode":
        """A copy with ``changes``; new Gaussians drop the relight data unless ``relight`` comes with them."""
        fields = dict(track_id=self.track_id, category=self.category, size=self.size.copy(),
                      world_from_agent=self.world_from_agent.copy(), present=self.present.copy(),
                      gaussians=self.gaussians, relight=self.relight)
        if "gaussians" in changes and "relight" not in changes:
            fields["relight"] = None
        fields.update(changes)
        return AgentNode(**fields)


def track_poses(boxes: pd.DataFrame, track_id: int, n_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """world_from_agent [F, 4, 4], present [F] bool and median size [3] of one track from the box table.

    Absent frames take the nearest present frame's pose, so the node has a rigid pose everywhere."""
    rows = boxes[boxes.track_id == track_id].sort_values("frame_idx")
    if rows.empty:
        raise OmniscsError(f"track {track_id} has no boxes in this scene")
    frames = rows["frame_idx"].to_numpy()
    R = quat_to_rotmat(rows[["qw", "qx", "qy", "qz"]].to_numpy(dtype=np.float64))
    poses_present = make_transform(R, rows[["cx", "cy", "cz"]].to_numpy(dtype=np.float64))
    present = np.zeros(n_frames, dtype=bool)
    present[frames] = True
    nearest = np.abs(np.arange(n_frames)[:, None] - frames[None, :]).argmin(axis=1)
    poses = poses_present[nearest]
    size = np.median(rows[["length", "width", "height"]].to_numpy(dtype=np.float64), axis=0)
    return poses, present, size


def points_in_agent_box(points_world: np.ndarray,    # [N, 3]
                        world_from_agent: np.ndarray,  # [4, 4]
                        size: np.ndarray,              # [3]
                        margin: float, ground_clearance: float,
                        ) -> tuple[np.ndarray, np.ndarray]:  # inside [N] bool, points in the agent frame [N, 3]
    """Which points lie in the box grown by ``margin`` (but above its floor + ``ground_clearance``: road
    returns under the wheels are not the agent)."""
    local = transform_points(invert_transform(world_from_agent), points_world)
    half = 0.5 * np.asarray(size, dtype=np.float64)
    inside = np.all(np.abs(local[:, :2]) <= half[:2] + margin, axis=1)
    inside &= (local[:, 2] <= half[2] + margin) & (local[:, 2] >= -half[2] + ground_clearance)
    return inside, local


def box_surface_points(size: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:  # -> [n, 3] agent frame
    """Points spread uniformly (by area) over the box faces: the seed of an agent no LiDAR ray hit."""
    L, W, H = (float(v) for v in size)
    areas = np.array([W * H, W * H, L * H, L * H, L * W, L * W])
    face = rng.choice(6, size=n, p=areas / areas.sum())
    uv = rng.uniform(-0.5, 0.5, size=(n, 2))
    half = 0.5 * np.array([L, W, H])
    pts = np.empty((n, 3))
    axis = face // 2               # 0: x faces, 1: y faces, 2: z faces
    sign = np.where(face % 2 == 0, 1.0, -1.0)
    for a in range(3):
        sel = axis == a
        others = [b for b in range(3) if b != a]
        pts[sel, a] = sign[sel] * half[a]
        pts[sel, others[0]] = uv[sel, 0] * 2 * half[others[0]]
        pts[sel, others[1]] = uv[sel, 1] * 2 * half[others[1]]
    return pts


def init_agent_gaussians(points_local: np.ndarray,  # [M, 3] agent frame (in-box LiDAR, or box surface)
                         colours: np.ndarray,       # [M, 3] in [0, 1]
                         size: np.ndarray,          # [3]
                         budget: int, sh_degree: int, opacity: float, rng: np.random.Generator,
                         ) -> GaussianParams:
    """Local Gaussians on the given points (subsampled to ``budget``), sized by point spacing."""
    if len(points_local) > budget:
        keep = rng.choice(len(points_local), size=budget, replace=False)
        points_local, colours = points_local[keep], colours[keep]
    # spacing relative to the box, so a handful of points on a truck still cover it
    max_scale = 0.25 * float(np.min(size))
    scales = neighbour_scales(points_local, max_scale=max_scale)
    n = len(points_local)
    return params_from_values(torch.from_numpy(points_local), torch.from_numpy(scales)[:, None].expand(n, 3),
                              torch.full((n,), opacity), torch.from_numpy(colours), sh_degree)
