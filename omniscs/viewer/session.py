"""The edits made in one viewer session, kept as the edit spec they amount to (``omniscs.edits``), and the scene
graph that spec gives through the edit machinery every command uses (``omniscs.nsg.edit.apply_graph_edits``).

A gizmo drag puts an agent at a new world pose at the current frame; since a pose edit right-multiplies one local
motion onto every pose of the agent, that drag is the motion ``inv(T_now) @ T_new`` in the agent's own frame, applied
at every frame. The moves of one agent compose into one motion, written as a ``translate`` followed by a ``rotate``
(the rotate turns the agent about its moved centre), so a session of many drags saves a short spec. Amounts are
rounded (``TRANSLATE_DECIMALS``, ``ROTATE_DECIMALS``) and the session's graph is always the one its saved spec gives,
so what the viewer shows is what ``omniscs render --edit @spec.json`` renders."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from omniscs.edits import Edit, Remove, Rotate, Translate, edit_to_dict, local_motion, parse_edits
from omniscs.errors import OmniscsError
from omniscs.geometry import euler_from_rotmat, invert_transform, is_rigid
from omniscs.nsg.edit import apply_graph_edits
from omniscs.nsg.graph import SceneGraph
from omniscs.storage import atomic_write_text, check_output

#: Decimals kept of a saved translation (metres: 0.1 mm) ...
TRANSLATE_DECIMALS = 4
#: ... and of a saved rotation (degrees).
ROTATE_DECIMALS = 3


class EditSession:
    """Moves and removals of a graph's agents; ``edits`` is their spec, ``graph`` the graph it gives."""

    def __init__(self, graph: SceneGraph) -> None:
        self.base = graph
        self._motions: dict[int, tuple[Translate, Rotate]] = {}  # track id -> its composed move, by first move
        self._removed: list[int] = []                            # in the order they were removed
        self._graph = graph

    @property
    def graph(self) -> SceneGraph:
        """The base graph with ``edits()`` applied."""
        return self._graph

    def edits(self) -> list[Edit]:
        """The session as an edit list: each moved agent's translate then rotate (zero amounts left out), then the
        removals. Edits of different agents commute, so this order changes nothing but readability."""
        out: list[Edit] = []
        for translate, rotate in self._motions.values():
            if (translate.longitudinal, translate.lateral, translate.vertical) != (0.0, 0.0, 0.0):
                out.append(translate)
            if (rotate.yaw_deg, rotate.pitch_deg, rotate.roll_deg) != (0.0, 0.0, 0.0):
                out.append(rotate)
        return out + [Remove(tid) for tid in self._removed]

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
        previous = self._motions.get(tid, (Translate(tid), Rotate(tid)))
        total = local_motion(previous[0]) @ local_motion(previous[1]) @ step
        roll, pitch, yaw = np.degrees(euler_from_rotmat(total[:3, :3]))
        x, y, z = (round(float(v), TRANSLATE_DECIMALS) + 0.0 for v in total[:3, 3])  # + 0.0: no "-0.0" in a spec
        translate, rotate = parse_edits([Translate(tid, x, y, z), Rotate(tid, *(round(float(v), ROTATE_DECIMALS) + 0.0
                                                                                   for v in (yaw, pitch, roll)))])
        return self._commit({**self._motions, tid: (translate, rotate)}, self._removed)

    def remove(self, track_id: int) -> SceneGraph:
        """Take agent ``track_id`` out of every frame (its moves go with it)."""
        tid = int(track_id)
        self._graph.agent(tid)
        motions = {k: v for k, v in self._motions.items() if k != tid}
        return self._commit(motions, [*self._removed, tid])

    def reset(self, track_id: int) -> SceneGraph:
        """Undo every edit of agent ``track_id`` (moves and removal)."""
        tid = int(track_id)
        return self._commit({k: v for k, v in self._motions.items() if k != tid},
                            [t for t in self._removed if t != tid])

    def _commit(self, motions: dict, removed: list[int]) -> SceneGraph:
        old = (self._motions, self._removed)
        self._motions, self._removed = motions, removed
        try:
            self._graph = apply_graph_edits(self.base, self.edits())
        except BaseException:
            self._motions, self._removed = old
            raise
        return self._graph

    def save(self, path: str | Path) -> Path:
        """Write the spec as a JSON list that ``omniscs render --edit @path`` (and fit, generate, scs appearance)
        reads; written atomically."""
        path = check_output(path, what="the edit spec")
        if path.suffix.lower() != ".json":
            raise OmniscsError(f"an edit spec is a .json file; got {path}")
        if path.is_dir():
            raise OmniscsError(f"{path} is a folder; give a file name ending in .json")
        return atomic_write_text(path, json.dumps(self.spec(), indent=2) + "\n")
