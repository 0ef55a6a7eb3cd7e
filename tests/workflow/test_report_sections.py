"""The report's data, radiographs, SfM, claims and run-figure sections, on a tiny grid where SfM is made to fail.

Real Snakemake jobs in a temp folder: the SfM failure must be visible in the rule log, in the SfM figure, in the
error of the ``poses: colmap`` cell (which must not train on the failed poses), and, after a whole run that
finishes, in ``summary.csv``, the claims table and the HTML report (the ``poses: colmap`` cell listed as not run,
with the reason); the overview figures and the evaluate rule's figures must exist and be registered in the report.
"""

from __future__ import annotations

import base64
import copy
import json
import re

import pandas as pd
import pytest
from smk_helpers import snakemake, write_config
from test_rules import CONFIG, VIEWS

pytestmark = pytest.mark.workflow

VOL = "results/tiny"
CELL = "mip~on/poses~{poses}/views~" + str(VIEWS) + "/seed~0"
GT_RUN = f"{VOL}/runs/init~fbp/compositor~radiative/" + CELL.format(poses="gt")
COLMAP_RUN = f"{VOL}/runs/init~fbp/compositor~radiative/" + CELL.format(poses="colmap")


@pytest.fixture(scope="module")
def wd(tmp_path_factory):
    d = tmp_path_factory.mktemp("wf_report")
    cfg = copy.deepcopy(CONFIG)
    # two-view geometry needs more inliers than any pair of these tiny radiographs has: nothing registers
    cfg["sfm"]["settings"].update(min_num_inliers=100000, init_min_num_inliers=100000)
    cfg["grid"]["axes"]["poses"] = ["gt", "colmap"]
    cfg["train"]["figures"] = True
    cfg["baselines"]["enabled"] = False
    write_config(d / "config.yaml", cfg)
    return d


def test_failed_sfm_is_visible_in_log_figure_and_colmap_cell(wd):
    snakemake(wd, f"{VOL}/sfm/pose_errors.png", configfile=wd / "config.yaml")
    summary = json.loads((wd / VOL / "sfm/summary.json").read_text())
    assert summary["ok"] is False and summary["reason"]
    log = (wd / "results/logs/sfm/tiny.log").read_text()
    warnings = [ln for ln in log.splitlines() if " WARNING " in ln and "SfM failed" in ln]
    assert warnings and summary["reason"] in warnings[0]
    assert (wd / VOL / "sfm/pose_errors.png").stat().st_size > 1000

    from ctsplat.analysis.overview import FAILED_COLOUR, plot_sfm

    fig = plot_sfm(pd.read_csv(wd / VOL / "sfm/poses.csv"), summary, wd / "again.png")
    title = fig._suptitle
    assert title.get_text().startswith("SfM FAILED: ") and summary["reason"] in title.get_text()
    assert title.get_color() == FAILED_COLOUR

    # the colmap cell refuses to train on the failed poses, with a message naming the SfM run and its summary
    proc = snakemake(wd, f"{COLMAP_RUN}/training.json", configfile=wd / "config.yaml", check=False)
    assert proc.returncode != 0
    train_log = (wd / COLMAP_RUN / "logs/train.log").read_text()
    assert "the SfM run failed" in train_log and "sfm/summary.json" in train_log
    assert not (wd / COLMAP_RUN / "model.pt").exists()


def test_overview_and_run_figures_are_in_the_report(wd):
    targets = [f"{VOL}/figures/volume_slices.png", f"{VOL}/figures/radiographs_circular.png",
               f"{VOL}/figures/radiographs_carm.png", f"{VOL}/sfm/pose_errors.png", f"{GT_RUN}/metrics.json"]
    snakemake(wd, *targets, configfile=wd / "config.yaml")
    for t in targets[:4]:
        assert (wd / t).stat().st_size > 1000, t
    for name in ("gallery.png", "slices.png", "turntable.gif"):  # train.figures is on: evaluate declares them
        assert (wd / GT_RUN / name).stat().st_size > 100, name
    snakemake(wd, *targets, "--report", "report.html", configfile=wd / "config.yaml")
    html = (wd / "report.html").read_text(errors="ignore")
    for word in ("Data", "Radiographs", "SfM", "Runs", "volume_slices.png", "radiographs_carm.png",
                 "pose_errors.png", "gallery.png", "slices.png"):
        assert word in html, word


def _embedded(html: str, name: str) -> str:
    """A file the report embeds (a base64 data URI after its name)."""
    m = re.search(re.escape(f'"{name}": {{') + r'.*?"data_uri": "data:[^"]*?base64,([A-Za-z0-9+/=]+)"', html, re.S)
    assert m, name
    return base64.b64decode(m.group(1)).decode()


def test_a_whole_run_with_a_failed_sfm_finishes_and_reports_the_cell_as_not_run(wd):
    snakemake(wd, configfile=wd / "config.yaml")  # the default target: every cell, gather, analyse
    assert not (wd / COLMAP_RUN / "model.pt").exists()  # never trained on the failed poses
    reason = json.loads((wd / VOL / "sfm/summary.json").read_text())["reason"]
    summary = pd.read_csv(wd / "results/summary.csv").set_index("poses")
    assert summary.loc["gt", "status"] == "trained" and summary.loc["gt", "test_psnr3d"] > 0
    row = summary.loc["colmap"]
    assert row["status"] == "not run" and pd.isna(row["test_psnr3d"]) and not row["sfm_ok"]
    assert row["not_run_reason"].startswith("SfM failed (") and reason in row["not_run_reason"]
    claims = pd.read_csv(wd / "results/figures/claims.csv")
    not_run = claims[claims["result"] == "not run"]
    assert len(not_run) == 1 and COLMAP_RUN in not_run["comparison"].iloc[0] and reason in not_run["note"].iloc[0]
    snakemake(wd, "--report", "report.html", configfile=wd / "config.yaml")
    html = (wd / "report.html").read_text(errors="ignore")
    assert "Claims" in html and "SfM" in html
    assert reason in _embedded(html, "results/figures/claims.csv")
    assert "not run" in _embedded(html, "results/summary.csv")

