"""MBIR (model-based iterative reconstruction, qGGMRF prior) through ``svmbir``, for circular parallel beams.

The view set's axial sinograms (:func:`ctsplat.baselines.circular_sinograms`: skimage's ``radon`` layout, sums of
normalised voxel values in pixel units) are handed to ``svmbir.recon`` slice by slice in its own conventions,
found by projecting an asymmetric image with both libraries: svmbir's image is skimage's transposed, its view
angle is skimage's ``theta + 180°`` (in radians) and its channels run the other way. Both put the rotation centre
on a pixel centre only for odd image sizes, so an even ``n`` is padded by one zero bin (and one image row and
column, cropped afterwards). svmbir's voxel unit is the pixel (``delta_channel = delta_pixel = 1``), so its result
is the normalised volume directly.

svmbir caches its system matrices on disk (``svmbir_lib_path``); the cache goes into a folder the caller names
(default a fresh temporary folder, removed afterwards), never ``$HOME``. Its ICD updates are deterministic on a
single thread only (with several threads its parallel super-voxel updates differ from run to run by ~1e-3), so
the default is one thread; more threads trade reproducibility for speed.

References
----------
Bouman, C. A., Sauer, K. (1996). A unified approach to statistical tomography using coordinate descent
optimization. IEEE Transactions on Image Processing 5(3), 480-492.
Thibault, J.-B., Sauer, K. D., Bouman, C. A., Hsieh, J. (2007). A three-dimensional statistical approach to
improved image quality for multislice helical CT. Medical Physics 34(11), 4526-4544. (The qGGMRF prior.)
svmbir: https://github.com/cabouman/svmbir (Super-Voxel Model-Based Iterative Reconstruction).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.formats.viewset import ViewSet
from ctsplat.utils import CtsplatError

__all__ = ["mbir_volume", "svmbir_available"]


def svmbir_available() -> str | None:
    """None when ``svmbir`` imports, else why not (one line)."""
    try:
        import svmbir  # noqa: F401
    except Exception as exc:  # an absent or broken install: MBIR is skipped with this reason
        return f"svmbir is not importable ({type(exc).__name__}: {exc}); pip install svmbir"
    return None


def mbir_volume(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, sharpness: float = 0.0,
                snr_db: float = 30.0, positivity: bool = True, max_iterations: int = 50,
                stop_threshold: float = 0.0, num_threads: int = 1, mu_scale_per_mm: float | None = None,
                clip: bool = True, lib_path: str | os.PathLike[str] | None = None) -> np.ndarray:
    """MBIR (qGGMRF) reconstruction of a circular parallel-beam view set onto the reference grid, via svmbir.

    Parameters
    ----------
    line_integrals : ndarray, shape (V, H, W)
        Line integrals of μ of the views in ``view_set``, same order (the training views).
    view_set : ViewSet
        Parallel camera, circular orbit at elevation 0 (as :func:`ctsplat.baselines.fbp_volume` needs).
    reference : Volume-like
        Anything with ``affine`` (4, 4) and ``shape`` (I, J, K); axis-aligned, square in-plane voxels.
    sharpness : float
        svmbir's ``sharpness`` (higher: sharper, noisier; 0 its default regularisation).
    snr_db : float
        Assumed signal-to-noise ratio of the sinogram (dB); higher weights the data more.
    positivity : bool
        Enforce non-negative voxels.
    max_iterations : int
        svmbir's ``max_iterations``.
    stop_threshold : float
        svmbir's ``stop_threshold`` (percent change); 0 runs all ``max_iterations``. svmbir's own default (0.02)
        stopped some small problems after a few iterations far from convergence (data misfit twice the converged
        one), so the default here is a fixed iteration count.
    num_threads : int
        svmbir's threads; 1 (the default) gives bit-identical results from run to run, more do not.
    mu_scale_per_mm : float, optional
        Maps normalised values to 1/mm; default ``reference.mu_scale_per_mm`` (1.0 if absent).
    clip : bool
        Clip to [0, 1].
    lib_path : path-like, optional
        Folder of svmbir's system-matrix cache; default a temporary folder removed afterwards.

    Returns
    -------
    ndarray, shape (I, J, K), float32
        The normalised volume on the reference grid.

    Raises
    ------
    CtsplatError
        When svmbir is not installed, or for a geometry slice-wise reconstruction cannot handle.
    """
    from ctsplat.baselines import _to_reference, circular_sinograms
    from ctsplat.recon.operators import reference_grid

    why = svmbir_available()
    if why:
        raise CtsplatError(why)
    import svmbir

    affine, shape, scale = reference_grid(reference)
    scale = scale if mu_scale_per_mm is None else float(mu_scale_per_mm)
    sino, theta, grid = circular_sinograms(line_integrals, view_set, affine, shape, scale)  # (K, n, V)
    n = grid.n
    odd = n + (1 - n % 2)
    if odd != n:  # one more bin at +n/2 (outside the object): svmbir's centre (odd - 1) / 2 = skimage's n // 2
        sino = np.pad(sino, ((0, 0), (0, 1), (0, 0)))
    sv = np.ascontiguousarray(np.transpose(sino[:, ::-1, :], (2, 0, 1)))  # (V, K, channels), channels reversed
    angles = np.deg2rad(theta) + np.pi
    threads = max(1, int(num_threads))

    def run(path: str) -> np.ndarray:
        return svmbir.recon(sv, angles, num_rows=odd, num_cols=odd, roi_radius=odd / 2.0, sharpness=float(sharpness),
                            snr_db=float(snr_db), positivity=bool(positivity), max_iterations=int(max_iterations),
                            stop_threshold=float(stop_threshold), num_threads=threads, svmbir_lib_path=path,
                            verbose=0)

    if lib_path is None:
        with tempfile.TemporaryDirectory(prefix="svmbir-") as tmp:
            rec = run(tmp)
    else:
        Path(lib_path).mkdir(parents=True, exist_ok=True)
        rec = run(str(lib_path))
    stack = np.transpose(np.asarray(rec, np.float64), (0, 2, 1))[:, :n, :n]  # back to skimage's image axes
    vol = _to_reference(stack, grid)
    return np.clip(vol, 0.0, 1.0) if clip else vol
