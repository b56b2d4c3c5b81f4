"""Open-loop planning metrics as UniAD reports them (its ``PlanningMetric``), on 6 waypoints at 0.5 s:

- **Frame**: UniAD's LiDAR frame (x to the ego's right, y forward, origin at the LiDAR); planned and true waypoints
  are the LiDAR origin's future positions in the frame of the current keyframe.
- **L2** per step: sqrt of the masked squared error (a step whose truth is unknown adds 0), averaged over every
  sample.
- **Collision** (``obj_box_col``) per step: the ego's box (1.85 m wide, 4.084 m long, centred 0.5 m ahead of the
  waypoint, axis-aligned: UniAD does not turn it with the heading) drawn on the 200 x 200 BEV grid at 0.5 m
  (x and y in [-50, 50] m; rows along y, columns along x) of that step's vehicle occupancy; a collision when any of
  its cells is occupied. Steps where the true trajectory itself collides are left out of the count (not of the
  denominator, which is every sample). The box covers the 8 x 4 cells whose centres lie inside it, moved by the
  waypoint and truncated to cells as UniAD does; cells off the grid are clamped to its border.
- **Known steps**: ``obj_box_col_known`` divides each step's collisions by the samples whose truth is known at
  that step (``known_per_step``) rather than by every sample; the two agree when every future is whole. Not one of
  UniAD's numbers: it reads sets of keyframes near a scenario's end, whose later steps are masked out.
- **Horizons**: 1 / 2 / 3 s under both conventions UniAD's results have been reported in: ``"uniad"`` (the value
  at that step) and ``"stp3"`` (the mean of the steps up to it, as ST-P3 and VAD report).

Occupancy: vehicle boxes (nuScenes ``vehicle.*``) of each future keyframe in the current frame, a cell occupied
when its centre lies inside a box's footprint (UniAD fills the box polygons of its occupancy labels the same way).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omniscs.errors import ValidationError

STEPS = 6
STEP_S = 0.5
#: The BEV grid: bounds (m) and cell size on both axes.
GRID_MIN, GRID_MAX, CELL = -50.0, 50.0, 0.5
GRID = int(round((GRID_MAX - GRID_MIN) / CELL))
#: UniAD's ego box (m) and how far its centre lies ahead of the waypoint.
EGO_WIDTH, EGO_LENGTH, EGO_SHIFT = 1.85, 4.084, 0.5
#: Horizons (s) and the step index each reads.
HORIZONS = {"1s": 1, "2s": 3, "3s": 5}
CONVENTIONS = ("uniad", "stp3")


def frames_for_planning(frame_rate_hz: float) -> int:
    """Frames a log recorded at ``frame_rate_hz`` needs for one keyframe with the whole future the metrics read
    (``STEPS`` waypoints ``STEP_S`` apart after it): 31 at 10 Hz. Each further evaluated keyframe needs ``STEP_S``
    more."""
    if not (frame_rate_hz > 0):
        raise ValidationError(f"frame rate must be positive; got {frame_rate_hz}")
    return int(round(STEPS * STEP_S * frame_rate_hz)) + 1


def _index(p: np.ndarray) -> np.ndarray:
    """Continuous grid index of a coordinate: cell k has its centre at GRID_MIN + (k + 0.5) CELL."""
    return (p - (GRID_MIN + 0.5 * CELL)) / CELL


def ego_cells() -> np.ndarray:  # [M, 2] int (row, column) with the ego's waypoint at the origin
    """The cells whose centres lie inside the ego box (row along y/forward, column along x/right)."""
    r0, r1 = _index(np.array([-EGO_LENGTH / 2 + EGO_SHIFT, EGO_LENGTH / 2 + EGO_SHIFT]))
    c0, c1 = _index(np.array([-EGO_WIDTH / 2, EGO_WIDTH / 2]))
    rows = np.arange(int(np.floor(r0)) + 1, int(np.ceil(r1)))
    cols = np.arange(int(np.floor(c0)) + 1, int(np.ceil(c1)))
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    return np.stack([rr.ravel(), cc.ravel()], 1)


def occupancy(boxes: np.ndarray) -> np.ndarray:  # [B, 5] x, y, length, width, yaw (rad from +x) -> bool [GRID, GRID]
    """Cells of UniAD's grid whose centres lie inside any box footprint (planning frame)."""
    centres = GRID_MIN + (np.arange(GRID) + 0.5) * CELL
    return footprints_on_grid(boxes, centres, centres)


def footprints_on_grid(boxes: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:  # -> bool [len(ys), len(xs)]
    """Cells (centres ``xs`` along columns, ``ys`` along rows, both increasing) inside any box footprint."""
    grid = np.zeros((len(ys), len(xs)), bool)
    for x, y, length, width, yaw in np.asarray(boxes, np.float64).reshape(-1, 5):
        reach = 0.5 * np.hypot(length, width)
        cols = np.flatnonzero(np.abs(xs - x) <= reach)
        rows = np.flatnonzero(np.abs(ys - y) <= reach)
        if not len(cols) or not len(rows):
            continue
        dx = xs[cols][None, :] - x
        dy = ys[rows][:, None] - y
        c, s = np.cos(yaw), np.sin(yaw)
        along, across = c * dx + s * dy, -s * dx + c * dy
        inside = (np.abs(along) <= length / 2) & (np.abs(across) <= width / 2)
        grid[np.ix_(rows, cols)] |= inside
    return grid


def box_collisions(trajectory: np.ndarray,  # [T, 2] x, y planning frame
                   occupied: np.ndarray) -> np.ndarray:  # bool [T, GRID, GRID] -> bool [T]
    """Per step, whether the ego box at the waypoint covers an occupied cell (UniAD's rule, above)."""
    cells = ego_cells()
    out = np.zeros(len(trajectory), bool)
    for t, (x, y) in enumerate(np.asarray(trajectory, np.float64)):
        r = np.clip((cells[:, 0] + y / CELL).astype(np.int32), 0, GRID - 1)
        c = np.clip((cells[:, 1] + x / CELL).astype(np.int32), 0, GRID - 1)
        out[t] = bool(occupied[t, r, c].any())
    return out


@dataclass(frozen=True)
class PlanningSample:
    """One evaluated keyframe: the true future and what is occupied at each step."""

    token: str
    trajectory: np.ndarray  # [T, 2] planning frame
    mask: np.ndarray        # [T] bool: the true waypoint is known
    vehicles: tuple         # per step [B, 5] boxes (x, y, length, width, yaw) in the planning frame
    command: str | None = None


def per_sample_planning(samples: list[PlanningSample], predictions: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each sample's per-step L2 (0 where the truth is unknown), collision (the plan's box on an occupied cell where
    the truth's is not), the truth's own collision and whether the truth is known: bool / float arrays [N, T].
    Every sample needs a finite prediction of its length."""
    if not samples:
        raise ValidationError("no samples to evaluate")
    steps = len(samples[0].trajectory)
    out = {k: np.zeros((len(samples), steps), dtype) for k, dtype in (("l2", np.float64), ("collision", bool),
                                                                     ("truth_collision", bool), ("known", bool))}
    for i, s in enumerate(samples):
        pred = predictions.get(s.token)
        if pred is None:
            raise ValidationError(f"no planned trajectory for sample {s.token!r}")
        pred = np.asarray(pred, np.float64)
        if pred.shape != (steps, 2) or not np.isfinite(pred).all():
            raise ValidationError(f"the trajectory of sample {s.token!r} must be {steps} finite (x, y) waypoints; "
                                  f"got shape {pred.shape}")
        m = s.mask.astype(np.float64)
        out["l2"][i] = np.sqrt(((pred - s.trajectory) ** 2 * m[:, None]).sum(-1))
        occupied = np.stack([occupancy(v) for v in s.vehicles])
        truth = box_collisions(s.trajectory, occupied)
        out["collision"][i] = box_collisions(pred, occupied) & ~truth
        out["truth_collision"][i] = truth
        out["known"][i] = s.mask
    return out


def evaluate_planning(samples: list[PlanningSample], predictions: dict[str, np.ndarray]) -> dict:
    """Per-step L2 and collision rate over ``samples`` (``predictions``: token -> [T, 2]), and both horizon
    conventions. Every sample needs a finite prediction of its length."""
    return aggregate_planning(per_sample_planning(samples, predictions))


def aggregate_planning(per: dict[str, np.ndarray]) -> dict:
    """``evaluate_planning``'s numbers from ``per_sample_planning``'s arrays (of all samples or a resample)."""
    n, steps = per["l2"].shape
    col, known = per["collision"].sum(0).astype(np.float64), per["known"].sum(0).astype(np.float64)
    per_step = {"L2": per["l2"].sum(0) / n, "obj_box_col": col / n,
                "obj_box_col_known": np.divide(col, known, out=np.zeros(steps), where=known > 0)}
    out = {"n_samples": n, "per_step": {k: v.tolist() for k, v in per_step.items()},
           "gt_collision_steps": per["truth_collision"].sum(0).astype(int).tolist(),
           "known_per_step": known.astype(int).tolist()}
    for convention in CONVENTIONS:
        out[convention] = {k: horizons(v, convention) for k, v in per_step.items()}
    return out


def horizons(per_step: np.ndarray, convention: str) -> dict[str, float]:
    """The 1 / 2 / 3 s values of a per-step metric: at the step (``uniad``) or the mean up to it (``stp3``)."""
    if convention not in CONVENTIONS:
        raise ValidationError(f"convention must be one of {CONVENTIONS}; got {convention!r}")
    v = np.asarray(per_step, np.float64)
    if convention == "uniad":
        return {h: float(v[i]) for h, i in HORIZONS.items() if i < len(v)}
    return {h: float(v[:i + 1].mean()) for h, i in HORIZONS.items() if i < len(v)}


def bootstrap_planning(per_a: dict[str, np.ndarray], per_b: dict[str, np.ndarray], groups: list[str],
                       statistic, n: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``statistic`` (``aggregate_planning``'s output -> float) of planners a and b on the same samples over ``n``
    resamples that draw whole ``groups`` (one per sample, e.g. its scene: keyframes of one scene are far from
    independent) with replacement: two arrays [n], paired draw by draw."""
    names = sorted(set(groups))
    if len(names) < 2 or n < 1:
        raise ValidationError("a bootstrap needs at least two groups (scenes) and one draw")
    g = np.asarray(groups, dtype=object)
    members = [np.flatnonzero(g == name) for name in names]
    rng = np.random.default_rng(seed)
    a, b = np.zeros(n), np.zeros(n)
    for k in range(n):
        rows = np.concatenate([members[i] for i in rng.integers(0, len(names), len(names))])
        a[k] = statistic(aggregate_planning({key: v[rows] for key, v in per_a.items()}))
        b[k] = statistic(aggregate_planning({key: v[rows] for key, v in per_b.items()}))
    return a, b
