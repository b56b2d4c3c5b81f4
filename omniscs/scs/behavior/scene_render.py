"""The scene graph as L_app's differentiable renderer: agents placed on (perturbed) trajectories, rendered.

``GraphTrajectoryRenderer`` turns the optimiser's world-frame trajectories (x, y, yaw per step, with
gradients) into images of the fitted Gaussian scene graph: every agent node named in the trajectories is
placed upright at its trajectory pose (height from the log) by Eq. 1 and the frame is rasterised with the
differentiable rasterizer, so gradients reach the trajectories and from there the latents. Tracks that the
scene's plan left in the background cannot move in the render (they are part of the background Gaussians);
``make_plan(..., behavior_variants=N)`` makes every vehicle a node so that this does not happen.

Cost control (every optimisation step renders): a few steps spread over the horizon, one camera, a downscaled
image (``RenderConsistencyConfig``; the benchmark reports the time per variant it costs), and the background
prepared once per rendered view (``nsg.graph.static_layer``: activated, coloured and culled to what the view
shows) and the agents' Gaussians activated once, so each step only places (all together), colours and projects
the agent nodes on top of it, and only those whose bounding sphere where they are placed may reach the image
(``nsg.graph.agent_may_show``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import OmniscsError
from omniscs.gaussians import activate
from omniscs.nsg.checkpoint import load_graph
from omniscs.nsg.compose import NodePose
from omniscs.nsg.graph import SceneGraph, agent_key, agent_may_show, node_radius, render_view, static_layer
from omniscs.scs.behavior.adversarial_config import AdversarialConfig
from omniscs.scs.behavior.checkpoint import load_traffic_model as load_model
from omniscs.scs.behavior.render_consistency import (AgentTrajectories, FeatureNetConfig, RenderConsistencyTerm,
                                                    build_feature_net, variant_ego_poses)
from omniscs.scs.behavior.model import TrafficModel
from omniscs.scs.behavior.problem import now_and_horizon
from omniscs.scs.behavior.tracks import TrafficScene


@dataclass(frozen=True)
class RenderConsistencyConfig:
    """What L_app renders at every optimisation step (its cost is linear in frames x pixels)."""

    camera: str | None = None
    """Camera rendered; None = the graph's first camera (the front camera of the rigs here)."""
    frames: int = 3
    """Horizon steps rendered, spread evenly from the first to the last step of the horizon."""
    downscale: int = 4
    """Images are rendered at 1/downscale of the camera's resolution."""
    weight: float = 1.0
    """Scale of L_app inside the term (AdversarialConfig.app_weight multiplies on top)."""
    feature_net: FeatureNetConfig = FeatureNetConfig()
    """The feature net F (fixed random init unless a user's local weights are named)."""


def placed_agents(graph: SceneGraph, frame: int, xy_yaw: dict[int, Tensor]) -> dict[int, NodePose]:
    """Upright poses (heights as logged) for the tracks of ``xy_yaw`` ({track id: [3] x, y, yaw}) that are agent
    nodes present in ``frame``; the others are left out (background tracks cannot move in the render)."""
    out = {}
    for tid, pose in xy_yaw.items():
        if tid in graph.agent_ids and graph.agent(tid).present[frame]:
            x, y, yaw = pose.unbind(-1)
            out[tid] = NodePose.from_xy_yaw(x, y, yaw, float(graph.agent(tid).world_from_agent[frame, 2, 3]))
    return out


class GraphTrajectoryRenderer:
    """``render(trajectories) -> [T', 3, H, W]`` for the steps it was built for (a Renderer of L_app)."""

    def __init__(self, graph: SceneGraph, source_frames: np.ndarray | None,  # [S] scene frame of each log step
                 horizon_steps: np.ndarray,  # [T] log steps of the optimised horizon
                 config: RenderConsistencyConfig = RenderConsistencyConfig()) -> None:
        if source_frames is None:
            raise OmniscsError("L_app needs the traffic on the scene's own frames (this log was resampled to the "
                               "model's time step, so its steps have no rendered frame)")
        if config.frames < 1 or config.downscale < 1:
            raise OmniscsError("render-consistency rendering needs frames >= 1 and downscale >= 1")
        self.graph = graph.replace(background=graph.background.detached(),
                                   agents=tuple(a.with_changes(gaussians=a.gaussians.detached(), relight=a.relight)
                                                for a in graph.agents))
        self.camera = config.camera or graph.cameras[0].name
        graph.camera(self.camera)
        horizon_steps = np.asarray(horizon_steps, dtype=np.int64)
        pick = np.unique(np.round(np.linspace(0, len(horizon_steps) - 1, config.frames)).astype(np.int64))
        self.positions = pick  # indices into the trajectories' T axis
        self.steps = horizon_steps[pick]
        self.frames = np.asarray(source_frames, dtype=np.int64)[self.steps]
        if np.any(self.frames < 0) or np.any(self.frames >= graph.n_frames):
            raise OmniscsError(f"frames {self.frames.tolist()} are outside the scene graph's {graph.n_frames} frames")
        self.views = [graph.view(self.camera, int(f)).downscaled(config.downscale) for f in self.frames]
        # the background never moves: activate, colour and cull it once per view (same images, less work per step)
        self.static = [static_layer(self.graph, v) for v in self.views]
        # and agent nodes whose bounding sphere, where they are placed, misses the view are left out of that step
        self.radii = {a.track_id: node_radius(a.gaussians) for a in self.graph.agents}
        # the agents' Gaussians never change either: activated once, not at every render
        self.activated = {agent_key(a.track_id): activate(a.gaussians) for a in self.graph.agents}

    def poses(self, trajectories: AgentTrajectories, position: int, frame: int) -> dict[int, NodePose]:
        """Differentiable poses of the agent nodes present in ``frame``; heights as logged."""
        return placed_agents(self.graph, frame, {tid: trajectories.poses[i, position]
                                                 for i, tid in enumerate(trajectories.track_ids)})

    def __call__(self, trajectories: AgentTrajectories) -> Tensor:  # [T', 3, H, W] in [0, 1]
        images = []
        for position, frame, view, static in zip(self.positions, self.frames, self.views, self.static):
            poses = self.poses(trajectories, int(position), int(frame))
            out = render_view(self.graph, view, agent_poses=poses, static=static,
                              only_agents=self.showing(view, poses), activated=self.activated)
            images.append(out.rgb.clamp(0.0, 1.0).permute(2, 0, 1))
        return torch.stack(images)

    def showing(self, view, poses: dict[int, NodePose]) -> list[int]:
        """Agent nodes present in the view's frame whose bounding sphere, at their pose, may reach the image."""
        near = self.graph.settings.near_plane
        out = []
        for a in self.graph.agents:
            if not a.present[view.frame_idx]:
                continue
            pose = poses.get(a.track_id)
            centre = (a.world_from_agent[view.frame_idx, :3, 3] if pose is None
                      else pose.translation.detach().to(torch.float64).numpy())
            if agent_may_show(view, centre, self.radii[a.track_id], near):
                out.append(a.track_id)
        return out

    @torch.no_grad()
    def logged(self) -> Tensor:  # [T', 3, H, W]: the unperturbed graph (every agent on its logged pose)
        return torch.stack([render_view(self.graph, v, static=s).rgb.clamp(0.0, 1.0).permute(2, 0, 1)
                            for v, s in zip(self.views, self.static)])


def scene_graph_render_consistency(graph: SceneGraph, traffic: TrafficScene, model: TrafficModel,
                           adversarial: AdversarialConfig = AdversarialConfig(),
                           config: RenderConsistencyConfig = RenderConsistencyConfig()) -> RenderConsistencyTerm:
    """L_app of one scene: the scene graph's renders of the perturbed trajectories against its renders of
    the log (F(Re(NSG))) over the horizon the optimiser will use, compared in ``config.feature_net``'s features."""
    if graph.scene_id != traffic.scene_id or graph.n_frames != len(traffic.timestamps_us):
        raise OmniscsError(f"scene graph of {graph.scene_id} ({graph.n_frames} frames) does not belong to the "
                           f"traffic of {traffic.scene_id} ({len(traffic.timestamps_us)} steps)")
    now, horizon = now_and_horizon(traffic, model.config, adversarial)
    horizon_steps = np.arange(now + 1, now + 1 + horizon)
    renderer = GraphTrajectoryRenderer(graph, traffic.source_frames, horizon_steps, config)
    return RenderConsistencyTerm(renderer, renderer.logged(), build_feature_net(config.feature_net), config.weight)


def render_consistency_from_checkpoint(nsg_dir: str | Path, scene, traffic: TrafficScene,
                               behavior_checkpoint: str | Path | None = None,
                               adversarial: AdversarialConfig = AdversarialConfig(),
                               config: RenderConsistencyConfig = RenderConsistencyConfig()) -> RenderConsistencyTerm:
    """L_app from a scene-graph checkpoint folder of ``scene`` (refused when it belongs to another scene)."""
    return scene_graph_render_consistency(load_graph(nsg_dir, scene), traffic, load_model(behavior_checkpoint),
                                  adversarial, config)


@torch.no_grad()
def render_variant(graph: SceneGraph, variant: dict, camera: str, frames: list[int]) -> np.ndarray:
    """The scene graph with every agent node on a variant's trajectory (and the ego on its plan) at ``frames``:
    [T, H, W, 3] in [0, 1], full resolution. The counterpart of ``variant_ground_truth`` of the behaviour benchmark."""
    if variant.get("source_frames") is None:
        raise OmniscsError("variant steps are not the scene's frames (the log was resampled); nothing to render")
    step_of = {int(f): k for k, f in enumerate(variant["source_frames"])}
    ego = variant_ego_poses(variant, graph.world_from_ego) if variant.get("ego") is not None else graph.world_from_ego
    images = []
    for f in frames:
        f = graph.check_frame(f)
        k = step_of.get(f)
        xy_yaw = {} if k is None else {int(key): torch.tensor(traj[k], dtype=torch.float64)
                                       for key, traj in variant["agents"].items() if traj[k] is not None}
        out = render_view(graph, graph.view(camera, f, world_from_ego=ego[f]), agent_poses=placed_agents(graph, f, xy_yaw))
        images.append(out.rgb.clamp(0.0, 1.0).numpy().astype(np.float64))
    return np.stack(images)
