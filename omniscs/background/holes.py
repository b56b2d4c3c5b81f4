"""Holes: what a removed or moved object hid, in each training view (pixels) and in the world (its RoI box).

The image hole of a view is the set of pixels whose ray passes through the object's box at its logged pose
(ray-box slab test per pixel: exact for boxes cut by the image border or reaching behind the camera), dilated
by a few pixels so the object's blurred silhouette and shadow-free rim are refilled too. The 3D region is the
box enlarged by a fixed factor (the RoI of the paper's RoI-guided background training): background Gaussians
inside it are re-optimised, the rest stay fixed.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform
from omniscs.nsg.observations import View

#: Pixels added around the projected box of a removed object (at full resolution).
HOLE_DILATION_PX = 4

#: Length and width of the RoI box are the object's times this; its height too, and it reaches down to the ground.
ROI_SCALE = 1.5

#: The RoI box also grows by this many metres on every side (small objects still get a margin).
ROI_MARGIN_M = 1.0


@dataclass(frozen=True)
class RemovedObject:
    """A large static object whose footprint is repaired: its box at each logged frame."""

    track_id: int
    size: np.ndarray             # [3] length, width, height (m)
    world_from_box: np.ndarray   # [F, 4, 4] float64 logged poses (box centre, +x heading)
    present: np.ndarray          # [F] bool

    def __post_init__(self) -> None:
        size = np.asarray(self.size, dtype=np.float64)
        if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise OmniscsError(f"track {self.track_id}: a box size must be 3 positive numbers; got {self.size!r}")
        poses = np.asarray(self.world_from_box, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.all(np.isfinite(poses)):
            raise OmniscsError(f"track {self.track_id}: poses must be finite [F, 4, 4] transforms")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "world_from_box", poses)
        object.__setattr__(self, "present", np.asarray(self.present, dtype=bool))

    @classmethod
    def from_node(cls, node) -> "RemovedObject":
        """The object as the scene graph's agent node models it (its box and per-frame poses)."""
        return cls(int(node.track_id), np.array(node.size), np.array(node.world_from_agent), np.array(node.present))

    def pose(self, frame_idx: int) -> np.ndarray:
        return self.world_from_box[int(frame_idx)]

    def roi(self, frame_idx: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The RoI box (world_from_box [4, 4], size [3]): the box grown by ROI_SCALE and ROI_MARGIN_M, at its
        first present frame (a static object's pose) unless ``frame_idx`` is given."""
        if frame_idx is None:
            present = np.flatnonzero(self.present)
            if len(present) == 0:
                raise OmniscsError(f"track {self.track_id} is present in no frame: there is nothing to repair")
            frame_idx = int(present[0])
        return self.pose(frame_idx), roi_size(self.size)


def roi_size(size: np.ndarray) -> np.ndarray:
    return np.asarray(size, dtype=np.float64) * ROI_SCALE + 2.0 * ROI_MARGIN_M


def pixel_rays(view: View) -> np.ndarray:  # [H, W, 3] float64 world-frame directions with camera z = 1
    u, v = np.meshgrid(np.arange(view.width) + 0.5, np.arange(view.height) + 0.5)
    K = view.K
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return d @ view.world_from_camera[:3, :3].T


def lift_pixels(view: View, which: np.ndarray, distance: np.ndarray) -> np.ndarray:  # -> [N, 3] world
    """The world points of the ``which`` pixels [H, W] bool of ``view`` at ``distance`` [H, W] (metres from the
    camera centre along each pixel's ray)."""
    rays = pixel_rays(view)[which]
    dirs = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return view.world_from_camera[:3, 3] + dirs * np.asarray(distance)[which][:, None].astype(np.float64)


def box_entry_distance(view: View, world_from_box: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Per pixel, the z-depth at which the pixel's ray enters the box (inf where it misses; 0 from inside)."""
    rays = pixel_rays(view).reshape(-1, 3)
    box_from_world = invert_transform(np.asarray(world_from_box, dtype=np.float64))
    o = box_from_world[:3, :3] @ view.world_from_camera[:3, 3] + box_from_world[:3, 3]
    d = rays @ box_from_world[:3, :3].T
    half = 0.5 * np.asarray(size, dtype=np.float64)
    tiny = 1e-12
    d_safe = np.where(np.abs(d) < tiny, np.where(d < 0, -tiny, tiny), d)
    t1, t2 = (-half - o) / d_safe, (half - o) / d_safe
    t_near = np.minimum(t1, t2).max(axis=1)
    t_far = np.maximum(t1, t2).min(axis=1)
    hit = (t_far >= np.maximum(t_near, 0.0)) & np.isfinite(t_far)
    return np.where(hit, np.maximum(t_near, 0.0), np.inf).reshape(view.height, view.width)


def hole_mask(view: View, objects: list[RemovedObject], dilation_px: int = HOLE_DILATION_PX) -> np.ndarray:
    """[H, W] bool: pixels of ``view`` (at its own resolution) that see any of ``objects`` at the view's frame,
    dilated by ``dilation_px`` (scaled down with the view: ``dilation_px`` is at full resolution of a view
    ``downscaled`` from it only if the caller scales it)."""
    mask = np.zeros((view.height, view.width), dtype=bool)
    for obj in objects:
        if not obj.present[view.frame_idx]:
            continue
        mask |= np.isfinite(box_entry_distance(view, obj.pose(view.frame_idx), obj.size))
    return dilate(mask, dilation_px)


def dilate(mask: np.ndarray, pixels: int) -> np.ndarray:
    """``mask`` grown by a disc of ``pixels`` radius."""
    if pixels <= 0 or not mask.any():
        return mask
    k = 2 * int(pixels) + 1
    return cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0


def ray_norms(view: View) -> np.ndarray:  # [H, W]: distance from the camera centre per metre of z-depth
    return np.linalg.norm(pixel_rays(view), axis=-1)


def hole_bbox(mask: np.ndarray, margin: int) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) of the mask's pixels grown by ``margin`` and clipped to the image; None for an empty mask."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    h, w = mask.shape
    return (max(0, int(xs.min()) - margin), max(0, int(ys.min()) - margin),
            min(w, int(xs.max()) + 1 + margin), min(h, int(ys.max()) + 1 + margin))


def crop_view(view: View, box: tuple[int, int, int, int]) -> View:
    """The sub-image (x0, y0, x1, y1) of ``view`` as a view of its own (the principal point moves)."""
    x0, y0, x1, y1 = box
    if not (0 <= x0 < x1 <= view.width and 0 <= y0 < y1 <= view.height):
        raise OmniscsError(f"crop {box} is not inside a {view.width}x{view.height} view")
    K = view.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return View(view.frame_idx, view.world_from_camera, K, x1 - x0, y1 - y0, view.camera)
