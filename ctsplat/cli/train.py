"""``ctsplat train`` and ``ctsplat evaluate``: fit a Gaussian model to radiographs, evaluate a finished run."""

from __future__ import annotations

import argparse
import contextlib
import json
from pathlib import Path
from typing import Any

from ctsplat.cli._common import apply_sets, section_config, seed_value


def load_train_config(path: str | None, overrides: list[str]) -> dict[str, Any]:
    """The ``train`` section from a YAML/JSON file (top level or under ``train:``) plus ``key=value`` overrides.

    Dotted keys set nested values (``densify.interval=100``); values parse as JSON, else YAML (numbers,
    booleans, lists); each value is checked against the schema's type and range (a wrong one is refused naming
    its key).
    """
    return section_config(path, overrides, "train")


def _train(args: argparse.Namespace) -> None:
    from ctsplat.evaluation import evaluate
    from ctsplat.training import train
    from ctsplat.training.checkpoint import list_checkpoints
    from ctsplat.training.config import resolve_config
    from ctsplat.training.loop import check_run_folder
    from ctsplat.utils import CtsplatError, run_lock

    cfg = load_train_config(args.config, args.set or [])
    for key in ("volume", "radiographs", "sfm_dir", "sfm_radiographs", "init", "compositor", "poses", "device"):
        val = getattr(args, key)
        if val is not None:
            cfg[key] = val
    for key in ("seed", "iterations", "views"):
        val = getattr(args, key)
        if val is not None:
            cfg[key] = int(val)
    if args.quiet:
        cfg["progress"] = False
    resolve_config(cfg)  # bad settings fail before the run folder is created and locked
    out = Path(args.out)
    check_run_folder(cfg, out)  # before the lock file goes into someone else's folder
    # one lock over training and evaluation, so no other process writes the folder in between
    with run_lock(out):
        earlier = [p.relative_to(out).as_posix() for p in list_checkpoints(out)[-1:]]
        earlier += [name for name in ("model.pt", "training.json") if (out / name).exists()]
        if earlier and not (args.resume or args.restart):
            raise CtsplatError(f"{out} already holds a training run ({', '.join(earlier)}); pass --resume to continue "
                               "it or --restart to discard it and start over")
        trained = train(cfg, out, resume=args.resume)
        if args.no_evaluate:
            print(json.dumps(trained))
            return
        res = evaluate(out, device=cfg.get("device", "auto"))
    keys = ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "n_gaussians", "wall_time_s", "uses_reference_volume")
    print(json.dumps({k: res[k] for k in keys}))


def _evaluate(args: argparse.Namespace) -> None:
    from ctsplat.evaluation import evaluate
    from ctsplat.utils import run_lock

    run_dir = Path(args.run_dir)
    # a folder that is not a run is reported by evaluate; locking would create it, or leave a lock file in it
    with run_lock(run_dir) if (run_dir / "config.json").is_file() else contextlib.nullcontext():
        res = evaluate(run_dir, split=args.split, device=args.device, settings=apply_sets({}, args.set) or None)
    print(json.dumps(res, indent=2, default=str))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train", help="train a Gaussian model on radiographs",
        description="Train a rectified radiative Gaussian model (seeding, densification, CSV logs, checkpoints, "
                    "model.pt/model.ply) into OUT, then evaluate it on the test views (metrics.json, figures) "
                    "as `ctsplat evaluate OUT` does.",
    )
    p.add_argument("--config", help="YAML/JSON file with the train section (top level or under 'train:')")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config value (repeatable; dotted keys for nested, e.g. densify.interval=100)")
    p.add_argument("--out", required=True, help="run folder to write")
    again = p.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue the run in OUT from its newest readable checkpoint (same config required)")
    again.add_argument("--restart", action="store_true",
                       help="discard the run already in OUT (checkpoints, model) and start over")
    p.add_argument("--volume", help="reference volume (.nii.gz)")
    p.add_argument("--radiographs", help="radiographs folder (line_integrals.tif + views.json)")
    p.add_argument("--sfm-dir", dest="sfm_dir", help="sfm step folder (poses: colmap / init: sfm)")
    p.add_argument("--sfm-radiographs", dest="sfm_radiographs",
                   help="radiographs folder of the view set SfM registered (default: the one sfm's summary names)")
    p.add_argument("--init", help="volume | uniform | fbp | sfm")
    p.add_argument("--compositor", help="radiative | radiative_unrectified | alpha")
    p.add_argument("--poses", help="gt | perturbed | colmap, each optionally +refine (e.g. colmap+refine)")
    p.add_argument("--device", help="auto | cpu | cuda")
    p.add_argument("--seed", type=seed_value)
    p.add_argument("--iterations", type=int)
    p.add_argument("--views", type=int, help="number of training views (0 = all)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-evaluate", dest="no_evaluate", action="store_true",
                   help="train only; evaluate later with `ctsplat evaluate OUT`")
    p.set_defaults(func=_train)

    e = subparsers.add_parser("evaluate", help="evaluate a trained run on a split",
                              description="Render a finished run's model on a split and measure PSNR/SSIM/LPIPS 2D, "
                                          "PSNR/SSIM 3D, FPS and milestones; writes RUN_DIR/metrics.json (test) "
                                          "or metrics_SPLIT.json, per_view_SPLIT.csv and, for test, the figures.")
    e.add_argument("run_dir", help="run folder written by `ctsplat train`")
    e.add_argument("--split", default="test", choices=["test", "val", "train"])
    e.add_argument("--device", default="auto")
    e.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="an evaluation setting (figures, turntable_frames, fps_width, fps_height, model_selection, "
                        "sharpen.amounts, sharpen.radius_voxels; repeatable); a setting not given keeps the value "
                        "the last evaluation of this split recorded, else the run's")
    e.set_defaults(func=_evaluate)
