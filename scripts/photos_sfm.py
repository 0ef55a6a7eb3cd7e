"""Snakemake adapter: rule photos_sfm -> ctsplat.photos.sfm.run_photo_sfm (the rule's threads as num_threads)."""

from pathlib import Path

from _adapter import logged

from ctsplat.photos.sfm import run_photo_sfm

with logged(snakemake):  # noqa: F821
    sfm = {**snakemake.params.sfm, "num_threads": int(snakemake.threads)}  # noqa: F821
    run_photo_sfm(snakemake.input[0], Path(snakemake.output.summary).parent, sfm)  # noqa: F821
