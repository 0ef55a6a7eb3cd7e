"""Projector benchmark: parallel circular projection vs ``skimage.transform.radon`` (ratio, one run) and
cone-beam throughput in rays x samples per second.

    .venv/bin/python benchmarks/projector.py [--size 128] [--angles 180] [--cone-views 16] [--device cpu]

Volume: the built-in analytic Shepp–Logan phantom rasterised at size^3 (2 mm voxels), zeroed outside the
inscribed cylinder so ``radon(circle=True)`` is valid. Both projectors see the same slices, angles and
detector grid (pixel centres on radon's bins). skimage's radon is single-threaded; torch uses --threads.
Writes benchmarks/out/projector.csv.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from _common import cli_main, write_csv

from ctsplat.geometry import ConeCamera, ParallelCamera, camera_rays, pose_from_angles, sphere_orbit
from ctsplat.phantom import rasterize, shepp_logan_ellipsoids
from ctsplat.projector import clip_rays_to_box, line_integrals

OUT = Path(__file__).resolve().parent / "out"


def phantom_volume(n: int, voxel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    affine = np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    affine[:3, 3] = -voxel_mm * (n // 2)  # voxel n//2 at the origin: skimage's rotation centre
    scale = 0.45 * n * voxel_mm / 0.92  # head fits the volume
    vol = rasterize(shepp_logan_ellipsoids(scale_mm=scale, beads=n >= 64), (n, n, n), affine, supersample=1)
    g = np.arange(n) - n // 2
    vol *= (g[:, None] ** 2 + g[None, :] ** 2 < (n // 2 - 1) ** 2)[:, :, None]
    return (0.019 * vol).astype(np.float32), affine


def n_samples(camera, Rs, ts, affine, vol, step_voxels: float) -> int:
    """Samples the trilinear projector evaluates: Σ over rays of ceil(clipped length / step), rays clipped
    to one voxel around the non-zero voxels as the projector does."""
    nz = np.argwhere(vol != 0)
    lo, hi = nz.min(0) - 1.0, nz.max(0) + 1.0
    Ainv = np.linalg.inv(affine)
    step = step_voxels * float(np.linalg.norm(affine[:3, :3], axis=0).min())
    total = 0
    for R, t in zip(Rs, ts, strict=True):
        o, d = camera_rays(camera, R, t)
        s0, length = clip_rays_to_box(o.reshape(-1, 3) @ Ainv[:3, :3].T + Ainv[:3, 3],
                                      d.reshape(-1, 3) @ Ainv[:3, :3].T, lo, hi)
        total += int(np.ceil(length[length > 0] / step).sum())
    return total


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--angles", type=int, default=180)
    ap.add_argument("--cone-views", type=int, default=16)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--skip-trilinear", action="store_true", help="do not time the trilinear path on the parallel set")
    args = ap.parse_args(argv)
    for name in ("size", "angles", "cone_views", "threads"):
        if getattr(args, name) < (8 if name == "size" else 1):
            ap.error(f"--{name.replace('_', '-')} must be >= {8 if name == 'size' else 1}, got {getattr(args, name)}")
    from ctsplat.utils import CtsplatError, resolve_device

    try:
        resolve_device(args.device)
    except CtsplatError as exc:
        ap.error(f"--device: {exc}")
    torch.set_num_threads(args.threads)
    from skimage.transform import radon

    n, h = args.size, 2.0
    vol, affine = phantom_volume(n, h)
    iso = np.zeros(3)
    theta = np.arange(args.angles) * 180.0 / args.angles
    # radon's bin b sits at (b - n//2) pixels from the centre voxel n//2; our pixel u at (u + 0.5 - n/2): shift
    # the isocentre by half a pixel along the detector (and along z) so both grids coincide for any n
    half = 0.5 * h * (1 - n % 2)
    poses = [pose_from_angles(a, 0.0, iso + half * np.array([np.sin(np.radians(a)), -np.cos(np.radians(a)), -1.0]),
                              2 * n * h) for a in theta]
    Rs, ts = np.stack([R for R, _ in poses]), np.stack([t for _, t in poses])
    cam = ParallelCamera(n, n, h)
    rows = []

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = np.stack([radon(vol[:, :, k], theta=theta, circle=True) for k in range(n)]) * h  # (K, det, angle)
    t_radon = time.perf_counter() - t0
    rows.append({"case": f"parallel circular {n}^3 x {args.angles}", "method": "skimage radon (per slice)",
                 "seconds": t_radon, "ratio_vs_radon": 1.0, "rel_l2_vs_radon": 0.0})

    def compare(p: np.ndarray) -> float:
        mine = np.transpose(p[:, ::-1, :], (1, 2, 0))  # (V, H, W) -> (K, det, angle); row v = slice n-1-k
        inner = (slice(2, n - 2), slice(2, n - 2))
        return float(np.linalg.norm(mine[inner] - ref[inner]) / np.linalg.norm(ref[inner]))

    methods = ["joseph"] + ([] if args.skip_trilinear else ["trilinear"])
    for method in methods:
        t0 = time.perf_counter()
        with torch.no_grad():
            p = line_integrals(vol, affine, cam, Rs, ts, device=args.device, method=method).cpu().numpy()
        sec = time.perf_counter() - t0
        rows.append({"case": f"parallel circular {n}^3 x {args.angles}", "method": f"ctsplat {method}",
                     "seconds": sec, "ratio_vs_radon": sec / t_radon, "rel_l2_vs_radon": compare(p)})

    # cone-beam throughput
    cone = ConeCamera(n, n, h * 1.5, 4.0 * n * h, 6.0 * n * h)
    views = sphere_orbit(args.cone_views, iso, cone.dso_mm, seed=0, split_fractions={"train": 1.0})
    Rc, tc = np.stack([v.R for v in views]), np.stack([v.t for v in views])
    samples = n_samples(cone, Rc, tc, affine, vol, 0.5)
    t0 = time.perf_counter()
    with torch.no_grad():
        line_integrals(vol, affine, cone, Rc, tc, device=args.device)
    sec = time.perf_counter() - t0
    rays = args.cone_views * n * n
    rows.append({"case": f"cone sphere {n}^3 x {args.cone_views} views {n}^2 px", "method": "ctsplat trilinear",
                 "seconds": sec, "rays": rays, "samples": samples, "rays_per_s": rays / sec,
                 "samples_per_s": samples / sec})

    df = pd.DataFrame(rows)
    OUT.mkdir(parents=True, exist_ok=True)
    write_csv(df, OUT / "projector.csv")
    print(f"torch threads: {torch.get_num_threads()}, device: {args.device}, cpu count: {os.cpu_count()}, "
          f"load average: {os.getloadavg()[0]:.1f}")
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(df.to_string(index=False, float_format=lambda x: f"{x:.4g}" if not math.isnan(x) else ""))
    print(f"-> {OUT / 'projector.csv'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """:func:`run` with the benchmarks' one-line errors and clean Ctrl-C / SIGTERM exits (:func:`_common.cli_main`)."""
    return cli_main(run, argv, "projector.py")


if __name__ == "__main__":
    sys.exit(main())
