"""Reading what the nuScenes tools read: the tables of a dataroot (the factory's exports or the real dataset) as
evaluation ground truth, and detection results in the nuScenes results format, with clear errors for what the
protocol does not accept. Plain JSON reading (no ``NuScenes`` object, no official split names): any scene set of
any dataroot can be evaluated."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.detection import CLASS_ATTRIBUTES, DETECTION_NAMES, Boxes, DetectionConfig, evaluate, filter_boxes
from omniscs.eval.planning import STEP_S, STEPS, PlanningSample, evaluate_planning, frames_for_planning
from omniscs.geometry import make_transform
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene.sources.nuscenes import find_version
from omniscs.taxonomy import NUSCENES_DETECTION_CLASS
from omniscs.untrusted import MAX_TABLE_BYTES, read_json

#: nuScenes category -> detection class (the devkit's ``category_to_detection_name``).
CATEGORY_TO_DETECTION: dict[str, str] = NUSCENES_DETECTION_CLASS
BIKE_RACK = "static_object.bicycle_rack"
#: Largest time between an annotation and its neighbour for a velocity (s; doubled across both neighbours).
MAX_VELOCITY_DT_S = 1.5
REFERENCE_CHANNEL = "LIDAR_TOP"
#: Size cap of a results file (bytes): 500 boxes per sample of the 6,019 validation samples is about 1 GB.
MAX_RESULTS_BYTES = 2 * 2**30


def resolve_version(dataroot: str | Path, version: str | None) -> str:
    """The table version to read: ``version`` when the dataroot holds it, or its only ``v1.0-*`` folder when
    ``version`` is None; anything else (no such dataroot, another version than asked, several to choose from) is one
    error naming the versions the dataroot holds. The factory's exports write ``DEFAULT_VERSION``
    (``omniscs.export.nuscenes``); the real dataset comes as v1.0-mini or v1.0-trainval."""
    try:
        return find_version(Path(dataroot), version)
    except ValidationError:
        raise
    except OmniscsError as exc:  # the evaluation's readers raise ValidationError for what is on disk
        raise ValidationError(str(exc)) from None


@dataclass
class NuScenesTables:
    """The tables of one dataroot version, indexed by token."""

    root: Path
    version: str
    tables: dict[str, dict[str, dict]]

    @classmethod
    def load(cls, dataroot: str | Path, version: str | None) -> "NuScenesTables":
        """The tables of ``version`` (None: the dataroot's only ``v1.0-*`` folder, ``resolve_version``); a version
        the dataroot does not hold is one error naming those it holds."""
        version = resolve_version(dataroot, version)
        folder = Path(dataroot) / version
        tables = {}
        for name in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor", "sample_annotation",
                     "instance", "category", "attribute"):
            path = folder / f"{name}.json"
            rows = read_json(path, "give the dataroot's own table (a list of records)", expect=list,
                             max_bytes=MAX_TABLE_BYTES, what="nuScenes table", error=ValidationError)
            bad = next((i for i, r in enumerate(rows) if not isinstance(r, dict) or not isinstance(r.get("token"), str)),
                       None)
            if bad is not None:
                raise ValidationError(f"{path}: record {bad} is not an object with a string 'token'; give the "
                                      "dataroot's own table")
            tables[name] = {r["token"]: r for r in rows}
        return cls(Path(dataroot), version, tables)

    def __getitem__(self, name: str) -> dict[str, dict]:
        return self.tables[name]

    def scene_samples(self, scenes: list[str] | None = None) -> list[str]:
        """Sample tokens of the named scenes (names or tokens; all scenes when None), scene by scene in time order."""
        by_name = {s["name"]: s for s in self["scene"].values()}
        chosen = list(self["scene"].values()) if not scenes else []
        for s in scenes or ():
            rec = by_name.get(s) or self["scene"].get(s)
            if rec is None:
                raise ValidationError(f"unknown scene {s!r} in {self.root / self.version}; it has "
                                      f"{sorted(by_name)[:8]}{' ...' if len(by_name) > 8 else ''}")
            chosen.append(rec)
        tokens = []
        for scene in chosen:
            tokens += self.chain("sample", scene["first_sample_token"], f"scene {scene.get('name')}")
        return tokens

    def chain(self, table: str, first: str, owner: str, limit: int | None = None) -> list[str]:
        """Tokens of ``table`` from ``first`` along ``next`` (at most ``limit``); a chain that loops or names a token
        the table lacks is one ValidationError naming the table (a hostile or damaged table never hangs us)."""
        tokens, seen, t = [], set(), first
        while t and (limit is None or len(tokens) < limit):
            if t in seen:
                raise ValidationError(f"{self.root / self.version / (table + '.json')}: the next chain of {owner} loops "
                                      f"at {t}; fix the table's next tokens")
            record = self[table].get(t)
            if record is None:
                raise ValidationError(f"{self.root / self.version / (table + '.json')}: the next chain of {owner} "
                                      f"names {t}, which the table lacks")
            seen.add(t)
            tokens.append(t)
            t = record.get("next")
        return tokens

    def reference_pose(self, sample_token: str) -> dict:
        """The ego pose of the sample's LIDAR_TOP keyframe."""
        return self["ego_pose"][self.reference_data(sample_token)["ego_pose_token"]]

    def reference_data(self, sample_token: str) -> dict:
        if not hasattr(self, "_keyframes"):
            channel = {t: self["sensor"][c["sensor_token"]]["channel"] for t, c in self["calibrated_sensor"].items()}
            self._keyframes = {sd["sample_token"]: sd for sd in self["sample_data"].values()
                               if sd.get("is_key_frame") and channel.get(sd["calibrated_sensor_token"]) ==
                               REFERENCE_CHANNEL}
        rec = self._keyframes.get(sample_token)
        if rec is None:
            raise ValidationError(f"sample {sample_token} has no {REFERENCE_CHANNEL} keyframe: the protocol measures "
                                  "distances from its ego pose")
        return rec

    def box_velocity(self, ann: dict) -> np.ndarray:
        """[3] m/s from the neighbouring annotations' centres (NaN without a neighbour or over too long a gap)."""
        prev, nxt = ann["prev"], ann["next"]
        if not prev and not nxt:
            return np.full(3, np.nan)
        for t in (prev, nxt):
            if t and t not in self["sample_annotation"]:
                raise ValidationError(f"{self.root / self.version / 'sample_annotation.json'}: annotation "
                                      f"{ann.get('token')} names a neighbour {t} the table lacks")
        first = self["sample_annotation"][prev] if prev else ann
        last = self["sample_annotation"][nxt] if nxt else ann
        dt = 1e-6 * (self["sample"][last["sample_token"]]["timestamp"]
                     - self["sample"][first["sample_token"]]["timestamp"])
        if dt > MAX_VELOCITY_DT_S * (2 if prev and nxt else 1) or dt <= 0:
            return np.full(3, np.nan)
        return (np.asarray(last["translation"], np.float64) - np.asarray(first["translation"], np.float64)) / dt


def load_ground_truth(tables: NuScenesTables, samples: list[str]) -> tuple[Boxes, dict[str, np.ndarray]]:
    """The evaluated boxes of ``samples`` (detection classes only, with their ego distance, point count and
    velocity) and each sample's bicycle racks (world_from_rack with the size folded in, for ``filter_boxes``)."""
    anns_by_sample: dict[str, list[dict]] = {}
    for ann in tables["sample_annotation"].values():
        anns_by_sample.setdefault(ann["sample_token"], []).append(ann)
    records, ego_dist, num_pts, racks = [], [], [], {}
    for token in samples:
        ego = np.asarray(tables.reference_pose(token)["translation"], np.float64)
        for ann in anns_by_sample.get(token, []):
            category = tables["category"][tables["instance"][ann["instance_token"]]["category_token"]]["name"]
            if category == BIKE_RACK:
                racks.setdefault(token, []).append(_unit_frame(ann))
            name = CATEGORY_TO_DETECTION.get(category)
            if name is None:
                continue
            attrs = ann.get("attribute_tokens", [])
            if len(attrs) > 1:
                raise ValidationError(f"annotation {ann['token']} has {len(attrs)} attributes; the protocol allows one")
            records.append({"sample_token": token, "translation": ann["translation"], "size": ann["size"],
                            "rotation": ann["rotation"], "velocity": tables.box_velocity(ann)[:2],
                            "detection_name": name,
                            "attribute_name": tables["attribute"][attrs[0]]["name"] if attrs else ""})
            ego_dist.append(float(np.hypot(*(np.asarray(ann["translation"][:2]) - ego[:2]))))
            num_pts.append(int(ann.get("num_lidar_pts", 0)) + int(ann.get("num_radar_pts", 0)))
    return (Boxes.from_records(records, ego_dist, num_pts),
            {k: np.stack(v) for k, v in racks.items()})


#: Points of a box tested against the cameras, in the unit cube [-0.5, 0.5]^3 (its frame from ``_unit_frame``): the
#: 3 x 3 x 3 grid of corners, edge and face midpoints and centre, so that a box reaching across an image with every
#: corner outside it still counts.
BOX_PROBES = np.array([[x, y, z] for x in (-0.5, 0, 0.5) for y in (-0.5, 0, 0.5) for z in (-0.5, 0, 0.5)], np.float64)
#: Least depth (m, along a camera's optical axis) of a point that counts as in front of the camera.
NEAR_M = 0.1


def camera_frustums(tables: NuScenesTables, samples: list[str]) -> dict[str, list[tuple]]:
    """{sample token: [(camera_from_global [4, 4], intrinsics [3, 3], width, height) of each camera keyframe]}."""
    channel = {t: tables["sensor"][c["sensor_token"]]["channel"] for t, c in tables["calibrated_sensor"].items()}
    wanted = set(samples)
    out: dict[str, list[tuple]] = {t: [] for t in samples}
    for sd in tables["sample_data"].values():
        if not (sd.get("is_key_frame") and sd["sample_token"] in wanted
                and channel.get(sd["calibrated_sensor_token"], "").startswith("CAM_")):
            continue
        calib = tables["calibrated_sensor"][sd["calibrated_sensor_token"]]
        K = np.asarray(calib.get("camera_intrinsic") or [], np.float64)
        if K.shape != (3, 3) or not sd.get("width") or not sd.get("height"):
            raise ValidationError(f"camera sample_data {sd['token']} needs a 3x3 camera_intrinsic, a width and a "
                                  "height to tell which boxes its camera sees")
        global_from_camera = _transform(tables["ego_pose"][sd["ego_pose_token"]]) @ _transform(calib)
        out[sd["sample_token"]].append((np.linalg.inv(global_from_camera), K, int(sd["width"]), int(sd["height"])))
    return out


def in_camera_view(boxes: Boxes, frustums: dict[str, list[tuple]]) -> np.ndarray:
    """[N] bool: a point of the box (``BOX_PROBES``) lies in front of a camera of its sample and inside that camera's
    image (the devkit's ``BoxVisibility.ANY``, with edge and face midpoints besides the corners; occlusion does not
    count). A camera-only detector cannot find boxes outside every view: on a rig that does not look all round (the
    factory's three front cameras) they are a recall no detector reaches. A sample with no camera sees nothing."""
    seen = np.zeros(len(boxes), bool)
    for i in range(len(boxes)):
        record = {"translation": boxes.translation[i], "rotation": boxes.rotation[i], "size": boxes.size[i]}
        frame = _unit_frame(record)
        corners = BOX_PROBES @ frame[:3, :3].T + frame[:3, 3]
        for camera_from_global, K, width, height in frustums.get(str(boxes.sample_token[i]), ()):
            cam = corners @ camera_from_global[:3, :3].T + camera_from_global[:3, 3]
            front = cam[:, 2] > NEAR_M
            if not front.any():
                continue
            uv = cam[front] @ K.T
            uv = uv[:, :2] / uv[:, 2:3]
            if np.any((uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)):
                seen[i] = True
                break
    return seen


def _unit_frame(ann: dict) -> np.ndarray:  # world_from_unit_cube [4, 4]
    T = _transform(ann)
    T[:3, :3] = T[:3, :3] @ np.diag(np.asarray(ann["size"], np.float64)[[1, 0, 2]])  # sizes are w, l, h; x: length
    return T


def read_detection_results(path: str | Path):
    """The JSON value of a detection results file, read as untrusted (``omniscs.untrusted``; NaN is the format's
    "no velocity", an infinity or an overflowing number never a measurement): a FIFO, a device, a folder, hostile or
    invalid JSON is one ValidationError naming the file; its content is checked by ``load_results``."""
    return read_json(path, "give a results file in the nuScenes detection results format", allow_nan=True,
                     max_bytes=MAX_RESULTS_BYTES, what="results file", error=ValidationError)


def load_results(path: str | Path, tables: NuScenesTables, samples: list[str],
                 config: DetectionConfig = DetectionConfig(), camera_view: bool = False,
                 data=None) -> tuple[Boxes, dict]:
    """Predictions of a results file (``{"meta": {...}, "results": {sample_token: [box, ...]}}``) for exactly the
    evaluated ``samples``, with their ego distance; and its meta. Unknown or missing sample tokens, more than
    ``max_boxes_per_sample`` boxes, unknown classes or attributes, non-finite numbers (a NaN velocity is allowed:
    no velocity) and non-positive sizes are refused with the first offending entry named. ``camera_view``: only the
    boxes a camera sees (``in_camera_view``), as ``evaluated_ground_truth``. ``data``: the file's JSON value when
    the caller read it already (``read_detection_results``)."""
    data = read_detection_results(path) if data is None else data
    if not isinstance(data, dict) or not isinstance(data.get("results"), dict):
        raise ValidationError(f"results {path} must be an object with a 'results' object (sample token -> boxes)")
    results, wanted = data["results"], set(samples)
    unknown = sorted(set(results) - wanted)
    if unknown:
        known = unknown[0] in tables["sample"]
        raise ValidationError(f"results {path} name {len(unknown)} sample(s) "
                              f"{'outside the evaluated scenes' if known else 'unknown to the dataroot'}, "
                              f"e.g. {unknown[0]!r}")
    missing = [t for t in samples if t not in results]
    if missing:
        raise ValidationError(f"results {path} lack {len(missing)} of the {len(samples)} evaluated samples, e.g. "
                              f"{missing[0]!r} (the protocol needs every sample, an empty list where nothing is seen)")
    records, ego_dist = [], []
    for token in samples:
        boxes = results[token]
        if not isinstance(boxes, list):
            raise ValidationError(f"results[{token!r}] must be a list of boxes")
        if len(boxes) > config.max_boxes_per_sample:
            raise ValidationError(f"results[{token!r}] has {len(boxes)} boxes; at most "
                                  f"{config.max_boxes_per_sample} per sample are allowed")
        ego = np.asarray(tables.reference_pose(token)["translation"], np.float64)
        for i, box in enumerate(boxes):
            rec = _checked_box(box, f"results[{token!r}][{i}]")
            if rec["sample_token"] != token:
                raise ValidationError(f"results[{token!r}][{i}] names sample {rec['sample_token']!r}")
            records.append(rec)
            ego_dist.append(float(np.hypot(rec["translation"][0] - ego[0], rec["translation"][1] - ego[1])))
    boxes = Boxes.from_records(records, ego_dist)
    if camera_view:
        boxes = boxes.take(in_camera_view(boxes, camera_frustums(tables, samples)))
    return boxes, data.get("meta", {})


#: What a results file's numbers may be (beyond this they are a mistake, and a distance or an error computed from
#: them would overflow): positions (metres, a dataroot's global frame), box sizes (metres), speeds (m/s), and the
#: smallest norm a rotation quaternion may have before it is normalised.
MAX_COORDINATE_M = 1e6
MAX_BOX_SIZE_M = 100.0
MAX_SPEED_MPS = 200.0
MIN_QUATERNION_NORM = 1e-6


def _numbers(value, n: int, where: str, field: str, allow_nan: bool = False) -> list[float]:
    """``value`` as ``n`` real numbers: JSON numbers only (a string or a boolean is refused, not read as one); finite
    unless ``allow_nan`` (NaN only)."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ValidationError(f"{where}: {field} needs {n} numbers; got {str(value)[:60]}")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
        raise ValidationError(f"{where}: {field} must be JSON numbers, not strings or booleans; got {value}")
    out = [float(x) for x in value]
    if not all(math.isfinite(x) or (allow_nan and math.isnan(x)) for x in out):
        unknown = " (or NaN: unknown)" if allow_nan else ""
        raise ValidationError(f"{where}: {field} must be finite{unknown}; got {value}")
    return out


def _checked_box(box, where: str) -> dict:
    if not isinstance(box, dict):
        raise ValidationError(f"{where} must be an object")
    missing = [k for k in ("sample_token", "translation", "size", "rotation", "detection_name", "detection_score")
               if k not in box]
    if missing:
        raise ValidationError(f"{where} is not a nuScenes detection box (it lacks {missing})")
    velocity = box.get("velocity", (math.nan, math.nan))
    velocity = list(velocity)[:2] if isinstance(velocity, (list, tuple)) else velocity
    rec = {"sample_token": str(box["sample_token"]),
           "translation": _numbers(box["translation"], 3, where, "translation"),
           "size": _numbers(box["size"], 3, where, "size"), "rotation": _numbers(box["rotation"], 4, where, "rotation"),
           "velocity": _numbers(velocity, 2, where, "velocity", allow_nan=True),
           "detection_name": str(box["detection_name"]),
           "detection_score": _numbers([box["detection_score"]], 1, where, "detection_score")[0],
           "attribute_name": str(box.get("attribute_name", ""))}
    if max(abs(x) for x in rec["translation"]) > MAX_COORDINATE_M:
        raise ValidationError(f"{where}: translation {rec['translation']} lies beyond {MAX_COORDINATE_M:g} m")
    if min(rec["size"]) <= 0 or max(rec["size"]) > MAX_BOX_SIZE_M:
        raise ValidationError(f"{where}: sizes must be positive and at most {MAX_BOX_SIZE_M:g} m; got {rec['size']}")
    if math.sqrt(sum(x * x for x in rec["rotation"])) < MIN_QUATERNION_NORM:
        raise ValidationError(f"{where}: the rotation {rec['rotation']} is not a quaternion (norm below "
                              f"{MIN_QUATERNION_NORM:g})")
    if any(abs(v) > MAX_SPEED_MPS for v in rec["velocity"] if not math.isnan(v)):
        raise ValidationError(f"{where}: velocity {rec['velocity']} is beyond {MAX_SPEED_MPS:g} m/s")
    if not 0.0 <= rec["detection_score"] <= 1.0:
        raise ValidationError(f"{where}: detection_score must lie in [0, 1]; got {rec['detection_score']}")
    if rec["detection_name"] not in DETECTION_NAMES:
        raise ValidationError(f"{where}: unknown detection_name {rec['detection_name']!r}; one of {DETECTION_NAMES}")
    allowed = CLASS_ATTRIBUTES[rec["detection_name"]]
    if rec["attribute_name"] and rec["attribute_name"] not in allowed:
        raise ValidationError(f"{where}: attribute {rec['attribute_name']!r} does not belong to "
                              f"{rec['detection_name']} (one of {allowed or 'none'})")
    return rec


def evaluated_classes(gt: Boxes, racks: dict[str, np.ndarray]) -> tuple[str, ...]:
    """The detection classes among the ground-truth boxes the protocol evaluates (``filter_boxes``), sorted."""
    return tuple(sorted(set(filter_boxes(gt, DetectionConfig(), racks).name)))


def evaluated_ground_truth(tables: NuScenesTables, samples: list[str], camera_view: bool = False
                           ) -> tuple[Boxes, dict[str, np.ndarray]]:
    """``load_ground_truth``, less the boxes no camera of their sample sees when ``camera_view``
    (``in_camera_view``)."""
    gt, racks = load_ground_truth(tables, samples)
    if camera_view:
        gt = gt.take(in_camera_view(gt, camera_frustums(tables, samples)))
    return gt, racks


def evaluate_detection_results(dataroot: str | Path, version: str, results: str | Path,
                               scenes: list[str] | None = None, config: DetectionConfig = DetectionConfig(),
                               camera_view: bool = False):
    """The protocol end to end: ground truth of ``scenes`` (all when None) of a dataroot, the results file's
    predictions for exactly those samples, both filtered, then ``detection.evaluate``. ``camera_view``: ground
    truth and predictions alike only where a camera sees them (``in_camera_view``); nuScenes' own protocol has no
    such filter, as its six cameras look all round. A results file that is not a regular file or not JSON is refused
    first, before any table is read."""
    data = read_detection_results(results)
    tables = NuScenesTables.load(dataroot, version)
    samples = tables.scene_samples(scenes)
    if not samples:
        raise ValidationError(f"{Path(dataroot) / version} has no samples to evaluate")
    gt, racks = evaluated_ground_truth(tables, samples, camera_view)
    pred, meta = load_results(results, tables, samples, config, camera_view, data=data)
    metrics = evaluate(filter_boxes(gt, config, racks), filter_boxes(pred, config, racks), config)
    return metrics, {"n_samples": len(samples), "meta": meta, "camera_view": bool(camera_view)}


# ----------------------------------------------------------------------------- planning
#: UniAD's planning frame (x right, y forward) in the ego frame (x forward, y left): ego = R @ planning.
EGO_FROM_PLANNING = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
#: How far keyframes may be from the metrics' 0.5 s spacing (s).
STEP_TOLERANCE_S = 0.1


def _transform(record: dict) -> np.ndarray:  # a record's translation + rotation -> [4, 4]

    return make_transform(quat_to_rotmat(np.asarray(record["rotation"], np.float64)), record["translation"])


def world_from_planning(tables: NuScenesTables, sample_token: str) -> np.ndarray:
    """UniAD's planning frame of a keyframe: origin at the LIDAR_TOP sensor, x to the ego's right, y forward."""
    sd = tables.reference_data(sample_token)
    world_from_ego = _transform(tables["ego_pose"][sd["ego_pose_token"]])
    world_from_lidar = world_from_ego @ _transform(tables["calibrated_sensor"][sd["calibrated_sensor_token"]])
    T = np.eye(4)
    T[:3, :3] = world_from_ego[:3, :3] @ EGO_FROM_PLANNING
    T[:3, 3] = world_from_lidar[:3, 3]
    return T


def load_planning_samples(tables: NuScenesTables, samples: list[str], steps: int | None = None):
    """The evaluated keyframes of ``samples``: those with ``steps`` future keyframes in their scene, each with the
    true future of the LiDAR origin and the vehicle boxes at each step in its planning frame. Returns the samples
    and how many keyframes had too short a future."""
    steps = STEPS if steps is None else steps
    anns_by_sample: dict[str, list[dict]] = {}
    for ann in tables["sample_annotation"].values():
        anns_by_sample.setdefault(ann["sample_token"], []).append(ann)
    out, short = [], 0
    for token in samples:
        future = tables.chain("sample", token, f"sample {token}", limit=steps + 1)[1:]
        if len(future) < steps:
            short += 1
            continue
        stamps = np.array([tables["sample"][s]["timestamp"] for s in [token, *future]], np.float64) * 1e-6
        gaps = np.diff(stamps)
        if np.any(np.abs(gaps - STEP_S) > STEP_TOLERANCE_S):
            raise ValidationError(f"keyframes after {token} are {gaps.round(3).tolist()} s apart; the planning metrics "
                                  f"take one waypoint every {STEP_S} s (export with keyframes at 2 Hz)")
        planning_from_world = np.linalg.inv(world_from_planning(tables, token))
        trajectory, vehicles = [], []
        for s in future:
            trajectory.append((planning_from_world @ world_from_planning(tables, s)[:, 3])[:2])
            boxes = []
            for ann in anns_by_sample.get(s, []):
                cat = tables["category"][tables["instance"][ann["instance_token"]]["category_token"]]["name"]
                if not cat.startswith("vehicle."):
                    continue
                box = planning_from_world @ _transform(ann)
                w, length = ann["size"][0], ann["size"][1]
                boxes.append([box[0, 3], box[1, 3], length, w, np.arctan2(box[1, 0], box[0, 0])])
            vehicles.append(np.array(boxes, np.float64).reshape(-1, 5))
        out.append(PlanningSample(token, np.array(trajectory), np.ones(steps, bool), tuple(vehicles)))
    return out, short


def read_planning_results(path: str | Path):
    """The JSON value of a planning results file, read as untrusted (``omniscs.untrusted``): a FIFO, a device, a
    folder, hostile or invalid JSON is one ValidationError naming the file; its content is checked by
    ``load_planning_results``."""
    return read_json(path, "give planning results ({'results': {sample_token: {'trajectory': [[x, y], ...]}}})",
                     max_bytes=MAX_RESULTS_BYTES, what="planning results", error=ValidationError)


def load_planning_results(path: str | Path, samples: list[str], steps: int | None = None,
                          allowed: list[str] | None = None, data=None) -> dict[str, np.ndarray]:
    """Planned trajectories: ``{"results": {sample_token: {"trajectory": [[x, y], ...]}}}`` (or the token mapped
    straight to the waypoints), in the planning frame; every evaluated sample must be there, and no token outside
    ``allowed`` (default: ``samples``; e.g. a scene's last keyframes, which have no full future, may be there).
    ``data``: the file's JSON value when the caller read it already (``read_planning_results``)."""
    steps = STEPS if steps is None else steps
    data = read_planning_results(path) if data is None else data
    results = data.get("results") if isinstance(data, dict) else None
    if not isinstance(results, dict):
        raise ValidationError(f"planning results {path} must be an object with a 'results' object "
                              "(sample token -> {'trajectory': [[x, y], ...]})")
    unknown = sorted(set(results) - set(samples if allowed is None else allowed))
    if unknown:
        raise ValidationError(f"planning results {path} name {len(unknown)} sample(s) not evaluated here, e.g. "
                              f"{unknown[0]!r}")
    out = {}
    for token in samples:
        entry = results.get(token)
        if entry is None:
            raise ValidationError(f"planning results {path} lack sample {token!r}")
        traj = entry.get("trajectory") if isinstance(entry, dict) else entry
        if not isinstance(traj, list) or not all(
                isinstance(w, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in w)
                for w in traj):
            raise ValidationError(f"results[{token!r}] must be a list of (x, y) waypoints of JSON numbers (not "
                                  "strings or booleans)")
        try:
            arr = np.asarray(traj, np.float64)
        except (TypeError, ValueError) as e:
            raise ValidationError(f"results[{token!r}] is not a list of (x, y) waypoints ({e})") from e
        if arr.ndim != 2 or arr.shape[1] < 2 or arr.shape[0] < steps or not np.isfinite(arr[:steps, :2]).all():
            raise ValidationError(f"results[{token!r}] must hold at least {steps} finite (x, y) waypoints; got shape "
                                  f"{arr.shape}")
        if np.abs(arr[:steps, :2]).max() > MAX_COORDINATE_M:
            raise ValidationError(f"results[{token!r}]: a waypoint lies beyond {MAX_COORDINATE_M:g} m of the ego")
        out[token] = arr[:steps, :2]
    return out


def evaluate_planning_results(dataroot: str | Path, version: str | None, results: str | Path,
                              scenes: list[str] | None = None, on_coverage=None) -> dict:
    """UniAD's planning metrics of a results file over the keyframes of ``scenes`` that have a full future.
    ``on_coverage(n_with_future, n_keyframes)`` hears how many there are before the results are read; none is an
    error saying how long a scene must be. A results file that is not a regular file or not JSON is refused first,
    before any table is read."""
    data = read_planning_results(results)
    tables = NuScenesTables.load(dataroot, version)
    keyframes = tables.scene_samples(scenes)
    samples, short = load_planning_samples(tables, keyframes)
    if on_coverage is not None:
        on_coverage(len(samples), len(keyframes))
    if not samples:
        longest = max((s["nbr_samples"] for s in tables["scene"].values()), default=0)
        raise ValidationError(f"no keyframe of {Path(dataroot) / tables.version} has the {STEPS * STEP_S:g} s of "
                              f"future the planning metrics need: a scene needs at least {STEPS + 1} keyframes at "
                              f"2 Hz ({frames_for_planning(10.0)} frames at 10 Hz) and the longest here has "
                              f"{longest}; make the logs longer (e.g. --frames 40)")
    predictions = load_planning_results(results, [s.token for s in samples], allowed=keyframes, data=data)
    out = evaluate_planning(samples, predictions)
    out["n_short_future"] = short
    return out
