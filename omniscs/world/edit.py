"""Apply edit specs (omniscs.edits) to a ground-truth World, giving a new World that re-renders exactly."""
from __future__ import annotations

import numpy as np

from omniscs.edits import (Edit, Insert, Remove, ReplaceModel, Rotate, SetTrajectory, Translate, local_motion,
                           parse_edits, resized_poses, poses_from_waypoints, resting_tilt)
from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform
from omniscs.taxonomy import CATEGORIES
from omniscs.world.assets import asset_category, build_asset
from omniscs.world.model import AgentTrack, World


def apply_edits(world: World, edits) -> World:
    """A new World with ``edits`` (edit objects, dicts or a JSON string) applied in order; ``world`` is untouched.

    Translate/Rotate right-multiply their local motion onto every pose; Remove drops the track;
    ReplaceModel swaps the asset and keeps the box (the renderer scales the new mesh to fit it), or takes the
    edit's ``size``, resting on the same ground;
    SetTrajectory replaces poses and presence; Insert adds a track.
    """
    tracks: dict[int, AgentTrack] = {a.track_id: a for a in world.agents}
    for edit in parse_edits(edits):
        _apply_one(world, tracks, edit)
    return world.replace(agents=tuple(tracks.values()))


def _track(tracks: dict[int, AgentTrack], track_id: int) -> AgentTrack:
    if track_id not in tracks:
        raise OmniscsError(f"edit refers to unknown track id {track_id}; this world has {sorted(tracks)}")
    return tracks[track_id]


def _finite(values, what: str) -> None:
    if not np.all(np.isfinite(np.asarray(values, dtype=np.float64))):
        raise OmniscsError(f"{what} must be finite numbers; got {values!r}")


def _replace(track: AgentTrack, **changes) -> AgentTrack:
    fields = dict(track_id=track.track_id, category=track.category, asset_id=track.asset_id,
                  size=track.size.copy(), poses=track.poses.copy(), present=track.present.copy())
    fields.update(changes)
    return AgentTrack(**fields)


def _apply_one(world: World, tracks: dict[int, AgentTrack], edit: Edit) -> None:
    if isinstance(edit, (Translate, Rotate)):
        values = ([edit.longitudinal, edit.lateral, edit.vertical] if isinstance(edit, Translate)
                  else [edit.yaw_deg, edit.pitch_deg, edit.roll_deg])
        _finite(values, f"{edit.op} amounts")
        t = _track(tracks, edit.track_id)
        tracks[t.track_id] = _replace(t, poses=t.poses @ local_motion(edit))
    elif isinstance(edit, Remove):
        _track(tracks, edit.track_id)
        del tracks[edit.track_id]
    elif isinstance(edit, ReplaceModel):
        t = _track(tracks, edit.track_id)
        build_asset(edit.asset_id)  # unknown ids raise here
        size = t.size if edit.size is None else np.asarray(edit.size, dtype=np.float64)
        tracks[t.track_id] = _replace(t, asset_id=edit.asset_id, category=asset_category(edit.asset_id),
                                      size=size.copy(), poses=resized_poses(t.poses, t.size, size))
    elif isinstance(edit, SetTrajectory):
        t = _track(tracks, edit.track_id)
        poses, present = poses_from_waypoints(edit.waypoints, world.n_frames)
        for f in np.flatnonzero(~present):  # absent frames keep a harmless pose
            poses[f] = t.poses[f]
        tracks[t.track_id] = _replace(t, poses=poses, present=present)
    elif isinstance(edit, Insert):
        tracks[edit.track_id] = _inserted_track(world, tracks, edit)
    else:  # parse_edits only yields the types above
        raise OmniscsError(f"unsupported edit {edit!r}")


def _inserted_track(world: World, tracks: dict[int, AgentTrack], edit: Insert) -> AgentTrack:
    if not isinstance(edit.track_id, (int, np.integer)) or edit.track_id < 0:
        raise OmniscsError(f"inserted track id must be a non-negative integer; got {edit.track_id!r}")
    if edit.track_id in tracks:
        raise OmniscsError(f"cannot insert track {edit.track_id}: that id is already used; pick an unused id "
                           f"(max used is {max(tracks)})")
    if edit.category not in CATEGORIES:
        raise OmniscsError(f"unknown category {edit.category!r} for inserted track; use one of {list(CATEGORIES)}")
    asset = build_asset(edit.asset_id)
    size = asset.size.copy() if edit.size is None else np.asarray(edit.size, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise OmniscsError(f"inserted box size must be 3 positive numbers (length, width, height); got {edit.size!r}")
    _finite([edit.roll_deg, edit.pitch_deg], "insert roll/pitch")
    if (edit.pose is None) == (edit.waypoints is None):
        raise OmniscsError("an insert needs exactly one of 'pose' (x, y, z, yaw) or 'waypoints' (one per frame)")
    if edit.pose is not None:
        if len(edit.pose) != 4:
            raise OmniscsError(f"insert pose must be (x, y, z, yaw); got {edit.pose!r}")
        _finite(edit.pose, "insert pose")
        waypoints = [tuple(edit.pose)] * world.n_frames
    else:
        waypoints = edit.waypoints
    poses, present = poses_from_waypoints(waypoints, world.n_frames)
    R, lift = resting_tilt(size, edit.roll_deg, edit.pitch_deg)
    poses = poses @ make_transform(R, np.zeros(3))
    poses[:, 2, 3] += lift
    return AgentTrack(track_id=int(edit.track_id), category=edit.category, asset_id=edit.asset_id, size=size,
                      poses=poses, present=present)
