"""Training-features benchmark: the baseline training config against each of the method's features switched on.

Protocol: a volume (default ``ct0051_head``) ingested to ``--grid``^3 normalised attenuation
(``ctsplat.volume.ingest``); circular parallel-beam orbits with 25 and 50 training views at ``--detector`` pixels,
10 validation and 100 test views (``ctsplat.projector.render_radiographs``); one training run per view count and
variant, every variant the baseline config (``init: fbp``, radiative, features off) with one feature on:

- ``augment``: pose perturbation (<= 0.5 deg, <= 0.5 px) and 0.5 % target noise (``train.augment``);
- ``density_warmup``: λρ × 10 for the first 15 % of the iterations (``train.lambda_density_warmup``);
- ``densify_error`` / ``densify_both``: error-driven densification alone / beside the gradient rule
  (``train.densify.strategy``);
- ``prune_redundant``: redundant-coverage merging (``train.densify.prune_redundant``);
- ``optimizer_method``: the method's optimiser preset (``train.optimizer_preset: method``);
- ``best_model``: no extra training; the baseline run's ``model_best.pt`` evaluated instead of its last model;
- ``all``: every training feature above on at once.

Reports per run: 3D PSNR/SSIM and 2D test PSNR (``ctsplat.evaluation.evaluate``), the validation PSNR of the
evaluated model (all validation views; the criterion for keeping a feature as default), its difference from the
baseline's, the training wall time and the number of Gaussians. Writes ``benchmarks/out/features/features.csv`` and
the run folders; prints a table. The ingested volume and radiographs are cached under ``cache/<data>-<hash>/``.

Usage::

    python benchmarks/features.py                                   # ct0051_head, 25 and 50 views (slow on CPU)
    python benchmarks/features.py --data PHANTOM_DICOM --grid 32 --detector 32 --views 8 --iterations 20
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _common import cli_main, data_cache, out_folder, shared_train_config, write_csv  # noqa: E402

from ctsplat.utils import write_json_atomic  # noqa: E402

#: train overrides of each variant (applied on top of the shared config; the baseline has none)
VARIANTS: dict[str, dict[str, Any]] = {
    "baseline": {},
    "augment": {"augment": {"enabled": True}},
    "density_warmup": {"lambda_density_warmup": {"factor": 10.0, "fraction": 0.15, "decay": 0.05}},
    "densify_error": {"densify": {"strategy": "error"}},
    "densify_both": {"densify": {"strategy": "both"}},
    "prune_redundant": {"densify": {"prune_redundant": {"enabled": True}}},
    "optimizer_method": {"optimizer_preset": "method"},
    "best_model": {},  # evaluates the baseline run's model_best.pt
    "all": {"augment": {"enabled": True},
            "lambda_density_warmup": {"factor": 10.0, "fraction": 0.15, "decay": 0.05},
            "densify": {"strategy": "both", "prune_redundant": {"enabled": True}},
            "optimizer_preset": "method"},
}

#: train keys (dotted prefixes) this script sets per run, and the option that sets them instead of --set
OWN_KEYS = {"volume": "--data", "radiographs": "--views / --detector", "init": "--init", "iterations": "--iterations",
            "n_init": "--n-init", "progress": None, "augment": "--variants", "lambda_density_warmup": "--variants",
            "optimizer_preset": "--variants", "densify.strategy": "--variants",
            "densify.prune_redundant": "--variants", "model_selection": "--variants"}


def prepare(data: Path, cache: Path, grid: int, n_views: int, n_val: int, n_test: int, detector: int
            ) -> tuple[Path, Path]:
    """Ingest once (``grid``^3) and render one radiograph set per training-view count (cached in ``cache``)."""
    from ctsplat.projector import render_radiographs
    from ctsplat.volume import ingest

    vol = cache / "volume.nii.gz"
    if not vol.exists():
        ingest(data, vol, {"grid": grid})
    rad = cache / f"radiographs_n{n_views:03d}_d{detector}"
    if not (rad / "views.json").exists():
        tot = n_views + n_val + n_test
        render_radiographs(vol, rad, {
            "camera": "parallel", "orbit": "circular", "detector_width": detector, "detector_height": detector,
            "n_views": n_views, "split": {"train": n_views / tot, "val": n_val / tot, "test": n_test / tot},
        }, seed=0)
    return vol, rad


def train_config(sets: list[str], iterations: int, n_init: int, init: str) -> dict[str, Any]:
    """The train settings every run shares: this benchmark's defaults, then ``--set`` (checked against the schema)."""
    return shared_train_config(sets, own_keys=OWN_KEYS, defaults={"init": init},
                               fixed={"iterations": iterations, "n_init": n_init})


def main(argv: list[str] | None = None) -> int:
    return cli_main(run, argv, "features.py")


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "ct0051_head"),
                    help="a DICOM / NIfTI / TIFF source (ingested with ctsplat.volume.ingest)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "features"))
    ap.add_argument("--views", type=int, nargs="+", default=[25, 50])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--init", default="fbp", choices=["fbp", "volume", "uniform"])
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--n-init", type=int, default=50000)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--detector", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="extra train config overrides for every run (as `ctsplat train --set`)")
    args = ap.parse_args(argv)
    for name in ("views", "grid", "detector", "threads", "iterations", "n_init"):
        values = getattr(args, name)
        if min(values if isinstance(values, list) else [values]) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1")

    import torch

    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from ctsplat.evaluation import evaluate
    from ctsplat.training import train
    from ctsplat.utils import deep_update

    shared = train_config(args.set, args.iterations, args.n_init, args.init)  # refused before any work
    data = Path(args.data)
    if not data.exists():
        print(f"features.py: error: no volume source at {data}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out_folder(out)
    cache = data_cache(out, data, f"-g{args.grid}")
    cache.mkdir(parents=True, exist_ok=True)
    variants = list(args.variants)
    if "best_model" in variants and "baseline" not in variants:
        variants.insert(0, "baseline")  # best_model evaluates the baseline run
    rows: list[dict[str, Any]] = []
    for n in args.views:
        vol, rad = prepare(data, cache, args.grid, n, 10, 100, args.detector)
        base_val = None
        for variant in variants:
            cfg = deep_update({**shared, "volume": str(vol), "radiographs": str(rad)}, VARIANTS[variant])
            run_dir = out / f"run_baseline_n{n:03d}" if variant == "best_model" else out / f"run_{variant}_n{n:03d}"
            model = "best" if variant == "best_model" else "last"
            t0 = time.perf_counter()
            if variant != "best_model":
                train(cfg, run_dir)
            res = evaluate(run_dir, device=cfg["device"], model=model, write=False)
            val = evaluate(run_dir, split="val", device=cfg["device"], model=model, write=False)
            total = time.perf_counter() - t0
            if variant == "baseline":
                base_val = val["psnr2d"]
            trained = json.loads((run_dir / "training.json").read_text())
            rows.append({
                "views": n, "variant": variant, "model": model, "psnr3d": res["psnr3d"], "ssim3d": res["ssim3d"],
                "psnr2d_test": res["psnr2d"], "val_psnr2d": val["psnr2d"],
                "val_delta_db": None if base_val is None else val["psnr2d"] - base_val,
                "model_iteration": res["model_iteration"], "wall_time_s": trained["wall_time_s"],
                "total_time_s": round(total, 3), "n_gaussians": res["n_gaussians"],
                "densify_cloned": trained.get("densify_cloned"), "densify_split": trained.get("densify_split"),
                "densify_pruned": trained.get("densify_pruned"), "config_hash": res["config_hash"],
                "settings": " ".join(args.set),
            })
            write_csv(pd.DataFrame(rows), out / "features.csv")
    table = pd.DataFrame(rows)
    write_csv(table, out / "features.csv")
    with pd.option_context("display.width", 200, "display.max_columns", 20, "display.float_format", "{:.3f}".format):
        print(table[["views", "variant", "psnr3d", "ssim3d", "psnr2d_test", "val_psnr2d", "val_delta_db",
                     "wall_time_s", "n_gaussians"]].to_string(index=False))
    write_json_atomic(out / "features.json", {"args": vars(args), "train": shared, "variants": VARIANTS})
    return 0


if __name__ == "__main__":
    sys.exit(main())
