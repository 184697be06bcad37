"""Fit the body model to a raw scan: any topology, orientation and placement, no landmarks.

The user guide, with the accuracy and speed measured on the benchmark scans, is docs/fitting.md ("Raw scans").

1. Clean: thin to a voxel grid and drop isolated points (statistical outlier removal,
   :func:`.phases.clean_points`); then separate the person from floors, walls, furniture and fragments
   (:func:`.scene.separate_person`: large planes, Euclidean clusters, a person-likeness test), and refuse a
   scan with no person in it.
2. Orientation: the scan's principal axes give 24 candidate body frames (each signed axis as "up", four
   headings about it). All are fitted at once, coarsely (the trunk's pose and the hips' and knees' flexion
   on a vertex subset: with the legs held straight a seated or crouching body is matched by bending the
   spine), and the best few by robust Chamfer score go on; after the limbs are posed the best one is kept.
   After the shape phase a runner-up that faces the other way goes on too when it nearly ties
   (:data:`.config.FLIPPED_MARGIN`): until its limbs are posed, a body seen from behind can fit nearly as
   well. On a full (not single-view) scan the best one also goes on with a straight-spine twin (the trunk's
   bend moved into the pelvis, the chest kept in place), since the orientation phase can still bend the
   spine to make up for legs that are not yet in place.
3. Coarse to fine: iterated closest points in both directions (scan point -> nearest model vertex,
   point-to-plane; model vertex -> nearest scan point), Geman-McClure weights with a shrinking scale, each
   round minimised by the staged L-BFGS of :class:`RegisteredFitter` (joint limits kept by the tanh
   mapping): the limbs, then the identity shape on a vertex subset, then a denser subset, point-to-plane.

   - The limbs are placed first by a grid search whose best few distinct candidates per limb are refined
     continuously (:class:`.limb_search.LimbSearch`), the head, hands and toes later by a grid search of
     their own. Before the limbs are searched a second time the fit also goes on from a twin with the
     scapulae at mid-range, as fits from the bind pose tend to hold the shoulders up with the scapulae at
     their limits. Both go through the first point-to-plane phase and the score picks one only then:
     refined to the end, the better fit also scores better, while after the limbs phase near-ties rank no
     better than chance.
   - The point-to-plane phases run their L-BFGS in the variables of the loss's Gauss-Newton metric at the
     phase's start (:meth:`RegisteredFitter.metric`: the Jacobian on the vertex subset, the normal direction
     weighted fully and the tangential ones by ``tangential``), starting with a Newton step; the first runs
     in two rounds, the second from the metric where the first ended. The surface's sliding modes (a thigh
     turned about its axis, the pelvis tilted against the lumbar bend) are nearly flat for a Chamfer loss:
     L-BFGS scaled per coordinate (:meth:`RegisteredFitter._preconditioner`) does not run them out in the
     iterations a fit can afford, while in the metric's variables they converge.
   - The one kept goes through a last, shorter point-to-plane phase ("valley": pelvis tilt, lumbar bend and
     hip flexion trade along a valley of the loss that the first point-to-plane phase does not run to its
     end).
   - The point-to-plane phases fit the "dense" farthest-point subset of the template
     (:class:`RegisteredFitConfig`), with the normals of a coarse mesh on it
     (:func:`~bodyfit.models.fitting.common.surface.coarse_faces`): the template's head, hands and toes
     carry two thirds of its vertices 2.5 mm apart, its trunk and limbs are 15-20 mm apart, and the subset
     keeps nearly every vertex of the latter. Counted alike, all the vertices would weight the model -> scan
     term towards the head and hands; the subset fits better, at a fraction of their cost.
4. Loose clothing (:mod:`.clothing`, :class:`.config.ClothingConfig`): when the scan stands off the fitted
   body outwards by more than 5 mm over more than 6% of its observed surface (the median offset of the
   nearest few dozen cleaned points: noise, holes and a single view leave it near zero), the body is
   fitted again inside the cloth with a one-sided loss (:func:`.losses.chamfer_term` with
   ``cloth_sigma_mm``: cloth standing off the body pulls it out hardly at all, a body outside the scan is
   pulled in), and the registration is refined on the scan points moved in by the clothing offset: it is
   the body under the cloth, and the report's ``extra["clothing"]`` says how far the cloth stands off it.
5. Non-rigid refinement (:mod:`~bodyfit.models.fitting.common.nonrigid`): per-vertex offsets for
   detail beyond the shape space.
6. Branches (:data:`.config.DEFAULT_BRANCHES`): from the shape phase up to the valley phase, step 3
   runs twice from the same state, at once on a thread each: once as above and once with the subset phases
   in the metric's variables too (more damped). The branch whose hypothesis scores best after the first
   point-to-plane phase goes on alone to the valley phase and steps 4 and 5. Each branch alone ends in a gross
   error (an arm folded over a hole, a head turned) on scans where the other does not, and the robust score
   tells which.

A scan smaller than a body (under :attr:`.config.ScanFitConfig.partial_extent` along its principal
axes: a head and shoulders) skips steps 3, 4 and 6: the "upper" vertex set alone is fitted, two ways, by the
trunk's, neck's and scapulae's DOFs, then the shape (:data:`.config.UPPER_BODY_PHASES`); the rest of
the body keeps the start pose, and the report says so and is never confident.

The phases, branches and settings are in :mod:`.config`; the losses in :mod:`.losses`, the hypotheses' steps
between their L-BFGS runs in :mod:`.hypotheses`, the scan's cleaning and the branches' bookkeeping in
:mod:`.phases`, and the result and its report in :mod:`.report`.

The fitted parameters are expressed in the scan's own frame when the pelvis angles can hold the scan's
orientation (an upright-ish body); otherwise they stay in the body frame and ``scan_to_body`` maps between.

References: the staged fitting (torso, then limbs, then all) of H. Wang, R. A. Güler, I. Kokkinos, G.
Papandreou and S. Zafeiriou, "BLSM: A Bone-Level Skinned Model of the Human Mesh", European Conference on
Computer Vision (ECCV), 2020; iterated closest points (P. J. Besl and N. D. McKay, "A Method for Registration
of 3-D Shapes", IEEE Transactions on Pattern Analysis and Machine Intelligence 14(2), 1992) with
point-to-plane distances (Y. Chen and G. Medioni, "Object modelling by registration of multiple range
images", Image and Vision Computing 10(3), 1992); the Chamfer distance (H. G. Barrow, J. M. Tenenbaum, R. C.
Bolles and H. C. Wolf, "Parametric correspondence and chamfer matching: Two new techniques for image
matching", International Joint Conference on Artificial Intelligence (IJCAI), 1977); the Geman-McClure loss
(S. Geman and D. E. McClure, "Statistical methods for tomographic image reconstruction", Bulletin of the
International Statistical Institute 52(4), 1987); L-BFGS (D. C. Liu and J. Nocedal, "On the limited memory
BFGS method for large scale optimization", Mathematical Programming 45, 1989) in the variables of the
Gauss-Newton metric (J. Nocedal and S. J. Wright, "Numerical Optimization", Springer, 2nd ed., 2006, chapter
10); farthest point sampling (Y. Eldar, M. Lindenbaum, M. Porat and Y. Y. Zeevi, "The Farthest Point Strategy
for Progressive Image Sampling", IEEE Transactions on Image Processing 6(9), 1997).
"""

from __future__ import annotations

import copy
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import torch

from bodyfit.io.scans import Scan
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.common.surface import (
    NormalOperators,
)
from bodyfit.models.fitting.registered.fitter import DataTerm, FixedBody, RegisteredFitter, State
from bodyfit.models.fitting.scan.clothing import (
    ClothingField,
    bare_vertices,
    clothing_field,
    looks_clothed,
    under_cloth,
)
from bodyfit.models.fitting.scan.config import (
    PART_NAMES,
    ScanBranch,
    ScanFitConfig,
    ScanPhase,
)
from bodyfit.models.fitting.scan.helper import ScanHelper
from bodyfit.models.fitting.scan.hypotheses import (
    DISTAL_SEARCH,
    DISTAL_TRUNCATION_M,
    DISTAL_VERTICES,
    EXPLAINED_M,
    STRAIGHTENED,
    UNSUPPORTED,
    VISIBLE_COS,
    HypothesisSteps,
    detect_view,
    orientation_candidates,
)
from bodyfit.models.fitting.scan.limb_search import Hypotheses, LimbSearch, Mapper
from bodyfit.models.fitting.scan.losses import (
    REACH_MM,
    chamfer_term,
    gauss_newton_metric,
    plane_surfaces,
    robust_score,
)
from bodyfit.models.fitting.scan.phases import (
    PhaseRun,
    PreparedScan,
    Progress,
    branch_bounds,
    clean_points,
    gather_branches,
    gather_shards,
    prepare_scan,
    principal_extent,
    refine_start,
)
from bodyfit.models.fitting.scan.report import (
    CONFIDENT_MEAN_MM,
    COVERED_MM,
    INLIER_MM,
    MIN_COVERAGE,
    MIN_INLIER_FRACTION,
    ScanFit,
    placed_fit,
    with_branch,
)
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS

__all__ = [
    "CONFIDENT_MEAN_MM",
    "COVERED_MM",
    "DISTAL_SEARCH",
    "DISTAL_TRUNCATION_M",
    "DISTAL_VERTICES",
    "EXPLAINED_M",
    "INLIER_MM",
    "MIN_COVERAGE",
    "MIN_INLIER_FRACTION",
    "REACH_MM",
    "STRAIGHTENED",
    "UNSUPPORTED",
    "VISIBLE_COS",
    "Progress",
    "ScanFit",
    "ScanFitter",
    "clean_points",
    "orientation_candidates",
]


class ScanFitter:
    """Fits :class:`BodyModel` to raw scans (one at a time; each scan's hypotheses are batched). With
    ``config.processes=2`` it starts a helper process (:mod:`.helper`); :meth:`close` stops it, as
    does the fitter's collection or the interpreter's exit. ``fitter``: a :class:`RegisteredFitter` of
    ``model`` to share (a service's, whose fits may run at the same time; it keeps no state between calls),
    else one of its own (seconds to build); its config sets the fit loop's float type."""

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
        self._bare = bare_vertices(model)
        self.limbs = LimbSearch(self.fitter)
        self._steps = HypothesisSteps(model, self.fitter, self._normals)
        # the vertex sets a point-to-plane phase can fit, and their surfaces (faces, normal operators)
        self._surfaces = plane_surfaces(model, self.fitter.index["dense"], self._normals, loop_float)
        self._helper = None
        if self.config.processes > 1:
            # the registered fitter travels too: the helper need not build its preconditioner again
            self._helper = ScanHelper(ScanFitter, model, replace(self.config, processes=1), self.fitter)

    def for_body(self, body: FixedBody) -> ScanFitter:
        """This fitter for one known person (:meth:`RegisteredFitter.for_body`): their decoder, their shape
        held fixed through every phase, so that a fit solves the orientation, pose and root only. It shares
        the cleaning, surfaces and settings, and runs in this process: the helper process holds the
        population's fitter."""
        fitter = copy.copy(self)
        fitter.fitter = self.fitter.for_body(body)
        fitter.limbs = LimbSearch(fitter.fitter)
        fitter._steps = HypothesisSteps(self.model, fitter.fitter, self._normals)
        fitter._helper = None
        return fitter

    def fit(
        self,
        scan: Scan | np.ndarray | PreparedScan,
        progress: Progress | None = None,
        orientation: np.ndarray | None = None,
        start: np.ndarray | None = None,
        up: np.ndarray | None = None,
    ) -> ScanFit:
        """Fit one scan.

        Args:
            scan: a :class:`Scan` from ``load_scan``, (N, 3) points in metres, or a
                :class:`~.phases.PreparedScan` (a service's check made it; not prepared again).
            progress: called with (steps done, steps in all, a line) once the scan is cleaned (0 done),
                then after each phase of each branch (:meth:`progress_steps` steps in all).
            orientation: (3, 3) rotation from the scan's axes to the body's (+X forward, +Y up, +Z right)
                when it is known (e.g. a dataset's convention); default: searched.
            start: (n_dof,) coordinates to start from (e.g. a T-pose); default: the bind pose.
            up: (3,) the scan's up direction in its own axes when only that is known (no ``orientation``):
                the search then tries eight headings about it instead of 24 frames.
        """
        began = time.perf_counter()
        prepared = prepare_scan(scan, self.config)
        points, cleaned, order, scene = prepared.points, prepared.cleaned, prepared.order, prepared.scene
        cfg = self.config
        extent = principal_extent(cleaned)
        partial = extent < cfg.partial_extent
        part = "upper" if partial else "all"
        hyp = self._candidates(cleaned, orientation, start, part, up)
        if cfg.single_view:
            detect_view(hyp, cleaned)
        tree = PointTree(cleaned)
        with ThreadPoolExecutor(cfg.workers) as pool:
            run = PhaseRun(cleaned, order, tree, progress, self.progress_steps(partial), pool)
            run.begin(f"fitting a {PART_NAMES[part]}")
            if not partial:
                fit = self._fit_branches(hyp, points, run, began)
            else:
                iterations, losses = self._run_phases(
                    hyp, cfg.partial_phases, cfg.branches[0], run, "", run.pool.map, shard=True
                )
                fit = self._result(hyp, points, run, iterations, losses, began, extent)
        if scene is None:
            return fit
        return replace(fit, report=replace(fit.report, extra={**fit.report.extra, "scene": scene}))

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
        non-rigid refinement; no orientation or limb search, so it is much faster than :meth:`fit`.

        Args:
            scan: a :class:`Scan` or (N, 3) points in metres, in the body's frame (+X forward, +Y up).
            shape: (n_shape,); coordinates: (n_dof,) (moved inside the limits); root: (3,) the body.
            progress: as for :meth:`fit` (one step per phase).
        """
        began = time.perf_counter()
        c, q, r, phases = refine_start(self.config, self.model, shape, coordinates, root)
        placed = prepare_scan(scan, self.config, scene=False)  # a body, already placed
        points, cleaned, order = placed.points, placed.cleaned, placed.order
        state = self.fitter.start_state(q[None], r[None], c[None])
        hyp = Hypotheses(np.eye(3)[None], np.zeros(3), np.zeros((1, 0, 3)), state, False)
        with ThreadPoolExecutor(self.config.workers) as pool:
            run = PhaseRun(cleaned, order, PointTree(cleaned), progress, len(phases), pool)
            run.begin("refining the body")
            iterations, losses = self._run_phases(hyp, phases, self.config.branches[0], run, "", map)
            return self._result(hyp, points, run, iterations, losses, began)

    def _fit_branches(self, hyp: Hypotheses, points: np.ndarray, run: PhaseRun, began: float) -> ScanFit:
        """The phases on the start hypotheses ``hyp``, the branched ones once per branch, and the result
        (the scan's raw points (N, 3))."""
        cfg = self.config
        split, until, branches = branch_bounds(self.config)
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
        ran, theirs = gather_branches(run_branch, len(branches), remote, run)
        if theirs is not None:
            starts[1] = theirs
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
        n_iter, cloth, field = self._under_cloth(hyp, run, branches[best])
        iterations += n_iter
        losses = {**losses, **branch_losses[best], **tail, **cloth}
        fit = self._result(hyp, points, run, iterations, losses, began, clothing=field)
        return with_branch(fit, best, scores)

    def _clothing_field(self, hyp: Hypotheses, cleaned: np.ndarray) -> ClothingField:
        """The cleaned scan's (M, 3) outward offset over the best hypothesis's body
        (:func:`.clothing.clothing_field`; a single view's over the side facing its sensor)."""
        cfg = self.config.clothing
        verts = self._vertices(hyp.state)
        seen = self._steps.visible(hyp, np.arange(self.model.n_vertices), verts)
        body_points = (cleaned - hyp.centre) @ hyp.rotation[0].T
        neighbours = 48 if cfg is None else cfg.neighbours
        seen_body = None if seen is None else seen[0]
        return clothing_field(verts[0], self.faces, body_points, neighbours, seen=seen_body)

    def _under_cloth(
        self, hyp: Hypotheses, run: PhaseRun, branch: ScanBranch
    ) -> tuple[int, dict[str, float], ClothingField | None]:
        """When the scan stands off the fitted body like loose clothing (:func:`.clothing.looks_clothed`),
        fit the body inside it (the one-sided ``config.clothing.phases``, reported as further steps); returns
        the iterations run, each phase's score and the clothing's offset over the body fitted under it
        (no scores and None when the scan does not look clothed, or when the fit under it is undone)."""
        cfg = self.config.clothing
        if cfg is None:
            return 0, {}, None
        field = self._clothing_field(hyp, run.cleaned)
        if not looks_clothed(field, cfg.threshold_mm / 1000.0, cfg.min_fraction):
            return 0, {}, None
        run.total += len(cfg.phases)
        before = hyp.copy()  # whole: the clothing phases may keep fewer hypotheses than they were given
        n_iter, losses = self._run_phases(hyp, cfg.phases, branch, run, "under the clothing: ", run.pool.map)
        under = self._clothing_field(hyp, run.cleaned)
        if under.bare_offset(self._bare) > cfg.bare_mm / 1000.0:
            # Cloth leaves the head and hands bare: a body pulled in under them as well is a bare body the
            # shape space cannot match (a real person's belly, say), not one under clothing.
            hyp.join([before])
            return n_iter, {}, None
        return n_iter, losses, under

    def progress_steps(self, partial: bool = False) -> int:
        """How many steps :meth:`fit` reports on a whole body: one per phase, the branched ones once per
        branch; on a head and shoulders (``partial``), one per partial phase."""
        if partial:
            return len(self.config.partial_phases)
        split, until, branches = branch_bounds(self.config)
        return len(self.config.phases) + (len(branches) - 1) * (until - split)

    def _run_phases(
        self,
        hyp: Hypotheses,
        phases: tuple[ScanPhase, ...],
        branch: ScanBranch,
        run: PhaseRun,
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
            self._steps.prepare(hyp, phase, run.cleaned[run.order[: phase.scan_points]])
            if shard and len(hyp.rotation) > 1:
                n_iter, score = self._sharded_step(hyp, phase, branch, run)
            else:
                n_iter, score = self._phase_step(hyp, phase, branch, run.tree, over)
            iterations += n_iter
            losses[phase.stage.name] = float(score.min())
            if phase.keep < len(hyp.rotation) or phase.one_per_frame:
                hyp.keep(self._steps.kept(hyp, phase, score))
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
            hyp.visible = self._steps.visible(hyp, self.fitter.index[phase.stage.vertices])
            term = self._chamfer(hyp, phase)
            metric = None
            if phase.stage.name in branch.metric_phases:
                metric = self._metric(hyp, phase, branch.damping)
            n_iter, _ = self.fitter.optimise(phase.stage, hyp.state, term, metric)
            iterations += n_iter
        return iterations, self._score(hyp, phase, tree)

    def _sharded_step(
        self, hyp: Hypotheses, phase: ScanPhase, branch: ScanBranch, run: PhaseRun
    ) -> tuple[int, np.ndarray]:
        """:meth:`_phase_step` on the two halves of ``hyp`` at once: the second in the helper process when
        there is one and it can take it, else both on the run's threads; ``hyp`` becomes the halves again.
        Either way each half is the same problem, so the fit does not depend on where it ran."""
        parts = [hyp.take(rows) for rows in np.array_split(np.arange(len(hyp.rotation)), 2)]
        remote = None
        if self._helper is not None:
            remote = self._helper.submit("_shard_task", parts[1], phase, branch, run.cleaned)

        def step(part: Hypotheses, over: Mapper) -> tuple[int, np.ndarray]:
            return self._phase_step(part, phase, branch, run.tree, over)

        iterations, score = gather_shards(step, parts, remote, run)
        hyp.join(parts)
        return iterations, score

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
            run = PhaseRun(cleaned, order, PointTree(cleaned), lambda _d, _t, x: lines.append(x), 0, pool)
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

    # -- steps (:class:`.hypotheses.HypothesisSteps`, :mod:`.losses`) ------------------------------------
    def _candidates(
        self,
        points: np.ndarray,
        orientation: np.ndarray | None,
        start: np.ndarray | None,
        part: str = "all",
        up: np.ndarray | None = None,
    ) -> Hypotheses:
        """The start hypotheses (:meth:`.hypotheses.HypothesisSteps.candidates`)."""
        return self._steps.candidates(points, orientation, start, part, up)

    def _vertices(self, state: State) -> np.ndarray:
        """(H, V, 3) model vertices (body frames, metres) of the current state."""
        return self._steps.vertices(state)

    def _frames(self, c: np.ndarray, q: np.ndarray, root: np.ndarray) -> np.ndarray:
        """(H, n_body, 4, 4) every body's frame for shapes c, coordinates q and roots (H, 3)."""
        return self._steps.frames(c, q, root)

    def _straighten_spine(self, hyp: Hypotheses) -> None:
        """Add straight-spine twins (:meth:`.hypotheses.HypothesisSteps.straighten_spine`)."""
        self._steps.straighten_spine(hyp)

    def _scapula_twin(self, hyp: Hypotheses) -> None:
        """Add mid-range scapula twins (:meth:`.hypotheses.HypothesisSteps.scapula_twin`)."""
        self._steps.scapula_twin(hyp)

    def _search_distal(self, hyp: Hypotheses) -> None:
        """Search the head, hands and toes (:meth:`.hypotheses.HypothesisSteps.search_distal`)."""
        self._steps.search_distal(hyp)

    def _chamfer(self, hyp: Hypotheses, phase: ScanPhase) -> DataTerm:
        """The phase's robust two-way Chamfer loss of every hypothesis (:func:`.losses.chamfer_term`)."""
        return chamfer_term(hyp, phase, self.fitter.config.dtype, self.config.tangential, self._surfaces)

    def _score(self, hyp: Hypotheses, phase: ScanPhase, tree: PointTree) -> np.ndarray:
        """(H,) each hypothesis's robust score on the phase's vertices (:func:`.losses.robust_score`)."""
        verts = self._vertices(hyp.state)[:, self.fitter.index[phase.stage.vertices]]
        return robust_score(verts, hyp, phase, tree)

    def _metric(self, hyp: Hypotheses, phase: ScanPhase, damping: float) -> torch.Tensor:
        """(H, P, P) the Gauss-Newton metric of ``phase``'s loss (its stage's variables) at each hypothesis's
        current state (:meth:`RegisteredFitter.metric` on the vertex subset, ``regularise=damping``; for a
        point-to-plane phase the normal direction weighted fully and the in-plane ones by the config's
        tangential weight): the phase's L-BFGS runs in the variables it makes the identity."""
        return gauss_newton_metric(self._steps, hyp, phase, damping, self.config.tangential)

    def _result(
        self,
        hyp: Hypotheses,
        points: np.ndarray,
        run: PhaseRun,
        iterations: int,
        losses: dict[str, float],
        start: float,
        partial_extent: float | None = None,
        clothing: ClothingField | None = None,
    ) -> ScanFit:
        """The fit of the best hypothesis of ``hyp``: refined, in the scan's frame, with every raw point's
        (N, 3) distance to the registration (in parts, on the run's threads) and the report
        (``partial_extent``: the scan's largest extent (m) when it was fitted as a head and shoulders).
        With ``clothing`` (the scan's offset over the body fitted under loose clothing) the registration
        is the body under the cloth: refined on the cleaned points moved in by the offset
        (:func:`.clothing.under_cloth`), the distances still those of the raw points, and the report's
        ``extra["clothing"]`` says how far the cloth stands off it."""
        if clothing is None:
            return placed_fit(
                self._steps, self.config, hyp, points, run, iterations, losses, start, partial_extent
            )
        R, m = hyp.rotation[0], hyp.centre
        body = self._vertices(hyp.state)[0]
        moved = under_cloth(body, self.faces, (run.cleaned - m) @ R.T, clothing) @ R + m
        under = replace(run, cleaned=moved, tree=PointTree(moved))
        fit = placed_fit(
            self._steps, self.config, hyp, points, under, iterations, losses, start, partial_extent
        )
        threshold = (self.config.clothing.threshold_mm if self.config.clothing else 0.0) / 1000.0
        extra = {**fit.report.extra, "clothing": clothing.summary(threshold)}
        return replace(fit, report=replace(fit.report, extra=extra))
