"""DICOM / NIfTI / TIFF reading on small synthetic series written with pydicom (fast), incl. every bad input."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import pydicom
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ctsplat.formats.sources import (
    LPS_TO_RAS,
    SliceGapWarning,
    find_dicom_series,
    read_dicom_series,
    read_nifti,
    read_source,
    read_tiff_stack,
    salted_hash,
    write_dicom_series,
)
from ctsplat.utils import CtsplatError
from ctsplat.volume import ingest, resample_stack

F = LPS_TO_RAS


def linear_hu(p_lps: np.ndarray) -> np.ndarray:
    """An HU field linear in LPS world position: geometry errors of half a voxel show up as >= 2 HU."""
    return 10.0 * p_lps[..., 0] + 7.0 * p_lps[..., 1] + 5.0 * p_lps[..., 2] + 200.0


def rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def make_series(
    folder: Path,
    *,
    shape=(8, 6, 5),
    spacing=(1.5, 2.0, 2.5),
    origin=(-5.0, 3.0, 20.0),
    row=(1.0, 0.0, 0.0),
    col=(0.0, 1.0, 0.0),
    positions=None,
    step=None,
    field=linear_hu,
    **kw,
) -> list[Path]:
    """Write a series whose HU = ``field(LPS position)`` at every pixel centre."""
    row, col = np.asarray(row, float), np.asarray(col, float)
    n_i, n_j, n_k = shape
    normal = np.cross(row, col)
    if step is not None:
        ipps = np.asarray(origin)[None] + np.arange(n_k)[:, None] * np.asarray(step)[None]
    else:
        pos = np.arange(n_k) * spacing[2] if positions is None else np.asarray(positions, float)
        ipps = np.asarray(origin)[None] + pos[:, None] * normal[None]
    i, j = np.meshgrid(np.arange(n_i), np.arange(n_j), indexing="ij")
    pts = (
        ipps[None, None, :, :]
        + (i[..., None, None] * spacing[0]) * row
        + (j[..., None, None] * spacing[1]) * col
    )
    hu = field(pts)
    return write_dicom_series(
        hu, folder, spacing_mm=spacing, origin_lps=origin, row_dir_lps=row, col_dir_lps=col,
        slice_positions_mm=positions, slice_step_lps=step, **kw,
    )


def place(folder: Path, path: Path) -> str:
    """How errors and warnings name a file of a DICOM folder: by its place in path order, never by its name."""
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return f"file {files.index(path) + 1} of {len(files)} in the input folder (in sorted path order)"


def assert_fails_cleanly(source, tmp_path: Path, match: str, **kw) -> str:
    """Ingest must raise a one-line CtsplatError matching ``match`` and leave the output folder empty."""
    out = tmp_path / "out"
    with pytest.raises(CtsplatError, match=match) as err:
        ingest(source, out / "volume.nii.gz", {"grid": 8}, **kw)
    msg = str(err.value)
    assert "\n" not in msg
    assert not out.exists() or not any(out.iterdir()), list(out.iterdir())
    return msg


# ------------------------------------------------------------------------------------------ geometry


def test_reader_geometry_matches_written_positions(tmp_path):
    files = make_series(tmp_path / "s")
    stack = read_dicom_series(tmp_path / "s")
    assert stack.data.shape == (8, 6, 5)
    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)
        ipp_ras = F @ np.asarray(ds.ImagePositionPatient, float)
        np.testing.assert_allclose(stack.origins[k], ipp_ras, atol=1e-5)
        hu = ds.pixel_array.astype(float) * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        np.testing.assert_array_equal(stack.data[:, :, k], hu.T)
    np.testing.assert_allclose(stack.row_dir, [-1, 0, 0])
    np.testing.assert_allclose(stack.col_dir, [0, -1, 0])
    assert stack.spacing_ij == (1.5, 2.0)
    assert stack.units == "hu"


def test_order_is_by_position_not_filename_or_instance_number(tmp_path):
    files = make_series(tmp_path / "s")
    ref = read_dicom_series(tmp_path / "s")
    # scramble: reversed file names, wrong InstanceNumber, identical SliceLocation
    other = tmp_path / "t"
    other.mkdir()
    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)
        ds.InstanceNumber = 1
        ds.SliceLocation = "0"
        ds.save_as(other / f"z{len(files) - k:02d}.dcm")
    stack = read_dicom_series(other)
    np.testing.assert_array_equal(stack.data, ref.data)
    np.testing.assert_allclose(stack.origins, ref.origins)


def world_points(affine, shape):
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    return idx @ affine[:3, :3].T + affine[:3, 3]


@pytest.mark.parametrize(
    "case",
    ["axial", "nonuniform", "oblique", "tilt", "feet_first_reversed"],
)
def test_resampled_values_match_world_field(tmp_path, case):
    """The resampled volume at each output voxel centre equals the analytic field at that world point.

    Linear interpolation reproduces a linear field exactly, so any error in ordering, spacing,
    LPS->RAS conversion, oblique orientation or tilt shows up as a mismatch (values are stored
    rounded to 1 HU, hence the 0.5 HU tolerance).
    """
    kw: dict = {}
    if case == "nonuniform":
        kw["positions"] = [0.0, 2.5, 5.0, 6.0, 9.5]
    elif case == "oblique":
        r = rotation([1, 2, 0.5], 25)
        kw.update(row=r @ [1, 0, 0], col=r @ [0, 1, 0])
    elif case == "tilt":  # gantry tilt 15 deg: each slice drifts along the column direction
        kw["step"] = np.array([0.0, 2.5 * np.tan(np.radians(15)), 2.5])
    elif case == "feet_first_reversed":
        kw.update(row=(-1.0, 0.0, 0.0), col=(0.0, 1.0, 0.0))
    make_series(tmp_path / "s", **kw)
    stack = read_dicom_series(tmp_path / "s")
    if case == "tilt":
        assert stack.tilt_deg == pytest.approx(15.0, abs=1e-3)
    vol, affine, _ = resample_stack(stack, voxel_size_mm=1.0)
    pts = world_points(affine, vol.shape)
    expected = linear_hu(pts @ F)  # RAS -> LPS is the same flip
    # interior: points whose in-plane and along-normal coordinates lie between source voxel centres
    u, v, n = stack.row_dir, stack.col_dir, stack.normal
    inside = (pts @ n >= stack.positions_mm[0] - 1e-6) & (pts @ n <= stack.positions_mm[-1] + 1e-6)
    for o in stack.origins:
        cu, cv = (pts - o) @ u, (pts - o) @ v
        inside &= (cu >= -1e-6) & (cu <= (stack.data.shape[0] - 1) * stack.spacing_ij[0] + 1e-6)
        inside &= (cv >= -1e-6) & (cv <= (stack.data.shape[1] - 1) * stack.spacing_ij[1] + 1e-6)
    assert inside.sum() > 20
    err = np.abs(vol - expected)[inside]
    assert err.max() <= 0.5 + 1e-3, err.max()
    # output grid is RAS-closest with a positive diagonal (no flips left)
    assert np.all(np.diag(affine[:3, :3]) > 0)


def test_native_grid_keeps_source_voxel_centres(tmp_path):
    make_series(tmp_path / "s")
    stack = read_dicom_series(tmp_path / "s")
    vol, affine, info = resample_stack(stack)
    assert info["mode"] == "native spacing"
    np.testing.assert_allclose(sorted(np.linalg.norm(affine[:3, :3], axis=0)), sorted([1.5, 2.0, 2.5]))
    # the source pixel (i, j, k) is an exact voxel of the output, with the same value
    for i, j, k in [(0, 0, 0), (3, 2, 4), (7, 5, 1)]:
        p = stack.origins[k] + i * 1.5 * stack.row_dir + j * 2.0 * stack.col_dir
        idx = np.linalg.solve(affine[:3, :3], p - affine[:3, 3])
        np.testing.assert_allclose(idx, np.round(idx), atol=1e-6)
        assert vol[tuple(np.round(idx).astype(int))] == pytest.approx(stack.data[i, j, k], abs=1e-3)


def test_grid_mode_is_isotropic_cube_padded_with_air(tmp_path):
    make_series(tmp_path / "s", field=lambda p: np.zeros(p.shape[:-1]) + 40.0)
    stack = read_dicom_series(tmp_path / "s")
    stack.data[0, 0, 0] = -1000.0  # air sample sets the fill value
    vol, affine, _ = resample_stack(stack, grid=16)
    assert vol.shape == (16, 16, 16)
    sp = np.linalg.norm(affine[:3, :3], axis=0)
    np.testing.assert_allclose(sp, sp[0])
    # largest extent (slices: 5 * 2.5 = 12.5 mm vs 12 and 12 mm in-plane) fits exactly
    assert sp[0] == pytest.approx(12.5 / 16)
    assert vol.min() == pytest.approx(-1000.0)  # padding outside the scan is air


# ------------------------------------------------------------------------------------------ other formats


def test_nifti_input_roundtrip_and_flipped_slice_axis(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.normal(size=(6, 5, 4)).astype(np.float32) * 100
    aff = np.array([[0, 0, 2.0, -3], [1.5, 0, 0, 4], [0, -1.2, 0, 7], [0, 0, 0, 1]])
    nib.save(nib.Nifti1Image(data, aff), tmp_path / "x.nii.gz")
    stack = read_nifti(tmp_path / "x.nii.gz")
    # every voxel keeps its world position
    for i, j, k in [(0, 0, 0), (5, 4, 3), (2, 1, 3)]:
        p = aff[:3, :3] @ [i, j, k] + aff[:3, 3]
        kk = int(np.argmin(np.abs(stack.positions_mm - p @ stack.normal)))
        q = stack.origins[kk] + i * stack.spacing_ij[0] * stack.row_dir + j * stack.spacing_ij[1] * stack.col_dir
        np.testing.assert_allclose(q, p, atol=1e-6)
        assert stack.data[i, j, kk] == data[i, j, k]
    assert np.all(np.diff(stack.positions_mm) > 0)
    vol, affine, _ = resample_stack(stack)
    # native resampling of a regular grid is the identity up to axis permutation/flip
    np.testing.assert_allclose(np.sort(vol.ravel()), np.sort(data.ravel()), atol=1e-3)


def _write_nifti_as_is(path: Path, header: nib.Nifti1Header, data: np.ndarray) -> None:
    """A single-file NIfTI with exactly this header (``nib.save`` would fix pixdim and the sform)."""
    header.set_data_shape(data.shape)
    header.set_data_dtype(data.dtype)
    header["vox_offset"] = 352
    with open(path, "wb") as fh:
        header.write_to(fh)
        fh.write(b"\0" * (352 - fh.tell()) + data.tobytes(order="F"))


def test_nifti_header_without_a_usable_geometry_is_named(tmp_path):
    data = np.zeros((6, 5, 4), np.float32)
    nan_sform = nib.Nifti1Header()
    nan_sform.set_sform(np.eye(4), code=1)
    nan_sform["srow_x"][0] = np.nan
    _write_nifti_as_is(tmp_path / "nan.nii", nan_sform, data)
    msg = assert_fails_cleanly(tmp_path / "nan.nii", tmp_path, "NaN or infinite entries")
    assert str(tmp_path / "nan.nii") in msg and "qform/sform" in msg
    zero = nib.Nifti1Header()  # no qform / sform: the voxel size is pixdim alone
    zero["pixdim"][1:4] = 0.0
    _write_nifti_as_is(tmp_path / "zero.nii", zero, data)
    assert_fails_cleanly(tmp_path / "zero.nii", tmp_path, r"pixdim\) \[0.0, 0.0, 0.0\] and no sform")
    zero.set_qform(np.eye(4), code=1)  # a qform scales by pixdim too
    zero["pixdim"][1:4] = 0.0
    _write_nifti_as_is(tmp_path / "zero_q.nii", zero, data)
    assert_fails_cleanly(tmp_path / "zero_q.nii", tmp_path, r"pixdim\) \[0.0, 0.0, 0.0\] and no sform")
    for size, name in ((1e-30, "small"), (1e30, "large")):  # a unit or header error, not a scan
        nib.save(nib.Nifti1Image(data, np.diag([size, 1.0, 1.0, 1.0])), tmp_path / f"{name}.nii.gz")
        shown = re.escape(f"{size:.3g}")
        assert_fails_cleanly(tmp_path / f"{name}.nii.gz", tmp_path, rf"voxel size {shown} x 1 x 1 mm lies outside "
                             r"1e-07 \.\. 1e\+07 mm \(a unit or header error\); fix the NIfTI header")
    stack = np.arange(120, dtype=np.float32).reshape(4, 5, 6)
    tifffile.imwrite(tmp_path / "s.tif", stack, photometric="minisblack")
    with pytest.raises(CtsplatError, match=r"lies outside .* give the TIFF voxel size in mm \(--tiff-voxel-size"):
        read_tiff_stack(tmp_path / "s.tif", 1e-20)
    tiny = np.diag([1e-6, 1e-6, 1e-6, 1.0])  # nanometre voxels are a volume, not a degenerate header
    nib.save(nib.Nifti1Image(np.arange(120, dtype=np.float32).reshape(6, 5, 4), tiny), tmp_path / "tiny.nii.gz")
    vol = ingest(tmp_path / "tiny.nii.gz", tmp_path / "t" / "v.nii.gz", {"voxel_size_mm": 1e-6})
    assert vol.shape == (6, 5, 4)
    np.testing.assert_allclose(vol.spacing_mm, 1e-6)


def test_tiff_stack_file_and_folder(tmp_path):
    arr = np.arange(4 * 5 * 6, dtype=np.uint16).reshape(4, 5, 6)  # (Z, Y, X)
    tifffile.imwrite(tmp_path / "stack.tif", arr, photometric="minisblack")
    folder = tmp_path / "slices"
    folder.mkdir()
    for z in range(4):  # natural order: 2 < 10
        tifffile.imwrite(folder / f"img_{[1, 2, 10, 11][z]}.tif", arr[z])
    for src in (tmp_path / "stack.tif", folder):
        stack = read_source(src, tiff_voxel_size_mm=(0.5, 0.6, 0.7))
        assert stack.units == "raw"
        np.testing.assert_array_equal(stack.data, arr.transpose(2, 1, 0))
        assert stack.spacing_ij == (0.5, 0.6)
        np.testing.assert_allclose(np.diff(stack.positions_mm), 0.7)
    with pytest.raises(CtsplatError, match="voxel size"):
        read_tiff_stack(tmp_path / "stack.tif", None)
    tifffile.imwrite(folder / "img_3.tif", arr[0, :4])  # the slice that does not fit is named
    with pytest.raises(CtsplatError, match=r"differ in size: img_3.tif is \(4, 6\), img_1.tif is \(5, 6\)"):
        read_source(folder, tiff_voxel_size_mm=0.5)
    (folder / "img_3.tif").write_bytes(b"junk" * 10)
    with pytest.raises(CtsplatError, match=r"TIFF slice .*img_3\.tif is not a readable TIFF .*remove it"):
        read_source(folder, tiff_voxel_size_mm=0.5)


# ------------------------------------------------------------------------------------------ compressed


def test_jpeg2000_series_decodes(tmp_path):
    pytest.importorskip("openjpeg")
    make_series(tmp_path / "plain", shape=(32, 32, 3))
    make_series(tmp_path / "j2k", shape=(32, 32, 3), transfer_syntax="1.2.840.10008.1.2.4.90")
    a, b = read_dicom_series(tmp_path / "plain"), read_dicom_series(tmp_path / "j2k")
    assert "JPEG 2000" in b.source["transfer_syntax"]
    np.testing.assert_array_equal(a.data, b.data)


def test_compressed_without_decoder_names_the_package(tmp_path, monkeypatch):
    pytest.importorskip("openjpeg")
    from pydicom.pixels.decoders.base import Decoder

    make_series(tmp_path / "j2k", shape=(32, 32, 3), transfer_syntax="1.2.840.10008.1.2.4.90")
    monkeypatch.setattr(Decoder, "is_available", property(lambda self: False))
    msg = assert_fails_cleanly(tmp_path / "j2k", tmp_path, "no decoder")
    assert "pylibjpeg-openjpeg" in msg and "pip install 'ctsplat[j2k]'" in msg
    # JPEG Lossless needs another plugin than the j2k extra holds: named as pip installs it
    from ctsplat.formats.sources import _check_decoder

    ds = pydicom.dcmread(make_series(tmp_path / "raw", shape=(8, 8, 2))[0])
    ds.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.4.70"
    with pytest.raises(CtsplatError, match=r"install pylibjpeg and pylibjpeg-libjpeg \(pip install pylibjpeg "
                                           r"pylibjpeg-libjpeg\)$"):
        _check_decoder(ds, "file 1")


# ------------------------------------------------------------------------------------------ bad input


def test_missing_input_and_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    assert_fails_cleanly(tmp_path / "empty", tmp_path, "is empty")
    assert_fails_cleanly(tmp_path / "nope", tmp_path, "does not exist")


def test_non_dicom_files_only(tmp_path):
    d = tmp_path / "junk"
    d.mkdir()
    (d / "notes.txt").write_text("not a scan\n" * 20)
    (d / "image.bin").write_bytes(bytes(range(256)) * 4)
    assert_fails_cleanly(d, tmp_path, "no DICOM image files")


@pytest.mark.parametrize("cut", ["pixels", "header", "encapsulated pixels"])
def test_truncated_file_named_and_skippable(tmp_path, caplog, cut):
    # encapsulated (JPEG 2000) pixel data cut short: pydicom reads the header and returns an empty dataset
    syntax = {"transfer_syntax": "1.2.840.10008.1.2.4.90"} if cut == "encapsulated pixels" else {}
    files = make_series(tmp_path / "s", shape=(32, 32, 6) if syntax else (8, 6, 6), **syntax)
    bad = files[2]
    raw = bad.read_bytes()
    bad.write_bytes(raw[:400] if cut == "header" else raw[:-40])
    msg = assert_fails_cleanly(tmp_path / "s", tmp_path, "corrupt or truncated")
    assert place(tmp_path / "s", bad) in msg and "skip" in msg
    assert bad.name not in msg  # DICOM file names are often SOP Instance UIDs
    with caplog.at_level(logging.WARNING, logger="ctsplat.formats.sources"), pytest.warns(SliceGapWarning):
        vol = ingest(tmp_path / "s", tmp_path / "ok" / "volume.nii.gz", {"grid": 8}, skip_corrupt=True)
    assert any(place(tmp_path / "s", bad) in r.getMessage() for r in caplog.records)
    assert not any(bad.name in r.getMessage() for r in caplog.records)
    assert vol.meta["source"]["n_slices"] == 5
    assert vol.meta["source"]["n_files_skipped"] == 1
    assert vol.meta["source"]["missing_slice_gaps"][0]["between_slices"] == [1, 2]  # where the skipped slice was


def test_damaged_file_meta_is_named_in_one_line(tmp_path):
    """A file meta element with a byte-damaged VR (pydicom decodes it only when read, so it fails after parsing)
    is a corrupt file, skippable; a TransferSyntaxUID that names no transfer syntax is one line too."""
    files = make_series(tmp_path / "vr", shape=(8, 6, 6))
    raw = files[2].read_bytes()
    tag = b"\x02\x00\x02\x00UI"  # (0002,0002) MediaStorageSOPClassUID, explicit VR
    assert raw.count(tag) == 1
    files[2].write_bytes(raw.replace(tag, b"\x02\x00\x02\x00U\x03"))
    msg = assert_fails_cleanly(tmp_path / "vr", tmp_path, "corrupt or truncated")
    assert place(tmp_path / "vr", files[2]) in msg and "Unknown Value Representation" in msg
    with pytest.warns(SliceGapWarning):
        vol = ingest(tmp_path / "vr", tmp_path / "ok" / "volume.nii.gz", {"grid": 8}, skip_corrupt=True)
    assert vol.meta["source"]["n_files_skipped"] == 1

    files = make_series(tmp_path / "ts", shape=(8, 6, 6))
    explicit_le = b"1.2.840.10008.1.2.1\x00"
    for f in files:
        raw = f.read_bytes()
        assert raw.count(explicit_le) == 1
        f.write_bytes(raw.replace(explicit_le, b"1.2.840.10008.9.9.9\x00"))  # same length, no transfer syntax
    msg = assert_fails_cleanly(tmp_path / "ts", tmp_path, "its TransferSyntaxUID is not a transfer syntax")
    assert "re-export the file or remove it" in msg


def test_mixed_series_without_choice_lists_them(tmp_path):
    make_series(tmp_path / "mix" / "a", uid_seed="a")
    make_series(tmp_path / "mix" / "b", uid_seed="b", filename="b_{k:04d}.dcm")
    series = find_dicom_series(tmp_path / "mix")
    assert len(series) == 2
    msg = assert_fails_cleanly(tmp_path / "mix", tmp_path, "no unique largest")
    for s in series:
        assert s.id in msg and s.uid not in msg  # named by the salted hash, never by the UID
        assert s.id == salted_hash(s.uid)
    for selector in (series[1].id, series[1].id.upper(), series[1].uid):  # the listed id, or the UID one knows
        stack = read_dicom_series(tmp_path / "mix", series_uid=selector)
        assert stack.data.shape[2] == 5
        assert stack.source["series_id"] == stack.source["series_uid_hash"] == series[1].id


def test_mixed_series_picks_largest_with_warning(tmp_path, caplog):
    make_series(tmp_path / "mix" / "a", uid_seed="a")
    make_series(tmp_path / "mix" / "b", uid_seed="b", shape=(8, 6, 3))
    with caplog.at_level(logging.WARNING, logger="ctsplat.formats.sources"):
        stack = read_dicom_series(tmp_path / "mix")
    assert stack.data.shape[2] == 5
    assert any("2 series" in r.getMessage() and stack.source["series_id"] in r.getMessage() for r in caplog.records)


def test_missing_image_position(tmp_path):
    files = make_series(tmp_path / "s")
    ds = pydicom.dcmread(files[3])
    del ds.ImagePositionPatient
    ds.save_as(files[3])
    msg = assert_fails_cleanly(tmp_path / "s", tmp_path, "ImagePositionPatient")
    assert place(tmp_path / "s", files[3]) in msg and files[3].name not in msg


@pytest.mark.filterwarnings("ignore:Invalid value for VR DS")
@pytest.mark.parametrize(("tag", "value", "needle"), [
    ("PixelSpacing", ["0", "0"], "invalid PixelSpacing (need 2 positive numbers (mm))"),
    ("PixelSpacing", ["-1", "1"], "invalid PixelSpacing"),
    ("ImagePositionPatient", ["nan", "0", "0"], "invalid ImagePositionPatient (need 3 finite numbers)"),
    ("ImageOrientationPatient", ["1", "0", "0", "0", "inf", "0"], "invalid ImageOrientationPatient"),
    ("RescaleSlope", "0", "invalid RescaleSlope/RescaleIntercept"),
    ("RescaleIntercept", "nan", "invalid RescaleSlope/RescaleIntercept"),
    ("PixelSpacing", "1.5", "invalid PixelSpacing (need 2 values, it holds 1)"),
    ("ImagePositionPatient", ["1", "2"], "invalid ImagePositionPatient (need 3 values, it holds 2)"),
])
def test_invalid_geometry_or_rescale_values_fail_naming_the_tag(tmp_path, tag, value, needle):
    files = make_series(tmp_path / "s")
    for f in files:  # every slice, as an exporter would write them
        ds = pydicom.dcmread(f)
        setattr(ds, tag, value)
        ds.save_as(f)
    msg = assert_fails_cleanly(tmp_path / "s", tmp_path, re.escape(needle))
    assert place(tmp_path / "s", files[0]) in msg or "file 1 of" in msg


@pytest.mark.filterwarnings("ignore:Invalid value for VR")
def test_descriptive_numbers_that_are_not_one_number_are_recorded_as_unknown(tmp_path):
    """KVP "140kV", a dual-energy KVP 80\\140 and SliceThickness "2 mm" are described, never used: recorded as
    null instead of ending the ingest in a traceback."""
    files = make_series(tmp_path / "s")
    for f in files:  # written as text (VR LO), as pydicom hands a malformed number over
        ds = pydicom.dcmread(f)
        ds[0x00180060] = pydicom.DataElement(0x00180060, "LO", "80\\140" if f == files[0] else "140kV")  # KVP
        ds[0x00180050] = pydicom.DataElement(0x00180050, "LO", "2 mm")  # SliceThickness
        ds.save_as(f)
    ingest(tmp_path / "s", tmp_path / "out" / "volume.nii.gz", {"grid": 8})
    source = json.loads((tmp_path / "out" / "volume.json").read_text())["source"]
    assert source["kvp"] is None and source["slice_thickness_mm"] is None
    ds = pydicom.dcmread(files[2])
    ds[0x00280008] = pydicom.DataElement(0x00280008, "LO", "one")  # NumberOfFrames
    ds.save_as(files[2])
    msg = assert_fails_cleanly(tmp_path / "s", tmp_path / "x", r"invalid NumberOfFrames \(not an integer\)")
    assert place(tmp_path / "s", files[2]) in msg


def test_an_unreadable_file_is_named_by_its_place_not_its_path(tmp_path):
    """Exports name folders after the patient: an operating-system error's path stays out of the message."""
    from ctsplat.formats.sources import _why

    err = PermissionError(13, "Permission denied", str(tmp_path / "PAT_DOE_JANE_19700923" / "IM0001"))
    assert _why(err) == "PermissionError: Permission denied"


def test_a_grid_with_no_layer_on_a_thin_slab_is_refused(tmp_path):
    # a 3 mm slab 80 mm wide: a 16-voxel cube has 5 mm layers, the nearest 2.5 mm from the slab's middle
    make_series(tmp_path / "s", shape=(8, 6, 3), spacing=(10.0, 10.0, 1.0))
    with pytest.raises(CtsplatError, match="no output layer of 5 mm lies on the 3 mm the slices cover"):
        ingest(tmp_path / "s", tmp_path / "out" / "volume.nii.gz", {"grid": 16})
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_single_slice(tmp_path):
    make_series(tmp_path / "s", shape=(8, 6, 1))
    assert_fails_cleanly(tmp_path / "s", tmp_path, "single slice")


def test_inconsistent_rows_columns(tmp_path):
    make_series(tmp_path / "s", uid_seed="same")
    make_series(tmp_path / "s", uid_seed="same", shape=(7, 6, 1), origin=(-5.0, 3.0, 40.0), filename="odd_{k}.dcm")
    assert_fails_cleanly(tmp_path / "s", tmp_path, "inconsistent slice size")


def test_inconsistent_pixel_spacing(tmp_path):
    files = make_series(tmp_path / "s")
    ds = pydicom.dcmread(files[1])
    ds.PixelSpacing = ["2.0", "1.0"]
    ds.save_as(files[1])
    assert_fails_cleanly(tmp_path / "s", tmp_path, "inconsistent PixelSpacing")


def test_duplicate_positions_name_both_files(tmp_path):
    files = make_series(tmp_path / "s")
    shutil.copy(files[2], tmp_path / "s" / "copy_of_2.dcm")
    msg = assert_fails_cleanly(tmp_path / "s", tmp_path, "duplicate slice position")
    assert place(tmp_path / "s", files[2]) in msg and place(tmp_path / "s", tmp_path / "s" / "copy_of_2.dcm") in msg
    assert "copy_of_2.dcm" not in msg and files[2].name not in msg


def test_mr_rejected_unless_allowed(tmp_path):
    make_series(tmp_path / "mr", modality="MR")
    msg = assert_fails_cleanly(tmp_path / "mr", tmp_path, "MR")
    assert "--allow-modality" in msg
    stack = read_dicom_series(tmp_path / "mr", allow_modalities=("CT", "MR"))
    assert stack.units == "raw"
    with pytest.raises(CtsplatError, match="needs HU"):
        ingest(tmp_path / "mr", tmp_path / "o" / "v.nii.gz", {"intensity": "window"}, allow_modalities=("MR",))
    vol = ingest(tmp_path / "mr", tmp_path / "o" / "v.nii.gz", {"grid": 8}, allow_modalities=("MR",))
    assert vol.meta["intensity"]["kind"] == "minmax_normalised"
    assert 0.0 <= vol.data.min() and vol.data.max() <= 1.0


def test_different_orientations_rejected(tmp_path):
    files = make_series(tmp_path / "s")
    ds = pydicom.dcmread(files[4])
    r = rotation([0, 0, 1], 10)
    ds.ImageOrientationPatient = [f"{x:.6f}" for x in (*(r @ [1, 0, 0]), *(r @ [0, 1, 0]))]
    ds.save_as(files[4])
    assert_fails_cleanly(tmp_path / "s", tmp_path, "different ImageOrientationPatient")



def test_non_orthonormal_orientation_names_the_series_and_a_file(tmp_path):
    make_series(tmp_path / "s", row=(1.0, 0.0, 0.0), col=(1.0, 0.0, 0.0))
    msg = assert_fails_cleanly(tmp_path / "s", tmp_path, "is not 2 orthonormal unit vectors")
    assert "series " in msg and "file 1 of 5" in msg


def test_grid_list_is_in_output_axis_order(tmp_path):
    # oblique-ish series whose row direction is LPS +y: output axes get permuted to RAS order
    make_series(tmp_path / "s", row=(0.0, 1.0, 0.0), col=(1.0, 0.0, 0.0))
    stack = read_dicom_series(tmp_path / "s")
    vol, affine, _ = resample_stack(stack, grid=[8, 10, 12])
    assert vol.shape == (8, 10, 12)
    assert np.all(np.diag(affine[:3, :3]) > 0)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(order=st.permutations(range(5)))
def test_property_any_file_order_gives_the_same_stack(tmp_path, order):
    src = tmp_path / "src"
    if not src.exists():
        make_series(src, positions=[0.0, 2.5, 5.0, 6.0, 9.5])
    ref = read_dicom_series(src)
    files = sorted(src.iterdir())
    dst = tmp_path / ("perm_" + "".join(map(str, order)))
    dst.mkdir(exist_ok=True)
    for n, m in enumerate(order):
        shutil.copy(files[m], dst / f"{n:02d}_{m}.dcm")
    stack = read_dicom_series(dst)
    np.testing.assert_array_equal(stack.data, ref.data)
    np.testing.assert_allclose(stack.origins, ref.origins)


def test_atomic_writes_leave_nothing_on_error_and_use_normal_permissions(tmp_path):
    from ctsplat.utils import atomic_path, write_json_atomic

    out = tmp_path / "a.json"
    write_json_atomic(out, {"x": 1})
    umask = os.umask(0o022)
    os.umask(umask)
    assert (out.stat().st_mode & 0o777) == 0o666 & ~umask  # not mkstemp's 0600
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "b.nii.gz") as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("writer failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


def test_atomic_dir_replaces_whole_folders_or_leaves_the_old_one(tmp_path):
    from ctsplat.utils import atomic_dir

    out = tmp_path / "views"
    out.mkdir()
    (out / "old.png").write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_dir(out, marker="*.png") as tmp:
        (tmp / "new.png").write_bytes(b"partial")
        raise RuntimeError("writer failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["views"]  # no temporary folder left
    assert sorted(p.name for p in out.iterdir()) == ["old.png"]
    with atomic_dir(out, marker="*.png") as tmp:
        (tmp / "new.png").write_bytes(b"new")
        assert not (out / "new.png").exists()  # nothing visible before the block ends
    assert sorted(p.name for p in out.iterdir()) == ["new.png"]
    umask = os.umask(0o022)
    os.umask(umask)
    assert (out.stat().st_mode & 0o777) == 0o777 & ~umask  # not mkdtemp's 0700
    assert sorted(p.name for p in tmp_path.iterdir()) == ["views"]


def test_failed_atomic_writes_remove_the_parent_folders_they_made(tmp_path):
    from ctsplat.utils import atomic_dir, atomic_path

    (tmp_path / "kept").mkdir()
    for writer in (atomic_dir, atomic_path):
        with pytest.raises(RuntimeError), writer(tmp_path / "kept" / "new" / "deeper" / "out") as tmp:
            (tmp / "part" if tmp.is_dir() else tmp).write_bytes(b"partial")
            raise RuntimeError("writer failed")
        assert sorted(p.name for p in tmp_path.rglob("*")) == ["kept"]  # the parent that existed stays
    # a parent that something else wrote into meanwhile is left, with its own parents
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "a" / "b" / "out.csv"):
        (tmp_path / "a" / "other.txt").write_text("not ours")
        raise RuntimeError("writer failed")
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == ["a", "a/other.txt", "kept"]
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "n" / ".." / "m" / "out.csv"):
        raise RuntimeError("writer failed")  # a ".." in the path: every folder made is still removed
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == ["a", "a/other.txt", "kept"]
    with atomic_dir(tmp_path / "x" / "y" / "out") as tmp:  # success keeps them
        (tmp / "f").write_text("done")
    assert (tmp_path / "x" / "y" / "out" / "f").read_text() == "done"


def test_atomic_dir_replaces_only_empty_folders_earlier_outputs_and_never_an_input(tmp_path):
    from ctsplat.utils import atomic_dir, check_output_dir

    mine = tmp_path / "mine"
    (mine / "photos").mkdir(parents=True)
    (mine / "photos" / "a.jpg").write_bytes(b"jpeg")
    (mine / "notes.txt").write_text("keep")
    for out in (mine, mine / "photos"):  # a folder that holds the input, and the input itself
        with pytest.raises(CtsplatError, match=r"is, or holds, the input .*choose another output folder"):
            with atomic_dir(out, marker="*.jpg", inputs=(mine / "photos",)):
                pass
    with pytest.raises(CtsplatError, match=r"mine already holds files that are not an earlier output of this step "
                                           r"\(no summary\.json in it\)"):
        check_output_dir(mine, marker="summary.json")
    with pytest.raises(CtsplatError, match="already holds files"):
        check_output_dir(mine)  # no marker: only a new or empty folder
    assert (mine / "notes.txt").read_text() == "keep" and (mine / "photos" / "a.jpg").is_file()
    empty = tmp_path / "empty" / "figures"  # empty sub-folders (as Snakemake makes them) do not count
    empty.mkdir(parents=True)
    check_output_dir(empty.parent)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(CtsplatError, match="exists and is not a folder"):
        check_output_dir(tmp_path / "afile")
    # the folder changes while the block runs: checked again before it is replaced
    out = tmp_path / "run"
    with pytest.raises(CtsplatError, match="already holds files"), atomic_dir(out, marker="config.json") as tmp:
        (tmp / "config.json").write_text("{}")
        out.mkdir()
        (out / "someone_elses.txt").write_text("x")
    assert (out / "someone_elses.txt").is_file() and not (out / "config.json").exists()


def test_a_folder_with_the_marker_and_other_files_is_not_replaced(tmp_path):
    from ctsplat.utils import atomic_dir, check_output_dir

    run = tmp_path / "project"  # a user's folder that happens to hold a file named like the step's marker
    (run / "sub").mkdir(parents=True)
    (run / "config.json").write_text("{}")
    (run / "notes.txt").write_text("keep")
    (run / "sub" / "data.csv").write_text("a,b")
    files = ("model.pt", "figures/*.png")
    with pytest.raises(CtsplatError, match=r"project holds notes\.txt and 1 more, which this step does not write"):
        with atomic_dir(run, marker="config.json", contents=files) as tmp:
            (tmp / "config.json").write_text("{}")
    assert sorted(p.relative_to(run).as_posix() for p in run.rglob("*")) == [
        "config.json", "notes.txt", "sub", "sub/data.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["project"]  # no temporary folder left
    # an earlier output (the marker, the listed files, Snakemake's timestamps, temporaries) is replaced whole
    earlier = tmp_path / "run"
    (earlier / "figures").mkdir(parents=True)
    (earlier / ".figures.u7e2kq").mkdir()
    for name in ("config.json", "model.pt", "figures/gallery.png", "figures/.snakemake_timestamp",
                 ".model.k3j9x_q.tmp.pt", "figures/.gallery.a81z0w.tmp.png",  # killed atomic_path writes' leftovers
                 ".figures.u7e2kq/acf.png"):  # and a killed atomic_dir's
        (earlier / name).write_text("old")
    with atomic_dir(earlier, marker="config.json", contents=files) as tmp:
        (tmp / "config.json").write_text("new")
    assert [p.name for p in earlier.iterdir()] == ["config.json"]
    assert (earlier / "config.json").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["project", "run"]  # the old folder, moved aside, is gone
    # a file that only looks like a listed one at another depth is foreign too
    (earlier / "model.pt").write_text("x")
    (earlier / "figures").mkdir()
    (earlier / "figures" / "model.pt").write_text("x")
    with pytest.raises(CtsplatError, match=r"holds figures/model\.pt, which"):
        check_output_dir(earlier, marker="config.json", contents=files)


@pytest.mark.parametrize("kind", ["file", "folder"])
def test_ctrl_c_while_the_temporary_is_created_leaves_nothing(tmp_path, monkeypatch, kind):
    # Ctrl-C lands just after the temporary exists on disk and before the writer has its name: the moment a
    # signal can otherwise leave a stray file
    import signal
    import tempfile

    from ctsplat.utils import atomic_dir, atomic_path

    name = "mkstemp" if kind == "file" else "mkdtemp"
    create = getattr(tempfile, name)

    def create_then_interrupt(*args, **kwargs):
        made = create(*args, **kwargs)
        signal.raise_signal(signal.SIGINT)
        return made

    monkeypatch.setattr(tempfile, name, create_then_interrupt)
    # Python's own Ctrl-C handler, whatever the suite inherited: a shell without job control starts background
    # jobs with SIGINT ignored, and then there is no interrupt to deliver
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        writer = atomic_path(tmp_path / "ckpt.pt") if kind == "file" else atomic_dir(tmp_path / "views")
        with pytest.raises(KeyboardInterrupt), writer:
            pass
        assert list(tmp_path.iterdir()) == []
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # Ctrl-C handled as before
    finally:
        signal.signal(signal.SIGINT, previous)


# ------------------------------------------------------------------------------------------ rescale


def head_hu(p_lps: np.ndarray) -> np.ndarray:
    """Air (-1000 HU) around a water ball (0 HU) with a bone core (+1000 HU), in LPS mm."""
    r = np.linalg.norm(p_lps - np.array([0.0, 0.0, 25.0]), axis=-1)
    return np.where(r < 4.0, 1000.0, np.where(r < 8.0, 0.0, -1000.0))


def strip_rescale(files, *, signed_hu: bool = False) -> np.ndarray:
    """Remove RescaleSlope/RescaleIntercept; ``signed_hu`` stores the HU themselves as int16. Returns HU (I, J, K)."""
    hu = []
    for f in files:
        ds = pydicom.dcmread(f)
        slice_hu = ds.pixel_array.astype(np.int32) * int(ds.RescaleSlope) + int(ds.RescaleIntercept)
        hu.append(slice_hu.T)
        if signed_hu:
            ds.PixelRepresentation = 1
            ds.PixelData = slice_hu.astype(np.int16).tobytes()
        del ds.RescaleSlope, ds.RescaleIntercept
        ds.save_as(f)
    return np.stack(hu, axis=2).astype(float)


def head_series(folder: Path) -> list[Path]:
    return make_series(folder, shape=(24, 24, 4), spacing=(1.0, 1.0, 2.0), origin=(-11.5, -11.5, 22.0),
                       field=head_hu)


def test_missing_rescale_on_raw_stored_values_is_an_error(tmp_path):
    files = head_series(tmp_path / "s")
    strip_rescale(files)  # stored values are HU + 1024 (24 .. 2024): not HU
    fix = r"rescale \[SLOPE, INTERCEPT\] \(--rescale SLOPE,INTERCEPT\)"
    with pytest.raises(CtsplatError, match=r"RescaleSlope.*" + fix) as err:
        read_dicom_series(tmp_path / "s")
    assert "\n" not in str(err.value) and "24 .. 2024" in str(err.value)
    assert_fails_cleanly(tmp_path / "s", tmp_path, "RescaleSlope")


def test_missing_rescale_with_explicit_option(tmp_path):
    files = head_series(tmp_path / "s")
    hu = strip_rescale(files)
    stack = read_dicom_series(tmp_path / "s", rescale=(1.0, -1024.0))
    np.testing.assert_array_equal(stack.data, hu)
    assert stack.source["rescale"] == {"from": "option", "slope": 1.0, "intercept": -1024.0,
                                       "n_slices_without_tags": 4}
    vol = ingest(tmp_path / "s", tmp_path / "v.nii.gz", {"grid": 8, "intensity": "hu"}, rescale=[1, -1024])
    assert vol.meta["source"]["rescale"]["from"] == "option"
    assert float(vol.data.min()) == pytest.approx(-1000.0, abs=1.0)


def test_header_rescale_slope_other_than_one(tmp_path):
    """Stored values become HU through slope and intercept from the header (scanners store 0.5 HU steps, or
    HU / 2 to fit a range): HU = stored × slope + intercept, slice by slice (slopes may differ between slices)."""
    files = head_series(tmp_path / "s")
    hu = strip_rescale(files)
    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)
        slope, intercept = (0.5, -1000.0) if k % 2 else (2.0, -1024.0)
        ds.PixelData = np.round((hu[:, :, k].T - intercept) / slope).astype(np.uint16).tobytes()
        ds.RescaleSlope, ds.RescaleIntercept = slope, intercept
        ds.save_as(f)
    stack = read_dicom_series(tmp_path / "s")
    np.testing.assert_array_equal(stack.data, hu)
    assert stack.source["rescale"]["from"] == "header"


def test_rescale_option_does_not_override_header_tags(tmp_path, caplog):
    make_series(tmp_path / "s")
    with caplog.at_level("WARNING", logger="ctsplat.formats.sources"):
        stack = read_dicom_series(tmp_path / "s", rescale=(2.0, 5.0))
    assert stack.source["rescale"] == {"from": "header", "slope": 1.0, "intercept": -1024.0,
                                       "n_slices_without_tags": 0, "option_unused": [2.0, 5.0]}
    assert "rescale [2.0, 5.0] was given, but every slice" in caplog.text  # reported, not silently dropped
    np.testing.assert_array_equal(stack.data, read_dicom_series(tmp_path / "s").data)


def test_missing_rescale_on_values_that_already_are_hu_is_accepted_and_recorded(tmp_path, caplog):
    files = head_series(tmp_path / "s")
    hu = strip_rescale(files, signed_hu=True)
    with caplog.at_level(logging.WARNING, logger="ctsplat.formats.sources"):
        stack = read_dicom_series(tmp_path / "s")
    np.testing.assert_array_equal(stack.data, hu)
    assert stack.source["rescale"]["from"] == "assumed_hu"
    assert "RescaleSlope" in caplog.text


def test_rescale_is_refused_for_non_dicom_input(tmp_path):
    path = tmp_path / "v.nii.gz"
    nib.save(nib.Nifti1Image(np.full((4, 4, 4), -1000, np.float32), np.eye(4)), str(path))
    with pytest.raises(CtsplatError, match="rescale applies to DICOM"):
        read_source(path, rescale=(1.0, 0.0))


def test_cli_ingest_rescale_flag(tmp_path, capsys):
    from ctsplat.cli import main

    strip_rescale(head_series(tmp_path / "s"))
    out = tmp_path / "o" / "v.nii.gz"
    assert main(["ingest", str(tmp_path / "s"), str(out), "--grid", "8"]) == 2
    assert "--rescale" in capsys.readouterr().err and not out.exists()
    assert main(["ingest", str(tmp_path / "s"), str(out), "--grid", "8", "--rescale", "1,-1024"]) == 0
    assert out.exists()


# ------------------------------------------------------------------------------------------ data quality


def test_missing_slices_gap_warns_with_size_and_place_and_is_recorded(tmp_path, caplog):
    """A 9 mm gap in a 1.5 mm series (5 slices lost) is interpolated, but warned about and kept in volume.json."""
    positions = [1.5 * k for k in range(20) if not 8 <= k <= 12]  # 10.5 mm -> 19.5 mm: a 9 mm gap
    make_series(tmp_path / "s", shape=(8, 6, len(positions)), spacing=(1.5, 2.0, 1.5), positions=positions)
    out = tmp_path / "out" / "volume.nii.gz"
    with caplog.at_level(logging.WARNING, logger="ctsplat"), pytest.warns(SliceGapWarning) as rec:
        vol = ingest(tmp_path / "s", out, {"grid": 8})
    with pytest.warns(SliceGapWarning):
        stack = read_dicom_series(tmp_path / "s")  # positions along the normal, as named in the warning
    lo, hi = stack.positions_mm[7], stack.positions_mm[8]
    assert hi - lo == pytest.approx(9.0)
    for msg in [str(w.message) for w in rec] + [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]:
        assert "9 mm between slices 7 and 8" in msg, msg
        assert f"at {lo:g} and {hi:g} mm" in msg and "spacing 1.5 mm" in msg and "~5 slice(s) missing" in msg
    assert any(r.levelname == "WARNING" and "gap" in r.getMessage() for r in caplog.records)
    gaps = [{"between_slices": [7, 8], "positions_mm": [lo, hi], "gap_mm": 9.0, "approx_missing_slices": 5}]
    assert vol.meta["source"]["missing_slice_gaps"] == gaps
    on_disk = json.loads((out.parent / "volume.json").read_text())["source"]
    assert on_disk["missing_slice_gaps"] == gaps and on_disk["nominal_slice_gap_mm"] == 1.5


def test_regular_and_slightly_uneven_spacing_do_not_warn(tmp_path):
    make_series(tmp_path / "a")
    make_series(tmp_path / "b", positions=[0.0, 2.5, 5.0, 6.0, 9.5])  # one 1.0 and one 3.5 mm step: not missing
    with warnings.catch_warnings():
        warnings.simplefilter("error", SliceGapWarning)
        for d in ("a", "b"):
            assert read_dicom_series(tmp_path / d).source["missing_slice_gaps"] == []


def test_many_gaps_are_counted_in_one_warning(tmp_path):
    positions = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]
    for _ in range(7):  # seven 3 mm holes in a 1 mm series
        positions.append(positions[-1] + 3.0)
        positions.append(positions[-1] + 1.0)
    make_series(tmp_path / "s", shape=(4, 4, len(positions)), positions=positions)
    with pytest.warns(SliceGapWarning) as rec:
        stack = read_dicom_series(tmp_path / "s")
    assert len(rec) == 1 and "has 7 gap(s)" in str(rec[0].message) and "and 2 more" in str(rec[0].message)
    assert len(stack.source["missing_slice_gaps"]) == 7


def test_uid_hashes_need_the_private_key(tmp_path, monkeypatch):
    """The ids are keyed by a private random key made on first use (mode 0600), stable for its owner; without the
    key, a reader of the outputs cannot test candidate UIDs against them."""
    import hashlib
    import stat

    from ctsplat.formats.sources import DEID_KEY_ENV, deid_key

    uid = "1.3.12.2.1107.5.1.1.20707.20020604103714064.2"
    monkeypatch.delenv(DEID_KEY_ENV, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "a"))
    first = salted_hash(uid)
    key_file = tmp_path / "a" / "ctsplat" / "deid_key"
    assert stat.S_IMODE(key_file.stat().st_mode) == 0o600 and len(key_file.read_bytes()) == 32
    assert salted_hash(uid) == first and deid_key() == key_file.read_bytes()  # the same key on every call
    # the public salt of the code no longer reproduces the id
    assert first != hashlib.sha256(f"ctsplat-deid-v1:{uid}".encode()).hexdigest()[:16]
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "b"))
    assert salted_hash(uid) != first  # another user's key, another id
    monkeypatch.setenv(DEID_KEY_ENV, "site secret")
    with pytest.raises(CtsplatError, match="CTSPLAT_DEID_SALT is too short \\(11 bytes\\)"):
        salted_hash(uid)  # eleven characters are found by trying them all
    monkeypatch.setenv(DEID_KEY_ENV, "site secret 4f1c9a0e")
    shared = salted_hash(uid)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "a"))
    assert salted_hash(uid) == shared  # one private value set on several machines: the same ids
    monkeypatch.delenv(DEID_KEY_ENV)
    key_file.write_bytes(b"short")
    with pytest.raises(CtsplatError, match="too short"):
        salted_hash(uid)


def test_workflow_stores_a_series_uid_selector_as_its_id():
    from ctsplat.formats.sources import outputs_selector

    uid = "1.2.840.113619.2.55.3.604688119.969.1268071029.320"
    assert outputs_selector(uid) == salted_hash(uid) and outputs_selector(f" {uid} ") == salted_hash(uid)
    assert outputs_selector("7") == "7" and outputs_selector("a1b2c3d4e5f60718") == "a1b2c3d4e5f60718"
    # a UID copied with its wrapping (a DICOM dump's brackets, quotes, a final dot) is a UID all the same, and any
    # other text is stored only as its hash
    for wrapped in (f"[{uid}]", f"'{uid}'", f'"{uid}"', f"{uid}.", f" <{uid}> "):
        assert outputs_selector(wrapped) == salted_hash(uid), wrapped
    assert outputs_selector("Doe^Jane head") == salted_hash("Doe^Jane head")


@pytest.mark.parametrize("with_range", [False, True])
def test_pixel_padding_takes_the_series_smallest_measured_value(tmp_path, with_range):
    # the padding outside the field of view holds no measurement: as a value (-3024 HU and the like) it would be
    # blurred into the edge voxels and enlarge a body mask
    files = make_series(tmp_path / "s", shape=(8, 6, 5))
    measured = []
    for f in files:
        ds = pydicom.dcmread(f)
        px = ds.pixel_array.copy()
        signed = int(ds.PixelRepresentation) == 1
        measured.append(px[1:].astype(float) * float(ds.RescaleSlope) + float(ds.RescaleIntercept))
        pad = int(px.min()) - 40 if signed else 0
        px[0, :] = pad  # the first row of every slice is padding
        if with_range:
            px[0, 0] = pad + 3  # within PixelPaddingValue .. PixelPaddingRangeLimit
            ds.add_new(0x00280121, "SS" if signed else "US", pad + 5)
        ds.add_new(0x00280120, "SS" if signed else "US", pad)
        ds.PixelData = px.astype(px.dtype).tobytes()
        ds.save_as(f)
    stack = read_dicom_series(tmp_path / "s")
    info = stack.source["pixel_padding"]
    fill = min(float(m.min()) for m in measured)
    assert info["n_pixels"] == 5 * 8 and info["filled_with"] == pytest.approx(fill)
    assert (info["range_limit"] - info["value"]) == (5 if with_range else 0)
    np.testing.assert_allclose(stack.data[:, 0, :], fill)  # values.T: the first row is j == 0
    for k, m in enumerate(measured):
        np.testing.assert_allclose(stack.data[:, 1:, k], m.T)
    assert read_dicom_series(tmp_path / "s").source["pixel_padding"] == info  # deterministic
    # padding pixels in some slices only (every slice carries the tag): the others are measured throughout
    for f in files[1::2]:
        ds = pydicom.dcmread(f)
        px = ds.pixel_array.copy()
        px[0, :] = px[1, :]
        ds.PixelData = px.tobytes()
        ds.save_as(f)
    assert read_dicom_series(tmp_path / "s").source["pixel_padding"]["n_pixels"] == 3 * 8


@pytest.mark.parametrize(("unit", "to_mm"), [("mm", 1.0), ("unknown", 1.0), ("micron", 1e-3), ("meter", 1e3)])
def test_nifti_spatial_unit_is_converted_to_mm(tmp_path, unit, to_mm):
    """A NIfTI in micrometres or metres is a volume of that size in mm, not one a thousand times off."""
    affine = np.diag([500.0, 400.0, 300.0, 1.0])
    affine[:3, 3] = [-1000.0, 20.0, 5.0]
    img = nib.Nifti1Image(np.arange(6 * 5 * 4, dtype=np.float32).reshape(6, 5, 4), affine)
    img.header.set_xyzt_units(unit)
    nib.save(img, tmp_path / "v.nii.gz")
    stack = read_source(tmp_path / "v.nii.gz")
    np.testing.assert_allclose(stack.spacing_ij, np.array([500.0, 400.0]) * to_mm)
    np.testing.assert_allclose(stack.origins[0], affine[:3, 3] * to_mm)
    np.testing.assert_allclose(stack.origins[1] - stack.origins[0], [0.0, 0.0, 300.0 * to_mm])
    assert stack.source["spatial_unit"] == unit
    np.testing.assert_allclose(stack.source["zooms_mm"], np.array([500.0, 400.0, 300.0]) * to_mm)


def test_complex_scans_are_refused_not_cut_to_their_real_part(tmp_path):
    data = (np.ones((4, 4, 4)) + 2j * np.ones((4, 4, 4))).astype(np.complex64)
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "c.nii.gz")
    with pytest.raises(CtsplatError, match=r"c\.nii\.gz holds complex values \(complex64\); ingest needs real"):
        read_nifti(tmp_path / "c.nii.gz")
    tifffile.imwrite(tmp_path / "c.tif", data, photometric="minisblack")
    with pytest.raises(CtsplatError, match=r"c\.tif holds complex values \(complex64\); ingest needs real"):
        read_tiff_stack(tmp_path / "c.tif", 1.0)


def test_nifti_without_an_orientation_is_refused(tmp_path):
    """Neither sform nor qform: nibabel falls back to an x-mirrored guess; refused instead of ingested mirrored."""
    data = np.zeros((6, 5, 4), np.float32)
    header = nib.Nifti1Header()
    header["pixdim"][1:4] = 1.0
    _write_nifti_as_is(tmp_path / "bare.nii", header, data)
    assert_fails_cleanly(tmp_path / "bare.nii", tmp_path, r"neither an sform nor a qform \(both codes 0\)")
