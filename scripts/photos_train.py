"""Snakemake adapter: rule photos_train -> ctsplat.photos.train.train_photos, then evaluate_photos."""

from pathlib import Path

from _adapter import logged

from ctsplat.photos.evaluate import evaluate_photos
from ctsplat.photos.train import train_photos

with logged(snakemake):  # noqa: F821
    settings = snakemake.params.photos  # noqa: F821
    run_dir = Path(snakemake.output.metrics).parent  # noqa: F821
    train = {**settings["train"], "num_threads": int(snakemake.threads)}  # noqa: F821
    train_photos(Path(snakemake.input.summary).parent, run_dir, train)  # noqa: F821
    evaluate_photos(run_dir, settings["evaluate"])
