"""Fit a registered-mesh sequence of one person: one shape, a pose per frame, continuous angles.

How (:class:`SequenceFitter`):

1. Heading. Each frame's pelvis is aligned rigidly (Kabsch, "A solution for the best rotation to relate two
   sets of vectors", Acta Crystallographica A, 1976, on the pelvis's own skin) and the frame is turned
   about the vertical and moved so that its pelvis faces +X at the origin. Fitting happens in these
   frames, where the pelvis coordinates stay near zero (far from the +-180 degree ends of
   ``pelvis_rotation``), and every result is turned back. The headings are unwrapped over time.
2. Shape. :class:`RegisteredFitter`'s full fit (staged as in Wang, Güler, Kokkinos, Papandreou, Zafeiriou,
   "BLSM: A Bone-Level Skinned Model of the Human Mesh", ECCV 2020, section 5.2), with one shape shared by
   ``keyframes`` frames spread over the sequence; the shape is then frozen for every frame.
3. Pose keyframes every ``stride`` frames: the fitter's rigid start (per-body Kabsch and inverse kinematics)
   and a pose-only fit with the frozen shape. Neighbouring keyframes whose coordinates jump while the fitted
   skin moves unlike the input are re-solved from each other's poses (:mod:`.basins`).
4. Every frame starts from the linear interpolation of its two neighbouring keyframes (a warm start within
   ``stride / 2`` frames of a fitted pose) and gets a short pose-only fit. The same check of one basin along
   time (:mod:`.basins`) then re-solves, from its neighbour's pose, a frame that left its neighbours' basin
   (a coordinate stuck at a limit): its coordinates jump while its input barely moves. Frames are independent
   problems given the shape and the keyframes, except for that check, which reads the last frame of the
   chunk before: there are no seams between chunks. :meth:`SequenceFitter.fit_frames` asks a
   :data:`FrameSource` for the frames chunk by chunk, so a sequence never has to be held whole: memory stays
   bounded by the chunk size whatever the length.
5. The joint coordinates (all but the pelvis's) are blended with their two neighbours in time
   (:attr:`SequenceConfig.blend`, a centred three-frame blend: it adds no lag). Back in the world frame the
   pelvis angles are recomputed from the pelvis orientation and unwrapped over time, so ``pelvis_rotation``
   is continuous even when the subject turns round (it may then leave [-pi, pi];
   :meth:`SequenceFit.coordinates_in_range` folds it back).

Each chunk's frames are final once the next chunk's poses are fitted (the blend reads one frame past
them): they are then skinned, measured and, when asked, streamed (``on_frames``, :class:`SequenceFrames`).
Temporal smoothness comes from the data term, the warm starts and the blend, whose weight is small (0.02 by
default). :class:`SequenceStats` measures the frame-to-frame jitter of the fit against the input's.

The settings are in :mod:`.config`, the frames of reference and per-frame arrays in :mod:`.frames`, the
sequence-level numbers in :mod:`.stats` and the results in :mod:`.result`.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel, PosedSkin
from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.registered.fitter import (
    CONFIDENT_MEAN_MM,
    FixedBody,
    RegisteredFitConfig,
    RegisteredFitter,
)
from bodyfit.models.fitting.retarget.fitter import wrap_pelvis
from bodyfit.models.fitting.sequence.basins import BasinCheck, settle
from bodyfit.models.fitting.sequence.config import FRAME_STAGES, KEY_STAGES, PELVIS_WEIGHT, SequenceConfig
from bodyfit.models.fitting.sequence.frames import FrameArrays, Headings, blend_joints, to_world, turn, yaw
from bodyfit.models.fitting.sequence.offsets import offsets_of_fit
from bodyfit.models.fitting.sequence.poses import FramePoses
from bodyfit.models.fitting.sequence.result import SequenceFit, SequenceFrames
from bodyfit.models.fitting.sequence.stats import JitterSum, SequenceStats, jitter
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS

__all__ = [
    "FRAME_STAGES",
    "KEY_STAGES",
    "PELVIS_WEIGHT",
    "FrameSource",
    "FramesCallback",
    "JitterSum",
    "SequenceConfig",
    "SequenceFit",
    "SequenceFitter",
    "SequenceFrames",
    "SequenceStats",
    "fit_sequence",
    "jitter",
]

FrameSource = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]
"""``source(frames)`` for frame indices (k,) in time order gives their meshes (k, V, 3) in our template's
vertex order, metres, and per-vertex weights (k, V) (None: ones)."""
FramesCallback = Callable[[SequenceFrames], None]
"""``on_frames(block)``: called with each block of final frames, in time order, while the fit runs."""
Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class _FramePass:
    """One fit's pass over every frame: where the frames come from and go, the pose fitter and the frozen
    shape c (1, n_shape) with its skin, and whom the pass tells."""

    source: FrameSource
    out: FrameArrays
    fitter: RegisteredFitter
    shape: np.ndarray
    skin: PosedSkin
    progress: Progress | None
    on_frames: FramesCallback | None

    @property
    def dtype(self) -> torch.dtype:
        return self.fitter.config.dtype

    @classmethod
    def of(
        cls,
        source: FrameSource,
        out: FrameArrays,
        fitter: RegisteredFitter,
        c: np.ndarray,
        progress: Progress | None,
        on_frames: FramesCallback | None,
    ) -> _FramePass:
        """The pass with the skin of shape c (1, n_shape) posed by ``fitter``'s decoder."""
        skin = fitter.decoder.posed(torch.as_tensor(c, dtype=fitter.config.dtype))
        return cls(source, out, fitter, c, skin, progress, on_frames)


class SequenceFitter:
    """Fits (T, V, 3) registered-mesh sequences of one person. Build once, reuse; holds no per-fit state.

    Args:
        fitter: the :class:`RegisteredFitter` (or the :class:`BodyModel`, for default settings) whose full
            fit gives the shape; its subset, preconditioning and dtype serve the pose fits too.
        config: :class:`SequenceConfig`.
    """

    def __init__(self, fitter: RegisteredFitter | BodyModel, config: SequenceConfig | None = None) -> None:
        self.config = config or SequenceConfig()
        self.fitter = fitter if isinstance(fitter, RegisteredFitter) else RegisteredFitter(fitter)
        base: RegisteredFitConfig = self.fitter.config
        # Pose fits run on their own (smaller) vertex subset; the shape fit keeps the given fitter's.
        self.pose_fitter = RegisteredFitter(self.model, replace(base, subset_size=self.config.pose_subset))
        skel = self.model.skeleton
        self.pelvis_dofs = [skel.dof_index(n) for n in PELVIS_ROTATIONS]
        self._joint_dofs = np.array([k for k, n in enumerate(skel.dof_names) if not n.startswith("pelvis_")])
        free = self.config.basin_free
        self._basin_dofs = np.array([k for k, n in enumerate(skel.dof_names) if not n.startswith(free)], int)
        self.headings = Headings(self.model)

    @property
    def model(self) -> BodyModel:
        return self.fitter.model

    def for_body(self, body: FixedBody) -> SequenceFitter:
        """This fitter for one known person (:meth:`RegisteredFitter.for_body`): no shape fit and no
        rest-pose offsets, every frame posed with their decoder and shape."""
        fitter = copy.copy(self)
        fitter.fitter = self.fitter.for_body(body)
        fitter.pose_fitter = self.pose_fitter.for_body(body)
        return fitter

    # -- fit -------------------------------------------------------------------------------------------
    def fit(
        self,
        frames: np.ndarray | torch.Tensor,
        weights: np.ndarray | None = None,
        progress: Progress | None = None,
        *,
        on_frames: FramesCallback | None = None,
    ) -> SequenceFit:
        """Fit a sequence held in memory.

        Args:
            frames: (T, V, 3) meshes in our template's vertex order, metres, T >= 1, in time order.
            weights: (T, V) per-vertex confidence (0 = missing), default ones.
            progress: called as ``progress(frames_done, T)`` after each chunk of the last pass.
            on_frames: called with each block of final frames as :meth:`fit_frames` says.
        Returns:
            :class:`SequenceFit` with the fitted vertices.
        Raises:
            ShapeError / NonFiniteError: bad input (wrong shape, no frames, NaN, bad weights).
        """
        x = np.asarray(frames)
        if x.ndim != 3 or len(x) == 0:
            raise ShapeError(
                f"a sequence must have shape (T, {self.model.n_vertices}, 3) with T >= 1 frames; "
                f"got {x.shape}"
            )
        w = None if weights is None else np.asarray(weights)
        if w is not None and w.shape != x.shape[:2]:
            raise ShapeError(f"vertex weights must have shape {x.shape[:2]}; got {w.shape}")

        def source(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
            rows: np.ndarray | slice = idx
            if len(idx) and (np.diff(idx) == 1).all():
                rows = slice(idx[0], idx[-1] + 1)  # a run of frames: a view, not a copy
            return x[rows], None if w is None else w[rows]

        return self.fit_frames(source, len(x), progress, keep_vertices=True, on_frames=on_frames)

    def fit_frames(
        self,
        source: FrameSource,
        n_frames: int,
        progress: Progress | None = None,
        keep_vertices: bool = False,
        *,
        on_frames: FramesCallback | None = None,
    ) -> SequenceFit:
        """Fit a sequence of ``n_frames`` frames that ``source`` gives a chunk at a time (see
        :data:`FrameSource`): the shape keyframes, then the pose keyframes, then every frame once, in
        chunks of ``config.chunk`` frames. Memory is bounded by the chunk, not the sequence, unless
        ``keep_vertices``.

        ``on_frames``, when given, is called with every frame once, in time order, in blocks of
        ``config.chunk`` frames (the last one shorter), each as soon as its frames are final: after the
        next chunk's poses are fitted (the blend reads one frame past the block), the last block at the end
        of the frame pass, all before this returns. The blocks' arrays are the final ones: concatenated, they
        equal the returned fit's coordinates, root, vertices and joints, and its reports' mean distances. An
        exception raised by ``on_frames`` stops the fit and propagates.

        Raises:
            ShapeError / NonFiniteError: bad frames from the source (wrong shape, NaN, bad weights).
        """
        start = time.perf_counter()
        T = int(n_frames)
        if T < 1:
            raise ShapeError(f"a sequence needs at least one frame; got {T}")
        # Shape on keyframes spread over the sequence, then frozen.
        shape_keys = self.shape_keyframes(T)
        c, offsets, pose_fitter = self._fit_shape(source, shape_keys)
        # Pose keyframes with the frozen shape, then every frame from their interpolation.
        q_init, r_init = self._key_poses(source, T, c, pose_fitter)
        out = FrameArrays(T, self.model, keep_vertices, self.pelvis_dofs)
        self._fit_every_frame(_FramePass.of(source, out, pose_fitter, c, progress, on_frames), q_init, r_init)
        seconds = time.perf_counter() - start
        return self._result(out, c, offsets, shape_keys, seconds)

    def _result(
        self,
        out: FrameArrays,
        c: np.ndarray,
        offsets: np.ndarray | None,
        shape_keys: np.ndarray,
        seconds: float,
    ) -> SequenceFit:
        """The fit of the frames in ``out`` with the shape c (1, n_shape), the offsets (V, 3) or None, the
        shape keyframes (K,), in ``seconds``."""
        T = len(out.q)
        iterations = sum(st.iterations for st in self.config.frame_stages)
        q = out.coordinates
        q_range = wrap_pelvis(q, self.model.skeleton)
        totals = out.totals
        reports = [
            self._report(st, q_range[t], iterations, seconds / T) for t, st in enumerate(totals.frames)
        ]
        stats = SequenceStats.measured(
            frames=T,
            seconds=seconds,
            mean_mm=totals.distance_sum / max(totals.distance_count, 1) * 1000.0,
            jitter_input_mm=totals.jitter_input.mm(),
            jitter_fit_mm=totals.jitter_fit.mm(),
            shape_keyframes=tuple(int(k) for k in shape_keys),
        )
        return SequenceFit(
            c[0],
            q,
            out.root,
            out.verts,
            out.joints,
            reports,
            stats,
            offsets,
            tuple(self.model.dof_names),
            q_range,
        )

    def shape_keyframes(self, n_frames: int) -> np.ndarray:
        """(K,) the frames the shape is fitted on: ``config.keyframes`` spread evenly over ``n_frames``
        (fewer when there are fewer frames)."""
        count = min(self.config.keyframes, n_frames)
        return np.unique(np.linspace(0, n_frames - 1, count).round().astype(np.int64))

    def facing_frames(self, source: FrameSource, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames idx (k,) from the source, checked and turned to face +X at the origin, as the fits see
        them: targets (k, V, 3) and weights (k, V)."""
        x, w, G, o = self._frames(source, idx)
        return turn(x, G, o), w

    def _fit_shape(
        self, source: FrameSource, shape_keys: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, RegisteredFitter]:
        """The shared shape c (1, n_shape) fitted to the frames ``shape_keys`` (K,), the rest-pose offsets
        (V, 3) fitted with it (None unless ``config.offsets``) and the pose fitter that carries them; a known
        person's shape (:meth:`for_body`) as it is."""
        if self.fitter.body is not None:
            return np.asarray(self.fitter.body.shape, np.float64)[None], None, self.pose_fitter
        x_c, w_s = self.facing_frames(source, shape_keys)
        shaped = self.fitter.fit(x_c, w_s, shared_shape=True)
        c = shaped.shape[:1]
        offsets, pose_fitter = None, self.pose_fitter
        if self.config.offsets is not None:
            offsets = offsets_of_fit(
                self.fitter.decoder, shaped, x_c, w_s, self.model.faces, self.config.offsets
            )
            pose_fitter = pose_fitter.with_offsets(offsets)
        return c, offsets, pose_fitter

    def _key_poses(
        self, source: FrameSource, T: int, c: np.ndarray, pose_fitter: RegisteredFitter
    ) -> tuple[np.ndarray, np.ndarray]:
        """Starting coordinates (T, n_dof) and roots (T, 3) of every frame: the poses of every
        ``config.stride``-th frame (and the last) fitted with the shape c (1, n_shape), interpolated."""
        cfg = self.config
        n_dof = self.model.skeleton.n_dof
        keys = np.unique(np.r_[np.arange(0, T, cfg.stride), T - 1])
        q_key, r_key = np.empty((len(keys), n_dof)), np.empty((len(keys), 3))
        for lo in range(0, len(keys), cfg.chunk):
            k = keys[lo : lo + cfg.chunk]
            x_k, w_k, G_k, o_k = self._frames(source, k)
            q0, r0 = self.fitter.bone_start(turn(x_k, G_k, o_k), w_k)
            q0 = self.model.skeleton.inside(q0, cfg.start_margin)
            problems = FramePoses(pose_fitter, (x_k, w_k, G_k, o_k), c, cfg.key_stages, cfg.workers)
            rows = slice(lo, lo + len(k))
            q_key[rows], r_key[rows] = problems.refit(np.arange(len(k)), q0, r0)
            before = None if lo == 0 else (q_key[lo - 1], r_key[lo - 1])
            settled = self._settle(problems, q_key[rows], r_key[rows], before, cfg.key_basins)
            q_key[rows], r_key[rows] = settled
        q_init = np.stack([np.interp(np.arange(T), keys, q_key[:, j]) for j in range(n_dof)], 1)
        r_init = np.stack([np.interp(np.arange(T), keys, r_key[:, j]) for j in range(3)], 1)
        return q_init, r_init

    def _fit_every_frame(self, run: _FramePass, q_init: np.ndarray, r_init: np.ndarray) -> None:
        """Nothing; fills ``run.out`` with the pose fit of every frame, in chunks, from q_init (T, n_dof) and
        r_init (T, 3), and streams each finished chunk to ``run.on_frames``."""
        T, chunk, stages = len(q_init), self.config.chunk, self.config.frame_stages
        out = run.out
        pending: tuple[int, int, np.ndarray, np.ndarray] | None = None
        for lo in range(0, T, chunk):
            hi = min(T, lo + chunk)
            x, w, out.G[lo:hi], out.origin[lo:hi] = self._frames(run.source, np.arange(lo, hi))
            G, origin = out.G[lo:hi], out.origin[lo:hi]
            problems = FramePoses(run.fitter, (x, w, G, origin), run.shape, stages, self.config.workers)
            q0 = self.model.skeleton.inside(q_init[lo:hi], self.config.start_margin)
            q, r = problems.refit(np.arange(hi - lo), q0, r_init[lo:hi])
            before = None if lo == 0 else (out.q_c[lo - 1], out.root_c[lo - 1])
            out.q_c[lo:hi], out.root_c[lo:hi] = self._settle(problems, q, r, before, self.config.basins)
            if pending is not None:  # one chunk behind: its last frame's blend needs this chunk's first
                self._finish(run, *pending)
            pending = (lo, hi, x, w)
        if pending is not None:
            self._finish(run, *pending)

    def _settle(
        self,
        problems: FramePoses,
        q: np.ndarray,
        root: np.ndarray,
        before: tuple[np.ndarray, np.ndarray] | None,
        check: BasinCheck | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Poses q (k, n_dof), root (k, 3) of ``problems``' frames (canonical frames) with neighbours that
        jump re-solved from each other (:func:`.basins.settle`; ``before``: the final pose of the frame before
        them, or None); unchanged when ``check`` is None."""
        if check is None:
            return q, root
        q, root, _ = settle(q, root, problems, check, self._basin_dofs, before)
        return q, root

    def _finish(self, run: _FramePass, lo: int, hi: int, x: np.ndarray, w: np.ndarray) -> None:
        """Nothing; blends, turns back to the world, unwraps, skins and measures frames lo:hi of ``run.out``
        (every neighbour's pose is known by now), then hands them to ``run.on_frames``. x: (k, V, 3) the
        input frames, w: (k, V) their weights."""
        out, dtype = run.out, run.dtype
        blended = blend_joints(out.q_c, lo, hi, self.config.blend, self._joint_dofs)
        out.q[lo:hi], out.root[lo:hi] = to_world(
            blended, out.root_c[lo:hi], out.G[lo:hi], out.origin[lo:hi], self.pelvis_dofs
        )
        out.coordinates[lo:hi] = out.unwrap(out.q[lo:hi])
        with torch.no_grad():
            v, j = run.skin.with_joints(
                torch.as_tensor(out.q[lo:hi], dtype=dtype), torch.as_tensor(out.root[lo:hi], dtype=dtype)
            )
        v_world = v.numpy().astype(np.float32, copy=False)  # float32 whatever the fitter's dtype
        out.joints[lo:hi] = j.double().numpy()
        if out.verts is not None:
            out.verts[lo:hi] = v_world
        out.totals.add(x, v_world, w)
        if run.on_frames is not None:
            errors = np.array([st.mean for st in out.totals.frames[lo:hi]])
            block = (out.coordinates[lo:hi].copy(), out.root[lo:hi].copy(), v_world, out.joints[lo:hi].copy())
            run.on_frames(SequenceFrames(lo, hi, *block, errors))
        if run.progress is not None:
            run.progress(hi, len(out.q))

    def _frames(
        self, source: FrameSource, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Frames idx (k,) from the source, checked, with their canonical frames (step 1): x (k, V, 3) float32
        and w (k, V) float64, G (k, 3, 3) world -> canonical rotations and the pelvis origins (k, 3)."""
        x, w = source(idx)
        x, w = self.fitter.validate(x, w, np.float32)
        if len(x) != len(idx):
            raise ShapeError(f"the frame source gave {len(x)} frames for {len(idx)} requested")
        heading, origin = self.headings(x, w)
        return x, w, yaw(-heading), origin

    def _report(self, stats: DistanceStats, q: np.ndarray, iterations: int, seconds: float) -> FitReport:
        """One frame's report from its distances (mm), coordinates q (n_dof,) in range and its share of
        the fit's time."""
        reasons = []
        if stats.mean > CONFIDENT_MEAN_MM:
            reasons.append(
                f"mean vertex error {stats.mean:.1f} mm exceeds {CONFIDENT_MEAN_MM:.0f} mm: the frame may "
                "not be this body"
            )
        return FitReport.judged(stats, q, self.model.skeleton.ranges, iterations, seconds, reasons)


def fit_sequence(
    fitter: RegisteredFitter | BodyModel,
    frames: np.ndarray | torch.Tensor,
    weights: np.ndarray | None = None,
    config: SequenceConfig | None = None,
    progress: Progress | None = None,
    *,
    on_frames: FramesCallback | None = None,
) -> SequenceFit:
    """Fit one person's registered-mesh sequence (T, V, 3). See :class:`SequenceFitter` (build that once
    to fit many sequences); ``on_frames`` streams the final frames as :meth:`SequenceFitter.fit_frames`
    says."""
    return SequenceFitter(fitter, config).fit(frames, weights, progress, on_frames=on_frames)
