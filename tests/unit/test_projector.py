"""Projector exactness against independent references (skimage radon, closed-form ellipsoid chords), noise, files."""

from __future__ import annotations

import functools
import json
import math
import os
import re
import warnings
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from skimage.transform import radon

from ctsplat.formats.viewset import ViewSet, load_radiographs
from ctsplat.formats.volume import Volume, load_volume, save_volume
from ctsplat.geometry import ConeCamera, ParallelCamera, camera_rays, pose_from_angles
from ctsplat.phantom import Ellipsoid, rasterize, shepp_logan_ellipsoids
from ctsplat.projector import (
    RADIOGRAPHS_DEFAULTS,
    add_noise,
    check_noise,
    clip_rays_to_box,
    line_integrals,
    render_radiographs,
)
from ctsplat.utils import CtsplatError

# ------------------------------------------------------------------------------ analytic ellipsoids
# The phantom's analytic 3D Shepp–Logan ellipsoids (ctsplat.phantom, world mm, values relative to water),
# shrunk to a 28 mm unit and moved to C0; μ = MU_WATER * value.
C0 = np.array([5.0, -3.0, 20.0])
S = 28.0
MU_WATER = 0.019


def ellipsoid_list():
    """(centre mm, semi-axes mm, rotation (columns = axes), μ value 1/mm) of the phantom's ellipsoids."""
    return [(C0 + e.centre_mm, e.semi_axes_mm, e.rotation, MU_WATER * e.value)
            for e in shepp_logan_ellipsoids(scale_mm=S, beads=False)]


def chord_integrals(origins: np.ndarray, dirs: np.ndarray, ellipsoids) -> np.ndarray:
    """Exact ∫ μ ds along rays ``o + s d`` (s >= 0, |d| = 1): Σ value × chord length through each ellipsoid.

    In the ellipsoid's unit-sphere frame ``p = A^-1 Q^T (o - c)``, ``q = A^-1 Q^T d``; the chord is the
    interval where ``|p + s q|^2 <= 1``: length ``2 sqrt(b^2 - |q|^2 (|p|^2 - 1)) / |q|^2`` with ``b = p.q``.
    """
    total = np.zeros(origins.shape[:-1])
    for c, a, Q, val in ellipsoids:
        p = ((origins - c) @ Q) / a
        q = (dirs @ Q) / a
        qq = np.sum(q * q, -1)
        b = np.sum(p * q, -1)
        disc = b * b - qq * (np.sum(p * p, -1) - 1.0)
        root = np.sqrt(np.maximum(disc, 0.0))
        s0 = np.maximum((-b - root) / qq, 0.0)
        s1 = np.maximum((-b + root) / qq, 0.0)
        total += val * np.where(disc > 0, s1 - s0, 0.0)
    return total


def voxelize(ells, affine: np.ndarray, shape, supersample: int = 2) -> np.ndarray:
    """Voxel averages of the ellipsoids (the phantom's rasteriser; the chord integrals above are the reference)."""
    es = [Ellipsoid(c, a, Q, v) for c, a, Q, v in ells]
    return rasterize(es, shape, affine, supersample=supersample)


def oblique_affine(n: int, side_mm: float) -> np.ndarray:
    """Voxel grid covering a cube of ``side_mm`` around C0 with permuted and flipped axes (i -> -y, j -> +x)."""
    h = side_mm / n
    M = np.array([[0.0, h, 0.0], [-h, 0.0, 0.0], [0.0, 0.0, h]])
    A = np.eye(4)
    A[:3, :3] = M
    A[:3, 3] = C0 - M @ np.full(3, (n - 1) / 2)
    return A


# ---------------------------------------------------------------------------------- exactness tests
def test_parallel_circular_orbit_equals_skimage_radon_per_slice():
    n, h = 33, 1.5  # odd size: skimage's rotation centre (n // 2) is the voxel centre (n - 1) / 2
    g = np.arange(n) - n // 2
    I, J, K = np.meshgrid(g, g, g, indexing="ij")
    vol = np.exp(-((I - 3) ** 2 / 30 + (J + 2) ** 2 / 60 + K**2 / 80))
    vol += 0.6 * np.exp(-((I + 5) ** 2 + (J - 4) ** 2 + (K - 3) ** 2) / 10)
    vol = (vol * (I**2 + J**2 < 15**2)).astype(np.float32)  # zero outside the reconstruction circle
    affine = np.diag([h, h, h, 1.0])  # axes (+x, +y, +z): slice [i, j] is radon's [row, col]
    affine[:3, 3] = [10.0, -20.0, 5.0]
    iso = affine[:3, :3] @ np.full(3, n // 2) + affine[:3, 3]
    theta = np.linspace(0.0, 360.0, 24, endpoint=False)
    poses = [pose_from_angles(a, 0.0, iso, 200.0) for a in theta]
    p = line_integrals(vol, affine, ParallelCamera(n, n, h), np.stack([R for R, _ in poses]),
                       np.stack([t for _, t in poses])).numpy()
    interior = slice(2, n - 2)
    for k in range(2, n - 2):
        ref = radon(vol[:, :, k], theta=theta, circle=True) * h  # (detector, angle), pixel units -> mm
        mine = p[:, n - 1 - k, :].T  # image row v = n-1-k holds slice k (superior at the top)
        err = np.linalg.norm(mine[interior] - ref[interior]) / np.linalg.norm(ref[interior])
        assert err < 0.01, (k, err)


def _views(n_views: int, dist: float):
    poses = [pose_from_angles(az, el, C0, dist) for az, el in ((0, 0), (37, 20), (101, -35), (200, 5))[:n_views]]
    return np.stack([R for R, _ in poses]), np.stack([t for _, t in poses])


def _phantom(name: str):
    ells = ellipsoid_list()
    if name == "no_skull":  # outer ellipsoid filled with the brain value
        ells = [ells[0][:3] + (ells[0][3] + ells[1][3],)] + ells[2:]
    return ells


@functools.cache
def _voxelized(name: str, n: int) -> np.ndarray:
    return voxelize(_phantom(name), oblique_affine(n, 64.0), (n, n, n), supersample=2)


@pytest.mark.parametrize("model", ["parallel", "cone", "parallel_circular"])
@pytest.mark.parametrize(("phantom", "bound"), [("shepp_logan", 0.07), ("no_skull", 0.035)])
def test_ellipsoid_chord_lengths_error_shrinks_with_voxel_size(model, phantom, bound):
    """Projections of voxelised ellipsoids converge to the exact chord integrals (first order in the voxel size).

    The Shepp–Logan skull (~0.8 mm thick here) is thinner than the voxels, so it dominates the error (~5% at
    48^3); without it (outer ellipsoid filled with the brain value) the error is ~2-3% at 48^3 and roughly
    halves with the voxel size.
    """
    ells = _phantom(phantom)
    if model == "cone":
        cam, dist = ConeCamera(24, 24, 4.5, 150.0, 250.0), 150.0
    else:
        cam, dist = ParallelCamera(24, 24, 2.8), 200.0
    Rs, ts = _views(4, dist)
    if model == "parallel_circular":  # elevation 0 -> the slice-wise Joseph projector
        poses = [pose_from_angles(az, 0.0, C0, dist) for az in (0.0, 37.0, 101.0, 200.0)]
        Rs, ts = np.stack([R for R, _ in poses]), np.stack([t for _, t in poses])
    exact = np.stack([chord_integrals(*camera_rays(cam, R, t), ells) for R, t in zip(Rs, ts, strict=True)])
    assert exact.max() > 0.2  # the rays do cross the phantom
    errors = []
    for n in (24, 48):
        A = oblique_affine(n, 64.0)
        p = line_integrals(_voxelized(phantom, n), A, cam, Rs, ts).numpy()
        errors.append(np.linalg.norm(p - exact) / np.linalg.norm(exact))
    assert errors[1] < 0.7 * errors[0], errors
    assert errors[1] < bound, errors


def test_cone_beam_converges_to_parallel_as_dso_grows():
    n, h = 24, 2.0
    A = oblique_affine(n, n * h)
    vol = voxelize(ellipsoid_list(), A, (n, n, n), supersample=1)
    par = ParallelCamera(20, 20, 2.5)
    Rs, ts = _views(3, 500.0)
    ref = line_integrals(vol, A, par, Rs, ts).numpy()
    errs = []
    for dso in (200.0, 2000.0, 20000.0):
        cone = ConeCamera(20, 20, 2.5 * 1.5, dso, 1.5 * dso)  # magnification 1.5: same pixel size at the isocentre
        Rc, tc = _views(3, dso)
        errs.append(np.linalg.norm(line_integrals(vol, A, cone, Rc, tc).numpy() - ref) / np.linalg.norm(ref))
    assert errs[0] > errs[1] > errs[2], errs
    assert errs[2] < 2e-3, errs


def test_joseph_and_trilinear_agree_on_circular_orbits():
    n = 24
    A = oblique_affine(n, 64.0)
    vol = _voxelized("no_skull", n)
    for cam, el in ((ParallelCamera(30, 28, 2.5), 0.0), (ParallelCamera(17, 33, 3.1), 0.0)):
        poses = [pose_from_angles(az, el, C0 + [1.0, -2.0, 0.7], 300.0) for az in np.linspace(0, 360, 13)]
        Rs, ts = np.stack([R for R, _ in poses]), np.stack([t for _, t in poses])
        jos = line_integrals(vol, A, cam, Rs, ts, method="joseph")
        tri = line_integrals(vol, A, cam, Rs, ts, method="trilinear", step_voxels=0.25)
        assert float(torch.linalg.norm(jos - tri) / torch.linalg.norm(tri)) < 0.01
        torch.testing.assert_close(line_integrals(vol, A, cam, Rs, ts), jos)  # auto picks joseph
        torch.testing.assert_close(line_integrals(vol, A, cam, Rs, ts, batch_samples=100), jos)
    Rs, ts = _views(2, 300.0)  # elevation != 0: no slice structure
    with pytest.raises(CtsplatError, match="joseph projector needs"):
        line_integrals(vol, A, ParallelCamera(8, 8, 2.0), Rs, ts, method="joseph")
    with pytest.raises(CtsplatError, match="joseph projector needs"):
        line_integrals(vol, A, ConeCamera(8, 8, 2.0, 300.0, 400.0), Rs[:1] * 0 + np.eye(3)[[1, 2, 0]], ts[:1],
                       method="joseph")


def test_joseph_counts_only_what_lies_in_front_of_a_detector_inside_the_volume():
    """A parallel detector through the volume's centre sees the half in front of it: Joseph against the clipped
    ray march, and two opposite half views (the one mirrored) against the whole line integral."""
    n = 24
    A = oblique_affine(n, 64.0)
    vol = _voxelized("no_skull", n)
    cam = ParallelCamera(30, 28, 2.5)
    centre = C0 + [1.0, -2.0, 0.7]
    for az in (0.0, 40.0):
        poses = [pose_from_angles(a, 0.0, centre, 300.0) for a in (az, az + 180.0, az)]
        Rs, ts = np.stack([R for R, _ in poses]), np.stack([t for _, t in poses])
        ts[:2] = -np.einsum("vij,j->vi", Rs[:2], centre)  # the first two detectors centred on the volume (C = -Rᵀt)
        jos = line_integrals(vol, A, cam, Rs, ts, method="joseph")
        tri = line_integrals(vol, A, cam, Rs, ts, method="trilinear", step_voxels=0.25)
        # the two differ at the cut by up to half a sample of the object's densest part (about 4 % here); without
        # the cut the detector would see the whole line (100 %)
        assert float(torch.linalg.norm(jos - tri) / torch.linalg.norm(tri)) < 0.08
        halves = jos[0] + jos[1].flip(-1)  # the opposite detector sees the image mirrored left to right
        assert float(torch.linalg.norm(halves - jos[2]) / torch.linalg.norm(jos[2])) < 0.08
        assert float(jos[0].sum()) < 0.8 * float(jos[2].sum())  # a real half, not the whole line twice


def test_clip_rays_to_box_against_brute_force():
    rng = np.random.default_rng(0)
    o = rng.uniform(-3, 3, (500, 3))
    d = rng.normal(size=(500, 3))
    d[:20, 0] = 0.0  # axis-parallel rays
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = np.array([-1.0, -0.5, 0.0]), np.array([1.0, 2.0, 1.5])
    s0, length = clip_rays_to_box(o, d, lo, hi)
    s = np.linspace(0, 12, 12001)
    pts = o[:, None] + s[None, :, None] * d[:, None]
    inside = np.all((pts > lo) & (pts < hi), -1)
    np.testing.assert_allclose(length, inside.sum(1) * (s[1] - s[0]), atol=3e-3)
    hit = length > 0
    first = np.argmax(inside, axis=1)
    np.testing.assert_allclose(s0[hit], s[first[hit]], atol=3e-3)


def test_batching_misses_and_step_are_consistent():
    n = 16
    A = oblique_affine(n, 40.0)
    vol = voxelize(ellipsoid_list(), A, (n, n, n), supersample=1) + 0.001
    cam = ParallelCamera(30, 30, 2.5)  # wider than the volume: border rays miss it
    Rs, ts = _views(2, 200.0)
    p = line_integrals(vol, A, cam, Rs, ts)
    p_small = line_integrals(vol, A, cam, Rs, ts, batch_samples=500)
    torch.testing.assert_close(p, p_small, rtol=1e-6, atol=1e-6)
    assert p[:, 0, 0].abs().max() == 0.0 and p[:, 15, 15].min() > 0
    p_fine = line_integrals(vol, A, cam, Rs, ts, step_voxels=0.1)
    assert float((p - p_fine).abs().max() / p_fine.max()) < 0.02
    # constant volume: the line integral is the chord length through the interpolant's support
    ones = np.ones((n, n, n), np.float32)
    R, t = pose_from_angles(90.0, 0.0, A[:3, :3] @ np.full(3, 7.5) + A[:3, 3], 200.0)
    p1 = line_integrals(ones, A, ParallelCamera(2, 2, 0.5), R[None], t[None]).numpy()
    np.testing.assert_allclose(p1, n * 40.0 / n, rtol=1e-5)  # n voxels of 2.5 mm: n - 1 + 2 half ramps
    # zero margins: clipping to the non-zero support changes only the quadrature, not the integral
    padded = np.zeros((n + 6, n + 6, n + 6), np.float32)
    padded[3:-3, 2:-4, 4:-2] = vol
    Ap = A.copy()
    Ap[:3, 3] -= A[:3, :3] @ np.array([3.0, 2.0, 4.0])
    tight = line_integrals(padded, Ap, cam, Rs, ts)
    full = line_integrals(torch.tensor(padded, requires_grad=True), Ap, cam, Rs, ts).detach()  # whole box
    assert float((tight - full).abs().max() / full.max()) < 0.01
    torch.testing.assert_close(tight, p, rtol=0.01, atol=0.01 * float(p.max()))
    assert float(line_integrals(np.zeros((4, 4, 4)), A, cam, Rs, ts).abs().max()) == 0.0
    with pytest.raises(CtsplatError, match="step_voxels"):
        line_integrals(vol, A, cam, Rs, ts, step_voxels=2.0)
    with pytest.raises(CtsplatError, match="empty view set"):
        line_integrals(vol, A, cam, np.zeros((0, 3, 3)), np.zeros((0, 3)))


def test_line_integrals_are_differentiable_and_linear():
    """Autograd gives the adjoint: <A x, y> = <x, A^T y> with A^T y = grad of <A x, y>."""
    n = 10
    A = oblique_affine(n, 20.0)
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.uniform(0, 1, (n, n, n)), dtype=torch.float32, requires_grad=True)
    cam = ConeCamera(8, 8, 3.0, 100.0, 150.0)
    Rs, ts = _views(2, 100.0)
    y = torch.tensor(rng.normal(size=(2, 8, 8)), dtype=torch.float32)
    Ax = line_integrals(x, A, cam, Rs, ts)
    (Ax * y).sum().backward()
    assert torch.isclose((Ax * y).sum(), (x * x.grad).sum(), rtol=1e-4)
    Ax2 = line_integrals(2 * x.detach() + 1, A, cam, Rs, ts)
    ones = line_integrals(torch.ones(n, n, n), A, cam, Rs, ts)
    torch.testing.assert_close(Ax2, 2 * Ax.detach() + ones, rtol=1e-5, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_cuda_matches_cpu():
    n = 24
    A = oblique_affine(n, 64.0)
    vol = voxelize(ellipsoid_list(), A, (n, n, n), supersample=1)
    cam = ConeCamera(24, 24, 4.5, 150.0, 250.0)
    Rs, ts = _views(4, 150.0)
    cpu = line_integrals(vol, A, cam, Rs, ts)
    gpu = line_integrals(vol, A, cam, Rs, ts, device="cuda")
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-4)


# ------------------------------------------------------------------------------------------ noise
def test_noise_statistics_seed_and_clipping():
    p = np.full((200, 200), 2.0)
    a, _ = add_noise(p, 1e5, 0.0, np.random.default_rng(0))
    b, _ = add_noise(p, 1e5, 0.0, np.random.default_rng(0))
    c, _ = add_noise(p, 1e5, 0.0, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # delta method: var(ln N) = 1 / (I0 e^-p) for Poisson counts
    expected_std = 1.0 / np.sqrt(1e5 * np.exp(-2.0))
    assert a.std() == pytest.approx(expected_std, rel=0.05)
    assert a.mean() == pytest.approx(2.0, abs=3 * expected_std / 200)
    # very few photons plus electronic noise: non-positive counts are clipped, results stay finite
    q, counts = add_noise(np.full((100, 100), 8.0), 100.0, 2.0, np.random.default_rng(2))
    assert counts.min() == 1.0 and np.isfinite(q).all() and q.max() == pytest.approx(np.log(100.0))
    with pytest.raises(CtsplatError, match="i0"):
        add_noise(p, 0.0, 0.0, np.random.default_rng(0))
    # a count numpy's Poisson sampler cannot draw (it raised ValueError past ~1e18): refused, and 1e15 still draws
    with pytest.raises(CtsplatError, match=r"must be positive and at most 1e\+15, got 1e\+19"):
        add_noise(p, 1e19, 0.0, np.random.default_rng(0))
    with pytest.raises(CtsplatError, match=r"noise\.i0 must be at most 1e\+15 photons per pixel, got 1e\+19; lower it"):
        check_noise({**RADIOGRAPHS_DEFAULTS["noise"], "enabled": True, "i0": 1e19})
    check_noise({**RADIOGRAPHS_DEFAULTS["noise"], "enabled": False, "i0": 1e19})  # unused while noise is off
    assert np.isfinite(add_noise(p, 1e15, 0.0, np.random.default_rng(0))[0]).all()
    with pytest.raises(CtsplatError, match="electronic_sigma"):
        add_noise(p, 10.0, -1.0, np.random.default_rng(0))


# ------------------------------------------------------------------------------------- the files
@pytest.fixture()
def small_volume(tmp_path):
    n = 20
    A = oblique_affine(n, 64.0)
    data = voxelize(ellipsoid_list(), A, (n, n, n), supersample=1) / 0.02  # normalised-ish
    path = tmp_path / "vol" / "volume.nii.gz"
    save_volume(Volume(data, A, {"volume_id": "phantom01", "intensity": {"mu_scale_per_mm": 0.02}}), path)
    return path, data, A


def test_render_radiographs_writes_the_contract(tmp_path, small_volume):
    vol_path, data, A = small_volume
    out = tmp_path / "radiographs"
    cfg = {"n_views": 14, "detector_width": 32, "detector_height": 24, "pixel_spacing_mm": 2.5}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the detector covers the object: no FOV warning
        vs = render_radiographs(vol_path, out, cfg, seed=3)
    p, vs2 = load_radiographs(out)
    assert p.shape == (len(vs), 24, 32) and p.dtype == np.float32
    assert len(vs) == 14 + 3 + 3 and vs2.volume_id == "phantom01"
    vol = load_volume(vol_path)  # the NIfTI affine is stored in float32
    np.testing.assert_allclose(vol.affine, A, atol=1e-5)
    expected = line_integrals(data * 0.02, vol.affine, vs.camera, vs.Rs(), vs.ts()).numpy()
    np.testing.assert_allclose(p, expected, rtol=1e-5, atol=1e-6)
    png = iio.imread(out / "png" / f"view_{vs.views[5].id:04d}.png")
    assert png.dtype == np.uint16 and png.shape == (24, 32)
    np.testing.assert_allclose(png / 65535.0, np.exp(-p[5]), atol=1.0 / 65535)
    prov = json.loads((out / "radiographs.json").read_text())
    assert prov["seed"] == 3 and prov["config"]["n_views"] == 14 and prov["volume_id"] == "phantom01"
    assert prov["mu_scale_per_mm"] == 0.02 and "code_version" in prov
    assert prov["splits"] == {"train": 14, "val": 3, "test": 3}
    assert sorted(x.name for x in out.iterdir()) == ["line_integrals.tif", "png", "radiographs.json", "views.json"]
    # noise: seeded and reproducible
    noisy = {"noise": {"enabled": True, "i0": 1e4, "electronic_sigma": 1.0}}
    render_radiographs(vol_path, tmp_path / "n1", {**cfg, **noisy}, seed=1)
    render_radiographs(vol_path, tmp_path / "n2", {**cfg, **noisy}, seed=1)
    render_radiographs(vol_path, tmp_path / "n3", {**cfg, **noisy}, seed=2)
    n1, n2, n3 = (load_radiographs(tmp_path / f"n{i}")[0] for i in (1, 2, 3))
    np.testing.assert_array_equal(n1, n2)
    assert not np.array_equal(n1, n3)
    assert 0 < np.abs(n1 - p).mean() < 0.1


def test_render_radiographs_bad_input(tmp_path, small_volume):
    vol_path, _, _ = small_volume
    small = {"n_views": 7, "detector_width": 8, "detector_height": 8, "pixel_spacing_mm": 2.0}
    with pytest.raises(CtsplatError, match=r"^radiographs.pixel_spacing_mm: the detector \(8 x 8 px\) leaves"):
        render_radiographs(vol_path, tmp_path / "fov", small)
    assert not (tmp_path / "fov").exists()
    with pytest.warns(UserWarning, match=r"% of the object lies outside the field of view"):
        render_radiographs(vol_path, tmp_path / "fov", {**small, "allow_truncation": True})
    prov = json.loads((tmp_path / "fov" / "radiographs.json").read_text())
    assert 0 < prov["fov_outside_fraction_worst_view"] < 1
    bad = [
        ({"camera": "cone", "dso_mm": 500.0, "dsd_mm": 400.0}, "must be larger than dso_mm"),
        ({"camera": "cone", "dso_mm": -5.0}, "dso_mm"),
        ({"pixel_spacing_mm": 0.0}, "spacing_mm"),
        ({"n_views": 0}, "empty view set"),
        ({"orbit": "sphere", "n_views": 4}, "split leaves"),
        ({"orbit": "helix"}, "unknown orbit"),
        ({"n_veiws": 3}, "unknown config key radiographs.n_veiws"),
    ]
    for cfg, match in bad:
        with pytest.raises(CtsplatError, match=match):
            render_radiographs(vol_path, tmp_path / "bad", {"detector_width": 8, "detector_height": 8, **cfg})
        assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())
    with pytest.raises(CtsplatError, match="does not exist"):
        load_radiographs(tmp_path / "nothing")
    assert set(RADIOGRAPHS_DEFAULTS) >= {"camera", "orbit", "n_views", "split", "noise"}
    json.dumps(RADIOGRAPHS_DEFAULTS)


def test_integer_radiographs_are_not_taken_as_line_integrals(tmp_path) -> None:
    import tifffile

    save_volume(Volume(np.ones((8, 8, 8), np.float32), np.eye(4), {"volume_id": "i"}), tmp_path / "v.nii.gz")
    render_radiographs(tmp_path / "v.nii.gz", tmp_path / "rad", {"n_views": 4, "detector_width": 8,
                                                                  "detector_height": 8})
    tif = tmp_path / "rad" / "line_integrals.tif"
    p = tifffile.imread(tif)
    tifffile.imwrite(tif, np.round(p * 1000).astype(np.uint16))  # counts or scaled values from another tool
    with pytest.raises(CtsplatError, match=r"line_integrals\.tif holds uint16 values, not line integrals"):
        load_radiographs(tmp_path / "rad")
    tifffile.imwrite(tif, p.astype(np.float64))  # any floating point type is line integrals
    np.testing.assert_array_equal(load_radiographs(tmp_path / "rad")[0], p)


def test_carm_view_set_fits_the_object_and_stores_the_design(tmp_path) -> None:
    """orbit: carm renders the SfM view set: every view a training view with its designed pose; the detector pitch
    fits the object's bounding sphere; the true orbit's error is seeded by the projection seed."""
    from ctsplat.formats.viewset import ViewSet
    from ctsplat.geometry import support_radius_mm
    from ctsplat.projector import fitted_pitch_mm

    data = np.zeros((24, 24, 24), np.float32)
    data[6:18, 6:18, 6:18] = 1.0
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    save_volume(Volume(data, aff, {"volume_id": "cube", "intensity": {"mu_scale_per_mm": 0.02}}),
                tmp_path / "v.nii.gz")
    cfg = {"camera": "cone", "orbit": "carm", "n_views": 10, "detector_width": 20, "detector_height": 20,
           "dso_mm": 300.0, "dsd_mm": 600.0, "wobble_deg": 10.0, "orbit_jitter_deg": 1.0, "device": "cpu"}
    vs = render_radiographs(tmp_path / "v.nii.gz", tmp_path / "a", cfg, seed=4)
    assert len(vs) == 10 and set(vs.indices("train")) == set(range(10)) and vs.has_design()
    radius = support_radius_mm(data, aff, vs.isocenter_mm)
    assert vs.camera.pitch_mm == pytest.approx(fitted_pitch_mm(radius, 300.0, 600.0, 20))
    # independently: the ray from the source to the detector's edge (u = W/2 pitch at DSD) passes the isocentre
    # at the sphere's radius (point-to-line distance DSO u / sqrt(u² + DSD²)), i.e. it grazes the bounding sphere
    edge_u = 20 / 2 * vs.camera.pitch_mm
    assert 300.0 * edge_u / math.hypot(edge_u, 600.0) == pytest.approx(radius, rel=1e-9)
    p, back = load_radiographs(tmp_path / "a")
    assert p.shape == (10, 20, 20) and back.has_design()
    # the object's shadow fits on the detector: no ray through the corner pixels hits it
    assert np.all(p[:, 0, 0] == 0) and np.all(p.max(axis=(1, 2)) > 0)
    again = ViewSet.load(tmp_path / "a" / "views.json")
    np.testing.assert_allclose(again.Rs(), vs.Rs())
    other = render_radiographs(tmp_path / "v.nii.gz", tmp_path / "b", cfg, seed=5)
    assert not np.allclose(other.Rs(), vs.Rs()) and np.allclose(other.design_Rs(), vs.design_Rs())
    with pytest.raises(CtsplatError, match="camera: cone"):
        render_radiographs(tmp_path / "v.nii.gz", tmp_path / "c", {**cfg, "camera": "parallel"})


def test_project_refuses_a_non_finite_volume(tmp_path) -> None:
    data = np.ones((8, 8, 8), np.float32)
    data[2, 3, 4] = np.nan
    data[5, 5, 5] = np.inf
    save_volume(Volume(data, np.eye(4), {"volume_id": "bad", "intensity": {"mu_scale_per_mm": 0.02}}),
                tmp_path / "v.nii.gz")
    with pytest.raises(CtsplatError, match="2 non-finite voxels"):
        render_radiographs(tmp_path / "v.nii.gz", tmp_path / "out", {"n_views": 4, "detector_width": 8,
                                                                      "detector_height": 8})
    assert not (tmp_path / "out").exists()


def test_project_refuses_a_volume_that_is_not_attenuation(tmp_path) -> None:
    hu = np.full((8, 8, 8), -1000.0, np.float32)  # air in HU
    hu[2:6, 2:6, 2:6] = 40.0
    opts = {"n_views": 4, "detector_width": 8, "detector_height": 8}
    save_volume(Volume(hu, np.eye(4), {"volume_id": "hu", "intensity": {"kind": "hu"}}), tmp_path / "hu.nii.gz")
    with pytest.raises(CtsplatError, match=r"holds raw HU \(intensity: hu\), not attenuation"):
        render_radiographs(tmp_path / "hu.nii.gz", tmp_path / "out", opts)
    save_volume(Volume(hu, np.eye(4), {"volume_id": "plain"}), tmp_path / "plain.nii.gz")
    with pytest.raises(CtsplatError, match=r"negative values down to -1000 .*looks like HU"):
        render_radiographs(tmp_path / "plain.nii.gz", tmp_path / "out", opts)
    assert not (tmp_path / "out").exists()
    ripple = np.where(hu > 0, 1.0, 0.0).astype(np.float32)
    ripple[0, 0, :] = -0.01  # a reconstruction's small negative ripple is still attenuation
    save_volume(Volume(ripple, np.eye(4), {"volume_id": "ripple"}), tmp_path / "ripple.nii.gz")
    # the NIfTI copied without its sidecar: normalised attenuation or mu in 1/mm? refused, not guessed
    lonely = tmp_path / "lonely" / "ripple.nii.gz"
    lonely.parent.mkdir()
    lonely.write_bytes((tmp_path / "ripple.nii.gz").read_bytes())
    with pytest.raises(CtsplatError, match=r"has no ripple\.json beside it .* run `ctsplat ingest` on it"):
        render_radiographs(lonely, tmp_path / "out", opts)
    assert not (tmp_path / "out").exists()
    render_radiographs(tmp_path / "ripple.nii.gz", tmp_path / "out", opts)
    assert (tmp_path / "out" / "line_integrals.tif").is_file()


def test_reading_radiographs_with_a_nan_pixel_names_the_view(tmp_path) -> None:
    import tifffile

    data = np.zeros((8, 8, 8), np.float32)
    data[2:6, 2:6, 2:6] = 1.0
    save_volume(Volume(data, np.eye(4), {"volume_id": "nan"}), tmp_path / "v.nii.gz")
    render_radiographs(tmp_path / "v.nii.gz", tmp_path / "rad", {"n_views": 4, "detector_width": 8,
                                                                  "detector_height": 8})
    p, vs = load_radiographs(tmp_path / "rad")
    p[2, 3, 3] = np.nan
    tifffile.imwrite(tmp_path / "rad" / "line_integrals.tif", p)
    with pytest.raises(CtsplatError, match=rf"1 non-finite pixels \(NaN/Inf\), the first in view {vs.views[2].id}"):
        load_radiographs(tmp_path / "rad")


def test_a_view_set_with_a_view_missing_its_rotation_is_named(tmp_path) -> None:
    data = np.ones((8, 8, 8), np.float32)
    save_volume(Volume(data, np.eye(4), {"volume_id": "vs"}), tmp_path / "v.nii.gz")
    render_radiographs(tmp_path / "v.nii.gz", tmp_path / "rad", {"n_views": 4, "detector_width": 8,
                                                                  "detector_height": 8})
    d = json.loads((tmp_path / "rad" / "views.json").read_text())
    del d["views"][1]["R"]
    (tmp_path / "rad" / "views.json").write_text(json.dumps(d))
    with pytest.raises(CtsplatError, match=r"views\.json is malformed \(no 'R' entry\); re-render it"):
        ViewSet.load(tmp_path / "rad" / "views.json")


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda d: d["views"][1].update(R=(2 * np.asarray(d["views"][1]["R"])).tolist()),
         "view 1: R is not a rotation matrix"),
        (lambda d: d["views"][1].update(R=(-np.asarray(d["views"][1]["R"])).tolist()),
         "view 1: R is not a rotation matrix"),  # orthonormal but a reflection
        (lambda d: d["views"][2].update(id=d["views"][0]["id"]), "view id 0 appears more than once"),
        (lambda d: d.update(views="abc"), "'views' is not a list of view objects"),
        (lambda d: d["views"][1].update(t=[float("nan"), 0.0, 0.0]), "view 1: t is not finite"),
        (lambda d: d["views"][2].update(azimuth_deg="x"), "view 2: azimuth_deg 'x' is not a number"),
        (lambda d: d["views"][0].update(elevation_deg=float("inf")), "view 0: elevation_deg is not finite"),
        (lambda d: d.update(camera=None), "'camera' is not an object"),
        (lambda d: d.update(isocenter_mm=[0.0, float("nan"), 0.0]), "isocenter_mm is not three finite numbers"),
    ],
)
def test_a_view_set_that_is_not_a_set_of_camera_poses_is_refused(tmp_path, edit, needle) -> None:
    data = np.ones((8, 8, 8), np.float32)
    save_volume(Volume(data, np.eye(4), {"volume_id": "vs"}), tmp_path / "v.nii.gz")
    render_radiographs(tmp_path / "v.nii.gz", tmp_path / "rad", {"n_views": 4, "detector_width": 8,
                                                                  "detector_height": 8})
    path = tmp_path / "rad" / "views.json"
    d = json.loads(path.read_text())
    edit(d)
    path.write_text(json.dumps(d))
    with pytest.raises(CtsplatError, match=rf"views\.json is malformed \({re.escape(needle)}.*\); re-render it"):
        ViewSet.load(path)


@pytest.mark.parametrize(("text", "needle"), [("[]", "holds a JSON array, not an object"),
                                                ("{", "is not valid JSON"), (b"\x89PNG\xff", "is not a text")])
def test_a_view_set_file_that_is_not_a_json_object_is_named(tmp_path, text, needle) -> None:
    path = tmp_path / "views.json"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(CtsplatError, match=rf"^view set {re.escape(str(path))} {needle}.*render it with"):
        ViewSet.load(path)


def test_a_json_object_of_another_format_is_named_as_the_view_set_it_is_not(tmp_path) -> None:
    path = tmp_path / "radiographs.json"  # the folder's other JSON, passed where views.json belongs
    path.write_text(json.dumps({"n_views": 4}))
    with pytest.raises(CtsplatError,
                       match=rf"^view set {re.escape(str(path))}: not a ctsplat view set \(format None\)"):
        ViewSet.load(path)


def test_a_volume_is_not_written_over_a_json_that_is_not_its_sidecar(tmp_path) -> None:
    # ct.nii.gz's JSON goes to ct.json, a name the user never gave: a BIDS sidecar or a config there is refused
    from ctsplat.volume import ingest

    vol = Volume(np.ones((8, 8, 8), np.float32), np.eye(4), {"volume_id": "a"})
    for content in ('{"Modality": "CT", "SeriesDescription": "bids"}', "not json", "[1, 2]"):
        (tmp_path / "ct.json").write_text(content)
        with pytest.raises(CtsplatError, match=r"ct\.json is not the sidecar of a volume, and writing ct\.nii\.gz"):
            save_volume(vol, tmp_path / "ct.nii.gz")
        with pytest.raises(CtsplatError, match=r"ct\.json is not the sidecar of a volume"):
            ingest(tmp_path / "no_such_source", tmp_path / "ct.nii.gz")  # refused before the source is read
        assert (tmp_path / "ct.json").read_text() == content and not (tmp_path / "ct.nii.gz").exists()
    (tmp_path / "ct.json").unlink()
    save_volume(vol, tmp_path / "ct.nii.gz")
    save_volume(Volume(np.zeros((4, 4, 4), np.float32), np.eye(4), {"volume_id": "b"}), tmp_path / "ct.nii.gz")
    assert load_volume(tmp_path / "ct.nii.gz").data.shape == (4, 4, 4)  # an earlier volume's sidecar is replaced


def test_a_volume_sidecar_that_does_not_belong_to_the_volume_is_refused(tmp_path) -> None:
    save_volume(Volume(np.ones((8, 8, 8), np.float32), np.eye(4), {"volume_id": "a"}), tmp_path / "a.nii.gz")
    save_volume(Volume(np.ones((6, 6, 6), np.float32), np.eye(4), {"volume_id": "b"}), tmp_path / "b.nii.gz")
    (tmp_path / "a.json").write_bytes((tmp_path / "b.json").read_bytes())
    with pytest.raises(CtsplatError, match=r"a\.json describes a \[6, 6, 6\] volume, but .*a\.nii\.gz is \[8, 8, 8\]"):
        load_volume(tmp_path / "a.nii.gz")
    (tmp_path / "a.json").write_text("{")
    with pytest.raises(CtsplatError, match=r"volume sidecar .*a\.json is not valid JSON .*ingest the volume again"):
        load_volume(tmp_path / "a.nii.gz")


def test_radiograph_folder_is_written_whole_or_not_at_all(tmp_path) -> None:
    """A file that cannot be written (here views.json blocked by a folder of that name) leaves nothing new behind,
    and a previous complete folder stays as it was."""
    from ctsplat.formats.viewset import write_radiographs
    from ctsplat.geometry import circular_orbit

    vs = ViewSet(ParallelCamera(8, 8, 1.0), circular_orbit(4, np.zeros(3), 20.0, split_fractions={"train": 1.0}),
                 "v1", np.zeros(3), {})
    out = tmp_path / "rad"
    (out / "views.json").mkdir(parents=True)
    with pytest.raises(CtsplatError, match="a folder of that name is in the way"):
        write_radiographs(out, np.zeros((4, 8, 8), np.float32), vs, {})
    assert sorted(p.name for p in out.iterdir()) == ["views.json"] and not list(tmp_path.glob(".rad.*"))
    (out / "views.json").rmdir()
    write_radiographs(out, np.ones((4, 8, 8), np.float32), vs, {})
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    (out / "radiographs.json").chmod(0o444)
    bad = ViewSet(ParallelCamera(8, 8, 1.0), vs.views[:2], "v1", np.zeros(3), {})
    with pytest.raises(CtsplatError, match="do not match"):
        write_radiographs(out, np.zeros((4, 8, 8), np.float32), bad, {})
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    p, back = load_radiographs(out)
    assert np.all(p == 1.0) and len(back) == 4


def test_radiographs_never_replace_files_of_someone_elses(tmp_path) -> None:
    """Writing radiographs into a folder replaces only an earlier projection's files: a folder holding a png/ of
    other pictures, a views.json or a same-named volume sidecar without an earlier radiographs.json, or any other
    file, is refused before any work, and nothing in it changes."""
    from ctsplat.formats.viewset import write_radiographs
    from ctsplat.geometry import circular_orbit

    vs = ViewSet(ParallelCamera(8, 8, 1.0), circular_orbit(4, np.zeros(3), 20.0, split_fractions={"train": 1.0}),
                 "v1", np.zeros(3), {})
    p = np.ones((4, 8, 8), np.float32)
    mine = tmp_path / "mine"
    (mine / "png").mkdir(parents=True)
    (mine / "png" / "holiday.png").write_bytes(b"mine")
    with pytest.raises(CtsplatError, match=r"mine holds png but no radiographs\.json of an earlier projection"):
        write_radiographs(mine, p, vs, {})
    save_volume(Volume(np.ones((8, 8, 8), np.float32), np.eye(4), {"volume_id": "r"}), tmp_path / "radiographs.nii.gz")
    sidecar = (tmp_path / "radiographs.json").read_bytes()
    with pytest.raises(CtsplatError, match=r"holds radiographs\.json but no radiographs\.json of an earlier"):
        write_radiographs(tmp_path, p, vs, {})  # the volume's own folder: its sidecar has the same name
    assert (tmp_path / "radiographs.json").read_bytes() == sidecar
    # an earlier projection is replaced, but not pictures someone put into its png/
    out = tmp_path / "rad"
    write_radiographs(out, p, vs, {})
    (out / "png" / "notes.png").write_bytes(b"mine")
    with pytest.raises(CtsplatError, match=r"png holds notes\.png, which a projection does not write"):
        write_radiographs(out, 2 * p, vs, {})
    (out / "png" / "notes.png").unlink()
    (out / "notes.txt").write_text("kept")  # nor mixed with other files (a training run's folder, someone's notes)
    with pytest.raises(CtsplatError, match=r"rad holds notes\.txt, which this step does not write, and its outputs "
                                           r"would be mixed with it"):
        write_radiographs(out, 2 * p, vs, {})
    assert np.all(load_radiographs(out)[0] == 1.0) and (out / "notes.txt").read_text() == "kept"
    (out / "notes.txt").unlink()
    write_radiographs(out, 2 * p, vs, {})
    assert np.all(load_radiographs(out)[0] == 2.0)
    other = tmp_path / "other"  # a folder of other files only
    other.mkdir()
    (other / "model.pt").write_bytes(b"x")
    with pytest.raises(CtsplatError, match=r"other already holds files that are not an earlier output"):
        write_radiographs(other, p, vs, {})
    assert sorted(f.name for f in other.iterdir()) == ["model.pt"]
    assert (mine / "png" / "holiday.png").read_bytes() == b"mine" and not list(tmp_path.glob(".*"))


def test_radiograph_folder_never_pairs_new_images_with_the_old_view_set(tmp_path, monkeypatch) -> None:
    """A crash between two of the final moves (simulated: the second rename fails) leaves a folder that
    load_radiographs refuses, not new line integrals beside the old views.json of the same shape."""
    import ctsplat.formats.viewset as viewset_mod
    from ctsplat.geometry import circular_orbit

    vs = ViewSet(ParallelCamera(8, 8, 1.0), circular_orbit(4, np.zeros(3), 20.0, split_fractions={"train": 1.0}),
                 "v1", np.zeros(3), {})
    out = tmp_path / "rad"
    viewset_mod.write_radiographs(out, np.ones((4, 8, 8), np.float32), vs, {})
    moved = []
    real_replace = os.replace

    def crash_on_second(src, dst):
        if Path(dst).parent == out:  # the final moves (the staging folder's own renames pass)
            if len(moved) == 1:
                raise OSError("simulated crash")
            moved.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(viewset_mod.os, "replace", crash_on_second)
    other = ViewSet(ParallelCamera(8, 8, 1.0), circular_orbit(4, np.zeros(3), 20.0, start_deg=45.0,
                                                              split_fractions={"train": 1.0}), "v2", np.zeros(3), {})
    with pytest.raises(OSError, match="simulated crash"):
        viewset_mod.write_radiographs(out, np.full((4, 8, 8), 2.0, np.float32), other, {})
    assert [Path(m).name for m in moved] == ["radiographs.json"]
    with pytest.raises(CtsplatError, match=r"views\.json does not exist"):
        load_radiographs(out)
    with pytest.raises(CtsplatError, match=r"line_integrals\.tif is a file; give the radiographs folder that holds"):
        load_radiographs(out / "line_integrals.tif")


@pytest.mark.parametrize(("intensity", "needle"), [
    ("attenuation", "'intensity' is 'attenuation', not an object"),
    ({"mu_scale_per_mm": "abc"}, "intensity.mu_scale_per_mm must be a finite number > 0 (1/mm per unit of the voxel "
                                 "values), got 'abc'"),
    ({"mu_scale_per_mm": None}, "got None"),
    ({"mu_scale_per_mm": -1.0}, "got -1.0"),
    ({"mu_scale_per_mm": float("nan")}, "got nan"),
])
def test_a_volume_sidecar_with_an_impossible_intensity_scale_is_refused_when_read(tmp_path, intensity, needle):
    """Every projection, seed and score multiplies by the scale: a NaN rendered NaN radiographs, -1 was recorded."""
    save_volume(Volume(np.ones((8, 8, 8), np.float32), np.eye(4), {"volume_id": "s"}), tmp_path / "v.nii.gz")
    meta = json.loads((tmp_path / "v.json").read_text())
    (tmp_path / "v.json").write_text(json.dumps({**meta, "intensity": intensity}))
    sidecar = re.escape(str(tmp_path / "v.json"))
    with pytest.raises(CtsplatError, match=rf"^volume sidecar {sidecar}: .*{re.escape(needle)}"):
        load_volume(tmp_path / "v.nii.gz")
    with pytest.raises(CtsplatError, match="ingest the volume again"):
        render_radiographs(tmp_path / "v.nii.gz", tmp_path / "rad", {"n_views": 2, "detector_width": 8,
                                                                      "detector_height": 8})
    assert not (tmp_path / "rad").exists()
