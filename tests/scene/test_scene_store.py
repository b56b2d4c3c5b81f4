"""Scene store: the API later stages rely on, validation that names file and field, atomic writes."""
import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from omniscs.errors import OmniscsError, ValidationError
from omniscs.scene import CameraRecord, SceneWriter, load_scene
from omniscs.scene.store import BOX_SCHEMA, FRAME_SCHEMA
from tests.conftest import write_tiny_scene


def test_loaded_scene_exposes_the_documented_api(tiny_scene):
    scene = load_scene(tiny_scene)
    assert scene.camera_names == ["CAM_FRONT"]
    assert list(scene.frames.columns[:2]) == ["frame_idx", "timestamp_us"]
    assert scene.intrinsics("CAM_FRONT").shape == (3, 3)
    assert scene.ego_from_camera("CAM_FRONT").shape == (4, 4)
    assert scene.image_size("CAM_FRONT") == (64, 36)
    np.testing.assert_allclose(scene.world_from_ego(3)[:3, 3], [3.0, 0.0, 0.0])
    img = scene.image("CAM_FRONT", 2)
    assert img.dtype == np.uint8 and img.shape == (36, 64, 3) and img[0, 0, 0] == 102
    assert scene.lidar(0).dtype == np.float32 and scene.lidar(0).shape == (50, 4)
    assert scene.depth("CAM_FRONT", 0) is None and scene.instance_mask("CAM_FRONT", 0) is None
    for col in ["frame_idx", "track_id", "category", "cx", "cy", "cz", "length", "width", "height", "yaw"]:
        assert col in scene.boxes.columns
    assert len(scene.boxes) == 10 and scene.world is None and scene.road_map is None


def test_unknown_camera_and_frame_out_of_range_are_clear_errors(tiny_scene):
    scene = load_scene(tiny_scene)
    with pytest.raises(OmniscsError, match="unknown camera 'CAM_BACK'"):
        scene.image("CAM_BACK", 0)
    with pytest.raises(OmniscsError, match="out of range"):
        scene.world_from_ego(99)


def _rewrite(path, schema, mutate):
    df = pq.read_table(path).to_pandas()
    df = mutate(df)
    pq.write_table(pa.Table.from_pandas(df, schema=schema, preserve_index=False), path)


def _set_pose_entry(df, frame, index, value):
    poses = [np.array(p, dtype=float) for p in df.world_from_ego]
    poses[frame][index] = value
    df["world_from_ego"] = poses
    return df


@pytest.mark.parametrize("mutate, message", [
    (lambda df: _set_pose_entry(df, 2, 3, np.nan), "frames.parquet: field world_from_ego of frame 2 has NaN"),
    (lambda df: _set_pose_entry(df, 1, 0, 2.0), "frames.parquet: field world_from_ego of frame 1 is not a rigid"),
    (lambda df: df.assign(timestamp_us=[0, 100, 100, 300, 400]), "frames.parquet: field timestamp_us is not strictly increasing at frame 2"),
])
def test_corrupt_frames_table_names_the_file_and_field(tiny_scene, mutate, message):
    _rewrite(tiny_scene / "frames.parquet", FRAME_SCHEMA, mutate)
    with pytest.raises(ValidationError, match=message.replace("(", r"\(")):
        load_scene(tiny_scene)


def test_box_with_zero_size_is_rejected(tiny_scene):
    _rewrite(tiny_scene / "boxes.parquet", BOX_SCHEMA, lambda df: df.assign(width=np.where(df.index == 3, 0.0, df.width)))
    with pytest.raises(ValidationError, match=r"boxes.parquet: field length/width/height must be > 0"):
        load_scene(tiny_scene)


def test_missing_image_and_unknown_camera_folder_are_rejected(tiny_scene):
    (tiny_scene / "images" / "CAM_FRONT" / "000003.png").unlink()
    with pytest.raises(ValidationError, match="000003.png: image file is missing"):
        load_scene(tiny_scene)


def test_unknown_camera_folder_is_rejected(tiny_scene):
    (tiny_scene / "images" / "CAM_SIDEWAYS").mkdir()
    with pytest.raises(ValidationError, match=r"unknown camera\(s\) \['CAM_SIDEWAYS'\]"):
        load_scene(tiny_scene)


def test_manifest_listing_an_unknown_camera_is_rejected(tiny_scene):
    m = json.loads((tiny_scene / "manifest.json").read_text())
    m["cameras"].append("CAM_BACK")
    (tiny_scene / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ValidationError, match="manifest.json: field cameras"):
        load_scene(tiny_scene)


def test_missing_lidar_and_table_files_are_rejected(tmp_path):
    a = write_tiny_scene(tmp_path / "a")
    (a / "lidar" / "000001.npy").unlink()
    with pytest.raises(ValidationError, match="000001.npy: LiDAR file is missing"):
        load_scene(a)
    b = write_tiny_scene(tmp_path / "b")
    (b / "boxes.parquet").unlink()
    with pytest.raises(ValidationError, match="boxes.parquet: file is missing"):
        load_scene(b)


def test_writer_failure_leaves_nothing_behind(tmp_path):
    out = tmp_path / "scene"
    with pytest.raises(ValidationError, match="not strictly increasing"):
        with SceneWriter(out, "bad", {"kind": "test"}) as w:
            w.set_frames(np.array([0, 0]), np.stack([np.eye(4), np.eye(4)]))
            w.set_cameras([CameraRecord("CAM_FRONT", 8, 8, np.diag([5.0, 5.0, 1.0]), np.eye(4))])
            for f in range(2):
                w.write_image("CAM_FRONT", f, np.zeros((8, 8, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_exception_inside_writer_leaves_existing_scene_untouched(tmp_path):
    out = write_tiny_scene(tmp_path / "scene")
    before = sorted(p.name for p in out.rglob("*"))
    with pytest.raises(RuntimeError):
        with SceneWriter(out, "tiny", {"kind": "test"}, overwrite=True) as w:
            w.write_image("CAM_FRONT", 0, np.zeros((8, 8, 3), np.uint8))
            raise RuntimeError("render crashed")
    assert sorted(p.name for p in out.rglob("*")) == before
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]
    load_scene(out)


def test_content_hash_changes_with_geometry_and_not_with_rewrite(tmp_path):
    a = load_scene(write_tiny_scene(tmp_path / "a"))
    b = load_scene(write_tiny_scene(tmp_path / "b"))
    c = load_scene(write_tiny_scene(tmp_path / "c", n_tracks=3))
    assert a.content_hash == b.content_hash != c.content_hash
