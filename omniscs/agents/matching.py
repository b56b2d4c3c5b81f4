"""Matching degraded road users to pool models (the degradations a scene's agents suffer are in
``omniscs.agents.degradation``): the embedders that map a crop to a vector (hand-made baselines here; the trained
MSNet plugs in through the same ``Embedder`` interface), ranking against the pool's keyframes (embeddings cached per pool and embedder), appearance plus box shape, and the
one-to-one assignment (Hungarian, scipy) gated by category.

A pool model is represented by its 30 keyframes; a query's similarity to a model is the best cosine similarity
over that model's keyframes."""
from __future__ import annotations

import hashlib
import io
from typing import TYPE_CHECKING, Callable, Protocol

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from omniscs.agents.degradation import Degradation, degrade
from omniscs.agents.msnet import shipped_embedder
from omniscs.errors import ValidationError
from omniscs.storage import atomic_write_bytes

if TYPE_CHECKING:
    from omniscs.agents.pool import Pool

CROP = 64  # embedders see square crops of this many pixels


#: Resolutions the pool's keyframes are also embedded at: each as if seen this many times smaller than a sharp crop
#: (downsampled, then brought back to CROP), so that a query seen small is compared with keyframes as blurred as it
#: is. Chosen on two sets of 60 validation queries (other worlds than the benchmark's), shipped MSNet with box
#: shape, top-1 against full-resolution keyframes: x4 23 -> 35 % and 23 -> 32 %; x4 + 40 % occlusion +
#: illumination 22 -> 28 % and 15 -> 20 %.
GALLERY_SCALES = (1.0, 2.0, 4.0, 8.0)


def _square(alpha: np.ndarray | None) -> tuple[float, float, float] | None:
    """Centre (row, column) and half side of the square around the object (``alpha`` > 0.5, 2 pixels of margin);
    None without an object."""
    if alpha is None or not (alpha > 0.5).any():
        return None
    ys, xs = np.nonzero(alpha > 0.5)
    return (0.5 * (ys.min() + ys.max()), 0.5 * (xs.min() + xs.max()),
            0.5 * max(ys.max() - ys.min(), xs.max() - xs.min()) + 2)


def crop_square(rgb: np.ndarray, alpha: np.ndarray | None = None, size: int = CROP) -> np.ndarray:
    """The object's square crop (its alpha's bounding box, or the whole image), resized to ``size``."""
    square = _square(alpha)
    if square is not None:
        cy, cx, half = square
        y0, y1 = int(max(0, cy - half)), int(min(rgb.shape[0], cy + half + 1))
        x0, x1 = int(max(0, cx - half)), int(min(rgb.shape[1], cx + half + 1))
        rgb = rgb[y0:y1, x0:x1]
    return cv2.resize(rgb, (size, size), interpolation=cv2.INTER_AREA)


def crop_scale(rgb: np.ndarray, alpha: np.ndarray | None = None, size: int = CROP) -> float:
    """How many times smaller than a sharp ``size``-pixel crop ``crop_square`` sees the object: ``size`` over the
    side of the square it cuts (1 when that side is ``size`` pixels or more)."""
    side = float(max(rgb.shape[:2]))
    square = _square(alpha)
    if square is not None:
        side = min(2.0 * square[2], side)
    return max(1.0, size / max(side, 1.0))


def gallery_scale(scale: float) -> float:
    """The entry of GALLERY_SCALES nearest (in octaves) to a query seen ``scale`` times smaller than a sharp crop;
    1 for anything not finite or below 1."""
    s = float(scale) if np.isfinite(scale) and scale > 1.0 else 1.0
    return min(GALLERY_SCALES, key=lambda g: abs(np.log2(g) - np.log2(s)))


class Embedder(Protocol):
    name: str

    def embed(self, crops: np.ndarray) -> np.ndarray:  # uint8 [N, CROP, CROP, 3] -> float32 [N, D] unit rows
        ...


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


class ColourHistogram:
    """HSV histogram (8 hue x 4 saturation x 4 value bins), square-rooted."""

    name = "colour histogram"

    def embed(self, crops: np.ndarray) -> np.ndarray:
        out = []
        for c in crops:
            hsv = cv2.cvtColor(c, cv2.COLOR_RGB2HSV)
            hist = cv2.calcHist([hsv], [0, 1, 2], None, [8, 4, 4], [0, 180, 0, 256, 0, 256]).ravel()
            out.append(np.sqrt(hist / max(hist.sum(), 1.0)))
        return _unit(np.stack(out))


class HOG:
    """OpenCV's HOG on the grey crop (16 px cells, 9 orientations)."""

    name = "HOG"

    def __init__(self) -> None:
        self._hog = cv2.HOGDescriptor((CROP, CROP), (16, 16), (8, 8), (8, 8), 9)

    def embed(self, crops: np.ndarray) -> np.ndarray:
        return _unit(np.stack([self._hog.compute(cv2.cvtColor(c, cv2.COLOR_RGB2GRAY)).ravel() for c in crops]))


class RawPixels:
    """The crop at 16 x 16, mean-removed."""

    name = "raw pixels"

    def embed(self, crops: np.ndarray) -> np.ndarray:
        small = np.stack([cv2.resize(c, (16, 16), interpolation=cv2.INTER_AREA) for c in crops]).astype(np.float32)
        flat = small.reshape(len(small), -1)
        return _unit(flat - flat.mean(1, keepdims=True))


def model_scores(query: np.ndarray, gallery: np.ndarray, gallery_model: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[Q, M] best cosine similarity of each query to each model's keyframes, and the model ids' order [M]."""
    models = np.unique(gallery_model)
    sim = query @ gallery.T  # [Q, G]
    scores = np.full((len(query), len(models)), -np.inf, np.float32)
    for j, m in enumerate(models):
        scores[:, j] = sim[:, gallery_model == m].max(1)
    return scores, models


def top_k_accuracy(scores: np.ndarray, models: np.ndarray, truth: np.ndarray, ks=(1, 5)) -> dict[int, float]:
    """Share of queries whose true model is among the ``k`` best scored."""
    order = np.argsort(-scores, axis=1)
    ranked = models[order]
    return {k: float(np.mean([t in row[:k] for t, row in zip(truth, ranked)])) for k in ks}


def assign(scores: np.ndarray, query_categories: list[str], model_categories: list[str]) -> list[int | None]:
    """One pool model per query (index into the models), each model used at most once, only within a category
    (Hungarian on 1 - similarity); None where no model of the query's category is left."""
    if scores.shape != (len(query_categories), len(model_categories)):
        raise ValidationError("scores must be [queries, models] and match the category lists")
    big = 1e6
    cost = np.where(np.array(query_categories)[:, None] == np.array(model_categories)[None, :], 1.0 - scores, big)
    cost = np.nan_to_num(cost, nan=big, posinf=big, neginf=big)
    rows, cols = linear_sum_assignment(cost)
    out: list[int | None] = [None] * len(query_categories)
    for r, c in zip(rows, cols):
        if cost[r, c] < big:
            out[r] = int(c)
    return out


# ----------------------------------------------------------------------------- matching to a pool
def pool_gallery(pool: Pool, embedder: Embedder, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, "object"]:
    """The pool's keyframe embeddings [G, D], the model id of each [G] and the pool table; computed once per pool
    content, embedder and ``scale`` (one of GALLERY_SCALES: the keyframes seen that many times smaller), cached
    under ``<pool>/embeddings/``."""
    if scale not in GALLERY_SCALES:
        raise ValidationError(f"gallery scale must be one of {GALLERY_SCALES}, not {scale!r}")

    table = pool.table()
    if table.empty:
        return np.zeros((0, 1), np.float32), np.zeros(0, dtype=object), table
    ids = sorted(table.model_id)
    name = getattr(embedder, "cache_key", embedder.name)  # an embedder with weights names them
    digest = hashlib.sha256(("\n".join(ids) + "|" + name).encode()).hexdigest()[:16]
    suffix = "" if scale == 1.0 else f"-x{scale:g}"
    cache = pool.root / "embeddings" / f"{name.replace(' ', '_')}-{digest}{suffix}.npz"
    if cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            return z["emb"], z["model"].astype(object), table
    embs, owners = [], []
    for mid in ids:
        rgba = pool.keyframes(mid)
        crops = np.stack([crop_square(np.ascontiguousarray(k[..., :3]), k[..., 3] / 255.0) for k in rgba])
        if scale != 1.0:  # a pure downsampling: the generator is not drawn from
            crops = np.stack([degrade(c, Degradation(downsample=scale), np.random.default_rng(0)) for c in crops])
        embs.append(embedder.embed(crops))
        owners += [mid] * len(crops)
    emb, model = np.concatenate(embs).astype(np.float32), np.array(owners)
    buf = io.BytesIO()
    np.savez(buf, emb=emb, model=model.astype(str))
    atomic_write_bytes(cache, buf.getvalue())
    return emb, model.astype(object), table


def default_embedder() -> Embedder:
    """The shipped MSNet (``omniscs.agents.msnet.SHIPPED``), else the colour histogram."""
    return shipped_embedder() or ColourHistogram()


def best_per_model(embeddings: np.ndarray, gallery: np.ndarray, columns: np.ndarray, n_models: int) -> np.ndarray:
    """[Q, M] the best cosine similarity of each embedding [Q, D] to each model's keyframes (``gallery`` [G, D],
    ``columns`` [G]: each keyframe's model index); -1 for a model with none."""
    best = np.full((len(embeddings), n_models), -1.0)
    np.maximum.at(best.T, columns, (embeddings @ gallery.T).T)
    return best


def best_at_scales(embeddings: np.ndarray, scales: np.ndarray, gallery_at: Callable[[float], np.ndarray],
                   columns: np.ndarray, n_models: int) -> np.ndarray:
    """[Q, M] ``best_per_model`` with each embedding [Q, D] against the keyframes at the ``gallery_scale`` of its
    scale [Q] (``gallery_at``: a GALLERY_SCALES entry -> the keyframe embeddings [G, D] at it)."""
    at = np.array([gallery_scale(s) for s in scales])
    if len(at) != len(embeddings):
        raise ValidationError(f"{len(at)} scales for {len(embeddings)} crops")
    best = np.zeros((len(embeddings), n_models))
    for g in np.unique(at):
        best[at == g] = best_per_model(embeddings[at == g], gallery_at(float(g)), columns, n_models)
    return best


def match_scores(queries: dict[int, np.ndarray], sizes: dict[int, np.ndarray], pool: Pool,
                 embedder: Embedder | None = None, size_weight: float = 1.0,
                 scales: dict[int, np.ndarray] | None = None):
    """(tracks, model ids [M], similarity [T, M], model categories [M]) for the tracks that have crops: the mean
    over a track's crops of the best keyframe cosine similarity, less ``size_weight`` x mean |log size ratio|.
    ``scales`` (track -> one ``crop_scale`` per crop): each crop is compared with the keyframes at the nearest
    GALLERY_SCALES entry (none given: all at full resolution)."""
    embedder = embedder or default_embedder()
    galleries = {1.0: pool_gallery(pool, embedder)}
    _, owner, table = galleries[1.0]

    def gallery_at(g: float) -> np.ndarray:
        if g not in galleries:
            galleries[g] = pool_gallery(pool, embedder, g)
        return galleries[g][0]

    tracks = [t for t in queries if len(queries[t])]
    if not tracks or table.empty:
        return [], np.zeros(0, dtype=object), np.zeros((len(tracks), 0)), np.zeros(0, dtype=object)
    table = table.set_index("model_id")
    models = np.array(sorted(table.index))
    model_size = table.loc[models, ["length", "width", "height"]].to_numpy(np.float64)
    index = {m: j for j, m in enumerate(models)}
    cols = np.array([index[m] for m in owner])
    scores = np.zeros((len(tracks), len(models)))
    for i, t in enumerate(tracks):
        emb = embedder.embed(queries[t])  # [k, D]
        at = np.asarray(scales[t], np.float64) if scales is not None and t in scales else np.ones(len(emb))
        if len(at) != len(emb):
            raise ValidationError(f"track {t}: {len(at)} scales for {len(emb)} crops")
        best = best_at_scales(emb, at, gallery_at, cols, len(models))
        shape = np.abs(np.log(np.maximum(model_size, 1e-3) / np.maximum(sizes[t], 1e-3)[None])).mean(1)
        scores[i] = best.mean(0) - size_weight * shape
    return tracks, models, scores, table.loc[models, "category"].to_numpy()


def match_tracks(queries: dict[int, np.ndarray], sizes: dict[int, np.ndarray], categories: dict[int, str],
                 pool: Pool, embedder: Embedder | None = None,
                 size_weight: float = 1.0, scales: dict[int, np.ndarray] | None = None) -> dict[int, tuple[str, float]]:
    """Each track (its crops, box size and category) assigned to its own pool model by ``match_scores``; one model
    per track, within its category (Hungarian). Tracks without crops or without a model of their category are
    left out. Returns track -> (model id, distance = 1 - similarity)."""
    tracks, models, scores, model_cats = match_scores(queries, sizes, pool, embedder, size_weight, scales)
    if not tracks or not len(models):
        return {}
    picked = assign(scores, [categories[t] for t in tracks], list(model_cats))
    return {t: (str(models[j]), float(1.0 - scores[i, j])) for i, (t, j) in enumerate(zip(tracks, picked))
            if j is not None}
