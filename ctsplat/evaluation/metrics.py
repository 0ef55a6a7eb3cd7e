"""Image and volume quality metrics: PSNR, SSIM (2D and 3D), LPIPS (optional).

3D conventions (shared by baselines and Gaussian models): volumes are normalised to [0, 1] and compared
with data range 1; 3D PSNR is over the whole volume; 3D SSIM is the mean of the 2D SSIMs over all axial,
coronal and sagittal slices (the mean of the three per-axis means).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from skimage.metrics import structural_similarity

__all__ = ["psnr", "ssim2d", "psnr3d", "ssim3d", "lpips_distance", "lpips_status"]


def psnr(test: np.ndarray, reference: np.ndarray, data_range: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(R^2 / MSE)``.

    ``data_range`` defaults to ``reference.max() - reference.min()`` (for 2D projections, whose
    values are line integrals and have no fixed range). Returns ``inf`` for identical inputs.
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
    """SSIM of two 2D images (Gaussian-free 7x7 window, as ``skimage``); range as in :func:`psnr`."""
    reference = np.asarray(reference, dtype=np.float64)
    if data_range is None:
        data_range = float(reference.max() - reference.min()) or 1.0
    return float(structural_similarity(np.asarray(test, np.float64), reference, data_range=data_range))


def psnr3d(test: np.ndarray, reference: np.ndarray) -> float:
    """3D PSNR of normalised volumes (data range 1) over the whole volume."""
    return psnr(test, reference, data_range=1.0)


def ssim3d(test: np.ndarray, reference: np.ndarray) -> float:
    """Mean of 2D SSIM (data range 1) over all slices along each of the three axes, averaged over axes."""
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
    """``None`` when LPIPS can be computed, else the reason it cannot."""
    return _lpips_model()[1]


def lpips_distance(test: np.ndarray, reference: np.ndarray) -> tuple[float | None, str | None]:
    """LPIPS (AlexNet) of two grey images replicated to 3 channels.

    Both images are scaled together to [-1, 1] by the reference's range. Returns ``(value, None)``,
    or ``(None, reason)`` when the ``lpips`` package or its weights are not usable — never a made-up number.
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
