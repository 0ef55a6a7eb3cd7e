"""ctsplat: CT scans to rectified radiative Gaussian-splatting models.

Data flows one way — volume → view sets → poses → model → metrics → figures — through packages with one job each:
``formats`` (DICOM/NIfTI/TIFF sources, the volume file, view sets and radiograph folders, PLY, run logs),
``volume`` (ingestion and preprocessing), ``phantom`` (Shepp–Logan head phantom), ``geometry`` (cameras, orbits),
``projector`` (Beer–Lambert line integrals; the only place radiographs are rendered), ``recon`` and ``baselines``
(FBP, FDK, SART/SIRT, ASD-POCS, MBIR, parameters chosen on validation views), ``photos`` (COLMAP + 3DGS on photos),
``sfm`` (COLMAP poses of the C-arm view set), ``scene`` (view sets + poses for a run), ``splat`` (the Gaussian
model, compositors, voxelizer, C++ kernel), ``training``, ``evaluation``, ``config`` and ``grid`` (workflow
settings), ``analysis`` (statistics and figures across runs) and ``cli``. Conventions (frames, units, cameras) are
fixed in ``docs/conventions.md``.
"""

__version__ = "0.1.0"
