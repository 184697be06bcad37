"""BVH reading: hierarchy, channels, frames, units and axes, forward kinematics, and malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bodyfit.io.bvh import CMU_UNITS, parse_bvh, read_bvh
from bodyfit.io.mocap import MocapFormatError

CLIP = Path(__file__).resolve().parents[1] / "data" / "cmu_bvh" / "cmu_131_01_clip.bvh"

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Knee
  {
    OFFSET 0 -10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -10 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.01
1 2 3 0 0 0 0 0 0
1 2 3 0 90 0 90 0 0
"""


def test_cmu_clip_header_and_units() -> None:
    m = read_bvh(CLIP, CMU_UNITS)
    assert m.n_frames == 240 and abs(m.rate - 120.0) < 0.01
    assert len(m.joints) == 31 and m.joints[0].name == "Hips" and m.joints[0].parent == -1
    assert m.values.shape == (240, sum(len(j.channels) for j in m.joints))
    p, R, names = m.world(end_sites=True)
    i = names.index
    # Bone lengths of an adult, in metres.
    for side in ("Left", "Right"):
        thigh = np.linalg.norm(p[:, i(f"{side}Hip")] - p[:, i(f"{side}Knee")], axis=-1)
        shank = np.linalg.norm(p[:, i(f"{side}Knee")] - p[:, i(f"{side}Ankle")], axis=-1)
        np.testing.assert_allclose(thigh, thigh[0], atol=1e-9)  # rigid bones
        assert 0.35 < thigh[0] < 0.5 and 0.33 < shank[0] < 0.48
    # Our axes: Y up (head above hips above feet), the left side at -Z, walking forward along +X.
    assert (p[:, i("Head_end"), 1] > p[:, 0, 1]).all() and (p[:, 0, 1] > p[:, i("LeftToe_end"), 1]).all()
    assert (p[:, i("LeftHip"), 2] < p[:, i("RightHip"), 2]).mean() > 0.9
    assert p[-1, 0, 0] - p[0, 0, 0] > 0.5
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    # The root's position channels, mapped (file X left, Z forward -> ours Z right, X forward).
    x, y, z = m.values[0, :3] * CMU_UNITS
    np.testing.assert_allclose(p[0, 0], [z, y, -x], atol=1e-12)


def test_channel_order_and_forward_kinematics() -> None:
    m = parse_bvh(SMALL, units=0.1, rotation=np.eye(3))
    assert m.names == ["Hips", "Knee"] and m.joints[1].channels == ("Zrotation", "Xrotation", "Yrotation")
    p, R, names = m.world(end_sites=True)
    assert names == ["Hips", "Knee", "Knee_end"]
    np.testing.assert_allclose(p[0], [[0.1, 0.2, 0.3], [0.1, -0.8, 0.3], [0.1, -1.8, 0.3]], atol=1e-12)
    # Frame 1: root turned 90 degrees about Y (no effect on a vertical bone), knee 90 degrees about Z.
    np.testing.assert_allclose(p[1, 1], [0.1, -0.8, 0.3], atol=1e-12)
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    np.testing.assert_allclose(R[1, 1], Ry @ Rz, atol=1e-12)
    np.testing.assert_allclose(p[1, 2], p[1, 1] + Ry @ Rz @ np.array([0.0, -1.0, 0.0]), atol=1e-12)
    # Default axes: file Y up, facing +Z -> ours.
    p_default, _, _ = parse_bvh(SMALL, units=0.1).world()
    np.testing.assert_allclose(p_default[0, 0], [0.3, 0.2, -0.1], atol=1e-12)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda s: s.replace("MOTION", "MOTON"), "no MOTION section"),
        (lambda s: s.replace("HIERARCHY", "HIERARCHIE"), "expected 'HIERARCHY'"),
        (lambda s: s.replace("Xrotation\n", "Wrotation\n"), "unknown channel 'Wrotation'"),
        (lambda s: s.replace("CHANNELS 3", "CHANNELS 7"), "channel count must be 0 to 6"),
        (
            lambda s: s.replace("OFFSET 0 -10 0\n    CHANNELS", "OFFSET 0 x 0\n    CHANNELS"),
            "expected a number",
        ),
        (lambda s: s.replace("Frames: 2", "Frames: 3"), "header says 3 frames but 2 follow"),
        (lambda s: s.replace("Frame Time: 0.01", "Frame Time: 0"), "frame time must be positive"),
        (lambda s: s.replace("1 2 3 0 90", "1 2 3 0"), "line 20: 8 values, the hierarchy has 9 channels"),
        (lambda s: s.replace("1 2 3 0 90", "1 2 nan 0 90"), "values must be finite"),
        (lambda s: s.replace("1 2 3 0 90", "1 2 a 0 90"), "not a number"),
        (lambda s: s.replace("Knee", "Hips"), "repeated: Hips"),
        (
            lambda s: s.replace("      OFFSET 0 -10 0\n    }\n  }\n}", "      OFFSET 0 -10 0\n    }\n  }\n"),
            "ends",
        ),
    ],
)
def test_malformed_files_raise(edit: object, words: str) -> None:
    text = edit(SMALL)  # type: ignore[operator]
    with pytest.raises(MocapFormatError, match=words.replace("(", r"\(").replace(")", r"\)")):
        parse_bvh(text, source="small.bvh")


def test_bad_arguments_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MocapFormatError, match="units"):
        parse_bvh(SMALL, units=-1.0)
    with pytest.raises(MocapFormatError, match="proper 3x3 rotation"):
        parse_bvh(SMALL, rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(MocapFormatError, match="cannot read"):
        read_bvh(tmp_path / "missing.bvh")
    m = parse_bvh(SMALL)
    with pytest.raises(MocapFormatError, match="no joint 'Elbow'; joints: Hips, Knee"):
        m.index("Elbow")


def test_position_channels_replace_the_offset() -> None:
    """A joint with position channels sits where the channels put it, whatever its OFFSET (the rest
    value): LAFAN1-style exports repeat the root's first-frame position as its OFFSET, and a non-root joint
    with six channels (Blender-style) carries its rest offset in both."""
    text = SMALL.replace("  OFFSET 0 0 0\n  CHANNELS 6", "  OFFSET 1 2 3\n  CHANNELS 6").replace(
        "    OFFSET 0 -10 0\n    CHANNELS 3 Zrotation Xrotation Yrotation",
        "    OFFSET 0 -10 0\n    CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
    )
    text = text.replace("1 2 3 0 0 0 0 0 0\n", "1 2 3 0 0 0 0 -10 0 0 0 0\n").replace(
        "1 2 3 0 90 0 90 0 0\n", "5 2 3 0 0 0 0 -8 0 0 0 0\n"
    )
    p, _, names = parse_bvh(text, rotation=np.eye(3)).world(end_sites=True)
    np.testing.assert_allclose(p[:, names.index("Hips")], [[1, 2, 3], [5, 2, 3]])
    np.testing.assert_allclose(p[:, names.index("Knee")], [[1, -8, 3], [5, -6, 3]])
    np.testing.assert_allclose(p[:, names.index("Knee_end")], [[1, -18, 3], [5, -16, 3]])
