"""The ablation grid: axis values expanded into runs, and run folders named after their grid cell.

A grid is the Cartesian product of the volumes and the values of every axis in :data:`GRID_AXES`, minus the
cells matched by ``grid.exclude``. Each run lives in a Paramspace-style folder
``results/{volume}/runs/init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0``.

The method's training features are optional axes (:data:`FEATURE_AXES`): a config that lists one under
``grid.axes`` adds it to every run folder after ``seed`` (``.../seed~0/augment~on``) and sets its training key per
run (:func:`train_overrides`); a config that lists none keeps the six-axis layout.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ctsplat.utils import CtsplatError, deep_update

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["GRID_AXES", "FEATURE_AXES", "ALL_AXES", "expand_grid", "normalise_mip", "run_axes", "run_relpath",
           "parse_run_dir", "needs_sfm", "cell_needs_sfm", "cells_need_sfm", "uses_colmap", "train_overrides",
           "with_train_overrides"]

#: The ablation axes every grid has, in the folder nesting order of a run directory.
GRID_AXES: tuple[str, ...] = ("init", "compositor", "mip", "poses", "views", "seed")
#: Optional axes (the method's training features) -> the dotted ``train`` key each sets; nested after ``seed`` in
#: this order when a config lists them.
FEATURE_AXES: dict[str, str] = {
    "augment": "augment.enabled",  # on | off
    "density_warmup": "lambda_density_warmup.factor",  # the factor (1: off)
    "densify": "densify.strategy",  # gradient | error | both
    "prune_redundant": "densify.prune_redundant.enabled",  # on | off
    "optimizer": "optimizer_preset",  # per_group | method
}
#: Every axis a run folder can have, in nesting order.
ALL_AXES: tuple[str, ...] = GRID_AXES + tuple(FEATURE_AXES)
#: Axes whose values are integers (parsed back to int from folder names).
INT_AXES: tuple[str, ...] = ("views", "seed")
#: Axes whose values are numbers (parsed back to float).
FLOAT_AXES: tuple[str, ...] = ("density_warmup",)
#: Axes whose values are on/off labels.
ONOFF_AXES: tuple[str, ...] = ("mip", "augment", "prune_redundant")


def run_axes(names: Any) -> tuple[str, ...]:
    """The axes of a grid or run: :data:`GRID_AXES` plus the optional :data:`FEATURE_AXES` that ``names`` holds.

    Parameters
    ----------
    names : iterable of str or mapping
        Axis names, e.g. ``grid.axes``, a row of :func:`expand_grid` or the columns of its table.

    Returns
    -------
    tuple of str
        In folder nesting order.

    Examples
    --------
    >>> run_axes({"init": [], "augment": ["on", "off"]})
    ('init', 'compositor', 'mip', 'poses', 'views', 'seed', 'augment')
    """
    present = set(names)
    return GRID_AXES + tuple(a for a in FEATURE_AXES if a in present)


def train_overrides(cell: Mapping[str, Any]) -> dict[str, Any]:
    """The ``train`` settings of a grid cell's feature axes, as a nested dict to merge into the train section.

    Parameters
    ----------
    cell : mapping
        A grid cell (folder labels: on/off as strings).

    Returns
    -------
    dict
        E.g. ``{"augment": {"enabled": True}, "densify": {"strategy": "error"}}``; empty without feature axes.

    Examples
    --------
    >>> train_overrides({"init": "fbp", "augment": "on", "density_warmup": "10"})
    {'augment': {'enabled': True}, 'lambda_density_warmup': {'factor': 10.0}}
    """
    out: dict[str, Any] = {}
    for axis, dotted in FEATURE_AXES.items():
        if axis not in cell:
            continue
        value = cell[axis]
        if axis in ONOFF_AXES:
            value = normalise_mip(value, axis) == "on"
        elif axis in FLOAT_AXES:
            value = float(value)
        else:
            value = str(value)
        node = out
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return out


def with_train_overrides(train: Mapping[str, Any], cell: Mapping[str, Any]) -> dict[str, Any]:
    """A ``train`` section with a grid cell's feature-axis settings (:func:`train_overrides`) merged in, key by key.

    Parameters
    ----------
    train : mapping
        The ``train`` section (not modified).
    cell : mapping
        A grid cell.

    Returns
    -------
    dict
        A new section; nested sections are merged, so the settings beside an overridden key stay.

    Examples
    --------
    >>> with_train_overrides({"densify": {"interval": 100, "strategy": "gradient"}}, {"densify": "error"})
    {'densify': {'interval': 100, 'strategy': 'error'}}
    """
    return deep_update(train, train_overrides(cell))


def normalise_mip(value: Any, axis: str = "mip") -> str:
    """An on/off axis value (``mip``, ``augment``, ``prune_redundant``) as a folder label.

    Parameters
    ----------
    value : bool or str
        ``True``/``"on"`` or ``False``/``"off"`` (YAML 1.1 reads a bare on/off as a boolean).
    axis : str
        The axis (for the error message).

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
    raise CtsplatError(f"invalid {axis} value {value!r}; allowed: on, off")


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
        Axis name -> list of values, for every name in :data:`GRID_AXES` and any of :data:`FEATURE_AXES`.
    volumes : sequence of str
        Volume names.
    exclude : sequence of mappings
        Each entry maps axis names (or ``volume``) to a value or a list of values; a cell is dropped when it
        matches every key of an entry.

    Returns
    -------
    pandas.DataFrame
        Columns ``volume, *run_axes(axes)`` (on/off axes as ``"on"``/``"off"``, ``views``/``seed`` int), one row
        per run, in product order.

    Raises
    ------
    CtsplatError
        When an axis is missing, lists one value twice (``mip: ["on", true]``), or the grid expands to zero runs.

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
    names = run_axes(axes)
    values = {a: list(axes[a]) for a in names}
    for a in ONOFF_AXES:
        if a in values:
            values[a] = [normalise_mip(v, a) for v in values[a]]
    for a in names:  # the schema's uniqueItems sees "on" and true as two values; they are one cell
        twice = next((v for i, v in enumerate(values[a]) if v in values[a][:i]), None)
        if twice is not None:
            raise CtsplatError(f"grid.axes.{a} lists {twice!r} twice (as {axes[a]!r}); every run would be made and "
                               "counted twice: keep one")
    rows = [dict(zip(("volume", *names), combo, strict=True))
            for combo in itertools.product(list(volumes), *(values[a] for a in names))]

    def norm(key: str, v: Any) -> Any:
        return normalise_mip(v, key) if key in ONOFF_AXES else v

    def excluded(row: dict[str, Any]) -> bool:
        return any(all(row[k] in [norm(k, v) for v in _as_list(vals)] for k, vals in entry.items())
                   for entry in exclude)

    kept = [r for r in rows if not excluded(r)]
    if not kept:
        raise CtsplatError(
            f"the ablation grid expands to zero runs ({len(rows)} cells, all removed by grid.exclude or no volumes); "
            "loosen grid.exclude or add axis values"
        )
    df = pd.DataFrame(kept, columns=["volume", *names])
    return df.astype(dict.fromkeys(INT_AXES, int)).reset_index(drop=True)


def needs_sfm(runs: Any, *, enabled: bool = False) -> bool:
    """Whether SfM must run for these grid cells: when ``enabled`` or when a cell uses COLMAP poses (``colmap``,
    ``colmap+refine``) or SfM points.

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
    return bool(enabled) or bool(cells_need_sfm(runs).any())


def cell_needs_sfm(cell: Mapping[str, Any]) -> bool:
    """Whether a grid cell trains on the SfM step's output: COLMAP poses (``colmap``, ``colmap+refine``) or SfM
    points (``init: sfm``).

    Parameters
    ----------
    cell : mapping
        A grid cell (its ``poses`` and ``init``).

    Returns
    -------
    bool

    Examples
    --------
    >>> cell_needs_sfm({"poses": "colmap+refine", "init": "fbp"}), cell_needs_sfm({"poses": "gt", "init": "sfm"})
    (True, True)
    """
    return uses_colmap(cell.get("poses")) or cell.get("init") == "sfm"


def cells_need_sfm(runs: Any) -> Any:
    """:func:`cell_needs_sfm` for every row of a table of grid cells.

    Parameters
    ----------
    runs : pandas.DataFrame
        Grid cells (``poses`` and ``init`` columns).

    Returns
    -------
    pandas.Series of bool
        Indexed like ``runs``.
    """
    import pandas as pd

    return pd.Series([cell_needs_sfm(r) for r in runs.to_dict("records")], index=runs.index, dtype=bool)


def uses_colmap(poses: Any) -> bool:
    """Whether a ``poses`` value trains on the poses SfM recovered (``colmap``, ``colmap+refine``).

    Parameters
    ----------
    poses : str
        A ``poses`` axis value.

    Returns
    -------
    bool

    Examples
    --------
    >>> uses_colmap("colmap+refine"), uses_colmap("perturbed")
    (True, False)
    """
    return str(poses).removesuffix("+refine") == "colmap"


def run_relpath(row: Mapping[str, Any]) -> str:
    """Run folder of one grid cell, relative to ``results/{volume}/runs``.

    Parameters
    ----------
    row : mapping
        A value for every axis in :data:`GRID_AXES` and any of :data:`FEATURE_AXES` (e.g. a row of
        :func:`expand_grid`).

    Returns
    -------
    str
        ``init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0`` (Snakemake Paramspace layout).

    Examples
    --------
    >>> run_relpath({"init": "fbp", "compositor": "radiative", "mip": "on", "poses": "gt", "views": 50, "seed": 0})
    'init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0'
    """
    return "/".join(f"{a}~{row[a]}" for a in run_axes(row))


def parse_run_dir(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The grid cell of a run folder ``.../{volume}/runs/init~x/.../seed~0`` (inverse of :func:`run_relpath`).

    Parameters
    ----------
    path : path-like
        The run folder.

    Returns
    -------
    dict
        Every axis of :data:`GRID_AXES` (``views`` and ``seed`` as int), the :data:`FEATURE_AXES` the folder has,
        and ``volume`` when the path has a ``runs`` component with a folder before it.

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
            if key in ALL_AXES:
                try:
                    out[key] = int(val) if key in INT_AXES else float(val) if key in FLOAT_AXES else val
                except ValueError:
                    kind = "an integer" if key in INT_AXES else "a number"
                    raise CtsplatError(f"{path}: not a run folder ({p}: {key} must be {kind}); point at the "
                                       "workflow's results folder or a run folder in it") from None
    missing = [a for a in GRID_AXES if a not in out]
    if missing:
        raise CtsplatError(f"{path}: not a run folder (no {missing[0]}~<value> component); point at the workflow's "
                           "results folder or a run folder in it")
    if "runs" in parts:
        i = len(parts) - 1 - parts[::-1].index("runs")
        if i >= 1:
            out["volume"] = parts[i - 1]
    return out
