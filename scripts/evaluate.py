"""Snakemake adapter: rule evaluate -> ctsplat.evaluation.evaluate (metrics.json and figures of a run folder)."""

from pathlib import Path

from _adapter import logged

from ctsplat.evaluation import evaluate
from ctsplat.utils import run_lock

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    run_dir = Path(sm.output.metrics).parent
    with run_lock(run_dir):
        evaluate(run_dir, device=sm.params.device, milestones=sm.params.milestones, settings=sm.params.settings)
