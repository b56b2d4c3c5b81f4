"""The traffic model: a graph network over agents with a latent per agent (prior and posterior, KL-regularised)
and a decoder whose controls are rolled through the kinematic bicycle model (STRIVE-like)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import torch
from torch import Tensor, nn

from omniscs.comfort import ComfortBounds
from omniscs.scs.behavior.features import (CROP_CHANNELS, FUTURE_FEATURES, HISTORY_FEATURES, POSITION_SCALE,
                                           SPEED_SCALE, STATIC_FEATURES, Batch)
from omniscs.scs.behavior.kinematics import (KinematicLimits, accelerations, bound_controls, rollout,
                                             soft_clip_accel)
from omniscs.scs.behavior.maps import CropSpec

#: Edge features: dx, dy, distance (receiver's frame, clipped), cos/sin relative yaw, relative velocity.
EDGE_FEATURES = 7
#: Relative positions are divided by this and clipped to +-EDGE_CLIP, so far agents stay finite features.
EDGE_SCALE_M, EDGE_CLIP = 20.0, 5.0


@dataclass(frozen=True)
class ModelConfig:
    """Architecture and time grid of the traffic model."""

    dt: float = 0.1
    """Seconds per step (the synthetic logs' 10 Hz)."""
    history_steps: int = 10
    """Observed steps up to and including the now step (1 s)."""
    future_steps: int = 30
    """Longest decoded horizon, steps (3 s); shorter horizons use the first steps."""
    hidden: int = 64
    """Width of node embeddings and MLPs."""
    latent: int = 32
    """Size of each agent's latent vector."""
    graph_rounds: int = 2
    """Message-passing rounds in the past encoder and in the decoder."""
    edge_radius_m: float = 60.0
    """Agents further apart than this exchange no messages."""
    control_knots: int = 10
    """Controls are decoded at this many knots and interpolated linearly to every step (smooth controls)."""
    min_logvar: float = -2.0
    """Lower clamp of predicted latent log-variances (posterior std >= 0.37): the decoder is trained on a
    neighbourhood of every latent, so nearby latents decode to nearby manoeuvres (a usable control space)."""
    max_logvar: float = 4.0
    """Upper clamp of predicted latent log-variances."""
    crop: CropSpec = field(default_factory=CropSpec)
    """Map patch each agent sees."""
    limits: KinematicLimits = field(default_factory=KinematicLimits)
    """Physical bounds of decoded trajectories."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        d = dict(d)
        d["crop"] = CropSpec(**d["crop"])
        d["limits"] = KinematicLimits(**d["limits"])
        return cls(**d)


def mlp(d_in: int, d_hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d_hidden), nn.SiLU(), nn.Linear(d_hidden, d_out))


def edge_features(state0: Tensor,     # [B, N, 5] x, y, yaw, v, yaw_rate (scene frame)
                  node_mask: Tensor,  # [B, N] bool
                  radius_m: float,
                  ) -> tuple[Tensor, Tensor]:  # features [B, N, N, EDGE_FEATURES] (receiver i, sender j), mask [B, N, N]
    """Pose of every sender j in every receiver i's frame, and which pairs are close enough to talk."""
    x, y, yaw, v = state0[..., 0], state0[..., 1], state0[..., 2], state0[..., 3]
    dx = x[:, None, :] - x[:, :, None]
    dy = y[:, None, :] - y[:, :, None]
    c, s = torch.cos(yaw)[:, :, None], torch.sin(yaw)[:, :, None]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    dist = torch.sqrt(dx * dx + dy * dy + 1e-12)
    dyaw = yaw[:, None, :] - yaw[:, :, None]
    rel_vx = v[:, None, :] * torch.cos(dyaw) - v[:, :, None]
    rel_vy = v[:, None, :] * torch.sin(dyaw)
    clip = lambda t: (t / EDGE_SCALE_M).clamp(-EDGE_CLIP, EDGE_CLIP)  # noqa: E731
    feats = torch.stack([clip(lx), clip(ly), clip(dist), torch.cos(dyaw), torch.sin(dyaw),
                         rel_vx / SPEED_SCALE, rel_vy / SPEED_SCALE], -1)
    n = state0.shape[1]
    eye = torch.eye(n, dtype=torch.bool, device=state0.device)[None]
    mask = node_mask[:, :, None] & node_mask[:, None, :] & ~eye & (dist < radius_m)
    return feats * mask[..., None], mask


class GraphBlock(nn.Module):
    """One round of message passing: mean of MLP messages from neighbours, residual update, layer norm."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.receiver = nn.Linear(dim, dim)
        self.sender = nn.Linear(dim, dim, bias=False)
        self.edge = nn.Linear(EDGE_FEATURES, dim, bias=False)
        self.update = mlp(2 * dim, dim, dim)
        self.norm = nn.LayerNorm(dim)

    def forward(self, h: Tensor,      # [B, N, D]
                edges: Tensor,         # [B, N, N, EDGE_FEATURES]
                edge_mask: Tensor,     # [B, N, N] bool
                ) -> Tensor:           # [B, N, D]
        pre = self.receiver(h)[:, :, None] + self.sender(h)[:, None, :] + self.edge(edges)
        # A one-layer message (linear parts split per receiver/sender/edge, so nothing costs N^2 D^2).
        m = nn.functional.silu(pre) * edge_mask[..., None]
        count = edge_mask.sum(2, keepdim=True).clamp_min(1).to(h.dtype)  # a lone agent gets a zero message
        agg = m.sum(2) / count
        return self.norm(h + self.update(torch.cat([h, agg], -1)))


class MapEncoder(nn.Module):
    """A small CNN over each agent's map patch."""

    def __init__(self, crop: CropSpec, dim: int) -> None:
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv2d(CROP_CHANNELS, 8, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(8, 16, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.SiLU(),
        )
        rows, cols = crop.shape
        with torch.no_grad():
            flat = self.conv(torch.zeros(1, CROP_CHANNELS, rows, cols)).numel()
        self.head = nn.Linear(flat, dim)

    def forward(self, crops: Tensor) -> Tensor:  # [B, N, C, Hc, Wc] -> [B, N, D]
        b, n = crops.shape[:2]
        f = self.conv(crops.reshape(b * n, *crops.shape[2:]))
        return self.head(f.reshape(b * n, -1)).reshape(b, n, -1)


@dataclass
class Decoded:
    """Decoded trajectories (scene frame) and the accelerations they imply."""

    states: Tensor  # [B, N, T, 5] x, y, yaw, v, yaw_rate at steps 1..T
    longitudinal_accel: Tensor  # [B, N, T] m/s²
    lateral_accel: Tensor  # [B, N, T] m/s²


class TrafficModel(nn.Module):
    """Past encoder (history MLP + map CNN + graph), Gaussian prior and posterior over per-agent latents, and
    a graph decoder of smooth controls rolled through the bicycle model from each agent's current state."""

    def __init__(self, config: ModelConfig = ModelConfig()) -> None:
        super().__init__()
        self.config = config
        d, z = config.hidden, config.latent
        self.history_encoder = mlp(config.history_steps * HISTORY_FEATURES + STATIC_FEATURES, 2 * d, d)
        self.map_encoder = MapEncoder(config.crop, d)
        self.node_init = mlp(2 * d, d, d)
        self.past_graph = nn.ModuleList([GraphBlock(d) for _ in range(config.graph_rounds)])
        self.prior_head = mlp(d, d, 2 * z)
        self.future_encoder = mlp(config.future_steps * FUTURE_FEATURES, 2 * d, d)
        self.posterior_in = mlp(2 * d, d, d)
        self.posterior_graph = GraphBlock(d)
        self.posterior_head = mlp(d, d, 2 * z)
        self.decoder_in = mlp(d + z, d, d)
        self.decoder_graph = nn.ModuleList([GraphBlock(d) for _ in range(config.graph_rounds)])
        self.control_head = mlp(d, 2 * d, 2 * config.control_knots)
        # A direct linear path from an agent's latent to its control knots keeps the decoder responsive to z
        # everywhere (its gradient cannot vanish in saturated hidden units).
        self.latent_controls = nn.Linear(z, 2 * config.control_knots, bias=False)

    # -- encoders ---------------------------------------------------------------------------------------
    def encode_past(self, batch: Batch) -> tuple[Tensor, Tensor, Tensor]:
        """Context [B, N, D] of every node given the past and the map, plus the edges used by every graph."""
        b, n = batch.node_mask.shape
        hist = torch.cat([batch.history.reshape(b, n, -1), batch.static], -1)
        h = self.node_init(torch.cat([self.history_encoder(hist), self.map_encoder(batch.crops)], -1))
        edges, edge_mask = edge_features(batch.state0, batch.node_mask, self.config.edge_radius_m)
        for block in self.past_graph:
            h = block(h, edges, edge_mask)
        return h * batch.node_mask[..., None], edges, edge_mask

    def _gaussian(self, out: Tensor) -> tuple[Tensor, Tensor]:
        mu, logvar = out.chunk(2, dim=-1)
        return mu, logvar.clamp(self.config.min_logvar, self.config.max_logvar)

    def prior(self, context: Tensor) -> tuple[Tensor, Tensor]:  # [B, N, D] -> mu, logvar [B, N, Z]
        return self._gaussian(self.prior_head(context))

    def future_features(self, batch: Batch) -> Tensor:  # -> [B, N, T_max * FUTURE_FEATURES]
        """Each node's logged future in its own frame at the now step (zero-padded to the longest horizon)."""
        x0, y0, yaw0 = batch.state0[..., 0:1], batch.state0[..., 1:2], batch.state0[..., 2:3]
        dx, dy = batch.future[..., 0] - x0, batch.future[..., 1] - y0
        c, s = torch.cos(yaw0), torch.sin(yaw0)
        dyaw = batch.future[..., 2] - yaw0
        m = batch.future_mask.to(dx.dtype)
        f = torch.stack([(c * dx + s * dy) / POSITION_SCALE, (-s * dx + c * dy) / POSITION_SCALE,
                         torch.cos(dyaw), torch.sin(dyaw), torch.ones_like(dx)], -1) * m[..., None]
        t_max = self.config.future_steps
        if f.shape[2] < t_max:
            f = torch.cat([f, f.new_zeros(f.shape[0], f.shape[1], t_max - f.shape[2], FUTURE_FEATURES)], 2)
        return f[:, :, :t_max].reshape(f.shape[0], f.shape[1], -1)

    def posterior(self, context: Tensor, batch: Batch, edges: Tensor, edge_mask: Tensor) -> tuple[Tensor, Tensor]:
        """q(z | past, future of every agent): mu, logvar [B, N, Z]."""
        h = self.posterior_in(torch.cat([context, self.future_encoder(self.future_features(batch))], -1))
        h = self.posterior_graph(h, edges, edge_mask)
        return self._gaussian(self.posterior_head(h))

    # -- decoder ----------------------------------------------------------------------------------------
    def decode(self, context: Tensor, z: Tensor, batch: Batch, edges: Tensor, edge_mask: Tensor,
               horizon: int | None = None, comfort: ComfortBounds | None = None,
               standstill_gradient: float = 0.0) -> Decoded:
        """Trajectories [B, N, T, 5] for latents ``z`` [B, N, Z]; T = horizon (default future_steps).

        With ``comfort``, accelerations are softly saturated into its bounds and the yaw rate is bounded by its
        lateral-acceleration and yaw-rate limits, so every decoded trajectory is comfortable by construction
        (used for adversarial synthesis; training and ADE/FDE use the physical limits only).
        ``standstill_gradient``: see ``kinematics.rollout`` (adversarial optimisation only)."""
        knots = self.control_knots(context, z, edges, edge_mask)
        return self.roll_knots(knots, batch.state0, horizon, comfort, standstill_gradient)

    def control_knots(self, context: Tensor,    # [B, N, D]
                      z: Tensor,                # [B, N, Z]
                      edges: Tensor, edge_mask: Tensor,
                      ) -> Tensor:              # [B, N, control_knots, 2] raw (unbounded) accel, yaw accel
        """The decoder's raw control knots before bounding and interpolation."""
        h = self.decoder_in(torch.cat([context, z], -1))
        for block in self.decoder_graph:
            h = block(h, edges, edge_mask)
        b, n = z.shape[:2]
        return (self.control_head(h) + self.latent_controls(z)).reshape(b, n, self.config.control_knots, 2)

    def roll_knots(self, knots: Tensor,   # [B, N, control_knots, 2] raw, as control_knots returns
                   state0: Tensor,        # [B, N, 5] x, y, yaw, v, yaw_rate at the now step
                   horizon: int | None = None, comfort: ComfortBounds | None = None,
                   standstill_gradient: float = 0.0) -> Decoded:
        """Raw knots -> interpolated, bounded controls -> bicycle rollout (see ``decode`` for the options)."""
        cfg = self.config
        horizon = cfg.future_steps if horizon is None else int(horizon)
        b, n = knots.shape[:2]
        flat = knots.reshape(b * n, cfg.control_knots, 2).transpose(1, 2)
        raw = nn.functional.interpolate(flat, size=cfg.future_steps, mode="linear", align_corners=True)
        raw = raw.transpose(1, 2).reshape(b, n, cfg.future_steps, 2)[:, :, :horizon]
        controls = bound_controls(raw, cfg.limits)
        limits = cfg.limits
        if comfort is not None:
            accel = soft_clip_accel(controls[..., 0], comfort.max_lon_accel, -comfort.min_lon_accel)
            controls = torch.stack([accel, controls[..., 1]], -1)
            limits = replace(limits, max_lateral_accel=min(limits.max_lateral_accel, comfort.max_abs_lat_accel),
                             max_yaw_rate=min(limits.max_yaw_rate, comfort.max_abs_yaw_rate))
        states = rollout(state0, controls, cfg.dt, limits, standstill_gradient)
        lon, lat = accelerations(state0, states, cfg.dt)
        return Decoded(states, lon, lat)

    # -- training ---------------------------------------------------------------------------------------
    def losses(self, batch: Batch, kl_weight: float, yaw_weight: float = 1.0,
               free_nats_per_dim: float = 0.0) -> dict[str, Tensor]:
        """ELBO terms on a batch: reconstruction (Huber on positions + heading) under posterior samples, and
        KL(q || p) where each latent dimension's first ``free_nats_per_dim`` nats are free ("free bits", which
        keeps the posterior from collapsing onto the prior)."""
        context, edges, edge_mask = self.encode_past(batch)
        mu_q, logvar_q = self.posterior(context, batch, edges, edge_mask)
        mu_p, logvar_p = self.prior(context)
        z = mu_q + torch.randn_like(mu_q) * torch.exp(0.5 * logvar_q)
        horizon = batch.future.shape[2]
        dec = self.decode(context, z, batch, edges, edge_mask, horizon)
        mask = batch.future_mask & batch.node_mask[..., None]
        count = mask.sum().clamp_min(1)
        err = dec.states[..., :2] - batch.future[..., :2]
        dist = torch.sqrt((err * err).sum(-1) + 1e-9)
        huber = torch.where(dist < 1.0, 0.5 * dist * dist, dist - 0.5)
        yaw_err = 1.0 - torch.cos(dec.states[..., 2] - batch.future[..., 2])
        recon = ((huber + yaw_weight * yaw_err) * mask).sum() / count
        kl = 0.5 * (logvar_p - logvar_q + (torch.exp(logvar_q) + (mu_q - mu_p) ** 2) / torch.exp(logvar_p) - 1.0)
        nodes = batch.node_mask.sum().clamp_min(1)
        kl_report = (kl.sum(-1) * batch.node_mask).sum() / nodes
        if free_nats_per_dim > 0:
            per_dim = (kl * batch.node_mask[..., None]).sum((0, 1)) / nodes  # [Z] mean over nodes
            kl_penalty = per_dim.clamp_min(free_nats_per_dim).sum()
        else:
            kl_penalty = kl_report
        ade = (dist * mask).sum() / count
        return {"loss": recon + kl_weight * kl_penalty, "recon": recon, "kl": kl_report, "ade": ade}
