"""Reading CT scans into a geometry-exact slice stack: DICOM series, NIfTI volumes, TIFF stacks.

Every reader returns a :class:`SliceStack`: a float32 array ``data[i, j, k]`` plus the full geometry of
each slice in the world frame (RAS+, mm; see ``docs/conventions.md``). DICOM patient coordinates are
LPS; the conversion ``(x, y, z)_RAS = (-x, -y, z)_LPS`` happens exactly once, here, in
:func:`lps_to_ras`. Nothing downstream sees LPS.

Geometry of a slice stack (all vectors in world RAS, mm)::

    world(i, j, k) = origins[k] + i * spacing_ij[0] * row_dir + j * spacing_ij[1] * col_dir

``row_dir`` (DICOM: first ImageOrientationPatient triplet) is the direction of increasing column
index ``i``; ``col_dir`` (second triplet) the direction of increasing row index ``j``. Slices are
sorted by ``origins[k] @ normal`` (strictly increasing), where ``normal`` is the unit vector
perpendicular to the slice plane pointing towards increasing ``k``. Gantry tilt shows up as an
in-plane drift of ``origins[k]``; non-uniform slice spacing as non-uniform ``positions_mm``. Both are
resolved exactly (in world coordinates) by :func:`ctsplat.volume.resample_stack`, so the reader
never assumes a regular grid along ``k``.

For DICOM this is the Image Plane module's mapping [1]_ ``P = S + i Δi X + j Δj Y`` (LPS), with
``S`` = ImagePositionPatient of the slice, ``X`` / ``Y`` = the row / column direction cosines of
ImageOrientationPatient, ``Δi`` = column spacing (PixelSpacing[1]) and ``Δj`` = row spacing
(PixelSpacing[0]), then converted to RAS. Stored pixel values become HU through the CT Image
module's ``HU = stored * RescaleSlope + RescaleIntercept`` [2]_. For NIfTI the slice geometry is
the image's affine (sform, else qform) [3]_, already RAS.

De-identification: ``SliceStack.source`` holds geometry and acquisition facts only (modality,
scanner model, kVp, spacing ...). UIDs appear only as keyed hashes with a private key (:func:`salted_hash`);
patient, study-date and institution fields and file names (often SOP Instance UIDs) are never
copied. The same holds for log lines, warnings, error messages and series listings: a series is
named by its :attr:`SeriesInfo.id` (the salted hash of its SeriesInstanceUID, as in the
provenance), and pydicom's own warnings, which quote offending header values verbatim, are muted
while headers are read.

References
----------
.. [1] DICOM PS3.3 "Information Object Definitions", C.7.6.2 Image Plane Module, C.7.6.2.1.1 Image
   Position and Image Orientation (Equation C.7.6.2.1-1),
   https://dicom.nema.org/medical/dicom/current/output/chtml/part03/sect_C.7.6.2.html
.. [2] DICOM PS3.3, C.8.2.1 CT Image Module (Rescale Intercept (0028,1052), Rescale Slope (0028,1053))
   and C.11.1 Modality LUT Module.
.. [3] R. W. Cox et al., "A (sort of) new image data format standard: NIfTI-1", NIfTI Data Format
   Working Group, 2004 (qform / sform, ``nifti1.h``), https://nifti.nimh.nih.gov/nifti-1/
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import logging
import os
import re
import secrets
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.utils import CtsplatError, LoggedWarning

__all__ = [
    "NIFTI_SUFFIXES",
    "NIFTI_UNIT_MM",
    "SCAN_FILE_SUFFIXES",
    "source_kind",
    "TIFF_SUFFIXES",
    "SliceStack",
    "SeriesInfo",
    "SliceGapWarning",
    "missing_slice_gaps",
    "LPS_TO_RAS",
    "lps_to_ras",
    "salted_hash",
    "deid_key",
    "outputs_selector",
    "selector_key",
    "find_dicom_series",
    "select_series",
    "read_dicom_series",
    "read_nifti",
    "read_tiff_stack",
    "read_source",
    "write_dicom_series",
    "looks_like_hu",
    "check_rescale",
]

log = logging.getLogger(__name__)

#: File names :func:`read_source` reads as one scan (a folder is a DICOM series or a TIFF-slice folder).
NIFTI_SUFFIXES = (".nii", ".nii.gz")
TIFF_SUFFIXES = (".tif", ".tiff")
SCAN_FILE_SUFFIXES = NIFTI_SUFFIXES + TIFF_SUFFIXES

#: Diagonal LPS <-> RAS flip (its own inverse).
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])

#: Tolerances for geometry consistency checks.
_ORIENT_TOL = 1e-4  # on direction cosines
_SPACING_RTOL = 1e-4  # relative, pixel spacing across slices
_DUPLICATE_TOL_MM = 1e-3  # two slices closer than this along the normal are duplicates

#: CT stored values without RescaleSlope/RescaleIntercept are taken as HU only when they look like HU
#: (see :func:`looks_like_hu`): at least this fraction of the voxels is air, within this HU range ...
_AIR_FRACTION_MIN = 1e-3
_AIR_HU = (-1100.0, -900.0)
#: ... and no value reaches this (12-bit HU data ends at 3071; raw unsigned values run to 4095).
_HU_MAX_PLAUSIBLE = 4000.0

#: A gap between neighbouring slices larger than this multiple of the series' median gap means slices are
#: missing (a 9 mm gap in a 1.5 mm series); smaller irregularities (the odd 1.0 mm step) are normal.
_MISSING_GAP_FACTOR = 1.5
#: How many gaps one warning names before it only counts the rest.
_GAPS_NAMED = 5

#: A DICOM UID: digit groups separated by dots (used to keep UIDs a user typed out of messages).
_UID_RE = re.compile(r"^\s*\d+(\.\d+)+\s*$")
#: The selectors that may be shown and stored as typed: a listed series id (16 hex digits) or a series number.
_PLAIN_SELECTOR_RE = re.compile(r"^([0-9a-fA-F]{16}|\d{1,12})$")
#: What a UID copied from a DICOM dump or a spreadsheet may bring around it.
_SELECTOR_WRAPPING = " \t[]()<>'\"`"

_DECODER_PACKAGES = {
    "1.2.840.10008.1.2.4.90": "pylibjpeg and pylibjpeg-openjpeg",  # JPEG 2000 lossless
    "1.2.840.10008.1.2.4.91": "pylibjpeg and pylibjpeg-openjpeg",  # JPEG 2000
    "1.2.840.10008.1.2.4.201": "pylibjpeg and pylibjpeg-openjpeg",  # HTJ2K lossless
    "1.2.840.10008.1.2.4.202": "pylibjpeg and pylibjpeg-openjpeg",
    "1.2.840.10008.1.2.4.203": "pylibjpeg and pylibjpeg-openjpeg",
    "1.2.840.10008.1.2.4.50": "pylibjpeg and pylibjpeg-libjpeg",  # JPEG baseline
    "1.2.840.10008.1.2.4.51": "pylibjpeg and pylibjpeg-libjpeg",
    "1.2.840.10008.1.2.4.57": "pylibjpeg and pylibjpeg-libjpeg",  # JPEG lossless
    "1.2.840.10008.1.2.4.70": "pylibjpeg and pylibjpeg-libjpeg",
    "1.2.840.10008.1.2.4.80": "pylibjpeg and pylibjpeg-libjpeg",  # JPEG-LS
    "1.2.840.10008.1.2.4.81": "pylibjpeg and pylibjpeg-libjpeg",
    "1.2.840.10008.1.2.5": "pylibjpeg and pylibjpeg-rle",  # RLE
}


def lps_to_ras(v: np.ndarray) -> np.ndarray:
    """Convert points or directions from DICOM patient coordinates (LPS) to the world frame (RAS).

    Parameters
    ----------
    v : array_like, shape (..., 3)
        Points (mm) or direction vectors in LPS.

    Returns
    -------
    ndarray, shape (..., 3), float
        The same points/vectors in RAS: ``(x, y, z) -> (-x, -y, z)``.
    """
    return np.asarray(v, dtype=float) @ LPS_TO_RAS


DEID_KEY_ENV = "CTSPLAT_DEID_SALT"
_DEID_KEY_MIN_BYTES = 16


def deid_key() -> bytes:
    """The secret key of :func:`salted_hash`: ``$CTSPLAT_DEID_SALT``, else this user's private random key.

    The private key (32 random bytes) lives in ``$XDG_CONFIG_HOME/ctsplat/deid_key`` (default
    ``~/.config/ctsplat/deid_key``, mode 0600) and is created on first use. A key that ships with the code would
    not protect anything: DICOM UIDs are built from a scanner's root, serial number and the acquisition time, so
    a reader who knows the key recovers a UID — and with it the study date and time — from its hash by trying the
    plausible ones. Set ``CTSPLAT_DEID_SALT`` to one private value to get the same series ids on several machines.

    Returns
    -------
    bytes

    Raises
    ------
    CtsplatError
        When the key file cannot be read or created (names the file and the variable to set instead).
    """
    env = os.environ.get(DEID_KEY_ENV, "").encode()
    if env:
        if len(env) < _DEID_KEY_MIN_BYTES:  # a short value is found by trying them all
            raise CtsplatError(f"{DEID_KEY_ENV} is too short ({len(env)} bytes); set it to a private random value of "
                               f"at least {_DEID_KEY_MIN_BYTES} characters (e.g. `openssl rand -hex 16`), or unset "
                               "it to use this user's own key")
        return env
    home = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    path = Path(home) / "ctsplat" / "deid_key"
    try:
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".deid_key.{os.getpid()}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "wb") as fh:
                fh.write(secrets.token_bytes(32))
            try:
                os.link(tmp, path)  # fails if another process created the key first: then theirs is used
            except FileExistsError:
                pass
            finally:
                tmp.unlink()
        key = path.read_bytes()
    except OSError as exc:
        raise CtsplatError(f"cannot read or create the de-identification key {path} ({exc.strerror or exc}); set "
                           f"{DEID_KEY_ENV} to a private value instead") from None
    if len(key) < _DEID_KEY_MIN_BYTES:
        raise CtsplatError(f"the de-identification key {path} is too short ({len(key)} bytes); delete it to make "
                           f"a new one, or set {DEID_KEY_ENV}")
    return key


def salted_hash(value: str, n: int = 16) -> str:
    """Keyed hash of an identifier: HMAC-SHA-256 with the private key of :func:`deid_key`.

    Deterministic for one key (one user, or one ``CTSPLAT_DEID_SALT``), and not reversible without it.

    Parameters
    ----------
    value : str
        The identifier (e.g. a SeriesInstanceUID).
    n : int
        Number of hexadecimal digits kept.

    Returns
    -------
    str
        ``n`` hex digits of ``HMAC-SHA-256(key, value)``.
    """
    return hmac.new(deid_key(), value.encode(), hashlib.sha256).hexdigest()[:n]


def outputs_selector(selector: str | None) -> str | None:
    """A series selector as it may be stored beside outputs: a raw SeriesInstanceUID becomes its id.

    :func:`select_series` finds a series by its id as by its UID, so the workflow hands this form to the ingest
    step and no UID reaches the workflow's own records (Snakemake stores every rule's parameters).

    Parameters
    ----------
    selector : str or None
        A series id, SeriesInstanceUID or SeriesNumber.

    Returns
    -------
    str or None
        A series id or number as given (:func:`selector_key`); anything else, a UID above all, as its
        :func:`salted_hash`.

    Examples
    --------
    >>> outputs_selector("3"), outputs_selector(None)
    ('3', None)
    >>> outputs_selector("[1.2.840.113619.2.55.3]") == salted_hash("1.2.840.113619.2.55.3")
    True
    """
    if selector is None:
        return None
    key = selector_key(selector)
    return key if _is_plain_selector(key) else salted_hash(key)


def _is_plain_selector(key: str) -> bool:
    """Whether an unwrapped selector may be shown and stored as typed: a listed series id or a series number."""
    return bool(_PLAIN_SELECTOR_RE.match(key))


def selector_key(selector: str) -> str:
    """A series selector without what a copied UID may bring around it (spaces, brackets, quotes, a final dot).

    Parameters
    ----------
    selector : str
        A series id, SeriesInstanceUID or SeriesNumber, as typed.

    Returns
    -------
    str

    Examples
    --------
    >>> selector_key(" [1.2.840.113619.2.55.3] "), selector_key("'1.2.3.'"), selector_key("0007")
    ('1.2.840.113619.2.55.3', '1.2.3', '0007')
    """
    key = str(selector).strip(_SELECTOR_WRAPPING)
    return key[:-1] if _UID_RE.match(key[:-1]) and key.endswith(".") else key


class SliceGapWarning(LoggedWarning):
    """A DICOM series has gaps between slices much larger than its spacing (slices probably missing)."""


def missing_slice_gaps(positions_mm: Sequence[float] | np.ndarray) -> tuple[float, list[dict[str, Any]]]:
    """Find gaps between sorted slice positions that are too large for the series' spacing.

    A gap counts as missing slices when it exceeds ``1.5`` times the median gap (the nominal
    spacing): a 9 mm gap in a 1.5 mm series (about 5 slices lost in the export) is one, the odd
    1.0 mm step of a 1.5 mm series is not.

    Parameters
    ----------
    positions_mm : (K,) floats
        Slice positions along the slice normal (mm), strictly increasing.

    Returns
    -------
    nominal_mm : float
        The median gap (0.0 for fewer than 2 slices).
    gaps : list of dict
        One record per gap, in slice order: ``between_slices`` (sorted indices ``[k, k + 1]``),
        ``positions_mm`` (the two slice positions), ``gap_mm`` and ``approx_missing_slices``
        (``round(gap / nominal) - 1``, at least 1). JSON-serialisable.
    """
    pos = np.asarray(positions_mm, float)
    if pos.size < 2:
        return 0.0, []
    diffs = np.diff(pos)
    nominal = float(np.median(diffs))
    if nominal <= 0:
        return nominal, []
    gaps = []
    for k in np.flatnonzero(diffs > _MISSING_GAP_FACTOR * nominal):
        g = float(diffs[k])
        gaps.append({
            "between_slices": [int(k), int(k) + 1],
            "positions_mm": [round(float(pos[k]), 3), round(float(pos[k + 1]), 3)],
            "gap_mm": round(g, 3),
            "approx_missing_slices": max(1, int(round(g / nominal)) - 1),
        })
    return nominal, gaps


def _warn_gaps(nominal: float, gaps: list[dict[str, Any]], n_slices: int, what: str) -> None:
    """One warning (``warnings.warn`` and the log) naming each large gap, its size and where it is."""
    if not gaps:
        return
    named = "; ".join(
        f"{g['gap_mm']:g} mm between slices {g['between_slices'][0]} and {g['between_slices'][1]} "
        f"(at {g['positions_mm'][0]:g} and {g['positions_mm'][1]:g} mm along the slice normal, "
        f"~{g['approx_missing_slices']} slice(s) missing)"
        for g in gaps[:_GAPS_NAMED]
    )
    more = f"; and {len(gaps) - _GAPS_NAMED} more" if len(gaps) > _GAPS_NAMED else ""
    msg = (
        f"{what} ({n_slices} slices, spacing {nominal:g} mm) has {len(gaps)} gap(s) larger than "
        f"{_MISSING_GAP_FACTOR:g}x its spacing, filled by linear interpolation: {named}{more}; slices are "
        f"probably missing - check the export is complete (recorded in volume.json source.missing_slice_gaps)"
    )
    log.warning("%s", msg)
    warnings.warn(msg, SliceGapWarning, stacklevel=3)


def _shown(value: str) -> str:
    """A series selector as it may appear in a message: a series id or number as typed, anything else (a DICOM
    UID, identifying, in whatever wrapping) only as its salted hash."""
    key = selector_key(value)
    if _is_plain_selector(key):
        return repr(key)
    what = "SeriesInstanceUID" if _UID_RE.match(key) else "series selector"
    return f"<{what} with hash {salted_hash(key)}>"


def looks_like_hu(values: np.ndarray) -> bool:
    """Whether values that came without a rescale can be taken as Hounsfield units of a CT scan.

    The rule: air is present (at least 0.1 % of the values within -1000 ± 100 HU; every CT field of
    view holds air around the body, in the airways or the sinuses) and no value reaches 4000 (the
    usual 12-bit HU range ends at 3071). Stored values that still need an intercept (typically
    ``HU + 1024``, unsigned, 0 .. 4095) have their air near 0 - 24 and fail the first test; the
    second catches raw values of other encodings that happen to reach below -900.

    Parameters
    ----------
    values : ndarray, any shape
        Stored values (finite).

    Returns
    -------
    bool
    """
    v = np.asarray(values)
    if v.size == 0:
        return False
    air = np.count_nonzero((v >= _AIR_HU[0]) & (v <= _AIR_HU[1]))
    return bool(air >= _AIR_FRACTION_MIN * v.size and float(v.max()) < _HU_MAX_PLAUSIBLE)


def check_rescale(rescale: Sequence[float] | None) -> tuple[float, float] | None:
    """Validate a user-given rescale for DICOM slices that lack RescaleSlope/RescaleIntercept.

    Parameters
    ----------
    rescale : (2,) floats or None
        ``[slope, intercept]``: ``HU = stored * slope + intercept``.

    Returns
    -------
    (float, float) or None
        ``(slope, intercept)``, or ``None`` when ``rescale`` is ``None``.
    """
    if rescale is None:
        return None
    try:
        slope, intercept = (float(x) for x in rescale)
    except (TypeError, ValueError):
        raise CtsplatError(f"rescale must be [slope, intercept] (two numbers), got {rescale!r}") from None
    if not (np.isfinite(slope) and np.isfinite(intercept) and slope != 0):
        raise CtsplatError(f"rescale [slope, intercept] must be finite with slope != 0, got {rescale!r}")
    return slope, intercept


@dataclass
class SliceStack:
    """A scan as read from disk, before resampling (see the module docstring for the geometry).

    Attributes
    ----------
    data : ndarray, shape (I, J, K), float32
        Values (HU when ``units == "hu"``); ``data[:, :, k]`` is slice ``k``.
    row_dir, col_dir : ndarray, shape (3,)
        Unit vectors (world RAS) of increasing ``i`` and ``j``; orthogonal.
    spacing_ij : tuple of float
        Pixel spacing (mm) along ``i`` and ``j``.
    origins : ndarray, shape (K, 3)
        World position (RAS, mm) of voxel ``(0, 0, k)``'s centre, sorted along ``normal``.
    units : str
        ``"hu"`` (Hounsfield units) or ``"raw"`` (scanner/intensity units of a non-CT source).
    source : dict
        De-identified description of the input (JSON-serialisable).
    """

    data: np.ndarray
    row_dir: np.ndarray
    col_dir: np.ndarray
    spacing_ij: tuple[float, float]
    origins: np.ndarray
    units: str = "hu"
    source: dict[str, Any] = field(default_factory=dict)

    @property
    def normal(self) -> np.ndarray:
        """Unit slice normal (RAS) pointing towards increasing ``k``, shape (3,)."""
        n = np.cross(self.row_dir, self.col_dir)
        n = n / np.linalg.norm(n)
        if len(self.origins) > 1 and float((self.origins[-1] - self.origins[0]) @ n) < 0:
            n = -n
        return n

    @property
    def positions_mm(self) -> np.ndarray:
        """Slice positions along ``normal`` (mm), shape (K,), strictly increasing."""
        return self.origins @ self.normal

    @property
    def tilt_deg(self) -> float:
        """Angle between the slice stacking direction and the slice normal (gantry tilt), degrees."""
        if len(self.origins) < 2:
            return 0.0
        d = self.origins[-1] - self.origins[0]
        c = float(abs(d @ self.normal) / np.linalg.norm(d))
        return float(np.degrees(np.arccos(min(1.0, c))))


# --------------------------------------------------------------------------------------------------
# DICOM
# --------------------------------------------------------------------------------------------------


@dataclass
class SeriesInfo:
    """Header facts of one DICOM series found in a folder.

    Attributes
    ----------
    uid : str
        The real SeriesInstanceUID (empty when the files have none); never written to outputs, logs
        or messages (and kept out of ``repr``).
    files : list of Path
        The series' image files, in directory-walk order.
    modality, number : str
        Modality and SeriesNumber of the first file (not its SeriesDescription: free text that may name the
        patient).
    id : str
        The series' identifier in listings, logs and messages, and the value to select it by: the
        salted hash of ``uid`` (:func:`salted_hash`, the provenance's ``series_uid_hash``), or for
        files without a SeriesInstanceUID the salted hash of the header facts they were grouped by.
    """

    uid: str = field(repr=False)
    files: list[Path]
    modality: str
    number: str
    id: str = ""

    def __post_init__(self) -> None:
        if not self.id:
            self.id = salted_hash(self.uid) if self.uid else salted_hash("no-SeriesInstanceUID")

    def label(self) -> str:
        """One-line description for listings and error messages: the series is named by its ``id``, never by its
        UID."""
        no_uid = ", no SeriesInstanceUID" if not self.uid else ""
        return f"{self.id} (#{self.number or '?'}, {self.modality or '?'}, {len(self.files)} files{no_uid})"


@contextlib.contextmanager
def _quiet_pydicom() -> Iterator[None]:
    """Mute pydicom while headers are read: its warnings and log lines quote invalid values (UIDs, names) verbatim.

    Value validation is switched off (IGNORE), warnings are ignored and the ``pydicom`` logger is
    disabled; all three are restored on exit. Warnings ctsplat itself raises are issued outside.
    """
    import pydicom.config as cfg

    mode = cfg.settings.reading_validation_mode
    logger = logging.getLogger("pydicom")
    disabled = logger.disabled
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cfg.settings.reading_validation_mode = cfg.IGNORE
        logger.disabled = True
        try:
            yield
        finally:
            cfg.settings.reading_validation_mode = mode
            logger.disabled = disabled


def _text(ds: Any, key: str) -> str:
    return str(ds.get(key, "") or "")


def _dcmread(path: Path, *, stop_before_pixels: bool) -> Any:
    import pydicom
    from pydicom.errors import InvalidDicomError

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return pydicom.dcmread(path, stop_before_pixels=stop_before_pixels)
        except InvalidDicomError:
            # Old files without the 128-byte preamble: accept only if they look like images.
            try:
                ds = pydicom.dcmread(path, stop_before_pixels=stop_before_pixels, force=True)
            except Exception:  # noqa: BLE001 - anything unreadable is "not DICOM" here
                return None
            if "SOPClassUID" in ds and "Rows" in ds and "ImagePositionPatient" in ds:
                return ds
            return None


def _is_image_sop(ds: Any) -> bool:
    sops = (ds.get("SOPClassUID"), getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", None))
    return any("Image Storage" in (getattr(sop, "name", "") or "") for sop in sops)


def _walk_files(folder: Path) -> list[Path]:
    files = [Path(root) / f for root, _, names in os.walk(folder) for f in names]
    return sorted(p for p in files if p.is_file() and not p.name.startswith("."))


class _FileLabels:
    """Names a file of the input folder by its place in path order, never by its name (DICOM file names are often
    SOP Instance UIDs, which carry the acquisition date and time) nor by the folder's path (the warnings that use
    these labels reach the workflow's logs, and an export's folders may be named after the patient)."""

    def __init__(self, folder: Path, files: list[Path]) -> None:
        self.folder = folder
        self.n = len(files)
        self.place = {p: i + 1 for i, p in enumerate(files)}

    def __call__(self, path: Path) -> str:
        return f"file {self.place[path]} of {self.n} in the input folder (in sorted path order)"


#: Header fields that tell series without a SeriesInstanceUID apart (hashed into their id, never shown).
_NO_UID_KEYS = ("StudyInstanceUID", "FrameOfReferenceUID", "SeriesNumber", "Modality", "SeriesDescription")


def _why(exc: BaseException, *, with_type: bool = True, limit: int = 160) -> str:
    """An exception's first line, shortened at a word boundary (pydicom's messages can run to paragraphs), with
    the raw values a reader's message may quote taken out: byte strings (a damaged element's value) and UIDs.

    Examples
    --------
    >>> _why(ValueError("fewer bytes than expected\\nsecond line"), limit=18)
    'ValueError: fewer bytes than ...'
    >>> _why(ValueError("Expected total bytes to be an even multiple of bytes per value. Instead received "
    ...                 "b'DOE^JANE' with length 8"), with_type=False)
    'Expected total bytes to be an even multiple of bytes per value. Instead received <bytes> with length 8'
    >>> _why(KeyError("1.3.12.2.1107.5.1.1.20707.20020604104421111.3"), with_type=False)
    "'<UID>'"
    >>> _why(PermissionError(13, "Permission denied", "/in/PAT_DOE_JANE/IM0001"))
    'PermissionError: Permission denied'

    An operating-system error names the file's path, whose folders an export may name after the patient: only its
    reason is kept (the caller names the file by its position).
    """
    if isinstance(exc, OSError) and exc.strerror:
        return f"{type(exc).__name__}: {exc.strerror}" if with_type else exc.strerror
    text = str(exc).split("\n")[0]
    text = re.sub(r"""b(['"]).*?(?<!\\)\1""", "<bytes>", text)
    text = re.sub(r"\d+(?:\.\d+){3,}", "<UID>", text)
    if len(text) > limit:
        text = text[:limit].rsplit(" ", 1)[0] + " ..."
    return f"{type(exc).__name__}: {text}" if with_type else text


def _handle_corrupt(path: Path, label: str, why: str, skip_corrupt: bool, skipped: list[Path]) -> None:
    if not skip_corrupt:
        raise CtsplatError(
            f"corrupt or truncated DICOM file: {label} ({why}); remove it or pass skip_corrupt "
            f"(--skip-corrupt) to ignore it with a warning"
        )
    log.warning("skipping corrupt DICOM file: %s (%s)", label, why)
    skipped.append(path)


def find_dicom_series(
    folder: str | Path, *, skip_corrupt: bool = False, _skipped: list[Path] | None = None
) -> list[SeriesInfo]:
    """Walk ``folder`` recursively and group DICOM image files by SeriesInstanceUID (headers only).

    Non-DICOM files and non-image DICOM objects (DICOMDIR, reports) are ignored. A file that starts
    as a DICOM image but is cut short is corrupt: an error naming it, or with ``skip_corrupt`` a
    warning.

    Parameters
    ----------
    folder : path
        Folder to search (sub-folders included; hidden files skipped).
    skip_corrupt : bool
        Skip corrupt files with a warning instead of failing.

    Returns
    -------
    list of SeriesInfo
        The series found, sorted by decreasing number of files.
    """
    folder = Path(folder)
    if not folder.exists():
        raise CtsplatError(f"input {folder} does not exist; give a DICOM folder, a .nii/.nii.gz file or a TIFF stack")
    if not folder.is_dir():
        raise CtsplatError(f"input {folder} is a file, not a DICOM folder; give the folder that holds the DICOM slices")
    files = _walk_files(folder)
    if not files:
        raise CtsplatError(f"input folder {folder} is empty; point ingest at a folder that contains DICOM slices")
    skipped = _skipped if _skipped is not None else []
    label = _FileLabels(folder, files)
    groups: dict[tuple[str, ...], SeriesInfo] = {}
    with _quiet_pydicom():  # header values are read here; pydicom would quote invalid ones
        for path in files:
            try:
                ds = _dcmread(path, stop_before_pixels=True)
                # pydicom decodes elements when first read: a damaged one fails here, not at parse time
                facts = None if ds is None else _series_facts(ds)
            except Exception as exc:  # noqa: BLE001 - DICOM prefix present but the header does not parse
                _handle_corrupt(path, label(path), _why(exc), skip_corrupt, skipped)
                continue
            if facts is None:
                continue  # not DICOM, or DICOMDIR, structured report, presentation state ...
            if not facts:
                _handle_corrupt(path, label(path), "image header ends before Rows/Columns", skip_corrupt, skipped)
                continue
            key = facts["key"]
            info = groups.get(key)
            if info is None:
                uid = facts["uid"]
                info = groups[key] = SeriesInfo(
                    uid=uid,
                    files=[],
                    modality=facts["modality"],
                    number=facts["number"],
                    id=salted_hash(uid) if uid else salted_hash("\x1f".join(key)),
                )
            info.files.append(path)
    if not groups:
        raise CtsplatError(
            f"no DICOM image files found in {folder} ({len(files)} other files); "
            f"point ingest at the folder holding the .dcm slices"
        )
    return sorted(groups.values(), key=lambda s: (-len(s.files), s.id))


def _series_facts(ds: Any) -> dict[str, Any] | None:
    """What :func:`find_dicom_series` groups a file by: None for a file that is not an image, an empty dict for
    an image header without Rows/Columns, else ``uid``, ``key``, ``modality`` and ``number``."""
    if not _is_image_sop(ds) and "Rows" not in ds:
        return None
    if "Rows" not in ds or "Columns" not in ds:
        return {}
    uid = _text(ds, "SeriesInstanceUID").strip()
    if uid:
        key: tuple[str, ...] = ("uid", uid)
    else:
        # No SeriesInstanceUID: keep series apart by what else identifies them, so each stays choosable.
        key = ("no-SeriesInstanceUID", *(_text(ds, k) for k in _NO_UID_KEYS), str(ds.get("Rows")),
               str(ds.get("Columns")))
    return {"uid": uid, "key": key, "modality": _text(ds, "Modality"), "number": _text(ds, "SeriesNumber")}


def select_series(series: Sequence[SeriesInfo], selector: str) -> list[SeriesInfo]:
    """The series a user's selector names: its ``id`` (as listed), its SeriesInstanceUID, or its SeriesNumber.

    Parameters
    ----------
    series : sequence of SeriesInfo
        The series found (:func:`find_dicom_series`).
    selector : str
        The ``id`` shown by ``ctsplat ingest --list-series`` (the salted hash, case-insensitive), the
        raw SeriesInstanceUID, or the SeriesNumber.

    Returns
    -------
    list of SeriesInfo
        The matches: by ``id`` or UID first (at most one), else every series with that number (compared as
        integers, as DICOM's IS type holds them: ``2`` and ``000002`` name the same series).
    """
    key = selector_key(selector)
    exact = [s for s in series if key.lower() == s.id.lower() or (s.uid and key == s.uid)]
    return exact or [s for s in series if s.number and _same_number(key, s.number)]


def _same_number(a: str, b: str) -> bool:
    """Whether two SeriesNumber texts name the same integer (exact text when either is not one)."""
    try:
        return int(a) == int(b)
    except ValueError:
        return a == b


def _choose_series(
    series: list[SeriesInfo], series_uid: str | None, allow_modalities: Sequence[str], folder: Path
) -> SeriesInfo:
    listing = "; ".join(s.label() for s in series)
    if series_uid is not None:
        chosen = select_series(series, str(series_uid))
        if not chosen:
            raise CtsplatError(
                f"series {_shown(str(series_uid))} not found in {folder}; give the id of one of the series found "
                f"(series_uid / --series-uid; `ctsplat ingest {folder} --list-series` lists them): {listing}"
            )
        if len(chosen) > 1:
            raise CtsplatError(
                f"series number {_shown(str(series_uid))} is ambiguous in {folder}; give the series id instead: "
                f"{'; '.join(s.label() for s in chosen)}"
            )
        pick = chosen[0]
    else:
        allowed = [s for s in series if s.modality.upper() in {m.upper() for m in allow_modalities}]
        if not allowed:
            mods = sorted({s.modality or "?" for s in series})
            raise CtsplatError(
                f"no {'/'.join(allow_modalities)} series in {folder} (found modality {', '.join(mods)}); "
                f"ingest expects CT in HU - to read it anyway pass allow_modalities (--allow-modality {mods[0]})"
            )
        top = [s for s in allowed if len(s.files) == len(allowed[0].files)]
        if len(top) > 1:
            raise CtsplatError(
                f"{len(allowed)} series in {folder} and no unique largest one; choose one by its id with "
                f"series_uid (--series-uid ID): {listing}"
            )
        pick = allowed[0]
        if len(series) > 1:
            log.warning(
                "%d series in the input folder; using the largest %s one, %s (choose another with series_uid / "
                "--series-uid ID): %s", len(series), pick.modality or "?", pick.id, listing,
            )
    if pick.modality.upper() not in {m.upper() for m in allow_modalities}:
        raise CtsplatError(
            f"series {pick.label()} has modality {pick.modality or '?'}, not {'/'.join(allow_modalities)}; ingest "
            f"expects CT in HU - pass allow_modalities (--allow-modality {pick.modality}) to read it anyway"
        )
    return pick


def _check_decoder(ds: Any, label: str) -> None:
    """Fail with the package to install when a compressed transfer syntax cannot be decoded."""
    ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    if ts is None:
        return
    try:
        compressed = ts.is_compressed
    except ValueError:  # pydicom: "UID is not a transfer syntax"
        raise CtsplatError(f"{label}: its TransferSyntaxUID is not a transfer syntax (a damaged file meta header); "
                           "re-export the file or remove it") from None
    if not compressed:
        return
    from pydicom.pixels.decoders.base import get_decoder

    try:
        decoder = get_decoder(ts)
    except NotImplementedError:
        raise CtsplatError(f"{label}: transfer syntax {ts.name} ({ts}) is not supported by pydicom") from None
    if not decoder.is_available:
        pkg = _DECODER_PACKAGES.get(str(ts), "a pydicom pixel-data plugin (pylibjpeg or gdcm)")
        # the j2k extra holds the JPEG 2000 decoder only; the other plugins are named as pip installs them
        how = ("pip install 'ctsplat[j2k]'" if "openjpeg" in pkg else
               f"pip install {pkg.replace(' and ', ' ')}" if pkg.startswith("pylibjpeg") else "see pydicom's docs")
        raise CtsplatError(f"{label} is compressed ({ts.name}) and no decoder is installed; install {pkg} ({how})")


def _optional_number(value: Any) -> float | None:
    """A descriptive header number (KVP, SliceThickness) as a float; None when absent or not one number (``"140kV"``,
    a dual-energy ``80\\140``): such fields are recorded, never used."""
    try:
        return float(value) if value not in (None, "") else None
    except (TypeError, ValueError):
        return None


def _header_int(ds: Any, key: str, label: str) -> int:
    """An integer header field that decides how a file is read (NumberOfFrames, SamplesPerPixel); 1 when absent."""
    value = ds.get(key, 1)
    try:
        return int(value or 1)
    except (TypeError, ValueError):
        raise CtsplatError(f"{label} has an invalid {key} (not an integer); fix the header or re-export the "
                           "series") from None


def _vec(ds: Any, key: str, n: int, label: str) -> np.ndarray:
    value = ds.get(key)
    if value is not None:
        try:  # one number where n were expected has no length: pydicom hands a malformed value over as it is
            count = 1 if isinstance(value, str | bytes) else len(value)
        except TypeError:
            count = 1
        if count != n:
            raise CtsplatError(f"{label} has an invalid {key} (need {n} values, it holds {count}); fix the header "
                               "or re-export the series")
    else:
        hint = {
            "ImagePositionPatient": "slice positions cannot be derived; re-export the series with geometry tags",
            "ImageOrientationPatient": "slice orientation is unknown; re-export the series with geometry tags",
            "PixelSpacing": "pixel size is unknown; re-export the series with PixelSpacing",
        }[key]
        raise CtsplatError(f"{label} has no {key}: {hint}")
    try:
        out = np.asarray([float(v) for v in value], dtype=float)
    except (TypeError, ValueError):
        out = np.full(n, np.nan)
    if not np.all(np.isfinite(out)) or (key == "PixelSpacing" and np.any(out <= 0)):
        need = "positive numbers (mm)" if key == "PixelSpacing" else "finite numbers"
        raise CtsplatError(f"{label} has an invalid {key} (need {n} {need}); fix the header or re-export the series")
    return out


def _padding_mask(ds: Any, pixels: np.ndarray) -> tuple[np.ndarray, tuple[int, int]] | None:
    """The slice's padding pixels (PixelPaddingValue, up to PixelPaddingRangeLimit) as stored, or None.

    Returns
    -------
    (mask, (value, limit)) or None
        ``mask`` (Rows, Columns) bool; ``value`` and ``limit`` in stored units (``limit == value`` without a
        range). None when the slice has no PixelPaddingValue or no pixel equals it.
    """
    if ds.get("PixelPaddingValue") in (None, ""):
        return None
    bits = int(ds.get("BitsAllocated", 16) or 16)

    def stored(v: Any) -> int:
        # the tag's VR is US or SS by PixelRepresentation; a signed value read as unsigned wraps around
        v = int(v)
        return v - (1 << bits) if int(ds.get("PixelRepresentation", 0) or 0) == 1 and v >= 1 << (bits - 1) else v

    value = stored(ds.PixelPaddingValue)
    limit = stored(ds.PixelPaddingRangeLimit) if ds.get("PixelPaddingRangeLimit") not in (None, "") else value
    lo, hi = min(value, limit), max(value, limit)
    mask = (pixels >= lo) & (pixels <= hi)
    return (mask, (value, limit)) if mask.any() else None


def _fill_padding(slices: list[tuple[Path, Any, np.ndarray]], padding: dict[int, np.ndarray],
                  values: set[tuple[int, int]]) -> dict[str, Any] | None:
    """Give the padding pixels (outside the reconstructed field of view) the series' smallest other value.

    Padding marks pixels that hold no measurement (DICOM PS3.3 C.7.5.1.1.2); kept as values (often -2000
    stored, -3024 HU) they would be blurred into the edge voxels by the resampling and enlarge a body mask.
    The smallest value the scanner did measure (air) takes their place, in place in ``slices``.

    Returns
    -------
    dict or None
        ``value`` / ``range_limit`` (stored units), ``n_pixels`` and ``filled_with`` (the volume's units); None
        without padding.
    """
    if not padding:
        return None
    measured = [float(np.min(v if i not in padding else v[~padding[i]])) for i, (_, _, v) in enumerate(slices)
                if i not in padding or not padding[i].all()]
    if not measured:
        raise CtsplatError("every pixel of the series is PixelPaddingValue padding; there is no image to ingest")
    fill = min(measured)
    for i, mask in padding.items():
        slices[i][2][mask] = fill
    (value, limit), *more = sorted(values)
    return {"value": value, "range_limit": limit, "n_pixels": int(sum(int(m.sum()) for m in padding.values())),
            "filled_with": fill, **({"other_values": [list(v) for v in more]} if more else {})}


def _rescale(ds: Any, label: str) -> tuple[float, float] | None:
    """The slice's ``(RescaleSlope, RescaleIntercept)``, None when either tag is absent or empty."""
    if ds.get("RescaleSlope") in (None, "") or ds.get("RescaleIntercept") in (None, ""):
        return None
    try:
        slope, intercept = float(ds.RescaleSlope), float(ds.RescaleIntercept)
    except (TypeError, ValueError):
        slope = intercept = float("nan")
    if not (np.isfinite(slope) and np.isfinite(intercept)) or slope == 0:
        raise CtsplatError(f"{label} has an invalid RescaleSlope/RescaleIntercept (need finite numbers, a non-zero "
                           "slope); fix the header, or remove the tags and pass rescale (--rescale SLOPE INTERCEPT)")
    return slope, intercept


def read_dicom_series(
    folder: str | Path,
    *,
    series_uid: str | None = None,
    allow_modalities: Sequence[str] = ("CT",),
    skip_corrupt: bool = False,
    rescale: Sequence[float] | None = None,
) -> SliceStack:
    """Read one DICOM series from a folder (searched recursively) into a :class:`SliceStack`.

    Steps: group files by SeriesInstanceUID, choose the series (``series_uid`` = the series id shown
    by ``--list-series``, the UID itself or the SeriesNumber, see :func:`select_series`; otherwise the
    allowed-modality series with most files, an error when that is ambiguous), check the geometry is
    consistent, order slices by ``IPP · n`` with ``n = row_cos × col_cos`` (never by file name,
    InstanceNumber or SliceLocation), apply ``HU = stored * RescaleSlope + RescaleIntercept``,
    convert LPS -> RAS.

    Gaps between neighbouring slices larger than 1.5 times the median gap (slices missing from the
    export, see :func:`missing_slice_gaps`) are bridged by interpolation when the stack is resampled;
    each one is named (size, slice indices, positions along the normal) in a
    :class:`SliceGapWarning` and a log warning, and recorded in ``source["missing_slice_gaps"]``.

    Slices without RescaleSlope/RescaleIntercept (both are required in CT images, but converters
    drop them) use ``rescale`` when given. Without it, CT stored values are taken as HU only when
    :func:`looks_like_hu` says so (with a warning); otherwise that is an error, because raw stored
    values (e.g. 0 .. 4095 for HU + 1024) read as HU give a wrong volume without any other sign.
    Values of other modalities are raw anyway and are kept as stored. ``source["rescale"]`` records
    what was applied (``from``: ``header``, ``option``, ``assumed_hu`` or ``stored_values``; a ``rescale``
    that no slice needed is warned about and kept as ``option_unused``).

    Pixels marked as padding (PixelPaddingValue, up to PixelPaddingRangeLimit: outside the reconstructed
    field of view) take the smallest value measured in the series, recorded in ``source["pixel_padding"]``.

    Oblique orientations and gantry tilt are supported: the full per-slice geometry is kept and
    resampled exactly by :func:`ctsplat.volume.resample_stack`. Multi-frame (enhanced) objects and
    slices with differing orientations are rejected with a message.

    Parameters
    ----------
    folder : path
        Folder holding the series (sub-folders are searched).
    series_uid : str, optional
        The series to read: its id (the salted hash ``ctsplat ingest --list-series`` shows), its
        SeriesInstanceUID or its SeriesNumber.
    allow_modalities : sequence of str
        Modalities accepted (default CT only; values of other modalities are not HU).
    skip_corrupt : bool
        Skip unreadable/truncated files with a warning instead of failing.
    rescale : (2,) floats, optional
        ``[slope, intercept]`` for slices lacking the rescale tags (``[1, 0]``: stored values are HU).
        Slices that carry the tags always use their own.

    Returns
    -------
    SliceStack
        ``data`` (Columns, Rows, K) float32 in HU (``units="hu"`` for CT, else ``"raw"``); geometry in
        RAS mm.

    References
    ----------
    DICOM PS3.3 C.7.6.2 (Image Plane module) and C.8.2.1 (CT Image module); see the module docstring.
    """
    with _quiet_pydicom():
        stack = _read_dicom_series(
            Path(folder), series_uid=series_uid, allow_modalities=allow_modalities, skip_corrupt=skip_corrupt,
            rescale=rescale,
        )
    src = stack.source
    _warn_gaps(src["nominal_slice_gap_mm"], src["missing_slice_gaps"], src["n_slices"], f"series {src['series_id']}")
    return stack


def _read_dicom_series(
    folder: Path,
    *,
    series_uid: str | None,
    allow_modalities: Sequence[str],
    skip_corrupt: bool,
    rescale: Sequence[float] | None,
) -> SliceStack:
    """:func:`read_dicom_series` without the gap warning (issued once pydicom's warnings are unmuted)."""
    from pydicom.pixels import pixel_array

    user_rescale = check_rescale(rescale)
    skipped: list[Path] = []
    series = find_dicom_series(folder, skip_corrupt=skip_corrupt, _skipped=skipped)
    label = _FileLabels(folder, _walk_files(folder))
    pick = _choose_series(series, series_uid, allow_modalities, folder)

    slices: list[tuple[Path, Any, np.ndarray]] = []
    without_rescale: list[int] = []  # indices into ``slices`` whose values are still stored values
    header_rescales: set[tuple[float, float]] = set()
    padding: dict[int, np.ndarray] = {}  # index into ``slices`` -> its padding pixels (``values.T``'s layout)
    padding_values: set[tuple[int, int]] = set()
    ref: dict[str, Any] = {}
    for path in pick.files:
        try:
            ds = _dcmread(path, stop_before_pixels=False)
            if ds is None:
                raise ValueError("not readable as DICOM")
            if "PixelData" not in ds:  # pydicom returns an empty dataset (with a warning) for truncated pixel data
                raise ValueError("no pixel data (the file is truncated or holds a header only)")
        except Exception as exc:  # noqa: BLE001
            _handle_corrupt(path, label(path), _why(exc), skip_corrupt, skipped)
            continue
        if _header_int(ds, "NumberOfFrames", label(path)) > 1:
            raise CtsplatError(
                f"{label(path)} is a multi-frame (enhanced) image; only one-slice-per-file series are supported - "
                f"convert it to a NIfTI (e.g. dcm2niix) and ingest that"
            )
        if _header_int(ds, "SamplesPerPixel", label(path)) != 1:
            raise CtsplatError(f"{label(path)} is not a greyscale image (SamplesPerPixel != 1); CT slices are "
                               "greyscale")
        _check_decoder(ds, label(path))
        _vec(ds, "ImagePositionPatient", 3, label(path))  # fail early when missing
        iop = _vec(ds, "ImageOrientationPatient", 6, label(path))
        ps = _vec(ds, "PixelSpacing", 2, label(path))
        rows, cols = int(ds.Rows), int(ds.Columns)
        if not ref:
            ref = {"iop": iop, "ps": ps, "rows": rows, "cols": cols, "path": path}
        else:
            if (rows, cols) != (ref["rows"], ref["cols"]):
                raise CtsplatError(
                    f"inconsistent slice size in series: {label(path)} is {rows}x{cols}, {label(ref['path'])} is "
                    f"{ref['rows']}x{ref['cols']} (rows x columns); remove the odd slices or choose another series"
                )
            if not np.allclose(ps, ref["ps"], rtol=_SPACING_RTOL, atol=0):
                raise CtsplatError(
                    f"inconsistent PixelSpacing in series: {label(path)} has {ps.tolist()}, {label(ref['path'])} has "
                    f"{ref['ps'].tolist()} mm; remove the odd slices or choose another series"
                )
            if not np.allclose(iop, ref["iop"], atol=_ORIENT_TOL):
                raise CtsplatError(
                    f"slices with different ImageOrientationPatient in one series ({label(path)} vs "
                    f"{label(ref['path'])}); not supported - split the series or re-export it"
                )
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pixels = pixel_array(ds)  # no cached copy on the dataset
        except Exception as exc:  # noqa: BLE001 - truncated pixel data, bad encapsulation ...
            msg = _why(exc, with_type=False)
            if "missing" in msg.lower() and "plugin" in msg.lower():
                pkg = _DECODER_PACKAGES.get(str(ds.file_meta.TransferSyntaxUID), "pylibjpeg")
                raise CtsplatError(f"{label(path)}: no decoder for its compressed pixel data; install {pkg}") from None
            _handle_corrupt(path, label(path), f"{type(exc).__name__}: {msg}", skip_corrupt, skipped)
            continue
        if pixels.shape != (rows, cols):
            _handle_corrupt(path, label(path), f"pixel array shape {pixels.shape} != {(rows, cols)}", skip_corrupt,
                            skipped)
            continue
        pad = _padding_mask(ds, pixels)
        if pad is not None:
            padding[len(slices)] = pad[0].T
            padding_values.add(pad[1])
        values = pixels.astype(np.float32)
        rescale_tags = _rescale(ds, label(path))
        if rescale_tags is not None:
            slope, intercept = rescale_tags
            header_rescales.add((slope, intercept))
            values = values * np.float32(slope) + np.float32(intercept)
        else:
            without_rescale.append(len(slices))
        del ds.PixelData  # keep only the header in memory
        slices.append((path, ds, values.T))  # (Columns, Rows): i along row_dir, j along col_dir

    if len(slices) < 2:
        what = "a single slice" if len(slices) == 1 else "no readable slices"
        raise CtsplatError(
            f"series {pick.label()} in {folder} has {what}; a volume needs at least 2 slices "
            f"(check the folder holds the whole series)"
        )

    iop = ref["iop"]
    row_lps, col_lps = iop[:3], iop[3:]
    if abs(np.linalg.norm(row_lps) - 1) > 1e-3 or abs(np.linalg.norm(col_lps) - 1) > 1e-3 or abs(
        row_lps @ col_lps
    ) > 1e-3:
        raise CtsplatError(f"ImageOrientationPatient {iop.tolist()} of series {pick.label()} in {folder} (e.g. "
                           f"{label(ref['path'])}) is not 2 orthonormal unit vectors; fix the header")
    row_lps = row_lps / np.linalg.norm(row_lps)
    col_lps = col_lps / np.linalg.norm(col_lps)
    normal_lps = np.cross(row_lps, col_lps)
    ipps = np.stack([_vec(ds, "ImagePositionPatient", 3, label(p)) for p, ds, _ in slices])
    pos = ipps @ normal_lps
    order = np.argsort(pos, kind="stable")
    pos_sorted = pos[order]
    gaps = np.diff(pos_sorted)
    dup = np.flatnonzero(gaps < _DUPLICATE_TOL_MM)
    if dup.size:
        a, b = slices[order[dup[0]]][0], slices[order[dup[0] + 1]][0]
        raise CtsplatError(
            f"duplicate slice position {pos_sorted[dup[0]]:.3f} mm along the normal in {label(a)} and {label(b)} "
            f"({dup.size} duplicate pair(s)); remove the duplicate files or choose the right series"
        )

    first = slices[order[0]][1]
    ts = getattr(getattr(first, "file_meta", None), "TransferSyntaxUID", None)
    modality = str(first.get("Modality", "") or "")
    units = "hu" if modality.upper() == "CT" else "raw"
    rescale_info = _apply_missing_rescale(slices, without_rescale, header_rescales, user_rescale, units, pick, folder)
    padding_info = _fill_padding(slices, padding, padding_values)
    data = np.stack([slices[o][2] for o in order], axis=2).astype(np.float32, copy=False)
    stack = SliceStack(
        data=data,
        row_dir=lps_to_ras(row_lps),
        col_dir=lps_to_ras(col_lps),
        spacing_ij=(float(ref["ps"][1]), float(ref["ps"][0])),  # PixelSpacing = [row spacing, column spacing]
        origins=lps_to_ras(ipps[order]),
        units=units,
    )
    rounded_gaps = sorted({round(float(g), 3) for g in gaps})
    nominal, missing = missing_slice_gaps(pos_sorted)
    study_uid = str(first.get("StudyInstanceUID", "") or "")
    stack.source = {
        "kind": "dicom",
        "series_id": pick.id,
        "series_uid_hash": salted_hash(pick.uid) if pick.uid else None,
        "study_uid_hash": salted_hash(study_uid) if study_uid else None,
        "modality": modality,
        "manufacturer": str(first.get("Manufacturer", "") or ""),
        "model": str(first.get("ManufacturerModelName", "") or ""),
        "kvp": _optional_number(first.get("KVP")),
        "transfer_syntax": ts.name if ts is not None else None,
        "n_series_found": len(series),
        "n_slices": len(slices),
        "n_files_skipped": len(skipped),
        "rows": ref["rows"],
        "columns": ref["cols"],
        "pixel_spacing_mm": [float(v) for v in ref["ps"]],
        "slice_thickness_mm": _optional_number(first.get("SliceThickness")),
        "slice_gaps_mm": rounded_gaps,
        "uniform_spacing": bool(np.ptp(gaps) < 1e-3),
        "nominal_slice_gap_mm": round(nominal, 6),
        "missing_slice_gaps": missing,
        "axial_coverage_mm": float(pos_sorted[-1] - pos_sorted[0]),
        "image_orientation_patient": [float(v) for v in iop],
        "gantry_tilt_deg": round(stack.tilt_deg, 4),
        "rescale": rescale_info,
        "pixel_padding": padding_info,
        "value_range": _finite_range(data),
        "units": units,
    }
    log.info(
        "read %d slices %dx%d (%s), gaps %s mm, tilt %.2f deg",
        len(slices), ref["cols"], ref["rows"], modality, rounded_gaps, stack.tilt_deg,
    )
    return stack


def _apply_missing_rescale(
    slices: list[tuple[Path, Any, np.ndarray]],
    without: list[int],
    header: set[tuple[float, float]],
    user: tuple[float, float] | None,
    units: str,
    pick: SeriesInfo,
    folder: Path,
) -> dict[str, Any]:
    """Rescale the slices that lacked the tags (in place in ``slices``); return the provenance record."""

    def one_or_all(values: set[float]) -> float | list[float]:
        return next(iter(values)) if len(values) == 1 else sorted(values)

    info: dict[str, Any] = {"from": "header"}
    if header:
        info.update(slope=one_or_all({s for s, _ in header}), intercept=one_or_all({i for _, i in header}))
    info["n_slices_without_tags"] = len(without)
    if not without:
        if user is not None:  # nothing to apply it to: say so rather than let the option look effective
            log.warning("rescale %s was given, but every slice of series %s carries its own RescaleSlope and "
                        "RescaleIntercept, which are used; the option does nothing here", list(user), pick.label())
            info["option_unused"] = list(user)
        return info
    if user is not None:
        slope, intercept = user
        for n in without:
            path, ds, values = slices[n]
            slices[n] = (path, ds, values * np.float32(slope) + np.float32(intercept))
        return {"from": "option", "slope": slope, "intercept": intercept, "n_slices_without_tags": len(without)}
    if units != "hu":
        return {"from": "stored_values", "slope": 1.0, "intercept": 0.0, "n_slices_without_tags": len(without)}
    stored = np.concatenate([slices[n][2].ravel() for n in without])
    lo, hi = float(stored.min()), float(stored.max())
    if not looks_like_hu(stored):
        raise CtsplatError(
            f"{len(without)} of {len(slices)} slices of series {pick.label()} in {folder} have no "
            f"RescaleSlope/RescaleIntercept and their stored values ({lo:g} .. {hi:g}) do not look like HU "
            f"(no air near -1000, or values >= {_HU_MAX_PLAUSIBLE:g}); give the scanner's rescale as rescale "
            f"[SLOPE, INTERCEPT] (--rescale SLOPE,INTERCEPT), e.g. 1,-1024, or 1,0 if the stored values are HU"
        )
    log.warning(
        "%d of %d slices have no RescaleSlope/RescaleIntercept; their stored values (%g .. %g) look like HU "
        "(air present) and are used as HU - pass rescale (--rescale SLOPE,INTERCEPT) if that is wrong",
        len(without), len(slices), lo, hi,
    )
    return {"from": "assumed_hu", "slope": 1.0, "intercept": 0.0, "n_slices_without_tags": len(without),
            "rule": "looks_like_hu: >= 0.1 % of values within -1000 +- 100, max < 4000"}


# --------------------------------------------------------------------------------------------------
# NIfTI and TIFF
# --------------------------------------------------------------------------------------------------


#: The voxel sizes ingest accepts, mm: 0.1 nm to 10 km, far beyond any scanner; anything else is a unit or header error
#: (a 1e-30 mm voxel turned every later affine singular, a 1e30 mm one gave line integrals of 1e29).
VOXEL_MM_RANGE = (1e-7, 1e7)


def _stack_from_affine(data: np.ndarray, affine: np.ndarray, units: str, source: dict[str, Any], *,
                       fix: str = "fix the NIfTI header (qform/sform)") -> SliceStack:
    """Regular grid with a (possibly sheared along k) RAS affine -> SliceStack (slices ascending); ``fix`` is what
    an error tells the user to do about the grid."""
    a = np.asarray(affine, float)
    if not np.isfinite(a).all():
        raise CtsplatError(f"volume affine has NaN or infinite entries; {fix}")
    di, dj = np.linalg.norm(a[:3, 0]), np.linalg.norm(a[:3, 1])
    dk = np.linalg.norm(a[:3, 2])
    if di <= 0 or dj <= 0 or dk <= 0:
        raise CtsplatError(f"volume affine has a zero-length axis; {fix}")
    lo, hi = VOXEL_MM_RANGE
    if not all(lo <= d <= hi for d in (di, dj, dk)):
        raise CtsplatError(f"voxel size {di:.3g} x {dj:.3g} x {dk:.3g} mm lies outside {lo:g} .. {hi:g} mm (a unit "
                           f"or header error); {fix}")
    u, v = a[:3, 0] / di, a[:3, 1] / dj
    if abs(u @ v) > 1e-4:
        raise CtsplatError("volume affine has non-orthogonal in-plane axes; resample it to an orthogonal grid first")
    k = np.arange(data.shape[2])
    origins = a[:3, 3][None, :] + k[:, None] * a[:3, 2][None, :]
    n = np.cross(u, v)
    if float(a[:3, 2] @ n) < 0:
        data, origins = data[:, :, ::-1], origins[::-1]
    if abs(a[:3, 2] @ n) < 1e-6 * dk:  # relative: micrometre voxels are still a volume
        raise CtsplatError("volume affine's third axis lies in the slice plane; fix the NIfTI header")
    return SliceStack(
        data=np.ascontiguousarray(data, dtype=np.float32),
        row_dir=u,
        col_dir=v,
        spacing_ij=(float(di), float(dj)),
        origins=np.asarray(origins, float),
        units=units,
        source=source,
    )


#: NIfTI spatial units (``xyzt_units``) in mm; "unknown" (code 0, what many writers leave) is read as mm, the
#: unit NIfTI readers assume.
NIFTI_UNIT_MM = {"mm": 1.0, "unknown": 1.0, "micron": 1e-3, "meter": 1e3}


def read_nifti(path: str | Path, *, units: str = "hu") -> SliceStack:
    """Read a 3D NIfTI-1/2 volume; its affine (sform, else qform, as nibabel resolves it) is the RAS world frame,
    converted to mm from the header's spatial unit (:data:`NIFTI_UNIT_MM`). A file with neither an sform nor a qform
    is refused: its orientation is unknown.

    Parameters
    ----------
    path : path
        ``.nii`` or ``.nii.gz`` file; a 4D file with singleton trailing axes is squeezed.
    units : {"hu", "raw"}
        What the stored values (after ``scl_slope`` / ``scl_inter``) are.

    Returns
    -------
    SliceStack
        ``data`` (I, J, K) float32, slices ordered along the slice normal.

    References
    ----------
    NIfTI-1 ``qform`` / ``sform`` (Cox et al. 2004); see the module docstring.
    """
    import nibabel as nib

    path = Path(path)
    try:
        img = nib.load(str(path))
        if img.get_data_dtype().kind == "c":  # float32 would keep the real part, silently
            raise CtsplatError(f"NIfTI {path} holds complex values ({img.get_data_dtype()}); ingest needs real "
                               "intensities: write the magnitude or the real part")
        data = np.asarray(img.dataobj, dtype=np.float32)  # applies scl_slope/scl_inter
    except CtsplatError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise CtsplatError(f"cannot read NIfTI {path} ({type(exc).__name__}: {exc}); is the file complete?") from None
    data = np.squeeze(data) if data.ndim > 3 else data
    if data.ndim != 3 or min(data.shape) < 2:
        raise CtsplatError(f"NIfTI {path} has shape {data.shape}; ingest needs a 3D volume with >= 2 slices")
    unit = img.header.get_xyzt_units()[0]
    if unit not in NIFTI_UNIT_MM:
        raise CtsplatError(f"NIfTI {path} gives its spatial unit as {unit!r}, not a length; write mm, micron or "
                           "meter into the header (xyzt_units)")
    to_mm = NIFTI_UNIT_MM[unit]
    source = {
        "kind": "nifti",
        "shape": list(data.shape),
        "zooms_mm": [float(z) * to_mm for z in img.header.get_zooms()[:3]],
        "spatial_unit": unit,
        "value_range": _finite_range(data),
        "units": units,
    }
    with nib.openers.ImageOpener(str(path)) as fh:  # the header as stored: nibabel's load sets zero pixdims to 1
        stored = type(img.header).from_fileobj(fh, check=False)
    pixdim = [float(z) for z in stored["pixdim"][1:4]]
    if int(stored["sform_code"]) == 0 and any(z == 0 for z in pixdim):  # the qform scales by pixdim as well
        raise CtsplatError(f"NIfTI {path} has voxel sizes (pixdim) {pixdim} and no sform, so its voxel size is "
                           "unknown; write the voxel size into the header")
    if int(stored["sform_code"]) == 0 and int(stored["qform_code"]) == 0:
        raise CtsplatError(f"NIfTI {path} has neither an sform nor a qform (both codes 0), so its orientation is "
                           "unknown (readers guess one with x mirrored); write the voxel-to-world affine into the "
                           "header, e.g. nibabel's img.set_qform(affine, code=1)")
    affine = np.asarray(img.affine, float).copy()
    affine[:3, :] *= to_mm  # world positions and voxel axes in mm
    try:
        return _stack_from_affine(data, affine, units, source)
    except CtsplatError as exc:
        raise CtsplatError(f"NIfTI {path}: {exc}") from None


def _finite_range(data: np.ndarray) -> list[float] | None:
    """``[min, max]`` over the finite values (non-finite ones are ingest's business), None if there are none."""
    finite = np.isfinite(data)
    if finite.all():
        return [float(data.min()), float(data.max())]
    if not finite.any():
        return None
    return [float(data[finite].min()), float(data[finite].max())]


def _natural_key(p: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


def _read_tiff(path: Path, what: str, fix: str) -> np.ndarray:
    """``tifffile.imread``, or one line naming the file that does not read."""
    import tifffile

    try:
        return tifffile.imread(path)
    except Exception as exc:  # noqa: BLE001 - tifffile raises many kinds for a broken file
        raise CtsplatError(f"{what} {path} is not a readable TIFF file (truncated, corrupt or not a TIFF: "
                           f"{type(exc).__name__}: {exc}); {fix}") from None


def read_tiff_stack(
    path: str | Path, voxel_size_mm: float | Sequence[float] | None, *, units: str = "raw"
) -> SliceStack:
    """Read a TIFF slice stack: one multi-page file, or a folder of 2D TIFFs (natural name order).

    TIFFs carry no patient geometry: slice ``k`` is page/file ``k``, image rows are ``j``, columns
    ``i``; axes are taken as world +x, +y, +z (RAS) with the volume centred on the origin.

    Parameters
    ----------
    path : path
        A multi-page ``.tif``/``.tiff`` file (pages = slices) or a folder of 2D TIFFs.
    voxel_size_mm : float or (3,) floats
        Voxel size (x, y, z) in mm; required (HiP-CT style stacks ship it in their metadata).
    units : {"raw", "hu"}
        What the stored values are (TIFF stacks carry no rescale; default raw intensities).

    Returns
    -------
    SliceStack
        ``data`` (X, Y, Z) float32, centred on the world origin.
    """

    path = Path(path)
    if voxel_size_mm is None:
        raise CtsplatError(f"TIFF stack {path} has no patient geometry; give its voxel size (--tiff-voxel-size MM)")
    vs = np.broadcast_to(np.asarray(voxel_size_mm, float), (3,)).copy()
    if np.any(vs <= 0):
        raise CtsplatError(f"TIFF voxel size must be positive, got {vs.tolist()}")
    if path.is_dir():
        files = sorted(
            (p for p in path.iterdir() if p.suffix.lower() in TIFF_SUFFIXES and not p.name.startswith(".")),
            key=_natural_key,
        )
        if not files:
            raise CtsplatError(f"folder {path} holds no .tif/.tiff files")
        pages = []
        for p in files:  # one at a time, so that the message names the slice
            pages.append(_read_tiff(p, "TIFF slice", "re-export it or remove it"))
            if pages[-1].shape != pages[0].shape:
                raise CtsplatError(f"TIFF slices in {path} differ in size: {p.name} is {pages[-1].shape}, "
                                   f"{files[0].name} is {pages[0].shape}; all slices must have the same shape")
        arr = np.stack(pages, axis=0)
    else:
        arr = _read_tiff(path, "TIFF stack", "re-export it")
    if arr.ndim != 3 or arr.shape[0] < 2:
        raise CtsplatError(f"TIFF stack {path} has shape {arr.shape}; need >= 2 greyscale slices (Z, Y, X)")
    if np.iscomplexobj(arr):  # float32 would keep the real part, silently
        raise CtsplatError(f"TIFF stack {path} holds complex values ({arr.dtype}); ingest needs real intensities: "
                           "write the magnitude or the real part")
    data = np.ascontiguousarray(arr.transpose(2, 1, 0), dtype=np.float32)  # (X, Y, Z)
    shape = np.asarray(data.shape, float)
    affine = np.diag([*vs, 1.0])
    affine[:3, 3] = -(shape - 1) / 2 * vs
    source = {
        "kind": "tiff",
        "shape": list(data.shape),
        "voxel_size_mm": vs.tolist(),
        "value_range": _finite_range(data),
        "units": units,
    }
    return _stack_from_affine(data, affine, units, source,
                              fix="give the TIFF voxel size in mm (--tiff-voxel-size, tiff_voxel_size_mm)")


def read_source(
    source: str | Path,
    *,
    series_uid: str | None = None,
    allow_modalities: Sequence[str] = ("CT",),
    skip_corrupt: bool = False,
    tiff_voxel_size_mm: float | Sequence[float] | None = None,
    rescale: Sequence[float] | None = None,
) -> SliceStack:
    """Read a scan, dispatching on the input: NIfTI file, TIFF file or folder of TIFFs, else a DICOM folder.

    Parameters
    ----------
    source : path
        ``.nii``/``.nii.gz`` file, ``.tif``/``.tiff`` file, folder holding only TIFFs, or DICOM folder.
    series_uid, allow_modalities, skip_corrupt, rescale
        Passed to :func:`read_dicom_series`; ``rescale`` is refused for NIfTI / TIFF input.
    tiff_voxel_size_mm : float or (3,) floats, optional
        Passed to :func:`read_tiff_stack` (required for TIFF input).

    Returns
    -------
    SliceStack
    """
    source = Path(source)
    if not source.exists():
        raise CtsplatError(f"input {source} does not exist; give a DICOM folder, a .nii/.nii.gz file or a TIFF stack")
    kind = source_kind(source)
    if rescale is not None and kind != "dicom":
        raise CtsplatError(
            f"rescale applies to DICOM input only, not {source} (NIfTI carries its own scl_slope/scl_inter, "
            f"TIFF values are raw); remove it"
        )
    if kind == "nifti":
        return read_nifti(source)
    if kind == "tiff":
        return read_tiff_stack(source, tiff_voxel_size_mm)
    if kind is None:
        raise CtsplatError(
            f"input file {source} is not a .nii/.nii.gz or .tif stack; for DICOM give the folder holding the slices"
        )
    return read_dicom_series(
        source, series_uid=series_uid, allow_modalities=allow_modalities, skip_corrupt=skip_corrupt, rescale=rescale
    )


#: Volume settings that apply to one kind of source (:func:`source_kind`; the built-in phantom is a DICOM series):
#: another kind would ignore or refuse them, so the config and ``ctsplat ingest`` refuse them up front.
SOURCE_KIND_KEYS: dict[str, str] = {"series_uid": "dicom", "allow_modalities": "dicom", "skip_corrupt": "dicom",
                                    "rescale": "dicom", "tiff_voxel_size_mm": "tiff"}


def source_kind(source: str | os.PathLike[str]) -> str | None:
    """How :func:`read_source` reads ``source``: ``"nifti"`` or ``"tiff"`` (a stack file, or a folder of TIFF slices
    only), ``"dicom"`` (any other folder, or a path that does not exist), None for a file of another kind."""
    source = Path(source)
    if source.is_file():
        name = source.name.lower()
        return "nifti" if name.endswith(NIFTI_SUFFIXES) else "tiff" if name.endswith(TIFF_SUFFIXES) else None
    if source.is_dir():
        entries = [p for p in source.iterdir() if not p.name.startswith(".")]
        if entries and all(p.is_file() and p.suffix.lower() in TIFF_SUFFIXES for p in entries):
            return "tiff"
    return "dicom"


# --------------------------------------------------------------------------------------------------
# Writing (phantom and tests)
# --------------------------------------------------------------------------------------------------


def write_dicom_series(
    hu: np.ndarray,
    out_dir: str | Path,
    *,
    spacing_mm: Sequence[float],
    origin_lps: Sequence[float],
    row_dir_lps: Sequence[float] = (1.0, 0.0, 0.0),
    col_dir_lps: Sequence[float] = (0.0, 1.0, 0.0),
    slice_positions_mm: Sequence[float] | None = None,
    slice_step_lps: Sequence[float] | None = None,
    modality: str = "CT",
    uid_seed: str = "ctsplat",
    patient_name: str = "Phantom^Ctsplat",
    patient_id: str = "CTSPLAT-PHANTOM",
    series_description: str = "ctsplat synthetic CT",
    filename: str = "slice_{k:04d}.dcm",
    intercept: float = -1024.0,
    transfer_syntax: str | None = None,
) -> list[Path]:
    """Write a volume of HU values as a real single-frame DICOM CT series (one file per slice).

    Geometry (DICOM LPS, mm): pixel ``(row j, column i)`` of slice ``k`` lies at
    ``IPP_k + i * spacing_mm[0] * row_dir + j * spacing_mm[1] * col_dir`` with
    ``IPP_k = origin_lps + positions[k] * n`` (``n = row_dir × col_dir``) unless ``slice_step_lps``
    (a full 3-vector per slice, e.g. for gantry tilt) is given: ``IPP_k = origin_lps + k * step``.
    Values are stored as uint16 with ``RescaleIntercept = intercept`` (slope 1), so ``hu`` is
    rounded to whole HU and must lie within ``[intercept, intercept + 65535]``. ``transfer_syntax``
    (a UID, e.g. JPEG 2000 lossless ``1.2.840.10008.1.2.4.90``) compresses the pixel data with
    pydicom's encoders (JPEG 2000 needs pylibjpeg-openjpeg and images of at least 32x32).

    Parameters
    ----------
    hu : ndarray, shape (I, J, K)
        HU values indexed ``[column, row, slice]``.
    out_dir : path
        Folder to write into (created if missing; existing files of the same names are overwritten).
    spacing_mm : (3,) floats
        Column spacing, row spacing, slice spacing (the last is used only when neither
        ``slice_positions_mm`` nor ``slice_step_lps`` is given).
    origin_lps : (3,) floats
        ImagePositionPatient of slice 0 (LPS, mm).
    row_dir_lps, col_dir_lps : (3,) floats
        ImageOrientationPatient row and column direction cosines (LPS).
    slice_positions_mm : (K,) floats, optional
        Slice positions along the normal (mm), relative to ``origin_lps``.
    slice_step_lps : (3,) floats, optional
        Full step between consecutive IPPs (LPS, mm); overrides ``slice_positions_mm``.
    modality : str
        ``"CT"`` (CT Image Storage) or another modality (written as MR Image Storage).
    uid_seed : str
        Seed of the deterministic UIDs (same seed -> same Study/Series/SOP UIDs).
    patient_name, patient_id, series_description : str
        Header text (synthetic; real patient data never passes through here).
    filename : str
        File name pattern, formatted with ``k`` (slice index).
    intercept : float
        RescaleIntercept (HU); RescaleSlope is 1.
    transfer_syntax : str, optional
        Transfer syntax UID to compress with; default explicit VR little endian (uncompressed).

    Returns
    -------
    list of Path
        The files written, in slice order.
    """
    import pydicom
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, MRImageStorage, generate_uid

    hu = np.asarray(hu)
    if hu.ndim != 3:
        raise CtsplatError(f"write_dicom_series needs a 3D array, got shape {hu.shape}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n_i, n_j, n_k = hu.shape
    row = np.asarray(row_dir_lps, float)
    col = np.asarray(col_dir_lps, float)
    normal = np.cross(row, col)
    origin = np.asarray(origin_lps, float)
    if slice_step_lps is not None:
        ipps = origin[None] + np.arange(n_k)[:, None] * np.asarray(slice_step_lps, float)[None]
    else:
        pos = np.arange(n_k) * float(spacing_mm[2]) if slice_positions_mm is None else np.asarray(slice_positions_mm)
        ipps = origin[None] + np.asarray(pos, float)[:, None] * normal[None]
    stored = np.rint(hu - intercept)
    if stored.min() < 0 or stored.max() > 65535:
        raise CtsplatError(f"HU values out of the storable range [{intercept}, {intercept + 65535}]")
    stored = stored.astype(np.uint16)

    def uid(*parts: object) -> str:
        return generate_uid(entropy_srcs=[uid_seed, *map(str, parts)])

    study, series, frame = uid("study"), uid("series"), uid("frame")
    sop_class = CTImageStorage if modality.upper() == "CT" else MRImageStorage
    paths = []
    for k in range(n_k):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = sop_class
        meta.MediaStorageSOPInstanceUID = uid("instance", k)
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        path = out_dir / filename.format(k=k)
        ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID = sop_class
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.Modality = modality
        ds.Manufacturer = "ctsplat"
        ds.PatientName = patient_name
        ds.PatientID = patient_id
        ds.PatientPosition = "HFS"
        ds.SeriesNumber = 1
        ds.InstanceNumber = k + 1
        ds.SeriesDescription = series_description
        ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
        ds.ImagePositionPatient = [f"{v:.6f}" for v in ipps[k]]
        ds.ImageOrientationPatient = [f"{v:.8f}" for v in (*row, *col)]
        ds.PixelSpacing = [f"{float(spacing_mm[1]):.6f}", f"{float(spacing_mm[0]):.6f}"]
        ds.SliceThickness = f"{float(spacing_mm[2]):.6f}"
        ds.SliceLocation = f"{float(ipps[k] @ normal):.6f}"
        ds.Rows, ds.Columns = n_j, n_i
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.RescaleIntercept = f"{intercept:g}"
        ds.RescaleSlope = "1"
        ds.RescaleType = "HU"
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T).tobytes()  # rows x columns
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if transfer_syntax is not None:
                ds.compress(transfer_syntax)
            pydicom.dcmwrite(path, ds, enforce_file_format=True)
        paths.append(path)
    return paths
