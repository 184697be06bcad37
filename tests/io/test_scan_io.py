"""Raw scan loading: every format round trip, unit detection, each error path, and a real Kinect scan."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from bodyfit.io.pcd import lzf_decompress
from bodyfit.io.scans import (
    MIN_POINTS,
    Scan,
    ScanError,
    largest_extent,
    load_scan,
    sample_surface,
    save_scan,
)

KINECT = Path(__file__).resolve().parents[1] / "data" / "scans" / "pcl_template_alignment_person.pcd"


@pytest.fixture(scope="module")
def body() -> trimesh.Trimesh:
    """A 1.7 m tall capsule, +Y up, 1,026 vertices: human-sized and not flat."""
    m = trimesh.creation.capsule(height=1.3, radius=0.2, count=[32, 32])
    v = m.vertices[:, [0, 2, 1]] + [0.0, 0.85, 0.0]
    return trimesh.Trimesh(v, m.faces[:, [0, 2, 1]], process=False)


def write_pcd(points: np.ndarray, data: str, normals: np.ndarray | None = None) -> bytes:
    """A PCL-style PCD: fields x y z [normal_x normal_y normal_z] rgb (packed float), plus a padding field.

    binary_compressed is written with literal-only LZF runs (valid LZF, no back references).
    """
    cols = [points] + ([normals] if normals is not None else [])
    xyz = np.concatenate(cols, axis=1).astype("<f4")
    n, k = xyz.shape
    names = ["x", "y", "z"] + (["normal_x", "normal_y", "normal_z"] if normals is not None else [])
    rec = np.zeros(n, [(f"c{i}", "<f4") for i in range(k)] + [("rgb", "<u4"), ("_", "<u2")])
    for i in range(k):
        rec[f"c{i}"] = xyz[:, i]
    rec["rgb"] = 0x00FF8040
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(names)} rgb _\nSIZE {'4 ' * k}4 2\nTYPE {'F ' * k}U U\nCOUNT {'1 ' * k}1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode()
    if data == "ascii":
        return header + "".join(" ".join(map(repr, row)) + " 4227136 0\n" for row in xyz.tolist()).encode()
    if data == "binary":
        return header + rec.tobytes()
    raw = b"".join(rec[name].tobytes() for name in rec.dtype.names or ())  # field by field
    packed = b"".join(bytes([len(raw[i : i + 32]) - 1]) + raw[i : i + 32] for i in range(0, len(raw), 32))
    return header + np.array([len(packed), len(raw)], "<u4").tobytes() + packed


def export(mesh: trimesh.Trimesh, **kwargs: Any) -> bytes:
    data = mesh.export(**kwargs)
    assert isinstance(data, str | bytes)
    return data.encode() if isinstance(data, str) else data


def assert_same_mesh(scan: Scan, mesh: trimesh.Trimesh, atol: float = 1e-6) -> None:
    np.testing.assert_allclose(scan.points, mesh.vertices, atol=atol)
    assert scan.faces is not None
    np.testing.assert_array_equal(scan.faces, mesh.faces)


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_ply_mesh_round_trip(body: trimesh.Trimesh, tmp_path: Path, encoding: str) -> None:
    path = tmp_path / "body.ply"
    path.write_bytes(export(body, file_type="ply", encoding=encoding))
    scan = load_scan(path)
    assert_same_mesh(scan, body)
    assert scan.source_units == "m" and scan.n_input_points == len(body.vertices)


def test_ply_point_cloud_with_normals_and_save_scan(body: trimesh.Trimesh, tmp_path: Path) -> None:
    cloud = Scan(body.vertices.copy(), None, body.vertex_normals.copy(), "m", len(body.vertices))
    save_scan(tmp_path / "cloud.ply", cloud)
    back = load_scan(tmp_path / "cloud.ply")
    np.testing.assert_array_equal(back.points, cloud.points)  # float64 on disk: exact
    assert back.faces is None and back.normals is not None
    np.testing.assert_array_equal(back.normals, cloud.normals)
    save_scan(tmp_path / "mesh.ply", Scan(body.vertices, body.faces, None, "m", len(body.vertices)))
    mesh = load_scan((tmp_path / "mesh.ply").read_bytes(), format="ply")
    assert_same_mesh(mesh, body, atol=0.0)


def test_obj_round_trip_keeps_vertex_order(body: trimesh.Trimesh, tmp_path: Path) -> None:
    perm = np.random.default_rng(0).permutation(len(body.vertices))
    shuffled = trimesh.Trimesh(body.vertices[perm], np.argsort(perm)[body.faces], process=False)
    (tmp_path / "body.obj").write_bytes(export(shuffled, file_type="obj", include_normals=True))
    assert_same_mesh(load_scan(tmp_path / "body.obj"), shuffled)
    points = "".join(f"v {x} {y} {z}\n" for x, y, z in body.vertices)
    cloud = load_scan(points.encode(), format="OBJ")
    assert cloud.faces is None
    np.testing.assert_allclose(cloud.points, body.vertices, atol=1e-7)


@pytest.mark.parametrize("file_type", ["stl", "stl_ascii"])
def test_stl_round_trip_merges_triangle_soup(body: trimesh.Trimesh, tmp_path: Path, file_type: str) -> None:
    (tmp_path / "body.stl").write_bytes(export(body, file_type=file_type))
    scan = load_scan(tmp_path / "body.stl")
    assert scan.n_points == len(body.vertices)  # 3 corners per face in the file, shared again here
    assert scan.faces is not None and scan.faces.shape == body.faces.shape
    np.testing.assert_allclose(scan.points[scan.faces], body.vertices[body.faces], atol=1e-6)


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_pcd_round_trip(body: trimesh.Trimesh, tmp_path: Path, data: str) -> None:
    (tmp_path / "cloud.pcd").write_bytes(write_pcd(body.vertices, data, body.vertex_normals))
    scan = load_scan(tmp_path / "cloud.pcd")
    np.testing.assert_allclose(scan.points, body.vertices, atol=1e-6)
    assert scan.normals is not None and scan.faces is None
    np.testing.assert_allclose(scan.normals, body.vertex_normals, atol=1e-6)
    plain = load_scan(write_pcd(body.vertices, data), format="pcd")
    assert plain.normals is None and plain.n_points == len(body.vertices)


def test_lzf_back_reference_may_overlap() -> None:
    # literal "ab", then copy 5 bytes from 2 back (overlapping): "ab" + "ababa"
    assert lzf_decompress(b"\x01ab" + bytes([(5 - 2) << 5, 1]), 7) == b"abababa"


def test_npz_round_trip_and_keys(body: trimesh.Trimesh, tmp_path: Path) -> None:
    scan = Scan(body.vertices, body.faces.astype(np.int64), body.vertex_normals, "m", len(body.vertices))
    save_scan(tmp_path / "body.npz", scan)
    back = load_scan(tmp_path / "body.npz")
    assert_same_mesh(back, body, atol=0.0)
    assert back.normals is not None
    np.testing.assert_array_equal(back.normals, scan.normals)
    np.savez(tmp_path / "v.npz", vertices=body.vertices)
    assert load_scan(tmp_path / "v.npz").faces is None


def test_millimetres_are_detected(body: trimesh.Trimesh, tmp_path: Path) -> None:
    np.savez(tmp_path / "mm.npz", points=body.vertices * 1000.0, faces=body.faces)
    mm = load_scan(tmp_path / "mm.npz")
    assert mm.source_units == "mm"
    np.testing.assert_allclose(mm.points, body.vertices, atol=1e-12)
    upper = body.vertices[body.vertices[:, 1] > 1.5]  # the top cap: a 0.4 m head-and-shoulders-sized part
    assert 0.38 < largest_extent(upper) < 0.4
    assert load_scan(_npz(tmp_path, upper * 1000.0)).source_units == "mm"
    assert load_scan(_npz(tmp_path, upper)).source_units == "m"
    forced = load_scan(_npz(tmp_path, body.vertices * 1000.0), units="mm")
    np.testing.assert_allclose(forced.points, body.vertices, atol=1e-12)


def _npz(tmp_path: Path, points: np.ndarray) -> Path:
    path = tmp_path / "p.npz"
    np.savez(path, points=points)
    return path


@pytest.mark.parametrize("extent", [0.05, 50.0, 5.1])  # a 5 cm object, cm (or a small mm scan), a room
def test_implausible_size_says_extent_and_fix(body: trimesh.Trimesh, tmp_path: Path, extent: float) -> None:
    path = _npz(tmp_path, body.vertices * extent / largest_extent(body.vertices))
    with pytest.raises(ScanError, match=r"largest extent is .*units='m'"):
        load_scan(path)
    assert load_scan(path, units="m").n_points == len(body.vertices)  # forcing the unit skips the check


def test_sample_surface_is_area_uniform_and_seeded() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 0, 1], [0, 2, 1]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 3
    p, n = sample_surface(v, f, 20_000, seed=3)
    on_second = p[:, 2] > 0.5
    assert abs(on_second.mean() - 3 / 3.5) < 0.01
    np.testing.assert_allclose(n[on_second], np.tile([0, 0, 1.0], (on_second.sum(), 1)))
    assert (p[~on_second].sum(axis=1) <= 1 + 1e-12).all()
    assert (p[on_second, 0] / 3 + p[on_second, 1] / 2 <= 1 + 1e-12).all()
    np.testing.assert_array_equal(p, sample_surface(v, f, 20_000, seed=3)[0])


# --- errors: the type and a message that names the problem --------------------------------------------


def _raises(match: str, *args: object, **kwargs: object) -> None:
    with pytest.raises(ScanError, match=match):
        load_scan(*args, **kwargs)  # type: ignore[arg-type]


def test_empty_garbage_missing_and_unknown(tmp_path: Path) -> None:
    (tmp_path / "empty.ply").write_bytes(b"")
    _raises("is empty", tmp_path / "empty.ply")
    garbage = np.random.default_rng(0).bytes(4000)
    _raises("could not read .* as PLY", garbage, format="ply")
    _raises("holds no points", garbage, format="stl")
    _raises("could not read .* as PCD: not a PCD file", garbage, format="pcd")
    _raises("could not read .* as NPZ", garbage, format="npz")
    _raises("cannot read", tmp_path / "missing.ply")
    _raises(r"unknown scan format 'xyz'.*supported: ply, obj, stl, pcd, npz", tmp_path / "body.xyz")
    _raises("format= is required", b"ply")
    _raises("unknown scan format 'las'", b"ply", format="las")


def test_nan_points_counted_or_dropped(body: trimesh.Trimesh, tmp_path: Path) -> None:
    v = body.vertices.copy()
    v[[3, 10, 500]] = np.nan
    v[7, 1] = np.inf
    np.savez(tmp_path / "nan.npz", points=v, faces=body.faces)
    _raises(r"4 of 1,026 points are NaN or infinite.*drop_nonfinite=True", tmp_path / "nan.npz")
    scan = load_scan(tmp_path / "nan.npz", drop_nonfinite=True)
    assert scan.n_points == len(v) - 4 and scan.n_input_points == len(v)
    used = np.isin(body.faces, [3, 7, 10, 500]).any(axis=1)
    assert scan.faces is not None and len(scan.faces) == (~used).sum()
    np.testing.assert_array_equal(scan.points[scan.faces], body.vertices[body.faces[~used]])


def test_too_few_and_degenerate_points(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    _raises(f"10 points; at least {MIN_POINTS}", _npz(tmp_path, rng.uniform(0, 1.7, (10, 3))))
    line = np.linspace(0, 1.7, 1000)[:, None] * np.array([[0.2, 1.0, 0.1]])
    _raises("line", _npz(tmp_path, line))
    tilted = trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 3.0])[:3, :3]
    plane = np.c_[rng.uniform(0, 1.7, (1000, 2)), np.zeros(1000)] @ tilted.T
    _raises("plane", _npz(tmp_path, plane))
    _raises("lie on one point", _npz(tmp_path, np.ones((400, 3))))


def test_bad_npz_keys_faces_and_pcd(body: trimesh.Trimesh, tmp_path: Path) -> None:
    np.savez(tmp_path / "k.npz", verts=body.vertices, tris=body.faces)
    _raises(r"keys \['tris', 'verts'\]; a scan needs 'points' or 'vertices'", tmp_path / "k.npz")
    np.savez(tmp_path / "f.npz", points=body.vertices, faces=body.faces + 5000)
    _raises("faces index vertices .* but the scan has 1026 points", tmp_path / "f.npz")
    compressed = write_pcd(body.vertices, "binary_compressed")
    _raises("binary_compressed .* corrupt: re-save it as binary or ascii", compressed[:-100], format="pcd")
    corrupt = bytearray(compressed)
    corrupt[compressed.index(b"binary_compressed\n") + 18 + 8] = 0xFF  # a back reference before the start
    _raises("corrupt LZF data .* re-save it as binary or ascii", bytes(corrupt), format="pcd")
    no_xyz = write_pcd(body.vertices, "ascii").replace(b"FIELDS x y z", b"FIELDS a b c")
    _raises("no x y z", no_xyz, format="pcd")
    _raises("units must be", _npz(tmp_path, body.vertices), units="cm")


# --- a real capture ---------------------------------------------------------------------------------------


def test_real_kinect_scan() -> None:
    """PCL's template-alignment tutorial cloud (tests/data/scans/SOURCES.md): a Kinect capture of one
    person's head and shoulders (a partial upper-body scan, about 0.6-0.8 m from the sensor) with the room
    behind, as an organized 640 x 480 cloud in metres, binary_compressed, NaN where there was no return."""
    with pytest.raises(ScanError, match="64,451 of 307,200 points are NaN"):
        load_scan(KINECT)
    scan = load_scan(KINECT, drop_nonfinite=True)
    assert scan.n_input_points == 640 * 480 and scan.n_points == 242_749
    assert scan.source_units == "m" and scan.faces is None and scan.normals is None
    assert 2.9 < largest_extent(scan.points) < 3.0  # the background spans ~3 m; the person far less
    assert 0.60 < scan.points[:, 2].min() < 0.61 and scan.points[:, 2].max() < 3.8  # depth along +Z
    person = scan.points[scan.points[:, 2] < 1.0]
    assert 0.3 < largest_extent(person) < 1.5
