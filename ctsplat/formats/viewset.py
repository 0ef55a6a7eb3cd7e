"""View sets: a camera plus posed views (``views.json``), and the radiograph folder that stores their images.

A view set is what every later step reads: the projector writes one folder per geometry, SfM registers the
images of one of them, training and evaluation read their targets from them. One writer
(:func:`write_radiographs`) and one reader (:func:`load_radiographs`) define the folder::

    line_integrals.tif   float32 pages (V, H, W): line integrals of μ (1/mm · mm, dimensionless), page order =
                         the order of ``views`` in views.json
    views.json           the :class:`ViewSet` (camera, per-view pose, angles, split; designed pose where the
                         views were taken off a designed orbit)
    png/view_{id:04d}.png  16-bit transmission ``exp(-p)`` (0 = opaque, 65535 = unattenuated), for viewing
    radiographs.json     provenance: config, seed, code version, volume id, statistics

Poses follow ``docs/conventions.md``: world mm, world-to-camera ``x_cam = R x_world + t`` (OpenCV / COLMAP).
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.geometry.cameras import Camera, camera_center, camera_from_dict, rotmat_to_qvec
from ctsplat.utils import (
    CtsplatError,
    atomic_dir,
    check_output_dir,
    code_version,
    read_json_object,
    scratch_dir,
    write_json_atomic,
)

__all__ = [
    "VIEWSET_FORMAT",
    "VIEWSET_FORMAT_VERSION",
    "SPLITS",
    "View",
    "ViewSet",
    "RADIOGRAPH_FILES",
    "check_radiograph_targets",
    "write_radiographs",
    "load_radiographs",
    "write_png_stack",
    "transmission_png16",
]

VIEWSET_FORMAT = "ctsplat.viewset"
VIEWSET_FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")


@dataclass
class View:
    """One radiograph's pose and split.

    Attributes
    ----------
    id : int
        View id, stable across every file that refers to the view (SfM models, per-view metrics).
    R : ndarray (3, 3)
        World-to-camera rotation.
    t : ndarray (3,)
        World-to-camera translation (mm).
    azimuth_deg, elevation_deg : float
        Direction of the source as seen from the isocentre (``docs/conventions.md``).
    split : {"train", "val", "test"}
    design : View or None
        The pose the view was *designed* to have (C-arm orbits, where the true pose deviates from the design);
        ``None`` when the pose is the design.
    """

    id: int
    R: np.ndarray
    t: np.ndarray
    azimuth_deg: float
    elevation_deg: float
    split: str = "train"
    design: View | None = None

    def __post_init__(self) -> None:
        self.R = np.asarray(self.R, float).reshape(3, 3)
        self.t = np.asarray(self.t, float).reshape(3)
        for name in ("azimuth_deg", "elevation_deg"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                raise ValueError(f"view {self.id}: {name} {value!r} is not a number")
            setattr(self, name, float(value))
        if self.split not in SPLITS:
            raise CtsplatError(f"view {self.id}: unknown split {self.split!r}; allowed: {', '.join(SPLITS)}")

    @property
    def center_mm(self) -> np.ndarray:
        """Camera centre (the source, for cone beam) in world mm, shape (3,)."""
        return camera_center(self.R, self.t)

    def to_dict(self) -> dict[str, Any]:
        d = {"id": int(self.id), "R": self.R.tolist(), "t": self.t.tolist(),
             "azimuth_deg": float(self.azimuth_deg), "elevation_deg": float(self.elevation_deg),
             "split": self.split, "qvec": rotmat_to_qvec(self.R).tolist(), "center_mm": self.center_mm.tolist()}
        if self.design is not None:
            d["design"] = {"R": self.design.R.tolist(), "t": self.design.t.tolist(),
                           "azimuth_deg": float(self.design.azimuth_deg),
                           "elevation_deg": float(self.design.elevation_deg)}
        return d

    @classmethod
    def from_dict(cls, v: dict[str, Any]) -> View:
        design = None
        if v.get("design") is not None:
            dd = v["design"]
            design = cls(int(v["id"]), dd["R"], dd["t"], dd["azimuth_deg"], dd["elevation_deg"], v["split"])
        return cls(int(v["id"]), v["R"], v["t"], v["azimuth_deg"], v["elevation_deg"], v["split"], design)


@dataclass
class ViewSet:
    """A camera plus a list of views rendered from one volume (``views.json``).

    JSON layout (``format = "ctsplat.viewset"``, ``format_version = 1``)::

        {"format": ..., "format_version": 1, "volume_id": str, "isocenter_mm": [x, y, z],
         "camera": {"model": "parallel", "width", "height", "spacing_mm", "cx", "cy"}
                 | {"model": "cone", "width", "height", "pitch_mm", "dso_mm", "dsd_mm", "fx", "fy", "cx", "cy"},
         "views": [{"id", "R" (3x3 world-to-camera), "t" (mm), "qvec" (COLMAP w,x,y,z), "center_mm",
                    "azimuth_deg", "elevation_deg", "split",
                    "design": {"R", "t", "azimuth_deg", "elevation_deg"} (optional)}, ...],
         "meta": {...}}

    The row order of ``views`` is the page order of ``line_integrals.tif``.
    """

    camera: Camera
    views: list[View]
    volume_id: str = "unknown"
    isocenter_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.isocenter_mm = np.asarray(self.isocenter_mm, float).reshape(3)
        if not self.views:
            raise CtsplatError("empty view set: need at least one view (check n_views)")

    def __len__(self) -> int:
        return len(self.views)

    def Rs(self) -> np.ndarray:
        """Stacked rotations, shape (V, 3, 3)."""
        return np.stack([v.R for v in self.views])

    def ts(self) -> np.ndarray:
        """Stacked translations (mm), shape (V, 3)."""
        return np.stack([v.t for v in self.views])

    def ids(self) -> np.ndarray:
        """View ids in page order, shape (V,)."""
        return np.array([v.id for v in self.views], dtype=int)

    def has_design(self) -> bool:
        """Whether every view carries its designed pose."""
        return all(v.design is not None for v in self.views)

    def design_Rs(self) -> np.ndarray:
        """Designed rotations (V, 3, 3); error when the view set was not taken off a designed orbit."""
        return np.stack([self._design(v).R for v in self.views])

    def design_ts(self) -> np.ndarray:
        """Designed translations (mm), shape (V, 3)."""
        return np.stack([self._design(v).t for v in self.views])

    @staticmethod
    def _design(v: View) -> View:
        if v.design is None:
            raise CtsplatError(f"view {v.id} has no designed pose; SfM needs a view set rendered with orbit: carm")
        return v.design

    def indices(self, split: str) -> np.ndarray:
        """Row indices (into the image stack) of the views in ``split``."""
        if split not in SPLITS:
            raise CtsplatError(f"unknown split {split!r}; allowed: {', '.join(SPLITS)}")
        return np.array([i for i, v in enumerate(self.views) if v.split == split], dtype=int)

    def subset(self, split: str) -> ViewSet:
        """The views of one split (same camera); error if that split is empty."""
        idx = self.indices(split)
        if idx.size == 0:
            raise CtsplatError(f"view set has no '{split}' views; re-render with a non-zero {split} fraction")
        return ViewSet(self.camera, [self.views[i] for i in idx], self.volume_id, self.isocenter_mm.copy(),
                       dict(self.meta))

    def to_dict(self) -> dict[str, Any]:
        return {"format": VIEWSET_FORMAT, "format_version": VIEWSET_FORMAT_VERSION, "volume_id": self.volume_id,
                "isocenter_mm": self.isocenter_mm.tolist(), "camera": self.camera.to_dict(),
                "views": [v.to_dict() for v in self.views], "meta": self.meta}

    def save(self, path: str | Path) -> None:
        write_json_atomic(path, self.to_dict())

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ViewSet:
        if d.get("format") != VIEWSET_FORMAT:
            raise CtsplatError(f"not a ctsplat view set (format {d.get('format')!r}); expected {VIEWSET_FORMAT!r}")
        version = d.get("format_version")
        if version != VIEWSET_FORMAT_VERSION:
            raise CtsplatError(f"view set format_version {version} is not supported (this ctsplat reads "
                               f"{VIEWSET_FORMAT_VERSION}); re-render the radiographs")
        if not isinstance(d["views"], list) or not all(isinstance(v, dict) for v in d["views"]):
            raise ValueError("'views' is not a list of view objects")
        views = [View.from_dict(v) for v in d["views"]]
        ids = [v.id for v in views]
        if len(set(ids)) != len(ids):
            raise ValueError(f"view id {next(i for i in ids if ids.count(i) > 1)} appears more than once")
        for v in views:  # a file written by hand or another tool: its poses must be rotations (to ~4 decimals)
            for key, R in (("R", v.R), *(() if v.design is None else (("design.R", v.design.R),))):
                if not (np.isfinite(R).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-3)
                        and np.linalg.det(R) > 0):
                    raise ValueError(f"view {v.id}: {key} is not a rotation matrix (orthonormal, determinant +1)")
            for pose, prefix in ((v, ""), *(() if v.design is None else ((v.design, "design."),))):
                values = {"t": pose.t, "azimuth_deg": pose.azimuth_deg, "elevation_deg": pose.elevation_deg}
                bad = next((k for k, x in values.items() if not np.isfinite(np.asarray(x, float)).all()), None)
                if bad is not None:  # a NaN translation renders an image of zeros, not an error
                    raise ValueError(f"view {v.id}: {prefix}{bad} is not finite")
        if not isinstance(d["camera"], dict):
            raise ValueError("'camera' is not an object")
        iso = np.asarray(d.get("isocenter_mm", [0, 0, 0]), float)
        if iso.shape != (3,) or not np.isfinite(iso).all():
            raise ValueError("isocenter_mm is not three finite numbers")
        return cls(camera_from_dict(d["camera"]), views, str(d.get("volume_id", "unknown")), iso,
                   dict(d.get("meta", {})))

    @classmethod
    def load(cls, path: str | Path) -> ViewSet:
        d = read_json_object(path, what="view set", fix="render it with `ctsplat project`")
        try:
            return cls.from_dict(d)
        except CtsplatError as exc:  # from_dict does not know the file; the message names it
            raise CtsplatError(f"view set {path}: {exc}") from None
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            what = f"no {exc.args[0]!r} entry" if isinstance(exc, KeyError) else str(exc).splitlines()[0]
            raise CtsplatError(f"view set {path} is malformed ({what}); re-render it") from None


# ------------------------------------------------------------------------------------------ radiograph folder
def transmission_png16(p: np.ndarray) -> np.ndarray:
    """Transmission ``exp(-p)`` in [0, 1] as uint16 (0 = opaque, 65535 = unattenuated); same shape as ``p``."""
    return np.round(np.clip(np.exp(-np.asarray(p, np.float64)), 0.0, 1.0) * 65535.0).astype(np.uint16)


def write_png_stack(images: np.ndarray, out_dir: str | Path, names: list[str]) -> None:
    """Write ``images`` (V, H, W) of an integer dtype as ``out_dir/<name>`` PNGs, replacing the folder whole.

    The folder appears complete or not at all (written under a temporary name, then renamed).

    Parameters
    ----------
    images : ndarray (V, H, W), uint8 or uint16
    out_dir : path
        Folder to (re)create.
    names : list of str, length V
        File names (with the ``.png`` suffix).
    """
    import imageio.v3 as iio

    if len(names) != len(images):
        raise CtsplatError(f"{len(images)} images but {len(names)} names")
    out_dir = Path(out_dir)
    with atomic_dir(out_dir, marker="*.png") as tmp:
        for name, img in zip(names, images, strict=True):
            iio.imwrite(tmp / name, img)


#: The entries of a radiograph folder :func:`write_radiographs` writes, in the order they are moved into place:
#: radiographs.json first, so a folder left half-moved is still known as an earlier output, views.json last, so
#: it is refused by :func:`load_radiographs` until complete. A folder holding other files is not written
#: (:func:`check_radiograph_targets`).
RADIOGRAPH_FILES = ("radiographs.json", "line_integrals.tif", "png", "views.json")


def check_radiograph_targets(out_dir: str | Path) -> None:
    """Refuse a folder where writing radiographs would replace something that is not an earlier radiograph output,
    or mix them with other files.

    An earlier output is known by its ``radiographs.json`` (with the line-integral statistics this module writes);
    without one, none of :data:`RADIOGRAPH_FILES` may exist. ``png/`` may hold only the views' PNGs, and the folder
    nothing but :data:`RADIOGRAPH_FILES` (a training run's or someone else's folder is refused, as the other steps
    refuse theirs: :func:`ctsplat.utils.check_output_dir`).

    Parameters
    ----------
    out_dir : str or Path
        The radiograph folder (need not exist).

    Raises
    ------
    CtsplatError
        One line naming what is in the way.
    """
    out_dir = Path(out_dir)
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise CtsplatError(f"output {out_dir} exists and is not a folder; choose another output folder")
    present = [n for n in RADIOGRAPH_FILES if (out_dir / n).exists() or (out_dir / n).is_symlink()]
    for name in present:  # every target checked before the first move, so the moves cannot fail halfway
        target = out_dir / name
        if target.is_dir() != (name == "png"):
            raise CtsplatError(f"cannot write {target}: a {'folder' if target.is_dir() else 'file'} of that name is "
                               "in the way; remove it or choose another output folder")
    if not present:
        _check_no_foreign_files(out_dir)
        return
    try:
        ours = "line_integral_stats" in json.loads((out_dir / "radiographs.json").read_text())
    except (OSError, ValueError, TypeError):
        ours = False
    if not ours:
        raise CtsplatError(f"{out_dir} holds {present[0]} but no radiographs.json of an earlier projection, and "
                           "writing radiographs would replace it; choose another output folder")
    png = out_dir / "png"

    def ours_png(f: Path) -> bool:
        view_png = f.parent == png and re.fullmatch(r"view_\d+\.png", f.name) is not None
        return view_png or f.name == ".snakemake_timestamp"

    foreign = sorted(f.relative_to(png).as_posix() for f in png.rglob("*")
                     if (f.is_file() or f.is_symlink()) and not ours_png(f)) if png.is_dir() else []
    if foreign:
        raise CtsplatError(f"{png} holds {foreign[0]}, which a projection does not write, and writing radiographs "
                           "would delete it; choose another output folder or move it away")
    _check_no_foreign_files(out_dir)


def _check_no_foreign_files(out_dir: Path) -> None:
    """Refuse a radiograph folder that holds files other than :data:`RADIOGRAPH_FILES`."""
    contents = [f"{n}/*" if n == "png" else n for n in RADIOGRAPH_FILES]
    check_output_dir(out_dir, marker=contents, in_place=True)


def write_radiographs(out_dir: str | Path, p: np.ndarray, view_set: ViewSet, provenance: dict[str, Any]) -> None:
    """Write a radiograph folder (see the module docstring): all of its files, or none of them.

    Every file is first written into a staging folder beside ``out_dir``; only when all are complete are they moved
    into place (renames on one file system), so a failure leaves ``out_dir`` as it was. The moves take the old
    ``views.json`` away first and put the new one in place last: a crash between two moves leaves a folder without
    ``views.json``, which :func:`load_radiographs` refuses, never new images beside the old view set.

    Parameters
    ----------
    out_dir : path
    p : ndarray (V, H, W)
        Line integrals (dimensionless), one page per view of ``view_set`` in its order.
    view_set : ViewSet
    provenance : dict
        Stored in ``radiographs.json`` beside view counts, camera and statistics.
    """
    import tifffile

    p = np.ascontiguousarray(p, dtype=np.float32)
    cam = view_set.camera
    if p.shape != (len(view_set), cam.height, cam.width):
        raise CtsplatError(f"images of shape {p.shape} do not match the view set "
                           f"({len(view_set)}, {cam.height}, {cam.width})")
    out_dir = Path(out_dir)
    check_radiograph_targets(out_dir)  # before the slow part
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    with scratch_dir(out_dir.parent, prefix=f".{out_dir.name}.") as stage:
        tifffile.imwrite(stage / "line_integrals.tif", p, photometric="minisblack", metadata={"axes": "QYX"})
        write_png_stack(transmission_png16(p), stage / "png", [f"view_{v.id:04d}.png" for v in view_set.views])
        view_set.save(stage / "views.json")
        write_json_atomic(stage / "radiographs.json", {
            "code_version": code_version(), **provenance,
            "n_views": len(view_set), "splits": {s: int(len(view_set.indices(s))) for s in SPLITS},
            "camera": cam.to_dict(),
            "line_integral_stats": {"min": float(p.min()), "max": float(p.max()), "mean": float(p.mean())},
            "units": "line integrals of mu in 1/mm (dimensionless); png = 16-bit transmission exp(-p)",
        })
        out_dir.mkdir(exist_ok=True)
        check_radiograph_targets(out_dir)  # again: the folder may have changed meanwhile
        (out_dir / "views.json").unlink(missing_ok=True)
        for name in RADIOGRAPH_FILES:
            if name == "png" and (out_dir / name).exists():
                shutil.rmtree(out_dir / name)
            os.replace(stage / name, out_dir / name)


def load_radiographs(out_dir: str | Path) -> tuple[np.ndarray, ViewSet]:
    """Read a radiograph folder written by :func:`write_radiographs`.

    Returns
    -------
    p : ndarray (V, H, W) float32
        Line integrals, page order = ``view_set.views``.
    view_set : ViewSet
    """
    import tifffile

    out_dir = Path(out_dir)
    if out_dir.is_file():
        raise CtsplatError(f"{out_dir} is a file; give the radiographs folder that holds it ({out_dir.parent})")
    if not out_dir.is_dir():
        raise CtsplatError(f"radiographs folder {out_dir} does not exist; run `ctsplat project` first")
    tif = out_dir / "line_integrals.tif"
    if not tif.exists():
        raise CtsplatError(f"{tif} does not exist; run `ctsplat project` for this geometry first")
    view_set = ViewSet.load(out_dir / "views.json")
    try:
        raw = tifffile.imread(tif)
    except (OSError, ValueError) as exc:  # truncated, corrupt, or not a TIFF at all (TiffFileError)
        raise CtsplatError(f"{tif} is not a readable TIFF file ({type(exc).__name__}: {exc}); re-render the "
                           "radiographs with `ctsplat project`") from None
    if raw.dtype.kind != "f":  # integers are counts or scaled values, not line integrals: they would train wrongly
        raise CtsplatError(f"{tif} holds {raw.dtype} values, not line integrals (floating point, as `ctsplat project` "
                           "writes them); convert the images to line integrals -ln(I / I0) or re-render them")
    p = np.asarray(raw, dtype=np.float32)
    if p.ndim == 2:
        p = p[None]
    expected = (len(view_set), view_set.camera.height, view_set.camera.width)
    if p.shape != expected:
        raise CtsplatError(f"{tif} holds images of shape {p.shape} but views.json describes {expected}; "
                           "re-render the radiographs")
    finite = np.isfinite(p)
    if not finite.all():  # one NaN turns every reconstruction and score NaN, and NaN scores never lose a comparison
        first = int(np.flatnonzero(~finite.reshape(len(p), -1).all(axis=1))[0])
        raise CtsplatError(f"{tif} has {int(finite.size - np.count_nonzero(finite))} non-finite pixels (NaN/Inf), "
                           f"the first in view {view_set.views[first].id}; re-render the radiographs")
    return p, view_set
