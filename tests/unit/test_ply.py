"""PLY vertex files (ctsplat.formats.ply): point clouds written by the sfm step and read by sfm seeding, the
generic vertex writer/reader behind the Gaussian PLY, and the errors for files it cannot read."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from ctsplat.formats.ply import read_ply_points, read_ply_vertices, write_ply_vertices, write_points_ply
from ctsplat.utils import CtsplatError


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_read_ply_points(tmp_path: Path, fmt: str) -> None:
    """x, y, z of a hand-written ASCII or little-endian PLY with colours read back; a missing file is named."""
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(7, 3))
    rgb = rng.integers(0, 255, size=(7, 3)).astype(np.uint8)
    head = (f"ply\nformat {fmt} 1.0\nelement vertex 7\nproperty float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    path = tmp_path / "p.ply"
    if fmt == "ascii":
        lines = [" ".join([*(f"{v:.9g}" for v in p), *(str(c) for c in q)]) for p, q in zip(xyz, rgb, strict=True)]
        body = "\n".join(lines) + "\n"
        path.write_text(head + body)
    else:
        dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
        arr = np.zeros(7, dt)
        arr["x"], arr["y"], arr["z"] = xyz.T
        arr["r"], arr["g"], arr["b"] = rgb.T
        path.write_bytes(head.encode() + arr.tobytes())
    got = read_ply_points(path)
    assert np.allclose(got, xyz.astype(np.float32), atol=1e-6)
    with pytest.raises(CtsplatError, match="does not exist"):
        read_ply_points(tmp_path / "missing.ply")


def test_write_points_ply_roundtrip(tmp_path: Path) -> None:
    """write_points_ply writes one ASCII line per point holding its x, y, z."""
    xyz = np.array([[0.0, 1.5, -2.25], [10.0, 20.0, 30.0]])
    write_points_ply(tmp_path / "p.ply", xyz)
    lines = (tmp_path / "p.ply").read_text().splitlines()
    assert "element vertex 2" in lines
    body = np.array([[float(v) for v in ln.split()] for ln in lines[lines.index("end_header") + 1:]])
    np.testing.assert_allclose(body, xyz)


def test_points_file_layout_with_colours(tmp_path: Path) -> None:
    """The exact ASCII text of a coloured point cloud, and an empty cloud reads back as shape (0, 3)."""
    # the exact text COLMAP-style readers get: six decimals, integer colours (truncated), one line per point
    write_points_ply(tmp_path / "c.ply", [[1.0, -2.5, 12345.678901], [0, 0, 1e-7]], rgb=[[255, 0, 7.9], [1, 2, 3]])
    assert (tmp_path / "c.ply").read_text() == (
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
        "1.000000 -2.500000 12345.678901 255 0 7\n0.000000 0.000000 0.000000 1 2 3\n"
    )
    np.testing.assert_allclose(read_ply_points(tmp_path / "c.ply"), [[1.0, -2.5, 12345.678901], [0, 0, 0]])
    write_points_ply(tmp_path / "e.ply", np.zeros((0, 3)))
    assert read_ply_points(tmp_path / "e.ply").shape == (0, 3)


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_vertex_roundtrip_keeps_names_order_and_types(tmp_path: Path, fmt: str) -> None:
    """Writer then reader keep property names, order, comments, binary dtypes and values."""
    rng = np.random.default_rng(1)
    cols = [("x", "float", rng.normal(size=5)), ("w", "double", rng.normal(size=5)),
            ("k", "uchar", rng.integers(0, 255, 5)), ("s", "short", rng.integers(-300, 300, 5))]
    write_ply_vertices(tmp_path / "v.ply", cols, fmt=fmt, comments=["made by a test"])
    raw = (tmp_path / "v.ply").read_bytes()
    assert b"comment made by a test\n" in raw.split(b"end_header")[0]
    got = read_ply_vertices(tmp_path / "v.ply")
    assert list(got) == ["x", "w", "k", "s"]
    if fmt != "ascii":
        assert [got[k].dtype for k in got] == [np.float32, np.float64, np.uint8, np.int16]
        np.testing.assert_array_equal(got["x"], cols[0][2].astype(np.float32))
        np.testing.assert_array_equal(got["w"], cols[1][2])
    else:
        np.testing.assert_allclose(got["x"], cols[0][2], atol=5e-7)
        np.testing.assert_allclose(got["w"], cols[1][2], rtol=1e-15)
    np.testing.assert_array_equal(got["k"], cols[2][2])
    np.testing.assert_array_equal(got["s"], cols[3][2])


def test_unreadable_files_say_why(tmp_path: Path) -> None:
    """Malformed, truncated, list-property, vertex-not-first and missing files raise errors that say why."""
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply\n")
    with pytest.raises(CtsplatError, match="not a PLY file"):
        read_ply_vertices(bad)
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n1 0\n")
    with pytest.raises(CtsplatError, match="list properties"):
        read_ply_vertices(bad)
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty float a\n"
                    b"element vertex 1\nproperty float x\nend_header\n" + bytes(8))
    with pytest.raises(CtsplatError, match="vertex element must come first"):
        read_ply_vertices(bad)
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n"
                    + bytes(8))
    with pytest.raises(CtsplatError, match="truncated"):
        read_ply_vertices(bad)
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float q\nend_header\n1\n")
    with pytest.raises(CtsplatError, match="lacks x/y/z"):
        read_ply_points(bad)
    with pytest.raises(CtsplatError, match="does not exist"):
        read_ply_vertices(tmp_path / "missing.ply")
    head = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n"
    for body, needle in ((b"1 2\n3\n", r"vertex row 2 \('3'\) does not hold 2 numbers"),
                         (b"1 2\n", "fewer than the 2 vertex rows"),
                         (b"1 2\n3 abc\n", r"vertex row 2 \('3 abc'\) does not hold 2 numbers")):
        bad.write_bytes(head + body)
        with pytest.raises(CtsplatError, match=needle):
            read_ply_vertices(bad)
    for line in (b"element vertex abc", b"element vertex -1", b"format", b"property float"):
        bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
                        .replace(b"element vertex 1" if line.startswith(b"element") else
                                 b"format binary_little_endian 1.0" if line == b"format" else
                                 b"property float x", line) + b"end_header\n" + bytes(8))
        with pytest.raises(CtsplatError, match=f"malformed PLY header line '{line.decode()}'"):
            read_ply_vertices(bad)
    with pytest.raises(CtsplatError, match="expected 2"):
        write_ply_vertices(tmp_path / "o.ply", [("x", "float", [1.0, 2.0]), ("y", "float", [1.0])])
    ok = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n"
    for old, new, needle in ((b"property float y", b"property float x", "property 'x' appears twice"),
                             (b"element vertex", b"elemnt vertex", "malformed PLY header line 'elemnt vertex 1'"),
                             (b"ply\n", b"plyfoo\n", "not a PLY file"),
                             (b"ascii 1.0", b"ascii 2.0", "PLY format version '2.0'"),
                             (b"1 2\n", b"1 2 3\n", r"vertex row 1 \('1 2 3'\) does not hold 2 numbers")):
        bad.write_bytes(ok.replace(old, new, 1))
        with pytest.raises(CtsplatError, match=needle):
            read_ply_vertices(bad)
    # the words end_header inside a comment do not end the header
    bad.write_bytes(ok.replace(b"element", b"comment made before end_header was written\nelement"))
    assert read_ply_vertices(bad)["y"].tolist() == [2.0]


def test_big_endian_file_written_by_hand_reads_back(tmp_path: Path) -> None:
    """A binary_big_endian body built with '>' numpy dtypes reads back as the same values (native order)."""
    x = np.array([1.5, -2.25, 3.0e6], np.float64)
    d = np.array([np.pi, -1e-300, 7.0])
    s = np.array([-300, 2, 32767])
    u = np.array([0, 70000, 4_000_000_000])
    dt = np.dtype([("x", ">f4"), ("d", ">f8"), ("s", ">i2"), ("u", ">u4")])
    arr = np.zeros(3, dt)
    arr["x"], arr["d"], arr["s"], arr["u"] = x, d, s, u
    head = (b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty double d\n"
            b"property short s\nproperty uint u\nend_header\n")
    (tmp_path / "be.ply").write_bytes(head + arr.tobytes())
    got = read_ply_vertices(tmp_path / "be.ply")
    assert list(got) == ["x", "d", "s", "u"]
    np.testing.assert_array_equal(got["x"], x.astype(np.float32))
    np.testing.assert_array_equal(got["d"], d)
    np.testing.assert_array_equal(got["s"], s)
    np.testing.assert_array_equal(got["u"], u)
    assert all(v.dtype.isnative for v in got.values())


def test_big_endian_writer_bytes_parse_by_hand(tmp_path: Path) -> None:
    """write_ply_vertices(fmt='binary_big_endian') lays the body out as big-endian '>f4' / '>i4' records."""
    x = np.array([1.0, -0.5, 1234.5])
    k = np.array([-7, 65536, 3])
    write_ply_vertices(tmp_path / "w.ply", [("x", "float", x), ("k", "int", k)], fmt="binary_big_endian")
    raw = (tmp_path / "w.ply").read_bytes()
    head, body = raw.split(b"end_header\n")
    assert b"format binary_big_endian 1.0\n" in head
    assert body[:8] == struct.pack(">fi", 1.0, -7)
    arr = np.frombuffer(body, dtype=np.dtype([("x", ">f4"), ("k", ">i4")]))
    np.testing.assert_array_equal(arr["x"], x)
    np.testing.assert_array_equal(arr["k"], k)


@pytest.mark.parametrize("ply_type", ["char", "int8"])
def test_signed_byte_property_reads_negative(tmp_path: Path, ply_type: str) -> None:
    """A char / int8 property is signed: the bytes 0x80 and 0xff read back as -128 and -1."""
    vals = np.array([-128, -1, 0, 1, 127])
    body = struct.pack(">5b", *vals.tolist())  # one signed byte per vertex (byte order is moot for one byte)
    assert body == bytes([0x80, 0xFF, 0x00, 0x01, 0x7F])
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty {ply_type} c\nend_header\n".encode()
    (tmp_path / "c.ply").write_bytes(head + body)
    got = read_ply_vertices(tmp_path / "c.ply")["c"]
    assert got.dtype == np.int8
    assert got.tolist() == vals.tolist()
    write_ply_vertices(tmp_path / "w.ply", [("c", ply_type, vals)])
    assert (tmp_path / "w.ply").read_bytes().split(b"end_header\n")[1] == body
    assert read_ply_vertices(tmp_path / "w.ply")["c"].tolist() == vals.tolist()


def test_gaussian_ply_opacity_of_a_radiative_model(tmp_path: Path) -> None:
    """Without an opacity, to_ply writes logit(clamp(1 - exp(-ρ·2·s̄), 0.01, 0.99)), s̄ the mean of the three scales."""
    from ctsplat.splat.gaussians import Gaussians

    scales = np.array([[1.0, 2.0, 6.0], [0.5, 0.5, 0.5], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    rho = np.array([0.1, 0.3, 20.0, 1e-4])
    g = Gaussians.from_values(np.zeros((4, 3)), scales, rho, dtype=torch.float64)
    g.to_ply(tmp_path / "g.ply")
    raw = (tmp_path / "g.ply").read_bytes()
    head, body = raw.split(b"end_header\n")
    props = [ln.split()[-1] for ln in head.decode().splitlines() if ln.startswith("property")]
    assert all(ln.split()[1] == "float" for ln in head.decode().splitlines() if ln.startswith("property"))
    table = np.frombuffer(body, dtype="<f4").reshape(4, len(props)).astype(np.float64)
    opacity = table[:, props.index("opacity")]
    alpha = [1.0 - math.exp(-r * 2.0 * (s[0] + s[1] + s[2]) / 3.0) for r, s in zip(rho, scales, strict=True)]
    alpha = [min(max(a, 0.01), 0.99) for a in alpha]
    np.testing.assert_allclose(alpha[:2], [1 - math.exp(-0.1 * 2 * 3.0), 1 - math.exp(-0.3 * 2 * 0.5)])
    assert alpha[2:] == [0.99, 0.01]
    expected = [math.log(a / (1.0 - a)) for a in alpha]
    np.testing.assert_allclose(opacity, expected, rtol=1e-5)
    np.testing.assert_allclose(table[:, props.index("density")], rho, rtol=1e-6)
