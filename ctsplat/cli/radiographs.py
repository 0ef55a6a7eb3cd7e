"""``ctsplat project`` (synthetic radiographs) and ``ctsplat baseline`` (classical reconstructions)."""

from __future__ import annotations

import argparse

from ctsplat.cli._common import section_config, seed_value


def run_project(args: argparse.Namespace) -> None:
    from ctsplat.projector import render_radiographs

    cfg = section_config(args.config, args.set, "radiographs")
    vs = render_radiographs(args.volume, args.out, cfg, seed=args.seed)
    counts = {s: len(vs.indices(s)) for s in ("train", "val", "test")}
    print(f"{len(vs)} {vs.camera.model}-beam radiographs ({counts}) -> {args.out}")


def run_baseline(args: argparse.Namespace) -> None:
    from ctsplat.baselines import run_baselines

    cfg = section_config(args.config, args.set, "baselines")
    df = run_baselines(args.volume, args.radiographs, args.out, cfg)
    print(df.to_string(index=False, float_format=lambda x: f"{x:.4f}"))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "project",
        help="render synthetic Beer-Lambert radiographs of a volume",
        description="Render line integrals (line_integrals.tif), 16-bit transmission PNGs, views.json and "
        "radiographs.json for a camera/orbit (settings: ctsplat.projector.RADIOGRAPHS_DEFAULTS).",
    )
    p.add_argument("--volume", required=True, help="NAME.nii.gz from ingest (its sidecar NAME.json beside it)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="YAML/JSON file with one geometry's settings (or a workflow config with one)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one setting, e.g. --set camera=cone --set n_views=50 --set noise.enabled=true")
    p.add_argument("--seed", type=seed_value, default=0, help="orbit/split/noise seed (default 0)")
    p.set_defaults(func=run_project)

    b = subparsers.add_parser(
        "baseline",
        help="classical reconstructions (FBP/FDK, SART, ASD-POCS, MBIR) from radiographs of any geometry",
        description="FBP, SART, ASD-POCS and MBIR (circular parallel beam) or FDK, SART and ASD-POCS (cone beam) "
        "from the training views, parameters chosen on the validation views; writes baselines.csv, trials.csv, "
        "NIfTI volumes and baselines.json (settings: ctsplat.baselines.BASELINE_DEFAULTS).",
    )
    b.add_argument("--volume", required=True, help="the reference volume.nii.gz the radiographs were rendered from")
    b.add_argument("--radiographs", required=True, help="folder written by `ctsplat project`")
    b.add_argument("--out", required=True, help="output folder")
    b.add_argument("--config", help="YAML/JSON file with the baselines settings (or a workflow config)")
    b.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one setting, e.g. --set n_views=[25,50,75] --set sart_max_iterations=3")
    b.set_defaults(func=run_baseline)
