"""ctsplat.recon: the exact adjoint, FDK against analytic values and FBP, SART / ASD-POCS, MBIR."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from ctsplat.baselines import fbp_volume
from ctsplat.formats.viewset import ViewSet
from ctsplat.formats.volume import Volume
from ctsplat.geometry import ConeCamera, ParallelCamera, circular_orbit, sphere_orbit
from ctsplat.projector import line_integrals
from ctsplat.recon.fdk import fdk_volume, is_circular_cone, ramp_filter
from ctsplat.recon.iterative import asd_pocs_iterates, sart_iterates, total_variation, tv_gradient
from ctsplat.recon.operators import Operator
from ctsplat.recon.suite import applicable_methods, auto_binning, bin_detector
from ctsplat.utils import CtsplatError

MU = 0.02


def grid(n: int, h: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Affine of an n^3 grid of h mm voxels centred on the origin, and the voxel-centre coordinates (mm)."""
    A = np.diag([h, h, h, 1.0])
    A[:3, 3] = -(n - 1) / 2 * h
    g = (np.arange(n) - (n - 1) / 2) * h
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    return A, X, Y, Z


def two_balls(n: int, h: float = 2.0) -> Volume:
    A, X, Y, Z = grid(n, h)
    s = n * h / 64
    vol = 0.5 * ((X - 8 * s) ** 2 + (Y + 6 * s) ** 2 + Z**2 <= (12 * s) ** 2)
    vol = vol + 0.3 * ((X + 10 * s) ** 2 + (Y - 6 * s) ** 2 + Z**2 <= (8 * s) ** 2)
    vol = gaussian_filter(vol.astype(np.float32), 0.7)
    return Volume(vol, A, {"volume_id": "balls", "intensity": {"mu_scale_per_mm": MU}})


def cone_set(n: int, h: float, n_views: int, arc: float = 360.0, dso_factor: float = 2.5, start: float = 0.0
             ) -> ViewSet:
    """R²-Gaussian's geometry in mm: DSO 2.5 L, DSD 3.5 L, detector 2 L with 2 pixels per voxel edge."""
    L = n * h
    cam = ConeCamera(2 * n, 2 * n, 2 * L / (2 * n) * (dso_factor + 1) / 3.5, dso_factor * L, (dso_factor + 1) * L)
    views = circular_orbit(n_views, np.zeros(3), dso_factor * L, split_fractions={"train": 1.0}, arc_deg=arc,
                           start_deg=start)
    return ViewSet(cam, views, "balls", np.zeros(3))


def render(vol: Volume, vs: ViewSet) -> np.ndarray:
    return line_integrals(vol.data * MU, vol.affine, vs.camera, vs.Rs(), vs.ts()).numpy()


@pytest.mark.parametrize("geometry", ["parallel_circular", "parallel_sphere", "cone_circular"])
def test_backprojector_is_the_exact_adjoint(geometry):
    n = 10
    A, *_ = grid(n, 3.0)
    if geometry == "cone_circular":
        vs = cone_set(n, 3.0, 5)
    else:
        cam = ParallelCamera(14, 12, 2.5)
        views = (circular_orbit(5, np.zeros(3), 80.0, split_fractions={"train": 1.0}) if geometry.endswith("circular")
                 else sphere_orbit(5, np.zeros(3), 80.0, split_fractions={"train": 1.0}))
        vs = ViewSet(cam, views)
    op = Operator(vs, A, (n, n, n), views_per_batch=2)
    rng = np.random.default_rng(0)
    x = torch.as_tensor(rng.random((n, n, n)), dtype=torch.float32)
    x[:3] = 0  # a zero margin: the operator must not narrow its support to the non-zero voxels
    y = torch.as_tensor(rng.standard_normal(op.image_shape), dtype=torch.float32)
    Ax, ATy = op.forward(x).double(), op.adjoint(y).double()
    lhs, rhs = float((Ax * y.double()).sum()), float((x.double() * ATy).sum())
    assert abs(lhs - rhs) <= 1e-5 * (abs(lhs) + abs(rhs)), (lhs, rhs)
    assert float(Ax.abs().max()) > 0
    # the fused residual step of SART/SIRT equals a forward pass followed by the adjoint
    b, w = torch.rand(op.image_shape), torch.rand(op.image_shape)
    upd, r2 = op.residual_adjoint(x, b, w)
    np.testing.assert_allclose(upd.numpy(), op.adjoint((b - op.forward(x)) * w).numpy(), rtol=1e-4, atol=1e-5)
    assert r2 == pytest.approx(float(((b - op.forward(x)) ** 2).sum()), rel=1e-5)
    # linear: A(2x) = 2 A(x), also for a volume whose zero margin changes
    x2 = x.clone()
    x2[3:] = 0
    x2[0] = 1.0
    np.testing.assert_allclose((op.forward(x + x2) - op.forward(x) - op.forward(x2)).numpy(), 0, atol=1e-4)


def test_ramp_filter_matches_skimage():
    from skimage.transform.radon_transform import _get_fourier_filter

    for name in ("ramp", "shepp-logan", "hann"):
        np.testing.assert_allclose(2 * ramp_filter(128, name), _get_fourier_filter(128, name)[:, 0], atol=1e-12)


def test_fdk_of_balls_matches_the_analytic_values_in_the_central_slice():
    vol = two_balls(32)
    vs = cone_set(32, 2.0, 90)
    assert is_circular_cone(vs) and applicable_methods(vs) == ("fdk", "sart", "asd_pocs")
    rec = fdk_volume(render(vol, vs), vs, vol, clip=False)
    assert rec.shape == vol.shape and rec.dtype == np.float32
    A, X, Y, Z = grid(32)
    centre = (X - 8) ** 2 + (Y + 6) ** 2 <= 8**2  # well inside the big ball (value 0.5)
    small = (X + 10) ** 2 + (Y - 6) ** 2 <= 4**2  # well inside the small one (0.3)
    k = 15
    assert rec[..., k][centre[..., k]].mean() == pytest.approx(0.5, abs=0.01)
    assert rec[..., k][small[..., k]].mean() == pytest.approx(0.3, abs=0.015)
    assert np.abs(rec - vol.data)[4:-4, 4:-4, 12:20].mean() < 0.01
    # a short scan (180 deg + fan + margin) with Parker weights, from another start angle
    delta = np.degrees(np.arctan(32 * vs.camera.pitch_mm / vs.camera.dsd_mm))
    short = cone_set(32, 2.0, 120, arc=180 + 2 * delta + 4, start=30.0)
    rs = fdk_volume(render(vol, short), short, vol, clip=False)
    assert rs[..., k][centre[..., k]].mean() == pytest.approx(0.5, abs=0.02)
    assert np.abs(rs - vol.data)[4:-4, 4:-4, 12:20].mean() < 0.02
    too_short = cone_set(32, 2.0, 60, arc=150.0)
    with pytest.raises(CtsplatError, match="short scan covers 1"):
        fdk_volume(render(vol, too_short), too_short, vol)


def test_fdk_weights_rays_by_their_cone_angle():
    """A wide cone (source one volume side from the isocentre) and a ball far off the axis: its rays leave the
    source at up to ~18 deg, where FDK's cosine weight D / sqrt(D² + u² + v²) matters (without it the ball comes
    out 2.3 % too dense, 0.511, and 0.05 mm too far out); near the source plane, where a full circular scan is
    nearly exact, the ball keeps its value and place."""
    n, h = 32, 2.0
    A, X, Y, Z = grid(n, h)
    ball = (X - 20.0) ** 2 + Y**2 + Z**2 <= 6.0**2
    vol = Volume(gaussian_filter(0.5 * ball.astype(np.float32), 0.5), A,
                 {"volume_id": "offaxis", "intensity": {"mu_scale_per_mm": MU}})
    L = n * h
    dso, dsd = 1.0 * L, 2.0 * L
    cam = ConeCamera(2 * n, 2 * n, 1.3 * L * dsd / dso / (2 * n), dso, dsd)  # 1.3 L wide at the isocentre
    vs = ViewSet(cam, circular_orbit(180, np.zeros(3), dso, split_fractions={"train": 1.0}, arc_deg=360.0),
                 "offaxis", np.zeros(3))
    rec = fdk_volume(render(vol, vs), vs, vol, clip=False)
    core = (X - 20.0) ** 2 + Y**2 + Z**2 <= 3.0**2
    k = n // 2 - 1  # a slice through the ball's centre, next to the source plane
    assert rec[..., k][core[..., k]].mean() == pytest.approx(0.5, abs=0.004)
    # the ball's centroid in that slice sits where it is (x = 20 mm)
    w = np.clip(rec[..., k], 0, None) * (np.abs(X[..., k] - 20.0) <= 10.0) * (np.abs(Y[..., k]) <= 10.0)
    assert float((w * X[..., k]).sum() / w.sum()) == pytest.approx(20.0, abs=0.02)


def test_fdk_in_the_parallel_limit_agrees_with_slice_wise_fbp():
    vol = two_balls(24)
    n, h = 24, 2.0
    pv = circular_orbit(60, np.zeros(3), 200.0, split_fractions={"train": 1.0}, arc_deg=360.0)
    par = ViewSet(ParallelCamera(n, n + 2, h), pv)
    far = 1e5
    cone = ViewSet(ConeCamera(n, n + 2, h * 1.5, far, 1.5 * far),
                   circular_orbit(60, np.zeros(3), far, split_fractions={"train": 1.0}, arc_deg=360.0))
    f_par = fbp_volume(render(vol, par), par, vol, clip=False)
    f_cone = fdk_volume(render(vol, cone), cone, vol, clip=False)
    inner = (slice(3, -3),) * 3
    diff = np.abs(f_par - f_cone)[inner]
    assert diff.mean() < 0.004 and diff.max() < 0.05, (diff.mean(), diff.max())
    # and the limit is a meaningful reconstruction, not two equal failures
    assert np.abs(f_cone - vol.data)[inner].mean() < 0.02


def test_fdk_refuses_other_geometries():
    vol = two_balls(12)
    vs = cone_set(12, 2.0, 8)
    p = render(vol, vs)
    wobble = ViewSet(vs.camera, circular_orbit(8, np.zeros(3), vs.camera.dso_mm, split_fractions={"train": 1.0},
                                               wobble_deg=5.0))
    with pytest.raises(CtsplatError, match="circular orbit without wobble"):
        fdk_volume(p, wobble, vol)
    with pytest.raises(CtsplatError, match="unknown FDK filter"):
        fdk_volume(p, vs, vol, filter_name="butterworth")
    with pytest.raises(CtsplatError, match="do not match"):
        fdk_volume(p[:3], vs, vol)
    assert applicable_methods(wobble) == ("sart", "asd_pocs")


def _residual(op: Operator, x: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(op.forward(x) - b))


@pytest.mark.parametrize("subsets", [1, 4])
def test_sart_reduces_the_residual_and_stays_non_negative(subsets):
    vol = two_balls(16)
    vs = cone_set(16, 2.0, 12)
    p = render(vol, vs)
    op = Operator(vs, vol.affine, vol.shape, step_voxels=1.0)
    b = torch.as_tensor(p / MU)
    res = [_residual(op, torch.zeros(vol.shape), b)]
    for _, x in sart_iterates(p, vs, vol, iterations=4, relaxation=1.0, subsets=subsets, step_voxels=1.0):
        assert float(x.min()) >= 0.0
        res.append(_residual(op, x, b))
    assert all(a > c for a, c in zip(res, res[1:], strict=False)), res
    assert res[-1] < 0.35 * res[0]


def test_asd_pocs_reduces_the_residual_and_tv_steps_lower_tv():
    vol = two_balls(16)
    vs = cone_set(16, 2.0, 10)
    p = render(vol, vs)
    rng = np.random.default_rng(1)
    noisy = p + rng.normal(0, 0.02 * p.max(), p.shape).astype(np.float32)
    op = Operator(vs, vol.affine, vol.shape, step_voxels=1.0)
    b = torch.as_tensor(p / MU)
    r0 = _residual(op, torch.zeros(vol.shape), b)
    tv_asd = tv_sart = None
    for _, x in asd_pocs_iterates(noisy, vs, vol, iterations=5, alpha=0.1, tv_steps=10, subsets=5, step_voxels=1.0):
        tv_asd = float(total_variation(x))
        assert float(x.min()) >= -0.05  # positivity is enforced on each data step; TV steps barely leave it
    for _, y in sart_iterates(noisy, vs, vol, iterations=5, subsets=5, step_voxels=1.0):
        tv_sart = float(total_variation(y))
    assert _residual(op, x, b) < 0.5 * r0
    assert tv_asd < 0.9 * tv_sart  # the TV steps regularise
    # the closed-form TV gradient is the autograd one, and one normalised descent step along it lowers the TV
    g = tv_gradient(y)
    leaf = y.clone().requires_grad_(True)
    total_variation(leaf).backward()
    np.testing.assert_allclose(g.numpy(), leaf.grad.numpy(), rtol=1e-4, atol=1e-4)
    step = y - 0.01 * torch.linalg.vector_norm(y) * g / torch.linalg.vector_norm(g)
    assert float(total_variation(step)) < tv_sart


def test_detector_binning_averages_pixels_and_keeps_the_geometry():
    vol = two_balls(16)
    vs = cone_set(16, 2.0, 4)
    p = render(vol, vs)
    assert auto_binning(vs, vol) == 2  # 2 mm pitch = 1.43 mm at the isocentre: 2 x 2 pixels = 1.43 voxels
    assert auto_binning(ViewSet(ParallelCamera(16, 16, 2.0), vs.views), vol) == 1  # one voxel per pixel already
    pb, vb = bin_detector(p, vs, 2)
    assert pb.shape == (4, 16, 16) and vb.camera.pitch_mm == pytest.approx(2 * vs.camera.pitch_mm)
    direct = render(vol, vb)
    assert np.abs(pb - direct).mean() < 0.05 * np.abs(direct).mean()
    with pytest.raises(CtsplatError, match="baselines.detector_binning 3"):
        bin_detector(p, vs, 3)


def test_mbir_recovers_a_disc():
    pytest.importorskip("svmbir")
    from ctsplat.recon.mbir import mbir_volume

    n, h = 24, 2.0
    A, X, Y, Z = grid(n, h)
    disc = ((X - 3) ** 2 + (Y + 2) ** 2 <= 8**2) & (np.abs(Z) < 20)
    vol = Volume(gaussian_filter(disc.astype(np.float32) * 0.6, 0.5), A, {"volume_id": "disc",
                                                                            "intensity": {"mu_scale_per_mm": MU}})
    vs = ViewSet(ParallelCamera(n, n + 2, h), circular_orbit(36, np.zeros(3), 100.0, split_fractions={"train": 1.0}))
    p = render(vol, vs)
    rec = mbir_volume(p, vs, vol, sharpness=0.0, snr_db=30.0, num_threads=1)
    inside = ((X - 3) ** 2 + (Y + 2) ** 2 <= 5**2) & (np.abs(Z) < 14)
    assert rec[inside].mean() == pytest.approx(0.6, abs=0.03)
    assert np.abs(rec - vol.data).mean() < 0.005
    assert np.abs(rec - vol.data).mean() < 0.5 * np.abs(fbp_volume(p, vs, vol) - vol.data).mean()
    assert rec.min() >= 0 and rec.max() <= 1
    again = mbir_volume(p, vs, vol, sharpness=0.0, snr_db=30.0)  # one thread (the default): bit-identical
    np.testing.assert_array_equal(again, rec)


def test_a_diverged_candidate_never_wins_the_choice():
    """A candidate whose reconstruction diverged (NaN) scores NaN on validation; NaN never loses a comparison, so
    listed first it used to be chosen over every finite candidate."""
    from ctsplat.recon.select import choose, choose_iterative

    class ByMean:  # stands in for the validation views: higher is better, NaN for a NaN volume
        def score(self, vol: np.ndarray) -> float:
            return float(-np.mean(vol))

    def volume(k: int) -> np.ndarray:
        return np.full((2, 2, 2), np.nan if k == 0 else 0.1 * k, np.float32)

    direct = choose("m", [{"k": 0}, {"k": 2}, {"k": 1}], volume, ByMean(), clip=False)
    assert direct.params == {"k": 1} and np.isnan(direct.trials[0]["val_psnr"])

    def iterates(k: int):
        for it in (1, 2):
            yield it, volume(k) if k == 0 else volume(k) * it

    iterative = choose_iterative("m", [{"k": 0}, {"k": 1}], iterates, ByMean(), clip=False)
    assert iterative.params == {"k": 1, "iterations": 1}


def test_the_best_classical_method_is_never_a_nan_one():
    from ctsplat.recon.select import Choice
    from ctsplat.recon.suite import best_choice

    vol = np.zeros((2, 2, 2), np.float32)
    choices = [Choice("sart", {}, float("nan"), vol, 1.0), Choice("asd_pocs", {}, 40.0, vol, 1.0)]
    assert best_choice(choices).method == "asd_pocs"


def _parker_reference(beta: float, gamma: float, d: float) -> float:
    """Parker's (1982) short-scan weight w(β, γ) for half fan angle ``d`` (0 outside 0 <= β <= π + 2d)."""
    if beta < 0.0 or beta > np.pi + 2 * d:
        return 0.0
    if beta < 2 * (d - gamma):
        return float(np.sin(np.pi / 4 * beta / (d - gamma)) ** 2)
    if beta > np.pi - 2 * gamma:
        return float(np.sin(np.pi / 4 * (np.pi + 2 * d - beta) / (d + gamma)) ** 2)
    return 1.0


@pytest.mark.parametrize("extra_deg", [0.0, 12.0])
def test_parker_weights_match_the_published_formula_and_sum_to_one_over_redundant_rays(extra_deg: float) -> None:
    """Short-scan weights against Parker 1982 written out (δ' = (scan - π) / 2 for a longer scan, Wesarg 2002),
    and w(β, γ) + w(β ± π + 2γ, -γ) = 1 for every ray, by brute force over a (β, γ) grid."""
    from ctsplat.recon.fdk import _parker

    delta = np.radians(10.0)
    scan = np.pi + 2 * delta + np.radians(extra_deg)
    d = (scan - np.pi) / 2  # = delta for the minimal short scan
    beta = np.linspace(0.0, scan, 181)
    gamma = np.linspace(-delta, delta, 13)[1:-1]  # inside the fan
    w = _parker(beta, gamma, delta, scan)
    ref = np.array([[_parker_reference(b, g, d) for g in gamma] for b in beta])
    np.testing.assert_allclose(w, ref, atol=1e-12)
    inner = (beta > 1e-9) & (beta < scan - 1e-9)
    assert (w[inner] > 0).all()  # every view inside the arc contributes (no data thrown away)

    def weight(b: np.ndarray, g: float) -> np.ndarray:  # the library's weights, 0 where no view exists
        vals = _parker(b, np.array([g]), delta, scan)[:, 0]
        return np.where((b >= 0) & (b <= scan), vals, 0.0)

    for k, g in enumerate(gamma):
        total = w[:, k] + weight(beta + np.pi + 2 * g, -g) + weight(beta - np.pi + 2 * g, -g)
        np.testing.assert_allclose(total, 1.0, atol=1e-12)


def test_a_short_scan_reports_the_length_of_its_arc() -> None:
    """N views at start + arc k / N cover ``arc`` (each view half a gap either side): the reported range, the
    shortfall message and the acceptance of an arc just over 180 deg + fan angle follow that true length."""
    from ctsplat.recon.fdk import _half_fan, angular_weights, orbit_angles, short_scan_shortfall

    arc = 150.0
    vs = cone_set(16, 2.0, 60, arc=arc, start=20.0)
    dbeta, short, _, scan = angular_weights(orbit_angles(vs))
    assert short
    assert scan == pytest.approx(np.radians(arc), abs=1e-9)
    np.testing.assert_allclose(dbeta, np.radians(arc / 60), rtol=1e-9)
    assert "covers 150 deg" in short_scan_shortfall(vs)
    fan = 2 * np.degrees(_half_fan(vs.camera))
    assert short_scan_shortfall(cone_set(16, 2.0, 40, arc=180 + fan + 0.3)) is None
    assert "covers" in short_scan_shortfall(cone_set(16, 2.0, 40, arc=180 + fan - 0.3))


def test_fdk_of_a_single_detector_impulse_matches_the_feldkamp_formula() -> None:
    """One pixel of one view set to 1: a voxel on that pixel's ray gets ½ Δβ (DSO / U)² h[0] / τ · D / √(D² + u² +
    v²) (Feldkamp et al. 1984 written out, u, v at the pixel centre, h[0] = ¼), for pixels off centre in u and v."""
    W, H, pitch, dso, dsd = 24, 20, 1.5, 60.0, 100.0
    cam = ConeCamera(W, H, pitch, dso, dsd)
    vs = ViewSet(cam, circular_orbit(4, np.zeros(3), dso, split_fractions={"train": 1.0}))
    R, t = vs.Rs()[0], vs.ts()[0]
    tau = pitch * dso / dsd
    for i, j, depth in [(1, W - 2, 0.8 * dso), (H - 1, 0, 1.1 * dso), (H // 2, W - 1, dso), (0, W // 2 - 1, dso)]:
        p = np.zeros((4, H, W), np.float32)
        p[0, i, j] = 1.0
        u, v = (j + 0.5 - W / 2) * pitch, (i + 0.5 - H / 2) * pitch  # pixel-centre coordinates on the detector
        cam_pt = np.array([u / dsd * depth, v / dsd * depth, depth])
        affine = np.eye(4)
        affine[:3, 3] = R.T @ (cam_pt - t)
        ref = Volume(np.zeros((1, 1, 1), np.float32), affine,
                     {"volume_id": "pt", "intensity": {"mu_scale_per_mm": 1.0}})
        got = fdk_volume(p, vs, ref, clip=False)[0, 0, 0]
        expected = 0.5 * (np.pi / 2) * (dso / depth) ** 2 * 0.25 / tau * dsd / np.sqrt(dsd**2 + u**2 + v**2)
        assert got == pytest.approx(expected, rel=2e-5), (i, j)


def _sirt_step(op: Operator, x: torch.Tensor, b: torch.Tensor, lam: float) -> torch.Tensor:
    """One SIRT update written out: max(0, x + λ C Aᵀ R (b - A x)), R = 1 / (A 1), C = 1 / (Aᵀ 1) (0 where unhit)."""
    row = op.forward(torch.ones(op.shape)).double()
    col = op.adjoint(torch.ones(op.image_shape)).double()
    rinv = torch.where(row > 1e-6, 1.0 / row.clamp_min(1e-6), torch.zeros(()))
    cinv = torch.where(col > 1e-6, 1.0 / col.clamp_min(1e-6), torch.zeros(()))
    resid = (b.double() - op.forward(x.float()).double()) * rinv
    return (x.double() + lam * cinv * op.adjoint(resid.float()).double()).clamp_min(0.0)


def _small_problem() -> tuple[Any, Any, np.ndarray, Operator, torch.Tensor, torch.Tensor]:
    """Two balls on a 10³ grid, 6 cone views, their radiographs, the operator, b = p / μ and a non-zero start."""
    vol = two_balls(10)
    vs = cone_set(10, 2.0, 6)
    p = render(vol, vs)
    op = Operator(vs, vol.affine, vol.shape, step_voxels=1.0)
    b = torch.as_tensor(p / MU)
    x0 = torch.as_tensor(np.random.default_rng(3).random(vol.shape) * 0.4, dtype=torch.float32)
    return vol, vs, p, op, b, x0


@pytest.mark.parametrize("relaxation", [0.5, 1.4])
def test_one_sirt_sweep_is_the_relaxed_update_written_out(relaxation: float) -> None:
    """One SART sweep with one subset (SIRT) and relaxation λ ≠ 1 from a non-zero start equals the Gilbert/Andersen-
    Kak update max(0, x + λ C Aᵀ R (b - A x)) composed by hand from the projector and its adjoint."""
    vol, vs, p, op, b, x0 = _small_problem()
    _, x1 = next(sart_iterates(p, vs, vol, iterations=1, relaxation=relaxation, subsets=1, step_voxels=1.0, x0=x0))
    expected = _sirt_step(op, x0, b, relaxation)
    assert float((expected - x0.double()).abs().max()) > 0.05  # the step is not negligible
    np.testing.assert_allclose(x1.double().numpy(), expected.numpy(), atol=2e-4 * float(expected.abs().max()))


def test_asd_pocs_follows_the_sidky_pan_step_size_recursion() -> None:
    """ASD-POCS iterates against Sidky & Pan (2008) written out: a SIRT sweep with λ shrinking by relaxation_red,
    then tv_steps normalised TV-descent steps of length dtvg = min(dtvg, α dp), dtvg shrunk by alpha_red when the TV
    steps moved the volume by more than r_max dp."""
    vol, vs, p, op, b, x0 = _small_problem()
    alpha, tv_steps, lam, lam_red, alpha_red, r_max = 1.0, 4, 1.0, 0.9, 0.5, 1.5
    got = [x.double() for _, x in asd_pocs_iterates(
        p, vs, vol, iterations=5, alpha=alpha, tv_steps=tv_steps, relaxation=lam, relaxation_red=lam_red,
        alpha_red=alpha_red, r_max=r_max, subsets=1, step_voxels=1.0, x0=x0)]
    x = x0.double()
    dtvg: float | None = None
    fired = []
    for k in range(5):
        x_data = _sirt_step(op, x, b, lam)
        dp = float(torch.linalg.vector_norm(x_data - x))
        dtvg = alpha * dp if dtvg is None else min(dtvg, alpha * dp)
        x = x_data
        for _ in range(tv_steps):
            g = tv_gradient(x.float()).double()
            x = x - dtvg / float(torch.linalg.vector_norm(g)) * g
        dg = float(torch.linalg.vector_norm(x - x_data))
        assert abs(dg / dp - r_max) > 0.05  # far from the threshold: float noise cannot flip the branch
        fired.append(dg > r_max * dp)
        if fired[-1]:
            dtvg *= alpha_red
        lam *= lam_red
        assert float(torch.linalg.vector_norm(got[k] - x)) < 1e-3 * float(torch.linalg.vector_norm(x)), k
    assert any(fired) and not all(fired), fired  # both branches of the adaptive rule are exercised


def test_patience_stops_a_candidate_after_that_many_checks_without_improvement() -> None:
    """choose_iterative(patience=P) runs an improving candidate to the end and stops a stalled one after exactly P
    iterations without a better score (counted by hand for each sequence)."""
    from ctsplat.recon.select import choose_iterative

    class ByMean:
        def score(self, vol: np.ndarray) -> float:
            return float(np.mean(vol))

    sequences = {"rising": [1, 2, 3, 4, 5, 6], "plateau": [1, 2, 2, 2, 2, 2, 7], "dip": [1, 0.5, 2, 1, 1.5, 1, 9]}

    def iterates(name: str) -> Iterator[tuple[int, np.ndarray]]:
        for it, s in enumerate(sequences[name], start=1):
            yield it, np.full((2, 2, 2), s, np.float32)

    def run(name: str, patience: int | None) -> list[int]:
        res = choose_iterative("m", [{"name": name}], iterates, ByMean(), clip=False, patience=patience)
        return [t["iterations"] for t in res.trials]

    assert run("rising", 2) == [1, 2, 3, 4, 5, 6]
    assert run("plateau", 2) == [1, 2, 3, 4]  # 2 is not better than 2: stalls at 3 and 4
    assert run("dip", 2) == [1, 2, 3, 4, 5]  # stalls at 2, improves at 3, stalls at 4 and 5
    assert run("dip", 3) == [1, 2, 3, 4, 5, 6]
    assert run("plateau", None) == list(range(1, 8))
    res = choose_iterative("m", [{"name": "dip"}], iterates, ByMean(), clip=False, patience=2)
    assert res.params == {"name": "dip", "iterations": 3} and not res.at_cap  # patience stopped it
    # still rising at its last iteration: the budget, not the validation views, stopped it, and the choice says so
    rising = choose_iterative("m", [{"name": "plateau"}, {"name": "rising"}], iterates, ByMean(), clip=False,
                              patience=2)
    assert rising.params == {"name": "rising", "iterations": 6} and rising.at_cap
    peaked = choose_iterative("m", [{"name": "dip"}], iterates, ByMean(), clip=False)  # best at its last, 9
    assert peaked.params["iterations"] == 7 and peaked.at_cap
    early = choose_iterative("m", [{"name": "plateau"}], iterates, ByMean(), clip=False, patience=10)
    assert early.params["iterations"] == 7 and early.at_cap
    settled = {"name": "settled"}
    sequences["settled"] = [1, 3, 2]
    assert not choose_iterative("m", [settled], iterates, ByMean(), clip=False).at_cap  # best before the last
