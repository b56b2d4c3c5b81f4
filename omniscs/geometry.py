"""Rigid-body geometry in float64: rotations, SE(3), boxes, pinhole cameras (quaternions: omniscs.quaternions).

Conventions (DESIGN.md): world z up; agent frame x forward, y left, z up; cameras OpenCV
(x right, y down, z forward); transforms are 4x4 float64 named ``a_from_b``.
"""
from __future__ import annotations

import numpy as np

#: Points closer to the camera than this (metres along +z) do not project.
DEFAULT_NEAR = 0.01


# ----------------------------------------------------------------------------- rotations
def rotmat_from_euler(roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll): roll about the agent's x (forward), then pitch, then yaw."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def euler_from_rotmat(R: np.ndarray) -> tuple[float, float, float]:  # [3, 3] -> (roll, pitch, yaw) rad
    """The inverse of ``rotmat_from_euler``: pitch in [-pi/2, pi/2]; at pitch +-pi/2 (gimbal lock) roll is 0 and
    yaw carries the whole turn about z."""
    R = np.asarray(R, dtype=np.float64)
    pitch = float(np.arctan2(-R[2, 0], np.hypot(R[2, 1], R[2, 2])))
    if np.hypot(R[2, 1], R[2, 2]) < 1e-12:
        return 0.0, pitch, float(np.arctan2(-R[0, 1], R[1, 1]))
    return float(np.arctan2(R[2, 1], R[2, 2])), pitch, float(np.arctan2(R[1, 0], R[0, 0]))


def yaw_from_matrix(R: np.ndarray) -> np.ndarray:  # [..., 3, 3] (or the rotation block of a pose) -> [...] rad
    """Heading of the rotated x axis in the xy plane (``quaternions.yaw_from_quaternion`` for quaternions)."""
    R = np.asarray(R, dtype=np.float64)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angle in [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


# ----------------------------------------------------------------------------- SE(3)
def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:  # [..., 3, 3], [..., 3] -> [..., 4, 4]
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose_from_xyz_yaw(x: float, y: float, z: float, yaw: float) -> np.ndarray:  # -> [4, 4]
    return make_transform(rotmat_from_euler(yaw=yaw), [x, y, z])


def invert_transform(T: np.ndarray) -> np.ndarray:  # [..., 4, 4] rigid -> [..., 4, 4]
    """Exact inverse of a rigid transform (transpose of R, not a general matrix inverse)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return make_transform(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def compose(*transforms: np.ndarray) -> np.ndarray:
    """compose(a_from_b, b_from_c, ...) -> a_from_(last). The one place transforms are chained."""
    out = np.asarray(transforms[0], dtype=np.float64)
    for T in transforms[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(a_from_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:  # [4,4], [N,3] -> [N,3]
    a_from_b = np.asarray(a_from_b, dtype=np.float64)
    points_b = np.asarray(points_b, dtype=np.float64)
    return points_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def is_rigid(T: np.ndarray, tol: float = 1e-6) -> bool:
    """True when T is a finite 4x4 with an orthonormal, right-handed rotation and last row 0 0 0 1."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (
        np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
        and np.allclose(T[3], [0, 0, 0, 1], atol=tol)
    )


# ----------------------------------------------------------------------------- boxes
_UNIT_CORNERS = np.array(
    [[sx, sy, sz] for sx in (0.5, -0.5) for sy in (0.5, -0.5) for sz in (0.5, -0.5)], dtype=np.float64
)  # [8, 3]: front-left-top first; first four corners are the front face (+x)


def world_from_box(center: np.ndarray, yaw: float, rotation: np.ndarray | None = None) -> np.ndarray:
    """Pose of a box frame; ``rotation`` (3x3) overrides yaw for full 3D orientation (e.g. overturned)."""
    R = rotmat_from_euler(yaw=yaw) if rotation is None else np.asarray(rotation, dtype=np.float64)
    return make_transform(R, center)


def box_corners(center: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:  # -> [8, 3]
    """Corners of a box (centre, (length, width, height), yaw); the first four lie on the front face."""
    return transform_points(world_from_box(center, yaw), _UNIT_CORNERS * np.asarray(size, dtype=np.float64))


def box_corners_from_pose(world_from_box: np.ndarray, size: np.ndarray) -> np.ndarray:  # [4,4],[3] -> [8,3]
    """Corners of a box in any orientation (e.g. overturned); same order as ``box_corners``."""
    return transform_points(world_from_box, _UNIT_CORNERS * np.asarray(size, dtype=np.float64))


#: The 12 edges of a box as pairs of indices into the corner order of ``box_corners``.
BOX_EDGES = ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7))


def clip_segment_to_near(a: np.ndarray, b: np.ndarray, near: float = DEFAULT_NEAR
                         ) -> tuple[np.ndarray, np.ndarray] | None:
    """Clip a camera-frame segment to z >= near; None when it lies wholly behind the plane."""
    za, zb = a[2], b[2]
    if za < near and zb < near:
        return None
    if za >= near and zb >= near:
        return a, b
    t = (near - za) / (zb - za)
    cut = a + t * (b - a)
    return (cut, b) if za < near else (a, cut)


def points_in_box(points: np.ndarray,         # [N, 3+] in some frame (columns past xyz are ignored)
                  frame_from_box: np.ndarray,  # [4, 4] the box's pose in that frame
                  size: np.ndarray,            # [3] length, width, height
                  margin: float = 0.0,         # metres added on every side
                  ) -> np.ndarray:             # -> [N] bool
    """Which points lie in the box (its faces included), grown by ``margin`` on every side."""
    local = transform_points(invert_transform(frame_from_box), np.asarray(points, dtype=np.float64)[:, :3])
    half = 0.5 * np.asarray(size, dtype=np.float64) + margin
    return np.all(np.abs(local) <= half, axis=-1)


# ----------------------------------------------------------------------------- cameras
def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:  # -> [3, 3]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def intrinsics_from_fov(width: int, height: int, hfov_rad: float) -> np.ndarray:  # -> [3, 3]
    f = 0.5 * width / np.tan(0.5 * hfov_rad)
    return intrinsics_matrix(f, f, 0.5 * width, 0.5 * height)


def project(points_cam: np.ndarray, K: np.ndarray, near: float = DEFAULT_NEAR
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinhole projection of camera-frame points.

    points_cam [N, 3] (OpenCV camera), K [3, 3] -> uv [N, 2] pixels, depth [N] (z), in_front [N] bool.
    Points at or behind ``near`` get ``in_front`` False and finite uv (their uv carries no meaning).
    """
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = p[:, 2]
    in_front = z > near
    safe_z = np.where(in_front, z, 1.0)
    uv = (p[:, :2] / safe_z[:, None]) @ np.asarray(K)[:2, :2].T + np.asarray(K)[:2, 2]
    uv = np.where(in_front[:, None], uv, 0.0)
    return uv, z.copy(), in_front


def unproject(uv: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:  # [N,2],[N] -> [N,3]
    """Camera-frame points at z-depth ``depth`` along the rays through pixels ``uv``."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    K = np.asarray(K, dtype=np.float64)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0]
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    return np.stack([x * depth, y * depth, depth], -1)


def spinning_beam_directions(beams: int, min_elevation_deg: float, max_elevation_deg: float,
                             azimuth_steps: int) -> np.ndarray:  # -> [beams * azimuth_steps, 3] unit, sensor frame
    """Unit ray directions of a spinning LiDAR (x forward, y left, z up), beam-major: row = elevation from the top
    beam to the bottom one (evenly spaced, both limits included), column = azimuth from -pi, evenly over 360°."""
    elevation = np.radians(np.linspace(max_elevation_deg, min_elevation_deg, beams))
    azimuth = np.linspace(-np.pi, np.pi, azimuth_steps, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)


def in_image(uv: np.ndarray, width: int, height: int) -> np.ndarray:  # [N, 2] -> [N] bool
    return (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)


#: camera_from_rig for an OpenCV camera mounted looking along the rig's +x (x forward, y left, z up).
CAMERA_FROM_FORWARD_RIG = np.array(
    [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def ego_from_camera_mount(x: float, y: float, z: float, yaw: float, pitch: float = 0.0) -> np.ndarray:
    """ego_from_camera for a camera at (x, y, z) in the ego frame, looking along heading ``yaw``
    (0 = forward), tilted down by ``pitch`` radians."""
    ego_from_rig = make_transform(rotmat_from_euler(pitch=pitch, yaw=yaw), [x, y, z])
    return compose(ego_from_rig, invert_transform(CAMERA_FROM_FORWARD_RIG))
