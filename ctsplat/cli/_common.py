"""Helpers shared by the subcommands: reading one config section from a file, ``--set KEY=VALUE`` overrides, and
checking the result against the section's types and ranges before anything runs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ctsplat.utils import SEED_MAX, CtsplatError


def seed_value(text: str) -> int:
    """argparse type of ``--seed``: an integer 0 .. :data:`ctsplat.utils.SEED_MAX`."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 0 <= seed <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"{seed} is outside 0 .. {SEED_MAX}")
    return seed


def load_section(path: str | None, section: str) -> dict[str, Any]:
    """Settings from a YAML/JSON file: the section itself, ``{section: {...}}``, a workflow config (its
    ``sfm.settings`` / ``baselines.settings``, or its one ``radiographs`` geometry), or a run folder's
    ``config.json`` (``{"config": {...}, "config_hash": ...}``, the settings it trained with); ``{}`` without a
    file."""
    if path is None:
        return {}
    p = Path(path)
    if not p.exists():
        raise CtsplatError(f"config file {p} does not exist")
    import yaml

    from ctsplat.config import load_config_text

    try:
        # JSON by its own parser: YAML 1.1 reads exponents without a dot (5e-05, as json.dumps writes them) as text
        cfg = (json.loads(p.read_text()) if p.suffix.lower() == ".json" else load_config_text(p.read_text())) or {}
    except UnicodeDecodeError:
        raise CtsplatError(f"config file {p} is not a text (YAML/JSON) file; give the config file") from None
    except (yaml.YAMLError, json.JSONDecodeError) as exc:
        raise CtsplatError(f"config file {p} is not valid YAML/JSON: {str(exc).splitlines()[0]}") from exc
    except CtsplatError as exc:
        raise CtsplatError(f"config file {p}: {exc}") from None
    if not isinstance(cfg, dict):
        raise CtsplatError(f"config file {p} must hold a mapping (the {section} section)")
    if isinstance(cfg.get("config"), dict) and "config_hash" in cfg:  # a run folder's record of its settings
        return dict(cfg["config"])
    if not isinstance(cfg.get(section), dict):
        return dict(cfg)
    values = dict(cfg[section])
    if section in ("sfm", "baselines") and {"enabled", "settings"} & set(values):  # a workflow config's section
        workflow = values
        values = dict(workflow.get("settings") or {})
        if section == "baselines" and workflow.get("n_views") is not None:
            values["n_views"] = workflow["n_views"]
    elif section == "radiographs" and values and all(isinstance(v, dict) for v in values.values()):
        from ctsplat.projector import RADIOGRAPHS_DEFAULTS

        if not set(values) & set(RADIOGRAPHS_DEFAULTS):  # geometry name -> settings, as in a workflow config
            if len(values) > 1:
                raise CtsplatError(f"config file {p} holds {len(values)} radiographs geometries ({', '.join(values)})"
                                   "; give a file with one geometry's settings (at top level or alone under "
                                   "radiographs:)")
            values = dict(next(iter(values.values())))
    return values


def parse_value(text: str) -> Any:
    """An override value: JSON when it parses (``50``, ``1e5``, ``null``), else YAML (``[1, 2]``, ``on``), else text.

    YAML 1.1 reads ``010`` as octal 8, ``08`` as text and ``1:30`` as 90 (base 60); such a value is refused.

    Raises
    ------
    CtsplatError
        For a number YAML would read in base 8 or 60.
    """
    import re

    try:
        return json.loads(text)
    except json.JSONDecodeError:
        pass
    import yaml

    if re.fullmatch(r"[-+]?0[0-9_]+|[-+]?[0-9][0-9_]*(:[0-5]?[0-9])+(\.[0-9_]*)?", text.strip()):
        raise CtsplatError(f"{text!r} would be read in base 8 or 60, or as text (YAML 1.1); write the number in "
                           "decimal without leading zeros")
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def apply_sets(cfg: dict[str, Any], sets: list[str] | None) -> dict[str, Any]:
    """Apply ``key=value`` / ``a.b=value`` overrides in place; values as :func:`parse_value`."""
    for item in sets or []:
        if "=" not in item:
            raise CtsplatError(f"--set expects KEY=VALUE, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            value = parse_value(raw.strip())
        except CtsplatError as exc:
            raise CtsplatError(f"--set {key.strip()}: {exc}") from None
        node = cfg
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise CtsplatError(f"--set {key}: {part} is not a section")
        node[parts[-1]] = value
    return cfg


def section_config(path: str | None, sets: list[str] | None, section: str) -> dict[str, Any]:
    """One library section from ``--config`` plus ``--set`` overrides, checked before the step runs.

    Every value must have the type and range of the workflow schema (:func:`ctsplat.config.check_section`), so a
    wrong value (``--set n_views=abc``, ``--set lr.means=-1``) is refused with its key path instead of failing
    later or being ignored.

    Parameters
    ----------
    path : str or None
        YAML/JSON file (see :func:`load_section`).
    sets : list of str or None
        ``KEY=VALUE`` overrides (see :func:`apply_sets`).
    section : str
        ``preprocessing``, ``radiographs``, ``sfm``, ``train`` or ``baselines``.

    Returns
    -------
    dict
        The user's settings (defaults are filled by the step).
    """
    from ctsplat.config import check_section

    return check_section(section, apply_sets(load_section(path, section), sets))
