"""``ctsplat photos-sfm``, ``photos-train`` and ``photos-run``: the sanity run on ordinary photographs.

``photos-sfm`` poses a photo folder with COLMAP, ``photos-train`` trains alpha 3DGS on the result and evaluates it
on the held-out photos (gallery, turntable, metrics.json), ``photos-run`` does both into one folder.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import Any

from ctsplat.cli._common import apply_sets, load_section

_METRIC_KEYS = ("psnr", "ssim", "lpips", "n_test", "resolution", "n_gaussians", "fps", "peak_rss_mb")


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    """The filled ``photos`` section from ``--config`` and ``--set`` (keys like ``train.iterations=3000``)."""
    from ctsplat.config import check_section
    from ctsplat.photos.config import photo_settings

    user = check_section("photos", apply_sets(load_section(args.config, "photos"), args.set))
    s = photo_settings(user)
    if getattr(args, "attribution", None) is not None:
        s["evaluate"]["attribution"] = args.attribution
    return s


def _sfm(args: argparse.Namespace) -> None:
    from ctsplat.photos.config import SFM_SUMMARY_KEYS
    from ctsplat.photos.sfm import run_photo_sfm

    s = _settings(args)
    summary = run_photo_sfm(args.images, args.out_dir, s["sfm"])
    print(json.dumps({k: summary.get(k) for k in SFM_SUMMARY_KEYS}))


def _train_and_evaluate(sfm_dir: str | Path, out_dir: str | Path, s: dict[str, Any]) -> dict[str, Any]:
    """Train and evaluate in the run's temporary folder, which replaces ``out_dir`` only when both succeed."""
    from ctsplat.photos.train import train_photos
    from ctsplat.utils import read_json_object

    train_photos(sfm_dir, out_dir, s["train"], evaluate=s["evaluate"])
    return read_json_object(Path(out_dir) / "metrics.json", what="photo metrics", fix="run photos-train again")


def _train(args: argparse.Namespace) -> None:
    m = _train_and_evaluate(args.sfm_dir, args.out_dir, _settings(args))
    print(json.dumps({k: m.get(k) for k in _METRIC_KEYS}))


def _run(args: argparse.Namespace) -> None:
    from ctsplat.photos.config import SFM_SUMMARY_KEYS
    from ctsplat.photos.sfm import run_photo_sfm
    from ctsplat.photos.train import check_run

    s = _settings(args)
    out = Path(args.out_dir)
    check_run(out / "run", s["train"])  # before the SfM step, not after it
    summary = run_photo_sfm(args.images, out / "sfm", s["sfm"])
    # an earlier run was trained on the SfM model just replaced: should training fail, it must not be left
    # beside poses in another frame
    shutil.rmtree(out / "run", ignore_errors=True)
    m = _train_and_evaluate(out / "sfm", out / "run", s)
    print(json.dumps({**{k: summary.get(k) for k in SFM_SUMMARY_KEYS}, **{k: m.get(k) for k in _METRIC_KEYS}}))


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML/JSON file with the photos section (or {photos: {...}})")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one photos key, e.g. --set train.iterations=3000 --set train.downscale=2")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "photos-sfm", help="COLMAP poses of a folder of photographs (undistorted PINHOLE scene)",
        description="SIFT features, exhaustive (small sets) or sequential matching, incremental (default) or global "
                    "mapping and undistortion: writes OUT_DIR/images, OUT_DIR/sparse/0 and OUT_DIR/summary.json "
                    "(registered and unregistered images, mean reprojection error, points).")
    p.add_argument("images", help="folder of JPEG/PNG/TIFF photographs")
    p.add_argument("out_dir", help="output folder (replaced on success)")
    _common(p)
    p.set_defaults(func=_sfm)

    p = subparsers.add_parser(
        "photos-train", help="alpha 3DGS with SH colour on a photos-sfm folder, evaluated on held-out photos",
        description="Train on every image but each 8th (the held-out test views), then write metrics.json, "
                    "per_view_test.csv, figures/gallery.png and figures/turntable.gif into OUT_DIR.")
    p.add_argument("sfm_dir", help="output folder of `ctsplat photos-sfm`")
    p.add_argument("out_dir", help="run folder (replaced on success)")
    p.add_argument("--attribution", help="credit line of the photographs, printed on the gallery and turntable")
    _common(p)
    p.set_defaults(func=_train)

    p = subparsers.add_parser(
        "photos-run", help="photos-sfm then photos-train: OUT_DIR/sfm and OUT_DIR/run",
        description="The whole sanity run on a folder of photographs: COLMAP poses into OUT_DIR/sfm, training and "
                    "held-out evaluation (metrics.json, gallery, turntable) into OUT_DIR/run.")
    p.add_argument("images", help="folder of JPEG/PNG/TIFF photographs")
    p.add_argument("out_dir", help="output folder")
    p.add_argument("--attribution", help="credit line of the photographs, printed on the gallery and turntable")
    _common(p)
    p.set_defaults(func=_run)
