"""Damaged scene stores: every bad manifest, table or data file is one ValidationError line naming the file (and
field), never a traceback; ``load_scene`` catches truncation by recorded sizes, ``verify_store`` catches changed
bytes by sha256 (or, in stores written before sizes and hashes were recorded, by decoding every file); a failing
writer leaves nothing behind."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from omniscs.errors import OmniscsError, ValidationError
from omniscs.geometry import ego_from_camera_mount, intrinsics_from_fov, pose_from_xyz_yaw
from omniscs.scene import CameraRecord, SceneWriter, load_scene
from omniscs.scene.store import FILES, MANIFEST, file_sha256, verify_store
from tests.conftest import write_tiny_scene
from tests.damage import files_under, set_column

W, H = 64, 36


def write_gt_scene(out: Path, n_frames: int = 2) -> Path:
    """A hand-made store with ground-truth files (depth, instance, semantic), like a synthetic one."""
    with SceneWriter(out, "tiny-gt", {"kind": "test"}) as w:
        w.set_frames(np.arange(n_frames, dtype=np.int64) * 100_000,
                     np.stack([pose_from_xyz_yaw(float(f), 0.0, 0.0, 0.0) for f in range(n_frames)]))
        w.set_cameras([CameraRecord("CAM_FRONT", W, H, intrinsics_from_fov(W, H, np.radians(70)),
                                    ego_from_camera_mount(1.5, 0.0, 1.6, 0.0))])
        for f in range(n_frames):
            w.write_image("CAM_FRONT", f, np.full((H, W, 3), 90, np.uint8))
            w.write_gt("CAM_FRONT", f, np.full((H, W), 5.0), np.full((H, W), -1), np.zeros((H, W)))
    return out


# ----------------------------------------------------------------------------- damage
def manifest(root: Path) -> dict:
    return json.loads((root / MANIFEST).read_text())


def set_manifest(change):
    def damage(root: Path):
        m = manifest(root)
        change(m)  # changes m in place
        (root / MANIFEST).write_text(json.dumps(m))
    return damage


def old_store(damage=None):
    """As a store written before sizes and hashes were recorded (no ``files`` field), then ``damage``."""
    def apply(root: Path):
        set_manifest(lambda m: m.pop(FILES))(root)
        if damage is not None:
            damage(root)
    return apply


def raw_manifest(text: bytes):
    return lambda root: (root / MANIFEST).write_bytes(text)


def table(name: str, change):
    """Rewrite a store table through ``change(pa.Table) -> pa.Table``."""
    def damage(root: Path):
        pq.write_table(change(pq.read_table(root / name)), root / name)
    return damage


def pose_entry(frame: int, index: int, value: float):
    def values(poses):
        poses[frame][index] = value
        return poses
    return set_column("world_from_ego", values, pa.list_(pa.float64(), 16))


def truncate(rel: str):
    def damage(root: Path):
        data = (root / rel).read_bytes()
        (root / rel).write_bytes(data[: len(data) // 2])
    return damage


def flip_byte(rel: str, where: float = 0.5):
    def damage(root: Path):
        data = bytearray((root / rel).read_bytes())
        data[int(len(data) * where)] ^= 0xFF
        (root / rel).write_bytes(bytes(data))
    return damage


def garbage(rel: str):
    """Same size, random bytes."""
    def damage(root: Path):
        n = (root / rel).stat().st_size
        (root / rel).write_bytes(np.random.default_rng(0).integers(0, 256, n, dtype=np.uint8).tobytes())
    return damage


def replace_image(rel: str, rgb: np.ndarray):
    def damage(root: Path):
        import cv2

        cv2.imwrite(str(root / rel), rgb)
    return damage


def rehashed(damage, rel: str):
    """``damage``, then the manifest's size and sha256 of ``rel`` brought up to date (a careless or hostile edit)."""
    def apply(root: Path):
        damage(root)
        set_manifest(lambda m: m[FILES].__setitem__(rel, [(root / rel).stat().st_size, file_sha256(root / rel)]))(root)
    return apply


def jpeg_bytes(rel: str):
    def damage(root: Path):
        import cv2

        (root / rel).write_bytes(cv2.imencode(".jpg", np.zeros((36, 64, 3), np.uint8))[1].tobytes())
    return damage


IMG = "images/CAM_FRONT/000002.png"
LIDAR = "lidar/000003.npy"
GT = "gt/CAM_FRONT/000001.npz"

#: id -> (damage, message regex, which check finds it: "load" = load_scene already, "verify" = verify_store only)
CASES = {
    # the manifest
    "manifest is a JSON list": (raw_manifest(b"[1, 2]"), r"manifest.json: must be a JSON object .* got a list", "load"),
    "manifest is a number": (raw_manifest(b"5"), r"manifest.json: must be a JSON object .* got a number", "load"),
    "manifest is not JSON": (raw_manifest(b"{schema_version: 1"), r"manifest.json is not valid JSON", "load"),
    "manifest is empty": (raw_manifest(b""), r"manifest.json is not valid JSON", "load"),
    "manifest is binary": (raw_manifest(b"\xff\xfe\x00\x81"), r"manifest.json is not UTF-8 text \(byte 0", "load"),
    "manifest nested 100,000 deep": (raw_manifest(b"[" * 100_000), r"manifest.json is nested more than 256 deep",
                                     "load"),
    "manifest with a 5000-digit number": (raw_manifest(b'{"n_frames": ' + b"9" * 5000 + b"}"),
                                          r"manifest.json holds an integer of 5000 digits", "load"),
    "manifest with Infinity": (raw_manifest(b'{"n_frames": Infinity}'), r"manifest.json holds Infinity", "load"),
    "manifest is missing": (lambda root: (root / MANIFEST).unlink(), r"manifest.json is missing", "load"),
    "missing fields": (set_manifest(lambda m: [m.pop("content_hash"), m.pop("has_gt")]),
                       r"manifest.json: missing field\(s\) \['has_gt', 'content_hash'\]", "load"),
    "schema version from the future": (set_manifest(lambda m: m.update(schema_version=99)),
                                       r"field schema_version is 99; this omniscs reads 1", "load"),
    "schema version a string": (set_manifest(lambda m: m.update(schema_version="1")),
                                r"field schema_version is '1'", "load"),
    "n_frames a string": (set_manifest(lambda m: m.update(n_frames="5")),
                          r"manifest.json: field n_frames must be an integer; got '5'", "load"),
    "n_frames wrong": (set_manifest(lambda m: m.update(n_frames=7)),
                       r"manifest.json: field n_frames is 7 but frames.parquet has 5 rows", "load"),
    "has_lidar a string": (set_manifest(lambda m: m.update(has_lidar="yes")),
                           r"field has_lidar must be true or false; got 'yes'", "load"),
    "source a string": (set_manifest(lambda m: m.update(source="syn:straight:0")),
                        r"field source must be a JSON object", "load"),
    "cameras a string": (set_manifest(lambda m: m.update(cameras="CAM_FRONT")), r"field cameras must be a JSON list",
                         "load"),
    "unsafe scene id": (set_manifest(lambda m: m.update(scene_id="../../x")),
                        r"manifest.json: field scene_id: scene id '../../x' is not a safe id", "load"),
    "scene id with a slash": (set_manifest(lambda m: m.update(scene_id="a/b")), r"field scene_id: .* not a safe id",
                              "load"),
    "unsafe camera name": (set_manifest(lambda m: m.update(cameras=["../CAM"])),
                           r"field cameras: camera name '../CAM' is not a safe id", "load"),
    "seed a string": (set_manifest(lambda m: m.update(seed="zero")), r"field seed must be an integer; got 'zero'", "load"),
    "global_from_world short": (set_manifest(lambda m: m.update(global_from_world=[1.0, 0.0, 0.0])),
                                r"field global_from_world must be 16 finite numbers", "load"),
    "files record outside the store": (set_manifest(lambda m: m[FILES].update({"../escape.png": [1, "0" * 64]})),
                                       r"field files names '../escape.png', not a file inside the store", "load"),
    "files record malformed": (set_manifest(lambda m: m[FILES].update({IMG: [12]})),
                               r"field files\['images/CAM_FRONT/000002.png'\] must be \[size in bytes, sha256 hex\]",
                               "load"),
    "recorded file missing": (set_manifest(lambda m: m[FILES].update({"lidar/000099.npy": [10, "0" * 64]})),
                              r"lidar/000099.npy: file is missing \(the manifest records it\)", "load"),
    # the tables
    "frames table not Parquet": (lambda root: (root / "frames.parquet").write_bytes(b"PAR1 not really"),
                                 r"frames.parquet: unreadable Parquet", "load"),
    "frames table truncated": (truncate("frames.parquet"), r"frames.parquet: unreadable Parquet", "load"),
    "frame_idx of strings": (table("frames.parquet", set_column("frame_idx", lambda v: [str(x) for x in v])),
                             r"frames.parquet: column frame_idx has type string, expected int32", "load"),
    "camera width a float": (table("cameras.parquet", set_column("width", lambda v: [float(x) for x in v])),
                             r"cameras.parquet: column width has type double, expected int32", "load"),
    "box yaw column missing": (table("boxes.parquet", lambda t: t.drop(["yaw"])),
                               r"boxes.parquet: missing column\(s\) \['yaw'\]", "load"),
    "extra box column": (table("boxes.parquet", lambda t: t.append_column("speed", pa.array([1.0] * t.num_rows))),
                         r"boxes.parquet: unexpected column\(s\) \['speed'\]", "load"),
    "pose of 15 numbers": (table("frames.parquet", set_column("world_from_ego", lambda v: [p[:15] for p in v],
                                                             pa.list_(pa.float64()))),
                           r"frames.parquet: column world_from_ego does not fit", "load"),
    "NaN pose": (table("frames.parquet", pose_entry(2, 3, float("nan"))),
                 r"frames.parquet: field world_from_ego of frame 2 has NaN or Inf", "load"),
    "Inf pose": (table("frames.parquet", pose_entry(1, 7, float("inf"))),
                 r"frames.parquet: field world_from_ego of frame 1 has NaN or Inf", "load"),
    "null pose": (table("frames.parquet", set_column("world_from_ego", lambda v: [None] + v[1:],
                                                     pa.list_(pa.float64(), 16))),
                  r"frames.parquet: column world_from_ego has 1 null value", "load"),
    "NaN box centre": (table("boxes.parquet", set_column("cx", lambda v: [float("nan")] + v[1:])),
                       r"boxes.parquet: box fields have NaN or Inf", "load"),
    "null category": (table("boxes.parquet", set_column("category", lambda v: [None] + v[1:], pa.string())),
                      r"boxes.parquet: column category has 1 null value", "load"),
    "track id beyond int64": (table("boxes.parquet", set_column("track_id", lambda v: [2**63 + 5] + v[1:],
                                                                pa.uint64())),
                              r"boxes.parquet: column track_id does not fit int64", "load"),
    "camera listed twice": (table("cameras.parquet", lambda t: pa.concat_tables([t, t])),
                            r"cameras.parquet: camera CAM_FRONT is listed twice", "load"),
    "unsafe camera in table": (table("cameras.parquet", set_column("camera", ["../CAM"])),
                               r"cameras.parquet: field camera: camera name '../CAM' is not a safe id", "load"),
    # data files (new stores: sizes in load_scene, hashes in verify_store)
    "truncated PNG": (truncate(IMG), r"000002.png: file is \d+ bytes but manifest.json records \d+ \(truncated", "load"),
    "truncated LiDAR": (truncate(LIDAR), r"000003.npy: file is \d+ bytes but manifest.json records", "load"),
    "missing image": (lambda root: (root / IMG).unlink(), r"000002.png: image file is missing", "load"),
    "missing LiDAR": (lambda root: (root / LIDAR).unlink(), r"000003.npy: LiDAR file is missing", "load"),
    "corrupt PNG of the same size": (flip_byte(IMG), r"000002.png: content differs from the sha256", "verify"),
    "LiDAR byte flipped": (flip_byte(LIDAR, 0.9), r"000003.npy: content differs from the sha256", "verify"),
    # a file swapped together with its recorded size and hash: the images' structure still tells
    "a JPEG under the PNG's name, hash updated": (rehashed(jpeg_bytes(IMG), IMG), r"000002.png: not a PNG image",
                                                  "verify"),
    "a PNG of another size, hash updated": (rehashed(replace_image(IMG, np.zeros((18, 32, 3), np.uint8)), IMG),
                                            r"000002.png: image is 32x18 but camera CAM_FRONT is 64x36", "verify"),
    "a cut-off PNG, hash updated": (rehashed(truncate(IMG), IMG), r"000002.png: the PNG image is cut off", "verify"),
    "boxes table changed": (flip_byte("boxes.parquet", 0.3), r"boxes.parquet", "load_or_verify"),
    # stores written before sizes and hashes were recorded: verify_store decodes
    "old store: garbage PNG": (old_store(garbage(IMG)), r"000002.png: image is unreadable", "verify"),
    "old store: corrupt PNG": (old_store(flip_byte(IMG)), r"000002.png: image is unreadable", "verify"),
    "old store: PNG of the wrong size": (old_store(replace_image(IMG, np.zeros((18, 32, 3), np.uint8))),
                                         r"000002.png: image is 32x18 but camera CAM_FRONT is 64x36", "verify"),
    "old store: truncated LiDAR": (old_store(truncate(LIDAR)), r"000003.npy: LiDAR file is damaged", "verify"),
    "old store: LiDAR of 3 columns": (old_store(lambda root: np.save(root / LIDAR, np.zeros((7, 3), np.float32))),
                                      r"000003.npy: LiDAR points must be float \[N, 4\]", "verify"),
    "old store: NaN LiDAR": (old_store(lambda root: np.save(root / LIDAR, np.full((7, 4), np.nan, np.float32))),
                             r"000003.npy: LiDAR points have NaN or Inf", "verify"),
    "old store: bad world.json": (old_store(lambda root: (root / "world.json").write_text("{")),
                                  r"world.json is not valid JSON .*; not a readable world description", "verify"),
    "old store: bad side table": (old_store(lambda root: (root / "attributes.parquet").write_bytes(b"nope")),
                                  r"attributes.parquet: unreadable Parquet", "verify"),
}

GT_CASES = {
    "truncated ground truth": (truncate(GT), r"000001.npz: file is \d+ bytes but manifest.json records", "load"),
    "old store: damaged ground truth": (old_store(truncate(GT)), r"000001.npz: ground-truth file is damaged", "verify"),
    "old store: ground truth without semantic": (
        old_store(lambda root: np.savez(root / GT, depth=np.zeros((H, W), np.float32),
                                        instance=np.zeros((H, W), np.int32))),
        r"000001.npz: ground-truth file has no 'semantic' array", "verify"),
    "old store: ground truth of the wrong size": (
        old_store(lambda root: np.savez(root / GT, depth=np.zeros((2, 2), np.float32),
                                        instance=np.zeros((H, W), np.int32), semantic=np.zeros((H, W), np.uint8))),
        r"000001.npz: array depth is float32 \[2, 2\]", "verify"),
}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    base = tmp_path_factory.mktemp("pristine")
    return {"tiny": write_tiny_scene(base / "tiny"), "gt": write_gt_scene(base / "gt")}


def _check(root: Path, damage, message: str, where: str, tmp_path: Path) -> None:
    damage(root)
    before = files_under(tmp_path)
    if where == "verify":
        load_scene(root)  # the cheap check passes: only the full one can see this damage
    with pytest.raises(ValidationError, match=message) as info:
        load_scene(root) if where == "load" else verify_store(root)
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before


@pytest.mark.parametrize("case", list(CASES))
def test_a_damaged_store_is_one_validation_error_line(case, pristine, tmp_path):
    import shutil

    root = Path(shutil.copytree(pristine["tiny"], tmp_path / "store"))
    damage, message, where = CASES[case]
    if where == "load_or_verify":
        _check_either(root, damage, message, tmp_path)
    else:
        _check(root, damage, message, where, tmp_path)


def _check_either(root: Path, damage, message: str, tmp_path: Path) -> None:
    """Damage that may or may not change what the cheap check sees: one of the two checks must name it."""
    damage(root)
    before = files_under(tmp_path)
    with pytest.raises(ValidationError, match=message) as info:
        verify_store(root)
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before


@pytest.mark.parametrize("case", list(GT_CASES))
def test_damaged_ground_truth_is_one_validation_error_line(case, pristine, tmp_path):
    import shutil

    root = Path(shutil.copytree(pristine["gt"], tmp_path / "store"))
    _check(root, *GT_CASES[case], tmp_path)


def test_a_path_that_is_not_a_store_is_refused(tmp_path):
    (tmp_path / "file").write_text("x")
    for path in (tmp_path / "nowhere", tmp_path / "file", tmp_path):
        with pytest.raises(ValidationError, match="manifest.json is missing") as info:
            load_scene(path)
        assert len(str(info.value).splitlines()) == 1


ACCESSOR_CASES = {
    "image": (garbage(IMG), lambda s: s.image("CAM_FRONT", 2), r"000002.png: image is unreadable"),
    "lidar": (truncate(LIDAR), lambda s: s.lidar(3), r"000003.npy: LiDAR file is damaged"),
    "lidar of 3 columns": (lambda root: np.save(root / LIDAR, np.zeros((4, 3), np.float32)), lambda s: s.lidar(3),
                           r"LiDAR points must be float \[N, 4\]"),
}


@pytest.mark.parametrize("case", list(ACCESSOR_CASES))
def test_reading_a_damaged_file_of_an_old_store_is_one_validation_error(case, pristine, tmp_path):
    import shutil

    root = Path(shutil.copytree(pristine["tiny"], tmp_path / "store"))
    damage, read, message = ACCESSOR_CASES[case]
    old_store(damage)(root)
    scene = load_scene(root)
    with pytest.raises(ValidationError, match=message) as info:
        read(scene)
    assert len(str(info.value).splitlines()) == 1


def test_a_new_store_records_every_file_and_verifies(pristine):
    root = pristine["gt"]
    files = manifest(root)[FILES]
    on_disk = sorted(p.relative_to(root).as_posix() for p in root.rglob("*")
                     if p.is_file() and p.name not in (MANIFEST, ".omniscs"))
    assert sorted(files) == on_disk and "gt/CAM_FRONT/000001.npz" in files
    assert all(files[rel] == [(root / rel).stat().st_size, file_sha256(root / rel)] for rel in files)
    seen = []
    assert verify_store(root, progress=lambda d, t: seen.append((d, t))).scene_id == "tiny-gt"
    assert seen[-1] == (len(files), len(files))


def test_an_old_store_without_records_still_loads_and_verifies_by_decoding(pristine, tmp_path):
    import shutil

    root = Path(shutil.copytree(pristine["gt"], tmp_path / "store"))
    old_store()(root)
    assert FILES not in manifest(root)
    assert load_scene(root).n_frames == 2 and verify_store(root).has_gt


# ----------------------------------------------------------------------------- writing
def _writer(out: Path, scene_id: str = "w", **kw) -> SceneWriter:
    return SceneWriter(out, scene_id, {"kind": "test"}, **kw)


def _cam(name: str = "CAM_FRONT") -> CameraRecord:
    return CameraRecord(name, W, H, intrinsics_from_fov(W, H, np.radians(70)), np.eye(4))


def _frames(w: SceneWriter, n: int = 2) -> None:
    w.set_frames(np.arange(n) * 100_000, np.stack([np.eye(4)] * n))


def _nan_lidar(w):
    _frames(w)
    w.set_cameras([_cam()])
    w.write_lidar(0, np.full((5, 4), np.nan))


def _small_image(w):
    w.set_cameras([_cam()])
    w.write_image("CAM_FRONT", 0, np.zeros((18, 32, 3), np.uint8))


def _no_cameras(w):
    _frames(w)


def _bad_extra(w):
    _frames(w, 1)
    w.set_cameras([_cam()])
    w.write_image("CAM_FRONT", 0, np.zeros((H, W, 3), np.uint8))
    w.set_extra(seed="zero")


def _timestamps_repeat(w):
    w.set_frames(np.array([0, 0]), np.stack([np.eye(4)] * 2))
    w.set_cameras([_cam()])
    for f in range(2):
        w.write_image("CAM_FRONT", f, np.zeros((H, W, 3), np.uint8))


WRITER_CASES = {
    "NaN LiDAR": (_nan_lidar, r"LiDAR points of frame 0 have NaN or Inf"),
    "image of the wrong size": (_small_image, r"image for CAM_FRONT/0 is 32x18 but the camera is 64x36"),
    "unsafe camera name": (lambda w: w.set_cameras([_cam("../CAM")]), r"camera name '../CAM' is not a safe id"),
    "camera twice": (lambda w: w.set_cameras([_cam(), _cam()]), r"camera names must be unique"),
    "reserved extra field": (lambda w: w.set_extra(scene_id="other"), r"extra manifest fields \['scene_id'\]"),
    "no cameras": (_no_cameras, r"a scene needs frames and cameras"),
    "extra field of the wrong type": (_bad_extra, r"/out/manifest.json: field seed must be an integer"),
    "timestamps repeat": (_timestamps_repeat, r"/out/frames.parquet: field timestamp_us is not strictly increasing"),
}


@pytest.mark.parametrize("case", list(WRITER_CASES))
def test_a_failing_writer_is_one_line_and_leaves_nothing(case, tmp_path):
    action, message = WRITER_CASES[case]
    before = files_under(tmp_path)
    with pytest.raises(OmniscsError, match=message) as info:
        with _writer(tmp_path / "out") as w:
            action(w)
    assert len(str(info.value).splitlines()) == 1 and ".tmp-" not in str(info.value)
    assert files_under(tmp_path) == before


def test_writer_refusals_before_any_file(tmp_path):
    before = files_under(tmp_path)
    for make, message in ((lambda: _writer(tmp_path / "out", "../x"), r"scene id '../x' is not a safe id"),
                          (lambda: SceneWriter(tmp_path / "out", "w", "not a dict"), r"source must be a dict"),
                          (lambda: _writer(tmp_path / "out").write_lidar(0, np.zeros((1, 4))), r"only inside `with"),
                          (lambda: _writer(tmp_path), r"already exists")):
        with pytest.raises(OmniscsError, match=message) as info:
            make()
        assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before


def test_an_exception_in_the_middle_leaves_no_output_folder(tmp_path):
    before = files_under(tmp_path)
    with pytest.raises(RuntimeError, match="render crashed"):
        with _writer(tmp_path / "a" / "b" / "out") as w:
            _frames(w)
            w.set_cameras([_cam()])
            w.write_image("CAM_FRONT", 0, np.zeros((H, W, 3), np.uint8))
            w.write_lidar(0, np.zeros((3, 4)))
            raise RuntimeError("render crashed")
    assert files_under(tmp_path) == before  # no output, no temporary, no parent folder made for it


# ----------------------------------------------------------------------------- properties
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner,
                                                                                      max_size=3), max_leaves=8)
MANIFEST_KEYS = ["schema_version", "scene_id", "source", "cameras", "n_frames", "has_lidar", "has_gt", "content_hash",
                 FILES, "template", "seed", "global_from_world", "ego_from_lidar"]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(MANIFEST_KEYS), value=JSON_VALUES)
def test_any_manifest_field_value_loads_or_is_one_validation_error(pristine, tmp_path_factory, key, value):
    """Property: whatever JSON a manifest field holds, ``load_scene`` loads the store or raises one ValidationError
    line (never KeyError, TypeError, AttributeError or a pyarrow error)."""
    import shutil

    root = Path(shutil.copytree(pristine["tiny"], tmp_path_factory.mktemp("m") / "store"))
    set_manifest(lambda m: m.update({key: value}))(root)
    try:
        load_scene(root)
    except ValidationError as exc:
        assert len(str(exc).splitlines()) == 1


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(index=st.integers(0, 10_000), fraction=st.floats(0.0, 0.95), garble=st.booleans())
def test_any_truncated_or_garbled_store_file_is_one_validation_error(pristine, tmp_path_factory, index, fraction,
                                                                      garble):
    """Property: cutting any file of a store short, or overwriting its start with garbage, is refused by
    ``verify_store`` with one ValidationError line."""
    import shutil

    root = Path(shutil.copytree(pristine["gt"], tmp_path_factory.mktemp("t") / "store"))
    files = sorted(p for p in root.rglob("*") if p.is_file() and p.name != ".omniscs")
    path = files[index % len(files)]
    data = path.read_bytes()
    if garble:
        n = max(1, int(len(data) * fraction))
        path.write_bytes(bytes(b ^ 0xA5 for b in data[:n]) + data[n:])
    else:
        path.write_bytes(data[: int(len(data.rstrip()) * fraction)])
    with pytest.raises(ValidationError) as info:
        verify_store(root)
    assert len(str(info.value).splitlines()) == 1
