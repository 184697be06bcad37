"""Batched, differentiable forward kinematics of a :class:`SkeletonSpec` (torch, ONNX-exportable).

Joints follow OpenSim's CustomJoint (Seth et al., "OpenSim: Simulating musculoskeletal dynamics and
neuromuscular control to study human and animal movement", PLoS Computational Biology 14(7), 2018), so the
frames match OpenSim's to float precision. The module holds buffers only. The tree is composed by pointer
jumping (every body at once, about log2(depth) rounds; W. D. Hillis and G. L. Steele, "Data Parallel
Algorithms", Communications of the ACM 29(12), 1986) with constant gather indices, so there is no
data-dependent control flow.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from bodyfit.models.rotations import cm_matmul, cm_matvec, euler_xyz_body_fixed
from bodyfit.models.skeleton.functions import FunctionTable, evaluate_table
from bodyfit.models.skeleton.spec import SkeletonSpec, translation_scale_weights


class Pose(NamedTuple):
    """Output of the forward kinematics.

    frames: (B, n_body, 4, 4) body frames in the world.
    joint_centres: (B, n_joint, 3) origins of the joints' child-side frames in the world.
    """

    frames: torch.Tensor
    joint_centres: torch.Tensor


def _unit(v: tuple[float, float, float]) -> list[float]:
    a = np.asarray(v, np.float64)
    return list(a / np.linalg.norm(a))


def _cm(constant: torch.Tensor) -> torch.Tensor:
    """A per-joint constant in the component-major layout: (J, 3, 3) -> (3, 3, J, 1), (J, 3) -> (3, J, 1)."""
    return constant.permute(*range(1, constant.dim()), 0).unsqueeze(-1)


def pointer_jumps(parents: list[int]) -> list[np.ndarray]:
    """The rounds of pointer jumping that compose a tree's transforms: bodies compose by replacing each
    body's transform (into its current ancestor's frame) by the ancestor's transform composed with it, and
    its ancestor by the ancestor's ancestor; index n (the body count) is the ground (identity).

    Args:
        parents: (n,) each body's parent index, -1 for the root.
    Returns:
        ceil(log2(depth + 1)) arrays (n + 1,): each round's ancestor index per body.
    """
    n = len(parents)
    pointer = np.array([n if p < 0 else p for p in parents] + [n])
    jumps = []
    while (pointer[:n] != n).any():
        jumps.append(pointer)
        pointer = pointer[pointer]
    return jumps


def rodrigues_tables(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rodrigues' R = u u^T + (I - u u^T) cos + [u]x sin, component-major, for every joint's three axes.

    The axis-angle rotation of O. Rodrigues, "Des lois géométriques qui régissent les déplacements d'un
    système solide dans l'espace", Journal de Mathématiques Pures et Appliquées 5, 1840.

    Args:
        axes: (J, 3, 3) unit axis k of joint j.
    Returns:
        u u^T, I - u u^T and [u]x, each (3, 3, 3, J, 1): (axis k, row, column, joint, batch).
    """
    outer = np.einsum("jka,jkb->kabj", axes, axes)[..., None]
    cross = np.zeros((3, 3, 3, len(axes)))
    x, y, z = axes.transpose(2, 1, 0)  # (3, J) each
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -z, y, -x
    cross[:, 1, 0], cross[:, 2, 0], cross[:, 2, 1] = z, -y, x
    return outer, np.eye(3)[None, :, :, None, None] - outer, cross[..., None]


class SkeletonKinematics(nn.Module):
    """Forward kinematics: coordinates (B, n_dof), root translation (B, 3), per-segment scale factors
    (B, n_seg, 3) -> body frames (B, n_body, 4, 4) and joint centres (B, n_joint, 3)."""

    # buffers (see __init__)
    cols: torch.Tensor
    fn_lower: torch.Tensor
    fn_upper: torch.Tensor
    fn_anchor: torch.Tensor
    fn_coef: torch.Tensor
    fn_sine: torch.Tensor
    fn_arc: torch.Tensor
    fn_multi: torch.Tensor
    rot_axes: torch.Tensor
    trans_axes: torch.Tensor
    trans_scale_w: torch.Tensor
    trans_unscaled: torch.Tensor
    p_rot: torch.Tensor
    p_trans: torch.Tensor
    c_rot: torch.Tensor
    c_trans: torch.Tensor
    p_seg: torch.Tensor
    c_seg: torch.Tensor
    f_seg: torch.Tensor
    rot_outer: torch.Tensor
    rot_perp: torch.Tensor
    rot_cross: torch.Tensor

    def __init__(self, spec: SkeletonSpec, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        self.spec = spec
        self.n_dof = len(spec.coordinates)
        self.n_seg = len(spec.segments)
        self.n_body = len(spec.bodies)
        names = [c.name for c in (*spec.coordinates, *spec.root_coordinates)]
        col = {n: i for i, n in enumerate(names)}
        zero_col = len(names)  # q_ext carries a trailing zero column for constant functions
        seg_idx = {s: i for i, s in enumerate(spec.segments)}
        body_seg = spec.body_segment_index

        fns, cols = [], []
        rot_axes, trans_axes, trans_w = [], [], []
        for j in spec.joints:
            for ax in (*j.rotations, *j.translations):
                fns.append(ax.function)
                cols.append(zero_col if ax.coordinate is None else col[ax.coordinate])
            rot_axes.append([_unit(a.axis) for a in j.rotations])
            trans_axes.append([_unit(a.axis) for a in j.translations])
            trans_w.append([translation_scale_weights(a.axis, a.function) for a in j.translations])
        table = FunctionTable.compile(fns)

        parents = spec.body_parent_index
        self._jumps = [torch.as_tensor(j) for j in pointer_jumps(parents)]

        def buf(name: str, value: np.ndarray | torch.Tensor, as_dtype: bool = True) -> None:
            t = torch.as_tensor(value)
            self.register_buffer(name, t.to(dtype) if as_dtype else t, persistent=False)

        buf("cols", np.array(cols), as_dtype=False)
        for k, v in table.__dict__.items():
            buf(f"fn_{k}", v, as_dtype=k != "multi")
        axes = np.array(rot_axes, np.float64)  # (J, 3, 3): axis k of joint j
        buf("rot_axes", axes)
        outer, perp, cross = rodrigues_tables(axes)
        buf("rot_outer", outer)
        buf("rot_perp", perp)
        buf("rot_cross", cross)
        buf("trans_axes", np.array(trans_axes, np.float64))  # (J, 3, 3)
        # Translation function k is multiplied by w_k . s (see translation_scale_weights); 1 if unscaled.
        w = np.array(trans_w, np.float64)  # (J, 3, 3)
        buf("trans_scale_w", w)
        buf("trans_unscaled", (w.sum(-1) == 0).astype(np.float64))
        po = [j.parent_offset for j in spec.joints]
        co = [j.child_offset for j in spec.joints]
        buf("p_rot", euler_xyz_body_fixed(np.array([o.orientation for o in po])))
        buf("p_trans", np.array([o.translation for o in po], np.float64))
        buf("c_rot", euler_xyz_body_fixed(np.array([o.orientation for o in co])))
        buf("c_trans", np.array([o.translation for o in co], np.float64))
        # Scale segments: parent offsets scale with the parent body's segment, child offsets with the
        # child's, translation functions with the joint's scale segment along each axis expressed in F.
        buf("p_seg", np.array([body_seg[p] if p >= 0 else -1 for p in parents]), as_dtype=False)
        buf("c_seg", np.array(body_seg), as_dtype=False)
        buf("f_seg", np.array([seg_idx.get(j.scale_segment, -1) for j in spec.joints]), as_dtype=False)

    def forward(
        self, q: torch.Tensor, root: torch.Tensor | None = None, scales: torch.Tensor | None = None
    ) -> Pose:
        """Args:
            q: (B, n_dof) coordinates in the spec's order (radians / metres).
            root: (B, 3) global translation, or None for zeros.
            scales: (B, n_seg, 3) per-segment scale factors, or None for ones.
        Returns:
            :class:`Pose`.
        """
        frames, child_offsets = self._compose(q, root, scales)
        centres = frames[:3, 3] + cm_matvec(frames[:3, :3], child_offsets)
        return Pose(frames.permute(3, 2, 0, 1).contiguous(), centres.permute(2, 1, 0).contiguous())

    def _scale_factors(
        self, scales: torch.Tensor | None, q: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Scale factors of the parent offsets, child offsets and translation functions, (3, J, B) each
        (or (3, 1, 1) ones). The ground (segment index -1) is never scaled."""
        if scales is None:
            ones = q.new_ones(3, 1, 1)
            return ones, ones, ones
        padded = torch.cat([scales, scales.new_ones(scales.shape[0], 1, 3)], dim=1).permute(2, 1, 0)
        return padded[:, self.p_seg], padded[:, self.c_seg], padded[:, self.f_seg]

    def frames_cm(
        self, q: torch.Tensor, root: torch.Tensor | None = None, scales: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Body frames in the world, component-major: (4, 4, n_body, B) (see
        :func:`~bodyfit.models.rotations.cm_matmul`); arguments as :meth:`forward`."""
        return self._compose(q, root, scales)[0]

    def _compose(
        self, q: torch.Tensor, root: torch.Tensor | None, scales: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """World frames (4, 4, n_body, B) and the scaled child offsets (3, J, B), component-major."""
        B = q.shape[0]
        if root is None:
            root = q.new_zeros(B, 3)
        q_ext = torch.cat([q, root, q.new_zeros(B, 1)], dim=-1)
        x = q_ext[:, self.cols]
        f = evaluate_table(
            x,
            self.fn_lower,
            self.fn_upper,
            self.fn_anchor,
            self.fn_coef,
            self.fn_sine,
            self.fn_arc,
            self.fn_multi,
        )
        # Everything below is component-major: (3, 3, J, B) matrices, (3, J, B) vectors.
        f = f.reshape(B, len(self.spec.joints), 6).permute(2, 1, 0)
        theta, d = f[:3], f[3:]  # (3, J, B) each
        s_p, s_c, s_f = self._scale_factors(scales, q)

        # Joint transform X_FM: body-fixed rotations about the three axes in turn; translations along
        # axes given in F, scaled with the joint's scale segment (OpenSim: the parent body).
        c, s = torch.cos(theta)[:, None, None], torch.sin(theta)[:, None, None]
        Rk = self.rot_outer + self.rot_perp * c + self.rot_cross * s  # (axis, 3, 3, J, B)
        R = cm_matmul(cm_matmul(Rk[0], Rk[1]), Rk[2])
        k = cm_matvec(_cm(self.trans_scale_w), s_f) + _cm(self.trans_unscaled)
        p = cm_matvec(_cm(self.trans_axes).transpose(0, 1), d * k)

        # Child-in-parent: X_pofs @ X_FM @ inv(X_cofs), offset translations scaled by their segments.
        Rc_T = _cm(self.c_rot).transpose(0, 1)
        P = _cm(self.p_rot)
        R_loc = cm_matmul(cm_matmul(P, R), Rc_T)
        child_offsets = _cm(self.c_trans) * s_c
        t_loc = cm_matvec(P, p - cm_matvec(R, cm_matvec(Rc_T, child_offsets)))
        t_loc = t_loc + _cm(self.p_trans) * s_p

        # Local transforms (child body in parent body, 4 x 4) and the ground, composed down the tree.
        top = torch.cat([R_loc, t_loc.unsqueeze(1)], dim=1)  # (3, 4, J, B)
        eye = torch.eye(4, dtype=q.dtype, device=q.device)[:, :, None, None]
        bottom = torch.zeros_like(top[:1]) + eye[3:]
        frames = torch.cat([torch.cat([top, bottom]), eye.expand(4, 4, 1, B)], dim=2)
        for pointer in self._jumps:
            frames = cm_matmul(frames[:, :, pointer], frames)
        return frames[:, :, : self.n_body], child_offsets
