"""Image and volume quality metrics: PSNR, SSIM (2D and 3D), LPIPS (optional).

Two 3D conventions, both on volumes normalised to [0, 1] and compared with data range 1:

- the project's own (:func:`psnr3d`, :func:`ssim3d`; ``psnr3d``/``ssim3d`` in every output): PSNR over the whole
  volume; SSIM the mean of skimage's 2D SSIM (uniform 7x7 window, borders cropped) over *all* axial, coronal and
  sagittal slices, averaged over the three axes;
- R²-Gaussian's ``metric_vol`` (:func:`psnr3d_r2`, :func:`ssim3d_r2`; ``psnr3d_r2``/``ssim3d_r2``), the field's
  sparse-view CT protocol: the same PSNR; SSIM per slice with an 11x11 Gaussian window (σ = 1.5, weights
  normalised), zero padding and the map averaged over the whole slice (C1 = 0.01², C2 = 0.03², population
  variances), only over slices whose reference has a positive maximum, averaged per axis and then over the
  three axes. A reference outside [0, 1] is min-max normalised first, with the same affine map applied to the test
  volume. The formulas are theirs; the volumes' scale is ctsplat's: R²-Gaussian's data generator clips to
  -1000..2000 HU and min-max scales, so its references reach 1, while ctsplat's normalised volumes map
  -1000..``hu_max`` HU (3000 by default) to [0, 1], so a head's densest bone stays below 1. Numbers of the two
  pipelines on one CT then differ by about 20 log10(1 / max) in PSNR, ``max`` the reference's largest value here;
  comparisons inside ctsplat are unaffected.

References
----------
Wang, Z., Bovik, A. C., Sheikh, H. R., Simoncelli, E. P. (2004). Image quality assessment: from error visibility to
structural similarity. IEEE Transactions on Image Processing 13(4), 600-612. (SSIM.)
Zhang, R., Isola, P., Efros, A. A., Shechtman, E., Wang, O. (2018). The unreasonable effectiveness of deep
features as a perceptual metric. CVPR. (LPIPS.)
Zha, R., Lin, T. J., Cai, Y., Cao, J., Zhang, Y., Li, H. (2024). R²-Gaussian: rectifying radiative Gaussian
splatting for tomographic reconstruction. NeurIPS. Code: github.com/Ruyi-Zha/r2_gaussian,
``r2_gaussian/utils/image_utils.py`` (``metric_vol``) and ``r2_gaussian/utils/loss_utils.py`` (``ssim``).
(:func:`psnr3d_r2`, :func:`ssim3d_r2`.)
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from scipy import ndimage
from skimage.metrics import structural_similarity

from ctsplat.utils import CtsplatError

__all__ = ["psnr", "ssim_window", "ssim2d", "psnr3d", "ssim3d", "psnr3d_r2", "ssim3d_r2", "ssim_map_r2", "normalise_r2",
           "lpips_distance", "lpips_status"]


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


def ssim_window(shape: tuple[int, ...]) -> int:
    """The uniform SSIM window for images of ``shape``: skimage's 7, or the largest odd size that fits a side
    shorter than 7 px.

    Parameters
    ----------
    shape : tuple of int
        The image's shape.

    Returns
    -------
    int
        An odd window size, 3 .. 7.

    Raises
    ------
    CtsplatError
        When a side is shorter than 3 px (no SSIM window fits).

    Examples
    --------
    >>> ssim_window((64, 5))
    5
    """
    side = min(int(s) for s in shape)
    if side < 3:
        raise CtsplatError(f"SSIM needs images at least 3 px on a side, got {tuple(int(s) for s in shape)}; use a "
                           "larger detector or volume")
    return min(7, side if side % 2 else side - 1)


def ssim2d(test: np.ndarray, reference: np.ndarray, data_range: float | None = None) -> float:
    """SSIM of two 2D images (``skimage.metrics.structural_similarity`` defaults: uniform 7x7 window, smaller for an
    image with a side under 7 px, :func:`ssim_window`).

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
    return float(structural_similarity(np.asarray(test, np.float64), reference, data_range=data_range,
                                       win_size=ssim_window(reference.shape)))


def psnr3d(test: np.ndarray, reference: np.ndarray) -> float:
    """3D PSNR of normalised volumes (data range 1) over the whole volume (the project's own convention).

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
    """3D SSIM (the project's own): the mean 2D SSIM (data range 1) over all slices along each axis, averaged over
    the three axes; skimage's uniform 7x7 window (smaller along an axis under 7 voxels, :func:`ssim_window`), empty
    slices included. See :func:`ssim3d_r2` for R²-Gaussian's.

    Parameters
    ----------
    test, reference : ndarray, shape (I, J, K)
        Normalised volumes, every axis at least 3 voxels.

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
        win = ssim_window(r.shape[1:])
        per_axis.append(np.mean([structural_similarity(a, b, data_range=1.0, win_size=win)
                                 for a, b in zip(t, r, strict=True)]))
    return float(np.mean(per_axis))


#: R²-Gaussian's SSIM window: 11 taps of a Gaussian with σ = 1.5, normalised to sum 1 (``loss_utils.gaussian``).
R2_SSIM_WINDOW = 11
R2_SSIM_SIGMA = 1.5


def _r2_window() -> np.ndarray:
    x = np.arange(R2_SSIM_WINDOW, dtype=np.float64) - R2_SSIM_WINDOW // 2
    g = np.exp(-(x**2) / (2.0 * R2_SSIM_SIGMA**2))
    return g / g.sum()


def normalise_r2(test: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both volumes on R²-Gaussian's [0, 1] scale: unchanged when the reference lies in [0, 1], else min-max.

    Parameters
    ----------
    test, reference : ndarray
        Volumes of one shape.

    Returns
    -------
    test, reference : ndarray, float64
        The reference in [0, 1]; the test volume under the same affine map (not clipped).

    Raises
    ------
    ValueError
        When the shapes differ or the volumes are not finite.
    """
    test = np.asarray(test, np.float64)
    reference = np.asarray(reference, np.float64)
    if test.shape != reference.shape:
        raise ValueError(f"shape mismatch: {test.shape} vs {reference.shape}")
    if not (np.isfinite(test).all() and np.isfinite(reference).all()):
        raise ValueError("volumes must be finite for 3D metrics")
    lo, hi = float(reference.min()), float(reference.max())
    if lo >= 0.0 and hi <= 1.0:
        return test, reference
    span = (hi - lo) or 1.0
    return (test - lo) / span, (reference - lo) / span


def psnr3d_r2(test: np.ndarray, reference: np.ndarray) -> float:
    """3D PSNR as R²-Gaussian's ``metric_vol(..., "psnr")``: ``10 log10(1 / MSE)`` over the whole volume.

    Parameters
    ----------
    test, reference : ndarray, shape (I, J, K)
        Reconstruction and reference (see :func:`normalise_r2`).

    Returns
    -------
    float
        PSNR in dB (data range 1); ``inf`` for identical volumes.

    Examples
    --------
    >>> psnr3d_r2(np.full((4, 4, 4), 0.1), np.zeros((4, 4, 4)))
    20.0
    """
    test, reference = normalise_r2(test, reference)
    return psnr(test, reference, data_range=1.0)


def ssim_map_r2(test: np.ndarray, reference: np.ndarray, axis: int) -> np.ndarray:
    """Per-pixel SSIM of every slice along ``axis``, as R²-Gaussian's ``ssim`` computes it for one slice.

    Local means, variances and covariance come from correlating each slice with the 11x11 Gaussian window
    (σ = 1.5) with zero padding (``conv2d(padding=5)``); ``C1 = 0.01²``, ``C2 = 0.03²`` (data range 1).

    Parameters
    ----------
    test, reference : ndarray, shape (I, J, K)
        Volumes on the [0, 1] scale.
    axis : int
        Slicing axis (0, 1 or 2); the other two are filtered.

    Returns
    -------
    ndarray, shape (I, J, K), float64
        The SSIM map (slice ``n`` along ``axis`` is that slice's map).
    """
    w = _r2_window()
    x = np.asarray(test, np.float64)
    y = np.asarray(reference, np.float64)

    def blur(v: np.ndarray) -> np.ndarray:
        for a in range(3):
            if a != axis:
                v = ndimage.correlate1d(v, w, axis=a, mode="constant", cval=0.0)
        return v

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))


def ssim3d_r2(test: np.ndarray, reference: np.ndarray) -> float:
    """3D SSIM as R²-Gaussian's ``metric_vol(..., "ssim")``.

    For each axis, the mean over the slices whose *reference* has a positive maximum of the slice's mean SSIM
    (:func:`ssim_map_r2`); the result is the mean of the three per-axis values. Slices whose reference is empty
    (all values <= 0) are skipped, so empty margins neither help nor hurt.

    Parameters
    ----------
    test, reference : ndarray, shape (I, J, K)
        Reconstruction and reference (see :func:`normalise_r2`).

    Returns
    -------
    float
        Mean SSIM, at most 1; ``nan`` when the reference is empty (no slice counts).

    Raises
    ------
    ValueError
        When the volumes are not 3D or their shapes differ.
    """
    test, reference = normalise_r2(test, reference)
    if test.ndim != 3:
        raise ValueError(f"need two 3D volumes of one shape, got {test.shape} and {reference.shape}")
    per_axis = []
    for axis in range(3):
        other = tuple(a for a in range(3) if a != axis)
        keep = reference.max(axis=other) > 0
        if not keep.any():
            return float("nan")
        per_slice = ssim_map_r2(test, reference, axis).mean(axis=other)
        per_axis.append(float(per_slice[keep].mean()))
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
    """LPIPS (AlexNet) of two grey images replicated to 3 channels, or of two RGB images.

    Grey images are scaled together to [-1, 1] by the reference's range; RGB images are taken as lying in [0, 1]
    (photographs) and mapped to [-1, 1], as LPIPS expects.

    Parameters
    ----------
    test, reference : ndarray, shape (H, W) or (H, W, 3)
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
    rgb = ref.ndim == 3 and ref.shape[-1] == 3
    lo, hi = (0.0, 1.0) if rgb else (float(ref.min()), float(ref.max()))
    scale = (hi - lo) or 1.0

    def prep(img: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy((np.asarray(img, np.float32) - lo) / scale * 2.0 - 1.0)
        return x.permute(2, 0, 1)[None] if rgb else x[None, None].repeat(1, 3, 1, 1)

    with torch.no_grad():
        return float(model(prep(test), prep(reference)).item()), None
