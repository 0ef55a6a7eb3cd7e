"""Snakemake adapter: rule analyse -> ctsplat.plots.analyse (results/figures/)."""

from _adapter import logged

from ctsplat.plots import ANALYSIS_OUTPUTS, analyse

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    analyse(sm.input.summary, {name: sm.output[name] for name in ANALYSIS_OUTPUTS},
            baselines_csvs=list(sm.input.baselines), analysis=sm.params.analysis)
