"""Snakemake adapter: rule evaluate -> ctsplat.evaluate.evaluate (writes eval_{split}.json in the run folder)."""

from pathlib import Path

from _adapter import logged

from ctsplat.evaluate import evaluate

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    evaluate(Path(sm.output.metrics).parent, split=sm.wildcards.split, device=sm.params.evaluation["device"])
