"""The bone mesh: attached to the right bodies, rigid with them, scaled with their segments."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.models.errors import ShapeError
from bodyfit.models.skeleton import Skeleton


def _body_vertices(skel: Skeleton, posed: torch.Tensor, body: str) -> torch.Tensor:
    mask = torch.as_tensor(skel.bone_mesh().vertex_body == skel.body_names.index(body))
    return posed[:, mask]


def test_bones_sit_between_their_joints(skeleton: Skeleton) -> None:
    pose = skeleton.forward(np.zeros((1, skeleton.n_dof)))
    bones = skeleton.pose_bones(pose.frames)
    joints = [j.name for j in skeleton.spec.joints]
    hip = pose.joint_centres[0, joints.index("hip_r")]
    knee = pose.joint_centres[0, joints.index("walker_knee_r")]
    femur = _body_vertices(skeleton, bones, "femur_r")[0]
    assert float(femur[:, 1].min()) > float(knee[1]) - 0.05 and float(femur[:, 1].max()) < float(hip[1]) + 0.1
    assert float((femur - knee).norm(dim=-1).min()) < 0.03  # the condyles reach the knee
    assert float((femur - hip).norm(dim=-1).min()) < 0.03  # the femoral head reaches the hip
    skull = _body_vertices(skeleton, bones, "head")[0]
    assert (
        float(skull[:, 1].min()) > float(hip[1]) + 0.4
    )  # the skull sits on the head body, not at the pelvis


def test_bones_move_rigidly_with_their_body(skeleton: Skeleton) -> None:
    q = skeleton.coordinates({"knee_angle_r": np.array([0.0, 1.2]), "neck_rotation": np.array([0.0, 0.7])})
    pose = skeleton.forward(q)
    bones = skeleton.pose_bones(pose.frames)
    for body, moves in (("tibia_r", True), ("femur_r", False), ("head", True), ("torso", False)):
        v = _body_vertices(skeleton, bones, body)
        assert bool((v[0] - v[1]).norm(dim=-1).max() > 0.01) == moves, body
        # Pairwise distances inside one bone do not change: rigid.
        d0, d1 = torch.cdist(v[0, ::25], v[0, ::25]), torch.cdist(v[1, ::25], v[1, ::25])
        assert torch.allclose(d0, d1, atol=1e-5)


def test_bones_scale_with_their_segment(skeleton: Skeleton) -> None:
    scales = np.ones((1, len(skeleton.segments), 3))
    scales[0, skeleton.segments.index("femur_r"), 1] = 1.2
    q = np.zeros((1, skeleton.n_dof))
    base = skeleton.pose_bones(skeleton.forward(q).frames)
    big = skeleton.pose_bones(skeleton.forward(q, scales=scales).frames, scales)
    length = {
        k: float(np.ptp(_body_vertices(skeleton, v, "femur_r")[0, :, 1].numpy()))
        for k, v in (("a", base), ("b", big))
    }
    assert length["b"] / length["a"] == pytest.approx(1.2, rel=1e-3)
    left = [float(np.ptp(_body_vertices(skeleton, v, "femur_l")[0, :, 1].numpy())) for v in (base, big)]
    assert left[0] == pytest.approx(left[1])


def test_bad_frames_are_refused(skeleton: Skeleton) -> None:
    with pytest.raises(ShapeError, match=r"\(B, n_body, 4, 4\)"):
        skeleton.pose_bones(torch.zeros(2, 4, 4))
