"""Built-in 3D Shepp–Logan head phantom: analytic ellipsoids in world mm, written as a real DICOM CT series.

Parameterisation (the contract used for exact line integrals)
-------------------------------------------------------------
The phantom is a sum of solid ellipsoids with additive values::

    r(x) = Σ_e value_e · 1[ ‖ diag(1 / semi_axes_e) · R_eᵀ (x − centre_e) ‖² ≤ 1 ]

- ``x``, ``centre_e``: world position (mm) in the ctsplat world frame (RAS+, the NIfTI frame of
  the ingested volume; see ``docs/conventions.md``). The phantom centre is the world origin.
- ``semi_axes_e`` (mm): semi-axis lengths along the ellipsoid's own axes.
- ``R_e`` (3x3 rotation, det +1): its *columns* are the ellipsoid's principal axes in world
  coordinates, column ``m`` carrying ``semi_axes_e[m]``. (Shepp–Logan ellipsoids are rotated about
  world z by ``phi``: ``R = [[cos φ, −sin φ, 0], [sin φ, cos φ, 0], [0, 0, 1]]``.)
- ``value_e`` (dimensionless): additive attenuation **relative to water**, so ``r = μ / μ_water``:
  air (outside) 0, water 1, the skull shell 2 (Kak & Slaney's table is defined this way).

Units downstream:
- HU written to the DICOM files: ``HU = 1000 (r − 1)`` (partial-volume averaged, rounded).
- Attenuation (1/mm): ``μ(x) = μ_water · r(x)`` with the ``mu_water_per_mm`` used at ingestion
  (default 0.019). A ray's exact line integral is ``∫ μ dl = μ_water Σ_e value_e · chord_e`` (mm).
- After ingestion with the default ``intensity: attenuation``, the normalised volume equals
  ``clip(r, 0, 1 + hu_max/1000) / (1 + hu_max/1000)``, i.e. ``μ / mu_scale_per_mm``.

Geometry of the default phantom: Kak & Slaney's 3D head (Principles of Computerized Tomographic
Imaging, 1988, p. 102) with normalised unit = ``scale_mm`` = 110 mm, giving a head of about
152 mm (left–right) x 202 mm (antero–posterior) x 198 mm (cranio–caudal). Optional beads are small
dense spheres (default radius 3 mm, value +2.0, i.e. ~2000 HU inside brain) at seeded random
positions inside the brain, as fiducial markers for feature matching.

References
----------
Kak, A. C., Slaney, M. (1988). Principles of Computerized Tomographic Imaging. IEEE Press. (The 3D head
phantom's ellipsoids and values.)
Shepp, L. A., Logan, B. F. (1974). The Fourier reconstruction of a head section. IEEE Transactions on Nuclear
Science 21(3), 21-43. (The head phantom.)
Yu, H., Ye, Y., Wang, G. (2004). Katsevich-type algorithms for variable radius spiral cone-beam CT. Proc. SPIE
5535, 550-557. (The higher-contrast values of ``variant="high_contrast"``.)
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.formats.sources import LPS_TO_RAS, write_dicom_series
from ctsplat.utils import CtsplatError, code_version, scratch_dir

__all__ = [
    "Ellipsoid",
    "PHANTOM_DEFAULTS",
    "shepp_logan_ellipsoids",
    "relative_attenuation",
    "rasterize",
    "write_phantom_dicom",
    "load_phantom_ellipsoids",
    "PHANTOM_MARKER",
]

log = logging.getLogger(__name__)

#: ``created_by`` of ``phantom.json``: the marker of a folder written by :func:`write_phantom_dicom`.
PHANTOM_MARKER = "ctsplat.phantom.write_phantom_dicom"
_SLICE_NAME = "slice_{k:04d}.dcm"
_SLICE_RE = re.compile(r"slice_\d{4,}\.dcm")
_STAGING_PREFIX = ".ctsplat-phantom-"

#: Defaults of the ``phantom`` config section.
PHANTOM_DEFAULTS: dict[str, Any] = {
    "size": 128,
    "fov_mm": 240.0,
    "beads": True,
    "n_beads": 12,
    "bead_radius_mm": 3.0,
    "seed": 0,
    "variant": "kak_slaney",
    "supersample": 2,
}

# Kak & Slaney 3D Shepp–Logan head, normalised units: semi-axes (a, b, c), centre (x, y, z),
# rotation phi (degrees, about z), value relative to water.
_KAK_SLANEY = [
    ("skull", (0.6900, 0.920, 0.900), (0.00, 0.000, 0.000), 0.0, 2.00),
    ("brain", (0.6624, 0.874, 0.880), (0.00, 0.000, 0.000), 0.0, -0.98),
    ("ventricle_right", (0.4100, 0.160, 0.210), (-0.22, 0.000, -0.250), 108.0, -0.02),
    ("ventricle_left", (0.3100, 0.110, 0.220), (0.22, 0.000, -0.250), 72.0, -0.02),
    ("lesion_large", (0.2100, 0.250, 0.500), (0.00, 0.350, -0.250), 0.0, 0.02),
    ("lesion_small", (0.0460, 0.046, 0.046), (0.00, 0.100, -0.250), 0.0, 0.02),
    ("feature_1", (0.0460, 0.023, 0.020), (-0.08, -0.650, -0.250), 0.0, 0.01),
    ("feature_2", (0.0460, 0.023, 0.020), (0.06, -0.650, -0.250), 90.0, 0.01),
    ("feature_3", (0.0560, 0.040, 0.100), (0.06, -0.105, 0.625), 90.0, 0.02),
    ("feature_4", (0.0560, 0.056, 0.100), (0.00, 0.100, 0.625), 0.0, -0.02),
]
# Same geometry, contrast of Yu, Ye & Wang (2004) scaled x2 so the skull stays at 2 x water.
_HIGH_CONTRAST = [2.0, -1.6, -0.4, -0.4, 0.4, 0.4, 0.2, 0.2, 0.4, -0.4]


@dataclass(frozen=True)
class Ellipsoid:
    """One solid ellipsoid of the phantom (see the module docstring for the exact definition).

    Parameters
    ----------
    centre_mm : ndarray, shape (3,)
        Centre in world RAS (mm).
    semi_axes_mm : ndarray, shape (3,)
        Semi-axis lengths (mm) along the columns of ``rotation``.
    rotation : ndarray, shape (3, 3)
        Columns = principal axes in world coordinates (orthonormal, det +1).
    value : float
        Additive attenuation relative to water (μ / μ_water).
    name : str
        Label (``skull``, ``brain``, ..., ``bead_00``); empty when not given.
    """

    centre_mm: np.ndarray
    semi_axes_mm: np.ndarray
    rotation: np.ndarray
    value: float
    name: str = ""

    def quadratic_form(self) -> np.ndarray:
        """The ellipsoid's quadratic form ``Q = R diag(1/s²) Rᵀ``: ``x`` is inside iff ``(x − c)ᵀ Q (x − c) ≤ 1``.

        Returns
        -------
        ndarray, shape (3, 3)
            Symmetric positive definite matrix (1/mm²).
        """
        return self.rotation @ np.diag(1.0 / np.asarray(self.semi_axes_mm, float) ** 2) @ self.rotation.T

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which points lie inside the ellipsoid (boundary included).

        Parameters
        ----------
        points : ndarray, shape (..., 3)
            World points (mm).

        Returns
        -------
        ndarray of bool, shape (...)
            True inside.
        """
        d = np.asarray(points, float) - self.centre_mm
        body = d @ self.rotation / self.semi_axes_mm
        return np.einsum("...i,...i->...", body, body) <= 1.0

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Tight axis-aligned world bounds: ``c ± sqrt(diag(R diag(s²) Rᵀ))``.

        Returns
        -------
        lo : ndarray, shape (3,)
            Lower corner (world mm).
        hi : ndarray, shape (3,)
            Upper corner (world mm).
        """
        half = np.sqrt(np.sum((self.rotation * self.semi_axes_mm[None, :]) ** 2, axis=1))
        return self.centre_mm - half, self.centre_mm + half

    def to_dict(self) -> dict[str, Any]:
        """The ellipsoid as the JSON object stored in ``phantom.json``.

        Returns
        -------
        dict
            ``name``, ``centre_mm`` (3,), ``semi_axes_mm`` (3,), ``rotation`` (3, 3) as nested lists, ``value``.
        """
        return {
            "name": self.name,
            "centre_mm": [float(x) for x in self.centre_mm],
            "semi_axes_mm": [float(x) for x in self.semi_axes_mm],
            "rotation": np.asarray(self.rotation, float).tolist(),
            "value": float(self.value),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Ellipsoid:
        """The ellipsoid described by a :meth:`to_dict` object.

        Parameters
        ----------
        d : dict
            ``centre_mm``, ``semi_axes_mm``, ``rotation``, ``value`` and optionally ``name``.

        Returns
        -------
        Ellipsoid
        """
        return cls(
            centre_mm=np.asarray(d["centre_mm"], float),
            semi_axes_mm=np.asarray(d["semi_axes_mm"], float),
            rotation=np.asarray(d["rotation"], float),
            value=float(d["value"]),
            name=str(d.get("name", "")),
        )


def _rot_z(phi_deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(phi_deg)), np.sin(np.radians(phi_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def shepp_logan_ellipsoids(
    *,
    scale_mm: float = 110.0,
    beads: bool = True,
    n_beads: int = 12,
    bead_radius_mm: float = 3.0,
    bead_value: float = 2.0,
    seed: int = 0,
    variant: str = "kak_slaney",
) -> list[Ellipsoid]:
    """The analytic 3D Shepp–Logan head (plus optional beads) in world mm; see the module docstring.

    Parameters
    ----------
    scale_mm : float
        Millimetres per normalised phantom unit (110 -> a head about 200 mm long).
    beads : bool
        Add ``n_beads`` spheres of radius ``bead_radius_mm`` and value ``bead_value`` at seeded
        random positions inside the brain (at least 6 radii apart).
    n_beads : int
        Number of beads.
    bead_radius_mm : float
        Bead radius (mm).
    bead_value : float
        Additive value of a bead, relative to water.
    seed : int
        Seeds the bead positions.
    variant : {"kak_slaney", "high_contrast"}
        Kak & Slaney's physical values (skull 2.0, brain 1.02, ventricles 1.00 x water), or the same
        geometry with Yu–Ye–Wang contrast x2 (brain 0.4, ventricles 0.0).

    Returns
    -------
    list of Ellipsoid
        Shepp–Logan ellipsoids first, then beads (names ``bead_00``...).

    Raises
    ------
    CtsplatError
        For an unknown variant, or when the beads do not fit in the brain at the required spacing.

    Examples
    --------
    >>> ells = shepp_logan_ellipsoids(beads=False)
    >>> [e.name for e in ells[:2]], ells[0].semi_axes_mm.round(1).tolist()
    (['skull', 'brain'], [75.9, 101.2, 99.0])
    """
    if variant not in ("kak_slaney", "high_contrast"):
        raise CtsplatError(f"phantom variant {variant!r} unknown; allowed: kak_slaney, high_contrast")
    out = []
    for m, (name, axes, centre, phi, value) in enumerate(_KAK_SLANEY):
        out.append(
            Ellipsoid(
                centre_mm=np.asarray(centre, float) * scale_mm,
                semi_axes_mm=np.asarray(axes, float) * scale_mm,
                rotation=_rot_z(phi),
                value=float(value if variant == "kak_slaney" else _HIGH_CONTRAST[m]),
                name=name,
            )
        )
    if beads and n_beads > 0:
        rng = np.random.default_rng(seed)
        brain = out[1]
        limit = brain.semi_axes_mm * 0.8
        min_dist = 6.0 * bead_radius_mm
        centres: list[np.ndarray] = []
        for _ in range(100_000):
            p = rng.uniform(-limit, limit)
            if np.sum((p / limit) ** 2) > 1.0:
                continue
            if all(np.linalg.norm(p - q) >= min_dist for q in centres):
                centres.append(p)
            if len(centres) == n_beads:
                break
        if len(centres) < n_beads:
            raise CtsplatError(f"cannot place {n_beads} beads of radius {bead_radius_mm} mm; use fewer or smaller")
        for b, c in enumerate(centres):
            out.append(Ellipsoid(c, np.full(3, float(bead_radius_mm)), np.eye(3), float(bead_value), f"bead_{b:02d}"))
    return out


def relative_attenuation(points: np.ndarray, ellipsoids: Sequence[Ellipsoid]) -> np.ndarray:
    """Relative attenuation ``r(x) = μ / μ_water`` at world points: the summed values of the containing ellipsoids.

    Parameters
    ----------
    points : ndarray, shape (..., 3)
        World points (mm).
    ellipsoids : sequence of Ellipsoid
        The phantom.

    Returns
    -------
    ndarray, shape (...)
        ``r`` (dimensionless; 0 in air, 1 in water).

    Examples
    --------
    >>> relative_attenuation(np.zeros((1, 3)), shepp_logan_ellipsoids(beads=False))  # centre: brain
    array([1.02])
    """
    points = np.asarray(points, float)
    out = np.zeros(points.shape[:-1])
    for e in ellipsoids:
        out += e.value * e.contains(points)
    return out


def rasterize(
    ellipsoids: Sequence[Ellipsoid], shape: Sequence[int], affine: np.ndarray, *, supersample: int = 2
) -> np.ndarray:
    """Voxel averages of ``r = μ / μ_water`` on a grid, by ``supersample³`` point samples per voxel.

    Parameters
    ----------
    ellipsoids : sequence of Ellipsoid
        The phantom (world mm).
    shape : sequence of int, shape (3,)
        Grid shape (I, J, K).
    affine : ndarray, shape (4, 4)
        Voxel index -> world RAS mm (any orientation); voxel ``(i, j, k)`` covers index range
        ``[i − ½, i + ½]`` etc.; sub-samples sit at offsets ``(m + ½)/s − ½``, ``m = 0..s−1``.
    supersample : int
        Sub-samples ``s`` per voxel and axis.

    Returns
    -------
    ndarray, shape (I, J, K), float32
        Partial-volume averages of ``r`` (dimensionless).
    """
    shape = tuple(int(x) for x in shape)
    affine = np.asarray(affine, float)
    s = int(supersample)
    offs = (np.arange(s) + 0.5) / s - 0.5
    sub = [(np.arange(n)[:, None] + offs[None, :]).ravel() for n in shape]  # sub-sample index coordinates
    acc = np.zeros([n * s for n in shape], np.float32)
    inv = np.linalg.inv(affine)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    for e in ellipsoids:
        lo, hi = e.bounding_box()
        box = lo + corners * (hi - lo)
        idx = box @ inv[:3, :3].T + inv[:3, 3]
        rng = [
            (int(np.searchsorted(c, idx[:, a].min(), "left")), int(np.searchsorted(c, idx[:, a].max(), "right")))
            for a, c in enumerate(sub)
        ]
        if any(a >= b for a, b in rng):
            continue
        q = e.quadratic_form()
        ci = [c[a:b] for c, (a, b) in zip(sub, rng, strict=True)]
        # d = a_i + b_j + c_k (world offsets from the centre, separable in the index axes), so
        # dᵀQd = aQa + bQb + cQc + 2 aQb + 2 aQc + 2 bQc: six broadcast adds instead of a 3D quadratic form.
        a = ci[0][:, None] * affine[:3, 0][None, :]
        b = ci[1][:, None] * affine[:3, 1][None, :]
        c = ci[2][:, None] * affine[:3, 2][None, :] + (affine[:3, 3] - e.centre_mm)[None, :]
        qa, qb, qc = (np.einsum("ni,ij,nj->n", x, q, x) for x in (a, b, c))
        ab, ac, bc = 2 * a @ q @ b.T, 2 * a @ q @ c.T, 2 * b @ q @ c.T
        base = qa[:, None] + qb[None, :] + ab
        step = max(1, int(2_000_000 // max(1, base.size)))
        for k0 in range(0, len(ci[2]), step):
            k1 = min(len(ci[2]), k0 + step)
            val = (
                base[:, :, None]
                + (qc[k0:k1][None, None, :] + ac[:, None, k0:k1] + bc[None, :, k0:k1])
            ) <= 1.0
            acc[rng[0][0]:rng[0][1], rng[1][0]:rng[1][1], rng[2][0] + k0:rng[2][0] + k1] += np.float32(e.value) * val
    return acc.reshape(shape[0], s, shape[1], s, shape[2], s).mean(axis=(1, 3, 5), dtype=np.float32)


def write_phantom_dicom(
    out_dir: str | Path,
    *,
    size: int = 128,
    beads: bool = True,
    seed: int = 0,
    fov_mm: float = 240.0,
    n_beads: int = 12,
    bead_radius_mm: float = 3.0,
    variant: str = "kak_slaney",
    supersample: int = 2,
    force: bool = False,
) -> Path:
    """Write the Shepp–Logan head as a real DICOM CT series (``size`` slices of ``size²`` pixels).

    The series is axial, head-first-supine: ImageOrientationPatient ``[1,0,0, 0,1,0]`` (LPS), voxel
    ``fov_mm / size`` mm isotropic, the grid centred on the phantom centre, which ingestion maps to
    the world origin (RAS). HU are partial-volume averages (``supersample³`` samples per voxel),
    stored as uint16 with RescaleIntercept −1024. ``out_dir/phantom.json`` lists the ellipsoids in
    world mm (see :func:`load_phantom_ellipsoids`); its ``created_by`` (:data:`PHANTOM_MARKER`)
    marks the folder as a phantom output.

    Where the files go, by what ``out_dir`` is:

    - missing: the folder is built under a temporary sibling name and renamed into place;
    - empty, or a previous phantom output (``phantom.json`` with the marker and nothing but
      ``slice_NNNN.dcm`` files beside it): the new files are built in a hidden staging folder inside
      it and moved over the old ones; slices of the previous phantom that the new one lacks are
      removed. The folder itself is never removed or renamed (``out_dir`` may be ``.``);
    - anything else (unrelated files, sub-folders, a patient series): refused, unless ``force``,
      which writes the phantom files into it, replacing files of the same names (``phantom.json``,
      ``slice_NNNN.dcm``) and leaving everything else in place (a previous phantom's slices that
      the new one lacks are removed when its ``phantom.json`` is there).

    Hidden entries (names starting with ``.``) are never touched and do not count.

    Parameters
    ----------
    out_dir : path
        Output folder.
    size : int
        Voxels per axis (slices, rows and columns), >= 8.
    beads : bool
        Add the beads (see :func:`shepp_logan_ellipsoids`).
    seed : int
        Seeds the bead positions.
    fov_mm : float
        Field-of-view edge (mm); voxels are ``fov_mm / size`` mm.
    n_beads : int
        Number of beads.
    bead_radius_mm : float
        Bead radius (mm).
    variant : {"kak_slaney", "high_contrast"}
        Phantom values (see :func:`shepp_logan_ellipsoids`).
    supersample : int
        Point samples per voxel and axis for the partial-volume HU.
    force : bool
        Write into a non-empty folder that is not a previous phantom output.

    Returns
    -------
    Path
        ``out_dir``.

    Raises
    ------
    CtsplatError
        For ``size < 8``, a non-positive ``fov_mm``, bad phantom parameters, or an output folder that may not
        be written (see above); nothing is written then.

    Examples
    --------
    >>> write_phantom_dicom("data/phantom", size=64, seed=1)
    PosixPath('data/phantom')
    """
    if not isinstance(size, int) or size < 8:
        raise CtsplatError(f"phantom size must be an integer >= 8, got {size!r}")
    if not 0 < fov_mm < math.inf:
        raise CtsplatError(f"phantom fov_mm must be a finite number > 0, got {fov_mm!r}")
    out_dir = Path(out_dir)
    stale = _check_phantom_target(out_dir, force)
    ellipsoids = shepp_logan_ellipsoids(
        beads=beads, n_beads=n_beads, bead_radius_mm=bead_radius_mm, seed=seed, variant=variant
    )
    h = float(fov_mm) / size
    origin_lps = np.full(3, -(size - 1) / 2 * h)
    affine_lps = np.eye(4)
    affine_lps[:3, :3] = np.eye(3) * h
    affine_lps[:3, 3] = origin_lps
    affine_ras = np.eye(4)
    affine_ras[:3, :] = LPS_TO_RAS @ affine_lps[:3, :]
    r = rasterize(ellipsoids, (size, size, size), affine_ras, supersample=supersample)
    hu = 1000.0 * (r.astype(np.float64) - 1.0)

    series_description = f"Shepp-Logan head phantom {variant} {size}^3{' + beads' if beads else ''}"
    info = {
        "format_version": 1,
        "created_by": PHANTOM_MARKER,
        "code_version": code_version(),
        "frame": "world RAS mm; phantom centre at the origin; ingested volumes share this frame",
        "value_units": "additive attenuation relative to water (mu / mu_water); HU = 1000 * (sum - 1)",
        "inside_test": "|| diag(1/semi_axes) @ rotation.T @ (x - centre) ||^2 <= 1 (rotation columns = axes)",
        "parameters": {
            "size": size, "fov_mm": fov_mm, "voxel_mm": h, "beads": beads, "n_beads": n_beads if beads else 0,
            "bead_radius_mm": bead_radius_mm, "seed": seed, "variant": variant, "supersample": supersample,
        },
        "ellipsoids": [e.to_dict() for e in ellipsoids],
    }
    absolute = Path(os.path.abspath(out_dir))
    if absolute.exists():
        parent, prefix = absolute, _STAGING_PREFIX
    else:
        absolute.parent.mkdir(parents=True, exist_ok=True)
        parent, prefix = absolute.parent, f".{absolute.name}."
    with scratch_dir(parent, prefix=prefix, suffix=".tmp") as tmp:
        write_dicom_series(
            hu, tmp, spacing_mm=(h, h, h), origin_lps=origin_lps, uid_seed=f"ctsplat-phantom-{seed}-{size}-{variant}",
            series_description=series_description, filename=_SLICE_NAME,
        )
        (tmp / "phantom.json").write_text(json.dumps(info, indent=2, allow_nan=False) + "\n")
        os.chmod(tmp, 0o755)
        if not absolute.exists():
            os.replace(tmp, absolute)
        else:
            new = sorted(p.name for p in tmp.iterdir())
            # slices first, the marker last: an interrupted update still reads as a phantom output
            for name in [n for n in new if n != "phantom.json"] + ["phantom.json"]:
                os.replace(tmp / name, absolute / name)
            for name in sorted(set(stale) - set(new)):
                (absolute / name).unlink(missing_ok=True)
    log.info("wrote Shepp-Logan phantom %d^3 (%.3f mm voxels, %d ellipsoids) to %s", size, h, len(ellipsoids), out_dir)
    return out_dir


def _is_phantom_marker(path: Path) -> bool:
    try:
        return json.loads(path.read_text()).get("created_by") == PHANTOM_MARKER
    except (OSError, ValueError, AttributeError):
        return False


def _check_phantom_target(out_dir: Path, force: bool) -> list[str]:
    """Refuse an output folder the phantom writer may not overwrite; return the previous phantom's slice names.

    Staging folders left by an interrupted write are removed here.
    """
    if not out_dir.exists():
        return []
    if not out_dir.is_dir():
        raise CtsplatError(f"phantom output {out_dir} exists and is not a folder; give a new or empty folder")
    for p in out_dir.iterdir():
        if p.is_dir() and p.name.startswith(_STAGING_PREFIX) and p.name.endswith(".tmp"):
            shutil.rmtree(p, ignore_errors=True)
    entries = [p for p in out_dir.iterdir() if not p.name.startswith(".")]
    marked = _is_phantom_marker(out_dir / "phantom.json")
    slices = [p.name for p in entries if p.is_file() and _SLICE_RE.fullmatch(p.name)]
    others = sorted(p.name for p in entries if p.name != "phantom.json" and p.name not in slices)
    if not entries or (marked and not others):
        return slices
    if force:
        return slices if marked else []
    what = "holds files the phantom writer did not write" if marked else "is not a previous phantom output"
    listing = ", ".join(others[:3]) + (" ..." if len(others) > 3 else "")
    raise CtsplatError(
        f"phantom output folder {out_dir} {what} ({listing}); give a new or empty folder, or pass force "
        f"(--force) to write the phantom files into it (other files are kept, same-named ones replaced)"
    )


def load_phantom_ellipsoids(path: str | Path) -> list[Ellipsoid]:
    """Read the ellipsoids of a phantom written by :func:`write_phantom_dicom`.

    Parameters
    ----------
    path : str or Path
        The phantom folder, or its ``phantom.json``.

    Returns
    -------
    list of Ellipsoid
        In world mm, in the order written (Shepp–Logan ellipsoids, then beads).

    Raises
    ------
    CtsplatError
        When ``phantom.json`` does not exist.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "phantom.json"
    if not path.exists():
        raise CtsplatError(f"{path} not found; write the phantom with `ctsplat phantom OUT_DIR` first")
    return [Ellipsoid.from_dict(d) for d in json.loads(path.read_text())["ellipsoids"]]
