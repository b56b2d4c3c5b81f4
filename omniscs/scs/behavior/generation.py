"""Making N distinct behaviour variants of a scene: the adversary and time-window schedule, retries, fallbacks."""
from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.scs.behavior.adversarial_config import AdversarialConfig
from omniscs.scs.behavior.render_consistency import RenderConsistencyTerm
from omniscs.scs.behavior.checkpoint import set_threads
from omniscs.scs.behavior.evaluation import VariantResult, outcome
from omniscs.scs.behavior.model import TrafficModel
from omniscs.scs.behavior.optimisation import knot_variant, optimise, warm_start
from omniscs.scs.behavior.problem import BehaviorProblem
from omniscs.scs.behavior.tracks import TrafficScene

log = logging.getLogger(__name__)

Candidate = tuple[int, bool, float]  # (node, reachable, closest approach m), as BehaviorProblem.candidates gives


def variant_schedule(candidates: list[Candidate], n_variants: int, horizon: int,
                     windows: tuple[tuple[float, float], ...]) -> list[tuple[int, tuple[int, int], bool]]:
    """(adversary node, horizon window, reachable) for each of ``n_variants``: reachable adversaries in
    turn (all adversaries when none is reachable), then again with the next time window."""
    reachable = [c for c in candidates if c[1]]
    pool = reachable or candidates
    out = []
    for k in range(n_variants):
        node, ok, _ = pool[k % len(pool)]
        lo, hi = windows[(k // len(pool)) % len(windows)]
        start, end = int(round(lo * horizon)), max(int(round(hi * horizon)), int(round(lo * horizon)) + 1)
        out.append((node, (start, min(end, horizon)), ok))
    return out


def optimise_with_fallback(problem: BehaviorProblem, candidates: list[Candidate], node: int,
                           window: tuple[int, int], reachable: bool, index: int,
                           used: set[tuple[int, tuple[int, int]]] | None = None,
                           on_step: Callable[[int], None] | None = None) -> VariantResult:
    """Optimise variant ``index`` with adversary ``node``; while it finds no collision, restart it from warm starts
    (up to ``restarts``); while it fails (no collision, or implausible), try the next reachable candidates the
    same way (up to ``attempts_per_variant`` adversaries) that no earlier variant used with this window, so
    variants stay distinct. Standing candidates (with ``warm_start_standing``) begin with the warm starts and
    start from the fitted latents last. Keeps the best outcome; its time covers every attempt; records its
    (adversary, window) in ``used``. ``on_step(iteration)`` is called after every optimiser step of every try."""
    cfg = problem.config
    used = set() if used is None else used
    others = [(c[0], c[1]) for c in candidates if c[1] and c[0] != node and (c[0], tuple(window)) not in used]
    tries = [(node, reachable)] + others[: max(0, cfg.attempts_per_variant - 1)]
    speed0 = problem.state0_np[:, 3]
    best, seconds = None, 0.0
    for attempt, (n, ok) in enumerate(tries, start=1):
        track = int(problem.traffic.track_ids[problem.node_tracks[n]])
        standing = cfg.warm_start_standing and speed0[n] < cfg.moving_speed
        starts = [*range(cfg.restarts), None] if standing else [None, *range(cfg.restarts)]  # None: fitted latents
        for restart in starts:
            began = time.perf_counter()
            z_start = None if restart is None else warm_start(problem, n, window, restart)
            result = optimise(problem, n, window, f"v{index:02d}-track{track}", ok, z_start=z_start,
                              on_step=on_step)
            seconds += time.perf_counter() - began
            if best is None or outcome(result) > outcome(best):
                best = result
            best.attempts = attempt
            if result.success:
                break
        if cfg.knot_fallback and not (best.success and best.plausible) and cfg.restarts > 0:
            began = time.perf_counter()
            fallback = knot_variant(problem, n, window, 0, f"v{index:02d}-track{track}", ok)
            seconds += time.perf_counter() - began
            if fallback.success and fallback.plausible:
                best = fallback
                best.attempts = attempt
        if best.success and best.plausible:
            break
    best.seconds = seconds
    adversary_node = int(np.flatnonzero(problem.traffic.track_ids[problem.node_tracks[1:]] == best.adversary)[0]) + 1
    used.add((adversary_node, tuple(window)))
    return best


def distinct_variants(problem: BehaviorProblem, candidates: list[Candidate], n_variants: int,
                      progress: Callable[[int, int], None] | None = None,
                      accept: Callable[[VariantResult], bool] | None = None,
                      budget: int | None = None) -> list[VariantResult]:
    """Up to ``n_variants`` variants, no two with the same (adversary, time window): the schedule's pairs in
    order, skipping pairs an earlier variant (or its fallback) already used. Fewer come back when the scene
    has fewer distinct pairs. With ``accept(variant)`` (the quality gates), variants are made until
    ``n_variants`` are accepted or ``budget`` variants were tried, and every variant tried comes back.
    ``progress(done, total)`` moves with the optimiser's steps: each requested variant is ``iterations + 1`` units,
    filled by the current optimisation and never going back (a restart, a further adversary or a rejected variant
    holds it where it was)."""
    pool = [c for c in candidates if c[1]] or candidates
    windows = problem.config.time_windows
    queue = variant_schedule(candidates, len(pool) * len(windows), problem.horizon, windows)
    budget = n_variants if accept is None or budget is None else max(int(budget), n_variants)
    if accept is not None and budget > n_variants and not any(c[1] for c in candidates):
        log.warning("scene %s: no vehicle can reach the ego's path within the horizon; %d variant(s) are tried, "
                    "not the budget of %d", problem.traffic.scene_id, n_variants, budget)
        budget = n_variants
    results: list[VariantResult] = []
    accepted = 0
    used: set[tuple[int, tuple[int, int]]] = set()
    unit = problem.config.iterations + 1
    shown = 0

    def report(done: int) -> None:
        nonlocal shown
        if progress and done > shown:
            shown = done
            progress(done, n_variants * unit)

    def on_step(it: int) -> None:
        report(accepted * unit + min(it + 1, unit - 1))

    while accepted < n_variants and len(results) < budget:
        queue = [q for q in queue if (q[0], tuple(q[1])) not in used]
        if not queue:
            log.warning("scene %s: only %d distinct (adversary, window) variants", problem.traffic.scene_id,
                        len(results))
            break
        node, window, reachable = queue.pop(0)
        results.append(optimise_with_fallback(problem, candidates, node, window, reachable, len(results), used,
                                              on_step=on_step if progress else None))
        accepted += 1 if accept is None or accept(results[-1]) else 0
        report(accepted * unit)
    if progress and shown < n_variants * unit:  # fewer accepted than requested: the stage's work is done anyway
        progress(n_variants * unit, n_variants * unit)
    return results


def generate_variants(traffic: TrafficScene, model: TrafficModel, n_variants: int,
                      config: AdversarialConfig = AdversarialConfig(),
                      render_consistency: RenderConsistencyTerm | None = None,
                      progress: Callable[[int, int], None] | None = None,
                      accept: Callable[[VariantResult], bool] | None = None,
                      budget: int | None = None) -> list[VariantResult]:
    """``n_variants`` behaviour variants of one scene (different adversaries, then different time windows); with
    ``accept``, variants are tried until ``n_variants`` are accepted or ``budget`` were tried
    (``distinct_variants``).

    Returns an empty list when no vehicle other than the ego is present at the now step.
    """
    if n_variants < 1:
        raise OmniscsError(f"the number of variants must be at least 1; got {n_variants}")
    previous = set_threads(config.torch_threads)
    try:
        problem = BehaviorProblem(traffic, model, config, render_consistency)
        candidates = problem.candidates()
        if not candidates:
            log.warning("scene %s: no vehicle besides the ego at step %d; no behaviour variant", traffic.scene_id,
                        problem.now)
            return []
        log.info("scene %s: %d candidate adversaries (%d reachable); latent fit ADE %.2f m", traffic.scene_id,
                 len(candidates), sum(c[1] for c in candidates), problem.fit_ade)
        return distinct_variants(problem, candidates, n_variants, progress, accept, budget)
    finally:
        set_threads(previous)
