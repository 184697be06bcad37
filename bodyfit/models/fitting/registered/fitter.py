"""Fit the body model to meshes in its own topology (registered meshes), batched.

Staged as in BLSM's fitting (Wang, Güler, Kokkinos, Papandreou, Zafeiriou, "BLSM: A Bone-Level Skinned Model
of the Human Mesh", ECCV 2020, section 5.2): a rigid start from each body's own skin (Kabsch, "A solution for
the best rotation to relate two sets of vectors", Acta Crystallographica A, 1976), then the trunk's pose and
the bone-length coefficients on trunk vertices, then every coordinate on a spread vertex subset, then
everything including identity shape, and a last pass on all vertices (:mod:`.stages`). Each stage minimises

    sum_b [ mean_v w_bv |v_bv(c_b, q_b, r_b) - x_bv|^2 (mm^2) + lambda |c_b|^2 ]

by L-BFGS (Liu and Nocedal, "On the limited memory BFGS method for large scale optimization", Mathematical
Programming, 1989) over unconstrained coordinates ``u`` (``q = from_unbounded(u)``, BLSM eq. 6), so every
pose it returns respects the joint limits; in preconditioned units, and in the last stages in the variables
of the loss's Gauss-Newton metric (:mod:`.metric`). The model holds buffers only; the optimisation state
lives here.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.lbfgs import batched_lbfgs
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.registered.metric import (
    State,
    gauss_newton_metric,
    unit_scales,
)
from bodyfit.models.fitting.registered.metric import (
    stage_jacobian as _stage_jacobian,
)
from bodyfit.models.fitting.registered.stages import (
    CORE_DOF_PREFIXES,
    DEFAULT_STAGES,
    MIN_PART_VERTICES,
    MIN_PART_WEIGHT,
    STAGE_METRIC_DAMPING,
    TRUNK_BODIES,
    TRUNK_DOF_PREFIXES,
    UPPER_BODY_M,
    UPPER_DOF_PREFIXES,
    RegisteredFitConfig,
    Stage,
    VertexSet,
    coordinate_masks,
    farthest_point_subset,
    shape_masks,
    vertex_sets,
)
from bodyfit.models.fitting.registered.start import BoneStart
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS, check_finite

__all__ = [
    "CONFIDENT_MEAN_MM",
    "CORE_DOF_PREFIXES",
    "DEFAULT_STAGES",
    "MIN_PART_VERTICES",
    "MIN_PART_WEIGHT",
    "STAGE_METRIC_DAMPING",
    "TRUNK_BODIES",
    "TRUNK_DOF_PREFIXES",
    "UPPER_BODY_M",
    "UPPER_DOF_PREFIXES",
    "BodyFit",
    "DataTerm",
    "FixedBody",
    "RegisteredFitConfig",
    "RegisteredFitter",
    "Stage",
    "State",
    "farthest_point_subset",
    "vertex_term",
]

CONFIDENT_MEAN_MM = 10.0
DataTerm = Callable[[torch.Tensor], torch.Tensor]


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


@dataclass(frozen=True)
class FixedBody:
    """One known person's body, which a fit holds fixed: ``shape`` (n_shape,) their coefficients, and
    ``decoders`` giving their decoder for a float type (a :class:`BodyDecoder` of the same model carrying what
    is personal, e.g. a subject file's template offsets). A fit given one solves the pose and the root only
    (:meth:`RegisteredFitter.for_body`)."""

    shape: np.ndarray
    decoders: Callable[[torch.dtype], BodyDecoder]

    def decoder(self, dtype: torch.dtype) -> BodyDecoder:
        """The person's decoder in ``dtype``."""
        return self.decoders(dtype)


def vertex_term(targets_mm: torch.Tensor, weights: torch.Tensor) -> DataTerm:
    """The registered data term: weighted mean squared vertex distance (B,) in mm^2, for targets (B, V', 3)
    in mm and weights (B, V') (mean one)."""

    def term(verts_mm: torch.Tensor) -> torch.Tensor:
        return (((verts_mm - targets_mm) ** 2).sum(-1) * weights).mean(1)

    return term


class RegisteredFitter:
    """Fits :class:`BodyModel` to (B, V, 3) meshes in its topology. Reusable and stateless between calls.

    Its vertex sets (:attr:`index`, :attr:`decoders`), coordinate and shape masks (:attr:`dof_mask`,
    :attr:`shape_mask`) are those a :class:`Stage` names (:mod:`.stages`).
    """

    def __init__(self, model: BodyModel, config: RegisteredFitConfig | None = None) -> None:
        self.model = model
        self.config = config or RegisteredFitConfig()
        dtype = self.config.dtype
        skel = model.skeleton
        self.decoder = model.decoder(dtype)
        self.body: FixedBody | None = None
        self.index = vertex_sets(model, self.config)
        self.decoders = self._decoders_of(self.decoder)
        self.dof_mask = coordinate_masks(skel, dtype)
        self.shape_mask = shape_masks(model.n_shape, model.n_bone, dtype)
        self.pelvis = [skel.dof_index(n) for n in PELVIS_ROTATIONS]
        self._bone_start = BoneStart(model, dtype)
        subset = self.decoders["subset"]
        self._scales = unit_scales(skel, subset, model.bind_coordinates, model.n_shape, dtype)

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

    def for_body(self, body: FixedBody) -> RegisteredFitter:
        """This fitter for one known person (:class:`FixedBody`): their decoder, every stage's shape frozen
        (whatever stages run through it: its own, a scan fit's phases, a sequence's) and fits started from
        their shape, so that a fit solves the pose and the root only; the preconditioning and settings are
        shared."""
        fitter = copy.copy(self)
        fitter.body = body
        fitter.decoder = body.decoder(self.config.dtype)
        fitter.decoders = self._decoders_of(fitter.decoder)
        fitter.shape_mask = {name: torch.zeros_like(mask) for name, mask in self.shape_mask.items()}
        return fitter

    def start_shape(self, rows: int) -> np.ndarray:
        """(rows, n_shape) the shape fits start from: the population mean (zeros), or the fixed body's."""
        if self.body is None:
            return np.zeros((rows, self.model.n_shape))
        return np.tile(np.asarray(self.body.shape, np.float64), (rows, 1))

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
        """Coordinates (B, n_dof) and root (B, 3) of meshes x (B, V, 3) with weights w (B, V) from each
        body's own rigid motion (:class:`.start.BoneStart`)."""
        return self._bone_start(x, w, iterations)

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
            c0 = self.start_shape(B)
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
        """Shape (B, n_shape), coordinates (B, n_dof) within the limits and root (B, 3), float64; a fixed
        body's shape as given (the state holds it in the fitter's float type)."""
        z_u, z_r, z_c = z
        s_u, s_r, s_c = self._scales
        with torch.no_grad():
            # In float64: float32 tanh saturates to exactly +-1, which rounds onto (or past) a bound.
            q = self.model.skeleton.from_unbounded((z_u * s_u).double())
            root = (z_r * s_r).double()
            if self.body is None:
                c = (z_c * s_c).double().expand(len(q), -1)
            else:
                c = torch.as_tensor(np.asarray(self.body.shape, np.float64)).expand(len(q), -1)
        return c, q, root

    def coordinates(self, z_u: torch.Tensor) -> torch.Tensor:
        """(B, n_dof) coordinates, within the limits and differentiable, of the state's preconditioned
        unbounded values ``z_u`` (B, n_dof) (:meth:`start_state`), through BLSM's tanh mapping (Wang, Güler,
        Kokkinos, Papandreou, Zafeiriou, "BLSM: A Bone-Level Skinned Model of the Human Mesh", ECCV 2020,
        eq. 6)."""
        return self.model.skeleton.from_unbounded(z_u * self._scales[0])

    def free_variables(self, stage: Stage) -> tuple[torch.Tensor, torch.Tensor]:
        """The stage's free coordinates and shape coefficients (their indices): ``optimise``'s variables
        are these coordinates, the root (3) and these coefficients, in that order."""
        fd = torch.nonzero(self.dof_mask[stage.coordinates]).flatten()
        fs = torch.nonzero(self.shape_mask[stage.shape]).flatten()
        return fd, fs

    def optimise(
        self, stage: Stage, z: State, data_term: DataTerm, metric: torch.Tensor | None = None
    ) -> tuple[int, float]:
        """Minimise ``data_term`` + shape prior over the stage's parameters by :func:`batched_lbfgs` (L-BFGS:
        Liu and Nocedal, "On the limited memory BFGS method for large scale optimization", Mathematical
        Programming, 1989): one problem per mesh, or one for the whole batch when the shape is shared.
        Updates ``z`` (u: (B, n_dof), root: (B, 3), c: (1 or B, n_shape), from :meth:`start_state`) in
        place.

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

    def stage_jacobian(self, stage: Stage, z: State, vertices: VertexSet, step: float = 0.05) -> torch.Tensor:
        """(B, V' * 3, P) d vertices (mm) / d the stage's variables (``optimise``'s layout, one problem per
        mesh), by forward differences of ``step`` units, on the vertex set ``vertices``
        (:func:`.metric.stage_jacobian`)."""
        free = self.free_variables(stage)
        return _stage_jacobian(self.decoders[vertices], self.model.skeleton, self._scales, free, z, step)

    def metric(
        self,
        stage: Stage,
        z: State,
        vertices: VertexSet,
        normals: np.ndarray | None = None,
        tangential: float = 1.0,
        regularise: float = 1e-3,
    ) -> torch.Tensor:
        """(problems, P, P) Gauss-Newton metric of a vertex-to-surface loss in ``optimise``'s variables at
        ``z`` (one problem per mesh, or one for the batch when the shape is shared), on the vertex set
        ``vertices`` with normals (B, V', 3) or None (:func:`.metric.gauss_newton_metric`), in the
        fitter's dtype."""
        J = self.stage_jacobian(stage, z, vertices)
        shape_scales = self._scales[2][self.free_variables(stage)[1]]
        M = gauss_newton_metric(
            J, shape_scales, z[2].shape[0], self.config.shape_prior, normals, tangential, regularise
        )
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
