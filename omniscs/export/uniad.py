"""UniAD training data: a nuScenes dataroot with map expansions, the info pickles UniAD's data converter writes
(``<prefix>_infos_temporal_{train,val}.pkl``) and the motion anchors its motion head loads, in one folder.

Output layout (UniAD's ``data/`` folder): ``nuscenes/`` (the dataroot, ``omniscs.export.nuscenes``), ``infos/``
(the pickles) and ``others/motion_anchor_infos_mode6.pkl``. UniAD's dataset opens the map expansions of all four
nuScenes locations, so a location that no log names gets an empty (valid) expansion; a location of a recorded
nuScenes log gets none (copy the real ``maps/expansion`` file there). Infos are built from the written tables through the
nuscenes-devkit, field by field as ``tools/data_converter/uniad_nuscenes_converter.py`` of OpenDriveLab/UniAD does:
boxes in the LIDAR_TOP frame of each keyframe, ``gt_velocity`` from ``NuScenes.box_velocity`` turned into that frame
(NaN, for an agent seen at one keyframe only, becomes 0 as UniAD's loader makes it), ``gt_inds`` the instance table
index, ``fut_traj`` [N, 16, 2] from ``PredictHelper.get_future_for_agent`` (8 s at 2 Hz, agent frame) with its
mask, ``visibility_tokens`` the visibility level (1..4) as int, names mapped to the ten detection classes like
mmdet3d's ``NuScenesDataset.NameMapping`` (unmapped categories keep their nuScenes name; UniAD ignores them).
Differences, because there is no CAN bus: ``can_bus`` (18 floats: translation 3, rotation quaternion w,x,y,z 4,
acceleration 3, angular velocity 3, velocity 3, then 0, 0) takes the motion from finite differences of the ego
poses of the LIDAR_TOP sweeps (central where both neighbours exist; ego frame; gravity not included). Paths are
``data_path_prefix`` + the dataroot-relative file name (UniAD's released infos use ``./data/nuscenes/...``).

**Box conventions** (``box_convention``). UniAD's branches write ``gt_boxes`` [N, 7] (centre x, y, z in the LiDAR
frame, three sizes, one yaw) differently:
  * ``"v1"`` (main branch, mmdet3d 0.17): sizes (w, l, h), yaw ``-yaw - pi/2`` of the nuScenes box.
  * ``"v2"`` (v2.0 branch, mmdet3d 1.0.0rc6): sizes (w, l, h), the nuScenes yaw unchanged.
``tests/export/test_export_uniad.py`` decodes the 8 corners of every written box with each branch's loader math
(``LiDARInstance3DBoxes(gt_boxes, origin=(0.5, 0.5, 0.5)).corners`` of that mmdet3d version) and compares them with
the scene store's box corners in the LiDAR frame: **v1 projects correctly under v1's loader**; v2 under v2's loader
(mmdet3d 1.x rotates counter-clockwise and reads sizes as x, y, z extents) puts the width along the heading, i.e. the
box turned by 90 degrees. The v2 numbers come back right only through the v2 branch's evaluation path
(``output_to_nusc_box``: a nuScenes ``Box`` that reads the sizes as w, l, h), which the test also shows.

**Motion anchors** (``motion_anchor_infos_mode6.pkl``): ``{'anchors_all': [4 float32 arrays [modes, 12, 2]], ...}``
for UniAD's class groups in its order (vehicle: car, truck, construction_vehicle, bus, trailer; bike: motorcycle,
bicycle; pedestrian; others: barrier, traffic_cone), each the k-means centres (scikit-learn, fixed seed) of the
12-step (6 s) futures of that group's agents in their own frame (the PredictHelper agent frame: +y along the
heading, +x to the right), over agents whose 12 future steps are all known. A group with fewer than
``anchor_min_samples`` such futures (short logs: a 4 s log has no 6 s future) adds the futures known for at least
``anchor_min_known`` steps, continued to 12 steps at their last step's velocity, and is clustered when that gives
at least ``anchor_modes`` distinct futures; a group with fewer still gets straight lines at the group's median speed
(``FALLBACK_SPEED_MPS`` when it has no agents), fanned over ``FALLBACK_FAN_RAD``, and a warning says so. Counts
(complete and extended futures), speeds and which groups fell back are recorded beside.

Pickles hold only builtins and arrays reduced to ``numpy.ndarray(shape, dtype, buffer)``, so the numpy 1.x that
UniAD runs on loads what numpy 2 wrote here.
"""
from __future__ import annotations

import json
import logging
import pickle
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.export.nuscenes import DEFAULT_VERSION, write_nuscenes
from omniscs.export.nuscenes_map import DEFAULT_LOCATION, NUSCENES_LOCATIONS, SCENE_SPACING_M, MapExpansion
from omniscs.geometry import invert_transform, make_transform
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene.store import Scene
from omniscs.taxonomy import NUSCENES_DETECTION_CLASS

log = logging.getLogger(__name__)

#: The camera channels UniAD reads, in its order (a scene without one of them simply leaves it out).
UNIAD_CAMERAS: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                                  "CAM_BACK_RIGHT")
#: UniAD's detection classes, in its config's order.
DETECTION_CLASSES: tuple[str, ...] = ("car", "truck", "construction_vehicle", "bus", "trailer", "barrier",
                                      "motorcycle", "bicycle", "pedestrian", "traffic_cone")
#: nuScenes category -> detection class (mmdet3d's NuScenesDataset.NameMapping).
NAME_MAPPING: dict[str, str] = NUSCENES_DETECTION_CLASS
#: UniAD's motion class groups (its ``group_id_list`` over DETECTION_CLASSES), in its order.
ANCHOR_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("vehicle", ("car", "truck", "construction_vehicle", "bus", "trailer")),
    ("bike", ("motorcycle", "bicycle")),
    ("pedestrian", ("pedestrian",)),
    ("others", ("barrier", "traffic_cone")),
)
#: Speed of a fallback anchor group that has no agents at all (m/s).
FALLBACK_SPEED_MPS: dict[str, float] = {"vehicle": 8.0, "bike": 4.0, "pedestrian": 1.3, "others": 0.0}
#: Fallback anchors fan out evenly over headings in [-FAN, +FAN] from straight ahead (radians).
FALLBACK_FAN_RAD = 0.3
BOX_CONVENTIONS: tuple[str, ...] = ("v1", "v2")
#: Seconds between UniAD's trajectory steps (nuScenes keyframes are 2 Hz).
STEP_S = 0.5
ANCHOR_FILE = "motion_anchor_infos_mode6.pkl"
DATAROOT_DIR, INFOS_DIR, OTHERS_DIR = "nuscenes", "infos", "others"
PICKLE_PROTOCOL = 4


@dataclass(frozen=True)
class UniADConfig:
    """How the UniAD infos and anchors are written."""

    box_convention: str = "v1"
    """``"v1"`` (UniAD main: w, l, h and -yaw - pi/2) or ``"v2"`` (UniAD v2.0: w, l, h and yaw); module docstring."""
    info_prefix: str = "nuscenes"
    """Pickles are ``infos/<info_prefix>_infos_temporal_{train,val}.pkl``."""
    data_path_prefix: str = "./data/nuscenes"
    """Prepended to dataroot-relative file names in ``lidar_path`` / ``data_path`` (where UniAD finds the dataroot)."""
    val_scenes: tuple[str, ...] = ()
    """Scenes for the val pickle, by store scene id or exported scene name; every other scene goes to train."""
    max_sweeps: int = 10
    """Previous LiDAR sweeps listed per keyframe."""
    future_steps: int = 16
    """Steps of ``fut_traj`` (UniAD's converter: 16, i.e. 8 s at 2 Hz)."""
    anchor_modes: int = 6
    """Anchors per class group (UniAD's ``num_anchor``)."""
    anchor_steps: int = 12
    """Steps per anchor (UniAD's ``predict_steps``: 6 s at 2 Hz)."""
    anchor_min_samples: int = 24
    """A group with fewer complete futures than this also uses futures extended from partial ones (module
    docstring); with fewer than ``anchor_modes`` distinct futures in all it gets fallback straight-line anchors."""
    anchor_min_known: int = 2
    """Known future steps (1 s at 2 Hz) a partial future needs to be extended to ``anchor_steps`` for the anchors."""
    anchor_seed: int = 0
    """Seed of the k-means initialisation."""

    def __post_init__(self):
        if self.box_convention not in BOX_CONVENTIONS:
            raise OmniscsError(f"unknown box convention {self.box_convention!r}; use 'v1' (UniAD main) or 'v2' "
                               "(UniAD v2.0)")
        if not isinstance(self.info_prefix, str) or not self.info_prefix or "/" in self.info_prefix:
            raise OmniscsError(f"UniAD info_prefix must be a non-empty name without '/'; got {self.info_prefix!r}")
        if not isinstance(self.data_path_prefix, str) or not self.data_path_prefix:
            raise OmniscsError(f"UniAD data_path_prefix must be a non-empty path; got {self.data_path_prefix!r}")
        if isinstance(self.val_scenes, str) or not all(isinstance(s, str) for s in self.val_scenes):
            raise OmniscsError(f"val_scenes must be a list of scene ids or names; got {self.val_scenes!r}")
        object.__setattr__(self, "val_scenes", tuple(self.val_scenes))
        for name in ("max_sweeps", "future_steps", "anchor_modes", "anchor_steps", "anchor_min_samples",
                     "anchor_min_known", "anchor_seed"):
            value = getattr(self, name)
            least = 0 if name in ("max_sweeps", "anchor_seed") else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise OmniscsError(f"UniAD {name} must be an integer >= {least}; got {value!r}")
        if self.anchor_steps > self.future_steps:
            raise OmniscsError(f"anchor_steps ({self.anchor_steps}) cannot exceed future_steps ({self.future_steps})")
        if self.anchor_min_samples < self.anchor_modes:
            raise OmniscsError(f"anchor_min_samples ({self.anchor_min_samples}) must be at least anchor_modes "
                               f"({self.anchor_modes}) to cluster")


# ----------------------------------------------------------------------------- entry point
def write_uniad(scenes: list[Scene], root: Path, version: str = DEFAULT_VERSION, keyframe_every: int | None = None,
                progress: Callable[[int, int], None] | None = None, location: str = DEFAULT_LOCATION,
                scene_spacing_m: float = SCENE_SPACING_M, keep_unseen: bool = False, **options) -> Path:
    """Write ``scenes`` as UniAD's data folder at ``root`` (layout in the module docstring); ``options`` are
    UniADConfig fields; ``keep_unseen`` keeps the boxes no sensor captured (``write_nuscenes``)."""
    unknown = sorted(set(options) - {f.name for f in fields(UniADConfig)})
    if unknown:
        raise OmniscsError(f"unknown UniAD option(s) {unknown}; it takes {[f.name for f in fields(UniADConfig)]}")
    config = UniADConfig(**options)
    dataroot = root / DATAROOT_DIR
    write_nuscenes(scenes, dataroot, version=version, keyframe_every=keyframe_every, progress=progress,
                   location=location, scene_spacing_m=scene_spacing_m, keep_unseen=keep_unseen)
    from nuscenes.nuscenes import NuScenes

    nusc = NuScenes(version=version, dataroot=str(dataroot), verbose=False)
    named = {log["location"] for log in nusc.log}
    for unused in (loc for loc in NUSCENES_LOCATIONS if loc not in named):
        path = dataroot / "maps" / "expansion" / f"{unused}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(MapExpansion(unused).to_json()))
    val_tokens = _val_scene_tokens(nusc, scenes, config.val_scenes)
    infos = uniad_infos(nusc, config)
    if not infos:
        raise OmniscsError("the UniAD export has no keyframe for either pickle (the scenes have no frames)")
    if not val_tokens:
        log.warning("UniAD export: the val pickle is empty and all %d scene(s) went to train; name the scenes to "
                    "validate on with --val-scene (repeat; one of %s)", len(scenes),
                    ", ".join(sorted(scene.scene_id for scene in scenes)[:4]) + (", ..." if len(scenes) > 4 else ""))
    metadata = {"version": version}
    (root / INFOS_DIR).mkdir(parents=True, exist_ok=True)
    for split, keep in (("train", lambda i: i["scene_token"] not in val_tokens),
                        ("val", lambda i: i["scene_token"] in val_tokens)):
        dump_portable_pickle({"infos": [i for i in infos if keep(i)], "metadata": metadata},
                             root / INFOS_DIR / f"{config.info_prefix}_infos_temporal_{split}.pkl")
    (root / OTHERS_DIR).mkdir(parents=True, exist_ok=True)
    dump_portable_pickle(motion_anchors(infos, config), root / OTHERS_DIR / ANCHOR_FILE)
    return root


def _val_scene_tokens(nusc, scenes: list[Scene], val_scenes: tuple[str, ...]) -> set[str]:
    by_name = {s["name"]: s["token"] for s in nusc.scene}
    by_id = {f"omniscs {scene.scene_id}": scene.scene_id for scene in scenes}
    for s in nusc.scene:
        if s["description"] in by_id:
            by_name.setdefault(by_id[s["description"]], s["token"])
    missing = [v for v in val_scenes if v not in by_name]
    if missing:
        raise OmniscsError(f"val scene(s) {missing} are not in this export; name scene ids or names among "
                           f"{sorted(by_name)}")
    return {by_name[v] for v in val_scenes}


# ----------------------------------------------------------------------------- infos
def _transform(translation, rotation) -> np.ndarray:  # nuScenes record fields -> [4, 4]
    return make_transform(quat_to_rotmat(np.asarray(rotation, np.float64)), np.asarray(translation, np.float64))


def uniad_infos(nusc, config: UniADConfig = UniADConfig()) -> list[dict]:
    """One info dict per keyframe sample of a devkit ``NuScenes``, in table order (keys in the module docstring)."""
    from nuscenes.prediction import PredictHelper

    helper = PredictHelper(nusc)
    motion = {scene["token"]: _scene_ego_motion(nusc, scene) for scene in nusc.scene}
    infos, frame_idx = [], 0
    for sample in nusc.sample:
        if "LIDAR_TOP" not in sample["data"]:
            scene = nusc.get("scene", sample["scene_token"])
            raise OmniscsError(f"scene {scene['name']} ({scene['description']}) has no LiDAR; UniAD infos live in "
                               "the LIDAR_TOP frame: export scenes rendered or recorded with LiDAR")
        infos.append(_sample_info(nusc, helper, sample, frame_idx, motion[sample["scene_token"]], config))
        frame_idx = 0 if sample["next"] == "" else frame_idx + 1
    return infos


def _sample_info(nusc, helper, sample: dict, frame_idx: int, motion: dict[int, np.ndarray], config: UniADConfig
                 ) -> dict:
    lidar_sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
    lidar_cs = nusc.get("calibrated_sensor", lidar_sd["calibrated_sensor_token"])
    pose = nusc.get("ego_pose", lidar_sd["ego_pose_token"])
    global_from_lidar = _transform(pose["translation"], pose["rotation"]) @ \
        _transform(lidar_cs["translation"], lidar_cs["rotation"])
    info = {
        "lidar_path": _path(config, lidar_sd["filename"]),
        "token": sample["token"], "prev": sample["prev"], "next": sample["next"],
        "can_bus": np.concatenate([pose["translation"], pose["rotation"], motion[pose["timestamp"]], [0.0, 0.0]]),
        "frame_idx": frame_idx, "sweeps": [], "cams": {},
        "scene_token": sample["scene_token"],
        "lidar2ego_translation": list(lidar_cs["translation"]), "lidar2ego_rotation": list(lidar_cs["rotation"]),
        "ego2global_translation": list(pose["translation"]), "ego2global_rotation": list(pose["rotation"]),
        "timestamp": sample["timestamp"],
    }
    for channel in UNIAD_CAMERAS:
        if channel in sample["data"]:
            cam = _sensor_info(nusc, sample["data"][channel], channel, global_from_lidar, config)
            sd = nusc.get("sample_data", sample["data"][channel])
            cam["cam_intrinsic"] = np.asarray(nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
                                              ["camera_intrinsic"], np.float64)
            info["cams"][channel] = cam
    sd = lidar_sd
    while len(info["sweeps"]) < config.max_sweeps and sd["prev"]:
        info["sweeps"].append(_sensor_info(nusc, sd["prev"], "lidar", global_from_lidar, config))
        sd = nusc.get("sample_data", sd["prev"])
    info.update(_annotations(nusc, helper, sample, global_from_lidar, config))
    return info


def _path(config: UniADConfig, filename: str) -> str:
    return f"{config.data_path_prefix.rstrip('/')}/{filename}"


def _sensor_info(nusc, sd_token: str, sensor_type: str, global_from_lidar: np.ndarray, config: UniADConfig) -> dict:
    """A camera or sweep entry: its calibration and pose, and its transform into the keyframe's LiDAR frame."""
    sd = nusc.get("sample_data", sd_token)
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    pose = nusc.get("ego_pose", sd["ego_pose_token"])
    lidar_from_sensor = invert_transform(global_from_lidar) @ _transform(pose["translation"], pose["rotation"]) @ \
        _transform(cs["translation"], cs["rotation"])
    return {"data_path": _path(config, sd["filename"]), "type": sensor_type, "sample_data_token": sd["token"],
            "sensor2ego_translation": list(cs["translation"]), "sensor2ego_rotation": list(cs["rotation"]),
            "ego2global_translation": list(pose["translation"]), "ego2global_rotation": list(pose["rotation"]),
            "timestamp": sd["timestamp"],
            "sensor2lidar_rotation": lidar_from_sensor[:3, :3].copy(),  # points_lidar = points @ R.T + t
            "sensor2lidar_translation": lidar_from_sensor[:3, 3].copy()}


def encode_boxes(centres: np.ndarray,  # [N, 3] LiDAR frame
                 wlh: np.ndarray,      # [N, 3] nuScenes sizes (width, length, height)
                 yaw: np.ndarray,      # [N] heading about the LiDAR z axis (nuScenes Box yaw)
                 convention: str) -> np.ndarray:  # -> [N, 7] gt_boxes
    if convention not in BOX_CONVENTIONS:
        raise OmniscsError(f"unknown box convention {convention!r}; use 'v1' (UniAD main) or 'v2' (UniAD v2.0)")
    angle = -yaw - np.pi / 2 if convention == "v1" else yaw
    return np.concatenate([centres.reshape(-1, 3), wlh.reshape(-1, 3), np.reshape(angle, (-1, 1))], axis=1)


def _annotations(nusc, helper, sample: dict, global_from_lidar: np.ndarray, config: UniADConfig) -> dict:
    anns = [nusc.get("sample_annotation", t) for t in sample["anns"]]
    _, boxes, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
    lidar_from_global = invert_transform(global_from_lidar)
    n = len(anns)
    centres = np.array([b.center for b in boxes], np.float64).reshape(n, 3)
    wlh = np.array([b.wlh for b in boxes], np.float64).reshape(n, 3)
    yaw = np.array([b.orientation.yaw_pitch_roll[0] for b in boxes], np.float64).reshape(n)
    velocity = np.zeros((n, 2))
    for i, ann in enumerate(anns):
        v = np.nan_to_num(nusc.box_velocity(ann["token"]), nan=0.0)  # one keyframe only: no velocity, as UniAD does
        velocity[i] = (lidar_from_global[:3, :3] @ v)[:2]
    fut = np.zeros((n, config.future_steps, 2))
    fut_mask = np.zeros((n, config.future_steps, 2))
    for i, ann in enumerate(anns):
        local = helper.get_future_for_agent(ann["instance_token"], sample["token"],
                                            seconds=config.future_steps * STEP_S, in_agent_frame=True)
        local = np.asarray(local, np.float64).reshape(-1, 2)[:config.future_steps]
        fut[i, :len(local)] = local
        fut_mask[i, :len(local)] = 1.0
    names = [NAME_MAPPING.get(ann["category_name"], ann["category_name"]) for ann in anns]
    return {
        "gt_boxes": encode_boxes(centres, wlh, yaw, config.box_convention),
        "gt_names": np.array(names, dtype=str),
        "gt_velocity": velocity,
        "num_lidar_pts": np.array([a["num_lidar_pts"] for a in anns], np.int64),
        "num_radar_pts": np.array([a["num_radar_pts"] for a in anns], np.int64),
        "valid_flag": np.array([a["num_lidar_pts"] + a["num_radar_pts"] > 0 for a in anns], bool),
        "gt_inds": np.array([nusc.getind("instance", a["instance_token"]) for a in anns], np.int64),
        "gt_ins_tokens": np.array([a["instance_token"] for a in anns], dtype=str),
        "fut_traj": fut,
        "fut_traj_valid_mask": fut_mask,
        "visibility_tokens": np.array([int(a["visibility_token"]) for a in anns], np.int64),
    }


def _scene_ego_motion(nusc, scene: dict) -> dict[int, np.ndarray]:
    """{timestamp: [acceleration 3, angular velocity 3, velocity 3]} (ego frame) at every LIDAR_TOP (else first
    sensor) sweep of a scene."""
    sample = nusc.get("sample", scene["first_sample_token"])
    channel = "LIDAR_TOP" if "LIDAR_TOP" in sample["data"] else sorted(sample["data"])[0]
    sd = nusc.get("sample_data", sample["data"][channel])
    seen = {sd["token"]}

    def step(token: str, direction: str) -> dict:  # a chain that loops is a damaged table, never a hang
        if token in seen:
            raise OmniscsError(f"the {channel} sample_data {direction} chain of scene {scene['name']} loops at "
                               f"{token}; fix the dataroot's sample_data.json")
        seen.add(token)
        return nusc.get("sample_data", token)

    while sd["prev"]:
        sd = step(sd["prev"], "prev")
    seen = {sd["token"]}
    poses, stamps = [], []
    while True:
        pose = nusc.get("ego_pose", sd["ego_pose_token"])
        poses.append(_transform(pose["translation"], pose["rotation"]))
        stamps.append(pose["timestamp"])
        if not sd["next"]:
            break
        sd = step(sd["next"], "next")
    acc, omega, vel = ego_motion(np.stack(poses), np.asarray(stamps, np.int64))
    return {int(t): np.concatenate([acc[i], omega[i], vel[i]]) for i, t in enumerate(stamps)}


def ego_motion(global_from_ego: np.ndarray,  # [F, 4, 4]
               timestamps_us: np.ndarray,    # [F] int64, strictly increasing
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # acceleration, angular velocity, velocity [F, 3] ego
    """Ego motion from poses by finite differences (central where both neighbours exist), in the ego frame: m/s^2,
    rad/s, m/s. A single pose gives zeros."""
    from scipy.spatial.transform import Rotation

    F = len(global_from_ego)
    if F < 2:
        return np.zeros((F, 3)), np.zeros((F, 3)), np.zeros((F, 3))
    t = timestamps_us.astype(np.float64) * 1e-6
    if np.any(np.diff(t) <= 0):
        raise OmniscsError("ego poses must have strictly increasing timestamps to derive the CAN bus motion")
    R = global_from_ego[:, :3, :3]
    v_global = np.gradient(global_from_ego[:, :3, 3], t, axis=0)
    a_global = np.gradient(v_global, t, axis=0)
    lo = np.maximum(np.arange(F) - 1, 0)
    hi = np.minimum(np.arange(F) + 1, F - 1)
    relative = np.einsum("fji,fjk->fik", R[lo], R[hi])  # ego_lo_from_ego_hi
    omega = Rotation.from_matrix(relative).as_rotvec() / (t[hi] - t[lo])[:, None]
    to_ego = np.transpose(R, (0, 2, 1))
    return (np.einsum("fij,fj->fi", to_ego, a_global), omega, np.einsum("fij,fj->fi", to_ego, v_global))


# ----------------------------------------------------------------------------- motion anchors
def motion_anchors(infos: list[dict], config: UniADConfig = UniADConfig()) -> dict:
    """UniAD's motion anchors from the infos' futures (module docstring): ``anchors_all`` [groups][modes, steps, 2]."""
    steps = config.anchor_steps
    anchors, counts, extended_counts, fell_back, speeds = [], [], [], [], []
    for group, classes in ANCHOR_GROUPS:
        futures, partial, group_speeds = [], [], []
        for info in infos:
            in_group = np.isin(info["gt_names"], classes)
            known = info["fut_traj_valid_mask"][:, :steps].all(axis=2)  # [N, steps]
            complete = in_group & known.all(axis=1)
            futures.append(info["fut_traj"][complete, :steps])
            partial.append(extended_futures(info["fut_traj"][in_group & ~complete, :steps],
                                            known[in_group & ~complete], config.anchor_min_known))
            group_speeds.append(np.linalg.norm(info["gt_velocity"][in_group], axis=1))
        futures = np.concatenate(futures).reshape(-1, steps, 2) if futures else np.zeros((0, steps, 2))
        group_speeds = np.concatenate(group_speeds) if group_speeds else np.zeros(0)
        speed = float(np.median(group_speeds)) if len(group_speeds) else FALLBACK_SPEED_MPS[group]
        n_extended = 0
        if len(futures) < config.anchor_min_samples:  # short logs: complete the set with extended partial futures
            extended = np.concatenate(partial).reshape(-1, steps, 2) if partial else np.zeros((0, steps, 2))
            n_extended = len(extended)
            futures = np.concatenate([futures, extended])
        distinct = len(np.unique(futures.reshape(len(futures), -1).round(6), axis=0)) if len(futures) else 0
        fallback = distinct < config.anchor_modes
        if fallback:
            centres = straight_anchors(speed, config.anchor_modes, steps)
        else:
            from sklearn.cluster import KMeans

            km = KMeans(n_clusters=config.anchor_modes, n_init=10, random_state=config.anchor_seed)
            km.fit(futures.reshape(len(futures), -1))
            centres = km.cluster_centers_.reshape(config.anchor_modes, steps, 2)
        anchors.append(np.asarray(centres, np.float32))
        counts.append(len(futures) - n_extended)
        extended_counts.append(n_extended)
        fell_back.append(bool(fallback))
        speeds.append(speed)
    straight = [f"{g} ({c} complete, {e} extended)" for (g, _), c, e, f in
                zip(ANCHOR_GROUPS, counts, extended_counts, fell_back) if f]
    if straight:
        log.warning("UniAD motion anchors: %s have fewer than %d distinct %.0f s futures (complete, or known for "
                    "%g s and extended), so their anchors are straight lines at the group's median speed, not "
                    "learnt from the data; longer logs with more agents give anchors from the data (a whole %g s "
                    "future needs %d frames at 10 Hz)", ", ".join(straight), config.anchor_modes, steps * STEP_S,
                    config.anchor_min_known * STEP_S, steps * STEP_S, int(round(steps * STEP_S * 10)) + 1)
    return {"anchors_all": anchors, "groups": [g for g, _ in ANCHOR_GROUPS],
            "group_classes": [list(c) for _, c in ANCHOR_GROUPS], "sample_counts": counts,
            "extended_counts": extended_counts, "fallback": fell_back, "median_speed_mps": speeds, "step_s": STEP_S,
            "frame": "agent: +y heading, +x right"}


def extended_futures(futures: np.ndarray,  # [N, S, 2] agent frame, valid where ``known``
                     known: np.ndarray,    # [N, S] bool
                     min_known: int) -> np.ndarray:  # -> [M, S, 2]
    """The futures whose first ``min_known`` steps or more are known, continued past their last known step at that
    step's velocity (constant velocity; the first step's from the agent's origin)."""
    out = []
    for future, mask in zip(futures, known):
        k = int(np.argmin(mask)) if not mask.all() else len(mask)  # leading known steps
        if k < min_known or k == 0:
            continue
        last = future[k - 1]
        velocity = last - (future[k - 2] if k >= 2 else np.zeros(2))
        ahead = np.arange(1, len(mask) - k + 1)[:, None]
        out.append(np.concatenate([future[:k], last + ahead * velocity]))
    return np.asarray(out, np.float64).reshape(-1, futures.shape[1] if futures.ndim == 3 else 0, 2)


def straight_anchors(speed: float, modes: int, steps: int) -> np.ndarray:  # -> [modes, steps, 2] agent frame
    """Straight lines at ``speed`` fanned evenly over [-FALLBACK_FAN_RAD, +FALLBACK_FAN_RAD] (positive = left)."""
    heading = np.linspace(-FALLBACK_FAN_RAD, FALLBACK_FAN_RAD, modes) if modes > 1 else np.zeros(1)
    travelled = speed * STEP_S * np.arange(1, steps + 1)  # [steps]
    return np.stack([-np.sin(heading)[:, None] * travelled, np.cos(heading)[:, None] * travelled], axis=-1)


# ----------------------------------------------------------------------------- pickles numpy 1.x can read
class _PortablePickler(pickle.Pickler):
    def reducer_override(self, obj):
        if isinstance(obj, np.ndarray):
            if obj.dtype.hasobject:
                raise OmniscsError("an info array holds Python objects; it cannot be pickled portably")
            data = np.ascontiguousarray(obj)
            return np.ndarray, (data.shape, data.dtype.str, bytearray(data.tobytes()))
        if isinstance(obj, np.generic):
            return type(obj.item()), (obj.item(),)
        return NotImplemented


def dump_portable_pickle(obj, path: Path) -> None:
    """Pickle ``obj`` so that numpy 1.x loads its arrays (no reference to numpy 2's private ``numpy._core``)."""
    with open(path, "wb") as fh:
        _PortablePickler(fh, protocol=PICKLE_PROTOCOL).dump(obj)
