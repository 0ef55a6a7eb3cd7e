"""``ctsplat sfm``: COLMAP poses from a C-arm cone-beam view set, aligned to the world and scored."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ctsplat.cli._common import section_config, seed_value
from ctsplat.utils import CtsplatError


def sfm_settings(config: str | None, sets: list[str] | None) -> dict[str, Any]:
    """The sfm settings of ``--config`` and ``--set``, checked; without ``geometry``.

    ``geometry`` names the workflow's C-arm view set; here the view set is the RADIOGRAPHS argument. A workflow
    config carries it (and is read for its other settings), while a ``--set geometry=...`` would be ignored, so
    that is refused.
    """
    if any(item.partition("=")[0].strip() == "geometry" for item in sets or []):
        raise CtsplatError("sfm.geometry only names the workflow's C-arm view set; `ctsplat sfm` registers the "
                           "RADIOGRAPHS folder it is given: drop geometry")
    cfg = section_config(config, sets, "sfm")
    cfg.pop("geometry", None)
    return cfg


def run(args: argparse.Namespace) -> None:
    from ctsplat.sfm import run_sfm

    cfg = sfm_settings(args.config, args.set)
    if not Path(args.radiographs).is_dir():
        raise CtsplatError(f"radiographs folder {args.radiographs} does not exist; run `ctsplat project --set "
                           "camera=cone --set orbit=carm` first")
    if args.volume is not None and not cfg.get("naive_slices"):
        raise CtsplatError("--volume is only read with naive_slices: true (SfM on the axial slices); add --set "
                           "naive_slices=true or drop --volume")
    if args.volume is not None and not Path(args.volume).exists():
        raise CtsplatError(f"volume {args.volume} does not exist; run `ctsplat ingest` first")
    summary = run_sfm(args.radiographs, args.out_dir, cfg, seed=args.seed, volume_path=args.volume)
    keys = ("ok", "reason", "n_views", "n_registered", "registration_rate", "models_found", "rot_err_deg_median",
            "centre_err_mm_median", "centre_err_frac_median", "alignment_inlier_rate")
    print(json.dumps({k: summary.get(k) for k in keys}))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sfm", help="COLMAP (pycolmap) poses from cone-beam radiographs; alignment and pose accuracy",
        description="Run pycolmap with the known intrinsics on the radiographs of a C-arm view set (written by "
                    "`ctsplat project` with camera: cone, orbit: carm), put the recovered poses in the frame of "
                    "the designed orbit, score them against the true ones after a Sim(3) to those, and write "
                    "sparse/0, poses.csv, summary.json, points3d.ply and aligned_views.json into OUT_DIR. Too few "
                    "registrations do not fail: summary.json records ok: false.")
    p.add_argument("radiographs", help="radiographs folder of the C-arm view set (line_integrals.tif, views.json)")
    p.add_argument("out_dir", help="output folder")
    p.add_argument("--config", help="YAML/JSON file with the sfm settings (or a workflow config: its sfm.settings)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one sfm key, e.g. --set matching=sequential --set pose_prior=isocentric")
    p.add_argument("--seed", type=seed_value, default=0, help="COLMAP and alignment seed, 0 .. 2^32 - 1 (default 0)")
    p.add_argument("--volume", help="the volume (.nii.gz), only needed for naive_slices")
    p.set_defaults(func=run)
