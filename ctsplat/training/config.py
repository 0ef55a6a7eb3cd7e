"""Training settings: the ``train`` config section with its defaults, validation, and the renderer settings.

:data:`TRAIN_DEFAULTS` is the single definition of every training key and its default (the workflow schema is
generated from it); :func:`resolve_config` fills and checks a user's section; :func:`render_kwargs` turns a
config into the renderer's keyword arguments, the same for training, validation and evaluation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ctsplat.splat.render import COMPOSITORS
from ctsplat.utils import CtsplatError, merge_config

__all__ = ["TRAIN_DEFAULTS", "INITS", "POSES", "SUPERVISIONS", "resolve_config", "render_kwargs", "mip_filter"]

INITS = ("volume", "uniform", "fbp", "sfm")
POSES = ("gt", "colmap")
SUPERVISIONS = ("line_integral", "transmission")

TRAIN_DEFAULTS: dict[str, Any] = {
    "volume": "",  # reference volume (.nii.gz): grid for 3D metrics, and the values for init: volume
    "radiographs": "",  # folder with line_integrals.tif + views.json
    "poses": "gt",  # gt | colmap
    "sfm_dir": "",  # folder of the sfm step (aligned_views.json, summary.json, points3d.ply)
    # poses: colmap: the radiographs folder of the view set SfM registered ("": the one its summary.json names)
    "sfm_radiographs": "",
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
    "views": 0,  # training views used, spread evenly over the candidates (ctsplat.scene); 0 = all
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


def render_kwargs(cfg: dict[str, Any], filter_3d_var: Any = None) -> dict[str, Any]:
    """Renderer keyword arguments of a run config: the same for training, validation and evaluation.

    Parameters
    ----------
    cfg : dict
        Resolved ``train`` config (``compositor``, ``mip``).
    filter_3d_var : tensor (N,), optional
        The 3D smoothing filter's variance per Gaussian (mm²) from :func:`mip_filter`; used only with ``mip``.

    Returns
    -------
    dict
        ``compositor``, ``mip_2d`` and, with ``mip``, ``filter_3d_var``.
    """
    kw: dict[str, Any] = {"compositor": cfg["compositor"], "mip_2d": bool(cfg["mip"])}
    if cfg["mip"]:
        kw["filter_3d_var"] = filter_3d_var
    return kw


def mip_filter(cfg: dict[str, Any], gaussians: Any, camera: Any, Rs: np.ndarray, ts: np.ndarray) -> Any:
    """The Mip-Splatting 3D filter variance (N,) mm² of ``gaussians`` over the *training* cameras, or None without
    ``mip`` (:func:`ctsplat.splat.render.compute_3d_filter`; Rs (V, 3, 3), ts (V, 3) mm).

    References
    ----------
    Yu, Z., Chen, A., Huang, B., Sattler, T., Geiger, A. (2024). Mip-Splatting: alias-free 3D Gaussian splatting.
    CVPR.
    """
    if not cfg["mip"]:
        return None
    from ctsplat.splat.render import compute_3d_filter

    return compute_3d_filter(gaussians.detach(), camera, Rs, ts)
