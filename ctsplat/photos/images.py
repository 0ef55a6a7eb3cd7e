"""A folder of photographs: which files are images, whether each decodes whole, and their sizes.

Checked before any output is written, so a bad folder fails with one line naming the file (or count) and leaves
nothing behind.

"Decodes whole" includes JPEG files whose compressed data libjpeg finds damaged inside the file: libjpeg (under
Pillow, and under COLMAP) recovers from those with a warning that Pillow does not pass on, filling the rest of the
image with grey, so Pillow alone reads such a photo as valid. :func:`jpeg_damage` decodes JPEG files a second time
with simplejpeg's strict mode, which turns libjpeg's warnings into errors, and keeps those that say the data is
corrupt. Damage that keeps the decoder in step (a flipped bit that still reads as valid codes) leaves no trace a
decoder can see, and passes.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image

from ctsplat.utils import CtsplatError, atomic_path

__all__ = ["IMAGE_SUFFIXES", "OTHER_IMAGE_SUFFIXES", "list_photos", "unread_entries", "check_photo_count",
           "check_photos", "jpeg_damage", "load_rgb", "strip_metadata"]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")

#: Suffixes of pictures that are not read (Pillow's formats, phones' HEIF/AVIF, cameras' raw files): a photo folder
#: entry with one of them is reported, not passed over in silence.
OTHER_IMAGE_SUFFIXES = frozenset(
    {*Image.registered_extensions(), ".heic", ".heif", ".avif", ".jxl", ".dng", ".cr2", ".cr3", ".nef", ".arw",
     ".orf", ".rw2", ".raf"} - set(IMAGE_SUFFIXES))

log = logging.getLogger(__name__)


def list_photos(folder: str | Path) -> list[str]:
    """The image file names in ``folder`` (not recursive), sorted.

    Parameters
    ----------
    folder : str or Path

    Returns
    -------
    list of str
        File names with a suffix of :data:`IMAGE_SUFFIXES` (any case), hidden files (``.name``, such as macOS's
        ``._name.jpg``) left out. Pictures that are not read (:func:`unread_entries`) are named in a warning.

    Raises
    ------
    CtsplatError
        When the folder does not exist or holds no image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise CtsplatError(f"photo folder {folder} does not exist or is not a folder")
    names = sorted(p.name for p in folder.iterdir()
                   if not p.name.startswith(".") and p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    unread = unread_entries(folder)
    if unread:
        log.warning("%s: %d entries look like photos but are not read (only %s files in the folder itself are; "
                    "links must reach a file): %s", folder, len(unread), ", ".join(IMAGE_SUFFIXES), ", ".join(unread))
    if not names:
        raise CtsplatError(f"photo folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)}); "
                           "point it at the folder with the photographs")
    return names


def unread_entries(folder: str | Path) -> list[str]:
    """The entries of a photo folder that look like pictures but are not read: other picture formats
    (:data:`OTHER_IMAGE_SUFFIXES`), links to nothing and sub-folders that hold photos (named ``name/``: the folder
    is not read recursively); hidden names left out.

    Parameters
    ----------
    folder : str or Path
        An existing folder.

    Returns
    -------
    list of str
        Sorted names.
    """
    def unread(p: Path) -> bool:
        suffix = p.suffix.lower()
        broken_link = suffix in IMAGE_SUFFIXES and p.is_symlink() and not p.exists()
        return not p.name.startswith(".") and (suffix in OTHER_IMAGE_SUFFIXES or broken_link)

    def holds_photos(p: Path) -> bool:
        return (not p.name.startswith(".") and p.is_dir()
                and any(q.suffix.lower() in IMAGE_SUFFIXES and q.is_file() for q in p.iterdir()))

    entries = list(Path(folder).iterdir())
    return sorted([p.name for p in entries if unread(p)] + [f"{p.name}/" for p in entries if holds_photos(p)])


def check_photo_count(folder: str | Path, n_photos: int, min_registered: int) -> None:
    """Refuse a folder with fewer photos than SfM must register in one model: no model can register more.

    Parameters
    ----------
    folder : str or Path
        The photo folder (named in the error).
    n_photos : int
        Photographs in it.
    min_registered : int
        ``photos.sfm.min_registered``.

    Raises
    ------
    CtsplatError
        When ``n_photos < min_registered``.
    """
    if n_photos < int(min_registered):
        raise CtsplatError(f"{folder} holds {n_photos} photos; SfM needs at least {min_registered} registered in one "
                           "model (photos.sfm.min_registered): add photos of the object")


def check_photos(folder: str | Path, names: list[str], *, single_camera: bool) -> dict[str, tuple[int, int]]:
    """Decode every image in full and check that one camera can describe them all.

    Parameters
    ----------
    folder : str or Path
    names : list of str
        File names in ``folder``.
    single_camera : bool
        All images must then share one size (one camera for all).

    Returns
    -------
    dict of str to (int, int)
        File name -> ``(width, height)`` px.

    Raises
    ------
    CtsplatError
        For the first image that does not decode whole (truncated, corrupt, or a JPEG whose data libjpeg decodes
        only by recovering from damage: :func:`jpeg_damage`), or, with ``single_camera``, for images of more than
        one size (the message counts each size and names an example).
    """
    folder = Path(folder)
    sizes: dict[str, tuple[int, int]] = {}
    for name in names:
        path = folder / name
        try:
            with _open_whole(path) as im:
                sizes[name] = (int(im.width), int(im.height))
        except Image.DecompressionBombError as exc:
            raise CtsplatError(f"image {path} is too large to decode safely ({str(exc).splitlines()[0]}); "
                               "downscale it or remove it") from exc
        except (OSError, SyntaxError, ValueError) as exc:
            raise CtsplatError(f"corrupt or truncated image {path}: {str(exc).splitlines()[0]}; "
                               "replace or remove it") from exc
    counts = Counter(sizes.values())
    if single_camera and len(counts) > 1:
        parts = []
        for (w, h), n in counts.most_common():
            example = next(k for k, v in sizes.items() if v == (w, h))
            parts.append(f"{n} at {w}x{h} (e.g. {example})")
        raise CtsplatError(f"photos in {folder} have {len(counts)} sizes: {'; '.join(parts)}; one camera cannot "
                           "describe them: set photos.sfm.camera_mode: per_image or resize them to one size")
    return sizes


#: How libjpeg's warnings that the compressed data is damaged begin (jerror.h: JWRN_HIT_MARKER, JWRN_HUFF_BAD_CODE,
#: JWRN_ARITH_BAD_CODE, JWRN_MUST_RESYNC, JWRN_EXTRANEOUS_DATA, JWRN_JPEG_EOF). Its other warnings (a JFIF revision,
#: scan parameters a baseline file should not carry) are about headers: the pixels decode as written.
_DAMAGE_WARNINGS = ("Corrupt JPEG data:", "Premature end of JPEG file")
#: A malformed ICC profile segment: a "corrupt data" warning that is not about the pixels.
_BENIGN_WARNINGS = ("bad ICC marker",)
#: Bytes between the last scan and the end-of-image marker: up to this many are padding (webcams and some cameras
#: write a few in intact files); more are data that a damaged scan left unread.
_PADDING_BYTES = 16
_PADDING = re.compile(r"(\d+) extraneous bytes before marker 0xd9")


def jpeg_damage(data: bytes) -> str | None:
    """libjpeg's warning when JPEG data decodes only by recovering from damage inside it, else None.

    Parameters
    ----------
    data : bytes
        A whole image file. Anything that does not start with a JPEG start-of-image marker gives None.

    Returns
    -------
    str or None
        The first line of libjpeg's first warning (e.g. "Corrupt JPEG data: premature end of data segment") when
        it says the compressed data is corrupt; None for a clean JPEG, for data after the end-of-image marker
        (camera trailers, MPO), for up to 16 bytes before that marker after the last scan (padding, which webcams
        write), for warnings about headers, and for JPEG kinds simplejpeg does not decode (Pillow has then
        decoded them).
        The strict decode stops at the first warning, so damage after a header warning is not seen.

    Examples
    --------
    >>> import io
    >>> from PIL import Image
    >>> buf = io.BytesIO()
    >>> Image.new("RGB", (64, 48), (200, 30, 30)).save(buf, "JPEG")
    >>> jpeg_damage(buf.getvalue()) is None
    True
    """
    if data[:2] != b"\xff\xd8":
        return None
    import simplejpeg  # imported here: only photo folders need it

    try:
        simplejpeg.decode_jpeg(data, strict=True)
    except ValueError as exc:
        message = str(exc).splitlines()[0] if str(exc) else ""
        padding = _PADDING.search(message)
        if padding is not None and int(padding.group(1)) <= _PADDING_BYTES:
            return None
        if message.startswith(_DAMAGE_WARNINGS) and not any(w in message for w in _BENIGN_WARNINGS):
            return message
    return None


@contextmanager
def _open_whole(path: str | Path) -> Iterator[Image.Image]:
    """A PIL image decoded in full; ValueError for a JPEG that decodes only by recovering from damage."""
    with Image.open(path) as im:  # from the path, so that Pillow's messages name the file
        im.load()  # decodes every byte: a truncated file fails here, not at SIFT time
        damage = jpeg_damage(Path(path).read_bytes()) if im.format in ("JPEG", "MPO") else None
        if damage is not None:
            raise ValueError(damage)
        yield im


def load_rgb(path: str | Path, downscale: int = 1) -> np.ndarray:
    """An image as float32 RGB in [0, 1], optionally downscaled by an integer factor (area averaging).

    Parameters
    ----------
    path : str or Path
    downscale : int
        The output is ``round(W / downscale) x round(H / downscale)``.

    Returns
    -------
    ndarray, shape (H', W', 3), float32

    Raises
    ------
    OSError, SyntaxError, ValueError
        Pillow's errors for a file it cannot decode whole; ValueError with libjpeg's warning for a JPEG that decodes
        only by recovering from damage (:func:`jpeg_damage`).
    """
    with _open_whole(path) as im:
        im = im.convert("RGB")
        if downscale > 1:
            size = (max(1, round(im.width / downscale)), max(1, round(im.height / downscale)))
            im = im.resize(size, Image.Resampling.BOX)
        return np.asarray(im, dtype=np.float32) / 255.0


#: JPEG segments kept by :func:`strip_metadata`: APP0 (JFIF), APP2 (ICC colour profile) and APP14 (Adobe colour
#: transform) say how to decode the pixels; every other APPn (EXIF and XMP in APP1, IPTC in APP13, vendor data) and
#: comments are dropped.
_JPEG_KEPT_APP = {0xE0, 0xE2, 0xEE}


def _jpeg_without_metadata(data: bytes) -> bytes:
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG file (no SOI marker)")
    out, i = [data[:2]], 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ValueError(f"bad JPEG marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0xDA:  # start of scan: the entropy-coded data and everything after it stay as they are
            out.append(data[i:])
            return b"".join(out)
        length = int.from_bytes(data[i + 2:i + 4], "big")
        segment = data[i:i + 2 + length]
        if not ((0xE0 <= marker <= 0xEF and marker not in _JPEG_KEPT_APP) or marker == 0xFE):
            out.append(segment)
        i += 2 + length
    raise ValueError("JPEG file ends before its image data")


def strip_metadata(path: str | Path) -> None:
    """Remove the metadata (EXIF with GPS position, camera serial, owner and date; XMP; IPTC; comments) from an
    image file in place, leaving its pixels bit for bit as they were.

    JPEG files lose their metadata segments without being decoded (no second lossy compression); PNG and TIFF files
    are written again without it (lossless formats), keeping an ICC colour profile.

    Parameters
    ----------
    path : str or Path
        A ``.jpg``/``.jpeg``, ``.png`` or ``.tif``/``.tiff`` file; replaced atomically.

    Raises
    ------
    CtsplatError
        When the file is not a readable image of its suffix.
    """
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            if path.suffix.lower() in (".jpg", ".jpeg"):
                tmp.write_bytes(_jpeg_without_metadata(path.read_bytes()))
            else:
                with Image.open(path) as im:
                    im.load()
                    icc = im.info.get("icc_profile")
                    # a copy holds the pixels only: saving the opened TIFF itself would copy its XMP, IPTC and
                    # Photoshop blocks into the new file
                    im.copy().save(tmp, format=im.format, **({"icc_profile": icc} if icc else {}))
    except (OSError, ValueError) as exc:
        raise CtsplatError(f"cannot remove the metadata of {path}: {str(exc).splitlines()[0]}") from exc
