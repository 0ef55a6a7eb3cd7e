"""``ctsplat sfm``: COLMAP poses from synthetic cone-beam radiographs of a volume, aligned and scored."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ctsplat.utils import CtsplatError


def _load_config(path: str | None) -> dict[str, Any]:
    """``sfm`` overrides from a YAML/JSON file: either the section itself or ``{sfm: {...}}``."""
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
    return dict(cfg.get("sfm", cfg))


def _value(text: str) -> Any:
    """``key=value`` override value: JSON when it parses (numbers, true/false, null), else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def run(args: argparse.Namespace) -> None:
    from ctsplat.sfm import run_sfm

    cfg = _load_config(args.config)
    for item in args.set or []:
        if "=" not in item:
            raise CtsplatError(f"--set expects key=value, got {item!r}")
        key, val = item.split("=", 1)
        cfg[key.strip()] = _value(val.strip())
    if not Path(args.volume).exists():
        raise CtsplatError(f"volume {args.volume} does not exist; run `ctsplat ingest` first")
    summary = run_sfm(args.volume, args.out_dir, cfg, seed=args.seed)
    keys = ("ok", "n_views", "n_registered", "registration_rate", "models_found", "rot_err_deg_median",
            "centre_err_mm_median")
    print(json.dumps({k: summary.get(k) for k in keys}))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sfm", help="COLMAP (pycolmap) poses from cone-beam radiographs; alignment and pose accuracy",
        description="Render a cone-beam SfM view set of VOLUME, run pycolmap with the known intrinsics, align "
                    "the recovered poses to the true ones and write sparse/0, poses.csv, summary.json, "
                    "points3d.ply and aligned_views.json into OUT_DIR. Too few registrations do not fail: "
                    "summary.json records ok: false.")
    p.add_argument("volume", help="preprocessed volume (.nii.gz with its volume.json)")
    p.add_argument("out_dir", help="output folder")
    p.add_argument("--config", help="YAML/JSON file with the sfm section (or {sfm: {...}})")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one sfm key, e.g. --set n_views=120 --set matching=sequential")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)
