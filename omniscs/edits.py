"""Edit specs: JSON-serialisable values that describe changes to agents.

The same list of edits is applied to the ground-truth world (``omniscs.world.apply_edits``) and to a
fitted scene graph, so an edit's fidelity can be measured against an exact re-render. Pose edits act
in the agent's local frame (x forward, y left, z up; origin at the box centre) for every frame, and a
list applies in order, each edit in the frame the previous ones left (after a 180° roll, +lateral
points to the agent's former right).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, pose_from_xyz_yaw, rotmat_from_euler


@dataclass(frozen=True)
class Translate:
    """Shift an agent in its own frame: +longitudinal = ahead, +lateral = to its left."""

    track_id: int
    longitudinal: float = 0.0
    lateral: float = 0.0
    vertical: float = 0.0
    op: str = field(default="translate", init=False)


@dataclass(frozen=True)
class Rotate:
    """Rotate an agent about its box centre, in its own frame (yaw about z; roll 180° = overturned)."""

    track_id: int
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    op: str = field(default="rotate", init=False)


@dataclass(frozen=True)
class Remove:
    """Delete an agent from every frame."""

    track_id: int
    op: str = field(default="remove", init=False)


@dataclass(frozen=True)
class ReplaceModel:
    """Swap the agent's appearance for another asset/model, scaled to the agent's box; motion is kept."""

    track_id: int
    asset_id: str
    op: str = field(default="replace_model", init=False)


@dataclass(frozen=True)
class SetTrajectory:
    """Replace the agent's whole trajectory: one [x, y, z, yaw] (world frame) per frame; null = absent."""

    track_id: int
    waypoints: tuple  # F entries of (x, y, z, yaw) or None
    op: str = field(default="set_trajectory", init=False)


@dataclass(frozen=True)
class Insert:
    """Add a new agent from an asset at a pose (static) or along waypoints (x, y, z, yaw per frame).

    ``roll_deg``/``pitch_deg`` tilt it in its own frame (roll 180 = overturned). ``size`` is the box
    (length, width, height); null takes the asset's own size.
    """

    track_id: int
    asset_id: str
    category: str
    pose: tuple | None = None  # (x, y, z, yaw) world frame, the same in every frame
    waypoints: tuple | None = None  # F entries of (x, y, z, yaw) or None
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    size: tuple | None = None
    op: str = field(default="insert", init=False)


Edit = Translate | Rotate | Remove | ReplaceModel | SetTrajectory | Insert
_OPS = {cls.__dataclass_fields__["op"].default: cls
        for cls in (Translate, Rotate, Remove, ReplaceModel, SetTrajectory, Insert)}


def edit_from_dict(d: dict) -> Edit:
    if not isinstance(d, dict) or "op" not in d:
        raise OmniscsError(f"an edit must be an object with an 'op' field, one of {sorted(_OPS)}; got {d!r}")
    cls = _OPS.get(d["op"])
    if cls is None:
        raise OmniscsError(f"unknown edit op {d['op']!r}; use one of {sorted(_OPS)}")
    args = {k: v for k, v in d.items() if k != "op"}
    for key in ("waypoints", "pose", "size"):
        if args.get(key) is not None:
            args[key] = _freeze(args[key])
    try:
        return cls(**args)
    except TypeError as exc:
        raise OmniscsError(f"bad fields for edit {d['op']!r}: {exc}") from None


def parse_edits(text_or_list) -> list[Edit]:
    """Edits from a JSON string, a list of dicts, or a list of edit objects."""
    if isinstance(text_or_list, str):
        try:
            text_or_list = json.loads(text_or_list)
        except json.JSONDecodeError as exc:
            raise OmniscsError(f"edit list is not valid JSON: {exc}") from None
    if isinstance(text_or_list, dict):
        text_or_list = [text_or_list]
    return [e if isinstance(e, tuple(_OPS.values())) else edit_from_dict(e) for e in text_or_list]


def edit_to_dict(e: Edit) -> dict:
    return _thaw(asdict(e))


def _freeze(x):
    return tuple(_freeze(v) for v in x) if isinstance(x, (list, tuple)) else x


def _thaw(x):
    if isinstance(x, dict):
        return {k: _thaw(v) for k, v in x.items()}
    return [_thaw(v) for v in x] if isinstance(x, (list, tuple)) else x


# ----------------------------------------------------------------------------- pose math
def local_motion(edit: Translate | Rotate) -> np.ndarray:  # -> [4, 4] agent_from_edited_agent
    """The rigid motion an edit applies in the agent's own frame (right-multiplied onto its poses)."""
    if isinstance(edit, Translate):
        return make_transform(np.eye(3), [edit.longitudinal, edit.lateral, edit.vertical])
    return make_transform(
        rotmat_from_euler(np.radians(edit.roll_deg), np.radians(edit.pitch_deg), np.radians(edit.yaw_deg)),
        np.zeros(3),
    )


def poses_from_waypoints(waypoints, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """[F] (x, y, z, yaw) or None -> poses [F, 4, 4] world_from_agent, present [F] bool."""
    if len(waypoints) != n_frames:
        raise OmniscsError(f"trajectory has {len(waypoints)} waypoints but the log has {n_frames} frames")
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    present = np.zeros(n_frames, dtype=bool)
    for i, w in enumerate(waypoints):
        if w is None:
            continue
        if len(w) != 4 or not np.all(np.isfinite(np.asarray(w, dtype=np.float64))):
            raise OmniscsError(f"waypoint {i} must be 4 finite numbers (x, y, z, yaw); got {w!r}")
        poses[i] = pose_from_xyz_yaw(*w)
        present[i] = True
    return poses, present


def resting_tilt(size: np.ndarray, roll_deg: float, pitch_deg: float) -> tuple[np.ndarray, float]:  # R [3, 3], dz
    """Local tilt (roll about x, then pitch about y) plus the vertical shift that keeps the tilted box
    resting on the ground that the upright box stood on (roll 180: no shift; roll 90: z - h/2 + w/2)."""
    R = rotmat_from_euler(np.radians(roll_deg), np.radians(pitch_deg), 0.0)
    half_up = 0.5 * float(np.abs(R[2]) @ np.asarray(size, dtype=np.float64))
    return R, half_up - 0.5 * float(size[2])
