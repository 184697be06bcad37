"""How a raw scan is fitted (:class:`.fitter.ScanFitter`): its phases, its branches and the settings.

The phases and their numbers are explained where the fitter is (:mod:`.fitter`); they are tuned on the
held-out scans of ``benchmarks/fit_scans.py`` and ``benchmarks/fit_busts.py``. Every config here is
keyword-only and checks its values where it is built, so a typo fails there rather than deep inside a fit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from bodyfit.models.fitting.common.nonrigid import NonRigidConfig
from bodyfit.models.fitting.registered.stages import Stage, check_at_least
from bodyfit.models.fitting.scan.scene import SceneConfig


@dataclass(frozen=True, kw_only=True)
class ScanPhase:
    """``stage.iterations`` L-BFGS iterations of ``stage`` on the robust two-way Chamfer loss.

    sigma_mm: Geman-McClure scale; keep: orientation candidates kept after the phase; scan_points: scan
    points used (a random subset of the cleaned scan); plane: point-to-plane distances (model normals) for
    the scan -> model term instead of point-to-point; two_way: False keeps the model -> scan term only (a
    part of the body fitted inside the whole scan); search_limbs: a grid search of the limbs' poses
    (:class:`.limb_search.LimbSearch`) before the phase; search_distal: a grid search of the head, hands
    and toes (:data:`.fitter.DISTAL_SEARCH`) before the phase; straighten: before the phase (and the
    searches), add to the best :data:`.fitter.STRAIGHTENED` hypotheses of a full scan a twin with a
    straight spine (:meth:`.fitter.ScanFitter._straighten_spine`; single-view scans go without, as their
    twins are picked wrongly);
    scapula_twin: before the phase (and the searches), add to every hypothesis a twin with the scapulae at
    the middle of their ranges (:meth:`.fitter.ScanFitter._scapula_twin`);
    flipped_margin: after the phase, also keep the best hypothesis that faces the other way from the best
    one (forward axes more than 90 degrees apart) when its score is within this fraction of the best's;
    rounds: the phase's L-BFGS runs this many times, ``stage.iterations`` each, every round from a fresh
    start where the last ended (the single view's visible vertices and, in a metric phase, the Gauss-Newton
    metric taken again there; the searches run before the first round only);
    cloth_sigma_mm: when positive (a point-to-plane phase only), the loss is one-sided: pairs whose scan
    point lies outside the body take this smaller Geman-McClure scale, keeping the body inside loose
    clothing (:func:`.losses.chamfer_term`);
    one_per_frame: after the phase, of the hypotheses that share a body frame (an orientation candidate's
    arm starts, :data:`.hypotheses.ARM_STARTS`), only the best can go on.

    Raises:
        ValueError: a scale that is not positive, fewer than one hypothesis kept, scan point or round, or a
            negative margin (the message names the field).
    """

    stage: Stage
    sigma_mm: float
    keep: int
    scan_points: int
    plane: bool = False
    two_way: bool = True
    search_limbs: bool = False
    search_distal: bool = False
    straighten: bool = False
    scapula_twin: bool = False
    flipped_margin: float = 0.0
    rounds: int = 1
    cloth_sigma_mm: float = 0.0
    one_per_frame: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.stage, Stage):
            raise ValueError(f"ScanPhase.stage must be a Stage; got {self.stage!r}")
        if not self.sigma_mm > 0:
            raise ValueError(f"ScanPhase.sigma_mm must be positive; got {self.sigma_mm!r}")
        for name in ("keep", "scan_points", "rounds"):
            check_at_least("ScanPhase", name, getattr(self, name), 1)
        check_at_least("ScanPhase", "flipped_margin", self.flipped_margin, 0.0)
        check_at_least("ScanPhase", "cloth_sigma_mm", self.cloth_sigma_mm, 0.0)
        if self.cloth_sigma_mm > 0 and not self.plane:
            raise ValueError("ScanPhase.cloth_sigma_mm needs a point-to-plane phase (plane=True)")


# A body seen from behind can fit a scan nearly as well as the right one until its limbs are posed (the CC BY
# T-posed man as bare points: 1.2% below the right heading after the shape phase, 12% above it after the
# limbs phase), while on held-out synthetic scans the best hypothesis facing the other way scores 28-74% above
# the best after the shape phase: a margin of 5% keeps the near-ties only.
FLIPPED_MARGIN = 0.05


DEFAULT_PHASES = (
    ScanPhase(
        stage=Stage(name="orient", coordinates="core", shape="none", vertices="coarse", iterations=25),
        sigma_mm=150.0,
        keep=3,
        scan_points=500,
        one_per_frame=True,
    ),
    ScanPhase(
        stage=Stage(name="pose", coordinates="all", shape="bone", vertices="subset", iterations=30),
        sigma_mm=60.0,
        keep=2,
        scan_points=1500,
        search_limbs=True,
        straighten=True,
    ),
    ScanPhase(
        stage=Stage(name="shape", coordinates="all", shape="all", vertices="subset", iterations=30),
        sigma_mm=25.0,
        keep=1,
        scan_points=3000,
        flipped_margin=FLIPPED_MARGIN,
    ),
    ScanPhase(
        stage=Stage(name="limbs", coordinates="all", shape="all", vertices="subset", iterations=20),
        sigma_mm=25.0,
        keep=2,
        scan_points=3000,
        search_limbs=True,
        search_distal=True,
        scapula_twin=True,
    ),
    ScanPhase(
        stage=Stage(name="fine", coordinates="all", shape="all", vertices="dense", iterations=15),
        sigma_mm=10.0,
        keep=1,
        scan_points=4000,
        plane=True,
        search_distal=True,
        rounds=2,
    ),
    ScanPhase(
        stage=Stage(name="valley", coordinates="all", shape="all", vertices="dense", iterations=25),
        sigma_mm=10.0,
        keep=1,
        scan_points=4000,
        plane=True,
    ),
)

# A scan smaller than a body (:attr:`ScanFitConfig.partial_extent`) is fitted as a head and shoulders: the
# "upper" vertex set (RegisteredFitter.index) placed by the trunk's, neck's and scapulae's DOFs, the rest of
# the body in the start pose, and the whole scan fitted two ways in three phases. The full-body phases would
# fold the whole body into a bust. The shape is fitted in the last phase only, once the bust is in place:
# fitted before, it grows shoulders into the scan to make up for a wrong placement. The first phase's scale
# is 40 mm because forearms in the crop then tilt the trunk less than at 80 (benchmarks/fit_busts.py: heads
# within 10 mm, 74% against 68%).
UPPER_BODY_PHASES = (
    ScanPhase(
        stage=Stage(name="upper_orient", coordinates="upper", shape="none", vertices="upper", iterations=30),
        sigma_mm=40.0,
        keep=3,
        scan_points=1500,
    ),
    ScanPhase(
        stage=Stage(name="upper_pose", coordinates="upper", shape="none", vertices="upper", iterations=40),
        sigma_mm=30.0,
        keep=1,
        scan_points=3000,
    ),
    ScanPhase(
        stage=Stage(name="upper_fine", coordinates="upper", shape="all", vertices="upper", iterations=40),
        sigma_mm=12.0,
        keep=1,
        scan_points=4000,
    ),
)
# What the vertex set a scan is fitted with ("all" or "upper") is called in reports.
PART_NAMES = {"all": "whole body", "upper": "head and shoulders"}
# A head and shoulders measures 0.4-0.7 m, up to 0.85 with an arm reaching out (benchmarks/fit_busts.py); the
# 102 whole bodies of benchmarks/fit_scans.py 1.27 m or more (a depth view), a crouching adult about 0.9.
PARTIAL_EXTENT_M = 0.85


# On the quick scan benchmark's fits, the share of the observed surface that the scan stands more than 5 mm
# off: 15-16% with the 3 cm clothing offset, at most 2% on the clean, noisy, holed, single-view and outlier
# scans (a hand fitted wrong over a hole).
CLOTHED_FRACTION = 0.06


@dataclass(frozen=True, kw_only=True)
class ClothingConfig:
    """When and how a scan is fitted as a body under loose clothing (:mod:`.clothing`). After the phases,
    the scan's outward offset over the fitted body (:func:`.clothing.clothing_field`: the median of the
    ``neighbours`` nearest cleaned points' signed offsets) is measured; when it exceeds ``threshold_mm``
    over more than ``min_fraction`` of the observed surface, the scan counts as clothed: ``phases``
    (one-sided, ``cloth_sigma_mm``) fit the body inside the cloth, and the registration is the body under
    it, with the clothing offset reported alongside (``report.extra["clothing"]``). When the body fitted
    inside stands more than ``bare_mm`` (median) under the scan at the head and hands too, which cloth
    leaves bare, the scan is taken for a bare body the shape space cannot match (on the CC BY man: 3.3 mm,
    against 0.5 under a synthetic loose shirt and trousers) and the fit before the clothing phases is kept."""

    threshold_mm: float = 5.0
    min_fraction: float = CLOTHED_FRACTION
    bare_mm: float = 2.0
    neighbours: int = 48
    phases: tuple[ScanPhase, ...] = ()

    def __post_init__(self) -> None:
        check_at_least("ClothingConfig", "threshold_mm", self.threshold_mm, 0.0)
        check_at_least("ClothingConfig", "min_fraction", self.min_fraction, 0.0)
        check_at_least("ClothingConfig", "bare_mm", self.bare_mm, 0.0)
        check_at_least("ClothingConfig", "neighbours", self.neighbours, 1)
        for phase in self.phases:
            if not phase.cloth_sigma_mm > 0:
                raise ValueError(f"ClothingConfig.phases must be one-sided; {phase.stage.name!r} is not")


# The body inside the cloth: the dense vertex set, point-to-plane, the clothing side at a 2 mm scale (a point
# 5 mm outside the body pulls it out a sixth as hard as at 2 mm, one 20 mm out hardly at all); the head, hands
# and toes searched again, as a trunk fitted to the cloth turns the neck and shoulders to make up for it.
CLOTHING_PHASES = (
    ScanPhase(
        stage=Stage(name="cloth", coordinates="all", shape="all", vertices="dense", iterations=40),
        sigma_mm=10.0,
        keep=1,
        scan_points=4000,
        plane=True,
        search_distal=True,
        rounds=2,
        cloth_sigma_mm=2.0,
    ),
)


@dataclass(frozen=True, kw_only=True)
class ScanBranch:
    """One way to run the phases from :attr:`ScanFitConfig.branch_from` on: metric_phases: the phases
    (by name) whose L-BFGS runs in the variables of the loss's Gauss-Newton metric
    (:meth:`.fitter.ScanFitter._metric`); damping: the metric's ``regularise``."""

    metric_phases: frozenset[str]
    damping: float

    def __post_init__(self) -> None:
        check_at_least("ScanBranch", "damping", self.damping, 0.0)


# Two branches from the shape phase to the valley phase, and the one whose hypothesis scores best after the
# first point-to-plane phase goes on. The second runs the subset phases in the metric too, with more damping:
# either alone ends in a gross error (an arm or the head placed wrong) on scans where the other does not. The
# point-to-plane phase's robust score picks between them better than the refined registrations' distance to
# the scan would, since a non-rigid registration lies close to the scan even where its body does not
# (benchmarks/fit_scans.py gives the current numbers).
DEFAULT_BRANCHES = (
    ScanBranch(metric_phases=frozenset({"fine", "valley", "cloth"}), damping=1e-3),
    ScanBranch(metric_phases=frozenset({"shape", "limbs", "fine", "valley", "cloth"}), damping=1e-2),
)


@dataclass(frozen=True, kw_only=True)
class ScanFitConfig:
    """voxel: cleaning grid (m); neighbours, outlier_cutoff: a point is dropped when its mean distance to
    its neighbours exceeds the median by ``outlier_cutoff`` robust standard deviations; tangential: weight
    of the in-plane part of point-to-plane distances; nonrigid: None skips the refinement; single_view:
    detect one sensor's view (:func:`.view.view_direction`) and then fit only the surface that faced it;
    branches: each runs the phases from the one named ``branch_from`` up to the one named ``branch_until``
    (the earlier ones run once, as the first branch says; no phase of that name: to the end); the branch
    whose hypothesis scores best on the last branched phase goes on alone, the way it says; one branch, or
    no phase named ``branch_from``, fits once; workers: threads the branches run on at once (they are
    independent, so the fit does not depend on it; torch's intra-op threads add little at these sizes:
    ``torch.set_num_threads(1)`` and 2 workers suit 2 cores); processes: 2 starts a helper process
    (:class:`.helper.ScanHelper`, its own copy of the fitter: ready about 1.5 s later, 0.5 GB)
    that runs the second branch and half of the hypotheses of the phases before the branches on another
    core (the fit is bound by the interpreter lock, so threads alone share one core's worth of Python); it
    suits a long-lived fitter (the service, a batch of scans), not a single fit. Work the helper cannot
    take (starting, busy with another fit's, or failed) runs in the calling process; the fit is the same
    either way (the hypotheses are independent problems, and the phases before the branches run them in
    the same two halves however many processes there are); partial_extent: a cleaned scan whose largest
    extent along its principal axes (:func:`bodyfit.io.scans.largest_extent`) is below this (m) is fitted as a
    head and shoulders by ``partial_phases`` (:data:`UPPER_BODY_PHASES`), never confidently; 0 turns that
    off; refine_from: the phase from which :meth:`.fitter.ScanFitter.refine` runs (a body already in
    place: the point-to-plane phases); scene: how the person is separated from floors, walls, furniture and
    fragments before a fit (:func:`.scene.separate_person`; the report's ``extra["scene"]`` says what was
    removed, and a scan with no person in it is refused); None fits every cleaned point; clothing: when a
    whole-body scan counts as clothed and how the body is then fitted under the cloth
    (:class:`ClothingConfig`); None fits the scan's surface as skin."""

    phases: tuple[ScanPhase, ...] = DEFAULT_PHASES
    branches: tuple[ScanBranch, ...] = DEFAULT_BRANCHES
    branch_from: str = "shape"
    branch_until: str = "valley"
    voxel: float = 0.01
    neighbours: int = 8
    outlier_cutoff: float = 3.0
    tangential: float = 0.1
    nonrigid: NonRigidConfig | None = field(default_factory=NonRigidConfig)
    single_view: bool = True
    seed: int = 0
    workers: int = 2
    processes: int = 1
    partial_phases: tuple[ScanPhase, ...] = UPPER_BODY_PHASES
    partial_extent: float = PARTIAL_EXTENT_M
    refine_from: str = "fine"
    scene: SceneConfig | None = field(default_factory=SceneConfig)
    clothing: ClothingConfig | None = field(default_factory=lambda: ClothingConfig(phases=CLOTHING_PHASES))

    def __post_init__(self) -> None:
        if self.processes not in (1, 2):
            raise ValueError(f"processes must be 1 or 2 (a helper process), not {self.processes}")
        check_at_least("ScanFitConfig", "len(phases)", len(self.phases), 1)
        check_at_least("ScanFitConfig", "len(branches)", len(self.branches), 1)
        check_at_least("ScanFitConfig", "workers", self.workers, 1)
        check_at_least("ScanFitConfig", "partial_extent", self.partial_extent, 0.0)
        if self.partial_extent > 0:
            check_at_least("ScanFitConfig", "len(partial_phases)", len(self.partial_phases), 1)
