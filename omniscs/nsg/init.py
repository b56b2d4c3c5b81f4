"""The scene graph before fitting: nodes from the plan, seeded from LiDAR, box surfaces and camera rays."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from omniscs.gaussians import GaussianParams, concat_params, empty_params, params_from_values
from omniscs.geometry import transform_points
from omniscs.nsg.agent import (AgentNode, box_surface_points, init_agent_gaussians, points_in_agent_box,
                               track_poses)
from omniscs.nsg.backdrop import identity_exposure
from omniscs.nsg.background import init_background, voxel_subsample
from omniscs.nsg.config import FitConfig
from omniscs.nsg.graph import SceneGraph
from omniscs.nsg.observations import Observations
from omniscs.nsg.sky import init_sky
from omniscs.plan import ScenePlan
from omniscs.scene.store import Scene

log = logging.getLogger(__name__)

#: An agent with fewer in-box LiDAR returns than this is also seeded on its box surface.
MIN_AGENT_LIDAR_SEEDS = 30

#: Smallest share of the budget the background keeps, however many agent nodes there are.
MIN_BACKGROUND_BUDGET = 1_000

#: Image rows (from the top, as a fraction of height) whose mean colour starts the sky texture.
SKY_INIT_ROWS = 0.05

#: A ray seed starts about this many pixels wide at its depth.
RAY_SEED_PIXELS = 4.0

#: Agent LiDAR returns are thinned with a voxel this many times smaller than the background's.
AGENT_VOXEL_DIVISOR = 3.0


@dataclass(frozen=True)
class NodeBudgets:
    """How many Gaussians each node may hold (its part of the plan's budget)."""

    background: int
    per_agent: int


def node_budgets(plan: ScenePlan, config: FitConfig) -> NodeBudgets:
    per_agent = config.plan.gaussians_per_agent
    background = max(MIN_BACKGROUND_BUDGET, plan.gaussian_budget - per_agent * len(plan.agent_nodes))
    return NodeBudgets(background, per_agent)


def background_scene_scale(scene: Scene, cameras: tuple[str, ...], min_scale: float = 10.0) -> float:
    """Radius of the camera centres around their mean, x1.1 (3DGS's scene extent), at least ``min_scale`` m."""
    centres = np.array([scene.world_from_camera(c, f)[:3, 3] for f in range(scene.n_frames) for c in cameras])
    return max(min_scale, 1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max()))


def agent_scene_scale(size: np.ndarray) -> float:
    """Half the box diagonal: an agent node's extent."""
    return 0.5 * float(np.linalg.norm(size))


def initial_graph(scene: Scene, plan: ScenePlan, config: FitConfig, obs: Observations) -> SceneGraph:
    """Seed every node of ``plan`` on ``config.device``; only the plan's training frames are looked at.
    Seeds are computed on the host (they come from numpy point clouds) and moved once at the end."""
    rng = np.random.default_rng(config.seed)
    init = config.init
    budgets = node_budgets(plan, config)
    F = scene.n_frames
    agents = {tid: track_poses(scene.boxes, tid, F) for tid in plan.agent_nodes}
    categories = scene.boxes.drop_duplicates("track_id").set_index("track_id")["category"].to_dict()

    bg_points, bg_frames = [], []
    agent_points: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {tid: [] for tid in agents}
    for f in plan.train_frames:
        pts = obs.lidar_world(f)
        if len(pts) == 0:
            continue
        background = np.ones(len(pts), dtype=bool)
        for tid, (poses, present, size) in agents.items():
            if not present[f]:
                continue
            inside, local = points_in_agent_box(pts, poses[f], size, init.agent_box_margin_m,
                                                init.agent_ground_clearance_m)
            background &= ~inside
            if inside.any():
                agent_points[tid].append((local[inside], np.full(int(inside.sum()), f)))
        bg_points.append(pts[background])
        bg_frames.append(np.full(int(background.sum()), f))

    bg_budget = int(budgets.background * config.init_budget_fraction)
    n_rays = int(bg_budget * init.ray_seed_fraction)
    background = _lidar_background(obs, bg_points, bg_frames, bg_budget - n_rays, config, rng)
    rays = _ray_seeds(obs, plan, n_rays, config, rng)
    background = concat_params([p for p in (background, rays) if len(p)]) if len(background) + len(rays) \
        else empty_params(config.sh_degree)

    nodes = []
    for tid, (poses, present, size) in agents.items():
        gaussians = _agent_seeds(obs, plan, agent_points[tid], poses, present, size,
                                 int(budgets.per_agent * config.init_budget_fraction), config, rng)
        nodes.append(AgentNode(int(tid), str(categories.get(tid, "unknown")), size, poses, present, gaussians))

    sky = init_sky(_sky_colour(obs, plan), config.sky_height, config.sky_width)
    exposure = {c: identity_exposure() for c in plan.cameras}
    cameras = tuple(scene.camera(c) for c in plan.cameras)
    graph = SceneGraph(scene.scene_id, scene.content_hash, background, tuple(nodes), sky, exposure, cameras,
                       scene.world_from_ego_all, config.sh_degree, config.render)
    return graph.to(config.torch_device)


def _lidar_background(obs: Observations, points: list[np.ndarray], frames: list[np.ndarray], budget: int,
                      config: FitConfig, rng: np.random.Generator) -> GaussianParams:
    if not points or budget <= 0:
        return empty_params(config.sh_degree)
    pts, fr = np.concatenate(points), np.concatenate(frames)
    # thin to twice the budget first: colouring is the slow part, and unseen points are dropped after it
    keep = voxel_subsample(pts, config.init.voxel_m, 2 * budget, rng)
    pts, fr = pts[keep], fr[keep]
    colours, seen = obs.colour_points(pts, fr)
    pts, colours = pts[seen][:budget], colours[seen][:budget]
    log.info("background: %d LiDAR seeds", len(pts))
    return init_background(pts, colours, config.sh_degree, config.init.opacity, config.init.max_seed_scale_m)


def _ray_seeds(obs: Observations, plan: ScenePlan, n: int, config: FitConfig,
               rng: np.random.Generator) -> GaussianParams:
    """Seeds along random pixel rays of training views, coloured by their pixel, at random inverse depth."""
    if n <= 0 or not plan.train_frames:
        return empty_params(config.sh_degree)
    init = config.init
    views = [(c, f) for f in plan.train_frames for c in plan.cameras]
    pick = rng.integers(len(views), size=n)
    points, colours, depths, fx = np.empty((n, 3)), np.empty((n, 3)), np.empty(n), np.empty(n)
    for v in np.unique(pick):
        cam, f = views[v]
        idx = np.flatnonzero(pick == v)
        view = obs.view(cam, f)
        col = rng.uniform(0, view.width, len(idx))
        row = rng.uniform(0, view.height, len(idx))
        depth = 1.0 / rng.uniform(1.0 / init.ray_seed_far_m, 1.0 / init.ray_seed_near_m, len(idx))
        cam_pts = np.stack([(col - view.K[0, 2]) / view.K[0, 0], (row - view.K[1, 2]) / view.K[1, 1],
                            np.ones_like(col)], -1) * depth[:, None]
        points[idx] = transform_points(view.world_from_camera, cam_pts)
        depths[idx], fx[idx] = depth, view.K[0, 0]
        img = obs.pixels(cam, f)
        colours[idx] = img[np.floor(row).astype(int), np.floor(col).astype(int)]
    # about the footprint of RAY_SEED_PIXELS pixels at the seed's depth
    seed_scale = np.minimum(depths * RAY_SEED_PIXELS / fx, config.init.max_seed_scale_m)
    return params_from_values(torch.from_numpy(points), torch.from_numpy(seed_scale)[:, None].expand(n, 3),
                              torch.full((n,), config.init.opacity), torch.from_numpy(colours), config.sh_degree)


def _agent_seeds(obs: Observations, plan: ScenePlan, hits: list[tuple[np.ndarray, np.ndarray]],
                 poses: np.ndarray, present: np.ndarray, size: np.ndarray, budget: int, config: FitConfig,
                 rng: np.random.Generator) -> GaussianParams:
    """In-box LiDAR returns in the agent frame, coloured in the frame they were captured; box-surface
    seeds (coloured where a camera sees them) when there are too few returns."""
    budget = max(1, budget)
    local = np.concatenate([h[0] for h in hits]) if hits else np.zeros((0, 3))
    frames = np.concatenate([h[1] for h in hits]) if hits else np.zeros(0, dtype=np.int64)
    if len(local):
        keep = voxel_subsample(local, config.init.voxel_m / AGENT_VOXEL_DIVISOR, budget, rng)
        local, frames = local[keep], frames[keep]
    if len(local) < MIN_AGENT_LIDAR_SEEDS:
        train_present = [f for f in plan.train_frames if present[f]] or list(np.flatnonzero(present))
        n = min(config.init.agent_surface_seeds, budget)
        surface = box_surface_points(size, n, rng)
        local = np.concatenate([local, surface])
        frames = np.concatenate([frames, rng.choice(np.asarray(train_present, dtype=np.int64), size=n)])
    world = np.empty_like(local)
    for f in np.unique(frames):
        sel = frames == f
        world[sel] = transform_points(poses[f], local[sel])
    colours, _ = obs.colour_points(world, frames)
    return init_agent_gaussians(local, colours, size, budget, config.sh_degree, config.init.opacity, rng)


def _sky_colour(obs: Observations, plan: ScenePlan) -> torch.Tensor:  # [3]
    tops = []
    for f in plan.train_frames[:: max(1, len(plan.train_frames) // 4)]:
        for c in plan.cameras:
            img = torch.from_numpy(obs.pixels(c, f))
            tops.append(img[: max(1, int(SKY_INIT_ROWS * img.shape[0]))].reshape(-1, 3))
    if not tops:
        return torch.full((3,), 0.5)
    return torch.cat(tops).mean(0)
