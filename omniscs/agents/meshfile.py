"""Reading a user's mesh file for the pool: its triangles, one colour per face and, where the file says, what each
face is made of (``agents.material``: linear albedo, specular reflectance at normal incidence, shininess).

Every geometry of the file (a glTF/GLB scene's nodes, an OBJ's material groups) is placed by its scene transform
and keeps its own material:

- glTF metallic-roughness (``PBRMaterial``): base colour = baseColorFactor x baseColorTexture (sampled at the face's
  centre in UV), metallic and roughness = their factors x metallicRoughnessTexture's blue and green channels; the
  glTF defaults where the file gives none (factors 1, white). The usual metallic-roughness to Blinn-Phong mapping:
  albedo = base (1 - metallic); specular reflectance F0 = 0.04 (1 - metallic) + metallic x mean(base) (a
  dielectric reflects 4 % head-on, a metal its own colour: our mirror term has one grey F0, so a metal's tint is
  lost); shininess = 2 / roughness^4 - 2 (alpha = roughness^2, Walter et al.'s Beckmann-to-Phong match), clipped
  to ``agents.material``'s range. The colour a splat viewer shows (the model's keyframes and Gaussian colours) stays
  the base colour.
- OBJ/MTL (``SimpleMaterial``): the diffuse colour (Kd, or its map_Kd sampled per face) is the albedo; Ns is
  already a Phong exponent and becomes the shininess. Ks says *that* a surface is glossy, not how much it mirrors
  (exporters write 0.5 by habit), so a face with a non-zero Ks counts as a dielectric (F0 0.04, as glTF's
  non-metals) and one without as matte.
- Vertex or face colours, or nothing: matte, the colours (or a neutral grey) as albedo.

Colours in files are sRGB; albedo is linear.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omniscs.agents.material import MAX_SHININESS
from omniscs.errors import ValidationError

#: Specular reflectance at normal incidence of a dielectric (glTF's value for every non-metal).
DIELECTRIC_F0 = 0.04
#: Colour of a face whose file gives none (sRGB 0..1).
NEUTRAL_GREY = 0.6
#: Lowest shininess of a material (``agents.material``; MAX_SHININESS the highest).
MIN_SHININESS = 1.0


@dataclass(frozen=True)
class MeshFile:
    """A mesh file's triangles and per-face appearance (F faces)."""

    vertices: np.ndarray       # [V, 3] float64
    faces: np.ndarray          # [F, 3] int64
    colour: np.ndarray         # [F, 3] linear: what the surface looks like (the base colour; keyframes, splats)
    albedo: np.ndarray         # [F, 3] linear diffuse reflectance (the base colour less what metals mirror)
    specular: np.ndarray | None   # [F] F0, or None: the file says nothing of it (every face matte)
    shininess: np.ndarray | None  # [F] Blinn-Phong exponent, or None
    materials: tuple[str, ...]    # per geometry: "pbr", "mtl", "colours" or "none"


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """File colours (sRGB 0..1) -> linear, by the curve the relight shades with (``nsg.relight.srgb_decode``)."""
    import torch

    from omniscs.nsg.relight import srgb_decode

    return srgb_decode(torch.as_tensor(np.asarray(c, np.float64))).numpy()


def roughness_to_shininess(roughness: np.ndarray) -> np.ndarray:
    """Blinn-Phong exponent of a metallic-roughness surface: 2 / alpha^2 - 2 with alpha = roughness^2."""
    r = np.clip(np.asarray(roughness, np.float64), 0.0, 1.0)
    alpha2 = np.maximum(r ** 4, 2.0 / (MAX_SHININESS + 2.0))  # keeps the exponent finite at roughness 0
    return np.clip(2.0 / alpha2 - 2.0, MIN_SHININESS, MAX_SHININESS)


def pbr_to_phong(base: np.ndarray, metallic: np.ndarray, roughness: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(albedo [F, 3], F0 [F], shininess [F]) of faces with linear base colour [F, 3], metallic [F], roughness [F]."""
    base = np.clip(np.asarray(base, np.float64), 0.0, 1.0)
    m = np.clip(np.asarray(metallic, np.float64), 0.0, 1.0)
    albedo = base * (1.0 - m)[:, None]
    f0 = DIELECTRIC_F0 * (1.0 - m) + m * base.mean(1)
    return albedo, np.clip(f0, 0.0, 1.0), roughness_to_shininess(roughness)


def _float_colour(c, default: float = 1.0) -> np.ndarray:  # RGBA/RGB uint8 or float -> [4] float 0..1
    if c is None:
        return np.full(4, default)
    a = np.asarray(c, np.float64).ravel()
    if a.size == 0 or not np.isfinite(a).all():
        return np.full(4, default)
    if np.asarray(c).dtype.kind in "ui" or a.max() > 1.0:
        a = a / 255.0
    if a.size == 3:
        a = np.append(a, 1.0)
    return np.clip(a[:4], 0.0, 1.0)


def _sample(image, uv: np.ndarray | None) -> np.ndarray | None:  # -> [F, 4] float 0..1 at face-centre uv
    if image is None or uv is None:
        return None
    from trimesh.visual.color import uv_to_color

    out = uv_to_color(uv, image)
    if out is None:
        return None
    return np.asarray(out, np.float64).reshape(len(uv), -1)[:, :4] / 255.0


def _face_uv(geom) -> np.ndarray | None:
    uv = getattr(geom.visual, "uv", None)
    if uv is None or len(uv) != len(geom.vertices):
        return None
    uv = np.asarray(uv, np.float64)
    if not np.isfinite(uv).all():
        return None
    return uv[np.asarray(geom.faces)].mean(1)


def _appearance(geom) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, str]:
    """(colour, albedo, F0 or None, shininess or None, kind) per face of one trimesh geometry."""
    from trimesh.visual.material import PBRMaterial, SimpleMaterial

    n = len(geom.faces)
    visual = geom.visual
    material = getattr(visual, "material", None)
    uv = _face_uv(geom) if material is not None else None
    if isinstance(material, PBRMaterial):
        base = np.tile(_float_colour(material.baseColorFactor), (n, 1))
        tex = _sample(material.baseColorTexture, uv)
        if tex is not None:
            k = min(4, tex.shape[1])
            base[:, :k] *= tex[:, :k]
        metallic = np.full(n, 1.0 if material.metallicFactor is None else float(material.metallicFactor))
        roughness = np.full(n, 1.0 if material.roughnessFactor is None else float(material.roughnessFactor))
        mr = _sample(material.metallicRoughnessTexture, uv)
        if mr is not None and mr.shape[1] >= 3:
            roughness, metallic = roughness * mr[:, 1], metallic * mr[:, 2]
        colour = srgb_to_linear(base[:, :3])
        albedo, f0, shininess = pbr_to_phong(colour, metallic, roughness)
        return colour, albedo, f0, shininess, "pbr"
    if isinstance(material, SimpleMaterial):
        tex = _sample(getattr(material, "image", None), uv)
        diffuse = np.tile(_float_colour(material.diffuse), (n, 1))
        colour = srgb_to_linear((tex if tex is not None else diffuse)[:, :3])
        glossy = float(np.max(_float_colour(material.specular, 0.0)[:3])) > 0.0
        ns = material.glossiness
        shininess = np.full(n, np.clip(float(ns) if ns is not None and np.isfinite(ns) else MIN_SHININESS,
                                       MIN_SHININESS, MAX_SHININESS))
        return colour, colour, np.full(n, DIELECTRIC_F0 if glossy else 0.0), shininess, "mtl"
    rgba, kind = np.full((n, 3), NEUTRAL_GREY), "none"
    if getattr(visual, "kind", None) is not None:  # colours the file defines (not trimesh's default grey)
        try:
            rgba, kind = np.asarray(visual.face_colors, np.float64)[:, :3] / 255.0, "colours"
        except Exception:  # a visual trimesh cannot turn into face colours: no colour information
            rgba, kind = np.full((n, 3), NEUTRAL_GREY), "none"
    if rgba.shape != (n, 3) or not np.isfinite(rgba).all():
        rgba, kind = np.full((n, 3), NEUTRAL_GREY), "none"
    colour = srgb_to_linear(rgba)
    return colour, colour, None, None, kind


def read_mesh_file(path: str | Path) -> MeshFile:
    """Every geometry of the mesh file at ``path`` (any format trimesh reads) in the file's frame, with its
    appearance (module docstring). Raises ValidationError for unreadable files, files without triangles and
    non-finite vertices."""
    import trimesh

    try:
        scene = trimesh.load(str(path), force="scene")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise ValidationError(f"{path}: not a mesh trimesh can read ({type(e).__name__}: {e})") from e
    parts = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry.get(name)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        colour, albedo, f0, shininess, kind = _appearance(geom)
        vertices = trimesh.transform_points(np.asarray(geom.vertices, np.float64), np.asarray(transform, np.float64))
        parts.append((vertices, np.asarray(geom.faces, np.int64), colour, albedo, f0, shininess, kind))
    if not parts:
        raise ValidationError(f"{path}: the file holds no triangles")
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    vertices = np.concatenate([p[0] for p in parts])
    if not np.isfinite(vertices).all():
        raise ValidationError(f"{path}: the mesh has non-finite vertices")
    faces = np.concatenate([p[1] + o for p, o in zip(parts, offsets)])
    described = any(p[4] is not None for p in parts)
    specular = np.concatenate([p[4] if p[4] is not None else np.zeros(len(p[1])) for p in parts]) if described else None
    shininess = (np.concatenate([p[5] if p[5] is not None else np.full(len(p[1]), MIN_SHININESS) for p in parts])
                 if described else None)
    return MeshFile(vertices, faces, np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts]),
                    specular, shininess, tuple(p[6] for p in parts))
