"""The per-scene plan: what a scene needs modelled, decided from its tracks and the requested edits.

"Model only what a scene requires" (DESIGN.md): tracks that move or that an edit names become agent nodes; everything
else stays in the background. Edits that turn an agent far from its observed views need a 360° model; moving or
removing a large static object, or replacing it by a smaller one, needs background repair. The Gaussian budget
follows the area the cameras see along the ego path. Stages nothing needs do not run.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np

from omniscs.edits import Edit, Insert, Remove, ReplaceModel, Rotate, SetTrajectory, Translate
from omniscs.errors import OmniscsError
from omniscs.scene.store import Scene
from omniscs.scene.summary import MOVING_PATH_LENGTH_M, agent_rows
from omniscs.taxonomy import VEHICLE_CATEGORIES

PLAN_VERSION = 1

#: A replacement uncovers what the old object hid when the old box reaches further than this (metres) beyond the
#: new object's box on some side (the new box rests on the ground the old one stood on, under the same motion).
#: A thinner sliver stays inside the dilated outline any rendered edge blurs over; a module constant rather than a
#: PlanConfig field because PlanConfig is part of every fit's key.
UNCOVERED_MARGIN_M = 0.25


@dataclass(frozen=True)
class PlanConfig:
    """Thresholds that decide what a scene needs; presets scale the Gaussian budget."""

    moving_path_length_m: float = MOVING_PATH_LENGTH_M
    """A track whose centre travels further than this becomes an agent node."""
    rotation_needing_360_deg: float = 45.0
    """An edit that turns an agent by more than this shows unobserved sides: it needs a 360° model."""
    large_object_volume_m3: float = 20.0
    """Static objects at least this big leave a visible hole when moved or removed: repair background."""
    view_range_m: float = 60.0
    """How far beside and ahead of the ego path the modelled background reaches."""
    gaussians_per_m2: float = 6.0
    """Background Gaussian density per square metre of the modelled area, per camera."""
    gaussians_per_agent: int = 3_000
    """Gaussians per agent node."""
    min_gaussians: int = 20_000
    """Floor on the total budget."""
    max_gaussians: int = 400_000
    """Ceiling on the total budget (memory and time on a 2-core machine)."""
    holdout_every: int = 4
    """Every Nth frame (N-1, 2N-1, ...) is held out of fitting for evaluation; 0 holds none out."""
    every_track_a_node: bool = False
    """Model every track as an agent node whatever the request (the baseline ``omniscs bench plan`` compares
    the plan with: what modelling everything costs)."""


@dataclass(frozen=True)
class ScenePlan:
    """What to model for one scene; written next to each checkpoint and shown by the CLI."""

    scene_id: str
    content_hash: str
    agent_nodes: tuple[int, ...]
    """Track ids modelled as agent nodes (own Gaussians in the agent frame + per-frame pose)."""
    node_reasons: dict[int, str]
    """Why each node exists: 'moving', 'edited', 'behavior' (a vehicle that behaviour variants may move), or
    several joined by '+'."""
    background_tracks: tuple[int, ...]
    """Static, unedited tracks: left in the background Gaussians."""
    needs_360: tuple[int, ...]
    """Agent nodes whose edits show sides never observed (large rotations, model swaps)."""
    background_repair: tuple[int, ...]
    """Large static objects that an edit moves, removes or replaces by a smaller object (one that leaves part of the
    old footprint uncovered): their footprint needs repair."""
    inserted: tuple[int, ...]
    """Track ids that edits insert (they come from the model pool, not from this log)."""
    cameras: tuple[str, ...]
    train_frames: tuple[int, ...]
    heldout_frames: tuple[int, ...]
    modelled_area_m2: float
    gaussian_budget: int
    stages: dict[str, bool]
    """Which pipeline stages run for this scene."""
    version: int = PLAN_VERSION

    def to_dict(self) -> dict:
        d = asdict(self)
        d["node_reasons"] = {str(k): v for k, v in self.node_reasons.items()}
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ScenePlan":
        d = dict(d)
        if d.get("version") != PLAN_VERSION:
            raise OmniscsError(f"plan version {d.get('version')} is not {PLAN_VERSION}; re-plan the scene")
        d["node_reasons"] = {int(k): v for k, v in d["node_reasons"].items()}
        for key in ("agent_nodes", "background_tracks", "needs_360", "background_repair", "inserted", "cameras",
                    "train_frames", "heldout_frames"):
            d[key] = tuple(d[key])
        return cls(**d)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    def summary(self) -> str:
        return (f"{len(self.agent_nodes)} agent node(s) {list(self.agent_nodes)}, "
                f"{len(self.background_tracks)} track(s) left in the background, "
                f"360° models for {list(self.needs_360)}, background repair for {list(self.background_repair)}, "
                f"{self.gaussian_budget:,} Gaussians over {self.modelled_area_m2:,.0f} m², "
                f"{len(self.train_frames)} training / {len(self.heldout_frames)} held-out frames")


def _edited_tracks(edits: list[Edit]) -> dict[int, list[Edit]]:
    by_track: dict[int, list[Edit]] = {}
    for e in edits:
        by_track.setdefault(int(e.track_id), []).append(e)
    return by_track


def _turns_far(edit: Edit, limit_deg: float) -> bool:
    if isinstance(edit, Rotate):
        return max(abs(edit.yaw_deg), abs(edit.roll_deg), abs(edit.pitch_deg)) > limit_deg
    return isinstance(edit, ReplaceModel)


def uncovered_margin(old_size, edit: ReplaceModel) -> float:
    """How far (m) an object's box of ``old_size`` (length, width, height) reaches beyond the box a ``ReplaceModel``
    edit puts in its place, on its worst side: the new box is centred where the old one was along the length and
    width and rests on the same ground (``omniscs.edits.resized_poses``), so the old box shows half the difference
    at each end and side and the whole difference on top. 0 when the new box covers the old one (a ``size`` of None
    scales the new model to the old box)."""
    if edit.size is None:
        return 0.0
    old = np.asarray(old_size, dtype=np.float64)
    new = np.asarray(edit.size, dtype=np.float64)
    reach = np.array([0.5 * (old[0] - new[0]), 0.5 * (old[1] - new[1]), old[2] - new[2]])
    return float(max(0.0, reach.max()))


def uncovers(old_size, edit: Edit) -> bool:
    """Whether ``edit`` leaves part of a box of ``old_size`` empty where the object stood: a replacement by an object
    whose box does not cover the old one within UNCOVERED_MARGIN_M."""
    return isinstance(edit, ReplaceModel) and uncovered_margin(old_size, edit) > UNCOVERED_MARGIN_M


def repair_objects(agents: dict[int, dict], edits: list[Edit], config: PlanConfig = PlanConfig()) -> tuple[int, ...]:
    """Track ids of the large static objects (``agents``: ``agent_rows`` by track id) whose footprint ``edits``
    uncover: moved, removed, or replaced by a smaller object. A moving object's background was seen from other
    frames, and a small object's hole is small: neither is repaired. Edits naming tracks outside ``agents``
    (inserted objects) uncover nothing."""
    out = []
    for t, es in _edited_tracks(edits).items():
        a = agents.get(t)
        if a is None or a["moving"] or a["length"] * a["width"] * a["height"] < config.large_object_volume_m3:
            continue
        size = (a["length"], a["width"], a["height"])
        if any(isinstance(e, (Translate, Rotate, Remove, SetTrajectory)) or uncovers(size, e) for e in es):
            out.append(int(t))
    return tuple(sorted(out))


def modelled_area(scene: Scene, view_range_m: float) -> float:
    """Area of the ego path's bounding box grown by ``view_range_m`` (m²): what the cameras can see."""
    xy = scene.world_from_ego_all[:, :2, 3]
    extent = xy.max(axis=0) - xy.min(axis=0) + 2 * view_range_m
    return float(extent[0] * extent[1])


def make_plan(scene: Scene, edits: list[Edit] | None = None, config: PlanConfig = PlanConfig(),
              cameras: list[str] | None = None, behavior_variants: int = 0, fit_nsg: bool = True,
              appearance_variants: int = 0,
              annotate: bool = False) -> ScenePlan:
    """Decide what to model for ``scene`` given the edits the requested variants will apply, how many
    behaviour-level variants are requested (their stage runs only when that is > 0, and then every vehicle
    becomes an agent node, since the adversarial optimisation may move any of them) and whether a scene graph
    is fitted at all (``fit_nsg``; without one, no later stage that models the scene runs). ``annotate`` renders
    and annotates the variants (the dataset's frames): it needs a scene graph and behaviour or appearance variants.
    ``appearance_variants`` > 0 (objects composited into the graph) also makes every vehicle a node: any may have
    its model replaced."""
    if isinstance(behavior_variants, bool) or not isinstance(behavior_variants, (int, np.integer)) \
            or behavior_variants < 0:
        raise OmniscsError(f"behavior_variants must be a non-negative integer; got {behavior_variants!r}")
    if isinstance(appearance_variants, bool) or not isinstance(appearance_variants, (int, np.integer)) \
            or appearance_variants < 0:
        raise OmniscsError(f"appearance_variants must be a non-negative integer; got {appearance_variants!r}")
    edits = list(edits or [])
    agents = {a["track_id"]: a for a in agent_rows(scene)}
    inserted = tuple(sorted(int(e.track_id) for e in edits if isinstance(e, Insert)))
    clash = sorted(set(inserted) & set(agents))
    if clash:
        raise OmniscsError(f"insert edits reuse track id(s) {clash} that the scene already has; pick new ids")
    by_track = {t: es for t, es in _edited_tracks(edits).items() if t not in inserted}
    unknown = sorted(set(by_track) - set(agents))
    if unknown:
        raise OmniscsError(f"edits name track id(s) {unknown} that scene {scene.scene_id} does not have")
    cams = tuple(cameras or scene.camera_names)
    for c in cams:
        scene.camera(c)

    reasons: dict[int, str] = {}
    for tid, a in agents.items():
        moving = a["path_length_m"] > config.moving_path_length_m
        edited = tid in by_track
        # behaviour variants may move any vehicle (L_app renders them where they move): each needs a node
        behaviour = behavior_variants > 0 and a["category"] in VEHICLE_CATEGORIES
        # appearance variants may replace any vehicle's model (the object inherits its motion): each needs a node
        appearance = appearance_variants > 0 and a["category"] in VEHICLE_CATEGORIES
        if moving or edited or behaviour or appearance or config.every_track_a_node:
            reasons[tid] = "+".join(r for r, on in (("moving", moving), ("edited", edited), ("behavior", behaviour),
                                                    ("appearance", appearance)) if on) or "every-track"
    nodes = tuple(sorted(reasons))
    needs_360 = tuple(sorted(t for t, es in by_track.items()
                             if any(_turns_far(e, config.rotation_needing_360_deg) for e in es)))
    repair = repair_objects(agents, [e for e in edits if int(e.track_id) in by_track], config)
    frames = np.arange(scene.n_frames)
    if config.holdout_every and scene.n_frames >= config.holdout_every:
        held = frames[(frames + 1) % config.holdout_every == 0]
    else:
        held = frames[:0]
    train = np.setdiff1d(frames, held)
    area = modelled_area(scene, config.view_range_m)
    budget = int(np.clip(config.gaussians_per_m2 * area * np.sqrt(len(cams))
                         + config.gaussians_per_agent * (len(nodes) + len(inserted)),
                         config.min_gaussians, config.max_gaussians))
    stages = {
        "fit_nsg": bool(fit_nsg),
        "agent_models": bool(fit_nsg and (needs_360 or inserted)),
        "background_repair": bool(fit_nsg and repair),
        "behavior_variants": behavior_variants > 0,
        "appearance_variants": bool(fit_nsg and appearance_variants > 0),
        "render_annotate": bool(annotate and fit_nsg and (behavior_variants > 0 or appearance_variants > 0 or edits)),
    }
    return ScenePlan(
        scene_id=scene.scene_id, content_hash=scene.content_hash, agent_nodes=nodes, node_reasons=reasons,
        background_tracks=tuple(sorted(set(agents) - set(nodes))), needs_360=needs_360,
        background_repair=repair, inserted=inserted, cameras=cams,
        train_frames=tuple(int(f) for f in train), heldout_frames=tuple(int(f) for f in held),
        modelled_area_m2=area, gaussian_budget=budget, stages=stages,
    )
