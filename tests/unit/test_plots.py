"""ctsplat.analysis.plots: figures carry exactly the data of ctsplat.analysis.stats (checked on the returned
artists) and PNGs."""

from __future__ import annotations

import hashlib
import json

import imageio.v3 as iio
import numpy as np
import pandas as pd
import pytest

from ctsplat.analysis import ANALYSIS_OUTPUTS, RUN_FIGURES, plots
from ctsplat.analysis.gather import gather, load_runs
from ctsplat.analysis.stats import (
    acf,
    acf_band,
    detrend,
    paired_table,
    porkchop_table,
    rolling_centered,
    velocity_curve,
)
from ctsplat.formats.runlog import METRICS_2D3D, read_per_view
from ctsplat.grid import run_relpath
from ctsplat.utils import CtsplatError


def _log(n=41, step=50, seed=0):
    rng = np.random.default_rng(seed)
    it = np.arange(n) * step
    return pd.DataFrame({
        "iteration": it,
        "timestamp": it * 0.1,
        "psnr2d": 18 + 12 * (1 - np.exp(-it / 600)) + rng.normal(0, 0.3, n),
        "ssim2d": 0.5 + 0.45 * (1 - np.exp(-it / 600)) + rng.normal(0, 0.01, n),
        "psnr3d": 15 + 10 * (1 - np.exp(-it / 800)),
        "ssim3d": 0.4 + 0.4 * (1 - np.exp(-it / 800)),
        "loss": np.linspace(1, 0.1, n),
    })


def _per_view(iterations=(0, 100, 200), views=5):
    rows = []
    for it in iterations:
        for v in range(views):
            rows.append({"iteration": it, "view_id": v, "azimuth_deg": (v * 77) % 360, "elevation_deg": 0.0,
                         "split": "val", "psnr2d": 20 + v + it / 100, "ssim2d": 0.5 + 0.01 * v})
    return pd.DataFrame(rows)


def _is_png(path):
    img = iio.imread(path)
    return img.ndim == 3 and img.shape[0] > 50 and img.shape[1] > 50


def _make_run(root, init="fbp", compositor="radiative", views=8, seed=0):
    cell = {"init": init, "compositor": compositor, "mip": "on", "poses": "gt", "views": views, "seed": seed}
    rd = root / "phantom" / "runs" / run_relpath(cell)
    rd.mkdir(parents=True)
    _log(seed=seed).to_csv(rd / "train_log.csv", index=False)
    _per_view().to_csv(rd / "per_view.csv", index=False)
    (rd / "metrics.json").write_text(json.dumps({"psnr3d": 24.0 + views / 10 + seed, "ssim3d": 0.7,
                                                 "psnr2d": 30.0, "ssim2d": 0.9}))
    return rd


def test_convergence_raw_thin_and_centred_mean_thick(tmp_path):
    log = _log()
    fig = plots.plot_convergence(log, tmp_path / "c.png", window=5)
    assert _is_png(tmp_path / "c.png")
    ax = fig.axes[0]
    raw, smooth = ax.get_lines()
    np.testing.assert_allclose(raw.get_ydata(), log["psnr2d"])
    np.testing.assert_allclose(smooth.get_ydata(), rolling_centered(log["psnr2d"], 5))
    assert smooth.get_linewidth() > 2 * raw.get_linewidth()
    assert [a.get_ylabel() for a in fig.axes[:4]] == [plots.METRIC_LABELS[m] for m in METRICS_2D3D]


def test_convergence_with_missing_3d_metrics(tmp_path):
    log = _log()
    log["psnr3d"] = np.nan
    fig = plots.plot_convergence(log, tmp_path / "c.png")
    assert not fig.axes[2].get_lines()  # an empty panel with a note, not a crash
    assert _is_png(tmp_path / "c.png")


def test_porkchop_heatmap_holds_the_pivot_table_with_azimuth_ticks_and_units(tmp_path):
    pv = read_per_view(_write(tmp_path / "pv.csv", _per_view()))
    fig = plots.plot_porkchop(pv, tmp_path / "p.png", split="val")
    mesh = fig.axes[0].collections[0]
    table = porkchop_table(pv, "psnr2d", split="val")
    np.testing.assert_allclose(np.asarray(mesh.get_array()).reshape(table.shape), table.to_numpy())
    # rows are labelled with what they are: azimuth in degrees (view ids 0..4 at (v * 77) % 360)
    ticks = [t.get_text() for t in fig.axes[0].get_yticklabels()]
    az = {v: (v * 77) % 360 for v in range(5)}
    assert ticks == [f"{az[v]}° (#{v})" for v in table.index]
    assert "azimuth (°)" in fig.axes[0].get_ylabel()
    cbar_labels = [a.get_ylabel() for a in fig.axes if a.get_ylabel() and a not in fig.axes[:1]]
    assert "PSNR 2D (dB)" in cbar_labels and any("SSIM 2D (unitless" in lb for lb in cbar_labels)
    assert _is_png(tmp_path / "p.png")


def _write(path, df):
    df.to_csv(path, index=False)
    return path


def test_acf_plot_is_of_the_detrended_curve_with_its_band(tmp_path):
    log = _log(n=120)
    fig = plots.plot_acf(log, tmp_path / "a.png", max_lag=10, window=7)
    pts = fig.axes[0].get_lines()[0]
    resid = detrend(log["psnr2d"], "rolling", 7)
    np.testing.assert_allclose(pts.get_ydata(), acf(resid, 10))
    band = fig.axes[0].patches[0]  # the axhspan of the 95 % band
    assert band.get_y() == pytest.approx(-acf_band(resid.size))
    assert band.get_y() + band.get_height() == pytest.approx(acf_band(resid.size))


def test_acf_runs_one_named_line_per_run_and_a_band(tmp_path):
    runs = [_make_run(tmp_path, init=i, seed=s) for i in ("fbp", "uniform") for s in (0, 1)]
    logs = load_runs(gather(runs, tmp_path / "s.csv"))
    fig = plots.plot_acf_runs(logs, tmp_path / "acf.png", max_lag=8, window=5)
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[:4] == ["init=fbp, seed=0", "init=fbp, seed=1", "init=uniform, seed=0", "init=uniform, seed=1"]
    assert labels[4].startswith("95 % band")
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    g = logs[(logs["init"] == "uniform") & (logs["seed"] == 1)]
    np.testing.assert_allclose(lines["init=uniform, seed=1"].get_ydata(), acf(detrend(g["psnr2d"], "rolling", 5), 8))
    styles = {(ln.get_color(), ln.get_linestyle()) for ln in lines.values() if ln.get_label() in labels}
    assert len(styles) == 4  # every run distinguishable


def _per_view_ssim(iterations=range(0, 1001, 100), views=12, seed=0, init_gap=0.0):
    rng = np.random.default_rng(seed)
    rows = []
    for it in iterations:
        for v in range(views):
            q = 1 - (0.3 + init_gap) * np.exp(-it / 300) - rng.exponential(0.004)
            rows.append({"iteration": it, "view_id": v, "azimuth_deg": 30.0 * v, "elevation_deg": 0.0,
                         "split": "val", "psnr2d": 20 + it / 100 + rng.normal(0, 0.5), "ssim2d": min(q, 1.0)})
    return pd.DataFrame(rows)


def test_kde_windows_from_per_view_values_bounded_and_labelled_in_iterations(tmp_path):
    pv = _per_view_ssim()
    fig = plots.plot_kde_windows(pv, tmp_path / "k.png", n_windows=3)
    ssim_ax = fig.axes[1]
    curves = [ln for ln in ssim_ax.get_lines() if ln.get_linestyle() == "-"]
    assert len(curves) == 3  # one density per window
    assert max(ln.get_xdata().max() for ln in curves) <= 1.0  # SSIM density never runs past 1
    legend = [t.get_text() for t in ssim_ax.get_legend().get_texts()]
    # windows named by their iteration range; each built from the per-view values (12 views per evaluation)
    assert legend[0].startswith("iterations 0–333") and "(n=48)" in legend[0]
    assert _is_png(tmp_path / "k.png")


def test_kde_conditions_one_curve_per_condition_not_pooled_over_init(tmp_path):
    frames = []
    for init, gap in (("fbp", 0.0), ("uniform", 0.2)):
        for seed in (0, 1):
            cell = {"volume": "phantom", "init": init, "compositor": "radiative", "mip": "on", "poses": "gt",
                    "views": 8, "seed": seed, "run_dir": f"r/{init}/{seed}"}
            frames.append(_per_view_ssim(seed=seed, init_gap=gap).assign(**cell))
    pv = pd.concat(frames, ignore_index=True)
    fig = plots.plot_kde_conditions(pv, tmp_path / "kc.png", n_windows=4)
    ax = fig.axes[1]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["init=fbp", "init=uniform"]  # seeds pooled within a condition, inits kept apart
    curves = {ln.get_label(): ln for ln in ax.get_lines()}
    assert max(curves[lb].get_xdata().max() for lb in labels) <= 1.0
    # the uniform curve is the density of its own last-window values only
    last = pv[(pv["init"] == "uniform") & (pv["iteration"] >= 750)]["ssim2d"]
    from ctsplat.analysis.stats import bounded_kde

    x, d = bounded_kde(last, -1.0, 1.0)
    np.testing.assert_allclose(curves["init=uniform"].get_ydata(), d)
    assert "iterations 750–1000" in fig.texts[0].get_text()


def test_kde_conditions_one_column_of_panels_per_compositor(tmp_path):
    frames = []
    for comp, gap in (("radiative", 0.0), ("alpha", 0.1), ("radiative_unrectified", 0.3)):
        for init in ("fbp", "uniform"):
            cell = {"volume": "phantom", "init": init, "compositor": comp, "mip": "on", "poses": "gt", "views": 8,
                    "seed": 0, "run_dir": f"r/{comp}/{init}"}
            frames.append(_per_view_ssim(seed=len(frames), init_gap=gap).assign(**cell))
    pv = pd.concat(frames, ignore_index=True)
    fig = plots.plot_kde_conditions(pv, tmp_path / "kf.png", n_windows=4)
    assert len(fig.axes) == 6  # PSNR and SSIM rows, one column per compositor
    titles = [ax.get_title() for ax in fig.axes[:3]]
    assert titles == ["compositor=alpha", "compositor=radiative", "compositor=radiative_unrectified"]
    for ax in fig.axes:  # each panel: the two inits of its own compositor, named without it
        assert sorted(ln.get_label() for ln in ax.get_lines() if not ln.get_label().startswith("_")) == \
            ["init=fbp", "init=uniform"]
    ssim_alpha = {ln.get_label(): ln for ln in fig.axes[3].get_lines()}
    from ctsplat.analysis.stats import bounded_kde

    last = pv[(pv["compositor"] == "alpha") & (pv["init"] == "uniform") & (pv["iteration"] >= 750)]["ssim2d"]
    np.testing.assert_allclose(ssim_alpha["init=uniform"].get_ydata(), bounded_kde(last, -1.0, 1.0)[1])
    legend = [t.get_text() for t in fig.axes[2].get_legend().get_texts()]
    assert legend == ["init=fbp", "init=uniform"]
    assert _is_png(tmp_path / "kf.png")


def test_convergence_by_axis_colours_by_axis_and_tells_every_run_apart(tmp_path):
    runs = [_make_run(tmp_path, init=i, views=v) for i in ("fbp", "uniform") for v in (8, 16)]
    logs = load_runs(gather(runs, tmp_path / "summary.csv"))
    fig = plots.plot_convergence_by_axis(logs, "views", tmp_path / "cv.png", window=3)
    lines = fig.axes[0].get_lines()
    assert len(lines) == 4
    by_label = {ln.get_label(): ln for ln in lines}
    # legend names each run by the axes that differ, the colour axis first
    assert sorted(by_label) == ["views=16, init=fbp", "views=16, init=uniform", "views=8, init=fbp",
                                "views=8, init=uniform"]
    assert len({ln.get_color() for ln in lines}) == 2  # one colour per views value ...
    assert by_label["views=8, init=fbp"].get_color() == by_label["views=8, init=uniform"].get_color()
    # ... and the runs that share a colour differ in line style
    assert by_label["views=8, init=fbp"].get_linestyle() != by_label["views=8, init=uniform"].get_linestyle()
    assert len({(ln.get_color(), ln.get_linestyle(), ln.get_marker()) for ln in lines}) == 4
    legend = [t.get_text() for t in fig.axes[1].get_legend().get_texts()]
    assert set(legend) == set(by_label)


def test_velocity_plot_matches_velocity_curve_and_names_conditions(tmp_path):
    runs = [_make_run(tmp_path, init=i) for i in ("fbp", "uniform")]
    logs = load_runs(gather(runs, tmp_path / "s.csv"))
    fig = plots.plot_velocity(logs, tmp_path / "v.png", per_iters=500)
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines() if not ln.get_label().startswith("_")}
    assert set(lines) == {"init=fbp", "init=uniform"}  # not the raw wildcard path
    g = logs[logs["init"] == "uniform"]
    vc = velocity_curve(g["iteration"], g["psnr2d"], 500)
    np.testing.assert_allclose(lines["init=uniform"].get_ydata(), vc["velocity"])
    assert fig.axes[0].get_ylabel() == "median PSNR2D gain (dB per 500 it)"
    assert lines["init=fbp"].get_color() != lines["init=uniform"].get_color()


def test_correlations_per_run_over_windows_never_pooled(tmp_path):
    runs = [_make_run(tmp_path, init=i) for i in ("fbp", "uniform")]
    logs = load_runs(gather(runs, tmp_path / "s.csv"))
    # the second run's 3D metric falls while its 2D metric rises: pooled, the two runs would hide that
    sel = logs["init"] == "uniform"
    logs.loc[sel, "psnr3d"] = 40 - logs.loc[sel, "psnr3d"]
    table = plots.correlation_table(logs, 3)
    assert set(table["run_dir"]) == {str(r) for r in runs}  # no pooled "all runs" row
    assert set(table["window"]) == {"all", "0–666", "666–1333", "1333–2000"}
    fig = plots.plot_correlations(logs, tmp_path / "c.png", n_windows=3)
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines() if not ln.get_label().startswith("_")}
    fbp = next(ln for lb, ln in lines.items() if lb.startswith("init=fbp"))
    uni = next(ln for lb, ln in lines.items() if lb.startswith("init=uniform"))
    np.testing.assert_allclose(fbp.get_xdata(), [333.0, 1000.0, 1666.5], atol=0.5)
    assert np.all(np.asarray(fbp.get_ydata()) > 0.5) and np.all(np.asarray(uni.get_ydata()) < -0.5)
    expect = table[(table["run_dir"] == str(runs[1])) & (table["x"] == "psnr2d") & (table["window"] != "all")]
    np.testing.assert_allclose(uni.get_ydata(), expect["spearman"])
    assert "whole run ρ=" in uni.get_label()
    assert fbp.get_color() != uni.get_color()  # runs told apart
    assert set(table["init"]) == {"fbp", "uniform"}


def test_baselines_plot_has_gs_and_classical_lines(tmp_path):
    summary = pd.DataFrame({"volume": ["p"] * 4, "init": ["fbp"] * 4, "compositor": ["radiative"] * 4,
                            "mip": ["on"] * 4, "poses": ["gt"] * 4, "views": [8, 8, 16, 16], "seed": [0, 1, 0, 1],
                            "test_psnr3d": [20.0, 22.0, 25.0, 27.0]})
    base = pd.DataFrame({"method": ["fbp", "fbp", "sart", "sart"], "filter": ["ramp", "ramp", None, None],
                         "iterations": [0, 0, 3, 3], "n_views": [8, 16, 8, 16], "psnr3d": [15.0, 18.0, 17.0, 19.0],
                         "ssim3d": [0.1] * 4})
    fig = plots.plot_baselines(summary, base, tmp_path / "b.png")
    labels = {line.get_label(): line for line in fig.axes[0].get_lines()}
    gs = "Gaussian, init=fbp, compositor=radiative, mip=on, poses=gt"  # one condition: named in full
    assert set(labels) == {"fbp", "sart", gs}  # one line per method (its settings chosen on validation)
    np.testing.assert_allclose(labels[gs].get_ydata(), [21.0, 26.0])  # mean over seeds
    np.testing.assert_allclose(labels["sart"].get_ydata(), [17.0, 19.0])
    two = pd.concat([summary, summary.assign(init="uniform", test_psnr3d=summary["test_psnr3d"] - 3)])
    fig = plots.plot_baselines(two, base, tmp_path / "b2.png")
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    assert {"Gaussian, init=fbp", "Gaussian, init=uniform"} <= set(lines)  # named by what differs
    colours = [ln.get_color() for ln in lines.values()]
    assert len(set(map(str, colours))) == len(colours)  # no two lines share a colour


def test_baselines_plot_with_one_view_count_is_ranked_bars(tmp_path):
    summary = pd.DataFrame({"volume": "p", "init": ["fbp", "fbp", "volume"], "compositor": ["radiative", "alpha",
                            "radiative"], "mip": "on", "poses": "gt", "views": 24, "seed": 0,
                            "test_psnr3d": [30.0, 27.0, 35.0]})
    base = pd.DataFrame({"method": ["fbp", "asd_pocs"], "n_views": [24, 24], "psnr3d": [25.0, 32.0],
                         "ssim3d": [0.5, 0.8]})
    fig = plots.plot_baselines(summary, base, tmp_path / "bars.png")
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_yticklabels()]
    widths = [p.get_width() for p in ax.patches]
    # best at the top (last bar), one bar per method and per Gaussian condition, the seeded run labelled
    assert labels == ["fbp (classical)", "init=fbp, compositor=alpha", "init=fbp, compositor=radiative",
                      "asd_pocs (classical)", "init=volume, compositor=radiative [reads reference]"]
    np.testing.assert_allclose(widths, [25.0, 27.0, 30.0, 32.0, 35.0])
    assert "24 training views" in ax.get_title() and ax.get_xlabel() == "test PSNR 3D (dB)"
    assert _is_png(tmp_path / "bars.png")


def test_baselines_of_several_volumes_are_never_pooled(tmp_path):
    # the phantom's SART (33 dB) must not stand in for the head's (22 dB)
    base = pd.DataFrame({"volume": ["phantom", "head"], "method": ["sart", "sart"], "n_views": [24, 24],
                         "psnr3d": [33.0, 22.0], "ssim3d": [0.9, 0.6]})
    summary = pd.DataFrame({"volume": ["phantom", "head"], "init": "fbp", "compositor": "radiative", "mip": "on",
                            "poses": "gt", "views": 24, "seed": 0, "test_psnr3d": [34.0, 25.5]})
    ax = plots.plot_baselines(summary, base, tmp_path / "bars.png").axes[0]
    bars = dict(zip([t.get_text() for t in ax.get_yticklabels()], [p.get_width() for p in ax.patches], strict=True))
    assert bars["sart, volume=head (classical)"] == 22.0 and bars["sart, volume=phantom (classical)"] == 33.0
    several = pd.concat([base, base.assign(n_views=48, psnr3d=base["psnr3d"] + 1)])
    fig = plots.plot_baselines(summary, several, tmp_path / "l.png")
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    np.testing.assert_allclose(lines["sart, volume=head"].get_ydata(), [22.0, 23.0])
    np.testing.assert_allclose(lines["sart, volume=phantom"].get_ydata(), [33.0, 34.0])


def test_analyse_refuses_a_bad_summary_in_one_line_and_draws_one_without_scores(tmp_path, monkeypatch):
    outputs = {"baselines": tmp_path / "f" / "baselines.png"}
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(CtsplatError, match=r"empty\.csv is empty; write it with `ctsplat gather`"):
        plots.analyse(tmp_path / "empty.csv", outputs)
    pd.DataFrame({"volume": ["p"], "psnr": [1.0]}).to_csv(tmp_path / "other.csv", index=False)
    with pytest.raises(CtsplatError, match=r"other\.csv is not a summary of `ctsplat gather` \(no run_dir, init, "
                                           r"compositor, mip, poses, views, seed column\)"):
        plots.analyse(tmp_path / "other.csv", outputs)
    pd.DataFrame({"run_dir": ["r"], "volume": ["p"], "init": ["fbp"], "compositor": ["alpha"], "mip": ["on"],
                  "poses": ["gt"], "seed": [0]}).to_csv(tmp_path / "noviews.csv", index=False)
    with pytest.raises(CtsplatError, match=r"noviews\.csv is not a summary of `ctsplat gather` \(no views column\)"):
        plots.analyse(tmp_path / "noviews.csv", outputs)
    cell = {"volume": ["p"], "init": ["fbp"], "compositor": ["alpha"], "mip": ["on"], "poses": ["gt"], "views": [8],
            "seed": [0]}
    pd.concat([pd.DataFrame({"run_dir": [d], **cell}) for d in ("a/r", "b/r")]).to_csv(tmp_path / "two.csv",
                                                                                      index=False)
    with pytest.raises(CtsplatError, match=r"a/r and b/r are runs of one grid cell"):
        plots.analyse(tmp_path / "two.csv", outputs)
    pd.DataFrame(columns=["run_dir", *cell]).to_csv(tmp_path / "header.csv", index=False)
    with pytest.raises(CtsplatError, match=r"header\.csv lists no runs; write it with `ctsplat gather`"):
        plots.analyse(tmp_path / "header.csv", outputs)
    assert not outputs["baselines"].parent.exists()
    view = {"id": 0, "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "t": [0.0, 0.0, 500.0]}
    (tmp_path / "views.json").write_text(json.dumps({"camera": {"model": "cone"}, "views": [view] * 2}, indent=1))
    with pytest.raises(CtsplatError, match=r"views\.json is not a CSV summary of `ctsplat gather` \(ParserError\)"):
        plots.analyse(tmp_path / "views.json", outputs)  # a JSON file given by mistake
    run = _make_run(tmp_path / "work")
    monkeypatch.chdir(tmp_path / "work")
    gather([run.relative_to(tmp_path / "work")], tmp_path / "work" / "summary.csv")  # run_dir relative, as Snakemake
    monkeypatch.chdir(tmp_path)
    with pytest.raises(CtsplatError, match=r"1 run folder\(s\) of .*summary\.csv not found from .* run analyse "
                                           r"from the folder that gather ran in"):
        plots.analyse(tmp_path / "work" / "summary.csv", outputs)
    # a run still in progress: its log has a header and no values yet
    monkeypatch.chdir(tmp_path / "work")
    pd.DataFrame(columns=_log().columns).to_csv(run / "train_log.csv", index=False)
    (run / "metrics.json").unlink()
    gather([run.relative_to(tmp_path / "work")], "summary.csv")
    plots.analyse("summary.csv", outputs)
    assert _is_png(outputs["baselines"])


def test_ablation_is_paired_lines_not_boxes(tmp_path):
    runs = [_make_run(tmp_path, init=i, views=v, seed=s) for i in ("fbp", "uniform") for v in (8, 16)
            for s in (0, 1)]
    summary = gather(runs, tmp_path / "s.csv")
    fig = plots.plot_ablation(summary, tmp_path / "ab.png")
    xlabels = [ax.get_xlabel() for ax in fig.axes]
    assert {"init", "views"} <= set(xlabels) and "seed" not in xlabels  # only the axes that vary, seed excepted
    assert not any(ax.patches for ax in fig.axes)  # no box plots
    assert fig.axes[0].get_ylabel() == "test PSNR 3D (dB)"  # first row: test PSNR3D; columns: init, views
    views_ax = fig.axes[1]
    grey = [ln for ln in views_ax.get_lines() if ln.get_label() != "median"]
    # one line per (init, seed) cell with only views changed: 2 inits x 2 seeds
    assert len(grey) == 4
    # _make_run: test psnr3d = 24 + views / 10 + seed -> every pair rises by 0.8 dB from 8 to 16 views
    for ln in grey:
        np.testing.assert_allclose(np.diff(ln.get_ydata()), 0.8)
    assert "4 pairs" in views_ax.get_title() and "+0.8 dB" in views_ax.get_title()
    table = paired_table(summary, "views", "test_psnr3d")
    assert list(table.columns) == ["8", "16"] and len(table) == 4
    assert _is_png(tmp_path / "ab.png")
    assert {ln.get_color() for ln in grey} == {"0.45"}  # one compositor: grey lines


def test_ablation_colours_the_pairs_by_compositor(tmp_path):
    summary = pd.DataFrame({"volume": "p", "init": ["fbp", "uniform"] * 2, "compositor": ["radiative"] * 2
                            + ["alpha"] * 2, "mip": "on", "poses": "gt", "views": 8, "seed": 0,
                            "test_psnr3d": [30.0, 28.0, 20.0, 19.0]})
    fig = plots.plot_ablation(summary, tmp_path / "ab.png")
    init_ax = next(ax for ax in fig.axes if ax.get_xlabel() == "init" or "uniform" in
                   [t.get_text() for t in ax.get_xticklabels()])
    lines = {ln.get_label(): ln for ln in init_ax.get_lines()}
    assert lines["compositor=alpha"].get_color() != lines["compositor=radiative"].get_color()
    np.testing.assert_allclose(lines["compositor=radiative"].get_ydata(), [30.0, 28.0])
    assert {t.get_text() for t in init_ax.get_legend().get_texts()} == {"compositor=alpha", "compositor=radiative",
                                                                        "median"}


def test_ablation_labels_the_init_that_reads_the_reference(tmp_path):
    summary = pd.DataFrame({"volume": "p", "init": ["fbp", "volume"], "compositor": "radiative", "mip": "on",
                            "poses": "gt", "views": 8, "seed": 0, "test_psnr3d": [30.0, 33.0]})
    fig = plots.plot_ablation(summary, tmp_path / "ab.png")
    ticks = [t.get_text() for ax in fig.axes for t in ax.get_xticklabels()]
    assert "fbp" in ticks and "volume\n(reads the reference)" in ticks


def test_analyse_and_run_figures_write_every_output(tmp_path):
    runs = [_make_run(tmp_path, init=i, compositor=c) for i in ("fbp", "uniform") for c in ("radiative", "alpha")]
    gather(runs, tmp_path / "summary.csv")
    base = tmp_path / "phantom" / "baselines" / "circular" / "baselines.csv"
    base.parent.mkdir(parents=True)
    pd.DataFrame({"method": ["fbp"], "filter": ["ramp"], "iterations": [0], "n_views": [8], "psnr3d": [15.0],
                  "ssim3d": [0.3], "seconds": [0.1]}).to_csv(base, index=False)
    outputs = {name: tmp_path / "figures" / fname for name, (fname, _) in ANALYSIS_OUTPUTS.items()}
    plots.analyse(tmp_path / "summary.csv", outputs, baselines_csvs=[base], analysis={"window": 3})
    for name, path in outputs.items():
        assert path.exists(), name
    ms = pd.read_csv(outputs["milestones"])
    assert len(ms) == 4 and {"iter_to_psnr2d_30", "iters_per_s"} <= set(ms.columns)
    prov = json.loads(outputs["provenance"].read_text())
    assert prov["n_runs"] == 4 and prov["analysis"]["window"] == 3 and prov["code_version"]
    assert prov["summary"]["sha256"] == hashlib.sha256((tmp_path / "summary.csv").read_bytes()).hexdigest()
    table = pd.read_csv(tmp_path / "summary.csv")
    assert prov["run_code_versions"] == (sorted(set(table["code_version"].dropna().astype(str)))
                                         if "code_version" in table else [])
    corr = pd.read_csv(outputs["correlations"])
    # per run: the whole run + analysis.kde_windows (4) windows, for the PSNR and SSIM pairs; nothing pooled
    assert len(corr) == 4 * (1 + 4) * 2 and set(corr["run_dir"]) == {str(r) for r in runs}
    run_out = {name: runs[0] / "figures" / f"{name}.png" for name in RUN_FIGURES}
    plots.run_figures(runs[0], run_out, {"window": 3})
    assert all(_is_png(p) for p in run_out.values())
    with pytest.raises(CtsplatError, match="unknown analysis output 'nope'"):
        plots.analyse(tmp_path / "summary.csv", {"nope": tmp_path / "x.png"})


def test_figures_say_what_they_plot_when_conditions_scores_or_pairs_run_short(tmp_path):
    """More conditions than colours, line styles and markers still get one style each; a reference-seeded run is
    labelled so in the line chart as in the bars; a summary without test metrics is not labelled "test"; the
    ablation title counts the pairs its median is over."""
    table = pd.DataFrame([{"c": f"init={i}, views={v}", "init": i, "views": v} for i in ("fbp", "uniform")
                          for v in (4, 8, 16, 24, 32, 40, 48, 56, 64)])
    styles = plots.condition_styles(table, "c", axes=["init", "views"])
    keys = [(str(st["color"]), st["linestyle"], st["marker"]) for st in styles.values()]
    assert len(set(keys)) == len(keys) == 18
    summary = pd.DataFrame({"volume": "p", "init": ["fbp", "fbp", "volume", "volume"], "compositor": "radiative",
                            "mip": "on", "poses": "gt", "views": [8, 16, 8, 16], "seed": 0,
                            "test_psnr3d": [20.0, 25.0, 30.0, 33.0]})
    base = pd.DataFrame({"method": ["fbp", "fbp"], "n_views": [8, 16], "psnr3d": [15.0, 18.0], "ssim3d": [0.1, 0.2]})
    fig = plots.plot_baselines(summary, base, tmp_path / "lines.png")
    labels = {ln.get_label() for ln in fig.axes[0].get_lines()}
    assert "Gaussian, init=volume [reads reference]" in labels and "Gaussian, init=fbp" in labels
    val = summary.rename(columns={"test_psnr3d": "val_psnr3d_last"}).query("views == 8")
    fig = plots.plot_baselines(val, base.query("n_views == 8"), tmp_path / "bars.png")
    assert fig.axes[0].get_xlabel() == "Gaussians: last validation PSNR 3D (dB); classical: test PSNR 3D (dB)"
    runs = [_make_run(tmp_path, init=i, views=v) for i in ("fbp", "uniform") for v in (8, 16)]
    runs.append(_make_run(tmp_path, init="volume", views=8))  # a cell without its 16-view partner
    fig = plots.plot_ablation(gather(runs, tmp_path / "s.csv"), tmp_path / "ab.png")
    init_ax = next(ax for ax in fig.axes if ax.get_xlabel() == "init")
    # the 16-view cells have fbp and uniform only: their line is drawn, but the median volume−fbp is over one pair
    assert init_ax.get_title().startswith("1 pairs; median volume−fbp")


def test_analyse_reads_every_input_before_writing_an_output(tmp_path):
    runs = [_make_run(tmp_path, init=i) for i in ("fbp", "uniform")]
    gather(runs, tmp_path / "summary.csv")
    _per_view().drop(columns="azimuth_deg").to_csv(runs[1] / "per_view.csv", index=False)
    outputs = {name: tmp_path / "figures" / fname for name, (fname, _) in ANALYSIS_OUTPUTS.items()}
    with pytest.raises(CtsplatError, match="missing column 'azimuth_deg'"):
        plots.analyse(tmp_path / "summary.csv", outputs)
    assert not (tmp_path / "figures").exists() or not any((tmp_path / "figures").iterdir())
