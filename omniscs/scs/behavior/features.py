"""Model inputs for one scene at one "now" step: agent histories, states, map patches and (for training) futures.

Nodes are the ego (node 0) and every vehicle present at the now step. Geometry is converted from the
world frame (float64) to the *scene frame* (origin at the ego box centre at the now step, x along its
heading) and then to float32 for learning. Other tracks (cones, barriers, pedestrians, agents that appear
later) are not nodes: they replay their log and appear in the map patches as obstacles.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from omniscs.geometry import wrap_angle
from omniscs.scs.behavior.maps import CropSpec
from omniscs.scs.behavior.tracks import TrafficScene

#: Categories a node can have, in one-hot order (omniscs.taxonomy vehicle classes).
NODE_CATEGORIES = ("car", "truck", "bus", "trailer", "construction_vehicle", "motorcycle", "bicycle")
#: Per history step: x, y, cos(dyaw), sin(dyaw) in the agent's frame at the now step, speed, yaw rate, valid.
HISTORY_FEATURES = 7
#: Per node: length, width, category one-hot, is_ego, speed, yaw rate at the now step.
STATIC_FEATURES = 2 + len(NODE_CATEGORIES) + 1 + 2
#: Per future step (posterior input): x, y, cos(dyaw), sin(dyaw) in the agent's frame at the now step, valid.
FUTURE_FEATURES = 5
#: Map patch channels: the SceneMap layers plus an obstacle layer.
CROP_CHANNELS = 5
#: Scales that bring metres, m/s and vehicle sizes to about unit range.
POSITION_SCALE, SPEED_SCALE, SIZE_SCALE = 10.0, 10.0, 5.0


@dataclass(frozen=True)
class SceneFrame:
    """The scene frame: origin (world xy) at the ego box centre at the now step, x along its heading."""

    origin: np.ndarray  # [2] float64
    yaw: float

    def to_scene(self, xy: np.ndarray, yaw: np.ndarray | None = None):  # world [..., 2] -> scene [..., 2]
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        d = np.asarray(xy, dtype=np.float64) - self.origin
        out = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
        return out if yaw is None else (out, wrap_angle(np.asarray(yaw) - self.yaw))

    def to_world_np(self, xyyaw: np.ndarray) -> np.ndarray:  # scene [..., 3] -> world [..., 3] float64
        xyyaw = np.asarray(xyyaw, dtype=np.float64)
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        x, y = xyyaw[..., 0], xyyaw[..., 1]
        return np.stack([self.origin[0] + c * x - s * y, self.origin[1] + s * x + c * y,
                         wrap_angle(xyyaw[..., 2] + self.yaw)], -1)

    def to_world(self, xyyaw: Tensor) -> Tensor:  # scene [..., 3] -> world [..., 3], differentiable
        c, s = float(np.cos(self.yaw)), float(np.sin(self.yaw))
        x, y = xyyaw[..., 0], xyyaw[..., 1]
        return torch.stack([self.origin[0] + c * x - s * y, self.origin[1] + s * x + c * y,
                            xyyaw[..., 2] + self.yaw], -1)


@dataclass
class SceneSample:
    """One scene at one now step, as tensors (float32, scene frame). N nodes, H history and T future steps."""

    scene_id: str
    now_step: int
    track_ids: np.ndarray  # [N] int64; -1 for the ego (node 0)
    track_index: np.ndarray  # [N] index into TrafficScene tracks; -1 for the ego
    frame: SceneFrame
    history: Tensor  # [N, H, HISTORY_FEATURES]
    static: Tensor  # [N, STATIC_FEATURES]
    state0: Tensor  # [N, 5] x, y, yaw, v, yaw_rate (scene frame)
    crops: Tensor  # [N, CROP_CHANNELS, Hc, Wc] uint8-quantised map patches (see dequantise_crops)
    future: Tensor  # [N, T, 3] x, y, yaw (scene frame); 0 where unknown
    future_mask: Tensor  # [N, T] bool
    sizes: Tensor  # [N, 2] length, width
    is_ego: Tensor  # [N] bool

    @property
    def n_nodes(self) -> int:
        return len(self.track_ids)


@dataclass
class Batch:
    """Samples padded to the largest node count: every tensor gains a leading B and ``node_mask`` [B, N]."""

    history: Tensor  # [B, N, H, HISTORY_FEATURES]
    static: Tensor  # [B, N, STATIC_FEATURES]
    state0: Tensor  # [B, N, 5]
    crops: Tensor  # [B, N, C, Hc, Wc] float32 in [-1, 1]
    future: Tensor  # [B, N, T, 3]
    future_mask: Tensor  # [B, N, T] bool
    sizes: Tensor  # [B, N, 2]
    is_ego: Tensor  # [B, N] bool
    node_mask: Tensor  # [B, N] bool

    def to(self, device: torch.device | str) -> "Batch":
        """The same batch on ``device`` (itself when already there)."""
        return Batch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})


def finite_rates(xy: np.ndarray, yaw: np.ndarray, present: np.ndarray, dt: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # [S,2],[S],[S] -> speed [S], yaw rate [S], ok [S]
    """Speed along the heading and yaw rate per step by central differences (one-sided at gaps and ends);
    ``ok`` is False where the track has no neighbour to difference with."""
    s = len(yaw)
    prev_ok = np.zeros(s, dtype=bool)
    next_ok = np.zeros(s, dtype=bool)
    prev_ok[1:] = present[1:] & present[:-1]
    next_ok[:-1] = present[:-1] & present[1:]
    idx = np.arange(s)
    lo = np.where(prev_ok, idx - 1, idx)
    hi = np.where(next_ok, idx + 1, idx)
    span = (hi - lo) * dt
    ok = present & (hi > lo)
    span = np.where(ok, span, 1.0)
    vel = (xy[hi] - xy[lo]) / span[:, None]
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    speed = np.maximum(np.einsum("sk,sk->s", vel, heading), 0.0)
    yaw_rate = wrap_angle(yaw[hi] - yaw[lo]) / span
    speed[~ok] = 0.0
    yaw_rate[~ok] = 0.0
    return speed, yaw_rate, ok


def quantise_crops(crops: Tensor) -> Tensor:  # [..., C, H, W] float in [-1, 1] -> uint8
    return ((crops.clamp(-1.0, 1.0) + 1.0) * 127.5).round().to(torch.uint8)


def dequantise_crops(crops: Tensor) -> Tensor:  # uint8 -> float32 in [-1, 1]
    return crops.to(torch.float32) / 127.5 - 1.0


def build_sample(traffic: TrafficScene, now_step: int, history_steps: int, future_steps: int,
                 crop_spec: CropSpec = CropSpec()) -> SceneSample:
    """Nodes (ego first, then vehicles present at ``now_step``), their histories, states and map patches, and
    the logged future over ``future_steps`` (masked where the log ends or the track is absent)."""
    s = traffic.n_steps
    frame = SceneFrame(traffic.ego_xy[now_step].copy(), float(traffic.ego_yaw[now_step]))
    vehicle = traffic.is_vehicle()
    nodes = [int(i) for i in np.flatnonzero(vehicle & traffic.present[:, now_step])]
    n = 1 + len(nodes)
    ego_present = np.ones(s, dtype=bool)
    tracks = [(traffic.ego_xy, traffic.ego_yaw, ego_present, traffic.ego_box.length, traffic.ego_box.width, "car")]
    for i in nodes:
        tracks.append((traffic.xy[i], traffic.yaw[i], traffic.present[i], traffic.sizes[i, 0], traffic.sizes[i, 1],
                       traffic.categories[i]))

    hist_steps = np.arange(now_step - history_steps + 1, now_step + 1)
    fut_steps = np.arange(now_step + 1, now_step + 1 + future_steps)
    history = np.zeros((n, history_steps, HISTORY_FEATURES), dtype=np.float64)
    static = np.zeros((n, STATIC_FEATURES), dtype=np.float64)
    state0 = np.zeros((n, 5), dtype=np.float64)
    future = np.zeros((n, future_steps, 3), dtype=np.float64)
    future_mask = np.zeros((n, future_steps), dtype=bool)
    sizes = np.zeros((n, 2), dtype=np.float64)
    world_xy0 = np.zeros((n, 2))
    world_yaw0 = np.zeros(n)
    for k, (xy, yaw, present, length, width, category) in enumerate(tracks):
        speed, yaw_rate, _ = finite_rates(xy, yaw, present, traffic.dt)
        p0, h0 = xy[now_step], float(yaw[now_step])
        world_xy0[k], world_yaw0[k] = p0, h0
        c, sn = np.cos(h0), np.sin(h0)
        # history in the agent's own frame at the now step
        valid_h = np.zeros(history_steps, dtype=bool)
        inside = (hist_steps >= 0)
        valid_h[inside] = present[hist_steps[inside]]
        hs = np.clip(hist_steps, 0, s - 1)
        d = xy[hs] - p0
        lx, ly = c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1]
        dyaw = wrap_angle(yaw[hs] - h0)
        feats = np.stack([lx / POSITION_SCALE, ly / POSITION_SCALE, np.cos(dyaw), np.sin(dyaw),
                          speed[hs] / SPEED_SCALE, yaw_rate[hs], np.ones(history_steps)], -1)
        history[k] = np.where(valid_h[:, None], feats, 0.0)
        # state at the now step (scene frame)
        (sx, sy), syaw = frame.to_scene(p0), wrap_angle(h0 - frame.yaw)
        state0[k] = [sx, sy, syaw, speed[now_step], yaw_rate[now_step]]
        onehot = np.zeros(len(NODE_CATEGORIES))
        if category in NODE_CATEGORIES:
            onehot[NODE_CATEGORIES.index(category)] = 1.0
        static[k] = [length / SIZE_SCALE, width / SIZE_SCALE, *onehot, float(k == 0),
                     speed[now_step] / SPEED_SCALE, yaw_rate[now_step]]
        sizes[k] = [length, width]
        # logged future (scene frame)
        inside = fut_steps < s
        fs = np.clip(fut_steps, 0, s - 1)
        future_mask[k] = inside & present[fs]
        fxy, fyaw = frame.to_scene(xy[fs], yaw[fs])
        future[k] = np.where(future_mask[k][:, None], np.concatenate([fxy, fyaw[:, None]], -1), 0.0)

    obstacles = [i for i in np.flatnonzero(traffic.present[:, now_step]) if i not in set(nodes)]
    boxes = np.array([[*traffic.xy[i, now_step], traffic.yaw[i, now_step], *traffic.sizes[i, :2]] for i in obstacles],
                     dtype=np.float64).reshape(-1, 5)
    crops = traffic.map.crops(world_xy0, world_yaw0, crop_spec, extra=traffic.map.footprint_layer(boxes))
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return SceneSample(
        scene_id=traffic.scene_id, now_step=int(now_step),
        track_ids=np.array([-1] + [int(traffic.track_ids[i]) for i in nodes], dtype=np.int64),
        track_index=np.array([-1] + nodes, dtype=np.int64), frame=frame,
        history=f32(history), static=f32(static), state0=f32(state0), crops=quantise_crops(crops),
        future=f32(future), future_mask=torch.from_numpy(future_mask), sizes=f32(sizes),
        is_ego=torch.from_numpy(np.arange(n) == 0),
    )


def collate(samples: list[SceneSample]) -> Batch:
    """Pad samples to the largest node count (padding nodes are masked out everywhere)."""
    b = len(samples)
    n = max(s.n_nodes for s in samples)
    t = max(s.future.shape[1] for s in samples)

    def pad(get, shape_tail, dtype):
        out = torch.zeros((b, n, *shape_tail), dtype=dtype)
        for k, s in enumerate(samples):
            v = get(s)
            out[(k, slice(0, v.shape[0])) + tuple(slice(0, d) for d in v.shape[1:])] = v
        return out

    first = samples[0]
    crops = pad(lambda s: s.crops, first.crops.shape[1:], torch.uint8)
    node_mask = torch.zeros((b, n), dtype=torch.bool)
    for k, s in enumerate(samples):
        node_mask[k, : s.n_nodes] = True
    return Batch(
        history=pad(lambda s: s.history, first.history.shape[1:], torch.float32),
        static=pad(lambda s: s.static, first.static.shape[1:], torch.float32),
        state0=pad(lambda s: s.state0, (5,), torch.float32),
        crops=dequantise_crops(crops) * node_mask[:, :, None, None, None],
        future=pad(lambda s: s.future, (t, 3), torch.float32),
        future_mask=pad(lambda s: s.future_mask, (t,), torch.bool),
        sizes=pad(lambda s: s.sizes, (2,), torch.float32),
        is_ego=pad(lambda s: s.is_ego, (), torch.bool),
        node_mask=node_mask,
    )


def batch_field_names() -> list[str]:
    return [f.name for f in fields(Batch)]
