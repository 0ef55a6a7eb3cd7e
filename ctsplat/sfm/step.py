"""The ``sfm`` step: COLMAP poses for the C-arm view set, aligned to the world and scored.

Axial CT slices share no features, so classical structure-from-motion fails on them (:func:`naive_slices_sfm`
reports that case). Cone-beam radiographs over a designed C-arm orbit with dense angular sampling and an elevation
wobble do share features (bone edges, beads), and COLMAP recovers their poses. The step reads the view set that
``ctsplat project`` rendered with ``orbit: carm`` (true and designed pose of every view), then

1. enhances the radiographs for feature detection (:mod:`ctsplat.sfm.features`),
2. runs pycolmap with the detector's pinhole intrinsics held fixed (:mod:`ctsplat.sfm.colmap`): SIFT, exhaustive
   or sequential matching, incremental or global mapping, or — with ``pose_prior`` — triangulation from the
   designed poses and bundle adjustment with priors, up to isocentric bundle adjustment (:mod:`ctsplat.sfm.bundle`:
   every camera a rotation about the designed isocentre at the designed DSO, a rigid C-arm),
3. merges partial models that share images, aligns the recovered centres to the true ones with a robust Sim(3)
   and measures per-view rotation / centre / reprojection errors (:mod:`ctsplat.sfm.align`),
4. writes ``sparse/0`` (binary and text COLMAP model), ``poses.csv``, ``summary.json``, ``points3d.ply`` and
   ``aligned_views.json`` with the same view ids as the input view set (:func:`run_sfm`).

Radiograph features of extended anatomy (skull rims, silhouettes, overlapping structures) are not projections of
fixed 3D points; free bundle adjustment trades a camera shift against a tilt, and transmission images admit a
depth-reversed (Necker) twin. The design prior and the rigid C-arm model remove both; measured results are in
``docs/sfm.md``.

Conventions (``docs/conventions.md``): world mm, ``x_cam = R x_world + t`` (OpenCV / COLMAP), cone-beam pinhole
intrinsics ``fx = fy = DSD / pitch``, ``cx = W/2``, ``cy = H/2``.

References
----------
Schönberger, J. L., Frahm, J.-M. (2016). Structure-from-motion revisited. CVPR.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from collections.abc import Mapping
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.formats.ply import write_points_ply
from ctsplat.formats.viewset import (
    VIEWSET_FORMAT,
    VIEWSET_FORMAT_VERSION,
    View,
    ViewSet,
    load_radiographs,
    write_png_stack,
)
from ctsplat.geometry import camera_center
from ctsplat.sfm.align import evaluate_poses, fuse_with_design
from ctsplat.sfm.colmap import (
    MODEL_FILES,
    REFINE_MODES,
    colmap_reconstruct,
    fix_reversal,
    merge_models,
    model_poses,
    per_image_reproj,
    set_poses_and_triangulate,
    write_model,
)
from ctsplat.sfm.features import enhance_for_features, feature_masks, write_pngs
from ctsplat.utils import (
    CtsplatError,
    atomic_path,
    check_output_dir,
    code_version,
    json_safe,
    made_parents,
    merge_config,
    read_json_object,
    scratch_dir,
    write_json_atomic,
)

__all__ = ["SFM_DEFAULTS", "run_sfm", "run_sfm_on_images", "naive_slices_sfm", "summarize", "sfm_failure"]

log = logging.getLogger(__name__)

#: Every file of an SfM output folder (the figure is the workflow's ``sfm_figure`` rule's). Any one of them marks
#: an earlier output (a run stopped halfway, or one whose outputs the workflow removed, holds only some);
#: :func:`run_sfm` refuses a folder holding anything else, whose files it would replace or delete.
SFM_FILES = ("summary.json", "poses.csv", "aligned_views.json", "points3d.ply", "pose_errors.png",
             "images/view_*.png", *(f"sparse/0/{f}" for f in MODEL_FILES), "colmap/*",
             ".sfm_work.*", ".naive_work.*")  # the step's scratch folders, left by a killed run

#: Defaults of the ``sfm`` config section (JSON-serialisable).
SFM_DEFAULTS: dict[str, Any] = {
    # the view set to register: a radiographs geometry rendered with orbit: carm (its views.json holds the
    # designed and the true pose of each view; camera and orbit settings live there)
    "geometry": "carm",
    # --- contrast enhancement ---
    "clahe_clip": 0.01,  # skimage equalize_adapthist clip_limit
    "clahe_kernel_frac": 0.125,  # kernel size as a fraction of the image size
    "percentile_low": 0.5,  # per-view intensity window before CLAHE (percent)
    "percentile_high": 99.5,
    "background_frac": 0.02,  # rays with p <= this · max are air: blanked (no static image-space features)
    "silhouette_margin_frac": 0.05,  # mask features within this fraction of detector_px of the silhouette
    "lowpass_px": 1.0,  # Gaussian pre-blur (px) against voxel moiré
    "highpass_frac": 0.03,  # subtract a Gaussian blur of σ = highpass_frac · detector_px before the window
    # --- features and matching ---
    "max_num_features": 4096,
    "peak_threshold": 0.004,  # SIFT DoG threshold (radiographs are low-contrast)
    "edge_threshold": 16.0,
    "upright": True,  # the orbit keeps world up at image top: skip SIFT orientation (more distinctive)
    "sift_first_octave": -1,  # -1: the image is upsampled once (finest DoG scales)
    "sift_num_octaves": 4,  # fewer octaves keep only small-scale (more point-like) features
    "sift_domain_size_pooling": False,  # DSP-SIFT descriptors
    "matching": "exhaustive",  # exhaustive | sequential
    "sequential_overlap": 12,  # neighbours matched in `sequential` (cyclic: the orbit closes)
    "max_ratio": 0.8,
    "max_distance": 0.7,
    "min_num_inliers": 15,  # two-view geometry
    "max_error_px": 4.0,  # RANSAC threshold (px)
    # --- mapping ---
    "mapper": "incremental",  # incremental | global
    "init_min_num_inliers": 50,
    "init_min_tri_angle_deg": 4.0,
    "abs_pose_min_num_inliers": 15,
    "abs_pose_min_inlier_ratio": 0.15,
    "filter_min_tri_angle_deg": 0.5,
    "triangulation_min_angle_deg": 0.5,
    "min_model_size": 3,
    # pose priors from the designed orbit:
    #   none     - plain SfM (incremental or global mapper), no prior knowledge of the poses
    #   position - designed source positions as COLMAP position priors (incremental mapper, robust loss)
    #   refine   - triangulate the matches from the designed poses, then bundle-adjust all poses freely
    #              (intrinsics fixed), re-triangulating between rounds (C-arm style calibration refinement)
    #   refine_prior - as refine, but bundle adjustment keeps the designed centres as priors (σ prior_sigma_mm)
    #   isocentric - refine_prior, then isocentric bundle adjustment (ctsplat.sfm.bundle): every camera a rotation
    #                about the designed isocentre at the designed DSO (a rigid C-arm), its rotation kept near the
    #                design by N(0, design_sigma_deg²)
    "pose_prior": "none",
    "refine_rounds": 3,
    "prior_sigma_mm": 5.0,  # std of the position prior (mm)
    "design_sigma_deg": 1.0,  # isocentric: std (deg, per axis) of a view's rotation about its design; null: none
    "isocentre_sigma_mm": 0.0,  # isocentric: 0 = rigid C-arm; > 0 frees a per-view isocentre offset of this std
    "isocentric_loss_px": 0.5,  # isocentric: Cauchy scale (px) of the reprojection loss
    # > 0: keep the SfM poses' deviation from the design only above this many harmonics along the orbit
    # (fuse_with_design: low frequencies from the design, high frequencies from the images); 0: off
    "fuse_harmonics": 0,
    "fix_reversal": True,  # pose_prior none: try each model's depth-reversed twin, keep the one matching the design
    "merge_models": True,
    "min_shared_images": 3,  # to merge two partial models
    # --- alignment and verdict ---
    "align_inlier_threshold_frac": 0.02,  # RANSAC inlier threshold as a fraction of DSO
    "align_iterations": 500,
    "min_registration_rate": 0.8,  # ok needs at least this fraction of views in the main model
    "max_median_rotation_error_deg": 2.0,  # ... and at most this median rotation error
    # ... and a median camera-centre error of at most this fraction of DSO: a depth-ambiguous orbit can have
    # right rotations and wrong distances
    "max_median_centre_error_frac": 0.05,
    # ... and at least this share of the registered views within the alignment's inlier threshold
    "min_alignment_inlier_rate": 0.5,
    "naive_slices": False,  # also run SfM on the raw axial slices (the failure case) and report it
    "keep_work": False,  # keep the COLMAP work folder (database, models) as colmap/; images/ is always kept
}


def colmap_seed(seed: int) -> int:
    """The seed COLMAP gets: pycolmap takes a signed 32-bit integer, the project's seeds run to 2³² - 1.

    Examples
    --------
    >>> colmap_seed(7), colmap_seed(2**31 + 7)
    (7, 7)
    """
    return int(seed) % 2**31


def summarize(rows: list[dict[str, Any]], report: dict[str, Any], cfg: dict[str, Any], *,
              dso_mm: float | None = None, alignment: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Summary numbers of one SfM run: registration rates, median / p90 errors, models, and the ``ok`` verdict.

    ``ok`` needs a registration rate of at least ``min_registration_rate``, a median rotation error of at most
    ``max_median_rotation_error_deg``, a median camera-centre error of at most ``max_median_centre_error_frac``
    of ``dso_mm`` (when given) and at least ``min_alignment_inlier_rate`` of the registered views within the
    alignment's inlier threshold (when ``alignment`` is given); otherwise ``reason`` names each number that fell
    short.

    Parameters
    ----------
    rows : list of dict
        Per-view rows of :func:`ctsplat.sfm.align.evaluate_poses` (optionally with ``reproj_err_px``).
    report : dict
        The merge report of :func:`ctsplat.sfm.colmap.merge_models` (``models_found``, ``model_sizes``,
        ``merged``).
    cfg : dict
        The ``sfm`` section (the verdict thresholds).
    dso_mm : float, optional
        Source-to-isocentre distance (mm), the scale of the centre-error check; None skips that check.
    alignment : mapping, optional
        The alignment of :func:`ctsplat.sfm.align.evaluate_poses` (``ok``, ``n_inliers``, ``n_used``); None
        skips the inlier check.

    Returns
    -------
    dict
        ``n_views``, ``n_registered``, ``registration_rate`` and ``largest_model_rate`` (fractions),
        ``models_found``, ``model_sizes``, ``merged``, ``rot_err_deg_median`` / ``_p90`` and
        ``rot_err_rotalign_deg_median`` (degrees), ``centre_err_mm_median`` / ``_p90`` (mm),
        ``centre_err_frac_median`` (of DSO), ``alignment_inlier_rate`` (fraction), ``reproj_err_px_median`` (px)
        (each None when it has no value), ``ok`` and, when not ok, ``reason``.

    Examples
    --------
    >>> rows = [{"registered": True, "rot_err_deg": 0.4, "centre_err_mm": 30.0}] * 10
    >>> cfg = dict(SFM_DEFAULTS)
    >>> summarize(rows, {"model_sizes": [10]}, cfg)["ok"]
    True
    >>> summarize(rows, {"model_sizes": [10]}, cfg, dso_mm=400.0)["reason"]
    'median centre error 0.075 of DSO (need <= 0.05)'
    """
    V = len(rows)
    reg = [r for r in rows if r["registered"] and np.isfinite(r["rot_err_deg"])]
    rot = np.array([r["rot_err_deg"] for r in reg])
    cen = np.array([r["centre_err_mm"] for r in reg])
    rep = np.array([r.get("reproj_err_px", np.nan) for r in reg], float)
    sizes = report.get("model_sizes", [])

    def q(a: np.ndarray, p: float) -> float | None:
        a = a[np.isfinite(a)]
        return float(np.percentile(a, p)) if a.size else None

    out = {
        "n_views": V,
        "n_registered": len(reg),
        "registration_rate": len(reg) / V if V else 0.0,
        "largest_model_rate": (sizes[0] / V) if sizes and V else 0.0,
        "models_found": int(report.get("models_found", 0)),
        "model_sizes": sizes,
        "merged": report.get("merged", []),
        "rot_err_deg_median": q(rot, 50),
        "rot_err_deg_p90": q(rot, 90),
        "rot_err_rotalign_deg_median": q(np.array([r.get("rot_err_rotalign_deg", np.nan) for r in reg], float), 50),
        "centre_err_mm_median": q(cen, 50),
        "centre_err_mm_p90": q(cen, 90),
        "reproj_err_px_median": q(rep, 50),
    }
    centre = out["centre_err_mm_median"]
    out["centre_err_frac_median"] = centre / dso_mm if dso_mm and centre is not None else None
    aligned = alignment is not None and bool(alignment.get("ok")) and int(alignment.get("n_used", 0)) > 0
    out["alignment_inlier_rate"] = int(alignment["n_inliers"]) / int(alignment["n_used"]) if aligned else None
    short = []
    if out["registration_rate"] < cfg["min_registration_rate"]:
        short.append(f"registration rate {out['registration_rate']:.4g} (need >= {cfg['min_registration_rate']})")
    rot_median = out["rot_err_deg_median"]
    if rot_median is None or rot_median > cfg["max_median_rotation_error_deg"]:
        shown = "none (fewer than 3 views registered)" if rot_median is None else f"{rot_median:.5g} deg"
        short.append(f"median rotation error {shown} (need <= {cfg['max_median_rotation_error_deg']} deg)")
    frac = out["centre_err_frac_median"]
    if frac is not None and frac > cfg["max_median_centre_error_frac"]:
        short.append(f"median centre error {frac:.5g} of DSO (need <= {cfg['max_median_centre_error_frac']})")
    inliers = out["alignment_inlier_rate"]
    if inliers is not None and inliers < cfg["min_alignment_inlier_rate"]:
        short.append(f"{inliers:.4g} of the registered views within the alignment threshold"
                     f" (need >= {cfg['min_alignment_inlier_rate']})")
    out["ok"] = not short
    if short:
        out["reason"] = "; ".join(short)
    return out


def sfm_failure(summary: Mapping[str, Any] | str | os.PathLike[str]) -> str | None:
    """Why an SfM run may not be trained on, or None when it may (its ``ok`` verdict, see :func:`summarize`).

    Parameters
    ----------
    summary : mapping or path-like
        The ``summary.json`` of :func:`run_sfm`, or its path.

    Returns
    -------
    str or None
        None when ``ok`` is true; otherwise one line naming the numbers that fell short (``reason``), or that the
        summary is missing.

    Examples
    --------
    >>> sfm_failure({"ok": True}) is None
    True
    >>> sfm_failure({"ok": False, "reason": "registration rate 0.10 (need >= 0.8)"})
    'registration rate 0.10 (need >= 0.8)'
    """
    if not isinstance(summary, Mapping):
        path = Path(summary)
        if not path.exists():
            return f"{path} does not exist (the sfm step did not run)"
        summary = read_json_object(path, what="SfM summary", fix="run the sfm step again")
    if summary.get("ok", False):
        return None
    return str(summary.get("reason") or "the SfM summary is not ok and records no reason")


def run_sfm_on_images(images_u8: np.ndarray, intrinsics: tuple[float, float, float, float], Rs_true: np.ndarray,
                      ts_true: np.ndarray, out_dir: str | Path, config: dict[str, Any], *, seed: int = 0,
                      prefix: str = "view", scale_mm: float, prior_centres: np.ndarray | None = None,
                      prior_poses: tuple[np.ndarray, np.ndarray] | None = None, masks: np.ndarray | None = None,
                      design: tuple[np.ndarray, np.ndarray] | None = None,
                      design_azimuth_deg: np.ndarray | None = None, ids: np.ndarray | None = None
                      ) -> tuple[dict[str, Any], list[dict[str, Any]], Any]:
    """COLMAP, merging and alignment on given 8-bit images with known true poses; writes only inside ``out_dir``.

    With ``fix_reversal`` and a ``design`` (and no pose prior), each model is replaced by its depth-reversed twin
    when that fits the design better. With ``fuse_harmonics > 0`` (and ``design`` + ``design_azimuth_deg``), the
    poses are fused with the design (:func:`~ctsplat.sfm.align.fuse_with_design`); the summary then also holds
    the unfused numbers under ``"unfused"`` and the registered views the fusion left out as SfM outliers under
    ``"fusion_outliers"``. Too few registrations do not raise: ``ok`` is False.

    Parameters
    ----------
    images_u8 : ndarray, shape (V, H, W), uint8
        Feature images (:func:`ctsplat.sfm.features.enhance_for_features`).
    intrinsics : tuple of float
        ``(fx, fy, cx, cy)`` in px, held fixed.
    Rs_true : ndarray, shape (V, 3, 3)
        True world->camera rotations (the reference the recovered poses are scored against).
    ts_true : ndarray, shape (V, 3)
        True world->camera translations (mm).
    out_dir : str or Path
        Work folder: ``images/``, ``masks/``, ``colmap/`` are written here.
    config : dict
        The ``sfm`` section, merged with :data:`SFM_DEFAULTS`.
    seed : int
        Seeds COLMAP and the alignment.
    prefix : str
        Image file name prefix.
    scale_mm : float
        Length scale of the orbit (DSO, mm); the alignment inlier threshold is ``align_inlier_threshold_frac``
        times this, and the verdict's centre-error bound ``max_median_centre_error_frac`` times this.
    prior_centres : ndarray, shape (V, 3), optional
        Designed camera centres (world mm) for ``pose_prior: position``.
    prior_poses : tuple of ndarray, optional
        Designed poses ``(Rs (V, 3, 3), ts (V, 3) mm)`` for the refine modes.
    masks : ndarray, shape (V, H, W), uint8, optional
        Feature masks (255 = keep).
    design : tuple of ndarray, optional
        Designed poses ``(Rs (V, 3, 3), ts (V, 3) mm)`` for the reversal check, the fusion and the
        ``design_rot_err_deg_median`` baseline.
    design_azimuth_deg : ndarray, shape (V,), optional
        Designed azimuths (degrees) for the fusion.
    ids : ndarray of int, shape (V,), optional
        View ids used in the image names; default ``0 .. V-1``.

    Returns
    -------
    summary : dict
        :func:`summarize`'s numbers plus ``colmap`` (stage statistics), ``reversal``, ``alignment`` and, when a
        design is given, ``design_rot_err_deg_median`` (what the design alone scores, degrees).
    rows : list of dict, length V
        Per view (see :func:`~ctsplat.sfm.align.evaluate_poses`) plus ``reproj_err_px``, ``in_main_model`` and
        ``model_pose`` (``(R, t)`` in the model's own frame, before the alignment to the truth; None when not
        registered).
    model_and_alignment : tuple
        ``(main pycolmap model or None, alignment dict of evaluate_poses)``.
    """
    cfg = dict(config)
    cfg["_seed"] = colmap_seed(seed)
    out_dir = Path(out_dir)
    img_dir = out_dir / "images"
    names = write_pngs(images_u8, img_dir, prefix=prefix, ids=ids)
    mask_dir = None
    if masks is not None:  # COLMAP reads the mask of image NAME from NAME.png
        mask_dir = out_dir / "masks"
        write_png_stack(np.asarray(masks, np.uint8), mask_dir, [f"{n}.png" for n in names])
    models, stats = colmap_reconstruct(img_dir, names, intrinsics, out_dir / "colmap", cfg,
                                       prior_centres=prior_centres, prior_poses=prior_poses, mask_dir=mask_dir)
    reversal = []
    if cfg["fix_reversal"] and design is not None and models and prior_centres is None and prior_poses is None:
        reversal = fix_reversal(models, {n: (design[0][i], design[1][i]) for i, n in enumerate(names)}, cfg,
                                float(cfg["align_inlier_threshold_frac"]) * scale_mm,
                                work=(out_dir / "colmap" / "database.db", img_dir, out_dir / "colmap" / "twin"))
    main, poses, report = merge_models(models, int(cfg["min_shared_images"])) if cfg["merge_models"] else \
        merge_models({k: v for k, v in models.items() if k == max(models, key=lambda j: models[j].num_reg_images())}
                     if models else {}, 3)
    if not cfg["merge_models"] and models:
        report["models_found"] = len(models)
        report["model_sizes"] = sorted((int(m.num_reg_images()) for m in models.values()), reverse=True)
    thr = float(cfg["align_inlier_threshold_frac"]) * scale_mm
    unfused = None
    outliers: list[str] = []
    if int(cfg["fuse_harmonics"]) > 0 and design is not None and design_azimuth_deg is not None and poses:
        rows0, _ = evaluate_poses(poses, names, Rs_true, ts_true, threshold_mm=thr,
                                  iterations=int(cfg["align_iterations"]), seed=seed)
        s0 = summarize(rows0, report, cfg)
        unfused = {k: s0[k] for k in ("rot_err_deg_median", "rot_err_deg_p90", "rot_err_rotalign_deg_median",
                                      "centre_err_mm_median", "registration_rate")}
        registered = set(poses)
        poses = fuse_with_design(poses, names, design[0], design[1], design_azimuth_deg, int(cfg["fuse_harmonics"]),
                                 full_circle=float(cfg.get("_arc_deg", 360.0)) >= 360.0, threshold_mm=thr,
                                 threshold_deg=float(np.degrees(thr / scale_mm)),
                                 iterations=int(cfg["align_iterations"]), seed=seed)
        outliers = sorted(registered - set(poses))
        if main is not None:  # the written model carries the fused poses, its points re-triangulated from them
            main = set_poses_and_triangulate(main, poses, out_dir / "colmap" / "database.db", img_dir,
                                              out_dir / "colmap" / "fused", cfg)
    rows, align = evaluate_poses(poses, names, Rs_true, ts_true, threshold_mm=thr,
                                 iterations=int(cfg["align_iterations"]), seed=seed)
    reproj = per_image_reproj(main) if main is not None else {}
    for r in rows:
        r["model_pose"] = poses.get(r["name"])  # in the model's own frame, for the export (design_frame)
        r["reproj_err_px"] = reproj.get(r["name"], np.nan)
        r["in_main_model"] = r["name"] in reproj or (main is not None and main.find_image_with_name(r["name"])
                                                       is not None and r["registered"] and r["name"] in
                                                       model_poses(main))
    summary = summarize(rows, report, cfg, dso_mm=scale_mm, alignment=align)
    summary["colmap"] = stats
    summary["reversal"] = reversal
    if unfused is not None:
        summary["unfused"] = unfused
        summary["fusion_outliers"] = outliers
    if design is not None:  # the designed orbit itself as the answer (no images): what a prior alone gives
        drows, _ = evaluate_poses({n: (design[0][i], design[1][i]) for i, n in enumerate(names)}, names, Rs_true,
                                  ts_true, threshold_mm=thr, iterations=int(cfg["align_iterations"]), seed=seed)
        summary["design_rot_err_deg_median"] = float(np.median([r["rot_err_deg"] for r in drows]))
    summary["alignment"] = {k: v for k, v in align.items()
                            if k in ("ok", "scale", "n_inliers", "n_used", "residual_rotation_deg")}
    return summary, rows, (main, align)


def run_sfm(radiographs_dir: str | Path, out_dir: str | Path, config: dict[str, Any] | None = None, seed: int = 0,
            *, volume_path: str | Path | None = None) -> dict[str, Any]:
    """Register the C-arm view set's radiographs with COLMAP, align the poses to the world, write the results.

    Parameters
    ----------
    radiographs_dir : path
        A radiograph folder written by ``ctsplat project`` for a geometry with ``orbit: carm``: its
        ``views.json`` holds each view's true pose (the reference the recovered poses are scored against) and
        its designed pose (the prior of the ``pose_prior`` modes).
    out_dir : path
        Receives ``sparse/0/`` (binary COLMAP model + ``text/``), ``poses.csv`` (per view: registered, errors),
        ``summary.json``, ``points3d.ply`` (aligned, world mm), ``aligned_views.json`` (the registered,
        plausible views with their recovered poses, same view ids as the input view set) and ``images/`` (the
        8-bit feature images COLMAP read).
    config : dict, optional
        The ``sfm`` section (:data:`SFM_DEFAULTS`).
    seed : int
        Seeds COLMAP's and the alignment's random choices.
    volume_path : path, optional
        The volume, only read for ``naive_slices`` (SfM on its axial slices, the failure case).

    Returns
    -------
    dict
        The summary (also written): registration rate, pose errors, COLMAP statistics, ``ok`` verdict. Too few
        registrations do not raise: ``ok`` is False.

    Raises
    ------
    CtsplatError
        For an unknown ``matching``, ``mapper`` or ``pose_prior``, ``pose_prior: position`` without the
        incremental mapper, ``naive_slices`` without ``volume_path``, a parallel-beam view set, or a view set
        without designed poses (not rendered with ``orbit: carm``).

    Examples
    --------
    >>> settings = {"pose_prior": "isocentric"}
    >>> summary = run_sfm("results/head/radiographs/carm", "results/head/sfm", settings)  # doctest: +SKIP
    >>> print(summary["ok"], summary["registration_rate"], summary["rot_err_deg_median"])  # doctest: +SKIP
    """
    cfg = merge_config("sfm", config, SFM_DEFAULTS)
    if cfg["matching"] not in ("exhaustive", "sequential"):
        raise CtsplatError(f"unknown sfm.matching {cfg['matching']!r}; allowed: exhaustive, sequential")
    if cfg["mapper"] not in ("incremental", "global"):
        raise CtsplatError(f"unknown sfm.mapper {cfg['mapper']!r}; allowed: incremental, global")
    if cfg["pose_prior"] not in ("none", "position", "refine", "refine_prior", "isocentric"):
        raise CtsplatError(f"unknown sfm.pose_prior {cfg['pose_prior']!r}; "
                           "allowed: none, position, refine, refine_prior, isocentric")
    if cfg["pose_prior"] == "position" and cfg["mapper"] != "incremental":
        raise CtsplatError("sfm.pose_prior 'position' needs sfm.mapper 'incremental' (global mapping ignores priors)")
    if cfg["naive_slices"] and volume_path is None:
        raise CtsplatError("sfm.naive_slices needs the volume: pass volume_path (CLI: --volume)")
    check_output_dir(out_dir, marker=SFM_FILES, in_place=True,
                     inputs=(radiographs_dir, *([volume_path] if volume_path is not None else [])))
    naive_volume = None
    if cfg["naive_slices"]:  # read before any output is replaced: a bad volume fails the step with nothing written
        from ctsplat.formats.volume import load_volume

        naive_volume = load_volume(volume_path).data
    p, vs = load_radiographs(radiographs_dir)
    cam = vs.camera
    if cam.model != "cone":
        raise CtsplatError(f"{radiographs_dir} holds {cam.model}-beam radiographs; SfM needs a cone-beam view set "
                           "(a radiographs geometry with camera: cone, orbit: carm)")
    if not vs.has_design():
        raise CtsplatError(f"{radiographs_dir}/views.json has no designed poses; render the SfM view set with "
                           "orbit: carm")
    cfg["_arc_deg"] = float(vs.meta.get("arc_deg") or 360.0)
    out_dir = Path(out_dir)
    is_new = not out_dir.exists()
    with made_parents(out_dir):  # a failed first run leaves no folder behind, and no parent it made
        out_dir.mkdir(exist_ok=True)
        try:
            return _register_and_write(p, vs, out_dir, cfg, seed, naive_volume, radiographs_dir)
        except BaseException:
            if is_new:
                shutil.rmtree(out_dir, ignore_errors=True)
            raise


def design_frame(rows: list[dict[str, Any]], design_centres: np.ndarray, *, in_design_frame: bool,
                 threshold_mm: float, iterations: int, seed: int) -> dict[str, Any] | None:
    """The recovered poses as training gets them: in the frame of the designed orbit, which a user knows, not of
    the true one, which only scores them.

    A model made with a pose prior or fused with the design (``in_design_frame``) is in the design's frame already
    and is exported as it is; any other is moved there by a robust Sim(3) from its camera centres to the designed
    ones (with the scores' alignment settings).

    Parameters
    ----------
    rows : list of dict
        Per view: ``view`` (row) and ``model_pose`` (``(R (3, 3), t (3,))`` in the model's frame, None when not
        registered), as :func:`run_sfm_on_images` returns them.
    design_centres : ndarray (V, 3)
        The designed camera centres, world mm.
    in_design_frame : bool
    threshold_mm, iterations, seed
        RANSAC inlier distance (mm), samples and seed of the Sim(3) to the design.

    Returns
    -------
    dict or None
        ``poses`` (row -> ``(R, t)`` world-to-camera, mm) and the Sim(3) ``scale``, ``R``, ``t`` from the SfM
        model's frame into the design's (for its points); None with fewer than 3 registered views.
    """
    from ctsplat.sfm.align import robust_sim3

    model = {int(r["view"]): (np.asarray(r["model_pose"][0], float), np.asarray(r["model_pose"][1], float))
             for r in rows if r["model_pose"] is not None}
    if len(model) < 3:
        return None
    if in_design_frame:
        e_s, e_R, e_t = 1.0, np.eye(3), np.zeros(3)
    else:
        keys = sorted(model)
        src = np.stack([camera_center(*model[k]) for k in keys])
        e_s, e_R, e_t, _ = robust_sim3(src, design_centres[keys], threshold_mm, iterations=iterations, seed=seed)
    poses = {}
    for k, (R, t) in model.items():
        Rw = R @ e_R.T
        cw = e_s * e_R @ camera_center(R, t) + e_t
        poses[k] = (Rw, -Rw @ cw)
    return {"poses": poses, "scale": e_s, "R": e_R, "t": e_t}


def _register_and_write(p: np.ndarray, vs: ViewSet, out_dir: Path, cfg: dict[str, Any], seed: int,
                        naive_volume: np.ndarray | None, radiographs_dir: str | Path) -> dict[str, Any]:
    """:func:`run_sfm` after its checks: enhance, register, align and write the outputs into ``out_dir``."""
    import pandas as pd

    # the verdict goes first: until the new one is written, training refuses whatever poses the folder holds
    (out_dir / "summary.json").unlink(missing_ok=True)
    cam = vs.camera
    iso = vs.isocenter_mm
    W, H = cam.width, cam.height
    ids = vs.ids()
    Rs_true, ts_true = vs.Rs(), vs.ts()
    design_Rs, design_ts = vs.design_Rs(), vs.design_ts()
    design_az = np.array([v.design.azimuth_deg for v in vs.views], float)
    design_centres = np.stack([camera_center(R, t) for R, t in zip(design_Rs, design_ts, strict=True)])
    imgs = enhance_for_features(p, clip=cfg["clahe_clip"], kernel_frac=cfg["clahe_kernel_frac"],
                                p_low=cfg["percentile_low"], p_high=cfg["percentile_high"],
                                highpass_frac=cfg["highpass_frac"], lowpass_px=cfg["lowpass_px"],
                                background_frac=cfg["background_frac"])
    margin = float(cfg["silhouette_margin_frac"]) * W
    masks = feature_masks(p, float(cfg["background_frac"]) or 0.02, margin) if margin > 0 else None
    with scratch_dir(out_dir, prefix=".sfm_work.") as work:
        try:
            summary, rows, (main, align) = run_sfm_on_images(
                imgs, (cam.fx, cam.fy, cam.cx, cam.cy), Rs_true, ts_true, work, cfg, seed=seed, ids=ids,
                scale_mm=float(cam.dso_mm),
                prior_centres=design_centres if cfg["pose_prior"] == "position" else None,
                prior_poses=(design_Rs, design_ts) if cfg["pose_prior"] in REFINE_MODES else None,
                masks=masks, design=(design_Rs, design_ts), design_azimuth_deg=design_az)
            # an earlier run's model and points go when this run has none: init sfm must not seed from them
            if main is not None:
                write_model(main, out_dir / "sparse" / "0")
            else:
                shutil.rmtree(out_dir / "sparse" / "0", ignore_errors=True)
            # what the scores could not align (fewer than 3 registered views) is not exported either
            export = design_frame(rows, design_centres,
                                  in_design_frame=cfg["pose_prior"] != "none" or "unfused" in summary,
                                  threshold_mm=float(cfg["align_inlier_threshold_frac"]) * float(cam.dso_mm),
                                  iterations=int(cfg["align_iterations"]), seed=seed) if align["ok"] else None
            if main is not None and export is not None:
                xyz = np.array([pt.xyz for pt in main.points3D.values()]).reshape(-1, 3)
                write_points_ply(out_dir / "points3d.ply", export["scale"] * xyz @ export["R"].T + export["t"])
            else:
                (out_dir / "points3d.ply").unlink(missing_ok=True)
            if (out_dir / "images").exists():
                shutil.rmtree(out_dir / "images")
            (work / "images").rename(out_dir / "images")
        finally:
            shutil.rmtree(out_dir / "colmap", ignore_errors=True)  # an earlier run's work folder is not this one's
            if cfg["keep_work"] and (work / "colmap").exists():
                (work / "colmap").rename(out_dir / "colmap")

    # physical plausibility: a view whose optical axis misses the isocentre by more than the detector's
    # half field of view atan((W/2) / fx) cannot have imaged the object; such poses are not exported
    half_fov = math.degrees(math.atan(0.5 * W / cam.fx))
    exported = export["poses"] if export is not None else {}
    for r in rows:
        r["plausible"] = False
        if r["view"] in exported:
            R_e, t_e = exported[r["view"]]
            c = camera_center(R_e, t_e)
            d = (iso - c) / max(float(np.linalg.norm(iso - c)), 1e-9)
            r["plausible"] = bool(math.degrees(math.acos(float(np.clip(R_e[2] @ d, -1, 1)))) <= half_fov)
    summary["n_plausible"] = int(sum(r["plausible"] for r in rows))
    summary["plausible_rate"] = summary["n_plausible"] / len(rows)
    by_row = vs.views
    table = pd.DataFrame([{
        "view_id": int(ids[r["view"]]), "name": r["name"], "azimuth_deg": by_row[r["view"]].azimuth_deg,
        "elevation_deg": by_row[r["view"]].elevation_deg, "registered": r["registered"],
        "rot_err_deg": r["rot_err_deg"], "rot_err_rotalign_deg": r["rot_err_rotalign_deg"],
        "centre_err_mm": r["centre_err_mm"], "reproj_err_px": r["reproj_err_px"], "plausible": r["plausible"],
    } for r in rows])
    with atomic_path(out_dir / "poses.csv") as tmp:
        table.to_csv(tmp, index=False, lineterminator="\n")
    # the recovered poses in the design's frame, with the designed directions: nothing the truth decided
    views = [View(int(ids[r["view"]]), *exported[r["view"]], by_row[r["view"]].design.azimuth_deg,
                  by_row[r["view"]].design.elevation_deg, "train", by_row[r["view"]].design)
             for r in rows if r["plausible"]]
    vs_meta = {"source": "sfm", "registration_rate": summary["registration_rate"], "ok": summary["ok"],
               "n_views_designed": len(rows), "radiographs": str(radiographs_dir)}
    if views:
        ViewSet(camera=cam, views=views, volume_id=vs.volume_id, isocenter_mm=iso, meta=vs_meta).save(
            out_dir / "aligned_views.json")
    else:  # nothing registered: same format with no views (ViewSet.load then refuses it with a clear message)
        write_json_atomic(out_dir / "aligned_views.json", {
            "format": VIEWSET_FORMAT, "format_version": VIEWSET_FORMAT_VERSION, "volume_id": vs.volume_id,
            "isocenter_mm": np.asarray(iso, float).tolist(), "camera": cam.to_dict(), "views": [], "meta": vs_meta})
    if naive_volume is not None:
        with scratch_dir(out_dir, prefix=".naive_work.") as naive_work:
            summary["naive_slices"] = naive_slices_sfm(naive_volume, naive_work, cfg, seed=seed)
    cfg.pop("_arc_deg", None)
    summary.update(config=cfg, seed=seed, code_version=code_version(), pycolmap=version("pycolmap"),
                   volume_id=vs.volume_id,
                   radiographs=str(radiographs_dir),
                   camera={"model": "PINHOLE", "width": W, "height": H, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                           "cy": cam.cy, "pitch_mm": cam.pitch_mm, "dso_mm": cam.dso_mm, "dsd_mm": cam.dsd_mm})
    write_json_atomic(out_dir / "summary.json", json_safe(summary))
    if not summary["ok"]:  # the step itself succeeds (the report shows the failure), so say it loudly here
        log.warning("SfM failed: %s; poses: colmap runs will refuse to train on these poses (%s)",
                    summary.get("reason", "no reason recorded"), out_dir / "summary.json")
    return summary


def naive_slices_sfm(volume_data: np.ndarray, work_dir: str | Path, config: dict[str, Any], seed: int = 0
                     ) -> dict[str, Any]:
    """The failure case: COLMAP on the raw axial slices (``data[:, :, k]``) treated as photographs.

    The slices are windowed to 8 bit (same percentile + CLAHE enhancement as the radiographs) and fed to the
    same pipeline with a guessed pinhole camera (``f = 1.2 · max(W, H)``, as COLMAP would guess). There is
    no ground-truth pose, so only registration counts are reported.

    Parameters
    ----------
    volume_data : ndarray, shape (I, J, K)
        Volume values; slice ``k`` is ``data[:, :, k]``.
    work_dir : str or Path
        Scratch folder.
    config : dict
        The ``sfm`` section (private ``_`` keys are ignored).
    seed : int
        Seeds COLMAP.

    Returns
    -------
    dict
        ``n_images``, ``models_found``, ``model_sizes``, ``registration_rate`` (largest model / slices) and
        ``colmap`` (stage statistics).
    """
    cfg = dict(merge_config("sfm", {k: v for k, v in config.items() if not k.startswith("_")}, SFM_DEFAULTS))
    cfg["_seed"] = colmap_seed(seed)
    cfg["_arc_deg"] = 0.0  # a stack of slices, not an orbit: no loop-closure pairs of the first and last slices
    data = np.asarray(volume_data, float)
    slices = np.moveaxis(data, 2, 0)  # (K, I, J)
    imgs = enhance_for_features(slices, clip=cfg["clahe_clip"], kernel_frac=cfg["clahe_kernel_frac"],
                                p_low=cfg["percentile_low"], p_high=cfg["percentile_high"],
                                highpass_frac=cfg["highpass_frac"], lowpass_px=cfg["lowpass_px"],
                                background_frac=cfg["background_frac"])
    work_dir = Path(work_dir)
    names = write_pngs(imgs, work_dir / "images", prefix="slice")
    H, W = imgs.shape[1:]
    f = 1.2 * max(H, W)
    models, stats = colmap_reconstruct(work_dir / "images", names, (f, f, W / 2, H / 2), work_dir / "colmap", cfg)
    sizes = sorted((int(m.num_reg_images()) for m in models.values()), reverse=True)
    return {"n_images": len(names), "models_found": len(models), "model_sizes": sizes,
            "registration_rate": (sizes[0] / len(names)) if sizes else 0.0, "colmap": stats}
