"""A sequence's frames of reference and per-frame arrays: each frame's heading and canonical frame
(:class:`Headings`, :func:`turn`), the way back to the world (:func:`to_world`), the blend of the joint
coordinates (:func:`blend_joints`), the pelvis angles unwrapped along time block by block
(:class:`PelvisUnwrap`), and what the frame pass fills in (:class:`FrameArrays`)."""

from __future__ import annotations

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.sequence.config import PELVIS_WEIGHT
from bodyfit.models.fitting.sequence.stats import FrameTotals
from bodyfit.models.rotations import kabsch, zxy_angles


def yaw(angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations about +Y by angle (T,)."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    return R


def turn(x: np.ndarray, G: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Points x (T, N, 3) into their frames' canonical frames: G (T, 3, 3) applied about origin (T, 3)."""
    return (x - origin[:, None]) @ np.swapaxes(G, -1, -2)  # batched BLAS


def zxy_matrix(a: np.ndarray) -> np.ndarray:
    """(T, 3, 3) ``Rz(a0) Rx(a1) Ry(a2)`` of intrinsic ZXY angles a (T, 3) (the pelvis's tilt, list and
    rotation)."""
    cz, sz = np.cos(a[:, 0]), np.sin(a[:, 0])
    cx, sx = np.cos(a[:, 1]), np.sin(a[:, 1])
    one, zero = np.ones_like(cz), np.zeros_like(cz)
    Rz = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    Rx = np.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).reshape(-1, 3, 3)
    return Rz @ Rx @ yaw(a[:, 2])


def to_world(
    q: np.ndarray, root: np.ndarray, G: np.ndarray, origin: np.ndarray, pelvis_dofs: list[int]
) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates q (k, n_dof) and roots (k, 3) of canonical frames (G (k, 3, 3), origin (k, 3)) in the
    world: the root and the pelvis's orientation (its ZXY angles at ``pelvis_dofs``) turned back, the
    pelvis angles in range, not yet unwrapped. Skinned, they give the canonical skin turned back."""
    Gt = np.swapaxes(G, -1, -2)
    out = q.copy()
    out[:, pelvis_dofs] = zxy_angles(Gt @ zxy_matrix(q[:, pelvis_dofs]))
    return out, np.einsum("tij,tj->ti", Gt, root) + origin


def blend_joints(q: np.ndarray, lo: int, hi: int, b: float, joints: np.ndarray) -> np.ndarray:
    """Rows lo:hi of q (T, n_dof) after the centred three-frame blend of weight b of the coordinates
    ``joints`` (:class:`.config.SequenceConfig`): ``q[t] <- (1 - 2 b) q[t] + b (q[t-1] + q[t+1])``. The
    first and last frames and the other coordinates are kept; rows lo - 1 and hi of q must be final."""
    out = q[lo:hi].copy()
    inner = np.arange(max(lo, 1), min(hi, len(q) - 1))
    if b == 0.0 or len(inner) == 0:
        return out
    rows = inner - lo
    out[np.ix_(rows, joints)] = (1.0 - 2.0 * b) * q[np.ix_(inner, joints)] + b * (
        q[np.ix_(inner - 1, joints)] + q[np.ix_(inner + 1, joints)]
    )
    return out


def unwrap_correction(dd: np.ndarray) -> np.ndarray:
    """The corrections (k,) that :func:`numpy.unwrap` (period 2 pi) adds for the angle steps dd (k,): the
    multiple of 2 pi that brings each step into [-pi, pi], 0 where the step is already below pi."""
    ddmod = np.mod(dd + np.pi, 2 * np.pi) - np.pi
    np.copyto(ddmod, np.pi, where=(ddmod == -np.pi) & (dd > 0))
    correct = ddmod - dd
    np.copyto(correct, 0, where=abs(dd) < np.pi)
    return correct


class PelvisUnwrap:
    """The pelvis angles unwrapped along time (no 2 pi jumps between frames), fed block by block in time
    order: the same numbers as :func:`numpy.unwrap` of the whole sequence, to the bit (each block carries the
    running sum of the corrections on, adding in the same order)."""

    def __init__(self, pelvis_dofs: list[int]) -> None:
        self.dofs = pelvis_dofs
        self._last: np.ndarray | None = None  # (3,) the previous block's last angles, as given
        self._carry = np.zeros(len(pelvis_dofs))  # (3,) the corrections' running sum at that frame

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """The next frames' coordinates q (k, n_dof), pelvis angles in range, with those angles unwrapped
        (float64, a copy)."""
        out = np.array(q, np.float64, copy=True)
        if not len(q):
            return out
        for j, k in enumerate(self.dofs):
            p = out[:, k].copy()
            if self._last is None:
                running = unwrap_correction(np.diff(p)).cumsum()
                out[1:, k] = p[1:] + running
            else:
                steps = np.diff(np.r_[self._last[j], p])
                running = np.r_[self._carry[j], unwrap_correction(steps)].cumsum()[1:]
                out[:, k] = p + running
            if len(running):
                self._carry[j] = running[-1]
        self._last = np.asarray(q, np.float64)[-1, self.dofs].copy()
        return out


class Headings:
    """Each frame's heading about +Y and pelvis origin, from a rigid fit (Kabsch, "A solution for the best
    rotation to relate two sets of vectors", Acta Crystallographica A, 1976) of the pelvis's own skin."""

    def __init__(self, model: BodyModel) -> None:
        self.model = model
        self.pelvis_vertices = np.flatnonzero(model.data["weights"][:, 0] > PELVIS_WEIGHT)
        fk = model.skeleton.kinematics(torch.float64)
        scales = torch.as_tensor(model.data["scale_mean"], dtype=torch.float64)[None]
        bind_q = torch.as_tensor(model.bind_coordinates, dtype=torch.float64)[None]
        # (4, 4) the mean body's pelvis frame in the template's pose
        self._pelvis_bind = fk(bind_q, None, scales).frames[0, 0].numpy()

    def __call__(self, x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame heading (T,) radians about +Y, unwrapped over time, and pelvis origin (T, 3), of frames
        x (T, V, 3) with weights w (T, V)."""
        idx = self.pelvis_vertices
        template = self.model.data["vertices_mean"][idx]
        R, t = kabsch(template, x[:, idx], w[:, idx] + 1e-12)
        bind = self._pelvis_bind
        forward = R @ bind[:3, 0]  # the pelvis's +X in the world
        origin = np.einsum("tij,j->ti", R, bind[:3, 3]) + t
        return np.unwrap(np.arctan2(-forward[:, 2], forward[:, 0])), origin


class FrameArrays:
    """What the frame pass fills in chunk by chunk, for T frames: canonical-frame poses q_c (T, n_dof) and
    root_c (T, 3); blended world poses q (T, n_dof), pelvis angles in range, and root (T, 3); the same poses
    with the pelvis angles unwrapped, coordinates (T, n_dof); canonical frames G (T, 3, 3) and origin (T, 3);
    skins verts (T, V, 3) float32 (None unless kept); joints (T, n_joints, 3); totals."""

    def __init__(self, T: int, model: BodyModel, keep_vertices: bool, pelvis_dofs: list[int]) -> None:
        n_dof = model.skeleton.n_dof
        self.q_c, self.root_c = np.empty((T, n_dof)), np.empty((T, 3))
        self.q, self.root = np.empty((T, n_dof)), np.empty((T, 3))  # blended, in the world
        self.coordinates = np.empty((T, n_dof))
        self.G, self.origin = np.empty((T, 3, 3)), np.empty((T, 3))
        self.verts = np.empty((T, model.n_vertices, 3), np.float32) if keep_vertices else None
        self.joints = np.empty((T, len(model.joint_names), 3))
        self.totals = FrameTotals()
        self.unwrap = PelvisUnwrap(pelvis_dofs)
