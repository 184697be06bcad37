"""The upgrade's summary reports the coordinates that sit at a joint limit in more than a few frames."""

from __future__ import annotations

import numpy as np

from bodyfit.models.upgrade.upgrade import AT_LIMIT_SHARE, _at_limits


def test_coordinates_at_a_limit_are_reported_with_their_share_of_the_frames() -> None:
    ranges = np.radians([[0.0, 150.0], [-10.0, 30.0], [-70.0, 80.0]])
    names = ("elbow_flex_r", "scapula_elevation_r", "wrist_flex_r")
    q = np.zeros((100, 3))
    q[:, 0] = np.radians(60.0)
    q[:, 1] = np.radians(29.5)  # within a degree of its upper limit throughout
    q[:3, 2] = np.radians(-69.9)  # at its lower limit in 3 % of the frames: not reported
    q[:, 0][:20] = np.radians(0.5)  # the elbow straight (its lower limit) in 20 % of them
    notes, held = _at_limits(names, q, ranges)
    assert held == {"scapula_elevation_r": 1.0, "elbow_flex_r": 0.2}
    assert AT_LIMIT_SHARE > 0.03
    assert len(notes) == 1
    assert notes[0].index("scapula_elevation_r 100 %") < notes[0].index("elbow_flex_r 20 %")
    assert _at_limits(names, np.zeros((10, 3)) + np.radians([60.0, 10.0, 0.0]), ranges) == ([], {})
    assert _at_limits(names, np.zeros((0, 3)), ranges) == ([], {})
