"""Held-out metrics of a photo run: PSNR/SSIM per view, LPIPS where available, FPS, peak memory, a gallery of
held-out renders beside the photographs, and a turntable around the scene.

PSNR uses data range 1 on renders clipped to [0, 1]; SSIM is the Gaussian-window SSIM (σ 1.5, 3DGS's window;
:func:`ctsplat.training.losses.ssim`) averaged over RGB; it averages the map over the pixels whose window lies
inside the image, where 3DGS's ``ssim`` zero-pads the border and averages over every pixel, so it reads
0.001–0.01 lower than 3DGS would on the same images. LPIPS (AlexNet, RGB mapped to [-1, 1]) is the mean over the
held-out views, or ``null`` with the reason when the ``lpips`` package or its weights cannot be loaded
(:func:`ctsplat.evaluation.metrics.lpips_status`). Every figure carries
the photographs' attribution line (``photos.evaluate.attribution``).

The held-out views are the test photos, or the validation photos of a run trained with ``holdout: validation``
(``metrics.json``'s ``held_out`` and the per-view ``split`` say which). Renders composite over the model's
background colour (``meta["background"]``).

Outputs in the run folder: ``metrics.json``, ``per_view_test.csv`` (the CT runs' per-view columns, with the
image name as ``view_id``), ``figures/gallery.png`` and ``figures/turntable.gif``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat.evaluation.metrics import lpips_distance, lpips_status
from ctsplat.formats.runlog import PER_VIEW_COLUMNS, CsvLog
from ctsplat.geometry.cameras import camera_center, look_at
from ctsplat.photos.config import SFM_SUMMARY_KEYS, held_out_split, photo_settings
from ctsplat.photos.dataset import PhotoScene, PhotoView, load_scene
from ctsplat.photos.train import image_metrics, peak_memory, render_view, reset_gpu_peak
from ctsplat.splat.gaussians import Gaussians
from ctsplat.utils import (
    CtsplatError,
    atomic_path,
    code_version,
    compute_platform,
    json_safe,
    read_json_object,
    resolve_device,
    write_json_atomic,
)

__all__ = ["evaluate_photos", "run_config", "run_scene", "turntable_poses", "save_photo_gallery", "save_turntable_gif"]

log = logging.getLogger(__name__)


def turntable_poses(views: list[PhotoView], n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` world->camera poses on a circle around the scene, at the photographs' mean height and distance.

    The circle's axis is the mean camera "up" (``-y`` of the OpenCV camera frames); its centre is the point
    nearest to all optical axes (least squares).

    Parameters
    ----------
    views : list of PhotoView
        At least two, with distinct optical axes.
    n : int
        Frames.

    Returns
    -------
    list of (ndarray (3, 3), ndarray (3,))
    """
    Rs = np.stack([v.R for v in views])
    C = camera_center(Rs, np.stack([v.t for v in views]))
    up = -Rs[:, 1].mean(0)
    up /= np.linalg.norm(up)
    d = Rs[:, 2]
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, di in zip(C, d, strict=True):
        P = np.eye(3) - np.outer(di, di)
        A += P
        b += P @ c
    target = np.linalg.lstsq(A, b, rcond=None)[0]
    rel = C - target
    h = float(np.mean(rel @ up))
    flat = rel - np.outer(rel @ up, up)
    r = float(np.mean(np.linalg.norm(flat, axis=1)))
    e1 = flat[0] / max(np.linalg.norm(flat[0]), 1e-12)
    e2 = np.cross(up, e1)
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        centre = target + h * up + r * (np.cos(a) * e1 + np.sin(a) * e2)
        poses.append(look_at(centre, target, up))
    return poses


def _footer(attribution: str) -> str:
    """The credit line under every figure; it says how the photographs were changed (CC BY asks for that)."""
    credit = attribution or "(no attribution given)"
    return f"Photographs: {credit} (undistorted and downscaled here; the renders are of a model trained on them)"


def save_photo_gallery(path: str | Path, photos: list[np.ndarray], renders: list[np.ndarray], names: list[str],
                       psnrs: list[float], attribution: str) -> None:
    """A PNG with one row per held-out view: photograph | render, the attribution line at the bottom.

    Parameters
    ----------
    path : str or Path
        Output PNG (atomic write).
    photos, renders : lists of ndarray (H, W, 3) in [0, 1]
    names : list of str
    psnrs : list of float
    attribution : str
        Credit line of the photographs.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(photos)
    h, w = photos[0].shape[:2]
    fig, axes = plt.subplots(n, 2, figsize=(2 * 3.2, n * 3.2 * h / w + 0.6), squeeze=False)
    for i in range(n):
        for j, (im, title) in enumerate(((photos[i], f"photo {names[i]} (held out)"),
                                         (renders[i], f"render, PSNR {psnrs[i]:.2f} dB"))):
            axes[i, j].imshow(np.clip(im, 0, 1))
            axes[i, j].set_title(title, fontsize=8)
            axes[i, j].axis("off")
    fig.text(0.5, 0.005, _footer(attribution), ha="center", va="bottom", fontsize=6, wrap=True)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def wrap_to_width(text: str, width_px: float, measure: Any) -> list[str]:
    """Break ``text`` into lines no wider than ``width_px`` (at spaces; a word wider than a line is cut).

    Parameters
    ----------
    text : str
    width_px : float
        Widest line, in the units of ``measure``.
    measure : callable(str) -> float
        Drawn width of a string (e.g. ``ImageDraw.textlength``).

    Returns
    -------
    list of str
        The lines; joined with spaces they give ``text`` again (with single spaces; cut words without one).

    Examples
    --------
    >>> wrap_to_width("a bb ccc", 3, len)
    ['a', 'bb', 'ccc']
    """
    lines: list[str] = []
    line = ""
    for word in text.split():
        while measure(word) > width_px and len(word) > 1:  # cut the longest head that fits (at least one char)
            k = max((i for i in range(1, len(word) + 1) if measure(word[:i]) <= width_px), default=1)
            if line:
                lines.append(line)
                line = ""
            lines.append(word[:k])
            word = word[k:]
        candidate = f"{line} {word}" if line else word
        if line and measure(candidate) > width_px:
            lines.append(line)
            line = word
        else:
            line = candidate
    if line:
        lines.append(line)
    return lines


def footer_font(size_px: int = 10) -> Any:
    """The turntable's footer font: matplotlib's DejaVu Sans (the gallery's), which covers Latin, Greek and
    Cyrillic letters and typographic dashes and quotes; Pillow's built-in font draws accented letters as boxes.

    Parameters
    ----------
    size_px : int
        Font size in pixels.

    Returns
    -------
    PIL.ImageFont.FreeTypeFont
    """
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size_px)


def save_turntable_gif(path: str | Path, frames: list[np.ndarray], attribution: str, fps: float = 12.0) -> None:
    """A looping GIF of RGB frames in [0, 1] with the attribution drawn under each frame, wrapped to its width.

    Parameters
    ----------
    path : str or Path
        Output GIF (atomic write).
    frames : list of ndarray (H, W, 3)
    attribution : str
    fps : float
    """
    from PIL import Image, ImageDraw

    width = frames[0].shape[1]
    font = footer_font()
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    footer = "\n".join(wrap_to_width(_footer(attribution), width - 4, lambda text: draw.textlength(text, font=font)))
    footer_px = int(draw.multiline_textbbox((0, 0), footer, font=font)[3]) + 3
    out = []
    for f in frames:
        im = Image.fromarray((np.clip(f, 0, 1) * 255 + 0.5).astype(np.uint8))
        canvas = Image.new("RGB", (im.width, im.height + footer_px), (0, 0, 0))
        canvas.paste(im, (0, 0))
        ImageDraw.Draw(canvas).multiline_text((2, im.height + 1), footer, fill=(200, 200, 200), font=font)
        out.append(canvas.convert("P", palette=Image.Palette.ADAPTIVE))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        out[0].save(tmp, format="GIF", save_all=True, append_images=out[1:], duration=int(1000 / fps), loop=0)


def run_config(run_dir: str | Path) -> dict[str, Any]:
    """The ``config.json`` contents of a photo run folder (one that also holds ``model.pt``).

    Parameters
    ----------
    run_dir : str or Path
        Output of :func:`ctsplat.photos.train.train_photos`.

    Returns
    -------
    dict
        ``sfm_dir``, ``train`` (the settings), ``config_hash``, ``code_version``.

    Raises
    ------
    CtsplatError
        When either file is missing (one line naming the folder).
    """
    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file() or not (run_dir / "model.pt").is_file():
        raise CtsplatError(f"{run_dir} is not a photo run (config.json and model.pt); run `ctsplat photos-train`")
    return read_json_object(run_dir / "config.json", what="photo run config", fix="run `ctsplat photos-train` again")


def run_scene(config: dict[str, Any], device: torch.device | str = "cpu") -> PhotoScene:
    """The scene a photo run was trained on, with its split, from the run's ``config.json`` contents.

    Parameters
    ----------
    config : dict
        ``sfm_dir`` and the ``train`` settings, as :func:`ctsplat.photos.train.train_photos` writes them.
    device : torch.device or str

    Returns
    -------
    PhotoScene
    """
    t = config["train"]
    return load_scene(config["sfm_dir"], downscale=int(t["downscale"]), test_every=int(t["test_every"]),
                      validation=held_out_split(t) == "val", validation_offset=t.get("validation_offset"),
                      device=device)


def evaluate_photos(run_dir: str | Path, settings: dict[str, Any] | None = None,
                    scene: PhotoScene | None = None) -> dict[str, Any]:
    """Evaluate a photo run on its held-out views and write the metrics and figures (module docstring).

    Parameters
    ----------
    run_dir : str or Path
        Output of :func:`ctsplat.photos.train.train_photos` (``config.json``, ``model.pt``).
    settings : dict, optional
        The ``photos.evaluate`` section.
    scene : PhotoScene, optional
        The scene the run was trained on (read from ``config.json``'s ``sfm_dir`` when not given).

    Returns
    -------
    dict
        The contents of ``metrics.json``: ``psnr``, ``ssim``, ``lpips`` (+ ``lpips_reason``), per-view lists,
        ``fps``, ``render_ms``, ``peak_rss_mb`` / ``peak_gpu_mb`` (training's; ``None`` for a run trained before
        they were recorded) and ``eval_peak_rss_mb`` / ``eval_peak_gpu_mb`` (the evaluating process's peak RSS, which
        includes training when both ran in one process, and this evaluation's GPU peak), ``n_gaussians``,
        ``resolution``, the SfM summary's registration numbers and the training report.
    """
    s = photo_settings({"evaluate": dict(settings or {})})["evaluate"]
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    t = cfg["train"]
    # every input is read before the first output is written: a bad one leaves the earlier outputs as they were
    training, sfm = ({} if not path.is_file() else read_json_object(path, what=what, fix=fix) for path, what, fix in (
        (run_dir / "training.json", "photo training record", "run `ctsplat photos-train` again"),
        (Path(cfg["sfm_dir"]) / "summary.json", "SfM summary", "run `ctsplat photos-sfm` again")))
    if not sfm:
        log.warning("%s has no summary.json: metrics.json will not report which photos registered; run `ctsplat "
                    "photos-sfm` again to have it", cfg["sfm_dir"])
    if not s["attribution"]:
        log.warning("photos.evaluate.attribution is empty: the gallery and turntable show the photographs without "
                    "their credit line; give it (--attribution) where their licence asks for one")
    device = resolve_device(t["device"])
    reset_gpu_peak(device)
    held = held_out_split(t)
    if scene is None:
        scene = run_scene(cfg, device)
    test = scene.split(held)
    if not test:
        raise CtsplatError(f"{cfg['sfm_dir']} has no held-out view (test_every {t['test_every']}); nothing to "
                           "evaluate")
    g = Gaussians.load(run_dir / "model.pt", device=device)
    bg = g.meta.get("background")
    rows, renders, times = [], [], []
    with torch.no_grad():
        render_view(g, test[0], background=bg)  # warm-up: kernel build and caches stay out of the timing
        for v in test:
            _synchronize(device)  # a GPU renders asynchronously: time the work, not its launch
            t0 = time.perf_counter()
            img = render_view(g, v, background=bg).image
            _synchronize(device)
            times.append(time.perf_counter() - t0)
            p, ss = image_metrics(img, v.image)
            rows.append({"iteration": "final", "view_id": v.name, "split": held, "psnr2d": p, "ssim2d": ss})
            renders.append(img.clamp(0, 1).cpu().numpy())
    lpips_reason = lpips_status()
    lpips_values = ([] if lpips_reason else
                    [lpips_distance(r, v.image.cpu().numpy())[0] for r, v in zip(renders, test, strict=True)])
    # the metrics go last: an evaluation that fails part-way leaves no metrics beside outputs they do not describe
    (run_dir / "metrics.json").unlink(missing_ok=True)
    log_csv = CsvLog(run_dir / "per_view_test.csv", PER_VIEW_COLUMNS)
    log_csv.reset()
    log_csv.append(rows)
    k = min(int(s["gallery_views"]), len(test))
    pick = np.unique(np.linspace(0, len(test) - 1, k).round().astype(int)) if k else np.array([], int)
    if len(pick):
        save_photo_gallery(run_dir / "figures" / "gallery.png", [test[i].image.cpu().numpy() for i in pick],
                           [renders[i] for i in pick], [test[i].name for i in pick],
                           [rows[i]["psnr2d"] for i in pick], s["attribution"])
    n_frames = int(s["turntable_frames"])
    if n_frames and len(scene.views) >= 2:
        cam = scene.views[0].camera
        with torch.no_grad():
            frames = [render_view(g, None, cam, R, tt, background=bg).image.clamp(0, 1).cpu().numpy()
                      for R, tt in turntable_poses(scene.views, n_frames)]
        save_turntable_gif(run_dir / "figures" / "turntable.gif", frames, s["attribution"])
    ms = float(np.mean(times)) * 1000
    metrics = {
        "psnr": float(np.mean([r["psnr2d"] for r in rows])),
        "ssim": float(np.mean([r["ssim2d"] for r in rows])),
        "lpips": float(np.mean(lpips_values)) if lpips_values else None,
        "lpips_reason": lpips_reason,
        "per_view": {r["view_id"]: {"psnr": r["psnr2d"], "ssim": r["ssim2d"],
                                    "lpips": lpips_values[i] if lpips_values else None}
                     for i, r in enumerate(rows)},
        "held_out": held,
        "n_test": len(test),
        "n_train": len(scene.split("train")),
        "test_views": [v.name for v in test],
        "resolution": [test[0].camera.width, test[0].camera.height],
        "downscale": int(t["downscale"]),
        "n_gaussians": len(g),
        "render_ms": ms,
        "fps": 1000.0 / ms if ms > 0 else None,
        "threads": torch.get_num_threads(),
        "device": str(device),
        # training's peak (training.json; the workflow evaluates in another process) and this evaluation's own
        "peak_rss_mb": training.get("peak_rss_mb"),
        "peak_gpu_mb": training.get("peak_gpu_mb"),
        **{f"eval_{k}": v for k, v in peak_memory(device).items()},
        "sfm": {k2: sfm.get(k2) for k2 in SFM_SUMMARY_KEYS},
        "training": training,
        "attribution": s["attribution"],
        # the trained run's provenance, and the code that scored it (the evaluation can run again on its own)
        "seed": int(t["seed"]),
        "config_hash": cfg.get("config_hash"),
        "training_code_version": cfg.get("code_version"),
        "code_version": code_version(),
        "platform": compute_platform(device),
    }
    write_json_atomic(run_dir / "metrics.json", json_safe(metrics))
    return metrics


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
