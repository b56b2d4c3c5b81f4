"""Scene stores (annotated variants, logs) as OpenSCENARIO 1.2 scenarios (``.xosc``) on OpenDRIVE road networks
(``.xodr``, ``omniscs.export.opendrive``), written with ``scenariogeneration``; and a reader of what was written.

**Frames and units.** OpenSCENARIO's world frame is right-handed with z up, and a WorldPosition's heading ``h`` is
counter-clockwise about +z from +x, pitch ``p`` about the entity's y' and roll ``r`` about its x'' (right-hand rule,
applied in the order h, p, r: R = Rz(h) Ry(p) Rx(r)). That is our world frame and ``geometry.rotmat_from_euler``'s
order, so world coordinates are written unchanged; h, p, r are read off each rotation matrix (``hpr_from_matrix``).
Headings along a trajectory are unwrapped (no jump of 2 pi between vertices, so a player never interpolates a spin).
Times are seconds since the scene's first frame: (timestamp_us - first timestamp_us) / 1e6.

**Reference points.** OpenSCENARIO places an entity by its reference point and puts its BoundingBox ``Center``
relative to it in the entity's frame. The ego's reference point is our ego frame's origin, the rear axle on the
ground (OpenSCENARIO puts a vehicle's reference point at its rear axle's centre; players such as esmini take it on
the ground, their catalogues' BoundingBox Center z being half the height); its box centre lies
``ego_centre_ahead_m`` ahead and half its height up. Every other entity's reference point is its box centre moved half the box height down its own z axis
(the middle of the box's bottom face); its Center is (0, 0, height / 2).

**Entities.** The ego, and one ScenarioObject per track of the store: Vehicles (car, truck, bus, trailer,
construction vehicle as truck, motorcycle as motorbike, bicycle), Pedestrians and MiscObjects (cones, barriers,
debris; and the objects an appearance variant inserted standing still, as obstacles with their full pose: an
overturned truck keeps its roll). Each gets a TeleportAction to its first pose in the Init; each that moves gets a
FollowTrajectoryAction (following mode position) along a Polyline of its logged (or adversarial, or solved)
poses with a time per vertex, Timing absolute (scale 1, offset 0). A track absent at the first frame waits at its
first pose until its first time, and stays at its last pose after it; the scenario stops after the last frame.
Vehicle performance and axles are nominal (``OpenScenarioConfig``): players that follow trajectories by position
do not use them. The ego's Vehicle carries the property ``type = ego_vehicle``, by which CARLA's ScenarioRunner
tells the ego from the other actors.

**Behaviour variants never rendered** (``variants.json`` of ``omniscs scs behavior``: planar box centres and yaws
per step) are written the same way on the scene store they were made from, which gives each track's category and
height and the heights above ground (``behaviour_variant_entities``).

**Road network check.** Every pose of every entity (its box centre) must lie on the scene's road network (drivable
area or sidewalk, within ``road_tolerance_m``); a variant whose trajectory leaves it is refused with the entity and
time.
"""
from __future__ import annotations

import datetime
import hashlib
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.edits import Insert, parse_edits
from omniscs.errors import OmniscsError
from omniscs.export.opendrive import RoadNetwork, road_network_of, road_source_id
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene.store import Scene
from omniscs.untrusted import read_json

#: OpenSCENARIO version written (1.2: esmini and ASAM's checker read it; Priority override needs 1.2).
OSC_MAJOR, OSC_MINOR = 1, 2
#: The variant description a variant store holds beside its tables (``omniscs.annotate.variant``).
VARIANT_JSON = "variant.json"
#: What each export folder holds besides the scenario and road files.
INDEX_JSON = "index.json"
#: Our category -> (OpenSCENARIO object type, its category).
OSC_CATEGORIES: dict[str, tuple[str, str]] = {
    "car": ("Vehicle", "car"), "truck": ("Vehicle", "truck"), "bus": ("Vehicle", "bus"),
    "trailer": ("Vehicle", "trailer"), "construction_vehicle": ("Vehicle", "truck"),
    "motorcycle": ("Vehicle", "motorbike"), "bicycle": ("Vehicle", "bicycle"),
    "pedestrian": ("Pedestrian", "pedestrian"),
    "traffic_cone": ("MiscObject", "obstacle"), "barrier": ("MiscObject", "barrier"),
    "debris": ("MiscObject", "obstacle"),
}
#: What an appearance variant's inserted static object becomes.
INSERTED_OBJECT = ("MiscObject", "obstacle")


@dataclass(frozen=True)
class OpenScenarioConfig:
    """How scene stores are written as OpenSCENARIO (the ego's box: ``scs.behavior.tracks.EgoBox`` and the
    placement's EGO_HEIGHT_M, the values the synthetic ego is built with; a test keeps them equal)."""

    ego_length: float = 4.6
    """Ego box length, metres."""
    ego_width: float = 1.9
    """Ego box width, metres."""
    ego_height: float = 1.6
    """Ego box height, metres."""
    ego_centre_ahead_m: float = 1.3
    """How far the ego's box centre lies ahead of the ego frame origin (the rear axle), metres."""
    road_tolerance_m: float = 0.1
    """How far outside the road network (drivable area and sidewalks) a box centre may lie, metres."""
    still_tolerance_m: float = 1e-3
    """A track whose poses all lie within this of its first (and turn less than it, in radians) gets no
    trajectory, only its initial position."""
    max_speed_mps: float = 70.0
    """Nominal Vehicle performance: top speed, m/s."""
    max_acceleration_mps2: float = 10.0
    """Nominal Vehicle performance: acceleration, m/s^2."""
    max_deceleration_mps2: float = 10.0
    """Nominal Vehicle performance: deceleration, m/s^2."""
    wheelbase_fraction: float = 0.6
    """Nominal axles: wheelbase as a fraction of the box length (centred in the box; the ego's rear axle at 0)."""
    wheel_diameter_m: float = 0.6
    """Nominal axles: wheel diameter, metres."""
    pedestrian_mass_kg: float = 80.0
    """Pedestrian mass (a required attribute), kg."""
    object_mass_kg: float = 50.0
    """MiscObject mass (a required attribute), kg."""


@dataclass(frozen=True)
class ScenarioEntity:
    """One entity of a scenario: what it is, its box and its poses (world frame, reference point)."""

    name: str
    """ScenarioObject name (unique in the scenario): "ego", "<category>_<track id>" or "object_<track id>"."""
    track_id: int
    """The store's track id; -1 for the ego."""
    object_type: str
    """"Vehicle", "Pedestrian" or "MiscObject"."""
    category: str
    """The OpenSCENARIO category of that type (VehicleCategory, PedestrianCategory, MiscObjectCategory)."""
    size: np.ndarray
    """[3] length, width, height of the BoundingBox, metres (a track's first box: recorded sizes vary a little)."""
    centre: np.ndarray
    """[3] the BoundingBox Center in the entity's frame relative to its reference point, metres."""
    times_s: np.ndarray
    """[T] seconds since the scene's first frame."""
    poses: np.ndarray
    """[T, 6] x, y, z (reference point, world, metres), h, p, r (radians, headings unwrapped along the track)."""
    moves: bool
    """Whether it gets a FollowTrajectoryAction (else only its initial TeleportAction)."""


def hpr_from_matrix(R: np.ndarray) -> np.ndarray:  # [..., 3, 3] -> [..., 3] heading, pitch, roll (radians)
    """The angles of R = Rz(h) Ry(p) Rx(r) (OpenSCENARIO's order); at pitch +-90 deg the roll is set to 0."""
    R = np.asarray(R, np.float64)
    cos_p = np.hypot(R[..., 0, 0], R[..., 1, 0])
    p = np.arctan2(-R[..., 2, 0], cos_p)
    locked = cos_p < 1e-9
    h = np.where(locked, np.arctan2(-R[..., 0, 1], R[..., 1, 1]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    r = np.where(locked, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    return np.stack([h, p, r], axis=-1)


def _unwrapped(poses: np.ndarray) -> np.ndarray:  # [T, 6] -> [T, 6] with h, p, r continuous along T
    out = poses.copy()
    out[:, 3:] = np.unwrap(out[:, 3:], axis=0)
    return out


def inserted_static_tracks(scene: Scene) -> set[int]:
    """Track ids an appearance or designed variant inserted standing still (from the store's variant.json: an
    appearance variant's static insert, a designed variant's inserts at one pose; empty otherwise)."""
    path = scene.path / VARIANT_JSON
    if not path.exists():
        return set()
    record = read_json(path, f"the variant store {scene.path} is damaged; build it again", expect=dict,
                       what="variant description")
    variant = record.get("variant")
    if isinstance(variant, dict) and variant.get("kind") == "designed":
        try:
            return {int(e.track_id) for e in parse_edits(variant.get("edits") or [])
                    if isinstance(e, Insert) and e.pose is not None}
        except OmniscsError as exc:
            raise OmniscsError(f"{path}: the designed variant's edits are damaged ({exc}); build the variant again") \
                from None
    if not isinstance(variant, dict) or variant.get("kind") != "appearance" or variant.get("placement") != "insert":
        return set()
    pose = variant.get("pose")
    if not isinstance(pose, dict) or not pose.get("static"):
        return set()
    track = variant.get("track_id")
    if not isinstance(track, int) or isinstance(track, bool):
        raise OmniscsError(f"{path}: the inserted object's track_id is {track!r}, not an integer; build the variant "
                           "again")
    return {track}


def scenario_entities(scene: Scene, config: OpenScenarioConfig = OpenScenarioConfig()) -> list[ScenarioEntity]:
    """The ego and every track of a scene store as scenario entities (see the module docstring)."""
    ts = scene.frames["timestamp_us"].to_numpy(np.int64)
    if len(ts) == 0:
        raise OmniscsError(f"scene {scene.scene_id} has no frame; nothing to export")
    times = (ts - ts[0]) / 1e6  # divided, not multiplied by 1e-6: whole tenths stay exact decimals
    world_from_ego = np.asarray(scene.world_from_ego_all, np.float64)
    ego_poses = np.concatenate([world_from_ego[:, :3, 3], hpr_from_matrix(world_from_ego[:, :3, :3])], axis=1)
    ego = ScenarioEntity("ego", -1, "Vehicle", "car", np.array([config.ego_length, config.ego_width,
                                                                config.ego_height]),
                         np.array([config.ego_centre_ahead_m, 0.0, config.ego_height / 2]), times,
                         _unwrapped(ego_poses), len(times) > 1)
    entities = [ego]
    inserted = inserted_static_tracks(scene)
    for track_id, rows in scene.boxes.groupby("track_id", sort=True):
        rows = rows.sort_values("frame_idx")
        track_id = int(track_id)
        category = str(rows.category.iloc[0])
        if track_id in inserted:
            object_type, osc_category = INSERTED_OBJECT
            name = f"object_{track_id}"
        elif category in OSC_CATEGORIES:
            object_type, osc_category = OSC_CATEGORIES[category]
            name = f"{category}_{track_id}"
        else:
            raise OmniscsError(f"scene {scene.scene_id}: track {track_id} has category {category!r}, which has no "
                               f"OpenSCENARIO counterpart here; known: {sorted(OSC_CATEGORIES)}")
        size = rows[["length", "width", "height"]].to_numpy(np.float64)
        centres = rows[["cx", "cy", "cz"]].to_numpy(np.float64)
        R = quat_to_rotmat(rows[["qw", "qx", "qy", "qz"]].to_numpy(np.float64))  # [T, 3, 3]
        height = size[0, 2]
        reference = centres - R[:, :, 2] * (height / 2)  # the middle of the box's bottom face
        poses = _unwrapped(np.concatenate([reference, hpr_from_matrix(R)], axis=1))
        moves = bool(len(poses) > 1 and (np.abs(poses - poses[0]).max(axis=0) > config.still_tolerance_m).any())
        entities.append(ScenarioEntity(name, track_id, object_type, osc_category, size[0].copy(),
                                       np.array([0.0, 0.0, height / 2]),
                                       times[rows.frame_idx.to_numpy(np.int64)], poses, moves))
    return entities


def _spec_rows(rows, what: str) -> tuple[np.ndarray, np.ndarray]:  # -> xy yaw [S, 3] (NaN where absent), present
    if not isinstance(rows, list):
        raise OmniscsError(f"{what} is not a list of [x, y, yaw] rows")
    out = np.full((len(rows), 3), np.nan)
    for i, row in enumerate(rows):
        if row is None:
            continue
        if not isinstance(row, list) or len(row) != 3 or not all(isinstance(v, (int, float)) and
                                                                 not isinstance(v, bool) for v in row):
            raise OmniscsError(f"{what}: step {i} is {row!r}, not [x, y, yaw] or null")
        out[i] = row
    return out, np.isfinite(out).all(axis=1)


def behaviour_variant_entities(spec: dict, scene: Scene, config: OpenScenarioConfig = OpenScenarioConfig()
                               ) -> list[ScenarioEntity]:
    """The entities of a behaviour variant that was never rendered (one ``variants.json`` entry of ``omniscs scs
    behavior``: box centres and yaws per step, planar) on its source scene store, which gives each track's category
    and height and every height above the ground (at the variant's source frames; the track's median where the
    variant was resampled). The ego's rows are its box centres ``ego_centre_ahead_of_origin_m`` ahead of its
    reference point."""
    vid = spec.get("variant_id") if isinstance(spec, dict) else None
    what = f"behaviour variant {vid!r}"
    try:
        stamps = np.asarray(spec["timestamps_us"], np.int64)
        ahead = float(spec.get("ego_centre_ahead_of_origin_m", config.ego_centre_ahead_m))
        agents, sizes = spec["agents"], spec["sizes"]
        frames = spec.get("source_frames")
    except (KeyError, TypeError, ValueError) as exc:
        raise OmniscsError(f"{what} lacks a readable {exc} field; write the variants again with `omniscs scs "
                           "behavior`") from None
    if spec.get("scene_id") != scene.scene_id:
        raise OmniscsError(f"{what} belongs to scene {spec.get('scene_id')!r}, not to {scene.scene_id}; give the "
                           "scene store the variants were made from")
    if len(stamps) == 0 or np.any(np.diff(stamps) <= 0):
        raise OmniscsError(f"{what}: timestamps_us must be strictly increasing and not empty")
    times = (stamps - stamps[0]) / 1e6
    frames = None if frames is None else np.asarray(frames, np.int64)
    if frames is not None and (len(frames) != len(stamps) or frames.min() < 0 or frames.max() >= scene.n_frames):
        raise OmniscsError(f"{what}: source_frames do not name frames of {scene.scene_id}")
    ego_rows, ego_present = _spec_rows(spec.get("ego"), f"{what} ego")
    if len(ego_rows) != len(stamps) or not ego_present.all():
        raise OmniscsError(f"{what}: the ego needs one [x, y, yaw] row per timestamp")
    ego_z = scene.world_from_ego_all[frames, 2, 3] if frames is not None else \
        np.full(len(stamps), float(np.median(scene.world_from_ego_all[:, 2, 3])))
    yaw = ego_rows[:, 2]
    ego_poses = np.stack([ego_rows[:, 0] - ahead * np.cos(yaw), ego_rows[:, 1] - ahead * np.sin(yaw), ego_z, yaw,
                          0 * yaw, 0 * yaw], axis=1)
    entities = [ScenarioEntity("ego", -1, "Vehicle", "car",
                               np.array([config.ego_length, config.ego_width, config.ego_height]),
                               np.array([ahead, 0.0, config.ego_height / 2]), times, _unwrapped(ego_poses),
                               len(times) > 1)]
    boxes = scene.boxes
    for key in sorted(agents, key=lambda k: int(k) if str(k).lstrip("-").isdigit() else 0):
        if not str(key).lstrip("-").isdigit():
            raise OmniscsError(f"{what}: agent key {key!r} is not a track id")
        track_id = int(key)
        rows = boxes[boxes.track_id == track_id].sort_values("frame_idx")
        if rows.empty:
            raise OmniscsError(f"{what}: track {track_id} is not in scene {scene.scene_id}; give the scene store "
                               "the variants were made from")
        xyyaw, present = _spec_rows(agents[key], f"{what} track {track_id}")
        if len(xyyaw) != len(stamps):
            raise OmniscsError(f"{what}: track {track_id} has {len(xyyaw)} rows for {len(stamps)} timestamps")
        if not present.any():
            continue
        category = str(rows.category.iloc[0])
        if category not in OSC_CATEGORIES:
            raise OmniscsError(f"scene {scene.scene_id}: track {track_id} has category {category!r}, which has no "
                               f"OpenSCENARIO counterpart here; known: {sorted(OSC_CATEGORIES)}")
        height = float(rows.height.iloc[0])
        length, width = (float(v) for v in sizes.get(str(key), rows[["length", "width"]].iloc[0].tolist()))
        bottom = rows.cz.to_numpy(np.float64) - height / 2
        by_frame = dict(zip(rows.frame_idx.to_numpy(np.int64), bottom))
        z = np.array([by_frame.get(int(f), float(np.median(bottom))) for f in frames]) if frames is not None else \
            np.full(len(stamps), float(np.median(bottom)))
        poses = np.stack([xyyaw[:, 0], xyyaw[:, 1], z, xyyaw[:, 2], 0 * z, 0 * z], axis=1)[present]
        poses = _unwrapped(poses)
        object_type, osc_category = OSC_CATEGORIES[category]
        moves = bool(len(poses) > 1 and (np.abs(poses - poses[0]).max(axis=0) > config.still_tolerance_m).any())
        entities.append(ScenarioEntity(f"{category}_{track_id}", track_id, object_type, osc_category,
                                       np.array([length, width, height]), np.array([0.0, 0.0, height / 2]),
                                       times[present], poses, moves))
    return entities


def write_behaviour_variants(specs: list, scene: Scene, root: Path, config: OpenScenarioConfig = OpenScenarioConfig(),
                             nuscenes_maps: str | Path | None = None) -> dict:
    """Write every behaviour variant of ``specs`` (a ``variants.json``) made from ``scene`` as
    ``<scene id>-<variant id>.xosc`` into ``root`` (an export's temporary folder) beside the scene's road network and
    ``index.json``; every variant is checked before anything is written."""
    import json

    if not isinstance(specs, list) or not specs:
        raise OmniscsError("variants.json holds no variant (a list of variants is expected); write the variants "
                           "again with `omniscs scs behavior`")
    network = road_network_of(scene, nuscenes_maps)
    road_file = f"{road_source_id(scene)}.xodr"
    prepared = []
    for spec in specs:
        entities = behaviour_variant_entities(spec, scene, config)
        name = f"{scene.scene_id}-{spec['variant_id']}"
        check_on_network(entities, network, f"variant {name}", config.road_tolerance_m)
        prepared.append((name, spec, entities))
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    (root / road_file).write_bytes(network.xodr)
    index = []
    for name, spec, entities in prepared:
        (root / f"{name}.xosc").write_bytes(scenario_document(entities, road_file, f"omniscs variant {name}", config,
                                                              int(spec["timestamps_us"][0])))
        index.append({"scene_id": name, "scenario": f"{name}.xosc", "road_network": road_file,
                      "roads": network.source, "entities": len(entities), "moving": sum(e.moves for e in entities),
                      "misc_objects": 0, "duration_s": float(entities[0].times_s[-1])})
    (root / INDEX_JSON).write_text(json.dumps({"openscenario": f"{OSC_MAJOR}.{OSC_MINOR}", "scenarios": index},
                                              indent=1))
    return {"scenarios": index}


def export_behaviour_variants(variants_json: str | Path, scene_path: str | Path, out: str | Path,
                              overwrite: bool = False, config: OpenScenarioConfig = OpenScenarioConfig(),
                              nuscenes_maps: str | Path | None = None) -> Path:
    """The behaviour variants of a ``variants.json`` (never rendered) as OpenSCENARIO at ``out``, on the road network
    of ``scene_path`` (the store they were made from); nothing is left at ``out`` on failure."""
    from omniscs.scene.store import load_scene
    from omniscs.storage import atomic_directory

    specs = read_json(variants_json, "write the variants again with `omniscs scs behavior`", expect=list,
                      what="behaviour variants")
    scene = load_scene(scene_path)
    with atomic_directory(out, overwrite=overwrite) as tmp:
        write_behaviour_variants(specs, scene, tmp, config, nuscenes_maps)
    return Path(out)


def box_centres(entity: ScenarioEntity) -> np.ndarray:  # -> [T, 3] world box centre at every pose
    from omniscs.geometry import rotmat_from_euler

    R = np.stack([rotmat_from_euler(r, p, h) for h, p, r in entity.poses[:, 3:]])
    return entity.poses[:, :3] + R @ entity.centre


def check_on_network(entities: list[ScenarioEntity], network: RoadNetwork, what: str,
                     tolerance_m: float) -> None:
    """An OmniscsError naming the first entity and time whose box centre leaves the network's area."""
    import shapely

    area = network.area.buffer(tolerance_m)
    for entity in entities:
        xy = box_centres(entity)[:, :2]
        inside = shapely.contains_xy(area, xy[:, 0], xy[:, 1])
        if not inside.all():
            i = int(np.flatnonzero(~inside)[0])
            raise OmniscsError(f"{what}: {entity.name} leaves the road network at t = {entity.times_s[i]:.2f} s "
                               f"(box centre at x = {xy[i, 0]:.2f}, y = {xy[i, 1]:.2f} m, more than "
                               f"{tolerance_m:g} m outside the drivable area and sidewalks); it cannot be replayed "
                               "on the exported roads: leave this variant out of the export")


# ----------------------------------------------------------------------------- writing
def _position(pose: np.ndarray):
    from scenariogeneration import xosc

    x, y, z, h, p, r = (float(v) + 0.0 for v in pose)  # + 0.0: no "-0.0" in the file
    return xosc.WorldPosition(x, y, z, h, p, r)


def _scenario_object(entity: ScenarioEntity, config: OpenScenarioConfig):
    from scenariogeneration import xosc

    length, width, height = (float(v) for v in entity.size)
    cx, cy, cz = (float(v) for v in entity.centre)
    box = xosc.BoundingBox(width, length, height, cx, cy, cz)
    if entity.object_type == "Vehicle":
        half_base = 0.5 * config.wheelbase_fraction * length
        rear_x = 0.0 if entity.track_id < 0 else cx - half_base  # the ego's reference point is its rear axle
        wheel = min(config.wheel_diameter_m, height)
        front = xosc.Axle(0.5, wheel, width, rear_x + 2 * half_base, wheel / 2)
        rear = xosc.Axle(0.0, wheel, width, rear_x, wheel / 2)
        vehicle = xosc.Vehicle(entity.name, getattr(xosc.VehicleCategory, entity.category), box, front, rear,
                               config.max_speed_mps, config.max_acceleration_mps2, config.max_deceleration_mps2)
        if entity.track_id < 0:  # CARLA's ScenarioRunner takes the vehicle with this property as the ego
            vehicle.add_property("type", "ego_vehicle")
        return vehicle
    if entity.object_type == "Pedestrian":
        return xosc.Pedestrian(entity.name, config.pedestrian_mass_kg,
                               getattr(xosc.PedestrianCategory, entity.category), box)
    return xosc.MiscObject(entity.name, config.object_mass_kg, getattr(xosc.MiscObjectCategory, entity.category),
                           box)


def scenario_document(entities: list[ScenarioEntity], road_file: str, description: str,
                      config: OpenScenarioConfig = OpenScenarioConfig(), start_us: int = 0) -> bytes:
    """The ``.xosc`` document of ``entities`` on the road network ``road_file`` (a path relative to the
    ``.xosc``). ``start_us``: the first frame's timestamp, written as the header's date (the same input always
    gives the same bytes)."""
    from scenariogeneration import xosc

    names = [e.name for e in entities]
    if len(set(names)) != len(names):
        raise OmniscsError(f"two scenario entities share a name: {sorted({n for n in names if names.count(n) > 1})}")
    objects = xosc.Entities()
    init = xosc.Init()
    for entity in entities:
        objects.add_scenario_object(entity.name, _scenario_object(entity, config))
        init.add_init_action(entity.name, xosc.TeleportAction(_position(entity.poses[0])))
    end_s = max(float(e.times_s[-1]) for e in entities)
    start = xosc.ValueTrigger("start", 0, xosc.ConditionEdge.none,
                              xosc.SimulationTimeCondition(0, xosc.Rule.greaterOrEqual), "start")
    act = xosc.Act("replay", start)
    for entity in entities:
        if not entity.moves:
            continue
        trajectory = xosc.Trajectory(f"{entity.name}_trajectory", False)
        trajectory.add_shape(xosc.Polyline([float(t) for t in entity.times_s],
                                           [_position(p) for p in entity.poses]))
        action = xosc.FollowTrajectoryAction(trajectory, xosc.FollowingMode.position, xosc.ReferenceContext.absolute,
                                             1, 0)
        event = xosc.Event(f"{entity.name}_follows", xosc.Priority.override)
        event.add_action(f"{entity.name}_trajectory_action", action)
        event.add_trigger(xosc.ValueTrigger(f"{entity.name}_start", 0, xosc.ConditionEdge.none,
                                            xosc.SimulationTimeCondition(0, xosc.Rule.greaterOrEqual)))
        maneuver = xosc.Maneuver(f"{entity.name}_maneuver")
        maneuver.add_event(event)
        group = xosc.ManeuverGroup(f"{entity.name}_group")
        group.add_actor(entity.name)
        group.add_maneuver(maneuver)
        act.add_maneuver_group(group)
    story = xosc.Story("variant")
    story.add_act(act)
    stop = xosc.ValueTrigger("end", 0, xosc.ConditionEdge.rising,
                             xosc.SimulationTimeCondition(end_s, xosc.Rule.greaterThan), "stop")
    storyboard = xosc.StoryBoard(init, stop)
    if act.maneuvergroup:
        storyboard.add_story(story)
    date = datetime.datetime(1970, 1, 1) + datetime.timedelta(microseconds=int(start_us))
    scenario = xosc.Scenario(description, "omniscs", xosc.ParameterDeclarations(), objects, storyboard,
                             xosc.RoadNetwork(roadfile=road_file), xosc.Catalog(), osc_minor_version=OSC_MINOR,
                             creation_date=date)
    root = scenario.get_element()
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)


@dataclass
class _RoadFiles:
    """The road files of one export: source scene id -> (file name, bytes)."""

    files: dict[str, tuple[str, bytes]] = field(default_factory=dict)

    def name_for(self, key: str, xodr: bytes) -> str:
        known = self.files.get(key)
        if known is not None and known[1] == xodr:
            return known[0]
        name = f"{key}.xodr" if known is None else f"{key}-{hashlib.sha256(xodr).hexdigest()[:8]}.xodr"
        self.files.setdefault(key if known is None else name, (name, xodr))
        return name


def write_openscenario(scenes: list[Scene], root: Path, progress: Callable[[int, int], None] | None = None,
                       config: OpenScenarioConfig = OpenScenarioConfig(),
                       nuscenes_maps: str | Path | None = None) -> dict:
    """Write every scene store as ``<scene id>.xosc`` into ``root`` (an export's temporary folder) beside the road
    network of its source scene (``<source scene id>.xodr``, one per road network) and ``index.json``. Every scene
    is checked (its road network exists, its entities stay on it) before anything is written. ``nuscenes_maps``: a
    nuScenes dataroot whose map expansions give recorded nuScenes logs their roads (``opendrive.road_network_of``)."""
    import json

    prepared, roads = [], _RoadFiles()
    for scene in scenes:
        network = road_network_of(scene, nuscenes_maps)
        entities = scenario_entities(scene, config)
        check_on_network(entities, network, f"scene {scene.scene_id}", config.road_tolerance_m)
        prepared.append((scene, network, entities, roads.name_for(road_source_id(scene), network.xodr)))
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for name, xodr in roads.files.values():
        (root / name).write_bytes(xodr)
    index = []
    for i, (scene, network, entities, road_file) in enumerate(prepared):
        ts = scene.frames["timestamp_us"].to_numpy(np.int64)
        document = scenario_document(entities, road_file, f"omniscs scene {scene.scene_id}", config, int(ts[0]))
        (root / f"{scene.scene_id}.xosc").write_bytes(document)
        index.append({"scene_id": scene.scene_id, "scenario": f"{scene.scene_id}.xosc", "road_network": road_file,
                      "roads": network.source, "entities": len(entities),
                      "moving": sum(e.moves for e in entities),
                      "misc_objects": sum(e.object_type == "MiscObject" for e in entities),
                      "duration_s": float((ts[-1] - ts[0]) / 1e6)})
        if progress is not None:
            progress(i + 1, len(prepared))
    (root / INDEX_JSON).write_text(json.dumps({"openscenario": f"{OSC_MAJOR}.{OSC_MINOR}",
                                               "scenarios": index}, indent=1))
    return {"scenarios": index}


# ----------------------------------------------------------------------------- reading back
@dataclass(frozen=True)
class ReadEntity:
    """An entity as an ``.xosc`` file states it (read with xml.etree, independent of the writer)."""

    name: str
    object_type: str
    category: str
    size: np.ndarray  # [3] length, width, height
    centre: np.ndarray  # [3] BoundingBox Center
    initial: np.ndarray  # [6] x, y, z, h, p, r of its TeleportAction
    times_s: np.ndarray  # [T] trajectory vertex times (empty without a trajectory)
    poses: np.ndarray  # [T, 6] trajectory vertex positions
    timing: str | None  # the trajectory's Timing domainAbsoluteRelative, None without one


def _world(position: ET.Element) -> np.ndarray:
    world = position.find("WorldPosition")
    if world is None:
        raise OmniscsError("an OpenSCENARIO position is not a WorldPosition; only files this exporter wrote are read")
    return np.array([float(world.get(k, 0.0)) for k in ("x", "y", "z", "h", "p", "r")])


def read_scenario(path: str | Path) -> dict[str, ReadEntity]:
    """{name: entity} of an ``.xosc`` file this exporter wrote (WorldPositions, Polyline trajectories)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise OmniscsError(f"{path} is not a readable OpenSCENARIO file ({exc}); export it again") from None
    initial = {}
    for private in root.iter("Private"):
        teleport = private.find("PrivateAction/TeleportAction/Position")
        if teleport is not None:
            initial[private.get("entityRef")] = _world(teleport)
    trajectories = {}
    for group in root.iter("ManeuverGroup"):
        actor = group.find("Actors/EntityRef").get("entityRef")
        follow = group.find(".//FollowTrajectoryAction")
        vertices = follow.findall(".//Polyline/Vertex")
        timing = follow.find(".//TimeReference/Timing")
        trajectories[actor] = (np.array([float(v.get("time")) for v in vertices]),
                               np.stack([_world(v.find("Position")) for v in vertices]),
                               None if timing is None else timing.get("domainAbsoluteRelative"))
    out = {}
    for obj in root.iter("ScenarioObject"):
        name = obj.get("name")
        kind = next(child for child in obj if child.tag in ("Vehicle", "Pedestrian", "MiscObject"))
        category = kind.get({"Vehicle": "vehicleCategory", "Pedestrian": "pedestrianCategory",
                             "MiscObject": "miscObjectCategory"}[kind.tag])
        box = kind.find("BoundingBox")
        dims, centre = box.find("Dimensions"), box.find("Center")
        times, poses, timing = trajectories.get(name, (np.zeros(0), np.zeros((0, 6)), None))
        out[name] = ReadEntity(name, kind.tag, category,
                               np.array([float(dims.get(k)) for k in ("length", "width", "height")]),
                               np.array([float(centre.get(k)) for k in ("x", "y", "z")]),
                               initial[name], times, poses, timing)
    return out


def road_file_of(path: str | Path) -> str:
    """The RoadNetwork LogicFile path an ``.xosc`` names."""
    logic = ET.parse(path).getroot().find("RoadNetwork/LogicFile")
    if logic is None:
        raise OmniscsError(f"{path} names no road network (RoadNetwork/LogicFile); export it again")
    return logic.get("filepath")


def angle_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # radians, any shape -> |a - b| modulo 2 pi
    return np.abs((np.asarray(a) - np.asarray(b) + math.pi) % (2 * math.pi) - math.pi)
