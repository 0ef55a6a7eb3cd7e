"""Which Gaussians a photo run's held-out photos fail on (:func:`ctsplat.photos.blame.blame_view`).

For every held-out photo of a run folder (the test photos, or the validation photos of a ``holdout: validation``
run): its PSNR, the ``--top`` Gaussians whose removal lowers its squared error most (each removed alone, among
the 50 with the largest first-order gain), their opacity, widest standard deviation (× the scene extent) and
distances from the photo's camera and the nearest training camera (world units), and the PSNR with the first
1 .. ``--top`` of them removed. Writes ``RUN/blame.csv`` (one row per photo and Gaussian) and prints one line per
photo.

Usage::

    python benchmarks/photo_blame.py benchmarks/out/photos/run --top 3
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from _common import cli_main, write_csv

from ctsplat.geometry.cameras import camera_center
from ctsplat.photos.blame import blame_view
from ctsplat.photos.config import held_out_split
from ctsplat.photos.evaluate import run_config, run_scene
from ctsplat.splat.gaussians import Gaussians
from ctsplat.utils import CtsplatError, resolve_device


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="benchmarks/photo_blame.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", help="a folder written by `ctsplat photos-train`")
    ap.add_argument("--top", type=int, default=3, help="Gaussians named and removed per photo (>= 1)")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    for name, value in (("--top", a.top), ("--threads", a.threads)):
        if value < 1:
            raise CtsplatError(f"{name} must be >= 1, got {value}")
    run_dir = Path(a.run_dir)
    cfg = run_config(run_dir)
    torch.set_num_threads(a.threads)
    device = resolve_device(cfg["train"]["device"])
    scene = run_scene(cfg, device)
    g = Gaussians.load(run_dir / "model.pt", device=device)
    bg = g.meta.get("background")
    train = scene.split("train")
    centres = camera_center(np.stack([v.R for v in train]), np.stack([v.t for v in train]))
    means = g.means.detach().cpu().numpy()
    training = run_dir / "training.json"  # the radius the run was trained with (older runs: every camera's)
    extent = scene.extent
    if training.is_file():
        extent = float(json.loads(training.read_text()).get("extent", extent))
    widest = torch.exp(g.log_scales).max(-1).values.cpu().numpy() / extent
    opacity = torch.sigmoid(g.opacity_raw).detach().cpu().numpy()
    rows = []
    for view in scene.split(held_out_split(cfg["train"])):
        r = blame_view(g, view, background=bg, top=a.top)
        own = camera_center(np.asarray(view.R, float), np.asarray(view.t, float))
        for rank, (i, gain, without) in enumerate(zip(r["index"], r["gain"], r["psnr_without"], strict=True), 1):
            rows.append({"photo": view.name, "psnr": r["psnr"], "rank": rank, "gaussian": i, "gain": gain,
                         "opacity": opacity[i], "widest_over_extent": widest[i],
                         "distance_to_camera": float(np.linalg.norm(means[i] - own)),
                         "distance_to_training_camera": float(np.linalg.norm(centres - means[i], axis=1).min()),
                         "psnr_without_first_k": without})
        print(f"{view.name}: {r['psnr']:.2f} dB; without the first 1..{a.top}: "
              + ", ".join(f"{p:.2f}" for p in r["psnr_without"]))
    write_csv(pd.DataFrame(rows), run_dir / "blame.csv")
    return 0


if __name__ == "__main__":
    sys.exit(cli_main(run, None, "benchmarks/photo_blame.py"))
