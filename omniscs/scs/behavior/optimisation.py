"""Optimising one variant: its latents under L_adv, the interception search, its warm start and knot fallback."""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from omniscs.scs.behavior.adversarial_config import NEAR_PAIR_MARGIN_M
from omniscs.scs.behavior.evaluation import (VariantResult, evaluate, plausibility_penalty, variant_result,
                                             weighted_penalty)
from omniscs.scs.behavior.kinematics import accelerations
from omniscs.scs.behavior.losses import (INTERCEPT_SOFTMIN_M, behavior_loss, box_gap, disc_centres, disc_overlap,
                                         restore_loss, track_fit_loss)
from omniscs.scs.behavior.model import Decoded
from omniscs.scs.behavior.problem import BehaviorProblem, to_numpy


def optimise(problem: BehaviorProblem, adversary: int, window: tuple[int, int], variant_id: str, reachable: bool,
             on_step: Callable[[int], None] | None = None,
             z_start: Tensor | None = None,  # [N, Z] a warm start; None: the fitted latents
             ) -> VariantResult:
    """Optimise all latents so that node ``adversary`` meets the ego plan within horizon steps ``window``,
    starting from ``z_start`` or the fitted latents; L_restore measures the distance to the fitted latents, i.e.
    to the log, either way. Keeps the best checked step (see ``evaluation.outcome``)."""
    cfg, device = problem.config, problem.device
    started = time.perf_counter()
    z_init = problem.z_fit
    z = (z_init if z_start is None else z_start).clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=cfg.lr)
    beh_mask = torch.zeros(problem.n_nodes, problem.horizon, dtype=torch.bool, device=device)
    beh_mask[adversary, window[0]:window[1]] = True
    restore_mask = torch.ones(problem.n_nodes, device=device)
    restore_mask[0] = 0.0  # the ego's latent stays: its trajectory is the planner's
    plan_np = problem.plan(problem.fitted_np)
    best: tuple | None = None
    it = 0
    for it in range(cfg.iterations + 1):
        final = it == cfg.iterations
        dec = problem.decode(z)
        plan = torch.from_numpy(plan_np).to(device, torch.float32)
        l_beh, _ = behavior_loss(dec.states[..., :2], plan[:, :2], beh_mask)
        l_restore = restore_loss(z, z_init, restore_mask)
        pen = plausibility_penalty(problem, dec, plan, adversary) if cfg.uses_plausibility_penalty else {}
        l_plaus = weighted_penalty(cfg, pen) if pen else l_beh * 0.0
        term = problem.render_consistency
        l_app = term(problem.world_trajectories(dec.states)) if term is not None else None
        total = cfg.beh_weight * l_beh + cfg.restore_weight * l_restore + l_plaus
        if l_app is not None:
            total = total + cfg.app_weight * l_app
        if it % cfg.check_every == 0 or final:
            states_np = to_numpy(dec.states)
            eval_plan = problem.plan(states_np)
            ev = evaluate(problem, states_np, dec.longitudinal_accel.detach().cpu().numpy(),
                          dec.lateral_accel.detach().cpu().numpy(), eval_plan, adversary)
            losses = {"L_adv": float(total.detach()), "L_beh": float(l_beh.detach()),
                      "L_app": None if l_app is None else float(l_app.detach()),
                      "L_restore": float(l_restore.detach()), "L_plaus": float(l_plaus.detach())}
            score = (ev.success and ev.plausible, ev.success, -len(ev.violations), -ev.min_distance_m)
            if best is None or score > best[0]:
                best = (score, states_np, eval_plan, ev, losses, it)
            if cfg.stop_on_success and ev.success and ev.plausible:
                break
        if final:
            break
        opt.zero_grad()
        total.backward()
        z.grad[0] = 0.0
        opt.step()
        if cfg.planner.kind == "rule" and it % cfg.replan_every == 0:
            plan_np = problem.plan(to_numpy(dec.states))
        if on_step:
            on_step(it)
    _, states_np, plan_np, ev, losses, best_it = best
    return variant_result(problem, variant_id, adversary, window, reachable, states_np, plan_np, ev, losses, best_it,
                          time.perf_counter() - started)


# ----------------------------------------------------------------------------- interception search
def obstacles(problem: BehaviorProblem, node: int) -> tuple[Tensor, Tensor, Tensor] | None:
    """Everyone but the ego and ``node`` that ``node`` could meet within the horizon, along their fitted or
    replayed trajectories: disc centres [A, 3, T, 2], radii [A], and where each counts [A, T] (present, and
    not already overlapping ``node`` in the log). None when nobody is near."""
    xyyaw, present, sizes, _ = problem.objects(problem.fitted_np, problem.logged_plan, node)
    state0 = problem.state0_np[node]
    travel = state0[3] * problem.horizon * problem.traffic.dt + 0.5 * problem.config.reach_accel_long * (
        problem.horizon * problem.traffic.dt) ** 2
    reach = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1])
    near = np.linalg.norm(xyyaw[..., :2] - state0[:2], axis=-1).min(-1) <= travel + reach + reach[node] \
        + NEAR_PAIR_MARGIN_M
    near[[0, node]] = False
    idx = np.flatnonzero(near)
    if not len(idx):
        return None
    centres, radii = disc_centres(torch.from_numpy(xyyaw[idx]).to(problem.device, torch.float32),
                                  torch.from_numpy(sizes[idx]).to(problem.device, torch.float32))
    valid = present[idx] & ~problem.log_overlaps[node, idx]
    return centres, radii, torch.from_numpy(valid).to(problem.device, torch.float32)


def intercept(problem: BehaviorProblem, node: int, window: tuple[int, int],
              plan: np.ndarray,  # [T, 3] ego plan (scene frame)
              generator: torch.Generator,  # CPU generator of the random starts (the same on every device)
              ) -> tuple[Tensor, float]:  # states [T, 5] (scene frame), smallest gap in the window, metres
    """A trajectory of ``node`` that meets the ego plan within horizon steps ``window``, searched directly
    over the decoder's control knots (through the same bounds and bicycle rollout, so it is comfortable when
    decoding is). From the node's fitted knots and ``intercept_samples - 1`` random perturbations of them, Adam
    minimises the soft minimum over the window of the box gap (``box_gap``, down to minus
    ``intercept_depth_m``), a pull toward the fitted knots and, with the plausibility penalty's weights,
    overlap with the others' fitted trajectories and leaving the road. Returns the best sample's states and
    its smallest gap in the window (negative: overlap)."""
    cfg, device = problem.config, problem.device
    n_samples = cfg.intercept_samples
    base = problem.fitted_knots[node]  # [K, 2]
    noise = torch.randn((n_samples, *base.shape), generator=generator, device=generator.device) * cfg.intercept_noise
    noise[0] = 0.0
    knots = (base + noise.to(device)).requires_grad_(True)
    opt = torch.optim.Adam([knots], lr=cfg.intercept_lr)
    state0 = problem.state0[node].expand(n_samples, 1, 5)
    target = torch.from_numpy(plan).to(device, torch.float32)
    in_window = torch.zeros(problem.horizon, dtype=torch.bool, device=device)
    in_window[window[0]:window[1]] = True
    size = tuple(float(x) for x in problem.node_sizes_np[node])
    others = obstacles(problem, node) if cfg.collision_weight else None
    offroad = bool(cfg.offroad_weight and problem.onroad_now[node])
    relu = torch.nn.functional.relu
    for it in range(cfg.intercept_iterations + 1):
        states = problem.model.roll_knots(knots[:, None], state0, problem.horizon, problem.comfort_limits,
                                          cfg.standstill_gradient).states[:, 0]  # [S, T, 5]
        gap = box_gap(states, size, target, problem.ego_size).clamp_min(-cfg.intercept_depth_m)
        gap = torch.where(in_window, gap, torch.full_like(gap, float("inf")))
        soft = -INTERCEPT_SOFTMIN_M * torch.logsumexp(-gap / INTERCEPT_SOFTMIN_M, -1)  # [S]
        objective = soft + cfg.intercept_effort_weight * ((knots - base) ** 2).mean((1, 2))
        if others is not None:
            centres, radii, valid = others
            mine, my_radius = disc_centres(states[..., :3], problem.node_sizes[node].expand(n_samples, 2))
            overlap = disc_overlap(mine[:, None], my_radius[:, None], centres[None], radii[None],
                                   cfg.clearance_m)  # [S, A, T]
            objective = objective + cfg.collision_weight * (overlap * valid).sum((1, 2))
        if offroad:
            world = problem.frame.to_world(states[..., :3])
            outside = problem.traffic.map.outside_distance(world[..., :2])  # [S, T]
            objective = objective + cfg.offroad_weight * (relu(outside) ** 2).sum(-1)
        if it == cfg.intercept_iterations:
            break
        opt.zero_grad()
        objective.sum().backward()
        opt.step()
    best = int(torch.argmin(objective.detach()))
    return states[best].detach(), float(gap[best].min().detach())


def interception_path(problem: BehaviorProblem, node: int, window: tuple[int, int], restart: int
                      ) -> tuple[Tensor, float]:  # states [T, 5], smallest gap m
    """``intercept`` against the plan for the fitted trajectories, with random starts from a generator seeded
    by (seed, node, window, restart); cached on the problem per configuration (warm starts and the knot fallback
    share it)."""
    cfg = problem.config
    key = (cfg, node, tuple(window), restart)
    if key not in problem.intercept_cache:
        seed = np.random.SeedSequence([cfg.seed, node, window[0], window[1], restart]).generate_state(1)[0]
        plan = problem.plan(problem.fitted_np)
        states, gap = intercept(problem, node, window, plan, torch.Generator(device="cpu").manual_seed(int(seed)))
        problem.intercept_cache[key] = (states.detach(), gap)
    return problem.intercept_cache[key]


def warm_start(problem: BehaviorProblem, node: int, window: tuple[int, int], restart: int) -> Tensor:  # -> [N, Z]
    """The fitted latents with ``node``'s latent refitted to an interception path (``interception_path``)."""
    cfg, device = problem.config, problem.device
    target, _ = interception_path(problem, node, window, restart)
    mask = torch.zeros(problem.n_nodes, problem.horizon, dtype=torch.bool, device=device)
    mask[node] = True
    full_target = torch.zeros(problem.n_nodes, problem.horizon, 3, device=device)
    full_target[node] = target[:, :3]
    z = problem.z_fit.clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=cfg.warm_fit_lr)
    for _ in range(cfg.warm_fit_iterations):
        loss = track_fit_loss(problem.decode(z).states, full_target, mask)
        opt.zero_grad()
        loss.backward()
        keep = z.grad[node].clone()
        z.grad.zero_()
        z.grad[node] = keep  # only the adversary's latent moves
        opt.step()
    return z.detach()


def knot_variant(problem: BehaviorProblem, node: int, window: tuple[int, int], restart: int, variant_id: str,
                 reachable: bool) -> VariantResult:
    """The variant in which ``node`` follows its interception path (restart ``restart``) and every other
    agent its reconstruction: evaluated, and its losses measured, exactly as an optimised variant."""
    cfg, device = problem.config, problem.device
    started = time.perf_counter()
    path, _ = interception_path(problem, node, window, restart)
    states = problem.fitted.states.detach().clone()
    lon, lat = problem.fitted.longitudinal_accel.detach().clone(), problem.fitted.lateral_accel.detach().clone()
    states[node] = path.to(states.dtype)
    lon[node], lat[node] = accelerations(problem.state0[node].to(states.dtype), states[node], problem.traffic.dt)
    states_np = to_numpy(states)
    plan_np = problem.plan(states_np)
    ev = evaluate(problem, states_np, lon.cpu().numpy(), lat.cpu().numpy(), plan_np, node)
    plan = torch.from_numpy(plan_np).to(device, torch.float32)
    beh_mask = torch.zeros(problem.n_nodes, problem.horizon, dtype=torch.bool, device=device)
    beh_mask[node, window[0]:window[1]] = True
    with torch.no_grad():
        l_beh = float(behavior_loss(states[..., :2], plan[:, :2], beh_mask)[0])
        pen = plausibility_penalty(problem, Decoded(states, lon, lat), plan, node) \
            if cfg.uses_plausibility_penalty else {}
        l_plaus = float(weighted_penalty(cfg, pen)) if pen else 0.0
        term = problem.render_consistency
        l_app = None if term is None else float(term(problem.world_trajectories(states)))
    total = cfg.beh_weight * l_beh + l_plaus + (0.0 if l_app is None else cfg.app_weight * l_app)
    losses = {"L_adv": total, "L_beh": l_beh, "L_app": l_app, "L_restore": 0.0, "L_plaus": l_plaus}
    result = variant_result(problem, variant_id, node, window, reachable, states_np, plan_np, ev, losses, 0,
                            time.perf_counter() - started)
    result.source = "knots"
    return result
