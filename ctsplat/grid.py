"""The ablation grid: axis values expanded into runs, and run folders named after their grid cell.

A grid is the Cartesian product of the volumes and the values of every axis in :data:`GRID_AXES`, minus the
cells matched by ``grid.exclude``. Each run lives in a Paramspace-style folder
``results/{volume}/runs/init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0``.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ctsplat.utils import CtsplatError

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["GRID_AXES", "expand_grid", "normalise_mip", "run_relpath", "parse_run_dir", "needs_sfm"]

#: The ablation axes, in the folder nesting order of a run directory.
GRID_AXES: tuple[str, ...] = ("init", "compositor", "mip", "poses", "views", "seed")
#: Axes whose values are integers (parsed back to int from folder names).
INT_AXES: tuple[str, ...] = ("views", "seed")


def normalise_mip(value: Any) -> str:
    """The ``mip`` axis value as a folder label.

    Parameters
    ----------
    value : bool or str
        ``True``/``"on"`` or ``False``/``"off"`` (YAML 1.1 reads a bare on/off as a boolean).

    Returns
    -------
    str
        ``"on"`` or ``"off"``.

    Raises
    ------
    CtsplatError
        For any other value.

    Examples
    --------
    >>> normalise_mip(True), normalise_mip("off")
    ('on', 'off')
    """
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
    axes : mapping of str to sequence
        Axis name -> list of values, for every name in :data:`GRID_AXES`.
    volumes : sequence of str
        Volume names.
    exclude : sequence of mappings
        Each entry maps axis names (or ``volume``) to a value or a list of values; a cell is dropped when it
        matches every key of an entry.

    Returns
    -------
    pandas.DataFrame
        Columns ``volume, *GRID_AXES`` (``mip`` as ``"on"``/``"off"``, ``views``/``seed`` int), one row per run,
        in product order.

    Raises
    ------
    CtsplatError
        When an axis is missing or the grid expands to zero runs.

    Examples
    --------
    >>> axes = {"init": ["fbp", "random"], "compositor": ["radiative"], "mip": [True], "poses": ["gt"],
    ...         "views": [50], "seed": [0]}
    >>> expand_grid(axes, ["head"], exclude=[{"init": "random"}])
      volume init compositor mip poses  views  seed
    0   head  fbp  radiative  on    gt     50     0
    """
    import pandas as pd

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
    return df.astype(dict.fromkeys(INT_AXES, int)).reset_index(drop=True)


def needs_sfm(runs: Any, *, enabled: bool = False) -> bool:
    """Whether SfM must run for these grid cells: when ``enabled`` or when a cell uses COLMAP poses or SfM points.

    Parameters
    ----------
    runs : pandas.DataFrame
        Grid cells (:func:`expand_grid`), e.g. those of one volume.
    enabled : bool
        The ``sfm.enabled`` setting.

    Returns
    -------
    bool
    """
    return bool(enabled) or bool(((runs["poses"] == "colmap") | (runs["init"] == "sfm")).any())


def run_relpath(row: Mapping[str, Any]) -> str:
    """Run folder of one grid cell, relative to ``results/{volume}/runs``.

    Parameters
    ----------
    row : mapping
        A value for every axis in :data:`GRID_AXES` (e.g. a row of :func:`expand_grid`).

    Returns
    -------
    str
        ``init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0`` (Snakemake Paramspace layout).

    Examples
    --------
    >>> run_relpath({"init": "fbp", "compositor": "radiative", "mip": "on", "poses": "gt", "views": 50, "seed": 0})
    'init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0'
    """
    return "/".join(f"{a}~{row[a]}" for a in GRID_AXES)


def parse_run_dir(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The grid cell of a run folder ``.../{volume}/runs/init~x/.../seed~0`` (inverse of :func:`run_relpath`).

    Parameters
    ----------
    path : path-like
        The run folder.

    Returns
    -------
    dict
        Every axis of :data:`GRID_AXES` (``views`` and ``seed`` as int), and ``volume`` when the path has a
        ``runs`` component with a folder before it.

    Raises
    ------
    CtsplatError
        When a ``{axis}~{value}`` component is missing.

    Examples
    --------
    >>> parse_run_dir("results/head/runs/init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0")
    {'init': 'fbp', 'compositor': 'radiative', 'mip': 'on', 'poses': 'gt', 'views': 50, 'seed': 0, 'volume': 'head'}
    """
    parts = Path(path).parts
    out: dict[str, Any] = {}
    for p in parts:
        if "~" in p:
            key, _, val = p.partition("~")
            if key in GRID_AXES:
                out[key] = int(val) if key in INT_AXES else val
    missing = [a for a in GRID_AXES if a not in out]
    if missing:
        raise CtsplatError(f"{path}: not a run folder (no {missing[0]}~<value> component)")
    if "runs" in parts:
        i = len(parts) - 1 - parts[::-1].index("runs")
        if i >= 1:
            out["volume"] = parts[i - 1]
    return out
