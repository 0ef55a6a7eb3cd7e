"""``ctsplat gather`` (summary.csv, one row per run) and ``ctsplat analyse`` (the results-chapter figures)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ctsplat.utils import CtsplatError

# Options that default to the workflow schema's `analysis` section (resolved when a command runs, so that
# `ctsplat --help` does not load the schema).
ANALYSIS_OPTIONS = ("window", "max_gap_iters", "velocity_per_iters", "acf_max_lag", "kde_windows")


def _default(key: str) -> str:
    return f"(default: analysis.{key} of the config schema)"


def _analysis_config(args: argparse.Namespace) -> dict[str, Any]:
    """The schema's ``analysis`` defaults, overridden by the options given on the command line."""
    from ctsplat.config import check_values, load_schema, schema_defaults

    cfg = schema_defaults("analysis")
    cfg.update({k: getattr(args, k) for k in ANALYSIS_OPTIONS if getattr(args, k, None) is not None})
    cfg["milestones"] = _thresholds(cfg["milestones"], args.milestone)
    check_values(cfg, load_schema()["properties"]["analysis"], "analysis")  # the workflow's ranges and metrics
    return cfg


def _thresholds(defaults: dict[str, float], items: list[str] | None) -> dict[str, float]:
    out = dict(defaults)
    for item in items or []:
        key, sep, val = item.partition("=")
        if not sep:
            raise CtsplatError(f"milestone {item!r} must look like metric=value, e.g. psnr2d=30")
        try:
            out[key] = float(val)
        except ValueError as exc:
            raise CtsplatError(f"milestone {item!r}: {val!r} is not a number") from exc
    return out


def _run_dirs(paths: list[str]) -> list[Path]:
    """Run folders from the arguments: a run folder itself, or any folder searched for grid runs (``KEY~VALUE``
    folders with ``train_log.csv`` or ``metrics.json``; a photo run, ``{volume}/photos/run``, is not one)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if not p.exists():
            raise CtsplatError(f"{p} does not exist")
        if (p / "train_log.csv").exists() or (p / "metrics.json").exists():
            out.append(p)
        else:
            found = sorted({q.parent for name in ("train_log.csv", "metrics.json") for q in p.rglob(name)
                            if "~" in q.parent.name})
            if not found:
                raise CtsplatError(f"no run folders (with train_log.csv or metrics.json) under {p}")
            out += found
    unique: dict[Path, Path] = {}
    for d in out:  # a folder named twice, or found under two of the arguments, is one run
        unique.setdefault(d.resolve(), d)
    return list(unique.values())


def run_gather(args: argparse.Namespace) -> None:
    from ctsplat.analysis.gather import gather

    cfg = _analysis_config(args)
    _check_baselines(args.baselines)
    df = gather(_run_dirs(args.runs), args.out, thresholds=cfg["milestones"],
                max_gap_iters=cfg["max_gap_iters"], per_iters=cfg["velocity_per_iters"],
                baselines_csvs=args.baselines or [])
    print(f"{args.out}: {len(df)} runs")


def run_analyse(args: argparse.Namespace) -> None:
    from ctsplat.analysis import ANALYSIS_OUTPUTS
    from ctsplat.analysis.plots import analyse

    out_dir = Path(args.out_dir)
    outputs = {name: out_dir / fname for name, (fname, _) in ANALYSIS_OUTPUTS.items()}
    provenance = outputs["provenance"]
    taken = [p.name for p in outputs.values() if p.exists() or p.is_symlink()]
    if taken and not provenance.is_file():  # an earlier analyse leaves its analysis.json beside its outputs
        raise CtsplatError(f"{out_dir} holds {taken[0]}, which analyse would replace but did not write (no "
                           f"{provenance.name} there); choose another --out-dir")
    cfg = _analysis_config(args)
    if not Path(args.summary).exists():
        raise CtsplatError(f"summary {args.summary} does not exist; run `ctsplat gather` first")
    _check_baselines(args.baselines)
    analyse(args.summary, outputs, baselines_csvs=args.baselines or [], analysis=cfg)
    for path in outputs.values():
        print(path)


def _check_baselines(paths: list[str] | None) -> None:
    missing = [b for b in paths or [] if not Path(b).is_file()]
    if missing:
        raise CtsplatError(f"baselines file {missing[0]} does not exist; run `ctsplat baseline` first")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--max-gap-iters", type=int,
                   help="forward-fill missing metrics from a value fewer than this many iterations earlier "
                        + _default("max_gap_iters"))
    p.add_argument("--velocity-per-iters", type=int,
                   help="velocity unit: gain per N iterations " + _default("velocity_per_iters"))
    p.add_argument("--baselines", nargs="*", help="baselines.csv files from `ctsplat baseline` (gather: each run "
                   "against the strongest classical method of its volume, by the volume_id in baselines.json, at "
                   "its views; analyse: the baselines figure)")
    p.add_argument("--milestone", action="append", metavar="METRIC=VALUE",
                   help="milestone threshold of psnr2d, ssim2d, psnr3d or ssim3d, repeatable; metrics not given "
                        "keep analysis.milestones of the config schema")


def register(subparsers: argparse._SubParsersAction) -> None:
    g = subparsers.add_parser("gather", help="one row per training run -> summary.csv",
                              description="Collect run folders (results/{volume}/runs/init~.../seed~N) into a "
                                          "summary CSV: axis values, metrics.json, final logged metrics, "
                                          "milestones, convergence velocity, the strongest baseline.")
    g.add_argument("runs", nargs="+", help="run folders, or folders to search for them (e.g. results/)")
    g.add_argument("--out", default="results/summary.csv",
                   help="output .csv, outside the run folders (default: %(default)s)")
    _common(g)
    g.set_defaults(func=run_gather)

    a = subparsers.add_parser("analyse", help="results figures and tables from summary.csv",
                              description="Convergence by ablation axis, velocity, ACF, KDE windows, 2D-3D "
                                          "correlations, milestones, ablation paired plots, Gaussian vs "
                                          "classical reconstructions.")
    a.add_argument("summary", help="summary.csv written by `ctsplat gather`")
    a.add_argument("--out-dir", default="results/figures", help="output folder (default: %(default)s)")
    a.add_argument("--window", type=int, help="centred rolling-mean window (evaluations) " + _default("window"))
    a.add_argument("--acf-max-lag", type=int, help="largest ACF lag (evaluations) " + _default("acf_max_lag"))
    a.add_argument("--kde-windows", type=int, help="training windows of the KDE figure " + _default("kde_windows"))
    _common(a)
    a.set_defaults(func=run_analyse)
