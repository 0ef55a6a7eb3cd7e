"""Image and volume quality metrics: PSNR, SSIM (2D and 3D), LPIPS (optional).

3D conventions (shared by baselines and Gaussian models): volumes are normalised to [0, 1] and compared
with data range 1; 3D PSNR is over the whole volume; 3D SSIM is the mean of the 2D SSIMs over all axial,
coronal and sagittal slices (the mean of the three per-axis means).

References
----------
Wang, Z., Bovik, A. C., Sheikh, H. R., Simoncelli, E. P. (2004). Image quality assessment: from error visibility to
structural similarity. IEEE Transactions on Image Processing 13(4), 600-612. (SSIM.)
Zhang, R., Isola, P., Efros, A. A., Shechtman, E., Wang, O. (2018). The unreasonable effectiveness of deep
features as a perceptual metric. CVPR. (LPIPS.)
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from skimage.metrics import structural_similarity

__all__ = ["psnr", "ssim2d", "psnr3d", "ssim3d", "lpips_distance", "lpips_status"]


def psnr(test: np.ndarray, reference: np.ndarray, data_range: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(R^2 / MSE)``.

    Parameters
    ----------
    test, reference : ndarray
        Images or volumes of one shape.
    data_range : float, optional
        ``R``; default ``reference.max() - reference.min()`` (1 for a constant reference), for 2D projections,
        whose values are line integrals and have no fixed range.

    Returns
    -------
    float
        PSNR in dB; ``inf`` for identical inputs.

    Raises
    ------
    ValueError
        When the shapes differ.

    Examples
    --------
    >>> psnr(np.full((4, 4), 0.1), np.zeros((4, 4)), data_range=1.0)
    20.0
    """
    test = np.asarray(test, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if test.shape != reference.shape:
        raise ValueError(f"shape mismatch: {test.shape} vs {reference.shape}")
    if data_range is None:
        data_range = float(reference.max() - reference.min()) or 1.0
    mse = float(np.mean((test - reference) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range**2 / mse))


def ssim2d(test: np.ndarray, reference: np.ndarray, data_range: float | None = None) -> float:
    """SSIM of two 2D images (``skimage.metrics.structural_similarity`` defaults: uniform 7x7 window).

    Parameters
    ----------
    test, reference : ndarray, shape (H, W)
        The images.
    data_range : float, optional
        Dynamic range; default as in :func:`psnr`.

    Returns
    -------
    float
        Mean SSIM, at most 1.
    """
    reference = np.asarray(reference, dtype=np.float64)
    if data_range is None:
        data_range = float(reference.max() - reference.min()) or 1.0
    return float(structural_similarity(np.asarray(test, np.float64), reference, data_range=data_range))


def psnr3d(test: np.ndarray, reference: np.ndarray) -> float:
    """3D PSNR of normalised volumes (data range 1) over the whole volume.

    Parameters
    ----------
    test, reference : ndarray, shape (I, J, K)
        Normalised volumes.

    Returns
    -------
    float
        PSNR in dB.
    """
    return psnr(test, reference, data_range=1.0)


def ssim3d(test: np.ndarray, reference: np.ndarray) -> float:
    """3D SSIM: the mean 2D SSIM (data range 1) over all slices along each axis, averaged over the three axes.

    Parameters
    ----------
    test, reference : ndarray, shape (I, J, K)
        Normalised volumes, every axis at least 7 voxels (the SSIM window).

    Returns
    -------
    float
        Mean SSIM, at most 1.

    Raises
    ------
    ValueError
        When the volumes are not 3D or their shapes differ.
    """
    test = np.asarray(test, np.float64)
    reference = np.asarray(reference, np.float64)
    if test.shape != reference.shape or test.ndim != 3:
        raise ValueError(f"need two 3D volumes of one shape, got {test.shape} and {reference.shape}")
    per_axis = []
    for axis in range(3):
        t = np.moveaxis(test, axis, 0)
        r = np.moveaxis(reference, axis, 0)
        per_axis.append(np.mean([structural_similarity(a, b, data_range=1.0) for a, b in zip(t, r, strict=True)]))
    return float(np.mean(per_axis))


@functools.cache
def _lpips_model() -> tuple[Any, str | None]:
    try:
        import lpips  # noqa: PLC0415  (optional; needs torchvision)
    except Exception as exc:  # ImportError, or torchvision's RuntimeError with a mismatched torch
        return None, f"lpips unavailable: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    try:
        model = lpips.LPIPS(net="alex", verbose=False)
    except Exception as exc:  # backbone weights missing offline
        return None, f"lpips backbone weights unavailable offline: {type(exc).__name__}: {exc}"
    model.eval()
    return model, None


def lpips_status() -> str | None:
    """Whether LPIPS can be computed here (the ``lpips`` package and its AlexNet weights load).

    Returns
    -------
    str or None
        ``None`` when it can, else the reason it cannot.
    """
    return _lpips_model()[1]


def lpips_distance(test: np.ndarray, reference: np.ndarray) -> tuple[float | None, str | None]:
    """LPIPS (AlexNet) of two grey images replicated to 3 channels.

    Both images are scaled together to [-1, 1] by the reference's range.

    Parameters
    ----------
    test, reference : ndarray, shape (H, W)
        The images.

    Returns
    -------
    value : float or None
        The LPIPS distance (0 for identical images), or None when the ``lpips`` package or its weights are not
        usable — never a made-up number.
    reason : str or None
        Why ``value`` is None; None otherwise.
    """
    model, reason = _lpips_model()
    if model is None:
        return None, reason
    import torch

    ref = np.asarray(reference, np.float32)
    lo, hi = float(ref.min()), float(ref.max())
    scale = (hi - lo) or 1.0

    def prep(img: np.ndarray) -> torch.Tensor:
        x = (np.asarray(img, np.float32) - lo) / scale * 2.0 - 1.0
        return torch.from_numpy(x)[None, None].repeat(1, 3, 1, 1)

    with torch.no_grad():
        return float(model(prep(test), prep(reference)).item()), None
