"""Driving policies a closed-loop run can be driven by. Each gets the simulator after every step and returns a plan
(UniAD-style: [6, 2] waypoints at 0.5 s in the planning frame, x right, y forward) or direct ``Controls``.

- ``replay``: the scenario's reference ego trajectory (the log, or the variant's plan) from the current instant; it
  ignores the other agents, so it shows what the log would have done here.
- ``rule``: lane keeping along the reference path with IDM car following of whatever is in the ego's corridor
  ahead (vehicles, people, static objects), looking at exact boxes.
- ``proxy``: the embedded proxy planner of the downstream stack (``omniscs.eval.planner``; it sees boxes and the
  map in bird's-eye view, not images).
- ``http://HOST:PORT``: a driving agent that serves DriveArena's driver API (``DriveArenaDriver``)."""
from __future__ import annotations

import base64
import io
import json
import math
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from omniscs.closedloop.traffic import IDMConfig, idm_accel
from omniscs.closedloop.vehicle import Controls
from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.planning import EGO_SHIFT, STEPS, STEP_S
from omniscs.eval.scenarios import HISTORY_S, boxes_in_frame, to_frame
from omniscs.taxonomy import VEHICLE_CATEGORIES
from omniscs.untrusted import loads_json

#: How far the reference path is extended past its end, so a policy can keep driving on (metres).
ROUTE_EXTENSION_M = 200.0


class Policy(Protocol):
    name: str

    def reset(self, sim) -> None: ...

    def act(self, sim) -> np.ndarray | Controls: ...


class Route:
    """A polyline with arc-length lookups (world frame), extended straight past its end."""

    def __init__(self, xy: np.ndarray) -> None:  # [R, 2]
        xy = np.asarray(xy, dtype=np.float64)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6])
        xy = xy[keep]
        if len(xy) < 2:
            xy = np.stack([xy[0], xy[0] + [1e-3, 0.0]])
        d = xy[-1] - xy[-2]
        xy = np.concatenate([xy, [xy[-1] + d / np.linalg.norm(d) * ROUTE_EXTENSION_M]])
        self.xy = xy
        self.arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])

    def project(self, p: np.ndarray) -> tuple[float, float]:  # [2] -> (arc length, signed lateral offset, left +)
        a, b = self.xy[:-1], self.xy[1:]
        ab = b - a
        w = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
        q = a + w[:, None] * ab
        i = int(np.argmin(np.linalg.norm(q - p, axis=1)))
        side = ab[i, 0] * (p[1] - a[i, 1]) - ab[i, 1] * (p[0] - a[i, 0])
        return float(self.arc[i] + w[i] * np.linalg.norm(ab[i])), float(math.copysign(np.linalg.norm(q[i] - p), side))

    def point(self, s: float) -> np.ndarray:  # -> [2]
        s = float(np.clip(s, 0.0, self.arc[-1]))
        i = min(int(np.searchsorted(self.arc, s, side="right")) - 1, len(self.xy) - 2)
        w = (s - self.arc[i]) / max(self.arc[i + 1] - self.arc[i], 1e-12)
        return self.xy[i] + w * (self.xy[i + 1] - self.xy[i])

    def heading(self, s: float) -> float:
        i = min(max(int(np.searchsorted(self.arc, s, side="right")) - 1, 0), len(self.xy) - 2)
        d = self.xy[i + 1] - self.xy[i]
        return math.atan2(d[1], d[0])


def _to_plan(sim, centres: np.ndarray,  # [P, 2] world: where the ego box centre should be at each waypoint time
             headings: np.ndarray) -> np.ndarray:  # [P] its heading there -> [P, 2] planning frame
    """UniAD's waypoints are where the planning frame's origin (EGO_SHIFT behind the box centre) will be."""
    origin = centres - EGO_SHIFT * np.stack([np.cos(headings), np.sin(headings)], -1)
    return to_frame(sim.planning_frame(), origin)


class ReplayPolicy:
    """Drive the reference trajectory: waypoints where the reference ego is 0.5, 1.0, ... 3.0 s from now."""

    name = "replay"

    def reset(self, sim) -> None:
        pass

    def act(self, sim) -> np.ndarray:
        ep = sim.episode
        sc = ep.scenario
        pts = []
        for k in range(1, STEPS + 1):
            t = ep.t + k * STEP_S
            if t <= sc.duration_s:
                pts.append(sc.ego_at(t))
            else:  # past the end: on along the last step's velocity
                v = (sc.ego[-1, :2] - sc.ego[-2, :2]) / sc.dt
                pts.append(np.append(sc.ego[-1, :2] + v * (t - sc.duration_s), sc.ego[-1, 2]))
        pts = np.array(pts)
        return _to_plan(sim, pts[:, :2], pts[:, 2])


@dataclass(frozen=True)
class RuleConfig:
    """The rule-based policy: follow the reference path, keep an IDM gap to anything in the corridor ahead."""

    idm: IDMConfig = field(default_factory=lambda: IDMConfig(max_accel=2.0, comfortable_decel=3.0, time_gap_s=1.2))
    """The ego's car-following parameters."""
    desired_speed: float | None = None
    """Cruise speed, m/s; None = the reference ego's speed at the nearest point of its path (at least
    ``min_speed``)."""
    min_speed: float = 3.0
    """Lowest cruise speed when it comes from the reference, m/s (a log that stopped still gets driven)."""
    corridor_margin_m: float = 0.4
    """An agent is in the corridor when its centre is within half the widths plus this of the path, metres."""
    lookahead_m: float = 60.0
    """How far ahead along the path agents are considered, metres."""


class RulePolicy:
    name = "rule"

    def __init__(self, config: RuleConfig = RuleConfig()) -> None:
        self.config = config

    def reset(self, sim) -> None:
        sc = sim.episode.scenario
        self.route = Route(sc.route)
        self.ref_speed = sc.reference_speed()
        self.ref_arc = np.array([self.route.project(p)[0] for p in sc.ego[:, :2]])

    def leader(self, sim, s_ego: float) -> tuple[float, float]:
        """(gap in metres, speed along the path) of the nearest agent in the corridor ahead; (inf, 0) if none."""
        ep, cfg = sim.episode, self.config
        sc = ep.scenario
        poses, vel = ep.agents[-1], ep.velocity[-1]
        best = (math.inf, 0.0)
        for i in range(len(sc.track_ids)):
            if not np.isfinite(poses[i]).all():
                continue
            s, lateral = self.route.project(poses[i, :2])
            ahead = s - s_ego
            half = 0.5 * (sc.sizes[i, 1] + sc.ego_width) + cfg.corridor_margin_m
            if not (0.0 < ahead < cfg.lookahead_m) or abs(lateral) > half:
                continue
            gap = ahead - 0.5 * (sc.sizes[i, 0] + sc.ego_length)
            h = self.route.heading(s)
            along = float(vel[i, 0] * math.cos(h) + vel[i, 1] * math.sin(h))
            if gap < best[0]:
                best = (gap, along)
        return best

    def act(self, sim) -> np.ndarray:
        ep, cfg = sim.episode, self.config
        centre = sim.ego_centre()
        s, _ = self.route.project(centre[:2])
        if cfg.desired_speed is not None:
            v0 = cfg.desired_speed
        else:
            k = int(np.argmin(np.abs(self.ref_arc - s)))
            v0 = max(float(self.ref_speed[k]), cfg.min_speed)
        gap, v_lead = self.leader(sim, s)
        v, h, pts, headings = ep.state.speed, 0.1, [], []
        for k in range(1, STEPS + 1):
            for _ in range(int(round(STEP_S / h))):
                a = idm_accel(v, v0, gap, v - v_lead, cfg.idm)
                moved = max(v * h + 0.5 * a * h * h, 0.0)
                v = max(v + a * h, 0.0)
                s += moved
                gap += v_lead * h - moved
            pts.append(self.route.point(s))
            headings.append(self.route.heading(s))
        return _to_plan(sim, np.array(pts), np.array(headings))


class ProxyPolicy:
    """The proxy planner (``omniscs.eval.planner``) on the simulator's exact boxes and map."""

    name = "proxy"

    def __init__(self, path=None) -> None:
        from omniscs.eval.planner import load_planner

        self.model = load_planner(path)

    def reset(self, sim) -> None:
        pass

    def act(self, sim) -> np.ndarray:
        import torch

        from omniscs.annotate.frames import COMMANDS
        from omniscs.eval.planner import features_of
        from omniscs.eval.scenarios import PlanningInput

        ep = sim.episode
        sc = ep.scenario
        frame = sim.planning_frame()
        vehicle = np.array([c in VEHICLE_CATEGORIES for c in sc.categories], bool)
        back = min(int(round(HISTORY_S / sc.dt)), len(ep.agents) - 1)
        now = boxes_in_frame(ep.agents[-1], sc.sizes[:, :2], vehicle, frame)
        past = boxes_in_frame(ep.agents[-1 - back], sc.sizes[:, :2], vehicle, frame)
        yaw_rate = (float(np.angle(np.exp(1j * (ep.ego[-1][2] - ep.ego[-1 - back][2])))) / (back * sc.dt)
                    if back else 0.0)
        inputs = PlanningInput(now, past, float(ep.state.speed), yaw_rate, COMMANDS[sim.command()], frame)
        raster, state, base = features_of(inputs, sc.drivable)
        with torch.no_grad():
            out = self.model(torch.from_numpy(raster)[None], torch.from_numpy(state)[None], torch.from_numpy(base)[None])
        return out[0].numpy().astype(np.float64)


#: DriveArena's world model renders its six cameras in this order, each 400 x 224, stacked top to bottom.
DRIVEARENA_CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT")
DRIVEARENA_SIZE = (400, 224)


class DriveArenaDriver:
    """A driving agent behind DriveArena's driver API (its UniAD and VAD servers): ``POST /driver-api/`` with the
    stacked camera images (base64 PNG) and the ego state, then ``GET /driver-get/`` until the plan is ready (204 =
    not yet) and read ``bbox_results[0].planning_traj`` ([1, 6, 2] in the planning frame). ``GET /driver-clean/``
    clears the agent's history at reset. Cameras the scene graph lacks are sent black."""

    name = "drivearena"

    def __init__(self, url: str, timeout_s: float = 30.0, poll_s: float = 0.05) -> None:
        if not url.startswith(("http://", "https://")):
            raise ValidationError(f"a DriveArena driver is an http(s) URL, not {url!r}")
        self.url = url.rstrip("/")
        self.timeout_s, self.poll_s = float(timeout_s), float(poll_s)

    def _call(self, method: str, path: str, body: dict | None = None) -> tuple[int, bytes]:
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method,
                                     headers={"Content-Type": "application/json"} if data else {})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as resp:
                return resp.status, resp.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()
        except (urllib.error.URLError, OSError) as e:
            raise OmniscsError(f"DriveArena driver at {self.url} unreachable: {e}") from None

    def reset(self, sim) -> None:
        status, body = self._call("GET", "/driver-clean/")
        if status not in (200, 204, 404):  # 404: a driver without the (optional) history reset
            raise OmniscsError(f"DriveArena driver could not clear its history: HTTP {status} {body[:200]!r}")

    def request(self, sim) -> dict:
        """The JSON body of one ``/driver-api/`` call for the simulator's current step."""
        from PIL import Image

        ep = sim.episode
        rgb = ep.last_observation.rgb if ep.last_observation is not None else {}
        W, H = DRIVEARENA_SIZE
        tiles = []
        for cam in DRIVEARENA_CAMERAS:
            img = rgb.get(cam)
            tiles.append(np.zeros((H, W, 3), np.uint8) if img is None
                         else np.asarray(Image.fromarray(img).resize((W, H), Image.BILINEAR)))
        buf = io.BytesIO()
        Image.fromarray(np.concatenate(tiles, 0)).save(buf, format="PNG")
        s = ep.state
        yaw_rate = sim.info()["yaw_rate"]
        return {"img_byte_array": base64.b64encode(buf.getvalue()).decode(), "timestamp": round(ep.t, 6),
                "command": sim.command(), "accel": [float(s.accel), float(s.speed * yaw_rate), 9.8],
                "rotation_rate": [0.0, 0.0, float(yaw_rate)], "vel": [float(s.speed), 0.0, 0.0],
                "ego_pose": sim.world_from_ego().tolist()}

    def act(self, sim) -> np.ndarray:
        status, body = self._call("POST", "/driver-api/", self.request(sim))
        if status != 200:
            raise OmniscsError(f"DriveArena driver refused the frame: HTTP {status} {body[:200]!r}")
        deadline = time.monotonic() + self.timeout_s
        while True:
            status, body = self._call("GET", "/driver-get/")
            if status == 200 and body:
                break
            if status not in (200, 204):
                raise OmniscsError(f"DriveArena driver failed: HTTP {status} {body[:200]!r}")
            if time.monotonic() > deadline:
                raise OmniscsError(f"DriveArena driver gave no plan within {self.timeout_s:.0f} s")
            time.sleep(self.poll_s)
        answer = loads_json(body, "the DriveArena driver's answer", expect=dict)  # another process: untrusted
        try:
            traj = answer["bbox_results"][0]["planning_traj"]
            plan = np.asarray(traj, dtype=np.float64).reshape(-1, 2)
        except (ValueError, KeyError, IndexError, TypeError) as e:
            raise OmniscsError(f"DriveArena driver's answer has no bbox_results[0].planning_traj: {e}") from None
        return plan


def make_policy(spec: str) -> Policy:
    """``replay``, ``rule``, ``proxy`` (the shipped planner), ``proxy:PATH`` (a saved one) or a DriveArena driver's
    ``http://HOST:PORT``."""
    if spec == "replay":
        return ReplayPolicy()
    if spec == "rule":
        return RulePolicy()
    if spec == "proxy":
        return ProxyPolicy()
    if spec.startswith("proxy:"):
        return ProxyPolicy(spec[len("proxy:"):])
    if spec.startswith(("http://", "https://")):
        return DriveArenaDriver(spec)
    raise ValidationError(f"unknown policy {spec!r}: use replay, rule, proxy, proxy:PATH or http://HOST:PORT "
                          "(a DriveArena driver)")
