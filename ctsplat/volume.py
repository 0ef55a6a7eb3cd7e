"""CT ingestion and preprocessing: a scan on disk -> a preprocessed volume file.

Ingestion (:func:`ingest`) = read (:mod:`ctsplat.formats.sources`: DICOM / NIfTI / TIFF -> geometry-exact
slice stack, LPS -> RAS once) -> refuse (or fill) NaN / Inf voxels -> resample in world coordinates onto a
regular (isotropic) grid (:func:`resample_stack`) -> optional body mask -> intensity mapping (HU -> μ, or a
WL/WW window) -> normalise to [0, 1] -> optional denoising -> write the volume file
(:mod:`ctsplat.formats.volume`: NIfTI-1 + provenance JSON) atomically. The world frame is RAS+, mm (see
``docs/conventions.md``).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np
import scipy.sparse as sparse
from threadpoolctl import threadpool_limits

from ctsplat.formats.volume import Volume, check_sidecar_target, compute_volume_id, json_path_for, save_volume
from ctsplat.utils import CtsplatError, code_version, merge_config, read_json_object

__all__ = [
    "PREPROCESSING_DEFAULTS",
    "WINDOW_PRESETS",
    "check_preprocessing",
    "preprocessing_in_effect",
    "ingest",
    "resample_stack",
    "hu_to_attenuation",
    "apply_window",
    "body_mask",
    "denoise",
    "NONFINITE_RULES",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------------
# Preprocessing configuration
# --------------------------------------------------------------------------------------------------

#: WL/WW window presets (HU): level, width.
WINDOW_PRESETS: dict[str, tuple[float, float]] = {
    "brain": (40.0, 80.0),
    "soft_tissue": (40.0, 400.0),
    "bone": (400.0, 1800.0),
    "lung": (-600.0, 1500.0),
}

#: Defaults of the ``preprocessing`` config section (JSON-serialisable).
#:
#: - ``voxel_size_mm``: isotropic voxel edge (mm); takes precedence over ``grid``.
#: - ``grid``: target grid, ``n`` (-> n^3 isotropic voxels covering the scan's largest extent, the
#:   other axes padded with air) or ``[I, J, K]`` in the output (RAS-closest) axis order; with both
#:   ``voxel_size_mm`` and ``grid`` null the scan keeps its in-plane spacing and the median slice gap.
#: - ``intensity``: ``"attenuation"`` (μ = μ_water (1 + HU/1000), clipped to [0, μ(hu_max)], divided by
#:   μ(hu_max) -> [0, 1]), ``"window"`` (WL/WW -> [0, 1]), ``"mu"`` (μ in 1/mm, not normalised) or
#:   ``"hu"`` (raw HU; not usable by the projector).
#: - ``mu_water_per_mm``: μ of water (1/mm), ≈ 0.019 at 70 keV.
#: - ``hu_max``: HU mapped to 1.0 by ``"attenuation"`` (denser values clip).
#: - ``window``: preset name (see ``WINDOW_PRESETS``) or ``[level, width]`` for ``"window"``.
#: - ``denoise``: null, ``"tv"`` (3D Chambolle TV, weight ``denoise_weight``) or ``"bilateral"``
#:   (per axial slice, ``sigma_color = denoise_weight``); applied to the mapped values, with the weight in units
#:   of the mapping's full scale (:func:`intensity_full_scale`), so it smooths alike whatever the intensity.
#: - ``mask``: null, ``"otsu"`` (largest Otsu foreground component, holes filled) or ``"convex_hull"``
#:   (that, then the per-slice convex hull); everything outside is set to air (HU -1000).
PREPROCESSING_DEFAULTS: dict[str, Any] = {
    "voxel_size_mm": None,
    "grid": 128,
    "intensity": "attenuation",
    "mu_water_per_mm": 0.019,
    "hu_max": 3000.0,
    "window": "brain",
    "denoise": None,
    "denoise_weight": 0.02,
    "mask": None,
}

_INTENSITY_MODES = ("attenuation", "window", "mu", "hu")

#: What ingest does with NaN / ±Inf voxels of the source: ``error`` (default; names how many and
#: where) or ``fill_min`` (replace them by the smallest finite value, air for CT; recorded in the
#: provenance as the ``nonfinite`` step).
NONFINITE_RULES = ("error", "fill_min")

#: ``created_by`` of an ingested volume's sidecar: what :func:`ingest` may replace.
INGEST_MARKER = "ctsplat.volume.ingest"


def _check_ingest_target(out_path: Path) -> None:
    """Refuse an existing output file that is not an earlier ingest output (its sidecar names no ingest): a
    volume of another step (an evaluation's read-out, a phantom) or a NIfTI of someone else's would be replaced."""
    if out_path.is_dir() or not (out_path.exists() or out_path.is_symlink()):  # a folder: the write says so
        return
    sidecar = json_path_for(out_path)
    try:
        ours = json.loads(sidecar.read_text()).get("created_by") == INGEST_MARKER
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        ours = False
    if not ours:
        raise CtsplatError(f"{out_path} exists and is not an earlier ingest output (no {sidecar.name} of an ingest "
                           "beside it), and ingesting would replace it; choose another output name or remove it")

def check_preprocessing(cfg: Mapping[str, Any]) -> None:
    """Check a ``preprocessing`` section (defaults filled) beyond its schema: names, ranges, the window.

    Parameters
    ----------
    cfg : mapping
        The section, every key of :data:`PREPROCESSING_DEFAULTS` present.

    Raises
    ------
    CtsplatError
        Naming the first bad key, e.g. an unknown window preset.
    """
    if cfg["intensity"] not in _INTENSITY_MODES:
        allowed = ", ".join(_INTENSITY_MODES)
        raise CtsplatError(f"preprocessing.intensity {cfg['intensity']!r} unknown; allowed: {allowed}")
    vs = cfg["voxel_size_mm"]
    if vs is not None and (not isinstance(vs, int | float) or vs <= 0):
        raise CtsplatError(f"preprocessing.voxel_size_mm must be a positive number of mm, got {vs!r}")
    g = cfg["grid"]
    if g is not None:
        ok = (isinstance(g, int) and g >= 2) or (
            isinstance(g, list | tuple) and len(g) == 3 and all(isinstance(x, int) and x >= 2 for x in g)
        )
        if not ok:
            raise CtsplatError(f"preprocessing.grid must be an integer >= 2 or a list of 3 such integers, got {g!r}")
    if cfg["intensity"] == "window":
        _window_params(cfg["window"])
    if cfg["denoise"] not in (None, "tv", "bilateral"):
        raise CtsplatError(f"preprocessing.denoise {cfg['denoise']!r} unknown; allowed: null, tv, bilateral")
    if cfg["mask"] not in (None, "otsu", "convex_hull"):
        raise CtsplatError(f"preprocessing.mask {cfg['mask']!r} unknown; allowed: null, otsu, convex_hull")
    if not cfg["mu_water_per_mm"] > 0 or not cfg["hu_max"] > -1000:
        raise CtsplatError("preprocessing.mu_water_per_mm must be > 0 and hu_max > -1000")


def preprocessing_in_effect(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """A ``preprocessing`` section with every setting that has no effect reset to its default.

    ``denoise_weight`` acts only with a ``denoise`` method, ``window`` only with ``intensity: window``,
    ``mu_water_per_mm`` with every intensity but ``hu``, ``hu_max`` only with ``attenuation`` and ``mu``, and
    ``grid`` only without ``voxel_size_mm``. Ingest records the section in this form, and the workflow compares it
    in this form, so changing a setting that does nothing neither reruns ingest (and everything after it) nor
    changes the record.

    Parameters
    ----------
    cfg : mapping
        The section; keys it lacks take :data:`PREPROCESSING_DEFAULTS`.

    Returns
    -------
    dict
        Every key of :data:`PREPROCESSING_DEFAULTS`; the inert ones at their defaults.

    Examples
    --------
    >>> preprocessing_in_effect({"denoise": None, "denoise_weight": 0.5})["denoise_weight"]
    0.02
    >>> preprocessing_in_effect({"denoise": "tv", "denoise_weight": 0.5})["denoise_weight"]
    0.5
    """
    out = {**PREPROCESSING_DEFAULTS, **cfg}
    inert = []
    if out["denoise"] is None:
        inert.append("denoise_weight")
    if out["intensity"] != "window":
        inert.append("window")
    if out["intensity"] == "hu":
        inert.append("mu_water_per_mm")
    if out["intensity"] in ("window", "hu"):
        inert.append("hu_max")
    if out["voxel_size_mm"] is not None:
        inert.append("grid")
    for key in inert:
        out[key] = PREPROCESSING_DEFAULTS[key]
    return out


def _window_params(window: str | Sequence[float]) -> tuple[float, float]:
    if isinstance(window, str):
        if window not in WINDOW_PRESETS:
            allowed = ", ".join(WINDOW_PRESETS)
            raise CtsplatError(f"unknown window preset {window!r}; allowed: {allowed} or [level, width]")
        return WINDOW_PRESETS[window]
    if isinstance(window, list | tuple) and len(window) == 2 and float(window[1]) > 0:
        level, width = float(window[0]), float(window[1])
        if level + width / 2 <= -1000.0:  # the top's attenuation scales the volume to 1/mm: it must be > 0
            raise CtsplatError(f"window [{level:g}, {width:g}] ends at {level + width / 2:g} HU, at or below air "
                               "(-1000 HU), where attenuation is 0; raise its level or width so that its top lies "
                               "above -1000 HU")
        return level, width
    raise CtsplatError(f"window must be a preset name or [level, width] with width > 0, got {window!r}")


# --------------------------------------------------------------------------------------------------
# Resampling in world coordinates
# --------------------------------------------------------------------------------------------------


def _interp_matrix(src: np.ndarray, dst: np.ndarray, sigma: float, lo: float, hi: float) -> sparse.csr_matrix:
    """Sparse (M, N) matrix resampling samples at ascending positions ``src`` (N,) to ``dst`` (M,).

    ``W = L @ G``: ``G`` is a Gaussian anti-aliasing filter over the source positions (std ``sigma``
    in the same units, rows normalised; identity when ``sigma == 0``) and ``L`` piecewise-linear
    interpolation, exact for non-uniform ``src``. Positions in ``[lo, src[0]]`` / ``[src[-1], hi]``
    take the edge value; rows of positions outside ``[lo, hi]`` are zero (filled by the caller).
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    n, m = len(src), len(dst)
    eps = 1e-6 * max(1.0, float(np.abs(src).max()))
    inside = (dst >= lo - eps) & (dst <= hi + eps)
    x = np.clip(dst, src[0], src[-1])
    idx = np.clip(np.searchsorted(src, x, side="right") - 1, 0, n - 2)
    w = (x - src[idx]) / (src[idx + 1] - src[idx])
    w = np.clip(w, 0.0, 1.0)
    rows = np.flatnonzero(inside)
    lmat = sparse.csr_matrix(
        (
            np.concatenate([1.0 - w[rows], w[rows]]),
            (np.concatenate([rows, rows]), np.concatenate([idx[rows], idx[rows] + 1])),
        ),
        shape=(m, n),
    )
    if sigma > 0:
        d = src[:, None] - src[None, :]
        g = np.exp(-0.5 * (d / sigma) ** 2)
        g[np.abs(d) > 4 * sigma] = 0.0
        g /= g.sum(axis=1, keepdims=True)
        lmat = lmat @ sparse.csr_matrix(g)
    return sparse.csr_matrix(lmat, dtype=np.float32)


def _is_identity(w: sparse.csr_matrix) -> bool:
    """True when a resampling matrix is exactly the identity (output samples = source samples)."""
    if w.shape[0] != w.shape[1] or w.nnz < w.shape[0]:
        return False
    diag = w.diagonal()
    return bool(np.all(diag == 1.0) and abs(w).sum() == w.shape[0])


def _grid_axes(
    lo: np.ndarray, hi: np.ndarray, first_centre: np.ndarray, last_centre: np.ndarray, native: np.ndarray,
    voxel_size_mm: float | None, grid: int | Sequence[int] | None, axis_out: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Spacing (3,), counts (3,), first-centre coordinate (3,) along the stack axes (u, v, n)."""
    length = hi - lo
    if voxel_size_mm is not None:
        h = np.full(3, float(voxel_size_mm))
        counts = np.maximum(1, np.rint(length / h)).astype(int)
        mode = f"isotropic {float(voxel_size_mm):g} mm"
    elif grid is not None:
        g = np.asarray([grid] * 3 if isinstance(grid, int) else list(grid), int)
        counts = g[axis_out]  # grid is given in output (RAS-closest) axis order
        h = np.full(3, float(np.max(length / counts)))
        mode = f"grid {'x'.join(map(str, g))} isotropic {h[0]:.4g} mm"
    else:
        h = native.astype(float)
        counts = np.rint((last_centre - first_centre) / h).astype(int) + 1
        return h, counts, first_centre.astype(float), "native spacing"
    centre = (lo + hi) / 2
    start = centre - (counts - 1) / 2 * h
    return h, counts, start, mode


#: float32 arrays of the output grid's size that ingest holds at its peak (resampled, coverage, mapped, denoised,
#: mask, the copy written), beside the two of the in-plane pass (output rows x columns x source slices).
_GRID_COPIES, _INPLANE_COPIES = 6, 2


def _check_grid_fits(counts: np.ndarray, n_slices: int, spacing_mm: np.ndarray) -> None:
    """Refuse an output grid whose arrays would not fit in this machine's memory, before allocating any."""
    counts = np.asarray(counts, float)  # products of int64 counts can wrap round before the comparison
    need = 4 * (_GRID_COPIES * float(np.prod(counts)) + _INPLANE_COPIES * float(counts[0] * counts[1] * n_slices))
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return  # no way to ask: the allocation itself will say
    if need > total:
        shape = " x ".join(str(int(c)) for c in counts)
        raise CtsplatError(f"the output grid {shape} ({float(spacing_mm.min()):.3g} mm voxels) needs about "
                           f"{need / 2**30:.0f} GiB, more than this machine's {total / 2**30:.0f} GiB of memory; "
                           f"choose a larger voxel_size_mm or a smaller grid")


def resample_stack(
    stack: Any,
    *,
    voxel_size_mm: float | None = None,
    grid: int | Sequence[int] | None = None,
    fill: float | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Resample a :class:`ctsplat.formats.sources.SliceStack` onto a regular grid, exactly in world coordinates.

    The output grid is aligned with the slice axes ``(u, v, n)`` = (row direction, column
    direction, slice normal), so oblique scans stay unrotated, and is finally permuted/flipped to
    the closest RAS+ orientation (``nibabel.io_orientation``). For an output voxel centre ``p``
    (world mm) the value is

    ``f(p) = Σ_k W_n[p·n, s_k] · (W_u^k ⊗ W_v^k)[S_k](p·u - o_k·u, p·v - o_k·v)``

    i.e. each source slice ``k`` (origin ``o_k``, position ``s_k = o_k·n``) is first resampled
    in-plane at the exact in-plane coordinates of ``p`` (this absorbs gantry tilt, where ``o_k``
    drifts in-plane), then the slices are interpolated linearly along ``n`` between their true,
    possibly non-uniform positions ``s_k``. Each 1D step is ``W = L G``: a Gaussian anti-aliasing
    filter with std ``max(0, (h - d) / 2)`` (``h`` output, ``d`` source spacing; as in
    ``skimage.transform.resize``) followed by linear interpolation. Linear functions of world
    position are reproduced exactly (away from the borders when downsampling). Points within half a
    source voxel outside the data take the edge value; points further out take ``fill``.

    Parameters
    ----------
    stack : SliceStack
        ``data`` (I, J, K) with per-slice geometry (see :mod:`ctsplat.formats.sources`).
    voxel_size_mm : float, optional
        Isotropic output voxel edge (mm); the grid covers the scan's extent (centred).
    grid : int or (3,) ints, optional
        Output shape (``n`` -> ``n^3``) with isotropic voxels sized so the largest extent fits;
        shorter axes are padded with ``fill``. Ignored when ``voxel_size_mm`` is given. With
        neither, the output keeps the in-plane spacing and the median slice gap, anchored on the
        first voxel (centres coincide with the source pixels of uniformly spaced slices).
    fill : float, optional
        Value outside the scan (default: the data minimum, i.e. air for CT).

    Returns
    -------
    data : ndarray, shape (A, B, C), float32
        Resampled values, in the units of ``stack.data``.
    affine : ndarray, shape (4, 4)
        Voxel index -> world RAS mm (orthogonal, RAS-closest axis order, positive diagonal).
    info : dict
        What was done (for provenance).
    """
    data = np.asarray(stack.data, dtype=np.float32)
    n_i, n_j, n_k = data.shape
    u, v, n = np.asarray(stack.row_dir, float), np.asarray(stack.col_dir, float), stack.normal
    di, dj = (float(x) for x in stack.spacing_ij)
    origins = np.asarray(stack.origins, float)
    su, sv, s = origins @ u, origins @ v, origins @ n
    if n_k < 2 or np.any(np.diff(s) <= 0):
        raise CtsplatError("slices must have strictly increasing positions along the normal")
    gap = float(np.median(np.diff(s)))
    fill = float(data.min()) if fill is None else float(fill)

    lo = np.array([su.min() - di / 2, sv.min() - dj / 2, s[0] - gap / 2])
    hi = np.array([su.max() + (n_i - 0.5) * di, sv.max() + (n_j - 0.5) * dj, s[-1] + gap / 2])
    first = np.array([su.min(), sv.min(), s[0]])
    last = np.array([su.max() + (n_i - 1) * di, sv.max() + (n_j - 1) * dj, s[-1]])
    axes = np.stack([u, v, n], axis=1)
    ornt = nib.orientations.io_orientation(np.c_[np.r_[axes, np.zeros((1, 3))], [0, 0, 0, 1]])
    h, counts, start, mode = _grid_axes(
        lo, hi, first, last, np.array([di, dj, gap]), voxel_size_mm, grid, ornt[:, 0].astype(int)
    )
    _check_grid_fits(counts, n_k, h)
    out_u = start[0] + np.arange(counts[0]) * h[0]
    out_v = start[1] + np.arange(counts[1]) * h[1]
    out_n = start[2] + np.arange(counts[2]) * h[2]

    # 1) in-plane, per group of slices sharing the same in-plane offset (all of them unless tilted)
    inter = np.empty((counts[0], counts[1], n_k), dtype=np.float32)
    cov_inter = np.empty_like(inter)
    keys = np.round(np.stack([su, sv], 1), 6)
    groups = np.unique(keys, axis=0)
    for key in groups:
        ks: Any = np.flatnonzero(np.all(keys == key, axis=1))
        if len(groups) == 1:
            ks = slice(None)  # no tilt: one group, views instead of fancy-indexed copies
        n_g = n_k if len(groups) == 1 else len(ks)
        src_u = key[0] + np.arange(n_i) * di
        src_v = key[1] + np.arange(n_j) * dj
        wu = _interp_matrix(src_u, out_u, max(0.0, (h[0] - di) / 2), src_u[0] - di / 2, src_u[-1] + di / 2)
        wv = _interp_matrix(src_v, out_v, max(0.0, (h[1] - dj) / 2), src_v[0] - dj / 2, src_v[-1] + dj / 2)
        sub = np.ascontiguousarray(data[:, :, ks])
        if _is_identity(wu) and _is_identity(wv):
            inter[:, :, ks] = sub  # output pixels coincide with the source pixels (native spacing)
        else:
            t = np.asarray(wu @ sub.reshape(n_i, -1), np.float32).reshape(counts[0], n_j, n_g)
            t = np.ascontiguousarray(t.transpose(1, 0, 2)).reshape(n_j, -1)
            t = np.asarray(wv @ t, np.float32).reshape(counts[1], counts[0], n_g).transpose(1, 0, 2)
            inter[:, :, ks] = t
        cov = np.outer(np.asarray(wu.sum(axis=1)).ravel(), np.asarray(wv.sum(axis=1)).ravel())
        cov_inter[:, :, ks] = cov[:, :, None]

    # 2) along the normal, between the true (possibly non-uniform) slice positions
    wn = _interp_matrix(s, out_n, max(0.0, (h[2] - gap) / 2), s[0] - gap / 2, s[-1] + gap / 2)
    if _is_identity(wn):
        out, cov = inter, cov_inter
    else:
        wnt = wn.T.toarray().astype(np.float32)  # (K, C)
        # BLAS splits this product by threads and rounds differently for each count: one thread, so the volume
        # (and its volume_id, which names every later output) is the same whatever the machine or job size
        with threadpool_limits(limits=1, user_api="blas"):
            out = (inter.reshape(-1, n_k) @ wnt).reshape(counts[0], counts[1], counts[2])
            cov = (cov_inter.reshape(-1, n_k) @ wnt).reshape(out.shape)
    if not np.asarray(wn.sum(axis=1)).any():  # every output layer between the slices' positions: fill alone
        raise CtsplatError(f"no output layer of {h[2]:.3g} mm lies on the {s[-1] - s[0] + gap:.3g} mm the slices "
                           "cover, so the volume would hold only the fill value; use a finer grid or voxel size")
    out += np.float32(fill) * (1.0 - cov)

    affine = np.eye(4)
    affine[:3, :3] = axes * h[None, :]
    affine[:3, 3] = axes @ start
    out = nib.orientations.apply_orientation(out, ornt)
    affine = affine @ nib.orientations.inv_ornt_aff(ornt, tuple(counts))
    info = {
        "step": "resample",
        "mode": mode,
        "method": "separable linear interpolation in world coordinates with Gaussian anti-aliasing",
        "source_spacing_mm": [di, dj, gap],
        "source_slice_gaps_mm": sorted({round(float(x), 3) for x in np.diff(s)}),
        "gantry_tilt_deg": round(float(stack.tilt_deg), 4),
        "voxel_size_mm": [float(np.linalg.norm(affine[:3, i])) for i in range(3)],
        "shape": [int(x) for x in out.shape],
        "fill_value": fill,
    }
    return np.ascontiguousarray(out, dtype=np.float32), affine, info


# --------------------------------------------------------------------------------------------------
# Intensity mapping, masking, denoising
# --------------------------------------------------------------------------------------------------


def _mu_at(hu: float, mu_water_per_mm: float) -> float:
    """Linear attenuation (1/mm) at a CT number: ``μ = μ_water (1 + HU / 1000)``."""
    return mu_water_per_mm * (1.0 + hu / 1000.0)


def hu_to_attenuation(
    hu: np.ndarray, mu_water_per_mm: float = 0.019, hu_max: float = 3000.0
) -> tuple[np.ndarray, float]:
    """HU -> normalised attenuation in [0, 1] and the factor mapping it back to μ (1/mm).

    ``μ = μ_water (1 + HU / 1000)`` clipped to ``[0, μ_max]`` with ``μ_max = μ_water (1 + hu_max/1000)``;
    returns ``(μ / μ_max, μ_max)``, so ``μ = normalised * mu_scale_per_mm``. This inverts the
    definition of the Hounsfield unit, ``HU = 1000 (μ - μ_water) / μ_water`` (air ≈ -1000, water 0).

    Parameters
    ----------
    hu : ndarray, any shape
        Values in HU.
    mu_water_per_mm : float
        Linear attenuation coefficient of water (1/mm) at the effective energy.
    hu_max : float
        HU mapped to 1.0; denser values clip.

    Returns
    -------
    normalised : ndarray, same shape, float32
        ``μ / μ_max`` in [0, 1].
    mu_scale_per_mm : float
        ``μ_max`` (1/mm).
    """
    mu_max = _mu_at(hu_max, mu_water_per_mm)
    mu = mu_water_per_mm * (1.0 + np.asarray(hu, np.float32) / np.float32(1000.0))
    return (np.clip(mu, 0.0, mu_max) / np.float32(mu_max)).astype(np.float32), float(mu_max)


def apply_window(hu: np.ndarray, level: float, width: float) -> np.ndarray:
    """WL/WW window: ``clip((HU - (level - width/2)) / width, 0, 1)``.

    Parameters
    ----------
    hu : ndarray, any shape
        Values in HU.
    level, width : float
        Window centre and width (HU); ``width > 0``.

    Returns
    -------
    ndarray, same shape, float32
        Windowed values in [0, 1].
    """
    x = (np.asarray(hu, np.float32) - np.float32(level - width / 2.0)) / np.float32(width)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def body_mask(values: np.ndarray, method: str = "otsu") -> np.ndarray:
    """Foreground (body) mask: Otsu threshold, largest 3D component, holes filled.

    Parameters
    ----------
    values : ndarray, shape (I, J, K)
        Voxel values (any units; brighter = denser).
    method : {"otsu", "convex_hull"}
        ``convex_hull`` additionally takes the 2D convex hull of each slice ``[:, :, k]``.

    Returns
    -------
    ndarray, shape (I, J, K), bool
        True inside the body (all True for a constant volume).
    """
    from scipy import ndimage
    from skimage.filters import threshold_otsu
    from skimage.morphology import convex_hull_image

    values = np.asarray(values, np.float32)
    if np.ptp(values) == 0:
        return np.ones(values.shape, bool)
    fg = values > threshold_otsu(values)
    labels, n = ndimage.label(fg)
    if n > 1:
        sizes = np.bincount(labels.ravel())
        sizes[0] = 0
        fg = labels == int(np.argmax(sizes))
    fg = ndimage.binary_fill_holes(fg)
    if method == "convex_hull":
        for k in range(fg.shape[2]):
            if fg[:, :, k].any():
                fg[:, :, k] = convex_hull_image(fg[:, :, k])
    elif method != "otsu":
        raise CtsplatError(f"mask method {method!r} unknown; allowed: otsu, convex_hull")
    return fg


def intensity_full_scale(intensity: dict[str, Any]) -> float:
    """The value span that an intensity mapping's [0, 1] stands for: 1 for the normalised mappings, μ at ``hu_max``
    (1/mm) for ``mu``, and for ``hu`` (where ``hu_max`` has no say) air to the default ``hu_max``, 4000 HU.

    Parameters
    ----------
    intensity : dict
        The mapping's record as ingest writes it into ``volume.json``: ``kind``, and for ``mu`` its
        ``mu_water_per_mm`` and ``hu_max``.

    Returns
    -------
    float
        In the mapped values' units.
    """
    kind = intensity["kind"]
    if kind == "attenuation_per_mm":
        return _mu_at(float(intensity["hu_max"]), float(intensity["mu_water_per_mm"]))
    if kind == "hu":
        return float(PREPROCESSING_DEFAULTS["hu_max"]) + 1000.0
    return 1.0


def denoise(values: np.ndarray, method: str, weight: float) -> np.ndarray:
    """Denoise a volume.

    Parameters
    ----------
    values : ndarray, shape (I, J, K)
        Voxel values (after intensity mapping).
    method : {"tv", "bilateral"}
        ``tv``: 3D Chambolle total variation (``skimage.restoration.denoise_tv_chambolle``);
        ``bilateral``: ``skimage.restoration.denoise_bilateral`` per slice ``[:, :, k]`` with
        ``sigma_spatial = 1`` voxel.
    weight : float
        TV weight, or the bilateral ``sigma_color`` (in the units of ``values``).

    Returns
    -------
    ndarray, shape (I, J, K), float32
    """
    from skimage.restoration import denoise_bilateral, denoise_tv_chambolle

    values = np.asarray(values, np.float32)
    if method == "tv":
        return denoise_tv_chambolle(values, weight=weight).astype(np.float32)
    if method == "bilateral":
        out = np.empty_like(values)
        lo = float(values.min())
        for k in range(values.shape[2]):
            out[:, :, k] = denoise_bilateral(
                values[:, :, k] - lo, sigma_color=weight, sigma_spatial=1.0, mode="edge"
            ) + lo
        return out
    raise CtsplatError(f"denoise method {method!r} unknown; allowed: tv, bilateral")


def _handle_nonfinite(stack: Any, rule: str, label: str) -> tuple[Any, dict[str, Any] | None]:
    """Check ``stack.data`` for NaN / ±Inf; fail or fill by ``rule`` (see :data:`NONFINITE_RULES`)."""
    data = stack.data
    bad = ~np.isfinite(data)
    if not bad.any():
        return stack, None
    count = int(np.count_nonzero(bad))
    n_nan = int(np.count_nonzero(np.isnan(data)))
    lo, hi = [], []
    for axis in range(3):
        hit = np.flatnonzero(bad.any(axis=tuple(a for a in range(3) if a != axis)))
        lo.append(int(hit[0]))
        hi.append(int(hit[-1]))
    # world position of the box's corner voxels: origins[k] + i di row_dir + j dj col_dir
    corners = np.array(list(itertools.product(*zip(lo, hi, strict=True))))
    di, dj = (float(x) for x in stack.spacing_ij)
    world = (np.asarray(stack.origins, float)[corners[:, 2]] + np.outer(corners[:, 0] * di, stack.row_dir)
             + np.outer(corners[:, 1] * dj, stack.col_dir))
    box = ", ".join(f"{a}..{b}" for a, b in zip(lo, hi, strict=True))
    wbox = ", ".join(f"{a:.1f}..{b:.1f}" for a, b in zip(world.min(0), world.max(0), strict=True))
    what = f"{count} non-finite voxels ({n_nan} NaN, {count - n_nan} Inf)"
    if bad.all():
        raise CtsplatError(f"{label} has no finite voxel ({what}); check the input file")
    if rule == "error":
        raise CtsplatError(
            f"{label} has {what} within voxel indices [{box}] of its (I, J, K) = {tuple(data.shape)} grid "
            f"(world RAS mm [{wbox}]); fix the input, or pass nonfinite: fill_min (--nonfinite fill_min) to "
            f"replace them by the smallest finite value"
        )
    fill = float(data[~bad].min())
    log.warning("replacing %s within voxel indices [%s] by the smallest finite value %g", what, box, fill)
    filled = np.where(bad, np.float32(fill), data).astype(np.float32)
    step = {"step": "nonfinite", "rule": rule, "count": count, "n_nan": n_nan, "n_inf": count - n_nan,
            "bbox_ijk": [lo, hi], "fill_value": fill}
    return dataclasses.replace(stack, data=filled), step


def _map_intensity(values: np.ndarray, cfg: dict[str, Any], units: str) -> tuple[np.ndarray, dict[str, Any]]:
    mode = cfg["intensity"]
    mu_w, hu_max = float(cfg["mu_water_per_mm"]), float(cfg["hu_max"])
    if units != "hu" and mode in ("window", "mu"):
        raise CtsplatError(
            f"intensity {mode!r} needs HU input but the source values are raw; use intensity: attenuation "
            f"(min-max normalised) or hu"
        )
    if mode == "attenuation" and units == "hu":
        out, scale = hu_to_attenuation(values, mu_w, hu_max)
        return out, {
            "kind": "attenuation_normalised",
            "formula": "mu = mu_water * (1 + HU/1000), clipped to [0, mu_scale_per_mm], divided by mu_scale_per_mm",
            "mu_water_per_mm": mu_w, "hu_max": hu_max, "mu_scale_per_mm": scale,
        }
    if mode == "attenuation":
        lo, hi = float(values.min()), float(values.max())
        out = (values - lo) / (hi - lo) if hi > lo else np.zeros_like(values)
        scale = _mu_at(hu_max, mu_w)
        return out.astype(np.float32), {
            "kind": "minmax_normalised",
            "formula": "(x - min) / (max - min); raw source units, mu_scale_per_mm assumes max = mu(hu_max)",
            "source_min": lo, "source_max": hi, "mu_scale_per_mm": scale, "physical": False,
        }
    if mode == "window":
        level, width = _window_params(cfg["window"])
        return apply_window(values, level, width), {
            "kind": "window",
            "window": cfg["window"], "level_hu": level, "width_hu": width,
            "formula": "clip((HU - (level - width/2)) / width, 0, 1); mu_scale_per_mm = mu of the window top",
            "mu_scale_per_mm": _mu_at(level + width / 2, mu_w), "physical": False,
        }
    if mode == "mu":
        out, scale = hu_to_attenuation(values, mu_w, hu_max)
        return (out * np.float32(scale)).astype(np.float32), {
            "kind": "attenuation_per_mm",
            "formula": "mu = mu_water * (1 + HU/1000), clipped to [0, mu_water * (1 + hu_max/1000)]",
            "mu_water_per_mm": mu_w, "hu_max": hu_max, "mu_scale_per_mm": 1.0,
        }
    return values.astype(np.float32), {"kind": "hu", "note": "raw HU; not attenuation, do not project"}


# --------------------------------------------------------------------------------------------------
# Ingest
# --------------------------------------------------------------------------------------------------


def _check_not_ingested(source: Path) -> None:
    """Refuse a NIfTI that ingest wrote (its provenance JSON beside it says so) unless it kept HU: ingest reads NIfTI
    values as HU, and a normalised volume read as HU maps onto water, one constant value."""
    from ctsplat.formats.sources import source_kind

    sidecar = json_path_for(source)
    if not sidecar.is_file() or source_kind(source) != "nifti":
        return
    try:
        meta = read_json_object(sidecar, what="volume provenance", fix="")
    except CtsplatError:
        return  # not ours
    kind = meta.get("intensity", {}).get("kind") if isinstance(meta.get("intensity"), dict) else None
    if meta.get("created_by") == INGEST_MARKER and kind != "hu":
        raise CtsplatError(f"{source} is a volume ingest already wrote ({sidecar.name}: intensity {kind}), not a "
                           f"scan in HU; use it as it is (project, baseline and train read it), or ingest the "
                           f"original scan again with other settings")


def _warn_unless_hu(values: np.ndarray, source: Any) -> None:
    """Warn when NIfTI values, which ingest reads as HU, hold no air (-1000 HU) or exceed 4000
    (:func:`ctsplat.formats.sources.looks_like_hu`)."""
    from ctsplat.formats.sources import looks_like_hu

    finite = values[np.isfinite(values)]
    if finite.size and not looks_like_hu(finite):
        log.warning("%s: ingest reads NIfTI values as Hounsfield units, but these (%g .. %g) hold no air near -1000 "
                    "HU or exceed 4000; if the file is not a CT in HU the intensity mapping is wrong", source,
                    float(finite.min()), float(finite.max()))


def _check_not_the_source(source: Path, out_path: Path) -> None:
    """Refuse an output (or its ``volume.json`` sidecar) that is the source file or lies in the source folder."""
    src = source.resolve()
    for out in (out_path, json_path_for(out_path)):
        target = out.resolve()
        if target == src or src in target.parents:
            raise CtsplatError(f"output {out} is, or lies inside, the source {source}; writing it would change the "
                               "input: choose an output path outside it")


def ingest(
    source: str | Path | Any,
    out_path: str | Path,
    preprocessing: dict[str, Any] | None = None,
    *,
    series_uid: str | None = None,
    allow_modalities: Sequence[str] = ("CT",),
    skip_corrupt: bool = False,
    tiff_voxel_size_mm: float | Sequence[float] | None = None,
    rescale: Sequence[float] | None = None,
    nonfinite: str = "error",
) -> Volume:
    """Ingest a CT scan (DICOM folder, NIfTI file or TIFF stack) into a preprocessed NIfTI volume.

    Writes ``out_path`` (``.nii.gz``/``.nii``, NIfTI-1, world RAS affine) and the sibling
    ``volume.json`` (provenance: de-identified source facts, configuration, every step applied,
    intensity mapping with ``mu_scale_per_mm``, ``volume_id``, code version), atomically. Nothing is
    written when any check fails.

    A DICOM series with gaps much larger than its slice spacing (slices missing from the export) is
    still resampled (the gap is interpolated), with a :class:`ctsplat.formats.sources.SliceGapWarning`
    naming each gap; the gaps are recorded in ``volume.json`` under ``source.missing_slice_gaps``.

    Parameters
    ----------
    source : path or SliceStack
        DICOM folder (searched recursively), ``.nii``/``.nii.gz`` file, ``.tif`` stack or folder of
        TIFFs; or a :class:`ctsplat.formats.sources.SliceStack` already read.
    out_path : path
        Output ``.nii.gz`` (or ``.nii``) file.
    preprocessing : dict, optional
        Overrides of :data:`PREPROCESSING_DEFAULTS`.
    series_uid : str, optional
        The series to read when the folder holds several: its id as ``ctsplat ingest --list-series``
        shows it (the salted hash recorded as ``source.series_id``), its SeriesInstanceUID or its
        SeriesNumber.
    allow_modalities : sequence of str
        DICOM modalities accepted (default CT).
    skip_corrupt : bool
        Skip unreadable DICOM files with a warning.
    tiff_voxel_size_mm : float or (3,) floats, optional
        Voxel size of a TIFF stack (required for TIFF input).
    rescale : (2,) floats, optional
        DICOM only: ``[slope, intercept]`` for slices without RescaleSlope/RescaleIntercept
        (``[1, 0]`` = the stored values are HU); see :func:`ctsplat.formats.sources.read_dicom_series`
        for what happens without it. Recorded in ``volume.json`` under ``source.rescale``.
    nonfinite : {"error", "fill_min"}
        NaN / ±Inf source voxels: an error naming how many and their bounding box (voxel indices of
        the slice stack as read, and world mm), or replaced by the smallest finite value (recorded
        as the ``nonfinite`` step). See :data:`NONFINITE_RULES`.

    Returns
    -------
    Volume
        The volume written (``data`` float32 (I, J, K), ``affine``, ``meta``).
    """
    from ctsplat.formats.sources import SliceStack, check_rescale, read_source

    out_path = Path(out_path)
    if not out_path.name.endswith((".nii.gz", ".nii")):
        raise CtsplatError(f"output {out_path} must end in .nii.gz or .nii")
    check_sidecar_target(out_path)  # before the slow part
    if not isinstance(source, SliceStack):
        _check_not_the_source(Path(source), out_path)
        _check_not_ingested(Path(source))
    _check_ingest_target(out_path)
    cfg = merge_config("preprocessing", preprocessing, PREPROCESSING_DEFAULTS)
    check_preprocessing(cfg)
    cfg = preprocessing_in_effect(cfg)
    check_rescale(rescale)
    if nonfinite not in NONFINITE_RULES:
        raise CtsplatError(f"nonfinite {nonfinite!r} unknown; allowed: {', '.join(NONFINITE_RULES)}")
    t0 = time.perf_counter()
    if isinstance(source, SliceStack):
        if rescale is not None:
            raise CtsplatError("rescale applies when ingest reads a DICOM series, not to a SliceStack already read")
        stack = source
    else:
        stack = read_source(
            source, series_uid=series_uid, allow_modalities=allow_modalities, skip_corrupt=skip_corrupt,
            tiff_voxel_size_mm=tiff_voxel_size_mm, rescale=rescale,
        )
    if stack.units == "hu" and stack.source.get("kind") == "nifti":
        _warn_unless_hu(stack.data, source)
    t_read = time.perf_counter()
    steps: list[dict[str, Any]] = [
        {"step": "read", "kind": stack.source.get("kind"), "lps_to_ras": stack.source.get("kind") == "dicom"}
    ]
    label = "the slice stack" if isinstance(source, SliceStack) else f"source {source}"
    stack, nonfinite_step = _handle_nonfinite(stack, nonfinite, label)
    if nonfinite_step is not None:
        steps.append(nonfinite_step)
    values, affine, rinfo = resample_stack(stack, voxel_size_mm=cfg["voxel_size_mm"], grid=cfg["grid"])
    steps.append(rinfo)
    t_resample = time.perf_counter()
    mask = None
    if cfg["mask"]:
        mask = body_mask(values, cfg["mask"])
    mapped, intensity = _map_intensity(values, cfg, stack.units)
    steps.append({"step": "intensity", **{k: v for k, v in intensity.items() if k != "formula"}})
    if cfg["denoise"]:
        weight = float(cfg["denoise_weight"]) * intensity_full_scale(intensity)
        mapped = denoise(mapped, cfg["denoise"], weight)
        steps.append({"step": "denoise", "method": cfg["denoise"], "weight": float(cfg["denoise_weight"]),
                      "weight_in_value_units": weight})
    if mask is not None:
        # air: HU -1000 through the same mapping (0 for attenuation/window/mu), the minimum for raw data
        if stack.units == "hu":
            air_value = float(_map_intensity(np.array([-1000.0], np.float32), cfg, "hu")[0][0])
        else:
            air_value = 0.0 if intensity["kind"] == "minmax_normalised" else float(values.min())
        mapped = np.where(mask, mapped, np.float32(air_value)).astype(np.float32)
        steps.append({
            "step": "mask", "method": cfg["mask"], "foreground_fraction": float(mask.mean()), "air_value": air_value,
        })
    mapped = np.ascontiguousarray(mapped, dtype=np.float32)
    affine = affine.astype(np.float32).astype(float)  # exactly what the NIfTI sform stores
    meta: dict[str, Any] = {
        "format_version": 1,
        "created_by": INGEST_MARKER,
        "code_version": code_version(),
        "volume_id": compute_volume_id(mapped, affine),
        "frame": "RAS+ world, mm (NIfTI affine: voxel index -> world)",
        "source": stack.source,
        "source_value_range": [float(stack.data.min()), float(stack.data.max())],
        "source_units": stack.units,
        "preprocessing": cfg,
        "steps": steps,
        "intensity": intensity,
        "value_range": [float(mapped.min()), float(mapped.max())],
    }
    vol = Volume(data=mapped, affine=affine, meta=meta)
    save_volume(vol, out_path)
    log.info(
        "ingested %s -> %s: shape %s, voxel %.3f mm, id %s (read %.2fs, resample %.2fs, total %.2fs)",
        stack.source.get("kind"), out_path, vol.shape, float(vol.spacing_mm[0]), vol.volume_id,
        t_read - t0, t_resample - t_read, time.perf_counter() - t0,
    )
    vol.meta.update(shape=list(vol.shape), spacing_mm=[float(x) for x in vol.spacing_mm], affine=affine.tolist())
    return vol
