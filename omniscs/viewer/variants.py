"""The variants of a scene (a ``variants.json`` of the behaviour or appearance stage) as the viewer shows them: an
appearance variant is its edit list; a behaviour variant moves the agent nodes it names along its trajectories
(placed as the render-and-annotate stage places them: upright at its (x, y, yaw), at the node's own height; frames it
leaves out keep the logged pose) and puts the ego on its plan."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from omniscs.edits import Edit, SetTrajectory, parse_edits
from omniscs.errors import OmniscsError
from omniscs.geometry import yaw_from_matrix
from omniscs.nsg.graph import SceneGraph

#: The file of a stage's variants in its folder.
VARIANTS_JSON = "variants.json"


def read_variants(path: str | Path) -> list[dict]:
    """The variants listed in ``path`` (a ``variants.json``, or the folder holding one); each needs a
    ``variant_id``. Anything else is one OmniscsError."""
    from omniscs.untrusted import read_json

    path = Path(path)
    if path.is_dir():
        path = path / VARIANTS_JSON
    if not path.is_file():
        raise OmniscsError(f"{path} does not exist; give a variants.json of the behaviour or appearance stage (or "
                           "its folder)")
    variants = read_json(path, "give a variants.json written by omniscs (a list of variants)", what="variants file")
    if not isinstance(variants, list) or not all(isinstance(v, dict) and "variant_id" in v for v in variants):
        raise OmniscsError(f"{path} is not a list of variants with a variant_id each; give a variants.json written "
                           "by the behaviour or appearance stage")
    return variants


def is_behaviour(variant: dict) -> bool:
    return "agents" in variant and "edits" not in variant


def variant_edits(graph: SceneGraph, variant: dict) -> list[Edit]:
    """The edits that make ``graph`` show ``variant``: an appearance variant's own edit list, or for a behaviour
    variant a ``set_trajectory`` of every agent node it moves."""
    if not is_behaviour(variant):
        return parse_edits(variant.get("edits") or [])
    steps = variant.get("source_frames")
    if steps is None:
        raise OmniscsError(f"variant {variant.get('variant_id')} has no scene frames (its log was resampled to the "
                           "behaviour model's time step); it cannot be shown on the fitted graph")
    step_of = {int(f): k for k, f in enumerate(steps)}
    out: list[Edit] = []
    for tid_text, trajectory in sorted((variant.get("agents") or {}).items(), key=lambda kv: int(kv[0])):
        tid = int(tid_text)
        if tid not in graph.agent_ids:
            continue  # a track left in the background cannot move (the stage keeps its logged box too)
        node = graph.agent(tid)
        waypoints = []
        for f in range(graph.n_frames):
            k = step_of.get(f)
            pose = trajectory[k] if k is not None and k < len(trajectory) else None
            if pose is not None and node.present[f]:
                x, y, yaw = (float(v) for v in pose)
                waypoints.append((x, y, float(node.world_from_agent[f, 2, 3]), yaw))
            elif node.present[f]:
                T = node.world_from_agent[f]
                waypoints.append((float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), float(yaw_from_matrix(T[:3, :3]))))
            else:
                waypoints.append(None)
        out.append(SetTrajectory(tid, tuple(waypoints)))
    return parse_edits(out)


def variant_ego(graph: SceneGraph, variant: dict) -> np.ndarray | None:  # -> [F, 4, 4] or None (the logged ego)
    """The ego's poses under a behaviour variant's plan (``omniscs.scs.behavior.render_consistency``), else None."""
    if not is_behaviour(variant) or variant.get("ego") is None:
        return None
    from omniscs.scs.behavior.render_consistency import variant_ego_poses

    return variant_ego_poses(variant, graph.world_from_ego)


def variant_summary(variant: dict) -> str:
    """The variant's figures as one Markdown paragraph (what the catalog's ``variants`` table holds)."""
    vid = variant.get("variant_id")
    if not is_behaviour(variant):
        return (f"**{vid}** (appearance, {variant.get('placement', '?')}): {variant.get('category', '?')} "
                f"`{variant.get('object_id', '?')}` as track {variant.get('track_id', '?')}; "
                f"{len(variant.get('edits') or [])} edit(s)")
    parts = [f"**{vid}** (behaviour, {variant.get('kind', '?')}): adversary track {variant.get('adversary', '?')}"]
    if variant.get("collision_time_s") is not None:
        parts.append(f"contact at {float(variant['collision_time_s']):.1f} s")
    for key, label in (("success", "reaches the ego"), ("plausible", "plausible")):
        if key in variant:
            parts.append(f"{label}: {'yes' if variant[key] else 'no'}")
    if variant.get("min_distance_m") is not None:
        parts.append(f"closest {float(variant['min_distance_m']):.2f} m")
    return "; ".join(parts)
