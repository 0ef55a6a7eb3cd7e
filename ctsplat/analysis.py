"""Ablation grids and training-log analysis.

Two halves, both plain functions over dicts / pandas tables so they are tested without Snakemake:

*Grid and config* (used by the Snakemake workflow at parse time): validate the workflow config against its JSON
schema (Draft 2020-12, defaults filled, errors name the key path), check library sections against the owning
modules' ``*_DEFAULTS``, check volume sources exist, and expand the ablation axes into a table of runs (product
minus exclusions) whose rows map to run folders ``init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0``.

*Log analysis* (the results chapter): read ``train_log.csv`` / ``per_view.csv`` tolerating gaps, centred rolling
means, convergence velocity, autocorrelation, milestones, 2D-vs-3D correlations, porkchop tables, and
:func:`gather`, which writes ``summary.csv`` with one row per run.
"""

from __future__ import annotations

import copy
import importlib
import itertools
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ctsplat.utils import CtsplatError, atomic_path, merge_config

__all__ = [
    "ANALYSIS_OUTPUTS",
    "RUN_FIGURES",
    "GRID_AXES",
    "LOG_COLUMNS",
    "PER_VIEW_COLUMNS",
    "LIBRARY_SECTIONS",
    "load_schema",
    "validate_config",
    "check_library_sections",
    "check_volume_sources",
    "expand_grid",
    "prepare_config",
    "normalise_mip",
    "run_relpath",
    "parse_run_dir",
    "read_train_log",
    "read_per_view",
    "rolling_centered",
    "acf",
    "convergence_velocity",
    "velocity_curve",
    "milestones",
    "threshold_tag",
    "correlations",
    "window_labels",
    "porkchop_table",
    "gather",
    "load_runs",
]

# Order = folder nesting order of a run directory.
GRID_AXES: tuple[str, ...] = ("init", "compositor", "mip", "poses", "views", "seed")
LOG_COLUMNS: tuple[str, ...] = ("iteration", "timestamp", "psnr2d", "ssim2d", "psnr3d", "ssim3d")
PER_VIEW_COLUMNS: tuple[str, ...] = ("iteration", "view", "azimuth", "elevation", "split", "psnr2d", "ssim2d")
METRICS_2D3D: tuple[str, ...] = ("psnr2d", "ssim2d", "psnr3d", "ssim3d")

# Workflow config section -> (module, DEFAULTS attribute, path inside the section that holds the settings).
LIBRARY_SECTIONS: dict[str, tuple[str, str]] = {
    "preprocessing": ("ctsplat.volume", "PREPROCESSING_DEFAULTS"),
    "radiographs": ("ctsplat.projector", "RADIOGRAPHS_DEFAULTS"),
    "baselines": ("ctsplat.baselines", "BASELINES_DEFAULTS"),
    "sfm": ("ctsplat.sfm", "SFM_DEFAULTS"),
    "train": ("ctsplat.train", "TRAIN_DEFAULTS"),
}

# Grid-level outputs of `analyse`: name -> (file name under results/figures/, report category). A fixed set so the
# workflow can declare them; written by ctsplat.plots.analyse.
ANALYSIS_OUTPUTS: dict[str, tuple[str, str]] = {
    **{f"convergence_by_{a}": (f"convergence_by_{a}.png", "Convergence") for a in GRID_AXES},
    "velocity": ("velocity.png", "Convergence"),
    "acf": ("acf.png", "Convergence"),
    "kde": ("kde.png", "Convergence"),
    "correlations_plot": ("correlations.png", "2D vs 3D"),
    "correlations": ("correlations.csv", "2D vs 3D"),
    "milestones": ("milestones.csv", "Milestones"),
    "ablation": ("ablation.png", "Ablation"),
    "baselines": ("baselines.png", "Baselines"),
}
RUN_FIGURES: tuple[str, ...] = ("convergence", "porkchop", "acf", "kde")

SCHEMA_PATH = Path(__file__).resolve().parent.parent / "workflow" / "schemas" / "config.schema.yaml"


# ----------------------------------------------------------------------------------------------------------------
# Config validation
# ----------------------------------------------------------------------------------------------------------------


def load_schema(path: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Load the workflow config JSON schema (YAML or JSON file)."""
    import yaml

    path = Path(path) if path is not None else SCHEMA_PATH
    with open(path) as fh:
        return yaml.safe_load(fh)


def _key_path(parts: Iterable[Any]) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "<config>"


def _validator_with_defaults():
    """A Draft 2020-12 validator class that fills ``default`` values of missing properties while validating."""
    from jsonschema import Draft202012Validator, validators

    base_properties = Draft202012Validator.VALIDATORS["properties"]

    def properties_with_defaults(validator, properties, instance, schema):
        if validator.is_type(instance, "object"):
            for name, sub in properties.items():
                if isinstance(sub, dict) and "default" in sub and name not in instance:
                    instance[name] = copy.deepcopy(sub["default"])
        yield from base_properties(validator, properties, instance, schema)

    return validators.extend(Draft202012Validator, {"properties": properties_with_defaults})


def validate_config(config: Mapping[str, Any], schema: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Validate ``config`` against the workflow schema and return a copy with defaults filled.

    Raises
    ------
    CtsplatError
        On the first (deepest-path) error, naming the key path, e.g.
        ``invalid config at grid.axes.views[0]: 'ten' is not of type 'integer'``.
    """
    schema = load_schema() if schema is None else schema
    filled = copy.deepcopy(dict(config))
    cls = _validator_with_defaults()
    errors = sorted(cls(schema).iter_errors(filled), key=lambda e: (-len(e.absolute_path), str(e.absolute_path)))
    if errors:
        err = errors[0]
        # oneOf/anyOf errors: report the most specific sub-error
        if err.context:
            err = max(err.context, key=lambda e: len(e.absolute_path))
        where = _key_path(err.absolute_path)
        msg = err.message
        if err.validator == "additionalProperties":
            allowed = sorted((err.schema.get("properties") or {}).keys())
            msg += f" (allowed: {', '.join(allowed)})" if allowed else ""
        raise CtsplatError(f"invalid config at {where}: {msg}")
    return filled


def check_library_sections(config: Mapping[str, Any], *, modules: Mapping[str, tuple[str, str]] | None = None) -> None:
    """Check library sections key by key against the owning modules' ``*_DEFAULTS`` (unknown key -> error).

    A module that cannot be imported (step not installed yet) is skipped; the step itself re-checks its config
    with :func:`ctsplat.utils.merge_config` when it runs.
    """
    modules = LIBRARY_SECTIONS if modules is None else modules

    def defaults_of(section: str) -> dict[str, Any] | None:
        if section not in modules:
            return None
        mod_name, attr = modules[section]
        try:
            mod = importlib.import_module(mod_name)
        except ImportError:
            return None
        return getattr(mod, attr, None)

    for display, section, values in _library_section_values(config):
        defaults = defaults_of(section)
        if defaults is not None:
            merge_config(display, values, defaults)


def _library_section_values(config: Mapping[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """(key path shown in errors, LIBRARY_SECTIONS key, user values) for every library section in ``config``."""
    out: list[tuple[str, str, dict[str, Any]]] = [("preprocessing", "preprocessing", config.get("preprocessing", {}))]
    for name, vol in config.get("volumes", {}).items():
        out.append((f"volumes.{name}.preprocessing", "preprocessing", vol.get("preprocessing", {})))
    for geo, values in config.get("radiographs", {}).items():
        out.append((f"radiographs.{geo}", "radiographs", values))
    out.append(("baselines.settings", "baselines", config.get("baselines", {}).get("settings", {})))
    out.append(("sfm.settings", "sfm", config.get("sfm", {}).get("settings", {})))
    out.append(("train", "train", config.get("train", {})))
    return out


def check_volume_sources(volumes: Mapping[str, Mapping[str, Any]], base_dir: str | os.PathLike[str] = ".") -> None:
    """Every volume source must be ``phantom`` or an existing path (relative paths from ``base_dir``)."""
    for name, vol in volumes.items():
        source = vol["source"]
        if source == "phantom":
            continue
        path = Path(source)
        if not path.is_absolute():
            path = Path(base_dir) / path
        if not path.exists():
            raise CtsplatError(
                f"volume source not found at volumes.{name}.source: {source!r} (resolved to {path.resolve()}); "
                "give a DICOM folder, a .nii/.nii.gz file, a TIFF stack, or 'phantom'"
            )


def normalise_mip(value: Any) -> str:
    """``True``/``"on"`` -> ``"on"``, ``False``/``"off"`` -> ``"off"`` (YAML 1.1 reads bare on/off as booleans)."""
    if value is True or value == "on":
        return "on"
    if value is False or value == "off":
        return "off"
    raise CtsplatError(f"invalid mip value {value!r}; allowed: on, off")


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, list | tuple) else [value]


def expand_grid(
    axes: Mapping[str, Sequence[Any]],
    volumes: Sequence[str],
    exclude: Sequence[Mapping[str, Any]] = (),
) -> pd.DataFrame:
    """Cartesian product of volumes × axis values, minus excluded cells.

    Parameters
    ----------
    axes : mapping axis name -> list of values, for every name in :data:`GRID_AXES`.
    volumes : volume names.
    exclude : entries mapping axis names (or ``volume``) to a value or list of values; a cell is dropped when it
        matches every key of an entry.

    Returns
    -------
    DataFrame with columns ``volume, *GRID_AXES`` (``mip`` as ``"on"``/``"off"``, ``views``/``seed`` int), one row
    per run, in product order.

    Raises
    ------
    CtsplatError
        When the grid expands to zero runs.
    """
    missing = [a for a in GRID_AXES if a not in axes]
    if missing:
        raise CtsplatError(f"grid.axes is missing {missing[0]!r}; axes: {', '.join(GRID_AXES)}")
    values = {a: list(axes[a]) for a in GRID_AXES}
    values["mip"] = [normalise_mip(v) for v in values["mip"]]
    rows = [dict(zip(("volume", *GRID_AXES), combo, strict=True))
            for combo in itertools.product(list(volumes), *(values[a] for a in GRID_AXES))]

    def norm(key: str, v: Any) -> Any:
        return normalise_mip(v) if key == "mip" else v

    def excluded(row: dict[str, Any]) -> bool:
        return any(all(row[k] in [norm(k, v) for v in _as_list(vals)] for k, vals in entry.items())
                   for entry in exclude)

    kept = [r for r in rows if not excluded(r)]
    if not kept:
        raise CtsplatError(
            f"the ablation grid expands to zero runs ({len(rows)} cells, all removed by grid.exclude or no volumes); "
            "loosen grid.exclude or add axis values"
        )
    df = pd.DataFrame(kept, columns=["volume", *GRID_AXES])
    return df.astype({"views": int, "seed": int}).reset_index(drop=True)


def run_relpath(row: Mapping[str, Any]) -> str:
    """``init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0`` for one grid row (Paramspace layout)."""
    return "/".join(f"{a}~{row[a]}" for a in GRID_AXES)


def parse_run_dir(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Axis values (and ``volume``) from a run folder path ``.../{volume}/runs/init~x/.../seed~0``.

    ``views`` and ``seed`` are returned as int. Missing axes raise :class:`CtsplatError`.
    """
    parts = Path(path).parts
    out: dict[str, Any] = {}
    for p in parts:
        if "~" in p:
            key, _, val = p.partition("~")
            if key in GRID_AXES:
                out[key] = int(val) if key in ("views", "seed") else val
    missing = [a for a in GRID_AXES if a not in out]
    if missing:
        raise CtsplatError(f"{path}: not a run folder (no {missing[0]}~<value> component)")
    if "runs" in parts:
        i = len(parts) - 1 - parts[::-1].index("runs")
        if i >= 1:
            out["volume"] = parts[i - 1]
    return out


def prepare_config(config: Mapping[str, Any], base_dir: str | os.PathLike[str] = ".") -> dict[str, Any]:
    """Everything the workflow checks at parse time, before any job runs.

    Validates against the schema (defaults filled; its library sections mirror the modules' DEFAULTS, see
    :func:`check_library_sections` for the import-time check), checks volume sources exist, resolves
    ``grid.geometry`` and ``baselines.geometry`` (null = the first radiographs geometry / the grid's), expands the
    grid (zero runs is an error) and checks the largest ``views`` value fits the training geometry. Returns the
    filled config.
    """
    cfg = validate_config(config)  # library sections are mirrored in the schema: no heavy imports at parse time
    check_volume_sources(cfg["volumes"], base_dir)
    geometries = list(cfg["radiographs"])
    if cfg["grid"]["geometry"] is None:
        cfg["grid"]["geometry"] = geometries[0]
    elif cfg["grid"]["geometry"] not in geometries:
        raise CtsplatError(
            f"invalid config at grid.geometry: {cfg['grid']['geometry']!r} is not a radiographs geometry "
            f"(defined: {', '.join(geometries)})"
        )
    if cfg["baselines"]["geometry"] is None:
        cfg["baselines"]["geometry"] = cfg["grid"]["geometry"]
    elif cfg["baselines"]["geometry"] not in geometries:
        raise CtsplatError(
            f"invalid config at baselines.geometry: {cfg['baselines']['geometry']!r} is not a radiographs geometry "
            f"(defined: {', '.join(geometries)})"
        )
    runs = expand_grid(cfg["grid"]["axes"], list(cfg["volumes"]), cfg["grid"]["exclude"])
    geo = cfg["radiographs"][cfg["grid"]["geometry"]]
    # circular orbits have exactly n_views training angles; a sphere splits n_views into train/val/test
    available = geo["n_views"] if geo["orbit"] == "circular" else int(geo["n_views"] * geo["split"]["train"])
    if int(runs["views"].max()) > available:
        raise CtsplatError(
            f"invalid config at grid.axes.views: {int(runs['views'].max())} training views requested but geometry "
            f"{cfg['grid']['geometry']!r} has only about {available} training views; raise "
            f"radiographs.{cfg['grid']['geometry']}.n_views or lower the views axis"
        )
    return cfg


# ----------------------------------------------------------------------------------------------------------------
# Log reading
# ----------------------------------------------------------------------------------------------------------------


def _ffill_short_gaps(df: pd.DataFrame, columns: Sequence[str], max_gap_iters: int) -> pd.DataFrame:
    """Forward-fill NaNs in ``columns`` from the last valid value when it is fewer than ``max_gap_iters`` away."""
    df = df.copy()
    it = df["iteration"].to_numpy(dtype=float)
    for col in columns:
        vals = df[col].to_numpy(dtype=float)
        valid = ~np.isnan(vals)
        # iteration of the last valid value at or before each row
        last_it = pd.Series(np.where(valid, it, np.nan)).ffill().to_numpy()
        filled = pd.Series(vals).ffill().to_numpy()
        fill = ~valid & ~np.isnan(last_it) & (it - last_it < max_gap_iters)
        vals = np.where(fill, filled, vals)
        df[col] = vals
    return df


def read_train_log(path: str | os.PathLike[str], *, max_gap_iters: int = 10) -> pd.DataFrame:
    """Read a ``train_log.csv`` (columns ``iteration,timestamp,psnr2d,ssim2d,psnr3d,ssim3d`` then extras).

    Missing values: rows without an iteration are dropped; a missing metric is forward-filled from the last logged
    value when that one is fewer than ``max_gap_iters`` iterations earlier, otherwise it stays NaN (plots and
    statistics drop it). Rows are sorted by iteration; duplicate iterations keep the last row (a resumed run).

    Returns
    -------
    DataFrame with numeric ``LOG_COLUMNS`` first and the extra columns after.
    """
    path = Path(path)
    try:
        df = pd.read_csv(path)
    except (OSError, pd.errors.EmptyDataError) as exc:
        raise CtsplatError(f"cannot read training log {path}: {exc}") from exc
    head = tuple(df.columns[: len(LOG_COLUMNS)])
    if head != LOG_COLUMNS:
        raise CtsplatError(f"{path}: first columns must be {','.join(LOG_COLUMNS)}, got {','.join(head)}")
    for col in LOG_COLUMNS:
        df[col] = pd.to_numeric(df[col], errors="coerce")
    df = df.dropna(subset=["iteration"])
    df = df.sort_values("iteration", kind="stable").drop_duplicates("iteration", keep="last")
    df["iteration"] = df["iteration"].astype(int)
    df = _ffill_short_gaps(df, ["timestamp", *METRICS_2D3D], max_gap_iters)
    return df.reset_index(drop=True)


def read_per_view(path: str | os.PathLike[str]) -> pd.DataFrame:
    """Read ``per_view.csv`` (iteration, view, azimuth, elevation, split, psnr2d, ssim2d; ``view_id``,
    ``azimuth_deg``, ``elevation_deg`` accepted as aliases); rows missing the iteration, view or both metrics are
    dropped."""
    path = Path(path)
    try:
        df = pd.read_csv(path)
    except (OSError, pd.errors.EmptyDataError) as exc:
        raise CtsplatError(f"cannot read per-view log {path}: {exc}") from exc
    # ctsplat.train writes view_id / azimuth_deg / elevation_deg
    aliases = {"view_id": "view", "azimuth_deg": "azimuth", "elevation_deg": "elevation"}
    df = df.rename(columns={k: v for k, v in aliases.items() if k in df.columns and v not in df.columns})
    missing = [c for c in PER_VIEW_COLUMNS if c not in df.columns]
    if missing:
        raise CtsplatError(f"{path}: missing column {missing[0]!r}; expected {','.join(PER_VIEW_COLUMNS)}")
    for col in ("iteration", "view", "azimuth", "elevation", "psnr2d", "ssim2d"):
        df[col] = pd.to_numeric(df[col], errors="coerce")
    df = df.dropna(subset=["iteration", "view"]).dropna(subset=["psnr2d", "ssim2d"], how="all")
    return df.astype({"iteration": int, "view": int}).reset_index(drop=True)


# ----------------------------------------------------------------------------------------------------------------
# Statistics
# ----------------------------------------------------------------------------------------------------------------


def rolling_centered(values: Sequence[float] | pd.Series, window: int) -> np.ndarray:
    """Centred rolling mean over ``window`` samples, NaN-aware, shrinking at the ends.

    ``out[i] = mean(x[i - (window-1)//2 - (window+1)%2 ... i + (window-1)//2])`` (pandas ``center=True``),
    ignoring NaNs; the first/last samples average over the part of the window that exists.
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

    Returns
    -------
    ndarray (min(max_lag, n-1) + 1,); ``r_0 = 1``. A constant series gives NaN for k >= 1.
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


def convergence_velocity(iterations: Sequence[float], values: Sequence[float], per_iters: int = 1000) -> float:
    """Median gain of ``values`` per ``per_iters`` iterations between successive evaluations.

    ``median_j (v_{j+1} - v_j) / (it_{j+1} - it_j) · per_iters`` over consecutive finite samples. For a linear ramp
    ``v = a·it + b`` this is exactly ``a · per_iters``. NaN when fewer than two finite samples.
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

    Returns a DataFrame with ``iteration`` (block centre) and ``velocity`` (gain per ``per_iters``).
    """
    it = np.asarray(iterations, dtype=float)
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(it) & np.isfinite(v)
    it, v = it[ok], v[ok]
    rows = []
    if it.size >= 2:
        block = np.floor(it[:-1] / per_iters)  # a step belongs to the block where it starts
        rate = np.diff(v) / np.where(np.diff(it) > 0, np.diff(it), np.nan) * per_iters
        for b in np.unique(block):
            r = rate[(block == b) & np.isfinite(rate)]
            if r.size:
                rows.append({"iteration": (b + 0.5) * per_iters, "velocity": float(np.median(r))})
    return pd.DataFrame(rows, columns=["iteration", "velocity"])


def milestones(log: pd.DataFrame, thresholds: Mapping[str, float]) -> dict[str, float | None]:
    """First iteration and time (s) at which each metric reaches ``>= threshold``, and iterations/s.

    Returns keys ``iter_to_{metric}_{tag}`` and ``time_to_{metric}_{tag}_s`` (None when never reached), named as in
    ``metrics.json`` of :func:`ctsplat.train.train` (tag :func:`threshold_tag`: ``psnr2d_30``, ``ssim2d_090``), and
    ``iters_per_s`` = last iteration / last timestamp.
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
    timed = log.dropna(subset=["timestamp"])
    timed = timed[timed["timestamp"] > 0]
    out["iters_per_s"] = (
        float(timed["iteration"].iloc[-1] / timed["timestamp"].iloc[-1]) if len(timed) else None
    )
    return out


def threshold_tag(thr: float) -> str:
    """``30 -> "30"``, ``0.9 -> "090"`` (fractions as hundredths, three digits), ``32.5 -> "32.5"``."""
    return f"{round(thr * 100):03d}" if 0 < thr < 1 else f"{thr:g}"


def correlations(
    log: pd.DataFrame, pairs: Sequence[tuple[str, str]] = (("psnr2d", "psnr3d"), ("ssim2d", "ssim3d"))
) -> pd.DataFrame:
    """Pearson and Spearman correlation between 2D and 3D metrics over training (rows with both finite).

    Returns a DataFrame with columns ``x, y, n, pearson, spearman`` (NaN when fewer than 3 pairs or constant).
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
    """Split training into ``n_windows`` equal iteration ranges; label each sample ``"a–b"`` by its window.

    The ranges cover [min, max] of ``iterations``; the last window includes its right end.
    """
    it = np.asarray(iterations, dtype=float)
    if it.size == 0:
        return np.array([], dtype=object)
    lo, hi = float(np.nanmin(it)), float(np.nanmax(it))
    edges = np.linspace(lo, hi, n_windows + 1)
    idx = np.clip(np.searchsorted(edges, it, side="right") - 1, 0, n_windows - 1)
    names = [f"{int(edges[i])}–{int(edges[i + 1])}" for i in range(n_windows)]
    return np.array([names[i] for i in idx], dtype=object)


def porkchop_table(per_view: pd.DataFrame, metric: str = "psnr2d", split: str | None = None) -> pd.DataFrame:
    """Pivot per-view metrics into a (view × iteration) table for a heatmap.

    Rows are views ordered by (azimuth, elevation, id), columns are iterations ascending; a view evaluated twice
    at one iteration keeps the mean. ``split`` filters to one split (e.g. ``"val"``) when given.
    """
    df = per_view if split is None else per_view[per_view["split"] == split]
    if df.empty:
        return pd.DataFrame()
    order = (df.drop_duplicates("view").sort_values(["azimuth", "elevation", "view"])["view"].tolist())
    table = df.pivot_table(index="view", columns="iteration", values=metric, aggfunc="mean")
    return table.reindex(index=order).sort_index(axis=1)


# ----------------------------------------------------------------------------------------------------------------
# Gather
# ----------------------------------------------------------------------------------------------------------------


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
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

    Columns: ``volume`` + :data:`GRID_AXES` (from the folder names), ``run_dir``, the flattened ``metrics.json``
    (nested keys joined with ``.``), and from ``train_log.csv`` the last logged 2D/3D metrics (``final_*``),
    milestones (:func:`milestones`) and the PSNR2D convergence velocity (``velocity_psnr2d``).
    """
    thresholds = {"psnr2d": 30.0, "ssim2d": 0.9} if thresholds is None else thresholds
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
            row["velocity_psnr2d"] = convergence_velocity(log["iteration"], log["psnr2d"], per_iters)
        if not metrics_path.exists() and not log_path.exists():
            raise CtsplatError(f"gather: {rd} has neither metrics.json nor train_log.csv; did training finish?")
        rows.append(row)
    df = pd.DataFrame(rows)
    with atomic_path(out_csv) as tmp:
        df.to_csv(tmp, index=False)
    return df


def load_runs(summary: pd.DataFrame, *, max_gap_iters: int = 10) -> pd.DataFrame:
    """All runs' training logs in one long table, each row tagged with its run's ``volume`` and axis values."""
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
