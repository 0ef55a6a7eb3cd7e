"""Snakemake adapter: rule train -> ctsplat.training.train (grid-cell config from params, paths from input).

resume="auto": a job killed at its time limit or preempted continues from its newest checkpoint when the cell's
config, its inputs' content and the code are unchanged (Snakemake keeps checkpoints/, which is not a declared
output); a rerun after any of them changed starts over.
"""

from pathlib import Path

from _adapter import logged

from ctsplat.training import train

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    config = dict(sm.params.train)
    config["volume"] = sm.input.volume
    config["radiographs"] = str(Path(sm.input.views).parent)
    config["sfm_dir"] = str(Path(sm.input.sfm).parent) if "sfm" in sm.input.keys() else ""
    config["sfm_radiographs"] = str(Path(sm.input.sfm_views).parent) if "sfm_views" in sm.input.keys() else ""
    train(config, Path(sm.output.model).parent, resume="auto")
