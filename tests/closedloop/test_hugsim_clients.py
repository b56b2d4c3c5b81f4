"""What HUGSIM's own driving clients read from a state, read here as they read it (their reads and their maths,
written for this test from their published client code, not their models), from a real server driven by
``hugsim-client``: a UniAD-style client (``cam_params`` -> ``lidar2img``, ``ego_pos`` / ``ego_rot`` -> can_bus) and
a NAVSIM-style one (cameras from ``intrinsic`` and ``l2c``, ego status, a one-hot command)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from annotate_fixtures import logged_variant
from omniscs.closedloop.scenario import variant_scenario
from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator
from omniscs.server.hugsim import create_app
from omniscs.server.transport import start_in_thread

CAMERA = "CAM_FRONT"
#: HUGSIM's clients' map from its world's OpenCV axes to the IMU's (their constant, restated).
OPENCV2IMU = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=np.float64)


def focal(fov: float, pixels: int) -> float:
    return pixels / (2 * math.tan(fov / 2))


def intrinsic_matrix(d: dict) -> np.ndarray:  # [4, 4], as their get_intrinsic builds it
    K = np.eye(4)
    K[0, 0], K[1, 1] = focal(d["fovx"], d["W"]), focal(d["fovy"], d["H"])
    K[0, 2], K[1, 2] = d["cx"], d["cy"]
    return K


def yaw_matrix(yaw: float) -> np.ndarray:  # [3, 3] about z (their SCR.from_euler('XYZ', [0, 0, yaw]))
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def uniad_reads(obs: dict, info: dict, cameras: list[str]) -> dict:
    """A UniAD-style client's parse of a state: images, lidar2img per camera, can_bus position and yaw, command."""
    imu_yaw = -info["ego_rot"][1]
    v2w = np.eye(4)
    v2w[:3, :3] = yaw_matrix(imu_yaw)
    v2w[:3, 3] = OPENCV2IMU @ np.asarray(info["ego_pos"], dtype=np.float64)
    lidar2img = {c: intrinsic_matrix(info["cam_params"][c]["intrinsic"]) @ np.asarray(info["cam_params"][c]["l2c"])
                 for c in cameras}
    cmd = [0, 0, 0]
    cmd[info["command"]] = 1
    return {"images": {c: obs["rgb"][c] for c in cameras}, "lidar2img": lidar2img, "v2w": v2w,
            "can_bus_yaw": imu_yaw % (2 * math.pi), "velocity": info["ego_velo"], "accel": info["accelerate"],
            "steer_rate": info["steer_rate"], "timestamp": info["timestamp"], "command": cmd}


def navsim_reads(obs: dict, info: dict, cameras: list[str]) -> dict:
    """A NAVSIM-style client's parse: per camera K (3x3) and sensor-to-LiDAR pose, the ego status."""
    cams = {}
    for c in cameras:
        d, l2c = info["cam_params"][c]["intrinsic"], np.asarray(info["cam_params"][c]["l2c"], dtype=np.float64)
        K = np.eye(3)
        K[0, 0], K[1, 1], K[0, 2], K[1, 2] = focal(d["fovx"], d["W"]), focal(d["fovy"], d["H"]), d["cx"], d["cy"]
        c2l = np.linalg.inv(l2c)
        cams[c] = {"image": obs["rgb"][c], "K": K, "sensor2lidar_rotation": c2l[:3, :3],
                   "sensor2lidar_translation": c2l[:3, 3]}
    command = np.zeros(4)
    command[info["command"]] = 1
    return {"cameras": cams, "ego_pose": OPENCV2IMU @ np.asarray(info["ego_pos"], dtype=np.float64),
            "steer": info["ego_steer"], "velocity": info["ego_velo"], "accel": info["accelerate"], "command": command}


@pytest.fixture(scope="module")
def state(world):
    """(obs, info, the simulator's own world_from_ego) of a state a real server sent to hugsim-client."""
    import os

    os.environ["IN_HF_SPACE"] = "false"  # else the client starts a web server of its own
    from hugsim_client import HugsimClient

    scene, graph, log = world
    variant = variant_scenario(scene, logged_variant(scene), log)
    app = create_app(lambda: Simulator(graph, scene, ClosedLoopConfig(cameras=(CAMERA,), width=96)),
                     {variant.scenario_id: variant}, ("tok",))
    with start_in_thread(app) as handle:
        client = HugsimClient(host=handle.url, api_token="tok")
        client.reset_env()
        client.execute_action(np.array([[0.0, 2.0 * k] for k in range(1, 7)], np.float32))
        got = client.get_current_state()
    return got.state.obs, got.state.info


def test_both_clients_find_every_key_they_read(state):
    obs, info = state
    uniad, navsim = uniad_reads(obs, info, [CAMERA]), navsim_reads(obs, info, [CAMERA])
    assert uniad["images"][CAMERA].dtype == np.uint8 and uniad["images"][CAMERA].shape == (54, 96, 3)
    assert navsim["cameras"][CAMERA]["image"].shape == (54, 96, 3)
    assert uniad["command"].count(1) == 1 and navsim["command"].sum() == 1
    for value in (uniad["velocity"], uniad["accel"], uniad["steer_rate"], uniad["timestamp"], navsim["steer"]):
        assert math.isfinite(value)
    assert uniad["timestamp"] > 0  # a step was driven


def test_the_focal_they_derive_is_the_one_the_image_was_rendered_with(state):
    obs, info = state
    K = np.asarray(info["cam_params"][CAMERA]["K"])
    d = info["cam_params"][CAMERA]["intrinsic"]
    assert (d["W"], d["H"]) == (obs["rgb"][CAMERA].shape[1], obs["rgb"][CAMERA].shape[0])
    np.testing.assert_allclose(intrinsic_matrix(d)[:3, :3], K, atol=1e-9)
    np.testing.assert_allclose(navsim_reads(obs, info, [CAMERA])["cameras"][CAMERA]["K"], K, atol=1e-9)


def test_their_ego_pose_and_yaw_are_the_egos(state):
    obs, info = state
    uniad = uniad_reads(obs, info, [CAMERA])
    T = np.asarray(info["world_from_ego"])
    np.testing.assert_allclose(uniad["v2w"][:3, 3], T[:3, 3], atol=1e-9)
    np.testing.assert_allclose(uniad["v2w"][:3, :3], T[:3, :3], atol=1e-9)
    assert math.isclose(uniad["can_bus_yaw"], info["ego_yaw"] % (2 * math.pi), abs_tol=1e-9)
    np.testing.assert_allclose(navsim_reads(obs, info, [CAMERA])["ego_pose"], info["ego_xyz"], atol=1e-9)


def test_their_lidar2img_puts_a_box_centre_on_the_pixels_the_renderer_drew_it_at(state):
    """The box centre of each agent drawn whole in the image, taken into the LiDAR frame from what the client
    reads (its pose from ego_pos/ego_rot, the LiDAR in the ego frame from v2c and l2c), lands through lidar2img
    within 1 px of that agent's rendered pixels."""
    obs, info = state
    uniad = uniad_reads(obs, info, [CAMERA])
    instance = obs["instance"][CAMERA]
    h, w = instance.shape
    cp = info["cam_params"][CAMERA]
    ego_from_lidar = np.linalg.inv(np.asarray(cp["v2c"])) @ np.asarray(cp["l2c"])
    lidar_from_world = np.linalg.inv(uniad["v2w"] @ ego_from_lidar)
    checked = 0
    for box in info["boxes"]:
        ys, xs = np.nonzero(instance == box["track_id"])
        if len(xs) < 20 or xs.min() == 0 or ys.min() == 0 or xs.max() == w - 1 or ys.max() == h - 1:
            continue  # not in view, or cut by the image's edge (its centre may lie outside the image)
        uvw = uniad["lidar2img"][CAMERA] @ (lidar_from_world @ np.array([*box["center"], 1.0]))
        assert uvw[2] > 0
        u, v = uvw[0] / uvw[2], uvw[1] / uvw[2]
        assert np.min(np.hypot(xs + 0.5 - u, ys + 0.5 - v)) <= 1.0, (box["track_id"], u, v)
        checked += 1
    assert checked >= 1, "no agent drawn whole in the image"
    # and the planning frame is the LiDAR frame: its y axis is the ego's heading, x to the right
    np.testing.assert_allclose(ego_from_lidar[:3, :3] @ [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(ego_from_lidar[:3, :3] @ [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], atol=1e-12)
