"""nuScenes v1.0 reader: one scene of a dataroot, read through nuscenes-devkit, into the scene store.

Reads the 13 tables (scene, sample, sample_data, sample_annotation, instance, category, attribute, visibility,
ego_pose, calibrated_sensor, sensor, log, map), the CAM_* images and the LIDAR_TOP ``.pcd.bin`` sweeps
(float32 x, y, z, intensity, ring in the sensor frame; moved to the ego frame). Frames are the 2 Hz keyframes
(samples), or with ``sweeps`` every LIDAR_TOP sample_data between the first and last keyframe, with each camera's
image nearest in time and annotations interpolated between an instance's neighbouring annotations (linear centre,
slerped rotation). A frame's time and ego pose are those of its LIDAR_TOP sample_data (or of the first camera
when the log has no LiDAR); nuScenes cameras fire up to ~40 ms from the LiDAR, and the store keeps one ego pose
per frame, so image-to-pose timing is as in the dataset's own keyframes.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from omniscs.checks import is_int
from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import make_transform
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene.sources.common import (
    BadFrame,
    DatasetSource,
    FrameData,
    FramePlan,
    RawBox,
    check_camera,
    fingerprint,
    interpolate_pose,
    json_value,
    read_float32_records,
    read_image_file,
    require_file,
    select_cameras,
)
from omniscs.scene.store import CameraRecord
from omniscs.untrusted import MAX_TABLE_BYTES, read_json

#: The v1.0 tables, in the order the devkit loads them.
TABLES: tuple[str, ...] = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor",
                           "ego_pose", "log", "scene", "sample", "sample_data", "sample_annotation", "map")

#: The 23 nuScenes v1.0 object categories with a short description, and the project class each maps to
#: (None: no project class; such boxes are left out and counted in the manifest's ``dropped_boxes``).
CATEGORIES: dict[str, tuple[str, str | None]] = {
    "human.pedestrian.adult": ("Adult walking, standing or sitting.", "pedestrian"),
    "human.pedestrian.child": ("Child walking, standing or sitting.", "pedestrian"),
    "human.pedestrian.construction_worker": ("Person working at a construction site.", "pedestrian"),
    "human.pedestrian.personal_mobility": ("Person on a scooter, skateboard or segway.", "pedestrian"),
    "human.pedestrian.police_officer": ("Police officer.", "pedestrian"),
    "human.pedestrian.stroller": ("Stroller, with or without a child.", "pedestrian"),
    "human.pedestrian.wheelchair": ("Wheelchair, with or without a person.", "pedestrian"),
    "animal": ("Animal.", None),
    "vehicle.car": ("Car, van, SUV or pick-up meant for up to 7 people.", "car"),
    "vehicle.emergency.police": ("Police car or motorcycle.", "car"),
    "vehicle.emergency.ambulance": ("Ambulance.", "truck"),
    "vehicle.truck": ("Vehicle for cargo: pick-up with a cargo bed, box truck, lorry, semi tractor.", "truck"),
    "vehicle.bus.bendy": ("Articulated bus.", "bus"),
    "vehicle.bus.rigid": ("Rigid bus.", "bus"),
    "vehicle.trailer": ("Trailer towed by a vehicle.", "trailer"),
    "vehicle.construction": ("Construction vehicle: excavator, loader, crane, bulldozer.", "construction_vehicle"),
    "vehicle.motorcycle": ("Motorcycle or moped, with or without a rider.", "motorcycle"),
    "vehicle.bicycle": ("Bicycle, with or without a rider.", "bicycle"),
    "movable_object.barrier": ("Temporary road barrier.", "barrier"),
    "movable_object.trafficcone": ("Traffic cone.", "traffic_cone"),
    "movable_object.pushable_pullable": ("Object pushed or pulled by a person: bin, dolly, cart.", "debris"),
    "movable_object.debris": ("Debris or movable object left on the road.", "debris"),
    "static_object.bicycle_rack": ("Rack for parking bicycles.", None),
}

#: The 8 nuScenes attributes with a short description.
ATTRIBUTES: dict[str, str] = {
    "vehicle.moving": "Vehicle is moving.",
    "vehicle.stopped": "Vehicle with a driver is stopped (e.g. at a traffic light).",
    "vehicle.parked": "Vehicle is parked without a driver.",
    "cycle.with_rider": "There is a rider on the bicycle or motorcycle.",
    "cycle.without_rider": "There is no rider on the bicycle or motorcycle.",
    "pedestrian.sitting_lying_down": "Pedestrian is sitting or lying down.",
    "pedestrian.standing": "Pedestrian is standing.",
    "pedestrian.moving": "Pedestrian is moving.",
}

#: nuScenes visibility levels: token, level and description (fraction of the object visible in all cameras).
VISIBILITY: tuple[tuple[str, str, str], ...] = (
    ("1", "v0-40", "visibility of whole object is between 0 and 40%"),
    ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
    ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
    ("4", "v80-100", "visibility of whole object is between 80 and 100%"),
)

#: Channel order of the six nuScenes cameras (the order cameras appear in the store).
CAMERA_ORDER: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                                 "CAM_BACK_RIGHT")
LIDAR_CHANNEL = "LIDAR_TOP"
#: Floats per LIDAR_TOP point in a ``.pcd.bin``: x, y, z, intensity, ring index.
LIDAR_VALUES_PER_POINT = 5

#: Sweeps mode: a camera image further than this from the LiDAR sweep's time leaves the frame without it.
MAX_CAMERA_OFFSET_US = 60_000


def find_version(root: Path, version: str | None) -> str:
    """The table version folder to read: ``version`` when given, else the only ``v1.0-*`` folder."""
    if not root.is_dir():
        raise OmniscsError(f"nuScenes dataroot {root} does not exist")
    found = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v1.0"))
    if version is not None:
        if version not in found:
            raise OmniscsError(f"{root} has no nuScenes table folder {version!r}; it has {found or 'none'}"
                               + (f" (name {found[0]!r} as the version, or leave it out)" if len(found) == 1 else ""))
        return version
    if not found:
        raise OmniscsError(f"{root} is not a nuScenes dataroot: it has no v1.0-* table folder; point at the folder "
                           "that holds v1.0-mini/ (or v1.0-trainval/) and samples/")
    if len(found) != 1:
        raise OmniscsError(f"{root}: name the nuScenes version (found {found})")
    return found[0]


def table_paths(root: Path, version: str) -> list[Path]:
    return [root / version / f"{t}.json" for t in TABLES]


def open_nuscenes(root: Path, version: str):
    """The devkit's NuScenes object; a missing, corrupt or inconsistent table is a ValidationError."""
    for path, table in zip(table_paths(root, version), TABLES):
        require_file(path, f"nuScenes table {table!r}")
        if path.stat().st_size > MAX_TABLE_BYTES:  # the devkit reads tables whole: refuse before it does
            raise ValidationError(f"{path}: nuScenes table {table!r} is {path.stat().st_size:,} bytes, more than the "
                                  f"{MAX_TABLE_BYTES:,} allowed; give the dataroot's own table")
    stamp = tuple(tuple(x) for x in fingerprint(table_paths(root, version), root))
    return _open_cached(str(root), version, stamp)


@lru_cache(maxsize=1)
def _open_cached(root: str, version: str, stamp: tuple):  # stamp: file sizes and times, so edits reload
    from nuscenes.nuscenes import NuScenes

    from omniscs.export.devkit import patch_nuscenes_devkit

    patch_nuscenes_devkit()  # the object handed out renders under numpy 2 too

    try:
        return NuScenes(version=version, dataroot=root, verbose=False)
    except KeyError as exc:
        problem = table_problem(Path(root), version)
        raise ValidationError(problem or f"{Path(root) / version}: tables are inconsistent: token {exc} is "
                                         "referenced but not defined") from None
    except Exception as exc:  # the devkit asserts, indexes and raises plain Exceptions on malformed tables
        problem = table_problem(Path(root), version)
        detail = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise ValidationError(problem or f"{Path(root) / version}: the devkit cannot load the tables "
                                         f"({detail})") from None


def _is_str(v) -> bool:
    return isinstance(v, str)


def _numbers(n: int):
    def check(v) -> bool:
        return (isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                             and np.isfinite(x) for x in v))
    return check


def _intrinsic(v) -> bool:
    return v == [] or (isinstance(v, list) and len(v) == 3 and all(_numbers(3)(row) for row in v))


def _str_list(v) -> bool:
    return isinstance(v, list) and all(isinstance(x, str) for x in v)


#: Fields the devkit and this reader use, per table, with what each must hold ("?" prefix: optional).
TABLE_FIELDS: dict[str, dict[str, tuple]] = {
    "category": {"token": (_is_str, "a string"), "name": (_is_str, "a string")},
    "attribute": {"token": (_is_str, "a string"), "name": (_is_str, "a string")},
    "visibility": {"token": (_is_str, "a string"), "level": (_is_str, "a string")},
    "instance": {"token": (_is_str, "a string"), "category_token": (_is_str, "a string")},
    "sensor": {"token": (_is_str, "a string"), "channel": (_is_str, "a string"), "modality": (_is_str, "a string")},
    "calibrated_sensor": {"token": (_is_str, "a string"), "sensor_token": (_is_str, "a string"),
                          "translation": (_numbers(3), "3 finite numbers"),
                          "rotation": (_numbers(4), "4 finite numbers (w, x, y, z)"),
                          "?camera_intrinsic": (_intrinsic, "a 3x3 matrix or []")},
    "ego_pose": {"token": (_is_str, "a string"), "translation": (_numbers(3), "3 finite numbers"),
                 "rotation": (_numbers(4), "4 finite numbers (w, x, y, z)"), "timestamp": (is_int, "an integer")},
    "log": {"token": (_is_str, "a string")},
    "scene": {"token": (_is_str, "a string"), "name": (_is_str, "a string"), "log_token": (_is_str, "a string"),
              "first_sample_token": (_is_str, "a string")},
    "sample": {"token": (_is_str, "a string"), "timestamp": (is_int, "an integer"), "next": (_is_str, "a string")},
    "sample_data": {"token": (_is_str, "a string"), "sample_token": (_is_str, "a string"),
                    "ego_pose_token": (_is_str, "a string"), "calibrated_sensor_token": (_is_str, "a string"),
                    "timestamp": (is_int, "an integer"), "is_key_frame": (lambda v: isinstance(v, bool), "a boolean"),
                    "filename": (_is_str, "a string"), "next": (_is_str, "a string")},
    "sample_annotation": {"token": (_is_str, "a string"), "sample_token": (_is_str, "a string"),
                          "instance_token": (_is_str, "a string"), "translation": (_numbers(3), "3 finite numbers"),
                          "size": (_numbers(3), "3 finite numbers"),
                          "rotation": (_numbers(4), "4 finite numbers (w, x, y, z)"),
                          "?attribute_tokens": (_str_list, "a list of tokens"),
                          "?num_lidar_pts": (is_int, "an integer")},
    "map": {"token": (_is_str, "a string"), "log_tokens": (_str_list, "a list of tokens"),
            "filename": (_is_str, "a string")},
}


def table_problem(root: Path, version: str) -> str | None:
    """The first malformed table, record or field under ``root/version`` as a one-line message naming the file
    (None when every table is a JSON list of records with the fields above). Runs only after a load failed."""
    for table in TABLES:
        path = root / version / f"{table}.json"
        if not path.is_file():
            return f"{path}: nuScenes table {table!r} is missing"
        try:
            rows = read_json(path, "fix or replace the table", max_bytes=MAX_TABLE_BYTES, what="nuScenes table")
        except OmniscsError as exc:
            return str(exc)
        if not isinstance(rows, list):
            return f"{path}: a nuScenes table must be a JSON list of records; got a {type(rows).__name__}"
        if table == "map" and not rows:
            return f"{path}: the map table is empty (every log needs a map record)"
        for i, row in enumerate(rows):
            if not isinstance(row, dict):
                return f"{path}: record {i} is a {type(row).__name__}, not an object"
            for name, (check, what) in TABLE_FIELDS[table].items():
                optional = name.startswith("?")
                name = name.lstrip("?")
                if name not in row:
                    if optional:
                        continue
                    return f"{path}: record {i} ({row.get('token', 'no token')}): field {name} is missing"
                if not check(row[name]):
                    value = repr(row[name])
                    value = value if len(value) <= 40 else value[:37] + "..."
                    return f"{path}: record {i} ({row.get('token', 'no token')}): field {name} must be {what}; got {value}"
    return None


def diagnose(source: DatasetSource) -> str | None:
    """What is malformed in the source's tables, if anything (see ``table_problem``)."""
    root = Path(source.dataroot)
    try:
        version = find_version(root, source.version)
    except OmniscsError as exc:
        return str(exc)
    return table_problem(root, version)


def check_scene(source: DatasetSource) -> None:
    """The tables load and name the source's scene (name or token), whose sample chain ends; else one
    OmniscsError."""
    root = Path(source.dataroot)
    version = find_version(root, source.version)
    nusc = open_nuscenes(root, version)
    sample_chain(nusc, _find_scene(nusc, source.scene, root), root / version)


def sample_chain(nusc, scene: dict, table_root: Path) -> list[dict]:
    """The scene's samples along their ``next`` tokens; a chain that loops or names a sample the table lacks is
    one ValidationError naming sample.json (a damaged or hostile table never hangs the reader)."""
    samples, token, seen = [], scene["first_sample_token"], set()
    while token:
        if token in seen:
            raise ValidationError(f"{table_root / 'sample.json'}: sample chain of scene {scene['name']} loops at "
                                  f"{token}; fix the table's next tokens")
        try:
            sample = nusc.get("sample", token)
        except KeyError:
            raise ValidationError(f"{table_root / 'sample.json'}: sample chain of scene {scene['name']} names "
                                  f"{token}, which the table lacks") from None
        seen.add(token)
        samples.append(sample)
        token = sample["next"]
    return samples


def dataset_files(source: DatasetSource) -> list[Path]:
    """The files whose change makes a stored copy of the scene stale (the tables)."""
    root = Path(source.dataroot)
    return table_paths(root, find_version(root, source.version))


def list_scenes(dataroot: str | Path, version: str | None = None) -> list[str]:
    root = Path(dataroot)
    version = find_version(root, version)
    names = [s.get("name") for s in open_nuscenes(root, version).scene]
    if not all(isinstance(n, str) and n for n in names):
        raise ValidationError(table_problem(root, version) or f"{root / version / 'scene.json'}: every scene needs a "
                                                              "non-empty string name")
    return names


def _find_scene(nusc, name: str | None, where: Path) -> dict:
    if name is None:
        if len(nusc.scene) != 1:
            raise OmniscsError(f"{where} holds {len(nusc.scene)} scenes; name one, e.g. "
                               f"nuscenes:{where}:{nusc.scene[0]['name'] if nusc.scene else 'scene-0001'}")
        return nusc.scene[0]
    for s in nusc.scene:
        if name in (s["name"], s["token"]):
            return s
    raise OmniscsError(f"{where} has no scene {name!r}; it has {[s['name'] for s in nusc.scene][:20]}")


def _pose(record: dict) -> np.ndarray:  # a record with translation and rotation (w, x, y, z) -> [4, 4]
    return make_transform(quat_to_rotmat(np.asarray(record["rotation"], dtype=np.float64)),
                          np.asarray(record["translation"], dtype=np.float64))


@dataclass
class _Frame:
    plan: FramePlan
    sample_data: dict[str, str | None]  # channel -> sample_data token (None: no image near enough)
    sample_token: str | None  # keyframes mode: the sample whose annotations are the boxes


class NuScenesReader:
    """Opened on one nuScenes scene; see the module docstring for frames, poses and interpolation."""

    def __init__(self, source: DatasetSource):
        self.source = source
        self.root = Path(source.dataroot)
        self.version = find_version(self.root, source.version)
        self.table_root = self.root / self.version
        try:
            self._open(source)
        except KeyError as exc:
            raise ValidationError(table_problem(self.root, self.version) or
                                  f"{self.table_root}: tables are inconsistent: token {exc} (scene "
                                  f"{source.scene}) is referenced but not defined") from None

    def _open(self, source: DatasetSource) -> None:
        nusc = self.nusc = open_nuscenes(self.root, self.version)
        self.scene = _find_scene(nusc, source.scene, self.root)
        self.samples = self._samples()
        channels = list(self.samples[0]["data"])
        cam_channels = sorted((c for c in channels if c.startswith("CAM_")),
                              key=lambda c: (CAMERA_ORDER.index(c) if c in CAMERA_ORDER else len(CAMERA_ORDER), c))
        where = f"nuScenes scene {self.scene['name']}"
        self.camera_channels = select_cameras(cam_channels, source.cameras, where)
        if not self.camera_channels:
            raise ValidationError(f"{self.table_root / 'sample_data.json'}: {where} has no camera sample_data")
        self.has_lidar = LIDAR_CHANNEL in channels
        self.ref_channel = LIDAR_CHANNEL if self.has_lidar else self.camera_channels[0]
        first = self.samples[0]["data"]
        self._calib = {ch: nusc.get("calibrated_sensor", nusc.get("sample_data", first[ch])["calibrated_sensor_token"])
                       for ch in self.camera_channels + ([LIDAR_CHANNEL] if self.has_lidar else [])}
        self.cameras = [check_camera(self._camera(ch, first[ch]), self.table_root / "calibrated_sensor.json")
                        for ch in self.camera_channels]
        self._frames = self._sweep_frames() if source.sweeps else self._keyframes()
        self.frames = [f.plan for f in self._frames]
        self._tracks = self._annotations_by_instance() if source.sweeps else {}
        log = nusc.get("log", self.scene["log_token"])
        self.extra = {
            "source_scene_id": self.scene["name"], "source_scene_token": self.scene["token"],
            "location": log.get("location"), "logfile": log.get("logfile"), "version": self.version,
            "frame_mode": "sweeps" if source.sweeps else "keyframes",
            "ego_from_lidar": (_pose(self._calib[LIDAR_CHANNEL]).reshape(16).tolist() if self.has_lidar else None),
            "dataset_fingerprint": fingerprint(dataset_files(source), self.root),
        }

    # ------------------------------------------------------------------ plan
    def _samples(self) -> list[dict]:
        return sample_chain(self.nusc, self.scene, self.table_root)

    def _camera(self, channel: str, sd_token: str) -> CameraRecord:
        sd = self.nusc.get("sample_data", sd_token)
        cs = self._calib[channel]
        K = np.asarray(cs.get("camera_intrinsic") or [], dtype=np.float64)
        if K.shape != (3, 3):
            raise ValidationError(f"{self.table_root / 'calibrated_sensor.json'}: {channel} record {cs['token']}: "
                                  "field camera_intrinsic is not a 3x3 matrix")
        width, height = int(sd.get("width") or 0), int(sd.get("height") or 0)
        if width <= 0 or height <= 0:
            rgb = read_image_file(self.root / sd["filename"])
            height, width = rgb.shape[:2]
        return CameraRecord(channel, width, height, K, _pose(cs))

    def _keyframes(self) -> list[_Frame]:
        frames = []
        for sample in self.samples:
            ref = sample["data"].get(self.ref_channel)
            pose_sd = ref or next(iter(sample["data"].values()))
            plan = FramePlan(sample["token"], int(sample["timestamp"]), self._ego_pose(pose_sd))
            frames.append(_Frame(plan, {ch: sample["data"].get(ch) for ch in self._channels()}, sample["token"]))
        return frames

    def _channels(self) -> list[str]:
        return self.camera_channels + ([LIDAR_CHANNEL] if self.has_lidar else [])

    def _chain(self, channel: str, t_end: int) -> list[dict]:
        """sample_data of ``channel`` from the first keyframe's forward, until after ``t_end``."""
        token = self.samples[0]["data"].get(channel)
        out, seen = [], set()
        while token:
            if token in seen:
                raise ValidationError(f"{self.table_root / 'sample_data.json'}: {channel} sample_data chain of scene "
                                      f"{self.scene['name']} loops at {token}; fix the table's next tokens")
            seen.add(token)
            sd = self.nusc.get("sample_data", token)
            out.append(sd)
            if sd["timestamp"] > t_end:
                break
            token = sd["next"]
        return out

    def _sweep_frames(self) -> list[_Frame]:
        t_last = int(self.samples[-1]["timestamp"])
        t_end_ref = int(self.nusc.get("sample_data", self.samples[-1]["data"][self.ref_channel])["timestamp"])
        refs = [sd for sd in self._chain(self.ref_channel, t_end_ref) if sd["timestamp"] <= t_end_ref]
        cams = {ch: self._chain(ch, t_last + MAX_CAMERA_OFFSET_US) for ch in self.camera_channels}
        cam_times = {ch: np.array([sd["timestamp"] for sd in chain], dtype=np.int64) for ch, chain in cams.items()}
        frames = []
        for sd in refs:
            t = int(sd["timestamp"])
            chosen: dict[str, str | None] = {self.ref_channel: sd["token"]}
            for ch in self.camera_channels:
                if ch == self.ref_channel:
                    continue
                j = int(np.argmin(np.abs(cam_times[ch] - t))) if len(cam_times[ch]) else -1
                near = j >= 0 and abs(int(cam_times[ch][j]) - t) <= MAX_CAMERA_OFFSET_US
                chosen[ch] = cams[ch][j]["token"] if near else None
            frames.append(_Frame(FramePlan(sd["token"], t, self._ego_pose(sd["token"])), chosen,
                                 sd["sample_token"] if sd["is_key_frame"] else None))
        return frames

    def _ego_pose(self, sd_token: str) -> np.ndarray:
        sd = self.nusc.get("sample_data", sd_token)
        return _pose(self.nusc.get("ego_pose", sd["ego_pose_token"]))

    def _annotations_by_instance(self) -> dict[str, list[tuple[int, dict]]]:
        tracks: dict[str, list[tuple[int, dict]]] = {}
        for sample in self.samples:
            for ann_token in self.nusc.get("sample", sample["token"])["anns"]:
                ann = self.nusc.get("sample_annotation", ann_token)
                tracks.setdefault(ann["instance_token"], []).append((int(sample["timestamp"]), ann))
        return tracks

    # ------------------------------------------------------------------ frames
    def frame_files(self, i: int) -> list[tuple[Path, str, int | None]]:
        """The image and LiDAR files frame ``i`` reads: (path, what, bytes per point or None)."""
        frame = self._frames[i]
        out = []
        for cam in self.cameras:
            token = frame.sample_data.get(cam.name)
            if token is not None:
                out.append((self.root / self.nusc.get("sample_data", token)["filename"], "image file", None))
        token = frame.sample_data.get(LIDAR_CHANNEL) if self.has_lidar else None
        if token is not None:
            out.append((self.root / self.nusc.get("sample_data", token)["filename"], "LiDAR file",
                        4 * LIDAR_VALUES_PER_POINT))
        return out

    def load_frame(self, i: int) -> FrameData:
        try:
            return self._load_frame(self._frames[i])
        except KeyError as exc:
            raise ValidationError(f"{self.table_root}: tables are inconsistent: token {exc} (frame "
                                  f"{self._frames[i].plan.key}) is referenced but not defined") from None

    def _load_frame(self, frame: _Frame) -> FrameData:
        images = {}
        for cam in self.cameras:
            token = frame.sample_data.get(cam.name)
            if token is None:
                raise BadFrame(f"{self.table_root / 'sample_data.json'}: no {cam.name} sample_data near "
                               f"frame {frame.plan.key}")
            sd = self._sample_data(token, cam.name)
            images[cam.name] = read_image_file(self.root / sd["filename"], (cam.width, cam.height))
        lidar = None
        if self.has_lidar:
            token = frame.sample_data.get(LIDAR_CHANNEL)
            if token is None:
                raise BadFrame(f"{self.table_root / 'sample_data.json'}: no {LIDAR_CHANNEL} sample_data in "
                               f"sample {frame.plan.key}")
            sd = self._sample_data(token, LIDAR_CHANNEL)
            raw = read_float32_records(self.root / sd["filename"], LIDAR_VALUES_PER_POINT)
            ego_from_lidar = _pose(self._calib[LIDAR_CHANNEL])
            xyz = raw[:, :3].astype(np.float64) @ ego_from_lidar[:3, :3].T + ego_from_lidar[:3, 3]
            lidar = np.concatenate([xyz, raw[:, 3:4]], axis=1).astype(np.float32)
        if frame.sample_token is not None:
            anns = [self.nusc.get("sample_annotation", t) for t in self.nusc.get("sample", frame.sample_token)["anns"]]
            boxes = [self._box(ann, _pose(ann), keyframe=True) for ann in anns]
        else:
            boxes = self._interpolated_boxes(frame.plan.timestamp_us)
        return FrameData(images=images, lidar=lidar, boxes=boxes)

    def _sample_data(self, token: str, channel: str) -> dict:
        sd = self.nusc.get("sample_data", token)
        if sd["calibrated_sensor_token"] != self._calib[channel]["token"]:
            cs = self.nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            if not np.allclose(_pose(cs), _pose(self._calib[channel])) or (
                    cs.get("camera_intrinsic") != self._calib[channel].get("camera_intrinsic")):
                raise ValidationError(f"{self.table_root / 'calibrated_sensor.json'}: {channel} calibration changes "
                                      f"within scene {self.scene['name']} (sample_data {token}); the store keeps one")
        return sd

    def _box(self, ann: dict, global_from_box: np.ndarray, keyframe: bool) -> RawBox:
        where = f"{self.table_root / 'sample_annotation.json'}: annotation {ann['token']}"
        size = np.asarray(ann.get("size") or [], dtype=np.float64)
        if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise BadFrame(f"{where}: field size {ann.get('size')} must be three positive numbers")
        name = self.nusc.get("category", self.nusc.get("instance", ann["instance_token"])["category_token"])["name"]
        category = CATEGORIES.get(name, (None, None))[1]
        attrs = {"instance_token": ann["instance_token"],
                 "attribute": json_value([self.nusc.get("attribute", t)["name"] for t in ann.get("attribute_tokens", [])])}
        if ann.get("visibility_token"):
            attrs["visibility"] = self.nusc.get("visibility", ann["visibility_token"])["level"]
        if keyframe:
            attrs["annotation_token"] = ann["token"]
        return RawBox(track_key=ann["instance_token"], category=category, source_category=name,
                      global_from_box=global_from_box, size=np.array([size[1], size[0], size[2]]),
                      num_lidar_points=int(ann.get("num_lidar_pts", -1)) if keyframe else -1, attributes=attrs)

    def _interpolated_boxes(self, t: int) -> list[RawBox]:
        """Boxes at time ``t`` between an instance's neighbouring annotations (none outside its annotated span)."""
        boxes = []
        for anns in self._tracks.values():
            times = np.array([ts for ts, _ in anns], dtype=np.int64)
            j = int(np.searchsorted(times, t, side="right")) - 1
            if j < 0 or (j == len(anns) - 1 and times[j] != t):
                continue
            t0, a0 = anns[j]
            if t0 == t:
                boxes.append(self._box(a0, _pose(a0), keyframe=False))
                continue
            t1, a1 = anns[j + 1]
            pose = interpolate_pose(_pose(a0), _pose(a1), (t - t0) / (t1 - t0))
            boxes.append(self._box(a0, pose, keyframe=False))
        return boxes
