"""Snakemake adapter: rule run_figures -> ctsplat.plots.run_figures."""

from pathlib import Path

from _adapter import logged

from ctsplat.plots import RUN_FIGURES, run_figures

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    run_figures(Path(sm.input.log).parent, {name: sm.output[name] for name in RUN_FIGURES}, sm.params.analysis)
