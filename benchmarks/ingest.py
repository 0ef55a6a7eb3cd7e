"""Benchmark: ingest of the real 512x512x108 head series (ct0051_head) and the JPEG 2000 abdomen slab.

Times reading the DICOM series, resampling it in world coordinates alone, and ``ingest`` from the
read stack (resample + intensity mapping + NIfTI/JSON write); ``total_s`` = read + ingest. Targets:
1 mm isotropic, the workflow's 128^3 grid, native spacing. Prints a table and writes
``benchmarks/out/ingest.csv``. Not a test: run ``.venv/bin/python benchmarks/ingest.py``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
from _common import cli_main, write_csv

from ctsplat.formats.sources import read_dicom_series
from ctsplat.volume import ingest, resample_stack

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("CTSPLAT_SHARED_DATA", ROOT.parent / "shared" / "data"))


def bench(name: str, folder: Path, cfg: dict, repeats: int) -> list[dict]:
    rows = []
    for rep in range(repeats):
        t0 = time.perf_counter()
        stack = read_dicom_series(folder)
        t1 = time.perf_counter()
        data, _, _ = resample_stack(stack, voxel_size_mm=cfg.get("voxel_size_mm"), grid=cfg.get("grid"))
        t2 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            vol = ingest(stack, Path(tmp) / "volume.nii.gz", cfg)  # resample again + map + write
        t3 = time.perf_counter()
        rows.append({
            "series": name, "target": cfg.get("label"), "repeat": rep,
            "source_shape": "x".join(map(str, stack.data.shape)), "output_shape": "x".join(map(str, vol.shape)),
            "voxel_mm": round(float(vol.spacing_mm[0]), 4),
            "read_s": t1 - t0, "resample_s": t2 - t1, "ingest_from_stack_s": t3 - t2,
            "total_s": (t1 - t0) + (t3 - t2),
        })
        del data
    return rows


def run(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    head, j2k = DATA / "ct0051_head", DATA / "totalseg_abdomen_j2k"
    if not head.is_dir():
        from ctsplat.utils import CtsplatError

        raise CtsplatError(f"ct0051_head not found in {DATA}; put the shared data beside the checkout or name its "
                           "folder in CTSPLAT_SHARED_DATA")
    targets = [
        {"label": "1 mm isotropic", "voxel_size_mm": 1.0, "grid": None},
        {"label": "grid 128^3", "grid": 128},
        {"label": "native spacing", "voxel_size_mm": None, "grid": None},
    ]
    rows = []
    for t in targets:
        cfg = {k: v for k, v in t.items() if k != "label"}
        for r in bench("ct0051_head", head, {**cfg}, args.repeats):
            r["target"] = t["label"]
            rows.append(r)
    if j2k.is_dir():
        for r in bench("totalseg_abdomen_j2k", j2k, {"voxel_size_mm": 1.0, "grid": None}, args.repeats):
            r["target"] = "1 mm isotropic"
            rows.append(r)
    df = pd.DataFrame(rows)
    out = ROOT / "benchmarks" / "out"
    out.mkdir(parents=True, exist_ok=True)
    write_csv(df, out / "ingest.csv")
    summary = df.groupby(["series", "target", "source_shape", "output_shape"], sort=False)[
        ["read_s", "resample_s", "ingest_from_stack_s", "total_s"]
    ].median()
    print(f"cpu threads: {os.cpu_count()}; median of {args.repeats} runs (seconds)")
    print(summary.round(2).to_string())
    print(f"wrote {out / 'ingest.csv'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """:func:`run` with the benchmarks' one-line errors and clean Ctrl-C / SIGTERM exits (:func:`_common.cli_main`)."""
    return cli_main(run, argv, "ingest.py")


if __name__ == "__main__":
    sys.exit(main())
