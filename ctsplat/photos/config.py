"""Settings of the photo path (the ``photos`` config section): SfM, alpha-3DGS training and evaluation.

One dict, :data:`PHOTOS_DEFAULTS`, with three subsections; the workflow schema's ``photos`` section is generated
from it (``python -m ctsplat.config --sync-defaults``) and :func:`photo_settings` fills a user's values from it.
The training defaults are 3DGS's (Kerbl et al. 2023) with the schedule shortened for CPU budgets (6000 iterations,
densification until iteration 1020, a black background: chosen on the skull set's validation photos, see
docs/results.md).
"""

from __future__ import annotations

from typing import Any

from ctsplat.utils import CtsplatError, merge_config

__all__ = ["PHOTOS_DEFAULTS", "DENSIFY_CHOICES", "SFM_SUMMARY_KEYS", "photo_settings", "held_out_split",
           "validation_position", "check_train_settings"]

#: the keys of a photo SfM folder's ``summary.json`` that the CLI prints and ``metrics.json`` repeats
SFM_SUMMARY_KEYS = ("n_images", "n_registered", "registration_rate", "unregistered", "not_read", "models_found",
                    "mean_reprojection_error_px", "n_points")

#: Defaults of the ``photos`` config section (JSON-serialisable).
#: The allowed values of the ``photos.train.densify`` keys that name a method (the schema's enums are these).
DENSIFY_CHOICES: dict[str, tuple[str, ...]] = {"strategy": ("default", "mcmc"), "gradient": ("mean", "pixel"),
                                               "size_prune": ("after_reset", "always")}

PHOTOS_DEFAULTS: dict[str, Any] = {
    "sfm": {
        "max_image_size": 1024,  # SIFT runs on images downscaled to this longest side (CPU budget)
        "max_num_features": 4096,
        "camera_mode": "single",  # single: one camera for all images (one size required) | per_image
        "camera_model": "SIMPLE_RADIAL",  # estimated by bundle adjustment; undistorted to PINHOLE afterwards
        "matching": "auto",  # auto: exhaustive up to exhaustive_max_images, sequential above | exhaustive | sequential
        "exhaustive_max_images": 120,
        "sequential_overlap": 10,
        "min_num_inliers": 15,  # two-view geometry
        "mapper": "incremental",  # incremental | global (GLOMAP-style global positioning)
        # incremental mapper thresholds, below COLMAP's defaults (100, 30, 0.25): objects on a dark background give
        # 2-5k features per photo, and the defaults split such a set into several models
        "init_min_num_inliers": 50,
        "abs_pose_min_num_inliers": 15,
        "abs_pose_min_inlier_ratio": 0.15,
        "min_registered": 3,  # fewer registered images in the largest model fail the step
        "num_threads": 2,  # undistortion; extraction, matching and mapping run on one thread (reproducible models)
        "seed": 0,
    },
    "train": {
        "iterations": 6000,  # chosen on the skull set's validation photos with stop_fraction (docs/results.md)
        "downscale": 4,  # images and intrinsics divided by this (1, 2, 4, 8)
        "test_every": 8,  # every n-th image (sorted by name, from the first) is held out for testing
        # test: monitor and evaluate on the test images | validation: leave the test images out entirely and hold
        # out every test_every-th remaining one (from validation_offset) instead, to choose settings on
        "holdout": "test",
        # which validation fold (the position of the first validation photo, 1 .. test_every - 1); null: midway
        "validation_offset": None,
        # the colour behind the Gaussians: a fixed [r, g, b] in [0, 1] or "learned" (one RGB trained with the
        # model, started at the median of the training photos' border pixels); black won on the skull set's
        # validation photos (docs/results.md)
        "background": [0.0, 0.0, 0.0],
        # a flash on the camera (ctsplat.photos.light): colours x (r_ref / r)^p, r the distance from the camera,
        # p trained from `exponent` at step `lr`; `bounded`: r clamped below at the nearest SfM point's distance
        # from a training camera, so a floater in front of a camera is not lit more than any surface (docs/results.md)
        "flash": {"enabled": False, "exponent": 0.0, "lr": 0.01, "bounded": True},
        "sh_degree": 3,  # the highest SH degree
        "sh_interval": 1000,  # the SH degree rises by one every this many iterations
        "lambda_dssim": 0.2,  # loss = (1 - λ) L1 + λ (1 - SSIM)
        # DropGaussian (Park et al. 2025): each training render leaves every Gaussian out with probability
        # drop_rate x iteration / iterations, the others' opacities / (1 - that); 0: off
        "drop_rate": 0.0,
        "init_opacity": 0.1,
        "init_scale": 1.0,  # a seed's scale = this x the RMS distance to its 3 nearest SfM points
        "max_points": 100000,  # SfM points used as seeds (random subset above this)
        "lr": {
            "means": 1.6e-4,  # times the scene extent; decays exponentially to means_final at the last iteration
            "means_final": 1.6e-6,
            "log_scales": 5e-3,
            "quats": 1e-3,
            "opacity": 5e-2,
            # the base colour is trained in RGB units; 3DGS's 2.5e-3 acts on its SH DC coefficient, a step of
            # 2.5e-3 x C0 = 7e-4 in colour: 3.5x smaller than this one, which tied on validation (docs/results.md)
            "colors": 2.5e-3,
            "sh_rest": 1.25e-4,
            "background": 1e-2,
        },
        "densify": {
            # default: 3DGS's clone / split / prune (ctsplat.photos.densify) | mcmc: relocation to a fixed budget
            # (ctsplat.photos.mcmc, with the mcmc section below)
            "strategy": "default",
            "interval": 100,
            "start": 500,
            "stop_fraction": 0.17,  # densification stops at this fraction of the iterations (6000: after 1020)
            "grad_threshold": 2e-4,  # mean view-space positional gradient (3DGS NDC units)
            # Pixel-GS's average, weighted by the pixels covered and scaled down near the camera (chosen on the
            # validation folds); "mean": 3DGS's. MCMC relocates by opacity and uses neither
            "gradient": "pixel",
            "percent_dense": 0.01,  # clone below / split above this fraction of the scene extent
            "prune_opacity": 0.005,
            # prune Gaussians wider than this fraction of the scene extent, after the first opacity reset (3DGS)
            "prune_scale_fraction": 0.1,
            "size_prune": "after_reset",  # "always": from the first densification step to the end of training
            # > 0: prune Gaussians wider (largest sigma) than this x their distance to the nearest training camera
            "near_prune": 0.0,
            "opacity_reset_interval": 3000,  # 0: never
            "max_gaussians": 300000,
        },
        # densify.strategy: mcmc (Kheradmand et al. 2024; gsplat's values but cap_max, sized for CPU budgets)
        "mcmc": {
            "cap_max": 30000,  # the Gaussians grow to this count and stay there
            "growth": 1.05,  # each step adds this factor - 1 of the current count, up to cap_max
            "stop_fraction": 0.83,  # relocation and growth stop at this fraction of the iterations
            "noise_lr": 5e5,  # position noise = covariance x this x the means' learning rate
            "opacity_reg": 0.01,  # loss += this x mean opacity
            "scale_reg": 0.01,  # loss += this x mean scale (world units)
        },
        "log_every": 250,  # held-out PSNR/SSIM rows of train_log.csv
        "num_threads": 2,
        "seed": 0,
        "device": "auto",
    },
    "evaluate": {
        "turntable_frames": 36,
        "gallery_views": 6,  # held-out views shown in the gallery (evenly spaced over the test set)
        "attribution": "",  # credit line of the photographs, printed on the gallery and the turntable
    },
}


def photo_settings(user: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``photos`` section filled with :data:`PHOTOS_DEFAULTS` (unknown keys fail naming their path).

    Parameters
    ----------
    user : dict, optional
        The user's values (any subset, nested by subsection).

    Returns
    -------
    dict
        ``{"sfm": {...}, "train": {...}, "evaluate": {...}}``, every key present.
    """
    return merge_config("photos", user, PHOTOS_DEFAULTS)


def held_out_split(settings: dict[str, Any]) -> str:
    """The split a run monitors and is evaluated on: ``val`` with ``holdout: validation``, else ``test``."""
    return "val" if settings.get("holdout", "test") == "validation" else "test"


def validation_position(test_every: int, validation_offset: int | None) -> int:
    """The position of the first validation photo among each ``test_every`` (the validation fold).

    Parameters
    ----------
    test_every : int
        Hold-out period; 0 holds nothing out (the offset is then not used).
    validation_offset : int, optional
        1 .. ``test_every`` - 1; ``None`` takes ``test_every // 2`` (midway between two test photos).

    Returns
    -------
    int

    Raises
    ------
    CtsplatError
        For an offset outside 1 .. ``test_every`` - 1.
    """
    k = int(test_every)
    off = k // 2 if validation_offset is None else int(validation_offset)
    if k and not 1 <= off < k:
        raise CtsplatError(f"photos.train.validation_offset must be 1..{k - 1} (test_every {k}), got {off}")
    return off


def check_train_settings(s: dict[str, Any]) -> None:
    """Refuse ``photos.train`` settings that no photo folder can train with, before any work is done.

    Parameters
    ----------
    s : dict
        The filled ``photos.train`` section.

    Raises
    ------
    CtsplatError
        One line naming the key: iterations below 1, a downscale other than 1, 2, 4 or 8, an SH degree outside
        0..3, a hold-out period that leaves no held-out photo (0) or no training photo, or a validation offset
        outside 1 .. ``test_every`` - 1.
    """
    every, validation = int(s["test_every"]), held_out_split(s) == "val"
    if every == 0:
        raise CtsplatError("photos.train.test_every 0 holds out no photo, and the run is evaluated on held-out "
                           "photos; use 8 (every 8th photo, the usual split)")
    if every == 1 or (validation and every == 2):
        held = "with the validation photos between them, " if validation else ""
        raise CtsplatError(f"photos.train.test_every {every} holds out every photo ({held}none is left for "
                           "training); use 8 (every 8th photo, the usual split)")
    if validation or s.get("validation_offset") is not None:
        validation_position(every, s.get("validation_offset"))
    if int(s["iterations"]) < 1:
        raise CtsplatError(f"photos.train.iterations must be >= 1, got {s['iterations']}")
    if int(s["downscale"]) not in (1, 2, 4, 8):
        raise CtsplatError(f"photos.train.downscale must be 1, 2, 4 or 8, got {s['downscale']}")
    if not 0 <= int(s["sh_degree"]) <= 3:
        raise CtsplatError(f"photos.train.sh_degree must be 0..3, got {s['sh_degree']}")
    for key, allowed in DENSIFY_CHOICES.items():
        if s["densify"][key] not in allowed:
            raise CtsplatError(f"unknown photos.train.densify.{key} {s['densify'][key]!r}; allowed: "
                               f"{', '.join(allowed)}")
