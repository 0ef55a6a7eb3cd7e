"""Workflow config validation (JSON schema, defaults, key paths), library-defaults mirror, schema shipped as package
data, grid expansion."""

from __future__ import annotations

import importlib
import itertools
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import yaml

from ctsplat.config import (
    LIBRARY_SECTIONS,
    check_config_files,
    check_library_sections,
    check_section,
    load_config_text,
    load_schema,
    prepare_config,
    schema_defaults,
    sync_library_defaults,
    validate_config,
)
from ctsplat.grid import expand_grid
from ctsplat.utils import CtsplatError

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted((ROOT / "config").glob("*.yaml"))


def test_defaults_filled_from_empty_config():
    cfg = validate_config({})
    vol = cfg["volumes"]["phantom"]
    assert vol["source"] == "phantom" and vol["phantom"]["size"] == 64 and vol["phantom"]["beads"] is True
    assert vol["series_uid"] is None and vol["allow_modalities"] == ["CT"] and vol["preprocessing"] == {}
    assert cfg["grid"]["axes"]["init"] == ["fbp"] and cfg["grid"]["exclude"] == []
    assert cfg["analysis"]["milestones"] == {"psnr2d": 30.0, "ssim2d": 0.9, "psnr3d": 30.0, "ssim3d": 0.9}
    assert cfg["resources"]["train"]["mem_mb"] > 0
    # nested library defaults are filled too (radiographs geometry -> split fractions)
    assert cfg["radiographs"]["circular"]["split"]["train"] == pytest.approx(0.7)


@pytest.mark.parametrize(
    ("config", "where"),
    [
        ({"grid": {"axes": {"views": ["ten"]}}}, "grid.axes.views[0]"),
        ({"grid": {"axes": {"init": ["magic"]}}}, "grid.axes.init[0]"),
        ({"grid": {"axes": {"seed": []}}}, "grid.axes.seed"),
        ({"train": {"iterations": "many"}}, "train.iterations"),
        ({"train": {"lr": {"means": "x"}}}, "train.lr.means"),
        ({"train": {"init": "fbp"}}, "train"),  # grid-controlled key
        ({"radiographs": {"c": {"camera": "fisheye"}}}, "radiographs.c.camera"),
        ({"volumes": {"v": {"source": "x", "phantom": {"size": 2}}}}, "volumes.v.phantom.size"),
        ({"volumes": {"bad/name": {"source": "x"}}}, "volumes"),
        ({"volumes": {"v": {"source": "x", "preprocessing": {"gird": 64}}}}, "volumes.v.preprocessing"),
        ({"device": "tpu"}, "device"),
        ({"analysis": {"window": 0}}, "analysis.window"),
        ({"train": {"checkpoint_every": 0}}, "train.checkpoint_every"),
        ({"train": {"eval_every": -5}}, "train.eval_every"),
        ({"train": {"nan_lr_decay": 2.0}}, "train.nan_lr_decay"),
        ({"train": {"lr": {"means": -0.01}}}, "train.lr.means"),
        ({"train": {"lambda_ssim": -1}}, "train.lambda_ssim"),
        ({"radiographs": {"c": {"noise": {"i0": 0}}}}, "radiographs.c.noise.i0"),
        ({"volumes": {"v": {"source": "x", "tiff_voxel_size_mm": -1}}}, "volumes.v.tiff_voxel_size_mm"),
        ({"volumes": {"v": {"source": "x", "phantom": {"variant": "kak"}}}}, "volumes.v.phantom.variant"),
        ({"analysis": {"milestones": {"psnr9d": 3}}}, "analysis.milestones"),
        # NaN is inside every JSON schema range (each comparison is false): refused as not finite
        ({"sfm": {"settings": {"min_registration_rate": float("nan")}}}, "sfm.settings.min_registration_rate"),
        ({"radiographs": {"c": {"elevation_range_deg": [0.0, float("inf")]}}},
         "radiographs.c.elevation_range_deg[1]"),
        ({"train": {"lr": {"means": np.float32("nan")}}}, "train.lr.means"),  # a config built in code
    ],
)
def test_bad_values_name_the_key_path(config, where):
    with pytest.raises(CtsplatError) as err:
        validate_config(config)
    assert f"invalid config at {where}:" in str(err.value)
    assert "\n" not in str(err.value)


def test_unknown_key_lists_allowed_keys():
    with pytest.raises(CtsplatError, match=r"unknown config key grid\.axis \(did you mean axes\?\); allowed keys in "
                                           r"grid: axes, exclude, geometry"):
        validate_config({"grid": {"axis": {}}})
    with pytest.raises(CtsplatError, match=r"invalid config at <config>: unknown config key trian \(did you mean "
                                           r"train\?\); allowed keys at the top level: analysis, baselines"):
        validate_config({"trian": {}})


def test_validate_does_not_mutate_input():
    cfg = {"grid": {"axes": {"views": [5]}}}
    validate_config(cfg)
    assert cfg == {"grid": {"axes": {"views": [5]}}}


SECTION_PATHS = {"preprocessing": ("preprocessing",), "radiographs": ("radiographs", "circular"),
                 "sfm": ("sfm", "settings"), "train": ("train",), "baselines": ("baselines", "settings"),
                 "photos": ("photos",)}


def test_every_library_section_is_checked():
    assert set(SECTION_PATHS) == set(LIBRARY_SECTIONS)


@pytest.mark.parametrize(("section", "path"), SECTION_PATHS.items(), ids=list(SECTION_PATHS))
def test_schema_defaults_mirror_library_defaults(section, path):
    """The schema's library sections fill exactly the owning module's DEFAULTS (minus grid-controlled keys)."""
    module, attr = LIBRARY_SECTIONS[section]
    mod = pytest.importorskip(module)
    defaults = getattr(mod, attr)
    filled = validate_config({})
    for p in path:
        filled = filled[p]
    from ctsplat.config import WORKFLOW_KEYS

    grid_keys = WORKFLOW_KEYS.get(section, (set(), ""))[0]
    if section == "train":  # the workflow sets these per run: the schema must not offer them
        assert grid_keys == {"volume", "radiographs", "sfm_dir", "sfm_radiographs", "init", "compositor", "mip",
                             "poses", "views", "seed", "device"}
    expect = {k: v for k, v in defaults.items() if k not in grid_keys}
    assert filled == expect


def test_sync_library_defaults_reproduces_the_shipped_schema(tmp_path):
    """The generated block of the schema is what ``python -m ctsplat.config --sync-defaults`` writes today."""
    for module, _ in LIBRARY_SECTIONS.values():
        pytest.importorskip(module)
    shipped = resources.files("ctsplat").joinpath("schemas/config.schema.yaml").read_text(encoding="utf-8")
    copy = tmp_path / "config.schema.yaml"
    copy.write_text(shipped, encoding="utf-8")
    assert sync_library_defaults(copy) == copy
    assert copy.read_text(encoding="utf-8") == shipped


def test_schema_is_package_data_and_defaults_are_copies():
    assert load_schema() == yaml.safe_load(
        resources.files("ctsplat").joinpath("schemas/config.schema.yaml").read_text(encoding="utf-8"))
    analysis = schema_defaults("analysis")
    assert analysis["milestones"] == {"psnr2d": 30.0, "ssim2d": 0.9, "psnr3d": 30.0, "ssim3d": 0.9}
    analysis["milestones"]["psnr2d"] = 0.0
    assert schema_defaults("analysis")["milestones"]["psnr2d"] == 30.0
    assert schema_defaults()["analysis"] == schema_defaults("analysis")


def test_schema_phantom_defaults_mirror_write_phantom_dicom():
    import inspect

    phantom = pytest.importorskip("ctsplat.phantom")
    sig = inspect.signature(phantom.write_phantom_dicom)
    filled = validate_config({})["volumes"]["phantom"]["phantom"]
    assert filled.keys() <= sig.parameters.keys()
    assert {k: sig.parameters[k].default for k in filled if k != "size"} == {k: v for k, v in filled.items()
                                                                             if k != "size"}


def test_check_library_sections_uses_module_defaults(monkeypatch):
    fake = type("M", (), {"FAKE_DEFAULTS": {"alpha": 1}})
    monkeypatch.setattr(importlib, "import_module", lambda name: fake)
    cfg = {"train": {"alpha": 2}}
    check_library_sections(cfg, modules={"train": ("fake", "FAKE_DEFAULTS")})
    with pytest.raises(CtsplatError, match="unknown config key train.beta"):
        check_library_sections({"train": {"beta": 1}}, modules={"train": ("fake", "FAKE_DEFAULTS")})


def test_expand_grid_product_and_exclusions():
    axes = {"init": ["fbp", "volume"], "compositor": ["radiative", "alpha"], "mip": [True, "off"],
            "poses": ["gt", "colmap"], "views": [25, 50], "seed": [0]}
    full = expand_grid(axes, ["a", "b"])
    assert len(full) == 2 * 2 * 2 * 2 * 2 * 2
    assert set(full["mip"]) == {"on", "off"}
    expect = set(itertools.product(["a", "b"], ["fbp", "volume"], ["radiative", "alpha"], ["on", "off"],
                                   ["gt", "colmap"], [25, 50], [0]))
    assert set(map(tuple, full.itertuples(index=False))) == expect
    ex = expand_grid(axes, ["a", "b"], exclude=[{"poses": "colmap", "init": ["volume"]},
                                                   {"volume": "b", "views": 50}, {"mip": False}])
    n = sum(1 for r in expect if not ((r[4] == "colmap" and r[1] == "volume") or (r[0] == "b" and r[5] == 50)
                                      or r[3] == "off"))
    assert len(ex) == n
    assert not ((ex["poses"] == "colmap") & (ex["init"] == "volume")).any()
    assert not (ex["mip"] == "off").any()


def test_empty_grid_is_an_error():
    axes = {"init": ["fbp"], "compositor": ["radiative"], "mip": ["on"], "poses": ["gt"], "views": [5], "seed": [0]}
    with pytest.raises(CtsplatError, match="expands to zero runs"):
        expand_grid(axes, ["a"], exclude=[{"init": "fbp"}])
    with pytest.raises(CtsplatError, match="expands to zero runs"):
        prepare_config({"grid": {"exclude": [{"seed": 0}]}})


@pytest.mark.parametrize(("axis", "values"), [("mip", ["on", True]), ("augment", [False, "off"])])
def test_an_axis_value_given_twice_is_an_error(axis, values):
    """The schema's uniqueItems sees "on" and true as two values; normalised they are one cell, run twice."""
    with pytest.raises(CtsplatError, match=rf"grid\.axes\.{axis} lists '(on|off)' twice .*keep one"):
        prepare_config({"grid": {"axes": {axis: values}}})


def test_an_exponent_yaml_reads_as_text_is_named_with_its_fix():
    with pytest.raises(CtsplatError, match=r"train\.lambda_density: '5e-5' is not of type 'number' \(YAML reads a "
                                           r"number in exponent form as text .*: write 5\.0e-5\)"):
        prepare_config({"train": {"lambda_density": "5e-5"}})
    with pytest.raises(CtsplatError, match=r"train\.iterations: '1e5' is not of type 'integer' \(YAML reads a number "
                                           r"in exponent form as text: write 100000\)$"):
        prepare_config({"train": {"iterations": "1e5"}})
    with pytest.raises(CtsplatError, match=r"train\.lr: '5e-5' is not of type 'object'$"):  # no number: no hint
        prepare_config({"train": {"lr": "5e-5"}})


@pytest.mark.parametrize(("override", "needle"), [
    ({"radiographs": {"circular": {"detector_width": 8, "detector_height": 8}}},
     r"radiographs\.circular: a 8 x 8 detector is smaller than the SSIM loss window \(11 px\)"),
    ({"radiographs": {"circular": {"n_views": 1}}, "grid": {"axes": {"views": [1]}}},
     r"radiographs\.circular: split leaves 'val' empty: 1 training views .*, or give n_val"),
    ({"radiographs": {"circular": {"orbit": "sphere", "n_views": 4, "n_val": None, "n_test": None}}},
     r"radiographs\.circular: split leaves 'test' empty: 4 views .*; use more views \(n_views\) or a larger test "
     r"fraction$"),
    ({"radiographs": {"circular": {"camera": "cone", "dso_mm": 500, "dsd_mm": 100}}},
     r"radiographs\.circular: dsd_mm \(100\) must be larger than dso_mm \(500\)"),
    ({"radiographs": {"circular": {"camera": "cone", "dso_mm": None, "dsd_mm": None, "dso_factor": 3,
                                   "dsd_factor": 2}}},
     r"radiographs\.circular: dsd_factor \(2\) must be larger than dso_factor \(3\)"),
    ({"preprocessing": {"grid": 2}}, r"preprocessing\.grid: 2 leaves fewer than 3 voxels on a side"),
    ({"volumes": {"p": {"source": "phantom", "preprocessing": {"grid": [16, 16, 2]}}}},
     r"volumes\.p\.preprocessing\.grid: \[16, 16, 2\] leaves fewer than 3 voxels"),
])
def test_settings_a_step_would_refuse_after_others_ran_are_refused_at_parse_time(override, needle):
    """Each of these failed only in the project or train job, after phantom, ingest and projection had run."""
    with pytest.raises(CtsplatError, match=rf"^invalid config at {needle}"):
        prepare_config(override)


def test_missing_volume_source_is_reported_with_key(tmp_path):
    with pytest.raises(CtsplatError, match=r"volumes\.head\.source: 'nope/ct'"):
        prepare_config({"volumes": {"head": {"source": "nope/ct"}}}, base_dir=tmp_path)
    (tmp_path / "ct").mkdir()
    (tmp_path / "ct" / "slice_0000.dcm").write_bytes(b"")
    cfg = prepare_config({"volumes": {"head": {"source": "ct"}}}, base_dir=tmp_path)
    assert cfg["grid"]["geometry"] == "circular"


def test_grid_geometry_must_exist():
    with pytest.raises(CtsplatError, match="grid.geometry: 'cone' is not a radiographs geometry"):
        prepare_config({"grid": {"geometry": "cone"}})


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_configs_validate(path):
    check_config_files([path])  # no repeated key
    with open(path) as fh:
        config = yaml.safe_load(fh)
    cfg = validate_config(config)
    runs = expand_grid(cfg["grid"]["axes"], list(cfg["volumes"]), cfg["grid"]["exclude"])
    assert len(runs) >= 1


def test_baselines_geometry_defaults_to_grid_geometry_and_must_exist():
    cfg = prepare_config({"radiographs": {"sph": {"orbit": "sphere"}, "circ": {}}, "grid": {"geometry": "sph"}})
    assert cfg["baselines"]["geometry"] == "sph"
    cfg = prepare_config({"radiographs": {"sph": {}, "circ": {}}, "baselines": {"geometry": "circ"}})
    assert cfg["baselines"]["geometry"] == "circ" and cfg["grid"]["geometry"] == "sph"
    with pytest.raises(CtsplatError, match="baselines.geometry: 'nope' is not a radiographs geometry"):
        prepare_config({"baselines": {"geometry": "nope"}})


def test_views_axis_must_fit_the_training_geometry():
    with pytest.raises(CtsplatError, match="grid.axes.views: 60 training views requested but geometry 'circular'"):
        prepare_config({"radiographs": {"circular": {"n_views": 50}}, "grid": {"axes": {"views": [25, 60]}}})
    prepare_config({"radiographs": {"circular": {"n_views": 60}}, "grid": {"axes": {"views": [25, 60]}}})
    with pytest.raises(CtsplatError, match="has only about 70 training views"):
        prepare_config({"radiographs": {"s": {"orbit": "sphere", "n_views": 100}},
                           "grid": {"axes": {"views": [80]}}})


def test_colmap_cells_must_fit_the_c_arm_view_set_and_others_the_grid_geometry():
    carm = {"camera": "cone", "orbit": "carm", "n_views": 30, "dso_mm": 600.0, "dsd_mm": 1000.0}
    # 40 views fit the circular geometry (50) but not the 30-view C-arm set that poses: colmap cells train on
    with pytest.raises(CtsplatError, match="40 training views requested but the C-arm view set of poses: colmap "
                                           "cells, 'carm' has only about 30"):
        prepare_config({"radiographs": {"circular": {"n_views": 50}, "carm": carm},
                        "grid": {"axes": {"poses": ["gt", "colmap"], "views": [20, 40]}}})
    # a colmap-only grid is measured against the C-arm set alone (the circular one has 12 views)
    prepare_config({"radiographs": {"circular": {"n_views": 12}, "carm": {**carm, "n_views": 90}},
                    "grid": {"axes": {"poses": ["colmap"], "views": [60]}}})


def test_baseline_view_counts_must_fit_the_baselines_geometry():
    with pytest.raises(CtsplatError, match=r"baselines\.n_views: 500 views requested but geometry 'circular' has "
                                           "only about 100"):
        prepare_config({"baselines": {"n_views": [10, 500]}})
    with pytest.raises(CtsplatError, match=r"invalid config at baselines\.n_views"):
        prepare_config({"baselines": {"n_views": []}})  # an empty list is not "the grid's views" (null is)
    assert prepare_config({"baselines": {"n_views": [10, 100]}})["baselines"]["n_views"] == [10, 100]


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({"volumes": {"p": {"source": "phantom", "preprocessing": {"denoise": "tv", "denoise_weight": -5}}}},
         "invalid config at volumes.p.preprocessing.denoise_weight: -5 is less than or equal to the minimum of 0"),
        ({"volumes": {"p": {"source": "phantom", "preprocessing": {"mu_water_per_mm": "x"}}}},
         "invalid config at volumes.p.preprocessing.mu_water_per_mm: 'x' is not of type 'number'"),
        ({"volumes": {"p": {"source": "phantom", "preprocessing": {"intensity": "window", "window": "brian"}}}},
         "invalid config at volumes.p.preprocessing: unknown window preset 'brian'"),
        ({"preprocessing": {"intensity": "window", "window": "brian"}},
         "invalid config at preprocessing: unknown window preset 'brian'"),
        ({"volumes": {"p": {"source": "phantom", "preprocessing": {"intensity": "hu"}}}},
         "invalid config at volumes.p.preprocessing.intensity: 'hu' keeps Hounsfield units"),
        ({"preprocessing": {"intensity": "hu"}}, "invalid config at preprocessing.intensity: 'hu' keeps"),
        ({"sfm": {"settings": {"percentile_low": 99.5, "percentile_high": 0.5}}},
         "invalid config at sfm.settings.percentile_low: 99.5 is not below percentile_high (0.5)"),
        ({"train": {"fbp_filter": "rampp"}}, "invalid config at train.fbp_filter: 'rampp' is not one of"),
        ({"radiographs": {"c": {"device": "gpu"}}}, "invalid config at radiographs.c.device"),
        ({"radiographs": {"c": {"split": {"train": 0.0, "val": 0.5, "test": 0.5}}}},
         "invalid config at radiographs.c.split.train"),
        ({"radiographs": {"s": {"orbit": "sphere", "n_val": 5}}},
         "invalid config at radiographs.s: n_val / n_test set the held-out views of orbit: circular"),
        ({"radiographs": {"c": {"pixel_spacing_mm": 1.0, "detector_size_factor": 2.0}}},
         "invalid config at radiographs.c: set pixel_spacing_mm or detector_size_factor, not both"),
        ({"radiographs": {"c": {"split": {"train": 0.85, "val": 0.0, "test": 0.15}}},
          "train": {"sharpen": {"amounts": [0.0, 0.5]}}},
         "invalid config at train.sharpen.amounts: the amount is chosen on validation views, but geometry 'c'"),
        ({"radiographs": {"c": {"split": {"train": 0.85, "val": 0.0, "test": 0.15}}},
          "train": {"model_selection": "best"}},
         "invalid config at train.model_selection: best chooses a model on validation views, but geometry 'c'"),
        # test metrics on the views that chose the settings: refused, not labelled after the fact
        ({"radiographs": {"c": {"n_test": 0}}},
         "invalid config at radiographs.c: the grid's geometry renders no test views, so the runs' test metrics would "
         "be measured on views that chose their settings; give it test views (n_test)"),
        ({"radiographs": {"c": {"split": {"train": 0.85, "val": 0.15, "test": 0.0}}}},
         "give it test views (n_test or split.test)"),
        ({"radiographs": {"s": {"orbit": "sphere", "split": {"train": 0.85, "val": 0.15, "test": 0.0}}}},
         "renders no test views, so the runs' test metrics would be measured on views that chose their settings; "
         "give it test views (split.test)"),
        ({"radiographs": {"c": {"n_val": 0}}, "baselines": {"enabled": True}},
         "invalid config at radiographs.c: the baselines' geometry renders no val views to choose the baselines' "
         "parameters on; give it val views (n_val) or set baselines.enabled: false"),
        ({"baselines": {"enabled": True, "settings": {"methods": ["fdk"]}}},
         "invalid config at baselines.settings.methods: ['fdk'] cannot reconstruct geometry 'circular' (parallel "
         "beam, orbit circular); it allows fbp, sart, asd_pocs, mbir"),
        ({"radiographs": {"s": {"orbit": "sphere", "camera": "cone"}},
          "baselines": {"settings": {"methods": ["mbir"]}}},
         "invalid config at baselines.settings.methods: ['mbir'] cannot reconstruct geometry 's' (cone beam, orbit "
         "sphere); it allows sart, asd_pocs"),
        ({"grid": {"axes": {"seed": [2**64]}}}, "invalid config at grid.axes.seed[0]: 18446744073709551616 is greater"),
        ({"volumes": {"p": {"source": "phantom", "phantom": {"seed": -1}}}}, "volumes.p.phantom.seed: -1 is less"),
        ({"volumes": {2024: {"source": "phantom"}}},
         "invalid config at volumes.2024: YAML read this name as the int 2024 (with a leading 0 it was read as an "
         "octal number), not text; quote it in the config file exactly as you wrote it (e.g. \"0051\":)"),
        ({"volumes": {True: {"source": "phantom"}}},
         "invalid config at volumes.True: YAML read this name as the bool True, not text; quote it"),
        ({"radiographs": {1: {"camera": "parallel"}}},
         "invalid config at radiographs.1: YAML read this name as the int 1"),
        ({"volumes": {"logs": {"source": "phantom"}}},
         "invalid config at volumes.logs: results/logs is the workflow's own; rename the volume"),
        ({"volumes": {"Head": {"source": "phantom"}, "head": {"source": "phantom"}}},
         "invalid config at volumes.head: 'Head' and 'head' differ only in case"),
    ],
    ids=["volume-range", "volume-type", "volume-window", "window", "volume-hu", "hu", "sfm-percentiles",
         "fbp-filter", "radiographs-device", "no-train-views", "sphere-n-val", "spacing-and-size", "sharpen-no-val",
         "best-no-val", "no-test-views", "no-test-fraction", "sphere-no-test-views", "baselines-no-val",
         "baselines-method-parallel",
         "baselines-method-sphere", "seed-too-large", "phantom-seed", "numeric-volume-name", "bool-volume-name",
         "numeric-geometry-name",
         "reserved-volume-name", "volume-names-by-case"],
)
def test_values_that_would_fail_a_job_fail_at_parse_time(config, message):
    with pytest.raises(CtsplatError) as err:
        prepare_config(config)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_ct_source_folder_must_hold_a_scan(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(CtsplatError, match=r"volumes\.v\.source is an empty folder"):
        prepare_config({"volumes": {"v": {"source": str(tmp_path / "empty")}}})
    (tmp_path / "photos").mkdir()
    for n in ("01.jpg", "02.JPG", "03.png"):
        (tmp_path / "photos" / n).write_bytes(b"")
    with pytest.raises(CtsplatError, match=r"holds photographs \(3 \.jpg/\.png files\), not a scan: for the photo "
                                           r"path set volumes\.v\.kind: photos"):
        prepare_config({"volumes": {"v": {"source": str(tmp_path / "photos")}}})
    (tmp_path / "photos" / "slice.dcm").write_bytes(b"")  # something else beside them: the ingest step decides
    prepare_config({"volumes": {"v": {"source": str(tmp_path / "photos")}}})


def test_scan_and_photo_sources_are_checked_for_their_kind_before_any_job(tmp_path, monkeypatch):
    """A file that is neither NIfTI nor TIFF, a photo folder without enough photographs, CT keys on a photo volume:
    each one line at parse time; `~` is the home folder, and a numeric series_uid is a series number."""
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(CtsplatError, match=r"volumes\.v\.source is a file that is neither NIfTI nor a TIFF stack: "
                                           r"'notes\.txt' \(suffixes \.nii, \.nii\.gz, \.tif, \.tiff\)"):
        prepare_config({"volumes": {"v": {"source": "notes.txt"}}}, base_dir=tmp_path)
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "readme.txt").write_text("x")
    ct = {"p": {"source": "phantom"}}
    with pytest.raises(CtsplatError, match=r"invalid config at volumes\.s\.source: photo folder .* holds no images"):
        prepare_config({"volumes": {**ct, "s": {"source": "photos", "kind": "photos"}}}, base_dir=tmp_path)
    (photos / "a.jpg").write_bytes(b"")
    (photos / "b.JPG").write_bytes(b"")
    with pytest.raises(CtsplatError, match=r"volumes\.s\.source: photos holds 2 photos; SfM needs at least 3 "
                                           r"registered in one model \(photos\.sfm\.min_registered\)"):
        prepare_config({"volumes": {**ct, "s": {"source": "photos", "kind": "photos"}}}, base_dir=tmp_path)
    (photos / "c.png").write_bytes(b"")
    cfg = prepare_config({"volumes": {**ct, "s": {"source": "photos", "kind": "photos"}}}, base_dir=tmp_path)
    assert list(cfg["photo_volumes"]) == ["s"]
    with pytest.raises(CtsplatError, match=r"invalid config at volumes\.s\.preprocessing: a volume of kind photos "
                                           r"reads only source; preprocessing, series_uid apply to CT volumes"):
        prepare_config({"volumes": {**ct, "s": {"source": "photos", "kind": "photos", "series_uid": "x",
                                                "preprocessing": {"grid": 16}}}}, base_dir=tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "scan").mkdir()
    (tmp_path / "scan" / "slice_0000.dcm").write_bytes(b"")
    cfg = prepare_config({"volumes": {"v": {"source": "~/scan", "series_uid": 3}}}, base_dir="/")
    assert cfg["volumes"]["v"]["source"] == str(tmp_path / "scan")
    assert cfg["volumes"]["v"]["series_uid"] == "3"
    # a UID written as a YAML list ([1.3...] unquoted, as a DICOM dump shows it) is refused without being echoed
    uid = "1.3.12.2.1107.5.1.1.20707.20020604104421111.3"
    with pytest.raises(CtsplatError, match=r"volumes\.v\.series_uid: give the series id") as err:
        prepare_config({"volumes": {"v": {"source": "~/scan", "series_uid": [uid]}}}, base_dir="/")
    assert "20707" not in str(err.value)


def test_a_number_given_as_text_is_named_as_text():
    """Snakemake's --config passes a nested value as text ("train={'iterations': 5}" gives '5')."""
    with pytest.raises(CtsplatError, match=r"train\.iterations: '5' is not of type 'integer' \(the value is text: "
                                           r"quoted in the file, or a nested value of Snakemake's --config"):
        prepare_config({"train": {"iterations": "5"}})
    with pytest.raises(CtsplatError, match=r"train\.iterations: 'five' is not of type 'integer'$"):
        prepare_config({"train": {"iterations": "five"}})


def test_split_error_marks_the_fractions_filled_in_by_default():
    with pytest.raises(CtsplatError, match=r"got 1\.15 \(train: 0\.7, val: 0\.3, test: 0\.15 \(default\)\)"):
        prepare_config({"radiographs": {"c": {"split": {"train": 0.7, "val": 0.3}}}})


def test_config_text_with_a_repeated_key_is_refused_naming_key_line_and_file(tmp_path):
    text = "volumes:\n  head: {source: a}\n  head: {source: phantom}\ntrain:\n  iterations: 5\n"
    with pytest.raises(CtsplatError, match=r"^key 'head' appears twice in one mapping \(again on line 3\); keep one$"):
        load_config_text(text)
    assert load_config_text("a: {x: 1}\nb: {x: 2}\n") == {"a": {"x": 1}, "b": {"x": 2}}  # equal keys, two mappings
    # a YAML merge key brings keys that the mapping may override; an unhashable key stays YAML's own error
    merged = load_config_text("base: &b {iterations: 5, seed: 1}\ntrain:\n  <<: *b\n  seed: 2\n")
    assert merged["train"] == {"iterations": 5, "seed": 2}
    with pytest.raises(yaml.YAMLError, match="unhashable"):
        load_config_text("? [a, b]\n: 1\n")
    (tmp_path / "ok.yaml").write_text("train: {iterations: 5}\n")
    (tmp_path / "twice.yaml").write_text(text)
    check_config_files([tmp_path / "ok.yaml"])
    with pytest.raises(CtsplatError, match=r"config file .*twice\.yaml: key 'head' appears twice"):
        check_config_files([tmp_path / "ok.yaml", tmp_path / "twice.yaml"])
    from ctsplat.cli._common import load_section

    with pytest.raises(CtsplatError, match=r"config file .*twice\.yaml: key 'head' appears twice"):
        load_section(str(tmp_path / "twice.yaml"), "train")


def test_classical_methods_from_settings_match_those_of_the_rendered_view_set():
    """The parse-time rule (settings) and the baseline step's (rendered views) agree on every orbit kind."""
    from ctsplat.formats.volume import Volume
    from ctsplat.geometry.orbits import classical_methods
    from ctsplat.projector import RADIOGRAPHS_DEFAULTS, build_view_set
    from ctsplat.recon.suite import applicable_methods

    data = np.zeros((16, 16, 16), np.float32)
    data[4:12, 4:12, 4:12] = 1.0
    volume = Volume(data, np.diag([2.0, 2.0, 2.0, 1.0]), {"volume_id": "cube", "intensity": {"mu_scale_per_mm": 0.02}})
    kinds = [{"camera": "parallel"}, {"camera": "cone"}, {"camera": "cone", "wobble_deg": 5.0},
             {"camera": "parallel", "wobble_deg": 5.0}, {"camera": "parallel", "wobble_deg": 5.0, "wobble_cycles": 0.0},
             {"camera": "parallel", "orbit": "sphere"},
             {"camera": "cone", "orbit": "sphere"}]
    for kind in kinds:
        settings = {**RADIOGRAPHS_DEFAULTS, "n_views": 24, "detector_width": 24, "detector_height": 24, **kind}
        view_set = build_view_set(volume, settings)
        assert set(applicable_methods(view_set)) == set(classical_methods(settings)), kind


def test_photo_validation_fold_must_lie_below_test_every(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a.jpg", "b.jpg", "c.jpg"):
        (photos / name).write_bytes(b"")
    config = {"volumes": {"p": {"source": "phantom"}, "skull": {"source": str(photos), "kind": "photos"}},
              "photos": {"train": {"holdout": "validation", "validation_offset": 50}}}
    with pytest.raises(CtsplatError, match=r"invalid config at photos\.train\.validation_offset must be "
                                           r"1\.\.7 \(test_every 8\), got 50"):
        prepare_config(config)


def test_split_fractions_must_sum_to_one():
    with pytest.raises(CtsplatError, match=r"at radiographs\.c\.split: fractions must sum to 1, got 1\.4 \(train"):
        prepare_config({"radiographs": {"c": {"split": {"train": 0.9, "val": 0.25, "test": 0.25}}}})
    with pytest.raises(CtsplatError, match=r"radiographs\.c\.split: fractions must sum to 1, got 0\.85"):
        prepare_config({"radiographs": {"c": {"split": {"train": 0.7, "val": 0.15, "test": 0.0}}}})
    # within 1e-6 of 1 (thirds) is accepted
    prepare_config({"radiographs": {"c": {"split": {"train": 0.333333, "val": 0.333333, "test": 0.333334}}}})
    with pytest.raises(CtsplatError, match=r"invalid config at radiographs\.split: fractions must sum to 1"):
        check_section("radiographs", {"split": {"train": 0.9}})


@pytest.mark.parametrize(
    ("entry", "where", "value"),
    [
        ({"init": "fpb"}, "grid.exclude[0].init", "'fpb'"),
        ({"init": ["fbp", "volum"]}, "grid.exclude[0].init", "'volum'"),
        ({"views": 7}, "grid.exclude[0].views", "7"),
        ({"mip": "off"}, "grid.exclude[0].mip", "'off'"),
        ({"volume": "haed"}, "grid.exclude[0].volume", "'haed'"),
    ],
)
def test_grid_exclude_values_must_match_an_axis_value(entry, where, value):
    axes = {"init": ["fbp", "volume"], "views": [5, 10], "mip": ["on"]}
    with pytest.raises(CtsplatError) as err:
        prepare_config({"volumes": {"head": {"source": "phantom"}}, "radiographs": {"c": {"n_views": 20}},
                        "grid": {"axes": axes, "exclude": [entry]}})
    assert str(err.value).startswith(f"invalid config at {where}: {value} is not a")
    cfg = prepare_config({"volumes": {"head": {"source": "phantom"}}, "radiographs": {"c": {"n_views": 20}},
                          "grid": {"axes": {**axes, "mip": ["on", False]},
                                   "exclude": [{"init": "volume", "views": [10], "mip": "off", "volume": "head"}]}})
    assert len(cfg["grid"]["exclude"]) == 1


@pytest.mark.parametrize(
    ("section", "values", "message"),
    [
        ("radiographs", {"n_views": "abc"}, "radiographs.n_views: 'abc' is not of type 'integer'"),
        ("train", {"eval_every": "abc"}, "train.eval_every: 'abc' is not of type 'integer'"),
        ("train", {"lr": {"means": "fast"}}, "train.lr.means: 'fast' is not of type 'number'"),
        ("train", {"views": -1}, "train.views: -1 is less than the minimum of 0"),  # a key the workflow sets
        ("train", {"compositor": "radiative_rectified"}, "train.compositor: 'radiative_rectified' is not one of"),
        ("baselines", {"n_views": [10, "x"]}, "baselines.n_views[1]: 'x' is not of type 'integer'"),
        ("sfm", {"max_ratio": 1.5}, "sfm.max_ratio: 1.5 is greater than the maximum of 1"),
        ("preprocessing", {"grid": 1}, "preprocessing.grid: 1 is less than the minimum of 2"),
    ],
)
def test_check_section_refuses_wrong_types_naming_key_and_type(section, values, message):
    with pytest.raises(CtsplatError) as err:
        check_section(section, values)
    assert str(err.value).startswith(f"invalid config at {message}")


def test_check_section_accepts_the_library_defaults():
    for section, (module, attr) in LIBRARY_SECTIONS.items():
        defaults = getattr(pytest.importorskip(module), attr)
        assert check_section(section, defaults) == defaults


def test_sfm_needs_its_carm_geometry_and_carm_is_never_the_training_geometry():
    carm = {"camera": "cone", "orbit": "carm", "n_views": 30}
    colmap_axes = {"init": ["fbp"], "compositor": ["radiative"], "mip": ["on"], "poses": ["colmap"],
                   "views": [10], "seed": [0]}
    with pytest.raises(CtsplatError, match=r"sfm\.settings\.geometry: 'carm' is not a radiographs geometry"):
        prepare_config({"radiographs": {"circ": {}}, "grid": {"axes": colmap_axes}})
    with pytest.raises(CtsplatError, match=r"sfm\.settings\.geometry: 'circ' is not a C-arm orbit"):
        prepare_config({"radiographs": {"circ": {}}, "sfm": {"enabled": True, "settings": {"geometry": "circ"}}})
    # the first geometry that is not a C-arm orbit trains; naming the C-arm one is refused
    cfg = prepare_config({"radiographs": {"carm": carm, "circ": {}}, "grid": {"axes": colmap_axes}})
    assert cfg["grid"]["geometry"] == "circ"
    with pytest.raises(CtsplatError, match=r"grid\.geometry: 'carm' is a C-arm orbit"):
        prepare_config({"radiographs": {"carm": carm, "circ": {}}, "grid": {"geometry": "carm"}})
    with pytest.raises(CtsplatError, match="every geometry is a C-arm orbit"):
        prepare_config({"radiographs": {"carm": carm}})
    assert prepare_config({"radiographs": {"circ": {}}})["sfm"]["enabled"] is False  # no SfM, no C-arm needed


# ---------------------------------------------------------------------------------------------------------------
# Every numeric key of the schema has a range: the README's promise that bad values fail before any job runs
# ---------------------------------------------------------------------------------------------------------------

#: Numeric keys without a meaningful bound, with the reason (key paths as errors show them, placeholders for names).
UNBOUNDED = {
    "preprocessing.window[0]": "window level: any HU value",
    "radiographs.g.start_deg": "start angle of the orbit: any angle (periodic)",
    "radiographs.g.isocenter_mm[0]": "a point in world mm",
    "sfm.settings.sift_first_octave": "SIFT octave index: negative upsamples, any integer is valid",
    "volumes.v.rescale[1]": "rescale intercept: any HU offset",
    "grid.exclude[0].views": "checked against the views axis by check_grid_exclude",
    "grid.exclude[0].seed": "checked against the seed axis by check_grid_exclude",
}
# names used for the free-form parts of the config (volume and geometry names)
PLACEHOLDERS = {"volumes": "v", "radiographs": "g"}


def _numeric_leaves(schema, node, path):
    """(key path parts, sub-schema, array lengths along the path) of every numeric value the schema allows."""
    if "$ref" in node:
        ref = node["$ref"].split("/")[-1]
        node = {**schema["$defs"][ref], **{k: v for k, v in node.items() if k != "$ref"}}
    for sub in node.get("allOf", []) + node.get("oneOf", []) + node.get("anyOf", []):
        yield from _numeric_leaves(schema, sub, path)
    for key, sub in (node.get("properties") or {}).items():
        yield from _numeric_leaves(schema, sub, [*path, key])
    extra = node.get("additionalProperties")
    if isinstance(extra, dict) and path and path[-1] in PLACEHOLDERS:
        yield from _numeric_leaves(schema, extra, [*path, PLACEHOLDERS[path[-1]]])
    prefix = node.get("prefixItems", [])
    for i, sub in enumerate(prefix):
        yield from _numeric_leaves(schema, sub, [*path, (i, node.get("minItems", 1))])
    if isinstance(node.get("items"), dict) and not prefix:
        yield from _numeric_leaves(schema, node["items"], [*path, (0, node.get("minItems", 1))])
    types = node.get("type", [])
    types = [types] if isinstance(types, str) else types
    if {"number", "integer"} & set(types):
        yield path, node


def _where(path):
    return "".join(f"[{p[0]}]" if isinstance(p, tuple) else (f".{p}" if i else p) for i, p in enumerate(path))


def _out_of_range(node):
    """Values just outside the sub-schema's range (below the lower bound, above the upper bound)."""
    integer = node.get("type") == "integer" or node.get("type") == ["integer"]
    out = []
    if "minimum" in node:
        out.append(node["minimum"] - 1 if integer else node["minimum"] - 0.5)
    if "exclusiveMinimum" in node:
        out.append(node["exclusiveMinimum"])
    if "maximum" in node:
        out.append(node["maximum"] + 1 if integer else node["maximum"] + 0.5)
    if "exclusiveMaximum" in node:
        out.append(node["exclusiveMaximum"])
    return out


def _config_with(path, value):
    """A config that is valid except for ``value`` at ``path`` (arrays filled with in-range values)."""
    config: dict = {}
    node = config
    for i, part in enumerate(path):
        last = i == len(path) - 1
        nxt = None if last else path[i + 1]
        if isinstance(part, tuple):
            raise AssertionError("arrays are built by their parent")
        if isinstance(nxt, tuple):  # an array of numbers: fill it with values that are in range everywhere
            index, length = nxt
            arr = [1.0] * max(length, index + 1)
            arr[index] = value
            node[part] = arr
            assert i + 1 == len(path) - 1, "numbers only at the end of arrays"
            break
        if last:
            node[part] = value
        else:
            node = node.setdefault(part, {"source": "phantom"} if path[i - 1:i] == ["volumes"] else {})
    return config


def _schema_leaves():
    schema = load_schema()
    return list(_numeric_leaves(schema, schema, []))


def test_schema_walk_finds_the_nested_numeric_keys():
    where = {_where(p) for p, _ in _schema_leaves()}
    for key in ("train.lr.means", "train.densify.grad_threshold", "radiographs.g.noise.i0", "radiographs.g.split.val",
                "volumes.v.phantom.size", "sfm.settings.max_ratio", "baselines.settings.sart_relaxation",
                "analysis.milestones.ssim2d", "resources.train.threads", "grid.axes.views[0]",
                "preprocessing.window[1]", "train.nan_lr_decay", "train.checkpoint_every", "train.eval_every"):
        assert key in where
    assert set(UNBOUNDED) <= where  # the exceptions name real keys


@pytest.mark.parametrize(("path", "node"), _schema_leaves(), ids=[_where(p) for p, _ in _schema_leaves()])
def test_every_numeric_key_refuses_an_out_of_range_value(path, node):
    where = _where(path)
    bad = _out_of_range(node)
    if where in UNBOUNDED:
        assert not bad, f"{where} has a bound now: remove it from UNBOUNDED"
        return
    assert bad, f"{where} has no range in the schema (add one in ctsplat.config.REFINE or list it in UNBOUNDED)"
    for value in bad:
        config = _config_with(path, value)
        with pytest.raises(CtsplatError) as err:
            validate_config(config)
        msg = str(err.value)
        assert msg.startswith(f"invalid config at {where}:"), (value, msg)
        assert "\n" not in msg


def test_needs_sfm_follows_enabled_and_the_cells():
    from ctsplat.grid import expand_grid, needs_sfm

    axes = {"init": ["fbp"], "compositor": ["radiative"], "mip": ["on"], "poses": ["gt"], "views": [4], "seed": [0]}
    assert not needs_sfm(expand_grid(axes, ["v"], []))
    assert needs_sfm(expand_grid(axes, ["v"], []), enabled=True)
    assert needs_sfm(expand_grid({**axes, "poses": ["gt", "colmap"]}, ["v"], []))
    assert needs_sfm(expand_grid({**axes, "init": ["sfm"]}, ["v"], []))


def test_a_rule_given_some_resources_keeps_the_defaults_of_the_others():
    cfg = prepare_config({"volumes": {"phantom": {"source": "phantom"}}, "resources": {"train": {"threads": 2}}})
    default = prepare_config({"volumes": {"phantom": {"source": "phantom"}}})["resources"]
    assert cfg["resources"]["train"] == {**default["train"], "threads": 2}
    assert set(default["train"]) == {"threads", "mem_mb", "runtime"}
    assert {r: v for r, v in cfg["resources"].items() if r != "train"} == {
        r: v for r, v in default.items() if r != "train"}


def test_an_sfm_run_marked_ok_must_be_one_training_accepts():
    cfg = {"volumes": {"phantom": {"source": "phantom"}}, "sfm": {"enabled": True, "settings": {
        "geometry": "carm", "min_registration_rate": 0.3}},
        "radiographs": {"circular": {}, "carm": {"camera": "cone", "orbit": "carm"}}}
    with pytest.raises(CtsplatError, match=r"sfm.settings.min_registration_rate: 0.3 is below "
                                           r"train.min_registration_rate \(0.5\)"):
        prepare_config(cfg)
    prepare_config({**cfg, "train": {"min_registration_rate": 0.3}})


def test_volume_settings_must_fit_their_kind_of_source(tmp_path):
    from ctsplat.formats.volume import Volume, save_volume

    save_volume(Volume(np.ones((4, 4, 4), np.float32), np.eye(4), {"volume_id": "v"}), tmp_path / "v.nii.gz")
    (tmp_path / "v.tif").write_bytes(b"II*\x00")
    (tmp_path / "ct").mkdir()
    (tmp_path / "ct" / "slice_0000.dcm").write_bytes(b"")
    cases = [
        ({"source": "v.nii.gz", "rescale": [1, -1024]}, r"volumes\.a\.rescale: it applies to DICOM sources only, "
                                                        r"and 'v\.nii\.gz' is NIFTI"),
        ({"source": "v.nii.gz", "series_uid": "3"}, r"volumes\.a\.series_uid: it applies to DICOM"),
        ({"source": "v.nii.gz", "skip_corrupt": True}, r"volumes\.a\.skip_corrupt: it applies to DICOM"),
        ({"source": "ct", "tiff_voxel_size_mm": 1.0}, r"volumes\.a\.tiff_voxel_size_mm: it applies to TIFF sources "
                                                      r"only, and 'ct' is DICOM"),
        ({"source": "v.tif"}, r"volumes\.a\.tiff_voxel_size_mm: a TIFF stack has no voxel size"),
        ({"source": "ct", "phantom": {"size": 32}}, r"volumes\.a\.phantom: it sets up the built-in phantom"),
        ({"source": "results/a/volume.nii.gz"}, r"volumes\.a\.source: 'results/a/volume\.nii\.gz' lies in "
                                                r"results/a/, the folder the workflow writes"),
    ]
    (tmp_path / "results" / "a").mkdir(parents=True)
    (tmp_path / "results" / "a" / "volume.nii.gz").write_bytes((tmp_path / "v.nii.gz").read_bytes())
    for vol, match in cases:
        with pytest.raises(CtsplatError, match=match):
            prepare_config({"volumes": {"a": vol}}, base_dir=tmp_path)
    for vol in ({"source": "v.tif", "tiff_voxel_size_mm": 0.5}, {"source": "ct", "rescale": [1, -1024]},
                {"source": "phantom", "phantom": {"size": 32}, "skip_corrupt": False},
                {"source": "results/b/volume.nii.gz"}):  # another volume's output is an ordinary input
        if "results/b" in vol["source"]:
            (tmp_path / "results" / "b").mkdir()
            (tmp_path / "results" / "b" / "volume.nii.gz").write_bytes((tmp_path / "v.nii.gz").read_bytes())
        prepare_config({"volumes": {"a": vol}}, base_dir=tmp_path)
