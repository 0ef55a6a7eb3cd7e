"""The classical reconstructions of ``protocol.py`` runs offered the read-out sharpening the Gaussians get.

The protocol sharpens the Gaussians' voxel read-out by unsharp masking, the amount chosen on the validation views
(``PROTOCOL_TRAIN``'s ``sharpen``), and ``protocol.py`` offers its classical baselines the same
(``baselines.sharpen``, applied by :func:`ctsplat.recon.suite.sharpened` to each method's chosen reconstruction);
this script applies that same function to the reconstructions an earlier run saved (``--out/cache/*/baselines_*``),
so a finished run need not reconstruct again (the reconstruction comes first and the sharpening after it in the
suite too, so the numbers are what a rerun with ``baselines.sharpen`` would give). Validation views only choose the
amount; the reference volume only scores the result.

Usage::

    python benchmarks/protocol_sharpen.py benchmarks/out/protocol_head50 [more protocol folders]

Writes ``sharpened.csv`` into each folder and prints one table: per saved reconstruction the validation PSNR, the
chosen amount, R²-Gaussian's 3D PSNR / SSIM as reconstructed and sharpened, and the 3D PSNR over the object (the
reference above ``--threshold``; see ``protocol_regions.py``) as reconstructed and sharpened. ``suite`` names the
baseline suite's cache folder (its ``baselines.json`` holds the settings), so that the rows of two suites in one
``--out`` folder (binned and full detector) can be told apart.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _common import cli_main, write_csv  # noqa: E402
from protocol import PROTOCOL_TRAIN, saved_volume  # noqa: E402
from protocol_regions import region_scores  # noqa: E402

COLUMNS = ["volume", "views", "method", "suite", "params", "val_psnr", "val_psnr_sharpened", "sharpen_amount",
           "psnr3d_r2", "psnr3d_r2_sharpened", "ssim3d_r2", "ssim3d_r2_sharpened", "psnr3d_object",
           "psnr3d_object_sharpened", "sharpen_seconds"]


def suites(out: Path) -> tuple[list[Path], list[Path]]:
    """The baseline suite folders (``baselines.json`` beside saved volumes) under a protocol ``--out`` folder:
    those made without sharpening, and those whose reconstructions were sharpened when made (not sharpened
    twice)."""
    found = sorted(p.parent for p in (out / "cache").glob("*-s*/baselines_*/baselines.json"))
    made_sharp = [f for f in found if any(json.loads((f / "baselines.json").read_text())["config"]
                                          .get("sharpen", {}).get("amounts", [0.0]))]
    return [f for f in found if f not in made_sharp], made_sharp


def sharpen_suite(folder: Path, *, amounts: list[float], radius_voxels: float, threshold: float,
                  device: str = "auto") -> list[dict]:
    """Each saved reconstruction of one suite, sharpened by the amount its validation views prefer, and scored."""
    from ctsplat.evaluation.metrics import psnr3d_r2, ssim3d_r2
    from ctsplat.formats.viewset import load_radiographs
    from ctsplat.formats.volume import load_volume
    from ctsplat.recon.select import Choice, Validator
    from ctsplat.recon.suite import auto_binning, bin_detector, sharpened
    from ctsplat.utils import CtsplatError, resolve_device

    info = json.loads((folder / "baselines.json").read_text())
    cfg = info["config"]
    reference = load_volume(info["volume_path"])
    p_all, vs_all = load_radiographs(info["radiographs_dir"])
    if vs_all.volume_id != reference.volume_id:
        raise CtsplatError(f"{info['radiographs_dir']} was rendered from another volume than {info['volume_path']}")
    val_rows = vs_all.indices("val")
    val_vs = vs_all.subset("val")
    binning = cfg["detector_binning"] or auto_binning(val_vs, reference)
    # the validator of the suite that chose the parameters: the same views, binned alike
    validator = Validator(*bin_detector(p_all[val_rows], val_vs, binning), reference,
                          device=resolve_device(device))
    ref = np.asarray(reference.data, np.float64)
    rows = []
    for r in info["results"]:
        n = int(r["n_views"])
        path = saved_volume(folder, r["method"], r.get("filter"), n)
        if path is None:
            raise CtsplatError(f"{folder}: no saved volume of {r['method']} at {n} views; rerun protocol.py")
        params = json.loads(r["params"])
        volume = np.asarray(load_volume(path).data, np.float32)
        choice = Choice(r["method"], params, float(r["val_psnr"]), volume, float(r["seconds"]))
        sharp = sharpened(choice, validator, amounts=amounts, radius_voxels=radius_voxels, clip=bool(cfg["clip"]))
        as_is = sharp.trials[amounts.index(0.0)]["val_psnr"]
        if abs(as_is - float(r["val_psnr"])) > 1e-6:  # not the validation the suite chose its parameters on
            raise CtsplatError(f"{path}: validation PSNR {as_is:.6f} dB here, {float(r['val_psnr']):.6f} dB when "
                               "the suite chose it; the radiographs or the volume changed since")
        rows.append({
            "volume": folder.parent.name.rsplit("-s", 1)[0], "views": n, "method": r["method"],
            "suite": folder.name, "params": json.dumps(params, sort_keys=True), "val_psnr": float(r["val_psnr"]),
            "val_psnr_sharpened": sharp.val_psnr, "sharpen_amount": sharp.params["sharpen_amount"],
            "psnr3d_r2": psnr3d_r2(volume, ref), "psnr3d_r2_sharpened": psnr3d_r2(sharp.volume, ref),
            "ssim3d_r2": ssim3d_r2(volume, ref), "ssim3d_r2_sharpened": ssim3d_r2(sharp.volume, ref),
            "psnr3d_object": region_scores(volume.astype(np.float64), ref, threshold=threshold)["psnr3d_object"],
            "psnr3d_object_sharpened": region_scores(sharp.volume.astype(np.float64), ref,
                                                     threshold=threshold)["psnr3d_object"],
            "sharpen_seconds": sharp.selection_seconds - choice.selection_seconds})
    return rows


def main(argv: list[str] | None = None) -> int:
    return cli_main(run, argv, "protocol_sharpen.py")


def run(argv: list[str] | None = None) -> int:
    from ctsplat.utils import CtsplatError

    default = PROTOCOL_TRAIN["sharpen"]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", nargs="+", help="benchmarks/protocol.py --out folders")
    ap.add_argument("--amounts", type=float, nargs="+", default=default["amounts"],
                    help="candidate amounts (default: the Gaussians' read-out's, %(default)s)")
    ap.add_argument("--radius-voxels", type=float, default=default["radius_voxels"])
    ap.add_argument("--threshold", type=float, default=0.01, help="reference value above which a voxel is object")
    ap.add_argument("--device", default="auto", help="the validation re-projection's device")
    args = ap.parse_args(argv)
    if 0.0 not in args.amounts or min(args.amounts) < 0 or max(args.amounts) > 4:
        raise CtsplatError(f"--amounts must be in [0, 4] and hold 0 (the reconstruction itself), got {args.amounts}")
    if not args.radius_voxels > 0:
        raise CtsplatError(f"--radius-voxels must be > 0, got {args.radius_voxels}")
    if not 0.0 <= args.threshold < 1.0:
        raise CtsplatError(f"--threshold must be in [0, 1), got {args.threshold}")
    tables = []
    for out in map(Path, args.out):
        found, made_sharp = suites(out)
        for folder in made_sharp:
            print(f"skipped {folder}: its reconstructions were sharpened when they were made (baselines.sharpen)",
                  file=sys.stderr)
        if not found:
            raise CtsplatError(f"no baseline suite made without sharpening, with saved volumes, under {out}/cache; "
                               "give a protocol.py --out folder")
        rows = [row for folder in found for row in sharpen_suite(folder, amounts=list(args.amounts),
                                                                   radius_voxels=args.radius_voxels,
                                                                   threshold=args.threshold, device=args.device)]
        table = pd.DataFrame(rows, columns=COLUMNS)
        write_csv(table, out / "sharpened.csv")
        tables.append(table)
    everything = pd.concat(tables, ignore_index=True)
    print(everything.drop(columns=["params"]).to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
