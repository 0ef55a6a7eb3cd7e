"""benchmarks/protocol.py: bad options are refused with one line before any work; a tiny run writes the table."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[2]


def script(name: str, *args: str, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run ``benchmarks/{name}`` with ``args`` in ``cwd`` (the repository on the path)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / name), *map(str, args)],
                          capture_output=True, text=True, env=env, cwd=cwd, timeout=timeout)


def bench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return script("protocol.py", *args, cwd=cwd)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--set", "init=volume"], "--set init is set by this benchmark per run"),
        (["--set", "iterations=5"], "use --iterations"),
        (["--set", "compositor=radiative_rectified"], "train.compositor: 'radiative_rectified' is not one of"),
        (["--set", "init_asd_pocs.iterations=-1"], "train.init_asd_pocs.iterations: -1 is less than the minimum"),
        (["--volumes", "no_such_scan"], "--volumes no_such_scan:"),
        (["--views", "0"], "--views must be >= 1"),
        (["--size", "4"], "--size must be >= 8"),
        (["--baseline-set", "asd_pocs_iterations=0"], "baselines.asd_pocs_iterations: 0 is less than the minimum"),
        (["--baseline-set", "sart_budget=5"], "unknown config key baselines.sart_budget"),
        (["--baseline-set", "n_views=3"], "--baseline-set n_views is set by this benchmark; use --views"),
    ],
)
def test_protocol_refuses_bad_options_before_any_work(tmp_path, args, needle):
    res = bench("--data", tmp_path / "no_data", "--out", tmp_path / "p", *args, cwd=tmp_path)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr, res.stderr
    assert needle in res.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "p").exists()


@pytest.mark.slow
def test_protocol_tiny_run_writes_the_table(tmp_path):
    out = tmp_path / "p"
    res = bench("--volumes", "phantom", "--views", "4", "--size", "16", "--iterations", "4", "--n-init", "100",
                "--threads", "1", "--set", "eval_every=2", "--set", "checkpoint_every=2", "--set", "figures=false",
                "--set", "init_asd_pocs.iterations=3", "--out", out, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    table = pd.read_csv(out / "protocol.csv")
    g = table[table["method"].str.startswith("gaussians")]
    assert len(g) == 1 and g["views"].iloc[0] == 4 and g["volume"].iloc[0] == "phantom"
    for col in ("psnr3d_r2", "ssim3d_r2", "psnr3d", "ssim3d", "psnr2d_test", "ssim2d_test", "wall_time_s"):
        assert math.isfinite(float(g[col].iloc[0])), col
    # a classical method's wall time is its whole selection (which holds the chosen reconstruction once)
    classical = table[~table["method"].str.startswith("gaussians")]
    base = pd.read_csv(next((out / "cache").rglob("baselines.csv")))
    chosen = base.set_index("method")["selection_seconds"]
    for _, row in classical.iterrows():
        name = row["method"].split(":")[0]
        if name in chosen:
            assert row["wall_time_s"] == pytest.approx(float(chosen[name])), name
    md = (out / "protocol.md").read_text()
    assert md.startswith("| volume | views | method | psnr3d_r2 |") and "| phantom | 4 | gaussians (radiative" in md
    assert "psnr3d_r2" in res.stdout  # the table is printed
    # the protocol's view set: cone beam in volume sides, noise on the training views only, 100 test views
    views = json.loads((out / "cache" / "phantom-s16" / "radiographs_n004" / "views.json").read_text())
    assert views["camera"]["model"] == "cone" and views["camera"]["width"] == 32
    assert views["meta"]["noise"]["model"] == "tigre" and views["meta"]["noise"]["splits"] == ["train"]
    assert sum(v["split"] == "test" for v in views["views"]) == 100
    info = json.loads((out / "protocol.json").read_text())
    assert info["args"]["size"] == 16 and info["train"]["compositor"] == "radiative"
    # the protocol's seed: FDK refined by ASD-POCS, its alpha kept when --set changes only the iterations
    assert info["train"]["init_asd_pocs"] == {"iterations": 3, "alpha": 0.1}
    assert "seed: fbp (fdk) + asd_pocs x3" in res.stderr
    # the baselines' budget is the protocol config's (the budget check's), not the library's short default
    import yaml

    budget = yaml.safe_load((ROOT / "config" / "r2_protocol.yaml").read_text())["baselines"]["settings"]
    assert {k: info["baselines"][k] for k in budget} == budget
    # a kept run of other settings is not reused as this call's row
    again = bench("--volumes", "phantom", "--views", "4", "--size", "16", "--iterations", "5", "--n-init", "100",
                  "--threads", "1", "--set", "eval_every=2", "--set", "checkpoint_every=2", "--set", "figures=false",
                  "--set", "init_asd_pocs.iterations=3", "--out", out, cwd=tmp_path)
    assert again.returncode == 2 and "holds a run of other settings" in again.stderr.strip().splitlines()[-1]


@pytest.mark.slow
def test_protocol_baseline_budget_run_skips_the_gaussians_and_keeps_its_own_cache(tmp_path):
    """``--baseline-set`` reaches the baselines (a one-iteration SART budget) in a cache folder of its own."""
    out = tmp_path / "p"
    common = ["--volumes", "phantom", "--views", "4", "--size", "16", "--skip-gaussians", "--out", out]
    res = bench(*common, "--baseline-set", "methods=[sart]", "--baseline-set", "sart_max_iterations=1",
                "--baseline-set", "sart_relaxation=0.5", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    table = pd.read_csv(out / "protocol.csv")
    assert list(table["method"]) == ["sart"]  # no Gaussian row, no other method
    folders = sorted((out / "cache" / "phantom-s16").glob("baselines_*"))
    assert len(folders) == 1 and folders[0].name != "baselines_radiographs_n004_v4"
    chosen = pd.read_csv(folders[0] / "baselines.csv")
    assert json.loads(chosen["params"].iloc[0])["relaxation"] == 0.5
    assert json.loads(chosen["params"].iloc[0])["iterations"] == 1
    info = json.loads((out / "protocol.json").read_text())
    assert info["baselines"]["sart_max_iterations"] == 1
    # the classical reconstruction is offered the Gaussians' read-out sharpening, chosen on validation alike
    assert info["baselines"]["sharpen"] == info["train"]["sharpen"] and len(info["train"]["sharpen"]["amounts"]) > 1
    assert "sharpen_amount" in json.loads(chosen["params"].iloc[0])


@pytest.mark.slow
def test_sharpening_a_finished_suite_gives_what_the_suite_gives_when_it_sharpens(tmp_path):
    """protocol_sharpen.py on a suite made without sharpening equals a suite made with it, number for number."""
    common = ["--volumes", "phantom", "--views", "6", "--size", "16", "--skip-gaussians", "--baseline-set",
              "methods=[fdk,sart]", "--baseline-set", "sart_max_iterations=2"]
    amounts = "[0, 0.3, 0.6, 1.0]"
    plain, sharp = tmp_path / "plain", tmp_path / "sharp"
    for out, sharpen in ((plain, "[0]"), (sharp, amounts)):
        res = script("protocol.py", *common, "--baseline-set", f"sharpen.amounts={sharpen}", "--out", out,
                     cwd=tmp_path)
        assert res.returncode == 0, res.stderr[-3000:]
    res = script("protocol_sharpen.py", plain, "--amounts", "0", "0.3", "0.6", "1.0", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    after = pd.read_csv(plain / "sharpened.csv").set_index("method")
    made = pd.read_csv(next((sharp / "cache").rglob("baselines.csv"))).set_index("method")
    assert sorted(after.index) == sorted(made.index) == ["fdk", "sart"]
    assert set(after["suite"]) == {next((plain / "cache").rglob("baselines.json")).parent.name}
    for method, row in after.iterrows():
        assert row["sharpen_amount"] == json.loads(made.loc[method, "params"])["sharpen_amount"]
        assert row["val_psnr_sharpened"] == pytest.approx(made.loc[method, "val_psnr"], abs=1e-6)
        assert row["val_psnr_sharpened"] >= row["val_psnr"]
    table = pd.read_csv(sharp / "protocol.csv").set_index("method")
    for method, row in after.iterrows():
        label = next(m for m in table.index if m.split(":")[0] == method)
        assert row["psnr3d_r2_sharpened"] == pytest.approx(table.loc[label, "psnr3d_r2"], abs=1e-6)
    # a suite that was sharpened when it was made is skipped, not sharpened twice
    res = script("protocol_sharpen.py", sharp, cwd=tmp_path)
    assert res.returncode == 2 and "were sharpened when they were made" in res.stderr
    assert "no baseline suite made without sharpening" in res.stderr.strip().splitlines()[-1]


def regions(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return script("protocol_regions.py", *args, cwd=cwd, timeout=120)


def test_protocol_regions_splits_the_error_by_region(tmp_path):
    """A reconstruction wrong only outside the object's box scores inf inside it, and the reverse."""
    from ctsplat.formats.volume import Volume, save_volume

    ref = np.zeros((10, 12, 8), np.float32)
    ref[2:5, 3:9, 4:6] = 0.5  # the object's box: 3 x 6 x 2 of 960 voxels
    ref[3, 4, 5] = 0.0  # a hole: inside the box, not object
    box = np.zeros(ref.shape, bool)
    box[2:5, 3:9, 4:6] = True
    out = tmp_path / "p"
    cache = out / "cache" / "slab-s10-0123abcd"  # protocol.volume_key of a scan: name, size, hash of its path
    save_volume(Volume(ref, np.eye(4)), cache / "volume.nii.gz")
    outside = ref + np.where(box, 0.0, 0.1).astype(np.float32)
    save_volume(Volume(outside, np.eye(4)), cache / "baselines_radiographs_n004_v4" / "sart_n004.nii.gz")
    inside = ref + np.where(ref > 0, 0.2, 0.0).astype(np.float32)
    save_volume(Volume(inside, np.eye(4)), out / "runs" / cache.name / "views004" / "model_volume.nii.gz")

    res = regions(out, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    table = pd.read_csv(out / "regions.csv").set_index("method")
    assert set(table.index) == {"sart", "gaussians"} and set(table["views"]) == {4}
    assert set(table["volume"]) == {"slab"}
    n, n_box, n_obj = ref.size, 36, 35
    assert table.loc["sart", "psnr3d_whole"] == pytest.approx(10 * np.log10(n / ((n - n_box) * 0.01)), abs=1e-3)
    assert table.loc["sart", "psnr3d_outside_box"] == pytest.approx(20.0, abs=1e-3)
    assert math.isinf(table.loc["sart", "psnr3d_object_box"]) and math.isinf(table.loc["sart", "psnr3d_object"])
    assert table.loc["gaussians", "psnr3d_object"] == pytest.approx(10 * np.log10(1 / 0.04), abs=1e-3)
    assert table.loc["gaussians", "psnr3d_object_box"] == pytest.approx(10 * np.log10(n_box / (n_obj * 0.04)),
                                                                         abs=1e-3)
    assert math.isinf(table.loc["gaussians", "psnr3d_outside_box"])
    assert table.loc["gaussians", "object_box_fraction"] == pytest.approx(n_box / n, rel=1e-3)
    assert table.loc["sart", "suite"] == "baselines_radiographs_n004_v4" and pd.isna(table.loc["gaussians", "suite"])

    # a second suite (other baseline settings) in the same folder: its rows are told apart by their suite
    save_volume(Volume(inside, np.eye(4)), cache / "baselines_radiographs_n004_v4_full" / "sart_n004.nii.gz")
    res = regions(out, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    sart = pd.read_csv(out / "regions.csv").query("method == 'sart'").set_index("suite")
    assert sorted(sart.index) == ["baselines_radiographs_n004_v4", "baselines_radiographs_n004_v4_full"]
    assert math.isinf(sart.loc["baselines_radiographs_n004_v4", "psnr3d_object"])
    assert sart.loc["baselines_radiographs_n004_v4_full", "psnr3d_object"] == pytest.approx(10 * np.log10(25),
                                                                                             abs=1e-3)


@pytest.mark.parametrize(("args", "needle"), [([], "no saved reconstructions under"),
                                              (["--threshold", "1.5"], "--threshold must be in [0, 1)")])
def test_protocol_regions_refuses_bad_input(tmp_path, args, needle):
    res = regions(tmp_path / "empty", *args, cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert needle in res.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "empty").exists()


@pytest.mark.parametrize(("args", "needle"), [([], "no baseline suite made without sharpening"),
                                              (["--amounts", "0.5"], "--amounts must be in [0, 4] and hold 0"),
                                              (["--amounts", "0", "5"], "--amounts must be in [0, 4]"),
                                              (["--radius-voxels", "0"], "--radius-voxels must be > 0")])
def test_protocol_sharpen_refuses_bad_input(tmp_path, args, needle):
    res = script("protocol_sharpen.py", tmp_path / "empty", *args, cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert needle in res.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "empty").exists()


def test_protocol_does_not_serve_one_scan_from_the_cache_of_another_of_the_same_name(tmp_path):
    """Two --data folders each holding a scan called ``scan``: the second run ingests its own, and protocol.json
    records the run from its start."""
    from ctsplat.phantom import write_phantom_dicom

    for folder, variant in (("dA", "kak_slaney"), ("dB", "high_contrast")):
        write_phantom_dicom(tmp_path / folder / "scan", size=16, beads=False, variant=variant)
    out = tmp_path / "p"
    scores = []
    for folder in ("dA", "dB"):
        res = bench("--volumes", "scan", "--data", tmp_path / folder, "--views", "4", "--size", "16",
                    "--skip-gaussians", "--baseline-set", "methods=[fdk]", "--out", out, cwd=tmp_path)
        assert res.returncode == 0, res.stderr[-3000:]
        record = json.loads((out / "protocol.json").read_text())
        assert record["finished"] and record["args"]["data"] == str(tmp_path / folder)
        scores.append(pd.read_csv(out / "protocol.csv")["psnr3d"].tolist())
    assert len(list((out / "cache").glob("scan-s16-*"))) == 2 and scores[0] != scores[1]
