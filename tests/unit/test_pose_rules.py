"""Pose rules against independent references: Sim(3) alignment, fusion bounds, bundle costs, features, verdicts.

Each test pins one numerical or decision rule of ``ctsplat.sfm`` (align, bundle, features, step),
``ctsplat.training.poses`` or ``ctsplat.geometry.cameras`` against a reference written out here (closed forms,
scipy's ``Rotation``, brute force or finite differences), never against the function under test.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from ctsplat.sfm.align import evaluate_poses, fuse_with_design, orbit_basis, robust_sim3


def _rot(rotvec: list[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis-angle vector (radians), by scipy."""
    return Rotation.from_rotvec(np.asarray(rotvec, float)).as_matrix()


def _look_at_poses(centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World->camera poses of cameras at ``centres`` looking at the origin, world +z up (written out here)."""
    Rs, ts = [], []
    for c in np.asarray(centres, float):
        z = -c / np.linalg.norm(c)
        y = -np.array([0.0, 0.0, 1.0]) + z[2] * z
        y /= np.linalg.norm(y)
        R = np.stack([np.cross(y, z), y, z])
        Rs.append(R)
        ts.append(-R @ c)
    return np.stack(Rs), np.stack(ts)


# ------------------------------------------------------------------------------------------------ align
def test_robust_sim3_breaks_an_inlier_count_tie_by_the_lower_msac_score() -> None:
    """Two equally large consistent groups: the exact one (MSAC score lower) wins, not the noisy one."""
    rng = np.random.default_rng(5)
    src = rng.normal(0, 10, (8, 3))
    s1, R1, t1 = 2.0, _rot([0.3, -0.2, 0.5]), np.array([1.0, 2.0, 3.0])
    s2, R2, t2 = 0.5, _rot([-1.0, 0.4, 0.1]), np.array([200.0, -100.0, 50.0])
    dst = np.empty_like(src)
    dst[:4] = s1 * src[:4] @ R1.T + t1  # group A: exact
    dst[4:] = s2 * src[4:] @ R2.T + t2 + rng.normal(0, 0.01, (4, 3))  # group B: as many points, noisy
    s, R, t, inl = robust_sim3(src, dst, threshold=0.5, iterations=500, seed=0)
    np.testing.assert_array_equal(inl, [True] * 4 + [False] * 4)
    assert s == pytest.approx(s1, rel=1e-9)
    np.testing.assert_allclose(R, R1, atol=1e-9)
    np.testing.assert_allclose(t, t1, atol=1e-7)


def test_residual_rotation_is_the_left_factor_of_the_aligned_rotations() -> None:
    """Recovered ``R_i = Δ R_true_i`` with the true centres: the residual is Δ and the per-view rest 0."""
    centres = np.array([[400.0 * np.cos(a), 400.0 * np.sin(a), 30.0 * np.sin(3 * a)]
                        for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)])
    Rs_true, ts_true = _look_at_poses(centres)
    delta = _rot([0.02, -0.03, 0.05])
    names = [f"v{i}" for i in range(12)]
    poses = {}
    for n, R, c in zip(names, Rs_true, centres, strict=True):
        Rd = delta @ R
        poses[n] = (Rd, -Rd @ c)
    rows, align = evaluate_poses(poses, names, Rs_true, ts_true, threshold_mm=1.0)
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(delta).as_rotvec()))
    assert align["residual_rotation_deg"] == pytest.approx(angle, abs=1e-6)
    assert max(r["rot_err_rotalign_deg"] for r in rows) < 1e-5
    assert min(r["rot_err_deg"] for r in rows) == pytest.approx(angle, abs=1e-5)


def test_arc_basis_is_the_cosine_series_from_k_0_to_2k() -> None:
    """On an arc the basis columns are ``cos(k π x)``, ``k = 0..2K``, of the arc position ``x`` in [0, 1]."""
    az = np.array([10.0, 40.0, 55.0, 100.0, 190.0])
    x = (az - 10.0) / 180.0
    ref = np.stack([np.cos(k * np.pi * x) for k in range(5)], 1)
    np.testing.assert_allclose(orbit_basis(az, 2, full_circle=False), ref, atol=1e-12)
    phi = np.deg2rad(az)
    ref_full = np.stack([np.ones(5), np.cos(phi), np.sin(phi), np.cos(2 * phi), np.sin(2 * phi)], 1)
    np.testing.assert_allclose(orbit_basis(az, 2, full_circle=True), ref_full, atol=1e-12)
    # the same arc turned to cross 0 degrees (wrapped azimuths 300..359, 0..130): the same basis
    crossing = np.mod(az + 290.0, 360.0)
    np.testing.assert_allclose(orbit_basis(crossing, 2, full_circle=False), ref, atol=1e-12)


def test_a_c_arm_arc_crossing_zero_wobbles_smoothly() -> None:
    """The wobble follows the angle along the orbit: no jump where the wrapped azimuth goes from 359 to 0."""
    from ctsplat.geometry.orbits import carm_orbit, circular_orbit

    for views in (carm_orbit(12, [0, 0, 0], 500.0, arc_deg=200.0, start_deg=300.0, wobble_deg=10.0,
                             wobble_cycles=1.25),
                  circular_orbit(12, [0, 0, 0], 500.0, arc_deg=200.0, start_deg=300.0, wobble_deg=10.0,
                                 wobble_cycles=1.25, split_fractions={"train": 1.0})):
        el = np.array([v.elevation_deg for v in views])
        step = np.deg2rad(200.0 / 12)  # 10 * 1.25 * step bounds the change between neighbours
        assert np.abs(np.diff(el)).max() <= 10.0 * 1.25 * step + 1e-9, el
        along = 300.0 + 200.0 * np.arange(12) / 12
        np.testing.assert_allclose(el, 10.0 * np.sin(np.deg2rad(1.25 * along)), atol=1e-9)


def test_fusion_with_only_2k_plus_1_registered_views_returns_the_input_unchanged() -> None:
    """``2K + 1`` registered views (< 2K + 2) leave nothing to fuse: the SfM poses come back as they are."""
    az = np.linspace(0, 360, 8, endpoint=False)
    centres = np.stack([500 * np.cos(np.deg2rad(az)), 500 * np.sin(np.deg2rad(az)), np.zeros(8)], 1)
    Rs, ts = _look_at_poses(centres)
    names = [f"v{i}" for i in range(8)]
    poses = {names[i]: (_rot([0.01 * i, 0, 0]) @ Rs[i], ts[i] * 0.5) for i in range(3)}  # K = 1: 3 = 2K + 1 views
    out = fuse_with_design(poses, names, Rs, ts, az, harmonics=1)
    assert set(out) == set(poses)
    for n in poses:
        np.testing.assert_array_equal(out[n][0], poses[n][0])
        np.testing.assert_array_equal(out[n][1], poses[n][1])
    poses[names[3]] = (Rs[3], ts[3])  # 2K + 2 views: now fused into the design frame (the design's own centres)
    fused = fuse_with_design(poses, names, Rs, ts, az, harmonics=1)
    assert not np.allclose(fused[names[0]][1], poses[names[0]][1])


# ----------------------------------------------------------------------------------------------- bundle
def _small_ba_problem(seed: int = 0) -> dict[str, np.ndarray]:
    """Six isocentric cameras (DSO 500 mm) on an arc, 15 points near the isocentre, noisy observations."""
    rng = np.random.default_rng(seed)
    az = np.deg2rad(np.linspace(0, 50, 6))
    centres = np.stack([500 * np.cos(az), 500 * np.sin(az), 20 * np.sin(3 * az)], 1)
    Rs, _ = _look_at_poses(centres)
    X = rng.uniform(-40, 40, (15, 3))
    ov, op = np.meshgrid(np.arange(6), np.arange(15), indexing="ij")
    ov, op = ov.ravel(), op.ravel()
    xc = np.einsum("mij,mj->mi", Rs[ov], X[op]) + [0.0, 0.0, 500.0]
    xy = 1000.0 * xc[:, :2] / xc[:, 2:] + 128.0 + rng.normal(0, 0.3, (len(ov), 2))
    Rs_init = np.stack([_rot(rng.normal(0, 0.01, 3)) @ R for R in Rs])
    return {"Rs": Rs, "Rs_init": Rs_init, "X": X + rng.normal(0, 0.5, X.shape), "ov": ov, "op": op, "xy": xy}


@pytest.mark.parametrize("sigma_iso", [0.0, 2.0])
def test_isocentric_ba_reports_the_energy_of_what_it_returns(sigma_iso: float) -> None:
    """``cost_final`` is the Cauchy + design-prior + offset-prior energy of the returned poses, hand-computed."""
    from ctsplat.sfm.bundle import isocentric_bundle_adjustment

    p = _small_ba_problem()
    c, sigma_deg = 0.5, 1.5
    res = isocentric_bundle_adjustment(p["Rs_init"], p["X"], p["ov"], p["op"], p["xy"], (1000.0, 1000.0, 128.0, 128.0),
                                       np.zeros(3), 500.0, design_Rs=p["Rs"], design_sigma_deg=sigma_deg,
                                       isocentre_sigma_mm=sigma_iso, loss_scale_px=c, max_iterations=6)
    assert res.iterations >= 1 and res.cost_final < res.cost_initial
    np.testing.assert_allclose(res.ts, -np.einsum("vij,j->vi", res.Rs, np.zeros(3)) + [0, 0, 500.0]
                               + res.offsets_mm, atol=1e-9)
    xc = np.einsum("mij,mj->mi", res.Rs[p["ov"]], res.points[p["op"]]) + res.ts[p["ov"]]  # x_cam = R X + t
    assert (xc[:, 2] > 0).all()
    r2 = ((1000.0 * xc[:, :2] / xc[:, 2:] + 128.0 - p["xy"]) ** 2).sum(1)
    dev = np.array([np.linalg.norm(Rotation.from_matrix(R @ Rd.T).as_rotvec()) for R, Rd in zip(res.Rs, p["Rs"],
                                                                                                   strict=True)])
    energy = (c**2 * np.log1p(r2 / c**2)).sum() + (dev**2).sum() / np.radians(sigma_deg) ** 2
    if sigma_iso > 0:
        energy += (res.offsets_mm**2).sum() / sigma_iso**2
        assert np.abs(res.offsets_mm).max() > 0
    else:
        assert not res.offsets_mm.any()
    assert res.cost_final == pytest.approx(energy, rel=1e-9)


def test_isocentric_ba_charges_a_point_behind_its_camera_more_than_any_residual() -> None:
    """A point behind a camera costs 1e6 in the energy (not 0), so the initial energy is above 1e6."""
    from ctsplat.sfm.bundle import isocentric_bundle_adjustment

    p = _small_ba_problem(1)
    X = p["X"].copy()
    X[0] = [900.0, 0.0, 0.0]  # behind camera 0 (at +500 x, looking at -x)
    res = isocentric_bundle_adjustment(p["Rs"], X, p["ov"], p["op"], p["xy"], (1000.0, 1000.0, 128.0, 128.0),
                                       np.zeros(3), 500.0, max_iterations=0)
    assert res.cost_initial > 1e6 and res.cost_final == res.cost_initial


# --------------------------------------------------------------------------------------------- features
def test_feature_masks_treat_the_image_border_as_background() -> None:
    """An all-object view keeps only pixels farther than the margin from the border (brute-force distance)."""
    from ctsplat.sfm.features import feature_masks

    H, W, margin = 9, 12, 2.5
    m = feature_masks(np.ones((H, W)), 0.02, margin)[0]
    i, j = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    dist = np.minimum.reduce([i + 1, H - i, j + 1, W - j])  # to the nearest pixel outside the image
    np.testing.assert_array_equal(m, np.where(dist > margin, 255, 0))


def test_feature_masks_with_no_margin_keep_everything_background_included() -> None:
    """``margin_px = 0`` masks nothing, not even the air around the object."""
    from ctsplat.sfm.features import feature_masks

    im = np.zeros((2, 8, 8))
    im[:, 2:6, 2:6] = 1.0
    assert (feature_masks(im, 0.02, 0.0) == 255).all()


def test_write_pngs_numbers_the_files_from_zero_by_default(tmp_path: Path) -> None:
    """Without ids the images are ``view_0000.png``, ``view_0001.png``, ... in order."""
    from ctsplat.sfm.features import write_pngs

    names = write_pngs(np.zeros((3, 4, 4), np.uint8), tmp_path / "im")
    assert names == ["view_0000.png", "view_0001.png", "view_0002.png"]
    assert sorted(p.name for p in (tmp_path / "im").iterdir()) == names


def test_enhancement_blanks_the_air_and_windows_over_the_object_only() -> None:
    """Air pixels are 0; the object's own range spans 0..255 even with a bright air outlier excluded."""
    from ctsplat.sfm.features import enhance_for_features

    im = np.zeros((32, 32))
    im[8:24, 8:24] = np.linspace(1.0, 2.0, 256).reshape(16, 16)
    out = enhance_for_features(im, background_frac=0.1, p_low=0.0, p_high=100.0)[0]
    assert (out[im <= 0.2] == 0).all()
    assert out[8:24, 8:24].max() == 255 and out[8:24, 8:24].min() <= 5


# ------------------------------------------------------------------------------------------------- step
def _rows(n: int, n_reg: int, rot: float, centre: float) -> list[dict]:
    """``n`` verdict rows, the first ``n_reg`` registered with the given errors."""
    return [{"registered": i < n_reg, "rot_err_deg": rot if i < n_reg else np.nan,
             "centre_err_mm": centre if i < n_reg else np.nan} for i in range(n)]


def test_the_verdict_passes_every_threshold_met_exactly_and_fails_just_beyond() -> None:
    """Each bound is inclusive: rate 0.8, 2.0 deg, 0.05 of DSO and half the views as inliers pass; beyond fails."""
    from ctsplat.sfm.step import SFM_DEFAULTS, summarize

    cfg = dict(SFM_DEFAULTS)
    rep = {"models_found": 1, "model_sizes": [8]}
    at = summarize(_rows(10, 8, 2.0, 20.0), rep, cfg, dso_mm=400.0, alignment={"ok": True, "n_inliers": 4,
                                                                                 "n_used": 8})
    assert at["ok"], at.get("reason")
    assert at["registration_rate"] == 0.8 and at["centre_err_frac_median"] == 0.05
    assert at["alignment_inlier_rate"] == 0.5
    for rows, align, word in [(_rows(10, 7, 2.0, 20.0), (4, 7), "registration rate"),
                              (_rows(10, 8, 2.001, 20.0), (4, 8), "rotation"),
                              (_rows(10, 8, 2.0, 20.1), (4, 8), "centre"),
                              (_rows(10, 8, 2.0, 20.0), (3, 8), "alignment threshold")]:
        out = summarize(rows, rep, cfg, dso_mm=400.0, alignment={"ok": True, "n_inliers": align[0],
                                                                  "n_used": align[1]})
        assert not out["ok"] and word in out["reason"] and out["reason"].count(";") == 0


def test_summary_counts_only_scored_views_and_the_largest_model() -> None:
    """Registered views without an error (too few to align) do not count; the largest model is the first size."""
    from ctsplat.sfm.step import SFM_DEFAULTS, summarize

    rows = [{"registered": True, "rot_err_deg": np.nan, "centre_err_mm": np.nan}] * 2 + _rows(8, 0, 0.0, 0.0)
    out = summarize(rows, {"models_found": 2, "model_sizes": [2, 1]}, dict(SFM_DEFAULTS))
    assert out["n_registered"] == 0 and out["registration_rate"] == 0.0
    assert out["largest_model_rate"] == 0.2 and not out["ok"]


def test_a_summary_without_ok_is_a_failure() -> None:
    """``sfm_failure`` of a summary that records no ``ok`` names that, rather than passing it."""
    from ctsplat.sfm.step import sfm_failure

    assert sfm_failure({}) == "the SfM summary is not ok and records no reason"
    assert sfm_failure({"ok": True}) is None


# ------------------------------------------------------------------------------------------- training poses
def _orbit(n: int = 6, elevation_deg: float = 15.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Look-at poses of ``n`` cameras at 600 mm around the isocentre (0, 0, 0), elevated, and their centres."""
    a = np.deg2rad(np.linspace(0, 300, n))
    e = np.deg2rad(elevation_deg * np.cos(a))
    centres = 600 * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1)
    Rs, ts = _look_at_poses(centres)
    return Rs, ts, centres


@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_pose_prior_is_half_weight_mean_of_radian_and_mm_terms(model: str) -> None:
    """``½ w mean(|ω|²/σ_rot² + |Pτ|²/σ_t²)`` with σ_rot in radians and τ_z dropped for parallel beam."""
    from ctsplat.training.poses import PoseCorrection

    Rs, ts, _ = _orbit(4)
    pc = PoseCorrection(Rs, ts, np.zeros(3), model, prior_rot_deg=2.0, prior_trans_mm=3.0, prior_weight=0.5)
    rng = np.random.default_rng(0)
    om, ta = rng.normal(0, 0.02, (4, 3)), rng.normal(0, 2.0, (4, 3))
    with torch.no_grad():
        pc.omega.copy_(torch.as_tensor(om))
        pc.tau.copy_(torch.as_tensor(ta))
    ta_eff = ta * ([1, 1, 0] if model == "parallel" else [1, 1, 1])
    e = (om**2).sum(1) / np.radians(2.0) ** 2 + (ta_eff**2).sum(1) / 9.0
    assert float(pc.prior().detach()) == pytest.approx(0.25 * e.mean(), rel=1e-5)
    assert float(pc.prior([1, 3]).detach()) == pytest.approx(0.25 * e[[1, 3]].mean(), rel=1e-5)


def test_parallel_beam_corrections_have_no_shift_along_the_rays() -> None:
    """For parallel beam (any cone_model) the shift's ray component is dropped and the camera ignores it."""
    from ctsplat.training.poses import PoseCorrection

    Rs, ts, _ = _orbit(3)
    pc = PoseCorrection(Rs, ts, np.zeros(3), "parallel", cone_model="rigid")
    with torch.no_grad():
        pc.tau.copy_(torch.tensor([[1.0, 2.0, 3.0]] * 3))
    assert pc.shift(1).tolist() == [1.0, 2.0, 0.0]
    _, t2 = pc.corrected_poses()
    np.testing.assert_allclose(t2, ts + [1.0, 2.0, 0.0], atol=1e-4)


def test_gauge_fix_removes_a_common_world_rotation_seen_in_each_camera_frame() -> None:
    """``ω_i = R_i Ω + ε_i`` with ``Σ R_iᵀ ε_i = 0``: the gauge fix leaves exactly ``ε_i``."""
    from ctsplat.training.poses import PoseCorrection

    Rs, ts, _ = _orbit(5)
    rng = np.random.default_rng(1)
    eps_w = rng.normal(0, 0.01, (5, 3))
    eps_w -= eps_w.mean(0)  # world-frame parts with zero mean
    eps = np.einsum("vij,vj->vi", Rs, eps_w)
    Om = np.array([0.03, -0.02, 0.05])
    pc = PoseCorrection(Rs, ts, np.zeros(3), "cone")
    with torch.no_grad():
        pc.omega.copy_(torch.as_tensor(np.einsum("vij,j->vi", Rs, Om) + eps))
    pc.fix_gauge()
    np.testing.assert_allclose(pc.omega.detach().numpy(), eps, atol=1e-6)


def test_rotation_angles_match_scipy_over_the_whole_range() -> None:
    """Angles of random rotations, from tiny to nearly 180 degrees, equal scipy's rotation-vector norm."""
    from ctsplat.training.poses import rotation_angles_deg

    rng = np.random.default_rng(2)
    axes = rng.normal(size=(7, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    ang = np.array([1e-4, 0.5, 10.0, 45.0, 90.0, 135.0, 179.0])
    R = Rotation.from_rotvec(axes * np.radians(ang)[:, None]).as_matrix()
    np.testing.assert_allclose(rotation_angles_deg(R), ang, rtol=1e-6)


def test_perturbing_by_zero_keeps_elevated_look_at_poses() -> None:
    """Zero rotation and shift noise returns the recorded poses, elevated views included."""
    from ctsplat.training.poses import perturb_poses

    Rs, ts, _ = _orbit(6, elevation_deg=25.0)
    R2, t2 = perturb_poses(Rs, ts, np.zeros(3), 0.0, 0.0, seed=3)
    np.testing.assert_allclose(R2, Rs, atol=1e-9)
    np.testing.assert_allclose(t2, ts, atol=1e-7)


def test_gauge_motion_recovers_a_world_shift_with_the_right_sign() -> None:
    """Poses trained in a frame shifted by ``b`` (``m = x + b``) give back ``G = I`` and that ``b``."""
    from ctsplat.training.poses import gauge_motion

    Rs, ts, _ = _orbit(6)
    b = np.array([3.0, -2.0, 1.5])
    ts_model = ts - np.einsum("vij,j->vi", Rs, b)  # R (x + b) + t_model = R x + t
    G, b2 = gauge_motion(Rs, ts_model, Rs, ts, "cone")
    np.testing.assert_allclose(G, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(b2, b, atol=1e-9)


# ------------------------------------------------------------------------------------------------ cameras
def test_colmap_qvec_has_a_non_negative_scalar_and_matches_scipy_up_to_sign() -> None:
    """``rotmat_to_qvec`` agrees with scipy's quaternion up to sign and always has ``w >= 0``."""
    from ctsplat.geometry.cameras import qvec_to_rotmat, rotmat_to_qvec

    for k, rv in enumerate(np.random.default_rng(4).normal(0, 1.5, (30, 3))):
        rv = rv / np.linalg.norm(rv) * np.radians(170.0 + k % 10)  # near 180 degrees: w small, either sign
        R = _rot(rv)
        q = rotmat_to_qvec(R)
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        ref = np.array([w, x, y, z])
        assert q[0] >= 0
        assert np.allclose(q, ref, atol=1e-12) or np.allclose(q, -ref, atol=1e-12)
        np.testing.assert_allclose(qvec_to_rotmat(q), R, atol=1e-12)


def test_cone_projection_of_a_point_behind_the_source_is_nan() -> None:
    """A point with ``z_cam < 0`` has no cone-beam image; one in front lands at ``f x / z + c`` (by hand)."""
    from ctsplat.geometry.cameras import ConeCamera, project_points

    cam = ConeCamera(64, 48, pitch_mm=0.5, dso_mm=500.0, dsd_mm=1000.0)
    uv, depth = project_points(cam, np.eye(3), np.zeros(3), np.array([[10.0, -5.0, -100.0], [10.0, -5.0, 100.0]]))
    assert np.isnan(uv[0]).all() and depth[0] == -100.0
    np.testing.assert_allclose(uv[1], [2000.0 * 10 / 100 + 32, 2000.0 * -5 / 100 + 24])


def test_isocentric_ba_pulls_rotations_onto_a_strong_design_prior() -> None:
    """Noise-free data at the design and a 0.05° prior: a 0.5° start converges onto the design rotations."""
    from ctsplat.sfm.bundle import isocentric_bundle_adjustment

    p = _small_ba_problem(2)
    rng = np.random.default_rng(3)
    xc = np.einsum("mij,mj->mi", p["Rs"][p["ov"]], p["X"][p["op"]]) + [0.0, 0.0, 500.0]
    xy = 1000.0 * xc[:, :2] / xc[:, 2:] + 128.0  # exact observations of the (perturbed) points at the design
    Rs0 = np.stack([_rot(rng.normal(0, 0.005, 3)) @ R for R in p["Rs"]])
    res = isocentric_bundle_adjustment(Rs0, p["X"], p["ov"], p["op"], xy, (1000.0, 1000.0, 128.0, 128.0),
                                       np.zeros(3), 500.0, design_Rs=p["Rs"], design_sigma_deg=0.05,
                                       loss_scale_px=2.0, max_iterations=30)
    err = [np.degrees(np.linalg.norm(Rotation.from_matrix(R @ Rd.T).as_rotvec())) for R, Rd in zip(res.Rs, p["Rs"],
                                                                                                     strict=True)]
    assert max(err) < 1e-3 and res.cost_final < 1e-6 * res.cost_initial


def test_enhancement_follows_its_documented_formula() -> None:
    """Pre-blur, high-pass, object-only percentile window, CLAHE, 8 bit, air blanked: rebuilt from scipy/skimage."""
    from scipy.ndimage import gaussian_filter
    from skimage.exposure import equalize_adapthist

    from ctsplat.sfm.features import enhance_for_features

    rng = np.random.default_rng(6)
    yy, xx = np.mgrid[0:40, 0:48]
    p = np.where((yy - 20) ** 2 / 15**2 + (xx - 24) ** 2 / 18**2 < 1, 5.0 + 0.1 * xx + rng.uniform(0, 1, (40, 48)), 0.0)
    kw = {"clip": 0.02, "kernel_frac": 0.25, "p_low": 2.0, "p_high": 97.0, "highpass_frac": 0.1, "lowpass_px": 1.0,
          "background_frac": 0.05}
    fg = p > 0.05 * p.max()
    q = gaussian_filter(p, 1.0, mode="nearest")
    q = q - gaussian_filter(q, 0.1 * 48, mode="nearest")
    lo, hi = np.percentile(q[fg], [2.0, 97.0])
    x = equalize_adapthist(np.clip((q - lo) / (hi - lo), 0, 1), kernel_size=12, clip_limit=0.02)
    ref = np.where(fg, np.round(np.clip(x, 0, 1) * 255), 0).astype(np.uint8)
    np.testing.assert_array_equal(enhance_for_features(p, **kw)[0], ref)


def test_parallel_isocentre_error_ignores_the_ray_component() -> None:
    """Shifts of the camera-frame isocentre: parallel beam scores only ``(x, y)``, cone beam all three (by hand)."""
    from ctsplat.training.poses import pose_errors

    Rs, ts, _ = _orbit(4)
    shift = np.array([[3.0, 0.0, 50.0], [0.0, 4.0, -20.0], [3.0, 4.0, 7.0], [0.0, 0.0, 9.0]])
    par = pose_errors(Rs, ts + shift, Rs, ts, np.zeros(3), "parallel")
    cone = pose_errors(Rs, ts + shift, Rs, ts, np.zeros(3), "cone")
    assert par["iso_err_median_mm"] == pytest.approx(np.median([3.0, 4.0, 5.0, 0.0]))
    assert cone["iso_err_median_mm"] == pytest.approx(np.median(np.linalg.norm(shift, axis=1)))
    assert par["rot_err_median_deg"] == pytest.approx(0.0, abs=1e-6)
