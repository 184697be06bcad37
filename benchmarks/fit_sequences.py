"""Sequence fitting: real motion (CMU subject 131) on held-out anny bodies, ours against independent
per-frame fits, one run.

What is measured
----------------
* Motion: CMU mocap subject 131 (BVH, 120 fps; ``tests/data/cmu_bvh`` holds the clip the tests use, the
  full trials are in ``../shared/data/cmu_bvh``), retargeted onto our skeleton scaled to each body
  (:func:`bodyfit.models.fitting.retarget.fitter.retarget`), root translation from the BVH.
* Bodies: adults from anny's shape distribution with a seed the asset build never used
  (``HELD_OUT_SEED``), the skeleton placed inside from their landmarks, posed frame by frame to the
  retargeted coordinates and skinned by anny's own rig (:func:`bodyfit.models.body.anny_posed.pose_anny`):
  ground truth our model never saw.
* Ours: :func:`bodyfit.models.fitting.sequence.fitter.fit_sequence` (one shape, pose per frame, warm starts),
  float32, each chunk's frames on the fitter's two threads and torch on one thread per op (the figure at
  torch's default threads is reported too). Time: wall time of the whole fit including the shape
  keyframes, after one untimed fit of the same clip (a long-lived process's warm allocations).
* Peer: :meth:`RegisteredFitter.fit` with default stages on every frame independently (a shape per frame),
  on the same frames in the same run.
* Error: mean per-vertex distance (mm) over all frames. Jitter: mean over frames and vertices of
  ``|x[t+1] - 2 x[t] + x[t-1]|`` (mm); ``seq_jitter_ratio`` = fit jitter / input jitter.
* Targets (issue 4): >= 100 frames/s on the 2-core CPU, <= 3 mm mean, jitter ratio <= 1.

Usage::

    python benchmarks/fit_sequences.py [--quick] [--json]
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.io.bvh import CMU_UNITS, BvhMotion, read_bvh
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.registered.fitter import RegisteredFitter
from bodyfit.models.fitting.retarget.fitter import retarget
from bodyfit.models.fitting.sequence.fitter import SequenceFitter, jitter

HELD_OUT_SEED = 4242  # the build uses 20261122 (+1, +2)
ROOT = Path(__file__).resolve().parents[1]
TEST_CLIP = ROOT / "tests" / "data" / "cmu_bvh" / "cmu_131_01_clip.bvh"
FULL_TRIALS = ROOT.parent / "shared" / "data" / "cmu_bvh"
TARGET_FPS = 100.0
TARGET_MM = 3.0


@dataclass(frozen=True)
class HeldOutMotion:
    """vertices: (T, V, 3) ground truth in our topology; q: (T, n_dof) the coordinates (pelvis unwrapped);
    root: (T, 3); scales: (n_seg, 3) the skeleton inside the body; rate: frames per second."""

    vertices: np.ndarray
    q: np.ndarray
    root: np.ndarray
    scales: np.ndarray
    rate: float


def turning(motion: BvhMotion, turns: float) -> BvhMotion:
    """The motion with its root turned about the vertical by ``turns`` full turns, linearly over time (a
    subject walking round): root position and orientation both turn, in the file's axes (Y up)."""
    T = motion.n_frames
    angle = np.linspace(0.0, 2 * np.pi * turns, T)
    values = motion.values.copy()
    root = motion.joints[0]
    cols = {name: k for k, name in enumerate(root.channels)}
    if not {"Xposition", "Zposition"} <= set(cols):
        raise ValueError("the root needs X and Z position channels")
    c, s = np.cos(angle), np.sin(angle)
    x, z = values[:, cols["Xposition"]].copy(), values[:, cols["Zposition"]].copy()
    x0, z0 = x[0], z[0]
    values[:, cols["Xposition"]] = x0 + c * (x - x0) + s * (z - z0)
    values[:, cols["Zposition"]] = z0 - s * (x - x0) + c * (z - z0)
    # Root orientation: R' = Ry(angle) R, re-expressed in the root's channel order.
    from scipy.spatial.transform import Rotation

    order = "".join(n[0] for n in root.channels if n.endswith("rotation"))
    rcols = [cols[n] for n in root.channels if n.endswith("rotation")]
    R = Rotation.from_euler(order, values[:, rcols], degrees=True)
    turned = Rotation.from_euler("Y", angle[:, None]) * R
    values[:, rcols] = np.unwrap(turned.as_euler(order, degrees=True), period=360.0, axis=0)
    return BvhMotion(motion.joints, values, motion.frame_time, motion.units, motion.rotation, motion.source)


def held_out_motion(
    model: BodyModel, motion: BvhMotion, body: int = 0, seed: int = HELD_OUT_SEED, n_bodies: int = 1
) -> HeldOutMotion:
    """Retarget ``motion`` onto held-out anny body ``body`` (of ``n_bodies`` sampled with ``seed``) and pose
    it frame by frame with anny's own skinning. Needs anny (the [build] extra) and its cache."""
    from bodyfit.models.body.anny_posed import pose_anny, template_landmarks
    from bodyfit.models.body.anny_source import AnnySource
    from bodyfit.models.body.skeleton_fit import place_skeletons
    from bodyfit.models.build_assets import default_cache_dir

    skel = model.skeleton
    src = AnnySource(default_cache_dir())
    pop = src.sample(n_bodies, seed)
    landmarks, _ = template_landmarks(src)
    rest = src.rest(pop)["vertices"]
    placed = place_skeletons(skel, rest[:, landmarks], 150)
    fk = skel.kinematics(torch.float64)
    frames_a = fk(
        torch.as_tensor(placed.q), torch.as_tensor(placed.root), torch.as_tensor(placed.scales)
    ).frames
    moved = retarget(motion, skel, placed.scales[body])
    q = moved.in_range(skel)
    T = len(q)
    verts = np.empty((T, model.n_vertices, 3))
    for lo in range(0, T, 64):
        hi = min(T, lo + 64)
        ids = np.full(hi - lo, body)
        v, _ = pose_anny(src, pop, skel, placed, ids, q[lo:hi], frames_a)
        verts[lo:hi] = v + moved.root[lo:hi, None]
    return HeldOutMotion(verts, moved.coordinates, moved.root, placed.scales[body], moved.rate)


def run(quick: bool) -> dict[str, Any]:
    """Ours and the per-frame peer on the same held-out motion; returns the figures (JSON-ready)."""
    torch.manual_seed(0)
    model = BodyModel.load()
    if quick or not FULL_TRIALS.exists():
        motion = read_bvh(TEST_CLIP, CMU_UNITS)
    else:
        motion = read_bvh(FULL_TRIALS / "cmu_131_01.bvh", CMU_UNITS)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # test data: many small calls, steadier on one thread
    data = held_out_motion(model, motion)
    torch.set_num_threads(threads)
    fitter = RegisteredFitter(model)
    seq = SequenceFitter(fitter)
    seq.fit(data.vertices)  # warm-up: a whole clip's first allocations, as in a long-lived process
    # The fitter spreads each chunk's frames over its own threads (SequenceConfig.workers, one per core), so
    # torch runs one thread per op, as the scan benchmark does; torch's default threads are measured too.
    torch.set_num_threads(1)
    start_cpu = time.process_time()
    fit = seq.fit(data.vertices)
    cpu = time.process_time() - start_cpu
    torch.set_num_threads(threads)
    default_threads = seq.fit(data.vertices).stats.fps
    n_peer = min(len(data.vertices), 48 if quick else 120)
    t0 = time.perf_counter()
    peer = fitter.fit(data.vertices[:n_peer])
    peer_s = time.perf_counter() - t0
    peer_err = np.array([r.distances.mean for r in peer.reports])
    ours_err = np.array([r.distances.mean for r in fit.reports])
    s = fit.stats
    # a moving sequence of many frames: its jitter is defined (None only for < 3 frames or a still input)
    assert s.jitter_input_mm is not None and s.jitter_fit_mm is not None and s.jitter_ratio is not None
    return {
        "seq_frames": s.frames,
        "seq_torch_threads": 1,
        "seq_workers": seq.config.workers,
        "seq_fps": round(s.fps, 1),
        "seq_fps_torch_default_threads": round(default_threads, 1),
        "seq_torch_default_threads": threads,
        "seq_cpu_ms_per_frame": round(cpu * 1000 / s.frames, 2),
        "seq_mm": round(s.mean_mm, 3),
        "seq_mm_max_frame": round(float(ours_err.max()), 3),
        "seq_jitter_input_mm": round(s.jitter_input_mm, 4),
        "seq_jitter_fit_mm": round(s.jitter_fit_mm, 4),
        "seq_jitter_ratio": round(s.jitter_ratio, 3),
        "seq_limit_violations": int(sum(r.limit_violations for r in fit.reports)),
        "seq_peer_frames": n_peer,
        "seq_peer_fps": round(n_peer / peer_s, 1),
        "seq_peer_mm": round(float(peer_err.mean()), 3),
        "seq_peer_mm_same_frames_ours": round(float(ours_err[:n_peer].mean()), 3),
        "seq_peer_jitter_ratio": round(jitter(peer.vertices) / jitter(data.vertices[:n_peer]), 3),
        "seq_targets_met": bool(s.fps >= TARGET_FPS and s.mean_mm <= TARGET_MM and s.jitter_ratio <= 1.0),
    }


def main(argv: list[str] | None = None) -> None:
    from bench_cli import bench_main  # benchmarks/ is on sys.path when this runs as a script

    bench_main(run, __doc__.split("\n")[0], "the tests' clip instead of a whole trial", argv)


if __name__ == "__main__":
    main()
