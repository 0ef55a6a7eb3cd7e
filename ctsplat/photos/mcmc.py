"""3D Gaussian splatting as Markov chain Monte Carlo (Kheradmand et al. 2024): density control by relocation.

The strategy beside :class:`ctsplat.photos.densify.AlphaDensify` for alpha compositing. Instead of cloning and
splitting by a gradient threshold and pruning by opacity, it

- every ``densify.interval`` iterations from ``densify.start`` until ``mcmc.stop_fraction`` × the iterations,
  moves the *dead* Gaussians (opacity ≤ ``densify.prune_opacity``) onto live ones drawn with probability
  proportional to their opacity, then adds ``mcmc.growth`` − 1 of the current count (at most up to
  ``mcmc.cap_max``) drawn the same way. A Gaussian drawn ``N − 1`` times becomes ``N`` copies whose opacity and
  scales (:func:`relocation`) make them render together like the one they replace, so a move changes the image
  only where the optimiser later moves the copies apart;
- after every optimiser step, moves each mean by Gaussian noise shaped by its own covariance and gated by its
  transparency (:meth:`MCMCDensify.perturb`: nearly opaque Gaussians stay, transparent ones explore), scaled by
  the means' current learning rate × ``mcmc.noise_lr`` (stochastic gradient Langevin dynamics);
- adds ``mcmc.opacity_reg`` × mean opacity + ``mcmc.scale_reg`` × mean scale to the loss
  (:meth:`MCMCDensify.regularisation`), which lets Gaussians that explain nothing fade and be relocated.

The count grows to ``cap_max`` and stays there: the budget is set directly, not by a threshold. Gaussians are never
deleted; ``cloned`` counts the added ones and ``pruned`` the relocated (dead) ones in the training log.

References
----------
Kheradmand, S., Rebain, D., Sharma, G., Sun, W., Tseng, Y.-C., Isack, H., Kar, A., Tagliasacchi, A., Yi, K. M.
(2024). 3D Gaussian splatting as Markov chain Monte Carlo. NeurIPS (eq. 9: the relocation rule).
"""

from __future__ import annotations

from typing import Any

import torch

from ctsplat.photos.densify import step_due
from ctsplat.splat.gaussians import covariance
from ctsplat.training.state import replace_params

__all__ = ["MCMCDensify", "relocation", "MAX_COPIES"]

#: The most copies one relocation splits a Gaussian into (a Gaussian drawn more often keeps this many).
MAX_COPIES = 51


def relocation(opacity: torch.Tensor, scales: torch.Tensor, copies: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity and scales of ``N`` coincident copies that together render like one Gaussian.

    Along any line through the centre, ``N`` copies of opacity ``o'`` and scales ``s'`` composite to the peak alpha
    ``1 − (1 − o')ᴺ`` and to the integrated alpha ``∫ 1 − (1 − o' g(x / s'))ᴺ dx``; both match the original's
    (``o`` and ``∫ o g(x / s) dx``) when

    ``o' = 1 − (1 − o)^(1/N)``,  ``s' = o s / Σ_{i=1..N} Σ_{k=0..i−1} C(i−1, k) (−1)ᵏ o'^(k+1) / √(k+1)``.

    Parameters
    ----------
    opacity : Tensor (M,)
        Opacities in (0, 1).
    scales : Tensor (M, 3)
        Standard deviations (any unit; returned in the same).
    copies : Tensor (M,) int
        ``N`` ≥ 1 per Gaussian, clipped to :data:`MAX_COPIES`.

    Returns
    -------
    opacity : Tensor (M,)
    scales : Tensor (M, 3)
        Same dtype and device as the inputs; computed in float64 (the alternating sum cancels).

    References
    ----------
    Kheradmand et al. (2024), eq. 9 (module docstring).

    Examples
    --------
    >>> o, s = relocation(torch.tensor([0.5]), torch.ones(1, 3), torch.tensor([2]))
    >>> round(float(1 - (1 - o[0]) ** 2), 6)  # two copies keep the peak alpha
    0.5
    """
    o = opacity.double()
    n = copies.clamp(1, MAX_COPIES).to(torch.float64)
    new_o = 1.0 - (1.0 - o) ** (1.0 / n)
    # the paper's double sum, equal to Σ_{k=1..N} C(N, k) (-1)^(k+1) a^k / √k (Σ_{i=k..N} C(i-1, k-1) = C(N, k)); its
    # terms alternate in sign and reach ~1.6e3 for opacities near 1 split 51 ways, while the sum is ≤ 1: float64
    nmax = int(n.max()) if n.numel() else 1
    i = torch.arange(1, nmax + 1, dtype=torch.float64, device=o.device)
    k = torch.arange(0, nmax, dtype=torch.float64, device=o.device)
    log_binom = torch.lgamma(i[:, None]) - torch.lgamma(k[None] + 1) - torch.lgamma((i[:, None] - k[None]).clamp_min(1))
    valid = (k[None] <= i[:, None] - 1).double()  # (I, K)
    coef = valid * torch.exp(log_binom) * (-1.0) ** k[None] / torch.sqrt(k[None] + 1)  # (I, K)
    powers = new_o[:, None] ** (k[None] + 1)  # (M, K)
    per_i = powers @ coef.T  # (M, I)
    denom = (per_i * (i[None] <= n[:, None]).double()).sum(-1)
    new_s = scales.double() * (o / denom)[:, None]
    return new_o.to(opacity.dtype), new_s.to(scales.dtype)


class MCMCDensify:
    """Relocation, growth to a cap and position noise (module docstring).

    Parameters
    ----------
    settings : dict
        The ``photos.train.densify`` section (``interval``, ``start``, ``prune_opacity``).
    mcmc : dict
        The ``photos.train.mcmc`` section (``cap_max``, ``growth``, ``stop_fraction``, ``noise_lr``,
        ``opacity_reg``, ``scale_reg``).
    iterations : int
        Total training iterations.
    """

    def __init__(self, settings: dict[str, Any], mcmc: dict[str, Any], *, iterations: int) -> None:
        self.settings = dict(settings)
        self.mcmc = dict(mcmc)
        self.iterations = int(iterations)
        self.stop = int(float(mcmc["stop_fraction"]) * self.iterations)
        self.min_opacity = float(settings["prune_opacity"])

    def accumulate(self, means2d_grad: torch.Tensor | None, visible: torch.Tensor, ndc_half: torch.Tensor, *,
                   footprints: torch.Tensor | None = None, depths: torch.Tensor | None = None) -> None:
        """Nothing to accumulate: the moves are driven by opacity, not by gradients."""

    def due(self, iteration: int) -> bool:
        """Whether :meth:`step` runs after ``iteration`` completed iterations (the clone / split schedule, with
        this strategy's stop; the default strategy's pruning options do not extend it)."""
        d = self.settings
        return step_due(iteration, start=int(d["start"]), interval=int(d["interval"]), until=self.stop)

    def reset_due(self, iteration: int) -> bool:
        """Never: the regulariser, not a reset, lets opacities fall."""
        return False

    def regularisation(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """``opacity_reg`` × mean opacity + ``scale_reg`` × mean scale (world units), added to the loss."""
        m = self.mcmc
        return float(m["opacity_reg"]) * torch.sigmoid(params["opacity_raw"]).mean() \
            + float(m["scale_reg"]) * torch.exp(params["log_scales"]).mean()

    def perturb(self, params: dict[str, torch.Tensor], gen: torch.Generator, lr_means: float) -> None:
        """Move every mean by ``Σ z · σ(100 (1 − o − 0.995)) · lr_means · noise_lr``, ``z ~ N(0, I)``, in place.

        Parameters
        ----------
        params : dict of str to Tensor
        gen : torch.Generator
            A CPU generator (the noise is drawn on the host, so a run is the same on every device).
        lr_means : float
            The means' learning rate at this iteration (world units).
        """
        with torch.no_grad():
            means = params["means"]
            o = torch.sigmoid(params["opacity_raw"])
            gate = torch.sigmoid(100.0 * ((1.0 - o) - 0.995))
            z = torch.randn(means.shape, generator=gen, dtype=means.dtype).to(means.device)
            step = z * (gate * float(lr_means) * float(self.mcmc["noise_lr"]))[:, None]
            cov = covariance(params["log_scales"], params["quats"])
            means.add_(torch.einsum("nij,nj->ni", cov, step))

    def step(self, params: dict[str, torch.Tensor], opt: torch.optim.Adam, gen: torch.Generator, *,
             iteration: int) -> tuple[dict[str, torch.Tensor], dict[str, int]]:
        """Relocate the dead Gaussians, then add new ones up to the cap (Adam moments of every moved or copied row
        start at zero).

        Parameters
        ----------
        params, opt, iteration
            As :meth:`ctsplat.photos.densify.AlphaDensify.step` (``iteration`` is unused here).
        gen : torch.Generator
            A CPU generator for the draws.

        Returns
        -------
        params : dict of str to Tensor
            New leaf tensors.
        stats : dict
            ``cloned`` (added), ``split`` (0), ``pruned`` (relocated), ``n``.
        """
        with torch.no_grad():
            o = torch.sigmoid(params["opacity_raw"].detach())
            dead = torch.nonzero(o <= self.min_opacity).flatten()
            live = torch.nonzero(o > self.min_opacity).flatten()
            moved = 0
            if dead.numel() and live.numel():
                src = live[self._draw(o[live], dead.numel(), gen)]
                self._copy(params, opt, src, dead)
                moved = int(dead.numel())
            n = params["means"].shape[0]
            target = min(int(self.mcmc["cap_max"]), int(float(self.mcmc["growth"]) * n))
            added = max(target - n, 0)
            if added:
                o = torch.sigmoid(params["opacity_raw"].detach())
                src = self._draw(o, added, gen)
                self._copy(params, opt, src, None)
                params = replace_params(opt, params, torch.arange(n, device=o.device),
                                        {k: v.detach()[src] for k, v in params.items()})
        return params, {"cloned": added, "split": 0, "pruned": moved, "n": int(params["means"].shape[0])}

    @staticmethod
    def _draw(weights: torch.Tensor, count: int, gen: torch.Generator) -> torch.Tensor:
        """``count`` indices drawn with replacement, probability ∝ ``weights`` (on the host, for determinism)."""
        w = weights.detach().double().cpu()
        return torch.multinomial(w / w.sum(), count, replacement=True, generator=gen).to(weights.device)

    def _copy(self, params: dict[str, torch.Tensor], opt: torch.optim.Adam, src: torch.Tensor,
              dst: torch.Tensor | None) -> None:
        """Give the sources drawn ``src`` (with repeats) their post-split opacity and scales in place, copy them
        onto rows ``dst`` (None: the caller appends them) and zero the Adam moments of both."""
        copies = torch.bincount(src, minlength=params["means"].shape[0])[src] + 1
        o = torch.sigmoid(params["opacity_raw"].detach()[src])
        new_o, new_s = relocation(o, torch.exp(params["log_scales"].detach()[src]), copies)
        eps = torch.finfo(new_o.dtype).eps
        new_o = new_o.clamp(self.min_opacity, 1.0 - eps)
        params["opacity_raw"].data[src] = torch.logit(new_o)
        params["log_scales"].data[src] = torch.log(new_s)
        rows = src if dst is None else torch.cat([src, dst])
        if dst is not None:
            for v in params.values():
                v.data[dst] = v.data[src]
        for p in params.values():
            st = opt.state.get(p, {})
            for key in ("exp_avg", "exp_avg_sq"):
                if key in st:
                    st[key][rows] = 0.0
