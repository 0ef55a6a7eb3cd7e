"""The shipped Snakemake profiles: valid YAML, the cluster template covers every rule, GPU for training."""

from __future__ import annotations

import re

import yaml
from smk_helpers import ROOT

RULES = {m.group(1) for p in (ROOT / "workflow" / "rules").glob("*.smk")
         for m in re.finditer(r"^(?:rule|checkpoint) (\w+):", p.read_text(), re.M)}


def test_rules_found():
    assert RULES == {"phantom", "ingest", "project", "baseline", "sfm", "sfm_figure", "train", "evaluate",
                     "run_figures", "overview_data", "overview_radiographs", "gather", "analyse", "photos_sfm",
                     "photos_train", "photos_evaluate"}


def test_slurm_template_profile():
    prof = yaml.safe_load((ROOT / "profiles" / "slurm" / "config.yaml").read_text())
    assert prof["executor"] == "slurm"
    assert {"slurm_partition", "slurm_account", "mem_mb", "runtime"} <= set(prof["default-resources"])
    assert set(prof["set-resources"]) == RULES  # per-rule resources for every rule
    for rule, res in prof["set-resources"].items():
        assert res["mem_mb"] > 0 and res["runtime"] > 0, rule
    assert prof["set-resources"]["train"]["gpu"] == 1
    assert set(prof["set-threads"]) <= RULES
    text = (ROOT / "profiles" / "slurm" / "config.yaml").read_text()
    assert "slurm-status-command: squeue" in text  # documented for clusters without accounting


def test_slurm_profile_gives_every_shipped_config_the_resources_it_asks_for():
    """The profile's set-resources / set-threads override a config's `resources`, so they must cover the largest
    request of every config in config/ (a smaller memory or time limit would kill those jobs on the cluster)."""
    prof = yaml.safe_load((ROOT / "profiles" / "slurm" / "config.yaml").read_text())
    short = []
    for path in sorted((ROOT / "config").glob("*.yaml")):
        for rule, res in (yaml.safe_load(path.read_text()).get("resources") or {}).items():
            given = {**prof["set-resources"][rule], "threads": prof["set-threads"].get(rule)}
            short += [f"{path.name}: {rule}.{key} {res[key]} > {given[key]}" for key in ("mem_mb", "runtime", "threads")
                      if key in res and given[key] is not None and given[key] < res[key]]
    assert not short, short


def test_default_workflow_profile():
    prof = yaml.safe_load((ROOT / "profiles" / "default" / "config.yaml").read_text())
    assert "params" in prof["rerun-triggers"] and "executor" not in prof
