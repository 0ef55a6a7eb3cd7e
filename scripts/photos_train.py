"""Snakemake adapter: rule photos_train -> ctsplat.photos.train.train_photos (the rule's threads as num_threads)."""

from pathlib import Path

from _adapter import logged

from ctsplat.photos.train import train_photos

with logged(snakemake):  # noqa: F821
    train = {**snakemake.params.train, "num_threads": int(snakemake.threads)}  # noqa: F821
    train_photos(Path(snakemake.input.summary).parent, Path(snakemake.output.model).parent, train)  # noqa: F821
