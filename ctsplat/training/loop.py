"""Training loop: a rectified radiative Gaussian model fitted to the radiographs of a scene.

Objective (per step, over a batch of training views; images are normalised-volume line integrals divided by a
fixed ``image_scale`` = max of the training targets, so they lie in [0, 1])::

    L = λ1 L1 + λs (1 - SSIM) + λρ mean(ρ) + λscale mean(‖s‖) + λtv TV(voxelised random sub-volume)

(:mod:`ctsplat.training.losses`). With ``supervision: transmission`` the compared images are ``exp(-μ_scale p)``
instead.

Optimiser: Adam with one parameter group per quantity (means, log-scales, quaternions, density; plus opacity and
colour for the alpha compositor), each with its own learning rate decayed by a cosine from ``lr`` to
``lr × lr_final_factor``. Mean learning rates are given in voxels per step (multiplied by the mean voxel edge).

Adaptive density control: :mod:`ctsplat.training.densify`. Seeding (``init``): :mod:`ctsplat.training.seeding`.

Robustness: a non-finite loss or parameter rolls back to the last good state, multiplies the learning rates by
``nan_lr_decay`` and is logged; ``nan_max_consecutive`` such events in a row stop the run with a ``CtsplatError``.
Deterministic on CPU: every random draw comes from generators seeded by ``seed`` whose states are checkpointed,
so ``resume`` continues bit-for-bit (:mod:`ctsplat.training.checkpoint`).

The run folder gets ``config.json`` (resolved config, hash, code version, scene provenance), ``train_log.csv`` and
``per_view.csv`` (periodic validation, :mod:`ctsplat.formats.runlog`), ``checkpoints/``, the final ``model.pt``
and ``model.ply`` and ``training.json`` (wall time, iterations, events). Test metrics are not computed here:
:func:`ctsplat.evaluation.evaluate` reads the finished run folder.

References
----------
Kerbl, B. et al. (2023). 3D Gaussian Splatting for real-time radiance field rendering. ACM TOG 42(4).
Zha, R. et al. (2024). R²-Gaussian: rectifying radiative Gaussian splatting for tomographic reconstruction.
NeurIPS.
"""
from __future__ import annotations

import logging
import os
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat.evaluation.run import peak_memory_mb, render_views, view_metrics, volume_metrics, voxelize_model
from ctsplat.formats.runlog import LOG_COLUMNS, LOG_EXTRAS, PER_VIEW_COLUMNS, CsvLog
from ctsplat.scene import Scene, ViewData, even_subset, load_scene
from ctsplat.splat.render import random_region, render, voxelize
from ctsplat.training import losses
from ctsplat.training.checkpoint import checkpoint_dir, latest_checkpoint, load_checkpoint, save_checkpoint
from ctsplat.training.config import mip_filter, render_kwargs, resolve_config
from ctsplat.training.densify import GradientDensify
from ctsplat.training.seeding import make_seed
from ctsplat.training.state import (
    TrainState,
    ViewSampler,
    as_gaussians,
    cosine_factor,
    init_params,
    make_optimizer,
    params_finite,
    restore,
    snapshot,
)
from ctsplat.utils import (
    CtsplatError,
    code_version,
    config_hash,
    json_safe,
    resolve_device,
    seed_everything,
    write_json_atomic,
)

__all__ = ["train", "RUN_OUTPUTS"]

log = logging.getLogger(__name__)

#: Files of a run folder that a fresh (not resumed) training run removes first: outputs of an earlier run that
#: would otherwise sit beside the new model.
RUN_OUTPUTS = ("training.json", "metrics.json", "model.pt", "model.ply", "model_volume.nii.gz", "per_view_test.csv")


def _check_writable(out_dir: Path) -> None:
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".write_probe_{os.getpid()}"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise CtsplatError(f"output folder {out_dir} is not writable ({exc.strerror or exc}); choose another "
                           "folder or fix its permissions") from exc


def _evaluate_periodic(state: TrainState, cfg: dict[str, Any], scene: Scene, val: ViewData
                       ) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """Validation metrics of the current model: a ``train_log.csv`` row and ``per_view.csv`` rows."""
    g = as_gaussians({k: v.detach() for k, v in state.params.items()})
    rk = render_kwargs(cfg, state.filter_var)
    preds = render_views(g, val.camera, val.Rs, val.ts, rk)
    vm = view_metrics(preds, val.images)
    vol = voxelize_model(g, scene.volume.shape, scene.volume.affine, rk.get("filter_3d_var"))
    m3 = volume_metrics(vol, scene.volume.data)
    row = {"psnr2d": float(np.mean(vm["psnr2d"])), "ssim2d": float(np.mean(vm["ssim2d"])), **m3}
    per_view = [
        {"iteration": state.iteration, "view_id": int(i), "azimuth_deg": float(a), "elevation_deg": float(e),
         "split": val.split, "psnr2d": float(p), "ssim2d": float(s)}
        for i, a, e, p, s in zip(val.ids, val.azimuth_deg, val.elevation_deg, vm["psnr2d"], vm["ssim2d"],
                                 strict=True)
    ]
    return row, per_view



def train(config: dict[str, Any], out_dir: str | Path, *, resume: bool = False,
          callback: Callable[[int, TrainState], None] | None = None) -> dict[str, Any]:
    """Train a Gaussian model and write the run folder (see the module docstring).

    Parameters
    ----------
    config : dict
        The ``train`` section (see :data:`TRAIN_DEFAULTS`); unknown keys raise ``CtsplatError``.
    out_dir : path
        Run folder: ``config.json``, ``train_log.csv``, ``per_view.csv``, ``checkpoints/``, ``model.pt``,
        ``model.ply``, ``training.json``.
    resume : bool
        Continue from the newest checkpoint in ``out_dir/checkpoints`` (same config required). Without a
        checkpoint the run starts from scratch.
    callback : callable(iteration, state), optional
        Called after every completed iteration (after logging and checkpointing); used by tests to inject
        faults or interrupt a run.

    Returns
    -------
    dict
        The training summary written to ``training.json``.
    """
    cfg = resolve_config(config)
    out_dir = Path(out_dir)
    _check_writable(out_dir)
    device = resolve_device(str(cfg["device"]))
    chash = config_hash(cfg)
    rng = seed_everything(int(cfg["seed"]))
    gen = torch.Generator(device="cpu")
    gen.manual_seed(int(cfg["seed"]))
    scene = load_scene(cfg)
    vol = scene.volume
    voxel_mm = float(np.mean(vol.spacing_mm))
    val = scene.val.take(even_subset(len(scene.val), int(cfg["eval_views"])))
    uses_ref = cfg["init"] == "volume"

    train_log = CsvLog(out_dir / "train_log.csv", LOG_COLUMNS + LOG_EXTRAS)
    view_log = CsvLog(out_dir / "per_view.csv", PER_VIEW_COLUMNS)
    ckpt = latest_checkpoint(out_dir) if resume else None
    if ckpt is not None:
        state = load_checkpoint(ckpt, cfg, device, rng, gen, voxel_mm, chash)
        train_log.truncate_after(state.iteration)
        view_log.truncate_after(state.iteration)
        log.info("resuming from %s (iteration %d)", ckpt, state.iteration)
    else:
        if resume:
            log.warning("no checkpoint in %s; starting from scratch", checkpoint_dir(out_dir))
        shutil.rmtree(checkpoint_dir(out_dir), ignore_errors=True)
        for name in RUN_OUTPUTS:
            (out_dir / name).unlink(missing_ok=True)
        seed = make_seed(cfg, scene, rng)
        params = init_params(seed, cfg, device)
        state = TrainState(params=params, opt=make_optimizer(params, cfg, voxel_mm))
        n0 = params["means"].shape[0]
        state.grad_accum = torch.zeros(n0, device=device)
        state.grad_count = torch.zeros(n0, device=device)
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
    densify = GradientDensify(cfg["densify"], compositor=cfg["compositor"], iterations=total)
    tr = scene.train
    state.filter_var = mip_filter(cfg, as_gaussians(state.params), tr.camera, tr.Rs, tr.ts)

    lam = {k: float(cfg[k]) for k in ("lambda_l1", "lambda_ssim", "lambda_density", "lambda_scale", "lambda_tv")}
    snap = snapshot(state)
    show = bool(cfg["progress"]) and sys.stderr.isatty()
    from tqdm import tqdm

    bar = tqdm(total=total, initial=state.iteration, disable=not show, desc="train", dynamic_ncols=True)
    t_start = time.perf_counter() - state.elapsed_s
    t_last, it_last = time.perf_counter(), state.iteration
    last_terms: dict[str, float] = {}
    last_loss = float("nan")
    while state.iteration < total:
        it = state.iteration + 1
        f = cosine_factor(it - 1, total, float(cfg["lr_final_factor"])) * state.lr_factor
        for g_ in state.opt.param_groups:
            g_["lr"] = g_["initial_lr"] * f
        if not state.queue:
            state.queue = sampler.refill(rng)
        batch = state.queue.pop(0)
        tv_region = random_region(vol.shape, int(cfg["tv_size"]), generator=gen) if lam["lambda_tv"] > 0 else None

        ok = params_finite(state.params)
        loss = None
        outs = []
        if ok:
            g = as_gaussians(state.params)
            rk = render_kwargs(cfg, state.filter_var)
            imgs = []
            for vi in batch:
                out = render(g, scene.train.camera, tr_R[vi], tr_t[vi], **rk)
                img = out.image.mean(-1) if out.image.ndim == 3 else out.image
                outs.append(out)
                if cfg["supervision"] == "transmission":
                    imgs.append(torch.exp(-scene.mu_scale * img))
                else:
                    imgs.append(img / image_scale)
            pred = torch.stack(imgs)
            ref = targets_loss[batch]
            tv_vol = None
            if tv_region is not None:
                tv_vol = voxelize(g, vol.shape, torch.as_tensor(vol.affine, dtype=torch.float32, device=device),
                                  region=tv_region, filter_3d_var=rk.get("filter_3d_var"))
            loss, terms = losses.total_loss(pred, ref, density=g.densities, scales=g.scales, data_range=1.0,
                                            tv_volume=tv_vol, **lam)
            ok = bool(torch.isfinite(loss))
        if ok:
            state.opt.zero_grad(set_to_none=True)
            loss.backward()
            ok = all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in state.params.values())
        if ok:
            with torch.no_grad():
                for out in outs:
                    densify.accumulate(state, out.means2d.grad, out.visible, ndc_half)
            state.opt.step()
            ok = params_finite(state.params)
        if not ok:
            state.nan_events += 1
            state.nan_consecutive += 1
            state.lr_factor *= float(cfg["nan_lr_decay"])
            log.warning("non-finite loss or parameter at iteration %d: rolled back, learning rate x%.3g "
                        "(%d in a row)", it, state.lr_factor, state.nan_consecutive)
            restore(state, snap)
            if state.nan_consecutive >= int(cfg["nan_max_consecutive"]):
                bar.close()
                raise CtsplatError(
                    f"training diverged: {state.nan_consecutive} non-finite steps in a row (last at iteration {it})"
                    f" even after lowering the learning rate to x{state.lr_factor:.3g}; lower train.lr or check "
                    "the inputs")
        else:
            state.nan_consecutive = 0
            last_terms, last_loss = terms, float(loss.detach())
        state.iteration = it

        counts = densify.maybe_step(state, it, vol, gen) if ok else None
        if counts is not None:
            for k in state.densify_counts:
                state.densify_counts[k] += counts[k]
            log.info("densify at %d: %s", it, counts)
            state.filter_var = mip_filter(cfg, as_gaussians(state.params), tr.camera, tr.Rs, tr.ts)
        if ok and (counts is not None or it % 10 == 0):
            snap = snapshot(state)

        bar.update(1)
        if it % int(cfg["eval_every"]) == 0 or it == total:
            row, per_view = _evaluate_periodic(state, cfg, scene, val)
            now = time.perf_counter()
            ips = (it - it_last) / max(now - t_last, 1e-9)
            t_last, it_last = now, it
            state.elapsed_s = now - t_start
            row.update(iteration=it, timestamp=round(state.elapsed_s, 3), loss=last_loss,
                       l1=last_terms.get("l1"), dssim=last_terms.get("dssim"),
                       density_reg=last_terms.get("density"), scale_reg=last_terms.get("scale"),
                       tv=last_terms.get("tv"), n_gaussians=int(state.params["means"].shape[0]),
                       lr_means=float(state.opt.param_groups[0]["lr"]), iters_per_s=round(ips, 3),
                       nan_events=state.nan_events, **state.densify_counts)
            train_log.append([row])
            view_log.append(per_view)
            bar.set_postfix(loss=f"{last_loss:.4f}", psnr=f"{row['psnr2d']:.2f}", n=row["n_gaussians"])
        if it % int(cfg["checkpoint_every"]) == 0 or it == total:
            state.elapsed_s = time.perf_counter() - t_start
            save_checkpoint(out_dir, state, rng, gen, chash, int(cfg["keep_checkpoints"]))
        if callback is not None:
            callback(it, state)
    bar.close()
    train_time = time.perf_counter() - t_start
    return _write_model(state, cfg, scene, out_dir, device, train_time, chash)



def _write_model(state: TrainState, cfg: dict[str, Any], scene: Scene, out_dir: Path, device: torch.device,
                 train_time: float, chash: str) -> dict[str, Any]:
    """The final model (``model.pt``, ``model.ply``) and the training summary (``training.json``)."""
    g = as_gaussians({k: v.detach() for k, v in state.params.items()})
    g.meta.update(config_hash=chash, uses_reference_volume=cfg["init"] == "volume", init=cfg["init"],
                  compositor=cfg["compositor"])
    g.save(out_dir / "model.pt")
    g.to_ply(out_dir / "model.ply")
    summary = {
        "wall_time_s": round(train_time, 3),
        "iterations": state.iteration,
        "iters_per_s": round(state.iteration / max(train_time, 1e-9), 3),
        "n_gaussians": len(g),
        "nan_events": state.nan_events,
        **{f"densify_{k}": v for k, v in state.densify_counts.items()},
        "n_train_views": len(scene.train),
        "eval_split_during_training": scene.eval_split,
        "device": str(device),
        "config_hash": chash,
        "code_version": code_version(),
    }
    summary["peak_memory_mb"], summary["peak_memory_kind"] = peak_memory_mb(device)
    summary["peak_memory_mb"] = round(summary["peak_memory_mb"], 1)
    write_json_atomic(out_dir / "training.json", json_safe(summary))
    return summary
