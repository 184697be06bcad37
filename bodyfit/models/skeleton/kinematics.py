"""Batched, differentiable forward kinematics of a :class:`SkeletonSpec` (torch, ONNX-exportable).

The module holds buffers only. The tree is composed level by level (all bodies of one depth at once) with
constant gather indices, so there is no data-dependent control flow.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from bodyfit.models.rotations import axis_angle_matrix, euler_xyz_body_fixed
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


def _levels(parents: list[int]) -> list[list[int]]:
    depth: list[int] = []
    for i, p in enumerate(parents):
        depth.append(0 if p < 0 else depth[p] + 1)
        assert p < i, "joints must be in topological order"
    return [[i for i, d in enumerate(depth) if d == lvl] for lvl in range(max(depth) + 1)]


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
    inv_order: torch.Tensor

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
        levels = _levels(parents)
        order = [i for lvl in levels for i in lvl]  # concatenation order of the level outputs
        pos_in_order = {b: k for k, b in enumerate(order)}
        self._levels = [torch.tensor(lvl) for lvl in levels]
        self._level_parents = [torch.tensor([pos_in_order.get(parents[i], 0) for i in lvl]) for lvl in levels]
        self._has_parent = [parents[lvl[0]] >= 0 for lvl in levels]
        assert all(all((parents[i] >= 0) == hp for i in lvl) for lvl, hp in zip(levels, self._has_parent))

        def buf(name: str, value: np.ndarray | torch.Tensor, as_dtype: bool = True) -> None:
            t = torch.as_tensor(value)
            self.register_buffer(name, t.to(dtype) if as_dtype else t, persistent=False)

        buf("cols", np.array(cols), as_dtype=False)
        for k, v in table.__dict__.items():
            buf(f"fn_{k}", v)
        buf("rot_axes", np.array(rot_axes, np.float64))  # (J, 3, 3)
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
        buf("inv_order", torch.as_tensor(np.argsort(order)), as_dtype=False)

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
        B = q.shape[0]
        if root is None:
            root = q.new_zeros(B, 3)
        q_ext = torch.cat([q, root, q.new_zeros(B, 1)], dim=-1)
        x = q_ext[:, self.cols]
        f = evaluate_table(
            x, self.fn_lower, self.fn_upper, self.fn_anchor, self.fn_coef, self.fn_sine, self.fn_arc
        )
        f = f.reshape(B, len(self.spec.joints), 6)
        theta, d = f[..., :3], f[..., 3:]  # (B, J, 3) each

        # Scale factors: ground (index -1) is never scaled.
        if scales is None:
            s_p = s_c = s_f = q.new_ones(1, 1, 3)
        else:
            padded = torch.cat([scales, scales.new_ones(B, 1, 3)], dim=1)
            s_p, s_c, s_f = padded[:, self.p_seg], padded[:, self.c_seg], padded[:, self.f_seg]

        # Joint transform X_FM: body-fixed rotations; translations along axes given in F.
        Rk = axis_angle_matrix(self.rot_axes, theta)  # (B, J, 3, 3, 3): one matrix per axis
        R = Rk[:, :, 0] @ Rk[:, :, 1] @ Rk[:, :, 2]
        # Translation functions scale with the joint's scale segment (OpenSim: the parent body).
        k = torch.einsum("jkc,bjc->bjk", self.trans_scale_w, s_f.expand(B, len(self.spec.joints), 3))
        p = torch.einsum("bjk,jkc->bjc", d * (k + self.trans_unscaled), self.trans_axes)

        # Child-in-parent: X_pofs @ X_FM @ inv(X_cofs), offset translations scaled by their segments.
        tp = self.p_trans * s_p
        tc = self.c_trans * s_c
        Rc_T = self.c_rot.transpose(-1, -2)
        R_loc = self.p_rot @ R @ Rc_T
        t_fm = p - (R @ (Rc_T @ tc.unsqueeze(-1))).squeeze(-1)  # X_FM @ inv(X_cofs), translation part
        t_loc = (self.p_rot @ t_fm.unsqueeze(-1)).squeeze(-1) + tp

        # Compose level by level.
        Rw: torch.Tensor | None = None
        tw: torch.Tensor | None = None
        for lvl, par, has_parent in zip(self._levels, self._level_parents, self._has_parent):
            R_l, t_l = R_loc[:, lvl], t_loc[:, lvl]
            if has_parent:
                assert Rw is not None and tw is not None
                Rp, tpw = Rw[:, par], tw[:, par]
                t_l = (Rp @ t_l.unsqueeze(-1)).squeeze(-1) + tpw
                R_l = Rp @ R_l
            Rw = R_l if Rw is None else torch.cat([Rw, R_l], dim=1)
            tw = t_l if tw is None else torch.cat([tw, t_l], dim=1)
        assert Rw is not None and tw is not None
        Rw, tw = Rw[:, self.inv_order], tw[:, self.inv_order]

        centres = tw + (Rw @ tc.expand(B, -1, -1).unsqueeze(-1)).squeeze(-1)
        top = torch.cat([Rw, tw.unsqueeze(-1)], dim=-1)
        bottom = torch.zeros_like(top[..., :1, :])
        bottom = bottom + torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=q.dtype, device=q.device)
        return Pose(torch.cat([top, bottom], dim=-2), centres)
