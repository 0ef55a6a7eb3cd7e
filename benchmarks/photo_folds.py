"""A photo-training setting against the default on validation folds: paired runs, mean difference and verdict.

Every pair trains the default and the candidate (the default plus ``--candidate KEY=VALUE`` overrides of the
``photos`` section) with ``ctsplat photos-train`` on one SfM folder, on the same validation fold
(``train.validation_offset``; the test photos are never trained on or scored) with the same seed, one thread per
run and ``--jobs`` runs at a time. :func:`ctsplat.photos.select.paired_comparison` then gives the mean PSNR
difference over the folds (a fold's seeds averaged first), its standard error and the verdict (the candidate wins
only when the mean clears Student's one-sided 97.5 % quantile of standard errors: about two for many folds). Finished
runs are kept and reused, so a comparison can be extended by more folds or seeds (not across kinds of CPU: a run
trained on another CPU capability, AVX2 against AVX512, takes another rounding path and is refused). A kept run
is reused by its settings, SfM folder and CPU, not by the code that trained it: a comparison extended after a code
change pairs runs of two codes, which is sound only when the training path did not change between them. So every
run's code version goes to ``pairs.csv`` and ``summary.json`` (``run_code_versions``), and runs of a code other
than this one are named on stderr. Writes ``OUT/pairs.csv`` (one row per pair), ``OUT/per_photo.csv`` and
``OUT/summary.json``, and prints the summary as one JSON line.

Usage::

    python benchmarks/photos.py --sfm-only             # the SfM folder, benchmarks/out/photos/sfm
    python benchmarks/photo_folds.py --candidate train.flash.enabled=true --folds 2 4 6 --seeds 0
    python benchmarks/photo_folds.py --candidate train.lambda_dssim=0.3 --folds 4 --seeds 0 1 2 3 --out DIR

A pair of 6000-iteration runs at 1/4 resolution takes about 30 minutes on 2 cores (docs/results.md).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import threading
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

import pandas as pd
from _common import cli_main, out_folder, write_csv

from ctsplat.cli._common import apply_sets
from ctsplat.config import check_section
from ctsplat.photos.config import photo_settings
from ctsplat.photos.select import paired_comparison, read_validation_run
from ctsplat.utils import (
    CtsplatError,
    code_version,
    compute_platform,
    dotted_items,
    read_json_object,
    write_json_atomic,
)

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "out"


def run_sets(fold: int, seed: int, extra: list[str]) -> list[str]:
    """The ``--set`` items of one run: the validation fold, the seed, one thread, then ``extra``."""
    return ["train.holdout=validation", f"train.validation_offset={fold}", f"train.seed={seed}",
            "train.num_threads=1", *extra]


def _same_run(config: dict[str, Any], sfm: Path, sets: list[str]) -> bool:
    """Whether a kept run's ``config.json`` trained these settings on this SfM folder: every filled setting equal,
    where a key the run does not record (an option added since) must have its default value."""
    if Path(config["sfm_dir"]).resolve() != sfm.resolve():
        return False
    have = dotted_items(config["train"])
    wanted = dotted_items(photo_settings(apply_sets({}, sets))["train"])
    defaults = dotted_items(photo_settings({})["train"])
    return all(have[k] == v if k in have else v == defaults.get(k) for k, v in wanted.items())


#: The ``photos-train`` processes running now, and whether the comparison is being stopped (an interrupt or
#: SIGTERM in the main thread): queued runs then start no process, running ones are terminated.
_RUNNING: set[subprocess.Popen] = set()
_LOCK = threading.Lock()
_STOPPING = threading.Event()


def _stop_children() -> None:
    """Terminate the running ``photos-train`` processes (each removes its temporary folder, as on SIGTERM)."""
    _STOPPING.set()
    with _LOCK:
        for proc in _RUNNING:
            proc.terminate()


def _kept(sfm: Path, run_dir: Path, sets: list[str]) -> bool:
    """Whether ``run_dir`` holds a finished run to keep: the same settings on the same SfM folder, trained on a CPU
    of this one's capability; one line when it holds a run that cannot be kept. Every run is checked before the
    first training starts, not hours into the comparison."""
    if not (run_dir / "training.json").is_file():
        return False
    fix = "remove it or choose another --out"
    config = read_json_object(run_dir / "config.json", what="kept run's config", fix=fix)
    training = read_json_object(run_dir / "training.json", what="kept run's training record", fix=fix)
    try:
        same = _same_run(config, sfm, sets)
    except (KeyError, TypeError, ValueError, CtsplatError):
        same = False
    if not same:
        raise CtsplatError(f"{run_dir} holds a run with other settings or another SfM folder; {fix}")
    made = (training.get("platform") or {}).get("cpu_capability")
    here = compute_platform()["cpu_capability"]
    if made is not None and made != here:
        # another kind of CPU rounds differently: the run would not pair with the other arm trained here
        raise CtsplatError(f"{run_dir} was trained on a {made} CPU and this one is {here}, so it does not pair "
                           f"with runs made here; {fix}")
    return True


def _train(sfm: Path, run_dir: Path, sets: list[str]) -> None:
    """One ``ctsplat photos-train`` process (its log beside the run folder)."""
    cmd = [sys.executable, "-c", "import sys; from ctsplat.cli import main; sys.exit(main())", "photos-train",
           str(sfm), str(run_dir)]
    for item in sets:
        cmd += ["--set", item]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    with open(run_dir.with_suffix(".log"), "w") as log, _LOCK:
        if _STOPPING.is_set():
            return
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        _RUNNING.add(proc)
    try:
        code = proc.wait()
    finally:
        with _LOCK:
            _RUNNING.discard(proc)
    if code != 0 and not _STOPPING.is_set():
        raise CtsplatError(f"photos-train into {run_dir} failed (exit {code}); see {run_dir.with_suffix('.log')}")


def run(argv: list[str] | None = None) -> int:
    """Parse the options, train the missing runs, write and print the comparison (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sfm", default=str(OUT / "photos" / "sfm"), help="output folder of `ctsplat photos-sfm`")
    ap.add_argument("--candidate", action="append", required=True, metavar="KEY=VALUE",
                    help="a photos key the candidate sets, e.g. train.flash.enabled=true (repeatable)")
    ap.add_argument("--base", action="append", default=[], metavar="KEY=VALUE",
                    help="a photos key both arms set (repeatable), e.g. train.iterations=3000")
    ap.add_argument("--folds", type=int, nargs="+", default=[4], help="validation offsets, 1 .. test_every - 1")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--jobs", type=int, default=2, help="runs at a time (one thread each)")
    ap.add_argument("--out", default=str(OUT / "photo_folds"))
    args = ap.parse_args(argv)
    sfm, out = Path(args.sfm), Path(args.out)
    if args.jobs < 1:
        raise CtsplatError(f"--jobs must be >= 1, got {args.jobs}")
    if not (sfm / "sparse" / "0" / "cameras.bin").is_file():
        raise CtsplatError(f"{sfm} is not a photo SfM folder; run `python benchmarks/photos.py --sfm-only` first")
    pairs = list(itertools.product(sorted(set(args.folds)), sorted(set(args.seeds))))
    fold_keys = ("train.holdout", "train.validation_offset", "train.seed")  # the fold design is this script's
    fixed = [item for item in [*args.base, *args.candidate] if item.split("=", 1)[0].strip() in fold_keys]
    if fixed:
        raise CtsplatError(f"--base/--candidate may not set {fixed[0].split('=', 1)[0]}: the folds and seeds hold "
                           "out the validation photos (--folds, --seeds), never the test photos")
    split = [item for item in args.candidate if item.split("=", 1)[0].strip() == "train.test_every"]
    if split:  # the arms would score different photos, and the candidate train on the default's test photos
        raise CtsplatError("--candidate may not set train.test_every: it decides the test and validation photos, "
                           "which both arms must share; set it with --base")
    arms = {"default": args.base, "candidate": [*args.base, *args.candidate]}
    test_every = photo_settings(check_section("photos", apply_sets({}, args.base)))["train"]["test_every"]
    for fold, seed in pairs:  # every run's settings are checked before the first one starts
        if not 1 <= fold < test_every:
            raise CtsplatError(f"--folds: {fold} is not a validation fold (1 .. {test_every - 1})")
        for extra in arms.values():
            train = photo_settings(check_section("photos", apply_sets({}, run_sets(fold, seed, extra))))["train"]
            # the parsed settings, not the strings: --set 'train={"holdout": "test"}' sets the same keys
            design = {"holdout": "validation", "validation_offset": fold, "seed": seed, "test_every": test_every}
            moved = [k for k, v in design.items() if train[k] != v]
            if moved:
                raise CtsplatError(f"--base/--candidate may not set train.{moved[0]}: the folds, seeds and test "
                                   "photos are this script's, the same for both arms")
    out_folder(out)
    jobs = [(out / f"fold{fold}_seed{seed}_{arm}", run_sets(fold, seed, extra))
            for fold, seed in pairs for arm, extra in arms.items()]
    jobs = [(d, sets) for d, sets in jobs if not _kept(sfm, d, sets)]
    pool = ThreadPoolExecutor(max_workers=args.jobs)
    try:
        futures = [pool.submit(_train, sfm, d, sets) for d, sets in jobs]
        done, _ = wait(futures, return_when=FIRST_EXCEPTION)
        failed = [f for f in futures if f in done and f.exception() is not None]
        if failed:  # the queued runs are cancelled (hours of training), the running ones finish
            pool.shutdown(wait=True, cancel_futures=True)
            raise failed[0].exception()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: nothing more starts, the running trainings stop
        pool.shutdown(wait=False, cancel_futures=True)
        _stop_children()
        raise
    finally:
        pool.shutdown(wait=True)
    runs = {(fold, seed, arm): read_validation_run(out / f"fold{fold}_seed{seed}_{arm}")
            for fold, seed in pairs for arm in arms}
    scored_test = [key for key, r in runs.items() if r["held_out"] != "val"]
    if scored_test:
        raise CtsplatError(f"run fold{scored_test[0][0]}_seed{scored_test[0][1]}_{scored_test[0][2]} scored its "
                           "test photos, not validation photos; remove it and run again")
    for fold, seed in pairs:
        if set(runs[(fold, seed, "default")]["per_photo"]) != set(runs[(fold, seed, "candidate")]["per_photo"]):
            raise CtsplatError(f"fold{fold}_seed{seed}: the two arms scored different validation photos; remove "
                               "both runs and run again")
    folds = [fold for fold, _ in pairs]  # seeds of one fold share its photos: one difference per fold
    result = paired_comparison([runs[p + ("default",)]["psnr"] for p in pairs],
                               [runs[p + ("candidate",)]["psnr"] for p in pairs], groups=folds)
    _write_tables(out, pairs, runs, result["differences"])
    here = code_version()
    versions = sorted({str(r["code_version"]) for r in runs.values()})
    other = sorted(f"fold{f}_seed{s}_{arm}" for (f, s, arm), r in runs.items() if str(r["code_version"]) != here)
    if other:
        print(f"note: {len(other)} of {len(runs)} runs were trained by another code than this one ({here}): "
              f"{', '.join(other)}; the pairs compare code as well as settings unless the training path is the same "
              "in both", file=sys.stderr)
    summary = {"candidate": args.candidate, "base": args.base, "folds": sorted(set(args.folds)),
               "seeds": sorted(set(args.seeds)), "sfm": str(sfm), "psnr": result,
               "ssim": paired_comparison([runs[p + ("default",)]["ssim"] for p in pairs],
                                         [runs[p + ("candidate",)]["ssim"] for p in pairs], groups=folds),
               "code_version": here, "run_code_versions": versions}
    write_json_atomic(out / "summary.json", summary)
    print(json.dumps(summary))
    return 0


def _write_tables(out: Path, pairs: list[tuple[int, int]], runs: dict[tuple[int, int, str], dict[str, Any]],
                  differences: list[float]) -> None:
    """``pairs.csv`` (one row per fold and seed) and ``per_photo.csv`` (one row per validation photo)."""
    rows = [{"fold": fold, "seed": seed, "default_psnr": runs[(fold, seed, "default")]["psnr"],
             "candidate_psnr": runs[(fold, seed, "candidate")]["psnr"],
             "difference_db": diff, "default_ssim": runs[(fold, seed, "default")]["ssim"],
             "candidate_ssim": runs[(fold, seed, "candidate")]["ssim"],
             "default_code_version": runs[(fold, seed, "default")]["code_version"],
             "candidate_code_version": runs[(fold, seed, "candidate")]["code_version"]}
            for (fold, seed), diff in zip(pairs, differences, strict=True)]
    photos = [{"fold": fold, "seed": seed, "photo": name, "default_psnr": psnr,
               "candidate_psnr": runs[(fold, seed, "candidate")]["per_photo"][name]}
              for fold, seed in pairs for name, psnr in runs[(fold, seed, "default")]["per_photo"].items()]
    for name, table in (("pairs.csv", rows), ("per_photo.csv", photos)):
        write_csv(pd.DataFrame(table), out / name)


if __name__ == "__main__":
    raise SystemExit(cli_main(run, None, "benchmarks/photo_folds.py"))
