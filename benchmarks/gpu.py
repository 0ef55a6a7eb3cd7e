"""GPU benchmark of the Triton kernels: forward+backward per view, 1080p forward FPS, voxelizer, 128³ training.

Usage (on a machine with a CUDA GPU and the ``gpu`` extra, ``pip install -e '.[gpu]'``)::

    python benchmarks/gpu.py                 # every row, training included (needs ../shared/data/ct0051_head)
    python benchmarks/gpu.py --train-sizes 128 256
    python benchmarks/gpu.py --no-train      # kernels only
    python benchmarks/gpu.py --reference     # also time the pure-PyTorch reference on the GPU

Rows (the issue's targets in brackets):

* ``fwd+bwd 50k 256²``: render + ``backward()`` of the radiative compositor, 50k Gaussians, parallel and cone beam,
  and the alpha compositor [≤ 1 ms on a data-centre GPU];
* ``fwd 1920x1080 200k``: forward only, no gradient [≥ 100 FPS];
* ``voxelize 50k 128³``: forward+backward of the volume read-out (the 3D TV term's, on the whole grid);
* ``train S³ 50 views``: ``benchmarks/protocol.py --volumes ct0051_head --views 50 --size S --set device=cuda
  --baseline-set methods=[fdk]`` (R²-Gaussian's cone-beam protocol on the head, the Gaussians' time to final
  quality, seed included) [128³: ≤ 1 minute; 256³ with 512² detectors (``--train-sizes 256``): ≤ 5 minutes].

Scene: :mod:`benchmarks.render`'s (N Gaussians uniform in a 160 mm cube, log-uniform scales 0.39..1.95 mm, 200 mm
field of view). Times are medians over repetitions after a warm-up (Triton compiles each kernel on first use),
with ``torch.cuda.synchronize()`` around each. Prints the GPU's name with a table and writes
``benchmarks/out/gpu.csv``. Exits with status 2 and a message when no CUDA device (or no triton) is present.
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import os
import statistics
import sys
import time
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "out"
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from _common import cli_main, run_child, write_csv  # noqa: E402


def _time(step, reps: int, budget_s: float) -> tuple[float, int]:
    import torch

    step()  # warm-up: Triton JIT, allocator
    torch.cuda.synchronize()
    times = []
    t_start = time.perf_counter()
    while len(times) < reps or (time.perf_counter() - t_start < budget_s and len(times) < 10 * reps):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        step()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), len(times)


def kernel_rows(backends: list[str], reps: int, budget_s: float) -> list[dict]:
    import torch
    from render import _scene  # benchmarks/render.py: the same scene as the CPU rows

    from ctsplat.geometry import ConeCamera, ParallelCamera
    from ctsplat.splat.render import render, voxelize

    dev = "cuda"
    g50, g200 = _scene(50_000, dev), _scene(200_000, dev)
    R = torch.eye(3, device=dev)
    t_par, t_cone = torch.tensor([0.0, 0.0, 300.0], device=dev), torch.tensor([0.0, 0.0, 500.0], device=dev)
    par = ParallelCamera(256, 256, 200.0 / 256)
    cone = ConeCamera(256, 256, 2 * 200.0 / 256, 500.0, 1000.0)
    hd = ParallelCamera(1920, 1080, 200.0 / 1080)
    grid = 128
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= 160.0 / grid
    affine[:3, 3] = -80.0 + 80.0 / grid

    def fwd_bwd(cam, t, comp: str, backend: str):
        def step() -> None:
            out = render(g50, cam, R, t, compositor=comp, backend=backend)
            out.image.sum().backward()
        return step

    def fwd_hd(backend: str):
        def step() -> None:
            with torch.no_grad():
                render(g200, hd, R, t_par, backend=backend)
        return step

    def vox(backend: str):
        def step() -> None:
            v = voxelize(g50, (grid, grid, grid), affine, backend=backend)
            v.sum().backward()
        return step

    rows = []
    for backend in backends:
        for name, step in (("fwd+bwd 50k 256² radiative parallel", fwd_bwd(par, t_par, "radiative", backend)),
                           ("fwd+bwd 50k 256² radiative cone", fwd_bwd(cone, t_cone, "radiative", backend)),
                           ("fwd+bwd 50k 256² alpha parallel", fwd_bwd(par, t_par, "alpha", backend)),
                           ("fwd 1920x1080 200k radiative", fwd_hd(backend)),
                           ("voxelize 50k 128³ fwd+bwd", vox(backend))):
            med, n = _time(step, reps, budget_s)
            rows.append({"row": name, "backend": backend, "median_ms": 1e3 * med, "fps": 1.0 / med, "reps": n})
    return rows


def train_row(data: str, size: int) -> dict | None:
    """The 50-view head protocol at ``size``³ (detectors ``2 size`` px) on the GPU through benchmarks/protocol.py,
    FDK as its only classical method (the Gaussians' time is the row); None (with a message) without the data."""
    if not (Path(data) / "ct0051_head").is_dir():
        print(f"train row skipped: ct0051_head not found in {data}", file=sys.stderr)
        return None
    from ctsplat.utils import CtsplatError

    out = OUT / f"gpu_protocol_s{size}"
    cmd = [sys.executable, str(HERE / "protocol.py"), "--volumes", "ct0051_head", "--views", "50", "--size",
           str(size), "--threads", str(os.cpu_count() or 1), "--set", "device=cuda", "--baseline-set",
           "methods=[fdk]", "--data", data, "--out", str(out)]
    t0 = time.perf_counter()
    # ROOT first, the caller's PYTHONPATH kept: a machine may hold the dependencies in a folder named there
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    proc = run_child(cmd, cwd=ROOT, env={**os.environ, "PYTHONPATH": path})
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        print(proc.stdout[-2000:] + proc.stderr[-4000:], file=sys.stderr)
        raise CtsplatError(f"train row failed (exit {proc.returncode}; its output above): {' '.join(cmd)}")
    with open(out / "protocol.csv") as fh:
        gs = [r for r in csv.DictReader(fh) if r["method"].startswith("gaussians")][-1]
    return {"row": f"train {size}³ 50 views (head protocol)", "backend": "auto(cuda)",
            "time_to_final_s": gs["time_to_final_quality_s"], "train_wall_s": gs["wall_time_s"],
            "psnr3d": gs["psnr3d_r2"], "script_wall_s": round(wall, 1)}


def run(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--reps", type=int, default=20, help="minimum timed repetitions per row")
    p.add_argument("--budget-s", type=float, default=3.0, help="keep repeating a row for this long (<= 10x reps)")
    p.add_argument("--reference", action="store_true", help="also time the pure-PyTorch reference")
    p.add_argument("--no-train", action="store_true", help="skip the training rows")
    p.add_argument("--train-sizes", type=int, nargs="+", default=[128], metavar="S",
                   help="volume grids of the training rows (default 128; 256 for the 256³ / 512² target)")
    p.add_argument("--data", default=str(ROOT.parent / "shared" / "data"), help="folder holding ct0051_head")
    args = p.parse_args(argv)
    if min(args.train_sizes) < 8:
        p.error("--train-sizes must be >= 8")
    if args.reps < 1 or not 0 < args.budget_s < float("inf"):
        p.error("--reps must be >= 1 and --budget-s a number of seconds > 0")
    import torch

    if not torch.cuda.is_available():
        print("gpu.py: error: no CUDA device is visible to torch (torch.cuda.is_available() is False); run this "
              "benchmark on a machine with an NVIDIA GPU and a CUDA build of torch", file=sys.stderr)
        return 2
    if importlib.util.find_spec("triton") is None:
        print("gpu.py: error: triton is not installed; pip install -e '.[gpu]'", file=sys.stderr)
        return 2
    name = torch.cuda.get_device_name(0)
    print(f"GPU: {name}; torch {torch.__version__}")
    rows = kernel_rows(["triton"] + (["reference"] if args.reference else []), args.reps, args.budget_s)
    print(f"{'row':40s} {'backend':10s} {'median ms':>10s} {'FPS':>9s}")
    for r in rows:
        print(f"{r['row']:40s} {r['backend']:10s} {r['median_ms']:10.3f} {r['fps']:9.1f}")
    for size in [] if args.no_train else args.train_sizes:
        tr = train_row(args.data, size)
        if tr is not None:
            rows.append(tr)
            print(f"{tr['row']}: time to final quality {tr['time_to_final_s']} s, training wall "
                  f"{tr['train_wall_s']} s, 3D PSNR (R²) {tr['psnr3d']} dB")
    fields = sorted({k for r in rows for k in r}, key=lambda k: (k != "row", k))
    write_csv(pd.DataFrame([{"gpu": name, **r} for r in rows], columns=["gpu", *fields]), OUT / "gpu.csv")
    print(f"wrote {OUT / 'gpu.csv'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """:func:`run` with the benchmarks' one-line errors and clean Ctrl-C / SIGTERM exits (:func:`_common.cli_main`)."""
    return cli_main(run, argv, "gpu.py")


if __name__ == "__main__":
    sys.exit(main())
