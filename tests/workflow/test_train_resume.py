"""A workflow train job killed after a checkpoint resumes on the next `snakemake` run and ends exactly where an
uninterrupted run ends; a changed training config starts over instead.

The job is killed for real (SIGKILL to the training process, whose pid the run folder's lock file records), as a
cluster kills a job at its time limit: Snakemake sees the job fail, removes its declared outputs and exits; the
rerun finds the checkpoints (not a declared output) and continues.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from smk_helpers import ROOT, SNAKEFILE, SNAKEMAKE, snakemake, write_config

pytestmark = [pytest.mark.workflow, pytest.mark.slow]

SIZE = 20
CONFIG = {
    "volumes": {"tiny": {"source": "phantom", "phantom": {"size": SIZE, "beads": True, "seed": 0}}},
    "preprocessing": {"grid": SIZE},
    "radiographs": {"circular": {"detector_width": SIZE, "detector_height": SIZE, "n_views": 12}},
    "train": {"iterations": 240, "n_init": 300, "eval_every": 20, "eval_views": 2, "checkpoint_every": 40,
              "densify": {"interval": 40, "start": 40}, "figures": False, "turntable_frames": 2, "fps_width": 16,
              "fps_height": 16, "lambda_tv": 0.0},
    "grid": {"axes": {"init": ["volume"], "compositor": ["radiative"], "mip": ["off"], "poses": ["gt"],
                      "views": [6], "seed": [0]}},
}
VOL = "results/tiny"
RUN = f"{VOL}/runs/init~volume/compositor~radiative/mip~off/poses~gt/views~6/seed~0"
TARGET = f"{RUN}/metrics.json"
RULES = ["phantom", "ingest", "project", "train", "evaluate"]
TIMING = {"timestamp", "iters_per_s"}
METRICS = ("psnr2d", "ssim2d", "psnr3d", "ssim3d", "n_gaussians", "iterations", "nan_events", "config_hash",
           "iter_to_psnr2d_30", "densify_cloned", "densify_split", "densify_pruned")


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(fh)]


def _result(run: Path) -> dict:
    metrics = json.loads((run / "metrics.json").read_text())
    return {"train_log": _rows(run / "train_log.csv"), "per_view": _rows(run / "per_view.csv"),
            "per_view_test": _rows(run / "per_view_test.csv"),
            "metrics": {k: metrics.get(k) for k in METRICS}}


def _start(wd: Path, configfile: Path) -> subprocess.Popen:
    cmd = [*SNAKEMAKE, "-s", str(SNAKEFILE), "-d", str(wd), "--cores", "1", TARGET, "--allowed-rules", *RULES,
           "--configfile", str(configfile)]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.Popen(cmd, cwd=wd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def _kill_train_after_first_checkpoint(wd: Path, configfile: Path) -> str:
    """Run snakemake, SIGKILL the training process once its first checkpoint exists; snakemake's output."""
    proc = _start(wd, configfile)
    ckpts = wd / RUN / "checkpoints"
    try:
        deadline = time.monotonic() + 600
        while not any(ckpts.glob("ckpt_*.pt")):
            assert proc.poll() is None, f"snakemake ended before a checkpoint:\n{proc.stdout.read()[-4000:]}"
            assert time.monotonic() < deadline, "no checkpoint within 10 minutes"
            time.sleep(0.02)
        pid = int((wd / RUN / ".ctsplat.lock").read_text().split()[0])  # the training process holds the lock
        os.kill(pid, signal.SIGKILL)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode != 0, out[-3000:]
    return out


@pytest.fixture(scope="module")
def upstream(tmp_path_factory) -> Path:
    """Volume and radiographs, built once and copied (with Snakemake's metadata) into each test's folder."""
    wd = tmp_path_factory.mktemp("upstream")
    write_config(wd / "config.yaml", CONFIG)
    snakemake(wd, f"{VOL}/radiographs/circular/views.json", "--allowed-rules", "phantom", "ingest", "project",
              configfile=wd / "config.yaml")
    return wd


def _copy(src: Path, dst: Path) -> Path:
    subprocess.run(["cp", "-a", f"{src}/.", str(dst)], check=True)  # -a keeps mtimes: nothing upstream reruns
    return dst


def test_killed_train_job_resumes_to_the_uninterrupted_result(upstream: Path, tmp_path: Path) -> None:
    ref = _copy(upstream, tmp_path / "ref")
    snakemake(ref, TARGET, "--allowed-rules", *RULES, configfile=ref / "config.yaml")
    expected = _result(ref / RUN)
    assert len(expected["train_log"]) == CONFIG["train"]["iterations"] // CONFIG["train"]["eval_every"]

    wd = _copy(upstream, tmp_path / "killed")
    _kill_train_after_first_checkpoint(wd, wd / "config.yaml")
    run = wd / RUN
    assert not (run / "training.json").exists() and not (run / "model.pt").exists()
    first = sorted(p.name for p in (run / "checkpoints").glob("ckpt_*.pt"))
    assert first and first[-1] != f"ckpt_{CONFIG['train']['iterations']:08d}.pt"

    snakemake(wd, TARGET, "--allowed-rules", *RULES, configfile=wd / "config.yaml")
    log = (run / "logs/train.log").read_text()
    assert "resuming from" in log, log[-3000:]
    assert _result(run) == expected


def test_changed_config_starts_over(upstream: Path, tmp_path: Path) -> None:
    wd = _copy(upstream, tmp_path / "changed")
    _kill_train_after_first_checkpoint(wd, wd / "config.yaml")
    cfg = yaml.safe_load((wd / "config.yaml").read_text())
    cfg["train"]["iterations"] = 80
    changed = write_config(wd / "changed.yaml", cfg)
    snakemake(wd, TARGET, "--allowed-rules", *RULES, configfile=changed)
    run = wd / RUN
    log = (run / "logs/train.log").read_text()
    assert "resuming from" not in log and "belong to another config" in log, log[-3000:]
    rows = _rows(run / "train_log.csv")
    assert [int(r["iteration"]) for r in rows] == list(range(20, 81, 20))
    assert json.loads((run / "training.json").read_text())["iterations"] == 80
