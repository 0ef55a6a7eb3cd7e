"""The photo path: bad photo folders fail with one line and leave nothing behind; alpha 3DGS with SH colour learns a
synthetic scene rendered by the renderer from known cameras; the config's ``kind: photos`` keeps photo folders
out of the CT grid."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from PIL import Image

from ctsplat.cli import main
from ctsplat.config import prepare_config
from ctsplat.geometry.cameras import camera_center, look_at
from ctsplat.photos.config import check_train_settings, photo_settings
from ctsplat.photos.dataset import PhotoScene, PhotoView, PinholeCamera, load_scene, scene_extent, split_names
from ctsplat.photos.evaluate import evaluate_photos, turntable_poses
from ctsplat.photos.images import check_photos, jpeg_damage, list_photos, load_rgb
from ctsplat.photos.sfm import run_photo_sfm
from ctsplat.photos.train import check_run, image_metrics, render_view, to_gaussians, train_photos, train_scene
from ctsplat.splat.gaussians import Gaussians
from ctsplat.utils import CtsplatError


def _jpeg(path: Path, w: int = 64, h: int = 48, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(path, quality=90)
    return path


def _nothing_written(parent: Path, out: Path) -> None:
    assert not out.exists()
    assert [p.name for p in parent.iterdir() if p.name.startswith(f".{out.name}.")] == []


# ------------------------------------------------------------------------------------------------ bad input
def test_folder_without_images_fails_naming_it(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "notes.txt").write_text("no images here")
    out = tmp_path / "sfm"
    with pytest.raises(CtsplatError, match=r"holds no images") as exc:
        run_photo_sfm(photos, out)
    assert str(photos) in str(exc.value) and "\n" not in str(exc.value)
    _nothing_written(tmp_path, out)


def test_truncated_jpeg_fails_naming_the_file(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _jpeg(photos / f"{i:02d}.jpg", seed=i)
    bad = photos / "01.jpg"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2])  # a download cut short
    out = tmp_path / "sfm"
    with pytest.raises(CtsplatError, match=r"corrupt or truncated image .*01\.jpg"):
        run_photo_sfm(photos, out)
    _nothing_written(tmp_path, out)


def _damaged(data: bytes, how: str) -> bytes:
    """JPEG ``data`` damaged inside its compressed scan (the middle of a 64 x 48 noise JPEG lies in it)."""
    b, mid = bytearray(data), len(data) // 2
    if how == "end marker":  # an end-of-image marker where scan data should be: libjpeg stops and fills grey
        b[mid:mid + 40] = b"\xff\xd9" * 20
    elif how == "zeros":  # a block of the file lost (e.g. a bad sector)
        b[mid:mid + 200] = bytes(200)
    else:  # "bytes": scattered bit rot
        rng = np.random.default_rng(1)
        for i in rng.integers(mid - 300, mid + 300, 30):
            b[i] ^= 0x5A
    return bytes(b)


@pytest.mark.parametrize("how", ["end marker", "zeros", "bytes"])
def test_jpeg_damaged_inside_fails_naming_the_file(tmp_path: Path, how: str) -> None:
    """Data damaged inside a JPEG, which libjpeg decodes by filling the rest grey and which Pillow therefore
    reads without an error, is refused before SfM with libjpeg's own warning."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _jpeg(photos / f"{i:02d}.jpg", seed=i)
    bad = photos / "01.jpg"
    clean = np.asarray(Image.open(bad).convert("RGB"), dtype=float)
    bad.write_bytes(_damaged(bad.read_bytes(), how))
    with Image.open(bad) as im:  # what makes the check needed: Pillow decodes it, differently
        im.load()
        assert np.abs(np.asarray(im.convert("RGB"), dtype=float) - clean).mean() > 1.0
    out = tmp_path / "sfm"
    with pytest.raises(CtsplatError, match=r"corrupt or truncated image .*01\.jpg: Corrupt JPEG data") as exc:
        run_photo_sfm(photos, out)
    assert "\n" not in str(exc.value)
    _nothing_written(tmp_path, out)
    with pytest.raises(ValueError, match="Corrupt JPEG data"):
        load_rgb(bad)


def test_jpeg_damage_passes_clean_jpegs_of_every_kind(tmp_path: Path) -> None:
    """Greyscale, CMYK, progressive and EXIF-bearing JPEGs, data after the end-of-image marker (camera trailers),
    bytes before it (webcams), a header warning and other formats are not damage."""
    import io

    rng = np.random.default_rng(0)
    rgb = Image.fromarray(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    kinds = {"rgb": (rgb, {}), "grey": (rgb.convert("L"), {}), "cmyk": (rgb.convert("CMYK"), {}),
             "progressive": (rgb, {"progressive": True}), "exif": (rgb, {"exif": Image.Exif()})}
    for name, (im, options) in kinds.items():
        buf = io.BytesIO()
        im.save(buf, "JPEG", quality=90, **options)
        data = buf.getvalue()
        assert jpeg_damage(data) is None, name
        assert jpeg_damage(data + b"\x00" * 512 + b"MPF trailer") is None, name
        assert jpeg_damage(data[:-2] + b"\x00" * 2 + data[-2:]) is None, name  # padding before the end marker
        assert jpeg_damage(_damaged(data, "zeros")).startswith("Corrupt JPEG data"), name
        (tmp_path / f"{name}.jpg").write_bytes(data)
    data = (tmp_path / "rgb.jpg").read_bytes()
    sos = data.index(b"\xff\xda") + 4 + 1 + 2 * data[data.index(b"\xff\xda") + 4]  # Ss, Se, AhAl follow
    assert data[sos:sos + 3] == b"\x00\x3f\x00"
    odd = data[:sos + 1] + b"\x00" + data[sos + 2:]  # Se 0 in a baseline scan: a header warning, same pixels
    with Image.open(io.BytesIO(odd)) as a, Image.open(io.BytesIO(data)) as b:
        assert np.array_equal(np.asarray(a), np.asarray(b))
    assert jpeg_damage(odd) is None
    buf = io.BytesIO()
    rgb.save(buf, "PNG")
    assert jpeg_damage(buf.getvalue()) is None
    (tmp_path / "png.png").write_bytes(buf.getvalue())
    rgb.save(tmp_path / "mpo.jpg", "MPO", save_all=True, append_images=[rgb.convert("L").convert("RGB")])
    with Image.open(tmp_path / "mpo.jpg") as im:  # two pictures in one file, which Pillow opens as MPO
        assert im.format == "MPO"
    sizes = check_photos(tmp_path, list_photos(tmp_path), single_camera=True)
    assert set(sizes.values()) == {(64, 48)} and len(sizes) == 7
    mpo = (tmp_path / "mpo.jpg").read_bytes()
    (tmp_path / "mpo.jpg").write_bytes(_damaged(mpo[: len(mpo) // 2], "zeros") + mpo[len(mpo) // 2:])
    with pytest.raises(CtsplatError, match=r"mpo\.jpg: Corrupt JPEG data"):
        check_photos(tmp_path, list_photos(tmp_path), single_camera=True)


def test_photo_listing_skips_hidden_files_and_names_the_pictures_it_does_not_read(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from ctsplat.photos.images import unread_entries

    for name in ("01.jpg", "02.JPG", "03.png"):
        _jpeg(tmp_path / name, seed=len(name))
    (tmp_path / "._01.jpg").write_bytes(b"\x00\x05\x16\x07AppleDouble")  # macOS's resource fork beside a copy
    (tmp_path / ".DS_Store").write_bytes(b"\x00")
    Image.new("RGB", (8, 8)).save(tmp_path / "04.webp")
    (tmp_path / "05.heic").write_bytes(b"\x00")
    (tmp_path / "06.jpg").symlink_to(tmp_path / "gone.jpg")
    (tmp_path / "notes.txt").write_text("not a picture")
    (tmp_path / "sub.jpg").mkdir()
    (tmp_path / "day2").mkdir()  # photos in a sub-folder are not read either: named, not dropped unsaid
    _jpeg(tmp_path / "day2" / "07.jpg", seed=7)
    with caplog.at_level("WARNING", logger="ctsplat.photos.images"):
        assert list_photos(tmp_path) == ["01.jpg", "02.JPG", "03.png"]
    assert unread_entries(tmp_path) == ["04.webp", "05.heic", "06.jpg", "day2/"]
    assert "4 entries look like photos but are not read" in caplog.text
    assert "04.webp, 05.heic, 06.jpg, day2/" in caplog.text
    check_photos(tmp_path, list_photos(tmp_path), single_camera=False)  # the hidden file is not opened


def test_sfm_refuses_a_full_disk_and_reports_colmap_failures_in_one_line(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil
    from collections import namedtuple

    import ctsplat.photos.sfm as sfm

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _jpeg(photos / f"{i:02d}.jpg", seed=i)
    need = 3 * sum(p.stat().st_size for p in photos.iterdir())
    out = tmp_path / "new" / "sfm"
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(need, 0, need - 1))
    monkeypatch.setattr(sfm, "_run", lambda *a: pytest.fail("SfM ran"))
    with pytest.raises(CtsplatError, match=rf"{tmp_path} has 0\.0 MiB free and SfM on 3 photos needs at least"):
        run_photo_sfm(photos, out)
    _nothing_written(tmp_path, tmp_path / "new")

    def fails(*args: object) -> None:
        raise RuntimeError("SQLite error [database.cc:1]: database or disk is full\nstack")

    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(need, 0, need))
    monkeypatch.setattr(sfm, "_run", fails)
    with pytest.raises(CtsplatError, match=r"COLMAP failed on .*photos: SQLite error .*disk is full; check the photos"):
        run_photo_sfm(photos, out)
    _nothing_written(tmp_path, tmp_path / "new")

    def refused(image_dir: Path, names: list[str], tmp: Path, settings: dict) -> None:
        reader = sfm.pycolmap.ImageReaderOptions()
        reader.camera_model = "NOT_A_MODEL"  # COLMAP's failed check arrives as a ValueError
        sfm.pycolmap.extract_features(tmp / "database.db", image_dir, reader_options=reader)

    monkeypatch.setattr(sfm, "_run", refused)
    with pytest.raises(CtsplatError, match=r"COLMAP failed on .*photos: .*Check failed"):
        run_photo_sfm(photos, out)
    _nothing_written(tmp_path, tmp_path / "new")


def test_mixed_sizes_need_a_camera_per_image(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    _jpeg(photos / "a.jpg", 64, 48)
    _jpeg(photos / "b.jpg", 64, 48, seed=1)
    _jpeg(photos / "c.jpg", 48, 64, seed=2)
    out = tmp_path / "sfm"
    with pytest.raises(CtsplatError, match=r"2 sizes: 2 at 64x48 \(e.g. a.jpg\); 1 at 48x64 \(e.g. c.jpg\).*per_image"):
        run_photo_sfm(photos, out)
    _nothing_written(tmp_path, out)
    sizes = check_photos(photos, list_photos(photos), single_camera=False)
    assert sizes == {"a.jpg": (64, 48), "b.jpg": (64, 48), "c.jpg": (48, 64)}


def test_too_few_registered_images_fail_with_the_count(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       capfd: pytest.CaptureFixture[str]) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):  # unrelated noise: features, but no two-view geometry between them
        _jpeg(photos / f"{i}.jpg", 160, 120, seed=10 + i)
    out = tmp_path / "sfm"
    with pytest.raises(CtsplatError, match=r"registered only 0 of 3 photos .*need >= 3"):
        run_photo_sfm(photos, out, {"num_threads": 1})
    _nothing_written(tmp_path, out)
    capfd.readouterr()
    assert main(["photos-sfm", str(photos), str(out), "--set", "sfm.num_threads=1"]) == 2
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]  # COLMAP's own log included
    assert len(err) == 1 and err[0].startswith("ctsplat photos-sfm: error: SfM registered only 0 of 3"), err
    (photos / "2.jpg").unlink()  # two photos cannot give three registered ones: said before COLMAP runs
    monkeypatch.setattr("ctsplat.photos.sfm._run", lambda *a: pytest.fail("COLMAP ran on too few photos"))
    with pytest.raises(CtsplatError, match=r"holds 2 photos; SfM needs at least 3 registered"):
        run_photo_sfm(photos, out, {"num_threads": 1})
    _nothing_written(tmp_path, out)


def test_cli_reports_one_line_and_exit_code_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    photos = tmp_path / "empty"
    photos.mkdir()
    assert main(["photos-sfm", str(photos), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("ctsplat photos-sfm: error: photo folder") and "\n" not in err
    assert main(["photos-train", str(tmp_path / "missing"), str(tmp_path / "run")]) == 2
    assert "run `ctsplat photos-sfm IMAGES OUT` first" in capsys.readouterr().err
    assert main(["photos-sfm", str(photos), str(tmp_path / "out"), "--set", "train.downscale=3"]) == 2
    assert "photos.train.downscale" in capsys.readouterr().err
    # each seed's scale comes from its three nearest neighbours: fewer than 4 points cannot seed a model
    assert main(["photos-train", str(tmp_path / "missing"), str(tmp_path / "run"), "--set", "train.max_points=3"]) == 2
    assert "photos.train.max_points: 3 is less than the minimum of 4" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("sets", "needle"), [
    (["train.holdout=validation", "train.validation_offset=9"], "validation_offset must be 1..7 (test_every 8), got 9"),
    (["train.test_every=1"], "test_every 1 holds out every photo (none is left for training)"),
    (["train.test_every=2", "train.holdout=validation"], "test_every 2 holds out every photo (with the validation"),
    (["train.test_every=0"], "test_every 0 holds out no photo"),
    ([], "output folder {out}/run already holds files"),
])
def test_photos_run_refuses_what_training_would_before_sfm_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str], sets: list[str],
                                                                needle: str) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _jpeg(photos / f"{i:02d}.jpg", seed=i)
    out = tmp_path / "out"
    if not sets:  # a run folder that holds someone else's files
        (out / "run").mkdir(parents=True)
        (out / "run" / "notes.txt").write_text("keep")
    monkeypatch.setattr("ctsplat.photos.sfm.run_photo_sfm", lambda *a, **k: pytest.fail("SfM ran"))
    assert main(["photos-run", str(photos), str(out), *[x for kv in sets for x in ("--set", kv)]]) == 2
    err = capsys.readouterr().err.strip()
    assert needle.format(out=out) in err and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == (["photos"] if sets else ["out", "photos"])


def test_photos_run_removes_the_run_of_a_replaced_sfm_model_when_training_fails(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Once the SfM model is replaced, the earlier run (poses in another frame) must not outlive a failed training."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _jpeg(photos / f"{i:02d}.jpg", seed=i)
    out = tmp_path / "out"
    (out / "run").mkdir(parents=True)
    for name in ("config.json", "model.pt", "metrics.json"):  # an earlier photo run
        (out / "run" / name).write_text("{}")

    def new_sfm(images: Path, sfm: Path, settings: dict) -> dict:
        sfm.mkdir(parents=True, exist_ok=True)
        (sfm / "summary.json").write_text("{}")
        return {}

    def failing_training(*args: object, **kwargs: object) -> None:
        assert not (out / "run").exists()  # gone before training starts
        raise CtsplatError("training failed here")

    monkeypatch.setattr("ctsplat.photos.sfm.run_photo_sfm", new_sfm)
    monkeypatch.setattr("ctsplat.photos.train.train_photos", failing_training)
    assert main(["photos-run", str(photos), str(out)]) == 2
    assert "training failed here" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["sfm"]


def test_workflow_refuses_photo_training_settings_at_parse_time(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a.jpg", "b.jpg", "c.jpg"):
        (photos / name).write_bytes(b"")
    volumes = {"p": {"source": "phantom"}, "skull": {"source": str(photos), "kind": "photos"}}
    with pytest.raises(CtsplatError, match=r"photos\.train\.test_every 1 holds out every photo"):
        prepare_config({"volumes": volumes, "photos": {"train": {"test_every": 1}}})
    prepare_config({"volumes": {"p": {"source": "phantom"}}, "photos": {"train": {"test_every": 1}}})  # no photos


def test_load_scene_refuses_a_folder_that_is_not_sfm_output(tmp_path: Path) -> None:
    with pytest.raises(CtsplatError, match=r"not a photo SfM folder .*photos-sfm"):
        load_scene(tmp_path)


# ------------------------------------------------------------------------------------------------ pieces
def test_every_eighth_image_is_held_out() -> None:
    names = [f"{i:02d}.jpg" for i in range(1, 18)]
    split = split_names(list(reversed(names)), 8)
    assert [n for n in names if split[n] == "test"] == ["01.jpg", "09.jpg", "17.jpg"]
    assert set(split_names(names, 0).values()) == {"train"}
    split = split_names(names, 8, validation=True)
    assert [n for n in names if split[n] == "test"] == ["01.jpg", "09.jpg", "17.jpg"]  # the same test photos
    assert [n for n in names if split[n] == "val"] == ["05.jpg", "13.jpg"]


def test_validation_folds_are_disjoint_and_never_touch_the_test_photos() -> None:
    names = [f"{i:02d}.jpg" for i in range(1, 67)]
    folds = {o: {n for n, s in split_names(names, 8, validation=True, validation_offset=o).items() if s == "val"}
             for o in range(1, 8)}
    test = {n for n, s in split_names(names, 8).items() if s == "test"}
    assert folds[2] == {f"{i:02d}.jpg" for i in range(3, 67, 8)}
    assert set().union(*folds.values()) == set(names) - test  # every training photo is in exactly one fold
    assert sum(map(len, folds.values())) == len(names) - len(test)
    assert split_names(names, 8, validation=True, validation_offset=4) == split_names(names, 8, validation=True)
    for bad in (0, 8, -1):
        with pytest.raises(CtsplatError, match=r"validation_offset must be 1\.\.7 \(test_every 8\), got"):
            split_names(names, 8, validation=True, validation_offset=bad)


def test_pinhole_camera_scales_with_the_image() -> None:
    cam = PinholeCamera(1061, 707, 2400.0, 2390.0, 520.5, 360.25)
    q = cam.scaled(4)
    assert (q.width, q.height) == (265, 177)
    assert q.model == "cone" and q.dsd_mm == q.fx  # what the renderer reads
    # a scene point lands at the same place in the image: its pixel coordinates (COLMAP's, the first pixel's centre
    # at 0.5) shrink with the image, each axis by its own factor (265 / 1061 across, 177 / 707 down)
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.2, -0.15, 2.0], [0.2, 0.15, 4.0], size=(50, 3))

    def pixels(c: PinholeCamera) -> np.ndarray:
        return pts[:, :2] / pts[:, 2:] * [c.fx, c.fy] + [c.cx, c.cy]

    assert np.allclose(pixels(q), pixels(cam) * [265 / 1061, 177 / 707], rtol=0, atol=1e-9)


def test_photo_settings_fill_defaults_and_refuse_unknown_keys() -> None:
    s = photo_settings({"train": {"iterations": 5}})
    assert s["train"]["iterations"] == 5 and s["train"]["lr"]["means"] == pytest.approx(1.6e-4)
    with pytest.raises(CtsplatError, match=r"photos\.train\.iteration"):
        photo_settings({"train": {"iteration": 5}})


# ------------------------------------------------------------------------------------------------ training
def _synthetic_scene(tmp: Path | None = None, background: tuple[float, float, float] | None = None
                     ) -> tuple[PhotoScene, Gaussians]:
    """24 coloured Gaussians seen by 16 cameras on a ring (64x48), rendered by the renderer itself over
    ``background`` (None: black)."""
    gen = torch.Generator().manual_seed(0)
    n = 24
    means = (torch.rand(n, 3, generator=gen) - 0.5) * 1.2
    colors = torch.rand(n, 3, generator=gen) * 0.8 + 0.1
    truth = Gaussians.from_values(means, 0.12, 1.0, opacities=0.8, colors=colors, sh_degree=1)
    truth.sh_rest[:, 0] = 0.1  # a little view dependence
    cam = PinholeCamera(64, 48, 70.0, 70.0, 32.0, 24.0)
    views = []
    for k in range(16):
        a = 2 * np.pi * k / 16
        centre = np.array([4 * np.cos(a), 4 * np.sin(a), 1.0 + 0.5 * np.sin(3 * a)])
        R, t = look_at(centre, np.zeros(3), (0, 0, 1))
        with torch.no_grad():
            img = render_view(truth, None, cam, R, t, background=background).image.clamp(0, 1)
        views.append(PhotoView(f"{k:02d}.png", img, cam, R, t, "test" if k % 8 == 0 else "train"))
    rng = np.random.default_rng(1)
    xyz = means.numpy() + rng.normal(0, 0.15, (n, 3))  # noisy "SfM" points, random colours
    xyz = np.concatenate([xyz, rng.uniform(-0.6, 0.6, (40, 3))])
    scene = PhotoScene(views, xyz, rng.uniform(0, 1, (len(xyz), 3)),
                       scene_extent([v.R for v in views], [v.t for v in views]))
    return scene, truth


def test_training_learns_a_synthetic_scene_from_known_cameras(tmp_path: Path) -> None:
    torch.set_num_threads(2)
    scene, _ = _synthetic_scene()
    s = photo_settings({"train": {"iterations": 600, "log_every": 200, "sh_interval": 150,
                                  "densify": {"start": 100, "interval": 100, "opacity_reset_interval": 0}}})["train"]
    model, report = train_scene(scene, s, tmp_path / "train_log.csv")
    assert report["n_test"] == 2 and report["n_train"] == 14
    assert report["final_test_psnr"] > report["initial_test_psnr"] + 8
    assert report["final_test_psnr"] > 24
    assert report["sh_degree"] == 3 and model.sh_degree == 3
    log = (tmp_path / "train_log.csv").read_text().splitlines()
    assert log[0].startswith("iteration,timestamp,psnr2d,ssim2d,psnr3d,ssim3d")
    assert len(log) == 1 + 4  # iteration 0, 200, 400, 600
    # held-out metric as evaluation computes it
    with torch.no_grad():
        p, ss = image_metrics(render_view(model, scene.split("test")[0]).image, scene.split("test")[0].image)
    assert p > 24 and 0.8 < ss <= 1


def test_learned_background_recovers_the_backdrop_colour() -> None:
    torch.set_num_threads(2)
    bg = (0.2, 0.45, 0.7)
    scene, _ = _synthetic_scene(background=bg)
    base = {"iterations": 300, "log_every": 1000, "sh_degree": 0,
            "densify": {"start": 100, "interval": 100, "opacity_reset_interval": 0}}
    learned = photo_settings({"train": {**base, "background": "learned"}})["train"]
    model, report = train_scene(scene, learned)
    assert np.allclose(model.meta["background"], bg, atol=0.03) and report["background"] == model.meta["background"]
    black = photo_settings({"train": {**base, "background": [0.0, 0.0, 0.0]}})["train"]
    _, report_black = train_scene(scene, black)
    assert report["final_test_psnr"] > report_black["final_test_psnr"] + 3
    assert report["final_test_psnr"] > 22


def test_sh_degree_slices_the_trained_coefficients() -> None:
    from ctsplat.photos.train import init_params

    params = init_params(np.random.default_rng(0).normal(size=(10, 3)), np.full((10, 3), 0.5),
                         photo_settings()["train"], np.random.default_rng(0))
    assert to_gaussians(params, 0).sh_rest is None
    assert [to_gaussians(params, d).sh_degree for d in (1, 2, 3)] == [1, 2, 3]
    assert to_gaussians(params, 2).sh_rest.data_ptr() == params["sh_rest"].data_ptr()  # a view, trained in place


def test_turntable_circles_the_object() -> None:
    scene, _ = _synthetic_scene()
    poses = turntable_poses(scene.views, 8)
    centres = np.stack([-R.T @ t for R, t in poses])
    assert np.allclose(np.linalg.norm(centres[:, :2], axis=1), 4.0, atol=0.2)
    for R, t in poses:  # each looks at the ring's centre (the object)
        assert (R @ np.zeros(3) + t)[2] > 3.5 and np.allclose((R @ np.zeros(3) + t)[:2], 0, atol=1e-6)


def test_evaluation_writes_metrics_gallery_and_turntable(tmp_path: Path) -> None:
    scene, truth = _synthetic_scene()
    run = tmp_path / "run"
    run.mkdir()
    truth.save(run / "model.pt")
    t = photo_settings()["train"]
    (run / "config.json").write_text(json.dumps({"sfm_dir": str(tmp_path / "sfm"), "train": t,
                                                 "config_hash": "0123456789abcdef", "code_version": "0.1.0+gtrain"}))
    m = evaluate_photos(run, {"turntable_frames": 4, "gallery_views": 2, "attribution": "by someone, CC BY 4.0"},
                        scene=scene)
    assert m["psnr"] > 40 and m["ssim"] > 0.99  # the true model renders its own targets
    assert (m["seed"], m["config_hash"], m["training_code_version"]) == (t["seed"], "0123456789abcdef",
                                                                         "0.1.0+gtrain")
    assert m["code_version"] and m["platform"]["threads"] >= 1
    assert m["lpips"] is None and m["lpips_reason"]
    assert m["fps"] > 0 and m["eval_peak_rss_mb"] > 0 and m["n_test"] == 2
    assert m["peak_rss_mb"] is None  # training's memory comes from training.json, which this run lacks
    assert json.loads((run / "metrics.json").read_text())["attribution"] == "by someone, CC BY 4.0"
    assert Image.open(run / "figures" / "gallery.png").size[0] > 100
    gif = Image.open(run / "figures" / "turntable.gif")
    assert gif.n_frames == 4
    assert (run / "per_view_test.csv").read_text().startswith("iteration,view_id,")


def test_evaluation_reads_every_input_before_writing_and_credits_the_photos(tmp_path: Path,
                                                                             caplog: pytest.LogCaptureFixture) -> None:
    from ctsplat.photos.evaluate import _footer

    scene, truth = _synthetic_scene()
    run = tmp_path / "run"
    run.mkdir()
    truth.save(run / "model.pt")
    (run / "config.json").write_text(json.dumps({"sfm_dir": str(tmp_path / "sfm"), "train": photo_settings()["train"]}))
    evaluate_photos(run, {"turntable_frames": 2, "gallery_views": 1, "attribution": "by someone, CC BY 4.0"},
                    scene=scene)
    before = {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    for bad in (run / "training.json", tmp_path / "sfm" / "summary.json"):  # a truncated record of either step
        bad.parent.mkdir(exist_ok=True)
        bad.write_text('{"final_test_psnr": 2')
        with pytest.raises(CtsplatError, match=rf"{bad.name} is not valid JSON.*run `ctsplat photos-"):
            evaluate_photos(run, {"turntable_frames": 2, "gallery_views": 1}, scene=scene)
        bad.unlink()
        assert {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    # an output that fails after the first is written leaves no metrics beside the new files
    (run / "figures" / "turntable.gif").unlink()
    (run / "figures" / "turntable.gif").mkdir()
    with pytest.raises(CtsplatError, match=r"turntable\.gif is a folder, but a file is to be written there"):
        evaluate_photos(run, {"turntable_frames": 2, "gallery_views": 1, "attribution": "x"}, scene=scene)
    assert not (run / "metrics.json").exists()
    (run / "figures" / "turntable.gif").rmdir()
    # CC BY asks for the credit and for a note of the changes; an empty credit line is reported
    footer = _footer("by someone, CC BY 4.0")
    assert footer.startswith("Photographs: by someone, CC BY 4.0") and "undistorted and downscaled" in footer
    with caplog.at_level("WARNING", logger="ctsplat.photos.evaluate"):
        evaluate_photos(run, {"turntable_frames": 0, "gallery_views": 0}, scene=scene)
    assert "photos.evaluate.attribution is empty" in caplog.text


# ------------------------------------------------------------------------------------------------ workflow config
def test_photo_volumes_stay_out_of_the_ct_grid(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("01.jpg", "02.jpg", "03.jpg"):  # photos.sfm.min_registered
        (photos / name).write_bytes(b"")
    cfg = prepare_config({"volumes": {"phantom": {"source": "phantom"},
                                      "skull": {"source": str(photos), "kind": "photos"}}})
    assert list(cfg["volumes"]) == ["phantom"] and list(cfg["photo_volumes"]) == ["skull"]
    assert cfg["photos"]["train"]["test_every"] == 8
    with pytest.raises(CtsplatError, match=r"volumes.skull.source: .*folder of photographs"):
        prepare_config({"volumes": {"phantom": {"source": "phantom"},
                                    "skull": {"source": str(tmp_path / "nope"), "kind": "photos"}}})
    with pytest.raises(CtsplatError, match=r"every volume is of kind photos"):
        prepare_config({"volumes": {"skull": {"source": str(photos), "kind": "photos"}}})
    with pytest.raises(CtsplatError, match=r"photos.train.downscale"):
        prepare_config({"volumes": {"phantom": {"source": "phantom"}}, "photos": {"train": {"downscale": 3}}})
    for key in ("gallery_views", "turntable_frames"):  # the workflow's photos_evaluate rule writes both figures
        with pytest.raises(CtsplatError, match=rf"photos.evaluate.{key}: .*must be >= 1"):
            prepare_config({"volumes": {"phantom": {"source": "phantom"},
                                        "skull": {"source": str(photos), "kind": "photos"}},
                            "photos": {"evaluate": {key: 0}}})


# ------------------------------------------------------------------------------------------------ benchmark
def _benchmark(args: list[str], cwd: Path | None = None) -> Any:
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run([sys.executable, str(root / "benchmarks" / "photos.py"), *args], capture_output=True,
                          text=True, env=env, timeout=120, cwd=cwd)


@pytest.mark.parametrize(("signum", "status", "how"), [(2, 130, "interrupted"), (15, 143, "terminated")])
def test_a_benchmark_killed_mid_step_removes_its_temporary_folder(tmp_path: Path, signum: int, status: int,
                                                                  how: str) -> None:
    """SIGTERM (a job's time limit) and Ctrl-C end a benchmark in one line, its steps' temporary folders removed."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    # Ctrl-C as a terminal delivers it: a shell starts background jobs with SIGINT ignored, and Python keeps that
    script = (f"import os, signal, sys; sys.path.insert(0, {str(root / 'benchmarks')!r})\n"
              "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
              "from _common import cli_main\n"
              "from ctsplat.utils import atomic_dir\n"
              "def run(argv):\n"
              f"    with atomic_dir({str(tmp_path / 'out')!r}) as tmp:\n"
              "        (tmp / 'half.txt').write_text('x')\n"
              f"        os.kill(os.getpid(), {signum})\n"
              "    return 0\n"
              "sys.exit(cli_main(run, [], 'bench.py'))\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "PYTHONPATH": str(root)})
    assert res.returncode == status, res.stderr[-2000:]
    assert res.stderr.strip() == f"bench.py: {how}; files are written whole or not at all: run it again"
    assert list(tmp_path.iterdir()) == []  # neither the output nor its hidden temporary folder


@pytest.mark.parametrize(("args", "needle"), [
    (["--downscale", "3"], "photos.train.downscale: 3 is not one of [1, 2, 4, 8]"),
    (["--iterations", "0"], "photos.train.iterations: 0 is less than the minimum of 1"),
    (["--images", "/nonexistent/photos"], "photo folder /nonexistent/photos not found"),
    (["--reuse-sfm"], "sfm/summary.json not found; run once without --reuse-sfm"),
])
def test_benchmark_refuses_bad_options_with_one_line(tmp_path: Path, args: list[str], needle: str) -> None:
    res = _benchmark([*args, "--out", str(tmp_path / "o")])
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("benchmarks/photos.py: error:") and needle in line, line
    assert not (tmp_path / "o").exists()


def test_benchmark_refuses_a_bad_seed_with_one_line(tmp_path: Path) -> None:
    res = _benchmark(["--seed", "-1", "--out", str(tmp_path / "o")])
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert "argument --seed: -1 is outside 0 .. 4294967295" in res.stderr.strip().splitlines()[-1], res.stderr
    assert not (tmp_path / "o").exists()


def test_benchmark_refuses_a_foreign_run_folder_before_sfm(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _jpeg(photos / f"{i:02d}.jpg", seed=i)
    (tmp_path / "o" / "run").mkdir(parents=True)
    (tmp_path / "o" / "run" / "notes.txt").write_text("keep")
    res = _benchmark(["--images", str(photos), "--out", str(tmp_path / "o")])
    assert res.returncode == 2 and "o/run already holds files" in res.stderr.strip().splitlines()[-1]
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["run"]  # no sfm/ from a step that did not run


def test_benchmark_out_may_be_the_current_folder(tmp_path: Path) -> None:
    """``--out .`` names the summary after the folder itself (``../bench.json``), not a crash after the run."""
    bench = tmp_path / "bench"
    (bench / "sfm").mkdir(parents=True)
    sfm = {"n_images": 3, "n_registered": 3, "registration_rate": 1.0, "unregistered": [], "models_found": 1,
           "mean_reprojection_error_px": 0.3, "n_points": 10}
    (bench / "sfm" / "summary.json").write_text(json.dumps(sfm))
    res = _benchmark(["--reuse-sfm", "--sfm-only", "--out", "."], cwd=bench)
    assert res.returncode == 0, res.stderr
    assert json.loads((tmp_path / "bench.json").read_text())["n_points"] == 10


@pytest.mark.parametrize(("args", "needle"), [
    (["RUN", "--top", "0"], "--top must be >= 1, got 0"),
    (["RUN"], "is not a photo run (config.json and model.pt); run `ctsplat photos-train`"),
])
def test_blame_benchmark_refuses_bad_input_with_one_line(tmp_path: Path, args: list[str], needle: str) -> None:
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    args = [str(tmp_path / "not_a_run") if a == "RUN" else a for a in args]
    res = subprocess.run([sys.executable, str(root / "benchmarks" / "photo_blame.py"), *args],
                         capture_output=True, text=True, env=env, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("benchmarks/photo_blame.py: error:") and needle in line, line
    assert not (tmp_path / "not_a_run").exists()


def test_densify_statistics_are_kept_beside_the_gaussians() -> None:
    from ctsplat.photos.densify import AlphaDensify

    # "meta" stands in for a GPU here: a statistic left on the CPU would meet CUDA gradients in accumulate()
    dens = AlphaDensify(photo_settings()["train"]["densify"], iterations=100, extent=1.0,
                        means=torch.empty(5, 3, device="meta"))
    assert dens.grad_accum.device.type == dens.grad_count.device.type == "meta"
    assert dens.grad_accum.shape == dens.grad_count.shape == (5,)


def test_pixel_gradient_is_the_pixel_weighted_depth_scaled_average() -> None:
    """``gradient: pixel`` (Pixel-GS): Σ_v n_v s_v ‖g_v‖ / Σ_v n_v over the views where a Gaussian is visible, with
    n_v its pixels and s_v = min(1, (z_v / (0.37 R))²), against the sums written out; ``mean`` keeps 3DGS's
    Σ_v ‖g_v‖ / (views visible)."""
    from ctsplat.photos.densify import AlphaDensify

    rng = np.random.default_rng(0)
    n, views, extent = 6, 4, 2.0
    grads = rng.normal(size=(views, n, 2))
    feet = rng.uniform(0.5, 400.0, size=(views, n))
    depths = rng.uniform(0.2, 3.0, size=(views, n))  # 0.37 x 2 = 0.74: some scaled down, some not
    visible = rng.random((views, n)) > 0.3
    visible[:, 5] = False  # never seen: statistic 0
    ndc = np.array([40.0, 30.0])
    stats = {}
    for mode in ("mean", "pixel"):
        settings = {**photo_settings()["train"]["densify"], "gradient": mode}
        dens = AlphaDensify(settings, iterations=100, extent=extent, means=torch.zeros(n, 3, dtype=torch.float64))
        dens.grad_accum = dens.grad_accum.double()
        dens.grad_count = dens.grad_count.double()
        for v in range(views):
            dens.accumulate(torch.tensor(grads[v]), torch.tensor(visible[v]), torch.tensor(ndc),
                            footprints=torch.tensor(feet[v]), depths=torch.tensor(depths[v]))
        stats[mode] = dens.mean_gradients().numpy()
    norm = np.linalg.norm(grads * ndc, axis=-1)
    scale = np.minimum(1.0, (depths / (0.37 * extent)) ** 2)
    assert (scale < 1).any() and (scale == 1).any()
    w = feet * visible
    with np.errstate(invalid="ignore"):
        pixel = np.where(w.sum(0) > 0, (w * scale * norm).sum(0) / w.sum(0), 0.0)
    mean = (visible * norm).sum(0) / np.maximum(visible.sum(0), 1)
    np.testing.assert_allclose(stats["pixel"], pixel, rtol=1e-12)
    np.testing.assert_allclose(stats["mean"], mean, rtol=1e-12)
    assert stats["pixel"][5] == stats["mean"][5] == 0.0
    settings = {**photo_settings()["train"]["densify"], "gradient": "pixel"}
    dens = AlphaDensify(settings, iterations=100, extent=extent, means=torch.zeros(n, 3))
    with pytest.raises(ValueError, match="footprints and depths"):
        dens.accumulate(torch.zeros(n, 2), torch.ones(n, dtype=torch.bool), torch.tensor(ndc))


def test_pixel_gradient_training_accumulates_each_views_footprints_and_depths(monkeypatch: pytest.MonkeyPatch
                                                                              ) -> None:
    """``gradient: pixel`` in training: each view's statistic gets that view's render's footprints and depths."""
    import ctsplat.photos.train as train_module
    from ctsplat.photos.densify import AlphaDensify

    scene, _ = _synthetic_scene()
    renders, seen = [], []
    render = train_module.render_view
    accumulate = AlphaDensify.accumulate

    def spy_render(*a: Any, **k: Any) -> Any:
        out = render(*a, **k)
        renders.append(out)
        return out

    def spy_accumulate(self: AlphaDensify, *a: Any, **k: Any) -> None:
        last = renders[-1]  # the training view's render: evaluation renders are not accumulated
        assert k["footprints"] is last.footprints and k["depths"] is last.depths
        assert torch.equal(a[1], last.visible) and float(last.footprints[last.visible].min()) > 0
        seen.append(float(k["footprints"].sum()))
        accumulate(self, *a, **k)

    monkeypatch.setattr(train_module, "render_view", spy_render)
    monkeypatch.setattr(AlphaDensify, "accumulate", spy_accumulate)
    densify = {"gradient": "pixel", "start": 3, "interval": 3, "stop_fraction": 1.0, "grad_threshold": 1e-9}
    s = photo_settings({"train": {"iterations": 6, "log_every": 100, "densify": densify}})["train"]
    _, report = train_scene(scene, s)
    assert len(seen) == 6 and min(seen) > 0 and report["n_gaussians"] != len(scene.xyz)


def _three_gaussians() -> dict[str, torch.Tensor]:
    """A wide opaque Gaussian (0.5 x the extent of 1), a small opaque one and a small transparent one."""
    from ctsplat.photos.train import init_params

    params = init_params(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), np.full((4, 3), 0.5),
                         photo_settings()["train"], np.random.default_rng(0))
    with torch.no_grad():
        params["log_scales"][:] = math.log(0.01)
        params["log_scales"][0] = math.log(0.5)
        params["opacity_raw"][:] = 2.0
        params["opacity_raw"][2] = -8.0  # opacity 3e-4, below prune_opacity
    return params


def test_split_children_are_drawn_from_the_parent_with_scales_over_1_6() -> None:
    """3DGS's split: each large Gaussian with a large gradient becomes two, their means sampled from the parent
    Gaussian N(μ, R S² Rᵀ) and their scales the parent's / 1.6 (Kerbl et al. 2023, Sec. 5.2); the sample
    covariance of 4000 children against the parent's covariance."""
    from scipy.spatial.transform import Rotation

    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer, init_params

    m = 2000
    scales = np.array([0.05, 0.02, 0.01])  # above percent_dense x extent (0.01): split, not clone
    quat_xyzw = Rotation.from_euler("zyx", [30, 40, 10], degrees=True).as_quat()
    params = init_params(np.zeros((m, 3)), np.full((m, 3), 0.5), photo_settings()["train"], np.random.default_rng(0))
    with torch.no_grad():
        params["log_scales"][:] = torch.log(torch.as_tensor(scales, dtype=params["log_scales"].dtype))
        params["quats"][:] = torch.as_tensor(np.roll(quat_xyzw, 1), dtype=params["quats"].dtype)  # wxyz
        params["opacity_raw"][:] = 2.0
    settings = {**photo_settings()["train"]["densify"], "start": 100, "max_gaussians": 10 * m}
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    dens = AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"])
    dens.grad_accum[:] = 1.0
    dens.grad_count[:] = 1.0
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=100)
    assert (st["split"], st["cloned"], st["n"]) == (m, 0, 2 * m)
    np.testing.assert_allclose(torch.exp(params["log_scales"]).detach().numpy(), np.tile(scales / 1.6, (2 * m, 1)),
                               rtol=1e-6)
    offsets = params["means"].detach().double().numpy()  # the parents sat at the origin
    rot = Rotation.from_quat(quat_xyzw).as_matrix()
    expected = rot @ np.diag(scales**2) @ rot.T
    np.testing.assert_allclose(np.cov(offsets.T), expected, atol=0.1 * scales[0] ** 2)
    assert abs(offsets.mean(0)).max() < 0.1 * scales[0]


@pytest.mark.parametrize(("size_prune", "reset"), [("after_reset", 3000), ("always", 3000), ("after_reset", 0)])
def test_size_prune_always_prunes_wide_gaussians_to_the_end_of_training(size_prune: str, reset: int) -> None:
    """... and "after_reset" never prunes by size when no reset comes (opacity_reset_interval 0)."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    settings = {**photo_settings()["train"]["densify"], "size_prune": size_prune, "opacity_reset_interval": reset}
    params = _three_gaussians()
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    settings["start"] = 100
    dens = AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"])  # densifies 100..170
    assert dens.due(100) and not dens.due(150) and not dens.due(1000)
    assert dens.due(300) == dens.due(900) == (size_prune == "always")  # prune-only steps after densification
    dens.grad_accum[:] = 1.0  # every Gaussian above grad_threshold
    dens.grad_count[:] = 1.0
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=300)
    # after densification stops nothing is cloned or split; the transparent Gaussian goes either way, and the wide
    # one only under "always" (3DGS's size prune otherwise waits for the first opacity reset, at 3000)
    assert st["cloned"] == st["split"] == 0
    widths = torch.exp(params["log_scales"]).max(-1).values
    assert st["pruned"] == (2 if size_prune == "always" else 1)
    assert bool((widths > 0.1).any()) == (size_prune == "after_reset")
    assert params["means"].shape[0] == st["n"] == len(opt.param_groups[0]["params"][0])


def test_density_schedules_stop_before_their_stop_and_no_reset_lands_on_it() -> None:
    """3DGS densifies while ``iteration < densify_until_iter``; a reset at the stop itself would leave its faded
    Gaussians unpruned. MCMC keeps its own stop whatever the default strategy's pruning options say."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.mcmc import MCMCDensify

    train = photo_settings()["train"]
    d = {**train["densify"], "stop_fraction": 0.5, "opacity_reset_interval": 3000}
    dens = AlphaDensify(d, iterations=30000, extent=1.0, means=_three_gaussians()["means"])
    assert [i for i in range(3000, 30001, 3000) if dens.reset_due(i)] == [3000, 6000, 9000, 12000]
    steps = [i for i in range(0, 30001, 100) if dens.due(i)]
    assert steps[0] == 500 and steps[-1] == 14900
    for extra in ({"size_prune": "always"}, {"near_prune": 0.5}, {}):
        mcmc = MCMCDensify({**train["densify"], **extra}, train["mcmc"], iterations=6000)
        assert max(i for i in range(0, 6001, 100) if mcmc.due(i)) == 4900  # stop 4980 (0.83 of 6000)
    for key, bad in (("strategy", "MCMC"), ("gradient", "pixels"), ("size_prune", "alway")):
        with pytest.raises(CtsplatError, match=rf"unknown photos\.train\.densify\.{key} '{bad}'"):
            check_train_settings({**train, "densify": {**train["densify"], key: bad}})


@pytest.mark.parametrize(("camera_z", "wide_pruned"), [(0.4, True), (-3.0, False)])
def test_near_prune_removes_gaussians_wider_than_their_distance_to_a_training_camera(
        camera_z: float, wide_pruned: bool) -> None:
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    settings = {**photo_settings()["train"]["densify"], "near_prune": 1.0, "start": 100}
    params = _three_gaussians()  # the wide one (sigma 0.5) at the origin, a small one at (0, 0, 1)
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    centres = torch.tensor([[0.0, 0.0, camera_z], [5.0, 5.0, 5.0]])
    dens = AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"], camera_centers=centres)
    assert dens.due(300) and dens.due(900)  # prune-only steps to the end of training
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=300)
    # 0.4 from the camera a sigma of 0.5 is pruned; 3 away it is not (the size rule waits for the reset at 3000);
    # the small Gaussian 0.6 or 4 from the camera stays either way, the transparent one goes either way
    widths = torch.exp(params["log_scales"]).max(-1).values
    assert bool((widths > 0.1).any()) != wide_pruned
    assert st["pruned"] == (2 if wide_pruned else 1) and params["means"].shape[0] == 2 + (not wide_pruned)
    with pytest.raises(ValueError, match="near_prune > 0 needs the training cameras' centres"):
        AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"])


def test_training_gives_the_density_control_the_training_cameras_centres(monkeypatch: pytest.MonkeyPatch) -> None:
    import ctsplat.photos.train as photo_train
    from ctsplat.photos.densify import AlphaDensify

    seen = []

    class Recording(AlphaDensify):
        def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
            super().__init__(*args, **kwargs)
            seen.append(self.camera_centers)

    monkeypatch.setattr(photo_train, "AlphaDensify", Recording)
    scene, _ = _synthetic_scene()
    train_scene(scene, photo_settings({"train": {"iterations": 1, "densify": {"near_prune": 1.0}}})["train"])
    train = scene.split("train")
    expected = np.stack([camera_center(v.R, v.t) for v in train])
    assert len(seen) == 1 and seen[0].shape == (len(train), 3) and len(train) < len(scene.views)
    assert np.allclose(seen[0].numpy(), expected, atol=1e-5)


def test_drop_gaussians_leaves_out_a_share_and_keeps_the_expected_opacity() -> None:
    from ctsplat.photos.train import drop_gaussians

    sig = torch.tensor([0.1, 0.5, 0.7, 0.95]).repeat(20000)
    x = torch.logit(sig).requires_grad_(True)
    o = torch.sigmoid(drop_gaussians(x, 0.2, torch.Generator().manual_seed(0)))
    kept = o > 1e-9
    assert abs(1 - float(kept.float().mean()) - 0.2) < 0.01  # binomial standard error 0.0014
    assert torch.allclose(o[kept], torch.clamp(sig / 0.8, max=0.999)[kept], atol=1e-5)
    assert float(o[~kept].max().detach()) < 1e-12
    means = o.detach().view(-1, 4).mean(0)
    assert torch.allclose(means[:3], sig[:3], atol=0.01)  # below the cap the expected opacity is unchanged
    (grad,) = torch.autograd.grad(o.sum(), x)
    expect = sig * (1 - sig) / 0.8  # d(σ(x) / 0.8)/dx, through the cap too (0.95 / 0.8 > 0.999)
    assert torch.allclose(grad[kept], expect[kept], rtol=1e-3) and float(grad[~kept].abs().max()) == 0.0
    assert drop_gaussians(x, 0.0, torch.Generator()) is x
    with pytest.raises(CtsplatError, match="leaves no Gaussian"):
        drop_gaussians(x, 1.0, torch.Generator())


def test_training_drops_gaussians_at_a_rate_rising_to_drop_rate(monkeypatch: pytest.MonkeyPatch) -> None:
    import ctsplat.photos.train as photo_train

    rates: list[float] = []

    def recording(opacity_raw: torch.Tensor, rate: float, gen: torch.Generator) -> torch.Tensor:
        rates.append(rate)
        return opacity_raw

    monkeypatch.setattr(photo_train, "drop_gaussians", recording)
    scene, _ = _synthetic_scene()
    train_scene(scene, photo_settings({"train": {"iterations": 4, "drop_rate": 0.2}})["train"])
    assert np.allclose(rates, [0.05, 0.1, 0.15, 0.2])
    rates.clear()
    train_scene(scene, photo_settings({"train": {"iterations": 2}})["train"])
    assert rates == [0.0, 0.0]


def test_training_without_held_out_photos_fails_before_training(tmp_path: Path) -> None:
    scene, _ = _synthetic_scene()
    for v in scene.views:
        v.split = "train"  # test_every 0: nothing held out, nothing to evaluate the run on
    with pytest.raises(CtsplatError, match=r"no test photo \(test_every 0\).*test_every to 2 or more"):
        train_scene(scene, photo_settings({"train": {"iterations": 10**6, "test_every": 0}})["train"])


def test_sfm_and_training_never_replace_their_input(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(3):
        _jpeg(photos / f"{k:02d}.jpg", seed=k)
    before = sorted(p.name for p in photos.iterdir())
    for out in (photos, tmp_path):  # the photo folder itself, and a folder that holds it
        with pytest.raises(CtsplatError, match=r"is, or holds, the input .*choose another output folder"):
            run_photo_sfm(photos, out)
        assert sorted(p.name for p in photos.iterdir()) == before
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    with pytest.raises(CtsplatError, match=r"notes already holds files that are not an earlier output"):
        run_photo_sfm(photos, other)
    assert (other / "keep.txt").read_text() == "mine"
    # a folder with the step's marker and files of someone else's (a project root with a config.json, a CT SfM
    # folder with its summary.json, a photo run trained inside an SfM folder): refused before any work
    (other / "summary.json").write_text("{}")
    (other / "config.json").write_text("{}")
    with pytest.raises(CtsplatError, match=r"notes holds config\.json and 1 more, which this step does not write"):
        run_photo_sfm(photos, other)
    with pytest.raises(CtsplatError, match=r"notes holds keep\.txt and 1 more, which this step does not write"):
        check_run(other, photo_settings({})["train"])
    assert sorted(p.name for p in other.iterdir()) == ["config.json", "keep.txt", "summary.json"]
    run = tmp_path / "earlier_run"  # a photo run with benchmarks/photo_blame.py's table of its model is one
    (run / "figures").mkdir(parents=True)
    for name in ("config.json", "model.pt", "metrics.json", "blame.csv", "figures/gallery.png",
                 ".training.x1y2z3.tmp.json"):  # the last: a killed write's leftover
        (run / name).write_text("x")
    check_run(run, photo_settings({})["train"])
    sfm = tmp_path / "sfm"
    (sfm / "sparse" / "0").mkdir(parents=True)
    (sfm / "summary.json").write_text("{}")
    with pytest.raises(CtsplatError, match=r"is, or holds, the input"):
        train_photos(sfm, sfm)  # refused before the scene is even read
    assert (sfm / "summary.json").is_file()


def test_photos_train_keeps_the_earlier_run_when_the_evaluation_fails(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Training and evaluation happen in the temporary folder: a failed evaluation leaves the earlier run whole."""
    import ctsplat.photos.evaluate as photo_evaluate
    import ctsplat.photos.train as photo_train

    scene, _ = _synthetic_scene()
    monkeypatch.setattr(photo_train, "load_scene", lambda *a, **k: scene)
    sfm, run = tmp_path / "sfm", tmp_path / "run"
    sfm.mkdir()
    sets = ["--set", "train.iterations=2", "--set", "evaluate.turntable_frames=2", "--attribution", "A"]
    assert main(["photos-train", str(sfm), str(run), *sets]) == 0
    capsys.readouterr()
    before = {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert {"model.pt", "metrics.json", "per_view_test.csv", "figures/gallery.png"} <= set(before)

    def failing(run_dir: Path, *args: object, **kwargs: object) -> None:
        (Path(run_dir) / "per_view_test.csv").write_text("half")  # part of its outputs, then the failure
        raise CtsplatError("the evaluation failed here")

    monkeypatch.setattr(photo_evaluate, "evaluate_photos", failing)
    assert main(["photos-train", str(sfm), str(run), *sets[:1], "train.iterations=3", *sets[2:]]) == 2
    assert "the evaluation failed here" in capsys.readouterr().err
    assert {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "sfm"]  # no temporary folder left


def test_turntable_attribution_is_wrapped_to_the_frame(tmp_path: Path) -> None:
    from PIL import ImageDraw

    from ctsplat.photos.evaluate import footer_font, save_turntable_gif, wrap_to_width

    text = ("Photographs: Photogrammetry Test Set: Skull - Cameramoves - Flash - No Background by alansartlog, "
            "CC BY 4.0 (github.com/AlansCodeLog/photogrammetry-test-sets)")
    font = footer_font()
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))

    def measure(line: str) -> float:
        return draw.textlength(line, font=font)

    lines = wrap_to_width(text, 120, measure)
    assert len(lines) > 3 and all(measure(line) <= 120 for line in lines)
    assert "".join(lines).replace(" ", "") == text.replace(" ", "")  # every character kept, in order
    assert wrap_to_width("abcdefghij", 3, len) == ["abc", "def", "ghi", "j"]  # a word wider than a line is cut
    frames = [np.full((40, 124, 3), 0.5)] * 2
    save_turntable_gif(tmp_path / "t.gif", frames, text.removeprefix("Photographs: "))
    gif = Image.open(tmp_path / "t.gif")
    assert gif.size[0] == 124 and gif.size[1] >= 40 + 10 * len(lines)  # a footer tall enough for every line
    # accented letters and dashes are drawn as themselves: with a font that lacks them both names would draw
    # the same boxes
    footers = []
    for name in ("J\u00fcrgen M\u00fcller \u2013 CC BY", "J\u00e9rgen M\u00e9ller \u2013 CC BY"):
        save_turntable_gif(tmp_path / "u.gif", frames, name)
        footers.append(np.asarray(Image.open(tmp_path / "u.gif").convert("L"))[40:])
    assert footers[0].shape == footers[1].shape and not np.array_equal(*footers)


def test_lpips_is_computed_on_rgb_renders_when_available(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import ctsplat.evaluation.metrics as metrics

    seen = []

    def fake(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # stands in for AlexNet LPIPS
        seen.append((a.shape, float(a.min()), float(a.max())))
        return ((a - b) ** 2).mean()

    monkeypatch.setattr(metrics, "_lpips_model", lambda: (fake, None))
    scene, truth = _synthetic_scene()
    run = tmp_path / "run"
    run.mkdir()
    dimmed = truth.detach()
    dimmed.colors.mul_(0.8)  # renders that differ from the photos
    dimmed.save(run / "model.pt")
    (run / "config.json").write_text(json.dumps({"sfm_dir": str(tmp_path), "train": photo_settings()["train"]}))
    m = evaluate_photos(run, {"turntable_frames": 0, "gallery_views": 0}, scene=scene)
    assert m["lpips_reason"] is None and m["lpips"] > 0
    assert all(shape == (1, 3, 48, 64) and lo >= -1 and hi <= 1 for shape, lo, hi in seen)  # RGB in [-1, 1]
    expected = []
    for v in scene.split("test"):
        with torch.no_grad():
            img = render_view(dimmed, v).image.clamp(0, 1).numpy()
        expected.append(float(np.mean((2 * img - 2 * v.image.numpy()) ** 2)))
    assert m["lpips"] == pytest.approx(np.mean(expected), rel=1e-5)
    assert [m["per_view"][v.name]["lpips"] for v in scene.split("test")] == pytest.approx(expected, rel=1e-5)


def test_an_image_too_large_to_decode_safely_fails_in_one_line(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    _jpeg(tmp_path / "01.jpg")  # 64 x 48 = 3072 px
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # PIL refuses images over twice this
    with pytest.raises(CtsplatError, match=r"01\.jpg is too large to decode safely .*downscale it"):
        check_photos(tmp_path, ["01.jpg"], single_camera=True)


def test_training_without_training_photos_fails_in_one_line() -> None:
    scene, _ = _synthetic_scene()
    for v in scene.views:
        v.split = "test" if v.split == "test" else "val"
    with pytest.raises(CtsplatError, match=r"no training photo left.*raise photos\.train\.test_every"):
        train_scene(scene, photo_settings({"train": {"iterations": 1}})["train"])


# ------------------------------------------------------------------------------------------------ choosing settings
def test_paired_comparison_is_the_paired_t_statistic() -> None:
    from scipy import stats

    from ctsplat.photos.select import paired_comparison

    default = [24.44, 23.66, 23.46, 23.77, 24.93]
    candidate = [24.03, 24.43, 24.39, 23.85, 24.53]
    r = paired_comparison(default, candidate)
    assert r["n"] == 5 and r["differences"] == pytest.approx(np.subtract(candidate, default).tolist())
    assert r["mean"] == pytest.approx(np.mean(np.subtract(candidate, default)))
    test = stats.ttest_rel(candidate, default, alternative="greater")
    assert r["t_score"] == pytest.approx(test.statistic)
    assert r["critical"] == pytest.approx(2.776, abs=1e-3)  # t(4) at 97.5 %: a win is a one-sided p <= 0.025
    assert r["verdict"] == "tie" and test.pvalue > 0.025
    assert paired_comparison(default, [d + 0.5 + 0.01 * i for i, d in enumerate(default)])["verdict"] == "candidate"
    assert paired_comparison(default, [d - 0.5 - 0.01 * i for i, d in enumerate(default)])["verdict"] == "default"
    one = paired_comparison([24.0], [25.0])
    assert one["standard_error"] is None and one["verdict"] == "tie"  # one pair says nothing about the spread
    same = paired_comparison([24.0, 23.0, 25.0], [24.5, 23.5, 25.5])  # every fold gains exactly 0.5 dB
    assert same["standard_error"] == 0 and same["t_score"] is None and same["verdict"] == "candidate"
    # 2.6 standard errors: a win by the normal rule, not by Student's t with 3 degrees of freedom (3.18)
    d = np.array([0.5, 0.3, 0.6, 0.0])
    near = paired_comparison(np.zeros(4), d)
    assert near["t_score"] == pytest.approx(2.646, abs=1e-3) and near["verdict"] == "tie"
    # a fold's seeds share its photos: their differences are averaged into one before the statistics
    grouped = paired_comparison(np.zeros(5), [1.0, 3.0, 0.5, 0.7, 0.6], groups=[4, 4, 1, 2, 3])
    assert grouped["units"] == 4 and grouped["unit_differences"] == pytest.approx([2.0, 0.5, 0.7, 0.6])
    assert grouped["mean"] == pytest.approx(0.95) and grouped["n"] == 5
    assert grouped["t_score"] == pytest.approx(stats.ttest_1samp([2.0, 0.5, 0.7, 0.6], 0).statistic)
    with pytest.raises(CtsplatError, match="3 folds for 5 pairs"):
        paired_comparison(np.zeros(5), np.ones(5), groups=[1, 2, 3])


@pytest.mark.parametrize(("a", "b"), [([1.0, 2.0], [1.0]), ([], []), ([1.0, float("nan")], [1.0, 2.0])])
def test_paired_comparison_refuses_unpaired_or_missing_scores(a: list[float], b: list[float]) -> None:
    from ctsplat.photos.select import paired_comparison

    with pytest.raises(CtsplatError, match=r"paired comparison"):
        paired_comparison(a, b)


def test_reading_an_unfinished_run_names_what_is_missing(tmp_path: Path) -> None:
    from ctsplat.photos.select import read_validation_run

    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(CtsplatError, match=r"not a finished photo run \(missing training\.json, per_view_test\.csv\)"):
        read_validation_run(tmp_path)
    (tmp_path / "per_view_test.csv").write_text("iteration,view_id,split,psnr2d,ssim2d\nfinal,05,val,24.0,0.8\n")
    (tmp_path / "training.json").write_text('{"final_test_psnr": 2')  # cut short
    with pytest.raises(CtsplatError, match=r"training\.json is not valid JSON.*remove the folder and train it again"):
        read_validation_run(tmp_path)
    (tmp_path / "training.json").write_text('{"final_test_psnr": 24.0}')
    with pytest.raises(CtsplatError, match=r"is not a whole photo run \(KeyError: 'train'"):
        read_validation_run(tmp_path)


@pytest.mark.parametrize(("args", "needle"), [
    (["--candidate", "train.flash.enabled=true", "--folds", "0"], "--folds: 0 is not a validation fold (1 .. 7)"),
    (["--candidate", "train.nonsense=1"], "nonsense"),
    (["--candidate", "train.iterations=0"], "photos.train.iterations: 0 is less than the minimum of 1"),
    (["--candidate", "train.holdout=test"], "may not set train.holdout: the folds and seeds hold out the validation"),
    (["--base", "train.seed=3", "--candidate", "train.sh_degree=1"], "may not set train.seed"),
    (["--candidate", "train.test_every=16"], "--candidate may not set train.test_every"),
    (["--candidate", 'train={"holdout": "test"}'], "may not set train.holdout: the folds, seeds and test photos"),
])
def test_fold_benchmark_refuses_bad_options_with_one_line(tmp_path: Path, args: list[str], needle: str) -> None:
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    sfm = tmp_path / "sfm" / "sparse" / "0"
    sfm.mkdir(parents=True)
    (sfm / "cameras.bin").write_bytes(b"")
    env = {**os.environ, "PYTHONPATH": str(root)}
    res = subprocess.run([sys.executable, str(root / "benchmarks" / "photo_folds.py"), "--sfm", str(tmp_path / "sfm"),
                          *args, "--out", str(tmp_path / "o")], capture_output=True, text=True, env=env, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("benchmarks/photo_folds.py: error:") and needle in line, line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("fold", "files", "needle"), [
    (2, {"training.json": "{}"}, "kept run's config"),
    (2, {"training.json": "{}", "config.json": '{"sfm_dir": "elsewhere", "train": {}}'},
     "holds a run with other settings or another SfM folder"),
])
def test_fold_benchmark_checks_kept_runs_before_training_any(tmp_path: Path, fold: int, files: dict,
                                                               needle: str) -> None:
    """A kept run that cannot pair (no config, other settings) in the last fold is named before the first fold
    trains, not hours later; nothing is trained."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    sfm = tmp_path / "sfm" / "sparse" / "0"
    sfm.mkdir(parents=True)
    (sfm / "cameras.bin").write_bytes(b"")
    kept = tmp_path / "o" / f"fold{fold}_seed0_candidate"
    kept.mkdir(parents=True)
    for name, text in files.items():
        (kept / name).write_text(text)
    env = {**os.environ, "PYTHONPATH": str(root)}
    res = subprocess.run([sys.executable, str(root / "benchmarks" / "photo_folds.py"), "--sfm", str(tmp_path / "sfm"),
                          "--candidate", "train.sh_degree=1", "--folds", "1", str(fold), "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, env=env, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("benchmarks/photo_folds.py: error:") and needle in line, line
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [kept.name]  # no training started


def test_fold_benchmark_stopped_by_sigterm_starts_no_queued_run(tmp_path: Path) -> None:
    """A job's time limit (SIGTERM) stops the comparison: the queued trainings never start (they ran for hours)."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    sfm = tmp_path / "sfm" / "sparse" / "0"
    sfm.mkdir(parents=True)
    (sfm / "cameras.bin").write_bytes(b"")
    script = (f"import os, signal, sys, threading, time; sys.path.insert(0, {str(root / 'benchmarks')!r})\n"
              "import photo_folds\n"
              "started = []\n"
              "def fake(sfm, run_dir, sets):\n"
              "    started.append(run_dir.name)\n"
              "    time.sleep(0.5)\n"
              "photo_folds._train = fake\n"
              "threading.Timer(0.2, lambda: os.kill(os.getpid(), signal.SIGTERM)).start()\n"
              f"rc = photo_folds.cli_main(photo_folds.run, ['--sfm', {str(tmp_path / 'sfm')!r}, '--candidate', "
              f"'train.sh_degree=0', '--folds', '1', '2', '3', '4', '--jobs', '2', '--out', {str(tmp_path / 'o')!r}], "
              "'photo_folds.py')\n"
              "print(len(started))\n"
              "sys.exit(rc)\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(root)})
    assert res.returncode == 143, res.stderr[-2000:]
    assert res.stdout.strip() == "2"  # the two running when it came; six of the eight never started
    assert res.stderr.strip().splitlines()[-1] == ("photo_folds.py: terminated; files are written whole or not at "
                                                   "all: run it again")


# ------------------------------------------------------------------------------------------------ blame
def test_blame_names_a_planted_floater_and_its_gain_is_the_opacity_derivative() -> None:
    from dataclasses import replace

    from ctsplat.photos.blame import blame_view, removal_gain

    torch.set_num_threads(1)
    scene, truth = _synthetic_scene()
    view = scene.views[0]  # its photo is the truth's render
    centre = camera_center(view.R, view.t)
    floater = Gaussians.from_values(torch.as_tensor(0.6 * centre[None], dtype=torch.float32), 0.3, 1.0,
                                    opacities=0.9, colors=torch.tensor([[0.9, 0.9, 0.9]]), sh_degree=1)
    model = Gaussians(**{k: torch.cat([getattr(truth, k), getattr(floater, k)]) for k in
                         ("means", "log_scales", "quats", "density_raw", "opacity_raw", "colors", "sh_rest")})
    r = blame_view(model, view, top=2)
    assert r["index"][0] == len(truth)  # the floater, appended last
    assert r["psnr"] < 25 and r["psnr_without"][0] > 60  # without it the render is the photo again
    # the ranked gains are the exact decreases of the summed squared error, each Gaussian removed alone
    with torch.no_grad():
        err_all = float(((render_view(model, view).image - view.image) ** 2).sum())
        for i, exact in zip(r["index"], r["gain"], strict=True):
            keep = torch.ones(len(model), dtype=torch.bool)
            keep[i] = False
            err_without = float(((render_view(model[keep], view).image - view.image) ** 2).sum())
            assert exact == pytest.approx(err_all - err_without, rel=1e-5, abs=1e-6)
    assert r["gain"] == sorted(r["gain"], reverse=True)
    # the gain is (dE/dx) / (1 - o); dE/dx against central differences of the summed squared error
    gain = removal_gain(model, view)
    assert r["first_order"] == pytest.approx([float(gain[i]) for i in r["index"]])
    x0 = model.opacity_raw.clone()
    for i in (r["index"][1], 3):
        err = []
        for h in (1e-2, -1e-2):
            x = x0.clone()
            x[i] += h
            with torch.no_grad():
                img = render_view(replace(model, opacity_raw=x), view).image
            err.append(float(((img.double() - view.image.double()) ** 2).sum()))
        fd = (err[0] - err[1]) / 2e-2
        assert float(gain[i]) * (1 - float(torch.sigmoid(x0[i]))) == pytest.approx(fd, rel=0.05, abs=1e-3)


def test_strip_metadata_keeps_pixels_and_colour_profile_and_drops_exif(tmp_path):
    from PIL import ImageCms

    from ctsplat.photos.images import strip_metadata

    rng = np.random.default_rng(0)
    pixels = (rng.random((24, 32, 3)) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif[0x013B] = "Jane Photographer"  # Artist
    exif[0xA431] = "SERIAL-123456"  # BodySerialNumber
    exif.get_ifd(0x8825)[2] = (48.0, 51.0, 29.0)  # GPSLatitude
    icc = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    # a TIFF's XMP (700), IPTC (33723) and Photoshop (34377) blocks, which Pillow copies when it saves a TIFF again
    xmp = b'<x:xmpmeta><rdf:Description exif:GPSLatitude="48,51.5N" dc:creator="Jane Photographer"/></x:xmpmeta>'
    tiff_tags = {"tiffinfo": {700: xmp, 33723: b"\x1c\x02\x50\x00\x11Jane Photographer",
                              34377: b"8BIM\x04\x04\x00\x00\x00\x00\x00\x0ctaken at home"}}
    for name, kw in (("a.jpg", {"quality": 90, "comment": b"taken at home"}), ("b.png", {}), ("c.tif", tiff_tags)):
        path = tmp_path / name
        Image.fromarray(pixels).save(path, exif=exif, icc_profile=icc, **kw)
        before = np.asarray(Image.open(path))
        assert b"Jane Photographer" in path.read_bytes()
        strip_metadata(path)
        data = path.read_bytes()
        assert b"Jane Photographer" not in data and b"SERIAL-123456" not in data and b"taken at home" not in data
        assert b"GPSLatitude" not in data
        with Image.open(path) as im:
            left = im.getexif()  # a TIFF keeps its structural tags (size, layout), nothing about its owner
            assert not {0x013B, 0x8825, 0x8769} & set(left) and im.info.get("icc_profile") == icc
            assert np.array_equal(np.asarray(im), before)  # the same pixels: JPEG not encoded again
    (tmp_path / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe1\x00\x10Exif")
    with pytest.raises(CtsplatError, match="cannot remove the metadata of .*broken.jpg"):
        strip_metadata(tmp_path / "broken.jpg")
    assert (tmp_path / "broken.jpg").read_bytes() == b"\xff\xd8\xff\xe1\x00\x10Exif"  # left as it was


# ----------------------------------------------------------- schedules, scale and evaluation rules
@pytest.fixture(scope="module")
def short_run_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]:
    """Eight iterations on the synthetic scene logged at every iteration (SH interval 3, no densification)."""
    torch.set_num_threads(2)
    scene, _ = _synthetic_scene()
    s = photo_settings({"train": {"iterations": 8, "log_every": 1, "sh_interval": 3, "sh_degree": 3,
                                  "densify": {"start": 100, "interval": 100, "opacity_reset_interval": 0}}})["train"]
    path = tmp_path_factory.mktemp("short_run") / "train_log.csv"
    train_scene(scene, s, path)
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return scene, s, rows


def test_logged_loss_is_the_3dgs_blend_of_l1_and_dssim(
        short_run_log: tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]) -> None:
    """Each logged loss is (1 - λ) L1 + λ (1 - SSIM) of the logged L1 and D-SSIM (Kerbl et al. 2023, eq. 7)."""
    _, s, rows = short_run_log
    lam = s["lambda_dssim"]
    assert lam == pytest.approx(0.2)
    trained = [r for r in rows if int(r["iteration"]) > 0]
    assert len(trained) == 8
    for r in trained:
        l1, dssim, loss = float(r["l1"]), float(r["dssim"]), float(r["loss"])
        assert l1 > 0.01 and dssim > 0.05  # both terms matter, so a wrong weight shows
        assert loss == pytest.approx((1 - lam) * l1 + lam * dssim, rel=1e-5)


def test_sh_degree_rises_by_one_after_every_interval(
        short_run_log: tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]) -> None:
    """Degree 0 for iterations 1..k, 1 for k+1..2k, 2 for 2k+1..3k (k = sh_interval = 3)."""
    _, _, rows = short_run_log
    got = {int(r["iteration"]): int(r["sh_degree"]) for r in rows}
    assert got == {0: 0, 1: 0, 2: 0, 3: 0, 4: 1, 5: 1, 6: 1, 7: 2, 8: 2}


def test_means_learning_rate_decays_log_linearly_from_lr0_to_lr_final(
        short_run_log: tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]) -> None:
    """lr_means is lr0·extent at the first iteration, lr_final·extent at the last, log-linear between (3DGS's
    exponential decay, get_expon_lr_func)."""
    scene, s, rows = short_run_log
    lr0, lr1 = s["lr"]["means"] * scene.extent, s["lr"]["means_final"] * scene.extent
    got = {int(r["iteration"]): float(r["lr_means"]) for r in rows if int(r["iteration"]) > 0}
    assert got[1] == pytest.approx(lr0, rel=1e-12) and got[8] == pytest.approx(lr1, rel=1e-12)
    for it, lr in got.items():
        t = (it - 1) / 7
        assert lr == pytest.approx(math.exp((1 - t) * math.log(lr0) + t * math.log(lr1)), rel=1e-12)


def test_seed_scale_is_the_rms_distance_to_the_three_nearest_other_points() -> None:
    """init_scale × sqrt(mean of the 3 smallest squared distances to other points), as 3DGS's distCUDA2 (brute
    force over all pairs, self excluded)."""
    from ctsplat.photos.train import init_params

    rng = np.random.default_rng(5)
    xyz = rng.uniform(-1, 1, (9, 3))
    s = {**photo_settings()["train"], "init_scale": 0.7}
    params = init_params(xyz, np.full((9, 3), 0.5), s, rng)
    d2 = ((xyz[:, None] - xyz[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    want = 0.7 * np.sqrt(np.sort(d2, axis=1)[:, :3].mean(1))
    got = torch.exp(params["log_scales"]).detach().double().numpy()
    np.testing.assert_allclose(got, np.repeat(want[:, None], 3, axis=1), rtol=1e-6)


def test_scene_extent_is_1_1_times_the_camera_ring_radius() -> None:
    """Cameras on a circle of radius r about their mean centre give 1.1·r (3DGS getNerfppNorm)."""
    centre = np.array([2.0, -1.0, 0.5])
    r = 3.0
    Rs, ts = [], []
    for k in range(7):
        a = 2 * np.pi * k / 7
        c = centre + r * np.array([np.cos(a), np.sin(a), 0.0])
        R, t = look_at(c, centre + [0.0, 0.0, -1.0], (0, 0, 1))
        Rs.append(R)
        ts.append(t)
    assert scene_extent(Rs, ts) == pytest.approx(1.1 * r, rel=1e-9)


def test_downscaled_size_rounds_to_nearest_like_the_loaded_image(tmp_path: Path) -> None:
    """1063x709 / 4 is 266x177 (round(265.75), round(177.25)) for the camera and for the loaded image alike."""
    from PIL import Image

    from ctsplat.photos.images import load_rgb

    path = tmp_path / "odd.png"
    Image.fromarray(np.zeros((709, 1063, 3), np.uint8)).save(path)
    q = PinholeCamera(1063, 709, 900.0, 900.0, 531.5, 354.5).scaled(4)
    assert (q.width, q.height) == (266, 177)
    assert load_rgb(path, 4).shape == (q.height, q.width, 3)
    assert q.fx == pytest.approx(900.0 * 266 / 1063) and q.fy == pytest.approx(900.0 * 177 / 709)


def test_turntable_ring_sits_at_the_photographs_mean_height() -> None:
    """The turntable cameras circle at the cameras' mean height above the point they look at (here 1.5)."""
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    views = []
    for k in range(8):
        a = 2 * np.pi * k / 8
        c = np.array([3 * np.cos(a), 3 * np.sin(a), 1.5 + (0.5 if k % 2 else -0.5)])  # heights 1 and 2
        R, t = look_at(c, np.zeros(3), (0, 0, 1))
        views.append(PhotoView(f"{k}.png", torch.zeros(24, 32, 3), cam, R, t, "train"))
    poses = turntable_poses(views, 6)
    centres = np.stack([-R.T @ t for R, t in poses])
    np.testing.assert_allclose(centres[:, 2], 1.5, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(centres[:, :2], axis=1), 3.0, atol=1e-6)


def _skimage_ssim(img: np.ndarray, ref: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(img, ref, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                       data_range=1.0, channel_axis=2))


def test_evaluation_ssim_is_the_mean_of_per_view_ssim_and_the_gallery_spans_the_views(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """metrics ssim = mean of per_view_test.csv's SSIM (each skimage's Gaussian SSIM), psnr likewise; the gallery
    shows held-out views evenly spaced over the test set (two of six: the first and the last)."""
    import ctsplat.photos.evaluate as photo_eval

    torch.set_num_threads(2)
    scene, truth = _synthetic_scene()
    for k, v in enumerate(scene.views):
        v.split = "test" if k % 3 == 0 else "train"  # six held-out views: 00, 03, ..., 15
    model = Gaussians.from_values(truth.means, 0.14, 1.0, opacities=0.7, colors=truth.colors * 0.8)  # not the truth
    run = tmp_path / "run"
    run.mkdir()
    model.save(run / "model.pt")
    (run / "config.json").write_text(json.dumps({"sfm_dir": str(tmp_path / "sfm"),
                                                 "train": photo_settings()["train"]}))
    shown: list[list[str]] = []
    monkeypatch.setattr(photo_eval, "save_photo_gallery", lambda path, photos, renders, names, *a: shown.append(names))
    m = evaluate_photos(run, {"turntable_frames": 0, "gallery_views": 2}, scene=scene)
    assert shown == [["00.png", "15.png"]]
    with (run / "per_view_test.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["view_id"] for r in rows] == [f"{k:02d}.png" for k in range(0, 16, 3)]
    ssims = [float(r["ssim2d"]) for r in rows]
    assert 0.3 < min(ssims) and max(ssims) < 0.99  # a model that is not the truth: SSIM well inside (0, 1)
    assert m["ssim"] == pytest.approx(float(np.mean(ssims)), rel=1e-12) and m["ssim"] <= 1
    assert m["psnr"] == pytest.approx(float(np.mean([float(r["psnr2d"]) for r in rows])), rel=1e-12)
    v = scene.split("test")[1]
    with torch.no_grad():
        img = render_view(model, v, background=model.meta.get("background")).image.clamp(0, 1)
    assert ssims[1] == pytest.approx(_skimage_ssim(img.double().numpy(), v.image.double().numpy()), abs=1e-6)


def _densify_params(scales: list[float], opacity: float = 0.9) -> dict[str, torch.Tensor]:
    """Opaque isotropic Gaussians on the x axis (one per scale), seeded like training seeds them."""
    from ctsplat.photos.train import init_params

    n = len(scales)
    xyz = np.stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)], 1)
    params = init_params(xyz, np.full((n, 3), 0.5), photo_settings()["train"], np.random.default_rng(0))
    with torch.no_grad():
        params["log_scales"][:] = torch.log(torch.tensor(scales))[:, None]
        params["opacity_raw"][:] = math.log(opacity / (1 - opacity))
    return params


def test_densify_budget_keeps_the_largest_gradients() -> None:
    """With room for two more Gaussians, the two with the largest mean gradients are the ones cloned."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    params = _densify_params([0.001] * 6)  # all small (clone) for an extent of 1
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    settings = {**photo_settings()["train"]["densify"], "start": 100, "max_gaussians": 8}
    dens = AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"])
    dens.grad_accum[:] = torch.tensor([5.0, 1.0, 4.0, 2.0, 3.0, 6.0]) * 1e-3  # all above grad_threshold
    dens.grad_count[:] = 1.0
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=100)
    assert (st["cloned"], st["split"], st["pruned"], st["n"]) == (2, 0, 0, 8)
    assert sorted(params["means"][6:, 0].tolist()) == [0.0, 5.0]  # copies of Gaussians 0 and 5


@pytest.mark.parametrize(("extent", "cloned", "split"), [(10.0, 1, 1), (1.0, 0, 2)])
def test_clone_split_boundary_is_percent_dense_times_the_extent(extent: float, cloned: int, split: int) -> None:
    """A Gaussian of σ 0.05 is cloned when percent_dense × extent (0.01 × 10) exceeds it and split when not (× 1);
    one of σ 0.5 is split either way."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    params = _densify_params([0.05, 0.5, 0.001, 0.001])
    opt = _optimizer(params, photo_settings()["train"]["lr"], extent)
    settings = {**photo_settings()["train"]["densify"], "start": 100}
    dens = AlphaDensify(settings, iterations=1000, extent=extent, means=params["means"])
    dens.grad_accum[:] = torch.tensor([1e-2, 1e-2, 0.0, 0.0])
    dens.grad_count[:] = 1.0
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=100)
    assert (st["cloned"], st["split"], st["pruned"]) == (cloned, split, 0)
    assert st["n"] == 4 + cloned + split


@pytest.mark.parametrize(("iteration", "wide_pruned"), [(200, False), (300, True)])
def test_size_prune_starts_after_the_first_reset_not_at_it(iteration: int, wide_pruned: bool) -> None:
    """3DGS prunes by size only when iteration > opacity_reset_interval: a step at the reset itself keeps wide
    Gaussians, the next one prunes them."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    params = _three_gaussians()  # wide (0.5 x the extent of 1), small, transparent
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    settings = {**photo_settings()["train"]["densify"], "start": 100, "opacity_reset_interval": 200}
    dens = AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"])
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=iteration)
    widths = torch.exp(params["log_scales"]).max(-1).values
    assert st["pruned"] == 1 + wide_pruned and st["cloned"] == st["split"] == 0
    assert bool((widths > 0.1).any()) != wide_pruned


def _one_camera_model(tmp_path: Path, monkeypatch, params: list[float]) -> Path:
    """An SfM folder whose model (read through a stand-in for pycolmap) holds one 32 x 24 PINHOLE photo, 01.jpg."""
    from types import SimpleNamespace

    from ctsplat.photos import dataset

    sparse = tmp_path / "sfm" / "sparse" / "0"
    sparse.mkdir(parents=True)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (sparse / name).write_bytes(b"")
    cam = SimpleNamespace(model=SimpleNamespace(name="PINHOLE"), params=params, width=32, height=24)
    image = SimpleNamespace(name="01.jpg", camera_id=1, has_pose=True)
    monkeypatch.setattr(dataset, "_read_model", lambda sparse: SimpleNamespace(
        images={1: image}, cameras={1: cam}, points3D={}))
    return tmp_path / "sfm"


def test_a_pinhole_camera_with_no_focal_length_is_impossible(tmp_path: Path, monkeypatch) -> None:
    """A cameras.bin cut short reads as focal lengths of 0: the camera is refused, and load_scene names the model
    as damaged (not a renderer error about cone-beam distances later)."""
    from ctsplat.photos import dataset

    for args, needle in (((32, 24, 0.0, 0.0, 16.0, 12.0), "focal lengths must be > 0 px, got fx 0.0, fy 0.0"),
                         ((32, 24, 30.0, float("nan"), 16.0, 12.0), "fy must be a finite number of pixels"),
                         ((32, 24, 30.0, 30.0, None, 12.0), "cx must be a finite number of pixels, got None")):
        with pytest.raises(CtsplatError, match=re.escape(needle)):
            dataset.PinholeCamera(*args)
    assert dataset.PinholeCamera(32, 24, np.float32(30.0), 30.0, 16.0, 12.0).fx == 30.0  # NumPy scalars are numbers
    sfm = _one_camera_model(tmp_path, monkeypatch, [0.0, 0.0, 16.0, 12.0])
    with pytest.raises(CtsplatError, match=r"gives 01\.jpg an impossible camera \(pinhole camera focal lengths must be "
                                           r"> 0 px, got fx 0\.0, fy 0\.0\); it is damaged"):
        dataset.load_scene(sfm)


def test_photos_smaller_than_the_ssim_window_are_refused_naming_the_downscale(tmp_path: Path, monkeypatch) -> None:
    from ctsplat.photos import dataset
    from ctsplat.training.losses import gaussian_window

    assert dataset.SSIM_WINDOW_PX == gaussian_window().numel()
    sfm = _one_camera_model(tmp_path, monkeypatch, [30.0, 30.0, 16.0, 12.0])
    with pytest.raises(CtsplatError, match=r"01\.jpg is 8 x 6 px at downscale 4, smaller than the 11 px SSIM window .*"
                                           r"lower the downscale \(train\.downscale\)"):
        dataset.load_scene(sfm, downscale=4)
