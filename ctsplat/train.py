"""Training a rectified radiative Gaussian model from radiographs: seeding, optimisation, densification, logging.

Objective (per step, over a batch of training views; images are normalised-volume line integrals divided by a
fixed ``image_scale`` = max of the training targets, so they lie in [0, 1])::

    L = λ1 L1 + λs (1 - SSIM) + λρ mean(ρ) + λscale mean(‖s‖) + λtv TV(voxelised random sub-volume)

(:mod:`ctsplat.losses`). With ``supervision: transmission`` the compared images are ``exp(-μ_scale p)`` instead.

Optimiser: Adam with one parameter group per quantity (means, log-scales, quaternions, density; plus opacity and
colour for the alpha compositor), each with its own learning rate decayed by a cosine from ``lr`` to
``lr × lr_final_factor``. Mean learning rates are given in voxels per step (multiplied by the mean voxel edge).

Adaptive density control every ``densify.interval`` steps within ``[densify.start, densify.stop]``: Gaussians whose
mean view-space positional gradient (norm of ∂L/∂(u, v) in 3DGS's NDC units, i.e. per-pixel gradient × W/2, H/2)
exceeds ``densify.grad_threshold`` are cloned when small (max scale
≤ ``densify.clone_max_scale_voxels`` voxels) or split in two (samples from the Gaussian, scales / 1.6) when large.
In the radiative compositors mass is conserved: a clone and its original get half the density each; split children
get ρ·1.6³/2 so the pair carries the parent's mass ``ρ (2π)^{3/2} Π s`` (``densify.split_mass: halve`` gives the
literal ρ/2 rule, which removes 1 - 2/1.6³ ≈ 76 % of a split Gaussian's mass). Then Gaussians with
ρ < ``prune_density``, oversized ones (max scale > ``prune_max_scale_fraction`` × volume extent) and those
whose centre left the volume box are pruned; the total is capped at ``max_gaussians`` (largest gradients first).

Robustness: a non-finite loss or parameter rolls back to the last good state, multiplies the learning rates by
``nan_lr_decay`` and is logged; ``nan_max_consecutive`` such events in a row stop the run with a ``CtsplatError``.
Deterministic on CPU: every random draw comes from generators seeded by ``seed`` whose states are checkpointed,
so ``resume`` continues bit-for-bit.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat import evaluate as ev
from ctsplat import losses, seeding
from ctsplat.utils import (
    CtsplatError,
    atomic_path,
    code_version,
    config_hash,
    json_safe,
    merge_config,
    resolve_device,
    seed_everything,
    write_json_atomic,
)

__all__ = ["TRAIN_DEFAULTS", "ViewData", "Scene", "load_scene", "render_kwargs", "train", "LOG_COLUMNS"]

log = logging.getLogger(__name__)

INITS = ("volume", "uniform", "fbp", "sfm")
COMPOSITORS = ("radiative", "radiative_unrectified", "alpha")
POSES = ("gt", "colmap")
SUPERVISIONS = ("line_integral", "transmission")
LOG_COLUMNS = ["iteration", "timestamp", "psnr2d", "ssim2d", "psnr3d", "ssim3d"]
LOG_EXTRAS = ["loss", "l1", "dssim", "density_reg", "scale_reg", "tv", "n_gaussians", "lr_means", "iters_per_s",
              "nan_events", "cloned", "split", "pruned"]
PER_VIEW_COLUMNS = ["iteration", "view_id", "azimuth_deg", "elevation_deg", "split", "psnr2d", "ssim2d"]

TRAIN_DEFAULTS: dict[str, Any] = {
    "volume": "",  # reference volume (.nii.gz): grid for 3D metrics, and the values for init: volume
    "radiographs": "",  # folder with line_integrals.tif + views.json
    "poses": "gt",  # gt | colmap
    "sfm_dir": "",  # folder of the sfm step (aligned_views.json, summary.json, points3d.ply)
    "min_registration_rate": 0.5,  # poses: colmap fails below this fraction of registered views
    "init": "fbp",  # volume | uniform | fbp | sfm
    "n_init": 50000,
    "init_top_fraction": 0.3,  # volume/fbp: voxels in the top 30 % are candidates
    "init_scale_voxels": None,  # null: 0.75 voxel for volume (the method's rule), 1.5 for fbp (smoother seed)
    "init_density": 0.05,  # uniform / sfm seeds (normalised units)
    "sfm_fill_fraction": 0.5,
    "fbp_filter": "ramp",
    "compositor": "radiative",  # radiative | radiative_unrectified | alpha
    "mip": False,
    "views": 0,  # number of training views used (evenly over the train split); 0 = all
    "seed": 0,
    "device": "auto",  # auto | cpu | cuda
    "iterations": 3000,
    "batch_views": 1,
    "supervision": "line_integral",  # line_integral | transmission
    "lambda_l1": 1.0,
    "lambda_ssim": 0.2,
    "lambda_density": 5e-5,
    "lambda_scale": 1e-4,
    "lambda_tv": 0.05,  # 0 disables
    "tv_size": 32,  # voxels per side of the random TV sub-volume
    "lr": {"means": 0.02, "scales": 5e-3, "quats": 1e-3, "density": 0.01, "opacity": 0.05, "colors": 0.01},
    "lr_final_factor": 0.1,
    "densify": {
        "interval": 500,
        "start": 500,
        "stop": 0,  # 0 = 0.75 × iterations
        "grad_threshold": 2e-4,
        "clone_max_scale_voxels": 1.5,
        "prune_density": 1e-4,
        "prune_max_scale_fraction": 0.2,
        "max_gaussians": 200000,
        "split_mass": "conserve",  # conserve | halve (radiative compositors; see densify_and_prune)
    },
    "eval_every": 250,
    "eval_views": 8,  # validation views per periodic evaluation (evenly spaced); 0 = all
    "checkpoint_every": 500,
    "keep_checkpoints": 2,
    "nan_lr_decay": 0.5,
    "nan_max_consecutive": 3,
    "figures": True,
    "turntable_frames": 24,
    "fps_width": 1920,
    "fps_height": 1080,
    "progress": True,
}


# ------------------------------------------------------------------------------------------ config
def resolve_config(config: dict[str, Any] | None) -> dict[str, Any]:
    """Fill defaults and validate choices; unknown keys and bad values raise ``CtsplatError``."""
    cfg = merge_config("train", config, TRAIN_DEFAULTS)
    for key, allowed in (("init", INITS), ("compositor", COMPOSITORS), ("poses", POSES),
                         ("supervision", SUPERVISIONS)):
        if cfg[key] not in allowed:
            raise CtsplatError(f"unknown train.{key} {cfg[key]!r}; allowed: {', '.join(allowed)}")
    if cfg["device"] not in ("auto", "cpu") and not str(cfg["device"]).startswith("cuda"):
        raise CtsplatError(f"unknown train.device {cfg['device']!r}; allowed: auto, cpu, cuda")
    for key in ("iterations", "n_init", "batch_views", "eval_every", "checkpoint_every"):
        if int(cfg[key]) <= 0:
            raise CtsplatError(f"train.{key} must be a positive integer, got {cfg[key]!r}")
    if int(cfg["views"]) < 0:
        raise CtsplatError(f"train.views must be >= 0 (0 = all training views), got {cfg['views']}")
    if cfg["supervision"] == "transmission" and cfg["compositor"] == "alpha":
        raise CtsplatError("supervision: transmission needs a radiative compositor (alpha images are not "
                           "line integrals)")
    if cfg["densify"]["split_mass"] not in ("conserve", "halve"):
        raise CtsplatError(f"unknown train.densify.split_mass {cfg['densify']['split_mass']!r}; allowed: conserve, "
                           "halve")
    if not cfg["volume"]:
        raise CtsplatError("train.volume is empty: give the preprocessed reference volume (.nii.gz)")
    if not cfg["radiographs"]:
        raise CtsplatError("train.radiographs is empty: give the folder written by `ctsplat project`")
    if (cfg["poses"] == "colmap" or cfg["init"] == "sfm") and not cfg["sfm_dir"]:
        raise CtsplatError(f"train.sfm_dir is empty but poses={cfg['poses']}, init={cfg['init']} needs the sfm "
                           "step's folder")
    return cfg


# ------------------------------------------------------------------------------------------ scene
@dataclass
class ViewData:
    """Views of one split with their camera, poses and target images (normalised line integrals).

    Attributes
    ----------
    camera : ParallelCamera | ConeCamera
    ids : (V,) int; Rs : (V, 3, 3); ts : (V, 3) mm; azimuth_deg, elevation_deg : (V,)
    images : (V, H, W) float32 — line integrals of the normalised volume (targets / mu_scale_per_mm), mm.
    split : str
    """

    camera: Any
    ids: np.ndarray
    Rs: np.ndarray
    ts: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    images: np.ndarray
    split: str

    def __len__(self) -> int:
        return int(len(self.ids))

    def take(self, idx: np.ndarray) -> ViewData:
        idx = np.asarray(idx, int)
        return ViewData(self.camera, self.ids[idx], self.Rs[idx], self.ts[idx], self.azimuth_deg[idx],
                        self.elevation_deg[idx], self.images[idx], self.split)


@dataclass
class Scene:
    """Everything training and evaluation read: views per split, reference volume, scales, provenance."""

    train: ViewData
    val: ViewData
    test: ViewData
    volume: Any  # ctsplat.volume.Volume (normalised)
    mu_scale: float
    eval_split: str
    info: dict[str, Any] = field(default_factory=dict)


def _read_radiographs(folder: Path) -> tuple[np.ndarray, Any]:
    """(images (V, H, W) float32 line integrals, ViewSet) from a radiographs folder."""
    if not folder.is_dir():
        raise CtsplatError(f"radiographs folder {folder} does not exist; run `ctsplat project` first")
    try:
        from ctsplat.projector import load_radiographs
    except ImportError:  # pragma: no cover - projector not installed yet
        load_radiographs = None
    if load_radiographs is not None:
        images, vs = load_radiographs(folder)
    else:  # pragma: no cover
        import tifffile

        from ctsplat.geometry import ViewSet

        vs = ViewSet.load(folder / "views.json")
        if not (folder / "line_integrals.tif").exists():
            raise CtsplatError(f"{folder}/line_integrals.tif is missing; re-run `ctsplat project`")
        images = tifffile.imread(folder / "line_integrals.tif")
    images = np.asarray(images, np.float32)
    if images.ndim == 2:
        images = images[None]
    if images.shape[0] != len(vs.views) or images.shape[1:] != (vs.camera.height, vs.camera.width):
        raise CtsplatError(
            f"{folder}: {images.shape[0]} images of {images.shape[1:]} px do not match views.json "
            f"({len(vs.views)} views of {(vs.camera.height, vs.camera.width)} px); re-run `ctsplat project`")
    return images, vs


def _view_data(vs: Any, images: np.ndarray, rows: np.ndarray, split: str, mu_scale: float) -> ViewData:
    views = [vs.views[i] for i in rows]
    return ViewData(
        camera=vs.camera,
        ids=np.array([v.id for v in views], int),
        Rs=np.stack([v.R for v in views]) if views else np.zeros((0, 3, 3)),
        ts=np.stack([v.t for v in views]) if views else np.zeros((0, 3)),
        azimuth_deg=np.array([v.azimuth_deg for v in views], float),
        elevation_deg=np.array([v.elevation_deg for v in views], float),
        images=(images[rows] / mu_scale).astype(np.float32) if len(rows) else
        np.zeros((0, vs.camera.height, vs.camera.width), np.float32),
        split=split,
    )


def _even_subset(n_total: int, n: int) -> np.ndarray:
    """``n`` indices spread evenly over ``range(n_total)`` (all when n is 0 or >= n_total)."""
    if n <= 0 or n >= n_total:
        return np.arange(n_total)
    return np.floor(np.arange(n) * n_total / n).astype(int)


def _sfm_defaults() -> dict[str, Any]:
    """``ctsplat.sfm.SFM_DEFAULTS`` (empty when the sfm module cannot be imported)."""
    try:
        from ctsplat.sfm import SFM_DEFAULTS
    except ImportError:  # pragma: no cover
        return {}
    return dict(SFM_DEFAULTS)


def _colmap_train(cfg: dict[str, Any], volume: Any, mu_scale: float) -> tuple[ViewData, dict[str, Any]]:
    """Training views with COLMAP poses from the sfm folder; targets rendered at the *true* poses."""
    from ctsplat.geometry import ViewSet

    sfm_dir = Path(cfg["sfm_dir"])
    summary_path = sfm_dir / "summary.json"
    if not summary_path.exists():
        raise CtsplatError(f"{summary_path} does not exist; run the sfm step before training with poses: colmap")
    summary = json.loads(summary_path.read_text())
    rate = float(summary.get("registration_rate", 0.0))
    n_total = int(summary.get("n_views", 0))
    if rate < float(cfg["min_registration_rate"]) or not (sfm_dir / "aligned_views.json").exists():
        raise CtsplatError(
            f"SfM registered only {rate:.0%} of {n_total} views (need >= {cfg['min_registration_rate']:.0%} for "
            f"poses: colmap; {summary.get('reason', 'no aligned poses')}); use poses: gt or improve the sfm step")
    if not summary.get("ok", False):
        log.warning("sfm summary is not ok (%s); training with its poses anyway", summary.get("reason", ""))
    aligned = ViewSet.load(sfm_dir / "aligned_views.json")
    if aligned.volume_id != volume.volume_id:
        raise CtsplatError(f"SfM poses in {sfm_dir} belong to volume {aligned.volume_id}, not {volume.volume_id}; "
                           "re-run the sfm step for this volume")
    ids = np.array([v.id for v in aligned.views], int)
    true_views = sfm_dir / "views.json"
    if true_views.exists() and (sfm_dir / "line_integrals.tif").exists():
        images_all, vs_true = _read_radiographs(sfm_dir)
        by_id = {v.id: i for i, v in enumerate(vs_true.views)}
        images = images_all[[by_id[i] for i in ids]]
    elif (sfm_dir / "true_views.json").exists():  # true poses saved by the sfm step: render targets there
        from ctsplat.projector import line_integrals

        tv = ViewSet.load(sfm_dir / "true_views.json")
        by_id = {v.id: v for v in tv.views}
        missing = [int(i) for i in ids if int(i) not in by_id]
        if missing:
            raise CtsplatError(f"{sfm_dir}/true_views.json lacks registered view id {missing[0]}; re-run the sfm step")
        scfg = {**_sfm_defaults(), **summary.get("config", {})}
        mu = torch.from_numpy(np.asarray(volume.data, np.float32) * mu_scale)
        with torch.no_grad():
            p = line_integrals(mu, torch.from_numpy(np.asarray(volume.affine, np.float64)), tv.camera,
                               torch.from_numpy(np.stack([by_id[int(i)].R for i in ids])),
                               torch.from_numpy(np.stack([by_id[int(i)].t for i in ids])),
                               step_voxels=float(scfg.get("step_voxels", 0.5)))
        images = p.cpu().numpy().astype(np.float32)
        n_total = n_total or len(tv.views)
    else:  # re-render the SfM orbit at the true poses (the SfM step keeps only 8-bit feature images)
        from ctsplat.projector import line_integrals
        from ctsplat.sfm import SFM_DEFAULTS, design_orbit

        scfg = {**SFM_DEFAULTS, **summary.get("config", {})}
        kw = {}
        if "orbit_jitter_deg" in scfg:  # the true (jittered) orbit of the sfm step, seeded by its seed
            kw = {"jitter_deg": float(scfg["orbit_jitter_deg"]), "seed": int(summary.get("seed", 0))}
        orbit = design_orbit(int(scfg["n_views"]), float(scfg["arc_deg"]), float(scfg["wobble_deg"]),
                             float(scfg["wobble_cycles"]), float(scfg["dso_mm"]), volume.center_mm(), **kw)
        mu = torch.from_numpy(np.asarray(volume.data, np.float32) * mu_scale)
        with torch.no_grad():
            p = line_integrals(mu, torch.from_numpy(np.asarray(volume.affine, np.float64)), aligned.camera,
                               torch.from_numpy(orbit["Rs"][ids]), torch.from_numpy(orbit["ts"][ids]),
                               step_voxels=float(scfg["step_voxels"]))
        images = p.cpu().numpy().astype(np.float32)
        n_total = n_total or int(scfg["n_views"])
    vd = _view_data(aligned, images, np.arange(len(ids)), "train", mu_scale)
    info = {"sfm_registration_rate": rate, "sfm_views_total": n_total, "views_dropped_unregistered":
            int(n_total - len(ids)), "sfm_ok": bool(summary.get("ok", False))}
    return vd, info


def load_scene(cfg: dict[str, Any]) -> Scene:
    """Read the reference volume and the radiographs, check they belong together, and build the splits."""
    from ctsplat.formats.volume import load_volume

    volume = load_volume(cfg["volume"])
    images, vs = _read_radiographs(Path(cfg["radiographs"]))
    if vs.volume_id != volume.volume_id:
        raise CtsplatError(
            f"radiographs in {cfg['radiographs']} were rendered from volume {vs.volume_id}, but train.volume is "
            f"{volume.volume_id}; re-render the radiographs for this volume or point to the matching volume")
    recorded = vs.meta.get("volume_shape")
    if recorded is not None and tuple(recorded) != volume.shape:
        raise CtsplatError(f"radiographs were rendered from a {tuple(recorded)} volume but train.volume is "
                           f"{volume.shape}; re-render the radiographs")
    mu_scale = volume.mu_scale_per_mm
    if not mu_scale > 0:
        raise CtsplatError(f"volume {cfg['volume']} has a non-positive mu_scale_per_mm ({mu_scale})")
    split_rows = {s: np.array([i for i, v in enumerate(vs.views) if v.split == s], int)
                  for s in ("train", "val", "test")}
    info: dict[str, Any] = {"views_dropped_unregistered": 0}
    if cfg["poses"] == "colmap":
        train, extra = _colmap_train(cfg, volume, mu_scale)
        info.update(extra)
    else:
        if split_rows["train"].size == 0:
            raise CtsplatError(f"radiographs in {cfg['radiographs']} have an empty train split; re-render with a "
                               "non-zero train fraction")
        rows = split_rows["train"]
        order = np.argsort(np.mod(np.asarray([vs.views[i].azimuth_deg for i in rows]), 360.0), kind="stable")
        rows = rows[order][_even_subset(rows.size, int(cfg["views"]))]
        train = _view_data(vs, images, rows, "train", mu_scale)
    if len(train) == 0:
        raise CtsplatError("the train split is empty after selecting views; check train.views and the view set")
    if split_rows["test"].size == 0 and split_rows["val"].size == 0:
        raise CtsplatError(f"radiographs in {cfg['radiographs']} have no val or test views to evaluate on; "
                           "re-render with non-zero val/test fractions")
    test_rows = split_rows["test"] if split_rows["test"].size else split_rows["val"]
    val_rows = split_rows["val"] if split_rows["val"].size else split_rows["test"]
    eval_split = "val" if split_rows["val"].size else "test"
    test = _view_data(vs, images, test_rows, "test", mu_scale)
    val = _view_data(vs, images, val_rows, eval_split, mu_scale)
    info.update(n_train_views=len(train), n_val_views=len(val), n_test_views=len(test),
                radiographs_volume_id=vs.volume_id, camera=vs.camera.to_dict(), train_camera=train.camera.to_dict())
    return Scene(train=train, val=val, test=test, volume=volume, mu_scale=mu_scale, eval_split=eval_split, info=info)


# ------------------------------------------------------------------------------------------ seeding
def make_seed(cfg: dict[str, Any], scene: Scene, rng: np.random.Generator) -> seeding.Seed:
    """The initial Gaussians for ``cfg['init']`` (only ``volume`` reads the reference voxel values)."""
    vol = scene.volume
    n = int(cfg["n_init"])
    lo, hi = seeding.grid_bounds_mm(vol.shape, vol.affine)
    scale = cfg["init_scale_voxels"]
    if cfg["init"] == "volume":
        return seeding.seed_from_grid(vol.data, vol.affine, n, rng, top_fraction=cfg["init_top_fraction"],
                                      scale_voxels=0.75 if scale is None else float(scale), uses_reference_volume=True,
                                      strategy="volume")
    if cfg["init"] == "uniform":
        return seeding.seed_uniform(lo, hi, n, rng, density=cfg["init_density"])
    if cfg["init"] == "sfm":
        pts = seeding.read_ply_points(Path(cfg["sfm_dir"]) / "points3d.ply")
        return seeding.seed_from_points(pts, lo, hi, n, rng, fill_fraction=cfg["sfm_fill_fraction"],
                                        density=cfg["init_density"])
    recon, method = fbp_reconstruction(scene, cfg.get("fbp_filter", "ramp"))
    return seeding.seed_from_grid(recon, vol.affine, n, rng, top_fraction=cfg["init_top_fraction"],
                                  scale_voxels=1.5 if scale is None else float(scale), uses_reference_volume=False,
                                  strategy="fbp" if method == "fbp" else "fbp (sirt)")


SIRT_SEED_ITERATIONS = 10


def fbp_reconstruction(scene: Scene, filter_name: str = "ramp") -> tuple[np.ndarray, str]:
    """Reconstruction of the *training* projections only onto the reference grid (geometry only, no voxel values).

    Circular parallel-beam orbits at elevation 0 use slice-wise FBP (``ctsplat.baselines.fbp_volume``); any other
    geometry (cone beam, wobbling or spherical orbits, SfM poses) uses ``SIRT_SEED_ITERATIONS`` iterations of
    ``ctsplat.baselines.sirt_volume``, which works with the projector's own geometry. The training targets are
    already normalised line integrals, so the result is in normalised units.

    Returns
    -------
    recon : ndarray (I, J, K) float32
    method : "fbp" or "sirt"
    """
    from ctsplat.baselines import fbp_volume, is_circular_parallel, sirt_volume
    from ctsplat.formats.volume import Volume
    from ctsplat.geometry import View, ViewSet

    tr = scene.train
    views = [View(int(i), R, t, float(a), float(e), "train")
             for i, R, t, a, e in zip(tr.ids, tr.Rs, tr.ts, tr.azimuth_deg, tr.elevation_deg, strict=True)]
    vs = ViewSet(tr.camera, views, scene.volume.volume_id, scene.volume.center_mm(), {})
    grid = Volume(np.zeros(scene.volume.shape, np.float32), np.asarray(scene.volume.affine, float), {})
    if is_circular_parallel(vs):
        return np.asarray(fbp_volume(tr.images, vs, grid, filter_name=filter_name, mu_scale_per_mm=1.0),
                          np.float32), "fbp"
    recon = sirt_volume(tr.images, vs, grid, iterations=SIRT_SEED_ITERATIONS, mu_scale_per_mm=1.0)
    return np.asarray(recon, np.float32), "sirt"


# ------------------------------------------------------------------------------------------ model state
PARAM_GROUPS = {"means": "means", "log_scales": "scales", "quats": "quats", "density_raw": "density",
                "opacity_raw": "opacity", "colors": "colors"}


def init_params(seed: seeding.Seed, cfg: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
    """Leaf parameter tensors (float32, requires_grad) from a seed."""
    from ctsplat.gaussians import Gaussians

    kw: dict[str, Any] = {}
    if cfg["compositor"] == "alpha":
        kw = {"opacities": 0.1, "colors": np.full((len(seed), 1), 0.5, np.float32)}
    g = Gaussians.from_values(seed.means, seed.scales, seed.densities, dtype=torch.float32, device=device, **kw)
    return {k: v.detach().clone().requires_grad_(True) for k, v in g.tensors().items() if k in PARAM_GROUPS}


def as_gaussians(params: dict[str, torch.Tensor]) -> Any:
    from ctsplat.gaussians import Gaussians

    return Gaussians(**params)


def render_kwargs(cfg: dict[str, Any], gaussians: Any, scene: Scene) -> dict[str, Any]:
    """Renderer keyword arguments for this config (3D mip filter from the training cameras when ``mip``)."""
    kw: dict[str, Any] = {"compositor": cfg["compositor"], "mip_2d": bool(cfg["mip"])}
    if cfg["mip"]:
        from ctsplat.render import compute_3d_filter

        kw["filter_3d_var"] = compute_3d_filter(gaussians.detach(), scene.train.camera, scene.train.Rs,
                                                scene.train.ts)
    return kw


def _make_optimizer(params: dict[str, torch.Tensor], cfg: dict[str, Any], voxel_mm: float) -> torch.optim.Adam:
    groups = []
    for name, p in params.items():
        lr = float(cfg["lr"][PARAM_GROUPS[name]]) * (voxel_mm if name == "means" else 1.0)
        groups.append({"params": [p], "lr": lr, "initial_lr": lr, "name": name})
    return torch.optim.Adam(groups, eps=1e-15)


def _cosine(it: int, total: int, final_factor: float) -> float:
    """Cosine decay factor from 1 at ``it = 0`` to ``final_factor`` at ``it = total``."""
    x = min(max(it / max(total, 1), 0.0), 1.0)
    return final_factor + (1.0 - final_factor) * 0.5 * (1.0 + math.cos(math.pi * x))


def _replace_params(opt: torch.optim.Adam, params: dict[str, torch.Tensor], keep: torch.Tensor,
                    new: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Keep rows ``keep`` of every parameter, append ``new`` rows; Adam moments follow (zeros for new rows)."""
    out = {}
    for group in opt.param_groups:
        name = group["name"]
        old = group["params"][0]
        state = opt.state.pop(old, {})
        extra = new.get(name)
        data = old.detach()[keep]
        if extra is not None and extra.shape[0]:
            data = torch.cat([data, extra.detach().to(data)])
        p = data.clone().requires_grad_(True)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                s = state[key][keep]
                if extra is not None and extra.shape[0]:
                    s = torch.cat([s, torch.zeros((extra.shape[0], *s.shape[1:]), dtype=s.dtype, device=s.device)])
                state[key] = s
            opt.state[p] = state
        group["params"][0] = p
        out[name] = p
    return out


@dataclass
class TrainState:
    """Mutable training state (checkpointed)."""

    params: dict[str, torch.Tensor]
    opt: torch.optim.Adam
    iteration: int = 0
    grad_accum: torch.Tensor | None = None
    grad_count: torch.Tensor | None = None
    lr_factor: float = 1.0
    nan_events: int = 0
    nan_consecutive: int = 0
    elapsed_s: float = 0.0
    queue: list[list[int]] = field(default_factory=list)
    filter_var: torch.Tensor | None = None
    densify_counts: dict[str, int] = field(default_factory=lambda: {"cloned": 0, "split": 0, "pruned": 0})


class ViewSampler:
    """Stratified view sampling over direction.

    Training views are ordered by azimuth (then elevation) and cut into ``batch`` contiguous strata; each epoch
    permutes every stratum and each batch takes one view per stratum, so every batch spans the directions and
    every view is used once per epoch (for ``batch = 1``: a random permutation per epoch).
    """

    def __init__(self, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, batch: int) -> None:
        order = np.lexsort((np.asarray(elevation_deg), np.mod(np.asarray(azimuth_deg), 360.0)))
        batch = max(1, min(int(batch), order.size))
        self.strata = [s for s in np.array_split(order, batch) if s.size]

    def refill(self, rng: np.random.Generator) -> list[list[int]]:
        perms = [rng.permutation(s) for s in self.strata]
        m = max(p.size for p in perms)
        return [[int(p[i % p.size]) for p in perms] for i in range(m)]


# ------------------------------------------------------------------------------------------ densification
def densify_and_prune(state: TrainState, cfg: dict[str, Any], scene: Scene, gen: torch.Generator) -> dict[str, int]:
    """One adaptive density control step (see module docstring). Returns counts of cloned/split/pruned."""
    from ctsplat.gaussians import inverse_softplus, quat_to_rotmat

    d = cfg["densify"]
    p = state.params
    n = p["means"].shape[0]
    dev = p["means"].device
    vol = scene.volume
    voxel = float(np.mean(vol.spacing_mm))
    with torch.no_grad():
        avg = state.grad_accum / state.grad_count.clamp_min(1)
        scales = torch.exp(p["log_scales"])
        smax = scales.max(-1).values
        dens = torch.nn.functional.softplus(p["density_raw"])
        cand = avg >= float(d["grad_threshold"])
        small = smax <= float(d["clone_max_scale_voxels"]) * voxel
        clone = cand & small
        split = cand & ~small
        budget = int(d["max_gaussians"]) - n
        n_new = int(clone.sum()) + int(split.sum())  # each adds one Gaussian net
        if n_new > max(budget, 0):
            idx = torch.nonzero(cand).flatten()
            order = torch.argsort(avg[idx], descending=True, stable=True)
            allowed = idx[order[: max(budget, 0)]]
            sel = torch.zeros(n, dtype=torch.bool, device=dev)
            sel[allowed] = True
            clone &= sel
            split &= sel
        radiative = cfg["compositor"] != "alpha"
        new_dens = dens.clone()
        if radiative:
            new_dens[clone] = dens[clone] * 0.5
            # each child has (1/1.6)^3 of the parent's volume: "conserve" keeps the pair's mass equal to the
            # parent's (ρ_child = ρ 1.6^3 / 2); "halve" is the literal rule ρ/2 (loses 76 % of the mass)
            grow = 1.6**3 if d["split_mass"] == "conserve" else 1.0
            new_dens[split] = dens[split] * 0.5 * grow
        new_raw = inverse_softplus(new_dens.clamp_min(1e-12))
        # clones: exact copies (half density each in radiative mode)
        ci = torch.nonzero(clone).flatten()
        si = torch.nonzero(split).flatten()
        add: dict[str, list[torch.Tensor]] = {k: [] for k in p}
        for k in p:
            src = new_raw if k == "density_raw" else p[k].detach()
            add[k].append(src[ci])
        # splits: two samples from the Gaussian, scales / 1.6; the original is replaced by the first sample
        if si.numel():
            rot = quat_to_rotmat(p["quats"].detach()[si])
            z = torch.randn((2, si.numel(), 3), generator=gen, dtype=torch.float32).to(dev)
            offs = torch.einsum("nij,knj->kni", rot, z * scales[si][None])
            s_new = torch.log(scales[si] / 1.6)
            for k in p:
                src = new_raw if k == "density_raw" else p[k].detach()
                if k == "means":
                    add[k].append(p["means"].detach()[si] + offs[0])
                    add[k].append(p["means"].detach()[si] + offs[1])
                elif k == "log_scales":
                    add[k].extend([s_new, s_new])
                else:
                    add[k].extend([src[si], src[si]])
        keep = torch.ones(n, dtype=torch.bool, device=dev)
        keep[si] = False
        # write halved densities of cloned originals
        p["density_raw"].data.copy_(torch.where(clone, new_raw, p["density_raw"].detach()))
        new = {k: torch.cat(v) if v else p[k].detach()[:0] for k, v in add.items()}
        # pruning criteria on survivors + new rows
        all_means = torch.cat([p["means"].detach()[keep], new["means"]])
        all_ls = torch.cat([p["log_scales"].detach()[keep], new["log_scales"]])
        all_dr = torch.cat([p["density_raw"].detach()[keep], new["density_raw"]])
        lo, hi = seeding.grid_bounds_mm(vol.shape, vol.affine)
        lo_t = torch.as_tensor(lo - 2 * voxel, dtype=all_means.dtype, device=dev)
        hi_t = torch.as_tensor(hi + 2 * voxel, dtype=all_means.dtype, device=dev)
        extent = float(np.max(hi - lo))
        bad = (torch.nn.functional.softplus(all_dr) < float(d["prune_density"]))
        bad |= torch.exp(all_ls).max(-1).values > float(d["prune_max_scale_fraction"]) * extent
        bad |= ((all_means < lo_t) | (all_means > hi_t)).any(-1)
        if bool(bad.all()):  # never prune everything
            bad[:] = False
    # apply: first keep/append, then prune
    state.params = _replace_params(state.opt, p, torch.nonzero(keep).flatten(), new)
    good = torch.nonzero(~bad).flatten()
    state.params = _replace_params(state.opt, state.params, good, {})
    m = state.params["means"].shape[0]
    state.grad_accum = torch.zeros(m, device=dev)
    state.grad_count = torch.zeros(m, device=dev)
    return {"cloned": int(ci.numel()), "split": int(si.numel()), "pruned": int(bad.sum()), "n": m}


# ------------------------------------------------------------------------------------------ logging
class CsvLog:
    """Append-only CSV with a fixed header; ``truncate_after(it)`` drops rows logged after a checkpoint."""

    def __init__(self, path: Path, columns: list[str]) -> None:
        self.path = path
        self.columns = columns

    def reset(self) -> None:
        with atomic_path(self.path) as tmp:
            tmp.write_text(",".join(self.columns) + "\n")

    def truncate_after(self, iteration: int) -> None:
        if not self.path.exists():
            self.reset()
            return
        with open(self.path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        with atomic_path(self.path) as tmp, open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=self.columns)
            w.writeheader()
            for r in rows:
                if int(r["iteration"]) <= iteration:
                    w.writerow({k: r.get(k, "") for k in self.columns})

    def append(self, rows: list[dict[str, Any]]) -> None:
        with open(self.path, "a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=self.columns)
            for r in rows:
                w.writerow({k: _fmt(r.get(k, "")) for k in self.columns})
            fh.flush()
            os.fsync(fh.fileno())

    def read(self) -> list[dict[str, str]]:
        with open(self.path, newline="") as fh:
            return list(csv.DictReader(fh))


def _fmt(v: Any) -> Any:
    if isinstance(v, float):
        return repr(v)
    return v


# ------------------------------------------------------------------------------------------ checkpoints
def _ckpt_dir(out_dir: Path) -> Path:
    return out_dir / "checkpoints"


def latest_checkpoint(out_dir: Path) -> Path | None:
    files = sorted(_ckpt_dir(out_dir).glob("ckpt_*.pt"))
    return files[-1] if files else None


def save_checkpoint(out_dir: Path, state: TrainState, rng: np.random.Generator, gen: torch.Generator,
                    cfg_hash: str, keep: int) -> Path:
    path = _ckpt_dir(out_dir) / f"ckpt_{state.iteration:08d}.pt"
    payload = {
        "format": "ctsplat.train_checkpoint",
        "config_hash": cfg_hash,
        "iteration": state.iteration,
        "params": {k: v.detach().cpu() for k, v in state.params.items()},
        "optimizer": state.opt.state_dict(),
        "grad_accum": state.grad_accum.cpu(),
        "grad_count": state.grad_count.cpu(),
        "lr_factor": state.lr_factor,
        "nan_events": state.nan_events,
        "nan_consecutive": state.nan_consecutive,
        "elapsed_s": state.elapsed_s,
        "queue": state.queue,
        "densify_counts": state.densify_counts,
        "np_rng": json.dumps(rng.bit_generator.state),
        "torch_gen": gen.get_state(),
        "torch_rng": torch.get_rng_state(),
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    for old in sorted(_ckpt_dir(out_dir).glob("ckpt_*.pt"))[:-max(1, keep)]:
        old.unlink(missing_ok=True)
    return path


def _load_checkpoint(path: Path, cfg: dict[str, Any], device: torch.device, rng: np.random.Generator,
                     gen: torch.Generator, voxel_mm: float, cfg_hash: str) -> TrainState:
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for corrupt files
        raise CtsplatError(f"cannot read checkpoint {path}: {str(exc).splitlines()[0]}; delete it to restart") from exc
    if ck.get("format") != "ctsplat.train_checkpoint":
        raise CtsplatError(f"{path} is not a ctsplat training checkpoint")
    if ck["config_hash"] != cfg_hash:
        raise CtsplatError(f"checkpoint {path} was written with a different config (hash {ck['config_hash']} vs "
                           f"{cfg_hash}); resume with the same config or start without --resume")
    params = {k: v.to(device).requires_grad_(True) for k, v in ck["params"].items()}
    opt = _make_optimizer(params, cfg, voxel_mm)
    opt.load_state_dict(ck["optimizer"])
    rng.bit_generator.state = json.loads(ck["np_rng"])
    gen.set_state(ck["torch_gen"])
    torch.set_rng_state(ck["torch_rng"])
    return TrainState(
        params=params, opt=opt, iteration=int(ck["iteration"]), grad_accum=ck["grad_accum"].to(device),
        grad_count=ck["grad_count"].to(device), lr_factor=float(ck["lr_factor"]), nan_events=int(ck["nan_events"]),
        nan_consecutive=int(ck["nan_consecutive"]), elapsed_s=float(ck["elapsed_s"]),
        queue=[list(map(int, b)) for b in ck["queue"]], densify_counts=dict(ck["densify_counts"]),
    )


def _snapshot(state: TrainState) -> dict[str, Any]:
    return {
        "params": {k: v.detach().clone() for k, v in state.params.items()},
        "opt": {k: (v.clone() if torch.is_tensor(v) else v) for k, v in _opt_tensors(state.opt).items()},
    }


def _opt_tensors(opt: torch.optim.Adam) -> dict[str, Any]:
    out = {}
    for g in opt.param_groups:
        st = opt.state.get(g["params"][0], {})
        for key, v in st.items():
            out[f"{g['name']}/{key}"] = v
    return out


def _restore(state: TrainState, snap: dict[str, Any]) -> None:
    for g in state.opt.param_groups:
        name = g["name"]
        old = g["params"][0]
        st = state.opt.state.pop(old, {})
        p = snap["params"][name].clone().requires_grad_(True)
        g["params"][0] = p
        state.params[name] = p
        new_st = {}
        for key in ("step", "exp_avg", "exp_avg_sq"):
            if f"{name}/{key}" in snap["opt"]:
                new_st[key] = snap["opt"][f"{name}/{key}"].clone()
        if new_st or st:
            state.opt.state[p] = new_st
    m = state.params["means"].shape[0]
    if state.grad_accum is None or state.grad_accum.shape[0] != m:
        state.grad_accum = torch.zeros(m, device=state.params["means"].device)
        state.grad_count = torch.zeros(m, device=state.params["means"].device)


def _params_finite(params: dict[str, torch.Tensor]) -> bool:
    return all(bool(torch.isfinite(v).all()) for v in params.values())


# ------------------------------------------------------------------------------------------ training
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
    g = as_gaussians({k: v.detach() for k, v in state.params.items()})
    rk = {"compositor": cfg["compositor"], "mip_2d": bool(cfg["mip"])}
    if cfg["mip"]:
        rk["filter_3d_var"] = state.filter_var
    preds = ev.render_views(g, val.camera, val.Rs, val.ts, rk)
    vm = ev.view_metrics(preds, val.images)
    vol = ev.voxelize_model(g, scene.volume.shape, scene.volume.affine, rk.get("filter_3d_var"))
    m3 = ev.volume_metrics(vol, scene.volume.data)
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
    """Train a Gaussian model and write the run folder; returns the final metrics (``metrics.json``).

    Parameters
    ----------
    config : dict
        The ``train`` section (see :data:`TRAIN_DEFAULTS`); unknown keys raise ``CtsplatError``.
    out_dir : path
        Run folder: ``config.json``, ``train_log.csv``, ``per_view.csv``, ``metrics.json``, ``model.pt``,
        ``model.ply``, ``model_volume.nii.gz``, ``gallery.png``, ``slices.png``, ``turntable.gif``,
        ``checkpoints/``.
    resume : bool
        Continue from the newest checkpoint in ``out_dir/checkpoints`` (same config required). Without a
        checkpoint the run starts from scratch.
    callback : callable(iteration, state), optional
        Called after every completed iteration (after logging and checkpointing); used by tests to inject
        faults or interrupt a run.
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
    val = scene.val.take(_even_subset(len(scene.val), int(cfg["eval_views"])))
    uses_ref = cfg["init"] == "volume"

    train_log = CsvLog(out_dir / "train_log.csv", LOG_COLUMNS + LOG_EXTRAS)
    view_log = CsvLog(out_dir / "per_view.csv", PER_VIEW_COLUMNS)
    ckpt = latest_checkpoint(out_dir) if resume else None
    if ckpt is not None:
        state = _load_checkpoint(ckpt, cfg, device, rng, gen, voxel_mm, chash)
        train_log.truncate_after(state.iteration)
        view_log.truncate_after(state.iteration)
        log.info("resuming from %s (iteration %d)", ckpt, state.iteration)
    else:
        if resume:
            log.warning("no checkpoint in %s; starting from scratch", _ckpt_dir(out_dir))
        shutil.rmtree(_ckpt_dir(out_dir), ignore_errors=True)
        for name in ("metrics.json", "model.pt", "model.ply", "model_volume.nii.gz"):
            (out_dir / name).unlink(missing_ok=True)
        seed = make_seed(cfg, scene, rng)
        params = init_params(seed, cfg, device)
        state = TrainState(params=params, opt=_make_optimizer(params, cfg, voxel_mm))
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
    d = cfg["densify"]
    total = int(cfg["iterations"])
    d_stop = int(d["stop"]) or int(0.75 * total)
    if cfg["mip"]:
        state.filter_var = render_kwargs(cfg, as_gaussians(state.params), scene)["filter_3d_var"]

    from ctsplat.render import random_region, render, voxelize

    lam = {k: float(cfg[k]) for k in ("lambda_l1", "lambda_ssim", "lambda_density", "lambda_scale", "lambda_tv")}
    snap = _snapshot(state)
    show = bool(cfg["progress"]) and sys.stderr.isatty()
    from tqdm import tqdm

    bar = tqdm(total=total, initial=state.iteration, disable=not show, desc="train", dynamic_ncols=True)
    t_start = time.perf_counter() - state.elapsed_s
    t_last, it_last = time.perf_counter(), state.iteration
    last_terms: dict[str, float] = {}
    last_loss = float("nan")
    while state.iteration < total:
        it = state.iteration + 1
        f = _cosine(it - 1, total, float(cfg["lr_final_factor"])) * state.lr_factor
        for g_ in state.opt.param_groups:
            g_["lr"] = g_["initial_lr"] * f
        if not state.queue:
            state.queue = sampler.refill(rng)
        batch = state.queue.pop(0)
        tv_region = random_region(vol.shape, int(cfg["tv_size"]), generator=gen) if lam["lambda_tv"] > 0 else None

        ok = _params_finite(state.params)
        loss = None
        outs = []
        if ok:
            g = as_gaussians(state.params)
            rk = {"compositor": cfg["compositor"], "mip_2d": bool(cfg["mip"])}
            if cfg["mip"]:
                rk["filter_3d_var"] = state.filter_var
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
                    gm = out.means2d.grad
                    if gm is not None:
                        vis = out.visible
                        state.grad_accum[vis] += (gm[vis] * ndc_half).norm(dim=-1)
                        state.grad_count[vis] += 1
            state.opt.step()
            ok = _params_finite(state.params)
        if not ok:
            state.nan_events += 1
            state.nan_consecutive += 1
            state.lr_factor *= float(cfg["nan_lr_decay"])
            log.warning("non-finite loss or parameter at iteration %d: rolled back, learning rate x%.3g "
                        "(%d in a row)", it, state.lr_factor, state.nan_consecutive)
            _restore(state, snap)
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

        densified = False
        if ok and d["interval"] and d["start"] <= it <= d_stop and it % int(d["interval"]) == 0 and it < total:
            counts = densify_and_prune(state, cfg, scene, gen)
            densified = True
            for k in state.densify_counts:
                state.densify_counts[k] += counts[k]
            log.info("densify at %d: %s", it, counts)
            if cfg["mip"]:
                state.filter_var = render_kwargs(cfg, as_gaussians(state.params), scene)["filter_3d_var"]
        if ok and (densified or it % 10 == 0):
            snap = _snapshot(state)

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
    return _finalize(state, cfg, scene, out_dir, device, train_time, chash, train_log)


def _finalize(state: TrainState, cfg: dict[str, Any], scene: Scene, out_dir: Path, device: torch.device,
              train_time: float, chash: str, train_log: CsvLog) -> dict[str, Any]:
    """Test-split evaluation, model files, figures and ``metrics.json``."""
    from ctsplat.formats.volume import Volume, save_volume

    uses_ref = cfg["init"] == "volume"
    g = as_gaussians({k: v.detach() for k, v in state.params.items()})
    g.meta.update(config_hash=chash, uses_reference_volume=uses_ref, init=cfg["init"], compositor=cfg["compositor"])
    # final 3D filter from the final means (what ``evaluate`` recomputes from model.pt)
    rk = render_kwargs(cfg, g, scene)
    test = scene.test
    preds = ev.render_views(g, test.camera, test.Rs, test.ts, rk)
    vm = ev.view_metrics(preds, test.images, with_lpips=True)
    vol_model = ev.voxelize_model(g, scene.volume.shape, scene.volume.affine, rk.get("filter_3d_var"))
    m3 = ev.volume_metrics(vol_model, scene.volume.data)
    CsvLog(out_dir / "per_view.csv", PER_VIEW_COLUMNS).append([
        {"iteration": state.iteration, "view_id": int(i), "azimuth_deg": float(a), "elevation_deg": float(e),
         "split": "test", "psnr2d": float(p), "ssim2d": float(s)}
        for i, a, e, p, s in zip(test.ids, test.azimuth_deg, test.elevation_deg, vm["psnr2d"], vm["ssim2d"],
                                 strict=True)
    ])
    g.save(out_dir / "model.pt")
    g.to_ply(out_dir / "model.ply")
    meta = {
        "source": "ctsplat.train voxelised Gaussian model",
        "intensity": {"unit": "normalised", "mu_scale_per_mm": scene.mu_scale},
        "reference_volume_id": scene.volume.volume_id,
        "uses_reference_volume": uses_ref,
        "config_hash": chash,
        "code_version": code_version(),
    }
    save_volume(Volume(vol_model.astype(np.float32), np.asarray(scene.volume.affine, float), meta),
                out_dir / "model_volume.nii.gz")
    if cfg["figures"]:
        ev.save_gallery(out_dir / "gallery.png", test.images, preds, [int(i) for i in test.ids], vm["psnr2d"])
        ev.save_slices(out_dir / "slices.png", vol_model, scene.volume.data)
        Rs, ts = ev.orbit_poses(test.Rs[0], test.ts[0], scene.volume.center_mm(), int(cfg["turntable_frames"]))
        frames = ev.render_views(g, test.camera, Rs, ts, rk)
        ev.save_turntable(out_dir / "turntable.gif", frames)
    fps = ev.forward_fps(g, test.camera, test.Rs[0], test.ts[0], rk, width=int(cfg["fps_width"]),
                         height=int(cfg["fps_height"]))
    mem, mem_kind = ev.peak_memory_mb(device)
    rows = train_log.read()
    lpips_vals = vm["lpips"]
    result = {
        "psnr2d": float(np.mean(vm["psnr2d"])),
        "ssim2d": float(np.mean(vm["ssim2d"])),
        "lpips": None if any(v is None for v in lpips_vals) else float(np.mean(lpips_vals)),
        "lpips_reason": vm["lpips_reason"],
        **m3,
        "split": "test",
        "n_test_views": len(test),
        "n_train_views": len(scene.train),
        "eval_split_during_training": scene.eval_split,
        "wall_time_s": round(train_time, 3),
        "iterations": state.iteration,
        "iters_per_s": round(state.iteration / max(train_time, 1e-9), 3),
        **ev.milestones(rows),
        "fps_forward": fps,
        "fps_resolution": [int(cfg["fps_width"]), int(cfg["fps_height"])],
        "peak_memory_mb": round(mem, 1),
        "peak_memory_kind": mem_kind,
        "n_gaussians": len(g),
        "model_size_bytes": ev.model_size_bytes(out_dir / "model.pt"),
        "model_ply_size_bytes": ev.model_size_bytes(out_dir / "model.ply"),
        "uses_reference_volume": uses_ref,
        "init": cfg["init"],
        "compositor": cfg["compositor"],
        "mip": bool(cfg["mip"]),
        "poses": cfg["poses"],
        "supervision": cfg["supervision"],
        "seed": int(cfg["seed"]),
        "nan_events": state.nan_events,
        "views_dropped_unregistered": scene.info.get("views_dropped_unregistered", 0),
        "sfm_registration_rate": scene.info.get("sfm_registration_rate"),
        "device": str(device),
        "config_hash": chash,
        "code_version": code_version(),
        "volume_id": scene.volume.volume_id,
    }
    write_json_atomic(out_dir / "metrics.json", json_safe(result))
    return result
