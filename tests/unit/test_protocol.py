"""The sparse-view protocol's pieces: noise on the training views only (TIGRE's model), the cone-beam geometry in
volume sides with explicit held-out counts, and default detectors that cover the object (real files)."""

from __future__ import annotations

import importlib.util
import json
import warnings

import numpy as np
import pytest

from ctsplat.config import check_section
from ctsplat.formats.viewset import load_radiographs
from ctsplat.formats.volume import Volume, save_volume
from ctsplat.geometry import check_fov
from ctsplat.projector import add_noise, build_view_set, check_noise, render_radiographs
from ctsplat.utils import CtsplatError


def cube_volume(n: int = 24, voxel: float = 2.0, fill: str = "ball") -> Volume:
    """An ``n^3`` grid of ``voxel`` mm edges centred on (10, -5, 3) mm holding a ball or a full cube of ones."""
    A = np.diag([voxel, voxel, voxel, 1.0])
    A[:3, 3] = np.array([10.0, -5.0, 3.0]) - voxel * (n - 1) / 2
    if fill == "cube":
        data = np.ones((n, n, n), np.float32)
    else:
        g = np.indices((n, n, n)).astype(float) - (n - 1) / 2
        data = (np.sqrt((g**2).sum(0)) < n / 4).astype(np.float32)
    return Volume(data, A, {"volume_id": f"cube{n}{fill}", "intensity": {"mu_scale_per_mm": 0.02}})


@pytest.fixture()
def ball_path(tmp_path):
    path = tmp_path / "vol" / "volume.nii.gz"
    save_volume(cube_volume(20), path)
    return path


# ------------------------------------------------------------------------------------------- noise
def test_tigre_noise_equals_ctnoise_add_then_r2_clip() -> None:
    """TIGRE's CTnoise.add written out with the same draws: scale by max p, Poisson + Gaussian, log, rescale."""
    rng = np.random.default_rng(5)
    p = rng.random((3, 16, 16)) * 4.0
    got, counts = add_noise(p, 1e4, 10.0, np.random.default_rng(1), model="tigre")
    ref_rng = np.random.default_rng(1)
    m = p.max()
    n = ref_rng.poisson(1e4 * np.exp(-p / m)) + ref_rng.normal(0, 10, p.shape)
    expected = np.float32(-np.log(n / 1e4) * m)
    expected[expected < 0] = 0.0  # R²-Gaussian: projs_train[projs_train < 0] = 0
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)
    assert got.min() == 0.0 and (counts > 1e4).any()  # the clip acted on counts above I0
    # the noise level does not depend on the physical scale of the line integrals (TIGRE normalises by max p)
    scaled, _ = add_noise(p * 7.0, 1e4, 10.0, np.random.default_rng(1), model="tigre")
    np.testing.assert_allclose(scaled, got * 7.0, rtol=1e-5, atol=1e-5)


def test_noise_log_of_zero_counts_stays_finite() -> None:
    p = np.full((64, 64), 50.0)  # no photon gets through
    for model in ("physical", "tigre"):
        q, counts = add_noise(p, 100.0, 5.0, np.random.default_rng(0), model=model)
        assert np.isfinite(q).all() and counts.min() >= 1.0
    q, _ = add_noise(p, 100.0, 5.0, np.random.default_rng(0), model="tigre")
    assert q.max() <= 50.0 * np.log(100.0) + 1e-3  # one photon: s ln(I0)
    zero, _ = add_noise(np.zeros((4, 4)), 1e4, 10.0, np.random.default_rng(0), model="tigre")
    assert not zero.any()  # nothing attenuates: TIGRE's 0/0 becomes noise-free zeros


def test_noise_only_on_training_views_and_recorded(tmp_path, ball_path) -> None:
    cfg = {"n_views": 12, "detector_width": 24, "detector_height": 24, "n_val": 3, "n_test": 5}
    render_radiographs(ball_path, tmp_path / "clean", cfg, seed=4)
    noisy = {**cfg, "noise": {"enabled": True, "i0": 1e4, "electronic_sigma": 10.0, "model": "tigre"}}
    render_radiographs(ball_path, tmp_path / "a", noisy, seed=4)
    render_radiographs(ball_path, tmp_path / "b", noisy, seed=4)
    clean, vs = load_radiographs(tmp_path / "clean")
    a, vs_a = load_radiographs(tmp_path / "a")
    b, _ = load_radiographs(tmp_path / "b")
    np.testing.assert_array_equal(a, b)  # deterministic by seed
    train, held = vs_a.indices("train"), np.concatenate([vs_a.indices("val"), vs_a.indices("test")])
    assert len(train) == 12 and len(held) == 8
    np.testing.assert_array_equal(a[held], clean[held])  # validation and test stay noise-free
    assert not np.array_equal(a[train], clean[train]) and a[train].min() >= 0.0
    meta = json.loads((tmp_path / "a" / "views.json").read_text())["meta"]["noise"]
    assert meta["model"] == "tigre" and meta["splits"] == ["train"] and meta["i0"] == 1e4
    assert meta["noisy_view_ids"] == [vs_a.views[i].id for i in train]
    prov = json.loads((tmp_path / "a" / "radiographs.json").read_text())
    assert prov["config"]["noise"]["electronic_sigma"] == 10.0
    # every split noisy when asked
    render_radiographs(ball_path, tmp_path / "all", {**noisy, "noise": {**noisy["noise"],
                                                                          "splits": ["train", "val", "test"]}}, seed=4)
    c, _ = load_radiographs(tmp_path / "all")
    assert not np.array_equal(c[held], clean[held])
    assert json.loads((tmp_path / "clean" / "views.json").read_text())["meta"]["noise"] == {"enabled": False}


@pytest.mark.parametrize(
    ("noise", "needle"),
    [
        ({"i0": 0.0}, "radiographs.noise.i0 must be a positive number"),
        ({"i0": float("inf")}, "radiographs.noise.i0 must be a positive number"),
        ({"electronic_sigma": -1.0}, "radiographs.noise.electronic_sigma must be a number of counts >= 0"),
        ({"model": "gauss"}, "radiographs.noise.model must be one of physical, tigre"),
        ({"splits": ["trian"]}, "radiographs.noise.splits must be a non-empty list"),
        ({"splits": []}, "radiographs.noise.splits must be a non-empty list"),
        ({"splits": ["train", "train"]}, "radiographs.noise.splits must be a non-empty list"),
    ],
)
def test_noise_settings_out_of_range_fail_before_any_work(tmp_path, ball_path, noise, needle) -> None:
    cfg = {"n_views": 6, "detector_width": 16, "detector_height": 16, "noise": {"enabled": True, **noise}}
    with pytest.raises(CtsplatError, match=needle) as err:
        render_radiographs(ball_path, tmp_path / "out", cfg)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()


def test_noise_settings_refused_by_the_schema_naming_the_key() -> None:
    with pytest.raises(CtsplatError, match=r"radiographs.noise.splits"):
        check_section("radiographs", {"noise": {"splits": ["trian"]}})
    with pytest.raises(CtsplatError, match=r"radiographs.noise.model"):
        check_section("radiographs", {"noise": {"model": "x"}})
    with pytest.raises(CtsplatError, match=r"radiographs.noise.i0"):
        check_section("radiographs", {"noise": {"i0": -3}})
    check_noise({"i0": 1e4, "electronic_sigma": 10, "model": "tigre", "splits": ["train"]})


# ---------------------------------------------------------------------------------------- geometry
PROTOCOL = {"camera": "cone", "orbit": "circular", "dso_mm": None, "dsd_mm": None, "detector_size_factor": 2.0,
            "detector_width": 48, "detector_height": 48, "n_views": 150, "n_val": 4, "n_test": 100}


def test_protocol_geometry_in_volume_sides() -> None:
    vol = cube_volume(24, 2.0)  # L = 48 mm
    vs = build_view_set(vol, PROTOCOL, seed=2)
    cam = vs.camera
    assert (cam.dso_mm, cam.dsd_mm) == pytest.approx((2.5 * 48, 3.5 * 48))
    assert cam.pitch_mm == pytest.approx(2.0 * 48 / 48)  # detector width 2 L
    assert vs.meta["volume_side_mm"] == 48.0 and vs.meta["pixel_spacing_source"] == "detector_size_factor"
    train = [v for v in vs.views if v.split == "train"]
    test = [v for v in vs.views if v.split == "test"]
    assert len(train) == 150 and len(test) == 100 and len(vs.indices("val")) == 4
    np.testing.assert_allclose([v.azimuth_deg for v in train], np.arange(150) * 360 / 150)
    # 25 / 50 / 75 of the 150 by the views rule (every 6th / 3rd / 2nd): uniform over 360 degrees
    from ctsplat.baselines import select_views

    for n in (25, 50, 75):
        az = np.sort([vs.views[i].azimuth_deg for i in select_views(vs, "train", n)])
        np.testing.assert_allclose(np.diff(az), 360 / n)
    az_test = np.array([v.azimuth_deg for v in test])
    assert az_test.min() >= 0 and az_test.max() < 360 and len(np.unique(np.round(az_test, 6))) == 100
    assert np.ptp(az_test) > 340  # spread over the whole circle
    assert not set(np.round(az_test, 9)) & set(np.round([v.azimuth_deg for v in vs.views if v.split == "val"], 9))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_fov(cam, vs.Rs(), vs.ts(), vol.data, vol.affine) == 0.0


def test_geometry_settings_refused_with_one_line() -> None:
    vol = cube_volume(16)
    bad = [
        ({"orbit": "sphere", "n_views": 20, "n_test": 5}, "n_val / n_test set the held-out views of orbit: circular"),
        ({"n_val": -1}, "n_val must be an integer >= 0"),
        ({"pixel_spacing_mm": 1.0, "detector_size_factor": 2.0}, "not both"),
        ({"detector_size_factor": 0.0}, "detector_size_factor must be a positive number"),
        ({"camera": "cone", "dso_mm": None, "dso_factor": 0.0}, "dso_factor must be a positive number"),
        ({"camera": "cone", "dso_mm": None, "dso_factor": 0.1}, "source would sit inside the object"),
    ]
    for cfg, needle in bad:
        with pytest.raises(CtsplatError, match=needle) as err:
            build_view_set(vol, {"detector_width": 16, "detector_height": 16, "n_views": 8, **cfg})
        assert "\n" not in str(err.value)
    with pytest.raises(CtsplatError, match=r"radiographs.n_test"):
        check_section("radiographs", {"n_test": -2})
    with pytest.raises(CtsplatError, match=r"radiographs.detector_size_factor"):
        check_section("radiographs", {"detector_size_factor": -2})


def test_explicit_held_out_counts_of_a_circular_orbit() -> None:
    vs = build_view_set(cube_volume(16), {"n_views": 10, "n_val": 0, "n_test": 7, "detector_width": 32,
                                          "detector_height": 32})
    assert [len(vs.indices(s)) for s in ("train", "val", "test")] == [10, 0, 7]
    vs = build_view_set(cube_volume(16), {"n_views": 10, "n_test": 7, "detector_width": 32, "detector_height": 32})
    assert [len(vs.indices(s)) for s in ("train", "val", "test")] == [10, 2, 7]  # val from the 70/15/15 split


@pytest.mark.parametrize(
    "cfg",
    [
        {"camera": "parallel", "orbit": "circular"},
        {"camera": "parallel", "orbit": "sphere"},
        {"camera": "cone", "orbit": "circular", "dso_mm": 150.0, "dsd_mm": 250.0},
        {"camera": "cone", "orbit": "sphere", "dso_mm": 150.0, "dsd_mm": 250.0},
    ],
)
def test_default_detector_covers_a_box_filling_object(cfg) -> None:
    """A cube filling its grid seen at 45 degrees spans its diagonal: one voxel per pixel would truncate it."""
    vol = cube_volume(24, 2.0, fill="cube")
    vs = build_view_set(vol, {**cfg, "n_views": 40, "detector_width": 24, "detector_height": 24})
    assert vs.meta["pixel_spacing_source"] == "covers_object"
    spacing = vs.camera.spacing_mm if cfg["camera"] == "parallel" else vs.camera.pitch_mm / vs.camera.magnification
    assert spacing > 2.0  # wider than one voxel at the isocentre
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_fov(vs.camera, vs.Rs(), vs.ts(), vol.data, vol.affine) == 0.0


def test_default_detector_keeps_one_voxel_per_pixel_when_that_covers() -> None:
    vol = cube_volume(24, 2.0)  # a ball of radius 6 voxels: one voxel per pixel covers it
    vs = build_view_set(vol, {"n_views": 20, "detector_width": 24, "detector_height": 24})
    assert vs.meta["pixel_spacing_source"] == "one_voxel" and vs.camera.spacing_mm == 2.0
    vs = build_view_set(vol, {"camera": "cone", "dso_mm": 150.0, "dsd_mm": 250.0, "n_views": 20,
                              "detector_width": 24, "detector_height": 24})
    assert vs.camera.pitch_mm == pytest.approx(2.0 * 250 / 150)


@pytest.mark.parametrize("orbit", ["circular", "sphere"])
@pytest.mark.parametrize("camera", ["parallel", "cone"])
def test_default_settings_do_not_truncate_the_real_head(tmp_path_factory, ct0051_head, camera, orbit) -> None:
    if not ct0051_head.is_dir():
        pytest.skip(f"{ct0051_head} not found")
    from ctsplat.volume import ingest

    vol = ingest(ct0051_head, tmp_path_factory.mktemp("head") / "volume.nii.gz", {"grid": 48})
    cfg = {"camera": camera, "orbit": orbit, "n_views": 60, "detector_width": 48, "detector_height": 48}
    if camera == "cone":
        cfg.update(dso_mm=None, dsd_mm=None)  # 2.5 L and 3.5 L
    vs = build_view_set(vol, cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_fov(vs.camera, vs.Rs(), vs.ts(), vol.data, vol.affine) == 0.0


@pytest.mark.parametrize(("name", "grid", "detector"),
                         [("r2_protocol.yaml", 128, 256), ("r2_protocol_256.yaml", 256, 512)])
def test_protocol_configs_validate_and_say_the_protocol(monkeypatch, name, grid, detector) -> None:
    from pathlib import Path

    import yaml

    from ctsplat.config import prepare_config

    root = Path(__file__).resolve().parents[2]
    if not (root.parent / "shared" / "data" / "ct0051_head").is_dir():
        pytest.skip("../shared/data not found (the configs name its scans)")
    monkeypatch.chdir(root)
    cfg = prepare_config(yaml.safe_load((root / "config" / name).read_text()), root)
    geo = cfg["radiographs"][cfg["grid"]["geometry"]]
    assert cfg["preprocessing"]["grid"] == grid and geo["detector_width"] == geo["detector_height"] == detector
    assert (geo["camera"], geo["orbit"], geo["arc_deg"], geo["dso_mm"], geo["dsd_mm"]) == ("cone", "circular", 360,
                                                                                          None, None)
    assert (geo["dso_factor"], geo["dsd_factor"], geo["detector_size_factor"]) == (2.5, 3.5, 2.0)
    assert geo["noise"] == {"enabled": True, "model": "tigre", "i0": 1e4, "electronic_sigma": 10.0,
                            "splits": ["train"]}
    # the workflow's configs and benchmarks/protocol.py each spell the protocol out: they must agree
    monkeypatch.syspath_prepend(str(root / "benchmarks"))
    spec = importlib.util.spec_from_file_location("protocol_benchmark", root / "benchmarks" / "protocol.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    expected = bench.protocol_geometry(geo["n_views"], grid)
    assert {k: geo[k] for k in expected} == expected
    assert {k: cfg["train"][k] for k in bench.PROTOCOL_TRAIN} == bench.PROTOCOL_TRAIN
    assert geo["n_test"] == 100 and geo["n_val"] > 0
    assert all(geo["n_views"] % v == 0 for v in cfg["grid"]["axes"]["views"]) and cfg["grid"]["axes"]["views"] == [
        25, 50, 75]
    assert cfg["grid"]["axes"]["compositor"] == ["radiative"] and cfg["grid"]["axes"]["init"] == ["fbp"]
    assert cfg["train"]["init_asd_pocs"]["iterations"] > 0  # the FDK seed refined as the benchmark does
    assert set(cfg["volumes"]) == {"phantom", "ct0051_head", "totalseg_abdomen_j2k"}
    assert cfg["baselines"]["enabled"] and cfg["baselines"]["geometry"] == "cone"
