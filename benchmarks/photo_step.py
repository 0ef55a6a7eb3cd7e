"""Time of one photo training iteration (render, L1 + D-SSIM, backward) on a trained model, at its final size.

Usage::

    python benchmarks/photo_step.py benchmarks/out/photos/sfm benchmarks/out/photos/run/model.pt
    PYTHONPATH=<worktree of another commit> python benchmarks/photo_step.py SFM MODEL   # that commit's code

What a training iteration of ``ctsplat photos-train`` costs once densification has grown the model (most of the run),
without the optimiser step and density control: each iteration renders one training photo (in the shuffled order
of the seed), takes 3DGS's loss with the library's ``lambda_dssim`` and back-propagates it to every parameter.
The first ``--warmup`` iterations are not timed (kernel build, first-touch pages). Prints one JSON line: the model
size, the image size, the threads and the median and mean seconds per iteration; ``--csv`` adds it as a row (the
table is written whole).
Set ``OMP_WAIT_POLICY=PASSIVE`` (the default here) so that torch's idle OpenMP workers do not spin against the
kernels' threads. Compare two commits by alternating runs with their worktrees on ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from _common import cli_main, earlier_table, write_csv  # noqa: E402

_PARAMS = ("means", "log_scales", "quats", "opacity_raw", "colors", "sh_rest")
#: The columns of a ``--csv`` row.
ROW_COLUMNS = ("code_version", "n_gaussians", "width", "height", "threads", "iterations", "median_s", "mean_s")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="photo_step.py", description=__doc__.split("\n\n")[0])
    p.add_argument("sfm_dir", help="the photos-sfm folder the model was trained on")
    p.add_argument("model", help="a trained model.pt of photos-train")
    p.add_argument("--downscale", type=int, default=4, help="image downscale of the training run (default 4)")
    p.add_argument("--iterations", type=int, default=40, help="timed iterations (default 40)")
    p.add_argument("--warmup", type=int, default=5, help="untimed iterations first (default 5)")
    p.add_argument("--threads", type=int, default=2, help="torch and kernel threads (default 2)")
    p.add_argument("--seed", type=int, default=0, help="order of the training photos (default 0)")
    p.add_argument("--csv", type=Path, default=None, help="add the result as a row of this CSV")
    return p


def run(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    import numpy as np
    import torch

    from ctsplat.photos.config import photo_settings
    from ctsplat.photos.dataset import load_scene
    from ctsplat.photos.train import render_view, to_gaussians
    from ctsplat.splat.gaussians import Gaussians
    from ctsplat.training.losses import ssim
    from ctsplat.utils import CtsplatError, code_version

    if args.iterations < 1 or args.warmup < 0 or args.threads < 1:
        raise CtsplatError("--iterations and --threads must be at least 1 and --warmup at least 0")
    earlier = earlier_table(args.csv) if args.csv is not None else None  # checked before the timing
    if earlier is not None and list(earlier.columns) != list(ROW_COLUMNS):
        raise CtsplatError(f"--csv {args.csv} holds columns {','.join(map(str, earlier.columns))}, not this "
                           f"benchmark's ({','.join(ROW_COLUMNS)}); give another file")
    torch.set_num_threads(args.threads)
    lam = float(photo_settings()["train"]["lambda_dssim"])
    scene = load_scene(args.sfm_dir, downscale=args.downscale)
    train = scene.split("train")
    g0 = Gaussians.load(args.model)
    params = {k: t.detach().clone().requires_grad_(True) for k in _PARAMS if (t := getattr(g0, k)) is not None}
    order = np.random.default_rng(args.seed).permutation(len(train))
    times = []
    for k in range(args.warmup + args.iterations):
        view = train[order[k % len(train)]]
        t0 = time.perf_counter()
        img = render_view(to_gaussians(params, g0.sh_degree), view, background=torch.zeros(3)).image
        l1 = torch.mean(torch.abs(img - view.image))
        dssim = 1.0 - ssim(img.permute(2, 0, 1), view.image.permute(2, 0, 1), 1.0)
        ((1 - lam) * l1 + lam * dssim).backward()
        for p in params.values():
            p.grad = None
        if k >= args.warmup:
            times.append(time.perf_counter() - t0)
    row = {"code_version": code_version(), "n_gaussians": int(params["means"].shape[0]),
           "width": int(train[0].camera.width), "height": int(train[0].camera.height), "threads": args.threads,
           "iterations": args.iterations, "median_s": statistics.median(times), "mean_s": statistics.fmean(times)}
    print(json.dumps(row))
    if args.csv is not None:  # one row added to the table, which is written whole
        import pandas as pd

        table = pd.concat([earlier, pd.DataFrame([row])], ignore_index=True) if earlier is not None else \
            pd.DataFrame([row])
        write_csv(table, args.csv)
    return 0


def main(argv: list[str] | None = None) -> int:
    return cli_main(run, argv, "photo_step.py")


if __name__ == "__main__":
    sys.exit(main())
