"""How variants are rendered and annotated (one frozen config; its fields are part of the annotate stage's key)."""
from __future__ import annotations

from dataclasses import asdict, dataclass

from omniscs.errors import OmniscsError

#: ``lidar_source`` values: the exact sweep where the scene has one (else the ring), a 360° ring of rendered views
#: at the LiDAR mount, or the dataset cameras' depth.
LIDAR_SOURCES = ("world", "ring", "cameras")
#: Bounds of ``lidar_ring_pixel_deg``: finer would render views thousands of pixels wide; coarser hardly samples.
MIN_RING_PIXEL_DEG, MAX_RING_PIXEL_DEG = 0.05, 5.0
#: The ring's azimuth step is at least this (degrees): 36,000 columns per beam already outnumber any sensor's.
MIN_LIDAR_STEP_DEG = 0.01
#: Beam elevations stay inside this (degrees): a level pinhole view cannot hold a beam pointing straight up or down.
MAX_ELEVATION_DEG = 80.0
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
    lidar_source: str = "world"
    """Where the simulated LiDAR's returns come from: ``world``, the exact sweep of the variant where the scene has
    one (procedural scenes: the world, with the variant's edits, ray-cast by its own HDL-32E-like sensor; cheaper
    than the ring), the ring everywhere else; ``ring``, a LIDAR_TOP-like spinning sensor at the ego's LiDAR
    mount whose beams are looked up in depth the scene graph renders in a ring of views around it (360°, like the
    logs' LiDAR; costs ``lidar_ring_views`` extra depth renders per frame); ``cameras``, the dataset cameras' own
    depth only (no extra render; boxes outside every camera get no points)."""
    lidar_beams: int = 32
    """Simulated LiDAR (ring): beams, evenly spaced between the elevation limits (nuScenes' HDL-32E: 32)."""
    lidar_max_elevation_deg: float = 10.67
    """Simulated LiDAR (ring): elevation of the top beam above the sensor's horizontal plane (HDL-32E: +10.67°)."""
    lidar_min_elevation_deg: float = -30.67
    """Simulated LiDAR (ring): elevation of the bottom beam (HDL-32E: -30.67°)."""
    lidar_vertical_step_deg: float = 1.33
    """Simulated LiDAR (cameras): angle between sampled rows of each camera's depth (HDL-32E-like: 41.3° over 31
    gaps)."""
    lidar_horizontal_step_deg: float = 0.33
    """Simulated LiDAR: azimuth step of the ring's beams (360° / step columns per beam), and the angle between sampled
    columns of each camera's depth (cameras)."""
    lidar_max_range_m: float = 70.0
    """Simulated LiDAR: returns further than this are dropped."""
    lidar_min_range_m: float = 1.0
    """Simulated LiDAR (ring): returns nearer than this to the sensor are dropped (a spinning LiDAR's blind range;
    nuScenes' devkit removes points within 1 m)."""
    lidar_background_clearance_m: float = 3.0
    """Simulated LiDAR (ring): background Gaussians whose centres lie nearer than this to the sensor are not drawn
    for it (agent nodes always are). The lowest beam of a roof LiDAR meets the road about 3 m out, so little of the
    static scene lies nearer; what a fit leaves there are stray Gaussians around the ego's own path, which no camera
    looked at from the sensor and which would otherwise fill whole ring views at a few decimetres."""
    lidar_ring_views: int = 6
    """Simulated LiDAR (ring): pinhole views around the mount that the depth is rendered in (at least 3; each covers
    360° / views of azimuth)."""
    lidar_depth_alpha: float = 0.5
    """Simulated LiDAR (ring): a beam returns where the Gaussians cover at least this much of its pixel."""
    lidar_ring_pixel_deg: float = 0.33
    """Simulated LiDAR (ring): angular size of a ring view's pixel at its centre, the ring's resolution: larger is
    cheaper (fewer pixels to render) and coarser (neighbouring beams share a pixel's depth). At the default the six
    views hold about as many pixels as 1.5 images of 480x270."""
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
        if self.lidar_source not in LIDAR_SOURCES:
            raise OmniscsError(f"annotate lidar_source must be one of {', '.join(LIDAR_SOURCES)}; got "
                               f"{self.lidar_source!r}")
        if int(self.lidar_ring_views) < 3:
            raise OmniscsError(f"annotate lidar_ring_views must be >= 3 (a pinhole view covers less than 180°); got "
                               f"{self.lidar_ring_views}")
        if not MIN_RING_PIXEL_DEG <= float(self.lidar_ring_pixel_deg) <= MAX_RING_PIXEL_DEG:
            raise OmniscsError(f"annotate lidar_ring_pixel_deg must lie in [{MIN_RING_PIXEL_DEG}, "
                               f"{MAX_RING_PIXEL_DEG}]; got {self.lidar_ring_pixel_deg}")
        if not -MAX_ELEVATION_DEG < float(self.lidar_min_elevation_deg) < float(self.lidar_max_elevation_deg) \
                < MAX_ELEVATION_DEG:
            raise OmniscsError(f"annotate lidar elevations must satisfy -{MAX_ELEVATION_DEG} < lidar_min_elevation_deg "
                               f"< lidar_max_elevation_deg < {MAX_ELEVATION_DEG}; got {self.lidar_min_elevation_deg} "
                               f"and {self.lidar_max_elevation_deg}")
        if not float(self.lidar_horizontal_step_deg) >= MIN_LIDAR_STEP_DEG:
            raise OmniscsError(f"annotate lidar_horizontal_step_deg must be >= {MIN_LIDAR_STEP_DEG} (360° / step "
                               f"beams per ring); got {self.lidar_horizontal_step_deg}")
        for name in ("frame_every", "min_mask_pixels", "lidar_beams"):
            if int(getattr(self, name)) < 1:
                raise OmniscsError(f"annotate {name} must be >= 1; got {getattr(self, name)}")
        if not isinstance(self.exact_fidelity, bool):
            raise OmniscsError(f"annotate exact_fidelity must be true or false; got {self.exact_fidelity!r}")
        if int(self.fidelity_every) < 0:
            raise OmniscsError(f"annotate fidelity_every must be >= 0; got {self.fidelity_every}")
        for name in ("mask_weight", "depth_alpha", "lidar_depth_alpha"):
            if not 0.0 < float(getattr(self, name)) <= 1.0:
                raise OmniscsError(f"annotate {name} must lie in (0, 1]; got {getattr(self, name)}")
        for name in ("lidar_min_range_m", "lidar_background_clearance_m"):
            if not 0.0 <= float(getattr(self, name)) < float(self.lidar_max_range_m):
                raise OmniscsError(f"annotate {name} must lie in [0, lidar_max_range_m); got {getattr(self, name)}")
        for name in ("min_label_depth_m", "lidar_vertical_step_deg", "lidar_horizontal_step_deg", "lidar_max_range_m",
                     "max_viewpoint_offset_m", "command_horizon_s", "command_lateral_m"):
            if not float(getattr(self, name)) > 0.0:
                raise OmniscsError(f"annotate {name} must be > 0; got {getattr(self, name)}")

    def to_dict(self) -> dict:
        return asdict(self)


def visibility_level(fraction: float) -> int:
    """nuScenes visibility level 1..4 (v0-40, v40-60, v60-80, v80-100) of a visible fraction in [0, 1]."""
    return 1 + sum(float(fraction) >= b for b in VISIBILITY_BOUNDS)
