"""Evaluation of a Gaussian model: held-out projections, voxelised 3D metrics, figures, speed and memory.

2D metrics are computed on line-integral images of the *normalised* volume (the training targets divided by
``mu_scale_per_mm``), PSNR/SSIM with each reference image's own range (``ctsplat.metrics``). 3D metrics compare
the model voxelised on the reference grid with the normalised reference volume (data range 1). LPIPS uses
``ctsplat.metrics.lpips_distance`` and is ``None`` with a recorded reason when it cannot be computed.

:func:`evaluate` recomputes ``metrics.json``-style test metrics for a finished run folder.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat import metrics
from ctsplat.utils import CtsplatError, atomic_path

__all__ = [
    "render_views",
    "view_metrics",
    "voxelize_model",
    "volume_metrics",
    "milestones",
    "peak_memory_mb",
    "forward_fps",
    "orbit_poses",
    "save_gallery",
    "save_slices",
    "save_turntable",
    "evaluate",
]

log = logging.getLogger(__name__)


def render_views(
    gaussians: Any,
    camera: Any,
    Rs: np.ndarray,
    ts: np.ndarray,
    render_kwargs: dict[str, Any] | None = None,
) -> np.ndarray:
    """Render views without gradient.

    Parameters
    ----------
    gaussians : ctsplat.gaussians.Gaussians
    camera : ParallelCamera | ConeCamera
    Rs : (V, 3, 3), ts : (V, 3)
        World-to-camera poses (mm).
    render_kwargs : dict
        Passed to :func:`ctsplat.render.render` (compositor, filter_3d_var, mip_2d).

    Returns
    -------
    ndarray, shape (V, H, W), float32
    """
    from ctsplat.render import render

    kw = dict(render_kwargs or {})
    dev, dt = gaussians.means.device, gaussians.means.dtype
    out = []
    with torch.no_grad():
        for R, t in zip(np.asarray(Rs), np.asarray(ts), strict=True):
            img = render(gaussians, camera, torch.as_tensor(R, dtype=dt, device=dev),
                         torch.as_tensor(t, dtype=dt, device=dev), **kw).image
            if img.ndim == 3:
                img = img.mean(-1)
            out.append(img.detach().float().cpu().numpy())
    return np.stack(out) if out else np.zeros((0, camera.height, camera.width), np.float32)


def view_metrics(preds: np.ndarray, refs: np.ndarray, *, with_lpips: bool = False) -> dict[str, np.ndarray | list]:
    """Per-view PSNR / SSIM (and optionally LPIPS) of predicted vs reference images.

    Returns
    -------
    dict with ``psnr2d`` (V,), ``ssim2d`` (V,), and if ``with_lpips`` ``lpips`` (list of float | None) and
    ``lpips_reason`` (str | None).
    """
    if preds.shape != refs.shape:
        raise ValueError(f"prediction shape {preds.shape} != reference shape {refs.shape}")
    ps = np.array([metrics.psnr(p, r) for p, r in zip(preds, refs, strict=True)])
    ss = np.array([metrics.ssim2d(p, r) for p, r in zip(preds, refs, strict=True)])
    out: dict[str, Any] = {"psnr2d": ps, "ssim2d": ss}
    if with_lpips:
        vals, reason = [], None
        for p, r in zip(preds, refs, strict=True):
            v, why = metrics.lpips_distance(p, r)
            vals.append(v)
            reason = reason or why
        out["lpips"] = vals
        out["lpips_reason"] = reason
    return out


def voxelize_model(gaussians: Any, shape: tuple[int, int, int], affine: np.ndarray,
                   filter_3d_var: torch.Tensor | None = None) -> np.ndarray:
    """The model's density field at the voxel centres of a grid, shape ``shape``, float32 (no gradient)."""
    from ctsplat.render import voxelize

    with torch.no_grad():
        vol = voxelize(gaussians, tuple(shape), torch.as_tensor(np.asarray(affine, float), dtype=gaussians.means.dtype,
                                                               device=gaussians.means.device),
                       filter_3d_var=filter_3d_var)
    return vol.float().cpu().numpy()


def volume_metrics(model_vol: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """``psnr3d`` (whole normalised volume, range 1) and ``ssim3d`` (mean 2D SSIM over the three axes)."""
    return {"psnr3d": metrics.psnr3d(model_vol, reference), "ssim3d": metrics.ssim3d(model_vol, reference)}


def milestones(log_rows: list[dict[str, Any]], *, psnr_target: float = 30.0, ssim_target: float = 0.90
               ) -> dict[str, float | None]:
    """Time (s) and iteration at which the logged validation PSNR2D / SSIM2D first reached the targets.

    ``None`` when never reached. ``log_rows`` are ``train_log.csv`` rows (dicts with ``iteration``,
    ``timestamp``, ``psnr2d``, ``ssim2d``) in iteration order.
    """
    out: dict[str, float | None] = {
        "time_to_psnr2d_30_s": None, "iter_to_psnr2d_30": None, "time_to_ssim2d_090_s": None,
        "iter_to_ssim2d_090": None,
    }
    for row in log_rows:
        p, s = float(row["psnr2d"]), float(row["ssim2d"])
        if out["time_to_psnr2d_30_s"] is None and math.isfinite(p) and p >= psnr_target:
            out["time_to_psnr2d_30_s"] = float(row["timestamp"])
            out["iter_to_psnr2d_30"] = int(row["iteration"])
        if out["time_to_ssim2d_090_s"] is None and math.isfinite(s) and s >= ssim_target:
            out["time_to_ssim2d_090_s"] = float(row["timestamp"])
            out["iter_to_ssim2d_090"] = int(row["iteration"])
    return out


def peak_memory_mb(device: torch.device) -> tuple[float, str]:
    """Peak memory in MiB and its kind: CUDA max allocated on a GPU, else the process's peak RSS."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20, "cuda_max_allocated"
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "process_peak_rss"


def scaled_camera(camera: Any, width: int, height: int) -> Any:
    """The same detector field of view resampled to ``width × height`` pixels (covers the original FOV)."""
    f = max(camera.width / width, camera.height / height)
    if camera.model == "parallel":
        return dataclasses.replace(camera, width=width, height=height, spacing_mm=camera.spacing_mm * f)
    return dataclasses.replace(camera, width=width, height=height, pitch_mm=camera.pitch_mm * f)


def forward_fps(gaussians: Any, camera: Any, R: np.ndarray, t: np.ndarray, render_kwargs: dict[str, Any],
                *, width: int = 1920, height: int = 1080, repeats: int = 2) -> float:
    """Frames per second of a forward render at ``width × height`` (median of ``repeats`` after one warm-up)."""
    cam = scaled_camera(camera, width, height)
    dev = gaussians.means.device
    times = []
    for i in range(repeats + 1):
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        t0 = time.perf_counter()
        render_views(gaussians, cam, np.asarray(R)[None], np.asarray(t)[None], render_kwargs)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        if i:
            times.append(time.perf_counter() - t0)
    return float(1.0 / np.median(times))


def orbit_poses(R0: np.ndarray, t0: np.ndarray, center_mm: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` poses turning the scene about the axis through ``center_mm`` along the camera's up direction.

    Rotating the world by ``Q`` about ``c`` (``x' = Q(x - c) + c``) seen by ``(R0, t0)`` equals the camera
    ``R = R0 Q``, ``t = t0 + R0 (c - Q c)``. The axis is ``-R0[1]`` (image up), so for a circular CT orbit the
    turntable is a rotation about the scanner axis. Works for any camera model.

    Returns
    -------
    Rs : (n, 3, 3), ts : (n, 3)
    """
    from scipy.spatial.transform import Rotation

    axis = -np.asarray(R0, float)[1]
    c = np.asarray(center_mm, float)
    Rs, ts = [], []
    for k in range(n):
        Q = Rotation.from_rotvec(axis * 2 * np.pi * k / n).as_matrix()
        Rs.append(R0 @ Q)
        ts.append(t0 + R0 @ (c - Q @ c))
    return np.stack(Rs), np.stack(ts)


def _imshow_row(axes: Any, images: list[np.ndarray], titles: list[str], cmaps: list[str],
                limits: list[tuple[float, float]]) -> None:
    for ax, im, title, cmap, (lo, hi) in zip(axes, images, titles, cmaps, limits, strict=True):
        h = ax.imshow(im, cmap=cmap, vmin=lo, vmax=hi)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
        ax.figure.colorbar(h, ax=ax, fraction=0.046, pad=0.02)


def _save_fig(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format=path.suffix.lstrip("."))
    plt.close(fig)


def save_gallery(path: str | Path, refs: np.ndarray, preds: np.ndarray, ids: list[int],
                 psnrs: np.ndarray, max_views: int = 6) -> None:
    """PNG gallery: one row per test view, columns reference | render | signed error."""
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
                    ["gray", "gray", "RdBu_r"], [(lo, hi), (lo, hi), (-e, e)])
    fig.tight_layout()
    _save_fig(fig, Path(path))


def save_slices(path: str | Path, model_vol: np.ndarray, reference: np.ndarray) -> None:
    """PNG of the central axial (k), coronal (j) and sagittal (i) slices: reference | model | error."""
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
                    ["gray", "gray", "RdBu_r"], [(0.0, 1.0), (0.0, 1.0), (-0.5, 0.5)])
    fig.tight_layout()
    _save_fig(fig, Path(path))


def save_turntable(path: str | Path, frames: np.ndarray, *, fps: float = 12.0) -> None:
    """Animated GIF (looping) of novel projections ``(n, H, W)``, each scaled by the stack's range to 8 bits."""
    import imageio.v3 as iio

    lo, hi = float(frames.min()), float(frames.max())
    u8 = np.clip((frames - lo) / ((hi - lo) or 1.0) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    path = Path(path)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, u8, extension=".gif", duration=1000.0 / fps, loop=0)


def evaluate(run_dir: str | Path, *, split: str = "test", device: str = "auto", write: bool = True
             ) -> dict[str, Any]:
    """Re-evaluate a finished training run on a split of its radiographs.

    Reads ``run_dir/config.json`` (written by :func:`ctsplat.train.train`) and ``run_dir/model.pt``; renders the
    split's views, voxelises the model and returns (and with ``write``, stores as ``run_dir/eval_{split}.json``)
    PSNR/SSIM/LPIPS 2D and PSNR/SSIM 3D.
    """
    from ctsplat import train as train_mod
    from ctsplat.gaussians import Gaussians
    from ctsplat.utils import json_safe, resolve_device, write_json_atomic

    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    model_path = run_dir / "model.pt"
    if not cfg_path.exists() or not model_path.exists():
        raise CtsplatError(f"{run_dir} is not a finished training run (needs config.json and model.pt); run "
                           "`ctsplat train` first")
    cfg = json.loads(cfg_path.read_text())["config"]
    dev = resolve_device(device)
    scene = train_mod.load_scene(cfg)
    g = Gaussians.load(model_path, device=dev)
    sel = {"test": scene.test, "val": scene.val, "train": scene.train}.get(split)
    if sel is None:
        raise CtsplatError(f"unknown split {split!r}; allowed: test, val, train")
    rk = train_mod.render_kwargs(cfg, g, scene)
    preds = render_views(g, sel.camera, sel.Rs, sel.ts, rk)
    vm = view_metrics(preds, sel.images, with_lpips=True)
    vol = voxelize_model(g, scene.volume.shape, scene.volume.affine, rk.get("filter_3d_var"))
    res = {
        "split": split,
        "n_views": len(sel.ids),
        "psnr2d": float(np.mean(vm["psnr2d"])),
        "ssim2d": float(np.mean(vm["ssim2d"])),
        "lpips": None if any(v is None for v in vm["lpips"]) else float(np.mean(vm["lpips"])),
        "lpips_reason": vm["lpips_reason"],
        **volume_metrics(vol, scene.volume.data),
        "n_gaussians": len(g),
        "uses_reference_volume": cfg["init"] == "volume",
    }
    if write:
        write_json_atomic(run_dir / f"eval_{split}.json", json_safe(res))
    return res


def model_size_bytes(*paths: str | Path) -> int:
    """Total size on disk of the given files (missing ones count 0)."""
    return int(sum(os.path.getsize(p) for p in paths if os.path.exists(p)))
