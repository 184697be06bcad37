"""A small reader for PCL's PCD point-cloud files (v0.5 / v0.7): ``DATA ascii``, ``binary`` and
``binary_compressed`` (LZF, decompressed by liblzf).

trimesh does not read PCD. Only what a scan needs is returned: the ``x y z`` coordinates and, when the file
has them, ``normal_x normal_y normal_z``. Other fields (``rgb``, ``intensity``, ``curvature``, PCL's ``_``
padding, ...) are parsed and dropped. ``VIEWPOINT`` is ignored: points are returned in the file's frame.
Organized clouds (``HEIGHT > 1``) come back flattened row by row, with their NaN "no return" pixels kept.

The header's counts are checked before anything is allocated or decompressed: POINTS (= WIDTH x HEIGHT)
against ``max_points`` and the data the file holds, and for binary_compressed the declared compressed and
raw sizes against the file, against what LZF can expand to, and against ``max_bytes``.

A size over a limit raises :class:`~bodyfit.io.errors.FileLimitError`; every other error is a
:class:`ValueError` whose message says what was wrong; :mod:`.scans` wraps it.
"""

from __future__ import annotations

import io
import warnings

import lzf
import numpy as np

from bodyfit.io.errors import FileLimitError
from bodyfit.io.npz import DEFAULT_MAX_BYTES

_TYPES = {"F": "f", "I": "i", "U": "u"}
_SIZES = (1, 2, 4, 8)
_RESAVE = "re-save it as binary or ascii"
THIN = "thin it (a 5 mm voxel grid keeps every detail a body fit uses)"
LZF_MAX_RATIO = 88  # an LZF back reference: 3 bytes in, at most 264 out


def read_pcd(
    data: bytes, *, max_points: int | None = None, max_bytes: int = DEFAULT_MAX_BYTES
) -> tuple[np.ndarray, np.ndarray | None]:
    """Parse a PCD file.

    Args:
        data: the whole file.
        max_points: the most points the header may declare (None: no limit).
        max_bytes: the most bytes the point data may hold, decompressed.
    Returns:
        points: (N, 3) float64 ``x y z`` in the file's units (NaN rows kept);
        normals: (N, 3) float64 ``normal_x normal_y normal_z``, or None when the file has no normals.
    Raises:
        FileLimitError: more points than ``max_points`` or more data than ``max_bytes``; ValueError: the rest.
    """
    header, body = _split_header(data)
    names, fields = _fields(header)
    n = _int(header, "POINTS") if "POINTS" in header else _int(header, "WIDTH") * _int(header, "HEIGHT", 1)
    if "WIDTH" in header and n != _int(header, "WIDTH") * _int(header, "HEIGHT", 1):
        raise ValueError(
            f"PCD header says POINTS {n} but WIDTH x HEIGHT = {header['WIDTH'][0]} x "
            f"{header.get('HEIGHT', ['1'])[0]}; the header is corrupt: fix it or {_RESAVE}"
        )
    if n < 0:
        raise ValueError(f"PCD header declares {n} points; the header is corrupt")
    kind = header["DATA"][0].lower()
    _check_body(kind, body, fields, n)  # a header that claims more than the file holds is corrupt (first)
    if max_points is not None and n > max_points:
        raise FileLimitError(f"the PCD declares {n:,} points; the limit is {max_points:,}: {THIN}", "POINTS")
    record = sum(dt.itemsize * c for _, dt, c in fields)
    if n * record > max_bytes:
        raise FileLimitError(
            f"the PCD declares {n:,} points of {record} bytes = {n * record:,} bytes; the limit is "
            f"{max_bytes:,} bytes: {THIN}",
            "POINTS",
        )
    columns = _READERS[kind](body, fields, n)
    missing = [c for c in ("x", "y", "z") if c not in columns]
    if missing:
        raise ValueError(f"PCD has fields {names} but no {' '.join(missing)}; a scan needs x y z")
    points = np.stack([columns[c] for c in ("x", "y", "z")], axis=1)
    normals = None
    if all(c in columns for c in ("normal_x", "normal_y", "normal_z")):
        normals = np.stack([columns[c] for c in ("normal_x", "normal_y", "normal_z")], axis=1)
    return points, normals


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Decompress an LZF block (liblzf's format, as PCL writes it) of known decompressed ``size`` bytes
    (liblzf itself: back references may overlap their output, as in run-length repeats).

    Raises:
        ValueError: corrupt data, or data that does not decompress to exactly ``size`` bytes.
    """
    if not data or size <= 0:  # liblzf cannot say "empty"; nothing decompresses to nothing
        if data or size:
            raise ValueError(f"corrupt LZF data ({len(data)} bytes for {size}); {_RESAVE}")
        return b""
    try:
        out = lzf.decompress(data, size)
    except ValueError:
        raise ValueError(f"corrupt LZF data in a binary_compressed PCD; {_RESAVE}") from None
    if out is None or len(out) != size:
        got = "more" if out is None else f"{len(out)}"
        raise ValueError(
            f"binary_compressed PCD decompressed to {got} bytes, header says {size}; the file is corrupt: "
            + _RESAVE
        )
    return bytes(out)


def _split_header(data: bytes) -> tuple[dict[str, list[str]], bytes]:
    header: dict[str, list[str]] = {}
    pos = 0
    while pos < len(data):
        end = data.find(b"\n", pos)
        end = len(data) if end < 0 else end
        line = data[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            if not values:
                raise ValueError("PCD 'DATA' line has no type")
            return header, data[pos:]
        if len(header) > 20:
            break
    raise ValueError("not a PCD file: no 'DATA ascii|binary|binary_compressed' header line")


def _int(header: dict[str, list[str]], key: str, default: int | None = None) -> int:
    if key not in header:
        if default is None:
            raise ValueError(f"PCD header has no {key} line")
        return default
    try:
        return int(header[key][0])
    except (ValueError, IndexError):
        raise ValueError(f"PCD header {key} {header[key]} is not an integer") from None


def _fields(header: dict[str, list[str]]) -> tuple[list[str], list[tuple[str, np.dtype, int]]]:
    """(names, [(name, dtype, count)]) of the header's FIELDS / SIZE / TYPE / COUNT lines."""
    names = header.get("FIELDS", header.get("COLUMNS"))
    if not names:
        raise ValueError("PCD header has no FIELDS line")
    sizes, types = header.get("SIZE", []), header.get("TYPE", [])
    counts = header.get("COUNT", ["1"] * len(names))
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise ValueError(f"PCD header FIELDS {names} do not match SIZE {sizes}, TYPE {types}, COUNT {counts}")
    fields = []
    for name, size, typ, count in zip(names, sizes, types, counts):
        bad_count = not count.isdigit() or int(count) < 1
        if typ.upper() not in _TYPES or not size.isdigit() or int(size) not in _SIZES or bad_count:
            raise ValueError(f"PCD field {name!r} has unsupported TYPE {typ} / SIZE {size} / COUNT {count}")
        if typ.upper() == "F" and int(size) < 4:
            raise ValueError(f"PCD field {name!r} is a {size}-byte float; only 4 and 8 are supported")
        fields.append((name, np.dtype(f"<{_TYPES[typ.upper()]}{size}"), int(count)))
    return names, fields


def _ascii(body: bytes, fields: list[tuple[str, np.dtype, int]], n: int) -> dict[str, np.ndarray]:
    """One row of numbers per point; at most n + 1 rows of the declared width are parsed (C speed)."""
    width = sum(c for _, _, c in fields)
    table = np.zeros((0, width))
    if n:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # e.g. "no data" for blank lines: the rows are counted below
                rows = io.BytesIO(body)
                table = np.loadtxt(rows, ndmin=2, max_rows=n + 1, usecols=range(width), encoding="ascii")
        except (ValueError, UnicodeDecodeError) as exc:
            raise ValueError(
                f"PCD ascii data is not {width} numbers per line ({str(exc).splitlines()[0]})"
            ) from None
    if len(table) != n:
        rows_found = "more than" if len(table) > n else len(table)
        raise ValueError(f"PCD ascii data has {rows_found} rows; the header says POINTS {n}")
    columns, start = {}, 0
    for name, _, count in fields:
        columns[name] = table[:, start].copy()
        start += count
    return columns


def _binary(body: bytes, fields: list[tuple[str, np.dtype, int]], n: int) -> dict[str, np.ndarray]:
    dtype = np.dtype([(f"f{i}", dt, (c,)) for i, (_, dt, c) in enumerate(fields)])
    table = np.frombuffer(body, dtype, count=n)
    return {name: table[f"f{i}"][:, 0].astype(np.float64) for i, (name, _, _) in enumerate(fields)}


def _binary_compressed(body: bytes, fields: list[tuple[str, np.dtype, int]], n: int) -> dict[str, np.ndarray]:
    """PCL's layout: uint32 compressed size, uint32 raw size, LZF data; the raw data is field by field
    (sizes checked by :func:`_check_body`)."""
    packed, size = (int(v) for v in np.frombuffer(body[:8], "<u4"))
    raw = lzf_decompress(body[8 : 8 + packed], size)
    columns, start = {}, 0
    for name, dt, count in fields:
        block = np.frombuffer(raw, dt, count=n * count, offset=start).reshape(n, count)
        columns[name] = block[:, 0].astype(np.float64)
        start += n * dt.itemsize * count
    return columns


_READERS = {"ascii": _ascii, "binary": _binary, "binary_compressed": _binary_compressed}


def _check_body(kind: str, body: bytes, fields: list[tuple[str, np.dtype, int]], n: int) -> None:
    """The data a header declares against the bytes the file holds (ascii: a digit and a separator per
    value at least; binary: n records; binary_compressed: its two sizes, and what LZF can expand to)."""
    record = sum(dt.itemsize * c for _, dt, c in fields)
    if kind == "ascii":
        width = sum(c for _, _, c in fields)
        if len(body) < 2 * n * width - 1:
            raise ValueError(f"PCD ascii data has {len(body)} bytes; POINTS {n} x {width} numbers need more")
    elif kind == "binary":
        if len(body) < n * record:
            raise ValueError(f"PCD binary data has {len(body)} bytes; POINTS {n} x {record} expected")
    elif kind == "binary_compressed":
        if len(body) < 8:
            raise ValueError(f"binary_compressed PCD is truncated; {_RESAVE}")
        packed, size = (int(v) for v in np.frombuffer(body[:8], "<u4"))
        if size != n * record or len(body) < 8 + packed:
            raise ValueError(
                f"binary_compressed PCD header is inconsistent (raw size {size}, expected {n * record}; "
                f"compressed {packed}, file has {len(body) - 8}); the file is corrupt: {_RESAVE}"
            )
        if size > packed * LZF_MAX_RATIO:
            raise ValueError(
                f"binary_compressed PCD claims {size:,} raw bytes from {packed:,} compressed, more than LZF "
                f"can expand ({LZF_MAX_RATIO}x); the file is corrupt: {_RESAVE}"
            )
    else:
        raise ValueError(f"unknown PCD 'DATA {kind}'; expected ascii, binary or binary_compressed")
