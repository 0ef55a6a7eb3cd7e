"""Helpers for the Slurm test: skip reasons, the cluster scripts, the test profile, Snakemake log parsing.

Pure functions (log parsing, profile merging) are unit-tested in ``test_slurm_helpers.py`` without a cluster.
"""

from __future__ import annotations

import copy
import os
import platform
import re
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
START = HERE / "start_cluster.sh"
STOP = HERE / "stop_cluster.sh"
OVERLAY_PROFILE = HERE / "profile" / "config.yaml"
PARTITION = "debug"  # the one partition start_cluster.sh creates
SLURM_COMMANDS = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "sinfo", "scontrol", "srun")


def state_dir() -> Path:
    """Where start_cluster.sh keeps the cluster's state, logs and PIDs (same default as the script)."""
    return Path(os.environ.get("CTSPLAT_SLURM_DIR", "/tmp/ctsplat-slurm"))


def skip_reason() -> str | None:
    """Why the single-node Slurm test cannot run here, or None when it can.

    It needs Linux, root (packages, /etc/slurm/slurm.conf, daemons) and either the Slurm and munge commands
    or apt-get to install them. ``CTSPLAT_SKIP_SLURM=1`` opts out explicitly.
    """
    if os.environ.get("CTSPLAT_SKIP_SLURM", "") not in ("", "0"):
        return "CTSPLAT_SKIP_SLURM is set"
    if platform.system() != "Linux":
        return f"needs Linux to run slurmctld/slurmd (this is {platform.system()})"
    if os.geteuid() != 0:
        return "needs root: it installs slurm/munge packages, writes /etc/slurm/slurm.conf and starts daemons"
    search = os.environ.get("PATH", "") + ":/usr/sbin:/sbin"
    missing = [c for c in SLURM_COMMANDS if shutil.which(c, path=search) is None]
    if missing and shutil.which("apt-get") is None:
        return f"Slurm commands missing ({', '.join(missing)}) and no apt-get to install slurmctld/slurmd/munge"
    return None


def cluster_alive(directory: Path) -> bool:
    """True when ``directory/pids`` lists daemons that are all still running (a cluster started earlier)."""
    pids = directory / "pids"
    if not pids.is_file():
        return False
    lines = [ln.split() for ln in pids.read_text().splitlines() if ln.strip()]
    if not lines:
        return False
    for name, pid in lines:
        try:
            if Path(f"/proc/{pid}/comm").read_text().strip() != name:
                return False
            if re.search(r"^State:\s+Z", Path(f"/proc/{pid}/status").read_text(), re.M):
                return False  # killed, not yet reaped
        except OSError:
            return False
    return True


def node_resources() -> tuple[int, int]:
    """(CPUs, RealMemory in MB) of the cluster's node, from ``scontrol show node --oneliner``."""
    out = subprocess.run(
        ["scontrol", "show", "node", "--oneliner"], capture_output=True, text=True, check=True, timeout=30
    ).stdout
    cpus = int(re.search(r"\bCPUTot=(\d+)", out).group(1))
    mem = int(re.search(r"\bRealMemory=(\d+)", out).group(1))
    return cpus, mem


# --- the test profile ---------------------------------------------------------------------------------------
def _is_placeholder(value: object) -> bool:
    return isinstance(value, str) and value.startswith("<") and value.endswith(">")


def _fit_resources(res: dict, *, partition: str, mem_mb: int) -> dict:
    """One rule's (or the default) resources made submittable to the test node."""
    out = {}
    for key, value in res.items():
        if key == "slurm_account":
            continue  # no slurmdbd: the plugin cannot validate an account (sacctmgr/sshare fail)
        if key == "gpu_model":
            continue  # the fake gres has no type
        if key == "slurm_partition":
            value = partition
        elif key == "mem_mb" and isinstance(value, int):
            value = min(value, mem_mb)
        elif _is_placeholder(value):
            continue
        out[key] = value
    return out


def merge_profile(template: dict, overlay: dict, *, cpus: int, mem_mb: int, partition: str = PARTITION) -> dict:
    """The test profile: the cluster template's per-rule settings, fitted to the node, under the overlay.

    Parameters
    ----------
    template : dict
        ``profiles/slurm/config.yaml`` (placeholders like ``"<PARTITION>"`` allowed).
    overlay : dict
        ``tests/slurm/profile/config.yaml``; its top-level keys win, except that ``default-resources`` and
        ``set-resources`` are merged per key (overlay over template).
    cpus, mem_mb : int
        What one node has: ``set-threads`` values are capped at ``max(1, cpus // 2)`` (two jobs side by side)
        and every ``mem_mb`` at ``mem_mb`` (sbatch rejects a request no node can satisfy).
    partition : str
        Replaces every ``slurm_partition``.

    Returns
    -------
    dict
        A profile config; ``slurm_account`` and ``gpu_model`` removed (no accounting, untyped fake gpus), GPU
        requests (``gpu: 1``) kept.
    """
    merged = {k: copy.deepcopy(v) for k, v in template.items()}
    for key, value in overlay.items():
        if key in ("default-resources", "set-resources") and isinstance(value, dict):
            base = merged.get(key) or {}
            if key == "default-resources":
                merged[key] = {**base, **value}
            else:
                merged[key] = {r: {**base.get(r, {}), **value.get(r, {})} for r in {*base, *value}}
        else:
            merged[key] = copy.deepcopy(value)
    merged["default-resources"] = _fit_resources(merged.get("default-resources") or {}, partition=partition,
                                                 mem_mb=mem_mb)
    merged["set-resources"] = {
        rule: _fit_resources(res or {}, partition=partition, mem_mb=mem_mb)
        for rule, res in (merged.get("set-resources") or {}).items()
    }
    if merged.get("set-threads"):
        # At most half the node per job, so two jobs (and their Python start-up) overlap on a 2-core runner.
        cap = max(1, cpus // 2)
        merged["set-threads"] = {rule: max(1, min(int(n), cap)) for rule, n in merged["set-threads"].items()}
    return merged


# --- the Snakemake log ---------------------------------------------------------------------------------------
_RULE_BLOCK = re.compile(r"^(local)?rule (\w+):\n((?:[ \t]+.*\n?)*)", re.M)
_ERROR_BLOCK = re.compile(r"^Error in rule (\w+):\n((?:[ \t]+.*\n?)*)", re.M)
_SUBMITTED = re.compile(r"^Job (\d+) has been submitted with SLURM jobid (\d+) \(log: (.+?)\)\.\s*$", re.M)
_FINISHED = re.compile(r"^Finished jobid: (\d+) \(Rule: (\w+)\)", re.M)
_FIELD = re.compile(r"^[ \t]+(\w+): (.*)$", re.M)
# `show-failed-logs` pastes a failed job's Slurm log (the job's own Snakemake output, with its *local* view of
# the same job ids) between two 80-character rules of "="; it is not part of the main run's record.
_EMBEDDED_LOG = re.compile(r"^Logfile [^\n]*:\n={40,}\n.*?^={40,}$", re.M | re.S)


@dataclass
class SnakemakeLog:
    """What one Snakemake run did, read from its log.

    ``jobs``: Snakemake job id -> (rule, local); ``submitted``: job id -> Slurm job id;
    ``slurm_logs``: job id -> Slurm log path; ``finished``: job id -> rule;
    ``failed``: job id -> (rule, external Slurm job id or None); ``outputs``: job id -> output paths.
    """

    jobs: dict[int, tuple[str, bool]] = field(default_factory=dict)
    submitted: dict[int, str] = field(default_factory=dict)
    slurm_logs: dict[int, Path] = field(default_factory=dict)
    finished: dict[int, str] = field(default_factory=dict)
    failed: dict[int, tuple[str, str | None]] = field(default_factory=dict)
    outputs: dict[int, list[str]] = field(default_factory=dict)

    def remote_jobs(self) -> dict[int, str]:
        """Jobs Snakemake ran through the executor (not ``localrule``): job id -> rule."""
        return {j: rule for j, (rule, local) in self.jobs.items() if not local}


def parse_snakemake_log(text: str) -> SnakemakeLog:
    """Parse a Snakemake 9 log (``.snakemake/log/*.snakemake.log``) written with the Slurm executor plugin."""
    log = SnakemakeLog()
    text = _EMBEDDED_LOG.sub("", text)
    for match in _RULE_BLOCK.finditer(text):
        fields = dict(_FIELD.findall(match.group(3)))
        if "jobid" in fields:
            job = int(fields["jobid"])
            log.jobs[job] = (match.group(2), match.group(1) is not None)
            log.outputs[job] = [p.strip() for p in fields.get("output", "").split(",") if p.strip()]
    for match in _SUBMITTED.finditer(text):
        job = int(match.group(1))
        log.submitted[job] = match.group(2)
        log.slurm_logs[job] = Path(match.group(3))
    for match in _FINISHED.finditer(text):
        log.finished[int(match.group(1))] = match.group(2)
    for match in _ERROR_BLOCK.finditer(text):
        fields = dict(_FIELD.findall(match.group(2)))
        if "jobid" in fields:
            log.failed[int(fields["jobid"])] = (match.group(1), fields.get("external_jobid"))
    return log


def slurm_jobs(job_ids: list[str]) -> dict[str, dict[str, str]]:
    """Slurm's own record of jobs (finished ones too, while younger than MinJobAge), from ``scontrol``.

    Returns Slurm job id -> fields ``JobState``, ``JobName``, ``Comment``, ``TresPerJob`` (``""`` when none),
    ``NumCPUs``. The plugin names all jobs of one run by its run id and writes ``rule_<rule>[_wildcards_...]``
    into the comment; ``--gpus=1`` shows as ``TresPerJob=gres:gpu:1``.
    """
    wanted = set(job_ids)
    out = subprocess.run(
        ["scontrol", "show", "job", "--oneliner"], capture_output=True, text=True, check=True, timeout=30
    ).stdout
    jobs = {}
    for line in out.splitlines():
        fields = dict(re.findall(r"(?:^|\s)(JobId|JobState|JobName|Comment|TresPerJob|NumCPUs)=(\S*)", line))
        if fields.get("JobId") in wanted:
            fields.setdefault("TresPerJob", "")
            jobs[fields.pop("JobId")] = fields
    return jobs
