"""Choosing photo-training settings on validation photos: a candidate against the default, run by run.

A single run of a setting on eight validation photos is uncertain by about ±0.4 dB on the skull set (the summation
order and the seed take training down different paths; docs/results.md), so a candidate is compared with the default
*paired*: both trained on the same validation fold (:func:`ctsplat.photos.dataset.split_names`) with the same seed,
and the differences of their held-out PSNR summarised by their mean and its standard error. A candidate replaces
the default only when the mean difference is at least ``z`` standard errors above zero.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.utils import CtsplatError

__all__ = ["paired_comparison", "read_validation_run"]


def paired_comparison(default: Sequence[float], candidate: Sequence[float], *, z: float = 2.0) -> dict[str, Any]:
    """The mean of the paired differences ``candidate - default``, its standard error, and the verdict.

    Parameters
    ----------
    default, candidate : sequences of float, length n
        One score per pair (e.g. held-out PSNR in dB), pair i trained on the same fold with the same seed.
    z : float, keyword-only
        How many standard errors the mean difference must clear (2 by default).

    Returns
    -------
    dict
        ``n``, ``differences`` (list), ``mean``, ``standard_error`` (sample standard deviation / sqrt(n); None
        for one pair), ``z_score`` (mean / standard error; None when it is undefined), ``z`` and ``verdict``:
        ``candidate`` (mean >= z standard errors), ``default`` (mean <= -z standard errors) or ``tie`` (anything
        else, one pair included).

    Raises
    ------
    CtsplatError
        For sequences of different lengths, an empty one, or a non-finite score.

    Examples
    --------
    >>> r = paired_comparison([24.0, 23.5, 24.2], [24.5, 24.1, 24.6])
    >>> r["verdict"], round(r["mean"], 2)
    ('candidate', 0.5)
    """
    a = np.asarray(default, float)
    b = np.asarray(candidate, float)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise CtsplatError(f"paired comparison needs two equally long, non-empty lists of scores, got {a.size} "
                           f"default and {b.size} candidate scores")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise CtsplatError("paired comparison got a non-finite score; check the runs' training.json")
    d = b - a
    mean = float(d.mean())
    se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else None
    score = mean / se if se else None
    verdict = "tie"
    if score is not None and score >= z:
        verdict = "candidate"
    elif score is not None and score <= -z:
        verdict = "default"
    return {"n": int(d.size), "differences": d.tolist(), "mean": mean, "standard_error": se, "z_score": score,
            "z": float(z), "verdict": verdict}


def read_validation_run(run_dir: str | Path) -> dict[str, Any]:
    """The held-out scores of a finished ``photos-train`` run folder.

    Parameters
    ----------
    run_dir : str or Path
        A run folder with ``training.json``, ``config.json`` and ``per_view_test.csv``.

    Returns
    -------
    dict
        ``psnr`` and ``ssim`` (the mean over the held-out photos), ``per_photo`` (name -> PSNR in dB),
        ``held_out`` (``val`` or ``test``), ``validation_offset``, ``seed``, ``n_gaussians`` and ``seconds``.

    Raises
    ------
    CtsplatError
        When the folder is not a finished run.
    """
    run_dir = Path(run_dir)
    need = [run_dir / f for f in ("training.json", "config.json", "per_view_test.csv")]
    missing = [p.name for p in need if not p.is_file()]
    if missing:
        raise CtsplatError(f"{run_dir} is not a finished photo run (missing {', '.join(missing)}); run "
                           "`ctsplat photos-train` into it")
    t = json.loads(need[0].read_text())
    train = json.loads(need[1].read_text())["train"]
    with need[2].open(newline="") as f:
        per_photo = {r["view_id"]: float(r["psnr2d"]) for r in csv.DictReader(f) if r["iteration"] == "final"}
    return {"psnr": float(t["final_test_psnr"]), "ssim": float(t["final_test_ssim"]), "per_photo": per_photo,
            "held_out": t["held_out"], "validation_offset": train.get("validation_offset"),
            "seed": int(train["seed"]), "n_gaussians": int(t["n_gaussians"]), "seconds": float(t["seconds"])}
