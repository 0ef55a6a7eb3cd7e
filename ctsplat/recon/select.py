"""Free parameters of the classical reconstructions, chosen on the validation views (re-projection error).

Every candidate reconstruction (a filter, a relaxation, an iteration count, a TV weight, an MBIR sharpness and
SNR) is rendered with :func:`ctsplat.projector.line_integrals` at the poses of the view set's *validation* views
and compared with their radiographs: the score is the PSNR of the line integrals (normalised units; data range the
range of the validation radiographs), :class:`Validator`. The candidate with the best score wins. Neither the test
views nor the reference volume are read here, so a method's test metrics, computed after the choice, are an honest
held-out measurement. Iterative methods are scored after every iteration, so the iteration count is chosen the
same way (early stopping on validation).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ctsplat.evaluation.metrics import psnr
from ctsplat.formats.viewset import ViewSet
from ctsplat.recon.operators import check_stack, reference_grid
from ctsplat.utils import CtsplatError

__all__ = ["Validator", "Choice", "choose", "choose_iterative"]


class Validator:
    """Scores a normalised volume by how well it re-projects onto the validation views.

    Parameters
    ----------
    line_integrals : ndarray, shape (V, H, W)
        The validation views' line integrals of μ (1/mm · mm), page order of ``view_set``.
    view_set : ViewSet
        The validation views (camera and poses).
    reference : Volume-like
        The reconstruction grid: ``affine`` (4, 4), ``shape`` and ``mu_scale_per_mm`` (its values are not read).
    mu_scale_per_mm : float, optional
        Default ``reference.mu_scale_per_mm``.
    device : str or torch.device, optional
        Where to project (default CPU).
    step_voxels : float
        Projector sampling step (the radiographs' own, 0.5, by default).

    Raises
    ------
    CtsplatError
        For an empty validation set or line integrals that do not match it.
    """

    def __init__(self, line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *,
                 mu_scale_per_mm: float | None = None, device: str | torch.device | None = None,
                 step_voxels: float = 0.5) -> None:
        if len(view_set) == 0:
            raise CtsplatError("the view set has no validation views to choose baseline parameters on; render it "
                               "with a non-zero val fraction (radiographs.<geometry>.split.val)")
        affine, _, scale = reference_grid(reference)
        scale = scale if mu_scale_per_mm is None else float(mu_scale_per_mm)
        self._set(check_stack(line_integrals, view_set).astype(np.float64) / scale, scale, view_set.camera,
                  view_set.Rs(), view_set.ts(), affine, device, step_voxels)

    def _set(self, target: np.ndarray, scale: float, camera: Any, Rs: np.ndarray, ts: np.ndarray, affine: np.ndarray,
             device: str | torch.device | None, step_voxels: float) -> None:
        self.scale, self.target = scale, target
        self.camera, self.Rs, self.ts = camera, np.asarray(Rs, float), np.asarray(ts, float)
        self.affine = np.asarray(affine, float)
        self.device = torch.device(device) if device else torch.device("cpu")
        self.step_voxels = float(step_voxels)
        self.data_range = float(target.max() - target.min()) or 1.0

    @classmethod
    def from_views(cls, line_integrals: np.ndarray, camera: Any, Rs: np.ndarray, ts: np.ndarray, affine: np.ndarray,
                   *, device: str | torch.device | None = None, step_voxels: float = 0.5) -> Validator:
        """A validator of views given as arrays (a :class:`ctsplat.scene.ViewData`'s ``images``, ``camera``,
        ``Rs``, ``ts``), their line integrals already in normalised units.

        Parameters
        ----------
        line_integrals : ndarray, shape (V, H, W)
            Line integrals of the normalised volume (mm).
        camera : ParallelCamera or ConeCamera
        Rs : ndarray, shape (V, 3, 3)
        ts : ndarray, shape (V, 3)
            World-to-camera poses (mm).
        affine : ndarray, shape (4, 4)
            Voxel index -> world mm of the reconstruction grid.
        device, step_voxels
            As for the constructor.
        """
        p = np.asarray(line_integrals, np.float64)
        if p.ndim != 3 or p.shape[0] == 0 or p.shape != (len(Rs), camera.height, camera.width):
            raise CtsplatError(f"validation line integrals of shape {p.shape} do not match {len(Rs)} views of "
                               f"{camera.height}x{camera.width} pixels")
        self = cls.__new__(cls)
        self._set(p, 1.0, camera, Rs, ts, affine, device, step_voxels)
        return self

    def render(self, volume: np.ndarray | torch.Tensor) -> np.ndarray:
        """Line integrals (normalised units) of ``volume`` at the validation poses, (V, H, W) float64."""
        from ctsplat.projector import line_integrals

        with torch.no_grad():
            x = torch.as_tensor(volume, dtype=torch.float32, device=self.device).detach()
            p = line_integrals(x, self.affine, self.camera, self.Rs, self.ts, step_voxels=self.step_voxels,
                               device=self.device)
        return p.cpu().numpy().astype(np.float64)

    def score(self, volume: np.ndarray | torch.Tensor) -> float:
        """Validation PSNR (dB) of the re-projected line integrals; higher is better."""
        return psnr(self.render(volume), self.target, self.data_range)


@dataclass
class Choice:
    """The winning candidate of one method and every candidate's validation score."""

    method: str
    params: dict[str, Any]
    val_psnr: float
    volume: np.ndarray
    seconds: float  # reconstruction time of the chosen candidate (validation scoring excluded)
    selection_seconds: float = 0.0  # every candidate's reconstruction (scoring excluded)
    trials: list[dict[str, Any]] = field(default_factory=list)
    #: an iterative method chose the last iteration its budget allowed, still improving on validation: the cap,
    #: not the validation views, stopped it
    at_cap: bool = False


def _finish(x: np.ndarray | torch.Tensor, clip: bool) -> np.ndarray:
    vol = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    vol = vol.astype(np.float32)
    return np.clip(vol, 0.0, 1.0) if clip else vol


def rank(score: float) -> float:
    """A validation score for comparisons: NaN (a diverged candidate's reconstruction) ranks below every number,
    since NaN never loses a ``>`` comparison and a NaN first candidate would otherwise win.

    Examples
    --------
    >>> max([float("nan"), 31.2], key=rank)
    31.2
    """
    return -math.inf if math.isnan(score) else score


def choose(method: str, candidates: Iterable[dict[str, Any]], reconstruct: Callable[..., np.ndarray],
           validator: Validator, *, clip: bool = True) -> Choice:
    """The candidate parameters whose reconstruction scores best on validation (direct methods).

    Parameters
    ----------
    method : str
        Name recorded in the result.
    candidates : iterable of dict
        Keyword arguments of ``reconstruct``, one dict per candidate.
    reconstruct : callable
        ``reconstruct(**params) -> ndarray (I, J, K)`` (normalised units).
    validator : Validator
        Scores each reconstruction on the validation views.
    clip : bool
        Clip to [0, 1] before scoring (the reported volume is the scored one).

    Returns
    -------
    Choice
        The best candidate (first one on ties) with every trial's parameters, score and seconds.
    """
    best: Choice | None = None
    trials: list[dict[str, Any]] = []
    total = 0.0
    for params in candidates:
        t0 = time.perf_counter()
        vol = _finish(reconstruct(**params), clip)
        sec = time.perf_counter() - t0
        total += sec
        score = validator.score(vol)
        trials.append({"method": method, **params, "val_psnr": score, "seconds": sec})
        if best is None or rank(score) > rank(best.val_psnr):
            best = Choice(method, dict(params), score, vol, sec)
    if best is None:
        raise CtsplatError(f"{method}: no candidate parameters to choose from")
    best.selection_seconds, best.trials = total, trials
    return best


def choose_iterative(method: str, candidates: Iterable[dict[str, Any]],
                     iterates: Callable[..., Iterator[tuple[int, Any]]], validator: Validator, *,
                     clip: bool = True, patience: int | None = None) -> Choice:
    """The candidate and iteration count whose iterate scores best on validation (iterative methods).

    Parameters
    ----------
    method : str
        Name recorded in the result.
    candidates : iterable of dict
        Keyword arguments of ``iterates``, one dict per candidate (e.g. relaxation, TV weight).
    iterates : callable
        ``iterates(**params)`` yields ``(iteration, volume)`` after each iteration.
    validator : Validator
        Scores every iterate on the validation views.
    clip : bool
        Clip to [0, 1] before scoring.
    patience : int, optional
        Stop a candidate after this many iterations without a better score (None: run them all).

    Returns
    -------
    Choice
        The best (candidate, iteration); ``params`` includes ``iterations``. ``trials`` has one row per
        candidate and iteration. ``at_cap``: the chosen iteration is the last its candidate ran, which patience
        did not stop (the iteration budget did).
    """
    best: Choice | None = None
    trials: list[dict[str, Any]] = []
    total = 0.0
    capped_at: dict[int, int] = {}  # candidate -> its last iteration, for those the budget stopped
    best_candidate = -1
    for k, params in enumerate(candidates):
        t0 = time.perf_counter()
        cand_best, since, last = -np.inf, 0, None
        stopped = False
        for it, x in iterates(**params):
            elapsed = time.perf_counter() - t0
            t1 = time.perf_counter()
            vol = _finish(x, clip)
            score = validator.score(vol)
            trials.append({"method": method, **params, "iterations": it, "val_psnr": score, "seconds": elapsed})
            if best is None or rank(score) > rank(best.val_psnr):
                best = Choice(method, {**params, "iterations": it}, score, vol, elapsed)
                best_candidate = k
            since = 0 if rank(score) > cand_best else since + 1
            cand_best = max(cand_best, rank(score))
            last = it
            t0 += time.perf_counter() - t1  # keep the scoring out of the reconstruction time
            if patience is not None and since >= patience:
                stopped = True
                break
        if not stopped and last is not None:
            capped_at[k] = last
        total += time.perf_counter() - t0
    if best is None:
        raise CtsplatError(f"{method}: no candidate parameters to choose from")
    best.selection_seconds, best.trials = total, trials
    best.at_cap = capped_at.get(best_candidate) == best.params["iterations"]
    return best
