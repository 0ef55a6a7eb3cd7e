"""Where the protocol's 3D PSNR comes from: every saved reconstruction of a ``protocol.py`` run, scored over the
whole volume, inside the object's bounding box and outside it.

R²-Gaussian's 3D PSNR averages over the whole cube. A scan that fills a small part of it (a thin slab such as
``totalseg_abdomen_j2k``: 20 slices in a cube as wide as the body) is then scored mostly on empty air, where an
exact zero and a faint streak differ by many dB. This script splits the same squared error by region so a reader
can see how much of a margin the object itself carries. The object is where the reference exceeds
``--threshold`` (attenuation normalised to [0, 1]); its bounding box is the box of those voxels. Every PSNR has data
range 1, as R²'s. A classical row's ``suite`` is the baseline suite's cache folder (one per set of baseline
settings, e.g. binned or full detector; its ``baselines.json`` holds them), so that two suites in one ``--out``
folder give rows that can be told apart; the Gaussians' rows leave it empty.

Usage::

    python benchmarks/protocol_regions.py benchmarks/out/protocol_abdomen50

Writes ``regions.csv`` into the protocol folder and prints it.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _common import cli_main, write_csv  # noqa: E402

COLUMNS = ["volume", "views", "method", "suite", "psnr3d_whole", "psnr3d_object_box", "psnr3d_outside_box",
           "psnr3d_object", "object_box_fraction", "object_fraction"]


def region_scores(test: np.ndarray, reference: np.ndarray, *, threshold: float) -> dict[str, float]:
    """3D PSNR (data range 1) of ``test`` over the whole volume, the object's bounding box, the rest, the object.

    Parameters
    ----------
    test, reference : ndarray, shape (X, Y, Z)
        Attenuation normalised to [0, 1].
    threshold : float
        Reference values above it are the object.

    Returns
    -------
    dict
        ``psnr3d_whole``, ``psnr3d_object_box``, ``psnr3d_outside_box``, ``psnr3d_object`` in dB (``inf`` where
        the error is zero, ``nan`` for an empty region) and the fractions of the volume in the box and the object.
    """
    from ctsplat.evaluation.metrics import psnr
    from ctsplat.utils import CtsplatError

    obj = reference > threshold
    if not obj.any():
        raise CtsplatError(f"no reference voxel exceeds --threshold {threshold}; lower it")
    box = np.zeros_like(obj)
    box[tuple(slice(int(i.min()), int(i.max()) + 1) for i in np.nonzero(obj))] = True

    def score(mask: np.ndarray) -> float:
        return psnr(test[mask], reference[mask], data_range=1.0) if mask.any() else float("nan")

    return {"psnr3d_whole": psnr(test, reference, data_range=1.0), "psnr3d_object_box": score(box),
            "psnr3d_outside_box": score(~box), "psnr3d_object": score(obj),
            "object_box_fraction": float(box.mean()), "object_fraction": float(obj.mean())}


def reconstructions(out: Path) -> list[tuple[str, int, str, str, Path, Path]]:
    """``(volume, views, method, suite, reconstruction, reference)`` for every saved volume under a protocol
    folder; ``suite`` is the baseline suite's folder name, empty for the Gaussians."""
    found = []
    for cache in sorted((out / "cache").glob("*-s*")):
        # protocol.volume_key: {name}-s{size}, and -{hash of the scan's path} for scans
        name, reference = re.sub(r"-s\d+(-[0-9a-f]{8})?$", "", cache.name), cache / "volume.nii.gz"
        for path in sorted(cache.glob("baselines_*/*_n[0-9][0-9][0-9].nii.gz")):
            method, n = path.name.removesuffix(".nii.gz").rsplit("_n", 1)
            found.append((name, int(n), method, path.parent.name, path, reference))
        for path in sorted((out / "runs" / cache.name).glob("views[0-9]*/model_volume.nii.gz")):
            found.append((name, int(path.parent.name.removeprefix("views")), "gaussians", "", path, reference))
    return found


def main(argv: list[str] | None = None) -> int:
    return cli_main(run, argv, "protocol_regions.py")


def run(argv: list[str] | None = None) -> int:
    from ctsplat.formats.volume import load_volume
    from ctsplat.utils import CtsplatError

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="a benchmarks/protocol.py --out folder")
    ap.add_argument("--threshold", type=float, default=0.01, help="reference value above which a voxel is object")
    args = ap.parse_args(argv)
    out = Path(args.out)
    if not 0.0 <= args.threshold < 1.0:
        raise CtsplatError(f"--threshold must be in [0, 1), got {args.threshold}")
    found = reconstructions(out)
    if not found:
        raise CtsplatError(f"no saved reconstructions under {out}/cache or {out}/runs; give a protocol.py --out folder")
    refs: dict[Path, np.ndarray] = {}
    rows = []
    for name, n, method, suite, path, ref_path in found:
        if ref_path not in refs:
            refs[ref_path] = np.asarray(load_volume(ref_path).data, dtype=np.float64)
        test = np.asarray(load_volume(path).data, dtype=np.float64)
        rows.append({"volume": name, "views": n, "method": method, "suite": suite,
                     **region_scores(test, refs[ref_path], threshold=args.threshold)})
    table = pd.DataFrame(rows, columns=COLUMNS).sort_values(["volume", "views", "method", "suite"], kind="stable")
    write_csv(table, out / "regions.csv", float_format="%.6g")
    print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
