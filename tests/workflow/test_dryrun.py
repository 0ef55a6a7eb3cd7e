"""Dry runs: exact job counts per rule on example grids, shipped configs, lint/format, bad input before any job."""

from __future__ import annotations

import itertools
import shutil
import subprocess
import sys

import pytest
from smk_helpers import ROOT, SNAKEFILE, job_counts, snakemake, write_config

pytestmark = pytest.mark.workflow


def _cells(axes, volumes, drop):
    keys = list(axes)
    return [dict(zip(["volume", *keys], c, strict=True)) for c in itertools.product(volumes, *axes.values())
            if not drop(dict(zip(["volume", *keys], c, strict=True)))]


def test_large_grid_schedules_shared_work_once_and_training_per_cell(tmp_path):
    (tmp_path / "ct").mkdir()
    (tmp_path / "ct" / "slice_0000.dcm").write_bytes(b"")  # a second volume from a (not yet read) DICOM folder
    axes = {"init": ["fbp", "volume", "sfm"], "compositor": ["radiative", "alpha"], "mip": ["on", "off"],
            "poses": ["gt", "colmap"], "views": [10, 20], "seed": [0, 1]}
    config = {
        "volumes": {"phantom": {"source": "phantom"}, "head": {"source": "ct"}},
        "radiographs": {"circ": {"n_views": 40}, "unused": {"camera": "cone"},
                        "carm": {"camera": "cone", "orbit": "carm", "n_views": 30}},
        "sfm": {"enabled": False},
        "grid": {"geometry": "circ", "axes": axes,
                 "exclude": [{"poses": "colmap", "init": "volume"}, {"volume": "head", "views": [20]}]},
    }
    cfg = write_config(tmp_path / "grid.yaml", config)
    counts = job_counts(snakemake(tmp_path, "-n", configfile=cfg).stdout)
    cells = _cells(axes, ["phantom", "head"], lambda c: (c["poses"] == "colmap" and c["init"] == "volume")
                   or (c["volume"] == "head" and c["views"] == 20))
    assert len(cells) == 80 + 40
    # sfm is a checkpoint: the cells that train on its output (poses: colmap, init: sfm) are scheduled only once
    # its summary says ok, so a dry run lists the others
    n = len([c for c in cells if c["poses"] != "colmap" and c["init"] != "sfm"])
    assert n == 32 + 16
    # project: the training geometry and the C-arm view set SfM registers, per volume; "unused" is never rendered
    # report figures: central slices per volume, a contact sheet per rendered view set, the SfM pose errors
    assert counts == {"phantom": 1, "ingest": 2, "project": 4, "baseline": 2, "sfm": 2, "train": n, "evaluate": n,
                      "run_figures": n, "gather": 1, "analyse": 1, "overview_data": 2, "overview_radiographs": 4,
                      "sfm_figure": 2, "all": 1, "total": 22 + 3 * n}
    assert not (tmp_path / "results").exists()


def test_optional_steps_switch_off(tmp_path):
    (tmp_path / "ct").mkdir()
    (tmp_path / "ct" / "slice_0000.dcm").write_bytes(b"")
    config = {
        "volumes": {"head": {"source": "ct"}},  # replaces the default config: no phantom job
        "baselines": {"enabled": False}, "sfm": {"enabled": False},
        "grid": {"axes": {"init": ["fbp", "uniform"], "compositor": ["radiative"], "mip": ["on"], "poses": ["gt"],
                          "views": [5, 6, 7], "seed": [3]}},
    }
    counts = job_counts(snakemake(tmp_path, "-n", configfile=write_config(tmp_path / "c.yaml", config)).stdout)
    assert counts == {"ingest": 1, "project": 1, "train": 6, "evaluate": 6, "run_figures": 6, "gather": 1,
                      "analyse": 1, "overview_data": 1, "overview_radiographs": 1, "all": 1, "total": 25}


def test_default_config_grid(tmp_path):
    counts = job_counts(snakemake(tmp_path, "-n", configfile=ROOT / "config" / "config.yaml").stdout)
    assert counts["phantom"] == counts["ingest"] == counts["gather"] == counts["analyse"] == 1
    assert counts["project"] == 2  # the training geometry and the C-arm view set of SfM
    # 3 init x 3 compositors x 2 mip with true poses; the poses: colmap cell waits for the sfm checkpoint
    assert counts["train"] == counts["evaluate"] == counts["run_figures"] == 18
    assert counts.get("sfm", 0) == 1 and counts.get("baseline", 0) == 1
    assert counts["overview_data"] == counts["sfm_figure"] == 1 and counts["overview_radiographs"] == 2


def test_real_data_example_dry_run(shared_data):
    """config/ct0051_head.yaml resolves its source relative to the repository root; no default phantom merged in."""
    proc = snakemake(ROOT, "-n", "--nolock", configfile=ROOT / "config" / "ct0051_head.yaml")
    counts = job_counts(proc.stdout)
    # 3 init x 2 compositors x 2 mip x 3 views with true poses (the colmap cells wait for the sfm checkpoint)
    assert counts["train"] == 36 and counts["ingest"] == 1 and "phantom" not in counts
    assert counts["sfm"] == counts["baseline"] == 1 and counts["project"] == 2


def test_lint_passes():
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-s", str(SNAKEFILE), "--lint", "--configfile",
                           str(ROOT / "config" / "config.yaml")], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Congratulations, your workflow is in a good condition" in proc.stdout + proc.stderr


def test_workflow_strings_have_no_invalid_escapes():
    # an invalid escape such as "\+" in a wildcard pattern is a SyntaxWarning at every parse on Python 3.12 (a
    # DeprecationWarning before) and an error in a later Python; a raw string says the same without one
    import tokenize
    import warnings

    for path in [SNAKEFILE, *sorted((ROOT / "workflow").rglob("*.smk"))]:
        with open(path, "rb") as fh:
            strings = [t for t in tokenize.tokenize(fh.readline) if t.type == tokenize.STRING]
        assert strings, path
        for tok in strings:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                try:
                    compile(tok.string, str(path), "eval")
                except (SyntaxError, SyntaxWarning, DeprecationWarning) as exc:
                    pytest.fail(f"{path.name}:{tok.start[0]}: {tok.string}: {exc}")


def test_snakefmt_formatted():
    exe = shutil.which("snakefmt") or str(ROOT / ".venv" / "bin" / "snakefmt")
    files = [str(SNAKEFILE), *map(str, sorted((ROOT / "workflow" / "rules").glob("*.smk")))]
    proc = subprocess.run([exe, "--check", *files], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


# ------------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({"grid": {"axes": {"views": ["ten"]}}}, "invalid config at grid.axes.views[0]: 'ten' is not of type"),
        ({"volumes": {"head": {"source": "missing/ct"}}}, "volume source not found at volumes.head.source"),
        ({"grid": {"exclude": [{"init": "fbp"}]}}, "the ablation grid expands to zero runs"),
    ],
    ids=["bad-value", "missing-source", "empty-grid"],
)
def test_bad_config_fails_before_any_job(tmp_path, config, message):
    proc = snakemake(tmp_path, "--cores", "1", configfile=write_config(tmp_path / "bad.yaml", config), check=False)
    assert proc.returncode != 0
    assert message in proc.stderr + proc.stdout
    assert not (tmp_path / "results").exists()  # nothing ran, nothing written


def test_a_config_file_that_repeats_a_key_fails_before_any_job(tmp_path):
    """Snakemake's YAML loader keeps the last of two equal keys; the workflow names the repeat instead."""
    config = tmp_path / "twice.yaml"
    config.write_text("volumes:\n  head: {source: missing/ct}\n  head: {source: phantom}\n")
    proc = snakemake(tmp_path, "-n", configfile=config, check=False)
    assert proc.returncode != 0
    out = proc.stderr + proc.stdout
    assert f"config file {config}: key 'head' appears twice in one mapping (again on line 3)" in out
    assert not (tmp_path / "results").exists()


def test_a_job_that_fails_on_bad_input_logs_one_line_without_a_traceback(tmp_path):
    """A source that passes the parse-time checks (a .nii.gz name) but is not NIfTI: the ingest job fails with the
    library's one-line error in its log, and writes no volume."""
    (tmp_path / "fake.nii.gz").write_bytes(b"not gzip")
    config = write_config(tmp_path / "bad.yaml", {**_tiny(), "volumes": {"v": {"source": "fake.nii.gz"}}})
    proc = snakemake(tmp_path, "--cores", "1", "results/v/volume.nii.gz", configfile=config, check=False)
    assert proc.returncode != 0
    log = (tmp_path / "results" / "logs" / "ingest" / "v.log").read_text()
    assert "Traceback" not in log
    [line] = [x for x in log.splitlines() if "ERROR" in x]
    assert "rule ingest failed: " in line and "fake.nii.gz" in line
    assert not (tmp_path / "results" / "v" / "volume.nii.gz").exists()


def _tiny():
    import yaml

    return yaml.safe_load((ROOT / "config" / "test_tiny.yaml").read_text())


def test_cuda_device_requests_a_gpu_for_the_jobs_that_run_on_it(tmp_path):
    """`--config device=cuda` on top of the default grid: the jobs that then run on CUDA (training, evaluation, the
    projector and the baselines, which follow the workflow's device) get resources gpu=1, the others none."""
    proc = snakemake(tmp_path, "-n", "--config", "device=cuda")
    jobs = proc.stdout.split("\n\n")
    gpu_rules = set()
    for block in jobs:
        head = block.strip().splitlines()
        rule = next((line.split()[-1].rstrip(":") for line in head if line.startswith(("rule ", "localrule "))), None)
        if rule and any("gpu=1" in line for line in head):
            gpu_rules.add(rule)
    assert gpu_rules == {"train", "evaluate", "project", "baseline"}
    counts = job_counts(proc.stdout)
    assert counts["train"] == 18  # the default config/config.yaml grid was loaded, device overridden
