"""Beer–Lambert projector: line integrals of μ along detector rays, noise, and the radiograph files.

For a detector ray ``x(s) = o + s d`` (``|d| = 1``, ``s`` in mm, ``s >= 0``) the line integral is

    p = ∫ μ(x(s)) ds  (dimensionless; μ in 1/mm),   transmission I = I0 exp(-p).

μ(x) is the trilinear interpolant of the voxel values (zero outside the grid), whose support is the
index box ``(-1, N)`` along each axis (narrowed to one voxel around the non-zero voxels when no gradient
is needed). Each ray is clipped to that box in index space (slab test), and
the clipped segment ``[s0, s0 + L]`` is integrated by the midpoint rule with ``n = ceil(L / step)``
equal steps ``h = L / n <= step = step_voxels * min(spacing)`` (per ray, so results do not depend on
batching):

    p ≈ h Σ_k μ(x(s0 + (k + ½) h)),   k = 0 .. n-1,

sampled with ``torch.nn.functional.grid_sample`` (trilinear, ``align_corners=True``). Rays are sorted by
length and processed in chunks of at most ``batch_samples`` samples, so memory stays bounded for any
number of views; everything runs on the device of ``device`` (CUDA when given CUDA tensors).

Parallel beams whose detector rows run along a voxel axis (circular orbits at elevation 0, the
classical CT protocol) use an exact-in-the-limit slice-wise Joseph traversal instead, ~10x faster
(see :func:`_joseph_slices`); ``method=`` picks explicitly.

Noise (optional, seeded, on the splits ``noise.splits`` names: the training views by default, so validation
and test targets stay noise-free): counts ``N = Poisson(I0 exp(-p / s)) + Normal(0, σ_e)`` and
``p_noisy = s ln(I0 / N)``, where ``s = 1`` for ``noise.model: physical`` (``p`` in physical units, μ in 1/mm)
and ``s = max p`` over the noisy views for ``noise.model: tigre`` — TIGRE's ``CTnoise.add(proj, Poisson=I0,
Gaussian=[0, σ_e])``, which rescales the stack so its most attenuating ray transmits ``exp(-1)``, so the noise
level does not depend on the volume's physical scale; R²-Gaussian then clips the noisy line integrals at ``>= 0``
(counts above ``I0``), and so does ``tigre`` here. The log of zero: counts below one photon (non-positive ones
come from electronic noise) are clipped to one photon before the log, so ``p_noisy <= s ln(I0)`` stays finite
(TIGRE returns inf/NaN there; at R²'s ``I0 = 1e4``, ``σ_e = 10`` the smallest expected count is ``I0 / e ≈ 3679``
and the clip never acts, so the values equal TIGRE's). The model is monochromatic (no beam hardening or
scatter): Poisson quantum noise of the transmitted photons plus Gaussian detector read-out noise, the usual
first-order CT noise model.

References
----------
Beer–Lambert law of attenuation: ``I = I0 exp(-∫ μ dl)``.
Biguri, A., Dosanjh, M., Hancock, S., Soleimani, M. (2016). TIGRE: a MATLAB-GPU toolbox for CBCT image
reconstruction. Biomedical Physics & Engineering Express 2(5), 055010. Code: github.com/CERN/TIGRE,
``Python/tigre/utilities/CTnoise.py`` (``add``: the ``tigre`` noise model).
Zha, R. et al. (2024). R²-Gaussian: rectifying radiative Gaussian splatting for tomographic reconstruction.
NeurIPS. Code: github.com/Ruyi-Zha/r2_gaussian, ``data_generator/synthetic_dataset/generate_data.py`` (noise on
the training projections only, clipped at >= 0; the cone-beam protocol geometry).
Hsieh, J. (2009). Computed Tomography: Principles, Design, Artifacts, and Recent Advances (2nd ed.). SPIE Press.
(Transmission model, photon and electronic noise.)
Joseph, P. M. (1982). An improved algorithm for reprojecting rays through pixel images. IEEE Transactions on
Medical Imaging 1(3), 192-196. (The slice-wise parallel-beam projector.)
Kak, A. C., Slaney, M. (1988). Principles of Computerized Tomographic Imaging. IEEE Press. (Projections as line
integrals of the attenuation coefficient.)
Kay, T. L., Kajiya, J. T. (1986). Ray tracing complex scenes. SIGGRAPH Computer Graphics 20(4), 269-278. (Slab
test for clipping rays to a box.)
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat.formats.viewset import ViewSet, check_radiograph_targets, write_radiographs
from ctsplat.geometry import (
    Camera,
    ConeCamera,
    ParallelCamera,
    camera_rays,
    carm_orbit,
    check_fov,
    check_orbit_settings,
    circular_orbit,
    covering_spacing_mm,
    object_points_mm,
    sphere_orbit,
    support_radius_mm,
)
from ctsplat.utils import CtsplatError, code_version, merge_config, resolve_device

__all__ = [
    "RADIOGRAPHS_DEFAULTS",
    "line_integrals",
    "clip_rays_to_box",
    "add_noise",
    "check_noise",
    "build_view_set",
    "render_radiographs",
]

log = logging.getLogger(__name__)

#: Defaults of the ``radiographs`` config section (one geometry); see :func:`build_view_set`.
RADIOGRAPHS_DEFAULTS: dict[str, Any] = {
    # camera model: "parallel" (orthographic) or "cone" (perspective, source at the camera centre)
    "camera": "parallel",
    "detector_width": 128,
    "detector_height": 128,
    # parallel: detector pixel spacing; cone: detector pitch (mm). null = detector_size_factor when set, else one
    # voxel (the largest voxel edge) per pixel at the isocentre (cone: pitch = voxel * dsd / dso), enlarged when
    # needed so that the object lies on the detector in every view (orbit carm: fitted, see fov_margin)
    "pixel_spacing_mm": None,
    # the detector's physical width (cone: on the detector plane; parallel: at the isocentre) in units of the
    # volume's side L (its largest extent, mm): spacing = detector_size_factor * L / detector_width. null = unused
    "detector_size_factor": None,
    "dso_mm": 1000.0,  # cone: source-to-isocentre distance (mm); null = dso_factor * L
    "dsd_mm": 1500.0,  # cone: source-to-detector distance (mm); null = dsd_factor * L
    "dso_factor": 2.5,  # cone with dso_mm null: DSO in units of L (R²-Gaussian's protocol: 2.5 L)
    "dsd_factor": 3.5,  # cone with dsd_mm null: DSD in units of L (R²-Gaussian's protocol: 3.5 L)
    # an explicit detector (pixel_spacing_mm or detector_size_factor) that leaves part of the object outside the
    # field of view is an error; true accepts the truncation (interior / region-of-interest studies) with a warning
    "allow_truncation": False,
    # parallel: distance of the ray-origin plane from the isocentre (mm); null = just outside the volume
    "parallel_distance_mm": None,
    "isocenter_mm": None,  # null = the volume's geometric centre
    # orbit: "circular" (n_views training angles about +z, plus random held-out angles), "sphere" (n_views
    # directions spread over the elevation band, split train/val/test) or "carm" (a designed cone-beam C-arm
    # orbit with an elevation wobble whose true poses deviate from the design; every view is a training view;
    # views.json stores both poses; the view set SfM registers)
    "orbit": "circular",
    "n_views": 100,
    "elevation_range_deg": [-60.0, 60.0],
    "sphere_sampling": "fibonacci",
    "wobble_deg": 0.0,  # circular / carm: elevation = wobble_deg * sin(wobble_cycles * azimuth)
    "wobble_cycles": 2.0,
    "start_deg": 0.0,
    # circular / carm: angular range of the views (deg). null = 180 for parallel beams (views at a and a + 180 are
    # mirror images, so 360 would repeat directions for even n_views) and 360 for cone beams.
    "arc_deg": None,
    # carm: the true orbit deviates from the design by N(0, σ²) per view in azimuth and elevation (deg) and its
    # isocentre by N(0, σ² I) (mm: the whole source-detector assembly shifts), seeded by the projection seed
    "orbit_jitter_deg": 0.0,
    "orbit_jitter_mm": 0.0,
    # carm with pixel_spacing_mm null: the detector pitch fits the object's bounding sphere (voxels above 20 % of
    # the maximum) times fov_margin onto the detector's shorter side
    "fov_margin": 1.0,
    "split": {"train": 0.7, "val": 0.15, "test": 0.15},
    # circular: explicit numbers of validation / test views (null = from the split fractions); n_views stays the
    # number of training views
    "n_val": None,
    "n_test": None,
    "step_voxels": 0.5,
    # photon + electronic noise (module docstring): i0 photons per pixel, electronic_sigma counts; model "physical"
    # (counts from the physical line integrals) or "tigre" (TIGRE's CTnoise.add: the stack rescaled to max p = 1,
    # noisy line integrals clipped at >= 0); splits: which views get noise (validation/test stay clean by default)
    "noise": {"enabled": False, "i0": 1.0e5, "electronic_sigma": 0.0, "model": "physical", "splits": ["train"]},
    "device": "auto",
    "batch_samples": 1 << 22,
}


# ---------------------------------------------------------------------------------------- projector
def clip_rays_to_box(origins: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: entry ``s0 >= 0`` and length ``L >= 0`` of rays ``o + s d`` inside the box ``[lo, hi]``.

    For each axis the ray is inside the slab ``lo <= x <= hi`` for ``s`` between ``(lo - o) / d`` and
    ``(hi - o) / d``; the ray is inside the box on the intersection of the three intervals, cut at ``s = 0``.
    A direction component of 0 gives the whole line or nothing, depending on whether the origin is inside
    that slab.

    Parameters
    ----------
    origins, dirs : ndarray, shape (N, 3)
        Ray origins and directions (any consistent units; ``s`` is in units of ``|d|``).
    lo, hi : ndarray, shape (3,)
        Box corners.

    Returns
    -------
    s0 : ndarray, shape (N,)
        Ray parameter where the ray enters the box (0 when the origin is inside).
    length : ndarray, shape (N,)
        Parameter length inside the box; 0 for rays that miss it.

    Examples
    --------
    >>> s0, length = clip_rays_to_box(np.array([[-5.0, 0.5, 0.5]]), np.array([[1.0, 0.0, 0.0]]),
    ...                               np.zeros(3), np.ones(3))
    >>> s0, length
    (array([5.]), array([1.]))
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t1 = (lo - origins) * inv
        t2 = (hi - origins) * inv
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    parallel_axis = dirs == 0
    inside = (origins > lo) & (origins < hi)
    tmin = np.where(parallel_axis, np.where(inside, -np.inf, np.inf), tmin)
    tmax = np.where(parallel_axis, np.where(inside, np.inf, -np.inf), tmax)
    s0 = np.maximum(tmin.max(axis=1), 0.0)
    s1 = tmax.min(axis=1)
    length = np.where(s1 > s0, s1 - s0, 0.0)
    return s0, length


def line_integrals(
    mu: torch.Tensor | np.ndarray,
    affine: np.ndarray,
    camera: Camera,
    Rs: np.ndarray,
    ts: np.ndarray,
    *,
    step_voxels: float = 0.5,
    device: str | torch.device | None = None,
    batch_samples: int = 1 << 22,
    method: str = "auto",
) -> torch.Tensor:
    """Line integrals ``p = ∫ μ dl`` through ``mu`` for every pixel of every view.

    Parameters
    ----------
    mu : Tensor or ndarray, shape (I, J, K)
        Attenuation in 1/mm (or normalised values: the result scales with them), indexed as ``affine`` says,
        at least 2 voxels per axis. Differentiable when a tensor requiring grad.
    affine : ndarray, shape (4, 4)
        Voxel index -> world (mm).
    camera : ParallelCamera or ConeCamera
        The detector, ``H`` rows by ``W`` columns.
    Rs : ndarray, shape (V, 3, 3)
        World-to-camera rotations (OpenCV).
    ts : ndarray, shape (V, 3)
        World-to-camera translations (mm).
    step_voxels : float
        Upper bound of the sampling step in units of the smallest voxel edge, in (0, 1] (<= 0.5 recommended).
    device : str | torch.device | None
        Where to compute; default the device of ``mu`` (CPU for arrays).
    batch_samples : int
        Maximum number of samples evaluated at once (memory bound: ~40 bytes per sample).
    method : {"auto", "trilinear", "joseph"}
        ``trilinear``: midpoint rule at ``<= step_voxels`` steps (any camera). ``joseph``: the slice-wise
        Joseph traversal (parallel beam whose detector rows run along one voxel axis, e.g. circular
        orbits at elevation 0; see :func:`_joseph_slices`). ``auto``: ``joseph`` when the geometry
        allows it, else ``trilinear``.

    Returns
    -------
    Tensor, shape (V, H, W), float32
        Line integrals (dimensionless for ``mu`` in 1/mm), on ``device``; 0 for rays that miss the volume.

    Raises
    ------
    CtsplatError
        For ``step_voxels`` outside (0, 1], a volume that is not 3D with >= 2 voxels per axis, no views, unequal
        numbers of rotations and translations, an affine that is not invertible, an unknown ``method``, or
        ``method="joseph"`` on a geometry it does not support.

    Examples
    --------
    A 32 mm cube of μ = 0.02 / mm in a grid of 2 mm voxels centred on the origin, seen from azimuth 0:

    >>> from ctsplat.geometry import pose_from_angles
    >>> mu = np.zeros((32, 32, 32), np.float32)
    >>> mu[8:24, 8:24, 8:24] = 0.02
    >>> affine = np.diag([2.0, 2.0, 2.0, 1.0])
    >>> affine[:3, 3] = -31.0
    >>> R, t = pose_from_angles(0.0, 0.0, [0.0, 0.0, 0.0], 100.0)
    >>> p = line_integrals(mu, affine, ParallelCamera(64, 64, 1.0), R[None], t[None])
    >>> p.shape, round(float(p.max()), 2)
    (torch.Size([1, 64, 64]), 0.64)
    """
    if not (0 < step_voxels <= 1.0):
        raise CtsplatError(f"step_voxels must be in (0, 1], got {step_voxels}")
    if device is None:
        device = mu.device if isinstance(mu, torch.Tensor) else torch.device("cpu")
    device = torch.device(device)
    mu_t = torch.as_tensor(mu, dtype=torch.float32).to(device)
    if mu_t.ndim != 3 or min(mu_t.shape) < 2:
        raise CtsplatError(f"volume must be 3D with at least 2 voxels per axis, got shape {tuple(mu_t.shape)}")
    shape = np.array(mu_t.shape, float)
    Rs = np.asarray(Rs, float).reshape(-1, 3, 3)
    ts = np.asarray(ts, float).reshape(-1, 3)
    if len(Rs) == 0:
        raise CtsplatError("empty view set: nothing to project")
    if len(Rs) != len(ts):
        raise CtsplatError(f"{len(Rs)} rotations but {len(ts)} translations: give one pose per view")
    A = np.asarray(affine, float)
    if A.shape != (4, 4) or not np.isfinite(A).all() or abs(np.linalg.det(A[:3, :3])) < 1e-12:
        raise CtsplatError(f"the volume's affine must be a finite, invertible 4 x 4 matrix, got {A.tolist()}")
    if method not in ("auto", "trilinear", "joseph"):
        raise CtsplatError(f"unknown projector method {method!r}; allowed: auto, trilinear, joseph")
    slice_axis = _slice_axis(camera, Rs, A)
    if method == "joseph" and slice_axis is None:
        raise CtsplatError("the joseph projector needs a parallel beam whose detector rows run along a voxel axis "
                           "(circular orbit at elevation 0); use method: trilinear")
    if method != "trilinear" and slice_axis is not None:
        return _joseph_slices(mu_t, A, camera, Rs, ts, slice_axis, batch_samples)
    Ainv = np.linalg.inv(A)
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    step_mm = step_voxels * float(spacing.min())
    lo, hi = np.full(3, -1.0), shape.copy()  # support of the trilinear interpolant, in index units
    if not mu_t.requires_grad:  # clip to the support of the non-zero voxels (no samples in empty margins)
        nonzero = mu_t != 0
        for axis in range(3):
            used = torch.nonzero(nonzero.any(dim=[a for a in range(3) if a != axis])).flatten()
            if used.numel() == 0:
                return torch.zeros(len(Rs), camera.height, camera.width, device=device)
            lo[axis], hi[axis] = float(used.min()) - 1.0, float(used.max()) + 1.0
    V, H, W = len(Rs), camera.height, camera.width
    vol = mu_t[None, None]  # (1, 1, D=I, H=J, W=K); grid_sample's (x, y, z) index (K, J, I)
    norm = torch.as_tensor(2.0 / (shape[::-1] - 1.0), dtype=torch.float32, device=device)  # (k, j, i) scale

    views_per_group = max(1, (1 << 20) // (H * W))  # bounds the host memory of the ray arrays
    images = []
    for g0 in range(0, V, views_per_group):
        pieces_idx, pieces_val = [], []
        # rays of this group of views in index space, clipped to the box
        o_g, d_g = [], []
        for R, t in zip(Rs[g0 : g0 + views_per_group], ts[g0 : g0 + views_per_group], strict=True):
            o, d = camera_rays(camera, R, t)
            o_g.append(o.reshape(-1, 3) @ Ainv[:3, :3].T + Ainv[:3, 3])
            d_g.append(d.reshape(-1, 3) @ Ainv[:3, :3].T)  # |d| = 1 mm in world -> s stays in mm
        o_all = np.concatenate(o_g)
        d_all = np.concatenate(d_g)
        s0_all, len_all = clip_rays_to_box(o_all, d_all, lo, hi)
        hit = np.flatnonzero(len_all > 0)  # pixel order: neighbouring rays sample neighbouring voxels
        n_all = np.maximum(np.ceil(len_all / step_mm), 1).astype(np.int64)  # samples per ray
        n_rays = max(1, batch_samples // int(n_all[hit].max())) if hit.size else 1
        for start in range(0, hit.size, n_rays):
            idx = hit[start : start + n_rays]
            n = int(n_all[idx].max())  # the longest ray of the chunk sets its sample count
            o = torch.as_tensor(o_all[idx], dtype=torch.float32, device=device)
            d = torch.as_tensor(d_all[idx], dtype=torch.float32, device=device)
            s0 = torch.as_tensor(s0_all[idx], dtype=torch.float32, device=device)
            h = torch.as_tensor(len_all[idx] / n_all[idx], dtype=torch.float32, device=device)
            n_ray = torch.as_tensor(n_all[idx], device=device)
            k = torch.arange(n, device=device)
            s = s0[:, None] + (k[None, :] + 0.5) * h[:, None]  # (R, n) mm
            # grid_sample coordinates (k, j, i) in [-1, 1]: o' + s d' with o', d' rescaled once per ray
            o_n = o.flip(-1) * norm - 1.0
            d_n = d.flip(-1) * norm
            grid = torch.addcmul(o_n[:, None, :], s[..., None], d_n[:, None, :])  # (R, n, 3)
            vals = torch.nn.functional.grid_sample(
                vol, grid[None, None], mode="bilinear", padding_mode="zeros", align_corners=True
            )[0, 0, 0]  # (R, n)
            vals = torch.where(k[None, :] < n_ray[:, None], vals, torch.zeros((), device=device))
            pieces_idx.append(torch.as_tensor(idx, device=device))
            pieces_val.append(vals.sum(-1) * h)
        group = torch.zeros(len(o_g) * H * W, dtype=torch.float32, device=device)
        if pieces_idx:
            group = group.index_put((torch.cat(pieces_idx),), torch.cat(pieces_val))
        images.append(group.reshape(len(o_g), H, W))
    return torch.cat(images)


def _slice_axis(camera: Camera, Rs: np.ndarray, A: np.ndarray) -> int | None:
    """The voxel axis ``c`` along which every detector column runs (parallel beam only), else ``None``.

    Needs ``y_cam = ±e_c`` in every view and ``e_c`` orthogonal to the other two voxel axes, so each
    detector row integrates within one plane ``index_c = const`` and ``index_c`` depends on the row only.
    """
    if camera.model != "parallel":
        return None
    E = A[:3, :3] / np.linalg.norm(A[:3, :3], axis=0)
    for c in range(3):
        others = [a for a in range(3) if a != c]
        if np.abs(E[:, others].T @ E[:, c]).max() > 1e-9:
            continue
        if np.abs(np.abs(Rs[:, 1] @ E[:, c]) - 1.0).max() < 1e-9:
            return c
    return None


def _joseph_slices(mu: torch.Tensor, A: np.ndarray, camera: Camera, Rs: np.ndarray, ts: np.ndarray, c: int,
                   batch_samples: int) -> torch.Tensor:
    """Joseph's (1982) projector, slice by slice, for parallel beams whose detector rows lie in voxel planes.

    Every ray of detector column ``u`` lies in the plane spanned by the other two voxel axes ``(p, q)``
    (in-plane ray ``o + s d``, ``s`` in mm). With ``a`` the axis along which the ray advances fastest
    (``|d_a|`` largest, in index units per mm), Joseph's method samples the ray where it crosses the
    voxel-centre lines ``index_a = m`` (``m = 0 .. N_a - 1``, ``s >= 0``), linearly interpolating across
    the other axis ``b``, and weights every sample by the path length per unit index, ``1 / |d_a|`` mm:

        P_k(u) = (1 / |d_a|) Σ_m [(1 - f) μ_k(m, ⌊β⌋) + f μ_k(m, ⌊β⌋ + 1)],
        β = o_b + (m - o_a) d_b / d_a,  f = β - ⌊β⌋,

    which integrates the bilinear interpolant exactly along axis-aligned rays. These weights form a
    sparse matrix (two entries per sample) applied to all slices at once: ``P = S @ μ[(p, q), k]``.
    A detector row ``v`` at slice coordinate ``k(v)`` gets the linear interpolation of ``P_k`` between
    the two nearest slices (zero beyond the support ``(-1, N_c)``), as trilinear interpolation does along
    such a ray. Differentiable in ``mu`` (sparse @ dense).
    """
    device = mu.device
    Ainv = np.linalg.inv(A)
    p_ax, q_ax = [a for a in range(3) if a != c]
    Nc, Np, Nq = (int(mu.shape[x]) for x in (c, p_ax, q_ax))
    vol = mu.permute(p_ax, q_ax, c).reshape(Np * Nq, Nc)  # rows: in-plane voxel (p, q), columns: slices
    V, W = len(Rs), camera.width
    per_batch = max(1, int(batch_samples // max(1, W * max(Np, Nq))))
    out = []
    for g0 in range(0, V, per_batch):
        r_idx, c_idx, w_all, rows = [], [], [], []
        batch = list(zip(Rs[g0 : g0 + per_batch], ts[g0 : g0 + per_batch], strict=True))
        for j, (R, t) in enumerate(batch):
            o, d = camera_rays(camera, R, t)
            o_idx = o @ Ainv[:3, :3].T + Ainv[:3, 3]  # (H, W, 3)
            d_idx = d[0, 0] @ Ainv[:3, :3].T
            o2 = o_idx[0][:, [p_ax, q_ax]]  # (W, 2) in-plane origins of the columns
            d2 = d_idx[[p_ax, q_ax]]
            a = int(np.argmax(np.abs(d2)))
            b = 1 - a
            n_a, n_b = (Np, Nq)[a], (Np, Nq)[b]
            m = np.arange(n_a, dtype=float)
            s = (m[None, :] - o2[:, a, None]) / d2[a]  # (W, n_a) mm along the ray
            beta = o2[:, b, None] + s * d2[b]
            b0 = np.floor(beta)
            f = beta - b0
            u = np.broadcast_to(np.arange(W)[:, None], s.shape)
            mm = np.broadcast_to(m[None, :], s.shape).astype(np.int64)
            for tap, wt in ((b0, 1.0 - f), (b0 + 1, f)):
                ok = (s >= 0) & (tap >= 0) & (tap < n_b) & (wt > 0)
                tb = tap[ok].astype(np.int64)
                flat = mm[ok] * Nq + tb if a == 0 else tb * Nq + mm[ok]
                r_idx.append(j * W + u[ok])
                c_idx.append(flat)
                w_all.append(wt[ok] / abs(d2[a]))
            rows.append(o_idx[:, 0, c])  # (H,) slice coordinate of each detector row
        S = torch.sparse_coo_tensor(
            torch.as_tensor(np.stack([np.concatenate(r_idx), np.concatenate(c_idx)]), device=device),
            torch.as_tensor(np.concatenate(w_all), dtype=torch.float32, device=device),
            size=(len(batch) * W, Np * Nq),
            check_invariants=False,
        )
        P = torch.sparse.mm(S, vol).reshape(len(batch), W, Nc)
        # rows: linear interpolation between slices, as a (H, Nc + 2) matrix per view over the slices
        # padded with zero planes at -1 and Nc (the support of the interpolant)
        P = torch.nn.functional.pad(P, (1, 1))  # (B, W, Nc + 2)
        Wk = np.zeros((len(batch), len(rows[0]), Nc + 2))
        for j, kc in enumerate(rows):
            inside = (kc > -1) & (kc < Nc)
            k0 = np.floor(kc[inside]).astype(np.int64) + 1  # padded index of the slice below
            f = kc[inside] - np.floor(kc[inside])
            rr = np.flatnonzero(inside)
            Wk[j, rr, k0] += 1.0 - f
            Wk[j, rr, k0 + 1] += f  # k0 + 1 <= Nc + 1 since kc < Nc
        out.append(torch.bmm(torch.as_tensor(Wk, dtype=torch.float32, device=device), P.transpose(1, 2)))
    return torch.cat(out)


NOISE_MODELS = ("physical", "tigre")
#: The largest photon count per pixel ``noise.i0`` may give.
MAX_I0 = 1e15


def check_noise(noise: dict[str, Any], key: str = "radiographs.noise") -> None:
    """Refuse noise settings out of range with one line naming the key (before any projection).

    Parameters
    ----------
    noise : dict
        The filled ``noise`` settings (:data:`RADIOGRAPHS_DEFAULTS`).
    key : str
        Where they sit in the config, for the message.

    Raises
    ------
    CtsplatError
        For a non-positive or non-finite ``i0``, a negative or non-finite ``electronic_sigma``, an unknown
        ``model``, or ``splits`` that is not a non-empty list of distinct split names.
    """
    from ctsplat.formats.viewset import SPLITS

    i0, sigma = noise.get("i0"), noise.get("electronic_sigma")
    if isinstance(i0, bool) or not isinstance(i0, int | float) or not (math.isfinite(i0) and i0 > 0):
        raise CtsplatError(f"{key}.i0 must be a positive number of photons per pixel, got {i0!r}")
    if noise.get("enabled") and i0 > MAX_I0:  # numpy's Poisson sampler stops near 1e18; no scanner counts 1e15
        raise CtsplatError(f"{key}.i0 must be at most {MAX_I0:.0e} photons per pixel, got {i0:g}; lower it (or set "
                           f"{key}.enabled: false for radiographs without noise)")
    if isinstance(sigma, bool) or not isinstance(sigma, int | float) or not (math.isfinite(sigma) and sigma >= 0):
        raise CtsplatError(f"{key}.electronic_sigma must be a number of counts >= 0, got {sigma!r}")
    if noise.get("model") not in NOISE_MODELS:
        raise CtsplatError(f"{key}.model must be one of {', '.join(NOISE_MODELS)}, got {noise.get('model')!r}")
    splits = noise.get("splits")
    if (not isinstance(splits, list | tuple) or not splits or len(set(splits)) != len(splits)
            or any(sp not in SPLITS for sp in splits)):
        raise CtsplatError(f"{key}.splits must be a non-empty list of distinct split names from "
                           f"{', '.join(SPLITS)}, got {splits!r}")


def add_noise(p: np.ndarray, i0: float, electronic_sigma: float, rng: np.random.Generator, *,
              model: str = "physical") -> tuple[np.ndarray, np.ndarray]:
    """Poisson photon noise with ``i0`` photons plus Gaussian electronic noise, back to line integrals.

    ``physical``: ``N = Poisson(i0 exp(-p)) + Normal(0, electronic_sigma)``, ``N <- max(N, 1)``,
    ``p_noisy = ln(i0 / N)`` (Beer–Lambert: the expected count behind a ray with line integral ``p`` is
    ``i0 exp(-p)``). ``tigre``: the same on ``p / s`` with ``s = max(p)`` and ``p_noisy = max(s ln(i0 / N), 0)``,
    as TIGRE's ``CTnoise.add`` followed by R²-Gaussian's clip of negative line integrals (module docstring); the
    one-photon floor keeps the log finite where TIGRE's would be inf/NaN.

    Parameters
    ----------
    p : ndarray, any shape
        Noise-free line integrals (dimensionless).
    i0 : float
        Unattenuated photon count per pixel, positive.
    electronic_sigma : float
        Standard deviation of the electronic noise (photon counts), >= 0.
    rng : numpy.random.Generator
        Source of the noise (seed it for reproducible radiographs).
    model : {"physical", "tigre"}
        How line integrals map to counts, see above.

    Returns
    -------
    p_noisy : ndarray, like ``p``, float32
        Noisy line integrals; at most ``s ln(i0)`` (one photon).
    counts : ndarray, like ``p``, float64
        Detected counts after clipping to >= 1.

    Raises
    ------
    CtsplatError
        For a non-positive or non-finite ``i0``, a negative ``electronic_sigma`` or an unknown ``model``.
    """
    if not (i0 > 0 and np.isfinite(i0)) or i0 > MAX_I0:
        raise CtsplatError(f"noise i0 (photons per pixel) must be positive and at most {MAX_I0:.0e}, got {i0}")
    if electronic_sigma < 0:
        raise CtsplatError(f"noise electronic_sigma must be >= 0, got {electronic_sigma}")
    if model not in NOISE_MODELS:
        raise CtsplatError(f"unknown noise model {model!r}; allowed: {', '.join(NOISE_MODELS)}")
    p64 = np.asarray(p, np.float64)
    scale = 1.0
    if model == "tigre":
        scale = float(p64.max()) if p64.size else 0.0
        if scale <= 0:  # nothing attenuates: TIGRE's 0/0; the noise-free zeros are the only consistent answer
            return np.zeros(p64.shape, np.float32), np.full(p64.shape, float(i0))
    expected = i0 * np.exp(-p64 / scale)
    counts = rng.poisson(expected).astype(np.float64)
    if electronic_sigma > 0:
        counts += rng.normal(0.0, electronic_sigma, size=counts.shape)
    counts = np.maximum(counts, 1.0)
    noisy = scale * np.log(i0 / counts)
    if model == "tigre":
        noisy = np.maximum(noisy, 0.0)
    return noisy.astype(np.float32), counts


# ------------------------------------------------------------------------------------- view sets
def fitted_pitch_mm(radius_mm: float, dso_mm: float, dsd_mm: float, detector_px: int, fov_margin: float = 1.0
                    ) -> float:
    """Cone-beam detector pitch (mm) at which a sphere of ``radius_mm`` about the isocentre fills the detector.

    The sphere's cone half-angle is ``asin(r / DSO)``; on the detector it spans ``DSD · tan(asin(r / DSO))`` to
    each side, so ``pitch = 2 DSD tan(asin(r / DSO)) · fov_margin / detector_px``. ``r / DSO`` is capped at
    0.99 so that a sphere reaching the source still gives a finite pitch.

    Parameters
    ----------
    radius_mm : float
        Radius of the object's bounding sphere (mm), e.g. :func:`ctsplat.geometry.support_radius_mm`.
    dso_mm, dsd_mm : float
        Source-to-isocentre and source-to-detector distances (mm).
    detector_px : int
        Pixels along the detector side the sphere must fit (the shorter side).
    fov_margin : float
        Factor > 1 leaves a margin around the sphere.

    Returns
    -------
    float
        Detector pitch (mm).
    """
    half = dsd_mm * math.tan(math.asin(min(radius_mm / dso_mm, 0.99)))
    return 2.0 * half * fov_margin / int(detector_px)


def build_view_set(volume: Any, config: dict[str, Any], seed: int = 0) -> ViewSet:
    """The camera and orbit described by a ``radiographs`` config section, for one volume.

    Fills the defaults of :data:`RADIOGRAPHS_DEFAULTS`: the isocentre is the volume's centre, a parallel
    detector starts its rays just outside the volume's bounding sphere. The detector spacing is
    ``pixel_spacing_mm``, or ``detector_size_factor · L / detector_width`` (``L`` the volume's largest extent), or
    for ``orbit: carm`` the pitch that fits the object's bounding sphere (:func:`fitted_pitch_mm`), or else one
    voxel (the largest edge) per pixel at the isocentre (cone: ``voxel · dsd / dso``), enlarged to the smallest
    spacing at which the object (voxels above 1 % of the maximum, as :func:`ctsplat.geometry.check_fov` counts it)
    lies on the detector in every view (:func:`ctsplat.geometry.covering_spacing_mm`), so the default never
    truncates the object; ``meta["pixel_spacing_source"]`` says which rule applied. Cone distances ``dso_mm`` /
    ``dsd_mm`` may be null: ``dso_factor · L`` / ``dsd_factor · L``. ``arc_deg`` defaults to 180 for parallel and
    360 for cone beams; ``n_val`` / ``n_test`` fix a circular orbit's held-out counts.

    Parameters
    ----------
    volume : ctsplat.formats.volume.Volume
        The volume (its grid, centre, id and, for ``carm``, its data).
    config : dict
        The ``radiographs`` section of one geometry (:data:`RADIOGRAPHS_DEFAULTS`).
    seed : int
        Seeds the orbit's random parts (held-out angles, sphere offsets, C-arm pose errors).

    Returns
    -------
    ViewSet
        Camera, views (``R``, ``t`` in mm, angles in degrees, split) and ``meta`` (orbit settings, seed,
        ``distance_mm``).

    Raises
    ------
    CtsplatError
        For unknown config keys or values, an isocentre that is not 3 numbers, non-positive distances, a
        parallel ray plane inside the volume, a C-arm orbit on a parallel camera, or a C-arm geometry with
        ``dsd_mm <= dso_mm`` or its source inside the object.

    Warns
    -----
    UserWarning
        When a cone-beam source lies inside the volume's bounding sphere.
    """
    cfg = merge_config("radiographs", config, RADIOGRAPHS_DEFAULTS)
    iso = np.asarray(cfg["isocenter_mm"] if cfg["isocenter_mm"] is not None else volume.center_mm(), float)
    if iso.shape != (3,):
        raise CtsplatError(f"isocenter_mm must be [x, y, z] in mm, got {cfg['isocenter_mm']!r}")
    check_orbit_settings(cfg)
    voxel = float(np.max(volume.spacing_mm))
    side = float(np.max(np.asarray(volume.shape, float) * np.asarray(volume.spacing_mm, float)))  # L (mm)
    corners = np.array([[a, b, c] for a in (-1, volume.shape[0]) for b in (-1, volume.shape[1])
                        for c in (-1, volume.shape[2])], float)
    corners_mm = corners @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    radius = float(np.linalg.norm(corners_mm - iso, axis=1).max())
    W, H = cfg["detector_width"], cfg["detector_height"]
    size_factor = cfg["detector_size_factor"]
    if size_factor is not None and not (isinstance(size_factor, int | float) and size_factor > 0):
        raise CtsplatError(f"radiographs.detector_size_factor must be a positive number (detector width in volume "
                           f"sides) or null, got {size_factor!r}")
    dso = dsd = object_radius = 0.0
    if cfg["camera"] == "parallel":
        distance = (radius * 1.05 + 1.0) if cfg["parallel_distance_mm"] is None else float(cfg["parallel_distance_mm"])
        if distance <= radius:
            raise CtsplatError(f"parallel_distance_mm {distance} must exceed the volume's radius {radius:.1f} mm "
                               "(rays start on the plane z_cam = 0)")
    elif cfg["camera"] == "cone":
        for name in ("dso", "dsd"):
            factor = cfg[f"{name}_factor"]
            if cfg[f"{name}_mm"] is None and not (isinstance(factor, int | float) and factor > 0):
                raise CtsplatError(f"radiographs.{name}_factor must be a positive number (volume sides) when "
                                   f"{name}_mm is null, got {factor!r}")
        dso = float(cfg["dso_mm"]) if cfg["dso_mm"] is not None else float(cfg["dso_factor"]) * side
        dsd = float(cfg["dsd_mm"]) if cfg["dsd_mm"] is not None else float(cfg["dsd_factor"]) * side
        for name, val in (("dso_mm", dso), ("dsd_mm", dsd)):
            if not val > 0:
                raise CtsplatError(f"{name} must be a positive distance in mm, got {val}")
        if dsd <= dso:  # checked before any warning below, so a bad geometry fails in one line
            raise CtsplatError(f"dsd_mm ({dsd}) must be larger than dso_mm ({dso}): the detector lies beyond the "
                               "isocentre")
        # every orbit: a source inside the object cannot image it (the rays start behind part of it)
        object_radius = support_radius_mm(volume.data, volume.affine, iso)
        if object_radius >= dso:
            raise CtsplatError(f"dso_mm ({dso:.1f}) must exceed the object's radius ({object_radius:.0f} mm about the "
                               "isocentre): the source would sit inside the object; raise dso_mm (and dsd_mm)")
        distance = dso
        if dso <= radius:
            warnings.warn(f"dso_mm {dso} puts the source inside the volume's bounding sphere (radius "
                          f"{radius:.1f} mm); part of the volume lies behind the source", stacklevel=2)
    arc = cfg["arc_deg"]
    if cfg["orbit"] == "circular":
        if arc is None:
            arc = 180.0 if cfg["camera"] == "parallel" else 360.0
        views = circular_orbit(cfg["n_views"], iso, distance, split_fractions=cfg["split"],
                               wobble_deg=float(cfg["wobble_deg"]), start_deg=float(cfg["start_deg"]), seed=seed,
                               arc_deg=float(arc), wobble_cycles=float(cfg["wobble_cycles"]),
                               heldout_counts={"val": cfg["n_val"], "test": cfg["n_test"]})
    elif cfg["orbit"] == "sphere":
        views = sphere_orbit(cfg["n_views"], iso, distance, elevation_range_deg=cfg["elevation_range_deg"],
                             sampling=cfg["sphere_sampling"], split_fractions=cfg["split"], seed=seed)
    else:
        arc = 360.0 if arc is None else arc
        views = carm_orbit(cfg["n_views"], iso, distance, arc_deg=float(arc), start_deg=float(cfg["start_deg"]),
                           wobble_deg=float(cfg["wobble_deg"]), wobble_cycles=float(cfg["wobble_cycles"]),
                           jitter_deg=float(cfg["orbit_jitter_deg"]), jitter_mm=float(cfg["orbit_jitter_mm"]),
                           seed=seed)
    # the detector spacing: explicit, in volume sides, fitted (C-arm) or one voxel enlarged to cover the object
    if cfg["pixel_spacing_mm"] is not None:
        spacing, source = float(cfg["pixel_spacing_mm"]), "pixel_spacing_mm"
    elif size_factor is not None:
        spacing, source = float(size_factor) * side / W, "detector_size_factor"
    elif cfg["orbit"] == "carm":
        spacing, source = fitted_pitch_mm(object_radius, dso, dsd, min(W, H), float(cfg["fov_margin"])), "carm_fit"
    else:
        one_voxel = voxel if cfg["camera"] == "parallel" else voxel * dsd / dso
        probe: Camera = ParallelCamera(W, H, 1.0) if cfg["camera"] == "parallel" else ConeCamera(W, H, 1.0, dso, dsd)
        Rs = np.stack([v.R for v in views])
        ts = np.stack([v.t for v in views])
        cover = covering_spacing_mm(probe, Rs, ts, object_points_mm(volume.data, volume.affine))
        spacing, source = max(one_voxel, cover), ("one_voxel" if one_voxel >= cover else "covers_object")
    camera: Camera = ParallelCamera(W, H, spacing) if cfg["camera"] == "parallel" else ConeCamera(W, H, spacing,
                                                                                                   dso, dsd)
    meta = {"orbit": cfg["orbit"], "n_views": int(cfg["n_views"]), "wobble_deg": float(cfg["wobble_deg"]),
            "wobble_cycles": float(cfg["wobble_cycles"]), "arc_deg": float(arc) if arc is not None else None,
            "elevation_range_deg": list(cfg["elevation_range_deg"]), "sphere_sampling": cfg["sphere_sampling"],
            "split": dict(cfg["split"]), "seed": int(seed), "distance_mm": distance, "volume_side_mm": side,
            "pixel_spacing_source": source}
    return ViewSet(camera, views, volume.volume_id, iso, meta)


# ------------------------------------------------------------------------------------------ step
def render_radiographs(volume_path: str | Path, out_dir: str | Path, config: dict[str, Any] | None = None,
                       seed: int = 0) -> ViewSet:
    """Render the synthetic radiographs of a volume and write them to ``out_dir``.

    Writes ``line_integrals.tif`` (float32 pages [V, H, W], line integrals of μ in 1/mm = volume data ×
    ``mu_scale_per_mm``, noisy when noise is enabled — the training target), ``views.json`` (the
    :class:`~ctsplat.geometry.ViewSet`, page order), ``png/view_{id:04d}.png`` (16-bit transmission
    ``exp(-p)``) and ``radiographs.json`` (provenance: config, seed, code version, volume id, field-of-view
    check, statistics, timing). Every file is written under a temporary name first.

    Parameters
    ----------
    volume_path : str or Path
        An ingested volume (NIfTI with ctsplat metadata).
    out_dir : str or Path
        Output folder (created).
    config : dict, optional
        The ``radiographs`` section of one geometry (:data:`RADIOGRAPHS_DEFAULTS`).
    seed : int
        Seeds the orbit and the noise.

    Returns
    -------
    ViewSet
        The view set written to ``views.json``.

    Raises
    ------
    CtsplatError
        For a volume with non-finite voxels, noise settings out of range (:func:`check_noise`), an invalid config
        (see :func:`build_view_set`), or an explicit detector (``pixel_spacing_mm`` / ``detector_size_factor``)
        that does not cover the object without ``allow_truncation: true``; nothing is written.

    Warns
    -----
    UserWarning
        When the detector does not cover the object (:func:`ctsplat.geometry.check_fov`) and that is allowed.
    """

    from ctsplat.formats.volume import check_attenuation, load_volume

    cfg = merge_config("radiographs", config, RADIOGRAPHS_DEFAULTS)
    check_noise(cfg["noise"])
    out_dir = Path(out_dir)
    check_radiograph_targets(out_dir)  # before the projection, not after it
    volume = load_volume(volume_path)
    bad = int(np.size(volume.data) - np.count_nonzero(np.isfinite(volume.data)))
    if bad:
        raise CtsplatError(f"volume {volume_path} has {bad} non-finite voxels (NaN/Inf); re-ingest it (ingest names "
                           "where they are, or fills them with nonfinite: fill_min)")
    check_attenuation(volume, volume_path)
    view_set = build_view_set(volume, cfg, seed)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fov_outside = check_fov(view_set.camera, view_set.Rs(), view_set.ts(), volume.data, volume.affine)
    source = view_set.meta.get("pixel_spacing_source")
    if fov_outside > 0 and source in ("pixel_spacing_mm", "detector_size_factor") and not cfg["allow_truncation"]:
        raise CtsplatError(
            f"radiographs.{source}: the detector ({view_set.camera.width} x {view_set.camera.height} px) leaves "
            f"{100 * fov_outside:.1f}% of the object outside the field of view in the worst view; enlarge it "
            f"(or set {source} to null to fit it), or set allow_truncation: true to accept a truncated scan")
    for w in caught:  # re-raised after the refusal above; the CLI and the workflow log warnings (captureWarnings)
        warnings.warn(w.message, stacklevel=2)
    device = resolve_device(cfg["device"])
    mu = torch.as_tensor(volume.data, dtype=torch.float32) * volume.mu_scale_per_mm
    t0 = time.perf_counter()
    with torch.no_grad():
        p = line_integrals(mu, volume.affine, view_set.camera, view_set.Rs(), view_set.ts(),
                           step_voxels=float(cfg["step_voxels"]), device=device,
                           batch_samples=int(cfg["batch_samples"])).cpu().numpy()
    seconds = time.perf_counter() - t0
    noise = cfg["noise"]
    if noise["enabled"]:
        rows = np.concatenate([view_set.indices(sp) for sp in noise["splits"]]).astype(int)
        rows.sort()
        if rows.size:
            rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x6E6F697365]))
            p[rows], _ = add_noise(p[rows], float(noise["i0"]), float(noise["electronic_sigma"]), rng,
                                   model=noise["model"])
        view_set.meta["noise"] = {"enabled": True, "model": noise["model"], "i0": float(noise["i0"]),
                                  "electronic_sigma": float(noise["electronic_sigma"]),
                                  "splits": list(noise["splits"]), "noisy_view_ids": [view_set.views[i].id
                                                                                      for i in rows]}
    else:
        view_set.meta["noise"] = {"enabled": False}
    p = np.ascontiguousarray(p, dtype=np.float32)

    write_radiographs(out_dir, p, view_set, {
        "config": cfg, "seed": int(seed), "code_version": code_version(), "volume_path": str(volume_path),
        "volume_id": volume.volume_id, "mu_scale_per_mm": volume.mu_scale_per_mm,
        "fov_outside_fraction_worst_view": fov_outside, "projection_seconds": seconds, "device": str(device),
    })
    log.info("rendered %d views of %s in %.1f s -> %s", len(view_set), volume.volume_id, seconds, out_dir)
    return view_set
