"""Training settings: the ``train`` config section with its defaults, validation, and the renderer settings.

:data:`TRAIN_DEFAULTS` is the single definition of every training key and its default (the workflow schema is
generated from it) and :data:`TRAIN_BOUNDS` of every numeric key's allowed range; :func:`resolve_config` fills and
checks a user's section; :func:`render_kwargs` turns a config into the renderer's keyword arguments, the same for
training, validation and evaluation.
"""

from __future__ import annotations

import contextlib
import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from ctsplat.baselines import FBP_FILTERS
from ctsplat.splat.render import COMPOSITORS
from ctsplat.utils import SEED_MAX, CtsplatError, merge_config

__all__ = ["TRAIN_DEFAULTS", "TRAIN_BOUNDS", "Bound", "INITS", "REFERENCE_INITS", "POSES", "SUPERVISIONS",
           "OPTIMIZER_PRESETS", "DENSIFY_STRATEGIES", "MODEL_SELECTIONS", "CONE_POSE_MODELS", "resolve_config",
           "render_kwargs", "mip_filter", "EVALUATION_KEYS"]

#: The ``train`` keys that do not change the trained model: the evaluation's figures and timing size, which model
#: it scores (``model_selection``: training writes both) and its read-out sharpening (chosen on validation views
#: after training), and the progress bar. The workflow hands them to the evaluation only, so changing them does
#: not train again.
EVALUATION_KEYS = ("figures", "turntable_frames", "fps_width", "fps_height", "model_selection", "sharpen",
                   "progress")

INITS = ("volume", "uniform", "fbp", "sfm")
#: the inits that read the reference volume's voxel values (their runs are labelled as such wherever shown)
REFERENCE_INITS = ("volume",)
OPTIMIZER_PRESETS = ("per_group", "method")
DENSIFY_STRATEGIES = ("gradient", "error", "both")
MODEL_SELECTIONS = ("last", "best")
CONE_POSE_MODELS = ("rigid", "carm")
POSES = ("gt", "perturbed", "colmap", "gt+refine", "perturbed+refine", "colmap+refine")
SUPERVISIONS = ("line_integral", "transmission")

TRAIN_DEFAULTS: dict[str, Any] = {
    "volume": "",  # reference volume (.nii.gz): grid for 3D metrics, and the values for init: volume
    "radiographs": "",  # folder with line_integrals.tif + views.json
    # gt: the true poses; perturbed: the true poses with a seeded per-view C-arm error (perturb_*); colmap: SfM's.
    # `+refine` refines the training poses jointly with the Gaussians (as pose_refine.enabled does)
    "poses": "gt",
    # poses: perturbed, drawn from `seed`: azimuth and elevation errors, N(0, σ²) each (degrees)
    "perturb_rot_deg": 1.0,
    "perturb_trans_mm": 0.5,  # poses: perturbed: isocentre shift, N(0, σ² I) (mm)
    # per-view rigid corrections of the training cameras about the designed isocentre (ctsplat.training.poses),
    # stepped from iteration `start` on by their own Adam (rates per step, same cosine as the Gaussians), with a
    # Gaussian prior of these standard deviations times `prior_weight` in the loss; held-out views are not refined.
    # start 0: from the first step (the fbp seed is the warm-up; waiting lost on validation, docs/results.md)
    # cone_model: the cone-beam correction, `rigid` (6 DoF) or `carm` (turn about the isocentre at the designed
    # source distance: 3 rotations and the 2 detector-plane shifts, as for parallel beam)
    "pose_refine": {"enabled": False, "start": 0, "lr_rot_deg": 0.05, "lr_trans_mm": 0.05, "prior_rot_deg": 2.0,
                    "prior_trans_mm": 2.0, "prior_weight": 1e-4, "cone_model": "rigid"},
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
    # fbp: this many ASD-POCS iterations (TV weight alpha; the baselines' other settings) on the training views,
    # started from the FBP/FDK volume, before the seeds are drawn; 0: the FBP/FDK volume itself
    "init_asd_pocs": {"iterations": 0, "alpha": 0.1},
    "compositor": "radiative",  # radiative | radiative_unrectified | alpha
    "mip": False,
    "views": 0,  # training views used, spread evenly over the candidates (ctsplat.scene); 0 = all
    "seed": 0,
    "device": "auto",  # auto | cpu | cuda
    "iterations": 3000,
    # training views rendered per step; the loss averages over them (1 chosen on validation, docs/results.md)
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
    # per_group: Adam with the `lr` rates above; method: Adam with 3e-3 for every group (means in units of the
    # volume's half-extent, the method's [-1, 1] scene box), both decayed by the same cosine to lr_final_factor
    "optimizer_preset": "per_group",
    # lambda_density x factor for the first `fraction` of the iterations, then a cosine over the next `decay`
    # fraction down to lambda_density (factor 1: off)
    "lambda_density_warmup": {"factor": 1.0, "fraction": 0.15, "decay": 0.05},
    # training views only: each rendered view's camera rotated about the volume centre by <= rot_deg and shifted
    # in the detector plane by <= shift_px pixels; targets get N(0, target_noise) noise (fraction of the largest
    # target); validation and evaluation never see either
    "augment": {"enabled": False, "rot_deg": 0.5, "shift_px": 0.5, "target_noise": 0.005},
    "densify": {
        "interval": 500,
        "start": 500,
        "stop": 0,  # 0 = 0.75 × iterations
        "grad_threshold": 2e-4,
        "clone_max_scale_voxels": 1.5,
        "prune_density": 1e-4,
        "prune_max_scale_fraction": 0.2,
        "max_gaussians": 200000,
        # prune (without densifying) every `interval` after `stop` and at the last iteration: Gaussians that
        # grow past the size limit late in training spread a haze (won on validation, docs/results.md)
        "prune_until_end": True,
        "split_mass": "conserve",  # conserve | halve (radiative compositors; see densify_and_prune)
        # gradient: positional-gradient rule; error: Gaussians under large training residuals; both: either
        "strategy": "gradient",
        # error / both: densify Gaussians whose mean residual under their footprint is >= this x the mean over
        # the visible Gaussians of the same views
        "error_ratio": 2.0,
        # merge nearly coincident Gaussians (centres within `distance` x their mean scale, scales within
        # `scale_tol` relative, covariances within `cov_tol` relative Frobenius): mass kept in radiative modes
        "prune_redundant": {"enabled": False, "distance": 0.1, "scale_tol": 0.1, "cov_tol": 0.1},
    },
    "eval_every": 250,
    # the model `ctsplat evaluate` measures by default: last (model.pt) or best (model_best.pt, the highest
    # validation PSNR at the periodic evaluations; always written)
    "model_selection": "last",
    # the voxel read-out's unsharp masking (ctsplat.evaluation.readout): the amount among `amounts` whose
    # re-projection scores best on the validation views, blur radius in voxels; [0.0] is off (the library default;
    # the cone-beam protocol offers 0-1, chosen there on validation, docs/results.md)
    "sharpen": {"amounts": [0.0], "radius_voxels": 1.0},
    "eval_views": 8,  # validation views per periodic evaluation (evenly spaced); 0 = all
    "checkpoint_every": 500,
    "keep_checkpoints": 2,
    "nan_lr_decay": 0.5,  # learning rates x this after each non-finite step, in (0, 1)
    "nan_max_consecutive": 3,  # stop after this many non-finite steps in a row ...
    "nan_max_events": 5,  # ... or this many within nan_window iterations (sporadic but persistent divergence)
    "nan_window": 100,
    # collapse: the run fails instead of writing a model (0 disables a check). At each validation: fewer than
    # collapse_min_gaussians Gaussians with density (alpha: opacity) >= densify.prune_density, or the mean loss
    # since the previous validation above collapse_loss_factor x the first interval's for collapse_loss_evals
    # validations in a row. At the end: validation PSNR more than collapse_psnr_drop_db below the initial model's,
    # or within collapse_empty_margin_db of an empty model's (all-zero images) and below the initial model's.
    "collapse_min_gaussians": 1,
    "collapse_loss_factor": 2.0,
    "collapse_loss_evals": 5,
    "collapse_psnr_drop_db": 5.0,
    "collapse_empty_margin_db": 0.1,
    "figures": True,
    "turntable_frames": 24,
    "fps_width": 1920,
    "fps_height": 1080,
    "progress": True,
}



@dataclass(frozen=True)
class Bound:
    """The allowed values of one numeric training key.

    Parameters
    ----------
    kind : {"integer", "number"}
        Integers also accept integral floats (``3000.0``); booleans are never numbers.
    low, high : float, optional
        Limits (None: unbounded).
    low_open, high_open : bool
        Whether the limit itself is excluded.
    nullable : bool
        Whether ``null`` (None) is allowed.
    array : bool
        The key holds a non-empty list of such values (a grid of candidates) instead of one.
    """

    kind: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    nullable: bool = False
    array: bool = False

    def describe(self) -> str:
        """``an integer >= 1``, ``a number in (0, 1)``, ``a non-empty list of numbers in [0, 4]``, ... (the error
        messages' wording)."""
        if self.array:
            what = "a non-empty list of integers" if self.kind == "integer" else "a non-empty list of numbers"
        else:
            what = "an integer" if self.kind == "integer" else "a number"
        fmt = _fmt_limit
        if self.low is not None and self.high is not None:
            rng = f"in {'(' if self.low_open else '['}{fmt(self.low)}, {fmt(self.high)}{')' if self.high_open else ']'}"
        elif self.low is not None:
            rng = f"{'>' if self.low_open else '>='} {fmt(self.low)}"
        elif self.high is not None:
            rng = f"{'<' if self.high_open else '<='} {fmt(self.high)}"
        else:
            rng = ""
        return f"{what} {rng}".strip() + (" or null" if self.nullable else "")

    def json_schema(self) -> dict[str, Any]:
        """The same bound as a JSON-schema fragment (``type``, ``minimum`` / ``exclusiveMinimum``, ...)."""
        item: dict[str, Any] = {"type": self.kind}
        if self.low is not None:
            item["exclusiveMinimum" if self.low_open else "minimum"] = self.low
        if self.high is not None:
            item["exclusiveMaximum" if self.high_open else "maximum"] = self.high
        out = {"type": "array", "minItems": 1, "items": item} if self.array else item
        if self.nullable:
            out["type"] = [out["type"], "null"]
        return out

    def check(self, key: str, value: Any) -> None:
        """Raise a one-line ``CtsplatError`` naming ``train.{key}`` when ``value`` is outside the bound."""
        if value is None and self.nullable:
            return
        if self.array:
            if isinstance(value, list | tuple) and value and all(self._holds(v) for v in value):
                return
        elif self._holds(value):
            return
        hint = ""
        if isinstance(value, str) and "e" in value.lower():
            mant, _, exp = value.lower().partition("e")
            with contextlib.suppress(ValueError):
                float(value)
                hint = f" (text: YAML reads {value} as a string; write {mant if '.' in mant else mant + '.0'}e{exp})"
        raise CtsplatError(f"train.{key} must be {self.describe()}, got {value!r}{hint}")

    def _holds(self, value: Any) -> bool:
        """Whether one value (not a list) is of the kind and within the limits."""
        number = isinstance(value, int | float) and not isinstance(value, bool)
        ok = number and math.isfinite(value)
        if ok and self.kind == "integer":
            ok = float(value).is_integer()
        if ok and self.low is not None:
            ok = value > self.low if self.low_open else value >= self.low
        if ok and self.high is not None:
            ok = value < self.high if self.high_open else value <= self.high
        return ok


def _fmt_limit(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(x)


_POS_INT = Bound("integer", 1)
_NONNEG_INT = Bound("integer", 0)
_NONNEG = Bound("number", 0)
_POS = Bound("number", 0, low_open=True)
_UNIT = Bound("number", 0, 1)

#: Allowed values of every numeric key of :data:`TRAIN_DEFAULTS` (dotted for nested keys); checked by
#: :func:`resolve_config`, mirrored by the workflow schema (:meth:`Bound.json_schema`).
TRAIN_BOUNDS: dict[str, Bound] = {
    "min_registration_rate": _UNIT,
    "perturb_rot_deg": Bound("number", 0, 10),
    "perturb_trans_mm": Bound("number", 0, 50),
    "pose_refine.start": _NONNEG_INT,
    "pose_refine.lr_rot_deg": _POS,
    "pose_refine.lr_trans_mm": _POS,
    "pose_refine.prior_rot_deg": _POS,
    "pose_refine.prior_trans_mm": _POS,
    "pose_refine.prior_weight": _NONNEG,
    "n_init": _POS_INT,
    "init_top_fraction": Bound("number", 0, 1, low_open=True),
    "init_scale_voxels": Bound("number", 0, low_open=True, nullable=True),
    "init_density": _POS,
    "sfm_fill_fraction": _UNIT,
    "views": _NONNEG_INT,
    "seed": Bound("integer", 0, SEED_MAX),
    "iterations": _POS_INT,
    "batch_views": _POS_INT,
    "init_asd_pocs.iterations": _NONNEG_INT,
    "init_asd_pocs.alpha": _POS,
    "sharpen.amounts": Bound("number", 0, 4, array=True),
    "sharpen.radius_voxels": Bound("number", 0, 10, low_open=True),
    "lambda_l1": _NONNEG,
    "lambda_ssim": _NONNEG,
    "lambda_density": _NONNEG,
    "lambda_scale": _NONNEG,
    "lambda_tv": _NONNEG,
    "tv_size": Bound("integer", 2),  # the TV term needs 2 voxels a side
    **{f"lr.{k}": _POS for k in TRAIN_DEFAULTS["lr"]},
    "lr_final_factor": _UNIT,
    "lambda_density_warmup.factor": Bound("number", 1),
    "lambda_density_warmup.fraction": _UNIT,
    "lambda_density_warmup.decay": _UNIT,
    "augment.rot_deg": Bound("number", 0, 1),
    "augment.shift_px": Bound("number", 0, 1),
    "augment.target_noise": Bound("number", 0, 0.1),
    "densify.error_ratio": _POS,
    "densify.prune_redundant.distance": Bound("number", 0, 1),
    "densify.prune_redundant.scale_tol": Bound("number", 0, 1),
    "densify.prune_redundant.cov_tol": Bound("number", 0, 1),
    "densify.interval": _NONNEG_INT,
    "densify.start": _NONNEG_INT,
    "densify.stop": _NONNEG_INT,
    "densify.grad_threshold": _NONNEG,
    "densify.clone_max_scale_voxels": _NONNEG,
    "densify.prune_density": _NONNEG,
    "densify.prune_max_scale_fraction": _POS,
    "densify.max_gaussians": _POS_INT,
    "eval_every": _POS_INT,
    "eval_views": _NONNEG_INT,
    "checkpoint_every": _POS_INT,
    "keep_checkpoints": _POS_INT,
    "nan_lr_decay": Bound("number", 0, 1, low_open=True, high_open=True),
    "nan_max_consecutive": _POS_INT,
    "nan_max_events": _POS_INT,
    "nan_window": _POS_INT,
    "collapse_min_gaussians": _NONNEG_INT,
    "collapse_loss_factor": Bound("number", 1, low_open=True),
    "collapse_loss_evals": _NONNEG_INT,
    "collapse_psnr_drop_db": _NONNEG,
    "collapse_empty_margin_db": _NONNEG,
    "turntable_frames": _POS_INT,
    "fps_width": _POS_INT,
    "fps_height": _POS_INT,
}

_BOOL_KEYS = ("mip", "figures", "progress", "augment.enabled", "densify.prune_redundant.enabled",
              "densify.prune_until_end", "pose_refine.enabled")


def _get(cfg: dict[str, Any], dotted: str) -> Any:
    node: Any = cfg
    parts = dotted.split(".")
    for i, part in enumerate(parts):
        if not isinstance(node, dict):
            section = ".".join(parts[:i])
            keys = ", ".join(_get(TRAIN_DEFAULTS, section))
            raise CtsplatError(f"train.{section} must be a mapping of its keys ({keys}), got {node!r}")
        node = node[part]
    return node


def resolve_config(config: dict[str, Any] | None) -> dict[str, Any]:
    """Fill defaults and validate a ``train`` section.

    Parameters
    ----------
    config : dict or None
        The user's ``train`` section (keys of :data:`TRAIN_DEFAULTS`; nested ``lr`` / ``densify`` partial).

    Returns
    -------
    dict
        The full section, defaults filled (values as given, not converted).

    Raises
    ------
    CtsplatError
        One line naming the key: unknown keys, unknown choices, numbers outside :data:`TRAIN_BOUNDS`, missing
        input paths.
    """
    cfg = merge_config("train", config, TRAIN_DEFAULTS)
    for key, allowed in (("init", INITS), ("compositor", COMPOSITORS), ("poses", POSES),
                         ("supervision", SUPERVISIONS), ("fbp_filter", FBP_FILTERS)):
        if cfg[key] not in allowed:
            raise CtsplatError(f"unknown train.{key} {cfg[key]!r}; allowed: {', '.join(allowed)}")
    if not isinstance(cfg["device"], str) or not re.fullmatch(r"auto|cpu|cuda(:\d+)?", cfg["device"]):
        raise CtsplatError(f"unknown train.device {cfg['device']!r}; allowed: auto, cpu, cuda, cuda:N")
    for dotted, bound in TRAIN_BOUNDS.items():
        bound.check(dotted, _get(cfg, dotted))
    for key in _BOOL_KEYS:
        if not isinstance(_get(cfg, key), bool):
            raise CtsplatError(f"train.{key} must be true or false, got {_get(cfg, key)!r}")
    if float(cfg["lambda_l1"]) == 0 and float(cfg["lambda_ssim"]) == 0:
        raise CtsplatError("train.lambda_l1 and train.lambda_ssim are both 0: the loss has no data term; make at "
                           "least one of them > 0")
    if cfg["supervision"] == "transmission" and cfg["compositor"] == "alpha":
        raise CtsplatError("supervision: transmission needs a radiative compositor (alpha images are not "
                           "line integrals)")
    for dotted, allowed in (("optimizer_preset", OPTIMIZER_PRESETS), ("densify.strategy", DENSIFY_STRATEGIES),
                            ("model_selection", MODEL_SELECTIONS), ("pose_refine.cone_model", CONE_POSE_MODELS)):
        if _get(cfg, dotted) not in allowed:
            raise CtsplatError(f"unknown train.{dotted} {_get(cfg, dotted)!r}; allowed: {', '.join(allowed)}")
    if cfg["densify"]["split_mass"] not in ("conserve", "halve"):
        raise CtsplatError(f"unknown train.densify.split_mass {cfg['densify']['split_mass']!r}; allowed: conserve, "
                           "halve")
    for key in ("volume", "radiographs", "sfm_dir", "sfm_radiographs"):
        if cfg.get(key) is not None and not isinstance(cfg[key], str):
            raise CtsplatError(f"train.{key} must be a path (text), got {cfg[key]!r}")
    if not cfg["volume"]:
        raise CtsplatError("train.volume is empty: give the preprocessed reference volume (.nii.gz)")
    if not cfg["radiographs"]:
        raise CtsplatError("train.radiographs is empty: give the folder written by `ctsplat project`")
    if refine_enabled(cfg) and int(cfg["pose_refine"]["start"]) >= int(cfg["iterations"]):
        raise CtsplatError(f"train.pose_refine.start ({cfg['pose_refine']['start']}) is not before train.iterations "
                           f"({cfg['iterations']}): the poses would never be refined; lower start, or turn "
                           "refinement off (poses without +refine, pose_refine.enabled: false)")
    if (cfg["poses"].startswith("colmap") or cfg["init"] == "sfm") and not cfg["sfm_dir"]:
        raise CtsplatError(f"train.sfm_dir is empty but poses={cfg['poses']}, init={cfg['init']} needs the sfm "
                           "step's folder (ctsplat train: --sfm-dir)")
    return cfg


def refine_enabled(cfg: dict[str, Any]) -> bool:
    """Whether a resolved ``train`` config refines the training poses (``pose_refine.enabled`` or ``poses: *+refine``).

    Parameters
    ----------
    cfg : dict

    Returns
    -------
    bool
    """
    return bool(cfg["pose_refine"]["enabled"]) or str(cfg["poses"]).endswith("+refine")


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
    """The Mip-Splatting 3D filter variance of ``gaussians`` over the *training* cameras, or None without ``mip``
    (:func:`ctsplat.splat.render.compute_3d_filter`).

    Parameters
    ----------
    cfg : dict
        Resolved ``train`` config (``mip``).
    gaussians : ctsplat.splat.Gaussians
        N Gaussians.
    camera : ctsplat.geometry.cameras camera
        The training views' camera.
    Rs : ndarray, shape (V, 3, 3)
    ts : ndarray, shape (V, 3)
        World-to-camera poses of the training views (mm).

    Returns
    -------
    Tensor (N,) or None
        Variance in mm².

    References
    ----------
    Yu, Z., Chen, A., Huang, B., Sattler, T., Geiger, A. (2024). Mip-Splatting: alias-free 3D Gaussian splatting.
    CVPR.
    """
    if not cfg["mip"]:
        return None
    from ctsplat.splat.render import compute_3d_filter

    return compute_3d_filter(gaussians.detach(), camera, Rs, ts)
