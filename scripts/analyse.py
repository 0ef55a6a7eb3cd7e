"""Snakemake adapter: rule analyse -> ctsplat.analysis.plots.analyse (results/figures/)."""

from _adapter import logged

from ctsplat.analysis import ANALYSIS_OUTPUTS
from ctsplat.analysis.plots import analyse

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    analyse(sm.input.summary, {name: sm.output[name] for name in ANALYSIS_OUTPUTS},
            baselines_csvs=list(sm.input.baselines), analysis=sm.params.analysis)
