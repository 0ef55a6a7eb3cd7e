"""The sparse-view CT protocol of R²-Gaussian (NeurIPS 2024) as one command: classical baselines vs Gaussians.

Per volume (``--volumes``: ``phantom`` — the built-in Shepp-Logan head, no beads — and scans in ``--data``, default
``ct0051_head`` and ``totalseg_abdomen_j2k``) and view count (``--views``, default 25 50 75):

1. ingest at ``--size``³ normalised attenuation (cube side ``L`` mm);
2. render the protocol radiographs (``config/r2_protocol.yaml``'s geometry): circular cone beam over 360°,
   DSO 2.5 L, DSD 3.5 L, a 2 L detector of ``2 · size`` pixels a side; training angles uniformly over 360° with
   TIGRE's noise (Poisson I0 = 1e4 + Gaussian σ = 10 counts, clipped at >= 0) on them only; 100 noise-free test
   views at random angles and 10 noise-free validation views. One rendering serves every view count when their
   least common multiple is small (150 angles for 25/50/75: every 6th / 3rd / 2nd), else one per count;
3. ``ctsplat.baselines.run_baselines`` (every classical method the geometry allows, parameters chosen on the
   validation views; each chosen reconstruction offered the Gaussians' read-out sharpening, ``baselines.sharpen``,
   its amount chosen on the validation views as well), its saved volumes also scored by R²-Gaussian's 3D metrics;
4. a Gaussian model per view count (``init: fbp``, i.e. FDK of the training views where available, refined by 20
   ASD-POCS iterations on the same views, ``PROTOCOL_TRAIN``; rectified radiative compositor), trained
   (``ctsplat.training.train``) and evaluated (``ctsplat.evaluation.evaluate``); its voxel read-out is
   sharpened by unsharp masking with the amount chosen on the validation views (``PROTOCOL_TRAIN``'s ``sharpen``;
   the unsharpened read-out's 3D PSNR is the table's ``psnr3d_r2_unsharpened``).

Table (printed, and written as ``protocol.csv`` + ``protocol.md`` under ``--out``; ``protocol.json`` holds the
arguments and settings): per volume, view count and method the 3D PSNR/SSIM by R²-Gaussian's ``metric_vol``
(``psnr3d_r2``, ``ssim3d_r2``) and by the project's convention (``psnr3d``, ``ssim3d``), the 2D PSNR/SSIM on the
test views, wall time, and time to final quality (Gaussians: the first logged training time with 3D PSNR within
0.25 dB of the final value; classical methods: the chosen reconstruction's time), plus each Gaussian model's
margin over the best classical method (chosen on validation where the baselines say so; else the best by 3D
PSNR, marked ``oracle``). Volumes, radiographs and baselines are cached under ``--out/cache``.

Usage::

    python benchmarks/protocol.py                                  # the full CPU protocol (hours on 2 cores)
    python benchmarks/protocol.py --volumes phantom --views 25 --size 64 --iterations 300    # a quick point
    python benchmarks/protocol.py --volumes ct0051_head --views 50 --skip-gaussians \
        --baseline-set asd_pocs_iterations=120                       # a larger budget than the protocol's

The classical methods get the budget of ``config/r2_protocol.yaml``'s ``baselines.settings`` (ASD-POCS up to 60
iterations over a TV grid, full detector: what the budget check found they need). ``--baseline-set`` changes
their candidates or budgets (keys of the config's ``baselines`` section); each set of settings caches its
baselines apart. A kept Gaussian run of other settings than the call's is refused, not reused.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _common import cli_main, data_key, out_folder, shared_train_config, time_to, write_csv  # noqa: E402

from ctsplat.utils import atomic_path, write_json_atomic  # noqa: E402

DEFAULT_VOLUMES = ["phantom", "ct0051_head", "totalseg_abdomen_j2k"]
N_VAL, N_TEST = 10, 100
MAX_SHARED_ANGLES = 600  # above this many, render one view set per view count instead of one shared set
TABLE_COLUMNS = ["volume", "views", "method", "psnr3d_r2", "ssim3d_r2", "psnr3d", "ssim3d", "psnr2d_test",
                 "ssim2d_test", "wall_time_s", "time_to_final_quality_s", "best_on_val", "margin_vs_best_classical_db",
                 "best_classical", "uses_reference_volume"]


def protocol_geometry(n_train: int, size: int) -> dict[str, Any]:
    """The ``radiographs`` settings of the protocol (``config/r2_protocol.yaml``) for ``n_train`` angles."""
    return {"camera": "cone", "orbit": "circular", "arc_deg": 360.0, "dso_mm": None, "dsd_mm": None,
            "dso_factor": 2.5, "dsd_factor": 3.5, "detector_size_factor": 2.0, "detector_width": 2 * size,
            "detector_height": 2 * size, "n_views": int(n_train), "n_val": N_VAL, "n_test": N_TEST,
            "allow_truncation": True,
            "noise": {"enabled": True, "model": "tigre", "i0": 1.0e4, "electronic_sigma": 10.0, "splits": ["train"]}}


def angle_sets(views: list[int]) -> list[tuple[int, list[int]]]:
    """Which training-angle counts to render and the view counts each serves (uniform subsets of one set)."""
    lcm = math.lcm(*views)
    if lcm <= MAX_SHARED_ANGLES:
        return [(lcm, sorted(set(views)))]
    return [(v, [v]) for v in sorted(set(views))]


def source_of(name: str, data: Path, cache: Path, size: int) -> Path:
    """The scan to ingest: the built-in phantom written as DICOM, or ``data / name``."""
    from ctsplat.utils import CtsplatError

    if name == "phantom":
        from ctsplat.phantom import write_phantom_dicom

        out = cache / "phantom_dicom"
        if not out.is_dir():
            write_phantom_dicom(out, size=size, beads=False, seed=0)
        return out
    path = data / name
    if not path.exists():
        raise CtsplatError(f"--volumes {name}: {path} not found (give --data, or one of phantom and the scans "
                           f"in {data})")
    return path


def volume_key(name: str, data: Path, size: int) -> str:
    """The folder name of one volume's cache and runs: ``{name}-s{size}``, plus a hash of the scan's resolved path
    for scans (``-{8 hex}``), so that another ``--data`` with a scan of the same name is not served from this
    one's cache."""
    if name == "phantom":
        return f"{name}-s{size}"
    return f"{name}-s{size}-{data_key(data / name)}"


def prepare(name: str, data: Path, out: Path, size: int, n_train: int) -> tuple[Path, Path]:
    """Ingest once per volume and size, render one protocol view set per training-angle count (cached)."""
    from ctsplat.projector import render_radiographs
    from ctsplat.volume import ingest

    cache = out / "cache" / volume_key(name, data, size)
    cache.mkdir(parents=True, exist_ok=True)
    vol = cache / "volume.nii.gz"
    if not vol.exists():
        ingest(source_of(name, data, cache, size), vol, {"grid": size})
    rad = cache / f"radiographs_n{n_train:03d}"
    if not (rad / "views.json").exists():
        render_radiographs(vol, rad, protocol_geometry(n_train, size), seed=0)
    return vol, rad


def r2_scores(volume_path: Path | None, reference: np.ndarray) -> tuple[float | None, float | None]:
    """R²-Gaussian's 3D PSNR/SSIM of a saved reconstruction (None when it was not saved: no path)."""
    from ctsplat.evaluation.metrics import psnr3d_r2, ssim3d_r2
    from ctsplat.formats.volume import load_volume

    if volume_path is None:
        return None, None
    vol = load_volume(volume_path).data
    return psnr3d_r2(vol, reference), ssim3d_r2(vol, reference)


def baselines_folder(rad: Path, views: list[int], settings: dict[str, Any]) -> Path:
    """The cache folder of one baseline suite: the radiographs, the view counts and (hashed) the settings it runs
    with, the library's defaults included (a changed default is another suite, not a cached one)."""
    from ctsplat.baselines import BASELINE_DEFAULTS
    from ctsplat.utils import config_hash, merge_config

    tag = config_hash(merge_config("baselines", settings, BASELINE_DEFAULTS))[:8]
    return rad.parent / f"baselines_{rad.name}_v{'-'.join(map(str, views))}_{tag}"


def saved_volume(bdir: Path, method: str, filt: Any, n: int) -> Path | None:
    """The reconstruction a baseline suite saved for one method and view count (``{method}[_{filter}]_n{n}``), or
    None when it saved none."""
    stem = [f"{method}_{filt}_n{n:03d}.nii.gz"] if isinstance(filt, str) and filt else []
    return next((bdir / s for s in [*stem, f"{method}_n{n:03d}.nii.gz"] if (bdir / s).exists()), None)


def baseline_rows(name: str, vol: Path, rad: Path, views: list[int], out: Path,
                  settings: dict[str, Any] | None = None) -> tuple[list[dict], str | None]:
    """Every classical method at every view count (cached ``baselines.csv``), with R²'s metrics of its volume.

    ``settings`` are ``baselines`` keys (``--baseline-set``) over the library's defaults, e.g. a larger iteration
    budget.
    """
    from ctsplat.baselines import run_baselines
    from ctsplat.formats.volume import load_volume
    from ctsplat.utils import CtsplatError

    settings = dict(settings or {})
    bdir = baselines_folder(rad, views, settings)
    try:
        table = pd.read_csv(bdir / "baselines.csv") if (bdir / "baselines.csv").exists() else \
            run_baselines(vol, rad, bdir, {**settings, "n_views": views, "save_volumes": True})
    except CtsplatError as exc:  # a baseline suite that cannot reconstruct this geometry: say so, keep going
        logging.getLogger("protocol").warning("baselines of %s: %s", name, exc)
        return [], str(exc)
    reference = load_volume(vol).data
    rows = []
    for _, b in table.iterrows():
        method, filt, n = str(b["method"]), b.get("filter"), int(b["n_views"])
        label = f"{method}:{filt}" if isinstance(filt, str) and filt else method
        p_r2, s_r2 = r2_scores(saved_volume(bdir, method, filt, n), reference)
        seconds = float(b["seconds"])
        rows.append({"volume": name, "views": n, "method": label, "psnr3d_r2": p_r2, "ssim3d_r2": s_r2,
                     "psnr3d": float(b["psnr3d"]), "ssim3d": float(b["ssim3d"]),
                     "psnr2d_test": b.get("psnr2d"), "ssim2d_test": b.get("ssim2d"),
                     # the selection's time already holds the chosen reconstruction's (every candidate's run)
                     "wall_time_s": float(b.get("selection_seconds", 0.0) or 0.0) or seconds,
                     "time_to_final_quality_s": seconds, "best_on_val": b.get("best_on_val"),
                     "uses_reference_volume": False})
    return rows, None


def best_classical(rows: list[dict], name: str, n: int) -> tuple[dict | None, str]:
    """The best classical row at one view count: the one chosen on validation, else (oracle) the best 3D PSNR."""
    cand = [r for r in rows if r["volume"] == name and r["views"] == n]
    if not cand:
        return None, ""
    chosen = [r for r in cand if r.get("best_on_val") in (True, "True", 1)]
    if chosen:
        return chosen[0], chosen[0]["method"]
    best = max(cand, key=lambda r: r["psnr3d"])
    return best, f"{best['method']} (oracle)"


#: train keys this script sets per run, and the option that sets them instead of --set
OWN_KEYS = {"volume": "--volumes", "radiographs": "--size", "init": None, "views": "--views",
            "iterations": "--iterations", "n_init": "--n-init", "progress": None}


#: the protocol's train settings beside the library defaults (``--set`` overrides them): the FDK seed refined by
#: ASD-POCS iterations on the training views, chosen on the validation views (docs/results.md)
PROTOCOL_TRAIN = {"init_asd_pocs": {"iterations": 20, "alpha": 0.1},
                  "sharpen": {"amounts": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0], "radius_voxels": 1.0}}


def train_config(sets: list[str], iterations: int, n_init: int) -> dict:
    """The train settings every run shares: the protocol's, then ``--set`` (checked against the schema)."""
    return shared_train_config(sets, own_keys=OWN_KEYS, defaults=PROTOCOL_TRAIN,
                               fixed={"init": "fbp", "iterations": iterations, "n_init": n_init})


#: baselines keys this script sets per view count
OWN_BASELINE_KEYS = {"n_views": "--views", "save_volumes": None}

#: The protocol's workflow config: its ``baselines.settings`` are this script's baseline budget too.
PROTOCOL_CONFIG = ROOT / "config" / "r2_protocol.yaml"


def protocol_baselines() -> dict[str, Any]:
    """The ``baselines.settings`` of :data:`PROTOCOL_CONFIG` without ``sharpen`` (given per call): the ASD-POCS
    budget and TV grid the budget check found the baselines need, on the full detector."""
    import yaml

    settings = dict(yaml.safe_load(PROTOCOL_CONFIG.read_text())["baselines"]["settings"])
    settings.pop("sharpen", None)
    return settings


def baseline_config(sets: list[str], *, sharpen: dict[str, Any]) -> dict[str, Any]:
    """The baselines settings beside the library defaults: the protocol config's budget
    (:func:`protocol_baselines`), ``sharpen`` (the Gaussians' read-out sharpening, offered to the classical
    reconstructions alike), then the ``--baseline-set KEY=VALUE`` overrides, checked against the ``baselines``
    section of the schema."""
    from ctsplat.cli._common import section_config
    from ctsplat.utils import CtsplatError

    user = section_config(None, sets, "baselines")
    for key, option in OWN_BASELINE_KEYS.items():
        if key in user:
            raise CtsplatError(f"--baseline-set {key} is set by this benchmark" + (f"; use {option}" if option else ""))
    return {**protocol_baselines(), "sharpen": dict(sharpen), **user}


def gaussian_row(name: str, vol: Path, rad: Path, n: int, shared: dict, run_dir: Path) -> dict:
    from ctsplat.evaluation import evaluate
    from ctsplat.training import train
    from ctsplat.training.config import resolve_config
    from ctsplat.utils import CtsplatError, config_hash, read_json_object

    cfg = {**shared, "volume": str(vol), "radiographs": str(rad), "views": n}
    if not (run_dir / "metrics.json").exists():
        train(cfg, run_dir)
        evaluate(run_dir, device=cfg["device"])
    kept = read_json_object(run_dir / "config.json", what="run config", fix="remove the run folder")
    if kept.get("config_hash") != config_hash(resolve_config(cfg)):  # a kept run of other settings is no row here
        raise CtsplatError(f"{run_dir} holds a run of other settings than this call's (--set, --iterations, "
                           "--n-init); remove it or give another --out")
    res = json.loads((run_dir / "metrics.json").read_text())
    log = pd.read_csv(run_dir / "train_log.csv")
    # the log holds the training's raw read-out: time to within 0.25 dB of the final raw one, plus the read-out's
    # sharpening (chosen on validation after training; its seconds are part of the run's time)
    sharpen_s = res.get("sharpen_seconds", 0.0)
    reached = time_to(log, res.get("psnr3d_unsharpened", res["psnr3d"]) - 0.25)
    method = f"gaussians ({res['compositor']}, init {res['init']}"
    method += f", read-out sharpened {res['sharpen_amount']:g})" if "sharpen_amount" in res else ")"
    return {"volume": name, "views": n, "method": method,
            "psnr3d_r2": res.get("psnr3d_r2"), "ssim3d_r2": res.get("ssim3d_r2"), "psnr3d": res["psnr3d"],
            "ssim3d": res["ssim3d"], "psnr2d_test": res["psnr2d"], "ssim2d_test": res["ssim2d"],
            "wall_time_s": res["wall_time_s"] + sharpen_s,
            "time_to_final_quality_s": None if reached is None else reached + sharpen_s,
            "psnr3d_r2_unsharpened": res.get("psnr3d_r2_unsharpened"),
            "best_on_val": None, "uses_reference_volume": res["uses_reference_volume"],
            "iterations": res["iterations"], "n_gaussians": res["n_gaussians"], "run_dir": str(run_dir)}


def markdown(table: pd.DataFrame) -> str:
    cols = [c for c in TABLE_COLUMNS if c in table]

    def fmt(v: Any) -> str:
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return ""
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for _, r in table.iterrows()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    return cli_main(run, argv, "protocol.py")


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--volumes", nargs="+", default=DEFAULT_VOLUMES,
                    help="phantom and/or folder names in --data (default: %(default)s)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--views", type=int, nargs="+", default=[25, 50, 75])
    ap.add_argument("--size", type=int, default=128, help="volume grid (size^3); detectors are 2 size px a side")
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--n-init", type=int, default=50000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="extra train config overrides (as `ctsplat train --set`), e.g. lambda_tv=0.05")
    ap.add_argument("--baseline-set", action="append", default=[], metavar="KEY=VALUE",
                    help="classical-baseline overrides (keys of the config's `baselines` section), e.g. "
                         "asd_pocs_iterations=30 or methods=[fdk,asd_pocs]")
    ap.add_argument("--skip-gaussians", action="store_true",
                    help="run the classical baselines only (e.g. to check them at a larger iteration budget)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out" / "protocol"))
    args = ap.parse_args(argv)
    for name in ("views", "size", "iterations", "threads", "n_init"):
        values = getattr(args, name)
        if min(values if isinstance(values, list) else [values]) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1")
    if args.size < 8:
        ap.error("--size must be >= 8")

    import torch

    from ctsplat.utils import CtsplatError

    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    shared = train_config(args.set, args.iterations, args.n_init)  # refused before any work
    baseline_settings = baseline_config(args.baseline_set, sharpen=shared["sharpen"])  # likewise
    data = Path(args.data)
    for name in args.volumes:
        if name != "phantom" and not (data / name).exists():
            raise CtsplatError(f"--volumes {name}: {data / name} not found (give --data, or use phantom)")
    out = out_folder(args.out)
    rows: list[dict] = []
    errors: dict[str, str] = {}

    def write() -> pd.DataFrame:
        table = pd.DataFrame(rows)
        if not table.empty:  # per volume (in --volumes order) and view count: baselines first, then the Gaussians
            table["_v"] = table["volume"].map({v: i for i, v in enumerate(args.volumes)})
            table = table.sort_values(["_v", "views"], kind="stable").drop(columns="_v")
        table = table[[c for c in TABLE_COLUMNS if c in table] + [c for c in table if c not in TABLE_COLUMNS]]
        write_csv(table, out / "protocol.csv")
        with atomic_path(out / "protocol.md") as tmp:
            tmp.write_text(markdown(table))
        return table

    def record(**extra: Any) -> None:  # what made the table beside it, from the start (an interrupted run too)
        write_json_atomic(out / "protocol.json", {"args": vars(args), "train": shared,
                                                  "baselines": baseline_settings,
                                                  "geometry": protocol_geometry(0, args.size), **extra})

    record(finished=False)
    t_start = time.perf_counter()
    for name in args.volumes:
        for n_train, counts in angle_sets(args.views):
            vol, rad = prepare(name, data, out, args.size, n_train)
            base, err = baseline_rows(name, vol, rad, counts, out, baseline_settings)
            if err:
                errors[name] = err
            rows.extend(base)
            write()
            for n in counts if not args.skip_gaussians else []:
                run_dir = out / "runs" / volume_key(name, data, args.size) / f"views{n:03d}"
                g = gaussian_row(name, vol, rad, n, shared, run_dir)
                best, label = best_classical(base, name, n)
                if best is not None:
                    key = "psnr3d_r2" if best.get("psnr3d_r2") is not None and g["psnr3d_r2"] is not None else "psnr3d"
                    g["margin_vs_best_classical_db"] = g[key] - best[key]
                    g["best_classical"] = label
                rows.append(g)
                write()
    table = write()
    record(finished=True, baseline_errors=errors, total_seconds=time.perf_counter() - t_start)
    print(markdown(table), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
