"""Snakemake adapter: rule gather -> ctsplat.analysis.gather.gather (results/summary.csv)."""

from _adapter import logged

from ctsplat.analysis.gather import gather

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    cfg = sm.params.analysis
    gather(sm.params.runs, sm.output.summary, thresholds=cfg["milestones"], max_gap_iters=cfg["max_gap_iters"],
           per_iters=cfg["velocity_per_iters"], baselines_csvs=list(sm.input.baselines))
