"""Snakemake adapter: rule ingest -> ctsplat.volume.ingest."""

from _adapter import logged

from ctsplat.volume import ingest

with logged(snakemake):  # noqa: F821
    ingest(snakemake.input.source, snakemake.output.volume, **snakemake.params.ingest)  # noqa: F821
