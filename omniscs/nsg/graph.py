"""The scene graph as a value (background, agent and sky nodes, per-camera exposure) and how it is rendered."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Collection, Mapping, NamedTuple

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import OmniscsError
from omniscs.gaussians import Gaussians, GaussianParams, activate
from omniscs.geometry import invert_transform, transform_points
from omniscs.nsg.agent import AgentNode
from omniscs.nsg.backdrop import with_backdrop
from omniscs.nsg.compose import NodePose, place_gaussians, place_many
from omniscs.nsg.observations import View
from omniscs.nsg.prepare import prepare_nodes
from omniscs.nsg.relight import Relight
from omniscs.nsg.sky import SkyParams
from omniscs.render import rasterize
from omniscs.render.sh import colors_from_sh
from omniscs.scene.store import CameraRecord

#: Key of the background node in per-node bookkeeping (slices, optimisers, checkpoints).
BACKGROUND = "background"


def agent_key(track_id: int) -> str:
    return f"agent.{int(track_id)}"


@dataclass(frozen=True)
class RenderSettings:
    """Rasterizer settings a graph is fitted and rendered with (stored in its checkpoint)."""

    near_plane: float = 0.2
    """Gaussians closer to the camera than this (metres) are culled; driving cameras see nothing nearer."""
    far_plane: float = 1e4
    """Gaussians further than this (metres) are culled."""
    eps2d: float = 0.3
    """Screen-space dilation added to every 2D covariance (pixels²), as in 3DGS."""
    rasterize_mode: str = "classic"
    """'classic' or 'antialiased' (Mip-Splatting opacity compensation)."""
    backend: str = "auto"
    """Rasterizer backend: 'auto' (gsplat on CUDA, else the CPU kernels), 'cpu', 'reference' or 'gsplat'."""


@dataclass(frozen=True)
class RenderOutput:
    """One rendered view."""

    rgb: Tensor     # [H, W, 3] after sky and exposure
    depth: Tensor   # [H, W] expected depth (metres along the camera axis; 0 where nothing covers)
    alpha: Tensor   # [H, W] Gaussian coverage (1 - what the sky shows)
    meta: dict[str, Any]          # the rasterizer's meta (means2d [1, N, 2] for densification, radii, ...)
    node_slices: dict[str, slice]  # which of the N rasterised Gaussians belong to which node
    labels: Tensor | None = None   # [H, W, E] blended label channels (``render_view(labels=...)``), else None


@dataclass(frozen=True)
class SceneGraph:
    """A fitted scene graph: never changed in place; edits return a new graph sharing unchanged tensors."""

    scene_id: str
    content_hash: str
    background: GaussianParams         # world frame
    agents: tuple[AgentNode, ...]      # sorted by track id
    sky: SkyParams
    exposure: Mapping[str, Tensor]     # camera -> [3, 4] affine colour correction [A | b]
    cameras: tuple[CameraRecord, ...]  # the logged rig (rendering can use any other camera too)
    world_from_ego: np.ndarray         # [F, 4, 4] float64 logged ego poses
    sh_degree: int
    settings: RenderSettings = field(default_factory=RenderSettings)

    def __post_init__(self) -> None:
        object.__setattr__(self, "exposure", MappingProxyType(dict(self.exposure)))
        object.__setattr__(self, "agents", tuple(sorted(self.agents, key=lambda a: a.track_id)))
        self.world_from_ego.flags.writeable = False
        ids = [a.track_id for a in self.agents]
        if len(set(ids)) != len(ids):
            raise OmniscsError(f"scene graph has duplicate agent track ids {sorted(ids)}")

    # -- lookup ------------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return self.world_from_ego.shape[0]

    @property
    def agent_ids(self) -> tuple[int, ...]:
        return tuple(a.track_id for a in self.agents)

    def agent(self, track_id: int) -> AgentNode:
        for a in self.agents:
            if a.track_id == int(track_id):
                return a
        raise OmniscsError(f"track {track_id} is not an agent node of this scene graph (nodes: {list(self.agent_ids)}); "
                           "tracks left in the background cannot be edited: re-fit with the edit in the plan")

    @property
    def n_gaussians(self) -> int:
        return len(self.background) + sum(len(a.gaussians) for a in self.agents)

    def camera(self, name: str) -> CameraRecord:
        for c in self.cameras:
            if c.name == name:
                return c
        raise OmniscsError(f"unknown camera {name!r}; this scene graph has {[c.name for c in self.cameras]}")

    def replace(self, **changes) -> "SceneGraph":
        return dataclasses.replace(self, **changes)

    @property
    def device(self) -> torch.device:
        """Where the graph's tensors live (and so where it renders: CUDA through gsplat, CPU through Numba)."""
        return self.background.device

    def to(self, device: torch.device | str) -> "SceneGraph":
        """The same graph with every tensor on ``device`` (shares the tensors already there)."""
        agents = tuple(a.with_changes(gaussians=a.gaussians.to(device),
                                      relight=None if a.relight is None else a.relight.to(device))
                       for a in self.agents)
        return self.replace(background=self.background.to(device), agents=agents,
                            sky=SkyParams(self.sky.texture.to(device)),
                            exposure={c: t.to(device) for c, t in self.exposure.items()})

    def check_frame(self, frame_idx: int) -> int:
        if not 0 <= int(frame_idx) < self.n_frames:
            raise OmniscsError(f"frame {frame_idx} is out of range; the scene graph has frames 0..{self.n_frames - 1}")
        return int(frame_idx)

    def view(self, camera: str, frame_idx: int, world_from_ego: np.ndarray | None = None) -> View:
        """A logged camera at frame ``frame_idx`` (agents posed as in that frame), optionally on another ego pose."""
        rec = self.camera(camera)
        f = self.check_frame(frame_idx)
        ego = self.world_from_ego[f] if world_from_ego is None else np.asarray(world_from_ego, dtype=np.float64)
        if ego.shape != (4, 4) or not np.all(np.isfinite(ego)):
            raise OmniscsError("world_from_ego must be a finite 4x4 rigid transform")
        return View(f, ego @ rec.ego_from_camera, rec.K.copy(), rec.width, rec.height, camera)

    @torch.no_grad()
    def render(self, view: View) -> RenderOutput:
        """Render without gradients (for inspection, evaluation and edited variants)."""
        return render_view(self, view)


@dataclass(frozen=True)
class StaticLayer:
    """The background node prepared once for one view: activated, coloured for that camera, and cut down to the
    Gaussians the rasterizer keeps in that view (the others never reach a pixel of it). Rendering the view again
    with moved agents (L_app, every optimisation step) then skips activating, colouring and projecting them."""

    frame_idx: int
    world_from_camera: np.ndarray  # [4, 4] the view it was made for
    K: np.ndarray                  # [3, 3]
    size: tuple[int, int]          # width, height
    means: Tensor                  # [M, 3] world frame, detached
    quats: Tensor                  # [M, 4]
    scales: Tensor                 # [M, 3]
    opacities: Tensor              # [M]
    colours: Tensor                # [M, 3]
    kept_of: int                   # background Gaussians before culling

    def matches(self, view: View) -> bool:
        return (self.frame_idx == view.frame_idx and self.size == (view.width, view.height)
                and np.array_equal(self.world_from_camera, view.world_from_camera) and np.array_equal(self.K, view.K))


@torch.no_grad()
def static_layer(graph: SceneGraph, view: View, sh_degree: int | None = None) -> StaticLayer:
    """The background of ``graph`` for ``view`` (see StaticLayer): one projection decides what stays."""
    degree = graph.sh_degree if sh_degree is None else min(sh_degree, graph.sh_degree)
    local = activate(graph.background.detached())
    on = dict(device=local.means.device, dtype=local.means.dtype)
    centre = torch.from_numpy(view.world_from_camera[:3, 3]).to(**on)
    colours = colors_from_sh(degree, local.sh, (local.means - centre)[None])[0]
    keep = torch.zeros(len(local), dtype=torch.bool, device=local.means.device)
    if len(local):
        s = graph.settings
        viewmat = torch.from_numpy(invert_transform(view.world_from_camera)).to(**on)[None]
        K = torch.from_numpy(view.K).to(**on)[None]
        _, _, meta = rasterize(local.means, local.quats, local.scales, local.opacities, colours, viewmat, K,
                               view.width, view.height, near_plane=s.near_plane, far_plane=s.far_plane, eps2d=s.eps2d,
                               render_mode="RGB", backend=s.backend, rasterize_mode=s.rasterize_mode)
        keep = (meta["radii"][0] > 0).reshape(len(local), -1).any(-1).to(local.means.device)
    return StaticLayer(int(view.frame_idx), np.array(view.world_from_camera, dtype=np.float64), np.array(view.K),
                       (int(view.width), int(view.height)), local.means[keep].contiguous(), local.quats[keep].contiguous(),
                       local.scales[keep].contiguous(), local.opacities[keep].contiguous(), colours[keep].contiguous(),
                       len(local))


def node_radius(params: GaussianParams) -> float:
    """Radius about the node's origin that holds every Gaussian out to 3 sigma of its largest axis (metres)."""
    if len(params) == 0:
        return 0.0
    g = activate(params.detached())
    return float((g.means.norm(dim=-1) + 3.0 * g.scales.max(dim=-1).values).max())


def agent_may_show(view: View, centre_world: np.ndarray, radius: float, near_plane: float,
                   margin: float = 0.5) -> bool:
    """False only when a sphere (centre, radius) lies wholly behind the near plane or outside one side of the view
    frustum widened by ``margin`` of the image size on every side (the slack covers the rasterizer's linearised
    splat extent near the image border): nothing in it can reach a pixel of ``view``."""
    cam_from_world = invert_transform(view.world_from_camera)
    x, y, z = cam_from_world[:3, :3] @ np.asarray(centre_world, dtype=np.float64) + cam_from_world[:3, 3]
    if z + radius < near_plane:
        return False
    K = view.K
    mu, mv = margin * view.width, margin * view.height
    for coord, lo, hi, f, c in ((x, -mu, view.width + mu, K[0, 0], K[0, 2]), (y, -mv, view.height + mv, K[1, 1], K[1, 2])):
        a_lo, a_hi = (lo - c) / f, (hi - c) / f  # coord / z must lie in [a_lo, a_hi]
        if (coord - a_lo * z) / np.hypot(1.0, a_lo) < -radius or (a_hi * z - coord) / np.hypot(1.0, a_hi) < -radius:
            return False
    return True


def render_view(graph: SceneGraph, view: View, sh_degree: int | None = None, absgrad: bool = False,
                agent_poses: Mapping[int, NodePose] | None = None, static: StaticLayer | None = None,
                only_agents: Collection[int] | None = None,
                labels: Mapping[str, Tensor] | None = None,
                activated: Mapping[str, GaussianParams] | None = None) -> RenderOutput:
    """Concatenate the nodes present in ``view.frame_idx`` (agents placed by Eq. 1), rasterise them, show
    the sky where they leave the pixel uncovered, and apply the camera's exposure correction.

    ``sh_degree`` caps the SH bands used (progressive SH while fitting); ``absgrad`` asks the rasterizer
    for per-pixel absolute screen gradients (densification); ``agent_poses`` places the named agent nodes
    (track id -> pose) instead of their logged pose in this frame, with gradients flowing into the poses;
    ``static`` is the background already prepared for this view (``static_layer``; same image, less work);
    ``only_agents`` renders just those agent nodes (the caller has shown the others cannot reach the image:
    ``agent_may_show``).
    ``labels`` ({node key: [n_node, E] float}) blends E extra channels with the same weights as the colours: a
    one-hot column per instance gives, per pixel, how much of the pixel each instance covers once what lies in
    front of it is taken off (auto-annotation); nodes without an entry blend zeros. Not with ``static``.
    ``activated`` ({node key: the node's Gaussians already activated}) spares activating them again when one
    unchanging graph is rendered many times (no gradients reach the raw parameters through it).
    Agent nodes with relight data (``omniscs.nsg.relight``) take their colours from it, lit at this frame's pose.
    """
    agent_poses = dict(agent_poses or {})
    if labels is not None and static is not None:
        raise OmniscsError("render_view blends labels over whole nodes; a static layer has culled the background")
    if static is not None and not static.matches(view):
        raise OmniscsError(f"static layer was made for frame {static.frame_idx} at {static.size[0]}x{static.size[1]}, "
                           f"not for this view (frame {view.frame_idx}, {view.width}x{view.height}, or another pose)")
    unknown = sorted(set(agent_poses) - set(graph.agent_ids))
    if unknown:
        raise OmniscsError(f"agent_poses names track(s) {unknown} that are not agent nodes of this graph")
    degree = graph.sh_degree if sh_degree is None else min(sh_degree, graph.sh_degree)
    f = graph.check_frame(view.frame_idx)
    camera_centre = view.world_from_camera[:3, 3]
    nodes: list[tuple[str, np.ndarray | NodePose | None, GaussianParams, Relight | None]] = []
    if static is None:
        nodes.append((BACKGROUND, None, graph.background, None))
    keep = None if only_agents is None else set(int(t) for t in only_agents)
    nodes += [(agent_key(a.track_id), agent_poses.get(a.track_id, a.world_from_agent[f]), a.gaussians, a.relight)
              for a in graph.agents if a.present[f] and (keep is None or a.track_id in keep)]
    parts, slices, start = [], {}, 0
    n_labels = 0 if labels is None else _label_width(labels)
    if static is not None and len(static.means):
        parts.append((static, static.colours))
        slices[BACKGROUND] = slice(0, len(static.means))
        start = len(static.means)
    nodes = [n for n in nodes if len(n[2])]
    if _fused_preparation(nodes, labels, static, activated):
        means, quats, scales, opacities, colours = prepare_nodes([(pose, params) for _, pose, params, _ in nodes],
                                                                 camera_centre, degree)
        parts.append((_Placed(means, quats, scales, opacities), colours))
        for key, _, params, _ in nodes:
            slices[key] = slice(start, start + len(params))
            start += len(params)
        nodes = []
    if len(nodes) > 1 and not n_labels and all(relight is None for *_, relight in nodes):
        placed, colours = _place_and_colour(nodes, camera_centre, degree, activated)
        parts.append((placed, colours))
        for key, _, params, _ in nodes:
            slices[key] = slice(start, start + len(params))
            start += len(params)
        nodes = []
    for key, world_from_node, params, relight in nodes:
        local = activated.get(key) if activated is not None else None
        if local is None or len(local) != len(params):
            local = activate(params)
        dirs = local.means - _centre_in_node(camera_centre, world_from_node).to(local.means.device, local.means.dtype)
        if relight is not None:  # lit by the scene's light at this frame's pose, seen from this camera
            colours = relight.colours(world_from_node.rotmat() if isinstance(world_from_node, NodePose)
                                      else world_from_node[:3, :3], dirs).to(local.means.dtype)
        else:
            colours = colors_from_sh(degree, local.sh, dirs[None])[0]
        placed = local if world_from_node is None else place_gaussians(local, world_from_node)
        if n_labels:
            colours = torch.cat([colours, _node_labels(labels, key, len(local), n_labels, colours)], -1)
        parts.append((placed, colours))
        slices[key] = slice(start, start + len(local))
        start += len(local)

    device = graph.sky.texture.device
    label_image = None
    if start == 0:
        zeros = torch.zeros(view.height, view.width, device=device)
        colour, depth, alpha, meta = zeros[..., None].expand(-1, -1, 3), zeros, zeros, {}
        if n_labels:
            label_image = torch.zeros(view.height, view.width, n_labels, device=device)
    else:
        def joined(tensors: list[Tensor]) -> Tensor:  # one part (a fit step's prepared nodes) needs no copy
            return tensors[0] if len(tensors) == 1 else torch.cat(tensors)

        means = joined([p.means for p, _ in parts])
        quats = joined([p.quats for p, _ in parts])
        scales = joined([p.scales for p, _ in parts])
        opacities = joined([p.opacities for p, _ in parts])
        colours = joined([c for _, c in parts])
        # CUDA tensors go to gsplat, CPU ones to the Numba kernels (backend 'auto' dispatches on the device)
        viewmat = torch.from_numpy(invert_transform(view.world_from_camera)).to(means.device, means.dtype)[None]
        K = torch.from_numpy(view.K).to(means.device, means.dtype)[None]
        s = graph.settings
        out, alphas, meta = rasterize(means, quats, scales, opacities, colours, viewmat, K, view.width, view.height,
                                      near_plane=s.near_plane, far_plane=s.far_plane, eps2d=s.eps2d,
                                      render_mode="RGB+ED", backend=s.backend, rasterize_mode=s.rasterize_mode,
                                      absgrad=absgrad)
        alpha = alphas[0, ..., 0]
        colour = out[0, ..., :3]
        depth = out[0, ..., -1]
        if n_labels:
            label_image = out[0, ..., 3:3 + n_labels]
    affine = graph.exposure.get(view.camera) if view.camera is not None else None
    rgb = with_backdrop(colour, alpha, graph.sky, affine, view)
    return RenderOutput(rgb, depth, alpha, meta, slices, label_image)


def _place_and_colour(nodes, camera_centre: np.ndarray, degree: int,
                      activated: Mapping[str, Gaussians] | None) -> tuple[Gaussians, Tensor]:
    """The node-by-node loop of ``render_view`` (activate, colour as seen from the camera in the node's frame,
    place by Eq. 1) for several nodes without relight data at once, through ``place_many``: a behaviour-level
    step renders a few dozen agent nodes with differentiable poses, and node by node that was some forty small
    operations per node each way. The same values to float32 rounding."""
    each = []
    for key, _, params, _ in nodes:
        g = activated.get(key) if activated is not None else None
        each.append(g if g is not None and len(g) == len(params) else activate(params))
    local = Gaussians(*(torch.cat([getattr(g, name) for g in each])
                        for name in ("means", "quats", "scales", "opacities", "sh")))
    node_of = torch.repeat_interleave(torch.arange(len(nodes), device=local.means.device),
                                      torch.tensor([len(g) for g in each], device=local.means.device))
    placed, rotations, translations = place_many(local, node_of, [pose for _, pose, _, _ in nodes])
    centre = torch.from_numpy(np.asarray(camera_centre, dtype=np.float64)).to(rotations.device, rotations.dtype)
    centres = torch.einsum("kji,kj->ki", rotations, centre - translations)  # the camera in each node's frame
    return placed, colors_from_sh(degree, local.sh, (local.means - centres[node_of])[None])[0]


class _Placed(NamedTuple):
    """World-frame rasterizer inputs of prepared nodes (what render_view concatenates)."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor


def _fused_preparation(nodes, labels, static, activated) -> bool:
    """Whether a render's nodes go through ``prepare_nodes`` (one fused pass, CPU) rather than node by node: when
    gradients are being taken into the Gaussians (a fit or refit step, where the per-node operations' overhead
    counts; other renders keep the node-by-node code, whose images they are compared with) and the nodes
    are plain float32 CPU Gaussians at fixed poses (no differentiable pose, relighting, labels or prepared
    background)."""
    if not torch.is_grad_enabled() or labels is not None or static is not None or activated is not None:
        return False
    return any(p.means.requires_grad or p.sh_dc.requires_grad for _, _, p, _ in nodes) and all(
        relight is None and not isinstance(pose, NodePose) and p.means.device.type == "cpu"
        and p.means.dtype == torch.float32 for _, pose, p, relight in nodes)


def _label_width(labels: Mapping[str, Tensor]) -> int:
    widths = {int(t.shape[-1]) for t in labels.values() if t.dim() == 2}
    if len(widths) != 1 or any(t.dim() != 2 for t in labels.values()):
        raise OmniscsError("render_view labels must be [n_node, E] tensors with one E for every node")
    return widths.pop()


def _node_labels(labels: Mapping[str, Tensor], key: str, n: int, width: int, like: Tensor) -> Tensor:  # [n, E]
    own = labels.get(key)
    if own is None:
        return like.new_zeros(n, width)
    if own.shape[0] != n:
        raise OmniscsError(f"render_view labels of {key} have {own.shape[0]} rows; the node has {n} Gaussians")
    return own.to(like.device, like.dtype)


def _centre_in_node(camera_centre: np.ndarray, world_from_node: np.ndarray | NodePose | None) -> Tensor:  # [3]
    """The camera centre in a node's frame (where its view-dependent colours are evaluated)."""
    if world_from_node is None:
        return torch.from_numpy(camera_centre)
    if isinstance(world_from_node, NodePose):
        R = world_from_node.rotmat()
        c = torch.from_numpy(camera_centre).to(R.device, R.dtype)
        return (c - world_from_node.translation.to(R.device, R.dtype)) @ R
    return torch.from_numpy(transform_points(invert_transform(world_from_node), camera_centre[None])[0])
