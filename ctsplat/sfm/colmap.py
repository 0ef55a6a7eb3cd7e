"""COLMAP through pycolmap: feature extraction, matching, incremental / global mapping, pose-prior refinement,
model merging and depth-reversal repair, with the known pinhole intrinsics of the cone-beam detector held fixed.

pycolmap is imported here and, for ordinary photographs, in :mod:`ctsplat.photos`; nowhere else in ctsplat.

References
----------
Schönberger, J. L., Frahm, J.-M. (2016). Structure-from-motion revisited. CVPR. (COLMAP's incremental mapper.)
Pan, L., Baráth, D., Pollefeys, M., Schönberger, J. L. (2024). Global structure-from-motion revisited. ECCV.
(The global mapper.)
Lowe, D. G. (2004). Distinctive image features from scale-invariant keypoints. International Journal of Computer
Vision 60(2), 91-110. (SIFT features and the ratio test.)
Triggs, B., McLauchlan, P. F., Hartley, R. I., Fitzgibbon, A. W. (2000). Bundle adjustment — a modern synthesis.
In Vision Algorithms: Theory and Practice, LNCS 1883, 298-372. Springer.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from ctsplat.geometry import camera_center
from ctsplat.sfm.align import evaluate_poses, umeyama
from ctsplat.utils import CtsplatError, atomic_dir

__all__ = ["MAPPING_THREADS", "MATCHING_THREADS", "REFINE_MODES", "colmap_reconstruct", "extraction_options",
           "matching_options", "match_pairs",
           "match_features", "colmap_map", "reverse_depth", "fix_reversal", "merge_models", "model_poses",
           "set_poses_and_triangulate", "isocentric_adjust", "per_image_reproj", "write_model", "MODEL_FILES"]

log = logging.getLogger(__name__)

#: ``pose_prior`` modes that triangulate from the designed poses and refine them (:func:`colmap_map`).
REFINE_MODES = ("refine", "refine_prior", "isocentric")

#: The files of a model folder :func:`write_model` writes (binary, and text under ``text/``; pycolmap 3.12 and later
#: add rigs and frames).
MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin", "text/*.txt")

MAPPING_THREADS = 1
"""Threads for COLMAP's mapping and every bundle adjustment. Ceres and the parallel triangulation add their parts
in the order the threads finish, so on more threads the poses differ in the last bits from run to run and the
incremental mapper grows the difference into different models."""

MATCHING_THREADS = 1
"""Threads for COLMAP's CPU feature matching. Its (faiss) matcher returns other matches now and then when pairs are
matched on more than one thread (2 of 30 runs on the same 36 radiographs, 4 of 4 alike on the 66 skull photos), and
the mapper grows any difference into another model; on one thread the matches repeat. Exact brute-force matching
repeats on any number of threads but took 17 times as long on the photos (208 s on two threads against 12 s; one
thread of the default matcher: 17 s)."""


def extraction_options() -> pycolmap.FeatureExtractionOptions:
    """SIFT extraction options for the CPU, on one thread (the caller sets the SIFT parameters).

    COLMAP numbers the images in the order its extraction threads finish them, and the numbers steer matching and
    mapping, so parallel extraction makes the model differ between runs on the same images; on one thread the
    numbers follow the order of the names given.

    Returns
    -------
    pycolmap.FeatureExtractionOptions
    """
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = 1
    ext.use_gpu = False
    return ext


def _sift_extraction(cfg: dict[str, Any]) -> pycolmap.FeatureExtractionOptions:
    ext = extraction_options()
    ext.sift.max_num_features = int(cfg["max_num_features"])
    ext.sift.peak_threshold = float(cfg["peak_threshold"])
    ext.sift.edge_threshold = float(cfg["edge_threshold"])
    ext.sift.upright = bool(cfg["upright"])
    ext.sift.first_octave = int(cfg["sift_first_octave"])
    ext.sift.num_octaves = int(cfg["sift_num_octaves"])
    ext.sift.domain_size_pooling = bool(cfg["sift_domain_size_pooling"])
    return ext


def matching_options() -> pycolmap.FeatureMatchingOptions:
    """Feature matching options for the CPU, on :data:`MATCHING_THREADS` (the caller sets the SIFT parameters).

    Returns
    -------
    pycolmap.FeatureMatchingOptions
    """
    mat = pycolmap.FeatureMatchingOptions()
    mat.num_threads = MATCHING_THREADS
    mat.use_gpu = False
    return mat


def match_pairs(db_path: str | Path, how: str, matching: pycolmap.FeatureMatchingOptions,
                verification: pycolmap.TwoViewGeometryOptions, *, overlap: int, quadratic_overlap: bool) -> None:
    """Match and verify a database's features: every pair, or each image with its successors.

    Parameters
    ----------
    db_path : str or Path
        COLMAP database with images and keypoints; the verified matches are added to it.
    how : {"exhaustive", "sequential"}
        Every pair, or each image with its ``overlap`` successors in name order.
    matching : pycolmap.FeatureMatchingOptions
        From :func:`matching_options`, its SIFT parameters set.
    verification : pycolmap.TwoViewGeometryOptions
        Two-view geometry verification.
    overlap : int
        Successors per image (sequential).
    quadratic_overlap : bool
        Sequential: also the successors at quadratic distances (COLMAP's default).
    """
    if how == "exhaustive":
        pycolmap.match_exhaustive(db_path, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
        return
    pair = pycolmap.SequentialPairingOptions()
    pair.overlap = int(overlap)
    pair.quadratic_overlap = bool(quadratic_overlap)
    pair.num_threads = MATCHING_THREADS
    pycolmap.match_sequential(db_path, matching_options=matching, pairing_options=pair,
                              verification_options=verification, device=pycolmap.Device.cpu)


def _matching(cfg: dict[str, Any]):  # noqa: ANN202 - pycolmap option objects
    mat = matching_options()
    mat.sift.max_ratio = float(cfg["max_ratio"])
    mat.sift.max_distance = float(cfg["max_distance"])
    ver = pycolmap.TwoViewGeometryOptions()
    ver.min_num_inliers = int(cfg["min_num_inliers"])
    ver.ransac.max_error = float(cfg["max_error_px"])
    ver.ransac.random_seed = int(cfg.get("_seed", 0))
    ver.detect_watermark = False  # radiographs are centred objects; "watermark" filtering rejects them
    return mat, ver


#: COLMAP treats a camera whose focal length exceeds this many image sizes as wrongly estimated and skips its
#: correspondences (its default is 10). Cone-beam intrinsics are exact and held fixed, and a small object far from
#: the source (a 20 mm phantom at 400 mm) has a longer focal length than that: the filter would register nothing.
MAX_FOCAL_LENGTH_RATIO = 1e4


def _incremental_options(cfg: dict[str, Any]):  # noqa: ANN202
    o = pycolmap.IncrementalPipelineOptions()
    o.max_focal_length_ratio = MAX_FOCAL_LENGTH_RATIO
    o.mapper.max_focal_length_ratio = MAX_FOCAL_LENGTH_RATIO
    o.triangulation.max_focal_length_ratio = MAX_FOCAL_LENGTH_RATIO
    o.num_threads = MAPPING_THREADS
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
    m.num_threads = MAPPING_THREADS
    o.triangulation.min_angle = float(cfg["triangulation_min_angle_deg"])
    o.triangulation.random_seed = int(cfg.get("_seed", 0))
    return o


def _global_options(cfg: dict[str, Any]):  # noqa: ANN202
    o = pycolmap.GlobalPipelineOptions()
    o.num_threads = MAPPING_THREADS
    o.random_seed = int(cfg.get("_seed", 0))
    o.min_num_matches = int(cfg["min_num_inliers"])
    o.min_model_size = int(cfg["min_model_size"])
    m = o.mapper
    m.num_threads = MAPPING_THREADS
    m.random_seed = int(cfg.get("_seed", 0))
    m.bundle_adjustment.refine_focal_length = False
    m.bundle_adjustment.refine_principal_point = False
    m.bundle_adjustment.refine_extra_params = False
    m.bundle_adjustment.ceres.use_gpu = False
    m.global_positioning.use_gpu = False
    m.min_tri_angle_deg = float(cfg["triangulation_min_angle_deg"])
    m.retriangulation.max_focal_length_ratio = MAX_FOCAL_LENGTH_RATIO
    return o


def colmap_reconstruct(image_dir: str | Path, image_names: list[str], intrinsics: tuple[float, float, float, float],
                       work_dir: str | Path, config: dict[str, Any], prior_centres: np.ndarray | None = None,
                       prior_poses: tuple[np.ndarray, np.ndarray] | None = None, mask_dir: str | Path | None = None
                       ) -> tuple[dict[int, Any], dict[str, Any]]:
    """Run pycolmap on ``image_names``: SIFT extraction, matching, then mapping (:func:`colmap_map`).

    All images share one PINHOLE camera with fixed intrinsics. Matching is exhaustive, or sequential with
    ``sequential_overlap`` neighbours (plus loop-closure pairs across the ends of a 360-degree orbit). The
    COLMAP database is (re)created as ``work_dir/database.db``, the models under ``work_dir/models``.

    Parameters
    ----------
    image_dir : str or Path
        Folder holding the images.
    image_names : list of str, length V
        File names (COLMAP image names) to use, in orbit order.
    intrinsics : tuple of float
        ``(fx, fy, cx, cy)`` in px, held fixed.
    work_dir : str or Path
        Scratch folder (created).
    config : dict
        The ``sfm`` section (:data:`ctsplat.sfm.step.SFM_DEFAULTS`) plus the private ``_seed`` and ``_arc_deg``.
    prior_centres : ndarray, shape (V, 3), optional
        Designed camera centres (world mm), in the order of ``image_names``. With ``pose_prior: position`` they
        are written to the database as Cartesian position priors with covariance ``prior_sigma_mm² I``; the
        incremental mapper then uses them (``use_prior_position``, robust loss) and returns models in the prior
        frame.
    prior_poses : tuple of ndarray, optional
        Designed poses ``(Rs (V, 3, 3), ts (V, 3) mm)``: instead of a mapper, the verified matches are
        triangulated from them and all poses and points are bundle-adjusted (the ``pose_prior`` refine modes).
    mask_dir : str or Path, optional
        Feature masks, ``<mask_dir>/<image name>.png``; features on 0 pixels are dropped.

    Returns
    -------
    models : dict of int to pycolmap.Reconstruction
        Reconstructions keyed by model index (empty when mapping failed).
    stats : dict
        Verified and matched pairs, median features per image, seconds per stage, and for ``isocentric`` the
        isocentric adjustment's report.

    Raises
    ------
    CtsplatError
        For an unknown ``matching`` or ``mapper``.
    """
    cfg = config
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db_path = work_dir / "database.db"
    if db_path.exists():
        db_path.unlink()
    with contextlib.suppress(Exception):
        pycolmap.set_random_seed(int(cfg.get("_seed", 0)))
        pycolmap.logging.minloglevel = 1 if log.isEnabledFor(logging.DEBUG) else 2  # glog: 1 WARNING, 2 ERROR
    ext = _sift_extraction(cfg)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in intrinsics)
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)  # <mask_dir>/<image name>.png; features on 0 pixels are dropped
    stats: dict[str, Any] = {}
    t0 = time.perf_counter()
    with colmap_errors(image_dir):
        pycolmap.extract_features(db_path, image_dir, image_names=list(image_names),
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=ext, device=pycolmap.Device.cpu)
        if prior_centres is not None and cfg.get("pose_prior") == "position":
            _write_pose_priors(db_path, image_names, np.asarray(prior_centres, float), float(cfg["prior_sigma_mm"]))
        t1 = time.perf_counter()
        match_features(db_path, image_names, cfg)
        t2 = time.perf_counter()
        models, map_stats = colmap_map(db_path, image_dir, work_dir, image_names, cfg, prior_centres=prior_centres,
                                       prior_poses=prior_poses)
    stats.update(map_stats, seconds_features=t1 - t0, seconds_matching=t2 - t1)
    return models, stats


@contextlib.contextmanager
def colmap_errors(image_dir: str | Path, *, fix: str = "check the sfm settings") -> Iterator[None]:
    """Turn COLMAP's errors into one line naming the image folder: its message's first line, then ``fix``.

    COLMAP's failed checks arrive as ``ValueError`` (C++ ``std::invalid_argument``: an option it refuses), its
    database and file errors as ``RuntimeError``; ctsplat's own errors pass unchanged.

    Parameters
    ----------
    image_dir : str or Path
        The images COLMAP was working on (for the message).
    fix : str, keyword-only
        What to do about it (for the message).

    Raises
    ------
    CtsplatError
        For a ``RuntimeError`` or ``ValueError`` of COLMAP's.
    """
    try:
        yield
    except CtsplatError:
        raise
    except (RuntimeError, ValueError) as exc:
        first = next((line.strip() for line in str(exc).splitlines() if line.strip()), "no message")
        raise CtsplatError(f"COLMAP failed on {image_dir}: {first}; {fix}") from exc


def match_features(db_path: str | Path, image_names: list[str], config: dict[str, Any]) -> None:
    """Match and verify the features in a COLMAP database, exhaustively or along the orbit.

    ``sequential`` matching pairs each image with its ``sequential_overlap`` successors and, on a full orbit
    (``_arc_deg`` of 360 or more), the last images with the first. Matching runs on :data:`MATCHING_THREADS`, so
    the same database gets the same matches.

    Parameters
    ----------
    db_path : str or Path
        COLMAP database with images and keypoints; the verified matches are added to it.
    image_names : list of str, length V
        Image names in orbit order (the loop-closure pairs).
    config : dict
        The ``sfm`` section (:data:`ctsplat.sfm.step.SFM_DEFAULTS`) plus the private ``_seed`` and ``_arc_deg``.

    Raises
    ------
    CtsplatError
        For an unknown ``matching``.
    """
    cfg = config
    matching = cfg["matching"]
    if matching not in ("exhaustive", "sequential"):
        raise CtsplatError(f"unknown sfm.matching {matching!r}; allowed: exhaustive, sequential")
    mat, ver = _matching(cfg)
    match_pairs(db_path, matching, mat, ver, overlap=int(cfg["sequential_overlap"]), quadratic_overlap=False)
    if matching == "sequential" and float(cfg.get("_arc_deg", 360.0)) >= 360.0:
        _match_loop_closure(Path(db_path), image_names, int(cfg["sequential_overlap"]), mat, ver)


def colmap_map(db_path: str | Path, image_dir: str | Path, work_dir: str | Path, image_names: list[str],
               config: dict[str, Any], prior_centres: np.ndarray | None = None,
               prior_poses: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[dict[int, Any], dict[str, Any]]:
    """The mapping stage of :func:`colmap_reconstruct` on a database that already holds verified matches.

    Separate so that exact (synthetic) correspondences can be fed through the very same mapping path.

    Parameters
    ----------
    db_path : str or Path
        COLMAP database with images, keypoints and verified matches.
    image_dir : str or Path
        Folder holding the images.
    work_dir : str or Path
        Scratch folder; ``work_dir/models`` is replaced.
    image_names : list of str, length V
        Image names, in the order of ``prior_centres`` / ``prior_poses``.
    config : dict
        The ``sfm`` section (see :func:`colmap_reconstruct`).
    prior_centres : ndarray, shape (V, 3), optional
        Designed camera centres (world mm) for ``pose_prior: position`` (already written to the database).
    prior_poses : tuple of ndarray, optional
        Designed poses ``(Rs (V, 3, 3), ts (V, 3) mm)``: triangulate and refine instead of mapping.

    Returns
    -------
    models : dict of int to pycolmap.Reconstruction
        Reconstructions keyed by model index.
    stats : dict
        ``verified_pairs``, ``matched_pairs``, ``features_median``, ``seconds_mapping`` and, for
        ``isocentric``, the isocentric adjustment's report.

    Raises
    ------
    CtsplatError
        For an unknown ``mapper``.
    """
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
        centres = {n: camera_center(Rs[i], ts[i]) for n, i in index.items()}
    rec = _retriangulate_and_adjust(rec, db_path, image_dir, out, cfg, prior_centres=centres)
    stats: dict[str, Any] = {}
    if cfg.get("pose_prior") == "isocentric" and rec.num_points3D() > 0:
        stats["isocentric"] = isocentric_adjust(rec, {n: (Rs[i], ts[i]) for n, i in index.items()}, cfg)
    return rec, stats


def isocentric_adjust(rec: Any, design: dict[str, tuple[np.ndarray, np.ndarray]], cfg: dict[str, Any]
                       ) -> dict[str, Any]:
    """Isocentric bundle adjustment (:mod:`ctsplat.sfm.bundle`) of a model's registered views and points, in place.

    The isocentre and DSO come from the designed poses (:func:`ctsplat.sfm.bundle.isocentre_from_poses`); the
    rotations start from the model's, every view keeps the prior ``N(0, design_sigma_deg²)`` on its deviation
    from the design. Only points seen by at least two designed views take part; the model's poses and those
    points are overwritten with the result.

    Parameters
    ----------
    rec : pycolmap.Reconstruction
        The model, changed in place.
    design : dict of str to (ndarray, ndarray)
        Image name -> designed pose ``(R (3, 3), t (3,) mm)`` world->camera.
    cfg : dict
        The ``sfm`` section: ``design_sigma_deg``, ``isocentre_sigma_mm``, ``isocentric_loss_px``.

    Returns
    -------
    dict
        ``views``, ``points`` and, when there were points, ``observations``, ``iterations``,
        ``reproj_err_px_median`` (px), ``isocentre_mm`` (3,), ``dso_mm`` and ``offset_mm_rms`` (mm).
    """
    from ctsplat.sfm.bundle import isocentre_from_poses, isocentric_bundle_adjustment

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
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = False
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = 1.0
    ba.ceres.solver_options.num_threads = MAPPING_THREADS
    ba.ceres.solver_options.max_num_iterations = 100
    return ba


def reverse_depth(rec: Any) -> Any:
    """The Necker-reversed twin of a reconstruction (in place), bundle-adjusted afterwards by the caller.

    Transmission images have no occlusion, so under weak perspective a scene and its depth-reversed mirror
    image explain the same feature positions: with the reflection ``M = diag(1, 1, -1)`` (world) and
    ``D = diag(1, 1, -1)`` (camera), ``R' = D R M`` and ``X' = M X`` give ``(R' X')_{xy} = (R X)_{xy}``.
    Each camera keeps its distance ``d`` to the points' centroid ``O``: ``c' = M O - d · z'`` (``z'`` the
    third row of ``R'``).

    Parameters
    ----------
    rec : pycolmap.Reconstruction
        The model, changed in place (poses and points).

    Returns
    -------
    pycolmap.Reconstruction
        ``rec``.
    """
    M = np.diag([1.0, 1.0, -1.0])
    xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    O = xyz.mean(0) if len(xyz) else np.zeros(3)
    for frame in rec.frames.values():
        if not frame.has_pose:
            continue
        m = frame.rig_from_world.matrix()
        R, t = m[:, :3], m[:, 3]
        c = camera_center(R, t)
        R2 = M @ R @ M  # D = M numerically
        c2 = M @ O - np.linalg.norm(c - O) * R2[2]
        frame.rig_from_world = pycolmap.Rigid3d(np.hstack([R2, (-R2 @ c2)[:, None]]))
    for p in rec.points3D.values():
        p.xyz = M @ p.xyz
    return rec


def _design_score(rec: Any, design: dict[str, tuple[np.ndarray, np.ndarray]], threshold: float) -> float:
    """Median rotation error (deg) of a model's cameras against the designed poses after Sim(3) alignment."""
    poses = model_poses(rec)
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
    Sim(3) alignment); poses are not pulled towards it. Models with fewer than 3 registered images are skipped.

    Parameters
    ----------
    models : dict of int to pycolmap.Reconstruction
        The models; a reversed twin that fits better replaces its model in place in this dict.
    design : dict of str to (ndarray, ndarray)
        Image name -> designed pose ``(R (3, 3), t (3,) mm)`` world->camera.
    cfg : dict
        The ``sfm`` section (bundle adjustment and triangulation options).
    threshold : float
        RANSAC inlier distance (mm) of the alignment to the design.
    work : tuple of Path, optional
        ``(database, image folder, scratch folder)``: re-triangulate the matches in the twin's frame before
        scoring it.

    Returns
    -------
    list of dict
        One entry per model checked: ``model``, ``images``, ``design_rot_err_deg``,
        ``reversed_design_rot_err_deg`` (degrees) and ``reversed``.
    """
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


def model_poses(rec: Any) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The world->camera poses of the registered images of a pycolmap model.

    Parameters
    ----------
    rec : pycolmap.Reconstruction
        The model.

    Returns
    -------
    dict of str to (ndarray, ndarray)
        Image name -> ``(R (3, 3), t (3,))``, in the model's frame and units.
    """
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
    of the shared images; its extra images' poses are added (``R' = R S_R^T``, ``c' = s S_R c + S_t``). A model
    whose shared centres disagree after the alignment (median residual above 5 % of their mean spread) is not
    merged. Merging repeats until no further model can be added.

    Parameters
    ----------
    models : dict of int to pycolmap.Reconstruction
        The models of one mapping run.
    min_shared : int
        Fewest images a model must share with the merged set to be merged.

    Returns
    -------
    model : pycolmap.Reconstruction or None
        The largest model, unchanged (points of merged models are not transferred); None without models.
    poses : dict of str to (ndarray, ndarray)
        Image name -> ``(R (3, 3), t (3,))`` world->camera in the largest model's frame, merged images included.
    report : dict
        ``models_found``, ``model_sizes`` (registered images, largest first) and ``merged`` (one entry per
        merged model: ``model_size``, ``shared``, ``added``).
    """
    if not models:
        return None, {}, {"models_found": 0, "model_sizes": [], "merged": []}
    order = sorted(models, key=lambda k: -models[k].num_reg_images())
    main = models[order[0]]
    poses = model_poses(main)
    sizes = [int(models[k].num_reg_images()) for k in order]
    merged = []
    changed = True
    remaining = order[1:]
    while changed and remaining:
        changed = False
        for k in list(remaining):
            other = model_poses(models[k])
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
                c = camera_center(R, t)
                c2 = s * Rg @ c + tg
                R2 = R @ Rg.T
                poses[n] = (R2, -R2 @ c2)
                added += 1
            merged.append({"model_size": int(models[k].num_reg_images()), "shared": len(shared), "added": added})
            remaining.remove(k)
            changed = True
    report = {"models_found": len(models), "model_sizes": sizes, "merged": merged}
    return main, poses, report


def set_poses_and_triangulate(rec: Any, poses: dict[str, tuple[np.ndarray, np.ndarray]], db_path: Path,
                               image_dir: Path, out: Path, cfg: dict[str, Any]) -> Any:
    """Set the model's registered images to ``poses`` and re-triangulate all points from them.

    Registered images that ``poses`` does not name are deregistered: their poses are in another frame.

    Parameters
    ----------
    rec : pycolmap.Reconstruction
        The model; poses of its registered images named in ``poses`` are overwritten.
    poses : dict of str to (ndarray, ndarray)
        Image name -> ``(R (3, 3), t (3,))`` world->camera.
    db_path : Path
        The COLMAP database with the verified matches.
    image_dir : Path
        Folder holding the images.
    out : Path
        Scratch folder for the triangulation (created).
    cfg : dict
        The ``sfm`` section (triangulation options).

    Returns
    -------
    pycolmap.Reconstruction
        The model with the new poses and freshly triangulated points.
    """
    for img in list(rec.images.values()):
        if img.has_pose and img.name in poses:
            R, t = poses[img.name]
            rec.frames[img.frame_id].rig_from_world = pycolmap.Rigid3d(np.hstack([R, np.asarray(t)[:, None]]))
        elif img.has_pose:
            rec.deregister_frame(img.frame_id)
    Path(out).mkdir(parents=True, exist_ok=True)
    return pycolmap.triangulate_points(rec, db_path, image_dir, out, clear_points=True,
                                       options=_incremental_options(cfg))


def per_image_reproj(rec: Any) -> dict[str, float]:
    """Mean reprojection error of each registered image's observations in a pycolmap model.

    Parameters
    ----------
    rec : pycolmap.Reconstruction
        The model.

    Returns
    -------
    dict of str to float
        Image name -> mean error (px) over its observations that project; images without any are absent.
    """
    errs: dict[str, list[float]] = {}
    for p in rec.points3D.values():
        for el in p.track.elements:
            img = rec.images[el.image_id]
            uv = img.points2D[el.point2D_idx].xy
            proj = img.project_point(p.xyz)
            if proj is not None:
                errs.setdefault(img.name, []).append(float(np.linalg.norm(np.asarray(proj) - np.asarray(uv))))
    return {k: float(np.mean(v)) for k, v in errs.items()}


def write_model(rec: Any, out_dir: Path) -> None:
    """Write a COLMAP model as binary (``out_dir``) and text (``out_dir/text``), replacing ``out_dir``.

    The model is written to a temporary sibling folder, which then replaces ``out_dir``; when writing fails the
    temporary folder is removed and ``out_dir`` is left as it was.

    Parameters
    ----------
    rec : pycolmap.Reconstruction
        The model.
    out_dir : Path
        Target folder (e.g. ``sparse/0``).
    """
    with atomic_dir(out_dir, marker="cameras.bin", contents=MODEL_FILES) as tmp:
        rec.write_binary(str(tmp))
        (tmp / "text").mkdir()
        rec.write_text(str(tmp / "text"))
