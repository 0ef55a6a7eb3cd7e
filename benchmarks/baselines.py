"""Classical baselines on real data: FBP (ramp, shepp-logan) and SART (best of 1..5 iterations) from
25/50/75 circular parallel-beam views of ct0051_head at 128^3 (128 detector pixels), 3D PSNR/SSIM.

    .venv/bin/python benchmarks/baselines.py [--source ../shared/data/ct0051_head] [--grid 128]
        [--views 25 50 75] [--sart-iterations 5] [--arc 360]

Steps: ``ctsplat.volume.ingest`` (default preprocessing, grid^3, cached under benchmarks/out/ per source and
grid), then for each view count a circular parallel orbit with exactly that many evenly spaced training angles
over ``--arc`` degrees (``ctsplat.projector.render_radiographs``, detector grid x grid, one voxel per pixel;
without ``--arc`` the workflow's default, 180 deg for parallel beams), then ``ctsplat.baselines.run_baselines``.
Writes benchmarks/out/baselines_<source>[_arcA].csv (``--work`` moves benchmarks/out) and prints the table.
Over 360 deg, parallel views at a and a + 180 are mirror images: an even view count gives only half as many
distinct directions as an odd one (50 views ~ 25 views); 180 deg avoids that.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import pandas as pd
import torch

from ctsplat.baselines import run_baselines
from ctsplat.formats.volume import load_volume
from ctsplat.projector import render_radiographs
from ctsplat.volume import ingest

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "out"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=str(ROOT.parent / "shared" / "data" / "ct0051_head"))
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--views", type=int, nargs="+", default=[25, 50, 75])
    ap.add_argument("--sart-iterations", type=int, default=5)
    ap.add_argument("--arc", type=float, default=None,
                    help="angular range of the circular orbit in deg, (0, 360] (default: the workflow's, 180 for "
                    "parallel beams; 360 gives mirrored parallel-beam views)")
    ap.add_argument("--out", default=None, help="CSV (default WORK/baselines_<source>[_arcA].csv)")
    ap.add_argument("--work", default=str(OUT), help="folder of the cached volumes and radiographs (default "
                    "%(default)s)")
    args = ap.parse_args(argv)
    if args.grid < 8 or min(args.views) < 1 or args.sart_iterations < 1:
        ap.error("--grid must be >= 8, --views and --sart-iterations >= 1")
    if args.arc is not None and not 0 < args.arc <= 360:
        ap.error(f"--arc must be in (0, 360], got {args.arc:g}")
    source = Path(args.source)
    if not source.exists():
        ap.error(f"--source {source} does not exist")
    torch.set_num_threads(min(2, os.cpu_count() or 1))

    # one cache folder per source (its name and a hash of its resolved path) and grid
    key = hashlib.sha256(str(source.resolve()).encode()).hexdigest()[:8]
    work = Path(args.work) / f"{source.name}-{key}_{args.grid}"
    vol_path = work / "volume.nii.gz"
    if not vol_path.exists():
        t0 = time.perf_counter()
        ingest(source, vol_path, {"grid": args.grid})
        print(f"ingested {source} -> {vol_path} in {time.perf_counter() - t0:.1f} s")
    vol = load_volume(vol_path)
    print(f"volume {vol.volume_id}: shape {vol.shape}, voxel {vol.spacing_mm.round(3).tolist()} mm, "
          f"mu_scale {vol.mu_scale_per_mm} /mm")
    tables = []
    tag = "" if args.arc is None else f"_arc{args.arc:g}"
    for n in args.views:
        rad = work / f"circular_parallel_{n}{tag}"
        cfg = {"camera": "parallel", "orbit": "circular", "n_views": n, "detector_width": args.grid,
               "detector_height": args.grid, "split": {"train": 1.0, "val": 0.0, "test": 0.0}, "device": "cpu",
               "arc_deg": args.arc}
        t0 = time.perf_counter()
        vs = render_radiographs(vol_path, rad, cfg, seed=0)
        t_proj = time.perf_counter() - t0
        df = run_baselines(vol_path, rad, work / f"baselines_{n}{tag}",
                           {"sart_max_iterations": args.sart_iterations})
        df["projection_seconds"] = t_proj
        print(df.to_string(index=False))
        tables.append(df.assign(arc_deg=vs.meta["arc_deg"]))
    table = pd.concat(tables, ignore_index=True)
    table.insert(0, "volume", f"{source.name}@{args.grid}^3")
    table.insert(1, "arc_deg", table.pop("arc_deg"))
    args.out = args.out or str(Path(args.work) / f"baselines_{source.name}{tag}.csv")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out, index=False, lineterminator="\n")
    print()
    print(table.to_string(index=False, float_format=lambda x: f"{x:.4f}"))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
