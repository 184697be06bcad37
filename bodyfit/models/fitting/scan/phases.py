"""What a scan fit's phases start from and share: the cleaned scan, the person alone (:func:`clean_points`,
:func:`prepare_scan`, :func:`principal_extent`), a refinement's start (:func:`refine_start`), the run's
progress and threads (:class:`PhaseRun`), where the branches start and end among the phases
(:func:`branch_bounds`) and the gathering of work split between threads or the helper process
(:func:`gather_shards`, :func:`gather_branches`)."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from threading import Lock
from typing import Any

import numpy as np

from bodyfit.io.scans import MIN_POINTS, Scan, ScanError, largest_extent
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nearest import PointTree
from bodyfit.models.fitting.scan.config import ScanBranch, ScanFitConfig, ScanPhase
from bodyfit.models.fitting.scan.limb_search import Hypotheses, Mapper
from bodyfit.models.fitting.scan.scene import raw_points_kept, separate_person

# A scan fit's progress: called with the steps done, the steps in all and a line saying what was done.
Progress = Callable[[int, int, str], None]
# a branch's run: the iterations and each phase's score
BranchRun = tuple[int, dict[str, float]]
# the helper's answer for a shard: its hypotheses after the step and their scores (H,); None if it failed
RemoteShard = Callable[[], tuple[Hypotheses, np.ndarray] | None]
# the helper's answer for a branch: its hypotheses, iterations, scores and progress lines; None if it failed
RemoteBranch = Callable[[], tuple[Hypotheses, int, dict[str, float], list[str]] | None]


def clean_points(points: np.ndarray, voxel: float, neighbours: int, cutoff: float) -> np.ndarray:
    """Points (M, 3): one per occupied ``voxel`` cell, minus isolated ones (mean distance to ``neighbours``
    nearest above median + cutoff * 1.4826 MAD).

    The statistical outlier removal of R. B. Rusu, Z. C. Marton, N. Blodow, M. Dolha and M. Beetz, "Towards 3D
    Point cloud based object maps for household environments", Robotics and Autonomous Systems 56(11), 2008,
    with the median and the median absolute deviation (F. R. Hampel, "The influence curve and its role in
    robust estimation", Journal of the American Statistical Association 69(346), 1974) in place of the mean
    and standard deviation, so that the outliers do not set their own threshold.
    """
    if not len(points):
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:  # one integer per cell: faster than unique rows
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


@dataclass(frozen=True)
class PreparedScan:
    """A scan cleaned and split from its scene (:func:`prepare_scan`): points (N, 3) its raw points that
    belong to the person; cleaned (M, 3) the cleaned points; order (M,) their random order; scene what the
    separation removed (None when it did not run); source the scan it was made from; made_with the settings
    it was made with (:func:`preparation`), so that a fitter with other settings prepares the source again.
    A service checks a scan by preparing it, and passes this on to the fit, which then does not redo it."""

    points: np.ndarray
    cleaned: np.ndarray
    order: np.ndarray
    scene: dict[str, Any] | None
    source: Scan | np.ndarray
    made_with: tuple[Any, ...]


def preparation(cfg: ScanFitConfig, scene: bool = True) -> tuple[Any, ...]:
    """The settings of ``cfg`` that :func:`prepare_scan` depends on (with ``scene``: the separation's)."""
    return (cfg.voxel, cfg.neighbours, cfg.outlier_cutoff, cfg.seed, cfg.scene if scene else None)


def prepare_scan(
    scan: Scan | np.ndarray | PreparedScan, cfg: ScanFitConfig, scene: bool = True
) -> PreparedScan:
    """A scan's raw points, its cleaned points, their random order and what was removed as scene clutter,
    by ``cfg`` (:class:`PreparedScan`). With ``scene`` and ``cfg.scene``, the person is separated from
    planes, objects and fragments (:func:`.scene.separate_person`): the cleaned points and the raw points
    are the person's only, and the summary says what was removed (else None). A :class:`PreparedScan`
    made with the same settings is returned as it is; one made with others is prepared again from its
    source.

    Raises:
        ScanError: not a finite (N, 3) array, or too few points left after cleaning.
        NoPersonError: ``scene`` and nothing in the scan looks like a person.
    """
    made_with = preparation(cfg, scene)
    if isinstance(scan, PreparedScan):
        if scan.made_with == made_with:
            return scan
        scan = scan.source
    points = scan.points if isinstance(scan, Scan) else np.asarray(scan, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise ScanError(f"scan points must be a finite (N, 3) array in metres; got shape {points.shape}")
    cleaned = clean_points(points, cfg.voxel, cfg.neighbours, cfg.outlier_cutoff)
    if len(cleaned) < MIN_POINTS:
        raise ScanError(
            f"only {len(cleaned)} points are left after thinning to a {cfg.voxel * 100:.0f} cm grid and "
            f"dropping isolated points; a body needs at least {MIN_POINTS}: send a denser scan"
        )
    summary = None
    if scene and cfg.scene is not None:
        split = separate_person(cleaned, cfg.scene)
        points = points[raw_points_kept(points, cleaned, split.keep)]
        cleaned = cleaned[split.keep]
        summary = split.summary()
    order = np.random.default_rng(cfg.seed).permutation(len(cleaned))
    return PreparedScan(points, cleaned, order, summary, scan, made_with)


def principal_extent(cleaned: np.ndarray) -> float:
    """The largest extent (m) of the points (M, 3) along their principal axes: however the scan is turned."""
    _, _, axes = np.linalg.svd(cleaned - cleaned.mean(0), full_matrices=False)
    return largest_extent(cleaned @ axes.T)


def refine_start(
    cfg: ScanFitConfig, model: BodyModel, shape: np.ndarray, coordinates: np.ndarray, root: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[ScanPhase, ...]]:
    """The body a refinement starts from, as float arrays: shape (n_shape,), coordinates (n_dof,), root (3,);
    and the phases it runs (``cfg.refine_from`` on).

    Raises:
        ValueError: an array of the wrong shape or not finite, or ``cfg.refine_from`` names no phase.
    """
    sizes = {"shape": model.n_shape, "coordinates": model.skeleton.n_dof, "root": 3}
    c, q, r = (np.asarray(value, np.float64) for value in (shape, coordinates, root))
    for (name, size), value in zip(sizes.items(), (c, q, r), strict=True):
        if value.shape != (size,) or not np.isfinite(value).all():
            raise ValueError(f"{name} must be a finite ({size},) array; got shape {value.shape}")
    names = [phase.stage.name for phase in cfg.phases]
    if cfg.refine_from not in names:
        raise ValueError(f"refine_from names no phase: {cfg.refine_from!r} is not in {names}")
    return c, q, r, cfg.phases[names.index(cfg.refine_from) :]


def branch_bounds(cfg: ScanFitConfig) -> tuple[int, int, tuple[ScanBranch, ...]]:
    """The indices of the first branched phase and of the first phase after the branches
    (``cfg.branch_from`` and ``cfg.branch_until``: the number of phases when there is none), and the
    branches that run (the first alone when no phase branches)."""
    names = [phase.stage.name for phase in cfg.phases]
    if cfg.branch_from not in names:
        return len(names), len(names), cfg.branches[:1]
    split = names.index(cfg.branch_from)
    until = names.index(cfg.branch_until) if cfg.branch_until in names[split + 1 :] else len(names)
    return split, until, cfg.branches


def gather_branches(
    run_branch: Callable[[int], BranchRun], count: int, remote: RemoteBranch | None, run: PhaseRun
) -> tuple[list[BranchRun], Hypotheses | None]:
    """Each of the ``count`` branches' runs, in order; and the second branch's hypotheses when the helper
    process ran it (``remote``; its progress lines are reported on ``run``), else None. Without ``remote``
    the branches run at once on the run's threads; with it, the first runs here (and the second too when
    the helper failed meanwhile)."""
    if remote is None:
        return list(run.pool.map(run_branch, range(count))), None  # at once, on the pool's threads
    try:
        ran = [run_branch(0)]
    finally:
        theirs = remote()
    if theirs is None:
        ran.append(run_branch(1))
        return ran, None
    hyp, n_iter, losses, lines = theirs
    ran.append((n_iter, losses))
    for line in lines:
        run.report(line)
    return ran, hyp


def gather_shards(
    step: Callable[[Hypotheses, Mapper], tuple[int, np.ndarray]],
    parts: list[Hypotheses],
    remote: RemoteShard | None,
    run: PhaseRun,
) -> tuple[int, np.ndarray]:
    """The first half's iterations and both halves' scores (H,) of a phase's ``step`` on the two halves
    ``parts`` (the second replaced by the helper's when ``remote`` ran it): without ``remote`` both run at
    once on the run's threads; with it, the first runs here (and the second too when the helper failed
    meanwhile)."""
    if remote is None:
        steps = run.pool.map(lambda part: step(part, map), parts)
        (iterations, score), (_, second) = steps
    else:
        try:
            iterations, score = step(parts[0], run.pool.map)
        finally:
            theirs = remote()
        if theirs is None:  # the helper failed meanwhile
            _, second = step(parts[1], run.pool.map)
        else:
            parts[1], second = theirs
    return iterations, np.concatenate([score, second])


@dataclass
class PhaseRun:
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
