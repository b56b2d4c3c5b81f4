"""The placement sampler (``omniscs.scs.appearance.placement``): draws proposals in batches, keeps the ones that pass
every check and do not overlap each other, and explains a shortfall."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import wrap_angle
from omniscs.scs.appearance.placement.checks import (ObjectPoses, boxes_overlap, camera_indices, in_range, no_overlap,
                                                    on_road, visible)
from omniscs.scs.appearance.placement.config import (CHECKS, OVERLAPS_ACCEPTED, PROPOSAL_BATCH, PlacementConfig,
                                                    positive_size)
from omniscs.scs.appearance.placement.context import PlacementContext


# ----------------------------------------------------------------------------- sampling
@dataclass(frozen=True)
class PlacementResult:
    """What the sampler found: accepted static placements and how the proposals fared."""

    placements: np.ndarray  # [K, 4] x, y, z (box centre), yaw; world
    frames: np.ndarray      # [K] int: the frame each was proposed at
    cameras: tuple[str, ...]  # [K] the camera each was proposed in
    size: np.ndarray        # [3] the object's length, width, height
    n_requested: int
    n_proposals: int
    rejected: dict[str, int] = field(default_factory=dict)
    """Check name (``CHECKS`` + ``OVERLAPS_ACCEPTED``) -> proposals it rejected (a proposal may fail several)."""

    @property
    def n_accepted(self) -> int:
        return len(self.placements)

    @property
    def acceptance(self) -> float:
        """Share of proposals accepted."""
        return self.n_accepted / self.n_proposals if self.n_proposals else 0.0

    def rejection_share(self) -> dict[str, float]:
        """Check name -> share of the proposals it rejected."""
        return {k: v / self.n_proposals if self.n_proposals else 0.0 for k, v in self.rejected.items()}

    def to_dict(self) -> dict:
        return {"placements": [[float(v) for v in p] for p in self.placements],
                "frames": [int(f) for f in self.frames], "cameras": list(self.cameras),
                "size": [float(v) for v in self.size], "n_requested": int(self.n_requested),
                "n_accepted": int(self.n_accepted), "n_proposals": int(self.n_proposals),
                "rejected": {k: int(v) for k, v in self.rejected.items()},
                "rejection_share": {k: float(v) for k, v in self.rejection_share().items()},
                "acceptance": float(self.acceptance)}


class PlacementError(OmniscsError):
    """The sampler found fewer valid placements than asked for; ``result`` holds what it found."""

    def __init__(self, message: str, result: PlacementResult) -> None:
        super().__init__(message)
        self.result = result


def sample_placements(context: PlacementContext, size, n: int, config: PlacementConfig = PlacementConfig(),
                      rng_seed: int = 0) -> PlacementResult:
    """Draw ``n`` valid static placements. Each proposal: a random frame and camera (``config.camera`` when
    set), a bearing uniform in the camera's horizontal field of view, a horizontal distance uniform in
    ``distance_m``, the box standing on ``ground_z``, a yaw by ``yaw_mode``. Every proposal goes through every
    check (rejections counted per check); one that passes them all is accepted unless it overlaps a placement
    accepted before it. Stops at ``n`` accepted or ``max_proposals``; raises ``PlacementError`` (an
    OmniscsError) naming the check that rejected most when fewer than ``n`` were found. Deterministic in
    ``rng_seed``."""
    size = positive_size(size)
    if int(n) != n or n < 1:
        raise OmniscsError(f"asked for {n} placements; ask for at least 1")
    if config.yaw_mode == "lane" and context.lane_direction is None:
        raise OmniscsError("yaw mode 'lane' needs lane directions, and this context has none; use 'uniform' or "
                           "'fixed'")
    cams = camera_indices(context, config)
    hfov = context.cameras.hfov()
    rng = np.random.default_rng(rng_seed)
    lo, hi = config.distance_m
    accepted, accepted_frames, accepted_cams = [], [], []
    rejected = {name: 0 for name in (*CHECKS, OVERLAPS_ACCEPTED)}
    n_proposals = 0
    road = {"centred": 0, "fitted": 0}  # proposals whose centre was on the road, and that passed on_road
    while len(accepted) < n and n_proposals < config.max_proposals:
        b = min(PROPOSAL_BATCH, config.max_proposals - n_proposals)
        # every draw happens in every batch whatever the mode, so a seed means the same proposals
        frame = rng.integers(0, context.n_frames, b)
        cam = cams[rng.integers(0, len(cams), b)]
        bearing = (rng.random(b) - 0.5) * hfov[cam]
        distance = lo + (hi - lo) * rng.random(b)
        uniform_yaw = rng.uniform(-np.pi, np.pi, b)
        jitter = rng.uniform(-1.0, 1.0, b) * config.lane_yaw_jitter

        world_from_camera = context.cameras.world_from_camera[frame, cam]  # [b, 4, 4]
        forward = world_from_camera[:, :2, 2]
        heading = np.arctan2(forward[:, 1], forward[:, 0]) + bearing
        xy = world_from_camera[:, :2, 3] + distance[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
        yaw = _proposal_yaw(context, config, xy, uniform_yaw, jitter)
        objects = ObjectPoses.at(context, size, np.concatenate([xy, yaw[:, None]], 1))
        centred = np.asarray(context.drivable(xy), dtype=bool).reshape(-1)
        ok = {"on_road": on_road(context, objects, config), "no_overlap": no_overlap(context, objects, config),
              "visible": visible(context, objects, config),
              "in_range": in_range(context, objects, frame, cam, config)}
        for i in range(b):
            n_proposals += 1
            road["centred"] += int(centred[i])
            road["fitted"] += int(ok["on_road"][i])
            failed = [name for name in CHECKS if not ok[name][i]]
            for name in failed:
                rejected[name] += 1
            if not failed:
                candidate = np.array([*objects.centre[i, 0], objects.yaw[i, 0]])
                if accepted and boxes_overlap(np.asarray(accepted)[:, :3], size, np.asarray(accepted)[:, 3],
                                              candidate[:3], size, candidate[3], config.clearance_m).any():
                    rejected[OVERLAPS_ACCEPTED] += 1
                else:
                    accepted.append(candidate)
                    accepted_frames.append(int(frame[i]))
                    accepted_cams.append(context.cameras.names[cam[i]])
            if len(accepted) == n:
                break
    result = PlacementResult(placements=np.asarray(accepted, dtype=np.float64).reshape(-1, 4),
                             frames=np.asarray(accepted_frames, dtype=np.int64), cameras=tuple(accepted_cams),
                             size=size, n_requested=int(n), n_proposals=n_proposals, rejected=rejected)
    if result.n_accepted < n:
        raise PlacementError(_shortfall_message(result, config, road, context.n_frames), result)
    return result


def _proposal_yaw(context: PlacementContext, config: PlacementConfig, xy: np.ndarray, uniform_yaw: np.ndarray,
                  jitter: np.ndarray) -> np.ndarray:  # [b]
    if config.yaw_mode == "fixed":
        return np.full(len(xy), wrap_angle(config.yaw))
    if config.yaw_mode == "uniform":
        return uniform_yaw
    lane_yaw, found = context.lane_direction(xy)
    return np.where(found, wrap_angle(np.asarray(lane_yaw, dtype=np.float64) + config.yaw + jitter), uniform_yaw)


def _shortfall_message(result: PlacementResult, config: PlacementConfig, road: dict[str, int], n_frames: int
                       ) -> str:
    worst = max((*CHECKS, OVERLAPS_ACCEPTED), key=lambda k: result.rejected[k])  # first of equals: CHECKS order
    k, total = result.rejected[worst], result.n_proposals
    length, width, _ = result.size
    lo, hi = config.distance_m
    counts = ", ".join(f"{name} {v}" for name, v in result.rejected.items() if v)
    advice = {
        "on_road": _road_advice(k, total, road, length, width, lo, hi, config),
        "no_overlap": (f"{k} of {total} proposals overlapped logged traffic or the ego's path; use a smaller "
                       f"object, a smaller clearance (now {config.clearance_m:.1f} m) or other distances"),
        "visible": (f"{k} of {total} proposals were visible in fewer than {config.min_visible_frames} frames of "
                    f"{config.camera or 'any camera'}; " + (
                        f"the log has only {n_frames} frames: lower min_visible_frames"
                        if config.min_visible_frames > n_frames else
                        f"bring --distance (now {lo:.0f}-{hi:.0f} m) within {config.max_distance_m:.0f} m, choose "
                        "another camera or lower min_visible_frames")),
        "in_range": (f"{k} of {total} proposals were outside {lo:.0f}-{hi:.0f} m of the camera; check "
                     f"--distance"),
        OVERLAPS_ACCEPTED: (f"{k} of {total} proposals overlapped objects placed before them; ask for fewer "
                            f"objects or widen --distance"),
    }[worst]
    return (f"found {result.n_accepted} of {result.n_requested} placements in {total} proposals "
            f"(rejected by {counts}): {advice}")


def _road_advice(k: int, total: int, road: dict[str, int], length: float, width: float, lo: float, hi: float,
                 config: PlacementConfig) -> str:
    if road["centred"] == 0:
        seen = f"{config.camera} sees no road" if config.camera else "no camera sees road"
        return (f"none of the {total} proposals landed on the drivable area: {seen} at {lo:.0f}-{hi:.0f} m (beyond "
                "the map?); choose other distances (--distance) or another camera")
    if road["fitted"] == 0:
        return (f"an object {length:.1f} m long and {width:.1f} m wide does not fit on this road: {k} of {total} "
                f"proposals left the drivable area (none of the {road['centred']} centred on it fit); use a smaller "
                f"object or widen --distance (now {lo:.0f}-{hi:.0f} m)")
    return (f"{k} of {total} proposals left the drivable area; use a smaller object, a smaller road margin (now "
            f"{config.road_margin_m:.1f} m) or other distances (--distance, now {lo:.0f}-{hi:.0f} m)")
