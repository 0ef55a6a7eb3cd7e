"""The Gaussian model: a plain container of tensors, activations, ``.pt`` save/load and 3DGS PLY export.

The attenuation field of ``N`` Gaussians (conventions.md) is

.. math::

    \\mu(x) = \\sum_i \\rho_i \\exp\\big(-\\tfrac12 (x - m_i)^T \\Sigma_i^{-1} (x - m_i)\\big),
    \\qquad \\Sigma_i = R(q_i)\\, S_i S_i^T R(q_i)^T,\\; S_i = \\mathrm{diag}(e^{\\ell_i}),

with means ``m`` in world mm, log-scales ``ℓ`` (scales in mm), wxyz quaternions ``q`` (normalised where used),
densities ``ρ = softplus(density_raw)`` (in the units of the volume the model is trained against, i.e. the
normalised volume; multiply by ``mu_scale_per_mm`` for 1/mm). For the alpha compositor the model also has
``opacity = sigmoid(opacity_raw)`` and a colour: ``colors (N, C)`` is the view-independent base colour (grey ``C=1``
or RGB ``C=3``) and optional ``sh_rest (N, K-1, C)`` holds real spherical-harmonic coefficients of degree
1..3 (``K = (deg+1)^2``) added on top (3DGS convention: ``c(d) = colors + sum_k Y_k(d) sh_rest_k``, clamped at 0).

References
----------
.. [1] B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian Splatting for Real-Time Radiance Field
   Rendering", ACM Transactions on Graphics 42(4), 2023 (parameterisation, SH basis, PLY layout).
.. [2] R. Zha, T. J. Lin, Y. Cai, J. Cao, Y. Zhang, H. Li, "R²-Gaussian: Rectifying Radiative Gaussian Splatting
   for Tomographic Reconstruction", NeurIPS 2024 (Gaussians as a density field).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ctsplat.formats.ply import write_ply_vertices
from ctsplat.utils import CtsplatError, save_torch_atomic

__all__ = ["Gaussians", "quat_to_rotmat", "covariance", "inverse_softplus", "eval_sh", "SH_C0", "SH_REST_SIZES"]

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))
#: Coefficients per channel of ``sh_rest`` at SH degrees 1, 2 and 3: ``(d + 1)² - 1``.
SH_REST_SIZES = (3, 8, 15)
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)
_FORMAT_VERSION = 1


def inverse_softplus(y: torch.Tensor) -> torch.Tensor:
    """Inverse of ``softplus``: ``x = y + log(-expm1(-y))`` (stable for small and large ``y > 0``).

    Parameters
    ----------
    y : Tensor (any shape)
        Values > 0 (activated densities).

    Returns
    -------
    Tensor (same shape)
        ``x`` with ``softplus(x) = y``.
    """
    y = torch.as_tensor(y)
    return y + torch.log(-torch.expm1(-y))


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from (not necessarily unit) wxyz quaternions.

    Parameters
    ----------
    quats : Tensor (N, 4)
        ``(w, x, y, z)``; normalised here.

    Returns
    -------
    Tensor (N, 3, 3)
        Rotation matrices (world from local axes).
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    r = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return r.reshape(q.shape[:-1] + (3, 3))


def covariance(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """World covariances ``Σ = R diag(s²) Rᵀ``.

    Parameters
    ----------
    log_scales : Tensor (N, 3)
        Natural log of the standard deviations (mm).
    quats : Tensor (N, 4)
        wxyz quaternions (normalised here).

    Returns
    -------
    Tensor (N, 3, 3)
        Covariances in mm².
    """
    rot = quat_to_rotmat(quats)
    m = rot * torch.exp(log_scales)[..., None, :]  # R S
    return m @ m.transpose(-1, -2)


def eval_sh(sh_rest: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Sum of the degree-1..3 real SH terms (3DGS basis and sign convention).

    Parameters
    ----------
    sh_rest : Tensor (N, K-1, C), K in {4, 9, 16}
        Coefficients of degrees 1..3 (colour units).
    dirs : Tensor (N, 3)
        Unit viewing directions (camera centre -> Gaussian) in world frame.

    Returns
    -------
    Tensor (N, C)
        ``sum_k Y_k(d) sh_rest_k`` (colour units), to be added to the base colour.
    """
    k = sh_rest.shape[1] + 1
    x, y, z = dirs.unbind(-1)
    basis = [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if k > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [
            _SH_C2[0] * xy, _SH_C2[1] * yz, _SH_C2[2] * (2 * zz - xx - yy), _SH_C2[3] * xz, _SH_C2[4] * (xx - yy),
        ]
        if k > 9:
            basis += [
                _SH_C3[0] * y * (3 * xx - yy), _SH_C3[1] * xy * z, _SH_C3[2] * y * (4 * zz - xx - yy),
                _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _SH_C3[4] * x * (4 * zz - xx - yy),
                _SH_C3[5] * z * (xx - yy), _SH_C3[6] * x * (xx - 3 * yy),
            ]
    b = torch.stack(basis, dim=-1)  # (N, K-1)
    return (b[..., None] * sh_rest).sum(dim=1)


def _rows(x: torch.Tensor, n: int, width: int | None, name: str) -> torch.Tensor:
    """``x`` as ``(n, width)`` (``(n,)`` for width None), or one line naming the argument that does not fit."""
    shape = (n,) if width is None else (n, width)
    try:
        return x.reshape(shape)
    except RuntimeError:
        want = "N" if n == -1 else str(n)
        expected = f"({want},)" if width is None else f"({want}, {'C' if width == -1 else width})"
        raise CtsplatError(f"from_values: {name} of shape {tuple(x.shape)} does not fit {want} Gaussians "
                           f"(expected {expected})") from None


@dataclass
class Gaussians:
    """``N`` anisotropic 3D Gaussians as plain tensors (any device/dtype; parameters may require grad).

    Attributes
    ----------
    means : Tensor (N, 3)
        Centres in world mm.
    log_scales : Tensor (N, 3)
        Natural log of the standard deviations along the local axes (mm).
    quats : Tensor (N, 4)
        Rotations as wxyz quaternions (normalised where used).
    density_raw : Tensor (N,)
        ``ρ = softplus(density_raw)`` (normalised-volume units; see module docstring).
    opacity_raw : Tensor (N,) or None
        ``opacity = sigmoid(opacity_raw)`` for the alpha compositor; ``None`` means opacity 1.
    colors : Tensor (N, C) or None
        Base colour (grey C=1, RGB C=3) for the alpha compositor; ``None`` means grey 1.
    sh_rest : Tensor (N, K-1, C) or None
        Degree 1..3 SH coefficients (``K = (deg+1)^2``).
    meta : dict
        Provenance (JSON-like values).
    filter_3d_var : Tensor (N,) or None
        The Mip-Splatting 3D filter variance (mm²) the model was trained with, saved with it so that it is
        rendered and scored with that filter (as Mip-Splatting stores its ``filter_3D``); None without one.
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    density_raw: torch.Tensor
    opacity_raw: torch.Tensor | None = None
    colors: torch.Tensor | None = None
    sh_rest: torch.Tensor | None = None
    meta: dict = field(default_factory=dict)
    filter_3d_var: torch.Tensor | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_values(
        cls,
        means: torch.Tensor | np.ndarray,
        scales_mm: torch.Tensor | np.ndarray | float,
        densities: torch.Tensor | np.ndarray | float,
        quats: torch.Tensor | np.ndarray | None = None,
        *,
        opacities: torch.Tensor | np.ndarray | float | None = None,
        colors: torch.Tensor | np.ndarray | None = None,
        sh_degree: int = 0,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> Gaussians:
        """Build from activated values.

        Parameters
        ----------
        means : array_like (N, 3)
            Centres, world mm.
        scales_mm : array_like (N, 3), (N,) or scalar
            Standard deviations in mm (> 0).
        densities : array_like (N,) or scalar
            ρ > 0 (normalised-volume units).
        quats : array_like (N, 4) or None
            wxyz rotations; None is the identity.
        opacities : array_like (N,) or scalar in (0, 1), optional
        colors : array_like (N, C), optional
        sh_degree : int in 0..3
            Allocates zero ``sh_rest`` of ``(deg+1)^2 - 1`` coefficients when > 0.
        dtype, device
            Of the tensors.

        Returns
        -------
        Gaussians
            With ``log_scales = log(scales_mm)``, ``density_raw = softplus⁻¹(ρ)``, ``opacity_raw = logit(o)``.
        """
        kw = {"dtype": dtype, "device": device}
        means_t = _rows(torch.as_tensor(means, **kw), -1, 3, "means")
        n = means_t.shape[0]
        scales = torch.as_tensor(scales_mm, **kw)
        if scales.ndim == 0:
            scales = scales.expand(n, 3)
        elif scales.ndim == 1 and scales.shape[0] == n:  # one isotropic scale per Gaussian (also when n is 3)
            scales = scales[:, None].expand(n, 3)
        else:
            scales = _rows(scales, n, 3, "scales_mm")
        if not bool(torch.all(scales > 0)):
            raise CtsplatError("from_values: scales_mm must be > 0 (standard deviations in mm)")
        dens = torch.as_tensor(densities, **kw)
        dens = dens.expand(n) if dens.ndim == 0 else _rows(dens, n, None, "densities")
        if not bool(torch.all(dens > 0)):
            raise CtsplatError("from_values: densities must be > 0 (softplus-parameterised)")
        q = torch.zeros(n, 4, **kw)
        q[:, 0] = 1.0
        if quats is not None:
            q = _rows(torch.as_tensor(quats, **kw), n, 4, "quats").clone()
        op_raw = None
        if opacities is not None:
            op = torch.as_tensor(opacities, **kw)
            op = op.expand(n) if op.ndim == 0 else _rows(op, n, None, "opacities")
            if not bool(torch.all((op > 0) & (op < 1))):
                raise CtsplatError("from_values: opacities must lie in (0, 1)")
            op_raw = torch.logit(op)
        cols = None if colors is None else _rows(torch.as_tensor(colors, **kw), n, -1, "colors").clone()
        sh_rest = None
        if sh_degree:
            if sh_degree not in (1, 2, 3):
                raise CtsplatError(f"from_values: sh_degree must be 0..3, got {sh_degree}")
            c = 1 if cols is None else cols.shape[1]
            sh_rest = torch.zeros(n, (sh_degree + 1) ** 2 - 1, c, **kw)
        return cls(
            means=means_t.clone(), log_scales=torch.log(scales).clone(), quats=q,
            density_raw=inverse_softplus(dens).clone(), opacity_raw=op_raw, colors=cols, sh_rest=sh_rest,
        )

    @classmethod
    def empty(cls, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Gaussians:
        """Zero Gaussians."""
        z = torch.zeros(0, 3, dtype=dtype, device=device)
        return cls.from_values(z, torch.ones(0, 3, dtype=dtype), torch.ones(0, dtype=dtype), dtype=dtype,
                               device=device)

    # ------------------------------------------------------------------ activations
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num(self) -> int:
        """Number of Gaussians ``N`` (as ``len``)."""
        return len(self)

    @property
    def scales(self) -> torch.Tensor:
        """Standard deviations (N, 3) in mm."""
        return torch.exp(self.log_scales)

    @property
    def densities(self) -> torch.Tensor:
        """ρ = softplus(density_raw), shape (N,)."""
        return F.softplus(self.density_raw)

    @property
    def opacities(self) -> torch.Tensor:
        """sigmoid(opacity_raw), shape (N,); ones when the model has no opacity."""
        if self.opacity_raw is None:
            return torch.ones_like(self.density_raw)
        return torch.sigmoid(self.opacity_raw)

    @property
    def rotations(self) -> torch.Tensor:
        """Rotation matrices (N, 3, 3)."""
        return quat_to_rotmat(self.quats)

    @property
    def covariances(self) -> torch.Tensor:
        """Σ (N, 3, 3) in mm²."""
        return covariance(self.log_scales, self.quats)

    @property
    def sh_degree(self) -> int:
        """Degree (0..3) of the spherical-harmonic colour; 0 without ``sh_rest``."""
        return 0 if self.sh_rest is None else int(round(math.sqrt(self.sh_rest.shape[1] + 1))) - 1

    def masses(self) -> torch.Tensor:
        """Integral of each Gaussian, ``ρ (2π)^{3/2} |Σ|^{1/2} = ρ (2π)^{3/2} s_x s_y s_z``.

        Returns
        -------
        Tensor (N,)
            Density units × mm³.
        """
        return self.densities * (2 * math.pi) ** 1.5 * torch.exp(self.log_scales.sum(-1))

    def tensors(self) -> dict[str, torch.Tensor]:
        """The non-None parameter tensors by name."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                out[f.name] = v
        return out

    def validate(self, check_finite: bool | tuple[str, ...] = True) -> None:
        """Raise ``CtsplatError`` naming the first parameter with a wrong shape or a NaN/Inf value.

        Parameters
        ----------
        check_finite : bool or tuple of str
            True checks every tensor for NaN/Inf, False none, a tuple of names only those.
        """
        n = len(self)
        shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "density_raw": (n,), "opacity_raw": (n,),
                  "filter_3d_var": (n,)}
        checked = []
        for name, t in self.tensors().items():
            if name in shapes and tuple(t.shape) != shapes[name]:
                raise CtsplatError(f"Gaussians.{name} has shape {tuple(t.shape)}, expected {shapes[name]}")
            if name in ("colors", "sh_rest") and (t.ndim != {"colors": 2, "sh_rest": 3}[name] or t.shape[0] != n):
                want = "(N, C)" if name == "colors" else "(N, K, C)"
                raise CtsplatError(f"Gaussians.{name} has shape {tuple(t.shape)}, expected {want} with N = {n}")
            if name == "sh_rest" and t.shape[1] not in SH_REST_SIZES:
                raise CtsplatError(f"Gaussians.sh_rest holds {t.shape[1]} coefficients per channel; SH degrees 1, 2 "
                                   f"and 3 hold {', '.join(map(str, SH_REST_SIZES))}")
            if name == "sh_rest" and self.colors is not None and t.shape[2] != self.colors.shape[1]:
                raise CtsplatError(f"Gaussians.sh_rest has {t.shape[2]} colour channels, the colours "
                                   f"{self.colors.shape[1]}; give both one channel count")
            check = check_finite if isinstance(check_finite, bool) else name in check_finite
            if check and t.numel():
                checked.append((name, t))
        if not checked:
            return
        # fast path: finite sums prove there is no NaN/Inf (both propagate), read with one host synchronisation
        # (on a GPU every read waits for the queued work); an overflowing sum falls through to the exact check
        sums = torch.stack([t.detach().sum().to(torch.float64) for _, t in checked])
        if bool(torch.isfinite(sums).all()):
            return
        for name, t in checked:
            if not bool(torch.isfinite(t).all()):
                bad = int((~torch.isfinite(t)).reshape(t.shape[0], -1).any(-1).nonzero()[0, 0])
                raise CtsplatError(
                    f"Gaussians.{name} contains NaN/Inf (first at index {bad}); "
                    "lower the learning rate or prune/reset those Gaussians"
                )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Gaussians:
        """Copy onto ``device`` / ``dtype`` (detached from nothing: plain ``Tensor.to``)."""
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, v in kw.items():
            if isinstance(v, torch.Tensor):
                kw[k] = v.to(device=device, dtype=dtype)
        return Gaussians(**kw)

    def detach(self) -> Gaussians:
        """The same tensors detached from the autograd graph (``meta`` shared)."""
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, v in kw.items():
            if isinstance(v, torch.Tensor):
                kw[k] = v.detach()
        return Gaussians(**kw)

    def __getitem__(self, idx: torch.Tensor | slice) -> Gaussians:
        """Subset by mask/index (tensor parameters indexed, meta shared)."""
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, v in kw.items():
            if isinstance(v, torch.Tensor):
                kw[k] = v[idx]
        return Gaussians(**kw)

    # ------------------------------------------------------------------ I/O
    def save(self, path: str | Path) -> None:
        """Save to a ``.pt`` file (tensors on CPU, detached; atomic write).

        Parameters
        ----------
        path : str or Path
        """
        payload = {
            "format": "ctsplat.gaussians",
            "version": _FORMAT_VERSION,
            "tensors": {k: v.detach().cpu() for k, v in self.tensors().items()},
            "meta": dict(self.meta),
        }
        save_torch_atomic(path, payload)

    @classmethod
    def load(cls, path: str | Path, device: torch.device | str | None = None) -> Gaussians:
        """Load a model written by :meth:`save` (also accepts a training checkpoint with a ``gaussians`` entry).

        Parameters
        ----------
        path : str or Path
        device : torch.device, str or None
            Where to put the tensors (default CPU).

        Returns
        -------
        Gaussians
            Validated (shapes, finiteness); ``meta`` as saved.
        """
        path = Path(path)
        if not path.is_file():
            raise CtsplatError(f"model file not found: {path}")
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - torch raises many types for corrupt files
            # torch's own first line advises loading untrusted files with weights_only=False: not repeated here
            raise CtsplatError(f"cannot read Gaussian model {path} ({type(exc).__name__}): it is not a .pt model "
                               "written by ctsplat (Gaussians.save); give a run's model.pt") from exc
        if isinstance(payload, dict) and "gaussians" in payload and "tensors" not in payload:
            payload = payload["gaussians"]
        if not isinstance(payload, dict) or payload.get("format") != "ctsplat.gaussians":
            raise CtsplatError(f"{path} is not a ctsplat Gaussian model (.pt written by Gaussians.save)")
        if payload.get("version", _FORMAT_VERSION) != _FORMAT_VERSION:  # its tensors may mean something else
            raise CtsplatError(f"{path} is a Gaussian model of format version {payload.get('version')!r}; this "
                               f"ctsplat reads version {_FORMAT_VERSION}: use the ctsplat that wrote it, or train "
                               "again")
        t, meta = payload.get("tensors"), payload.get("meta", {})
        if not isinstance(t, dict) or not isinstance(meta, dict):
            raise CtsplatError(f"{path}: the model's tensors and meta must be mappings; it is not a model written by "
                               "Gaussians.save")
        missing = [k for k in ("means", "log_scales", "quats", "density_raw") if k not in t]
        if missing:
            raise CtsplatError(f"{path}: model is missing tensor {missing[0]!r}")
        known = {f.name for f in fields(cls)} - {"meta"}
        unknown = [k for k, v in t.items() if k not in known or not isinstance(v, torch.Tensor)]
        if unknown:
            raise CtsplatError(f"{path}: model holds {unknown[0]!r}, which is not a Gaussian parameter tensor; it was "
                               "not written by this version's Gaussians.save")
        g = cls(**{k: v.to(device) for k, v in t.items()}, meta=dict(meta))
        g.validate()
        return g

    def to_ply(self, path: str | Path, *, density: bool | None = None) -> None:
        """Export a binary little-endian PLY readable by standard 3DGS viewers.

        Properties: ``x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3 density`` with the 3DGS
        encodings (``f_dc = (colour - 0.5) / C0``, ``opacity`` = logit, ``scale`` = log, ``rot`` = wxyz) plus the
        radiative ``density`` ρ (activated, in the normalised units the model was trained in: × ``mu_scale_per_mm``,
        named in a header comment when ``meta`` records it, gives 1/mm) where it renders. Grey colours are
        replicated to RGB; a model without colours is shown grey with brightness ``ρ / max ρ``; a model without
        opacity gets opacity ``1 - exp(-ρ·2 s̄)`` clamped to [0.01, 0.99] (viewer display only). A model that
        renders with Mip-Splatting's 3D filter (``filter_3d_var``, ``meta["mip"]``) is written with the filter
        fused in, as Mip-Splatting exports it: variances ``s² + v`` and opacity and density × ``sqrt(Π s² / (s² +
        v))`` (:func:`ctsplat.splat.render.render`'s filtered kernel), so that a viewer without the filter draws the
        field the model renders. Read back with :func:`ctsplat.formats.ply.read_ply_vertices`.

        Parameters
        ----------
        path : str or Path
            Output ``.ply`` (atomic write).
        density : bool or None
            Write the radiative ``density`` column. A model trained with the alpha compositor renders opacity and
            colour only, so its densities mean nothing to a reader: False leaves them out (the plain 3DGS layout).
            Default: unless ``meta["compositor"]`` is ``"alpha"``.

        References
        ----------
        Yu, Z., Chen, A., Huang, B., Sattler, T., Geiger, A. (2024). Mip-Splatting: alias-free 3D Gaussian
        splatting. CVPR (the 3D smoothing filter and its fused export).
        """
        if density is None:
            density = self.meta.get("compositor") != "alpha"
        n = len(self)
        fused = self.filter_3d_var is not None and bool(self.meta.get("mip", True))
        with torch.no_grad():
            log_scales = self.log_scales.detach().cpu().double()
            comp = torch.ones(n, dtype=torch.float64)
            if fused:
                s2 = torch.exp(2 * log_scales)
                s2f = s2 + self.filter_3d_var.detach().cpu().double().reshape(-1, 1)
                comp = torch.sqrt(torch.prod(s2 / s2f, dim=-1))
                log_scales = 0.5 * torch.log(s2f)
            dens = self.densities.detach().cpu().double() * comp
            if self.colors is not None:
                col = self.colors.detach().cpu().double()
                if col.shape[1] not in (1, 3):
                    raise CtsplatError(f"to_ply: colours of {col.shape[1]} channels; 3DGS PLY stores grey (1) or "
                                       "RGB (3)")
                col = col.expand(n, 3) if col.shape[1] == 1 else col
            else:
                col = (dens / dens.max().clamp_min(1e-12))[:, None].expand(n, 3) if n else torch.zeros(0, 3)
            f_dc = (col - 0.5) / SH_C0
            if self.opacity_raw is not None:
                op_raw = torch.logit(torch.sigmoid(self.opacity_raw.detach().cpu().double()) * comp) if fused \
                    else self.opacity_raw.detach().cpu().double()
            else:
                thick = 2 * torch.exp(log_scales).mean(-1)
                op = (1 - torch.exp(-dens * thick)).clamp(0.01, 0.99)
                op_raw = torch.logit(op)
            rest = torch.zeros(n, 0, dtype=torch.float64)
            if self.sh_rest is not None:
                sr = self.sh_rest.detach().cpu().double()  # (N, K-1, C)
                sr = sr.expand(n, sr.shape[1], 3) if sr.shape[2] == 1 else sr[:, :, :3]
                rest = sr.transpose(1, 2).reshape(n, -1)  # channel-major as in 3DGS
            q = self.quats.detach().cpu().double()
            q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            normal = torch.zeros(n)
            cols = [
                ("x", self.means[:, 0]), ("y", self.means[:, 1]), ("z", self.means[:, 2]),
                ("nx", normal), ("ny", normal), ("nz", normal),
                *[(f"f_dc_{i}", f_dc[:, i]) for i in range(3)],
                *[(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])],
                ("opacity", op_raw),
                *[(f"scale_{i}", log_scales[:, i]) for i in range(3)],
                *[(f"rot_{i}", q[:, i]) for i in range(4)],
                *([("density", dens)] if density else []),
            ]
            cols = [(name, "float", v.detach().cpu().numpy()) for name, v in cols]
        comments = [f"ctsplat Gaussians ({'3DGS layout + radiative density' if density else '3DGS layout'})"]
        if fused:
            comments.append("Mip-Splatting 3D filter fused in (scales, opacity and density include it)")
        scale = self.meta.get("mu_scale_per_mm")
        if density and isinstance(scale, int | float) and math.isfinite(scale) and scale > 0:
            comments.append(f"density is normalised: x mu_scale_per_mm {float(scale)!r} = attenuation in 1/mm")
        write_ply_vertices(path, cols, fmt="binary_little_endian", comments=comments)
