"""Forward kinematics: gradients, ONNX parity, symmetry, the added joints' geometry, dtypes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.models.skeleton import Skeleton
from bodyfit.models.skeleton.build import (
    CERVICAL_LENGTH,
    SCAPULA_CONTACT_R,
    THORACIC_LENGTH,
    THORAX_AXIS,
    THORAX_VERTICAL_RADIUS,
)
from bodyfit.models.skeleton.model import LATERAL_DOFS
from tests.conftest import random_pose

LATERAL = LATERAL_DOFS


def test_gradcheck_float64(skeleton: Skeleton) -> None:
    fk = skeleton.kinematics(torch.float64)
    q = torch.tensor(random_pose(skeleton, 2, seed=1) * 0.9, requires_grad=True)
    root = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    scales = (1 + 0.1 * torch.rand(2, len(skeleton.segments), 3, dtype=torch.float64)).requires_grad_()

    def f(q: torch.Tensor, root: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        pose = fk(q, root, scales)
        return torch.cat([pose.frames.flatten(1), pose.joint_centres.flatten(1)], 1)

    assert torch.autograd.gradcheck(f, (q, root, scales), eps=1e-6, atol=1e-6)


def test_gradient_is_finite_at_zero_pose(skeleton: Skeleton) -> None:
    """The arc functions divide by the bend angle; at exactly zero their gradient must stay finite."""
    fk = skeleton.kinematics(torch.float64)
    q = torch.zeros(1, skeleton.n_dof, dtype=torch.float64, requires_grad=True)
    fk(q).joint_centres.sum().backward()
    assert q.grad is not None and torch.isfinite(q.grad).all()


def test_float32_matches_float64(skeleton: Skeleton) -> None:
    q = random_pose(skeleton, 500, seed=2)
    a = skeleton.kinematics(torch.float32)(torch.tensor(q, dtype=torch.float32))
    b = skeleton.kinematics(torch.float64)(torch.tensor(q))
    assert a.frames.dtype == torch.float32
    assert float((a.frames.double() - b.frames).abs().max()) < 2e-6


def test_any_batch_size(skeleton: Skeleton) -> None:
    fk = skeleton.kinematics(torch.float64)
    q = torch.tensor(random_pose(skeleton, 5, seed=3))
    full = fk(q).frames
    for i in range(5):
        assert torch.allclose(fk(q[i : i + 1]).frames[0], full[i], atol=1e-14)
    assert fk(q[:0]).frames.shape == (0, len(skeleton.body_names), 4, 4)


def test_left_right_mirror_symmetry(skeleton: Skeleton) -> None:
    """Mirrored coordinates give the mirror image (z -> -z) of every body. Measured: positions agree
    exactly, orientations to 1e-5 rad (Rajagopal2015 writes pi/2 as 1.5708 in some frame offsets)."""
    fk = skeleton.kinematics(torch.float64)
    q = random_pose(skeleton, 200, seed=4)
    q[:, [skeleton.dof_index(n) for n in LATERAL]] *= 0.5
    a = fk(torch.tensor(q)).frames
    b = fk(torch.tensor(skeleton.mirror_coordinates(q))).frames
    M = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    twin = skeleton.twin_bodies()
    mirrored = M @ b[:, twin] @ M
    assert float((a[..., :3, 3] - mirrored[..., :3, 3]).norm(dim=-1).max()) < 1e-9
    assert float((a[..., :3, :3] - mirrored[..., :3, :3]).abs().max()) < 1e-4


def _centre(skel: Skeleton, pose: torch.Tensor, joint: str) -> torch.Tensor:
    return pose[:, [j.name for j in skel.spec.joints].index(joint)]


@pytest.mark.parametrize("dof", ["thorax_extension", "thorax_bending", "neck_extension", "neck_bending"])
def test_spine_segment_keeps_its_arc_length(skeleton: Skeleton, dof: str) -> None:
    """Pure extension or bending: the segment's tip lies on a circular arc of length L from its base,
    so the chord is 2 L sin(theta / 2) / theta."""
    L = THORACIC_LENGTH if dof.startswith("thorax") else CERVICAL_LENGTH
    base, tip = (
        ("thorax_extension", "neck_extension") if dof.startswith("thorax") else ("neck_extension", None)
    )
    lo, hi = skeleton.ranges[skeleton.dof_index(dof)]
    theta = np.linspace(lo, hi, 9)
    q = skeleton.coordinates({dof: theta})
    pose = skeleton.forward(torch.tensor(q))
    rest = skeleton.forward(torch.zeros(1, skeleton.n_dof, dtype=torch.float64))
    base_pt = _centre(skeleton, rest.joint_centres, base)  # the base is fixed on the parent body
    if tip is None:  # the cervical tip is the head frame's point L above its base
        head = skeleton.body_names.index("head")
        tip_pt = (pose.frames[:, head] @ torch.tensor([0.0, L, 0.0, 1.0], dtype=torch.float64))[:, :3]
    else:
        tip_pt = _centre(skeleton, pose.joint_centres, tip)
    th = torch.as_tensor(theta)
    chord = torch.where(th.abs() < 1e-9, torch.full_like(th, L), 2 * L * torch.sin(th / 2) / th)
    assert torch.allclose((tip_pt - base_pt).norm(dim=-1), chord, atol=1e-9)


def test_scapula_slides_on_thoracic_ellipsoid(skeleton: Skeleton) -> None:
    rng = np.random.default_rng(9)
    n = 200
    values: dict[str, np.ndarray] = {}
    for k in ("abduction", "elevation", "upward_rot"):
        for side in "rl":
            lo, hi = skeleton.ranges[skeleton.dof_index(f"scapula_{k}_{side}")]
            values[f"scapula_{k}_{side}"] = rng.uniform(float(lo), float(hi), n)
    pose = skeleton.forward(torch.tensor(skeleton.coordinates(values)))
    torso = pose.frames[0, skeleton.body_names.index("torso")]  # the torso does not move here
    r_h = float(np.hypot(SCAPULA_CONTACT_R[0] - THORAX_AXIS[0], SCAPULA_CONTACT_R[2] - THORAX_AXIS[1]))
    for side in "rl":
        i = skeleton.body_names.index(f"scapula_{side}")
        p = (torch.linalg.inv(torso) @ pose.frames[:, i, :, 3].unsqueeze(-1))[:, :3, 0]  # torso frame
        horiz = torch.hypot(p[:, 0] - THORAX_AXIS[0], p[:, 2] - THORAX_AXIS[1])
        on_surface = (horiz / r_h) ** 2 + ((p[:, 1] - SCAPULA_CONTACT_R[1]) / THORAX_VERTICAL_RADIUS) ** 2
        assert torch.allclose(on_surface, torch.ones_like(on_surface), atol=1e-9)
        assert float(p[:, 2].abs().min()) > 0.02  # stays on its own side


def test_onnx_export_matches_torch(skeleton: Skeleton) -> None:
    ort = pytest.importorskip("onnxruntime")
    from bodyfit.models.skeleton.onnx_export import export_fk_onnx

    fk = skeleton.kinematics(torch.float32)
    sess = ort.InferenceSession(export_fk_onnx(fk), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(12)
    for B in (1, 1000):  # dynamic batch
        q = random_pose(skeleton, B, seed=B).astype(np.float32)
        root = rng.uniform(-1, 1, (B, 3)).astype(np.float32)
        scales = rng.uniform(0.8, 1.2, (B, len(skeleton.segments), 3)).astype(np.float32)
        frames, centres = sess.run(None, {"coordinates": q, "root": root, "scales": scales})
        ref = fk(torch.tensor(q), torch.tensor(root), torch.tensor(scales))
        assert np.abs(frames[..., :3, 3] - ref.frames[..., :3, 3].numpy()).max() <= 1e-6
        assert np.abs(centres - ref.joint_centres.numpy()).max() <= 1e-6
        assert np.abs(frames[..., :3, :3] - ref.frames[..., :3, :3].numpy()).max() <= 1e-6
