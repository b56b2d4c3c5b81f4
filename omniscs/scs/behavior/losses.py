"""The losses of behaviour-variant synthesis (L_beh, L_restore, latent fits) and the box and disc geometry they use."""
from __future__ import annotations

import torch
from torch import Tensor

#: Small constant inside square roots so distances are differentiable at 0.
DIST_EPS = 1e-6
#: Temperature of the soft minimum over time of the box gap in the interception and feasibility searches (metres).
INTERCEPT_SOFTMIN_M = 0.3


def behavior_loss(agent_xy: Tensor,  # [N, T, 2] agent box centres
                  plan_xy: Tensor,   # [T, 2] planner's box centre
                  mask: Tensor,      # [N, T] bool: which agents and steps take part
                  ) -> tuple[Tensor, Tensor]:  # L_beh (scalar), weights delta [N, T]
    """L_beh = sum_{i,t} delta_t^i ||T_t^i - T_t^plan||², delta = softmax over (i, t) of -||T_t^i - T_t^plan||.

    The softmax is taken in log space (log-sum-exp), so agents hundreds of metres or kilometres away give
    weights of exactly 0, never 0/0; with no participating entry the loss is 0.
    """
    d2 = ((agent_xy - plan_xy[None]) ** 2).sum(-1)
    if not bool(mask.any()):
        return d2.sum() * 0.0, torch.zeros_like(d2)
    d = torch.sqrt(d2 + DIST_EPS)
    logits = torch.where(mask, -d, torch.full_like(d, -float("inf")))
    # exp(logit - max) / sum(...): the log-sum-exp shift, normalised after the shift so that the weights sum
    # to 1 to float precision even when every distance is ~1e6 m (subtracting the full log-sum-exp would not)
    delta = torch.softmax(logits.reshape(-1), dim=0).reshape(d.shape)
    delta = torch.where(mask, delta, torch.zeros_like(d))
    return (delta * d2).sum(), delta


def restore_loss(z: Tensor, z_init: Tensor, mask: Tensor) -> Tensor:  # [N, Z], [N, Z], [N] bool -> scalar
    """L_restore = sum over masked agents of ||z - z_init||²."""
    return (((z - z_init) ** 2).sum(-1) * mask).sum()


def disc_centres(xyyaw: Tensor,  # [A, T, 3]
                 sizes: Tensor,  # [A, 2] length, width
                 ) -> tuple[Tensor, Tensor]:  # centres [A, 3, T, 2], radii [A]
    """Three discs of radius width/2 along each box's length (front, middle, back): a smooth stand-in for
    the box in the collision penalty."""
    length, width = sizes[:, 0], sizes[:, 1]
    reach = (0.5 * length - 0.5 * width).clamp_min(0.0)
    offsets = torch.stack([-reach, torch.zeros_like(reach), reach], 1)  # [A, 3]
    heading = torch.stack([torch.cos(xyyaw[..., 2]), torch.sin(xyyaw[..., 2])], -1)  # [A, T, 2]
    centres = xyyaw[:, None, :, :2] + offsets[:, :, None, None] * heading[:, None]
    return centres, 0.5 * width


def disc_overlap(centres_a: Tensor, radii_a: Tensor,  # [..., 3, T, 2], [...]
                 centres_b: Tensor, radii_b: Tensor,  # [..., 3, T, 2], [...] (leading dims broadcast)
                 clearance: float) -> Tensor:         # [..., T]
    """Squared overlap, summed over the 3 x 3 disc pairs, of discs a and b grown to keep ``clearance`` apart."""
    diff = centres_a[..., :, None, :, :] - centres_b[..., None, :, :, :]  # [..., 3, 3, T, 2]
    dist = torch.sqrt((diff ** 2).sum(-1) + DIST_EPS)
    need = (radii_a + radii_b + clearance)[..., None, None, None]
    return (torch.nn.functional.relu(need - dist) ** 2).sum((-3, -2))


def box_gap(xyyaw: Tensor,                  # [S, T, 3] agent box centres and headings
            size: tuple[float, float],      # agent length, width
            plan: Tensor,                   # [T, 3] ego box centre and heading
            ego_size: tuple[float, float],  # ego length, width
            ) -> Tensor:                    # [S, T] metres, negative when the boxes overlap
    """Separating-axis gap of two rotated boxes: the largest, over both boxes' axes, of the distance between the
    centres projected on the axis minus both boxes' projected half extents. Positive: apart (a lower bound of the
    distance); negative: overlapping, by minus the penetration depth."""
    d = xyyaw[..., :2] - plan[:, :2]
    rel = xyyaw[..., 2] - plan[:, 2]
    cos_rel, sin_rel = torch.cos(rel).abs(), torch.sin(rel).abs()
    ego_l, ego_w, l, w = 0.5 * ego_size[0], 0.5 * ego_size[1], 0.5 * size[0], 0.5 * size[1]
    ce, se = torch.cos(plan[:, 2]), torch.sin(plan[:, 2])
    ca, sa = torch.cos(xyyaw[..., 2]), torch.sin(xyyaw[..., 2])
    gaps = torch.stack([
        (ce * d[..., 0] + se * d[..., 1]).abs() - ego_l - (l * cos_rel + w * sin_rel),  # ego's heading
        (-se * d[..., 0] + ce * d[..., 1]).abs() - ego_w - (l * sin_rel + w * cos_rel),  # ego's side
        (ca * d[..., 0] + sa * d[..., 1]).abs() - l - (ego_l * cos_rel + ego_w * sin_rel),  # agent's heading
        (-sa * d[..., 0] + ca * d[..., 1]).abs() - w - (ego_l * sin_rel + ego_w * cos_rel),  # agent's side
    ], -1)
    return gaps.max(-1).values


def track_fit_loss(states: Tensor,  # [N, T, >=3] decoded x, y, yaw
                   target: Tensor,  # [N, T, >=3] x, y, yaw to reproduce
                   mask: Tensor,    # [N, T] bool: which entries count
                   ) -> Tensor:     # scalar: mean Huber position error (1 m knee) + (1 - cos) heading error
    """How far decoded trajectories are from the ones to reproduce (fitting latents to the log or to a path)."""
    err = torch.sqrt(((states[..., :2] - target[..., :2]) ** 2).sum(-1) + DIST_EPS)
    huber = torch.where(err < 1.0, 0.5 * err * err, err - 0.5)
    yaw = 1.0 - torch.cos(states[..., 2] - target[..., 2])
    return ((huber + yaw) * mask).sum() / mask.sum().clamp_min(1)
