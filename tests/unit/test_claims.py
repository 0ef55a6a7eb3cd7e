"""ctsplat.analysis.claims: the method's claims checked on a summary table built by hand (known answers)."""

from __future__ import annotations

import itertools

import pandas as pd
import pytest

from ctsplat.analysis.claims import CLAIM_COLUMNS, claims_table

OFFSET = {"radiative": 0.0, "radiative_unrectified": -1.0, "alpha": -3.0}


def _summary(unrectified_wins_at: tuple[str, str] | None = None, baseline: float = 26.0) -> pd.DataFrame:
    rows = []
    for init, comp, mip in itertools.product(("fbp", "uniform", "volume"), OFFSET, ("on", "off")):
        score = 30.0 + OFFSET[comp] + (0.5 if mip == "on" else 0.0) + {"fbp": 0.0, "uniform": -2.0,
                                                                         "volume": 4.0}[init]
        if unrectified_wins_at == (init, mip) and comp == "radiative_unrectified":
            score += 2.0
        rows.append({"volume": "phantom", "init": init, "compositor": comp, "mip": mip, "poses": "gt", "views": 24,
                     "seed": 0, "status": "trained", "test_psnr3d": score, "test_ssim3d": score / 40,
                     "iterations": 500, "wall_time_s": 40.0, "best_baseline": "asd_pocs",
                     "best_baseline_test_psnr3d": baseline, "best_baseline_test_ssim3d": 0.7,
                     "run_dir": f"r/{init}/{comp}/{mip}"})
    rows.append({"volume": "phantom", "init": "fbp", "compositor": "radiative", "mip": "on", "poses": "colmap",
                 "views": 24, "seed": 0, "status": "not run", "run_dir": "r/colmap",
                 "not_run_reason": "SfM failed (sfm/summary.json): median rotation error 3.2 deg"})
    return pd.DataFrame(rows)


def _row(table: pd.DataFrame, start: str) -> pd.Series:
    hits = table[table["comparison"].str.startswith(start)]
    assert len(hits) == 1, start
    return hits.iloc[0]


def test_claims_hold_with_their_exact_differences():
    t = claims_table(_summary())
    assert list(t.columns) == list(CLAIM_COLUMNS)
    fbp = _row(t, "rectified radiative (init=fbp")
    assert (fbp["result"], fbp["n_pairs"], fbp["n_as_expected"]) == ("holds", 1, 1)
    assert fbp["median_difference_psnr3d_db"] == pytest.approx(30.5 - 26.0)
    uni = _row(t, "rectified radiative (init=uniform")
    assert uni["median_difference_psnr3d_db"] == pytest.approx(28.5 - 26.0)
    assert not t["comparison"].str.contains("init=volume, mip on").any()  # reads the reference: never "the method"
    unrect = _row(t, "rectified vs unrectified")
    assert (unrect["result"], unrect["n_pairs"], unrect["n_as_expected"]) == ("holds", 6, 6)
    assert unrect["median_difference_psnr3d_db"] == pytest.approx(1.0)
    # the pairs seeded from the reference volume are counted in, and the note says how many
    assert unrect["note"] == "2 of 6 pairs seeded from the reference volume (init=volume)"
    assert _row(t, "rectified radiative vs alpha")["median_difference_psnr3d_db"] == pytest.approx(3.0)
    mip = _row(t, "mip filter")
    assert (mip["result"], mip["median_difference_psnr3d_db"]) == ("measured", pytest.approx(0.5))
    assert mip["note"] == "on higher in 9 of 9 pairs; 3 of 9 pairs seeded from the reference volume (init=volume)"
    assert "seeded" not in _row(t, "init fbp vs uniform")["note"]
    assert _row(t, "init volume")["median_difference_psnr3d_db"] == pytest.approx(4.0)
    not_run = _row(t, "cell r/colmap")
    assert not_run["result"] == "not run" and "median rotation error 3.2 deg" in not_run["note"]


def test_failed_claims_say_so_and_why():
    t = claims_table(_summary(unrectified_wins_at=("uniform", "off"), baseline=31.0))
    fbp = _row(t, "rectified radiative (init=fbp")
    assert fbp["result"] == "fails" and fbp["median_difference_psnr3d_db"] == pytest.approx(-0.5)
    assert fbp["note"].startswith("asd_pocs is 0.50 dB higher at 24 views (phantom): the Gaussians trained 500 "
                                  "iterations in 40 s") and "total variation" in fbp["note"]
    unrect = _row(t, "rectified vs unrectified")
    assert (unrect["result"], unrect["n_as_expected"]) == ("mixed", 5)
    assert unrect["note"] == ("radiative_unrectified is as good or better in 1 of 6 pairs: init=uniform, mip=off, "
                              "poses=gt, views=24 (-1.00 dB); 2 of 6 pairs seeded from the reference volume "
                              "(init=volume)")


def test_the_headline_claim_says_it_was_not_measured_without_baselines():
    s = _summary().drop(columns=[c for c in _summary().columns if c.startswith("best_baseline")])
    t = claims_table(s)
    head = t[t["comparison"].str.contains("strongest classical")]
    assert list(head["result"]) == ["no pairs"] and "gather ran without --baselines" in head["note"].iloc[0]


def test_the_headline_claim_stays_when_the_baseline_columns_are_empty_or_the_grid_has_no_mip():
    """gather always writes the baseline columns, empty without baselines: the headline row says "no pairs" then;
    a grid with the mip filter off only is compared at mip off, and says so."""
    s = _summary().assign(best_baseline=None, best_baseline_test_psnr3d=None, best_baseline_test_ssim3d=None)
    head = claims_table(s)[lambda t: t["comparison"].str.contains("strongest classical")]
    assert list(head["result"]) == ["no pairs"] and "baselines.enabled is false" in head["note"].iloc[0]
    off = claims_table(_summary()[lambda t: t["mip"] != "on"])
    fbp = _row(off, "rectified radiative (init=fbp, mip off")
    assert (fbp["result"], fbp["median_difference_psnr3d_db"]) == ("holds", pytest.approx(30.0 - 26.0))


def test_the_headline_claim_names_pairs_of_different_geometries():
    same = claims_table(_summary().assign(geometry="circular", best_baseline_geometry="circular"))
    assert _row(same, "rectified radiative (init=fbp")["note"] == ""
    s = _summary().assign(geometry="sphere1200", best_baseline_geometry="circular150")
    fbp = _row(claims_table(s), "rectified radiative (init=fbp")
    assert fbp["result"] == "holds"
    assert fbp["note"] == ("1 of 1 pairs compare different view geometries (Gaussians on sphere1200, classical on "
                           "circular150): the same volume and view count, not the same views, so those differences "
                           "are not like for like")


def test_the_headline_claim_keeps_each_init_when_a_run_has_no_test_metrics():
    """A trained run without test metrics (its evaluation failed) leaves its own init's row as "no pairs" naming it,
    keeps that init at mip on, and is not named in another init's row; runs with baselines but no test metrics are
    not blamed on the baselines."""
    s = _summary()
    lone = (s["init"] == "uniform") & (s["compositor"] == "radiative") & (s["mip"] == "on")
    s.loc[lone, ["test_psnr3d", "test_ssim3d"]] = float("nan")
    t = claims_table(s)
    uni = _row(t, "rectified radiative (init=uniform, mip on")
    assert uni["result"] == "no pairs" and "r/uniform/radiative/on" in uni["note"] and "baseline" not in uni["note"]
    fbp = _row(t, "rectified radiative (init=fbp, mip on")
    assert fbp["result"] == "holds" and "uniform" not in fbp["note"]
    honest = (s["compositor"] == "radiative") & (s["init"] != "volume")
    s.loc[honest, ["test_psnr3d", "test_ssim3d"]] = float("nan")
    head = claims_table(s)[lambda x: x["comparison"].str.contains("strongest classical")]
    assert list(head["result"]) == ["no pairs"] and "without test_psnr3d" in head["note"].iloc[0]
    assert "baselines.enabled is false" not in head["note"].iloc[0]
