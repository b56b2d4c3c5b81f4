"""One scene set up for behaviour-variant synthesis: model context, latents fitted to the log, ego plan, candidates."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from omniscs.comfort import ComfortBounds
from omniscs.errors import OmniscsError
from omniscs.scs.behavior.adversarial_config import NON_ADVERSARY_CATEGORIES, AdversarialConfig
from omniscs.scs.behavior.render_consistency import AgentTrajectories, RenderConsistencyTerm
from omniscs.devices import resolve_device
from omniscs.scs.behavior.checkpoint import model_on
from omniscs.scs.behavior.collision import box_iou, footprints, overlapping
from omniscs.scs.behavior.features import SceneSample, build_sample, collate
from omniscs.scs.behavior.losses import track_fit_loss
from omniscs.scs.behavior.model import Decoded, TrafficModel
from omniscs.scs.behavior.planner import check_planner, rule_based_plan
from omniscs.scs.behavior.tracks import TrafficScene


def to_numpy(t: Tensor) -> np.ndarray:  # any device -> float64 copy on the CPU
    return t.detach().cpu().numpy().astype(np.float64)


def now_and_horizon(traffic: TrafficScene, model_config, config: AdversarialConfig) -> tuple[int, int]:
    """The now step (the model's past ends there) and the horizon after it; a log too short is a user error."""
    s = traffic.n_steps
    now = model_config.history_steps - 1 if config.now_step is None else int(config.now_step)
    now = min(now, s - 1 - config.min_future_steps)
    if now < 0 or s - 1 - now < config.min_future_steps:
        raise OmniscsError(f"scene {traffic.scene_id} is {s} steps ({s * traffic.dt:.1f} s) long; behaviour "
                           f"variants need at least {config.min_future_steps + 1} steps "
                           f"({(config.min_future_steps + 1) * traffic.dt:.1f} s)")
    return now, min(model_config.future_steps, s - 1 - now)


class BehaviorProblem:
    """One scene prepared for adversarial optimisation: model context, fitted latents, planner, candidates.

    Node 0 is the ego; nodes 1.. are the vehicles present at the now step. Tensors live on ``config.device``
    (``device``); ``sample`` keeps the CPU copy that numpy code reads. Evaluation and optimisation are functions
    of a problem (``evaluation``, ``optimisation``)."""

    def __init__(self, traffic: TrafficScene, model: TrafficModel, config: AdversarialConfig = AdversarialConfig(),
                 render_consistency: RenderConsistencyTerm | None = None) -> None:
        check_planner(config.planner.kind)
        mc = model.config
        if abs(traffic.dt - mc.dt) > 1e-3 * mc.dt:
            raise OmniscsError(f"scene {traffic.scene_id} has {traffic.dt:.3f} s steps but the model expects "
                               f"{mc.dt:.3f} s; load it with traffic_from_scene(scene, dt={mc.dt})")
        self.device = resolve_device(config.device)
        self.traffic, self.config, self.render_consistency = traffic, config, render_consistency
        self.model = model_on(model, self.device)
        self.now, self.horizon = now_and_horizon(traffic, mc, config)
        now = self.now
        self.sample: SceneSample = build_sample(traffic, now, mc.history_steps, self.horizon, mc.crop)
        self.batch = collate([self.sample]).to(self.device)
        with torch.no_grad():
            self.context, self.edges, self.edge_mask = self.model.encode_past(self.batch)
            self.z_post, _ = self.model.posterior(self.context, self.batch, self.edges, self.edge_mask)
        self.n_nodes = self.sample.n_nodes
        self.state0 = self.batch.state0[0]  # [N, 5] x, y, yaw, v, yaw rate (scene frame, on device)
        self.state0_np = self.sample.state0.numpy().astype(np.float64)  # the same on the CPU
        self.node_sizes = self.batch.sizes[0]  # [N, 2] length, width (on device)
        self.node_sizes_np = self.sample.sizes.numpy().astype(np.float64)
        self.frame = self.sample.frame
        self.node_tracks = self.sample.track_index  # [N], -1 = ego
        node_set = set(int(i) for i in self.node_tracks[1:])
        window = slice(now + 1, now + 1 + self.horizon)
        # Tracks that are not nodes replay their log (static objects, pedestrians, agents that appear later).
        self.replay_tracks = [i for i in range(traffic.n_tracks)
                              if i not in node_set and traffic.present[i, window].any()]
        rxy, ryaw = self.frame.to_scene(traffic.xy[self.replay_tracks, window], traffic.yaw[self.replay_tracks, window])
        self.replay_xyyaw = np.concatenate([rxy, ryaw[..., None]], -1).reshape(len(self.replay_tracks), self.horizon, 3)
        self.replay_present = traffic.present[self.replay_tracks, window].reshape(len(self.replay_tracks), self.horizon)
        self.replay_sizes = traffic.sizes[self.replay_tracks, :2].reshape(-1, 2)
        exy, eyaw = self.frame.to_scene(traffic.ego_xy[window], traffic.ego_yaw[window])
        self.logged_plan = np.concatenate([exy, eyaw[:, None]], -1)  # [T, 3] scene frame
        self.ego_size = (traffic.ego_box.length, traffic.ego_box.width)
        self.onroad_now = traffic.map.is_drivable(self.frame.to_world_np(self.state0_np[:, :3])[:, :2])  # [N]
        self.log_overlaps = self._logged_overlaps()  # [A, A, T] pairs of ``objects`` that overlap in the log
        #: Interception paths by (config, node, window, restart), shared by warm starts and the knot fallback.
        self.intercept_cache: dict[tuple, tuple[Tensor, float]] = {}
        self.pinned = np.zeros(self.n_nodes, dtype=bool)  # nodes that replay their log (see pin_colliding_...)
        self._pinned_states: Tensor | None = None
        self.z_fit, self.fit_ade = self._fit_latents()
        with torch.no_grad():
            self.fitted = self.decode(self.z_fit)
            self.fitted_knots = self.model.control_knots(self.context, self.z_fit[None], self.edges,
                                                         self.edge_mask)[0]
        if config.pin_colliding_reconstructions:
            pinned = self._colliding_reconstructions()
            if pinned.any():
                self.pinned = pinned
                self._pinned_states = self._logged_states()
                with torch.no_grad():
                    self.fitted = self.decode(self.z_fit)

    # -- model ----------------------------------------------------------------------------------------
    @property
    def comfort_limits(self) -> ComfortBounds | None:
        """Decoding limits just inside the comfort bounds (None when comfort decoding is off)."""
        cfg = self.config
        if not cfg.comfort_decoding:
            return None
        cb, m = cfg.comfort, cfg.comfort_decoding_margin
        return cb.scaled(m)

    @property
    def fitted_np(self) -> np.ndarray:  # [N, T, 5] the reconstruction's states (scene frame), float64 on the CPU
        return to_numpy(self.fitted.states)

    def decode(self, z: Tensor) -> Decoded:  # z [N, Z] -> states [N, T, 5] (scene frame)
        dec = self.model.decode(self.context, z[None], self.batch, self.edges, self.edge_mask, self.horizon,
                                comfort=self.comfort_limits, standstill_gradient=self.config.standstill_gradient)
        states, lon, lat = dec.states[0], dec.longitudinal_accel[0], dec.lateral_accel[0]
        if self._pinned_states is not None:  # pinned nodes replay their log (no gradient, no accelerations)
            pin = torch.from_numpy(self.pinned).to(self.device)[:, None]
            states = torch.where(pin[..., None], self._pinned_states.to(states.dtype), states)
            lon = torch.where(pin, torch.zeros_like(lon), lon)
            lat = torch.where(pin, torch.zeros_like(lat), lat)
        return Decoded(states, lon, lat)

    def _logged_states(self) -> Tensor:  # [N, T, 5]: the log where present, the reconstruction elsewhere
        """Logged future states (speed and yaw rate by finite differences) of the nodes, for pinning."""
        states = self.fitted.states.detach().clone()
        future, mask = self.batch.future[0].to(states.dtype), self.batch.future_mask[0]
        prev = torch.cat([self.state0[:, None, :3].to(states.dtype), future[:, :-1]], 1)
        dt = self.traffic.dt
        speed = torch.linalg.norm(future[..., :2] - prev[..., :2], dim=-1) / dt
        yaw_rate = torch.atan2(torch.sin(future[..., 2] - prev[..., 2]), torch.cos(future[..., 2] - prev[..., 2])) / dt
        logged = torch.cat([future, speed[..., None], yaw_rate[..., None]], -1)
        return torch.where(mask[..., None], logged, states)

    def _colliding_reconstructions(self) -> np.ndarray:  # [N] bool
        """Non-ego nodes whose fitted reconstruction overlaps (IoU > collision_iou) another non-ego agent at a step
        where the log has them apart. Overlaps with the ego are left alone: such an agent is a natural adversary."""
        xyyaw, present, sizes, _ = self.objects(self.fitted_np, self.logged_plan)
        fp = footprints(xyyaw[..., :2], xyyaw[..., 2], sizes[:, 0, None], sizes[:, 1, None])  # [A, T, 4, 2]
        pinned = np.zeros(self.n_nodes, dtype=bool)
        for a, b, t in zip(*self.touching(xyyaw, present, sizes)):
            if a == 0:
                continue
            decoded = [k for k in (a, b) if k < self.n_nodes]
            if decoded and not pinned[decoded].all() and box_iou(fp[a, t], fp[b, t]) > self.config.collision_iou:
                pinned[decoded] = True
        return pinned

    def _fit_latents(self) -> tuple[Tensor, float]:
        """Latents whose decoded trajectories reproduce the logged future (posterior mean, then refined)."""
        cfg = self.config
        target = self.batch.future[0]  # [N, T, 3]
        mask = self.batch.future_mask[0]
        z_post = self.z_post[0]
        z = z_post.clone().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=cfg.fit_lr)
        for _ in range(cfg.fit_iterations):
            loss = (track_fit_loss(self.decode(z).states, target, mask)
                    + cfg.fit_posterior_weight * ((z - z_post) ** 2).sum())
            opt.zero_grad()
            loss.backward()
            opt.step()
        z = z.detach()
        with torch.no_grad():
            states = self.decode(z).states
            err = torch.sqrt(((states[..., :2] - target[..., :2]) ** 2).sum(-1))
            non_ego = mask.clone()
            non_ego[0] = False
            ade = float((err * non_ego).sum() / non_ego.sum().clamp_min(1)) if bool(non_ego.any()) else 0.0
        return z, ade

    def world_trajectories(self, states: Tensor) -> AgentTrajectories:  # [N, T, 5] scene frame
        """Non-ego node trajectories in the world frame, for a renderer (differentiable)."""
        steps = np.arange(self.now + 1, self.now + 1 + self.horizon)
        return AgentTrajectories(
            track_ids=[int(self.traffic.track_ids[t]) for t in self.node_tracks[1:]],
            poses=self.frame.to_world(states[1:, :, :3]), steps=steps,
            timestamps_us=self.traffic.timestamps_us[steps])

    # -- planner --------------------------------------------------------------------------------------
    def plan(self, node_states: np.ndarray) -> np.ndarray:  # [N, T, 5] scene frame -> [T, 3] ego plan
        if self.config.planner.kind == "replay":
            return self.logged_plan
        others = np.concatenate([node_states[1:, :, :3], self.replay_xyyaw], 0)
        present = np.concatenate([np.ones((self.n_nodes - 1, self.horizon), bool), self.replay_present], 0)
        sizes = np.concatenate([self.node_sizes_np[1:], self.replay_sizes], 0)
        ego_state = self.state0_np[0]
        path = np.vstack([ego_state[None, :2], self.logged_plan[:, :2]])
        logged_speeds = np.linalg.norm(np.diff(path, axis=0), axis=1) / self.traffic.dt
        desired = float(max(logged_speeds.max(initial=0.0), ego_state[3]))
        if desired < 0.1:  # the ego stands still in the log: the planner keeps it there
            return np.repeat(np.array([[ego_state[0], ego_state[1], ego_state[2]]]), self.horizon, 0)
        return rule_based_plan(path, float(ego_state[3]), others, present, sizes, self.ego_size, self.horizon,
                               self.traffic.dt, self.config.planner, desired_speed=desired)

    # -- candidates -----------------------------------------------------------------------------------
    def candidates(self) -> list[tuple[int, bool, float]]:
        """(node, reachable, closest approach m) for every non-ego node that may be an adversary: reachable
        moving ones first, then reachable standing ones (they must pull out), then the rest; each group by how
        close its fitted trajectory comes to the ego plan."""
        fitted_all = self.fitted_np
        plan = self.plan(fitted_all)
        out = []
        for k in range(1, self.n_nodes):
            track = int(self.node_tracks[k])
            if self.traffic.categories[track] in NON_ADVERSARY_CATEGORIES or self.pinned[k]:
                continue
            closest = float(np.linalg.norm(fitted_all[k, :, :2] - plan[:, :2], axis=1).min())
            out.append((k, self.reachable(k, plan), closest, self.state0_np[k, 3] >= self.config.moving_speed))
        out.sort(key=lambda c: (not c[1], not c[3], c[2]))
        return [c[:3] for c in out]

    def reachable(self, node: int, plan: np.ndarray) -> bool:  # plan [T, 3] scene frame
        """Whether ``node`` could touch the ego plan within comfort bounds: around its fitted trajectory, at
        time t it can be 0.5 * a * t² further or (braking, never reversing) shorter along its path, and offset
        sideways by at most min(0.5 * a_lat * t², 0.5 * curvature_max * s²) after travelling s metres (a standing
        car must roll before it can steer); the boxes touch when the ego's extent, seen along and across the
        adversary's heading, meets the adversary's half length or half width."""
        cb = self.config.comfort
        tau = np.arange(1, self.horizon + 1) * self.traffic.dt
        fitted = to_numpy(self.fitted.states[node])  # [T, 5]
        state0 = self.state0_np[node]
        travelled = np.cumsum(np.linalg.norm(np.diff(np.vstack([state0[None, :2], fitted[:, :2]]), axis=0),
                                             axis=1))
        longer = 0.5 * self.config.reach_accel_long * tau ** 2
        shorter = np.minimum(-0.5 * cb.min_lon_accel * tau ** 2, travelled)
        s_max = travelled + longer
        side = np.minimum(0.5 * cb.max_abs_lat_accel * tau ** 2,
                          0.5 * self.model.config.limits.max_curvature * s_max ** 2)
        c, s = np.cos(fitted[:, 2]), np.sin(fitted[:, 2])
        d = plan[:, :2] - fitted[:, :2]
        along, across = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        length, width = self.node_sizes_np[node]
        rel = plan[:, 2] - fitted[:, 2]  # the ego's extent seen along / across the adversary
        reach_along = 0.5 * (length + np.abs(np.cos(rel)) * self.ego_size[0] + np.abs(np.sin(rel)) * self.ego_size[1])
        reach_across = 0.5 * (width + np.abs(np.sin(rel)) * self.ego_size[0] + np.abs(np.cos(rel)) * self.ego_size[1])
        ok = (along <= longer + reach_along) & (along >= -shorter - reach_along) & (np.abs(across) <= side + reach_across)
        return bool(ok.any())

    # -- everyone in the horizon ----------------------------------------------------------------------
    def node_present(self, adversary: int | None = None) -> np.ndarray:  # -> [N, T] bool
        """Where decoded nodes exist: the ego and the adversary always; other agents while their log has them
        (an agent that leaves the log, e.g. at the end of the road, leaves the variant too)."""
        present = self.batch.future_mask[0].cpu().numpy().copy()
        present[0] = True
        if adversary is not None:
            present[adversary] = True
        return present

    def objects(self, node_states: np.ndarray,  # [N, T, >=3] scene frame
                plan: np.ndarray,               # [T, 3] ego plan
                adversary: int | None = None,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
        """Everyone in the horizon: ego (0), decoded non-ego nodes, replayed tracks. xyyaw [A, T, 3],
        present [A, T], sizes [A, 2], and a track id per object (-1 = ego)."""
        xyyaw = np.concatenate([plan[None], node_states[1:, :, :3], self.replay_xyyaw], 0)
        present = np.concatenate([self.node_present(adversary), self.replay_present], 0)
        sizes = np.concatenate([np.array([self.ego_size]), self.node_sizes_np[1:], self.replay_sizes], 0)
        ids = [-1] + [int(self.traffic.track_ids[t]) for t in self.node_tracks[1:]] + \
              [int(self.traffic.track_ids[t]) for t in self.replay_tracks]
        return xyyaw, present, sizes, ids

    def touching(self, xyyaw: np.ndarray, present: np.ndarray, sizes: np.ndarray  # from ``objects``
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # object a < object b, step t
        """(a, b, t) where two present objects' centres are close enough for their boxes to touch (within the sum
        of their half diagonals) and the log does not already have them overlapping."""
        reach = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1])
        centre_d = np.linalg.norm(xyyaw[:, None, :, :2] - xyyaw[None, :, :, :2], axis=-1)  # [A, A, T]
        close = (centre_d <= (reach[:, None] + reach[None, :])[..., None]) & present[:, None] & present[None, :]
        close &= np.triu(np.ones(close.shape[:2], bool), 1)[..., None] & ~self.log_overlaps
        return np.nonzero(close)

    def _logged_overlaps(self) -> np.ndarray:  # [A, A, T] bool: pairs that already overlap in the log
        logged = np.zeros((self.n_nodes, self.horizon, 5))
        logged[:, :, :3] = to_numpy(self.batch.future[0])
        xyyaw, present, sizes, _ = self.objects(logged, self.logged_plan)
        known = present.copy()
        known[: self.n_nodes] = self.batch.future_mask[0].cpu().numpy()
        known[0] = True
        fp = footprints(xyyaw[..., :2], xyyaw[..., 2], sizes[:, 0, None], sizes[:, 1, None])  # [A, T, 4, 2]
        over = overlapping(fp[:, None], fp[None, :])  # [A, A, T]
        return over & known[:, None] & known[None, :]
