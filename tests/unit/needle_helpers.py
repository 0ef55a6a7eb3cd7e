"""Needle-like Gaussians (axis ratios 1e2 to 1e4, rotated out of the image axes) rendered in float32 by one backend
and in float64 by the reference: the float32 2D determinant ``c00 c11 − c01²`` cancels for them, so these scenes
check that every backend forms it without cancellation (Cauchy–Binet) in the forward and the backward."""

from __future__ import annotations

import torch
from scipy.spatial.transform import Rotation

from ctsplat.geometry import ConeCamera, ParallelCamera
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import render

PARAMS = ("means", "log_scales", "quats", "density_raw")
# (long σ, thin σ) mm; on a 0.02 mm detector pixel the thin axis is 0.5-5 px wide
SHAPES = ((30.0, 0.03), (300.0, 0.03), (1000.0, 0.1))


def needle_scene(long_mm: float, thin_mm: float, dtype: torch.dtype, device: str = "cpu") -> Gaussians:
    """Two needles (a line and a flat ribbon) through the image centre at 33° and 71° to the detector rows."""
    q = Rotation.from_euler("zyx", [[33, 20, 10], [71, 20, 10]], degrees=True).as_quat()[:, [3, 0, 1, 2]]
    g = Gaussians.from_values([[0.3, -0.2, 0.1], [-0.5, 0.4, 0.0]],
                              [[long_mm, thin_mm, thin_mm], [thin_mm, long_mm, 2 * thin_mm]], [1.0, 0.7], q,
                              dtype=dtype).to(device)
    for p in PARAMS:
        getattr(g, p).requires_grad_(True)
    return g


def needle_errors(backend: str, model: str, compositor: str, mip: bool, device: str = "cpu") -> dict[str, float]:
    """Largest float32 error of the image and of each parameter's gradient (of a random weighting of the image),
    relative to the float64 reference's largest value, over :data:`SHAPES`; NaN where the float32 render is not
    finite."""
    cam = ParallelCamera(96, 80, 0.02) if model == "parallel" else ConeCamera(96, 80, 0.04, 600.0, 1200.0)
    R = torch.eye(3, dtype=torch.float64)
    t = torch.tensor([0.0, 0.0, 600.0], dtype=torch.float64)
    w = torch.rand(80, 96, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    worst: dict[str, float] = {}
    for long_mm, thin_mm in SHAPES:
        res = {}
        for dtype, b in ((torch.float64, "reference"), (torch.float32, backend)):
            g = needle_scene(long_mm, thin_mm, dtype, device)
            fv = torch.tensor([1e-4, 2e-4], dtype=dtype, device=device) if mip else None
            img = render(g, cam, R.to(dtype).to(device), t.to(dtype).to(device), compositor=compositor, mip_2d=mip,
                         filter_3d_var=fv, backend=b).image
            grads = torch.autograd.grad((img.double() * w.to(device)).sum(), [getattr(g, p) for p in PARAMS])
            res[dtype] = [img.detach().double().cpu(), *(x.double().cpu() for x in grads)]
        assert float(res[torch.float64][0].max()) > 0.01, "the needles are in view"
        for name, ref, x in zip(("image", *PARAMS), res[torch.float64], res[torch.float32], strict=True):
            err = float((x - ref).abs().max()) / float(ref.abs().max())
            if not torch.isfinite(x).all():
                err = float("nan")
            prev = worst.get(name, 0.0)
            worst[name] = err if err != err or prev != prev else max(prev, err)
    return worst


def assert_needles_accurate(backend: str, model: str, device: str = "cpu") -> None:
    """The radiative compositors, with and without the mip filters: image within 1e-4 and every gradient within
    2e-3 of the float64 reference (relative to its largest value)."""
    for comp, mip in (("radiative", False), ("radiative", True), ("radiative_unrectified", True)):
        err = needle_errors(backend, model, comp, mip, device=device)
        assert err["image"] <= 1e-4, (model, comp, mip, err)
        assert all(err[p] <= 2e-3 for p in PARAMS), (model, comp, mip, err)
