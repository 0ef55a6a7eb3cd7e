"""Figures of one evaluated run: a gallery of held-out projections, central slices, a turntable GIF."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.utils import atomic_path

__all__ = ["save_gallery", "save_slices", "save_turntable"]


def _imshow_row(axes: Any, images: list[np.ndarray], titles: list[str], cmaps: list[str],
                limits: list[tuple[float, float]], unit: str) -> None:
    for ax, im, title, cmap, (lo, hi) in zip(axes, images, titles, cmaps, limits, strict=True):
        h = ax.imshow(im, cmap=cmap, vmin=lo, vmax=hi)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
        ax.figure.colorbar(h, ax=ax, fraction=0.046, pad=0.02).set_label(unit, fontsize=7)


def _save_fig(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format=path.suffix.lstrip("."))
    plt.close(fig)


def save_gallery(path: str | Path, refs: np.ndarray, preds: np.ndarray, ids: list[int],
                 psnrs: np.ndarray, max_views: int = 6) -> None:
    """Write a PNG gallery: one row per test view, columns reference | render | signed error.

    At most ``max_views`` rows, spread evenly over the views. Reference and render share the reference's grey
    range; the error map is symmetric about 0.

    Parameters
    ----------
    path : str or Path
        Output PNG (written atomically).
    refs, preds : ndarray, shape (V, H, W)
        Reference and rendered line integrals (mm, normalised-volume units).
    ids : list of int, length V
        View ids, for the titles.
    psnrs : ndarray, shape (V,)
        Per-view PSNR (dB), for the titles.
    max_views : int
        Most rows.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(max_views, len(refs))
    pick = np.linspace(0, len(refs) - 1, n).round().astype(int) if n else []
    fig, axes = plt.subplots(n, 3, figsize=(9, 2.8 * n), squeeze=False)
    for row, i in enumerate(pick):
        ref, pred = refs[i], preds[i]
        lo, hi = float(ref.min()), float(ref.max())
        err = pred - ref
        e = float(np.abs(err).max()) or 1.0
        _imshow_row(axes[row], [ref, pred, err],
                    [f"view {ids[i]} reference", f"render ({psnrs[i]:.1f} dB)", "error (render - ref)"],
                    ["gray", "gray", "RdBu_r"], [(lo, hi), (lo, hi), (-e, e)], "line integral (normalised μ × mm)")
    fig.tight_layout()
    _save_fig(fig, Path(path))


def save_slices(path: str | Path, model_vol: np.ndarray, reference: np.ndarray) -> None:
    """Write a PNG of the central sagittal (i), coronal (j) and axial (k) slices: reference | model | error.

    Grey range [0, 1] (normalised volumes), error range [-0.5, 0.5].

    Parameters
    ----------
    path : str or Path
        Output PNG (written atomically).
    model_vol, reference : ndarray, shape (I, J, K)
        Voxelised model and reference, normalised.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 3, figsize=(9, 8.4), squeeze=False)
    names = ["sagittal (i)", "coronal (j)", "axial (k)"]
    for axis in range(3):
        c = reference.shape[axis] // 2
        ref = np.take(reference, c, axis=axis).T[::-1]
        mod = np.take(model_vol, c, axis=axis).T[::-1]
        _imshow_row(axes[axis], [ref, mod, mod - ref],
                    [f"{names[axis]} reference", "model", "error (model - ref)"],
                    ["gray", "gray", "RdBu_r"], [(0.0, 1.0), (0.0, 1.0), (-0.5, 0.5)], "normalised μ")
    fig.tight_layout()
    _save_fig(fig, Path(path))


def save_turntable(path: str | Path, frames: np.ndarray, *, fps: float = 12.0) -> None:
    """Write a looping animated GIF of novel projections, scaled together by the stack's range to 8 bits.

    Parameters
    ----------
    path : str or Path
        Output GIF (written atomically).
    frames : ndarray, shape (n, H, W)
        The projections, in playback order.
    fps : float
        Frames per second.
    """
    import imageio.v3 as iio

    lo, hi = float(frames.min()), float(frames.max())
    u8 = np.clip((frames - lo) / ((hi - lo) or 1.0) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    path = Path(path)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, u8, extension=".gif", duration=1000.0 / fps, loop=0)
