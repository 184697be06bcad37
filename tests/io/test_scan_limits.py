"""Scan files are checked from their headers before anything is allocated or decompressed: PLY element
counts, binary STL's triangle count, OBJ lines, PCD's POINTS and binary_compressed sizes; and LZF decodes
as liblzf does, overlapping back references included."""

from __future__ import annotations

import struct
from functools import partial

import lzf
import numpy as np
import pytest
import trimesh

from bodyfit.io.errors import FileLimitError
from bodyfit.io.pcd import LZF_MAX_RATIO, lzf_decompress, read_pcd
from bodyfit.io.scans import ScanError, load_scan
from tests.io.checks import peak_memory, refused


@pytest.fixture(scope="module")
def body() -> trimesh.Trimesh:
    """A 1.7 m capsule (+Y up), 1,026 vertices and 2,048 faces."""
    m = trimesh.creation.capsule(height=1.3, radius=0.2, count=[32, 32])
    return trimesh.Trimesh(m.vertices[:, [0, 2, 1]] + [0.0, 0.85, 0.0], m.faces[:, [0, 2, 1]], process=False)


def ply_header(n: int, faces: int = 0, form: str = "binary_little_endian") -> bytes:
    lines = ["ply", f"format {form} 1.0", f"element vertex {n}", "property float x", "property float y"]
    lines += ["property float z"]
    if faces:
        lines += [f"element face {faces}", "property list uchar int vertex_indices"]
    return ("\n".join([*lines, "end_header"]) + "\n").encode()


# -- PLY -----------------------------------------------------------------------------------------------------
def test_a_ply_header_claiming_more_than_the_file_holds_is_corrupt() -> None:
    data = ply_header(10**9) + bytes(36)
    with peak_memory(2):
        refused(
            ScanError,
            "declares 1,000,000,000 vertex, at least 12,000,000,000 bytes of data, but the file has 36",
            lambda: load_scan(data, format="ply", max_points=2_000_000),
        )
    faces = ply_header(3, faces=10**8) + bytes(36) + bytes(13)  # one face record of 10**8
    refused(ScanError, "at least 100,000,036 bytes", lambda: load_scan(faces, format="ply"))
    ascii_lie = ply_header(5_000_000, form="ascii") + b"0 0 0\n1 1 1\n"
    refused(
        ScanError,
        "the ascii PLY header declares 5,000,000 vertex",
        lambda: load_scan(ascii_lie, format="ply"),
    )
    padded = ply_header(1, form="ascii") + b"0 0 0\n" + b"1\n" * 5000  # every line would be parsed
    refused(
        ScanError, "5,001 lines of data but its header declares 1", lambda: load_scan(padded, format="ply")
    )


def test_ply_counts_over_the_limits(body: trimesh.Trimesh) -> None:
    for encoding in ("binary", "ascii"):
        data = trimesh.exchange.ply.export_ply(body, encoding=encoding)
        assert load_scan(data, format="ply", max_points=len(body.vertices)).n_points == len(body.vertices)
        refused(
            FileLimitError,
            "declares 1,026 points; the limit is 1,000: thin it",
            partial(load_scan, data, format="ply", max_points=1000),
        )
    twice = trimesh.Trimesh(body.vertices, np.r_[body.faces, body.faces], process=False)
    faces = trimesh.exchange.ply.export_ply(twice, encoding="binary")  # 4,096 faces: over 2 x 1,026
    refused(
        FileLimitError,
        "declares 4,096 faces; the limit is 2,052",
        lambda: load_scan(faces, format="ply", max_points=1026),
    )


# -- STL and OBJ ---------------------------------------------------------------------------------------------
def test_binary_stl_triangle_count_against_the_file_length(body: trimesh.Trimesh) -> None:
    data = trimesh.exchange.stl.export_stl(body)
    assert load_scan(data, format="stl").n_points == len(body.vertices)
    lie = data[:80] + struct.pack("<I", 10**9) + data[84:]
    with peak_memory(2):
        refused(
            ScanError,
            "declares 1,000,000,000 triangles (50,000,000,084 bytes) but the file has",
            lambda: load_scan(lie, format="stl"),
        )
    refused(ScanError, "declares 2,048 triangles", lambda: load_scan(data[:-50], format="stl"))  # truncated
    refused(
        FileLimitError,
        "declares 2,048 faces; the limit is 1,000",
        lambda: load_scan(data, format="stl", max_points=500),
    )
    text = trimesh.exchange.stl.export_stl_ascii(body).encode()
    refused(FileLimitError, "declares 2,048 faces", lambda: load_scan(text, format="stl", max_points=500))


def test_obj_lines_against_the_limits(body: trimesh.Trimesh) -> None:
    data = trimesh.exchange.obj.export_obj(body).encode()
    assert load_scan(data, format="obj", max_points=1026).n_points == 1026
    refused(
        FileLimitError,
        "declares 1,026 points; the limit is 1,000",
        lambda: load_scan(data, format="obj", max_points=1000),
    )


# -- PCD -----------------------------------------------------------------------------------------------------
def pcd(n: int, data: str, body: bytes = b"", width: int | None = None) -> bytes:
    header = (
        "VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
        f"WIDTH {n if width is None else width}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    )
    return header.encode() + body


def pcl_compressed(points: np.ndarray, rgb: int = 0x00FF8040) -> bytes:
    """A binary_compressed PCD as PCL writes it: the fields one after the other, compressed by liblzf."""
    xyz = np.ascontiguousarray(points, "<f4")
    raw = b"".join(xyz[:, i].tobytes() for i in range(3)) + np.full(len(points), rgb, "<u4").tobytes()
    packed = lzf.compress(raw)
    return pcd(len(points), "binary_compressed", struct.pack("<II", len(packed), len(raw)) + packed)


def test_a_pcd_declaring_3_gb_in_134_bytes_is_refused_before_decompressing() -> None:
    n = 3 * 2**30 // 16  # 16 bytes a point: 3 GiB raw, a size that fits PCL's uint32 field
    data = pcd(n, "binary_compressed", struct.pack("<II", 10, n * 16) + bytes(10))
    with peak_memory(2):
        refused(
            ScanError, f"more than LZF can expand ({LZF_MAX_RATIO}x)", lambda: load_scan(data, format="pcd")
        )
        refused(
            ScanError,
            "PCD binary data has 0 bytes; POINTS 201326592",
            lambda: load_scan(pcd(n, "binary"), format="pcd"),
        )
        refused(ScanError, "PCD ascii data has 0 bytes", lambda: load_scan(pcd(n, "ascii"), format="pcd"))


def test_pcd_points_and_raw_size_against_the_limits() -> None:
    points = np.random.default_rng(0).uniform(0.0, 1.7, (5000, 3))
    data = pcl_compressed(points)
    assert load_scan(data, format="pcd", max_points=5000).n_points == 5000
    refused(
        FileLimitError,
        "the PCD declares 5,000 points; the limit is 4,999",
        lambda: load_scan(data, format="pcd", max_points=4999),
    )
    refused(
        FileLimitError,
        "5,000 points of 16 bytes = 80,000 bytes; the limit is 79,999 bytes",
        lambda: load_scan(data, format="pcd", max_bytes=79_999),
    )
    refused(
        ScanError,
        "POINTS 5000 but WIDTH x HEIGHT = 4000 x 1",
        lambda: load_scan(pcd(5000, "binary", width=4000), format="pcd"),
    )


def test_ascii_pcd_rows() -> None:
    rows = np.random.default_rng(1).uniform(0.0, 1.7, (400, 3))
    text = "".join(f"{x} {y} {z} 7\n" for x, y, z in rows).encode()
    points, _ = read_pcd(pcd(400, "ascii", text))
    np.testing.assert_allclose(points, rows)
    refused(
        ValueError,
        "has more than rows; the header says POINTS 399",
        lambda: read_pcd(pcd(399, "ascii", text)),
    )
    refused(
        ValueError,
        "has 400 rows; the header says POINTS 401",
        lambda: read_pcd(pcd(401, "ascii", text + b" ")),
    )
    refused(
        ValueError,
        "not 4 numbers per line",
        lambda: read_pcd(pcd(400, "ascii", text.replace(b" 7\n", b" x\n"))),
    )


# -- LZF -----------------------------------------------------------------------------------------------------
def reference_lzf(data: bytes, size: int) -> tuple[bytes, int]:
    """liblzf's decoder written out byte by byte (slow, obviously right); also counts the back
    references that overlap their own output."""
    out, ip, overlaps = bytearray(), 0, 0
    while ip < len(data):
        ctrl = data[ip]
        ip += 1
        if ctrl < 32:
            out += data[ip : ip + ctrl + 1]
            ip += ctrl + 1
            continue
        length = ctrl >> 5
        if length == 7:
            length += data[ip]
            ip += 1
        ref = len(out) - ((ctrl & 0x1F) << 8) - data[ip] - 1
        ip += 1
        assert ref >= 0
        overlaps += ref + length + 2 > len(out)
        for k in range(length + 2):
            out.append(out[ref + k])
    assert len(out) == size
    return bytes(out), overlaps


def test_lzf_overlapping_back_references_decode_as_liblzf_does() -> None:
    # "ab", then 264 bytes copied from one back (each byte its own source), then 9 from two back
    stream = b"\x01ab" + bytes([7 << 5, 255, 0]) + bytes([7 << 5, 0, 1])
    expected, overlaps = reference_lzf(stream, 2 + 264 + 9)
    assert expected == b"ab" + b"b" * 264 + b"b" * 9 and overlaps == 2
    assert lzf_decompress(stream, len(expected)) == expected


def test_a_pcl_compressed_cloud_matches_a_reference_decode() -> None:
    rng = np.random.default_rng(2)
    points = np.repeat(rng.uniform(0.0, 1.7, (700, 3)), 3, axis=0)  # repeats: many back references
    data = pcl_compressed(points)
    body = data[data.index(b"DATA binary_compressed\n") + 23 :]
    packed, size = struct.unpack("<II", body[:8])
    raw, overlaps = reference_lzf(body[8 : 8 + packed], size)
    assert overlaps > 0  # the constant rgb field is a run: LZF copies it onto itself
    assert lzf_decompress(body[8 : 8 + packed], size) == raw
    got, normals = read_pcd(data)
    expected = np.frombuffer(raw[: 12 * len(points)], "<f4").reshape(3, -1).T
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got, points.astype("<f4"))
    assert normals is None


def test_corrupt_lzf() -> None:
    refused(
        ValueError, "corrupt LZF data", lambda: lzf_decompress(b"\x01ab" + bytes([1 << 5, 9]), 5)
    )  # before the start
    refused(ValueError, "decompressed to 2 bytes, header says 5", lambda: lzf_decompress(b"\x01ab", 5))
    refused(ValueError, "decompressed to more bytes, header says 1", lambda: lzf_decompress(b"\x01ab", 1))
    assert lzf_decompress(b"", 0) == b""
    refused(ValueError, "corrupt LZF data", lambda: lzf_decompress(b"", 4))
