"""Isocentric bundle adjustment (ctsplat.sfm.bundle): Jacobians against finite differences, exact recovery of a
jittered isocentric orbit from noisy correspondences with outliers, the soft isocentre, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from orbit_helpers import design_orbit
from scipy.spatial.transform import Rotation

from ctsplat.geometry import ConeCamera, project_points
from ctsplat.sfm.align import rotation_error_deg
from ctsplat.sfm.bundle import (
    isocentre_from_poses,
    isocentric_bundle_adjustment,
    isocentric_poses,
    reprojection_jacobians,
)
from ctsplat.utils import CtsplatError

CAM = ConeCamera(width=128, height=128, pitch_mm=2.0, dso_mm=400.0, dsd_mm=800.0)
K = (CAM.fx, CAM.fy, CAM.cx, CAM.cy)
ISO = np.array([3.0, -5.0, 8.0])


def _scene(jitter_mm: float = 0.0, noise_px: float = 0.0, outlier_frac: float = 0.0, seed: int = 0
           ) -> dict[str, np.ndarray]:
    """36 views over 360 deg (1 deg off the design per view), 300 points in a 70 mm ball, all observations."""
    design = design_orbit(36, 360.0, 20.0, 2.0, CAM.dso_mm, ISO)
    truth = design_orbit(36, 360.0, 20.0, 2.0, CAM.dso_mm, ISO, jitter_deg=1.0, jitter_mm=jitter_mm, seed=seed + 3)
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(300, 3))
    pts = ISO + 70.0 * d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.2, 1.0, (300, 1))
    ov, op, xy = [], [], []
    for v in range(36):
        uv = project_points(CAM, truth["Rs"][v], truth["ts"][v], pts)[0]
        ov += [v] * len(pts)
        op += list(range(len(pts)))
        xy.append(uv + rng.normal(0.0, noise_px, uv.shape) if noise_px else uv)
    xy = np.concatenate(xy)
    bad = rng.random(len(xy)) < outlier_frac
    xy[bad] += rng.uniform(-30.0, 30.0, (int(bad.sum()), 2))
    return {"design": design, "truth": truth, "pts": pts, "ov": np.array(ov), "op": np.array(op), "xy": xy}


def _gauge_free_error(Rs: np.ndarray, Rs_true: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-view rotation error (deg) after the best single rotation about the isocentre (the data's gauge: the
    images do not change if the scene and all cameras turn together), and that rotation's angle (deg)."""
    U, _, Vt = np.linalg.svd(np.einsum("vji,vjk->ik", Rs, Rs_true))  # chordal mean of R_iᵀ R_true_i
    G = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return rotation_error_deg(Rs @ G, Rs_true), float(rotation_error_deg(G, np.eye(3)))


def test_reprojection_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(0)
    Rs = Rotation.random(4, random_state=1).as_matrix()
    X = ISO + rng.uniform(-60, 60, (5, 3))
    s = rng.normal(0, 2.0, (4, 3))
    ov, op = np.repeat(np.arange(4), 5), np.tile(np.arange(5), 4)
    xy = rng.uniform(0, 128, (20, 2))
    r, Jr, Js, Jx, z = reprojection_jacobians(Rs, X, s, ov, op, xy, K, ISO, CAM.dso_mm)
    assert (z > 0).all()
    h = 1e-6

    def residual(R: np.ndarray, X_: np.ndarray, s_: np.ndarray) -> np.ndarray:
        return reprojection_jacobians(R, X_, s_, ov, op, xy, K, ISO, CAM.dso_mm)[0]

    def shifted(a: np.ndarray, k: int, step: float) -> np.ndarray:
        b = a.copy()
        b[:, k] += step
        return b

    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        turn = [Rotation.from_rotvec(sign * e).as_matrix() @ Rs for sign in (1, -1)]
        cases = [(Jr, [(turn[0], X, s), (turn[1], X, s)]),
                 (Js, [(Rs, X, shifted(s, k, h)), (Rs, X, shifted(s, k, -h))]),
                 (Jx, [(Rs, shifted(X, k, h), s), (Rs, shifted(X, k, -h), s)])]
        for J, (plus, minus) in cases:
            fd = (residual(*plus) - residual(*minus)) / (2 * h)
            np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-5, atol=1e-6)


def test_isocentre_and_translations_of_a_designed_orbit_are_exact() -> None:
    o = design_orbit(24, 200.0, 15.0, 2.0, 350.0, ISO)
    iso, dso = isocentre_from_poses(o["Rs"], o["ts"])
    np.testing.assert_allclose(iso, ISO, atol=1e-9)
    assert dso == pytest.approx(350.0)
    np.testing.assert_allclose(isocentric_poses(o["Rs"], iso, dso), o["ts"], atol=1e-9)
    with pytest.raises(CtsplatError, match="parallel"):
        isocentre_from_poses(np.repeat(o["Rs"][:1], 3, 0), o["ts"][:3])


def test_noise_free_correspondences_give_the_true_orbit_from_the_design() -> None:
    """Exact data: without a prior the orbit comes out exact up to the gauge; the design prior trades a little
    of the weakly determined view-to-view detail for staying near the design, less as its sigma widens."""
    sc = _scene()
    X0 = sc["pts"] + np.random.default_rng(5).normal(0.0, 3.0, sc["pts"].shape)
    design_err = rotation_error_deg(sc["design"]["Rs"], sc["truth"]["Rs"])
    assert np.median(design_err) > 0.8  # the start is the design, 1 deg off
    errs = {}
    for sigma in (None, 10.0, 1.0):
        res = isocentric_bundle_adjustment(sc["design"]["Rs"], X0, sc["ov"], sc["op"], sc["xy"], K, ISO,
                                           CAM.dso_mm, design_Rs=sc["design"]["Rs"], design_sigma_deg=sigma)
        errs[sigma], gauge = _gauge_free_error(res.Rs, sc["truth"]["Rs"])
        assert res.cost_final < res.cost_initial / 100
        if sigma is None:
            assert res.reproj_err_px_median < 1e-5
            c = np.einsum("vji,vj->vi", res.Rs, -res.ts)
            assert np.allclose(np.linalg.norm(c - ISO, axis=1), CAM.dso_mm)  # rigid C-arm: every source at DSO
        else:
            assert gauge < 0.5  # the prior fixes the global rotation near the design's mean
    assert errs[None].max() < 1e-4  # exact view-to-view poses
    assert errs[10.0].max() < 1e-3 < errs[1.0].max() < 0.1


def test_noise_and_outliers_are_absorbed_by_the_cauchy_loss() -> None:
    sc = _scene(noise_px=0.3, outlier_frac=0.05, seed=1)
    res = isocentric_bundle_adjustment(sc["design"]["Rs"], sc["pts"], sc["ov"], sc["op"], sc["xy"], K, ISO,
                                       CAM.dso_mm, design_Rs=sc["design"]["Rs"], design_sigma_deg=1.0)
    err, _ = _gauge_free_error(res.Rs, sc["truth"]["Rs"])
    assert np.median(err) < 0.1 and err.max() < 0.25
    assert 0.2 < res.reproj_err_px_median < 0.6


def test_soft_isocentre_recovers_a_wobbling_gantry_that_the_rigid_model_cannot() -> None:
    sc = _scene(jitter_mm=2.0, seed=2)
    kw = {"design_Rs": sc["design"]["Rs"], "design_sigma_deg": 1.0}
    rigid = isocentric_bundle_adjustment(sc["design"]["Rs"], sc["pts"], sc["ov"], sc["op"], sc["xy"], K, ISO,
                                         CAM.dso_mm, **kw)
    soft = isocentric_bundle_adjustment(sc["design"]["Rs"], sc["pts"], sc["ov"], sc["op"], sc["xy"], K, ISO,
                                        CAM.dso_mm, isocentre_sigma_mm=2.0, **kw)
    e_rigid, _ = _gauge_free_error(rigid.Rs, sc["truth"]["Rs"])
    e_soft, _ = _gauge_free_error(soft.Rs, sc["truth"]["Rs"])
    assert np.median(e_soft) < 0.02 < np.median(e_rigid)
    assert np.linalg.norm(rigid.offsets_mm) == 0.0


@pytest.mark.parametrize("case", ["shape", "index", "single", "loss"])
def test_bad_input_is_refused_in_one_line(case: str) -> None:
    sc = _scene()
    args = [sc["design"]["Rs"], sc["pts"], sc["ov"], sc["op"], sc["xy"], K, ISO, CAM.dso_mm]
    kw: dict = {}
    if case == "shape":
        args[4] = sc["xy"][:, :1]
    elif case == "index":
        args[2] = sc["ov"] + 1
    elif case == "single":
        keep = ~((sc["op"] == 0) & (sc["ov"] > 0))  # point 0 seen once
        args[2], args[3], args[4] = sc["ov"][keep], sc["op"][keep], sc["xy"][keep]
    else:
        kw["loss_scale_px"] = 0.0
    with pytest.raises(CtsplatError, match="isocentric BA") as exc:
        isocentric_bundle_adjustment(*args, **kw)
    assert "\n" not in str(exc.value)
