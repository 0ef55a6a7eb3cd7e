"""The volume read-out of a trained model: unsharp masking whose amount is chosen on the validation views.

A Gaussian model trained on noisy, sparse projections under a TV prior reads out smoother than the object: edges
are spread over a voxel or two and small bright structures lose contrast (the classical bias of TV-regularised
reconstruction). Unsharp masking, ``x + a (x - G_r * x)`` with ``G_r`` a Gaussian of standard deviation ``r``
voxels, restores part of that contrast; too much of it amplifies noise. The amount ``a`` is a free parameter of
the read-out, so it is chosen like every baseline parameter (:mod:`ctsplat.recon.select`): each candidate volume
is re-projected at the *validation* poses and the one with the best PSNR against the validation radiographs wins.
Choosing the amount reads neither the test views nor the reference volume. The step itself was not chosen that
way: unsharp masking, its 1-voxel radius and the alternatives set aside (denoising, shifts) were compared by 3D PSNR
against the head's reference on its 50-view model (docs/results.md), so results with sharpening on that cell are
in-sample for those choices. ``amounts`` must contain 0 for the unsharpened read-out to stay a candidate; a single
``[0]`` switches the step off.

References
----------
.. [1] Gonzalez, R. C. and Woods, R. E., *Digital Image Processing*, 4th ed., Pearson, 2018, sec. 3.6
   (unsharp masking and highboost filtering).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

__all__ = ["sharpen", "choose_sharpening", "check_sharpen_config"]


def sharpen(volume: np.ndarray, *, amount: float, radius_voxels: float = 1.0) -> np.ndarray:
    """Unsharp masking of a volume, clipped at 0 (attenuation is not negative).

    Parameters
    ----------
    volume : ndarray, shape (I, J, K)
        Normalised attenuation.
    amount : float
        ``a`` in ``x + a (x - G_r * x)``; 0 returns the volume (clipped at 0).
    radius_voxels : float
        ``r``, the standard deviation of the Gaussian blur, in voxels.

    Returns
    -------
    ndarray, shape (I, J, K), float32

    Examples
    --------
    >>> import numpy as np
    >>> x = np.zeros((9, 9, 9)); x[4, 4, 4] = 1.0
    >>> float(sharpen(x, amount=0.5)[4, 4, 4]) > 1.0
    True
    """
    from skimage.filters import unsharp_mask

    x = np.asarray(volume, np.float32)
    if amount == 0:
        return np.clip(x, 0.0, None)
    out = unsharp_mask(x, radius=float(radius_voxels), amount=float(amount), preserve_range=True, channel_axis=None)
    return np.clip(out, 0.0, None).astype(np.float32)


def check_sharpen_config(section: dict[str, Any]) -> tuple[list[float], float]:
    """The checked ``amounts`` and ``radius_voxels`` of a ``train.sharpen`` section, or a one-line error naming the
    key (their bounds are in :data:`ctsplat.training.config.TRAIN_BOUNDS`)."""
    from ctsplat.training.config import TRAIN_BOUNDS

    amounts, radius = section.get("amounts"), section.get("radius_voxels")
    TRAIN_BOUNDS["sharpen.amounts"].check("sharpen.amounts", amounts)
    TRAIN_BOUNDS["sharpen.radius_voxels"].check("sharpen.radius_voxels", radius)
    return [float(a) for a in amounts], float(radius)


def choose_sharpening(volume: np.ndarray, validator: Any, *, amounts: list[float], radius_voxels: float = 1.0,
                      clip: bool = False) -> tuple[np.ndarray, dict[str, Any]]:
    """The sharpened read-out whose re-projection scores best on the validation views.

    Parameters
    ----------
    volume : ndarray, shape (I, J, K)
        The model's read-out on the reference grid (normalised units).
    validator : ctsplat.recon.select.Validator
        The validation views (never the test views).
    amounts : list of float
        Candidate amounts (see :func:`sharpen`); ties go to the first.
    radius_voxels : float
        Blur radius of every candidate (voxels).
    clip : bool
        Clip every candidate to [0, 1] before scoring (the classical baselines' ``clip``).

    Returns
    -------
    volume : ndarray, shape (I, J, K), float32
        The chosen read-out.
    info : dict
        ``sharpen_amount`` (chosen), ``sharpen_radius_voxels``, ``sharpen_val_psnr`` (dB per candidate, in
        ``amounts`` order), ``sharpen_filter_seconds`` (filtering only, per candidate) and ``sharpen_seconds``
        (filtering and scoring, s).

    Examples
    --------
    >>> from ctsplat.recon.select import Validator
    >>> v = Validator.from_views(images, camera, Rs, ts, affine)  # doctest: +SKIP
    >>> vol, info = choose_sharpening(read_out, v, amounts=[0, 0.2, 0.4])  # doctest: +SKIP
    """
    from ctsplat.recon.select import choose

    t0 = time.perf_counter()
    # amount 0 is the volume as given (sharpen would also clip it at 0, which an unclipped reconstruction is not)
    choice = choose("sharpen", [{"amount": float(a)} for a in amounts],
                    lambda amount: volume if amount == 0 else sharpen(volume, amount=amount,
                                                                      radius_voxels=radius_voxels),
                    validator, clip=clip)
    info = {"sharpen_amount": choice.params["amount"], "sharpen_radius_voxels": float(radius_voxels),
            "sharpen_val_psnr": [t["val_psnr"] for t in choice.trials],
            "sharpen_filter_seconds": [t["seconds"] for t in choice.trials],
            "sharpen_seconds": time.perf_counter() - t0}
    return choice.volume, info
