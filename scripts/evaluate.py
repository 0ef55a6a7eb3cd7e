"""Snakemake adapter: rule evaluate -> ctsplat.evaluation.evaluate (metrics.json and figures of a run folder)."""

from pathlib import Path

from _adapter import logged

from ctsplat.evaluation import evaluate

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    evaluate(Path(sm.output.metrics).parent, device=sm.params.device, milestones=sm.params.milestones)
