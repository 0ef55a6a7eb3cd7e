"""A flash on the camera: each Gaussian's colour scaled by its distance from the camera centre.

Photographs taken with a flash on the camera light a surface more the nearer the camera is; spherical-harmonic
colour, a function of the viewing direction only, cannot say that, and fits such a set with colours that are right
at one distance. The model here multiplies every Gaussian's colour by ``(r_ref / r)^p``: ``r`` its distance from
the camera centre, ``r_ref`` a fixed reference distance (:func:`reference_distance`: the training cameras' mean
distance from the scene's middle, so the colours are those seen from there) and one exponent ``p`` trained with the
model (``p = 0``: plain 3DGS colour; ``p = 2``: a point light's inverse square with no ambient light). It predicts
a held-out photo's brightness from its pose alone, with no parameter per photo.

The falloff grows without bound as ``r → 0``, so a faint floater just in front of a camera would be lit many
times over and wash the photo out. With a near bound ``r_min`` (:func:`nearest_point_distance`: the smallest
distance from a training camera to an SfM point, the nearest surface any training photo is known to see), ``r`` is
clamped below at ``r_min``: nothing is lit more than that surface.

Examples
--------
>>> import torch
>>> flash_falloff(torch.tensor([[0.0, 0.0, 2.0]]), torch.zeros(3), exponent=2.0, r_ref=1.0)
tensor([0.2500])
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

__all__ = ["flash_falloff", "nearest_point_distance", "reference_distance"]

#: Distances are clamped below at this fraction of ``r_ref`` (a Gaussian at the camera centre is never drawn).
_MIN_DISTANCE_FRACTION = 1e-3


def flash_falloff(means: torch.Tensor, centre: torch.Tensor, *, exponent: torch.Tensor | float,
                  r_ref: float, r_min: float | None = None) -> torch.Tensor:
    """The factor ``(r_ref / r)^p`` on each Gaussian's colour for a flash at ``centre``.

    Parameters
    ----------
    means : Tensor (N, 3)
        Gaussian centres, in the scene's (SfM) units.
    centre : Tensor (3,)
        The camera centre, ``-Rᵀ t``, same units.
    exponent : Tensor () or float
        ``p``; differentiable when a tensor that requires grad.
    r_ref : float
        The distance at which the factor is 1, same units (> 0).
    r_min : float, optional
        Distances below this are raised to it (the near bound; same units). None: no bound.

    Returns
    -------
    Tensor (N,)
        Positive factors, at most ``(r_ref / r_min)^p``; differentiable in ``means`` and ``centre`` (where
        ``r > r_min``) and in ``exponent``.
    """
    floor = max(_MIN_DISTANCE_FRACTION * r_ref, float(r_min) if r_min is not None else 0.0)
    r = torch.linalg.norm(means - centre.to(means), dim=-1).clamp_min(floor)
    return (r_ref / r).pow(torch.as_tensor(exponent, dtype=means.dtype, device=means.device))


def reference_distance(camera_centres: Any, points: Any) -> float:
    """The cameras' mean distance from the median of ``points``: the ``r_ref`` of :func:`flash_falloff`.

    Parameters
    ----------
    camera_centres : array (V, 3)
    points : array (P, 3)
        The SfM points (the scene's middle is their per-axis median, robust to stray points).

    Returns
    -------
    float
        In the scene's units.
    """
    mid = np.median(np.asarray(points, float), axis=0)
    return float(np.mean(np.linalg.norm(np.asarray(camera_centres, float) - mid, axis=1)))


def nearest_point_distance(camera_centres: Any, points: Any) -> float:
    """The smallest distance from any of ``camera_centres`` to any of ``points``: the ``r_min`` of
    :func:`flash_falloff`.

    Parameters
    ----------
    camera_centres : array (V, 3)
        The training cameras' centres.
    points : array (P, 3)
        The SfM points, same units.

    Returns
    -------
    float
        In the scene's units.
    """
    # a k-d tree: the full (V, P) distance matrix would not fit for large SfM models
    dist, _ = cKDTree(np.asarray(points, float)).query(np.asarray(camera_centres, float))
    return float(np.min(dist))
