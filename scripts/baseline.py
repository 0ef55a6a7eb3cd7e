"""Snakemake adapter: rule baseline -> ctsplat.baselines.run_baselines."""

from pathlib import Path

from _adapter import logged

from ctsplat.baselines import run_baselines

with logged(snakemake):  # noqa: F821
    radiographs_dir = Path(snakemake.input.views).parent  # noqa: F821
    out_dir = Path(snakemake.output.csv).parent  # noqa: F821
    run_baselines(snakemake.input.volume, radiographs_dir, out_dir, snakemake.params.baselines)  # noqa: F821
