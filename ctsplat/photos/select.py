"""Choosing photo-training settings on validation photos: a candidate against the default, run by run.

A single run of a setting on eight validation photos is uncertain by about ±0.4 dB on the skull set (the summation
order and the seed take training down different paths; docs/results.md), so a candidate is compared with the default
*paired*: both trained on the same validation fold (:func:`ctsplat.photos.dataset.split_names`) with the same seed,
and the differences of their held-out PSNR summarised by their mean and its standard error. Pairs on one fold share
its photos, so their differences are averaged into one per fold first. A candidate replaces the default only when
the mean difference is at least ``t`` standard errors above zero, ``t`` Student's one-sided 97.5 % quantile with
n - 1 degrees of freedom (2.57 for six folds; 1.96, the "two standard errors", for many).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.utils import CtsplatError, read_json_object

__all__ = ["paired_comparison", "read_validation_run"]


def paired_comparison(default: Sequence[float], candidate: Sequence[float], *,
                      groups: Sequence[Any] | None = None, level: float = 0.975) -> dict[str, Any]:
    """The mean of the paired differences ``candidate - default``, its standard error, and the verdict.

    Parameters
    ----------
    default, candidate : sequences of float, length n
        One score per pair (e.g. held-out PSNR in dB), pair i trained on the same fold with the same seed.
    groups : sequence, length n, keyword-only, optional
        The fold of each pair: the differences of one fold are averaged first (its seeds share the fold's photos,
        so they are not independent), and the statistics run over the folds. None: every pair its own fold.
    level : float, keyword-only
        One-sided confidence the mean difference must reach (Student's t with ``units - 1`` degrees of freedom).

    Returns
    -------
    dict
        ``n`` (pairs), ``units`` (folds), ``differences`` (per pair), ``unit_differences`` (per fold, in order of
        first appearance), ``mean`` (over the folds), ``standard_error`` (their sample standard deviation /
        sqrt(units); None for one fold), ``t_score`` (mean / standard error; None when it is undefined),
        ``critical`` (the t quantile it must reach; None for one fold) and ``verdict``: ``candidate`` (t_score >=
        critical, or every fold the same positive difference), ``default`` (the mirror) or ``tie`` (anything else,
        one fold included).

    Raises
    ------
    CtsplatError
        For sequences of different lengths, an empty one, or a non-finite score.

    References
    ----------
    Student (1908). The probable error of a mean. Biometrika 6(1), 1-25.

    Examples
    --------
    >>> r = paired_comparison([24.0, 23.5, 24.2], [24.5, 24.1, 24.6])
    >>> r["verdict"], round(r["mean"], 2), round(r["critical"], 2)
    ('candidate', 0.5, 4.3)
    """
    from scipy import stats

    a = np.asarray(default, float)
    b = np.asarray(candidate, float)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise CtsplatError(f"paired comparison needs two equally long, non-empty lists of scores, got {a.size} "
                           f"default and {b.size} candidate scores")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise CtsplatError("paired comparison got a non-finite score; check the runs' training.json")
    if groups is not None and len(groups) != a.size:
        raise CtsplatError(f"paired comparison got {len(groups)} folds for {a.size} pairs")
    d = b - a
    keys = list(range(a.size)) if groups is None else list(groups)
    order = list(dict.fromkeys(keys))
    u = np.array([d[[k == g for k in keys]].mean() for g in order])
    mean = float(u.mean())
    se = float(u.std(ddof=1) / np.sqrt(u.size)) if u.size > 1 else None
    critical = float(stats.t.ppf(level, u.size - 1)) if u.size > 1 else None
    score = mean / se if se else None
    verdict = "tie"
    if critical is not None:
        if (score is not None and score >= critical) or (se == 0 and mean > 0):
            verdict = "candidate"
        elif (score is not None and score <= -critical) or (se == 0 and mean < 0):
            verdict = "default"
    return {"n": int(d.size), "units": int(u.size), "differences": d.tolist(), "unit_differences": u.tolist(),
            "mean": mean, "standard_error": se, "t_score": score, "critical": critical, "verdict": verdict}


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
        ``held_out`` (``val`` or ``test``), ``validation_offset``, ``seed``, ``n_gaussians``, ``seconds`` and
        ``code_version`` (the code that trained it, None when not recorded).

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
    fix = "remove the folder and train it again"
    t = read_json_object(need[0], what="photo training record", fix=fix)
    cfg = read_json_object(need[1], what="photo run config", fix=fix)
    try:
        train = cfg["train"]
        with need[2].open(newline="") as f:
            per_photo = {r["view_id"]: float(r["psnr2d"]) for r in csv.DictReader(f) if r["iteration"] == "final"}
        return {"psnr": float(t["final_test_psnr"]), "ssim": float(t["final_test_ssim"]), "per_photo": per_photo,
                "held_out": t["held_out"], "validation_offset": train.get("validation_offset"),
                "seed": int(train["seed"]), "n_gaussians": int(t["n_gaussians"]), "seconds": float(t["seconds"]),
                "code_version": cfg.get("code_version")}
    except (KeyError, TypeError, ValueError) as exc:
        raise CtsplatError(f"{run_dir} is not a whole photo run ({type(exc).__name__}: {exc} in training.json, "
                           f"config.json or per_view_test.csv); {fix}") from None
