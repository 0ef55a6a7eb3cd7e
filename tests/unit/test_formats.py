"""On-disk formats checked against independent references: the 16-bit transmission PNG mapping and the statistics
of a radiograph folder (ctsplat.formats.viewset), and the geometry, metric range and HU guard of a volume
(ctsplat.formats.volume), with expected values written out by hand or taken from nibabel and numpy."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import nibabel as nib
import numpy as np
import pytest

from ctsplat.formats.viewset import View, ViewSet, transmission_png16, write_radiographs
from ctsplat.formats.volume import Volume, check_attenuation, load_volume, save_volume
from ctsplat.geometry.cameras import ParallelCamera, pose_from_angles
from ctsplat.utils import CtsplatError


def _png16_reference(p: float) -> int:
    """The documented mapping, written out: transmission exp(-p) clipped to [0, 1], times 65535, rounded."""
    return int(round(min(max(math.exp(-p), 0.0), 1.0) * 65535.0))


# ------------------------------------------------------------------------------------ transmission PNG values
def test_transmission_png16_rounds_to_nearest_and_saturates() -> None:
    """exp(-p) maps to round(exp(-p)·65535): half transmission is 32768, p <= 0 saturates at 65535, large p at 0."""
    # fractional parts above one half: rounding goes up where truncation (floor) would go down
    ups = [-math.log(t / 65535.0) for t in (1000.7, 12345.6, 40000.9)]
    p = np.array([0.0, -math.log(0.5), -1.0, -25.0, 50.0, math.inf, *ups])
    got = transmission_png16(p)
    assert got.dtype == np.uint16 and got.shape == p.shape
    assert got.tolist() == [65535, 32768, 65535, 65535, 0, 0, 1001, 12346, 40001]
    assert got.tolist() == [_png16_reference(float(v)) for v in p]
    grid = np.linspace(0.0, 3.0, 12).reshape(3, 4)  # shape kept, every value by the written-out formula
    out = transmission_png16(grid)
    assert out.shape == (3, 4)
    assert out.ravel().tolist() == [_png16_reference(float(v)) for v in grid.ravel()]


# ------------------------------------------------------------------------------------ radiograph folder stats
def _view_set(n_views: int, width: int, height: int) -> ViewSet:
    views = []
    for i in range(n_views):
        R, t = pose_from_angles(90.0 * i, 0.0, [0.0, 0.0, 0.0], 100.0)
        views.append(View(i, R, t, 90.0 * i, 0.0, "train"))
    return ViewSet(ParallelCamera(width, height, 1.0), views, "vol-x", np.zeros(3), {})


def test_radiographs_json_records_stats_of_the_written_line_integrals(tmp_path: Path) -> None:
    """radiographs.json min/max/mean equal numpy's on the written TIFF, and the PNGs hold round(exp(-p)·65535)."""
    import tifffile

    rng = np.random.default_rng(3)
    p = rng.gamma(2.0, 0.6, size=(3, 5, 4)).astype(np.float32)  # skewed: mean well away from min and max
    p[0, 0, 0] = 0.0
    out = tmp_path / "rad"
    write_radiographs(out, p, _view_set(3, 4, 5), {"seed": 7})
    written = np.asarray(tifffile.imread(out / "line_integrals.tif"), np.float64)
    np.testing.assert_array_equal(written, p.astype(np.float64))
    meta = json.loads((out / "radiographs.json").read_text())
    stats = meta["line_integral_stats"]
    assert set(stats) == {"min", "max", "mean"}
    assert stats["min"] == 0.0
    assert stats["max"] == pytest.approx(float(written.max()), rel=1e-7)
    assert stats["mean"] == pytest.approx(float(written.sum() / written.size), rel=1e-6)
    assert abs(stats["mean"] - stats["max"]) > 0.5  # the three numbers are distinct for this data
    assert meta["seed"] == 7 and meta["n_views"] == 3
    for i in range(3):
        png = iio.imread(out / "png" / f"view_{i:04d}.png")
        assert png.dtype == np.uint16
        assert png.ravel().tolist() == [_png16_reference(float(v)) for v in written[i].ravel()]


# ------------------------------------------------------------------------------------------ volume geometry
def test_extent_and_spacing_of_an_anisotropic_volume(tmp_path: Path) -> None:
    """Spacing (1, 2, 3) mm on a (4, 5, 6) grid covers (4, 10, 18) mm, also with permuted axes and after a save."""
    data = np.zeros((4, 5, 6), np.float32)
    aff = np.diag([1.0, 2.0, 3.0, 1.0])
    aff[:3, 3] = [-5.0, 7.0, 11.0]
    vol = Volume(data, aff, {})
    np.testing.assert_allclose(vol.spacing_mm, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(vol.spacing_mm, nib.affines.voxel_sizes(aff))
    np.testing.assert_allclose(vol.extent_mm(), [4 * 1.0, 5 * 2.0, 6 * 3.0])
    # voxel axes i, j, k along world z, x, y: spacing is per voxel axis (column norms), not per world axis
    perm = np.zeros((4, 4))
    perm[2, 0], perm[0, 1], perm[1, 2], perm[3, 3] = 1.0, 2.0, 3.0, 1.0
    vol_p = Volume(data, perm, {})
    np.testing.assert_allclose(vol_p.spacing_mm, nib.affines.voxel_sizes(perm))
    np.testing.assert_allclose(vol_p.extent_mm(), [4.0, 10.0, 18.0])
    save_volume(vol, tmp_path / "a.nii.gz")
    back = load_volume(tmp_path / "a.nii.gz")
    zooms = nib.load(str(tmp_path / "a.nii.gz")).header.get_zooms()
    np.testing.assert_allclose(back.extent_mm(), np.asarray(back.shape) * np.asarray(zooms))
    np.testing.assert_allclose(back.extent_mm(), [4.0, 10.0, 18.0])


@pytest.mark.parametrize(
    ("lo", "hi", "expected"),
    [(-0.5, 2.0, 2.5), (-3.0, -1.0, 2.0), (0.25, 3.0, 2.75), (0.0, 1.0, 1.0), (0.1, 0.6, 1.0), (-2.0, -2.0, 1.0)],
)
def test_metric_range_without_intensity_metadata(lo: float, hi: float, expected: float) -> None:
    """Without intensity metadata the range is max - min, 1 for data inside [0, 1] and 1 for a constant volume."""
    data = np.full((3, 3, 3), (lo + hi) / 2, np.float32)
    data[0, 0, 0], data[2, 2, 2] = lo, hi
    assert Volume(data, np.eye(4), {}).metric_range == pytest.approx(expected)
    assert Volume(data, np.eye(4), {"volume_id": "x"}).metric_range == pytest.approx(expected)


def test_metric_range_with_intensity_metadata_ignores_the_data() -> None:
    """A normalised intensity kind gives 1; μ in 1/mm gives μ_water·(1 + hu_max/1000)."""
    data = np.array([-4.0, 0.0, 9.0], np.float32).reshape(1, 1, 3)
    assert Volume(data, np.eye(4), {"intensity": {"kind": "window"}}).metric_range == 1.0
    mu = {"kind": "attenuation_per_mm", "mu_water_per_mm": 0.02, "hu_max": 3000.0}
    assert Volume(data, np.eye(4), {"intensity": mu}).metric_range == pytest.approx(0.02 * 4.0)


# ------------------------------------------------------------------------------------------------ HU guard
def _with_negative_fraction(fraction: float) -> Volume:
    """1000 voxels whose negative values make up ``fraction`` of the absolute sum (positives 1, negatives -1)."""
    n_neg = round(1000 * fraction)
    data = np.ones(1000, np.float32)
    data[:n_neg] = -1.0
    meta = {"intensity": {"kind": "attenuation_normalised"}}
    return Volume(data.reshape(10, 10, 10), np.eye(4), meta)


def test_hu_guard_threshold_is_one_percent_of_absolute_mass() -> None:
    """Negative mass of 2 % (or 1.1 %) of the absolute sum is refused; 0.5 % and exactly 1 % pass."""
    for fraction in (0.02, 0.011):
        vol = _with_negative_fraction(fraction)
        data = vol.data.astype(np.float64)
        assert -data[data < 0].sum() / np.abs(data).sum() == pytest.approx(fraction)
        with pytest.raises(CtsplatError, match="looks like HU"):
            check_attenuation(vol, "v.nii.gz")
    for fraction in (0.005, 0.01):
        check_attenuation(_with_negative_fraction(fraction), "v.nii.gz")
    with pytest.raises(CtsplatError, match="raw HU"):
        check_attenuation(Volume(np.ones((2, 2, 2), np.float32), np.eye(4), {"intensity": {"kind": "hu"}}), "h")
    with pytest.raises(CtsplatError, match="no v.json beside it"):
        check_attenuation(Volume(np.ones((2, 2, 2), np.float32), np.eye(4), {}), "v.nii.gz")
