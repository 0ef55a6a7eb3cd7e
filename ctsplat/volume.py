"""Preprocessed CT volumes: the ``Volume`` container, NIfTI + JSON I/O, and preprocessing steps.

A volume is a float32 array indexed ``[i, j, k]`` with a 4x4 affine mapping voxel indices to the
world frame (RAS+, mm); see ``docs/conventions.md``. ``meta`` is the content of ``volume.json``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np

from ctsplat.utils import CtsplatError, atomic_path, write_json_atomic

__all__ = ["Volume", "load_volume", "save_volume", "json_path_for"]


@dataclass
class Volume:
    """A CT volume in the world frame.

    Attributes
    ----------
    data : ndarray, shape (I, J, K), float32
        Voxel values: HU, μ in 1/mm, or normalised [0, 1] (see ``meta["intensity"]``).
    affine : ndarray, shape (4, 4)
        Voxel index -> world (RAS+, mm).
    meta : dict
        Provenance and intensity mapping; ``meta["intensity"]["mu_scale_per_mm"]`` maps values to 1/mm.
    """

    data: np.ndarray
    affine: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def spacing_mm(self) -> np.ndarray:
        """Voxel edge lengths (mm), shape (3,)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.data.shape)  # type: ignore[return-value]

    @property
    def mu_scale_per_mm(self) -> float:
        """Factor mapping ``data`` to attenuation in 1/mm (1.0 when ``data`` already is μ)."""
        return float(self.meta.get("intensity", {}).get("mu_scale_per_mm", 1.0))

    @property
    def volume_id(self) -> str:
        return str(self.meta.get("volume_id", "unknown"))

    def center_mm(self) -> np.ndarray:
        """World position (mm) of the volume's geometric centre, shape (3,)."""
        idx = (np.asarray(self.shape, float) - 1.0) / 2.0
        return self.affine[:3, :3] @ idx + self.affine[:3, 3]

    def extent_mm(self) -> np.ndarray:
        """Physical size (mm) covered by the voxels (shape * spacing), shape (3,)."""
        return np.asarray(self.shape, float) * self.spacing_mm


def json_path_for(nii_path: str | Path) -> Path:
    """``.../volume.nii.gz`` -> ``.../volume.json``."""
    p = Path(nii_path)
    name = p.name
    for ext in (".nii.gz", ".nii"):
        if name.endswith(ext):
            return p.with_name(name[: -len(ext)] + ".json")
    return p.with_suffix(".json")


def save_volume(volume: Volume, path: str | Path) -> None:
    """Write ``volume`` as NIfTI-1 (``.nii.gz``) plus its sibling JSON, both atomically."""
    data = np.asarray(volume.data, dtype=np.float32)
    img = nib.Nifti1Image(data, np.asarray(volume.affine, float))
    img.header.set_xyzt_units("mm")
    img.set_qform(volume.affine, code=1)
    img.set_sform(volume.affine, code=1)
    meta = dict(volume.meta)
    meta.update(
        shape=list(data.shape),
        spacing_mm=[float(s) for s in volume.spacing_mm],
        affine=np.asarray(volume.affine, float).tolist(),
    )
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))
    write_json_atomic(json_path_for(path), meta)


def load_volume(path: str | Path) -> Volume:
    """Read a NIfTI volume and its sibling JSON (if present) into a ``Volume``."""
    path = Path(path)
    if not path.exists():
        raise CtsplatError(f"volume file {path} does not exist; run the ingest step first")
    img = nib.load(str(path))
    data = np.asarray(img.get_fdata(dtype=np.float32), dtype=np.float32)
    meta: dict[str, Any] = {}
    jp = json_path_for(path)
    if jp.exists():
        meta = json.loads(jp.read_text())
    return Volume(data=data, affine=np.asarray(img.affine, float), meta=meta)
