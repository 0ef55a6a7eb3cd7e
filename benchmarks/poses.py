"""Pose benchmark: training with true, perturbed and SfM poses, each with and without joint pose refinement.

Protocol: a volume (default ``ct0051_head``; ``--data phantom`` for the built-in Shepp–Logan phantom with beads)
ingested to ``--grid``^3 (``ctsplat.volume.ingest``); per beam (``parallel``, ``cone``) a circular training orbit
with ``--views`` training, 10 validation and 100 test views at ``--detector`` pixels (cone: DSO 600 mm, DSD
1000 mm); for the SfM variants one C-arm cone-beam view set (90 views, ±15° wobble, true orbit 1° / 0.5 mm off its
design per view) registered once by ``ctsplat.sfm.run_sfm`` with the C-arm recipe of ``config/config.yaml``.
One training run per beam and ``poses`` value (``init: fbp``, radiative):

- ``gt``: the true poses; ``perturbed``: the true poses with a per-view C-arm error (``perturb_rot_deg``,
  ``perturb_trans_mm``; default N(0, 1°) azimuth/elevation, N(0, 0.5 mm) isocentre) — images stay exact;
- ``perturbed+refine``: the same, refined jointly with the Gaussians (``train.pose_refine``);
- ``colmap`` / ``colmap+refine``: ``--views`` of the C-arm views SfM registered at the recovered poses (cone-beam
  images whatever the beam; validated and tested on the beam's own held-out views, as the workflow does).

Cone-beam refinement runs once per ``--cone-models`` entry (``train.pose_refine.cone_model``: ``rigid``, the
6-DoF correction, and/or ``carm``, no shift along the central ray); the ``cone_model`` column names it.

Reports per run: 3D PSNR/SSIM (also after undoing the rigid motion of the training poses that no image can show:
``psnr3d_gauge_aligned``; equal to ``psnr3d`` at the true poses) and 2D test PSNR
(``ctsplat.evaluation.evaluate``), the median / p90 rotation error (degrees) and median isocentre error (mm) of the
training poses before and after refinement, the final and best validation PSNR (the criterion for choosing
settings) and the training wall time. Writes ``benchmarks/out/poses/poses.csv`` and the run folders; prints a
table. Ingested volumes, radiographs and the SfM result are cached under ``cache/``.

Usage::

    python benchmarks/poses.py                        # ct0051_head at 128^3, 50 views, both beams (slow on CPU)
    python benchmarks/poses.py --data phantom --grid 24 --detector 24 --views 8 --iterations 30 \\
        --poses gt perturbed perturbed+refine --beams parallel          # smoke test
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

POSES = ("gt", "perturbed", "perturbed+refine", "colmap", "colmap+refine")
CONE = {"dso_mm": 600.0, "dsd_mm": 1000.0}
CARM = {"camera": "cone", "orbit": "carm", "n_views": 90, "wobble_deg": 15.0, **CONE, "orbit_jitter_deg": 1.0,
        "orbit_jitter_mm": 0.5}
#: keys each run sets, and the option that sets them (refused in --set)
OWN_KEYS = {"volume": "--data", "radiographs": "--views / --detector", "poses": "--poses", "views": "--views",
            "sfm_dir": None, "iterations": "--iterations", "n_init": "--n-init", "progress": None,
            "pose_refine.cone_model": "--cone-models"}
#: the C-arm SfM recipe of config/config.yaml (docs/sfm.md)
SFM = {"pose_prior": "isocentric", "design_sigma_deg": 1.0, "highpass_frac": 0.03, "lowpass_px": 1.0,
       "percentile_low": 0.5, "percentile_high": 99.5, "silhouette_margin_frac": 0.05}


def ingest_volume(data: str, cache: Path, grid: int) -> Path:
    """The ingested volume (``grid``^3), cached; ``data == "phantom"`` writes the built-in phantom as DICOM first."""
    from ctsplat.volume import ingest

    vol = cache / "volume.nii.gz"
    if vol.exists():
        return vol
    src = Path(data)
    if data == "phantom":
        from ctsplat.phantom import write_phantom_dicom

        src = cache / "phantom_dicom"
        write_phantom_dicom(src, size=grid, beads=True)
    ingest(src, vol, {"grid": grid})
    return vol


def training_views(vol: Path, cache: Path, beam: str, n: int, detector: int) -> Path:
    """The beam's circular orbit: ``n`` training, 10 validation and 100 test views (cached)."""
    from ctsplat.projector import render_radiographs

    rad = cache / f"{beam}_n{n:03d}_v010_t100_d{detector}"
    if not (rad / "views.json").exists():
        tot = n + 110
        # a circular orbit's n_views counts the training views; the fractions set the held-out counts from it
        cfg = {"camera": beam, "orbit": "circular", "detector_width": detector, "detector_height": detector,
               "n_views": n, "split": {"train": n / tot, "val": 10 / tot, "test": 100 / tot}}
        if beam == "cone":
            cfg.update(CONE, arc_deg=360.0)
        render_radiographs(vol, rad, cfg, seed=0)
    return rad


def sfm_result(vol: Path, cache: Path, detector: int) -> Path:
    """The C-arm view set and its SfM result (``cache/sfm``), computed once."""
    from ctsplat.projector import render_radiographs
    from ctsplat.sfm import run_sfm

    carm = cache / f"carm_d{detector}"
    if not (carm / "views.json").exists():
        render_radiographs(vol, carm, {**CARM, "detector_width": detector, "detector_height": detector}, seed=0)
    out = cache / f"sfm_d{detector}"
    if not (out / "summary.json").exists():
        run_sfm(carm, out, SFM, seed=0, volume_path=vol)
    return out


def train_config(sets: list[str], iterations: int, n_init: int) -> dict[str, Any]:
    """The settings every run shares: this benchmark's defaults, then ``--set`` (checked against the schema)."""
    return shared_train_config(sets, own_keys=OWN_KEYS, defaults={"init": "fbp"},
                               fixed={"iterations": iterations, "n_init": n_init})


def main(argv: list[str] | None = None) -> int:
    return cli_main(run, argv, "poses.py")


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "ct0051_head"),
                    help="a DICOM / NIfTI / TIFF source, or 'phantom'")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "poses"))
    ap.add_argument("--beams", nargs="+", default=["parallel", "cone"], choices=["parallel", "cone"])
    ap.add_argument("--poses", nargs="+", default=list(POSES), choices=list(POSES))
    ap.add_argument("--views", type=int, default=50)
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--n-init", type=int, default=50000)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--detector", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="extra train config overrides for every run (as `ctsplat train --set`)")
    ap.add_argument("--cone-models", nargs="+", default=["rigid"], choices=["rigid", "carm"],
                    help="cone-beam refinement models, one run each (train.pose_refine.cone_model)")
    args = ap.parse_args(argv)
    for name in ("views", "grid", "detector", "threads", "iterations", "n_init"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1")

    import torch

    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from ctsplat.evaluation import evaluate
    from ctsplat.formats.runlog import read_train_log
    from ctsplat.training import train

    shared = train_config(args.set, args.iterations, args.n_init)  # refused before any work
    if args.data != "phantom" and not Path(args.data).exists():
        print(f"poses.py: error: no volume source at {args.data}", file=sys.stderr)
        return 2
    out = out_folder(args.out)
    cache = data_cache(out, args.data, f"-g{args.grid}")
    cache.mkdir(parents=True, exist_ok=True)
    vol = ingest_volume(args.data, cache, args.grid)
    sfm_dir = sfm_result(vol, cache, args.detector) if any(p.startswith("colmap") for p in args.poses) else None
    rows: list[dict[str, Any]] = []
    for beam in args.beams:
        rad = training_views(vol, cache, beam, args.views, args.detector)
        variants = [(p, m) for p in args.poses
                    for m in (args.cone_models if beam == "cone" and p.endswith("+refine") else [None])]
        for poses, cone_model in variants:
            cfg = {**shared, "volume": str(vol), "radiographs": str(rad), "poses": poses, "views": args.views}
            if cone_model is not None:
                cfg["pose_refine"] = {**cfg.get("pose_refine", {}), "cone_model": cone_model}
            if poses.startswith("colmap"):
                cfg["sfm_dir"] = str(sfm_dir)
            tag = "_carm" if cone_model == "carm" else ""
            run_dir = out / f"run_{beam}_{poses.replace('+', '_')}{tag}_n{args.views:03d}"
            t0 = time.perf_counter()
            train(cfg, run_dir)
            res = evaluate(run_dir, device=cfg["device"], write=False)
            trained = json.loads((run_dir / "training.json").read_text())
            rows.append({
                "beam": beam, "poses": poses, "cone_model": cone_model or "", "views": args.views,
                "psnr3d": res["psnr3d"], "ssim3d": res["ssim3d"],
                # the same after undoing the common motion of the training poses, which no image can show
                "psnr3d_gauge_aligned": res.get("psnr3d_gauge_aligned", res["psnr3d"]),
                "ssim3d_gauge_aligned": res.get("ssim3d_gauge_aligned", res["ssim3d"]),
                "psnr2d_test": res["psnr2d"],
                # the criterion for choosing settings: the validation views at the end and at their best
                "psnr2d_val": float(read_train_log(run_dir / "train_log.csv")["psnr2d"].iloc[-1]),
                "best_val_psnr": trained.get("best_val_psnr"),
                **{k: trained.get(f"pose_{k}") for k in (
                    "rot_err_median_deg_before", "rot_err_p90_deg_before", "rot_err_median_deg_after",
                    "rot_err_aligned_median_deg_before", "rot_err_aligned_median_deg_after",
                    "rot_err_p90_deg_after", "iso_err_median_mm_before", "iso_err_median_mm_after")},
                "wall_time_s": trained["wall_time_s"], "total_time_s": round(time.perf_counter() - t0, 3),
                "n_gaussians": res["n_gaussians"], "config_hash": res["config_hash"], "settings": " ".join(args.set),
            })
            write_csv(pd.DataFrame(rows), out / "poses.csv")
    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        print(df.drop(columns=["config_hash", "settings"]).round(3).to_string(index=False))
    print(f"wrote {out / 'poses.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
