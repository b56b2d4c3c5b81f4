"""Shared fixtures: an isolated Prefect home, tiny hand-made scenes and small rendered synthetic scenes."""
from __future__ import annotations

import atexit
import os
import shutil
import tempfile

# Prefect reads its settings when first imported: isolate it before any test module imports it (and remove it
# when the test process ends, so test runs leave nothing in /tmp).
os.environ["PREFECT_HOME"] = tempfile.mkdtemp(prefix="omniscs-prefect-")
atexit.register(shutil.rmtree, os.environ["PREFECT_HOME"], True)
os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from omniscs.geometry import ego_from_camera_mount, intrinsics_from_fov, pose_from_xyz_yaw  # noqa: E402
from omniscs.scene import CameraRecord, SceneWriter  # noqa: E402


@pytest.fixture(scope="session")
def prefect_harness():
    """One temporary Prefect server for the whole session (starting one costs ~15 s)."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=180):
        yield


def write_tiny_scene(out: Path, n_frames: int = 5, n_tracks: int = 2, width: int = 64, height: int = 36,
                     scene_id: str = "tiny", with_lidar: bool = True) -> Path:
    """A hand-made scene store (flat grey images, straight-line motion) in a few milliseconds."""
    rng = np.random.default_rng(0)
    with SceneWriter(out, scene_id, {"kind": "test"}) as w:
        w.set_frames(np.arange(n_frames, dtype=np.int64) * 100_000,
                     np.stack([pose_from_xyz_yaw(1.0 * f, 0.0, 0.0, 0.0) for f in range(n_frames)]))
        w.set_cameras([CameraRecord("CAM_FRONT", width, height, intrinsics_from_fov(width, height, np.radians(70)),
                                    ego_from_camera_mount(1.5, 0.0, 1.6, 0.0))])
        rows = []
        for t in range(n_tracks):
            for f in range(n_frames):
                rows.append(dict(frame_idx=f, track_id=t, category="car", cx=10.0 + 5 * t + 0.5 * f * t,
                                 cy=3.0 * t, cz=0.8, length=4.5, width=1.9, height=1.6, yaw=0.0))
        w.set_boxes(rows)
        for f in range(n_frames):
            w.write_image("CAM_FRONT", f, np.full((height, width, 3), 100 + f, np.uint8))
            if with_lidar:
                w.write_lidar(f, rng.normal(size=(50, 4)).astype(np.float32))
    return out


@pytest.fixture
def tiny_scene(tmp_path) -> Path:
    return write_tiny_scene(tmp_path / "tiny")
