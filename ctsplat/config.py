"""The workflow configuration: JSON schema, defaults, and the checks run before any job.

The schema (``ctsplat/schemas/config.schema.yaml``, JSON Schema Draft 2020-12, shipped as package data) defines
every key of the workflow config with its default; :func:`validate_config` fills those defaults while validating
and names the key path of the first error. The library sections of the schema (``preprocessing``,
``radiographs.<geometry>``, ``baselines.settings``, ``sfm.settings``, ``train``) mirror the ``*_DEFAULTS`` dicts
of the modules listed in :data:`LIBRARY_SECTIONS`; ``python -m ctsplat.config --sync-defaults`` regenerates them
after a module changes its defaults. Every numeric key has a range (:data:`REFINE`). :func:`check_section` applies
the same types and ranges to one section as a command-line step receives it (a config file plus ``--set``).
"""

from __future__ import annotations

import argparse
import copy
import functools
import importlib
import os
import textwrap
from collections.abc import Iterable, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from ctsplat.grid import expand_grid, needs_sfm, uses_colmap
from ctsplat.photos.config import DENSIFY_CHOICES
from ctsplat.utils import SEED_MAX, CtsplatError, first_nonfinite, merge_config, unknown_key_message

__all__ = [
    "LIBRARY_SECTIONS",
    "canonical",
    "on_workflow_device",
    "load_schema",
    "validate_config",
    "schema_defaults",
    "check_library_sections",
    "check_volume_sources",
    "check_section",
    "check_values",
    "check_split",
    "check_grid_exclude",
    "section_schema",
    "prepare_config",
    "sync_library_defaults",
    "RESULTS_DIR",
]

SCHEMA_RESOURCE = "schemas/config.schema.yaml"  # inside the ctsplat package

#: The workflow's output folder, relative to its working directory: ``RESULTS_DIR/{volume}/...``.
RESULTS_DIR = "results"

# Library section of the workflow config -> (module, attribute holding the section's defaults).
LIBRARY_SECTIONS: dict[str, tuple[str, str]] = {
    "preprocessing": ("ctsplat.volume", "PREPROCESSING_DEFAULTS"),
    "radiographs": ("ctsplat.projector", "RADIOGRAPHS_DEFAULTS"),
    "sfm": ("ctsplat.sfm.step", "SFM_DEFAULTS"),
    "train": ("ctsplat.training.config", "TRAIN_DEFAULTS"),
    "baselines": ("ctsplat.baselines", "BASELINES_DEFAULTS"),
    "photos": ("ctsplat.photos.config", "PHOTOS_DEFAULTS"),
}


# ----------------------------------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------------------------------


def load_schema(path: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Load the workflow config JSON schema.

    Parameters
    ----------
    path : path-like, optional
        A YAML or JSON schema file; default: the schema shipped in the ``ctsplat`` package.

    Returns
    -------
    dict
        The schema.
    """
    import yaml

    if path is None:
        return copy.deepcopy(_shipped_schema())
    with open(path, encoding="utf-8") as fh:
        return yaml.safe_load(fh)


@functools.cache
def _shipped_schema() -> dict[str, Any]:
    import yaml  # parsing the YAML takes ~0.2 s: once per process

    return yaml.safe_load(resources.files("ctsplat").joinpath(SCHEMA_RESOURCE).read_text(encoding="utf-8"))


def load_config_text(text: str) -> Any:
    """Parse a YAML (or JSON) config, refusing a key repeated within one mapping.

    PyYAML, and with it Snakemake's ``--configfile``, keeps the last of two equal keys without a word, so a second
    ``volumes: head:`` or ``train:`` block would silently replace the first.

    Parameters
    ----------
    text : str
        The file's text.

    Returns
    -------
    object
        What :func:`yaml.safe_load` returns.

    Raises
    ------
    CtsplatError
        For a repeated key, naming it and its line.
    yaml.YAMLError
        For text that is not YAML.

    Examples
    --------
    >>> load_config_text("train:\\n  iterations: 5\\ntrain:\\n  iterations: 6\\n")
    Traceback (most recent call last):
    ...
    ctsplat.utils.CtsplatError: key 'train' appears twice in one mapping (again on line 3); keep one
    """
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
            seen: set[Any] = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *anchor`: keys written here override it
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    repeated = key in seen
                except TypeError:  # an unhashable key: SafeLoader's own error below says so
                    break
                if repeated:
                    raise CtsplatError(f"key {key!r} appears twice in one mapping (again on line "
                                       f"{key_node.start_mark.line + 1}); keep one")
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)


def check_config_files(paths: Iterable[str | os.PathLike[str]]) -> None:
    """Refuse a workflow config file that repeats a key (:func:`load_config_text`), naming the file.

    Parameters
    ----------
    paths : iterable of path-like
        The files given to ``--configfile`` (or the default config).

    Raises
    ------
    CtsplatError
        For the first repeated key.
    """
    import yaml

    for path in paths:
        try:
            load_config_text(Path(path).read_text(encoding="utf-8"))
        except CtsplatError as exc:
            raise CtsplatError(f"config file {path}: {exc}") from None
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            continue  # Snakemake read it already, and reports what it cannot read


def _key_path(parts: Iterable[Any]) -> str:
    """``grid.axes.views[0]`` from the path parts of a validation error (``<config>`` for the root)."""
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "<config>"


def _validator_with_defaults():
    """A Draft 2020-12 validator class that fills ``default`` values of missing properties while validating."""
    from jsonschema import Draft202012Validator, validators

    base_properties = Draft202012Validator.VALIDATORS["properties"]

    def properties_with_defaults(validator, properties, instance, schema):
        if validator.is_type(instance, "object"):
            for name, sub in properties.items():
                if isinstance(sub, dict) and "default" in sub and name not in instance:
                    instance[name] = copy.deepcopy(sub["default"])
        yield from base_properties(validator, properties, instance, schema)

    return validators.extend(Draft202012Validator, {"properties": properties_with_defaults})


def validate_config(config: Mapping[str, Any], schema: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Validate a workflow config against the schema and fill its defaults.

    Parameters
    ----------
    config : mapping
        The workflow config (as loaded from YAML); not modified.
    schema : mapping, optional
        Default: :func:`load_schema`.

    Returns
    -------
    dict
        A deep copy of ``config`` with every missing key that has a schema default filled in.

    Raises
    ------
    CtsplatError
        On the first (deepest-path) error, naming the key path, e.g.
        ``invalid config at grid.axes.views[0]: 'ten' is not of type 'integer'``.
    """
    schema = load_schema() if schema is None else schema
    filled = copy.deepcopy(dict(config))
    _reject_non_string_keys(filled)
    _reject_non_finite(filled)
    cls = _validator_with_defaults()
    _raise_first_error(cls(schema).iter_errors(filled))
    return filled


def _reject_non_string_keys(values: Any, prefix: str = "") -> None:
    """Refuse mapping keys that YAML read as something other than text: a volume named ``2024:`` becomes the
    integer 2024 (``0051:`` the octal 41, ``on:`` True), which the schema's name patterns never see and the rules
    cannot find again. One line naming the key and how to quote it."""
    if isinstance(values, Mapping):
        for key, value in values.items():
            if not isinstance(key, str):
                where = f"{prefix}." if prefix else ""
                octal = " (with a leading 0 it was read as an octal number)" if type(key) is int else ""
                raise CtsplatError(f"invalid config at {where}{key!r}: YAML read this name as the "
                                   f"{type(key).__name__} {key!r}{octal}, not text; quote it in the config file "
                                   "exactly as you wrote it (e.g. \"0051\":)")
            _reject_non_string_keys(value, f"{prefix}.{key}" if prefix else key)
    elif isinstance(values, list):
        for i, value in enumerate(values):
            _reject_non_string_keys(value, f"{prefix}[{i}]")


def _reject_non_finite(values: Any, prefix: str = "") -> None:
    """Refuse NaN and infinite numbers anywhere in a config (JSON schema ranges let NaN through, and ``--set x=NaN``
    or YAML's ``.nan`` parse as numbers); one line naming the key path."""
    where = first_nonfinite(values, prefix)
    if where is not None:
        raise CtsplatError(f"invalid config at {where or '<config>'}: not a finite number (NaN or infinite); give "
                           "a finite value")


def _raise_first_error(errors: Iterable[Any], prefix: Iterable[Any] = ()) -> None:
    """Raise the first (deepest-path) jsonschema error as one line naming its key path; nothing without errors."""
    errors = sorted(errors, key=lambda e: (-len(e.absolute_path), str(e.absolute_path)))
    if not errors:
        return
    err = errors[0]
    # oneOf/anyOf errors: report the most specific sub-error (deepest path; a range or enum error over a type
    # error of another alternative)
    if err.context:
        err = max(err.context, key=lambda e: (len(e.absolute_path), e.validator != "type"))
    where = _key_path([*prefix, *err.absolute_path])
    if where.endswith("series_uid"):  # jsonschema's message quotes the value, and a UID identifies a scan
        raise CtsplatError(f"invalid config at {where}: give the series id `ctsplat ingest SOURCE --list-series` "
                           "prints, or its series number (the value given is not shown: it may be a UID)")
    msg = err.message
    if err.validator == "additionalProperties" and isinstance(err.instance, Mapping):
        allowed = (err.schema.get("properties") or {}).keys()
        extra = sorted(str(k) for k in set(err.instance) - set(allowed))
        if allowed and extra:  # as a step names it (merge_config), with the closest allowed key
            section = "" if where == "<config>" else where
            raise CtsplatError(f"invalid config at {where}: {unknown_key_message(section, extra[0], allowed)}")
    if err.validator == "type" and isinstance(err.instance, str) and _reads_as_non_text(err.instance):
        msg += (" (the value is text: quoted in the file, or a nested value of Snakemake's --config, which arrives "
                "as text; write it unquoted in a --configfile)")
    elif err.validator == "type" and isinstance(err.instance, str) and (as_float := _yaml_float(err.instance)):
        types = err.validator_value if isinstance(err.validator_value, list) else [err.validator_value]
        value = float(as_float)
        if "number" in types:
            msg += (f" (YAML reads a number in exponent form as text unless it has a dot and a signed exponent: "
                    f"write {as_float})")
        elif "integer" in types and value.is_integer():
            msg += f" (YAML reads a number in exponent form as text: write {int(value)})"
    raise CtsplatError(f"invalid config at {where}: {msg}")


def _yaml_float(text: str) -> str | None:
    """``text`` as a YAML 1.1 float when it is a number in exponent form that YAML reads as text (``5e-5``,
    ``1.5E3``: no dot, or no sign on the exponent), e.g. ``5.0e-5``; None otherwise.

    Examples
    --------
    >>> _yaml_float("5e-5"), _yaml_float("1.5E3"), _yaml_float("abc")
    ('5.0e-5', '1.5e+3', None)
    """
    import re

    match = re.fullmatch(r"\s*([-+]?)(\d+)(?:\.(\d*))?[eE]([-+]?)(\d+)\s*", text)
    if match is None:
        return None
    sign, whole, frac, exp_sign, exp = match.groups()
    return f"{sign}{whole}.{frac or '0'}e{exp_sign or '+'}{exp}"


def _reads_as_non_text(text: str) -> bool:
    """Whether ``text`` would be a number, boolean or null had YAML read it unquoted."""
    import yaml

    try:
        return not isinstance(yaml.safe_load(text), str)
    except yaml.YAMLError:
        return False


def check_split(split: Mapping[str, Any], where: str, given: Iterable[str] | None = None) -> None:
    """Check that train/val/test fractions sum to 1 (within 1e-6).

    The orbits would normalise any sum, so a typo (``train: 0.9`` beside ``val: 0.25``) silently changes every
    split; the fractions must say what they mean.

    Parameters
    ----------
    split : mapping
        ``{"train": f, "val": f, "test": f}`` with the defaults filled.
    where : str
        Key path shown in the error, e.g. ``radiographs.circular.split``.
    given : iterable of str, optional
        The fractions the user wrote; the error marks the others as defaults (a user who wrote ``train`` and
        ``val`` alone may not know that ``test`` took its default). None: all were given.

    Raises
    ------
    CtsplatError
        When the fractions do not sum to 1.
    """
    values = {k: split.get(k, 0.0) for k in ("train", "val", "test")}
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values.values()):
        return  # a wrong type is the schema's error
    total = sum(float(v) for v in values.values())
    if abs(total - 1.0) > 1e-6:
        given = set(values) if given is None else set(given)
        shown = ", ".join(f"{k}: {v:g}" + ("" if k in given else " (default)") for k, v in values.items())
        raise CtsplatError(f"invalid config at {where}: fractions must sum to 1, got {total:g} ({shown}); e.g. "
                           "train: 0.7, val: 0.15, test: 0.15")


def section_schema(section: str) -> dict[str, Any]:
    """JSON schema of one library section as a step takes it, including the keys the workflow sets per run.

    The same types and ranges as the workflow schema's ``$defs`` (:data:`REFINE`); the keys of
    :data:`WORKFLOW_KEYS` are typed from the module's defaults (and refined where :data:`REFINE` names them).

    Parameters
    ----------
    section : str
        A key of :data:`LIBRARY_SECTIONS`.

    Returns
    -------
    dict
        The section's schema (imports the owning module).
    """
    mod_name, attr = LIBRARY_SECTIONS[section]
    defaults = getattr(importlib.import_module(mod_name), attr)
    return _schema_section(section, defaults, set(), "")


def check_values(values: Mapping[str, Any], schema: Mapping[str, Any], where: str) -> None:
    """Validate ``values`` against a (sub-)schema without filling defaults.

    Parameters
    ----------
    values : mapping
        The settings.
    schema : mapping
        A JSON schema, e.g. a section of :func:`load_schema`'s ``properties``.
    where : str
        Key path of ``values`` in the workflow config, prefixed to the error's key path (``a.b``).

    Raises
    ------
    CtsplatError
        For the first (deepest-path) error, naming its key path.
    """
    from jsonschema import Draft202012Validator

    _reject_non_finite(dict(values), where)
    _raise_first_error(Draft202012Validator(schema).iter_errors(dict(values)), where.split(".") if where else ())


def check_section(section: str, values: Mapping[str, Any], where: str | None = None) -> dict[str, Any]:
    """Check one library section's settings (a config file plus ``--set`` overrides) before a step runs.

    Unknown keys are refused as the step refuses them (:func:`ctsplat.utils.merge_config`); types and ranges come
    from :func:`section_schema`; ``radiographs`` split fractions must also sum to 1 (:func:`check_split`). Defaults
    are not filled: the step does that.

    Parameters
    ----------
    section : str
        A key of :data:`LIBRARY_SECTIONS`.
    values : mapping
        The user's settings for that section.
    where : str, optional
        Key path prefix shown in errors (default: ``section``).

    Returns
    -------
    dict
        ``values`` as a plain dict (unchanged).

    Raises
    ------
    CtsplatError
        One line naming the key path and what is expected, e.g.
        ``invalid config at train.lr.means: 'fast' is not of type 'number'``.
    """
    values = dict(values)
    where = section if where is None else where
    mod_name, attr = LIBRARY_SECTIONS[section]
    merge_config(where, values, getattr(importlib.import_module(mod_name), attr))  # unknown keys, as the step says
    check_values(values, section_schema(section), where)
    if section == "radiographs" and isinstance(values.get("split"), Mapping):
        check_split({"train": 0.7, "val": 0.15, "test": 0.15, **values["split"]}, f"{where}.split",
                    given=values["split"])
    return values


def check_grid_exclude(cfg: Mapping[str, Any]) -> None:
    """Check that every value named in ``grid.exclude`` is a value of its axis (or a volume name).

    An entry whose value matches nothing (a typo such as ``init: fpb``) would silently exclude nothing.

    Parameters
    ----------
    cfg : mapping
        The filled workflow config.

    Raises
    ------
    CtsplatError
        Naming ``grid.exclude[i].<key>``, the value and the values it can take.
    """
    from ctsplat.grid import ONOFF_AXES, normalise_mip

    axes = cfg["grid"]["axes"]
    known: dict[str, list[Any]] = {"volume": list(cfg["volumes"])}
    for name, vals in axes.items():
        known[name] = [normalise_mip(v, name) for v in vals] if name in ONOFF_AXES else list(vals)
    for i, entry in enumerate(cfg["grid"]["exclude"]):
        for key, vals in entry.items():
            for v in vals if isinstance(vals, list) else [vals]:
                try:
                    norm = normalise_mip(v, key) if key in ONOFF_AXES else v
                except CtsplatError:
                    norm = v
                if norm not in known.get(key, []):
                    shown = ", ".join(map(str, known.get(key, []))) or "the axis is not in grid.axes"
                    what = "a volume name" if key == "volume" else f"a value of grid.axes.{key}"
                    raise CtsplatError(f"invalid config at grid.exclude[{i}].{key}: {v!r} is not {what} ({shown}); "
                                       "fix or remove it (it would exclude nothing)")


@functools.cache
def _default_config() -> dict[str, Any]:
    return validate_config({})


def schema_defaults(section: str | None = None) -> dict[str, Any]:
    """The schema's defaults: the config an empty workflow config validates to, or one top-level section of it.

    Parameters
    ----------
    section : str, optional
        A top-level key of the workflow config, e.g. ``"analysis"``.

    Returns
    -------
    dict
        A fresh copy (safe to modify).
    """
    cfg = _default_config()
    return copy.deepcopy(cfg if section is None else cfg[section])


def check_library_sections(config: Mapping[str, Any], *, modules: Mapping[str, tuple[str, str]] | None = None) -> None:
    """Check library sections key by key against the owning modules' ``*_DEFAULTS``.

    A module that cannot be imported is skipped; each step re-checks its config with
    :func:`ctsplat.utils.merge_config` when it runs.

    Parameters
    ----------
    config : mapping
        The workflow config.
    modules : mapping, optional
        Section -> (module, attribute); default :data:`LIBRARY_SECTIONS`.

    Raises
    ------
    CtsplatError
        For a key the module's defaults do not have, naming its key path.
    """
    modules = LIBRARY_SECTIONS if modules is None else modules

    def defaults_of(section: str) -> dict[str, Any] | None:
        if section not in modules:
            return None
        mod_name, attr = modules[section]
        try:
            mod = importlib.import_module(mod_name)
        except ImportError:
            return None
        return getattr(mod, attr, None)

    for display, section, values in _library_section_values(config):
        defaults = defaults_of(section)
        if defaults is not None:
            merge_config(display, values, defaults)


def _library_section_values(config: Mapping[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """(key path shown in errors, LIBRARY_SECTIONS key, user values) for every library section in ``config``."""
    out: list[tuple[str, str, dict[str, Any]]] = [("preprocessing", "preprocessing", config.get("preprocessing", {}))]
    for name, vol in config.get("volumes", {}).items():
        out.append((f"volumes.{name}.preprocessing", "preprocessing", vol.get("preprocessing", {})))
    for geo, values in config.get("radiographs", {}).items():
        out.append((f"radiographs.{geo}", "radiographs", values))
    out.append(("baselines.settings", "baselines", config.get("baselines", {}).get("settings", {})))
    out.append(("sfm.settings", "sfm", config.get("sfm", {}).get("settings", {})))
    out.append(("train", "train", config.get("train", {})))
    out.append(("photos", "photos", config.get("photos", {})))
    return out


def _check_not_own_output(name: str, source: str, base_dir: str | os.PathLike[str]) -> None:
    """Refuse a source inside the volume's own results folder: the workflow writes there, and removes a step's
    outputs before it runs the step again (the source would be its own ingest output)."""
    if source == "phantom":
        return
    path = Path(source).expanduser()
    own = (Path(base_dir) / RESULTS_DIR / name).resolve()
    resolved = (path if path.is_absolute() else Path(base_dir) / path).resolve()
    if resolved == own or own in resolved.parents:
        raise CtsplatError(f"invalid config at volumes.{name}.source: {source!r} lies in {RESULTS_DIR}/{name}/, the "
                           "folder the workflow writes this volume's outputs to; move or copy it elsewhere")


def _check_source_keys(name: str, vol: Mapping[str, Any], given: Mapping[str, Any],
                       base_dir: str | os.PathLike[str]) -> None:
    """Refuse a CT volume's settings that its kind of source would ignore or refuse late, in its ingest job
    (:data:`ctsplat.formats.sources.SOURCE_KIND_KEYS`, ``phantom`` on a file source, a TIFF without a voxel size)."""
    from ctsplat.formats.sources import SOURCE_KIND_KEYS, source_kind

    source = str(vol["source"])
    path = Path(source).expanduser()
    kind = "dicom" if source == "phantom" else source_kind(path if path.is_absolute() else Path(base_dir) / path)
    for key, wants in SOURCE_KIND_KEYS.items():
        if given.get(key) not in (None, False) and kind != wants:
            raise CtsplatError(f"invalid config at volumes.{name}.{key}: it applies to {wants.upper()} sources only, "
                               f"and {source!r} is {str(kind).upper()}; remove it")
    if given.get("phantom") and source != "phantom":
        raise CtsplatError(f"invalid config at volumes.{name}.phantom: it sets up the built-in phantom (source: "
                           f"phantom), not {source!r}; remove it")
    if kind == "tiff" and vol.get("tiff_voxel_size_mm") is None:
        raise CtsplatError(f"invalid config at volumes.{name}.tiff_voxel_size_mm: a TIFF stack has no voxel size; "
                           "give it in mm (one number, or three for x, y, z)")


def check_volume_sources(volumes: Mapping[str, Mapping[str, Any]], base_dir: str | os.PathLike[str] = ".", *,
                         min_photos: int = 1) -> None:
    """Check that every volume source is ``phantom`` or an existing path of the kind its volume reads.

    Parameters
    ----------
    volumes : mapping
        The ``volumes`` section: name -> ``{source: ...}`` (a leading ``~`` is the user's home).
    base_dir : path-like
        Folder that relative source paths are resolved from (the workflow's working directory).
    min_photos : int
        Photographs a volume of kind ``photos`` needs at least (``photos.sfm.min_registered``).

    Raises
    ------
    CtsplatError
        For the first missing source, a scan file that is neither NIfTI nor TIFF, a scan folder that is empty or
        holds only photographs, or a photo folder with fewer than ``min_photos`` images; naming
        ``volumes.<name>.source``.
    """
    from ctsplat.formats.sources import SCAN_FILE_SUFFIXES, source_kind

    for name, vol in volumes.items():
        source = vol["source"]
        if source == "phantom" and vol.get("kind", "ct") != "photos":
            continue
        path = Path(source).expanduser()
        if not path.is_absolute():
            path = Path(base_dir) / path
        if vol.get("kind", "ct") == "photos":
            _check_photo_folder(name, source, path, min_photos)
            continue
        if not path.exists():
            raise CtsplatError(
                f"volume source not found at volumes.{name}.source: {source!r} (resolved to {path.resolve()}); "
                "give a DICOM folder, a .nii/.nii.gz file, a TIFF stack, or 'phantom'"
            )
        if path.is_dir():
            _check_scan_folder(name, source, path)
        elif source_kind(path) is None:
            raise CtsplatError(f"volume source at volumes.{name}.source is a file that is neither NIfTI nor a TIFF "
                               f"stack: {source!r} (suffixes {', '.join(SCAN_FILE_SUFFIXES)}); for DICOM give the "
                               "folder holding the slices")


def _check_photo_folder(name: str, source: str, path: Path, min_photos: int) -> None:
    """A photo volume's source must be a folder with at least ``min_photos`` images."""
    from ctsplat.photos.images import check_photo_count, list_photos

    if not path.is_dir():
        raise CtsplatError(f"photo folder not found at volumes.{name}.source: {source!r} (resolved to "
                           f"{path.resolve()}); a volume of kind photos needs a folder of photographs")
    try:
        check_photo_count(source, len(list_photos(path)), min_photos)
    except CtsplatError as exc:
        raise CtsplatError(f"invalid config at volumes.{name}.source: {exc}") from None


#: Names the workflow writes beside the volume folders in ``results/``.
RESERVED_VOLUME_NAMES = ("summary.csv", "figures", "logs", "benchmarks", "report.html")


def _check_volume_names(volumes: Mapping[str, Any]) -> None:
    """Volume names become ``results/{name}/``: none may be one of the workflow's own entries there, and no two may
    differ only in case (they would share a folder on case-insensitive file systems)."""
    seen: dict[str, str] = {}
    for name in volumes:
        if name.lower() in RESERVED_VOLUME_NAMES:
            raise CtsplatError(f"invalid config at volumes.{name}: results/{name} is the workflow's own; rename the "
                               f"volume (reserved: {', '.join(RESERVED_VOLUME_NAMES)})")
        if name.lower() in seen:
            raise CtsplatError(f"invalid config at volumes.{name}: {seen[name.lower()]!r} and {name!r} differ only in "
                               "case, and would share one results folder on case-insensitive file systems; rename one")
        seen[name.lower()] = name


def _check_scan_folder(name: str, source: str, path: Path) -> None:
    """A CT source folder must hold files, and not only photographs (a photo folder needs ``kind: photos``)."""
    from ctsplat.formats.sources import TIFF_SUFFIXES
    from ctsplat.photos.images import IMAGE_SUFFIXES

    suffixes = [Path(f).suffix.lower() for _, _, files in os.walk(path) for f in files if not f.startswith(".")]
    if not suffixes:
        raise CtsplatError(f"volume source at volumes.{name}.source is an empty folder: {source!r} (resolved to "
                           f"{path.resolve()}); give the folder with the scan's files")
    photo = [x for x in suffixes if x in IMAGE_SUFFIXES and x not in TIFF_SUFFIXES]  # TIFF stacks are scans
    if len(photo) == len(suffixes):
        raise CtsplatError(f"volume source at volumes.{name}.source holds photographs ({len(photo)} "
                           f"{'/'.join(sorted(set(photo)))} files), not a scan: for the photo path set "
                           f"volumes.{name}.kind: photos")


def canonical(value: Any) -> Any:
    """A copy of a config value with every mapping's keys sorted, recursively (lists keep their order).

    Snakemake's params rerun trigger compares a rule's params as written, key order included; the workflow hands
    its params over in this form so that reordering a YAML section, or writing out a default, reruns nothing.

    Parameters
    ----------
    value : any
        A config value (mappings, lists, scalars).

    Returns
    -------
    any
        The same value, mappings as plain dicts in key order.

    Examples
    --------
    >>> canonical({"b": 1, "a": {"d": [2, {"f": 0, "e": 1}], "c": 3}})
    {'a': {'c': 3, 'd': [2, {'e': 1, 'f': 0}]}, 'b': 1}
    """
    if isinstance(value, Mapping):
        return {k: canonical(value[k]) for k in sorted(value, key=str)}
    if isinstance(value, list | tuple):
        return [canonical(v) for v in value]
    return value


def on_workflow_device(settings: Mapping[str, Any], user: Mapping[str, Any] | None, device: str) -> dict[str, Any]:
    """A section's settings on the workflow's device unless the user's own section names one.

    The radiographs, baselines and photo sections each have a ``device`` default of their own; a workflow whose
    top-level ``device`` is ``cuda`` should run them there too, unless the section was set explicitly.

    Parameters
    ----------
    settings : mapping
        The section as validated (defaults filled in).
    user : mapping or None
        The same section as the user wrote it (before defaults), None when absent.
    device : str
        The workflow's ``device``.

    Returns
    -------
    dict
        A copy of ``settings`` with ``device`` replaced unless ``user`` sets it.

    Examples
    --------
    >>> on_workflow_device({"device": "cpu", "k": 1}, None, "cuda")
    {'device': 'cuda', 'k': 1}
    >>> on_workflow_device({"device": "cpu"}, {"device": "cpu"}, "cuda")
    {'device': 'cpu'}
    """
    out = dict(settings)
    if "device" not in (user or {}):
        out["device"] = device
    return out


def prepare_config(config: Mapping[str, Any], base_dir: str | os.PathLike[str] = ".") -> dict[str, Any]:
    """Everything the workflow checks at parse time, before any job runs.

    Validates against the schema with defaults filled (the schema mirrors the library defaults, so no step module
    is imported here), checks that volume sources exist, moves the volumes of ``kind: photos`` from ``volumes`` to
    ``photo_volumes`` (they run the photo path, not the CT grid; at least one CT volume must remain), resolves
    ``grid.geometry`` and ``baselines.geometry`` (null = the first radiographs geometry that is not a C-arm orbit /
    the grid's), expands the grid (zero runs is
    an error), checks that the largest ``views`` value fits the training geometry and that SfM, when a run needs
    it, has its C-arm geometry (``sfm.settings.geometry``). The split fractions of every radiographs geometry must
    sum to 1 (:func:`check_split`) and every ``grid.exclude`` value must name an axis value
    (:func:`check_grid_exclude`). ``dso_mm`` against the object's size needs the volume: the projector checks it.

    Parameters
    ----------
    config : mapping
        The workflow config as given by the user; not modified.
    base_dir : path-like
        Folder that relative volume source paths are resolved from.

    Returns
    -------
    dict
        The filled config.

    Raises
    ------
    CtsplatError
        One line naming the offending key and how to fix it.
    """
    cfg = validate_config(config)
    # a rule given only some of threads / mem_mb / runtime keeps the defaults of the others
    for rule, spec in load_schema()["properties"]["resources"]["properties"].items():
        cfg["resources"][rule] = {**spec["default"], **cfg["resources"].get(rule, {})}
    _check_volume_names(cfg["volumes"])
    check_volume_sources(cfg["volumes"], base_dir, min_photos=int(cfg["photos"]["sfm"]["min_registered"]))
    for name, vol in cfg["volumes"].items():
        if isinstance(vol["source"], str) and vol["source"].startswith("~"):
            vol["source"] = str(Path(vol["source"]).expanduser())
        _check_not_own_output(name, str(vol["source"]), base_dir)
        if vol["kind"] != "photos":
            _check_source_keys(name, vol, (config.get("volumes") or {}).get(name) or {}, base_dir)
            _check_volume_preprocessing(name, vol.get("preprocessing") or {}, cfg["preprocessing"])
            if vol.get("series_uid") is not None:
                vol["series_uid"] = str(vol["series_uid"])  # a series number, as `ingest --series-uid` takes it
            continue
        ct_keys = sorted(set((config.get("volumes") or {}).get(name) or {}) - {"source", "kind"})
        if ct_keys:
            raise CtsplatError(f"invalid config at volumes.{name}.{ct_keys[0]}: a volume of kind photos reads only "
                               f"source; {', '.join(ct_keys)} apply to CT volumes (photo settings live in photos:), "
                               "so remove them")
    # photo folders take the photos path (workflow/rules/photos.smk), never the CT grid
    cfg["photo_volumes"] = {n: v for n, v in cfg["volumes"].items() if v["kind"] == "photos"}
    cfg["volumes"] = {n: v for n, v in cfg["volumes"].items() if v["kind"] != "photos"}
    if cfg["photo_volumes"]:
        for key in ("gallery_views", "turntable_frames"):  # the photos_train rule's outputs include both figures
            if int(cfg["photos"]["evaluate"][key]) < 1:
                raise CtsplatError(f"invalid config at photos.evaluate.{key}: the workflow writes the gallery and "
                                   f"the turntable of every photo volume, so it must be >= 1 (0 skips the figure "
                                   f"only in `ctsplat photos-train`)")
    if not cfg["volumes"]:
        raise CtsplatError("invalid config at volumes: every volume is of kind photos, and the CT grid needs one CT "
                           "volume (e.g. phantom: {source: phantom}); photographs alone: `ctsplat photos-run`")
    geometries = list(cfg["radiographs"])
    training_geometries = [g for g in geometries if cfg["radiographs"][g]["orbit"] != "carm"]
    if cfg["grid"]["geometry"] is None:
        if not training_geometries:
            raise CtsplatError("invalid config at radiographs: every geometry is a C-arm orbit (orbit: carm, no "
                               "val/test views); add a circular or sphere geometry to train and evaluate on")
        cfg["grid"]["geometry"] = training_geometries[0]
    elif cfg["grid"]["geometry"] not in geometries:
        raise CtsplatError(
            f"invalid config at grid.geometry: {cfg['grid']['geometry']!r} is not a radiographs geometry "
            f"(defined: {', '.join(geometries)})"
        )
    elif cfg["grid"]["geometry"] not in training_geometries:
        raise CtsplatError(
            f"invalid config at grid.geometry: {cfg['grid']['geometry']!r} is a C-arm orbit (orbit: carm) with no "
            "val/test views; name a circular or sphere geometry (C-arm views train through poses: colmap)"
        )
    if cfg["baselines"]["geometry"] is None:
        cfg["baselines"]["geometry"] = cfg["grid"]["geometry"]
    elif cfg["baselines"]["geometry"] not in geometries:
        raise CtsplatError(
            f"invalid config at baselines.geometry: {cfg['baselines']['geometry']!r} is not a radiographs geometry "
            f"(defined: {', '.join(geometries)})"
        )
    elif cfg["baselines"]["enabled"] and cfg["baselines"]["geometry"] not in training_geometries:
        raise CtsplatError(
            f"invalid config at baselines.geometry: {cfg['baselines']['geometry']!r} is a C-arm orbit (orbit: carm) "
            "with no validation views to choose the baselines' parameters on; name a circular or sphere geometry"
        )
    from ctsplat.geometry.orbits import (
        check_held_out_views,
        check_orbit_settings,
        classical_methods,
        has_held_out_views,
    )

    for geo, values in cfg["radiographs"].items():
        user_split = ((config.get("radiographs") or {}).get(geo) or {}).get("split")
        check_split(values["split"], f"radiographs.{geo}.split",
                    given=user_split if isinstance(user_split, Mapping) else None)
        check_orbit_settings(values, f"invalid config at radiographs.{geo}")
        check_held_out_views(values, f"invalid config at radiographs.{geo}")
    check_grid_exclude(cfg)
    sfm_settings = cfg["sfm"]["settings"]
    if float(sfm_settings["percentile_low"]) >= float(sfm_settings["percentile_high"]):
        raise CtsplatError(
            f"invalid config at sfm.settings.percentile_low: {sfm_settings['percentile_low']:g} is not below "
            f"percentile_high ({sfm_settings['percentile_high']:g}), so every image would be blank; e.g. 0.5 and 99.5"
        )
    if cfg["photo_volumes"]:  # the photo jobs would refuse these only after SfM has run
        from ctsplat.photos.config import check_train_settings

        try:
            check_train_settings(cfg["photos"]["train"])
        except CtsplatError as exc:
            raise CtsplatError(f"invalid config at {exc}") from None
    runs = expand_grid(cfg["grid"]["axes"], list(cfg["volumes"]), cfg["grid"]["exclude"])
    sfm_geometry = cfg["sfm"]["settings"]["geometry"]
    if needs_sfm(runs, enabled=cfg["sfm"]["enabled"]):
        # an SfM run marked ok must be one the training accepts, or its cells fail instead of being listed as not run
        sfm_rate = float(cfg["sfm"]["settings"]["min_registration_rate"])
        train_rate = float(cfg["train"]["min_registration_rate"])
        if sfm_rate < train_rate:
            raise CtsplatError(
                f"invalid config at sfm.settings.min_registration_rate: {sfm_rate:g} is below "
                f"train.min_registration_rate ({train_rate:g}), so an SfM run marked ok could still be refused by "
                "training; raise the first or lower the second"
            )
        carm = cfg["radiographs"].get(sfm_geometry)
        if carm is None or carm["orbit"] != "carm" or carm["camera"] != "cone":
            what = "is not a radiographs geometry" if carm is None else "is not a C-arm orbit"
            raise CtsplatError(
                f"invalid config at sfm.settings.geometry: {sfm_geometry!r} {what}; SfM (sfm.enabled, poses: colmap "
                f"or init: sfm) registers a C-arm view set: add radiographs.{sfm_geometry} with camera: cone, "
                "orbit: carm (config/README.md)"
            )
    _check_detector_fits_ssim(cfg)
    grid_geo = cfg["radiographs"][cfg["grid"]["geometry"]]
    no_val = not has_held_out_views(grid_geo, "val")
    if not has_held_out_views(grid_geo, "test"):
        raise CtsplatError(
            f"invalid config at radiographs.{cfg['grid']['geometry']}: the grid's geometry renders no test views, so "
            f"the runs' test metrics would be measured on views that chose their settings; give it test views "
            f"({_held_out_key(grid_geo, 'test')})"
        )
    if cfg["train"]["model_selection"] == "best" and no_val:
        raise CtsplatError(
            f"invalid config at train.model_selection: best chooses a model on validation views, but geometry "
            f"{cfg['grid']['geometry']!r} renders none (it would choose on the test views); give it validation views "
            "(n_val or split.val) or set model_selection: last"
        )
    if any(float(a) for a in cfg["train"]["sharpen"]["amounts"]) and no_val:
        raise CtsplatError(
            f"invalid config at train.sharpen.amounts: the amount is chosen on validation views, but geometry "
            f"{cfg['grid']['geometry']!r} renders none; give it validation views (n_val or split.val) or set "
            "train.sharpen.amounts: [0]"
        )
    # poses: colmap cells train on the C-arm view set SfM registers, the others on the grid's geometry
    colmap = runs["poses"].map(uses_colmap).to_numpy(bool)
    for cells, geo_name, what in ((~colmap, cfg["grid"]["geometry"], "geometry"),
                                  (colmap, sfm_geometry, "the C-arm view set of poses: colmap cells,")):
        if not cells.any() or geo_name not in cfg["radiographs"]:
            continue
        most = int(runs.loc[cells, "views"].max())
        available = _training_views(cfg["radiographs"][geo_name])
        if most > available:
            raise CtsplatError(
                f"invalid config at grid.axes.views: {most} training views requested but {what} {geo_name!r} has "
                f"only about {available} training views; raise radiographs.{geo_name}.n_views or lower the views "
                "axis"
            )
    if cfg["baselines"]["enabled"]:
        base = cfg["baselines"]["geometry"]
        base_geo = cfg["radiographs"][base]
        if not has_held_out_views(base_geo, "val"):
            raise CtsplatError(
                f"invalid config at radiographs.{base}: the baselines' geometry renders no val views to choose the "
                f"baselines' parameters on; give it val views ({_held_out_key(base_geo, 'val')}) or set "
                "baselines.enabled: false"
            )
        possible = classical_methods(base_geo)
        wanted = list(cfg["baselines"]["settings"]["methods"])
        if wanted and not set(wanted) & set(possible):
            raise CtsplatError(
                f"invalid config at baselines.settings.methods: {wanted} cannot reconstruct geometry {base!r} "
                f"({base_geo['camera']} beam, orbit {base_geo['orbit']}); it allows {', '.join(possible)}"
            )
        counts = cfg["baselines"]["n_views"] or []
        available = _training_views(cfg["radiographs"][base])
        if any(int(c) > available for c in counts):
            raise CtsplatError(
                f"invalid config at baselines.n_views: {max(int(c) for c in counts)} views requested but geometry "
                f"{base!r} has only about {available} training views; lower baselines.n_views or raise "
                f"radiographs.{base}.n_views"
            )
    return cfg


def _held_out_key(geometry: Mapping[str, Any], split: str) -> str:
    """The key that sets a geometry's ``val`` / ``test`` views: a circular orbit's ``n_<split>`` (which wins over
    the fractions when set), else ``split.<split>``."""
    if geometry["orbit"] != "circular":
        return f"split.{split}"
    return f"n_{split}" if geometry.get(f"n_{split}") is not None else f"n_{split} or split.{split}"


def _training_views(geometry: Mapping[str, Any]) -> int:
    """How many training views a radiographs geometry (defaults filled) renders, about: circular and C-arm orbits
    have exactly ``n_views``, a sphere splits ``n_views`` into train/val/test."""
    if geometry["orbit"] in ("circular", "carm"):
        return int(geometry["n_views"])
    return int(geometry["n_views"] * geometry["split"]["train"])


def _check_volume_preprocessing(name: str, override: Mapping[str, Any], defaults: Mapping[str, Any]) -> None:
    """A volume's ``preprocessing`` overrides: the section's types and ranges, and an intensity the projector takes.
    """
    where = f"volumes.{name}.preprocessing"
    check_values(override, section_schema("preprocessing"), where)
    settings = {**defaults, **override}
    if settings["intensity"] == "hu":
        key = f"{where}.intensity" if "intensity" in override else "preprocessing.intensity"
        raise CtsplatError(f"invalid config at {key}: 'hu' keeps Hounsfield units, which the projector cannot use "
                           "(negative below water); use attenuation, window or mu (hu is for `ctsplat ingest` "
                           "alone)")
    from ctsplat.volume import check_preprocessing

    try:
        check_preprocessing(settings)  # what the schema cannot say (a window preset's name)
    except CtsplatError as exc:
        raise CtsplatError(f"invalid config at {where if override else 'preprocessing'}: {exc}") from None
    grid = settings["grid"]
    sides = grid if isinstance(grid, list) else [grid]
    if settings["voxel_size_mm"] is None and grid is not None and min(int(g) for g in sides) < MIN_GRID_SIDE:
        key = f"{where}.grid" if "grid" in override else "preprocessing.grid"
        raise CtsplatError(f"invalid config at {key}: {grid} leaves fewer than {MIN_GRID_SIDE} voxels on a side, and "
                           f"the runs' 3D SSIM needs {MIN_GRID_SIDE}; give a grid of at least {MIN_GRID_SIDE}")


#: Voxels a side the runs' 3D SSIM needs (its smallest window, :func:`ctsplat.evaluation.metrics.ssim_window`).
MIN_GRID_SIDE = 3


def _check_detector_fits_ssim(cfg: Mapping[str, Any]) -> None:
    """The training geometry's detector against the SSIM loss window (``train.lambda_ssim`` > 0): training would
    refuse it only after ingest and projection."""
    geo = cfg["grid"]["geometry"]
    rad = cfg["radiographs"][geo]
    side = min(int(rad["detector_width"]), int(rad["detector_height"]))
    if float(cfg["train"]["lambda_ssim"]) <= 0 or side >= 32:  # every window fits: no need to load the loss
        return
    from ctsplat.training.losses import gaussian_window

    window = gaussian_window().numel()
    if side < window:
        raise CtsplatError(f"invalid config at radiographs.{geo}: a {rad['detector_width']} x "
                           f"{rad['detector_height']} detector is smaller than the SSIM loss window ({window} px) "
                           f"that train.lambda_ssim uses; render at least {window} x {window} or set lambda_ssim: 0")


# ----------------------------------------------------------------------------------------------------------------
# Library sections of the schema, generated from the modules' defaults
# ----------------------------------------------------------------------------------------------------------------

GENERATED_BEGIN = "  # ---- generated from the library DEFAULTS"
GENERATED_END = "  # ---- end generated"

# Keys of a library's defaults that the workflow sets itself (not user config), with the reason shown in the schema.
WORKFLOW_KEYS: dict[str, tuple[set[str], str]] = {
    "train": ({"volume", "radiographs", "sfm_dir", "sfm_radiographs", "init", "compositor", "mip", "poses", "views",
               "seed", "device"},
              "without the keys the grid sets per run"),
    "baselines": ({"n_views"}, "without n_views (the grid's view counts)"),
}

# Schema refinements the defaults cannot express: enums, ranges, nullable and union types. Keys of nested sections
# are dotted (``("train", "lr.means")``). Every numeric key has a range: counts >= 1 (>= 0 where 0 means "off" or
# "all"), lengths and scales > 0, fractions and rates in [0, 1], loss weights >= 0, learning rates > 0; the schema
# walk in tests/unit/test_analysis_config.py lists the few numeric keys without a meaningful bound.
_POSITIVE = {"type": "number", "exclusiveMinimum": 0}
_NON_NEGATIVE = {"type": "number", "minimum": 0}
_FRACTION = {"type": "number", "minimum": 0, "maximum": 1}
_ANGLE_DEG = {"type": "number", "minimum": 0, "maximum": 180}
_COUNT = {"type": "integer", "minimum": 1}
_COUNT0 = {"type": "integer", "minimum": 0}
_SEED = {"type": "integer", "minimum": 0, "maximum": SEED_MAX}
REFINE: dict[tuple[str, str], dict[str, Any]] = {
    ("preprocessing", "voxel_size_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("preprocessing", "grid"): {"type": ["integer", "array", "null"], "minimum": 2,
                                "items": {"type": "integer", "minimum": 2}, "minItems": 3, "maxItems": 3},
    ("preprocessing", "intensity"): {"enum": ["attenuation", "window", "mu", "hu"]},
    ("preprocessing", "mu_water_per_mm"): _POSITIVE,
    ("preprocessing", "hu_max"): {"type": "number", "exclusiveMinimum": -1000},  # mu(hu_max) must be > 0
    # [level, width] in HU, or a preset name
    ("preprocessing", "window"): {"type": ["string", "array"], "items": {"type": "number"}, "minItems": 2,
                                  "maxItems": 2, "prefixItems": [{"type": "number"}, _POSITIVE]},
    ("preprocessing", "denoise"): {"enum": [None, "tv", "bilateral"]},
    ("preprocessing", "denoise_weight"): _POSITIVE,
    ("preprocessing", "mask"): {"enum": [None, "otsu", "convex_hull"]},
    ("radiographs", "camera"): {"enum": ["parallel", "cone"]},
    ("radiographs", "orbit"): {"enum": ["circular", "sphere", "carm"]},
    ("radiographs", "sphere_sampling"): {"enum": ["fibonacci", "stratified"]},
    ("radiographs", "pixel_spacing_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("radiographs", "dso_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("radiographs", "dsd_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("radiographs", "dso_factor"): _POSITIVE,
    ("radiographs", "dsd_factor"): _POSITIVE,
    ("radiographs", "detector_size_factor"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("radiographs", "n_val"): {"type": ["integer", "null"], "minimum": 0},
    ("radiographs", "n_test"): {"type": ["integer", "null"], "minimum": 0},
    ("radiographs", "parallel_distance_mm"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("radiographs", "arc_deg"): {"type": ["number", "null"], "exclusiveMinimum": 0, "maximum": 360},
    ("radiographs", "isocenter_mm"): {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 3,
                                      "maxItems": 3},
    ("radiographs", "n_views"): _COUNT,
    ("radiographs", "elevation_range_deg"): {"type": "array", "minItems": 2, "maxItems": 2,
                                             "items": {"type": "number", "exclusiveMinimum": -90,
                                                       "exclusiveMaximum": 90}},
    # elevation = wobble_deg * sin(...) must stay off the poles
    ("radiographs", "wobble_deg"): {"type": "number", "exclusiveMinimum": -90, "exclusiveMaximum": 90},
    ("radiographs", "wobble_cycles"): _NON_NEGATIVE,
    ("radiographs", "detector_width"): _COUNT,
    ("radiographs", "detector_height"): _COUNT,
    ("radiographs", "orbit_jitter_mm"): _NON_NEGATIVE,
    ("radiographs", "orbit_jitter_deg"): _NON_NEGATIVE,
    ("radiographs", "fov_margin"): _POSITIVE,
    # the three fractions sum to 1 (check_split); every view set has training views
    ("radiographs", "split.train"): {"type": "number", "exclusiveMinimum": 0, "maximum": 1},
    ("radiographs", "split.val"): _FRACTION,
    ("radiographs", "split.test"): _FRACTION,
    ("radiographs", "step_voxels"): _POSITIVE,
    ("radiographs", "noise.i0"): _POSITIVE,
    ("radiographs", "noise.electronic_sigma"): _NON_NEGATIVE,
    ("radiographs", "noise.model"): {"enum": ["physical", "tigre"]},
    ("radiographs", "noise.splits"): {"type": "array", "minItems": 1, "uniqueItems": True,
                                      "items": {"enum": ["train", "val", "test"]}},
    ("radiographs", "batch_samples"): _COUNT,
    ("sfm", "geometry"): {"type": "string", "pattern": "^[A-Za-z0-9][A-Za-z0-9_.-]*$"},
    ("sfm", "clahe_clip"): _FRACTION,  # skimage equalize_adapthist clip_limit
    ("sfm", "clahe_kernel_frac"): {"type": "number", "exclusiveMinimum": 0, "maximum": 1},
    ("sfm", "percentile_low"): {"type": "number", "minimum": 0, "maximum": 100},
    ("sfm", "percentile_high"): {"type": "number", "minimum": 0, "maximum": 100},
    ("sfm", "background_frac"): _FRACTION,
    ("sfm", "silhouette_margin_frac"): _FRACTION,
    ("sfm", "lowpass_px"): _NON_NEGATIVE,  # 0 = no pre-blur
    ("sfm", "highpass_frac"): _NON_NEGATIVE,  # 0 = no high-pass
    ("sfm", "max_num_features"): _COUNT,
    ("sfm", "peak_threshold"): _POSITIVE,  # COLMAP refuses 0
    ("sfm", "edge_threshold"): _POSITIVE,
    ("sfm", "sift_num_octaves"): _COUNT,
    ("sfm", "matching"): {"enum": ["exhaustive", "sequential"]},
    ("sfm", "sequential_overlap"): _COUNT,
    ("sfm", "max_ratio"): {"type": "number", "exclusiveMinimum": 0, "maximum": 1},
    ("sfm", "max_distance"): _POSITIVE,
    ("sfm", "min_num_inliers"): _COUNT,  # COLMAP refuses 0 (as the two below)
    ("sfm", "max_error_px"): _POSITIVE,
    ("sfm", "mapper"): {"enum": ["incremental", "global"]},
    ("sfm", "init_min_num_inliers"): _COUNT,
    ("sfm", "init_min_tri_angle_deg"): _ANGLE_DEG,
    ("sfm", "abs_pose_min_num_inliers"): _COUNT,
    ("sfm", "abs_pose_min_inlier_ratio"): _FRACTION,
    ("sfm", "filter_min_tri_angle_deg"): _ANGLE_DEG,
    ("sfm", "triangulation_min_angle_deg"): {"type": "number", "exclusiveMinimum": 0, "maximum": 180},  # > 0: COLMAP
    ("sfm", "min_model_size"): _COUNT,
    ("sfm", "pose_prior"): {"enum": ["none", "position", "refine", "refine_prior", "isocentric"]},
    ("sfm", "refine_rounds"): _COUNT,
    ("sfm", "prior_sigma_mm"): _POSITIVE,
    ("sfm", "design_sigma_deg"): {"type": ["number", "null"], "exclusiveMinimum": 0},
    ("sfm", "isocentre_sigma_mm"): _NON_NEGATIVE,
    ("sfm", "isocentric_loss_px"): _POSITIVE,
    ("sfm", "fuse_harmonics"): _COUNT0,  # 0 = off
    ("sfm", "min_shared_images"): {"type": "integer", "minimum": 3},  # a similarity between models needs 3 centres
    ("sfm", "align_inlier_threshold_frac"): _POSITIVE,
    ("sfm", "align_iterations"): _COUNT,
    ("sfm", "min_registration_rate"): _FRACTION,
    ("sfm", "max_median_rotation_error_deg"): {"type": "number", "exclusiveMinimum": 0, "maximum": 180},
    ("sfm", "max_median_centre_error_frac"): _POSITIVE,
    ("sfm", "min_alignment_inlier_rate"): _FRACTION,
    ("train", "supervision"): {"enum": ["line_integral", "transmission"]},
    ("train", "densify.split_mass"): {"enum": ["conserve", "halve"]},
    ("train", "densify.strategy"): {"enum": ["gradient", "error", "both"]},
    ("train", "optimizer_preset"): {"enum": ["per_group", "method"]},
    ("train", "pose_refine.cone_model"): {"enum": ["rigid", "carm"]},
    ("train", "model_selection"): {"enum": ["last", "best"]},
    # keys the workflow sets per run (not in the schema; checked by check_section for the command line)
    ("train", "device"): {"type": "string", "pattern": "^(auto|cpu|cuda(:[0-9]+)?)$"},
    ("train", "init"): {"enum": ["volume", "uniform", "fbp", "sfm"]},
    ("train", "compositor"): {"enum": ["radiative", "radiative_unrectified", "alpha"]},
    ("train", "poses"): {"enum": ["gt", "perturbed", "colmap", "gt+refine", "perturbed+refine", "colmap+refine"]},
    ("baselines", "methods"): {"type": "array", "minItems": 1, "uniqueItems": True,
                               "items": {"enum": ["fbp", "fdk", "sart", "asd_pocs", "mbir"]}},
    ("baselines", "fbp_filters"): {"type": "array", "minItems": 1,
                                   "items": {"enum": ["ramp", "shepp-logan", "cosine", "hamming", "hann"]}},
    # the validation views choose the parameters and the test views score: reconstructing from either would leak
    ("baselines", "split"): {"enum": ["train"]},
    ("baselines", "sart_max_iterations"): _COUNT,
    ("baselines", "sart_relaxation"): {"type": ["number", "array"], "exclusiveMinimum": 0, "exclusiveMaximum": 2,
                                       "minItems": 1,
                                       "items": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 2}},
    ("baselines", "sart_subsets"): _COUNT,
    ("baselines", "asd_pocs_iterations"): _COUNT,
    ("baselines", "asd_pocs_alpha"): {"type": ["number", "array"], "exclusiveMinimum": 0, "maximum": 10,
                                      "minItems": 1, "items": {"type": "number", "exclusiveMinimum": 0,
                                                               "maximum": 10}},
    ("baselines", "asd_pocs_tv_steps"): _COUNT,
    ("baselines", "asd_pocs_subsets"): _COUNT,
    ("baselines", "mbir_sharpness"): {"type": ["number", "array"], "minimum": -10, "maximum": 10, "minItems": 1,
                                      "items": {"type": "number", "minimum": -10, "maximum": 10}},
    ("baselines", "mbir_snr_db"): {"type": ["number", "array"], "minimum": 0, "maximum": 100, "minItems": 1,
                                   "items": {"type": "number", "minimum": 0, "maximum": 100}},
    ("baselines", "mbir_max_iterations"): _COUNT,
    ("baselines", "mbir_threads"): _COUNT,
    ("baselines", "patience"): {"type": ["integer", "null"], "minimum": 1},
    ("baselines", "detector_binning"): {"type": ["integer", "null"], "minimum": 1, "maximum": 16},
    ("baselines", "step_voxels"): {"type": "number", "exclusiveMinimum": 0, "maximum": 1},
    ("baselines", "device"): {"type": "string", "pattern": "^(auto|cpu|cuda(:[0-9]+)?)$"},
    ("photos", "sfm.max_image_size"): {"type": "integer", "minimum": 64},
    ("photos", "sfm.max_num_features"): _COUNT,
    ("photos", "sfm.camera_mode"): {"enum": ["single", "per_image"]},
    ("photos", "sfm.camera_model"): {"enum": ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]},
    ("photos", "sfm.matching"): {"enum": ["auto", "exhaustive", "sequential"]},
    ("photos", "sfm.exhaustive_max_images"): _COUNT,
    ("photos", "sfm.sequential_overlap"): _COUNT,
    ("photos", "sfm.min_num_inliers"): _COUNT,
    ("photos", "sfm.mapper"): {"enum": ["incremental", "global"]},
    ("photos", "sfm.init_min_num_inliers"): _COUNT,
    ("photos", "sfm.abs_pose_min_num_inliers"): _COUNT,
    ("photos", "sfm.abs_pose_min_inlier_ratio"): _FRACTION,
    ("photos", "sfm.min_registered"): {"type": "integer", "minimum": 3},
    ("photos", "sfm.num_threads"): _COUNT,
    ("photos", "sfm.seed"): _SEED,
    ("photos", "train.iterations"): _COUNT,
    ("photos", "train.downscale"): {"enum": [1, 2, 4, 8]},
    ("photos", "train.test_every"): {"type": "integer", "minimum": 0},
    ("photos", "train.holdout"): {"enum": ["test", "validation"]},
    ("photos", "train.validation_offset"): {"type": ["integer", "null"], "minimum": 1},
    ("photos", "train.background"): {"anyOf": [{"enum": ["learned"]},
                                                {"type": "array", "items": {"type": "number", "minimum": 0,
                                                                            "maximum": 1},
                                                 "minItems": 3, "maxItems": 3}]},
    ("photos", "train.flash.exponent"): {"type": "number", "minimum": 0, "maximum": 4},  # 2: inverse square
    ("photos", "train.flash.lr"): _NON_NEGATIVE,
    ("photos", "train.sh_degree"): {"type": "integer", "minimum": 0, "maximum": 3},
    ("photos", "train.sh_interval"): _COUNT,
    ("photos", "train.lambda_dssim"): _FRACTION,
    ("photos", "train.drop_rate"): {"type": "number", "minimum": 0, "exclusiveMaximum": 1},
    ("photos", "train.init_opacity"): {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
    ("photos", "train.init_scale"): _POSITIVE,
    ("photos", "train.max_points"): {"type": "integer", "minimum": 4},  # a seed scale needs 3 neighbours
    **{("photos", f"train.lr.{k}"): _NON_NEGATIVE for k in ("means", "means_final", "log_scales", "quats",
                                                             "opacity", "colors", "sh_rest", "background")},
    ("photos", "train.densify.strategy"): {"enum": list(DENSIFY_CHOICES["strategy"])},
    ("photos", "train.densify.interval"): {"type": "integer", "minimum": 0},
    ("photos", "train.densify.start"): {"type": "integer", "minimum": 0},
    ("photos", "train.densify.stop_fraction"): _FRACTION,
    ("photos", "train.densify.grad_threshold"): _POSITIVE,
    ("photos", "train.densify.percent_dense"): _POSITIVE,
    ("photos", "train.densify.prune_opacity"): _FRACTION,
    ("photos", "train.densify.prune_scale_fraction"): _POSITIVE,
    ("photos", "train.densify.size_prune"): {"enum": list(DENSIFY_CHOICES["size_prune"])},
    ("photos", "train.densify.near_prune"): {"type": "number", "minimum": 0},
    ("photos", "train.densify.gradient"): {"enum": list(DENSIFY_CHOICES["gradient"])},
    ("photos", "train.densify.opacity_reset_interval"): {"type": "integer", "minimum": 0},
    ("photos", "train.densify.max_gaussians"): _COUNT,
    ("photos", "train.mcmc.cap_max"): _COUNT,
    ("photos", "train.mcmc.growth"): {"type": "number", "minimum": 1},
    ("photos", "train.mcmc.stop_fraction"): _FRACTION,
    ("photos", "train.mcmc.noise_lr"): _NON_NEGATIVE,
    ("photos", "train.mcmc.opacity_reg"): _NON_NEGATIVE,
    ("photos", "train.mcmc.scale_reg"): _NON_NEGATIVE,
    ("photos", "train.log_every"): _COUNT,
    ("photos", "train.num_threads"): _COUNT,
    ("photos", "train.seed"): _SEED,
    ("photos", "train.device"): {"enum": ["auto", "cpu", "cuda"]},
    ("photos", "evaluate.turntable_frames"): {"type": "integer", "minimum": 0},
    ("photos", "evaluate.gallery_views"): {"type": "integer", "minimum": 0},
    ("baselines", "n_views"): {"type": ["integer", "array", "null"], "minimum": 0, "minItems": 1,
                               "items": {"type": "integer", "minimum": 0}},
    ("train", "fbp_filter"): {"enum": ["ramp", "shepp-logan", "cosine", "hamming", "hann"]},
    ("radiographs", "device"): {"type": "string", "pattern": "^(auto|cpu|cuda(:[0-9]+)?)$"},
}


def _json_type(v: Any) -> dict[str, Any]:
    if v is None:
        return {}
    for py, js in ((bool, "boolean"), (int, "integer"), (float, "number"), (str, "string"), (list, "array"),
                   (dict, "object")):
        if isinstance(v, py):
            return {"type": js}
    return {}


def _refinement(section: str, dotted: str) -> dict[str, Any]:
    """The schema refinement of one library key: training keys (and the baselines' ``sharpen``, the same rule) take
    their range from :data:`ctsplat.training.config.TRAIN_BOUNDS` (the one definition, also checked by the library),
    the others from :data:`REFINE`."""
    if section == "train" or (section == "baselines" and dotted.startswith("sharpen.")):  # the read-out's rule
        from ctsplat.training.config import TRAIN_BOUNDS

        if dotted in TRAIN_BOUNDS:
            return TRAIN_BOUNDS[dotted].json_schema()
    return copy.deepcopy(REFINE.get((section, dotted), {}))


def _schema_section(name: str, defaults: Mapping[str, Any], skip: set[str], description: str,
                    prefix: str = "") -> dict[str, Any]:
    props: dict[str, Any] = {}
    for key, val in defaults.items():
        if key in skip:
            continue
        if isinstance(val, dict) and val:
            props[key] = {"type": "object", "additionalProperties": False, "default": {},
                          "properties": _schema_section(name, val, set(), "", f"{prefix}{key}.")["properties"]}
        else:
            props[key] = {**_json_type(val), "default": val}
            refined = _refinement(name, prefix + key)
            if refined:
                props[key].pop("type", None)
                props[key].update(refined)
    out = {"type": "object", "additionalProperties": False, "properties": props}
    if description:
        out["description"] = description
    return out


def _generated_block() -> str:
    """YAML text of the schema's ``$defs`` for the library sections, from the modules' current defaults."""
    import yaml

    defs = {}
    for section, (mod_name, attr) in LIBRARY_SECTIONS.items():
        defaults = getattr(importlib.import_module(mod_name), attr)
        skip, why = WORKFLOW_KEYS.get(section, (set(), ""))
        defs[section] = _schema_section(section, defaults, skip, f"{mod_name}.{attr}" + (f" {why}" if why else ""))
    return textwrap.indent(yaml.safe_dump(defs, sort_keys=False, default_flow_style=None, width=110), "  ")


def _schema_file(schema_path: str | os.PathLike[str] | None) -> Path:
    """The schema file to rewrite: ``schema_path``, else the one of this source tree."""
    return Path(schema_path) if schema_path is not None else Path(__file__).resolve().parent / SCHEMA_RESOURCE


def sync_library_defaults(schema_path: str | os.PathLike[str] | None = None) -> Path:
    """Regenerate the library sections of the schema file from the modules' ``*_DEFAULTS``.

    A developer tool: rewrites only the lines between the ``# ---- generated`` and ``# ---- end generated``
    markers; per-key refinements come from :data:`REFINE`. Run it after a step module changes its defaults
    (``tests/unit/test_analysis_config.py`` fails while the schema and the library disagree).

    Parameters
    ----------
    schema_path : path-like, optional
        Default: the schema file of this source tree (``ctsplat/schemas/config.schema.yaml``).

    Returns
    -------
    pathlib.Path
        The schema file (written only when its text changes).
    """
    path = _schema_file(schema_path)
    before = path.read_text(encoding="utf-8")
    lines = before.splitlines(keepends=True)
    b = next(i for i, line in enumerate(lines) if line.startswith(GENERATED_BEGIN))
    e = next(i for i, line in enumerate(lines) if line.startswith(GENERATED_END))
    text = "".join(lines[: b + 1]) + _generated_block() + "".join(lines[e:])
    if text != before:  # unchanged: the file (and its time stamp) stays as it is
        path.write_text(text, encoding="utf-8")
    return path


def main(argv: list[str] | None = None) -> None:
    """``python -m ctsplat.config --sync-defaults [--schema PATH]``."""
    parser = argparse.ArgumentParser(prog="python -m ctsplat.config", description="Workflow config schema tools.")
    parser.add_argument("--sync-defaults", action="store_true", required=True,
                        help="regenerate the schema's library sections from the modules' *_DEFAULTS")
    parser.add_argument("--schema", help="schema file to rewrite (default: the one in this source tree)")
    args = parser.parse_args(argv)
    path = _schema_file(args.schema)
    before = path.read_text(encoding="utf-8") if path.is_file() else None
    sync_library_defaults(path)
    print(f"{'unchanged' if path.read_text(encoding='utf-8') == before else 'updated'} {path}")


if __name__ == "__main__":
    main()
