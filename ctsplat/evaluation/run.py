"""Evaluation of a trained Gaussian model: held-out projections, voxelised 3D metrics, speed; the run's metrics.

2D metrics are computed on line-integral images of the *normalised* volume (the training targets divided by
``mu_scale_per_mm``), PSNR/SSIM with each reference image's own range (``ctsplat.evaluation.metrics``). 3D
metrics compare the model voxelised on the reference grid with the normalised reference volume (data range 1).
LPIPS uses ``ctsplat.evaluation.metrics.lpips_distance`` and is ``None`` with a recorded reason when it cannot be
computed.

:func:`evaluate` is the one implementation of a run's held-out metrics (``metrics.json``); training only logs
validation metrics while it runs.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import resource
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat.evaluation import metrics
from ctsplat.utils import (
    CtsplatError,
    code_version,
    compute_platform,
    deep_update,
    is_finite_real,
    json_safe,
    read_json_object,
    resolve_device,
    write_json_atomic,
)

__all__ = [
    "render_views",
    "view_metrics",
    "per_view_rows",
    "voxelize_model",
    "volume_metrics",
    "readout_sharpening",
    "check_validation_choices",
    "peak_memory_mb",
    "forward_fps",
    "orbit_poses",
    "evaluate",
    "model_size_bytes",
]

log = logging.getLogger(__name__)


def render_views(
    gaussians: Any,
    camera: Any,
    Rs: np.ndarray,
    ts: np.ndarray,
    render_kwargs: dict[str, Any] | None = None,
) -> np.ndarray:
    """Render views of a Gaussian model without gradient.

    Parameters
    ----------
    gaussians : ctsplat.splat.Gaussians
        The model (its device and dtype are used).
    camera : ParallelCamera or ConeCamera
        The detector, ``H`` rows by ``W`` columns.
    Rs : ndarray, shape (V, 3, 3)
        World-to-camera rotations.
    ts : ndarray, shape (V, 3)
        World-to-camera translations (mm).
    render_kwargs : dict, optional
        Passed to :func:`ctsplat.splat.render` (compositor, filter_3d_var, mip_2d).

    Returns
    -------
    ndarray, shape (V, H, W), float32
        The rendered images (line integrals in normalised-volume units, mm; colour renders averaged over
        channels).
    """
    from ctsplat.splat.render import render

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

    Parameters
    ----------
    preds, refs : ndarray, shape (V, H, W)
        Rendered and reference images; each reference sets its own data range.
    with_lpips : bool
        Also compute LPIPS.

    Returns
    -------
    dict
        ``psnr2d`` (V,) dB and ``ssim2d`` (V,); with ``with_lpips`` also ``lpips`` (list of float or None, length
        V) and ``lpips_reason`` (str or None).

    Raises
    ------
    ValueError
        When the shapes differ.
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
    """The model's density field at the voxel centres of a grid (no gradient).

    Parameters
    ----------
    gaussians : ctsplat.splat.Gaussians
        The model.
    shape : tuple of int, shape (3,)
        Grid shape ``(I, J, K)``.
    affine : ndarray, shape (4, 4)
        Voxel index -> world mm.
    filter_3d_var : Tensor, shape (N,), optional
        Mip-Splatting 3D filter variance (mm²), so the read-out matches the rendered field.

    Returns
    -------
    ndarray, shape (I, J, K), float32
        Density in normalised-volume units.
    """
    from ctsplat.splat.render import voxelize

    with torch.no_grad():
        vol = voxelize(gaussians, tuple(shape), np.asarray(affine, float), filter_3d_var=filter_3d_var)
    return vol.float().cpu().numpy()


def per_view_rows(iteration: int, views: Any, vm: dict[str, Any]) -> list[dict[str, Any]]:
    """``per_view*.csv`` rows (:data:`ctsplat.formats.runlog.PER_VIEW_COLUMNS`) of one evaluation.

    Parameters
    ----------
    iteration : int
        The model's training iteration.
    views : ctsplat.scene.ViewData
        The evaluated views (ids, angles in degrees, split).
    vm : dict
        :func:`view_metrics` of those views (``psnr2d`` dB, ``ssim2d``, one value per view).

    Returns
    -------
    list of dict
        One row per view.
    """
    return [
        {"iteration": int(iteration), "view_id": int(i), "azimuth_deg": float(a), "elevation_deg": float(e),
         "split": views.split, "psnr2d": float(p), "ssim2d": float(q)}
        for i, a, e, p, q in zip(views.ids, views.azimuth_deg, views.elevation_deg, vm["psnr2d"], vm["ssim2d"],
                                 strict=True)
    ]


def gauge_aligned_model(gaussians: Any, G: np.ndarray, b: np.ndarray) -> Any:
    """The model moved from its training frame into the true frame: ``x = Gᵀ (m - b)`` (see
    :func:`ctsplat.training.poses.gauge_motion`), covariances turned by ``Gᵀ``.

    Parameters
    ----------
    gaussians : ctsplat.splat.Gaussians
    G : ndarray (3, 3)
    b : ndarray (3,), mm

    Returns
    -------
    ctsplat.splat.Gaussians
        A moved copy (the input is unchanged).
    """
    from scipy.spatial.transform import Rotation

    from ctsplat.training.poses import quat_mul

    g = gaussians.detach()
    dt, dev = g.means.dtype, g.means.device
    Gt = torch.as_tensor(np.asarray(G, float), dtype=dt, device=dev)
    bt = torch.as_tensor(np.asarray(b, float), dtype=dt, device=dev)
    x, y, z, w = Rotation.from_matrix(np.asarray(G, float).T).as_quat()
    q = torch.tensor([w, x, y, z], dtype=dt, device=dev)
    # rows: (m - b)ᵀ G = (Gᵀ (m - b))ᵀ; new tensors, so the caller's model keeps its own
    return dataclasses.replace(g, means=(g.means - bt) @ Gt, quats=quat_mul(q.expand_as(g.quats), g.quats))


def volume_metrics(model_vol: np.ndarray, reference: np.ndarray, *, r2: bool = False,
                   data_range: float = 1.0) -> dict[str, float]:
    """3D metrics of a voxelised model against the reference.

    Parameters
    ----------
    model_vol, reference : ndarray, shape (I, J, K)
        Volumes in the reference volume's units.
    r2 : bool
        Also R²-Gaussian's ``metric_vol`` values (the held-out evaluation; periodic validation skips them).
    data_range : float
        The units' full range (:attr:`ctsplat.formats.volume.Volume.metric_range`): both volumes are divided by it,
        so the metrics compare normalised volumes (1: they already are).

    Returns
    -------
    dict of str to float
        ``psnr3d`` (dB, whole volume, data range 1) and ``ssim3d`` (mean 2D SSIM over the three axes), the
        project's convention; with ``r2`` also ``psnr3d_r2`` and ``ssim3d_r2`` (:mod:`ctsplat.evaluation.metrics`).
    """
    if data_range != 1.0:
        model_vol, reference = model_vol / data_range, reference / data_range
    out = {"psnr3d": metrics.psnr3d(model_vol, reference), "ssim3d": metrics.ssim3d(model_vol, reference)}
    if r2:
        out.update(psnr3d_r2=metrics.psnr3d_r2(model_vol, reference), ssim3d_r2=metrics.ssim3d_r2(model_vol, reference))
    return out


def peak_memory_mb(device: torch.device) -> tuple[float, str]:
    """Peak memory in MiB and its kind: CUDA max allocated on a GPU, else the process's peak RSS.

    Parameters
    ----------
    device : torch.device
        The device the work ran on.

    Returns
    -------
    mib : float
        Peak memory (MiB).
    kind : str
        ``"cuda_max_allocated"`` or ``"process_peak_rss"`` (Linux ``ru_maxrss``, KiB / 1024).
    """
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20, "cuda_max_allocated"
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "process_peak_rss"


def scaled_camera(camera: Any, width: int, height: int) -> Any:
    """The same detector field of view resampled to ``width × height`` pixels.

    The pixel size grows by ``max(W / width, H / height)``, so the new detector covers the original field of
    view (and more along one axis when the aspect ratios differ).

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera
        The detector.
    width, height : int
        New size (px).

    Returns
    -------
    ParallelCamera or ConeCamera
        Same model and distances, new size and pixel spacing / pitch (mm).
    """
    f = max(camera.width / width, camera.height / height)
    if camera.model == "parallel":
        return dataclasses.replace(camera, width=width, height=height, spacing_mm=camera.spacing_mm * f)
    return dataclasses.replace(camera, width=width, height=height, pitch_mm=camera.pitch_mm * f)


def forward_fps(gaussians: Any, camera: Any, R: np.ndarray, t: np.ndarray, render_kwargs: dict[str, Any],
                *, width: int = 1920, height: int = 1080, repeats: int = 2) -> float:
    """Frames per second of a forward render at ``width × height`` (median of ``repeats`` after one warm-up).

    Parameters
    ----------
    gaussians : ctsplat.splat.Gaussians
        The model.
    camera : ParallelCamera or ConeCamera
        The detector; resampled with :func:`scaled_camera`.
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).
    render_kwargs : dict
        Passed to the renderer.
    width, height : int
        Render size (px).
    repeats : int
        Timed renders.

    Returns
    -------
    float
        Frames per second (CUDA synchronised around each render on a GPU).
    """
    from ctsplat.splat.render import render

    cam = scaled_camera(camera, width, height)
    dev, dt = gaussians.means.device, gaussians.means.dtype
    # the pose on the device and the image left there: the render alone is timed, not copies to or from the host
    Rt = torch.as_tensor(np.asarray(R), dtype=dt, device=dev)
    tt = torch.as_tensor(np.asarray(t), dtype=dt, device=dev)
    times = []
    with torch.no_grad():
        for i in range(repeats + 1):
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            t0 = time.perf_counter()
            render(gaussians, cam, Rt, tt, **render_kwargs)
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

    Parameters
    ----------
    R0 : ndarray, shape (3, 3)
        World-to-camera rotation of the first frame.
    t0 : ndarray, shape (3,)
        World-to-camera translation of the first frame (mm).
    center_mm : ndarray, shape (3,)
        Point on the rotation axis (world mm), e.g. the volume centre.
    n : int
        Number of poses, one full turn (``2π k / n``, ``k < n``).

    Returns
    -------
    Rs : ndarray, shape (n, 3, 3)
        World-to-camera rotations.
    ts : ndarray, shape (n, 3)
        World-to-camera translations (mm).
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


#: The run config's settings (``config.json``'s ``config``) and the training record's entries the evaluation reads.
_RUN_CONFIG_KEYS = ("volume", "radiographs", "init", "compositor", "mip", "poses", "supervision", "seed", "figures",
                    "turntable_frames", "fps_width", "fps_height")
_TRAINING_KEYS = ("wall_time_s", "iterations", "iters_per_s", "nan_events")


def evaluate(run_dir: str | Path, *, split: str = "test", device: str = "auto",
             milestones: Mapping[str, float] | None = None, write: bool = True,
             model: str | None = None, settings: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Evaluate a finished training run: the one place its held-out metrics are computed.

    Reads ``run_dir/config.json``, ``model.pt``, ``training.json`` and ``train_log.csv`` (written by
    :func:`ctsplat.training.train`) and the scene's view sets; renders the split's views at the scene's poses for
    them (the true poses of the test and validation views; a ``train`` split at its training poses),
    voxelises the model on the reference grid, and measures 2D PSNR/SSIM/LPIPS, 3D PSNR/SSIM, forward FPS and the
    time to the validation milestones.

    Parameters
    ----------
    run_dir : str or Path
        A finished training run.
    split : {"test", "val", "train"}
        Views to evaluate on; model selection uses ``val``, the reported numbers ``test``.
    device : str
        ``auto`` | ``cpu`` | ``cuda``.
    milestones : mapping, optional
        Validation targets, ``{metric: threshold}``, for the ``iter_to_*`` / ``time_to_*_s`` columns
        (:func:`ctsplat.analysis.stats.milestones`); default: those an earlier evaluation of this split recorded
        (``evaluation_milestones``), else the ``analysis.milestones`` section's defaults.
    write : bool
        Write ``metrics.json`` (``metrics_{split}.json`` for other splits), ``per_view_{split}.csv`` and, for the
        test split, ``model_volume.nii.gz`` and the figures (``gallery.png``, ``slices.png``, ``turntable.gif``)
        when the run's config asks for figures.
    model : {"last", "best"}, optional
        ``last``: ``model.pt``; ``best``: ``model_best.pt`` (highest validation PSNR during training). Default:
        the run's ``model_selection``. Recorded as ``model`` (and ``model_iteration``) in the metrics.
    settings : mapping, optional
        :data:`ctsplat.training.config.EVALUATION_KEYS` (``figures``, ``turntable_frames``, ``fps_width``,
        ``fps_height``, ``model_selection``, ``sharpen``) used instead of the run's own; other keys are refused.
        A key not given takes the value an earlier evaluation of this split recorded (``evaluation_settings`` in
        its metrics file: the workflow evaluates with its own, which the run's ``config.json`` does not hold),
        else the run's.

    Returns
    -------
    dict
        The metrics (JSON-serialisable; see ``metrics.json``): PSNR in dB, SSIM and LPIPS dimensionless, times
        in seconds, memory in MiB, sizes in bytes.

    Raises
    ------
    CtsplatError
        When ``run_dir`` lacks ``config.json``, ``model.pt`` or ``training.json``, for an unknown split, or when
        the scene cannot be loaded (:func:`ctsplat.scene.load_scene`).

    Examples
    --------
    >>> run = "results/head/runs/init~fbp/compositor~radiative/mip~on/poses~gt/views~50/seed~0"
    >>> m = evaluate(run)  # doctest: +SKIP
    >>> m["psnr2d"], m["psnr3d"], m["ssim3d"]  # doctest: +SKIP
    """
    from ctsplat.analysis.stats import milestones as milestone_times
    from ctsplat.config import schema_defaults
    from ctsplat.evaluation import figures
    from ctsplat.formats.runlog import PER_VIEW_COLUMNS, CsvLog, read_train_log
    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.scene import load_scene
    from ctsplat.splat.gaussians import Gaussians
    from ctsplat.training.config import (
        EVALUATION_KEYS,
        REFERENCE_INITS,
        TRAIN_BOUNDS,
        mip_filter,
        render_kwargs,
    )

    run_dir = Path(run_dir)
    needed = [run_dir / n for n in ("config.json", "model.pt", "training.json")]
    if not all(p.exists() for p in needed):
        missing = ", ".join(p.name for p in needed if not p.exists())
        raise CtsplatError(f"{run_dir} is not a finished training run (missing {missing}); run `ctsplat train` "
                           "first")
    if split not in ("test", "val", "train"):
        raise CtsplatError(f"unknown split {split!r}; allowed: test, val, train")
    unknown = sorted(set(settings or {}) - set(EVALUATION_KEYS))
    if unknown:
        raise CtsplatError(f"evaluate settings: {unknown[0]!r} is not an evaluation key; allowed: "
                           f"{', '.join(EVALUATION_KEYS)}")
    from ctsplat.config import check_section

    check_section("train", dict(settings or {}))  # types and nested keys, as train checks them
    fix = "train the run again (`ctsplat train`)"
    run_cfg = read_json_object(run_dir / "config.json", what="run config", fix=fix)
    if not isinstance(run_cfg.get("config"), dict):
        raise CtsplatError(f"run config {run_dir / 'config.json'} has no 'config' object; {fix}")
    # score again as the earlier evaluation of this split did, where no setting is given
    earlier = _recorded_evaluation(run_dir, split, EVALUATION_KEYS)
    # key by key: --set sharpen.amounts=... keeps the recorded radius_voxels
    cfg = deep_update(deep_update(run_cfg["config"], earlier.get("evaluation_settings", {})), dict(settings or {}))
    milestones = earlier.get("evaluation_milestones") if milestones is None else milestones
    for metric, value in dict(milestones or {}).items():
        if not is_finite_real(value):
            raise CtsplatError(f"evaluation milestone {metric!r} must be a finite number, got {value!r} (an earlier "
                               f"metrics file that was edited? remove {_metrics_path(run_dir, split).name} and "
                               "evaluate again)")
    model = model or cfg.get("model_selection", "last")
    if model not in ("last", "best"):
        raise CtsplatError(f"unknown model {model!r}; allowed: last, best")
    model_path = run_dir / ("model_best.pt" if model == "best" else "model.pt")
    if not model_path.exists():
        raise CtsplatError(f"{run_dir} has no {model_path.name} (model: {model}); evaluate model: last, or retrain "
                           "with a version that writes it")
    trained = read_json_object(run_dir / "training.json", what="training record", fix=fix)
    for path, record, keys in ((run_dir / "config.json", cfg, _RUN_CONFIG_KEYS),
                               (run_dir / "training.json", trained, _TRAINING_KEYS)):
        missing = [k for k in keys if k not in record]
        if missing:  # a record of another version, or an edited one: named here, not as a KeyError later
            raise CtsplatError(f"{path} has no {missing[0]!r} entry (written by another version, or edited); {fix}")
    for key in ("turntable_frames", "fps_width", "fps_height"):  # given as settings, or an edited config
        if key in cfg:
            TRAIN_BOUNDS[key].check(key, cfg[key])
    dev = resolve_device(device)
    scene = load_scene(cfg)
    check_validation_choices(scene, cfg, model)
    pose_fields, refined = _model_poses(run_dir, trained, model)  # before any rendering: it may refuse the run
    g = Gaussians.load(model_path, device=dev)
    views = scene.split(split)
    if split == "test" and scene.info.get("test_views_from") == "val":
        log.warning("%s: the view set has no test views; the test metrics are on the validation views, which also "
                    "chose the model (metrics.json: views_from val)", run_dir)
    tr = scene.train
    # the 3D filter the model was trained (and, for model_best, selected) with; recomputed only for a model
    # saved without one
    stored = g.filter_3d_var if cfg["mip"] else None
    rk = render_kwargs(cfg, stored if stored is not None else mip_filter(cfg, g, tr.camera, tr.Rs, tr.ts))
    preds = render_views(g, views.camera, views.Rs, views.ts, rk)
    _check_finite(preds, "pixel", model_path, g)
    vm = view_metrics(preds, views.images, with_lpips=True)
    vol_model = voxelize_model(g, scene.volume.shape, scene.volume.affine, rk.get("filter_3d_var"))
    _check_finite(vol_model, "voxel", model_path, g)
    vol_raw, sharpening = vol_model, readout_sharpening(cfg, vol_model, scene, dev)
    if sharpening:
        vol_model = sharpening.pop("volume")
        raw = volume_metrics(vol_raw, scene.volume.data, r2=True, data_range=scene.volume.metric_range)
        sharpening.update({f"{k}_unsharpened": v for k, v in raw.items()})
    m3 = volume_metrics(vol_model, scene.volume.data, r2=True, data_range=scene.volume.metric_range)
    m3.update(_gauge_aligned_metrics(refined, g, scene, rk, sharpening))
    log_path = run_dir / "train_log.csv"
    targets = dict(milestones) if milestones else schema_defaults("analysis")["milestones"]
    times = milestone_times(read_train_log(log_path), targets) if log_path.exists() else {}
    fps = forward_fps(g, views.camera, views.Rs[0], views.ts[0], rk, width=int(cfg["fps_width"]),
                      height=int(cfg["fps_height"]))
    uses_ref = cfg["init"] in REFERENCE_INITS
    lpips_vals = vm["lpips"]
    result = {
        "psnr2d": float(np.mean(vm["psnr2d"])),
        "ssim2d": float(np.mean(vm["ssim2d"])),
        "lpips": None if any(v is None for v in lpips_vals) else float(np.mean(lpips_vals)),
        "lpips_reason": vm["lpips_reason"],
        **m3,
        **sharpening,
        "split": split,
        # "val" when the view set has no test views and the test split is its validation views
        "views_from": scene.info.get("test_views_from", "test") if split == "test" else split,
        "n_views": len(views),
        "n_train_views": len(scene.train),
        "eval_split_during_training": scene.eval_split,
        "wall_time_s": trained["wall_time_s"],
        "iterations": trained["iterations"],
        "iters_per_s": trained["iters_per_s"],
        **times,
        "fps_forward": fps,
        "fps_resolution": [int(cfg["fps_width"]), int(cfg["fps_height"])],
        "peak_memory_mb": trained.get("peak_memory_mb"),
        "peak_memory_kind": trained.get("peak_memory_kind"),
        "n_gaussians": len(g),
        "model": model,
        # what this evaluation scored with, so that evaluating the run again scores it alike
        "evaluation_settings": {**{k: cfg[k] for k in EVALUATION_KEYS if k != "progress" and k in cfg},
                                "model_selection": model},
        "evaluation_milestones": dict(targets),
        "model_iteration": g.meta.get("iteration", trained["iterations"] if model == "last" else None),
        "model_size_bytes": model_size_bytes(model_path),
        "model_ply_size_bytes": _ply_size_bytes(g, run_dir, model),
        "uses_reference_volume": uses_ref,
        "init": cfg["init"],
        "compositor": cfg["compositor"],
        "mip": bool(cfg["mip"]),
        "poses": cfg["poses"],
        "supervision": cfg["supervision"],
        "seed": int(cfg["seed"]),
        "nan_events": trained["nan_events"],
        "views_dropped_unregistered": scene.info.get("views_dropped_unregistered", 0),
        "sfm_registration_rate": scene.info.get("sfm_registration_rate"),
        "device": str(dev),
        "config_hash": run_cfg.get("config_hash"),
        "code_version": code_version(),
        # torch's CPU kernels round by vector instructions and threads: what the scores were computed with
        "platform": compute_platform(dev),
        "volume_id": scene.volume.volume_id,
        # training-pose errors against the true poses, before and after pose refinement, of the poses the
        # evaluated model was fitted at (training.json)
        **pose_fields,
    }
    if not write:
        return result
    metrics_path = _metrics_path(run_dir, split)
    # the metrics go last: an evaluation that fails part-way leaves no metrics beside outputs they do not describe
    metrics_path.unlink(missing_ok=True)
    per_view = CsvLog(run_dir / f"per_view_{split}.csv", PER_VIEW_COLUMNS)
    per_view.reset()
    per_view.append(per_view_rows(result["model_iteration"] if result["model_iteration"] is not None
                                  else trained["iterations"], views, vm))
    if split == "test":
        meta = {"source": "ctsplat voxelised Gaussian model",
                # the read-out is in the reference's units (normalised, or 1/mm for a reference stored in 1/mm)
                "intensity": {**scene.volume.meta.get("intensity", {}), "mu_scale_per_mm": scene.mu_scale},
                "reference_volume_id": scene.volume.volume_id, "uses_reference_volume": uses_ref,
                "config_hash": run_cfg.get("config_hash"), "code_version": code_version()}
        save_volume(Volume(vol_model.astype(np.float32), np.asarray(scene.volume.affine, float),
                           {**meta, "sharpen_amount": result.get("sharpen_amount", 0.0)}),
                    run_dir / "model_volume.nii.gz")
        unsharpened = run_dir / "model_volume_unsharpened.nii.gz"
        if sharpening:
            save_volume(Volume(vol_raw.astype(np.float32), np.asarray(scene.volume.affine, float), meta), unsharpened)
        else:  # an earlier evaluation's would sit beside a read-out that is not sharpened
            unsharpened.unlink(missing_ok=True)
        if cfg["figures"]:
            figures.save_gallery(run_dir / "gallery.png", views.images, preds, [int(i) for i in views.ids],
                                 vm["psnr2d"])
            # the figure's fixed grey range is the normalised one: scale as the 3D metrics do (mu volumes are in 1/mm)
            scale = scene.volume.metric_range
            figures.save_slices(run_dir / "slices.png", vol_model / scale, scene.volume.data / scale)
            Rs, ts = orbit_poses(views.Rs[0], views.ts[0], scene.volume.center_mm(), int(cfg["turntable_frames"]))
            figures.save_turntable(run_dir / "turntable.gif", render_views(g, views.camera, Rs, ts, rk))
        else:  # figures of an earlier evaluation would sit beside metrics they do not show
            for name in ("gallery.png", "slices.png", "turntable.gif"):
                (run_dir / name).unlink(missing_ok=True)
    write_json_atomic(metrics_path, json_safe(result))
    return result


def _check_finite(values: np.ndarray, what: str, model_path: Path, g: Any) -> None:
    """Refuse a render or read-out that is not finite: finite parameters whose sums overflow float32 where
    Gaussians overlap (loading already refuses non-finite parameters)."""
    if not np.isfinite(values).all():
        raise CtsplatError(f"{model_path} renders {int((~np.isfinite(values)).sum())} non-finite {what}(s) of "
                           f"{values.size} (largest density {float(g.densities.max()):.3g}: the sums overflow "
                           "float32); retrain it, and report it if its training log shows no collapse")


def readout_sharpening(cfg: dict[str, Any], volume: np.ndarray, scene: Any, device: Any) -> dict[str, Any]:
    """The run's ``sharpen`` step on its voxel read-out (:mod:`ctsplat.evaluation.readout`).

    Parameters
    ----------
    cfg : dict
        The run's resolved ``train`` config (``sharpen``; a config without the key has the step off).
    volume : ndarray, shape (I, J, K)
        The voxel read-out on the reference grid (normalised units).
    scene : ctsplat.scene.Scene
        The run's scene; only its validation views are read.
    device : torch.device
        Where the candidates are re-projected.

    Returns
    -------
    dict
        ``{}`` when the step is off (every amount 0); else
        :func:`~ctsplat.evaluation.readout.choose_sharpening`'s info plus ``volume``, the chosen read-out.

    Raises
    ------
    CtsplatError
        When the step is on and the scene has no validation views.
    """
    from ctsplat.evaluation.readout import choose_sharpening
    from ctsplat.recon.select import Validator

    amounts, radius = sharpen_settings(cfg)
    if not any(amounts):
        return {}
    check_validation_choices(scene, cfg, "last")  # the amount only
    val = scene.val
    validator = Validator.from_views(val.images, val.camera, val.Rs, val.ts, np.asarray(scene.volume.affine, float),
                                     device=device)
    vol, info = choose_sharpening(volume, validator, amounts=amounts, radius_voxels=radius)
    return {**info, "volume": vol}


def sharpen_settings(cfg: dict[str, Any]) -> tuple[list[float], float]:
    """``(amounts, radius_voxels)`` of a run config's ``sharpen`` section (off for configs without one)."""
    from ctsplat.evaluation.readout import check_sharpen_config
    from ctsplat.training.config import TRAIN_DEFAULTS

    return check_sharpen_config(cfg.get("sharpen") or TRAIN_DEFAULTS["sharpen"])


def check_validation_choices(scene: Any, cfg: dict[str, Any], model: str | None = None) -> None:
    """Fail in one line when a choice made on validation views (the read-out's ``sharpen`` amount, ``model: best``)
    meets a scene without validation views: its ``val`` split would be the test views, which never choose anything.

    Parameters
    ----------
    scene : ctsplat.scene.Scene
    cfg : dict
        The run's ``train`` config.
    model : str, optional
        The model scored (``last`` or ``best``); default ``cfg["model_selection"]``.
    """
    if scene.eval_split == "val":
        return
    amounts, _ = sharpen_settings(cfg)
    if any(amounts):
        raise CtsplatError(f"train.sharpen.amounts {amounts} is chosen on validation views, but the radiographs in "
                           f"{cfg['radiographs']} have none; render them with a validation split "
                           "(radiographs.<geometry>.n_val or split.val) or set train.sharpen.amounts: [0]")
    if (model or cfg.get("model_selection", "last")) == "best":
        raise CtsplatError(f"model_selection: best chooses a model on validation views, but the radiographs in "
                           f"{cfg['radiographs']} have none (it would choose on the test views); render them "
                           "with a validation split (n_val or split.val) or set model_selection: last")


def _metrics_path(run_dir: Path, split: str) -> Path:
    """Where an evaluation of ``split`` writes its metrics: ``metrics.json`` (test), else ``metrics_{split}.json``."""
    return run_dir / ("metrics.json" if split == "test" else f"metrics_{split}.json")


def _recorded_evaluation(run_dir: Path, split: str, keys: tuple[str, ...]) -> dict[str, Any]:
    """``evaluation_settings`` (those of ``keys``) and ``evaluation_milestones`` of the split's earlier metrics
    file, each a dict; an empty dict when there is none or it records neither."""
    path = _metrics_path(run_dir, split)
    if not path.is_file():
        return {}
    earlier = read_json_object(path, what="earlier metrics", fix="remove it and evaluate again")
    out = {k: earlier[k] for k in ("evaluation_settings", "evaluation_milestones") if isinstance(earlier.get(k), dict)}
    if "evaluation_settings" in out:
        out["evaluation_settings"] = {k: v for k, v in out["evaluation_settings"].items() if k in keys}
        from ctsplat.config import check_section

        check_section("train", out["evaluation_settings"], where=f"{path} evaluation_settings")
    if out:
        log.info("%s: the settings %s recorded are used where none is given", run_dir, path.name)
    return out


def _model_poses(run_dir: Path, trained: dict[str, Any], model: str) -> tuple[dict[str, Any], Path]:
    """The training-pose fields of ``training.json`` and the refined-pose file (it may not exist: no refinement)
    that belong to the evaluated model: the final poses for ``model.pt``; for ``model_best.pt`` of a run with pose
    refinement, the poses it was fitted at when it was saved (``best_model_poses``, ``refined_views_best.json``)."""
    fields = {k: v for k, v in trained.items() if k.startswith("pose_")}
    if model != "best" or not trained.get("pose_refine"):
        return fields, run_dir / "refined_views.json"
    best, refined = trained.get("best_model_poses"), run_dir / "refined_views_best.json"
    if not isinstance(best, dict) or not refined.is_file():
        missing = "its 'best_model_poses' entry" if not isinstance(best, dict) else refined.name
        raise CtsplatError(f"{run_dir} lacks {missing}, the poses model_best.pt was fitted at (written by another "
                           "version); evaluate model: last, or train the run again")
    return {**fields, **best}, refined


def _gauge_aligned_metrics(refined: Path, g: Any, scene: Any, rk: dict[str, Any],
                           sharpening: dict[str, Any]) -> dict[str, Any]:
    """3D metrics of a model trained at poses other than the true ones, after the rigid motion its training images
    cannot observe (:func:`ctsplat.training.poses.gauge_motion` of the training poses it was fitted at, ``refined``
    or without that file the recorded ones, against the true ones) is undone: ``psnr3d_gauge_aligned``,
    ``ssim3d_gauge_aligned``, and that motion (``gauge_rotation_deg``, ``gauge_shift_mm``). Empty for runs at the
    true poses. The moved read-out gets the sharpening chosen for the run's own (``sharpening``, empty when off),
    so the pair differs from ``psnr3d`` / ``ssim3d`` by the motion alone."""
    from ctsplat.evaluation.readout import sharpen
    from ctsplat.training.poses import gauge_motion, rotation_angles_deg

    tr = scene.train
    Rs_true, ts_true = tr.truth()
    Rs, ts = np.asarray(tr.Rs, float), np.asarray(tr.ts, float)
    if refined.exists():
        fix = "train the run again (its refined poses are damaged)"
        doc = read_json_object(refined, what="refined training poses", fix=fix)
        try:
            by_id = {int(v["id"]): v for v in doc["views"]}
            Rs = np.stack([np.asarray(by_id[int(i)]["R"], float) for i in tr.ids])
            ts = np.stack([np.asarray(by_id[int(i)]["t"], float) for i in tr.ids])
        except (KeyError, TypeError, ValueError) as exc:
            raise CtsplatError(f"{refined} lacks a training view's pose ({type(exc).__name__}: {exc}); "
                               f"{fix}") from None
    if np.allclose(Rs, Rs_true, atol=1e-12) and np.allclose(ts, ts_true, atol=1e-9):
        return {}
    G, b = gauge_motion(Rs, ts, Rs_true, ts_true, tr.camera.model, center_mm=scene.isocenter_mm)
    moved = gauge_aligned_model(g, G, b)
    vol = voxelize_model(moved, scene.volume.shape, scene.volume.affine, rk.get("filter_3d_var"))
    if sharpening and float(sharpening["sharpen_amount"]) != 0:  # amount 0 is the read-out as given
        vol = sharpen(vol, amount=float(sharpening["sharpen_amount"]),
                      radius_voxels=float(sharpening["sharpen_radius_voxels"]))
    m = volume_metrics(vol, scene.volume.data, data_range=scene.volume.metric_range)
    return {"psnr3d_gauge_aligned": m["psnr3d"], "ssim3d_gauge_aligned": m["ssim3d"],
            "gauge_rotation_deg": float(rotation_angles_deg(G[None])[0]), "gauge_shift_mm": float(np.linalg.norm(b))}


def _ply_size_bytes(g: Any, run_dir: Path, model: str) -> int:
    """Bytes of the evaluated model's 3DGS PLY: ``model.ply`` for the last model; for ``model_best.pt``, of which
    no PLY is kept, the size of the one it writes (training writes ``model.ply`` the same way)."""
    if model != "best":
        return model_size_bytes(run_dir / "model.ply")
    with tempfile.TemporaryDirectory() as tmp:
        g.to_ply(Path(tmp) / "model_best.ply")
        return model_size_bytes(Path(tmp) / "model_best.ply")


def model_size_bytes(*paths: str | Path) -> int:
    """Total size on disk of the given files (missing ones count 0).

    Parameters
    ----------
    *paths : str or Path
        Files.

    Returns
    -------
    int
        Bytes.
    """
    return int(sum(os.path.getsize(p) for p in paths if os.path.exists(p)))
