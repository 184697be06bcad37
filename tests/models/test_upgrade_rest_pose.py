"""Path (b)'s proxy turned into SMPL's rest pose: the segment rotations read off a posed body."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodyfit.models.upgrade.proxy import load_proxy, shoulder_pivots
from bodyfit.models.upgrade.rest_pose import rest_alignment, segment_alignment, swing
from bodyfit.models.upgrade.smpl_joints import SMPL_JOINTS


@pytest.fixture(scope="module")
def proxy():
    return load_proxy().model


def _posed(proxy, turns: dict[str, np.ndarray]) -> np.ndarray:
    poses = np.zeros((1, 24, 3))
    for name, rotvec in turns.items():
        poses[0, SMPL_JOINTS.index(name)] = rotvec
    return proxy.forward(poses)[0][0].astype(np.float64)


def test_knees_bent_in_the_target_are_read_back_as_the_rest_pose(proxy) -> None:
    """Knees flexed 12 degrees and ankles turned 15 (symmetrically) in the target body: the alignment gives
    those local rotations, and leaves joints that did not move near identity."""
    knee, ankle = np.radians([12.0, 0, 0]), np.radians([-15.0, 0, 0])
    target = _posed(proxy, {"left_knee": knee, "right_knee": knee, "left_ankle": ankle, "right_ankle": ankle})
    rest = proxy.v_template.astype(np.float64)
    joints = np.asarray(proxy.J_regressor @ rest)
    local = rest_alignment(segment_alignment(rest, target[None], proxy.weights, joints))
    degrees = Rotation.from_matrix(local).as_rotvec(degrees=True)
    for side in ("left", "right"):
        np.testing.assert_allclose(degrees[SMPL_JOINTS.index(f"{side}_knee")], [12.0, 0, 0], atol=1.5)
        np.testing.assert_allclose(degrees[SMPL_JOINTS.index(f"{side}_ankle")], [-15.0, 0, 0], atol=2.0)
    still = [j for j, n in enumerate(SMPL_JOINTS) if "knee" not in n and "ankle" not in n]
    assert np.linalg.norm(degrees[still], axis=1).max() < 1.5


def test_the_rest_pose_is_made_symmetric(proxy) -> None:
    """Only the left elbow bent in the target: the alignment splits it between the two sides, mirrored."""
    target = _posed(proxy, {"left_elbow": np.radians([0, 20.0, 0])})
    rest = proxy.v_template.astype(np.float64)
    local = rest_alignment(segment_alignment(rest, target[None], proxy.weights, proxy.J_regressor @ rest))
    left = Rotation.from_matrix(local[SMPL_JOINTS.index("left_elbow")]).as_rotvec(degrees=True)
    right = Rotation.from_matrix(local[SMPL_JOINTS.index("right_elbow")]).as_rotvec(degrees=True)
    np.testing.assert_allclose(left, [0, 10.0, 0], atol=1.5)
    np.testing.assert_allclose(right, [0, -10.0, 0], atol=1.5)


def test_swing_drops_the_twist_about_the_axis() -> None:
    axis = np.array([1.0, 0, 0])
    R = Rotation.from_rotvec([0.5, 0, 0]) * Rotation.from_rotvec([0, 0, 0.3])  # a twist after a swing
    s = swing(R, axis)
    np.testing.assert_allclose(s.apply(axis), R.apply(axis), atol=1e-12)
    assert abs(s.as_rotvec() @ axis) < 1e-12  # no component about the axis itself


def test_the_shoulder_joints_move_a_quarter_down_the_arm_bone() -> None:
    """SMPL's shoulder joint is the glenohumeral centre, a quarter of the way down SOMA's arm bone; every
    other joint stays at its SOMA bone head."""
    labels = ["Hips", "LeftArm", "LeftForeArm", "RightArm", "RightForeArm"]
    heads = np.zeros((2, len(labels), 3))
    heads[:, 1], heads[:, 2] = [0.16, 0.40, 0.0], [0.42, 0.40, 0.0]
    heads[:, 3], heads[:, 4] = [-0.16, 0.40, 0.0], [-0.42, 0.40, 0.0]
    joints = np.random.default_rng(0).normal(size=(2, len(SMPL_JOINTS), 3))
    out = shoulder_pivots(heads, labels, joints)
    np.testing.assert_allclose(out[:, SMPL_JOINTS.index("left_shoulder")], [[0.225, 0.40, 0.0]] * 2)
    np.testing.assert_allclose(out[:, SMPL_JOINTS.index("right_shoulder")], [[-0.225, 0.40, 0.0]] * 2)
    others = [j for j, n in enumerate(SMPL_JOINTS) if not n.endswith("_shoulder")]
    np.testing.assert_array_equal(out[:, others], joints[:, others])


def test_the_proxy_turns_its_arms_about_the_shoulder_joint(proxy) -> None:
    """The stored proxy's shoulder joint lies in its upper arm, about halfway from the collar to the elbow
    (221 mm out on the mean body): an arm brought down from the rest pose turns about the glenohumeral
    centre instead of sinking into the chest."""
    rest = proxy.v_template.astype(np.float64)
    J = np.asarray(proxy.J_regressor @ rest)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        shoulder, elbow = J[SMPL_JOINTS.index(f"{side}_shoulder")], J[SMPL_JOINTS.index(f"{side}_elbow")]
        collar = J[SMPL_JOINTS.index(f"{side}_collar")]
        along = (shoulder[0] - collar[0]) / (elbow[0] - collar[0])
        assert 0.45 < along < 0.6, (side, along)  # at SOMA's arm head: 0.36 of the way, 155 mm out
        assert sign * shoulder[0] > 0.2, (side, shoulder)
