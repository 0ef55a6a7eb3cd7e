"""The system matrix ``A`` of the classical reconstructions: the project's projector, and its exact adjoint.

``A x`` is :func:`ctsplat.projector.line_integrals` of the volume ``x`` (voxel values, e.g. the normalised volume)
at the views of a view set; ``Aᵀ y = ∇_x <A x, y>`` is its adjoint, by automatic differentiation. The projector
narrows its sampling box to the non-zero voxels of a volume that needs no gradient, which would make ``A`` depend
on ``x``; here ``x`` is always presented as a leaf that requires a gradient, so every forward projection samples
the full support ``(-1, N)`` of the interpolant and ``A`` is one fixed linear operator whose adjoint ``Aᵀ`` is
exact (to float32 rounding): ``<A x, y> = <x, Aᵀ y>``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from ctsplat.formats.viewset import ViewSet
from ctsplat.utils import CtsplatError

__all__ = ["Operator", "reference_grid", "check_stack"]


def reference_grid(reference: Any) -> tuple[np.ndarray, tuple[int, int, int], float]:
    """``(affine, shape, mu_scale_per_mm)`` of a Volume-like object (``mu_scale_per_mm`` 1.0 when absent)."""
    affine = np.asarray(reference.affine, float)
    shape = tuple(int(s) for s in (reference.shape if hasattr(reference, "shape") else reference.data.shape))
    scale = float(getattr(reference, "mu_scale_per_mm", 1.0))
    return affine, shape, scale  # type: ignore[return-value]


def check_stack(line_integrals: np.ndarray, view_set: ViewSet) -> np.ndarray:
    """The line integrals as float32 (V, H, W), or a one-line error when they do not match the view set."""
    p = np.asarray(line_integrals, np.float32)
    cam = view_set.camera
    if p.shape != (len(view_set), cam.height, cam.width):
        raise CtsplatError(f"line integrals of shape {p.shape} do not match the view set "
                           f"({len(view_set)}, {cam.height}, {cam.width})")
    return p


class Operator:
    """``A`` (views of ``view_set``) and ``Aᵀ`` on a reference grid, views processed in batches.

    Parameters
    ----------
    view_set : ViewSet
        Camera and poses (any geometry).
    affine : ndarray, shape (4, 4)
        Voxel index -> world mm of the reconstruction grid.
    shape : tuple of int
        ``(I, J, K)``.
    device : str or torch.device, optional
        Where to compute (default CPU).
    views_per_batch : int
        Views projected at once (memory bound).
    step_voxels : float
        Sampling step of the projector, in (0, 1] voxel (see :func:`ctsplat.projector.line_integrals`).
    method : {"auto", "trilinear", "joseph"}
        Projector method; ``auto`` uses the exact slice-wise Joseph projector where the geometry allows.
    """

    def __init__(self, view_set: ViewSet, affine: np.ndarray, shape: tuple[int, int, int], *,
                 device: str | torch.device | None = None, views_per_batch: int = 8, step_voxels: float = 0.5,
                 method: str = "auto") -> None:
        if len(view_set) == 0:
            raise CtsplatError("empty view set: nothing to reconstruct from")
        self.view_set = view_set
        self.affine = np.asarray(affine, float)
        self.shape = tuple(int(s) for s in shape)
        self.device = torch.device(device) if device else torch.device("cpu")
        self.views_per_batch = max(1, int(views_per_batch))
        self.step_voxels = float(step_voxels)
        self.method = method
        self.Rs, self.ts = view_set.Rs(), view_set.ts()
        cam = view_set.camera
        self.image_shape = (len(view_set), cam.height, cam.width)

    def batches(self, rows: np.ndarray | None = None) -> Iterator[np.ndarray]:
        """Row indices of the views, ``views_per_batch`` at a time (all views, or ``rows``)."""
        rows = np.arange(len(self.view_set)) if rows is None else np.asarray(rows, int)
        for i in range(0, len(rows), self.views_per_batch):
            yield rows[i : i + self.views_per_batch]

    def _project(self, x: torch.Tensor, rows: np.ndarray) -> torch.Tensor:
        from ctsplat.projector import line_integrals

        return line_integrals(x, self.affine, self.view_set.camera, self.Rs[rows], self.ts[rows],
                              step_voxels=self.step_voxels, device=self.device, method=self.method)

    def forward(self, x: torch.Tensor, rows: np.ndarray | None = None) -> torch.Tensor:
        """``A x`` for the views ``rows`` (default all), shape (len(rows), H, W), float32."""
        leaf = x.detach().to(self.device, torch.float32).requires_grad_(True)
        with torch.no_grad():  # a leaf that requires grad keeps the projector's full, x-independent support
            return torch.cat([self._project(leaf, b) for b in self.batches(rows)])

    def adjoint(self, y: torch.Tensor, rows: np.ndarray | None = None) -> torch.Tensor:
        """``Aᵀ y`` for images ``y`` of the views ``rows`` (default all), shape (I, J, K), float32."""
        rows = np.arange(len(self.view_set)) if rows is None else np.asarray(rows, int)
        y = torch.as_tensor(y, dtype=torch.float32, device=self.device)
        out = torch.zeros(self.shape, device=self.device)
        start = 0
        for b in self.batches(rows):
            x = torch.zeros(self.shape, device=self.device, requires_grad=True)  # A is linear: any x
            with torch.enable_grad():
                (self._project(x, b) * y[start : start + len(b)]).sum().backward()
            out += x.grad
            start += len(b)
        return out

    def residual_adjoint(self, x: torch.Tensor, b: torch.Tensor, weight: torch.Tensor,
                         rows: np.ndarray | None = None) -> tuple[torch.Tensor, float]:
        """``Aᵀ (weight · (b - A x))`` and ``‖b - A x‖²`` for the views ``rows``, with one projection per batch.

        ``A x`` is computed once with its autograd graph and the adjoint is that graph's backward pass, so a SART /
        SIRT update costs one forward and one backward pass instead of a forward pass, then another forward pass
        and a backward pass for :meth:`adjoint`.

        Parameters
        ----------
        x : torch.Tensor, shape (I, J, K)
            The volume.
        b : torch.Tensor, shape (len(rows), H, W)
            Measured line integrals of the views ``rows``.
        weight : torch.Tensor, shape (len(rows), H, W)
            Per-ray weight of the residual (e.g. ``1 / (A 1)``).
        rows : ndarray of int, optional
            The views (default all).

        Returns
        -------
        update : torch.Tensor, shape (I, J, K)
            ``Aᵀ (weight · (b - A x))``.
        residual_sq : float
            ``‖b - A x‖²`` over those views.
        """
        rows = np.arange(len(self.view_set)) if rows is None else np.asarray(rows, int)
        leaf = x.detach().to(self.device, torch.float32).requires_grad_(True)
        res2, start = 0.0, 0
        with torch.enable_grad():
            for batch in self.batches(rows):
                y = self._project(leaf, batch)
                sl = slice(start, start + len(batch))
                r = (b[sl] - y).detach()
                res2 += float((r * r).sum())
                (y * (r * weight[sl])).sum().backward()  # d<Ax, w>/dx = Aᵀ w, A linear
                start += len(batch)
        return leaf.grad if leaf.grad is not None else torch.zeros_like(leaf), res2
