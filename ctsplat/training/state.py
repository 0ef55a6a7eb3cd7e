"""Optimisation state of a training run: parameters, Adam with one group per quantity, schedules, sampling.

Parameters are raw tensors (``means`` mm, ``log_scales`` log mm, ``quats``, ``density_raw`` = softplus⁻¹ ρ; plus
``opacity_raw`` and ``colors`` for the alpha compositor), each its own Adam group with its own learning rate,
decayed by a cosine from ``lr`` to ``lr × lr_final_factor`` (:func:`cosine_factor`).

References
----------
Kingma, D. P., Ba, J. (2015). Adam: a method for stochastic optimization. ICLR.
Loshchilov, I., Hutter, F. (2017). SGDR: stochastic gradient descent with warm restarts. ICLR (cosine schedule).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ctsplat.training.seeding import Seed

__all__ = ["PARAM_GROUPS", "TrainState", "ViewSampler", "init_params", "as_gaussians", "make_optimizer",
           "cosine_factor", "replace_params", "snapshot", "restore", "params_finite"]

PARAM_GROUPS = {"means": "means", "log_scales": "scales", "quats": "quats", "density_raw": "density",
                "opacity_raw": "opacity", "colors": "colors"}


def init_params(seed: Seed, cfg: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
    """Leaf parameter tensors (float32, requires_grad) from a seed."""
    from ctsplat.splat.gaussians import Gaussians

    kw: dict[str, Any] = {}
    if cfg["compositor"] == "alpha":
        kw = {"opacities": 0.1, "colors": np.full((len(seed), 1), 0.5, np.float32)}
    g = Gaussians.from_values(seed.means, seed.scales, seed.densities, dtype=torch.float32, device=device, **kw)
    return {k: v.detach().clone().requires_grad_(True) for k, v in g.tensors().items() if k in PARAM_GROUPS}


def as_gaussians(params: dict[str, torch.Tensor]) -> Any:
    """A :class:`ctsplat.splat.Gaussians` view of the parameter tensors (no copy)."""
    from ctsplat.splat.gaussians import Gaussians

    return Gaussians(**params)



def make_optimizer(params: dict[str, torch.Tensor], cfg: dict[str, Any], voxel_mm: float) -> torch.optim.Adam:
    """Adam with one group per parameter tensor; mean learning rates are in voxels per step (× ``voxel_mm``)."""
    groups = []
    for name, p in params.items():
        lr = float(cfg["lr"][PARAM_GROUPS[name]]) * (voxel_mm if name == "means" else 1.0)
        groups.append({"params": [p], "lr": lr, "initial_lr": lr, "name": name})
    return torch.optim.Adam(groups, eps=1e-15)


def cosine_factor(it: int, total: int, final_factor: float) -> float:
    """Cosine decay factor from 1 at ``it = 0`` to ``final_factor`` at ``it = total``."""
    x = min(max(it / max(total, 1), 0.0), 1.0)
    return final_factor + (1.0 - final_factor) * 0.5 * (1.0 + math.cos(math.pi * x))


def replace_params(opt: torch.optim.Adam, params: dict[str, torch.Tensor], keep: torch.Tensor,
                    new: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Keep rows ``keep`` of every parameter, append ``new`` rows; Adam moments follow (zeros for new rows)."""
    out = {}
    for group in opt.param_groups:
        name = group["name"]
        old = group["params"][0]
        state = opt.state.pop(old, {})
        extra = new.get(name)
        data = old.detach()[keep]
        if extra is not None and extra.shape[0]:
            data = torch.cat([data, extra.detach().to(data)])
        p = data.clone().requires_grad_(True)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                s = state[key][keep]
                if extra is not None and extra.shape[0]:
                    s = torch.cat([s, torch.zeros((extra.shape[0], *s.shape[1:]), dtype=s.dtype, device=s.device)])
                state[key] = s
            opt.state[p] = state
        group["params"][0] = p
        out[name] = p
    return out


@dataclass
class TrainState:
    """Mutable training state (checkpointed)."""

    params: dict[str, torch.Tensor]
    opt: torch.optim.Adam
    iteration: int = 0
    grad_accum: torch.Tensor | None = None
    grad_count: torch.Tensor | None = None
    lr_factor: float = 1.0
    nan_events: int = 0
    nan_consecutive: int = 0
    elapsed_s: float = 0.0
    queue: list[list[int]] = field(default_factory=list)
    filter_var: torch.Tensor | None = None
    densify_counts: dict[str, int] = field(default_factory=lambda: {"cloned": 0, "split": 0, "pruned": 0})


class ViewSampler:
    """Stratified view sampling over direction.

    Training views are ordered by azimuth (then elevation) and cut into ``batch`` contiguous strata; each epoch
    permutes every stratum and each batch takes one view per stratum, so every batch spans the directions and
    every view is used once per epoch (for ``batch = 1``: a random permutation per epoch).
    """

    def __init__(self, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, batch: int) -> None:
        order = np.lexsort((np.asarray(elevation_deg), np.mod(np.asarray(azimuth_deg), 360.0)))
        batch = max(1, min(int(batch), order.size))
        self.strata = [s for s in np.array_split(order, batch) if s.size]

    def refill(self, rng: np.random.Generator) -> list[list[int]]:
        perms = [rng.permutation(s) for s in self.strata]
        m = max(p.size for p in perms)
        return [[int(p[i % p.size]) for p in perms] for i in range(m)]



def snapshot(state: TrainState) -> dict[str, Any]:
    """A copy of the parameters and Adam moments to roll back to after a non-finite step."""
    return {
        "params": {k: v.detach().clone() for k, v in state.params.items()},
        "opt": {k: (v.clone() if torch.is_tensor(v) else v) for k, v in opt_tensors(state.opt).items()},
    }


def opt_tensors(opt: torch.optim.Adam) -> dict[str, Any]:
    out = {}
    for g in opt.param_groups:
        st = opt.state.get(g["params"][0], {})
        for key, v in st.items():
            out[f"{g['name']}/{key}"] = v
    return out


def restore(state: TrainState, snap: dict[str, Any]) -> None:
    """Put a :func:`snapshot` back into ``state`` (parameters, optimiser groups and moments)."""
    for g in state.opt.param_groups:
        name = g["name"]
        old = g["params"][0]
        st = state.opt.state.pop(old, {})
        p = snap["params"][name].clone().requires_grad_(True)
        g["params"][0] = p
        state.params[name] = p
        new_st = {}
        for key in ("step", "exp_avg", "exp_avg_sq"):
            if f"{name}/{key}" in snap["opt"]:
                new_st[key] = snap["opt"][f"{name}/{key}"].clone()
        if new_st or st:
            state.opt.state[p] = new_st
    m = state.params["means"].shape[0]
    if state.grad_accum is None or state.grad_accum.shape[0] != m:
        state.grad_accum = torch.zeros(m, device=state.params["means"].device)
        state.grad_count = torch.zeros(m, device=state.params["means"].device)


def params_finite(params: dict[str, torch.Tensor]) -> bool:
    """Whether every parameter tensor is finite."""
    return all(bool(torch.isfinite(v).all()) for v in params.values())
