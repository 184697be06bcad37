"""The safe .npz reader: every array checked from its .npy header before it is built, hostile archives
refused with a typed error that names the problem, in little memory."""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from bodyfit.io import DEFAULT_MAX_BYTES, ArraySpec, Dim, FileFormatError, FileLimitError, npz_keys, read_npz
from bodyfit.io.npz import FLOAT, INTEGER, NUMBER, TEXT
from tests.io.checks import MB, archive, npy, patch_members, peak_memory, refused, savez, savez_compressed

T = Dim("T", 20_000, "frames", "split the sequence")
FRAMES = {"frames": ArraySpec(((T, 4, 3),), FLOAT), "weights": ArraySpec(((T, 4),), NUMBER, required=False)}
UNLIMITED = {"frames": ArraySpec(((Dim("T"), 4, 3),), FLOAT)}  # then only the decompressed-bytes cap holds


# -- what it reads -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("compressed", [False, True])
def test_reads_what_numpy_reads(tmp_path: Path, compressed: bool) -> None:
    rng = np.random.default_rng(0)
    frames = rng.normal(size=(5, 4, 3)).astype(">f4")  # big-endian kept as stored
    weights = np.asfortranarray(rng.uniform(size=(5, 4)))  # Fortran order: read back the same
    other = np.array([object()], dtype=object)  # never read: not asked for
    data = (savez_compressed if compressed else savez)(frames=frames, weights=weights, other=other)
    (tmp_path / "s.npz").write_bytes(data)
    for source in (data, tmp_path / "s.npz", str(tmp_path / "s.npz")):
        got = read_npz(source, FRAMES)
        assert got["frames"].dtype == np.dtype(">f4") and got["weights"].flags.f_contiguous
        np.testing.assert_array_equal(got["frames"], frames)
        np.testing.assert_array_equal(got["weights"], weights)
    assert npz_keys(data) == ["frames", "weights", "other"]
    assert set(read_npz(savez(frames=frames), FRAMES)) == {"frames"}  # optional arrays may be absent


def test_text_scalars_and_alternative_shapes() -> None:
    K = Dim("K")
    specs = {
        "gender": ArraySpec(((), (1,)), TEXT),
        "rate": ArraySpec(((), (1,)), NUMBER),
        "betas": ArraySpec(((K,), (1, K), (T, K)), NUMBER),
        "poses": ArraySpec(((T, 72), (T, 156)), NUMBER),
        "faces": ArraySpec(((Dim("F"), 3),), INTEGER),
    }
    got = read_npz(
        savez(
            gender=np.array(b"male"),
            rate=np.array([120.0]),
            betas=np.zeros((6, 10)),
            poses=np.zeros((6, 156)),
            faces=np.zeros((2, 3), np.uint32),
        ),
        specs,
    )
    assert got["gender"][()] == b"male" and got["betas"].shape == (6, 10) and got["poses"].shape == (6, 156)
    refused(
        FileFormatError,
        "betas must have shape (K,), (1, K) or (T=6, K); it has (5, 10)",
        lambda: read_npz(
            savez(poses=np.zeros((6, 72)), betas=np.zeros((5, 10))),
            {"poses": specs["poses"], "betas": specs["betas"]},
        ),
        key="betas",
    )


# -- dtypes and shapes, from the header alone ----------------------------------------------------------------
@pytest.mark.parametrize(
    ("frames", "words"),
    [
        (np.array([[[None] * 3] * 4] * 2, dtype=object), "Python objects"),
        (np.zeros((2, 4, 3), [("x", "<f4"), ("y", "<f4")]), "structured (record) array"),
        (np.zeros((2, 4, 3), "V8"), "structured (record) array"),
        (np.full((2, 4, 3), "1.0"), "must hold floats; it holds <U3 (text)"),
        (np.zeros((2, 4, 3), np.int64), "must hold floats; it holds int64 (integers)"),
        (np.zeros((2, 4, 3), bool), "must hold floats; it holds bool (booleans)"),
        (np.zeros((2, 4, 3), np.complex128), "must hold floats; it holds complex128"),
        (np.float64(1.0), "must have shape (T, 4, 3); it has () (a scalar)"),
        (np.zeros((2, 5, 3)), "must have shape (T, 4, 3); it has (2, 5, 3)"),
        (np.zeros(24), "must have shape (T, 4, 3); it has (24,)"),
    ],
)
def test_wrong_dtypes_and_shapes_are_refused_by_name(frames: np.ndarray, words: str) -> None:
    data = savez(frames=frames) if frames.dtype != object else archive({"frames": _object_npy()})
    refused(FileFormatError, words, lambda: read_npz(data, FRAMES), key="frames")


def _object_npy() -> bytes:
    return npy((2, 4, 3), "|O", b"\x80\x04N.")  # a pickle: never reached


def test_named_sizes_must_agree_and_missing_arrays_are_named() -> None:
    data = savez(frames=np.zeros((5, 4, 3)), weights=np.zeros((4, 4)))
    refused(
        FileFormatError, "weights must have shape (T=5, 4); it has (4, 4)", lambda: read_npz(data, FRAMES)
    )
    message = refused(
        FileFormatError,
        "holds ['points']; it needs 'frames' (T, 4, 3)",
        lambda: read_npz(savez(points=np.zeros(3)), FRAMES),
    )
    assert "the file" in message


# -- headers that lie, zip bombs -----------------------------------------------------------------------------
def test_a_header_claiming_a_billion_rows_is_refused_before_any_allocation() -> None:
    data = archive({"frames": npy((10**9, 4, 3), data=bytes(96))})
    with peak_memory(2):
        refused(
            FileLimitError,
            "frames declares 1,000,000,000 frames; the limit is 20,000: split",
            lambda: read_npz(data, FRAMES),
        )
    with peak_memory(2):
        message = refused(FileLimitError, "decompress to 89.4 GiB", lambda: read_npz(data, UNLIMITED))
    assert (
        "frames (1000000000, 4, 3) float64" in message
        and f"the limit is {DEFAULT_MAX_BYTES / 2**30:.1f} GiB" in message
    )


def test_a_zip_bomb_stops_at_the_cap() -> None:
    buf = io.BytesIO()  # 64 MiB of zero frames in about 64 KiB
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf, zf.open("frames.npy", "w") as f:
        f.write(npy((2**20 * 64 // 96, 4, 3)))
        for _ in range(64):
            f.write(bytes(MB))
    data = buf.getvalue()
    assert len(data) < MB
    with peak_memory(2):
        refused(
            FileLimitError, "decompress to 64.0 MiB", lambda: read_npz(data, UNLIMITED, max_bytes=16 * MB)
        )
    # the same stream behind a header claiming 10 frames: reading stops after 10 frames' bytes
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf, zf.open("frames.npy", "w") as f:
        f.write(npy((10, 4, 3)))
        for _ in range(64):
            f.write(bytes(MB))
    with peak_memory(4):
        refused(
            FileFormatError,
            "holds more data than its header declares (10, 4, 3)",
            lambda: read_npz(buf.getvalue(), FRAMES),
        )


def test_data_shorter_or_longer_than_the_header_says() -> None:
    rows = np.arange(60.0).tobytes()  # 5 frames of (4, 3)
    for method in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        fewer = archive({"frames": npy((2, 4, 3), data=rows)}, method)
        refused(
            FileFormatError,
            "more data than its header declares (2, 4, 3)",
            partial(read_npz, fewer, FRAMES),
        )
        more = archive({"frames": npy((9, 4, 3), data=rows)}, method)
        refused(
            FileFormatError,
            "holds 480 bytes of data but its header declares (9, 4, 3) float64 = 864 bytes",
            partial(read_npz, more, FRAMES),
            key="frames",
        )
    assert read_npz(archive({"frames": npy((5, 4, 3), data=rows)}), FRAMES)["frames"].sum() == sum(range(60))


def test_fortran_order_headers_are_read_transposed() -> None:
    a = np.arange(60.0).reshape(5, 4, 3)
    data = archive({"frames": npy((5, 4, 3), data=np.asfortranarray(a).T.tobytes(), fortran=True)})
    got = read_npz(data, FRAMES)["frames"]
    np.testing.assert_array_equal(got, a)
    assert got.shape == (5, 4, 3)


def test_bad_npy_headers() -> None:
    refused(FileFormatError, "is not a .npy array", lambda: read_npz(archive({"frames": b"x" * 100}), FRAMES))
    v3 = archive({"frames": npy((1, 4, 3), v=3, data=bytes(96))})
    refused(FileFormatError, "format version 3.0", lambda: read_npz(v3, FRAMES))
    negative = archive({"frames": npy((-1, 4, 3))})
    refused(FileFormatError, "negative size", lambda: read_npz(negative, FRAMES))
    v2 = archive({"frames": npy((1, 4, 3), v=2, data=bytes(96))})
    assert read_npz(v2, FRAMES)["frames"].shape == (1, 4, 3)


# -- the archive ---------------------------------------------------------------------------------------------
def test_encrypted_members_and_unknown_compression_are_refused() -> None:
    data = savez(frames=np.zeros((2, 4, 3)))
    refused(
        FileFormatError,
        "'frames' in the file is encrypted",
        lambda: read_npz(patch_members(data, flag=1), FRAMES),
    )
    refused(
        FileFormatError,
        "compressed with an unknown method (zip method 77); only stored and deflate",
        lambda: read_npz(patch_members(data, method=77), FRAMES),
    )
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_BZIP2) as zf:
        zf.writestr("frames.npy", npy((2, 4, 3), data=bytes(192)))
    refused(
        FileFormatError, "compressed with bzip2 (zip method 12)", lambda: read_npz(buf.getvalue(), FRAMES)
    )


@pytest.mark.parametrize("cut", [0, 10, 200, -30, -1])
def test_truncated_and_non_zip_files(cut: int) -> None:
    data = savez(frames=np.zeros((2, 4, 3)))
    part = data[:cut] if cut > 0 else data[: len(data) + cut]
    refused(FileFormatError, "not a readable .npz", lambda: read_npz(part if cut else b"", FRAMES))
    refused(FileFormatError, "not a readable .npz", lambda: npz_keys(b"PK\x03\x04 not a zip"))


def test_corrupt_member_data() -> None:
    data = bytearray(savez_compressed(frames=np.arange(600.0).reshape(50, 4, 3)))
    at = data.find(b"frames.npy") + len("frames.npy") + 40  # inside the deflate stream
    data[at : at + 8] = b"\xff" * 8
    refused(FileFormatError, "corrupt or truncated", lambda: read_npz(bytes(data), FRAMES))


def test_a_huge_zip_directory_is_refused_before_it_is_parsed() -> None:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for i in range(25_000):
            zf.writestr(f"{i}", b"")
    refused(FileLimitError, "zip directory is", lambda: read_npz(buf.getvalue(), FRAMES))


def test_duplicate_members_are_refused() -> None:
    buf = io.BytesIO()
    with pytest.warns(UserWarning), zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("frames.npy", npy((1, 4, 3), data=bytes(96)))
        zf.writestr("frames.npy", npy((1, 4, 3), data=bytes(96)))
    refused(FileFormatError, "holds 2 arrays named 'frames'", lambda: read_npz(buf.getvalue(), FRAMES))


def test_per_array_byte_limit() -> None:
    specs = {"gender": ArraySpec(((),), TEXT, max_bytes=1024)}
    refused(
        FileLimitError,
        "it may hold at most 1.0 KiB",
        lambda: read_npz(savez(gender=np.array("x" * 1000)), specs),
    )


def test_the_package_stays_light() -> None:
    code = "import sys, bodyfit.io; print(sorted({'torch', 'fastapi', 'grpc'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
