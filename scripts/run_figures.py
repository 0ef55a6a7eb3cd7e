"""Snakemake adapter: rule run_figures -> ctsplat.analysis.plots.run_figures."""

from pathlib import Path

from _adapter import logged

from ctsplat.analysis import RUN_FIGURES
from ctsplat.analysis.plots import run_figures

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    run_figures(Path(sm.input.log).parent, {name: sm.output[name] for name in RUN_FIGURES}, sm.params.analysis)
