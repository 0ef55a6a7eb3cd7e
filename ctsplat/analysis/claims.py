"""The method's claims, checked on the grid: one row per comparison, with its verdict and, when it fails, why.

The claims of the rectified radiative model (R²-Gaussian) that a grid can test:

- the model with an honest init (one that does not read the reference volume) beats the strongest classical
  reconstruction at the same view count, in test 3D PSNR;
- the rectified compositor beats the unrectified one (X-Gaussian) and alpha compositing (3DGS), each in pairs of
  runs that differ only in the compositor.

The other axes (mip filter, init, poses) are reported as measured effects, without an expected sign.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from ctsplat.analysis.gather import NOT_RUN
from ctsplat.analysis.stats import CONDITION_AXES, paired_table

__all__ = ["CLAIM_COLUMNS", "BASELINE_PRIORS", "claims_table"]

#: Columns of :func:`claims_table`.
CLAIM_COLUMNS: tuple[str, ...] = ("comparison", "expected", "result", "n_pairs", "n_as_expected",
                                  "median_difference_psnr3d_db", "median_difference_ssim3d", "note")

#: Why a classical method can beat a short Gaussian run on a piecewise-constant volume (its prior fits it).
BASELINE_PRIORS: dict[str, str] = {
    "asd_pocs": "ASD-POCS minimises total variation, the exact prior of a piecewise-constant volume such as the "
                "phantom",
    "mbir": "MBIR's edge-preserving qGGMRF prior suits a piecewise-constant volume such as the phantom",
    "sart": "SART ran to its best iteration count on validation views",
    "fbp": "FBP had its filter chosen on validation views (it inverts the transform exactly only as views get dense "
           "and noise-free)",
}
_HONEST = "init does not read the reference volume"


def _verdict(diffs: np.ndarray) -> str:
    wins = int((diffs > 0).sum())
    return "holds" if wins == len(diffs) else ("fails" if wins == 0 else "mixed")


def _describe(row: Mapping[str, Any], axes: list[str]) -> str:
    return ", ".join(f"{a}={row[a]}" for a in axes)


def _geometry_note(pairs: pd.DataFrame) -> str:
    """What a headline claim must say when the Gaussians and the classical methods saw different view geometries."""
    if not {"geometry", "best_baseline_geometry"} <= set(pairs.columns):
        return ""
    both = pairs.dropna(subset=["geometry", "best_baseline_geometry"])
    apart = both[both["geometry"].astype(str) != both["best_baseline_geometry"].astype(str)]
    if apart.empty:
        return ""
    kinds = sorted({f"Gaussians on {a}, classical on {b}" for a, b in
                    zip(apart["geometry"], apart["best_baseline_geometry"], strict=True)})
    return (f"{len(apart)} of {len(pairs)} pairs compare different view geometries ({'; '.join(kinds)}): the same "
            "volume and view count, not the same views, so those differences are not like for like")


def _unscored_note(runs: pd.DataFrame) -> str:
    """Name the trained runs among ``runs`` that have no test 3D PSNR (an evaluation that failed or never ran):
    they are left out of a claim, which must say so."""
    if "test_psnr3d" not in runs:
        return ""
    trained = runs if "status" not in runs else runs[runs["status"].astype(str) != NOT_RUN]
    missing = trained[pd.to_numeric(trained["test_psnr3d"], errors="coerce").isna()]
    if missing.empty:
        return ""
    first = str(missing["run_dir"].iloc[0]) if "run_dir" in missing else str(missing.index[0])
    return (f"{len(missing)} trained run(s) without test_psnr3d left out (e.g. {first}): evaluate them, then "
            "gather and analyse again")


_NO_BASELINE = ("no classical baseline at its volume and view count: baselines.enabled is false, gather ran "
                "without --baselines, or the baselines were made at other view counts")


def _baseline_rows(summary: pd.DataFrame) -> list[dict[str, Any]]:
    """The headline claim, one row per init: rectified radiative runs at the true poses (mip on where that init
    has it) against the strongest classical reconstruction at the same volume and view count; a "no pairs" row,
    never none, when nothing can be compared, saying why (no test metrics, no baseline)."""
    need = {"best_baseline", "best_baseline_test_psnr3d", "test_psnr3d", "compositor", "init", "poses"}
    s = pd.DataFrame()
    if need <= set(summary.columns):
        s = summary[(summary["compositor"] == "radiative") & (summary["init"] != "volume")
                    & (summary["poses"] == "gt")]
        if "status" in s:
            s = s[s["status"].astype(str) != NOT_RUN]
    if s.empty:  # the headline claim: say that it was not measured, never drop it
        return [{"comparison": f"rectified radiative vs the strongest classical reconstruction ({_HONEST})",
                 "expected": "Gaussians higher", "result": "no pairs", "n_pairs": 0, "n_as_expected": None,
                 "median_difference_psnr3d_db": None, "median_difference_ssim3d": None,
                 "note": f"no rectified radiative run at the true poses has a {_NO_BASELINE}"}]
    rows = []
    for init, g in s.groupby("init", sort=True):
        mip = "on"
        if "mip" in g:  # per init, before runs are dropped: a run without metrics must not switch the claim
            mip = "on" if (g["mip"].astype(str) == "on").any() else str(g["mip"].iloc[0])
            g = g[g["mip"].astype(str) == mip]
        unscored = _unscored_note(g)
        test = pd.to_numeric(g["test_psnr3d"], errors="coerce")
        base = pd.to_numeric(g["best_baseline_test_psnr3d"], errors="coerce")
        no_base = int((test.notna() & base.isna()).sum())
        g = g.assign(d=test - base).dropna(subset=["d"])
        label = (f"rectified radiative (init={init}, mip {mip}, poses gt) vs the strongest classical reconstruction "
                 f"at the same views ({_HONEST})")
        missing = f"{no_base} scored run(s) have no {_NO_BASELINE}" if no_base else ""
        if g.empty:
            rows.append({"comparison": label, "expected": "Gaussians higher", "result": "no pairs", "n_pairs": 0,
                         "n_as_expected": None, "median_difference_psnr3d_db": None,
                         "median_difference_ssim3d": None, "note": "; ".join(x for x in (unscored, missing) if x)})
            continue
        d = g["d"].to_numpy(float)
        ssim = (pd.to_numeric(g.get("test_ssim3d"), errors="coerce")
                - pd.to_numeric(g.get("best_baseline_test_ssim3d"), errors="coerce")).median()
        result = _verdict(d)
        lost = g[g["d"] <= 0]
        note = ""
        if len(lost):
            worst = lost.loc[lost["d"].idxmin()]
            method = str(worst["best_baseline"])
            budget = ""
            if "iterations" in worst and pd.notna(worst["iterations"]):
                budget = f"the Gaussians trained {int(worst['iterations'])} iterations"
                if "wall_time_s" in worst and pd.notna(worst["wall_time_s"]):
                    budget += f" in {float(worst['wall_time_s']):.0f} s"
                budget += ", a short run; "
            gap = -float(worst["d"])
            ahead = f"{gap:.2f} dB higher" if gap > 0 else "level"  # a tie, not "-0.00 dB higher"
            note = (f"{method} is {ahead} at {int(worst['views'])} views ({worst['volume']}): "
                    f"{budget}{BASELINE_PRIORS.get(method, method + ' had its settings chosen on validation views')}")
        note = "; ".join(x for x in (_geometry_note(g), note, unscored, missing) if x)
        rows.append({"comparison": label, "expected": "Gaussians higher", "result": result, "n_pairs": len(d),
                     "n_as_expected": int((d > 0).sum()), "median_difference_psnr3d_db": float(np.median(d)),
                     "median_difference_ssim3d": float(ssim) if pd.notna(ssim) else None, "note": note})
    if all(r["result"] == "no pairs" for r in rows):  # nothing compared at all: one row, every reason once
        notes = list(dict.fromkeys(n for r in rows for n in r["note"].split("; ") if n))
        return [{**rows[0], "comparison": f"rectified radiative vs the strongest classical reconstruction ({_HONEST})",
                 "note": "; ".join(notes)}]
    return rows


def _paired_rows(summary: pd.DataFrame, axis: str, high: str, low: str, expected: str | None,
                 label: str) -> dict[str, Any] | None:
    """One comparison of two values of ``axis`` over the runs that differ only in it (None: no such pairs)."""
    if axis not in summary or not {high, low} <= set(summary[axis].astype(str)):
        return None
    psnr = paired_table(summary, axis, "test_psnr3d") if "test_psnr3d" in summary else pd.DataFrame()
    if psnr.empty or high not in psnr or low not in psnr:
        return {"comparison": label, "expected": expected or "measured", "result": "no pairs", "n_pairs": 0,
                "n_as_expected": None, "median_difference_psnr3d_db": None, "median_difference_ssim3d": None,
                "note": f"no two runs with results differ only in {axis} ({high} vs {low})"}
    pairs = psnr[[high, low]].dropna()
    d = (pairs[high] - pairs[low]).to_numpy(float)
    ssim_tab = paired_table(summary, axis, "test_ssim3d") if "test_ssim3d" in summary else pd.DataFrame()
    ssim = ((ssim_tab[high] - ssim_tab[low]).median()
            if not ssim_tab.empty and high in ssim_tab and low in ssim_tab else None)
    out = {"comparison": label, "expected": expected or "measured", "n_pairs": len(d),
           "median_difference_psnr3d_db": float(np.median(d)) if len(d) else None,
           "median_difference_ssim3d": float(ssim) if ssim is not None and pd.notna(ssim) else None}
    # pairs whose both runs were seeded from the reference volume are counted in, and said so
    seeded = 0
    if axis != "init" and "init" in pairs.index.names:
        seeded = int((pairs.index.get_level_values("init").astype(str) == "volume").sum())
    seeded_note = f"{seeded} of {len(d)} pairs seeded from the reference volume (init=volume)" if seeded else ""
    unscored = _unscored_note(summary[summary[axis].astype(str).isin([high, low])])
    if expected is None:
        measured = f"{high} higher in {int((d > 0).sum())} of {len(d)} pairs"
        return {**out, "result": "measured", "n_as_expected": None,
                "note": "; ".join(x for x in (measured, seeded_note, unscored) if x)}
    result = _verdict(d) if len(d) else "no pairs"
    note = ""
    if result != "holds" and len(d):
        others = [a for a in CONDITION_AXES if a != axis and a in pairs.index.names]
        lost = pairs[(pairs[high] - pairs[low]) <= 0]
        named = [a for a in others if a not in ("volume", "seed")]
        cells = []
        for idx, r in lost.iterrows():
            where = dict(zip(others, idx if isinstance(idx, tuple) else (idx,), strict=True))
            cells.append(f"{_describe(where, named)} ({r[high] - r[low]:+.2f} dB)")
        cells = "; ".join(cells)
        note = f"{low} is as good or better in {len(lost)} of {len(d)} pairs: {cells}"
    note = "; ".join(x for x in (note, seeded_note, unscored) if x)
    return {**out, "result": result, "n_as_expected": int((d > 0).sum()), "note": note}


def claims_table(summary: pd.DataFrame) -> pd.DataFrame:
    """Check the method's claims on a grid's ``summary.csv``.

    Parameters
    ----------
    summary : pandas.DataFrame
        The table of :func:`ctsplat.analysis.gather.gather` (test metrics, axes, the
        :data:`ctsplat.analysis.gather.BASELINE_SUMMARY_COLUMNS`, ``status``).

    Returns
    -------
    pandas.DataFrame
        :data:`CLAIM_COLUMNS`, one row per comparison the grid can make:

        - per honest init, rectified radiative (mip on, true poses) minus the strongest classical reconstruction
          at the same volume and views (test 3D PSNR, dB), expected positive;
        - rectified minus unrectified, and rectified minus alpha, over the runs that differ only in the
          compositor, expected positive;
        - the measured effects of the mip filter (on minus off), of the init (fbp minus uniform; volume minus fbp,
          where volume reads the reference) and of the poses (colmap minus gt).

        ``result`` is ``holds`` (every pair as expected), ``mixed``, ``fails`` (none), ``measured`` (no expected
        sign), ``no pairs``, or ``not run`` (the cells were not trained; ``note`` says why). ``note`` names the
        pairs that went the other way, and for the baseline comparison the budget and the baseline's prior.

    Examples
    --------
    >>> s = pd.DataFrame({"volume": "v", "init": "fbp", "compositor": ["radiative", "alpha"], "mip": "on",
    ...                   "poses": "gt", "views": 8, "seed": 0, "test_psnr3d": [30.0, 27.0],
    ...                   "test_ssim3d": [0.9, 0.8]})
    >>> table = claims_table(s)  # no baselines gathered here: the headline row says so
    >>> table[["result", "n_pairs"]].values.tolist()
    [['no pairs', 0], ['holds', 1]]
    >>> float(table["median_difference_psnr3d_db"].iloc[1])
    3.0
    """
    trained = summary[summary["status"] != "not run"] if "status" in summary else summary
    rows = _baseline_rows(trained)
    for high, low, expected, label in (
            ("radiative", "radiative_unrectified", "rectified higher", "rectified vs unrectified radiative "
                                                                       "compositor (X-Gaussian), paired"),
            ("radiative", "alpha", "rectified higher", "rectified radiative vs alpha compositing (3DGS), paired")):
        row = _paired_rows(trained, "compositor", high, low, expected, label)
        if row is not None:
            rows.append(row)
    for axis, high, low, label in (("mip", "on", "off", "mip filter on vs off, paired"),
                                   ("init", "fbp", "uniform", "init fbp vs uniform, paired"),
                                   ("init", "volume", "fbp", "init volume (reads the reference) vs fbp, paired"),
                                   ("poses", "colmap", "gt", "poses colmap (SfM poses of the C-arm view set) vs gt "
                                                             "(true poses of the training geometry), paired")):
        row = _paired_rows(trained, axis, high, low, None, label)
        if row is not None:
            rows.append(row)
    if "status" in summary:
        for _, r in summary[summary["status"] == NOT_RUN].iterrows():
            rows.append({"comparison": f"cell {r['run_dir']}", "expected": "trained", "result": "not run",
                         "n_pairs": 0, "n_as_expected": None, "median_difference_psnr3d_db": None,
                         "median_difference_ssim3d": None, "note": str(r.get("not_run_reason", ""))})
    table = pd.DataFrame(rows, columns=list(CLAIM_COLUMNS))
    table["n_as_expected"] = table["n_as_expected"].astype("Int64")  # counts, empty where none applies (not 6.0)
    return table
