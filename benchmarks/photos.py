"""Photo sanity-run benchmark: COLMAP + alpha 3DGS on the whole skull photo set, evaluated on held-out photos.

The 66 photographs of ``../shared/data/skull_photos`` ("Photogrammetry Test Set: Skull - Cameramoves - Flash - No
Background" by alansartlog, CC BY 4.0, github.com/AlansCodeLog/photogrammetry-test-sets; keep this attribution
with any figure) are posed by :func:`ctsplat.photos.sfm.run_photo_sfm`, trained at ``--downscale`` (default 1/4:
about 265x177) by :func:`ctsplat.photos.train.train_photos` on every image but each 8th and evaluated on the
held-out ones by :func:`ctsplat.photos.evaluate.evaluate_photos`. Prints one JSON line and writes the ``--out``
folder (``benchmarks/out/photos/``: sfm/, run/ with metrics.json, gallery and turntable) and the JSON line beside
it, named after it (``benchmarks/out/photos.json``).

Usage::

    python benchmarks/photos.py                       # SfM + the default 6000 iterations at 1/4 resolution
    python benchmarks/photos.py --iterations 3000 --downscale 2
    python benchmarks/photos.py --sfm-only
    python benchmarks/photos.py --reuse-sfm           # train again on benchmarks/out/photos/sfm
    python benchmarks/photos.py --reuse-sfm --seed 1  # another training seed on the same model
    python benchmarks/photos.py --reuse-sfm --holdout validation   # score photos between the test photos instead

Targets: >= 95 % of the 66 photos registered in one model; held-out PSNR >= 25 dB and SSIM >= 0.8 at 1/4
resolution within 20 minutes on 2 CPU cores. Measured (defaults, 2 idle cores, docs/results.md): 64 of 66 photos
(97 %) in one model, 0.27 px mean reprojection error, 4438 points; at 266x177 held-out PSNR 24.6 dB (missed; 23.9 dB
over seeds 0-2) and SSIM 0.85 (met) in 11 min 12 s with the SfM model reused; the error left is mostly the
backdrop (the stand's untextured plate and the table, which SfM does not reconstruct) and the under-exposed photos.
Settings are compared on validation photos with ``benchmarks/photo_folds.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch
from _common import cli_main

from ctsplat.cli._common import seed_value
from ctsplat.config import check_section
from ctsplat.photos.config import PHOTOS_DEFAULTS, check_train_settings, photo_settings
from ctsplat.photos.evaluate import evaluate_photos
from ctsplat.photos.sfm import run_photo_sfm
from ctsplat.photos.train import check_run, train_photos
from ctsplat.utils import CtsplatError, code_version, write_json_atomic

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "out"
SKULL = Path(os.environ.get("CTSPLAT_SHARED_DATA", ROOT.parent / "shared" / "data")) / "skull_photos"
ATTRIBUTION = ('"Photogrammetry Test Set: Skull - Cameramoves - Flash - No Background" by alansartlog, CC BY 4.0 '
               "(github.com/AlansCodeLog/photogrammetry-test-sets)")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; bad options and bad input end in one line on stderr (exit status 2), an interrupt in one
    line too (:func:`_common.cli_main`)."""
    return cli_main(run, argv, "benchmarks/photos.py")


def run(argv: list[str] | None = None) -> int:
    """Parse the options, then SfM, training and evaluation (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", default=str(SKULL), help="photo folder (default: the skull set)")
    ap.add_argument("--iterations", type=int, default=PHOTOS_DEFAULTS["train"]["iterations"])
    ap.add_argument("--downscale", type=int, default=PHOTOS_DEFAULTS["train"]["downscale"])
    ap.add_argument("--holdout", choices=("test", "validation"), default="test",
                    help="validation: leave the test photos out and score photos between them (to choose settings)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--seed", type=seed_value, default=PHOTOS_DEFAULTS["train"]["seed"],
                    help="training seed (the seeds' spread of the held-out scores; SfM is seeded apart)")
    ap.add_argument("--sfm-only", action="store_true")
    ap.add_argument("--reuse-sfm", action="store_true", help="train on the SfM folder of a previous run")
    ap.add_argument("--out", default=str(OUT / "photos"))
    args = ap.parse_args(argv)
    train = {"iterations": args.iterations, "downscale": args.downscale, "holdout": args.holdout,
             "num_threads": args.threads, "device": args.device, "seed": args.seed}
    check_section("photos", {"train": train})
    out = Path(args.out).resolve()  # its name names the summary beside it, so "." must become a real name
    train_s = photo_settings({"train": train})["train"]
    if args.sfm_only:
        check_train_settings(train_s)
    else:  # what training would refuse, refused before the SfM step
        check_run(out / "run", train_s)
    summary = out / "sfm" / "summary.json"
    if args.reuse_sfm and not summary.is_file():
        raise CtsplatError(f"--reuse-sfm: {summary} not found; run once without --reuse-sfm")
    if not args.reuse_sfm and not Path(args.images).is_dir():
        raise CtsplatError(f"photo folder {args.images} not found (expected ../shared/data/skull_photos)")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    if args.reuse_sfm:
        sfm = json.loads(summary.read_text())
        sfm_s = 0.0
    else:
        sfm = run_photo_sfm(args.images, out / "sfm", {"num_threads": args.threads})
        sfm_s = time.perf_counter() - t0
    row = {"n_images": sfm["n_images"], "n_registered": sfm["n_registered"],
           "registration_rate": sfm["registration_rate"], "unregistered": sfm["unregistered"],
           "models_found": sfm["models_found"], "mean_reprojection_error_px": sfm["mean_reprojection_error_px"],
           "n_points": sfm["n_points"], "sfm_seconds": sfm_s}
    if not args.sfm_only:
        t1 = time.perf_counter()
        train_photos(out / "sfm", out / "run", train)
        train_s = time.perf_counter() - t1
        m = evaluate_photos(out / "run", {"attribution": ATTRIBUTION})
        row.update({"iterations": args.iterations, "downscale": args.downscale, "held_out": m["held_out"],
                    "resolution": m["resolution"],
                    "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"], "lpips_reason": m["lpips_reason"],
                    "n_test": m["n_test"], "n_train": m["n_train"], "n_gaussians": m["n_gaussians"],
                    "fps": m["fps"], "peak_rss_mb": m["peak_rss_mb"], "train_seconds": train_s,
                    "train_loop_seconds": m["training"].get("seconds")})
    row.update({"total_seconds": time.perf_counter() - t0, "threads": args.threads, "device": args.device,
                "seed": args.seed,
                "code_version": code_version()})
    write_json_atomic(out.with_name(out.name + ".json"), row)  # beside the --out folder: photos.json by default
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
