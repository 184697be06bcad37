"""Marker trajectories from motion capture files: TRC (OpenSim, Vicon, Cortex exports) and C3D.

Every reader returns a :class:`MarkerTrial`: marker names, positions ``(T, M, 3)`` in metres in *our*
world frame (OpenSim ground: +Y up, +X forward, +Z right; see :mod:`bodyfit.models`), the frame rate and
the frame times. Missing samples are NaN: empty TRC cells, C3D points with a negative residual and, unless
``zeros_missing=False``, samples at exactly (0, 0, 0), which many exporters write for a gap (the Hamner
running trial of the OpenSim examples does).

Frame assumption: the file's axes are taken as ours unless ``rotation`` says otherwise. That holds for
TRC files written for OpenSim (they are Y up already). Many C3D files are Z up: pass
``rotation=lab_rotation(up="z", forward="x")`` (or any proper 3x3 rotation) to map lab axes to ours.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bodyfit.io.c3d import C3DError, parse_c3d_points
from bodyfit.models.errors import BodyfitError

UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "meters": 1.0, "millimeters": 1e-3}
_AXES = {"x": 0, "y": 1, "z": 2}


class MocapFormatError(BodyfitError):
    """A motion capture file is malformed or uses something this reader does not support."""


@dataclass(frozen=True)
class MarkerTrial:
    """Marker trajectories of one trial.

    Attributes:
        names: (M,) marker names, unique.
        positions: (T, M, 3) metres in our world frame; NaN where a marker is missing.
        rate: frames per second.
        times: (T,) seconds.
        source: where the data came from (file name), for messages.
    """

    names: tuple[str, ...]
    positions: np.ndarray
    rate: float
    times: np.ndarray
    source: str = ""
    _index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.positions, np.float64)
        if p.ndim != 3 or p.shape[2] != 3 or p.shape[1] != len(self.names):
            raise MocapFormatError(
                f"marker positions must have shape (T, {len(self.names)}, 3) for {len(self.names)} names; "
                f"got {p.shape}"
            )
        if len(set(self.names)) != len(self.names):
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise MocapFormatError(f"marker names must be unique; repeated: {', '.join(dup)}")
        t = np.asarray(self.times, np.float64)
        if t.shape != (p.shape[0],):
            raise MocapFormatError(f"times must have shape ({p.shape[0]},); got {t.shape}")
        if not (np.isfinite(self.rate) and self.rate > 0):
            raise MocapFormatError(f"frame rate must be a positive number of Hz; got {self.rate}")
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "_index", {n: i for i, n in enumerate(self.names)})

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return len(self.names)

    def marker(self, name: str) -> np.ndarray:
        """(T, 3) trajectory of one marker."""
        if name not in self._index:
            raise MocapFormatError(f"no marker {name!r} in {self.source or 'the trial'}")
        return self.positions[:, self._index[name]]

    def frames(self, index: slice | np.ndarray) -> MarkerTrial:
        """The trial restricted to some frames (a slice or an index array)."""
        sel = np.arange(self.n_frames)[index]
        return MarkerTrial(self.names, self.positions[sel], self.rate, self.times[sel], self.source)

    def between(self, start: float, stop: float) -> MarkerTrial:
        """Frames with ``start <= time <= stop`` (seconds, half a frame of tolerance)."""
        tol = 0.5 / self.rate
        return self.frames(np.flatnonzero((self.times >= start - tol) & (self.times <= stop + tol)))

    def rotated(self, rotation: np.ndarray) -> MarkerTrial:
        """Positions mapped by a (3, 3) rotation: ``p_new = rotation @ p``."""
        R = check_rotation(rotation)
        return MarkerTrial(self.names, self.positions @ R.T, self.rate, self.times, self.source)


def check_rotation(rotation: np.ndarray) -> np.ndarray:
    """A (3, 3) proper rotation as float64, or MocapFormatError."""
    R = np.asarray(rotation, np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise MocapFormatError("rotation must be a proper 3x3 rotation matrix (orthonormal, det +1)")
    return R


def lab_rotation(up: str = "y", forward: str = "x") -> np.ndarray:
    """Rotation from a lab frame whose ``up`` and ``forward`` axes are named (``"x"``, ``"-z"``, ...) to
    ours (+Y up, +X forward, +Z right). Returns (3, 3)."""

    def axis(s: str) -> np.ndarray:
        s = s.strip().lower()
        sign = -1.0 if s.startswith("-") else 1.0
        if s.lstrip("+-") not in _AXES:
            raise MocapFormatError(f"axis must be one of x, y, z with an optional sign; got {s!r}")
        v = np.zeros(3)
        v[_AXES[s.lstrip("+-")]] = sign
        return v

    u, f = axis(up), axis(forward)
    if abs(u @ f) > 0:
        raise MocapFormatError(f"up ({up}) and forward ({forward}) must be different axes")
    lab = np.stack([f, u, np.cross(f, u)])  # rows: lab coordinates of our x, y, z
    return lab


def _times(raw: np.ndarray, rate: float, n: int) -> np.ndarray:
    """File times when they are usable; regular times ``t0 + i / rate`` when the file's are rounded."""
    if raw.shape == (n,) and np.isfinite(raw).all() and n > 0:
        regular = raw[0] + np.arange(n) / rate
        return regular if np.abs(raw - regular).max() < min(2e-3, 0.25 / rate) else raw
    return np.arange(n) / rate


def _mask_zeros(positions: np.ndarray, zeros_missing: bool) -> np.ndarray:
    """(T, M, 3) with exact (0, 0, 0) samples set to NaN when ``zeros_missing``."""
    if zeros_missing:
        positions = positions.copy()
        positions[(positions == 0.0).all(-1)] = np.nan
    return positions


def parse_trc(
    text: str, rotation: np.ndarray | None = None, source: str = "TRC", zeros_missing: bool = True
) -> MarkerTrial:
    """Parse the text of a TRC file (tab separated, or comma separated when a spreadsheet re-saved it;
    header keys DataRate, NumFrames, NumMarkers, Units).

    Empty cells are missing samples (NaN). Raises MocapFormatError naming what is wrong.
    """
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise MocapFormatError(
            f"{source} is not a TRC file: the first line must start with 'PathFileType' (OpenSim / Vicon "
            "TRC layout: 5 header lines, then one tab-separated row per frame)"
        )
    comma = "\t" not in lines[1] and "," in lines[1]  # a TRC re-saved as CSV by a spreadsheet
    rate, n_markers, unit, names = _trc_header(lines, source, comma)
    rows = _trc_rows(lines, 2 + 3 * n_markers, source, comma)
    data = np.asarray(rows, np.float64)
    positions = _mask_zeros(data[:, 2:].reshape(len(rows), n_markers, 3), zeros_missing) * UNITS[unit]
    trial = MarkerTrial(tuple(names), positions, rate, _times(data[:, 1], rate, len(rows)), source)
    return trial if rotation is None else trial.rotated(rotation)


def _split(line: str, comma: bool) -> list[str]:
    """A TRC line's cells: commas when ``comma``, else tabs, else runs of blanks."""
    if comma:
        return line.split(",")
    return line.split("\t") if "\t" in line else line.split()


def _trc_header(lines: list[str], source: str, comma: bool) -> tuple[float, int, str, list[str]]:
    """Returns the data rate (Hz), the marker count, the lower-case unit and the marker names from a TRC
    file's header lines (2 to 4)."""
    keys = [k.strip() for k in (lines[1].split(",") if comma else lines[1].split()) if k.strip()]
    values = [v.strip() for v in (lines[2].split(",") if comma else lines[2].split()) if v.strip()]
    header = dict(zip(keys, values))
    for key in ("DataRate", "NumMarkers", "Units"):
        if key not in header:
            raise MocapFormatError(f"{source}: header line 2 lacks {key!r} (found {', '.join(keys)})")
    try:
        rate = float(header["DataRate"])
        n_markers = int(header["NumMarkers"])
    except ValueError as exc:
        raise MocapFormatError(f"{source}: DataRate and NumMarkers must be numbers ({exc})") from exc
    unit = header["Units"].strip().lower()
    if unit not in UNITS:
        raise MocapFormatError(f"{source}: unknown Units {header['Units']!r}; expected one of {list(UNITS)}")
    names = [n.strip() for n in lines[3].split("," if comma else "\t")[2:] if n.strip()]
    if len(names) != n_markers:
        raise MocapFormatError(
            f"{source}: the header says NumMarkers={n_markers} but line 4 names {len(names)} markers"
        )
    return rate, n_markers, unit, names


def _trc_rows(lines: list[str], width: int, source: str, comma: bool) -> list[list[float]]:
    """Returns the TRC file's data rows (frame, time, then x y z per marker), each ``width`` numbers with
    empty cells as NaN; blank lines are skipped and at least one row is required."""
    rows = []
    for k, line in enumerate(lines[5:], start=6):
        if not line.strip(",\t "):
            continue
        cells = _split(line, comma)
        if len(cells) > width and any(c.strip() for c in cells[width:]):
            raise MocapFormatError(f"{source} line {k}: {len(cells)} columns, expected at most {width}")
        cells = (cells + [""] * width)[:width]
        try:
            rows.append([float(c) if c.strip() else np.nan for c in cells])
        except ValueError as exc:
            raise MocapFormatError(f"{source} line {k}: not a number ({exc})") from exc
    if not rows:
        raise MocapFormatError(f"{source} holds no frames")
    return rows


def parse_c3d(
    data: bytes, rotation: np.ndarray | None = None, source: str = "C3D", zeros_missing: bool = True
) -> MarkerTrial:
    """Parse the bytes of a C3D file's point section (Intel, DEC or MIPS; integer or float data).

    Points with a negative residual are missing (NaN). Analog data are ignored.
    """
    try:
        labels, xyz, rate, unit = parse_c3d_points(data)
    except C3DError as exc:
        raise MocapFormatError(f"{source}: {exc}") from exc
    factor = UNITS.get(unit.strip().lower())
    if factor is None:
        raise MocapFormatError(f"{source}: unknown POINT:UNITS {unit!r}; expected one of {list(UNITS)}")
    names = _unique([n.strip() for n in labels])
    xyz = _mask_zeros(xyz, zeros_missing) * factor
    trial = MarkerTrial(tuple(names), xyz, rate, np.arange(len(xyz)) / rate, source)
    return trial if rotation is None else trial.rotated(rotation)


def _unique(names: list[str]) -> list[str]:
    """Make names unique by suffixing repeats (``M``, ``M_2``); empty names become ``marker_<i>``."""
    out: list[str] = []
    for i, n in enumerate(names):
        base = n or f"marker_{i + 1}"
        name, k = base, 2
        while name in out:
            name, k = f"{base}_{k}", k + 1
        out.append(name)
    return out


def read_trc(path: str | Path, rotation: np.ndarray | None = None) -> MarkerTrial:
    """Read a TRC file. See :func:`parse_trc`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise MocapFormatError(f"cannot read {p}: {exc.strerror}") from exc
    return parse_trc(text, rotation, p.name)


def read_c3d(path: str | Path, rotation: np.ndarray | None = None) -> MarkerTrial:
    """Read a C3D file's markers. See :func:`parse_c3d`."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise MocapFormatError(f"cannot read {p}: {exc.strerror}") from exc
    return parse_c3d(data, rotation, p.name)


def read_markers(path: str | Path, rotation: np.ndarray | None = None) -> MarkerTrial:
    """Read a ``.trc`` or ``.c3d`` file (chosen by suffix)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".trc":
        return read_trc(path, rotation)
    if suffix == ".c3d":
        return read_c3d(path, rotation)
    raise MocapFormatError(f"unsupported marker file {Path(path).name!r}: give a .trc or .c3d file")


def write_trc(path: str | Path, trial: MarkerTrial, units: str = "mm") -> Path:
    """Write a trial as an OpenSim-readable TRC file (missing samples as empty cells)."""
    if units not in ("mm", "m"):
        raise MocapFormatError(f"units must be 'mm' or 'm'; got {units!r}")
    scale = 1.0 / UNITS[units]
    T, M = trial.n_frames, trial.n_markers
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{trial.rate:g}\t{trial.rate:g}\t{T}\t{M}\t{units}\t{trial.rate:g}\t1\t{T}",
        "Frame#\tTime\t" + "\t\t\t".join(trial.names) + "\t\t",
        "\t\t" + "\t".join(f"{a}{i + 1}" for i in range(M) for a in "XYZ"),
        "",
    ]
    for k in range(T):
        vals = trial.positions[k].ravel() * scale
        cells = ["" if not np.isfinite(v) else f"{v:.6f}" for v in vals]
        lines.append(f"{k + 1}\t{trial.times[k]:.6f}\t" + "\t".join(cells))
    out = Path(path)
    out.write_text("\n".join(lines) + "\n")
    return out


__all__ = [
    "MarkerTrial",
    "MocapFormatError",
    "lab_rotation",
    "parse_c3d",
    "parse_trc",
    "read_c3d",
    "read_markers",
    "read_trc",
    "write_trc",
]
