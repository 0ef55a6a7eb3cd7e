"""Classical baselines: slice-by-slice FBP and SART for circular parallel beams, and the baseline step for any geometry.

:func:`run_baselines` (the ``baseline`` rule) runs every classical method the geometry allows through
:mod:`ctsplat.recon` (FDK for circular cone beams, 3D SART and ASD-POCS for any orbit, MBIR through svmbir and the
slice-wise methods below for circular parallel beams), each with its free parameters chosen on the validation views,
and only then measures them on the test views and the reference volume.

A circular parallel orbit at elevation 0 (``ctsplat.geometry.circular_orbit``) sees each axial slice of
the volume independently: detector row ``v`` holds the line integrals of the slice at height
``z = iso_z - (v + 0.5 - H/2) * spacing``, and the view at azimuth ``a`` is exactly
``skimage.transform.radon(slice, theta=a)`` of the slice ``mu[:, :, k]`` (axes +x, +y; see
``ctsplat.geometry``). So the reconstruction of the normalised volume is, for every axial slice ``k``:

1. resample the projections onto the sinogram grid skimage expects — bin ``b`` at signed distance
   ``(b - n//2) h`` from the rotation centre, where ``h`` is the in-plane voxel size and the centre is
   the voxel ``(I//2, J//2)`` of the reference grid (cubic-spline interpolation in ``u`` and ``v``; exact
   when the grids coincide);
2. divide by ``mu_scale_per_mm * h`` (line integrals of μ in mm -> sums of normalised voxel values);
3. ``skimage.transform.iradon`` (FBP; ``ramp`` or ``shepp-logan`` filter) or ``iradon_sart`` (SART,
   1..N iterations, each started from the previous one);
4. crop the ``n x n`` image onto the reference grid; optionally clip to [0, 1].

3D PSNR/SSIM against the reference use :mod:`ctsplat.evaluation.metrics` (normalised volumes, data range 1).

For geometries slice-wise reconstruction cannot handle (cone beam, sphere or wobbling orbits),
:func:`sirt_volume` runs SIRT in 3D with :func:`ctsplat.projector.line_integrals` as the system matrix.

References
----------
Andersen, A. H., Kak, A. C. (1984). Simultaneous algebraic reconstruction technique (SART): a superior
implementation of the ART algorithm. Ultrasonic Imaging 6(1), 81-94.
Gilbert, P. (1972). Iterative methods for the three-dimensional reconstruction of an object from projections.
Journal of Theoretical Biology 36(1), 105-117. (SIRT.)
Kak, A. C., Slaney, M. (1988). Principles of Computerized Tomographic Imaging. IEEE Press. (Filtered
back-projection, Ch. 3; algebraic reconstruction: ART, SIRT, SART, Ch. 7.)
Shepp, L. A., Logan, B. F. (1974). The Fourier reconstruction of a head section. IEEE Transactions on Nuclear
Science 21(3), 21-43. (The ``shepp-logan`` filter.)
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.formats.viewset import ViewSet
from ctsplat.utils import (
    CtsplatError,
    atomic_dir,
    check_output_dir,
    code_version,
    json_safe,
    merge_config,
    resolve_device,
    write_json_atomic,
)

__all__ = [
    "BASELINE_DEFAULTS",
    "BASELINES_DEFAULTS",
    "BASELINE_COLUMNS",
    "FBP_FILTERS",
    "is_circular_parallel",
    "select_views",
    "circular_sinograms",
    "fbp_volume",
    "sart_volumes",
    "sirt_volume",
    "run_baselines",
]

log = logging.getLogger(__name__)

#: ``skimage.transform.iradon`` filters accepted by :func:`fbp_volume` and ``baselines.fbp_filters``.
FBP_FILTERS = ("ramp", "shepp-logan", "cosine", "hamming", "hann")

#: Defaults of the ``baselines`` config section (see :func:`run_baselines`). Lists are candidates: every free
#: parameter is chosen on the validation views (``ctsplat.recon.select``); ``*_iterations`` are maxima (the
#: iteration count is chosen too).
BASELINE_DEFAULTS: dict[str, Any] = {
    # methods to run where the geometry allows them: fbp, sart, asd_pocs, mbir (circular parallel beam); fdk, sart,
    # asd_pocs (circular cone beam); sart, asd_pocs (any other orbit)
    "methods": ["fbp", "fdk", "sart", "asd_pocs", "mbir"],
    "fbp_filters": ["ramp", "shepp-logan"],  # FBP and FDK filter candidates
    "sart_max_iterations": 10,
    "sart_relaxation": [0.25, 1.0],  # candidates (a number = one)
    "sart_subsets": 10,  # 3D SART (cone beam, other orbits): ordered subsets per sweep (1 = SIRT)
    "asd_pocs_iterations": 10,
    "asd_pocs_alpha": [0.005, 0.02],  # TV weight candidates (TV step / first data step, Sidky & Pan 2008)
    "asd_pocs_tv_steps": 20,
    "asd_pocs_subsets": 10,
    "mbir_sharpness": [0.0, 1.0],  # svmbir qGGMRF candidates (circular parallel beam only)
    "mbir_snr_db": [30.0],
    "mbir_max_iterations": 50,  # svmbir ICD iterations (run to the end: no early stop)
    "mbir_threads": 1,  # svmbir threads: 1 is reproducible bit for bit, more are faster but vary by ~1e-3
    "patience": 2,  # stop an iterative candidate after this many iterations without a better validation score
    # 3D iterative methods and validation scores: average b x b detector pixels. 1 (the default) reconstructs from
    # the detector the Gaussians train on; null = the coarsest binning whose pixel at the isocentre is at most 1.5
    # voxels (2 for the cone-beam protocol's 2 pixels per voxel edge): faster, and it cost ASD-POCS about 2 dB of
    # 3D PSNR in small reruns of the protocol, so a comparison made with it handicaps the baseline
    "detector_binning": 1,
    "step_voxels": 1.0,  # 3D iterative methods: projector sampling step (voxels)
    "device": "auto",  # FDK and the 3D iterative methods: auto | cpu | cuda
    "split": "train",  # the views reconstructed from (only train: val chooses parameters, test scores)
    # number(s) of views: null/0 = all views of the split; an int or a list of ints = that many views spread
    # evenly over the split sorted by azimuth (the same subset `train.views` uses), one result row each
    "n_views": None,
    "clip": True,  # clip reconstructions to the normalised range [0, 1]
    # every method's chosen reconstruction sharpened by unsharp masking, the amount chosen on the validation views
    # among these (0 = as reconstructed), as the Gaussians' read-out may be (train.sharpen): a comparison that
    # sharpens one side offers it to the other
    "sharpen": {"amounts": [0.0], "radius_voxels": 1.0},
    "save_volumes": True,
}
BASELINES_DEFAULTS = BASELINE_DEFAULTS  # the name the workflow's config section uses


@dataclass
class _SliceGrid:
    """How the iradon image maps onto the reference grid (axes flipped so i ~ +x, j ~ +y)."""

    n: int  # iradon image size (n x n), sinogram bins
    flips: tuple[bool, bool, bool]
    off: tuple[int, int]  # iradon pixel (r, c) = reference (i + off[0], j + off[1]) after flips
    shape: tuple[int, int, int]


def _grid_axes(affine: np.ndarray, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, tuple[bool, ...]]:
    """Voxel sizes and origin of an axis-aligned grid after flipping negative axes."""
    M = np.asarray(affine, float)[:3, :3]
    off_diag = M - np.diag(np.diag(M))
    if np.abs(off_diag).max() > 1e-6 * np.abs(M).max():
        raise CtsplatError("slice-wise FBP/SART needs an axis-aligned reference grid (diagonal affine, i ~ x, j ~ y, "
                           "k ~ z); resample the volume first")
    d = np.diag(M)
    flips = tuple(bool(x < 0) for x in d)
    origin = np.asarray(affine, float)[:3, 3] + np.where(flips, d * (np.asarray(shape) - 1), 0.0)
    return np.abs(d), origin, flips


def is_circular_parallel(view_set: ViewSet) -> bool:
    """Whether a view set is parallel-beam on a planar circular orbit about +z at elevation 0.

    That is what slice-wise FBP/SART need: every view's detector rows are axial slices (``y_cam = -z_world``).

    Parameters
    ----------
    view_set : ViewSet
        The views and their camera.

    Returns
    -------
    bool
        True when the camera is parallel, the set is non-empty and every view looks horizontally with world +z
        at the image top (to 1e-6).
    """
    if view_set.camera.model != "parallel" or not len(view_set):
        return False
    Rs = view_set.Rs()
    return bool(np.abs(Rs[:, 2, 2]).max() <= 1e-6 and np.abs(Rs[:, 1] - [0.0, 0.0, -1.0]).max() <= 1e-6)


def circular_sinograms(line_integrals: np.ndarray, view_set: ViewSet, affine: np.ndarray,
                       shape: tuple[int, int, int], mu_scale_per_mm: float = 1.0
                       ) -> tuple[np.ndarray, np.ndarray, _SliceGrid]:
    """Per-axial-slice sinograms in skimage's ``radon`` layout from a circular parallel view set.

    Parameters
    ----------
    line_integrals : ndarray (V, H, W)
        Line integrals of μ (dimensionless), page order of ``view_set``.
    view_set : ViewSet
        Parallel camera, every view at elevation 0 (rays in the axial plane, world +z up in the image).
    affine : ndarray, shape (4, 4)
        Voxel index -> world mm of the reference grid; axis-aligned (diagonal), square in-plane voxels.
    shape : tuple of int, shape (3,)
        ``(I, J, K)`` of the reference grid.
    mu_scale_per_mm : float
        Divides the line integrals so the result reconstructs the normalised volume.

    Returns
    -------
    sinograms : ndarray, shape (K, n, V), float64
        Per axial slice ``k``, sums of normalised voxel values along rays, in pixel units (as ``radon``
        returns); ``n = max(I, J)`` bins.
    theta : ndarray, shape (V,)
        Projection angles (degrees) = azimuths.
    grid : _SliceGrid
        How the ``n x n`` reconstructions map back onto the reference grid.

    Raises
    ------
    CtsplatError
        For a cone-beam camera, line integrals that do not match the view set, an orbit that is not planar
        circular at elevation 0, or a reference grid that is not axis-aligned with square in-plane voxels.
    """
    from scipy.ndimage import map_coordinates

    p = np.asarray(line_integrals, float)
    cam = view_set.camera
    if cam.model != "parallel":
        raise CtsplatError("FBP/SART baselines need a parallel-beam view set (camera: parallel); got a cone beam")
    if p.shape != (len(view_set), cam.height, cam.width):
        raise CtsplatError(f"line integrals of shape {p.shape} do not match the view set "
                           f"({len(view_set)}, {cam.height}, {cam.width})")
    Rs = view_set.Rs()
    if not is_circular_parallel(view_set):
        raise CtsplatError("FBP/SART baselines need a planar circular orbit about +z at elevation 0 "
                           "(orbit: circular, wobble_deg: 0)")
    spacing, origin, flips = _grid_axes(affine, shape)
    if abs(spacing[0] - spacing[1]) > 1e-6 * spacing[0]:
        raise CtsplatError(f"slice-wise FBP/SART needs square in-plane voxels, got {spacing[:2]} mm")
    h = float(spacing[0])
    nI, nJ, nK = shape
    n = max(nI, nJ)
    ci, cj = nI // 2, nJ // 2
    off = (n // 2 - ci, n // 2 - cj)
    P0 = origin[:2] + h * np.array([ci, cj])  # world (x, y) of the rotation centre iradon uses
    theta = np.array([v.azimuth_deg for v in view_set.views], float)
    z = origin[2] + spacing[2] * np.arange(nK)
    sp = cam.spacing_mm
    b = np.arange(n) - n // 2
    sino = np.zeros((nK, n, len(view_set)))
    for a, (img, R, t) in enumerate(zip(p, Rs, view_set.ts(), strict=True)):
        # x_cam = R X + t. Bin b is the ray through P0 + b h R[0] (R[0] = (-sin a, cos a, 0), radon's
        # detector axis); slice k is the row through z_k (R[1] = (0, 0, -1)).
        u_mm = b * h + R[0, :2] @ P0 + t[0]
        v_mm = R[1, 2] * z + t[1]
        u_pix = u_mm / sp + cam.cx - 0.5
        v_pix = v_mm / sp + cam.cy - 0.5
        vv, uu = np.meshgrid(v_pix, u_pix, indexing="ij")  # (K, n)
        sino[:, :, a] = map_coordinates(img, [vv, uu], order=3, mode="nearest")
    sino /= mu_scale_per_mm * h
    return sino, theta, _SliceGrid(n, flips, off, (nI, nJ, nK))


def _to_reference(stack: np.ndarray, grid: _SliceGrid) -> np.ndarray:
    """(K, n, n) iradon images -> (I, J, K) reference array (crop, undo flips)."""
    nI, nJ, _ = grid.shape
    vol = np.moveaxis(stack[:, grid.off[0] : grid.off[0] + nI, grid.off[1] : grid.off[1] + nJ], 0, -1)
    for axis, f in enumerate(grid.flips):
        if f:
            vol = np.flip(vol, axis)
    return np.ascontiguousarray(vol, dtype=np.float32)


def _reference_grid(reference: Any) -> tuple[np.ndarray, tuple[int, int, int], float]:
    affine = np.asarray(reference.affine, float)
    shape = tuple(int(s) for s in (reference.shape if hasattr(reference, "shape") else reference.data.shape))
    scale = float(getattr(reference, "mu_scale_per_mm", 1.0))
    return affine, shape, scale  # type: ignore[return-value]


def fbp_volume(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, filter_name: str = "ramp",
               mu_scale_per_mm: float | None = None, clip: bool = True) -> np.ndarray:
    """Slice-by-slice filtered back-projection onto a reference grid (e.g. for ``init: fbp``).

    ``skimage.transform.iradon`` per axial slice, each view weighted by the share of the directions it covers
    (:func:`parallel_view_weights`: any arc and uneven subsets, not only views spread evenly over 180° or 360°).

    Parameters
    ----------
    line_integrals : ndarray (V, H, W)
        Line integrals of μ (as in ``line_integrals.tif``) of the views in ``view_set``, same order —
        pass the *training* views only (``p[vs.indices("train")]`` with ``vs.subset("train")``).
    view_set : ViewSet
        Parallel camera, circular orbit at elevation 0 (``orbit: circular``, ``wobble_deg: 0``); other
        geometries raise ``CtsplatError``.
    reference : Volume-like
        Anything with ``affine`` (4, 4) and ``shape`` (I, J, K) (a ``ctsplat.volume.Volume``); its grid must
        be axis-aligned with square in-plane voxels. Its voxel values are not read.
    filter_name : str
        ``skimage.transform.iradon`` filter: ramp, shepp-logan, cosine, hamming, hann.
    mu_scale_per_mm : float, optional
        Maps normalised values to 1/mm; default ``reference.mu_scale_per_mm`` (1.0 if absent).
    clip : bool
        Clip to [0, 1] (the normalised range).

    Returns
    -------
    ndarray, shape (I, J, K), float32
        The normalised volume on the reference grid.

    Raises
    ------
    CtsplatError
        For an unknown filter or a geometry slice-wise FBP cannot handle (:func:`circular_sinograms`).

    Examples
    --------
    >>> from ctsplat.formats.viewset import load_radiographs
    >>> from ctsplat.formats.volume import load_volume
    >>> volume = load_volume("results/head/volume.nii.gz")  # doctest: +SKIP
    >>> p, vs = load_radiographs("results/head/radiographs/circular")  # doctest: +SKIP
    >>> rows = vs.indices("train")  # doctest: +SKIP
    >>> rec = fbp_volume(p[rows], vs.subset("train"), volume, filter_name="shepp-logan")  # doctest: +SKIP
    """
    from skimage.transform import iradon

    if filter_name not in FBP_FILTERS:
        raise CtsplatError(f"unknown FBP filter {filter_name!r}; allowed: {', '.join(FBP_FILTERS)}")
    affine, shape, scale = _reference_grid(reference)
    scale = scale if mu_scale_per_mm is None else float(mu_scale_per_mm)
    sino, theta, grid = circular_sinograms(line_integrals, view_set, affine, shape, scale)
    weights = parallel_view_weights(theta)
    if np.ptp(weights) > 1e-6:  # iradon weights every view alike; evenly spaced sets need no correction
        sino = sino * weights
    stack = np.stack([iradon(s, theta=theta, output_size=grid.n, filter_name=filter_name, circle=True)
                      for s in sino])
    vol = _to_reference(stack, grid)
    return np.clip(vol, 0.0, 1.0) if clip else vol


def parallel_view_weights(theta_deg: np.ndarray) -> np.ndarray:
    """Relative quadrature weights of parallel-beam views for filtered back-projection, mean 1.

    A parallel view and the one opposite it see the same line integrals, so the directions live on a circle of
    π: each view gets half the gaps to its neighbours there, views of one direction sharing it
    (:func:`ctsplat.recon.fdk.angular_weights` on the doubled angles). ``skimage.transform.iradon`` weights every
    view by ``π / 2V``, right only for views spread evenly over 180° or 360°; scaling each view's sinogram
    column by these weights makes it right for any arc (on 270°, the directions seen twice would otherwise count
    twice) and for uneven subsets. A limited arc (below 180°) keeps even weights: its missing wedge is not
    spread over the end views.

    Parameters
    ----------
    theta_deg : ndarray, shape (V,)
        Projection angles, degrees.

    Returns
    -------
    ndarray, shape (V,)
        Weights, mean 1; all 1 for views spread evenly over 180° or 360°.

    References
    ----------
    Kak, A. C., Slaney, M. (1988). Principles of Computerized Tomographic Imaging, IEEE Press, ch. 3.3
    (the back-projection integral over [0, π)).

    Examples
    --------
    >>> parallel_view_weights(np.array([0.0, 60.0, 120.0, 180.0, 240.0])).round(3)  # 0/180 and 60/240 coincide
    array([0.833, 0.833, 1.667, 0.833, 0.833])
    """
    from ctsplat.recon.fdk import angular_weights

    theta = np.asarray(theta_deg, float)
    if theta.size < 2:
        return np.ones(theta.size)
    # directions to 1e-9 degrees: the opposite view of an even orbit lands on its partner up to rounding
    phi = np.round(np.mod(theta, 180.0), 9)
    phi[phi >= 180.0] = 0.0
    directions, which, count = np.unique(phi, return_inverse=True, return_counts=True)
    if directions.size < 2:
        return np.ones(theta.size)
    cell = angular_weights(np.deg2rad(2.0 * directions))[0]
    weights = cell[which] / count[which]
    return weights / weights.mean()


def sart_volumes(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, iterations: int = 5,
                 relaxation: float = 0.15, mu_scale_per_mm: float | None = None, clip: bool = True):
    """Slice-by-slice SART onto a reference grid, yielding the volume after each iteration.

    Each iteration is one ``skimage.transform.iradon_sart`` sweep (Andersen & Kak 1984) per axial slice, started
    from the previous iteration's (unclipped) slice. Same geometry requirements as :func:`fbp_volume`.

    Parameters
    ----------
    line_integrals : ndarray, shape (V, H, W)
        Line integrals of μ of the views in ``view_set``, same order.
    view_set : ViewSet
        Parallel camera, circular orbit at elevation 0.
    reference : Volume-like
        Anything with ``affine`` (4, 4) and ``shape`` (I, J, K); see :func:`fbp_volume`.
    iterations : int
        Number of SART sweeps, >= 1.
    relaxation : float
        SART relaxation factor (``iradon_sart``'s ``relaxation``).
    mu_scale_per_mm : float, optional
        Maps normalised values to 1/mm; default ``reference.mu_scale_per_mm`` (1.0 if absent).
    clip : bool
        Clip each yielded volume to [0, 1] (the iterate itself stays unclipped).

    Yields
    ------
    iteration : int
        1 .. ``iterations``.
    volume : ndarray, shape (I, J, K), float32
        The normalised volume after that iteration.

    Raises
    ------
    CtsplatError
        For ``iterations < 1`` or a geometry slice-wise SART cannot handle (:func:`circular_sinograms`).
    """
    from skimage.transform import iradon_sart

    if int(iterations) < 1:
        raise CtsplatError(f"sart_max_iterations must be >= 1, got {iterations}")
    affine, shape, scale = _reference_grid(reference)
    scale = scale if mu_scale_per_mm is None else float(mu_scale_per_mm)
    sino, theta, grid = circular_sinograms(line_integrals, view_set, affine, shape, scale)
    current = [None] * len(sino)
    for it in range(1, int(iterations) + 1):
        current = [iradon_sart(s, theta=theta, image=img, relaxation=relaxation)
                   for s, img in zip(sino, current, strict=True)]
        vol = _to_reference(np.stack(current), grid)
        yield it, (np.clip(vol, 0.0, 1.0) if clip else vol)


def sirt_volume(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, iterations: int = 10,
                relaxation: float = 1.0, mu_scale_per_mm: float | None = None, clip: bool = True,
                device: str | None = None, views_per_batch: int = 8) -> np.ndarray:
    """SIRT on the reference grid for *any* geometry (cone beam, sphere orbits), with the projector's adjoint.

    ``x <- clip(x + λ C Aᵀ R (b - A x))`` with ``A`` = :func:`ctsplat.projector.line_integrals` (its
    adjoint ``Aᵀ y = ∇_x <A x, y>`` by autograd), ``R = 1 / (A 1)`` per ray and ``C = 1 / (Aᵀ 1)`` per
    voxel (zero where a ray or voxel is never hit), ``b`` = line integrals / ``mu_scale_per_mm``, starting
    from ``x = 0``. This is SIRT (Gilbert 1972) with row- and column-sum normalisation. Views
    are processed ``views_per_batch`` at a time so memory stays bounded. A geometry-agnostic alternative
    to :func:`fbp_volume` for ``init: fbp`` when the orbit is not circular parallel.

    Parameters
    ----------
    line_integrals : ndarray, shape (V, H, W)
        Line integrals of μ of the views in ``view_set``, same order.
    view_set : ViewSet
        Any camera and orbit.
    reference : Volume-like
        Anything with ``affine`` (4, 4) and ``shape`` (I, J, K); the grid need not be axis-aligned.
    iterations : int
        Number of SIRT updates, >= 1.
    relaxation : float
        Step ``λ``.
    mu_scale_per_mm : float, optional
        Maps normalised values to 1/mm; default ``reference.mu_scale_per_mm`` (1.0 if absent).
    clip : bool
        Clip the iterate to [0, 1] after every update.
    device : str, optional
        Torch device; default CPU.
    views_per_batch : int
        Views projected at once.

    Returns
    -------
    ndarray, shape (I, J, K), float32
        The normalised volume on the reference grid.

    Raises
    ------
    CtsplatError
        For ``iterations < 1`` or line integrals that do not match the view set.
    """
    import torch

    from ctsplat.projector import line_integrals as project

    if int(iterations) < 1:
        raise CtsplatError(f"SIRT iterations must be >= 1, got {iterations}")
    affine, shape, scale = _reference_grid(reference)
    scale = scale if mu_scale_per_mm is None else float(mu_scale_per_mm)
    cam = view_set.camera
    p = np.asarray(line_integrals, np.float32)
    if p.shape != (len(view_set), cam.height, cam.width):
        raise CtsplatError(f"line integrals of shape {p.shape} do not match the view set "
                           f"({len(view_set)}, {cam.height}, {cam.width})")
    dev = torch.device(device) if device else torch.device("cpu")
    b = torch.as_tensor(p / scale, device=dev)
    Rs, ts = view_set.Rs(), view_set.ts()
    batches = [slice(i, i + views_per_batch) for i in range(0, len(view_set), views_per_batch)]

    def forward(x: torch.Tensor, sl: slice) -> torch.Tensor:
        with torch.no_grad():
            return project(x, affine, cam, Rs[sl], ts[sl], device=dev, method="trilinear")

    def adjoint(y: torch.Tensor, sl: slice) -> torch.Tensor:
        x = torch.zeros(shape, device=dev, requires_grad=True)  # A is linear: the gradient does not depend on x
        (project(x, affine, cam, Rs[sl], ts[sl], device=dev, method="trilinear") * y).sum().backward()
        return x.grad

    ones = torch.ones(shape, device=dev)
    row = torch.cat([forward(ones, sl) for sl in batches])
    rinv = torch.where(row > 1e-6, 1.0 / row.clamp_min(1e-6), torch.zeros((), device=dev))
    col = sum(adjoint(torch.ones_like(b[sl]), sl) for sl in batches)
    cinv = torch.where(col > 1e-6, 1.0 / col.clamp_min(1e-6), torch.zeros((), device=dev))
    x = torch.zeros(shape, device=dev)
    for _ in range(int(iterations)):
        update = sum(adjoint((b[sl] - forward(x, sl)) * rinv[sl], sl) for sl in batches)
        x = x + relaxation * cinv * update
        if clip:
            x = x.clamp(0.0, 1.0)
    return x.cpu().numpy().astype(np.float32)


def select_views(view_set: ViewSet, split: str, n: int) -> np.ndarray:
    """Row indices of ``n`` views of ``split`` spread evenly in azimuth order (all when ``n`` is 0 or too large).

    Training's ``views`` rule, :func:`ctsplat.scene.spread_views`: sort the split's views by ``azimuth mod 360``
    and take positions ``floor(m * N / n)``, ``m = 0..n-1``.

    Parameters
    ----------
    view_set : ViewSet
        The view set.
    split : {"train", "val", "test"}
        Which views to choose from.
    n : int
        How many; ``<= 0`` or ``>=`` the split's size takes all.

    Returns
    -------
    ndarray of int, shape (n,)
        Row indices into ``view_set.views`` (and the line-integral stack), in azimuth order.

    Raises
    ------
    CtsplatError
        When the split has no views.
    """
    from ctsplat.scene import spread_views

    if view_set.indices(split).size == 0:
        raise CtsplatError(f"view set has no '{split}' views; re-render with a non-zero {split} fraction")
    return spread_views(view_set, split, n)


#: Columns of ``baselines.csv``: the first seven as before (the analysis figures read them), then the validation
#: score that chose the parameters, the chosen parameters (JSON), the 2D test metrics, the time of every candidate,
#: whether the row is the best classical reconstruction on validation for its view count, and whether an iterative
#: method chose the last iteration of its budget while still improving (``at_cap``: its budget stopped it).
BASELINE_COLUMNS = ["method", "filter", "iterations", "n_views", "psnr3d", "ssim3d", "seconds", "val_psnr", "params",
                    "psnr2d", "ssim2d", "selection_seconds", "best_on_val", "at_cap"]

#: The setting that caps each iterative method's iterations (named when the cap binds).
ITERATION_CAPS = {"sart": "sart_max_iterations", "asd_pocs": "asd_pocs_iterations"}

#: The files of a baselines folder beside ``baselines.csv`` and ``baselines.json``: every trial, and each reconstruction
#: (``{method}_n{views:03d}.nii.gz`` with its sidecar, when ``save_volumes``). A folder holding anything else is
#: not replaced.
BASELINE_FILES = ("trials.csv", "*_n[0-9][0-9][0-9]*.nii.gz", "*_n[0-9][0-9][0-9]*.json")
#: Any of these marks a folder as an earlier baselines output. ``trials.csv`` is one: the workflow declares the two
#: tables as the rule's outputs, and Snakemake removes them before it reruns the step.
BASELINE_MARKERS = ("baselines.csv", "baselines.json", "trials.csv")


def _counts(value: Any) -> list[int]:
    counts = [0] if value in (None, 0) else ([int(value)] if isinstance(value, int | float) else list(value))
    if not counts or any(not isinstance(c, int | float) or int(c) < 0 for c in counts):
        raise CtsplatError(f"baselines.n_views must be null, a non-negative integer or a list of them, got {value}")
    return [int(c) for c in counts]


def run_baselines(volume_path: str | Path, radiographs_dir: str | Path, out_dir: str | Path,
                  config: dict[str, Any] | None = None) -> Any:
    """Every classical reconstruction the geometry allows, parameters chosen on validation, then test metrics.

    Methods and their candidates: :data:`BASELINE_DEFAULTS` and :mod:`ctsplat.recon.suite` (circular parallel
    beam: FBP, SART, ASD-POCS, MBIR; circular cone beam: FDK, SART, ASD-POCS; other orbits: SART, ASD-POCS). For
    each view count in ``config["n_views"]`` (views of ``split`` chosen by :func:`select_views`) every method's
    free parameters are chosen by the re-projection PSNR on the view set's *validation* views
    (:mod:`ctsplat.recon.select`); only then are the chosen volume's 3D metrics against the reference and its 2D
    metrics on the test views computed. Writes ``out_dir/baselines.csv`` (:data:`BASELINE_COLUMNS`, one row per
    method and view count; ``seconds`` is the chosen reconstruction's time, metrics excluded), every candidate's
    validation score to ``out_dir/trials.csv``, the volumes ``{method}_n{views:03d}.nii.gz`` (normalised,
    reference grid; when ``save_volumes``) and ``baselines.json`` (provenance).

    Parameters
    ----------
    volume_path : str or Path
        The reference volume (its grid, and its values for the metrics).
    radiographs_dir : str or Path
        Radiographs of that volume, any geometry, with validation views.
    out_dir : str or Path
        Output folder (created).
    config : dict, optional
        The ``baselines`` section (:data:`BASELINE_DEFAULTS`).

    Returns
    -------
    pandas.DataFrame
        The ``baselines.csv`` table: PSNR in dB, SSIM in [0, 1], seconds of reconstruction.

    Raises
    ------
    CtsplatError
        Before any work, for a bad setting (naming the key), radiographs of another volume, an empty split, no
        validation views, or methods that cannot reconstruct the geometry.
    """
    import pandas as pd

    from ctsplat.config import check_section
    from ctsplat.evaluation.metrics import psnr, psnr3d, ssim2d, ssim3d
    from ctsplat.formats.viewset import load_radiographs
    from ctsplat.formats.volume import Volume, load_volume, save_volume
    from ctsplat.recon.select import Validator
    from ctsplat.recon.suite import best_choice, classical_reconstructions

    check_section("baselines", dict(config or {}))
    cfg = merge_config("baselines", config, BASELINE_DEFAULTS)
    counts = _counts(cfg["n_views"])
    out_dir = Path(out_dir)
    check_output_dir(out_dir, marker=BASELINE_MARKERS, contents=BASELINE_FILES, inputs=(volume_path, radiographs_dir))
    volume = load_volume(volume_path)
    p_all, vs_all = load_radiographs(radiographs_dir)
    if vs_all.volume_id != volume.volume_id:
        raise CtsplatError(f"radiographs in {radiographs_dir} were rendered from volume {vs_all.volume_id}, "
                           f"not {volume.volume_id} ({volume_path}); re-render them")
    val_rows = vs_all.indices("val")
    if val_rows.size == 0:
        raise CtsplatError(f"radiographs in {radiographs_dir} have no validation views to choose the baselines' "
                           "parameters on; render them with validation views (radiographs n_val for a circular orbit, "
                           "else split.val)")
    val_vs = vs_all.subset("val")
    test_rows = vs_all.indices("test")
    subsets = [select_views(vs_all, cfg["split"], c) for c in counts]  # errors on an empty split, before any work
    # counts capped to the split's size name the same views (0, 50 and 80 of 50): each subset runs once
    first: dict[tuple[int, ...], int] = {}
    for i, idx in enumerate(subsets):
        first.setdefault(tuple(idx), i)
    counts, subsets = [counts[i] for i in first.values()], [subsets[i] for i in first.values()]
    ref = volume.data
    unit = volume.metric_range  # 3D metrics compare normalised volumes
    rows: list[dict[str, Any]] = []
    trials: list[dict[str, Any]] = []
    volumes: dict[str, np.ndarray] = {}
    # the test views re-projected on the reconstructions' device (at 256³ and 512² detectors the CPU takes minutes)
    test = (Validator(p_all[test_rows], vs_all.subset("test"), volume, device=resolve_device(cfg["device"]))
            if test_rows.size else None)
    for requested, idx in zip(counts, subsets, strict=True):
        if requested and len(idx) < requested:
            log.warning("baselines: %d views requested but the %s split has %d; using all", requested,
                        cfg["split"], len(idx))
        vs = ViewSet(vs_all.camera, [vs_all.views[i] for i in idx], vs_all.volume_id, vs_all.isocenter_mm,
                     dict(vs_all.meta))
        nv = len(vs)
        choices = classical_reconstructions(p_all[idx], vs, p_all[val_rows], val_vs, volume, cfg,
                                            work_dir=out_dir.parent)
        best = best_choice(choices)
        for c in choices:  # test metrics only now, after every choice is made
            row = {"method": c.method, "filter": c.params.get("filter", ""),
                   "iterations": int(c.params.get("iterations", 0)), "n_views": nv,
                   "psnr3d": psnr3d(c.volume / unit, ref / unit), "ssim3d": ssim3d(c.volume / unit, ref / unit),
                   "seconds": c.seconds, "val_psnr": c.val_psnr,
                   "params": json.dumps(c.params, sort_keys=True), "psnr2d": float("nan"), "ssim2d": float("nan"),
                   "selection_seconds": c.selection_seconds, "best_on_val": c is best, "at_cap": bool(c.at_cap)}
            if c.at_cap:
                log.warning("baselines, %d views: %s chose the last of its %d iterations, still improving on "
                            "validation: its budget, not the validation views, stopped it; raise baselines.%s",
                            nv, c.method, int(c.params["iterations"]), ITERATION_CAPS.get(c.method, "iterations"))
            if test is not None:
                pred, target = test.render(c.volume), test.target
                row["psnr2d"] = float(np.mean([psnr(a, b) for a, b in zip(pred, target, strict=True)]))
                row["ssim2d"] = float(np.mean([ssim2d(a, b) for a, b in zip(pred, target, strict=True)]))
            rows.append(row)
            trials.extend({"n_views": nv, **t} for t in c.trials)
            volumes[f"{c.method}_n{nv:03d}"] = c.volume
            log.info("baselines, %d views: %s %s -> val %.2f dB, 3D PSNR %.2f dB", nv, c.method, c.params,
                     c.val_psnr, row["psnr3d"])

    df = pd.DataFrame(rows, columns=BASELINE_COLUMNS)
    # the folder is replaced whole: no volume of an earlier run's view counts stays beside this run's tables
    with atomic_dir(out_dir, marker=BASELINE_MARKERS, contents=BASELINE_FILES,
                    inputs=(volume_path, radiographs_dir)) as tmp:
        if cfg["save_volumes"]:
            for name, rec in volumes.items():
                meta = {"volume_id": f"{volume.volume_id}-{name}", "reference_volume_id": volume.volume_id,
                        "intensity": {"mu_scale_per_mm": volume.mu_scale_per_mm, "normalised": True},
                        "baseline": name, "code_version": code_version()}
                save_volume(Volume(rec, volume.affine, meta), tmp / f"{name}.nii.gz")
        pd.DataFrame(trials).to_csv(tmp / "trials.csv", index=False, lineterminator="\n")
        write_json_atomic(tmp / "baselines.json", json_safe({
            "config": cfg, "code_version": code_version(), "volume_path": str(volume_path),
            "volume_id": volume.volume_id, "radiographs_dir": str(radiographs_dir), "results": rows,
            "selection": "parameters chosen by re-projection PSNR on the validation views; test metrics after",
        }))
        df.to_csv(tmp / "baselines.csv", index=False, lineterminator="\n")
    return df
