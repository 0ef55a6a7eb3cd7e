"""Workflow config validation (JSON schema, defaults, key paths), library-defaults mirror, schema shipped as package
data, grid expansion."""

from __future__ import annotations

import importlib
import itertools
from importlib import resources
from pathlib import Path

import pytest
import yaml

from ctsplat.config import (
    LIBRARY_SECTIONS,
    check_library_sections,
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
    assert cfg["analysis"]["milestones"] == {"psnr2d": 30.0, "ssim2d": 0.9}
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
    ],
)
def test_bad_values_name_the_key_path(config, where):
    with pytest.raises(CtsplatError) as err:
        validate_config(config)
    assert f"invalid config at {where}:" in str(err.value)
    assert "\n" not in str(err.value)


def test_unknown_key_lists_allowed_keys():
    with pytest.raises(CtsplatError, match=r"invalid config at grid: .*'axis'.*allowed: axes, exclude, geometry"):
        validate_config({"grid": {"axis": {}}})
    with pytest.raises(CtsplatError, match=r"invalid config at <config>: .*'trian'"):
        validate_config({"trian": {}})


def test_validate_does_not_mutate_input():
    cfg = {"grid": {"axes": {"views": [5]}}}
    validate_config(cfg)
    assert cfg == {"grid": {"axes": {"views": [5]}}}


SECTION_PATHS = {"preprocessing": ("preprocessing",), "radiographs": ("radiographs", "circular"),
                 "sfm": ("sfm", "settings"), "train": ("train",), "baselines": ("baselines", "settings")}


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
    assert analysis["milestones"] == {"psnr2d": 30.0, "ssim2d": 0.9}
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


def test_missing_volume_source_is_reported_with_key(tmp_path):
    with pytest.raises(CtsplatError, match=r"volumes\.head\.source: 'nope/ct'"):
        prepare_config({"volumes": {"head": {"source": "nope/ct"}}}, base_dir=tmp_path)
    (tmp_path / "ct").mkdir()
    cfg = prepare_config({"volumes": {"head": {"source": "ct"}}}, base_dir=tmp_path)
    assert cfg["grid"]["geometry"] == "circular"


def test_grid_geometry_must_exist():
    with pytest.raises(CtsplatError, match="grid.geometry: 'cone' is not a radiographs geometry"):
        prepare_config({"grid": {"geometry": "cone"}})


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_configs_validate(path):
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
