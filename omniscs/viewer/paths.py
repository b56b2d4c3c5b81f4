"""A new trajectory for an agent from a few dragged control points (a cut-in is drawn with three or four): the path
between them is linear in time, the heading follows the direction of travel, the height stays where the agent was.
The result is the per-frame waypoints of a ``set_trajectory`` edit (``omniscs.edits.SetTrajectory``)."""
from __future__ import annotations

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import yaw_from_matrix

#: Most control points shown on a path (evenly spaced over the frames the agent is present in).
MAX_CONTROL_POINTS = 6
#: Below this step (metres per frame) an agent counts as standing: it keeps the heading it had.
STANDING_STEP_M = 0.05


def control_frames(present: np.ndarray, n: int = MAX_CONTROL_POINTS) -> np.ndarray:  # [F] bool -> [K] int
    """Up to ``n`` frames evenly spread over the present ones, the first and the last always among them."""
    frames = np.flatnonzero(np.asarray(present, dtype=bool))
    if len(frames) <= n:
        return frames
    return frames[np.unique(np.round(np.linspace(0, len(frames) - 1, n)).astype(int))]


def path_waypoints(world_from_agent: np.ndarray,  # [F, 4, 4] the agent's current poses
                   present: np.ndarray,           # [F] bool
                   frames: np.ndarray,            # [K] int, increasing, present: the control frames
                   control_xy: np.ndarray,        # [K, 2] world: where the control points now are
                   ) -> list[tuple[float, float, float, float] | None]:  # F entries (x, y, z, yaw) or None
    """The agent's new path: at every present frame the position linear in frame number between the control points
    around it (held before the first and after the last), the current height, and the heading of the direction of
    travel (the heading it had where it stands still). Absent frames stay None."""
    poses = np.asarray(world_from_agent, dtype=np.float64)
    present = np.asarray(present, dtype=bool)
    frames = np.asarray(frames, dtype=np.int64)
    control_xy = np.asarray(control_xy, dtype=np.float64).reshape(-1, 2)
    if len(frames) == 0 or len(frames) != len(control_xy):
        raise OmniscsError(f"a path needs one control point per control frame; got {len(control_xy)} points for "
                           f"{len(frames)} frames")
    if np.any(np.diff(frames) <= 0) or not present[frames].all():
        raise OmniscsError("control frames must increase and be frames the agent is present in")
    if not np.all(np.isfinite(control_xy)):
        raise OmniscsError("control points must be finite")
    keep = np.flatnonzero(present)
    xy = np.stack([np.interp(keep, frames, control_xy[:, i]) for i in range(2)], -1)  # [P, 2]
    yaw = yaw_from_matrix(poses[keep, :3, :3]).copy()
    if len(keep) > 1:
        step = np.gradient(xy, keep, axis=0)  # metres per frame, central differences
        moving = np.hypot(step[:, 0], step[:, 1]) > STANDING_STEP_M
        yaw[moving] = np.arctan2(step[moving, 1], step[moving, 0])
    out: list[tuple[float, float, float, float] | None] = [None] * len(present)
    for i, f in enumerate(keep):
        out[f] = (float(xy[i, 0]), float(xy[i, 1]), float(poses[f, 2, 3]), float(yaw[i]))
    return out


def is_upright(world_from_agent: np.ndarray, present: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether the agent stands on its wheels (its up axis is world up) in every present frame: a path of
    ``set_trajectory`` is upright, so a tilted agent (on its side, overturned) keeps its own motion."""
    up = np.asarray(world_from_agent, dtype=np.float64)[np.asarray(present, dtype=bool), 2, 2]
    return bool(np.all(up > 1.0 - tol))
