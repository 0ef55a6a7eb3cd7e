"""Renderer correctness against independent references: quadrature line integrals, analytic masses, the radiograph
projector applied to the voxelised field, a brute-force alpha compositor, gradcheck, the fused kernel vs reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from needle_helpers import assert_needles_accurate
from scipy.spatial.transform import Rotation

from ctsplat.geometry import ConeCamera, ParallelCamera, camera_rays, pose_from_angles
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import EPS_2D, compute_3d_filter, project, render, voxelize
from ctsplat.utils import CtsplatError

D64 = torch.float64
@pytest.mark.parametrize("backend", ["reference", "kernel"])
def test_alpha_footprints_count_the_pixels_where_alpha_reaches_1_255(backend):
    """Pixel-GS's weight: the ellipse area where ``o e^q ≥ 1/255`` against a per-pixel count with the EWA
    covariance rebuilt in numpy, for Gaussians inside the image and cut by its edge."""
    if backend == "kernel" and not _kernel_available():
        pytest.skip("fused C++ kernel unavailable")
    g = _mixture(8, seed=3, spread=8.0, smin=1.0, smax=2.5)
    cam = ParallelCamera(96, 80, 0.25)
    R, t = _pose(30.0, 10.0, dist=100.0)
    out = render(g, cam, R, t, compositor="alpha", sigma_cutoff=4.0, backend=backend)
    m, cov, op = g.means.detach().numpy(), g.covariances.detach().numpy(), g.opacities.detach().numpy()
    xc = m @ R.numpy().T + t.numpy()
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    J = np.hstack([np.eye(2) / cam.spacing_mm, np.zeros((2, 1))])
    inside = cut = 0
    for i in range(len(m)):
        c2 = J @ R.numpy() @ cov[i] @ R.numpy().T @ J.T + (0.3 + EPS_2D) * np.eye(2)
        P = np.linalg.inv(c2)
        mu = np.array([xc[i, 0] / cam.spacing_mm + cam.cx, xc[i, 1] / cam.spacing_mm + cam.cy])
        du, dv = u - mu[0], v - mu[1]
        q = -0.5 * (P[0, 0] * du**2 + 2 * P[0, 1] * du * dv + P[1, 1] * dv**2)
        count = int((op[i] * np.exp(q) >= 1 / 255).sum())
        r2 = 2 * math.log(255 * op[i])
        half = np.sqrt(r2 * np.diag(c2))  # the ellipse's half width and half height, px
        fp = float(out.footprints[i])
        if np.all(mu - half >= 0) and np.all(mu + half <= [cam.width, cam.height]):
            inside += 1
            assert fp == pytest.approx(count, rel=0.02), i
        else:  # cut by the image's edge
            cut += 1
            assert fp == pytest.approx(count, rel=0.1), i
    assert inside >= 3 and cut >= 2 and out.footprints.min() >= 0
    assert render(g, cam, R, t, compositor="radiative", backend=backend).footprints is None


@pytest.mark.parametrize("backend", ["reference", "kernel"])
def test_alpha_footprints_are_capped_by_the_drawn_box_and_zero_when_culled(backend):
    """With a 1σ box the ellipse where α ≥ 1/255 covers the whole box, so the footprint is the box (clipped to the
    image); a Gaussian behind a pinhole camera's centre is culled and covers nothing (float32, cone camera)."""
    if backend == "kernel" and not _kernel_available():
        pytest.skip("fused C++ kernel unavailable")
    g = _mixture(6, seed=5, spread=4.0, smin=1.0, smax=2.0, dtype=torch.float32)
    cam = ConeCamera(64, 48, 1.0, 150.0, 300.0)
    R, t = _pose(20.0, 5.0, dist=150.0)
    with torch.no_grad():  # the last one 10 mm behind the source
        g.means[-1] = torch.as_tensor(-R.T @ t, dtype=torch.float32) - 10.0 * torch.as_tensor(R[2], dtype=torch.float32)
    out = render(g, cam, R, t, compositor="alpha", sigma_cutoff=1.0, backend=backend)
    proj = project(g, cam, R, t, compositor="alpha", sigma_cutoff=1.0)
    bb = proj.bbox
    box = ((bb[:, 1] - bb[:, 0]) * (bb[:, 3] - bb[:, 2])).double()
    assert not bool(proj.valid[-1]) and float(out.footprints[-1]) == 0.0
    assert out.footprints.dtype == torch.float32
    inside = proj.valid & (box > 0)
    assert int(inside.sum()) >= 4
    np.testing.assert_allclose(out.footprints[inside].double().numpy(), box[inside].numpy(), rtol=1e-5)


DIRECTIONS = [(0.0, 0.0), (37.0, 20.0), (100.0, -45.0), (210.0, 70.0)]


def _pose(az: float, el: float, iso=(0.0, 0.0, 0.0), dist: float = 300.0):
    R, t = pose_from_angles(az, el, iso, dist)
    return torch.tensor(R, dtype=D64), torch.tensor(t, dtype=D64)


def _mixture(n: int, seed: int, spread: float = 6.0, smin: float = 1.0, smax: float = 3.0, dtype=D64) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=D64) - 0.5) * 2 * spread
    scales = smin + (smax - smin) * torch.rand(n, 3, generator=g, dtype=D64)
    dens = 0.2 + torch.rand(n, generator=g, dtype=D64)
    quats = torch.randn(n, 4, generator=g, dtype=D64)
    op = 0.2 + 0.5 * torch.rand(n, generator=g, dtype=D64)
    cols = torch.rand(n, 1, generator=g, dtype=D64)
    return Gaussians.from_values(means, scales, dens, quats, opacities=op, colors=cols, dtype=dtype)


def _analytic_mass(g: Gaussians) -> float:
    return float(g.masses().sum())


# ------------------------------------------------------------------------------------------------ exactness
@pytest.mark.parametrize("az,el", DIRECTIONS)
def test_parallel_single_gaussian_matches_quadrature_line_integral(az, el):
    """Rotated anisotropic Gaussian: every pixel equals a fine trapezoid line integral along its ray (1e-4 rel)."""
    q = Rotation.from_euler("zyx", [30, 50, -20], degrees=True).as_quat()  # xyzw
    g = Gaussians.from_values([[1.5, -2.0, 0.7]], [[4.0, 1.5, 2.5]], [0.8], [[q[3], q[0], q[1], q[2]]], dtype=D64)
    cam = ParallelCamera(40, 36, 0.6)
    R, t = _pose(az, el)
    img = render(g, cam, R, t, sigma_cutoff=8.0).image.numpy()
    # independent reference: sample μ along each pixel's ray (numpy, world frame)
    o, d = camera_rays(cam, R.numpy(), t.numpy())
    # ray origins 300 mm from the isocentre: cover ±30 mm (> 7σ) around it; 0.05 mm steps (trapezoid on a smooth,
    # fully covered Gaussian converges exponentially: far below 1e-4)
    s = np.linspace(270.0, 330.0, 1201)
    m = g.means.detach().numpy()[0]
    P = np.linalg.inv(g.covariances.detach().numpy()[0])
    ref = np.zeros(img.shape)
    for row in range(cam.height):
        x = o[row][:, None, :] + s[None, :, None] * d[row][:, None, :] - m  # (W, S, 3)
        f = 0.8 * np.exp(-0.5 * np.einsum("wsi,ij,wsj->ws", x, P, x))
        ref[row] = np.trapezoid(f, s, axis=1)
    assert ref.max() > 1.0  # the Gaussian is in view and the quadrature covers it
    big = ref > 1e-3 * ref.max()
    np.testing.assert_allclose(img[big], ref[big], rtol=1e-4)
    np.testing.assert_allclose(img, ref, rtol=0, atol=1e-4 * ref.max())


def _mass_scene() -> Gaussians:
    # anisotropic, rotated, all inside the detector field of view; σ ≥ 1 mm = 2 px so pixel sums equal integrals
    q = torch.tensor(Rotation.from_euler("xyz", [[10, 70, 30], [80, -20, 45], [0, 0, 0]], degrees=True).as_quat())
    quats = q[:, [3, 0, 1, 2]]
    return Gaussians.from_values(
        [[0.0, 0.0, 0.0], [6.0, -4.0, 3.0], [-5.0, 5.0, -6.0]],
        [[5.0, 1.0, 1.2], [1.0, 3.5, 1.0], [2.0, 2.0, 4.0]],
        [1.0, 0.5, 2.0], quats, dtype=D64,
    )


@pytest.mark.parametrize("mip", [False, True])
def test_rectified_parallel_conserves_mass_every_direction(mip):
    g = _mass_scene()
    cam = ParallelCamera(128, 128, 0.5)
    fv = torch.full((3,), 0.8, dtype=D64) if mip else None  # a strong 3D filter (mm²) to make the point
    target = _analytic_mass(g)
    for az, el in DIRECTIONS:
        R, t = _pose(az, el)
        img = render(g, cam, R, t, filter_3d_var=fv, mip_2d=mip, sigma_cutoff=6.0).image
        assert float(img.sum()) * 0.25 == pytest.approx(target, rel=1e-7)


def test_rectified_default_cutoff_loses_at_most_the_documented_tail():
    g = _mass_scene()
    cam = ParallelCamera(128, 128, 0.5)
    target = _analytic_mass(g)
    for az, el in DIRECTIONS[:2]:
        R, t = _pose(az, el)
        mass = float(render(g, cam, R, t).image.sum()) * 0.25
        # Šidák: the 3σ box keeps at least erf(3/√2)² of each Gaussian and at most one marginal's erf(3/√2)
        deficit = (target - mass) / target
        assert 1 - math.erf(3 / math.sqrt(2)) < deficit <= (1 - math.erf(3 / math.sqrt(2)) ** 2) * 1.0001


def test_unrectified_violates_mass_conservation_for_anisotropic_gaussians():
    g = _mass_scene()
    cam = ParallelCamera(128, 128, 0.5)
    masses = []
    for az, el in DIRECTIONS:
        R, t = _pose(az, el)
        masses.append(float(render(g, cam, R, t, compositor="radiative_unrectified", sigma_cutoff=6).image.sum()))
    masses = np.array(masses) * 0.25
    assert masses.max() / masses.min() > 1.3  # view-dependent
    assert np.all(np.abs(masses / _analytic_mass(g) - 1) > 0.05)


@pytest.mark.parametrize("mip", [False, True])
def test_rectified_cone_conserves_magnified_mass(mip):
    """Cone beam: ∫ p dA_detector = Σ ρ (2π)^{3/2} |Σ|^{1/2} · DSD² r / z³ (solid-angle Jacobian at each centre)."""
    g = _mass_scene()
    cam = ConeCamera(160, 160, 0.8, 400.0, 800.0)
    fv = torch.full((3,), 0.5, dtype=D64) if mip else None
    for az, el in DIRECTIONS:
        R, t = _pose(az, el, dist=400.0)
        img = render(g, cam, R, t, filter_3d_var=fv, mip_2d=mip, sigma_cutoff=6.0).image
        xc = g.means @ R.T + t
        w = cam.dsd_mm**2 * xc.norm(dim=-1) / xc[:, 2] ** 3
        target = float((g.masses() * w).sum())
        assert float(img.sum()) * cam.pitch_mm**2 == pytest.approx(target, rel=1e-7)


def test_large_gaussian_is_not_clipped():
    """σ = 40 px: the footprint grows with the Gaussian (no fixed patch); far pixels carry the analytic value."""
    g = Gaussians.from_values([[0.0, 0.0, 0.0]], [[20.0, 20.0, 5.0]], [1.0], dtype=D64)
    cam = ParallelCamera(400, 400, 0.5)
    R, t = torch.eye(3, dtype=D64), torch.tensor([0.0, 0.0, 100.0], dtype=D64)
    out = render(g, cam, R, t)
    img = out.image
    assert int(out.radii[0]) >= 120
    peak = 1.0 * math.sqrt(2 * math.pi) * 5.0
    # pixel centre (300.5, 200.5) lies (100.5, 0.5) px (2.5 σ) from the projected mean (200, 200)
    assert float(img[200, 300]) == pytest.approx(peak * math.exp(-0.5 * (100.5**2 + 0.5**2) / 40**2), rel=1e-4)
    frac = math.erf(3 / math.sqrt(2)) ** 2  # mass inside the 3σ box
    assert float(img.sum()) * 0.25 == pytest.approx(_analytic_mass(g) * frac, rel=2e-3)


# ------------------------------------------------------------------------------------------------ vs projector
@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_mixture_matches_projector_on_voxelised_field(model):
    from ctsplat.projector import line_integrals

    g = _mixture(8, seed=3, spread=8.0, smin=3.0, smax=5.0)
    shape = (56, 56, 56)
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    affine[:3, 3] = -27.5  # centred grid, 1 mm voxels
    mu = voxelize(g, shape, affine, sigma_cutoff=5.0)
    if model == "parallel":
        cam, dist = ParallelCamera(48, 48, 1.0), 300.0
    else:
        cam, dist = ConeCamera(48, 48, 2.0, 300.0, 600.0), 300.0
    poses = [_pose(az, el, dist=dist) for az, el in DIRECTIONS[:3]]
    Rs = np.stack([p[0].numpy() for p in poses])
    ts = np.stack([p[1].numpy() for p in poses])
    ref = line_integrals(mu.float(), affine, cam, Rs, ts, step_voxels=0.25).double()
    for v, (R, t) in enumerate(poses):
        img = render(g, cam, R, t, sigma_cutoff=5.0).image
        err = float((img - ref[v]).norm() / ref[v].norm())
        assert err < 0.01, (model, v, err)
        bad = render(g, cam, R, t, compositor="radiative_unrectified", sigma_cutoff=5.0).image
        assert float((bad - ref[v]).norm() / ref[v].norm()) > 0.2  # the test can tell a wrong model apart


# ------------------------------------------------------------------------------------------------ alpha
def _brute_alpha(g: Gaussians, cam, R: torch.Tensor, t: torch.Tensor, mip_2d: bool = False,
                 background: float = 0.0, cap: float = 0.99) -> np.ndarray:
    """Independent per-pixel loop (numpy): EWA 2D covariance, 0.3 px low-pass, alpha capped at ``cap``, depth-sorted
    front to back, then ``background`` times the transmittance left."""
    m = g.means.detach().numpy()
    cov = g.covariances.detach().numpy()
    op = g.opacities.detach().numpy()
    col = g.colors.detach().numpy()[:, 0]
    Rn, tn = R.numpy(), t.numpy()
    xc = m @ Rn.T + tn
    mus, covs = [], []
    for i in range(len(m)):
        x, y, z = xc[i]
        if cam.model == "parallel":
            J = np.diag([1 / cam.spacing_mm, 1 / cam.spacing_mm])
            J = np.hstack([J, np.zeros((2, 1))])
            mu2 = np.array([x / cam.spacing_mm + cam.cx, y / cam.spacing_mm + cam.cy])
        else:
            J = np.array([[cam.fx / z, 0, -cam.fx * x / z**2], [0, cam.fy / z, -cam.fy * y / z**2]])
            mu2 = np.array([cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy])
        c2 = J @ Rn @ cov[i] @ Rn.T @ J.T
        k = (0.1 if mip_2d else 0.3) + EPS_2D  # documented low-pass / mip filter plus the numerical floor
        c2f = c2 + k * np.eye(2)
        o = op[i] * (math.sqrt(np.linalg.det(c2) / np.linalg.det(c2f)) if mip_2d else 1.0)
        mus.append(mu2)
        covs.append((np.linalg.inv(c2f), o))
    order = np.argsort(xc[:, 2], kind="stable")
    img = np.zeros((cam.height, cam.width))
    for v in range(cam.height):
        for u in range(cam.width):
            T = 1.0
            for i in order:
                d = np.array([u + 0.5, v + 0.5]) - mus[i]
                P, o = covs[i]
                a = min(cap, o * math.exp(-0.5 * d @ P @ d))
                img[v, u] += T * a * col[i]
                T *= 1 - a
            img[v, u] += T * background
    return img


@pytest.mark.parametrize("model", ["parallel", "cone"])
@pytest.mark.parametrize("mip", [False, True])
def test_alpha_matches_bruteforce_loop(model, mip):
    g = _mixture(6, seed=1, spread=3.0, smin=0.5, smax=2.0)
    cam = ParallelCamera(14, 12, 1.0) if model == "parallel" else ConeCamera(14, 12, 2.0, 100.0, 200.0)
    R, t = _pose(40.0, 15.0, dist=100.0)
    img = render(g, cam, R, t, compositor="alpha", mip_2d=mip, sigma_cutoff=30.0).image.numpy()
    ref = _brute_alpha(g, cam, R, t, mip_2d=mip)
    assert ref.max() > 0.3
    np.testing.assert_allclose(img, ref, atol=1e-10)


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_nearly_opaque_gaussians_are_capped_at_alpha_099(backend):
    """3DGS caps each Gaussian's alpha at 0.99 (a pixel never turns fully opaque, so the ones behind keep a
    gradient); opacities of 0.995-0.9999 exceed it near every centre. The capped alphas pass no gradient to the
    opacity, and the fused kernel's backward agrees with the reference's autograd."""
    g = _mixture(6, seed=1, spread=3.0, smin=2.0, smax=4.0)
    g.opacity_raw = torch.logit(torch.linspace(0.995, 0.9999, 6, dtype=D64))
    cam = ParallelCamera(14, 12, 1.0)
    R, t = _pose(40.0, 15.0, dist=100.0)
    g.opacity_raw.requires_grad_(True)
    img = render(g, cam, R, t, compositor="alpha", sigma_cutoff=30.0, backend=backend).image
    ref = _brute_alpha(g, cam, R, t)
    np.testing.assert_allclose(img.detach().numpy(), ref, atol=1e-10)
    assert np.abs(_brute_alpha(g, cam, R, t, cap=1.0) - ref).max() > 1e-4  # the cap is what this scene tests
    w = torch.rand(img.shape, generator=torch.Generator().manual_seed(2), dtype=D64)
    (grad,) = torch.autograd.grad((img * w).sum(), g.opacity_raw)
    g_ref = Gaussians(**{**g.tensors(), "opacity_raw": g.opacity_raw.detach().clone().requires_grad_(True)})
    img_ref = render(g_ref, cam, R, t, compositor="alpha", sigma_cutoff=30.0, backend="reference").image
    (grad_ref,) = torch.autograd.grad((img_ref * w).sum(), g_ref.opacity_raw)
    np.testing.assert_allclose(grad.numpy(), grad_ref.numpy(), rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_alpha_background_matches_bruteforce_loop_and_gradcheck(backend):
    g = _mixture(5, seed=2, spread=3.0, smin=0.5, smax=2.0)
    cam = ConeCamera(12, 10, 2.0, 100.0, 200.0)
    R, t = _pose(30.0, -10.0, dist=100.0)
    img = render(g, cam, R, t, compositor="alpha", sigma_cutoff=30.0, background=[0.7], backend=backend).image
    ref = _brute_alpha(g, cam, R, t, background=0.7)
    assert ref.min() < 0.6 < 0.69 < ref.max()  # both covered pixels and bare background
    np.testing.assert_allclose(img.numpy(), ref, atol=1e-10)
    with pytest.raises(CtsplatError, match="background has 3 channels"):
        render(g, cam, R, t, compositor="alpha", background=[0.1, 0.2, 0.3], backend=backend)
    with pytest.raises(CtsplatError, match="alpha compositor"):
        render(g, cam, R, t, background=[0.1], backend=backend)

    def f(bg, op):
        h = Gaussians(**{**g.tensors(), "opacity_raw": op})
        return render(h, cam, R, t, compositor="alpha", sigma_cutoff=12.0, background=bg, backend=backend).image

    inputs = (torch.tensor([0.3], dtype=D64, requires_grad=True), g.opacity_raw.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


# ------------------------------------------------------------------------------------------------ gradients
def _params(g: Gaussians, compositor: str) -> list[str]:
    return ["means", "log_scales", "quats", "opacity_raw" if compositor == "alpha" else "density_raw"]


@pytest.mark.parametrize("compositor", ["radiative", "radiative_unrectified", "alpha"])
@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_gradcheck_small_scene(compositor, model):
    g0 = _mixture(3, seed=7, spread=2.0, smin=0.8, smax=1.6)
    cam = ParallelCamera(9, 8, 0.8) if model == "parallel" else ConeCamera(9, 8, 1.5, 80.0, 160.0)
    R, t = _pose(25.0, 10.0, dist=80.0)
    names = _params(g0, compositor)
    fv = torch.full((3,), 0.05, dtype=D64)

    def f(*tensors):
        kw = dict(g0.tensors())
        kw.update(dict(zip(names, tensors, strict=True)))
        g = Gaussians(**kw)
        # reference path, and the default path (the fused kernels when available) with both mip filters
        a = render(g, cam, R, t, compositor=compositor, sigma_cutoff=12.0, backend="reference").image
        b = render(g, cam, R, t, compositor=compositor, sigma_cutoff=12.0, filter_3d_var=fv, mip_2d=True).image
        return a, b

    inputs = tuple(getattr(g0, n).clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_kernel_matches_reference_forward_and_backward(model):
    from ctsplat.splat import _kernel

    if not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    for dtype, tol in ((D64, 1e-10), (torch.float32, 2e-4)):
        g = _mixture(300, seed=11, spread=30.0, smin=0.3, smax=4.0, dtype=dtype)
        for p in g.tensors().values():
            p.requires_grad_(True)
        cam = ParallelCamera(64, 48, 0.8) if model == "parallel" else ConeCamera(64, 48, 1.6, 200.0, 400.0)
        # some Gaussians lie far outside the cone's field of view (clamped linearisation point) or behind it
        R, t = _pose(60.0, -20.0, dist=200.0 if model == "parallel" else 40.0)
        R, t = R.to(dtype), t.to(dtype)
        w = torch.rand(48, 64, generator=torch.Generator().manual_seed(0), dtype=dtype)
        fv = torch.rand(300, generator=torch.Generator().manual_seed(1), dtype=dtype)
        params = [g.means, g.log_scales, g.quats, g.density_raw]
        for comp in ("radiative", "radiative_unrectified"):
            combos = ((False, None), (True, None), (True, fv), (False, fv)) if dtype == D64 else ((True, fv),)
            for mip, filt in combos:
                res = {}
                for backend in ("reference", "kernel"):
                    out = render(g, cam, R, t, compositor=comp, backend=backend, mip_2d=mip, filter_3d_var=filt)
                    loss = (out.image * w).sum()
                    loss.backward()
                    res[backend] = (out.image.detach(), out.means2d.grad, out.radii, out.visible)
                    res[backend] += tuple(p.grad for p in params)
                    for p in params:
                        p.grad = None
                a, b = res["reference"], res["kernel"]
                assert float(a[0].abs().max()) > 1.0
                assert float((a[0] - b[0]).abs().max()) <= tol * float(a[0].abs().max()), (comp, mip)
                assert torch.equal(a[2], b[2]) and torch.equal(a[3], b[3])
                for x, y in zip(a[4:] + a[1:2], b[4:] + b[1:2], strict=True):
                    assert float((x - y).abs().max()) <= tol * 10 * float(x.abs().max()), (comp, mip, filt)


@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_alpha_kernel_matches_reference(model):
    from ctsplat.splat import _kernel

    if not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    for dtype, tol in ((D64, 1e-10), (torch.float32, 2e-5)):
        g = _mixture(300, seed=11, spread=30.0, smin=0.3, smax=4.0, dtype=dtype)
        g.colors = torch.rand(300, 3, generator=torch.Generator().manual_seed(3), dtype=dtype)  # RGB
        params = [g.means, g.log_scales, g.quats, g.opacity_raw, g.colors]
        for p in params:
            p.requires_grad_(True)
        cam = ParallelCamera(64, 48, 0.8) if model == "parallel" else ConeCamera(64, 48, 1.6, 200.0, 400.0)
        R, t = _pose(60.0, -20.0, dist=200.0 if model == "parallel" else 40.0)
        R, t = R.to(dtype), t.to(dtype)
        w = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
        for mip, filt in ((False, None), (True, torch.full((300,), 0.1, dtype=dtype))):
            res = {}
            for backend in ("reference", "kernel"):
                out = render(g, cam, R, t, compositor="alpha", backend=backend, mip_2d=mip, filter_3d_var=filt)
                assert out.image.shape == (48, 64, 3)
                res[backend] = (out.image.detach(), *torch.autograd.grad((out.image * w).sum(), params))
            assert float(res["reference"][0].max()) > 0.5
            for x, y in zip(res["reference"], res["kernel"], strict=True):
                assert float((x - y).abs().max()) <= tol * float(x.abs().max())


@pytest.mark.parametrize("compositor", ["radiative", "radiative_unrectified", "alpha"])
def test_very_flat_gaussians_have_finite_gradients(compositor):
    # pancakes (1e-5 mm thick) seen face-on, edge-on and obliquely; float32 as in training
    q = torch.tensor(Rotation.from_euler("y", [[0], [90], [45]], degrees=True).as_quat())[:, [3, 0, 1, 2]]
    g = Gaussians.from_values([[0.0, 0, 0], [3.0, 2, 0], [-3.0, -2, 1]], [[3.0, 3.0, 1e-5]] * 3, [1.0] * 3, q,
                              opacities=[0.5] * 3)
    for p in g.tensors().values():
        p.requires_grad_(True)
    for cam in (ParallelCamera(32, 32, 0.5), ConeCamera(32, 32, 1.0, 100.0, 200.0)):
        for az in (0.0, 90.0, 33.0):
            R, t = _pose(az, 0.0, dist=100.0)
            out = render(g, cam, R.float(), t.float(), compositor=compositor, mip_2d=True)
            assert torch.isfinite(out.image).all()
            grads = torch.autograd.grad(out.image.sum(), [g.means, g.log_scales, g.quats, g.density_raw,
                                                          g.opacity_raw], allow_unused=True)
            for gr in grads:
                assert gr is None or bool(torch.isfinite(gr).all())


@pytest.mark.parametrize("backend", ["reference", "kernel"])
@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_needle_gaussians_render_and_differentiate_in_float32(backend, model):
    # axis ratios 1e3-1e4: c00 c11 - c01² cancelled to noise or below zero (NaN images) before Cauchy-Binet
    if backend == "kernel" and not _kernel_available():
        pytest.skip("C kernel unavailable")
    assert_needles_accurate(backend, model)


def _kernel_available() -> bool:
    from ctsplat.splat import _kernel

    return _kernel.available()


def test_means2d_keeps_its_gradient_for_densification():
    g = _mixture(5, seed=2, dtype=torch.float32)
    g.means.requires_grad_(True)
    out = render(g, ParallelCamera(32, 32, 0.5), *_pose(0.0, 0.0))
    out.image.sum().backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (5, 2)
    assert bool(out.visible.all()) and bool((out.radii > 0).all())


# ------------------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("name", ["means", "log_scales", "quats", "density_raw"])
def test_nan_or_inf_parameter_raises_naming_it(name):
    g = _mixture(4, seed=0)
    bad = getattr(g, name).clone()
    bad.view(-1)[2] = float("nan") if name != "log_scales" else float("inf")
    setattr(g, name, bad)
    with pytest.raises(CtsplatError, match=name):
        render(g, ParallelCamera(16, 16, 1.0), *_pose(0.0, 0.0))


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_nan_colour_raises_for_alpha(backend):
    g = _mixture(4, seed=0)
    g.colors = g.colors.clone()
    g.colors[1, 0] = float("nan")
    with pytest.raises(CtsplatError, match="colors"):
        render(g, ParallelCamera(16, 16, 1.0), *_pose(0.0, 0.0), compositor="alpha", backend=backend)


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_bad_filter_variance_raises(backend):
    g = _mixture(4, seed=0)
    for fv, msg in ((torch.tensor([0.1, -0.2, 0.1, 0.1], dtype=D64), ">= 0"),
                    (torch.tensor([0.1, float("nan"), 0.1, 0.1], dtype=D64), "NaN")):
        with pytest.raises(CtsplatError, match=msg):
            render(g, ParallelCamera(16, 16, 1.0), *_pose(0.0, 0.0), filter_3d_var=fv, backend=backend)


def test_a_3d_filter_with_unpaired_poses_raises_in_one_line():
    R, t = _pose(0.0, 0.0)
    with pytest.raises(CtsplatError, match="compute_3d_filter: 2 rotations but 1 translations"):
        compute_3d_filter(_mixture(4, seed=0), ParallelCamera(16, 16, 1.0), torch.stack([R, R]), t[None])


def test_a_pose_of_the_wrong_shape_raises_in_one_line():
    g = _mixture(4, seed=0)
    R, t = _pose(0.0, 0.0)
    for bad_R, bad_t in ((R[None], t), (R, t[:2]), (R[:2], t)):
        with pytest.raises(CtsplatError, match=r"render needs one pose, R \(3, 3\) and t \(3,\)"):
            render(g, ParallelCamera(16, 16, 1.0), bad_R, bad_t)


def test_bad_cutoff_and_a_filter_of_another_model_raise_in_one_line():
    from ctsplat.splat.render import voxelize

    g = _mixture(4, seed=0)
    for cutoff in (0.0, float("inf"), float("nan")):
        with pytest.raises(CtsplatError, match="sigma_cutoff must be a finite number > 0"):
            render(g, ParallelCamera(16, 16, 1.0), *_pose(0.0, 0.0), sigma_cutoff=cutoff)
        with pytest.raises(CtsplatError, match="sigma_cutoff must be a finite number > 0"):
            voxelize(g, (8, 8, 8), torch.eye(4, dtype=D64), sigma_cutoff=cutoff)
    with pytest.raises(CtsplatError, match="filter_3d_var has 3 values for 4 Gaussians"):
        voxelize(g, (8, 8, 8), torch.eye(4, dtype=D64), filter_3d_var=torch.zeros(3, dtype=D64))
    with pytest.raises(CtsplatError, match="sigma_cutoff must be a finite number > 0, got '3'"):
        render(g, ParallelCamera(16, 16, 1.0), *_pose(0.0, 0.0), sigma_cutoff="3")
    # voxelize checks what render checks: the filter's values, and its own shapes
    for fv, msg in ((torch.tensor([0.1, -0.2, 0.1, 0.1], dtype=D64), ">= 0"),
                    (torch.tensor([0.1, float("nan"), 0.1, 0.1], dtype=D64), "NaN")):
        with pytest.raises(CtsplatError, match=msg):
            voxelize(g, (8, 8, 8), torch.eye(4, dtype=D64), filter_3d_var=fv)
    for kw, msg in (({"affine": torch.eye(3, dtype=D64)}, r"needs a \(4, 4\) affine"),
                    ({"shape": (8, 8)}, r"grid shape \(I, J, K\)"),
                    ({"region": ((0, 4), (0, 4))}, "region must be")):
        args = {"shape": (8, 8, 8), "affine": torch.eye(4, dtype=D64), **kw}
        with pytest.raises(CtsplatError, match=msg):
            voxelize(g, args.pop("shape"), args.pop("affine"), **args)
    # a pose with NaN/Inf would cull every Gaussian: an error, not a blank image
    R, t = _pose(0.0, 0.0)
    for bad_R, bad_t in ((R * float("nan"), t), (R, t + torch.tensor([float("inf"), 0.0, 0.0], dtype=t.dtype))):
        with pytest.raises(CtsplatError, match=r"pose \(R, t\) contains NaN/Inf"):
            render(g, ParallelCamera(16, 16, 1.0), bad_R, bad_t)


def test_float32_kernel_rows_of_every_length_and_image_corners():
    # footprint rows 1..37 px long (every remainder of the kernel's 8-lane row chunks), clipped at all four image
    # corners and edges; float32 kernel against the float64 reference, values and gradients
    from ctsplat.splat import _kernel

    if not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    cam = ParallelCamera(37, 29, 1.0)
    n = 400
    gen = torch.Generator().manual_seed(21)
    corners = torch.tensor([[-18.5, -14.5], [18.5, -14.5], [-18.5, 14.5], [18.5, 14.5], [0.0, 0.0]], dtype=D64)
    xy = corners[torch.arange(n) % 5] + 4.0 * (torch.rand(n, 2, generator=gen, dtype=D64) - 0.5)
    means = torch.cat([xy, torch.zeros(n, 1, dtype=D64)], 1)
    sig = torch.linspace(0.15, 7.0, n, dtype=D64)[:, None] * torch.tensor([[1.0, 0.6, 1.0]], dtype=D64)
    g64 = Gaussians.from_values(means, sig, 0.5 + torch.rand(n, generator=gen, dtype=D64),
                                torch.randn(n, 4, generator=gen, dtype=D64), dtype=D64)
    g32 = g64.detach().to(dtype=torch.float32)
    w = torch.rand(29, 37, generator=gen, dtype=D64)
    R, t = _pose(0.0, 0.0)
    res = []
    for g, backend in ((g64, "reference"), (g32, "kernel")):
        params = [g.means, g.log_scales, g.quats, g.density_raw]
        for p in params:
            p.requires_grad_(True)
        out = render(g, cam, R.to(g.means.dtype), t.to(g.means.dtype), backend=backend)
        grads = torch.autograd.grad((out.image * w.to(out.image.dtype)).sum(), params)
        res.append((out.image.detach().double(), [gr.double() for gr in grads], out.radii))
    (a, ga, ra), (b, gb, rb) = res
    assert torch.equal(ra, rb)
    bb = project(g64, cam, R, t).bbox
    lengths = set((bb[:, 1] - bb[:, 0]).tolist())
    assert set(range(1, 25)) <= lengths  # every remainder mod 8, one to three chunks per row
    assert float((a - b).abs().max()) <= 2e-6 * float(a.abs().max())
    for x, y in zip(ga, gb, strict=True):
        assert float((x - y).abs().max()) <= 2e-5 * float(x.abs().max())


def test_zero_gaussians_render_empty_image():
    g = Gaussians.empty(dtype=D64)
    for comp in ("radiative", "alpha"):
        out = render(g, ConeCamera(20, 10, 1.0, 100.0, 200.0), *_pose(10.0, 0.0, dist=100.0), compositor=comp)
        assert out.image.shape == (10, 20) and float(out.image.abs().sum()) == 0.0
        assert out.means2d.shape == (0, 2) and out.visible.shape == (0,)


def test_gaussians_behind_cone_source_are_culled():
    cam = ConeCamera(32, 32, 1.0, 100.0, 200.0)
    R, t = torch.eye(3, dtype=D64), torch.zeros(3, dtype=D64)  # source at the origin looking along +z
    # one in front (z = 100 mm), one behind the source on the same axis (z = -100 mm)
    g = Gaussians.from_values([[0.0, 0, 100], [0.0, 0, -100]], 2.0, [1.0, 5.0], opacities=0.5, dtype=D64)
    for comp in ("radiative", "radiative_unrectified", "alpha"):
        out = render(g, cam, R, t, compositor=comp)
        assert out.visible.tolist() == [True, False] and int(out.radii[1]) == 0
        front = render(g[torch.tensor([0])], cam, R, t, compositor=comp).image
        assert torch.equal(out.image, front)


def test_bad_compositor_and_transmission_and_mu_scale():
    g = _mixture(3, seed=0)
    cam, (R, t) = ParallelCamera(16, 16, 1.0), _pose(0.0, 0.0)
    with pytest.raises(CtsplatError, match="compositor"):
        render(g, cam, R, t, compositor="mip")
    p = render(g, cam, R, t).image
    tr = render(g, cam, R, t, transmission=True, mu_scale=0.02).image
    torch.testing.assert_close(tr, torch.exp(-0.02 * p))


# ------------------------------------------------------------------------------------------------ 3D filter, voxelizer
def test_compute_3d_filter_uses_finest_sampling_of_the_cameras():
    g = Gaussians.from_values([[0.0, 0, 0], [10.0, 0, 0], [0.0, 5000.0, 0]], 1.0, 1.0, dtype=D64)
    par = ParallelCamera(64, 64, 0.7)
    Rs = torch.stack([_pose(0, 0)[0], _pose(90, 0)[0]])
    ts = torch.stack([_pose(0, 0)[1], _pose(90, 0)[1]])
    v = compute_3d_filter(g, par, Rs, ts)
    torch.testing.assert_close(v, torch.full((3,), 0.2 * 0.7**2, dtype=D64))
    cone = ConeCamera(64, 64, 1.0, 200.0, 400.0)
    (R1, t1), (R2, t2) = _pose(0, 0, dist=200.0), _pose(180, 0, dist=300.0)
    v = compute_3d_filter(g, cone, torch.stack([R1, R2]), torch.stack([t1, t2]))
    fx = cone.fx
    # Gaussian 0 at the isocentre: nearer camera wins (z = 200 mm); Gaussian 1 at x=10 is nearer to camera 1 too
    assert float(v[0]) == pytest.approx(0.2 * (200.0 / fx) ** 2)
    z1 = float((g.means[1] @ R1.T + t1)[2])
    assert float(v[1]) == pytest.approx(0.2 * (z1 / fx) ** 2)
    assert float(v[2]) == pytest.approx(float(v.max()))  # unseen -> the largest interval among seen ones
    assert float(v[2]) == pytest.approx(float(v[:2].max()))


def _dense_field(g: Gaussians, shape, affine) -> torch.Tensor:
    idx = torch.stack(torch.meshgrid(*[torch.arange(s, dtype=D64) for s in shape], indexing="ij"), -1)
    A = torch.as_tensor(affine, dtype=D64)
    pos = idx @ A[:3, :3].T + A[:3, 3]
    P = torch.linalg.inv(g.covariances)
    d = pos[..., None, :] - g.means
    q = torch.einsum("...ni,nij,...nj->...n", d, P, d)
    return (g.densities * torch.exp(-0.5 * q)).sum(-1)


@pytest.mark.parametrize("backend", ["reference", "kernel"])
def test_voxelize_matches_dense_evaluation_and_chunks_and_regions(backend):
    from ctsplat.splat import _kernel

    if backend == "kernel" and not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    g = _mixture(12, seed=5, spread=6.0, smin=0.6, smax=2.5)
    shape = (20, 18, 16)
    affine = np.array([[0.0, 0.9, 0.0, -8.0], [0.8, 0.0, 0.1, -7.0], [0.0, 0.0, 1.1, -9.0], [0, 0, 0, 1.0]])
    params = [g.means, g.log_scales, g.quats, g.density_raw]
    for p in params:
        p.requires_grad_(True)
    ref = _dense_field(g, shape, affine)
    w = torch.rand(shape, generator=torch.Generator().manual_seed(1), dtype=D64)
    g_ref = torch.autograd.grad((ref * w).sum(), params)
    for chunk in (1_000_000, 500):  # one chunk, many chunks (reference path)
        vol = voxelize(g, shape, affine, sigma_cutoff=8.0, chunk=chunk, backend=backend)
        torch.testing.assert_close(vol, ref, rtol=1e-10, atol=1e-12)
        for a, b in zip(g_ref, torch.autograd.grad((vol * w).sum(), params), strict=True):
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)
    region = ((3, 11), (0, 7), (5, 16))
    sub = voxelize(g, shape, affine, sigma_cutoff=8.0, region=region, chunk=700, backend=backend)
    torch.testing.assert_close(sub, ref[3:11, 0:7, 5:16], rtol=1e-10, atol=1e-12)
    # the default 3σ cut only drops values below exp(-4.5) of each Gaussian's peak
    cut = voxelize(g, shape, affine, backend=backend)
    assert float((ref - cut).detach().abs().max()) <= float(g.densities.detach().sum()) * math.exp(-4.5)
    with pytest.raises(CtsplatError, match="region"):
        voxelize(g, shape, affine, region=((0, 30), (0, 5), (0, 5)), backend=backend)
    flat = affine.copy()
    flat[2, :3] = 0.0  # every voxel on one plane
    for bad in (flat, np.where(np.eye(4) > 0, np.nan, affine)):
        with pytest.raises(CtsplatError, match="affine .* singular or not finite"):
            voxelize(g, shape, torch.as_tensor(bad), backend=backend)
    # float32 kernel vs float64 reference
    g32 = g.detach().to(dtype=torch.float32)
    v32 = voxelize(g32, shape, affine, sigma_cutoff=8.0, backend=backend)
    torch.testing.assert_close(v32.double(), ref.detach(), rtol=1e-4, atol=1e-5)


def test_voxelize_with_3d_filter_conserves_mass():
    g = _mixture(3, seed=9, spread=2.0, smin=0.8, smax=1.5)
    shape = (40, 40, 40)
    affine = np.diag([0.5, 0.5, 0.5, 1.0])
    affine[:3, 3] = -9.75
    fv = torch.tensor([0.3, 0.6, 1.0], dtype=D64)
    vol = voxelize(g, shape, affine, filter_3d_var=fv, sigma_cutoff=6.0)
    assert float(vol.sum()) * 0.125 == pytest.approx(_analytic_mass(g), rel=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_cuda_matches_cpu():
    g = _mixture(40, seed=4, spread=10.0)
    for comp in ("radiative", "radiative_unrectified", "alpha"):
        for cam in (ParallelCamera(40, 32, 0.5), ConeCamera(40, 32, 1.0, 150.0, 300.0)):
            R, t = _pose(30.0, 10.0, dist=150.0)
            a = render(g, cam, R, t, compositor=comp, mip_2d=True).image
            b = render(g.to("cuda"), cam, R.cuda(), t.cuda(), compositor=comp, mip_2d=True).image.cpu()
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


def test_kernel_builds_when_a_compiler_exists_and_is_deterministic():
    import shutil

    from ctsplat.splat import _kernel

    if not any(shutil.which(c) for c in ("c++", "g++", "clang++")):
        pytest.skip("no C++ compiler on PATH")
    assert _kernel.available(), _kernel._failed
    g = _mixture(6000, seed=8, spread=40.0, smin=0.3, smax=2.0, dtype=torch.float32)
    g.means.requires_grad_(True)
    cam, (R, t) = ParallelCamera(96, 80, 1.0), _pose(20.0, 5.0)
    runs = []
    for _ in range(2):
        for comp in ("radiative", "alpha"):
            out = render(g, cam, R.float(), t.float(), compositor=comp)
            (grad,) = torch.autograd.grad(out.image.square().sum(), [g.means])
            runs.append((out.image.detach(), grad))
    for (a, ga), (b, gb) in zip(runs[:2], runs[2:], strict=True):
        assert torch.equal(a, b) and torch.equal(ga, gb)


@pytest.mark.parametrize("dtype", [torch.float32, D64])
def test_kernel_scatters_agree_for_every_thread_count(dtype):
    """The voxel scatter is cut into slabs of the grid, each summed in Gaussian order by one thread: 1, 2, 3 and 5
    threads give the same bits. The image scatter sums per-thread images in thread order: the same values to
    rounding, and the same bits on a repeat. Both match the float64 reference (as many Gaussians as the threaded
    path needs, footprints cut at every edge)."""
    from ctsplat.splat import _kernel

    if not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    g = _mixture(6000, seed=3, spread=36.0, smin=0.2, smax=3.0, dtype=dtype)
    cam, (R, t) = ParallelCamera(67, 53, 1.0), _pose(15.0, -10.0)
    R, t = R.to(dtype), t.to(dtype)
    affine = np.diag([1.3, 1.1, 0.9, 1.0])
    affine[:3, 3] = -30.0
    w = torch.rand(53, 67, generator=torch.Generator().manual_seed(2), dtype=dtype)
    params = [g.means, g.log_scales, g.quats, g.density_raw]
    for p in params:
        p.requires_grad_(True)
    before = torch.get_num_threads()
    runs = []
    try:
        for k in (1, 2, 3, 5):
            torch.set_num_threads(k)
            img = render(g, cam, R, t, backend="kernel").image
            vol = voxelize(g, (47, 55, 67), affine, backend="kernel")
            grads = torch.autograd.grad((img * w).sum() + vol.square().sum(), params)
            runs.append((img.detach(), vol.detach(), grads))
        torch.set_num_threads(3)
        again = render(g, cam, R, t, backend="kernel").image.detach()
    finally:
        torch.set_num_threads(before)
    assert torch.equal(again, runs[2][0])
    tol = 1e-10 if dtype == D64 else 2e-5
    for img, vol, grads in runs[1:]:
        assert torch.equal(vol, runs[0][1])
        assert float((img - runs[0][0]).abs().max()) <= tol * float(runs[0][0].abs().max())
        for a, b in zip(grads, runs[0][2], strict=True):
            assert float((a - b).abs().max()) <= 10 * tol * float(b.abs().max())
    ref_img = render(g, cam, R, t, backend="reference").image.detach()
    ref_vol = voxelize(g, (47, 55, 67), affine, backend="reference").detach()
    assert float(ref_img.abs().max()) > 1.0 and float(ref_vol.abs().max()) > 0.1
    assert float((runs[0][0] - ref_img).abs().max()) <= tol * float(ref_img.abs().max())
    assert float((runs[0][1] - ref_vol).abs().max()) <= tol * float(ref_vol.abs().max())


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_alpha_sh_colour_depends_on_view_direction(backend):
    from ctsplat.splat.gaussians import eval_sh

    g = Gaussians.from_values([[0.0, 0.0, 0.0]], 1.0, 1.0, opacities=0.8, colors=[[0.5, 0.4, 0.3]], sh_degree=1,
                              dtype=D64)
    g.sh_rest[0] = torch.tensor([[0.2, 0.0, -0.1], [0.0, 0.3, 0.0], [-0.2, 0.1, 0.1]], dtype=D64)
    cam = ParallelCamera(15, 15, 0.5)  # odd size: the mean projects onto the centre of pixel (7, 7)
    seen = []
    for az, el in ((0.0, 0.0), (90.0, 30.0), (200.0, -40.0)):
        R, t = _pose(az, el)
        img = render(g, cam, R, t, compositor="alpha", backend=backend).image
        expected = (torch.tensor([[0.5, 0.4, 0.3]], dtype=D64) + eval_sh(g.sh_rest, R[2][None])).clamp_min(0)[0]
        torch.testing.assert_close(img[7, 7], 0.8 * expected)  # α = o at the centre (no low-pass loss there)
        seen.append(img[7, 7])
    assert float((seen[0] - seen[1]).abs().max()) > 0.05


@pytest.mark.parametrize("compositor", ["radiative", "radiative_unrectified", "alpha"])
def test_extreme_raw_parameters_have_finite_gradients(compositor):
    # softplus / sigmoid underflow to 0 in float32 (raw = -120) and saturate (raw = +60)
    g = _mixture(4, seed=6, spread=3.0, dtype=torch.float32)
    g.density_raw = torch.tensor([-120.0, 60.0, 0.0, -120.0])
    g.opacity_raw = torch.tensor([-120.0, 60.0, 0.0, -120.0])
    params = [g.means, g.log_scales, g.quats, g.density_raw, g.opacity_raw]
    for p in params:
        p.requires_grad_(True)
    fv = torch.full((4,), 0.05)
    for backend in ("reference", "auto"):
        out = render(g, ParallelCamera(24, 24, 0.5), *_pose(10.0, 5.0), compositor=compositor, backend=backend,
                     filter_3d_var=fv, mip_2d=True)
        grads = torch.autograd.grad(out.image.sum(), params, allow_unused=True)
        assert torch.isfinite(out.image).all()
        assert all(gr is None or bool(torch.isfinite(gr).all()) for gr in grads)


@pytest.mark.parametrize("log_scale", [-20.0, -30.0, -45.0])
def test_vanishing_gaussians_keep_finite_exact_values_and_gradients_in_float32(log_scale):
    """Every scale e^-20..e^-45 mm: the product of the variances underflows in float32, and the amplitude's
    square root had an infinite derivative there. The reference path now gives the closed form (a Gaussian at a
    pixel centre, parallel beam, pitch 1: ``ρ sqrt(2π s⁶ / |Σ̂ + k₂I|)``) and its finite gradient."""
    cam, R, t = ParallelCamera(33, 33, 1.0), np.eye(3), np.array([0.0, 0.0, 300.0])  # the mean on pixel (16, 16)
    for fv in (None, torch.full((1,), 0.01)):
        g = Gaussians.from_values(torch.zeros(1, 3), float(np.exp(log_scale)), 0.5, dtype=torch.float32)
        for p in (g.means, g.log_scales, g.density_raw):
            p.requires_grad_(True)
        out = render(g, cam, R, t, backend="reference", filter_3d_var=fv)
        grads = torch.autograd.grad(out.image.sum(), [g.means, g.log_scales, g.density_raw])
        assert all(bool(torch.isfinite(gr).all()) for gr in grads)
        s2 = math.exp(2 * log_scale)
        v = 0.0 if fv is None else 0.01
        det_f = (s2 + v + EPS_2D) ** 2
        amp = 0.5 * math.sqrt(2 * math.pi) * math.exp(3 * log_scale) / math.sqrt(det_f)  # ρ (2π)^½ s³ / |Σ̂'|^½
        if amp < 1e-36:  # below float32's normal range (e^-45): finite is all there is to check
            continue
        assert float(out.image.detach().sum()) == pytest.approx(amp, rel=1e-4)
        # d amp / d log s_k = amp (1 - s_k² / (s_k² + v + k₂)) across the image, amp along the ray
        expected = [amp * (1 - s2 / (s2 + v + EPS_2D))] * 2 + [amp]
        np.testing.assert_allclose(grads[1][0].numpy(), expected, rtol=1e-3)


@pytest.mark.parametrize("backend", ["reference", "kernel", "triton"])
def test_half_precision_and_mixed_dtypes_fail_in_one_line_on_every_backend(backend):
    cam = ParallelCamera(8, 8, 1.0)
    R, t = torch.eye(3), torch.tensor([0.0, 0.0, 100.0])
    for dtype in (torch.float16, torch.bfloat16):
        g = Gaussians.from_values([[0.0, 0, 0]], [[2.0, 1, 1]], [1.0], [[1.0, 0, 0, 0]], dtype=dtype)
        with pytest.raises(CtsplatError, match=r"float32 or float64 Gaussians, got torch\.(b?float16)"):
            render(g, cam, R, t, backend=backend)
    g = Gaussians.from_values([[0.0, 0, 0]], [[2.0, 1, 1]], [1.0], [[1.0, 0, 0, 0]], dtype=torch.float32)
    g.log_scales = g.log_scales.double()
    with pytest.raises(CtsplatError, match=r"Gaussians\.log_scales is torch\.float64, the means torch\.float32"):
        render(g, cam, R, t, backend=backend)


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_nan_in_a_parameter_the_compositor_does_not_render_is_ignored_alike(backend):
    cam = ParallelCamera(16, 16, 1.0)
    R, t = torch.eye(3), torch.tensor([0.0, 0.0, 100.0])
    g = Gaussians.from_values([[0.0, 0, 0]], [[2.0, 1, 1]], [1.0], [[1.0, 0, 0, 0]], opacities=[0.5],
                              colors=[[0.5]], dtype=torch.float32)
    clean = {c: render(g, cam, R, t, compositor=c, backend=backend).image for c in ("radiative", "alpha")}
    g.colors = torch.full_like(g.colors, float("nan"))  # a radiative render never reads the colours
    assert torch.equal(render(g, cam, R, t, backend=backend).image, clean["radiative"])
    with pytest.raises(CtsplatError, match="colors"):
        render(g, cam, R, t, compositor="alpha", backend=backend)
    g.colors = torch.full_like(g.colors, 0.5)
    g.density_raw = torch.full_like(g.density_raw, float("nan"))  # nor an alpha render the densities
    assert torch.equal(render(g, cam, R, t, compositor="alpha", backend=backend).image, clean["alpha"])
    with pytest.raises(CtsplatError, match="density_raw"):
        render(g, cam, R, t, backend=backend)


def test_edge_inputs_fail_in_one_line_or_keep_the_graph():
    """A reference alpha render that no Gaussian reaches still backpropagates (zero gradients); a parameter on
    another device, a pose that needs a gradient on a fused backend, and a non-finite camera are refused."""
    from types import SimpleNamespace

    g = _mixture(3, seed=4, dtype=torch.float64)
    g.means = g.means + torch.tensor([500.0, 0.0, 0.0], dtype=D64)  # far outside the image
    for p in (g.means, g.opacity_raw, g.colors):
        p.requires_grad_(True)
    cam = ParallelCamera(8, 6, 1.0)
    R, t = _pose(20.0, 10.0, dist=100.0)
    img = render(g, cam, R, t, compositor="alpha", backend="reference").image
    ((img - 0.3) ** 2).mean().backward()
    assert float(img.detach().abs().max()) == 0.0 and float(g.opacity_raw.grad.abs().max()) == 0.0
    moved = Gaussians(**{**g.detach().tensors(), "log_scales": g.log_scales.detach().to("meta")})
    with pytest.raises(CtsplatError, match=r"Gaussians\.log_scales is on meta, the means on cpu"):
        render(moved, cam, R, t, backend="auto")
    from ctsplat.splat import _kernel

    if _kernel.available():
        with pytest.raises(CtsplatError, match="no gradient to the pose"):
            render(g.detach(), cam, R.clone().requires_grad_(True), t, backend="kernel")
    R_grad = R.clone().requires_grad_(True)
    render(g.detach(), cam, R_grad, t, backend="reference").image.sum().backward()
    assert R_grad.grad is not None
    for bad, match in ((SimpleNamespace(model="parallel", width=8, height=6, spacing_mm=float("nan")), "spacing"),
                       (SimpleNamespace(model="cone", width=8, height=6, pitch_mm=0.0, dsd_mm=100.0), "pitch"),
                       (SimpleNamespace(model="parallel", width=8, height=6, spacing_mm=1.0, cx=float("nan"),
                                        cy=3.0), "principal point")):
        with pytest.raises(CtsplatError, match=match):
            render(g.detach(), bad, R, t)


def test_blank_outputs_keep_every_parameter_in_the_graph_and_bad_inputs_are_named():
    """A reference alpha render no Gaussian reaches, of a model without trained opacity or colours, and a voxel
    region no Gaussian reaches still backpropagate (zero gradients, as the fused kernels give); voxelize refuses
    half precision, mixed dtypes and an unknown backend whether or not a Gaussian reaches it; render refuses an SH
    layout of no degree and a non-positive or non-finite mu_scale."""
    g = _mixture(3, seed=4, dtype=torch.float64)
    means = (g.means + torch.tensor([500.0, 0.0, 0.0], dtype=D64)).requires_grad_(True)
    scales = g.log_scales.clone().requires_grad_(True)
    bare = Gaussians(means=means, log_scales=scales, quats=g.quats, density_raw=g.density_raw)
    cam = ParallelCamera(8, 6, 1.0)
    R, t = _pose(20.0, 10.0, dist=100.0)
    render(bare, cam, R, t, compositor="alpha", backend="reference").image.sum().backward()
    assert means.grad is not None and float(means.grad.abs().max()) == 0.0
    affine = np.eye(4)
    for backend in ("reference", "auto"):
        means.grad = None
        voxelize(bare, (4, 4, 4), affine, backend=backend).sum().backward()
        assert float(means.grad.abs().max()) == 0.0 and scales.grad is not None
    for model, needle in ((g.detach().to(dtype=torch.float16), "take float32 or float64 Gaussians"),
                          (Gaussians(**{**g.detach().tensors(), "density_raw": g.density_raw.detach().float()}),
                           "Gaussians.density_raw is torch.float32, the means torch.float64")):
        with pytest.raises(CtsplatError, match=needle):
            voxelize(model, (4, 4, 4), affine)
    for far in (False, True):
        with pytest.raises(CtsplatError, match="unknown voxelize backend 'bogus'"):
            voxelize(bare.detach() if far else g.detach(), (4, 4, 4), affine, backend="bogus")
    coloured = _mixture(3, seed=5, dtype=torch.float64)
    coloured.colors = torch.rand(3, 3, dtype=D64)
    for sh, needle in ((torch.zeros(3, 5, 3, dtype=D64), "holds 5 coefficients per channel"),
                       (torch.zeros(3, 3, 2, dtype=D64), "sh_rest has 2 colour channels, the colours 3")):
        coloured.sh_rest = sh
        with pytest.raises(CtsplatError, match=needle):
            render(coloured, cam, R, t, compositor="alpha")
    for scale in (float("nan"), 0.0, -1e3, float("inf")):
        with pytest.raises(CtsplatError, match="mu_scale must be a finite number > 0"):
            render(g.detach(), cam, R, t, mu_scale=scale)


def test_the_kernels_channel_limit_is_one_line_naming_the_way_out():
    """32 colours and a background are 33 channels to the C++ alpha kernel: refused in one line that names the
    reference backend, which renders them."""
    from ctsplat.splat import _kernel

    if not _kernel.available():
        pytest.skip("the C++ kernel does not build here")
    g = _mixture(3, seed=6, dtype=torch.float64)
    g.colors = torch.rand(3, 32, dtype=D64)
    cam = ParallelCamera(8, 6, 1.0)
    R, t = _pose(20.0, 10.0, dist=100.0)
    with pytest.raises(CtsplatError, match=r"at most 32 channels \(31 colours with a background\), got 33"):
        render(g, cam, R, t, compositor="alpha", backend="kernel", background=torch.zeros(32, dtype=D64))
    img = render(g, cam, R, t, compositor="alpha", backend="reference", background=torch.zeros(32, dtype=D64)).image
    assert img.shape == (6, 8, 32)
