"""FDK (Feldkamp-Davis-Kress) reconstruction for circular cone-beam orbits, on a reference grid.

For a flat detector at source-to-detector distance ``DSD``, source-to-isocentre distance ``DSO`` and a circular
orbit about the detector's column axis, every voxel ``x`` is (Feldkamp, Davis & Kress 1984; Kak & Slaney 1988,
eq. 3.181)

    f(x) = Σ_views w_β ½ Δβ (DSO / U)² Q_β(u(x), v(x)),
    Q_β = (1 / τ) h ⊛_u [ p_β · DSD / √(DSD² + u² + v²) ],

with ``p_β`` the line integrals of view ``β`` (divided by ``mu_scale_per_mm`` for the normalised volume), ``u, v``
the detector coordinates (mm) of the pixel centres, ``τ = pitch · DSO / DSD`` the pixel pitch scaled to the
isocentre, ``h`` the discrete ramp kernel (``h[0] = ¼``, ``h[n] = -1 / (π n)²`` for odd ``n``, 0 for even; in
pixel units, applied along the detector rows through a zero-padded FFT, optionally apodised), ``U = z_cam(x)``
the depth of the voxel along the view's optical axis, ``u(x), v(x)`` its projection onto the detector
(bilinear interpolation of ``Q``; zero off the detector) and ``Δβ`` the angle each view covers (half the gaps
to its neighbours in azimuth). A full scan (360°) covers every ray twice, hence ``½``; a short scan (at least
180° plus the fan angle, less than 360°) instead weights each view by Parker's (1982) function ``w_β(γ)`` of the
fan angle ``γ = atan(u / DSD)``, which makes the redundant rays sum to one, and drops the ``½``.

In the parallel limit (``DSO``, ``DSD`` → ∞ at a fixed isocentre pitch) this is filtered back-projection over the
same angles, which :func:`ctsplat.baselines.fbp_volume` computes slice by slice.

References
----------
Feldkamp, L. A., Davis, L. C., Kress, J. W. (1984). Practical cone-beam algorithm. Journal of the Optical Society
of America A 1(6), 612-619.
Kak, A. C., Slaney, M. (1988). Principles of Computerized Tomographic Imaging. IEEE Press. (Ch. 3: the ramp
kernel, fan-beam and cone-beam weighting.)
Parker, D. L. (1982). Optimal short scan convolution reconstruction for fan beam CT. Medical Physics 9(2),
254-257.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ctsplat.baselines import FBP_FILTERS
from ctsplat.formats.viewset import ViewSet
from ctsplat.geometry.cameras import camera_center
from ctsplat.recon.operators import check_stack, reference_grid
from ctsplat.utils import CtsplatError

__all__ = ["FDK_FILTERS", "fdk_volume", "is_circular_cone", "orbit_angles", "ramp_filter", "short_scan_shortfall"]

#: Apodisation windows of the ramp filter: the ones slice-wise FBP offers (``skimage.transform.iradon``'s names),
#: since one ``baselines.fbp_filters`` list feeds both.
FDK_FILTERS = FBP_FILTERS


def ramp_filter(size: int, filter_name: str = "ramp") -> np.ndarray:
    """Frequency response (length ``size``, FFT order) of the discrete ramp kernel in pixel units, apodised.

    Parameters
    ----------
    size : int
        Padded length (even).
    filter_name : str
        One of :data:`FDK_FILTERS`.

    Returns
    -------
    ndarray, shape (size,)
        Real response; multiplying the FFT of a zero-padded row by it convolves the row with ``h`` (pixel units).

    Raises
    ------
    CtsplatError
        For an unknown filter name.
    """
    if filter_name not in FDK_FILTERS:
        raise CtsplatError(f"unknown FDK filter {filter_name!r}; allowed: {', '.join(FDK_FILTERS)}")
    n = np.concatenate((np.arange(1, size // 2 + 1, 2), np.arange(size // 2 - 1, 0, -2)))
    h = np.zeros(size)
    h[0] = 0.25
    h[1::2] = -1.0 / (np.pi * n) ** 2
    resp = np.real(np.fft.fft(h))
    omega = np.pi * np.fft.fftfreq(size)[1:]
    if filter_name == "shepp-logan":
        resp[1:] *= np.sin(omega) / omega
    elif filter_name == "cosine":
        resp *= np.fft.fftshift(np.sin(np.linspace(0, np.pi, size, endpoint=False)))
    elif filter_name == "hamming":
        resp *= np.fft.fftshift(np.hamming(size))
    elif filter_name == "hann":
        resp *= np.fft.fftshift(np.hanning(size))
    return resp


def _axis_and_angles(view_set: ViewSet) -> tuple[np.ndarray, np.ndarray] | None:
    """The common rotation axis (world) and each view's angle about it (rad), or None when there is none."""
    Rs = view_set.Rs()
    axis = -Rs[:, 1].mean(axis=0)
    if np.abs(Rs[:, 1] + axis).max() > 1e-6:
        return None
    axis = axis / np.linalg.norm(axis)
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    return axis, np.arctan2(Rs[:, 2] @ e2, Rs[:, 2] @ e1)


def is_circular_cone(view_set: ViewSet) -> bool:
    """Whether a view set is cone beam on a planar circular orbit about the detector's column axis (no wobble).

    Parameters
    ----------
    view_set : ViewSet
        The views and their camera.

    Returns
    -------
    bool
        True when the camera is a cone, and every view shares the detector's column direction (to 1e-6) with its
        source at the camera's ``dso_mm`` from a common isocentre (to 1e-3 relative).
    """
    if view_set.camera.model != "cone" or len(view_set) < 2 or _axis_and_angles(view_set) is None:
        return False
    Rs, ts = view_set.Rs(), view_set.ts()
    centres = camera_center(Rs, ts)
    dso = view_set.camera.dso_mm
    # the isocentre of each view: dso along its optical axis from its source
    iso = centres + dso * Rs[:, 2]
    return bool(np.abs(iso - iso.mean(axis=0)).max() <= 1e-3 * dso)


def orbit_angles(view_set: ViewSet) -> np.ndarray:
    """Each view's angle about the orbit's rotation axis (rad, in (-π, π]); see :func:`is_circular_cone`."""
    found = _axis_and_angles(view_set)
    if found is None:
        raise CtsplatError("the views share no rotation axis (a circular orbit at elevation 0 needs one)")
    return found[1]


def angular_weights(beta: np.ndarray) -> tuple[np.ndarray, bool, float, float]:
    """Per-view ``Δβ`` (half the gaps to the neighbours), whether the scan is short, its start and its range.

    A scan is short when its largest gap exceeds three times the median gap (a missing arc, not a sparse
    circle); its range then runs from the view after that gap to the view before it.

    Parameters
    ----------
    beta : ndarray, shape (V,)
        Source angles, radians, on a 2π circle (any order; distinct).

    Returns
    -------
    dbeta : ndarray, shape (V,)
        The angle each view covers, radians (end views of a short scan: half a gap beyond them).
    short : bool
    start, scan : float
        The short scan's first angle and range, radians (0 and 2π for a full circle).
    """
    V = len(beta)
    order = np.argsort(beta)
    b = beta[order]
    gaps = np.diff(np.concatenate([b, b[:1] + 2 * np.pi]))  # gap after each sorted view (circular)
    big = int(np.argmax(gaps))
    short = V > 2 and gaps[big] > 3.0 * np.median(gaps)
    dbeta = np.empty(V)
    if not short:
        dbeta[order] = 0.5 * (gaps + np.roll(gaps, 1))
        return dbeta, False, 0.0, 2 * np.pi
    # the scan runs from b[big + 1] (after the missing arc) forwards to b[big]; end views get half a gap outside
    start = b[(big + 1) % V]
    rel = np.mod(beta - start, 2 * np.pi)
    o = np.argsort(rel)
    r = rel[o]
    g = np.diff(r)
    inner = 0.5 * (np.concatenate([[g[0]], g]) + np.concatenate([g, [g[-1]]]))
    dbeta[o] = inner
    return dbeta, True, float(start), float(r[-1] + g.mean())


def short_scan_shortfall(view_set: ViewSet) -> str | None:
    """Why FDK cannot reconstruct a circular cone-beam orbit: a short scan under 180° plus the fan angle.

    Parameters
    ----------
    view_set : ViewSet
        A circular cone-beam view set (:func:`is_circular_cone`).

    Returns
    -------
    str or None
        One line naming the arc and what it needs; None when the orbit is a full scan or a long enough short scan.
    """
    _, short, _, scan = angular_weights(orbit_angles(view_set))
    return _shortfall(scan, _half_fan(view_set.camera)) if short else None


def _half_fan(cam: Any) -> float:
    """Half the fan angle of a cone-beam detector's width (rad)."""
    return float(np.arctan((cam.width / 2.0) * cam.pitch_mm / cam.dsd_mm))


def _shortfall(scan: float, delta: float) -> str | None:
    """The one line of :func:`short_scan_shortfall` for a short scan of ``scan`` rad and half fan angle ``delta``."""
    if scan >= np.pi + 2 * delta - 1e-6:
        return None
    return (f"FDK short scan covers {np.degrees(scan):.0f} deg, less than 180 deg plus the fan angle "
            f"({np.degrees(np.pi + 2 * delta):.0f} deg); render a longer arc")


def _parker(rel_beta: np.ndarray, gamma: np.ndarray, delta: float, scan: float) -> np.ndarray:
    """Parker's short-scan weights ``w(β, γ)``, shape (V, W); ``delta`` half fan angle, ``scan`` the range (rad).

    For scans longer than ``π + 2δ`` the extra range widens the transition regions (Wesarg et al. 2002's
    generalisation with ``δ' = (scan - π) / 2``).
    """
    d = max((scan - np.pi) / 2.0, delta)
    b = rel_beta[:, None]
    g = gamma[None, :]
    w = np.ones((len(rel_beta), len(gamma)))
    lo = b < 2 * (d - g)
    hi = b > np.pi - 2 * g
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(lo, np.sin(np.pi / 4 * b / (d - g)) ** 2, w)
        w = np.where(hi, np.sin(np.pi / 4 * (np.pi + 2 * d - b) / (d + g)) ** 2, w)
    w = np.where(b > np.pi + 2 * d, 0.0, w)
    return np.nan_to_num(w)


def fdk_volume(line_integrals: np.ndarray, view_set: ViewSet, reference: Any, *, filter_name: str = "ramp",
               mu_scale_per_mm: float | None = None, clip: bool = True, device: str | torch.device | None = None,
               views_per_batch: int = 4) -> np.ndarray:
    """FDK reconstruction of a circular cone-beam view set onto a reference grid (full or short scan).

    Parameters
    ----------
    line_integrals : ndarray, shape (V, H, W)
        Line integrals of μ of the views in ``view_set``, same order (the training views).
    view_set : ViewSet
        Cone camera on a circular orbit without wobble (:func:`is_circular_cone`); angles need not be uniform.
    reference : Volume-like
        Anything with ``affine`` (4, 4) and ``shape`` (I, J, K) (a ``ctsplat.volume.Volume``); any orientation.
    filter_name : str
        Ramp apodisation, one of :data:`FDK_FILTERS` (``ramp``, ``shepp-logan``, ...).
    mu_scale_per_mm : float, optional
        Maps normalised values to 1/mm; default ``reference.mu_scale_per_mm`` (1.0 if absent).
    clip : bool
        Clip to [0, 1] (the normalised range).
    device : str or torch.device, optional
        Where to back-project (default CPU).
    views_per_batch : int
        Views back-projected at once (memory: ~12 bytes per voxel per view).

    Returns
    -------
    ndarray, shape (I, J, K), float32
        The normalised volume on the reference grid (``fbp_volume``'s units).

    Raises
    ------
    CtsplatError
        For an unknown filter, line integrals that do not match the view set, or a view set that is not a
        circular cone-beam orbit.

    Examples
    --------
    >>> from ctsplat.formats.viewset import load_radiographs
    >>> from ctsplat.formats.volume import load_volume
    >>> volume = load_volume("results/head/volume.nii.gz")  # doctest: +SKIP
    >>> p, vs = load_radiographs("results/head/radiographs/cone")  # doctest: +SKIP
    >>> rows = vs.indices("train")  # doctest: +SKIP
    >>> rec = fdk_volume(p[rows], vs.subset("train"), volume, filter_name="shepp-logan")  # doctest: +SKIP
    """
    if filter_name not in FDK_FILTERS:
        raise CtsplatError(f"unknown FDK filter {filter_name!r}; allowed: {', '.join(FDK_FILTERS)}")
    p = check_stack(line_integrals, view_set)
    if not is_circular_cone(view_set):
        raise CtsplatError("FDK needs a cone-beam view set on a circular orbit without wobble (camera: cone, "
                           "orbit: circular, wobble_deg: 0); use SIRT/ASD-POCS for other orbits")
    affine, shape, scale = reference_grid(reference)
    scale = scale if mu_scale_per_mm is None else float(mu_scale_per_mm)
    dev = torch.device(device) if device else torch.device("cpu")
    cam = view_set.camera
    V, H, W = p.shape
    dso, dsd, pitch = cam.dso_mm, cam.dsd_mm, cam.pitch_mm
    tau = pitch * dso / dsd
    u = (np.arange(W) + 0.5 - cam.cx) * pitch
    v = (np.arange(H) + 0.5 - cam.cy) * pitch
    cosw = dsd / np.sqrt(dsd**2 + u[None, :] ** 2 + v[:, None] ** 2)  # (H, W)

    beta = orbit_angles(view_set)
    dbeta, short, start, scan = angular_weights(beta)
    if short:
        gamma = np.arctan(u / dsd)
        delta = _half_fan(cam)
        shortfall = _shortfall(scan, delta)
        if shortfall is not None:
            raise CtsplatError(shortfall)
        # Parker's β runs with the orbit and γ with it: the sign of γ follows the direction of rotation
        view_w = _parker(np.mod(beta - start, 2 * np.pi), -gamma, delta, scan) * dbeta[:, None]  # (V, W)
    else:
        view_w = np.repeat(0.5 * dbeta[:, None], W, axis=1)

    size = max(64, 1 << int(math.ceil(math.log2(2 * W))))
    resp = torch.as_tensor(ramp_filter(size, filter_name), dtype=torch.float32, device=dev)

    idx = np.stack(np.meshgrid(*(np.arange(s, dtype=np.float32) for s in shape), indexing="ij"), -1).reshape(-1, 3)
    X = torch.as_tensor(idx @ affine[:3, :3].T.astype(np.float32) + affine[:3, 3].astype(np.float32),
                        device=dev)  # (N, 3) world mm of the voxel centres
    out = torch.zeros(X.shape[0], dtype=torch.float32, device=dev)
    Rs = torch.as_tensor(view_set.Rs(), dtype=torch.float32, device=dev)
    ts = torch.as_tensor(view_set.ts(), dtype=torch.float32, device=dev)
    cosw_t = torch.as_tensor(cosw, dtype=torch.float32, device=dev)
    for b0 in range(0, V, max(1, int(views_per_batch))):
        sl = slice(b0, min(V, b0 + max(1, int(views_per_batch))))
        q = torch.as_tensor(p[sl] / scale, device=dev) * cosw_t
        q = torch.nn.functional.pad(q, (0, size - W))
        q = torch.fft.irfft(torch.fft.rfft(q, dim=-1) * resp[: size // 2 + 1], n=size, dim=-1)[..., :W] / tau
        q = q * torch.as_tensor(view_w[sl], dtype=torch.float32, device=dev)[:, None, :]
        xc = torch.einsum("bij,nj->bni", Rs[sl], X) + ts[sl][:, None, :]  # (B, N, 3) camera frame
        z = xc[..., 2].clamp_min(1e-6)
        gu = (cam.fx * xc[..., 0] / z + cam.cx) * (2.0 / W) - 1.0  # pixel centres at index + 0.5
        gv = (cam.fy * xc[..., 1] / z + cam.cy) * (2.0 / H) - 1.0
        grid = torch.stack([gu, gv], -1)[:, None]  # (B, 1, N, 2)
        vals = torch.nn.functional.grid_sample(q[:, None], grid, mode="bilinear", padding_mode="zeros",
                                               align_corners=False)[:, 0, 0]  # (B, N)
        out += ((dso / z) ** 2 * vals).sum(0)
    vol = out.reshape(shape).cpu().numpy().astype(np.float32)
    return np.clip(vol, 0.0, 1.0) if clip else vol
