"""Fit the body model to meshes in its own topology (registered meshes), batched.

Staged as in BLSM (paper 000, section 5.2): a rigid start from the trunk (Kabsch), then the trunk's pose and
the bone-length coefficients on trunk vertices, then every coordinate on a spread vertex subset, then
everything including identity shape, and a last pass on all vertices. Each stage minimises

    sum_b [ mean_v w_bv |v_bv(c_b, q_b, r_b) - x_bv|^2 (mm^2) + lambda |c_b|^2 ]

by L-BFGS over unconstrained coordinates ``u`` (``q = from_unbounded(u)``, BLSM eq. 6), so every pose it
returns respects the joint limits. The model holds buffers only; the optimisation state lives here.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.lbfgs import batched_lbfgs
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.rotations import kabsch, zxy_angles
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS, check_finite

TRUNK_BODIES = ("pelvis", "torso", "thoracic_link", "thorax")
TRUNK_DOF_PREFIXES = ("pelvis_", "lumbar_", "thorax_")
# The trunk and the legs' flexion: a seated or crouching body's pose, which the trunk alone can only mimic
# by bending the spine.
CORE_DOF_PREFIXES = (*TRUNK_DOF_PREFIXES, "hip_flexion_", "knee_angle_")
# A head-and-shoulders capture: the mean body's vertices this far below the top of its head (head, neck,
# shoulders and upper chest), and the DOFs that place them (the trunk's, the neck's and the scapulae's).
UPPER_BODY_M = 0.55
UPPER_DOF_PREFIXES = (*TRUNK_DOF_PREFIXES, "neck_", "scapula_")
CONFIDENT_MEAN_MM = 10.0
MIN_PART_WEIGHT = 0.7  # a vertex belongs to a body's rigid part above this skinning weight
MIN_PART_VERTICES = 20

State = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # preconditioned (u, root, shape), see start_state
DataTerm = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class Stage:
    """One fitting stage.

    coordinates: "trunk" (pelvis, lumbar, thoracic DOFs), "core" (those and the hips' and knees' flexion),
    "upper" (the trunk's, the neck's and the scapulae's) or "all"; shape: "none", "bone" or "all";
    vertices: "trunk", "coarse", "subset" or "dense" (farthest-point subsets of the whole body, nested),
    "upper" (head, neck, shoulders and upper chest: :data:`UPPER_BODY_M`) or "all";
    iterations: L-BFGS iterations; metric: None, or the vertex set whose Gauss-Newton metric
    (:meth:`RegisteredFitter.metric`, at the stage's start) the stage's L-BFGS runs in.
    """

    name: str
    coordinates: str
    shape: str
    vertices: str
    iterations: int
    metric: str | None = None


# The last two stages run in the Gauss-Newton metric of the 200-vertex subset: on the 200 held-out bodies of
# benchmarks/fit_registered.py, 25 + 5 iterations so gave 1.50 mm at 40 ms per mesh against 1.83 mm at 45 ms
# for 80 + 10 plain ones (the 1,000-vertex subset's metric costs more than the iterations it saves).
DEFAULT_STAGES = (
    Stage("trunk", "trunk", "bone", "trunk", 10),
    Stage("limbs", "all", "none", "subset", 20),
    Stage("all", "all", "all", "subset", 25, metric="coarse"),
    Stage("refine", "all", "all", "all", 5, metric="coarse"),
)
# The damping of the stages' metrics (``regularise`` of :meth:`RegisteredFitter.metric`): with 1e-3 the first
# (Newton) step took one of six bodies of the model, turned anywhere, into a wrong minimum (3.6 mm against
# 0.6 mm without the metric); with 3e-3 all six end within 0.4 mm.
STAGE_METRIC_DAMPING = 3e-3


@dataclass(frozen=True)
class RegisteredFitConfig:
    """stages: run in order; dense_size, subset_size, coarse_size: vertices of the farthest-point subsets
    "dense", "subset" and "coarse" (the first ones of the same sample); shape_prior: weight of
    |c|^2 (coefficients are in population standard deviations) against the loss in mm^2."""

    stages: tuple[Stage, ...] = DEFAULT_STAGES
    dense_size: int = 6500
    subset_size: int = 1000
    coarse_size: int = 200
    shape_prior: float = 1e-2
    dtype: torch.dtype = torch.float32


@dataclass(frozen=True)
class BodyFit:
    """Fitted parameters and the registration, batch first.

    shape: (B, n_shape); coordinates: (B, n_dof) in range; root: (B, 3); vertices: (B, V, 3) the model
    at the fitted parameters (the registration in our topology); joints: (B, J, 3); reports: B reports.
    """

    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    reports: list[FitReport] = field(default_factory=list)


def vertex_term(targets_mm: torch.Tensor, weights: torch.Tensor) -> DataTerm:
    """The registered data term: weighted mean squared vertex distance (B,) in mm^2, for targets (B, V', 3)
    in mm and weights (B, V') (mean one)."""

    def term(verts_mm: torch.Tensor) -> torch.Tensor:
        return (((verts_mm - targets_mm) ** 2).sum(-1) * weights).mean(1)

    return term


def farthest_point_subset(points: np.ndarray, n: int) -> np.ndarray:
    """Indices (n,) of a farthest-point sample of points (V, 3), starting from the point nearest the mean.
    Each pick lowers the distances of the points within the current largest distance of it only (a ball
    query), 10x faster than updating all at 5,000 of 13,000 vertices, with the same picks."""
    n = min(n, len(points))
    chosen = np.empty(n, np.int64)
    chosen[0] = int(np.argmin(np.linalg.norm(points - points.mean(0), axis=1)))
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    tree = cKDTree(points)
    for k in range(1, n):
        c = chosen[k] = int(np.argmax(dist))
        near = np.asarray(tree.query_ball_point(points[c], dist[c]), np.int64)
        dist[near] = np.minimum(dist[near], np.linalg.norm(points[near] - points[c], axis=1))
    return chosen


class RegisteredFitter:
    """Fits :class:`BodyModel` to (B, V, 3) meshes in its topology. Reusable and stateless between calls."""

    def __init__(self, model: BodyModel, config: RegisteredFitConfig | None = None) -> None:
        self.model = model
        self.config = config or RegisteredFitConfig()
        dtype = self.config.dtype
        skel = model.skeleton
        self.decoder = model.decoder(dtype)
        template = model.data["vertices_mean"]
        body_of_vertex = np.argmax(model.data["weights"], axis=1)
        trunk_ids = [skel.body_names.index(b) for b in TRUNK_BODIES]
        cfg = self.config
        spread = farthest_point_subset(template, max(cfg.dense_size, cfg.subset_size, cfg.coarse_size))
        self.index = {
            "trunk": np.flatnonzero(np.isin(body_of_vertex, trunk_ids)),
            "dense": np.sort(spread[: cfg.dense_size]),
            "subset": np.sort(spread[: cfg.subset_size]),
            "coarse": np.sort(spread[: cfg.coarse_size]),
            "upper": np.flatnonzero(template[:, 1] > template[:, 1].max() - UPPER_BODY_M),
            "all": np.arange(model.n_vertices),
        }
        self.decoders = self._decoders_of(self.decoder)
        self.dof_mask = {
            name: torch.as_tensor([n.startswith(prefixes) for n in skel.dof_names], dtype=dtype)
            for name, prefixes in (
                ("trunk", TRUNK_DOF_PREFIXES),
                ("core", CORE_DOF_PREFIXES),
                ("upper", UPPER_DOF_PREFIXES),
            )
        }
        self.dof_mask["all"] = torch.ones(skel.n_dof, dtype=dtype)
        nb, ns = model.n_bone, model.n_shape
        self.shape_mask = {
            "none": torch.zeros(ns, dtype=dtype),
            "bone": torch.as_tensor(np.arange(ns) < nb, dtype=dtype),
            "all": torch.ones(ns, dtype=dtype),
        }
        self.pelvis = [skel.dof_index(n) for n in PELVIS_ROTATIONS]
        # Bodies with enough of their own skin for a rigid fit, and those vertices.
        W = model.data["weights"]
        self._part_bodies: list[int] = []
        self._part_index: list[np.ndarray] = []
        for j in range(W.shape[1]):
            own = np.flatnonzero(W[:, j] > MIN_PART_WEIGHT)
            if len(own) >= MIN_PART_VERTICES:
                self._part_bodies.append(j)
                self._part_index.append(own)
        # (n_body, 4, 4) the mean body's bind pose, float64
        mean_scales = torch.as_tensor(np.asarray(model.data["scale_mean"], np.float64))[None]
        bind_q = torch.as_tensor(model.bind_coordinates)[None]
        self._bind_frames = skel.kinematics(torch.float64)(bind_q, None, mean_scales).frames[0].numpy()
        self._scales = self._preconditioner()

    def _decoders_of(self, decoder: BodyDecoder) -> dict[str, BodyDecoder]:
        """``decoder`` restricted to each vertex set of :attr:`index`."""
        return {k: decoder if k == "all" else decoder.restricted(v) for k, v in self.index.items()}

    def with_offsets(self, offsets: np.ndarray) -> RegisteredFitter:
        """This fitter for one person whose template carries rest-pose offsets (V, 3) metres (see
        :meth:`BodyDecoder.with_offsets`); the preconditioning and settings are shared."""
        fitter = copy.copy(self)
        fitter.decoder = self.model.decoder(self.config.dtype).with_offsets(offsets)
        fitter.decoders = self._decoders_of(fitter.decoder)
        return fitter

    # -- input -----------------------------------------------------------------------------------------
    def validate(
        self,
        targets: np.ndarray | torch.Tensor,
        weights: np.ndarray | None,
        dtype: type[np.floating] = np.float64,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(B, V, 3) targets as an array of ``dtype`` (no copy when they already are one) and (B, V) weights,
        float64; raises ShapeError / NonFiniteError."""
        x: np.ndarray = np.asarray(targets, dtype)
        V = self.model.n_vertices
        if x.ndim == 2:
            x = x[None]
        if x.ndim != 3 or x.shape[1:] != (V, 3):
            raise ShapeError(
                f"registered meshes must have shape (B, {V}, 3) (our template's vertices in its order, "
                f"metres); got {x.shape}. Fit other topologies as scans or through a stored correspondence."
            )
        check_finite("mesh vertices", x)
        w = np.ones(x.shape[:2]) if weights is None else np.asarray(weights, np.float64)
        if w.shape != x.shape[:2]:
            raise ShapeError(f"vertex weights must have shape {x.shape[:2]}; got {w.shape}")
        check_finite("vertex weights", w)
        if (w < 0).any() or (w.sum(axis=1) <= 0).any():
            raise ShapeError("vertex weights must be non-negative with at least one positive weight per mesh")
        return x, w

    # -- start -----------------------------------------------------------------------------------------
    def bone_start(self, x: np.ndarray, w: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates (B, n_dof) and root (B, 3) from each body's own rigid motion.

        Every skinned body's vertices are aligned rigidly (Kabsch) from the template to the target, giving
        the body's world orientation. The pelvis frame gives the root and the pelvis coordinates (intrinsic
        ZXY Euler angles = tilt, list, rotation) directly; the other coordinates are fitted to the bodies'
        orientations (inverse kinematics on rotations, L-BFGS, in range). This sees each joint's rotation
        directly, so large rotations (a raised arm, a deep squat) do not trap the vertex fit in a wrong pose.
        """
        B = len(x)
        dtype = self.config.dtype
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

    # -- fit -------------------------------------------------------------------------------------------
    def fit(
        self,
        targets: np.ndarray | torch.Tensor,
        weights: np.ndarray | None = None,
        init: BodyFit | None = None,
        shared_shape: bool = False,
    ) -> BodyFit:
        """Fit B meshes.

        Args:
            targets: (B, V, 3) vertices in our template's order, metres, any placement.
            weights: (B, V) per-vertex confidence (0 = missing), default ones.
            init: a previous fit to start from (warm start), instead of the rigid start.
            shared_shape: one shape for all B meshes (a sequence of one person).
        Returns:
            :class:`BodyFit` with one report per mesh.
        """
        start = time.perf_counter()
        x, w = self.validate(targets, weights)
        B = len(x)
        dtype = self.config.dtype
        if init is None:
            q0, r0 = self.bone_start(x, w)
            c0 = np.zeros((B, self.model.n_shape))
        else:
            q0, r0, c0 = init.coordinates, init.root, init.shape
        z = self.start_state(q0, r0, c0.mean(0, keepdims=True) if shared_shape else c0)
        xt = torch.as_tensor(x, dtype=dtype)
        wt = torch.as_tensor(w / w.mean(axis=1, keepdims=True), dtype=dtype)
        iterations = 0
        losses: dict[str, float] = {}
        for stage in self.config.stages:
            idx = torch.as_tensor(self.index[stage.vertices])
            metric = None
            if stage.metric is not None:
                metric = self.metric(stage, z, stage.metric, regularise=STAGE_METRIC_DAMPING)
            n_iter, loss = self.optimise(stage, z, vertex_term(xt[:, idx] * 1000.0, wt[:, idx]), metric)
            iterations += n_iter
            losses[stage.name] = loss
        c, q, root = self.parameters(z)
        with torch.no_grad():
            verts, joints, _, _ = self.decoder(c.to(dtype), q.to(dtype), root.to(dtype))
        seconds = time.perf_counter() - start
        v_np = verts.double().numpy()
        q_np = q.numpy()
        dist = np.linalg.norm(v_np - x, axis=-1)
        reports = [self._report(dist[b], w[b], q_np[b], iterations, seconds / B, losses) for b in range(B)]
        return BodyFit(c.numpy(), q_np, root.numpy(), v_np, joints.double().numpy(), reports)

    # -- optimisation state ----------------------------------------------------------------------------
    def start_state(self, q0: np.ndarray, r0: np.ndarray, c0: np.ndarray) -> State:
        """The optimisation state for coordinates q0 (B, n_dof) (moved inside the limits), root r0 (B, 3) and
        shape c0 (B or 1, n_shape) (one row: a shape shared by the batch)."""
        dtype = self.config.dtype
        skel = self.model.skeleton
        s_u, s_r, s_c = self._scales
        q0t = torch.as_tensor(skel.inside(np.asarray(q0, np.float64), 1e-3), dtype=dtype)
        z_u = (skel.to_unbounded(q0t) / s_u).detach()
        z_r = torch.as_tensor(np.asarray(r0), dtype=dtype) / s_r
        z_c = torch.as_tensor(np.asarray(c0), dtype=dtype) / s_c
        return z_u, z_r, z_c

    def parameters(self, z: State) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Shape (B, n_shape), coordinates (B, n_dof) within the limits and root (B, 3), float64."""
        z_u, z_r, z_c = z
        s_u, s_r, s_c = self._scales
        with torch.no_grad():
            # In float64: float32 tanh saturates to exactly +-1, which rounds onto (or past) a bound.
            q = self.model.skeleton.from_unbounded((z_u * s_u).double())
            root = (z_r * s_r).double()
            c = (z_c * s_c).double().expand(len(q), -1)
        return c, q, root

    def coordinates(self, z_u: torch.Tensor) -> torch.Tensor:
        """(B, n_dof) coordinates, within the limits and differentiable, of the state's preconditioned
        unbounded values ``z_u`` (B, n_dof) (:meth:`start_state`)."""
        return self.model.skeleton.from_unbounded(z_u * self._scales[0])

    def _preconditioner(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per-parameter units (u: (n_dof,), root: (3,), c: (n_shape,)) in which one unit moves the subset's
        vertices by about 1 mm RMS, from the Jacobian at the mean body in the bind pose. L-BFGS starts from a
        scalar Hessian guess; without this the pelvis (moving every vertex) and a wrist (moving a few) differ
        in curvature by orders of magnitude and it converges slowly."""
        skel = self.model.skeleton
        dtype = self.config.dtype
        q = skel.inside(self.model.bind_coordinates, 0.1)
        n_dof, ns = skel.n_dof, self.model.n_shape
        p0 = torch.cat([
            skel.to_unbounded(torch.as_tensor(q[None], dtype=dtype)), torch.zeros(1, 3 + ns, dtype=dtype)
        ], dim=1)  # fmt: skip
        decoder = self.decoders["subset"]

        def f(p: torch.Tensor) -> torch.Tensor:
            u, r, c = p[:, :n_dof], p[:, n_dof : n_dof + 3], p[:, n_dof + 3 :]
            return decoder(c, skel.from_unbounded(u), r)[0] * 1000.0

        # Rows are independent, so P copies of p0 give every column at once (row k along parameter k), as
        # Jacobian-vector products by two reverse passes: g(w) = J^T w is linear in w, and its own
        # vector-Jacobian product with e_k is J e_k. (torch's forward mode imports its compiler: 1 s more.)
        P = p0.shape[1]
        with torch.enable_grad():
            x = p0.repeat(P, 1).requires_grad_()
            y = f(x)
            v = torch.zeros_like(y, requires_grad=True)
            (g,) = torch.autograd.grad(y, x, v, create_graph=True)
            (cols,) = torch.autograd.grad(g, v, torch.eye(P, dtype=dtype))
        rms = cols.reshape(P, -1, 3).norm(dim=-1).pow(2).mean(-1).sqrt().clamp_min(1e-3)  # (P,) mm per unit
        scale = 1.0 / rms
        return scale[:n_dof], scale[n_dof : n_dof + 3], scale[n_dof + 3 :]

    def free_variables(self, stage: Stage) -> tuple[torch.Tensor, torch.Tensor]:
        """The stage's free coordinates and shape coefficients (their indices): ``optimise``'s variables
        are these coordinates, the root (3) and these coefficients, in that order."""
        fd = torch.nonzero(self.dof_mask[stage.coordinates]).flatten()
        fs = torch.nonzero(self.shape_mask[stage.shape]).flatten()
        return fd, fs

    def optimise(
        self, stage: Stage, z: State, data_term: DataTerm, metric: torch.Tensor | None = None
    ) -> tuple[int, float]:
        """Minimise ``data_term`` + shape prior over the stage's parameters by :func:`batched_lbfgs`: one
        problem per mesh, or one for the whole batch when the shape is shared. Updates ``z`` (u: (B, n_dof),
        root: (B, 3), c: (1 or B, n_shape), from :meth:`start_state`) in place.

        Args:
            data_term: maps the model's vertices ``self.index[stage.vertices]`` (B, V_stage, 3) in mm to a
                (B,) loss in mm^2.
            metric: (problems, P, P) positive definite (:meth:`metric`): L-BFGS then runs in the variables
                that make it the identity, starting with a Newton step (a problem whose metric is not
                positive definite runs in the stage's own variables).
        Returns:
            iterations run and the final loss per mesh.
        """
        z_u, z_r, z_c = z
        _, s_r, s_c = self._scales
        B = z_u.shape[0]
        rows = z_c.shape[0]
        per_row = B // rows
        decoder = self.decoders[stage.vertices]
        fd, fs = self.free_variables(stage)
        n_pose = per_row * (len(fd) + 3)
        prior = self.config.shape_prior

        def unpack(Z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            pose = Z[:, :n_pose].reshape(B, len(fd) + 3)
            u = z_u.index_copy(1, fd, pose[:, : len(fd)])
            # A frozen shape stays out of the graph: backward then skips the skin's rest-shape half.
            c = z_c.index_copy(1, fs, Z[:, n_pose:]) if len(fs) else z_c
            return u, pose[:, len(fd) :], c

        # A frozen shape shared by every mesh (a sequence's frames, a shared-shape fit): its skin as a
        # function of the pose alone, cheaper per evaluation (BodyDecoder.posed).
        shared = None if len(fs) or not bool((z_c == z_c[:1]).all()) else decoder.posed(z_c[:1] * s_c)

        def losses(Z: torch.Tensor) -> torch.Tensor:
            u, r, c = unpack(Z)
            c_full = c * s_c
            if shared is None:
                verts = decoder(c_full.repeat_interleave(per_row, 0), self.coordinates(u), r * s_r)[0]
            else:
                verts = shared(self.coordinates(u), r * s_r)
            err = data_term(verts * 1000.0)  # (B,)
            return err.reshape(rows, per_row).sum(1) + prior * (c_full**2).sum(1)

        Z0 = torch.cat([torch.cat([z_u[:, fd], z_r], 1).reshape(rows, n_pose), z_c[:, fs]], 1)
        if metric is None:
            result = batched_lbfgs(losses, Z0, stage.iterations)
            Z = result.z
        else:
            L, failed = torch.linalg.cholesky_ex(metric)  # metric = L L^T; Z = Z0 + L^-T y
            eye = torch.eye(L.shape[-1], dtype=L.dtype)
            L = torch.where((failed != 0)[:, None, None], eye, L)  # not positive definite: no metric

            def to_z(y: torch.Tensor) -> torch.Tensor:
                return Z0 + torch.linalg.solve_triangular(L.mT, y[..., None], upper=True)[..., 0]

            result = batched_lbfgs(
                lambda y: losses(to_z(y)), torch.zeros_like(Z0), stage.iterations, newton_start=True
            )
            Z = to_z(result.z)
        u, r, c = unpack(Z)
        z_u.copy_(u)
        z_r.copy_(r)
        z_c.copy_(c)
        return stage.iterations, float(result.loss.sum()) / B

    def stage_jacobian(self, stage: Stage, z: State, vertices: str, step: float = 0.05) -> torch.Tensor:
        """(B, V' * 3, P) d vertices (mm) / d the stage's variables (``optimise``'s layout, one problem per
        mesh), by forward differences of ``step`` units, on the vertex set ``vertices``."""
        z_u, z_r, z_c = z
        _, s_r, s_c = self._scales
        B = z_u.shape[0]
        fd, fs = self.free_variables(stage)
        P = len(fd) + 3 + len(fs)
        decoder = self.decoders[vertices]
        Z0 = torch.cat([z_u[:, fd], z_r, z_c[:, fs].expand(B, -1)], 1)
        Z = Z0[:, None].repeat(1, P + 1, 1)
        Z[:, 1:] += step * torch.eye(P, dtype=Z.dtype)
        Z = Z.reshape(B * (P + 1), P)
        u = z_u.repeat_interleave(P + 1, 0).index_copy(1, fd, Z[:, : len(fd)])
        c = z_c.expand(B, -1).repeat_interleave(P + 1, 0).index_copy(1, fs, Z[:, len(fd) + 3 :])
        with torch.no_grad():
            v = decoder(c * s_c, self.coordinates(u), Z[:, len(fd) : len(fd) + 3] * s_r)[0] * 1000.0
        v = v.reshape(B, P + 1, -1)
        return ((v[:, 1:] - v[:, :1]) / step).mT

    def metric(
        self,
        stage: Stage,
        z: State,
        vertices: str,
        normals: np.ndarray | None = None,
        tangential: float = 1.0,
        regularise: float = 1e-3,
    ) -> torch.Tensor:
        """(problems, P, P) Gauss-Newton metric of a vertex-to-surface loss in ``optimise``'s variables at
        ``z`` (one problem per mesh, or one for the batch when the shape is shared):

            sum over the problem's meshes of 2 mean_v J_v^T N_v J_v, + the shape prior's Hessian
            + regularise * mean(diag) I,

        J_v (3, P) the Jacobian of vertex v of ``vertices`` (mm per unit, :meth:`stage_jacobian`);
        N_v = n n^T + tangential (I - n n^T) for normals (B, V', 3), the identity without them."""
        J = self.stage_jacobian(stage, z, vertices).double()
        B, _, P = J.shape
        J = J.reshape(B, -1, 3, P)
        M = tangential * torch.einsum("bvkp,bvkq->bpq", J, J)
        if normals is not None:
            Jn = torch.einsum("bvk,bvkp->bvp", torch.as_tensor(normals, dtype=J.dtype), J)
            M += (1.0 - tangential) * Jn.mT @ Jn
        M *= 2.0 / J.shape[1]
        fs = self.free_variables(stage)[1]
        M = _shared(M, len(fs), z[2].shape[0])
        n = M.shape[-1]
        if len(fs):  # the shape's variables come last
            s_c = self._scales[2][fs].double()
            M[:, n - len(fs) :, n - len(fs) :] += torch.diag(2.0 * self.config.shape_prior * s_c**2)
        M += regularise * M.diagonal(dim1=1, dim2=2).mean(1)[:, None, None] * torch.eye(n, dtype=M.dtype)
        return M.to(self.config.dtype)

    def _report(
        self,
        dist: np.ndarray,
        w: np.ndarray,
        q: np.ndarray,
        iterations: int,
        seconds: float,
        losses: dict[str, float],
    ) -> FitReport:
        used = dist[w > 0]
        stats = DistanceStats.of(used)
        reasons = []
        if stats.mean > CONFIDENT_MEAN_MM:
            reasons.append(
                f"mean vertex error {stats.mean:.1f} mm exceeds {CONFIDENT_MEAN_MM:.0f} mm: the mesh may not "
                "be a human body in our topology, or its pose is outside the joint limits"
            )
        extra = {"stage_loss_mm2": {k: round(v, 4) for k, v in losses.items()}}
        return FitReport.judged(stats, q, self.model.skeleton.ranges, iterations, seconds, reasons, extra)


def _shared(M: torch.Tensor, n_shape: int, problems: int) -> torch.Tensor:
    """Per-mesh metrics M (B, P, P), the last ``n_shape`` variables the shape's, as ``problems`` metrics in
    :meth:`RegisteredFitter.optimise`'s layout: unchanged for one problem per mesh; for a shared shape, each
    problem's meshes' pose blocks on the diagonal, their couplings to the shape, and the shape's block summed.
    """
    B, P, _ = M.shape
    if problems == B:
        return M
    m = B // problems
    p = P - n_shape
    blocks = M.reshape(problems, m, P, P)
    out = torch.zeros(problems, m * p + n_shape, m * p + n_shape, dtype=M.dtype)
    for k in range(m):
        rows = slice(k * p, (k + 1) * p)
        out[:, rows, rows] = blocks[:, k, :p, :p]
        out[:, rows, m * p :] = blocks[:, k, :p, p:]
        out[:, m * p :, rows] = blocks[:, k, p:, :p]
    out[:, m * p :, m * p :] = blocks[:, :, p:, p:].sum(1)
    return out
