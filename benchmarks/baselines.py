"""Classical baselines on a parallel-beam and a cone-beam geometry: every method, parameters chosen on validation.

    .venv/bin/python benchmarks/baselines.py [--source ../shared/data/ct0051_head | phantom] [--grid 64]
        [--views 50] [--geometries parallel cone] [--arc 180] [--sart-iterations N] [--set KEY=VALUE ...]

Steps: ``ctsplat.volume.ingest`` (default preprocessing, grid^3; ``--source phantom`` writes the built-in phantom
as DICOM first; cached under benchmarks/out/ per source and grid), then for each geometry and view count the
radiographs (``ctsplat.projector.render_radiographs``) and ``ctsplat.baselines.run_baselines``:

- ``parallel``: circular parallel beam over ``--arc`` deg (default 180: over 360, views at a and a + 180 are mirror
  images), a grid x grid detector (one voxel per pixel) -> FBP, SART, ASD-POCS, MBIR;
- ``cone``: R²-Gaussian's geometry, circular cone beam over 360 deg, DSO = 2.5 L, DSD = 3.5 L, a flat detector of
  2 L with 2 pixels per voxel edge (L = the volume's side) -> FDK, SART, ASD-POCS.

Each orbit has the view count's training angles plus held-out angles (15 % validation, 15 % test, noise-free);
every free parameter is chosen on the validation views, 3D PSNR/SSIM and 2D test PSNR/SSIM come after. ``--set``
overrides a ``baselines`` setting (``--set asd_pocs_alpha=[0.02]``; ``--sart-iterations`` is
``sart_max_iterations``). Writes benchmarks/out/baselines_<source>_<grid>[_arcA].csv and prints the table.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import pandas as pd
import torch
import yaml
from _common import cli_main, out_folder, write_csv

from ctsplat.baselines import run_baselines
from ctsplat.config import check_section
from ctsplat.formats.volume import load_volume
from ctsplat.projector import render_radiographs
from ctsplat.volume import ingest

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "out"


def geometry_config(name: str, grid: int, side_mm: float, n_views: int, arc_deg: float = 180.0) -> dict:
    """The ``radiographs`` settings of one benchmark geometry (``arc_deg``: the parallel beam's orbit)."""
    common = {"orbit": "circular", "n_views": n_views, "split": {"train": 0.7, "val": 0.15, "test": 0.15},
              "device": "cpu"}
    if name == "parallel":
        return {**common, "camera": "parallel", "detector_width": grid, "detector_height": grid, "arc_deg": arc_deg}
    det = 2 * grid
    return {**common, "camera": "cone", "detector_width": det, "detector_height": det, "arc_deg": 360.0,
            "dso_mm": 2.5 * side_mm, "dsd_mm": 3.5 * side_mm, "pixel_spacing_mm": 2.0 * side_mm / det}


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", default=str(ROOT.parent / "shared" / "data" / "ct0051_head"),
                    help="a DICOM folder / NIfTI / TIFF stack, or 'phantom' (default: %(default)s)")
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--views", type=int, nargs="+", default=[50])
    ap.add_argument("--geometries", nargs="+", default=["parallel", "cone"], choices=["parallel", "cone"])
    ap.add_argument("--arc", type=float, default=None,
                    help="angular range of the parallel-beam orbit in deg, (0, 360] (default 180)")
    ap.add_argument("--sart-iterations", type=int, default=None, help="baselines.sart_max_iterations")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a baselines setting (YAML value), e.g. --set asd_pocs_alpha=[0.02]")
    ap.add_argument("--out", default=None, help="CSV (default WORK/baselines_<source>_<grid>.csv)")
    ap.add_argument("--work", default=str(OUT), help="folder of the cached volumes and radiographs (default "
                    "%(default)s)")
    args = ap.parse_args(argv)
    if args.grid < 8 or min(args.views) < 1 or (args.sart_iterations is not None and args.sart_iterations < 1):
        ap.error("--grid must be >= 8, --views and --sart-iterations >= 1")
    if args.arc is not None and not 0 < args.arc <= 360:
        ap.error(f"--arc must be in (0, 360], got {args.arc:g}")
    settings = {} if args.sart_iterations is None else {"sart_max_iterations": args.sart_iterations}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--set {item!r}: expected KEY=VALUE")
        settings[key] = yaml.safe_load(value)
    check_section("baselines", settings)  # before the ingest and the rendering, not after them
    torch.set_num_threads(min(2, os.cpu_count() or 1))

    if args.source != "phantom" and not Path(args.source).exists():
        ap.error(f"--source {args.source} does not exist (or use --source phantom)")
    out_folder(args.work, "--work")  # after every check of the options and the source
    if args.source == "phantom":
        from ctsplat.phantom import write_phantom_dicom

        key, name = "builtin", "phantom"
        source = Path(args.work) / "phantom_dicom"
        if not source.exists():
            write_phantom_dicom(source)
    else:
        source = Path(args.source)
        key, name = hashlib.sha256(str(source.resolve()).encode()).hexdigest()[:8], source.name
    work = Path(args.work) / f"{name}-{key}_{args.grid}"
    vol_path = work / "volume.nii.gz"
    if not vol_path.exists():
        t0 = time.perf_counter()
        ingest(source, vol_path, {"grid": args.grid})
        print(f"ingested {source} -> {vol_path} in {time.perf_counter() - t0:.1f} s")
    vol = load_volume(vol_path)
    side = float(max(vol.shape[i] * vol.spacing_mm[i] for i in range(3)))
    print(f"volume {vol.volume_id}: shape {vol.shape}, voxel {vol.spacing_mm.round(3).tolist()} mm, side {side:.1f} mm")
    tables = []
    tag = "" if args.arc is None else f"_arc{args.arc:g}"
    for geo in args.geometries:
        for n in args.views:
            rad = work / f"circular_{geo}_{n}{tag if geo == 'parallel' else ''}"
            cfg = geometry_config(geo, args.grid, side, n, 180.0 if args.arc is None else args.arc)
            if not (rad / "views.json").exists():
                render_radiographs(vol_path, rad, cfg, seed=0)
            t0 = time.perf_counter()
            df = run_baselines(vol_path, rad, rad.with_name(f"baselines_{rad.name}"), {"save_volumes": False,
                                                                                     **settings})
            wall = time.perf_counter() - t0
            df.insert(0, "geometry", geo)
            df.insert(1, "arc_deg", cfg["arc_deg"])
            df["wall_seconds_all_methods"] = wall
            print(df.drop(columns=["params"]).to_string(index=False, float_format=lambda x: f"{x:.3f}"))
            tables.append(df)
    table = pd.concat(tables, ignore_index=True)
    table.insert(0, "volume", f"{name}@{args.grid}^3")
    args.out = args.out or str(Path(args.work) / f"baselines_{name}_{args.grid}{tag}.csv")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_csv(table, args.out)
    print()
    show = table.assign(chosen=[json.dumps({k: v for k, v in json.loads(p).items() if k != "detector_binning"})
                                for p in table["params"]])
    cols = ["geometry", "arc_deg", "n_views", "method", "chosen", "val_psnr", "psnr3d", "ssim3d", "psnr2d", "seconds",
            "selection_seconds", "best_on_val"]
    print(show[cols].to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    print(f"-> {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """:func:`run` with the benchmarks' one-line errors and clean Ctrl-C / SIGTERM exits (:func:`_common.cli_main`)."""
    return cli_main(run, argv, "baselines.py")


if __name__ == "__main__":
    sys.exit(main())
