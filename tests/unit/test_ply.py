"""PLY vertex files (ctsplat.formats.ply): point clouds written by the sfm step and read by sfm seeding, the
generic vertex writer/reader behind the Gaussian PLY, and the errors for files it cannot read."""

from __future__ import annotations

import numpy as np
import pytest

from ctsplat.formats.ply import read_ply_points, read_ply_vertices, write_ply_vertices, write_points_ply
from ctsplat.utils import CtsplatError


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_read_ply_points(tmp_path, fmt: str) -> None:
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


def test_write_points_ply_roundtrip(tmp_path) -> None:
    xyz = np.array([[0.0, 1.5, -2.25], [10.0, 20.0, 30.0]])
    write_points_ply(tmp_path / "p.ply", xyz)
    lines = (tmp_path / "p.ply").read_text().splitlines()
    assert "element vertex 2" in lines
    body = np.array([[float(v) for v in ln.split()] for ln in lines[lines.index("end_header") + 1:]])
    np.testing.assert_allclose(body, xyz)


def test_points_file_layout_with_colours(tmp_path) -> None:
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
def test_vertex_roundtrip_keeps_names_order_and_types(tmp_path, fmt: str) -> None:
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


def test_unreadable_files_say_why(tmp_path) -> None:
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
    with pytest.raises(CtsplatError, match="expected 2"):
        write_ply_vertices(tmp_path / "o.ply", [("x", "float", [1.0, 2.0]), ("y", "float", [1.0])])
