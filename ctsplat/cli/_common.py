"""Helpers shared by the subcommands: reading one config section from a file, ``--set KEY=VALUE`` overrides."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ctsplat.utils import CtsplatError


def load_section(path: str | None, section: str) -> dict[str, Any]:
    """Settings from a YAML/JSON file: either the section itself or ``{section: {...}}``; ``{}`` without a file."""
    if path is None:
        return {}
    p = Path(path)
    if not p.exists():
        raise CtsplatError(f"config file {p} does not exist")
    import yaml  # JSON is YAML too

    try:
        cfg = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise CtsplatError(f"config file {p} is not valid YAML/JSON: {str(exc).splitlines()[0]}") from exc
    if not isinstance(cfg, dict):
        raise CtsplatError(f"config file {p} must hold a mapping (the {section} section)")
    return dict(cfg[section]) if isinstance(cfg.get(section), dict) else dict(cfg)


def parse_value(text: str) -> Any:
    """An override value: JSON when it parses (``50``, ``1e5``, ``null``), else YAML (``[1, 2]``, ``on``), else text."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        pass
    import yaml

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
        value = parse_value(raw.strip())
        node = cfg
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise CtsplatError(f"--set {key}: {part} is not a section")
        node[parts[-1]] = value
    return cfg
