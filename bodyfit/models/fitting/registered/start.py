"""A registered fit's start: each body's own rigid motion (Kabsch, "A solution for the best rotation to
relate two sets of vectors", Acta Crystallographica A, 1976), then the coordinates that give the bodies those
orientations (inverse kinematics on rotations)."""

from __future__ import annotations

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.registered.stages import rigid_parts
from bodyfit.models.rotations import kabsch, zxy_angles
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS


class BoneStart:
    """Starting coordinates of registered meshes from their bodies' rigid motions. Build once per model and
    dtype; holds no per-fit state."""

    def __init__(self, model: BodyModel, dtype: torch.dtype) -> None:
        self.model = model
        self.dtype = dtype
        skel = model.skeleton
        self.pelvis = [skel.dof_index(n) for n in PELVIS_ROTATIONS]
        # Bodies with enough of their own skin for a rigid fit, and those vertices.
        self._part_bodies, self._part_index = rigid_parts(model.data["weights"])
        # (n_body, 4, 4) the mean body's bind pose, float64
        mean_scales = torch.as_tensor(np.asarray(model.data["scale_mean"], np.float64))[None]
        bind_q = torch.as_tensor(model.bind_coordinates)[None]
        self._bind_frames = skel.kinematics(torch.float64)(bind_q, None, mean_scales).frames[0].numpy()

    def __call__(self, x: np.ndarray, w: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates (B, n_dof) and root (B, 3) of meshes x (B, V, 3) in the template's vertex order, with
        weights w (B, V), from each body's own rigid motion.

        Every skinned body's vertices are aligned rigidly (Kabsch) from the template to the target, giving
        the body's world orientation. The pelvis frame gives the root and the pelvis coordinates (intrinsic
        ZXY Euler angles = tilt, list, rotation) directly; the other coordinates are fitted to the bodies'
        orientations (inverse kinematics on rotations, in range: L-BFGS, Liu and Nocedal, "On the limited
        memory BFGS method for large scale optimization", Mathematical Programming, 1989). This sees each
        joint's rotation directly, so large rotations (a raised arm, a deep squat) do not trap the vertex fit
        in a wrong pose.
        """
        B = len(x)
        dtype = self.dtype
        skel = self.model.skeleton
        bind = self._bind_frames
        template = self.model.data["vertices_mean"]
        target = np.zeros((B, len(self._part_bodies), 4, 4))
        for k, (body, idx) in enumerate(zip(self._part_bodies, self._part_index, strict=True)):
            R, t = kabsch(template[idx], x[:, idx], w[:, idx] + 1e-12)
            target[:, k, :3, :3] = R @ bind[body, :3, :3]
            target[:, k, :3, 3] = np.einsum("bij,j->bi", R, bind[body, :3, 3]) + t
        pelvis = target[:, self._part_bodies.index(0)]
        lo, hi = skel.ranges[:, 0], skel.ranges[:, 1]
        q = np.repeat(self.model.bind_coordinates[None], B, axis=0)
        q[:, self.pelvis] = zxy_angles(pelvis[:, :3, :3])
        q = skel.inside(q, 0.1)
        q[:, self.pelvis] = np.clip(q[:, self.pelvis], lo[self.pelvis] + 1e-3, hi[self.pelvis] - 1e-3)
        root = torch.as_tensor(pelvis[:, :3, 3], dtype=dtype)
        free = torch.ones(skel.n_dof, dtype=dtype)
        free[self.pelvis] = 0.0
        u = skel.to_unbounded(torch.as_tensor(q, dtype=dtype)).requires_grad_(True)
        scales = torch.as_tensor(self.model.data["scale_mean"], dtype=dtype).expand(B, -1, -1)
        bodies = torch.as_tensor(self._part_bodies)
        R_target = torch.as_tensor(target[..., :3, :3], dtype=dtype)
        fk = skel.kinematics(dtype)
        opt = torch.optim.LBFGS(
            [u], max_iter=iterations, history_size=20, tolerance_grad=1e-10, line_search_fn="strong_wolfe"
        )

        def closure() -> torch.Tensor:
            opt.zero_grad()
            u_eff = u * free + u.detach() * (1 - free)
            F = fk(skel.from_unbounded(u_eff), root, scales).frames[:, bodies]
            loss = ((F[..., :3, :3] - R_target) ** 2).sum()
            loss.backward()
            return loss

        opt.step(closure)
        return skel.from_unbounded(u).detach().double().numpy(), root.double().numpy()
