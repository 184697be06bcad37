"""Safe reading of ``.npz`` files (``numpy.savez`` / ``savez_compressed`` archives) from untrusted sources.

``numpy.load`` trusts the file: a 3 MB archive of zeros can decompress to gigabytes, and a .npy header can
claim 10^9 rows. :func:`read_npz` reads only the arrays the caller names, and of each one first the .npy
header alone (shape, memory order, dtype), checked against its :class:`ArraySpec`: the dtype kind (numbers
or text, never Python objects, records or raw void), the number of dimensions and the sizes, named sizes
shared across arrays (:class:`Dim`, e.g. T frames) with their limits, and the total declared bytes against
``max_bytes``. Only then is each array allocated, at its declared size, and filled from the member's
stream in 1 MiB chunks: a member whose data is shorter or longer than its header says is refused, and a
zip bomb cannot go past the cap. Encrypted members, compression methods other than stored and deflate,
zips with huge directories, non-zip and truncated files are refused.

Errors: :class:`~bodyfit.io.errors.FileLimitError` for a size over a limit (frames, points, bytes), else
:class:`~bodyfit.io.errors.FileFormatError`; both name the array (``key``) and say how to fix the file.
"""

from __future__ import annotations

import io
import math
import os
import tokenize
import zipfile
import zlib
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, cast

import numpy as np
from numpy.lib import format as npy

from bodyfit.io.errors import FileFormatError, FileLimitError

DEFAULT_MAX_BYTES = 1024 * 2**20  # decompressed bytes of all the arrays read from one file
MAX_DIRECTORY_BYTES = 2**20  # a zip directory this large lists tens of thousands of members
_CHUNK = 2**20
_METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED)
_METHOD_NAMES = {9: "deflate64", 12: "bzip2", 14: "lzma", 93: "zstandard", 98: "ppmd", 99: "AES encryption"}
_SAVE = "save the arrays with numpy.savez or numpy.savez_compressed"
DAMAGED = (
    zipfile.BadZipFile,
    zlib.error,
    tokenize.TokenError,
    SyntaxError,
    EOFError,
    OSError,
    ValueError,
    NotImplementedError,
    RuntimeError,
)
"""What a damaged archive raises while it is read, by ``zipfile`` or ``numpy.load``: a corrupt deflate
stream (``zlib.error``), a .npy header that no longer parses (``tokenize.TokenError``, ``SyntaxError``), a
file cut short (``EOFError``)."""

FLOAT, NUMBER, INTEGER, TEXT = "f", "fiu", "iu", "US"  # numpy dtype kinds
_KINDS = {"f": "floats", "i": "integers", "u": "unsigned integers", "U": "text", "S": "text", "b": "booleans"}

Source = bytes | bytearray | str | os.PathLike[str]


@dataclass(frozen=True)
class Dim:
    """A named size shared by the arrays that use it (e.g. T frames in poses (T, 72) and trans (T, 3)),
    at most ``limit`` (None: no limit); ``what`` and ``fix`` word the limit's message ("poses declares
    25,000 frames; the limit is 20,000: split the sequence")."""

    name: str
    limit: int | None = None
    what: str = ""
    fix: str = "split the file"


Shape = tuple[int | Dim, ...]


@dataclass(frozen=True)
class ArraySpec:
    """What one array of an archive must be.

    Attributes:
        shapes: the accepted shapes, one entry per axis: an int (that size) or a :class:`Dim` (a named size,
            equal in every array that names it); e.g. ``((T, 72), (T, 156))``, or ``((), (1,))`` for a scalar.
        kinds: the accepted dtype kinds (:data:`FLOAT`, :data:`NUMBER`, :data:`INTEGER`, :data:`TEXT`).
        required: a missing array is an error (else it is left out of the result).
        max_bytes: the most this array may hold (e.g. a short text); None: only the file's cap.
        hint: added to this array's error messages (what it holds, how to save it).
    """

    shapes: tuple[Shape, ...]
    kinds: str = NUMBER
    required: bool = True
    max_bytes: int | None = None
    hint: str = ""


@dataclass(frozen=True)
class _Header:
    info: zipfile.ZipInfo
    shape: tuple[int, ...]
    fortran: bool
    dtype: np.dtype

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


def npz_keys(source: Source, *, name: str | None = None) -> list[str]:
    """The names of an archive's arrays (its ``.npy`` members without the suffix), in archive order; reads
    the zip directory only.

    Raises:
        FileFormatError: not a zip archive, or truncated; FileLimitError: a huge zip directory.
    """
    with _open(source, name or _name(source)) as zf:
        return list(_members(zf))


def read_npz(
    source: Source,
    specs: Mapping[str, ArraySpec],
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    name: str | None = None,
) -> dict[str, np.ndarray]:
    """Read the arrays ``specs`` names from an .npz, each checked from its header before it is built.

    Args:
        source: the file's bytes or its path.
        specs: array name -> what it must be; other arrays of the archive are never decompressed.
        max_bytes: the most bytes the arrays read may hold together, decompressed.
        name: the file's name in messages (default: the path's name, or "the .npz").
    Returns:
        name -> array with the declared shape and dtype (byte order as stored), for each array present.
    Raises:
        FileLimitError: a named size over its :class:`Dim` limit, an array over its ``max_bytes``, or all of
            them over ``max_bytes``.
        FileFormatError: anything else wrong (missing, wrong dtype or shape, encrypted, unsupported
            compression, truncated or corrupt); ``key`` names the array.
    """
    where = name or _name(source)
    with _open(source, where) as zf:
        members = _members(zf)
        headers: dict[str, _Header] = {}
        sizes: dict[str, int] = {}  # Dim name -> the size the first array naming it declared
        for key, spec in specs.items():
            infos = members.get(key, [])
            if not infos:
                if spec.required:
                    found = list(members) or "no arrays"
                    raise FileFormatError(
                        f"{where} holds {found}; it needs {key!r} {_shapes(spec.shapes, sizes)}{_hint(spec)}",
                        key,
                    )
                continue
            if len(infos) > 1:
                raise FileFormatError(f"{where} holds {len(infos)} arrays named {key!r}; {_SAVE}", key)
            headers[key] = header = _read_header(zf, infos[0], key, where)
            _check(header, spec, key, sizes)
        total = sum(h.nbytes for h in headers.values())
        if total > max_bytes:
            parts = ", ".join(f"{k} {h.shape} {h.dtype} = {_size(h.nbytes)}" for k, h in headers.items())
            raise FileLimitError(
                f"{where}'s arrays decompress to {_size(total)} ({parts}); the limit is {_size(max_bytes)} "
                "per file: split or thin the data"
            )
        return {key: _read_data(zf, header, key, where) for key, header in headers.items()}


# -- the archive ---------------------------------------------------------------------------------------------
@contextmanager
def _open(source: Source, where: str) -> Iterator[zipfile.ZipFile]:
    fp: IO[bytes]
    if isinstance(source, bytes | bytearray):
        fp = io.BytesIO(source)
    else:
        try:
            fp = open(source, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise FileFormatError(f"cannot read {where}: {exc.strerror or exc}") from None
    with fp:
        size = _directory_size(fp)
        if size is not None and size > MAX_DIRECTORY_BYTES:
            raise FileLimitError(
                f"{where}'s zip directory is {_size(size)} (tens of thousands of members); an .npz holds "
                f"a few arrays: {_SAVE} with only the arrays needed"
            )
        try:
            zf = zipfile.ZipFile(fp)
        except DAMAGED as exc:
            raise FileFormatError(
                f"{where} is not a readable .npz (a zip archive of .npy arrays): not a zip file, or a "
                f"truncated one ({exc}); {_SAVE}"
            ) from None
        with zf:
            yield zf


def _directory_size(fp: IO[bytes]) -> int | None:
    """The central directory's size as the zip's end record (or zip64 end record) declares it; None when
    there is none (``zipfile`` then says the file is not a zip)."""
    end = fp.seek(0, io.SEEK_END)
    tail_len = min(end, 22 + 65535)  # the end record (22 bytes) and the longest comment
    fp.seek(end - tail_len)
    tail = fp.read(tail_len)
    fp.seek(0)
    at = len(tail) - 22 if tail[-22:-18] == b"PK\x05\x06" else tail.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(tail):
        return None
    size = int.from_bytes(tail[at + 12 : at + 16], "little")
    if size == 0xFFFFFFFF and at >= 20 and tail[at - 20 : at - 16] == b"PK\x06\x07":  # zip64
        fp.seek(int.from_bytes(tail[at - 12 : at - 4], "little"))
        record = fp.read(56)
        fp.seek(0)
        if len(record) == 56 and record[:4] == b"PK\x06\x06":
            size = int.from_bytes(record[40:48], "little")
    return size


def _members(zf: zipfile.ZipFile) -> dict[str, list[zipfile.ZipInfo]]:
    members: dict[str, list[zipfile.ZipInfo]] = {}
    for info in zf.infolist():
        if info.filename.endswith(".npy"):
            members.setdefault(info.filename[:-4], []).append(info)
    return members


# -- one array -----------------------------------------------------------------------------------------------
def _read_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, key: str, where: str) -> _Header:
    if info.flag_bits & 0x1:
        raise FileFormatError(
            f"{key!r} in {where} is encrypted; arrays are read without a password: {_SAVE} (no encryption)",
            key,
        )
    if info.compress_type not in _METHODS:
        method = _METHOD_NAMES.get(info.compress_type, "an unknown method")
        raise FileFormatError(
            f"{key!r} in {where} is compressed with {method} (zip method {info.compress_type}); only stored "
            f"and deflate members are read: {_SAVE}",
            key,
        )
    try:
        with zf.open(info) as f:
            shape, fortran, dtype = _npy_header(f, key, where)
    except FileFormatError:
        raise
    except DAMAGED as exc:
        raise FileFormatError(f"{key!r} in {where} is corrupt or truncated ({exc}); {_SAVE}", key) from None
    if any(n < 0 for n in shape):
        raise FileFormatError(f"{key!r} in {where} declares a negative size {shape}: a corrupt file", key)
    return _Header(info, shape, fortran, dtype)


def _npy_header(f: IO[bytes], key: str, where: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    try:
        version = npy.read_magic(f)
    except ValueError:
        raise FileFormatError(f"{key!r} in {where} is not a .npy array; {_SAVE}", key) from None
    if version == (1, 0):
        return npy.read_array_header_1_0(f)
    if version == (2, 0):
        return npy.read_array_header_2_0(f)
    raise FileFormatError(
        f"{key!r} in {where} is a .npy of format version {version[0]}.{version[1]} (records with non-Latin-1 "
        "field names); save plain numeric arrays",
        key,
    )


def _check(header: _Header, spec: ArraySpec, key: str, sizes: dict[str, int]) -> None:
    """Check a header against its spec; record the named sizes it sets in ``sizes``."""
    dt, hint = header.dtype, _hint(spec)
    wanted = " or ".join(dict.fromkeys(_KINDS.get(k, k) for k in spec.kinds))
    if dt.hasobject:
        raise FileFormatError(
            f"{key} is an array of Python objects ({dt}), which would need unpickling and is never read; "
            f"save it as {wanted}{hint}",
            key,
        )
    if dt.names is not None or dt.kind == "V":
        raise FileFormatError(
            f"{key} is a structured (record) array ({dt}); save plain {wanted}, one array per field{hint}",
            key,
        )
    if dt.kind not in spec.kinds:
        kind = _KINDS.get(dt.kind, dt.kind)
        raise FileFormatError(f"{key} must hold {wanted}; it holds {dt} ({kind}){hint}", key)
    for shape in spec.shapes:
        bound = _match(shape, header.shape, sizes)
        if bound is not None:
            break
    else:
        got = f"{header.shape}" + (" (a scalar)" if header.shape == () else "")
        raise FileFormatError(f"{key} must have shape {_shapes(spec.shapes, sizes)}; it has {got}{hint}", key)
    for dim, n in bound.items():
        if dim.limit is not None and n > dim.limit:
            raise FileLimitError(
                f"{key} declares {n:,} {dim.what or 'along ' + dim.name}; the limit is {dim.limit:,}: "
                + dim.fix,
                key,
            )
        sizes[dim.name] = n
    if spec.max_bytes is not None and header.nbytes > spec.max_bytes:
        raise FileLimitError(
            f"{key} declares {header.shape} {dt} = {_size(header.nbytes)}; it may hold at most "
            f"{_size(spec.max_bytes)}{hint}",
            key,
        )


def _match(shape: Shape, actual: tuple[int, ...], sizes: Mapping[str, int]) -> dict[Dim, int] | None:
    """The named sizes ``actual`` gives ``shape``'s :class:`Dim` axes, or None when it does not fit."""
    if len(shape) != len(actual):
        return None
    bound: dict[Dim, int] = {}
    seen: dict[str, int] = dict(sizes)
    for axis, n in zip(shape, actual):
        if isinstance(axis, Dim):
            if seen.setdefault(axis.name, n) != n:
                return None
            bound[axis] = n
        elif axis != n:
            return None
    return bound


def _read_data(zf: zipfile.ZipFile, header: _Header, key: str, where: str) -> np.ndarray:
    """The member's array, filled in chunks into an array allocated at the header's (checked) size."""
    out = np.empty(header.shape[::-1] if header.fortran else header.shape, header.dtype)
    if out.nbytes != header.nbytes:  # e.g. a zero-width text dtype numpy widens
        raise FileFormatError(f"{key!r} in {where} has an unsupported dtype {header.dtype}; {_SAVE}", key)
    view = out.reshape(-1).view(np.uint8).data
    n = len(view)
    pos, extra = 0, b""
    try:
        with zf.open(header.info) as f:
            _npy_header(f, key, where)
            while pos < n:
                got = cast(io.BufferedIOBase, f).readinto(view[pos : pos + _CHUNK])
                if not got:
                    break
                pos += got
            if pos == n:
                extra = f.read(1)  # also reaches the end, where zipfile checks the CRC
    except DAMAGED as exc:
        raise FileFormatError(f"{key!r} in {where} is corrupt or truncated ({exc}); {_SAVE}", key) from None
    declared = f"its header declares {header.shape} {header.dtype} = {header.nbytes:,} bytes"
    if pos < n:
        raise FileFormatError(
            f"{key!r} in {where} holds {pos:,} bytes of data but {declared}: the file is truncated or the "
            f"header is wrong; {_SAVE}",
            key,
        )
    if extra:
        raise FileFormatError(
            f"{key!r} in {where} holds more data than {declared}: the header is wrong; {_SAVE}", key
        )
    return out.T if header.fortran else out


# -- words ---------------------------------------------------------------------------------------------------
def _name(source: Source) -> str:
    return "the file" if isinstance(source, bytes | bytearray) else Path(source).name


def _hint(spec: ArraySpec) -> str:
    return f" ({spec.hint})" if spec.hint else ""


def _shapes(shapes: tuple[Shape, ...], sizes: Mapping[str, int]) -> str:
    def axis(a: int | Dim) -> str:
        if isinstance(a, int):
            return str(a)
        return f"{a.name}={sizes[a.name]:,}" if a.name in sizes else a.name

    words = ["(" + ", ".join(axis(a) for a in s) + ("," if len(s) == 1 else "") + ")" for s in shapes]
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " or " + words[-1]


def _size(n: int) -> str:
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:,.1f} {unit}"
    return f"{n} bytes"
