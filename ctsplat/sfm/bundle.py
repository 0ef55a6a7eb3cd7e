"""Isocentric bundle adjustment: camera poses constrained to a C-arm's rigid source-isocentre geometry.

A C-arm (or any gantry) carries the source and detector rigidly: the camera centre sits at the source-to-
isocentre distance ``DSO`` from the isocentre and the principal ray passes through it. A view's pose then has
three degrees of freedom (a rotation ``R`` about the isocentre), not six:

``x_cam = R (X - iso) + (0, 0, DSO) + s``,  i.e. ``t = -R iso + (0, 0, DSO) + s``,

with ``s`` (camera frame, mm) the view's isocentre offset: zero for the rigid model (``isocentre_sigma_mm=0``)
or a free offset with the prior ``N(0, σ_iso² I)`` (a gantry that sags). Free six-DoF bundle adjustment on
radiographs of anatomy trades a camera shift against a tilt (features of overlapping structures are not
fixed 3D points), which bends the orbit; the constraint removes that trade.

The solver minimises

``E = Σ_obs c² log(1 + |π(x_cam) - x_obs|² / c²) + Σ_i |log(R_i R_design_iᵀ)|² / σ_d² + Σ_i |s_i|² / σ_iso²``

(Cauchy loss of scale ``c`` px on the reprojection error; a Gaussian prior of ``σ_d`` per axis on each view's
deviation from its designed rotation) by Levenberg-Marquardt on iteratively reweighted normal equations. Points
are eliminated per point (3×3 blocks, Schur complement), leaving a dense ``(nc V)²`` camera system
(``nc`` = 3, or 6 with the offsets). Rotations update on the left: ``R ← exp([δ]×) R``, so with
``Y = R (X - iso)``: ``∂x_cam/∂δ = -[Y]×``, ``∂x_cam/∂X = R``, ``∂x_cam/∂s = I``, and
``∂π/∂x_cam = [[fx/z, 0, -fx x/z²], [0, fy/z, -fy y/z²]]``.

pycolmap's bundle adjusters refine six-DoF poses (position priors only), so this one is hand-written;
:func:`reprojection_jacobians` is checked against finite differences in the tests.

References
----------
Triggs, B., McLauchlan, P. F., Hartley, R. I., Fitzgibbon, A. W. (2000). Bundle adjustment — a modern synthesis.
In Vision Algorithms: Theory and Practice, LNCS 1883, 298-372. Springer. (Levenberg-Marquardt on the normal
equations, Schur complement of the points, robust (Cauchy) costs by iterative reweighting.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ctsplat.geometry import camera_center
from ctsplat.utils import CtsplatError

__all__ = ["IsocentricResult", "isocentre_from_poses", "isocentric_poses", "reprojection_jacobians",
           "isocentric_bundle_adjustment"]


@dataclass
class IsocentricResult:
    """Output of :func:`isocentric_bundle_adjustment` (world -> camera, OpenCV/COLMAP convention).

    Parameters
    ----------
    Rs : ndarray, shape (V, 3, 3)
        Adjusted world->camera rotations.
    ts : ndarray, shape (V, 3)
        The matching translations ``-R iso + (0, 0, DSO) + s`` (mm).
    points : ndarray, shape (N, 3)
        Adjusted points (world mm).
    offsets_mm : ndarray, shape (V, 3)
        Isocentre offsets ``s`` (camera frame, mm); zeros for the rigid model.
    iterations : int
        Levenberg-Marquardt iterations run.
    cost_initial, cost_final : float
        The energy ``E`` (px², plus the prior terms) before and after.
    reproj_err_px_median : float
        Median reprojection error (px) over the observations in front of their camera.
    """

    Rs: np.ndarray
    ts: np.ndarray
    points: np.ndarray
    offsets_mm: np.ndarray
    iterations: int
    cost_initial: float
    cost_final: float
    reproj_err_px_median: float


def isocentre_from_poses(Rs: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, float]:
    """The point nearest to every principal ray (least squares) and the median camera distance to it.

    For a designed orbit whose cameras look at the isocentre this returns ``(iso, DSO)`` exactly.

    Parameters
    ----------
    Rs : ndarray, shape (V, 3, 3)
        World->camera rotations.
    ts : ndarray, shape (V, 3)
        World->camera translations (mm).

    Returns
    -------
    iso : ndarray, shape (3,)
        Minimiser of the summed squared distances to the principal rays (world mm).
    dso_mm : float
        Median distance of the camera centres from ``iso`` (mm).

    Raises
    ------
    CtsplatError
        When the principal rays are (nearly) parallel, so no point is nearest to all of them.
    """
    Rs, ts = np.asarray(Rs, float), np.asarray(ts, float)
    centres = camera_center(Rs, ts)
    d = Rs[:, 2, :]  # principal ray directions (world)
    P = np.eye(3) - np.einsum("vi,vj->vij", d, d)  # projectors orthogonal to each ray
    A, b = P.sum(0), np.einsum("vij,vj->i", P, centres)
    if np.linalg.cond(A) > 1e10:
        raise CtsplatError("the principal rays are (nearly) parallel: no isocentre; use a designed orbit")
    iso = np.linalg.solve(A, b)
    return iso, float(np.median(np.linalg.norm(centres - iso, axis=1)))


def isocentric_poses(Rs: np.ndarray, iso: np.ndarray, dso_mm: float, offsets_mm: np.ndarray | None = None
                     ) -> np.ndarray:
    """Translations ``t_i = -R_i iso + (0, 0, DSO) + s_i`` of isocentric cameras with rotations ``Rs``.

    Parameters
    ----------
    Rs : ndarray, shape (V, 3, 3)
        World->camera rotations.
    iso : ndarray, shape (3,)
        Isocentre (world mm).
    dso_mm : float
        Source-to-isocentre distance (mm).
    offsets_mm : ndarray, shape (V, 3), optional
        Isocentre offsets ``s_i`` (camera frame, mm); default none.

    Returns
    -------
    ndarray, shape (V, 3)
        World->camera translations (mm).
    """
    t = -np.einsum("vij,j->vi", np.asarray(Rs, float), np.asarray(iso, float)) + np.array([0.0, 0.0, dso_mm])
    return t if offsets_mm is None else t + offsets_mm


def _skew(a: np.ndarray) -> np.ndarray:
    """``[a]×`` for a batch (..., 3) -> (..., 3, 3)."""
    z = np.zeros(a.shape[:-1])
    return np.stack([np.stack([z, -a[..., 2], a[..., 1]], -1), np.stack([a[..., 2], z, -a[..., 0]], -1),
                     np.stack([-a[..., 1], a[..., 0], z], -1)], -2)


def reprojection_jacobians(Rs: np.ndarray, points: np.ndarray, offsets_mm: np.ndarray, obs_view: np.ndarray,
                           obs_point: np.ndarray, obs_xy: np.ndarray, intrinsics: tuple[float, float, float, float],
                           iso: np.ndarray, dso_mm: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reprojection residuals of isocentric cameras and their Jacobians, per observation.

    Parameters
    ----------
    Rs : ndarray, shape (V, 3, 3)
        World->camera rotations.
    points : ndarray, shape (N, 3)
        Points (world mm).
    offsets_mm : ndarray, shape (V, 3)
        Isocentre offsets ``s`` (camera frame, mm).
    obs_view, obs_point : ndarray of int, shape (M,)
        View and point of each observation.
    obs_xy : ndarray, shape (M, 2)
        Observed keypoints (px).
    intrinsics : tuple of float
        ``(fx, fy, cx, cy)`` in px.
    iso : ndarray, shape (3,)
        Isocentre (world mm).
    dso_mm : float
        Source-to-isocentre distance (mm).

    Returns
    -------
    r : ndarray, shape (M, 2)
        Residuals ``π(x_cam) - x_obs`` (px).
    J_rot : ndarray, shape (M, 2, 3)
        Jacobian w.r.t. the left rotation increment δ (``R ← exp([δ]×) R``), px per radian.
    J_off : ndarray, shape (M, 2, 3)
        Jacobian w.r.t. the view's isocentre offset ``s``, px per mm.
    J_pt : ndarray, shape (M, 2, 3)
        Jacobian w.r.t. the point, px per mm.
    depth : ndarray, shape (M,)
        Camera-frame ``z`` of each observation (mm); residuals use ``1e-9`` where ``|z| <= 1e-9``.
    """
    fx, fy, cx, cy = intrinsics
    Y = np.einsum("mij,mj->mi", Rs[obs_view], points[obs_point] - iso)
    xc = Y + np.array([0.0, 0.0, dso_mm]) + offsets_mm[obs_view]
    z = xc[:, 2]
    zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
    r = np.stack([fx * xc[:, 0] / zs + cx, fy * xc[:, 1] / zs + cy], 1) - obs_xy
    Jp = np.zeros((len(z), 2, 3))
    Jp[:, 0, 0], Jp[:, 0, 2] = fx / zs, -fx * xc[:, 0] / zs**2
    Jp[:, 1, 1], Jp[:, 1, 2] = fy / zs, -fy * xc[:, 1] / zs**2
    return r, -Jp @ _skew(Y), Jp, Jp @ Rs[obs_view], z


def _scatter_sum(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """``out[k] = Σ_{index[m] = k} values[m]`` for values (M, ...) -> (n, ...) (``np.bincount`` per component;
    several times faster than ``np.add.at``)."""
    flat = values.reshape(len(values), -1)
    out = np.stack([np.bincount(index, weights=flat[:, c], minlength=n) for c in range(flat.shape[1])], 1)
    return out.reshape((n, *values.shape[1:]))


def _track_pairs(obs_point: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """All ordered pairs (a, b) of observations of the same point (the Schur complement's fill pattern)."""
    order = np.argsort(obs_point, kind="stable")
    L = np.bincount(obs_point, minlength=n_points)
    start = np.concatenate([[0], np.cumsum(L)[:-1]])
    sq = L**2
    owner = np.repeat(np.arange(n_points), sq)
    k = np.arange(int(sq.sum())) - np.repeat(np.cumsum(sq) - sq, sq)
    a = start[owner] + k // L[owner]
    b = start[owner] + k % L[owner]
    return order[a], order[b]


def isocentric_bundle_adjustment(Rs_init: np.ndarray, points_init: np.ndarray, obs_view: np.ndarray,
                                 obs_point: np.ndarray, obs_xy: np.ndarray,
                                 intrinsics: tuple[float, float, float, float], iso: np.ndarray, dso_mm: float, *,
                                 design_Rs: np.ndarray | None = None, design_sigma_deg: float | None = None,
                                 isocentre_sigma_mm: float = 0.0, loss_scale_px: float = 0.5,
                                 max_iterations: int = 50, tolerance: float = 1e-8) -> IsocentricResult:
    """Bundle-adjust isocentric cameras (rotations about ``iso`` at distance ``dso_mm``) and 3D points.

    Parameters
    ----------
    Rs_init : ndarray, shape (V, 3, 3)
        Initial rotations (world -> camera); the initial translations follow from them.
    points_init : ndarray, shape (N, 3)
        Initial points (world mm).
    obs_view, obs_point : ndarray of int, shape (M,)
        The view and point of each observation (each point seen at least twice).
    obs_xy : ndarray, shape (M, 2)
        Observed keypoints (px; COLMAP pixel convention: pixel centres at +0.5).
    intrinsics : tuple of float
        ``(fx, fy, cx, cy)`` in px, held fixed.
    iso : ndarray, shape (3,)
        Isocentre (world mm).
    dso_mm : float
        Source-to-isocentre distance (mm), positive.
    design_Rs : ndarray, shape (V, 3, 3), optional
        Designed rotations, the centre of the rotation prior. Without ``design_Rs`` and ``design_sigma_deg`` the
        solution is defined up to a rotation about ``iso`` (gauge).
    design_sigma_deg : float, optional
        Prior standard deviation ``σ_d`` (degrees, per axis) of each view's rotation about its designed one.
    isocentre_sigma_mm : float
        0 for the rigid model; > 0 frees a per-view offset with this prior standard deviation (mm).
    loss_scale_px : float
        Cauchy scale ``c`` (px) of the reprojection loss, positive.
    max_iterations : int
        Most Levenberg-Marquardt iterations.
    tolerance : float
        Stop when an accepted step decreases the cost by less than this fraction.

    Returns
    -------
    IsocentricResult
        Adjusted poses, points and offsets with the costs and the median reprojection error.

    Raises
    ------
    CtsplatError
        For arrays of inconsistent shapes, observations that index missing views or points (or none), a point
        seen fewer than twice, a non-positive ``loss_scale_px`` or ``dso_mm``, a negative ``isocentre_sigma_mm``,
        or a ``design_Rs`` of the wrong shape or non-positive ``design_sigma_deg``.
    """
    Rs = np.array(Rs_init, float)
    X = np.array(points_init, float)
    ov, op = np.asarray(obs_view, np.int64), np.asarray(obs_point, np.int64)
    oxy = np.asarray(obs_xy, float)
    V, N, M = len(Rs), len(X), len(ov)
    if Rs.shape != (V, 3, 3) or X.shape != (N, 3) or op.shape != (M,) or oxy.shape != (M, 2):
        raise CtsplatError("isocentric BA: expected Rs (V,3,3), points (N,3), obs_view/obs_point (M,), obs_xy (M,2)")
    if M == 0 or ov.min() < 0 or ov.max() >= V or op.min() < 0 or op.max() >= N:
        raise CtsplatError("isocentric BA: observations must index existing views and points (and be non-empty)")
    if np.bincount(op, minlength=N).min() < 2:
        raise CtsplatError("isocentric BA: every point needs at least two observations")
    if not (loss_scale_px > 0 and dso_mm > 0 and isocentre_sigma_mm >= 0):
        raise CtsplatError("isocentric BA: loss_scale_px and dso_mm must be > 0, isocentre_sigma_mm >= 0")
    use_prior = design_Rs is not None and design_sigma_deg is not None
    if use_prior:
        design_Rs = np.asarray(design_Rs, float)
        if design_Rs.shape != (V, 3, 3) or not design_sigma_deg > 0:
            raise CtsplatError("isocentric BA: design_Rs must be (V,3,3) and design_sigma_deg > 0")
        w_prior = 1.0 / np.radians(design_sigma_deg) ** 2
    soft = isocentre_sigma_mm > 0
    nc = 6 if soft else 3
    s = np.zeros((V, 3))
    iso = np.asarray(iso, float)
    c2 = loss_scale_px**2
    pa, pb = _track_pairs(op, N)
    eye_c, eye3 = np.eye(nc), np.eye(3)

    def design_dev(R: np.ndarray) -> np.ndarray:
        return Rotation.from_matrix(R @ design_Rs.transpose(0, 2, 1)).as_rotvec()

    def evaluate(R: np.ndarray, X: np.ndarray, s: np.ndarray) -> tuple[float, tuple, np.ndarray | None]:
        """Cost, residuals + Jacobians (reused by the next step once accepted), deviation from the design."""
        terms = reprojection_jacobians(R, X, s, ov, op, oxy, intrinsics, iso, dso_mm)
        r, z = terms[0], terms[-1]
        e = c2 * np.log1p((r**2).sum(1) / c2)
        c = float(np.where(z > 0, e, 1e6).sum())  # a point behind its camera costs more than any residual
        dev = design_dev(R) if use_prior else None
        if use_prior:
            c += w_prior * float((dev**2).sum())
        if soft:
            c += float((s**2).sum()) / isocentre_sigma_mm**2
        return c, terms, dev

    cur, terms, dev = evaluate(Rs, X, s)
    cost0 = cur
    lam, it = 1e-3, 0
    while it < max_iterations:
        it += 1
        r, Jr, Js, Jx, z = terms
        w = np.where(z > 0, 1.0 / (1.0 + (r**2).sum(1) / c2), 0.0)  # IRLS weights of the Cauchy loss
        Jc = np.concatenate([Jr, Js], 2) if soft else Jr
        WJc, WJx = Jc * w[:, None, None], Jx * w[:, None, None]
        Hcc = _scatter_sum(ov, np.einsum("mki,mkj->mij", WJc, Jc), V)
        Hpp = _scatter_sum(op, np.einsum("mki,mkj->mij", WJx, Jx), N)
        Hcp = np.einsum("mki,mkj->mij", WJc, Jx)
        gc = _scatter_sum(ov, np.einsum("mki,mk->mi", WJc, r), V)
        gx = _scatter_sum(op, np.einsum("mki,mk->mi", WJx, r), N)
        if use_prior:  # d log(exp(δ) R R_dᵀ)/dδ ≈ I near the design
            Hcc[:, [0, 1, 2], [0, 1, 2]] += w_prior
            gc[:, :3] += w_prior * dev
        if soft:
            Hcc[:, [3, 4, 5], [3, 4, 5]] += 1.0 / isocentre_sigma_mm**2
            gc[:, 3:] += s / isocentre_sigma_mm**2
        accepted = False
        while lam <= 1e8:
            Hc = Hcc + lam * np.einsum("vii->vi", Hcc)[:, :, None] * eye_c
            Hp = Hpp + (lam * np.einsum("nii->ni", Hpp) + 1e-9)[:, :, None] * eye3
            Pinv = np.linalg.inv(Hp)
            T = np.einsum("mij,mjk->mik", Hcp, Pinv[op])  # Hcp Hpp⁻¹ per observation
            Sb = -_scatter_sum(ov[pa] * V + ov[pb], np.einsum("pij,pkj->pik", T[pa], Hcp[pb]), V * V)
            Sb = Sb.reshape(V, V, nc, nc)
            Sb[np.arange(V), np.arange(V)] += Hc
            bc = gc - _scatter_sum(ov, np.einsum("mij,mj->mi", Hcp, np.einsum("nij,nj->ni", Pinv, gx)[op]), V)
            try:
                dc = -np.linalg.solve(Sb.transpose(0, 2, 1, 3).reshape(V * nc, V * nc), bc.ravel()).reshape(V, nc)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            back = _scatter_sum(op, np.einsum("mij,mi->mj", Hcp, dc[ov]), N)
            dX = -np.einsum("nij,nj->ni", Pinv, gx + back)
            R_new = Rotation.from_rotvec(dc[:, :3]).as_matrix() @ Rs
            s_new = s + dc[:, 3:] if soft else s
            new, new_terms, new_dev = evaluate(R_new, X + dX, s_new)
            if new < cur:
                accepted = True
                rel = (cur - new) / max(cur, 1e-300)
                Rs, X, s, cur, terms, dev = R_new, X + dX, s_new, new, new_terms, new_dev
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 4.0
        if not accepted or rel < tolerance:
            break
    r, z = terms[0], terms[-1]
    front = z > 0
    med = float(np.median(np.linalg.norm(r[front], axis=1))) if front.any() else float("nan")
    return IsocentricResult(Rs=Rs, ts=isocentric_poses(Rs, iso, dso_mm, s), points=X, offsets_mm=s, iterations=it,
                            cost_initial=cost0, cost_final=cur, reproj_err_px_median=med)
