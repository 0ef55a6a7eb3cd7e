"""Snakemake adapter: rules overview_data, overview_radiographs, sfm_figure -> ctsplat.analysis.overview."""

from pathlib import Path

from _adapter import logged

from ctsplat.analysis.overview import radiographs_figure, sfm_figure, volume_figure

with logged(snakemake):  # noqa: F821
    sm = snakemake  # noqa: F821
    if sm.rule == "overview_data":
        volume_figure(sm.input.volume, sm.output.figure, title=sm.wildcards.volume)
    elif sm.rule == "overview_radiographs":
        radiographs_figure(Path(sm.input.views).parent, sm.output.figure, split=sm.params.split,
                           max_images=sm.params.max_images)
    else:
        sfm_figure(Path(sm.input.summary).parent, sm.output.figure)
