"""Radiographs as SfM input: contrast enhancement for feature detection, feature masks, 8-bit PNGs for COLMAP.

Radiographs are low-contrast and dominated by the object's silhouette; SIFT finds repeatable points on them only
after a high-pass, a per-view intensity window and CLAHE, with the silhouette and the air masked out.

References
----------
Zuiderveld, K. (1994). Contrast limited adaptive histogram equalization. Graphics Gems IV, 474-485.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ctsplat.formats.viewset import write_png_stack
from ctsplat.utils import CtsplatError

__all__ = ["enhance_for_features", "feature_masks", "write_pngs"]


def enhance_for_features(images: np.ndarray, *, clip: float = 0.01, kernel_frac: float = 0.125,
                         p_low: float = 0.5, p_high: float = 99.5, highpass_frac: float = 0.0, lowpass_px: float = 0.0,
                         background_frac: float = 0.0) -> np.ndarray:
    """Contrast-enhance radiographs for SIFT: optional high-pass, per-view percentile window, CLAHE, 8-bit.

    Parameters
    ----------
    images : ndarray, shape (V, H, W) or (H, W), float
        Line integrals ``p`` (or any intensity), finite; higher = more attenuation (shown bright, like bone).
    clip : float
        CLAHE clip limit (``equalize_adapthist``'s ``clip_limit``, normalised to [0, 1]).
    kernel_frac : float
        CLAHE tile size as a fraction of ``max(H, W)`` (at least 8 px).
    p_low, p_high : float
        Percentiles (0-100) of the intensity window, over the object's pixels.
    highpass_frac : float
        High-pass Gaussian σ as a fraction of ``max(H, W)``; 0 disables the high-pass.
    lowpass_px : float
        Pre-blur Gaussian σ (px); 0 disables it.
    background_frac : float
        Pixels with ``p <= background_frac · max(p)`` are air; 0 treats every pixel as object.

    Returns
    -------
    ndarray, shape (V, H, W), uint8
        ``round(255 · CLAHE(clip((q - P_low(q)) / (P_high(q) - P_low(q)), 0, 1)))`` per view
        (``skimage.exposure.equalize_adapthist`` with ``kernel_size = kernel_frac · max(H, W)``), where
        ``q = p - G_σ * p`` with a Gaussian of ``σ = highpass_frac · max(H, W)`` px when ``highpass_frac > 0``
        (removes the smooth path-length component so small structures such as beads stand out), else ``q = p``;
        ``p`` is first blurred by a Gaussian of ``lowpass_px`` px when ``lowpass_px > 0`` (suppresses voxel
        staircase / moiré patterns that the high-pass would otherwise amplify into view-dependent features).
        Pixels with ``p <= background_frac · max(p)`` (rays through air, when ``background_frac > 0``) are set
        to 0 after the enhancement and excluded from the window: CLAHE would turn their flat noise into
        features fixed in image space, which pull every camera towards "not moving".

    Raises
    ------
    CtsplatError
        For images that are not (V, H, W) or (H, W), or hold non-finite values.
    """
    from scipy.ndimage import gaussian_filter
    from skimage.exposure import equalize_adapthist

    arr = np.asarray(images, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or not np.all(np.isfinite(arr)):
        raise CtsplatError("enhance_for_features: expected finite images of shape (V, H, W)")
    out = np.empty(arr.shape, np.uint8)
    ks = max(8, int(round(kernel_frac * max(arr.shape[1:]))))
    for i, im in enumerate(arr):
        fg = im > background_frac * im.max() if background_frac > 0 else np.ones(im.shape, bool)
        if lowpass_px > 0:
            im = gaussian_filter(im, lowpass_px, mode="nearest")
        if highpass_frac > 0:
            im = im - gaussian_filter(im, highpass_frac * max(arr.shape[1:]), mode="nearest")
        lo, hi = np.percentile(im[fg], [p_low, p_high]) if fg.any() else (0.0, 0.0)
        x = np.clip((im - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(im)
        if hi > lo:
            x = equalize_adapthist(x, kernel_size=ks, clip_limit=clip)
        out[i] = np.where(fg, np.round(np.clip(x, 0, 1) * 255), 0).astype(np.uint8)
    return out


def feature_masks(images: np.ndarray, background_frac: float, margin_px: float) -> np.ndarray:
    """Where SIFT features may be kept: the object's support eroded by ``margin_px`` pixels.

    The support of a view is ``p > background_frac · max(p)``. Its outer boundary (the silhouette) and the
    tangent rays just inside it give features that slide over the object's surface as the view turns; they
    are not projections of fixed 3D points and bias bundle adjustment, so they are masked out.

    Parameters
    ----------
    images : ndarray, shape (V, H, W) or (H, W)
        Line integrals ``p``.
    background_frac : float
        Support threshold as a fraction of each view's maximum.
    margin_px : float
        Erosion distance (px): pixels closer than this to the background (or the image border) are dropped.

    Returns
    -------
    ndarray, shape (V, H, W), uint8
        255 where features are kept, 0 elsewhere (COLMAP mask convention); all 255 when ``margin_px <= 0``.
    """
    from scipy.ndimage import distance_transform_edt

    arr = np.asarray(images, float)
    if arr.ndim == 2:
        arr = arr[None]
    out = np.full(arr.shape, 255, np.uint8)
    if margin_px <= 0:
        return out
    for i, im in enumerate(arr):
        fg = im > background_frac * im.max()
        dist = distance_transform_edt(np.pad(fg, 1))[1:-1, 1:-1]  # distance to the nearest background pixel
        out[i] = np.where(dist > margin_px, 255, 0).astype(np.uint8)
    return out


def write_pngs(images: np.ndarray, out_dir: str | Path, prefix: str = "view", ids: np.ndarray | None = None
               ) -> list[str]:
    """Write 8-bit images as ``{prefix}_{id:04d}.png`` into a fresh ``out_dir``.

    Parameters
    ----------
    images : ndarray, shape (V, H, W), uint8
        The images.
    out_dir : str or Path
        Output folder, replaced whole (written under a temporary name, then renamed).
    prefix : str
        File name prefix.
    ids : ndarray of int, shape (V,), optional
        Number in each file name; default ``0 .. V-1``.

    Returns
    -------
    list of str, length V
        The file names (COLMAP image names), in the images' order.
    """
    ids = np.arange(len(images)) if ids is None else np.asarray(ids, int)
    names = [f"{prefix}_{int(i):04d}.png" for i in ids]
    write_png_stack(np.asarray(images, np.uint8), out_dir, names)
    return names
