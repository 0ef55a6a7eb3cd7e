r"""Joint pose–density refinement: per-view rigid corrections of the training cameras, optimised with the Gaussians.

Parametrisation (one model for both detectors)
----------------------------------------------
View ``i`` has a recorded world-to-camera pose ``x_cam = R x + t`` (OpenCV) and the designed isocentre ``p``
(world mm), seen at ``c = R p + t`` in the camera frame. Its correction ``(ω, τ)`` (``ω`` an axis-angle vector in
the *camera* frame, radians; ``τ`` mm) turns the camera about the isocentre and shifts it::

    x_cam' = ΔR (x_cam - c) + c + τ,    ΔR = exp([ω]×)
    R' = ΔR R,    t' = ΔR (t - c) + c + τ

- ``parallel`` beam: 3 rotation DoF and the 2 in-plane detector shifts (``τ_z = 0``: a shift along the rays
  changes nothing in a parallel projection, so it is not a parameter);
- ``cone`` beam, ``cone_model="rigid"``: the full rigid correction (6 DoF) about the designed isocentre. A C-arm
  that turns about a wobbling isocentre is a special case; the full model also absorbs source-distance errors.
- ``cone`` beam, ``cone_model="carm"``: the C-arm model of the isocentric bundle adjustment: the camera turns about
  the designed isocentre at the designed source distance (3 rotations and the 2 detector-plane shifts, ``τ_z = 0``
  as for parallel beam). A shift along the central ray only magnifies a cone-beam image by ``τ_z / DSO``, which the
  radiographs constrain weakly; fixing it removes that poorly determined direction.

Equivalent transform of the Gaussians (how gradients reach the pose)
--------------------------------------------------------------------
Rendering with ``(R', t')`` gives the same camera-frame Gaussians as rendering, with the *recorded* ``(R, t)``,
Gaussians moved by the world-frame rigid motion ``x -> W (x - p) + p + Rᵀ τ`` with ``W = Rᵀ ΔR R = exp([Rᵀ ω]×)``:
``R (W (m - p) + p + Rᵀτ) + t = ΔR R (m - p) + c + τ = ΔR (R m + t - c) + c + τ``. So means become
``W (m - p) + p + Rᵀ τ``, quaternions are left-multiplied by the quaternion of ``W`` (covariances ``W Σ Wᵀ``) and
scales and densities are unchanged. Every renderer backend is differentiable with respect to means and quaternions,
so autograd gives the gradient with respect to ``(ω, τ)`` through any backend without pose derivatives in the
kernels (tested against finite differences in ``tests/unit/test_pose_refine.py``).

Prior and gauge
---------------
The corrections have a Gaussian prior toward zero, ``½ w (|ω|²/σ_rot² + |τ|²/σ_trans²)`` per view
(:meth:`PoseCorrection.prior`). A rigid motion of *all* cameras together with the model leaves every image
unchanged, so the mean correction is unobservable: a world rotation ``Ω`` about the isocentre appears in view ``i``
as ``ω_i = R_i Ω`` and a world shift ``T`` as ``τ_i = P R_i T`` (``P`` drops the ray component for parallel beam).
Left free it drifts with the model and the model ends up off the frame of the held-out poses; after every step
:meth:`PoseCorrection.fix_gauge` removes the least-squares fit of that motion (for ``ω``: the mean of ``R_iᵀ ω_i``),
so the corrections have no common part and the model stays in the frame of the training poses *on average*. The
held-out (validation, test) views are not refined: they are scored at their recorded poses in that frame.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ctsplat.splat.gaussians import quat_to_rotmat
from ctsplat.training.config import CONE_POSE_MODELS, refine_enabled
from ctsplat.utils import CtsplatError

__all__ = ["rotvec_to_quat", "quat_mul", "correct_pose", "transform_gaussians", "PoseCorrection",
           "pose_errors", "rotation_angles_deg", "common_rotation", "gauge_motion", "perturb_poses", "pose_source",
           "refine_enabled"]


def pose_source(poses: str) -> str:
    """The pose source of a ``poses`` value: ``gt``, ``perturbed`` or ``colmap`` (``+refine`` dropped).

    Parameters
    ----------
    poses : str
        A ``train.poses`` value, e.g. ``"colmap+refine"``.

    Returns
    -------
    str

    Examples
    --------
    >>> pose_source("perturbed+refine")
    'perturbed'
    """
    return str(poses).removesuffix("+refine")


# ------------------------------------------------------------------------------------------- rotations
def rotvec_to_quat(w: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(w, x, y, z)`` of axis-angle vectors, smooth (and differentiable) at zero.

    Parameters
    ----------
    w : Tensor (..., 3)
        Axis × angle (radians).

    Returns
    -------
    Tensor (..., 4)
    """
    theta = torch.sqrt((w * w).sum(-1, keepdim=True) + 1e-30)
    half = 0.5 * theta
    # sin(θ/2)/θ = ½ sinc(θ/2π) with torch's normalised sinc: finite, smooth at θ = 0
    return torch.cat([torch.cos(half), 0.5 * torch.sinc(half / math.pi) * w], -1)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b`` of quaternions ``(w, x, y, z)`` (the rotation ``b`` first, then ``a``).

    Parameters
    ----------
    a, b : Tensor (..., 4)
        Broadcast against each other.

    Returns
    -------
    Tensor (..., 4)
    """
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def correct_pose(R: torch.Tensor, t: torch.Tensor, omega: torch.Tensor, tau: torch.Tensor, iso: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The corrected camera ``R' = ΔR R``, ``t' = ΔR (t - c) + c + τ`` (module docstring).

    Parameters
    ----------
    R : Tensor (3, 3)
    t : Tensor (3,)
        Recorded world-to-camera pose (mm).
    omega : Tensor (3,)
        Rotation correction, camera frame (radians).
    tau : Tensor (3,)
        Shift correction, camera frame (mm).
    iso : Tensor (3,)
        Designed isocentre, world mm.

    Returns
    -------
    R', t' : Tensor (3, 3), Tensor (3,)
    """
    dR = quat_to_rotmat(rotvec_to_quat(omega))
    c = R @ iso + t
    return dR @ R, dR @ (t - c) + c + tau


def transform_gaussians(params: dict[str, torch.Tensor], R: torch.Tensor, omega: torch.Tensor, tau: torch.Tensor,
                        iso: torch.Tensor) -> dict[str, torch.Tensor]:
    """Parameters of the Gaussians moved so that the recorded camera ``R`` sees what the corrected one sees.

    Parameters
    ----------
    params : dict of str to Tensor
        Training parameters (``means`` (N, 3) mm, ``quats`` (N, 4), others passed through).
    R : Tensor (3, 3)
        Recorded world-to-camera rotation.
    omega, tau : Tensor (3,)
        The view's correction (camera frame; radians, mm).
    iso : Tensor (3,)
        Designed isocentre, world mm.

    Returns
    -------
    dict of str to Tensor
        ``means`` ``W (m - p) + p + Rᵀ τ`` and ``quats`` ``q_W ⊗ q`` (differentiable in every input); the other
        tensors are the same objects.
    """
    qW = rotvec_to_quat(R.T @ omega)
    W = quat_to_rotmat(qW)
    out = dict(params)
    out["means"] = (params["means"] - iso) @ W.T + iso + R.T @ tau
    out["quats"] = quat_mul(qW, params["quats"])
    return out


# ------------------------------------------------------------------------------------------ the module
class PoseCorrection(torch.nn.Module):
    """Per-view pose corrections ``(ω, τ)`` of the training views, their prior and the gauge fix.

    Parameters
    ----------
    Rs : ndarray (V, 3, 3)
    ts : ndarray (V, 3)
        Recorded world-to-camera poses of the training views (mm).
    iso_mm : ndarray (3,)
        Designed isocentre (world mm): the point the corrections turn the camera about.
    model : {"parallel", "cone"}
        The detector: parallel beam has no shift along the rays.
    cone_model : {"rigid", "carm"}
        Cone beam only: the full rigid correction, or no shift along the central ray (module docstring).
    prior_rot_deg, prior_trans_mm : float
        Standard deviations of the prior (> 0).
    prior_weight : float
        Weight ``w`` of the prior in the loss (>= 0).
    device : torch.device, optional
    """

    def __init__(self, Rs: np.ndarray, ts: np.ndarray, iso_mm: np.ndarray, model: str, *, cone_model: str = "rigid",
                 prior_rot_deg: float = 1.0, prior_trans_mm: float = 1.0, prior_weight: float = 1e-3,
                 device: Any = None) -> None:
        super().__init__()
        if model not in ("parallel", "cone"):
            raise CtsplatError(f"pose refinement supports parallel and cone cameras, not {model!r}")
        if cone_model not in CONE_POSE_MODELS:
            raise CtsplatError(f"unknown train.pose_refine.cone_model {cone_model!r}; allowed: "
                               f"{', '.join(CONE_POSE_MODELS)}")
        if not (prior_rot_deg > 0 and prior_trans_mm > 0):
            raise CtsplatError("train.pose_refine.prior_rot_deg and prior_trans_mm must be > 0 (a zero prior would "
                               "freeze the poses; disable pose_refine instead)")
        f32 = torch.float32
        V = len(Rs)
        self.model = model
        self.register_buffer("Rs", torch.as_tensor(np.asarray(Rs), dtype=f32, device=device))
        self.register_buffer("ts", torch.as_tensor(np.asarray(ts), dtype=f32, device=device))
        self.register_buffer("iso", torch.as_tensor(np.asarray(iso_mm, float), dtype=f32, device=device))
        along_ray = model == "cone" and cone_model == "rigid"
        mask = [1.0, 1.0, 1.0 if along_ray else 0.0]
        self.register_buffer("mask", torch.tensor(mask, dtype=f32, device=device))
        self.omega = torch.nn.Parameter(torch.zeros(V, 3, dtype=f32, device=device))
        self.tau = torch.nn.Parameter(torch.zeros(V, 3, dtype=f32, device=device))
        self.sigma_rot = math.radians(float(prior_rot_deg))
        self.sigma_trans = float(prior_trans_mm)
        self.prior_weight = float(prior_weight)

    def __len__(self) -> int:
        return int(self.omega.shape[0])

    def shift(self, i: int) -> torch.Tensor:
        """The shift of view ``i`` (mm, camera frame), without the ray component for parallel beam and the C-arm
        model."""
        return self.tau[i] * self.mask

    def transform(self, params: dict[str, torch.Tensor], i: int) -> dict[str, torch.Tensor]:
        """Gaussian parameters as the recorded camera of view ``i`` must see them (:func:`transform_gaussians`).

        Parameters
        ----------
        params : dict of str to Tensor
        i : int
            Training view index.

        Returns
        -------
        dict of str to Tensor
        """
        return transform_gaussians(params, self.Rs[i], self.omega[i], self.shift(i), self.iso)

    def corrected_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """The corrected world-to-camera poses of every training view.

        Returns
        -------
        Rs, ts : ndarray (V, 3, 3), ndarray (V, 3), float64
        """
        with torch.no_grad():
            out = [correct_pose(self.Rs[i].double(), self.ts[i].double(), self.omega[i].double(),
                                self.shift(i).double(), self.iso.double()) for i in range(len(self))]
        if not out:
            return np.zeros((0, 3, 3)), np.zeros((0, 3))
        return (np.stack([r.cpu().numpy() for r, _ in out]), np.stack([t.cpu().numpy() for _, t in out]))

    def prior(self, views: list[int] | None = None) -> torch.Tensor:
        """``½ w mean_i (|ω_i|²/σ_rot² + |τ_i|²/σ_trans²)`` over ``views`` (all when None).

        Parameters
        ----------
        views : list of int, optional

        Returns
        -------
        Tensor ()
        """
        idx = slice(None) if views is None else torch.as_tensor(views, device=self.omega.device)
        om = self.omega[idx]
        ta = self.tau[idx] * self.mask
        e = (om * om).sum(-1) / self.sigma_rot ** 2 + (ta * ta).sum(-1) / self.sigma_trans ** 2
        return 0.5 * self.prior_weight * e.mean()

    @torch.no_grad()
    def fix_gauge(self) -> None:
        """Remove the common rigid motion of all views from the corrections (module docstring), in place.

        ``ω_i -= R_i Ω`` with ``Ω = mean_i R_iᵀ ω_i``; ``τ_i -= P R_i T`` with ``T`` the least-squares solution of
        ``P R_i T ≈ τ_i`` (pseudo-inverse: directions no view constrains stay as they are).
        """
        R = self.Rs
        Om = torch.einsum("vji,vj->i", R, self.omega) / max(len(self), 1)
        self.omega -= torch.einsum("vij,j->vi", R, Om)
        PR = self.mask[None, :, None] * R  # (V, 3, 3): P R_i
        A = torch.einsum("vki,vkj->ij", PR, PR)
        b = torch.einsum("vki,vk->i", PR, self.tau * self.mask)
        T = torch.linalg.pinv(A.double()).to(A) @ b
        self.tau -= torch.einsum("vij,j->vi", PR, T)
        self.tau *= self.mask

    def state(self) -> dict[str, torch.Tensor]:
        """The corrections, for checkpoints: ``omega`` and ``tau`` (V, 3) on CPU."""
        return {"omega": self.omega.detach().cpu().clone(), "tau": self.tau.detach().cpu().clone()}

    @torch.no_grad()
    def load(self, st: dict[str, torch.Tensor]) -> None:
        """Put corrections saved by :meth:`state` back (shapes must match)."""
        self.omega.copy_(st["omega"].to(self.omega))
        self.tau.copy_(st["tau"].to(self.tau))


# ------------------------------------------------------------------------------------ errors, perturbation
def pose_errors(Rs: np.ndarray, ts: np.ndarray, Rs_true: np.ndarray, ts_true: np.ndarray, iso_mm: np.ndarray,
                model: str) -> dict[str, float]:
    """Rotation and isocentre errors of poses against the true ones: median and 90th percentile.

    The rotation error is the angle of ``R R_trueᵀ`` (degrees); the isocentre error is the distance between where
    the two poses put the designed isocentre in the camera frame (mm; for parallel beam only its detector-plane
    components, since the ray component is unobservable), the quantity the corrections act on.

    Parameters
    ----------
    Rs, Rs_true : ndarray (V, 3, 3)
    ts, ts_true : ndarray (V, 3)
    iso_mm : ndarray (3,)
    model : {"parallel", "cone"}

    Returns
    -------
    dict
        ``rot_err_median_deg``, ``rot_err_p90_deg``, ``iso_err_median_mm``, ``iso_err_p90_mm``, and
        ``rot_err_aligned_median_deg`` / ``rot_err_aligned_p90_deg``: the rotation errors after removing the best
        common world rotation (the gauge refinement cannot observe, see :meth:`PoseCorrection.fix_gauge`).
    """
    Rs, Rs_true = np.asarray(Rs, float), np.asarray(Rs_true, float)
    rot = rotation_angles_deg(np.einsum("vij,vkj->vik", Rs, Rs_true))
    G = common_rotation(Rs, Rs_true)
    rot_aligned = rotation_angles_deg(np.einsum("vij,jl,vkl->vik", Rs, G, Rs_true))
    iso = np.asarray(iso_mm, float)
    d = (Rs @ iso + ts) - (Rs_true @ iso + ts_true)
    if model == "parallel":
        d = d[:, :2]
    dist = np.linalg.norm(d, axis=-1)
    return {"rot_err_median_deg": float(np.median(rot)), "rot_err_p90_deg": float(np.percentile(rot, 90)),
            "rot_err_aligned_median_deg": float(np.median(rot_aligned)),
            "rot_err_aligned_p90_deg": float(np.percentile(rot_aligned, 90)),
            "iso_err_median_mm": float(np.median(dist)), "iso_err_p90_mm": float(np.percentile(dist, 90))}


def common_rotation(Rs: np.ndarray, Rs_true: np.ndarray) -> np.ndarray:
    """The world rotation ``G`` with ``R_i G ≈ R_true_i`` for all views: the chordal mean of ``R_iᵀ R_true_i``.

    A rotation of every camera together with the model changes no image, so this common part of the pose errors
    is the gauge that pose refinement cannot observe (:meth:`PoseCorrection.fix_gauge`).

    Parameters
    ----------
    Rs, Rs_true : ndarray (V, 3, 3)
        World-to-camera rotations: estimated (or refined) and true.

    Returns
    -------
    ndarray (3, 3)
        The rotation (SVD projection of ``Σ R_iᵀ R_true_i`` onto SO(3)).

    References
    ----------
    Hartley, R., Trumpf, J., Dai, Y., Li, H. (2013). Rotation averaging. IJCV 103(3), 267–305.
    """
    u, _, vt = np.linalg.svd(np.einsum("vji,vjk->ik", np.asarray(Rs, float), np.asarray(Rs_true, float)))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def gauge_motion(Rs: np.ndarray, ts: np.ndarray, Rs_true: np.ndarray, ts_true: np.ndarray, model: str, *,
                 center_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The rigid world motion ``m = G x + b`` between the true frame (``x``) and the frame of a model trained at
    the poses ``(Rs, ts)`` (``m``): what the training images cannot tell apart from the truth.

    Each view asks ``R_i (G x + b) + t_i = R_true_i x + t_true_i``. ``G`` is :func:`common_rotation`; the views'
    rotations differ from ``R_true_i G⁻¹`` a little, so the shift is fitted where the object is, at ``c =
    center_mm`` (the isocentre): ``b = c + b' - G c`` with ``b'`` the least-squares solution of ``P R_i b' = P
    ((R_true_i c + t_true_i) - (R_i c + t_i))`` (``P`` drops the ray component for parallel beam, where a shift
    along the rays changes no image; directions no view constrains get 0). Fitted at the world origin instead,
    the shift would depend on where a scan's coordinates put their origin, hundreds of mm away for many.

    Parameters
    ----------
    Rs, Rs_true : ndarray (V, 3, 3)
    ts, ts_true : ndarray (V, 3)
        World-to-camera poses (mm): those the model was trained at, and the true ones.
    model : {"parallel", "cone"}
    center_mm : ndarray (3,), optional
        The point the shift is fitted at, world mm (default: the origin).

    Returns
    -------
    G : ndarray (3, 3)
    b : ndarray (3,), mm
    """
    Rs, ts = np.asarray(Rs, float), np.asarray(ts, float)
    Rs_true, ts_true = np.asarray(Rs_true, float), np.asarray(ts_true, float)
    c = np.zeros(3) if center_mm is None else np.asarray(center_mm, float).reshape(3)
    G = common_rotation(Rs, Rs_true)
    P = np.diag([1.0, 1.0, 0.0 if model == "parallel" else 1.0])
    PR = np.einsum("ij,vjk->vik", P, Rs)
    rhs = np.einsum("ij,vj->vi", P, (Rs_true @ c + ts_true) - (Rs @ c + ts))
    b_c = np.linalg.pinv(np.einsum("vki,vkj->ij", PR, PR)) @ np.einsum("vki,vk->i", PR, rhs)
    return G, c + b_c - G @ c


def rotation_angles_deg(rel: np.ndarray) -> np.ndarray:
    """Rotation angles (degrees) of matrices (V, 3, 3), from atan2 of sine and cosine (arccos loses small angles).

    Parameters
    ----------
    rel : ndarray (V, 3, 3)
        Rotation matrices.

    Returns
    -------
    ndarray (V,)
        Angles in degrees, in [0, 180].
    """
    cos = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
    skew = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), cos))


def perturb_poses(Rs: np.ndarray, ts: np.ndarray, iso_mm: np.ndarray, rot_deg: float, trans_mm: float, seed: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The C-arm pose error of the SfM study applied to recorded look-at poses (``poses: perturbed``).

    Each camera keeps its distance to the isocentre; its azimuth and elevation get independent N(0, rot_deg²)
    errors and the whole assembly (camera and the point it looks at) is shifted by N(0, trans_mm² I), as
    :func:`ctsplat.geometry.orbits.carm_orbit` draws its true orbit. Image up stays world +z.

    Parameters
    ----------
    Rs : ndarray (V, 3, 3)
    ts : ndarray (V, 3)
        True poses (look-at cameras aimed at ``iso_mm``).
    iso_mm : ndarray (3,)
    rot_deg, trans_mm : float
        Standard deviations (>= 0).
    seed : int

    Returns
    -------
    Rs, ts : ndarray (V, 3, 3), ndarray (V, 3)
    """
    from ctsplat.geometry.cameras import camera_center, look_at

    rng = np.random.default_rng([int(seed), 20260])
    iso = np.asarray(iso_mm, float)
    out_R, out_t = [], []
    for R, t in zip(np.asarray(Rs, float), np.asarray(ts, float), strict=True):
        s = camera_center(R, t) - iso
        dist = float(np.linalg.norm(s))
        az = math.degrees(math.atan2(s[1], s[0])) + rng.normal(0.0, rot_deg)
        el = math.degrees(math.asin(np.clip(s[2] / dist, -1, 1))) + rng.normal(0.0, rot_deg)
        shift = rng.normal(0.0, trans_mm, 3)
        a, e = math.radians(az), math.radians(el)
        c = iso + shift + dist * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        R2, t2 = look_at(c, iso + shift)
        out_R.append(R2)
        out_t.append(t2)
    return np.stack(out_R), np.stack(out_t)
