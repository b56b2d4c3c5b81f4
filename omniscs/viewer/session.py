"""The edits made in one viewer session, kept as the edit spec they amount to (``omniscs.edits``), and the scene
graph that spec gives through the edit machinery every command uses (``omniscs.nsg.edit.apply_graph_edits``).

A gizmo drag puts an agent at a new world pose at the current frame; since a pose edit right-multiplies one local
motion onto every pose of the agent, that drag is the motion ``inv(T_now) @ T_new`` in the agent's own frame, applied
at every frame. The moves of one agent compose into one motion, written as a ``translate`` followed by a ``rotate``
(the rotate turns the agent about its moved centre), so a session of many drags saves a short spec. Amounts are
rounded (``TRANSLATE_DECIMALS``, ``ROTATE_DECIMALS``) and the session's graph is always the one its saved spec gives,
so what the viewer shows is what ``omniscs render --edit @spec.json`` renders.

An agent can also get another model (``replace_model``, scaled to its box) and new agents can be inserted from a model
(``insert``, standing at a ground point, upright or tilted); an inserted agent is then moved like any other, its
moves written after its insert."""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from omniscs.edits import (Edit, Insert, Remove, ReplaceModel, Rotate, SetTrajectory, Translate, edit_to_dict,
                           local_motion, parse_edits)
from omniscs.errors import OmniscsError
from omniscs.geometry import euler_from_rotmat, invert_transform, is_rigid
from omniscs.nsg.edit import ModelResolver, apply_graph_edits, node_model_resolver
from omniscs.nsg.graph import SceneGraph
from omniscs.storage import atomic_write_text, check_output

#: Decimals kept of a saved translation (metres: 0.1 mm) ...
TRANSLATE_DECIMALS = 4
#: ... and of a saved rotation (degrees).
ROTATE_DECIMALS = 3


@dataclass(frozen=True)
class TrackEdits:
    """Everything the session did to one track, in the order the spec applies it."""

    track_id: int
    insert: Insert | None = None          # the track is new: made from a model at a pose
    replace: ReplaceModel | None = None   # its model swapped (an inserted track changes its insert instead)
    trajectory: SetTrajectory | None = None  # a path drawn for it (an inserted track's insert takes the waypoints)
    translate: Translate | None = None    # its composed moves since: translate, then rotate about the moved centre
    rotate: Rotate | None = None

    def edits(self) -> list[Edit]:
        out: list[Edit] = [e for e in (self.insert, self.replace, self.trajectory) if e is not None]
        if self.translate is not None and (self.translate.longitudinal, self.translate.lateral,
                                           self.translate.vertical) != (0.0, 0.0, 0.0):
            out.append(self.translate)
        if self.rotate is not None and (self.rotate.yaw_deg, self.rotate.pitch_deg,
                                        self.rotate.roll_deg) != (0.0, 0.0, 0.0):
            out.append(self.rotate)
        return out


class EditSession:
    """Edits of a graph's agents made in the viewer; ``edits`` is their spec, ``graph`` the graph it gives.
    ``resolve`` turns model ids into models (``omniscs.agents.pool.model_resolver`` for a pool's ``pm-...``; by
    default the graph's own ``nsg:<track>`` nodes); ``reserved_ids`` are track ids an inserted agent may not take
    (the log's tracks left in the background)."""

    def __init__(self, graph: SceneGraph, resolve: ModelResolver | None = None, reserved_ids=(),
                 prefix=()) -> None:
        self.base = graph
        self.resolve = resolve or node_model_resolver(graph)
        self.reserved_ids = frozenset(int(t) for t in reserved_ids)
        self.prefix: list[Edit] = parse_edits(list(prefix))  # edits made before the session (a variant's)
        self._tracks: dict[int, TrackEdits] = {}  # by the track's first edit
        self._removed: list[int] = []             # logged agents removed, in the order they were removed
        self._graph = apply_graph_edits(graph, self.prefix, self.resolve) if self.prefix else graph

    @property
    def graph(self) -> SceneGraph:
        """The base graph with ``edits()`` applied."""
        return self._graph

    def edits(self) -> list[Edit]:
        """The session as an edit list: the ``prefix`` (a variant's edits), then per track its insert, model
        replacement, path, translate and rotate (zero amounts left out), then the removals. Edits of different
        tracks commute, so the order across tracks changes nothing but readability."""
        return [*self.prefix, *(e for t in self._tracks.values() for e in t.edits()),
                *(Remove(tid) for tid in self._removed)]

    def spec(self) -> list[dict]:
        """``edits()`` in their JSON form (what ``save`` writes)."""
        return [edit_to_dict(e) for e in self.edits()]

    @property
    def removed(self) -> tuple[int, ...]:
        """Tracks removed in this session, in the order they were removed."""
        return tuple(self._removed)

    def editable(self, track_id: int) -> bool:
        return int(track_id) in self._graph.agent_ids

    def move(self, track_id: int, frame: int,
             world_from_box: np.ndarray,  # [4, 4] the agent's new pose at ``frame`` (a gizmo's pose)
             ) -> SceneGraph:
        """Put agent ``track_id`` at ``world_from_box`` at ``frame`` (and so move its whole trajectory by the same
        motion in its own frame); returns the new graph. An agent not in the graph, a pose that is not rigid or a move
        beyond the edit bounds is one OmniscsError, and the session stays as it was."""
        tid = int(track_id)
        f = self._graph.check_frame(frame)
        node = self._graph.agent(tid)  # raises for a removed or unknown agent
        target = np.asarray(world_from_box, dtype=np.float64)
        if target.shape != (4, 4) or not np.all(np.isfinite(target)) or not is_rigid(target, tol=1e-5):
            raise OmniscsError(f"the new pose of agent {tid} must be a finite rigid 4x4 transform")
        step = invert_transform(node.world_from_agent[f]) @ target  # agent_from_moved_agent
        track = self._tracks.get(tid, TrackEdits(tid))
        total = local_motion(track.translate or Translate(tid)) @ local_motion(track.rotate or Rotate(tid)) @ step
        roll, pitch, yaw = np.degrees(euler_from_rotmat(total[:3, :3]))
        x, y, z = (round(float(v), TRANSLATE_DECIMALS) + 0.0 for v in total[:3, 3])  # + 0.0: no "-0.0" in a spec
        translate, rotate = parse_edits([Translate(tid, x, y, z), Rotate(tid, *(round(float(v), ROTATE_DECIMALS) + 0.0
                                                                                   for v in (yaw, pitch, roll)))])
        return self._commit({**self._tracks, tid: replace(track, translate=translate, rotate=rotate)}, self._removed)

    def replace_model(self, track_id: int, asset_id: str) -> SceneGraph:
        """Give agent ``track_id`` the model ``asset_id``, scaled to its box; its motion is kept."""
        tid = int(track_id)
        self._graph.agent(tid)
        track = self._tracks.get(tid, TrackEdits(tid))
        if track.insert is not None:
            track = replace(track, insert=replace(track.insert, asset_id=asset_id))
        else:
            track = replace(track, replace=ReplaceModel(tid, asset_id))
        return self._commit({**self._tracks, tid: track}, self._removed)

    def insert(self, asset_id: str, category: str, x: float, y: float, ground_z: float, yaw: float = 0.0,
               roll_deg: float = 0.0) -> int:
        """A new agent from model ``asset_id`` at its own size, standing on the ground (``ground_z``, metres) at
        (x, y) with heading ``yaw`` (radians), tilted by ``roll_deg`` (90: on its side, 180: overturned) and resting
        on the ground; present in every frame. Returns its track id (the next one free of the graph's nodes, the
        session's inserts and ``reserved_ids``)."""
        model = self.resolve(asset_id)
        size = np.asarray(model.size, dtype=np.float64)
        taken = set(self.base.agent_ids) | set(self._graph.agent_ids) | set(self._tracks) | set(self.reserved_ids)
        tid = max(taken, default=0) + 1
        pose = (round(float(x), TRANSLATE_DECIMALS), round(float(y), TRANSLATE_DECIMALS),
                round(float(ground_z) + 0.5 * float(size[2]), TRANSLATE_DECIMALS), round(float(yaw), 6))
        insert = parse_edits([Insert(tid, asset_id, category, pose=pose, roll_deg=float(roll_deg))])[0]
        self._commit({**self._tracks, tid: TrackEdits(tid, insert=insert)}, self._removed)
        return tid

    def set_path(self, track_id: int, waypoints) -> SceneGraph:
        """Give agent ``track_id`` a new path: one (x, y, z, yaw) per frame or None where absent
        (``omniscs.viewer.paths.path_waypoints``). Its earlier moves are part of the path, so they are dropped; a
        tilted agent (on its side, overturned) cannot take a path, which is upright."""
        from omniscs.viewer.paths import is_upright

        tid = int(track_id)
        node = self._graph.agent(tid)
        if not is_upright(node.world_from_agent, node.present):
            raise OmniscsError(f"agent {tid} is tilted (on its side or overturned); a drawn path is upright: move it "
                               "with its gizmo instead")
        rounded = tuple(None if w is None else (round(w[0], TRANSLATE_DECIMALS) + 0.0,
                                                round(w[1], TRANSLATE_DECIMALS) + 0.0,
                                                round(w[2], TRANSLATE_DECIMALS) + 0.0, round(w[3], 6) + 0.0)
                        for w in waypoints)
        track = self._tracks.get(tid, TrackEdits(tid))
        if track.insert is not None:
            insert = parse_edits([replace(track.insert, pose=None, waypoints=rounded)])[0]
            track = TrackEdits(tid, insert=insert)
        else:
            trajectory = parse_edits([SetTrajectory(tid, rounded)])[0]
            track = TrackEdits(tid, replace=track.replace, trajectory=trajectory)
        return self._commit({**self._tracks, tid: track}, self._removed)

    def remove(self, track_id: int) -> SceneGraph:
        """Take agent ``track_id`` out of every frame (its other edits go with it; an inserted agent is simply
        not inserted)."""
        tid = int(track_id)
        self._graph.agent(tid)
        inserted = tid in self._tracks and self._tracks[tid].insert is not None
        tracks = {k: v for k, v in self._tracks.items() if k != tid}
        return self._commit(tracks, self._removed if inserted else [*self._removed, tid])

    def reset(self, track_id: int) -> SceneGraph:
        """Undo every edit of agent ``track_id`` (moves, model, removal; an inserted agent keeps its insert)."""
        tid = int(track_id)
        track = self._tracks.get(tid)
        tracks = {k: v for k, v in self._tracks.items() if k != tid}
        if track is not None and track.insert is not None:
            tracks[tid] = TrackEdits(tid, insert=track.insert)
        return self._commit(tracks, [t for t in self._removed if t != tid])

    def _commit(self, tracks: dict[int, TrackEdits], removed: list[int]) -> SceneGraph:
        old = (self._tracks, self._removed)
        self._tracks, self._removed = tracks, removed
        try:
            self._graph = apply_graph_edits(self.base, self.edits(), self.resolve)
        except BaseException:
            self._tracks, self._removed = old
            raise
        return self._graph

    def save(self, path: str | Path) -> Path:
        """Write the spec as a JSON list that ``omniscs render --edit @path`` (and fit, generate, scs appearance)
        reads (with ``--pool`` when it names pool models); written atomically."""
        path = check_output(path, what="the edit spec")
        if path.suffix.lower() != ".json":
            raise OmniscsError(f"an edit spec is a .json file; got {path}")
        if path.is_dir():
            raise OmniscsError(f"{path} is a folder; give a file name ending in .json")
        return atomic_write_text(path, json.dumps(self.spec(), indent=2) + "\n")
