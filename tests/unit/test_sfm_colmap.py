"""End-to-end SfM with a real (tiny) pycolmap run on a C-arm view set of a bead volume, and the failure path."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pycolmap = pytest.importorskip("pycolmap")

from orbit_helpers import design_orbit  # noqa: E402

from ctsplat.formats.viewset import ViewSet  # noqa: E402
from ctsplat.formats.volume import Volume, save_volume  # noqa: E402
from ctsplat.projector import render_radiographs  # noqa: E402
from ctsplat.sfm.colmap import match_features  # noqa: E402
from ctsplat.sfm.step import SFM_DEFAULTS, run_sfm, sfm_failure  # noqa: E402
from ctsplat.utils import CtsplatError  # noqa: E402

N, SP = 40, 4.0  # 40^3 voxels of 4 mm


def _grid() -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    aff = np.diag([SP, SP, SP, 1.0])
    aff[:3, 3] = -(N - 1) / 2 * SP
    ax = np.arange(N) * SP + aff[0, 3]
    return aff, np.meshgrid(ax, ax, ax, indexing="ij")


def _bead_volume(path: Path, n_beads: int = 70, seed: int = 0) -> np.ndarray:
    """Beads of random size and density in air (no silhouette); returns their centres (mm)."""
    rng = np.random.default_rng(seed)
    aff, (X, Y, Z) = _grid()
    vol = np.zeros((N, N, N))
    centres = rng.uniform(-55.0, 55.0, (n_beads, 3))
    for c in centres:
        r = rng.uniform(0.6, 1.0) * SP
        vol += rng.uniform(0.5, 1.0) * np.exp(-((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) / (2 * r**2))
    save_volume(Volume(vol.astype(np.float32), aff, {"volume_id": "beads", "intensity": {"mu_scale_per_mm": 0.05}}),
                path)
    return centres


ORBIT = {"camera": "cone", "orbit": "carm", "n_views": 36, "arc_deg": 120.0, "wobble_deg": 15.0,
         "detector_width": 112, "detector_height": 112, "dso_mm": 300.0, "dsd_mm": 600.0}
CFG = {"pose_prior": "none", "highpass_frac": 0.03, "lowpass_px": 1.0, "percentile_low": 0.5,
       "percentile_high": 99.5, "background_frac": 0.0, "silhouette_margin_frac": 0.0,
       "max_median_rotation_error_deg": 10.0}


def _carm(volume: Path, out: Path, **over: object) -> Path:
    """The C-arm view set SfM reads, rendered by the projector as the workflow's `project` rule does."""
    render_radiographs(volume, out, {**ORBIT, **over}, seed=0)
    return out


@pytest.fixture(scope="module")
def bead_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, np.ndarray]:
    d = tmp_path_factory.mktemp("sfm_beads")
    centres = _bead_volume(d / "volume.nii.gz")
    summary = run_sfm(_carm(d / "volume.nii.gz", d / "carm"), d / "out", CFG, seed=0)
    return d / "out", summary, centres


def test_bead_views_register_in_one_model_with_accurate_poses(bead_run) -> None:
    out, s, _ = bead_run
    assert s["models_found"] >= 1
    assert s["largest_model_rate"] >= 0.9
    assert s["registration_rate"] >= 0.9
    # beads are true 3D points: COLMAP recovers the orbit (a broken pipeline gives tens of degrees; at this
    # tiny size, 112 px and f ~ 200 px, the recovered orbit is tilted by a few degrees - see benchmarks/sfm.py)
    assert s["rot_err_deg_median"] < 10.0
    assert s["centre_err_mm_median"] < 0.05 * ORBIT["dso_mm"]
    assert s["centre_err_frac_median"] == pytest.approx(s["centre_err_mm_median"] / ORBIT["dso_mm"])
    assert s["alignment_inlier_rate"] == s["alignment"]["n_inliers"] / s["alignment"]["n_used"] >= 0.5
    assert s["ok"] is True
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["registration_rate"] == pytest.approx(s["registration_rate"])
    assert on_disk["n_views"] == ORBIT["n_views"] and "code_version" in on_disk
    assert on_disk["config"]["pose_prior"] == CFG["pose_prior"]


def test_the_same_views_give_the_same_poses(bead_run, tmp_path: Path) -> None:
    """Two runs on the same radiographs recover the same poses and points (COLMAP numbers the images in name
    order)."""
    out, _, _ = bead_run
    recs = []
    for name in ("a", "b"):
        run_sfm(out.parent / "carm", tmp_path / name, CFG, seed=0)
        recs.append(pycolmap.Reconstruction(str(tmp_path / name / "sparse" / "0")))
    first, again = recs
    ids = {img.name: img.image_id for img in first.images.values()}
    assert ids == {img.name: img.image_id for img in again.images.values()}
    assert list(ids) and sorted(ids, key=ids.get) == sorted(ids)
    for img in again.images.values():
        pose = first.image(img.image_id).cam_from_world().matrix()
        np.testing.assert_array_equal(img.cam_from_world().matrix(), pose)
    assert first.num_points3D() == again.num_points3D()


def test_matching_the_same_features_again_gives_the_same_matches(bead_run, tmp_path: Path) -> None:
    """Matching one database's features over and over writes the same matches and two-view geometries each time
    (COLMAP's CPU matcher on two threads wrote other matches in about 1 of 15 runs on these radiographs)."""
    out, _, _ = bead_run
    run_sfm(out.parent / "carm", tmp_path / "kept", {**CFG, "keep_work": True}, seed=0)
    db = tmp_path / "kept" / "colmap" / "database.db"
    cfg = {**SFM_DEFAULTS, **CFG, "_seed": 0}
    names = sorted(p.name for p in (tmp_path / "kept" / "images").iterdir())
    tables = []
    for _ in range(24):  # on two threads 1 run in 15 matched otherwise: 24 runs catch that 4 times in 5
        handle = pycolmap.Database.open(str(db))
        handle.clear_matches()
        handle.clear_two_view_geometries()
        handle.close()
        match_features(db, names, cfg)
        handle = pycolmap.Database.open(str(db))
        pairs, matches = handle.read_all_matches()
        verified, geometries = handle.read_two_view_geometries()
        handle.close()
        # the database keeps the pairs in the order they were written, which parallel matching may change
        tables.append(({p: m.tobytes() for p, m in zip(pairs, matches, strict=True)},
                       {p: (g.config, g.inlier_matches.tobytes(), g.F.tobytes(), g.E.tobytes(), g.H.tobytes())
                        for p, g in zip(verified, geometries, strict=True)}))
    assert tables[0][0] and tables[0][1]
    for again in tables[1:]:
        assert again == tables[0]


def test_a_view_the_fusion_leaves_out_is_unregistered_everywhere(bead_run, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Fusion with the design (fuse_harmonics > 0) that finds an outlier: the view is listed, unregistered in
    poses.csv and left out of the written model, whose other images carry the fused poses."""
    import ctsplat.sfm.step as step

    out, _, _ = bead_run
    fused: dict = {}
    real = step.fuse_with_design

    def one_outlier(poses, *args, **kwargs):  # the robust fusion as it would leave one view out
        fused.update(real(poses, *args, **kwargs))
        fused.pop(sorted(fused)[5])
        return dict(fused)

    monkeypatch.setattr(step, "fuse_with_design", one_outlier)
    s = run_sfm(out.parent / "carm", tmp_path / "fused", {**CFG, "fuse_harmonics": 1}, seed=0)
    (left_out,) = s["fusion_outliers"]
    assert left_out not in fused and "unfused" in s
    df = pd.read_csv(tmp_path / "fused" / "poses.csv")
    assert not df.loc[df["name"] == left_out, "registered"].item()
    assert int(df["registered"].sum()) == len(fused) == s["n_registered"]
    rec = pycolmap.Reconstruction(str(tmp_path / "fused" / "sparse" / "0"))
    names = {img.name for img in rec.images.values() if img.has_pose}
    assert names == set(fused)
    for img in rec.images.values():
        if img.has_pose:
            np.testing.assert_allclose(img.cam_from_world().matrix()[:, :3], fused[img.name][0], atol=1e-9)


def test_colmap_export_is_readable_and_keeps_the_known_intrinsics(bead_run) -> None:
    out, s, _ = bead_run
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    txt = pycolmap.Reconstruction(str(out / "sparse" / "0" / "text"))
    assert rec.num_reg_images() == txt.num_reg_images() == s["model_sizes"][0]
    assert rec.num_points3D() == txt.num_points3D() > 0
    for name in ("cameras.bin", "images.bin", "points3D.bin", "text/cameras.txt", "text/images.txt",
                 "text/points3D.txt"):
        assert (out / "sparse" / "0" / name).is_file()
    (cam,) = rec.cameras.values()
    c = s["camera"]
    assert cam.model.name == "PINHOLE"
    np.testing.assert_allclose(cam.params, [c["fx"], c["fy"], c["cx"], c["cy"]], rtol=1e-9)
    assert c["fx"] == pytest.approx(ORBIT["dsd_mm"] / c["pitch_mm"])  # fx = DSD / pitch
    assert c["cx"] == ORBIT["detector_width"] / 2


def test_poses_csv_and_aligned_views_agree(bead_run) -> None:
    out, s, _ = bead_run
    df = pd.read_csv(out / "poses.csv")
    assert len(df) == ORBIT["n_views"]
    assert int(df["registered"].sum()) == s["n_registered"]
    assert df.loc[df.registered, "rot_err_deg"].notna().all()
    assert df.loc[~df.registered, "rot_err_deg"].isna().all()
    assert df["rot_err_deg"].median() == pytest.approx(s["rot_err_deg_median"])
    vs = ViewSet.load(out / "aligned_views.json")
    assert s["n_plausible"] >= 0.9 * ORBIT["n_views"]  # recovered axes point at the object
    assert sorted(v.id for v in vs.views) == sorted(df.loc[df.registered & df.plausible, "view_id"].tolist())
    orbit = design_orbit(ORBIT["n_views"], ORBIT["arc_deg"], ORBIT["wobble_deg"], 2.0, ORBIT["dso_mm"],
                         vs.isocenter_mm)
    registered = df.loc[df.registered]
    errs = [np.linalg.norm(v.center_mm - orbit["centres"][v.id]) for v in vs.views]
    np.testing.assert_allclose(errs, registered.set_index("view_id").loc[[v.id for v in vs.views], "centre_err_mm"],
                               rtol=1e-6)
    # the recovered views keep the ids and designed poses of the C-arm view set (jitter 0: design = truth)
    carm = ViewSet.load(out.parent / "carm" / "views.json")
    assert len(carm) == ORBIT["n_views"] and carm.has_design()
    np.testing.assert_allclose(carm.Rs(), orbit["Rs"], atol=1e-12)
    np.testing.assert_allclose(vs.design_Rs(), carm.design_Rs()[[v.id for v in vs.views]], atol=1e-12)


def test_aligned_points_are_in_world_mm_inside_the_volume(bead_run) -> None:
    out, _, _ = bead_run
    lines = (out / "points3d.ply").read_text().splitlines()
    n = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[-1])
    xyz = np.array([[float(v) for v in ln.split()[:3]] for ln in lines[lines.index("end_header") + 1:]])
    assert xyz.shape == (n, 3) and n == pycolmap.Reconstruction(str(out / "sparse" / "0")).num_points3D()
    half = N * SP / 2  # the volume spans [-80, 80] mm; the SfM frame itself has arbitrary scale and origin
    assert np.mean(np.all(np.abs(xyz) <= half, axis=1)) >= 0.9
    assert np.ptp(xyz, axis=0).max() > 0.3 * N * SP


def test_featureless_volume_records_failure_without_crashing(tmp_path: Path) -> None:
    aff, _ = _grid()
    empty = np.zeros((N, N, N), np.float32)  # nothing to see: no features, no registration
    save_volume(Volume(empty, aff, {"volume_id": "empty", "intensity": {"mu_scale_per_mm": 0.02}}),
                tmp_path / "empty.nii.gz")
    rad = _carm(tmp_path / "empty.nii.gz", tmp_path / "carm", n_views=8, detector_width=64, detector_height=64)
    (tmp_path / "out" / "sparse" / "0").mkdir(parents=True)  # an earlier, successful run's model and points
    (tmp_path / "out" / "sparse" / "0" / "points3D.bin").write_bytes(b"old")
    (tmp_path / "out" / "points3d.ply").write_text("old")
    s = run_sfm(rad, tmp_path / "out", CFG)
    assert not (tmp_path / "out" / "sparse" / "0").exists() and not (tmp_path / "out" / "points3d.ply").exists()
    assert s["ok"] is False
    assert s["registration_rate"] < SFM_DEFAULTS["min_registration_rate"]
    assert "registration rate" in s["reason"]
    on_disk = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert on_disk["ok"] is False
    df = pd.read_csv(tmp_path / "out" / "poses.csv")
    assert len(df) == 8
    assert json.loads((tmp_path / "out" / "aligned_views.json").read_text())["format"] == "ctsplat.viewset"


def test_bad_config_fails_fast_and_writes_nothing(tmp_path: Path) -> None:
    aff, _ = _grid()
    save_volume(Volume(np.full((N, N, N), 0.1, np.float32), aff, {}), tmp_path / "v.nii.gz")
    rad = _carm(tmp_path / "v.nii.gz", tmp_path / "carm", n_views=4, detector_width=16, detector_height=16)
    for bad, msg in (({"matching": "vocab"}, "sfm.matching"), ({"mapper": "hier"}, "sfm.mapper"),
                     ({"n_views": 3}, "sfm.n_views"), ({"naive_slices": True}, "naive_slices needs the volume")):
        with pytest.raises(CtsplatError, match=msg):
            run_sfm(rad, tmp_path / "out", bad)
    with pytest.raises(CtsplatError, match="dsd_mm"):  # the orbit's geometry is checked where it is rendered
        render_radiographs(tmp_path / "v.nii.gz", tmp_path / "bad", {**ORBIT, "dsd_mm": 100.0})
    circular = tmp_path / "circular"
    render_radiographs(tmp_path / "v.nii.gz", circular, {"n_views": 4, "detector_width": 16, "detector_height": 16})
    with pytest.raises(CtsplatError, match="cone-beam view set"):
        run_sfm(circular, tmp_path / "out", {})
    (tmp_path / "not_a_volume.nii.gz").write_text("x")
    with pytest.raises(CtsplatError, match=r"not_a_volume\.nii\.gz is not a readable NIfTI"):  # before any output
        run_sfm(rad, tmp_path / "out", {"naive_slices": True}, volume_path=tmp_path / "not_a_volume.nii.gz")
    assert not (tmp_path / "out").exists() and not (tmp_path / "bad").exists()


def test_a_run_that_fails_while_registering_leaves_no_new_folder(tmp_path: Path, monkeypatch) -> None:
    aff, _ = _grid()
    save_volume(Volume(np.full((N, N, N), 0.1, np.float32), aff, {}), tmp_path / "v.nii.gz")
    rad = _carm(tmp_path / "v.nii.gz", tmp_path / "carm", n_views=4, detector_width=16, detector_height=16)

    def fail(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("ctsplat.sfm.step.colmap_reconstruct", fail)
    with pytest.raises(OSError, match="No space left"):
        run_sfm(rad, tmp_path / "new" / "sfm", {})
    assert not (tmp_path / "new").exists()
    (tmp_path / "results").mkdir()
    with pytest.raises(OSError, match="No space left"):  # only the folders the run made go
        run_sfm(rad, tmp_path / "results" / "head" / "sfm", {})
    assert (tmp_path / "results").is_dir() and list((tmp_path / "results").iterdir()) == []
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "summary.json").write_text('{"ok": true}')
    (earlier / "aligned_views.json").write_text("{}")
    with pytest.raises(OSError, match="No space left"):
        run_sfm(rad, earlier, {})
    # the earlier run's verdict goes with the failed rerun: nothing trains on poses no summary vouches for
    assert [q.name for q in earlier.iterdir()] == ["aligned_views.json"]
    assert "does not exist" in sfm_failure(earlier / "summary.json")


def test_cli_sfm_help_and_bad_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from ctsplat.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["sfm", "--help"])
    assert exc.value.code == 0
    assert "aligned_views.json" in capsys.readouterr().out
    assert main(["sfm", str(tmp_path / "missing"), str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err


def _model(names: list[str], Rs: np.ndarray, ts: np.ndarray):  # noqa: ANN202 - pycolmap.Reconstruction
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=64, height=64, params=[100.0, 100.0, 32.0, 32.0], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    for k, (n, R, t) in enumerate(zip(names, Rs, ts, strict=True)):
        img = pycolmap.Image(name=n, camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(np.hstack([R, t[:, None]])))
    return rec


def test_reverse_depth_gives_the_weak_perspective_twin_and_twice_the_original() -> None:
    """The Necker twin: points mirrored in z, every camera at its old distance from the points' centroid, and each
    point's camera-frame x, y about the centroid unchanged (z negated), so an orthographic view cannot tell the two
    apart; reversing twice gives the model back (cameras that look at the centroid, as on a C-arm orbit)."""
    from ctsplat.sfm.colmap import model_poses, reverse_depth

    iso = np.array([0.0, 0.0, 5.0])  # off the world origin, so the mirror plane z = 0 matters
    orb = design_orbit(12, 360.0, 10.0, 2.0, 400.0, iso)
    names = [f"view_{i:04d}.png" for i in range(12)]
    rec = _model(names, orb["Rs"], orb["ts"])
    pts = np.random.default_rng(0).uniform(-20.0, 20.0, (30, 3))
    pts += iso - pts.mean(0)  # the centroid at the isocentre, which the cameras look at
    ids = [rec.add_point3D(x, pycolmap.Track()) for x in pts]
    before = model_poses(rec)
    reverse_depth(rec)
    after = model_poses(rec)
    mirror = np.diag([1.0, 1.0, -1.0])
    centroid = pts.mean(0)
    np.testing.assert_allclose(np.array([rec.points3D[i].xyz for i in ids]), pts @ mirror, atol=1e-9)
    for n in names:
        (R, t), (R2, t2) = before[n], after[n]
        c, c2 = -R.T @ t, -R2.T @ t2
        assert np.linalg.norm(c2 - mirror @ centroid) == pytest.approx(np.linalg.norm(c - centroid), rel=1e-9)
        seen, seen2 = (pts - centroid) @ R.T, (pts @ mirror - mirror @ centroid) @ R2.T
        np.testing.assert_allclose(seen2[:, :2], seen[:, :2], atol=1e-9)
        np.testing.assert_allclose(seen2[:, 2], -seen[:, 2], atol=1e-9)
    reverse_depth(rec)
    for n, (R, t) in model_poses(rec).items():
        np.testing.assert_allclose(R, before[n][0], atol=1e-9)
        np.testing.assert_allclose(t, before[n][1], atol=1e-6)


def test_fix_reversal_keeps_whichever_twin_fits_the_design() -> None:
    """A model in its depth-reversed (Necker) form is replaced by its twin, which fits the designed orbit (rotation
    error 180° before, ~0 after); a model that already fits is kept."""
    from ctsplat.sfm.colmap import fix_reversal, model_poses, reverse_depth
    from ctsplat.sfm.step import SFM_DEFAULTS

    orb = design_orbit(12, 360.0, 10.0, 2.0, 400.0)
    names = [f"view_{i:04d}.png" for i in range(12)]
    design = {n: (orb["Rs"][i], orb["ts"][i]) for i, n in enumerate(names)}
    pts = np.random.default_rng(0).uniform(-20.0, 20.0, (30, 3))
    pts -= pts.mean(0)
    models = {}
    for k, flip in enumerate((True, False)):
        rec = _model(names, orb["Rs"], orb["ts"])
        for x in pts:
            rec.add_point3D(x, pycolmap.Track())
        models[k] = reverse_depth(rec) if flip else rec
    report = fix_reversal(models, design, dict(SFM_DEFAULTS), threshold=8.0)
    assert [r["reversed"] for r in report] == [True, False]
    assert report[0]["design_rot_err_deg"] == pytest.approx(180.0, abs=1e-6)
    assert report[0]["reversed_design_rot_err_deg"] < 1e-3 and report[1]["design_rot_err_deg"] < 1e-3
    for k in (0, 1):
        for n, (R, t) in model_poses(models[k]).items():
            np.testing.assert_allclose(R, design[n][0], atol=1e-6)
            np.testing.assert_allclose(t, design[n][1], atol=1e-4)


def test_merge_models_maps_a_partial_model_into_the_largest_frame() -> None:
    from scipy.spatial.transform import Rotation

    from ctsplat.sfm.colmap import merge_models

    orb = design_orbit(15, 360.0, 10.0, 2.0, 400.0)
    names = [f"view_{i:04d}.png" for i in range(15)]
    a = _model(names[:10], orb["Rs"][:10], orb["ts"][:10])  # the largest model, in the world frame
    # model b holds views 7..14 in another frame: x_b = s Q x_w + p
    s, Q, p = 0.01, Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix(), np.array([1.0, 2.0, 3.0])
    Rb = [orb["Rs"][i] @ Q.T for i in range(7, 15)]
    cb = [s * Q @ orb["centres"][i] + p for i in range(7, 15)]
    b = _model(names[7:], np.stack(Rb), np.stack([-R @ c for R, c in zip(Rb, cb, strict=True)]))
    main, poses, report = merge_models({0: b, 1: a}, min_shared=3)
    assert main.num_reg_images() == 10
    assert report["models_found"] == 2 and report["model_sizes"] == [10, 8]
    assert report["merged"] == [{"model_size": 8, "shared": 3, "added": 5}]
    assert sorted(poses) == names
    for i, n in enumerate(names):
        R, t = poses[n]
        np.testing.assert_allclose(R, orb["Rs"][i], atol=1e-9)
        np.testing.assert_allclose(-R.T @ t, orb["centres"][i], atol=1e-6)
    # too little overlap: the partial model is reported but not merged
    _, poses2, report2 = merge_models({0: b, 1: a}, min_shared=4)
    assert report2["merged"] == [] and len(poses2) == 10


def test_exported_poses_and_points_do_not_depend_on_the_true_poses(bead_run, tmp_path: Path) -> None:
    """Training on SfM poses must use nothing the truth decided: with the true orbit turned 5° as a whole (the
    images, the design and the recovered model unchanged), the exported poses, their directions and the seed points
    are the same (aligned to the truth, they turned with it); the scores, taken after a Sim(3) to the truth, too."""
    import shutil

    from scipy.spatial.transform import Rotation

    out, s, _ = bead_run
    carm = tmp_path / "carm"
    shutil.copytree(out.parent / "carm", carm)
    doc = json.loads((carm / "views.json").read_text())
    turn = Rotation.from_euler("z", 5.0, degrees=True).as_matrix()
    for v in doc["views"]:
        v["R"] = (np.asarray(v["R"]) @ turn.T).tolist()
        v["azimuth_deg"] = float(v["azimuth_deg"]) + 5.0
    (carm / "views.json").write_text(json.dumps(doc))
    shutil.copytree(out, tmp_path / "out")  # an earlier run in the folder, with its kept COLMAP work folder
    (tmp_path / "out" / "colmap").mkdir()
    (tmp_path / "out" / "colmap" / "database.db").write_text("an earlier run's")
    other = run_sfm(carm, tmp_path / "out", CFG, seed=0)
    assert not (tmp_path / "out" / "colmap").exists()  # keep_work is off: no work folder of another run stays
    assert other["rot_err_deg_median"] == pytest.approx(s["rot_err_deg_median"], abs=1e-6)
    first, second = ViewSet.load(out / "aligned_views.json"), ViewSet.load(tmp_path / "out" / "aligned_views.json")
    assert [v.id for v in first.views] == [v.id for v in second.views]
    np.testing.assert_allclose(second.Rs(), first.Rs(), atol=1e-9)
    np.testing.assert_allclose(second.ts(), first.ts(), atol=1e-6)
    np.testing.assert_allclose([v.azimuth_deg for v in second.views], [v.design.azimuth_deg for v in first.views])
    assert (tmp_path / "out" / "points3d.ply").read_text() == (out / "points3d.ply").read_text()
