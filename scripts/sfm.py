"""Snakemake adapter: rule sfm -> ctsplat.sfm.run_sfm."""

from pathlib import Path

from _adapter import logged

from ctsplat.sfm import run_sfm

with logged(snakemake):  # noqa: F821
    out_dir = Path(snakemake.output.summary).parent  # noqa: F821
    run_sfm(  # noqa: F821
        Path(snakemake.input.views).parent,  # noqa: F821
        out_dir,
        snakemake.params.sfm,  # noqa: F821
        seed=snakemake.params.seed,  # noqa: F821
        volume_path=snakemake.input.volume,  # noqa: F821
    )
