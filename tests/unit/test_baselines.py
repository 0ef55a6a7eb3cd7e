"""FBP/SART baselines against skimage's own radon -> iradon pipeline, metrics and files."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from skimage.transform import iradon, iradon_sart, radon

from ctsplat.baselines import (
    BASELINE_COLUMNS,
    BASELINE_DEFAULTS,
    circular_sinograms,
    fbp_volume,
    parallel_view_weights,
    run_baselines,
    sart_volumes,
    select_views,
    sirt_volume,
)
from ctsplat.evaluation.metrics import psnr3d, ssim3d
from ctsplat.formats.viewset import ViewSet
from ctsplat.formats.volume import Volume, load_volume, save_volume
from ctsplat.geometry import ConeCamera, ParallelCamera, circular_orbit
from ctsplat.projector import line_integrals, render_radiographs
from ctsplat.utils import CtsplatError

MU = 0.02


def phantom(n: int) -> np.ndarray:
    """Normalised [0, 1] head-like phantom, zero outside the inscribed cylinder."""
    from scipy.ndimage import gaussian_filter

    g = (np.arange(n) - (n - 1) / 2) / (n / 2)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    vol = 0.8 * ((X / 0.8) ** 2 + (Y / 0.65) ** 2 + (Z / 0.9) ** 2 <= 1)
    vol = vol - 0.5 * ((X / 0.7) ** 2 + (Y / 0.55) ** 2 + (Z / 0.8) ** 2 <= 1)
    vol = vol + 0.4 * np.exp(-((X - 0.2) ** 2 + (Y + 0.1) ** 2 + Z**2) / 0.02)
    vol = gaussian_filter(vol, 0.6)  # no voxel-sharp edges (both projectors are exact for smooth data only)
    return np.clip(vol * (X**2 + Y**2 < 0.95**2), 0, 1).astype(np.float32)


def make_volume(n: int, h: float = 2.0, flip_x: bool = False, dz: float = 1.0) -> Volume:
    A = np.diag([-h if flip_x else h, h, h * dz, 1.0])
    A[:3, 3] = [40.0 if flip_x else -30.0, -25.0, 100.0]
    return Volume(phantom(n), A, {"volume_id": f"ph{n}", "intensity": {"mu_scale_per_mm": MU}})


def project(vol: Volume, n_views: int, width: int | None = None, spacing: float | None = None, **orbit):
    n = vol.shape[0]
    cam = ParallelCamera(width or n, int(vol.shape[2] * vol.spacing_mm[2] / (spacing or vol.spacing_mm[0])) + 2,
                         spacing or float(vol.spacing_mm[0]))
    views = circular_orbit(n_views, vol.center_mm(), 300.0, split_fractions={"train": 1.0}, **orbit)
    vs = ViewSet(cam, views, vol.volume_id, vol.center_mm())
    p = line_integrals(vol.data * MU, vol.affine, cam, vs.Rs(), vs.ts()).numpy()
    return p, vs


@pytest.mark.parametrize("filter_name", ["ramp", "shepp-logan"])
def test_fbp_volume_equals_iradon_of_skimage_radon(filter_name):
    """Odd grid with the isocentre on a voxel: the sinograms coincide with radon's, so must the reconstructions."""
    vol = make_volume(33)
    p, vs = project(vol, 40)
    rec = fbp_volume(p, vs, vol, filter_name=filter_name, clip=False)
    theta = np.array([v.azimuth_deg for v in vs.views])
    radons = [radon(vol.data[:, :, k], theta, circle=True) for k in range(33)]
    sino, theta2, _ = circular_sinograms(p, vs, vol.affine, vol.shape, MU)
    np.testing.assert_array_equal(theta2, theta)
    # the sinograms differ only by discretisation (trilinear ray sampling vs rotate-and-sum) on a sharp phantom
    assert np.linalg.norm(sino - np.stack(radons)) / np.linalg.norm(np.stack(radons)) < 0.01
    ref = np.stack([iradon(r, theta, filter_name=filter_name, circle=True) for r in radons], -1)
    err = np.linalg.norm(rec - ref) / np.linalg.norm(ref)
    assert err < 0.025, err  # the ramp filter amplifies those high-frequency differences


def test_fbp_on_even_flipped_grid_with_other_detector_spacing():
    """Half-pixel offsets, a flipped x axis and a finer detector are resampled: as good as skimage's own pipeline."""
    vol = make_volume(32, flip_x=True, dz=1.5)
    p, vs = project(vol, 60, width=72, spacing=1.0)  # detector pixel = half a voxel
    rec = fbp_volume(p, vs, vol)
    theta = np.array([v.azimuth_deg for v in vs.views])
    data = vol.data[::-1]  # flip x back so rows go along +x, as radon's geometry expects
    direct = np.stack([iradon(radon(data[:, :, k], theta, circle=True), theta, circle=True) for k in range(32)], -1)
    direct = np.clip(direct[::-1], 0, 1)
    assert psnr3d(rec, vol.data) > psnr3d(direct, vol.data) - 1.0
    assert psnr3d(rec, vol.data) > 22.0
    assert psnr3d(rec, vol.data) > psnr3d(np.zeros_like(rec), vol.data) + 8


def test_parallel_view_weights_share_each_direction_once():
    """Half the gaps to the neighbouring directions on the circle of 180 degrees, split between coinciding views."""
    even = np.arange(40) * 4.5
    np.testing.assert_allclose(parallel_view_weights(even), 1.0, atol=1e-9)
    np.testing.assert_allclose(parallel_view_weights(np.arange(40) * 9.0), 1.0, atol=1e-9)  # 360: pairs coincide
    rng = np.random.default_rng(0)
    theta = np.arange(25) * 7.2 + rng.uniform(0, 4, 25)  # uneven, no gap wide enough to be a missing wedge
    phi = np.r_[theta[-1] - 180, theta, theta[0] + 180]
    cell = (phi[2:] - phi[:-2]) / 2  # brute force on the unrolled circle
    order = rng.permutation(25)
    np.testing.assert_allclose(parallel_view_weights(theta[order] + 180 * rng.integers(0, 2, 25)),
                               (cell / cell.mean())[order], rtol=1e-9)
    arc = parallel_view_weights(np.arange(90) * 3.0)  # 270: 0..87 seen twice, 90..177 once
    np.testing.assert_allclose(arc[:30], arc[30:60] / 2) and np.testing.assert_allclose(arc[:30], arc[60:])
    np.testing.assert_allclose(parallel_view_weights(np.arange(30) * 3.0), 1.0)  # a limited arc stays even


def test_fbp_on_an_arc_between_180_and_360_degrees_counts_each_direction_once():
    vol = make_volume(33)
    p180, vs180 = project(vol, 60, arc_deg=180.0)
    p270, vs270 = project(vol, 90, arc_deg=270.0)  # the same 3-degree step
    good = psnr3d(fbp_volume(p180, vs180, vol), vol.data)
    rec = fbp_volume(p270, vs270, vol)
    assert psnr3d(rec, vol.data) > good - 0.3, (psnr3d(rec, vol.data), good)
    sino, theta, _ = circular_sinograms(p270, vs270, vol.affine, vol.shape, MU)  # iradon's even weights alone
    plain = np.clip(np.stack([iradon(s, theta, circle=True) for s in sino], -1), 0, 1)
    assert psnr3d(plain, vol.data) < good - 2.0, (psnr3d(plain, vol.data), good)


def test_sart_matches_skimage_and_improves():
    vol = make_volume(33)
    p, vs = project(vol, 30)
    its = list(sart_volumes(p, vs, vol, iterations=3, clip=False))
    assert [i for i, _ in its] == [1, 2, 3]
    theta = np.array([v.azimuth_deg for v in vs.views])
    k = 20
    sino = radon(vol.data[:, :, k], theta, circle=True)
    one = iradon_sart(sino, theta, relaxation=0.15)
    two = iradon_sart(sino, theta, image=one.copy(), relaxation=0.15)  # (it updates image in place)
    for (_, rec), ref in zip(its[:2], (one, two), strict=True):
        assert np.linalg.norm(rec[:, :, k] - ref) / np.linalg.norm(ref) < 0.02  # sinograms differ by ~0.5%
    psnrs = [psnr3d(np.clip(r, 0, 1), vol.data) for _, r in its]
    assert psnrs[2] > psnrs[0]


def test_sirt_reconstructs_from_a_cone_beam_sphere_orbit():
    """The geometry-agnostic fallback: SIRT with the projector's autograd adjoint converges on cone beams."""
    from ctsplat.geometry import sphere_orbit

    vol = make_volume(12, h=5.0)
    cam = ConeCamera(14, 14, 5.0 * 1.5, 300.0, 450.0)
    views = sphere_orbit(16, vol.center_mm(), 300.0, split_fractions={"train": 1.0}, seed=0)
    vs = ViewSet(cam, views, vol.volume_id, vol.center_mm())
    p = line_integrals(vol.data * MU, vol.affine, cam, vs.Rs(), vs.ts(), method="trilinear").numpy()
    with pytest.raises(CtsplatError, match="planar circular orbit|parallel-beam"):
        fbp_volume(p, vs, vol)
    few = sirt_volume(p, vs, vol, iterations=2)
    more = sirt_volume(p, vs, vol, iterations=8)
    zeros = psnr3d(np.zeros_like(more), vol.data)
    assert psnr3d(more, vol.data) > psnr3d(few, vol.data) > zeros
    assert psnr3d(more, vol.data) > zeros + 6, (psnr3d(more, vol.data), zeros)
    reproj = line_integrals(more * MU, vol.affine, cam, vs.Rs(), vs.ts(), method="trilinear").numpy()
    assert np.linalg.norm(reproj - p) / np.linalg.norm(p) < 0.15


QUICK = {"sart_max_iterations": 3, "sart_relaxation": [0.15, 1.0], "asd_pocs_iterations": 2, "asd_pocs_alpha": 0.02,
         "asd_pocs_tv_steps": 5, "mbir_sharpness": 0.0, "mbir_snr_db": 30.0, "mbir_max_iterations": 20}


def test_run_baselines_writes_csv_volumes_and_metrics(tmp_path):
    vol = make_volume(24)
    vol_path = tmp_path / "volume.nii.gz"
    save_volume(vol, vol_path)
    rad = tmp_path / "rad"
    render_radiographs(vol_path, rad, {"n_views": 36, "detector_width": 24, "detector_height": 40})
    out = tmp_path / "baselines"
    df = run_baselines(vol_path, rad, out, {**QUICK, "n_views": [12, 36, 99]})
    assert list(df.columns) == BASELINE_COLUMNS
    methods = ["fbp", "sart", "asd_pocs", "mbir"]
    assert list(df["method"]) == methods * 2 and df["filter"][0] in ("ramp", "shepp-logan")
    assert list(df["n_views"]) == [12] * 4 + [36] * 4  # 99 > 36 training views: the same 36 views, run once
    csv = pd.read_csv(out / "baselines.csv", keep_default_na=False)
    assert len(csv) == 8 and list(csv["n_views"]) == list(df["n_views"])
    trials = pd.read_csv(out / "trials.csv")
    for (nv, method), g in df.groupby(["n_views", "method"]):
        t = trials[(trials.n_views == nv) & (trials.method == method)]
        row = g.iloc[0]
        assert row["val_psnr"] == pytest.approx(t["val_psnr"].max())  # the choice is the best on validation
        params = json.loads(row["params"])
        best = t.loc[t["val_psnr"].idxmax()]
        for k, v in params.items():
            if k in best and k != "detector_binning":
                assert best[k] == v or str(best[k]) == str(v), (method, k)
    sart = trials[(trials.method == "sart") & (trials.n_views == 36)]
    assert sorted(set(sart["relaxation"])) == [0.15, 1.0] and set(sart["iterations"]) <= {1, 2, 3}
    for block in range(2):  # one best per view count
        g = df.iloc[4 * block : 4 * block + 4]
        assert g["best_on_val"].sum() == 1 and g.loc[g["best_on_val"], "val_psnr"].iloc[0] == g["val_psnr"].max()
    assert df["psnr2d"].notna().all() and (df["ssim2d"] > 0.5).all()
    fbp12, fbp36 = df[df["method"] == "fbp"]["psnr3d"].iloc[:2]
    assert fbp36 > fbp12  # more views, better FBP
    ref = load_volume(vol_path).data
    for name, row in (("fbp_n036", df.iloc[4]), ("sart_n036", df.iloc[5]), ("mbir_n036", df.iloc[7])):
        rec = load_volume(out / f"{name}.nii.gz")
        assert rec.shape == ref.shape and np.allclose(rec.affine, vol.affine, atol=1e-5)
        assert psnr3d(rec.data, ref) == pytest.approx(row["psnr3d"], abs=1e-3)
        assert ssim3d(rec.data, ref) == pytest.approx(row["ssim3d"], abs=1e-3)
        assert rec.data.min() >= 0 and rec.data.max() <= 1
    assert (df[df.n_views == 36]["psnr3d"] > 20).all(), df
    prov = json.loads((out / "baselines.json").read_text())
    assert prov["volume_id"] == "ph24" and len(prov["results"]) == 8
    assert not list(tmp_path.glob("**/svmbir-*"))  # svmbir's cache is removed
    json.dumps(BASELINE_DEFAULTS)
    # a second run replaces the folder whole: no reconstruction of the first run's view counts stays behind
    run_baselines(vol_path, rad, out, {**QUICK, "n_views": [12], "methods": ["fbp"]})
    assert sorted(p.name for p in out.iterdir()) == ["baselines.csv", "baselines.json", "fbp_n012.json",
                                                     "fbp_n012.nii.gz", "trials.csv"]
    # Snakemake removes a rule's declared outputs (the two tables) before it reruns the step: what is left is still
    # this step's folder, and is replaced
    (out / "baselines.csv").unlink()
    (out / "baselines.json").unlink()
    run_baselines(vol_path, rad, out, {**QUICK, "n_views": [12], "methods": ["fbp"]})
    assert (out / "baselines.csv").is_file()
    (out / "notes.txt").write_text("mine")  # a file it did not write: refused before any work
    with pytest.raises(CtsplatError, match=r"baselines holds notes\.txt, which this step does not write, and replacing "
                       r"the folder would delete it"):
        run_baselines(vol_path, rad, out, {**QUICK, "n_views": [12], "methods": ["fbp"]})
    assert (out / "notes.txt").read_text() == "mine"


def test_run_baselines_on_a_cone_beam_geometry(tmp_path):
    vol = make_volume(16)
    vol_path = tmp_path / "volume.nii.gz"
    save_volume(vol, vol_path)
    rad = tmp_path / "rad"
    render_radiographs(vol_path, rad, {"camera": "cone", "n_views": 24, "detector_width": 32, "detector_height": 32,
                                       "dso_mm": 80.0, "dsd_mm": 112.0, "pixel_spacing_mm": 112.0 / 80.0 * 2 * 32 / 32})
    df = run_baselines(vol_path, rad, tmp_path / "out", {**QUICK, "save_volumes": False})
    assert list(df["method"]) == ["fdk", "sart", "asd_pocs"]
    assert (df["psnr3d"] > 18).all() and df["best_on_val"].sum() == 1, df
    assert json.loads(df["params"][1])["detector_binning"] == 1
    assert all("sharpen_amount" not in json.loads(p) for p in df["params"])  # off by default
    # offered the read-out sharpening: the same reconstructions, each sharpened by the amount validation prefers
    amounts = [0.0, 0.3, 0.6]
    sharp = run_baselines(vol_path, rad, tmp_path / "sharp", {**QUICK, "sharpen": {"amounts": amounts}})
    for (_, a), (_, b) in zip(df.iterrows(), sharp.iterrows(), strict=True):
        params = json.loads(b["params"])
        chosen = params.pop("sharpen_amount")
        assert params == json.loads(a["params"]) and chosen in amounts
        assert b["val_psnr"] >= a["val_psnr"]  # amount 0 (the reconstruction itself) is a candidate
        assert (chosen == 0) == (b["val_psnr"] == a["val_psnr"])
    saved = load_volume(tmp_path / "sharp" / "fdk_n024.nii.gz").data
    trials = pd.read_csv(tmp_path / "sharp" / "trials.csv")
    assert len(trials[trials["sharpen_amount"].notna()]) == len(amounts) * len(sharp)
    assert saved.min() >= 0 and saved.max() <= 1  # clipped like every baseline


def test_a_cone_arc_too_short_for_fdk_skips_it_and_runs_the_others(tmp_path, caplog):
    import logging

    vol = make_volume(16)
    save_volume(vol, tmp_path / "volume.nii.gz")
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad", {
        "camera": "cone", "arc_deg": 180.0, "n_views": 18, "detector_width": 32, "detector_height": 32,
        "dso_mm": 80.0, "dsd_mm": 112.0, "pixel_spacing_mm": 2.8})
    with caplog.at_level(logging.WARNING, logger="ctsplat.recon.suite"):
        df = run_baselines(tmp_path / "volume.nii.gz", tmp_path / "rad", tmp_path / "out",
                           {**QUICK, "save_volumes": False, "methods": ["fdk", "sart"]})
    assert list(df["method"]) == ["sart"]
    assert any("FDK skipped: FDK short scan covers" in r.getMessage() for r in caplog.records)
    with pytest.raises(CtsplatError, match=r"methods \['fdk'\] \(baselines.settings.methods in a workflow config\) "
                                           "cannot reconstruct"):
        run_baselines(tmp_path / "volume.nii.gz", tmp_path / "rad", tmp_path / "out2", {**QUICK, "methods": ["fdk"]})


def test_baseline_choice_reads_validation_views_only(tmp_path):
    """Corrupting the test views and the reference volume changes the test metrics, never the choice."""
    from ctsplat.formats.viewset import load_radiographs, write_radiographs

    vol = make_volume(20)
    vol_path = tmp_path / "volume.nii.gz"
    save_volume(vol, vol_path)
    rad = tmp_path / "rad"
    render_radiographs(vol_path, rad, {"n_views": 24, "detector_width": 20, "detector_height": 24,
                                       "split": {"train": 0.6, "val": 0.2, "test": 0.2}})
    cfg = {**QUICK, "methods": ["fbp", "sart"], "fbp_filters": ["ramp", "shepp-logan", "hann"], "save_volumes": False}
    before = run_baselines(vol_path, rad, tmp_path / "a", cfg)
    p, vs = load_radiographs(rad)
    rng = np.random.default_rng(0)
    bad = p.copy()
    bad[vs.indices("test")] = rng.random(bad[vs.indices("test")].shape) * p.max()
    write_radiographs(rad, bad, vs, {"volume_id": vs.volume_id})
    save_volume(Volume(rng.random(vol.shape).astype(np.float32), vol.affine, vol.meta), vol_path)
    after = run_baselines(vol_path, rad, tmp_path / "b", cfg)
    for col in ("method", "filter", "iterations", "params", "val_psnr", "best_on_val"):
        assert list(after[col]) == list(before[col]), col
    assert (after["psnr3d"] < before["psnr3d"] - 5).all() and (after["psnr2d"] < before["psnr2d"] - 5).all()
    # while the validation views do decide it
    bad[vs.indices("val")] += rng.normal(0, 0.3 * p.std(), bad[vs.indices("val")].shape).astype(np.float32)
    write_radiographs(rad, bad, vs, {"volume_id": vs.volume_id})
    assert (run_baselines(vol_path, rad, tmp_path / "c", cfg)["val_psnr"] < before["val_psnr"] - 3).all()


@pytest.mark.parametrize(("settings", "message"), [
    ({"methods": ["fbp", "art"]}, "baselines.methods"),
    ({"sart_relaxation": [0.5, 2.5]}, "baselines.sart_relaxation"),
    ({"asd_pocs_alpha": -1}, "baselines.asd_pocs_alpha"),
    ({"detector_binning": 0}, "baselines.detector_binning"),
    ({"mbir_snr_db": "high"}, "baselines.mbir_snr_db"),
    ({"fbp_filters": []}, "baselines.fbp_filters"),
    ({"sart_iterations": 3}, "sart_iterations"),
    ({"methods": ["fdk"]}, "cannot reconstruct this geometry"),
    ({"detector_binning": 5}, "baselines.detector_binning 5 must be >= 1 and divide"),
    ({"sharpen": {"amounts": [0, -0.5]}}, "baselines.sharpen.amounts"),
    ({"sharpen": {"radius_voxels": 0}}, "baselines.sharpen.radius_voxels"),
])
def test_bad_baseline_options_fail_before_any_work(tmp_path, settings, message):
    vol = make_volume(12)
    vol_path = tmp_path / "v.nii.gz"
    save_volume(vol, vol_path)
    render_radiographs(vol_path, tmp_path / "rad", {"n_views": 10, "detector_width": 12, "detector_height": 16})
    with pytest.raises(CtsplatError, match=message) as err:
        run_baselines(vol_path, tmp_path / "rad", tmp_path / "out", {"methods": ["sart"], **settings})
    assert "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()


def test_select_views_matches_the_training_subset_rule():
    views = circular_orbit(40, np.zeros(3), 100.0, start_deg=200.0, seed=0)
    vs = ViewSet(ParallelCamera(8, 8, 1.0), views)
    rows = select_views(vs, "train", 10)
    az = np.array([vs.views[i].azimuth_deg for i in rows])
    np.testing.assert_allclose(np.sort(az), 2.0 + np.arange(10) * 36.0)  # every 4th of 200 + 9 k mod 360
    assert all(vs.views[i].split == "train" for i in rows)
    assert len(select_views(vs, "train", 0)) == 40 and len(select_views(vs, "test", 0)) == 9


def test_baselines_bad_input(tmp_path):
    vol = make_volume(16)
    p, vs = project(vol, 12)
    cone_vs = ViewSet(ConeCamera(16, 32, 1.0, 300.0, 400.0), vs.views, vs.volume_id, vs.isocenter_mm)
    with pytest.raises(CtsplatError, match="parallel-beam"):
        fbp_volume(p, cone_vs, vol)
    pw, vsw = project(vol, 12, wobble_deg=5.0)
    with pytest.raises(CtsplatError, match="planar circular orbit"):
        fbp_volume(pw, vsw, vol)
    oblique = Volume(vol.data, np.array([[0, 2.0, 0, 0], [2.0, 0, 0, 0], [0, 0, 3.0, 0], [0, 0, 0, 1]]), vol.meta)
    with pytest.raises(CtsplatError, match="axis-aligned"):
        fbp_volume(p, vs, oblique)
    with pytest.raises(CtsplatError, match="do not match"):
        fbp_volume(p[:5], vs, vol)
    with pytest.raises(CtsplatError, match="unknown FBP filter"):
        fbp_volume(p, vs, vol, filter_name="butterworth")
    vol_path = tmp_path / "v.nii.gz"
    save_volume(vol, vol_path)
    render_radiographs(vol_path, tmp_path / "rad", {"n_views": 10, "detector_width": 16, "detector_height": 32,
                                                    "split": {"train": 1.0, "val": 0.0, "test": 0.0}})
    with pytest.raises(CtsplatError, match="no validation views"):
        run_baselines(vol_path, tmp_path / "rad", tmp_path / "out", {})
    for held_out in ("val", "test"):  # reconstructing from the views that choose or score would leak
        with pytest.raises(CtsplatError, match=rf"baselines.split: '{held_out}' is not one of \['train'\]"):
            run_baselines(vol_path, tmp_path / "rad", tmp_path / "out", {"split": held_out})
    other = Volume(vol.data, vol.affine, {**vol.meta, "volume_id": "other"})
    save_volume(other, tmp_path / "o.nii.gz")
    with pytest.raises(CtsplatError, match="rendered from volume ph16"):
        run_baselines(tmp_path / "o.nii.gz", tmp_path / "rad", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_workflow_config_takes_cone_beam_baselines_and_refuses_a_carm_geometry():
    from ctsplat.config import prepare_config

    cfg = prepare_config({"radiographs": {"cone": {"camera": "cone"}}})
    assert cfg["baselines"]["geometry"] == "cone" and cfg["baselines"]["enabled"]
    carm = {"camera": "cone", "orbit": "carm", "n_views": 30}
    with pytest.raises(CtsplatError, match=r"baselines\.geometry: 'carm' is a C-arm orbit .* no validation views"):
        prepare_config({"radiographs": {"circ": {}, "carm": carm}, "baselines": {"geometry": "carm"}})
    assert prepare_config({"radiographs": {"circ": {}, "carm": carm},
                           "baselines": {"geometry": "carm", "enabled": False}})["baselines"]["geometry"] == "carm"
    with pytest.raises(CtsplatError, match=r"baselines\.settings\.asd_pocs_alpha"):
        prepare_config({"radiographs": {"circ": {}}, "baselines": {"settings": {"asd_pocs_alpha": [0.1, 0]}}})


def test_3d_metrics_do_not_depend_on_the_volume_units(tmp_path):
    # the same object stored normalised (μ / μ_max) and in 1/mm (intensity mu): the same reconstructions, so the
    # same 3D scores; data range 1 on the volume in 1/mm would add 20 log10(1 / μ_max) ≈ 22 dB
    mu_max = 0.019 * (1 + 3000 / 1000)
    base = make_volume(16)
    scores = {}
    for name, data, intensity in (
            ("normalised", base.data, {"kind": "attenuation_normalised", "mu_water_per_mm": 0.019, "hu_max": 3000.0,
                                       "mu_scale_per_mm": mu_max}),
            ("per_mm", base.data * np.float32(mu_max), {"kind": "attenuation_per_mm", "mu_water_per_mm": 0.019,
                                                        "hu_max": 3000.0, "mu_scale_per_mm": 1.0})):
        vol = Volume(data, base.affine, {"volume_id": name, "intensity": intensity})
        save_volume(vol, tmp_path / f"{name}.nii.gz")
        render_radiographs(tmp_path / f"{name}.nii.gz", tmp_path / f"rad_{name}",
                           {"n_views": 24, "detector_width": 16, "detector_height": 20})
        df = run_baselines(tmp_path / f"{name}.nii.gz", tmp_path / f"rad_{name}", tmp_path / f"out_{name}",
                           {**QUICK, "methods": ["fbp"], "n_views": [16]})
        scores[name] = df.iloc[0][["psnr3d", "ssim3d"]].astype(float).to_numpy()
    assert load_volume(tmp_path / "per_mm.nii.gz").metric_range == pytest.approx(mu_max)
    assert scores["per_mm"] == pytest.approx(scores["normalised"], abs=1e-3)
    assert 10 < scores["normalised"][0] < 40


def test_3d_ssim_of_a_thin_volume_uses_a_smaller_window():
    from ctsplat.evaluation.metrics import ssim_window

    rng = np.random.default_rng(0)
    ref = rng.random((20, 20, 5))
    test = ref + rng.normal(0, 0.05, ref.shape)
    assert ssim_window((20, 5)) == 5 and ssim_window((20, 4)) == 3 and ssim_window((64, 64)) == 7
    assert ssim3d(ref, ref) == pytest.approx(1.0) and 0 < ssim3d(test, ref) < 1
    with pytest.raises(CtsplatError, match=r"SSIM needs images at least 3 px on a side, got \(20, 2\)"):
        ssim3d(ref[:, :, :2], ref[:, :, :2])
