"""A variant as frames to render: which scene frames, the ego's poses, every box (world frame) and where each agent
node is placed. The render and the labels read the same poses, so a box always sits where its node is drawn."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from omniscs.annotate.config import AnnotateConfig
from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform, pose_from_xyz_yaw, wrap_angle
from omniscs.quaternions import rotmat_to_quat
from omniscs.scene.store import BOX_COLUMNS, Scene

#: UniAD's command one-hot order (VAD/UniAD converters): index 0 right, 1 left, 2 forward.
COMMANDS = ("right", "left", "forward")
#: An agent counts as moved by the variant when a rendered frame puts it this far (metres) or this much turned
#: (degrees) from its logged box.
MOVED_M, MOVED_DEG = 0.05, 1.0


@dataclass(frozen=True)
class VariantFrames:
    """The frames of one variant that are rendered, renumbered 0..T-1 in the variant's store."""

    scene_frames: np.ndarray     # [T] int: the source scene's frame of each rendered frame
    timestamps_us: np.ndarray    # [T] int64
    world_from_ego: np.ndarray   # [T, 4, 4] float64: the ego on the variant's trajectory (its solution when solved)
    boxes: pd.DataFrame          # BOX_COLUMNS rows, frame_idx = 0..T-1, world frame
    velocities: np.ndarray       # [len(boxes), 3] world-frame velocity of each box row (m/s)
    node_poses: tuple[dict[int, np.ndarray], ...]  # [T] {track id: world_from_agent [4, 4]} for moved agent nodes
    commands: np.ndarray         # [T] int: index into COMMANDS
    viewpoint_offset_m: np.ndarray  # [T] distance of the ego from the nearest logged ego position
    dropped_frames: tuple[int, ...]  # scene frames not rendered: the ego left the fitted area there
    moved: frozenset[int] = frozenset()  # agents the variant puts off their logged pose in a rendered frame

    @property
    def n_frames(self) -> int:
        return len(self.scene_frames)


def variant_frames(scene: Scene, variant: dict, agent_nodes: set[int] | frozenset[int],
                   ego_xy_yaw: np.ndarray | None = None,  # [S, 3] world box centre of the ego; None = the variant's
                   config: AnnotateConfig = AnnotateConfig(),
                   edited: dict | None = None) -> VariantFrames:
    """Frames, ego poses and boxes of ``variant`` (a ``variants.json`` entry) over ``scene``. Agent nodes the variant
    moves are placed upright at its (x, y, yaw) with their logged height; every other track keeps its logged box
    (tracks left in the background cannot move). ``ego_xy_yaw`` replaces the variant's ego (the ego's solution); a
    variant whose ``ego`` is null keeps the logged ego poses. ``edited`` ({track id: node annotation boxes, or None
    for a removed track}; ``omniscs.scs.appearance.compose.node_boxes``) gives the boxes of tracks an edit changed,
    replaced or inserted: they come from the edited graph's nodes, which draw themselves where they are."""
    from omniscs.scs.behavior.render_consistency import variant_ego_poses

    steps_frames = variant.get("source_frames")
    if steps_frames is None:
        raise OmniscsError(f"variant {variant.get('variant_id')} has no scene frames (its log was resampled to the "
                           "behaviour model's time step); it cannot be rendered")
    steps_frames = np.asarray(steps_frames, dtype=np.int64)
    ego = variant.get("ego")
    if ego_xy_yaw is not None:
        ego = np.asarray(ego_xy_yaw, dtype=np.float64).reshape(-1, 3)
        if len(ego) != len(steps_frames) or not np.all(np.isfinite(ego)):
            raise OmniscsError(f"the ego trajectory has {len(ego)} finite steps; the variant has {len(steps_frames)}")
        ego = ego.tolist()
    if ego is not None and len(ego) != len(steps_frames):
        raise OmniscsError(f"variant {variant.get('variant_id')}: its ego trajectory does not cover its steps")
    if np.any(steps_frames < 0) or np.any(steps_frames >= scene.n_frames):
        raise OmniscsError(f"variant {variant.get('variant_id')} names frames outside the scene's 0..{scene.n_frames - 1}")
    logged = scene.world_from_ego_all
    ego_poses = logged.copy() if ego is None else variant_ego_poses(dict(variant, ego=ego), logged)
    edited = edited or {}

    picked = np.arange(0, len(steps_frames), int(config.frame_every))
    frames = steps_frames[picked]
    offsets = np.array([np.min(np.linalg.norm(logged[:, :2, 3] - ego_poses[f, :2, 3], axis=1)) for f in frames])
    keep = offsets <= config.max_viewpoint_offset_m
    dropped = tuple(int(f) for f in frames[~keep])
    picked, frames, offsets = picked[keep], frames[keep], offsets[keep]
    ts = scene.frames["timestamp_us"].to_numpy(np.int64)[frames]
    world_from_ego = ego_poses[frames]
    commands = driving_commands(ego_poses[steps_frames], scene.frames["timestamp_us"].to_numpy(np.int64)[steps_frames],
                                config)[picked]

    agents = variant.get("agents") or {}
    rows, node_poses, moved = [], [], set()
    for t, (k, f) in enumerate(zip(picked, frames)):
        placed: dict[int, np.ndarray] = {}
        for box in scene.boxes_at(int(f)).itertuples(index=False):
            tid = int(box.track_id)
            if tid in edited:  # the edited node's own box below (or none: removed)
                continue
            row = {c: getattr(box, c) for c in BOX_COLUMNS}
            row["frame_idx"] = t
            traj = agents.get(str(tid))
            pose = traj[k] if traj is not None and k < len(traj) else None
            if tid in agent_nodes and pose is not None:
                x, y, yaw = (float(v) for v in pose)
                if (np.hypot(x - box.cx, y - box.cy) > MOVED_M
                        or abs(float(wrap_angle(yaw - box.yaw))) > np.radians(MOVED_DEG)):
                    moved.add(tid)
                world_from_agent = pose_from_xyz_yaw(x, y, float(box.cz), yaw)
                placed[tid] = world_from_agent
                q = rotmat_to_quat(world_from_agent[:3, :3])
                row.update(cx=x, cy=y, yaw=float(wrap_angle(yaw)), qw=q[0], qx=q[1], qy=q[2], qz=q[3])
            row["num_lidar_points"], row["visible_pixels"] = -1, -1
            rows.append(row)
        for tid, node_rows in sorted(edited.items()):
            if node_rows is not None and int(f) in node_rows:
                rows.append({**node_rows[int(f)], "frame_idx": t, "track_id": tid, "num_lidar_points": -1,
                             "visible_pixels": -1})
        node_poses.append(placed)
    boxes = pd.DataFrame(rows, columns=BOX_COLUMNS)
    moved |= set(edited)
    return VariantFrames(frames.astype(np.int64), ts, world_from_ego, boxes, box_velocities(boxes, ts),
                         tuple(node_poses), commands, offsets, dropped, frozenset(moved))


def box_velocities(boxes: pd.DataFrame, timestamps_us: np.ndarray) -> np.ndarray:  # -> [N, 3] m/s, world frame
    """Velocity of each box row by central differences over its track's neighbouring frames (one-sided at the
    ends, 0 for a track seen in one frame only)."""
    out = np.zeros((len(boxes), 3))
    if len(boxes) == 0:
        return out
    t_s = np.asarray(timestamps_us, dtype=np.float64) / 1e6
    frame = boxes["frame_idx"].to_numpy(np.int64)
    xyz = boxes[["cx", "cy", "cz"]].to_numpy(np.float64)
    for _, index in boxes.groupby("track_id").indices.items():
        index = index[np.argsort(frame[index])]
        if len(index) < 2:
            continue
        for j, row in enumerate(index):
            a, b = index[max(j - 1, 0)], index[min(j + 1, len(index) - 1)]
            dt = t_s[frame[b]] - t_s[frame[a]]
            if dt > 0:
                out[row] = (xyz[b] - xyz[a]) / dt
    return out


def driving_commands(world_from_ego: np.ndarray,  # [S, 4, 4] the ego over the variant's steps
                     timestamps_us: np.ndarray,   # [S]
                     config: AnnotateConfig = AnnotateConfig()) -> np.ndarray:  # [S] index into COMMANDS
    """The driving command of every step by UniAD's rule: where the ego is ``command_horizon_s`` later (or at the
    last step), in the current ego frame; right when it lies ``command_lateral_m`` or more to the right, left
    when as far to the left, forward otherwise."""
    ts = np.asarray(timestamps_us, dtype=np.int64)
    out = np.full(len(ts), COMMANDS.index("forward"), dtype=np.int64)
    horizon_us = int(round(config.command_horizon_s * 1e6))
    for s in range(len(ts)):
        later = int(np.searchsorted(ts, ts[s] + horizon_us, side="left"))
        later = min(later, len(ts) - 1)
        ahead = invert_transform(world_from_ego[s]) @ world_from_ego[later][:, 3]
        lateral = float(ahead[1])  # ego frame: +y is left
        if lateral <= -config.command_lateral_m:
            out[s] = COMMANDS.index("right")
        elif lateral >= config.command_lateral_m:
            out[s] = COMMANDS.index("left")
    return out

