"""The Slurm test's own helpers (no cluster needed): Snakemake log parsing and the test profile."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
import yaml
from slurm_helpers import OVERLAY_PROFILE, START, STOP, merge_profile, parse_snakemake_log

ROOT = Path(__file__).resolve().parents[2]

# An excerpt of a real Snakemake 9.27 / plugin 2.8.0 log from this cluster (paths shortened), including the
# failed job's Slurm log that `show-failed-logs` pastes in (with the job's *local* view of job 0).
LOG = """\
Building DAG of jobs...
SLURM run ID: 4b7219cc-8092-4614-9246-2ce41814b0de
Job stats:
job                   count
------------------  -------
train                       2
deliberate_failure          1
gather                      1
all                         1
total                       5

[Sat Nov 21 06:17:21 2026]
rule train:
    output: results/phantom/runs/init~fbp/mip~on/seed~0/metrics.json
    jobid: 3
    reason: Missing output files: results/phantom/runs/init~fbp/mip~on/seed~0/metrics.json
    wildcards: init=fbp, mip=on, seed=0
    resources: tmpdir=<TBD>, mem_mb=1000, slurm_partition=debug, runtime=15, gpu=1
Shell command: None
[Sat Nov 21 06:17:21 2026]
rule train:
    output: results/phantom/runs/init~fbp/mip~off/seed~0/metrics.json
    jobid: 4
    wildcards: init=fbp, mip=off, seed=0
Job 3 has been submitted with SLURM jobid 9 (log: /w/.snakemake/slurm_logs/rule_train/fbp_on_0/9.log).
Job 4 has been submitted with SLURM jobid 8 (log: /w/.snakemake/slurm_logs/rule_train/fbp_off_0/8.log).
[Sat Nov 21 06:17:57 2026]
rule deliberate_failure:
    output: deliberate_failure.txt
    jobid: 0
    reason: Missing output files: deliberate_failure.txt
Shell command: echo 'failing on purpose' >&2; exit 3
Job 0 has been submitted with SLURM jobid 11 (log: /w/.snakemake/slurm_logs/rule_deliberate_failure/11.log).
[Sat Nov 21 06:18:11 2026]
Finished jobid: 3 (Rule: train)
1 of 5 steps (20%) done
Finished jobid: 4 (Rule: train)
2 of 5 steps (40%) done
rule gather:
    input: a, b
    output: results/summary.csv
    jobid: 2
Job 2 has been submitted with SLURM jobid 12 (log: /w/.snakemake/slurm_logs/rule_gather/12.log).
[Sat Nov 21 06:18:40 2026]
Error in rule deliberate_failure:
    message: SLURM-job '11' failed, SLURM status is: 'FAILED'. Detailed failure reason unavailable.
    jobid: 0
    output: deliberate_failure.txt
    log: /w/.snakemake/slurm_logs/rule_deliberate_failure/11.log (check log file(s) for error details)
    shell:
        echo 'failing on purpose' >&2; exit 3
        (command exited with non-zero exit code)
    external_jobid: 11
Logfile /w/.snakemake/slurm_logs/rule_deliberate_failure/11.log:
================================================================================
Building DAG of jobs...
localrule deliberate_failure:
    output: deliberate_failure.txt
    jobid: 0
failing on purpose
Error in rule deliberate_failure:
    message: None
    jobid: 0
================================================================================
[Sat Nov 21 06:18:51 2026]
Finished jobid: 2 (Rule: gather)
[Sat Nov 21 06:18:51 2026]
localrule all:
    input: results/summary.csv
    jobid: 1
Finished jobid: 1 (Rule: all)
Exiting because a job execution failed. Look above for error messages
"""


def test_parse_snakemake_log_jobs_submissions_failures() -> None:
    log = parse_snakemake_log(LOG)
    assert log.jobs == {
        3: ("train", False), 4: ("train", False), 0: ("deliberate_failure", False),
        2: ("gather", False), 1: ("all", True),
    }
    assert log.remote_jobs() == {3: "train", 4: "train", 0: "deliberate_failure", 2: "gather"}
    assert log.submitted == {3: "9", 4: "8", 0: "11", 2: "12"}
    assert log.slurm_logs[0] == Path("/w/.snakemake/slurm_logs/rule_deliberate_failure/11.log")
    assert log.finished == {3: "train", 4: "train", 2: "gather", 1: "all"}
    # The pasted job log (local view, message None, no external id) must not replace the main record.
    assert log.failed == {0: ("deliberate_failure", "11")}


def test_parse_snakemake_log_without_slurm_has_no_submissions() -> None:
    local = LOG.replace("has been submitted with SLURM jobid", "was started as")
    assert parse_snakemake_log(local).submitted == {}


TEMPLATE = {
    "executor": "slurm",
    "jobs": 100,
    "retries": 1,
    "latency-wait": 60,
    "default-resources": {"slurm_partition": "<PARTITION>", "slurm_account": "<ACCOUNT>", "mem_mb": 4000,
                          "runtime": 60},
    "set-threads": {"train": 4, "project": 1},
    "set-resources": {
        "train": {"slurm_partition": "<GPU_PARTITION>", "gpu": 1, "gpu_model": "a100", "mem_mb": 32000,
                  "runtime": 1440},
        "gather": {"mem_mb": 500, "runtime": 15},
    },
}


def test_merge_profile_fits_template_to_node_and_overlay_wins() -> None:
    overlay = {"jobs": 4, "retries": 0, "slurm-status-command": "squeue",
               "default-resources": {"slurm_partition": "debug", "mem_mb": 1000, "runtime": 15}}
    got = merge_profile(TEMPLATE, overlay, cpus=4, mem_mb=8000)
    assert got["executor"] == "slurm" and got["latency-wait"] == 60  # template keys kept
    assert got["jobs"] == 4 and got["retries"] == 0 and got["slurm-status-command"] == "squeue"
    assert got["default-resources"] == {"slurm_partition": "debug", "mem_mb": 1000, "runtime": 15}
    # GPU request kept, untyped; partition replaced; memory capped at the node; account dropped.
    assert got["set-resources"]["train"] == {"slurm_partition": "debug", "gpu": 1, "mem_mb": 8000, "runtime": 1440}
    assert got["set-resources"]["gather"] == {"mem_mb": 500, "runtime": 15}
    assert got["set-threads"] == {"train": 2, "project": 1}  # half the node at most
    assert TEMPLATE["set-resources"]["train"]["mem_mb"] == 32000  # template not modified
    assert merge_profile(TEMPLATE, overlay, cpus=1, mem_mb=8000)["set-threads"] == {"train": 1, "project": 1}


def test_repository_profiles_merge_into_valid_test_profile() -> None:
    """The real template and overlay: no placeholder or account survives, status via squeue."""
    template = yaml.safe_load((ROOT / "profiles" / "slurm" / "config.yaml").read_text())
    overlay = yaml.safe_load(OVERLAY_PROFILE.read_text())
    got = merge_profile(template, overlay, cpus=2, mem_mb=4000)
    text = yaml.safe_dump(got)
    assert "<" not in text and "slurm_account" not in text
    assert got["executor"] == "slurm"
    assert got["slurm-status-command"] == "squeue"
    assert got["retries"] == 0 and got["keep-going"] is True
    assert all(r.get("mem_mb", 0) <= 4000 for r in got["set-resources"].values())
    assert {k for k in overlay if k.startswith("slurm-")} <= set(got)


def test_plugin_knows_the_overlay_settings() -> None:
    """Every `slurm-*` key of the overlay is a setting of the installed executor plugin (names change between
    versions; Snakemake would reject an unknown one only at run time)."""
    import dataclasses

    plugin = pytest.importorskip("snakemake_executor_plugin_slurm")
    fields = {f.name.replace("_", "-") for f in dataclasses.fields(plugin.ExecutorSettings)}
    overlay = yaml.safe_load(OVERLAY_PROFILE.read_text())
    used = {k.removeprefix("slurm-") for k in overlay if k.startswith("slurm-")}
    assert used and used <= fields, f"unknown plugin settings: {used - fields}"


@pytest.mark.skipif(os.name != "posix", reason="bash scripts")
@pytest.mark.parametrize("script", [START, STOP])
def test_cluster_scripts_are_valid_bash(script: Path) -> None:
    assert os.access(script, os.X_OK), f"{script} is not executable"
    subprocess.run(["bash", "-n", str(script)], check=True)


def test_stop_without_cluster_is_a_no_op(tmp_path: Path) -> None:
    proc = subprocess.run(["bash", str(STOP)], env={**os.environ, "CTSPLAT_SLURM_DIR": str(tmp_path)},
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and "nothing to stop" in proc.stderr
