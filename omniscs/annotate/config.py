"""How variants are rendered and annotated (one frozen config; its fields are part of the annotate stage's key)."""
from __future__ import annotations

from dataclasses import asdict, dataclass

from omniscs.errors import OmniscsError

#: nuScenes' four visibility levels: lower bounds of the visible fraction of v40-60, v60-80, v80-100 (v0-40 below).
VISIBILITY_BOUNDS = (0.4, 0.6, 0.8)


@dataclass(frozen=True)
class AnnotateConfig:
    """Render and ground-truth settings of the render + annotate stage."""

    frame_every: int = 1
    """Render every Nth frame of a variant's steps (1 = every frame)."""
    mask_weight: float = 0.5
    """A pixel belongs to an instance when the instance's unoccluded share of the pixel is at least this: the
    front-most node where its alpha is high."""
    depth_alpha: float = 0.5
    """Depth is written where the Gaussians cover at least this much of a pixel (0 = no surface elsewhere)."""
    min_mask_pixels: int = 1
    """An instance with fewer mask pixels than this has no tight 2D box in that camera."""
    min_label_depth_m: float = 0.5
    """Box corners nearer than this to the camera plane are clipped there before projection (boxes behind or
    beside the camera still get a correct image rectangle)."""
    lidar_vertical_step_deg: float = 1.33
    """Simulated LiDAR: angle between sampled rows of each camera's depth (HDL-32E-like: 41.3° over 31 gaps)."""
    lidar_horizontal_step_deg: float = 0.33
    """Simulated LiDAR: angle between sampled columns of each camera's depth."""
    lidar_max_range_m: float = 70.0
    """Simulated LiDAR: returns further than this are dropped."""
    max_viewpoint_offset_m: float = 4.0
    """Frames whose ego lies further than this from every logged ego position are not rendered: the scene graph
    was never fitted from there (the variant is kept and the frames it lost are recorded)."""
    command_horizon_s: float = 3.0
    """The driving command looks this far ahead along the ego's trajectory (UniAD's rule)."""
    command_lateral_m: float = 2.0
    """Lateral offset (ego frame, metres) at the command horizon beyond which the command is left or right."""
    fidelity_every: int = 1
    """Measure the fidelity of every Nth rendered frame (0 = never): the proxies every scene gets (logged PSNR and
    feature drift against the graph's unedited render) and, with ``exact_fidelity``, the exact comparison."""
    exact_fidelity: bool = True
    """Also compare with the exact render of the variant where the scene has one (procedural scenes: the world is
    rendered again at every measured frame, then PSNR/SSIM; the costliest part of the stage)."""

    def __post_init__(self) -> None:
        for name in ("frame_every", "min_mask_pixels"):
            if int(getattr(self, name)) < 1:
                raise OmniscsError(f"annotate {name} must be >= 1; got {getattr(self, name)}")
        if not isinstance(self.exact_fidelity, bool):
            raise OmniscsError(f"annotate exact_fidelity must be true or false; got {self.exact_fidelity!r}")
        if int(self.fidelity_every) < 0:
            raise OmniscsError(f"annotate fidelity_every must be >= 0; got {self.fidelity_every}")
        for name in ("mask_weight", "depth_alpha"):
            if not 0.0 < float(getattr(self, name)) <= 1.0:
                raise OmniscsError(f"annotate {name} must lie in (0, 1]; got {getattr(self, name)}")
        for name in ("min_label_depth_m", "lidar_vertical_step_deg", "lidar_horizontal_step_deg", "lidar_max_range_m",
                     "max_viewpoint_offset_m", "command_horizon_s", "command_lateral_m"):
            if not float(getattr(self, name)) > 0.0:
                raise OmniscsError(f"annotate {name} must be > 0; got {getattr(self, name)}")

    def to_dict(self) -> dict:
        return asdict(self)


def visibility_level(fraction: float) -> int:
    """nuScenes visibility level 1..4 (v0-40, v40-60, v60-80, v80-100) of a visible fraction in [0, 1]."""
    return 1 + sum(float(fraction) >= b for b in VISIBILITY_BOUNDS)
