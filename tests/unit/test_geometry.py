"""Geometry: camera models, poses, COLMAP conversions, orbits, splits, view-set JSON, field-of-view checks."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ctsplat.formats.viewset import VIEWSET_FORMAT_VERSION, View, ViewSet
from ctsplat.geometry import (
    ConeCamera,
    ParallelCamera,
    Rt_from_c2w,
    assign_splits,
    c2w_from_Rt,
    camera_center,
    camera_rays,
    camera_to_world,
    check_fov,
    circular_orbit,
    fov_outside_fraction,
    opencv_to_opengl_c2w,
    pose_from_angles,
    project_points,
    qvec_to_rotmat,
    rotmat_to_qvec,
    sphere_orbit,
    split_counts,
    world_to_camera,
)
from ctsplat.projector import line_integrals
from ctsplat.utils import CtsplatError

ISO = np.array([12.0, -30.0, 150.0])


def random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    return R, rng.normal(0, 100, 3)


@pytest.mark.parametrize("camera", [ParallelCamera(40, 30, 1.3), ConeCamera(40, 30, 0.9, 500.0, 800.0)],
                         ids=["parallel", "cone"])
def test_rays_hit_their_pixel_centres(camera):
    """A point anywhere along a pixel's ray projects back to that pixel's centre (u + 0.5, v + 0.5)."""
    rng = np.random.default_rng(0)
    R, t = random_pose(rng)
    origins, dirs = camera_rays(camera, R, t)
    assert origins.shape == dirs.shape == (30, 40, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-12)
    s = rng.uniform(10, 900, size=(30, 40, 1))
    pts = (origins + s * dirs).reshape(-1, 3)
    uv, depth = project_points(camera, R, t, pts)
    v, u = np.meshgrid(np.arange(30) + 0.5, np.arange(40) + 0.5, indexing="ij")
    np.testing.assert_allclose(uv[:, 0], u.ravel(), atol=1e-8)
    np.testing.assert_allclose(uv[:, 1], v.ravel(), atol=1e-8)
    assert np.all(depth > 0)


def test_parallel_rays_share_the_camera_axis_and_cone_rays_the_source():
    rng = np.random.default_rng(1)
    R, t = random_pose(rng)
    _, d = camera_rays(ParallelCamera(8, 6, 2.0), R, t)
    np.testing.assert_allclose(d, np.broadcast_to(R[2], d.shape))
    o, _ = camera_rays(ConeCamera(8, 6, 1.0, 100.0, 150.0), R, t)
    np.testing.assert_allclose(o, np.broadcast_to(-R.T @ t, o.shape))


def test_cone_intrinsics_and_magnification():
    cam = ConeCamera(64, 48, 0.5, 600.0, 900.0)
    assert cam.fx == cam.fy == pytest.approx(900.0 / 0.5)
    np.testing.assert_allclose(cam.K, [[1800, 0, 32], [0, 1800, 24], [0, 0, 1]])
    R, t = pose_from_angles(30.0, 10.0, ISO, cam.dso_mm)
    # the isocentre is on the axis at depth DSO; an offset of 1 mm there spans magnification/pitch pixels
    uv, z = project_points(cam, R, t, np.stack([ISO, ISO + R[0]]))
    np.testing.assert_allclose(z, [600.0, 600.0])
    np.testing.assert_allclose(uv[0], [32.0, 24.0], atol=1e-9)
    assert uv[1, 0] - uv[0, 0] == pytest.approx(cam.magnification / cam.pitch_mm)


def test_camera_centre_of_tensors_matches_arrays_and_carries_gradients():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(3)
    poses = [random_pose(rng) for _ in range(4)]
    Rs, ts = np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses])
    want = np.stack([world_to_camera(np.zeros(3), R.T, -R.T @ t) for R, t in poses])  # the origin seen backwards
    np.testing.assert_allclose(camera_center(Rs, ts), want, atol=1e-9)
    R_t, t_t = torch.tensor(Rs), torch.tensor(ts, requires_grad=True)
    c = camera_center(R_t, t_t)
    assert isinstance(c, torch.Tensor) and c.shape == (4, 3)
    np.testing.assert_allclose(c.detach().numpy(), want, atol=1e-9)
    np.testing.assert_allclose(camera_center(R_t[0], t_t[0]).detach().numpy(), want[0], atol=1e-9)
    (g,) = torch.autograd.grad(c[:, 0].sum(), t_t)  # dC/dt = -Rᵀ: row 0 of -Rᵀ is minus column 0 of R
    np.testing.assert_allclose(g.numpy(), -Rs[:, :, 0], atol=1e-12)


def test_world_camera_conversions_both_ways():
    rng = np.random.default_rng(2)
    R, t = random_pose(rng)
    X = rng.normal(0, 50, (100, 3))
    Xc = world_to_camera(X, R, t)
    np.testing.assert_allclose(Xc, (R @ X.T).T + t)
    np.testing.assert_allclose(camera_to_world(Xc, R, t), X, atol=1e-10)
    np.testing.assert_allclose(world_to_camera(camera_to_world(Xc, R, t), R, t), Xc, atol=1e-10)
    np.testing.assert_allclose(world_to_camera(camera_center(R, t), R, t), 0.0, atol=1e-10)
    c2w = c2w_from_Rt(R, t)
    np.testing.assert_allclose((c2w[:3, :3] @ Xc.T).T + c2w[:3, 3], X, atol=1e-10)
    R2, t2 = Rt_from_c2w(c2w)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-10)
    gl = opencv_to_opengl_c2w(c2w)
    np.testing.assert_allclose(gl[:3, 1], -c2w[:3, 1])  # y up
    np.testing.assert_allclose(gl[:3, 2], -c2w[:3, 2])  # z backward
    np.testing.assert_allclose(gl[:3, 3], c2w[:3, 3])


def test_colmap_qvec_matches_scipy_and_round_trips():
    rng = np.random.default_rng(3)
    for _ in range(20):
        R, _ = random_pose(rng)
        q = rotmat_to_qvec(R)
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        assert q[0] >= 0
        np.testing.assert_allclose(np.abs(np.dot(q, [w, x, y, z])), 1.0, atol=1e-10)
        np.testing.assert_allclose(qvec_to_rotmat(q), R, atol=1e-10)
        np.testing.assert_allclose(qvec_to_rotmat(q), Rotation.from_quat([x, y, z, w]).as_matrix(), atol=1e-10)


def test_head_is_upright_and_radiological_left_right():
    """World +z (superior) is at the image top in every view; frontal view shows the patient's right on the left."""
    up = ISO + np.array([0.0, 0.0, 40.0])
    for cam, dist in ((ParallelCamera(64, 64, 2.0), 300.0), (ConeCamera(64, 64, 2.0, 500.0, 800.0), 500.0)):
        views = sphere_orbit(40, ISO, dist, elevation_range_deg=(-70, 70), seed=0)
        views += circular_orbit(12, ISO, dist, wobble_deg=20.0)
        for v in views:
            uv, _ = project_points(cam, v.R, v.t, np.stack([ISO, up]))
            assert uv[1, 1] < uv[0, 1], (v.azimuth_deg, v.elevation_deg)
            np.testing.assert_allclose(uv[0], [32.0, 32.0], atol=1e-9)  # isocentre on the axis
            np.testing.assert_allclose(np.linalg.det(v.R), 1.0, atol=1e-12)
            np.testing.assert_allclose(v.R @ v.R.T, np.eye(3), atol=1e-12)
            # camera centre at the requested angles and distance
            c = v.center_mm - ISO
            np.testing.assert_allclose(np.linalg.norm(c), dist)
            assert np.degrees(np.arcsin(c[2] / dist)) == pytest.approx(v.elevation_deg)
    cam = ParallelCamera(64, 64, 2.0)
    right, anterior = ISO + [40.0, 0, 0], ISO + [0, 40.0, 0]
    R, t = pose_from_angles(90.0, 0.0, ISO, 300.0)  # frontal: camera anterior, looking posterior
    assert project_points(cam, R, t, right[None])[0][0, 0] < 32.0
    np.testing.assert_allclose(R[2], [0.0, -1.0, 0.0], atol=1e-12)
    R, t = pose_from_angles(0.0, 0.0, ISO, 300.0)  # lateral from the patient's right: face to the image right
    assert project_points(cam, R, t, anterior[None])[0][0, 0] > 32.0
    np.testing.assert_allclose(R[2], [-1.0, 0.0, 0.0], atol=1e-12)


def test_sphere_orbit_spreads_within_elevation_limits():
    for sampling in ("fibonacci", "stratified"):
        views = sphere_orbit(200, ISO, 400.0, elevation_range_deg=(-30, 50), sampling=sampling, seed=4)
        el = np.array([v.elevation_deg for v in views])
        az = np.array([v.azimuth_deg for v in views])
        assert el.min() >= -30 and el.max() <= 50
        # equal-area: the fraction above elevation e matches the band's area fraction
        s = np.sin(np.radians(el))
        lo, hi = np.sin(np.radians(-30)), np.sin(np.radians(50))
        for e in (-10.0, 10.0, 30.0):
            expected = (hi - np.sin(np.radians(e))) / (hi - lo)
            assert np.mean(s > np.sin(np.radians(e))) == pytest.approx(expected, abs=0.05), (sampling, e)
        counts, _ = np.histogram(az, bins=8, range=(0, 360))
        assert counts.min() >= 0.6 * 200 / 8, (sampling, counts)
        splits = [v.split for v in views]
        assert (splits.count("train"), splits.count("val"), splits.count("test")) == (140, 30, 30)


def test_circular_orbit_train_angles_even_and_heldout_random():
    views = circular_orbit(50, ISO, 400.0, seed=5)
    tr = [v for v in views if v.split == "train"]
    np.testing.assert_allclose([v.azimuth_deg for v in tr], np.arange(50) * 7.2)
    assert all(v.elevation_deg == 0 for v in views)
    val = [v.azimuth_deg for v in views if v.split == "val"]
    test = [v.azimuth_deg for v in views if v.split == "test"]
    assert len(val) == len(test) == round(50 * 15 / 70)
    # one held-out angle per equal sector, and the angles depend on the seed
    assert np.all(np.diff(np.floor(np.array(test) / (360 / len(test)))) == 1)
    other = circular_orbit(50, ISO, 400.0, seed=6)
    assert [v.azimuth_deg for v in other if v.split == "test"] != test
    wob = circular_orbit(40, ISO, 400.0, wobble_deg=10.0)
    el = np.array([v.elevation_deg for v in wob if v.split == "train"])  # train azimuths include 45, 135, ...
    assert el.max() == pytest.approx(10.0) and el.min() == pytest.approx(-10.0)
    half = circular_orbit(20, ISO, 400.0, arc_deg=180.0, seed=1)
    np.testing.assert_allclose([v.azimuth_deg for v in half if v.split == "train"], np.arange(20) * 9.0)
    assert max(v.azimuth_deg for v in half) < 180.0
    with pytest.raises(CtsplatError, match="arc_deg"):
        circular_orbit(20, ISO, 400.0, arc_deg=0.0)
    no_hold = circular_orbit(10, ISO, 400.0, split_fractions={"train": 1.0, "val": 0, "test": 0})
    assert [v.split for v in no_hold] == ["train"] * 10


def test_assign_splits_seeded_stratified_and_counts():
    views = sphere_orbit(100, ISO, 400.0, split_fractions={"train": 0.8, "val": 0.1, "test": 0.1}, seed=0)
    az = np.array([v.azimuth_deg for v in views])
    el = np.array([v.elevation_deg for v in views])
    a = assign_splits(az, el, {"train": 0.7, "val": 0.15, "test": 0.15}, seed=7)
    b = assign_splits(az, el, {"train": 0.7, "val": 0.15, "test": 0.15}, seed=7)
    c = assign_splits(az, el, {"train": 0.7, "val": 0.15, "test": 0.15}, seed=8)
    assert a == b and a != c
    assert (a.count("train"), a.count("val"), a.count("test")) == (70, 15, 15)
    # stratified: every elevation band (5 equal-area bands) holds test and val views
    band = np.minimum(((np.sin(np.radians(el)) - np.sin(np.radians(-60))) / (2 * np.sin(np.radians(60))) * 5), 4)
    for s in ("val", "test"):
        assert set(band[np.array(a) == s].astype(int)) == set(range(5)), s
    # circular: azimuth-stratified; no 90-degree arc without a test view
    ring = np.arange(40) * 9.0
    labels = np.array(assign_splits(ring, np.zeros(40), {"train": 0.5, "val": 0.25, "test": 0.25}, seed=1))
    tests = np.sort(ring[labels == "test"])
    gaps = np.diff(np.concatenate([tests, tests[:1] + 360]))
    assert gaps.max() <= 90


def test_split_counts_largest_remainder_and_empty_split_error():
    # 7 + 1.5 + 1.5: the spare view goes to the first of the tied remainders
    assert split_counts(10, {"train": 0.7, "val": 0.15, "test": 0.15}) == {"train": 7, "val": 2, "test": 1}
    assert split_counts(7, {"train": 0.6, "val": 0.2, "test": 0.2}) == {"train": 4, "val": 2, "test": 1}
    assert sum(split_counts(33, {"train": 0.7, "val": 0.15, "test": 0.15}).values()) == 33
    with pytest.raises(CtsplatError, match="split leaves '(val|test)' empty"):
        split_counts(3, {"train": 0.7, "val": 0.15, "test": 0.15})
    with pytest.raises(CtsplatError, match="empty"):
        sphere_orbit(4, ISO, 100.0)
    with pytest.raises(CtsplatError, match="split leaves 'val' empty"):
        circular_orbit(2, ISO, 100.0)
    with pytest.raises(CtsplatError, match="unknown split"):
        split_counts(10, {"train": 0.5, "holdout": 0.5})


def test_empty_view_sets_are_errors():
    with pytest.raises(CtsplatError, match="empty view set"):
        sphere_orbit(0, ISO, 100.0)
    with pytest.raises(CtsplatError, match="empty view set"):
        circular_orbit(0, ISO, 100.0)
    with pytest.raises(CtsplatError, match="empty view set"):
        ViewSet(ParallelCamera(4, 4, 1.0), [])
    vs = ViewSet(ParallelCamera(4, 4, 1.0), circular_orbit(4, ISO, 100.0, split_fractions={"train": 1}))
    with pytest.raises(CtsplatError, match="no 'test' views"):
        vs.subset("test")


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: ParallelCamera(32, 32, 0.0), "spacing_mm"),
        (lambda: ParallelCamera(32, 32, -1.0), "spacing_mm"),
        (lambda: ParallelCamera(0, 32, 1.0), "width"),
        (lambda: ConeCamera(32, 32, 0.0, 100.0, 200.0), "pitch_mm"),
        (lambda: ConeCamera(32, 32, 1.0, -100.0, 200.0), "dso_mm"),
        (lambda: ConeCamera(32, 32, 1.0, 100.0, 0.0), "dsd_mm"),
        (lambda: ConeCamera(32, 32, 1.0, 200.0, 200.0), "must be larger than dso_mm"),
        (lambda: ConeCamera(32, 32, 1.0, 300.0, 200.0), "must be larger than dso_mm"),
        (lambda: pose_from_angles(0.0, 0.0, ISO, 0.0), "distance"),
        (lambda: pose_from_angles(0.0, 90.0, ISO, 100.0), "elevation"),
        (lambda: sphere_orbit(10, ISO, 100.0, elevation_range_deg=(-95, 10)), "elevation_range_deg"),
        (lambda: ParallelCamera(float("inf"), 32, 1.0), "width must be a whole number of pixels from 1 to 65536"),
        (lambda: ParallelCamera(32, "a", 1.0), "height must be a whole number of pixels from 1 to 65536, got 'a'"),
        (lambda: ParallelCamera(True, 32, 1.0), "width must be a whole number of pixels from 1 to 65536, got True"),
        (lambda: ParallelCamera(32, 10**9, 1.0), "height must be a whole number of pixels from 1 to 65536, got 10"),
        (lambda: pose_from_angles(0.0, float("nan"), ISO, 100.0), "elevation nan deg is out of range"),
        (lambda: circular_orbit(8, ISO, 100.0, wobble_deg=float("nan")), "elevation nan deg is out of range"),
        (lambda: line_integrals(np.zeros((4, 4, 4)), np.eye(4), ParallelCamera(4, 4, 1.0), np.eye(3)[None],
                                np.zeros((2, 3))), "1 rotations but 2 translations"),
        (lambda: line_integrals(np.zeros((4, 4, 4)), np.diag([1.0, 1.0, 0.0, 1.0]), ParallelCamera(4, 4, 1.0),
                                np.eye(3)[None], np.zeros((1, 3))), "finite, invertible 4 x 4"),
    ],
)
def test_bad_geometry_is_a_clear_error(make, match):
    with pytest.raises(CtsplatError, match=match):
        make()


def test_view_set_json_round_trip_and_version(tmp_path):
    cam = ConeCamera(20, 10, 0.7, 400.0, 650.0)
    views = sphere_orbit(20, ISO, 400.0, seed=3)
    vs = ViewSet(cam, views, "abc123", ISO, {"orbit": "sphere"})
    path = tmp_path / "views.json"
    vs.save(path)
    d = json.loads(path.read_text())
    assert d["format_version"] == VIEWSET_FORMAT_VERSION and d["camera"]["fx"] == pytest.approx(650 / 0.7)
    back = ViewSet.load(path)
    assert back.camera == cam and back.volume_id == "abc123" and back.meta == {"orbit": "sphere"}
    np.testing.assert_allclose(back.Rs(), vs.Rs())
    np.testing.assert_allclose(back.ts(), vs.ts())
    np.testing.assert_allclose(back.isocenter_mm, ISO)
    assert [v.split for v in back.views] == [v.split for v in views]
    np.testing.assert_allclose(qvec_to_rotmat(d["views"][3]["qvec"]), views[3].R, atol=1e-12)
    test = back.subset("test")
    assert all(v.split == "test" for v in test.views) and len(test) == 3
    np.testing.assert_array_equal(back.indices("test"), [i for i, v in enumerate(views) if v.split == "test"])
    d["format_version"] = 99
    path.write_text(json.dumps(d))
    with pytest.raises(CtsplatError, match="format_version 99"):
        ViewSet.load(path)
    with pytest.raises(CtsplatError, match="does not exist"):
        ViewSet.load(tmp_path / "missing.json")
    with pytest.raises(CtsplatError, match="unknown split"):
        View(0, np.eye(3), np.zeros(3), 0.0, 0.0, "holdout")


def test_fov_fraction_and_warning():
    # a 20 x 20 x 20 mm cube of points viewed by a parallel detector 10 mm wide: half outside along u and v
    g = np.linspace(-9.5, 9.5, 20)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + ISO
    R, t = pose_from_angles(0.0, 0.0, ISO, 100.0)
    frac = fov_outside_fraction(ParallelCamera(10, 20, 1.0), R[None], t[None], pts)
    np.testing.assert_allclose(frac, [0.5])
    data = np.zeros((20, 20, 20), np.float32)
    data[5:15, 5:15, 5:15] = 1.0
    affine = np.eye(4)
    affine[:3, 3] = ISO - 9.5
    with pytest.warns(UserWarning, match=r"60\.0% of the object lies outside the field of view"):
        worst = check_fov(ParallelCamera(4, 40, 1.0), R[None], t[None], data, affine)
    assert worst == pytest.approx(0.6)  # 4 of 10 voxel columns inside
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_fov(ParallelCamera(12, 12, 1.0), R[None], t[None], data, affine) == 0.0
    # one corner voxel of 4097 outside: the warning names a non-zero share, not "0.0%"
    rim = np.zeros((20, 20, 20), np.float32)
    rim[2:18, 2:18, 2:18] = 1.0
    rim[0, 0, 0] = 1.0
    with pytest.warns(UserWarning, match=r"detector does not cover the volume: 0\.024% of the object"):
        assert check_fov(ParallelCamera(17, 17, 1.0), R[None], t[None], rim, affine) == pytest.approx(1 / 4097)
    # cone: points behind the source are outside
    cone = ConeCamera(1000, 1000, 1.0, 5.0, 10.0)
    R, t = pose_from_angles(0.0, 0.0, ISO, 5.0)
    assert fov_outside_fraction(cone, R[None], t[None], pts)[0] == pytest.approx(0.25)  # x > 5 mm


# ------------------------------------------------------------------------------------------ C-arm orbit
def test_arc_rule_is_shared_by_circular_and_carm_orbits() -> None:
    from ctsplat.geometry import arc_azimuths, carm_orbit

    np.testing.assert_allclose(arc_azimuths(4, 360.0), [0, 90, 180, 270])
    np.testing.assert_allclose(arc_azimuths(4, 180.0, 10.0), [10, 55, 100, 145])  # the end is not repeated
    circ = [v.azimuth_deg for v in circular_orbit(6, np.zeros(3), 500.0, arc_deg=120.0,
                                                  split_fractions={"train": 1.0})]
    carm = [v.design.azimuth_deg for v in carm_orbit(6, np.zeros(3), 500.0, arc_deg=120.0, wobble_deg=0.0)]
    np.testing.assert_allclose(circ, carm)
    with pytest.raises(CtsplatError, match="arc_deg"):
        arc_azimuths(3, 400.0)


def test_carm_orbit_design_and_true_poses() -> None:
    from ctsplat.geometry import carm_orbit, pose_from_angles

    iso = np.array([1.0, -2.0, 3.0])
    design = carm_orbit(24, iso, 500.0, wobble_deg=15.0, wobble_cycles=2.0)
    for v in design:  # no jitter: the truth is the design, on the sinusoidal wobble, looking at the isocentre
        assert v.split == "train" and v.design is not None
        np.testing.assert_allclose(v.R, v.design.R, atol=1e-12)
        assert v.elevation_deg == pytest.approx(15.0 * np.sin(np.radians(2.0 * v.azimuth_deg)))
        R, t = pose_from_angles(v.azimuth_deg, v.elevation_deg, iso, 500.0)
        np.testing.assert_allclose(v.R, R, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(v.center_mm - iso), 500.0)
    jit = carm_orbit(24, iso, 500.0, wobble_deg=15.0, jitter_deg=1.0, jitter_mm=2.0, seed=3)
    again = carm_orbit(24, iso, 500.0, wobble_deg=15.0, jitter_deg=1.0, jitter_mm=2.0, seed=3)
    np.testing.assert_array_equal(np.stack([v.R for v in jit]), np.stack([v.R for v in again]))  # seeded
    np.testing.assert_allclose(np.stack([v.design.R for v in jit]), np.stack([v.R for v in design]), atol=1e-12)
    d_az = np.array([v.azimuth_deg - v.design.azimuth_deg for v in jit])
    assert 0.3 < d_az.std() < 2.0  # N(0, 1 deg) per view
    # the whole assembly shifts: the true source still sits at DSO from its own (shifted) isocentre on the axis
    for v in jit:
        axis = v.R[2]
        c = v.center_mm
        foot = c + axis * np.dot(iso - c, axis)  # closest point of the optical axis to the design isocentre
        assert np.linalg.norm(foot - iso) < 10.0
    with pytest.raises(CtsplatError, match="n_views >= 2"):
        carm_orbit(1, iso, 500.0)
    with pytest.raises(CtsplatError, match="orbit_jitter_deg"):
        carm_orbit(4, iso, 500.0, jitter_deg=-1.0)


def test_view_set_round_trips_designed_poses(tmp_path) -> None:
    from ctsplat.geometry import carm_orbit

    views = carm_orbit(5, np.zeros(3), 400.0, jitter_deg=1.0, seed=1)
    vs = ViewSet(ConeCamera(16, 16, 1.0, 400.0, 800.0), views, "v1", np.zeros(3), {"orbit": "carm"})
    vs.save(tmp_path / "views.json")
    back = ViewSet.load(tmp_path / "views.json")
    assert back.has_design()
    np.testing.assert_allclose(back.design_Rs(), vs.design_Rs())
    np.testing.assert_allclose(back.Rs(), vs.Rs())
    assert [v.design.azimuth_deg for v in back.views] == pytest.approx([v.design.azimuth_deg for v in views])
    plain = ViewSet(vs.camera, [View(0, np.eye(3), np.zeros(3), 0.0, 0.0)], "v1")
    assert not plain.has_design()
    with pytest.raises(CtsplatError, match="orbit: carm"):
        plain.design_Rs()
