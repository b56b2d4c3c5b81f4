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

import subprocess  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from omniscs.geometry import ego_from_camera_mount, intrinsics_from_fov, pose_from_xyz_yaw  # noqa: E402
from omniscs.scene import CameraRecord, SceneWriter  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]
#: What may appear in the checkout while tests run: caches of Python and of the test tools.
CHECKOUT_NOISE = ("__pycache__", ".hypothesis", ".pytest_cache")


def _checkout_state() -> set[str]:
    """Everything git sees in the checkout besides its committed files: changes, new files, ignored files (a new
    folder counts as one entry)."""
    out = subprocess.run(["git", "status", "--porcelain", "--untracked-files=normal", "--ignored=matching"],
                         cwd=ROOT, capture_output=True, text=True)
    if out.returncode != 0:  # not a git checkout (an unpacked source tree): nothing to compare
        return set()
    return {line for line in out.stdout.splitlines() if not any(n in line for n in CHECKOUT_NOISE)}


def pytest_sessionstart(session):
    if not hasattr(session.config, "workerinput"):  # the controller (or a run without xdist), once
        session.config._checkout_before = _checkout_state()


def pytest_sessionfinish(session, exitstatus):
    before = getattr(session.config, "_checkout_before", None)
    if before is None:
        return
    left = sorted(_checkout_state() - before)
    if left:
        session.config.get_terminal_writer().line(
            "the test run changed the checkout (tests must write under tmp_path or $OMNISCS_HOME): " + ", ".join(left),
            red=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.fixture(autouse=True)
def _workspace_outside_the_checkout(tmp_path, monkeypatch):
    """Every test's default workspace ($OMNISCS_HOME) is a temporary folder, never ./omniscs-data."""
    monkeypatch.setenv("OMNISCS_HOME", str(tmp_path / "omniscs-home"))


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
