"""Edit specs: JSON-serialisable values that describe changes to agents.

The same list of edits is applied to the ground-truth world (``omniscs.world.apply_edits``) and to a
fitted scene graph, so an edit's fidelity can be measured against an exact re-render. Pose edits act
in the agent's local frame (x forward, y left, z up; origin at the box centre) for every frame, and a
list applies in order, each edit in the frame the previous ones left (after a 180° roll, +lateral
points to the agent's former right).
"""
from __future__ import annotations

from dataclasses import MISSING, asdict, dataclass, field, fields

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, pose_from_xyz_yaw, rotmat_from_euler
from omniscs.untrusted import loads_json


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
    """Swap the agent's appearance for another asset/model; motion is kept. With ``size`` null the model is scaled
    to the agent's box; with ``size`` (length, width, height; e.g. the model's own size) the box becomes that size,
    resting on the ground the agent's box stood on (appearance-level SCS keeps an object's own proportions)."""

    track_id: int
    asset_id: str
    size: tuple | None = None
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

#: Bounds of edit values: beyond them an edit is a typo, not a scenario.
MAX_TRACK_ID = 2**31 - 1
"""Largest track id (readers number tracks from 0; KITTI's own ids are small)."""
MAX_SHIFT_M = 1_000.0
"""Largest translate amount along each axis (metres)."""
MAX_ANGLE_DEG = 360.0
"""Largest rotate or insert-tilt angle (degrees, either sign)."""
MAX_COORD_M = 100_000.0
"""Largest world coordinate of an insert pose or a waypoint (metres from the log's first ego pose)."""
MAX_YAW_RAD = 1_000.0
"""Largest yaw of a pose or waypoint (radians; unwrapped yaws may pass 2 pi)."""
MAX_SIZE_M = 100.0
"""Largest inserted box side (metres)."""
MAX_WAYPOINTS = 100_000
"""Most waypoints of one trajectory (one per frame)."""
MAX_NAME_LENGTH = 200
"""Longest asset id or category name."""

#: Fields holding an amount: (largest magnitude, unit).
_AMOUNTS = {"longitudinal": (MAX_SHIFT_M, "metres"), "lateral": (MAX_SHIFT_M, "metres"),
            "vertical": (MAX_SHIFT_M, "metres"), "yaw_deg": (MAX_ANGLE_DEG, "degrees"),
            "pitch_deg": (MAX_ANGLE_DEG, "degrees"), "roll_deg": (MAX_ANGLE_DEG, "degrees")}


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _is_sequence(v) -> bool:
    return isinstance(v, (list, tuple, np.ndarray))


def _fields_of(cls) -> tuple[list[str], list[str]]:
    """(every field a user may give, the required ones) of an edit class."""
    given = [f for f in fields(cls) if f.init]
    return [f.name for f in given], [f.name for f in given if f.default is MISSING and f.default_factory is MISSING]


def _xyz_yaw(value, what: str, where: str) -> tuple:
    if not _is_sequence(value) or len(value) != 4 or not all(_is_number(v) for v in value):
        raise OmniscsError(f"{where}: {what} must be 4 numbers [x, y, z, yaw]; got {_short(value)}")
    out = tuple(float(v) for v in value)
    if not all(np.isfinite(out)) or max(abs(v) for v in out[:3]) > MAX_COORD_M or abs(out[3]) > MAX_YAW_RAD:
        raise OmniscsError(f"{where}: {what} must be finite, with |x|, |y|, |z| <= {MAX_COORD_M:g} m and "
                           f"|yaw| <= {MAX_YAW_RAD:g} rad; got {_short(value)}")
    return out


def _short(value) -> str:
    text = repr(_thaw(value) if isinstance(value, (list, tuple)) else value)
    return text if len(text) <= 80 else text[:77] + "..."


def _check_field(name: str, value, where: str):
    """``value`` of field ``name`` normalised (ints, floats, tuples), or one OmniscsError saying what is wrong."""
    if name == "track_id":
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
                or not 0 <= int(value) <= MAX_TRACK_ID:
            raise OmniscsError(f"{where}: field track_id must be an integer from 0 to {MAX_TRACK_ID}; got "
                               f"{_short(value)}")
        return int(value)
    if name in _AMOUNTS:
        bound, unit = _AMOUNTS[name]
        if not _is_number(value) or not np.isfinite(float(value)) or abs(float(value)) > bound:
            raise OmniscsError(f"{where}: field {name} must be a finite number of {unit} from -{bound:g} to "
                               f"{bound:g}; got {_short(value)}")
        return float(value)
    if name in ("asset_id", "category"):
        if not isinstance(value, str) or not value.strip() or len(value) > MAX_NAME_LENGTH or "\n" in value:
            raise OmniscsError(f"{where}: field {name} must be a non-empty name of at most {MAX_NAME_LENGTH} "
                               f"characters; got {_short(value)}")
        if name == "category":
            from omniscs.taxonomy import CATEGORIES

            if value not in CATEGORIES:
                raise OmniscsError(f"{where}: unknown category {value!r}; use one of {list(CATEGORIES)}")
        return value
    if name == "pose":
        return None if value is None else _xyz_yaw(value, "field pose", where)
    if name == "waypoints":
        if value is None:
            return None
        if not _is_sequence(value) or not 1 <= len(value) <= MAX_WAYPOINTS:
            raise OmniscsError(f"{where}: field waypoints must be a list of 1 to {MAX_WAYPOINTS} entries "
                               f"[x, y, z, yaw] or null (one per frame); got {_short(value)}")
        return tuple(None if w is None else _xyz_yaw(w, f"waypoint {i}", where) for i, w in enumerate(value))
    if name == "size":
        if value is None:
            return None
        if (not _is_sequence(value) or len(value) != 3 or not all(_is_number(v) for v in value)
                or not all(np.isfinite(float(v)) and 0 < float(v) <= MAX_SIZE_M for v in value)):
            raise OmniscsError(f"{where}: field size must be 3 numbers (length, width, height) above 0 and at most "
                               f"{MAX_SIZE_M:g} m, or null; got {_short(value)}")
        return tuple(float(v) for v in value)
    raise OmniscsError(f"{where}: unknown field {name!r}")


def _build(cls, args: dict, where: str) -> Edit:
    op = cls.__dataclass_fields__["op"].default
    allowed, required = _fields_of(cls)
    unknown = sorted(k for k in args if k not in allowed)
    if unknown:
        raise OmniscsError(f"{where}: unknown field(s) {unknown}; a {op} edit takes {allowed}")
    missing = [k for k in required if k not in args]
    if missing:
        raise OmniscsError(f"{where}: missing field(s) {missing}; a {op} edit needs {required}")
    values = {k: _check_field(k, v, where) for k, v in args.items()}
    if cls is Insert and (values.get("pose") is None) == (values.get("waypoints") is None):
        raise OmniscsError(f"{where}: an insert needs exactly one of 'pose' [x, y, z, yaw] or 'waypoints' (one "
                           "per frame)")
    return cls(**values)


def _where(index: int | None, op) -> str:
    op_text = f" ({op})" if isinstance(op, str) and op in _OPS else ""
    return f"edit {index}{op_text}" if index is not None else f"edit{op_text}"


def edit_from_dict(d: dict, index: int | None = None) -> Edit:
    """One edit from its JSON form ``{"op": ..., "track_id": ..., ...}``; anything malformed (not an object, an
    unknown op or field, a missing field, a value of the wrong type, NaN/Inf or out of bounds) is one
    OmniscsError naming the edit (``index`` in its list) and field."""
    where = _where(index, d.get("op") if isinstance(d, dict) else None)
    if not isinstance(d, dict) or "op" not in d:
        raise OmniscsError(f"{where}: an edit must be a JSON object with an 'op' field, one of {sorted(_OPS)}; "
                           f"got {_short(d)}")
    op = d["op"]
    if not isinstance(op, str) or op not in _OPS:
        raise OmniscsError(f"{where}: unknown edit op {_short(op)}; use one of {sorted(_OPS)}")
    return _build(_OPS[op], {k: v for k, v in d.items() if k != "op"}, where)


def check_edit(edit: Edit, index: int | None = None) -> Edit:
    """An edit object with every field checked as ``edit_from_dict`` checks JSON (a normalised copy)."""
    where = _where(index, edit.op)

    return _build(type(edit), {f.name: getattr(edit, f.name) for f in fields(edit) if f.init}, where)


def parse_edits(text_or_list) -> list[Edit]:
    """Edits from a JSON string (one edit object or a list of them), a dict, a list of dicts, or edit objects;
    each is checked (see ``edit_from_dict``), and anything else is one OmniscsError."""
    value = text_or_list
    if isinstance(value, (str, bytes, bytearray)):
        value = loads_json(value, "the edit list", 'give one edit object or a list of them, e.g. '
                                                   '[{"op": "remove", "track_id": 3}]')
    if isinstance(value, (dict, *_OPS.values())):
        value = [value]
    if not isinstance(value, (list, tuple)):
        raise OmniscsError(f"edits must be one edit object with an 'op' field, or a list of them (e.g. "
                           f'[{{"op": "remove", "track_id": 3}}]); got {_short(value)}')
    return [check_edit(e, i) if isinstance(e, tuple(_OPS.values())) else edit_from_dict(e, i)
            for i, e in enumerate(value)]


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


def resized_poses(poses: np.ndarray, old_size, new_size) -> np.ndarray:  # [F, 4, 4] -> [F, 4, 4]
    """Box poses moved along their own up axis so a box of ``new_size`` rests where one of ``old_size`` stood."""
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, 3] += out[:, :3, 2] * 0.5 * (float(new_size[2]) - float(old_size[2]))
    return out


def resting_tilt(size: np.ndarray, roll_deg: float, pitch_deg: float) -> tuple[np.ndarray, float]:  # R [3, 3], dz
    """Local tilt (roll about x, then pitch about y) plus the vertical shift that keeps the tilted box
    resting on the ground that the upright box stood on (roll 180: no shift; roll 90: z - h/2 + w/2)."""
    R = rotmat_from_euler(np.radians(roll_deg), np.radians(pitch_deg), 0.0)
    half_up = 0.5 * float(np.abs(R[2]) @ np.asarray(size, dtype=np.float64))
    return R, half_up - 0.5 * float(size[2])
