"""Preprocessing steps, ingest provenance/atomicity/determinism and the ``ctsplat ingest`` CLI (synthetic data)."""

from __future__ import annotations

import json
import os

import nibabel as nib
import numpy as np
import pytest
from scipy import ndimage

from ctsplat.cli import main
from ctsplat.formats.sources import SliceStack
from ctsplat.formats.volume import Volume, compute_volume_id, json_path_for, load_volume, save_volume
from ctsplat.utils import CtsplatError
from ctsplat.volume import (
    PREPROCESSING_DEFAULTS,
    WINDOW_PRESETS,
    apply_window,
    body_mask,
    denoise,
    hu_to_attenuation,
    ingest,
    preprocessing_in_effect,
)


def nifti_input(tmp_path, data, spacing=(1.0, 1.0, 1.0), name="scan.nii.gz"):
    aff = np.diag([*spacing, 1.0])
    aff[:3, 3] = [-10.0, 5.0, 30.0]
    path = tmp_path / name
    nib.save(nib.Nifti1Image(np.asarray(data, np.float32), aff), path)
    return path


def head_like(n=24, seed=0):
    """Air (-1000) box with a noisy tissue ball (40 HU), an air cavity inside, and a separate 'table'."""
    rng = np.random.default_rng(seed)
    x = np.stack(np.meshgrid(*[np.arange(n) - (n - 1) / 2] * 3, indexing="ij"), -1)
    r = np.linalg.norm(x, axis=-1)
    hu = np.full((n, n, n), -1000.0)
    ball = r < n * 0.32
    hu[ball] = 40.0
    hu[np.linalg.norm(x - [2, 0, 0], axis=-1) < 2.5] = -1000.0  # cavity inside the ball
    hu[:, -2:, :] = 200.0  # table slab, not touching the ball
    hu += rng.normal(0, 20, hu.shape)
    return hu, ball


# ------------------------------------------------------------------------------------------ intensity


def test_hu_to_attenuation_formula_and_clipping():
    hu = np.array([-1024.0, -1000.0, 0.0, 1000.0, 3000.0, 3500.0])
    mu_w, hu_max = 0.0195, 3000.0
    norm, scale = hu_to_attenuation(hu, mu_w, hu_max)
    mu = mu_w * (1 + hu / 1000)  # independent restatement of mu = mu_water (1 + HU/1000)
    assert scale == pytest.approx(mu_w * 4.0)
    np.testing.assert_allclose(norm * scale, np.clip(mu, 0, scale), rtol=1e-6, atol=1e-9)
    assert norm.min() == 0.0 and norm.max() == 1.0 and norm.dtype == np.float32
    assert norm[2] * scale == pytest.approx(mu_w)  # water


@pytest.mark.parametrize("preset", list(WINDOW_PRESETS))
def test_window_presets(preset):
    level, width = WINDOW_PRESETS[preset]
    hu = np.array([level - width, level - width / 2, level, level + width / 4, level + width / 2, level + width])
    out = apply_window(hu, level, width)
    np.testing.assert_allclose(out, [0.0, 0.0, 0.5, 0.75, 1.0, 1.0], atol=1e-6)
    assert WINDOW_PRESETS["brain"] == (40.0, 80.0)


# ------------------------------------------------------------------------------------------ mask / denoise


def test_body_mask_keeps_body_fills_cavities_drops_table():
    hu, ball = head_like()
    m = body_mask(hu, "otsu")
    assert m[ball].all()  # ball incl. its internal cavity
    assert not m[:, -2:, :].any()  # table removed (not the largest component)
    assert m.sum() == pytest.approx(ball.sum(), rel=0.05)
    hull = body_mask(hu, "convex_hull")
    assert np.all(hull >= m) and hull.sum() >= m.sum()


def test_ingest_with_mask_sets_air_outside(tmp_path):
    hu, ball = head_like()
    vol = ingest(nifti_input(tmp_path, hu), tmp_path / "o" / "v.nii.gz", {"grid": None, "mask": "otsu"})
    assert vol.shape == hu.shape
    eroded = ndimage.binary_erosion(ball, iterations=1)
    outside = ~ndimage.binary_dilation(ball, iterations=1)
    assert np.all(vol.data[outside] == 0.0)  # air (and the table) -> exactly 0 attenuation
    tissue = vol.data[eroded & (hu > -500)]
    np.testing.assert_allclose(np.median(tissue), 1040 / 4000, atol=0.01)  # 40 HU through the default mapping
    assert [s["step"] for s in vol.meta["steps"]] == ["read", "resample", "intensity", "mask"]


@pytest.mark.parametrize("method,weight", [("tv", 0.05), ("bilateral", 0.1)])
def test_denoise_reduces_noise_keeps_edges(method, weight):
    rng = np.random.default_rng(1)
    clean = np.zeros((24, 24, 6), np.float32)
    clean[12:] = 0.5
    noisy = clean + rng.normal(0, 0.03, clean.shape).astype(np.float32)
    out = denoise(noisy, method, weight)
    flat = (slice(2, 9), slice(None), slice(None))
    assert out[flat].std() < 0.5 * noisy[flat].std()
    np.testing.assert_allclose(out[flat].mean(), 0.0, atol=0.01)
    profile = out.mean(axis=(1, 2))
    assert profile[10] < 0.15 and profile[13] > 0.35  # the step stays at the same place and stays sharp


@pytest.mark.parametrize("method", ["tv", "bilateral"])
def test_denoise_weight_smooths_alike_in_every_intensity_unit(tmp_path, method):
    """denoise_weight is a fraction of the mapping's full scale: the same noisy scan ingested as normalised
    attenuation, as mu (1/mm) and as HU comes out the same up to the unit conversion, instead of smoothing mu
    (values ~ 0.02) flat and HU (values ~ 1000) not at all."""
    rng = np.random.default_rng(2)
    hu, _ = head_like(16)
    hu = hu + rng.normal(0, 60, hu.shape).astype(np.float32)
    src = nifti_input(tmp_path, np.clip(hu, -1000, None))
    base = {"grid": 16, "denoise": method, "denoise_weight": 0.05}
    att = ingest(src, tmp_path / "a" / "v.nii.gz", {**base, "intensity": "attenuation"}).data
    mu = ingest(src, tmp_path / "m" / "v.nii.gz", {**base, "intensity": "mu"}).data
    raw = ingest(src, tmp_path / "h" / "v.nii.gz", {**base, "intensity": "hu"}).data
    plain = ingest(src, tmp_path / "p" / "v.nii.gz", {"grid": 16, "intensity": "attenuation"}).data
    mu_top = 0.019 * 4.0  # mu at the default hu_max, 3000 HU
    np.testing.assert_allclose(mu / mu_top, att, atol=1e-4)
    # HU are not clipped at hu_max or air: compare where the attenuation mapping is linear
    inside = (plain > 0.05) & (plain < 0.95)
    np.testing.assert_allclose(((raw + 1000.0) / 4000.0)[inside], att[inside], atol=0.02)
    assert np.abs(att - plain)[inside].mean() > 0.003  # it did smooth


# ------------------------------------------------------------------------------------------ ingest output


def test_ingest_writes_nifti_and_provenance(tmp_path):
    hu, _ = head_like()
    out = tmp_path / "res" / "volume.nii.gz"
    vol = ingest(nifti_input(tmp_path, hu, spacing=(1.0, 1.0, 2.0)), out, {"grid": 16})
    meta = json.loads(json_path_for(out).read_text())
    loaded = load_volume(out)
    np.testing.assert_array_equal(loaded.data, vol.data)
    np.testing.assert_array_equal(loaded.affine, vol.affine)
    assert meta["volume_id"] == compute_volume_id(loaded.data, loaded.affine) == loaded.volume_id
    assert loaded.mu_scale_per_mm == pytest.approx(0.019 * 4.0)
    assert meta["intensity"]["mu_scale_per_mm"] == loaded.mu_scale_per_mm
    assert meta["shape"] == [16, 16, 16] and meta["preprocessing"]["grid"] == 16
    assert meta["source_value_range"] == [pytest.approx(float(hu.min()), abs=1e-3), pytest.approx(float(hu.max()),
                                                                                                   abs=1e-3)]
    assert 0.0 <= loaded.data.min() and loaded.data.max() <= 1.0
    img = nib.load(out)
    assert int(img.header["sform_code"]) == 1 and int(img.header["qform_code"]) == 1
    assert img.header.get_xyzt_units()[0] == "mm"
    np.testing.assert_allclose(img.header.get_best_affine(), vol.affine, atol=1e-4)
    # the largest extent is along k: 24 slices * 2 mm = 48 mm over 16 voxels -> 3 mm isotropic
    np.testing.assert_allclose(loaded.spacing_mm, 3.0)
    # centre of the grid is the centre of the scan's extent
    src_centre = np.array([-10.0, 5.0, 30.0]) + (np.array(hu.shape) - 1) / 2 * [1.0, 1.0, 2.0]
    np.testing.assert_allclose(loaded.center_mm(), src_centre, atol=1e-4)
    assert sorted(p.name for p in out.parent.iterdir()) == ["volume.json", "volume.nii.gz"]


def test_ingest_refuses_its_own_normalised_output_and_warns_on_values_that_are_not_hu(tmp_path, caplog):
    """Ingest reads NIfTI values as HU: a volume it wrote in normalised units (its volume.json beside it) would map
    onto water, one constant value, and is refused; one it wrote in HU is a scan again; another file whose values
    hold no air is ingested with a warning naming the range."""
    hu, _ = head_like()
    first = tmp_path / "first" / "volume.nii.gz"
    ingest(nifti_input(tmp_path, hu), first, {"grid": 12})
    again = tmp_path / "again" / "volume.nii.gz"
    with pytest.raises(CtsplatError, match="is a volume ingest already wrote .*intensity attenuation_normalised"):
        ingest(first, again, {"grid": 12})
    assert not again.parent.exists()
    in_hu = tmp_path / "hu" / "volume.nii.gz"
    ingest(nifti_input(tmp_path, hu), in_hu, {"grid": 12, "intensity": "hu"})
    caplog.clear()
    vol = ingest(in_hu, tmp_path / "from_hu" / "volume.nii.gz", {"grid": 12})
    assert vol.data.max() > vol.data.min() and "Hounsfield" not in caplog.text
    caplog.clear()
    ingest(nifti_input(tmp_path, hu / 1000.0 + 1.0, name="mu_like.nii.gz"), tmp_path / "mu" / "volume.nii.gz",
           {"grid": 12})
    lo, hi = float((hu / 1000.0 + 1.0).min()), float((hu / 1000.0 + 1.0).max())
    assert f"reads NIfTI values as Hounsfield units, but these ({lo:g} .. {hi:g}) hold no air" in caplog.text


def test_ingest_is_deterministic(tmp_path):
    hu, _ = head_like()
    src = nifti_input(tmp_path, hu)
    a = ingest(src, tmp_path / "a" / "v.nii.gz", {"grid": 12, "denoise": "tv"})
    b = ingest(src, tmp_path / "b" / "v.nii.gz", {"grid": 12, "denoise": "tv"})
    np.testing.assert_array_equal(a.data, b.data)
    assert a.volume_id == b.volume_id
    c = ingest(src, tmp_path / "c" / "v.nii.gz", {"grid": 12})
    assert c.volume_id != a.volume_id


def test_a_setting_that_does_nothing_changes_neither_the_volume_nor_its_record(tmp_path):
    """denoise_weight without denoise, window without intensity: window, grid beside voxel_size_mm: the same
    volume and the same volume.json as the defaults (the workflow compares the same form and reruns nothing)."""
    hu, _ = head_like()
    src = nifti_input(tmp_path, hu)
    base = {"grid": 12}
    inert = {"grid": 12, "denoise_weight": 0.3, "window": "bone"}
    a = ingest(src, tmp_path / "a" / "v.nii.gz", base)
    b = ingest(src, tmp_path / "b" / "v.nii.gz", inert)
    np.testing.assert_array_equal(a.data, b.data)
    meta = [json.loads(json_path_for(tmp_path / d / "v.nii.gz").read_text()) for d in "ab"]
    assert meta[0]["preprocessing"] == meta[1]["preprocessing"] == preprocessing_in_effect(inert)
    # the same keys in effect keep their values
    acting = preprocessing_in_effect({"denoise": "tv", "denoise_weight": 0.3, "intensity": "window", "window": "bone"})
    assert acting["denoise_weight"] == 0.3 and acting["window"] == "bone"
    assert preprocessing_in_effect({"voxel_size_mm": 2.0, "grid": 64})["grid"] == PREPROCESSING_DEFAULTS["grid"]
    assert preprocessing_in_effect({"intensity": "hu", "hu_max": 100.0})["hu_max"] == PREPROCESSING_DEFAULTS["hu_max"]
    assert preprocessing_in_effect({"intensity": "mu", "hu_max": 100.0})["hu_max"] == 100.0
    window = preprocessing_in_effect({"intensity": "window", "hu_max": 100.0, "mu_water_per_mm": 0.03})
    assert window["hu_max"] == PREPROCESSING_DEFAULTS["hu_max"] and window["mu_water_per_mm"] == 0.03
    # a setting that acts: another volume
    c = ingest(src, tmp_path / "c" / "v.nii.gz", {"grid": 12, "denoise": "tv", "denoise_weight": 0.3})
    assert c.volume_id != a.volume_id


def test_ingest_gives_the_same_volume_with_any_number_of_blas_threads(tmp_path):
    """The slice-normal resampling is a BLAS product, which rounds by how it splits the work among threads: the
    workflow (one thread per job) and the command line (all cores) must still write the same volume_id (the
    built-in phantom's DICOM series at 64³ differed in the last bits between 1 and 2 threads)."""
    import subprocess
    import sys

    code = "import sys; from ctsplat.cli import main; sys.exit(main(sys.argv[1:]))"
    subprocess.run([sys.executable, "-c", code, "phantom", str(tmp_path / "dicom")], check=True, capture_output=True)
    ids = []
    for threads in ("1", "2", "4"):
        env = {**os.environ, "OPENBLAS_NUM_THREADS": threads, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads}
        out = tmp_path / f"t{threads}" / "v.nii.gz"
        subprocess.run([sys.executable, "-c", code, "ingest", str(tmp_path / "dicom"), str(out), "--grid", "64"],
                       env=env, check=True, capture_output=True)
        ids.append(json.loads(json_path_for(out).read_text())["volume_id"])
    assert ids[0] == ids[1] == ids[2], ids


def test_intensity_modes_record_mu_scale(tmp_path):
    hu, _ = head_like()
    src = nifti_input(tmp_path, hu)
    w = ingest(src, tmp_path / "w" / "v.nii.gz", {"grid": 8, "intensity": "window", "window": "soft_tissue"})
    level, width = WINDOW_PRESETS["soft_tissue"]
    assert w.mu_scale_per_mm == pytest.approx(0.019 * (1 + (level + width / 2) / 1000))
    m = ingest(src, tmp_path / "m" / "v.nii.gz", {"grid": 8, "intensity": "mu"})
    a = ingest(src, tmp_path / "a" / "v.nii.gz", {"grid": 8})
    assert m.mu_scale_per_mm == 1.0
    np.testing.assert_allclose(m.data, a.data * a.mu_scale_per_mm, rtol=1e-5, atol=1e-8)
    h = ingest(src, tmp_path / "h" / "v.nii.gz", {"grid": 8, "intensity": "hu"})
    np.testing.assert_allclose(a.data, np.clip((1000 + h.data) / 4000, 0, 1), atol=1e-6)


def test_failed_write_leaves_nothing_and_keeps_previous(tmp_path, monkeypatch):
    hu, _ = head_like()
    src = nifti_input(tmp_path, hu)
    out = tmp_path / "o" / "volume.nii.gz"
    first = ingest(src, out, {"grid": 8})
    before = {p.name: p.read_bytes() for p in out.parent.iterdir()}

    def boom(img, filename):
        with open(filename, "wb") as fh:
            fh.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(nib, "save", boom)
    with pytest.raises(OSError, match="disk full"):
        ingest(src, out, {"grid": 12})
    after = {p.name: p.read_bytes() for p in out.parent.iterdir()}
    assert after == before  # no temp files, previous outputs untouched
    assert load_volume(out).volume_id == first.volume_id


def test_ingest_replaces_only_an_earlier_ingest_output(tmp_path):
    """A NIfTI of someone else's or another step's volume (an evaluation's read-out, with a volume sidecar) at the
    output path is refused before the source is read; an earlier ingest output is replaced."""
    hu, _ = head_like()
    src = nifti_input(tmp_path, hu)
    theirs = tmp_path / "theirs.nii.gz"
    nib.save(nib.Nifti1Image(np.ones((4, 4, 4), np.float32), np.eye(4)), theirs)
    read_out = tmp_path / "run" / "model_volume.nii.gz"
    save_volume(Volume(np.ones((4, 4, 4), np.float32), np.eye(4), {"volume_id": "x"}), read_out)
    for out in (theirs, read_out):
        before = out.read_bytes()
        with pytest.raises(CtsplatError, match=rf"{out.name} exists and is not an earlier ingest output .*choose "
                                               "another output name or remove it"):
            ingest(tmp_path / "no_such_source", out, {"grid": 8})
        assert out.read_bytes() == before
    out = tmp_path / "o" / "volume.nii.gz"
    ingest(src, out, {"grid": 8})
    assert ingest(src, out, {"grid": 12}).data.shape == load_volume(out).data.shape == (12, 12, 12)


@pytest.mark.parametrize(
    "cfg,match",
    [
        ({"voxel_sise_mm": 1.0}, "unknown config key preprocessing.voxel_sise_mm"),
        ({"intensity": "density"}, "intensity"),
        ({"intensity": "window", "window": "liver"}, "unknown window preset"),
        # its top is the scale to 1/mm: at or below air it would be <= 0, a volume no step could read
        ({"intensity": "window", "window": [-1100, 100]}, r"window \[-1100, 100\] ends at -1050 HU, at or below air"),
        ({"grid": 1}, "grid"),
        ({"voxel_size_mm": -1}, "voxel_size_mm"),
        ({"mask": "magic"}, "mask"),
        ({"denoise": "nlm"}, "denoise"),
    ],
)
def test_bad_config_is_one_line_and_writes_nothing(tmp_path, cfg, match):
    hu, _ = head_like(8)
    src = nifti_input(tmp_path, hu)
    with pytest.raises(CtsplatError, match=match) as err:
        ingest(src, tmp_path / "o" / "v.nii.gz", cfg)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "o").exists()


def test_defaults_are_json_serialisable():
    assert json.loads(json.dumps(PREPROCESSING_DEFAULTS)) == PREPROCESSING_DEFAULTS


def test_stack_normal_points_along_slices():
    s = SliceStack(
        data=np.zeros((2, 2, 3), np.float32), row_dir=np.array([1.0, 0, 0]), col_dir=np.array([0, 1.0, 0]),
        spacing_ij=(1.0, 1.0), origins=np.array([[0, 0, 5.0], [0, 0, 3.0], [0, 0, 1.0]]),
    )
    np.testing.assert_allclose(s.normal, [0, 0, -1])
    assert np.all(np.diff(s.positions_mm) > 0)


# ------------------------------------------------------------------------------------------ CLI


def test_cli_ingest_and_errors(tmp_path, capsys):
    hu, _ = head_like(12)
    src = nifti_input(tmp_path, hu)
    out = tmp_path / "cli" / "volume.nii.gz"
    assert main(["ingest", str(src), str(out), "--voxel-size", "2", "--intensity", "window", "--window", "40,80"]) == 0
    vol = load_volume(out)
    np.testing.assert_allclose(vol.spacing_mm, 2.0)
    assert vol.meta["intensity"]["level_hu"] == 40 and vol.meta["intensity"]["width_hu"] == 80
    # a window's top maps to mu_water (1 + HU_top / 1000): --mu-water sets the scale the radiographs use
    out2 = tmp_path / "cli2" / "volume.nii.gz"
    assert main(["ingest", str(src), str(out2), "--voxel-size", "2", "--intensity", "window", "--window", "40,80",
                 "--mu-water", "0.02"]) == 0
    assert load_volume(out2).meta["intensity"]["mu_scale_per_mm"] == pytest.approx(0.02 * (1 + 80 / 1000))
    assert vol.meta["intensity"]["mu_scale_per_mm"] == pytest.approx(0.019 * (1 + 80 / 1000))
    assert main(["ingest", str(src), str(tmp_path / "x" / "v.nii.gz"), "--intensity", "hu", "--mu-water", "0.02"]) == 2
    assert "--mu-water only applies to intensity attenuation / mu / window, not hu" in capsys.readouterr().err
    assert main(["ingest", str(tmp_path / "missing"), str(tmp_path / "x" / "v.nii.gz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]
    assert not (tmp_path / "x").exists()


def test_cli_config_file_and_native(tmp_path):
    hu, _ = head_like(10)
    src = nifti_input(tmp_path, hu, spacing=(1.0, 1.0, 2.0))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("preprocessing:\n  intensity: mu\n  hu_max: 2000\n")
    out = tmp_path / "o" / "v.nii.gz"
    assert main(["ingest", str(src), str(out), "--config", str(cfg), "--native"]) == 0
    vol = load_volume(out)
    assert vol.shape == hu.shape
    np.testing.assert_allclose(sorted(vol.spacing_mm), [1.0, 1.0, 2.0])
    assert vol.meta["preprocessing"]["hu_max"] == 2000 and vol.mu_scale_per_mm == 1.0
    np.testing.assert_allclose(vol.data, np.clip(0.019 * (1 + hu / 1000), 0, 0.019 * 3), rtol=1e-5, atol=1e-7)


def test_ingest_refuses_a_grid_larger_than_memory_before_allocating_it(tmp_path):
    """A voxel size far below the scan's spacing asks for more memory than any machine has: one line naming the
    grid, no output, instead of the kernel killing the process (and its neighbours) mid-way."""
    hu, _ = head_like(12)
    out = tmp_path / "o" / "v.nii.gz"
    with pytest.raises(CtsplatError, match=r"output grid 12000 x 12000 x 12000 \(0.001 mm voxels\) needs about "
                                           r"\d+ GiB, more than this machine's \d+ GiB"):
        ingest(nifti_input(tmp_path, hu), out, {"voxel_size_mm": 0.001})
    assert not out.parent.exists()


def test_cli_grid_options_replace_the_config_files_grid_whichever_key_it_used(tmp_path):
    """--grid on the command line wins over a file's voxel_size_mm, and --voxel-size over a file's grid."""
    hu, _ = head_like(12)
    src = nifti_input(tmp_path, hu)
    by_size, by_grid = tmp_path / "size.yaml", tmp_path / "grid.yaml"
    by_size.write_text("preprocessing:\n  voxel_size_mm: 4\n")
    by_grid.write_text("preprocessing:\n  grid: 4\n")
    assert main(["ingest", str(src), str(tmp_path / "a" / "v.nii.gz"), "--config", str(by_size), "--grid", "6"]) == 0
    assert load_volume(tmp_path / "a" / "v.nii.gz").shape == (6, 6, 6)
    assert main(["ingest", str(src), str(tmp_path / "b" / "v.nii.gz"), "--config", str(by_grid),
                 "--voxel-size", "1.5"]) == 0
    np.testing.assert_allclose(load_volume(tmp_path / "b" / "v.nii.gz").spacing_mm, 1.5)


# ------------------------------------------------------------------------------------------ non-finite input


def strict_json(path):
    """Parse as standard JSON: NaN / Infinity are not JSON, so they fail here (json.loads accepts them)."""

    def refuse(token):
        raise ValueError(f"{path} holds {token}, which is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


def with_bad_block(n=16):
    hu, _ = head_like(n)
    hu[3:5, 6:9, 10] = np.nan
    hu[4, 7, 11] = np.inf
    return hu


def test_nonfinite_input_is_an_error_naming_count_and_bounding_box(tmp_path):
    src = nifti_input(tmp_path, with_bad_block())
    out = tmp_path / "o" / "volume.nii.gz"
    with pytest.raises(CtsplatError, match=r"7 non-finite voxels \(6 NaN, 1 Inf\).*\[3\.\.4, 6\.\.8, 10\.\.11\]"
                       r".*nonfinite: fill_min \(--nonfinite fill_min\)") as err:
        ingest(src, out, {"grid": 8})
    assert "\n" not in str(err.value)
    assert not out.parent.exists() or not any(out.parent.iterdir())


def test_nonfinite_fill_min_is_recorded_and_json_is_valid(tmp_path):
    hu = with_bad_block()
    src = nifti_input(tmp_path, hu)
    out = tmp_path / "o" / "volume.nii.gz"
    vol = ingest(src, out, {"grid": 8}, nonfinite="fill_min")
    assert np.isfinite(vol.data).all()
    meta = strict_json(json_path_for(out))
    finite_min = float(np.min(hu[np.isfinite(hu)]))
    step = next(s for s in meta["steps"] if s["step"] == "nonfinite")
    assert step == {"step": "nonfinite", "rule": "fill_min", "count": 7, "n_nan": 6, "n_inf": 1,
                    "bbox_ijk": [[3, 6, 10], [4, 8, 11]], "fill_value": pytest.approx(finite_min)}
    assert meta["source_value_range"][0] == pytest.approx(finite_min)
    assert all(np.isfinite(meta["source"]["value_range"]))
    assert meta["volume_id"] == load_volume(out).volume_id


def test_nonfinite_all_voxels_or_bad_rule(tmp_path):
    src = nifti_input(tmp_path, np.full((4, 4, 4), np.nan))
    with pytest.raises(CtsplatError, match="no finite voxel"):
        ingest(src, tmp_path / "o" / "v.nii.gz", {"grid": 4}, nonfinite="fill_min")
    with pytest.raises(CtsplatError, match="nonfinite 'zero' unknown; allowed: error, fill_min"):
        ingest(src, tmp_path / "o" / "v.nii.gz", {"grid": 4}, nonfinite="zero")


def test_cli_ingest_nonfinite(tmp_path, capsys):
    src = nifti_input(tmp_path, with_bad_block())
    out = tmp_path / "o" / "v.nii.gz"
    assert main(["ingest", str(src), str(out), "--grid", "8"]) == 2
    assert "non-finite" in capsys.readouterr().err and not out.exists()
    assert main(["ingest", str(src), str(out), "--grid", "8", "--nonfinite", "fill_min"]) == 0
    strict_json(json_path_for(out))


def test_write_json_atomic_refuses_nan_and_json_safe_writes_null(tmp_path):
    from ctsplat.utils import json_safe, write_json_atomic

    out = tmp_path / "m.json"
    with pytest.raises(CtsplatError, match=r"m\.json: .*NaN/Infinity at results\[1\]\.psnr3d"):
        write_json_atomic(out, {"results": [{"psnr3d": 1.0}, {"psnr3d": float("inf")}]})
    with pytest.raises(CtsplatError, match=r"at a\.b\[2\]"):
        write_json_atomic(out, {"a": {"b": np.array([1.0, 2.0, np.nan])}})
    assert list(tmp_path.iterdir()) == []
    obj = {"psnr": float("inf"), "ssim": np.float32("nan"), "ok": 1.5, "arr": np.array([np.nan, 2.0]),
           "nested": [{"x": -np.inf}], "n": 3, "s": "nan", "b": True, "none": None}
    write_json_atomic(out, json_safe(obj))
    assert strict_json(out) == {"psnr": None, "ssim": None, "ok": 1.5, "arr": [None, 2.0], "nested": [{"x": None}],
                                "n": 3, "s": "nan", "b": True, "none": None}
