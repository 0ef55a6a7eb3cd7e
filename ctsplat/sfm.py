"""SfM-guided poses: COLMAP (pycolmap) on synthetic cone-beam radiographs, Sim(3) alignment, pose accuracy.

Axial CT slices share no features, so classical structure-from-motion fails on them. Cone-beam radiographs
rendered over a designed orbit with dense angular sampling and an elevation wobble do share features (bone
edges, beads), and COLMAP recovers their poses. This module

1. designs the orbit (:func:`design_orbit`) and renders the views with :mod:`ctsplat.projector`,
2. enhances them for feature detection (:func:`enhance_for_features`: CLAHE, 8-bit),
3. runs pycolmap (:func:`colmap_reconstruct`: SIFT, exhaustive / sequential(+loop) / spatial matching,
   incremental or global mapping) with the *known* pinhole intrinsics held fixed,
4. merges partial models that share images (:func:`merge_models`),
5. aligns recovered camera centres to the true ones with a robust Sim(3) (:func:`robust_sim3`) and measures
   per-view rotation / centre / reprojection errors (:func:`evaluate_poses`),
6. writes ``sparse/0`` (binary and text COLMAP model), ``poses.csv``, ``summary.json``, ``points3d.ply`` and
   ``aligned_views.json`` (:func:`run_sfm`).

Measured (``benchmarks/sfm.py``): on fiducial beads in air the pipeline registers every view in one model
with a median rotation error of about 1 degree (256 px); on the head CT and the Shepp-Logan phantom most
views register (global mapper: all) but the poses are wrong by degrees to tens of degrees. The conventions are
exact (``tests/unit/test_sfm_exact.py``: projector beads land on COLMAP's pinhole projection to < 0.1 px, and
exact correspondences through the same mapping and evaluation give < 0.01 degree). Radiograph features of
extended anatomy (skull rims, silhouettes, overlapping structures) are not projections of fixed 3D points:
bundle adjustment started *at the true poses* drifts by several degrees to a smoothly bent orbit with a
lower reprojection error, and transmission images admit a depth-reversed (Necker) twin solution
(:func:`reverse_depth`). The view-to-view pose changes are recovered much better than the orbit's shape, so
``fuse_harmonics`` (:func:`fuse_with_design`) takes the orbit's smooth shape from the design and the per-view
detail from the images: on the head (180 views, 256 px, true orbit N(0, 1 deg) off the design) the median
rotation error drops from 1.0-1.3 deg (design alone) to 0.42-0.56 deg over 8 orbit seeds. Better still is to
remove the shift-versus-tilt trade altogether: ``pose_prior: isocentric`` bundle-adjusts every camera as a
rotation about the designed isocentre at the designed DSO (a rigid C-arm, :mod:`ctsplat.bundle`), which gives
0.36-0.47 deg (<= 0.5 deg on all 8 seeds) on the same views without any fusion (README, "SfM poses").

Conventions (``docs/conventions.md``): world mm, ``x_cam = R x_world + t`` (OpenCV / COLMAP), cone-beam
pinhole intrinsics ``fx = fy = DSD / pitch``, ``cx = W/2``, ``cy = H/2``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.utils import CtsplatError, atomic_path, code_version, json_safe, merge_config, write_json_atomic

__all__ = [
    "SFM_DEFAULTS",
    "design_orbit",
    "support_radius_mm",
    "enhance_for_features",
    "feature_masks",
    "write_pngs",
    "colmap_reconstruct",
    "colmap_map",
    "merge_models",
    "orbit_basis",
    "fuse_with_design",
    "umeyama",
    "robust_sim3",
    "rotation_error_deg",
    "evaluate_poses",
    "summarize",
    "write_points_ply",
    "run_sfm",
    "run_sfm_on_images",
    "naive_slices_sfm",
]

log = logging.getLogger(__name__)

#: ``pose_prior`` modes that triangulate from the designed poses and refine them (:func:`colmap_map`).
REFINE_MODES = ("refine", "refine_prior", "isocentric")

#: Defaults of the ``sfm`` config section (JSON-serialisable).
SFM_DEFAULTS: dict[str, Any] = {
    # --- designed orbit (cone beam) ---
    "n_views": 90,  # views over `arc_deg`
    "arc_deg": 360.0,  # azimuth range; 360 closes the loop
    "wobble_deg": 15.0,  # elevation amplitude: el = wobble * sin(wobble_cycles * az)
    "wobble_cycles": 2.0,
    "detector_px": 128,  # square detector W = H
    "dso_mm": 600.0,  # source -> isocentre
    "dsd_mm": 1000.0,  # source -> detector
    "pitch_mm": None,  # detector pixel pitch; None: fit the volume bounding sphere * fov_margin
    "fov_margin": 1.0,
    "step_voxels": 0.5,  # projector sampling step
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
    "matching": "exhaustive",  # exhaustive | sequential | spatial
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
    #   isocentric - refine_prior, then isocentric bundle adjustment (ctsplat.bundle): every camera a rotation
    #                about the designed isocentre at the designed DSO (a rigid C-arm), its rotation kept near the
    #                design by N(0, design_sigma_deg²)
    "pose_prior": "none",
    "refine_rounds": 3,
    "prior_sigma_mm": 5.0,  # std of the position prior (mm)
    "design_sigma_deg": 1.0,  # isocentric: std (deg, per axis) of a view's rotation about its design; null: none
    "isocentre_sigma_mm": 0.0,  # isocentric: 0 = rigid C-arm; > 0 frees a per-view isocentre offset of this std
    "isocentric_loss_px": 0.5,  # isocentric: Cauchy scale (px) of the reprojection loss
    "orbit_jitter_deg": 0.0,  # true views deviate from the design by N(0, σ) in azimuth and elevation
    "orbit_jitter_mm": 0.0,  # ... and their isocentre by N(0, σ² I) mm (the whole source-detector assembly shifts)
    # > 0: keep the SfM poses' deviation from the design only above this many harmonics along the orbit
    # (fuse_with_design: low frequencies from the design, high frequencies from the images); 0: off
    "fuse_harmonics": 0,
    "fix_reversal": True,  # pose_prior none: try each model's depth-reversed twin, keep the one matching the design
    "merge_models": True,
    "min_shared_images": 3,  # to merge two partial models
    "num_threads": 1,
    # --- alignment and verdict ---
    "align_inlier_threshold_frac": 0.02,  # RANSAC inlier threshold as a fraction of DSO
    "align_iterations": 500,
    "min_registration_rate": 0.8,  # ok needs at least this fraction of views in the main model
    "max_median_rotation_error_deg": 2.0,  # ... and at most this median rotation error
    "naive_slices": False,  # also run SfM on the raw axial slices (the failure case) and report it
    "keep_work": False,  # keep the COLMAP database and PNGs (otherwise PNGs are kept, database dropped)
}


# ----------------------------------------------------------------------------------------------------------
# Orbit and images
# ----------------------------------------------------------------------------------------------------------
def design_orbit(n_views: int, arc_deg: float, wobble_deg: float, wobble_cycles: float, dso_mm: float,
                 isocenter_mm: np.ndarray | None = None, *, jitter_deg: float = 0.0, jitter_mm: float = 0.0,
                 seed: int = 0) -> dict[str, np.ndarray]:
    """Designed cone-beam orbit around the world z axis with a sinusoidal elevation wobble.

    Source position of view ``i`` (azimuth φ_i = i · arc / n for a full circle, or evenly spaced
    including both ends for a partial arc; elevation θ_i = wobble · sin(cycles · φ_i)), plus, with
    ``jitter_deg > 0``, independent N(0, jitter²) deviations of φ_i and θ_i (a real orbit off its design):
    ``c_i = iso + DSO (cos θ cos φ, cos θ sin φ, sin θ)``; the camera looks at the isocentre. With
    ``jitter_mm > 0`` each view's whole source-detector assembly is also shifted by N(0, jitter_mm² I) (a gantry
    whose isocentre wobbles): ``c_i += δ_i`` and the camera looks at ``iso + δ_i``.

    Returns
    -------
    dict with ``Rs`` (V, 3, 3), ``ts`` (V, 3) world->camera, ``centres`` (V, 3) mm, ``azimuth_deg`` (V,),
    ``elevation_deg`` (V,).
    """
    if n_views < 2:
        raise CtsplatError(f"sfm.n_views must be >= 2, got {n_views}")
    if not 0 < arc_deg <= 360:
        raise CtsplatError(f"sfm.arc_deg must be in (0, 360], got {arc_deg}")
    if abs(wobble_deg) >= 80:
        raise CtsplatError(f"sfm.wobble_deg must be < 80 degrees, got {wobble_deg}")
    iso = np.zeros(3) if isocenter_mm is None else np.asarray(isocenter_mm, float)
    full = math.isclose(arc_deg, 360.0)
    az = np.arange(n_views) * arc_deg / n_views if full else np.linspace(0.0, arc_deg, n_views)
    el = wobble_deg * np.sin(np.deg2rad(wobble_cycles * az))
    if jitter_deg > 0:
        rng = np.random.default_rng(seed)
        az = az + rng.normal(0.0, jitter_deg, n_views)
        el = el + rng.normal(0.0, jitter_deg, n_views)
    shift = np.zeros((n_views, 3))
    if jitter_mm > 0:
        shift = np.random.default_rng([seed, 1]).normal(0.0, jitter_mm, (n_views, 3))
    a, e = np.deg2rad(az), np.deg2rad(el)
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
    centres = iso + shift + dso_mm * dirs
    from ctsplat.geometry import look_at

    Rs, ts = zip(*(look_at(c, iso + d) for c, d in zip(centres, shift, strict=True)), strict=True)
    return {"Rs": np.stack(Rs), "ts": np.stack(ts), "centres": centres, "azimuth_deg": az, "elevation_deg": el}


def enhance_for_features(images: np.ndarray, *, clip: float = 0.01, kernel_frac: float = 0.125,
                         p_low: float = 0.5, p_high: float = 99.5, highpass_frac: float = 0.0, lowpass_px: float = 0.0,
                         background_frac: float = 0.0) -> np.ndarray:
    """Contrast-enhance radiographs for SIFT: optional high-pass, per-view percentile window, CLAHE, 8-bit.

    Parameters
    ----------
    images : ndarray (V, H, W) or (H, W), float
        Line integrals ``p`` (or any intensity); higher = more attenuation (shown bright, like bone).

    Returns
    -------
    ndarray (V, H, W) uint8
        ``round(255 · CLAHE(clip((q - P_low(q)) / (P_high(q) - P_low(q)), 0, 1)))`` per view
        (``skimage.exposure.equalize_adapthist`` with ``kernel_size = kernel_frac · max(H, W)``), where
        ``q = p - G_σ * p`` with a Gaussian of ``σ = highpass_frac · max(H, W)`` px when ``highpass_frac > 0``
        (removes the smooth path-length component so small structures such as beads stand out), else ``q = p``;
        ``p`` is first blurred by a Gaussian of ``lowpass_px`` px when ``lowpass_px > 0`` (suppresses voxel
        staircase / moiré patterns that the high-pass would otherwise amplify into view-dependent features).
        Pixels with ``p <= background_frac · max(p)`` (rays through air, when ``background_frac > 0``) are set
        to 0 after the enhancement and excluded from the window: CLAHE would turn their flat noise into
        features fixed in image space, which pull every camera towards "not moving".
    """
    from scipy.ndimage import gaussian_filter
    from skimage.exposure import equalize_adapthist

    arr = np.asarray(images, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or not np.all(np.isfinite(arr)):
        raise CtsplatError("enhance_for_features: expected finite images of shape (V, H, W)")
    out = np.empty(arr.shape, np.uint8)
    ks = max(8, int(round(kernel_frac * max(arr.shape[1:]))))
    for i, im in enumerate(arr):
        fg = im > background_frac * im.max() if background_frac > 0 else np.ones(im.shape, bool)
        if lowpass_px > 0:
            im = gaussian_filter(im, lowpass_px, mode="nearest")
        if highpass_frac > 0:
            im = im - gaussian_filter(im, highpass_frac * max(arr.shape[1:]), mode="nearest")
        lo, hi = np.percentile(im[fg], [p_low, p_high]) if fg.any() else (0.0, 0.0)
        x = np.clip((im - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(im)
        if hi > lo:
            x = equalize_adapthist(x, kernel_size=ks, clip_limit=clip)
        out[i] = np.where(fg, np.round(np.clip(x, 0, 1) * 255), 0).astype(np.uint8)
    return out


def feature_masks(images: np.ndarray, background_frac: float, margin_px: float) -> np.ndarray:
    """Where SIFT features may be kept: the object's support eroded by ``margin_px`` pixels (uint8 0/255).

    The support of a view is ``p > background_frac · max(p)``. Its outer boundary (the silhouette) and the
    tangent rays just inside it give features that slide over the object's surface as the view turns; they
    are not projections of fixed 3D points and bias bundle adjustment, so they are masked out.
    Returns (V, H, W) uint8 (255 = keep); all 255 when ``margin_px <= 0``.
    """
    from scipy.ndimage import distance_transform_edt

    arr = np.asarray(images, float)
    if arr.ndim == 2:
        arr = arr[None]
    out = np.full(arr.shape, 255, np.uint8)
    if margin_px <= 0:
        return out
    for i, im in enumerate(arr):
        fg = im > background_frac * im.max()
        dist = distance_transform_edt(np.pad(fg, 1))[1:-1, 1:-1]  # distance to the nearest background pixel
        out[i] = np.where(dist > margin_px, 255, 0).astype(np.uint8)
    return out


def write_pngs(images: np.ndarray, out_dir: str | Path, prefix: str = "view") -> list[str]:
    """Write uint8 images (V, H, W) as ``{prefix}_{i:04d}.png``; return the file names (COLMAP image names)."""
    import imageio.v3 as iio

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for i, im in enumerate(images):
        name = f"{prefix}_{i:04d}.png"
        with atomic_path(out_dir / name) as tmp:
            iio.imwrite(tmp, np.asarray(im, np.uint8), extension=".png")
        names.append(name)
    return names


# ----------------------------------------------------------------------------------------------------------
# COLMAP
# ----------------------------------------------------------------------------------------------------------
def _options(cfg: dict[str, Any]):  # noqa: ANN202 - pycolmap option objects
    import pycolmap

    nt = int(cfg["num_threads"])
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = nt
    ext.use_gpu = False
    ext.sift.max_num_features = int(cfg["max_num_features"])
    ext.sift.peak_threshold = float(cfg["peak_threshold"])
    ext.sift.edge_threshold = float(cfg["edge_threshold"])
    ext.sift.upright = bool(cfg["upright"])
    ext.sift.first_octave = int(cfg["sift_first_octave"])
    ext.sift.num_octaves = int(cfg["sift_num_octaves"])
    ext.sift.domain_size_pooling = bool(cfg["sift_domain_size_pooling"])
    mat = pycolmap.FeatureMatchingOptions()
    mat.num_threads = nt
    mat.use_gpu = False
    mat.sift.max_ratio = float(cfg["max_ratio"])
    mat.sift.max_distance = float(cfg["max_distance"])
    ver = pycolmap.TwoViewGeometryOptions()
    ver.min_num_inliers = int(cfg["min_num_inliers"])
    ver.ransac.max_error = float(cfg["max_error_px"])
    ver.ransac.random_seed = int(cfg.get("_seed", 0))
    ver.detect_watermark = False  # radiographs are centred objects; "watermark" filtering rejects them
    return ext, mat, ver


def _incremental_options(cfg: dict[str, Any]):  # noqa: ANN202
    import pycolmap

    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = int(cfg["num_threads"])
    o.random_seed = int(cfg.get("_seed", 0))
    o.min_num_matches = int(cfg["min_num_inliers"])
    o.min_model_size = int(cfg["min_model_size"])
    o.multiple_models = True
    o.ba_refine_focal_length = False  # known intrinsics from the detector geometry
    o.ba_refine_principal_point = False
    o.ba_refine_extra_params = False
    o.extract_colors = False
    m = o.mapper
    m.init_min_num_inliers = int(cfg["init_min_num_inliers"])
    m.init_min_tri_angle = float(cfg["init_min_tri_angle_deg"])
    m.abs_pose_min_num_inliers = int(cfg["abs_pose_min_num_inliers"])
    m.abs_pose_min_inlier_ratio = float(cfg["abs_pose_min_inlier_ratio"])
    m.abs_pose_refine_focal_length = False
    m.abs_pose_refine_extra_params = False
    m.filter_min_tri_angle = float(cfg["filter_min_tri_angle_deg"])
    m.random_seed = int(cfg.get("_seed", 0))
    m.num_threads = int(cfg["num_threads"])
    o.triangulation.min_angle = float(cfg["triangulation_min_angle_deg"])
    o.triangulation.random_seed = int(cfg.get("_seed", 0))
    return o


def _global_options(cfg: dict[str, Any]):  # noqa: ANN202
    import pycolmap

    o = pycolmap.GlobalPipelineOptions()
    o.num_threads = int(cfg["num_threads"])
    o.random_seed = int(cfg.get("_seed", 0))
    o.min_num_matches = int(cfg["min_num_inliers"])
    o.min_model_size = int(cfg["min_model_size"])
    m = o.mapper
    m.num_threads = int(cfg["num_threads"])
    m.random_seed = int(cfg.get("_seed", 0))
    m.bundle_adjustment.refine_focal_length = False
    m.bundle_adjustment.refine_principal_point = False
    m.bundle_adjustment.refine_extra_params = False
    m.bundle_adjustment.ceres.use_gpu = False
    m.global_positioning.use_gpu = False
    m.min_tri_angle_deg = float(cfg["triangulation_min_angle_deg"])
    return o


def colmap_reconstruct(image_dir: str | Path, image_names: list[str], intrinsics: tuple[float, float, float, float],
                       work_dir: str | Path, config: dict[str, Any], prior_centres: np.ndarray | None = None,
                       prior_poses: tuple[np.ndarray, np.ndarray] | None = None, mask_dir: str | Path | None = None
                       ) -> tuple[dict[int, Any], dict[str, Any]]:
    """Run pycolmap on ``image_names`` (all one PINHOLE camera with fixed ``(fx, fy, cx, cy)`` in px).

    ``prior_centres`` (V, 3) mm, in the order of ``image_names``: camera-centre priors (the designed orbit)
    written to the database as Cartesian pose priors with covariance ``prior_sigma_mm² I``; the incremental
    mapper then uses them (``use_prior_position``, robust loss) and returns models in the prior frame.
    ``prior_poses`` ``(Rs (V,3,3), ts (V,3))``: designed poses; instead of a mapper, the verified matches are
    triangulated from them and all poses and points are bundle-adjusted (:func:`_refine_from_design`).

    Returns ``(models, stats)``: pycolmap reconstructions keyed by model index and statistics
    (features per image, verified pairs, seconds per stage).
    """
    import pycolmap

    cfg = config
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db_path = work_dir / "database.db"
    if db_path.exists():
        db_path.unlink()
    with contextlib.suppress(Exception):
        pycolmap.set_random_seed(int(cfg.get("_seed", 0)))
        pycolmap.logging.minloglevel = 1 if log.isEnabledFor(logging.DEBUG) else 2  # glog: 1 WARNING, 2 ERROR
    ext, mat, ver = _options(cfg)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in intrinsics)
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)  # <mask_dir>/<image name>.png; features on 0 pixels are dropped
    stats: dict[str, Any] = {}
    t0 = time.perf_counter()
    pycolmap.extract_features(db_path, image_dir, image_names=list(image_names),
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=ext, device=pycolmap.Device.cpu)
    if prior_centres is not None and cfg.get("pose_prior") == "position":
        _write_pose_priors(db_path, image_names, np.asarray(prior_centres, float), float(cfg["prior_sigma_mm"]))
    t1 = time.perf_counter()
    matching = cfg["matching"]
    if matching == "exhaustive":
        pycolmap.match_exhaustive(db_path, matching_options=mat, verification_options=ver, device=pycolmap.Device.cpu)
    elif matching == "sequential":
        pair = pycolmap.SequentialPairingOptions()
        pair.overlap = int(cfg["sequential_overlap"])
        pair.quadratic_overlap = False
        pair.num_threads = int(cfg["num_threads"])
        pycolmap.match_sequential(db_path, matching_options=mat, pairing_options=pair, verification_options=ver,
                                  device=pycolmap.Device.cpu)
        if float(cfg.get("arc_deg", 360.0)) >= 360.0:
            _match_loop_closure(db_path, image_names, int(cfg["sequential_overlap"]), mat, ver)
    else:
        raise CtsplatError(f"unknown sfm.matching {matching!r}; allowed: exhaustive, sequential")
    t2 = time.perf_counter()
    models, map_stats = colmap_map(db_path, image_dir, work_dir, image_names, cfg, prior_centres=prior_centres,
                                   prior_poses=prior_poses)
    stats.update(map_stats, seconds_features=t1 - t0, seconds_matching=t2 - t1)
    return models, stats


def colmap_map(db_path: str | Path, image_dir: str | Path, work_dir: str | Path, image_names: list[str],
               config: dict[str, Any], prior_centres: np.ndarray | None = None,
               prior_poses: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[dict[int, Any], dict[str, Any]]:
    """The mapping stage of :func:`colmap_reconstruct` on a database that already holds verified matches.

    Separate so that exact (synthetic) correspondences can be fed through the very same mapping path.
    Returns ``(models, stats)`` (verified pairs, median features per image, mapping seconds).
    """
    import pycolmap

    cfg = config
    db_path, work_dir = Path(db_path), Path(work_dir)
    stats: dict[str, Any] = {}
    t2 = time.perf_counter()
    db = pycolmap.Database.open(str(db_path))
    try:
        n_kp = [db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()]
        stats["verified_pairs"] = int(db.num_verified_image_pairs())
        stats["matched_pairs"] = int(db.num_matched_image_pairs())
    finally:
        db.close()
    stats["features_median"] = float(np.median(n_kp)) if n_kp else 0.0
    out = work_dir / "models"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    mapper = cfg["mapper"]
    if prior_poses is not None:
        rec, refine_stats = _refine_from_design(db_path, Path(image_dir), out, image_names, prior_poses, cfg)
        models = {0: rec}
        stats.update(refine_stats)
    elif mapper == "incremental":
        opts = _incremental_options(cfg)
        if prior_centres is not None and cfg.get("pose_prior") == "position":
            opts.use_prior_position = True
            opts.use_robust_loss_on_prior_position = True
        models = pycolmap.incremental_mapping(db_path, image_dir, out, options=opts)
    elif mapper == "global":
        models = pycolmap.global_mapping(db_path, image_dir, out, options=_global_options(cfg))
    else:
        raise CtsplatError(f"unknown sfm.mapper {mapper!r}; allowed: incremental, global")
    stats["seconds_mapping"] = time.perf_counter() - t2
    return dict(models), stats


def _refine_from_design(db_path: Path, image_dir: Path, out: Path, image_names: list[str],
                        poses: tuple[np.ndarray, np.ndarray], cfg: dict[str, Any]) -> Any:
    """Triangulate from the designed poses, then alternate free-pose bundle adjustment and re-triangulation.

    Bundle adjustment minimises the robust (Cauchy, 1 px) reprojection error over all poses and points with
    the intrinsics fixed; the 7-DoF gauge is left to the damped solver and removed later by the Sim(3)
    alignment. ``refine_rounds`` rounds of (triangulate with ``clear_points``, BA).
    """
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        cams = db.read_all_cameras()
        images = db.read_all_images()
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cams[0])
    index = {n: i for i, n in enumerate(image_names)}
    Rs, ts = poses
    for im in images:
        i = index[im.name]
        img = pycolmap.Image(name=im.name, camera_id=cams[0].camera_id, image_id=im.image_id)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(np.hstack([Rs[i], ts[i][:, None]])))
    centres = None
    if cfg.get("pose_prior") in ("refine_prior", "isocentric"):
        centres = {n: -Rs[i].T @ ts[i] for n, i in index.items()}
    rec = _retriangulate_and_adjust(rec, db_path, image_dir, out, cfg, prior_centres=centres)
    stats: dict[str, Any] = {}
    if cfg.get("pose_prior") == "isocentric" and rec.num_points3D() > 0:
        stats["isocentric"] = _isocentric_adjust(rec, {n: (Rs[i], ts[i]) for n, i in index.items()}, cfg)
    return rec, stats


def _isocentric_adjust(rec: Any, design: dict[str, tuple[np.ndarray, np.ndarray]], cfg: dict[str, Any]
                       ) -> dict[str, Any]:
    """Isocentric bundle adjustment (:mod:`ctsplat.bundle`) of a model's registered views and points, in place.

    The isocentre and DSO come from the designed poses (``design``: image name -> (R, t)); the rotations start
    from the model's, every view keeps the prior ``N(0, design_sigma_deg²)`` on its deviation from the design.
    Returns what was done (views, points, observations, iterations, reprojection error, offsets).
    """
    import pycolmap

    from ctsplat.bundle import isocentre_from_poses, isocentric_bundle_adjustment

    names = sorted(design)
    iso, dso = isocentre_from_poses(np.stack([design[n][0] for n in names]), np.stack([design[n][1] for n in names]))
    images = [im for im in rec.images.values() if im.has_pose and im.name in design]
    view_of = {im.image_id: k for k, im in enumerate(images)}
    pids, obs_v, obs_p, obs_xy = [], [], [], []
    for pid, pt in rec.points3D.items():
        els = [e for e in pt.track.elements if e.image_id in view_of]
        if len(els) < 2:
            continue
        for e in els:
            obs_v.append(view_of[e.image_id])
            obs_p.append(len(pids))
            obs_xy.append(rec.images[e.image_id].points2D[e.point2D_idx].xy)
        pids.append(pid)
    if not pids:
        return {"views": len(images), "points": 0}
    cam = rec.cameras[images[0].camera_id]
    fx, fy, cx, cy = (float(v) for v in cam.params[:4])
    sigma = cfg["design_sigma_deg"]
    res = isocentric_bundle_adjustment(
        np.stack([im.cam_from_world().rotation.matrix() for im in images]),
        np.stack([rec.points3D[p].xyz for p in pids]), np.array(obs_v), np.array(obs_p), np.array(obs_xy),
        (fx, fy, cx, cy), iso, dso, design_Rs=np.stack([design[im.name][0] for im in images]),
        design_sigma_deg=None if sigma is None else float(sigma),
        isocentre_sigma_mm=float(cfg["isocentre_sigma_mm"]), loss_scale_px=float(cfg["isocentric_loss_px"]))
    for k, im in enumerate(images):
        rec.frames[im.frame_id].rig_from_world = pycolmap.Rigid3d(np.hstack([res.Rs[k], res.ts[k][:, None]]))
    for j, pid in enumerate(pids):
        rec.points3D[pid].xyz = res.points[j]
    return {"views": len(images), "points": len(pids), "observations": len(obs_v), "iterations": res.iterations,
            "reproj_err_px_median": res.reproj_err_px_median, "isocentre_mm": iso.tolist(), "dso_mm": dso,
            "offset_mm_rms": float(np.sqrt((res.offsets_mm**2).sum(1).mean()))}


def _prior_bundle_adjustment(rec: Any, centres: dict[str, np.ndarray], sigma_mm: float, ba: Any) -> None:
    """Bundle adjustment with Gaussian priors ``N(c_design, sigma² I)`` on the camera centres (world mm), in place.

    Reprojection residuals (robust loss of ``ba``) plus ``|c_i - c_design_i|² / sigma²`` per image
    (pycolmap's pose-prior bundle adjuster); the reconstruction stays in the world frame of the priors.
    """
    import pycolmap

    conf = pycolmap.BundleAdjustmentConfig()
    priors = []
    for im in rec.images.values():
        if im.has_pose and im.name in centres:
            conf.add_image(im.image_id)
            priors.append(pycolmap.PosePrior(position=np.asarray(centres[im.name], float),
                                             position_covariance=np.eye(3) * sigma_mm**2,
                                             coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
                                             corr_data_id=im.data_id))
    po = pycolmap.PosePriorBundleAdjustmentOptions()
    po.prior_position_fallback_stddev = sigma_mm
    pycolmap.create_pose_prior_bundle_adjuster(ba, po, conf, priors, rec).solve()


def _retriangulate_and_adjust(rec: Any, db_path: Path, image_dir: Path, out: Path, cfg: dict[str, Any],
                              prior_centres: dict[str, np.ndarray] | None = None) -> Any:
    """``refine_rounds`` rounds of (re-triangulate all verified matches from the current poses, BA).

    BA is free (gauge left to the damped solver) or, with ``prior_centres`` (image name -> designed camera
    centre, world mm), pose-prior BA (:func:`_prior_bundle_adjustment`) that keeps the world frame.
    """
    import pycolmap

    Path(out).mkdir(parents=True, exist_ok=True)
    opts = _incremental_options(cfg)
    ba = _ba_options(cfg)
    for _ in range(max(1, int(cfg["refine_rounds"]))):
        rec = pycolmap.triangulate_points(rec, db_path, image_dir, out, clear_points=True, options=opts)
        if rec.num_points3D() == 0:
            break
        if prior_centres is None:
            pycolmap.bundle_adjustment(rec, ba)
        else:
            _prior_bundle_adjustment(rec, prior_centres, float(cfg["prior_sigma_mm"]), ba)
    for img in list(rec.images.values()):  # views that observe no point are not registered
        if img.has_pose and img.num_points3D == 0:
            rec.deregister_frame(img.frame_id)
    return rec


def _ba_options(cfg: dict[str, Any]):  # noqa: ANN202
    import pycolmap

    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = False
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = 1.0
    ba.ceres.solver_options.num_threads = int(cfg["num_threads"])
    ba.ceres.solver_options.max_num_iterations = 100
    return ba


def reverse_depth(rec: Any) -> Any:
    """The Necker-reversed twin of a reconstruction (in place), bundle-adjusted afterwards by the caller.

    Transmission images have no occlusion, so under weak perspective a scene and its depth-reversed mirror
    image explain the same feature positions: with the reflection ``M = diag(1, 1, -1)`` (world) and
    ``D = diag(1, 1, -1)`` (camera), ``R' = D R M`` and ``X' = M X`` give ``(R' X')_{xy} = (R X)_{xy}``.
    Each camera keeps its distance ``d`` to the points' centroid ``O``: ``c' = M O - d · z'`` (``z'`` the
    third row of ``R'``). Returns ``rec``.
    """
    import pycolmap

    M = np.diag([1.0, 1.0, -1.0])
    xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    O = xyz.mean(0) if len(xyz) else np.zeros(3)
    for frame in rec.frames.values():
        if not frame.has_pose:
            continue
        m = frame.rig_from_world.matrix()
        R, t = m[:, :3], m[:, 3]
        c = -R.T @ t
        R2 = M @ R @ M  # D = M numerically
        c2 = M @ O - np.linalg.norm(c - O) * R2[2]
        frame.rig_from_world = pycolmap.Rigid3d(np.hstack([R2, (-R2 @ c2)[:, None]]))
    for p in rec.points3D.values():
        p.xyz = M @ p.xyz
    return rec


def _design_score(rec: Any, design: dict[str, tuple[np.ndarray, np.ndarray]], threshold: float) -> float:
    """Median rotation error (deg) of a model's cameras against the designed poses after Sim(3) alignment."""
    poses = _model_poses(rec)
    names = [n for n in poses if n in design]
    if len(names) < 3:
        return float("inf")
    rows, align = evaluate_poses(poses, names, np.stack([design[n][0] for n in names]),
                                 np.stack([design[n][1] for n in names]), threshold_mm=threshold, iterations=200)
    errs = [r["rot_err_deg"] for r in rows if np.isfinite(r["rot_err_deg"])]
    return float(np.median(errs)) if errs else float("inf")


def fix_reversal(models: dict[int, Any], design: dict[str, tuple[np.ndarray, np.ndarray]], cfg: dict[str, Any],
                 threshold: float, work: tuple[Path, Path, Path] | None = None) -> list[dict[str, Any]]:
    """For each model, keep it or its bundle-adjusted depth-reversed twin, whichever fits the design better.

    The designed orbit only arbitrates between the two discrete SfM solutions (median rotation error after
    Sim(3) alignment); poses are not pulled towards it. Returns one report entry per model.
    """
    import pycolmap

    report = []
    for k, rec in list(models.items()):
        if rec.num_reg_images() < 3:
            continue
        before = _design_score(rec, design, threshold)
        twin = pycolmap.Reconstruction(rec)
        reverse_depth(twin)
        pycolmap.bundle_adjustment(twin, _ba_options(cfg))
        if work is not None:  # (database, images, scratch dir): re-triangulate the matches in the twin's frame
            twin = _retriangulate_and_adjust(twin, *work, cfg)
        after = _design_score(twin, design, threshold)
        flipped = after < before
        if flipped:
            models[k] = twin
        report.append({"model": int(k), "images": int(rec.num_reg_images()), "design_rot_err_deg": before,
                       "reversed_design_rot_err_deg": after, "reversed": bool(flipped)})
    return report


def _write_pose_priors(db_path: Path, image_names: list[str], centres: np.ndarray, sigma_mm: float) -> None:
    """Store Cartesian position priors (mm) with isotropic covariance ``σ² I`` for the named images."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        by_name = {im.name: im for im in db.read_all_images()}
        for name, c in zip(image_names, centres, strict=True):
            prior = pycolmap.PosePrior(position=np.asarray(c, float), position_covariance=np.eye(3) * sigma_mm**2,
                                       coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
                                       corr_data_id=by_name[name].data_id)
            db.write_pose_prior(prior)
    finally:
        db.close()


def _match_loop_closure(db_path: Path, image_names: list[str], overlap: int, mat: Any, ver: Any) -> None:
    """Close a 360° orbit: match the last ``overlap`` images with the first ``overlap`` (cyclic neighbours)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
    finally:
        db.close()
    n = len(image_names)
    pairs = []
    for i in range(n):
        for d in range(1, overlap + 1):
            j = i + d
            if j >= n:
                pairs.append((image_names[i], image_names[j - n]))
    pairs = [(a, b) for a, b in pairs if a != b and a in ids and b in ids]
    if not pairs:
        return
    with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as fh:
        fh.write("\n".join(f"{a} {b}" for a, b in pairs) + "\n")
        pair_file = fh.name
    try:
        popt = pycolmap.ImportedPairingOptions()
        popt.match_list_path = pair_file
        pycolmap.match_image_pairs(db_path, matching_options=mat, pairing_options=popt, verification_options=ver,
                                   device=pycolmap.Device.cpu)
    finally:
        Path(pair_file).unlink(missing_ok=True)


def _model_poses(rec: Any) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Image name -> (R (3,3), t (3,)) world->camera of the registered images of a pycolmap model."""
    out = {}
    for img in rec.images.values():
        if not img.has_pose:
            continue
        m = img.cam_from_world().matrix()
        out[img.name] = (np.asarray(m[:, :3], float), np.asarray(m[:, 3], float))
    return out


def merge_models(models: dict[int, Any], min_shared: int = 3) -> tuple[Any, dict[str, tuple[np.ndarray, np.ndarray]],
                                                                        dict[str, Any]]:
    """Keep the largest model and merge into its frame every other model sharing ``>= min_shared`` images.

    The smaller model is mapped into the largest one's frame with the Sim(3) (Umeyama) aligning the centres
    of the shared images; its extra images' poses are added (``R' = R S_R^T``, ``c' = s S_R c + S_t``).
    Returns ``(largest pycolmap model, merged poses {name: (R, t)}, report)``; the COLMAP model itself
    stays the largest one (points of merged models are not transferred).
    """
    if not models:
        return None, {}, {"models_found": 0, "model_sizes": [], "merged": []}
    order = sorted(models, key=lambda k: -models[k].num_reg_images())
    main = models[order[0]]
    poses = _model_poses(main)
    sizes = [int(models[k].num_reg_images()) for k in order]
    merged = []
    changed = True
    remaining = order[1:]
    while changed and remaining:
        changed = False
        for k in list(remaining):
            other = _model_poses(models[k])
            shared = sorted(set(other) & set(poses))
            if len(shared) < min_shared:
                continue
            src = np.stack([-other[n][0].T @ other[n][1] for n in shared])
            dst = np.stack([-poses[n][0].T @ poses[n][1] for n in shared])
            s, Rg, tg = umeyama(src, dst, with_scale=True)
            resid = np.linalg.norm((s * src @ Rg.T + tg) - dst, axis=1)
            spread = np.linalg.norm(dst - dst.mean(0), axis=1).mean()
            if len(shared) >= 3 and np.median(resid) > 0.05 * max(spread, 1e-9):
                continue  # inconsistent overlap: do not merge
            added = 0
            for n, (R, t) in other.items():
                if n in poses:
                    continue
                c = -R.T @ t
                c2 = s * Rg @ c + tg
                R2 = R @ Rg.T
                poses[n] = (R2, -R2 @ c2)
                added += 1
            merged.append({"model_size": int(models[k].num_reg_images()), "shared": len(shared), "added": added})
            remaining.remove(k)
            changed = True
    report = {"models_found": len(models), "model_sizes": sizes, "merged": merged}
    return main, poses, report


def _set_poses_and_triangulate(rec: Any, poses: dict[str, tuple[np.ndarray, np.ndarray]], db_path: Path,
                               image_dir: Path, out: Path, cfg: dict[str, Any]) -> Any:
    """Set the model's registered images to ``poses`` (world->camera) and re-triangulate all points from them."""
    import pycolmap

    for img in rec.images.values():
        if img.has_pose and img.name in poses:
            R, t = poses[img.name]
            rec.frames[img.frame_id].rig_from_world = pycolmap.Rigid3d(np.hstack([R, np.asarray(t)[:, None]]))
    Path(out).mkdir(parents=True, exist_ok=True)
    return pycolmap.triangulate_points(rec, db_path, image_dir, out, clear_points=True,
                                       options=_incremental_options(cfg))


def orbit_basis(azimuth_deg: np.ndarray, harmonics: int, full_circle: bool) -> np.ndarray:
    """Smooth functions along the orbit, (V, 2 K + 1): Fourier ``1, cos kφ, sin kφ`` (k <= K) on a full circle,
    else the cosine series ``cos(k π x)`` (k <= 2K) of the normalised arc position ``x in [0, 1]``."""
    a = np.asarray(azimuth_deg, float)
    if full_circle:
        phi = np.deg2rad(a)
        cols = [np.ones_like(phi)]
        for k in range(1, harmonics + 1):
            cols += [np.cos(k * phi), np.sin(k * phi)]
        return np.stack(cols, 1)
    x = (a - a.min()) / max(float(np.ptp(a)), 1e-12)
    return np.stack([np.cos(k * np.pi * x) for k in range(2 * harmonics + 1)], 1)


def fuse_with_design(poses: dict[str, tuple[np.ndarray, np.ndarray]], names: list[str], design_Rs: np.ndarray,
                     design_ts: np.ndarray, azimuth_deg: np.ndarray, harmonics: int, full_circle: bool = True
                     ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Low frequencies along the orbit from the design, high frequencies from SfM.

    SfM on radiographs of extended anatomy recovers the *view-to-view* pose changes well but bends the orbit
    as a whole (a smooth, systematic deformation: features of overlapping structures are not fixed 3D points).
    The gantry's designed orbit is the opposite: right on average, off by independent per-view errors.
    With the SfM poses mapped to the design frame (Umeyama Sim(3) on the centres) and, per view ``i``, the
    deviation from the design ``ω_i = log(R_i R_design_iᵀ)`` (world rotation vector) and
    ``δ_i = c_i - c_design_i``, the fused pose keeps only the part of ``(ω, δ)`` orthogonal to the smooth basis
    ``B`` (:func:`orbit_basis`, ``2 K + 1`` functions of the designed azimuth): ``ω' = ω - B B⁺ ω``,
    ``R' = exp(ω') R_design``, ``c' = c_design + δ - B B⁺ δ``. The global Sim(3) and any smooth bend
    are thereby taken from the design; what is left of the design's own per-view error is its projection on
    ``B``, about ``sqrt((2K+1) / V)`` of it. Returns the fused poses (world->camera) in the design frame.
    """
    from scipy.spatial.transform import Rotation

    idx = [i for i, n in enumerate(names) if n in poses]
    if len(idx) < max(3, 2 * harmonics + 2):
        return dict(poses)
    cs = np.stack([-poses[names[i]][0].T @ poses[names[i]][1] for i in idx])
    dc = np.einsum("vji,vj->vi", design_Rs[idx], -np.asarray(design_ts, float)[idx])
    s, Rg, tg = umeyama(cs, dc)
    om = np.stack([Rotation.from_matrix(poses[names[i]][0] @ Rg.T @ design_Rs[i].T).as_rotvec() for i in idx])
    dl = s * cs @ Rg.T + tg - dc
    B = orbit_basis(np.asarray(azimuth_deg, float)[idx], harmonics, full_circle)
    om = om - B @ np.linalg.lstsq(B, om, rcond=None)[0]
    dl = dl - B @ np.linalg.lstsq(B, dl, rcond=None)[0]
    out = {}
    for k, i in enumerate(idx):
        R = Rotation.from_rotvec(om[k]).as_matrix() @ design_Rs[i]
        out[names[i]] = (R, -R @ (dc[k] + dl[k]))
    return out


# ----------------------------------------------------------------------------------------------------------
# Alignment and metrics
# ----------------------------------------------------------------------------------------------------------
def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991).

    With centred ``X = src - μ_s``, ``Y = dst - μ_d`` and ``Σ = Yᵀ X / n = U D Vᵀ``:
    ``R = U S Vᵀ`` (``S = diag(1, 1, det(U Vᵀ))``), ``s = tr(D S) / σ_s²`` (``σ_s² = |X|² / n``),
    ``t = μ_d - s R μ_s``.

    Parameters
    ----------
    src, dst : ndarray (N, 3), N >= 3 (not all collinear)

    Returns
    -------
    s : float, R : ndarray (3, 3), t : ndarray (3,)
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[0] < 3:
        raise CtsplatError(f"umeyama needs matching (N>=3, 3) point sets, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    X, Y = src - mu_s, dst - mu_d
    sigma = Y.T @ X / len(src)
    U, D, Vt = np.linalg.svd(sigma)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (X**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def robust_sim3(src: np.ndarray, dst: np.ndarray, threshold: float, *, iterations: int = 500,
                seed: int = 0) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """RANSAC Sim(3) (minimal 3-point Umeyama samples), refit on the largest inlier set.

    Inliers: ``|s R src_i + t - dst_i| <= threshold`` (units of ``dst``). Deterministic for a ``seed``.
    Returns ``(s, R, t, inlier mask (N,))``. With fewer than 3 points raises ``CtsplatError``.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    n = len(src)
    if n < 3:
        raise CtsplatError(f"robust_sim3 needs at least 3 correspondences, got {n}")
    rng = np.random.default_rng(seed)
    best = np.zeros(n, bool)
    best_err = np.inf
    for _ in range(iterations if n > 3 else 1):
        idx = rng.choice(n, 3, replace=False) if n > 3 else np.arange(3)
        a = src[idx]
        if np.linalg.norm(np.cross(a[1] - a[0], a[2] - a[0])) < 1e-12:
            continue
        s, R, t = umeyama(a, dst[idx])
        err = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
        inl = err <= threshold
        score = np.minimum(err, threshold).sum()  # MSAC
        if inl.sum() > best.sum() or (inl.sum() == best.sum() and score < best_err):
            best, best_err = inl, score
    if best.sum() < 3:
        best = np.ones(n, bool)
    for _ in range(3):  # refit and re-select
        s, R, t = umeyama(src[best], dst[best])
        err = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
        new = err <= threshold
        if new.sum() < 3 or np.array_equal(new, best):
            break
        best = new
    s, R, t = umeyama(src[best], dst[best])
    return s, R, t, best


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Geodesic angle (degrees) between rotations: ``arccos((tr(R_aᵀ R_b) - 1) / 2)``; batched over (..., 3, 3)."""
    Ra = np.asarray(R_a, float)
    Rb = np.asarray(R_b, float)
    tr = np.einsum("...ji,...ji->...", Ra, Rb)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def evaluate_poses(poses: dict[str, tuple[np.ndarray, np.ndarray]], names: list[str], Rs_true: np.ndarray,
                   ts_true: np.ndarray, *, threshold_mm: float, iterations: int = 500, seed: int = 0
                   ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Align recovered poses to the true ones (robust Sim(3) on centres) and measure per-view errors.

    With the Sim(3) ``x_w = s R_g x_sfm + t_g``, a recovered camera ``(R, c)`` becomes
    ``R_w = R R_gᵀ``, ``c_w = s R_g c + t_g`` (world mm). Per view: rotation error
    ``∠(R_w, R_true)`` (deg), centre error ``|c_w - c_true|`` (mm).

    Returns ``(rows, alignment)``; rows have ``view, name, registered, rot_err_deg, centre_err_mm,
    R (aligned), t (aligned)`` (NaN / None when not registered); alignment has ``s, R, t, inliers``.
    """
    V = len(names)
    centres_true = np.einsum("vji,vj->vi", Rs_true, -np.asarray(ts_true, float))  # c = -Rᵀ t
    reg = [i for i, n in enumerate(names) if n in poses]
    rows: list[dict[str, Any]] = []
    align: dict[str, Any] = {"ok": False}
    if len(reg) >= 3:
        src = np.stack([-poses[names[i]][0].T @ poses[names[i]][1] for i in reg])
        dst = centres_true[reg]
        s, Rg, tg, inl = robust_sim3(src, dst, threshold_mm, iterations=iterations, seed=seed)
        align = {"ok": True, "scale": s, "R": Rg, "t": tg, "n_inliers": int(inl.sum()), "n_used": len(reg)}
    for i, n in enumerate(names):
        row: dict[str, Any] = {"view": i, "name": n, "registered": n in poses, "rot_err_deg": np.nan,
                               "centre_err_mm": np.nan, "R": None, "t": None}
        if n in poses and align["ok"]:
            R, t = poses[n]
            c = -R.T @ t
            Rw = R @ align["R"].T
            cw = align["scale"] * align["R"] @ c + align["t"]
            row.update(rot_err_deg=float(rotation_error_deg(Rw, Rs_true[i])),
                       centre_err_mm=float(np.linalg.norm(cw - centres_true[i])), R=Rw, t=-Rw @ cw)
        rows.append(row)
    assert len(rows) == V
    # residual global rotation: Δ = argmin_Δ Σ ||Δ R_true_i - R_w_i||_F (chordal mean, SVD projection onto SO(3))
    # over the alignment inliers; "rot_err_rotalign_deg" = ∠(R_w_i, Δ R_true_i). Under weak perspective the
    # camera distances (hence the centres) are poorly determined, so a centre-only Sim(3) can leave the whole
    # recovered orbit tilted by a few degrees; this second number separates that tilt from per-view noise.
    for r in rows:
        r["rot_err_rotalign_deg"] = np.nan
    if align["ok"]:
        idx = [r["view"] for r in rows if r["R"] is not None]
        M = sum(rows[i]["R"] @ Rs_true[i].T for i in idx)
        U, _, Vt = np.linalg.svd(M)
        D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
        delta = U @ D @ Vt
        align["residual_rotation_deg"] = float(rotation_error_deg(delta, np.eye(3)))
        for i in idx:
            rows[i]["rot_err_rotalign_deg"] = float(rotation_error_deg(rows[i]["R"], delta @ Rs_true[i]))
    return rows, align


def summarize(rows: list[dict[str, Any]], report: dict[str, Any], cfg: dict[str, Any]) -> dict[str, Any]:
    """Summary numbers: registration rates, median / p90 errors, models, and the ``ok`` verdict."""
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
    ok = (out["registration_rate"] >= cfg["min_registration_rate"] and out["rot_err_deg_median"] is not None
          and out["rot_err_deg_median"] <= cfg["max_median_rotation_error_deg"])
    out["ok"] = bool(ok)
    if not ok:
        out["reason"] = (f"registration rate {out['registration_rate']:.2f} (need >= {cfg['min_registration_rate']}),"
                         f" median rotation error {out['rot_err_deg_median']} deg"
                         f" (need <= {cfg['max_median_rotation_error_deg']})")
    return out


def _per_image_reproj(rec: Any) -> dict[str, float]:
    """Mean reprojection error (px) of each registered image's observations in a pycolmap model."""
    errs: dict[str, list[float]] = {}
    for p in rec.points3D.values():
        for el in p.track.elements:
            img = rec.images[el.image_id]
            uv = img.points2D[el.point2D_idx].xy
            proj = img.project_point(p.xyz)
            if proj is not None:
                errs.setdefault(img.name, []).append(float(np.linalg.norm(np.asarray(proj) - np.asarray(uv))))
    return {k: float(np.mean(v)) for k, v in errs.items()}


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray | None = None) -> None:
    """ASCII PLY of points (N, 3) mm with optional uint8 colours (N, 3), written atomically."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    lines = ["ply", "format ascii 1.0", f"element vertex {len(xyz)}", "property float x", "property float y",
             "property float z"]
    if rgb is not None:
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    lines.append("end_header")
    body = []
    for i, p in enumerate(xyz):
        s = f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}"
        if rgb is not None:
            c = np.asarray(rgb[i]).astype(int)
            s += f" {c[0]} {c[1]} {c[2]}"
        body.append(s)
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines + body) + "\n")


def _write_model(rec: Any, out_dir: Path) -> None:
    """COLMAP model as binary (``out_dir``) and text (``out_dir/text``), replaced atomically."""
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".sparse.", dir=out_dir.parent))
    try:
        rec.write_binary(str(tmp))
        (tmp / "text").mkdir()
        rec.write_text(str(tmp / "text"))
        if out_dir.exists():
            shutil.rmtree(out_dir)
        tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def run_sfm_on_images(images_u8: np.ndarray, intrinsics: tuple[float, float, float, float], Rs_true: np.ndarray,
                      ts_true: np.ndarray, out_dir: str | Path, config: dict[str, Any], *, seed: int = 0,
                      prefix: str = "view", scale_mm: float = 1.0, prior_centres: np.ndarray | None = None,
                      prior_poses: tuple[np.ndarray, np.ndarray] | None = None, masks: np.ndarray | None = None,
                      design: tuple[np.ndarray, np.ndarray] | None = None,
                      design_azimuth_deg: np.ndarray | None = None
                      ) -> tuple[dict[str, Any], list[dict[str, Any]], Any]:
    """COLMAP + merging + alignment on given 8-bit images with known true poses; no files beside the work dir.

    With ``fuse_harmonics > 0`` (and ``design`` + ``design_azimuth_deg``), the poses are fused with the design
    (:func:`fuse_with_design`); the summary then also holds the unfused numbers under ``"unfused"``.

    Returns ``(summary, rows, model_or_None)``; rows are per view (see :func:`evaluate_poses`) plus
    ``reproj_err_px``; the summary also holds COLMAP stage statistics. Never raises on too few registrations.
    """
    cfg = dict(config)
    cfg["_seed"] = seed
    out_dir = Path(out_dir)
    img_dir = out_dir / "images"
    names = write_pngs(images_u8, img_dir, prefix=prefix)
    mask_dir = None
    if masks is not None:
        mask_dir = out_dir / "masks"
        for name, m in zip(names, write_pngs(masks, mask_dir, prefix=prefix), strict=True):
            (mask_dir / m).rename(mask_dir / f"{name}.png")
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
    if int(cfg["fuse_harmonics"]) > 0 and design is not None and design_azimuth_deg is not None and poses:
        rows0, _ = evaluate_poses(poses, names, Rs_true, ts_true, threshold_mm=thr,
                                  iterations=int(cfg["align_iterations"]), seed=seed)
        s0 = summarize(rows0, report, cfg)
        unfused = {k: s0[k] for k in ("rot_err_deg_median", "rot_err_deg_p90", "rot_err_rotalign_deg_median",
                                      "centre_err_mm_median", "registration_rate")}
        poses = fuse_with_design(poses, names, design[0], design[1], design_azimuth_deg, int(cfg["fuse_harmonics"]),
                                 full_circle=float(cfg.get("arc_deg", 360.0)) >= 360.0)
        if main is not None:  # the written model carries the fused poses, its points re-triangulated from them
            main = _set_poses_and_triangulate(main, poses, out_dir / "colmap" / "database.db", img_dir,
                                              out_dir / "colmap" / "fused", cfg)
    rows, align = evaluate_poses(poses, names, Rs_true, ts_true, threshold_mm=thr,
                                 iterations=int(cfg["align_iterations"]), seed=seed)
    reproj = _per_image_reproj(main) if main is not None else {}
    for r in rows:
        r["reproj_err_px"] = reproj.get(r["name"], np.nan)
        r["in_main_model"] = r["name"] in reproj or (main is not None and main.find_image_with_name(r["name"])
                                                       is not None and r["registered"] and r["name"] in
                                                       _model_poses(main))
    summary = summarize(rows, report, cfg)
    summary["colmap"] = stats
    summary["reversal"] = reversal
    if unfused is not None:
        summary["unfused"] = unfused
    if design is not None:  # the designed orbit itself as the answer (no images): what a prior alone gives
        drows, _ = evaluate_poses({n: (design[0][i], design[1][i]) for i, n in enumerate(names)}, names, Rs_true,
                                  ts_true, threshold_mm=thr, iterations=int(cfg["align_iterations"]), seed=seed)
        summary["design_rot_err_deg_median"] = float(np.median([r["rot_err_deg"] for r in drows]))
    summary["alignment"] = {k: v for k, v in align.items()
                            if k in ("ok", "scale", "n_inliers", "n_used", "residual_rotation_deg")}
    return summary, rows, (main, align)


# ----------------------------------------------------------------------------------------------------------
# Step function
# ----------------------------------------------------------------------------------------------------------
def support_radius_mm(data: np.ndarray, affine: np.ndarray, centre_mm: np.ndarray, rel_threshold: float = 0.2
                      ) -> float:
    """Radius (mm) around ``centre_mm`` of the sphere holding every voxel above ``rel_threshold · max``.

    Used to size the detector to the object rather than to the (mostly empty) volume box. Falls back to
    the half-diagonal of the box for an empty volume.
    """
    data = np.asarray(data)
    vmax = float(data.max()) if data.size else 0.0
    ijk = np.argwhere(data > rel_threshold * vmax) if vmax > 0 else np.empty((0, 3))
    if len(ijk) == 0:
        ext = np.asarray(data.shape, float) * np.linalg.norm(np.asarray(affine)[:3, :3], axis=0)
        return 0.5 * float(np.linalg.norm(ext))
    xyz = ijk @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3]
    vox = float(np.linalg.norm(np.linalg.norm(np.asarray(affine)[:3, :3], axis=0)))  # voxel diagonal
    return float(np.linalg.norm(xyz - np.asarray(centre_mm), axis=1).max()) + vox


def _pitch_mm(cfg: dict[str, Any], radius_mm: float) -> float:
    """Detector pitch so that the object's bounding sphere (radius r) fits the detector with ``fov_margin``.

    The sphere's cone half-angle is ``asin(r / DSO)``; on the detector it spans ``DSD · tan(asin(r/DSO))``.
    """
    if cfg["pitch_mm"] is not None:
        return float(cfg["pitch_mm"])
    half = cfg["dsd_mm"] * math.tan(math.asin(min(radius_mm / cfg["dso_mm"], 0.99)))
    return 2.0 * half * float(cfg["fov_margin"]) / int(cfg["detector_px"])


def run_sfm(volume_path: str | Path, out_dir: str | Path, config: dict[str, Any] | None = None, seed: int = 0
            ) -> dict[str, Any]:
    """Render the SfM cone-beam view set, run COLMAP, align, and write the results into ``out_dir``.

    Writes ``sparse/0/`` (binary COLMAP model + ``text/``), ``poses.csv``, ``summary.json``,
    ``points3d.ply`` (aligned, world mm), ``aligned_views.json`` (registered views, B's ViewSet format),
    ``true_views.json`` (the true poses of all views, same ids) and ``images/`` (the 8-bit PNGs).
    Too few registrations do not raise: ``summary["ok"]`` is False.
    Returns the summary dict.
    """
    import pandas as pd
    import torch

    from ctsplat.formats.volume import load_volume
    from ctsplat.geometry import VIEWSET_FORMAT, VIEWSET_FORMAT_VERSION, ConeCamera, View, ViewSet
    from ctsplat.projector import line_integrals

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
    if cfg["dsd_mm"] <= cfg["dso_mm"]:
        raise CtsplatError(f"sfm.dsd_mm ({cfg['dsd_mm']}) must exceed sfm.dso_mm ({cfg['dso_mm']})")
    vol = load_volume(volume_path)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    iso = vol.center_mm()
    radius = support_radius_mm(vol.data, vol.affine, iso)
    if radius >= cfg["dso_mm"]:
        raise CtsplatError(f"sfm.dso_mm ({cfg['dso_mm']}) must exceed the volume radius ({radius:.0f} mm)")
    W = H = int(cfg["detector_px"])
    cam = ConeCamera(width=W, height=H, pitch_mm=_pitch_mm(cfg, radius), dso_mm=float(cfg["dso_mm"]),
                     dsd_mm=float(cfg["dsd_mm"]))
    orbit_args = (int(cfg["n_views"]), float(cfg["arc_deg"]), float(cfg["wobble_deg"]), float(cfg["wobble_cycles"]),
                  float(cfg["dso_mm"]), iso)
    designed = design_orbit(*orbit_args)
    orbit = design_orbit(*orbit_args, jitter_deg=float(cfg["orbit_jitter_deg"]),
                         jitter_mm=float(cfg["orbit_jitter_mm"]), seed=seed)  # the true views
    mu = torch.from_numpy(np.asarray(vol.data, np.float32) * vol.mu_scale_per_mm)
    with torch.no_grad():
        p = line_integrals(mu, np.asarray(vol.affine, float), cam, orbit["Rs"], orbit["ts"],
                           step_voxels=float(cfg["step_voxels"]))
    imgs = enhance_for_features(p.cpu().numpy(), clip=cfg["clahe_clip"], kernel_frac=cfg["clahe_kernel_frac"],
                                p_low=cfg["percentile_low"], p_high=cfg["percentile_high"],
                                highpass_frac=cfg["highpass_frac"], lowpass_px=cfg["lowpass_px"],
                                background_frac=cfg["background_frac"])
    margin = float(cfg["silhouette_margin_frac"]) * W
    masks = feature_masks(p.cpu().numpy(), float(cfg["background_frac"]) or 0.02, margin) if margin > 0 else None
    work = Path(tempfile.mkdtemp(prefix=".sfm_work.", dir=out_dir))
    try:
        summary, rows, (main, align) = run_sfm_on_images(
            imgs, (cam.fx, cam.fy, cam.cx, cam.cy), orbit["Rs"], orbit["ts"], work, cfg, seed=seed,
            scale_mm=float(cfg["dso_mm"]),
            prior_centres=designed["centres"] if cfg["pose_prior"] == "position" else None,
            prior_poses=(designed["Rs"], designed["ts"]) if cfg["pose_prior"] in REFINE_MODES else None,
            masks=masks, design=(designed["Rs"], designed["ts"]), design_azimuth_deg=designed["azimuth_deg"])
        if main is not None:
            _write_model(main, out_dir / "sparse" / "0")
            if align["ok"]:
                xyz = np.array([pt.xyz for pt in main.points3D.values()]).reshape(-1, 3)
                write_points_ply(out_dir / "points3d.ply", align["scale"] * xyz @ align["R"].T + align["t"])
        if (out_dir / "images").exists():
            shutil.rmtree(out_dir / "images")
        (work / "images").rename(out_dir / "images")
    finally:
        if cfg["keep_work"] and (work / "colmap").exists():
            shutil.rmtree(out_dir / "colmap", ignore_errors=True)
            (work / "colmap").rename(out_dir / "colmap")
        shutil.rmtree(work, ignore_errors=True)

    # physical plausibility: a view whose optical axis misses the isocentre by more than the detector's
    # half field of view atan((W/2) / fx) cannot have imaged the object; such poses are not exported
    half_fov = math.degrees(math.atan(0.5 * W / cam.fx))
    for r in rows:
        r["plausible"] = False
        if r["R"] is not None:
            c = -r["R"].T @ r["t"]
            d = (iso - c) / max(float(np.linalg.norm(iso - c)), 1e-9)
            r["plausible"] = bool(math.degrees(math.acos(float(np.clip(r["R"][2] @ d, -1, 1)))) <= half_fov)
    summary["n_plausible"] = int(sum(r["plausible"] for r in rows))
    summary["plausible_rate"] = summary["n_plausible"] / len(rows)
    table = pd.DataFrame([{
        "view": r["view"], "name": r["name"], "azimuth_deg": orbit["azimuth_deg"][r["view"]],
        "elevation_deg": orbit["elevation_deg"][r["view"]], "registered": r["registered"],
        "rot_err_deg": r["rot_err_deg"], "rot_err_rotalign_deg": r["rot_err_rotalign_deg"],
        "centre_err_mm": r["centre_err_mm"], "reproj_err_px": r["reproj_err_px"], "plausible": r["plausible"],
    } for r in rows])
    with atomic_path(out_dir / "poses.csv") as tmp:
        table.to_csv(tmp, index=False)
    views = [View(id=r["view"], R=r["R"], t=r["t"], azimuth_deg=float(orbit["azimuth_deg"][r["view"]]),
                  elevation_deg=float(orbit["elevation_deg"][r["view"]]), split="train")
             for r in rows if r["R"] is not None and r["plausible"]]
    vs_meta = {"source": "sfm", "registration_rate": summary["registration_rate"], "ok": summary["ok"],
               "n_views_designed": len(rows)}
    if views:
        ViewSet(camera=cam, views=views, volume_id=vol.volume_id, isocenter_mm=iso, meta=vs_meta).save(
            out_dir / "aligned_views.json")
    else:  # nothing registered: same format with no views (ViewSet.load then refuses it with a clear message)
        write_json_atomic(out_dir / "aligned_views.json", {
            "format": VIEWSET_FORMAT, "format_version": VIEWSET_FORMAT_VERSION, "volume_id": vol.volume_id,
            "isocenter_mm": np.asarray(iso, float).tolist(), "camera": cam.to_dict(), "views": [], "meta": vs_meta})
    # the true poses the SfM radiographs were rendered at (all views), same format: lets a consumer render
    # training targets at the true poses and train with the recovered ones (same ids)
    true_views = [View(id=i, R=orbit["Rs"][i], t=orbit["ts"][i], azimuth_deg=float(orbit["azimuth_deg"][i]),
                       elevation_deg=float(orbit["elevation_deg"][i]), split="train") for i in range(len(rows))]
    ViewSet(camera=cam, views=true_views, volume_id=vol.volume_id, isocenter_mm=iso,
            meta={"source": "sfm-true"}).save(out_dir / "true_views.json")
    if cfg["naive_slices"]:
        summary["naive_slices"] = naive_slices_sfm(vol.data, out_dir / ".naive_work", cfg, seed=seed)
        shutil.rmtree(out_dir / ".naive_work", ignore_errors=True)
    summary.update(config=cfg, seed=seed, code_version=code_version(), volume_id=vol.volume_id,
                   camera={"model": "PINHOLE", "width": W, "height": H, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                           "cy": cam.cy, "pitch_mm": cam.pitch_mm, "dso_mm": cam.dso_mm, "dsd_mm": cam.dsd_mm})
    write_json_atomic(out_dir / "summary.json", json_safe(summary))
    return summary


def naive_slices_sfm(volume_data: np.ndarray, work_dir: str | Path, config: dict[str, Any], seed: int = 0
                     ) -> dict[str, Any]:
    """The failure case: COLMAP on the raw axial slices (``data[:, :, k]``) treated as photographs.

    The slices are windowed to 8 bit (same percentile + CLAHE enhancement as the radiographs) and fed to the
    same pipeline with a guessed pinhole camera (``f = 1.2 · max(W, H)``, as COLMAP would guess). There is
    no ground-truth pose, so only registration counts are reported.
    """
    cfg = dict(merge_config("sfm", {k: v for k, v in config.items() if not k.startswith("_")}, SFM_DEFAULTS))
    cfg["_seed"] = seed
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
