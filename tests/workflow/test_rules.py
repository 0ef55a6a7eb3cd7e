"""One test per rule: real Snakemake jobs on a tiny phantom grid (1 run) in a temp folder, outputs checked.

Each test asks for its rule's outputs as targets with ``--allowed-rules`` limited to that rule and its upstream
chain, so it also passes when run alone (upstream outputs are built on first use and reused by later tests).
"""

from __future__ import annotations

import json
import os

import nibabel as nib
import numpy as np
import pandas as pd
import pytest
import tifffile
import yaml
from smk_helpers import snakemake, write_config

pytestmark = pytest.mark.workflow

SIZE = 24
N_TRAIN = 8
VIEWS = 4
CONFIG = {
    "volumes": {"tiny": {"source": "phantom", "phantom": {"size": SIZE, "beads": True, "seed": 0}}},
    "preprocessing": {"grid": SIZE},
    "radiographs": {"circular": {"detector_width": SIZE, "detector_height": SIZE, "n_views": N_TRAIN},
                    "carm": {"camera": "cone", "orbit": "carm", "n_views": 12, "wobble_deg": 15.0, "dso_mm": 600.0,
                             "dsd_mm": 1000.0, "detector_width": 48, "detector_height": 48}},
    "baselines": {"enabled": True, "settings": {"sart_max_iterations": 1, "save_volumes": False}},
    "sfm": {"enabled": True, "settings": {"geometry": "carm", "max_num_features": 512}},
    "train": {"iterations": 10, "n_init": 500, "eval_every": 5, "eval_views": 2, "checkpoint_every": 10,
              "densify": {"interval": 5, "start": 5}, "figures": False, "turntable_frames": 2, "fps_width": 32,
              "fps_height": 32},
    "grid": {"axes": {"init": ["fbp"], "compositor": ["radiative"], "mip": ["on"], "poses": ["gt"],
                      "views": [VIEWS], "seed": [0]}},
    "analysis": {"window": 2, "velocity_per_iters": 5, "acf_max_lag": 2, "kde_windows": 2},
}
VOL = "results/tiny"
RUN = f"{VOL}/runs/init~fbp/compositor~radiative/mip~on/poses~gt/views~{VIEWS}/seed~0"
CHAIN = {
    "phantom": [],
    "ingest": ["phantom"],
    "project": ["phantom", "ingest"],
    "baseline": ["phantom", "ingest", "project"],
    "sfm": ["phantom", "ingest", "project"],
    "train": ["phantom", "ingest", "project"],
    "evaluate": ["phantom", "ingest", "project", "train"],
    "run_figures": ["phantom", "ingest", "project", "train"],
    "gather": ["phantom", "ingest", "project", "train", "evaluate"],
    "analyse": ["phantom", "ingest", "project", "train", "evaluate", "baseline", "gather"],
}


@pytest.fixture(scope="module")
def wd(tmp_path_factory):
    d = tmp_path_factory.mktemp("wf")
    write_config(d / "config.yaml", CONFIG)
    return d


def run_rule(wd, rule, *targets, extra=()):
    allowed = [*CHAIN[rule], rule]
    return snakemake(wd, *targets, "--allowed-rules", *allowed, *extra, configfile=wd / "config.yaml")


def test_rule_phantom(wd):
    run_rule(wd, "phantom", f"{VOL}/phantom_dicom")
    files = sorted((wd / VOL / "phantom_dicom").rglob("*.dcm")) or sorted(
        p for p in (wd / VOL / "phantom_dicom").rglob("*") if p.is_file())
    assert len(files) == SIZE  # one DICOM file per slice
    import pydicom

    ds = pydicom.dcmread(files[0])
    assert ds.Modality == "CT" and int(ds.Rows) == SIZE
    assert (wd / "results/logs/phantom/tiny.log").exists() and (wd / "results/benchmarks/phantom/tiny.tsv").exists()


def test_rule_ingest(wd):
    run_rule(wd, "ingest", f"{VOL}/volume.nii.gz")
    img = nib.load(wd / VOL / "volume.nii.gz")
    assert img.shape == (SIZE, SIZE, SIZE)
    data = np.asarray(img.dataobj)
    assert 0.0 <= data.min() and data.max() <= 1.0 and data.max() > 0.1  # normalised attenuation
    meta = json.loads((wd / VOL / "volume.json").read_text())
    assert meta["intensity"]["mu_scale_per_mm"] > 0


def test_rule_project(wd):
    run_rule(wd, "project", f"{VOL}/radiographs/circular/views.json")
    rd = wd / VOL / "radiographs" / "circular"
    p = tifffile.imread(rd / "line_integrals.tif")
    views = json.loads((rd / "views.json").read_text())["views"]
    assert p.shape == (len(views), SIZE, SIZE) and p.dtype == np.float32
    assert sum(v["split"] == "train" for v in views) == N_TRAIN
    assert p.max() > 0 and len(list((rd / "png").glob("*.png"))) == len(views)


def test_rule_baseline(wd):
    run_rule(wd, "baseline", f"{VOL}/baselines/circular/baselines.csv")
    df = pd.read_csv(wd / VOL / "baselines/circular/baselines.csv")
    assert {"method", "filter", "iterations", "n_views", "psnr3d", "ssim3d", "seconds"} <= set(df.columns)
    assert set(df["method"]) >= {"fbp", "sart"}
    assert (df["n_views"] == VIEWS).all()  # the grid's view counts
    assert np.isfinite(df["psnr3d"]).all()
    # a rerun replaces the folder that Snakemake emptied of the rule's declared outputs (the two tables)
    proc = run_rule(wd, "baseline", f"{VOL}/baselines/circular/baselines.csv", extra=("--forcerun", "baseline"))
    assert "rule baseline:" in proc.stdout + proc.stderr
    assert pd.read_csv(wd / VOL / "baselines/circular/baselines.csv")["psnr3d"].tolist() == df["psnr3d"].tolist()


def test_rule_sfm(wd):
    run_rule(wd, "sfm", f"{VOL}/sfm/summary.json")
    summary = json.loads((wd / VOL / "sfm/summary.json").read_text())
    # 12 views of a 32³ phantom register nothing: the rule does not crash, and records the failure with its numbers
    # (a registering run: tests/unit/test_sfm_colmap.py and `make run`)
    assert summary["ok"] is False and summary["registration_rate"] == 0.0
    assert summary["reason"].startswith("registration rate 0 (need >= 0.8)")
    poses = pd.read_csv(wd / VOL / "sfm/poses.csv")
    # SfM registered the C-arm view set that `project` rendered: same views, same ids
    carm = json.loads((wd / VOL / "radiographs/carm/views.json").read_text())
    assert sorted(poses["view_id"]) == sorted(v["id"] for v in carm["views"])
    assert len(poses) == CONFIG["radiographs"]["carm"]["n_views"] and all("design" in v for v in carm["views"])


def test_rule_train(wd):
    run_rule(wd, "train", f"{RUN}/training.json")
    log = pd.read_csv(wd / RUN / "train_log.csv")
    assert list(log.columns[:6]) == ["iteration", "timestamp", "psnr2d", "ssim2d", "psnr3d", "ssim3d"]
    assert log["iteration"].max() == CONFIG["train"]["iterations"]
    trained = json.loads((wd / RUN / "training.json").read_text())
    assert trained["iterations"] == 10 and trained["n_train_views"] == VIEWS and len(trained["config_hash"]) == 16
    assert not (wd / RUN / "metrics.json").exists()  # test metrics are the evaluate rule's
    cfg = json.loads((wd / RUN / "config.json").read_text())["config"]
    assert cfg["iterations"] == 10 and cfg["views"] == VIEWS and cfg["device"] == "cpu"
    assert (wd / RUN / "logs/train.log").stat().st_size > 0 and (wd / RUN / "logs/train_benchmark.tsv").exists()


def test_changed_training_params_rerun_only_training(wd):
    """A run folder left by an older config: Snakemake's params trigger reruns it (and only what depends on it)."""
    run_rule(wd, "train", f"{RUN}/training.json")
    cfg = yaml.safe_load((wd / "config.yaml").read_text())
    cfg["train"]["lambda_ssim"] = 0.3
    changed = write_config(wd / "changed.yaml", cfg)
    proc = snakemake(wd, f"{RUN}/training.json", "-n", "--allowed-rules", *CHAIN["train"], "train",
                     configfile=changed)
    out = proc.stdout + proc.stderr
    assert "rule train:" in out and "Params have changed since last execution" in out
    assert "rule ingest:" not in out and "rule project:" not in out
    same = snakemake(wd, f"{RUN}/training.json", "-n", configfile=wd / "config.yaml")
    assert "Nothing to be done" in same.stdout + same.stderr


def test_a_preprocessing_setting_that_does_nothing_reruns_nothing(wd):
    run_rule(wd, "ingest", f"{VOL}/volume.nii.gz")
    cfg = yaml.safe_load((wd / "config.yaml").read_text())
    inert = {**cfg, "preprocessing": {**cfg["preprocessing"], "denoise_weight": 0.5, "window": "bone"}}
    proc = snakemake(wd, f"{VOL}/volume.nii.gz", "-n", configfile=write_config(wd / "inert.yaml", inert))
    assert "Nothing to be done" in proc.stdout + proc.stderr, proc.stdout[-3000:]
    acting = {**cfg, "preprocessing": {**cfg["preprocessing"], "denoise": "tv", "denoise_weight": 0.5}}
    proc = snakemake(wd, f"{VOL}/volume.nii.gz", "-n", configfile=write_config(wd / "acting.yaml", acting))
    assert "rule ingest:" in proc.stdout + proc.stderr


def test_rule_evaluate(wd):
    run_rule(wd, "evaluate", f"{RUN}/metrics.json")
    metrics = json.loads((wd / RUN / "metrics.json").read_text())
    views = json.loads((wd / VOL / "radiographs/circular/views.json").read_text())["views"]
    n_test = sum(v["split"] == "test" for v in views)
    assert metrics["split"] == "test" and metrics["n_views"] == n_test and metrics["views_from"] == "test"
    assert metrics["init"] == "fbp" and metrics["mip"] is True and metrics["n_train_views"] == VIEWS
    assert metrics["uses_reference_volume"] is False and len(metrics["config_hash"]) == 16
    assert len(pd.read_csv(wd / RUN / "per_view_test.csv")) == n_test
    # the rule's numbers are the library's: evaluating the saved model again in this process gives the same
    from ctsplat.evaluation import evaluate

    cwd = os.getcwd()
    os.chdir(wd)  # the run's config names its inputs relative to the workflow's directory
    try:
        again = evaluate(RUN, device="cpu", write=False)
    finally:
        os.chdir(cwd)
    assert again["psnr2d"] == pytest.approx(metrics["psnr2d"], abs=1e-6)
    assert again["psnr3d"] == pytest.approx(metrics["psnr3d"], abs=1e-6)


def test_evaluation_settings_and_key_order_do_not_train_again(wd):
    run_rule(wd, "evaluate", f"{RUN}/metrics.json")
    cfg = yaml.safe_load((wd / "config.yaml").read_text())

    def reversed_keys(value):
        return {k: reversed_keys(value[k]) for k in reversed(list(value))} if isinstance(value, dict) else value

    # the same settings in another order, a default written out: nothing to do
    same = {**reversed_keys(cfg), "train": {**reversed_keys(cfg["train"]), "lambda_l1": 1.0}}
    # the milestones as the schema's defaults, written in reverse order (evaluate reads them as params)
    same["analysis"] = {**same["analysis"], "milestones": {"psnr3d": 30.0, "ssim2d": 0.9, "psnr2d": 30.0}}
    proc = snakemake(wd, f"{RUN}/metrics.json", "-n", configfile=write_config(wd / "reordered.yaml", same))
    assert "Nothing to be done" in proc.stdout + proc.stderr, proc.stdout[-3000:]
    # a figure setting, or which model is scored: the evaluation again, not the training
    for key, value in (("turntable_frames", 3), ("model_selection", "best")):
        changed = {**cfg, "train": {**cfg["train"], key: value}}
        proc = snakemake(wd, f"{RUN}/metrics.json", "-n", configfile=write_config(wd / f"{key}.yaml", changed))
        out = proc.stdout + proc.stderr
        assert "rule evaluate:" in out and "rule train:" not in out, (key, out[-3000:])


def test_rule_run_figures(wd):
    names = ["convergence", "porkchop", "acf", "kde"]
    run_rule(wd, "run_figures", *[f"{RUN}/figures/{n}.png" for n in names])
    for n in names:
        assert (wd / RUN / "figures" / f"{n}.png").stat().st_size > 1000


def test_rules_gather_analyse_and_report(wd):
    run_rule(wd, "gather", "results/summary.csv")
    summary = pd.read_csv(wd / "results/summary.csv")
    assert len(summary) == 1
    row = summary.iloc[0]
    assert (row["volume"], row["init"], row["views"], row["mip"]) == ("tiny", "fbp", VIEWS, "on")
    assert np.isfinite(row["test_psnr3d"]) and np.isfinite(row["val_psnr2d_last"])
    run_rule(wd, "analyse", "results/figures/ablation.png", "results/figures/baselines.png")
    from ctsplat.analysis import ANALYSIS_OUTPUTS

    for fname, _ in ANALYSIS_OUTPUTS.values():
        assert (wd / "results/figures" / fname).exists(), fname
    # the HTML report over what exists (every figure registered with caption and category)
    snakemake(wd, "results/summary.csv", *[f"results/figures/{f}" for f, _ in ANALYSIS_OUTPUTS.values()],
              "--report", "report.html", configfile=wd / "config.yaml")
    html = (wd / "report.html").read_text(errors="ignore")
    assert len(html) > 10000 and "ablation.png" in html and "Convergence" in html
