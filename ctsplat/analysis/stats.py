"""Statistics of training logs: centred rolling means, autocorrelation, convergence velocity, milestones,
2D-vs-3D correlations and per-view tables.

Plain functions over arrays and pandas tables of the run logs (:mod:`ctsplat.formats.runlog`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from ctsplat.grid import ALL_AXES
from ctsplat.utils import CtsplatError

__all__ = [
    "rolling_centered",
    "acf",
    "detrend",
    "acf_band",
    "convergence_velocity",
    "velocity_curve",
    "threshold_tag",
    "milestones",
    "mean_iters_per_s",
    "correlations",
    "window_labels",
    "windowed_correlations",
    "porkchop_table",
    "METRIC_RANGES",
    "bounded_kde",
    "varying_axes",
    "condition_labels",
    "CONDITION_AXES",
    "natural_value",
    "paired_table",
]

# Columns that name a run's condition, in naming order (the seed is a replicate, not a condition).
CONDITION_AXES: tuple[str, ...] = ("volume", *ALL_AXES)
#: An optional axis's value in the run tables of runs whose grid did not have it.
ABSENT = "(absent)"

# Range of each metric: PSNR is unbounded (negative when the error exceeds the data range, as for unrectified runs);
# SSIM lies in [-1, 1]. Densities are confined to it.
METRIC_RANGES: dict[str, tuple[float | None, float | None]] = {
    "psnr2d": (None, None), "psnr3d": (None, None), "ssim2d": (-1.0, 1.0), "ssim3d": (-1.0, 1.0)}


def rolling_centered(values: Sequence[float] | pd.Series, window: int) -> np.ndarray:
    """Centred rolling mean over ``window`` samples, NaN-aware, shrinking at the ends.

    ``out[i] = mean(x[i - (window-1)//2 - (window+1)%2 ... i + (window-1)//2])`` (pandas ``center=True``),
    ignoring NaNs; the first/last samples average over the part of the window that exists.

    Parameters
    ----------
    values : sequence of float, shape (n,)
    window : int
        Window length in samples, >= 1.

    Returns
    -------
    numpy.ndarray, shape (n,)
    """
    if window < 1:
        raise CtsplatError(f"rolling window must be >= 1, got {window}")
    s = pd.Series(np.asarray(values, dtype=float))
    return s.rolling(window, center=True, min_periods=1).mean().to_numpy()


def acf(values: Sequence[float], max_lag: int) -> np.ndarray:
    r"""Sample autocorrelation function, lags 0..max_lag (NaNs dropped first).

    .. math:: r_k = \frac{\sum_{t=0}^{n-k-1} (x_t - \bar x)(x_{t+k} - \bar x)}{\sum_{t=0}^{n-1} (x_t - \bar x)^2}

    (the standard biased estimator, as in ``statsmodels.tsa.stattools.acf``). For an AR(1) process
    ``x_t = φ x_{t-1} + ε_t`` the expectation is ``r_k ≈ φ^k``.

    Parameters
    ----------
    values : sequence of float, shape (n,)
    max_lag : int
        Largest lag (in samples).

    Returns
    -------
    numpy.ndarray, shape (min(max_lag, n-1) + 1,)
        ``r_0 = 1``; a constant series gives NaN for k >= 1.
    """
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    n = x.size
    if n < 2:
        return np.array([1.0]) if n == 1 else np.array([])
    x = x - x.mean()
    denom = float(np.dot(x, x))
    lags = min(max_lag, n - 1)
    if denom == 0.0:
        return np.concatenate([[1.0], np.full(lags, np.nan)])
    return np.array([1.0] + [float(np.dot(x[: n - k], x[k:])) / denom for k in range(1, lags + 1)])


def detrend(values: Sequence[float], method: str = "rolling", window: int = 25) -> np.ndarray:
    """Remove the trend of a training curve so its autocorrelation measures the evaluation noise, not convergence.

    Parameters
    ----------
    values : sequence of float, shape (n,)
        A metric per evaluation (NaNs dropped first).
    method : {"rolling", "diff"}
        ``"rolling"``: residual from the centred rolling mean over ``2 * (window // 2) + 1`` samples (made odd
        so it is centred), kept only where the whole
        window exists (the first and last ``window // 2`` samples are dropped, where a shrinking window would
        leave part of the trend in); ``"diff"``: first differences ``x[t+1] - x[t]``.
    window : int
        Rolling-mean window (samples), >= 1.

    Returns
    -------
    numpy.ndarray
        The detrended series: ``n - 2 * (window // 2)`` samples for ``"rolling"``, ``n - 1`` for ``"diff"``
        (never fewer than 0). A linear trend leaves exactly zero (``"rolling"``) or a constant (``"diff"``).

    Raises
    ------
    CtsplatError
        For an unknown method or a window < 1.
    """
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    if method == "diff":
        return np.diff(x)
    if method != "rolling":
        raise CtsplatError(f"unknown detrending method {method!r}; allowed: rolling, diff")
    if window < 1:
        raise CtsplatError(f"rolling window must be >= 1, got {window}")
    half = window // 2
    if x.size <= 2 * half:
        return np.array([])
    resid = x - rolling_centered(x, 2 * half + 1)
    return resid[half: x.size - half]


def acf_band(n: int) -> float:
    """Half-width of the 95 % band of the sample ACF of ``n`` samples of white noise: ``1.96 / sqrt(n)``.

    Parameters
    ----------
    n : int
        Number of samples the ACF was computed from.

    Returns
    -------
    float
        NaN for ``n < 1``.
    """
    return 1.96 / np.sqrt(n) if n >= 1 else float("nan")


def convergence_velocity(iterations: Sequence[float], values: Sequence[float], per_iters: int = 1000) -> float:
    """Median gain of ``values`` per ``per_iters`` iterations between successive evaluations.

    ``median_j (v_{j+1} - v_j) / (it_{j+1} - it_j) · per_iters`` over consecutive finite samples. For a linear ramp
    ``v = a·it + b`` this is exactly ``a · per_iters``.

    Parameters
    ----------
    iterations : sequence of float, shape (n,)
    values : sequence of float, shape (n,)
        A metric at those iterations (e.g. PSNR2D in dB).
    per_iters : int
        The velocity's unit: gain per this many iterations.

    Returns
    -------
    float
        Units of ``values`` per ``per_iters`` iterations; NaN when fewer than two finite samples.
    """
    it = np.asarray(iterations, dtype=float)
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(it) & np.isfinite(v)
    it, v = it[ok], v[ok]
    if it.size < 2:
        return float("nan")
    d_it = np.diff(it)
    keep = d_it > 0
    if not keep.any():
        return float("nan")
    return float(np.median(np.diff(v)[keep] / d_it[keep]) * per_iters)


def velocity_curve(
    iterations: Sequence[float], values: Sequence[float], per_iters: int = 1000
) -> pd.DataFrame:
    """Convergence velocity over training: the median gain per ``per_iters`` in each block of ``per_iters``.

    A step between two evaluations belongs to the block where it starts.

    Parameters
    ----------
    iterations : sequence of float, shape (n,)
    values : sequence of float, shape (n,)
    per_iters : int
        Block length and velocity unit (iterations).

    Returns
    -------
    pandas.DataFrame
        ``iteration`` (block centre) and ``velocity`` (gain per ``per_iters``), one row per block with a step.
    """
    it = np.asarray(iterations, dtype=float)
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(it) & np.isfinite(v)
    it, v = it[ok], v[ok]
    rows = []
    if it.size >= 2:
        block = np.floor(it[:-1] / per_iters)
        rate = np.diff(v) / np.where(np.diff(it) > 0, np.diff(it), np.nan) * per_iters
        for b in np.unique(block):
            r = rate[(block == b) & np.isfinite(rate)]
            if r.size:
                rows.append({"iteration": (b + 0.5) * per_iters, "velocity": float(np.median(r))})
    return pd.DataFrame(rows, columns=["iteration", "velocity"])


def threshold_tag(thr: float) -> str:
    """The part of a milestone key that names its threshold.

    Parameters
    ----------
    thr : float
        The threshold.

    Returns
    -------
    str
        ``30 -> "30"``, ``32.5 -> "32.5"``; a fraction as ``0`` and its decimal digits, at least two:
        ``0.9 -> "090"``, ``0.95 -> "095"``, ``0.995 -> "0995"``.

    Examples
    --------
    >>> [threshold_tag(t) for t in (30, 0.9, 0.905, 0.995)]
    ['30', '090', '0905', '0995']
    """
    if 0 < thr < 1:
        return "0" + f"{thr:.10f}".split(".")[1].rstrip("0").ljust(2, "0")
    return f"{thr:g}"


def milestones(log: pd.DataFrame, thresholds: Mapping[str, float]) -> dict[str, float | None]:
    """First iteration and time at which each metric reaches its threshold.

    Parameters
    ----------
    log : pandas.DataFrame
        A training log (:func:`ctsplat.formats.runlog.read_train_log`) in iteration order, with ``iteration``,
        ``timestamp`` (s since the start of training) and the metric columns.
    thresholds : mapping of str to float
        Metric column -> threshold; reached when the metric is ``>=`` it. The workflow's thresholds are the config's
        ``analysis.milestones``.

    Returns
    -------
    dict
        For each metric ``iter_to_{metric}_{tag}`` (int) and ``time_to_{metric}_{tag}_s`` (float, s), with
        ``tag = threshold_tag(threshold)`` (``iter_to_psnr2d_30``, ``time_to_ssim2d_090_s``); None when never
        reached or the metric is not in the log.
    """
    out: dict[str, float | None] = {}
    for metric, thr in thresholds.items():
        key = f"{metric}_{threshold_tag(thr)}"
        hit = log[log[metric] >= thr] if metric in log else log.iloc[0:0]
        if len(hit):
            first = hit.iloc[0]
            out[f"iter_to_{key}"] = int(first["iteration"])
            ts = first["timestamp"]
            out[f"time_to_{key}_s"] = float(ts) if pd.notna(ts) else None
        else:
            out[f"iter_to_{key}"] = None
            out[f"time_to_{key}_s"] = None
    return out


def mean_iters_per_s(log: pd.DataFrame) -> float | None:
    """Mean training speed of a log: last timed iteration / its timestamp.

    Parameters
    ----------
    log : pandas.DataFrame
        A training log with ``iteration`` and ``timestamp`` (s).

    Returns
    -------
    float or None
        Iterations per second; None when no row has a positive timestamp.
    """
    timed = log.dropna(subset=["timestamp"])
    timed = timed[timed["timestamp"] > 0]
    return float(timed["iteration"].iloc[-1] / timed["timestamp"].iloc[-1]) if len(timed) else None


def correlations(
    log: pd.DataFrame, pairs: Sequence[tuple[str, str]] = (("psnr2d", "psnr3d"), ("ssim2d", "ssim3d"))
) -> pd.DataFrame:
    """Pearson and Spearman correlation between 2D and 3D metrics over training (rows with both finite).

    Parameters
    ----------
    log : pandas.DataFrame
        One or more training logs.
    pairs : sequence of (str, str)
        Column pairs (x, y).

    Returns
    -------
    pandas.DataFrame
        Columns ``x, y, n, pearson, spearman``, one row per pair; NaN coefficients when fewer than 3 pairs or a
        constant column.
    """
    from scipy import stats

    rows = []
    for x, y in pairs:
        sub = log[[x, y]].dropna() if x in log and y in log else pd.DataFrame(columns=[x, y])
        n = len(sub)
        p = s = float("nan")
        if n >= 3 and sub[x].nunique() > 1 and sub[y].nunique() > 1:
            p = float(stats.pearsonr(sub[x], sub[y]).statistic)
            s = float(stats.spearmanr(sub[x], sub[y]).statistic)
        rows.append({"x": x, "y": y, "n": n, "pearson": p, "spearman": s})
    return pd.DataFrame(rows, columns=["x", "y", "n", "pearson", "spearman"])


def window_labels(iterations: Sequence[float], n_windows: int) -> np.ndarray:
    """Label each sample by the training window it falls in.

    Training is split into ``n_windows`` equal iteration ranges covering [min, max] of ``iterations``; the last
    window includes its right end.

    Parameters
    ----------
    iterations : sequence of float, shape (n,)
    n_windows : int

    Returns
    -------
    numpy.ndarray of str, shape (n,)
        ``"a–b"`` (the window's iteration range) per sample.
    """
    it = np.asarray(iterations, dtype=float)
    if it.size == 0:
        return np.array([], dtype=object)
    lo, hi = float(np.nanmin(it)), float(np.nanmax(it))
    edges = np.linspace(lo, hi, n_windows + 1)
    idx = np.clip(np.searchsorted(edges, it, side="right") - 1, 0, n_windows - 1)
    names = [f"{int(edges[i])}–{int(edges[i + 1])}" for i in range(n_windows)]
    return np.array([names[i] for i in idx], dtype=object)


def windowed_correlations(
    log: pd.DataFrame, n_windows: int,
    pairs: Sequence[tuple[str, str]] = (("psnr2d", "psnr3d"), ("ssim2d", "ssim3d")),
) -> pd.DataFrame:
    """2D-3D correlations of one run over its whole training and within successive training windows.

    Evaluations of one run over time are not independent samples, and runs differ in level: the correlation is
    computed per run, and per window (equal iteration ranges, :func:`window_labels`) to show how far the 2D metric
    tracks the 3D one early and late in training.

    Parameters
    ----------
    log : pandas.DataFrame
        The training log of ONE run.
    n_windows : int
        Number of windows.
    pairs : sequence of (str, str)
        Column pairs (x, y).

    Returns
    -------
    pandas.DataFrame
        Columns ``window`` (``"all"`` or ``"a–b"``), ``it_start``, ``it_end``, ``it_centre`` (iterations),
        ``x, y, n, pearson, spearman`` (as :func:`correlations`): first the whole run, then each window in order.
    """
    cols = ["window", "it_start", "it_end", "it_centre", "x", "y", "n", "pearson", "spearman"]
    if log.empty:
        return pd.DataFrame(columns=cols)
    it = log["iteration"].to_numpy(dtype=float)
    frames = [correlations(log, pairs).assign(window="all", it_start=it.min(), it_end=it.max(),
                                              it_centre=(it.min() + it.max()) / 2)]
    labels = window_labels(it, n_windows)
    edges = np.linspace(it.min(), it.max(), n_windows + 1)
    seen: set[str] = set()
    for i in range(n_windows):
        name = f"{int(edges[i])}–{int(edges[i + 1])}"
        if name in seen:  # a span shorter than n_windows iterations repeats names; count each sample once
            continue
        seen.add(name)
        sub = log[labels == name]
        frames.append(correlations(sub, pairs).assign(window=name, it_start=edges[i], it_end=edges[i + 1],
                                                      it_centre=(edges[i] + edges[i + 1]) / 2))
    return pd.concat(frames, ignore_index=True)[cols]


def porkchop_table(per_view: pd.DataFrame, metric: str = "psnr2d", split: str | None = None) -> pd.DataFrame:
    """Pivot per-view metrics into a (view × iteration) table for a heatmap.

    Parameters
    ----------
    per_view : pandas.DataFrame
        A per-view log (:func:`ctsplat.formats.runlog.read_per_view`).
    metric : str
        Column to pivot.
    split : str, optional
        Keep only this split (e.g. ``"val"``).

    Returns
    -------
    pandas.DataFrame
        Index ``view_id`` ordered by (azimuth, elevation, id), columns iterations ascending; a view evaluated twice
        at one iteration keeps the mean. Empty when no row is left.
    """
    df = per_view if split is None else per_view[per_view["split"] == split]
    if df.empty:
        return pd.DataFrame()
    order = (df.drop_duplicates("view_id").sort_values(["azimuth_deg", "elevation_deg", "view_id"])["view_id"]
             .tolist())
    table = df.pivot_table(index="view_id", columns="iteration", values=metric, aggfunc="mean")
    return table.reindex(index=order).sort_index(axis=1)


def bounded_kde(values: Sequence[float], lower: float | None = None, upper: float | None = None, *,
                n_grid: int = 256) -> tuple[np.ndarray, np.ndarray]:
    r"""Gaussian kernel density estimate confined to ``[lower, upper]`` by reflection at the bounds.

    With :math:`\hat f` the ordinary Gaussian KDE (Scott's bandwidth :math:`h`), the estimate is
    :math:`\hat f(x) + \hat f(2l - x) + \hat f(2u - x)` on :math:`[l, u]` and zero outside, so no mass is placed
    beyond a bound (e.g. SSIM > 1) and the density still integrates to 1 over the metric's range.

    Parameters
    ----------
    values : sequence of float, shape (n,)
        Samples (NaNs dropped); every sample must lie within the bounds.
    lower, upper : float, optional
        The metric's range (:data:`METRIC_RANGES`); None = unbounded on that side.
    n_grid : int
        Number of evaluation points.

    Returns
    -------
    x : numpy.ndarray, shape (n_grid,)
        Evaluation points spanning the samples ± 3 h, clipped to the bounds.
    density : numpy.ndarray, shape (n_grid,)
        The estimate at ``x``; empty arrays when fewer than two distinct finite samples.

    Raises
    ------
    CtsplatError
        When a sample lies outside ``[lower, upper]``.
    """
    from scipy import stats

    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if np.unique(v).size < 2:
        return np.array([]), np.array([])
    if (lower is not None and v.min() < lower) or (upper is not None and v.max() > upper):
        raise CtsplatError(f"KDE sample outside the metric's range [{lower}, {upper}]: {v.min():g}..{v.max():g}")
    kde = stats.gaussian_kde(v)
    h = float(np.sqrt(kde.covariance[0, 0]))
    lo, hi = v.min() - 3 * h, v.max() + 3 * h
    lo = lo if lower is None else max(lo, lower)
    hi = hi if upper is None else min(hi, upper)
    x = np.linspace(lo, hi, n_grid)
    dens = kde(x)
    if lower is not None:
        dens = dens + kde(2 * lower - x)
    if upper is not None:
        dens = dens + kde(2 * upper - x)
    return x, dens


def varying_axes(table: pd.DataFrame, axes: Sequence[str], exclude: Sequence[str] = ("seed",)) -> list[str]:
    """The columns of ``axes`` that take more than one value in ``table`` (in the order given).

    Parameters
    ----------
    table : pandas.DataFrame
        One row per run (or per log row), with the axis columns.
    axes : sequence of str
        Candidate columns, e.g. ``("volume", *GRID_AXES)``.
    exclude : sequence of str
        Columns never returned (the seed: replicates of one condition).

    Returns
    -------
    list of str
    """
    return [a for a in axes if a in table and a not in exclude and table[a].astype(str).nunique() > 1]


def condition_labels(table: pd.DataFrame, axes: Sequence[str], exclude: Sequence[str] = ("seed",)) -> pd.Series:
    """Name each row's condition by the axes that differ across the table: ``"init=fbp, views=24"``.

    Parameters
    ----------
    table : pandas.DataFrame
        One row per run (or per log row), with the axis columns.
    axes : sequence of str
        Candidate columns in naming order, e.g. ``("volume", *GRID_AXES)``.
    exclude : sequence of str
        Columns left out of the name (by default the seed, so replicates share a condition); pass ``()`` to
        name single runs.

    Returns
    -------
    pandas.Series of str
        Indexed like ``table``; ``"all runs"`` when no axis varies.
    """
    used = varying_axes(table, axes, exclude)
    if not used:
        return pd.Series("all runs", index=table.index, dtype=object)
    return table[used].astype(str).apply(lambda r: ", ".join(f"{a}={r[a]}" for a in used), axis=1).astype(object)


def natural_value(v: str) -> tuple[int, float | str]:
    """Sort key of an axis value: numbers first, in numeric order (``"8" < "16"``), then text."""
    try:
        return (0, float(v))
    except ValueError:
        return (1, v)


def run_cells(summary: pd.DataFrame) -> pd.DataFrame:
    """The summary with every condition axis filled (``ABSENT`` where a run's grid lacked an optional axis),
    refused when two runs are of one grid cell.

    Parameters
    ----------
    summary : pandas.DataFrame
        The table of :func:`ctsplat.analysis.gather.gather`.

    Returns
    -------
    pandas.DataFrame
        A copy whose :data:`CONDITION_AXES` columns hold no NaN (pandas drops index rows holding NaN, so a run
        without an optional axis would silently leave every table indexed by the axes).

    Raises
    ------
    CtsplatError
        When two runs share every axis value (two experiments with the same volume names gathered into one
        summary): a pair or a curve would be their average.
    """
    axes = [a for a in CONDITION_AXES if a in summary]
    filled = summary[axes].astype(object).where(summary[axes].notna(), ABSENT)
    cells = summary.assign(**{a: filled[a] for a in axes})
    repeated = cells.duplicated(axes, keep=False)
    if repeated.any():
        first = cells[repeated].iloc[0]
        clash = cells[repeated & (cells[axes] == first[axes]).all(axis=1)]
        dirs = clash["run_dir"].astype(str).tolist() if "run_dir" in clash else [str(i) for i in clash.index]
        where = ", ".join(f"{a}={first[a]}" for a in axes)
        raise CtsplatError(f"{dirs[0]} and {dirs[1]} are runs of one grid cell ({where}); a summary gathers one "
                           "experiment: gather the others into their own summary")
    return cells


def paired_table(summary: pd.DataFrame, axis: str, metric_col: str) -> pd.DataFrame:
    """Runs that differ only in ``axis``: one row per pair group, one column per value of ``axis``.

    Parameters
    ----------
    summary : pandas.DataFrame
        The table of :func:`ctsplat.analysis.gather.gather`.
    axis : str
        The ablation axis that changes within a group.
    metric_col : str
        The summary column compared.

    Returns
    -------
    pandas.DataFrame
        Index: the values of every other axis (volume and seed included, so each group is one cell of the grid
        with only ``axis`` changed; a feature axis a run does not have reads ``ABSENT``); columns: the values of
        ``axis`` in natural order; groups with fewer than two finite values are dropped.

    Raises
    ------
    CtsplatError
        When two runs are of one grid cell (:func:`run_cells`).
    """
    others = [a for a in CONDITION_AXES if a != axis and a in summary]
    cells = run_cells(summary)
    df = cells.assign(_score=pd.to_numeric(summary[metric_col], errors="coerce"), _level=summary[axis].astype(str))
    wide = df.pivot_table(index=others, columns="_level", values="_score", aggfunc="first")
    wide = wide[sorted(wide.columns, key=natural_value)]
    return wide[wide.notna().sum(axis=1) >= 2]
