"""The method's training features beside the core loop: view augmentation, the early density-regulariser schedule
and redundant-coverage pruning.

- :func:`perturb_pose` / :class:`Augmenter`: conservative augmentation of a training view by moving its *camera*
  (a rotation of at most ``rot_deg`` about the volume centre and an in-plane shift of at most ``shift_px``
  detector pixels), never by warping the radiograph, so image and geometry stay consistent; plus mild Gaussian
  noise on the target. Only training steps use it; validation and evaluation render at the recorded poses.
- :func:`density_lambda`: λρ × ``factor`` for the first ``fraction`` of the iterations, then a cosine decay over
  ``decay`` of them to the base λρ (floaters are suppressed while the model is still coarse).
- :func:`merge_redundant`: nearly coincident Gaussians (centres within ``distance`` × their mean scale, scales and
  covariances within a relative tolerance) are merged into one; in the radiative compositors the merged Gaussian
  carries both masses, so the rendered views change by less than the covariance tolerance allows.

References
----------
Zha, R. et al. (2024). R²-Gaussian: rectifying radiative Gaussian splatting for tomographic reconstruction.
NeurIPS.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

__all__ = ["pixel_mm", "perturb_pose", "Augmenter", "density_lambda", "redundant_pairs", "merge_redundant"]


def pixel_mm(camera: Any) -> float:
    """Size of one detector pixel at the isocentre (mm): parallel ``spacing_mm``, cone ``pitch_mm / magnification``.

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera

    Returns
    -------
    float
        mm per pixel in the plane through the isocentre.
    """
    if hasattr(camera, "spacing_mm"):
        return float(camera.spacing_mm)
    return float(camera.pitch_mm) / float(camera.magnification)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / max(float(np.linalg.norm(axis)), 1e-12)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def perturb_pose(R: np.ndarray, t: np.ndarray, center_mm: np.ndarray, rot_deg: float, shift_mm: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A camera pose moved by a random rotation of at most ``rot_deg`` about ``center_mm`` and an in-plane shift of
    at most ``shift_mm``.

    With ``x_cam = R x + t`` and ``c = R center + t`` the centre in camera coordinates, the new pose is
    ``x_cam' = ΔR (x_cam - c) + c + δ``: ``R' = ΔR R``, ``t' = ΔR (t - c) + c + δ``, ``δ = (δx, δy, 0)``.

    Parameters
    ----------
    R : ndarray (3, 3)
    t : ndarray (3,)
        World-to-camera pose (mm).
    center_mm : ndarray (3,)
        The point the camera turns about (the volume centre), world mm.
    rot_deg : float
        Largest rotation angle (degrees); the angle is uniform in ``[0, rot_deg]`` about a uniform random axis.
    shift_mm : float
        Largest shift (mm), uniform over the disc of that radius in the detector plane.
    rng : numpy.random.Generator

    Returns
    -------
    R', t' : ndarray (3, 3), ndarray (3,)
    """
    axis = rng.normal(size=3)
    angle = math.radians(float(rot_deg)) * float(rng.uniform())
    dR = _axis_angle(axis, angle)
    r = float(shift_mm) * math.sqrt(float(rng.uniform()))
    phi = 2.0 * math.pi * float(rng.uniform())
    delta = np.array([r * math.cos(phi), r * math.sin(phi), 0.0])
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    c = R @ np.asarray(center_mm, float) + t
    return dR @ R, dR @ (t - c) + c + delta


class Augmenter:
    """Per-step augmentation of training views (see the module docstring); a no-op when disabled.

    Parameters
    ----------
    settings : dict
        The ``train.augment`` section (``enabled``, ``rot_deg``, ``shift_px``, ``target_noise``).
    camera : ParallelCamera or ConeCamera
        The training views' camera (its pixel size turns ``shift_px`` into mm).
    center_mm : ndarray (3,)
        The volume centre (rotation centre), world mm.
    """

    def __init__(self, settings: dict[str, Any], camera: Any, center_mm: np.ndarray) -> None:
        self.enabled = bool(settings["enabled"])
        self.rot_deg = float(settings["rot_deg"])
        self.shift_mm = float(settings["shift_px"]) * pixel_mm(camera)
        self.noise = float(settings["target_noise"])
        self.center = np.asarray(center_mm, float)

    def pose(self, R: torch.Tensor, t: torch.Tensor, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """The pose a training step renders with: ``(R, t)`` itself when disabled (nothing drawn), else perturbed.

        Parameters
        ----------
        R : Tensor (3, 3)
        t : Tensor (3,)
        rng : numpy.random.Generator
            The run's generator (checkpointed, so a resumed run draws the same perturbations).

        Returns
        -------
        R', t' : Tensor (3, 3), Tensor (3,)
            Same dtype and device as the inputs.
        """
        if not self.enabled or (self.rot_deg == 0 and self.shift_mm == 0):
            return R, t
        R2, t2 = perturb_pose(R.detach().cpu().double().numpy(), t.detach().cpu().double().numpy(), self.center,
                              self.rot_deg, self.shift_mm, rng)
        return torch.as_tensor(R2, dtype=R.dtype, device=R.device), torch.as_tensor(t2, dtype=t.dtype, device=t.device)

    def target(self, ref: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """``ref`` plus N(0, ``target_noise``²) noise (images scaled to [0, 1]); ``ref`` itself when disabled.

        Parameters
        ----------
        ref : Tensor (B, H, W)
            Targets in the loss's units.
        gen : torch.Generator
            The run's CPU generator (checkpointed).

        Returns
        -------
        Tensor (B, H, W)
        """
        if not self.enabled or self.noise == 0:
            return ref
        noise = torch.randn(ref.shape, generator=gen, dtype=torch.float32).to(ref)
        return ref + self.noise * noise


def density_lambda(base: float, iteration: int, total: int, warmup: dict[str, Any]) -> float:
    """λρ at a step: ``base × factor`` up to ``fraction × total``, a cosine down to ``base`` over the next
    ``decay × total`` iterations, then ``base``.

    Parameters
    ----------
    base : float
        ``lambda_density``.
    iteration : int
        Completed iterations before this step (0 for the first).
    total : int
        Iterations of the run.
    warmup : dict
        The ``train.lambda_density_warmup`` section (``factor`` >= 1, ``fraction``, ``decay`` in [0, 1]).

    Returns
    -------
    float

    Examples
    --------
    >>> w = {"factor": 10.0, "fraction": 0.1, "decay": 0.1}
    >>> [round(density_lambda(1.0, i, 100, w), 3) for i in (0, 9, 10, 15, 20, 50)]
    [10.0, 10.0, 10.0, 5.5, 1.0, 1.0]
    """
    factor = float(warmup["factor"])
    if factor == 1.0:
        return float(base)
    x = iteration / max(int(total), 1)
    hold, decay = float(warmup["fraction"]), float(warmup["decay"])
    if x <= hold:
        w = 1.0
    elif decay > 0 and x < hold + decay:
        w = 0.5 * (1.0 + math.cos(math.pi * (x - hold) / decay))
    else:
        w = 0.0
    return float(base) * (1.0 + (factor - 1.0) * w)


def _covariances(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    from ctsplat.splat.gaussians import quat_to_rotmat

    rot = quat_to_rotmat(quats)
    s2 = torch.exp(2.0 * log_scales)
    return rot @ torch.diag_embed(s2) @ rot.transpose(-1, -2)


def redundant_pairs(params: dict[str, torch.Tensor], settings: dict[str, Any]) -> torch.Tensor:
    """Pairs of nearly coincident Gaussians, each Gaussian in at most one pair.

    A pair ``(i, j)`` qualifies when ``‖μi - μj‖ <= distance × min(mean scale)``, every scale differs by at most
    ``scale_tol`` (relative, sorted per Gaussian so axis order does not matter) and
    ``‖Σi - Σj‖_F <= cov_tol × ‖Σi‖_F``. Pairs are taken greedily, closest first.

    Parameters
    ----------
    params : dict of str to Tensor
        ``means`` (N, 3) mm, ``log_scales`` (N, 3), ``quats`` (N, 4).
    settings : dict
        The ``train.densify.prune_redundant`` section.

    Returns
    -------
    Tensor (P, 2) int64
        ``(keep, drop)`` index pairs.
    """
    from scipy.spatial import cKDTree

    means = params["means"].detach().double().cpu()
    ls = params["log_scales"].detach().double().cpu()
    n = means.shape[0]
    empty = torch.zeros((0, 2), dtype=torch.int64)
    dist = float(settings["distance"])
    if n < 2 or dist <= 0:
        return empty
    mscale = torch.exp(ls).mean(-1)
    radius = dist * float(mscale.max())
    cand = cKDTree(means.numpy()).query_pairs(radius, output_type="ndarray")
    if cand.size == 0:
        return empty
    i, j = torch.as_tensor(cand[:, 0]), torch.as_tensor(cand[:, 1])
    d = (means[i] - means[j]).norm(dim=-1)
    ok = d <= dist * torch.minimum(mscale[i], mscale[j])
    si, sj = torch.exp(ls[i]).sort(-1).values, torch.exp(ls[j]).sort(-1).values
    ok &= ((si - sj).abs() <= float(settings["scale_tol"]) * torch.maximum(si, sj)).all(-1)
    i, j, d = i[ok], j[ok], d[ok]
    if i.numel() == 0:
        return empty
    q = params["quats"].detach().double().cpu()
    ci, cj = _covariances(ls[i], q[i]), _covariances(ls[j], q[j])
    ok = torch.linalg.matrix_norm(ci - cj) <= float(settings["cov_tol"]) * torch.linalg.matrix_norm(ci)
    i, j, d = i[ok], j[ok], d[ok]
    used = np.zeros(n, dtype=bool)
    out = []
    for k in torch.argsort(d, stable=True).tolist():
        a, b = int(i[k]), int(j[k])
        if not used[a] and not used[b]:
            used[a] = used[b] = True
            out.append((a, b))
    return torch.as_tensor(out, dtype=torch.int64).reshape(-1, 2)


def merge_redundant(params: dict[str, torch.Tensor], settings: dict[str, Any], compositor: str
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Which Gaussians survive a redundant-coverage merge, and the merged values of the kept ones.

    Radiative compositors: the kept Gaussian of a pair takes the pair's mass, ``ρ = (ρi Vi + ρj Vj) / Vi``
    (``V = Π s``), so the sum of both footprints is preserved up to their (small) shape difference. Alpha: the
    kept opacity is ``1 - (1 - oi)(1 - oj)``.

    Parameters
    ----------
    params : dict of str to Tensor
        The training parameters (``density_raw``; ``opacity_raw`` for alpha).
    settings : dict
        The ``train.densify.prune_redundant`` section.
    compositor : str

    Returns
    -------
    drop : Tensor (N,) bool
        Gaussians removed.
    updates : dict of str to Tensor
        Full replacement tensors (N rows) for the parameters whose kept rows changed (``density_raw`` or
        ``opacity_raw``); empty when nothing merges.
    """
    from ctsplat.splat.gaussians import inverse_softplus

    n = params["means"].shape[0]
    dev = params["means"].device
    pairs = redundant_pairs(params, settings).to(dev)
    drop = torch.zeros(n, dtype=torch.bool, device=dev)
    if pairs.shape[0] == 0:
        return drop, {}
    a, b = pairs[:, 0], pairs[:, 1]
    drop[b] = True
    with torch.no_grad():
        if compositor == "alpha":
            op = torch.sigmoid(params["opacity_raw"].detach())
            new = op.clone()
            new[a] = 1.0 - (1.0 - op[a]) * (1.0 - op[b])
            return drop, {"opacity_raw": torch.logit(new.clamp(1e-6, 1 - 1e-6))}
        dens = torch.nn.functional.softplus(params["density_raw"].detach())
        vol = torch.exp(params["log_scales"].detach().sum(-1))
        new = dens.clone()
        new[a] = (dens[a] * vol[a] + dens[b] * vol[b]) / vol[a]
        return drop, {"density_raw": inverse_softplus(new.clamp_min(1e-12))}
