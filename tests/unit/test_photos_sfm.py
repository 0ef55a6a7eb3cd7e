"""COLMAP on a subset of the real skull photographs (../shared/data/skull_photos, CC BY 4.0, "Photogrammetry Test
Set: Skull - Cameramoves - Flash - No Background" by alansartlog): ten neighbouring photos (three rings of the
capture, at the set's 1068x712, a quarter of the originals) register in one model and load as training data.
Skipped with a reason when the data is absent."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ctsplat.photos.config import photo_settings
from ctsplat.photos.dataset import load_scene, scene_extent
from ctsplat.photos.sfm import run_photo_sfm
from ctsplat.utils import CtsplatError

sys.path.insert(0, str(Path(__file__).parent))
from test_photos import _jpeg  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SKULL = Path(os.environ.get("CTSPLAT_SHARED_DATA", ROOT.parent / "shared" / "data")) / "skull_photos"
# the ten camera centres nearest to 38.jpg's in a model of the whole set: one side of the skull seen from the
# three heights of the capture (at lower resolution, e.g. 512 px, they fall apart into several small models)
NEIGHBOURS = [f"{i:02d}.jpg" for i in (19, 20, 21, 36, 37, 38, 39, 54, 55, 56)]


@pytest.fixture(scope="module")
def skull_subset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not SKULL.is_dir():
        pytest.skip(f"skull photos not found at {SKULL} (expected ../shared/data/skull_photos)")
    folder = tmp_path_factory.mktemp("skull10")
    for name in NEIGHBOURS[1:]:
        (folder / name).symlink_to(SKULL / name)
    # the first photo carries an owner's EXIF (inserted without touching its pixels), which no output may keep
    data = (SKULL / NEIGHBOURS[0]).read_bytes()
    exif = Image.Exif()
    exif[0x013B] = "Jane Photographer"  # Artist
    exif[0x8298] = "(c) Jane Photographer"  # Copyright
    payload = b"Exif\x00\x00" + exif.tobytes()
    (folder / NEIGHBOURS[0]).write_bytes(data[:2] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
                                         + data[2:])
    with Image.open(folder / NEIGHBOURS[0]) as im:
        assert im.getexif().get(0x013B) == "Jane Photographer"
    return folder


def test_ten_neighbouring_skull_photos_register_in_one_model(skull_subset: Path, tmp_path: Path) -> None:
    out = tmp_path / "sfm"
    summary = run_photo_sfm(skull_subset, out, {"num_threads": 2})
    assert summary["n_images"] == 10
    assert summary["n_registered"] >= 9, summary["unregistered"]
    assert sorted(summary["registered"] + summary["unregistered"]) == NEIGHBOURS
    assert summary["matching"] == "exhaustive"
    assert 0 < summary["mean_reprojection_error_px"] < 1.5
    assert summary["n_points"] > 300
    assert json.loads((out / "summary.json").read_text())["n_registered"] == summary["n_registered"]
    for f in ("cameras.bin", "images.bin", "points3D.bin", "text/cameras.txt"):
        assert (out / "sparse" / "0" / f).is_file()
    assert "PINHOLE" in (out / "sparse" / "0" / "text" / "cameras.txt").read_text()
    assert len(list((out / "images").iterdir())) == summary["n_registered"]
    for image in (out / "images").iterdir():  # the undistorted copies keep no EXIF
        assert b"Jane Photographer" not in image.read_bytes(), image.name
    assert not (out / "work").exists()

    scene = load_scene(out, downscale=4, test_every=8)
    assert [v.name for v in scene.split("test")] == [v.name for v in scene.views[::8]]
    fold = load_scene(out, downscale=8, test_every=4, validation=True, validation_offset=3)
    assert [v.name for v in fold.split("val")] == [v.name for v in fold.views[3::4]]
    assert [v.name for v in fold.split("test")] == [v.name for v in fold.views[::4]]
    # the scene radius (learning rate, densification thresholds) is the training cameras' alone, as in 3DGS
    for sc in (scene, fold):
        assert sc.extent == scene_extent([v.R for v in sc.split("train")], [v.t for v in sc.split("train")])
        assert abs(sc.extent - scene_extent([v.R for v in sc.views], [v.t for v in sc.views])) > 1e-3
    v = scene.views[0]
    assert tuple(v.image.shape) == (v.camera.height, v.camera.width, 3)
    assert 0.8 * 1068 / 4 < v.camera.width <= 1068 / 4 + 1
    # the SfM points project inside the photos that see them (poses and intrinsics agree)
    x = scene.xyz @ v.R.T + v.t
    uv = x[:, :2] / x[:, 2:] * [v.camera.fx, v.camera.fy] + [v.camera.cx, v.camera.cy]
    inside = (x[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < v.camera.width) & (uv[:, 1] >= 0) \
        & (uv[:, 1] < v.camera.height)
    assert np.mean(inside) > 0.5
    assert scene.rgb.min() >= 0 and scene.rgb.max() <= 1 and scene.rgb.std() > 0.02  # coloured points
    # every observation of the undistorted model, projected with the cameras and poses load_scene hands the renderer,
    # lands where COLMAP measured it (its keypoints): at full size and at a quarter (the keypoints scaled per axis)
    import pycolmap

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    by_name = {img.name: img for img in rec.images.values()}
    for factor in (1, 4):
        errors = []
        for view in load_scene(out, downscale=factor).views:
            img = by_name[view.name]
            obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in img.points2D if p.has_point3D()]
            xy = np.array([o[0] for o in obs]) * [view.camera.width / img.camera.width,
                                                  view.camera.height / img.camera.height]
            xc = np.array([o[1] for o in obs]) @ view.R.T + view.t
            uv = xc[:, :2] / xc[:, 2:] * [view.camera.fx, view.camera.fy] + [view.camera.cx, view.camera.cy]
            errors.append(np.linalg.norm(uv - xy, axis=1))
        err = np.concatenate(errors)
        assert np.median(err) < 0.5 / factor and np.percentile(err, 90) < 1.5 / factor, (factor, np.median(err))
    # a model file missing or cut short is named in one line, with what to do
    import shutil

    for name, cut, needle in (("points3D.bin", None, r"lacks points3D\.bin; run `ctsplat photos-sfm` again"),
                              ("images.bin", None, r"lacks images\.bin"),
                              ("images.bin", 0.5, r"cannot read the SfM model in .*photos-sfm` again"),
                              ("points3D.bin", 0.5, r"cannot read the SfM model in .*photos-sfm` again")):
        damaged = tmp_path / f"damaged_{name}_{cut}"
        shutil.copytree(out, damaged)
        model = damaged / "sparse" / "0" / name
        if cut is None:
            model.unlink()
        else:
            model.write_bytes(model.read_bytes()[:int(cut * model.stat().st_size)])
        with pytest.raises(CtsplatError, match=needle):
            load_scene(damaged, downscale=8)
    broken = sorted((out / "images").iterdir())[0]  # a truncated or damaged copy is named with what to do
    data = broken.read_bytes()
    broken.write_bytes(data[:2000])
    with pytest.raises(CtsplatError, match=rf"corrupt or truncated SfM image .*{broken.name}: .*photos-sfm` again"):
        load_scene(out, downscale=4)
    mid = len(data) // 2
    broken.write_bytes(data[:mid] + b"\xff\xd9" * 100 + data[mid + 200:])
    with pytest.raises(CtsplatError, match=rf"SfM image .*{broken.name}: Corrupt JPEG data.*photos-sfm` again"):
        load_scene(out, downscale=4)


def test_a_camera_per_photo_summary_describes_one_photo(skull_subset: Path, tmp_path: Path) -> None:
    """With ``camera_mode: per_image`` every photo has its own focal length; the summary's undistorted camera and
    COLMAP's estimate are both the first registered photo's."""
    import pycolmap

    summary = run_photo_sfm(skull_subset, tmp_path / "sfm", {"num_threads": 2, "camera_mode": "per_image"})
    rec = pycolmap.Reconstruction(str(tmp_path / "sfm" / "sparse" / "0"))
    first = min((img for img in rec.images.values() if img.has_pose), key=lambda img: img.name)
    assert summary["camera_of"] == first.name == summary["registered"][0]
    assert summary["camera"]["fx"] == pytest.approx(float(rec.cameras[first.camera_id].params[0]), rel=1e-12)
    focals = {round(float(c.params[0]), 3) for c in rec.cameras.values()}
    assert len(focals) > 1  # the cameras differ, so picking another photo's would show
    # the undistorter keeps the focal length: the estimate is of the same photo
    assert summary["estimated_camera"]["params"][0] == pytest.approx(summary["camera"]["fx"], rel=1e-9)


def test_the_same_photos_give_the_same_model(skull_subset: Path, tmp_path: Path) -> None:
    """Two runs on the same photos write identical models, and COLMAP's image ids follow the names (with parallel
    extraction they follow the threads' finishing order, and the model changes from run to run)."""
    import pycolmap

    for name in ("a", "b"):
        run_photo_sfm(skull_subset, tmp_path / name, {"num_threads": 2})
    for f in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (tmp_path / "a/sparse/0" / f).read_bytes() == (tmp_path / "b/sparse/0" / f).read_bytes(), f
    rec = pycolmap.Reconstruction(str(tmp_path / "a/sparse/0"))
    assert all(NEIGHBOURS[img.image_id - 1] == img.name for img in rec.images.values())


def test_workflow_runs_a_photo_volume_beside_the_ct_grid(skull_subset: Path, tmp_path: Path) -> None:
    """The photo rules (real Snakemake process) pose, train and evaluate a photo volume; the CT grid never
    schedules a job for it."""
    import subprocess
    import sys

    import yaml

    cfg = {"volumes": {"phantom": {"source": "phantom", "phantom": {"size": 32}},
                       "skull": {"source": str(skull_subset), "kind": "photos"}},
           "photos": {"train": {"iterations": 20, "log_every": 10, "downscale": 8},
                      "evaluate": {"turntable_frames": 2, "gallery_views": 2, "attribution": "alansartlog, CC BY 4.0"}},
           "preprocessing": {"grid": 32}, "radiographs": {"circular": {"detector_width": 32, "detector_height": 32,
                                                                        "n_views": 12}},
           "baselines": {"enabled": False}, "sfm": {"enabled": False},
           "grid": {"axes": {"init": ["uniform"], "compositor": ["radiative"], "mip": ["on"], "poses": ["gt"],
                             "views": [8], "seed": [0]}}}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    base = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(tmp_path), "--cores", "2"]
    cfg_arg = ["--configfile", str(tmp_path / "config.yaml")]  # list-valued: targets go before it
    dry = subprocess.run([*base, "-n", *cfg_arg], capture_output=True, text=True, env=env, timeout=300)
    assert dry.returncode == 0, dry.stderr[-3000:]
    blocks = re.split(r"\n(?:local)?rule ", dry.stdout)
    skull_rules = {b.split(":", 1)[0] for b in blocks if "volume=skull" in b}
    assert skull_rules == {"photos_sfm", "photos_train", "photos_evaluate"}  # no CT rule for the photo volume
    run = subprocess.run([*base, "results/skull/photos/run/metrics.json", *cfg_arg], capture_output=True, text=True,
                         env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-4000:]
    metrics = json.loads((tmp_path / "results/skull/photos/run/metrics.json").read_text())
    assert metrics["sfm"]["n_registered"] >= 9 and metrics["n_test"] == 2 and metrics["psnr"] > 10
    assert metrics["attribution"] == "alansartlog, CC BY 4.0"
    # the memory reported is the training job's (the evaluation ran in its own process, reported beside it)
    training = json.loads((tmp_path / "results/skull/photos/run/training.json").read_text())
    assert metrics["peak_rss_mb"] == training["peak_rss_mb"] > 0 and metrics["eval_peak_rss_mb"] > 0
    for f in ("figures/gallery.png", "figures/turntable.gif", "train_log.csv", "model.ply"):
        assert (tmp_path / "results/skull/photos/run" / f).is_file()
    from ctsplat.formats.ply import read_ply_vertices

    assert "density" not in read_ply_vertices(tmp_path / "results/skull/photos/run/model.ply")  # alpha: plain 3DGS
    assert not (tmp_path / "results/phantom").exists()  # only the photo target was asked for


def test_fold_benchmark_pairs_real_runs_and_reuses_them(skull_subset: Path, tmp_path: Path) -> None:
    """``benchmarks/photo_folds.py`` trains default and candidate on each fold (real ``photos-train`` processes),
    scores only that fold's photos, and a second call with one more fold trains only the new pair."""
    import subprocess
    import sys

    import pandas as pd

    from ctsplat.photos.dataset import split_names

    sfm = tmp_path / "sfm"
    run_photo_sfm(skull_subset, sfm, {"num_threads": 2})
    out = tmp_path / "folds"
    base = ["--base", "train.iterations=20", "--base", "train.log_every=10", "--base", "train.downscale=8",
            "--base", "train.test_every=4", "--base", "evaluate.turntable_frames=2",
            "--base", "evaluate.gallery_views=1"]
    cmd = [sys.executable, str(ROOT / "benchmarks" / "photo_folds.py"), "--sfm", str(sfm), "--out", str(out), *base,
           "--candidate", "train.sh_degree=0", "--seeds", "0"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    first = subprocess.run([*cmd, "--folds", "1"], capture_output=True, text=True, env=env, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    stamp = (out / "fold1_seed0_default" / "training.json").stat().st_mtime_ns
    second = subprocess.run([*cmd, "--folds", "1", "3"], capture_output=True, text=True, env=env, timeout=600)
    assert second.returncode == 0, second.stderr[-3000:]
    assert (out / "fold1_seed0_default" / "training.json").stat().st_mtime_ns == stamp  # kept, not retrained
    import torch

    made = json.loads((out / "fold1_seed0_default" / "training.json").read_text())["platform"]
    assert made["threads"] == 1 and made["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    summary = json.loads(second.stdout.strip().splitlines()[-1])
    assert summary == json.loads((out / "summary.json").read_text())
    assert summary["psnr"]["n"] == 2 and summary["psnr"]["verdict"] in ("tie", "candidate", "default")
    pairs = pd.read_csv(out / "pairs.csv")
    assert pairs["difference_db"].tolist() == pytest.approx(summary["psnr"]["differences"])
    names = sorted(p.name for p in (sfm / "images").iterdir())
    photos = pd.read_csv(out / "per_photo.csv")
    for fold in (1, 3):
        val = sorted(n for n, s in split_names(names, 4, validation=True, validation_offset=fold).items()
                     if s == "val")
        assert sorted(photos.loc[photos["fold"] == fold, "photo"]) == val
    from ctsplat.utils import code_version

    # every run's code is recorded; a kept run of another code is reused (its settings are the same) but named
    assert summary["run_code_versions"] == [code_version()] and "another code" not in second.stderr
    assert set(pairs["default_code_version"]) == set(pairs["candidate_code_version"]) == {code_version()}
    kept = out / "fold1_seed0_default" / "config.json"
    kept.write_text(json.dumps({**json.loads(kept.read_text()), "code_version": "0123abc"}))
    third = subprocess.run([*cmd, "--folds", "1", "3"], capture_output=True, text=True, env=env, timeout=600)
    assert third.returncode == 0, third.stderr[-3000:]
    assert "1 of 4 runs were trained by another code than this one" in third.stderr
    assert "fold1_seed0_default;" in third.stderr
    assert json.loads(third.stdout.strip().splitlines()[-1])["run_code_versions"] == sorted(["0123abc",
                                                                                             code_version()])
    pairs = pd.read_csv(out / "pairs.csv").set_index("fold")
    assert pairs.loc[1, "default_code_version"] == "0123abc" and pairs.loc[3, "default_code_version"] == code_version()
    cfg = json.loads((out / "fold3_seed0_candidate" / "config.json").read_text())["train"]
    assert cfg["validation_offset"] == 3 and cfg["sh_degree"] == 0 and cfg["num_threads"] == 1
    clash = subprocess.run([*cmd[:-4], "--candidate", "train.sh_degree=1", "--seeds", "0", "--folds", "1"],
                           capture_output=True, text=True, env=env, timeout=600)
    assert clash.returncode == 2 and "holds a run with other settings" in clash.stderr.strip().splitlines()[-1]
    # a kept run is compared on every setting, not only the ones this call sets: a --base left out (the default
    # 6000 iterations against the kept 20) or another SfM folder is refused before any training
    import shutil

    shutil.copytree(sfm, tmp_path / "sfm_copy")
    k = cmd.index("train.iterations=20")
    for changed in (cmd[:k - 1] + cmd[k + 1:], [str(tmp_path / "sfm_copy") if c == str(sfm) else c for c in cmd]):
        refused = subprocess.run([*changed, "--folds", "1"], capture_output=True, text=True, env=env, timeout=600)
        assert refused.returncode == 2, refused.stderr[-2000:]
        assert "other settings or another SfM folder" in refused.stderr.strip().splitlines()[-1]
    # which Gaussians the held-out photos fail on, for one of these runs: every validation photo, its PSNR as the
    # evaluation scored it, and the named Gaussians in order of their removal gain
    run = out / "fold1_seed0_default"
    blame = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "photo_blame.py"), str(run), "--top", "2"],
                           capture_output=True, text=True, env=env, timeout=600)
    assert blame.returncode == 0, blame.stderr[-3000:]
    table = pd.read_csv(run / "blame.csv")
    scored = pd.read_csv(run / "per_view_test.csv").set_index("view_id")["psnr2d"]
    assert sorted(set(table["photo"])) == sorted(scored.index)
    for photo, rows in table.groupby("photo"):
        assert rows["rank"].tolist() == [1, 2] and rows["gain"].is_monotonic_decreasing
        assert rows["psnr"].iloc[0] == pytest.approx(scored[photo], abs=1e-4)
    # a run trained on another kind of CPU rounds differently and is not paired with runs made here
    made_file = out / "fold1_seed0_default" / "training.json"
    made_file.write_text(json.dumps({**json.loads(made_file.read_text()), "platform": {"cpu_capability": "OTHER"}}))
    other = subprocess.run([*cmd, "--folds", "1"], capture_output=True, text=True, env=env, timeout=600)
    assert other.returncode == 2
    assert "was trained on a OTHER CPU" in other.stderr.strip().splitlines()[-1]


# ---------------------------------------------------------------------- summary and matching rules
@pytest.mark.parametrize(("n", "want"), [(120, "exhaustive"), (121, "sequential"), (3, "exhaustive")])
def test_auto_matching_is_exhaustive_up_to_and_including_the_limit(n: int, want: str) -> None:
    """matching auto: exhaustive for n ≤ exhaustive_max_images (120), sequential above."""
    from ctsplat.photos.sfm import matching_mode

    s = photo_settings()["sfm"]
    assert s["exhaustive_max_images"] == 120
    assert matching_mode(s, n) == want


def test_sfm_summary_registration_rate_counts_the_unregistered_photos(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """registration_rate = registered / photos (3 of 5 = 0.6) with the two others listed as unregistered; COLMAP
    is replaced by a model that registers 3 of the 5 photos (the summary is what is tested)."""
    import shutil
    from types import SimpleNamespace

    import ctsplat.photos.sfm as sfm

    photos = tmp_path / "photos"
    photos.mkdir()
    names = [f"{i:02d}.jpg" for i in range(5)]
    for i, name in enumerate(names):
        _jpeg(photos / name, seed=i)
    registered = ["00.jpg", "02.jpg", "03.jpg"]
    cam = SimpleNamespace(model=SimpleNamespace(name="PINHOLE"), params=np.array([60.0, 60.0, 32.0, 24.0]),
                          width=64, height=48)
    model = SimpleNamespace(
        images={i: SimpleNamespace(name=n, has_pose=True, camera_id=1) for i, n in enumerate(registered)},
        cameras={1: cam}, num_reg_images=lambda: len(registered), write_binary=lambda path: None,
        compute_mean_reprojection_error=lambda: 0.5, compute_mean_track_length=lambda: 3.0,
        num_points3D=lambda: 100)

    def undistort(out: Path, sparse: Path, image_dir: Path, num_threads: int) -> None:
        (out / "images").mkdir(parents=True)
        for n in registered:
            shutil.copy(image_dir / n, out / "images" / n)

    monkeypatch.setattr(sfm, "_extract_and_match", lambda *a: "exhaustive")
    monkeypatch.setattr(sfm, "_map", lambda *a: {0: model})
    monkeypatch.setattr(sfm, "write_model", lambda *a: None)
    monkeypatch.setattr(sfm, "pycolmap", SimpleNamespace(undistort_images=undistort, Reconstruction=lambda p: model))
    summary = sfm.run_photo_sfm(photos, tmp_path / "sfm")
    assert (summary["n_images"], summary["n_registered"]) == (5, 3)
    assert summary["registered"] == registered and summary["unregistered"] == ["01.jpg", "04.jpg"]
    assert summary["registration_rate"] == pytest.approx(3 / 5, rel=1e-12)
    assert json.loads((tmp_path / "sfm" / "summary.json").read_text())["registration_rate"] == pytest.approx(0.6)


def test_the_skull_photos_are_not_damaged() -> None:
    """Every photo of the real set passes the strict JPEG decode: the damage check refuses no real camera file."""
    from ctsplat.photos.images import jpeg_damage, list_photos

    if not SKULL.is_dir():
        pytest.skip(f"skull photos not found at {SKULL} (expected ../shared/data/skull_photos)")
    names = list_photos(SKULL)
    assert len(names) == 66
    assert [n for n in names if jpeg_damage((SKULL / n).read_bytes()) is not None] == []
