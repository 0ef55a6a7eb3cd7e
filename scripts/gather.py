"""Snakemake adapter: rule gather -> ctsplat.analysis.gather.gather (results/summary.csv)."""

from pathlib import Path

from _adapter import logged

from ctsplat.analysis.gather import gather

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    cfg = sm.params.analysis
    gather([Path(p).parent for p in sm.input.metrics], sm.output.summary, thresholds=cfg["milestones"],
           max_gap_iters=cfg["max_gap_iters"], per_iters=cfg["velocity_per_iters"])
