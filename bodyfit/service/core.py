"""The transport-neutral service core: loads the model once, then synthesizes, fits and streams.

REST and gRPC call the same :class:`BodyService` methods; they only translate wire formats and map
:mod:`bodyfit.service.errors` to statuses. The service holds read-only model buffers, an ONNX Runtime
session and a semaphore bounding concurrent heavy work; one instance serves concurrent requests.
"""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import torch

from bodyfit.io.scans import Scan
from bodyfit.io.smpl import SmplSequence
from bodyfit.models.assets import read_manifest, verified_asset
from bodyfit.models.body.model import BodyModel
from bodyfit.models.body.onnx_export import BODY_ONNX
from bodyfit.models.fitting.common.report import FitReport
from bodyfit.models.fitting.registered.fitter import BodyFit, FixedBody, RegisteredFitter
from bodyfit.models.fitting.registered.smpl_topology import SMPL_VERTICES, fit_smpl_mesh
from bodyfit.models.fitting.scan.config import ScanFitConfig
from bodyfit.models.fitting.scan.fitter import ScanFit, ScanFitter
from bodyfit.models.fitting.scan.phases import PreparedScan, prepare_scan
from bodyfit.models.fitting.sequence.fitter import SequenceFit, SequenceFitter, SequenceFrames
from bodyfit.models.rig.subject import Subject
from bodyfit.models.upgrade.axes import up_axis_name
from bodyfit.models.upgrade.inputs import check_axis_angle, layout_error
from bodyfit.models.upgrade.proxy import ShapeHintError, ShapeHints, SmplProxy, load_proxy
from bodyfit.models.upgrade.smpl_model import SmplModel, load_smpl_model
from bodyfit.models.upgrade.upgrade import (
    UpgradeResult,
    upgrade_fitter,
    upgrade_from_rotations,
    upgrade_with_model,
    write_upgrade,
)
from bodyfit.service import uploads
from bodyfit.service.batching import Outputs, SynthBatcher
from bodyfit.service.errors import BusyError, InvalidInputError, LimitExceededError
from bodyfit.service.formats import Bodies
from bodyfit.service.hints import ScanHints, height_check, hint_use
from bodyfit.service.jobs import Job
from bodyfit.service.limits import Limits
from bodyfit.service.personal import check_alone, personal_body
from bodyfit.service.synthesis import SynthRequest, batch_of, synthesis_parameters
from bodyfit.service.uploads import SEQUENCE_BYTES_PER_FRAME
from bodyfit.service.validation import (
    check_finite_result,
    check_frames,
    check_scan,
    invalid_input,
)
from bodyfit.wire import Dof, FittedAs, MeshSizes, ModelInfo, ShapeSizes
from bodyfit.wire.measure import MeasurementInfo, Measurements

LOG = logging.getLogger("bodyfit.service")


def model_info(model: BodyModel, manifest: dict[str, Any]) -> ModelInfo:
    """What clients need to build requests (``GET /v1/model``) for a loaded ``model`` and its asset
    ``manifest``: DOF names, ranges and units ("rad" / "m"), shape coefficient counts, mesh sizes, joint
    names, and the package version with each asset file's sha256."""
    skel = model.skeleton
    try:
        pkg = version("bodyfit")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
        pkg = "unknown"
    files = manifest.get("files", {})
    return ModelInfo(
        version=pkg,
        dofs=tuple(
            Dof(name=name, min=float(lo), max=float(hi), unit="m" if c.motion == "translational" else "rad")
            for name, (lo, hi), c in zip(model.dof_names, skel.ranges, skel.spec.coordinates, strict=True)
        ),
        shape=ShapeSizes(n_bone=model.n_bone, n_identity=model.n_identity, n_shape=model.n_shape),
        mesh=MeshSizes(n_vertices=model.n_vertices, n_faces=len(model.faces)),
        joint_names=tuple(model.joint_names),
        assets={
            "format": str(manifest.get("format", "")),
            "sources": dict(manifest.get("sources", {})),
            "sha256": {name: str(entry.get("sha256", "")) for name, entry in files.items()},
        },
    )


@dataclass(frozen=True)
class PendingSynthesis:
    """A validated synthesis whose model call is queued: ``future`` gives (vertices, joints); ``body``: the
    subject's body that posed it (its decoder, not the ONNX session), or None."""

    request: SynthRequest
    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    future: Future[Outputs]
    body: FixedBody | None = None


# how :meth:`BodyService.fit_mesh` fits a mesh (:meth:`BodyService.route`), as ``MeshFit.fitted_as`` says
REGISTERED: FittedAs = "registered"
SMPL_TOPOLOGY: FittedAs = "SMPL topology"
RAW_SCAN: FittedAs = "raw scan"


@dataclass(frozen=True)
class MeshFit:
    """One fitted mesh or scan: how it was fitted (:data:`REGISTERED`, :data:`SMPL_TOPOLOGY` or
    :data:`RAW_SCAN`), the parameters shape (n_shape,), coordinates (n_dof,), root (3,), the registration
    ``vertices`` (V, 3) in our topology, ``joints`` (J, 3), the error report, and ``to_model`` (4, 4).

    One frame convention for every route: ``vertices`` and ``joints`` lie in the input's own frame (on the
    uploaded mesh or scan), and ``to_model`` is the rigid map from the input's frame to the frame in which
    the parameters pose the body: ``model.forward(shape, coordinates, root)`` gives (before the non-rigid
    refinement) ``vertices @ R.T + t`` with ``R, t = to_model[:3, :3], to_model[:3, 3]``. It is the identity
    when the parameters themselves hold the input's placement (registered meshes; raw scans of an upright-ish
    body)."""

    fitted_as: FittedAs
    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    report: FitReport
    to_model: np.ndarray = field(default_factory=lambda: np.eye(4))

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "shape": self.shape,
            "coordinates": self.coordinates,
            "root": self.root,
            "vertices": self.vertices,
            "joints": self.joints,
            "to_model": self.to_model,
        }


@dataclass
class _Fitters:
    registered: RegisteredFitter
    scan: ScanFitter
    sequence: SequenceFitter
    upgrade: SequenceFitter
    proxy: SmplProxy


@dataclass
class BodyService:
    """The loaded model and fitters; build with :meth:`load` (once per process). ``scan_processes`` is read
    when the fitters are built (:attr:`fitters`: at load, or on first use with ``fitters=False``)."""

    model: BodyModel
    session: ort.InferenceSession
    limits: Limits = field(default_factory=Limits)
    manifest: dict[str, Any] = field(default_factory=dict)
    smpl_model_path: Path | None = None
    assets: Path | None = None
    scan_processes: int = 1
    _fitters: _Fitters | None = None
    _smpl: SmplModel | None = None
    _slots: threading.BoundedSemaphore = field(init=False)
    _batcher: SynthBatcher = field(init=False)

    def __post_init__(self) -> None:
        self._slots = threading.BoundedSemaphore(self.limits.max_concurrent)
        self._batcher = SynthBatcher(self.session, max_bodies=self.limits.max_batch)
        self._faces = self.model.faces.astype(np.int32)
        self._info = model_info(self.model, self.manifest)

    @classmethod
    def load(
        cls,
        assets: Path | None = None,
        limits: Limits | None = None,
        threads: int | None = None,
        fitters: bool = True,
        smpl_model: Path | None = None,
        scan_processes: int = 1,
    ) -> BodyService:
        """Load the hash-checked assets, the ONNX session and the fitters.

        Args:
            assets: asset folder (default: the checkout's assets/ or $BODYFIT_ASSETS).
            limits: request limits.
            threads: threads of ONNX Runtime (default: its own choice) and torch (default 1), set once for
                the process.
            fitters: build the fitters now (a server); otherwise on first use (synthesis only).
            smpl_model: an SMPL-family model file for upgrades (path a); checked now when given.
            scan_processes: 2 gives the raw-scan fitter a helper process (``ScanFitConfig.processes``:
                about 20% faster per scan on two cores, 0.5 GB more memory), started with the fitters.
        Raises:
            AssetError: a missing or corrupted asset, with how to rebuild it.
        """
        began = time.perf_counter()
        LOG.info("loading the body model from %s", assets or "the built-in assets")
        model = BodyModel.load(assets)
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = threads
            options.inter_op_num_threads = 1
        # Set once for the process, never per request: the fits' own workers, the scan helper process and
        # concurrent requests use the cores, and more intra-op threads crowd them (a clean raw scan took
        # 3.8-4.0 s with two torch threads and the helper against 3.2-3.4 s with one, BENCHMARKS.md).
        torch.set_num_threads(threads or 1)
        LOG.info("body model loaded (%.1f s); starting the ONNX Runtime session", time.perf_counter() - began)
        session = ort.InferenceSession(
            str(verified_asset(BODY_ONNX, assets)), options, providers=["CPUExecutionProvider"]
        )
        service = cls(
            model, session, limits or Limits(), read_manifest(assets), smpl_model, assets, scan_processes
        )
        if smpl_model is not None:
            LOG.info("loading the SMPL-family model %s for upgrades", smpl_model)
            service._smpl = load_smpl_model(smpl_model)
        if fitters:
            LOG.info(
                "building the fitters (%.1f s so far; %s)",
                time.perf_counter() - began,
                "starting the scan helper process" if scan_processes > 1 else "no scan helper process",
            )
            _ = service.fitters
        LOG.info("ready to serve (%.1f s)", time.perf_counter() - began)
        return service

    @property
    def fitters(self) -> _Fitters:
        """The registered, scan, sequence and upgrade fitters (built on first use)."""
        if self._fitters is None:
            registered = RegisteredFitter(self.model)
            self._fitters = _Fitters(
                registered,
                ScanFitter(self.model, ScanFitConfig(processes=self.scan_processes), registered),
                SequenceFitter(registered),
                upgrade_fitter(registered),
                load_proxy(self.assets),
            )
        return self._fitters

    # -- info ------------------------------------------------------------------------------------------
    def info(self) -> ModelInfo:
        return self._info

    def subject_body(self, subject: bytes | Subject | None) -> FixedBody | None:
        """A request's subject file as the person's body (:func:`bodyfit.service.personal.personal_body`):
        transports call it before any work starts, so that a bad subject is refused up front.

        Raises:
            InvalidInputError: an empty upload, not a subject file, a damaged one or one built for another
                body model (field ``subject``).
        """
        return personal_body(self.model, subject)

    # -- synthesis -------------------------------------------------------------------------------------
    def synthesize(self, request: SynthRequest) -> Bodies:
        """Parameters -> posed skin and joints (ONNX Runtime), and the posed bone mesh when asked for.

        Raises:
            InvalidInputError: wrong shapes, NaN, unknown DOF names, out-of-range values (the message
                names the field and the fix).
            LimitExceededError: more bodies than ``limits.max_batch``.
        """
        pending = self.start_synthesis(request)
        return self.finish_synthesis(pending, *pending.future.result())

    def with_built_shape(self, request: SynthRequest) -> tuple[SynthRequest, Measurements | None]:
        """``request`` with the shape of the body built from its ``measurements`` (every one of its B
        bodies has it), and the :meth:`measure` answer of that build (requested, achieved, residuals,
        unmet); ``request`` itself and None when it asks for no measurements.

        Raises:
            InvalidInputError: both shape and measurements, sex without measurements, an unknown
                measurement name (with the closest names) or an implausible value (with its range); a
                subject with shape, measurements or sex, or a subject file that cannot be used.
        """
        if request.subject is not None:
            body = self.subject_body(request.subject)
            check_alone(body, [(n, getattr(request, n)) for n in ("shape", "measurements", "sex")])
            return request, None
        if request.measurements is None:
            if request.sex is not None:
                raise InvalidInputError("sex goes with measurements (a body built from them)", field="sex")
            return request, None
        if request.shape is not None:
            raise InvalidInputError(
                "give shape or measurements, not both: the body built from measurements has its own shape",
                field="measurements",
            )
        batch = batch_of(request)
        if batch > self.limits.max_batch:
            raise LimitExceededError(
                f"{batch} bodies asked for in one call; the limit is {self.limits.max_batch}: split it",
                field="batch",
            )
        built = self.measure(measurements=dict(request.measurements), sex=request.sex)
        assert built.shape is not None
        shape = np.repeat(np.asarray(built.shape, np.float64), batch, 0)
        return replace(request, shape=shape, measurements=None, sex=None), built

    def start_synthesis(self, request: SynthRequest) -> PendingSynthesis:
        """Validate ``request`` (raising as :meth:`synthesize`) and queue its model call; concurrent
        requests share one call (:class:`SynthBatcher`). Await ``future`` then :meth:`finish_synthesis`.
        A request with measurements is built first (:meth:`with_built_shape`, whose report is dropped here);
        one with a subject is posed at once by the subject's decoder (the ONNX model has no personal
        template), its future already done.
        """
        request, _ = self.with_built_shape(request)
        q, root, shape = synthesis_parameters(request, self.model, self.limits.max_batch)
        body = self.subject_body(request.subject)
        if body is None:
            return PendingSynthesis(request, shape, q, root, self._batcher.submit(shape, q, root))
        shape = np.repeat(body.shape[None].astype(np.float32), len(q), 0)
        vertices, joints, _, _ = _posed(body, shape, q, root)
        done: Future[Outputs] = Future()
        done.set_result((vertices.numpy(), joints.numpy()))
        return PendingSynthesis(request, shape, q, root, done, body)

    def finish_synthesis(self, pending: PendingSynthesis, vertices: np.ndarray, joints: np.ndarray) -> Bodies:
        """The :class:`Bodies` of a finished model call, with the bone mesh posed when it was asked for."""
        bones = bone_faces = None
        if pending.request.skeleton and pending.body is not None:
            _, _, frames, scales = _posed(pending.body, pending.shape, pending.coordinates, pending.root)
            with torch.no_grad():
                bones = self.model.pose_bones(frames, scales).numpy().astype(np.float32)
            bone_faces = np.asarray(self.model.skeleton.bone_mesh().faces, np.int32)
        elif pending.request.skeleton:
            with torch.no_grad():
                out = self.model.forward(pending.shape, pending.coordinates, pending.root, skeleton_mesh=True)
            assert out.bones is not None
            bones = out.bones.numpy().astype(np.float32)
            bone_faces = np.asarray(self.model.skeleton.bone_mesh().faces, np.int32)
        check_finite_result(
            "synthesized bodies",
            {"vertices": vertices, "joints": joints, "bones": bones},
            "send shape coefficients and coordinates within their ranges (GET /v1/model)",
            "shape",
        )
        return Bodies(
            vertices=vertices,
            faces=self._faces,
            joints=joints,
            joint_names=tuple(self.model.joint_names),
            bones=bones,
            bone_faces=bone_faces,
        )

    # -- anthropometry --------------------------------------------------------------------------------
    def measure(
        self,
        request: SynthRequest | None = None,
        vertices: np.ndarray | None = None,
        measurements: dict[str, float] | None = None,
        sex: str | None = None,
    ) -> Measurements:
        """The anthropometric measurements (docs/anthropometry.md) of the bodies of ``request`` (its shape
        and coordinates; the measuring posture when it has none), of ``vertices`` (B, V, 3) in the model's
        topology, or of the body built from ``measurements`` for ``sex`` (with its shape and residuals).

        Raises:
            InvalidInputError: wrong shapes, values out of range, an unknown measurement name (with the
                closest names) or an implausible value (named, with its plausible range).
            LimitExceededError: more bodies than ``limits.max_batch``.
        """
        from bodyfit.models.anthropometry import definitions, inverse
        from bodyfit.models.anthropometry import measure as anthropometry

        built = None
        with self._slot(), invalid_input("measurements" if measurements is not None else "shape"):
            if measurements is not None:
                built = inverse.shape_from_measurements(self.model, measurements, sex)
                values = {k: np.asarray([v]) for k, v in built.achieved.items()}
            elif vertices is not None:
                values = anthropometry.measure_vertices(self.model, vertices)
            else:
                assert request is not None and request.shape is not None
                q, _, shape = synthesis_parameters(request, self.model, self.limits.max_batch)
                posed = None if request.coordinates is None else q
                values = anthropometry.measure(self.model, shape.astype(np.float64), posed)
        about = definitions.MEASUREMENTS
        return Measurements(
            measurements=[MeasurementInfo(name=k, kind=about[k].kind, unit=about[k].unit) for k in values],
            values={k: np.asarray(v, np.float64).tolist() for k, v in values.items()},
            shape=None if built is None else [built.shape.tolist()],
            requested=None if built is None else built.requested,
            residuals=None if built is None else built.residuals,
            unmet=[] if built is None else built.unmet,
            flagged=built is not None and built.flagged,
        )

    # -- fitting ---------------------------------------------------------------------------------------
    def read_scan(self, data: bytes, format: str, units: str = "auto") -> Scan:
        """Read an uploaded mesh or point cloud (:func:`bodyfit.service.uploads.read_scan`)."""
        return uploads.read_scan(data, format, units, self.limits)

    def read_sequence(self, data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
        """Read an uploaded registered sequence (:func:`bodyfit.service.uploads.read_sequence`)."""
        return uploads.read_sequence(data, self.limits, self.model.n_vertices)

    def route(self, scan: Scan) -> FittedAs:
        """How :meth:`fit_mesh` fits ``scan``: :data:`REGISTERED` (our topology's vertex count),
        :data:`SMPL_TOPOLOGY` (6,890 vertices with faces) or :data:`RAW_SCAN` (anything else)."""
        if scan.n_points == self.model.n_vertices:
            return REGISTERED
        if scan.n_points == SMPL_VERTICES and scan.faces is not None:
            return SMPL_TOPOLOGY
        return RAW_SCAN

    def check_scan(self, scan: Scan) -> Scan | PreparedScan:
        """Check, before any fitting, that ``scan`` can be the body :meth:`fit_mesh` fits it as
        (:func:`bodyfit.service.validation.check_scan`: a whole body for our topology and SMPL's). Returns
        it ready to fit: pass that to :meth:`fit_mesh`, which then neither checks nor cleans it again.

        Raises:
            InvalidInputError: what is wrong (degenerate, not human-sized, the wrong units) and the fix.
        """
        return check_scan(scan, whole_body=self.route(scan) != RAW_SCAN)

    def fit_mesh(
        self,
        scan: Scan | PreparedScan,
        job: Job | None = None,
        hints: ScanHints | None = None,
        body: FixedBody | None = None,
    ) -> MeshFit:
        """Fit one mesh or scan, routed by its topology: 13,348 vertices -> registered fit; 6,890 vertices
        with faces -> SMPL topology (placed through the stored map, then refined on the mesh's surface);
        anything else -> raw scan (orientation searched unless ``hints`` give it, no landmarks). The answer
        is in the input's frame with the map to the parameters' frame alongside (:class:`MeshFit`).

        ``hints`` (:meth:`ScanHints.given`, checked there): up and facing give a raw scan's orientation
        (both needed; not searched then) or an SMPL-topology mesh's (in place of SMPL's +Y up, facing +Z);
        the pose class gives a raw scan's start pose; the height is checked against the fitted body's (a
        difference over :data:`~bodyfit.service.hints.HEIGHT_TOLERANCE_M` makes the fit not confident);
        sex is recorded. The report's ``extra["hints"]`` says how each given hint was used. ``body``: a
        subject's (:meth:`subject_body`), whose shape and template are held fixed: only the orientation,
        pose and root are fitted. ``scan`` may be :meth:`check_scan`'s answer (checked and cleaned once).

        Raises:
            InvalidInputError: a scan that cannot be a body (:meth:`check_scan`), found so during the
                fit, or whose fit is not finite.
            BusyError: no worker slot within ``limits.queue_seconds``.
            JobCancelledError: ``job`` was cancelled (the client went away).
            DeadlineExceededError: ``job`` ran past its time limit.
        """
        job = job or Job(timeout_s=self.limits.max_seconds)
        ready = scan if isinstance(scan, PreparedScan) else self.check_scan(scan)
        scan = _source(ready)
        with self._slot(), invalid_input("file"):
            fitters = self.fitters
            route = self.route(scan)
            # a scan fit says how many steps it takes once it knows what it fits (a whole body here)
            total = fitters.scan.progress_steps() if route == RAW_SCAN else 1
            job.report("fit", 0, total, f"{scan.n_points:,} points")

            def progress(done: int, steps: int, line: str) -> None:
                nonlocal total
                total = steps
                job.report("fit", done, steps, line)

            fit = _fit_routed(fitters, route, ready, progress, hints or ScanHints(), body)
            check_finite_result(
                "fit",
                {**fit.arrays(), "report distances": np.array(fit.report.distances.mean)},
                "the input is probably not a body, or not in metres: check the file and its units",
                "file",
            )
            job.report("fit", total, total, "done")
            return fit

    def check_sequence(self, frames: np.ndarray, weights: np.ndarray | None = None) -> None:
        """Check a registered sequence before any fitting: at most ``limits.max_frames`` frames, then
        :func:`check_frames` (dtype, shape, finite in float32, weights, every frame a human-sized body).

        Raises:
            LimitExceededError: too many frames.
            InvalidInputError: what is wrong and the fix.
        """
        x = np.asarray(frames)
        limit, fix = self.frame_limit(SEQUENCE_BYTES_PER_FRAME)
        if x.ndim >= 1 and len(x) > limit:
            raise LimitExceededError(f"{len(x):,} frames sent; the limit is {limit:,}: {fix}", field="frames")
        check_frames(x, weights, self.model.n_vertices)

    def fit_sequence(
        self,
        frames: np.ndarray,
        weights: np.ndarray | None = None,
        job: Job | None = None,
        checked: bool = False,
        on_frames: Callable[[SequenceFrames], None] | None = None,
        body: FixedBody | None = None,
    ) -> SequenceFit:
        """Fit a registered sequence (T, V, 3) of one person (one shape, per-frame pose). ``checked``: the
        caller ran :meth:`check_sequence` on these arrays already (it runs here otherwise). ``on_frames``:
        called with each block of final frames while the fit runs, in time order, every frame once
        (:meth:`bodyfit.models.fitting.sequence.fitter.SequenceFitter.fit_frames`), each block checked
        finite first, so that a transport streams the first frames while the rest are fitted. ``body``: a
        subject's (:meth:`subject_body`): no shape fit, every frame posed with the subject's body.

        Raises:
            InvalidInputError: wrong shape or dtype, NaN, no frames, a frame that is not a body
                (:meth:`check_sequence`), or a fit that is not finite.
            LimitExceededError: more than ``limits.max_frames`` frames.
            BusyError: no worker slot within ``limits.queue_seconds``.
            JobCancelledError: ``job`` was cancelled (the client went away).
            DeadlineExceededError: ``job`` ran past its time limit.
        """
        job = job or Job(timeout_s=self.limits.max_seconds)
        x = np.asarray(frames)
        if not checked:
            self.check_sequence(x, weights)
        with self._slot():
            job.report("fit", 0, max(len(x), 1), "shape and keyframes")

            def progress(done: int, total: int) -> None:
                job.report("fit", done, total, f"{done}/{total} frames")

            def checked_frames(block: SequenceFrames) -> None:
                _check_sequence_frames(block)
                if on_frames is not None:
                    on_frames(block)

            with invalid_input("frames"):
                fitter = self.fitters.sequence if body is None else self.fitters.sequence.for_body(body)
                fit = fitter.fit(
                    x, weights, progress=progress, on_frames=None if on_frames is None else checked_frames
                )
            _check_sequence_fit(fit)
            return fit

    # -- SMPL upgrade ----------------------------------------------------------------------------------
    def read_upgrade(self, data: bytes, filename: str) -> SmplSequence:
        """Read an uploaded AMASS-style .npz (:func:`bodyfit.service.uploads.read_upgrade`); poses in
        another rotation layout (rotation matrices, quaternions, 6D) or in degrees are refused naming the
        expected one (:mod:`bodyfit.models.upgrade.inputs`).

        Raises:
            LimitExceededError: too large or too many frames; InvalidInputError: unreadable or malformed.
        """
        try:
            sequence = uploads.read_upgrade(data, filename, self.limits)
        except InvalidInputError:
            found = layout_error(data, filename or "upload.npz")
            if found is not None:
                raise InvalidInputError(str(found), field="file") from None
            raise
        with invalid_input("file"):
            check_axis_angle(sequence)
        return sequence

    def upgrade(
        self,
        sequence: SmplSequence,
        job: Job | None = None,
        hints: ShapeHints | None = None,
        up: str | None = None,
        body: FixedBody | None = None,
    ) -> UpgradeResult:
        """Upgrade an SMPL-format sequence: path (a) with the server's SMPL-family model file, else path (b)
        from the joint rotations, its shape from ``hints`` (see :func:`shape_hints`) or the population
        mean (the result's notes say which ran). ``up``: the input's up axis (see :func:`upgrade_up`);
        None: detected from the motion. ``body``: a subject's (:meth:`subject_body`), whose shape, template
        and skeleton are held fixed (path (a) poses the SMPL meshes from the sequence's betas still, but fits
        only the poses to them); the .osim carries the subject's bone scales.

        Raises:
            InvalidInputError: a sequence found unusable during the work, or whose result is not finite;
                shape hints together with a subject.
            BusyError: no worker slot within ``limits.queue_seconds``.
            JobCancelledError: ``job`` was cancelled (the client went away).
            DeadlineExceededError: ``job`` ran past its time limit.
        """
        job = job or Job(timeout_s=self.limits.max_seconds)
        check_alone(body, [("shape hints (sex, height_m, mass_kg)", hints)])
        with self._slot():
            job.report("upgrade", 0, sequence.n_frames, "posing the SMPL meshes")

            def progress(done: int, total: int) -> None:
                job.report("upgrade", done, total, f"{done}/{total} frames")

            with invalid_input("file"):
                fitters = self.fitters
                upgrader = fitters.upgrade if body is None else fitters.upgrade.for_body(body)
                if self._smpl is None:
                    result = upgrade_from_rotations(sequence, upgrader, fitters.proxy, hints, progress, up=up)
                else:
                    result = upgrade_with_model(sequence, self._smpl, upgrader, progress=progress, up=up)
            _check_upgrade(result)
            if hints is not None and result.path == "a":
                note = "shape hints were not used: path (a) shapes the body from the sequence's betas"
                result = replace(result, notes=(*result.notes, note))
            return result

    def upgrade_files(self, result: UpgradeResult, name: str) -> dict[str, bytes]:
        """The upgrade's files as bytes: npz, json (summary), osim and mot (see ``write_upgrade``)."""
        with tempfile.TemporaryDirectory() as tmp, invalid_input("file"):
            # the answer carries four files, not a Geometry folder: the .osim names OpenSim's own meshes
            paths = write_upgrade(result, self.model, Path(tmp), name, geometry=False)
            return {ext: path.read_bytes() for ext, path in paths.items()}

    def frame_limit(self, bytes_per_frame: int) -> tuple[int, str]:
        """The most frames one request may hold and how to split it (:func:`.uploads.frame_limit`)."""
        return uploads.frame_limit(self.limits, bytes_per_frame)

    @contextmanager
    def _slot(self) -> Iterator[None]:
        if not self._slots.acquire(timeout=self.limits.queue_seconds):
            raise BusyError(
                f"all {self.limits.max_concurrent} worker slots stayed busy for "
                f"{self.limits.queue_seconds:g} s; retry later"
            )
        try:
            yield
        finally:
            self._slots.release()


def shape_hints(sex: str | None, height_m: float | None, mass_kg: float | None) -> ShapeHints | None:
    """Path (b)'s shape hints from request fields (:meth:`ShapeHints.given`).

    Raises:
        InvalidInputError: naming the hint that cannot describe an adult.
    """
    try:
        return ShapeHints.given(sex, height_m, mass_kg)
    except ShapeHintError as exc:
        raise InvalidInputError(str(exc), field=exc.field) from exc


def upgrade_up(text: str | None) -> str | None:
    """An upgrade's ``up`` field: one of +x, -x, +y, -y, +z, -z (a bare axis is +); None, "" or "auto":
    detect it from the motion.

    Raises:
        InvalidInputError: naming the field and the allowed values.
    """
    try:
        return up_axis_name(text)
    except ValueError as exc:
        raise InvalidInputError(str(exc), field="up") from None


def _for_body(fitters: _Fitters, body: FixedBody) -> _Fitters:
    """The registered and scan fitters of ``fitters`` for a subject's body (:meth:`ScanFitter.for_body`, whose
    registered fitter serves both); the sequence, upgrade and proxy as they are (a mesh fit uses neither)."""
    scan = fitters.scan.for_body(body)
    return replace(fitters, registered=scan.fitter, scan=scan)


def _personal_refinement(
    scanner: ScanFitter,
    scan: Scan | PreparedScan,
    start: ScanFit,
    body: FixedBody,
    progress: Callable[[int, int, str], None],
) -> ScanFit:
    """A raw scan of a known person: of two fits of the person's body (:meth:`ScanFitter.for_body`, shape
    and template held fixed) the one whose surface lies closer to the scan's points. One is ``scanner``'s
    own search (orientation and limbs searched with the person's body); the other refines the population's
    fit ``start`` (its point-to-plane phases and the non-rigid refinement, from ``start``'s pose). The
    population's pose is fitted with a free shape, so it carries that shape's errors into a limb's angle;
    the person's own search can settle with the legs swapped on a surface it matches within a millimetre,
    where the population's fit places the limbs first. Both hold the same body, so their distances to the
    scan compare. A head and shoulders is fitted by ``scanner`` alone (its own upper-body phases)."""
    own = scanner.fit(scan, progress=progress)
    if start.report.extra.get("fitted_part") == "head and shoulders":
        return own
    placed = _placed_refinement(scanner, scan, start, body, progress)
    return own if _scan_residual(own) < _scan_residual(placed) else placed


def _scan_residual(fit: ScanFit) -> float:
    """How far ``fit``'s surface lies from the scan: the mean distance (m) of its kept points to the
    registration, each capped at 2 cm so that a stray point does not decide between two fits of one body."""
    return float(np.minimum(fit.point_distances, 0.02).mean())


def _placed_refinement(
    scanner: ScanFitter,
    scan: Scan | PreparedScan,
    start: ScanFit,
    body: FixedBody,
    progress: Callable[[int, int, str], None],
) -> ScanFit:
    """The population's fit ``start`` refined by ``scanner`` with the person's shape held (see
    :func:`_personal_refinement`), answered in the scan's frame.

    In the frame ``start``'s parameters pose the body in (``x_body = R x_scan + t`` from its
    ``scan_to_body``) the refinement's parameters hold the placement themselves, so its map is ``start``'s.
    """
    turn = start.scan_to_body
    R, t = turn[:3, :3], turn[:3, 3]
    person = prepare_scan(scan, scanner.config).points
    fit = scanner.refine(person @ R.T + t, body.shape, start.coordinates, start.root, progress)

    def back(x: np.ndarray) -> np.ndarray:
        return (x - t) @ R

    scene = {k: v for k, v in start.report.extra.items() if k == "scene"}  # what the separation removed
    return replace(
        fit,
        vertices=back(fit.vertices),
        registration=back(fit.registration),
        joints=back(fit.joints),
        scan_to_body=fit.scan_to_body @ turn,
        report=replace(fit.report, extra={**fit.report.extra, **scene}),
    )


def _posed(
    body: FixedBody, shape: np.ndarray, q: np.ndarray, root: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A subject's bodies in float32: vertices (B, V, 3), joints (B, J, 3), frames (B, n_body, 4, 4) and
    scales (B, n_seg, 3) of their shapes (B, n_shape), coordinates (B, n_dof) and roots (B, 3)."""
    with torch.no_grad():
        args = (torch.as_tensor(np.asarray(a), dtype=torch.float32) for a in (shape, q, root))
        return body.decoder(torch.float32)(*args)


def _source(ready: Scan | PreparedScan) -> Scan:
    """The scan a :meth:`BodyService.check_scan` answer was made from."""
    scan = ready.source if isinstance(ready, PreparedScan) else ready
    assert isinstance(scan, Scan)  # the service prepares Scans only
    return scan


def _fit_routed(
    fitters: _Fitters,
    route: FittedAs,
    ready: Scan | PreparedScan,
    progress: Callable[[int, int, str], None],
    hints: ScanHints,
    body: FixedBody | None = None,
) -> MeshFit:
    """Fit ``scan`` the way ``route`` says (:meth:`BodyService.route`), with ``hints`` where the route can
    use them, in the input's frame (:class:`MeshFit`); ``progress`` (done, steps, line) gets the scan
    fitter's steps. ``body``: a subject's, held fixed (:func:`_for_body`); a mesh in our topology and a raw
    scan of a whole body are placed by the population's fit first (:func:`_personal_refinement`).
    ``ready``: the scan or its preparation (:meth:`BodyService.check_scan`), which a raw scan's fit reuses."""
    scan = _source(ready)
    orientation = hints.orientation()
    start = hints.start(fitters.scan.model)
    personal = fitters if body is None else _for_body(fitters, body)
    if route == REGISTERED:
        placed = fitters.registered.fit(scan.points)
        if body is not None:  # from the population's pose, as a raw scan (_personal_refinement)
            start_from = replace(placed, shape=personal.registered.start_shape(1))
            placed = personal.registered.fit(scan.points, init=start_from)
        fit = _first(placed, REGISTERED)
        return _with_hints(fit, fitters.scan.model, hints, False, False)
    if route == SMPL_TOPOLOGY:  # placed through the map, then refined on the mesh's surface
        assert scan.faces is not None  # the route needs them
        registered, faces = personal.registered, scan.faces
        f = fit_smpl_mesh(registered, personal.scan, scan.points, faces, orientation, progress=progress)
        start = None
        up = None
    else:
        up = hints.up_only()  # up without facing: the search keeps it
        f = fitters.scan.fit(ready, progress=progress, orientation=orientation, start=start, up=up)
        if body is not None:
            f = _personal_refinement(personal.scan, ready, f, body, progress)
    fit = MeshFit(route, f.shape, f.coordinates, f.root, f.registration, f.joints, f.report, f.scan_to_body)
    used = (orientation is not None, start is not None, up is not None)
    return _with_hints(fit, fitters.scan.model, hints, *used)


def _with_hints(
    fit: MeshFit, model: BodyModel, hints: ScanHints, oriented: bool, started: bool, up_used: bool = False
) -> MeshFit:
    """``fit`` with its report saying how each given hint was used (``extra["hints"]``: value, used, how),
    and not confident when the fitted body's height disagrees with the height hint."""
    if not hints.given_names():
        return fit
    use = hint_use(hints, fit.fitted_as, oriented, started, up_used)
    notes, used, reasons = dict(use.notes), set(use.used), list(fit.report.reasons)
    if hints.height_m is not None:
        partial = fit.report.extra.get("fitted_part") == "head and shoulders"
        notes["height_m"], reason = height_check(model, fit.shape, hints.height_m, partial)
        used |= set() if partial else {"height_m"}
        reasons += [] if reason is None else [reason]
    record = replace(use, notes=notes, used=frozenset(used)).record(hints)
    report = replace(
        fit.report,
        confident=fit.report.confident and len(reasons) == len(fit.report.reasons),
        reasons=tuple(reasons),
        extra={**fit.report.extra, "hints": record},
    )
    return replace(fit, report=report)


def _check_sequence_fit(fit: SequenceFit) -> None:
    """Raises InvalidInputError when any array of a sequence fit is not finite."""
    check_finite_result(
        "sequence fit",
        {
            "shape": fit.shape,
            "coordinates": fit.coordinates,
            "root": fit.root,
            "joints": fit.joints,
            "vertices": fit.vertices,
            "error_mm": np.array([r.distances.mean for r in fit.reports]),
        },
        "check that the frames are one person in our topology, in metres, in time order",
        "frames",
    )


def _check_sequence_frames(block: SequenceFrames) -> None:
    """Raises InvalidInputError when an array of a streamed block of sequence frames is not finite."""
    check_finite_result(
        f"sequence fit (frames {block.start}-{block.stop - 1})",
        {
            "coordinates": block.coordinates,
            "root": block.root,
            "joints": block.joints,
            "vertices": block.vertices,
            "error_mm": block.error_mm,
        },
        "check that the frames are one person in our topology, in metres, in time order",
        "frames",
    )


def _check_upgrade(result: UpgradeResult) -> None:
    """Raises InvalidInputError when an array of an upgrade is not finite; error_mm is left out, NaN by
    design where there is no input mesh (path b, bad frames)."""
    check_finite_result(
        "upgrade",
        {
            "coordinates": result.coordinates,
            "root": result.root,
            "joints": result.joints,
            "shape": result.shape,
            "scales": result.scales,
            "offsets": result.offsets,
        },
        "check the sequence's poses (axis-angle radians), trans (metres) and betas",
        "file",
    )


def _first(fit: BodyFit, kind: FittedAs) -> MeshFit:
    return MeshFit(
        kind, fit.shape[0], fit.coordinates[0], fit.root[0], fit.vertices[0], fit.joints[0], fit.reports[0]
    )
