"""Overview figures of the report's data, radiographs and SfM sections (matplotlib, headless).

Each ``plot_*`` function takes arrays or DataFrames, writes one PNG atomically and returns the matplotlib Figure
(closed, so tests can inspect titles and colours without a display). The ``*_figure`` functions read the workflow's
files (``volume.nii.gz``, a radiographs folder, an ``sfm`` folder) and call them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from ctsplat.utils import CtsplatError, atomic_path, read_json_object  # noqa: E402

__all__ = [
    "plot_volume_slices",
    "plot_contact_sheet",
    "plot_sfm",
    "sfm_title",
    "volume_figure",
    "radiographs_figure",
    "sfm_figure",
    "FAILED_COLOUR",
]

#: Title colour of a failed SfM run.
FAILED_COLOUR = "red"
_POSES_COLUMNS = ("view_id", "azimuth_deg", "registered", "rot_err_deg")


def _save(fig: plt.Figure, out: str | os.PathLike[str]) -> plt.Figure:
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return fig


def plot_volume_slices(data: np.ndarray, out: str | os.PathLike[str], *, spacing_mm: Sequence[float] = (1, 1, 1),
                       title: str = "", unit: str = "normalised attenuation (0-1)") -> plt.Figure:
    """Three orthogonal central slices of a volume on one shared grey scale, with a colour bar in ``unit``.

    Parameters
    ----------
    data : ndarray (I, J, K)
        The volume (voxel values in ``unit``).
    out : path
        PNG to write.
    spacing_mm : sequence of 3 floats
        Voxel size along I, J, K (mm), so the slices have their physical aspect ratio.
    title : str
        Figure title (e.g. the volume name).
    unit : str
        Label of the colour bar.

    Returns
    -------
    matplotlib.figure.Figure
    """
    data = np.asarray(data, dtype=np.float32)
    if data.ndim != 3 or min(data.shape) < 1:
        raise CtsplatError(f"plot_volume_slices needs a 3-D volume, got shape {data.shape}")
    sx, sy, sz = (float(s) for s in spacing_mm)
    ci, cj, ck = (n // 2 for n in data.shape)
    finite = data[np.isfinite(data)]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if vmax <= vmin:
        vmax = vmin + 1.0
    # (slice, name, aspect = row spacing / column spacing after the transpose that puts the first axis across)
    panels = [(data[ci, :, :].T, f"I = {ci} (J across, K up)", sz / sy),
              (data[:, cj, :].T, f"J = {cj} (I across, K up)", sz / sx),
              (data[:, :, ck].T, f"K = {ck} (I across, J up)", sy / sx)]
    fig, axes = plt.subplots(1, 3, figsize=(11, 4), constrained_layout=True)
    im = None
    for ax, (img, name, aspect) in zip(axes, panels, strict=True):
        im = ax.imshow(img, cmap="gray", vmin=vmin, vmax=vmax, origin="lower", aspect=aspect)
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=list(axes), shrink=0.85, label=unit)
    if title:
        fig.suptitle(title)
    return _save(fig, out)


def plot_contact_sheet(images: np.ndarray, out: str | os.PathLike[str], *, labels: Sequence[str] | None = None,
                       title: str = "", unit: str = "line integral (dimensionless)", max_images: int = 16
                       ) -> plt.Figure:
    """A grid of up to ``max_images`` radiographs, evenly chosen, on one shared scale with a colour bar.

    Parameters
    ----------
    images : ndarray (V, H, W)
        Radiographs (line integrals).
    out : path
        PNG to write.
    labels : sequence of str, optional
        One label per image (e.g. view id and azimuth), drawn above it.
    title : str
        Figure title.
    unit : str
        Label of the colour bar.
    max_images : int
        At most this many images (evenly spaced over the stack).

    Returns
    -------
    matplotlib.figure.Figure
    """
    images = np.asarray(images, dtype=np.float32)
    if images.ndim == 2:
        images = images[None]
    if images.ndim != 3 or images.shape[0] == 0:
        raise CtsplatError(f"plot_contact_sheet needs a (V, H, W) stack of at least one image, got {images.shape}")
    n_total = images.shape[0]
    pick = np.unique(np.floor(np.arange(min(max_images, n_total)) * n_total / min(max_images, n_total)).astype(int))
    cols = math.ceil(math.sqrt(len(pick)))
    rows = math.ceil(len(pick) / cols)
    finite = images[pick][np.isfinite(images[pick])]
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if vmax <= vmin:
        vmax = vmin + 1.0
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols + 1.2, 2.2 * rows + 0.5), squeeze=False,
                             constrained_layout=True)
    im = None
    for k, ax in enumerate(axes.ravel()):
        ax.set_axis_off()
        if k >= len(pick):
            continue
        im = ax.imshow(images[pick[k]], cmap="gray", vmin=vmin, vmax=vmax)
        if labels is not None:
            ax.set_title(labels[pick[k]], fontsize=8)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label=unit)
    fig.suptitle(title or f"{len(pick)} of {n_total} views")
    return _save(fig, out)


def sfm_title(summary: dict[str, Any]) -> tuple[str, str]:
    """Title and colour of the SfM figure: ``SfM OK: median x deg`` (black) or ``SfM FAILED: reason`` (red)."""
    if summary.get("ok", False):
        med = summary.get("rot_err_deg_median")
        med_s = f"{med:.2f}" if med is not None else "n/a"
        return (f"SfM OK: median rotation error {med_s} deg, registered "
                f"{summary.get('n_registered', '?')}/{summary.get('n_views', '?')} views"), "black"
    return f"SfM FAILED: {summary.get('reason', 'no reason recorded')}", FAILED_COLOUR


def plot_sfm(poses: pd.DataFrame, summary: dict[str, Any], out: str | os.PathLike[str]) -> plt.Figure:
    """Per-view rotation error against azimuth, registered and unregistered views, with the SfM verdict as title.

    Parameters
    ----------
    poses : DataFrame
        ``poses.csv`` of the sfm step: ``view_id``, ``azimuth_deg``, ``registered``, ``rot_err_deg`` (and
        optionally ``centre_err_mm``, ``plausible``).
    summary : dict
        ``summary.json`` of the sfm step (``ok``, ``reason``, ``rot_err_deg_median``, ...).
    out : path
        PNG to write.

    Returns
    -------
    matplotlib.figure.Figure
        Its suptitle is :func:`sfm_title` in that colour (red when SfM failed).
    """
    missing = [c for c in _POSES_COLUMNS if c not in poses.columns]
    if missing:
        raise CtsplatError(f"poses table lacks columns {missing}; re-run the sfm step")
    df = poses.sort_values("azimuth_deg")
    reg = df["registered"].astype(bool) & np.isfinite(df["rot_err_deg"].astype(float))
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True, height_ratios=[3, 1],
                                  constrained_layout=True)
    if reg.any():
        ax.plot(df.loc[reg, "azimuth_deg"], df.loc[reg, "rot_err_deg"], "o-", ms=4, lw=0.8, color="C0",
                label="registered view")
        ax.set_yscale("log")
        med = float(np.median(df.loc[reg, "rot_err_deg"]))
        ax.axhline(med, color="C0", ls="--", lw=0.8, label=f"median {med:.2f} deg")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no view registered", ha="center", va="center", transform=ax.transAxes,
                color=FAILED_COLOUR)
    ax.set_ylabel("rotation error (deg)")
    ax2.scatter(df.loc[reg, "azimuth_deg"], np.ones(int(reg.sum())), marker="|", s=150, color="C2",
                label=f"registered ({int(reg.sum())})")
    ax2.scatter(df.loc[~reg, "azimuth_deg"], np.zeros(int((~reg).sum())), marker="|", s=150, color=FAILED_COLOUR,
                label=f"not registered ({int((~reg).sum())})")
    ax2.set_yticks([0, 1], ["no", "yes"])
    ax2.set_ylim(-0.5, 1.5)
    ax2.set_ylabel("registered")
    ax2.set_xlabel("azimuth (deg)")
    ax2.legend(fontsize=8, loc="center right")
    text, colour = sfm_title(summary)
    fig.suptitle(text, color=colour, fontsize=10, wrap=True)
    return _save(fig, out)


def volume_figure(volume_path: str | os.PathLike[str], out: str | os.PathLike[str], *, title: str = ""
                  ) -> plt.Figure:
    """:func:`plot_volume_slices` of an ingested ``volume.nii.gz``, the colour bar in its intensity's unit."""
    from ctsplat.formats.volume import load_volume

    vol = load_volume(volume_path)
    return plot_volume_slices(vol.data, out, spacing_mm=vol.spacing_mm, title=title or Path(volume_path).parent.name,
                              unit=vol.unit)


def radiographs_figure(radiographs_dir: str | os.PathLike[str], out: str | os.PathLike[str], *,
                       split: str | None = "train", max_images: int = 16, title: str = "") -> plt.Figure:
    """:func:`plot_contact_sheet` of a radiographs folder's views of one split (``None``: all views)."""
    from ctsplat.formats.viewset import load_radiographs

    images, vs = load_radiographs(radiographs_dir)
    rows = [i for i, v in enumerate(vs.views) if split is None or v.split == split]
    if not rows:
        raise CtsplatError(f"{radiographs_dir}/views.json has no {split} views; re-render the radiographs")
    labels = [f"view {vs.views[i].id}, az {vs.views[i].azimuth_deg:.0f} deg" for i in rows]
    what = f"{split} views" if split else "views"
    return plot_contact_sheet(images[rows], out, labels=labels, max_images=max_images,
                              title=title or f"{Path(radiographs_dir).name}: {min(max_images, len(rows))} of "
                                             f"{len(rows)} {what}")


def sfm_figure(sfm_dir: str | os.PathLike[str], out: str | os.PathLike[str]) -> plt.Figure:
    """:func:`plot_sfm` of an sfm folder (``poses.csv`` and ``summary.json``)."""
    sfm_dir = Path(sfm_dir)
    summary = read_json_object(sfm_dir / "summary.json", what="SfM summary", fix="run the sfm step again")
    return plot_sfm(pd.read_csv(sfm_dir / "poses.csv"), summary, out)
