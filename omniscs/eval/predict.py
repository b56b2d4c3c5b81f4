"""Predictions of a nuScenes dataroot in the formats ``omniscs eval`` reads: the proxy planner's waypoints of every
keyframe (planning results) and, through ``detector_decoding.detect``, the proxy detector's boxes (the nuScenes
detection results format); and the check that a results file made elsewhere (a user's external model) is one the
evaluation will take, before it is kept.

What the planner sees at a keyframe of a dataroot (``dataroot_planning_inputs``), in UniAD's planning frame of that
keyframe (``nuscenes_io.world_from_planning``: at the LiDAR, x right, y forward; the frame ``eval planning`` reads
waypoints in):
  - the annotated boxes now and ``HISTORY_S`` before (the previous keyframe at 2 Hz; at a scene's first keyframe,
    which has none, the boxes now stand in for them, as if the agents stood still);
  - the ego's speed and yaw rate over the ``HISTORY_S`` before the keyframe, from the LIDAR_TOP poses (keyframes
    and sweeps), over the span there is at a scene's start, and at its very first keyframe over the first pose
    after it (the ego's motion at that instant, which UniAD reads from the CAN bus);
  - UniAD's driving command, from the true future as UniAD's evaluation takes it (``scenarios.command_of`` of the
    keyframes' LiDAR positions up to ``STEPS`` ahead; forward at a scene's last keyframe);
  - the drivable area of the map expansion of the scene's location (``maps/expansion/<location>.json``: the union
    of its ``drivable_area`` polygons, holes cut out), or none when the dataroot has no map file for it.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from omniscs.errors import ValidationError
from omniscs.eval.nuscenes_io import (
    EGO_FROM_PLANNING,
    REFERENCE_CHANNEL,
    STEP_TOLERANCE_S,
    NuScenesTables,
    load_planning_results,
    load_planning_samples,
    load_results,
    read_planning_results,
    world_from_planning,
)
from omniscs.eval.detector_views import transform_of
from omniscs.eval.planning import STEP_S, STEPS
from omniscs.eval.scenarios import HISTORY_S, PlanningInput, boxes_in_frame, command_of, to_frame
from omniscs.progress import Progress, no_progress
from omniscs.quaternions import quat_to_rotmat
from omniscs.untrusted import MAX_TABLE_BYTES, read_json

#: The tasks ``omniscs predict`` makes results for.
TASKS = ("detection", "planning")


# ----------------------------------------------------------------------------- the map of a dataroot
class DrivableArea:
    """The drivable area of one nuScenes map expansion (global frame): the union of its ``drivable_area`` polygons,
    each with its holes cut out. ``is_drivable`` is what the planner's raster reads."""

    def __init__(self, polygons: list) -> None:  # shapely Polygons
        import shapely

        self._area = shapely.union_all(polygons) if polygons else shapely.Polygon()
        shapely.prepare(self._area)

    def is_drivable(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] global -> [N] bool
        import shapely

        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return np.asarray(shapely.contains_xy(self._area, xy[:, 0], xy[:, 1]), bool)

    @classmethod
    def from_expansion(cls, path: str | Path) -> "DrivableArea":
        """The drivable area of a map expansion file (nuScenes map expansion v1.3 layout); a clear error for a file
        that is not one."""
        import shapely

        # a map expansion of a real city is tens of MB
        data = read_json(path, "give a nuScenes map expansion (v1.3) file", expect=dict, max_bytes=MAX_TABLE_BYTES,
                         what="map expansion", error=ValidationError)
        try:
            nodes = {n["token"]: (float(n["x"]), float(n["y"])) for n in data["node"]}
            polygons = {p["token"]: p for p in data["polygon"]}
            out = []
            for record in data["drivable_area"]:
                for token in record["polygon_tokens"]:
                    poly = polygons[token]
                    exterior = [nodes[n] for n in poly["exterior_node_tokens"]]
                    holes = [[nodes[n] for n in h["node_tokens"]] for h in poly.get("holes", [])]
                    if len(exterior) >= 3:
                        out.append(shapely.Polygon(exterior, [h for h in holes if len(h) >= 3]).buffer(0))
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValidationError(f"{path} is not a nuScenes map expansion with drivable_area polygons "
                                  f"({type(e).__name__}: {e})") from e
        return cls(out)


def scene_drivable_areas(tables: NuScenesTables) -> dict[str, DrivableArea | None]:
    """{scene token: the drivable area of its log's location, or None when the dataroot has no map expansion of it}."""
    log_path = tables.root / tables.version / "log.json"  # not among the tables the evaluation loads
    try:
        logs = {r["token"]: r for r in read_json(log_path, "give the dataroot's own log table", expect=list,
                                                 max_bytes=MAX_TABLE_BYTES, what="nuScenes table",
                                                 error=ValidationError)} if log_path.exists() else {}
    except (KeyError, TypeError) as e:
        raise ValidationError(f"{log_path} is not a nuScenes log table ({type(e).__name__}: {e})") from e
    by_location: dict[str, DrivableArea | None] = {}
    out = {}
    for token, scene in tables["scene"].items():
        location = logs.get(scene.get("log_token"), {}).get("location")
        if location is None:
            out[token] = None
            continue
        if location not in by_location:
            path = tables.root / "maps" / "expansion" / f"{location}.json"
            by_location[location] = DrivableArea.from_expansion(path) if path.is_file() else None
        out[token] = by_location[location]
    return out


# ----------------------------------------------------------------------------- planning inputs of a dataroot
def _frame_2d(world_from_planning_3d: np.ndarray) -> np.ndarray:  # [4, 4] -> [3, 3] (x, y and the yaw about z)
    T = np.eye(3)
    x_axis = world_from_planning_3d[:2, 0]
    heading = math.atan2(x_axis[1], x_axis[0])
    c, s = math.cos(heading), math.sin(heading)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 2] = world_from_planning_3d[:2, 3]
    return T


def _heading(frame: np.ndarray) -> float:  # the frame's y axis (the ego's heading) in the world, rad
    return math.atan2(frame[1, 1], frame[0, 1])


def _lidar_frames(tables: NuScenesTables) -> dict[str, list[tuple[float, np.ndarray]]]:
    """{scene token: [(time s, world_from_planning [3, 3]) of every LIDAR_TOP sample_data, keyframes and sweeps],
    in time order}."""
    channel = {t: tables["sensor"][c["sensor_token"]]["channel"] for t, c in tables["calibrated_sensor"].items()}
    out: dict[str, list[tuple[float, np.ndarray]]] = {}
    for sd in tables["sample_data"].values():
        if channel.get(sd["calibrated_sensor_token"]) != REFERENCE_CHANNEL:
            continue
        scene = tables["sample"][sd["sample_token"]]["scene_token"]
        world_from_ego = transform_of(tables["ego_pose"][sd["ego_pose_token"]])
        ego_from_lidar = transform_of(tables["calibrated_sensor"][sd["calibrated_sensor_token"]])
        planning = np.eye(4)  # as nuscenes_io.world_from_planning places it, for sweeps too
        planning[:3, :3] = world_from_ego[:3, :3] @ EGO_FROM_PLANNING
        planning[:3, 3] = (world_from_ego @ ego_from_lidar)[:3, 3]
        out.setdefault(scene, []).append((sd["timestamp"] * 1e-6, _frame_2d(planning)))
    for poses in out.values():
        poses.sort(key=lambda p: p[0])
    return out


def ego_motion_at(poses: list[tuple[float, np.ndarray]], t: float) -> tuple[float, float]:
    """(speed m/s, yaw rate rad/s) of the ego at time ``t`` s from its LiDAR poses (module docstring): over the
    ``HISTORY_S`` before ``t`` (the earliest pose in that window), else over the first pose after ``t``; (0, 0)
    without another pose."""
    now = min(poses, key=lambda p: abs(p[0] - t))
    earlier = [p for p in poses if t - HISTORY_S - STEP_TOLERANCE_S <= p[0] < t - 1e-6]
    if earlier:
        a, b = earlier[0], now
    else:
        later = [p for p in poses if p[0] > t + 1e-6]
        if not later:
            return 0.0, 0.0
        a, b = now, later[0]
    dt = b[0] - a[0]
    if dt <= 0:
        return 0.0, 0.0
    moved = float(np.linalg.norm(b[1][:2, 2] - a[1][:2, 2]))
    turned = math.remainder(_heading(b[1]) - _heading(a[1]), math.tau)
    return moved / dt, turned / dt


def _sample_boxes(tables: NuScenesTables, anns: list[dict], frame: np.ndarray) -> np.ndarray:  # -> [B, 6]
    """The sample's annotated boxes in ``frame`` (x, y, length, width, yaw, is_vehicle)."""
    if not anns:
        return np.zeros((0, 6))
    pose, sizes, vehicle = [], [], []
    for ann in anns:
        R = quat_to_rotmat(np.asarray(ann["rotation"], np.float64))
        pose.append([ann["translation"][0], ann["translation"][1], math.atan2(R[1, 0], R[0, 0])])
        sizes.append([ann["size"][1], ann["size"][0]])  # nuScenes sizes are w, l, h
        category = tables["category"][tables["instance"][ann["instance_token"]]["category_token"]]["name"]
        vehicle.append(category.startswith("vehicle."))
    return boxes_in_frame(np.array(pose, np.float64), np.array(sizes, np.float64), np.array(vehicle), frame)


def dataroot_planning_inputs(tables: NuScenesTables, samples: list[str], progress: Progress = no_progress
                             ) -> list[tuple[str, PlanningInput, DrivableArea | None]]:
    """(sample token, what the planner sees, the drivable area) of each of ``samples`` (module docstring). The
    keyframes must be ``STEP_S`` apart (2 Hz), as the planning metrics read them."""
    anns_by_sample: dict[str, list[dict]] = {}
    for ann in tables["sample_annotation"].values():
        anns_by_sample.setdefault(ann["sample_token"], []).append(ann)
    maps = scene_drivable_areas(tables)
    lidar = _lidar_frames(tables)
    out = []
    for i, token in enumerate(samples):
        sample = tables["sample"][token]
        frame = _frame_2d(world_from_planning(tables, token))
        t = sample["timestamp"] * 1e-6
        prev = sample["prev"]
        if prev:
            if prev not in tables["sample"]:
                raise ValidationError(f"{tables.root / tables.version / 'sample.json'}: sample {token} names a previous "
                                      f"sample {prev} the table lacks")
            gap = t - tables["sample"][prev]["timestamp"] * 1e-6
            if abs(gap - HISTORY_S) > STEP_TOLERANCE_S:
                raise ValidationError(f"keyframes {prev} and {token} are {gap:.3f} s apart; the planner reads one "
                                      f"keyframe every {STEP_S} s (export with keyframes at 2 Hz)")
        future = [_frame_2d(world_from_planning(tables, nxt))[:2, 2]
                  for nxt in tables.chain("sample", token, f"sample {token}", limit=STEPS + 1)[1:]]
        command = command_of(to_frame(frame, np.array(future))) if future else "forward"
        now = _sample_boxes(tables, anns_by_sample.get(token, []), frame)
        past = _sample_boxes(tables, anns_by_sample.get(prev, []), frame) if prev else now
        speed, yaw_rate = ego_motion_at(lidar.get(sample["scene_token"], [(t, frame)]), t)
        out.append((token, PlanningInput(now, past, speed, yaw_rate, command, frame), maps.get(sample["scene_token"])))
        progress(i + 1, len(samples), "reading keyframes")
    return out


def predict_planning(model, dataroot: str | Path, version: str | None, scenes: list[str] | None = None,
                     progress: Progress = no_progress) -> dict:
    """Planning results of the proxy planner ``model`` (``planner.ProxyPlanner``) for every keyframe of ``scenes``
    (names or tokens; all when None): ``{"meta": {...}, "results": {sample_token: {"trajectory": [[x, y] x STEPS]}}}``
    in UniAD's planning frame, what ``eval planning`` reads."""
    from omniscs.eval.planner import plan_inputs

    tables = NuScenesTables.load(dataroot, version)
    samples = tables.scene_samples(scenes)
    if not samples:
        raise ValidationError(f"{Path(dataroot) / tables.version} has no keyframes to plan for")
    inputs = dataroot_planning_inputs(tables, samples, progress)
    waypoints = plan_inputs(model, [(inp, drivable) for _, inp, drivable in inputs], progress=progress)
    meta = {"method": "omniscs proxy planner (bird's-eye view of the annotated boxes)", "frame":
            "UniAD planning frame of each keyframe: at the LiDAR, x right, y forward (m)", "step_s": STEP_S,
            "version": tables.version, "has_map": sum(d is not None for _, _, d in inputs)}
    return {"meta": meta, "results": {token: {"trajectory": np.asarray(w, np.float64).round(4).tolist()}
                                      for (token, _, _), w in zip(inputs, waypoints)}}


# ----------------------------------------------------------------------------- results made elsewhere
def check_results(task: str, path: str | Path, dataroot: str | Path, version: str | None,
                  scenes: list[str] | None = None) -> int:
    """A results file (e.g. an external model's) read as ``eval detection`` / ``eval planning`` will read it, so
    that a bad one fails here, named, before it is kept; returns the number of samples it covers."""
    tables = NuScenesTables.load(dataroot, version)
    samples = tables.scene_samples(scenes)
    if task == "detection":
        load_results(path, tables, samples)
        return len(samples)
    if task == "planning":
        evaluated, _ = load_planning_samples(tables, samples)
        data = read_planning_results(path)
        load_planning_results(path, [s.token for s in evaluated], allowed=samples, data=data)
        return len(data["results"])
    raise ValidationError(f"unknown task {task!r}; one of {TASKS}")
