"""SfM helpers: Sim(3) alignment, rotation metric, orbit design, enhancement, pose evaluation (no COLMAP run)."""

from __future__ import annotations

import numpy as np
import pytest
from orbit_helpers import design_orbit
from scipy.spatial.transform import Rotation

from ctsplat.geometry import ConeCamera, camera_center, project_points, support_radius_mm
from ctsplat.sfm.align import evaluate_poses, robust_sim3, rotation_error_deg, umeyama
from ctsplat.sfm.features import enhance_for_features, feature_masks
from ctsplat.sfm.step import SFM_DEFAULTS, sfm_failure, summarize
from ctsplat.utils import CtsplatError, merge_config


def _random_sim3(rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
    return float(rng.uniform(0.2, 5.0)), Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), \
        rng.normal(0, 100, 3)


def test_umeyama_recovers_known_sim3_exactly() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(0, 50, (20, 3))
    s, R, t = _random_sim3(rng)
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst)
    assert s2 == pytest.approx(s, rel=1e-10)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-8)
    assert np.linalg.det(R2) == pytest.approx(1.0)


def test_umeyama_never_returns_a_reflection() -> None:
    # dst is a mirror image of src: the best *proper* rotation must be returned (det = +1)
    rng = np.random.default_rng(2)
    src = rng.normal(0, 1, (10, 3))
    dst = src * np.array([1.0, 1.0, -1.0])
    _, R, _ = umeyama(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_robust_sim3_recovers_exactly_despite_outliers() -> None:
    rng = np.random.default_rng(3)
    src = rng.normal(0, 100, (40, 3))
    s, R, t = _random_sim3(rng)
    dst = s * src @ R.T + t
    bad = rng.choice(40, 12, replace=False)  # 30 % gross outliers
    dst[bad] += rng.normal(0, 300, (12, 3)) + 200.0
    # plain least squares is pulled away by the outliers ...
    s_ls, R_ls, _ = umeyama(src, dst)
    assert rotation_error_deg(R_ls, R) > 1.0 or abs(s_ls - s) > 0.05 * s
    # ... the robust fit recovers the exact transform and flags exactly the outliers
    s2, R2, t2, inl = robust_sim3(src, dst, threshold=1.0, iterations=300, seed=0)
    assert s2 == pytest.approx(s, rel=1e-9)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-6)
    expected = np.ones(40, bool)
    expected[bad] = False
    np.testing.assert_array_equal(inl, expected)


def test_the_verdict_never_prints_a_failing_value_as_a_passing_one() -> None:
    """159 of 200 views (0.795 < 0.8), a rotation error of 2.0004° (> 2°), 79 of 159 inliers (0.497 < 0.5): each
    is shown with the digits that make it fail, not rounded onto its threshold."""
    cfg = merge_config("sfm", {"max_median_rotation_error_deg": 2.0}, SFM_DEFAULTS)
    rows = [{"registered": i < 159, "rot_err_deg": 2.0004 if i < 159 else np.nan, "centre_err_mm": 1.0}
            for i in range(200)]
    out = summarize(rows, {"models_found": 1, "model_sizes": [159]}, cfg, dso_mm=400.0,
                    alignment={"ok": True, "n_inliers": 79, "n_used": 159})
    assert out["ok"] is False
    assert "registration rate 0.795 (need >= 0.8)" in out["reason"]
    assert "median rotation error 2.0004 deg (need <= 2.0 deg)" in out["reason"]
    assert "0.4969 of the registered views" in out["reason"]


def test_robust_sim3_without_a_consensus_reports_no_inliers() -> None:
    """No 3-point sample agrees within the threshold: the fit uses every point, and the inliers it reports are the
    points within the threshold of that fit (none), not all of them (the verdict's inlier rate reads them)."""
    rng = np.random.default_rng(5)
    src = rng.normal(0, 100, (8, 3))
    dst = rng.normal(0, 100, (8, 3))  # unrelated: residuals of tens of mm
    s, R, t, inl = robust_sim3(src, dst, threshold=1.0, iterations=100, seed=0)
    err = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
    assert err.min() > 1.0 and not inl.any()


def test_robust_sim3_needs_three_points() -> None:
    with pytest.raises(CtsplatError, match="at least 3"):
        robust_sim3(np.zeros((2, 3)), np.zeros((2, 3)), threshold=1.0)


def test_rotation_error_matches_axis_angle() -> None:
    rng = np.random.default_rng(4)
    R0 = Rotation.random(random_state=5).as_matrix()
    for angle in (0.0, 0.3, 7.5, 90.0, 179.0):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        dR = Rotation.from_rotvec(np.deg2rad(angle) * axis).as_matrix()
        assert rotation_error_deg(R0, dR @ R0) == pytest.approx(angle, abs=1e-5)
        assert rotation_error_deg(dR @ R0, R0) == pytest.approx(angle, abs=1e-5)
    batch = rotation_error_deg(np.stack([R0, R0]), np.stack([R0, R0.T @ R0 @ R0]))
    assert batch.shape == (2,)


def test_design_orbit_geometry() -> None:
    iso = np.array([5.0, -3.0, 12.0])
    orb = design_orbit(24, 360.0, 15.0, 2.0, 500.0, iso)
    cam = ConeCamera(width=64, height=48, pitch_mm=2.0, dso_mm=500.0, dsd_mm=900.0)
    assert orb["Rs"].shape == (24, 3, 3)
    for R, t, c, az, el in zip(orb["Rs"], orb["ts"], orb["centres"], orb["azimuth_deg"], orb["elevation_deg"],
                               strict=True):
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(-R.T @ t, c, atol=1e-9)  # centre
        assert np.linalg.norm(c - iso) == pytest.approx(500.0)
        assert np.degrees(np.arcsin((c - iso)[2] / 500.0)) == pytest.approx(el)
        assert el == pytest.approx(15.0 * np.sin(np.deg2rad(2.0 * az)))
        uv, depth = project_points(cam, R, t, iso[None])
        np.testing.assert_allclose(uv[0], [cam.cx, cam.cy], atol=1e-9)  # isocentre on the axis
        assert depth[0] == pytest.approx(500.0)
        up = project_points(cam, R, t, (iso + [0, 0, 10.0])[None])[0][0]
        assert up[1] < cam.cy  # world up is image up
    np.testing.assert_allclose(np.diff(orb["azimuth_deg"]), 15.0)
    jit = design_orbit(24, 360.0, 15.0, 2.0, 500.0, iso, jitter_deg=1.0, seed=3)
    d = jit["azimuth_deg"] - orb["azimuth_deg"]
    assert 0.3 < np.std(d) < 2.0
    wob = design_orbit(24, 360.0, 15.0, 2.0, 500.0, iso, jitter_deg=1.0, jitter_mm=2.0, seed=3)
    np.testing.assert_allclose(wob["azimuth_deg"], jit["azimuth_deg"])  # same angular jitter, plus a shift
    shift = wob["centres"] - jit["centres"]
    assert 1.0 < np.sqrt((shift**2).mean()) < 3.5
    for R, t, d_ in zip(wob["Rs"], wob["ts"], shift, strict=True):  # the rigid assembly moved: it looks at iso + d
        np.testing.assert_allclose(project_points(cam, R, t, (iso + d_)[None])[0][0], [cam.cx, cam.cy], atol=1e-9)
    with pytest.raises(CtsplatError):
        design_orbit(1, 360.0, 0.0, 1.0, 500.0)


def test_enhance_for_features_is_8bit_and_uses_the_range() -> None:
    yy, xx = np.mgrid[:64, :64]
    im = np.exp(-((xx - 30) ** 2 + (yy - 34) ** 2) / 200.0) + 0.1 * np.sin(xx / 3.0)
    out = enhance_for_features(np.stack([im, 2 * im + 1, np.zeros_like(im)]))
    assert out.dtype == np.uint8 and out.shape == (3, 64, 64)
    assert out[0].min() == 0 and out[0].max() == 255
    np.testing.assert_array_equal(out[0], out[1])  # per-view window: affine intensity changes do not matter
    assert not out[2].any()  # blank view stays blank, no crash
    with pytest.raises(CtsplatError, match="finite"):
        enhance_for_features(np.full((2, 8, 8), np.nan))


def test_support_radius_measures_the_object_not_the_box() -> None:
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    aff[:3, 3] = -31.0
    data = np.zeros((32, 32, 32), np.float32)
    ax = np.arange(32) * 2.0 - 31.0
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    data[X**2 + Y**2 + Z**2 <= 20.0**2] = 1.0
    r = support_radius_mm(data, aff, np.zeros(3))
    assert 19.0 <= r <= 20.0 + 2 * np.sqrt(3) + 1e-9
    assert support_radius_mm(np.zeros_like(data), aff, np.zeros(3)) == pytest.approx(np.sqrt(3) * 32.0)


def test_evaluate_poses_undoes_an_unknown_similarity() -> None:
    rng = np.random.default_rng(7)
    orb = design_orbit(12, 360.0, 10.0, 2.0, 400.0)
    s, Rg, tg = _random_sim3(rng)  # maps SfM frame -> world: x_w = s Rg x + tg
    names = [f"view_{i:04d}.png" for i in range(12)]
    poses = {}
    for i in range(12):
        if i == 5:
            continue  # not registered
        c_w = orb["centres"][i]
        c = Rg.T @ (c_w - tg) / s
        R = orb["Rs"][i] @ Rg
        if i == 7:  # a badly recovered view: 3 degrees off, centre 30 mm (world) off
            R = Rotation.from_rotvec([0, 0, np.deg2rad(3.0)]).as_matrix() @ R
            c = c + Rg.T @ np.array([30.0, 0, 0]) / s
        poses[names[i]] = (R, -R @ c)
    rows, align = evaluate_poses(poses, names, orb["Rs"], orb["ts"], threshold_mm=5.0, seed=0)
    assert align["scale"] == pytest.approx(s, rel=1e-9)
    assert align["n_inliers"] == 10
    assert not rows[5]["registered"] and np.isnan(rows[5]["rot_err_deg"]) and rows[5]["R"] is None
    for i, r in enumerate(rows):
        if i in (5, 7):
            continue
        assert r["rot_err_deg"] < 1e-5 and r["centre_err_mm"] < 1e-6
        np.testing.assert_allclose(r["R"], orb["Rs"][i], atol=1e-9)
        np.testing.assert_allclose(r["t"], orb["ts"][i], atol=1e-6)
    assert rows[7]["rot_err_deg"] == pytest.approx(3.0, abs=1e-6)
    assert rows[7]["centre_err_mm"] == pytest.approx(30.0, abs=1e-6)
    for r in rows:
        r["reproj_err_px"] = 0.5
    cfg = merge_config("sfm", {}, SFM_DEFAULTS)
    summ = summarize(rows, {"models_found": 1, "model_sizes": [11]}, cfg)
    assert summ["n_registered"] == 11 and summ["registration_rate"] == pytest.approx(11 / 12)
    assert summ["rot_err_deg_median"] == pytest.approx(0.0, abs=1e-5)
    assert summ["ok"] is True


def test_evaluate_poses_with_too_few_registrations_reports_not_ok() -> None:
    orb = design_orbit(10, 360.0, 0.0, 1.0, 400.0)
    names = [f"v{i}" for i in range(10)]
    poses = {names[0]: (orb["Rs"][0], orb["ts"][0]), names[1]: (orb["Rs"][1], orb["ts"][1])}
    rows, align = evaluate_poses(poses, names, orb["Rs"], orb["ts"], threshold_mm=5.0)
    assert not align["ok"]
    assert all(np.isnan(r["rot_err_deg"]) for r in rows)
    summ = summarize(rows, {"models_found": 1, "model_sizes": [2]}, merge_config("sfm", {}, SFM_DEFAULTS))
    assert summ["ok"] is False and summ["registration_rate"] == 0.0 and "registration rate" in summ["reason"]


def test_the_verdict_fails_right_rotations_with_wrong_centres_or_few_inliers() -> None:
    """Rotations alone do not make an orbit: wrong camera distances, or most views off the alignment, fail."""
    cfg = merge_config("sfm", {}, SFM_DEFAULTS)
    report = {"models_found": 1, "model_sizes": [20]}
    rows = [{"registered": True, "rot_err_deg": 0.3, "centre_err_mm": 10.0 + i} for i in range(20)]
    good = summarize(rows, report, cfg, dso_mm=400.0, alignment={"ok": True, "n_inliers": 17, "n_used": 20})
    assert good["ok"] is True and good["centre_err_frac_median"] == pytest.approx(19.5 / 400.0)
    assert good["alignment_inlier_rate"] == pytest.approx(0.85)
    far = [dict(r, centre_err_mm=30.0 + i) for i, r in enumerate(rows)]  # median 39.5 mm, 9.9 % of DSO
    bad = summarize(far, report, cfg, dso_mm=400.0, alignment={"ok": True, "n_inliers": 7, "n_used": 20})
    assert bad["ok"] is False and bad["rot_err_deg_median"] <= cfg["max_median_rotation_error_deg"]
    assert bad["reason"] == ("median centre error 0.09875 of DSO (need <= 0.05); 0.35 of the registered views"
                             " within the alignment threshold (need >= 0.5)")
    assert sfm_failure(bad) == bad["reason"]
    loose = merge_config("sfm", {"max_median_centre_error_frac": 0.1, "min_alignment_inlier_rate": 0.3},
                         SFM_DEFAULTS)
    assert summarize(far, report, loose, dso_mm=400.0, alignment={"ok": True, "n_inliers": 7, "n_used": 20})["ok"]
    unscaled = summarize(far, report, cfg)  # no DSO, no alignment: only registration and rotation are checked
    assert unscaled["ok"] is True and unscaled["centre_err_frac_median"] is None
    assert unscaled["alignment_inlier_rate"] is None


def test_unknown_config_key_is_rejected() -> None:
    with pytest.raises(CtsplatError, match="sfm.nviews"):
        merge_config("sfm", {"nviews": 3}, SFM_DEFAULTS)


def test_orbit_basis_shapes_and_span() -> None:
    from ctsplat.sfm.align import orbit_basis

    az = np.arange(36) * 10.0
    B = orbit_basis(az, 3, True)
    assert B.shape == (36, 7)
    np.testing.assert_allclose(B.T @ B, np.diag([36.0] + [18.0] * 6), atol=1e-9)  # orthogonal on a full circle
    P = orbit_basis(np.linspace(0.0, 120.0, 20), 2, False)
    assert P.shape == (20, 5) and np.linalg.matrix_rank(P) == 5


def bent_sfm_orbit(V: int = 120) -> tuple[dict, dict, list[str], dict]:
    """(design, truth, names, SfM poses): SfM = truth bent smoothly along the orbit (6 deg, 20 mm), in another
    Sim(3) frame; design = truth without its white 1 deg jitter."""
    design = design_orbit(V, 360.0, 15.0, 2.0, 500.0)
    truth = design_orbit(V, 360.0, 15.0, 2.0, 500.0, jitter_deg=1.0, seed=4)
    names = [f"v{i}" for i in range(V)]
    phi = np.deg2rad(design["azimuth_deg"])
    s, Q, p = 0.02, Rotation.from_rotvec([0.4, -1.0, 0.3]).as_matrix(), np.array([3.0, -1.0, 2.0])
    sfm = {}
    for i, n in enumerate(names):
        bend = Rotation.from_rotvec(np.deg2rad(6.0) * np.array([np.cos(phi[i]), 0.5 * np.sin(2 * phi[i]), 0.3]))
        R = bend.as_matrix() @ truth["Rs"][i]  # smooth 6 deg bend of the orbit (SfM's systematic error)
        c = truth["centres"][i] + 20.0 * np.array([np.sin(phi[i]), 0.0, np.cos(3 * phi[i])])
        Rb, cb = R @ Q.T, s * Q @ c + p  # expressed in an arbitrary SfM frame
        sfm[n] = (Rb, -Rb @ cb)
    return design, truth, names, sfm


def test_fuse_with_design_keeps_view_to_view_detail_and_drops_the_smooth_bend() -> None:
    """SfM poses = truth bent smoothly along the orbit, in another Sim(3) frame; design = truth + white jitter.
    Fusing takes the bend (and the frame) from the design and the per-view jitter from SfM."""
    from ctsplat.sfm.align import fuse_with_design

    design, truth, names, sfm = bent_sfm_orbit()
    raw, _ = evaluate_poses(sfm, names, truth["Rs"], truth["ts"], threshold_mm=10.0)
    fused = fuse_with_design(sfm, names, design["Rs"], design["ts"], design["azimuth_deg"], 3)
    rows, _ = evaluate_poses(fused, names, truth["Rs"], truth["ts"], threshold_mm=10.0)
    des, _ = evaluate_poses({n: (design["Rs"][i], design["ts"][i]) for i, n in enumerate(names)}, names,
                            truth["Rs"], truth["ts"], threshold_mm=10.0)
    err = np.median([r["rot_err_deg"] for r in rows])
    assert np.median([r["rot_err_deg"] for r in raw]) > 3.0
    assert np.median([r["rot_err_deg"] for r in des]) > 0.8
    assert err < 0.35 * np.median([r["rot_err_deg"] for r in des])  # only the jitter's smooth part remains
    # with no harmonics to remove beyond the mean, a bent SfM orbit stays bent
    mean_only = fuse_with_design(sfm, names, design["Rs"], design["ts"], design["azimuth_deg"], 0)
    rows0, _ = evaluate_poses(mean_only, names, truth["Rs"], truth["ts"], threshold_mm=10.0)
    assert np.median([r["rot_err_deg"] for r in rows0]) > 2.0


def test_robust_fusion_leaves_out_views_sfm_placed_wrongly_and_keeps_the_rest_as_without_them() -> None:
    """Three views SfM got wrong (a centre 150 mm off, a rotation 25 deg off, both): the robust fusion leaves
    exactly them out and fuses the others as it would without them; the plain fusion spreads their error."""
    from ctsplat.sfm.align import fuse_with_design

    design, truth, names, sfm = bent_sfm_orbit()
    bad = {"v10": (0.0, 150.0), "v47": (25.0, 0.0), "v90": (40.0, 300.0)}
    wrong = dict(sfm)
    for n, (deg, mm) in bad.items():
        R, t = sfm[n]
        c = camera_center(R, t) + 0.02 * mm * np.array([0.6, 0.0, 0.8])  # the SfM frame's scale is 0.02
        Rw = Rotation.from_rotvec(np.deg2rad(deg) * np.array([0.0, 0.6, 0.8])).as_matrix() @ R
        wrong[n] = (Rw, -Rw @ c)
    args = (names, design["Rs"], design["ts"], design["azimuth_deg"], 3)
    def median_errors(fused):  # (deg, mm) over the views SfM got right
        rows, _ = evaluate_poses(fused, names, truth["Rs"], truth["ts"], threshold_mm=10.0)
        good = [r for r in rows if r["name"] not in bad]
        return np.median([r["rot_err_deg"] for r in good]), np.median([r["centre_err_mm"] for r in good])

    robust = fuse_with_design(wrong, *args, threshold_mm=10.0, threshold_deg=1.0)
    assert set(robust) == set(names) - set(bad)
    clean = median_errors(fuse_with_design({n: sfm[n] for n in names if n not in bad}, *args))
    rot, centre = median_errors(robust)
    assert rot < 1.05 * clean[0] and centre < 1.05 * clean[1]  # as if SfM had not registered the three
    # without the thresholds the three views stay in and bend every other view's fused pose
    plain = fuse_with_design(wrong, *args)
    assert set(plain) == set(names)
    assert median_errors(plain)[0] > 1.5 * clean[0] and median_errors(plain)[1] > 1.5 * clean[1]
    # few views for the basis: none left out (the L1 fit passes through most of them, so their median says
    # nothing); SfM exact here, the design 1 deg off per view
    for n_views, seed in ((16, 0), (25, 0), (25, 3)):  # each left 3-4 correct views out without that rule
        few = design_orbit(n_views, 360.0, 15.0, 2.0, 500.0)
        exact = design_orbit(n_views, 360.0, 15.0, 2.0, 500.0, jitter_deg=1.0, seed=seed)
        few_names = [f"v{i}" for i in range(n_views)]
        exact_poses = {n: (exact["Rs"][i], exact["ts"][i]) for i, n in enumerate(few_names)}
        kept = fuse_with_design(exact_poses, few_names, few["Rs"], few["ts"], few["azimuth_deg"], 6,
                                threshold_mm=10.0, threshold_deg=1.15)
        assert set(kept) == set(few_names), (n_views, seed)
    # no outliers: the robust fusion keeps every view and scores as the plain one
    same = fuse_with_design(sfm, *args, threshold_mm=10.0, threshold_deg=1.0)
    assert set(same) == set(names)
    np.testing.assert_allclose(median_errors(same), median_errors(fuse_with_design(sfm, *args)), rtol=0.05)


def test_feature_masks_keep_the_support_shrunk_by_the_margin() -> None:
    """A disc of radius 20 px with a faint halo below the background threshold: features are kept exactly where a
    pixel lies more than `margin_px` inside the disc (the distance to the disc's edge, written out), in every
    view of a stack; no margin keeps everything."""
    yy, xx = np.mgrid[0:64, 0:80].astype(float)
    r = np.hypot(yy - 30.0, xx - 44.0)
    disc = np.where(r <= 20.0, 1.0 - r / 40.0, 0.01)  # halo 0.01 < 0.02 x max
    masks = feature_masks(np.stack([disc, disc[:, ::-1]]), background_frac=0.02, margin_px=4.0)
    assert masks.shape == (2, 64, 80) and set(np.unique(masks)) == {0, 255}
    inside = r <= 20.0
    # distance from a pixel centre of the disc to its nearest pixel outside, to within the pixel grid (1 px)
    keep = masks[0] == 255
    assert keep[r < 20.0 - 4.0 - 1.0].all() and not keep[r > 20.0 - 4.0 + 1.0].any()
    assert not keep[~inside].any()
    np.testing.assert_array_equal(masks[1], masks[0][:, ::-1])
    assert (feature_masks(disc, 0.02, 0.0) == 255).all()
    # the image border counts as background: a support touching it is eroded from there too
    edge = feature_masks(np.ones((10, 10)), 0.02, 2.0)[0] == 255
    assert edge[2:8, 2:8].all() and not edge[:2].any() and not edge[:, -2:].any()


def test_sfm_refuses_an_output_folder_with_files_it_does_not_write(tmp_path) -> None:
    # the step replaces images/, the model and its tables in place: a folder of someone else's that happens to
    # hold a summary.json is refused before anything is read or removed
    from ctsplat.sfm.step import run_sfm

    out = tmp_path / "project"
    (out / "images").mkdir(parents=True)
    (out / "images" / "IMG_001.jpg").write_bytes(b"mine")
    (out / "summary.json").write_text('{"mine": 1}')
    with pytest.raises(CtsplatError, match=r"project holds images/IMG_001\.jpg, which this step does not write, "
                       r"and its outputs would be mixed with it"):
        run_sfm(tmp_path / "radiographs", out)
    with pytest.raises(CtsplatError, match=r"is, or holds, the input"):
        run_sfm(out, out)
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        "images", "images/IMG_001.jpg", "summary.json"]
    assert (out / "summary.json").read_text() == '{"mine": 1}'


@pytest.mark.parametrize(("key", "value"), [("min_num_inliers", 0), ("init_min_num_inliers", 0),
                                            ("abs_pose_min_num_inliers", 0), ("triangulation_min_angle_deg", 0),
                                            ("peak_threshold", 0)])
def test_values_colmap_refuses_are_refused_by_the_schema(key: str, value: float) -> None:
    from ctsplat.config import check_section

    with pytest.raises(CtsplatError, match=rf"sfm\.{key}"):
        check_section("sfm", {key: value})


def test_colmap_errors_become_one_line_naming_the_images() -> None:
    from ctsplat.sfm.colmap import colmap_errors

    with pytest.raises(CtsplatError, match=r"COLMAP failed on imgs: \[incremental_pipeline\.cc:350\] Check failed: "
                                           r"options_->Check\(\); check the sfm settings$"):
        with colmap_errors("imgs"):
            raise ValueError("[incremental_pipeline.cc:350] Check failed: options_->Check()\n  stack")
    with pytest.raises(CtsplatError, match=r"^ours$"), colmap_errors("imgs"):
        raise CtsplatError("ours")  # ctsplat's own errors pass unchanged
