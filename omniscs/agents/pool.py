"""The model pool: 360-degree Gaussian models of road users in their vehicle frame (+x heading, y left, z up, origin at
the centre of the box, metres), gathered from meshes, imported splat files and well-observed scene tracks.

On disk (``<pool>/``): ``models/<model_id>/`` holds ``gaussians.safetensors`` (the raw parameters),
``material.safetensors`` where the model has one (``agents.material``: per-Gaussian albedo, specular reflectance and
shininess, from a mesh build) and ``model.json`` (category, box size, provenance, source, quality, version, what
calibration did); ``index/`` holds one Parquet row per model (``INDEX_COLUMNS``), read together as the pool's table,
and ``keyframes.npz`` (30 RGBA views around the model at 12 degrees of azimuth, rendered when it joins). The id is a
content hash of the parameters, material and category (``pm-<12 hex>``): adding the same model again is a no-op
that returns its id. A model's folder is written whole (a temporary sibling renamed into place) before its index
row, and each row is its own file, so two writers adding at once never lose or half-write an entry, and a reader
never sees a row without its model. Keyframe embeddings are cached per embedder under ``embeddings/``
(``agents.matching.pool_gallery``)."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from omniscs.errors import OmniscsError, ValidationError
from omniscs.gaussians import GaussianParams, rigidly_moved
from omniscs.ids import check_id
from omniscs.locks import output_lock
from omniscs.storage import atomic_directory, atomic_write_bytes, inside
from omniscs.taxonomy import CATEGORIES
from omniscs.untrusted import check_parquet_files, read_own_json

POOL_VERSION = 1
MODELS, INDEX = "models", "index"
GAUSSIANS, MATERIAL, META, KEYFRAMES = "gaussians.safetensors", "material.safetensors", "model.json", "keyframes.npz"
PROVENANCES = ("mesh", "imported", "scene_track")
INDEX_COLUMNS = ("model_id", "category", "length", "width", "height", "n_gaussians", "sh_degree", "provenance",
                 "source", "quality", "version", "added_at_us")
INDEX_SCHEMA = pa.schema([(c, pa.large_string()) if c in ("model_id", "category", "provenance", "source")
                          else (c, pa.float64()) if c in ("length", "width", "height", "quality")
                          else (c, pa.int64()) for c in INDEX_COLUMNS])


def model_id_of(params: GaussianParams, category: str, material=None) -> str:
    """``pm-<12 hex>`` of the parameters' (and the material's, when there is one) bytes and the category."""
    h = hashlib.sha256(category.encode())
    tensors = {**params.as_dict(), **({} if material is None else material.as_dict())}
    for name, t in tensors.items():
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().astype(np.float32).tobytes())
    return f"pm-{h.hexdigest()[:12]}"


@dataclass(frozen=True)
class PoolModel:
    model_id: str
    params: GaussianParams
    meta: dict
    material: object = None  # agents.material.GaussianMaterial, or None (a model made from splats)


#: The largest Gaussian a pool model may hold (metres, along any axis; the stored log-scale's exponential) and the
#: largest extent of its centres: a vehicle or an object on the road, not a scene. A PLY whose log-scales were
#: written as scales (80 is e^80 = 5e34 m) is refused rather than stored as a model that fills every view.
MAX_GAUSSIAN_SIZE_M = 10.0
MAX_MODEL_EXTENT_M = 100.0


def check_model_extent(params: GaussianParams) -> None:
    """Refuse a model whose Gaussians (as the renderer turns the log-scales into sizes) or centres reach beyond what
    an object can be (``MAX_GAUSSIAN_SIZE_M``, ``MAX_MODEL_EXTENT_M``), or whose orientations are not quaternions."""
    largest = float(params.log_scales.detach().double().max())
    if largest > np.log(MAX_GAUSSIAN_SIZE_M):
        raise ValidationError(f"a pool model's Gaussians may be at most {MAX_GAUSSIAN_SIZE_M:g} m across; the largest "
                              f"here is e^{largest:.3g} = {np.exp(min(largest, 700.0)):.3g} m (log-scales are stored: "
                              "was a size written where its logarithm belongs?)")
    means = params.means.detach().double()
    extent = float((means.max(0).values - means.min(0).values).max()) if len(params) else 0.0
    if extent > MAX_MODEL_EXTENT_M:
        raise ValidationError(f"a pool model may span at most {MAX_MODEL_EXTENT_M:g} m; this one spans {extent:.3g} m")
    if float(params.quats.detach().double().norm(dim=1).min()) < 1e-6:
        raise ValidationError("a pool model's orientations must be quaternions (a norm of at least 1e-6)")


class Pool:
    """A pool folder (created on the first add)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise ValidationError(f"pool {self.root} is a file, not a folder")

    def folder(self, model_id: str) -> Path:
        """The folder of model ``model_id``, which must stay inside the pool: a ``models/`` folder (or a model's)
        that is a symbolic link out of it is refused (``storage.inside``), not followed."""
        folder = self.root / MODELS / model_id
        if self.root.exists():
            inside(folder, self.root, f"pool model folder of {model_id}")
        return folder

    def add(self, params: GaussianParams, category: str, provenance: str, source: str,
            quality: float | None = None, calibration: dict | None = None, build: dict | None = None,
            material=None) -> str:
        """Put a model (already in its vehicle frame) into the pool; returns its id (the same model: the same id,
        nothing written twice). ``build``: how the model was made (e.g. ``model_from_mesh``'s "build": method,
        version, settings), kept in its ``model.json``; ``material``: its ``GaussianMaterial`` (one per Gaussian),
        when it has one."""
        if category not in CATEGORIES:
            raise ValidationError(f"unknown category {category!r}; one of {list(CATEGORIES)}")
        if provenance not in PROVENANCES:
            raise ValidationError(f"provenance must be one of {PROVENANCES}; got {provenance!r}")
        if len(params) == 0:
            raise ValidationError("a pool model needs at least one Gaussian")
        if not params.is_finite():
            raise ValidationError("a pool model's parameters must be finite")
        check_model_extent(params)
        if material is not None and len(material) != len(params):
            raise ValidationError(f"the material is for {len(material)} Gaussians; the model has {len(params)}")
        params = params.detached()
        model_id = model_id_of(params, category, material)
        folder = self.folder(model_id)
        means = params.means.double().numpy()
        size = means.max(0) - means.min(0)
        meta = {"model_id": model_id, "category": category, "size": size.tolist(), "n_gaussians": len(params),
                "sh_degree": params.sh_degree, "provenance": provenance, "source": str(source),
                "quality": None if quality is None or not np.isfinite(quality) else float(quality),
                "version": POOL_VERSION, "calibration": calibration, "build": build,
                "added_at_us": int(time.time() * 1e6)}
        with output_lock(folder):  # one writer per model at a time: adding, or removing (``remove``)
            if not (folder / META).is_file():
                from safetensors.torch import save_file

                from omniscs.agents.mesh import keyframes

                views = keyframes(params, np.maximum(size, 1e-3))
                with atomic_directory(folder) as tmp:
                    save_file({k: v.contiguous() for k, v in params.as_dict().items()}, str(tmp / GAUSSIANS))
                    if material is not None:
                        save_file(material.as_dict(), str(tmp / MATERIAL))
                    np.savez_compressed(tmp / KEYFRAMES, rgba=views)
                    (tmp / META).write_text(json.dumps(meta, indent=1, sort_keys=True))
            index = self.root / INDEX / f"{model_id}.parquet"
            if not index.is_file():
                row = pd.DataFrame([{"model_id": model_id, "category": category, "length": float(size[0]),
                                     "width": float(size[1]), "height": float(size[2]), "n_gaussians": len(params),
                                     "sh_degree": params.sh_degree, "provenance": provenance, "source": str(source),
                                     "quality": meta["quality"], "version": POOL_VERSION,
                                     "added_at_us": meta["added_at_us"]}], columns=list(INDEX_COLUMNS))
                index.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(index, row.to_parquet(index=False))
        return model_id

    def remove(self, model_id: str) -> dict:
        """Take a model out of the pool; returns its metadata. Its index row goes first and then its folder, so a
        reader of the table never meets a row without its model; a writer adding the same model waits (one lock per
        model). Embedding caches follow the pool's content and are recomputed on their next use. A model the pool
        does not hold is a clear error, and nothing changes."""
        check_id("pool model id", model_id)
        folder = self.folder(model_id)
        index = self.root / INDEX / f"{model_id}.parquet"
        if not (folder / META).is_file() and not index.is_file():
            raise ValidationError(f"pool {self.root} has no model {model_id}")
        with output_lock(folder):
            try:
                meta = read_own_json(folder / META, "remove it", what="pool model record")
            except OmniscsError:  # a row left without its model (removed by hand): the row still goes
                meta = {"model_id": model_id}
            index.unlink(missing_ok=True)
            if folder.exists():
                trash = folder.parent / f".{folder.name}.removed-{os.getpid()}"
                os.replace(folder, trash)
                shutil.rmtree(trash, ignore_errors=True)
        return meta

    def table(self) -> pd.DataFrame:
        """One row per model (``INDEX_COLUMNS``), by id; empty when the pool is."""
        import pyarrow.dataset as ds

        files = sorted((self.root / INDEX).glob("pm-*.parquet"))
        if not files:
            return pd.DataFrame(columns=list(INDEX_COLUMNS))
        # junk, a truncated row or a foreign Parquet file is one error naming it, never a pyarrow trace or rows
        check_parquet_files(files, INDEX_SCHEMA, f"pool {self.root} index file",
                            "index rows are written by omniscs only: remove that file, or add its model again",
                            required=("model_id",))
        # one scan over the row files: 0.26 s for 320 rows, against 1.6 s reading them one by one
        table = ds.dataset([str(f) for f in files], format="parquet", schema=INDEX_SCHEMA).to_table()
        return table.to_pandas().sort_values("model_id", ignore_index=True)

    def get(self, model_id: str) -> PoolModel:
        from safetensors.torch import load_file

        check_id("pool model id", model_id)
        folder = self.folder(model_id)
        if not (folder / META).is_file():
            raise ValidationError(f"pool {self.root} has no model {model_id}")
        from omniscs.agents.material import GaussianMaterial

        try:
            tensors = load_file(str(folder / GAUSSIANS))
            params = GaussianParams.from_dict(tensors)
            material = GaussianMaterial.from_dict(load_file(str(folder / MATERIAL))) \
                if (folder / MATERIAL).is_file() else None
            if material is not None and len(material) != len(params):
                raise ValidationError(f"material for {len(material)} Gaussians, model of {len(params)}")
            meta = read_own_json(folder / META, "add the model again", expect=dict, what="pool model record")
            return PoolModel(model_id, params, meta, material)
        except Exception as e:  # safetensors raises its own error type for a damaged file
            raise ValidationError(f"pool model {model_id} in {self.root} is damaged ({type(e).__name__}: {e})") from e

    def keyframes(self, model_id: str) -> np.ndarray:
        """uint8 [30, H, W, 4] RGBA views of the model around it at 12 degree steps (``agents.mesh.keyframes``)."""
        self.get(model_id)
        try:
            with np.load(self.folder(model_id) / KEYFRAMES) as z:
                return z["rgba"]
        except Exception as e:  # missing, truncated or not an npz
            raise ValidationError(f"pool model {model_id} in {self.root} has no readable keyframes ({KEYFRAMES}: "
                                  f"{type(e).__name__}); add the model again (omniscs pool import / build) or remove "
                                  "its folder") from None

    def import_ply(self, path: str | Path, category: str, calibrate: bool = True) -> str:
        """A 3D Gaussian splatting PLY (e.g. an image-to-3D generator's output) into the pool: read, turned and
        moved into the vehicle frame (``calibrate``; else taken as it is), added; returns its id."""
        from omniscs.agents.ply import read_gaussian_ply

        params = read_gaussian_ply(path)
        calibration = None
        if calibrate:
            params, calibration = calibrated(params, category)
        return self.add(params, category, "imported", str(Path(path).name), calibration=calibration)

    def import_mesh(self, path: str | Path, category: str, calibrate: bool = True, gaussians: int = 20_000,
                    refine_steps: int = 100) -> str:
        """A mesh trimesh reads (OBJ/MTL, GLB/glTF, PLY, STL, OFF; face or vertex colours, textures sampled per
        face, and the file's materials: ``agents.meshfile``) into the pool: centred, made into Gaussians
        (``agents.mesh.model_from_mesh``) that keep each face's material for relighting, turned into the vehicle
        frame (``calibrate``), added; returns its id."""
        from omniscs.agents.mesh import model_from_mesh
        from omniscs.agents.meshfile import read_mesh_file

        mesh = read_mesh_file(path)
        vertices = mesh.vertices - 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
        params, info = model_from_mesh(vertices, mesh.faces, mesh.colour, gaussians, refine_steps,
                                       face_specular=mesh.specular, face_shininess=mesh.shininess,
                                       face_albedo=mesh.albedo)
        calibration = None
        if calibrate:
            params, calibration = calibrated(params, category)
        return self.add(params, category, "imported", str(Path(path).name), quality=info["quality_psnr"],
                        calibration=calibration, build={**info["build"], "materials": sorted(set(mesh.materials))},
                        material=info["material"])

    def import_file(self, path: str | Path, category: str, calibrate: bool = True) -> str:
        """A 3D Gaussian splatting PLY (``import_ply``) or any mesh (``import_mesh``), told apart by content."""
        path = Path(path)
        if not path.is_file():
            raise ValidationError(f"{path} is not a file")
        if path.suffix.lower() == ".ply":
            head = path.read_bytes()[:4096]
            if b"f_dc_0" in head or b"property float opacity" in head:
                return self.import_ply(path, category, calibrate)
        return self.import_mesh(path, category, calibrate)

    def export_ply(self, model_id: str, path: str | Path) -> Path:
        from omniscs.agents.ply import write_gaussian_ply

        return write_gaussian_ply(self.get(model_id).params, path)


def calibrated(params: GaussianParams, category: str) -> tuple[GaussianParams, dict]:
    """``params`` moved into their vehicle frame by ``calibrate_points`` on the Gaussian centres (with their base
    colours), and what the calibration found."""
    from omniscs.agents.calibrate import calibrate_points
    from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET

    colours = np.clip(SH_COLOR_OFFSET + SH_C0 * params.sh_dc.detach().double().numpy(), 0.0, 1.0)
    cal = calibrate_points(params.means.detach().double().numpy(), category, colours)
    moved = rigidly_moved(params, cal.rotation, cal.translation)
    return moved, {"rotation": np.round(cal.rotation, 9).tolist(), "translation": np.round(cal.translation, 9).tolist(),
                   "fitness": cal.fitness, "heading_by": cal.heading_by}


def model_resolver(pool: str | Path, fallback=None):
    """An edit's asset-id resolver (``omniscs.nsg.edit.ModelResolver``) for pool model ids (``pm-...``) of ``pool``;
    other ids go to ``fallback`` (e.g. the graph's own ``nsg:<track>`` nodes)."""
    from omniscs.nsg.edit import AgentModel

    p = Pool(pool)

    def resolve(asset_id: str):
        if isinstance(asset_id, str) and asset_id.startswith("pm-"):
            model = p.get(asset_id)
            return AgentModel(model.params, np.maximum(np.asarray(model.meta["size"], np.float64), 1e-3),
                              model.meta["category"])
        if fallback is None:
            raise ValidationError(f"asset {asset_id!r} is not a pool model id (pm-...) of {p.root}")
        return fallback(asset_id)
    return resolve
