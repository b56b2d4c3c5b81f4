"""Densify / prune / opacity-reset of Gaussians (3DGS adaptive density control), one strategy for every node type.

Modelled on gsplat's ``DefaultStrategy``: screen-space gradients of the means are averaged per Gaussian
over the views that saw it; small Gaussians with large gradients are cloned, large ones split in two;
transparent (and, after the first opacity reset, oversized) ones are pruned; opacities are reset
periodically. A budget from the scene plan caps the count. Kerbl et al. 2023, "3D Gaussian Splatting
for Real-Time Radiance Field Rendering", Sec. 5.2.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from omniscs.gaussians import PARAM_NAMES, GaussianParams, activate
from omniscs.quaternions import rotmats_from_unit_quats

#: Adam moment buffers that follow their parameter rows when Gaussians are added or removed.
ADAM_BUFFERS = ("exp_avg", "exp_avg_sq")


@dataclass(frozen=True)
class DensifyStrategy:
    """When and how Gaussians are added and removed; scales are relative to the node's ``scene_scale``."""

    prune_opa: float = 0.005
    """Gaussians with opacity below this are pruned."""
    grow_grad2d: float = 0.0002
    """Average screen-space gradient of the mean (normalised by image size) above which a Gaussian grows."""
    grow_scale3d: float = 0.01
    """Growing Gaussians no larger than this (x scene_scale) are cloned; larger ones are split."""
    prune_scale3d: float = 0.1
    """After the first opacity reset, Gaussians larger than this (x scene_scale) are pruned."""
    refine_start_iter: int = 500
    """First iteration at which Gaussians are grown or pruned."""
    refine_stop_iter: int = 15_000
    """No growing or pruning from this iteration on."""
    refine_every: int = 100
    """Grow and prune every this many iterations."""
    reset_every: int = 3_000
    """Every this many iterations opacities are clamped to 2 x prune_opa (0 = never)."""
    split_scale_divisor: float = 1.6
    """A split Gaussian's two children have its scales divided by this."""
    absgrad: bool = False
    """Use the sum of per-pixel absolute gradients (AbsGS) instead of the summed gradient."""

    def is_refine_step(self, step: int) -> bool:
        return self.refine_start_iter <= step < self.refine_stop_iter and step % self.refine_every == 0 and step > 0

    def is_reset_step(self, step: int) -> bool:
        return self.reset_every > 0 and step > 0 and step % self.reset_every == 0 and step < self.refine_stop_iter


def all_finite(tensors) -> bool:
    """Whether every value of the float32 ``tensors`` is finite, in one reduction each and one test (a fit checks its
    parameters every step): a float64 sum of float32 values cannot overflow, and is NaN or infinite exactly when one
    value is. Tensors of another type are tested value by value."""
    tensors = list(tensors)
    with torch.no_grad():
        if any(t.dtype != torch.float32 for t in tensors):
            return all(bool(torch.isfinite(t).all()) for t in tensors)
        return bool(torch.isfinite(torch.stack([t.sum(dtype=torch.float64) for t in tensors])).all())


class SharedAdam:
    """One fused Adam for the raw parameters of many nodes: a parameter group per (name, learning rate), so every
    node's tensors of one name and rate are updated by one kernel call (Adam is elementwise: the same update as an
    optimiser per node, with a dozen nodes' six tensors in about a dozen calls instead of seventy)."""

    def __init__(self) -> None:
        self.optimizer: torch.optim.Adam | None = None
        self._group: dict[tuple, int] = {}

    def add(self, key: tuple, tensor: Tensor, lr: float) -> None:
        """Optimise ``tensor`` in the group named ``key`` (made with rate ``lr`` when new)."""
        if key in self._group:
            self.optimizer.param_groups[self._group[key]]["params"].append(tensor)
            return
        group = {"params": [tensor], "lr": lr}
        if self.optimizer is None:
            self.optimizer = torch.optim.Adam([group], eps=1e-15, fused=True)
        else:
            self.optimizer.add_param_group(group)
        self._group[key] = len(self.optimizer.param_groups) - 1

    def replace(self, key: tuple, old: Tensor, new: Tensor, state: dict | None) -> None:
        """Put ``new`` where ``old`` was in group ``key``, with ``state`` (Adam's moments for its rows) or none."""
        params = self.optimizer.param_groups[self._group[key]]["params"]
        params[next(i for i, t in enumerate(params) if t is old)] = new
        self.optimizer.state.pop(old, None)
        if state is not None:
            self.optimizer.state[new] = state

    def state(self, tensor: Tensor) -> dict | None:
        return None if self.optimizer is None else self.optimizer.state.get(tensor)

    def set_lr(self, key: tuple, lr: float) -> None:
        self.optimizer.param_groups[self._group[key]]["lr"] = lr

    def step(self) -> None:
        """One Adam step of every tensor that has a gradient, then the gradients cleared. The update is
        ``torch.optim.Adam(fused=True)``'s own kernel, called once per learning rate with the tensors of every group
        at that rate, instead of through the optimiser's Python for each group: a fit with 40 agent nodes has 50
        groups (one means rate per node), and that Python was a tenth of its step at the scale-out setting."""
        opt = self.optimizer
        if opt is None:
            return
        calls: dict[tuple, tuple[list[Tensor], ...]] = {}
        with torch.no_grad():
            for group in opt.param_groups:
                if group["amsgrad"] or group["maximize"] or group["weight_decay"] or not group["fused"]:
                    raise ValueError("SharedAdam's groups are plain fused Adam")
                for p in group["params"]:
                    grad = p.grad
                    if grad is None:
                        continue
                    state = opt.state[p]
                    if not state:  # as Adam makes it lazily for a fused group
                        state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                        state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                        state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    key = (group["lr"], *group["betas"], group["eps"], p.device, p.dtype)
                    lists = calls.setdefault(key, ([], [], [], [], []))
                    for items, item in zip(lists, (p, grad, state["exp_avg"], state["exp_avg_sq"], state["step"])):
                        items.append(item)
                    p.grad = None
            if calls:
                torch._foreach_add_([step for lists in calls.values() for step in lists[4]], 1)
            for (lr, beta1, beta2, eps, _, _), (params, grads, exp_avgs, exp_avg_sqs, state_steps) in calls.items():
                torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, [], state_steps, amsgrad=False, lr=lr,
                                   beta1=beta1, beta2=beta2, weight_decay=0.0, eps=eps, maximize=False,
                                   grad_scale=None, found_inf=None)


class OptimisedGaussians:
    """A node's raw parameters as leaf tensors, their Adam moments, and the gradient statistics the strategy
    accumulates between refinements. ``adam`` shares one optimiser between nodes (the caller then steps it once for
    all of them; ``step`` only steps an optimiser the node made for itself)."""

    def __init__(self, params: GaussianParams, learning_rates: dict[str, float], adam: SharedAdam | None = None) -> None:
        self.params: dict[str, Tensor] = {k: v.detach().clone().requires_grad_(True)
                                          for k, v in params.as_dict().items()}
        self._owns_adam = adam is None
        self.adam = SharedAdam() if adam is None else adam
        # the means' rate is this node's own (it decays, and scales with the node's size); nodes share the others
        self._key = {k: (k, id(self)) if k == "means" else (k, learning_rates[k]) for k in PARAM_NAMES}
        for k in PARAM_NAMES:
            self.adam.add(self._key[k], self.params[k], learning_rates[k])
        self.device = params.device
        self.grad2d = torch.zeros(len(params), device=self.device)
        self.count = torch.zeros(len(params), device=self.device)

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    def current(self) -> GaussianParams:
        """The live parameters (gradients flow into them)."""
        return GaussianParams.from_dict(self.params)

    def frozen(self) -> GaussianParams:
        return GaussianParams.from_dict({k: v.detach().clone() for k, v in self.params.items()})

    def step(self) -> None:
        """One Adam step of this node's own optimiser (a shared one is stepped by its owner)."""
        if self._owns_adam:
            self.adam.step()

    def set_lr(self, name: str, lr: float) -> None:
        if name != "means" and not self._owns_adam:
            raise ValueError("only the means' rate is a node's own when nodes share an optimiser")
        self.adam.set_lr(self._key[name], lr)

    # -- row surgery: parameters and Adam moments change together --------------------------
    def keep_and_append(self, keep: Tensor, new_rows: dict[str, Tensor] | None = None) -> None:
        """Keep the rows where ``keep`` [N] is True, then append ``new_rows`` (zero Adam moments)."""
        n_new = 0 if new_rows is None else next(iter(new_rows.values())).shape[0]
        for name in PARAM_NAMES:
            old = self.params[name]
            data = old.detach()[keep]
            if n_new:
                data = torch.cat([data, new_rows[name].to(data.dtype)])
            fresh = data.clone().requires_grad_(True)
            state = self.adam.state(old)
            if state is not None:
                for buf in ADAM_BUFFERS:
                    if buf in state:
                        moved = state[buf][keep]
                        if n_new:
                            moved = torch.cat([moved, moved.new_zeros((n_new,) + moved.shape[1:])])
                        state[buf] = moved
            self.adam.replace(self._key[name], old, fresh, state)
            self.params[name] = fresh
        self.grad2d = torch.cat([self.grad2d[keep], torch.zeros(n_new, device=self.device)])
        self.count = torch.cat([self.count[keep], torch.zeros(n_new, device=self.device)])

    def reset_moments(self, name: str) -> None:
        state = self.adam.state(self.params[name])
        if state:
            for buf in ADAM_BUFFERS:
                if buf in state:
                    state[buf].zero_()


def screen_gradient_norms(grad2d: Tensor,  # [N, 2] d loss / d means2d (or absgrad) of one view
                          radii: Tensor,   # [N, 2] or [N] screen radii; 0 = culled
                          width: int, height: int) -> tuple[Tensor, Tensor]:  # norms [N], visible [N] bool
    """Each Gaussian's screen-space gradient norm in normalised device units, and whether the view saw it; a
    step computes them once for all nodes (``add_screen_gradients`` per node's rows)."""
    visible = (radii.reshape(radii.shape[0], -1) > 0).any(-1)
    scaled = grad2d.detach().clone()
    scaled[:, 0] *= 0.5 * width
    scaled[:, 1] *= 0.5 * height
    return torch.nan_to_num(scaled.norm(dim=-1), nan=0.0, posinf=0.0), visible


def add_screen_gradients(node: OptimisedGaussians, norms: Tensor, visible: Tensor) -> None:
    """Add one view's gradient norms (``screen_gradient_norms``, this node's rows) to the Gaussians it saw."""
    # masks rather than boolean indexing: no gather/scatter and no host sync (a step calls this per node)
    node.grad2d += torch.where(visible, norms, 0.0)
    node.count += visible


def accumulate_gradients(strategy: DensifyStrategy, node: OptimisedGaussians,
                         grad2d: Tensor,  # [N, 2] this node's rows of d loss / d means2d (or absgrad)
                         radii: Tensor,   # [N, 2] or [N] screen radii; 0 = culled
                         width: int, height: int) -> None:
    """Add this view's normalised screen-space gradient norms to the Gaussians it saw."""
    add_screen_gradients(node, *screen_gradient_norms(grad2d, radii, width, height))


def refine(strategy: DensifyStrategy, node: OptimisedGaussians, step: int, scene_scale: float, budget: int,
           generator: torch.Generator,  # a CPU generator (see _split_rows)
           ) -> dict[str, int]:
    """Grow (clone/split, within ``budget``) then prune; resets the gradient statistics. Returns counts."""
    with torch.no_grad():
        g = activate(node.current())
        max_scale = g.scales.max(-1).values
        avg = node.grad2d / node.count.clamp_min(1.0)
        high = avg > strategy.grow_grad2d
        small = max_scale <= strategy.grow_scale3d * scene_scale
        room = max(0, budget - len(node))
        candidates = torch.nonzero(high).squeeze(1)
        # each clone and each split adds one Gaussian; keep the strongest gradients that fit the budget
        if len(candidates) > room:
            order = torch.argsort(avg[candidates], descending=True)
            candidates = candidates[order[:room]]
        chosen = torch.zeros(len(node), dtype=torch.bool, device=node.device)
        chosen[candidates] = True
        clone = chosen & small
        split = chosen & ~small
        new_rows = _clone_rows(node, clone)
        split_rows = _split_rows(node, g, split, strategy.split_scale_divisor, generator)
        rows = {k: torch.cat([new_rows[k], split_rows[k]]) for k in PARAM_NAMES}
        node.keep_and_append(~split, rows)

        g = activate(node.current())
        prune = (g.opacities < strategy.prune_opa) | ~torch.isfinite(g.means).all(-1)
        if step > strategy.reset_every > 0:
            prune |= g.scales.max(-1).values > strategy.prune_scale3d * scene_scale
        if bool(prune.any()):
            node.keep_and_append(~prune)
        node.grad2d.zero_()
        node.count.zero_()
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(prune.sum())}


def reset_opacities(strategy: DensifyStrategy, node: OptimisedGaussians) -> None:
    """Clamp opacities to at most 2 x prune_opa, so the ones the images do not need fade and get pruned."""
    with torch.no_grad():
        ceiling = torch.logit(torch.tensor(2.0 * strategy.prune_opa))
        node.params["opacity_logits"].clamp_(max=float(ceiling))
    node.reset_moments("opacity_logits")


def _clone_rows(node: OptimisedGaussians, mask: Tensor) -> dict[str, Tensor]:
    return {k: node.params[k].detach()[mask] for k in PARAM_NAMES}


def _split_rows(node: OptimisedGaussians, g, mask: Tensor, divisor: float,
                generator: torch.Generator) -> dict[str, Tensor]:
    """Two children per split Gaussian, drawn from it, with scales / ``divisor``."""
    raw = {k: node.params[k].detach()[mask] for k in PARAM_NAMES}
    scales, quats = g.scales[mask], g.quats[mask]
    n = scales.shape[0]
    # drawn on the host generator whatever the device: the same seed splits the same way on CPU and GPU
    offsets = torch.randn(2, n, 3, generator=generator).to(scales.device) * scales[None]
    means = raw["means"][None] + torch.einsum("nij,cnj->cni", rotmats_from_unit_quats(quats), offsets)
    out = {k: torch.cat([v, v]) for k, v in raw.items()}
    out["means"] = means.reshape(2 * n, 3)
    out["log_scales"] = torch.log(scales / divisor).repeat(2, 1)
    return out
