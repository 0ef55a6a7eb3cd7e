"""CPU thread scaling of the fused C++ kernels: forward+backward per view and the voxelizer, at 1, 2, ... threads.

Usage::

    python benchmarks/threads.py                       # 1 and 2 threads, 15 repetitions
    python benchmarks/threads.py --threads 1,2,4,8,16 --reps 21

Configurations (the renderer benchmark's scene, :mod:`benchmarks.render`: N Gaussians uniform in a 160 mm cube,
log-uniform scales 0.39..1.95 mm):

* ``render parallel``: radiative forward+backward, 50k Gaussians, 256², parallel beam over 200 mm;
* ``render cone``: the same through a cone-beam camera (source 500 mm from the centre, detector at 1000 mm);
* ``voxelize``: forward+backward of the 50k Gaussians on a 128³ grid over the cube (the evaluation's read-out);
* ``voxelize region``: the same on a 32³ region in the middle of that grid (the 3D TV term's read-out, every
  training iteration).

All thread counts run in this one process, interleaved repetition by repetition (``torch.set_num_threads``, which
the kernels follow), so a load change on a shared machine hits every thread count alike; the table gives the median
time per configuration and thread count, the speed-up over 1 thread and the parallel efficiency. Set
``OMP_WAIT_POLICY=PASSIVE`` (the default here) so that torch's idle OpenMP workers do not spin against the kernel's
threads. Gradients are cleared before every step, as training's ``zero_grad(set_to_none=True)`` does (no
accumulation into the previous step's gradients). Writes ``benchmarks/out/threads.csv``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import pandas as pd
from _common import cli_main, write_csv

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

OUT = Path(__file__).resolve().parent / "out"


def _scene(n: int, seed: int = 0):
    import torch

    from ctsplat.splat.gaussians import Gaussians

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 160.0
    lo, hi = math.log(0.39), math.log(1.95)
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g))
    dens = 0.05 + 0.5 * torch.rand(n, generator=g)
    gs = Gaussians.from_values(means, scales, dens, torch.randn(n, 4, generator=g))
    for name in ("means", "log_scales", "quats", "density_raw"):
        getattr(gs, name).requires_grad_(True)
    return gs


def _steps(n: int, size: int, grid: int) -> dict:
    """name -> callable running one forward+backward with the fused kernel."""
    import torch

    from ctsplat.geometry import ConeCamera, ParallelCamera
    from ctsplat.splat.render import render, voxelize

    gs = _scene(n)
    R = torch.eye(3)
    par = ParallelCamera(size, size, 200.0 / size)
    cone = ConeCamera(size, size, 2 * 200.0 / size, 500.0, 1000.0)
    t_par, t_cone = torch.tensor([0.0, 0.0, 300.0]), torch.tensor([0.0, 0.0, 500.0])
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= 160.0 / grid
    affine[:3, 3] = -80.0 + 80.0 / grid

    params = [getattr(gs, name) for name in ("means", "log_scales", "quats", "density_raw")]

    def clear() -> None:  # as training's zero_grad(set_to_none=True): no accumulation into old gradients
        for p in params:
            p.grad = None

    def fwd_bwd(cam, t):
        def step() -> None:
            clear()
            out = render(gs, cam, R, t, compositor="radiative", backend="kernel")
            out.image.sum().backward()
        return step

    def vox() -> None:
        clear()
        v = voxelize(gs, (grid, grid, grid), affine, backend="kernel")
        v.sum().backward()

    lo, hi = grid // 2 - grid // 8, grid // 2 + grid // 8
    region = ((lo, hi),) * 3

    def vox_region() -> None:
        clear()
        v = voxelize(gs, (grid, grid, grid), affine, region=region, backend="kernel")
        v.square().sum().backward()

    return {f"render parallel {n // 1000}k {size}²": fwd_bwd(par, t_par),
            f"render cone {n // 1000}k {size}²": fwd_bwd(cone, t_cone),
            f"voxelize {n // 1000}k {grid}³": vox, f"voxelize {n // 1000}k region {hi - lo}³": vox_region}


def run(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", default="1,2", help="comma-separated thread counts (default 1,2)")
    p.add_argument("--reps", type=int, default=15, help="timed repetitions per configuration and thread count")
    p.add_argument("--n", type=int, default=50_000, help="Gaussians")
    p.add_argument("--size", type=int, default=256, help="image side, px")
    p.add_argument("--grid", type=int, default=128, help="voxelizer grid side")
    args = p.parse_args(argv)
    from ctsplat.utils import CtsplatError

    try:
        threads = [int(x) for x in args.threads.split(",")]
    except ValueError:
        raise CtsplatError(f"--threads {args.threads!r}: expected comma-separated integers, e.g. 1,2") from None
    if min(threads) < 1 or min(args.reps, args.n, args.size, args.grid) < 1:
        raise CtsplatError("--threads, --reps, --n, --size and --grid must be at least 1")
    import torch

    from ctsplat.splat import _kernel

    if not _kernel.available():
        raise CtsplatError(f"the fused C++ kernel is unavailable ({_kernel._failed}); install a C++ compiler")
    steps = _steps(args.n, args.size, args.grid)
    rows = []
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start; "
          f"median of {args.reps} interleaved repetitions")
    print(f"{'configuration':28s} " + " ".join(f"{f'{k} thr (ms)':>12s}" for k in threads)
          + f" {'speed-up':>9s} {'efficiency':>10s}")
    for name, step in steps.items():
        times: dict[int, list[float]] = {k: [] for k in threads}
        for k in threads:  # warm-up: kernel build, first-touch of the per-thread buffers
            torch.set_num_threads(k)
            step()
        for _ in range(args.reps):
            for k in threads:
                torch.set_num_threads(k)
                t0 = time.perf_counter()
                step()
                times[k].append(time.perf_counter() - t0)
        med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
        kmax = threads[-1]
        speed = med[threads[0]] / med[kmax] * threads[0]
        eff = speed / kmax
        print(f"{name:28s} " + " ".join(f"{med[k]:12.2f}" for k in threads) + f" {speed:8.2f}x {eff:9.0%}")
        for k in threads:
            rows.append({"configuration": name, "threads": k, "median_ms": round(med[k], 3),
                         "min_ms": round(1e3 * min(times[k]), 3), "speedup_vs_1": round(med[threads[0]] / med[k]
                                                                                          * threads[0], 3),
                         "reps": args.reps, "load_avg_1min": round(os.getloadavg()[0], 2)})
    write_csv(pd.DataFrame(rows), OUT / "threads.csv")
    print(f"load average {os.getloadavg()[0]:.2f} at the end; wrote {OUT / 'threads.csv'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """:func:`run` with the benchmarks' one-line errors and clean Ctrl-C / SIGTERM exits (:func:`_common.cli_main`)."""
    return cli_main(run, argv, "threads.py")


if __name__ == "__main__":
    sys.exit(main())
