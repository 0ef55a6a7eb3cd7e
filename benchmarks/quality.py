"""Quality benchmark: Gaussian models vs FBP/SART on ct0051_head.

Protocol: ``ct0051_head`` ingested to 128^3 normalised attenuation; circular parallel-beam orbits with 25/50/75
training views at 128 detector pixels, 10 validation and 100 random test views; FBP (ramp, Shepp-Logan) and SART
(best of 1..5 iterations) from the same training views (``ctsplat.baselines``); Gaussian models with
``init=fbp`` (honest: FBP of the training projections only) and ``init=volume`` (seeded from the reference volume,
labelled ``uses_reference_volume``), rectified radiative compositor.

Reports per run: 3D PSNR/SSIM, margin over the best baseline, 2D test PSNR/SSIM, wall time, time to beat the best
baseline and time to final quality (first logged time with 3D PSNR within 0.25 dB of the final value).
Writes ``benchmarks/out/quality/quality.csv``, ``quality_curves.csv`` (time-to-quality curves: every logged
iteration of every run) and the run folders; prints a table.

Usage::

    python benchmarks/quality.py                     # full protocol (slow on CPU)
    python benchmarks/quality.py --views 50 --inits fbp --iterations 600   # one quick point
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def prepare(data: Path, out: Path, n_views: int, n_val: int, n_test: int, detector: int) -> tuple[Path, Path]:
    """Ingest once (cached) and render one radiograph set per training-view count (cached)."""
    from ctsplat.projector import render_radiographs
    from ctsplat.volume import ingest

    vol = out / "volume.nii.gz"
    if not vol.exists():
        ingest(data, vol, {"grid": 128})
    rad = out / f"radiographs_n{n_views:03d}"
    if not (rad / "views.json").exists():
        tot = n_views + n_val + n_test
        render_radiographs(vol, rad, {
            "camera": "parallel", "orbit": "circular", "detector_width": detector, "detector_height": detector,
            "n_views": n_views, "split": {"train": n_views / tot, "val": n_val / tot, "test": n_test / tot},
        }, seed=0)
    return vol, rad


def baselines(vol: Path, rad: Path, out: Path) -> pd.DataFrame:
    from ctsplat.baselines import run_baselines

    csv = out / "baselines.csv"
    if csv.exists():
        return pd.read_csv(csv)
    return run_baselines(vol, rad, out, {"save_volumes": False})


def time_to(rows: pd.DataFrame, value: float) -> float | None:
    hit = rows[rows["psnr3d"] >= value]
    return None if hit.empty else float(hit["timestamp"].iloc[0])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "ct0051_head"))
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "quality"))
    ap.add_argument("--views", type=int, nargs="+", default=[25, 50, 75])
    ap.add_argument("--inits", nargs="+", default=["fbp", "volume"])
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--n-init", type=int, default=50000)
    ap.add_argument("--detector", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="extra train config overrides (as `ctsplat train --set`)")
    ap.add_argument("--tag", default="", help="suffix for the run folders (to compare settings)")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from ctsplat.cli.train import load_train_config
    from ctsplat.evaluation import evaluate
    from ctsplat.training import train

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(args.data)
    if not data.is_dir():
        print(f"ct0051_head not found at {data}", file=sys.stderr)
        return 2
    rows, curves = [], []
    for n in args.views:
        vol, rad = prepare(data, out, n, 10, 100, args.detector)
        base = baselines(vol, rad, out / f"baselines_n{n:03d}")
        best = base.loc[base["psnr3d"].idxmax()]
        for _, b in base.iterrows():
            rows.append({"views": n, "method": f"{b['method']}:{b['filter'] if isinstance(b['filter'], str) else ''}"
                         .rstrip(":"), "psnr3d": b["psnr3d"], "ssim3d": b["ssim3d"], "wall_time_s": b["seconds"],
                         "uses_reference_volume": False})
        for init in args.inits:
            cfg = load_train_config(None, args.set)
            cfg.update(volume=str(vol), radiographs=str(rad), init=init, compositor="radiative",
                       iterations=args.iterations, n_init=args.n_init, device="cpu", progress=False)
            run_dir = out / f"run_{init}_n{n:03d}{args.tag}"
            t0 = time.perf_counter()
            train(cfg, run_dir)
            res = evaluate(run_dir, device="cpu")
            total = time.perf_counter() - t0
            log = pd.read_csv(run_dir / "train_log.csv")
            log.insert(0, "run", run_dir.name)
            log.insert(1, "views", n)
            log.insert(2, "init", init)
            curves.append(log)
            rows.append({
                "views": n, "method": f"gs:{init}", "psnr3d": res["psnr3d"], "ssim3d": res["ssim3d"],
                "margin_vs_best_baseline_db": res["psnr3d"] - float(best["psnr3d"]),
                "best_baseline": f"{best['method']}:{best['filter']}", "best_baseline_psnr3d": float(best["psnr3d"]),
                "psnr2d_test": res["psnr2d"], "ssim2d_test": res["ssim2d"], "wall_time_s": res["wall_time_s"],
                "total_time_s": total, "iterations": res["iterations"], "n_gaussians": res["n_gaussians"],
                "time_to_beat_baseline_s": time_to(log, float(best["psnr3d"])),
                "time_to_final_quality_s": time_to(log, res["psnr3d"] - 0.25),
                "uses_reference_volume": res["uses_reference_volume"], "config_hash": res["config_hash"],
            })
            pd.DataFrame(rows).to_csv(out / "quality.csv", index=False)
            pd.concat(curves).to_csv(out / "quality_curves.csv", index=False)
    table = pd.DataFrame(rows)
    table.to_csv(out / "quality.csv", index=False)
    with pd.option_context("display.width", 200, "display.max_columns", 20, "display.float_format", "{:.3f}".format):
        print(table[[c for c in ("views", "method", "psnr3d", "ssim3d", "margin_vs_best_baseline_db", "psnr2d_test",
                                 "wall_time_s", "time_to_beat_baseline_s", "time_to_final_quality_s",
                                 "uses_reference_volume") if c in table]].to_string(index=False))
    (out / "quality.json").write_text(json.dumps({"args": vars(args)}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
