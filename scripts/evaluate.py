"""Snakemake adapter: rule evaluate -> ctsplat.evaluate.evaluate."""

from pathlib import Path

from _adapter import logged

from ctsplat.evaluate import evaluate

with logged(snakemake):  # noqa: F821
    evaluate(Path(snakemake.output.metrics).parent, **snakemake.params.evaluation)  # noqa: F821
