"""The ablation grid through a real single-node Slurm cluster (slurmctld + slurmd + munge on localhost).

The session fixture starts the cluster with ``start_cluster.sh`` (installing Slurm 22.05 / munge from the
distribution's packages when missing) and stops exactly the daemons it started afterwards. The test runs the
repository's workflow on the tiny grid ``config/test_tiny.yaml`` (4 training runs) in a temporary directory with
``snakemake --profile slurm`` (a user profile, installed under ``$XDG_CONFIG_HOME/snakemake/slurm/`` as the
README says), the profile being ``profiles/slurm`` (the users' cluster template, GPU request for training
included) overlaid with ``tests/slurm/profile/config.yaml`` (``slurm-status-command:
squeue``: there is no accounting database). Besides the grid (target ``results/summary.csv``) it asks for one
deliberately failing job, and checks:

* every job Snakemake ran remotely went through ``sbatch``: its Slurm job id is in the Snakemake log, Slurm
  itself (``scontrol show job``) knows the job under the run's name, with the rule in the comment, recorded it
  COMPLETED (the failing one FAILED) with a (fake) GPU exactly for the rules the profile gives one, and the
  job's Slurm log exists;
* every output of every other job exists, and ``summary.csv`` has exactly one row per grid cell (the cells
  computed here from the config's axes, not by the workflow's code);
* the failing job is reported as failed (Snakemake exits non-zero, names the rule and its Slurm job id, the
  job's own stderr is in its Slurm log) while the other results are complete (``--keep-going``).

Skipped (with the reason) when not root, not Linux, or neither Slurm nor apt-get is available; outside CI
(``CI`` unset) also when the packages cannot be installed or a Slurm set-up that is not ours is in the way
(in CI those fail the test).
"""

from __future__ import annotations

import itertools
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from slurm_helpers import (
    OVERLAY_PROFILE,
    START,
    STOP,
    cluster_alive,
    merge_profile,
    node_resources,
    parse_snakemake_log,
    skip_reason,
    slurm_jobs,
    state_dir,
)
from snakemake.utils import update_config

ROOT = Path(__file__).resolve().parents[2]
SNAKEMAKE_TIMEOUT_S = 900

pytestmark = [pytest.mark.slurm, pytest.mark.workflow, pytest.mark.slow]


@pytest.fixture(scope="session")
def slurm_cluster():
    """A running single-node cluster; started (and afterwards stopped) here unless one was already up."""
    reason = skip_reason()
    if reason:
        pytest.skip(f"single-node Slurm test skipped: {reason}")
    directory = state_dir()
    already_up = cluster_alive(directory)
    env = {**os.environ, "CTSPLAT_SLURM_DIR": str(directory)}
    proc = subprocess.run(
        ["bash", str(START)], env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=900
    )
    if proc.returncode in (3, 4) and os.environ.get("CI", "").lower() not in ("1", "true", "yes"):
        # Outside CI: packages not installable (no network) or a real Slurm set-up on this machine.
        pytest.skip(f"single-node Slurm test skipped: {proc.stderr.strip().splitlines()[-1]}")
    if proc.returncode != 0:
        pytest.fail(f"start_cluster.sh failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}", pytrace=False)
    try:
        yield directory
    finally:
        if not already_up:
            subprocess.run(["bash", str(STOP)], env=env, stdin=subprocess.DEVNULL, capture_output=True,
                           text=True, timeout=120)


def _write_profile(profile_dir: Path) -> dict:
    """profiles/slurm (the template) under tests/slurm/profile (the overlay), fitted to the node."""
    template = yaml.safe_load((ROOT / "profiles" / "slurm" / "config.yaml").read_text())
    overlay = yaml.safe_load(OVERLAY_PROFILE.read_text())
    cpus, mem_mb = node_resources()
    profile = merge_profile(template, overlay, cpus=cpus, mem_mb=mem_mb)
    profile_dir.mkdir(parents=True)
    (profile_dir / "config.yaml").write_text(yaml.safe_dump(profile, sort_keys=False))
    return profile


# --- the workflow under test ------------------------------------------------------------------------------
# The repository's workflow, run in a temporary directory: a two-line Snakefile there includes the repository's
# Snakefile and adds one rule that fails on purpose (nothing depends on it, so with --keep-going everything else
# completes). config/ and the workflow profile profiles/default are copied beside it so that the run sees what a
# user's run from the repository root sees; results/ is written there, never into the repository.
CONFIG = "config/test_tiny.yaml"
AXES = ("init", "compositor", "mip", "poses", "views", "seed")  # run folder order (docs: result layout)
TARGETS = ["results/summary.csv", "deliberate_failure"]

WRAPPER = """\
# Test wrapper (tests/slurm/test_slurm.py): the repository's workflow plus one job that fails on purpose.
include: {snakefile!r}


rule deliberate_failure:
    output:
        "deliberate_failure.txt",
    shell:
        "echo 'failing on purpose' >&2; exit 3"
"""


def _load_yaml(path: Path) -> dict:
    return yaml.safe_load(path.read_text()) or {}


def _expected_cells(config: dict) -> list[dict]:
    """Grid cells from the config, computed here: volumes x product of the axes, minus `exclude` entries."""

    def norm(axis: str, value: object) -> str:
        if axis == "mip" and isinstance(value, bool):  # YAML 1.1 reads a bare on/off as a boolean
            return "on" if value else "off"
        return str(value)

    grid = config["grid"]
    axes = {a: [norm(a, v) for v in grid["axes"][a]] for a in AXES}
    cells = [
        {"volume": volume, **dict(zip(AXES, values, strict=True))}
        for volume in config["volumes"]
        for values in itertools.product(*axes.values())
    ]

    def excluded(cell: dict) -> bool:
        for entry in grid.get("exclude") or []:
            if all(cell[k] in [norm(k, v) for v in (vals if isinstance(vals, list) else [vals])]
                   for k, vals in entry.items()):
                return True
        return False

    return [c for c in cells if not excluded(c)]


def _prepare_workdir(work: Path) -> list[dict]:
    """Set up the run directory; return the expected grid cells."""
    work.mkdir(parents=True)
    shutil.copytree(ROOT / "config", work / "config")
    if (ROOT / "profiles" / "default").is_dir():
        shutil.copytree(ROOT / "profiles" / "default", work / "profiles" / "default")
    (work / "Snakefile").write_text(WRAPPER.format(snakefile=str(ROOT / "Snakefile")))
    # What Snakemake does with `configfile: config/config.yaml` in the Snakefile plus --configfile.
    config = _load_yaml(work / "config" / "config.yaml")
    update_config(config, _load_yaml(work / CONFIG))
    return _expected_cells(config)


def _run_dir(cell: dict) -> str:
    return f"results/{cell['volume']}/runs/" + "/".join(f"{a}~{cell[a]}" for a in AXES)


# --- the test --------------------------------------------------------------------------------------------
def test_ablation_grid_runs_through_sbatch(slurm_cluster: Path, tmp_path: Path) -> None:
    work = tmp_path / "work"
    cells = _prepare_workdir(work)
    assert len(cells) >= 4, f"the test grid {CONFIG} should have >= 4 training runs, has {len(cells)}"
    # Installed as the user profile `slurm` (README: ~/.config/snakemake/slurm/), so the command is the users'.
    xdg = tmp_path / "xdg"
    profile = _write_profile(xdg / "snakemake" / "slurm")
    gpu_rules = {rule for rule, res in profile["set-resources"].items() if res.get("gpu")}

    # --keep-going on the command line: profiles/default (the workflow profile) sets it false and, applied after
    # --profile, wins over the profile's keep-going: true.
    cmd = [sys.executable, "-m", "snakemake", *TARGETS, "--configfile", CONFIG, "--profile", "slurm", "--keep-going"]
    env = {**os.environ, "XDG_CONFIG_HOME": str(xdg)}
    with open(tmp_path / "snakemake.out", "w") as out:
        proc = subprocess.run(cmd, cwd=work, env=env, stdin=subprocess.DEVNULL, stdout=out,
                              stderr=subprocess.STDOUT, text=True, timeout=SNAKEMAKE_TIMEOUT_S)
    console = (tmp_path / "snakemake.out").read_text()
    tail = f"\n--- Snakemake console (tail) ---\n{console[-6000:]}"
    logs = sorted((work / ".snakemake" / "log").glob("*.snakemake.log"))
    assert logs, f"no Snakemake log written{tail}"
    log = parse_snakemake_log(logs[-1].read_text())
    # Snakemake names the profile it found; nothing called `slurm` beside the workflow, so it is the user's.
    assert re.search(r"^Using profiles? slurm\b", console, re.M), f"profile `slurm` not used{tail}"
    assert not (work / "slurm").exists()

    # The failing job makes the whole run fail (exit 1), after everything else was done.
    assert proc.returncode == 1, f"snakemake exit {proc.returncode}, expected 1 (one failed job){tail}"

    # Every job Snakemake ran remotely was submitted with sbatch (its Slurm job id is in the log).
    remote = log.remote_jobs()
    assert remote, f"no jobs parsed from the log{tail}"
    assert set(log.submitted) == set(remote), f"jobs without a Slurm job id: {set(remote) - set(log.submitted)}{tail}"
    assert len(set(log.submitted.values())) == len(log.submitted), "two Snakemake jobs share one Slurm job id"
    train_jobs = [j for j, rule in remote.items() if rule == "train"]
    assert len(train_jobs) == len(cells), f"{len(train_jobs)} training jobs for {len(cells)} grid cells{tail}"
    failing = [j for j, rule in remote.items() if rule == "deliberate_failure"]
    assert len(failing) == 1, f"deliberate_failure jobs: {failing}{tail}"
    (fail_job,) = failing

    # Slurm's own record: each of those ids is a job of this run (one job name), with the rule in its comment,
    # finished COMPLETED (the failing one FAILED), GPU rules of the cluster profile got their (fake) GPU.
    slurm = slurm_jobs(list(log.submitted.values()))
    for job, slurm_id in log.submitted.items():
        rule = remote[job]
        assert slurm_id in slurm, f"Slurm does not know job {slurm_id} (Snakemake job {job}, rule {rule})"
        record = slurm[slurm_id]
        assert record["Comment"].startswith(f"rule_{rule}"), f"Slurm job {slurm_id} ({rule}): {record}"
        expected_state = "FAILED" if job == fail_job else "COMPLETED"
        assert record["JobState"] == expected_state, f"Slurm job {slurm_id} ({rule}): {record}"
        assert ("gpu" in record["TresPerJob"]) == (rule in gpu_rules), f"Slurm job {slurm_id} ({rule}): {record}"
        assert log.slurm_logs[job].is_file(), f"missing Slurm log {log.slurm_logs[job]}"
    assert len({r["JobName"] for r in slurm.values()}) == 1, "jobs of one run must share the run's job name"

    # The failure is reported: rule, Slurm job id, and the job's own stderr in its Slurm log; no output.
    assert log.failed == {fail_job: ("deliberate_failure", log.submitted[fail_job])}, f"failed: {log.failed}{tail}"
    assert "failing on purpose" in log.slurm_logs[fail_job].read_text()
    assert not (work / "deliberate_failure.txt").exists()

    # The other results survived: every other job finished and its outputs exist; one summary row per cell.
    unfinished = set(remote) - {fail_job} - set(log.finished)
    assert not unfinished, f"unfinished jobs: {sorted(remote[j] for j in unfinished)}{tail}"
    for job in set(remote) - {fail_job}:
        assert log.outputs[job], f"no outputs parsed for job {job} ({remote[job]})"
        for path in log.outputs[job]:
            assert (work / path).exists(), f"missing output of {remote[job]}: {path}"
    for cell in cells:
        run_dir = work / _run_dir(cell)
        for name in ("train_log.csv", "metrics.json", "model.pt"):
            assert (run_dir / name).is_file(), f"missing {name} in {run_dir}"
    summary = pd.read_csv(work / "results" / "summary.csv", dtype=str)
    columns = ["volume", *AXES]
    assert len(summary) == len(cells), f"summary.csv has {len(summary)} rows for {len(cells)} runs"
    got = sorted(map(tuple, summary[columns].itertuples(index=False)))
    assert got == sorted(tuple(c[k] for k in columns) for c in cells)
