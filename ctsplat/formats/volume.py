"""The volume file: a NIfTI-1 image (``volume.nii.gz``) plus its provenance JSON (``volume.json``).

A volume is a float32 array indexed ``[i, j, k]`` with a 4x4 affine mapping voxel indices to the
world frame (RAS+, mm; see ``docs/conventions.md``)::

    world(i, j, k) = affine[:3, :3] @ (i, j, k) + affine[:3, 3]

The affine is stored as both the qform and the sform of the NIfTI header (code 1, "scanner
anatomical"), with spatial units mm; NIfTI's world frame is RAS+, the same as ctsplat's, so no
axis flip happens here. The sibling JSON holds ``meta`` (provenance, intensity mapping with
``mu_scale_per_mm``, ``volume_id``) plus ``shape``, ``spacing_mm`` and ``affine`` as written.

``volume_id`` (:func:`compute_volume_id`) is the identity of a volume file's content: a hash of the
float32 voxels and the affine as stored. Radiographs, SfM poses and training runs record the
``volume_id`` they were made from, and readers compare it to detect a stale pairing.

References
----------
.. [1] R. W. Cox et al., "A (sort of) new image data format standard: NIfTI-1", NIfTI Data Format
   Working Group, 2004; header fields ``qform_code``, ``sform_code``, ``srow_x/y/z`` ("Method 3"),
   https://nifti.nimh.nih.gov/nifti-1/
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np

from ctsplat.utils import CtsplatError, atomic_path, is_finite_real, read_json_object, write_json_atomic

__all__ = ["Volume", "load_volume", "save_volume", "json_path_for", "check_sidecar_target", "compute_volume_id",
           "check_attenuation"]


#: Labels of the intensity kinds that :func:`ctsplat.volume.ingest` writes.
_UNITS = {
    "attenuation_normalised": "normalised attenuation (0-1)",
    "minmax_normalised": "min-max normalised source values (0-1)",
    "window": "windowed HU (0-1)",
    "attenuation_per_mm": "attenuation μ (1/mm)",
    "hu": "HU",
}


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
        """Grid shape ``(I, J, K)``."""
        return tuple(int(s) for s in self.data.shape)  # type: ignore[return-value]

    @property
    def mu_scale_per_mm(self) -> float:
        """Factor mapping ``data`` to attenuation in 1/mm (1.0 when ``data`` already is μ)."""
        return float(self.meta.get("intensity", {}).get("mu_scale_per_mm", 1.0))

    @property
    def unit(self) -> str:
        """What ``data`` holds, for axis and colour-bar labels (from ``meta["intensity"]["kind"]``)."""
        return _UNITS.get(self.meta.get("intensity", {}).get("kind"), "voxel value")

    @property
    def metric_range(self) -> float:
        """The data range that 3D PSNR/SSIM compare ``data`` in: μ of ``hu_max`` (1/mm) for a volume stored in 1/mm
        (intensity ``mu``), 1 for the normalised intensities (and a volume without metadata in [0, 1]), else the
        volume's own max - min."""
        intensity = self.meta.get("intensity", {})
        if intensity.get("kind") == "attenuation_per_mm":
            return float(intensity["mu_water_per_mm"]) * (1.0 + float(intensity["hu_max"]) / 1000.0)
        if "kind" in intensity:
            return 1.0
        lo, hi = float(np.min(self.data)), float(np.max(self.data))
        return 1.0 if 0.0 <= lo and hi <= 1.0 else (hi - lo) or 1.0

    @property
    def volume_id(self) -> str:
        """Content identity recorded in ``meta`` (see :func:`compute_volume_id`); ``"unknown"`` if absent."""
        return str(self.meta.get("volume_id", "unknown"))

    def center_mm(self) -> np.ndarray:
        """World position (mm) of the volume's geometric centre, shape (3,)."""
        idx = (np.asarray(self.shape, float) - 1.0) / 2.0
        return self.affine[:3, :3] @ idx + self.affine[:3, 3]

    def extent_mm(self) -> np.ndarray:
        """Physical size (mm) covered by the voxels (shape * spacing), shape (3,)."""
        return np.asarray(self.shape, float) * self.spacing_mm


def compute_volume_id(data: np.ndarray, affine: np.ndarray) -> str:
    """Short content hash of a volume file: the float32 voxels, the affine (rounded to 1 µm) and the shape.

    Parameters
    ----------
    data : ndarray, shape (I, J, K)
        Voxel values (hashed as float32, C order).
    affine : ndarray, shape (4, 4)
        Voxel index -> world RAS (mm).

    Returns
    -------
    str
        12 hexadecimal digits of the SHA-256.
    """
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(data, dtype=np.float32).tobytes())
    h.update(np.round(np.asarray(affine, float), 3).astype("<f8").tobytes())
    h.update(str(tuple(np.shape(data))).encode())
    return h.hexdigest()[:12]


def json_path_for(nii_path: str | Path) -> Path:
    """The provenance JSON beside a volume file.

    Parameters
    ----------
    nii_path : path
        ``.../name.nii.gz`` or ``.../name.nii`` (any other suffix is replaced).

    Returns
    -------
    Path
        ``.../name.json``.
    """
    p = Path(nii_path)
    name = p.name
    for ext in (".nii.gz", ".nii"):
        if name.endswith(ext):
            return p.with_name(name[: -len(ext)] + ".json")
    return p.with_suffix(".json")


def check_sidecar_target(path: str | Path) -> None:
    """Refuse to write a volume whose sidecar name (:func:`json_path_for`) holds a JSON file that is not one.

    A volume's JSON is written beside it under a name the user never gave (``ct.nii.gz`` -> ``ct.json``), so a
    BIDS sidecar, a config or any other JSON of that name would be replaced without a word; a sidecar that
    :func:`save_volume` wrote (``shape``, ``spacing_mm`` and ``affine`` in it) is replaced as the volume is.

    Parameters
    ----------
    path : str or Path
        The volume file to be written.

    Raises
    ------
    CtsplatError
        One line naming the JSON file.
    """
    json_path = json_path_for(path)
    if not (json_path.exists() or json_path.is_symlink()):
        return
    try:
        meta = json.loads(json_path.read_text())
        ours = isinstance(meta, dict) and {"shape", "spacing_mm", "affine"} <= set(meta)
    except (OSError, UnicodeDecodeError, ValueError):
        ours = False
    if not ours:
        raise CtsplatError(f"{json_path} is not the sidecar of a volume, and writing {Path(path).name} would replace "
                           "it (a volume's JSON goes beside it under its name); choose another output name")


def save_volume(volume: Volume, path: str | Path) -> None:
    """Write ``volume`` as NIfTI-1 plus its sibling JSON (:func:`json_path_for`), both atomically.

    A JSON of that name that is not a volume's sidecar is refused (:func:`check_sidecar_target`).

    Parameters
    ----------
    volume : Volume
        ``data`` (I, J, K) is stored as float32; ``affine`` (4, 4) as qform and sform (code 1), units mm.
    path : path
        Output ``.nii.gz`` (compressed) or ``.nii``.
    """
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
    # Both files go to temp names first; the JSON is renamed into place just before the NIfTI, so a
    # crash leaves either nothing new or a JSON without its volume - never a volume without its JSON.
    # When the NIfTI cannot be put in place (an error or an interrupt), the JSON is put back as it was.
    check_sidecar_target(path)
    json_path = json_path_for(path)
    previous = json_path.read_bytes() if json_path.is_file() else None
    json_written = False
    try:
        with atomic_path(path) as tmp:
            nib.save(img, str(tmp))
            write_json_atomic(json_path, meta)
            json_written = True
    except BaseException:
        if json_written:
            if previous is None:
                json_path.unlink(missing_ok=True)
            else:
                with atomic_path(json_path) as tmp:
                    tmp.write_bytes(previous)
        raise


def load_volume(path: str | Path) -> Volume:
    """Read a NIfTI volume and its sibling JSON (if present).

    Parameters
    ----------
    path : path
        ``.nii.gz`` / ``.nii`` file; the world frame is the image's affine (sform, else qform, as
        nibabel resolves it), voxel index -> RAS mm.

    Returns
    -------
    Volume
        ``data`` float32 (I, J, K), ``affine`` (4, 4), ``meta`` from the JSON (empty when there is none).
    """
    path = Path(path)
    if not path.exists():
        raise CtsplatError(f"volume file {path} does not exist; run the ingest step first")
    try:
        img = nib.load(str(path))
        data = np.asarray(img.get_fdata(dtype=np.float32), dtype=np.float32)
    except (nib.filebasedimages.ImageFileError, OSError, EOFError, ValueError) as exc:
        raise CtsplatError(f"volume file {path} is not a readable NIfTI ({str(exc).splitlines()[0]}); give the "
                           "volume.nii.gz that ingest wrote") from None
    meta: dict[str, Any] = {}
    jp = json_path_for(path)
    if jp.exists():
        meta = read_json_object(jp, what="volume sidecar", fix="ingest the volume again (it writes both files)")
        recorded = meta.get("shape")
        if recorded is not None and list(recorded) != list(data.shape):
            raise CtsplatError(f"volume sidecar {jp} describes a {recorded} volume, but {path} is {list(data.shape)}: "
                               "they belong to different volumes; ingest the volume again (it writes both files)")
        _check_intensity(meta, jp)
    return Volume(data=data, affine=np.asarray(img.affine, float), meta=meta)


def _check_intensity(meta: dict[str, Any], sidecar: Path) -> None:
    """Refuse a sidecar whose ``intensity`` is not a mapping, or whose scale to 1/mm is not a finite number > 0
    (every projection, seed and score multiplies by it)."""
    fix = "ingest the volume again (it writes both files)"
    intensity = meta.get("intensity", {})
    if not isinstance(intensity, dict):
        raise CtsplatError(f"volume sidecar {sidecar}: 'intensity' is {intensity!r}, not an object; {fix}")
    if "mu_scale_per_mm" in intensity:
        scale = intensity["mu_scale_per_mm"]
        if not (is_finite_real(scale) and scale > 0):
            raise CtsplatError(f"volume sidecar {sidecar}: intensity.mu_scale_per_mm must be a finite number > 0 "
                               f"(1/mm per unit of the voxel values), got {scale!r}; {fix}")


def check_attenuation(volume: Volume, name: str | Path) -> None:
    """Refuse a volume whose values are not attenuation (HU, or mostly negative values), before it is projected.

    Parameters
    ----------
    volume : Volume
    name : str or Path
        How the error names it (its file).

    Raises
    ------
    CtsplatError
        For a volume without the sidecar ``ingest`` writes (its intensity, hence its scale to 1/mm, unknown), for
        intensity ``hu`` (``volume.json``), or when the negative values outweigh 1 % of the absolute total (a
        volume in HU; a reconstruction's small negative ripples pass).
    """
    if not volume.meta:  # load_volume found no sidecar
        raise CtsplatError(f"volume {name} has no {json_path_for(Path(name)).name} beside it (the sidecar ingest "
                           "writes), so whether it holds normalised attenuation or mu in 1/mm is unknown; keep the "
                           "sidecar next to it under the same stem, or run `ctsplat ingest` on it (NIfTI input "
                           "works; --intensity mu for a map already in 1/mm)")
    if volume.meta.get("intensity", {}).get("kind") == "hu":
        raise CtsplatError(f"volume {name} holds raw HU (intensity: hu), not attenuation; ingest it again with "
                           "intensity attenuation (the default) or mu before projecting it")
    data = np.asarray(volume.data, np.float64)
    negative = float(-data[data < 0].sum())
    total = float(np.abs(data).sum())
    if negative > 0.01 * total:
        raise CtsplatError(f"volume {name} has negative values down to {float(data.min()):g} ({negative:.3g} of "
                           f"{total:.3g} in absolute sum): it looks like HU, not attenuation; ingest it with "
                           "`ctsplat ingest` (intensity attenuation) or clip it at 0")
