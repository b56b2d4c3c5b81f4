"""The closed-loop simulator: a fitted scene graph, a scenario and the ego's bicycle model. A step takes a plan (UniAD
style waypoints) or direct controls, tracks it, advances the ego and the other agents, renders the cameras at the new
pose and reports what happened (collision, off-road, route completion). Pure Python over the scene graph's renderer.

Frames: world as everywhere (z up); the ego frame's origin is the rear axle (the box centre lies
``ego_centre_ahead_m`` ahead); plans are in UniAD's planning frame (x right, y forward, origin ``EGO_SHIFT`` behind
the box centre: ``omniscs.eval.scenarios``), waypoints every ``plan_dt`` seconds. The ground is taken flat: the ego's
height is the logged ego's at the nearest logged position, roll and pitch zero."""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from omniscs.annotate.config import AnnotateConfig
from omniscs.annotate.frames import COMMANDS, driving_commands
from omniscs.annotate.variant import background_tracks
from omniscs.annotate.views import Instance, ViewAnnotator, background_members
from omniscs.closedloop import metrics
from omniscs.closedloop.hugsim_frames import cam_params, ego_from_lidar, hugsim_position, hugsim_rotation
from omniscs.closedloop.scenario import ClosedLoopScenario
from omniscs.closedloop.traffic import IDMConfig, Traffic
from omniscs.closedloop.vehicle import (Controls, PurePursuitConfig, VehicleLimits, VehicleState, advance, plan_to_ego,
                                        pure_pursuit, yaw_rate_of)
from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.planning import EGO_SHIFT
from omniscs.geometry import pose_from_xyz_yaw, wrap_angle
from omniscs.nsg.observations import View
from omniscs.scene.store import CameraRecord

log = logging.getLogger(__name__)

OUTPUTS = ("rgb", "depth", "instance", "semantic")
#: Height of the ego's box in ``info["ego_box"]`` (scene stores record the ego's footprint only), metres.
EGO_HEIGHT_M = 1.6
#: Why an episode ended.
REASONS = ("collision", "offroad", "left_fitted_area", "route_completed", "scenario_end", "max_steps")


@dataclass(frozen=True)
class ClosedLoopConfig:
    """How a closed-loop run renders, tracks and ends."""

    cameras: tuple[str, ...] | None = None
    """Cameras rendered each step (names of the graph's fitted rig); None = all of them."""
    width: int | None = None
    """Render width in pixels (intrinsics scaled); None = the camera's own."""
    height: int | None = None
    """Render height in pixels; None = the width's aspect-preserving value or the camera's own."""
    outputs: tuple[str, ...] = OUTPUTS
    """Which images each step returns per camera: any of rgb, depth, instance, semantic."""
    reactive: bool = False
    """Agents brake by IDM when the ego is ahead in their path (``omniscs.closedloop.traffic``)."""
    idm: IDMConfig = field(default_factory=IDMConfig)
    """IDM parameters of reactive agents."""
    vehicle: VehicleLimits = field(default_factory=VehicleLimits)
    """The ego's bicycle model."""
    controller: PurePursuitConfig = field(default_factory=PurePursuitConfig)
    """The tracker that turns plans into controls."""
    plan_dt: float = 0.5
    """Spacing of plan waypoints, seconds (UniAD: 0.5)."""
    max_offset_m: float = 6.0
    """The episode ends when the ego is further than this from every logged ego position: the scene graph has
    seen nothing of the world out there (metres)."""
    stop_on_collision: bool = True
    """End the episode at the first contact with an agent (HUGSIM does)."""
    stop_on_offroad: bool = False
    """End the episode when the ego leaves the drivable area."""
    route_done: float = 0.99
    """Route completion at which the episode ends as completed."""
    max_plan_m: float = 200.0
    """A plan with a waypoint further than this from the ego is refused (metres)."""
    max_plan_speed: float = 60.0
    """A plan implying a faster speed between waypoints is refused (m/s)."""

    def __post_init__(self):
        bad = sorted(set(self.outputs) - set(OUTPUTS))
        if bad or not self.outputs:
            raise ValidationError(f"closed-loop outputs {bad or '()'} unknown; choose from {list(OUTPUTS)}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if v is not None and not 16 <= int(v) <= 4096:
                raise ValidationError(f"render {name} {v} must be between 16 and 4096 pixels")
        if not (self.plan_dt > 0 and self.max_offset_m > 0 and 0 < self.route_done <= 1):
            raise ValidationError("plan_dt and max_offset_m must be > 0, route_done in (0, 1]")


@dataclass(frozen=True)
class Observation:
    """What the cameras saw at one step: per camera name, the requested images."""

    rgb: dict[str, np.ndarray]       # uint8 [H, W, 3]
    depth: dict[str, np.ndarray]     # float32 [H, W] metres along the camera axis, 0 = nothing
    instance: dict[str, np.ndarray]  # int32 [H, W] track id, -1 = none
    semantic: dict[str, np.ndarray]  # uint8 [H, W] (omniscs.taxonomy.SEMANTIC_IDS; 255 = unknown background)


@dataclass(frozen=True)
class StepResult:
    """What one reset or step returns."""

    observation: Observation
    """The cameras at the new pose (after leaving the fitted area: the last picture taken inside it)."""
    info: dict
    """JSON-able facts of this step (see ``Simulator.info``)."""
    done: bool
    """Whether the episode has ended."""
    reason: str | None
    """Why it ended (one of REASONS), None while it goes on."""


@dataclass
class Timing:
    """Seconds spent per part of the steps so far."""

    render: float = 0.0
    controller: float = 0.0
    world: float = 0.0  # bicycle model, traffic, collision and route checks

    def as_dict(self) -> dict:
        return {"render_s": self.render, "controller_s": self.controller, "world_s": self.world}


@dataclass
class Episode:
    """The mutable record of one run (what the metrics and pictures read)."""

    scenario: ClosedLoopScenario
    state: VehicleState
    traffic: Traffic
    t: float = 0.0
    step: int = 0
    done: bool = False
    reason: str | None = None
    ego: list = field(default_factory=list)          # [T] (x, y, yaw) box centre
    speed: list = field(default_factory=list)        # [T]
    agents: list = field(default_factory=list)       # [T] [N, 3]
    velocity: list = field(default_factory=list)     # [T] [N, 2]
    plans: list = field(default_factory=list)        # [T] [P, 2] world waypoints of the plan issued at that step
    controls: list = field(default_factory=list)     # [T] (accel, steer_rate) applied after that step
    contacts: list = field(default_factory=list)     # [T] list of metrics.Contact
    offroad: list = field(default_factory=list)      # [T] bool
    route_completion: float = 0.0
    timing: Timing = field(default_factory=Timing)
    last_observation: Observation | None = None


class Simulator:
    """Closed-loop episodes in one fitted scene graph. One simulator runs one episode at a time; several simulators
    may share a graph (it is never changed)."""

    def __init__(self, graph, scene, config: ClosedLoopConfig = ClosedLoopConfig(),
                 annotator: ViewAnnotator | None = None, members: dict | None = None,
                 rig: list[CameraRecord] | None = None) -> None:
        """``rig``: cameras to render instead of the fitted ones (e.g. a 6-camera nuScenes-size rig; a camera the
        fit never saw gets no exposure correction); ``config.cameras`` then picks among them."""
        if graph.scene_id != scene.scene_id:
            raise OmniscsError(f"scene graph of {graph.scene_id} does not belong to scene {scene.scene_id}")
        self.graph, self.scene, self.config = graph, scene, config
        self.annotator = annotator or ViewAnnotator(graph, AnnotateConfig())
        self.members = members if members is not None else background_members(graph, background_tracks(scene, graph))
        available = {c.name: c for c in (rig if rig is not None else graph.cameras)}
        self.fitted = frozenset(c.name for c in graph.cameras)
        names = list(config.cameras) if config.cameras is not None else list(available)
        unknown = [c for c in names if c not in available]
        if unknown or not names:
            raise ValidationError(f"camera(s) {unknown or names} not in the rig {list(available)}")
        self.rig = [_resized(available[c], config.width, config.height) for c in names]
        self.logged_xy = np.asarray(graph.world_from_ego)[:, :2, 3]
        self.node_ids = frozenset(graph.agent_ids)
        self.episode: Episode | None = None

    # -- episode -------------------------------------------------------------------------------
    def reset(self, scenario: ClosedLoopScenario) -> StepResult:
        if scenario.scene_id != self.scene.scene_id:
            raise ValidationError(f"scenario {scenario.scenario_id} is not of scene {self.scene.scene_id}")
        if int(np.max(scenario.scene_frames)) >= self.graph.n_frames:
            raise ValidationError(f"scenario {scenario.scenario_id} shows frames beyond the graph's {self.graph.n_frames}")
        cx, cy, yaw = scenario.ego[0]
        ahead = scenario.ego_centre_ahead_m
        v0 = float(scenario.reference_speed()[0])
        yaw_rate = float(wrap_angle(scenario.ego[1, 2] - scenario.ego[0, 2])) / scenario.dt
        L = self.config.vehicle.wheelbase_m
        steer = math.atan(L * yaw_rate / v0) if v0 > 0.5 else 0.0
        steer = float(np.clip(steer, -self.config.vehicle.max_steer_rad, self.config.vehicle.max_steer_rad))
        state = VehicleState(cx - ahead * math.cos(yaw), cy - ahead * math.sin(yaw), float(yaw), v0, steer)
        traffic = Traffic(scenario, self.config.reactive, self.config.idm, movable=self.node_ids)
        self.episode = Episode(scenario, state, traffic)
        self._commands = _reference_commands(scenario)
        self._record()
        obs = self._observe()
        return StepResult(obs, self.info(), False, None)

    def step(self, action) -> StepResult:
        """Advance one step (``scenario.dt`` seconds) under ``action``: a plan ([P, 2] waypoints in the planning
        frame, one every ``plan_dt``) or ``Controls``."""
        ep = self._episode()
        if ep.done:
            raise OmniscsError(f"the episode ended ({ep.reason}); reset it to drive again")
        cfg, sc = self.config, ep.scenario
        tick = time.perf_counter()
        if isinstance(action, Controls):
            controls, plan_world = action, None
        else:
            plan = self.check_plan(action)
            ahead = sc.ego_centre_ahead_m - EGO_SHIFT
            controls = pure_pursuit(ep.state, plan_to_ego(plan, ahead), cfg.plan_dt, cfg.vehicle, cfg.controller,
                                    origin_ahead_m=ahead)
            plan_world = self.plan_in_world(plan)
        ep.plans[-1] = plan_world
        ep.controls[-1] = (controls.accel, controls.steer_rate)
        tock = time.perf_counter()
        ep.timing.controller += tock - tick
        ep.state = advance(ep.state, controls, sc.dt, cfg.vehicle)
        ep.t += sc.dt
        ep.step += 1
        centre = self.ego_centre()
        ep.traffic.step(sc.dt, centre, ep.state.speed, (sc.ego_length, sc.ego_width))
        self._record()
        reason = self._ending()
        ep.timing.world += time.perf_counter() - tock
        if reason == "left_fitted_area":
            log.warning("%s: the ego drove %.1f m from every logged position at %.1f s; the scene graph has seen "
                        "nothing there: the episode ends", sc.scenario_id, self._offset(), ep.t)
            obs = ep.last_observation
        else:
            obs = self._observe()
        ep.done, ep.reason = reason is not None, reason
        return StepResult(obs, self.info(), ep.done, reason)

    def stop(self, reason: str) -> None:
        """End the episode now (e.g. ``max_steps``: the caller's step budget ran out); ``info()["reason"]`` says why."""
        if reason not in REASONS:
            raise ValidationError(f"unknown reason {reason!r}; one of {list(REASONS)}")
        ep = self._episode()
        if not ep.done:
            ep.done, ep.reason = True, reason

    # -- plans ---------------------------------------------------------------------------------
    def check_plan(self, plan) -> np.ndarray:  # -> [P, 2] float64 planning frame
        try:
            plan = np.asarray(plan, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValidationError(f"a plan must be numbers [P, 2] (x right, y forward, metres): {exc}") from None
        if plan.ndim == 3 and plan.shape[0] == 1:
            plan = plan[0]
        if plan.ndim != 2 or plan.shape[1] != 2 or not 1 <= plan.shape[0] <= 100:
            raise ValidationError(f"a plan must be [P, 2] waypoints with 1 <= P <= 100 (got shape {list(plan.shape)})")
        if not np.isfinite(plan).all():
            raise ValidationError("the plan has NaN or infinite waypoints")
        far = float(np.max(np.linalg.norm(plan, axis=1)))
        if far > self.config.max_plan_m:
            raise ValidationError(f"the plan reaches {far:.0f} m from the ego (limit {self.config.max_plan_m:.0f} m)")
        steps = np.linalg.norm(np.diff(np.concatenate([[[0.0, 0.0]], plan]), axis=0), axis=1) / self.config.plan_dt
        if float(steps.max()) > self.config.max_plan_speed:
            raise ValidationError(f"the plan implies {float(steps.max()):.0f} m/s between waypoints "
                                  f"(limit {self.config.max_plan_speed:.0f} m/s)")
        return plan

    def planning_frame(self) -> np.ndarray:  # -> [3, 3] world_from_planning (2D) at the current state
        x, y, yaw = self.ego_centre()
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([[s, c, x - EGO_SHIFT * c], [-c, s, y - EGO_SHIFT * s], [0.0, 0.0, 1.0]])

    def plan_in_world(self, plan: np.ndarray) -> np.ndarray:  # [P, 2] planning frame -> [P, 2] world box centres
        """Where a plan puts the ego's box centre: each waypoint (the planning origin's future position) moved
        EGO_SHIFT ahead along the plan's direction there (the current heading while the plan barely moves)."""
        T = self.planning_frame()
        origin = plan @ T[:2, :2].T + T[:2, 2]
        path = np.concatenate([T[None, :2, 2], origin])
        d = np.diff(path, axis=0)
        yaw = np.where(np.linalg.norm(d, axis=1) > 1e-3, np.arctan2(d[:, 1], d[:, 0]), self.ego_centre()[2])
        return origin + EGO_SHIFT * np.stack([np.cos(yaw), np.sin(yaw)], -1)

    # -- state ---------------------------------------------------------------------------------
    def ego_centre(self) -> np.ndarray:  # -> [3] x, y, yaw of the ego box centre
        ep = self._episode()
        s, a = ep.state, ep.scenario.ego_centre_ahead_m
        return np.array([s.x + a * math.cos(s.yaw), s.y + a * math.sin(s.yaw), s.yaw])

    def _nearest_reference(self) -> int:
        """The reference step whose ego position is nearest the simulated ego's."""
        return int(np.argmin(np.linalg.norm(self._episode().scenario.ego[:, :2] - self.ego_centre()[:2], axis=1)))

    def world_from_ego(self) -> np.ndarray:  # -> [4, 4]
        s, sc = self._episode().state, self._episode().scenario
        return pose_from_xyz_yaw(s.x, s.y, float(sc.ego_z[self._nearest_reference()]), s.yaw)

    def command(self) -> int:
        """UniAD's driving command (index into COMMANDS) of the nearest reference position."""
        return int(self._commands[self._nearest_reference()])

    def boxes(self) -> list[dict]:
        """The agents present now: id, category, centre (x, y, z), size (l, w, h), yaw, velocity (vx, vy)."""
        ep = self._episode()
        sc = ep.scenario
        poses, vel = ep.agents[-1], ep.velocity[-1]
        z = agent_heights(sc, int(round(ep.traffic.t / sc.dt)))
        out = []
        for i, tid in enumerate(sc.track_ids):
            if not np.isfinite(poses[i]).all():
                continue
            out.append({"track_id": int(tid), "category": sc.categories[i],
                        "center": [float(poses[i, 0]), float(poses[i, 1]), float(z[i])],
                        "size": [float(v) for v in sc.sizes[i]], "yaw": float(poses[i, 2]),
                        "velocity": [float(vel[i, 0]), float(vel[i, 1])]})
        return out

    def info(self) -> dict:
        """JSON-able facts of the current step. HUGSIM's keys in HUGSIM's conventions (``hugsim_frames``: ego_pos and
        ego_rot in its OpenCV-axes world, cam_params with intrinsic {fovx, fovy, H, W, cx, cy}, l2c and v2c), and
        ego_velo, ego_steer, accelerate, steer_rate, timestamp, command, ego_box and obj_boxes in HUGSIM's layout
        [x, y, z, w, l, h, yaw] (box centres), collision, rc; plus ours (ego_xyz, ego_yaw, world_from_ego in our z-up
        world, velocity, boxes with ids, offroad, reason)."""
        ep = self._episode()
        sc, s = ep.scenario, ep.state
        centre = self.ego_centre()
        T = self.world_from_ego()
        heading = np.array([math.cos(s.yaw), math.sin(s.yaw)])
        yaw_rate = yaw_rate_of(s, self.config.vehicle)
        boxes = self.boxes()
        contacts = ep.contacts[-1]
        command = self.command()
        lidar = ego_from_lidar(sc.ego_centre_ahead_m - EGO_SHIFT)
        return {
            "scenario_id": sc.scenario_id, "step": ep.step, "timestamp": round(ep.t, 6),
            "ego_pos": hugsim_position(T[:3, 3]), "ego_rot": hugsim_rotation(s.yaw),
            "ego_xyz": [float(v) for v in T[:3, 3]], "ego_yaw": float(s.yaw),
            "ego_velo": float(s.speed), "ego_steer": float(s.steer), "accelerate": float(s.accel),
            "steer_rate": float(s.steer_rate), "yaw_rate": float(yaw_rate),
            "velocity": [float(v) for v in s.speed * heading],
            "acceleration": [float(s.accel), float(s.speed * yaw_rate)],  # longitudinal, lateral (m/s²)
            "command": command, "command_name": COMMANDS[command],
            "ego_box": [float(centre[0]), float(centre[1]), float(T[2, 3]), sc.ego_width, sc.ego_length,
                        EGO_HEIGHT_M, float(centre[2])],
            "obj_boxes": [[b["center"][0], b["center"][1], b["center"][2], b["size"][1], b["size"][0], b["size"][2],
                           b["yaw"]] for b in boxes],
            "boxes": boxes,
            "world_from_ego": T.tolist(),
            "cam_params": {c.name: cam_params(c.K, c.width, c.height, c.ego_from_camera, lidar) for c in self.rig},
            "collision": bool(contacts), "collided_with": [int(sc.track_ids[c.track]) for c in contacts],
            "offroad": bool(ep.offroad[-1]), "rc": float(ep.route_completion),
            "fitted_area_offset_m": float(self._offset()), "reason": ep.reason,
        }

    def trace(self) -> "metrics.RunTrace":
        """The episode so far as the metrics read it."""
        ep = self._episode()
        sc = ep.scenario
        ref = metrics.progress_along(sc.ego[:, :2], sc.route)
        times = np.arange(len(ep.ego)) * sc.dt
        ref_progress = np.interp(times / sc.dt, np.arange(sc.n_steps), ref)
        return metrics.RunTrace(
            dt=sc.dt, ego=np.array(ep.ego), ego_speed=np.array(ep.speed), ego_size=(sc.ego_length, sc.ego_width),
            agents=np.stack(ep.agents, 1) if len(sc.track_ids) else np.zeros((0, len(ep.ego), 3)),
            agent_sizes=sc.sizes[:, :2], agent_kinds=sc.kinds,
            agent_velocity=np.stack(ep.velocity, 1) if len(sc.track_ids) else np.zeros((0, len(ep.ego), 2)),
            plans=tuple(ep.plans), plan_dt=self.config.plan_dt, route=sc.route,
            reference_progress=ref_progress, drivable=sc.drivable)

    # -- internals -----------------------------------------------------------------------------
    def _episode(self) -> Episode:
        if self.episode is None:
            raise OmniscsError("no episode: reset the simulator with a scenario first")
        return self.episode

    def _record(self) -> None:
        ep = self._episode()
        sc = ep.scenario
        centre = self.ego_centre()
        poses = ep.traffic.poses()
        vel = ep.traffic.velocities(sc.dt)
        kinds = sc.kinds
        ep.ego.append(centre)
        ep.speed.append(ep.state.speed)
        ep.agents.append(poses)
        ep.velocity.append(vel)
        ep.plans.append(None)
        ep.controls.append(None)
        size = (sc.ego_length, sc.ego_width)
        ep.contacts.append(metrics.collisions_at(centre, size, ep.state.speed, poses, sc.sizes[:, :2], kinds, vel))
        ep.offroad.append(metrics.offroad(centre, size, sc.drivable))
        ep.route_completion = max(ep.route_completion, metrics.route_completion(centre[:2], sc.route))

    def _offset(self) -> float:
        ep = self._episode()
        return float(np.min(np.linalg.norm(self.logged_xy - np.array([ep.state.x, ep.state.y]), axis=1)))

    def _ending(self) -> str | None:
        ep, cfg = self._episode(), self.config
        if cfg.stop_on_collision and ep.contacts[-1]:
            return "collision"
        if cfg.stop_on_offroad and ep.offroad[-1]:
            return "offroad"
        if self._offset() > cfg.max_offset_m:
            return "left_fitted_area"
        if ep.route_completion >= cfg.route_done:
            return "route_completed"
        if ep.step >= ep.scenario.n_steps - 1:
            return "scenario_end"
        return None

    def _observe(self) -> Observation:
        ep, cfg = self._episode(), self.config
        tick = time.perf_counter()
        sc = ep.scenario
        frame = sc.frame_at(ep.t)
        poses = ep.agents[-1]
        k = min(int(round(ep.traffic.t / sc.dt)), sc.n_steps - 1)
        node_poses, hidden, instances = {}, set(), []
        want_labels = "instance" in cfg.outputs or "semantic" in cfg.outputs
        logged = self.scene.boxes_at(frame) if want_labels else None
        logged_rows = {int(r.track_id): r for r in logged.itertuples()} if logged is not None else {}
        for i, tid in enumerate(int(t) for t in sc.track_ids):
            present = bool(np.isfinite(poses[i]).all())
            if tid in self.node_ids:
                if not present:
                    hidden.add(tid)
                    continue
                z = sc.agents_z[i, k]
                z = float(z) if np.isfinite(z) else float(np.nanmean(sc.agents_z[i]))
                T = pose_from_xyz_yaw(float(poses[i, 0]), float(poses[i, 1]), z, float(poses[i, 2]))
                node_poses[tid] = T
                if want_labels:
                    instances.append(Instance(tid, sc.categories[i], T, sc.sizes[i]))
            elif want_labels and tid in logged_rows:  # left in the background: drawn where it was logged
                r = logged_rows[tid]
                T = pose_from_xyz_yaw(float(r.cx), float(r.cy), float(r.cz), float(r.yaw))
                instances.append(Instance(tid, str(r.category), T, np.array([r.length, r.width, r.height]),
                                          self.members.get(tid)))
        T = self.world_from_ego()
        out = {k: {} for k in OUTPUTS}
        for cam in self.rig:
            view = View(frame, T @ cam.ego_from_camera, np.array(cam.K, dtype=np.float64), int(cam.width),
                        int(cam.height), cam.name if cam.name in self.fitted else None)
            ann = self.annotator.annotate(view, node_poses, instances, hidden=frozenset(hidden), boxes=False)
            for key in cfg.outputs:
                out[key][cam.name] = getattr(ann, key)
        obs = Observation(**out)
        ep.last_observation = obs
        ep.timing.render += time.perf_counter() - tick
        return obs


def agent_heights(sc: ClosedLoopScenario, k: int) -> np.ndarray:  # -> [N] metres
    """Each agent's box centre height at scenario step ``k`` (clamped to the scenario); where the scenario has no
    height there, the agent's mean height (NaN for an agent that never has one)."""
    z = sc.agents_z[:, min(max(int(k), 0), sc.n_steps - 1)].astype(np.float64)
    known = np.isfinite(sc.agents_z)
    counts = known.sum(1)
    means = np.where(counts > 0, np.where(known, sc.agents_z, 0.0).sum(1) / np.maximum(counts, 1), np.nan)
    return np.where(np.isfinite(z), z, means)


def _resized(cam: CameraRecord, width: int | None, height: int | None) -> CameraRecord:
    if width is None and height is None:
        return cam
    w = int(width) if width is not None else int(round(cam.width * int(height) / cam.height))
    h = int(height) if height is not None else int(round(cam.height * w / cam.width))
    K = np.array(cam.K, dtype=np.float64).copy()
    K[0] *= w / cam.width
    K[1] *= h / cam.height
    return replace(cam, width=w, height=h, K=K)


def _reference_commands(sc: ClosedLoopScenario) -> np.ndarray:  # -> [S] index into COMMANDS
    a = sc.ego_centre_ahead_m
    poses = np.stack([pose_from_xyz_yaw(x - a * math.cos(yaw), y - a * math.sin(yaw), 0.0, yaw)
                      for x, y, yaw in sc.ego])
    return driving_commands(poses, sc.timestamps_us, AnnotateConfig())
