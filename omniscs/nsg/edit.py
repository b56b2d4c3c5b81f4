"""Edits of a fitted scene graph: the same edit specs as the ground-truth world, applied as values (never in place)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from omniscs.edits import Insert, Remove, ReplaceModel, Rotate, SetTrajectory, Translate, local_motion, parse_edits, \
    poses_from_waypoints, resized_poses, resting_tilt
from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams, with_sh_degree
from omniscs.geometry import make_transform
from omniscs.nsg.agent import AgentNode
from omniscs.nsg.graph import SceneGraph
from omniscs.quaternions import normalize_quats, quat_to_rotmat, rotmat_to_quat
from omniscs.taxonomy import CATEGORIES

#: Prefix of asset ids that name a fitted agent node: ``nsg:<track_id>`` (this graph) or
#: ``nsg:<track_id>@<checkpoint folder>`` (another fit). The model pool of later stages adds other sources.
NODE_ASSET_PREFIX = "nsg:"


@dataclass(frozen=True)
class AgentModel:
    """An agent appearance that can be put in a box: local Gaussians fitted to a box of ``size``."""

    gaussians: GaussianParams  # agent frame
    size: np.ndarray           # [3] the box it was fitted in
    category: str


ModelResolver = Callable[[str], AgentModel]


def node_model_resolver(graph: SceneGraph) -> ModelResolver:
    """Resolve ``nsg:<track_id>`` in ``graph`` and ``nsg:<track_id>@<ckpt>`` in another checkpoint."""
    def resolve(asset_id: str) -> AgentModel:
        if not asset_id.startswith(NODE_ASSET_PREFIX):
            raise OmniscsError(f"asset {asset_id!r} is not a fitted agent node: name one as {NODE_ASSET_PREFIX}<track_id> "
                               f"or {NODE_ASSET_PREFIX}<track_id>@<checkpoint>, or a pool model (pm-...) with a pool")
        ref = asset_id[len(NODE_ASSET_PREFIX):]
        track, _, ckpt = ref.partition("@")
        try:
            track_id = int(track)
        except ValueError:
            raise OmniscsError(f"asset {asset_id!r}: {track!r} is not a track id") from None
        source = graph
        if ckpt:
            from omniscs.nsg.checkpoint import load_graph
            source = load_graph(Path(ckpt), device=graph.device)
        node = source.agent(track_id)
        return AgentModel(node.gaussians, np.array(node.size), node.category)
    return resolve


def scale_to_box(gaussians: GaussianParams, from_size: np.ndarray, to_size: np.ndarray) -> GaussianParams:
    """Stretch local Gaussians fitted in a box of ``from_size`` to fill ``to_size``, exactly: means scale per
    axis and each covariance becomes D Σ D (re-factored into a rotation and scales)."""
    D = np.asarray(to_size, dtype=np.float64) / np.asarray(from_size, dtype=np.float64)
    if not np.all(np.isfinite(D)) or np.any(D <= 0):
        raise OmniscsError(f"cannot scale a model of size {from_size} to a box of size {to_size}")
    if np.allclose(D, 1.0) or len(gaussians) == 0:
        return gaussians
    R = quat_to_rotmat(normalize_quats(gaussians.quats.detach().double().cpu().numpy()))  # [N, 3, 3]
    s2 = np.exp(2.0 * gaussians.log_scales.detach().double().cpu().numpy())
    cov = np.einsum("nij,nj,nkj->nik", R, s2, R)
    cov = D[None, :, None] * cov * D[None, None, :]
    eigval, eigvec = np.linalg.eigh(cov)
    flip = np.linalg.det(eigvec) < 0
    eigvec[flip, :, 0] *= -1.0                                 # a proper rotation
    on = dict(device=gaussians.means.device, dtype=gaussians.means.dtype)  # the covariance algebra ran on the host
    return GaussianParams(
        means=gaussians.means * torch.from_numpy(D).to(**on),
        quats=torch.from_numpy(rotmat_to_quat(eigvec)).to(**on),
        log_scales=torch.from_numpy(0.5 * np.log(np.maximum(eigval, 1e-300))).to(**on),
        opacity_logits=gaussians.opacity_logits, sh_dc=gaussians.sh_dc, sh_rest=gaussians.sh_rest)


def apply_graph_edits(graph: SceneGraph, edits, resolve: ModelResolver | None = None) -> SceneGraph:
    """A new graph with ``edits`` (edit objects, dicts or JSON) applied in order; ``graph`` is not changed.

    Translate/Rotate right-multiply their local motion onto every pose of the node (as in the world);
    Remove drops the node; ReplaceModel puts another model's Gaussians, scaled to this box, under this
    node's motion; SetTrajectory replaces poses and presence; Insert adds a node with its own poses.
    """
    resolve = resolve or node_model_resolver(graph)
    nodes = {a.track_id: a for a in graph.agents}
    for edit in parse_edits(edits):
        tid = int(edit.track_id)
        if isinstance(edit, Insert):
            if tid in nodes:
                raise OmniscsError(f"cannot insert track {tid}: the scene graph already has a node with that id")
            nodes[tid] = _inserted_node(graph, edit, resolve)
            continue
        if tid not in nodes:
            graph.agent(tid)  # raises the explanatory error
        node = nodes[tid]
        if isinstance(edit, (Translate, Rotate)):
            amounts = [edit.longitudinal, edit.lateral, edit.vertical] if isinstance(edit, Translate) \
                else [edit.yaw_deg, edit.pitch_deg, edit.roll_deg]
            if not np.all(np.isfinite(np.asarray(amounts, dtype=np.float64))):
                raise OmniscsError(f"{edit.op} amounts must be finite numbers; got {amounts}")
            nodes[tid] = node.with_changes(world_from_agent=node.world_from_agent @ local_motion(edit))
        elif isinstance(edit, Remove):
            del nodes[tid]
        elif isinstance(edit, ReplaceModel):
            model = resolve(edit.asset_id)
            size = np.array(node.size, dtype=np.float64) if edit.size is None else np.asarray(edit.size, np.float64)
            gaussians = scale_to_box(with_sh_degree(model.gaussians, graph.sh_degree).to(graph.device), model.size,
                                     size)
            nodes[tid] = node.with_changes(gaussians=gaussians, category=model.category, size=size,
                                           world_from_agent=resized_poses(node.world_from_agent, node.size, size))
        elif isinstance(edit, SetTrajectory):
            poses, present = poses_from_waypoints(edit.waypoints, graph.n_frames)
            poses[~present] = node.world_from_agent[~present]
            nodes[tid] = node.with_changes(world_from_agent=poses, present=present)
        else:
            raise OmniscsError(f"unsupported edit {edit!r}")
    return graph.replace(agents=tuple(nodes.values()))


def _inserted_node(graph: SceneGraph, edit: Insert, resolve: ModelResolver) -> AgentNode:
    if edit.track_id < 0:
        raise OmniscsError(f"inserted track id must be a non-negative integer; got {edit.track_id!r}")
    if edit.category not in CATEGORIES:
        raise OmniscsError(f"unknown category {edit.category!r} for inserted track; use one of {list(CATEGORIES)}")
    model = resolve(edit.asset_id)
    size = np.array(model.size) if edit.size is None else np.asarray(edit.size, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise OmniscsError(f"inserted box size must be 3 positive numbers (length, width, height); got {edit.size!r}")
    if (edit.pose is None) == (edit.waypoints is None):
        raise OmniscsError("an insert needs exactly one of 'pose' (x, y, z, yaw) or 'waypoints' (one per frame)")
    if edit.pose is not None and len(edit.pose) != 4:
        raise OmniscsError(f"insert pose must be (x, y, z, yaw); got {edit.pose!r}")
    waypoints = [tuple(edit.pose)] * graph.n_frames if edit.pose is not None else edit.waypoints
    poses, present = poses_from_waypoints(waypoints, graph.n_frames)
    R, lift = resting_tilt(size, edit.roll_deg, edit.pitch_deg)  # the same resting rule as the ground-truth world
    poses = poses @ make_transform(R, np.zeros(3))
    poses[:, 2, 3] += lift
    return AgentNode(int(edit.track_id), edit.category, size, poses, present,
                     scale_to_box(with_sh_degree(model.gaussians, graph.sh_degree).to(graph.device), model.size, size))
