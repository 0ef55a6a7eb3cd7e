"""Classical baselines on real data: FBP (ramp, shepp-logan) and SART (best of 1..5 iterations) from
25/50/75 circular parallel-beam views of ct0051_head at 128^3 (128 detector pixels), 3D PSNR/SSIM.

    .venv/bin/python benchmarks/baselines.py [--source ../shared/data/ct0051_head] [--grid 128]
        [--views 25 50 75] [--sart-iterations 5] [--arc 360]

Steps: ``ctsplat.volume.ingest`` (default preprocessing, grid^3, cached under benchmarks/out/), then for
each view count a circular parallel orbit with exactly that many evenly spaced training angles
(``ctsplat.projector.render_radiographs``, detector grid x grid, one voxel per pixel), then
``ctsplat.baselines.run_baselines``. Writes benchmarks/out/baselines_ct0051.csv and prints the table.
Over 360 deg, parallel views at a and a + 180 are mirror images: an even view count gives only half as many
distinct directions as an odd one (50 views ~ 25 views); ``--arc 180`` avoids that.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import pandas as pd
import torch

from ctsplat.baselines import run_baselines
from ctsplat.formats.viewset import ViewSet, write_radiographs
from ctsplat.formats.volume import load_volume
from ctsplat.geometry import circular_orbit
from ctsplat.projector import build_view_set, line_integrals, render_radiographs
from ctsplat.volume import ingest

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "out"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=str(ROOT.parent / "shared" / "data" / "ct0051_head"))
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--views", type=int, nargs="+", default=[25, 50, 75])
    ap.add_argument("--sart-iterations", type=int, default=5)
    ap.add_argument("--arc", type=float, default=360.0,
                    help="angular range of the circular orbit (360 = the workflow's orbit; 180 = no mirrored "
                    "parallel-beam views)")
    ap.add_argument("--out", default=None, help="CSV (default benchmarks/out/baselines_ct0051[_arc180].csv)")
    args = ap.parse_args()
    torch.set_num_threads(min(2, os.cpu_count() or 1))

    work = OUT / f"ct0051_{args.grid}"
    vol_path = work / "volume.nii.gz"
    if not vol_path.exists():
        t0 = time.perf_counter()
        ingest(args.source, vol_path, {"grid": args.grid})
        print(f"ingested {args.source} -> {vol_path} in {time.perf_counter() - t0:.1f} s")
    vol = load_volume(vol_path)
    print(f"volume {vol.volume_id}: shape {vol.shape}, voxel {vol.spacing_mm.round(3).tolist()} mm, "
          f"mu_scale {vol.mu_scale_per_mm} /mm")
    tables = []
    tag = "" if args.arc == 360 else f"_arc{args.arc:g}"
    for n in args.views:
        rad = work / f"circular_parallel_{n}{tag}"
        cfg = {"camera": "parallel", "orbit": "circular", "n_views": n, "detector_width": args.grid,
               "detector_height": args.grid, "split": {"train": 1.0, "val": 0.0, "test": 0.0}, "device": "cpu"}
        t0 = time.perf_counter()
        if args.arc == 360:
            render_radiographs(vol_path, rad, cfg, seed=0)
        else:  # same camera, training angles over arc_deg (not a RADIOGRAPHS_DEFAULTS setting yet)
            vs = build_view_set(vol, cfg, seed=0)
            views = circular_orbit(n, vs.isocenter_mm, vs.meta["distance_mm"], split_fractions=cfg["split"],
                                   arc_deg=args.arc)
            vs = ViewSet(vs.camera, views, vol.volume_id, vs.isocenter_mm, {**vs.meta, "arc_deg": args.arc})
            with torch.no_grad():
                p = line_integrals(vol.data * vol.mu_scale_per_mm, vol.affine, vs.camera, vs.Rs(), vs.ts())
            write_radiographs(rad, p.numpy(), vs, {"config": cfg, "arc_deg": args.arc, "volume_id": vol.volume_id,
                                                    "mu_scale_per_mm": vol.mu_scale_per_mm})
        t_proj = time.perf_counter() - t0
        df = run_baselines(vol_path, rad, work / f"baselines_{n}{tag}",
                           {"sart_max_iterations": args.sart_iterations})
        df["projection_seconds"] = t_proj
        print(df.to_string(index=False))
        tables.append(df)
    table = pd.concat(tables, ignore_index=True)
    table.insert(0, "volume", f"ct0051_head@{args.grid}^3")
    table.insert(1, "arc_deg", args.arc)
    args.out = args.out or str(OUT / f"baselines_ct0051{tag}.csv")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out, index=False)
    print()
    print(table.to_string(index=False, float_format=lambda x: f"{x:.4f}"))
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
