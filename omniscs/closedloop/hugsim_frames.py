"""HUGSIM's frames beside ours, written once: what HUGSIM's own driving clients (its UniAD, VAD and NAVSIM-style
clients) read from a state, in the conventions they read it in.

- HUGSIM's world has OpenCV axes (x right, y down, z forward); its clients map a position into the IMU frame
  (x forward, y left, z up: our world's axes) with ``OPENCV2IMU``. So ``ego_pos`` is our world position turned
  by ``OPENCV2IMU``'s transpose, and ``OPENCV2IMU @ ego_pos`` gives our x, y, z back.
- ``ego_rot`` is Euler XYZ in HUGSIM's world; the clients take the ego's yaw as ``-ego_rot[1]``: ``[0, -yaw, 0]``.
- ``cam_params[cam]``:
  - ``intrinsic`` is ``{fovx, fovy, H, W, cx, cy}``, the fields of view in radians of the focal the image was
    rendered with (``fx = W / (2 tan(fovx / 2))``). Our ``fx``, ``fy`` stay beside them.
  - ``l2c`` takes points from the LiDAR frame to the camera's (OpenCV).
  - ``v2c`` takes them from the vehicle (IMU) frame, our ego frame, to the camera's.
- The LiDAR frame is UniAD's planning frame: x right, y forward, z up. Its origin is the planning origin (where a
  plan's waypoints are: ``EGO_SHIFT`` behind the box centre), at a nuScenes LIDAR_TOP's height. A client that
  projects with ``K @ l2c`` and plans in that frame agrees with the server's reading of its plans.
- ``command``: 0 right, 1 left, 2 straight (UniAD's, as ``omniscs.annotate.frames.COMMANDS``)."""
from __future__ import annotations

import math

import numpy as np

#: HUGSIM's clients' map from its world's OpenCV axes (x right, y down, z forward) to the IMU's (x forward, y left,
#: z up).
OPENCV2IMU = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: Height of the LiDAR frame's origin above the ego frame's (a nuScenes LIDAR_TOP's mount), metres.
LIDAR_HEIGHT_M = 1.84
#: ego_from_lidar's rotation: the LiDAR's x (right) is the ego's -y, its y (forward) the ego's x, z up both.
EGO_FROM_LIDAR_AXES = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def hugsim_position(world_xyz) -> list[float]:  # [3] our world (z up) -> [3] HUGSIM's world (OpenCV axes)
    """A world position as HUGSIM's state gives it (``OPENCV2IMU @ result`` is ``world_xyz``)."""
    return [float(v) for v in OPENCV2IMU.T @ np.asarray(world_xyz, dtype=np.float64)]


def hugsim_rotation(yaw: float) -> list[float]:
    """The ego's heading as HUGSIM's ``ego_rot`` (Euler XYZ in its world; its clients read ``-ego_rot[1]``)."""
    return [0.0, -float(yaw), 0.0]


def ego_from_lidar(planning_origin_ahead_m: float) -> np.ndarray:  # -> [4, 4]
    """The LiDAR frame the state's ``l2c`` starts from, in the ego frame: UniAD's planning frame (x right, y forward,
    z up) at the planning origin, ``planning_origin_ahead_m`` ahead of the ego origin, ``LIDAR_HEIGHT_M`` up."""
    T = np.eye(4)
    T[:3, :3] = EGO_FROM_LIDAR_AXES
    T[:3, 3] = [float(planning_origin_ahead_m), 0.0, LIDAR_HEIGHT_M]
    return T


def fov(focal: float, pixels: int) -> float:
    """The field of view (radians) of ``pixels`` at focal length ``focal`` (pixels)."""
    return 2.0 * math.atan(pixels / (2.0 * focal))


def cam_params(K, width: int, height: int, ego_from_camera, ego_from_lidar_frame: np.ndarray) -> dict:
    """One camera's ``cam_params`` entry: HUGSIM's ``intrinsic`` (with our ``fx``, ``fy``), ``l2c``, ``v2c``, and
    our ``K`` and ``ego_from_camera``."""
    K = np.asarray(K, dtype=np.float64)
    camera_from_ego = np.linalg.inv(np.asarray(ego_from_camera, dtype=np.float64))
    return {"intrinsic": {"fovx": fov(K[0, 0], width), "fovy": fov(K[1, 1], height), "H": int(height),
                          "W": int(width), "cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]),
                          "fy": float(K[1, 1])},
            "l2c": (camera_from_ego @ ego_from_lidar_frame).tolist(), "v2c": camera_from_ego.tolist(),
            "K": K.tolist(), "ego_from_camera": np.asarray(ego_from_camera, dtype=np.float64).tolist()}
