"""Small synthetic Gaussian scenes: a street for benchmarks and samples, random blobs for tests."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from omniscs.quaternions import yaw_to_quat

#: Street layout, metres (world: x down the street, y left, z up).
STREET_LENGTH = 80.0
STREET_START = 1.0
FACADE_OFFSET = 8.0
FACADE_HEIGHT = 12.0
CAMERA_HEIGHT = 1.6
CAMERA_PITCH_DOWN = math.radians(5.0)
CAMERA_HFOV = math.radians(70.0)
CAR_SIZE = (4.5, 1.8, 1.5)
CARS_PER_SCENE = 16
LANE_OFFSETS = (-2.0, 2.0, -6.0, 6.0)

#: Scale range of benchmark Gaussians (metres) and the thickness of surface-hugging ones.
MIN_SCALE, MAX_SCALE = 0.05, 0.5

#: Fractions of Gaussians on the road, on facades; the rest are on cars.
GROUND_FRACTION, FACADE_FRACTION = 0.45, 0.35


@dataclass(frozen=True)
class StreetScene:
    """Activated Gaussian parameters and C cameras."""

    means: Tensor      # [N, 3] world
    quats: Tensor      # [N, 4] (w, x, y, z)
    scales: Tensor     # [N, 3]
    opacities: Tensor  # [N]
    colors: Tensor     # [N, 3]
    viewmats: Tensor   # [C, 4, 4] cam_from_world
    Ks: Tensor         # [C, 3, 3]
    width: int
    height: int

    def as_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``omniscs.render.rasterize``."""
        return dict(means=self.means, quats=self.quats, scales=self.scales, opacities=self.opacities,
                    colors=self.colors, viewmats=self.viewmats, Ks=self.Ks, width=self.width, height=self.height)


def street_camera(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:  # viewmat [4, 4], K [3, 3]
    """Camera at driving height on the street's centre line, looking down the street, pitched slightly down."""
    forward = np.array([math.cos(CAMERA_PITCH_DOWN), 0.0, -math.sin(CAMERA_PITCH_DOWN)])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(forward, right)
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = np.stack([right, down, forward], 1)
    world_from_cam[:3, 3] = (0.0, 0.0, CAMERA_HEIGHT)
    focal = 0.5 * width / math.tan(0.5 * CAMERA_HFOV)
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return np.linalg.inv(world_from_cam), K


def street_scene(n: int, width: int, height: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> StreetScene:
    """N Gaussians on a road, two facades and cars, seen by one street camera."""
    rng = np.random.default_rng(seed)
    n_ground = int(n * GROUND_FRACTION)
    n_facade = int(n * FACADE_FRACTION)
    n_car = n - n_ground - n_facade
    scales = np.exp(rng.uniform(math.log(MIN_SCALE), math.log(MAX_SCALE), (n, 3)))
    quats = np.zeros((n, 4))
    colors = np.zeros((n, 3))

    ground = np.stack([rng.uniform(STREET_START, STREET_START + STREET_LENGTH, n_ground),
                       rng.uniform(-FACADE_OFFSET, FACADE_OFFSET, n_ground), np.zeros(n_ground)], -1)
    scales[:n_ground, 2] = MIN_SCALE
    quats[:n_ground] = yaw_to_quat(rng.uniform(0, 2 * math.pi, n_ground))
    colors[:n_ground] = 0.35 + 0.1 * rng.standard_normal((n_ground, 1))

    side = rng.choice([-1.0, 1.0], n_facade)
    facade = np.stack([rng.uniform(STREET_START, STREET_START + STREET_LENGTH, n_facade),
                       side * FACADE_OFFSET, rng.uniform(0.0, FACADE_HEIGHT, n_facade)], -1)
    sl = slice(n_ground, n_ground + n_facade)
    scales[sl, 1] = MIN_SCALE
    quats[sl] = yaw_to_quat(rng.uniform(-0.2, 0.2, n_facade))
    building = np.floor(facade[:, 0] / 10.0) + 7 * (side > 0)
    colors[sl] = 0.3 + 0.5 * np.stack([np.sin(building), np.sin(building * 1.7 + 1), np.sin(building * 2.3 + 2)], -1) ** 2

    car_centres = np.stack([rng.uniform(8.0, STREET_START + STREET_LENGTH - 5.0, CARS_PER_SCENE),
                            rng.choice(LANE_OFFSETS, CARS_PER_SCENE), np.full(CARS_PER_SCENE, CAR_SIZE[2] / 2)], -1)
    which = rng.integers(0, CARS_PER_SCENE, n_car)
    face_axis = rng.integers(0, 3, n_car)
    local = rng.uniform(-0.5, 0.5, (n_car, 3))
    local[np.arange(n_car), face_axis] = rng.choice([-0.5, 0.5], n_car)
    cars = car_centres[which] + local * np.array(CAR_SIZE)
    sl = slice(n_ground + n_facade, n)
    quats[sl] = rng.standard_normal((n_car, 4))
    car_colors = rng.uniform(0.05, 0.95, (CARS_PER_SCENE, 3))
    colors[sl] = car_colors[which]

    viewmat, K = street_camera(width, height)
    as32 = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    return StreetScene(
        means=as32(np.concatenate([ground, facade, cars])), quats=as32(quats), scales=as32(scales),
        opacities=as32(rng.uniform(0.2, 1.0, n)), colors=as32(np.clip(colors, 0.0, 1.0)),
        viewmats=as32(viewmat[None]), Ks=as32(K[None]), width=width, height=height,
    )


def random_scene(
    n: int, width: int, height: int, n_cameras: int = 1, seed: int = 0, dtype: torch.dtype = torch.float64,
    depth_range: tuple[float, float] = (2.0, 8.0), scale_range: tuple[float, float] = (0.02, 0.4),
) -> StreetScene:
    """N random anisotropic Gaussians in front of C cameras that differ in pose and intrinsics."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(*depth_range, n)
    half_fov = 0.6
    means = np.stack([rng.uniform(-1.2, 1.2, n) * depth * half_fov, rng.uniform(-1.2, 1.2, n) * depth * half_fov, depth], -1)
    viewmats, Ks = [], []
    for cam in range(n_cameras):
        yaw = 0.15 * cam
        R = np.array([[math.cos(yaw), 0.0, -math.sin(yaw)], [0.0, 1.0, 0.0], [math.sin(yaw), 0.0, math.cos(yaw)]])
        viewmat = np.eye(4)
        viewmat[:3, :3] = R
        viewmat[:3, 3] = (0.1 * cam, -0.05 * cam, 0.2 * cam)
        focal = (0.5 + 0.25 * cam) * width
        viewmats.append(viewmat)
        Ks.append([[focal, 0.0, 0.5 * width + 3.0 * cam], [0.0, focal * (1.0 + 0.1 * cam), 0.5 * height - 2.0 * cam],
                   [0.0, 0.0, 1.0]])
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype)  # noqa: E731
    return StreetScene(
        means=as_t(means), quats=as_t(rng.standard_normal((n, 4))),
        scales=as_t(np.exp(rng.uniform(math.log(scale_range[0]), math.log(scale_range[1]), (n, 3)))),
        opacities=as_t(rng.uniform(0.05, 0.95, n)), colors=as_t(rng.uniform(0.0, 1.0, (n, 3))),
        viewmats=as_t(np.stack(viewmats)), Ks=as_t(np.asarray(Ks)), width=width, height=height,
    )
