"""nuScenes v1.0 writer: scene stores as a dataroot the nuscenes-devkit loads (all 13 tables, samples and sweeps).

Per scene: one log (and a map record per location, pointing at a small placeholder mask PNG written here: no
raster prior is made), one calibrated_sensor per camera and LIDAR_TOP, one ego_pose and one sample_data per frame and
sensor, keyframe samples every ``keyframe_every`` frames (default: the 2 Hz nuScenes rate) with the frames between
them as sweeps (``sweeps/``; their sample_token is the next keyframe's sample, the devkit's convention), and a
sample_annotation per keyframe and box, chained per instance. Tokens are md5 digests of what identifies a record,
so exports are reproducible. Coordinates: a recorded log with a nuScenes location keeps its dataset global frame
(``global_from_world`` of the manifest); every other scene is placed in a grid cell of the chosen nuScenes
``location`` and its roads go into that location's map expansion ``maps/expansion/<location>.json`` (placement,
time shifts and map records: ``omniscs.export.nuscenes_map``). Images are JPEG (quality ``JPEG_QUALITY``);
LIDAR_TOP sweeps are float32 x, y, z, intensity, ring in the LiDAR frame (ring is 0: the store does not keep it).
The LiDAR frame has nuScenes' axes (x to the ego's right, y forward, z up; ``nuscenes_lidar_mount``): the store's
LiDAR position with those axes unless its own mount already points x to the right (a recorded nuScenes log keeps
its calibration). Tools built on nuScenes read directions in that frame: UniAD's driving command is the lateral
(x) offset of the planned end point, its planning metric draws the ego box along y.

Estimated fields: ``visibility`` from the store's visible pixels over the boxes' image rectangles (v80-100 when the
store does not know them, or the value a nuScenes reader kept); ``attribute`` from the track's speed (or kept);
``num_lidar_pts`` counted in the LiDAR sweep when the store does not know it; ``num_radar_pts`` 0.

Like nuScenes' own annotation, an object is labelled from the keyframe where a sensor first captures it (LiDAR
points or visible pixels) to the one where a sensor last does, through occlusions between; an object no sensor
captures is not labelled (``seen_span``; ``keep_unseen`` keeps every box of the store).
"""
from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.export.common import (
    BOX_POINT_MARGIN_M,
    STILL_SPEED_MPS,
    attribute_lookup,
    box_poses,
    box_velocities,
    ego_from_lidar,
    encode_jpeg,
    encode_mask_png,
    token,
    visible_fraction,
    write_bytes,
)
from omniscs.export.nuscenes_map import DEFAULT_LOCATION, SCENE_SPACING_M, ScenePlacement, map_expansions, place_scenes
from omniscs.geometry import invert_transform, points_in_box
from omniscs.quaternions import rotmat_to_quat
from omniscs.scene.seen import captured, labelled
from omniscs.scene.sources.nuscenes import ATTRIBUTES, CATEGORIES, LIDAR_CHANNEL, TABLES, VISIBILITY
from omniscs.scene.store import Scene
from omniscs.untrusted import loads_json

#: nuScenes annotates keyframes at 2 Hz.
KEYFRAME_PERIOD_US = 500_000
DEFAULT_VERSION = "v1.0-trainval"
#: The synthetic world's asset kinds (the store's source_category) as nuScenes categories.
SOURCE_LABELS: dict[str, str] = {
    "sedan": "vehicle.car", "suv": "vehicle.car", "van": "vehicle.car", "pickup": "vehicle.car",
    "box_truck": "vehicle.truck", "bus": "vehicle.bus.rigid", "trailer": "vehicle.trailer",
    "excavator": "vehicle.construction", "wheel_loader": "vehicle.construction",
    "traffic_cone": "movable_object.trafficcone", "barrier": "movable_object.barrier",
    "debris": "movable_object.debris",
}
#: Project classes as nuScenes categories, for labels the table above does not know.
CATEGORY_LABELS: dict[str, str] = {
    "car": "vehicle.car", "truck": "vehicle.truck", "bus": "vehicle.bus.rigid", "trailer": "vehicle.trailer",
    "construction_vehicle": "vehicle.construction", "pedestrian": "human.pedestrian.adult",
    "motorcycle": "vehicle.motorcycle", "bicycle": "vehicle.bicycle", "traffic_cone": "movable_object.trafficcone",
    "barrier": "movable_object.barrier", "debris": "movable_object.debris",
}
#: Visible-fraction lower bounds of the visibility levels v40-60, v60-80, v80-100.
VISIBILITY_BOUNDS = (0.4, 0.6, 0.8)
#: Side length of the placeholder map mask (pixels).
MAP_MASK_PIXELS = 8
#: Floats per point in a written .pcd.bin.
LIDAR_VALUES_PER_POINT = 5


def nuscenes_label(category: str, source_category: str | None) -> str:
    """The nuScenes category of a store box; it always maps back to the same project class."""
    for candidate in (source_category, SOURCE_LABELS.get(source_category or "")):
        if candidate in CATEGORIES and CATEGORIES[candidate][1] == category:
            return candidate
    if category not in CATEGORY_LABELS:
        raise OmniscsError(f"category {category!r} has no nuScenes label")
    return CATEGORY_LABELS[category]


def channel_of(camera: str) -> str:
    return camera if camera.startswith("CAM_") else f"CAM_{camera.upper()}"


def _visibility_token(fraction: float | None) -> str:
    if fraction is None:
        return VISIBILITY[-1][0]
    level = sum(fraction >= b for b in VISIBILITY_BOUNDS)
    return VISIBILITY[level][0]


def _attribute_names(label: str, speed: float, track_moves: bool) -> list[str]:
    moving = speed >= STILL_SPEED_MPS
    if label in ("vehicle.bicycle", "vehicle.motorcycle"):
        return ["cycle.with_rider" if track_moves else "cycle.without_rider"]
    if label.startswith("vehicle."):
        return ["vehicle.moving" if moving else ("vehicle.stopped" if track_moves else "vehicle.parked")]
    if label.startswith("human.pedestrian"):
        return ["pedestrian.moving" if moving else "pedestrian.standing"]
    return []


#: nuScenes' LIDAR_TOP axes in the ego frame: x to the right, y forward, z up (columns: the LiDAR axes).
NUSCENES_LIDAR_AXES = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
#: A store's own LiDAR mount is kept when its x axis is within this angle of the ego's right (degrees).
LIDAR_AXES_TOLERANCE_DEG = 10.0


def nuscenes_lidar_mount(ego_from_lidar: np.ndarray) -> np.ndarray:  # [4, 4] -> [4, 4]
    """The exported LIDAR_TOP mount: ``ego_from_lidar`` as it is when its x axis points to the ego's right (within
    LIDAR_AXES_TOLERANCE_DEG), else the same position with nuScenes' axes."""
    mount = np.asarray(ego_from_lidar, np.float64)
    if float(mount[:3, 0] @ NUSCENES_LIDAR_AXES[:, 0]) >= np.cos(np.radians(LIDAR_AXES_TOLERANCE_DEG)):
        return mount.copy()
    out = np.eye(4)
    out[:3, :3] = NUSCENES_LIDAR_AXES
    out[:3, 3] = mount[:3, 3]
    return out


def keyframe_indices(timestamps_us: np.ndarray, keyframe_every: int | None) -> np.ndarray:
    """Every ``keyframe_every``-th frame from 0 (default: as many frames as make the 2 Hz nuScenes rate)."""
    if keyframe_every is None:
        dt = float(np.median(np.diff(timestamps_us))) if len(timestamps_us) > 1 else KEYFRAME_PERIOD_US
        keyframe_every = max(1, int(round(KEYFRAME_PERIOD_US / dt)))
    if keyframe_every < 1:
        raise OmniscsError(f"keyframe_every must be >= 1; got {keyframe_every}")
    return np.arange(0, len(timestamps_us), keyframe_every)


class _Tables:
    def __init__(self):
        self.rows: dict[str, list[dict]] = {t: [] for t in TABLES}
        self.maps: dict[str, dict] = {}

    def add(self, table: str, **record) -> str:
        self.rows[table].append(record)
        return record["token"]


def write_nuscenes(scenes: list[Scene], root: Path, version: str = DEFAULT_VERSION, keyframe_every: int | None = None,
                   progress: Callable[[int, int], None] | None = None, location: str = DEFAULT_LOCATION,
                   scene_spacing_m: float = SCENE_SPACING_M, keep_unseen: bool = False) -> Path:
    """Write ``scenes`` as a nuScenes dataroot at ``root`` (tables under ``root/version``, map expansions under
    ``root/maps/expansion``); scenes without a recorded nuScenes location go to ``location``, one grid cell of
    ``scene_spacing_m`` metres each. Boxes no sensor captured before an object is first seen or after it is last
    seen, and objects never seen, are left out as nuScenes' annotators leave them (``seen_span``) unless
    ``keep_unseen``."""
    if not isinstance(version, str) or not version.startswith("v1.0"):
        raise OmniscsError(f"nuScenes versions look like v1.0-mini or v1.0-trainval; got {version!r}")
    placements = place_scenes(scenes, location, scene_spacing_m)
    tables = _Tables()
    for name, (description, _) in CATEGORIES.items():
        tables.add("category", token=token("category", name), name=name, description=description)
    for name, description in ATTRIBUTES.items():
        tables.add("attribute", token=token("attribute", name), name=name, description=description)
    for vis_token, level, description in VISIBILITY:
        tables.add("visibility", token=vis_token, level=level, description=description)
    total = sum(s.n_frames for s in scenes)
    done = 0
    names = _scene_names(scenes)
    for scene, name, placement in zip(scenes, names, placements):
        for _ in _write_scene(scene, name, root, tables, keyframe_every, placement, keep_unseen):
            done += 1
            if progress:
                progress(done, total)
    for location, record in tables.maps.items():
        tables.add("map", **record)
        # one channel, as nuScenes' semantic priors: the devkit's MapMask indexes it as a 2-D binary mask
        mask = np.zeros((MAP_MASK_PIXELS, MAP_MASK_PIXELS), np.uint8)
        write_bytes(root / record["filename"], encode_mask_png(mask))
    for location, expansion in map_expansions(placements, [s.scene_id for s in scenes]).items():
        write_bytes(root / "maps" / "expansion" / f"{location}.json", json.dumps(expansion).encode())
    (root / version).mkdir(parents=True, exist_ok=True)
    for table, rows in tables.rows.items():
        (root / version / f"{table}.json").write_text(json.dumps(rows, indent=0))
    return root


def _scene_names(scenes: list[Scene]) -> list[str]:
    names = []
    for i, scene in enumerate(scenes, 1):
        own = scene.manifest.get("source_scene_id") if scene.manifest.get("dataset") == "nuscenes" else None
        names.append(own if own and own not in names else f"scene-{i:04d}")
    return names


def _write_scene(scene: Scene, scene_name: str, root: Path, tables: _Tables, keyframe_every: int | None,
                 placement: ScenePlacement, keep_unseen: bool):
    """Write one scene's files and records; yields once per frame written."""
    sid = scene.scene_id
    ts = scene.frames["timestamp_us"].to_numpy(np.int64) + placement.time_offset_us
    poses = placement.global_from_world @ scene.world_from_ego_all
    keys = keyframe_indices(ts, keyframe_every)
    is_key = np.zeros(len(ts), bool)
    is_key[keys] = True
    location = placement.location
    logfile = scene.manifest.get("logfile") if scene.manifest.get("dataset") == "nuscenes" else None
    logfile = logfile or f"omniscs-{sid}"
    log_token = token("log", sid)
    date = datetime.fromtimestamp(int(ts[0]) / 1e6, tz=timezone.utc).strftime("%Y-%m-%d")
    tables.add("log", token=log_token, logfile=logfile, vehicle="omniscs-ego", date_captured=date, location=location)
    map_record = tables.maps.setdefault(location, {"token": token("map", location), "log_tokens": [],
                                                   "category": "semantic_prior",
                                                   "filename": f"maps/{token('map', location)}.png"})
    map_record["log_tokens"].append(log_token)

    channels = {channel_of(c): c for c in scene.camera_names}
    if len(channels) != len(scene.camera_names):
        raise OmniscsError(f"scene {sid}: camera names {scene.camera_names} give duplicate nuScenes channels")
    sensors = dict(channels)
    if scene.has_lidar:
        sensors[LIDAR_CHANNEL] = None
    calib = {}
    known_sensors = {r["channel"] for r in tables.rows["sensor"]}
    lidar_mount = nuscenes_lidar_mount(ego_from_lidar(scene))
    for channel, cam in sensors.items():
        if channel not in known_sensors:
            tables.add("sensor", token=token("sensor", channel), channel=channel,
                       modality="lidar" if cam is None else "camera")
        ego_from_sensor = lidar_mount if cam is None else scene.ego_from_camera(cam)
        calib[channel] = tables.add(
            "calibrated_sensor", token=token("calibrated_sensor", sid, channel), sensor_token=token("sensor", channel),
            translation=ego_from_sensor[:3, 3].tolist(), rotation=rotmat_to_quat(ego_from_sensor[:3, :3]).tolist(),
            camera_intrinsic=[] if cam is None else scene.intrinsics(cam).tolist())

    scene_token = token("scene", sid)
    sample_tokens = [token("sample", sid, int(f)) for f in keys]
    for j, f in enumerate(keys):
        tables.add("sample", token=sample_tokens[j], timestamp=int(ts[f]), scene_token=scene_token,
                   prev=sample_tokens[j - 1] if j > 0 else "", next=sample_tokens[j + 1] if j + 1 < len(keys) else "")
    tables.add("scene", token=scene_token, log_token=log_token, nbr_samples=len(keys),
               first_sample_token=sample_tokens[0], last_sample_token=sample_tokens[-1], name=scene_name,
               description=f"omniscs {sid}")
    owner = np.searchsorted(keys, np.arange(len(ts)), side="left").clip(max=len(keys) - 1)

    lidar_from_ego = invert_transform(lidar_mount)
    for f in range(len(ts)):
        folder = "samples" if is_key[f] else "sweeps"
        for channel, cam in sensors.items():
            sd_token = token("sample_data", sid, channel, f)
            pose_token = tables.add("ego_pose", token=token("ego_pose", sid, channel, f),
                                    translation=poses[f, :3, 3].tolist(),
                                    rotation=rotmat_to_quat(poses[f, :3, :3]).tolist(), timestamp=int(ts[f]))
            if cam is None:
                filename = f"{folder}/{channel}/{logfile}__{channel}__{ts[f]}.pcd.bin"
                pts = scene.lidar(f)
                out = np.zeros((len(pts), LIDAR_VALUES_PER_POINT), np.float32)
                out[:, :3] = pts[:, :3].astype(np.float64) @ lidar_from_ego[:3, :3].T + lidar_from_ego[:3, 3]
                out[:, 3] = pts[:, 3]
                (root / filename).parent.mkdir(parents=True, exist_ok=True)
                out.tofile(root / filename)
                fmt, width, height = "pcd", 0, 0
            else:
                filename = f"{folder}/{channel}/{logfile}__{channel}__{ts[f]}.jpg"
                write_bytes(root / filename, encode_jpeg(scene.image(cam, f)))
                fmt, (width, height) = "jpg", scene.image_size(cam)
            tables.add("sample_data", token=sd_token, sample_token=sample_tokens[owner[f]], ego_pose_token=pose_token,
                       calibrated_sensor_token=calib[channel], timestamp=int(ts[f]), fileformat=fmt,
                       is_key_frame=bool(is_key[f]), height=height, width=width, filename=filename,
                       prev=token("sample_data", sid, channel, f - 1) if f > 0 else "",
                       next=token("sample_data", sid, channel, f + 1) if f + 1 < len(ts) else "")
        yield f
    _annotations(scene, keys, sample_tokens, tables, placement.global_from_world, keep_unseen)


def seen_span(rows, points_of: dict[int, int]) -> list:
    """Index labels of the keyframe box ``rows`` (one scene, sorted by frame) that an annotator labels
    (``omniscs.scene.seen``: per track, from the first box a sensor captured to the last), in the rows' order;
    ``points_of``: index label -> LiDAR points."""
    keep = labelled((i, int(t), int(f), captured(points_of[i], v))
                    for i, t, f, v in zip(rows.index, rows["track_id"], rows["frame_idx"], rows["visible_pixels"]))
    return [i for i in rows.index if i in keep]


def _annotations(scene: Scene, keys: np.ndarray, sample_tokens: list[str], tables: _Tables,
                 global_from_world: np.ndarray, keep_unseen: bool) -> None:
    sid = scene.scene_id
    boxes = scene.boxes.reset_index(drop=True)
    if len(boxes) == 0:
        return
    world_from_box = box_poses(boxes)
    global_from_box = global_from_world @ world_from_box
    velocity = box_velocities(scene)
    speed = np.linalg.norm(velocity[:, :2], axis=1)
    moves = {int(t): bool((speed[g.index] >= STILL_SPEED_MPS).any()) for t, g in boxes.groupby("track_id")}
    kept_visibility = attribute_lookup(scene, "visibility")
    kept_attributes = attribute_lookup(scene, "attribute")
    level_tokens = {level: tok for tok, level, _ in VISIBILITY}
    sample_of = {int(f): sample_tokens[j] for j, f in enumerate(keys)}
    lidar_cache: dict[int, np.ndarray] = {}
    chains: dict[int, list[str]] = {}
    categories: dict[int, str] = {}
    on_keys = boxes[boxes["frame_idx"].isin(keys)].sort_values(["frame_idx", "track_id"])
    points_of: dict[int, int] = {}
    for i, row in zip(on_keys.index, on_keys.itertuples()):
        f, n_points = int(row.frame_idx), int(row.num_lidar_points)
        if n_points < 0:
            if scene.has_lidar:
                if f not in lidar_cache:
                    lidar_cache = {f: scene.lidar(f)}
                ego_from_box = invert_transform(scene.world_from_ego(f)) @ world_from_box[i]
                size = np.array([row.length, row.width, row.height])
                n_points = int(points_in_box(lidar_cache[f], ego_from_box, size, BOX_POINT_MARGIN_M).sum())
            else:
                n_points = 0
        points_of[i] = n_points
    if not keep_unseen:
        on_keys = on_keys.loc[seen_span(on_keys, points_of)]
    for i, row in zip(on_keys.index, on_keys.itertuples()):
        f, tid = int(row.frame_idx), int(row.track_id)
        label = nuscenes_label(row.category, row.source_category)
        categories.setdefault(tid, label)
        n_points = points_of[i]
        if (f, tid) in kept_visibility and kept_visibility[(f, tid)] in level_tokens:
            vis = level_tokens[kept_visibility[(f, tid)]]
        else:
            vis = _visibility_token(visible_fraction(scene, row, world_from_box[i]))
        if (f, tid) in kept_attributes:
            names = [n for n in loads_json(kept_attributes[(f, tid)], f"the attributes of track {tid} at frame {f}",
                                           "the store's attributes.parquet is damaged", expect=list)
                     if n in ATTRIBUTES]
        else:
            names = _attribute_names(label, float(speed[i]), moves[tid])
        ann = token("sample_annotation", sid, tid, f)
        chains.setdefault(tid, []).append(ann)
        tables.add("sample_annotation", token=ann, sample_token=sample_of[f], instance_token=token("instance", sid, tid),
                   visibility_token=vis, attribute_tokens=[token("attribute", n) for n in names],
                   translation=global_from_box[i][:3, 3].tolist(), size=[row.width, row.length, row.height],
                   rotation=rotmat_to_quat(global_from_box[i][:3, :3]).tolist(), prev="", next="",
                   num_lidar_pts=n_points, num_radar_pts=0)
    by_token = {r["token"]: r for r in tables.rows["sample_annotation"][-len(on_keys):]} if len(on_keys) else {}
    for tid, chain in chains.items():
        for a, b in zip(chain, chain[1:]):
            by_token[a]["next"], by_token[b]["prev"] = b, a
        tables.add("instance", token=token("instance", sid, tid), category_token=token("category", categories[tid]),
                   nbr_annotations=len(chain), first_annotation_token=chain[0], last_annotation_token=chain[-1])

