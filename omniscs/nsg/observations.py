"""What a fit sees of a scene: camera views, images as float tensors, LiDAR in the world frame, point colours."""
from __future__ import annotations

from dataclasses import dataclass
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from omniscs.geometry import invert_transform, transform_points
from omniscs.scene.store import Scene

#: LiDAR points closer to a camera than this (metres along its axis) are not used to colour or supervise.
MIN_POINT_DEPTH = 0.5


@dataclass(frozen=True)
class View:
    """One camera image to render: where the camera is, its intrinsics and size, and which frame's agent poses."""

    frame_idx: int
    world_from_camera: np.ndarray  # [4, 4] float64, OpenCV camera
    K: np.ndarray                  # [3, 3] float64
    width: int
    height: int
    camera: str | None = None      # its exposure correction; None = none (a camera the fit never saw)

    def downscaled(self, factor: int) -> "View":
        """The same view at 1/factor resolution (pixel-centre convention: K scales by 1/factor)."""
        if factor == 1:
            return self
        K = self.K.copy()
        K[:2] /= factor
        return View(self.frame_idx, self.world_from_camera, K, max(1, self.width // factor),
                    max(1, self.height // factor), self.camera)


def project_points(view: View, points_world: np.ndarray,  # [N, 3]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # uv [N, 2], depth [N], inside [N] bool
    cam = transform_points(invert_transform(view.world_from_camera), points_world)
    z = cam[:, 2]
    safe = np.where(z > MIN_POINT_DEPTH, z, 1.0)
    uv = (cam[:, :2] / safe[:, None]) @ view.K[:2, :2].T + view.K[:2, 2]
    inside = (z > MIN_POINT_DEPTH) & (uv[:, 0] >= 0) & (uv[:, 0] < view.width) & (uv[:, 1] >= 0) \
        & (uv[:, 1] < view.height)
    return uv, z, inside


class Observations:
    """Images (float32 [H, W, 3] in [0, 1], on ``device``: they meet the graph's renders there) and LiDAR
    of a scene's frames, loaded on first use and kept."""

    def __init__(self, scene: Scene, cameras: tuple[str, ...] | list[str] | None = None,
                 device: torch.device | str = "cpu") -> None:
        self.scene = scene
        self.cameras = tuple(cameras or scene.camera_names)
        self.device = torch.device(device)
        self._pixels: dict[tuple[str, int], np.ndarray] = {}
        self._images: dict[tuple[str, int], Tensor] = {}
        self._downscaled: dict[tuple[str, int, int], Tensor] = {}
        self._lidar: dict[int, np.ndarray] = {}
        self._depth_targets: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}

    def view(self, camera: str, frame_idx: int) -> View:
        rec = self.scene.camera(camera)
        return View(int(frame_idx), self.scene.world_from_camera(camera, frame_idx), rec.K.copy(), rec.width,
                    rec.height, camera)

    def pixels(self, camera: str, frame_idx: int) -> np.ndarray:  # [H, W, 3] float32 in [0, 1], host memory
        """The image as numpy, for seeding Gaussians from point colours (host-side work on any device)."""
        key = (camera, int(frame_idx))
        if key not in self._pixels:
            self._pixels[key] = self.scene.image(camera, frame_idx).astype(np.float32) / 255.0
        return self._pixels[key]

    def image(self, camera: str, frame_idx: int, factor: int = 1) -> Tensor:  # [H/factor, W/factor, 3] on device
        key = (camera, int(frame_idx))
        if key not in self._images:
            self._images[key] = torch.from_numpy(self.pixels(camera, frame_idx)).to(self.device)
        full = self._images[key]
        if factor == 1:
            return full
        small_key = (camera, int(frame_idx), factor)
        if small_key not in self._downscaled:
            h, w = full.shape[0] // factor, full.shape[1] // factor
            small = F.interpolate(full.permute(2, 0, 1)[None], size=(h, w), mode="area")[0].permute(1, 2, 0)
            self._downscaled[small_key] = small.contiguous()
        return self._downscaled[small_key]

    def lidar_world(self, frame_idx: int) -> np.ndarray:  # [N, 3] float64 world frame
        if frame_idx not in self._lidar:
            if not self.scene.has_lidar:
                self._lidar[frame_idx] = np.zeros((0, 3))
            else:
                pts = self.scene.lidar(frame_idx)[:, :3].astype(np.float64)
                self._lidar[frame_idx] = transform_points(self.scene.world_from_ego(frame_idx), pts)
        return self._lidar[frame_idx]

    def lidar_depth_targets(self, camera: str, frame_idx: int) -> tuple[np.ndarray, np.ndarray]:
        """LiDAR returns of ``frame_idx`` seen by ``camera``: full-resolution pixels uv [M, 2] and depths [M]."""
        key = (camera, int(frame_idx))
        if key not in self._depth_targets:
            uv, z, inside = project_points(self.view(camera, frame_idx), self.lidar_world(frame_idx))
            self._depth_targets[key] = (uv[inside], z[inside])
        return self._depth_targets[key]

    def colour_points(self, points_world: np.ndarray,  # [N, 3]
                      frame_ids: np.ndarray,           # [N] frame each point was captured in
                      ) -> tuple[np.ndarray, np.ndarray]:  # colours [N, 3] in [0, 1], seen [N] bool
        """Colour of each point in the first camera of its own frame that sees it (nearest pixel)."""
        colours = np.full((len(points_world), 3), 0.5)
        seen = np.zeros(len(points_world), dtype=bool)
        for f in np.unique(frame_ids):
            idx = np.flatnonzero(frame_ids == f)
            for cam in self.cameras:
                todo = idx[~seen[idx]]
                if len(todo) == 0:
                    break
                view = self.view(cam, int(f))
                uv, _, inside = project_points(view, points_world[todo])
                hit = todo[inside]
                px = np.floor(uv[inside]).astype(np.int64)
                img = self.pixels(cam, int(f))
                colours[hit] = img[px[:, 1], px[:, 0]]
                seen[hit] = True
        return colours, seen
