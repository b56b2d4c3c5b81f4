"""The ego's answer to a behaviour variant: a comfortable, collision-free trajectory near its plan (the "solution"
step of STRIVE). A planner trained on a variant learns this trajectory instead of the plan that collides.

After the variant's now step, per-step controls (acceleration, yaw acceleration) of the ego are optimised through
the kinematic bicycle model (``kinematics.rollout``) from many starts at once (Adam on one batch): stay near the
plan, keep the comfort bounds, keep a margin to every agent of the variant at every step (the separating-axis gap
of ``losses.box_gap``), stay on the drivable area. The best start is then checked exactly: footprint IoU 0 with
every agent at every step (``collision.box_iou``, as the behaviour evaluation measures contact), the comfort
bounds (with a small tolerance) and the road. When no start passes, the best attempt is kept with the reason: the
variant stays a test case."""
from __future__ import annotations

import io
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from omniscs.errors import OmniscsError
from omniscs.geometry import wrap_angle
from omniscs.comfort import VARIANT_COMFORT, ComfortBounds
from omniscs.scs.behavior.collision import box_iou, footprints
from omniscs.scs.behavior.kinematics import KinematicLimits, bound_controls, rollout, soft_clip_accel
from omniscs.scs.behavior.losses import box_gap
from omniscs.scs.behavior.tracks import TrafficScene
from omniscs.storage import atomic_write_bytes


@dataclass(frozen=True)
class SolutionConfig:
    """The ego's solution search (more starts and steps: fewer variants left unsolved, more time)."""

    comfort: ComfortBounds = VARIANT_COMFORT
    """Bounds the solution keeps (longitudinal, lateral acceleration, yaw rate)."""
    margin_m: float = 0.5
    """Gap kept to every agent's footprint (metres); below it the collision term grows."""
    starts: int = 48
    """Starting control sequences optimised together: zero controls, braking, and random ones."""
    steps: int = 150
    """Adam steps."""
    lr: float = 0.08
    """Adam learning rate on the raw (pre-squash) controls."""
    init_std: float = 1.0
    """Standard deviation of the random raw controls."""
    deviation_weight: float = 1.0
    """Weight of the mean squared distance to the plan (m²)."""
    heading_weight: float = 0.5
    """Weight of the mean squared heading difference to the plan (rad²)."""
    effort_weight: float = 0.02
    """Weight of the mean squared controls (comfort beyond the bounds)."""
    collision_weight: float = 50.0
    """Weight of the squared margin violation summed over agents and steps."""
    offroad_weight: float = 10.0
    """Weight of the squared distance off the drivable area (steps where the plan is on it)."""
    comfort_tolerance: float = 1.05
    """A solution within this factor of the comfort bounds counts as comfortable (the check is on finite
    differences of the rolled-out trajectory)."""
    seed: int = 0
    """Seed of the random starts (the same variant gives the same solution)."""
    search_radius_m: float = 10.0
    """Agents that never come within this distance of the plan's path after now (at any step of either: an ego
    that brakes or speeds up stays on the path, off schedule) are left out of the search's loss; they cost time,
    not safety, since the exact check afterwards still covers every agent."""

    def __post_init__(self) -> None:
        if int(self.starts) < 2 or int(self.steps) < 0:
            raise OmniscsError(f"solution search needs starts >= 2 and steps >= 0; got {self.starts}, {self.steps}")
        for name in ("margin_m", "lr", "init_std", "comfort_tolerance", "search_radius_m"):
            if not (math.isfinite(float(getattr(self, name))) and float(getattr(self, name)) > 0):
                raise OmniscsError(f"solution {name} must be a finite number > 0; got {getattr(self, name)}")


@dataclass(frozen=True)
class EgoSolution:
    """The ego's trajectory for one variant and what it achieves."""

    trajectory: np.ndarray  # [S, 3] world x, y, yaw of the ego box centre (the variant's ego up to now_step)
    speeds: np.ndarray      # [S] m/s
    solved: bool
    reason: str | None      # why not solved
    min_gap_m: float        # smallest footprint gap to any agent after now (negative: overlap depth)
    max_accel_mps2: float
    max_decel_mps2: float
    max_lateral_accel_mps2: float
    max_yaw_rate_radps: float
    mean_deviation_m: float  # from the plan, after now
    max_deviation_m: float
    seconds: float

    def to_dict(self) -> dict:
        d = asdict(self)
        d["trajectory"] = [[round(float(v), 4) for v in row] for row in self.trajectory]
        d["speeds"] = [round(float(v), 4) for v in self.speeds]
        for key, value in d.items():
            if isinstance(value, float):
                d[key] = value if math.isfinite(value) else None
        return d


def _rows(value, what: str, n: int) -> np.ndarray:  # [n, 3] with NaN rows for None
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise OmniscsError(f"variant {what} must be a list of {n} [x, y, yaw] rows (or null)")
    out = np.full((n, 3), np.nan)
    for i, row in enumerate(value):
        if row is None:
            continue
        try:
            out[i] = np.asarray(row, dtype=np.float64).reshape(3)
        except (TypeError, ValueError):
            raise OmniscsError(f"variant {what} row {i} is not [x, y, yaw]: {row!r}") from None
        if not np.all(np.isfinite(out[i])):
            raise OmniscsError(f"variant {what} row {i} has NaN or Inf values")
    return out


def _size(sizes: dict, key: str) -> tuple[float, float]:
    s = sizes.get(key)
    try:
        length, width = (float(v) for v in s)
    except (TypeError, ValueError):
        raise OmniscsError(f"variant sizes[{key!r}] must be [length, width]; got {s!r}") from None
    if not (length > 0 and width > 0 and math.isfinite(length) and math.isfinite(width)):
        raise OmniscsError(f"variant sizes[{key!r}] must be positive and finite; got {s!r}")
    return length, width


def _parse(variant: dict):
    for key in ("ego", "agents", "sizes", "now_step", "dt"):
        if key not in variant:
            raise OmniscsError(f"variant {variant.get('variant_id')} lacks {key!r}; give a variants.json entry")
    plan_list = variant["ego"]
    n = len(plan_list) if isinstance(plan_list, (list, tuple)) else -1
    plan = _rows(plan_list, "ego", n)
    if n < 1 or np.isnan(plan).any():
        raise OmniscsError("variant ego must have a finite [x, y, yaw] at every step")
    now, dt = variant["now_step"], variant["dt"]
    if isinstance(now, bool) or not isinstance(now, int) or not 0 <= now < n:
        raise OmniscsError(f"variant now_step must be an integer step in 0..{n - 1}; got {now!r}")
    if not isinstance(dt, (int, float)) or not (math.isfinite(dt) and dt > 0):
        raise OmniscsError(f"variant dt must be a positive number of seconds; got {dt!r}")
    if not isinstance(variant["agents"], dict) or not isinstance(variant["sizes"], dict):
        raise OmniscsError("variant agents and sizes must be objects keyed by track id")
    agents = {str(k): _rows(v, f"agents[{k}]", n) for k, v in variant["agents"].items()}
    sizes = {k: _size(variant["sizes"], k) for k in agents}
    return plan, int(now), float(dt), agents, sizes, _size(variant["sizes"], "ego")


def _state0(plan: np.ndarray, now: int, dt: float) -> np.ndarray:  # [5] x, y, yaw, v, yaw_rate at now
    if now >= 1:
        a, b = plan[now - 1], plan[now]
    elif len(plan) > 1:
        a, b = plan[0], plan[1]
    else:
        a = b = plan[0]
    speed = float(np.linalg.norm(b[:2] - a[:2]) / dt)
    yaw_rate = float(wrap_angle(b[2] - a[2]) / dt)
    return np.array([plan[now, 0], plan[now, 1], plan[now, 2], speed, yaw_rate])


def _measures(traj: np.ndarray, speeds: np.ndarray, dt: float) -> dict:  # [T+1, 3], [T+1]
    if len(traj) < 2:
        return {"accel": 0.0, "decel": 0.0, "lateral": 0.0, "yaw_rate": 0.0}
    lon = np.diff(speeds) / dt
    w = wrap_angle(np.diff(traj[:, 2])) / dt
    lat = speeds[1:] * w
    return {"accel": float(max(lon.max(), 0.0)), "decel": float(max(-lon.min(), 0.0)),
            "lateral": float(np.abs(lat).max()), "yaw_rate": float(np.abs(w).max())}


def solve_ego(variant: dict, traffic: TrafficScene | None = None,
              config: SolutionConfig = SolutionConfig()) -> EgoSolution:
    """The ego's comfortable, collision-free trajectory near the plan of ``variant`` (a ``variants.json`` entry);
    ``traffic`` gives the drivable area (None: the road is not checked)."""
    started = time.perf_counter()
    plan, now, dt, agents, sizes, ego_size = _parse(variant)
    n = len(plan)
    horizon = n - now - 1
    cb = config.comfort
    limits = KinematicLimits(max_accel=cb.max_lon_accel, max_decel=-cb.min_lon_accel, max_yaw_rate=cb.max_abs_yaw_rate,
                             max_lateral_accel=cb.max_abs_lat_accel)
    state0 = _state0(plan, now, dt)
    ids = sorted(agents)
    others = np.stack([agents[k][now + 1:] for k in ids]) if ids and horizon > 0 else np.zeros((0, max(horizon, 0), 3))
    present = ~np.isnan(others[..., 0]) if len(others) else np.zeros(others.shape[:2], bool)
    road = traffic.map if traffic is not None else None
    target = plan[now + 1:]
    if horizon <= 0:  # nothing after now: the plan is the solution
        speeds = np.full(n, state0[3])
        return _finish(plan, speeds, plan, now, dt, others, present, [], sizes, ego_size, road, config, started)

    dtype = torch.float64
    gen = torch.Generator().manual_seed(int(config.seed))
    raw = torch.randn(config.starts, horizon, 2, generator=gen, dtype=dtype) * config.init_std
    raw[0] = 0.0                       # keep speed and yaw rate
    raw[1, :, 0], raw[1, :, 1] = -3.0, 0.0  # brake hard, straight
    raw.requires_grad_(True)
    x0 = torch.tensor(state0, dtype=dtype)
    tgt = torch.tensor(target, dtype=dtype)
    agents_t = torch.tensor(np.nan_to_num(others), dtype=dtype)  # [A, T, 3]
    present_t = torch.tensor(present, dtype=dtype)
    plan_on_road = torch.ones(horizon, dtype=dtype)
    if road is not None:
        plan_on_road = torch.tensor(road.is_drivable(target[:, :2]) | ~road.covers(target[:, :2]), dtype=dtype)

    def roll(r: torch.Tensor) -> torch.Tensor:  # [B, T, 2] -> [B, T, 5]
        c = bound_controls(r, limits)
        c = torch.stack([soft_clip_accel(c[..., 0], cb.max_lon_accel, -cb.min_lon_accel), c[..., 1]], -1)
        return rollout(x0.expand(r.shape[0], 5), c, dt, limits, standstill_gradient=0.1)

    near = _near_plan(target, ego_size, others, present, ids, sizes, config.search_radius_m)

    def loss_of(r: torch.Tensor) -> torch.Tensor:  # [B]
        states = roll(r)
        dev = ((states[..., :2] - tgt[:, :2]) ** 2).sum(-1).mean(-1)
        head = (torch.atan2(torch.sin(states[..., 2] - tgt[:, 2]), torch.cos(states[..., 2] - tgt[:, 2])) ** 2).mean(-1)
        effort = (bound_controls(r, limits) ** 2).sum(-1).mean(-1)
        loss = config.deviation_weight * dev + config.heading_weight * head + config.effort_weight * effort
        for a, k in enumerate(ids):
            if not near[a]:
                continue
            gaps = box_gap(states[..., :3], ego_size, agents_t[a], sizes[k])  # [B, T] (the gap is symmetric)
            loss = loss + config.collision_weight * ((torch.relu(config.margin_m - gaps) ** 2) * present_t[a]).sum(-1)
        if road is not None and config.offroad_weight:
            off = road.outside_distance(states[..., :2])
            loss = loss + config.offroad_weight * ((off ** 2) * plan_on_road).sum(-1)
        return loss

    opt = torch.optim.Adam([raw], lr=config.lr)
    for _ in range(int(config.steps)):
        opt.zero_grad()
        loss = loss_of(raw)
        loss.sum().backward()
        opt.step()
    with torch.no_grad():
        states = roll(raw).numpy()  # [B, T, 5]
    best, best_rank = None, None
    for b in range(config.starts):
        traj = np.concatenate([plan[:now + 1], states[b, :, :3]])
        speeds = np.concatenate([np.full(now + 1, state0[3]), states[b, :, 3]])
        check = _check(traj, speeds, plan, now, dt, others, present, ids, sizes, ego_size, road, config)
        rank = (check["collides"], not check["on_road"], not check["comfortable"], check["mean_dev"])
        if best_rank is None or rank < best_rank:
            best, best_rank = (traj, speeds), rank
    return _finish(best[0], best[1], plan, now, dt, others, present, ids, sizes, ego_size, road, config, started)


def _near_plan(target: np.ndarray, ego_size, others: np.ndarray, present: np.ndarray, ids: list[str], sizes: dict,
               radius: float) -> list[bool]:
    """Per agent: does its footprint come within ``radius`` of the plan's path after now, at any pair of steps
    (centre distance less both half-diagonals, a lower bound of the footprint gap)?"""
    ego_half = 0.5 * math.hypot(*ego_size)
    out = []
    for a, k in enumerate(ids):
        on = present[a]
        if not on.any():
            out.append(False)
            continue
        centre = np.linalg.norm(others[a, on, None, :2] - target[None, :, :2], axis=-1)  # [T_on, T]
        out.append(bool((centre - ego_half - 0.5 * math.hypot(*sizes[k])).min() < radius))
    return out


def _check(traj, speeds, plan, now, dt, others, present, ids, sizes, ego_size, road, config) -> dict:
    after = traj[now + 1:]
    fe = footprints(after[:, :2], after[:, 2], ego_size[0], ego_size[1])  # [T, 4, 2]
    collides, min_gap = False, math.inf
    for a, k in enumerate(ids):
        on = present[a]
        if not on.any():
            continue
        fa = footprints(others[a, on, :2], others[a, on, 2], sizes[k][0], sizes[k][1])
        collides |= bool((box_iou(fe[on], fa) > 0).any())
        gap = box_gap(torch.tensor(others[a, on][None]), sizes[k], torch.tensor(after[on]), ego_size)[0]
        min_gap = min(min_gap, float(gap.min()))
    m = _measures(traj[now:], speeds[now:], dt)
    cb, tol = config.comfort, config.comfort_tolerance
    comfortable = (m["accel"] <= cb.max_lon_accel * tol and m["decel"] <= -cb.min_lon_accel * tol
                   and m["lateral"] <= cb.max_abs_lat_accel * tol and m["yaw_rate"] <= cb.max_abs_yaw_rate * tol)
    on_road = True
    if road is not None and len(after):
        plan_ok = road.is_drivable(plan[now + 1:, :2]) | ~road.covers(plan[now + 1:, :2])
        off = ~road.is_drivable(after[:, :2]) & road.covers(after[:, :2])
        on_road = not bool((off & plan_ok).any())
    dev = np.linalg.norm(after[:, :2] - plan[now + 1:, :2], axis=1) if len(after) else np.zeros(1)
    return {"collides": collides, "min_gap": min_gap, "comfortable": comfortable, "on_road": on_road,
            "mean_dev": float(dev.mean()), "max_dev": float(dev.max()), **m}


def _finish(traj, speeds, plan, now, dt, others, present, ids, sizes, ego_size, road, config, started) -> EgoSolution:
    c = _check(traj, speeds, plan, now, dt, others, present, ids, sizes, ego_size, road, config)
    reason = None
    if c["collides"]:
        reason = "collision unavoidable within comfort bounds"
    elif not c["on_road"]:
        reason = "every collision-free trajectory found leaves the road"
    elif not c["comfortable"]:
        reason = "no collision-free trajectory within the comfort bounds"
    min_gap = c["min_gap"] if math.isfinite(c["min_gap"]) else 1e9  # no agent after now: nothing to hit
    return EgoSolution(np.asarray(traj, np.float64), np.asarray(speeds, np.float64), reason is None, reason,
                       float(min_gap), c["accel"], c["decel"], c["lateral"], c["yaw_rate"], c["mean_dev"],
                       c["max_dev"], time.perf_counter() - started)


def solution_bev_picture(variant: dict, solution: EgoSolution, traffic: TrafficScene, out_png: str | Path) -> Path:
    """The variant over the map: the ego's plan (dashed black), its solution (solid green), the adversary's
    variant trajectory (red), footprints at the plan's collision step (or closest approach) for the plan, the
    solution and the adversary. Written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    plan, now, dt, agents, sizes, ego_size = _parse(variant)
    adv_key = str(variant.get("adversary"))
    adv = agents.get(adv_key)
    sol = solution.trajectory
    pts = [plan[:, :2], sol[:, :2]] + ([adv[~np.isnan(adv[:, 0]), :2]] if adv is not None else [])
    focus = np.vstack(pts)
    lo, hi = focus.min(0) - 15.0, focus.max(0) + 15.0
    span = hi - lo
    fig, ax = plt.subplots(figsize=(10.0, float(np.clip(10.0 * span[1] / max(span[0], 1e-6), 3.5, 10.0))), dpi=110)
    m = traffic.map
    h, w = m.shape
    extent = (m.origin[0], m.origin[0] + w * m.resolution, m.origin[1], m.origin[1] + h * m.resolution)
    ax.imshow(np.where(m.layers[0] > 0.5, 0.72, 0.93), origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1,
              interpolation="nearest", zorder=0)
    step = variant.get("collision_step")
    if step is None and adv is not None:
        d = np.linalg.norm(plan[now + 1:, :2] - np.nan_to_num(adv[now + 1:, :2], nan=1e9), axis=1)
        step = now + 1 + int(np.argmin(d)) if len(d) else now
    step = int(min(step if step is not None else now, len(plan) - 1))
    for k, traj in agents.items():
        if k == adv_key:
            continue
        ax.plot(traj[:, 0], traj[:, 1], "-", color="0.45", lw=0.8, zorder=2)
    if adv is not None:
        ax.plot(adv[:, 0], adv[:, 1], "-", color="tab:red", lw=2.0, zorder=4, label=f"adversary {adv_key}")
        if np.isfinite(adv[step, 0]):
            fp = footprints(adv[step, :2], adv[step, 2], *sizes[adv_key])
            ax.fill(fp[:, 0], fp[:, 1], color="tab:red", alpha=0.35, zorder=4)
    ax.plot(plan[:, 0], plan[:, 1], "--", color="black", lw=1.6, zorder=5, label="ego plan")
    ax.plot(sol[:, 0], sol[:, 1], "-", color="tab:green", lw=2.2, zorder=6, label="ego solution")
    for traj, colour in ((plan, "black"), (sol, "tab:green")):
        fp = footprints(traj[step, :2], traj[step, 2], *ego_size)
        ax.fill(fp[:, 0], fp[:, 1], facecolor="none", edgecolor=colour, lw=1.6, zorder=6)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    status = "solved" if solution.solved else f"not solved: {solution.reason}"
    ax.set_title(f"{variant.get('scene_id')} {variant.get('variant_id')}: ego solution {status}; min gap "
                 f"{solution.min_gap_m:.2f} m, mean deviation {solution.mean_deviation_m:.2f} m; boxes at "
                 f"t = {step * dt:.1f} s", fontsize=8)
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
    ax.grid(True, alpha=0.25)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_bytes(out_png, buf.getvalue())
