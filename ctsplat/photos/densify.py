"""Adaptive density control for alpha-composited 3DGS on photographs (Kerbl et al. 2023, section 5.2).

The radiative strategy beside it (:class:`ctsplat.training.densify.GradientDensify`) conserves mass and prunes by
density and by the CT volume's box; photographs have neither a density nor a box, so this strategy follows 3DGS
itself: Gaussians whose mean view-space positional gradient exceeds ``grad_threshold`` are cloned (max scale at
most ``percent_dense`` × the scene extent) or split in two (larger ones; samples from the Gaussian, scales / 1.6);
Gaussians with opacity below ``prune_opacity`` are pruned, and after the first opacity reset also those wider
than ``prune_scale_fraction`` × the extent (3DGS's schedule: the large Gaussians that fill a backdrop early on are
kept until then). 3DGS's other rule after a reset, Gaussians wider than 20 px in a view, is not applied: in 3DGS's
code it never acts, because cloning and splitting zero every screen radius before the prune reads them, and its
authors kept it so because the paper's results were made that way (graphdeco-inria/gaussian-splatting, issue 123).
Every ``opacity_reset_interval`` iterations opacities are clamped to at most 0.01, while densifying
(:func:`step_due`: from ``start``, before the stop). With ``size_prune: always`` the size rule applies from the
first densification step, and prune-only steps (both rules, no clone or split) follow every ``interval`` iterations
after densification stops, to the end of training: a schedule that stops densifying before the first reset would
otherwise never prune by size. With ``near_prune`` > 0, Gaussians whose largest standard deviation exceeds
``near_prune`` × their distance to the nearest training camera centre are pruned at every densification step and in
prune-only steps to the end of training: such a Gaussian fills more than a photo's field of view of that camera, so
it is no surface that camera saw, yet a held-out camera near it looks through it. The gradient
statistics are accumulated exactly as the radiative strategy does (:meth:`GradientDensify.accumulate`, 3DGS's NDC
units). With ``gradient: pixel`` they follow Pixel-GS instead: each view's gradient norm is weighted by the pixels
the Gaussian covers in it, so that a large Gaussian in a region the SfM points do not seed, seen whole in some
views and at an edge in others, is not averaged below the threshold, and scaled by ``min(1, (z / (0.37 R))²)``
(``z`` its depth in the view, ``R`` the scene extent), so that Gaussians close to a camera, which cover many of
its pixels, do not densify into floaters. The pixels are :func:`ctsplat.splat.render.alpha_footprints`, which
counts those where the Gaussian is hidden too; Pixel-GS counts only those it is blended into before the pixel's
transmittance falls below 1e-4 (a compositor output this renderer does not have).

References
----------
Kerbl, B., Kopanas, G., Leimkühler, T., Drettakis, G. (2023). 3D Gaussian Splatting for real-time radiance field
rendering. ACM TOG 42(4).
Zhang, Z., Hu, W., Lao, Y., He, T., Zhao, H. (2024). Pixel-GS: Density control with pixel-aware gradient for 3D
Gaussian splatting. ECCV.
"""

from __future__ import annotations

from typing import Any

import torch

from ctsplat.splat.gaussians import quat_to_rotmat
from ctsplat.training.densify import GradientDensify
from ctsplat.training.state import replace_params

__all__ = ["AlphaDensify", "step_due"]

_RESET_OPACITY = 0.01
#: Pixel-GS's depth at which a view's gradient is no longer scaled down, as a fraction of the scene extent.
PIXEL_GS_DEPTH_FRACTION = 0.37


def step_due(iteration: int, *, start: int, interval: int, until: int) -> bool:
    """Whether a density-control step runs after ``iteration`` completed iterations: every ``interval`` from
    ``start`` (included: the defaults were chosen with it, where 3DGS starts after its ``densify_from_iter``) up to
    ``until`` (excluded, as 3DGS's ``densify_until_iter``).

    Parameters
    ----------
    iteration, start, interval, until : int
        ``interval`` 0: never.

    Returns
    -------
    bool

    Examples
    --------
    >>> [i for i in range(0, 1100, 100) if step_due(i, start=500, interval=100, until=1000)]
    [500, 600, 700, 800, 900]
    """
    return bool(interval) and start <= iteration < until and iteration % interval == 0


class AlphaDensify:
    """Clone / split / prune / opacity reset for alpha compositing (module docstring).

    Parameters
    ----------
    settings : dict
        The ``photos.train.densify`` section.
    iterations : int
        Total training iterations.
    extent : float
        Scene extent (:func:`ctsplat.photos.dataset.scene_extent`), world units.
    means : Tensor (N, 3)
        The initial means: the gradient statistics take their count and device.
    camera_centers : Tensor (C, 3), optional
        The training cameras' centres, world units; needed when ``near_prune`` > 0.
    """

    def __init__(self, settings: dict[str, Any], *, iterations: int, extent: float, means: torch.Tensor,
                 camera_centers: torch.Tensor | None = None) -> None:
        self.settings = dict(settings)
        if float(settings["near_prune"]) > 0 and (camera_centers is None or camera_centers.shape[0] == 0):
            raise ValueError("densify.near_prune > 0 needs the training cameras' centres")
        self.camera_centers = camera_centers
        self.iterations = int(iterations)
        self.extent = float(extent)
        self.stop = int(float(settings["stop_fraction"]) * self.iterations)
        self.grad_accum = torch.zeros(means.shape[0], device=means.device)
        self.grad_count = torch.zeros(means.shape[0], device=means.device)

    def accumulate(self, means2d_grad: torch.Tensor | None, visible: torch.Tensor, ndc_half: torch.Tensor, *,
                   footprints: torch.Tensor | None = None, depths: torch.Tensor | None = None) -> None:
        """Add one view's positional-gradient norms to the visible Gaussians' statistics.

        Parameters
        ----------
        means2d_grad : Tensor (N, 2) or None
            ∂L/∂(u, v) of the projected means, px.
        visible : Tensor (N,) bool
        ndc_half : Tensor (2,)
            ``(W/2, H/2)``.
        footprints, depths : Tensor (N,), optional
            Pixels covered and depth in the view (``RenderOutput.footprints``, ``.depths``); needed with
            ``gradient: pixel``.
        """
        if self.settings["gradient"] != "pixel":
            GradientDensify.accumulate(self, means2d_grad, visible, ndc_half)
            return
        if means2d_grad is None:
            return
        if footprints is None or depths is None:
            raise ValueError("densify.gradient: pixel needs each view's footprints and depths")
        near = PIXEL_GS_DEPTH_FRACTION * self.extent
        scale = torch.clamp((depths / near) ** 2, max=1.0)
        norm = (means2d_grad * ndc_half).norm(dim=-1) * scale
        weight = torch.where(visible, footprints.to(norm.dtype), 0.0)
        self.grad_accum += norm * weight
        self.grad_count += weight

    def mean_gradients(self) -> torch.Tensor:
        """Each Gaussian's accumulated gradient statistic (0 where it was never visible), Tensor (N,).

        The count is views (``mean``, at least 1 where visible) or pixels (``pixel``, possibly below 1): the floor
        only keeps 0 / 0 finite, and where the count is 0 the sum is 0 too.
        """
        return self.grad_accum / self.grad_count.clamp_min(1e-30)

    def due(self, iteration: int) -> bool:
        """Whether a densification step (after the stop, with ``size_prune: always`` or ``near_prune``, a
        prune-only step) runs after ``iteration`` completed iterations."""
        d = self.settings
        until = self.iterations if d["size_prune"] == "always" or float(d["near_prune"]) > 0 else self.stop
        return step_due(iteration, start=int(d["start"]), interval=int(d["interval"]), until=until)

    def reset_due(self, iteration: int) -> bool:
        """Whether opacities are reset after ``iteration``: while densifying, as in 3DGS, so that a densification
        step always follows a reset (one at the stop would leave its faded Gaussians unpruned)."""
        k = int(self.settings["opacity_reset_interval"])
        return bool(k) and iteration % k == 0 and iteration < min(self.stop, self.iterations)

    def step(self, params: dict[str, torch.Tensor], opt: torch.optim.Adam, gen: torch.Generator, *,
             iteration: int) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
        """One clone / split / prune step (Adam moments follow; statistics reset).

        Parameters
        ----------
        params : dict of str to Tensor
            ``means``, ``log_scales``, ``quats``, ``opacity_raw``, ``colors``, ``sh_rest`` (N rows each).
        opt : torch.optim.Adam
            Its groups are named after the parameters.
        gen : torch.Generator
            Source of the split samples.
        iteration : int
            The completed iterations; the size prune applies once it exceeds ``opacity_reset_interval``.

        Returns
        -------
        params : dict of str to Tensor
            New leaf tensors.
        stats : dict
            ``cloned``, ``split``, ``pruned``, ``n``.
        """
        d = self.settings
        n = params["means"].shape[0]
        dev = params["means"].device
        with torch.no_grad():
            avg = self.mean_gradients()
            scales = torch.exp(params["log_scales"])
            smax = scales.max(-1).values
            cand = (avg >= float(d["grad_threshold"])) & (iteration <= self.stop)
            small = smax <= float(d["percent_dense"]) * self.extent
            budget = max(int(d["max_gaussians"]) - n, 0)
            if int(cand.sum()) > budget:  # keep the largest gradients within the cap
                idx = torch.nonzero(cand).flatten()
                keep_idx = idx[torch.argsort(avg[idx], descending=True, stable=True)[:budget]]
                cand = torch.zeros_like(cand)
                cand[keep_idx] = True
            ci = torch.nonzero(cand & small).flatten()
            si = torch.nonzero(cand & ~small).flatten()
            new: dict[str, list[torch.Tensor]] = {k: [v.detach()[ci]] for k, v in params.items()}
            if si.numel():
                rot = quat_to_rotmat(params["quats"].detach()[si])
                z = torch.randn((2, si.numel(), 3), generator=gen).to(dev)
                offs = torch.einsum("nij,knj->kni", rot, z * scales[si][None])
                for k, v in params.items():
                    if k == "means":
                        new[k] += [v.detach()[si] + offs[0], v.detach()[si] + offs[1]]
                    elif k == "log_scales":
                        new[k] += [torch.log(scales[si] / 1.6)] * 2
                    else:
                        new[k] += [v.detach()[si]] * 2
            keep = torch.ones(n, dtype=torch.bool, device=dev)
            keep[si] = False
            params = replace_params(opt, params, torch.nonzero(keep).flatten(),
                                    {k: torch.cat(v) for k, v in new.items()})
            op = torch.sigmoid(params["opacity_raw"])
            bad = op < float(d["prune_opacity"])
            reset = int(d["opacity_reset_interval"])  # 0: no reset, so "after the first reset" never comes
            if d["size_prune"] == "always" or (reset > 0 and iteration > reset):
                bad |= torch.exp(params["log_scales"]).max(-1).values > float(d["prune_scale_fraction"]) * self.extent
            if float(d["near_prune"]) > 0:
                dist = torch.cdist(params["means"], self.camera_centers.to(params["means"])).min(-1).values
                bad |= torch.exp(params["log_scales"]).max(-1).values > float(d["near_prune"]) * dist
            if bool(bad.all()):  # never prune everything
                bad[:] = False
            params = replace_params(opt, params, torch.nonzero(~bad).flatten(), {})
        m = params["means"].shape[0]
        self.grad_accum = torch.zeros(m, device=dev)
        self.grad_count = torch.zeros(m, device=dev)
        return params, {"cloned": int(ci.numel()), "split": int(si.numel()), "pruned": int(bad.sum()), "n": m}

    @staticmethod
    def reset_opacity(params: dict[str, torch.Tensor], opt: torch.optim.Adam) -> None:
        """Clamp every opacity to at most 0.01 and zero its Adam moments (3DGS's opacity reset), in place."""
        with torch.no_grad():
            p = params["opacity_raw"]
            p.copy_(torch.minimum(p, torch.logit(torch.tensor(_RESET_OPACITY, dtype=p.dtype))))
            st = opt.state.get(p, {})
            for key in ("exp_avg", "exp_avg_sq"):
                if key in st:
                    st[key].zero_()
