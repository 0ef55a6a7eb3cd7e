"""The analytic Shepp–Logan phantom, its rasteriser, and its DICOM series through the real ingestion path."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest

from ctsplat.cli import main
from ctsplat.formats.sources import read_dicom_series
from ctsplat.formats.volume import load_volume
from ctsplat.phantom import (
    Ellipsoid,
    load_phantom_ellipsoids,
    rasterize,
    relative_attenuation,
    shepp_logan_ellipsoids,
    write_phantom_dicom,
)
from ctsplat.utils import CtsplatError
from ctsplat.volume import ingest


def voxel_centres(affine, shape):
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).astype(float)
    return idx @ affine[:3, :3].T + affine[:3, 3]


@pytest.fixture(scope="module")
def phantom_dir(tmp_path_factory):
    return write_phantom_dicom(tmp_path_factory.mktemp("ph") / "dicom", size=48, seed=3)


def test_ellipsoid_definition_matches_docstring():
    e = shepp_logan_ellipsoids(beads=False)[2]  # rotated ventricle (phi = 108 deg)
    np.testing.assert_allclose(e.rotation @ e.rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(e.rotation) == pytest.approx(1.0)
    # the end points of each principal axis lie on the surface; slightly beyond is outside
    for m in range(3):
        tip = e.centre_mm + e.semi_axes_mm[m] * e.rotation[:, m]
        assert e.contains(e.centre_mm + 0.999 * (tip - e.centre_mm))
        assert not e.contains(e.centre_mm + 1.001 * (tip - e.centre_mm))
    # quadratic form agrees with contains() on random points
    rng = np.random.default_rng(0)
    pts = e.centre_mm + rng.normal(0, 30, (2000, 3))
    d = pts - e.centre_mm
    q = np.einsum("ni,ij,nj->n", d, e.quadratic_form(), d)
    np.testing.assert_array_equal(q <= 1.0, e.contains(pts))
    lo, hi = e.bounding_box()
    inside = pts[e.contains(pts)]
    assert np.all(inside >= lo - 1e-9) and np.all(inside <= hi + 1e-9)


def test_phantom_is_head_sized_and_physical():
    ells = shepp_logan_ellipsoids(beads=False)
    skull = ells[0]
    size = 2 * skull.semi_axes_mm
    assert 140 < size.min() and size.max() < 220 and 190 < size.max()  # a ~200 mm adult head
    r = relative_attenuation(np.array([[0.0, 0.0, 0.0], [0, 0, 500.0], [0, skull.semi_axes_mm[1] - 2, 0]]), ells)
    assert r[1] == 0.0  # air outside
    assert r[2] == pytest.approx(2.0)  # skull shell = 2 x water (1000 HU)
    assert 0.98 < r[0] < 1.06  # brain-like near water


def test_beads_seeded_inside_brain_and_separated():
    a = shepp_logan_ellipsoids(seed=1)
    b = shepp_logan_ellipsoids(seed=1)
    c = shepp_logan_ellipsoids(seed=2)
    beads = [e for e in a if e.name.startswith("bead")]
    assert len(beads) == 12
    np.testing.assert_array_equal([e.centre_mm for e in beads], [e.centre_mm for e in b if e.name.startswith("bead")])
    assert not np.allclose([e.centre_mm for e in beads], [e.centre_mm for e in c if e.name.startswith("bead")])
    brain = a[1]
    centres = np.array([e.centre_mm for e in beads])
    assert brain.contains(centres).all()
    dists = np.linalg.norm(centres[:, None] - centres[None], axis=-1) + np.eye(len(centres)) * 1e9
    assert dists.min() >= 6 * beads[0].semi_axes_mm[0]


def test_rasterize_equals_point_sampling_and_volume_integrals():
    ells = shepp_logan_ellipsoids(seed=0)
    aff = np.array([[0, -7.0, 0, 110], [6.5, 0, 0, -100], [0, 0, 7.5, -115], [0, 0, 0, 1]])  # permuted, flipped
    shape = (32, 30, 31)
    r1 = rasterize(ells, shape, aff, supersample=1)
    direct = relative_attenuation(voxel_centres(aff, shape), ells)
    np.testing.assert_allclose(r1, direct, atol=1e-6)
    # supersampled voxel averages integrate to the analytic ellipsoid volumes: Σ v · 4/3 π abc
    grid = np.diag([2.0, 2.0, 2.0, 1.0])
    grid[:3, 3] = -119.0
    r4 = rasterize(ells, (120, 120, 120), grid, supersample=2)
    total = r4.sum() * 8.0  # mm³
    analytic = sum(e.value * 4 / 3 * np.pi * np.prod(e.semi_axes_mm) for e in ells)
    assert total == pytest.approx(analytic, rel=2e-3)


def test_phantom_dicom_is_a_real_ct_series(phantom_dir):
    files = sorted(phantom_dir.glob("*.dcm"))
    assert len(files) == 48
    ds = pydicom.dcmread(files[0])
    assert ds.Modality == "CT" and ds.SOPClassUID.name == "CT Image Storage"
    assert [float(x) for x in ds.ImageOrientationPatient] == [1, 0, 0, 0, 1, 0]
    assert float(ds.PixelSpacing[0]) == pytest.approx(240 / 48)
    zs = sorted(float(pydicom.dcmread(f, stop_before_pixels=True).ImagePositionPatient[2]) for f in files)
    np.testing.assert_allclose(np.diff(zs), 5.0, atol=1e-5)
    assert zs[0] == pytest.approx(-zs[-1])  # centred on the world origin
    stack = read_dicom_series(phantom_dir)
    assert stack.data.min() == -1000.0  # air
    assert stack.data.max() > 1200.0  # beads (partial-volumed at 5 mm voxels) are denser than the 1000 HU skull


def test_ingested_phantom_lines_up_with_ellipsoids_in_world_mm(phantom_dir, tmp_path):
    """The analytic ellipsoids, evaluated at the ingested NIfTI's own voxel centres, reproduce its HU."""
    ells = load_phantom_ellipsoids(phantom_dir)
    assert len(ells) == 22
    out = tmp_path / "volume.nii.gz"
    ingest(phantom_dir, out, {"grid": None, "intensity": "hu"})
    vol = load_volume(out)
    expected = 1000.0 * (rasterize(ells, vol.shape, vol.affine, supersample=2) - 1.0)
    np.testing.assert_allclose(vol.data, expected, atol=0.5 + 1e-3)  # stored rounded to whole HU
    # a one-voxel mistake (e.g. a missing LPS->RAS flip) would be visible: the phantom is not symmetric
    flipped = np.flip(expected, axis=1)
    assert np.abs(vol.data - flipped).max() > 100


def test_default_ingest_of_phantom_matches_documented_normalisation(phantom_dir, tmp_path):
    vol = ingest(phantom_dir, tmp_path / "v.nii.gz", {"grid": 32})
    ells = load_phantom_ellipsoids(phantom_dir)
    r = relative_attenuation(np.zeros((1, 3)), ells)[0]  # phantom centre, well inside brain
    centre_idx = np.linalg.solve(vol.affine[:3, :3], -vol.affine[:3, 3])
    value = vol.data[tuple(np.round(centre_idx).astype(int))]
    # normalised = mu / mu_scale = r mu_water / (mu_water (1 + hu_max/1000))
    assert value == pytest.approx(r / 4.0, abs=0.01)
    assert vol.mu_scale_per_mm == pytest.approx(0.019 * 4.0)


def test_write_replaces_atomically_and_cleans_up_on_failure(tmp_path, monkeypatch):
    out = tmp_path / "ph"
    write_phantom_dicom(out, size=16, beads=False)
    first = sorted(p.name for p in out.iterdir())
    write_phantom_dicom(out, size=16, beads=False)
    assert sorted(p.name for p in out.iterdir()) == first

    import ctsplat.phantom as ph

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(ph, "write_dicom_series", boom)
    with pytest.raises(OSError):
        write_phantom_dicom(tmp_path / "new", size=16)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ph"]  # no temp folders, nothing half-written
    with pytest.raises(CtsplatError, match="size"):
        write_phantom_dicom(tmp_path / "bad", size=3)
    for fov in (0.0, float("inf"), float("nan")):
        with pytest.raises(CtsplatError, match="fov_mm must be a finite number > 0"):
            write_phantom_dicom(tmp_path / "bad", size=16, fov_mm=fov)
    assert not (tmp_path / "bad").exists()


def test_ellipsoid_dict_roundtrip():
    e = shepp_logan_ellipsoids(beads=False)[3]
    f = Ellipsoid.from_dict(e.to_dict())
    np.testing.assert_array_equal(f.rotation, e.rotation)
    assert f.value == e.value and f.name == e.name


def test_cli_phantom_then_ingest(tmp_path, capsys):
    assert main(["phantom", str(tmp_path / "dicom"), "--size", "16", "--no-beads"]) == 0
    assert len(list((tmp_path / "dicom").glob("*.dcm"))) == 16
    assert main(["ingest", str(tmp_path / "dicom"), str(tmp_path / "v.nii.gz"), "--grid", "16"]) == 0
    assert "volume_id" in capsys.readouterr().out
    assert load_volume(tmp_path / "v.nii.gz").shape == (16, 16, 16)


def _tree(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_phantom_never_deletes_a_folder_it_did_not_write(tmp_path, capsys):
    out = tmp_path / "mine"
    (out / "sub").mkdir(parents=True)
    (out / "notes.txt").write_text("keep me")
    (out / "sub" / "data.bin").write_bytes(b"\0")
    before = _tree(tmp_path)
    with pytest.raises(CtsplatError, match="--force"):
        write_phantom_dicom(out, size=8, beads=False)
    assert _tree(tmp_path) == before and (out / "notes.txt").read_text() == "keep me"
    assert main(["phantom", str(out), "--size", "8", "--no-beads"]) == 2
    assert "--force" in capsys.readouterr().err
    assert _tree(tmp_path) == before


def test_phantom_refuses_a_patient_series_folder(tmp_path):
    from ctsplat.formats.sources import write_dicom_series

    out = tmp_path / "patient"
    write_dicom_series(np.zeros((8, 8, 3)), out, spacing_mm=(1, 1, 1), origin_lps=(0, 0, 0), filename="IM{k}")
    before = _tree(tmp_path)
    with pytest.raises(CtsplatError, match="not a previous phantom output"):
        write_phantom_dicom(out, size=8, beads=False)
    assert _tree(tmp_path) == before


def test_phantom_force_writes_beside_other_files_and_keeps_them(tmp_path, capsys):
    out = tmp_path / "mixed"
    (out / "sub").mkdir(parents=True)
    (out / "notes.txt").write_text("keep me")
    assert main(["phantom", str(out), "--size", "8", "--no-beads", "--force"]) == 0
    assert (out / "notes.txt").read_text() == "keep me" and (out / "sub").is_dir()
    assert len(list(out.glob("slice_*.dcm"))) == 8 and load_phantom_ellipsoids(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mixed"]  # no temp or trash folders beside it
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_phantom_into_current_folder_and_again(tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main(["phantom", ".", "--size", "8", "--no-beads"]) == 0
    first = _tree(work)
    assert len([n for n in first if n.endswith(".dcm")]) == 8 and "phantom.json" in first
    assert main(["phantom", ".", "--size", "8", "--no-beads"]) == 0  # a previous phantom output: replaced
    assert _tree(work) == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"]  # no ..*.old / .tmp folders left
    assert read_dicom_series(work).data.shape == (8, 8, 8)


def test_previous_phantom_output_is_replaced_without_stale_slices(tmp_path):
    out = tmp_path / "ph"
    write_phantom_dicom(out, size=12, beads=False)
    write_phantom_dicom(out, size=8, beads=False)
    assert len(list(out.glob("*.dcm"))) == 8
    assert read_dicom_series(out).data.shape == (8, 8, 8)
    (tmp_path / "empty").mkdir()
    write_phantom_dicom(tmp_path / "empty", size=8, beads=False)  # an empty folder is fine without force
    assert len(list((tmp_path / "empty").glob("*.dcm"))) == 8
    (tmp_path / "file").write_text("x")
    with pytest.raises(CtsplatError, match="not a folder"):
        write_phantom_dicom(tmp_path / "file", size=8)
