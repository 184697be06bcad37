"""A small reader for the point (marker) section of C3D files (https://www.c3d.org, "The C3D File Format
User Guide", Motion Lab Systems 2008).

Layout used here: a 512-byte header block (16-bit words: word 1 = first parameter block and the 0x50
key; word 2 = number of points; words 4-5 = first and last frame; words 7-8 = POINT:SCALE as a float,
negative for float data; word 9 = first data block; word 10 = analog samples per frame; words 11-12 =
frame rate), then the parameter section (a 4-byte header whose last byte is the processor: 84 Intel, 85
DEC, 86 MIPS), then per frame ``n_points`` x (X, Y, Z, residual) followed by the analog samples. Integer
data are multiplied by |POINT:SCALE|; a negative residual marks a missing sample. DEC floats are VAX
F-floats: swap the 16-bit halves, read as IEEE and divide by 4. Pure functions, no I/O.

The files it reads, and why it is kept rather than ezc3d, are in docs/readers.md (vendor files in
tests/data/vendors).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

INTEL, DEC, MIPS = 84, 85, 86
BLOCK = 512


class C3DError(ValueError):
    """The bytes are not a C3D file this reader understands (the caller wraps it in a domain error)."""


def _dec_to_ieee(raw: np.ndarray) -> np.ndarray:
    """(n,) little-endian uint32 words of DEC (VAX F) floats -> float32 values."""
    swapped = ((raw >> 16) | (raw << 16)).astype("<u4")
    return swapped.view("<f4") / 4.0


def _floats(buf: bytes, count: int, processor: int) -> np.ndarray:
    """``count`` 32-bit floats of the file's processor type -> (count,) float64."""
    if processor == MIPS:
        return np.frombuffer(buf, ">f4", count).astype(np.float64)
    if processor == DEC:
        return _dec_to_ieee(np.frombuffer(buf, "<u4", count)).astype(np.float64)
    return np.frombuffer(buf, "<f4", count).astype(np.float64)


def _int16(buf: bytes, count: int, processor: int) -> np.ndarray:
    return np.frombuffer(buf, ">i2" if processor == MIPS else "<i2", count).astype(np.int64)


def parse_parameters(data: bytes) -> tuple[dict[str, Any], int]:
    """The parameter section as ``{"GROUP:NAME": value}`` and the processor type.

    Values: str (1-D char), list[str] (2-D char arrays, stripped), numpy arrays (numbers, Fortran order
    reshaped to the declared dimensions reversed), or scalars for zero-dimension parameters.
    """
    if len(data) < BLOCK or data[1] != 0x50:
        raise C3DError("not a C3D file (byte 2 of the header must be 0x50)")
    start = (data[0] - 1) * BLOCK
    if start < BLOCK or start + 4 > len(data):
        raise C3DError(f"parameter section start block {data[0]} lies outside the file")
    processor = data[start + 3]
    if processor not in (INTEL, DEC, MIPS):
        raise C3DError(f"unknown processor type {processor} (expected 84 Intel, 85 DEC or 86 MIPS)")
    i16 = ">h" if processor == MIPS else "<h"
    end = start + data[start + 2] * BLOCK
    groups: dict[int, str] = {}
    params: dict[int, list[tuple[str, Any]]] = {}
    i = start + 4
    while i + 2 <= min(end, len(data)):
        n_chars, gid = struct.unpack("bb", data[i : i + 2])
        if n_chars == 0:
            break
        name = data[i + 2 : i + 2 + abs(n_chars)].decode("latin-1").upper()
        j = i + 2 + abs(n_chars)
        (offset,) = struct.unpack(i16, data[j : j + 2])
        if gid < 0:
            groups[-gid] = name
        else:
            params.setdefault(gid, []).append((name, _param_value(data, j + 2, processor)))
        if offset == 0:
            break
        i = j + offset
    out = {f"{groups.get(g, str(g))}:{n}": v for g, items in params.items() for n, v in items}
    return out, processor


def _chars(raw: bytes) -> str:
    """Character data as text, without the blanks or NUL bytes that pad it (MotionMonitor pads with
    NULs)."""
    return raw.decode("latin-1").replace("\x00", " ").strip()


def _param_value(data: bytes, k: int, processor: int) -> Any:
    kind, n_dims = struct.unpack("bB", data[k : k + 2])
    dims = list(data[k + 2 : k + 2 + n_dims])
    k += 2 + n_dims
    count = int(np.prod(dims)) if dims else 1
    size = abs(kind)
    if size not in (1, 2, 4):
        raise C3DError(f"parameter data type {kind} is not one of -1, 1, 2, 4")
    raw = data[k : k + count * size]
    if len(raw) < count * size:
        raise C3DError("the parameter section is truncated")
    if kind == -1:
        if len(dims) <= 1:
            return _chars(raw)
        width = dims[0]
        if width == 0:  # some exporters (Motion Analysis Cortex, Optotrak) declare empty strings this way
            return [""] * int(np.prod(dims[1:]))
        return [_chars(raw[w : w + width]) for w in range(0, count, width)]
    if kind == 1:
        values = np.frombuffer(raw, np.uint8).astype(np.int64)
    elif kind == 2:
        values = _int16(raw, count, processor)
    else:
        values = _floats(raw, count, processor)
    if not dims:
        return values[0]
    return values.reshape(dims[::-1])


def _get(params: dict[str, Any], key: str, default: Any) -> Any:
    value = params.get(key, default)
    return value.ravel()[0] if isinstance(value, np.ndarray) and value.size else value


def _text(value: Any, default: str) -> str:
    """A character parameter as one string (a 2-D one gives its first entry)."""
    if isinstance(value, list):
        value = value[0] if value else ""
    return str(value).strip() or default


def _frame_range(params: dict[str, Any], first: int, last: int) -> tuple[int, int]:
    """First and last frame: TRIAL:ACTUAL_START_FIELD / END_FIELD (two 16-bit words each, for trials
    over 65,535 frames) when present, else the header's."""
    if "TRIAL:ACTUAL_START_FIELD" in params and "TRIAL:ACTUAL_END_FIELD" in params:
        s = np.asarray(params["TRIAL:ACTUAL_START_FIELD"]).ravel() & 0xFFFF
        e = np.asarray(params["TRIAL:ACTUAL_END_FIELD"]).ravel() & 0xFFFF
        if s.size >= 2 and e.size >= 2:
            return int(s[0] + (s[1] << 16)), int(e[0] + (e[1] << 16))
    return first, last


def _analog_per_frame(params: dict[str, Any], header_count: int, rate: float) -> int:
    """Analog samples stored after each point frame (all channels).

    The C3D guide defines it as ANALOG:USED x ANALOG:RATE / POINT:RATE; header word 3 repeats it. Files
    whose analog rate is not a whole multiple of the point rate disagree: Motion Analysis EVaRT writes
    17 x 28 in the header of a 1000 Hz / 60 Hz trial but stores 16 x 28, and MotionMonitor writes the
    channel count alone. The parameters, with the ratio rounded down, match the data in both; the header
    serves when the parameters are absent.
    """
    used = int(_get(params, "ANALOG:USED", -1))
    analog_rate = float(_get(params, "ANALOG:RATE", 0.0))
    if used >= 0 and analog_rate > 0 and rate > 0:
        return used * int(analog_rate / rate + 1e-6) if used else 0
    return header_count


def parse_c3d_points(data: bytes) -> tuple[list[str], np.ndarray, float, str]:
    """Markers of a C3D file.

    Returns:
        labels (M,), positions (T, M, 3) in the file's units (NaN where the residual is negative),
        point rate (Hz), POINT:UNITS.
    Raises:
        C3DError: not a C3D file, no points, or fewer bytes than the header declares.
    """
    params, processor = parse_parameters(data)
    i16 = ">H" if processor == MIPS else "<H"
    words = [struct.unpack(i16, data[2 * w : 2 * w + 2])[0] for w in range(12)]
    n_points = int(_get(params, "POINT:USED", words[1])) & 0xFFFF
    scale = float(_get(params, "POINT:SCALE", _floats(data[12:16], 1, processor)[0]))
    rate = float(_get(params, "POINT:RATE", _floats(data[20:24], 1, processor)[0]))
    data_block = int(_get(params, "POINT:DATA_START", words[8])) & 0xFFFF
    if data_block < 2:  # PhoeniX and some converters leave the parameter at 0: the header holds it
        data_block = words[8]
    first, last = _frame_range(params, words[3], words[4])
    n_frames = last - first + 1
    if n_points <= 0:
        raise C3DError(
            "the file has no 3D points (POINT:USED = 0): it holds only analog or force-plate data; "
            "export the marker trajectories (C3D or TRC) to fit a body"
        )
    if n_frames <= 0 or rate <= 0:
        raise C3DError(f"bad frame range {first}..{last} or point rate {rate}")
    xyz = _point_frames(
        data, processor, n_points, n_frames, data_block, scale, _analog_per_frame(params, words[2], rate)
    )
    labels: list[str] = []
    for key in ("POINT:LABELS", "POINT:LABELS2", "POINT:LABELS3"):
        value = params.get(key, [])
        labels += [value] if isinstance(value, str) else list(value)
    labels = (labels + [""] * n_points)[:n_points]
    return labels, xyz, rate, _text(params.get("POINT:UNITS", "mm"), "mm")


def _point_frames(
    data: bytes, processor: int, n_points: int, n_frames: int, data_block: int, scale: float, analog: int
) -> np.ndarray:
    """(n_frames, n_points, 3) positions from the data section: per frame ``n_points`` x (X, Y, Z,
    residual), then ``analog`` samples; 16-bit integers times |scale| when ``scale`` > 0, else floats."""
    is_float = scale < 0
    size = 4 if is_float else 2
    frame_values = 4 * n_points + analog
    start = (data_block - 1) * BLOCK
    need = start + n_frames * frame_values * size
    if data_block < 2 or need > len(data):
        raise C3DError(
            f"the file is truncated: {n_frames} frames of {n_points} points need {need} bytes, "
            f"it has {len(data)}; re-export it from the capture software"
        )
    body = data[start:need]
    count = n_frames * frame_values
    values = _floats(body, count, processor) if is_float else _int16(body, count, processor).astype(float)
    frames = values.reshape(n_frames, frame_values)[:, : 4 * n_points].reshape(n_frames, n_points, 4)
    xyz = frames[..., :3] * (1.0 if is_float else abs(scale))
    xyz[frames[..., 3] < 0] = np.nan
    return xyz
