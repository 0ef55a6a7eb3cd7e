"""Iterative reconstructions for any geometry: SART/SIRT (ordered subsets) and ASD-POCS (TV-regularised).

``A`` is the project's projector and ``Aᵀ`` its exact adjoint (:class:`ctsplat.recon.operators.Operator`), so these
methods work for parallel and cone beams on circular, sphere and C-arm orbits alike; ``b`` is the line integrals
divided by ``mu_scale_per_mm`` (the normalised volume's units).

**SART / SIRT.** The views are split into ``subsets`` groups, interleaved in azimuth; one iteration visits every
group once and updates

    x <- max(0, x + λ C_S A_Sᵀ R_S (b_S - A_S x)),   R = 1 / (A 1) per ray,  C_S = 1 / (A_Sᵀ 1) per voxel

(zero where a ray or voxel is never hit). One subset is SIRT (Gilbert 1972), one view per subset is SART (Andersen
& Kak 1984); in between is ordered-subsets SART. ``max(0, ·)`` is the non-negativity constraint.

**ASD-POCS** (adaptive steepest descent, projection onto convex sets; Sidky & Pan 2008): every iteration is one
data-consistency sweep (the SART update above, relaxation ``λ`` shrinking by ``relaxation_red`` per iteration) and
the positivity projection, then ``tv_steps`` steps of steepest descent on the total variation, each of length
``dtvg`` along the normalised TV gradient. ``dtvg`` starts at ``alpha`` times the first sweep's change ``dp`` and
shrinks by ``alpha_red`` whenever the TV steps moved the volume by more than ``r_max · dp`` (the adaptive rule
that keeps the TV descent from dominating the data steps); it is also capped at ``alpha`` times the current
sweep's change, so that a zero start (whose first sweep changes everything) does not let TV dominate the few
iterations a CPU budget allows. ``alpha`` is the TV weight.

References
----------
Andersen, A. H., Kak, A. C. (1984). Simultaneous algebraic reconstruction technique (SART): a superior
implementation of the ART algorithm. Ultrasonic Imaging 6(1), 81-94.
Gilbert, P. (1972). Iterative methods for the three-dimensional reconstruction of an object from projections.
Journal of Theoretical Biology 36(1), 105-117.
Sidky, E. Y., Pan, X. (2008). Image reconstruction in circular cone-beam computed tomography by constrained,
total-variation minimization. Physics in Medicine and Biology 53(17), 4777-4807.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from ctsplat.formats.viewset import ViewSet
from ctsplat.recon.operators import Operator, check_stack, reference_grid
from ctsplat.utils import CtsplatError

__all__ = [
    "total_variation",
    "tv_gradient",
    "sart_iterates",
    "sart_volume",
    "asd_pocs_iterates",
    "asd_pocs_volume",
]


def total_variation(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Isotropic total variation ``Σ √(Δi² + Δj² + Δk² + eps)`` with forward differences (voxel units)."""
    di = x[1:, :-1, :-1] - x[:-1, :-1, :-1]
    dj = x[:-1, 1:, :-1] - x[:-1, :-1, :-1]
    dk = x[:-1, :-1, 1:] - x[:-1, :-1, :-1]
    return torch.sqrt(di * di + dj * dj + dk * dk + eps).sum()


def tv_gradient(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Gradient of :func:`total_variation` with respect to ``x`` (same shape), in closed form.

    With ``D = √(Δi² + Δj² + Δk² + eps)`` on the voxels that have all three forward neighbours, each such voxel
    gets ``-(Δi + Δj + Δk) / D`` and its neighbours along i, j, k get ``Δi / D``, ``Δj / D``, ``Δk / D``.
    """
    x = x.detach()
    c = x[:-1, :-1, :-1]
    di = x[1:, :-1, :-1] - c
    dj = x[:-1, 1:, :-1] - c
    dk = x[:-1, :-1, 1:] - c
    inv = torch.rsqrt(di * di + dj * dj + dk * dk + eps)
    di, dj, dk = di * inv, dj * inv, dk * inv
    g = torch.zeros_like(x)
    g[:-1, :-1, :-1] -= di + dj + dk
    g[1:, :-1, :-1] += di
    g[:-1, 1:, :-1] += dj
    g[:-1, :-1, 1:] += dk
    return g


def _subsets(view_set: ViewSet, subsets: int) -> list[np.ndarray]:
    """Row indices in ``subsets`` groups, interleaved in azimuth order (neighbouring views in different groups)."""
    order = np.argsort(np.mod([v.azimuth_deg for v in view_set.views], 360.0), kind="stable")
    n = max(1, min(int(subsets), len(order)))
    return [order[s::n] for s in range(n)]


def _setup(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, mu_scale_per_mm: float | None,
           device: str | torch.device | None, views_per_batch: int, step_voxels: float
           ) -> tuple[Operator, torch.Tensor]:
    p = check_stack(line_integrals, view_set)
    affine, shape, scale = reference_grid(reference)
    scale = scale if mu_scale_per_mm is None else float(mu_scale_per_mm)
    op = Operator(view_set, affine, shape, device=device, views_per_batch=views_per_batch, step_voxels=step_voxels)
    return op, torch.as_tensor(p / scale, device=op.device)


class _Sweeper:
    """One SART/SIRT sweep over the subsets, with the ray and voxel normalisations computed once."""

    def __init__(self, op: Operator, b: torch.Tensor, subsets: int) -> None:
        self.op, self.b = op, b
        self.groups = _subsets(op.view_set, subsets)
        row = op.forward(torch.ones(op.shape, device=op.device))
        self.rinv = torch.where(row > 1e-6, 1.0 / row.clamp_min(1e-6), torch.zeros((), device=op.device))
        self.cinv = []
        for g in self.groups:
            col = op.adjoint(torch.ones((len(g), *b.shape[1:]), device=op.device), g)
            self.cinv.append(torch.where(col > 1e-6, 1.0 / col.clamp_min(1e-6), torch.zeros((), device=op.device)))

    def sweep(self, x: torch.Tensor, relaxation: float) -> tuple[torch.Tensor, float]:
        """``x`` after one pass over every subset (non-negative), and the data residual ``‖b - A x‖`` seen."""
        res2 = 0.0
        for g, cinv in zip(self.groups, self.cinv, strict=True):
            update, r2 = self.op.residual_adjoint(x, self.b[g], self.rinv[g], g)
            res2 += r2
            x = (x + relaxation * cinv * update).clamp_min(0.0)
        return x, res2**0.5


def _check(iterations: int, relaxation: float) -> None:
    if int(iterations) < 1:
        raise CtsplatError(f"iterations must be >= 1, got {iterations}")
    if not 0 < float(relaxation) < 2:
        raise CtsplatError(f"relaxation must be in (0, 2), got {relaxation}")


def sart_iterates(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, iterations: int = 10,
                  relaxation: float = 1.0, subsets: int = 1, mu_scale_per_mm: float | None = None,
                  device: str | torch.device | None = None, views_per_batch: int = 8, step_voxels: float = 0.5,
                  x0: torch.Tensor | np.ndarray | None = None) -> Iterator[tuple[int, torch.Tensor]]:
    """SART/SIRT with non-negativity on the reference grid, yielding the iterate after each iteration.

    Parameters
    ----------
    line_integrals : ndarray, shape (V, H, W)
        Line integrals of μ of the views in ``view_set``, same order.
    view_set : ViewSet
        Any camera and orbit.
    reference : Volume-like
        Anything with ``affine`` (4, 4) and ``shape`` (I, J, K).
    iterations : int
        Number of sweeps over all views, >= 1.
    relaxation : float
        ``λ`` in (0, 2).
    subsets : int
        Ordered subsets per sweep: 1 = SIRT, ``V`` = SART (one view at a time).
    mu_scale_per_mm : float, optional
        Maps normalised values to 1/mm; default ``reference.mu_scale_per_mm`` (1.0 if absent).
    device : str or torch.device, optional
        Torch device (CUDA when given); default CPU.
    views_per_batch : int
        Views projected at once.
    step_voxels : float
        Projector sampling step (voxels).
    x0 : tensor or ndarray, optional
        Starting volume (normalised); default zeros.

    Yields
    ------
    iteration : int
        1 .. ``iterations``.
    volume : torch.Tensor, shape (I, J, K), float32
        The non-negative iterate (normalised units, not clipped above), on ``device``.

    Raises
    ------
    CtsplatError
        For ``iterations < 1``, a relaxation outside (0, 2) or line integrals that do not match the view set.
    """
    _check(iterations, relaxation)
    op, b = _setup(line_integrals, view_set, reference, mu_scale_per_mm, device, views_per_batch, step_voxels)
    sweeper = _Sweeper(op, b, subsets)
    x = torch.zeros(op.shape, device=op.device) if x0 is None else torch.as_tensor(x0, dtype=torch.float32,
                                                                                   device=op.device).clamp_min(0)
    for it in range(1, int(iterations) + 1):
        x, _ = sweeper.sweep(x, float(relaxation))
        yield it, x


def sart_volume(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, iterations: int = 10,
                relaxation: float = 1.0, subsets: int = 1, clip: bool = True, **kwargs: Any) -> np.ndarray:
    """The last iterate of :func:`sart_iterates` as a float32 array (clipped to [0, 1] when ``clip``).

    Parameters
    ----------
    line_integrals, view_set, reference, iterations, relaxation, subsets
        As in :func:`sart_iterates`.
    clip : bool
        Clip to the normalised range [0, 1].
    **kwargs
        ``mu_scale_per_mm``, ``device``, ``views_per_batch``, ``step_voxels``, ``x0``.

    Returns
    -------
    ndarray, shape (I, J, K), float32
        The normalised volume on the reference grid.
    """
    x = deque(sart_iterates(line_integrals, view_set, reference, iterations=iterations, relaxation=relaxation,
                            subsets=subsets, **kwargs), maxlen=1)[0][1]
    vol = x.cpu().numpy().astype(np.float32)
    return np.clip(vol, 0.0, 1.0) if clip else vol


def asd_pocs_iterates(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, iterations: int = 20,
                      alpha: float = 0.2, tv_steps: int = 20, relaxation: float = 1.0, relaxation_red: float = 0.99,
                      alpha_red: float = 0.95, r_max: float = 0.95, subsets: int = 1,
                      mu_scale_per_mm: float | None = None, device: str | torch.device | None = None,
                      views_per_batch: int = 8, step_voxels: float = 0.5,
                      x0: torch.Tensor | np.ndarray | None = None) -> Iterator[tuple[int, torch.Tensor]]:
    """ASD-POCS (Sidky & Pan 2008): SART data sweeps + positivity, alternating with adaptive TV descent.

    Parameters
    ----------
    line_integrals, view_set, reference
        As in :func:`sart_iterates`.
    iterations : int
        Outer iterations (one data sweep and ``tv_steps`` TV steps each), >= 1.
    alpha : float
        TV weight: the TV step length is ``alpha`` times the first data sweep's change, > 0.
    tv_steps : int
        TV steepest-descent steps per iteration (``ng``), >= 1.
    relaxation, relaxation_red : float
        SART relaxation ``λ`` in (0, 2) and its factor per iteration (``β_red``) in (0, 1].
    alpha_red, r_max : float
        Factor the TV step shrinks by (in (0, 1)) when the TV steps moved the volume by more than ``r_max`` times
        the data step.
    subsets : int
        Ordered subsets of each data sweep (1 = SIRT).
    mu_scale_per_mm, device, views_per_batch, step_voxels, x0
        As in :func:`sart_iterates`.

    Yields
    ------
    iteration : int
        1 .. ``iterations``.
    volume : torch.Tensor, shape (I, J, K), float32
        The iterate after the TV steps (normalised units), on ``device``.

    Raises
    ------
    CtsplatError
        For out-of-range parameters or line integrals that do not match the view set.
    """
    _check(iterations, relaxation)
    if not alpha > 0:
        raise CtsplatError(f"ASD-POCS alpha (TV weight) must be > 0, got {alpha}")
    if int(tv_steps) < 1:
        raise CtsplatError(f"ASD-POCS tv_steps must be >= 1, got {tv_steps}")
    if not (0 < alpha_red < 1 and 0 < r_max and 0 < relaxation_red <= 1):
        raise CtsplatError("ASD-POCS needs alpha_red in (0, 1), r_max > 0 and relaxation_red in (0, 1]")
    op, b = _setup(line_integrals, view_set, reference, mu_scale_per_mm, device, views_per_batch, step_voxels)
    sweeper = _Sweeper(op, b, subsets)
    x = torch.zeros(op.shape, device=op.device) if x0 is None else torch.as_tensor(x0, dtype=torch.float32,
                                                                                   device=op.device).clamp_min(0)
    lam = float(relaxation)
    dtvg: float | None = None
    for it in range(1, int(iterations) + 1):
        x_prev = x
        x, _ = sweeper.sweep(x, lam)
        dp = float(torch.linalg.vector_norm(x - x_prev))
        # Sidky & Pan set the TV step once from the first data step and shrink it adaptively; from a zero start
        # that first step is the whole image, so the step is also capped at alpha times the current data step
        dtvg = float(alpha) * dp if dtvg is None else min(dtvg, float(alpha) * dp)
        x_data = x
        for _ in range(int(tv_steps)):
            g = tv_gradient(x)
            gn = float(torch.linalg.vector_norm(g))
            if gn == 0.0:
                break
            x = x - (dtvg / gn) * g
        dg = float(torch.linalg.vector_norm(x - x_data))
        if dg > r_max * dp:
            dtvg *= float(alpha_red)
        lam *= float(relaxation_red)
        yield it, x


def asd_pocs_volume(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, clip: bool = True,
                    **kwargs: Any) -> np.ndarray:
    """The last iterate of :func:`asd_pocs_iterates` as a float32 array (clipped to [0, 1] when ``clip``).

    Parameters
    ----------
    line_integrals, view_set, reference
        As in :func:`asd_pocs_iterates`.
    clip : bool
        Clip to the normalised range [0, 1].
    **kwargs
        The other arguments of :func:`asd_pocs_iterates`.

    Returns
    -------
    ndarray, shape (I, J, K), float32
        The normalised volume on the reference grid.
    """
    x = deque(asd_pocs_iterates(line_integrals, view_set, reference, **kwargs), maxlen=1)[0][1]
    vol = x.cpu().numpy().astype(np.float32)
    return np.clip(vol, 0.0, 1.0) if clip else vol
