"""The service's results (fits, sequence fits, upgrades, progress) as the documents of :mod:`bodyfit.wire`:
one place decides what a fit's result, a sequence's chunks and an upgrade's summary hold, for REST (JSON /
NDJSON) and gRPC alike."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from bodyfit import wire as w
from bodyfit.models.fitting.common.report import FitReport
from bodyfit.models.fitting.sequence.fitter import SequenceFit, SequenceFrames
from bodyfit.models.rig.build import RigBuild
from bodyfit.models.upgrade.upgrade import UpgradeResult
from bodyfit.service.core import MeshFit
from bodyfit.service.formats import json_ready
from bodyfit.service.jobs import Progress
from bodyfit.wire.subjects import SubjectResultEvent

encode_array = w.WireArray.from_numpy


def progress_event(p: Progress) -> w.ProgressEvent:
    return w.ProgressEvent(stage=p.stage, done=p.done, total=p.total, message=p.message)


def fit_report(report: FitReport) -> w.FitReport:
    return w.FitReport.model_validate(json_ready(report.to_dict()))  # numpy numbers in ``extra``


def mesh_fit_result(fit: MeshFit, dof_names: list[str], joint_names: list[str]) -> w.MeshFitEvent:
    """The final event of a scan / mesh fit; its arrays float32."""
    arrays = {k: encode_array(np.asarray(v, np.float32)) for k, v in fit.arrays().items()}
    return w.MeshFitEvent(
        fitted_as=fit.fitted_as,
        dof_names=tuple(dof_names),
        joint_names=tuple(joint_names),
        arrays=w.MeshFitArrays(**arrays),
        report=fit_report(fit.report),
    )


def sequence_chunk(
    start: int,
    coordinates: np.ndarray,
    root: np.ndarray,
    vertices: np.ndarray,
    joints: np.ndarray,
    error_mm: np.ndarray,
) -> w.SequenceChunkEvent:
    """The chunk event of k fitted frames from ``start``: coordinates (k, n_dof), root (k, 3), vertices
    (k, V, 3), joints (k, J, 3) (sent as float32) and error_mm (k,), each frame's mean distance."""
    arrays = w.SequenceChunkArrays(
        coordinates=encode_array(coordinates),
        root=encode_array(root),
        vertices=encode_array(vertices),
        joints=encode_array(np.asarray(joints, np.float32)),
        error_mm=encode_array(error_mm),
    )
    return w.SequenceChunkEvent(start=start, stop=start + len(coordinates), arrays=arrays)


class SequenceChunker:
    """Re-slices the blocks of final frames a sequence fit streams
    (:class:`~bodyfit.models.fitting.sequence.result.SequenceFrames`, the fitter's own block size) into chunk
    events of ``chunk`` frames, handing each to ``emit`` as soon as its frames are all in: call it with each
    block in time order, then :meth:`flush` once the fit has returned, for the last, shorter chunk."""

    PARTS = ("coordinates", "root", "vertices", "joints", "error_mm")

    def __init__(self, chunk: int, emit: Callable[[w.SequenceChunkEvent], None]) -> None:
        self.chunk = chunk
        self.emit = emit
        self._held: SequenceFrames | None = None  # the frames received and not yet emitted
        self.start = 0  # the first frame not yet emitted

    def __call__(self, block: SequenceFrames) -> None:
        stop = self.start if self._held is None else self._held.stop
        if block.start != stop:
            raise ValueError(f"frames {block.start}-{block.stop - 1} came out of order")
        if self._held is not None:  # one join per block; the chunks below are views of it
            joined = {n: np.concatenate([getattr(self._held, n), getattr(block, n)]) for n in self.PARTS}
            block = SequenceFrames(start=self.start, stop=block.stop, **joined)
        lo, n = 0, block.stop - block.start  # block.start == self.start here
        while n - lo >= self.chunk:
            self._send(block, lo, lo + self.chunk)
            lo += self.chunk
        rest = {name: getattr(block, name)[lo:] for name in self.PARTS}
        self._held = SequenceFrames(start=self.start, stop=block.stop, **rest) if lo < n else None

    def flush(self) -> None:
        """Emit the frames still held (fewer than ``chunk``)."""
        if self._held is not None:
            self._send(self._held, 0, self._held.stop - self._held.start)
            self._held = None

    def _send(self, frames: SequenceFrames, lo: int, hi: int) -> None:
        """Emit rows lo:hi of ``frames`` as the chunk event that starts at :attr:`start`."""
        self.emit(sequence_chunk(self.start, *(getattr(frames, n)[lo:hi] for n in self.PARTS)))
        self.start += hi - lo


def sequence_summary(fit: SequenceFit, joint_names: list[str]) -> w.SequenceResultEvent:
    """The final event of a sequence fit (the per-frame arrays came in the chunks)."""
    return w.SequenceResultEvent(
        dof_names=tuple(fit.dof_names),
        joint_names=tuple(joint_names),
        arrays=w.SequenceArrays(shape=encode_array(fit.shape)),
        stats=w.SequenceStats.model_validate(json_ready(fit.stats.to_dict())),
        limit_violations=sum(r.limit_violations for r in fit.reports),
        confident_frames=sum(r.confident for r in fit.reports),
    )


def upgrade_chunks(result: UpgradeResult, chunk: int) -> list[w.UpgradeChunkEvent]:
    """Per-chunk events of an upgrade: frames ``[start, stop)`` with coordinates, root, joints (float32),
    per-frame error (mm) and bad-frame flags."""
    events = []
    for lo in range(0, len(result.coordinates), chunk):
        hi = min(len(result.coordinates), lo + chunk)
        arrays = w.UpgradeChunkArrays(
            coordinates=encode_array(result.coordinates[lo:hi]),
            root=encode_array(result.root[lo:hi]),
            joints=encode_array(result.joints[lo:hi].astype(np.float32)),
            error_mm=encode_array(result.error_mm[lo:hi]),
            bad_frames=encode_array(result.bad_frames[lo:hi]),
        )
        events.append(w.UpgradeChunkEvent(start=lo, stop=hi, arrays=arrays))
    return events


def upgrade_summary(result: UpgradeResult, files: dict[str, bytes]) -> w.UpgradeResultEvent:
    """The final event of an upgrade: names, shape and bone scales, the summary, and the files."""
    return w.UpgradeResultEvent(
        dof_names=tuple(result.dof_names),
        joint_names=tuple(result.joint_names),
        segment_names=tuple(result.segment_names),
        arrays=w.UpgradeArrays(shape=encode_array(result.shape), scales=encode_array(result.scales)),
        summary=w.UpgradeSummary.model_validate(json_ready(result.summary())),
        files=files,
    )


def subject_result(built: RigBuild) -> SubjectResultEvent:
    """The final event of a rig build: each scan's error under the generic model and the rig (mm), the
    undetermined joints, the seconds and the subject file's bytes."""
    return SubjectResultEvent(
        scans=built.subject.scans,
        generic_mm=tuple(float(v) for v in built.generic_mm),
        personal_mm=tuple(float(v) for v in built.personal_mm),
        undetermined_joints=built.undetermined,
        seconds=built.seconds,
        subject=built.subject.to_bytes(),
    )
