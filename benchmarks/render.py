"""Renderer benchmark: forward+backward time per view vs N and image size, 1080p forward FPS, peak memory.

Usage::

    python benchmarks/render.py                 # full grid (N = 10k..500k x 128², 256², 512²), 2 threads
    python benchmarks/render.py --quick         # N = 10k, 50k x 128², 256²
    python benchmarks/render.py --threads 1 --compositor radiative_unrectified --reference

Scene: N Gaussians uniform in a 160 mm cube, random rotations, log-uniform scales 0.39..1.95 mm (0.5..2.5 px at
256² over a 200 mm field of view), parallel beam. The field of view is fixed, so the footprint area in pixels grows
with the pixel count and the work per view is proportional to N × pixels: linear scaling means the ratios printed
below (time ratio / size ratio) stay near 1. Every configuration runs in a fresh subprocess (with
``OMP_WAIT_POLICY=PASSIVE`` unless set) so that its peak resident memory (``ru_maxrss``) is its own. Prints a table
and writes ``benchmarks/out/render.csv``. The machine's load average is recorded with every row (timings on a
shared CPU are noisy: report them as measured).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import time
from pathlib import Path

from _common import cli_main, run_child, write_csv

OUT = Path(__file__).resolve().parent / "out"
FOV_MM = 200.0


def _scene(n: int, device: str, seed: int = 0):
    import torch

    from ctsplat.splat.gaussians import Gaussians

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 160.0
    lo, hi = math.log(0.39), math.log(1.95)
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g))
    dens = 0.05 + 0.5 * torch.rand(n, generator=g)
    quats = torch.randn(n, 4, generator=g)
    gs = Gaussians.from_values(means, scales, dens, quats, opacities=torch.full((n,), 0.5), device=device)
    for name in ("means", "log_scales", "quats", "density_raw", "opacity_raw"):
        getattr(gs, name).requires_grad_(True)
    return gs


def run_one(n: int, width: int, height: int, mode: str, backend: str, compositor: str, device: str,
            threads: int, budget_s: float) -> dict:
    """Time one configuration in this process; ``mode`` is 'fwdbwd', 'fwd' or 'voxelize' (grid width³)."""
    import torch

    from ctsplat.geometry import ParallelCamera
    from ctsplat.splat import _kernel
    from ctsplat.splat.render import render

    torch.set_num_threads(threads)
    spacing = FOV_MM / min(width, height)
    cam = ParallelCamera(width, height, spacing)
    R = torch.eye(3, device=device)
    t = torch.tensor([0.0, 0.0, 300.0], device=device)
    gs = _scene(n, device)
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()

    def step() -> None:
        if mode == "fwd":
            with torch.no_grad():
                render(gs, cam, R, t, compositor=compositor, backend=backend)
        else:
            out = render(gs, cam, R, t, compositor=compositor, backend=backend)
            out.image.sum().backward()
        sync()

    if mode == "voxelize":
        from ctsplat.splat.render import voxelize

        affine = torch.eye(4, dtype=torch.float64)
        affine[:3, :3] *= FOV_MM / width  # grid covering the field of view
        affine[:3, 3] = -FOV_MM / 2

        def step() -> None:  # noqa: F811
            vol = voxelize(gs, (width, width, width), affine)
            (vol * vol).sum().backward()
            sync()
    else:
        step()  # warm-up (kernel build / load, allocator)
    wall, cpu = [], []
    t_start = time.perf_counter()
    min_reps = 1 if mode == "voxelize" else 3
    while len(wall) < min_reps or (time.perf_counter() - t_start < budget_s and len(wall) < 15):
        c0, w0 = time.process_time(), time.perf_counter()
        step()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    wall.sort()
    cpu.sort()
    used_kernel = device == "cpu" and backend != "reference" and _kernel.available()
    peak = (torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda")
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return {
        "mode": mode, "compositor": compositor, "device": device, "backend": "kernel" if used_kernel else "reference",
        "threads": threads, "n_gaussians": n, "width": width, "height": height, "pixels": width * height,
        "reps": len(wall), "ms_median": 1e3 * wall[len(wall) // 2], "ms_min": 1e3 * wall[0],
        "cpu_ms_median": 1e3 * cpu[len(cpu) // 2], "fps": 1.0 / wall[len(wall) // 2],
        "peak_mem_mb": peak, "loadavg_1min": os.getloadavg()[0],
    }


def _spawn(args: list[str]) -> dict:
    # PASSIVE: idle OpenMP workers of torch sleep instead of spinning -- on a shared, overloaded CPU spinning
    # workers steal the cores the other thread needs (measured here: 2-thread fwd+bwd 5x slower without it)
    env = dict(os.environ, OMP_NUM_THREADS=args[args.index("--threads") + 1])
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    res = run_child([sys.executable, __file__, "--one", *args], env=env)
    if res.returncode != 0:
        raise RuntimeError(res.stderr.strip().splitlines()[-1] if res.stderr.strip() else "benchmark child failed")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _voxelize_arg(text: str) -> tuple[int, int]:
    """``N:S`` -> (N Gaussians, S³ grid), both >= 1."""
    try:
        n, size = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N:S (e.g. 500000:256), got {text!r}") from None
    if n < 1 or size < 1:
        raise argparse.ArgumentTypeError(f"N and S must be >= 1, got {text!r}")
    return n, size


def run(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--one"]:  # child process: one configuration, JSON on stdout
        q = argparse.ArgumentParser()
        for k in ("--n", "--width", "--height", "--threads"):
            q.add_argument(k, type=int, required=True)
        for k in ("--mode", "--backend", "--compositor", "--device"):
            q.add_argument(k, required=True)
        q.add_argument("--budget-s", type=float, required=True)
        o = q.parse_args(argv[1:])
        print(json.dumps(run_one(o.n, o.width, o.height, o.mode, o.backend, o.compositor, o.device, o.threads,
                                 o.budget_s)))
        return 0
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--compositor", choices=["radiative", "radiative_unrectified", "alpha"],
                   help="compositor of the render grid (default radiative)")
    p.add_argument("--reference", action="store_true", help="also time the pure-PyTorch reference (N <= 50k)")
    p.add_argument("--budget-s", type=float, default=4.0, help="time budget per configuration (>= 3 reps)")
    p.add_argument("--voxelize", type=_voxelize_arg, default=None, metavar="N:S",
                   help="also time voxelize fwd+bwd of N Gaussians on an S³ grid (peak memory), e.g. 500000:256")
    p.add_argument("--only-voxelize", action="store_true", help="skip the render grid")
    a = p.parse_args(argv)
    if a.only_voxelize and not a.voxelize:
        p.error("--only-voxelize needs --voxelize N:S (otherwise nothing runs)")
    if a.only_voxelize and (a.reference or a.quick or a.compositor):
        p.error("--reference, --quick and --compositor apply to the render grid, which --only-voxelize skips")
    if a.threads < 1 or a.budget_s < 0:
        p.error("--threads must be >= 1 and --budget-s >= 0")
    compositor = a.compositor or "radiative"

    import pandas as pd
    import torch

    ns = [10_000, 50_000] if a.quick else [10_000, 50_000, 200_000, 500_000]
    sizes = [128, 256] if a.quick else [128, 256, 512]
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    jobs = []
    for dev in devices if not a.only_voxelize else []:
        for n in ns:
            for s in sizes:
                jobs.append((n, s, s, "fwdbwd", "auto", dev))
        if a.reference and dev == "cpu":
            for n in [n for n in ns if n <= 50_000]:
                jobs.append((n, 256, 256, "fwdbwd", "reference", dev))
        jobs.append((50_000 if a.quick else 200_000, 1920, 1080, "fwd", "auto", dev))
    if a.voxelize:
        nv, sv = a.voxelize
        jobs.append((nv, sv, sv, "voxelize", "auto", "cpu"))
    rows = []
    print(f"load average at start: {os.getloadavg()}; {os.cpu_count()} CPUs; threads={a.threads}", flush=True)
    for n, w, h, mode, backend, dev in jobs:
        args = ["--n", str(n), "--width", str(w), "--height", str(h), "--mode", mode, "--backend", backend,
                "--compositor", compositor, "--device", dev, "--threads", str(a.threads),
                "--budget-s", str(a.budget_s)]
        try:
            row = _spawn(args)
        except RuntimeError as exc:
            print(f"FAILED {n} {w}x{h} {mode} {backend} {dev}: {exc}", flush=True)
            continue
        rows.append(row)
        print(f"{row['device']:4s} {row['backend']:9s} {row['mode']:6s} N={n:>7d} {w}x{h}: "
              f"{row['ms_median']:9.1f} ms (min {row['ms_min']:.1f}, cpu {row['cpu_ms_median']:.1f}) "
              f"peak {row['peak_mem_mb']:.0f} MB  load {row['loadavg_1min']:.1f}", flush=True)
    if not rows:
        print("no configuration succeeded")
        return 1
    df = pd.DataFrame(rows)
    OUT.mkdir(parents=True, exist_ok=True)
    csv = OUT / ("render_voxelize.csv" if a.only_voxelize else "render.csv")
    write_csv(df, csv)
    print()
    cols = ["device", "backend", "mode", "n_gaussians", "width", "height", "ms_median", "ms_min", "cpu_ms_median",
            "fps", "peak_mem_mb", "loadavg_1min"]
    print(df[cols].to_string(index=False, float_format=lambda x: f"{x:.1f}"))
    # linear-scaling ratios: (time ratio) / (work ratio) between consecutive sizes; ~1 = linear. Process CPU time
    # is used: on a shared machine the wall time mostly measures the other users' load.
    fb = df[(df["mode"] == "fwdbwd") & (df["backend"] != "reference")]
    if fb.empty:
        print(f"wrote {csv}")
        return 0
    print("\nscaling in N (per image size), CPU time: t(N2)/t(N1) / (N2/N1)")
    for (dev, w), grp in fb.groupby(["device", "width"]):
        grp = grp.sort_values("n_gaussians")
        r = [f"{b.n_gaussians // 1000}k/{a_.n_gaussians // 1000}k: "
             f"{(b.cpu_ms_median / a_.cpu_ms_median) / (b.n_gaussians / a_.n_gaussians):.2f}"
             for a_, b in zip(grp.itertuples(), list(grp.itertuples())[1:], strict=False)]
        print(f"  {dev} {w}²: " + ", ".join(r))
    print("scaling in pixels (per N), CPU time: t(P2)/t(P1) / (P2/P1)")
    for (dev, n), grp in fb.groupby(["device", "n_gaussians"]):
        grp = grp.sort_values("pixels")
        r = [f"{b.width}²/{a_.width}²: {(b.cpu_ms_median / a_.cpu_ms_median) / (b.pixels / a_.pixels):.2f}"
             for a_, b in zip(grp.itertuples(), list(grp.itertuples())[1:], strict=False)]
        print(f"  {dev} N={n // 1000}k: " + ", ".join(r))
    target = fb[(fb["n_gaussians"] == 50_000) & (fb["width"] == 256) & (fb["device"] == "cpu")]
    if len(target):
        tr = target.iloc[0]
        print(f"\ntarget 50k @ 256² fwd+bwd <= 20 ms: median {tr['ms_median']:.1f} ms, min {tr['ms_min']:.1f} ms, "
              f"CPU {tr['cpu_ms_median']:.1f} ms (load {tr['loadavg_1min']:.1f})")
    print(f"wrote {csv}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """:func:`run` with the benchmarks' one-line errors and clean Ctrl-C / SIGTERM exits (:func:`_common.cli_main`)."""
    return cli_main(run, argv, "render.py")


if __name__ == "__main__":
    sys.exit(main())
