"""Rules of ingest, config checks and the 3D filter that a one-line slip would break unnoticed by the other tests.

Each test checks the library against an independent reference, never against itself:

- :func:`ctsplat.volume.resample_stack`: the Gaussian anti-aliasing filter (std ``(h - d) / 2``, truncated at 4 std)
  against ``scipy.ndimage.gaussian_filter1d`` followed by ``scipy.ndimage.map_coordinates`` (linear); the native
  slice spacing is the *median* slice gap, values between non-uniform slices follow ``numpy.interp``; on the real
  ``ct0051_head`` series (one odd gap at the end) the native spacing is the median gap and the values match pydicom.
- :func:`ctsplat.volume.check_preprocessing`: a window of width 0 is refused.
- :func:`ctsplat.volume.ingest` of raw (non-HU) values: ``attenuation`` is exactly ``(x - min) / (max - min)``, and a
  body mask with ``intensity: hu`` sets the outside to the data minimum.
- :func:`ctsplat.config.check_split` tolerance (1e-6), the SfM percentile order (equal is refused) and
  :func:`ctsplat.config.on_workflow_device`.
- :func:`ctsplat.splat.render.compute_3d_filter`: ``v = 0.2 T²`` with ``T`` the finest sampling interval
  ``z / max(f_x, f_y)`` and a Gaussian inside the image (near its edge) counted as seen.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy import ndimage

from ctsplat.config import check_split, on_workflow_device, prepare_config
from ctsplat.formats.sources import SliceStack
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import compute_3d_filter
from ctsplat.utils import CtsplatError
from ctsplat.volume import PREPROCESSING_DEFAULTS, check_preprocessing, ingest, resample_stack

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
HEAD = DATA / "ct0051_head"


def _axial_stack(data: np.ndarray, positions: np.ndarray, spacing: tuple[float, float] = (1.0, 1.0)) -> SliceStack:
    """An axial RAS-aligned stack: row_dir +x, col_dir +y, slices at z = ``positions``."""
    origins = np.zeros((len(positions), 3))
    origins[:, 2] = positions
    return SliceStack(data=np.asarray(data, np.float32), row_dir=np.array([1.0, 0.0, 0.0]),
                      col_dir=np.array([0.0, 1.0, 0.0]), spacing_ij=spacing, origins=origins)


# ------------------------------------------------------------------------------------------ resampling


def test_downsampling_filter_matches_scipy_gaussian_then_linear() -> None:
    """4x downsampling = Gaussian of std (h - d)/2 truncated at 4 std, then linear interpolation (scipy)."""
    rng = np.random.default_rng(3)
    n = 64
    profile = rng.normal(size=n)
    data = np.broadcast_to(profile[:, None, None], (n, 8, 8)).copy()
    out, affine, _ = resample_stack(_axial_stack(data, np.arange(8.0)), voxel_size_mm=4.0)
    assert out.shape == (16, 2, 2)
    np.testing.assert_allclose(np.diag(affine)[:3], 4.0)
    # output centres in source index units (source pixel i sits at x = i mm)
    x_out = affine[0, 3] + 4.0 * np.arange(16)
    sigma = (4.0 - 1.0) / 2  # 1.5 samples; 4 sigma = 6 samples, the radius scipy uses with truncate=4
    smooth = ndimage.gaussian_filter1d(profile, sigma, truncate=4.0, mode="nearest")
    ref = ndimage.map_coordinates(smooth, [x_out], order=1)
    interior = (x_out >= 7) & (x_out <= n - 8)  # the 6-sample window fully inside: no border renormalisation
    assert interior.sum() >= 10
    np.testing.assert_allclose(out[interior, 0, 0], ref[interior], rtol=0, atol=1e-5)
    np.testing.assert_allclose(out[:, 0, 0], out[:, 1, 1], atol=1e-6)  # constant along the other axes


def test_native_spacing_uses_median_gap_and_interpolates_between_true_positions() -> None:
    """Native mode: slice spacing = median gap, values between non-uniform slices as numpy.interp."""
    positions = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 10.0])  # gaps 1,1,1,1,6: median 1, mean 2
    slice_values = np.array([5.0, -3.0, 2.0, 7.0, 1.0, 13.0])
    data = np.broadcast_to(slice_values[None, None, :], (4, 3, 6)).copy()
    out, affine, info = resample_stack(_axial_stack(data, positions))
    assert out.shape == (4, 3, 11)
    assert affine[2, 2] == pytest.approx(1.0) and affine[2, 3] == pytest.approx(0.0)
    assert info["source_spacing_mm"][2] == pytest.approx(1.0)
    z = affine[2, 3] + affine[2, 2] * np.arange(out.shape[2])
    np.testing.assert_allclose(out[1, 1, :], np.interp(z, positions, slice_values), rtol=0, atol=1e-5)


@pytest.mark.skipif(not HEAD.is_dir(), reason="real data ../shared/data/ct0051_head absent (fresh clone)")
def test_real_head_series_native_spacing_and_values_match_pydicom() -> None:
    """ct0051_head: HU = stored * slope + intercept (pydicom), LPS->RAS origins, native z spacing = median gap."""
    pydicom = pytest.importorskip("pydicom")
    from ctsplat.formats.sources import read_source

    stack = read_source(HEAD)
    dss = [pydicom.dcmread(p) for p in sorted(HEAD.glob("*.dcm"))]
    lps = np.array([[float(x) for x in ds.ImagePositionPatient] for ds in dss])
    ras = lps * np.array([-1.0, -1.0, 1.0])
    normal = stack.normal
    order = np.argsort(ras @ normal)
    np.testing.assert_allclose(stack.origins, ras[order], atol=1e-4)
    iop = np.array([float(x) for x in dss[0].ImageOrientationPatient])
    np.testing.assert_allclose(stack.row_dir, iop[:3] * [-1, -1, 1], atol=1e-6)
    np.testing.assert_allclose(stack.col_dir, iop[3:] * [-1, -1, 1], atol=1e-6)
    for k in (0, len(order) // 2, len(order) - 1):
        ds = dss[order[k]]
        hu = ds.pixel_array.astype(np.float64) * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        np.testing.assert_allclose(stack.data[:, :, k], hu.T, atol=1e-3)  # data[i, j] = pixel (row j, column i)
    gaps = np.diff(np.sort(ras @ normal))
    assert np.ptp(gaps) > 0.1  # the series has a non-uniform gap (the rule below matters)
    small = SliceStack(data=stack.data[:16, :16, :].copy(), row_dir=stack.row_dir, col_dir=stack.col_dir,
                       spacing_ij=stack.spacing_ij, origins=stack.origins, units=stack.units)
    out, affine, _ = resample_stack(small)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    assert sorted(spacing)[-1] == pytest.approx(float(np.median(gaps)), abs=1e-4)
    assert np.prod(out.shape) == 16 * 16 * (int(round((gaps.sum()) / np.median(gaps))) + 1)


def test_window_of_zero_width_is_refused() -> None:
    """A window [level, 0] is an error (the width divides the HU values)."""
    cfg = {**PREPROCESSING_DEFAULTS, "intensity": "window", "window": [40.0, 0.0]}
    with pytest.raises(CtsplatError, match="width > 0"):
        check_preprocessing(cfg)
    check_preprocessing({**cfg, "window": [40.0, 1.0]})


def _raw_ball(n: int = 20) -> np.ndarray:
    """Raw-unit volume: noisy background 10..20 with a bright ball (500) in the middle."""
    rng = np.random.default_rng(7)
    x = np.stack(np.meshgrid(*[np.arange(n) - (n - 1) / 2] * 3, indexing="ij"), -1)
    data = rng.uniform(10.0, 20.0, (n, n, n))
    data[np.linalg.norm(x, axis=-1) < n * 0.3] = 500.0
    return data


def test_raw_values_attenuation_is_exact_min_max_normalisation(tmp_path: Path) -> None:
    """Raw units, native grid (identity resampling): attenuation = (x - min) / (max - min)."""
    data = _raw_ball()
    stack = dataclasses.replace(_axial_stack(data, np.arange(20.0)), units="raw")
    vol = ingest(stack, tmp_path / "v.nii.gz", {"grid": None, "voxel_size_mm": None})
    assert vol.meta["intensity"]["kind"] == "minmax_normalised"
    ref = (data - data.min()) / (data.max() - data.min())
    np.testing.assert_allclose(vol.data, ref, rtol=0, atol=1e-6)


def test_raw_values_masked_outside_take_the_data_minimum(tmp_path: Path) -> None:
    """Raw units, intensity hu, otsu mask: voxels outside the body become the smallest value, inside unchanged."""
    data = _raw_ball()
    stack = dataclasses.replace(_axial_stack(data, np.arange(20.0)), units="raw")
    vol = ingest(stack, tmp_path / "v.nii.gz", {"grid": None, "voxel_size_mm": None, "intensity": "hu",
                                                 "mask": "otsu"})
    ball = data == 500.0
    np.testing.assert_allclose(vol.data[ball], 500.0)
    np.testing.assert_allclose(vol.data[~ball], np.float32(data.min()), rtol=0, atol=1e-5)


# ------------------------------------------------------------------------------------------ config


def test_split_fractions_off_by_more_than_1e6_are_refused() -> None:
    """Fractions summing to 1.005 fail; 1 + 5e-7 passes (tolerance 1e-6)."""
    with pytest.raises(CtsplatError, match="fractions must sum to 1"):
        check_split({"train": 0.7, "val": 0.15, "test": 0.155}, "radiographs.c.split")
    check_split({"train": 0.7, "val": 0.15, "test": 0.1500005}, "radiographs.c.split")


def test_equal_sfm_percentiles_are_refused() -> None:
    """percentile_low == percentile_high leaves every image blank: refused at parse time."""
    with pytest.raises(CtsplatError, match="percentile_low: 50 is not below percentile_high"):
        prepare_config({"sfm": {"settings": {"percentile_low": 50.0, "percentile_high": 50.0}}})


def test_on_workflow_device_keeps_the_users_device_only() -> None:
    """The workflow's device replaces a section's default unless the user set that section's device."""
    settings = {"device": "cpu", "k": 1}
    assert on_workflow_device(settings, None, "cuda") == {"device": "cuda", "k": 1}
    assert on_workflow_device(settings, {"k": 2}, "cuda") == {"device": "cuda", "k": 1}
    assert on_workflow_device(settings, {"device": "cpu"}, "cuda") == {"device": "cpu", "k": 1}
    assert settings == {"device": "cpu", "k": 1}  # not modified


# ------------------------------------------------------------------------------------------ 3D filter


def _cone(fx: float, fy: float, w: int = 100, h: int = 80) -> SimpleNamespace:
    """A duck-typed cone camera with explicit focal lengths (px)."""
    return SimpleNamespace(model="cone", width=w, height=h, pitch_mm=1.0, dsd_mm=fx, fx=fx, fy=fy)


def test_3d_filter_uses_the_finest_sampling_interval_of_anisotropic_cone_pixels() -> None:
    """Cone beam: v = 0.2 (z / max(fx, fy))² (Mip-Splatting, finest of the two pixel pitches)."""
    z = torch.tensor([200.0, 400.0], dtype=torch.float64)
    means = torch.stack([torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), z], -1)
    g = Gaussians.from_values(means, 1.0, 1.0, dtype=torch.float64)
    fx, fy = 500.0, 800.0
    v = compute_3d_filter(g, _cone(fx, fy), np.eye(3)[None], np.zeros((1, 3)))
    np.testing.assert_allclose(v.numpy(), 0.2 * (z.numpy() / max(fx, fy)) ** 2, rtol=1e-12)


def test_3d_filter_counts_a_gaussian_near_the_image_edge_as_seen() -> None:
    """A Gaussian projecting inside the image, near its left edge, gets its own interval, not the fill."""
    f, w, h = 1000.0, 100, 80
    cam = _cone(f, f, w, h)
    # Gaussian 0 at the centre, 400 mm deep; Gaussian 1 at 100 mm depth projecting to u = 5 px (of 100)
    z1 = 100.0
    x1 = (5.0 - w / 2) * z1 / f
    means = torch.tensor([[0.0, 0.0, 400.0], [x1, 0.0, z1]], dtype=torch.float64)
    g = Gaussians.from_values(means, 1.0, 1.0, dtype=torch.float64)
    v = compute_3d_filter(g, cam, np.eye(3)[None], np.zeros((1, 3)))
    expected = 0.2 * (np.array([400.0, z1]) / f) ** 2
    np.testing.assert_allclose(v.numpy(), expected, rtol=1e-12)
    assert math.isclose(float(v[1]), 0.2 * (z1 / f) ** 2, rel_tol=1e-12)
