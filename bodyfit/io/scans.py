"""Raw scans in: PLY, OBJ, STL, PCD or NPZ files (or their bytes) to a validated :class:`Scan` in metres.

Formats: PLY (ascii or binary; mesh or point cloud; vertex normals ``nx ny nz`` read when present), OBJ,
STL (ascii or binary; STL is a triangle soup, so its exactly equal corners are merged into shared vertices),
PCD (PCL point clouds: ascii, binary and binary_compressed; ``normal_x..`` read when present; see
:mod:`.pcd`) and NPZ (``points`` or ``vertices``, optional ``faces`` and ``normals``). Meshes are read with
trimesh and ``process=False``, so vertex order is kept.

Units (``units="auto"``): the scan's largest extent E is measured robustly (see :func:`largest_extent`).
A human, whole or a partial upper-body capture, spans 0.1 m to 3 m (:data:`MIN_EXTENT_M`,
:data:`MAX_EXTENT_M`), so E in [0.1, 3] is read as metres. E in [250, 3000] (:data:`MIN_EXTENT_MM`) is read
as millimetres and divided by 1000. Anything else fails with the extent in the message: in particular
10-250 is ambiguous (a whole body in centimetres is 170; a head-and-shoulders scan in millimetres may be
200), and more than 3 m is a scene or the wrong unit. ``units="m"`` / ``"mm"`` force the unit and skip the
size check (for a small partial scan in mm, or a scan with a large background to be cropped later).

Limits (``max_points``, and :data:`FACES_PER_POINT` faces per allowed point): the counts a file declares
(PLY ``element vertex`` / ``element face``, binary STL's triangle count, PCD's POINTS, an NPZ's array
headers, an OBJ's ``v`` / ``f`` lines) are checked before anything is allocated, against the limits and
against the bytes the file holds; decompressed data (NPZ, binary_compressed PCD) against ``max_bytes``. A
count over a limit raises :class:`~bodyfit.io.errors.FileLimitError`, anything else :class:`ScanError`.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from bodyfit.io.errors import FileLimitError
from bodyfit.io.npz import DEFAULT_MAX_BYTES, INTEGER, NUMBER, ArraySpec, Dim, npz_keys, read_npz
from bodyfit.io.pcd import THIN, read_pcd
from bodyfit.models.errors import BodyfitError

FORMATS = ("ply", "obj", "stl", "pcd", "npz")
MIN_POINTS = 300
MIN_EXTENT_M = 0.1
MAX_EXTENT_M = 3.0
MIN_EXTENT_MM = 250.0
_FLAT = 1e-3  # a singular value below this fraction of the largest means the points lie on a plane / line
_POINT_KEYS = ("points", "vertices")
FACES_PER_POINT = 2  # a closed triangle mesh has about two faces per vertex
# bytes of one PLY property of each type
_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2}
_PLY_SIZES |= {"int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4}
_PLY_SIZES |= {"double": 8, "float64": 8}


class ScanError(BodyfitError):
    """A scan file or array is unreadable, empty, non-finite, degenerate or not human-sized."""


@dataclass(frozen=True)
class Scan:
    """A validated raw scan.

    Attributes:
        points: (N, 3) float64 positions in metres, finite, N >= MIN_POINTS.
        faces: (F, 3) int64 indices into ``points`` for a mesh, or None for a point cloud.
        normals: (N, 3) float64 per-point normals as stored in the file (not renormalised), or None.
        source_units: "m" or "mm": the units the file was in (points are always metres).
        n_input_points: points in the input, before non-finite rows were dropped.
    """

    points: np.ndarray
    faces: np.ndarray | None
    normals: np.ndarray | None
    source_units: str
    n_input_points: int

    @property
    def n_points(self) -> int:
        return len(self.points)


def load_scan(
    path_or_bytes: str | os.PathLike[str] | bytes,
    format: str | None = None,
    units: str = "auto",
    drop_nonfinite: bool = False,
    *,
    max_points: int | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> Scan:
    """Read and validate a scan file.

    Args:
        path_or_bytes: a file path, or the file's bytes (then ``format`` is required).
        format: one of :data:`FORMATS`; default: the path's suffix.
        units: "auto" (see the module docstring), "m" or "mm".
        drop_nonfinite: drop points with NaN / inf coordinates (and faces using them) instead of raising.
        max_points: the most points (and ``FACES_PER_POINT`` times as many faces) the file may declare or
            hold; None: no limit.
        max_bytes: the most bytes compressed data (NPZ, binary_compressed PCD) may decompress to.
    Returns:
        the :class:`Scan`, points (N, 3) in metres.
    Raises:
        FileLimitError: more points or faces than allowed, or more decompressed bytes (checked from the
            header where the format has one).
        ScanError: what was wrong with the file and how to fix it.
    """
    data, name, format = _scan_bytes(path_or_bytes, format)
    fmt = format.lower()
    if fmt not in FORMATS:
        raise ScanError(f"unknown scan format {format!r}; supported: {', '.join(FORMATS)}")
    if not data.strip():
        raise ScanError(f"{name} is empty")
    caps = _Caps(max_points, None if max_points is None else FACES_PER_POINT * max_points, max_bytes)
    points, faces, normals = _read_format(data, fmt, name, caps)
    if len(points) == 0:
        raise ScanError(f"{name} holds no points (empty, or not a valid {fmt.upper()} file)")
    if max_points is not None and len(points) > max_points:
        raise FileLimitError(f"{name} holds {len(points):,} points; the limit is {max_points:,}: {THIN}")
    return scan_from_arrays(points, faces, normals, units=units, drop_nonfinite=drop_nonfinite)


def _scan_bytes(path_or_bytes: str | os.PathLike[str] | bytes, format: str | None) -> tuple[bytes, str, str]:
    """Returns the file's bytes, its name for messages, and its format as given (default: the suffix)."""
    if isinstance(path_or_bytes, bytes | bytearray):
        if format is None:
            raise ScanError(f"format= is required when loading bytes; one of {', '.join(FORMATS)}")
        return bytes(path_or_bytes), f"<{len(path_or_bytes)} bytes>", format
    path = Path(path_or_bytes)
    format = format or path.suffix.lstrip(".")
    name = str(path)
    if format.lower() not in FORMATS:
        raise ScanError(f"unknown scan format {format!r} ({name}); supported: {', '.join(FORMATS)}")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ScanError(f"cannot read {name}: {e.strerror or e}") from None
    return data, name, format


def _read_format(data: bytes, fmt: str, name: str, caps: _Caps) -> _Arrays:
    """Returns points (N, 3), faces (F, 3) or None and normals (N, 3) or None as the reader for ``fmt``
    found them; a reader's own failure becomes a ScanError naming the file."""
    try:
        return _READERS[fmt](data, caps)
    except (ScanError, FileLimitError):
        raise
    except Exception as e:
        raise ScanError(f"could not read {name} as {fmt.upper()}: {e}") from None


def scan_from_arrays(
    points: np.ndarray,
    faces: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    *,
    units: str = "auto",
    drop_nonfinite: bool = False,
) -> Scan:
    """Validate arrays as a :class:`Scan` (the checks of :func:`load_scan`).

    Args:
        points: (N, 3) positions in metres or millimetres; faces: (F, 3) integer indices or None;
        normals: (N, 3) or None; units, drop_nonfinite: as in :func:`load_scan`.
    Returns:
        the :class:`Scan`.
    """
    if units not in ("auto", "m", "mm"):
        raise ScanError(f"units must be 'auto', 'm' or 'mm', got {units!r}")
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ScanError(f"points must have shape (N, 3), got {p.shape}")
    n_input = len(p)
    nrm = None if normals is None else np.asarray(normals, dtype=np.float64)
    if nrm is not None and nrm.shape != p.shape:
        raise ScanError(f"normals must have the points' shape {p.shape}, got {nrm.shape}")
    f = _checked_faces(faces, n_input)
    p, nrm, f = _finite_rows(p, nrm, f, drop_nonfinite)
    if len(p) < MIN_POINTS:
        raise ScanError(f"the scan has {len(p)} points; at least {MIN_POINTS} are needed to fit a body")
    _check_not_flat(p)
    source_units = units if units != "auto" else _detect_units(p)
    if source_units == "mm":
        p = p / 1000.0
    return Scan(p, f, nrm, source_units, n_input)


def _checked_faces(faces: np.ndarray | None, n_input: int) -> np.ndarray | None:
    """Returns faces (F, 3) as int64 indices into ``n_input`` points, or None for no faces (None or empty)."""
    f = None if faces is None or len(faces) == 0 else np.asarray(faces)
    if f is None:
        return None
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ScanError(f"faces must be (F, 3) integers, got {f.shape} {f.dtype}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= n_input:
        raise ScanError(
            f"faces index vertices {f.min()}..{f.max()} but the scan has {n_input} points: a corrupt mesh"
        )
    return f


def _finite_rows(
    p: np.ndarray, nrm: np.ndarray | None, f: np.ndarray | None, drop_nonfinite: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Returns points (N', 3), normals and faces without the non-finite points (raises unless
    ``drop_nonfinite``); the inputs themselves when every point is finite."""
    bad = np.asarray(~np.isfinite(p).all(axis=1))
    if not bad.any():
        return p, nrm, f
    if not drop_nonfinite:
        raise ScanError(
            f"{int(bad.sum()):,} of {len(p):,} points are NaN or infinite (depth cameras and organized "
            "PCD clouds mark missing pixels this way); pass drop_nonfinite=True to drop them"
        )
    return _drop_rows(p, nrm, f, bad)


def _check_not_flat(p: np.ndarray) -> None:
    """Returns None; raises when the points (N, 3) lie on one point, a line or a plane."""
    sv = np.sqrt(np.clip(np.linalg.eigvalsh(np.cov(p.T)), 0.0, None))[::-1]
    if sv[0] == 0 or sv[1] < _FLAT * sv[0]:
        raise ScanError("the scan's points all lie on one point or a line (degenerate); it cannot be a body")
    if sv[2] < _FLAT * sv[0]:
        raise ScanError("the scan's points all lie on a plane (degenerate); it cannot be a body")


def largest_extent(points: np.ndarray) -> float:
    """The largest per-axis extent of (N, 3) finite points, between the 1st and 99th percentiles so that a
    few outliers do not count (for uniform outliers in a box, or a scan's stray returns)."""
    lo, hi = np.percentile(points, [1.0, 99.0], axis=0)
    return float((hi - lo).max())


def save_scan(path: str | os.PathLike[str], scan: Scan) -> None:
    """Write a scan (points in metres) as binary little-endian PLY (float64 vertices, with ``nx ny nz``
    when the scan has normals, and faces when it has them) or NPZ (``points``, ``faces``, ``normals``),
    chosen by the suffix."""
    path = Path(path)
    suffix = path.suffix.lower().lstrip(".")
    if suffix == "npz":
        arrays = {"points": scan.points}
        if scan.faces is not None:
            arrays["faces"] = scan.faces
        if scan.normals is not None:
            arrays["normals"] = scan.normals
        np.savez(path, **arrays)  # type: ignore[arg-type]
        return
    if suffix != "ply":
        raise ScanError(f"save_scan writes .ply or .npz, not {path.suffix!r}")
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if scan.normals is not None else [])
    cols = [scan.points] + ([scan.normals] if scan.normals is not None else [])
    vertex = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f8")
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertex)}"]
    lines += [f"property double {n}" for n in names]
    n_faces = 0 if scan.faces is None else len(scan.faces)
    if n_faces:
        lines += [f"element face {n_faces}", "property list uchar int vertex_indices"]
    header = "\n".join([*lines, "end_header"]) + "\n"
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vertex.tobytes())
        if scan.faces is not None and n_faces:
            rec = np.zeros(n_faces, dtype=[("n", "u1"), ("v", "<i4", (3,))])
            rec["n"], rec["v"] = 3, scan.faces
            fh.write(rec.tobytes())


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, n: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Sample n points uniformly by area on a triangle mesh, deterministically for a seed.

    A face is drawn with probability proportional to its area, then a point in it with the square-root
    barycentric formula of R. Osada, T. Funkhouser, B. Chazelle and D. Dobkin, "Shape Distributions", ACM
    Transactions on Graphics 21(4), 2002.

    Args:
        vertices: (V, 3); faces: (F, 3) indices.
    Returns:
        points (n, 3) and their unit face normals (n, 3) (outward for counter-clockwise faces).
    """
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces, np.int64)]  # (F, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    if not area.sum() > 0:
        raise ScanError("the mesh has no area to sample")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    w = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)  # uniform barycentric weights
    points = np.einsum("nk,nkd->nd", w, tri[face])
    normals = cross[face] / np.maximum(area[face], 1e-300)[:, None]
    return points, normals


def _detect_units(p: np.ndarray) -> str:
    extent = largest_extent(p)
    if MIN_EXTENT_M <= extent <= MAX_EXTENT_M:
        return "m"
    if MIN_EXTENT_MM <= extent <= MAX_EXTENT_M * 1000.0:
        return "mm"
    raise ScanError(
        f"the scan's largest extent is {extent:.4g}: not a human in metres ({MIN_EXTENT_M}-{MAX_EXTENT_M}) "
        f"or millimetres ({MIN_EXTENT_MM:g}-{MAX_EXTENT_M * 1000:g}); pass units='m' or units='mm' to load "
        "it anyway (and crop any background), or scale the points to metres or millimetres first"
    )


def _drop_rows(
    p: np.ndarray, nrm: np.ndarray | None, f: np.ndarray | None, bad: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Drop rows ``bad`` (N,) of points (N, 3) and normals, and the faces that use them (reindexed)."""
    keep = ~bad
    if f is not None:
        new_index = np.cumsum(keep) - 1
        f = new_index[f[keep[f].all(axis=1)]]
        f = f if len(f) else None
    return p[keep], None if nrm is None else nrm[keep], f


_Arrays = tuple[np.ndarray, np.ndarray | None, np.ndarray | None]


@dataclass(frozen=True)
class _Caps:
    """What a reader may allocate: points and faces (None: no limit) and decompressed bytes."""

    points: int | None
    faces: int | None
    bytes: int

    def check(self, n: int, what: str, limit: int | None) -> None:
        if limit is not None and n > limit:
            raise FileLimitError(f"the file declares {n:,} {what}; the limit is {limit:,}: {THIN}", what)


def _read_ply(data: bytes, caps: _Caps) -> _Arrays:
    _check_ply(data, caps)
    d = trimesh.exchange.ply.load_ply(io.BytesIO(data))
    return np.asarray(d.get("vertices", np.zeros((0, 3)))), d.get("faces"), d.get("vertex_normals")


def _check_ply(data: bytes, caps: _Caps) -> None:
    """The header's element counts against the data the file holds (at least a digit and a separator per
    ascii value; the fixed sizes, and each list's count, per binary element), then against the limits."""
    end = data.find(b"end_header")
    stop = data.find(b"\n", end)
    if not data.startswith(b"ply") or end < 0 or stop < 0:
        raise ValueError("not a PLY file: it needs a header from 'ply' to 'end_header'")
    lines = [line.split() for line in data[:end].decode("ascii", errors="replace").splitlines()]
    form = next((line[1] for line in lines if line[:1] == ["format"] and len(line) > 1), "")
    if form not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"PLY format {form!r} unknown; use ascii, binary_little_endian or binary_big_endian")
    counts, least = _ply_elements(lines, form)
    need = sum(counts[e] * least[e] for e in counts) - (1 if form == "ascii" else 0)
    body = len(data) - stop - 1
    if need > body:
        detail = ", ".join(f"{c:,} {n}" for n, c in counts.items())
        raise ValueError(
            f"the {form} PLY header declares {detail}, at least {need:,} bytes of data, but the file has "
            f"{body:,}: it is truncated or its header is wrong; re-export it"
        )
    rows = data.count(b"\n", stop + 1) if form == "ascii" else 0  # each line is parsed, wanted or not
    if rows > sum(counts.values()) + 1000:
        raise ValueError(
            f"the ascii PLY has {rows:,} lines of data but its header declares {sum(counts.values()):,} "
            "elements (one a line); its header is wrong: re-export it"
        )
    # only a header whose data is there is held to the limits: else the file is corrupt, not too large
    caps.check(counts.get("vertex", 0), "points", caps.points)
    caps.check(counts.get("face", 0), "faces", caps.faces)
    if caps.points is not None and caps.faces is not None:
        caps.check(sum(counts.values()), "PLY elements", caps.points + caps.faces)


def _ply_elements(lines: list[list[str]], form: str) -> tuple[dict[str, int], dict[str, int]]:
    """Returns each element's declared count and the fewest bytes one of it takes, from the PLY header's
    lines (split into words) for the format ``form``."""
    counts: dict[str, int] = {}
    least: dict[str, int] = {}
    for line in lines:
        if line[:1] == ["element"]:
            if len(line) != 3 or not line[2].isdigit():
                raise ValueError(f"PLY header line {' '.join(line)!r} should be 'element NAME COUNT'")
            counts[line[1]], least[line[1]] = int(line[2]), 0
        elif line[:1] == ["property"] and counts:
            least[next(reversed(counts))] += _ply_property_bytes(line, form)
    return counts, least


def _ply_property_bytes(line: list[str], form: str) -> int:
    """Returns the fewest bytes the PLY ``property`` header line (split into words) takes in the data."""
    if form == "ascii":
        return 2  # a digit and a separator
    # a list counts its length field only: it may be empty
    typ = line[2] if line[1:2] == ["list"] and len(line) > 2 else " ".join(line[1:2])
    size = _PLY_SIZES.get(typ)
    if size is None:
        raise ValueError(f"PLY header line {' '.join(line)!r} has an unknown type")
    return size


def _read_obj(data: bytes, caps: _Caps) -> _Arrays:
    for key, what, limit in ((b"v", "points", caps.points), (b"f", "faces", caps.faces)):
        if limit is not None:  # lines that start with "v " / "f " (C-speed counts, before any parsing)
            n = sum(data.count(b"\n" + key + sep) + data.startswith(key + sep) for sep in (b" ", b"\t"))
            caps.check(n, what, limit)
    loaded = trimesh.load(io.BytesIO(data), file_type="obj", process=False, maintain_order=True)
    if isinstance(loaded, trimesh.Scene):  # several objects: one mesh; none: no points
        geoms = list(loaded.geometry.values())
        loaded = geoms[0] if len(geoms) == 1 else loaded.to_mesh() if geoms else trimesh.Trimesh()
    faces = getattr(loaded, "faces", None)
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))))
    return vertices, None if faces is None or len(faces) == 0 else np.asarray(faces), None


def _read_stl(data: bytes, caps: _Caps) -> _Arrays:
    count = int.from_bytes(data[80:84], "little") if len(data) >= 84 else -1
    if count >= 0 and (84 + 50 * count == len(data) or data[:256].lstrip()[:5].lower() != b"solid"):
        if 84 + 50 * count != len(data):  # binary: 80-byte header, uint32 count, 50 bytes a triangle
            raise ValueError(
                f"it holds no points: its binary header declares {count:,} triangles ({84 + 50 * count:,} "
                f"bytes) but the file has {len(data):,} bytes (truncated, or not an STL file); re-export it"
            )
        caps.check(count, "faces", caps.faces)
    elif caps.faces is not None:  # ascii: three "vertex" lines a triangle
        caps.check(-(-(data.count(b"vertex") + data.count(b"VERTEX")) // 3), "faces", caps.faces)
    d = trimesh.exchange.stl.load_stl(io.BytesIO(data))
    if "vertices" not in d:
        return np.zeros((0, 3)), None, None
    corners = np.asarray(d["vertices"], np.float64)[np.asarray(d["faces"])].reshape(-1, 3)
    unique, first, inverse = np.unique(corners, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep the vertices in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return unique[order], rank[inverse.reshape(-1)].reshape(-1, 3), None


def _read_pcd(data: bytes, caps: _Caps) -> _Arrays:
    points, normals = read_pcd(data, max_points=caps.points, max_bytes=caps.bytes)
    return points, None, normals


def _read_npz(data: bytes, caps: _Caps) -> _Arrays:
    """points or vertices (N, 3) numbers, optional faces (F, 3) integers and normals (N, 3), each checked
    from its header (:func:`bodyfit.io.npz.read_npz`)."""
    keys = npz_keys(data, name="the NPZ")
    key = next((k for k in _POINT_KEYS if k in keys), None)
    if key is None:
        raise ScanError(
            f"the NPZ has keys {sorted(keys)}; a scan needs 'points' or 'vertices' (N, 3), optionally "
            "'faces' (F, 3) and 'normals' (N, 3)"
        )
    N, F = Dim("N", caps.points, "points", THIN), Dim("F", caps.faces, "faces", THIN)
    specs = {
        key: ArraySpec(((N, 3),), NUMBER, hint="positions, metres or millimetres"),
        "faces": ArraySpec(((F, 3), (0,)), INTEGER, required=False, hint="vertex indices of triangles"),
        "normals": ArraySpec(((N, 3),), NUMBER, required=False, hint="one per point"),
    }
    z = read_npz(data, specs, max_bytes=caps.bytes, name="the NPZ")
    return z[key], z.get("faces"), z.get("normals")


_READERS = {"ply": _read_ply, "obj": _read_obj, "stl": _read_stl, "pcd": _read_pcd, "npz": _read_npz}
