"""What HUGSIM's own driving clients read from a state, read here as they read it (their reads and their maths,
written for this test from their published client code, not their models), from a server started by
``omniscs closedloop serve`` and driven by ``hugsim-client``:
- the UniAD client (``parse_raw``: images resized to 1600x900 with the focal doubled, ``lidar2img`` from
  ``intrinsic`` and ``l2c``, can_bus from ``ego_pos`` / ``ego_rot``, ``l2g`` in its LiDAR-global axes, the command);
- the VAD client (the same images and ``lidar2img``, can_bus with the ego's z, the ego's past displacements from a
  history of ``ego_pos``, a one-hot future command);
- the NAVSIM (LTF) client (cameras from ``intrinsic`` and ``l2c``, the ego status, a one-hot command);
- HUGSIM's own foreground-collision check over ``ego_box`` and ``obj_boxes``.
The server renders at 800x450, the size for which the UniAD and VAD clients' resize to 1600x900 and doubled focal
agree (docs/guide/closedloop.md)."""
from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapely.geometry import Polygon

from omniscs.scs.behavior.collision import footprints

#: The server runs as its own process and serves two episodes at 800 px: in `make test-slow` (make test's five minutes).
pytestmark = pytest.mark.slow

CAMERA = "CAM_FRONT"
#: The UniAD and VAD clients resize every image to this size and double the focal: a server for them renders at half.
CLIENT_SIZE = (1600, 900)
RENDER_WIDTH = 800
#: HUGSIM's clients' maps from its world's OpenCV axes to the IMU's and to their LiDAR-global axes (their constants).
OPENCV2IMU = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=np.float64)
OPENCV2LIDAR = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64)


def focal(fov: float, pixels: int) -> float:
    return pixels / (2 * math.tan(fov / 2))


def intrinsic_matrix(d: dict) -> np.ndarray:  # [4, 4], as their get_intrinsic builds it
    K = np.eye(4)
    K[0, 0], K[1, 1] = focal(d["fovx"], d["W"]), focal(d["fovy"], d["H"])
    K[0, 2], K[1, 2] = d["cx"], d["cy"]
    return K


def doubled(K: np.ndarray) -> np.ndarray:  # their "training gs downsample 2x, recover scale"
    K = K.copy()
    K[0, 0], K[0, 2], K[1, 1], K[1, 2] = 2 * K[0, 0], 2 * K[0, 2], 2 * K[1, 1], 2 * K[1, 2]
    return K


def lidar_to_image(info: dict, camera: str) -> np.ndarray:  # [4, 4], their rescale_K @ l2c
    params = info["cam_params"][camera]
    return doubled(intrinsic_matrix(params["intrinsic"])) @ np.asarray(params["l2c"])


def euler_xyz(angles) -> np.ndarray:  # [3, 3], their SCR.from_euler('XYZ', angles).as_matrix()
    return Rotation.from_euler("XYZ", angles).as_matrix()


def uniad_reads(obs: dict, info: dict, cameras: list[str]) -> dict:
    """The UniAD client's parse of a state."""
    imu_yaw, lidar_yaw = -info["ego_rot"][1], info["ego_rot"][1]
    images = {c: cv2.resize(obs["rgb"][c], CLIENT_SIZE) for c in cameras}
    lidar2img = {c: lidar_to_image(info, c) for c in cameras}
    ego_pos = np.asarray(info["ego_pos"], dtype=np.float64)
    can_bus = np.zeros(18)
    can_bus[:3] = OPENCV2IMU @ ego_pos
    can_bus[2] = 0.0
    can_bus[3:7] = Rotation.from_euler("XYZ", [0, 0, imu_yaw]).as_quat()[[3, 0, 1, 2]]
    can_bus[10:13] = [0.0, 0.0, -info["steer_rate"]]
    can_bus[13:16] = [info["ego_velo"], 0.0, 0.0]
    yaw = imu_yaw + 2 * np.pi if imu_yaw < 0 else imu_yaw
    can_bus[-2], can_bus[-1] = yaw, yaw / np.pi * 180
    return {"images": images, "lidar2img": lidar2img, "can_bus": can_bus,
            "l2g_r_mat": euler_xyz([0, 0, lidar_yaw]), "l2g_t": OPENCV2LIDAR @ ego_pos,
            "timestamp": info["timestamp"], "command": info["command"]}


def vad_reads(obs: dict, info: dict, cameras: list[str], history: list) -> dict:
    """The VAD client's parse of a state; ``history`` is its queue of past positions (it keeps the last 3)."""
    imu_yaw = -info["ego_rot"][1]
    lidar2img = {c: lidar_to_image(info, c) for c in cameras}
    v2w = np.eye(4)
    v2w[:3, :3] = euler_xyz([0, 0, imu_yaw])
    v2w[:3, 3] = OPENCV2IMU @ np.asarray(info["ego_pos"], dtype=np.float64)
    history.append(v2w[:3, 3].copy())
    while len(history) < 3:
        history.append(v2w[:3, 3].copy())
    del history[:-3]
    past = (np.stack(history) - v2w[:3, 3]) @ v2w[:3, :3].T      # their np.dot(v2w[:3, :3], past.T).T
    steps = (past[1:, :2] - past[:-1, :2])[:, [1, 0]]
    can_bus = np.zeros(18)
    can_bus[:3] = v2w[:3, 3]
    can_bus[3:7] = Rotation.from_euler("XYZ", [0, 0, imu_yaw]).as_quat()[[3, 0, 1, 2]]
    can_bus[10:13] = [0.0, 0.0, -info["steer_rate"]]
    can_bus[13:16] = [info["ego_velo"], 0.0, 0.0]
    yaw = imu_yaw + 2 * np.pi if imu_yaw < 0 else imu_yaw
    can_bus[-2], can_bus[-1] = yaw, yaw / np.pi * 180
    cmd = [0, 0, 0]
    cmd[info["command"]] = 1
    return {"images": {c: cv2.resize(obs["rgb"][c], CLIENT_SIZE) for c in cameras}, "lidar2img": lidar2img,
            "v2w": v2w, "can_bus": can_bus, "ego_his_trajs": steps, "ego_fut_cmd": cmd}


def navsim_reads(obs: dict, info: dict, cameras: list[str]) -> dict:
    """The NAVSIM (LTF) client's parse: per camera K and sensor-to-LiDAR pose, the ego status."""
    cams = {}
    for c in cameras:
        l2c = np.asarray(info["cam_params"][c]["l2c"], dtype=np.float64)
        c2l = np.linalg.inv(l2c)
        cams[c] = {"image": cv2.resize(obs["rgb"][c], (1920, 1080)),
                   "K": intrinsic_matrix(info["cam_params"][c]["intrinsic"]),
                   "sensor2lidar_rotation": c2l[:3, :3], "sensor2lidar_translation": c2l[:3, 3]}
    command = np.zeros(4)
    command[info["command"]] = 1
    return {"cameras": cams, "ego_pose": OPENCV2IMU @ np.asarray(info["ego_pos"], dtype=np.float64),
            "steer": info["ego_steer"], "velocity": info["ego_velo"], "accel": info["accelerate"], "command": command}


def hugsim_rectangle(x: float, y: float, width: float, length: float, yaw: float) -> Polygon:
    """HUGSIM's create_rectangle: length along the heading, width across it, centred at (x, y)."""
    c, s = math.cos(yaw), math.sin(yaw)
    offsets = [(length / 2, width / 2), (length / 2, -width / 2), (-length / 2, -width / 2), (-length / 2, width / 2)]
    return Polygon([(x + dx * c - dy * s, y + dx * s + dy * c) for dx, dy in offsets])


def hugsim_foreground_collision(ego_box, obj_boxes) -> bool:
    """HUGSIM's fg_collision_det over the state's ego_box and obj_boxes ([x, y, z, w, l, h, yaw] each)."""
    ego_x, ego_y, _, ego_w, ego_l, _, ego_yaw = ego_box
    ego = hugsim_rectangle(ego_x, ego_y, ego_w, ego_l, ego_yaw)
    return any(ego.intersects(hugsim_rectangle(x, y, w, l, yaw)) for x, y, _, w, l, _, yaw in obj_boxes)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def states(world, workspace):
    """Every state a client saw in two episodes of the stopping variant, served by ``omniscs closedloop serve`` (a
    separate process) and driven by hugsim-client: {"turning": veering left for 1.1 s, "straight": from reset to
    the collision with the car that stops ahead}, each [(obs, info), ...]."""
    os.environ["IN_HF_SPACE"] = "false"  # else the client starts a web server of its own
    from hugsim_client import HugsimClient

    scene, ws = world[0], workspace
    port = _free_port()
    env = dict(os.environ, OMNISCS_SERVER_TOKENS="tok", OMNISCS_HOME=str(ws))
    server = subprocess.Popen(
        [sys.executable, "-c", "import sys; from omniscs.cli import main; sys.argv[0] = 'omniscs'; main()",
         "closedloop", "serve", "--scenario", f"{scene.scene_id}/stop", "--port", str(port), "--camera", CAMERA,
         "--width", str(RENDER_WIDTH)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=1):
                    break
            except OSError:
                if server.poll() is not None or time.monotonic() > deadline:
                    server.kill()
                    pytest.fail(f"omniscs closedloop serve did not start: {server.communicate()[0][-2000:]}")
                time.sleep(0.2)
        client = HugsimClient(host=f"http://127.0.0.1:{port}", api_token="tok")
        seen = {}
        # an episode that veers left (the yaw grows: a sign error in ego_rot shows) and one straight into the car
        for name, plan, steps in (("turning", [[-0.15 * k * k, 2.5 * k] for k in range(1, 7)], 12),
                                  ("straight", [[0.0, 3.0 * k] for k in range(1, 7)], 80)):
            client.reset_env()
            got = client.get_current_state()
            seen[name] = [(got.state.obs, got.state.info)]
            while not got.done and len(seen[name]) < steps:
                got = client.execute_action(np.array(plan, np.float32))
                seen[name].append((got.state.obs, got.state.info))
    finally:
        server.terminate()
        server.wait(timeout=30)
    return seen


def test_every_client_finds_every_key_it_reads(states):
    obs, info = states["straight"][1]
    uniad = uniad_reads(obs, info, [CAMERA])
    vad = vad_reads(obs, info, [CAMERA], [])
    navsim = navsim_reads(obs, info, [CAMERA])
    assert obs["rgb"][CAMERA].dtype == np.uint8 and obs["rgb"][CAMERA].shape == (450, 800, 3)
    assert uniad["images"][CAMERA].shape == vad["images"][CAMERA].shape == (900, 1600, 3)
    assert navsim["cameras"][CAMERA]["image"].shape == (1080, 1920, 3)
    assert sum(vad["ego_fut_cmd"]) == 1 and navsim["command"].sum() == 1 and uniad["command"] in (0, 1, 2)
    for value in (info["ego_velo"], info["accelerate"], info["steer_rate"], info["timestamp"], info["ego_steer"]):
        assert math.isfinite(value)
    assert np.isfinite(uniad["can_bus"]).all() and np.isfinite(vad["can_bus"]).all()
    assert info["timestamp"] > 0  # a step was driven
    assert len(info["ego_box"]) == 7 and all(len(b) == 7 for b in info["obj_boxes"]) and info["obj_boxes"]


def test_the_focal_they_derive_is_the_one_the_image_was_rendered_with(states):
    obs, info = states["straight"][0]
    K = np.asarray(info["cam_params"][CAMERA]["K"])
    d = info["cam_params"][CAMERA]["intrinsic"]
    assert (d["W"], d["H"]) == (obs["rgb"][CAMERA].shape[1], obs["rgb"][CAMERA].shape[0])
    np.testing.assert_allclose(intrinsic_matrix(d)[:3, :3], K, atol=1e-9)
    # the UniAD / VAD clients' 1600x900 image is exactly twice the rendered one, so their doubled focal is right
    assert (2 * d["W"], 2 * d["H"]) == CLIENT_SIZE


def test_their_ego_pose_and_yaw_are_the_egos(states):
    turned = states["turning"][-1][1]["ego_yaw"]
    assert 0.05 < turned < 1.0, turned  # the episode veered left
    for obs, info in states["turning"] + states["straight"][-1:]:
        T = np.asarray(info["world_from_ego"])
        uniad, vad = uniad_reads(obs, info, [CAMERA]), vad_reads(obs, info, [CAMERA], [])
        np.testing.assert_allclose(vad["v2w"], T, atol=1e-9)
        np.testing.assert_allclose(vad["can_bus"][:3], info["ego_xyz"], atol=1e-9)
        np.testing.assert_allclose(uniad["can_bus"][:2], info["ego_xyz"][:2], atol=1e-9)
        assert math.isclose(uniad["can_bus"][-2], info["ego_yaw"] % (2 * math.pi), abs_tol=1e-9)
        w, x, y, z = uniad["can_bus"][3:7]
        np.testing.assert_allclose(Rotation.from_quat([x, y, z, w]).as_matrix(), T[:3, :3], atol=1e-9)
        np.testing.assert_allclose(navsim_reads(obs, info, [CAMERA])["ego_pose"], info["ego_xyz"], atol=1e-9)


def test_vads_history_holds_the_egos_last_displacements(states):
    history, moved = [], []
    seen = states["turning"][-4:]
    for obs, info in seen:
        vad = vad_reads(obs, info, [CAMERA], history)
        moved.append(np.linalg.norm(vad["ego_his_trajs"], axis=-1))
    xyz = np.array([info["ego_xyz"] for _, info in seen])
    travelled = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=-1)   # metres per step
    np.testing.assert_allclose(moved[3], travelled[1:3], atol=1e-9)     # the two steps before the fourth state
    np.testing.assert_allclose(moved[0], [0.0, 0.0], atol=1e-12)        # a fresh queue is padded with the present
    assert abs(seen[-1][1]["ego_yaw"]) > 0.05                           # ... while turning
    assert travelled.min() > 0.1                                         # the ego really moved


def test_their_lidar2img_puts_a_box_centre_where_the_renderer_drew_it(states):
    """The box centre of each agent drawn whole in the image, taken into the LiDAR frame from what the client
    reads (its pose from ego_pos/ego_rot, the LiDAR in the ego frame from v2c and l2c), lands through their
    lidar2img, on their 1600x900 image, at twice the pixel our camera model projects it to (1e-6 px), and inside
    the outline of that agent's rendered pixels (their convex hull, within 1 px: a graph fitted at thumbnail size
    leaves gaps between an agent's Gaussians at 800x450)."""
    checked = 0
    for obs, info in states["straight"][:6] + states["turning"][:6]:
        vad = vad_reads(obs, info, [CAMERA], [])
        instance = obs["instance"][CAMERA]
        h, w = instance.shape
        cp = info["cam_params"][CAMERA]
        ego_from_lidar = np.linalg.inv(np.asarray(cp["v2c"])) @ np.asarray(cp["l2c"])
        lidar_from_world = np.linalg.inv(vad["v2w"] @ ego_from_lidar)
        camera_from_world = np.linalg.inv(np.asarray(info["world_from_ego"]) @ np.asarray(cp["ego_from_camera"]))
        for box in info["boxes"]:
            ys, xs = np.nonzero(instance == box["track_id"])
            if len(xs) < 50 or xs.min() == 0 or ys.min() == 0 or xs.max() == w - 1 or ys.max() == h - 1:
                continue  # not in view, or cut by the image's edge (its centre may lie outside the image)
            centre = np.array([*box["center"], 1.0])
            uvw = vad["lidar2img"][CAMERA] @ (lidar_from_world @ centre)
            assert uvw[2] > 0
            u, v = uvw[0] / uvw[2] / 2, uvw[1] / uvw[2] / 2   # their 1600x900 pixels -> the rendered image's
            ours = np.asarray(cp["K"]) @ (camera_from_world @ centre)[:3]
            np.testing.assert_allclose([u, v], ours[:2] / ours[2], atol=1e-6)
            hull = cv2.convexHull(np.stack([xs, ys], -1).astype(np.float32) + 0.5)
            assert cv2.pointPolygonTest(hull, (float(u), float(v)), True) >= -1.0, (box["track_id"], u, v)
            checked += 1
    assert checked >= 3, "too few agents drawn whole in the image"
    # and the planning frame is the LiDAR frame: its y axis is the ego's heading, x to the right
    np.testing.assert_allclose(ego_from_lidar[:3, :3] @ [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(ego_from_lidar[:3, :3] @ [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], atol=1e-12)


def test_uniads_lidar_to_global_puts_lidar_points_where_the_world_has_them(states):
    """UniAD applies l2g to row vectors (``p @ l2g_r_mat + l2g_t``) in its LiDAR-global axes (OPENCV2LIDAR of
    HUGSIM's world): a point of the LiDAR frame lands where world_from_ego @ ego_from_lidar puts it."""
    global_from_world = OPENCV2LIDAR @ OPENCV2IMU.T
    points = np.array([[0.0, 0.0, 0.0], [1.5, 10.0, 0.3], [-4.0, 25.0, -1.0]])   # x right, y ahead, z up
    for obs, info in states["turning"] + states["straight"][-1:]:
        uniad = uniad_reads(obs, info, [CAMERA])
        cp = info["cam_params"][CAMERA]
        ego_from_lidar = np.linalg.inv(np.asarray(cp["v2c"])) @ np.asarray(cp["l2c"])
        world_from_lidar = np.asarray(info["world_from_ego"]) @ ego_from_lidar
        want = (world_from_lidar[:3, :3] @ points.T).T + world_from_lidar[:3, 3]
        got = points @ uniad["l2g_r_mat"] + uniad["l2g_t"]
        # the ego position is the ego frame's origin, the LiDAR's is above and ahead of it: compare displacements
        np.testing.assert_allclose((got - got[0]) @ global_from_world, want - want[0], atol=1e-9)


def test_hugsims_own_collision_check_on_ego_box_and_obj_boxes_agrees_with_the_servers(states):
    first, last = states["straight"][0][1], states["straight"][-1][1]
    assert last["collision"] and last["collided_with"] == [1]       # the replay ran into the car that stopped
    assert hugsim_foreground_collision(last["ego_box"], last["obj_boxes"])
    assert not first["collision"] and not hugsim_foreground_collision(first["ego_box"], first["obj_boxes"])
    # their rectangles are our footprints: obj_boxes and ego_box are [x, y, z, w, l, h, yaw] of box centres
    for box, row in zip(last["boxes"], last["obj_boxes"]):
        ours = footprints(np.array([box["center"][:2]]), np.array([box["yaw"]]), box["size"][0], box["size"][1])[0]
        theirs = np.asarray(hugsim_rectangle(row[0], row[1], row[3], row[4], row[6]).exterior.coords)[:4]
        assert Polygon(ours).symmetric_difference(Polygon(theirs)).area < 1e-9
    x, y, _, w, l, _, yaw = last["ego_box"]
    assert math.isclose(yaw, last["ego_yaw"], abs_tol=1e-12) and l > w > 0
    ahead = np.subtract([x, y], last["ego_xyz"][:2]) @ [math.cos(yaw), math.sin(yaw)]
    assert 0.0 <= ahead < l / 2  # the box centre, ahead of the ego frame's origin (the rear axle) along the heading
