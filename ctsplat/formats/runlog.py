"""The run logs of a training run: ``train_log.csv`` and ``per_view.csv``.

``train_log.csv`` has one row per periodic evaluation: :data:`LOG_COLUMNS` (iteration, seconds since the start of
training, validation-split 2D metrics and 3D metrics) followed by :data:`LOG_EXTRAS` (loss terms, model size,
learning rate, speed, densification counts). ``per_view.csv`` has one row per evaluated view and evaluation
(:data:`PER_VIEW_COLUMNS`). Both are written by :class:`CsvLog` (append-only, fsynced, truncated back to a
checkpoint on resume) and read by :func:`read_train_log` / :func:`read_per_view`.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ctsplat.utils import CtsplatError, atomic_path

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "METRICS_2D3D",
    "LOG_COLUMNS",
    "LOG_EXTRAS",
    "PER_VIEW_COLUMNS",
    "CsvLog",
    "read_train_log",
    "read_per_view",
]

METRICS_2D3D: tuple[str, ...] = ("psnr2d", "ssim2d", "psnr3d", "ssim3d")
LOG_COLUMNS: tuple[str, ...] = ("iteration", "timestamp", *METRICS_2D3D)
LOG_EXTRAS: tuple[str, ...] = ("loss", "l1", "dssim", "density_reg", "scale_reg", "tv", "n_gaussians", "lr_means",
                               "iters_per_s", "nan_events", "cloned", "split", "pruned")
PER_VIEW_COLUMNS: tuple[str, ...] = ("iteration", "view_id", "azimuth_deg", "elevation_deg", "split", "psnr2d",
                                     "ssim2d")


class CsvLog:
    """Append-only CSV with a fixed header.

    Parameters
    ----------
    path : pathlib.Path
        The CSV file.
    columns : sequence of str
        Header; rows are written in this column order, missing values as empty fields.
    """

    def __init__(self, path: Path, columns: Sequence[str]) -> None:
        self.path = path
        self.columns = list(columns)

    def reset(self) -> None:
        """Start the file over with only the header."""
        with atomic_path(self.path) as tmp:
            tmp.write_text(",".join(self.columns) + "\n")

    def truncate_after(self, iteration: int) -> None:
        """Drop the rows logged after ``iteration`` (a resumed run continues from its checkpoint's iteration)."""
        if not self.path.exists():
            self.reset()
            return
        text = self.path.read_text()
        if not text.endswith("\n"):  # a row cut short by a crash is dropped, not kept as a row of empty fields
            text = text[: text.rfind("\n") + 1]
        rows = list(csv.DictReader(io.StringIO(text, newline="")))
        with atomic_path(self.path) as tmp, open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=self.columns, lineterminator="\n")
            w.writeheader()
            for r in rows:
                if (it := _iteration(r)) is not None and it <= iteration:
                    w.writerow({k: r.get(k, "") for k in self.columns})

    def header_matches(self) -> bool:
        """Whether the file is missing or empty or starts with this log's header (rows are written by position).

        :meth:`truncate_after` rewrites a file with another header under this one, column by column name."""
        if not self.path.exists():
            return True
        with open(self.path, newline="") as fh:
            first = fh.readline().rstrip("\r\n")
        return not first or first == ",".join(self.columns)

    def append(self, rows: list[dict[str, Any]]) -> None:
        """Append rows (dicts keyed by column) and flush them to disk."""
        if not self.header_matches():
            raise CtsplatError(f"{self.path} has another header than this log's columns, so appended rows would "
                               "land under other columns; move it away or start the run over")
        with open(self.path, "a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=self.columns, lineterminator="\n")
            for r in rows:
                w.writerow({k: _fmt(r.get(k, "")) for k in self.columns})
            fh.flush()
            os.fsync(fh.fileno())


def _fmt(v: Any) -> Any:
    """Floats at full precision (``repr`` round-trips), everything else as the csv module writes it."""
    if isinstance(v, float):
        return repr(float(v))  # a NumPy float64 is a float, but its own repr is "np.float64(...)"
    return v


def _iteration(row: dict[str, Any]) -> int | None:
    """A log row's iteration, None for a row without a readable one."""
    try:
        return int(row.get("iteration") or "")
    except ValueError:
        return None


def _ffill_short_gaps(df: pd.DataFrame, columns: Sequence[str], max_gap_iters: int) -> pd.DataFrame:
    """Forward-fill NaNs in ``columns`` from the last valid value when it is fewer than ``max_gap_iters`` away."""
    import numpy as np
    import pandas as pd

    df = df.copy()
    it = df["iteration"].to_numpy(dtype=float)
    for col in columns:
        vals = df[col].to_numpy(dtype=float)
        valid = ~np.isnan(vals)
        # iteration of the last valid value at or before each row
        last_it = pd.Series(np.where(valid, it, np.nan)).ffill().to_numpy()
        filled = pd.Series(vals).ffill().to_numpy()
        fill = ~valid & ~np.isnan(last_it) & (it - last_it < max_gap_iters)
        df[col] = np.where(fill, filled, vals)
    return df


def read_train_log(path: str | os.PathLike[str], *, max_gap_iters: int = 10) -> pd.DataFrame:
    """Read a ``train_log.csv``, tolerating gaps.

    Rows without an iteration are dropped; a missing timestamp or metric is forward-filled from the last logged
    value when that one is fewer than ``max_gap_iters`` iterations earlier, otherwise it stays NaN (plots and
    statistics drop it). Rows are sorted by iteration; duplicate iterations keep the last row (a resumed run).

    Parameters
    ----------
    path : path-like
        The CSV file; its first columns must be :data:`LOG_COLUMNS`.
    max_gap_iters : int
        Longest gap (iterations, exclusive) bridged by forward-filling.

    Returns
    -------
    pandas.DataFrame
        Numeric :data:`LOG_COLUMNS` first (``iteration`` int, ``timestamp`` in s), then the extra columns.

    Raises
    ------
    CtsplatError
        When the file cannot be read or its first columns differ from :data:`LOG_COLUMNS`.
    """
    import pandas as pd

    path = Path(path)
    try:
        df = pd.read_csv(path)
    except (OSError, UnicodeDecodeError, pd.errors.EmptyDataError, pd.errors.ParserError) as exc:
        raise CtsplatError(f"cannot read training log {path}: {' '.join(str(exc).split())}") from exc
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
    """Read a ``per_view.csv``.

    Rows missing the iteration or the view id, or both metrics, are dropped.

    Parameters
    ----------
    path : path-like
        The CSV file with the :data:`PER_VIEW_COLUMNS`.

    Returns
    -------
    pandas.DataFrame
        :data:`PER_VIEW_COLUMNS` with ``iteration`` and ``view_id`` int, angles in degrees.

    Raises
    ------
    CtsplatError
        When the file cannot be read or lacks a column.
    """
    import pandas as pd

    path = Path(path)
    try:
        df = pd.read_csv(path)
    except (OSError, UnicodeDecodeError, pd.errors.EmptyDataError, pd.errors.ParserError) as exc:
        raise CtsplatError(f"cannot read per-view log {path}: {' '.join(str(exc).split())}") from exc
    missing = [c for c in PER_VIEW_COLUMNS if c not in df.columns]
    if missing:
        raise CtsplatError(f"{path}: missing column {missing[0]!r}; expected {','.join(PER_VIEW_COLUMNS)}")
    for col in PER_VIEW_COLUMNS:
        if col != "split":
            df[col] = pd.to_numeric(df[col], errors="coerce")
    df = df.dropna(subset=["iteration", "view_id"]).dropna(subset=["psnr2d", "ssim2d"], how="all")
    return df.astype({"iteration": int, "view_id": int}).reset_index(drop=True)
