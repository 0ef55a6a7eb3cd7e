"""``summary.csv``: one row per training run, and all runs' logs in one long table."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from ctsplat.analysis.stats import convergence_velocity, mean_iters_per_s, milestones, run_cells
from ctsplat.formats.runlog import LOG_COLUMNS, METRICS_2D3D, PER_VIEW_COLUMNS, read_per_view, read_train_log
from ctsplat.grid import GRID_AXES, cell_needs_sfm, parse_run_dir, run_axes, uses_colmap
from ctsplat.utils import CtsplatError, atomic_path, dotted_items, read_json_object

log = logging.getLogger(__name__)

__all__ = ["TEST_METRICS", "SFM_COLUMNS", "BASELINE_SUMMARY_COLUMNS", "NOT_RUN", "velocity_column",
           "sfm_summary_path", "read_baselines", "gather", "read_summary", "load_runs", "load_per_view"]


# Test-split metrics of metrics.json, renamed so they cannot be mistaken for the validation values of the log.
TEST_METRICS: tuple[str, ...] = ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_r2", "ssim3d_r2", "lpips",
                                 "lpips_reason", "psnr3d_gauge_aligned", "ssim3d_gauge_aligned")
# Pose-error columns of a poses: colmap run: summary.csv column -> key of the volume's sfm/summary.json.
SFM_COLUMNS: dict[str, str] = {
    "sfm_rot_err_deg_median": "rot_err_deg_median",
    "sfm_rot_err_deg_p90": "rot_err_deg_p90",
    "sfm_centre_err_mm_median": "centre_err_mm_median",
    "sfm_centre_err_frac_median": "centre_err_frac_median",
    "sfm_alignment_inlier_rate": "alignment_inlier_rate",
    "sfm_registration_rate": "registration_rate",
    "sfm_ok": "ok",
}


# Per run, the strongest classical reconstruction at the same volume and view count (baselines.csv): the method
# with the highest test 3D PSNR, an upper bound on the classical methods (each tuned on validation views).
# ``best_baseline_geometry`` names the view geometry the classical methods ran on, which a workflow may set apart
# from the Gaussians' (``baselines.geometry``); the run's own is its ``geometry`` column.
BASELINE_SUMMARY_COLUMNS: tuple[str, ...] = ("best_baseline", "best_baseline_test_psnr3d", "best_baseline_test_ssim3d",
                                             "test_psnr3d_minus_best_baseline_db", "best_baseline_geometry")
#: ``status`` of a grid cell that did not train (``not_run_reason`` says why); trained cells have "trained".
NOT_RUN = "not run"


def velocity_column(per_iters: int) -> str:
    """Name of the summary column of the PSNR2D convergence velocity, which carries its unit.

    Parameters
    ----------
    per_iters : int
        The velocity's unit (gain per this many iterations).

    Returns
    -------
    str
        ``velocity_psnr2d_per_{per_iters}it``.
    """
    return f"velocity_psnr2d_per_{per_iters}it"


def sfm_summary_path(run_dir: str | os.PathLike[str]) -> Path | None:
    """The ``sfm/summary.json`` of the volume a run folder belongs to (``{volume}/runs/...`` -> ``{volume}/sfm``).

    Parameters
    ----------
    run_dir : path-like
        A run folder.

    Returns
    -------
    pathlib.Path or None
        The path (which may not exist); None when the folder has no ``runs`` component.
    """
    parts = Path(run_dir).parts
    if "runs" not in parts:
        return None
    i = len(parts) - 1 - parts[::-1].index("runs")
    return Path(*parts[:i], "sfm", "summary.json") if i else Path("sfm", "summary.json")


def _sfm_columns(run_dir: Path) -> dict[str, Any]:
    """Pose errors of the SfM result a ``poses: colmap`` run trained on; ``sfm_ok`` False when there is none."""
    path = sfm_summary_path(run_dir)
    if path is None or not path.exists():
        return {**dict.fromkeys(SFM_COLUMNS), "sfm_ok": False}
    summary = _read_json(path)
    out = {col: summary.get(key) for col, key in SFM_COLUMNS.items()}
    out["sfm_ok"] = bool(summary.get("ok", False))
    return out


def _run_geometry(run_dir: Path) -> str | None:
    """The view geometry a run trained on: the name of its radiographs folder (``.../radiographs/{geometry}``) in
    its ``config.json``; None when the run has no such record."""
    path = run_dir / "config.json"
    if not path.exists():
        return None
    radiographs = (_read_json(path).get("config") or {}).get("radiographs")
    return Path(radiographs).name if radiographs else None


def _not_run_reason(run_dir: Path, row: Mapping[str, Any]) -> str | None:
    """Why a cell that trains on SfM output has no results: its volume's SfM run failed (None otherwise)."""
    if not cell_needs_sfm(row):
        return None
    path = sfm_summary_path(run_dir)
    if path is None:
        return None
    from ctsplat.sfm.step import sfm_failure  # pycolmap loads only when a cell needs SfM

    failure = sfm_failure(path)
    return None if failure is None else f"SfM failed ({path}): {failure}"


#: The columns of ``baselines.csv`` the summary and the figures read (the method, then numbers).
BASELINE_REQUIRED = ("method", "n_views", "psnr3d", "ssim3d")


def read_baselines(paths: Sequence[str | os.PathLike[str]]) -> pd.DataFrame:
    """``baselines.csv`` files in one table, with the volume and the geometry taken from
    ``.../{volume}/baselines/{geometry}/baselines.csv`` when a file has no ``volume`` / ``geometry`` column.

    Parameters
    ----------
    paths : sequence of path-like
        ``baselines.csv`` files of :func:`ctsplat.baselines.run_baselines`.

    Returns
    -------
    pandas.DataFrame
        Their rows (:data:`ctsplat.baselines.BASELINE_COLUMNS` + ``volume``, ``geometry``, ``volume_id`` from the
        ``baselines.json`` beside the file (None without one) and ``baselines_csv``, the file); empty when no path
        is given.

    Raises
    ------
    CtsplatError
        One line naming a file that cannot be read as CSV or lacks the columns the summary and figures use
        (:data:`BASELINE_REQUIRED`).
    """
    frames = []
    for p in paths:
        fix = "give the baselines.csv that `ctsplat baseline` wrote"
        try:
            b = pd.read_csv(p)
        except pd.errors.EmptyDataError:
            raise CtsplatError(f"baselines table {p} is empty; {fix}") from None
        except (OSError, pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise CtsplatError(f"cannot read baselines table {p} ({type(exc).__name__}: "
                               f"{str(exc).splitlines()[0] if str(exc) else 'unreadable'}); {fix}") from None
        missing = [c for c in BASELINE_REQUIRED if c not in b]
        if missing:
            raise CtsplatError(f"{p} is not a baselines table (no {', '.join(missing)} column); {fix}")
        bad = b[list(BASELINE_REQUIRED[1:])].apply(pd.to_numeric, errors="coerce").isna().any(axis=1)
        if bad.any():
            raise CtsplatError(f"{p} row {int(bad.to_numpy().argmax()) + 2} has no number in "
                               f"{'/'.join(BASELINE_REQUIRED[1:])}; {fix}")
        parts = Path(p).parts
        at = parts.index("baselines") if "baselines" in parts[:-1] else None
        if "volume" not in b:
            b["volume"] = parts[at - 1] if at else ""
        if "geometry" not in b:
            b["geometry"] = parts[at + 1] if at is not None and at + 2 < len(parts) else ""
        sidecar = Path(p).with_name("baselines.json")
        b["volume_id"] = _read_json(sidecar).get("volume_id") if sidecar.is_file() else None
        b["baselines_csv"] = str(p)
        frames.append(b)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _same_volume(baselines: pd.DataFrame, run: Mapping[str, Any]) -> pd.Series:
    """Which baseline rows reconstruct the run's volume: the same ``volume_id`` (the content hash) where both
    record one, else the same volume name (the folder above ``baselines/`` and ``runs/``)."""
    vid = run.get("volume_id")
    known = baselines["volume_id"].notna() & isinstance(vid, str)
    return (known & (baselines["volume_id"] == vid)) | (~known & (baselines["volume"] == run.get("volume")))


def _baseline_columns(df: pd.DataFrame, baselines: pd.DataFrame) -> pd.DataFrame:
    """:data:`BASELINE_SUMMARY_COLUMNS` for each row of the summary (empty where no baseline matches)."""
    out = pd.DataFrame(index=df.index, columns=list(BASELINE_SUMMARY_COLUMNS), dtype=object)
    if baselines.empty or "views" not in df:
        return out
    b = baselines.assign(psnr3d=pd.to_numeric(baselines["psnr3d"], errors="coerce")).dropna(subset=["psnr3d"])
    used: set[str] = set()
    for i, r in df.iterrows():
        if pd.isna(r.get("views")):
            continue
        match = b[_same_volume(b, r) & (b["n_views"] == int(r["views"]))]
        if match.empty:
            continue
        used.update(match["baselines_csv"])
        best = match.loc[match["psnr3d"].idxmax()]
        score = pd.to_numeric(pd.Series([r.get("test_psnr3d")]), errors="coerce").iloc[0]
        out.loc[i] = [best["method"], float(best["psnr3d"]), float(best["ssim3d"]),
                      float(score - best["psnr3d"]) if pd.notna(score) else None, best["geometry"] or None]
    for path in dict.fromkeys(baselines["baselines_csv"]):
        if path not in used:
            log.warning("gather: no run matches the baselines in %s (a run matches by its volume_id, recorded in "
                        "baselines.json beside the file, else by the volume folder name, and by its view count); "
                        "they are left out of the summary", path)
    return out


def gather(
    run_dirs: Sequence[str | os.PathLike[str]],
    out_csv: str | os.PathLike[str],
    *,
    thresholds: Mapping[str, float] | None = None,
    max_gap_iters: int = 10,
    per_iters: int = 1000,
    baselines_csvs: Sequence[str | os.PathLike[str]] = (),
) -> pd.DataFrame:
    """Write ``summary.csv``: one row per grid cell with every axis value and its final metrics.

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
    baselines_csvs : sequence of path-like
        ``baselines.csv`` files (:func:`read_baselines`); each run is compared with the strongest classical
        reconstruction at its volume and view count.

    Returns
    -------
    pandas.DataFrame
        The table written, one row per grid cell:

        - ``volume`` + :data:`ctsplat.grid.GRID_AXES` and any feature axes (from the folder names) and ``run_dir``;
        - ``status``: ``trained``, or :data:`NOT_RUN` for a cell that trains on SfM output when its volume's SfM
          run failed, with the reason in ``not_run_reason`` (its metric columns are empty);
        - the held-out test metrics of ``metrics.json`` as ``test_psnr2d``, ``test_ssim2d``, ``test_psnr3d``,
          ``test_ssim3d``, R²-Gaussian's ``test_psnr3d_r2``, ``test_ssim3d_r2`` (empty for runs evaluated before
          they existed), ``test_lpips`` (``test_lpips_reason``), ``test_psnr3d_gauge_aligned`` /
          ``test_ssim3d_gauge_aligned`` (runs not at the true poses), and its other keys flattened (nested keys
          joined with ``.``);
        - from ``train_log.csv`` the last logged validation values ``val_{metric}_last`` and the iteration of the
          last row ``val_iteration_last``, the milestones ``iter_to_{metric}_{tag}`` / ``time_to_{metric}_{tag}_s``
          (:func:`ctsplat.analysis.stats.milestones`, tags from the thresholds), ``iters_per_s`` and the median
          PSNR2D gain per ``per_iters`` iterations (:func:`velocity_column`);
        - for ``poses: colmap`` runs the pose errors of the volume's ``sfm/summary.json`` (:data:`SFM_COLUMNS`;
          ``sfm_ok`` False when that file is missing), empty for the other runs;
        - ``geometry``: the view geometry the run trained on (its radiographs folder's name);
        - :data:`BASELINE_SUMMARY_COLUMNS`: the classical method with the highest test 3D PSNR at the run's volume
          and view count, its test 3D PSNR / SSIM, the run's test 3D PSNR minus it (dB), and the geometry the
          classical methods ran on (which may differ from the run's: ``baselines.geometry``).

    Raises
    ------
    CtsplatError
        When no run folder is given, a folder is not a run folder, or a run has neither file (unless it is a cell
        of a failed SfM run); when ``out_csv`` is an input, lies in a run folder or is a file other than an
        earlier summary; when a baselines table cannot be read (:func:`read_baselines`).
    """
    if thresholds is None:
        from ctsplat.config import schema_defaults

        thresholds = schema_defaults("analysis")["milestones"]
    if not run_dirs:
        raise CtsplatError("gather: no run folders given")
    for rd in run_dirs:  # every folder is a run folder, and the summary goes elsewhere, before any run is read
        parse_run_dir(Path(rd))
    _check_summary_path(out_csv, run_dirs, baselines_csvs)
    baselines = read_baselines(baselines_csvs)
    rows = []
    for rd in run_dirs:
        rd = Path(rd)
        row: dict[str, Any] = {"volume": None, **parse_run_dir(rd), "run_dir": str(rd)}
        metrics_path = rd / "metrics.json"
        log_path = rd / "train_log.csv"
        # a cell of a failed SfM run is not run even when an earlier, successful SfM left its outputs behind
        reason = _not_run_reason(rd, row)
        if reason is not None:
            rows.append({**row, "status": NOT_RUN, "not_run_reason": reason})
            continue
        if not metrics_path.exists() and not log_path.exists():
            raise CtsplatError(f"gather: {rd} has neither metrics.json nor train_log.csv; did training finish?")
        row["status"] = "trained"
        row["geometry"] = _run_geometry(rd)
        if metrics_path.exists():
            metrics = _read_json(metrics_path)
            for m in TEST_METRICS:
                row[f"test_{m}"] = metrics.pop(m, None)
            for k, v in dotted_items(metrics, lists_as_json=True).items():
                # milestones come from the log with this gather's thresholds; pose errors from sfm/summary.json;
                # the evaluation's own settings are the workflow's, the same for every run
                if k not in row and k not in SFM_COLUMNS and not k.startswith(
                        ("iter_to_", "time_to_", "evaluation_settings.", "evaluation_milestones.")):
                    row[k] = v
        if log_path.exists():
            log = read_train_log(log_path, max_gap_iters=max_gap_iters)
            for m in METRICS_2D3D:
                finite = log[m].dropna()
                row[f"val_{m}_last"] = float(finite.iloc[-1]) if len(finite) else None
            row["val_iteration_last"] = int(log["iteration"].iloc[-1]) if len(log) else None
            row.update(milestones(log, thresholds))
            row["iters_per_s"] = mean_iters_per_s(log)
            row[velocity_column(per_iters)] = convergence_velocity(log["iteration"], log["psnr2d"], per_iters)
        rows.append(row)
    df = pd.DataFrame(rows)
    for col in [c for c in df.columns if c.startswith("iter_to_")]:
        df[col] = df[col].astype("Int64")  # iterations, written without ".0" when some run missed the milestone
    colmap = df["poses"].map(uses_colmap)
    if colmap.any():
        sfm = pd.DataFrame([_sfm_columns(Path(r)) if c else dict.fromkeys(SFM_COLUMNS)
                            for r, c in zip(df["run_dir"], colmap, strict=True)], index=df.index)
        df = df.drop(columns=[c for c in SFM_COLUMNS if c in df]).join(sfm)
    df = df.join(_baseline_columns(df, baselines))
    _check_summary_path(out_csv, run_dirs, baselines_csvs)  # again: the file may have appeared meanwhile
    with atomic_path(out_csv) as tmp:
        df.to_csv(tmp, index=False, lineterminator="\n")
    return df


def _check_summary_path(out_csv: str | os.PathLike[str], run_dirs: Sequence[str | os.PathLike[str]],
                        baselines_csvs: Sequence[str | os.PathLike[str]]) -> None:
    """Refuse a summary path that is not a ``.csv``, is one of the baselines files read, or lies in a run folder:
    writing it would replace a run's own file or an input (a folder is :func:`ctsplat.utils.atomic_path`'s to
    name)."""
    out = Path(out_csv)
    if str(out_csv).endswith(("/", os.sep)) or out.is_dir():
        return
    if out.suffix.lower() != ".csv":
        raise CtsplatError(f"gather: the summary {out} must be a .csv file (e.g. {out.with_suffix('.csv').name})")
    target = out.resolve()
    if any(target == Path(b).resolve() for b in baselines_csvs):
        raise CtsplatError(f"gather: the summary {out} is one of the baselines files it reads; write it elsewhere")
    if out.is_file():  # an earlier summary is replaced; any other table is not gather's to replace
        try:
            header = pd.read_csv(out, nrows=0).columns
        except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError):
            header = pd.Index([])
        if not {"run_dir", "volume"} <= set(header):
            raise CtsplatError(f"gather: {out} exists and is not a summary of `ctsplat gather` (no run_dir and "
                               "volume columns), and writing the summary would replace it; write it elsewhere")
    for rd in map(Path, run_dirs):
        if rd.resolve() in target.parents:
            raise CtsplatError(f"gather: the summary {out} lies inside the run folder {rd}; write it elsewhere "
                               f"(e.g. beside the volumes' folders, as the workflow's results/summary.csv)")


def _read_json(path: Path) -> dict[str, Any]:
    """A run's JSON file, or one line naming it when it does not parse."""
    return read_json_object(path, what="run file", fix="the step that wrote it was interrupted or the file was "
                                                       "edited: run that step again")


def read_summary(path: str | os.PathLike[str]) -> pd.DataFrame:
    """Read a ``summary.csv`` written by :func:`gather`, checking that it is one and that its runs are reachable.

    Parameters
    ----------
    path : path-like
        The CSV. Its ``run_dir`` values are as :func:`gather` was given them, relative to the folder it ran in.

    Returns
    -------
    pandas.DataFrame

    Raises
    ------
    CtsplatError
        One line: the file is empty or not a summary (no ``run_dir`` / ``volume`` column), or a trained run's folder
        is not found from here (analyse runs from the folder that gather ran in).
    """
    path = Path(path)
    try:
        summary = pd.read_csv(path)
    except pd.errors.EmptyDataError:
        raise CtsplatError(f"{path} is empty; write it with `ctsplat gather`") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise CtsplatError(f"{path} is not a CSV summary of `ctsplat gather` ({type(exc).__name__}); give the "
                           "summary.csv it wrote") from None
    missing = [c for c in ("run_dir", "volume", *GRID_AXES) if c not in summary]
    if missing:
        raise CtsplatError(f"{path} is not a summary of `ctsplat gather` (no {', '.join(missing)} column)")
    if summary.empty:  # gather refuses to write one without runs: a header alone is a damaged or hand-made file
        raise CtsplatError(f"{path} lists no runs; write it with `ctsplat gather` from the run folders")
    run_cells(summary)  # two runs of one cell: refused before any table or figure is drawn
    trained = summary if "status" not in summary else summary[summary["status"] != NOT_RUN]
    gone = [d for d in trained["run_dir"].astype(str) if not Path(d).is_dir()]
    if gone:
        raise CtsplatError(f"{len(gone)} run folder(s) of {path} not found from {Path.cwd()} (e.g. {gone[0]}); "
                           "run analyse from the folder that gather ran in")
    return summary


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
        for col in ("volume", *run_axes(summary.columns), "run_dir"):
            log[col] = r[col]
        frames.append(log)
    if not frames:
        return pd.DataFrame(columns=[*LOG_COLUMNS, "volume", *GRID_AXES, "run_dir"])
    return pd.concat(frames, ignore_index=True)


def load_per_view(summary: pd.DataFrame, *, split: str | None = "val") -> pd.DataFrame:
    """All runs' per-view evaluations during training (``per_view.csv``) in one long table.

    Parameters
    ----------
    summary : pandas.DataFrame
        The table of :func:`gather` (needs ``run_dir``, ``volume`` and the grid axes).
    split : str, optional
        Keep only this split's views (None: all).

    Returns
    -------
    pandas.DataFrame
        :data:`ctsplat.formats.runlog.PER_VIEW_COLUMNS` of every run that has a ``per_view.csv``, each row tagged
        with its run's ``volume``, axis values and ``run_dir``.
    """
    frames = []
    for _, r in summary.iterrows():
        path = Path(r["run_dir"]) / "per_view.csv"
        if not path.exists():
            continue
        pv = read_per_view(path)
        if split is not None:
            pv = pv[pv["split"] == split]
        for col in ("volume", *run_axes(summary.columns), "run_dir"):
            pv[col] = r[col]
        frames.append(pv)
    if not frames:
        return pd.DataFrame(columns=[*PER_VIEW_COLUMNS, "volume", *GRID_AXES, "run_dir"])
    return pd.concat(frames, ignore_index=True)
