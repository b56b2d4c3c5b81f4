"""One variant rendered and annotated, written as a scene store (the project's one format, so every reader,
writer and exporter works on it unchanged) plus the rows of the ``samples`` and ``annotations`` catalog tables.

Beside the usual store files a variant store holds ``attributes.parquet`` (per frame and track the nuScenes
visibility level the exporter uses) and ``variant.json`` (the variant, the ego's solution, the driving command of
every frame, the source frames and the frames that were dropped because the ego left the fitted area)."""
from __future__ import annotations

import json
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.annotate.config import AnnotateConfig, visibility_level
from omniscs.annotate.fidelity import box_mask, feature_drift, finite_or_none, image_fidelity
from omniscs.annotate.frames import COMMANDS, VariantFrames, variant_frames
from omniscs.annotate.lidar import beam_directions, lidar_from_depth, lidar_from_views, points_in_boxes, ring_views
from omniscs.annotate.views import Instance, ViewAnnotation, ViewAnnotator, background_members
from omniscs.errors import OmniscsError
from omniscs.export.common import BOX_POINT_MARGIN_M, ego_from_lidar
from omniscs.geometry import invert_transform, make_transform, yaw_from_matrix
from omniscs.nsg.graph import SceneGraph
from omniscs.progress import Progress, no_progress
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene.sources.common import ATTRIBUTE_SCHEMA, ATTRIBUTES
from omniscs.nsg.observations import View
from omniscs.scene.store import CameraRecord, Scene, gt_path, image_path
from omniscs.scene.writer import SceneWriter

log = logging.getLogger(__name__)

VARIANT_JSON = "variant.json"
#: Views waiting for the writer thread at most (PNG and compressed ground truth; both release the GIL).
WRITE_QUEUE = 8
#: nuScenes' visibility level names, by level 1..4.
VISIBILITY_NAMES = {1: "v0-40", 2: "v40-60", 3: "v60-80", 4: "v80-100"}
#: A reference image for fidelity: (rgb uint8 [H, W, 3], instance int32 [H, W]) of a camera at a rendered frame.
Reference = Callable[[VariantFrames, str, int], tuple[np.ndarray, np.ndarray]]
#: The exact LiDAR sweep of a rendered frame: float32 [N, 4] (x, y, z in the ego frame, intensity 0..255).
Sweep = Callable[[VariantFrames, int], np.ndarray]


@dataclass(frozen=True)
class AnnotatedVariant:
    """What ``write_annotated_variant`` wrote."""

    store: Path
    samples: list[dict]
    annotations: list[dict]
    summary: dict


def _world_from_box(row) -> np.ndarray:  # -> [4, 4]
    R = quat_to_rotmat(np.array([row.qw, row.qx, row.qy, row.qz], dtype=np.float64))
    return make_transform(R, np.array([row.cx, row.cy, row.cz], dtype=np.float64))


def background_tracks(scene: Scene, graph: SceneGraph) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{track id: (world_from_box, size)} of the tracks left in the background (their first box: they do not move)."""
    out = {}
    nodes = set(graph.agent_ids)
    for tid, rows in scene.boxes.groupby("track_id"):
        if int(tid) in nodes:
            continue
        first = rows.sort_values("frame_idx").iloc[0]
        out[int(tid)] = (_world_from_box(first), first[["length", "width", "height"]].to_numpy(np.float64))
    return out


def write_annotated_variant(graph: SceneGraph, scene: Scene, variant: dict, out_dir: str | Path, store_id: str,
                            ego_xy_yaw: np.ndarray | None = None, solution: dict | None = None,
                            reference: Reference | None = None, config: AnnotateConfig = AnnotateConfig(),
                            progress: Progress = no_progress, annotator: ViewAnnotator | None = None,
                            members: dict | None = None, rig: list[CameraRecord] | None = None,
                            describe: Callable[[VariantFrames], str] | None = None,
                            edited: dict | None = None, lidar: Sweep | None = None) -> AnnotatedVariant:
    """Render every camera of every frame of ``variant`` through ``graph`` (the ego on ``ego_xy_yaw``, its solution,
    when given) with full ground truth, as the scene store ``out_dir`` (id ``store_id``). ``reference`` gives the
    exact image of a frame (procedural scenes) for fidelity; on every scene the viewpoint offset and the feature
    drift against the unedited render of the logged cameras are measured (``omniscs.annotate.fidelity``).
    ``annotator`` and ``members`` (background tracks' Gaussians) may be shared between variants of one graph.
    ``rig`` renders other cameras than the logged ones (e.g. a nuScenes-size rig; no exposure correction for a
    camera the fit never saw); fidelity is then not measured unless ``reference`` knows those cameras.
    ``describe(frames) -> world.json`` writes the variant's procedural world into its store (synthetic sources:
    its roads reach the exports' maps). ``edited`` gives the boxes of the nodes an appearance variant's edits made
    or changed (``variant_frames``); ``graph`` is then the edited graph. ``lidar`` gives the exact sweep of a frame
    (procedural scenes, ``config.lidar_source`` world); without it the sweep is looked up in the graph's depth (the
    ring, or the cameras with ``lidar_source`` cameras)."""
    started = time.perf_counter()
    if graph.scene_id != scene.scene_id:
        raise OmniscsError(f"scene graph of {graph.scene_id} does not belong to scene {scene.scene_id}")
    annotator = annotator or ViewAnnotator(graph, config)
    if members is None:
        members = background_members(graph, background_tracks(scene, graph))
    vf = variant_frames(scene, variant, frozenset(graph.agent_ids), ego_xy_yaw, config, edited)
    if vf.dropped_frames:
        log.warning("variant %s of %s: the ego leaves the fitted area (> %.1f m from every logged ego position) in "
                    "%d frame(s); those frames are not rendered", variant.get("variant_id"), scene.scene_id,
                    config.max_viewpoint_offset_m, len(vf.dropped_frames))
    if vf.n_frames == 0:
        raise OmniscsError(f"variant {variant.get('variant_id')} of {scene.scene_id}: the ego is outside the fitted "
                           "area in every frame; nothing can be rendered")
    fitted = {r.name for r in graph.cameras}
    cameras = list(rig) if rig is not None else [graph.camera(c) for c in scene.camera_names if c in fitted]
    adversary = int(variant.get("adversary", -1))
    moved = set(vf.moved)
    boxes = vf.boxes.copy()
    boxes["visible_pixels"] = 0
    vis_alpha: dict[tuple[int, int], list[tuple[float, float]]] = {}
    samples, annotations, fidelity = [], [], []
    render_s = label_s = write_s = lidar_s = 0.0
    lidar_mount = ego_from_lidar(scene)  # [4, 4] the log's LiDAR mount, or a nuScenes-like one when it has none
    ring = ring_views(config) if lidar is None and config.lidar_source != "cameras" else []
    beams = beam_directions(config) if ring else None
    source = {"kind": "variant", "scene_id": scene.scene_id, "variant_id": str(variant.get("variant_id")),
              "scene_content_hash": scene.content_hash}
    out_dir = Path(out_dir)
    total = vf.n_frames * len(cameras)
    pending: list[Future] = []  # image and ground-truth files encoded by a writer thread beside the rendering
    with SceneWriter(out_dir, store_id, source, overwrite=True) as writer, \
            ThreadPoolExecutor(1, thread_name_prefix="variant-writer") as pool:
        writer.set_frames(vf.timestamps_us, vf.world_from_ego)
        writer.set_cameras(cameras)
        writer.set_extra(source_scene_id=scene.scene_id, ego_from_lidar=lidar_mount.reshape(16).tolist(),
                         **_location(scene))
        if describe is not None and rig is None:
            writer.write_world_json(describe(vf))
        rows_by_frame = {t: g for t, g in boxes.groupby("frame_idx")}
        for t in range(vf.n_frames):
            f = int(vf.scene_frames[t])
            frame_rows = rows_by_frame.get(t, boxes.iloc[0:0])
            row_of = {int(r.track_id): r for r in frame_rows.itertuples()}  # track id -> its box row (Index = row)
            instances = [Instance(int(r.track_id), str(r.category), _world_from_box(r),
                                  np.array([r.length, r.width, r.height], dtype=np.float64),
                                  members.get(int(r.track_id)) if int(r.track_id) not in graph.agent_ids else None)
                         for r in frame_rows.itertuples()]
            depth_views = []
            for cam in cameras:
                tick = time.perf_counter()
                view = View(f, vf.world_from_ego[t] @ cam.ego_from_camera, np.array(cam.K, dtype=np.float64),
                            int(cam.width), int(cam.height),
                            cam.name if cam.name in fitted else None)
                ann = annotator.annotate(view, vf.node_poses[t], instances)
                tock = time.perf_counter()
                render_s += ann_render_seconds(annotator)
                label_s += (tock - tick) - ann_render_seconds(annotator)
                pending.append(pool.submit(_write_view, writer, cam.name, t, ann))
                while len(pending) > WRITE_QUEUE:  # bounded: wait for the oldest (its error surfaces here)
                    pending.pop(0).result()
                write_s += time.perf_counter() - tock
                depth_views.append((ann.depth, cam.K, cam.ego_from_camera))
                fid = {}
                measured = bool(config.fidelity_every) and t % config.fidelity_every == 0
                if measured and reference is not None:
                    ref_rgb, ref_instance = reference(vf, cam.name, t)
                    fid = image_fidelity(ann.rgb, ref_rgb, ref_instance >= 0)
                if measured and rig is None:
                    tick = time.perf_counter()
                    fid.update(unedited_fidelity(annotator, scene, cam.name, f, ann, moved))
                    render_s += time.perf_counter() - tick
                if fid:
                    fidelity.append(fid)
                samples.append(_sample_row(scene, variant, store_id, vf, t, cam.name, ann, fid))
                for label in ann.labels:
                    key = (t, label.track_id)
                    full = label.own_alpha / label.in_image_fraction if label.in_image_fraction > 0 else 0.0
                    vis_alpha.setdefault(key, []).append((label.visible_alpha, full))
                    annotations.append(_annotation_row(label, row_of[label.track_id], vf, t, cam.name, variant, store_id,
                                                       adversary, moved, config))
                progress(t * len(cameras) + cameras.index(cam) + 1, total, f"variant {variant.get('variant_id')}")
            tick = time.perf_counter()
            if lidar is not None:
                points = lidar(vf, t)
            elif ring:  # the 360° sensor: depth rendered in the ring of views at the mount, then the beams looked up
                world_from_lidar = vf.world_from_ego[t] @ lidar_mount
                ring_depth = [(annotator.depth(View(f, world_from_lidar @ r.lidar_from_view, r.K, r.width, r.height),
                                               vf.node_poses[t], min_alpha=config.lidar_depth_alpha,
                                               background_clearance_m=config.lidar_background_clearance_m),
                               r.K, r.lidar_from_view)
                              for r in ring]
                points = lidar_from_views(ring_depth, beams, lidar_mount, config.lidar_max_range_m,
                                          config.lidar_min_range_m)
            else:
                points = lidar_from_depth(depth_views, config)
            lidar_s += time.perf_counter() - tick
            tick = time.perf_counter()
            writer.write_lidar(t, points)
            if len(frame_rows):
                ego_from_world = invert_transform(vf.world_from_ego[t])
                ego_from_boxes = np.stack([ego_from_world @ _world_from_box(r) for r in frame_rows.itertuples()])
                sizes = frame_rows[["length", "width", "height"]].to_numpy(np.float64)
                # returns lie on the surfaces, the rendered (alpha-blended) ones a few centimetres either side:
                # counted with the slack the exporters and the procedural source count with
                boxes.loc[frame_rows.index, "num_lidar_points"] = points_in_boxes(points, ego_from_boxes, sizes,
                                                                                  BOX_POINT_MARGIN_M)
            label_s += time.perf_counter() - tick
        tick = time.perf_counter()
        for future in pending:
            future.result()
        write_s += time.perf_counter() - tick
        lidar_count = {(int(f), int(k)): int(n) for f, k, n in zip(boxes.frame_idx, boxes.track_id,
                                                                     boxes.num_lidar_points)}
        for row in annotations:  # the frame's LiDAR count, known once the frame's cameras are all rendered
            row["num_lidar_points"] = lidar_count[(row["frame_idx"], row["track_id"])]
        pixels = {}
        for row in annotations:
            pixels[(row["frame_idx"], row["track_id"])] = pixels.get((row["frame_idx"], row["track_id"]), 0) \
                + row["mask_pixels"]
        boxes["visible_pixels"] = [int(pixels.get((int(f), int(k)), 0)) for f, k in zip(boxes.frame_idx, boxes.track_id)]
        writer.set_boxes(boxes)
        attributes = _visibility_rows(boxes, vis_alpha)
        pq.write_table(pa.Table.from_pandas(attributes, schema=ATTRIBUTE_SCHEMA, preserve_index=False),
                       writer.tmp / ATTRIBUTES)
        summary = _summary(variant, vf, solution, fidelity, render_s, label_s, write_s, time.perf_counter() - started,
                           total, len(annotations), lidar_s,
                           "world" if lidar is not None else "ring" if ring else "cameras")
        (writer.tmp / VARIANT_JSON).write_text(json.dumps({
            "variant": variant, "ego_solution": solution, "scene_frames": vf.scene_frames.tolist(),
            "commands": [COMMANDS[c] for c in vf.commands], "dropped_frames": list(vf.dropped_frames),
            "summary": summary}, indent=1, allow_nan=False))
    for row in samples:
        row.update(variant_fidelity_psnr=summary["fidelity_psnr"], variant_feature_drift=summary["feature_drift"],
                   ego_solved=summary["ego_solved"])
    return AnnotatedVariant(out_dir, samples, annotations, summary)


def _write_view(writer: SceneWriter, camera: str, t: int, ann: ViewAnnotation) -> None:
    writer.write_image(camera, t, ann.rgb)
    writer.write_gt(camera, t, ann.depth, ann.instance, ann.semantic)


def unedited_fidelity(annotator: ViewAnnotator, scene: Scene, camera: str, frame: int, ann: ViewAnnotation,
                      moved: set[int]) -> dict:
    """The proxies of a rendered variant view that need no exact reference, both from the graph's unedited render
    of the same source frame and camera at the logged pose: ``feature_drift`` of the view against it, outside
    every pixel a moved agent covers in either (its mask, its projected box in the variant, its logged box in the
    unedited view): what the edit and the new viewpoint changed; and ``logged_psnr``, the unedited render against
    the logged image: how well the graph reproduces this frame at all (a view the fit trained on)."""
    logged, unedited, logged_psnr = annotator.unedited(camera, frame, lambda: scene.image(camera, frame))
    rects = [lab.box2d for lab in ann.labels if lab.track_id in moved and lab.box2d is not None]
    logged_rects = annotator.logged_rects(camera, frame, lambda: scene.boxes_at(frame))
    rects += [logged_rects[t] for t in sorted(moved) if t in logged_rects]
    skip = np.isin(ann.instance, sorted(moved)) | box_mask(ann.instance.shape, rects)
    drift = feature_drift(ann.rgb, unedited, ~skip) if unedited.shape == ann.rgb.shape else None
    return {"feature_drift": finite_or_none(drift), "logged_psnr": finite_or_none(logged_psnr)}


def ann_render_seconds(annotator: ViewAnnotator) -> float:
    return annotator.last_render_seconds


def _location(scene: Scene) -> dict:
    out = {}
    for key in ("location", "dataset", "global_from_world"):
        if scene.manifest.get(key) is not None:
            out[key] = scene.manifest[key]
    if out.get("dataset") is not None:  # a variant is not a log of that dataset: keep where it was, not its tables
        out["origin_dataset"] = out.pop("dataset")
    return out


def _visibility_rows(boxes: pd.DataFrame, vis_alpha: dict) -> pd.DataFrame:
    """Per frame and track the nuScenes visibility level over all cameras: the unoccluded alpha summed over the
    cameras, over the largest whole-object alpha one camera would see (own alpha over its in-image fraction)."""
    rows = []
    for f, tid in zip(boxes.frame_idx, boxes.track_id):
        seen = vis_alpha.get((int(f), int(tid)), [])
        full = max((b for _, b in seen), default=0.0)
        fraction = 0.0 if full <= 0 else min(1.0, sum(a for a, _ in seen) / full)
        rows.append({"frame_idx": int(f), "track_id": int(tid), "camera": "", "name": "visibility",
                     "value": VISIBILITY_NAMES[visibility_level(fraction)]})
    return pd.DataFrame(rows, columns=ATTRIBUTE_SCHEMA.names)


def _sample_row(scene: Scene, variant: dict, store_id: str, vf: VariantFrames, t: int, camera: str,
                ann: ViewAnnotation, fid: dict) -> dict:
    """A ``samples`` row; image and ground-truth paths are relative to the variant's store."""
    pose = vf.world_from_ego[t]
    return {"scene_id": scene.scene_id, "variant_id": str(variant.get("variant_id")), "store_id": store_id,
            "frame_idx": t, "scene_frame": int(vf.scene_frames[t]), "camera": camera,
            "timestamp_us": int(vf.timestamps_us[t]), "image_path": image_path(Path(), camera, t).as_posix(),
            "gt_path": gt_path(Path(), camera, t).as_posix(), "ego_x": float(pose[0, 3]), "ego_y": float(pose[1, 3]),
            "ego_yaw": float(yaw_from_matrix(pose[:3, :3])), "command": COMMANDS[int(vf.commands[t])],
            "n_boxes": len(ann.labels), "n_visible": sum(lab.mask_pixels > 0 for lab in ann.labels),
            "viewpoint_offset_m": float(vf.viewpoint_offset_m[t]), "fidelity_psnr": fid.get("psnr"),
            "fidelity_ssim": fid.get("ssim"), "fidelity_masked_psnr": fid.get("masked_psnr"),
            "fidelity_masked_ssim": fid.get("masked_ssim"), "feature_drift": fid.get("feature_drift"),
            "logged_psnr": fid.get("logged_psnr")}


def _annotation_row(label, row, vf: VariantFrames, t: int, camera: str, variant: dict,
                    store_id: str, adversary: int, moved: set[int], config: AnnotateConfig) -> dict:
    world_from_box = _world_from_box(row)
    ego_from_box = invert_transform(vf.world_from_ego[t]) @ world_from_box
    velocity = vf.velocities[row.Index] if row.Index < len(vf.velocities) else np.zeros(3)
    b = label.box2d
    tight = label.box2d_tight
    return {"scene_id": str(variant.get("scene_id")), "variant_id": str(variant.get("variant_id")),
            "store_id": store_id, "frame_idx": t, "camera": camera, "track_id": int(label.track_id),
            "category": str(row.category), "is_adversary": int(label.track_id) == adversary,
            "moved": int(label.track_id) in moved,
            "cx": float(row.cx), "cy": float(row.cy), "cz": float(row.cz), "length": float(row.length),
            "width": float(row.width), "height": float(row.height), "yaw": float(row.yaw),
            "ego_x": float(ego_from_box[0, 3]), "ego_y": float(ego_from_box[1, 3]), "ego_z": float(ego_from_box[2, 3]),
            "ego_yaw": float(yaw_from_matrix(ego_from_box[:3, :3])),
            "cam_x": float(label.camera_from_box[0, 3]), "cam_y": float(label.camera_from_box[1, 3]),
            "cam_z": float(label.camera_from_box[2, 3]),
            "x1": b[0], "y1": b[1], "x2": b[2], "y2": b[3],
            "tight_x1": None if tight is None else tight[0], "tight_y1": None if tight is None else tight[1],
            "tight_x2": None if tight is None else tight[2], "tight_y2": None if tight is None else tight[3],
            "mask_pixels": int(label.mask_pixels), "visible_fraction": float(label.visibility),
            "visibility_level": visibility_level(label.visibility), "in_image_fraction": float(label.in_image_fraction),
            "num_lidar_points": -1, "vx": float(velocity[0]), "vy": float(velocity[1]), "vz": float(velocity[2])}


#: ``kind`` of an appearance-level variant (``omniscs.scs.appearance``).
APPEARANCE = "appearance"
#: ``kind`` of a designed variant (a request's edit spec, ``omniscs.scs.appearance.variants.designed_variant``).
DESIGNED = "designed"
#: Variants composed from their edits over the graph (the logged ego), as against driven behaviour variants.
COMPOSED = (APPEARANCE, DESIGNED)


def variant_level(variant: dict) -> str:
    """The dataset level of a variant spec: ``appearance`` and ``designed`` (their ``kind``), else ``behaviour``."""
    kind = variant.get("kind")
    return kind if kind in COMPOSED else "behaviour"


def _summary(variant: dict, vf: VariantFrames, solution: dict | None, fidelity: list[dict], render_s: float,
             label_s: float, write_s: float, seconds: float, n_images: int, n_annotations: int,
             lidar_s: float, lidar_source: str) -> dict:
    def mean(key: str) -> float | None:
        values = [f[key] for f in fidelity if f.get(key) is not None]
        return float(np.mean(values)) if values else None

    return {"variant_id": str(variant.get("variant_id")),
            "level": variant_level(variant),
            "n_frames": vf.n_frames, "n_images": n_images,
            "n_annotations": n_annotations, "dropped_frames": len(vf.dropped_frames),
            "ego_solved": None if solution is None else bool(solution.get("solved")),
            "fidelity_psnr": mean("psnr"), "fidelity_ssim": mean("ssim"), "fidelity_masked_psnr": mean("masked_psnr"),
            "fidelity_masked_ssim": mean("masked_ssim"), "feature_drift": mean("feature_drift"),
            "logged_psnr": mean("logged_psnr"),
            "fidelity_frames": len(fidelity),
            "max_viewpoint_offset_m": float(vf.viewpoint_offset_m.max()),
            "render_seconds": render_s, "annotate_seconds": label_s, "write_seconds": write_s,
            "lidar_seconds": lidar_s, "lidar_source": lidar_source, "seconds": seconds}
