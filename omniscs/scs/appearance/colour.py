"""The scene's colour transform for inserted objects: how the scene's camera and light (exposure, white balance) turn
a pool model's colours into the colours this scene's images show.

Pool models carry the colours of their keyframes (one fixed light). The scene's own vehicles, matched to their
nearest pool models and put in their place, tell how the scene maps those colours: on the pixels where a vehicle is
what the camera saw, per vehicle the per-channel gain and bias that map its model's colours closest to the logged
ones (``omniscs.agents.dual.fit_colour_correction``), and the median over vehicles. On the development log
(straight:9001) this came closest to the oracle map (the same asset's pool model against its exact render: gains
0.48-0.65, biases 0.19-0.29): median 0.45 / 0.18-0.27; a moment match gave 0.57 / 0.13-0.20 and lost up to 2 dB; one
least-squares fit over every vehicle's pixels at once collapsed to the mean colour (gains near 0)."""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.taxonomy import VEHICLE_CATEGORIES

log = logging.getLogger(__name__)

IDENTITY = np.hstack([np.eye(3), np.zeros((3, 1))])


@dataclass(frozen=True)
class ColourFitConfig:
    """How the scene's colour transform is estimated."""

    max_vehicles: int = 4
    """Vehicle nodes used (the best seen: most pixels over their views)."""
    min_view_pixels: int = 600
    """A view of a vehicle counts when its box covers at least this many pixels."""
    views_per_vehicle: int = 4
    """The largest views of each vehicle used for its fit."""
    gain_range: tuple[float, float] = (0.4, 2.5)
    """Per-channel gains are clipped to this range (a wrong match must not turn colours inside out)."""
    bias_range: tuple[float, float] = (-0.3, 0.3)
    """Per-channel biases are clipped to this range (colours in 0..1)."""

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ColourTransform:
    """The scene's transform [A | b] ([3, 4]; A diagonal) and how it was found."""

    affine: np.ndarray
    vehicles: tuple[int, ...]
    per_vehicle: tuple[tuple[float, ...], ...]  # each vehicle's own (gain r, g, b, bias r, g, b), for inspection
    reason: str

    def to_dict(self) -> dict:
        return {"affine": np.round(self.affine, 6).tolist(), "vehicles": list(self.vehicles),
                "per_vehicle": [list(v) for v in self.per_vehicle], "reason": self.reason}


def scene_colour_transform(graph, scene, pool, frames=None, config: ColourFitConfig = ColourFitConfig(),
                           embedder=None) -> ColourTransform:
    """Estimate the scene's colour transform from its vehicle nodes and their nearest pool models (see the module).
    No vehicle node, no pool model of their categories, or no usable view: identity, with the reason."""
    from omniscs.agents.dual import (colour_samples, fit_colour_correction, largest_views, placed_candidate,
                                     query_crops, track_views)
    from omniscs.agents.matching import match_scores

    if pool is None:
        return ColourTransform(IDENTITY.copy(), (), (), "no model pool: colours unchanged")
    table = pool.table()
    if table.empty:
        return ColourTransform(IDENTITY.copy(), (), (), "the model pool is empty: colours unchanged")
    frames = list(range(scene.n_frames)) if frames is None else [int(f) for f in frames]
    seen = []
    for node in graph.agents:
        if node.category not in VEHICLE_CATEGORIES or node.category not in set(table.category):
            continue
        views = track_views(scene, node.track_id, frames, config.min_view_pixels)
        if views:
            seen.append((sum(v.pixels for v in views), node.track_id, views))
    seen = sorted(seen, key=lambda s: -s[0])[:config.max_vehicles]
    if not seen:
        return ColourTransform(IDENTITY.copy(), (), (), "no vehicle node seen well enough: colours unchanged")
    queries = {t: query_crops(graph, scene, t, views, config.views_per_vehicle) for _, t, views in seen}
    sizes = {t: np.asarray(graph.agent(t).size) for t in queries}
    try:
        tracks, models, scores, categories = match_scores(queries, sizes, pool, embedder)
    except OmniscsError as exc:  # e.g. a pool model whose keyframes are missing: no match, colours unchanged
        return ColourTransform(IDENTITY.copy(), (), (), f"pool models could not be matched ({exc}): colours unchanged")
    fits, used = [], []
    for i, t in enumerate(tracks):
        same = np.flatnonzero(categories == graph.agent(t).category)
        if not len(same):
            continue
        best = str(models[same[np.argmax(scores[i, same])]])
        views = dict((tid, v) for _, tid, v in seen)[t]
        samples = colour_samples(graph, scene, t, largest_views(views, config.views_per_vehicle))
        candidate = placed_candidate(pool, best, sizes[t], graph.sh_degree, graph.device)
        affine = fit_colour_correction(graph, t, candidate, samples)
        if np.allclose(affine, IDENTITY):  # too few pixels: the fit fell back to identity
            continue
        fits.append(np.concatenate([np.diag(affine[:, :3]), affine[:, 3]]))
        used.append(t)
    if not fits:
        return ColourTransform(IDENTITY.copy(), (), (), "no vehicle gave a colour fit: colours unchanged")
    median = np.median(np.stack(fits), 0)
    gains = np.clip(median[:3], *config.gain_range)
    bias = np.clip(median[3:], *config.bias_range)
    affine = np.hstack([np.diag(gains), bias[:, None]])
    if not np.all(np.isfinite(affine)):
        raise OmniscsError("the scene's colour transform is not finite")
    return ColourTransform(affine, tuple(used), tuple(tuple(float(x) for x in f) for f in fits),
                           f"median of {len(fits)} vehicle(s) fitted to their nearest pool models")
