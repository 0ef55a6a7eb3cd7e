"""Photographs -> camera poses with COLMAP (pycolmap): SIFT, matching, incremental mapping, undistortion to PINHOLE.

The output folder is a standard undistorted COLMAP scene, as 3DGS implementations read it::

    OUT/images/<name>        undistorted photographs (registered images only)
    OUT/sparse/0/            PINHOLE cameras, poses and coloured points (binary; text in sparse/0/text)
    OUT/summary.json         registered / unregistered images, mean reprojection error, points, timings

Unlike the radiograph path (:mod:`ctsplat.sfm.colmap`, known detector intrinsics held fixed) the photo path
estimates the intrinsics (focal length, principal point, radial distortion) in bundle adjustment, as COLMAP does
for ordinary photographs. Images that do not register are listed in ``summary.json`` (never dropped silently).
The folder is written under a temporary name and renamed into place, so a failure leaves nothing behind.

References
----------
Schönberger, J. L., Frahm, J.-M. (2016). Structure-from-motion revisited. CVPR.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from ctsplat.photos.config import photo_settings
from ctsplat.photos.images import check_photo_count, check_photos, list_photos, strip_metadata, unread_entries
from ctsplat.sfm.colmap import (
    MAPPING_THREADS,
    MODEL_FILES,
    colmap_errors,
    extraction_options,
    match_pairs,
    matching_options,
    write_model,
)
from ctsplat.utils import CtsplatError, atomic_dir, code_version, write_json_atomic

__all__ = ["run_photo_sfm", "matching_mode"]

log = logging.getLogger(__name__)

#: The files of an SfM folder beside its ``summary.json``: the undistorted photos and the model. A folder holding
#: anything else is not replaced.
SFM_FILES = ("images/*", *(f"sparse/0/{f}" for f in MODEL_FILES))


def matching_mode(settings: dict[str, Any], n_images: int) -> str:
    """``exhaustive`` or ``sequential`` for ``n_images`` under the ``matching`` setting (``auto`` by count).

    Parameters
    ----------
    settings : dict
        The ``photos.sfm`` section.
    n_images : int

    Returns
    -------
    str
    """
    mode = settings["matching"]
    if mode == "auto":
        return "exhaustive" if n_images <= int(settings["exhaustive_max_images"]) else "sequential"
    if mode not in ("exhaustive", "sequential"):
        raise CtsplatError(f"unknown photos.sfm.matching {mode!r}; allowed: auto, exhaustive, sequential")
    return mode


def _extract_and_match(db: Path, image_dir: Path, names: list[str], s: dict[str, Any]) -> str:
    ext = extraction_options()
    ext.max_image_size = int(s["max_image_size"])
    ext.sift.max_num_features = int(s["max_num_features"])
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = str(s["camera_model"])
    mode = pycolmap.CameraMode.SINGLE if s["camera_mode"] == "single" else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=mode, reader_options=reader,
                              extraction_options=ext, device=pycolmap.Device.cpu)
    ver = pycolmap.TwoViewGeometryOptions()
    ver.min_num_inliers = int(s["min_num_inliers"])
    ver.ransac.random_seed = int(s["seed"])
    how = matching_mode(s, len(names))
    # sequential without loop detection, which needs a vocabulary tree file: photo sets here are ordered captures
    match_pairs(db, how, matching_options(), ver, overlap=int(s["sequential_overlap"]), quadratic_overlap=True)
    return how


def _map(db: Path, image_dir: Path, out: Path, s: dict[str, Any]) -> dict[int, Any]:
    out.mkdir(parents=True, exist_ok=True)
    if s["mapper"] == "global":
        g = pycolmap.GlobalPipelineOptions()
        g.num_threads = MAPPING_THREADS
        g.random_seed = int(s["seed"])
        g.min_num_matches = int(s["min_num_inliers"])
        g.mapper.num_threads = MAPPING_THREADS
        g.mapper.random_seed = int(s["seed"])
        g.mapper.bundle_adjustment.ceres.use_gpu = False
        g.mapper.global_positioning.use_gpu = False
        return dict(pycolmap.global_mapping(db, image_dir, out, options=g))
    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = MAPPING_THREADS
    o.random_seed = int(s["seed"])
    o.min_num_matches = int(s["min_num_inliers"])
    o.min_model_size = 3
    o.multiple_models = True  # all models are counted in the summary; the largest is kept
    o.extract_colors = True  # point colours seed the Gaussians' colours
    o.mapper.num_threads = MAPPING_THREADS
    o.mapper.random_seed = int(s["seed"])
    o.mapper.init_min_num_inliers = int(s["init_min_num_inliers"])
    o.mapper.abs_pose_min_num_inliers = int(s["abs_pose_min_num_inliers"])
    o.mapper.abs_pose_min_inlier_ratio = float(s["abs_pose_min_inlier_ratio"])
    return dict(pycolmap.incremental_mapping(db, image_dir, out, options=o))


def run_photo_sfm(image_dir: str | Path, out_dir: str | Path, settings: dict[str, Any] | None = None
                  ) -> dict[str, Any]:
    """Poses, intrinsics and a coloured point cloud from a folder of photographs (module docstring).

    Parameters
    ----------
    image_dir : str or Path
        Folder of JPEG/PNG/TIFF photographs of one scene.
    out_dir : str or Path
        Output folder (replaced after success, and only when it is new, empty or an earlier SfM output; never the
        image folder or one that holds it).
    settings : dict, optional
        The ``photos.sfm`` section (:data:`ctsplat.photos.config.PHOTOS_DEFAULTS`); missing keys take defaults.

    Returns
    -------
    dict
        The summary also written to ``summary.json``: ``n_images``, ``n_registered``, ``registered`` and
        ``unregistered`` (names), ``not_read`` (pictures in the folder that are not read:
        :func:`ctsplat.photos.images.unread_entries`), ``registration_rate``, ``models_found``, ``model_sizes``,
        ``mean_reprojection_error_px``, ``n_points``, ``mean_track_length``, ``matching``, ``camera`` (PINHOLE
        intrinsics of the first camera) and ``seconds_*``.

    Raises
    ------
    CtsplatError
        For a folder without images, a corrupt image, mixed sizes with one camera, or fewer than
        ``min_registered`` images registered in the largest model.
    """
    s = photo_settings({"sfm": dict(settings or {})})["sfm"]
    image_dir, out_dir = Path(image_dir), Path(out_dir)
    if s["camera_mode"] not in ("single", "per_image"):
        raise CtsplatError(f"unknown photos.sfm.camera_mode {s['camera_mode']!r}; allowed: single, per_image")
    names = list_photos(image_dir)
    if s["mapper"] not in ("incremental", "global"):
        raise CtsplatError(f"unknown photos.sfm.mapper {s['mapper']!r}; allowed: incremental, global")
    check_photos(image_dir, names, single_camera=s["camera_mode"] == "single")
    check_photo_count(image_dir, len(names), s["min_registered"])  # before COLMAP runs
    matching_mode(s, len(names))
    with contextlib.suppress(Exception):
        pycolmap.set_random_seed(int(s["seed"]))
        pycolmap.logging.minloglevel = 3  # glog: fatal only; a failed step ends in one line of ours, not two
    _check_free_space(image_dir, names, out_dir)
    with (atomic_dir(out_dir, marker="summary.json", contents=SFM_FILES, inputs=(image_dir,)) as tmp,
          colmap_errors(image_dir, fix=f"check the photos and the free space beside {out_dir}")):
        summary = _run(image_dir, names, tmp, s)
    return summary


def _check_free_space(image_dir: Path, names: list[str], out_dir: Path) -> None:
    """Refuse to start when the output's file system cannot hold the SfM folder: about three times the photos
    (the undistorted copies, COLMAP's database of features and matches, the model)."""
    need = 3 * sum((image_dir / n).stat().st_size for n in names)
    where = next(p for p in (Path(os.path.abspath(out_dir)), *Path(os.path.abspath(out_dir)).parents) if p.exists())
    free = shutil.disk_usage(where).free
    if free < need:
        raise CtsplatError(f"{where} has {free / 2**20:.1f} MiB free and SfM on {len(names)} photos needs at least "
                           f"{need / 2**20:.1f} MiB; free some space or choose another output folder")


def _run(image_dir: Path, names: list[str], tmp: Path, s: dict[str, Any]) -> dict[str, Any]:
    work = tmp / "work"
    work.mkdir()
    db = work / "database.db"
    t0 = time.perf_counter()
    how = _extract_and_match(db, image_dir, names, s)
    t1 = time.perf_counter()
    models = _map(db, image_dir, work / "models", s)
    t2 = time.perf_counter()
    sizes = sorted((int(m.num_reg_images()) for m in models.values()), reverse=True)
    if not models or sizes[0] < int(s["min_registered"]):
        got = sizes[0] if sizes else 0
        raise CtsplatError(f"SfM registered only {got} of {len(names)} photos in {image_dir} in one model (need "
                           f">= {s['min_registered']}); the photos need more overlap or texture")
    best = max(models.values(), key=lambda m: m.num_reg_images())
    best_dir = work / "best"
    best_dir.mkdir()
    best.write_binary(str(best_dir))
    und = work / "undistorted"
    pycolmap.undistort_images(und, best_dir, image_dir, num_threads=int(s["num_threads"]))
    rec = pycolmap.Reconstruction(str(und / "sparse"))
    write_model(rec, tmp / "sparse" / "0")
    (und / "images").rename(tmp / "images")
    for image in sorted((tmp / "images").rglob("*")):  # the undistorter copies EXIF (GPS, serial numbers, dates)
        if image.is_file():
            strip_metadata(image)
    t3 = time.perf_counter()
    registered = sorted(img.name for img in rec.images.values() if img.has_pose)
    unregistered = sorted(set(names) - set(registered))
    if unregistered:
        log.warning("%d of %d photos did not register: %s", len(unregistered), len(names), ", ".join(unregistered))
    # one photo's camera in both models (with photos.sfm.camera_mode: per_image each photo has its own)
    first = min((img for img in rec.images.values() if img.has_pose), key=lambda img: img.name)
    cam = rec.cameras[first.camera_id]
    fx, fy, cx, cy = (float(v) for v in cam.params[:4])
    raw_cam = best.cameras[next(img.camera_id for img in best.images.values() if img.name == first.name)]
    summary = {
        "image_dir": str(image_dir),
        "n_images": len(names),
        "n_registered": len(registered),
        "registration_rate": len(registered) / len(names),
        "registered": registered,
        "unregistered": unregistered,
        "not_read": unread_entries(image_dir),  # other picture formats and broken links, warned about
        "models_found": len(models),
        "model_sizes": sizes,
        "mean_reprojection_error_px": float(best.compute_mean_reprojection_error()),
        "n_points": int(rec.num_points3D()),
        "mean_track_length": float(best.compute_mean_track_length()),
        "matching": how,
        "mapper": s["mapper"],
        "camera": {"model": "PINHOLE", "width": int(cam.width), "height": int(cam.height), "fx": fx, "fy": fy,
                   "cx": cx, "cy": cy},
        "camera_of": first.name,  # the first registered photo's (every photo's with one shared camera)
        "estimated_camera": {"model": raw_cam.model.name, "params": np.asarray(raw_cam.params).tolist()},
        "seconds_features_matching": t1 - t0,
        "seconds_mapping": t2 - t1,
        "seconds_undistortion": t3 - t2,
        "settings": s,
        "code_version": code_version(),
        "pycolmap": version("pycolmap"),
    }
    shutil.rmtree(work)
    write_json_atomic(tmp / "summary.json", summary)
    return summary
