"""``summary.csv``: one row per training run, and all runs' logs in one long table."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from ctsplat.analysis.stats import convergence_velocity, mean_iters_per_s, milestones
from ctsplat.formats.runlog import LOG_COLUMNS, METRICS_2D3D, read_train_log
from ctsplat.grid import GRID_AXES, parse_run_dir
from ctsplat.utils import CtsplatError, atomic_path

__all__ = ["gather", "load_runs"]


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested keys joined with ``.``; lists as JSON text, so each value fits one CSV cell."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{key}."))
        elif isinstance(v, list | tuple):
            out[key] = json.dumps(v)
        else:
            out[key] = v
    return out


def gather(
    run_dirs: Sequence[str | os.PathLike[str]],
    out_csv: str | os.PathLike[str],
    *,
    thresholds: Mapping[str, float] | None = None,
    max_gap_iters: int = 10,
    per_iters: int = 1000,
) -> pd.DataFrame:
    """Write ``summary.csv``: one row per run with every axis value and its final metrics.

    Parameters
    ----------
    run_dirs : sequence of path-like
        Run folders ``.../{volume}/runs/init~.../seed~N``, each with ``metrics.json`` and/or ``train_log.csv``.
    out_csv : path-like
        The CSV to write (atomically).
    thresholds : mapping of str to float, optional
        Milestone thresholds (metric -> value); default the schema's ``analysis.milestones``.
    max_gap_iters : int
        Gap tolerance of :func:`ctsplat.formats.runlog.read_train_log`.
    per_iters : int
        Unit of the convergence velocity (gain per this many iterations).

    Returns
    -------
    pandas.DataFrame
        The table written: ``volume`` + :data:`ctsplat.grid.GRID_AXES` (from the folder names), ``run_dir``, the
        flattened ``metrics.json`` (nested keys joined with ``.``), and from ``train_log.csv`` the last logged
        metrics (``final_*``, ``final_iteration``), the milestones (:func:`ctsplat.analysis.stats.milestones`),
        ``iters_per_s`` and the PSNR2D convergence velocity ``velocity_psnr2d``.

    Raises
    ------
    CtsplatError
        When no run folder is given, a folder is not a run folder, or a run has neither file.
    """
    if thresholds is None:
        from ctsplat.config import schema_defaults

        thresholds = schema_defaults("analysis")["milestones"]
    if not run_dirs:
        raise CtsplatError("gather: no run folders given")
    rows = []
    for rd in run_dirs:
        rd = Path(rd)
        row: dict[str, Any] = {"volume": None, **parse_run_dir(rd), "run_dir": str(rd)}
        metrics_path = rd / "metrics.json"
        if metrics_path.exists():
            with open(metrics_path) as fh:
                metrics = json.load(fh)
            for k, v in _flatten(metrics).items():
                if k not in row:
                    row[k] = v
        log_path = rd / "train_log.csv"
        if log_path.exists():
            log = read_train_log(log_path, max_gap_iters=max_gap_iters)
            for m in METRICS_2D3D:
                finite = log[m].dropna()
                row[f"final_{m}"] = float(finite.iloc[-1]) if len(finite) else None
            row["final_iteration"] = int(log["iteration"].iloc[-1]) if len(log) else None
            row.update(milestones(log, thresholds))
            row["iters_per_s"] = mean_iters_per_s(log)
            row["velocity_psnr2d"] = convergence_velocity(log["iteration"], log["psnr2d"], per_iters)
        if not metrics_path.exists() and not log_path.exists():
            raise CtsplatError(f"gather: {rd} has neither metrics.json nor train_log.csv; did training finish?")
        rows.append(row)
    df = pd.DataFrame(rows)
    with atomic_path(out_csv) as tmp:
        df.to_csv(tmp, index=False, lineterminator="\n")
    return df


def load_runs(summary: pd.DataFrame, *, max_gap_iters: int = 10) -> pd.DataFrame:
    """All runs' training logs in one long table.

    Parameters
    ----------
    summary : pandas.DataFrame
        The table of :func:`gather` (needs ``run_dir``, ``volume`` and the grid axes).
    max_gap_iters : int
        Gap tolerance of :func:`ctsplat.formats.runlog.read_train_log`.

    Returns
    -------
    pandas.DataFrame
        The log rows of every run that has a ``train_log.csv``, each tagged with its run's ``volume``, axis values
        and ``run_dir``.
    """
    frames = []
    for _, r in summary.iterrows():
        log_path = Path(r["run_dir"]) / "train_log.csv"
        if not log_path.exists():
            continue
        log = read_train_log(log_path, max_gap_iters=max_gap_iters)
        for col in ("volume", *GRID_AXES, "run_dir"):
            log[col] = r[col]
        frames.append(log)
    if not frames:
        return pd.DataFrame(columns=[*LOG_COLUMNS, "volume", *GRID_AXES, "run_dir"])
    return pd.concat(frames, ignore_index=True)
