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
With ``prune_until_end`` (the default) the same pruning, without densification, goes on every ``interval`` after
``stop`` and at the last iteration: a few Gaussians keep growing after densification stops (long, thin ones of up
to 2/3 of the volume, fitting single views) and spread a haze over every view.
With ``prune_redundant``, nearly coincident Gaussians are first merged in pairs
(:func:`ctsplat.training.features.merge_redundant`); this step's clones, coincident by construction, are not
merged before they have had an interval to separate.

:class:`ErrorDensify` (``strategy: error`` or ``both``) selects the Gaussians under large training residuals
instead of (or beside) those with large positional gradients; :func:`make_densify` picks the class.

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

import logging
from typing import Any

import numpy as np
import torch

from ctsplat.splat.gaussians import inverse_softplus, quat_to_rotmat
from ctsplat.training.features import merge_redundant
from ctsplat.training.seeding import grid_bounds_mm
from ctsplat.training.state import TrainState, amplitude, replace_params

__all__ = ["GradientDensify", "ErrorDensify", "make_densify", "reset_stats"]

log = logging.getLogger(__name__)


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

    #: Whether the loop must call :meth:`ErrorDensify.accumulate_error` (residual maps).
    wants_error = False

    def __init__(self, settings: dict[str, Any], *, compositor: str, iterations: int) -> None:
        self.settings = dict(settings)
        self.compositor = compositor
        self.iterations = int(iterations)
        self.stop = int(settings["stop"]) or int(0.75 * self.iterations)
        interval, start = int(settings["interval"]), int(settings["start"])
        if interval:
            first = -(-max(start, 1) // interval) * interval  # the first multiple of the interval from start on
            last = min(self.stop, self.iterations - 1)
            if first > last:
                log.warning("train.densify never clones or splits: no multiple of densify.interval (%d) lies in "
                            "[densify.start, min(stop, iterations - 1)] = [%d, %d]; lower densify.interval or "
                            "densify.start, raise densify.stop, or set densify.interval: 0 to turn densification off",
                            interval, start, last)

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
                   ndc_half: torch.Tensor, *, loss_views: int = 1) -> None:
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
        loss_views : int
            Views the loss averages over (``batch_views``): each view's gradient is ``1 / loss_views`` of its own
            loss's, so it is scaled back and ``grad_threshold`` keeps its meaning for any batch (as gsplat scales
            by its number of cameras).
        """
        if means2d_grad is None:
            return
        # masked arithmetic rather than boolean indexing: the same sums, without the host synchronisation that
        # indexing with a mask costs on a GPU (its result size must be read back)
        norm = (means2d_grad * (ndc_half * loss_views)).norm(dim=-1)
        state.grad_accum += torch.where(visible, norm, 0.0)
        state.grad_count += visible.to(state.grad_count.dtype)

    def maybe_step(self, state: TrainState, iteration: int, volume: Any, gen: torch.Generator
                   ) -> dict[str, int] | None:
        """Densify and prune when due (:meth:`due`), or prune only (:meth:`prune_due`).

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
        if self.due(iteration):
            return self.step(state, volume, gen)
        if self.prune_due(iteration):
            return self.prune(state, volume)
        return None

    def prune_due(self, iteration: int) -> bool:
        """Like :meth:`due`, for the prune-only steps: with ``prune_until_end``, every ``interval`` after ``stop``
        and at the last iteration."""
        d = self.settings
        if not d.get("prune_until_end") or not d["interval"] or iteration <= self.stop:
            return False
        return iteration % int(d["interval"]) == 0 or iteration == self.iterations

    def prune_mask(self, means: torch.Tensor, log_scales: torch.Tensor, amplitude: torch.Tensor,
                   volume: Any) -> torch.Tensor:
        """The Gaussians pruning removes: amplitude (density; alpha: opacity) < ``prune_density``, max scale >
        ``prune_max_scale_fraction`` × the volume's extent, or centre more than 2 voxels outside the volume box (never
        all of them).

        Parameters
        ----------
        means : Tensor (N, 3)
            Centres (mm).
        log_scales : Tensor (N, 3)
        amplitude : Tensor (N,)
            :func:`ctsplat.training.state.amplitude` of each Gaussian.
        volume : ctsplat.formats.volume.Volume

        Returns
        -------
        Tensor (N,) bool
        """
        d = self.settings
        voxel = float(np.mean(volume.spacing_mm))
        lo, hi = grid_bounds_mm(volume.shape, volume.affine)
        dev = means.device
        lo_t = torch.as_tensor(lo - 2 * voxel, dtype=means.dtype, device=dev)
        hi_t = torch.as_tensor(hi + 2 * voxel, dtype=means.dtype, device=dev)
        extent = float(np.max(hi - lo))
        bad = amplitude < float(d["prune_density"])
        bad |= torch.exp(log_scales).max(-1).values > float(d["prune_max_scale_fraction"]) * extent
        bad |= ((means < lo_t) | (means > hi_t)).any(-1)
        if bool(bad.all()):  # never prune everything
            bad[:] = False
        return bad

    def prune(self, state: TrainState, volume: Any) -> dict[str, int]:
        """Prune only (:meth:`prune_mask`); the gradient statistics are reset.

        Parameters
        ----------
        state : TrainState
            Changed in place (parameters and Adam moments).
        volume : ctsplat.formats.volume.Volume

        Returns
        -------
        dict
            ``cloned`` and ``split`` (0), ``pruned``, ``merged`` (0) and ``n``.
        """
        p = state.params
        with torch.no_grad():
            bad = self.prune_mask(p["means"].detach(), p["log_scales"].detach(), amplitude(p, self.compositor),
                                  volume)
        if bool(bad.any()):
            state.params = replace_params(state.opt, p, torch.nonzero(~bad).flatten(), {})
        reset_stats(state)
        n = int(state.params["means"].shape[0])
        return {"cloned": 0, "split": 0, "pruned": int(bad.sum()), "merged": 0, "n": n}

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
        # merging first: clones of this step start coincident by design; those of earlier steps had an interval
        # to separate
        merged = self.merge(state)
        p = state.params
        n = p["means"].shape[0]
        dev = p["means"].device
        vol = volume
        voxel = float(np.mean(vol.spacing_mm))
        with torch.no_grad():
            cand, avg = self.candidates(state)
            scales = torch.exp(p["log_scales"])
            smax = scales.max(-1).values
            dens = torch.nn.functional.softplus(p["density_raw"])
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
            amp = amplitude({k: torch.cat([p[k].detach()[keep], new[k]]) for k in ("density_raw", "opacity_raw")
                             if k in p}, self.compositor)
            bad = self.prune_mask(all_means, all_ls, amp, vol)
        # apply: first keep/append, then prune
        state.params = replace_params(state.opt, p, torch.nonzero(keep).flatten(), new)
        good = torch.nonzero(~bad).flatten()
        state.params = replace_params(state.opt, state.params, good, {})
        m = state.params["means"].shape[0]
        reset_stats(state)
        return {"cloned": int(ci.numel()), "split": int(si.numel()), "pruned": int(bad.sum()) + merged,
                "merged": merged, "n": m}

    def candidates(self, state: TrainState) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaussians to clone or split, and their priority when the ``max_gaussians`` budget is short.

        Parameters
        ----------
        state : TrainState
            Its positional-gradient statistics.

        Returns
        -------
        cand : Tensor (N,) bool
            Mean positional gradient >= ``grad_threshold``.
        priority : Tensor (N,)
            The mean positional gradient.
        """
        avg = state.grad_accum / state.grad_count.clamp_min(1)
        return avg >= float(self.settings["grad_threshold"]), avg

    def merge(self, state: TrainState) -> int:
        """Redundant-coverage pruning (``prune_redundant``, :func:`ctsplat.training.features.merge_redundant`).

        Parameters
        ----------
        state : TrainState
            Changed in place (parameters and Adam moments).

        Returns
        -------
        int
            Gaussians removed.
        """
        settings = self.settings.get("prune_redundant") or {}
        if not settings.get("enabled"):
            return 0
        drop, updates = merge_redundant(state.params, settings, self.compositor)
        n_drop = int(drop.sum())
        if n_drop == 0 or n_drop == drop.numel():
            return 0
        with torch.no_grad():
            for k, v in updates.items():
                state.params[k].data.copy_(v)
        keep = torch.nonzero(~drop).flatten()
        state.params = replace_params(state.opt, state.params, keep, {})
        for name in ("grad_accum", "grad_count", "err_accum", "err_count"):
            stat = getattr(state, name)
            if stat is not None and stat.shape[0] == drop.shape[0]:
                setattr(state, name, stat[keep])
        return n_drop


class ErrorDensify(GradientDensify):
    """Error-driven densification, alone (``strategy: error``) or beside the gradient rule (``both``).

    After each training render the absolute residual map of the view is splatted back onto the Gaussians that
    cover it: with ``a`` a Gaussian's amplitude parameter and ``I`` the rendered image, ``e = Σ_p |r_p| ∂I_p/∂a /
    Σ_p ∂I_p/∂a`` is the mean residual under the Gaussian's footprint, weighted by its contribution (the
    per-Gaussian factor of ``∂I/∂a`` cancels). ``a`` is ``density_raw`` for the radiative compositors, whose
    ``∂I_p/∂a`` is the footprint, and the colour for alpha, whose ``∂I_p/∂c_i = α_i(p) T_i(p)`` is the blending
    weight (the opacity's derivative changes sign across a footprint: ``T_i G_i (c_i − C_behind)``, no weight
    of a mean). Both are non-negative, so ``e`` lies between the smallest and largest residual. Each view's ``e`` is
    divided by its mean over that view's visible Gaussians and accumulated like the positional-gradient
    statistic; Gaussians whose mean ratio reaches ``error_ratio`` are cloned or split by the same rules as
    :class:`GradientDensify` (``both``: either criterion).

    Parameters
    ----------
    settings, compositor, iterations
        As :class:`GradientDensify`; ``settings["strategy"]`` is ``error`` or ``both``.

    References
    ----------
    Rota Bulò, S., Porzi, L., Kontschieder, P. (2024). Revising densification in Gaussian splatting. ECCV
    (per-pixel error distributed to the Gaussians that render it).
    """

    wants_error = True

    def __init__(self, settings: dict[str, Any], *, compositor: str, iterations: int) -> None:
        super().__init__(settings, compositor=compositor, iterations=iterations)
        self.mode = str(settings.get("strategy", "error"))
        self.amplitude_key = "colors" if compositor == "alpha" else "density_raw"

    def collecting(self, iteration: int) -> bool:
        """Whether the step ``iteration`` (1-based) feeds a densification to come (residual maps cost a backward).

        Parameters
        ----------
        iteration : int

        Returns
        -------
        bool
        """
        d = self.settings
        return bool(d["interval"]) and iteration <= self.stop and iteration < self.iterations

    def error_ratios(self, state: TrainState, image: torch.Tensor, residual: torch.Tensor,
                     visible: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Splat one view's absolute residual onto the Gaussians that cover it (call before the loss's backward).

        Parameters
        ----------
        state : TrainState
            Its parameters (the amplitude parameter's gradient path).
        image : Tensor (H, W)
            The rendered view, attached to the graph (kept for the loss's backward).
        residual : Tensor (H, W)
            Prediction minus target, in any units (only ratios are used).
        visible : Tensor (N,) bool

        Returns
        -------
        (cover, ratio) or None
            ``cover`` (N,) bool, the Gaussians with a footprint in the view; ``ratio`` their mean residual divided
            by its mean over ``cover``. None when no Gaussian covers a residual.
        """
        amp = state.params[self.amplitude_key]
        w = residual.detach().abs().to(image.dtype)
        g_w, = torch.autograd.grad(image, amp, grad_outputs=w, retain_graph=True, allow_unused=True)
        g_1, = torch.autograd.grad(image, amp, grad_outputs=torch.ones_like(image), retain_graph=True,
                                   allow_unused=True)
        if g_w is None or g_1 is None:
            return None
        with torch.no_grad():
            g_w, g_1 = g_w.reshape(len(amp), -1).sum(1), g_1.reshape(len(amp), -1).sum(1)  # colours: (N, C)
            cover = visible & (g_1.abs() > 0)
            if not bool(cover.any()):
                return None
            e = g_w[cover] / g_1[cover]
            mean = e.mean()
            if not bool(mean > 0) or not bool(torch.isfinite(e).all()):
                return None
            return cover, e / mean

    @staticmethod
    def accumulate_error(state: TrainState, ratios: tuple[torch.Tensor, torch.Tensor] | None) -> None:
        """Add one view's :meth:`error_ratios` to the error statistic.

        Parameters
        ----------
        state : TrainState
            ``err_accum`` / ``err_count`` (N,) are updated in place.
        ratios : (cover, ratio) or None
        """
        if ratios is None:
            return
        cover, ratio = ratios
        state.err_accum[cover] += ratio
        state.err_count[cover] += 1

    def candidates(self, state: TrainState) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaussians whose mean error ratio reaches ``error_ratio`` (``both``: or the gradient rule's).

        Parameters
        ----------
        state : TrainState

        Returns
        -------
        cand : Tensor (N,) bool
        priority : Tensor (N,)
            The error ratio (``both``: the larger of it and the gradient rule's priority, each relative to its
            threshold).
        """
        err = state.err_accum / state.err_count.clamp_min(1)
        thr = float(self.settings["error_ratio"])
        cand = err >= thr
        if self.mode != "both":
            return cand, err
        g_cand, g_avg = super().candidates(state)
        g_thr = max(float(self.settings["grad_threshold"]), 1e-30)
        return cand | g_cand, torch.maximum(err / thr, g_avg / g_thr)


def make_densify(settings: dict[str, Any], *, compositor: str, iterations: int) -> GradientDensify:
    """The strategy object of ``settings["strategy"]``: :class:`GradientDensify` or :class:`ErrorDensify`.

    Parameters
    ----------
    settings : dict
        The ``train.densify`` section.
    compositor : str
    iterations : int

    Returns
    -------
    GradientDensify
    """
    cls = GradientDensify if settings.get("strategy", "gradient") == "gradient" else ErrorDensify
    return cls(settings, compositor=compositor, iterations=iterations)


def reset_stats(state: TrainState) -> None:
    """Zero the densification statistics (positional gradient and error), sized to the current Gaussians.

    Parameters
    ----------
    state : TrainState
    """
    m = state.params["means"].shape[0]
    dev = state.params["means"].device
    state.grad_accum = torch.zeros(m, device=dev)
    state.grad_count = torch.zeros(m, device=dev)
    state.err_accum = torch.zeros(m, device=dev)
    state.err_count = torch.zeros(m, device=dev)

