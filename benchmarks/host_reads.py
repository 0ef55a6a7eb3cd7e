"""Host reads of tensor values per training iteration on the GPU path, counted without a GPU.

Usage::

    python benchmarks/host_reads.py                  # 10- and 30-iteration runs on the phantom, 64³, 50 views
    python benchmarks/host_reads.py --set lambda_tv=0

On a GPU every read of a tensor's value by the host (``bool(t)``, ``float(t)``, ``int(t)``, ``t.item()``,
``t.tolist()``, and the result sizes of ``nonzero`` / boolean indexing / ``repeat_interleave``) waits for all
queued kernels: the GPU then idles while Python issues the next ones. A training loop that reads the device a few
dozen times per iteration runs at the speed of its host, whatever the kernels do.

This script runs :func:`ctsplat.training.train` with the Triton kernels in Triton's CPU interpreter
(``TRITON_INTERPRET=1``; the same wrapper code as on CUDA, so the same reads) on the protocol's phantom at 64³
(``benchmarks/protocol.py``'s geometry, 50 views, 3000 seeds, FDK seed) and counts, per iteration (a 30- minus a
10-iteration run, divided by 20):

* the Python-level reads made by ctsplat code, by call site (the immediate caller in ``ctsplat/``: reads inside
  torch, e.g. Adam's step counters, which live on the CPU, are not counted);
* the ``aten::nonzero`` and ``aten::repeat_interleave`` calls (profiler), whose output sizes are read back.

Reads of tensors that live on the CPU also on a GPU run (``random_region``'s draws from its CPU generator, region
bounds) are listed too; the table marks the call sites, so what is a device read on a GPU can be told apart.
Writes ``host_reads.csv`` in the ``--out`` folder (default ``benchmarks/out/host_reads``).
"""

from __future__ import annotations

import argparse
import collections
import importlib
import os
import sys
from pathlib import Path

import pandas as pd

os.environ["TRITON_INTERPRET"] = "1"  # before triton is imported
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "out"
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from _common import cli_main, out_folder, write_csv  # noqa: E402


def _count(its: int, sets: list[str], vol: Path, rad: Path, out: Path) -> tuple[collections.Counter, dict[str, int]]:
    import protocol
    from torch.profiler import ProfilerActivity, profile

    from ctsplat.training import train
    from ctsplat.utils import count_host_reads

    cfg = protocol.train_config(["device=cpu", "init_asd_pocs.iterations=0", *sets], its, 3000)
    cfg.update(volume=str(vol), radiographs=str(rad), views=50, eval_every=10 * its)
    with count_host_reads() as reads, profile(activities=[ProfilerActivity.CPU]) as prof:
        train(cfg, out / f"run{its}")
    # outermost events only: an overload that calls another of the same name is one call
    ops = collections.Counter(e.name for e in prof.events()
                              if e.name in ("aten::nonzero", "aten::repeat_interleave")
                              and (e.cpu_parent is None or e.cpu_parent.name != e.name))
    return reads, ops


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="train config overrides")
    ap.add_argument("--out", default=str(OUT / "host_reads"))
    args = ap.parse_args(argv)
    import protocol

    protocol.train_config(["device=cpu", *args.set], 10, 3000)  # a bad --set is refused before any work

    render_mod = importlib.import_module("ctsplat.splat.render")  # the module (the package exports a function)
    # the Triton wrappers on CPU tensors, as ``auto`` picks them on CUDA
    render_mod._use_triton = lambda backend, device: backend in ("auto", "triton")
    render_mod._use_kernel = lambda backend, device: False
    out = Path(args.out)
    out_folder(out)
    vol, rad = protocol.prepare("phantom", Path("unused"), out, 64, 50)
    c10, o10 = _count(10, args.set, vol, rad, out)
    c30, o30 = _count(30, args.set, vol, rad, out)
    rows = []
    for key in sorted(set(c30) | set(c10)):
        per_it = (c30[key] - c10[key]) / 20
        if per_it > 0:
            rows.append({"read": key[0], "site": key[1], "code": key[3], "per_iteration": per_it})
    for op in sorted(set(o30) | set(o10)):
        per_it = (o30.get(op, 0) - o10.get(op, 0)) / 20
        if per_it > 0:
            rows.append({"read": op, "site": "(profiler)", "code": "", "per_iteration": per_it})
    rows.sort(key=lambda r: -r["per_iteration"])
    write_csv(pd.DataFrame(rows, columns=["read", "site", "code", "per_iteration"]), out / "host_reads.csv")
    for r in rows:
        print(f"{r['per_iteration']:6.2f}  {r['read']:24s} {r['site']:32s} {r['code'][:70]}")
    print(f"total per iteration: {sum(r['per_iteration'] for r in rows):.2f}; wrote {out / 'host_reads.csv'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return cli_main(run, argv, "host_reads.py")


if __name__ == "__main__":
    sys.exit(main())
