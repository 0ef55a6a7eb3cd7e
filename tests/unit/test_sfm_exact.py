"""Oracle tests of the SfM conventions: the projector, the 8-bit images and COLMAP's pinhole agree to sub-pixel,
and exact correspondences fed through the same COLMAP mapping + Sim(3) evaluation give ~0 pose error.

These pin down every convention a pose pipeline can get wrong (pixel-centre offset, row/column order, principal
point, world->camera vs camera->world, the rotation metric, the alignment): a flip or a half-pixel shift shows up
here as a pixel offset or as degrees of rotation error, independently of how good the image features are.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import torch
from orbit_helpers import design_orbit

from ctsplat.geometry import ConeCamera, project_points
from ctsplat.projector import line_integrals
from ctsplat.sfm.align import evaluate_poses
from ctsplat.sfm.features import enhance_for_features, write_pngs
from ctsplat.sfm.step import SFM_DEFAULTS
from ctsplat.utils import merge_config


def _centroid(im: np.ndarray, u: float, v: float, r: int = 4) -> np.ndarray:
    """Intensity centroid (COLMAP pixel coordinates: centre of pixel (i, j) at (j + 0.5, i + 0.5)) near (u, v)."""
    u0, v0 = int(u), int(v)
    win = np.asarray(im, float)[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
    w = np.clip(win - np.median(win), 0.0, None)
    vv, uu = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1] + 0.5
    return np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum()


def test_bead_centroids_in_radiographs_and_pngs_match_the_colmap_pinhole(tmp_path: Path) -> None:
    import imageio.v3 as iio

    n, sp = 48, 2.0
    aff = np.diag([sp, sp, sp, 1.0])
    aff[:3, 3] = [-40.0, -50.0, -43.0]  # off-centre box: catches a principal-point / origin mistake
    X, Y, Z = np.meshgrid(*[np.arange(n) * sp + aff[a, 3] for a in range(3)], indexing="ij")
    centre = aff[:3, 3] + (n - 1) / 2 * sp
    rng = np.random.default_rng(0)
    pts = centre + rng.uniform(-18, 18, (5, 3))
    vol = sum(np.exp(-((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) / (2 * 1.5**2)) for c in pts)
    cam = ConeCamera(width=72, height=60, pitch_mm=1.5, dso_mm=300.0, dsd_mm=600.0)  # W != H: catches a transpose
    orb = design_orbit(4, 360.0, 20.0, 1.0, 300.0, centre + [2.0, 1.0, -3.0])  # elevated views: no symmetry
    p = line_integrals(torch.tensor(vol, dtype=torch.float32), aff, cam, orb["Rs"], orb["ts"], step_voxels=0.25).numpy()
    assert p.shape == (4, 60, 72)
    png = iio.imread(tmp_path / write_pngs(enhance_for_features(p), tmp_path)[1])  # what COLMAP reads (view 1)
    worst, worst_png, checked = 0.0, 0.0, 0
    for k in range(4):
        uv, _ = project_points(cam, orb["Rs"][k], orb["ts"][k], pts)
        for u, v in uv:
            if not (6 <= u < cam.width - 6 and 6 <= v < cam.height - 6):
                continue
            checked += 1
            worst = max(worst, float(np.abs(_centroid(p[k], u, v) - (u, v)).max()))
            if k == 1:
                worst_png = max(worst_png, float(np.abs(_centroid(png, u, v) - (u, v)).max()))
    assert checked >= 16
    assert worst < 0.1  # the projector's beads sit where COLMAP's PINHOLE model puts them
    assert worst_png < 0.5  # ... also after the 8-bit enhancement (CLAHE shifts centroids slightly)


def _exact_database(work: Path, cam: ConeCamera, Rs: np.ndarray, ts: np.ndarray, pts: np.ndarray, cfg: dict,
                    noise_px: float, rng: np.random.Generator) -> list[str]:
    """A COLMAP database whose keypoints are the exact projections (+ noise) of ``pts`` and whose matches are the
    true correspondences, geometrically verified by COLMAP itself (as after feature matching)."""
    import pycolmap

    from ctsplat.sfm.colmap import _matching, _sift_extraction

    names = write_pngs(np.zeros((len(Rs), cam.height, cam.width), np.uint8), work / "images")
    db_path = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    ext, (_, ver) = _sift_extraction(cfg), _matching(cfg)
    pycolmap.extract_features(db_path, work / "images", image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(str(db_path))
    ids = {im.name: im.image_id for im in db.read_all_images()}
    seen = []
    for name, R, t in zip(names, Rs, ts, strict=True):
        uv = project_points(cam, R, t, pts)[0] + rng.normal(0.0, noise_px, (len(pts), 2))
        idx = np.flatnonzero((uv >= 0).all(1) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height))
        kp = np.zeros((len(idx), 6), np.float32)
        kp[:, :2], kp[:, 2], kp[:, 5] = uv[idx], 1.0, 1.0
        (db.update_keypoints if db.exists_keypoints(ids[name]) else db.write_keypoints)(ids[name], kp)
        seen.append({int(p): k for k, p in enumerate(idx)})
    pairs = []
    for a, b in itertools.combinations(range(len(names)), 2):
        common = sorted(set(seen[a]) & set(seen[b]))
        db.write_matches(ids[names[a]], ids[names[b]], np.array([[seen[a][q], seen[b][q]] for q in common], np.uint32))
        pairs.append(f"{names[a]} {names[b]}")
    db.close()
    (work / "pairs.txt").write_text("\n".join(pairs) + "\n")
    pycolmap.verify_matches(db_path, work / "pairs.txt", ver)
    return names


@pytest.mark.parametrize(("mapper", "pitch_mm"), [("incremental", 2.4), ("global", 2.4),
                                                  ("incremental", 0.4), ("global", 0.4)])
def test_exact_correspondences_give_exact_poses_through_the_colmap_path(tmp_path: Path, mapper: str,
                                                                        pitch_mm: float) -> None:
    """Pitch 0.4 mm: a focal length of 15.6 image widths (a small object far from the source), beyond the 10 at
    which COLMAP's default filter takes a camera for a wrongly estimated one and registers nothing."""
    pytest.importorskip("pycolmap")
    from ctsplat.sfm.colmap import colmap_map, merge_models

    cfg = merge_config("sfm", {"mapper": mapper}, SFM_DEFAULTS)
    iso = np.array([4.0, -7.0, 10.0])
    truth = design_orbit(16, 120.0, 15.0, 2.0, 300.0, iso, jitter_deg=1.0, seed=1)
    cam = ConeCamera(width=96, height=80, pitch_mm=pitch_mm, dso_mm=300.0, dsd_mm=600.0)
    rng = np.random.default_rng(0)
    pts = iso + rng.uniform(-50.0, 50.0, (150, 3)) * pitch_mm / 2.4  # the same share of the field of view
    names = _exact_database(tmp_path, cam, truth["Rs"], truth["ts"], pts, cfg, 0.0, rng)
    models, stats = colmap_map(tmp_path / "database.db", tmp_path / "images", tmp_path, names, cfg)
    assert stats["features_median"] > 100
    _, poses, report = merge_models(models, 3)
    assert report["model_sizes"][0] == 16
    rows, align = evaluate_poses(poses, names, truth["Rs"], truth["ts"], threshold_mm=6.0)
    assert align["n_inliers"] == 16
    rot = np.array([r["rot_err_deg"] for r in rows])
    cen = np.array([r["centre_err_mm"] for r in rows])
    assert rot.max() < 0.01 and cen.max() < 0.05 * pitch_mm / 2.4  # exact data: exact poses (a slip gives degrees)


@pytest.mark.parametrize("mode", ["refine", "refine_prior", "isocentric"])
def test_refine_from_a_jittered_design_recovers_the_true_orbit(tmp_path: Path, mode: str) -> None:
    """pose_prior 'refine' / 'refine_prior' / 'isocentric': triangulate from the design (1 deg off), bundle-adjust
    (with the designed centres as priors of sigma 5 mm; then with every camera a rotation about the isocentre):
    consistent image data pull the poses onto the truth."""
    pytest.importorskip("pycolmap")
    from ctsplat.sfm.colmap import colmap_map, merge_models

    cfg = merge_config("sfm", {"pose_prior": mode, "prior_sigma_mm": 5.0}, SFM_DEFAULTS)
    design = design_orbit(16, 120.0, 15.0, 2.0, 300.0)
    truth = design_orbit(16, 120.0, 15.0, 2.0, 300.0, jitter_deg=1.0, seed=2)
    cam = ConeCamera(width=96, height=80, pitch_mm=2.4, dso_mm=300.0, dsd_mm=600.0)
    rng = np.random.default_rng(1)
    pts = rng.uniform(-50.0, 50.0, (150, 3))
    names = _exact_database(tmp_path, cam, truth["Rs"], truth["ts"], pts, cfg, 0.1, rng)
    models, _ = colmap_map(tmp_path / "database.db", tmp_path / "images", tmp_path, names, cfg,
                           prior_poses=(design["Rs"], design["ts"]))
    _, poses, _ = merge_models(models, 3)
    if mode == "isocentric":  # the model's cameras sit at DSO from the isocentre, looking through it
        c = np.stack([-R.T @ t for R, t in poses.values()])
        np.testing.assert_allclose(np.linalg.norm(c, axis=1), 300.0, rtol=1e-9)
        np.testing.assert_allclose([R[2] @ (-ci) / 300.0 for (R, _), ci in zip(poses.values(), c, strict=True)], 1.0)
    rows, _ = evaluate_poses(poses, names, truth["Rs"], truth["ts"], threshold_mm=6.0)
    design_rows, _ = evaluate_poses({n: (design["Rs"][i], design["ts"][i]) for i, n in enumerate(names)}, names,
                                    truth["Rs"], truth["ts"], threshold_mm=6.0)
    design_err = np.median([r["rot_err_deg"] for r in design_rows])
    assert design_err > 0.8  # the design alone is not the answer
    assert np.median([r["rot_err_deg"] for r in rows]) < min(0.25, design_err / 4)
