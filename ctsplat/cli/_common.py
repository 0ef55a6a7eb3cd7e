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
    text = p.read_text()
    if p.suffix.lower() == ".json":
        cfg = json.loads(text)
    else:
        import yaml

        cfg = yaml.safe_load(text) or {}
    if not isinstance(cfg, dict):
        raise CtsplatError(f"config file {p} must hold a mapping")
    return dict(cfg.get(section, cfg))


def apply_sets(cfg: dict[str, Any], sets: list[str] | None) -> dict[str, Any]:
    """Apply ``key=value`` / ``a.b=value`` overrides in place; values parse as JSON when they can (``n_views=50``)."""
    for item in sets or []:
        if "=" not in item:
            raise CtsplatError(f"--set expects KEY=VALUE, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            value = json.loads(raw.strip())
        except json.JSONDecodeError:
            value = raw.strip()
        node = cfg
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise CtsplatError(f"--set {key}: {part} is not a section")
        node[parts[-1]] = value
    return cfg
