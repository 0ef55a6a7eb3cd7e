"""Figures of the results chapter (matplotlib/seaborn, headless), from the tables of :mod:`ctsplat.analysis`.

Every function takes plain DataFrames, writes one PNG atomically and returns the matplotlib Figure (closed, so
tests can inspect its artists without a display). Per-run figures: :func:`plot_convergence`,
:func:`plot_porkchop`, :func:`plot_acf`, :func:`plot_kde_windows`, all written by :func:`run_figures`. Grid
figures: :func:`plot_convergence_by_axis`, :func:`plot_velocity`, :func:`plot_ablation`, :func:`plot_baselines`,
:func:`plot_correlations`; :func:`analyse` writes all of them plus the milestones and correlations tables.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import seaborn as sns  # noqa: E402

from ctsplat.analysis import ANALYSIS_OUTPUTS  # noqa: E402
from ctsplat.analysis.gather import load_per_view, load_runs, read_baselines, read_summary  # noqa: E402
from ctsplat.analysis.stats import (  # noqa: E402
    CONDITION_AXES,
    METRIC_RANGES,
    acf,
    acf_band,
    bounded_kde,
    condition_labels,
    detrend,
    mean_iters_per_s,
    milestones,
    natural_value,
    paired_table,
    porkchop_table,
    rolling_centered,
    varying_axes,
    velocity_curve,
    window_labels,
    windowed_correlations,
)
from ctsplat.config import schema_defaults  # noqa: E402
from ctsplat.formats.runlog import METRICS_2D3D, read_per_view, read_train_log  # noqa: E402
from ctsplat.grid import ALL_AXES, GRID_AXES  # noqa: E402
from ctsplat.utils import CtsplatError, atomic_path, code_version, write_json_atomic  # noqa: E402

__all__ = [
    "plot_convergence",
    "plot_porkchop",
    "plot_acf",
    "plot_acf_runs",
    "plot_kde_windows",
    "plot_kde_conditions",
    "condition_styles",
    "plot_convergence_by_axis",
    "plot_velocity",
    "plot_ablation",
    "plot_baselines",
    "plot_correlations",
    "correlation_table",
    "run_figures",
    "analyse",
]

METRIC_LABELS = {"psnr2d": "PSNR 2D (dB)", "ssim2d": "SSIM 2D", "psnr3d": "PSNR 3D (dB)", "ssim3d": "SSIM 3D"}
# Colour-bar labels with units (SSIM is a dimensionless index, 1 = identical).
CBAR_LABELS = {"psnr2d": "PSNR 2D (dB)", "ssim2d": "SSIM 2D (unitless, 1 = identical)",
               "psnr3d": "PSNR 3D (dB)", "ssim3d": "SSIM 3D (unitless, 1 = identical)"}


LINESTYLES: tuple[str, ...] = ("-", "--", ":", "-.")
MARKERS: tuple[str, ...] = ("o", "s", "^", "D", "v", "P", "X", "*")


def condition_styles(table: pd.DataFrame, label_col: str = "condition", exclude: Sequence[str] = ("seed",),
                     axes: Sequence[str] = CONDITION_AXES) -> dict[str, dict[str, Any]]:
    """Line style of each condition so every one can be told apart without relying on colour alone.

    The first axis that varies (:func:`ctsplat.analysis.stats.varying_axes`) picks the colour, the second the
    line style, the remaining ones together the marker.

    Parameters
    ----------
    table : pandas.DataFrame
        Rows with the axis columns and ``label_col`` (:func:`ctsplat.analysis.stats.condition_labels`).
    label_col : str
        Column holding each row's condition name.
    exclude : sequence of str
        Axes not used for styling (as for the labels).
    axes : sequence of str
        Candidate axes in order of precedence (the first varying one picks the colour).

    Returns
    -------
    dict
        Condition name -> ``{"color", "linestyle", "marker"}`` (matplotlib keywords), in sorted name order.
    """
    used = varying_axes(table, axes, exclude)
    first = table.drop_duplicates(label_col).sort_values(label_col, key=lambda c: c.map(_natural_key))
    levels = [sorted(table[a].astype(str).unique(), key=natural_value) for a in used]
    palette = sns.color_palette(n_colors=max(len(levels[0]), 1) if levels else 1)
    rest = sorted({tuple(str(r[a]) for a in used[2:]) for _, r in first.iterrows()}, key=str)
    out: dict[str, dict[str, Any]] = {}
    for _, r in first.iterrows():
        colour = palette[levels[0].index(str(r[used[0]]))] if used else palette[0]
        ls = LINESTYLES[levels[1].index(str(r[used[1]])) % len(LINESTYLES)] if len(used) > 1 else "-"
        marker = MARKERS[rest.index(tuple(str(r[a]) for a in used[2:])) % len(MARKERS)] if len(used) > 2 else "o"
        out[str(r[label_col])] = {"color": colour, "linestyle": ls, "marker": marker, "markevery": 0.1}
    seen = [(tuple(st["color"]) if not isinstance(st["color"], str) else st["color"], st["linestyle"], st["marker"])
            for st in out.values()]
    if len(set(seen)) < len(seen):  # more levels than the palette, line styles or markers tell apart: one colour each
        colours = sns.color_palette("husl", n_colors=len(out))
        out = {name: {"color": colours[i], "linestyle": LINESTYLES[i % len(LINESTYLES)],
                      "marker": MARKERS[i % len(MARKERS)], "markevery": 0.1} for i, name in enumerate(out)}
    return out


def _natural_key(label: str) -> tuple:
    """Sort key of a condition name with numbers compared as numbers (views=8 before views=16)."""
    import re

    return tuple(natural_value(p) for p in re.split(r"(\d+(?:\.\d+)?)", str(label)))


def _save(fig: plt.Figure, out: str | os.PathLike[str]) -> plt.Figure:
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return fig


def _empty(ax: plt.Axes, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")
    ax.set_xticks([])
    ax.set_yticks([])


# ----------------------------------------------------------------------------------------------------------------
# Per run
# ----------------------------------------------------------------------------------------------------------------


def plot_convergence(log: pd.DataFrame, out: str | os.PathLike[str], *, window: int = 25,
                     title: str = "") -> plt.Figure:
    """2×2 panels (PSNR2D, SSIM2D, PSNR3D, SSIM3D vs iteration): raw values thin, centred rolling mean thick.

    Parameters
    ----------
    log : pandas.DataFrame
        A training log (:func:`ctsplat.formats.runlog.read_train_log`).
    out : path-like
        PNG file to write.
    window : int
        Rolling-mean window (evaluations).
    title : str
        Figure title (default: a generic one).

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5), sharex=True)
    for ax, m in zip(axes.ravel(), METRICS_2D3D, strict=True):
        sub = log[["iteration", m]].dropna()
        if sub.empty:
            _empty(ax, f"no {m} logged")
            continue
        ax.plot(sub["iteration"], sub[m], lw=0.6, alpha=0.5, color="C0", label="raw")
        ax.plot(sub["iteration"], rolling_centered(sub[m], window), lw=2.2, color="C0",
                label=f"centred mean (W={window})")
        ax.set_ylabel(METRIC_LABELS[m])
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("iteration")
    axes[0, 0].legend(loc="lower right", fontsize=8)
    fig.suptitle(title or "Convergence")
    return _save(fig, out)


def plot_porkchop(per_view: pd.DataFrame, out: str | os.PathLike[str], *, split: str | None = None,
                  title: str = "") -> plt.Figure:
    """Heatmaps of PSNR2D and SSIM2D per view (rows, ordered by azimuth) over iterations (columns).

    Rows are labelled with the view's azimuth in degrees and its id; the colour bars carry the metric's unit.

    Parameters
    ----------
    per_view : pandas.DataFrame
        A per-view log (:func:`ctsplat.formats.runlog.read_per_view`).
    out : path-like
        PNG file to write.
    split : str, optional
        Show only this split's views.
    title : str
        Figure title (default: a generic one).

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, m in zip(axes, ("psnr2d", "ssim2d"), strict=True):
        table = porkchop_table(per_view, m, split=split)
        if table.empty:
            _empty(ax, "no per-view evaluations")
            continue
        sns.heatmap(table, ax=ax, cmap="viridis", cbar_kws={"label": CBAR_LABELS[m]}, yticklabels=True)
        az = per_view.drop_duplicates("view_id").set_index("view_id")["azimuth_deg"]
        ax.set_yticks(np.arange(len(table)) + 0.5)
        ax.set_yticklabels([f"{az[v]:.0f}° (#{v})" for v in table.index], rotation=0,
                           fontsize=max(4, min(8, 400 // len(table))))
        ax.set_xlabel("iteration")
        ax.set_ylabel("view: azimuth (°) and (#view id)" if ax is axes[0] else "")
        ax.set_title(METRIC_LABELS[m])
    fig.suptitle(title or f"Per-view metrics{f' ({split} split)' if split else ''}")
    return _save(fig, out)


def plot_acf(log: pd.DataFrame, out: str | os.PathLike[str], *, max_lag: int = 40, metric: str = "psnr2d",
             window: int = 25, title: str = "") -> plt.Figure:
    """Autocorrelation of a metric's detrended series by lag (in evaluations), with the 95 % white-noise band.

    The curve is detrended first (:func:`ctsplat.analysis.stats.detrend`: residual from the centred rolling mean
    over ``window`` evaluations), since the ACF of a still-converging curve only shows its trend; the raw ACF is
    drawn faintly for comparison. The band is ±1.96/√n with n the number of detrended samples.

    Parameters
    ----------
    log : pandas.DataFrame
        A training log.
    out : path-like
        PNG file to write.
    max_lag : int
        Largest lag (evaluations).
    metric : str
        Log column.
    window : int
        Rolling-mean window of the detrending (evaluations).
    title : str
        Figure title (default: a generic one).

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    fig, ax = plt.subplots(figsize=(7, 4))
    vals = log[metric].dropna().to_numpy() if metric in log else np.array([])
    resid = detrend(vals, "rolling", window)
    r = acf(resid, max_lag)
    if r.size < 2 or not np.isfinite(r[1:]).any():
        _empty(ax, f"too few evaluations to detrend (need more than {2 * (window // 2)})")
    else:
        lags = np.arange(r.size)
        ax.vlines(lags, 0, r, color="C0")
        ax.plot(lags, r, "o", color="C0", ms=3, label=f"detrended (residual from centred mean, W={window})")
        raw = acf(vals, max_lag)
        ax.plot(np.arange(raw.size), raw, "x", color="0.6", ms=3, label="raw curve (trend)")
        band = acf_band(resid.size)
        ax.axhspan(-band, band, color="0.85", zorder=0, label=f"95 % band ±1.96/√n, n={resid.size}")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel("lag (evaluations)")
        ax.set_ylabel(f"ACF of {METRIC_LABELS.get(metric, metric)}")
        ax.legend(fontsize=7)
    ax.set_title(title or "Autocorrelation")
    return _save(fig, out)


def _draw_kde(ax: plt.Axes, values: np.ndarray, metric: str, **style: Any) -> bool:
    """Draw the bounded KDE of ``values`` (False when it has no density: fewer than two distinct values)."""
    lower, upper = METRIC_RANGES.get(metric, (None, None))
    x, dens = bounded_kde(values, lower, upper)
    if not x.size:
        return False
    ax.plot(x, dens, **style)
    return True


def plot_kde_windows(per_view: pd.DataFrame, out: str | os.PathLike[str], *, n_windows: int = 4,
                     split: str | None = "val", title: str = "") -> plt.Figure:
    """KDEs of the per-view PSNR2D and SSIM2D of one run over successive training windows.

    Each window (equal iteration ranges, :func:`ctsplat.analysis.stats.window_labels`) pools the per-view values
    of the evaluations that fall in it; densities are confined to the metric's range
    (:func:`ctsplat.analysis.stats.bounded_kde`, SSIM ≤ 1) and the legend gives each window in iterations.

    Parameters
    ----------
    per_view : pandas.DataFrame
        A per-view log (:func:`ctsplat.formats.runlog.read_per_view`) of one run.
    out : path-like
        PNG file to write.
    n_windows : int
        Number of windows.
    split : str, optional
        Use only this split's views (None: all; falls back to all when the split is absent).
    title : str
        Figure title (default: a generic one).

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    if split is not None and "split" in per_view and (per_view["split"] == split).any():
        per_view = per_view[per_view["split"] == split]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, m in zip(axes, ("psnr2d", "ssim2d"), strict=True):
        sub = per_view[["iteration", m]].dropna() if m in per_view else pd.DataFrame()
        if len(sub) < 2:
            _empty(ax, f"too few per-view {m} values")
            continue
        sub = sub.assign(window=window_labels(sub["iteration"], n_windows))
        order = list(dict.fromkeys(sub.sort_values("iteration")["window"]))
        colours = sns.color_palette("viridis", n_colors=len(order))
        for w, c in zip(order, colours, strict=True):
            vals = sub.loc[sub["window"] == w, m].to_numpy()
            label = f"iterations {w} (n={vals.size})"
            if not _draw_kde(ax, vals, m, color=c, lw=1.8, label=label):
                ax.plot([], [], color=c, label=label + ", no spread")
            ax.plot(vals, np.zeros_like(vals), "|", color=c, ms=8, alpha=0.5)
        ax.set_xlabel(f"per-view {METRIC_LABELS[m]}")
        ax.set_ylabel("density")
        ax.legend(fontsize=7, title="training window", title_fontsize=7)
    fig.suptitle(title or "Per-view metric distributions over training windows")
    return _save(fig, out)


def plot_kde_conditions(per_views: pd.DataFrame, out: str | os.PathLike[str], *, n_windows: int = 4) -> plt.Figure:
    """KDEs of the per-view PSNR2D and SSIM2D at the end of training, one curve per condition.

    A condition is a cell of the grid without its seed (:func:`ctsplat.analysis.stats.condition_labels`): the
    per-view values of its seeds are pooled, never those of runs that differ in another axis. Each run contributes
    the evaluations in the last of ``n_windows`` equal iteration ranges of its training; that window (in
    iterations) is named in the title, or per curve when runs differ in length. Densities are confined to the
    metric's range (SSIM ≤ 1). When the compositor varies, each compositor gets its own column of panels (their
    levels differ by many dB, and one panel of every condition is unreadable); the legend then names the other
    axes, with one style per condition across the columns.

    Parameters
    ----------
    per_views : pandas.DataFrame
        All runs' per-view logs (:func:`ctsplat.analysis.gather.load_per_view`).
    out : path-like
        PNG file to write.
    n_windows : int
        Training is split into this many windows; the last one is shown.

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    if per_views.empty:
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
        for ax in axes:
            _empty(ax, "no per-view evaluations (per_view.csv)")
        return _save(fig, out)
    last = []
    for _, g in per_views.groupby("run_dir", sort=True):
        w = window_labels(g["iteration"], n_windows)
        final = w[int(np.argmax(g["iteration"].to_numpy()))]
        last.append(g[w == final].assign(window=final))
    pv = pd.concat(last, ignore_index=True)
    facets = (sorted(pv["compositor"].astype(str).unique(), key=natural_value)
              if "compositor" in pv and pv["compositor"].nunique() > 1 else [None])
    in_panel = [a for a in CONDITION_AXES if facets == [None] or a != "compositor"]
    pv["condition"] = condition_labels(pv, in_panel)
    styles = condition_styles(pv, axes=in_panel)
    windows = pv.groupby("condition")["window"].agg(lambda w: ", ".join(sorted(set(w))))
    same_window = pv["window"].nunique() == 1
    metric_names = ("psnr2d", "ssim2d")
    if facets == [None]:
        fig, grid = plt.subplots(1, 2, figsize=(12, 4.5), squeeze=False)
        panels = [(grid[0, k], m, None) for k, m in enumerate(metric_names)]
    else:
        fig, grid = plt.subplots(2, len(facets), figsize=(4.6 * len(facets) + 3.0, 7.5), squeeze=False)
        panels = [(grid[r, c], m, f) for r, m in enumerate(metric_names) for c, f in enumerate(facets)]
    for ax, m, facet in panels:
        sub = pv if facet is None else pv[pv["compositor"].astype(str) == facet]
        for cond, st in styles.items():
            vals = sub.loc[sub["condition"] == cond, m].dropna().to_numpy()
            if facet is not None and not vals.size:
                continue
            label = cond if same_window else f"{cond} (it {windows[cond]})"
            if not _draw_kde(ax, vals, m, lw=1.6, label=label, **st):
                ax.plot([], [], label=label + ", no spread", **st)
        ax.set_xlabel(f"per-view {METRIC_LABELS[m]}")
        ax.set_ylabel("density")
        if facet is not None:
            ax.set_title(f"compositor={facet}", fontsize=9)
    handles: dict[str, Any] = {}
    for ax, _, _ in panels:
        for h, lb in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lb, h)
    order = sorted(handles, key=_natural_key)
    grid[0, -1].legend([handles[k] for k in order], order, fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0),
                       handlelength=3.5)
    when = f"iterations {pv['window'].iloc[0]}" if same_window else f"the last 1/{n_windows} of each run"
    fig.suptitle(f"Per-view validation metrics by condition, {when} (seeds pooled)")
    if facets != [None]:
        fig.tight_layout()
    return _save(fig, out)


def run_figures(run_dir: str | os.PathLike[str], outputs: Mapping[str, str | os.PathLike[str]],
                analysis: Mapping[str, Any] | None = None) -> None:
    """All per-run figures of one run folder.

    Parameters
    ----------
    run_dir : path-like
        The run folder, with ``train_log.csv`` and ``per_view.csv``.
    outputs : mapping of str to path-like
        Figure name (in :data:`ctsplat.analysis.RUN_FIGURES`) -> PNG path; only these are written.
    analysis : mapping, optional
        The workflow config's ``analysis`` section (the keys of :data:`ctsplat.analysis.RUN_FIGURE_KEYS` are
        read); missing keys take the schema defaults.
    """
    cfg = {**schema_defaults("analysis"), **(analysis or {})}
    run_dir = Path(run_dir)
    log = read_train_log(run_dir / "train_log.csv", max_gap_iters=cfg["max_gap_iters"])
    title = str(run_dir)
    if "convergence" in outputs:
        plot_convergence(log, outputs["convergence"], window=cfg["window"], title=title)
    if "porkchop" in outputs:
        per_view = read_per_view(run_dir / "per_view.csv")
        split = "val" if (per_view["split"] == "val").any() else None
        plot_porkchop(per_view, outputs["porkchop"], split=split, title=title)
    if "acf" in outputs:
        plot_acf(log, outputs["acf"], max_lag=cfg["acf_max_lag"], window=cfg["window"], title=title)
    if "kde" in outputs:
        plot_kde_windows(read_per_view(run_dir / "per_view.csv"), outputs["kde"], n_windows=cfg["kde_windows"],
                         title=title)


# ----------------------------------------------------------------------------------------------------------------
# Across runs
# ----------------------------------------------------------------------------------------------------------------


def _run_label(df: pd.DataFrame) -> pd.Series:
    return df["volume"].astype(str) + "/" + df[[a for a in ALL_AXES if a in df]].astype(str).agg("/".join, axis=1)


def plot_convergence_by_axis(logs: pd.DataFrame, axis: str, out: str | os.PathLike[str], *,
                             window: int = 25) -> plt.Figure:
    """All runs' PSNR2D/SSIM2D/PSNR3D/SSIM3D centred rolling means overlaid, coloured by one ablation axis.

    The colour is the value of ``axis``; runs that share it differ in line style and marker by the other axes
    that vary (:func:`condition_styles`), and the legend names every run by those axes ("init=fbp, views=24").

    Parameters
    ----------
    logs : pandas.DataFrame
        All runs' logs (:func:`ctsplat.analysis.gather.load_runs`).
    axis : str
        A grid axis (:data:`ctsplat.grid.GRID_AXES`).
    out : path-like
        PNG file to write.
    window : int
        Rolling-mean window (evaluations).

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    fig, axes = plt.subplots(2, 2, figsize=(13, 7), sharex=True)
    if logs.empty:
        for ax in axes.ravel():
            _empty(ax, "no training logs")
        return _save(fig, out)
    # the colour axis first, so it is the one that picks the colour
    order = (axis, *[a for a in CONDITION_AXES if a != axis])
    used = varying_axes(logs, order, exclude=())
    logs = logs.assign(run=condition_labels(logs, order, exclude=()))
    styles = condition_styles(logs, "run", exclude=(), axes=order)
    for ax, m in zip(axes.ravel(), METRICS_2D3D, strict=True):
        for run, st in styles.items():
            sub = logs.loc[logs["run"] == run, ["iteration", m]].dropna()
            if sub.empty:
                continue
            ax.plot(sub["iteration"], rolling_centered(sub[m], window), lw=1.6, alpha=0.9, label=run, ms=4, **st)
        ax.set_ylabel(METRIC_LABELS[m])
        ax.grid(alpha=0.3)
    axes[0, 1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), handlelength=3.5)
    for ax in axes[1]:
        ax.set_xlabel("iteration")
    note = "" if axis in used else f" ({axis} has one value here)"
    fig.suptitle(f"Convergence coloured by {axis}{note} (centred mean, W={window} evaluations)")
    return _save(fig, out)


def plot_velocity(logs: pd.DataFrame, out: str | os.PathLike[str], *, per_iters: int = 1000) -> plt.Figure:
    """Convergence velocity (median PSNR2D gain per ``per_iters`` iterations) over training, one line per run.

    Runs are named by the axes that differ across them ("init=fbp, views=24") and styled so each can be told
    apart (:func:`condition_styles`).

    Parameters
    ----------
    logs : pandas.DataFrame
        All runs' logs (:func:`ctsplat.analysis.gather.load_runs`).
    out : path-like
        PNG file to write.
    per_iters : int
        Block length and velocity unit (iterations).

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    fig, ax = plt.subplots(figsize=(9, 4.5))
    drawn = 0
    if not logs.empty:
        logs = logs.assign(run=condition_labels(logs, CONDITION_AXES, exclude=()))
        for run, st in condition_styles(logs, "run", exclude=()).items():
            g = logs[logs["run"] == run]
            vc = velocity_curve(g["iteration"], g["psnr2d"], per_iters)
            if len(vc):
                ax.plot(vc["iteration"], vc["velocity"], ms=4, label=run, **{**st, "markevery": 1})
                drawn += 1
    if drawn:
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(f"iteration (centre of each {per_iters}-iteration block)")
        ax.set_ylabel(f"median PSNR2D gain (dB per {per_iters} it)")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), handlelength=3.5)
        ax.grid(alpha=0.3)
    else:
        _empty(ax, "not enough evaluations")
    ax.set_title("Convergence velocity")
    return _save(fig, out)


def correlation_table(logs: pd.DataFrame, n_windows: int) -> pd.DataFrame:
    """Per-run 2D-3D correlations, over the whole run and per training window, of all runs.

    Parameters
    ----------
    logs : pandas.DataFrame
        All runs' logs (:func:`ctsplat.analysis.gather.load_runs`).
    n_windows : int
        Training windows per run (:func:`ctsplat.analysis.stats.windowed_correlations`).

    Returns
    -------
    pandas.DataFrame
        ``run_dir``, ``run`` (named by the axes that differ), ``volume`` and the grid axes, then the columns of
        :func:`ctsplat.analysis.stats.windowed_correlations`. No pooled row: runs are not exchangeable samples.
    """
    axes = [a for a in CONDITION_AXES if a in logs]
    cols = ["run_dir", "run", *axes, "window", "it_start", "it_end", "it_centre", "x", "y", "n", "pearson",
            "spearman"]
    if logs.empty:
        return pd.DataFrame(columns=cols)
    logs = logs.assign(run=condition_labels(logs, CONDITION_AXES, exclude=()))
    frames = [windowed_correlations(g, n_windows).assign(run_dir=rd, run=g["run"].iloc[0],
                                                         **{a: g[a].iloc[0] for a in axes})
              for rd, g in logs.groupby("run_dir", sort=True)]
    return pd.concat(frames, ignore_index=True)[cols]


def plot_correlations(logs: pd.DataFrame, out: str | os.PathLike[str], *, n_windows: int = 4) -> plt.Figure:
    """How well the 2D metric tracks the 3D one over training: per-run Spearman correlation per training window.

    One line per run (named by the axes that differ), x = the window's centre iteration, y = the Spearman
    correlation of the run's 2D and 3D metric within that window; the legend gives each run's correlation over its
    whole training. Nothing is pooled across runs.

    Parameters
    ----------
    logs : pandas.DataFrame
        All runs' logs (:func:`ctsplat.analysis.gather.load_runs`).
    out : path-like
        PNG file to write.
    n_windows : int
        Training windows per run.

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), sharey=True)
    table = correlation_table(logs, n_windows)
    styles = condition_styles(table, "run", exclude=()) if not table.empty else {}
    for ax, (x, y) in zip(axes, (("psnr2d", "psnr3d"), ("ssim2d", "ssim3d")), strict=True):
        sub = table[(table["x"] == x) & (table["y"] == y)]
        drawn = 0
        for run, st in styles.items():
            g = sub[sub["run"] == run]
            whole = g[g["window"] == "all"]["spearman"]
            win = g[g["window"] != "all"]
            if not np.isfinite(win["spearman"].to_numpy(dtype=float)).any():
                continue
            rho = float(whole.iloc[0]) if len(whole) else float("nan")
            ax.plot(win["it_centre"], win["spearman"], label=f"{run} (whole run ρ={rho:.2f})",
                    **{**st, "markevery": 1})
            drawn += 1
        if not drawn:
            _empty(ax, "too few paired 2D/3D evaluations per window")
            continue
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylim(-1.05, 1.05)
        ax.set_xlabel("iteration (centre of the training window)")
        ax.set_title(f"{METRIC_LABELS[x]} vs {METRIC_LABELS[y]}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("Spearman ρ within the window")
    fig.suptitle(f"2D-3D correlation per run over training ({n_windows} equal windows per run)")
    return _save(fig, out)


def _metric_columns(summary: pd.DataFrame) -> list[str]:
    """The summary's test metrics (``test_*``), else the last logged validation ones (``val_*_last``)."""
    cols = [f"test_{m}" for m in ("psnr3d", "ssim3d", "psnr2d", "ssim2d")
            if f"test_{m}" in summary and pd.to_numeric(summary[f"test_{m}"], errors="coerce").notna().any()]
    return cols or [f"val_{m}_last" for m in METRICS_2D3D if f"val_{m}_last" in summary]


def _bare_metric(col: str) -> str:
    """``test_psnr3d`` / ``val_psnr3d_last`` -> ``psnr3d``."""
    return col.removeprefix("test_").removeprefix("val_").removesuffix("_last")


def _level_label(axis: str, value: Any) -> str:
    """A grid axis value as a tick label; inits that read the reference volume say so."""
    from ctsplat.training.config import REFERENCE_INITS

    return f"{value}\n(reads the reference)" if axis == "init" and value in REFERENCE_INITS else str(value)


def plot_ablation(summary: pd.DataFrame, out: str | os.PathLike[str]) -> plt.Figure:
    """Paired comparisons: each line is one cell of the grid with one axis changed (metrics × axes panels).

    For each axis that varies (the seed excepted) the runs identical in every other axis are joined by a line
    across the axis's values, so the effect of the axis is read from the slopes, not from box plots of a few
    points; the panel title gives the number of pairs and the median change between the first and last value.

    Parameters
    ----------
    summary : pandas.DataFrame
        The table of :func:`ctsplat.analysis.gather.gather` (``test_*`` metrics of ``metrics.json``, else the
        last logged ``val_*_last``).
    out : path-like
        PNG file to write.

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    metric_cols = _metric_columns(summary)
    axes_used = varying_axes(summary, ALL_AXES) or list(GRID_AXES[:1])
    metric_cols = metric_cols or ["test_psnr3d"]
    fig, axs = plt.subplots(len(metric_cols), len(axes_used), figsize=(3.4 * len(axes_used) + 1,
                                                                       2.9 * len(metric_cols)), squeeze=False)
    for i, col in enumerate(metric_cols):
        m = _bare_metric(col)
        for j, axis in enumerate(axes_used):
            ax = axs[i, j]
            wide = paired_table(summary, axis, col) if col in summary else pd.DataFrame()
            if wide.empty:
                _empty(ax, f"no runs differing only in {axis}")
                continue
            x = np.arange(len(wide.columns))
            # lines of different compositors sit at very different levels: colour them so pairs are told apart
            by = ("compositor" if axis != "compositor" and "compositor" in wide.index.names
                  and wide.index.get_level_values("compositor").nunique() > 1 else None)
            colours = ({v: f"C{k}" for k, v in enumerate(sorted(set(wide.index.get_level_values(by))))}
                       if by else {})
            for idx, row in wide.iterrows():
                ok = row.notna().to_numpy()
                key = dict(zip(wide.index.names, idx if isinstance(idx, tuple) else (idx,), strict=True)).get(by)
                ax.plot(x[ok], row.to_numpy(dtype=float)[ok], "-o", color=colours.get(key, "0.45"), lw=1, ms=4,
                        alpha=0.8, label=f"compositor={key}" if by else None)
            med = wide.median(axis=0)
            ax.plot(x, med.to_numpy(dtype=float), "-D", color="k", lw=2.2, ms=6, label="median", zorder=5)
            if by and i == 0:
                handles, labels = ax.get_legend_handles_labels()
                seen = dict(zip(labels, handles, strict=True))
                ax.legend(seen.values(), seen.keys(), fontsize=6, loc="best")
            ax.set_xticks(x, [_level_label(axis, c) for c in wide.columns])
            first, last = wide.columns[0], wide.columns[-1]
            diff = wide[last] - wide[first]
            unit = " dB" if m.startswith("psnr") else ""
            ax.set_title(f"{int(diff.notna().sum())} pairs; median {last}−{first}: {diff.median():+.3g}{unit}",
                         fontsize=8)
            ax.set_xlabel(axis if i == len(metric_cols) - 1 else "")
            ax.set_ylabel(f"test {METRIC_LABELS.get(m, m)}" if col.startswith("test_") else
                          f"last validation {METRIC_LABELS.get(m, m)}")
            ax.grid(alpha=0.3)
    fig.suptitle("Paired ablation: each thin line is one grid cell with only that axis changed (coloured by "
                 "compositor where it varies); black: the median")
    fig.tight_layout()
    return _save(fig, out)


def _baseline_label(baselines: pd.DataFrame) -> pd.Series:
    """Each classical row's label: its method, and its volume when ``baselines`` holds several (a method's scores
    on different volumes are different lines, never one maximum over volumes)."""
    label = baselines["method"].astype(str)
    if "volume" in baselines and baselines["volume"].nunique() > 1:
        label = label + ", volume=" + baselines["volume"].astype(str)
    return label


def plot_baselines(summary: pd.DataFrame, baselines: pd.DataFrame, out: str | os.PathLike[str], *,
                   metric: str = "psnr3d") -> plt.Figure:
    """Gaussian runs vs classical reconstructions per number of training views.

    3D metric; a Gaussian condition is the mean over seeds, drawn with its points.

    Parameters
    ----------
    summary : pandas.DataFrame
        The table of :func:`ctsplat.analysis.gather.gather`; runs are grouped by (init, compositor, mip, poses).
    baselines : pandas.DataFrame
        Columns ``method, n_views, psnr3d, ssim3d`` (+ ``volume``) of ``baselines.csv``: one row per method and
        view count, its settings chosen on validation views; one line per method.
    out : path-like
        PNG file to write.
    metric : str
        ``psnr3d`` or ``ssim3d``.

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    col = f"test_{metric}" if f"test_{metric}" in summary else f"val_{metric}_last"
    views = set()
    if col in summary:
        views |= set(summary.loc[pd.to_numeric(summary[col], errors="coerce").notna(), "views"].astype(int))
    if not baselines.empty and "n_views" in baselines:
        views |= set(baselines["n_views"].astype(int))
    if len(views) == 1:
        return _plot_baseline_bars(summary, baselines, out, col=col, metric=metric, views=views.pop())
    fig, ax = plt.subplots(figsize=(8, 5))
    drawn = False
    if not baselines.empty and metric in baselines:
        b = baselines.copy()
        # one line per method (and volume): its settings (filter, iterations, weights) were chosen on validation views
        b["label"] = _baseline_label(b)
        # classical methods in greys with their own markers, so they never share a colour with a Gaussian run
        labels = sorted(b["label"].unique())
        greys = np.linspace(0.0, 0.6, max(len(labels), 1))
        for k, label in enumerate(labels):
            g = b[b["label"] == label].groupby("n_views", as_index=False)[metric].max()
            ax.plot(g["n_views"], g[metric], linestyle=LINESTYLES[1 + k % 3], marker=MARKERS[1 + k % 7],
                    color=str(greys[k]), label=label, lw=1.2)
            drawn = True
    s = (summary.assign(score=pd.to_numeric(summary[col], errors="coerce")).dropna(subset=["score"])
         if col in summary else summary.iloc[:0])
    if len(s):
        cond_axes = [a for a in ("volume", *ALL_AXES) if a not in ("views", "seed") and a in s]
        named = varying_axes(s, cond_axes) or [a for a in cond_axes if a != "volume"]
        from ctsplat.training.config import REFERENCE_INITS

        reads = s["init"].isin(REFERENCE_INITS) if "init" in s else pd.Series(False, index=s.index)
        s = s.assign(condition="Gaussian, " + s[named].astype(str).apply(
            lambda r: ", ".join(f"{a}={r[a]}" for a in named), axis=1) + reads.map({True: " [reads reference]",
                                                                                     False: ""}))
        for cond, st in condition_styles(s, "condition", axes=cond_axes).items():
            g = s[s["condition"] == cond]
            mean = g.groupby("views", as_index=False)["score"].mean()
            ax.plot(mean["views"], mean["score"], lw=2, ms=6, label=cond, **{**st, "markevery": 1})
            ax.scatter(g["views"], g["score"], color=st["color"], s=12, alpha=0.6)
            drawn = True
    if drawn:
        ax.set_xlabel("number of training views")
        ax.set_ylabel(_score_label(col, metric))
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), handlelength=3.5)
        ax.grid(alpha=0.3)
    else:
        _empty(ax, "no Gaussian runs or baselines")
    ax.set_title("Gaussian model vs classical reconstructions per view count")
    return _save(fig, out)


def _score_label(col: str, metric: str) -> str:
    """The axis label of the Gaussians' score column: test values, or the last validation values where the summary
    has no test metrics (the classical methods' values beside them are test values)."""
    name = METRIC_LABELS.get(metric, metric)
    return f"test {name}" if col.startswith("test_") else f"Gaussians: last validation {name}; classical: test {name}"


def _plot_baseline_bars(summary: pd.DataFrame, baselines: pd.DataFrame, out: str | os.PathLike[str], *, col: str,
                        metric: str, views: int) -> plt.Figure:
    """One view count: every Gaussian run and classical method as a bar, best first (see :func:`plot_baselines`)."""
    from ctsplat.training.config import REFERENCE_INITS

    bars: list[tuple[str, float, str]] = []  # (label, score, colour)
    if not baselines.empty and metric in baselines:
        for label, g in baselines.groupby(_baseline_label(baselines)):
            bars.append((f"{label} (classical)", float(pd.to_numeric(g[metric], errors="coerce").max()), "0.55"))
    if col in summary and len(summary):
        s = summary.assign(score=pd.to_numeric(summary[col], errors="coerce")).dropna(subset=["score"])
        cond_axes = [a for a in ("volume", *ALL_AXES) if a not in ("views", "seed") and a in s]
        named = varying_axes(s, cond_axes) or [a for a in cond_axes if a != "volume"]
        for _, g in s.groupby(named, sort=False):
            r = g.iloc[0]
            label = ", ".join(f"{a}={r[a]}" for a in named)
            ref = r.get("init") in REFERENCE_INITS
            bars.append((label + (" [reads reference]" if ref else ""), float(g["score"].mean()),
                         "C1" if ref else ("C0" if r.get("compositor") == "radiative" else "C2")))
    fig, ax = plt.subplots(figsize=(8, 0.28 * max(len(bars), 4) + 1.4))
    if not bars:
        _empty(ax, "no Gaussian runs or baselines")
    else:
        bars.sort(key=lambda b: b[1])
        y = np.arange(len(bars))
        ax.barh(y, [b[1] for b in bars], color=[b[2] for b in bars])
        ax.set_yticks(y, [b[0] for b in bars], fontsize=7)
        lo = min(b[1] for b in bars)
        ax.set_xlim(lo - 2.0 if metric.startswith("psnr") else max(0.0, lo - 0.1), None)
        for yi, b in zip(y, bars, strict=True):
            ax.text(b[1], yi, f" {b[1]:.2f}", va="center", fontsize=7)
        ax.set_xlabel(_score_label(col, metric))
        ax.grid(alpha=0.3, axis="x")
    ax.set_title(f"Gaussian runs vs classical reconstructions, {views} training views\n(grey: classical, settings "
                 "chosen on validation views; blue: rectified radiative; green: other compositors; orange: seeded "
                 "from the reference)", fontsize=8)
    fig.tight_layout()
    return _save(fig, out)


def analyse(summary_csv: str | os.PathLike[str], outputs: Mapping[str, str | os.PathLike[str]], *,
            baselines_csvs: Sequence[str | os.PathLike[str]] = (), analysis: Mapping[str, Any] | None = None) -> None:
    """Write the grid-level figures and tables from ``summary.csv``.

    Parameters
    ----------
    summary_csv : path-like
        The table of :func:`ctsplat.analysis.gather.gather`.
    outputs : mapping of str to path-like
        Output name (a key of :data:`ctsplat.analysis.ANALYSIS_OUTPUTS`) -> file; only these are written.
    baselines_csvs : sequence of path-like
        ``baselines.csv`` files, concatenated; the volume is taken from ``results/{volume}/baselines/...`` when a
        CSV has no ``volume`` column.
    analysis : mapping, optional
        The workflow config's ``analysis`` section; missing keys take the schema defaults.

    Raises
    ------
    CtsplatError
        For an output name that is not in :data:`ctsplat.analysis.ANALYSIS_OUTPUTS`.
    """
    cfg = {**schema_defaults("analysis"), **(analysis or {})}
    unknown = sorted(set(outputs) - set(ANALYSIS_OUTPUTS))
    if unknown:
        raise CtsplatError(f"unknown analysis output {unknown[0]!r}; known: {', '.join(ANALYSIS_OUTPUTS)}")
    summary = read_summary(summary_csv)
    baselines = read_baselines(baselines_csvs)  # every input is read before the first output is written
    logs = load_runs(summary, max_gap_iters=cfg["max_gap_iters"])
    per_view = load_per_view(summary) if "kde" in outputs else None
    if "provenance" in outputs:  # first: what the outputs are made from, and it marks the folder as analyse's
        write_json_atomic(outputs["provenance"], analysis_provenance(summary_csv, summary, cfg, baselines_csvs))
    for a in GRID_AXES:
        key = f"convergence_by_{a}"
        if key in outputs:
            plot_convergence_by_axis(logs, a, outputs[key], window=cfg["window"])
    if "velocity" in outputs:
        plot_velocity(logs, outputs["velocity"], per_iters=cfg["velocity_per_iters"])
    if "acf" in outputs:
        plot_acf_runs(logs, outputs["acf"], max_lag=cfg["acf_max_lag"], window=cfg["window"])
    if "kde" in outputs:
        plot_kde_conditions(per_view, outputs["kde"], n_windows=cfg["kde_windows"])
    if "correlations_plot" in outputs:
        plot_correlations(logs, outputs["correlations_plot"], n_windows=cfg["kde_windows"])
    if "correlations" in outputs:
        _write_csv(correlation_table(logs, cfg["kde_windows"]), outputs["correlations"])
    if "milestones" in outputs:
        rows = []
        for run, g in logs.groupby("run_dir", sort=True) if not logs.empty else []:
            rows.append({"run_dir": run, **{a: g[a].iloc[0] for a in ("volume", *ALL_AXES) if a in g},
                         **milestones(g, cfg["milestones"]), "iters_per_s": mean_iters_per_s(g)})
        keys = list(milestones(pd.DataFrame(), cfg["milestones"]))
        table = pd.DataFrame(rows, columns=None if rows else ["run_dir", "volume", *keys, "iters_per_s"])
        for col in [c for c in keys if c.startswith("iter_to_")]:
            table[col] = table[col].astype("Int64")
        _write_csv(table, outputs["milestones"])
    if "ablation" in outputs:
        plot_ablation(summary, outputs["ablation"])
    if "claims" in outputs:
        from ctsplat.analysis.claims import claims_table

        _write_csv(claims_table(summary), outputs["claims"])
    if "baselines" in outputs:
        plot_baselines(summary, baselines, outputs["baselines"])


def analysis_provenance(summary_csv: str | os.PathLike[str], summary: pd.DataFrame, analysis: Mapping[str, Any],
                        baselines_csvs: Sequence[str | os.PathLike[str]] = ()) -> dict[str, Any]:
    """What the grid-level figures and tables were made from, and with which code and settings.

    Parameters
    ----------
    summary_csv : path-like
        The summary the figures read.
    summary : DataFrame
        Its contents.
    analysis : mapping
        The ``analysis`` settings used (defaults filled).
    baselines_csvs : sequence of path-like
        The baseline tables read.

    Returns
    -------
    dict
        ``code_version`` (of the analysis), ``analysis`` (settings), ``summary`` (path and SHA-256), the runs'
        ``run_code_versions`` and ``run_config_hashes`` (distinct values), ``n_runs`` and ``baselines`` (paths).
    """
    import hashlib

    def distinct(col: str) -> list[str]:
        return sorted({str(v) for v in summary[col].dropna()}) if col in summary else []

    return {
        "code_version": code_version(),
        "analysis": dict(analysis),
        "summary": {"path": str(summary_csv), "sha256": hashlib.sha256(Path(summary_csv).read_bytes()).hexdigest()},
        "n_runs": int(len(summary)),
        "run_code_versions": distinct("code_version"),
        "run_config_hashes": distinct("config_hash"),
        "baselines": [str(b) for b in baselines_csvs],
    }


def plot_acf_runs(logs: pd.DataFrame, out: str | os.PathLike[str], *, max_lag: int = 40,
                  window: int = 25) -> plt.Figure:
    """ACF of each run's detrended PSNR2D by lag, one line per run, with the 95 % white-noise band.

    Detrending as in :func:`plot_acf`; the band is drawn for the run with the fewest detrended samples (the
    widest). Runs are named by the axes that differ (:func:`ctsplat.analysis.stats.condition_labels`).

    Parameters
    ----------
    logs : pandas.DataFrame
        All runs' logs (:func:`ctsplat.analysis.gather.load_runs`).
    out : path-like
        PNG file to write.
    max_lag : int
        Largest lag (evaluations).
    window : int
        Rolling-mean window of the detrending (evaluations).

    Returns
    -------
    matplotlib.figure.Figure
        The figure written to ``out`` (closed).
    """
    fig, ax = plt.subplots(figsize=(9, 4.5))
    drawn, n_min = 0, None
    if not logs.empty:
        logs = logs.assign(run=condition_labels(logs, CONDITION_AXES, exclude=()))
        styles = condition_styles(logs, "run", exclude=())
        for run, st in styles.items():
            resid = detrend(logs.loc[logs["run"] == run, "psnr2d"].to_numpy(), "rolling", window)
            r = acf(resid, max_lag)
            if r.size >= 2 and np.isfinite(r[1:]).any():
                ax.plot(np.arange(r.size), r, ms=3, label=run, **{**st, "markevery": 1})
                drawn += 1
                n_min = resid.size if n_min is None else min(n_min, resid.size)
    if drawn:
        band = acf_band(n_min)
        ax.axhspan(-band, band, color="0.85", zorder=0, label=f"95 % band ±1.96/√n, n={n_min}")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel("lag (evaluations)")
        ax.set_ylabel("ACF of detrended PSNR2D")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), handlelength=3.5)
    else:
        _empty(ax, f"too few evaluations to detrend (need more than {2 * (window // 2)})")
    ax.set_title(f"Autocorrelation of PSNR2D after removing the trend (centred mean, W={window})")
    return _save(fig, out)


def _write_csv(df: pd.DataFrame, out: str | os.PathLike[str]) -> None:
    with atomic_path(out) as tmp:
        df.to_csv(tmp, index=False, lineterminator="\n")
