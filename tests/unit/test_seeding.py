"""Seeding strategies: candidate voxels, jitter, mass conservation, uniform boxes, SfM points."""

from __future__ import annotations

import numpy as np
import pytest

from ctsplat.training import seeding
from ctsplat.utils import CtsplatError


def _affine(spacing=(1.5, 2.0, 2.5), origin=(-10.0, 4.0, 7.0)) -> np.ndarray:
    a = np.eye(4)
    a[:3, :3] = np.diag(spacing)
    a[:3, 3] = origin
    return a


def _blob(shape=(12, 10, 9), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.random(shape).astype(np.float32) * (rng.random(shape) > 0.4)


def test_volume_seed_picks_top_fraction_and_stays_in_voxel() -> None:
    data = _blob()
    aff = _affine()
    seed = seeding.seed_from_grid(data, aff, 200, np.random.default_rng(1), uses_reference_volume=True,
                                  strategy="volume")
    assert len(seed) == 200 and seed.uses_reference_volume
    idx = (seed.means - aff[:3, 3]) / np.diag(aff)[:3]
    vox = np.round(idx).astype(int)
    assert np.all(np.abs(idx - vox) <= 0.5 + 1e-5)
    thr = np.quantile(data, 0.7)
    vals = data[vox[:, 0], vox[:, 1], vox[:, 2]]
    assert np.all(vals >= thr) and np.all(vals > 0)
    # 0.75 voxel isotropic scale, identity rotation implied; density proportional to the voxel value
    assert np.allclose(seed.scales, 0.75 * np.mean([1.5, 2.0, 2.5]))
    ratio = seed.densities / vals
    assert np.allclose(ratio, ratio[0], rtol=1e-5)


def test_volume_seed_conserves_mass_when_each_candidate_drawn_once() -> None:
    data = _blob(seed=3)
    aff = _affine()
    thr = np.quantile(data, 0.7)
    cand = (data >= thr) & (data > 0)
    m = int(cand.sum())
    seed = seeding.seed_from_grid(data, aff, m, np.random.default_rng(0), uses_reference_volume=False,
                                  strategy="fbp")
    s = seed.scales[:, 0].astype(float)
    mass = float(np.sum(seed.densities * (2 * np.pi) ** 1.5 * s**3))
    ref = float(data[cand].sum()) * 1.5 * 2.0 * 2.5
    assert mass == pytest.approx(ref, rel=1e-5)


def test_volume_seed_deterministic_and_errors() -> None:
    data = _blob()
    a = seeding.seed_from_grid(data, _affine(), 50, np.random.default_rng(7), uses_reference_volume=True,
                               strategy="volume")
    b = seeding.seed_from_grid(data, _affine(), 50, np.random.default_rng(7), uses_reference_volume=True,
                               strategy="volume")
    assert np.array_equal(a.means, b.means) and np.array_equal(a.densities, b.densities)
    with pytest.raises(CtsplatError, match="no positive voxels"):
        seeding.seed_from_grid(-np.ones((4, 4, 4)), _affine(), 5, np.random.default_rng(0),
                               uses_reference_volume=True, strategy="volume")
    with pytest.raises(CtsplatError, match="n_init"):
        seeding.seed_from_grid(data, _affine(), 0, np.random.default_rng(0), uses_reference_volume=True,
                               strategy="volume")


def test_grid_bounds_cover_voxel_edges() -> None:
    lo, hi = seeding.grid_bounds_mm((12, 10, 9), _affine())
    assert np.allclose(lo, [-10 - 0.75, 4 - 1.0, 7 - 1.25])
    assert np.allclose(hi, [-10 + 11.5 * 1.5, 4 + 9.5 * 2.0, 7 + 8.5 * 2.5])


def test_uniform_seed_in_box() -> None:
    lo, hi = np.array([-5.0, 0.0, 2.0]), np.array([5.0, 8.0, 4.0])
    seed = seeding.seed_uniform(lo, hi, 1000, np.random.default_rng(0), density=0.02)
    assert len(seed) == 1000 and not seed.uses_reference_volume
    assert np.all(seed.means >= lo) and np.all(seed.means <= hi)
    # roughly uniform: each half of the box gets about half
    assert 400 < int((seed.means[:, 0] < 0).sum()) < 600
    assert np.allclose(seed.densities, 0.02)
    assert np.allclose(seed.scales, 0.5 * (160.0 / 1000) ** (1 / 3))
    with pytest.raises(CtsplatError):
        seeding.seed_uniform(hi, lo, 10, np.random.default_rng(0))


def test_points_seed_drops_outside_and_fills() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(30, 3))
    outside = np.array([[5.0, 0, 0], [0, -7.0, 0]])
    lo, hi = -np.ones(3), np.ones(3)
    seed = seeding.seed_from_points(np.vstack([pts, outside]), lo, hi, 100, np.random.default_rng(1),
                                    fill_fraction=0.5)
    assert len(seed) == 100 and seed.strategy == "sfm"
    assert np.all(np.abs(seed.means) <= 1.0 + 1e-6)
    # all 30 inside points are kept (30 <= 50 allowed), in order
    assert np.allclose(seed.means[:30], pts, atol=1e-6)
    # too many points: subsampled to n - fill
    many = rng.uniform(-1, 1, size=(500, 3))
    seed2 = seeding.seed_from_points(many, lo, hi, 100, np.random.default_rng(1), fill_fraction=0.25)
    assert len(seed2) == 100
    kept = seed2.means[:75].astype(float)
    d = np.abs(kept[:, None, :] - many[None]).max(-1).min(1)
    assert np.all(d < 1e-6)


def test_points_seed_scale_is_the_mean_distance_to_three_other_points() -> None:
    """Each kept point's scale against a brute-force mean over its 3 nearest *other* points (3DGS's rule)."""
    pts = np.array([[0.0, 0, 0], [4, 0, 0], [0, 5, 0], [0, 0, 6], [7, 7, 0], [-5, 3, 4]])
    lo, hi = -10 * np.ones(3), 10 * np.ones(3)
    seed = seeding.seed_from_points(pts, lo, hi, len(pts), np.random.default_rng(0), fill_fraction=0.0)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    want = np.sort(d, axis=1)[:, :3].mean(1)
    d_fill = (20.0 ** 3 / len(pts)) ** (1 / 3)
    assert np.all((want > 0.25 * d_fill) & (want < d_fill))  # the clip does not act on this set
    np.testing.assert_allclose(seed.scales, np.repeat(want[:, None], 3, axis=1), rtol=1e-6)
