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

import itertools
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from bodyfit.models.body.lbs import blend_blocks, blend_linear, blend_rows
from bodyfit.models.rotations import cm_matmul, cm_matvec
from bodyfit.models.skeleton.model import Skeleton

# Coordinates that rotate a segment about its own long axis (OpenSim names without the side suffix).
TWIST_COORDINATES = ("hip_rotation", "arm_rot", "pro_sup", "neck_rotation")
SKINNING_MODES = ("lbs", "lbs_dq")
# Twist weight below which a class is dropped from a vertex's blend (prune_twist_weights).
TWIST_FLOOR = 0.02


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
        """Twist weights (V, n_class) of skinning weights (V, n_body) (:func:`class_twist_weights`)."""
        return class_twist_weights(weights, self.body_class, self.n_class)


def class_twist_weights(
    weights: np.ndarray, body_class: np.ndarray, n_class: int, floor: float = TWIST_FLOOR
) -> np.ndarray:
    """Twist weights (V, n_class): skinning weights (V, n_body) summed over each class's bodies (body_class
    (n_body,)), the classes below ``floor`` pruned (:func:`prune_twist_weights`)."""
    summed = np.asarray(weights, np.float64) @ np.eye(n_class)[body_class]
    return prune_twist_weights(summed, floor)


def prune_twist_weights(twist: np.ndarray, floor: float) -> np.ndarray:
    """Twist weights (V, n_class) with every class's weight outside a vertex's largest lowered by ``floor``
    (at least to zero) and the difference given to the largest: a vertex whose weight outside its main class
    is a few hundredths (the head's on the thorax, the buttock's on both thighs) turns rigidly with that
    class instead of blending. Continuous in the weights (no jump between neighbouring vertices); the
    identity for ``floor`` 0."""
    t = np.asarray(twist, np.float64)
    rows, main = np.arange(len(t)), np.argmax(t, axis=1)
    out = np.maximum(t - floor, 0.0)
    out[rows, main] = 0.0
    out[rows, main] = 1.0 - out.sum(axis=1)
    return out


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
    rot = cm_matmul(transforms[:, :3], R_t)
    shift = transforms[:, 3] - cm_matvec(rot, twists[:, 3])
    return torch.cat([rot, shift.unsqueeze(1)], dim=1)


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of two quaternions (4,) [w, x, y, z] in numpy."""
    return HAMILTON @ np.outer(a, b).reshape(16)


def monomial_table(rig: TwistRig) -> np.ndarray:
    """A (n_class 2^D (1 + n_bone), 8 n_class): every class's dual quaternion as one matrix product.

    A joint's twist is ``(cos h, sin h u) + eps sin h (0, m)`` with h the half angle, u the axis and the
    moment m = p x u affine in the bone coefficients c_b (the centre p is). A class's twist, the product of
    its chain's D joint twists, is therefore a sum over the 2^D products of one cosine or sine per joint
    (the monomials), each times a constant quaternion (real part) or times [1, c_b] and a constant
    quaternion (dual part): ``q = (monomials (x) [1, c_b]) @ A``, rows ordered (class, monomial with the
    root's factor most significant, [1, c_b]), columns (component, class). The padding joint (index K of
    the chain) has cos 1, sin 0.
    """
    K, (D, C), nb1 = len(rig.coordinate), rig.chain.shape, rig.centre.shape[0]
    factor = np.zeros((K + 1, 2, 4))  # each joint's quaternion coefficient of cos h and sin h
    factor[:, 0, 0] = 1.0
    factor[:K, 1, 1:] = rig.axis
    moment = np.zeros((K + 1, nb1, 4))
    moment[:K, :, 1:] = np.cross(rig.centre, rig.axis[None]).transpose(1, 0, 2)
    table = np.zeros((C, 2**D, nb1, 8))
    for c in range(C):
        joints = rig.chain[:, c]
        for m, picks in enumerate(itertools.product((0, 1), repeat=D)):
            parts = [factor[k, a] for k, a in zip(joints, picks, strict=True)]
            table[c, m, 0, :4] = _product(parts)
            for i in (i for i in range(D) if picks[i]):
                for beta in range(nb1):
                    table[c, m, beta, 4:] += _product([*parts[:i], moment[joints[i], beta], *parts[i + 1 :]])
    out = np.zeros((C, 2**D, nb1, 8, C))
    out[np.arange(C), ..., np.arange(C)] = table
    return out.reshape(C * 2**D * nb1, 8 * C)


def _product(quaternions: list[np.ndarray]) -> np.ndarray:
    out = quaternions[0]
    for q in quaternions[1:]:
        out = _hamilton(out, q)
    return out


def class_dual_quaternions(
    angle: torch.Tensor, bone: torch.Tensor, chain: torch.Tensor, table: torch.Tensor
) -> torch.Tensor:
    """The twist classes' unit dual quaternions from the twist angles, as :func:`class_twists` computes
    them, in about fifteen operations (:func:`monomial_table`).

    Args:
        angle: (B, K) twist angles (radians from the bind pose); bone: (B, 1 + n_bone) [1, c_b];
            chain: (D, n_class); table: from :func:`monomial_table`.
    Returns:
        (B, 8, n_class), real parts in the hemisphere of the identity so that blends take the short way.
    """
    half = torch.nn.functional.pad(0.5 * angle, (0, 1))  # the padding joint: cos 1, sin 0
    h = torch.stack([torch.cos(half), torch.sin(half)], dim=-1)  # (B, K + 1, 2)
    monomials = h[:, chain[0]]
    for level in range(1, chain.shape[0]):
        monomials = (monomials.unsqueeze(-1) * h[:, chain[level]].unsqueeze(-2)).flatten(2)
    features = (monomials.unsqueeze(-1) * bone[:, None, None]).flatten(1)
    q = (features @ table).reshape(angle.shape[0], 8, -1)
    return q * torch.where(q[:, :1] < 0, -1.0, 1.0).to(q.dtype)


def _pair_table() -> np.ndarray:
    """P (13, 32) on the outer product q r^T (8 x 4, row-major) of a dual quaternion q and a real part r:
    rows 0-11 the numerator of the rigid map as a 3 x 4 matrix, row-major (ROTATION on the real parts,
    TRANSLATION on dual x real), row 12 the squared norm r . r."""
    table = np.zeros((3, 4, 32))
    table[:, :3, :16] = ROTATION.reshape(3, 3, 16)
    table[:, 3, 16:] = TRANSLATION
    norm = np.zeros((1, 32))
    norm[0, [0, 5, 10, 15]] = 1.0
    return np.concatenate([table.reshape(12, 32), norm])


PAIR_TABLE = _pair_table()


def class_rigid(q: torch.Tensor) -> torch.Tensor:
    """Rigid transforms (B, 12, n_class), the 3 x 4 matrices row-major, of unit dual quaternions
    (B, 8, n_class) (KCvO08, algorithm 1)."""
    table = torch.as_tensor(PAIR_TABLE[:12], dtype=q.dtype)
    return table @ (q.unsqueeze(2) * q[:, :4].unsqueeze(1)).flatten(1, 2)


def pair_weights(twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The class pairs a vertex's blend needs and their weights.

    The normalised blend ``b = sum_c t_c q_c`` moves a point v to ``(R(b) v + T(b)) / |b_r|^2`` with R,
    T and the norm quadratic in b: sums over pairs (a, c) of ``t_a t_c`` times a bilinear form of q_a and
    q_c (:func:`pair_rows`, symmetrised, so a pair a < c counts once with t_a t_c and a pair (c, c) with
    t_c^2 / 2).

    Args:
        twist: (V, n_class) twist weights.
    Returns:
        pairs (P, 2) with a <= c, every (c, c) first, then the pairs a < c that some vertex uses;
        weights (V, P).
    """
    n = twist.shape[1]
    used = twist != 0
    pairs = [(c, c) for c in range(n)]
    pairs += [(a, c) for a in range(n) for c in range(a + 1, n) if (used[:, a] & used[:, c]).any()]
    index = np.asarray(pairs, np.int64)
    weights = twist[:, index[:, 0]] * twist[:, index[:, 1]]
    weights[:, :n] *= 0.5
    return index, weights


def pair_rows(q: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """Rotation, translation and norm numerators (B, 13, P) of the class pairs (P, 2): the symmetrised
    ``PAIR_TABLE @ (q_a r_c^T + q_c r_a^T)`` of the classes' dual quaternions q (B, 8, n_class)."""
    a, c = q[:, :, pairs[:, 0]], q[:, :, pairs[:, 1]]
    outer = a.unsqueeze(2) * c[:, :4].unsqueeze(1) + c.unsqueeze(2) * a[:, :4].unsqueeze(1)
    return torch.as_tensor(PAIR_TABLE, dtype=q.dtype) @ outer.flatten(1, 2)


def skin_columns(
    weights: np.ndarray, twist: np.ndarray, body_class: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The columns of the skin's linear blend and every vertex's weights on them.

    The skin is LBS over transforms ``S_j W_c`` (a body's swing times a class's twist) applied to each
    vertex's rest position. A vertex whose twist weights lie on one class c is plain LBS by ``S_j W_c``:
    its bodies' transforms ``M_j = S_j W_{c(j)}`` where a body is in c, ``S_j W_c`` where it is in another
    (its twist pruned away, :func:`prune_twist_weights`). A vertex that blends classes is first moved by
    its blend (:func:`blended_rest`), then by its bodies' swings ``S_j = S_j W_0`` (class 0 is untwisted,
    so a body of class 0 gives its own ``M_j``). The columns are the n_body transforms M_j, then every
    such (body j, class c) some vertex needs.

    Args:
        weights: (V, n_body) skinning weights; twist: (V, n_class); body_class: (n_body,).
    Returns:
        extra (E, 2) the (body, class) of the columns after the bodies'; columns (V, n_body + E) each
        vertex's weights on the columns.
    """
    V, n_body = weights.shape
    single = (twist != 0).sum(axis=1) == 1
    target = np.where(single, np.argmax(twist, axis=1), 0)
    v, j = np.nonzero(weights)
    other = body_class[j] != target[v]
    extra = np.unique(np.c_[j[other], target[v[other]]], axis=0).reshape(-1, 2)
    column = np.full((n_body, twist.shape[1]), -1, np.int64)
    column[extra[:, 0], extra[:, 1]] = n_body + np.arange(len(extra))
    columns = np.zeros((V, n_body + len(extra)))
    columns[v[~other], j[~other]] = weights[v[~other], j[~other]]
    columns[v[other], column[j[other], target[v[other]]]] = weights[v[other], j[other]]
    return extra, columns


def blended_rest(rest: torch.Tensor, rows: torch.Tensor, weights_t: torch.Tensor) -> torch.Tensor:
    """Rest vertices moved by the normalised dual-quaternion blend of their twist classes (KCvO08,
    algorithm 1): ``(R v + T) / n`` with R, T and the norm n sums over class pairs of the pairs' rows
    weighted by :func:`pair_weights`, applied as LBS applies its matrices.

    Args:
        rest: (B, 1, 4, N) homogeneous rest vertices [x, y, z, 1]; rows: (B, 13, P) the class pairs' rows
            (:func:`pair_rows`); weights_t: (P, N) the vertices' pair weights, transposed.
    Returns:
        (B, 3, N).
    """
    B, N = rest.shape[0], rest.shape[-1]
    numerator = (rows[:, :12] @ weights_t).reshape(B, 3, 4, N)
    return (numerator * rest).sum(2) / (rows[:, 12] @ weights_t).unsqueeze(1)


class RestBlock(nn.Module):
    """One contiguous range of the skin's vertices: the columns that carry them and their weights on
    those columns (:func:`skin_columns`)."""

    columns: torch.Tensor
    weights_t: torch.Tensor

    def __init__(self, columns: np.ndarray, weights_t: np.ndarray, dtype: torch.dtype) -> None:
        """columns (m,); weights_t (m, V_k)."""
        super().__init__()
        self.register_buffer("columns", torch.as_tensor(columns, dtype=torch.long))
        self.register_buffer("weights_t", torch.as_tensor(np.ascontiguousarray(weights_t)).to(dtype))

    def forward(self, rest: torch.Tensor, rows: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """rest (B, 3, V_k); rows: every column's rows from :func:`~bodyfit.models.body.lbs.blend_rows`
        -> (3, B, V_k), coordinates first."""
        return blend_linear(
            rest, self.weights_t, rows[0].index_select(1, self.columns), rows[1].index_select(1, self.columns)
        )


def _compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Rigid maps a after b, component-major (3, 4, ...) each -> (3, 4, ...)."""
    rotation = cm_matmul(a[:, :3], b)  # (3, 4, ...): R_a [R_b | t_b]
    return torch.cat([rotation[:, :3], (rotation[:, 3] + a[:, 3]).unsqueeze(1)], dim=1)


class TwistSkin(nn.Module):
    """The skin under swing-twist skinning: one linear blend over every vertex, in the template's order,
    of rest positions in which the vertices that blend twist classes are first moved by their blend.

    The rest vertices (B, 3, V) = [1, c] @ basis; the vertices that blend classes (a sixth of the template,
    scattered over most of its order) get theirs from :func:`blended_rest` over the class pairs they use,
    written over the template's by one ScatterElements; every vertex is then skinned by LBS over the
    columns of :func:`skin_columns`, in contiguous blocks that each need few columns
    (:func:`~bodyfit.models.body.lbs.blend_blocks`). The twist costs one blend of those vertices, not a
    second LBS of the blocks that hold them.
    """

    pairs: torch.Tensor
    pair_weights_t: torch.Tensor
    body_class: torch.Tensor
    extra: torch.Tensor
    mixed: torch.Tensor
    basis: torch.Tensor
    mixed_basis: torch.Tensor

    def __init__(
        self,
        basis: np.ndarray,
        weights: np.ndarray,
        twist: np.ndarray,
        body_class: np.ndarray,
        dtype: torch.dtype,
        n_blocks: int,
    ) -> None:
        """basis (1 + K, 3, V); weights (V, n_body); twist (V, n_class) twist weights; body_class (n_body,)
        each body's class."""
        super().__init__()
        mixed = np.flatnonzero((twist != 0).sum(axis=1) > 1)
        pairs, pair_w = pair_weights(twist[mixed])
        used = np.flatnonzero((pair_w != 0).any(axis=0))
        extra, columns = skin_columns(weights, twist, body_class)
        homogeneous = np.zeros((len(basis), 4, len(mixed)))
        homogeneous[:, :3] = basis[:, :, mixed]
        homogeneous[0, 3] = 1.0  # [1, c] @ basis: the constant coefficient gives the homogeneous 1
        self.register_buffer("pairs", torch.as_tensor(pairs[used]))
        self.register_buffer(
            "pair_weights_t", torch.as_tensor(np.ascontiguousarray(pair_w[:, used].T)).to(dtype)
        )
        self.register_buffer("body_class", torch.as_tensor(body_class, dtype=torch.long))
        self.register_buffer("extra", torch.as_tensor(extra, dtype=torch.long))
        self.register_buffer("mixed", torch.as_tensor(mixed, dtype=torch.long))
        self.register_buffer("basis", torch.as_tensor(basis.reshape(len(basis), -1)).to(dtype))
        self.register_buffer("mixed_basis", torch.as_tensor(homogeneous.reshape(len(basis), -1)).to(dtype))
        ranges = blend_blocks(columns, n_blocks)
        self.sizes = [b - a for a, b, _ in ranges]
        self.blocks = nn.ModuleList(RestBlock(cols, columns[a:b, cols].T, dtype) for a, b, cols in ranges)

    def forward(self, coeffs: torch.Tensor, transforms: torch.Tensor, twists: torch.Tensor) -> torch.Tensor:
        """coeffs (B, 1 + K); transforms (3, 4, n_body, B): every body's skinning transform M_j,
        component-major; twists (B, 8, n_class): every class's twist dual quaternion -> (B, V, 3)."""
        B, n = coeffs.shape[0], len(self.mixed)
        rigid = class_rigid(twists).reshape(B, 3, 4, -1).permute(1, 2, 3, 0)  # (3, 4, n_class, B)
        swings = swing_transforms(transforms, rigid.index_select(2, self.body_class))
        extra = _compose(swings.index_select(2, self.extra[:, 0]), rigid.index_select(2, self.extra[:, 1]))
        rows = blend_rows(torch.cat([transforms, extra], dim=2))
        rest = (coeffs @ self.basis).reshape(B, 3, -1)
        if n:
            home = (coeffs @ self.mixed_basis).reshape(B, 1, 4, n)
            moved = blended_rest(home, pair_rows(twists, self.pairs), self.pair_weights_t)
            rest = rest.scatter(2, self.mixed.expand(B, 3, n), moved)
        parts = rest.split(self.sizes, dim=2)
        out = torch.cat([block(part, rows) for block, part in zip(self.blocks, parts, strict=True)], dim=2)
        return out.permute(1, 2, 0)
