"""Snakemake adapter: rule photos_evaluate -> ctsplat.photos.evaluate.evaluate_photos."""

from pathlib import Path

import torch
from _adapter import logged

from ctsplat.photos.evaluate import evaluate_photos

with logged(snakemake):  # noqa: F821
    torch.set_num_threads(int(snakemake.threads))  # noqa: F821
    evaluate_photos(Path(snakemake.output.metrics).parent, snakemake.params.evaluate)  # noqa: F821
