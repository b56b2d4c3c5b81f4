"""What a pool model's surface is made of, per Gaussian: what its colours follow when the scene's light changes.

- ``albedo``: linear diffuse reflectance (0..1, per channel), without any light;
- ``specular``: reflectance at normal incidence (0: matte, no mirror term; car paint about 0.05, glass 0.09, chrome
  0.55), the F0 of Schlick's Fresnel approximation;
- ``shininess``: the Blinn-Phong exponent of the sun's highlight (about 10 for rough plastic, 400 for glass).

Mesh builds know them from the mesh's faces (``agents.mesh``); models that come as splats (imported PLY, scene
tracks) have none, and ``agents.relight`` estimates their albedo from their colours. ``omniscs.nsg.relight`` shades
them under a scene's sun and sky.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from omniscs.errors import ValidationError

#: Highest Blinn-Phong exponent a material may hold (beyond it a highlight is narrower than a pixel anyway).
MAX_SHININESS = 2000.0
NAMES = ("albedo", "specular", "shininess")


@dataclass(frozen=True)
class GaussianMaterial:
    albedo: Tensor     # [N, 3] linear 0..1
    specular: Tensor   # [N] 0..1
    shininess: Tensor  # [N] 1..MAX_SHININESS

    def __post_init__(self) -> None:
        n = self.albedo.shape[0] if self.albedo.ndim == 2 else -1
        if self.albedo.shape != (n, 3) or self.specular.shape != (n,) or self.shininess.shape != (n,):
            raise ValidationError(f"a material needs albedo [N, 3], specular [N] and shininess [N]; got "
                                  f"{tuple(self.albedo.shape)}, {tuple(self.specular.shape)}, "
                                  f"{tuple(self.shininess.shape)}")
        for name in NAMES:
            if not bool(torch.isfinite(getattr(self, name)).all()):
                raise ValidationError(f"a material's {name} holds NaN or Inf values")
        if bool((self.albedo < 0).any() | (self.albedo > 1).any()) \
                or bool((self.specular < 0).any() | (self.specular > 1).any()) \
                or bool((self.shininess < 1).any() | (self.shininess > MAX_SHININESS).any()):
            raise ValidationError(f"a material needs albedo and specular in 0..1 and shininess in 1..{MAX_SHININESS:g}")

    def __len__(self) -> int:
        return int(self.albedo.shape[0])

    @classmethod
    def from_faces(cls, face: np.ndarray, face_albedo: np.ndarray, face_specular: np.ndarray | None = None,
                   face_shininess: np.ndarray | None = None) -> "GaussianMaterial":
        """The material of Gaussians drawn on faces ``face`` ([N] indices) of a mesh whose faces have linear albedo
        [F, 3] and, when given, specular reflectance [F] and shininess [F] (none: matte)."""
        face = np.asarray(face, dtype=np.int64)
        albedo = np.clip(np.asarray(face_albedo, dtype=np.float64)[face], 0.0, 1.0)
        spec = np.zeros(len(face)) if face_specular is None else np.asarray(face_specular, np.float64)[face]
        shin = np.ones(len(face)) if face_shininess is None else np.asarray(face_shininess, np.float64)[face]
        return cls(torch.as_tensor(albedo, dtype=torch.float32),
                   torch.as_tensor(np.clip(spec, 0.0, 1.0), dtype=torch.float32),
                   torch.as_tensor(np.clip(shin, 1.0, MAX_SHININESS), dtype=torch.float32))

    def as_dict(self) -> dict[str, Tensor]:
        return {f"material.{k}": getattr(self, k).detach().cpu().contiguous().float() for k in NAMES}

    @classmethod
    def from_dict(cls, tensors: dict[str, Tensor]) -> "GaussianMaterial | None":
        """The material saved by ``as_dict``, or None when ``tensors`` hold none."""
        if not any(k.startswith("material.") for k in tensors):
            return None
        missing = [k for k in NAMES if f"material.{k}" not in tensors]
        if missing:
            raise ValidationError(f"material tensors incomplete: missing {missing}")
        return cls(*(tensors[f"material.{k}"].float() for k in NAMES))

    def select(self, index: Tensor) -> "GaussianMaterial":
        index = torch.as_tensor(index, dtype=torch.long).cpu()
        return GaussianMaterial(self.albedo[index], self.specular[index], self.shininess[index])
