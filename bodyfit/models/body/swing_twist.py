"""Swing-twist skinning: dual-quaternion blending for the twist about a limb's axis, LBS for the swing.

The skinning function of P. Fechteler, A. Hilsmann and P. Eisert, "Example-based Body Model Optimization and
Skinning", Eurographics 2016 Short Papers (section 2), after L. Kavan and O. Sorkine, "Elasticity-Inspired
Deformers for Character Articulation", ACM Transactions on Graphics 31(6) (SIGGRAPH Asia), 2012: each joint's
rotation is split into a twist about the joint's own axis and a swing; a vertex's twist is the dual-quaternion
linear blend (DLB) of its bodies' twists (L. Kavan, S. Collins, J. Žára and C. O'Sullivan, "Skinning with Dual
Quaternions", ACM SIGGRAPH Symposium on Interactive 3D Graphics and Games (I3D), 2007, and "Geometric
Skinning with Approximate Dual Quaternion Blending", ACM Transactions on Graphics 27(4), 2008), after which
linear blend skinning applies the swings. LBS alone blends two frames twisted by an angle a apart into a
matrix that scales the limb's cross-section by cos(a / 2) (the candy wrapper); a blended unit dual quaternion
is a rigid motion, so the twisted cross-section keeps its area.

In our skeleton the twist joints are those with a coordinate that rotates a segment about its own axis
(:data:`TWIST_COORDINATES`). Each is the last rotation of its joint, so the joint's rotation relative to the
bind pose factors exactly as ``swing @ twist`` with the twist a rotation by ``q - q_bind`` about the
coordinate's axis in the bind pose, through the joint centre: no swing-twist decomposition of a matrix (and
none of its singularity at 180 degrees of swing) is needed.

A body's twist ``W_j`` is the product of the twists of the twist joints between the root and it (the forearm's
radius carries the humeral and the pronation twist, the ulna only the humeral). Bodies with the same product
form a twist class. With ``M_j`` a body's skinning transform, its swing is ``S_j = M_j W_j^-1`` and

    v' = sum_j w_j S_j DLB_v(W) v,     DLB_v(W) = normalise(sum_c t_vc W_c)

with twist weights ``t_vc`` the skinning weights summed over the bodies of class c (one weight set for both
parts; paper 002 optimises a second set for DLB). A vertex on one body is moved by ``S_j W_j = M_j`` exactly,
a vertex blended across a pure twist is rotated rigidly by the blended twist, and one blended across a joint
without twist (the knee, the elbow) is skinned by plain LBS, since both bodies share their twist.

Dual quaternions are stored component-major, (8, ...) = [w, x, y, z] real then [w, x, y, z] dual part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.skeleton.model import Skeleton

# Coordinates that rotate a segment about its own long axis (OpenSim names without the side suffix).
TWIST_COORDINATES = ("hip_rotation", "arm_rot", "pro_sup", "neck_rotation")
SKINNING_MODES = ("lbs", "lbs_dq")


@dataclass(frozen=True)
class TwistRig:
    """The twist joints of a skeleton and the twist classes of its bodies, as arrays (float64).

    coordinate: (K,) index of each twist joint's coordinate in q; bind: (K,) its bind-pose value;
    axis: (K, 3) unit twist axis in the bind pose (world); centre: (1 + n_bone, K, 3) joint centre in the bind
    pose, affine in the bone coefficients (row 0 the mean body's); chain: (D, n_class) indices into the K
    twist joints plus one identity (index K) whose product, first row first, is the class's twist;
    body_class: (n_body,) each body's class (class 0 is the untwisted one).
    """

    coordinate: np.ndarray
    bind: np.ndarray
    axis: np.ndarray
    centre: np.ndarray
    chain: np.ndarray
    body_class: np.ndarray

    @property
    def n_class(self) -> int:
        return int(self.chain.shape[1])

    def class_weights(self, weights: np.ndarray) -> np.ndarray:
        """Twist weights (V, n_class): skinning weights (V, n_body) summed over each class's bodies."""
        one_hot = np.eye(self.n_class)[self.body_class]
        return np.asarray(weights, np.float64) @ one_hot


def _twist_joints(skeleton: Skeleton) -> list[tuple[int, int, int]]:
    """(joint index, coordinate index, axis slot) of every joint whose last coordinate-driven rotation is a
    twist coordinate, in the spec's joint order (parents before children)."""
    found = []
    for j, joint in enumerate(skeleton.spec.joints):
        driven = [k for k, ax in enumerate(joint.rotations) if ax.coordinate is not None]
        if not driven:
            continue
        last = joint.rotations[driven[-1]].coordinate
        assert last is not None
        base = last[:-2] if last.endswith(("_r", "_l")) else last
        if base in TWIST_COORDINATES:
            found.append((j, skeleton.dof_index(last), driven[-1]))
    return found


def _bind_geometry(
    skeleton: Skeleton, data: dict[str, np.ndarray], joints: list[tuple[int, int, int]]
) -> tuple[np.ndarray, np.ndarray]:
    """Twist axes (K, 3) and joint centres (1 + n_bone, K, 3), affine in c_b, of the bind pose.

    The axis is that of the child's rotation relative to the bind pose when the twist coordinate alone
    moves; the centre is the joint's child-side frame origin. Both come from the forward kinematics in
    float64, the centre's affinity in c_b checked on random bodies.
    """
    fk = skeleton.kinematics(torch.float64)
    mean = torch.as_tensor(np.asarray(data["scale_mean"], np.float64))
    basis = torch.as_tensor(np.asarray(data["scale_basis"], np.float64))
    q_bind = torch.as_tensor(np.asarray(data["bind_q"], np.float64))
    nb = basis.shape[0]
    index = [j for j, _, _ in joints]

    def centres(c_b: torch.Tensor) -> torch.Tensor:
        scales = mean + torch.einsum("nk,kjc->njc", c_b, basis)
        return fk(q_bind.expand(len(c_b), -1), None, scales).joint_centres[:, index]

    with torch.no_grad():
        C = centres(torch.cat([torch.zeros(1, nb), torch.eye(nb)]).double())
        affine = torch.cat([C[:1], C[1:] - C[:1]]).numpy()
        probe = torch.as_tensor(np.random.default_rng(0).normal(size=(3, nb)) * 2.0)
        if (
            float((centres(probe) - (C[0] + torch.einsum("nk,kjc->njc", probe, C[1:] - C[0]))).abs().max())
            > 1e-9
        ):
            raise AssertionError("twist joint centres are not affine in the bone coefficients")
        axes = []
        rest = fk(q_bind[None]).frames[0]
        for j, col, _ in joints:
            q = q_bind.clone()
            q[col] += 1e-3
            child = skeleton.spec.body_names.index(skeleton.spec.joints[j].child)
            R = fk(q[None]).frames[0, child, :3, :3] @ rest[child, :3, :3].T
            axial = torch.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
            axes.append((axial / axial.norm()).numpy())
    return np.asarray(axes), affine


def twist_rig(skeleton: Skeleton, data: dict[str, np.ndarray]) -> TwistRig:
    """The :class:`TwistRig` of ``skeleton`` with the body asset's bind pose and bone basis ``data``."""
    joints = _twist_joints(skeleton)
    axes, centre = _bind_geometry(skeleton, data, joints)
    spec = skeleton.spec
    child_of = {spec.body_names.index(spec.joints[j].child): k for k, (j, _, _) in enumerate(joints)}
    parents = spec.body_parent_index
    paths: list[tuple[int, ...]] = []
    for b in range(len(spec.bodies)):
        path: list[int] = []
        node = b
        while node >= 0:
            if node in child_of:
                path.append(child_of[node])
            node = parents[node]
        paths.append(tuple(path[::-1]))
    classes = sorted(set(paths), key=lambda p: (len(p), p))
    depth = max(1, max(len(p) for p in classes))
    chain = np.full((depth, len(classes)), len(joints), np.int64)
    for c, members in enumerate(classes):
        chain[: len(members), c] = members
    return TwistRig(
        coordinate=np.array([col for _, col, _ in joints], np.int64),
        bind=np.asarray(data["bind_q"], np.float64)[[col for _, col, _ in joints]],
        axis=axes,
        centre=centre,
        chain=chain,
        body_class=np.array([classes.index(p) for p in paths], np.int64),
    )


def _hamilton_table() -> np.ndarray:
    """C (4, 16) with (a b)_i = sum_jk C[i, 4 j + k] a_j b_k: the Hamilton product as one matrix product of
    the outer product a b^T, a few large operations in ONNX instead of sixteen small ones."""
    # Each row: (i, j, k, sign) of the terms a_j b_k of component i, components [w, x, y, z].
    terms = [
        (0, 0, 0, 1), (0, 1, 1, -1), (0, 2, 2, -1), (0, 3, 3, -1),
        (1, 0, 1, 1), (1, 1, 0, 1), (1, 2, 3, 1), (1, 3, 2, -1),
        (2, 0, 2, 1), (2, 1, 3, -1), (2, 2, 0, 1), (2, 3, 1, 1),
        (3, 0, 3, 1), (3, 1, 2, 1), (3, 2, 1, -1), (3, 3, 0, 1),
    ]  # fmt: skip
    table = np.zeros((4, 16))
    for i, j, k, sign in terms:
        table[i, 4 * j + k] = sign
    return table


HAMILTON = _hamilton_table()


def _rotation_table() -> np.ndarray:
    """G (9, 16) with R_flat = G (r r^T)_flat the row-major rotation of a unit quaternion r = [w, v]:
    R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]x."""
    table = np.zeros((3, 3, 4, 4))
    for i in range(3):
        table[i, i, 0, 0] = 1.0
        for k in range(1, 4):
            table[i, i, k, k] -= 1.0
        for j in range(3):
            table[i, j, i + 1, j + 1] += 2.0
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):  # [v]x has -v_k at (i, j), +v_k at (j, i)
        table[i, j, 0, k + 1] -= 2.0
        table[j, i, 0, k + 1] += 2.0
    return table.reshape(9, 16)


ROTATION = _rotation_table()
# Translation 2 (d r*)_vec of a unit dual quaternion as TRANSLATION @ (d r^T)_flat: the conjugate negates
# r's vector part.
TRANSLATION = 2.0 * (HAMILTON.reshape(4, 4, 4) * np.array([1.0, -1.0, -1.0, -1.0])).reshape(4, 16)[1:]


def _bilinear(table: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """table (m, 16) applied to the outer products of 4-vectors a, b (4, ...) -> (m, ...)."""
    outer = (a.unsqueeze(1) * b.unsqueeze(0)).reshape(16, -1)
    return (table @ outer).reshape(table.shape[0], *a.shape[1:])


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of quaternions (4, ...) [w, x, y, z] of the same shape."""
    return _bilinear(torch.as_tensor(HAMILTON, dtype=a.dtype), a, b)


def dual_quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Product of dual quaternions (8, ...): the rigid motion ``a`` after ``b``."""
    real = quaternion_multiply(a[:4], b[:4])
    dual = quaternion_multiply(a[:4], b[4:]) + quaternion_multiply(a[4:], b[:4])
    return torch.cat([real, dual])


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product of vectors (3, ...) component-major, from two cyclic shifts of each."""
    one, two = torch.tensor([1, 2, 0]), torch.tensor([2, 0, 1])
    return a[one] * b[two] - a[two] * b[one]


def twist_dual_quaternions(angle: torch.Tensor, axis: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """Unit dual quaternions of rotations by ``angle`` about the lines through ``centre`` along ``axis``.

    A rotation by a about the line with direction u and moment m = c x u is the screw of zero pitch
    (cos a/2, sin a/2 u) + eps (0, sin a/2 m).

    Args:
        angle: (K, B) radians; axis: (3, K, 1) unit directions; centre: (3, K, B) points on the lines.
    Returns:
        (8, K, B).
    """
    half = 0.5 * angle
    s = torch.sin(half)
    moment = cross(centre, axis.expand_as(centre))
    return torch.cat([torch.cos(half)[None], axis * s, torch.zeros_like(s)[None], moment * s])


def class_twists(joint_dq: torch.Tensor, chain: torch.Tensor) -> torch.Tensor:
    """Each twist class's dual quaternion: the product of its chain's joint twists, the root's first.

    Args:
        joint_dq: (8, K, B) twist of every twist joint; chain: (D, n_class) indices into K joints plus the
            identity (index K).
    Returns:
        (8, n_class, B), real parts in the hemisphere of the identity so that blends take the short way.
    """
    identity = torch.zeros_like(joint_dq[:, :1])
    identity[0] = 1.0
    table = torch.cat([joint_dq, identity], dim=1)
    out = table[:, chain[0]]
    for level in range(1, chain.shape[0]):
        out = dual_quaternion_multiply(out, table[:, chain[level]])
    return out * torch.where(out[:1] < 0, -1.0, 1.0).to(out.dtype)


def rigid_of_dual_quaternion(q: torch.Tensor) -> torch.Tensor:
    """Rigid transforms (3, 4, ...) of unit dual quaternions (8, ...): rotation of the real part r and
    translation 2 (d r*)_vec of the dual part d (KCvO08, algorithm 1)."""
    dtype = q.dtype
    rotation = _bilinear(torch.as_tensor(ROTATION, dtype=dtype), q[:4], q[:4])
    translation = _bilinear(torch.as_tensor(TRANSLATION, dtype=dtype), q[4:], q[:4])
    return torch.cat([rotation.reshape(3, 3, *q.shape[1:]), translation.unsqueeze(1)], dim=1)


def swing_transforms(transforms: torch.Tensor, twists: torch.Tensor) -> torch.Tensor:
    """Swings ``S_j = M_j W_j^-1`` of skinning transforms M (3, 4, n, B) and their bodies' twists W
    (3, 4, n, B), component-major rigid maps -> (3, 4, n, B)."""
    R_t = twists[:, :3].transpose(0, 1)  # W's inverse rotation
    rot = (transforms[:, :3].unsqueeze(2) * R_t.unsqueeze(0)).sum(1)
    shift = transforms[:, 3] - (rot * twists[:, 3].unsqueeze(0)).sum(1)
    return torch.cat([rot, shift.unsqueeze(1)], dim=1)


def _shift(a: torch.Tensor, by: int) -> torch.Tensor:
    """Components (axis 1, size 3) cyclically shifted by ``by``: a Gather of whole rows."""
    return a.index_select(1, torch.tensor([(by + i) % 3 for i in range(3)]))


def blend_twist(rest: torch.Tensor, blended: torch.Tensor) -> torch.Tensor:
    """Apply blended (not normalised) dual quaternions to points: DLB's normalisation and rigid map.

    With r, d the blend's real and dual parts, the normalised rigid motion moves v to
    ``v + 2 [r_v x (r_v x v + r_w v + d_v) + r_w d_v - d_w r_v] / |r|^2`` (KCvO08, algorithm 1, with the
    rotation written as nested cross products). Components lie on axis 1 throughout so that every step is
    one large elementwise operation.

    Args:
        rest: (B, 3, V) points; blended: (B, 8, V) the per-point weighted sums of unit dual quaternions.
    Returns:
        (B, 3, V) moved points.
    """
    r_w, r_v, d_w, d_v = blended[:, 0:1], blended[:, 1:4], blended[:, 4:5], blended[:, 5:8]

    def cross_1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return _shift(a, 1) * _shift(b, 2) - _shift(a, 2) * _shift(b, 1)

    inner = cross_1(r_v, rest) + r_w * rest + d_v
    step = cross_1(r_v, inner) + r_w * d_v - d_w * r_v
    scale = 2.0 / (blended[:, 0:4] * blended[:, 0:4]).sum(1, keepdim=True)
    return rest + step * scale
