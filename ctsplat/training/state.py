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
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ctsplat.training.seeding import Seed

__all__ = ["PARAM_GROUPS", "METHOD_LR", "TrainState", "ViewSampler", "init_params", "as_gaussians", "amplitude",
           "make_optimizer", "cosine_factor", "replace_params", "snapshot", "restore", "all_finite"]

PARAM_GROUPS = {"means": "means", "log_scales": "scales", "quats": "quats", "density_raw": "density",
                "opacity_raw": "opacity", "colors": "colors"}


def init_params(seed: Seed, cfg: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
    """Leaf parameter tensors (float32, requires_grad) from a seed.

    Parameters
    ----------
    seed : Seed
        Means (N, 3) mm, scales (N, 3) mm, densities (N,) (:mod:`ctsplat.training.seeding`).
    cfg : dict
        Resolved ``train`` config; the alpha compositor adds ``opacity_raw`` (N,) (opacity 0.1) and ``colors``
        (N, 1) (0.5).
    device : torch.device

    Returns
    -------
    dict of str to Tensor
        ``means`` (N, 3) mm, ``log_scales`` (N, 3) log mm, ``quats`` (N, 4), ``density_raw`` (N,) and, for alpha,
        ``opacity_raw`` (N,) and ``colors`` (N, 1); keys of :data:`PARAM_GROUPS`.
    """
    from ctsplat.splat.gaussians import Gaussians

    kw: dict[str, Any] = {}
    if cfg["compositor"] == "alpha":
        kw = {"opacities": 0.1, "colors": np.full((len(seed), 1), 0.5, np.float32)}
    g = Gaussians.from_values(seed.means, seed.scales, seed.densities, dtype=torch.float32, device=device, **kw)
    return {k: v.detach().clone().requires_grad_(True) for k, v in g.tensors().items() if k in PARAM_GROUPS}


def amplitude(params: dict[str, torch.Tensor], compositor: str) -> torch.Tensor:
    """What each Gaussian renders with: its density (radiative compositors), or its opacity (alpha; the alpha
    model keeps a density parameter that nothing renders).

    Parameters
    ----------
    params : dict of str to Tensor
        ``density_raw`` (N,), and ``opacity_raw`` (N,) for alpha.
    compositor : str

    Returns
    -------
    Tensor (N,)
        ``softplus(density_raw)`` or ``sigmoid(opacity_raw)``, detached.
    """
    if compositor == "alpha":
        return torch.sigmoid(params["opacity_raw"].detach())
    return torch.nn.functional.softplus(params["density_raw"].detach())


def as_gaussians(params: dict[str, torch.Tensor]) -> Any:
    """A :class:`ctsplat.splat.Gaussians` view of the parameter tensors (no copy).

    Parameters
    ----------
    params : dict of str to Tensor
        As :func:`init_params` returns.

    Returns
    -------
    ctsplat.splat.Gaussians
        Sharing the tensors (gradients flow to ``params``).
    """
    from ctsplat.splat.gaussians import Gaussians

    return Gaussians(**params)



#: The method's optimiser setting (``optimizer_preset: method``): one Adam learning rate for every group.
METHOD_LR = 3e-3


def make_optimizer(params: dict[str, torch.Tensor], cfg: dict[str, Any], voxel_mm: float,
                   half_extent_mm: float | None = None) -> torch.optim.Adam:
    """Adam with one group per parameter tensor.

    ``optimizer_preset: per_group``: each group's rate from ``lr``, mean rates in voxels per step (× ``voxel_mm``).
    ``method``: :data:`METHOD_LR` for every group, the means' in units of the volume's half-extent (the method
    trains in a [-1, 1] scene box), i.e. × ``half_extent_mm``. Both are decayed by the loop's cosine.

    Parameters
    ----------
    params : dict of str to Tensor
        Leaf tensors (:func:`init_params`).
    cfg : dict
        Resolved ``train`` config (``optimizer_preset``; ``lr``: one rate per quantity of :data:`PARAM_GROUPS`).
    voxel_mm : float
        Mean voxel edge in mm.
    half_extent_mm : float, optional
        Half the volume's largest extent (mm); required by the ``method`` preset.

    Returns
    -------
    torch.optim.Adam
        Groups named after the parameters, each with ``initial_lr`` (the schedule's start).
    """
    method = cfg.get("optimizer_preset", "per_group") == "method"
    if method and not half_extent_mm:
        raise ValueError("optimizer_preset: method needs the volume's half-extent (half_extent_mm)")
    groups = []
    for name, p in params.items():
        if method:
            lr = METHOD_LR * (float(half_extent_mm) if name == "means" else 1.0)
        else:
            lr = float(cfg["lr"][PARAM_GROUPS[name]]) * (voxel_mm if name == "means" else 1.0)
        groups.append({"params": [p], "lr": lr, "initial_lr": lr, "name": name})
    return torch.optim.Adam(groups, eps=1e-15)


def cosine_factor(it: int, total: int, final_factor: float) -> float:
    """Cosine decay factor from 1 at ``it = 0`` to ``final_factor`` at ``it = total``.

    Parameters
    ----------
    it : int
        Completed iterations (clipped to ``[0, total]``).
    total : int
        Iterations of the run.
    final_factor : float
        The factor at the end (``lr_final_factor``).

    Returns
    -------
    float
    """
    x = min(max(it / max(total, 1), 0.0), 1.0)
    return final_factor + (1.0 - final_factor) * 0.5 * (1.0 + math.cos(math.pi * x))


def replace_params(opt: torch.optim.Adam, params: dict[str, torch.Tensor], keep: torch.Tensor,
                    new: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Keep rows ``keep`` of every parameter, append ``new`` rows; Adam moments follow (zeros for new rows).

    Parameters
    ----------
    opt : torch.optim.Adam
        The optimiser (from :func:`make_optimizer`); its groups get the new tensors.
    params : dict of str to Tensor
        Current parameters, N rows each.
    keep : Tensor (K,) int64
        Indices of the rows kept.
    new : dict of str to Tensor
        Rows appended per parameter (M rows each; missing keys append nothing).

    Returns
    -------
    dict of str to Tensor
        New leaf tensors with K + M rows.
    """
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
    """Mutable training state (checkpointed).

    Attributes
    ----------
    params : dict of str to Tensor
        Leaf parameters (:func:`init_params`).
    opt : torch.optim.Adam
    iteration : int
        Completed iterations.
    grad_accum, grad_count : Tensor (N,)
        Densification statistics: summed view-space positional-gradient norms (NDC) and view counts.
    err_accum, err_count : Tensor (N,)
        Error-driven densification statistics: summed residual ratios and view counts
        (:class:`ctsplat.training.densify.ErrorDensify`).
    lr_factor : float
        Product of the ``nan_lr_decay`` factors applied so far.
    nan_events, nan_consecutive : int
        Non-finite steps in total and in a row.
    nan_iters : list of int
        Iterations of the non-finite steps within the last ``nan_window`` iterations.
    elapsed_s : float
        Wall time so far (s), the seed's reconstruction included, across resumes.
    queue : list of list of int
        Remaining view batches of the current epoch.
    filter_var : Tensor (N,) or None
        Mip 3D filter variance (mm²), computed at each densify step and checkpointed.
    densify_counts : dict of str to int
        Cloned, split and pruned Gaussians so far.
    pose, pose_opt : PoseCorrection, torch.optim.Adam or None
        Per-view pose corrections of the training views and their optimiser (pose refinement only).
    health : dict
        Collapse watch (:mod:`ctsplat.training.loop`): ``psnr_initial`` (dB), ``loss_first`` (mean loss of the
        first validation interval), ``loss_sum`` / ``loss_n`` (finite losses since the last validation),
        ``loss_high`` (validations in a row with a high loss); also ``peak_memory_mb``, the peak at the last
        checkpoint across resumes (MiB).
    """

    params: dict[str, torch.Tensor]
    opt: torch.optim.Adam
    iteration: int = 0
    grad_accum: torch.Tensor | None = None
    grad_count: torch.Tensor | None = None
    err_accum: torch.Tensor | None = None
    err_count: torch.Tensor | None = None
    lr_factor: float = 1.0
    nan_events: int = 0
    nan_consecutive: int = 0
    nan_iters: list[int] = field(default_factory=list)
    elapsed_s: float = 0.0
    queue: list[list[int]] = field(default_factory=list)
    filter_var: torch.Tensor | None = None
    densify_counts: dict[str, int] = field(default_factory=lambda: {"cloned": 0, "split": 0, "pruned": 0})
    health: dict[str, Any] = field(default_factory=dict)
    pose: Any = None
    pose_opt: Any = None

    def __post_init__(self) -> None:
        # statistics not given (a fresh run, or a checkpoint written without them) start at zero, one per Gaussian
        m, dev = self.params["means"].shape[0], self.params["means"].device
        for name in ("grad_accum", "grad_count", "err_accum", "err_count"):
            if getattr(self, name) is None:
                setattr(self, name, torch.zeros(m, device=dev))


class ViewSampler:
    """Stratified view sampling over direction.

    Training views are ordered by azimuth (then elevation) and cut into ``batch`` contiguous strata (sizes differ by
    at most one); each epoch permutes every stratum and each batch takes one view per stratum, so every batch spans
    the directions. An epoch has as many batches as the largest stratum has views: every view is used once, and
    when ``batch`` does not divide the number of views, the smaller strata use one view twice (so their views are
    drawn ``(k + 1) / k`` times as often, ``k`` their size; for ``batch = 1``: a random permutation per epoch).

    Parameters
    ----------
    azimuth_deg, elevation_deg : ndarray (V,)
        Directions of the training views (degrees).
    batch : int
        Views per batch (clipped to ``[1, V]``).
    """

    def __init__(self, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, batch: int) -> None:
        order = np.lexsort((np.asarray(elevation_deg), np.mod(np.asarray(azimuth_deg), 360.0)))
        batch = max(1, min(int(batch), order.size))
        self.strata = [s for s in np.array_split(order, batch) if s.size]

    def refill(self, rng: np.random.Generator) -> list[list[int]]:
        """One epoch of batches, one view per stratum in each: every training view at least once (class docstring).

        Parameters
        ----------
        rng : numpy.random.Generator

        Returns
        -------
        list of list of int
            Batches of view indices (``batch`` each).
        """
        perms = [rng.permutation(s) for s in self.strata]
        m = max(p.size for p in perms)
        return [[int(p[i % p.size]) for p in perms] for i in range(m)]



def snapshot(state: TrainState) -> dict[str, Any]:
    """A copy of the parameters and Adam moments to roll back to after a non-finite step.

    Parameters
    ----------
    state : TrainState

    Returns
    -------
    dict
        ``params`` (cloned tensors) and ``opt`` (cloned Adam moments, keyed ``name/key``).
    """
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
    """Put a :func:`snapshot` back into ``state`` (parameters, optimiser groups and moments).

    Parameters
    ----------
    state : TrainState
        Changed in place; the densification statistics are reset when the number of Gaussians changed.
    snap : dict
        From :func:`snapshot`.
    """
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
    dev = state.params["means"].device
    if state.grad_accum is None or state.grad_accum.shape[0] != m:
        state.grad_accum = torch.zeros(m, device=dev)
        state.grad_count = torch.zeros(m, device=dev)
    if state.err_accum is None or state.err_accum.shape[0] != m:
        state.err_accum = torch.zeros(m, device=dev)
        state.err_count = torch.zeros(m, device=dev)


def all_finite(tensors: Iterable[torch.Tensor | None]) -> bool:
    """Whether every element of every tensor (``None`` skipped) is finite, with one host synchronisation.

    On a GPU each ``bool(tensor)`` waits for the queued work; the training step checks its parameters and gradients
    every iteration, so the flags are combined on the device and read once.

    Parameters
    ----------
    tensors : iterable of Tensor or None
        Tensors on one device.

    Returns
    -------
    bool
    """
    flags = [torch.isfinite(t).all() for t in tensors if t is not None]
    return bool(torch.stack(flags).all()) if flags else True
