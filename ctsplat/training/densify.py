"""Adaptive density control: where the model gets more Gaussians and which it loses, as a strategy object.

:class:`GradientDensify` is 3DGS's rule adapted to radiative compositing. Every ``interval`` steps within
``[start, stop]`` it clones or splits Gaussians whose mean view-space positional gradient (norm of ∂L/∂(u, v) in
3DGS's NDC units: per-pixel gradient × (W/2, H/2)) exceeds ``grad_threshold``: small ones (max scale ≤
``clone_max_scale_voxels`` voxels) are cloned, large ones split in two (samples from the Gaussian, scales / 1.6).
In the radiative compositors mass is conserved: a clone and its original get half the density each; split
children get ρ·1.6³/2 so the pair carries the parent's mass ``ρ (2π)^{3/2} Π s`` (``split_mass: halve`` gives
the literal ρ/2 rule, which removes 1 - 2/1.6³ ≈ 76 % of a split Gaussian's mass). Then Gaussians with
ρ < ``prune_density``, oversized ones (max scale > ``prune_max_scale_fraction`` × volume extent) and those whose
centre left the volume box are pruned; the total is capped at ``max_gaussians`` (largest gradients first).

A strategy has two hooks, called by the training loop: :meth:`GradientDensify.accumulate` after each backward
pass (gradient statistics) and :meth:`GradientDensify.maybe_step` after each optimiser step.

References
----------
Kerbl, B., Kopanas, G., Leimkühler, T., Drettakis, G. (2023). 3D Gaussian Splatting for real-time radiance field
rendering. ACM TOG 42(4) (adaptive density control).
Zha, R., Lin, T. J., Cai, Y., Cao, J., Zhang, Y., Li, H. (2024). R²-Gaussian: rectifying radiative Gaussian
splatting for tomographic reconstruction. NeurIPS (mass-conserving densification of radiative Gaussians).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ctsplat.splat.gaussians import inverse_softplus, quat_to_rotmat
from ctsplat.training.seeding import grid_bounds_mm
from ctsplat.training.state import TrainState, replace_params

__all__ = ["GradientDensify"]


class GradientDensify:
    """Gradient-driven clone / split / prune (see the module docstring).

    Parameters
    ----------
    settings : dict
        The ``train.densify`` section (``interval``, ``start``, ``stop`` (0: 0.75 × iterations),
        ``grad_threshold``, ``clone_max_scale_voxels``, ``prune_density``, ``prune_max_scale_fraction``,
        ``max_gaussians``, ``split_mass``).
    compositor : str
        ``alpha`` keeps densities on clone/split; the radiative compositors conserve mass.
    iterations : int
        Total training iterations (no densification at the last one).
    """

    def __init__(self, settings: dict[str, Any], *, compositor: str, iterations: int) -> None:
        self.settings = dict(settings)
        self.compositor = compositor
        self.iterations = int(iterations)
        self.stop = int(settings["stop"]) or int(0.75 * self.iterations)

    def due(self, iteration: int) -> bool:
        """Whether :meth:`maybe_step` densifies after ``iteration``.

        Parameters
        ----------
        iteration : int
            Completed iterations.

        Returns
        -------
        bool
        """
        d = self.settings
        return bool(d["interval"]) and d["start"] <= iteration <= self.stop and iteration % int(d["interval"]) == 0 \
            and iteration < self.iterations

    @staticmethod
    def accumulate(state: TrainState, means2d_grad: torch.Tensor | None, visible: torch.Tensor,
                   ndc_half: torch.Tensor) -> None:
        """Add one view's positional-gradient norms (NDC units) to the visible Gaussians' statistics.

        Parameters
        ----------
        state : TrainState
            ``grad_accum`` / ``grad_count`` (N,) are updated in place.
        means2d_grad : (N, 2) or None
            ∂L/∂(u, v) in pixels of the projected means.
        visible : (N,) bool
        ndc_half : (2,)
            ``(W/2, H/2)``: pixels per NDC unit.
        """
        if means2d_grad is None:
            return
        state.grad_accum[visible] += (means2d_grad[visible] * ndc_half).norm(dim=-1)
        state.grad_count[visible] += 1

    def maybe_step(self, state: TrainState, iteration: int, volume: Any, gen: torch.Generator
                   ) -> dict[str, int] | None:
        """Densify and prune when due (:meth:`due`).

        Parameters
        ----------
        state : TrainState
        iteration : int
            Completed iterations.
        volume : ctsplat.formats.volume.Volume
            The reference grid (voxel size, box for pruning).
        gen : torch.Generator
            Source of the split samples.

        Returns
        -------
        dict or None
            ``cloned``, ``split``, ``pruned``, ``n`` (Gaussians after the step), or None when not due.
        """
        if not self.due(iteration):
            return None
        return self.step(state, volume, gen)

    def step(self, state: TrainState, volume: Any, gen: torch.Generator) -> dict[str, int]:
        """One densify-and-prune step on ``state`` (parameters and Adam moments follow).

        Parameters
        ----------
        state : TrainState
            Changed in place; its gradient statistics are reset.
        volume : ctsplat.formats.volume.Volume
            The reference grid (voxel size, box for pruning).
        gen : torch.Generator
            Source of the split samples.

        Returns
        -------
        dict
            ``cloned``, ``split``, ``pruned`` and ``n`` (Gaussians after the step).
        """
        d = self.settings
        p = state.params
        n = p["means"].shape[0]
        dev = p["means"].device
        vol = volume
        voxel = float(np.mean(vol.spacing_mm))
        with torch.no_grad():
            avg = state.grad_accum / state.grad_count.clamp_min(1)
            scales = torch.exp(p["log_scales"])
            smax = scales.max(-1).values
            dens = torch.nn.functional.softplus(p["density_raw"])
            cand = avg >= float(d["grad_threshold"])
            small = smax <= float(d["clone_max_scale_voxels"]) * voxel
            clone = cand & small
            split = cand & ~small
            budget = int(d["max_gaussians"]) - n
            n_new = int(clone.sum()) + int(split.sum())  # each adds one Gaussian net
            if n_new > max(budget, 0):
                idx = torch.nonzero(cand).flatten()
                order = torch.argsort(avg[idx], descending=True, stable=True)
                allowed = idx[order[: max(budget, 0)]]
                sel = torch.zeros(n, dtype=torch.bool, device=dev)
                sel[allowed] = True
                clone &= sel
                split &= sel
            radiative = self.compositor != "alpha"
            new_dens = dens.clone()
            if radiative:
                new_dens[clone] = dens[clone] * 0.5
                # each child has (1/1.6)^3 of the parent's volume: "conserve" keeps the pair's mass equal to the
                # parent's (ρ_child = ρ 1.6^3 / 2); "halve" is the literal rule ρ/2 (loses 76 % of the mass)
                grow = 1.6**3 if d["split_mass"] == "conserve" else 1.0
                new_dens[split] = dens[split] * 0.5 * grow
            new_raw = inverse_softplus(new_dens.clamp_min(1e-12))
            # clones: exact copies (half density each in radiative mode)
            ci = torch.nonzero(clone).flatten()
            si = torch.nonzero(split).flatten()
            add: dict[str, list[torch.Tensor]] = {k: [] for k in p}
            for k in p:
                src = new_raw if k == "density_raw" else p[k].detach()
                add[k].append(src[ci])
            # splits: two samples from the Gaussian, scales / 1.6; the original is replaced by the first sample
            if si.numel():
                rot = quat_to_rotmat(p["quats"].detach()[si])
                z = torch.randn((2, si.numel(), 3), generator=gen, dtype=torch.float32).to(dev)
                offs = torch.einsum("nij,knj->kni", rot, z * scales[si][None])
                s_new = torch.log(scales[si] / 1.6)
                for k in p:
                    src = new_raw if k == "density_raw" else p[k].detach()
                    if k == "means":
                        add[k].append(p["means"].detach()[si] + offs[0])
                        add[k].append(p["means"].detach()[si] + offs[1])
                    elif k == "log_scales":
                        add[k].extend([s_new, s_new])
                    else:
                        add[k].extend([src[si], src[si]])
            keep = torch.ones(n, dtype=torch.bool, device=dev)
            keep[si] = False
            # write halved densities of cloned originals
            p["density_raw"].data.copy_(torch.where(clone, new_raw, p["density_raw"].detach()))
            new = {k: torch.cat(v) if v else p[k].detach()[:0] for k, v in add.items()}
            # pruning criteria on survivors + new rows
            all_means = torch.cat([p["means"].detach()[keep], new["means"]])
            all_ls = torch.cat([p["log_scales"].detach()[keep], new["log_scales"]])
            all_dr = torch.cat([p["density_raw"].detach()[keep], new["density_raw"]])
            lo, hi = grid_bounds_mm(vol.shape, vol.affine)
            lo_t = torch.as_tensor(lo - 2 * voxel, dtype=all_means.dtype, device=dev)
            hi_t = torch.as_tensor(hi + 2 * voxel, dtype=all_means.dtype, device=dev)
            extent = float(np.max(hi - lo))
            bad = (torch.nn.functional.softplus(all_dr) < float(d["prune_density"]))
            bad |= torch.exp(all_ls).max(-1).values > float(d["prune_max_scale_fraction"]) * extent
            bad |= ((all_means < lo_t) | (all_means > hi_t)).any(-1)
            if bool(bad.all()):  # never prune everything
                bad[:] = False
        # apply: first keep/append, then prune
        state.params = replace_params(state.opt, p, torch.nonzero(keep).flatten(), new)
        good = torch.nonzero(~bad).flatten()
        state.params = replace_params(state.opt, state.params, good, {})
        m = state.params["means"].shape[0]
        state.grad_accum = torch.zeros(m, device=dev)
        state.grad_count = torch.zeros(m, device=dev)
        return {"cloned": int(ci.numel()), "split": int(si.numel()), "pruned": int(bad.sum()), "n": m}

