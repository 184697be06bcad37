"""Fit the body model to a raw scan: any topology, orientation and placement, no landmarks.

1. Clean: thin to a voxel grid and drop isolated points (statistical outlier removal).
2. Orientation: the scan's principal axes give 24 candidate body frames (each signed axis as "up", four
   headings about it). All are fitted at once, coarsely (the trunk's pose and the hips' and knees' flexion
   on a vertex subset: with the legs held straight a seated or crouching body is matched by bending the
   spine), and the best few by robust Chamfer score go on; after the limbs are posed the best one is kept.
   After the shape phase a runner-up that faces the other way goes on too when it nearly ties
   (:data:`.config.FLIPPED_MARGIN`): until its limbs are posed, a body seen from behind can fit
   nearly as well.
   On a full (not single-view) scan the best one also goes on with a straight-spine twin (the trunk's bend
   moved into the pelvis, the chest kept in place), since the orientation phase can still bend the spine
   to make up for legs that are not yet in place.
3. Coarse to fine (DESIGN.md section 6): iterated closest points in both directions (scan point -> nearest
   model vertex, point-to-plane; model vertex -> nearest scan point), Geman-McClure weights with a shrinking
   scale, each round minimised by the staged L-BFGS of :class:`RegisteredFitter` (joint limits kept by the
   tanh mapping): the limbs, then the identity shape on a vertex subset, then a denser subset (below),
   point-to-plane. The point-to-plane phases run their L-BFGS in the variables of the loss's Gauss-Newton
   metric at the phase's start (:meth:`RegisteredFitter.metric`: the Jacobian on the vertex subset, the normal
   direction weighted fully and the tangential ones by ``tangential``), starting with a Newton step; the first
   runs in two rounds of 15 iterations, the second from the metric where the first ended (on 102 held-out
   scans as accurate as 50 iterations in one metric, for 30 iterations). The surface's sliding modes (a
   thigh turned about its axis, the pelvis tilted against the lumbar bend) are nearly flat for a Chamfer
   loss, and L-BFGS scaled per coordinate (:meth:`RegisteredFitter._preconditioner`)
   had not run them out after 50 iterations: on clean held-out scans the parametric fit then lay 2-3 mm from
   the scan points and 4-6 mm from the truth, against about 1 and 2 mm in the metric's variables. The limbs
   are placed first by a grid search whose best few distinct candidates per limb are refined continuously
   (:class:`.limb_search.LimbSearch`), the head, hands and toes later by a grid search of their own. Before
   the limbs are searched a second time the fit also goes on from a twin with the scapulae at mid-range, as
   fits from the bind pose tend to hold the shoulders up with the scapulae at their limits. Both go through
   the first point-to-plane phase and the score picks one only then: refined to the end, the better fit scores
   better (on 36 held-out scans it picked the one with the lower registration error every time the two
   differed by more than 3 mm), while after the limbs phase near-ties rank no better than chance. The one kept
   goes through a last, shorter point-to-plane phase ("valley": pelvis tilt, lumbar bend and hip flexion trade
   along a valley of the loss that the first point-to-plane phase does not run to its end). The point-to-plane
   phases fit the "dense" farthest-point subset of 6,500 vertices (:class:`RegisteredFitConfig`), with the
   normals of a coarse mesh on it (:func:`~bodyfit.models.fitting.common.surface.coarse_faces`): the
   template's head, hands and toes carry
   two thirds of its vertices 2.5 mm apart, its trunk and limbs are 15-20 mm apart, and the subset keeps
   nearly every vertex of the latter. On the 102 held-out benchmark scans that fit better than all the
   vertices (with 50 iterations in one metric, registration error 7.41 mm mean and 3.86 median on 6,500
   vertices and 7.75 and 4.05 on 5,000, against 8.24 and 5.01 on all of them; every vertex counted alike
   weighted the model -> scan term towards the head and hands) at a third of their cost.
4. Non-rigid refinement (:mod:`~bodyfit.models.fitting.common.nonrigid`): per-vertex offsets for
   detail beyond the shape space.
5. Branches (:data:`.config.DEFAULT_BRANCHES`): from the shape phase up to the valley phase, step 3
   runs twice from the same state, at once on a thread each: once as above and once with the subset phases
   in the metric's variables too (more damped). The branch whose hypothesis scores best after the first
   point-to-plane phase goes on alone to the valley phase and step 4. Each branch alone ends in a gross
   error (an arm folded over a hole, a head turned) on scans where the other does not, and the robust score
   tells which.

A scan smaller than a body (under :attr:`.config.ScanFitConfig.partial_extent` along its principal
axes: a head and shoulders) skips steps 3 and 5: the "upper" vertex set alone is fitted, two ways, by the
trunk's, neck's and scapulae's DOFs, then the shape (:data:`.config.UPPER_BODY_PHASES`); the rest of
the body keeps the start pose, and the report says so and is never confident.

The phases, branches and settings are in :mod:`.config`.

The fitted parameters are expressed in the scan's own frame when the pelvis angles can hold the scan's
orientation (an upright-ish body); otherwise they stay in the body frame and ``scan_to_body`` maps between.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from itertools import pairwise
from threading import Lock

import numpy as np
import torch

from bodyfit.io.scans import MIN_POINTS, Scan, ScanError, largest_extent
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.nonrigid import refine_nonrigid
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.common.surface import (
    NormalOperators,
    coarse_faces,
    point_to_surface,
    vertex_normals,
)
from bodyfit.models.fitting.registered.fitter import DataTerm, RegisteredFitter, State
from bodyfit.models.fitting.scan.config import (
    PART_NAMES,
    ScanBranch,
    ScanFitConfig,
    ScanPhase,
)
from bodyfit.models.fitting.scan.helper import ScanHelper
from bodyfit.models.fitting.scan.limb_search import (
    Hypotheses,
    LimbSearch,
    Mapper,
    grid_vertices,
    search_grids,
)
from bodyfit.models.fitting.scan.view import Silhouette, view_direction
from bodyfit.models.rotations import zxy_angles
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS

# A scan fit's progress: called with the steps done, the steps in all and a line saying what was done.
Progress = Callable[[int, int, str], None]

CONFIDENT_MEAN_MM = 10.0
MIN_INLIER_FRACTION = 0.85
MIN_COVERAGE = 0.5
INLIER_MM = 30.0  # scan points further than this from the registration count as outliers
COVERED_MM = 20.0  # a model vertex is covered when a scan point lies this close
# In the point-to-plane phases, a model vertex further than this from every fit point adds a constant to the
# model -> scan term: it lies over a hole (or where a single view saw nothing), and the nearest point, on
# the hole's rim, pulled heads and hands over holes out of place (held-out hole scans: 13.3 -> 11.6 mm).
REACH_MM = 25.0
VISIBLE_COS = -0.1  # a vertex faces a single view's sensor when its normal is this close to towards it


# The small, vertex-dense ends of the body, searched the same way once the limbs are placed: their bodies and
# DOFs. Their surfaces are small but carry most of the template's vertices (head 32%, hands 24%, toes 11%).
DISTAL_SEARCH = (
    (("head", "cervical_link"), {"neck_extension": 5, "neck_bending": 3, "neck_rotation": 7}),
    *(
        (bodies, grid)
        for s in ("r", "l")
        for bodies, grid in (
            ((f"hand_{s}",), {f"pro_sup_{s}": 5, f"wrist_flex_{s}": 5, f"wrist_dev_{s}": 3}),
            ((f"toes_{s}",), {f"mtp_angle_{s}": 7}),
        )
    ),
)
DISTAL_VERTICES = 400  # of each distal chain's vertices, at most, that score its candidates
DISTAL_TRUNCATION_M = 0.02
EXPLAINED_M = 0.02  # a scan point this close to the rest of the body is not a distal chain's to explain
UNSUPPORTED = 0.8  # a distal chain whose best candidate's cost is this share of the truncation's has no data
STRAIGHTENED = 1  # of the hypotheses (best first), those that get a straight-spine twin
# The orientation phase keeps 3 hypotheses and the best gets a twin: the pose phase runs 4, in halves of 2. On
# the 102 held-out benchmark scans the final fit came from the orientation phase's third best once (a clothing
# scan) and never from its fourth; keeping 4 with two twins (6, halves of 3) fitted them to 8.12 mm mean,
# keeping 3 with one twin to 7.90 (keeping 2 with two twins: 8.51), the pose phase 0.42 s long on the calling
# process against 0.52-0.62.


@dataclass(frozen=True)
class ScanFit:
    """A fitted scan.

    shape (n_shape,), coordinates (n_dof,) in range, root (3,): the parameters, in the scan's frame unless
    ``scan_to_body`` is not the identity (then in the body frame ``body = scan_to_body @ scan``).
    vertices (V, 3): the parametric body in the scan's frame (metres); registration (V, 3): the non-rigid
    registration in our topology (equal to ``vertices`` without refinement); joints (J, 3) in the scan's
    frame. point_distances (N,): every scan point's distance to the registration surface (m).
    """

    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    registration: np.ndarray
    joints: np.ndarray
    scan_to_body: np.ndarray
    point_distances: np.ndarray
    report: FitReport


def clean_points(points: np.ndarray, voxel: float, neighbours: int, cutoff: float) -> np.ndarray:
    """Points (M, 3): one per occupied ``voxel`` cell, minus isolated ones (mean distance to ``neighbours``
    nearest above median + cutoff * 1.4826 MAD)."""
    if not len(points):
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:  # one integer per cell: 7x faster than rows
        keys = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, first = np.unique(keys, axis=0 if keys.ndim == 2 else None, return_index=True)  # first of each cell
    thin = points[np.sort(first)]
    if len(thin) <= neighbours + 1:
        return thin
    d, _ = PointTree(thin).query(thin, k=neighbours + 1)
    spread = d[:, 1:].mean(axis=1)
    median = np.median(spread)
    mad = np.median(np.abs(spread - median))
    return thin[spread <= median + cutoff * 1.4826 * mad + 1e-12]


def orientation_candidates(points: np.ndarray) -> np.ndarray:
    """(24, 3, 3) rotations from scan axes to body axes (+X forward, +Y up, +Z right): every signed
    principal axis as up, and four headings (the other principal axes, both signs) about it."""
    _, _, axes = np.linalg.svd(points - points.mean(0), full_matrices=False)
    out = []
    for i in range(3):
        others = [axes[k] for k in range(3) if k != i]
        for up in (axes[i], -axes[i]):
            for forward in (others[0], -others[0], others[1], -others[1]):
                out.append(np.stack([forward, up, np.cross(forward, up)]))
    return np.array(out)


@dataclass
class _PhaseRun:
    """What one scan's phases share: the cleaned points (M, 3), their random order (M,), their tree, the
    progress callback with the number of steps it will be told of, and the threads the branches run on."""

    cleaned: np.ndarray
    order: np.ndarray
    tree: PointTree
    progress: Progress | None
    total: int
    pool: ThreadPoolExecutor
    lock: Lock = field(default_factory=Lock)
    done: int = 0

    def begin(self, what: str) -> None:
        """Report step 0: the cleaned scan and ``what`` is fitted."""
        if self.progress is not None:
            self.progress(0, self.total, f"{len(self.cleaned):,} points cleaned; {what}")

    def report(self, line: str) -> None:
        """Count a step done and pass it on with ``line``, one branch's thread at a time."""
        with self.lock:
            self.done += 1
            if self.progress is not None:
                self.progress(self.done, self.total, line)


class ScanFitter:
    """Fits :class:`BodyModel` to raw scans (one at a time; each scan's hypotheses are batched). With
    ``config.processes=2`` it starts a helper process (:mod:`.helper`); :meth:`close` stops it, as
    does the fitter's collection or the interpreter's exit. ``fitter``: a :class:`RegisteredFitter` of
    ``model`` to share (a service's, whose fits may run at the same time; it keeps no state between calls),
    else one of its own (about 1.3-2.5 s to build); its config sets the fit loop's float type."""

    def __init__(
        self, model: BodyModel, config: ScanFitConfig | None = None, fitter: RegisteredFitter | None = None
    ) -> None:
        if fitter is not None and fitter.model is not model:
            raise ValueError("the shared RegisteredFitter must fit the same BodyModel as the ScanFitter")
        self.model = model
        self.config = config or ScanFitConfig()
        self.fitter = fitter if fitter is not None else RegisteredFitter(model)
        self.faces = np.asarray(model.data["faces"], np.int64)
        # in the fit loop's float type: the point-to-plane phase takes normals at every evaluation
        loop_float = np.float32 if self.fitter.config.dtype == torch.float32 else np.float64
        self._normals = NormalOperators.of(self.faces, model.n_vertices, loop_float)
        self.pelvis = [model.skeleton.dof_index(n) for n in PELVIS_ROTATIONS]
        owner = np.argmax(model.data["weights"], axis=1)  # each vertex's body
        names = model.skeleton.body_names
        self.limbs = LimbSearch(self.fitter)
        distal = []
        self._distal_parts = []  # each distal chain's vertices, then those of no chain
        for bodies, _ in DISTAL_SEARCH:
            own = np.flatnonzero(np.isin(owner, [names.index(b) for b in bodies]))
            distal.append(own[:: max(1, len(own) // DISTAL_VERTICES)])
            self._distal_parts.append(own)
        chained = np.concatenate(self._distal_parts)
        self._distal_parts.append(np.setdiff1d(np.arange(model.n_vertices), chained))
        self._neutral = model.skeleton.inside(model.bind_coordinates, 0.1)
        self._distal_decoder = self.fitter.decoder.restricted(np.concatenate(distal))
        # each distal chain's columns in the distal decoder's output
        bounds = np.cumsum([0] + [len(v) for v in distal])
        self._distal_columns = [slice(a, b) for a, b in pairwise(bounds)]
        self._spine = np.setdiff1d(np.flatnonzero(self.fitter.dof_mask["trunk"].numpy()), self.pelvis)
        self._thorax = names.index("thorax")
        self._scapula = [i for i, n in enumerate(model.skeleton.dof_names) if n.startswith("scapula_")]
        self._distal_grid = search_grids(model.skeleton, DISTAL_SEARCH)
        # the vertex sets a point-to-plane phase can fit, and their surfaces (faces, normal operators)
        dense = self.fitter.index["dense"]
        dense_faces = coarse_faces(model.data["vertices_mean"], self.faces, dense)
        self._surfaces = {
            "all": (self.faces, self._normals),
            "dense": (dense_faces, NormalOperators.of(dense_faces, len(dense), loop_float)),
        }
        self._helper = None
        if self.config.processes > 1:
            # the registered fitter travels too: the helper need not build its preconditioner again
            self._helper = ScanHelper(ScanFitter, model, replace(self.config, processes=1), self.fitter)

    def fit(
        self,
        scan: Scan | np.ndarray,
        progress: Progress | None = None,
        orientation: np.ndarray | None = None,
        start: np.ndarray | None = None,
    ) -> ScanFit:
        """Fit one scan.

        Args:
            scan: a :class:`Scan` from ``load_scan``, or (N, 3) points in metres.
            progress: called with (steps done, steps in all, a line) once the scan is cleaned (0 done),
                then after each phase of each branch (:meth:`progress_steps` steps in all).
            orientation: (3, 3) rotation from the scan's axes to the body's (+X forward, +Y up, +Z right)
                when it is known (e.g. a dataset's convention); default: searched.
            start: (n_dof,) coordinates to start from (e.g. a T-pose); default: the bind pose.
        """
        began = time.perf_counter()
        points, cleaned, order = self._prepare(scan)
        cfg = self.config
        _, _, axes = np.linalg.svd(cleaned - cleaned.mean(0), full_matrices=False)
        extent = largest_extent(cleaned @ axes.T)  # along its principal axes: however it is turned
        partial = extent < cfg.partial_extent
        part = "upper" if partial else "all"
        hyp = self._candidates(cleaned, orientation, start, part)
        if cfg.single_view:
            hyp.view = view_direction(cleaned)
            if hyp.view is not None:
                hyp.silhouette = Silhouette.of(cleaned, hyp.view)
        tree = PointTree(cleaned)
        with ThreadPoolExecutor(cfg.workers) as pool:
            run = _PhaseRun(cleaned, order, tree, progress, self.progress_steps(partial), pool)
            run.begin(f"fitting a {PART_NAMES[part]}")
            if not partial:
                return self._fit_branches(hyp, points, run, began)
            iterations, losses = self._run_phases(
                hyp, cfg.partial_phases, cfg.branches[0], run, "", run.pool.map, shard=True
            )
            return self._result(hyp, points, run, iterations, losses, began, extent)

    def refine(
        self,
        scan: Scan | np.ndarray,
        shape: np.ndarray,
        coordinates: np.ndarray,
        root: np.ndarray,
        progress: Progress | None = None,
    ) -> ScanFit:
        """Refine a body already placed on a scan (e.g. a registered fit through a topology map): the
        point-to-plane phases from the one named ``config.refine_from`` on, from that body, then the
        non-rigid refinement; no orientation or limb search. About 1 s per scan.

        Args:
            scan: a :class:`Scan` or (N, 3) points in metres, in the body's frame (+X forward, +Y up).
            shape: (n_shape,); coordinates: (n_dof,) (moved inside the limits); root: (3,) the body.
            progress: as for :meth:`fit` (one step per phase).
        """
        began = time.perf_counter()
        sizes = {"shape": self.model.n_shape, "coordinates": self.model.skeleton.n_dof, "root": 3}
        c, q, r = (np.asarray(value, np.float64) for value in (shape, coordinates, root))
        for (name, size), value in zip(sizes.items(), (c, q, r), strict=True):
            if value.shape != (size,) or not np.isfinite(value).all():
                raise ValueError(f"{name} must be a finite ({size},) array; got shape {value.shape}")
        names = [phase.stage.name for phase in self.config.phases]
        if self.config.refine_from not in names:
            raise ValueError(f"refine_from names no phase: {self.config.refine_from!r} is not in {names}")
        phases = self.config.phases[names.index(self.config.refine_from) :]
        points, cleaned, order = self._prepare(scan)
        state = self.fitter.start_state(q[None], r[None], c[None])
        hyp = Hypotheses(np.eye(3)[None], np.zeros(3), np.zeros((1, 0, 3)), state, False)
        with ThreadPoolExecutor(self.config.workers) as pool:
            run = _PhaseRun(cleaned, order, PointTree(cleaned), progress, len(phases), pool)
            run.begin("refining the body")
            iterations, losses = self._run_phases(hyp, phases, self.config.branches[0], run, "", map)
            return self._result(hyp, points, run, iterations, losses, began)

    def _prepare(self, scan: Scan | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A scan's raw points (N, 3), its cleaned points (M, 3) and their random order (M,).

        Raises:
            ScanError: not a finite (N, 3) array, or too few points left after cleaning.
        """
        points = scan.points if isinstance(scan, Scan) else np.asarray(scan, np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
            raise ScanError(f"scan points must be a finite (N, 3) array in metres; got shape {points.shape}")
        cfg = self.config
        cleaned = clean_points(points, cfg.voxel, cfg.neighbours, cfg.outlier_cutoff)
        if len(cleaned) < MIN_POINTS:
            raise ScanError(
                f"only {len(cleaned)} points are left after thinning to a {cfg.voxel * 100:.0f} cm grid and "
                f"dropping isolated points; a body needs at least {MIN_POINTS}: send a denser scan"
            )
        return points, cleaned, np.random.default_rng(cfg.seed).permutation(len(cleaned))

    def _fit_branches(self, hyp: Hypotheses, points: np.ndarray, run: _PhaseRun, began: float) -> ScanFit:
        """The phases on the start hypotheses ``hyp``, the branched ones once per branch, and the result
        (the scan's raw points (N, 3))."""
        cfg = self.config
        split, until, branches = self._branches()
        phases = cfg.phases
        # before and after the branches the pool's threads are free for a phase's own work
        iterations, losses = self._run_phases(
            hyp, phases[:split], branches[0], run, "", run.pool.map, shard=True
        )
        starts = [hyp] + [hyp.copy() for _ in branches[1:]]
        labels = [f"branch {b + 1}: " * (len(branches) > 1) for b in range(len(branches))]

        def run_branch(b: int) -> tuple[int, dict[str, float]]:
            return self._run_phases(starts[b], phases[split:until], branches[b], run, labels[b], map)

        remote = None
        if self._helper is not None and len(branches) == 2 and split < until:
            remote = self._helper.submit(
                "_branch_task", starts[1], phases[split:until], branches[1], run.cleaned, run.order, labels[1]
            )
        if remote is None:
            ran = list(run.pool.map(run_branch, range(len(branches))))  # at once, on the pool's threads
        else:  # the second branch in the helper process
            try:
                ran = [run_branch(0)]
            finally:
                theirs = remote()
            if theirs is None:
                ran.append(run_branch(1))
            else:
                starts[1], n_iter, mine_losses, lines = theirs
                ran.append((n_iter, mine_losses))
                for line in lines:
                    run.report(line)
        branch_losses = []
        for n_iter, mine_losses in ran:
            iterations += n_iter
            branch_losses.append(mine_losses)
        # each branch's score on its last phase (none when no phase branches)
        scores = [mine[phases[until - 1].stage.name] for mine in branch_losses] if split < until else [0.0]
        best = int(np.argmin(scores))
        hyp = starts[best]
        n_iter, tail = self._run_phases(hyp, phases[until:], branches[best], run, "", run.pool.map)
        iterations += n_iter
        fit = self._result(hyp, points, run, iterations, {**losses, **branch_losses[best], **tail}, began)
        extra = {
            **fit.report.extra,
            "branch": best,
            "branch_scores": [round(x, 5) for x in scores],
        }
        return replace(fit, report=replace(fit.report, extra=extra))

    def progress_steps(self, partial: bool = False) -> int:
        """How many steps :meth:`fit` reports on a whole body: one per phase, the branched ones once per
        branch; on a head and shoulders (``partial``), one per partial phase."""
        if partial:
            return len(self.config.partial_phases)
        split, until, branches = self._branches()
        return len(self.config.phases) + (len(branches) - 1) * (until - split)

    def _branches(self) -> tuple[int, int, tuple[ScanBranch, ...]]:
        """The indices of the first branched phase and of the first phase after the branches
        (``config.branch_from`` and ``config.branch_until``: the number of phases when there is none), and
        the branches that run (the first alone when no phase branches)."""
        names = [phase.stage.name for phase in self.config.phases]
        if self.config.branch_from not in names:
            return len(names), len(names), self.config.branches[:1]
        split = names.index(self.config.branch_from)
        until = (
            names.index(self.config.branch_until)
            if self.config.branch_until in names[split + 1 :]
            else len(names)
        )
        return split, until, self.config.branches

    def _run_phases(
        self,
        hyp: Hypotheses,
        phases: tuple[ScanPhase, ...],
        branch: ScanBranch,
        run: _PhaseRun,
        label: str,
        over: Mapper,
        shard: bool = False,
    ) -> tuple[int, dict[str, float]]:
        """Run ``phases`` on ``hyp`` (updated in place) the way ``branch`` says; returns the iterations run
        and each phase's best robust score. ``over`` maps the limb search over the hypotheses (the run's
        pool where its threads are free: from within a branch, which holds one of them, it would wait on
        itself with a single worker); ``shard``: each phase's work runs on two halves of the hypotheses at
        once (:meth:`_sharded_step`; the run's pool must be free)."""
        iterations, losses = 0, {}
        for phase in phases:
            hyp.points = np.einsum(
                "hij,nj->hni", hyp.rotation, run.cleaned[run.order[: phase.scan_points]] - hyp.centre
            )
            if phase.straighten and hyp.view is None:
                self._straighten_spine(hyp)
            if phase.scapula_twin:
                self._scapula_twin(hyp)
            if shard and len(hyp.rotation) > 1:
                n_iter, score = self._sharded_step(hyp, phase, branch, run)
            else:
                n_iter, score = self._phase_step(hyp, phase, branch, run.tree, over)
            iterations += n_iter
            losses[phase.stage.name] = float(score.min())
            if phase.keep < len(hyp.rotation):
                hyp.keep(self._kept(hyp, phase, score))
            run.report(f"{label}{phase.stage.name}: robust score {score.min():.3f}")
        return iterations, losses

    def _phase_step(
        self, hyp: Hypotheses, phase: ScanPhase, branch: ScanBranch, tree: PointTree, over: Mapper
    ) -> tuple[int, np.ndarray]:
        """One phase's work on ``hyp`` (its fit points and twins in place; updated in place): the searches
        and the rounds of L-BFGS. Returns the iterations run and each hypothesis's score (H,) against the
        cleaned scan's ``tree`` (:meth:`_score`). The hypotheses are independent problems."""
        if phase.search_limbs:
            self.limbs(hyp, over)
        if phase.search_distal:
            self._search_distal(hyp)
        iterations = 0
        for _ in range(phase.rounds):
            hyp.visible = self._visible(hyp, self.fitter.index[phase.stage.vertices])
            term = self._chamfer(hyp, phase)
            metric = None
            if phase.stage.name in branch.metric_phases:
                metric = self._metric(hyp, phase, branch.damping)
            n_iter, _ = self.fitter.optimise(phase.stage, hyp.state, term, metric)
            iterations += n_iter
        return iterations, self._score(hyp, phase, tree)

    def _sharded_step(
        self, hyp: Hypotheses, phase: ScanPhase, branch: ScanBranch, run: _PhaseRun
    ) -> tuple[int, np.ndarray]:
        """:meth:`_phase_step` on the two halves of ``hyp`` at once: the second in the helper process when
        there is one and it can take it, else both on the run's threads; ``hyp`` becomes the halves again.
        Either way each half is the same problem, so the fit does not depend on where it ran."""
        parts = [hyp.take(rows) for rows in np.array_split(np.arange(len(hyp.rotation)), 2)]
        remote = None
        if self._helper is not None:
            remote = self._helper.submit("_shard_task", parts[1], phase, branch, run.cleaned)
        if remote is None:
            steps = run.pool.map(lambda part: self._phase_step(part, phase, branch, run.tree, map), parts)
            (iterations, score), (_, second) = steps
        else:
            try:
                iterations, score = self._phase_step(parts[0], phase, branch, run.tree, run.pool.map)
            finally:
                theirs = remote()
            if theirs is None:  # the helper failed meanwhile
                _, second = self._phase_step(parts[1], phase, branch, run.tree, run.pool.map)
            else:
                parts[1], second = theirs
        hyp.join(parts)
        return iterations, np.concatenate([score, second])

    def _shard_task(
        self, hyp: Hypotheses, phase: ScanPhase, branch: ScanBranch, cleaned: np.ndarray
    ) -> tuple[Hypotheses, np.ndarray]:
        """The helper process's half of :meth:`_sharded_step`: the hypotheses after the step, their scores
        against the cleaned scan (M, 3)."""
        return hyp, self._phase_step(hyp, phase, branch, PointTree(cleaned), map)[1]

    def _branch_task(
        self,
        hyp: Hypotheses,
        phases: tuple[ScanPhase, ...],
        branch: ScanBranch,
        cleaned: np.ndarray,
        order: np.ndarray,
        label: str,
    ) -> tuple[Hypotheses, int, dict[str, float], list[str]]:
        """The helper process's branch (:meth:`_fit_branches`): the hypotheses after ``phases``, the
        iterations run, each phase's score, and the progress lines (in order)."""
        lines: list[str] = []
        with ThreadPoolExecutor(1) as pool:
            run = _PhaseRun(cleaned, order, PointTree(cleaned), lambda _d, _t, x: lines.append(x), 0, pool)
            iterations, losses = self._run_phases(hyp, phases, branch, run, label, map)
        return hyp, iterations, losses, lines

    @property
    def helper(self) -> ScanHelper | None:
        """The helper process (``processes=2``), or None."""
        return self._helper

    def wait_for_helper(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for the helper process to start (``processes=2``); whether it runs
        (False without one)."""
        return self._helper is not None and self._helper.wait_ready(timeout)

    def close(self) -> None:
        """Stop the helper process, if any (the fitter still fits, in one process)."""
        if self._helper is not None:
            self._helper.close()

    # -- steps -----------------------------------------------------------------------------------------
    def _candidates(
        self, points: np.ndarray, orientation: np.ndarray | None, start: np.ndarray | None, part: str = "all"
    ) -> Hypotheses:
        """The start hypotheses: each orientation (given, or :func:`orientation_candidates`) with the start
        pose, and the surface of the vertex set ``part`` ("all" or "upper") centred on the points'
        centroid."""
        rotation = orientation_candidates(points) if orientation is None else np.asarray(orientation)[None]
        H = len(rotation)
        model = self.model
        q_start = model.bind_coordinates if start is None else np.asarray(start, np.float64)
        q0 = np.repeat(model.skeleton.inside(q_start, 0.1)[None], H, axis=0)
        inside = np.zeros(model.n_vertices, bool)
        inside[self.fitter.index[part]] = True
        tri = model.data["vertices_mean"][self.faces[inside[self.faces].all(1)]]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        centre_offset = (tri.mean(1) * area[:, None]).sum(0) / area.sum()  # the surface's centroid
        r0 = np.repeat(-centre_offset[None], H, axis=0)
        state = self.fitter.start_state(q0, r0, np.zeros((H, model.n_shape)))
        return Hypotheses(rotation, points.mean(0), np.zeros((H, 0, 3)), state, orientation is None)

    def _vertices(self, state: State) -> np.ndarray:
        """(H, V, 3) model vertices (body frames, metres) of the current state."""
        c, q, root = self.fitter.parameters(state)
        dtype = self.fitter.config.dtype
        with torch.no_grad():
            v = self.fitter.decoder(c.to(dtype), q.to(dtype), root.to(dtype))[0]
        return v.double().numpy()

    def _chamfer(self, hyp: Hypotheses, phase: ScanPhase) -> DataTerm:
        """The robust two-way Chamfer loss of every hypothesis on the stage's vertices (H, V', 3) in mm:

            mean_i rho(|v_j(i) - p_i|) + 0.5 mean_j rho(|v_j - s(j)|),  rho(d) = d^2 s^2 / (d^2 + s^2)

        with p_i the phase's fit points, j(i) the vertex nearest p_i, s(j) the fit point nearest v_j (both
        found again at every evaluation), and the scan -> model distance point-to-plane when
        ``phase.plane`` (the normals of the stage's vertex set's surface, "all" or "dense"); then a vertex
        further than :data:`REACH_MM` from every fit point adds a constant to the second mean."""
        dtype = self.fitter.config.dtype
        P = torch.as_tensor(hyp.points * 1000.0, dtype=dtype)
        fit_points = hyp.points
        point_trees = [PointTree(p) for p in fit_points]
        s2 = phase.sigma_mm**2
        tangential = self.config.tangential
        plane = phase.plane
        if plane and phase.stage.vertices not in self._surfaces:
            raise ValueError(
                f"point-to-plane Chamfer needs a vertex set with a surface ({', '.join(self._surfaces)}); "
                f"the stage {phase.stage.name!r} fits {phase.stage.vertices!r}"
            )
        faces, normal_ops = self._surfaces.get(phase.stage.vertices, self._surfaces["all"])

        def rho(d2: torch.Tensor) -> torch.Tensor:
            return d2 * s2 / (d2 + s2)

        seen = None if hyp.visible is None else torch.as_tensor(hyp.visible, dtype=dtype)
        seen_index = None if hyp.visible is None else [np.flatnonzero(m) for m in hyp.visible]

        def term(verts_mm: torch.Tensor) -> torch.Tensor:
            v = verts_mm.detach().double().numpy() / 1000.0
            H = len(v)
            pairs = np.empty(fit_points.shape[:2], np.int64)
            targets = np.empty(v.shape)
            for h in range(H):
                if seen_index is None:
                    pairs[h] = PointTree(v[h]).query(fit_points[h])[1]
                else:  # a single view's points lie on the surface that faced the sensor
                    pairs[h] = seen_index[h][PointTree(v[h, seen_index[h]]).query(fit_points[h])[1]]
                targets[h] = fit_points[h][point_trees[h].query(v[h])[1]]
            J = torch.as_tensor(pairs).unsqueeze(-1).expand(-1, -1, 3)
            r = torch.gather(verts_mm, 1, J) - P  # (H, N, 3)
            d2 = (r**2).sum(-1)
            if plane:
                n = vertex_normals(verts_mm.detach().numpy(), faces, normal_ops)  # float32
                along = (r * torch.as_tensor(np.take_along_axis(n, pairs[..., None], 1), dtype=dtype)).sum(-1)
                d2 = along**2 + tangential * (d2 - along**2)
            m2s = rho(((verts_mm - torch.as_tensor(targets * 1000.0, dtype=dtype)) ** 2).sum(-1))
            if plane:  # beyond the reach, a constant: no pull towards a hole's rim
                m2s = m2s.clamp_max(REACH_MM**2 * s2 / (REACH_MM**2 + s2))
            m2s_mean = m2s.mean(1) if seen is None else (m2s * seen).sum(1) / seen.sum(1).clamp_min(1.0)
            return (rho(d2).mean(1) if phase.two_way else 0.0) + 0.5 * m2s_mean

        return term

    def _metric(self, hyp: Hypotheses, phase: ScanPhase, damping: float) -> torch.Tensor:
        """(H, P, P) the Gauss-Newton metric of ``phase``'s loss (its stage's variables) at each hypothesis's
        current state (:meth:`RegisteredFitter.metric` on the vertex subset, ``regularise=damping``; for a
        point-to-plane phase the normal direction weighted fully and the in-plane ones by the config's
        tangential weight): the phase's L-BFGS runs in the variables it makes the identity."""
        if not phase.plane:
            return self.fitter.metric(phase.stage, hyp.state, "subset", regularise=damping)
        index = self.fitter.index["subset"]
        normals = vertex_normals(self._vertices(hyp.state), self.faces, self._normals)[:, index]
        return self.fitter.metric(phase.stage, hyp.state, "subset", normals, self.config.tangential, damping)

    def _visible(
        self, hyp: Hypotheses, index: np.ndarray, verts: np.ndarray | None = None
    ) -> np.ndarray | None:
        """(H, len(index)) which of the vertices ``index`` face a single-view scan's sensor in each
        hypothesis's current state (normal towards it, with a little slack at the silhouette); None for a
        full scan. ``verts``: the state's (H, V, 3) vertices (:meth:`_vertices`) when the caller has them."""
        if hyp.view is None:
            return None
        verts = self._vertices(hyp.state) if verts is None else verts
        towards = hyp.rotation @ hyp.view  # (H, 3) in each body frame
        normals = vertex_normals(verts, self.faces, self._normals)[:, index]
        return np.einsum("hvi,hi->hv", normals, towards) > VISIBLE_COS

    def _kept(self, hyp: Hypotheses, phase: ScanPhase, score: np.ndarray) -> np.ndarray:
        """Rows of the hypotheses that go on after ``phase``: the best ``phase.keep`` by ``score`` (H,),
        and the best one facing the other way from the best (see :class:`ScanPhase`'s ``flipped_margin``)
        when it scores within the margin and none of those faces that way."""
        order = np.argsort(score)
        rows = order[: phase.keep]
        if phase.flipped_margin <= 0.0:
            return rows
        c, q, root = (t.numpy() for t in self.fitter.parameters(hyp.state))
        pelvis_forward = self._frames(c, q, root)[:, 0, :3, 0]  # (H, 3) body frames
        forward = np.einsum("hji,hj->hi", hyp.rotation, pelvis_forward)  # in the scan's frame
        facing = forward @ forward[order[0]]
        near = score <= (1.0 + phase.flipped_margin) * score[order[0]]
        if (facing[rows] < 0.0).any():
            return rows
        flipped = [h for h in order[phase.keep :] if facing[h] < 0.0 and near[h]]
        return np.array([*rows, *flipped[:1]])

    def _straighten_spine(self, hyp: Hypotheses) -> None:
        """Add, for each of the best :data:`STRAIGHTENED` hypotheses, a twin with its trunk's bend moved into
        the pelvis: the lumbar and thoracic coordinates go to zero and the pelvis turns (and the root moves)
        so that the thorax keeps its place. The orientation phase fits the trunk and the legs' flexion
        coarsely; on a seated or crouching body it still tends to tilt the pelvis back and bend the spine
        to keep the chest upright (30-50 degrees when the legs are held straight), a minimum the later phases
        do not leave. The chest's fit is the reliable part of it."""
        c, q, root = (t.numpy()[:STRAIGHTENED] for t in self.fitter.parameters(hyp.state))
        thorax = self._thorax
        frames = self._frames(c, q, root)
        straight = q.copy()
        straight[:, self._spine] = 0.0
        bent = self._frames(c, straight, root)
        # pelvis -> thorax rotation with a straight spine; the new pelvis carries the thorax where it was
        relative = np.swapaxes(bent[:, 0, :3, :3], 1, 2) @ bent[:, thorax, :3, :3]
        straight[:, self.pelvis] = zxy_angles(frames[:, thorax, :3, :3] @ np.swapaxes(relative, 1, 2))
        moved = self._frames(c, straight, root)
        root_straight = root + frames[:, thorax, :3, 3] - moved[:, thorax, :3, 3]
        hyp.add_twins(np.arange(len(q)), self.fitter.start_state(straight, root_straight, c))

    def _scapula_twin(self, hyp: Hypotheses) -> None:
        """Add, for every hypothesis, a twin with the scapulae at the middle of their ranges (the limb search
        that follows places the arms from them). Fits started from the bind pose bring the shoulders onto
        the scan by elevating the scapulae to their limit and rotating them down, with the arms flexed
        30-45 degrees more to match: a minimum that scores within a fraction of a percent of the right one,
        which the twin starts outside of."""
        c, q, root = (t.numpy() for t in self.fitter.parameters(hyp.state))
        twin = q.copy()
        twin[:, self._scapula] = self.model.skeleton.ranges[self._scapula].mean(1)
        hyp.add_twins(np.arange(len(q)), self.fitter.start_state(twin, root, c))

    def _frames(self, c: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
        """(H, n_body, 4, 4) every body's frame for shapes c, coordinates q and roots (H, 3)."""
        dtype = self.fitter.config.dtype
        rows = (torch.as_tensor(x, dtype=dtype) for x in (c, q, root))
        with torch.no_grad():
            return self.fitter.decoders["coarse"](*rows)[2].double().numpy()

    def _search_distal(self, hyp: Hypotheses) -> None:
        """Set the head's, hands' and toes' searched DOFs (:data:`DISTAL_SEARCH`) of every hypothesis to the
        candidate (or the current pose, if better) whose vertices lie closest to the scan points the rest of
        the body does not explain (further than :data:`EXPLAINED_M` from its vertices; mean squared distance
        truncated at :data:`DISTAL_TRUNCATION_M`). A chain that no candidate brings near such points (a hand
        or head the scan lost to a hole) goes to the bind pose's values: searched against all points, it
        was folded onto whatever surface lay near (a wrist flexed 60 degrees onto the thigh). The chains are
        independent of each other."""
        c, q, root = (t.numpy() for t in self.fitter.parameters(hyp.state))
        grids = self._distal_grid
        K = max(len(g) for _, g in grids)
        whole = self._vertices(hyp.state)
        for h in range(len(q)):
            v = grid_vertices(self._distal_decoder, grids, c[h], q[h], root[h], self.fitter.config.dtype)
            points = hyp.points[h]
            # each point's distance to each part (the chains, the rest), inf beyond EXPLAINED_M
            parts = self._distal_parts
            near = np.stack([PointTree(whole[h, p]).query(points, EXPLAINED_M)[0] for p in parts])
            for chain, ((dofs, values), cols) in enumerate(zip(grids, self._distal_columns, strict=True)):
                loose = points[np.delete(near, chain, axis=0).min(0) > EXPLAINED_M]
                if not len(loose):
                    q[h, dofs] = self._neutral[dofs]
                    continue
                n = len(values)
                mine = np.append(np.arange(n), K)  # this chain's candidates, then the current pose
                d = PointTree(loose).query(v[mine][:, cols].reshape(-1, 3), DISTAL_TRUNCATION_M)[0]
                cost = (np.minimum(d, DISTAL_TRUNCATION_M) ** 2).reshape(n + 1, -1).mean(1)
                best = int(np.argmin(cost))
                if cost[best] > UNSUPPORTED * DISTAL_TRUNCATION_M**2:
                    q[h, dofs] = self._neutral[dofs]
                elif best < n:
                    q[h, dofs] = values[best]
        hyp.state = self.fitter.start_state(q, root, c)

    def _score(self, hyp: Hypotheses, phase: ScanPhase, tree: PointTree) -> np.ndarray:
        """(H,) each hypothesis's robust Chamfer score on the phase's vertices (rho / sigma^2, lower is
        better; a single view's on the vertices facing its sensor)."""
        verts = self._vertices(hyp.state)[:, self.fitter.index[phase.stage.vertices]]
        sigma = phase.sigma_mm / 1000.0
        score = np.empty(len(verts))
        for h, v in enumerate(verts):
            if hyp.visible is not None:
                v = v[hyp.visible[h]]
            d_s = PointTree(v).query(hyp.points[h])[0]
            d_m = tree.query(v @ hyp.rotation[h] + hyp.centre)[0]
            score[h] = 0.5 * (d_m**2 / (d_m**2 + sigma**2)).mean()
            if phase.two_way:
                score[h] += (d_s**2 / (d_s**2 + sigma**2)).mean()
        return score

    def _result(
        self,
        hyp: Hypotheses,
        points: np.ndarray,
        run: _PhaseRun,
        iterations: int,
        losses: dict[str, float],
        start: float,
        partial_extent: float | None = None,
    ) -> ScanFit:
        """The fit of the best hypothesis of ``hyp``: refined, in the scan's frame, with every raw point's
        (N, 3) distance to the registration (in parts, on the run's threads) and the report
        (``partial_extent``: the scan's largest extent (m) when it was fitted as a head and shoulders)."""
        model, skel = self.model, self.model.skeleton
        R, m = hyp.rotation[0], hyp.centre
        c, q, root = (t[0].numpy() for t in self.fitter.parameters(hyp.state))
        all_verts = self._vertices(hyp.state)
        body_verts = all_verts[0]
        body_points = (run.cleaned - m) @ R.T
        registration = body_verts
        if self.config.nonrigid is not None:
            # a single view's side facing its sensor
            seen = self._visible(hyp, np.arange(model.n_vertices), all_verts)
            registration = refine_nonrigid(
                body_verts,
                self.faces,
                body_points,
                self.config.nonrigid,
                seen=None if seen is None else seen[0],
            )
        # Parameters in the scan's frame when the pelvis angles can hold its orientation.
        out = model.forward(c[None], q[None], root[None], dtype=torch.float64)
        pelvis = out.frames[0, 0].numpy()
        q_scan = q.copy()
        q_scan[self.pelvis] = zxy_angles(R.T @ pelvis[:3, :3])
        root_scan = R.T @ pelvis[:3, 3] + m
        inside = np.all((q_scan >= skel.ranges[:, 0] + 1e-6) & (q_scan <= skel.ranges[:, 1] - 1e-6))
        scan_to_body = np.eye(4)
        if inside:
            q, root = q_scan, root_scan
        else:
            scan_to_body[:3, :3], scan_to_body[:3, 3] = R, -R @ m
        joints = out.joints[0].numpy() @ R + m
        vertices = body_verts @ R + m
        registration = registration @ R + m
        parts = np.array_split(points, self.config.workers)
        distances = np.concatenate(
            list(run.pool.map(lambda part: point_to_surface(part, registration, self.faces), parts))
        )
        offset = float(np.linalg.norm(registration - vertices, axis=1).mean())
        coverage = float(np.mean(run.tree.query(registration, COVERED_MM / 1000)[0] < np.inf))
        seconds = time.perf_counter() - start
        report = self._report(
            distances,
            coverage,
            offset,
            hyp.searched,
            hyp.view,
            q,
            iterations,
            seconds,
            losses,
            partial_extent,
        )
        return ScanFit(c, q, root, vertices, registration, joints, scan_to_body, distances, report)

    def _report(
        self,
        distances: np.ndarray,
        coverage: float,
        offset: float,
        searched: bool,
        view: np.ndarray | None,
        q: np.ndarray,
        iterations: int,
        seconds: float,
        losses: dict[str, float],
        partial_extent: float | None = None,
    ) -> FitReport:
        inlier = distances * 1000.0 <= INLIER_MM
        stats = DistanceStats.of(distances[inlier])
        fraction = float(inlier.mean())
        reasons = []
        if fraction < MIN_INLIER_FRACTION:
            reasons.append(
                f"only {fraction:.0%} of the scan's points lie within {INLIER_MM:.0f} mm of the fitted body: "
                "crop the background or other objects, or the scan may not be a human body"
            )
        if not stats.mean <= CONFIDENT_MEAN_MM:
            reasons.append(
                f"mean scan-to-body distance {stats.mean:.1f} mm exceeds {CONFIDENT_MEAN_MM:.0f} mm"
            )
        if coverage < MIN_COVERAGE:
            reasons.append(
                f"the scan covers {coverage:.0%} of the body surface: the shape and pose of the rest are "
                "guesses"
            )
        if partial_extent is not None:
            reasons.append(
                f"the scan is {partial_extent:.2f} m across, less than a body: it was fitted as a head and "
                "shoulders; the rest of the body is the shape space's guess, in the start pose"
            )
        if view is not None:
            reasons.append(
                "the scan is one sensor's view: the side of the body it did not see is the model's guess"
            )
        if searched:
            reasons.append(
                "the orientation was searched: on varied poses such fits often match the surface with a "
                "wrong heading or wrong limbs, which the distances cannot show; pass orientation= (and a "
                "start pose) when you know them"
            )
        extra = {
            "inlier_fraction": round(fraction, 4),
            "inlier_threshold_mm": INLIER_MM,
            "coverage": round(coverage, 4),
            "single_view": None if view is None else [round(float(x), 4) for x in view],
            "nonrigid_offset_mm": round(offset * 1000, 2),
            "phase_scores": {k: round(v, 5) for k, v in losses.items()},
            "fitted_part": PART_NAMES["all" if partial_extent is None else "upper"],
        }
        return FitReport.judged(stats, q, self.model.skeleton.ranges, iterations, seconds, reasons, extra)
