"""A corpus of hostile and malformed requests for every endpoint, REST and gRPC, made on the fly.

Each case is refused by a correct server with a 4xx (REST) or a client-error status (gRPC) in well under a
second, without the server allocating much: zip bombs, .npy headers that lie about their size, pickled
object arrays and .pkl files, truncated and garbage files in every scan format, huge declared counts,
NaN / inf, degenerate geometry, wrong units, wrong keys and types. ``tests/e2e/test_hostile.py`` sends it
to a real server; ``benchmarks/reliability.py`` times it and measures the server's memory.

Sizes: ``bomb_mb`` is what the zip bombs decompress to (above any sane cap; the files stay small).
"""

from __future__ import annotations

import io
import json
import pickle
import struct
import time
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

SCAN, SEQUENCE, UPGRADE, SYNTHESIZE = "scan", "sequence", "upgrade", "synthesize"
N_VERTICES = 13_348  # the model's vertex count (frames of a registered sequence)


@dataclass(frozen=True)
class Case:
    """One hostile request.

    endpoint: SCAN / SEQUENCE / UPGRADE (an uploaded file) or SYNTHESIZE (a JSON body); filename and data:
    the upload (for SYNTHESIZE, data is the JSON body); fields: form fields (``units``, ``format``);
    grpc: whether the case also goes over gRPC (a file the gRPC request carries the same way), and
    grpc_only: a gRPC request with no REST twin (``grpc_request`` builds it).
    """

    name: str
    endpoint: str
    filename: str
    data: bytes
    fields: dict[str, str] = field(default_factory=dict)
    grpc: bool = True
    grpc_request: dict[str, Any] | None = None


# -- file builders -----------------------------------------------------------------------------------
def npz(**arrays: Any) -> bytes:
    """A regular compressed .npz (object arrays allowed, so pickles can be built)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def npy_header(shape: tuple[int, ...], dtype: str = "<f4", fortran: bool = False) -> bytes:
    """A version 1.0 .npy header declaring ``shape`` and ``dtype``, whatever data follows it."""
    text = repr({"descr": dtype, "fortran_order": fortran, "shape": tuple(shape)})
    pad = 64 - (10 + len(text) + 1) % 64
    text = text + " " * pad + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode("latin1")


def zip_members(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for name, payload in members.items():
            z.writestr(name, payload)
    return buf.getvalue()


def lying_npz(key: str, shape: tuple[int, ...], payload_bytes: int, dtype: str = "<f4") -> bytes:
    """An .npz whose ``key`` member declares ``shape`` but holds ``payload_bytes`` of zeros."""
    return zip_members({f"{key}.npy": npy_header(shape, dtype) + bytes(payload_bytes)})


def bomb_npz(key: str, shape: tuple[int, ...], extra: dict[str, bytes] | None = None) -> bytes:
    """A deflated .npz whose ``key`` member really holds ``shape`` float32 zeros (streamed: the file is small
    and making it never holds the decompressed bytes)."""
    header = npy_header(shape)
    total = int(np.prod(shape)) * 4
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    chunk = bytes(1 << 20)
    parts = [comp.compress(header)]
    crc = zlib.crc32(header)
    left = total
    while left:
        piece = chunk[: min(left, len(chunk))]
        parts.append(comp.compress(piece))
        crc = zlib.crc32(piece, crc)
        left -= len(piece)
    parts.append(comp.flush())
    data = b"".join(parts)
    return _raw_zip({f"{key}.npy": (data, crc, len(header) + total, 8)}, extra or {})


def _raw_zip(
    members: dict[str, tuple[bytes, int, int, int]], plain: dict[str, bytes], flags: int = 0
) -> bytes:
    """A zip written by hand: ``members`` name -> (stored data, crc, uncompressed size, method); ``plain``
    members are stored. ``flags`` are set on every member (bit 0: encrypted)."""
    entries = dict(members)
    for name, payload in plain.items():
        entries[name] = (payload, zlib.crc32(payload), len(payload), 0)
    out = io.BytesIO()
    central = []
    for name, (data, crc, size, method) in entries.items():
        offset = out.tell()
        raw = name.encode()
        zip64 = size >= 0xFFFFFFFF or len(data) >= 0xFFFFFFFF
        usize, csize = (0xFFFFFFFF, 0xFFFFFFFF) if zip64 else (size, len(data))
        extra = struct.pack("<HHQQ", 1, 16, size, len(data)) if zip64 else b""
        out.write(
            struct.pack(
                "<4s5H3I2H", b"PK\x03\x04", 45, flags, method, 0, 0, crc, csize, usize, len(raw), len(extra)
            )
        )
        out.write(raw + extra + data)
        cextra = struct.pack("<HHQQQ", 1, 24, size, len(data), offset) if zip64 else b""
        coff = 0xFFFFFFFF if zip64 else offset
        central.append(
            struct.pack(
                "<4s6H3I5H2I",
                b"PK\x01\x02",
                45,
                45,
                flags,
                method,
                0,
                0,
                crc,
                csize,
                usize,
                len(raw),
                len(cextra),
                0,
                0,
                0,
                0,
                coff,
            )
            + raw
            + cextra
        )
    start = out.tell()
    for entry in central:
        out.write(entry)
    size = out.tell() - start
    out.write(struct.pack("<4s4H2IH", b"PK\x05\x06", 0, 0, len(central), len(central), size, start, 0))
    return out.getvalue()


def body_points(n: int = 2000, seed: int = 0) -> np.ndarray:
    """(n, 3) points of a rough human-sized cloud in metres (an ellipsoid 1.7 m tall)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * np.array([0.15, 0.85, 0.25]) + np.array([0.0, 0.9, 0.0])


def ply_ascii(points: np.ndarray, declared: int | None = None, faces: str = "") -> bytes:
    n = len(points) if declared is None else declared
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
    )
    if faces:
        head += f"element face {faces.count(chr(10))}\nproperty list uchar int vertex_indices\n"
    body = "".join(f"{x} {y} {z}\n" for x, y, z in points)
    return (head + "end_header\n" + body + faces).encode()


def ply_binary(points: np.ndarray, declared: int | None = None) -> bytes:
    n = len(points) if declared is None else declared
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n"
    )
    return head.encode() + np.asarray(points, "<f4").tobytes()


def obj_text(points: np.ndarray, faces: str = "") -> bytes:
    return ("".join(f"v {x} {y} {z}\n" for x, y, z in points) + faces).encode()


def stl_binary(triangles: np.ndarray, declared: int | None = None) -> bytes:
    n = len(triangles) if declared is None else declared
    rec = np.zeros(len(triangles), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = triangles
    return b"\0" * 80 + struct.pack("<I", n) + rec.tobytes()


def pcd(points: np.ndarray, kind: str = "ascii", declared: int | None = None) -> bytes:
    n = len(points) if declared is None else declared
    head = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {kind}\n"
    )
    if kind == "ascii":
        return (head + "".join(f"{x} {y} {z}\n" for x, y, z in points)).encode()
    return head.encode() + np.asarray(points, "<f4").tobytes()


def pcd_compressed(n: int, packed: bytes, raw_size: int) -> bytes:
    """A binary_compressed PCD declaring ``n`` points and ``raw_size`` decompressed bytes for ``packed``."""
    head = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary_compressed\n"
    )
    return head.encode() + struct.pack("<II", len(packed), raw_size) + packed


def lzf_repeats(n_out: int) -> bytes:
    """An LZF stream of ``n_out`` bytes made of overlapping back-references (one literal, then copies of
    264 bytes at distance 1): tiny input, long pure-Python decode in a naive decoder."""
    out = bytearray([0, 0])  # a literal run of one byte: 0
    left = n_out - 1
    while left > 0:
        length = min(left, 264)
        if length < 3:
            out += bytes([length - 1]) + bytes(length)
            break
        out += bytes([0xE0, length - 9, 0])  # back-reference: length (7 + ext + 2), offset 0 (distance 1)
        left -= length
    return bytes(out)


def _pickle_npz() -> bytes:
    return npz(points=np.array([object()] * 3, dtype=object))


def amass(frames: int = 30, **over: Any) -> dict[str, Any]:
    """An AMASS-style sequence's arrays (poses (T, 72), trans, betas, gender, frame rate), then ``over``."""
    arrays: dict[str, Any] = {
        "poses": np.zeros((frames, 72)),
        "trans": np.zeros((frames, 3)) + np.array([0.0, 0.9, 0.0]),
        "betas": np.zeros(10),
        "gender": np.array("neutral"),
        "mocap_framerate": np.array(30.0),
    }
    arrays.update(over)
    return {k: v for k, v in arrays.items() if v is not None}


class _Pwned:
    def __reduce__(self) -> tuple[Callable[..., Any], tuple[str]]:
        return (print, ("unpickled",))


# -- the corpus ---------------------------------------------------------------------------------------
def corpus(bomb_mb: int = 2048) -> list[Case]:
    """Every hostile case (more than 100), REST and gRPC."""
    return [*_scan_cases(bomb_mb), *_sequence_cases(bomb_mb), *_upgrade_cases(bomb_mb), *_synth_cases()]


def _scan_cases(bomb_mb: int) -> Iterator[Case]:
    """Yields every hostile scan upload, always in the same order (the zip bomb inflates to ``bomb_mb``
    MiB)."""
    pts = body_points()
    tri = pts[:999].reshape(-1, 3, 3)
    rng = np.random.default_rng(7)
    garbage = rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
    valid = {
        "ply": ply_binary(pts),
        "obj": obj_text(pts),
        "stl": stl_binary(tri),
        "pcd": pcd(pts, "binary"),
        "npz": npz(points=pts),
    }
    yield from _scan_file_cases(valid, garbage)
    yield from _scan_count_cases(pts, tri)
    yield from _scan_content_cases(pts, valid, rng)
    yield from _scan_npz_cases(pts, garbage, bomb_mb)


def _scan_case(name: str, fmt: str, data: bytes, **fields: str) -> Case:
    """Returns the scan upload ``scan/<fmt>/<name>`` of ``data`` as ``scan.<fmt>`` with form ``fields``."""
    return Case(f"scan/{fmt}/{name}", SCAN, f"scan.{fmt}", data, fields)


def _scan_file_cases(valid: dict[str, bytes], garbage: bytes) -> Iterator[Case]:
    """Yields, for every format, broken files made from its ``valid`` bytes (empty, cut, zeroed, garbage)."""
    for fmt, good in valid.items():
        yield _scan_case("empty", fmt, b"")
        yield _scan_case("garbage", fmt, garbage)
        if fmt != "obj":  # a text OBJ cut short is a smaller valid OBJ
            yield _scan_case("truncated", fmt, good[: len(good) // 3])
        yield _scan_case("header-only", fmt, good[:120])
        yield _scan_case("zeros", fmt, bytes(len(good)))
        yield _scan_case("text-in-binary", fmt, b"hello, this is not a scan\n" * 50)


def _scan_count_cases(pts: np.ndarray, tri: np.ndarray) -> Iterator[Case]:
    """Yields files whose declared counts lie about the data, from body points (N, 3) and triangles
    (K, 3, 3)."""
    yield _scan_case("declares-1e9-vertices-binary", "ply", ply_binary(pts, declared=10**9))
    yield _scan_case("declares-1e9-vertices-ascii", "ply", ply_ascii(pts, declared=10**9))
    yield _scan_case("declares-2e9-vertices", "ply", ply_binary(pts, declared=2**31 + 5))
    yield _scan_case("negative-count", "ply", ply_ascii(pts, declared=-5))
    yield _scan_case("faces-out-of-range", "ply", ply_ascii(pts, faces="3 0 1 999999999\n" * 10))
    yield _scan_case("declares-1e8-triangles", "stl", stl_binary(tri, declared=10**8))
    yield _scan_case("declares-1e9-points-binary", "pcd", pcd(pts, "binary", declared=10**9))
    yield _scan_case("declares-1e9-points-ascii", "pcd", pcd(pts, "ascii", declared=10**9))
    yield _scan_case("compressed-claims-3gb", "pcd", pcd_compressed(10**8, b"\0" * 16, 3 * 10**9))
    yield _scan_case("compressed-size-mismatch", "pcd", pcd_compressed(2000, lzf_repeats(24_000), 12_000))
    yield _scan_case(
        "compressed-lzf-repeats-4gb", "pcd", pcd_compressed(2000, lzf_repeats(4 * 2**20), 2**32 - 1)
    )
    yield _scan_case("obj-face-index-1e9", "obj", obj_text(pts, "f 1 2 1000000000\n"))
    yield _scan_case("obj-inf", "obj", obj_text(np.full((500, 3), np.inf)))
    yield _scan_case("obj-cut-mid-line", "obj", obj_text(pts[:100])[:-7])


def _scan_content_cases(pts: np.ndarray, valid: dict[str, bytes], rng: np.random.Generator) -> Iterator[Case]:
    """Yields readable files whose points are no body in metres, or whose units or format are wrong."""
    yield _scan_case("all-nan", "npz", npz(points=np.full((2000, 3), np.nan)))
    yield _scan_case("inf-points", "ply", ply_binary(np.full((2000, 3), np.inf)))
    yield _scan_case("all-zero", "npz", npz(points=np.zeros((2000, 3))))
    yield _scan_case("one-point-repeated", "ply", ply_binary(np.tile([[0.1, 0.2, 0.3]], (2000, 1))))
    yield _scan_case("collinear", "npz", npz(points=np.outer(np.linspace(0, 1.7, 2000), [0, 1, 0])))
    yield _scan_case("planar", "pcd", pcd(np.c_[rng.random((2000, 2)) * 1.7, np.zeros(2000)], "binary"))
    yield _scan_case("too-few-points", "npz", npz(points=pts[:20]))
    yield _scan_case("building-sized", "npz", npz(points=pts * 40.0))
    yield _scan_case("centimetres", "npz", npz(points=pts * 100.0))
    yield _scan_case("metres-sent-as-mm", "npz", npz(points=pts), units="mm")
    yield _scan_case("unknown-units", "npz", npz(points=pts), units="furlongs")
    yield _scan_case("ply-sent-as-stl", "stl", valid["ply"])
    yield _scan_case("unknown-format", "xyz", valid["ply"], format="xyz")


def _scan_npz_cases(pts: np.ndarray, garbage: bytes, bomb_mb: int) -> Iterator[Case]:
    """Yields hostile NPZ archives: wrong keys and types, pickles, lying headers and zip tricks."""
    yield _scan_case("wrong-keys", "npz", npz(cloud=pts))
    yield _scan_case("points-2d-wrong-width", "npz", npz(points=pts[:, :2]))
    yield _scan_case("points-scalar", "npz", npz(points=np.array(3.0)))
    yield _scan_case("points-strings", "npz", npz(points=np.array(["a", "b", "c"] * 700)))
    yield _scan_case("points-structured", "npz", npz(points=np.zeros(2000, dtype=[("x", "f4"), ("y", "f4")])))
    yield _scan_case("points-complex", "npz", npz(points=pts.astype(np.complex64)))
    yield _scan_case("faces-float", "npz", npz(points=pts, faces=np.zeros((10, 3))))
    yield _scan_case("pickled-object-array", "npz", _pickle_npz())
    yield _scan_case("pickle-as-npz", "npz", pickle.dumps(_Pwned()))
    yield _scan_case("lying-header-1e9-rows", "npz", lying_npz("points", (10**9, 3), 1024))
    yield _scan_case("lying-header-short", "npz", lying_npz("points", (2000, 3), 24_000 * 2, "<f8"))
    yield _scan_case("lying-header-huge-dims", "npz", lying_npz("points", (2**40, 2**40), 64))
    yield _scan_case("fortran-huge", "npz", zip_members({"points.npy": npy_header((3, 10**9), "<f8", True)}))
    yield _scan_case("zip-bomb", "npz", bomb_npz("points", (bomb_mb * 2**20 // 12, 3)))
    yield _scan_case(
        "encrypted-member",
        "npz",
        _raw_zip({}, {"points.npy": npy_header((10, 3), "<f8") + bytes(240)}, flags=1),
    )
    yield _scan_case("unknown-compression", "npz", _raw_zip({"points.npy": (b"\0" * 64, 0, 64, 99)}, {}))
    yield _scan_case(
        "bzip2-member",
        "npz",
        zip_members({"points.npy": npy_header((10, 3)) + bytes(120)}, zipfile.ZIP_BZIP2),
    )
    yield _scan_case("nested-zip", "npz", zip_members({"points.npy": npz(points=pts)}))
    yield _scan_case("not-a-zip-with-pk", "npz", b"PK\x03\x04" + garbage)


def _sequence_cases(bomb_mb: int) -> Iterator[Case]:
    def case(name: str, data: bytes, grpc: bool = False, request: dict[str, Any] | None = None) -> Case:
        return Case(f"sequence/{name}", SEQUENCE, "frames.npz", data, {}, grpc, request)

    v = N_VERTICES
    yield case("zero-frames-bomb", bomb_npz("frames", (bomb_mb * 2**20 // (v * 12), v, 3)))
    yield case("all-zero-frames", npz(frames=np.zeros((4, v, 3), np.float32)))
    yield case("constant-frames", npz(frames=np.ones((4, v, 3), np.float32)))
    yield case("nan-frames", npz(frames=np.full((3, v, 3), np.nan, np.float32)))
    yield case("inf-frames", npz(frames=np.full((3, v, 3), np.inf, np.float32)))
    yield case(
        "giant-frames", npz(frames=np.random.default_rng(0).random((3, v, 3)).astype(np.float32) * 1e5)
    )
    yield case("wrong-vertex-count", npz(frames=np.zeros((3, 6890, 3), np.float32)))
    yield case("int32-frames", npz(frames=np.ones((2, v, 3), np.int32)))
    yield case("bool-frames", npz(frames=np.ones((2, v, 3), bool)))
    yield case("string-frames", npz(frames=np.array(["x"] * 6)))
    yield case("no-frames-key", npz(meshes=np.zeros((2, v, 3), np.float32)))
    yield case("no-frames", npz(frames=np.zeros((0, v, 3), np.float32)))
    yield case("lying-header-1e9-frames", lying_npz("frames", (10**9, v, 3), 4096))
    yield case(
        "weights-lying-header",
        zip_members(
            {
                "frames.npy": npy_header((2, v, 3)) + bytes(2 * v * 12),
                "weights.npy": npy_header((10**9, v)) + bytes(64),
            }
        ),
    )
    yield case("weights-wrong-shape", npz(frames=np.zeros((2, v, 3), np.float32), weights=np.ones((5, 7))))
    yield case("pickled-frames", npz(frames=np.array([object()], dtype=object)))
    yield case("pickle-file", pickle.dumps(_Pwned()))
    yield case("garbage", b"\x00\xff" * 3000)
    # gRPC arrays (no file): declared shapes and dtypes that do not match their bytes
    for name, array in {
        "shape-2^62": {"dtype": "float32", "shape": [0, 2**62], "data": b""},
        "shape-1e9-no-data": {"dtype": "float32", "shape": [10**9, v, 3], "data": b""},
        "shape-mismatch": {"dtype": "float32", "shape": [2, v, 3], "data": bytes(1000)},
        "negative-shape": {"dtype": "float32", "shape": [-2, v, 3], "data": b""},
        "object-dtype": {"dtype": "object", "shape": [1], "data": b"\0" * 8},
        "int32-frames": {"dtype": "int32", "shape": [1, v, 3], "data": bytes(v * 12)},
        "bool-frames": {"dtype": "bool", "shape": [1, v, 3], "data": bytes(v * 3)},
        "zero-frames": {"dtype": "float32", "shape": [2, v, 3], "data": bytes(2 * v * 12)},
    }.items():
        yield Case(f"sequence/grpc/{name}", SEQUENCE, "", b"", {}, True, {"frames": array})


def _upgrade_cases(bomb_mb: int) -> Iterator[Case]:
    def case(name: str, data: bytes, filename: str = "motion.npz") -> Case:
        return Case(f"upgrade/{name}", UPGRADE, filename, data)

    yield case("pkl-file", pickle.dumps({"poses": np.zeros((2, 72))}), "motion.pkl")
    yield case("pickle-as-npz", pickle.dumps(_Pwned()))
    yield case("pickled-poses", npz(**amass(poses=np.array([object()] * 2, dtype=object))))
    yield case("poses-bomb", bomb_npz("poses", (bomb_mb * 2**20 // (72 * 4), 72)))
    yield case("lying-header-1e9-frames", lying_npz("poses", (10**9, 72), 4096, "<f8"))
    yield case("lying-header-short", lying_npz("poses", (100, 72), 800, "<f8"))
    yield case("numeric-gender", npz(**amass(gender=np.array(3.5))))
    yield case("bytes-gender", npz(**amass(gender=np.array(b"\xff\xfe"))))
    yield case("poses-wrong-width", npz(**amass(poses=np.zeros((30, 70)))))
    yield case("poses-1d", npz(**amass(poses=np.zeros(72))))
    yield case("poses-strings", npz(**amass(poses=np.array(["a"] * 72))))
    yield case("poses-nan", npz(**amass(poses=np.full((30, 72), np.nan))))
    yield case("poses-inf", npz(**amass(poses=np.full((30, 72), np.inf))))
    yield case("poses-huge", npz(**amass(poses=np.full((30, 72), 1e30))))
    yield case("trans-wrong-shape", npz(**amass(trans=np.zeros((5, 2)))))
    yield case("trans-nan", npz(**amass(trans=np.full((30, 3), np.nan))))
    yield case("trans-1e308", npz(**amass(trans=np.full((30, 3), 1e308))))
    yield case("betas-1e6", npz(**amass(betas=np.full(10, 1e6))))
    yield case("betas-nan", npz(**amass(betas=np.full(10, np.nan))))
    yield case("framerate-zero", npz(**amass(mocap_framerate=np.array(0.0))))
    yield case("framerate-negative", npz(**amass(mocap_framerate=np.array(-30.0))))
    yield case("framerate-nan", npz(**amass(mocap_framerate=np.array(np.nan))))
    yield case("framerate-string", npz(**amass(mocap_framerate=np.array("fast"))))
    yield case("no-poses", npz(**amass(poses=None)))
    yield case("zero-frames", npz(**amass(frames=0)))
    yield case("wrong-keys", npz(rotations=np.zeros((30, 72))))
    yield case("garbage", np.random.default_rng(3).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    yield case("truncated", npz(**amass())[:300])
    yield case("empty", b"")
    yield case("encrypted", _raw_zip({}, {"poses.npy": npy_header((2, 72), "<f8") + bytes(1152)}, flags=1))
    yield case("unknown-compression", _raw_zip({"poses.npy": (b"\0" * 64, 0, 64, 99)}, {}))


def _synth_cases() -> Iterator[Case]:
    def case(name: str, body: Any, grpc: dict[str, Any] | None = None) -> Case:
        data = body if isinstance(body, bytes) else json.dumps(body).encode()
        return Case(f"synthesize/{name}", SYNTHESIZE, "", data, {}, grpc is not None, grpc)

    yield case("root-1e308", {"root": [[0, 1e308, 0]]}, {"root": [[0.0, 1e308, 0.0]]})
    yield case("root-nan-literal", b'{"root": [[NaN, 0, 0]]}')
    yield case("root-infinity-literal", b'{"root": [[Infinity, 0, 0]]}')
    yield case("shape-1e6", {"shape": [[1e6] * 32]}, {"shape": [[1e6] * 32]})
    yield case("shape-wrong-width", {"shape": [[0.0] * 3]}, {"shape": [[0.0] * 3]})
    yield case("batch-0-glb", {"batch": 0, "format": "glb"}, {"batch": -1})
    yield case("zero-bodies-glb", {"shape": [], "format": "glb"})
    yield case("zero-bodies-npz", {"root": [], "format": "npz"})
    yield case("batch-1e9", {"batch": 10**9}, {"batch": 2**31 - 1})
    yield case("bool-as-string", {"skeleton": "yes"})
    yield case("number-as-string", {"batch": "2"})
    yield case("unknown-key", {"colour": "blue"})
    yield case("unknown-dof", {"coordinates": {"knee_angel_r": 1.0}}, {"named": {"knee_angel_r": [1.0]}})
    yield case("dof-out-of-range", {"coordinates": {"knee_angle_r": 9.0}}, {"named": {"knee_angle_r": [9.0]}})
    yield case("ragged-matrix", {"root": [[0, 0, 0], [0, 0]]})
    yield case("unknown-format", {"format": "fbx"})
    yield case("not-json", b"{garbage")
    yield case("json-array", b"[1, 2, 3]")
    yield case("deep-nesting", b"[" * 100_000 + b"]" * 100_000)
    yield case("huge-number", b'{"root": [[0, 1' + b"0" * 5000 + b", 0]]}")


# -- sending ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Answer:
    """How the server answered one case: ``code`` is the HTTP status ("422") or the gRPC status name
    ("INVALID_ARGUMENT"), "timeout" when no answer came in time; ``refused``: a client-error answer (REST
    4xx; gRPC INVALID_ARGUMENT, RESOURCE_EXHAUSTED, FAILED_PRECONDITION or OUT_OF_RANGE)."""

    case: str
    transport: str
    code: str
    refused: bool
    seconds: float
    detail: str


GRPC_REFUSALS = ("INVALID_ARGUMENT", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION", "OUT_OF_RANGE")


def send_rest(http: Any, case: Case) -> Answer:
    """Send ``case`` with an ``httpx.Client`` whose base URL is the server's (one JSON answer, no stream)."""
    import httpx

    began = time.perf_counter()
    try:
        if case.endpoint == SYNTHESIZE:
            r = http.post("/v1/synthesize", content=case.data, headers={"content-type": "application/json"})
        else:
            path = {SCAN: "/v1/fit/scan", SEQUENCE: "/v1/fit/sequence", UPGRADE: "/v1/upgrade"}[case.endpoint]
            r = http.post(path, files={"file": (case.filename, case.data)}, data=case.fields)
    except httpx.TimeoutException:
        return Answer(case.name, "rest", "timeout", False, time.perf_counter() - began, "no answer")
    seconds = time.perf_counter() - began
    detail = r.text[:300]
    return Answer(case.name, "rest", str(r.status_code), 400 <= r.status_code < 500, seconds, detail)


def send_grpc(stub: Any, case: Case, timeout_s: float = 30.0) -> Answer:
    """Send ``case`` over gRPC with a ``BodyfitStub``; stream events are read to the end."""
    import grpc

    from bodyfit.api import bodyfit_pb2 as pb

    began = time.perf_counter()
    try:
        if case.endpoint == SYNTHESIZE:
            stub.Synthesize(_synth_message(pb, case.grpc_request or {}), timeout=timeout_s)
        elif case.endpoint == SEQUENCE:
            frames = (case.grpc_request or {})["frames"]
            for _ in stub.FitSequence(pb.FitSequenceRequest(frames=pb.Array(**frames)), timeout=timeout_s):
                pass
        elif case.endpoint == SCAN:
            fmt = case.fields.get("format", case.filename.rsplit(".", 1)[-1])
            request = pb.FitScanRequest(data=case.data, format=fmt, units=case.fields.get("units", "auto"))
            for _ in stub.FitScan(request, timeout=timeout_s):
                pass
        else:
            for _ in stub.Upgrade(
                pb.UpgradeRequest(data=case.data, filename=case.filename), timeout=timeout_s
            ):
                pass
    except grpc.RpcError as exc:
        code = exc.code()
        seconds = time.perf_counter() - began
        if code == grpc.StatusCode.DEADLINE_EXCEEDED and seconds >= timeout_s * 0.99:
            return Answer(case.name, "grpc", "timeout", False, seconds, "no answer")
        return Answer(
            case.name, "grpc", code.name, code.name in GRPC_REFUSALS, seconds, str(exc.details())[:300]
        )
    return Answer(case.name, "grpc", "OK", False, time.perf_counter() - began, "accepted")


def _synth_message(pb: Any, spec: dict[str, Any]) -> Any:
    def array(values: Any) -> Any:
        a = np.asarray(values, np.float64)
        return pb.Array(dtype="float64", shape=list(a.shape), data=a.tobytes())

    request = pb.SynthesizeRequest(batch=int(spec.get("batch", 0)))
    for key in ("shape", "root"):
        if key in spec:
            getattr(request, key).CopyFrom(array(spec[key]))
    for name, values in spec.get("named", {}).items():
        request.named_coordinates[name].values.extend(values)
    return request
