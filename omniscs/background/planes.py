"""Planar proxies of what a removed object hid: the road, the sidewalk and the facades behind it are planes, and
their texture can be gathered from every view and inpainted once, on the plane itself.

What stands behind a parked truck in a street is mostly flat: the carriageway, the raised sidewalk, a facade.
The planes are found with RANSAC (open3d) among the LiDAR returns around the object (outside its box), or among
the background's Gaussian centres where a log has no LiDAR. A hole pixel takes the nearest plane its ray meets
behind the object's front, within that plane's support (the convex hull of its inliers) and not where the training
views see through the plane (FreeSpace): an exact depth where the world is flat, in place of a monocular estimate.

Each plane gets a texture (texels ``texel_m`` on a side, in the plane's own 2D coordinates) over the part of it
the hole pixels see, plus a ring of context. Every training view gives colour to the texels it sees (inside the
image, outside its own hole, with nothing its render shows in front of the texel); each texel takes the per-channel
median of the colours it got, which keeps what most views agree on. What no view saw is filled on the texture,
where the kerb lines and the rows of windows run straight: first along the street (the removed object's heading:
a parked vehicle stands along the kerb), from the seen texels on the same line (or, as an option, by copying the
seen texels whole periods away where the texture repeats), then by the inpainter. Every view then reads the same
texture: one consistent fill for all views.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from omniscs.background.holes import RemovedObject, lift_pixels, pixel_rays
from omniscs.errors import OmniscsError
from omniscs.geometry import invert_transform, points_in_box, transform_points
from omniscs.nsg.observations import View, project_points

log = logging.getLogger(__name__)

#: Points around the object that can carry its planes: this many metres beyond its box sideways and lengthwise,
#: from a metre below its bottom to this many metres above its top.
REGION_MARGIN_M = 8.0
REGION_ABOVE_M = 6.0

#: Points inside the object's box grown by this factor belong to the object, not to its surroundings.
OBJECT_GROW = 1.05


@dataclass(frozen=True)
class PlaneConfig:
    """How planes are found and textured."""

    distance_m: float = 0.05
    """RANSAC inlier distance."""
    voxel_m: float = 0.1
    """The region's points are thinned to one per voxel of this size first (even density near and far)."""
    max_planes: int = 6
    """Planes are taken one after another from what is left, up to this many."""
    min_share: float = 0.03
    """A plane needs at least this share of the region's (thinned) points ..."""
    min_points: int = 100
    """... and at least this many."""
    iterations: int = 2_000
    """RANSAC iterations per plane."""
    texel_m: float = 0.04
    """Texture resolution on the plane."""
    context_m: float = 2.0
    """The texture covers the hole's hits on the plane plus this much around them (the inpainter's context)."""
    max_texels: int = 1_000_000
    """Texels per plane at most (the texel grows for very large extents)."""
    visible_tolerance: float = 0.05
    """A view sees a texel where its solid background's depth is within this share of the texel's depth."""
    seed: int = 0
    """open3d's RANSAC seed (the planes are the same from run to run)."""
    free_space: bool = True
    """A hit is refused where the training views see through it: a plane's convex support can reach where the
    plane is not (a wall across the street, the sidewalk's level over the road), and views that see what lies
    behind such a point show it empty. The ray then goes on to the next plane it meets."""
    free_cell_m: float = 0.25
    """Hits are checked per cell of this size on the plane."""
    free_tolerance: float = 0.1
    """A view sees through a point where its solid surface lies beyond the point by more than this share of the
    point's depth (or it sees nothing there at all), and sees the point where the two agree within
    ``visible_tolerance``."""
    free_votes: int = 2
    """A cell is empty where at least this many views see through it and more see through it than see it."""
    texel_colour: str = "median"
    """A texel seen by several views takes their per-channel 'median' colour (robust to what one view alone shows
    there) or the 'nearest' one's (the finest; the default until the eighth session of 2026-11-27)."""
    unobserved: str = "street"
    """How texels no view saw are filled before the inpainter: 'periodic' (where the seen texture repeats along the
    street, street_period, each takes the median of the seen texels whole periods away on its line; the rest as
    'street'), 'street' (each takes the per-channel median of the
    observed texels nearest it on its line along the street, the removed object's heading on the plane, within
    ``street_reach_m``: kerbs, lane lines, paving and rows of windows run along the street; what has no observed
    texel on its line is left to the inpainter) or 'inpaint' (the inpainter fills them all: the default until the
    ninth session of 2026-11-27). Chosen on the development logs 90 and 91, hole PSNR at novel views 17.99 -> 18.05
    and 20.09 -> 20.57 dB (12 samples per side: 18.06 / 20.61; 100 with 6 m of texture context: 18.23 / 20.44).
    The medians also carry the shadows that lie along the street next to the object (its own included) into what
    they fill. 'periodic' (tried in the fifteenth session of 2026-11-28, not the default): on the development logs
    90, 91, 93 and 94 hole PSNR at novel views 17.29 -> 18.20, 20.79 -> 20.86, 17.97 -> 17.98 and 18.13 -> 18.05 dB
    (log 90's unseen sidewalk and facade, 13.5 and 17.2 dB, went to 16.1 and 19.0), but on the held-out logs
    101-105 19.62 against 19.82 dB (1.0 dB worse on log 103; docs/design-notes.md, background repair)."""
    period_min_m: float = 1.0
    """'periodic': the shortest shift along the street searched for the texture's period ..."""
    period_max_m: float = 8.0
    """... and the longest (rows of windows, paving slabs, parking bays repeat within this)."""
    period_contrast: float = 0.6
    """'periodic': a shift is the texture's period only where the observed texels differ from their copies that
    far along the street by less than this share of the median difference over all the shifts searched."""
    period_copies: int = 3
    """'periodic': an unobserved texel takes the per-channel median of this many observed texels whole periods
    away along the street (the nearest ones)."""
    street_reach_m: float = 12.0
    """How far along its line a texel looks for observed ones."""
    street_samples: int = 100
    """At most this many observed texels on each side (the nearest ones) give a texel its median."""
    texel_visibility: str = "unoccluded"
    """When a view sees a texel: 'unoccluded' (nothing its render shows lies in front of the texel, outside its
    own hole) or 'agree' (its solid background's depth agrees with the texel's within ``visible_tolerance``: the
    default until the eighth session of 2026-11-27, which left most texels unobserved, since the fitted
    background behind a large object is seldom solid at the right depth). Chosen with ``texel_colour`` and
    ``free_space`` on the development logs 90 and 91: hole PSNR at novel views 16.82 -> 17.99 and 19.58 -> 20.09 dB
    (visibility alone +1.04 / +0.28, the median +0.19 / +0.23, the free-space check -0.06 on log 90)."""

    def __post_init__(self) -> None:
        if self.texel_colour not in ("median", "nearest"):
            raise OmniscsError(f"unknown texel_colour {self.texel_colour!r}; use 'median' or 'nearest'")
        if self.texel_visibility not in ("unoccluded", "agree"):
            raise OmniscsError(f"unknown texel_visibility {self.texel_visibility!r}; use 'unoccluded' or 'agree'")
        if self.unobserved not in ("periodic", "street", "inpaint"):
            raise OmniscsError(f"unknown unobserved {self.unobserved!r}; use 'periodic', 'street' or 'inpaint'")
        if not (0.0 < self.period_min_m < self.period_max_m and 0.0 < self.period_contrast <= 1.0
                and self.period_copies >= 1):
            raise OmniscsError(f"bad period search: need 0 < period_min_m ({self.period_min_m}) < period_max_m "
                               f"({self.period_max_m}), 0 < period_contrast ({self.period_contrast}) <= 1 and "
                               f"period_copies ({self.period_copies}) >= 1")


@dataclass
class Plane:
    """n . x + d = 0 (unit n, world frame), with 2D coordinates (u, v) on it and its support polygon."""

    normal: np.ndarray   # [3]
    offset: float
    u: np.ndarray        # [3] unit, in the plane
    v: np.ndarray        # [3] unit, in the plane
    hull: np.ndarray     # [K, 2] convex polygon of the inliers in (u, v), counter-clockwise
    inliers: int
    street: np.ndarray | None = None  # [3] unit world direction along which the surface runs straight, if known

    def coords(self, points: np.ndarray) -> np.ndarray:  # [N, 3] -> [N, 2]
        return np.stack([points @ self.u, points @ self.v], axis=1)

    def point(self, uv: np.ndarray) -> np.ndarray:  # [N, 2] -> [N, 3] on the plane
        return (-self.offset * self.normal)[None] + uv[:, :1] * self.u[None] + uv[:, 1:2] * self.v[None]

    def supports(self, uv: np.ndarray) -> np.ndarray:  # [N, 2] -> [N] bool: inside the convex hull
        inside = np.ones(len(uv), bool)
        k = len(self.hull)
        for i in range(k):
            a, b = self.hull[i], self.hull[(i + 1) % k]
            inside &= (b[0] - a[0]) * (uv[:, 1] - a[1]) - (b[1] - a[1]) * (uv[:, 0] - a[0]) >= -1e-9
        return inside


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def region_points(points: np.ndarray, obj: RemovedObject) -> np.ndarray:
    """The world ``points`` [N, 3] around ``obj`` (REGION_MARGIN_M, REGION_ABOVE_M) and outside its box."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pose, size = obj.roi()[0], obj.size
    local = transform_points(invert_transform(pose), points)
    half = 0.5 * size
    near = ((np.abs(local[:, 0]) < half[0] + REGION_MARGIN_M) & (np.abs(local[:, 1]) < half[1] + REGION_MARGIN_M)
            & (local[:, 2] > -half[2] - 1.0) & (local[:, 2] < half[2] + REGION_ABOVE_M))
    near &= np.isfinite(points).all(axis=1)
    near &= ~points_in_box(points, pose, size * OBJECT_GROW)
    return points[near]


def fit_planes(points: np.ndarray, config: PlaneConfig = PlaneConfig(),
               street: np.ndarray | None = None) -> list[Plane]:
    """Planes among ``points`` [N, 3] (world), largest first; [] when none has enough inliers. ``street`` (a world
    direction, e.g. a parked vehicle's heading) is kept on each plane for filling its unobserved texels."""
    import open3d as o3d

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < max(3, config.min_points):
        return []
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(config.voxel_m)
    total = len(cloud.points)
    need = max(config.min_points, int(np.ceil(config.min_share * total)))
    o3d.utility.random.seed(config.seed)
    planes: list[Plane] = []
    rest = cloud
    while len(planes) < config.max_planes and len(rest.points) >= need:
        model, inliers = _segment_plane(rest, config)
        inliers = np.asarray(inliers, dtype=np.int64)
        if len(inliers) < need:
            break
        pts = np.asarray(rest.points)[inliers]
        rest = rest.select_by_index(inliers.tolist(), invert=True)
        n = np.asarray(model[:3], dtype=np.float64)
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm < 1e-9:
            continue
        n, d = n / norm, float(model[3]) / norm
        u, v = _basis(n)
        uv = np.stack([pts @ u, pts @ v], axis=1)
        try:
            hull = uv[ConvexHull(uv).vertices]  # counter-clockwise in 2D
        except QhullError:  # inliers on a line: no area to support a hit
            continue
        planes.append(Plane(n, d, u, v, hull, len(inliers), street))
    return planes


def _segment_plane(cloud, config: PlaneConfig):
    """open3d's RANSAC on one thread: its threads race to report the best plane, so with several the same seed
    can give a different plane now and then (1 run in 30 on the background tests' log)."""
    import open3d as o3d

    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        return cloud.segment_plane(config.distance_m, 3, config.iterations)
    finally:
        o3d.utility.set_max_threads(threads)


def plane_hits(view: View, mask: np.ndarray, planes: list[Plane], entry: np.ndarray,
               behind_share: float = 0.9, empty=None) -> tuple[np.ndarray, np.ndarray]:
    """For the ``mask`` pixels of ``view``: the distance to the camera centre at which the ray meets the nearest
    plane, within the plane's support and beyond ``behind_share`` of ``entry`` (the z-depth where the ray enters
    the object's box: what the object hid lies behind its front), and which plane; NaN / -1 where none.
    ``empty(k, points [M, 3]) -> [M] bool`` (FreeSpace) refuses hits where plane ``k`` is not."""
    h, w = mask.shape
    dist = np.full((h, w), np.nan, np.float32)
    which = np.full((h, w), -1, np.int64)
    if not planes or not mask.any():
        return dist, which
    rays = pixel_rays(view)[mask]
    zscale = np.linalg.norm(rays, axis=1)
    dirs = rays / zscale[:, None]
    origin = view.world_from_camera[:3, 3]
    best = np.full(len(dirs), np.inf)
    best_k = np.full(len(dirs), -1)
    floor = behind_share * np.where(np.isfinite(entry[mask]), entry[mask], 0.0) * zscale
    for k, p in enumerate(planes):
        den = dirs @ p.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(origin @ p.normal + p.offset) / np.where(np.abs(den) > 1e-9, den, np.nan)
        ok = np.isfinite(t) & (t > floor) & (t < best)
        if ok.any():
            idx = np.flatnonzero(ok)
            hit = origin[None] + dirs[idx] * t[idx, None]
            keep = p.supports(p.coords(hit))
            if empty is not None and keep.any():
                keep[keep] = ~empty(k, hit[keep])
            idx = idx[keep]
            best[idx], best_k[idx] = t[idx], k
    found = np.isfinite(best)
    d = np.where(found, best, np.nan)
    dist[mask], which[mask] = d.astype(np.float32), np.where(found, best_k, -1)
    return dist, which


@dataclass
class Donor:
    """A training view lending colour: its image, its solid background's z-depth (inf where not solid or where
    its own hole is) at the working resolution, and where it shows nothing at all (the sky; None: unknown)."""

    view: View
    image: np.ndarray     # [h, w, 3] uint8
    solid_z: np.ndarray   # [h, w] float
    shows_nothing: np.ndarray | None = None  # [h, w] bool
    near_z: np.ndarray | None = None  # [h, w] z-depth of the first thing it shows (0 in its own hole, inf: nothing);
    #                                    None: texels are seen by the 'agree' rule


class FreeSpace:
    """Where the training views (``donors``) see through points of the planes: per plane, cells of
    ``free_cell_m`` checked once and remembered. ``empty(k, points)`` says which points of plane ``k`` lie in
    space that at least ``free_votes`` views see through (solid surface well beyond the point, or nothing at all
    outside the views' own holes) and that more views see through than see (surface at the point's depth)."""

    def __init__(self, planes: list[Plane], donors: list[Donor], config: PlaneConfig = PlaneConfig()) -> None:
        self.planes, self.donors, self.config = planes, donors, config
        self.known: list[dict[tuple[int, int], bool]] = [{} for _ in planes]

    def _votes(self, points: np.ndarray) -> np.ndarray:  # [M, 3] -> [M] bool empty
        c = self.config
        free = np.zeros(len(points), np.int64)
        seen = np.zeros(len(points), np.int64)
        for dn in self.donors:
            uv, z, inside = project_points(dn.view, points)
            idx = np.flatnonzero(inside)
            if not len(idx):
                continue
            px = np.floor(uv[idx]).astype(np.int64)
            solid = dn.solid_z[px[:, 1], px[:, 0]]
            zz = z[idx]
            nothing = (dn.shows_nothing[px[:, 1], px[:, 0]] if dn.shows_nothing is not None
                       else np.zeros(len(idx), bool))
            free[idx] += (np.isfinite(solid) & (solid > zz * (1.0 + c.free_tolerance))) | nothing
            seen[idx] += np.isfinite(solid) & (np.abs(solid - zz) <= c.visible_tolerance * zz)
        return (free >= c.free_votes) & (free > seen)

    def empty(self, k: int, points: np.ndarray) -> np.ndarray:
        plane, cell = self.planes[k], self.config.free_cell_m
        ij = np.floor(plane.coords(points) / cell).astype(np.int64)
        keys, inverse = np.unique(ij, axis=0, return_inverse=True)
        known = self.known[k]
        todo = [i for i, key in enumerate(map(tuple, keys)) if key not in known]
        if todo:
            centres = (keys[todo] + 0.5) * cell
            flags = self._votes(plane.point(centres))
            for i, f in zip(todo, flags):
                known[tuple(keys[i])] = bool(f)
        flags = np.array([known[tuple(key)] for key in keys], bool)
        return flags[inverse.reshape(-1)]


@dataclass
class PlaneTexture:
    """A plane's texture: texel (i, j) is centred at uv0 + ((j + 0.5), (i + 0.5)) * texel."""

    plane: Plane
    uv0: np.ndarray       # [2]
    texel: float
    rgb: np.ndarray       # [H, W, 3] uint8
    observed: np.ndarray  # [H, W] bool: some view saw the texel
    needed: np.ndarray    # [H, W] bool: a hole pixel reads it

    def lookup(self, uv: np.ndarray) -> np.ndarray:  # [N, 2] -> [N, 3] uint8, bilinear
        h, w = self.rgb.shape[:2]
        x = (uv[:, 0] - self.uv0[0]) / self.texel - 0.5
        y = (uv[:, 1] - self.uv0[1]) / self.texel - 0.5
        x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 1)
        y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 1)
        x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
        fx = np.clip(x - x0, 0.0, 1.0)[:, None]
        fy = np.clip(y - y0, 0.0, 1.0)[:, None]
        c = self.rgb.astype(np.float64)
        out = ((c[y0, x0] * (1 - fx) + c[y0, x1] * fx) * (1 - fy) + (c[y1, x0] * (1 - fx) + c[y1, x1] * fx) * fy)
        return np.clip(np.round(out), 0, 255).astype(np.uint8)


def build_textures(planes: list[Plane], hits: list[tuple[View, np.ndarray, np.ndarray]], donors: list[Donor],
                   inpainter, config: PlaneConfig = PlaneConfig()) -> list[PlaneTexture | None]:
    """One texture per plane that a hole pixel hits (None for the others): ``hits`` are (view, distance, which)
    from plane_hits; every donor colours the texels it sees; the rest is inpainted with ``inpainter``."""
    out: list[PlaneTexture | None] = []
    for k, plane in enumerate(planes):
        uvs = [plane.coords(lift_pixels(v, w == k, d)) for v, d, w in hits if (w == k).any()]
        if not uvs:
            out.append(None)
            continue
        uv = np.concatenate(uvs)
        lo, hi = uv.min(axis=0) - config.context_m, uv.max(axis=0) + config.context_m
        texel = max(config.texel_m, float(np.sqrt(np.prod(hi - lo) / config.max_texels)))
        w, h = (np.ceil((hi - lo) / texel).astype(np.int64) + 1).tolist()
        jj, ii = np.meshgrid(np.arange(w), np.arange(h))
        centres = np.stack([lo[0] + (jj.ravel() + 0.5) * texel, lo[1] + (ii.ravel() + 0.5) * texel], axis=1)
        pts = plane.point(centres)
        rgb = np.zeros((h * w, 3), np.uint8)
        best = np.full(h * w, np.inf)
        samples: list[tuple[np.ndarray, np.ndarray]] = []
        for dn in donors:
            uvp, z, inside = project_points(dn.view, pts)
            idx = np.flatnonzero(inside)
            if not len(idx):
                continue
            px = np.floor(uvp[idx]).astype(np.int64)
            if config.texel_visibility == "unoccluded" and dn.near_z is not None:
                ok = dn.near_z[px[:, 1], px[:, 0]] >= (1.0 - config.visible_tolerance) * z[idx]
            else:
                solid = dn.solid_z[px[:, 1], px[:, 0]]
                ok = np.isfinite(solid) & (np.abs(z[idx] - solid) <= config.visible_tolerance * z[idx])
            if config.texel_colour == "median":
                samples.append((idx[ok], dn.image[px[ok, 1], px[ok, 0]]))
                best[idx[ok]] = np.minimum(best[idx[ok]], z[idx[ok]])
                continue
            ok &= z[idx] < best[idx]
            idx, px = idx[ok], px[ok]
            best[idx] = z[idx]
            rgb[idx] = dn.image[px[:, 1], px[:, 0]]
        if samples:
            rgb = _median_colours(samples, h * w)
        observed = np.isfinite(best).reshape(h, w)
        rgb = rgb.reshape(h, w, 3)
        needed = np.zeros((h, w), bool)
        x = np.clip(((uv[:, 0] - lo[0]) / texel).astype(np.int64), 0, w - 1)
        y = np.clip(((uv[:, 1] - lo[1]) / texel).astype(np.int64), 0, h - 1)
        needed[y, x] = True
        if (~observed).any() and observed.any():
            known = observed
            if config.unobserved == "periodic" and plane.street is not None:
                rgb, known = periodic_fill(rgb, observed, plane, lo, texel, config)
                rgb, known = street_fill(rgb, known, plane, lo, texel, config)
            elif config.unobserved == "street" and plane.street is not None:
                rgb, known = street_fill(rgb, observed, plane, lo, texel, config)
            if (~known).any():
                rgb = inpainter.inpaint(rgb, ~known)
        elif not observed.any():
            out.append(None)  # nothing seen anywhere on it: no texture to continue
            continue
        out.append(PlaneTexture(plane, lo, texel, rgb, observed, needed))
    return out


def _street_along(plane: Plane) -> np.ndarray | None:
    """The street direction in the plane's 2D coordinates (unit), None where the plane has none or the street
    crosses the plane more than it runs along it (a wall across the street)."""
    if plane.street is None:
        return None
    along = np.array([plane.street @ plane.u, plane.street @ plane.v], dtype=np.float64)
    norm = float(np.linalg.norm(along))
    if not np.isfinite(norm) or norm < 0.5:
        return None
    return along / norm


def _shift(a: np.ndarray, di: int, dj: int, fill) -> np.ndarray:
    """``a`` read at (i + di, j + dj) (``fill`` outside)."""
    h, w = a.shape[:2]
    out = np.full_like(a, fill)
    ys, yd = slice(max(0, di), min(h, h + di)), slice(max(0, -di), min(h, h - di))
    xs, xd = slice(max(0, dj), min(w, w + dj)), slice(max(0, -dj), min(w, w - dj))
    if ys.start < ys.stop and xs.start < xs.stop:
        out[yd, xd] = a[ys, xs]
    return out


def street_period(rgb: np.ndarray, observed: np.ndarray, along: np.ndarray, texel: float,
                  config: PlaneConfig = PlaneConfig()) -> float | None:
    """The shift along the street (m) under which the observed texture repeats best (rows of windows, paving),
    or None when no shift stands out from the others."""
    col = rgb.astype(np.float32)
    shifts = np.arange(config.period_min_m, config.period_max_m + 1e-9, texel)
    scores = np.full(len(shifts), np.nan)
    for n, d in enumerate(shifts):
        di, dj = int(round(d * along[1] / texel)), int(round(d * along[0] / texel))
        both = observed & _shift(observed, di, dj, False)
        if both.sum() < 500:
            continue
        scores[n] = float(np.abs(col - _shift(col, di, dj, 0.0)).sum(-1)[both].mean())
    if not np.isfinite(scores).any():
        return None
    best = float(np.nanmin(scores))
    if not best < config.period_contrast * float(np.nanmedian(scores)):
        return None
    return float(shifts[np.flatnonzero(scores <= 1.05 * best)[0]])


def periodic_fill(rgb: np.ndarray, observed: np.ndarray, plane: Plane, uv0: np.ndarray, texel: float,
                  config: PlaneConfig = PlaneConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Unobserved texels copied from the observed ones whole periods away along the street (the per-channel median
    of the ``period_copies`` nearest), where the texture repeats (street_period)."""
    along = _street_along(plane)
    if along is None or observed.all() or not observed.any():
        return rgb, observed
    period = street_period(rgb, observed, along, texel, config)
    log.debug("plane texture period along the street: %s", period)
    if period is None:
        return rgb, observed
    col = rgb.astype(np.float32)
    col[~observed] = np.nan
    ks = [k for n in range(1, int(config.street_reach_m // period) + 1) for k in (n, -n)]
    stack = np.stack([_shift(col, int(round(k * period * along[1] / texel)), int(round(k * period * along[0] / texel)),
                             np.nan) for k in ks])                                     # [K, H, W, 3]
    valid = np.isfinite(stack[..., 0])
    stack[np.cumsum(valid, axis=0) > config.period_copies] = np.nan
    todo = ~observed & valid.any(axis=0)
    out = rgb.copy()
    out[todo] = np.clip(np.round(np.nanmedian(stack[:, todo], axis=0)), 0, 255).astype(np.uint8)
    return out, observed | todo


def street_fill(rgb: np.ndarray, observed: np.ndarray, plane: Plane, uv0: np.ndarray, texel: float,
                config: PlaneConfig = PlaneConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Unobserved texels of a texture ([H, W, 3] uint8, [H, W] observed) filled along the plane's street direction:
    each takes the per-channel median of the ``street_samples`` observed texels nearest it on either side on its
    line (a band one texel wide across it), within ``street_reach_m``. Returns the texture and which texels
    now have a colour. A plane the street direction does not run along (a wall across the street) is left as it
    is."""
    along = _street_along(plane)
    if along is None or observed.all() or not observed.any():
        return rgb, observed
    across = np.array([-along[1], along[0]])
    h, w = observed.shape
    ii, jj = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    uv = np.stack([uv0[0] + (jj.ravel() + 0.5) * texel, uv0[1] + (ii.ravel() + 0.5) * texel], axis=1)
    s, line = uv @ along, np.floor(uv @ across / texel).astype(np.int64)
    seen = observed.ravel()
    flat = rgb.reshape(-1, 3)
    out, known = flat.copy(), seen.copy()
    k = max(1, int(config.street_samples))
    # observed texels sorted by (line, s); each unobserved texel reads the k nearest on both sides of its line
    obs_idx = np.flatnonzero(seen)
    order = obs_idx[np.lexsort((s[obs_idx], line[obs_idx]))]
    o_line, o_s = line[order], s[order]
    todo = np.flatnonzero(~seen)
    first = np.searchsorted(o_line, line[todo], side="left")
    last = np.searchsorted(o_line, line[todo], side="right")
    span = float(s.max() - s.min()) + 1.0
    o_key = (o_line - line.min()) * span + (o_s - s.min())  # increasing: lines one after another, s within each
    pos = np.searchsorted(o_key, (line[todo] - line.min()) * span + (s[todo] - s.min()))
    offsets = np.arange(-k, k)
    cand = pos[:, None] + offsets[None, :]                                  # [T, 2k]
    valid = (cand >= first[:, None]) & (cand < last[:, None])
    cand = np.clip(cand, 0, len(order) - 1)  # some texel is seen (checked above): order is not empty
    valid &= np.abs(o_s[cand] - s[todo][:, None]) <= config.street_reach_m
    has = np.flatnonzero(valid.any(axis=1))
    for part in np.array_split(has, max(1, len(has) // 100_000)):  # bounded memory on large textures
        cols = flat[order[cand[part]]].astype(np.float32)                   # [T', 2k, 3]
        cols[~valid[part]] = np.nan
        out[todo[part]] = np.clip(np.round(np.nanmedian(cols, axis=1)), 0, 255).astype(np.uint8)
        known[todo[part]] = True
    return out.reshape(h, w, 3), known.reshape(h, w)


def _median_colours(samples: list[tuple[np.ndarray, np.ndarray]], n: int) -> np.ndarray:
    """Per texel (0..n-1), the per-channel median of the colours the views gave it ([n, 3] uint8, 0 where none)."""
    idx = np.concatenate([i for i, _ in samples])
    cols = np.concatenate([c for _, c in samples])
    out = np.zeros((n, 3), np.uint8)
    counts = np.bincount(idx, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    for ch in range(3):
        order = np.lexsort((cols[:, ch], idx))
        out[has, ch] = cols[order, ch][starts[has] + counts[has] // 2]
    return out


def texture_colours(view: View, dist: np.ndarray, which: np.ndarray,
                    textures: list[PlaneTexture | None]) -> tuple[np.ndarray, np.ndarray]:
    """Colour [h, w, 3] uint8 of the pixels whose plane has a texture, and where that is [h, w] bool."""
    h, w = dist.shape
    colour = np.zeros((h, w, 3), np.uint8)
    done = np.zeros((h, w), bool)
    for k, tex in enumerate(textures):
        if tex is None or not (which == k).any():
            continue
        sel = which == k
        colour[sel] = tex.lookup(tex.plane.coords(lift_pixels(view, sel, dist)))
        done |= sel
    return colour, done

