"""Training loop: a rectified radiative Gaussian model fitted to the radiographs of a scene.

Objective (per step, over a batch of training views; images are normalised-volume line integrals divided by a
fixed ``image_scale`` = max of the training targets, so they lie in [0, 1])::

    L = λ1 L1 + λs (1 - SSIM) + λρ mean(ρ) + λscale mean(‖s‖) + λtv TV(voxelised random sub-volume)

(:mod:`ctsplat.training.losses`). With ``supervision: transmission`` the compared images are ``exp(-μ_scale p)``
instead. λρ follows ``lambda_density_warmup`` (:func:`ctsplat.training.features.density_lambda`); with
``augment`` each training render uses a slightly moved camera and a noisy target
(:class:`ctsplat.training.features.Augmenter`), never the validation renders.

Pose refinement (``pose_refine.enabled`` or ``poses: *+refine``): from iteration ``pose_refine.start`` on, each
training view's camera carries a rigid correction (:class:`ctsplat.training.poses.PoseCorrection`) rendered as the
equivalent motion of the Gaussians, stepped by its own Adam together with the Gaussians, with a prior toward the
starting pose in the loss and the common (unobservable) motion removed after every step. Validation and evaluation
views keep their recorded poses. The corrected training poses go to ``refined_views.json``; pose errors against
the true poses, before and after, to ``training.json``. The poses ``model_best.pt`` was trained at go to
``refined_views_best.json``, and their errors to ``training.json``'s ``best_model_poses``, so that an evaluation of
that model reports the poses it was fitted with.

Optimiser: Adam with one parameter group per quantity (means, log-scales, quaternions, density; plus opacity and
colour for the alpha compositor), each with its own learning rate decayed by a cosine from ``lr`` to
``lr × lr_final_factor``. Mean learning rates are given in voxels per step (multiplied by the mean voxel edge).
``optimizer_preset: method`` uses one rate for all groups instead (:func:`ctsplat.training.state.make_optimizer`).

Adaptive density control: :mod:`ctsplat.training.densify` (``densify.strategy``: positional gradient, training
residual, or both; ``densify.prune_redundant``). Seeding (``init``): :mod:`ctsplat.training.seeding`.

Robustness: a non-finite loss or parameter rolls the model back to its last snapshot (taken every 10 iterations
and after each densification, so up to 9 good steps are undone; the iteration count, the view order and the random
streams go on, and a densification due at that iteration is skipped), multiplies the learning rates by
``nan_lr_decay`` and is logged; ``nan_max_consecutive`` such events in a row, or ``nan_max_events`` within
``nan_window`` iterations (a run that diverges every other step never has many in a row), stop the run with a
``CtsplatError``. A run that ends with a collapsed model also fails instead of writing a model (``collapse_*``
keys, see :data:`ctsplat.training.config.TRAIN_DEFAULTS`): too few Gaussians with a visible amplitude, a loss far
above its first interval's for several validations in a row, or a final validation PSNR far below the initial
model's or hardly above an empty model's. Its logs and checkpoints stay for diagnosis; ``model.pt``,
``training.json`` and the other final outputs are removed.

Deterministic on CPU: every random draw comes from generators seeded by ``seed`` whose states are checkpointed,
so ``resume`` continues bit-for-bit (:mod:`ctsplat.training.checkpoint`); a truncated newest checkpoint is moved
aside and the previous one used. The run folder is locked while training (:func:`ctsplat.utils.run_lock`): a
second process writing the same folder fails at once, naming the first.

The run folder gets ``config.json`` (resolved config, hash, code version, scene provenance), ``train_log.csv`` and
``per_view.csv`` (periodic validation, :mod:`ctsplat.formats.runlog`), ``checkpoints/``, the final ``model.pt``
and ``model.ply``, ``model_best.pt`` (the model at the periodic validation with the highest PSNR; kept in
``checkpoints/`` while training, so that a resumed run has it even when a workflow manager removed the outputs) and
``training.json`` (wall time, iterations, events, best iteration). Test metrics are not computed here:
:func:`ctsplat.evaluation.evaluate` reads the finished run folder.

References
----------
Kerbl, B. et al. (2023). 3D Gaussian Splatting for real-time radiance field rendering. ACM TOG 42(4).
Zha, R. et al. (2024). R²-Gaussian: rectifying radiative Gaussian splatting for tomographic reconstruction.
NeurIPS.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from ctsplat.evaluation.metrics import ssim_window
from ctsplat.evaluation.run import (
    check_validation_choices,
    peak_memory_mb,
    per_view_rows,
    render_views,
    view_metrics,
    volume_metrics,
    voxelize_model,
)
from ctsplat.formats.runlog import LOG_COLUMNS, LOG_EXTRAS, PER_VIEW_COLUMNS, CsvLog
from ctsplat.scene import Scene, ViewData, even_subset, load_scene
from ctsplat.splat.render import random_region, render, resolved_backend, voxelize
from ctsplat.training import losses
from ctsplat.training.checkpoint import (
    Checkpoint,
    checkpoint_dir,
    find_resumable,
    load_checkpoint,
    save_checkpoint,
)
from ctsplat.training.config import EVALUATION_KEYS, REFERENCE_INITS, mip_filter, render_kwargs, resolve_config
from ctsplat.training.densify import make_densify, reset_stats
from ctsplat.training.features import Augmenter, density_lambda
from ctsplat.training.poses import PoseCorrection, pose_errors, refine_enabled
from ctsplat.training.seeding import make_seed
from ctsplat.training.state import (
    TrainState,
    ViewSampler,
    all_finite,
    amplitude,
    as_gaussians,
    cosine_factor,
    init_params,
    make_optimizer,
    restore,
    snapshot,
)
from ctsplat.utils import (
    CtsplatError,
    atomic_path,
    check_output_dir,
    code_version,
    compute_platform,
    config_hash,
    json_safe,
    resolve_device,
    run_lock,
    seed_everything,
    write_json_atomic,
)

__all__ = ["train", "check_run_folder", "RUN_OUTPUTS", "RUN_FILES", "ALPHA_OPACITIES", "fit_alpha_seeds"]

log = logging.getLogger(__name__)

#: Files of a run folder that a fresh (not resumed) training run removes first: outputs of an earlier run that
#: would otherwise sit beside the new model.
RUN_OUTPUTS = ("training.json", "metrics.json", "metrics_val.json", "metrics_train.json", "model.pt", "model_best.pt",
               "model.ply", "model_volume.nii.gz", "per_view_test.csv", "per_view_val.csv", "per_view_train.csv",
               "refined_views.json", "refined_views_best.json")

#: The best validation model and its poses: written into ``checkpoints/`` while training, copied out at the end.
BEST_FILES = ("model_best.pt", "refined_views_best.json")

#: Every file a run folder holds: training's, the evaluation's (any split, the figures, the read-outs and their
#: sidecars), the per-run figures (:data:`ctsplat.analysis.RUN_FIGURES`, in ``figures/``), the lock, and the
#: workflow's per-run logs. :func:`train` refuses a folder holding anything else, since a new run replaces the
#: checkpoints and outputs in it.
RUN_FILES = (*RUN_OUTPUTS, *(f"checkpoints/{n}" for n in BEST_FILES), "config.json", "train_log.csv", "per_view.csv",
             "checkpoints/ckpt_*.pt*", "metrics_*.json", "per_view_*.csv", "model_volume_*.nii.gz",
             "model_volume*.json", "gallery.png", "slices.png", "turntable.gif", "figures/*.png", ".ctsplat.lock",
             "logs/*")


def _evaluate_periodic(state: TrainState, cfg: dict[str, Any], scene: Scene, val: ViewData
                       ) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """Validation metrics of the current model: a ``train_log.csv`` row and ``per_view.csv`` rows."""
    g = as_gaussians({k: v.detach() for k, v in state.params.items()})
    rk = render_kwargs(cfg, state.filter_var)
    preds = render_views(g, val.camera, val.Rs, val.ts, rk)
    vm = view_metrics(preds, val.images)
    vol = voxelize_model(g, scene.volume.shape, scene.volume.affine, rk.get("filter_3d_var"))
    m3 = volume_metrics(vol, scene.volume.data, data_range=scene.volume.metric_range)
    row = {"psnr2d": float(np.mean(vm["psnr2d"])), "ssim2d": float(np.mean(vm["ssim2d"])), **m3}
    return row, per_view_rows(state.iteration, val, vm)


def _val_psnr(state: TrainState, cfg: dict[str, Any], val: ViewData) -> float:
    """Mean validation 2D PSNR (dB) of the current model (as ``train_log.csv``'s ``psnr2d``, without the 3D part)."""
    g = as_gaussians({k: v.detach() for k, v in state.params.items()})
    preds = render_views(g, val.camera, val.Rs, val.ts, render_kwargs(cfg, state.filter_var))
    return float(np.mean(view_metrics(preds, val.images)["psnr2d"]))


#: Initial opacities :func:`fit_alpha_seeds` chooses from (3DGS starts at 0.1).
ALPHA_OPACITIES: tuple[float, ...] = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4)


def fit_alpha_seeds(state: TrainState, cfg: dict[str, Any], train: ViewData, *, n_views: int = 8
                    ) -> tuple[float, float]:
    """Scale a fresh alpha model to the training views: colour = the brightest target, opacity fitted.

    Alpha compositing never renders above its brightest colour, so the seeds start at the brightest training
    target (white, in 3DGS's terms); their common initial opacity is the one of :data:`ALPHA_OPACITIES` whose
    rendering has the least squared error on up to ``n_views`` evenly spaced training views. Dense seeds (a
    uniform init) then start faint instead of flooding the air, sparse ones opaque enough to reach the targets.

    Parameters
    ----------
    state : TrainState
        A fresh alpha model (``colors`` (N, 1), ``opacity_raw`` (N,)); set in place.
    cfg : dict
        Resolved ``train`` config (render settings).
    train : ViewData
        Training views: camera, poses (V, 3, 3) / (V, 3), images (V, H, W) (line integrals).
    n_views : int
        Views used for the fit.

    Returns
    -------
    (float, float)
        The colour (line-integral units) and the opacity chosen.
    """
    idx = np.unique(np.linspace(0, len(train.Rs) - 1, min(n_views, len(train.Rs))).round().astype(int))
    y = np.asarray(train.images[idx], np.float64)
    colour = max(float(y.max()), 1e-6)
    rk = render_kwargs(cfg, state.filter_var)
    best: tuple[float, float] | None = None
    with torch.no_grad():
        state.params["colors"].fill_(colour)
        for opacity in ALPHA_OPACITIES:
            state.params["opacity_raw"].fill_(math.log(opacity / (1.0 - opacity)))
            g = as_gaussians({k: v.detach() for k, v in state.params.items()})
            pred = np.asarray(render_views(g, train.camera, train.Rs[idx], train.ts[idx], rk), np.float64)
            sse = float((((pred.mean(-1) if pred.ndim == 4 else pred) - y) ** 2).sum())
            if best is None or sse < best[0]:
                best = (sse, opacity)
        state.params["opacity_raw"].fill_(math.log(best[1] / (1.0 - best[1])))
    return colour, best[1]


def _empty_psnr(val: ViewData) -> float:
    """Mean validation 2D PSNR (dB) of an empty model (all-zero images): the floor a collapsed model sits at."""
    zeros = np.zeros_like(val.images)
    return float(np.mean(view_metrics(zeros, val.images)["psnr2d"]))


def _watch_loss(state: TrainState, cfg: dict[str, Any]) -> str | None:
    """Update the loss watch at a validation; the collapse reason when the loss stayed high too long."""
    h = state.health
    n = int(h.get("loss_n", 0))
    mean = float(h.get("loss_sum", 0.0)) / n if n else None
    h["loss_sum"], h["loss_n"] = 0.0, 0
    if mean is None:
        return None
    if h.get("loss_first") is None:
        h["loss_first"] = mean
        return None
    first, factor, evals = float(h["loss_first"]), float(cfg["collapse_loss_factor"]), int(cfg["collapse_loss_evals"])
    h["loss_high"] = int(h.get("loss_high", 0)) + 1 if first > 0 and mean > factor * first else 0
    if evals and h["loss_high"] >= evals:
        return (f"the mean loss stayed above {factor:g} x its first interval's ({first:.4g}) for {h['loss_high']} "
                f"validations in a row (now {mean:.4g})")
    return None


def _collapse_reason(state: TrainState, cfg: dict[str, Any], row: dict[str, float], final: bool,
                     psnr_empty: float) -> str | None:
    """Why the model counts as collapsed at this validation, or None (see the ``collapse_*`` keys)."""
    reason = _watch_loss(state, cfg)
    if reason:
        return reason
    min_n = int(cfg["collapse_min_gaussians"])
    if min_n:
        amp = amplitude(state.params, cfg["compositor"])
        thr = float(cfg["densify"]["prune_density"])
        alive = int((amp >= thr).sum())
        if alive < min_n:
            what = "opacity" if cfg["compositor"] == "alpha" else "density"
            return (f"only {alive} of {amp.shape[0]} Gaussians have a {what} >= densify.prune_density ({thr:g}), "
                    f"fewer than collapse_min_gaussians ({min_n})")
    if not final:
        return None
    psnr = float(row["psnr2d"])
    drop = float(cfg["collapse_psnr_drop_db"])
    initial = state.health.get("psnr_initial")
    if drop and initial is not None and math.isfinite(initial) and not psnr >= initial - drop:
        return (f"the final validation PSNR {psnr:.2f} dB is more than collapse_psnr_drop_db ({drop:g} dB) below the "
                f"initial model's {initial:.2f} dB")
    # a model that starts near the empty level (alpha or uniform seeds) may stay there a while and be healthy;
    # it has collapsed when it also lost what the initial model had
    margin = float(cfg["collapse_empty_margin_db"])
    if margin and math.isfinite(psnr_empty) and not psnr >= psnr_empty + margin and initial is not None \
            and psnr < initial:
        return (f"the final validation PSNR {psnr:.2f} dB is within collapse_empty_margin_db ({margin:g} dB) of an "
                f"empty model's {psnr_empty:.2f} dB and below the initial model's {initial:.2f} dB")
    return None


#: What an earlier run's evaluation and figures leave in a run folder (patterns of :data:`RUN_FILES`), removed with
#: :data:`RUN_OUTPUTS` when a run starts afresh.
EVALUATION_OUTPUTS = ("metrics_*.json", "per_view_*.csv", "model_volume_*.nii.gz", "model_volume*.json",
                      "gallery.png", "slices.png", "turntable.gif", "figures/*.png")


def _discard_outputs(out_dir: Path) -> None:
    """Remove the final outputs of an earlier run and what its evaluation made of them (they must not sit beside
    a new or failed run's logs)."""
    for name in RUN_OUTPUTS:
        (out_dir / name).unlink(missing_ok=True)
    for pattern in EVALUATION_OUTPUTS:
        for path in out_dir.glob(pattern):
            path.unlink(missing_ok=True)


def _restore_logs(out_dir: Path, ck: Checkpoint, logs: dict[str, CsvLog]) -> None:
    """Put the logs back as they were at the checkpoint (the files may be gone: a workflow manager removes a
    killed job's outputs); checkpoints without stored logs truncate the files instead."""
    stored = ck.payload.get("logs") or {}
    for name, csv_log in logs.items():
        if name in stored:
            with atomic_path(out_dir / name) as tmp:
                tmp.write_text(stored[name])
        if name not in stored or not csv_log.header_matches():  # (a checkpoint of code that logged other columns)
            csv_log.truncate_after(ck.iteration)


def train(config: dict[str, Any], out_dir: str | Path, *, resume: bool | Literal["auto"] = False,
          callback: Callable[[int, TrainState], None] | None = None) -> dict[str, Any]:
    """Train a Gaussian model and write the run folder (see the module docstring).

    Parameters
    ----------
    config : dict
        The ``train`` section (see :data:`TRAIN_DEFAULTS`); unknown keys and out-of-range values raise
        ``CtsplatError``.
    out_dir : path
        Run folder: ``config.json``, ``train_log.csv``, ``per_view.csv``, ``checkpoints/``, ``model.pt``,
        ``model.ply``, ``training.json``. Locked while training: a second process fails fast.
    resume : bool or "auto"
        False: start from scratch (existing checkpoints and final outputs are removed). True: continue from the
        newest readable checkpoint in ``out_dir/checkpoints``; one written with a different config raises
        ``CtsplatError``. ``"auto"`` (the workflow): continue when that checkpoint has this config's hash, else
        start from scratch. Without a readable checkpoint both start from scratch.
    callback : callable(iteration, state), optional
        Called after every completed iteration (after logging and checkpointing); used by tests to inject
        faults or interrupt a run.

    Returns
    -------
    dict
        The training summary written to ``training.json``.

    Raises
    ------
    CtsplatError
        Bad config or inputs, an ``out_dir`` holding files that are not a run's (:data:`RUN_FILES`), another
        process writing ``out_dir``, divergence (non-finite steps) or a collapsed model.
    """
    if resume not in (True, False, "auto"):
        raise CtsplatError(f"resume must be True, False or 'auto', got {resume!r}")
    cfg = resolve_config(config)
    out_dir = Path(out_dir)
    check_run_folder(cfg, out_dir)
    # the lock checks that the folder is writable, and removes it again if this run created it and fails on its
    # inputs before writing anything
    with run_lock(out_dir, "output folder"):
        return _train(cfg, out_dir, resume, callback)


def check_run_folder(cfg: dict[str, Any], out_dir: str | Path) -> None:
    """Refuse a run folder that holds files that are not a run's (:data:`RUN_FILES`), or that is or holds one of
    the run's inputs: a new run replaces the checkpoints and outputs in it.

    Parameters
    ----------
    cfg : dict
        The train config (``volume``, ``radiographs``, ``sfm_dir``, ``sfm_radiographs`` are its inputs).
    out_dir : str or Path
        The run folder (need not exist).

    Raises
    ------
    CtsplatError
        One line naming the file in the way.
    """
    inputs = [cfg[k] for k in ("volume", "radiographs", "sfm_dir", "sfm_radiographs") if cfg.get(k)]
    check_output_dir(out_dir, marker=RUN_FILES, inputs=inputs, in_place=True)


def _train(cfg: dict[str, Any], out_dir: Path, resume: bool | str,
           callback: Callable[[int, TrainState], None] | None) -> dict[str, Any]:
    """:func:`train` with a resolved config, holding the run folder's lock."""
    device = resolve_device(str(cfg["device"]))
    chash = config_hash(cfg)
    rng = seed_everything(int(cfg["seed"]))
    gen = torch.Generator(device="cpu")
    gen.manual_seed(int(cfg["seed"]))
    scene = load_scene(cfg)
    ckey = resume_key(cfg, scene)
    check_validation_choices(scene, cfg)  # before any work: the read-out's amount and model: best need them
    window = losses.gaussian_window().numel()
    cam = scene.train.camera
    if float(cfg["lambda_ssim"]) > 0 and min(cam.width, cam.height) < window:
        raise CtsplatError(f"train.lambda_ssim needs radiographs of at least {window} x {window} pixels (the SSIM "
                           f"window), got {cam.width} x {cam.height}; set lambda_ssim: 0 or render larger ones")
    # the scores every evaluation computes (2D SSIM of the views, 3D SSIM of the read-out): before anything is written
    for what, shape, fix in (("radiographs are", (cam.width, cam.height), "render larger ones"),
                             ("reference volume is", scene.volume.shape, "ingest it at a larger grid")):
        try:
            ssim_window(shape)
        except CtsplatError:
            raise CtsplatError(f"the {what} {' x '.join(map(str, shape))}: the SSIM scores need at least 3 on a "
                               f"side; {fix}") from None
    if scene.eval_split != "val":
        log.warning("the radiographs in %s have no validation views: the periodic evaluation (train_log.csv, "
                    "model_best.pt, the collapse checks) scores the test views; the final model is unaffected",
                    cfg["radiographs"])
    vol = scene.volume
    voxel_mm = float(np.mean(vol.spacing_mm))
    half_extent_mm = 0.5 * float(np.max(vol.extent_mm()))
    val = scene.val.take(even_subset(len(scene.val), int(cfg["eval_views"])))
    uses_ref = cfg["init"] in REFERENCE_INITS

    train_log = CsvLog(out_dir / "train_log.csv", LOG_COLUMNS + LOG_EXTRAS)
    view_log = CsvLog(out_dir / "per_view.csv", PER_VIEW_COLUMNS)
    ckpt: Checkpoint | None = None
    if resume:
        ckpt, _ = find_resumable(out_dir, ckey)
        if ckpt is None:
            log.warning("no readable checkpoint in %s; starting from scratch", checkpoint_dir(out_dir))
        elif resume == "auto" and ckpt.config_hash != ckey:
            log.info("the checkpoints in %s belong to another config, other inputs or other code; starting from "
                     "scratch", checkpoint_dir(out_dir))
            ckpt = None
    if ckpt is not None:
        state = load_checkpoint(ckpt, cfg, device, rng, gen, voxel_mm, ckey, half_extent_mm)
        _restore_logs(out_dir, ckpt, {"train_log.csv": train_log, "per_view.csv": view_log})
        log.info("resuming from %s (iteration %d)", ckpt.path, state.iteration)
    else:
        shutil.rmtree(checkpoint_dir(out_dir), ignore_errors=True)
        _discard_outputs(out_dir)
        t_seed = time.perf_counter()
        seed = make_seed(cfg, scene, rng)
        params = init_params(seed, cfg, device)
        # the seed's reconstruction (FDK, ASD-POCS iterations) is part of the method's time: the wall time and
        # the log's timestamps start before it
        state = TrainState(params=params, opt=make_optimizer(params, cfg, voxel_mm, half_extent_mm),
                           elapsed_s=time.perf_counter() - t_seed)
        log.info("seed: %s, %d Gaussians, %.1f s", seed.strategy, len(seed), state.elapsed_s)
        reset_stats(state)
        train_log.reset()
        view_log.reset()
    write_json_atomic(out_dir / "config.json", {"config": cfg, "config_hash": chash, "code_version": code_version(),
                                                "uses_reference_volume": uses_ref, "scene": scene.info})

    # targets on device, scaled to [0, 1]
    image_scale = float(np.max(scene.train.images)) or 1.0
    targets = torch.as_tensor(scene.train.images, device=device)
    if cfg["supervision"] == "transmission":
        targets_loss = torch.exp(-scene.mu_scale * targets)
    else:
        targets_loss = targets / image_scale
    tr_R = torch.as_tensor(scene.train.Rs, dtype=torch.float32, device=device)
    tr_t = torch.as_tensor(scene.train.ts, dtype=torch.float32, device=device)
    # positional gradients in 3DGS's NDC units (d/d ndc = d/d px * size / 2), so the threshold means the same
    ndc_half = torch.tensor([0.5 * scene.train.camera.width, 0.5 * scene.train.camera.height], device=device)
    sampler = ViewSampler(scene.train.azimuth_deg, scene.train.elevation_deg, int(cfg["batch_views"]))
    total = int(cfg["iterations"])
    densify = make_densify(cfg["densify"], compositor=cfg["compositor"], iterations=total)
    tr = scene.train
    augment = Augmenter(cfg["augment"], tr.camera, vol.center_mm())
    state.pose, state.pose_opt = _make_pose_refiner(cfg, scene, device)
    if ckpt is not None and state.pose is not None:
        _load_pose(state, ckpt)
    pr_start = int(cfg["pose_refine"]["start"])
    if ckpt is None or state.filter_var is None or state.filter_var.shape[0] != state.params["means"].shape[0]:
        state.filter_var = mip_filter(cfg, as_gaussians(state.params), tr.camera, tr.Rs, tr.ts)
    if ckpt is None and cfg["compositor"] == "alpha":
        log.info("alpha seeds: colour %.4g (the brightest target), opacity %.3g (fitted to the training views)",
                 *fit_alpha_seeds(state, cfg, tr))
    psnr_empty = _empty_psnr(val)
    if "psnr_initial" not in state.health:
        state.health["psnr_initial"] = _val_psnr(state, cfg, val)
        log.info("initial model: validation PSNR %.2f dB (an empty model: %.2f dB)", state.health["psnr_initial"],
                 psnr_empty)

    lam = {k: float(cfg[k]) for k in ("lambda_l1", "lambda_ssim", "lambda_density", "lambda_scale", "lambda_tv")}
    lambda_density = lam["lambda_density"]
    snap = snapshot(state)
    pose_snap = _pose_snapshot(state)
    show = bool(cfg["progress"]) and sys.stderr.isatty()
    from tqdm import tqdm

    bar = tqdm(total=total, initial=state.iteration, disable=not show, desc="train", dynamic_ncols=True)
    t_start = time.perf_counter() - state.elapsed_s
    t_last, it_last = time.perf_counter(), state.iteration
    last_terms: dict[str, torch.Tensor] = {}
    last_loss = float("nan")
    # the finite losses since the last validation, summed on the device (float64, as the host sum it feeds) and
    # read at validations and checkpoints only
    loss_sum = torch.tensor(float(state.health.get("loss_sum", 0.0)), dtype=torch.float64, device=device)
    while state.iteration < total:
        it = state.iteration + 1
        f = cosine_factor(it - 1, total, float(cfg["lr_final_factor"])) * state.lr_factor
        for g_ in state.opt.param_groups:
            g_["lr"] = g_["initial_lr"] * f
        refining = state.pose is not None and it > pr_start
        if state.pose_opt is not None:
            for g_ in state.pose_opt.param_groups:
                g_["lr"] = g_["initial_lr"] * f
        if not state.queue:
            state.queue = sampler.refill(rng)
        batch = state.queue.pop(0)
        lam["lambda_density"] = density_lambda(lambda_density, it - 1, total, cfg["lambda_density_warmup"])
        tv_region = random_region(vol.shape, int(cfg["tv_size"]), generator=gen) if lam["lambda_tv"] > 0 else None

        ok = all_finite(state.params.values())
        loss = None
        outs = []
        if ok:
            g = as_gaussians(state.params)
            rk = render_kwargs(cfg, state.filter_var)
            imgs = []
            for vi in batch:
                R_i, t_i = augment.pose(tr_R[vi], tr_t[vi], rng)
                g_i = as_gaussians(state.pose.transform(state.params, vi)) if refining else g
                out = render(g_i, scene.train.camera, R_i, t_i, **rk)
                img = out.image.mean(-1) if out.image.ndim == 3 else out.image
                outs.append(out)
                if cfg["supervision"] == "transmission":
                    imgs.append(torch.exp(-scene.mu_scale * img))
                else:
                    imgs.append(img / image_scale)
            pred = torch.stack(imgs)
            ref = augment.target(targets_loss[batch], gen)
            tv_vol = None
            if tv_region is not None:
                tv_vol = voxelize(g, vol.shape, vol.affine, region=tv_region, filter_3d_var=rk.get("filter_3d_var"))
            loss, terms = losses.total_loss(pred, ref, density=g.densities, scales=g.scales, data_range=1.0,
                                            tv_volume=tv_vol, **lam)
            if refining:
                loss = loss + state.pose.prior(batch)
        err_ratios = []
        if ok and densify.wants_error and densify.collecting(it):
            err_ratios = [densify.error_ratios(state, pred[k], pred[k] - ref[k], out.visible)
                          for k, out in enumerate(outs)]
        if ok:
            state.opt.zero_grad(set_to_none=True)
            if refining:
                state.pose_opt.zero_grad(set_to_none=True)
            loss.backward()  # a non-finite loss is caught below with the gradients, in one host synchronisation
            ok = all_finite([loss.detach(), *(p.grad for p in state.params.values()),
                             *((p.grad for p in state.pose.parameters()) if refining else ())])
        if ok:
            with torch.no_grad():
                for out in outs:
                    densify.accumulate(state, out.means2d.grad, out.visible, ndc_half, loss_views=len(outs))
                for ratios in err_ratios:
                    densify.accumulate_error(state, ratios)
            state.opt.step()
            if refining:
                state.pose_opt.step()
                state.pose.fix_gauge()
            ok = all_finite([*state.params.values(), *(state.pose.parameters() if refining else ())])
        if not ok:
            state.nan_events += 1
            state.nan_consecutive += 1
            window = int(cfg["nan_window"])
            state.nan_iters = [i for i in state.nan_iters if i > it - window] + [it]
            state.lr_factor *= float(cfg["nan_lr_decay"])
            log.warning("non-finite loss or parameter at iteration %d: rolled back, learning rate x%.3g "
                        "(%d in a row, %d in the last %d iterations)", it, state.lr_factor, state.nan_consecutive,
                        len(state.nan_iters), window)
            restore(state, snap)
            _pose_restore(state, pose_snap)
            if state.nan_consecutive >= int(cfg["nan_max_consecutive"]):
                bar.close()
                raise CtsplatError(
                    f"training diverged: {state.nan_consecutive} non-finite steps in a row (last at iteration {it})"
                    f" even after lowering the learning rate to x{state.lr_factor:.3g}; lower train.lr or check "
                    "the inputs")
            if len(state.nan_iters) >= int(cfg["nan_max_events"]):
                bar.close()
                raise CtsplatError(
                    f"training diverged: {len(state.nan_iters)} non-finite steps within {window} iterations "
                    f"(iterations {state.nan_iters[0]}..{it}, nan_max_events {cfg['nan_max_events']}) even after "
                    f"lowering the learning rate to x{state.lr_factor:.3g}; lower train.lr or check the inputs")
        else:
            state.nan_consecutive = 0
            last_terms, last_loss_t = terms, loss.detach()
            loss_sum = loss_sum + last_loss_t.double()
            state.health["loss_n"] = int(state.health.get("loss_n", 0)) + 1
        state.iteration = it

        counts = densify.maybe_step(state, it, vol, gen) if ok else None
        if counts is not None:
            for k in state.densify_counts:
                state.densify_counts[k] += counts[k]
            log.info("%s at %d: %s", "densify" if densify.due(it) else "prune", it, counts)
            state.filter_var = mip_filter(cfg, as_gaussians(state.params), tr.camera, tr.Rs, tr.ts)
        if ok and (counts is not None or it % 10 == 0):
            snap = snapshot(state)
            pose_snap = _pose_snapshot(state)

        bar.update(1)
        if it % int(cfg["eval_every"]) == 0 or it == total:
            state.health["loss_sum"] = float(loss_sum)
            if last_terms:
                last_loss = float(last_loss_t)
            row, per_view = _evaluate_periodic(state, cfg, scene, val)
            now = time.perf_counter()
            ips = (it - it_last) / max(now - t_last, 1e-9)
            t_last, it_last = now, it
            state.elapsed_s = now - t_start
            terms_now = {k: float(v) for k, v in last_terms.items()}
            row.update(iteration=it, timestamp=round(state.elapsed_s, 3), loss=last_loss,
                       l1=terms_now.get("l1"), dssim=terms_now.get("dssim"),
                       density_reg=terms_now.get("density"), scale_reg=terms_now.get("scale"),
                       tv=terms_now.get("tv"), n_gaussians=int(state.params["means"].shape[0]),
                       lr_means=float(state.opt.param_groups[0]["lr"]), iters_per_s=round(ips, 3),
                       nan_events=state.nan_events, **state.densify_counts)
            train_log.append([row])
            view_log.append(per_view)
            bar.set_postfix(loss=f"{last_loss:.4f}", psnr=f"{row['psnr2d']:.2f}", n=row["n_gaussians"])
            if state.pose is not None:
                err = _pose_errors(state, scene)
                log.info("pose refinement at %d: median rotation error %.3f deg, isocentre %.3f mm", it,
                         err["pose_rot_err_median_deg_after"], err["pose_iso_err_median_mm_after"])
            reason = _collapse_reason(state, cfg, row, it == total, psnr_empty)
            loss_sum = torch.tensor(float(state.health.get("loss_sum", 0.0)), dtype=torch.float64, device=device)
            if reason:
                bar.close()
                _discard_outputs(out_dir)
                raise CtsplatError(f"training collapsed at iteration {it}: {reason}; no model written (logs kept "
                                   f"in {out_dir}); lower train.lr or check the inputs")
            if not float(row["psnr2d"]) <= float(state.health.get("best_psnr", -math.inf)):
                state.health.update(best_psnr=float(row["psnr2d"]), best_iteration=it)
                # kept beside the checkpoints until the run ends: a workflow manager removes a failed or rerun
                # job's outputs, and a resumed run may not beat the best again
                best_dir = checkpoint_dir(out_dir)
                best_dir.mkdir(parents=True, exist_ok=True)
                if state.pose is not None:  # the poses this model is fitted to, for its evaluation
                    _write_refined_views(state, scene, best_dir, name="refined_views_best.json")
                    state.health["best_model_poses"] = _pose_errors(state, scene)
                _save_model(state, cfg, best_dir / "model_best.pt", chash, scene.mu_scale)
        if it % int(cfg["checkpoint_every"]) == 0 or it == total:
            state.health["loss_sum"] = float(loss_sum)
            state.elapsed_s = time.perf_counter() - t_start
            # the peak so far, across resumes: a resumed process alone would report only its own span
            state.health["peak_memory_mb"] = max(float(state.health.get("peak_memory_mb", 0.0)),
                                                 peak_memory_mb(device)[0])
            save_checkpoint(out_dir, state, rng, gen, ckey, int(cfg["keep_checkpoints"]))
            # a run resumed from this checkpoint rolls a non-finite step back to it: so does this one
            snap = snapshot(state)
            pose_snap = _pose_snapshot(state)
        if callback is not None:
            callback(it, state)
    bar.close()
    train_time = time.perf_counter() - t_start
    return _write_model(state, cfg, scene, out_dir, device, train_time, chash)


def resume_key(cfg: dict[str, Any], scene: Scene) -> str:
    """What a checkpoint must have been written for to be continued: this config, this scene's content and this
    code.

    The config names its inputs by path only, so a view set rendered again under the same path (a Snakemake rerun
    after an input changed), another SfM model, or a code fix would otherwise resume a finished run from its last
    checkpoint and write the old model again.

    Parameters
    ----------
    cfg : dict
        The resolved train config.
    scene : Scene
        The loaded scene: every split's images, poses and camera, and the volume's content id.

    Returns
    -------
    str
        A hash (:func:`ctsplat.utils.config_hash`) of the config, a SHA-256 of the scene's arrays and the SfM
        seed points (when ``sfm_dir`` is set), and :func:`ctsplat.utils.code_version`.
    """
    h = hashlib.sha256(scene.volume.volume_id.encode())
    for views in (scene.train, scene.val, scene.test):
        h.update(json.dumps(views.camera.to_dict(), sort_keys=True).encode())
        for array in (views.ids, views.Rs, views.ts, views.images):
            h.update(np.ascontiguousarray(array).tobytes())
    points = Path(str(cfg.get("sfm_dir") or "")) / "points3d.ply"
    if cfg.get("sfm_dir") and points.is_file():  # the colmap seed reads them
        h.update(points.read_bytes())
    trained = {k: v for k, v in cfg.items() if k not in EVALUATION_KEYS}  # they do not change the trained model
    return config_hash({"config": trained, "scene": h.hexdigest(), "code_version": code_version()})


def _save_model(state: TrainState, cfg: dict[str, Any], path: Path, chash: str, mu_scale: float) -> Any:
    """Write the current model to ``path`` (``.pt``) with its provenance, iteration and how it renders (compositor,
    mip, ``mu_scale_per_mm``: densities are normalised, times it in 1/mm); returns the Gaussians."""
    g = as_gaussians({k: v.detach() for k, v in state.params.items()})
    if state.filter_var is not None:  # the 3D filter this model was rendered with: evaluation uses the same
        g.filter_3d_var = state.filter_var.detach()
    g.meta.update(config_hash=chash, uses_reference_volume=cfg["init"] in REFERENCE_INITS, init=cfg["init"],
                  compositor=cfg["compositor"], mip=bool(cfg["mip"]), mu_scale_per_mm=float(mu_scale),
                  iteration=state.iteration)
    if "best_psnr" in state.health:
        g.meta.update(best_iteration=int(state.health["best_iteration"]), best_val_psnr=state.health["best_psnr"])
    g.save(path)
    return g


def _write_model(state: TrainState, cfg: dict[str, Any], scene: Scene, out_dir: Path, device: torch.device,
                 train_time: float, chash: str) -> dict[str, Any]:
    """The final model (``model.pt``, ``model.ply``), the best validation model (``model_best.pt``, saved in
    ``checkpoints/`` at the periodic evaluations, and its poses) and the training summary (``training.json``)."""
    for name in BEST_FILES:
        kept = checkpoint_dir(out_dir) / name
        if kept.is_file():
            with atomic_path(out_dir / name) as tmp:
                shutil.copyfile(kept, tmp)
    g = _save_model(state, cfg, out_dir / "model.pt", chash, scene.mu_scale)
    g.to_ply(out_dir / "model.ply")
    summary = {
        "wall_time_s": round(train_time, 3),
        "iterations": state.iteration,
        "iters_per_s": round(state.iteration / max(train_time, 1e-9), 3),
        "n_gaussians": len(g),
        "nan_events": state.nan_events,
        "best_iteration": state.health.get("best_iteration"),
        "best_val_psnr": state.health.get("best_psnr"),
        **{f"densify_{k}": v for k, v in state.densify_counts.items()},
        "n_train_views": len(scene.train),
        "eval_split_during_training": scene.eval_split,
        "device": str(device),
        "renderer": resolved_backend("auto", device),
        "platform": compute_platform(device),
        "config_hash": chash,
        "code_version": code_version(),
    }
    summary.update(pose_refine=state.pose is not None, **_pose_errors(state, scene))
    if state.pose is not None:
        _write_refined_views(state, scene, out_dir)
        summary["best_model_poses"] = state.health.get("best_model_poses")
    peak, summary["peak_memory_kind"] = peak_memory_mb(device)
    summary["peak_memory_mb"] = round(max(peak, float(state.health.get("peak_memory_mb", 0.0))), 1)
    write_json_atomic(out_dir / "training.json", json_safe(summary))
    return summary


# ------------------------------------------------------------------------------------------ pose refinement
def _make_pose_refiner(cfg: dict[str, Any], scene: Scene, device: torch.device
                       ) -> tuple[PoseCorrection | None, torch.optim.Adam | None]:
    """The training views' pose corrections and their Adam (rates in radians and mm per step), or None, None."""
    if not refine_enabled(cfg):
        return None, None
    pr = cfg["pose_refine"]
    tr = scene.train
    pose = PoseCorrection(tr.Rs, tr.ts, scene.isocenter_mm, tr.camera.model, cone_model=str(pr["cone_model"]),
                          prior_rot_deg=float(pr["prior_rot_deg"]),
                          prior_trans_mm=float(pr["prior_trans_mm"]), prior_weight=float(pr["prior_weight"]),
                          device=device)
    groups = [{"params": [pose.omega], "lr": math.radians(float(pr["lr_rot_deg"])), "name": "pose_rot"},
              {"params": [pose.tau], "lr": float(pr["lr_trans_mm"]), "name": "pose_trans"}]
    for g_ in groups:
        g_["initial_lr"] = g_["lr"]
    return pose, torch.optim.Adam(groups, eps=1e-15)


def _load_pose(state: TrainState, ckpt: Checkpoint) -> None:
    """The corrections and their optimiser state of a checkpoint (a resumed run continues them exactly)."""
    stored = ckpt.payload.get("pose")
    if stored is None:
        raise CtsplatError(f"checkpoint {ckpt.path} has no pose corrections although pose refinement is on; start "
                           "over (ctsplat train --restart)")
    state.pose.load(stored["corrections"])
    state.pose_opt.load_state_dict(stored["optimizer"])


def _pose_snapshot(state: TrainState) -> dict[str, Any] | None:
    """A copy of the corrections and their Adam state to roll back to after a non-finite step."""
    if state.pose is None:
        return None
    import copy

    return {"corrections": state.pose.state(), "optimizer": copy.deepcopy(state.pose_opt.state_dict())}


def _pose_restore(state: TrainState, snap: dict[str, Any] | None) -> None:
    if state.pose is None or snap is None:
        return
    state.pose.load(snap["corrections"])
    state.pose_opt.load_state_dict(snap["optimizer"])


def _pose_errors(state: TrainState, scene: Scene) -> dict[str, float]:
    """Rotation and isocentre errors of the training poses against the true ones, before and after refinement."""
    tr = scene.train
    Rs_true, ts_true = tr.truth()
    model = tr.camera.model
    before = pose_errors(tr.Rs, tr.ts, Rs_true, ts_true, scene.isocenter_mm, model)
    if state.pose is None:
        after = before
    else:
        Rs, ts = state.pose.corrected_poses()
        after = pose_errors(Rs, ts, Rs_true, ts_true, scene.isocenter_mm, model)
    out = {f"pose_{k}_before": v for k, v in before.items()}
    out.update({f"pose_{k}_after": v for k, v in after.items()})
    return out


def _write_refined_views(state: TrainState, scene: Scene, out_dir: Path, *, name: str = "refined_views.json") -> None:
    """``name`` (``refined_views.json``): the corrected training poses now, with their corrections, their starting
    poses and the iteration."""
    tr = scene.train
    Rs, ts = state.pose.corrected_poses()
    om = np.degrees(state.pose.omega.detach().cpu().double().numpy())
    ta = (state.pose.tau * state.pose.mask).detach().cpu().double().numpy()
    views = [{"id": int(tr.ids[i]), "R": Rs[i].tolist(), "t": ts[i].tolist(), "R_start": tr.Rs[i].tolist(),
              "t_start": tr.ts[i].tolist(), "omega_deg": om[i].tolist(), "tau_mm": ta[i].tolist()}
             for i in range(len(tr))]
    write_json_atomic(out_dir / name, {
        "format": "ctsplat.refined_views", "format_version": 1, "iteration": state.iteration,
        "camera": tr.camera.to_dict(),
        "isocenter_mm": np.asarray(scene.isocenter_mm, float).tolist(),
        "convention": "x_cam = R x + t (OpenCV); omega (deg, camera frame) turns the camera about the isocentre, "
                      "tau (mm, camera frame) shifts it: R = exp(omega) R_start, t = exp(omega) (t_start - c) + c + "
                      "tau, c = R_start iso + t_start",
        "views": views})
