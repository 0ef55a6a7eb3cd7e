"""Boundary rules of the metrics, read-out, log statistics, claims verdicts and orbits, checked against hand-counted
values or an independent formula (never the function under test).

Each test pins one rule that an off-by-one, a flipped comparison or a dropped term would break unnoticed by the
other tests: R²-Gaussian's [0, 1] range check, the read-out's blur radius, ties in the claims verdicts, the
convergence velocity at repeated iterations, window edges, KDE support, paired groups, the equal-area Fibonacci
lattice, the support radius and the covering detector spacing.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy.ndimage import gaussian_filter

from ctsplat.analysis.claims import claims_table
from ctsplat.analysis.stats import (
    bounded_kde,
    convergence_velocity,
    mean_iters_per_s,
    paired_table,
    window_labels,
)
from ctsplat.evaluation.metrics import normalise_r2, psnr3d_r2
from ctsplat.evaluation.readout import choose_sharpening
from ctsplat.geometry.cameras import ParallelCamera
from ctsplat.geometry.orbits import covering_spacing_mm, fibonacci_directions, has_held_out_views, support_radius_mm
from ctsplat.utils import CtsplatError

# ------------------------------------------------------------------------------------------------ metrics


def test_r2_range_check_includes_one_as_the_upper_bound() -> None:
    """A reference in [0.2, 1.0] (max exactly 1) is already on R²-Gaussian's scale: no min-max rescaling."""
    rng = np.random.default_rng(3)
    ref = 0.2 + 0.8 * rng.random((6, 7, 8))
    ref.flat[0] = 1.0
    test = ref + 0.05 * rng.standard_normal(ref.shape)
    t, r = normalise_r2(test, ref)
    np.testing.assert_array_equal(r, ref)
    np.testing.assert_array_equal(t, test)
    expected = 10.0 * math.log10(1.0 / float(np.mean((test - ref) ** 2)))  # data range 1, raw values
    assert psnr3d_r2(test, ref) == pytest.approx(expected, rel=1e-12)


# ------------------------------------------------------------------------------------------------ read-out


class _RecordingValidator:
    """Duck-typed validator: records each scored volume and scores it by its mean (any number works here)."""

    def __init__(self) -> None:
        self.seen: list[np.ndarray] = []

    def score(self, volume: np.ndarray) -> float:
        self.seen.append(np.asarray(volume).copy())
        return float(np.mean(volume))


def test_choose_sharpening_blurs_with_the_requested_radius() -> None:
    """The candidate scored and returned is ``x + a (x - G_r * x)`` with the caller's ``r``, not the default 1."""
    rng = np.random.default_rng(5)
    x = rng.random((10, 11, 12)).astype(np.float32)
    validator = _RecordingValidator()
    vol, info = choose_sharpening(x, validator, amounts=[0.7], radius_voxels=2.5)
    blurred = gaussian_filter(x.astype(np.float64), 2.5, mode="reflect")
    expected = np.clip(x + 0.7 * (x - blurred), 0.0, None)
    np.testing.assert_allclose(vol, expected, atol=1e-5)
    np.testing.assert_allclose(validator.seen[0], expected, atol=1e-5)
    assert info["sharpen_amount"] == 0.7 and info["sharpen_radius_voxels"] == 2.5


# ------------------------------------------------------------------------------------------------ log statistics


def test_convergence_velocity_skips_repeated_iterations() -> None:
    """A step with no iteration gain is dropped, not counted as an infinite rate: median of 1/100 and 3/100."""
    it = [0.0, 100.0, 100.0, 200.0]
    v = [0.0, 1.0, 5.0, 8.0]  # kept steps: (1 - 0) / 100 and (8 - 5) / 100
    assert convergence_velocity(it, v, per_iters=1000) == pytest.approx(1000 * (0.01 + 0.03) / 2)


def test_mean_iters_per_s_is_none_without_a_positive_timestamp() -> None:
    """A log timed only at t = 0 has no speed (None), not 0/0."""
    log = pd.DataFrame({"iteration": [0, 10], "timestamp": [0.0, np.nan]})
    assert mean_iters_per_s(log) is None
    log2 = pd.DataFrame({"iteration": [0, 10, 30], "timestamp": [0.0, 2.0, 6.0]})
    assert mean_iters_per_s(log2) == pytest.approx(30 / 6.0)


def test_window_labels_put_an_interior_edge_in_the_later_window() -> None:
    """Windows are [a, b) except the last, [a, b]: 0..100 in two windows puts 50 in the second."""
    labels = window_labels([0.0, 49.0, 50.0, 99.0, 100.0], 2)
    assert list(labels) == ["0–50", "0–50", "50–100", "50–100", "50–100"]


def test_bounded_kde_grid_spans_three_scott_bandwidths() -> None:
    """Unbounded: the grid runs from min - 3h to max + 3h, h Scott's bandwidth ``std(ddof=1) n^(-1/5)``."""
    v = np.array([0.0, 1.0, 1.5, 4.0, 7.0])
    h = float(np.std(v, ddof=1)) * v.size ** (-1 / 5)
    x, dens = bounded_kde(v, n_grid=101)
    assert x[0] == pytest.approx(v.min() - 3 * h, rel=1e-12)
    assert x[-1] == pytest.approx(v.max() + 3 * h, rel=1e-12)
    # the plain Gaussian KDE written out
    ref = np.exp(-((x[:, None] - v[None]) ** 2) / (2 * h * h)).sum(axis=1) / (v.size * h * math.sqrt(2 * math.pi))
    np.testing.assert_allclose(dens, ref, rtol=1e-10)


def test_paired_table_drops_groups_with_one_finite_value() -> None:
    """Only groups holding at least two finite values of the axis are pairs (hand-built summary)."""
    s = pd.DataFrame({"volume": "v", "init": "fbp", "seed": [0, 0, 1, 2, 2],
                      "compositor": ["radiative", "alpha", "radiative", "radiative", "alpha"],
                      "test_psnr3d": [30.0, 27.0, 31.0, 29.0, np.nan]})
    wide = paired_table(s, "compositor", "test_psnr3d")
    assert len(wide) == 1
    assert wide.index.get_level_values("seed").tolist() == [0]
    assert float(wide["radiative"].iloc[0] - wide["alpha"].iloc[0]) == pytest.approx(3.0)


# ------------------------------------------------------------------------------------------------ claims


def _compositor_pairs(diffs: list[float]) -> pd.DataFrame:
    """Radiative and alpha runs, one pair per seed, radiative minus alpha = ``diffs[seed]`` (dB)."""
    rows = []
    for seed, d in enumerate(diffs):
        for comp, score in (("radiative", 30.0 + d), ("alpha", 30.0)):
            rows.append({"volume": "v", "init": "fbp", "compositor": comp, "mip": "on", "poses": "gt", "views": 8,
                         "seed": seed, "test_psnr3d": score, "test_ssim3d": score / 40})
    return pd.DataFrame(rows)


def _alpha_row(table: pd.DataFrame) -> pd.Series:
    hits = table[table["comparison"].str.startswith("rectified radiative vs alpha")]
    assert len(hits) == 1
    return hits.iloc[0]


@pytest.mark.parametrize(("diffs", "result", "n_as_expected"), [
    ([0.0, 1.0], "mixed", 1),  # a tie is not "higher"
    ([0.0, 0.0], "fails", 0),
    ([1.0, -1.0, -1.0], "mixed", 1),  # one win of three is mixed, not a failure
    ([2.0, 1.0, 0.5], "holds", 3),
])
def test_paired_claim_verdict_counts_only_strict_wins(diffs: list[float], result: str, n_as_expected: int) -> None:
    """``holds`` needs every pair strictly higher, ``fails`` none; ties count against the claim."""
    row = _alpha_row(claims_table(_compositor_pairs(diffs)))
    assert (row["result"], row["n_pairs"], row["n_as_expected"]) == (result, len(diffs), n_as_expected)
    assert row["median_difference_psnr3d_db"] == pytest.approx(float(np.median(diffs)))
    lost = sum(d <= 0 for d in diffs)
    if lost:
        assert row["note"].startswith(f"alpha is as good or better in {lost} of {len(diffs)} pairs")


def _headline(rows: list[dict[str, object]]) -> pd.DataFrame:
    base = {"volume": "v", "init": "fbp", "compositor": "radiative", "mip": "on", "poses": "gt", "views": 8,
            "seed": 0, "best_baseline": "asd_pocs", "best_baseline_test_psnr3d": 28.0,
            "best_baseline_test_ssim3d": 0.7, "test_ssim3d": 0.8}
    return pd.DataFrame([{**base, **r} for r in rows])


def _headline_row(table: pd.DataFrame) -> pd.Series:
    hits = table[table["comparison"].str.contains("strongest classical")]
    assert len(hits) == 1
    return hits.iloc[0]


def test_headline_claim_counts_only_runs_at_the_true_poses() -> None:
    """A radiative run at SfM poses is not a headline pair: one pair (gt), +2 dB, holds."""
    s = _headline([{"test_psnr3d": 30.0}, {"poses": "colmap", "test_psnr3d": 25.0}])
    row = _headline_row(claims_table(s))
    assert (row["result"], row["n_pairs"], row["median_difference_psnr3d_db"]) == ("holds", 1, pytest.approx(2.0))


def test_headline_claim_prefers_mip_on_whatever_the_row_order() -> None:
    """With both mip settings present the headline compares mip on, even when a mip-off row comes first."""
    s = _headline([{"mip": "off", "test_psnr3d": 29.0}, {"mip": "on", "test_psnr3d": 31.0}])
    row = _headline_row(claims_table(s))
    assert "mip on" in row["comparison"]
    assert (row["n_pairs"], row["median_difference_psnr3d_db"]) == (1, pytest.approx(3.0))


def test_headline_tie_fails_and_names_the_baseline() -> None:
    """A Gaussian run only equal to the baseline is not higher: the claim fails and the note names the baseline."""
    row = _headline_row(claims_table(_headline([{"test_psnr3d": 28.0}])))
    assert (row["result"], row["n_as_expected"]) == ("fails", 0)
    assert row["note"].startswith("asd_pocs is level at 8 views (v)")  # not "-0.00 dB higher"


def test_headline_note_names_the_worst_loss() -> None:
    """Of two lost pairs the note names the one the baseline wins by most (2.00 dB, asd_pocs), not 0.50 dB."""
    s = _headline([{"seed": 0, "test_psnr3d": 27.5, "best_baseline": "sart"},
                   {"seed": 1, "test_psnr3d": 26.0, "best_baseline": "asd_pocs"}])
    row = _headline_row(claims_table(s))
    assert (row["result"], row["n_pairs"]) == ("fails", 2)
    assert row["note"].startswith("asd_pocs is 2.00 dB higher at 8 views (v)")


# ------------------------------------------------------------------------------------------------ orbits


def test_fibonacci_directions_are_equal_area_midpoints_and_golden_angle_apart() -> None:
    """``sin e`` at the midpoints of n equal bins of [sin e_min, sin e_max]; azimuth step 360/φ² (golden angle)."""
    az, el = fibonacci_directions(4, (-30.0, 30.0), azimuth_offset_deg=10.0)
    np.testing.assert_allclose(np.sin(np.radians(el)), [-0.375, -0.125, 0.125, 0.375], atol=1e-12)
    phi = (1 + math.sqrt(5)) / 2
    golden = 360.0 / phi**2  # 137.5077...°
    np.testing.assert_allclose(az, np.mod(10.0 + golden * np.arange(4), 360.0), atol=1e-9)


def test_has_held_out_views_zero_count_means_none() -> None:
    """An explicit count of 0 renders no views whatever the fraction; no count falls back to the fraction."""
    cfg = {"orbit": "circular", "n_val": 0, "n_test": None, "split": {"val": 0.15, "test": 0.15}}
    assert has_held_out_views(cfg, "val") is False
    assert has_held_out_views(cfg, "test") is True
    assert has_held_out_views({**cfg, "split": {"test": 0.0}}, "test") is False


def test_support_radius_adds_one_voxel_diagonal() -> None:
    """One voxel at index (1, 1, 1), 2 mm voxels at the origin: centre distance √12 plus the voxel diagonal √12."""
    data = np.zeros((3, 3, 3))
    data[1, 1, 1] = 1.0
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    assert support_radius_mm(data, affine, np.zeros(3)) == pytest.approx(2 * math.sqrt(12.0))


def test_covering_spacing_leaves_the_margin_inside_the_edge() -> None:
    """Parallel 10x20 px detector, farthest point 4 mm (x) and 6 mm (y) off axis, 1 px margin: max(4/4, 6/9)."""
    cam = ParallelCamera(10, 20, 1.0)
    pts = np.array([[4.0, 0.0, 0.0], [-2.0, 6.0, 1.0], [0.0, -1.0, 0.0]])
    spacing = covering_spacing_mm(cam, np.eye(3)[None], np.zeros((1, 3)), pts, margin_px=1.0)
    assert spacing == pytest.approx(max(4.0 / (5.0 - 1.0), 6.0 / (10.0 - 1.0)))
    # at that spacing the farthest point sits exactly margin_px inside the detector edge (u = W - 1)
    assert 4.0 / spacing + cam.width / 2 == pytest.approx(cam.width - 1.0)


def test_paired_table_keeps_runs_without_an_optional_axis_and_refuses_two_runs_of_one_cell() -> None:
    """A feature axis only some runs have would drop the others from the pairs (pandas drops NaN index rows);
    two runs of one cell (two experiments in one summary) would be averaged into one pair."""
    s = _compositor_pairs([1.0, 2.0])
    s["augment"] = [np.nan, np.nan, "on", "on"]  # seed 0's runs predate the axis
    wide = paired_table(s, "compositor", "test_psnr3d")
    assert len(wide) == 2 and sorted(wide.index.get_level_values("augment")) == ["(absent)", "on"]
    row = _alpha_row(claims_table(s))
    assert (row["result"], row["n_pairs"]) == ("holds", 2)
    twice = pd.concat([_compositor_pairs([1.0]), _compositor_pairs([-5.0])]).assign(run_dir=[f"r{i}" for i in range(4)])
    with pytest.raises(CtsplatError, match=r"r0 and r2 are runs of one grid cell \(volume=v, init=fbp, "
                                           r"compositor=radiative"):
        paired_table(twice, "compositor", "test_psnr3d")


def test_claims_name_trained_runs_without_a_test_metric() -> None:
    """A run whose evaluation failed leaves the pairs it belongs to; the claim's note says so."""
    s = _compositor_pairs([1.0, 2.0, 0.5]).assign(run_dir=[f"r{i}" for i in range(6)], status="trained")
    s.loc[2, "test_psnr3d"] = np.nan  # seed 1's radiative run
    row = _alpha_row(claims_table(s))
    assert (row["result"], row["n_pairs"]) == ("holds", 2)
    assert "1 trained run(s) without test_psnr3d left out (e.g. r2)" in row["note"]
    assert claims_table(s)["n_as_expected"].dtype == "Int64"
