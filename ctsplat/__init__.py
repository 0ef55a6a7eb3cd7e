"""ctsplat: CT scans to rectified radiative Gaussian-splatting models.

Modules (one job each): ``io`` (DICOM/NIfTI/TIFF readers and writers), ``volume`` (preprocessing),
``phantom`` (Shepp–Logan head phantom), ``geometry`` (cameras, orbits, view sets), ``projector``
(Beer–Lambert line integrals), ``baselines`` (FBP/SART), ``gaussians`` (model container, PLY),
``render`` (compositors, voxelizer), ``seeding``, ``train``, ``metrics``, ``sfm``, ``analysis``,
``plots``, ``cli``. Conventions (frames, units, cameras) are fixed in ``docs/conventions.md``.
"""

__version__ = "0.1.0"
