"""Fit a registered-mesh sequence of one person: one shape, a pose per frame, continuous angles.

How (:class:`SequenceFitter`):

1. Heading. Each frame's pelvis is aligned rigidly (Kabsch on the pelvis's own skin) and the frame is turned
   about the vertical and moved so that its pelvis faces +X at the origin. Fitting happens in these
   frames, where the pelvis coordinates stay near zero (far from the +-180 degree ends of
   ``pelvis_rotation``), and every result is turned back. The headings are unwrapped over time.
2. Shape. :class:`RegisteredFitter`'s full fit, with one shape shared by ``keyframes`` frames spread over
   the sequence; the shape is then frozen for every frame.
3. Pose keyframes every ``stride`` frames: the fitter's rigid start (per-body Kabsch and inverse kinematics)
   and a pose-only fit with the frozen shape.
4. Every frame starts from the linear interpolation of its two neighbouring keyframes (a warm start within
   ``stride / 2`` frames of a fitted pose) and gets a short pose-only fit. Frames are independent problems
   given the shape and the keyframes, so splitting them into chunks (memory) changes nothing: there are no
   seams between chunks. :meth:`SequenceFitter.fit_frames` asks a :data:`FrameSource` for the frames chunk
   by chunk, so a sequence never has to be held whole: memory stays bounded by the chunk size whatever
   the length.
5. Back in the world frame the pelvis angles are recomputed from the pelvis orientation and unwrapped over
   time, so ``pelvis_rotation`` is continuous even when the subject turns round (it may then leave
   [-pi, pi]; :meth:`SequenceFit.coordinates_in_range` folds it back).

Temporal smoothness comes from the data term and the warm starts: nothing filters the result, so it cannot
lag real motion. :class:`SequenceStats` measures the frame-to-frame jitter of the fit against the input's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel, PosedSkin
from bodyfit.models.errors import ShapeError
from bodyfit.models.fitting.common.report import DistanceStats, FitReport
from bodyfit.models.fitting.registered.fitter import (
    CONFIDENT_MEAN_MM,
    BodyFit,
    RegisteredFitConfig,
    RegisteredFitter,
    Stage,
    vertex_term,
)
from bodyfit.models.fitting.retarget.fitter import unwrap_pelvis, wrap_pelvis
from bodyfit.models.fitting.sequence.offsets import OffsetConfig, fit_rest_offsets
from bodyfit.models.rotations import kabsch, zxy_angles
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS

FrameSource = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]]
"""``source(frames)`` for frame indices (k,) in time order gives their meshes (k, V, 3) in our template's
vertex order, metres, and per-vertex weights (k, V) (None: ones)."""

KEY_STAGES = (Stage("key_pose", "all", "none", "subset", 40),)
FRAME_STAGES = (Stage("pose", "all", "none", "subset", 24),)
PELVIS_WEIGHT = 0.5  # skinning weight above which a vertex belongs to the pelvis, for the heading


@dataclass(frozen=True)
class SequenceConfig:
    """keyframes: frames (spread evenly) the shape is fitted on; stride: frames between pose keyframes;
    chunk: frames fitted together (memory only: frames are independent given the keyframes);
    pose_subset: vertices of the farthest-point subset the pose stages ("subset") fit;
    key_stages / frame_stages: pose-only stages (shape "none") for pose keyframes and for every frame;
    blend: weight b of the centred three-frame blend of the joint coordinates (all but the pelvis's) after
    the per-frame fits, ``q[t] <- (1 - 2 b) q[t] + b (q[t-1] + q[t+1])``: symmetric in time, so it adds
    no lag; a convex combination, so it stays within the limits; 0 turns it off;
    offsets: fit the person's rest-pose offsets (:mod:`.offsets`: surface detail
    beyond the shape space) on the shape keyframes and fit every pose with them; None: shape space only;
    workers: threads a chunk's pose fits are split over (frames are independent problems)."""

    keyframes: int = 8
    stride: int = 8
    chunk: int = 256
    pose_subset: int = 400
    key_stages: tuple[Stage, ...] = KEY_STAGES
    frame_stages: tuple[Stage, ...] = FRAME_STAGES
    blend: float = 0.02
    offsets: OffsetConfig | None = None
    workers: int = 2


@dataclass(frozen=True)
class SequenceStats:
    """Sequence-level numbers.

    frames; seconds (wall, whole fit); fps = frames / seconds; mean_mm: mean per-vertex distance over all
    frames; jitter_input_mm / jitter_fit_mm: mean over frames and vertices of the second difference in
    time ``|x[t+1] - 2 x[t] + x[t-1]|`` (mm); jitter_ratio: fit over input (1 = as smooth as the input);
    shape_keyframes: the frames the shape was fitted on. Where jitter is undefined it is None, never NaN,
    and ``jitter_note`` says why: the second difference needs three frames (no vertex seen, weight > 0, in
    three consecutive frames: both None), and the ratio needs an input that moves (a still input has
    jitter 0: the ratio is None, the fit's own jitter is kept).
    """

    frames: int
    seconds: float
    fps: float
    mean_mm: float
    jitter_input_mm: float | None
    jitter_fit_mm: float | None
    jitter_ratio: float | None
    shape_keyframes: tuple[int, ...]
    jitter_note: str | None = None

    @classmethod
    def measured(
        cls,
        frames: int,
        seconds: float,
        mean_mm: float,
        jitter_input_mm: float,
        jitter_fit_mm: float,
        shape_keyframes: tuple[int, ...],
    ) -> SequenceStats:
        """The stats of a fit from its raw jitter means (NaN where :class:`JitterSum` saw no second
        difference), with the undefined ones as None and the note saying why."""
        note = None
        j_in: float | None = jitter_input_mm
        j_fit: float | None = jitter_fit_mm
        ratio: float | None = None
        if not (np.isfinite(jitter_input_mm) and np.isfinite(jitter_fit_mm)):
            j_in = j_fit = None
            note = (
                f"jitter needs three consecutive frames (a second difference in time); the sequence has "
                f"{frames}"
                if frames < 3
                else "jitter needs a vertex seen (weight > 0) in three consecutive frames; none is"
            )
        elif jitter_input_mm > 0:
            ratio = jitter_fit_mm / jitter_input_mm
        else:
            note = "the input does not move (jitter 0): jitter_ratio is undefined; jitter_fit_mm is the fit's"
        return cls(frames, seconds, frames / seconds, mean_mm, j_in, j_fit, ratio, shape_keyframes, note)

    def to_dict(self) -> dict[str, object]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class SequenceFit:
    """One person over T frames.

    shape: (n_shape,) for every frame; offsets: (V, 3) the person's rest-pose offsets (metres) when the
    fit was asked for them, else None (the skin is then the shape space's); coordinates: (T, n_dof), the
    pelvis angles unwrapped over time (see :meth:`coordinates_in_range`); root: (T, 3); vertices:
    (T, V, 3) float32, the registration, or None when the fit was asked not to keep them; joints:
    (T, J, 3); reports: one :class:`FitReport` per frame; stats: :class:`SequenceStats`.
    """

    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    vertices: np.ndarray | None
    joints: np.ndarray
    reports: list[FitReport]
    stats: SequenceStats
    offsets: np.ndarray | None = None
    dof_names: tuple[str, ...] = field(default=(), repr=False)
    _in_range: np.ndarray | None = field(default=None, repr=False)

    def registration(self, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """Fitted vertices of frames lo:hi (k, V, 3) float32.

        Raises:
            ValueError: the fit was run without keeping its vertices.
        """
        if self.vertices is None:
            raise ValueError("this fit did not keep its vertices; fit with keep_vertices=True")
        return self.vertices[lo:hi]

    def coordinates_in_range(self) -> np.ndarray:
        """(T, n_dof) with the pelvis angles folded into [-pi, pi]: valid input to :meth:`BodyModel.forward`
        (the same poses)."""
        assert self._in_range is not None
        return self._in_range


class JitterSum:
    """Running mean second difference in time of trajectories fed chunk by chunk, in time order (the
    :func:`jitter` of the whole sequence, without holding it)."""

    def __init__(self) -> None:
        self._tail: tuple[np.ndarray, np.ndarray] | None = None  # the last two frames and their masks
        self._total = 0.0
        self._count = 0

    def add(self, x: np.ndarray, weights: np.ndarray | None = None) -> None:
        """The next frames x (k, N, 3) metres, with weights (k, N) (None: all count)."""
        seen = np.ones(x.shape[:2], bool) if weights is None else np.asarray(weights) > 0
        if self._tail is not None:  # the differences across the join with the previous chunk
            prev_x, prev_seen = self._tail
            self._sum(np.concatenate([prev_x, x[:2]]), np.concatenate([prev_seen, seen[:2]]))
            x_end, seen_end = np.concatenate([prev_x, x[-2:]]), np.concatenate([prev_seen, seen[-2:]])
        else:
            x_end, seen_end = x, seen
        self._sum(x, seen)
        self._tail = (x_end[-2:].copy(), seen_end[-2:].copy())

    def _sum(self, x: np.ndarray, seen: np.ndarray) -> None:
        if len(x) < 3:
            return
        d = x[2:] - x[1:-1]
        d -= x[1:-1]
        d += x[:-2]
        acc = _lengths(d)
        ok = seen[2:] & seen[1:-1] & seen[:-2]
        acc = acc if ok.all() else acc[ok]
        self._total += float(acc.sum(dtype=np.float64))
        self._count += acc.size

    def mm(self) -> float:
        """The mean so far in mm; NaN before three frames."""
        return self._total / self._count * 1000.0 if self._count else float("nan")


class _Totals:
    """What the frame pass accumulates chunk by chunk: distance sums, per-frame statistics, jitter."""

    def __init__(self) -> None:
        self.distance_sum = 0.0
        self.distance_count = 0
        self.frames: list[DistanceStats] = []
        self.jitter_input = JitterSum()
        self.jitter_fit = JitterSum()

    def add(self, x: np.ndarray, fitted: np.ndarray, w: np.ndarray) -> None:
        """Input frames x (k, V, 3), fitted skins (k, V, 3), weights (k, V); float32 metres. The jitter is
        summed on a second thread meanwhile (numpy's array operations release the interpreter)."""
        with ThreadPoolExecutor(1) as pool:
            smooth = pool.submit(self._add_jitter, x, fitted, w)
            dist = _lengths(fitted - x)
            seen = w > 0
            used = dist if seen.all() else dist[seen]
            self.distance_sum += float(used.sum(dtype=np.float64))
            self.distance_count += used.size
            self.frames.extend(DistanceStats.of_rows(dist, seen))
            smooth.result()

    def _add_jitter(self, x: np.ndarray, fitted: np.ndarray, w: np.ndarray) -> None:
        self.jitter_input.add(x, w)
        self.jitter_fit.add(fitted, w)


class _FrameArrays:
    """What the frame pass fills in chunk by chunk, for T frames: canonical-frame poses q_c (T, n_dof) and
    root_c (T, 3); blended world poses q (T, n_dof) and root (T, 3); canonical frames G (T, 3, 3) and
    origin (T, 3); skins verts (T, V, 3) float32 (None unless kept); joints (T, n_joints, 3); totals."""

    def __init__(self, T: int, model: BodyModel, keep_vertices: bool) -> None:
        n_dof = model.skeleton.n_dof
        self.q_c, self.root_c = np.empty((T, n_dof)), np.empty((T, 3))
        self.q, self.root = np.empty((T, n_dof)), np.empty((T, 3))  # blended, in the world
        self.G, self.origin = np.empty((T, 3, 3)), np.empty((T, 3))
        self.verts = np.empty((T, model.n_vertices, 3), np.float32) if keep_vertices else None
        self.joints = np.empty((T, len(model.joint_names), 3))
        self.totals = _Totals()


def jitter(x: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Mean second difference in time of trajectories x (T, N, 3) metres, in mm; over points with positive
    weight (T, N) in all three frames; NaN for fewer than 3 frames."""
    total = JitterSum()
    total.add(x, weights)
    return total.mm()


def _yaw(angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations about +Y by angle (T,)."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    return R


def _lengths(d: np.ndarray) -> np.ndarray:
    """Lengths of vectors d (..., 3), in d's dtype (per component: twice as fast as einsum here)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.sqrt(x * x + y * y + z * z)


def _turn(x: np.ndarray, G: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Points x (T, N, 3) into their frames' canonical frames: G (T, 3, 3) applied about origin (T, 3)."""
    return (x - origin[:, None]) @ np.swapaxes(G, -1, -2)  # batched BLAS


def _zxy_matrix(a: np.ndarray) -> np.ndarray:
    """(T, 3, 3) ``Rz(a0) Rx(a1) Ry(a2)``."""
    cz, sz = np.cos(a[:, 0]), np.sin(a[:, 0])
    cx, sx = np.cos(a[:, 1]), np.sin(a[:, 1])
    one, zero = np.ones_like(cz), np.zeros_like(cz)
    Rz = np.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    Rx = np.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).reshape(-1, 3, 3)
    return Rz @ Rx @ _yaw(a[:, 2])


class SequenceFitter:
    """Fits (T, V, 3) registered-mesh sequences of one person. Build once, reuse; holds no per-fit state.

    Args:
        fitter: the :class:`RegisteredFitter` (or the :class:`BodyModel`, for default settings) whose full
            fit gives the shape; its subset, preconditioning and dtype serve the pose fits too.
        config: :class:`SequenceConfig`.
    """

    def __init__(self, fitter: RegisteredFitter | BodyModel, config: SequenceConfig | None = None) -> None:
        self.config = config or SequenceConfig()
        for stage in (*self.config.key_stages, *self.config.frame_stages):
            if stage.shape != "none":
                raise ValueError(f"sequence pose stages keep the shape frozen; stage {stage.name!r} fits it")
        if self.config.stride < 1 or self.config.keyframes < 1 or self.config.chunk < 1:
            raise ValueError("keyframes, stride and chunk must be at least 1")
        if not 0.0 <= self.config.blend < 0.5:
            raise ValueError(f"blend must be in [0, 0.5); got {self.config.blend}")
        self.fitter = fitter if isinstance(fitter, RegisteredFitter) else RegisteredFitter(fitter)
        base: RegisteredFitConfig = self.fitter.config
        # Pose fits run on their own (smaller) vertex subset; the shape fit keeps the given fitter's.
        self.pose_fitter = RegisteredFitter(self.model, replace(base, subset_size=self.config.pose_subset))
        skel = self.model.skeleton
        self.pelvis_dofs = [skel.dof_index(n) for n in PELVIS_ROTATIONS]
        self._joint_dofs = np.array([k for k, n in enumerate(skel.dof_names) if not n.startswith("pelvis_")])
        self.pelvis_vertices = np.flatnonzero(self.model.data["weights"][:, 0] > PELVIS_WEIGHT)
        fk = skel.kinematics(torch.float64)
        scales = torch.as_tensor(self.model.data["scale_mean"], dtype=torch.float64)[None]
        bind = (
            fk(torch.as_tensor(self.model.bind_coordinates, dtype=torch.float64)[None], None, scales)
            .frames[0, 0]
            .numpy()
        )
        self._pelvis_bind = bind  # (4, 4) the mean body's pelvis frame in the template's pose

    @property
    def model(self) -> BodyModel:
        return self.fitter.model

    # -- frames ----------------------------------------------------------------------------------------
    def headings(self, x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame heading (T,) radians about +Y, unwrapped over time, and pelvis origin (T, 3), from a
        rigid fit of the pelvis's skin."""
        idx = self.pelvis_vertices
        template = self.model.data["vertices_mean"][idx]
        R, t = kabsch(template, x[:, idx], w[:, idx] + 1e-12)
        bind = self._pelvis_bind
        forward = R @ bind[:3, 0]  # the pelvis's +X in the world
        origin = np.einsum("tij,j->ti", R, bind[:3, 3]) + t
        return np.unwrap(np.arctan2(-forward[:, 2], forward[:, 0])), origin

    # -- fit -------------------------------------------------------------------------------------------
    def fit(
        self,
        frames: np.ndarray | torch.Tensor,
        weights: np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> SequenceFit:
        """Fit a sequence held in memory.

        Args:
            frames: (T, V, 3) meshes in our template's vertex order, metres, T >= 1, in time order.
            weights: (T, V) per-vertex confidence (0 = missing), default ones.
            progress: called as ``progress(frames_done, T)`` after each chunk of the last pass.
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

        return self.fit_frames(source, len(x), progress, keep_vertices=True)

    def fit_frames(
        self,
        source: FrameSource,
        n_frames: int,
        progress: Callable[[int, int], None] | None = None,
        keep_vertices: bool = False,
    ) -> SequenceFit:
        """Fit a sequence of ``n_frames`` frames that ``source`` gives a chunk at a time (see
        :data:`FrameSource`): the shape keyframes, then the pose keyframes, then every frame once, in
        chunks of ``config.chunk`` frames. Memory is bounded by the chunk, not the sequence, unless
        ``keep_vertices``.

        Raises:
            ShapeError / NonFiniteError: bad frames from the source (wrong shape, NaN, bad weights).
        """
        start = time.perf_counter()
        T = int(n_frames)
        if T < 1:
            raise ShapeError(f"a sequence needs at least one frame; got {T}")
        # Shape on keyframes spread over the sequence, then frozen.
        shape_keys = np.unique(np.linspace(0, T - 1, min(self.config.keyframes, T)).round().astype(np.int64))
        c, offsets, pose_fitter = self._fit_shape(source, shape_keys)
        # Pose keyframes with the frozen shape, then every frame from their interpolation.
        q_init, r_init = self._key_poses(source, T, c, pose_fitter)
        out = _FrameArrays(T, self.model, keep_vertices)
        self._fit_every_frame(source, out, pose_fitter, c, q_init, r_init, progress)
        iterations = sum(st.iterations for st in self.config.frame_stages)

        q = unwrap_pelvis(out.q, self.model.skeleton)
        seconds = time.perf_counter() - start

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

    def _fit_shape(
        self, source: FrameSource, shape_keys: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, RegisteredFitter]:
        """The shared shape c (1, n_shape) fitted to the frames ``shape_keys`` (K,), the rest-pose offsets
        (V, 3) fitted with it (None unless ``config.offsets``) and the pose fitter that carries them."""
        x_s, w_s, G_s, o_s = self._frames(source, shape_keys)
        x_c = _turn(x_s, G_s, o_s)
        shaped = self.fitter.fit(x_c, w_s, shared_shape=True)
        c = shaped.shape[:1]
        offsets, pose_fitter = None, self.pose_fitter
        if self.config.offsets is not None:
            offsets = self._offsets(shaped, x_c, w_s, self.config.offsets)
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
            q0, r0 = self.fitter.bone_start(_turn(x_k, G_k, o_k), w_k)
            q_key[lo : lo + len(k)], r_key[lo : lo + len(k)] = self._pose(
                pose_fitter, x_k, w_k, G_k, o_k, c, q0, r0, cfg.key_stages
            )
        q_init = np.stack([np.interp(np.arange(T), keys, q_key[:, j]) for j in range(n_dof)], 1)
        r_init = np.stack([np.interp(np.arange(T), keys, r_key[:, j]) for j in range(3)], 1)
        return q_init, r_init

    def _fit_every_frame(
        self,
        source: FrameSource,
        out: _FrameArrays,
        pose_fitter: RegisteredFitter,
        c: np.ndarray,
        q_init: np.ndarray,
        r_init: np.ndarray,
        progress: Callable[[int, int], None] | None,
    ) -> None:
        """Nothing; fills ``out`` with the pose fit of every frame, in chunks, from q_init (T, n_dof) and
        r_init (T, 3) with the shape c (1, n_shape)."""
        T, chunk, stages = len(q_init), self.config.chunk, self.config.frame_stages
        dtype = pose_fitter.config.dtype
        skin = pose_fitter.decoder.posed(torch.as_tensor(c, dtype=dtype))
        pending: tuple[int, int, np.ndarray, np.ndarray] | None = None
        for lo in range(0, T, chunk):
            hi = min(T, lo + chunk)
            x, w, out.G[lo:hi], out.origin[lo:hi] = self._frames(source, np.arange(lo, hi))
            out.q_c[lo:hi], out.root_c[lo:hi] = self._pose(
                pose_fitter, x, w, out.G[lo:hi], out.origin[lo:hi], c, q_init[lo:hi], r_init[lo:hi], stages
            )
            if pending is not None:  # one chunk behind: its last frame's blend needs this chunk's first
                self._finish(out, skin, dtype, *pending, progress)
            pending = (lo, hi, x, w)
        if pending is not None:
            self._finish(out, skin, dtype, *pending, progress)

    def _finish(
        self,
        out: _FrameArrays,
        skin: PosedSkin,
        dtype: torch.dtype,
        lo: int,
        hi: int,
        x: np.ndarray,
        w: np.ndarray,
        progress: Callable[[int, int], None] | None,
    ) -> None:
        """Nothing; blends, turns back to the world, skins and measures frames lo:hi of ``out`` (every
        neighbour's pose is known by now). x: (k, V, 3) the input frames, w: (k, V) their weights."""
        out.q[lo:hi], out.root[lo:hi] = self._world(
            self._blend(out.q_c, lo, hi), out.root_c[lo:hi], out.G[lo:hi], out.origin[lo:hi]
        )
        with torch.no_grad():
            v, j = skin.with_joints(
                torch.as_tensor(out.q[lo:hi], dtype=dtype), torch.as_tensor(out.root[lo:hi], dtype=dtype)
            )
        v_world = v.numpy().astype(np.float32, copy=False)  # float32 whatever the fitter's dtype
        out.joints[lo:hi] = j.double().numpy()
        if out.verts is not None:
            out.verts[lo:hi] = v_world
        out.totals.add(x, v_world, w)
        if progress is not None:
            progress(hi, len(out.q))

    def _offsets(self, shaped: BodyFit, x: np.ndarray, w: np.ndarray, config: OffsetConfig) -> np.ndarray:
        """Rest-pose offsets (V, 3) from the shape fit ``shaped`` of keyframes x (K, V, 3) (canonical frames)
        with weights w (K, V)."""
        decoder = self.fitter.decoder
        dtype = self.fitter.config.dtype
        with torch.no_grad():
            _, _, frames, _ = decoder(
                *(torch.as_tensor(a, dtype=dtype) for a in (shaped.shape, shaped.coordinates, shaped.root))
            )
        rotations = decoder.blended_rotations(frames)
        return fit_rest_offsets(rotations, x - shaped.vertices, w, self.model.faces, config)

    def _world(
        self, q: np.ndarray, root: np.ndarray, G: np.ndarray, origin: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates q (k, n_dof) and roots (k, 3) of canonical frames (G (k, 3, 3), origin (k, 3)) in the
        world: the root and the pelvis's orientation turned back (the pelvis angles in range, not yet
        unwrapped). Skinned, they give the canonical skin turned back."""
        Gt = np.swapaxes(G, -1, -2)
        out = q.copy()
        out[:, self.pelvis_dofs] = zxy_angles(Gt @ _zxy_matrix(q[:, self.pelvis_dofs]))
        return out, np.einsum("tij,tj->ti", Gt, root) + origin

    def _blend(self, q: np.ndarray, lo: int, hi: int) -> np.ndarray:
        """Rows lo:hi of q (T, n_dof) after the centred blend of the joint coordinates (see
        :class:`SequenceConfig`); the first and last frames and the pelvis are kept."""
        out = q[lo:hi].copy()
        b = self.config.blend
        inner = np.arange(max(lo, 1), min(hi, len(q) - 1))
        if b == 0.0 or len(inner) == 0:
            return out
        joints = self._joint_dofs
        rows = inner - lo
        out[np.ix_(rows, joints)] = (1.0 - 2.0 * b) * q[np.ix_(inner, joints)] + b * (
            q[np.ix_(inner - 1, joints)] + q[np.ix_(inner + 1, joints)]
        )
        return out

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
        return x, w, _yaw(-heading), origin

    def _pose(
        self,
        fitter: RegisteredFitter,
        x: np.ndarray,
        w: np.ndarray,
        G: np.ndarray,
        origin: np.ndarray,
        c: np.ndarray,
        q0: np.ndarray,
        r0: np.ndarray,
        stages: tuple[Stage, ...],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pose-only fit, in the canonical frames (G, origin), of world frames x (B, V, 3) with weights
        w (B, V), the shape c (1, n_shape) frozen, from q0 (B, n_dof) and r0 (B, 3): one problem per frame,
        the frames split into ``config.workers`` runs fitted at once, a thread each. Only the stages'
        vertices are turned. Returns coordinates (B, n_dof) and root (B, 3)."""
        dtype = fitter.config.dtype

        def fit(rows: slice) -> tuple[np.ndarray, np.ndarray]:
            w_r, G_r, o_r = w[rows], G[rows], origin[rows]
            w_mean = w_r.mean(axis=1, keepdims=True)
            z = fitter.start_state(q0[rows], r0[rows], np.repeat(c, len(w_r), axis=0))
            for stage in stages:
                idx = fitter.index[stage.vertices]
                xt = torch.as_tensor(_turn(x[rows, idx], G_r, o_r) * 1000.0, dtype=dtype)
                wt = torch.as_tensor(w_r[:, idx] / w_mean, dtype=dtype)
                fitter.optimise(stage, z, vertex_term(xt, wt))
            _, q, root = fitter.parameters(z)
            return q.numpy(), root.numpy()

        runs = [
            slice(int(r[0]), int(r[-1]) + 1)
            for r in np.array_split(np.arange(len(x)), self.config.workers)
            if len(r)
        ]
        with ThreadPoolExecutor(len(runs)) as pool:
            done = list(pool.map(fit, runs))
        return np.concatenate([q for q, _ in done]), np.concatenate([root for _, root in done])

    def _report(self, stats: DistanceStats, q: np.ndarray, iterations: int, seconds: float) -> FitReport:
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
    progress: Callable[[int, int], None] | None = None,
) -> SequenceFit:
    """Fit one person's registered-mesh sequence (T, V, 3). See :class:`SequenceFitter` (build that once
    to fit many sequences)."""
    return SequenceFitter(fitter, config).fit(frames, weights, progress)
