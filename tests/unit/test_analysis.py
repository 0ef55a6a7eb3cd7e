"""ctsplat.analysis (stats, gather) and the run-log format on synthetic logs with known answers (AR(1) ACF,
linear-ramp velocity, milestones, ...)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from ctsplat.analysis.gather import gather, load_per_view, load_runs
from ctsplat.analysis.stats import (
    METRIC_RANGES,
    acf,
    acf_band,
    bounded_kde,
    condition_labels,
    convergence_velocity,
    correlations,
    detrend,
    mean_iters_per_s,
    milestones,
    porkchop_table,
    rolling_centered,
    velocity_curve,
    window_labels,
    windowed_correlations,
)
from ctsplat.formats.runlog import LOG_COLUMNS, PER_VIEW_COLUMNS, CsvLog, read_per_view, read_train_log
from ctsplat.grid import parse_run_dir, run_relpath
from ctsplat.utils import CtsplatError


def _write_log(path, df):
    df.to_csv(path, index=False)
    return path


def _log(iterations, psnr2d, ssim2d=None, psnr3d=None, ssim3d=None, dt=0.5, extra=True):
    it = np.asarray(iterations)
    n = it.size
    df = pd.DataFrame({
        "iteration": it,
        "timestamp": it * dt,
        "psnr2d": psnr2d,
        "ssim2d": np.linspace(0.5, 0.95, n) if ssim2d is None else ssim2d,
        "psnr3d": np.linspace(15, 25, n) if psnr3d is None else psnr3d,
        "ssim3d": np.linspace(0.4, 0.8, n) if ssim3d is None else ssim3d,
    })
    if extra:
        df["loss"] = np.linspace(1, 0.1, n)
        df["n_gaussians"] = 1000
    return df


# ---------------------------------------------------------------------------------------------- statistics


def test_acf_of_ar1_matches_phi_power_k():
    rng = np.random.default_rng(0)
    phi, n = 0.7, 20000
    x = np.empty(n)
    x[0] = rng.normal()
    eps = rng.normal(size=n)
    for t in range(1, n):
        x[t] = phi * x[t - 1] + eps[t]
    r = acf(x, 6)
    assert r[0] == 1.0
    # standard error of r_k for n = 20000 is ~ 0.01-0.02; compare with the theoretical phi^k
    np.testing.assert_allclose(r[1:], phi ** np.arange(1, 7), atol=0.03)


def test_acf_matches_direct_formula_and_handles_nan_and_constant():
    x = np.array([1.0, 3.0, np.nan, 2.0, 5.0, 4.0])
    r = acf(x, 10)
    y = np.array([1.0, 3.0, 2.0, 5.0, 4.0]) - 3.0
    expect = [np.sum(y[: 5 - k] * y[k:]) / np.sum(y * y) for k in range(5)]
    np.testing.assert_allclose(r, expect)
    assert r.size == 5  # lags capped at n - 1
    c = acf(np.ones(5), 3)
    assert c[0] == 1.0 and np.isnan(c[1:]).all()


def test_acf_of_a_trend_after_detrending_stays_inside_the_band():
    rng = np.random.default_rng(7)
    it = np.arange(400)
    trend = 18 + 12 * (1 - np.exp(-it / 80))  # a converging PSNR curve
    x = trend + rng.normal(0, 0.3, it.size)
    raw = acf(x, 20)
    assert raw[1] > 0.9  # the raw ACF only shows the trend
    resid = detrend(x, "rolling", 25)
    assert resid.size == 400 - 24
    r = acf(resid, 20)
    band = acf_band(resid.size)
    assert band == pytest.approx(1.96 / np.sqrt(376))
    inside = np.abs(r[1:]) <= band
    assert inside.mean() >= 0.9  # white noise: ~95 % of the lags inside the band
    # a pure linear trend is removed exactly; first differences leave its slope
    np.testing.assert_allclose(detrend(0.5 * it + 3, "rolling", 9), 0, atol=1e-9)
    np.testing.assert_allclose(detrend(0.5 * it + 3, "diff"), 0.5)
    assert detrend(np.arange(5.0), "rolling", 25).size == 0
    with pytest.raises(CtsplatError, match="unknown detrending method"):
        detrend(x, "loess")


def test_velocity_of_linear_ramp_is_slope_times_per():
    it = np.arange(0, 5001, 50)
    v = 0.004 * it + 12.0  # 4 dB per 1000 iterations
    assert convergence_velocity(it, v, 1000) == pytest.approx(4.0)
    assert convergence_velocity(it, v, 100) == pytest.approx(0.4)
    curve = velocity_curve(it, v, 1000)
    assert len(curve) == 5
    np.testing.assert_allclose(curve["velocity"], 4.0)
    np.testing.assert_allclose(curve["iteration"], [500, 1500, 2500, 3500, 4500])


def test_velocity_is_median_not_mean_and_skips_nan():
    it = np.array([0, 100, 200, 300, 400, 500])
    v = np.array([10.0, 11.0, 12.0, np.nan, 14.0, 30.0])  # one outlier jump at the end
    # steps (finite pairs): 0->100: 1, 100->200: 1, 200->400: 2 over 200 its = 1, 400->500: 16
    assert convergence_velocity(it, v, 100) == pytest.approx(1.0)
    assert np.isnan(convergence_velocity([0], [1.0]))


def test_rolling_centered_mean_matches_manual_window():
    x = np.array([1.0, 2.0, 3.0, 4.0, 10.0, 6.0, 7.0])
    r = rolling_centered(x, 3)
    expect = [np.mean(x[max(0, i - 1): i + 2]) for i in range(len(x))]
    np.testing.assert_allclose(r, expect)
    np.testing.assert_allclose(rolling_centered(x, 1), x)
    with pytest.raises(CtsplatError):
        rolling_centered(x, 0)


def test_milestones_first_crossing_and_iters_per_s():
    it = np.arange(0, 1001, 100)
    psnr = np.linspace(20, 35, it.size)  # 20, 21.5, ... crosses 30 at index 7 (30.5)
    ssim = np.linspace(0.5, 0.95, it.size)  # 0.5 + 0.045 k >= 0.9 at k = 9 (0.905)
    log = _log(it, psnr, ssim, dt=0.25)
    m = milestones(log, {"psnr2d": 30.0, "ssim2d": 0.9, "psnr3d": 99.0})
    speed = mean_iters_per_s(log)
    first_p = int(it[np.argmax(psnr >= 30)])
    first_s = int(it[np.argmax(ssim >= 0.9)])
    assert m["iter_to_psnr2d_30"] == first_p == 700
    assert m["time_to_psnr2d_30_s"] == pytest.approx(first_p * 0.25)
    assert m["iter_to_ssim2d_090"] == first_s == 900
    assert m["iter_to_psnr3d_99"] is None and m["time_to_psnr3d_99_s"] is None
    assert speed == pytest.approx(4.0)


def test_milestones_of_a_written_log_with_keys_named_from_thresholds(tmp_path):
    p = tmp_path / "train_log.csv"
    CsvLog(p, LOG_COLUMNS).reset()
    CsvLog(p, LOG_COLUMNS).append([
        {"iteration": 10, "timestamp": 1.0, "psnr2d": 25.0, "ssim2d": 0.80},
        {"iteration": 20, "timestamp": 2.5, "psnr2d": 30.5, "ssim2d": 0.89},
        {"iteration": 30, "timestamp": 4.0, "psnr2d": 29.0, "ssim2d": 0.91},
        {"iteration": 40, "timestamp": 5.0, "psnr2d": 33.0, "ssim2d": 0.95},
    ])
    log = read_train_log(p)
    m = milestones(log, {"psnr2d": 30.0, "ssim2d": 0.9})
    assert m["time_to_psnr2d_30_s"] == 2.5 and m["iter_to_psnr2d_30"] == 20
    assert m["time_to_ssim2d_090_s"] == 4.0 and m["iter_to_ssim2d_090"] == 30
    never = milestones(log.iloc[:1], {"psnr2d": 30.0, "ssim2d": 0.9})
    assert never["time_to_psnr2d_30_s"] is None and never["time_to_ssim2d_090_s"] is None
    other = milestones(log, {"psnr2d": 32.5, "ssim2d": 0.95})  # keys follow the targets
    assert other == {"iter_to_psnr2d_32.5": 40, "time_to_psnr2d_32.5_s": 5.0, "iter_to_ssim2d_095": 40,
                     "time_to_ssim2d_095_s": 5.0}


def test_correlations_agree_with_scipy_and_detect_monotone_nonlinear():
    rng = np.random.default_rng(1)
    x = np.linspace(10, 30, 50)
    y_lin = 0.5 * x + rng.normal(0, 0.5, x.size)
    y_exp = np.exp(x / 3.0)  # monotone, non-linear: Spearman 1, Pearson < 1
    log = pd.DataFrame({"psnr2d": x, "psnr3d": y_lin, "ssim2d": x, "ssim3d": y_exp})
    c = correlations(log).set_index("x")
    assert c.loc["psnr2d", "pearson"] == pytest.approx(np.corrcoef(x, y_lin)[0, 1])
    assert c.loc["psnr2d", "spearman"] == pytest.approx(stats.spearmanr(x, y_lin).statistic)
    assert c.loc["ssim2d", "spearman"] == pytest.approx(1.0)
    assert c.loc["ssim2d", "pearson"] < 0.95
    assert c.loc["ssim2d", "n"] == 50
    # too few / constant -> NaN, not an exception
    short = correlations(pd.DataFrame({"psnr2d": [1.0, 2.0], "psnr3d": [1.0, 3.0],
                                          "ssim2d": [1.0, 1.0], "ssim3d": [2.0, 3.0]}))
    assert short["pearson"].isna().all()


def test_bounded_kde_of_ssim_stays_within_one_and_keeps_its_mass():
    rng = np.random.default_rng(3)
    ssim = np.clip(1 - rng.exponential(0.01, 200), 0, 1)  # piled up against the bound, as late in training
    lo, hi = METRIC_RANGES["ssim2d"]
    x, dens = bounded_kde(ssim, lo, hi)
    assert x.max() == 1.0 and x.min() < ssim.min()
    assert np.all(dens >= 0)
    # the reflected density integrates to 1 over [.., 1]; the plain KDE puts a tenth of its mass above SSIM 1
    assert np.trapezoid(dens, x) == pytest.approx(1.0, abs=0.01)
    plain = stats.gaussian_kde(ssim)
    assert np.trapezoid(plain(x), x) < 0.95
    # an unbounded side is left alone: the PSNR support reaches below the smallest sample
    xp, _ = bounded_kde(rng.normal(30, 1, 100), *METRIC_RANGES["psnr2d"])
    assert xp.min() < 27
    xn, _ = bounded_kde(rng.normal(-2, 1, 100), *METRIC_RANGES["psnr3d"])  # PSNR below 0 (an unrectified run)
    assert xn.min() < -4
    assert bounded_kde([0.5, 0.5], lo, hi)[0].size == 0  # no spread, no density
    with pytest.raises(CtsplatError, match="outside the metric's range"):
        bounded_kde([0.5, 1.2], lo, hi)


def test_condition_labels_name_the_axes_that_differ():
    runs = pd.DataFrame({"volume": ["p"] * 4, "init": ["fbp", "fbp", "uniform", "uniform"],
                         "compositor": ["radiative"] * 4, "views": [24, 24, 12, 24], "seed": [0, 1, 0, 0]})
    labels = condition_labels(runs, ("volume", "init", "compositor", "views", "seed"))
    assert list(labels) == ["init=fbp, views=24", "init=fbp, views=24", "init=uniform, views=12",
                            "init=uniform, views=24"]  # seeds share a condition; constant axes are not named
    runs_named = condition_labels(runs, ("init", "views", "seed"), exclude=())
    assert runs_named[1] == "init=fbp, views=24, seed=1"
    assert set(condition_labels(runs.iloc[:1], ("init",))) == {"all runs"}


def test_windowed_correlations_follow_the_change_over_training():
    rng = np.random.default_rng(2)
    it = np.arange(0, 2000, 10)
    p2 = 20 + rng.normal(0, 1, it.size)
    # 3D tracks 2D in the first half of training and is unrelated noise in the second half
    p3 = np.where(it < 1000, p2 + rng.normal(0, 0.1, it.size), 25 + rng.normal(0, 1, it.size))
    log = pd.DataFrame({"iteration": it, "psnr2d": p2, "psnr3d": p3, "ssim2d": p2 / 40, "ssim3d": p3 / 40})
    t = windowed_correlations(log, 2)
    ps = t[t["x"] == "psnr2d"].set_index("window")
    assert list(ps.index) == ["all", "0–995", "995–1990"]
    assert ps.loc["0–995", "spearman"] > 0.95 and abs(ps.loc["995–1990", "spearman"]) < 0.3
    assert ps.loc["0–995", "n"] + ps.loc["995–1990", "n"] == ps.loc["all", "n"] == it.size
    assert ps.loc["0–995", "it_centre"] == pytest.approx(497.5)
    w = log[(it >= 995)]
    assert ps.loc["995–1990", "pearson"] == pytest.approx(np.corrcoef(w["psnr2d"], w["psnr3d"])[0, 1])


def test_window_labels_equal_iteration_ranges():
    it = np.arange(0, 1001, 100)
    labels = window_labels(it, 4)
    assert labels[0] == labels[2] == "0–250"  # 0, 100, 200
    assert labels[3] == "250–500"
    assert labels[-1] == "750–1000"  # right end included in the last window
    assert len(set(labels)) == 4


def test_porkchop_table_orders_views_by_azimuth_and_averages_duplicates():
    rows = []
    az = {3: 10.0, 1: 200.0, 2: 90.0}
    for it in (0, 100):
        for v, a in az.items():
            rows.append({"iteration": it, "view_id": v, "azimuth_deg": a, "elevation_deg": 0.0, "split": "val",
                         "psnr2d": 20 + v + it / 100, "ssim2d": 0.5})
    rows.append({"iteration": 100, "view_id": 3, "azimuth_deg": 10.0, "elevation_deg": 0.0, "split": "val",
                 "psnr2d": 25.0, "ssim2d": 0.5})
    rows.append({"iteration": 100, "view_id": 9, "azimuth_deg": 0.0, "elevation_deg": 0.0, "split": "test",
                 "psnr2d": 99.0, "ssim2d": 0.9})
    df = pd.DataFrame(rows)
    t = porkchop_table(df, "psnr2d", split="val")
    assert list(t.index) == [3, 2, 1]
    assert list(t.columns) == [0, 100]
    assert t.loc[3, 100] == pytest.approx((24.0 + 25.0) / 2)
    assert t.loc[1, 0] == pytest.approx(21.0)
    assert 9 in porkchop_table(df, "psnr2d").index
    assert porkchop_table(df, "psnr2d", split="nope").empty


# ---------------------------------------------------------------------------------------------- log reading


def test_read_train_log_fills_short_gaps_and_keeps_long_gaps(tmp_path):
    it = [0, 5, 10, 20, 30, 45, 50]
    psnr = [10.0, np.nan, 12.0, np.nan, np.nan, np.nan, 16.0]
    df = _log(it, psnr)
    df.loc[1, "ssim3d"] = np.nan
    p = _write_log(tmp_path / "train_log.csv", df)
    log = read_train_log(p, max_gap_iters=10)
    # it 5: last valid at 0 (gap 5 < 10) -> filled; it 20: last valid at 10 (gap 10, not < 10) -> NaN
    assert log.loc[1, "psnr2d"] == 10.0
    assert np.isnan(log.loc[3, "psnr2d"]) and np.isnan(log.loc[4, "psnr2d"]) and np.isnan(log.loc[5, "psnr2d"])
    assert log.loc[6, "psnr2d"] == 16.0
    assert log.loc[1, "ssim3d"] == df.loc[0, "ssim3d"]
    assert list(log.columns[:6]) == list(LOG_COLUMNS) and "loss" in log.columns
    # a larger tolerance fills the long gap too
    log20 = read_train_log(p, max_gap_iters=21)
    assert log20.loc[3, "psnr2d"] == 12.0 and log20.loc[4, "psnr2d"] == 12.0 and np.isnan(log20.loc[5, "psnr2d"])


def test_read_train_log_drops_rows_without_iteration_and_dedups(tmp_path):
    p = tmp_path / "train_log.csv"
    p.write_text(
        "iteration,timestamp,psnr2d,ssim2d,psnr3d,ssim3d,loss\n"
        "0,0.0,10,0.1,5,0.1,1.0\n"
        ",1.0,11,0.2,6,0.2,0.9\n"
        "100,2.0,12,0.3,,0.3,0.8\n"
        "100,2.5,13,0.35,7,0.31,0.7\n"
        "50,1.5,,,,,0.85\n"
    )
    log = read_train_log(p)
    assert list(log["iteration"]) == [0, 50, 100]
    assert log.loc[2, "psnr2d"] == 13.0  # resumed run: last duplicate wins
    assert np.isnan(log.loc[1, "psnr2d"])  # 50 iterations after the last value: not filled


def test_read_train_log_rejects_wrong_columns(tmp_path):
    p = tmp_path / "train_log.csv"
    p.write_text("iteration,psnr2d,timestamp,ssim2d,psnr3d,ssim3d\n0,1,2,3,4,5\n")
    with pytest.raises(CtsplatError, match="first columns must be iteration,timestamp"):
        read_train_log(p)
    with pytest.raises(CtsplatError, match="cannot read"):
        read_train_log(tmp_path / "missing.csv")


def test_read_per_view_reads_the_written_columns(tmp_path):
    p = tmp_path / "per_view.csv"
    log = CsvLog(p, PER_VIEW_COLUMNS)
    log.reset()
    log.append([{"iteration": 0, "view_id": 1, "azimuth_deg": 10.0, "elevation_deg": 0.0, "split": "val",
                 "psnr2d": 20.0, "ssim2d": 0.5},
                {"iteration": 0, "view_id": 2, "azimuth_deg": 20.0, "elevation_deg": 0.0, "split": "val"},
                {"iteration": 100, "view_id": 1, "azimuth_deg": 10.0, "elevation_deg": 0.0, "split": "test",
                 "psnr2d": 22.0, "ssim2d": 0.6}])
    assert p.read_text().splitlines()[0] == "iteration,view_id,azimuth_deg,elevation_deg,split,psnr2d,ssim2d"
    df = read_per_view(p)
    assert list(df["view_id"]) == [1, 1] and list(df["split"]) == ["val", "test"]
    p.write_text("iteration,view_id,split,psnr2d,ssim2d\n0,1,val,1,1\n")
    with pytest.raises(CtsplatError, match="missing column 'azimuth_deg'"):
        read_per_view(p)


def test_csv_log_writes_numpy_floats_and_truncates_a_crashed_log(tmp_path):
    p = tmp_path / "train_log.csv"
    log = CsvLog(p, LOG_COLUMNS)
    log.reset()
    log.append([{"iteration": 10, "timestamp": np.float64(1.5), "psnr2d": np.float64(30.25)},
                {"iteration": 20, "timestamp": 3.0, "psnr2d": 31.0}])
    assert p.read_text().splitlines()[1] == "10,1.5,30.25,,,"
    assert read_train_log(p)["psnr2d"].tolist() == [30.25, 31.0]
    with open(p, "a") as fh:  # a crash in the middle of a row, and a row without an iteration
        fh.write(",4.0,1,1,1,1\n30,5.0,3")
    log.truncate_after(200)
    assert p.read_text().splitlines() == [",".join(LOG_COLUMNS), "10,1.5,30.25,,,", "20,3.0,31.0,,,"]
    log.truncate_after(10)
    assert p.read_text().splitlines()[1:] == ["10,1.5,30.25,,,"]
    # a file of other columns: rows appended by position would land under them
    p.write_text("iteration,psnr2d\n10,30.0\n")
    with pytest.raises(CtsplatError, match="has another header than this log's columns"):
        log.append([{"iteration": 20}])
    log.truncate_after(10)  # a resumed run rewrites it under its own columns, by name
    assert p.read_text().splitlines() == [",".join(LOG_COLUMNS), "10,,30.0,,,"]
    p.write_text(",".join(LOG_COLUMNS) + "\n10,1,2,3,4,5\n20,1,2,3,4,5,6,7\n")  # a ragged row
    with pytest.raises(CtsplatError, match=r"cannot read training log .*train_log\.csv: Error tokenizing"):
        read_train_log(p)


# ---------------------------------------------------------------------------------------------- gather


def _fake_run(root, volume="phantom", init="fbp", compositor="radiative", mip="on", poses="gt", views=8, seed=0,
              slope=0.01, with_metrics=True):
    cell = {"init": init, "compositor": compositor, "mip": mip, "poses": poses, "views": views, "seed": seed}
    rd = root / volume / "runs" / run_relpath(cell)
    rd.mkdir(parents=True)
    it = np.arange(0, 2001, 100)
    _write_log(rd / "train_log.csv", _log(it, 20 + slope * it))
    if with_metrics:
        (rd / "metrics.json").write_text(json.dumps({"psnr3d": 25.0 + seed, "ssim3d": 0.8, "init": init,
                                                     "nested": {"a": 1}, "fps_resolution": [1920, 1080]}))
    return rd


def test_gather_one_row_per_run_with_axes_and_metrics(tmp_path):
    runs = [_fake_run(tmp_path, init=i, seed=s, slope=0.001 * (s + 1)) for i in ("fbp", "uniform") for s in (0, 1)]
    out = tmp_path / "summary.csv"
    df = gather(runs, out)
    back = pd.read_csv(out)
    assert len(back) == 4 and out.exists()
    assert set(back["init"]) == {"fbp", "uniform"} and set(back["seed"]) == {0, 1}
    assert (back["volume"] == "phantom").all() and (back["views"] == 8).all() and (back["mip"] == "on").all()
    assert list(back["test_psnr3d"]) == [25.0, 26.0, 25.0, 26.0]
    assert back["nested.a"].tolist() == [1] * 4
    row = df[(df["init"] == "fbp") & (df["seed"] == 1)].iloc[0]
    assert row["velocity_psnr2d_per_1000it"] == pytest.approx(2.0)  # 0.002 dB/it -> 2 dB per 1000
    assert row["val_psnr2d_last"] == pytest.approx(20 + 0.002 * 2000)
    # psnr2d = 20 + 0.002 it >= 30 first at it = 5000: never within 2000 iterations
    assert pd.isna(row["iter_to_psnr2d_30"])
    row0 = df[(df["init"] == "uniform") & (df["seed"] == 0)].iloc[0]
    assert row0["val_iteration_last"] == 2000


def test_gather_names_test_and_validation_columns_apart(tmp_path):
    rd = _fake_run(tmp_path)
    (rd / "metrics.json").write_text(json.dumps({
        "psnr2d": 31.0, "ssim2d": 0.91, "psnr3d": 24.0, "ssim3d": 0.7, "psnr3d_r2": 24.5, "ssim3d_r2": 0.8,
        "lpips": 0.12, "lpips_reason": None, "iter_to_psnr2d_30": 5, "time_to_psnr2d_30_s": 0.5,
        "sfm_registration_rate": None, "wall_time_s": 3.0}))
    gather([rd], tmp_path / "summary.csv", thresholds={"psnr2d": 25.0, "ssim2d": 0.9, "psnr3d": 20.0,
                                                         "ssim3d": 0.75}, per_iters=500)
    cols = set(pd.read_csv(tmp_path / "summary.csv").columns)
    row = pd.read_csv(tmp_path / "summary.csv").iloc[0]
    assert {"test_psnr2d", "test_ssim2d", "test_psnr3d", "test_ssim3d", "test_lpips"} <= cols
    assert (row["test_psnr3d_r2"], row["test_ssim3d_r2"]) == (24.5, 0.8)
    assert {"val_psnr2d_last", "val_ssim2d_last", "val_psnr3d_last", "val_ssim3d_last", "val_iteration_last"} <= cols
    # no bare metric names and no final_* columns that could be read as either split
    assert not cols & {"psnr2d", "ssim2d", "psnr3d", "ssim3d", "psnr3d_r2", "ssim3d_r2", "lpips"}
    assert not [c for c in cols if c.startswith("final_")]
    assert (row["test_psnr2d"], row["test_lpips"], row["wall_time_s"]) == (31.0, 0.12, 3.0)
    # milestone keys follow the configured thresholds, 3D ones included; the stale one of metrics.json is gone
    assert {"iter_to_psnr2d_25", "iter_to_ssim2d_090", "iter_to_psnr3d_20", "iter_to_ssim3d_075",
            "time_to_psnr3d_20_s"} <= cols
    assert "iter_to_psnr2d_30" not in cols
    # _log: psnr3d = linspace(15, 25, 21) over it 0..2000 -> >= 20 first at index 10 (it 1000)
    assert row["iter_to_psnr3d_20"] == 1000
    assert "velocity_psnr2d_per_500it" in cols
    assert not [c for c in cols if c.startswith("sfm_")]  # no colmap run: no pose-error columns


def test_gather_adds_sfm_pose_errors_to_colmap_runs(tmp_path):
    gt = _fake_run(tmp_path, poses="gt")
    colmap = _fake_run(tmp_path, poses="colmap")
    other = _fake_run(tmp_path, volume="head", poses="colmap")  # its volume has no sfm/summary.json
    (tmp_path / "phantom" / "sfm").mkdir()
    (tmp_path / "phantom" / "sfm" / "summary.json").write_text(json.dumps({
        "ok": False, "registration_rate": 0.5, "rot_err_deg_median": 91.6, "rot_err_deg_p90": 170.0,
        "centre_err_mm_median": 885.0, "reason": "too few registrations"}))
    df = gather([gt, colmap, other], tmp_path / "summary.csv").set_index("run_dir")
    back = pd.read_csv(tmp_path / "summary.csv").set_index("run_dir")
    r = back.loc[str(colmap)]
    assert (r["sfm_rot_err_deg_median"], r["sfm_rot_err_deg_p90"], r["sfm_centre_err_mm_median"],
            r["sfm_registration_rate"]) == (91.6, 170.0, 885.0, 0.5)
    assert bool(df.loc[str(colmap), "sfm_ok"]) is False
    assert not back.loc[str(other), "sfm_ok"] and pd.isna(back.loc[str(other), "sfm_rot_err_deg_median"])
    assert back.loc[str(gt), ["sfm_ok", "sfm_rot_err_deg_median"]].isna().all()  # not an SfM run


def test_gather_errors(tmp_path):
    with pytest.raises(CtsplatError, match="no run folders"):
        gather([], tmp_path / "s.csv")
    with pytest.raises(CtsplatError, match="not a run folder"):
        gather([tmp_path], tmp_path / "s.csv")
    with pytest.raises(CtsplatError, match=r"not a run folder \(views~abc: views must be an integer\)"):
        gather([tmp_path / "init~fbp/compositor~alpha/mip~off/poses~gt/views~abc/seed~0"], tmp_path / "s.csv")
    rd = tmp_path / "v" / "runs" / "init~fbp/compositor~alpha/mip~off/poses~gt/views~3/seed~0"
    rd.mkdir(parents=True)
    with pytest.raises(CtsplatError, match="neither metrics.json nor train_log.csv"):
        gather([rd], tmp_path / "s.csv")
    assert not (tmp_path / "s.csv").exists()
    good = _fake_run(tmp_path / "r")
    (tmp_path / "existing").mkdir()
    # "new/" would otherwise be written as a file named "new", and "existing" fail with an OSError
    with pytest.raises(CtsplatError, match="new/ names a folder .* give a file path"):
        gather([good], f"{tmp_path / 'new'}/")
    with pytest.raises(CtsplatError, match="existing is a folder, but a file is to be written there; remove"):
        gather([good], tmp_path / "existing")
    assert not (tmp_path / "new").exists() and list((tmp_path / "existing").iterdir()) == []


def test_gather_refuses_a_summary_that_would_replace_an_input(tmp_path):
    """The summary is a CSV written beside the runs: a path with another suffix (pandas would compress it by the
    suffix), one inside a run folder, or a baselines file it reads is refused, and the file is left as it was."""
    good = _fake_run(tmp_path / "r")
    volume = good / "model_volume.nii.gz"
    volume.write_bytes(b"a volume")
    bl = tmp_path / "bl.csv"
    pd.DataFrame({"method": ["fbp"], "n_views": [8], "psnr3d": [20.0], "ssim3d": [0.5]}).to_csv(bl, index=False)
    before = bl.read_bytes()
    for out, match in ((tmp_path / "summary.nii.gz", "must be a .csv file"), (volume, "must be a .csv file"),
                       (good / "summary.csv", "lies inside the run folder"), (bl, "one of the baselines files")):
        with pytest.raises(CtsplatError, match=match):
            gather([good], out, baselines_csvs=[bl])
    assert volume.read_bytes() == b"a volume" and bl.read_bytes() == before
    assert not (tmp_path / "summary.nii.gz").exists() and not (good / "summary.csv").exists()


def test_gather_matches_baselines_outside_the_layout_by_volume_id_and_names_a_file_it_cannot_match(tmp_path,
                                                                                                  caplog):
    """A baselines.csv made by ``ctsplat baseline --out`` anywhere carries its volume's id in baselines.json; a run
    of that volume matches it by the id, a run of another volume of the same name does not, and a file no run
    matches is named in a warning instead of silently leaving the columns empty."""
    run = _fake_run(tmp_path)
    other = _fake_run(tmp_path / "elsewhere")  # volume "phantom" as well, but other content
    for rd, vid in ((run, "vol-a"), (other, "vol-b")):
        m = json.loads((rd / "metrics.json").read_text())
        (rd / "metrics.json").write_text(json.dumps({**m, "volume_id": vid}))
    bdir = tmp_path / "my_baselines"
    bdir.mkdir()
    pd.DataFrame({"method": ["fbp"], "n_views": [8], "psnr3d": [21.0], "ssim3d": [0.6]}).to_csv(
        bdir / "baselines.csv", index=False)
    (bdir / "baselines.json").write_text(json.dumps({"volume_id": "vol-a"}))
    back = gather([run, other], tmp_path / "s.csv", baselines_csvs=[bdir / "baselines.csv"]).set_index("run_dir")
    assert back.loc[str(run), "best_baseline_test_psnr3d"] == 21.0
    assert pd.isna(back.loc[str(other), "best_baseline"])
    assert "no run matches" not in caplog.text
    (bdir / "baselines.json").write_text(json.dumps({"volume_id": "vol-c"}))
    back = gather([run], tmp_path / "s.csv", baselines_csvs=[bdir / "baselines.csv"])
    assert back["best_baseline"].isna().all()
    assert f"no run matches the baselines in {bdir / 'baselines.csv'}" in caplog.text


def test_gather_writes_milestone_iterations_as_integers_when_some_run_misses_one(tmp_path):
    runs = [_fake_run(tmp_path, seed=0, slope=0.01), _fake_run(tmp_path, seed=1, slope=0.001)]  # 30 dB at 1000 / never
    gather(runs, tmp_path / "s.csv", thresholds={"psnr2d": 30.0})
    written = pd.read_csv(tmp_path / "s.csv", dtype=str, keep_default_na=False)  # the text as written
    assert list(written["iter_to_psnr2d_30"]) == ["1000", ""]


def test_gather_names_a_corrupt_metrics_file_in_one_line(tmp_path):
    rd = _fake_run(tmp_path)
    (rd / "metrics.json").write_text("{bad")
    with pytest.raises(CtsplatError, match=r"metrics\.json is not valid JSON .*run that step again"):
        gather([rd], tmp_path / "s.csv")
    assert not (tmp_path / "s.csv").exists()


def test_parse_run_dir_roundtrip():
    row = {"volume": "head", "init": "sfm", "compositor": "radiative_unrectified", "mip": "off", "poses": "colmap",
           "views": 75, "seed": 2}
    path = f"results/{row['volume']}/runs/{run_relpath(row)}"
    assert path == "results/head/runs/init~sfm/compositor~radiative_unrectified/mip~off/poses~colmap/views~75/seed~2"
    assert parse_run_dir(path) == row


def test_load_runs_tags_rows(tmp_path):
    runs = [_fake_run(tmp_path, compositor=c) for c in ("radiative", "alpha")]
    summary = gather(runs, tmp_path / "summary.csv")
    logs = load_runs(summary)
    assert len(logs) == 2 * 21
    assert set(logs["compositor"]) == {"radiative", "alpha"}


def test_load_per_view_tags_rows_and_keeps_the_split(tmp_path):
    runs = [_fake_run(tmp_path, init=i) for i in ("fbp", "uniform")]
    for rd in runs:
        pd.DataFrame({"iteration": [100, 100, 200], "view_id": [1, 2, 1], "azimuth_deg": [0.0, 90.0, 0.0],
                      "elevation_deg": 0.0, "split": ["val", "val", "train"], "psnr2d": [20.0, 21.0, 22.0],
                      "ssim2d": [0.5, 0.6, 0.7]}).to_csv(rd / "per_view.csv", index=False)
    pv = load_per_view(gather(runs, tmp_path / "s.csv"))
    assert len(pv) == 4 and set(pv["split"]) == {"val"} and set(pv["init"]) == {"fbp", "uniform"}


def test_gather_lists_the_cells_of_a_failed_sfm_run_as_not_run(tmp_path):
    gt = _fake_run(tmp_path, poses="gt")
    colmap = tmp_path / "phantom" / "runs" / run_relpath({"init": "fbp", "compositor": "radiative", "mip": "on",
                                                          "poses": "colmap", "views": 8, "seed": 0})
    (tmp_path / "phantom" / "sfm").mkdir(parents=True)
    (tmp_path / "phantom" / "sfm" / "summary.json").write_text(json.dumps({
        "ok": False, "registration_rate": 1.0, "rot_err_deg_median": 3.2, "reason": "median rotation error 3.2 deg"}))
    back = gather([gt, colmap], tmp_path / "summary.csv").set_index("run_dir")
    assert back.loc[str(gt), "status"] == "trained" and pd.isna(back.loc[str(gt), "not_run_reason"])
    r = back.loc[str(colmap)]
    assert r["status"] == "not run" and pd.isna(r["test_psnr3d"])
    assert r["not_run_reason"].startswith("SfM failed (") and "median rotation error 3.2 deg" in r["not_run_reason"]
    assert r["sfm_rot_err_deg_median"] == 3.2 and not r["sfm_ok"]
    # an ok SfM run does not excuse a missing result: the cell should have trained
    (tmp_path / "phantom" / "sfm" / "summary.json").write_text(json.dumps({"ok": True, "registration_rate": 1.0}))
    with pytest.raises(CtsplatError, match="neither metrics.json nor train_log.csv"):
        gather([gt, colmap], tmp_path / "summary2.csv")
    # trained while an earlier SfM run was ok, the cell's outputs stay when SfM fails later: not run all the same
    trained = _fake_run(tmp_path, poses="colmap", views=8, seed=0)
    assert trained == colmap and (colmap / "metrics.json").exists()
    assert gather([gt, colmap], tmp_path / "summary3.csv").set_index("run_dir").loc[str(colmap), "status"] == "trained"
    (tmp_path / "phantom" / "sfm" / "summary.json").write_text(json.dumps({
        "ok": False, "registration_rate": 1.0, "rot_err_deg_median": 3.2, "reason": "median rotation error 3.2 deg"}))
    stale = gather([gt, colmap], tmp_path / "summary4.csv").set_index("run_dir").loc[str(colmap)]
    assert stale["status"] == "not run" and pd.isna(stale["test_psnr3d"])


def test_gather_compares_each_run_with_the_strongest_baseline_at_its_views(tmp_path):
    runs = [_fake_run(tmp_path, views=v) for v in (8, 16)] + [_fake_run(tmp_path, volume="head", views=8)]
    bdir = tmp_path / "phantom" / "baselines" / "circular"
    bdir.mkdir(parents=True)
    pd.DataFrame({"method": ["fbp", "asd_pocs", "fbp", "asd_pocs"], "n_views": [8, 8, 16, 16],
                  "psnr3d": [22.0, 27.5, 24.0, 23.0], "ssim3d": [0.6, 0.85, 0.7, 0.65]}).to_csv(
        bdir / "baselines.csv", index=False)
    (runs[1] / "config.json").write_text(json.dumps({"config": {"radiographs": "results/phantom/radiographs/cone"}}))
    back = gather(runs, tmp_path / "summary.csv", baselines_csvs=[bdir / "baselines.csv"]).set_index("run_dir")
    r8, r16, head = back.loc[str(runs[0])], back.loc[str(runs[1])], back.loc[str(runs[2])]
    assert (r8["best_baseline"], r8["best_baseline_test_psnr3d"]) == ("asd_pocs", 27.5)
    assert r8["test_psnr3d_minus_best_baseline_db"] == pytest.approx(25.0 - 27.5)
    assert (r16["best_baseline"], r16["best_baseline_test_ssim3d"]) == ("fbp", 0.7)
    assert r16["test_psnr3d_minus_best_baseline_db"] == pytest.approx(1.0)
    assert pd.isna(head["best_baseline"])  # no baseline of that volume
    # the geometries: the baselines' from their folder, a run's from its config.json (None without one)
    assert r8["best_baseline_geometry"] == "circular" and pd.isna(r8["geometry"])
    assert (r16["geometry"], r16["best_baseline_geometry"]) == ("cone", "circular")


@pytest.mark.parametrize("content", [b"\x89PNG\r\n\x1a\n\xff\xfe\x00binary",
                                     b"iteration,view_id,azimuth_deg,elevation_deg,split,psnr2d,ssim2d\n"
                                     b"0,1,10,0,val,20,0.5\n0,2,20,0,val,21,0.6,extra,fields\n"])
def test_unreadable_logs_are_named_in_one_line(tmp_path, content):
    """A binary file or a row with more fields than the header: one line naming the file, not a traceback."""
    for name, reader in (("per_view.csv", read_per_view), ("train_log.csv", read_train_log)):
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(CtsplatError, match=rf"cannot read .*{name}"):
            reader(p)
