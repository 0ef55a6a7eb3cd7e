"""PLY files: the vertex element of ASCII and binary PLY (Gaussian models, point clouds).

A PLY file is an ASCII header -- ``ply``, ``format ascii|binary_little_endian|binary_big_endian 1.0``,
``comment`` lines, ``element NAME COUNT`` lines each followed by that element's ``property TYPE NAME`` lines,
``end_header`` -- and a body holding the elements in header order. Here only scalar properties of a leading
``vertex`` element are read and written: that is what COLMAP, 3DGS viewers and ctsplat write.

Two layouts are used in ctsplat: the Gaussian model (binary little-endian float32 properties in the 3DGS order,
written by :meth:`ctsplat.splat.gaussians.Gaussians.to_ply`) and point clouds (``x y z`` in mm plus optional
``red green blue`` uchar colours, :func:`write_points_ply` / :func:`read_ply_points`).

References
----------
.. [1] G. Turk, "The PLY Polygon File Format", 1994.
.. [2] B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian Splatting for Real-Time Radiance Field
   Rendering", ACM Transactions on Graphics 42(4), 2023 (the Gaussian PLY layout).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ctsplat.utils import CtsplatError, atomic_path

__all__ = ["PLY_TYPES", "write_ply_vertices", "read_ply_vertices", "write_points_ply", "read_ply_points"]

#: PLY scalar property type -> NumPy dtype code (both spellings of the PLY specification)
PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


def write_ply_vertices(
    path: str | Path,
    columns: Sequence[tuple[str, str, ArrayLike]],
    *,
    fmt: str = "binary_little_endian",
    comments: Sequence[str] = (),
) -> None:
    """Write a PLY file whose only element is ``vertex``, one scalar property per column (atomic write).

    Parameters
    ----------
    path : str or Path
        Output file; its folder is created.
    columns : sequence of (name, ply_type, values)
        The properties in file order. ``ply_type`` is a key of :data:`PLY_TYPES` (``"float"``, ``"uchar"``, ...);
        ``values`` has shape (N,), the same N for every column, and is cast to that type (units are the
        caller's).
    fmt : {"binary_little_endian", "binary_big_endian", "ascii"}
        Body encoding. ASCII writes ``float`` values with six decimals (``%.6f``), ``double`` with 17
        significant digits and integer types as integers (truncated).
    comments : sequence of str
        ``comment`` lines of the header, written after ``element vertex N`` (single lines).
    """
    if any("\n" in c or "\r" in c for c in comments):
        raise CtsplatError("PLY comments must be single lines")
    if fmt not in _FORMATS:
        raise CtsplatError(f"unknown PLY format {fmt!r}; expected one of {', '.join(_FORMATS)}")
    cols = []
    for name, ply_type, values in columns:
        if ply_type not in PLY_TYPES:
            raise CtsplatError(f"PLY property {name!r}: unknown type {ply_type!r}; expected one of "
                               f"{', '.join(PLY_TYPES)}")
        cols.append((name, ply_type, np.asarray(values).reshape(-1)))
    n = len(cols[0][2]) if cols else 0
    for name, _, v in cols:
        if len(v) != n:
            raise CtsplatError(f"PLY property {name!r} has {len(v)} values, expected {n} (one per vertex)")
    # the comments follow the element line: the reference 3DGS viewer (SIBR) reads the vertex count from the
    # header's third line
    header = ["ply", f"format {fmt} 1.0", f"element vertex {n}", *(f"comment {c}" for c in comments)]
    header += [f"property {ply_type} {name}" for name, ply_type, _ in cols]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii")
    if fmt == "ascii":
        conv, spec = [], []
        for _, ply_type, v in cols:
            code = PLY_TYPES[ply_type]
            if code[0] == "f":
                conv.append(v.astype(np.float64).tolist())
                spec.append("%.6f" if code == "f4" else "%.17g")
            else:
                conv.append(v.astype(np.int64).tolist())
                spec.append("%d")
        line = " ".join(spec)
        body = "".join(line % row + "\n" for row in zip(*conv, strict=True)).encode("ascii")
    else:
        order = _FORMATS[fmt]
        arr = np.zeros(n, dtype=[(name, order + PLY_TYPES[ply_type]) for name, ply_type, _ in cols])
        for name, _, v in cols:
            arr[name] = v
        body = arr.tobytes()
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(head)
        fh.write(body)


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:
    """The scalar properties of a PLY file's vertex element (ASCII or binary; the vertex element first).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    dict of str to ndarray
        ``{property name: values (N,)}`` in header order: binary files keep the stored type (native byte order),
        ASCII values are float64. Empty when the file has no vertex element.
    """
    path = Path(path)
    if not path.is_file():
        raise CtsplatError(f"PLY file {path} does not exist")
    raw = path.read_bytes()
    end = re.search(rb"^end_header\r?(\n|$)", raw, flags=re.MULTILINE)  # the line, not the words in a comment
    if not re.match(rb"ply\r?\n", raw) or end is None:
        raise CtsplatError(f"{path} is not a PLY file (no 'ply' magic / end_header)")
    header = raw[:end.start()].decode("ascii", "replace").splitlines()[1:]
    body = raw[end.end():]
    fmt, count, props, element, elements = "ascii", 0, [], None, []
    for line in header:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        try:
            if parts[0] not in ("format", "element", "property"):
                raise ValueError("unknown keyword")
            if parts[0] == "format":
                fmt = parts[1]
                if parts[2] != "1.0":
                    raise CtsplatError(f"{path}: PLY format version {parts[2]!r}; this reader reads 1.0")
            elif parts[0] == "element":
                element = parts[1]
                elements.append(element)
                if element == "vertex":
                    count = int(parts[2])
                    if count < 0:
                        raise ValueError("negative count")
            elif parts[0] == "property" and element == "vertex":
                if parts[1] == "list":
                    raise CtsplatError(f"{path}: list properties on vertices are not supported")
                if parts[1] not in PLY_TYPES:
                    raise CtsplatError(f"{path}: unknown PLY property type {parts[1]!r}")
                if any(parts[2] == name for name, _ in props):
                    raise CtsplatError(f"{path}: vertex property {parts[2]!r} appears twice in the PLY header")
                props.append((parts[2], PLY_TYPES[parts[1]]))
        except CtsplatError:
            raise
        except (ValueError, IndexError):
            raise CtsplatError(f"{path}: malformed PLY header line {line.strip()!r}") from None
    if fmt not in _FORMATS:
        raise CtsplatError(f"{path}: unknown PLY format {fmt!r}; expected one of {', '.join(_FORMATS)}")
    if "vertex" not in elements:
        return {}
    if elements[0] != "vertex":
        raise CtsplatError(f"{path}: the vertex element must come first in the PLY body")
    names = [p[0] for p in props]
    if count == 0:
        return {nm: np.zeros(0, dtype=np.float64 if fmt == "ascii" else t) for nm, t in props}
    if fmt == "ascii":
        rows = body.decode("ascii", "replace").splitlines()[:count]
        if len(rows) < count:
            raise CtsplatError(f"{path}: ASCII body has fewer than the {count} vertex rows its header declares")
        table = np.empty((count, len(props)))
        for i, r in enumerate(rows):
            values = r.split()
            try:
                if len(values) != len(props):
                    raise ValueError
                table[i] = [float(v) for v in values]
            except ValueError:
                raise CtsplatError(f"{path}: vertex row {i + 1} ({r.strip()[:60]!r}) does not hold {len(props)} "
                                   "numbers") from None
        return {nm: table[:, i] for i, nm in enumerate(names)}
    dt = np.dtype([(nm, _FORMATS[fmt] + t) for nm, t in props])
    if len(body) < count * dt.itemsize:
        raise CtsplatError(f"{path}: truncated PLY body ({len(body)} bytes for {count} vertices of "
                           f"{dt.itemsize} bytes)")
    arr = np.frombuffer(body, dtype=dt, count=count)
    return {nm: arr[nm].astype(arr[nm].dtype.newbyteorder("=")) for nm in names}


def write_points_ply(path: str | Path, xyz: ArrayLike, rgb: ArrayLike | None = None) -> None:
    """ASCII PLY point cloud, written atomically.

    Parameters
    ----------
    path : str or Path
    xyz : array_like (N, 3)
        Point positions, world mm (written with six decimals).
    rgb : array_like (N, 3) or None
        Optional colours, 0..255 (written as uchar ``red green blue``).
    """
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    cols = [("x", "float", xyz[:, 0]), ("y", "float", xyz[:, 1]), ("z", "float", xyz[:, 2])]
    if rgb is not None:
        c = np.asarray(rgb).reshape(-1, 3)
        cols += [("red", "uchar", c[:, 0]), ("green", "uchar", c[:, 1]), ("blue", "uchar", c[:, 2])]
    write_ply_vertices(path, cols, fmt="ascii")


def read_ply_points(path: str | Path) -> np.ndarray:
    """Vertex positions of a PLY point cloud (ASCII or binary, vertex element first; as COLMAP / 3DGS tools write).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    ndarray (P, 3) float64
        ``x, y, z`` per vertex, in the file's units (world mm for the point clouds of the sfm step).
    """
    path = Path(path)
    if not path.exists():
        raise CtsplatError(f"SfM point cloud {path} does not exist; run the sfm step first")
    cols = read_ply_vertices(path)
    if not {"x", "y", "z"} <= set(cols):
        raise CtsplatError(f"{path}: vertex element lacks x/y/z properties")
    return np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(float)
