"""Snakemake adapter: rule project -> ctsplat.projector.render_radiographs."""

from pathlib import Path

from _adapter import logged

from ctsplat.projector import render_radiographs

with logged(snakemake):  # noqa: F821
    out_dir = Path(snakemake.output.views).parent  # noqa: F821
    render_radiographs(snakemake.input.volume, out_dir, snakemake.params.radiographs, seed=snakemake.params.seed)  # noqa: F821
