"""Broken datasets: every bad nuScenes, KITTI or Waymo v2 input is one OmniscsError line naming the file (and
field), raised as early as possible (``resolve`` refuses a missing scene or a malformed table before anything is
written), and a failed read leaves no output folder. Datasets are a 5-frame, one-camera tiny scene exported to each
format, so the whole module runs in seconds."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from omniscs.errors import OmniscsError
from omniscs.export import export_scenes
from omniscs.scene import source_from_dict
from omniscs.scene.sources import DatasetSource, read_dataset_scene, resolve, validate_source
from omniscs.scene.store import verify_store
from tests.conftest import write_tiny_scene
from tests.damage import files_under, set_column as column

VERSION = "v1.0-mini"


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("datasets")
    store = write_tiny_scene(base / "tiny")
    return {"nuscenes": export_scenes([store], "nuscenes", base / "nuscenes", version=VERSION, keyframe_every=2),
            "kitti": export_scenes([store], "kitti", base / "kitti"),
            "waymo-v2": export_scenes([store], "waymo-v2", base / "waymo")}


# ----------------------------------------------------------------------------- nuScenes damage
def nus_table(name: str, change):
    def damage(root: Path):
        path = root / VERSION / f"{name}.json"
        rows = json.loads(path.read_text())
        rows = change(rows) if change is not None else rows
        path.write_text(json.dumps(rows))
    return damage


def nus_text(name: str, data: bytes):
    return lambda root: (root / VERSION / f"{name}.json").write_bytes(data)


def nus_file(prefix: str, index: int = 1):
    """The ``index``-th keyframe file of a sensor folder (e.g. ``samples/LIDAR_TOP``)."""
    def find(root: Path) -> Path:
        return sorted((root / prefix).iterdir())[index]
    return find


def unlink(find):
    return lambda root: find(root).unlink()


def truncate_by(find, n: int = 7):
    def damage(root: Path):
        path = find(root)
        path.write_bytes(path.read_bytes()[:-n])
    return damage


def _set(field, value, row: int = 0):
    def change(rows):
        rows[row][field] = value
        return rows
    return change


def _drop(field, row: int = 0):
    def change(rows):
        rows[row].pop(field)
        return rows
    return change


def _zero_focal(rows):
    for r in rows:
        if r["camera_intrinsic"]:
            r["camera_intrinsic"][0][0] = 0.0
    return rows


NUSCENES = {
    # id: (damage, scene, the earliest step that must refuse it, message); steps: "resolve" (scene and table
    # checks), "open" (validate_source: reader opened, per-frame files stat-ed), "read" (only decoding finds it)
    "scene that does not exist": (None, "scene-0042", "resolve", r"has no scene 'scene-0042'; it has \['scene-0001'\]"),
    "dataroot without tables": (lambda root: shutil.rmtree(root / VERSION), None, "resolve",
                                r"is not a nuScenes dataroot: it has no v1.0-\* table folder"),
    "two table versions": (lambda root: shutil.copytree(root / VERSION, root / "v1.0-trainval"), None, "resolve",
                           r"name the nuScenes version \(found \['v1.0-mini', 'v1.0-trainval'\]\)"),
    "missing table": (lambda root: (root / VERSION / "ego_pose.json").unlink(), None, "resolve",
                      r"ego_pose.json: nuScenes table 'ego_pose' is missing"),
    "table not JSON": (nus_text("sample", b'[{"token": '), None, "resolve", r"sample.json is not valid JSON"),
    "table binary": (nus_text("sample_data", b"\x89PNG\x00\xff"), None, "resolve",
                     r"sample_data.json is not UTF-8 text \(byte 0 is 0x89\)"),
    "table an object": (nus_table("scene", lambda rows: {"scenes": rows}), None, "resolve",
                        r"scene.json: a nuScenes table must be a JSON list of records; got a dict"),
    "record not an object": (nus_table("sensor", lambda rows: ["CAM_FRONT"] + rows[1:]), None, "resolve",
                             r"sensor.json: record 0 is a str, not an object"),
    "record without its token": (nus_table("category", _drop("token")), None, "resolve",
                                 r"category.json: record 0 \(no token\): field token is missing"),
    "field missing": (nus_table("sample_data", _drop("calibrated_sensor_token", 2)), None, "resolve",
                      r"sample_data.json: record 2 \(\w+\): field calibrated_sensor_token is missing"),
    "rotation a string": (nus_table("ego_pose", _set("rotation", "abc", 1)), None, "open",
                          r"ego_pose.json: record 1 \(\w+\): field rotation must be 4 finite numbers"),
    "timestamp a string": (nus_table("sample", _set("timestamp", "noon", 1)), None, "open",
                           r"sample.json: record 1 \(\w+\): field timestamp must be an integer; got 'noon'"),
    "scene name a number": (nus_table("scene", _set("name", 7)), None, "resolve",
                            r"scene.json: record 0 \(\w+\): field name must be a string; got 7"),
    "dangling token": (nus_table("sample_annotation", _set("instance_token", "f" * 32)), None, "resolve",
                       r"tables are inconsistent: token 'f{32}'"),
    "empty map table": (nus_table("map", lambda rows: []), None, "resolve",
                        r"map.json: the map table is empty"),
    "map image missing": (lambda root: shutil.rmtree(root / "maps"), None, "resolve",
                          r"v1.0-mini: the devkit cannot load the tables \(map mask .* does not exist"),
    "zero focal length": (nus_table("calibrated_sensor", _zero_focal), None, "open",
                          r"calibrated_sensor.json: camera CAM_FRONT intrinsics are not a pinhole matrix"),
    "missing image file": (unlink(nus_file("samples/CAM_FRONT")), None, "open",
                           r"__CAM_FRONT__200000.jpg: image file is missing \(frame \w+; pass skip_bad_frames"),
    "missing LiDAR file": (unlink(nus_file("samples/LIDAR_TOP", 2)), None, "open",
                           r"__LIDAR_TOP__400000.pcd.bin: LiDAR file is missing"),
    "truncated LiDAR file": (truncate_by(nus_file("samples/LIDAR_TOP", 0)), None, "open",
                             r"__LIDAR_TOP__0.pcd.bin: LiDAR file is truncated"),
    "size unknown and image missing": (lambda root: (nus_table("sample_data", _set("width", 0))(root),
                                                     unlink(nus_file("samples/CAM_FRONT", 0))(root)), None, "open",
                                       r"__CAM_FRONT__0.jpg: image file is missing"),
    "image not an image": (lambda root: nus_file("samples/CAM_FRONT", 0)(root).write_bytes(b"not a jpeg"), None,
                           "read", r"__CAM_FRONT__0.jpg: image is unreadable"),
}


# ----------------------------------------------------------------------------- KITTI damage
def kitti(rel: str) -> Path:
    return Path("training") / rel


def kitti_edit(rel: str, change):
    def damage(root: Path):
        path = root / kitti(rel)
        path.write_text(change(path.read_text()))
    return damage


def _line_value(key: str, index: int, value: str):
    def change(text: str) -> str:
        lines = text.splitlines()
        for i, line in enumerate(lines):
            if line.startswith(key):
                fields = line.split()
                fields[index] = value
                lines[i] = " ".join(fields)
        return "\n".join(lines) + "\n"
    return change


KITTI = {
    "sequence that does not exist": (None, "0042", "resolve", r"has no sequence '0042'; it has \['0000'\]"),
    "not a KITTI root": (lambda root: shutil.rmtree(root / "training" / "image_02"), None, "resolve",
                         r"is not a KITTI tracking root: no image_02/"),
    "missing poses": (lambda root: (root / kitti("oxts/0000.txt")).unlink(), "0000", "resolve",
                      r"oxts/0000.txt: OXTS pose file is missing"),
    "missing labels": (lambda root: (root / kitti("label_02/0000.txt")).unlink(), "0000", "resolve",
                       r"label_02/0000.txt: KITTI label file is missing"),
    "missing calibration": (lambda root: (root / kitti("calib/0000.txt")).unlink(), "0000", "resolve",
                            r"calib/0000.txt: KITTI calibration file is missing"),
    "calibration NaN": (kitti_edit("calib/0000.txt", _line_value("Tr_velo_cam", 2, "nan")), None, "open",
                        r"calib/0000.txt: line \d+ \(Tr_velo_cam\) has a NaN or Inf value"),
    "calibration binary": (lambda root: (root / kitti("calib/0000.txt")).write_bytes(b"\xff\xfe\x00P2"), None, "open",
                           r"calib/0000.txt: KITTI calibration file is not text"),
    "calibration word": (kitti_edit("calib/0000.txt", _line_value("P2", 1, "abc")), None, "open",
                         r"calib/0000.txt: line 3 \(P2:\) has a value that is not a number"),
    "zero focal length": (kitti_edit("calib/0000.txt", _line_value("P2", 1, "0.0")), None, "open",
                          r"field P2 is not a rectified projection"),
    "poses binary": (lambda root: (root / kitti("oxts/0000.txt")).write_bytes(b"\x80\x81"), None, "open",
                     r"oxts/0000.txt: OXTS pose file is not text"),
    "label frame not a number": (kitti_edit("label_02/0000.txt", lambda t: "x" + t), None, "open",
                                 r"label_02/0000.txt: line 1: field frame 'x0' is not an integer"),
    "missing image file": (lambda root: (root / kitti("image_02/0000/000003.png")).unlink(), None, "open",
                           r"000003.png: image file is missing \(frame 3; pass skip_bad_frames"),
    "missing velodyne file": (lambda root: (root / kitti("velodyne/0000/000001.bin")).unlink(), None, "open",
                              r"000001.bin: LiDAR file is missing \(frame 1"),
    "truncated velodyne file": (truncate_by(lambda root: root / kitti("velodyne/0000/000004.bin"), 5), None, "open",
                                r"000004.bin: LiDAR file is truncated"),
}


# ----------------------------------------------------------------------------- Waymo v2 damage
def waymo(component: str, change):
    def damage(root: Path):
        path = root / component / "tiny.parquet"
        pq.write_table(change(pq.read_table(path)), path)
    return damage


TS = "key.frame_timestamp_micros"
WAYMO = {
    "segment that does not exist": (None, "other", "resolve", r"has no segment 'other'; it has \['tiny'\]"),
    "not a split folder": (lambda root: shutil.rmtree(root / "vehicle_pose"), None, "resolve",
                           r"is not a Waymo v2 split folder: it has no vehicle_pose/"),
    "missing component": (lambda root: (root / "camera_image" / "tiny.parquet").unlink(), None, "resolve",
                          r"camera_image/tiny.parquet: Waymo v2 component 'camera_image' is missing"),
    "range images without calibration": (lambda root: (root / "lidar_calibration" / "tiny.parquet").unlink(), None,
                                         "resolve", r"component 'lidar_calibration' is missing \(the segment has"),
    "component not Parquet": (lambda root: (root / "camera_calibration" / "tiny.parquet").write_bytes(b"nope"), None,
                              "resolve", r"camera_calibration/tiny.parquet: unreadable Parquet"),
    "timestamps as strings": (waymo("vehicle_pose", column(TS, lambda v: [str(x) for x in v])), None, "resolve",
                              r"vehicle_pose/tiny.parquet: column key.frame_timestamp_micros has type string, "
                              r"expected integer"),
    "image bytes as strings": (waymo("camera_image", column("[CameraImageComponent].image", lambda v: ["jpeg"] * len(v))),
                               None, "resolve", r"column \[CameraImageComponent\].image has type string, expected binary"),
    "box type a float": (waymo("lidar_box", column("[LiDARBoxComponent].type", lambda v: [float(x) for x in v])), None,
                         "resolve", r"lidar_box/tiny.parquet: column \[LiDARBoxComponent\].type has type double"),
    "pose of strings": (waymo("vehicle_pose", column("[VehiclePoseComponent].world_from_vehicle.transform",
                                                     lambda v: [[str(x) for x in m] for m in v])), None, "resolve",
                        r"transform has type list<\w+: string>, expected list of numbers"),
    "missing width column": (waymo("camera_calibration", lambda t: t.drop(["[CameraCalibrationComponent].width"])),
                             None, "resolve", r"missing column\(s\) \['\[CameraCalibrationComponent\].width'\]"),
    "null timestamp": (waymo("vehicle_pose", column(TS, lambda v: [None] + v[1:], pa.int64())), None, "open",
                       r"vehicle_pose/tiny.parquet: column key.frame_timestamp_micros has 1 null value"),
    "pose of 15 numbers": (waymo("vehicle_pose", column("[VehiclePoseComponent].world_from_vehicle.transform",
                                                        lambda v: [m[:15] for m in v])), None, "open",
                           r"vehicle_pose/tiny.parquet: frame \d+: transform is not 16 finite numbers"),
    "zero focal length": (waymo("camera_calibration", column("[CameraCalibrationComponent].intrinsic.f_u", [0.0])),
                          None, "open", r"camera_calibration/tiny.parquet: camera CAM_FRONT intrinsics are not"),
    "image size zero": (waymo("camera_calibration", column("[CameraCalibrationComponent].width", [0], pa.int32())),
                        None, "open", r"camera CAM_FRONT has image size 0x36"),
    "camera calibrated twice": (waymo("camera_calibration", lambda t: pa.concat_tables([t, t])), None, "open",
                                r"camera_calibration/tiny.parquet: camera CAM_FRONT is calibrated twice"),
    "image bytes not an image": (waymo("camera_image", column("[CameraImageComponent].image",
                                                              lambda v: [b"x"] + v[1:], pa.binary())), None, "read",
                                 r"camera_image/tiny.parquet: frame 0 camera CAM_FRONT: image bytes are empty or not"),
}

CASES = {**{f"nuscenes: {k}": ("nuscenes", *v) for k, v in NUSCENES.items()},
         **{f"kitti: {k}": ("kitti", *v) for k, v in KITTI.items()},
         **{f"waymo-v2: {k}": ("waymo-v2", *v) for k, v in WAYMO.items()}}


@pytest.mark.parametrize("case", list(CASES))
def test_a_broken_dataset_is_one_line_early_and_writes_nothing(case, datasets, tmp_path):
    fmt, damage, scene, stage, message = CASES[case]
    root = Path(shutil.copytree(datasets[fmt], tmp_path / "data"))
    if damage is not None:
        damage(root)
    source = DatasetSource(fmt, str(root), scene)
    before = files_under(tmp_path)
    if stage == "resolve":  # the pipeline resolves every source before any work: it must refuse here
        with pytest.raises(OmniscsError, match=message) as info:
            resolve(source)
        assert len(str(info.value).splitlines()) == 1
    if stage in ("resolve", "open"):  # known without decoding a single image
        with pytest.raises(OmniscsError, match=message) as info:
            validate_source(source)
        assert len(str(info.value).splitlines()) == 1
    with pytest.raises(OmniscsError, match=message) as info:
        read_dataset_scene(source, tmp_path / "out" / "store")
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before  # no store, no temporary, no parent folder made for it


@pytest.mark.parametrize("fmt", ["nuscenes", "kitti", "waymo-v2"])
def test_a_good_dataset_resolves_reads_and_verifies(fmt, datasets, tmp_path):
    source = resolve(DatasetSource(fmt, str(datasets[fmt])))
    assert source.scene is not None
    scene = verify_store(read_dataset_scene(source, tmp_path / "store"))
    assert "attributes.parquet" in scene.manifest["files"]  # the side table is recorded with the rest


SOURCE_DICTS = {
    "not an object": ([1, 2], r"a source must be a JSON object with a 'kind'"),
    "unknown kind": ({"kind": "carla"}, r"unknown source kind 'carla'"),
    "unknown synthetic field": ({"kind": "synthetic", "frames": 4}, r"unknown field\(s\) \['frames'\] for a synthetic"),
    "synthetic frames a string": ({"kind": "synthetic", "n_frames": "4"}, r"field n_frames must be an integer; got '4'"),
    "synthetic seed a bool": ({"kind": "synthetic", "seed": True}, r"field seed must be an integer; got True"),
    "synthetic seed beyond 32 bits": ({"kind": "synthetic", "seed": 2**40}, r"seed must be a whole number from 0 to "
                                                                            r"4294967295"),
    "synthetic huge frames": ({"kind": "synthetic", "n_frames": 10**7}, r"limited to 10000 frames"),
    "store without path": ({"kind": "store"}, r"bad store source .* missing 1 required positional argument"),
    "store path a number": ({"kind": "store", "path": 5}, r"needs the path of a scene store; got 5"),
    "dataset without dataroot": ({"kind": "kitti"}, r"a kitti source needs a 'dataroot'"),
    "dataset unknown field": ({"kind": "kitti", "dataroot": "/x", "sequence": "0"}, r"unknown field\(s\) \['sequence'\]"),
    "dataset cameras a string": ({"kind": "nuscenes", "dataroot": "/x", "cameras": "CAM_FRONT"},
                                 r"cameras must be a list of camera names"),
    "dataset sweeps a string": ({"kind": "nuscenes", "dataroot": "/x", "sweeps": "yes"}, r"sweeps must be true or false"),
    "dataset scene a number": ({"kind": "waymo-v2", "dataroot": "/x", "scene": 3}, r"scene must be a non-empty string"),
}


@pytest.mark.parametrize("case", list(SOURCE_DICTS))
def test_a_bad_source_dict_is_one_line(case, tmp_path):
    d, message = SOURCE_DICTS[case]
    before = files_under(tmp_path)
    with pytest.raises(OmniscsError, match=message) as info:
        source_from_dict(d)
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before
