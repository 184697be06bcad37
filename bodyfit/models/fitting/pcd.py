"""A small reader for PCL's PCD point-cloud files (v0.5 / v0.7): ``DATA ascii``, ``binary`` and
``binary_compressed`` (LZF).

trimesh does not read PCD. Only what a scan needs is returned: the ``x y z`` coordinates and, when the file
has them, ``normal_x normal_y normal_z``. Other fields (``rgb``, ``intensity``, ``curvature``, PCL's ``_``
padding, ...) are parsed and dropped. ``VIEWPOINT`` is ignored: points are returned in the file's frame.
Organized clouds (``HEIGHT > 1``) come back flattened row by row, with their NaN "no return" pixels kept.

Every error is a :class:`ValueError` whose message says what was wrong; :mod:`.scan_io` wraps it.
"""

from __future__ import annotations

import numpy as np

_TYPES = {"F": "f", "I": "i", "U": "u"}
_SIZES = (1, 2, 4, 8)
_RESAVE = "re-save it as binary or ascii"


def read_pcd(data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """Parse a PCD file.

    Args:
        data: the whole file.
    Returns:
        points: (N, 3) float64 ``x y z`` in the file's units (NaN rows kept);
        normals: (N, 3) float64 ``normal_x normal_y normal_z``, or None when the file has no normals.
    """
    header, body = _split_header(data)
    names, fields = _fields(header)
    n = _int(header, "POINTS") if "POINTS" in header else _int(header, "WIDTH") * _int(header, "HEIGHT", 1)
    kind = header["DATA"][0].lower()
    if kind == "ascii":
        columns = _ascii(body, fields, n)
    elif kind == "binary":
        columns = _binary(body, fields, n)
    elif kind == "binary_compressed":
        columns = _binary_compressed(body, fields, n)
    else:
        raise ValueError(f"unknown PCD 'DATA {kind}'; expected ascii, binary or binary_compressed")
    missing = [c for c in ("x", "y", "z") if c not in columns]
    if missing:
        raise ValueError(f"PCD has fields {names} but no {' '.join(missing)}; a scan needs x y z")
    points = np.stack([columns[c] for c in ("x", "y", "z")], axis=1)
    normals = None
    if all(c in columns for c in ("normal_x", "normal_y", "normal_z")):
        normals = np.stack([columns[c] for c in ("normal_x", "normal_y", "normal_z")], axis=1)
    return points, normals


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Decompress an LZF block (liblzf's format, as PCL writes it) of known decompressed ``size`` bytes."""
    out = bytearray(size)
    ip = op = 0
    n = len(data)
    try:
        while ip < n:
            ctrl = data[ip]
            ip += 1
            if ctrl < 32:  # a literal run of ctrl + 1 bytes
                length = ctrl + 1
                if ip + length > n or op + length > size:
                    raise IndexError
                out[op : op + length] = data[ip : ip + length]
                ip += length
                op += length
                continue
            length = ctrl >> 5  # a back reference
            if length == 7:
                length += data[ip]
                ip += 1
            ref = op - ((ctrl & 0x1F) << 8) - data[ip] - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > size:
                raise IndexError
            if ref + length <= op:
                out[op : op + length] = out[ref : ref + length]
            else:  # overlapping copy: repeat the last (op - ref) bytes
                for k in range(length):
                    out[op + k] = out[ref + k]
            op += length
    except IndexError:
        raise ValueError(f"corrupt LZF data in a binary_compressed PCD; {_RESAVE}") from None
    if op != size:
        raise ValueError(
            f"binary_compressed PCD decompressed to {op} bytes, header says {size}; the file is corrupt: "
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
        if typ.upper() not in _TYPES or not size.isdigit() or int(size) not in _SIZES or not count.isdigit():
            raise ValueError(f"PCD field {name!r} has unsupported TYPE {typ} / SIZE {size} / COUNT {count}")
        if typ.upper() == "F" and int(size) < 4:
            raise ValueError(f"PCD field {name!r} is a {size}-byte float; only 4 and 8 are supported")
        fields.append((name, np.dtype(f"<{_TYPES[typ.upper()]}{size}"), int(count)))
    return names, fields


def _ascii(body: bytes, fields: list[tuple[str, np.dtype, int]], n: int) -> dict[str, np.ndarray]:
    width = sum(c for _, _, c in fields)
    try:
        values = np.array(body.decode("ascii").split(), dtype=np.float64)
    except (UnicodeDecodeError, ValueError):
        raise ValueError("PCD ascii data holds something that is not a number") from None
    if values.size != n * width:
        raise ValueError(f"PCD ascii data has {values.size} numbers; POINTS {n} x {width} values expected")
    table = values.reshape(n, width)
    columns, start = {}, 0
    for name, _, count in fields:
        columns[name] = table[:, start].copy()
        start += count
    return columns


def _binary(body: bytes, fields: list[tuple[str, np.dtype, int]], n: int) -> dict[str, np.ndarray]:
    dtype = np.dtype([(f"f{i}", dt, (c,)) for i, (_, dt, c) in enumerate(fields)])
    if len(body) < n * dtype.itemsize:
        raise ValueError(f"PCD binary data has {len(body)} bytes; POINTS {n} x {dtype.itemsize} expected")
    table = np.frombuffer(body, dtype, count=n)
    return {name: table[f"f{i}"][:, 0].astype(np.float64) for i, (name, _, _) in enumerate(fields)}


def _binary_compressed(body: bytes, fields: list[tuple[str, np.dtype, int]], n: int) -> dict[str, np.ndarray]:
    """PCL's layout: uint32 compressed size, uint32 raw size, LZF data; the raw data is field by field."""
    if len(body) < 8:
        raise ValueError(f"binary_compressed PCD is truncated; {_RESAVE}")
    packed, size = (int(v) for v in np.frombuffer(body[:8], "<u4"))
    expected = sum(n * dt.itemsize * c for _, dt, c in fields)
    if size != expected or len(body) < 8 + packed:
        raise ValueError(
            f"binary_compressed PCD header is inconsistent (raw size {size}, expected {expected}; compressed "
            f"{packed}, file has {len(body) - 8}); the file is corrupt: {_RESAVE}"
        )
    raw = lzf_decompress(body[8 : 8 + packed], size)
    columns, start = {}, 0
    for name, dt, count in fields:
        block = np.frombuffer(raw, dt, count=n * count, offset=start).reshape(n, count)
        columns[name] = block[:, 0].astype(np.float64)
        start += n * dt.itemsize * count
    return columns
