"""Compositing an object into a fitted scene graph: an appearance variant is a list of edit specs (the same JSON values
as everywhere else) that either replaces an agent's local model ``G_A-loc`` with the object's (the object keeps its
own size and inherits the agent's motion) or inserts it at a user pose (upright, on its side, overturned), resting on
the road. Around the edits: the annotation box of each changed node (the box of the rotated model), the scene's
colour transform applied to the object, and a soft contact shadow under it; the last two are switchable."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch

from omniscs.agents.dual import colour_corrected
from omniscs.edits import Insert, ReplaceModel, edit_to_dict, parse_edits
from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams, with_sh_degree
from omniscs.geometry import pose_from_xyz_yaw, rotmat_from_euler
from omniscs.nsg.agent import AgentNode
from omniscs.nsg.edit import AgentModel, ModelResolver, apply_graph_edits
from omniscs.nsg.graph import SceneGraph
from omniscs.quaternions import rotmat_to_quat
from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET

KIND = "appearance"
#: ``kind`` of a designed variant: a user's edit spec (e.g. saved in ``omniscs view``) rendered as one variant; composed
#: as an appearance variant is, its edits as they are.
DESIGNED = "designed"
PLACEMENTS = ("replace", "insert")
SPEC_VERSION = 1
#: Track ids of contact-shadow nodes: the object's id plus this (never a box, never annotated).
SHADOW_ID_OFFSET = 1_000_000_000
#: Tilted heading: below this horizontal length of the rotated x axis the yaw is read from the y axis (pitch ~90°).
GIMBAL_EPS = 1e-6


@dataclass(frozen=True)
class CompositeConfig:
    """How an object is fitted into the scene's look (each part switchable, each measured by ``bench appearance``)."""

    colour_fit: bool = True
    """Apply the scene's colour transform (exposure and white balance; ``omniscs.scs.appearance.colour``) to the
    object's colours."""
    shadow: bool = True
    """Put a soft contact shadow (dark, flat Gaussians on the road) under the object."""
    shadow_opacity: float = 0.35
    """Opacity of the shadow under the object's footprint."""
    shadow_reach_m: float = 0.3
    """How far beyond the footprint the shadow fades out (Gaussian fall-off, metres)."""
    shadow_spacing_m: float = 0.15
    """Spacing of the shadow's Gaussians (metres)."""
    shadow_lift_m: float = 0.02
    """Height of the shadow above the road surface (metres), so that it is drawn over the road."""

    def __post_init__(self) -> None:
        if not (0.0 <= self.shadow_opacity < 1.0 and self.shadow_reach_m > 0 and self.shadow_spacing_m > 0
                and 0.0 <= self.shadow_lift_m < 1.0):
            raise OmniscsError(f"bad composite settings {self}: shadow opacity in [0, 1), reach and spacing above 0")

    def to_dict(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------- variant specs
def replace_variant(scene_id: str, variant_id: str, track_id: int, model: AgentModel, model_id: str) -> dict:
    """An appearance variant that swaps track ``track_id``'s model for ``model`` (its own size; the track's motion)."""
    edit = ReplaceModel(int(track_id), model_id, size=tuple(float(v) for v in model.size))
    return _spec(scene_id, variant_id, "replace", int(track_id), model_id, model.category, [edit], None)


def insert_variant(scene_id: str, variant_id: str, track_id: int, model: AgentModel, model_id: str,
                   x: float, y: float, ground_z: float, yaw: float, roll_deg: float = 0.0, pitch_deg: float = 0.0,
                   waypoints: list | None = None) -> dict:
    """An appearance variant that adds ``model`` as track ``track_id`` standing at (x, y, yaw) on the road at height
    ``ground_z`` (static), or along ``waypoints`` (one [x, y, ground z, yaw] or None per frame), tilted by
    ``roll_deg``/``pitch_deg`` (roll 180 = overturned, 90 = on its side) and resting on the road."""
    size = tuple(float(v) for v in model.size)
    if waypoints is None:
        pose = (float(x), float(y), float(ground_z) + 0.5 * size[2], float(yaw))
        edit = Insert(int(track_id), model_id, model.category, pose=pose, roll_deg=float(roll_deg),
                      pitch_deg=float(pitch_deg), size=size)
    else:
        lifted = tuple(None if w is None else (float(w[0]), float(w[1]), float(w[2]) + 0.5 * size[2], float(w[3]))
                       for w in waypoints)
        edit = Insert(int(track_id), model_id, model.category, waypoints=lifted, roll_deg=float(roll_deg),
                      pitch_deg=float(pitch_deg), size=size)
    pose_info = {"x": float(x), "y": float(y), "ground_z": float(ground_z), "yaw": float(yaw),
                 "roll_deg": float(roll_deg), "pitch_deg": float(pitch_deg), "static": waypoints is None}
    return _spec(scene_id, variant_id, "insert", int(track_id), model_id, model.category, [edit], pose_info)


def _spec(scene_id: str, variant_id: str, placement: str, track_id: int, model_id: str, category: str, edits,
          pose: dict | None) -> dict:
    # the object is the variant's SCS agent: annotated is_adversary, drawn red in dataset previews
    return {"variant_id": variant_id, "scene_id": scene_id, "kind": KIND, "placement": placement,
            "track_id": int(track_id), "adversary": int(track_id), "object_id": model_id, "category": category,
            "edits": [edit_to_dict(e) for e in edits], "pose": pose, "spec_version": SPEC_VERSION}


def check_variant(variant: dict) -> dict:
    """``variant`` checked as an appearance variant (kind, placement, a track id, parseable edits) or a designed one
    (kind and parseable edits); one OmniscsError naming what is wrong otherwise."""
    vid = variant.get("variant_id") if isinstance(variant, dict) else None
    if not isinstance(variant, dict) or variant.get("kind") not in (KIND, DESIGNED):
        raise OmniscsError(f"variant {vid}: not an appearance or designed variant (kind must be {KIND!r} or "
                           f"{DESIGNED!r})")
    if variant.get("kind") == KIND and variant.get("placement") not in PLACEMENTS:
        raise OmniscsError(f"variant {vid}: placement must be one of {PLACEMENTS}; got {variant.get('placement')!r}")
    parse_edits(variant.get("edits") or [])
    if not variant.get("edits"):
        raise OmniscsError(f"variant {vid}: an appearance variant needs at least one edit")
    return variant


# ----------------------------------------------------------------------------- annotation boxes
def heading_and_tilt(R: np.ndarray) -> tuple[float, np.ndarray]:  # [3, 3] world_from_agent -> yaw, tilt [3, 3]
    """Split a rotation into its heading (yaw about z) and the tilt left in the heading's frame, R = Rz(yaw) tilt.
    The heading is the rotated x axis's direction on the ground; when the x axis stands upright (pitch 90°) the
    rotated y axis gives it instead."""
    R = np.asarray(R, dtype=np.float64)
    if math.hypot(R[0, 0], R[1, 0]) > GIMBAL_EPS:
        yaw = math.atan2(R[1, 0], R[0, 0])
    else:
        yaw = math.atan2(-R[0, 1], R[1, 1])
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return yaw, Rz.T @ R


def node_boxes(node: AgentNode) -> dict[int, dict]:
    """{frame: box row} of a node where it is present: the upright box around the node's rotated box, so a tilted
    model (on its side, overturned) is annotated by the box it fills (nuScenes boxes turn about z only); centre =
    the node's centre, heading = its yaw."""
    size = np.asarray(node.size, dtype=np.float64)
    out = {}
    for f in np.flatnonzero(node.present):
        T = node.world_from_agent[f]
        yaw, tilt = heading_and_tilt(T[:3, :3])
        extent = np.abs(tilt) @ size
        q = rotmat_to_quat(pose_from_xyz_yaw(0.0, 0.0, 0.0, yaw)[:3, :3])
        out[int(f)] = {"category": node.category, "source_category": node.category,
                       "cx": float(T[0, 3]), "cy": float(T[1, 3]), "cz": float(T[2, 3]),
                       "length": float(extent[0]), "width": float(extent[1]), "height": float(extent[2]),
                       "yaw": float(yaw), "qw": float(q[0]), "qx": float(q[1]), "qy": float(q[2]), "qz": float(q[3])}
    return out


# ----------------------------------------------------------------------------- shadow
def contact_shadow(footprint: np.ndarray,  # [2] length, width of the object's box on the ground (metres)
                   config: CompositeConfig, sh_degree: int, device="cpu") -> GaussianParams:  # ground frame
    """A soft dark patch: flat black Gaussians on a grid over the footprint grown by twice the reach, in a frame
    whose origin is the footprint's centre on the road (z up); opacity ``shadow_opacity`` inside the footprint,
    falling off as a Gaussian of the distance outside it (the darkening the sky light gets under and around an
    object standing on the road)."""
    half = 0.5 * np.asarray(footprint, dtype=np.float64)
    grow = 2.0 * config.shadow_reach_m
    sp = config.shadow_spacing_m
    xs = np.arange(-half[0] - grow, half[0] + grow + 1e-9, sp)
    ys = np.arange(-half[1] - grow, half[1] + grow + 1e-9, sp)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.stack([gx.ravel(), gy.ravel()], 1)
    outside = np.linalg.norm(np.maximum(np.abs(xy) - half, 0.0), axis=1)
    alpha = config.shadow_opacity * np.exp(-0.5 * (outside / config.shadow_reach_m) ** 2)
    keep = alpha > 0.01
    xy, alpha = xy[keep], alpha[keep]
    n = len(xy)
    means = np.concatenate([xy, np.full((n, 1), config.shadow_lift_m)], 1)
    on = dict(dtype=torch.float32, device=device)
    black = (0.0 - SH_COLOR_OFFSET) / SH_C0
    params = GaussianParams(
        means=torch.tensor(means, **on),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], **on).repeat(n, 1),
        log_scales=torch.tensor(np.log([[0.75 * sp, 0.75 * sp, 0.005]]), **on).repeat(n, 1),
        opacity_logits=torch.tensor(np.log(alpha / (1.0 - alpha)), **on),
        sh_dc=torch.full((n, 3), black, **on),
        sh_rest=torch.zeros((n, 0, 3), **on))
    return with_sh_degree(params, sh_degree)


def shadow_node(node: AgentNode, config: CompositeConfig, sh_degree: int, device="cpu") -> AgentNode:
    """The contact shadow of ``node``: a node of its own (track id + SHADOW_ID_OFFSET, never annotated) that follows
    the object's footprint on the road in every frame the object is present."""
    boxes = node_boxes(node)
    poses = np.tile(np.eye(4), (len(node.present), 1, 1))
    footprint = np.zeros(2)
    for f, b in boxes.items():
        poses[f] = pose_from_xyz_yaw(b["cx"], b["cy"], b["cz"] - 0.5 * b["height"], b["yaw"])
        footprint = np.maximum(footprint, [b["length"], b["width"]])
    if not boxes:
        raise OmniscsError(f"track {node.track_id} is present in no frame: it casts no shadow")
    shadow = contact_shadow(footprint, config, sh_degree, device)
    size = np.array([footprint[0] + 4 * config.shadow_reach_m, footprint[1] + 4 * config.shadow_reach_m, 0.05])
    return AgentNode(int(node.track_id) + SHADOW_ID_OFFSET, node.category, size, poses, node.present.copy(), shadow)


# ----------------------------------------------------------------------------- composition
def colour_resolver(resolve: ModelResolver, affine: np.ndarray | None) -> ModelResolver:
    """``resolve`` with every model's colours mapped by ``affine`` ([3, 4], A | b; None: unchanged)."""
    if affine is None:
        return resolve

    def mapped(asset_id: str) -> AgentModel:
        m = resolve(asset_id)
        return AgentModel(colour_corrected(m.gaussians, np.asarray(affine, dtype=np.float64)), m.size, m.category)
    return mapped


@dataclass(frozen=True)
class Composite:
    """An appearance variant composed into a graph."""

    graph: SceneGraph                 # the edited graph (shadow nodes included)
    boxes: dict[int, dict | None]     # track id -> {frame: box row} of every changed node; None = removed
    objects: tuple[int, ...]          # the tracks that show the inserted or replacing object


def compose_variant(graph: SceneGraph, variant: dict, resolve: ModelResolver, config: CompositeConfig = CompositeConfig(),
                    colour: np.ndarray | None = None) -> Composite:
    """``graph`` with the appearance variant's edits applied (models from ``resolve``; colours through the scene's
    ``colour`` transform, default the variant's own ``colour``, when ``config.colour_fit``), a contact shadow under each object (``config.shadow``), and the
    annotation boxes of every node the edits touched."""
    check_variant(variant)
    if colour is None and variant.get("colour") is not None:
        colour = np.asarray(variant["colour"], dtype=np.float64)
        if colour.shape != (3, 4) or not np.all(np.isfinite(colour)):
            raise OmniscsError(f"variant {variant.get('variant_id')}: colour must be a finite 3 x 4 matrix [A | b]")
    edits = parse_edits(variant["edits"])
    loaded: dict[str, AgentModel] = {}  # each model read once, checked, then handed to the edits
    for e in edits:
        if isinstance(e, (Insert, ReplaceModel)) and e.asset_id not in loaded:
            model = loaded[e.asset_id] = resolve(e.asset_id)
            if not isinstance(model.gaussians, GaussianParams) or len(model.gaussians) == 0:
                raise OmniscsError(f"variant {variant.get('variant_id')}: model {e.asset_id} has no Gaussians")
            if not model.gaussians.is_finite():
                raise OmniscsError(f"variant {variant.get('variant_id')}: model {e.asset_id} has non-finite parameters")
    models = colour_resolver(lambda a: loaded[a] if a in loaded else resolve(a), colour if config.colour_fit else None)
    edited = apply_graph_edits(graph, edits, models)
    before = {a.track_id for a in graph.agents}
    after = {a.track_id: a for a in edited.agents}
    touched = sorted({int(e.track_id) for e in edits})
    boxes = {t: (node_boxes(after[t]) if t in after else None) for t in touched}
    objects = tuple(int(e.track_id) for e in edits if isinstance(e, (Insert, ReplaceModel)))
    if config.shadow and objects:
        shadows = [shadow_node(after[t], config, graph.sh_degree, graph.device) for t in objects]
        clash = [s.track_id for s in shadows if s.track_id in before]
        if clash:
            raise OmniscsError(f"shadow track id(s) {clash} are taken by agents of the graph")
        edited = edited.replace(agents=tuple(edited.agents) + tuple(shadows))
    return Composite(edited, boxes, objects)


def new_track_id(scene, graph: SceneGraph, taken: set[int] | None = None) -> int:
    """The smallest track id above every id of the scene's boxes, the graph's nodes and ``taken``."""
    ids = set(int(t) for t in scene.boxes.track_id.unique()) | set(graph.agent_ids) | set(taken or ())
    return max(ids, default=-1) + 1


def model_upright_box(model: AgentModel, roll_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:  # -> [3]
    """The box (length, width, height along the heading) a model fills once tilted by roll/pitch."""
    R = rotmat_from_euler(math.radians(roll_deg), math.radians(pitch_deg), 0.0)
    return np.abs(R) @ np.asarray(model.size, dtype=np.float64)


ResolverFactory = Callable[[SceneGraph], ModelResolver]
