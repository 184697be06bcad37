"""The SMPL-format test data's poses: the elbows carry the forearm's twist about its own axis."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.smpl_testdata import forearm_twist


def _frames(rotvecs: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(rotvecs).as_matrix()


def _radius(ulna_rest: np.ndarray, radius_rest: np.ndarray, ulna: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Radius orientations (T, 3, 3) turned by ``turn`` (3, 3), in the ulna's frame, from the rest."""
    return ulna @ turn @ ulna_rest.T @ radius_rest


def test_the_twist_about_the_forearm_is_kept_and_the_swing_dropped() -> None:
    """The radius turned against the ulna by 30 degrees about the forearm's axis, then swung 20 degrees about
    a perpendicular one: the elbow carries the 30 about the axis only, whatever the ulna's own orientation
    and the rest relation of the two bones."""
    a = np.array([0.0, -1.0, 0.2]) / np.hypot(1.0, 0.2)
    side = np.cross(a, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    ulna_rest = _frames(np.array([0.1, 0.4, -0.2]))
    radius_rest = ulna_rest @ _frames(np.array([0.0, 0.0, 0.3]))
    ulna = _frames(np.array([[0.5, -0.2, 0.1], [0.0, 0.0, 0.0]]))
    twist, swing = _frames(np.radians(30.0) * a), _frames(np.radians(20.0) * side)
    for turn in (twist, swing @ twist):
        out = forearm_twist(ulna_rest, radius_rest, ulna, _radius(ulna_rest, radius_rest, ulna, turn), a)
        degrees = Rotation.from_matrix(out).as_rotvec(degrees=True)
        np.testing.assert_allclose(degrees, [30.0 * a] * 2, atol=1e-9)
    # a swing alone leaves the forearm untwisted
    out = forearm_twist(ulna_rest, radius_rest, ulna, _radius(ulna_rest, radius_rest, ulna, swing), a)
    np.testing.assert_allclose(out, np.repeat(np.eye(3)[None], 2, axis=0), atol=1e-9)


def test_no_turn_gives_no_twist() -> None:
    ulna_rest = _frames(np.array([0.3, 0.1, 0.0]))
    radius_rest = ulna_rest @ _frames(np.array([0.0, 0.2, 0.0]))
    ulna = _frames(np.array([[0.2, 0.2, 0.2]]))
    radius = _radius(ulna_rest, radius_rest, ulna, np.eye(3))
    twist = forearm_twist(ulna_rest, radius_rest, ulna, radius, np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(twist[0], np.eye(3), atol=1e-12)
