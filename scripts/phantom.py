"""Snakemake adapter: rule phantom -> ctsplat.phantom.write_phantom_dicom."""

from _adapter import logged

from ctsplat.phantom import write_phantom_dicom

with logged(snakemake):  # noqa: F821
    write_phantom_dicom(snakemake.output[0], **snakemake.params.phantom)  # noqa: F821
