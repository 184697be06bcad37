"""The body model: one parameter set drives the skin, the anatomical joints and the skeleton.

    scales   s = s_mean + c_b P_b                          (BLSM eq. 4; per segment, x y z)
    template V = V_mean + c_b P_bc + c_s P_s                (BLSM eq. 1, 7, 8; in the bind pose)
    frames   T(q, s)                                        (the skeleton's forward kinematics)
    bind     T(q_bind, s): fixed rotations, origins affine in c_b (no second forward kinematics)
    skin     v = sum_j w_j T_j T_bind,j^-1 V                (LBS, BLSM eq. 12; skinning="lbs")
             v = sum_j w_j S_j DLB(W) V                     (swing-twist, paper 002; skinning="lbs_dq")
    joints   anatomical joint centres, fixed points of the skeleton's bodies

Shape coefficients are ``c = [c_b, c_s]``, each in units of its population standard deviation (so a
standard normal draw is a plausible body). Coordinates are the skeleton's (OpenSim names and ranges);
``root`` is the pelvis translation.

Equation numbers are those of H. Wang, R. A. Güler, I. Kokkinos, G. Papandreou and S. Zafeiriou, "BLSM: A
Bone-Level Skinned Model of the Human Mesh", European Conference on Computer Vision (ECCV), 2020.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch
from torch import nn

from bodyfit.models.assets import verified_asset
from bodyfit.models.body.bone_geometry import apply_bone_geometry
from bodyfit.models.body.lbs import blend_block, blend_blocks, blend_rows
from bodyfit.models.body.swing_twist import (
    SKINNING_MODES,
    TwistRig,
    TwistSkin,
    class_dual_quaternions,
    class_twist_weights,
    monomial_table,
    rigid_of_dual_quaternion,
    twist_rig,
)
from bodyfit.models.errors import AssetError, BodyfitError, ShapeError
from bodyfit.models.rotations import cm_matmul, cm_matvec
from bodyfit.models.skeleton.bones import pose_bones
from bodyfit.models.skeleton.model import Skeleton, check_finite
from bodyfit.models.skeleton.spec import SkeletonSpec

BODY_ASSET = "body.npz"
_T = TypeVar("_T")

# Anatomical joints: name -> (joint of the skeleton, which side of it the centre is fixed to). "child" is
# the joint's frame on the child body (it follows the child, e.g. through the knee's translations);
# "parent" the joint's frame on its parent (the start of a spine arc). The subtalar joint is left out:
# Rajagopal2015 puts its frame at the posterior-inferior corner of the calcaneus, at the skin of the heel,
# not at a joint centre; the radioulnar frame sits on the radial head, at the skin of thin forearms. Both
# axes are in ``frames``.
_MIDLINE_JOINTS = (
    ("pelvis", "ground_pelvis", "child"),
    ("lumbosacral", "back", "child"),
    ("thoracolumbar", "thorax_extension", "parent"),
    ("cervicothoracic", "neck_extension", "parent"),
    ("skull_base", "neck", "child"),
)
_SIDE_JOINTS = (
    ("hip", "hip", "child"),
    ("knee", "walker_knee", "child"),
    ("ankle", "ankle", "child"),
    ("mtp", "mtp", "child"),
    ("shoulder", "acromial", "child"),
    ("elbow", "elbow", "child"),
    ("wrist", "radius_hand", "child"),
)
ANATOMICAL_JOINTS: tuple[tuple[str, str, str], ...] = _MIDLINE_JOINTS + tuple(
    (f"{name}_{s}", f"{joint}_{s}", where) for s in ("r", "l") for name, joint, where in _SIDE_JOINTS
)


def joint_anchors(spec: SkeletonSpec) -> tuple[list[int], np.ndarray]:
    """Body index and body-frame point (before scaling) of every anatomical joint.

    Returns:
        bodies: (J,) body indices; points: (J, 3).
    """
    bodies, points = [], []
    for _, joint_name, where in ANATOMICAL_JOINTS:
        joint = spec.joint(joint_name)
        if where == "parent":
            bodies.append(spec.body_names.index(joint.parent))
            points.append(joint.parent_offset.translation)
        else:
            bodies.append(spec.body_names.index(joint.child))
            points.append(joint.child_offset.translation)
    return bodies, np.asarray(points, np.float64)


def body_points(
    frames: torch.Tensor, scales: torch.Tensor, body: torch.Tensor, segment: torch.Tensor, local: torch.Tensor
) -> torch.Tensor:
    """World positions of body-fixed points.

    Args:
        frames: (B, n_body, 4, 4); scales: (B, n_seg, 3); body, segment: (P,) indices; local: (P, 3) or
            (B, P, 3) points in their body frames before scaling.
    Returns:
        (B, P, 3).
    """
    T = frames[:, body]
    p = local * scales[:, segment]
    return (T[..., :3, :3] @ p.unsqueeze(-1)).squeeze(-1) + T[..., :3, 3]


def bind_frames_affine(skeleton: Skeleton, data: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Bind-pose body frames as an affine function of the bone coefficients c_b.

    At a fixed pose a body's origin is a sum of rotated, scaled joint offsets, so it is linear in the
    segment scales and hence in c_b, and the orientations do not depend on them: the forward pass then
    needs forward kinematics for the pose only. Checked against forward kinematics here.

    Returns:
        base (n_body, 4, 4) frames at c_b = 0; delta (n_bone, n_body, 3) origin change per coefficient;
        float64.
    """
    fk = skeleton.kinematics(torch.float64)
    mean = torch.as_tensor(np.asarray(data["scale_mean"], np.float64))
    basis = torch.as_tensor(np.asarray(data["scale_basis"], np.float64))
    q_bind = torch.as_tensor(np.asarray(data["bind_q"], np.float64))
    nb = basis.shape[0]

    def frames(c_b: torch.Tensor) -> torch.Tensor:
        scales = mean + torch.einsum("nk,kjc->njc", c_b, basis)
        return fk(q_bind.expand(len(c_b), -1), None, scales).frames

    with torch.no_grad():
        F = frames(torch.cat([torch.zeros(1, nb), torch.eye(nb)]).double())
        base, delta = F[0], F[1:, :, :3, 3] - F[0, :, :3, 3]
        probe = torch.as_tensor(np.random.default_rng(0).normal(size=(4, nb)) * 2.0)
        linear = base[:, :3, 3] + torch.einsum("nk,kjc->njc", probe, delta)
        exact = frames(probe)
    if float((exact[..., :3, 3] - linear).abs().max()) > 1e-9 or not torch.allclose(
        exact[..., :3, :3], base[:, :3, :3].expand_as(exact[..., :3, :3])
    ):
        raise AssertionError("bind-pose frames are not affine in the bone coefficients")
    return base.numpy(), delta.numpy()


# Vertices per skinning block (see :func:`blend_blocks`): about 12 blocks for the whole template.
_BLOCK_VERTICES = 1100


class SkinBlock(nn.Module):
    """Buffers of one block of vertices: the bodies that carry them, their weights on those bodies and
    their template basis, rest (B, 3, V_k) = [1, c] @ basis."""

    bodies: torch.Tensor
    weights_t: torch.Tensor
    basis: torch.Tensor

    def __init__(
        self, bodies: np.ndarray, weights_t: np.ndarray, basis: np.ndarray, dtype: torch.dtype
    ) -> None:
        """bodies (m,); weights_t (m, V_k); basis (1 + K, 3, V_k)."""
        super().__init__()
        self.register_buffer("bodies", torch.as_tensor(bodies, dtype=torch.long))
        self.register_buffer("weights_t", torch.as_tensor(np.ascontiguousarray(weights_t)).to(dtype))
        self.register_buffer("basis", torch.as_tensor(basis.reshape(len(basis), -1)).to(dtype))

    def forward(
        self, coeffs: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor
    ) -> torch.Tensor:
        """coeffs (B, 1 + K); rotations, translations: every body's rows from :func:`blend_rows`
        -> (B, V_k, 3)."""
        rest = (coeffs @ self.basis).reshape(coeffs.shape[0], 3, self.weights_t.shape[1])
        return blend_block(rest, self.weights_t, rotations[:, self.bodies], translations[:, self.bodies])


def skin_blocks(
    basis: np.ndarray,
    weights: np.ndarray,
    dtype: torch.dtype,
    twist: tuple[np.ndarray, np.ndarray] | None = None,
) -> nn.Module:
    """The skin split into :class:`SkinBlock` s (a ModuleList), or the :class:`TwistSkin` when the twist
    weights (V, n_class) and each body's twist class (n_body,) are given. basis (1 + K, 3, V); weights
    (V, n_body)."""
    n_blocks = max(1, round(weights.shape[0] / _BLOCK_VERTICES))
    if twist is not None:
        return TwistSkin(basis, weights, *twist, dtype, n_blocks)
    blocks = blend_blocks(weights, n_blocks)
    return nn.ModuleList(
        SkinBlock(bodies, weights[a:b, bodies].T, basis[:, :, a:b], dtype) for a, b, bodies in blocks
    )


class BodyDecoder(nn.Module):
    """Buffers-only torch module: (shape, coordinates, root) -> skin vertices, joints, frames, scales.

    No validation (see :class:`BodyModel`); any batch size; dtype and skinning (``"lbs"`` or ``"lbs_dq"``,
    :mod:`~bodyfit.models.body.swing_twist`) fixed at construction.
    """

    scale_mean: torch.Tensor
    scale_basis: torch.Tensor
    bind_rot_t: torch.Tensor
    bind_shift: torch.Tensor
    joint_local: torch.Tensor
    joint_body: torch.Tensor
    joint_segment: torch.Tensor
    # skinning "lbs_dq" only (see _init_twist)
    twist_coordinate: torch.Tensor
    twist_bind: torch.Tensor
    twist_table: torch.Tensor
    twist_chain: torch.Tensor
    body_class: torch.Tensor

    def __init__(
        self, skeleton: Skeleton, data: dict[str, np.ndarray], dtype: torch.dtype, skinning: str = "lbs"
    ) -> None:
        super().__init__()
        if skinning not in SKINNING_MODES:
            raise BodyfitError(f"skinning must be one of {', '.join(SKINNING_MODES)}; got {skinning!r}")
        self.skinning = skinning
        self.fk = skeleton.kinematics(dtype)
        self.n_bone = int(data["scale_basis"].shape[0])
        self.n_seg = n_seg = len(skeleton.segments)
        bodies, local = joint_anchors(skeleton.spec)
        seg_of_body = np.asarray(skeleton.spec.body_segment_index)

        def buf(name: str, value: np.ndarray) -> None:
            self.register_buffer(name, torch.as_tensor(np.ascontiguousarray(value, np.float64)).to(dtype))

        buf("scale_mean", data["scale_mean"].reshape(n_seg * 3))
        buf("scale_basis", data["scale_basis"].reshape(self.n_bone, n_seg * 3))
        # Template: rest (B, 3, V) = [1, c] (B, 1 + K) @ basis (1 + K, 3, V).
        basis = np.concatenate(
            [data["vertices_mean"][None], data["bone_correctives"], data["identity_basis"]]
        )
        self._basis = basis.transpose(0, 2, 1)
        self._weights = np.asarray(data["weights"], np.float64)
        self._twist: np.ndarray | None = None
        if skinning == "lbs_dq":
            self._init_twist(twist_rig(skeleton, data), buf)
        self.skin = skin_blocks(self._basis, self._weights, dtype, self._twist_of(self._twist))
        # inv(bind) = [Rb^T, -Rb^T tb]: Rb^T is fixed and Rb^T tb = [1, c_b] @ bind_shift.
        base, delta = bind_frames_affine(skeleton, data)
        rot_t = base[:, :3, :3].transpose(0, 2, 1)
        origins = np.concatenate([base[None, :, :3, 3], delta])  # (1 + n_bone, n_body, 3)
        buf("bind_rot_t", rot_t.transpose(1, 2, 0)[..., None])  # component-major (3, 3, n_body, 1)
        buf("bind_shift", np.einsum("sij,ksj->ksi", rot_t, origins).reshape(1 + self.n_bone, -1))
        buf("joint_local", local)
        self.register_buffer("joint_body", torch.as_tensor(bodies, dtype=torch.long))
        self.register_buffer("joint_segment", torch.as_tensor(seg_of_body[bodies], dtype=torch.long))

    def _init_twist(self, rig: TwistRig, buf: Callable[[str, np.ndarray], None]) -> None:
        """Buffers of the twist joints and classes (:class:`~bodyfit.models.body.swing_twist.TwistRig`):
        twist coordinates, their bind values, the classes' chains, the table of their dual quaternions
        (:func:`~bodyfit.models.body.swing_twist.monomial_table`) and the classes' bodies."""
        self._twist = rig.class_weights(self._weights)
        self.register_buffer("twist_coordinate", torch.as_tensor(rig.coordinate, dtype=torch.long))
        buf("twist_bind", rig.bind)
        buf("twist_table", monomial_table(rig))
        self.register_buffer("twist_chain", torch.as_tensor(rig.chain, dtype=torch.long))
        self.register_buffer("body_class", torch.as_tensor(rig.body_class, dtype=torch.long))

    def _twist_of(self, twist: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """Twist weights (V, n_class) with the bodies' classes, as :func:`skin_blocks` takes them."""
        return None if twist is None else (twist, self.body_class.numpy())

    def restricted(self, vertices: np.ndarray) -> BodyDecoder:
        """A decoder that outputs only ``vertices`` (V',) template indices, sharing every other buffer.
        Fitting runs its early iterations on such a subset."""
        index = np.asarray(vertices, np.int64)
        sub = copy.copy(self)
        sub._modules = dict(self._modules)
        twist = None if self._twist is None else self._twist[index]
        sub.skin = skin_blocks(
            self._basis[:, :, index], self._weights[index], self.bind_rot_t.dtype, self._twist_of(twist)
        )
        return sub

    def with_offsets(self, offsets: np.ndarray) -> BodyDecoder:
        """A decoder for one person whose template carries rest-pose offsets (V, 3) metres (surface detail
        beyond the shape space, skinned with the template), sharing every other buffer. Offsets of zero
        give this decoder's output."""
        d = np.asarray(offsets, np.float64)
        if d.shape != (self._basis.shape[2], 3):
            raise ShapeError(f"rest offsets must have shape ({self._basis.shape[2]}, 3); got {d.shape}")
        out = copy.copy(self)
        out._modules = dict(self._modules)
        out._basis = self._basis.copy()
        out._basis[0] += d.T
        out.skin = skin_blocks(out._basis, self._weights, self.bind_rot_t.dtype, self._twist_of(self._twist))
        return out

    def with_weights(self, weights: np.ndarray) -> BodyDecoder:
        """A decoder for one person skinned with their own weights (V, n_body) (rows non-negative, summing to
        one), sharing every other buffer; template offsets already in this decoder are kept. Under skinning
        "lbs_dq" the twist weights follow the new weights (each class's bodies' weights summed, as
        :meth:`~bodyfit.models.body.swing_twist.TwistRig.class_weights` makes them). This decoder's own
        weights give this decoder's output."""
        w = np.asarray(weights, np.float64)
        if w.shape != self._weights.shape:
            raise ShapeError(f"skinning weights must have shape {self._weights.shape}; got {w.shape}")
        out = copy.copy(self)
        out._modules = dict(self._modules)
        out._weights = w.copy()
        if self._twist is not None:
            out._twist = class_twist_weights(w, self.body_class.numpy(), self._twist.shape[1])
        out.skin = skin_blocks(self._basis, out._weights, self.bind_rot_t.dtype, self._twist_of(out._twist))
        return out

    def blended_rotations(self, frames: torch.Tensor, q: torch.Tensor | None = None) -> np.ndarray:
        """Each vertex's blended linear skinning part, sum_j w_vj R_j R_bind,j^T: what a rest-pose offset is
        multiplied by. frames (B, n_body, 4, 4) from :meth:`forward` -> (B, V, 3, 3) float64.

        Under skinning "lbs_dq" the offset is first turned by the vertex's blended twist and then by the
        blended swings, so the coordinates q (B, n_dof) that gave ``frames`` are needed too."""
        rot_bind_t = self.bind_rot_t[..., 0].permute(2, 0, 1).double().numpy()  # (n_body, 3, 3)
        M = frames[..., :3, :3].double().numpy() @ rot_bind_t
        if self._twist is None:
            return np.einsum("vj,bjik->bvik", self._weights, M)
        if q is None:
            raise BodyfitError('the skin\'s blended rotations under skinning "lbs_dq" need the coordinates q')
        coeffs = torch.zeros(len(q), 1 + self.n_bone, dtype=self.twist_table.dtype)
        coeffs[:, 0] = 1.0  # the twists' rotations do not depend on the joint centres
        twists = self.class_twists(q.to(coeffs.dtype), coeffs).double()
        W = rigid_of_dual_quaternion(twists)[:, :3].permute(3, 2, 0, 1).numpy()  # (B, n_class, 3, 3)
        swing = M @ W[:, self.body_class.numpy()].transpose(0, 1, 3, 2)
        blend = torch.einsum("vc,kcb->kbv", torch.as_tensor(self._twist), twists)
        turn = rigid_of_dual_quaternion(blend / blend[:4].norm(dim=0))[:, :3].permute(2, 3, 0, 1).numpy()
        return np.einsum("vj,bjik->bvik", self._weights, swing) @ turn

    def forward(
        self, shape: torch.Tensor, q: torch.Tensor, root: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Args:
            shape: (B, n_shape) coefficients [bone, identity]; q: (B, n_dof); root: (B, 3).
        Returns:
            vertices (B, V, 3), joints (B, J, 3), frames (B, n_body, 4, 4), scales (B, n_seg, 3).
        """
        scales, coeffs = self._shape_terms(shape)
        world = self.fk.frames_cm(q, root, scales)  # (4, 4, n_body, B)
        shift = self._bind_shift(coeffs)
        if self._twist is None:
            rows = blend_rows(self._transforms(world, shift))
            assert isinstance(self.skin, nn.ModuleList)
            vertices = torch.cat([block(coeffs, *rows) for block in self.skin], dim=1)
        else:
            vertices = self._twist_skin(world, coeffs, q, shift)
        frames = world.permute(3, 2, 0, 1).contiguous()
        return vertices, self.joints(frames, scales), frames, scales

    def _twist_skin(
        self, world: torch.Tensor, coeffs: torch.Tensor, q: torch.Tensor, shift: torch.Tensor
    ) -> torch.Tensor:
        """Swing-twist skin (B, V, 3) of world frames (4, 4, n_body, B), skin coefficients [1, c]
        (B, 1 + n_shape), coordinates q (B, n_dof) and the bind shift of :meth:`_bind_shift`."""
        return self.skin(coeffs, self._transforms(world, shift), self._class_twists(q, coeffs))

    def class_twists(self, q: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        """The twist classes' unit dual quaternions (8, n_class, B) of coordinates q (B, n_dof) and skin
        coefficients [1, c] (B, 1 + n_shape) (skinning "lbs_dq" only)."""
        return self._class_twists(q, coeffs).permute(1, 2, 0)

    def _class_twists(self, q: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        """:meth:`class_twists` batch first: (B, 8, n_class)."""
        angle = q[:, self.twist_coordinate] - self.twist_bind
        bone = coeffs[:, : 1 + self.n_bone]
        return class_dual_quaternions(angle, bone, self.twist_chain, self.twist_table)

    def joints(self, frames: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        """Anatomical joint centres (B, J, 3) of body frames (B, n_body, 4, 4) and segment scales
        (B, n_seg, 3)."""
        return body_points(frames, scales, self.joint_body, self.joint_segment, self.joint_local)

    def posed(self, shape: torch.Tensor) -> PosedSkin:
        """The skin of one fixed shape (1, n_shape) as a function of the pose alone (:class:`PosedSkin`):
        ``skin(q (B, n_dof), root (B, 3))`` gives the vertices (B, V, 3) of ``forward(shape.expand(B, -1),
        q, root)``."""
        return PosedSkin(self, shape)

    def _shape_terms(self, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Segment scales (B, n_seg, 3) and skin coefficients [1, c] (B, 1 + n_shape) of shapes c
        (B, n_shape)."""
        scales = self.scale_mean + shape[:, : self.n_bone] @ self.scale_basis
        coeffs = torch.cat([torch.ones_like(shape[:, :1]), shape], dim=1)
        return scales.reshape(shape.shape[0], self.n_seg, 3), coeffs

    def _bind_shift(self, coeffs: torch.Tensor) -> torch.Tensor:
        """Rb^T tb of every body for shapes [1, c] (B, 1 + n_shape): (3, n_body, B), component-major."""
        shift = coeffs[:, : 1 + self.n_bone] @ self.bind_shift
        return shift.reshape(coeffs.shape[0], self.bind_rot_t.shape[2], 3).permute(2, 1, 0)

    def _transforms(self, world: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
        """Skinning transforms T inv(T_bind) = [R Rb^T, t - R (Rb^T tb)] (3, 4, n_body, B) of the world frames
        (4, 4, n_body, B), with ``shift`` (3, n_body, B or 1) from :meth:`_bind_shift`; component-major."""
        R, t = world[:3, :3], world[:3, 3]
        return torch.cat([cm_matmul(R, self.bind_rot_t), (t - cm_matvec(R, shift)).unsqueeze(1)], 1)


class PosedSkin:
    """The skin of one fixed shape as a function of the pose alone (:meth:`BodyDecoder.posed`).

    With the rest shape fixed, each block's skin is one GEMM, (3 B, 4 m) @ (4 m, V_k): the m bodies'
    transforms against the rest coordinates weighted by their skinning weights, [w x; w y; w z; w], computed
    here once. Pose fits with a frozen shape (a sequence's frames) so skip the (3, B, 3, V) products of
    :func:`blend_block` and its backward: about a fifth of an evaluation. Swing-twist skinning moves each
    rest vertex by a pose-dependent twist first, so under it the skin is the decoder's own forward.
    """

    def __init__(self, decoder: BodyDecoder, shape: torch.Tensor) -> None:
        self.decoder = decoder
        with torch.no_grad():
            shape = shape.reshape(1, -1).to(decoder.scale_mean.dtype)
            self.shape = shape
            self.scales, coeffs = decoder._shape_terms(shape)
            self.shift = decoder._bind_shift(coeffs)
            self.blocks: list[tuple[torch.Tensor, torch.Tensor]] = []  # each block's bodies and GEMM matrix
            for block in decoder.skin if isinstance(decoder.skin, nn.ModuleList) else ():
                assert isinstance(block, SkinBlock)
                rest, w = (coeffs @ block.basis).reshape(3, -1), block.weights_t
                weighted = torch.cat([w[None] * rest[:, None], w[None]]).flatten(0, 1)
                self.blocks.append((block.bodies, weighted))

    def __call__(self, q: torch.Tensor, root: torch.Tensor) -> torch.Tensor:
        """Vertices (B, V, 3) of coordinates q (B, n_dof) and roots (B, 3)."""
        return self._skin(self._world(q, root), q)

    def with_joints(self, q: torch.Tensor, root: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices (B, V, 3) and anatomical joint centres (B, J, 3) of q (B, n_dof) and roots (B, 3)."""
        world = self._world(q, root)
        frames = world.permute(3, 2, 0, 1)
        return self._skin(world, q), self.decoder.joints(frames, self.scales.expand(q.shape[0], -1, -1))

    def _world(self, q: torch.Tensor, root: torch.Tensor) -> torch.Tensor:
        return self.decoder.fk.frames_cm(q, root, self.scales.expand(q.shape[0], -1, -1))

    def _skin(self, world: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        B = world.shape[-1]
        if self.decoder._twist is not None:
            coeffs = torch.cat([torch.ones_like(self.shape[:, :1]), self.shape], dim=1).expand(B, -1)
            return self.decoder._twist_skin(world, coeffs, q, self.shift)
        transforms = self.decoder._transforms(world, self.shift)
        parts = [
            (transforms[:, :, bodies].permute(0, 3, 1, 2).reshape(3 * B, -1) @ M).reshape(3, B, -1)
            for bodies, M in self.blocks
        ]
        return torch.cat(parts, 2).permute(1, 2, 0)


@dataclass(frozen=True)
class BodyOutput:
    """vertices (B, V, 3); joints (B, J, 3); frames (B, n_body, 4, 4); scales (B, n_seg, 3);
    bones (B, V_bone, 3) skeleton-mesh vertices when asked for, else None."""

    vertices: torch.Tensor
    joints: torch.Tensor
    frames: torch.Tensor
    scales: torch.Tensor
    bones: torch.Tensor | None = None


class BodyModel:
    """The loaded body model: validated forward, names, faces; buffers live in :class:`BodyDecoder`.

    ``skinning`` is the default of :meth:`decoder` and :meth:`forward`: ``"lbs"`` (linear blend skinning) or
    ``"lbs_dq"`` (LBS for the swing, dual-quaternion blending for the twist about the limbs' axes;
    :mod:`~bodyfit.models.body.swing_twist`).
    """

    def __init__(self, skeleton: Skeleton, data: dict[str, np.ndarray], skinning: str = "lbs") -> None:
        if skinning not in SKINNING_MODES:
            raise BodyfitError(f"skinning must be one of {', '.join(SKINNING_MODES)}; got {skinning!r}")
        self.skinning = skinning
        self.skeleton = skeleton
        self.data = data
        self.faces = data["faces"].astype(np.int64)
        self.n_bone = int(data["scale_basis"].shape[0])
        self.n_identity = int(data["identity_basis"].shape[0])
        self.joint_names = [name for name, _, _ in ANATOMICAL_JOINTS]
        self.landmark_names = [str(n) for n in data["landmark_names"]]
        self._decoders: dict[tuple[torch.dtype, str], BodyDecoder] = {}
        self._bone_vertices: np.ndarray | None = None
        self._derived: dict[str, Any] = {}

    @classmethod
    def load(cls, folder: Path | None = None, skinning: str = "lbs") -> BodyModel:
        """Load the built-in body model (hash-checked against the manifest) with its default skinning."""
        skeleton = Skeleton.load(folder)
        path = verified_asset(BODY_ASSET, folder)
        try:
            with np.load(path) as npz:
                data = {k: npz[k] for k in npz.files}
        except (OSError, ValueError) as exc:
            raise AssetError(f"cannot read {path}: {exc}; rebuild it with `bodyfit build-assets`") from exc
        return cls(skeleton, data, skinning)

    @property
    def n_shape(self) -> int:
        return self.n_bone + self.n_identity

    @property
    def n_vertices(self) -> int:
        return int(self.data["vertices_mean"].shape[0])

    @property
    def vertex_bodies(self) -> np.ndarray:
        """(V,) int: for each template vertex, the index (into ``skeleton.body_names``) of the skeleton body
        whose skinning weight on it is largest: the body a vertex belongs to."""
        return np.asarray(self.data["weights"]).argmax(axis=1)

    @property
    def dof_names(self) -> list[str]:
        return self.skeleton.dof_names

    @property
    def bind_coordinates(self) -> np.ndarray:
        """(n_dof,) coordinates of the bind pose, in which the template is stored."""
        return np.asarray(self.data["bind_q"], np.float64)

    def derived(self, key: str, build: Callable[[], _T]) -> _T:
        """A value computed from this model alone (a measuring topology, a Jacobian, checked populations),
        built by ``build()`` on first use under ``key`` and kept with the model: derived data lives and dies
        with its model, never in module state. ``key`` is namespaced by its user
        (``"anthropometry.topology"``)."""
        if key not in self._derived:
            self._derived[key] = build()
        return cast(_T, self._derived[key])

    def decoder(self, dtype: torch.dtype = torch.float32, skinning: str | None = None) -> BodyDecoder:
        """The torch module for ``dtype`` and ``skinning`` (None: the model's); built once per pair."""
        key = (dtype, self.skinning if skinning is None else skinning)
        if key not in self._decoders:
            self._decoders[key] = BodyDecoder(self.skeleton, self.data, *key)
        return self._decoders[key]

    def scaled_decoder(
        self, scale_offsets: np.ndarray, dtype: torch.dtype = torch.float32, skinning: str | None = None
    ) -> BodyDecoder:
        """A decoder (not cached) whose segment scales are the shape space's plus ``scale_offsets``
        (n_seg, 3): one person's joint centres, moved against the skin. The template is unchanged, so the
        skin of the bind pose stays where it was; every joint offset and body in a segment scales with it, as
        OpenSim scales a model, so the skeleton stays this one's. Offsets of zero give :meth:`decoder`'s
        output."""
        d = np.asarray(scale_offsets, np.float64)
        mean = np.asarray(self.data["scale_mean"], np.float64)
        if d.shape != mean.shape:
            raise ShapeError(f"segment scale offsets must have shape {mean.shape}; got {d.shape}")
        check_finite("segment scale offsets", d)
        if (mean + d <= 0).any():
            raise ShapeError("segment scale offsets must leave every segment scale positive")
        data = {**self.data, "scale_mean": mean + d}
        return BodyDecoder(self.skeleton, data, dtype, self.skinning if skinning is None else skinning)

    def validate_shape(
        self, shape: torch.Tensor | np.ndarray | None, batch: int, dtype: torch.dtype
    ) -> torch.Tensor:
        """(B, n_shape) shape coefficients as a tensor; None means the mean body."""
        if shape is None:
            return torch.zeros(batch, self.n_shape, dtype=dtype)
        t = torch.as_tensor(np.array(shape) if isinstance(shape, np.ndarray) else shape).to(dtype)
        if t.ndim != 2 or t.shape[1] != self.n_shape or t.shape[0] != batch:
            raise ShapeError(
                f"shape coefficients must have shape ({batch}, {self.n_shape}): {self.n_bone} bone "
                f"coefficients then {self.n_identity} identity coefficients; got {tuple(t.shape)}"
            )
        check_finite("shape coefficients", t)
        return t

    def forward(
        self,
        shape: torch.Tensor | np.ndarray | None = None,
        coordinates: torch.Tensor | np.ndarray | None = None,
        root: torch.Tensor | np.ndarray | None = None,
        skeleton_mesh: bool = False,
        dtype: torch.dtype = torch.float32,
        offsets: np.ndarray | None = None,
        skinning: str | None = None,
    ) -> BodyOutput:
        """Validated forward pass.

        Args:
            shape: (B, n_shape) or None (mean body).
            coordinates: (B, n_dof) in ``dof_names`` order (radians / metres) or None (zero pose). Build it
                by name with ``model.skeleton.coordinates({...})``.
            root: (B, 3) pelvis translation in metres, or None.
            skeleton_mesh: also pose the Rajagopal bone mesh scaled to the body.
            offsets: (V, 3) one person's rest-pose offsets in metres (from a sequence fit or an upgrade:
                surface detail beyond the shape space), or None.
            skinning: "lbs" or "lbs_dq", or None for the model's default.

        Raises:
            ShapeError: an array does not have the documented shape.
            NonFiniteError: an input holds NaN or infinite values.
            CoordinateRangeError: a coordinate is outside its joint limits.
        """
        if coordinates is None:
            batch = 1 if shape is None else int(np.shape(shape)[0])
            coordinates = np.zeros((batch, self.skeleton.n_dof))
        q, r, _ = self.skeleton.validate(coordinates, root, dtype=dtype)
        B = q.shape[0]
        c = self.validate_shape(shape, B, dtype)
        r = torch.zeros(B, 3, dtype=dtype) if r is None else r
        decoder = self.decoder(dtype, skinning)
        if offsets is not None:
            check_finite("rest offsets", np.asarray(offsets, np.float64))
            decoder = decoder.with_offsets(offsets)
        vertices, joints, frames, scales = decoder(c, q, r)
        bones = self.pose_bones(frames, scales) if skeleton_mesh else None
        return BodyOutput(vertices, joints, frames, scales, bones)

    def sample(self, n: int, sex: str | None = None, population: str = "nhanes", seed: int = 0) -> np.ndarray:
        """(n, n_shape) shape coefficients of bodies drawn from a real population ("nhanes", "ansur"; "anny":
        the shape space's standard normal), as :func:`bodyfit.models.anthropometry.population.sample` draws
        them.

        Raises:
            PopulationError: an unknown population or sex, or no population file for this shape space.
        """
        from bodyfit.models.anthropometry.population import sample  # the surveys load on first use

        return sample(self, n, sex, population, seed)

    def bone_vertices(self) -> np.ndarray:
        """The bone mesh's vertices (V_bone, 3) in their body frames, after the asset's affine maps (per
        body, or per piece: one bone) that fit them inside the skin (:mod:`bone_geometry`); the skeleton's own
        mesh when the asset has none."""
        if self._bone_vertices is None:
            bones = self.skeleton.bone_mesh()
            geometry, pieces = self.data.get("bone_geometry"), self.data.get("bone_piece")
            self._bone_vertices = (
                np.asarray(bones.vertices, np.float64)
                if geometry is None
                else apply_bone_geometry(
                    bones, np.asarray(geometry, np.float64), None if pieces is None else np.asarray(pieces)
                )
            )
        return self._bone_vertices

    def pose_bones(self, frames: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        """Bone mesh vertices (B, V_bone, 3) of this body model for frames (B, n_body, 4, 4) and segment
        scales (B, n_seg, 3) from :meth:`forward`; triangles ``skeleton.bone_mesh().faces``."""
        bones = self.skeleton.bone_mesh()
        return pose_bones(
            torch.as_tensor(self.bone_vertices()),
            torch.as_tensor(bones.vertex_body),
            torch.as_tensor(bones.vertex_segment),
            frames,
            scales,
        )
