"""Every behaviour variant of one scene rendered and annotated: the ego's solution first (the planning target of
each variant), then one scene store per variant, and the rows and pictures that describe them."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.annotate.config import AnnotateConfig
from omniscs.annotate.replay import Replay, write_replay
from omniscs.annotate.variant import (COMPOSED, DESIGNED, AnnotatedVariant, Reference, Sweep, background_tracks,
                                      variant_level, write_annotated_variant)
from omniscs.annotate.views import ViewAnnotator, background_members
from omniscs.errors import OmniscsError
from omniscs.gates import GateConfig, Verdict, edited_visible_frames, rendered_verdict
from omniscs.ids import check_id
from omniscs.nsg.graph import SceneGraph
from omniscs.progress import Progress, no_progress
from omniscs.scene.store import Scene
from omniscs.storage import atomic_write_json
from omniscs.untrusted import read_own_json

log = logging.getLogger(__name__)

#: What the annotate stage writes beside the variant stores: every catalog row and every variant's summary.
ROWS_JSON = "rows.json"


def variant_store_id(scene_id: str, variant_id: str) -> str:
    """The scene id of a variant's store (a safe id: it names a folder)."""
    return check_id("variant store id", f"{scene_id}-{variant_id}")


def annotate_variants(graph: SceneGraph, scene: Scene, variants: list[dict], out_dir: str | Path,
                      solve: Callable[[dict], object] | None = None, reference: Reference | None = None,
                      config: AnnotateConfig = AnnotateConfig(), picture: Callable | None = None,
                      describe: Callable | None = None, progress: Progress = no_progress,
                      replay: Replay | None = None, compose: Callable[[dict], object] | None = None,
                      reference_for: Callable[[dict], Reference | None] | None = None,
                      gates: GateConfig | None = None, wanted: dict[str, int] | None = None,
                      keep_failed: bool = False, lidar: Sweep | None = None,
                      lidar_for: Callable[[dict], Sweep | None] | None = None) -> list[AnnotatedVariant]:
    """Render and annotate ``variants`` (``variants.json`` entries of ``scene``) into ``out_dir/<store id>/``.

    ``solve(variant) -> EgoSolution`` gives the ego's avoiding trajectory (``scs.behavior.solution``): when it is
    solved the ego drives it in the rendered frames, else the ego keeps the variant's plan and the variant is kept
    as a test case (``ego_solved`` false). ``picture(variant, solution, png)`` draws the variant's BEV with the
    solution. ``describe(frames) -> world.json`` (procedural sources) goes into each variant's store. ``replay`` (the
    graph's logged views, ``omniscs.annotate.replay``) spares rendering them again for the fidelity proxies.
    Appearance and designed variants (``kind`` appearance, designed) keep the logged ego over every frame and are
    drawn by the graph ``compose(variant)`` returns (``omniscs.scs.appearance.compose.Composite``: the edited graph and the boxes of
    the nodes it changed), compared with ``reference_for(variant)`` (their exact images) when given. ``lidar`` and
    ``lidar_for(variant)`` give the exact LiDAR sweeps of behaviour and appearance variants (procedural scenes);
    without them the sweep is looked up in the graph's depth (``write_annotated_variant``).

    With ``gates`` (``omniscs.gates``) every rendered variant's summary gets its verdict (``gate``): what its
    behaviour stage found, the ego's solution, the edited object's visibility and the fidelity floors. A variant
    already failed before rendering (no collision, no ego solution) is not rendered unless ``keep_failed``; once
    ``wanted[level]`` variants of a level passed, its later (spare) candidates are not rendered. Those not rendered
    are listed in ``rows.json`` under ``rejected`` and ``spare``. Writes ``rows.json`` (samples, annotations,
    summaries) last."""
    out_dir = Path(out_dir)
    annotator = ViewAnnotator(graph, config, replay)
    members = background_members(graph, background_tracks(scene, graph))
    results, pictures, rejected, spare = [], [], [], []
    passed = {"behaviour": 0, "appearance": 0, "designed": 0}
    for i, variant in enumerate(variants):
        level = variant_level(variant)
        if gates is not None and wanted is not None and passed[level] >= wanted.get(level, len(variants)):
            spare.append({"variant_id": str(variant.get("variant_id")), "level": level})
            continue
        before = Verdict.from_dict(variant.get("gate")) if gates is not None else Verdict(True)
        if not before.passed and not keep_failed:
            rejected.append({"variant_id": str(variant.get("variant_id")), "level": level, **before.to_dict()})
            continue
        if variant.get("scene_id") not in (None, scene.scene_id):
            raise OmniscsError(f"variant {variant.get('variant_id')} belongs to scene {variant.get('scene_id')}, "
                               f"not {scene.scene_id}")
        vid = str(variant.get("variant_id"))
        store_id = variant_store_id(scene.scene_id, vid)
        done = i * 1.0

        def step(k, n, what=None, _done=done):
            progress(int(_done * 1000 + 1000 * k / max(n or 1, 1)), 1000 * len(variants), what)

        if variant.get("kind") in COMPOSED:
            if compose is None:
                raise OmniscsError(f"variant {vid} is an {level} variant; annotating it needs its composition "
                                   "(a model pool or the graph's own nodes)")
            composite = compose(variant)
            framed = dict(variant, source_frames=list(range(scene.n_frames)), ego=None)
            result = write_annotated_variant(
                composite.graph, scene, framed, out_dir / store_id, store_id,
                reference=reference_for(variant) if reference_for is not None else None, config=config,
                progress=step, annotator=ViewAnnotator(composite.graph, config, replay), members=members,
                describe=describe, edited=composite.boxes,
                lidar=lidar_for(variant) if lidar_for is not None else None)
            if gates is not None:
                tracks = variant.get("tracks") if level == DESIGNED else [variant["track_id"]]
                seen = {int(t): edited_visible_frames(result.annotations, int(t), gates) for t in tracks}
                least = min(seen, key=seen.get) if seen else None
                result.summary["edited_visible_frames"] = seen.get(least, 0)
                if level == DESIGNED:
                    result.summary["least_visible_track"] = least
                passed[level] += _judge(result, before, gates)
            results.append(result)
            continue
        solution = solve(variant) if solve is not None else None
        solved = solution is not None and bool(solution.solved)
        if gates is not None and gates.require_ego_solution and solution is not None and not solved \
                and not keep_failed:
            rejected.append({"variant_id": vid, "level": level, **(before & rendered_verdict(
                {"level": level, "ego_solved": False}, gates)).to_dict()})
            continue
        ego = np.asarray(solution.trajectory) if solved else None
        if solution is not None and not solved:
            log.warning("variant %s of %s: no comfortable collision-free ego trajectory (%s); kept as a test case "
                        "with the ego on its plan", vid, scene.scene_id, solution.reason)
        result = write_annotated_variant(graph, scene, variant, out_dir / store_id, store_id, ego_xy_yaw=ego,
                                         solution=None if solution is None else solution.to_dict(),
                                         reference=reference, config=config, progress=step, annotator=annotator,
                                         members=members, describe=describe, lidar=lidar)
        if picture is not None and solution is not None:
            pictures.append(Path(picture(variant, solution, out_dir / f"{store_id}-bev.png")).name)
        if gates is not None:
            passed[level] += _judge(result, before, gates)
        results.append(result)
    atomic_write_json(out_dir / ROWS_JSON, {
        "samples": [r for v in results for r in v.samples],
        "annotations": [r for v in results for r in v.annotations],
        "variants": [dict(v.summary, store_id=v.store.name, scene_id=scene.scene_id) for v in results],
        "bev": pictures, "rejected": rejected, "spare": spare, "wanted": wanted})
    # variants left unrendered (failed before rendering, spares not needed) never reported their share
    progress(1000 * len(variants), 1000 * len(variants), f"{len(results)} variant(s) rendered")
    return results


def _judge(result: AnnotatedVariant, before: Verdict, gates: GateConfig) -> bool:
    """Record a rendered variant's verdict in its summary (what was known before rendering and what the render
    shows); whether it passed."""
    verdict = before & rendered_verdict(result.summary, gates)
    result.summary["gate"] = verdict.to_dict()
    if not verdict.passed:
        log.warning("variant %s fails the quality gates: %s", result.summary.get("variant_id"),
                    "; ".join(verdict.reasons))
    return verdict.passed


def read_rows(out_dir: str | Path) -> dict:
    """The rows an annotate stage wrote (samples, annotations, variant summaries, BEV file names)."""
    return read_own_json(Path(out_dir) / ROWS_JSON, "run the annotate stage again", expect=dict)


def replay_scene(graph: SceneGraph, scene: Scene, out_dir: str | Path, progress: Progress = no_progress) -> dict:
    """Every logged view of ``scene`` rendered through ``graph`` unedited, with its PSNR against the logged image,
    written as a replay (``omniscs.annotate.replay``) into ``out_dir``."""
    if graph.scene_id != scene.scene_id:
        raise OmniscsError(f"scene graph of {graph.scene_id} does not belong to scene {scene.scene_id}")
    annotator = ViewAnnotator(graph)
    views = [(cam, f) for f in range(scene.n_frames) for cam in scene.camera_names]

    def rendered():
        for cam, f in views:
            view, rgb, logged_psnr = annotator.unedited(cam, f, lambda c=cam, t=f: scene.image(c, t), keep=False)
            yield cam, view.frame_idx, rgb, logged_psnr

    return write_replay(out_dir, rendered(), len(views), progress)
