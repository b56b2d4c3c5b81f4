"""The placement checks of appearance-level SCS (``omniscs.scs.appearance.placement``: on the road, no overlap, seen
by a camera) run on an agent the viewer moved, against the edited scene: the other agent nodes where the edits put
them (removed ones gone), the tracks left in the background and the ego where they were logged."""
from __future__ import annotations

import dataclasses

import numpy as np

from omniscs.geometry import yaw_from_matrix
from omniscs.nsg.graph import SceneGraph
from omniscs.scs.appearance.placement.checks import PlacementCheck, check_placement
from omniscs.scs.appearance.placement.config import PlacementConfig
from omniscs.scs.appearance.placement.context import Obstacles, PlacementContext, placement_context


class LivePlacement:
    """The checks of one log, gathered once (``placement_context``: its road, ground, cameras and boxes), run on
    any agent of an edited graph of that log."""

    def __init__(self, scene, config: PlacementConfig = PlacementConfig()) -> None:
        self.logged = placement_context(scene)
        self.config = config

    def context(self, graph: SceneGraph, track_id: int, removed=()) -> PlacementContext:
        """The log's context with the obstacles of the edited ``graph``: every agent node but ``track_id`` at its
        edited poses in place of its logged boxes; ``removed`` (tracks the edits took out) gone."""
        replaced = set(graph.agent_ids) | {int(t) for t in removed} | {int(track_id)}
        kept = self.logged.obstacles.without(sorted(replaced))
        parts = [(kept.frame_idx, kept.track_id, kept.centre, kept.size, kept.yaw)]
        for a in graph.agents:
            if a.track_id == int(track_id):
                continue
            frames = np.flatnonzero(a.present)
            poses = a.world_from_agent[frames]
            parts.append((frames, np.full(len(frames), a.track_id), poses[:, :3, 3], np.tile(a.size, (len(frames), 1)),
                          yaw_from_matrix(poses[:, :3, :3])))
        obstacles = Obstacles.from_arrays(*(np.concatenate([p[i] for p in parts]) for i in range(5)))
        return dataclasses.replace(self.logged, obstacles=obstacles)

    def check(self, graph: SceneGraph, track_id: int, removed=()) -> PlacementCheck:
        """The checks on agent ``track_id`` of ``graph`` over the frames it is present in, at its box centres and
        headings (``removed``: tracks the edits took out, no longer obstacles)."""
        agent = graph.agent(track_id)
        frames = np.flatnonzero(agent.present)
        poses = agent.world_from_agent[frames]
        xyz_yaw = np.concatenate([poses[:, :3, 3], yaw_from_matrix(poses[:, :3, :3])[:, None]], 1)  # [T, 4]
        return check_placement(self.context(graph, track_id, removed), agent.size, xyz_yaw, self.config,
                               frames=frames)
