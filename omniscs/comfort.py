"""Comfort bounds on a trajectory's kinematics, written once: the behaviour variants keep their agents within one
set, closed-loop runs are scored against the published ones (nuPlan's, as NAVSIM and HUGSIM use them)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ComfortBounds:
    """Bounds a comfortable trajectory keeps at every sample; a bound set to None is not checked."""

    min_lon_accel: float
    """Most negative longitudinal acceleration allowed (m/s², negative: the braking bound)."""
    max_lon_accel: float
    """Largest longitudinal acceleration allowed (m/s²)."""
    max_abs_lat_accel: float
    """Largest |lateral acceleration| (m/s²), lateral acceleration = longitudinal speed * yaw rate."""
    max_abs_yaw_rate: float
    """Largest |yaw rate| (rad/s)."""
    max_abs_yaw_accel: float | None = None
    """Largest |yaw acceleration| (rad/s²); None: not checked."""
    max_abs_lon_jerk: float | None = None
    """Largest |longitudinal jerk| (m/s³); None: not checked."""
    max_abs_jerk: float | None = None
    """Largest |time derivative of the acceleration magnitude| (m/s³); None: not checked."""

    def scaled(self, factor: float) -> ComfortBounds:
        """Every bound multiplied by ``factor`` (a margin inside the bounds when below 1)."""
        scale = lambda b: None if b is None else factor * b  # noqa: E731
        return ComfortBounds(scale(self.min_lon_accel), scale(self.max_lon_accel), scale(self.max_abs_lat_accel),
                             scale(self.max_abs_yaw_rate), scale(self.max_abs_yaw_accel),
                             scale(self.max_abs_lon_jerk), scale(self.max_abs_jerk))


#: What a plausible behaviour variant stays within (the issue's comfort bounds; kinematics only, no jerk).
VARIANT_COMFORT = ComfortBounds(min_lon_accel=-4.05, max_lon_accel=2.4, max_abs_lat_accel=4.9, max_abs_yaw_rate=1.0)
#: nuPlan's comfort bounds as NAVSIM's PDM score uses them.
NAVSIM_COMFORT = ComfortBounds(min_lon_accel=-4.05, max_lon_accel=2.40, max_abs_lat_accel=4.89,
                               max_abs_yaw_rate=0.95, max_abs_yaw_accel=1.93, max_abs_lon_jerk=4.13,
                               max_abs_jerk=8.37)
#: HUGSIM's bounds (its score calculator has no jerk-magnitude bound and a looser longitudinal jerk).
HUGSIM_COMFORT = ComfortBounds(min_lon_accel=-4.05, max_lon_accel=2.40, max_abs_lat_accel=4.89,
                               max_abs_yaw_rate=0.95, max_abs_yaw_accel=1.93, max_abs_lon_jerk=8.37,
                               max_abs_jerk=None)
