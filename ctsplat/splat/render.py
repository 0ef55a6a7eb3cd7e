r"""Differentiable Gaussian splatting for X-ray line integrals (rectified radiative), unrectified and alpha compositing.

Pipeline (all vectorised over Gaussians; no Python loop over Gaussians)
-----------------------------------------------------------------------
1. **Project** (:func:`project`, differentiable PyTorch): camera-frame mean ``t = R m + t_w`` and covariance
   ``Σ_c = R Σ Rᵀ``; the ray-space Jacobian ``J`` maps camera mm to *(u px, v px, l mm)* where ``l`` is the distance
   along the ray:

   - parallel beam: ``J = diag(1/s, 1/s, 1)`` (``s`` = detector spacing, mm/px) -- an exact affine map;
   - cone beam (source = camera centre): ``u = f_x x/z + c_x``, ``v = f_y y/z + c_y``, ``l = ‖t‖``, linearised at the
     Gaussian's centre (local-affine EWA)::

         J = [[f_x/z, 0, -f_x x/z²], [0, f_y/z, -f_y y/z²], [x/r, y/r, z/r]],   r = ‖t‖.

   ``Σ̃ = J Σ_c Jᵀ`` is the 3×3 ray-space covariance, ``Σ̂`` its 2×2 image block (px²).
2. **Amplitude per compositor** (``d`` = pixel centre minus projected mean, px):

   - ``radiative`` (rectified): integrating the ray-space Gaussian along ``l`` at fixed ``(u, v)`` gives
     ``p(u,v) = Σ_i ρ_i sqrt(2π |Σ̃_i| / |Σ̂_i|) exp(-½ dᵀ Σ̂_i⁻¹ d)``, because for a 3D Gaussian
     ``∫ exp(-½ xᵀ Σ̃⁻¹ x) dl = sqrt(2π / (Σ̃⁻¹)_{ll}) exp(-½ dᵀ Σ̂⁻¹ d)`` and ``1/(Σ̃⁻¹)_{ll} = |Σ̃|/|Σ̂|``.
     Exact for parallel beam. ``|Σ̃| = |J|² Π_k s_k²`` is evaluated from the scales (stable for flat Gaussians),
     and ``|Σ̂| = Σ_{j<k} s_j² s_k² m_jk²`` by the Cauchy–Binet formula, ``m_jk`` the 2×2 minors of ``T = J₂ R_c``
     (``J₂`` the image rows of ``J``, ``R_c`` the Gaussian's axes in the camera frame): a sum of non-negative terms,
     where ``Σ̂₀₀ Σ̂₁₁ − Σ̂₀₁²`` would cancel in float32 for needle-like Gaussians (axis ratios above ~1e3) — every
     backend forms it this way, the hand-written backward passes included.
     Image mass: ``Σ_pixels p · A_px = Σ_i ρ_i (2π)^{3/2} |Σ_i|^{1/2}`` (``A_px`` = pixel area, mm²).
   - ``radiative_unrectified`` (X-Gaussian style): ``p = Σ_i ρ_i exp(-½ dᵀ Σ̂_i⁻¹ d)`` -- the view-dependent
     "integration bias": its image mass is ``ρ 2π |Σ̂|^{1/2} A_px``, which changes with the direction for
     anisotropic Gaussians.
   - ``alpha`` (3DGS): ``α_i = min(0.99, o_i exp(-½ dᵀ Σ̂_i'⁻¹ d))`` with ``Σ̂' = Σ̂ + 0.3 I`` (low-pass),
     composited front to back in depth (``z_cam``) order: ``C = Σ_i c_i α_i Π_{j<i} (1 - α_j)``
     (no 1/255 skip and no early termination, so it is smooth and matches the brute-force reference).
3. **Rasterise**: each Gaussian touches only the pixels of its ``sigma_cutoff``-σ axis-aligned bounding box in the image
   (half widths ``k sqrt(Σ̂_00)``, ``k sqrt(Σ̂_11)`` px), so footprints adapt to the Gaussian's size -- a large Gaussian
   is never clipped and a small one costs a few pixels. (Gaussian, pixel) pairs are generated with
   ``repeat_interleave`` and scattered with ``index_add`` (alpha: stably sorted by pixel, then depth) in the
   reference path (:mod:`ctsplat.splat._reference`); the fast CPU path runs projection and rasterisation as fused
   C++ kernels with hand-written backward passes (:mod:`ctsplat.splat._kernel`; tested against the reference and
   by gradcheck).
   The bounding box truncates the tails: with the default ``k = 3`` the lost mass of a Gaussian is between
   ``1 - erf(3/√2) ≈ 0.27 %`` and ``1 - erf(3/√2)² ≈ 0.54 %`` (Šidák); pass ``sigma_cutoff=5`` for ~1e-6.

Mip filter (Mip-Splatting), mass-conserving in radiative mode
-------------------------------------------------------------
*3D smoothing filter* (``filter_3d_var`` = ``v`` mm², from :func:`compute_3d_filter`): the Gaussian is convolved
with an isotropic 3D Gaussian of variance ``v``: ``Σ' = Σ + v I = R diag(s² + v) Rᵀ``. Convolution conserves the
integral, so the filtered kernel is ``ρ sqrt(|Σ|/|Σ'|) exp(-½ xᵀ Σ'⁻¹ x)`` with ``|Σ|/|Σ'| = Π_k s_k²/(s_k² + v)``:
``∫ ρ sqrt(|Σ|/|Σ'|) exp(-½ xᵀΣ'⁻¹x) dx = ρ (2π)^{3/2} |Σ|^{1/2}`` -- the mass is conserved while the *peak* drops.
(Keeping ρ, i.e. conserving the peak, would inflate the mass by ``sqrt(|Σ'|/|Σ|)``, unbounded for thin Gaussians.)
In alpha mode the same factor multiplies the opacity, exactly as in Mip-Splatting.

*2D mip filter* (``mip_2d=True``): the image footprint is convolved with a 2D Gaussian of variance ``k₂ = 0.1`` px²
(Mip-Splatting's box-filter approximation of the pixel) instead of the plain 0.3 px dilation. For the rectified
line-integral image, convolving ``ρ sqrt(2π|Σ̃|/|Σ̂|) exp(-½ dᵀΣ̂⁻¹d)`` with ``N(0, k₂ I)`` gives exactly::

    ρ sqrt(2π |Σ̃| / |Σ̂'|) exp(-½ dᵀ Σ̂'⁻¹ d),    Σ̂' = Σ̂ + k₂ I,

i.e. the rectification factor is evaluated with the *filtered* ``|Σ̂'|`` and the *unfiltered* ``|Σ̃|``; its 2D integral
``ρ (2π)^{3/2} |Σ̃|^{1/2}`` is unchanged (mass conserved; the compensation is ``sqrt(|Σ̂|/|Σ̂'|)`` relative to the
unfiltered amplitude). Unrectified and alpha modes use Mip-Splatting's ``sqrt(|Σ̂|/|Σ̂'|)`` on ρ resp. opacity.
All modes add a numerical floor of ``1e-4`` px² to ``Σ̂`` (mass-conserving in radiative mode), which keeps
degenerate (flat, edge-on) Gaussians finite and differentiable.

Notes for training
------------------
* ``out.means2d`` is the projected-mean tensor actually used by the rasteriser, with ``retain_grad()`` already
  called when it requires grad: after ``loss.backward()`` read ``out.means2d.grad`` (N, 2) px for densification.
* ``out.visible`` / ``out.radii`` (px, 0 when culled) mark Gaussians that touched at least one pixel.
* Densities are in normalised-volume units; render against targets divided by ``mu_scale_per_mm`` or pass
  ``mu_scale``. ``compute_3d_filter`` once per densification step (cameras are fixed), then pass its result to every
  :func:`render` and to :func:`voxelize` (``filter_3d_var``) so the volume read-out matches the rendered field.
* ``backend="auto"`` uses the fused C++ kernels (all compositors) on CPU when a C++ compiler is available
  (compiled once into ``~/.cache/ctsplat``), on CUDA the Triton tile kernels (:mod:`ctsplat.splat._triton`, the
  ``gpu`` extra) after the PyTorch :func:`project`, else the pure-PyTorch reference (on CUDA with one logged
  warning). All are differentiable w.r.t. means, log-scales, quats, density_raw (alpha: also opacity_raw, colours,
  sh_rest); float32 and float64. ``backend="triton"`` on CPU tensors needs ``TRITON_INTERPRET=1`` (tests).
* Thread count = ``torch.get_num_threads()``. On a shared, overloaded CPU set ``OMP_WAIT_POLICY=PASSIVE`` in the
  environment before starting Python: torch's idle OpenMP workers otherwise spin and steal the cores (2-thread
  fwd+bwd measured ~5x slower without it).

References
----------
.. [1] M. Zwicker, H. Pfister, J. van Baar, M. Gross, "EWA Volume Splatting", IEEE Visualization 2001 (ray-space
   Jacobian, local-affine projection of 3D Gaussians).
.. [2] B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian Splatting for Real-Time Radiance Field
   Rendering", ACM Transactions on Graphics 42(4), 2023 (alpha compositor, 0.3 px² low-pass, clamped
   linearisation point, bounding-box footprints).
.. [3] R. Zha, T. J. Lin, Y. Cai, J. Cao, Y. Zhang, H. Li, "R²-Gaussian: Rectifying Radiative Gaussian Splatting
   for Tomographic Reconstruction", NeurIPS 2024 (rectified radiative line integrals, voxelizer).
.. [4] Y. Cai, Y. Liang, J. Wang, A. Wang, Y. Zhang, X. Yang, Z. Zhou, L. Zhang, "Radiative Gaussian Splatting for
   Efficient X-ray Novel View Synthesis", ECCV 2024 (X-Gaussian: the unrectified radiative compositor).
.. [5] Z. Yu, A. Chen, B. Huang, T. Sattler, A. Geiger, "Mip-Splatting: Alias-free 3D Gaussian Splatting",
   CVPR 2024 (3D smoothing and 2D mip filters).
"""

from __future__ import annotations

import logging
import math
import numbers
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ctsplat.geometry.cameras import camera_center
from ctsplat.splat import _kernel, _reference, _triton
from ctsplat.splat.gaussians import Gaussians, eval_sh, quat_to_rotmat
from ctsplat.utils import CtsplatError

__all__ = [
    "COMPOSITORS",
    "BACKENDS",
    "RenderOutput",
    "Projection",
    "ALPHA_MIN",
    "alpha_footprints",
    "camera_intrinsics",
    "project",
    "render",
    "resolved_backend",
    "compute_3d_filter",
    "voxelize",
    "random_region",
    "render_to_folder",
]

COMPOSITORS = ("radiative", "radiative_unrectified", "alpha")
# auto: the fused C++ kernels on CPU when they build, the Triton kernels on CUDA when triton imports, else the reference
BACKENDS = ("auto", "reference", "kernel", "triton")
LOWPASS_ALPHA = 0.3  # px², 3DGS dilation
MIP_2D_VAR = 0.1  # px², Mip-Splatting 2D filter
EPS_2D = 1e-4  # px², numerical floor
NEAR_MM = 1e-2  # cone beam: Gaussians with z_cam below this are culled (behind / at the source)


@dataclass
class RenderOutput:
    """Result of :func:`render`.

    Attributes
    ----------
    image : Tensor (H, W) (or (H, W, C) for multi-channel alpha colours)
        Line integrals (radiative modes; ``exp(-mu_scale·p)`` if ``transmission``) or composited colour.
    means2d : Tensor (N, 2)
        Projected means in pixels ``(u, v)``; retains its gradient after ``backward()``.
    radii : Tensor (N,) int32
        Footprint radius in pixels (max half-width of the bounding box), 0 for culled Gaussians.
    visible : Tensor (N,) bool
        Gaussian touched at least one pixel.
    depths : Tensor (N,)
        ``z_cam`` in mm (sorting key for alpha).
    footprints : Tensor (N,) or None
        Alpha only: :func:`alpha_footprints`, the pixels where each Gaussian's α reaches 1/255 (no gradient).
    """

    image: torch.Tensor
    means2d: torch.Tensor
    radii: torch.Tensor
    visible: torch.Tensor
    depths: torch.Tensor
    footprints: torch.Tensor | None = None


@dataclass
class Projection:
    """Per-Gaussian 2D quantities (all (N, ...) tensors, differentiable)."""

    means2d: torch.Tensor  # (N, 2) px
    conics: torch.Tensor  # (N, 3) (a, b, c) of the inverse filtered 2D covariance, px⁻²
    cov2d: torch.Tensor  # (N, 3) (Σ̂'00, Σ̂'01, Σ̂'11) filtered, px²
    amps: torch.Tensor  # (N,) peak value (radiative: ρ·rect; unrectified: ρ; alpha: opacity)
    depths: torch.Tensor  # (N,) z_cam mm
    valid: torch.Tensor  # (N,) bool, not culled
    bbox: torch.Tensor  # (N, 4) int64 (u0, u1, v0, v1), half-open, clipped to the image; empty if culled


# ---------------------------------------------------------------------------------------------- cameras
def camera_intrinsics(camera: Any) -> dict[str, Any]:
    """Read a (duck-typed) camera: ``model``, ``width``, ``height`` and ``spacing_mm`` or ``pitch_mm/dso_mm/dsd_mm``.

    Parameters
    ----------
    camera : ParallelCamera | ConeCamera or any object with those attributes
        Optional ``cx``, ``cy`` (principal point, px; default the image centre) and, for cone beam, ``fx``, ``fy``
        (px; default ``dsd_mm / pitch_mm``).

    Returns
    -------
    dict
        ``{"model", "W", "H", "cx", "cy"}`` (px) plus ``"sx", "sy"`` (mm/px, parallel) or ``"fx", "fy"`` (px,
        cone), and ``"pixel_area_mm2"`` (detector pixel area, for mass checks; for cone at the detector plane).
    """
    model = getattr(camera, "model", None)
    try:
        w, h = int(camera.width), int(camera.height)
    except AttributeError as exc:
        raise CtsplatError(f"camera {camera!r} has no width/height") from exc
    if w <= 0 or h <= 0:
        raise CtsplatError(f"camera size must be positive, got {w}x{h}")
    cx = float(getattr(camera, "cx", w / 2))
    cy = float(getattr(camera, "cy", h / 2))
    if not (math.isfinite(cx) and math.isfinite(cy)):
        raise CtsplatError(f"camera principal point must be finite, got cx={cx}, cy={cy}")
    if model == "parallel":
        sp = camera.spacing_mm
        sx, sy = (float(sp), float(sp)) if not hasattr(sp, "__len__") else (float(sp[0]), float(sp[1]))
        if not (0 < sx < math.inf and 0 < sy < math.inf):
            raise CtsplatError(f"parallel camera spacing_mm must be finite and > 0, got {sp}")
        return {"model": model, "W": w, "H": h, "cx": cx, "cy": cy, "sx": sx, "sy": sy, "pixel_area_mm2": sx * sy}
    if model == "cone":
        pitch = float(camera.pitch_mm)
        dsd = float(camera.dsd_mm)
        if not (0 < pitch < math.inf and 0 < dsd < math.inf):
            raise CtsplatError(f"cone camera pitch_mm and dsd_mm must be finite and > 0, got {pitch} and {dsd}")
        fx = float(getattr(camera, "fx", dsd / pitch))
        fy = float(getattr(camera, "fy", dsd / pitch))
        if not (0 < fx < math.inf and 0 < fy < math.inf):
            raise CtsplatError(f"cone camera focal lengths must be finite and > 0, got fx={fx}, fy={fy}")
        return {"model": model, "W": w, "H": h, "cx": cx, "cy": cy, "fx": fx, "fy": fy,
                "pixel_area_mm2": pitch * pitch}
    raise CtsplatError(f"unknown camera model {model!r}; expected 'parallel' or 'cone'")


def _as_pose(R: Any, t: Any, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    R_t = torch.as_tensor(R, dtype=like.dtype, device=like.device).reshape(3, 3)
    t_t = torch.as_tensor(t, dtype=like.dtype, device=like.device).reshape(3)
    return R_t, t_t


def _det_cov2d(T: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
    """|T diag(s2) Tᵀ| by the Cauchy–Binet formula: (N, 2, 3) T, (N, 3) s2 → (N,).

    ``Σ_{j<k} s2_j s2_k (T_0j T_1k − T_0k T_1j)²``: a sum of non-negative terms, so it keeps its relative precision
    for needle-like Gaussians, where ``c00 c11 − c01²`` of the rounded entries cancels to noise (or below zero) in
    float32 once the 2D axis ratio passes ~1e3.
    """
    t0, t1 = T[:, 0, :], T[:, 1, :]
    m01 = t0[:, 0] * t1[:, 1] - t0[:, 1] * t1[:, 0]
    m02 = t0[:, 0] * t1[:, 2] - t0[:, 2] * t1[:, 0]
    m12 = t0[:, 1] * t1[:, 2] - t0[:, 2] * t1[:, 1]
    return s2[:, 0] * s2[:, 1] * m01**2 + s2[:, 0] * s2[:, 2] * m02**2 + s2[:, 1] * s2[:, 2] * m12**2


#: Below this a product of variances is taken from logarithms: in float32 it underflows to 0 for Gaussians whose
#: scales are all below about e⁻²⁰ mm, and the square root's infinite derivative at 0 turned their gradients NaN.
_TINY_PRODUCT = 1e-30


def _sqrt_via_log(x: torch.Tensor, log_x: torch.Tensor) -> torch.Tensor:
    """``sqrt(x)``, with ``x`` also given as its logarithm: ``exp(½ log x)`` where ``x < _TINY_PRODUCT``.

    Elsewhere the same numbers as ``torch.sqrt(x)``; where ``x`` may have underflowed, a finite value and gradient.
    Each branch sees safe inputs where it is not taken, so neither sends NaN through :func:`torch.where`.
    """
    tiny = x < _TINY_PRODUCT
    via_log = torch.exp(0.5 * torch.where(tiny, log_x, torch.zeros_like(log_x)))
    return torch.where(tiny, via_log, torch.sqrt(torch.where(tiny, torch.ones_like(x), x)))


def _filter_compensation(log_scales: torch.Tensor, s2: torch.Tensor, s2f: torch.Tensor,
                         log_s2f: torch.Tensor) -> torch.Tensor:
    """``sqrt(|Σ| / |Σ'|)`` of the 3D filter (mass-conserving): (N, 3) log scales, variances, filtered variances
    and their logarithms → (N,); finite in value and gradient for vanishing scales."""
    return _sqrt_via_log(torch.prod(s2 / s2f, dim=-1), (2 * log_scales - log_s2f).sum(-1))


# ---------------------------------------------------------------------------------------------- projection
def _dilation(compositor: str, mip_2d: bool) -> float:
    """2D filter variance (px²) added to Σ̂: alpha low-pass 0.3 / mip 0.1 / radiative 0, plus the ``EPS_2D`` floor."""
    if compositor == "alpha":
        k2 = MIP_2D_VAR if mip_2d else LOWPASS_ALPHA
    else:
        k2 = MIP_2D_VAR if mip_2d else 0.0
    return k2 + EPS_2D


def project(
    gaussians: Gaussians,
    camera: Any,
    R: Any,
    t: Any,
    *,
    compositor: str = "radiative",
    filter_3d_var: torch.Tensor | None = None,
    mip_2d: bool = False,
    sigma_cutoff: float = 3.0,
) -> Projection:
    """Project Gaussians into the image: 2D means, filtered conics, amplitudes and pixel bounding boxes.

    Pure PyTorch (differentiable, any device); the math is in the module docstring (EWA local-affine projection,
    rectification, 3D / 2D filters). :func:`render` uses it on the reference path; the fused kernel computes the
    same quantities.

    Parameters
    ----------
    gaussians : Gaussians (N)
    camera : ParallelCamera | ConeCamera
        See :func:`camera_intrinsics`.
    R : array_like (3, 3)
    t : array_like (3,)
        World-to-camera pose, ``x_cam = R x + t`` (mm).
    compositor : {"radiative", "radiative_unrectified", "alpha"}
        Sets the amplitude and the 2D filter.
    filter_3d_var : Tensor (N,) or None
        3D smoothing-filter variance, mm² (:func:`compute_3d_filter`).
    mip_2d : bool
        2D mip filter (0.1 px²) instead of the compositor's default dilation.
    sigma_cutoff : float
        Bounding-box half-width in standard deviations of the filtered 2D footprint.

    Returns
    -------
    Projection
        ``means2d (N, 2)`` px, ``conics (N, 3)`` px⁻², ``cov2d (N, 3)`` px², ``amps (N,)``, ``depths (N,)`` mm,
        ``valid (N,)`` bool, ``bbox (N, 4)`` int64 half-open pixel ranges.
    """
    cam = camera_intrinsics(camera)
    means = gaussians.means
    R_t, t_t = _as_pose(R, t, means)
    n = means.shape[0]
    dtype, dev = means.dtype, means.device

    s2 = torch.exp(2 * gaussians.log_scales)  # (N, 3) mm²
    dens = gaussians.densities
    if filter_3d_var is not None:
        v = torch.as_tensor(filter_3d_var, dtype=dtype, device=dev).reshape(-1)
        if v.shape[0] != n:
            raise CtsplatError(f"filter_3d_var has {v.shape[0]} entries for {n} Gaussians")
        s2f = s2 + v[:, None]
        log_s2f = torch.log(s2f)
        comp3d = _filter_compensation(gaussians.log_scales, s2, s2f, log_s2f)
    else:
        s2f = s2
        log_s2f = 2 * gaussians.log_scales
        comp3d = None
    rot_c = R_t @ quat_to_rotmat(gaussians.quats)  # (N,3,3) the Gaussians' axes in the camera frame
    x_c = means @ R_t.T + t_t  # (N,3)
    z = x_c[:, 2]

    if cam["model"] == "parallel":
        u = x_c[:, 0] / cam["sx"] + cam["cx"]
        v_ = x_c[:, 1] / cam["sy"] + cam["cy"]
        jd = torch.tensor([1 / cam["sx"], 1 / cam["sy"]], dtype=dtype, device=dev)
        detj2 = (jd[0] * jd[1]) ** 2 * torch.ones_like(z)
        T = rot_c[:, :2, :] * jd[None, :, None]  # (N,2,3) the image rows of J times the Gaussian's axes
        # every Gaussian, also one behind the rays' start plane z = 0 (the projector starts there): the splat is
        # the line integral over the whole line, which differs only for Gaussians outside the volume's sphere
        valid = torch.ones(n, dtype=torch.bool, device=dev)
    else:
        fx, fy = cam["fx"], cam["fy"]
        valid = z > NEAR_MM
        zs = torch.where(valid, z, torch.ones_like(z))
        u = fx * x_c[:, 0] / zs + cam["cx"]
        v_ = fy * x_c[:, 1] / zs + cam["cy"]
        # 3DGS-style clamp of the linearisation point for far off-screen Gaussians (keeps J bounded)
        lim_x = 1.3 * 0.5 * cam["W"] / fx + abs(cam["cx"] - cam["W"] / 2) / fx
        lim_y = 1.3 * 0.5 * cam["H"] / fy + abs(cam["cy"] - cam["H"] / 2) / fy
        tx = zs * torch.clamp(x_c[:, 0] / zs, -lim_x, lim_x)
        ty = zs * torch.clamp(x_c[:, 1] / zs, -lim_y, lim_y)
        r = torch.sqrt(tx * tx + ty * ty + zs * zs)
        zero = torch.zeros_like(zs)
        J = torch.stack(
            [
                torch.stack([fx / zs, zero, -fx * tx / zs**2], -1),
                torch.stack([zero, fy / zs, -fy * ty / zs**2], -1),
                torch.stack([tx / r, ty / r, zs / r], -1),
            ],
            dim=-2,
        )  # (N,3,3)
        detj2 = torch.linalg.det(J) ** 2
        T = J[:, :2, :] @ rot_c

    # Σ̂ = T diag(s2f) Tᵀ (px²) and |Σ̂| (unfiltered 2D); the floor keeps sqrt differentiable for degenerate
    # (edge-on flat) Gaussians
    ts = T * s2f[:, None, :]
    c00, c01, c11 = (ts[:, 0] * T[:, 0]).sum(-1), (ts[:, 0] * T[:, 1]).sum(-1), (ts[:, 1] * T[:, 1]).sum(-1)
    det_cb = _det_cov2d(T, s2f)
    det_hat = det_cb.clamp_min(1e-20)
    k2 = _dilation(compositor, mip_2d)
    f00, f01, f11 = c00 + k2, c01, c11 + k2
    det_f = det_cb + k2 * (c00 + c11) + k2 * k2  # |Σ̂ + k2 I|
    conics = torch.stack([f11 / det_f, -f01 / det_f, f00 / det_f], dim=-1)

    if compositor == "radiative":
        det_tilde = detj2 * torch.prod(s2f, dim=-1)  # |Σ̃| = |J|² |Σ'|
        log_ratio = math.log(2 * math.pi) + torch.log(detj2) + log_s2f.sum(-1) - torch.log(det_f)
        amp = dens * _sqrt_via_log(2 * math.pi * det_tilde / det_f, log_ratio)
        if comp3d is not None:
            amp = amp * comp3d
    elif compositor == "radiative_unrectified":
        amp = dens
        if comp3d is not None:
            amp = amp * comp3d
        if mip_2d:
            amp = amp * torch.sqrt(det_hat / det_f)
    elif compositor == "alpha":
        amp = gaussians.opacities
        if comp3d is not None:
            amp = amp * comp3d
        if mip_2d:
            amp = amp * torch.sqrt(det_hat / det_f)
    else:
        raise CtsplatError(f"unknown compositor {compositor!r}; expected one of {', '.join(COMPOSITORS)}")

    means2d = torch.stack([u, v_], dim=-1)
    with torch.no_grad():
        hx = sigma_cutoff * torch.sqrt(f00.detach().clamp_min(0))
        hy = sigma_cutoff * torch.sqrt(f11.detach().clamp_min(0))
        md = means2d.detach()
        # pixel centres (i + 0.5) inside [m - h, m + h]
        big = 1e9
        u0 = torch.ceil((md[:, 0] - hx - 0.5).clamp(-big, big)).clamp(0, cam["W"])
        u1 = (torch.floor((md[:, 0] + hx - 0.5).clamp(-big, big)) + 1).clamp(0, cam["W"])
        v0 = torch.ceil((md[:, 1] - hy - 0.5).clamp(-big, big)).clamp(0, cam["H"])
        v1 = (torch.floor((md[:, 1] + hy - 0.5).clamp(-big, big)) + 1).clamp(0, cam["H"])
        bbox = torch.stack([u0, u1, v0, v1], dim=-1).to(torch.int64)
        ok = valid & torch.isfinite(md).all(-1) & torch.isfinite(hx) & torch.isfinite(hy)
        bbox[~ok] = 0
        bbox[:, 1] = torch.maximum(bbox[:, 1], bbox[:, 0])
        bbox[:, 3] = torch.maximum(bbox[:, 3], bbox[:, 2])
    return Projection(means2d=means2d, conics=conics, cov2d=torch.stack([f00, f01, f11], -1), amps=amp,
                      depths=z, valid=valid, bbox=bbox)


# ---------------------------------------------------------------------------------------------- render
_log = logging.getLogger(__name__)
_triton_fallback_logged = False


#: The α below which 3DGS's rasteriser skips a (Gaussian, pixel) pair: the edge of a Gaussian's footprint.
ALPHA_MIN = 1.0 / 255.0


def alpha_footprints(proj: Projection, height: int, width: int) -> torch.Tensor:
    """Pixels covered by each Gaussian where its α reaches 1/255, whoever lies in front of it.

    The region ``o exp(-½ dᵀ C d) ≥ 1/255`` is an ellipse of area ``2π ln(255 o) / sqrt(det C)`` (``C`` the conic,
    ``o`` the opacity). For an ellipse cut by the image's edges the area is scaled by the fractions of its width
    and of its height that lie in the image, and capped by the Gaussian's pixel box clipped to the image: exact
    for an ellipse wholly in the image, an estimate otherwise (an ellipse elongated along a diagonal and cut at
    a corner can be off by a factor of 2-3). Pixel-GS's weight is the count of pixels its rasteriser blends the
    Gaussian into before their transmittance falls below 1e-4; this one counts occluded pixels too.

    Parameters
    ----------
    proj : Projection
        Of the alpha compositor (``amps`` are opacities in (0, 1)).
    height, width : int
        The image, px.

    Returns
    -------
    Tensor (N,)
        px; 0 for culled Gaussians and those with opacity at most 1/255. No gradient.

    References
    ----------
    Zhang, Z., Hu, W., Lao, Y., He, T., Zhao, H. (2024). Pixel-GS: Density control with pixel-aware gradient for
    3D Gaussian splatting. ECCV.
    """
    with torch.no_grad():
        con, o, bb, m = proj.conics, proj.amps, proj.bbox, proj.means2d.detach()
        det = (con[:, 0] * con[:, 2] - con[:, 1] ** 2).clamp_min(1e-30)
        r2 = 2.0 * torch.log((o / ALPHA_MIN).clamp_min(1.0))  # 0 where the opacity never reaches 1/255
        area = math.pi * r2 / det.sqrt()
        for axis, size, var in ((0, width, con[:, 2] / det), (1, height, con[:, 0] / det)):  # the inverse's diagonal
            half = (r2 * var).sqrt().clamp_min(1e-30)
            lo, hi = (m[:, axis] - half).clamp_min(0.0), (m[:, axis] + half).clamp_max(float(size))
            area = area * ((hi - lo).clamp_min(0.0) / (2.0 * half)).clamp_max(1.0)
        box = ((bb[:, 1] - bb[:, 0]).clamp_min(0) * (bb[:, 3] - bb[:, 2]).clamp_min(0)).to(o.dtype)
        return torch.where(proj.valid, torch.minimum(area, box), 0.0)


def _check_backend(backend: str, what: str) -> None:
    if backend not in BACKENDS:
        raise CtsplatError(f"unknown {what} backend {backend!r}; expected auto, reference, kernel or triton")


def _use_kernel(backend: str, device: torch.device) -> bool:
    """Whether the fused C++ kernels run: CPU tensors only; ``auto`` when they build, ``kernel`` always."""
    if backend == "kernel" and device.type != "cpu":
        raise CtsplatError(f"backend 'kernel' (the C++ CPU kernels) cannot render {device.type} tensors; use "
                           "auto, triton or reference")
    if backend in ("reference", "triton") or device.type != "cpu":
        return False
    return _kernel.available() if backend == "auto" else True


def _use_triton(backend: str, device: torch.device) -> bool:
    """Whether the Triton kernels run: ``triton`` always (or a one-line error saying what is missing), ``auto`` on
    CUDA tensors when triton is installed (else the reference, with one logged warning)."""
    global _triton_fallback_logged
    if backend == "triton":
        reason = _triton.unavailable_reason(device)
        if reason is not None:
            raise CtsplatError(f"backend='triton' cannot run: {reason}")
        return True
    if backend != "auto" or device.type != "cuda":
        return False
    reason = _triton.unavailable_reason(device)
    if reason is not None and not _triton_fallback_logged:
        _triton_fallback_logged = True
        _log.warning("rendering on CUDA with the slow pure-PyTorch reference: %s", reason)
    return reason is None


def resolved_backend(backend: str = "auto", device: str | torch.device = "cpu") -> str:
    """The implementation that :func:`render` and :func:`voxelize` run for ``backend`` on ``device``.

    Parameters
    ----------
    backend : {"auto", "reference", "kernel", "triton"}
        The requested backend.
    device : str or torch.device
        Where the Gaussians live.

    Returns
    -------
    str
        ``"triton"`` (GPU kernels), ``"kernel"`` (fused C++ CPU kernels) or ``"reference"`` (pure PyTorch).

    Examples
    --------
    >>> resolved_backend("reference", "cpu")
    'reference'
    """
    _check_backend(backend, "render")
    device = torch.device(device)
    if _use_triton(backend, device):
        return "triton"
    return "kernel" if _use_kernel(backend, device) else "reference"


def _fused(backend: str, device: torch.device) -> ModuleType | None:
    """The module whose fused kernels run for ``backend`` on ``device`` (``_triton`` or ``_kernel``), or ``None``
    for the pure-PyTorch reference."""
    if _use_triton(backend, device):
        return _triton
    return _kernel if _use_kernel(backend, device) else None


def _check_tensors(gaussians: Gaussians) -> None:
    """Every backend renders float32 or float64 Gaussians, all of one dtype (half precision overflows in |Σ̂|) and
    on one device (the fused kernels read raw pointers of every tensor on the means' device)."""
    dtype, dev = gaussians.means.dtype, gaussians.means.device
    if dtype not in (torch.float32, torch.float64):
        raise CtsplatError(f"render and voxelize take float32 or float64 Gaussians, got {dtype}; convert them with "
                           "gaussians.to(dtype=torch.float32)")
    for name, v in gaussians.tensors().items():
        if v.dtype != dtype:
            raise CtsplatError(f"Gaussians.{name} is {v.dtype}, the means {dtype}; convert the model to one dtype "
                               f"(gaussians.to(dtype={dtype}))")
        if v.device != dev:
            raise CtsplatError(f"Gaussians.{name} is on {v.device}, the means on {dev}; move the model to one "
                               "device (Gaussians.to)")


# the parameters each compositor renders: NaN/Inf in these is an error, in the others (a radiative model's colours, an
# alpha model's densities) it is not, on every backend alike (the fused projection flags only what it reads,
# _PROJECTED, and the rest is checked beside it)
_PROJECTED = ("means", "log_scales", "quats", "density_raw", "opacity_raw")
_RENDERED = {"radiative": ("means", "log_scales", "quats", "density_raw"),
             "radiative_unrectified": ("means", "log_scales", "quats", "density_raw"),
             "alpha": ("means", "log_scales", "quats", "opacity_raw", "colors", "sh_rest")}


def _check_cutoff(sigma_cutoff: Any) -> None:
    if not isinstance(sigma_cutoff, numbers.Real) or isinstance(sigma_cutoff, bool) or not 0 < sigma_cutoff < math.inf:
        raise CtsplatError(f"sigma_cutoff must be a finite number > 0, got {sigma_cutoff!r}")


def _check_inputs(gaussians: Gaussians, filter_3d_var: torch.Tensor | None, compositor: str) -> None:
    gaussians.validate(check_finite=_RENDERED[compositor])
    _check_filter_var(filter_3d_var)


def _check_filter_var(filter_3d_var: torch.Tensor | None) -> None:
    """Refuse 3D filter variances that are negative or not finite (they would give NaN renders and volumes)."""
    if filter_3d_var is not None:
        fv = torch.as_tensor(filter_3d_var)
        # both conditions in one host synchronisation; the messages below tell them apart
        if fv.numel() and not bool(((fv >= 0) & torch.isfinite(fv)).all()):
            if not bool(torch.isfinite(fv).all()):
                raise CtsplatError("filter_3d_var contains NaN/Inf; recompute it with compute_3d_filter")
            raise CtsplatError("filter_3d_var must be >= 0 (a variance in mm²)")


def _colors_for_view(gaussians: Gaussians, R: torch.Tensor, t: torch.Tensor, model: str) -> torch.Tensor:
    n = len(gaussians)
    m = gaussians.means
    base = gaussians.colors if gaussians.colors is not None else torch.ones(n, 1, dtype=m.dtype, device=m.device)
    if gaussians.sh_rest is None:
        return base
    if model == "parallel":
        d = R[2].expand(n, 3)  # viewing direction +z_cam in world
    else:
        d = F.normalize(m - camera_center(R, t), dim=-1)
    return torch.clamp_min(base + eval_sh(gaussians.sh_rest, d), 0.0)


def render(
    gaussians: Gaussians,
    camera: Any,
    R: Any,
    t: Any,
    *,
    compositor: str = "radiative",
    filter_3d_var: torch.Tensor | None = None,
    mip_2d: bool = False,
    transmission: bool = False,
    mu_scale: float = 1.0,
    sigma_cutoff: float = 3.0,
    background: Any = None,
    color_scale: torch.Tensor | None = None,
    backend: str = "auto",
) -> RenderOutput:
    """Render one view.

    Parameters
    ----------
    gaussians : Gaussians (N)
    camera : ParallelCamera | ConeCamera (duck-typed, see :func:`camera_intrinsics`)
    R : (3, 3), t : (3,)
        World-to-camera pose, ``x_cam = R x + t`` (mm).
    compositor : "radiative" | "radiative_unrectified" | "alpha"
    filter_3d_var : Tensor (N,) mm² or None
        Mip-Splatting 3D filter variance (:func:`compute_3d_filter`); mass-conserving (module docstring).
    mip_2d : bool
        2D mip filter (0.1 px²) instead of the alpha low-pass (0.3 px²) / no filter (radiative).
    transmission : bool
        Radiative modes: return ``exp(-mu_scale · p)`` instead of the line integral ``mu_scale · p``.
    mu_scale : float
        Factor applied to densities (e.g. ``mu_scale_per_mm`` to get 1/mm line integrals).
    sigma_cutoff : float
        Footprint half-width in standard deviations (bounding box).
    background : Tensor (C,) or sequence of C floats, optional
        Alpha only: the colour behind the Gaussians, ``C = Σ_i c_i α_i T_i + b T_N`` with ``T_N = Π_i (1 - α_i)``
        the transmittance left after the last Gaussian (None: black, ``b = 0``). Differentiable when it is a
        tensor that requires grad. The kernels composite one extra colour channel of ones, which is the pixel's
        opacity ``1 - T_N``.
    color_scale : Tensor (N,), optional
        Alpha only: a factor on each Gaussian's colour after its view-dependent SH colour (e.g. a light's falloff
        with distance, :func:`ctsplat.photos.light.flash_falloff`); differentiable.
    backend : "auto" | "reference" | "kernel" | "triton"
        "auto": fused C++ kernels on CPU when available, Triton kernels on CUDA when triton is installed, else the
        pure-PyTorch reference.

    Returns
    -------
    RenderOutput
        ``image (H, W)`` (alpha with C>1 colour channels: (H, W, C)), ``means2d (N, 2)``, ``radii (N,)``,
        ``visible (N,)``, ``depths (N,)``, ``footprints (N,)`` (alpha; else None).
    """
    if compositor not in COMPOSITORS:
        raise CtsplatError(f"unknown compositor {compositor!r}; expected one of {', '.join(COMPOSITORS)}")
    _check_backend(backend, "render")
    if transmission and compositor == "alpha":
        raise CtsplatError("transmission=True only applies to the radiative compositors")
    if background is not None and compositor != "alpha":
        raise CtsplatError("background only applies to the alpha compositor (radiative images have no background)")
    if color_scale is not None and compositor != "alpha":
        raise CtsplatError("color_scale only applies to the alpha compositor (radiative Gaussians have no colour)")
    _check_cutoff(sigma_cutoff)
    if tuple(np.shape(R)) != (3, 3) or tuple(np.shape(t)) != (3,):  # shapes only: no device read-back per call
        raise CtsplatError(f"render needs one pose, R (3, 3) and t (3,); got {tuple(np.shape(R))} and "
                           f"{tuple(np.shape(t))}")
    on_host = [x for x in (R, t) if not (isinstance(x, torch.Tensor) and x.device.type != "cpu")]
    if not all(np.isfinite(np.asarray(x.detach() if isinstance(x, torch.Tensor) else x, float)).all()
               for x in on_host):  # a NaN pose culls every Gaussian: a blank image, not an error, without this
        raise CtsplatError("the camera pose (R, t) contains NaN/Inf")
    if isinstance(mu_scale, bool) or not (isinstance(mu_scale, int | float) and 0 < mu_scale < math.inf):
        raise CtsplatError(f"mu_scale must be a finite number > 0 (1/mm per density unit), got {mu_scale!r}")
    cam = camera_intrinsics(camera)
    H, W = cam["H"], cam["W"]
    _check_tensors(gaussians)
    fused = _fused(backend, gaussians.means.device)
    if fused is not None:
        # the fused kernels treat the pose as fixed
        if any(isinstance(x, torch.Tensor) and x.requires_grad for x in (R, t)):
            raise CtsplatError("the fused render backends give no gradient to the pose (R, t); use "
                               "backend='reference' to differentiate with respect to it")
        # the fused projection flags NaN/Inf in what it reads (one pass, no per-view torch reductions); the full
        # check then names the parameter. What it renders but does not read (alpha colours) is checked here.
        gaussians.validate(check_finite=tuple(p for p in _RENDERED[compositor] if p not in _PROJECTED))
        proj, radii, visible, nonfinite = _project_kernel(fused, gaussians, cam, R, t, compositor, filter_3d_var,
                                                          mip_2d, sigma_cutoff)
        if nonfinite:
            _check_inputs(gaussians, filter_3d_var, compositor)
            raise CtsplatError("Gaussian parameters contain NaN/Inf; lower the learning rate or prune/reset them")
    else:
        _check_inputs(gaussians, filter_3d_var, compositor)
        proj = project(gaussians, camera, R, t, compositor=compositor, filter_3d_var=filter_3d_var,
                       mip_2d=mip_2d, sigma_cutoff=sigma_cutoff)
        bb = proj.bbox
        visible = (bb[:, 1] > bb[:, 0]) & (bb[:, 3] > bb[:, 2])
        radii = torch.where(
            visible, torch.maximum(bb[:, 1] - bb[:, 0], bb[:, 3] - bb[:, 2]).div(2, rounding_mode="floor") + 1, 0
        ).to(torch.int32)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()

    if compositor == "alpha":
        R_t, t_t = _as_pose(R, t, gaussians.means)
        cols = _colors_for_view(gaussians, R_t, t_t, cam["model"])
        if color_scale is not None:
            color_scale = torch.as_tensor(color_scale)
            if color_scale.shape != (cols.shape[0],):
                raise CtsplatError(f"color_scale has shape {tuple(color_scale.shape)}; expected ({cols.shape[0]},), "
                                   "one factor per Gaussian")
            cols = cols * color_scale.to(cols)[:, None]
        bg = None
        if background is not None:
            bg = torch.as_tensor(background, dtype=proj.amps.dtype, device=cols.device).reshape(-1)
            if bg.shape[0] != cols.shape[1]:
                raise CtsplatError(f"background has {bg.shape[0]} channels, the colours {cols.shape[1]}")
            cols = torch.cat([cols, torch.ones_like(cols[:, :1])], dim=1)
        if fused is not None:
            img = fused.AlphaComposite.apply(proj.means2d, proj.conics, proj.amps, cols.to(proj.amps.dtype),
                                             proj.bbox, proj.depths, H, W)
        else:
            img = _reference.splat_alpha_reference(proj, cols, H, W)
        if bg is not None:
            img = img[..., :-1] + (1.0 - img[..., -1:]) * bg
        if img.shape[-1] == 1:
            img = img[..., 0]
    else:
        if fused is not None:
            img = fused.SplatAdditive.apply(proj.means2d, proj.conics, proj.amps, proj.bbox, H, W)
        else:
            img = _reference.splat_additive_reference(proj, H, W)
        if mu_scale != 1.0:
            img = img * mu_scale
        if transmission:
            img = torch.exp(-img)
    footprints = alpha_footprints(proj, H, W) if compositor == "alpha" else None
    return RenderOutput(image=img, means2d=proj.means2d, radii=radii, visible=visible, depths=proj.depths,
                        footprints=footprints)


def _project_kernel(
    fused: ModuleType, gaussians: Gaussians, cam: dict[str, Any], R: Any, t: Any, compositor: str, filter_3d_var: Any,
    mip_2d: bool, sigma_cutoff: float,
) -> tuple[Projection, torch.Tensor, torch.Tensor, bool]:
    """:func:`project` through a fused projection (``fused``: the C kernel on CPU or the Triton kernel,
    float32/float64); also returns ``radii`` (N,) int32, ``visible`` (N,) bool and whether an input held NaN/Inf
    (or a negative filter variance)."""
    means = gaussians.means
    R_t, t_t = _as_pose(R, t, means)
    fv = None
    if filter_3d_var is not None:
        fv = torch.as_tensor(filter_3d_var, dtype=means.dtype, device=means.device).reshape(-1)
        if fv.shape[0] != means.shape[0]:
            raise CtsplatError(f"filter_3d_var has {fv.shape[0]} entries for {means.shape[0]} Gaussians")
    cam_vec = _kernel.camera_vector(cam, R_t, t_t, _dilation(compositor, mip_2d), NEAR_MM, sigma_cutoff)
    mode = {"radiative": 0, "radiative_unrectified": 1, "alpha": 2}[compositor]
    raw = gaussians.density_raw
    if compositor == "alpha":
        # no opacity -> opacity 1 (sigmoid(40) == 1 in float32), as Gaussians.opacities says
        raw = gaussians.opacity_raw if gaussians.opacity_raw is not None else torch.full_like(raw.detach(), 40.0)
    extra = (cam["model"] == "cone",) if fused is _triton else ()  # the Triton kernel compiles per camera model
    m2d, con, amp, depth, bb, radii, valid, visible, nonfinite = fused.Project.apply(
        means, gaussians.log_scales, gaussians.quats, raw, fv, cam_vec, mode, bool(mip_2d), *extra
    )
    proj = Projection(means2d=m2d, conics=con, cov2d=torch.empty(0), amps=amp, depths=depth, valid=valid, bbox=bb)
    return proj, radii, visible, bool(nonfinite)


# ---------------------------------------------------------------------------------------------- 3D filter
def compute_3d_filter(
    gaussians: Gaussians, camera: Any, Rs: Any, ts: Any, *, margin: float = 0.15, factor: float = 0.2
) -> torch.Tensor:
    """Mip-Splatting 3D smoothing-filter variance per Gaussian from the training cameras (no gradient).

    The sampling interval of a camera at a Gaussian is ``T = s`` (parallel: detector spacing, mm) or
    ``T = z / f_x = pitch · z / DSD`` (cone, z = depth in mm). The finest sampling over the cameras that see the
    Gaussian (centre within the image enlarged by ``margin`` on each side, in front of the source) sets the
    filter: ``v = factor · T_min²`` mm² (Mip-Splatting: ``factor = 0.2``). Gaussians seen by no camera get the
    largest ``T_min`` found among the others.

    Parameters
    ----------
    gaussians : Gaussians (N)
    camera : ParallelCamera | ConeCamera
        Shared by the views (see :func:`camera_intrinsics`).
    Rs : array_like (V, 3, 3)
    ts : array_like (V, 3)
        World-to-camera poses of the training views (mm).
    margin : float
        Fraction of the image size added on each side when deciding whether a camera sees a Gaussian.
    factor : float
        ``v = factor · T_min²``.

    Returns
    -------
    Tensor (N,)
        Variance in mm², same dtype/device as the means.
    """
    cam = camera_intrinsics(camera)
    m = gaussians.means.detach()
    n = m.shape[0]
    Rs_t = torch.as_tensor(Rs, dtype=m.dtype, device=m.device).reshape(-1, 3, 3)
    ts_t = torch.as_tensor(ts, dtype=m.dtype, device=m.device).reshape(-1, 3)
    if Rs_t.shape[0] != ts_t.shape[0]:
        raise CtsplatError(f"compute_3d_filter: {Rs_t.shape[0]} rotations but {ts_t.shape[0]} translations; pass one "
                           "pose per camera")
    best = torch.full((n,), math.inf, dtype=m.dtype, device=m.device)
    W, H = cam["W"], cam["H"]
    for R_v, t_v in zip(Rs_t, ts_t, strict=True):
        xc = m @ R_v.T + t_v
        if cam["model"] == "parallel":
            u = xc[:, 0] / cam["sx"] + cam["cx"]
            v = xc[:, 1] / cam["sy"] + cam["cy"]
            interval = torch.full_like(u, min(cam["sx"], cam["sy"]))
            front = torch.ones_like(u, dtype=torch.bool)
        else:
            z = xc[:, 2]
            front = z > NEAR_MM
            zs = torch.where(front, z, torch.ones_like(z))
            u = cam["fx"] * xc[:, 0] / zs + cam["cx"]
            v = cam["fy"] * xc[:, 1] / zs + cam["cy"]
            interval = zs / max(cam["fx"], cam["fy"])
        seen = front & (u >= -margin * W) & (u <= (1 + margin) * W) & (v >= -margin * H) & (v <= (1 + margin) * H)
        best = torch.where(seen, torch.minimum(best, interval), best)
    finite = torch.isfinite(best)
    if n and not bool(finite.all()):
        fill = best[finite].max() if bool(finite.any()) else torch.tensor(
            cam.get("sx", 1.0) if cam["model"] == "parallel" else 1.0, dtype=m.dtype)
        best = torch.where(finite, best, fill.to(best))
    return factor * best**2


# ---------------------------------------------------------------------------------------------- voxelizer
def random_region(
    shape: tuple[int, int, int], size: int | tuple[int, int, int], generator: torch.Generator | None = None
) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    """A random sub-volume of ``size`` voxels per axis (clipped to ``shape``), for :func:`voxelize`'s ``region``.

    Parameters
    ----------
    shape : (I, J, K)
        Grid size in voxels.
    size : int or (int, int, int)
        Sub-volume size in voxels (per axis).
    generator : torch.Generator or None
        Source of the random start indices.

    Returns
    -------
    ((i0, i1), (j0, j1), (k0, k1))
        Half-open voxel index ranges.
    """
    sz = (size,) * 3 if isinstance(size, int) else tuple(size)
    out = []
    for dim, s in zip(shape, sz, strict=True):
        s = min(int(s), int(dim))
        start = int(torch.randint(0, int(dim) - s + 1, (1,), generator=generator))
        out.append((start, start + s))
    return tuple(out)  # type: ignore[return-value]


def voxelize(
    gaussians: Gaussians,
    shape: tuple[int, int, int],
    affine: Any,
    *,
    chunk: int = 1_000_000,
    region: tuple[tuple[int, int], tuple[int, int], tuple[int, int]] | None = None,
    filter_3d_var: torch.Tensor | None = None,
    sigma_cutoff: float = 3.0,
    backend: str = "auto",
) -> torch.Tensor:
    """Differentiable ``μ(x) = Σ ρ_i exp(-½ (x-m_i)ᵀ Σ_i⁻¹ (x-m_i))`` at voxel centres ``affine @ [i, j, k, 1]``.

    Each Gaussian touches only the voxels inside its ``sigma_cutoff``-σ bounding box in index space (half extent
    along index axis ``a``: ``k sqrt((A⁻¹ Σ A⁻ᵀ)_aa)``, ``A = affine[:3, :3]``). (Gaussian, voxel) pairs are processed
    in chunks of at most ``chunk`` pairs (a single Gaussian larger than ``chunk`` forms its own chunk) and added in
    place into the output; the backward re-computes each chunk, so peak memory is the output grid plus one chunk
    (about 100 bytes per pair: ~100 MB at the default 1M pairs), whatever N is.

    Parameters
    ----------
    gaussians : Gaussians (N)
    shape : (I, J, K)
        Full grid size in voxels.
    affine : array_like (4, 4)
        Voxel index -> world mm; a singular or non-finite one fails (checked unless it is a tensor on a GPU).
    chunk : int
        Reference path: (Gaussian, voxel) pairs per chunk.
    region : ((i0, i1), (j0, j1), (k0, k1)) or None
        Evaluate only this half-open sub-volume (see :func:`random_region`); output has the region's shape.
    filter_3d_var : Tensor (N,) or None
        Variance in mm² of the mass-conserving 3D filter (as in :func:`render`).
    sigma_cutoff : float
        Box half-extent in standard deviations.
    backend : "auto" | "reference" | "kernel" | "triton"
        "auto": the fused C++ kernel on CPU when available (hand-written backward, memory = output grid + O(N);
        ``chunk`` is then unused), the Triton kernel on CUDA when triton is installed, else the chunked PyTorch
        reference.

    Returns
    -------
    Tensor (I, J, K) (or the region's shape), density units of ρ, same dtype/device as the means.
    """
    gaussians.validate()
    _check_tensors(gaussians)
    _check_backend(backend, "voxelize")
    means = gaussians.means
    dtype, dev = means.dtype, means.device
    _check_cutoff(sigma_cutoff)
    if filter_3d_var is not None and int(torch.as_tensor(filter_3d_var).numel()) != means.shape[0]:
        raise CtsplatError(f"filter_3d_var has {int(torch.as_tensor(filter_3d_var).numel())} values for "
                           f"{means.shape[0]} Gaussians; compute it for this model (compute_3d_filter)")
    if not (isinstance(filter_3d_var, torch.Tensor) and filter_3d_var.device.type != "cpu"):
        _check_filter_var(filter_3d_var)  # where the values are on the host: no device read-back per call
    if tuple(np.shape(affine)) != (4, 4) or len(tuple(shape)) != 3:
        raise CtsplatError(f"voxelize needs a (4, 4) affine and a grid shape (I, J, K); got {tuple(np.shape(affine))} "
                           f"and {tuple(shape)}")
    if region is not None and tuple(np.shape(region)) != (3, 2):
        raise CtsplatError(f"voxelize region must be ((i0, i1), (j0, j1), (k0, k1)), got {region}")
    if not (isinstance(affine, torch.Tensor) and affine.device.type != "cpu"):
        # checked on the host when it is there (a device affine would cost a read-back per call): the inverse
        # below is taken without an error flag
        a3 = np.asarray(affine.detach() if isinstance(affine, torch.Tensor) else affine, float)
        a3 = a3.reshape(4, 4)[:3, :3]
        if not np.isfinite(a3).all() or np.linalg.matrix_rank(a3) < 3:
            raise CtsplatError(f"voxelize affine {a3.tolist()} is singular or not finite; pass the volume's "
                               "voxel-to-mm affine")
    A = torch.as_tensor(affine, dtype=dtype, device=dev).reshape(4, 4)
    shape = tuple(int(s) for s in shape)
    if region is None:
        region = ((0, shape[0]), (0, shape[1]), (0, shape[2]))
    # checked on the host (the region is small integers): no device round trip per call
    bounds = [(int(a), int(b)) for a, b in torch.as_tensor(region, dtype=torch.int64).cpu().reshape(3, 2).tolist()]
    if any(a < 0 or b > s or b <= a for (a, b), s in zip(bounds, shape, strict=True)):
        raise CtsplatError(f"voxelize region {region} is empty or outside the grid {shape}")
    reg = torch.tensor(bounds, dtype=torch.int64, device=dev)
    out_shape = tuple(b - a for a, b in bounds)
    n_out = out_shape[0] * out_shape[1] * out_shape[2]
    fvar = None if filter_3d_var is None else torch.as_tensor(filter_3d_var, dtype=dtype, device=dev).reshape(-1, 1)
    # boxes first, without gradients, so that the differentiable terms below are built for the Gaussians that reach
    # the output only (a small region, as the TV term's, keeps a small share of them)
    with torch.no_grad():
        Ainv = torch.linalg.inv_ex(A[:3, :3])[0]  # inv_ex: no host synchronisation for the error flag
        if dev.type == "cpu" and dtype in (torch.float32, torch.float64) and _kernel.available():
            # the same arithmetic in one threaded C pass: on CPU the tensor version below costs more than the
            # voxelizer itself for a small region (a dozen N-sized temporaries)
            lo, ext = _kernel.voxel_boxes(means, gaussians.log_scales, gaussians.quats, fvar, Ainv, A[:3, 3], reg,
                                          sigma_cutoff)
        else:
            s2f = torch.exp(2 * gaussians.log_scales) + (0.0 if fvar is None else fvar)
            # variance along index axis a: (A⁻¹ R diag(s²) Rᵀ A⁻ᵀ)_aa = Σ_k (A⁻¹ R)_ak² s²_k
            rot_t = quat_to_rotmat(gaussians.quats).transpose(-1, -2).reshape(-1, 3)
            ar_t = (rot_t @ Ainv.T).reshape(-1, 3, 3)  # (A⁻¹ R)ᵀ per Gaussian
            var_idx = (ar_t.square() * s2f[:, :, None]).sum(1)
            centre = (means - A[:3, 3]) @ Ainv.T
            half = sigma_cutoff * torch.sqrt(var_idx.clamp_min(0))
            rlo, rhi = reg[:, 0].to(dtype), reg[:, 1].to(dtype)
            lo = torch.ceil(centre - half).clamp(min=rlo, max=rhi).to(torch.int64)
            hi = (torch.floor(centre + half) + 1).clamp(min=rlo, max=rhi).to(torch.int64)
            ext = (hi - lo).clamp_min(0)
        keep = torch.nonzero(ext.prod(-1) > 0).flatten()
    if keep.numel() == 0:
        # zero, still connected to every parameter it depends on (a backward through it must not fail)
        linked = (gaussians.densities.sum() + means.sum() + gaussians.log_scales.sum() + gaussians.quats.sum())
        return torch.zeros(n_out, dtype=dtype, device=dev).reshape(out_shape) + 0 * linked

    def kept(t: torch.Tensor) -> torch.Tensor:  # no copy when every Gaussian reaches the output
        return t if keep.numel() == len(t) else t[keep]

    s2 = torch.exp(2 * kept(gaussians.log_scales))
    dens = kept(gaussians.densities)
    if fvar is not None:
        s2f_k = s2 + kept(fvar)
        dens = dens * _filter_compensation(kept(gaussians.log_scales), s2, s2f_k, torch.log(s2f_k))
    else:
        s2f_k = s2
    # precision R diag(1/s²) Rᵀ: its 6 distinct entries
    rot = quat_to_rotmat(kept(gaussians.quats))
    prec = (rot / s2f_k[:, None, :]) @ rot.transpose(-1, -2)
    prec6 = torch.stack([prec[:, 0, 0], prec[:, 1, 1], prec[:, 2, 2], prec[:, 0, 1], prec[:, 0, 2], prec[:, 1, 2]], -1)
    fused = _fused(backend, dev)
    args = (kept(means), prec6, dens, kept(lo), kept(ext), A, reg[:, 0], out_shape)
    if fused is not None:
        out = fused.Voxelize.apply(*args)
    else:
        out = _reference.voxelize_reference(*args, chunk)
    return out.reshape(out_shape)


# ---------------------------------------------------------------------------------------------- batch rendering
#: The files of a :func:`render_to_folder` output beside its ``render.json``.
RENDER_FILES = ("images.tif", "png/view_*.png")


def render_to_folder(
    model_path: Any,
    views_path: Any,
    out_dir: Any,
    *,
    compositor: str | None = None,
    split: str | None = None,
    mip: bool | None = None,
    mu_scale: float | None = None,
    device: str = "cpu",
) -> dict[str, Any]:
    """Render every view of a ``views.json`` with a saved model into a folder (the ``ctsplat render`` step).

    Writes ``images.tif``: float32 pages (V, H, W) in view-set order -- line integrals (radiative modes, times
    ``mu_scale``) or composited grey values (alpha); ``png/view_{id:04d}.png``: 16-bit transmission ``exp(-p)``
    (radiative) or the clipped [0, 1] image (alpha); ``render.json``: what was rendered and how long it took.

    Parameters
    ----------
    model_path : str or Path
        Model ``.pt`` (:meth:`Gaussians.save`).
    views_path : str or Path
        ``views.json`` of a radiograph view set.
    out_dir : str or Path
        Output folder: new, empty or an earlier render (with ``render.json``), and neither an input nor a folder
        holding one; written whole or not at all (:func:`ctsplat.utils.atomic_dir`).
    compositor : {"radiative", "radiative_unrectified", "alpha"} or None
        Default: the one the model was trained with (``meta["compositor"]``), else ``"radiative"``.
    split : {"train", "val", "test"} or None
        Only this split's views.
    mip : bool or None
        The model's own 3D filter (the one it was trained with, when it was saved with one), else one computed from
        the view set's ``train`` views (all views if it has none); and the 2D mip filter. Default: as the model was
        trained (``meta["mip"]``, else whether it was saved with a 3D filter).
    mu_scale : float or None
        Density factor (1/mm per normalised unit); default the model's ``meta["mu_scale_per_mm"]``, else 1.
    device : str
        "cpu", "cuda" or "auto".

    Returns
    -------
    dict
        The ``render.json`` content (``n_views``, ``n_gaussians``, ``seconds``, ...).
    """
    import time

    import imageio.v3 as iio
    import numpy as np
    import tifffile

    from ctsplat.formats.viewset import ViewSet
    from ctsplat.utils import atomic_dir, check_output_dir, code_version, resolve_device, write_json_atomic

    # before the slow part
    check_output_dir(out_dir, marker="render.json", contents=RENDER_FILES, inputs=(model_path, views_path))
    dev = resolve_device(device)
    g = Gaussians.load(model_path, device=dev)
    vs = ViewSet.load(views_path)
    scale = mu_scale if mu_scale is not None else g.meta.get("mu_scale_per_mm", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, int | float) or not (math.isfinite(scale) and scale > 0):
        raise CtsplatError(f"{model_path} records mu_scale_per_mm {scale!r}, not a finite number > 0; give the "
                           "scale to 1/mm with --mu-scale")
    scale = float(scale)
    if compositor is None:
        compositor = str(g.meta.get("compositor", "radiative"))
    if mip is None:
        mip = bool(g.meta.get("mip", g.filter_3d_var is not None))
    fv = g.filter_3d_var if mip else None
    if mip and fv is None:  # that of the training views (the views themselves when none), before any subset
        train_idx = vs.indices("train")
        base = vs if train_idx.size == 0 else ViewSet(vs.camera, [vs.views[i] for i in train_idx])
        fv = compute_3d_filter(g, vs.camera, base.Rs(), base.ts())
    if split is not None:
        vs = vs.subset(split)
    images = []
    t0 = time.perf_counter()
    with torch.no_grad():
        for view in vs.views:
            out = render(g, vs.camera, view.R, view.t, compositor=compositor, filter_3d_var=fv, mip_2d=mip,
                         mu_scale=scale if compositor != "alpha" else 1.0)
            img = out.image if out.image.ndim == 2 else out.image.mean(-1)
            images.append(img.detach().cpu().float().numpy())
    seconds = time.perf_counter() - t0
    stack = np.stack(images).astype(np.float32)
    if not np.isfinite(stack).all():  # e.g. a huge --mu-scale overflows float32
        raise CtsplatError(f"rendering {model_path} gave non-finite pixels (mu_scale {scale:g}); use a smaller "
                           "--mu-scale, or check the model")
    info = {"model": str(model_path), "views": str(views_path), "compositor": compositor, "split": split,
            "mip": mip, "mu_scale": scale, "n_views": len(vs), "n_gaussians": len(g), "seconds": seconds,
            "code_version": code_version()}
    # the whole folder or nothing: it replaces an earlier render only once every file is written
    with atomic_dir(out_dir, marker="render.json", contents=RENDER_FILES, inputs=(model_path, views_path)) as tmp:
        tifffile.imwrite(tmp / "images.tif", stack, photometric="minisblack", metadata={"axes": "QYX"})
        (tmp / "png").mkdir()
        for view, img in zip(vs.views, stack, strict=True):
            vis = np.exp(-img.astype(np.float64)) if compositor != "alpha" else img
            png = np.round(np.clip(vis, 0.0, 1.0) * 65535.0).astype(np.uint16)
            iio.imwrite(tmp / "png" / f"view_{view.id:04d}.png", png, extension=".png")
        write_json_atomic(tmp / "render.json", info)
    return info
