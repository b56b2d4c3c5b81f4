"""1-to-N appearance variants of a scene: objects from the model pool put into the scene graph, each variant either
replacing a vehicle's model (the object inherits its motion) or inserting the object at a valid pose the placement
sampler found (upright, on its side, overturned); the specs on disk (``variants.json``) and their catalog rows."""
from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.nsg.edit import ModelResolver
from omniscs.progress import Progress, no_progress
from omniscs.edits import Insert, Remove, ReplaceModel, SetTrajectory, edit_to_dict, parse_edits
from omniscs.scs.appearance.compose import (DESIGNED, SPEC_VERSION, CompositeConfig, insert_variant,
                                            model_upright_box, new_track_id, replace_variant)
from omniscs.scs.appearance.placement import (PlacementConfig, PlacementError, check_placement, placement_context,
                                              sample_placements)
from omniscs.storage import atomic_write_json
from omniscs.taxonomy import VEHICLE_CATEGORIES

log = logging.getLogger(__name__)

VARIANTS_JSON = "variants.json"
CATALOG_ROWS = "catalog_rows.json"
#: Named poses of an inserted object: (roll, pitch) in degrees, in its own frame.
POSES: dict[str, tuple[float, float]] = {"upright": (0.0, 0.0), "on_side": (90.0, 0.0), "overturned": (180.0, 0.0)}


@dataclass(frozen=True)
class AppearanceConfig:
    """How a scene's appearance variants are drawn."""

    placements: tuple[str, ...] = ("insert", "replace")
    """Placement kinds, used in turn: insert (a new object at a sampled pose) and replace (a vehicle's model)."""
    poses: tuple[str, ...] = ("overturned", "on_side", "upright")
    """Poses of inserted objects, used in turn (names of POSES)."""
    seed: int = 0
    """Seed of the object order, the replaced vehicles and the placement sampler."""
    placement: PlacementConfig = field(default_factory=PlacementConfig)
    """Where inserted objects may go (distances, camera, visibility, clearance; ``omniscs.scs.appearance.placement``)."""
    composite: CompositeConfig = field(default_factory=CompositeConfig)
    """Colour fit and contact shadow of the composited objects."""

    def __post_init__(self) -> None:
        bad = [p for p in self.placements if p not in ("insert", "replace")]
        if not self.placements or bad:
            raise OmniscsError(f"appearance placements must be some of insert, replace; got {list(self.placements)}")
        bad = [p for p in self.poses if p not in POSES]
        if not self.poses or bad:
            raise OmniscsError(f"unknown pose(s) {bad or '(none given)'}; use some of {list(POSES)}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class AppearanceVariants:
    """What ``make_appearance_variants`` drew: the variant specs and the sampler's record."""

    variants: list[dict]
    placements: list[dict]  # per variant: the sampler's proposals, rejections per check (inserts) or the checks
    colour: dict | None      # the scene's colour transform (``ColourTransform.to_dict``)


def replacement_check(context, node, size, config: PlacementConfig):
    """Every placement check on ``node``'s whole trajectory with a box of ``size`` in its place (the node itself left
    out of the obstacles): whether an object of that size may replace it."""

    frames = np.flatnonzero(node.present)
    T = node.world_from_agent[frames]
    poses = np.stack([T[:, 0, 3], T[:, 1, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])], 1)
    others = dataclasses.replace(context, obstacles=context.obstacles.without([node.track_id]))
    return check_placement(others, np.asarray(size, dtype=np.float64), poses, config, frames=frames)


def _replaceable(graph, model, context, config: PlacementConfig) -> list[int]:
    """Vehicle nodes whose whole trajectory stays valid with the object's own size in their place."""
    return [node.track_id for node in graph.agents
            if node.category in VEHICLE_CATEGORIES and node.present.any()
            and replacement_check(context, node, model.size, config).ok]


def make_appearance_variants(graph, scene, resolve: ModelResolver, objects: list[str], n: int,
                             config: AppearanceConfig = AppearanceConfig(), colour: dict | None = None,
                             progress: Progress = no_progress, spare: int = 0) -> AppearanceVariants:
    """``n`` appearance variants of ``scene`` (ids ``a000``, ``a001``, ...) composing ``objects`` (model ids that
    ``resolve`` knows, used in a seeded order): placements and poses in turn (``config``). Inserts go where the
    placement sampler finds a valid pose (no overlap with any agent, static object, the ego or another inserted
    object at any frame; on the road; in view for enough frames); a replace takes a vehicle node whose trajectory
    the object's own size keeps valid, else the variant is an insert. An impossible request is an OmniscsError.
    ``spare`` more candidates follow the ``n`` (for the quality gates to fall back on; the render decides which
    pass); a spare that cannot be placed ends the list instead of failing it."""
    if n < 1:
        raise OmniscsError(f"ask for at least one appearance variant; got {n}")
    if not objects:
        raise OmniscsError("no object to composite: give model ids (pm-...) or a pool holding models")
    rng = np.random.default_rng(config.seed)
    order = [objects[i] for i in rng.permutation(len(objects))]
    context = placement_context(scene)
    variants, records, taken = [], [], set()
    total = n + max(0, int(spare))
    for i in range(total):
        progress(i, total, f"appearance variant {i + 1} of {total}")
        if i >= n:
            try:
                _draw_one(i, graph, scene, resolve, order, config, context, rng, variants, records, taken)
            except OmniscsError as exc:
                log.info("scene %s: %d spare appearance candidate(s) drawn; the next cannot be placed (%s)",
                         scene.scene_id, i - n, exc)
                break
            continue
        _draw_one(i, graph, scene, resolve, order, config, context, rng, variants, records, taken)
    progress(total, total, "appearance variants drawn")
    return AppearanceVariants(variants, records, colour)


def _draw_one(i: int, graph, scene, resolve: ModelResolver, order: list[str], config: AppearanceConfig, context,
              rng: np.random.Generator, variants: list[dict], records: list[dict], taken: set) -> None:
    """Appearance variant ``i`` (appended to ``variants``, the sampler's record to ``records``)."""
    model_id = order[i % len(order)]
    model = resolve(model_id)
    vid = f"a{i:03d}"
    placement = config.placements[i % len(config.placements)]
    if placement == "replace":
        used = {v["track_id"] for v in variants if v["placement"] == "replace"}
        options = [t for t in _replaceable(graph, model, context, config.placement) if t not in used]
        if options:
            track = int(options[int(rng.integers(len(options)))])
            variants.append(replace_variant(scene.scene_id, vid, track, model, model_id))
            records.append({"variant_id": vid, "placement": "replace", "track_id": track,
                            "replaceable": len(options)})
            return
        log.warning("variant %s of %s: no vehicle keeps a valid trajectory with %s (%.1f x %.1f x %.1f m) in its "
                    "place; the object is inserted instead", vid, scene.scene_id, model_id, *model.size)
    pose_name = config.poses[sum(v["placement"] == "insert" for v in variants) % len(config.poses)]
    roll, pitch = POSES[pose_name]
    failed = []
    for attempt in range(len(order)):  # an object that fits nowhere (longer than the road is wide) gives way
        if attempt:
            model_id = order[(i + attempt) % len(order)]
            model = resolve(model_id)
        box = model_upright_box(model, roll, pitch)
        try:
            result = sample_placements(context, box, 1, config.placement, int(rng.integers(2**31)))
            break
        except PlacementError as exc:
            failed.append({"object_id": model_id, "error": str(exc), **exc.result.to_dict()})
    else:
        raise OmniscsError(f"variant {vid} of {scene.scene_id}: none of the {len(order)} object(s) can be placed "
                           f"{pose_name.replace('_', ' ')}; the first: {failed[0]['error']}")
    if failed:
        log.warning("variant %s of %s: %d object(s) fit nowhere %s (e.g. %s); %s is placed instead", vid,
                    scene.scene_id, len(failed), pose_name, failed[0]["object_id"], model_id)
    x, y, z, yaw = (float(v) for v in result.placements[0])
    z -= 0.5 * float(box[2])  # the sampler gives the box centre; the variant stands on the road there
    track = new_track_id(scene, graph, taken)
    taken.add(track)
    variants.append(insert_variant(scene.scene_id, vid, track, model, model_id, x, y, z, yaw, roll, pitch))
    variants[-1]["pose"]["name"] = pose_name
    records.append({"variant_id": vid, "placement": "insert", "track_id": track, "pose_name": pose_name,
                    "objects_that_fit_nowhere": failed, **result.to_dict()})


def catalog_row(variant: dict, variants_json: Path) -> dict:
    """The ``variants`` row of an appearance variant (kind ``appearance``; the behaviour columns are null)."""
    pose = variant.get("pose") or {}
    return {"scene_id": variant["scene_id"], "variant_id": variant["variant_id"], "kind": "appearance",
            "adversary": int(variant["track_id"]), "placement": variant["placement"],
            "object_id": variant["object_id"], "object_category": variant["category"],
            "pose": pose.get("name", "replace" if variant["placement"] == "replace" else "upright"),
            "edits_json": json.dumps(variant["edits"], sort_keys=True), "success": None, "plausible": None,
            "reachable": None, "n_violations": 0, "violations": [], "variants_path": str(variants_json)}


#: Variant id of the designed variant a request's edits make (one per scene).
DESIGNED_ID = "d000"


def designed_variant(scene_id: str, edits: list[dict], pool: str | None = None,
                     colour: list | None = None) -> dict:
    """A user's edit spec (``edits``: edit objects, e.g. saved by ``omniscs view``) as one variant of ``scene_id``
    to render and annotate beside the drawn ones (kind ``designed``): composed like an appearance variant (models
    from ``pool``; inserted and re-modelled objects through the scene's ``colour`` transform [A | b] when given),
    the ego on its logged path. ``tracks``: the tracks it shows edited (every edited one not removed), whose
    visibility the quality gates check; ``adversary``: the first track given a new path, else the first inserted
    or re-modelled one, else the first edited."""
    parsed = parse_edits(edits)
    if not parsed:
        raise OmniscsError("a designed variant needs at least one edit")
    removed = {int(e.track_id) for e in parsed if isinstance(e, Remove)}
    tracks = list(dict.fromkeys(int(e.track_id) for e in parsed if int(e.track_id) not in removed))
    adversary = next((int(e.track_id) for kinds in ((SetTrajectory,), (Insert, ReplaceModel))
                      for e in parsed if isinstance(e, kinds)), int(parsed[0].track_id))
    objects = [e for e in parsed if isinstance(e, (Insert, ReplaceModel))]
    return {"scene_id": scene_id, "variant_id": DESIGNED_ID, "kind": DESIGNED, "spec_version": SPEC_VERSION,
            "edits": [edit_to_dict(e) for e in parsed], "tracks": tracks, "adversary": adversary,
            "object_id": objects[0].asset_id if objects else None,
            "category": getattr(objects[0], "category", None) if objects else None,
            "pool": None if pool is None else str(Path(pool).resolve()), "colour": colour}


def designed_catalog_row(variant: dict, variants_json: Path) -> dict:
    """The ``variants`` row of a designed variant (kind ``designed``, placement ``designed``)."""
    return {"scene_id": variant["scene_id"], "variant_id": variant["variant_id"], "kind": DESIGNED,
            "adversary": int(variant["adversary"]), "placement": DESIGNED, "object_id": variant.get("object_id"),
            "object_category": variant.get("category"), "pose": None,
            "edits_json": json.dumps(variant["edits"], sort_keys=True), "success": None, "plausible": None,
            "reachable": None, "n_violations": 0, "violations": [], "variants_path": str(variants_json)}


def write_appearance_variants(drawn: AppearanceVariants, out_dir: Path, published_dir: Path | None = None) -> dict:
    """``variants.json`` (specs, placements, colour transform) and ``catalog_rows.json`` into ``out_dir``; the rows
    point into ``published_dir`` (where ``out_dir`` ends up) when given."""
    out_dir = Path(out_dir)
    final = Path(published_dir or out_dir) / VARIANTS_JSON
    atomic_write_json(out_dir / VARIANTS_JSON, drawn.variants)
    atomic_write_json(out_dir / "placements.json", {"placements": drawn.placements, "colour": drawn.colour})
    rows = [catalog_row(v, final) for v in drawn.variants]
    atomic_write_json(out_dir / CATALOG_ROWS, rows)
    return {"variants": VARIANTS_JSON, "placements": "placements.json", "catalog_rows": CATALOG_ROWS}
