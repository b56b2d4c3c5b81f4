"""Quality gates: the verdict each SCS variant gets before it may enter a dataset (``GateConfig`` holds the
floors). Behaviour variants are judged on their outcome before they are rendered; every variant is judged on what
its render shows (the edited object's visibility, fidelity against the exact or the unedited render)."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Iterable

from omniscs.errors import OmniscsError


@dataclass(frozen=True)
class GateConfig:
    """What a variant must show to enter a dataset. A variant that fails is kept in the workspace and the catalog
    with its reasons, and left out of the dataset unless the request keeps failed variants."""

    near_miss_m: float = 0.0
    """Behaviour: a variant without contact still passes when the centres of the ego and the adversary come this
    close (metres; 0 = a collision is required)."""
    require_plausible: bool = True
    """Behaviour: the adversary must stay within comfort bounds, on the road and clear of every other agent."""
    require_ego_solution: bool = True
    """Behaviour: the ego must have a comfortable collision-free avoiding trajectory (what it drives in the
    dataset); without one the variant is only a test case."""
    min_visible_frames: int = 3
    """Appearance (and designed variants, for each track they edit and keep): frames in which the composited object
    must be visible (``min_mask_pixels`` in one camera and at
    least ``min_visible_fraction`` of it unoccluded)."""
    min_mask_pixels: int = 100
    """Appearance: mask pixels the object needs in a camera for a frame to count as visible."""
    min_visible_fraction: float = 0.25
    """Appearance: unoccluded share of the object a frame needs to count as visible."""
    min_psnr_db: float = 20.0
    """Fidelity floor against the exact render (procedural scenes): mean PSNR over the measured frames."""
    min_logged_psnr_db: float = 16.0
    """Fidelity floor of recorded logs (no exact render): mean PSNR of the graph's unedited render against the
    logged images."""
    max_feature_drift: float = 0.1
    """Fidelity ceiling of recorded logs: feature drift against the unedited render, edited agents left out
    (0 = same structure)."""

    def __post_init__(self) -> None:
        for name in ("near_miss_m", "min_psnr_db", "min_logged_psnr_db", "max_feature_drift"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0.0:
                raise OmniscsError(f"gate {name} must be a finite number >= 0; got {getattr(self, name)}")
        for name in ("min_visible_frames", "min_mask_pixels"):
            if int(getattr(self, name)) < 0:
                raise OmniscsError(f"gate {name} must be >= 0; got {getattr(self, name)}")
        if not 0.0 <= float(self.min_visible_fraction) <= 1.0:
            raise OmniscsError(f"gate min_visible_fraction must lie in [0, 1]; got {self.min_visible_fraction}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Verdict:
    """Whether a variant passes the gates, and why not."""

    passed: bool
    reasons: tuple[str, ...] = ()
    """One plain sentence per failed gate (empty when it passed)."""

    @classmethod
    def of(cls, reasons: Iterable[str]) -> "Verdict":
        reasons = tuple(reasons)
        return cls(not reasons, reasons)

    def __and__(self, other: "Verdict") -> "Verdict":
        return Verdict.of(self.reasons + other.reasons)

    def to_dict(self) -> dict:
        return {"passed": self.passed, "reasons": list(self.reasons)}

    @classmethod
    def from_dict(cls, d: dict | None) -> "Verdict":
        return cls(True) if d is None else cls(bool(d["passed"]), tuple(d.get("reasons") or ()))


def behaviour_verdict(spec: dict, gates: GateConfig) -> Verdict:
    """A behaviour variant's outcome (its ``variants.json`` spec: ``success``, ``min_distance_m``, ``plausible``,
    ``violations``) against the gates, before it is rendered."""
    reasons = []
    distance = spec.get("min_distance_m")
    near = distance is not None and gates.near_miss_m > 0 and float(distance) <= gates.near_miss_m
    if not spec.get("success") and not near:
        closest = "" if distance is None else f" (closest approach {float(distance):.1f} m between centres)"
        if gates.near_miss_m > 0:
            reason = f"neither a collision nor a near-miss (<= {gates.near_miss_m:g} m) within the horizon{closest}"
        else:
            reason = f"no collision within the horizon{closest}"
        if spec.get("reachable") is False:
            horizon = _horizon_s(spec)
            reason += (f"; no vehicle could reach the ego's path within the {horizon:.1f} s horizon" if horizon
                       else "; no vehicle could reach the ego's path within the horizon") + \
                " (a longer log gives a longer one)"
        reasons.append(reason)
    if gates.require_plausible and not spec.get("plausible", True):
        shown = ", ".join(list(spec.get("violations") or [])[:3]) or "unspecified"
        reasons.append(f"implausible adversary ({shown})")
    return Verdict.of(reasons)


def _horizon_s(spec: dict) -> float | None:
    """Seconds from a behaviour variant's now step to its last step (None when the spec does not say)."""
    try:
        return (len(spec["timestamps_us"]) - 1 - int(spec["now_step"])) * float(spec["dt"])
    except (KeyError, TypeError, ValueError):
        return None


def edited_visible_frames(annotations: list[dict], track_id: int, gates: GateConfig) -> int:
    """Frames in which track ``track_id`` (the composited object) shows ``min_mask_pixels`` in some camera with at
    least ``min_visible_fraction`` of it unoccluded (``annotations``: the variant's annotation rows)."""
    frames = {int(a["frame_idx"]) for a in annotations
              if int(a["track_id"]) == int(track_id) and int(a["mask_pixels"]) >= gates.min_mask_pixels
              and float(a["visible_fraction"]) >= gates.min_visible_fraction}
    return len(frames)


def rendered_verdict(summary: dict, gates: GateConfig) -> Verdict:
    """What a variant's render shows (its annotate summary: ``level``, ``ego_solved``, ``edited_visible_frames`` (of a
    designed variant: its least visible edited track's, ``least_visible_track``), the fidelity means) against the
    gates."""
    reasons = []
    if summary.get("level") == "behaviour" and gates.require_ego_solution and summary.get("ego_solved") is False:
        reasons.append("the ego has no comfortable collision-free avoiding trajectory (only a test case)")
    if summary.get("level") in ("appearance", "designed"):
        seen = int(summary.get("edited_visible_frames") or 0)
        if seen < gates.min_visible_frames:
            what = "the composited object" if summary.get("level") == "appearance" else \
                f"edited track {summary.get('least_visible_track')}"
            reasons.append(f"{what} is visible in {seen} frame(s), fewer than "
                           f"{gates.min_visible_frames} (>= {gates.min_mask_pixels} mask pixels, >= "
                           f"{gates.min_visible_fraction:.0%} unoccluded)")
    psnr = summary.get("fidelity_psnr")
    if psnr is not None:
        if float(psnr) < gates.min_psnr_db:
            reasons.append(f"fidelity PSNR {float(psnr):.1f} dB against the exact render is below "
                           f"{gates.min_psnr_db:g} dB")
    else:
        logged, drift = summary.get("logged_psnr"), summary.get("feature_drift")
        if logged is not None and float(logged) < gates.min_logged_psnr_db:
            reasons.append(f"the scene graph renders the logged views at {float(logged):.1f} dB, below "
                           f"{gates.min_logged_psnr_db:g} dB")
        if drift is not None and float(drift) > gates.max_feature_drift:
            reasons.append(f"feature drift {float(drift):.3f} against the unedited render is above "
                           f"{gates.max_feature_drift:g}")
    return Verdict.of(reasons)
