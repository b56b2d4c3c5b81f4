"""Spinning-LiDAR model: beam directions of a ``LidarSpec`` and the return intensity of each material."""
from __future__ import annotations

import numpy as np

from omniscs.geometry import spinning_beam_directions
from omniscs.world.assets import Material
from omniscs.world.model import LidarSpec

#: Intensities are reported like nuScenes LIDAR_TOP: float in [0, 255].
INTENSITY_MAX = 255.0

#: Diffuse reflectivity at normal incidence per material (0..1).
_REFLECTIVITY = {
    Material.ASPHALT: 0.08, Material.LANE_PAINT: 0.55, Material.CONCRETE: 0.25, Material.KERB: 0.3,
    Material.FACADE: 0.25, Material.ROOF: 0.2, Material.METAL: 0.35, Material.FOLIAGE: 0.3, Material.BARK: 0.15,
    Material.GRASS: 0.25, Material.CAR_PAINT: 0.3, Material.GLASS: 0.05, Material.TYRE: 0.04,
    Material.HEADLIGHT: 0.6, Material.TAILLIGHT: 0.5, Material.PLASTIC: 0.2, Material.CHROME: 0.5,
    Material.LAMP: 0.5, Material.PLATE: 0.95, Material.CONTAINER: 0.3, Material.REFLECTIVE: 1.0,
    Material.SIGN_LIGHT: 0.4, Material.ROCK: 0.2, Material.WOOD: 0.25, Material.SIGNAL: 0.4,
}
#: Retro-reflectors return light back along the beam whatever the incidence angle.
_RETROREFLECTIVE = {Material.PLATE, Material.REFLECTIVE, Material.HEADLIGHT, Material.TAILLIGHT}

REFLECTIVITY = np.zeros(max(Material) + 1, dtype=np.float32)
RETRO = np.zeros(max(Material) + 1, dtype=bool)
for _m, _r in _REFLECTIVITY.items():
    REFLECTIVITY[_m] = _r
    RETRO[_m] = _m in _RETROREFLECTIVE


def beam_directions(spec: LidarSpec) -> np.ndarray:  # -> [beams * azimuth_steps, 3] unit, lidar frame
    """Unit ray directions, beam-major (row = elevation from top to bottom, column = azimuth over 360°)."""
    return spinning_beam_directions(spec.beams, spec.min_elevation_deg, spec.max_elevation_deg, spec.azimuth_steps)


def intensity(material: np.ndarray, cos_incidence: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """material [N] uint8, |cos| of the incidence angle [N], range [N] metres -> intensity [N] in [0, 255]."""
    cos_incidence = np.clip(np.abs(cos_incidence), 0.0, 1.0)
    shape = np.where(RETRO[material], 1.0, cos_incidence)
    # A mild range falloff: real sensors calibrate most of it away.
    falloff = 1.0 / (1.0 + (np.asarray(distance) / 120.0) ** 2)
    return np.clip(INTENSITY_MAX * REFLECTIVITY[material] * shape * falloff, 0.0, INTENSITY_MAX).astype(np.float32)
