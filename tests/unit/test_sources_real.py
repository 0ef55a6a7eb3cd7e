"""Done-when checks on the real scans in ../shared/data (skipped with a reason when absent)."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest

from ctsplat.formats.sources import LPS_TO_RAS, read_dicom_series
from ctsplat.formats.volume import load_volume
from ctsplat.volume import ingest


def headers(folder: Path) -> list[tuple[Path, pydicom.Dataset]]:
    return [(p, pydicom.dcmread(p, stop_before_pixels=True)) for p in sorted(folder.iterdir())]


def z_sorted_files(folder: Path) -> list[Path]:
    hs = headers(folder)
    return [p for p, ds in sorted(hs, key=lambda t: float(t[1].ImagePositionPatient[2]))]


@pytest.fixture(scope="module")
def head_stack(ct0051_head):
    return read_dicom_series(ct0051_head)


@pytest.fixture(scope="module")
def head_ingest(head_stack, tmp_path_factory):
    out = tmp_path_factory.mktemp("head") / "volume.nii.gz"
    vol = ingest(head_stack, out, {"voxel_size_mm": 2.0})  # the stack read from ct0051_head (saves a re-read)
    return out, vol


@pytest.fixture(scope="module")
def head_subset(ct0051_head, tmp_path_factory):
    """12 evenly spaced slices (every 9th) of ct0051 plus the last one (after the odd 1.0 mm gap)."""
    files = z_sorted_files(ct0051_head)
    pick = files[0:100:9] + [files[-1]]
    d = tmp_path_factory.mktemp("subset")
    for p in pick:
        shutil.copy(p, d / p.name)
    return d


def test_head_hu_range_and_spacing_from_positions(head_stack):
    assert head_stack.data.shape == (512, 512, 108)
    assert head_stack.data.min() == -1024.0 and head_stack.data.max() == 3033.0  # HU before any mapping
    assert head_stack.source["slice_gaps_mm"] == [1.0, 1.5]  # from IPP, not SliceThickness (2.0)
    assert head_stack.source["uniform_spacing"] is False
    np.testing.assert_allclose(np.diff(head_stack.positions_mm).max(), 1.5, atol=1e-4)


def test_head_extent_and_orientation(head_ingest, head_stack):
    out, vol = head_ingest
    # physical coverage of the source: 512 x 0.4785 mm in-plane, 160 mm between first and last slice
    np.testing.assert_allclose(np.asarray(head_stack.spacing_ij) * 512, 245.0, atol=0.1)
    assert head_stack.positions_mm[-1] - head_stack.positions_mm[0] == pytest.approx(160.0, abs=0.01)
    ext = load_volume(out).extent_mm()
    np.testing.assert_allclose(ext[:2], 245.0, atol=2.5)
    assert ext[2] == pytest.approx(160.0, abs=3.5)
    np.testing.assert_allclose(vol.spacing_mm, 2.0)
    assert np.all(np.diag(vol.affine[:3, :3]) > 0)  # RAS-closest axis order
    assert vol.meta["source_value_range"] == [-1024.0, 3033.0]


def test_head_nifti_affine_maps_voxels_to_image_positions(head_subset, tmp_path):
    """Voxel centres of the written NIfTI land on ImagePositionPatient (RAS-flipped) of each slice,
    with the DICOM pixel's HU there."""
    out = tmp_path / "native.nii.gz"
    ingest(head_subset, out, {"voxel_size_mm": None, "grid": None, "intensity": "hu"})
    vol = load_volume(out)
    inv = np.linalg.inv(vol.affine)
    uniform, off_grid = 0, 0
    for p in sorted(head_subset.iterdir()):
        ds = pydicom.dcmread(p)
        hu = ds.pixel_array.astype(float) * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        ipp = np.asarray(ds.ImagePositionPatient, float)
        iop = np.asarray(ds.ImageOrientationPatient, float)
        row, col = iop[:3], iop[3:]
        dr, dc = (float(x) for x in ds.PixelSpacing)
        for r, c in [(0, 0), (256, 200), (300, 311), (511, 17)]:
            world_lps = ipp + c * dc * row + r * dr * col
            idx = inv[:3, :3] @ (LPS_TO_RAS @ world_lps) + inv[:3, 3]
            np.testing.assert_allclose(idx[:2], np.round(idx[:2]), atol=1e-3)  # in-plane: always on a voxel
            if abs(idx[2] - round(idx[2])) < 1e-3:
                assert vol.data[tuple(np.round(idx).astype(int))] == pytest.approx(hu[r, c], abs=1e-2)
                uniform += 1
            else:
                off_grid += 1
    assert uniform == 4 * 12  # the 12 evenly spaced slices sit exactly on voxel centres
    assert off_grid == 4  # the last slice, 1.0 mm after its neighbour, falls between two output slices


def test_head_same_volume_for_shuffled_renamed_files(head_subset, tmp_path):
    ref = ingest(head_subset, tmp_path / "ref" / "v.nii.gz", {"grid": 24})
    files = sorted(head_subset.iterdir())
    for seed in (1, 2):
        rng = np.random.default_rng(seed)
        d = tmp_path / f"shuffled{seed}"
        for n, m in enumerate(rng.permutation(len(files))):
            sub = d / f"sub{n % 3}"  # also spread over sub-folders (recursive walk)
            sub.mkdir(parents=True, exist_ok=True)
            shutil.copy(files[m], sub / f"{rng.integers(1e9):09d}")
        vol = ingest(d, tmp_path / f"out{seed}" / "v.nii.gz", {"grid": 24})
        np.testing.assert_array_equal(vol.data, ref.data)
        np.testing.assert_array_equal(vol.affine, ref.affine)
        assert vol.volume_id == ref.volume_id


def test_head_outputs_carry_no_identifiers(ct0051_head, head_ingest):
    out, _ = head_ingest
    secrets: set[str] = set()
    for _, ds in headers(ct0051_head)[:5]:
        for key in ("PatientID", "PatientName", "PatientBirthDate"):
            value = str(ds.get(key, "") or "")
            if value:
                secrets.add(value)
        for key in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID"):
            secrets.add(str(ds.get(key)))
        bd = str(ds.get("PatientBirthDate", "") or "")
        if len(bd) == 8:
            secrets.add(f"{bd[:4]}-{bd[4:6]}-{bd[6:]}")
    assert len(secrets) >= 5  # the test data does carry identifiers
    files = [p for p in out.parent.rglob("*") if p.is_file()]
    assert {p.name for p in files} == {"volume.nii.gz", "volume.json"}
    for p in files:
        blob = p.read_bytes()
        if p.name.endswith(".gz"):
            blob = gzip.decompress(blob)
        text = blob.decode("latin-1")
        for s in secrets:
            assert s not in text, f"{s!r} found in {p.name}"


def test_j2k_series_ingests(totalseg_j2k, tmp_path):
    pytest.importorskip("openjpeg")
    vol = ingest(totalseg_j2k, tmp_path / "v.nii.gz", {"grid": 32})
    src = vol.meta["source"]
    assert "JPEG 2000" in src["transfer_syntax"]
    assert src["n_slices"] == 20 and src["slice_gaps_mm"] == [2.0]
    assert vol.meta["source_value_range"] == [-1024.0, 1839.0]
    assert vol.shape == (32, 32, 32) and 0.0 <= vol.data.min() and vol.data.max() <= 1.0
