"""Marker trajectory files: TRC and C3D readers, units, frames, missing samples and every error path."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from bodyfit.io.c3d import _dec_to_ieee
from bodyfit.io.mocap import (
    MarkerTrial,
    MocapFormatError,
    lab_rotation,
    parse_c3d,
    parse_trc,
    read_c3d,
    read_markers,
    read_trc,
    write_trc,
)

DATA = Path(__file__).resolve().parents[1] / "data"
GAIT = DATA / "opensim_gait"


def test_trc_values_units_and_times() -> None:
    trial = read_trc(GAIT / "gait2392_subject01_walk1.trc")
    assert trial.positions.shape == (151, 41, 3) and trial.rate == 60.0
    assert trial.names[:3] == ("R.ASIS", "L.ASIS", "V.Sacral") and trial.names[-1] == "Top.Head"
    np.testing.assert_allclose(trial.marker("R.ASIS")[0], [0.61724762, 1.05527502, 0.17078198])
    np.testing.assert_allclose(trial.times[:3], [0.0, 1 / 60, 2 / 60])  # the file rounds to 0.017
    assert not np.isnan(trial.positions).any()
    assert trial.between(0.5, 1.0).n_frames == 31


def _trc_text(units: str = "mm", rows: list[str] | None = None, header: str | None = None) -> str:
    rows = rows or ["1\t0.0\t1000\t2000\t3000\t\t\t", "2\t0.01\t0\t0\t0\t4\t5\t6"]
    return "\n".join(
        [
            "PathFileType\t4\t(X/Y/Z)\tx.trc",
            header or "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits",
            f"100\t100\t{len(rows)}\t2\t{units}",
            "Frame#\tTime\tA\t\t\tB\t\t",
            "\t\tX1\tY1\tZ1\tX2\tY2\tZ2",
            "",
            *rows,
        ]
    )


def test_trc_missing_cells_zeros_and_metres() -> None:
    trial = parse_trc(_trc_text("mm"))
    np.testing.assert_allclose(trial.marker("A")[0], [1.0, 2.0, 3.0])
    assert np.isnan(trial.marker("B")[0]).all()  # empty cells
    assert np.isnan(trial.marker("A")[1]).all()  # 0 0 0 = gap
    assert not np.isnan(parse_trc(_trc_text(), zeros_missing=False).marker("A")[1]).any()
    np.testing.assert_allclose(parse_trc(_trc_text("m")).marker("B")[1], [4.0, 5.0, 6.0])


def test_lab_rotation_maps_z_up_to_y_up() -> None:
    R = lab_rotation(up="z", forward="x")
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 1, 0])  # lab up -> our +Y
    np.testing.assert_allclose(R @ [1, 0, 0], [1, 0, 0])
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    trial = parse_trc(_trc_text("m"), rotation=R)
    np.testing.assert_allclose(trial.marker("B")[1], R @ [4.0, 5.0, 6.0])
    with pytest.raises(MocapFormatError, match="different axes"):
        lab_rotation(up="x", forward="x")


def test_c3d_real_file() -> None:
    trial = read_markers(DATA / "c3d" / "pyomeca_markers_analogs_20frames.c3d")
    assert trial.positions.shape == (20, 51, 3) and trial.rate == 100.0
    assert trial.names[8] == "Daphnee:ASISr"
    np.testing.assert_allclose(trial.positions[0, 0], [0.04416279, -0.27686194, 0.67569684], atol=1e-7)
    np.testing.assert_allclose(trial.times[-1], 0.19)


def _c3d_bytes(points: np.ndarray, residual: np.ndarray, scale: float, labels: list[str]) -> bytes:
    """A minimal Intel C3D: header block, one parameter block (POINT group), point data (no analogs)."""
    T, M, _ = points.shape
    header = bytearray(512)
    header[0], header[1] = 2, 0x50
    struct.pack_into("<hhhhh", header, 2, M, 0, 1, T, 0)
    struct.pack_into("<f", header, 12, scale)
    struct.pack_into("<hh", header, 16, 3, 0)
    struct.pack_into("<f", header, 20, 50.0)
    params = bytearray([1, 0x50, 1, 84])
    group = b"POINT"
    params += struct.pack("<bb", len(group), -1) + group + struct.pack("<h", 3) + b"\x00"
    width = max(len(n) for n in labels)
    text = b"".join(n.ljust(width).encode() for n in labels)
    entries = [
        (b"USED", struct.pack("<bB", 2, 0) + struct.pack("<h", M)),
        (b"SCALE", struct.pack("<bB", 4, 0) + struct.pack("<f", scale)),
        (b"UNITS", struct.pack("<bBB", -1, 1, 2) + b"mm"),
        (b"LABELS", struct.pack("<bBBB", -1, 2, width, M) + text),
    ]
    for k, (name, body) in enumerate(entries):
        nxt = 2 + len(body) + 1 if k < len(entries) - 1 else 0
        params += struct.pack("<bb", len(name), 1) + name + struct.pack("<h", nxt) + body + b"\x00"
    params = params.ljust(512, b"\x00")
    values = np.concatenate([points, residual[..., None]], axis=-1)
    data = values.astype("<f4").tobytes() if scale < 0 else np.round(values).astype("<i2").tobytes()
    return bytes(header) + bytes(params) + data


def test_c3d_integer_and_float_formats() -> None:
    pts = np.array([[[100.0, 200.0, 300.0], [10.0, 20.0, 30.0]]] * 3)
    res = np.array([[0.0, 0.0], [0.0, -1.0], [0.0, 0.0]])
    as_int = parse_c3d(_c3d_bytes(pts / 0.5, res, 0.5, ["A", "B"]))  # integers times POINT:SCALE
    np.testing.assert_allclose(as_int.marker("A")[0], [0.1, 0.2, 0.3])
    assert np.isnan(as_int.marker("B")[1]).all() and not np.isnan(as_int.marker("B")[2]).any()
    as_float = parse_c3d(_c3d_bytes(pts, res, -1.0, ["A", "B"]))
    np.testing.assert_allclose(as_float.positions, as_int.positions, equal_nan=True)
    assert as_float.rate == 50.0
    # DEC (VAX F) floats: 1.0 is stored as the words 0x4080, 0x0000.
    np.testing.assert_allclose(_dec_to_ieee(np.array([0x00004080], dtype="<u4")), [1.0])


def test_write_trc_round_trip(tmp_path: Path) -> None:
    trial = read_trc(GAIT / "gait2392_subject01_walk1.trc").frames(slice(0, 10))
    back = read_trc(write_trc(tmp_path / "x.trc", trial))
    np.testing.assert_allclose(back.positions, trial.positions, atol=1e-9)
    assert back.names == trial.names and back.rate == trial.rate


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("garbage\x00\x01 not a trc", "not a TRC file"),
        (_trc_text(header="Foo\tBar"), "lacks 'DataRate'"),
        (_trc_text("furlongs"), "unknown Units"),
        (_trc_text(rows=["1\t0.0\t1\t2\tx\t4\t5\t6"]), "not a number"),
        (_trc_text(rows=["1\t0.0\t1\t2\t3\t4\t5\t6\t7\t8\t9"]), "columns"),
        (_trc_text(rows=[""]), "no frames"),
    ],
)
def test_trc_errors(text: str, match: str) -> None:
    with pytest.raises(MocapFormatError, match=match):
        parse_trc(text)


def test_file_errors(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.c3d"
    garbage.write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(MocapFormatError, match="not a C3D file"):
        read_c3d(garbage)
    real = (DATA / "c3d" / "pyomeca_markers_analogs_20frames.c3d").read_bytes()
    with pytest.raises(MocapFormatError, match="truncated"):
        parse_c3d(real[:20000])
    with pytest.raises(MocapFormatError, match=r"\.trc or \.c3d"):
        read_markers(tmp_path / "x.bvh")
    with pytest.raises(MocapFormatError, match="cannot read"):
        read_trc(tmp_path / "missing.trc")
    with pytest.raises(MocapFormatError, match="unique"):
        MarkerTrial(("A", "A"), np.zeros((1, 2, 3)), 100.0, np.zeros(1))
