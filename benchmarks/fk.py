"""Forward kinematics benchmark: our batched torch FK against OpenSim 4.6, on the same poses, in one run.

What is measured
----------------
* Poses: ``N`` random poses (fixed seed). Every DOF that Rajagopal2015 has (``Coordinate.rajagopal``) is
  drawn uniformly within its range; our extension DOFs (thorax, neck, scapulae) stay 0, so our skeleton
  reduces to Rajagopal2015. The root translation (pelvis_tx/ty/tz) is uniform in [-1, 1]^3 m.
* Accuracy: each pose is set in OpenSim (``OpenSimReference``: coordinates set, ``realizePosition``) and
  the ground transforms of every body that exists in Rajagopal2015 (OpenSim's body set decides) are
  compared with our FK in float64: the largest position error (m, Euclidean) and the largest rotation
  error (rad, geodesic angle between the two rotations) over all poses and bodies.
* OpenSim speed: poses per second of a Python loop that, per pose, sets the coordinates, realizes the
  position stage and reads every body transform into a numpy array (as a Python user has to).
* Our speed, float32 under ``torch.inference_mode`` with torch's default thread count: poses per second
  for a loop of single-pose calls (B=1, inputs already tensors) and for one batched call (B=1024, the
  same poses cycled). Every speed is the median of several timed repeats after warm-up runs.
* Ratios are ours / OpenSim (above 1: ours is faster).

Usage::

    python benchmarks/fk.py            # 1000 accuracy poses, full timing repeats
    python benchmarks/fk.py --quick    # 200 poses, fewer repeats (well under 2 minutes on 2 cores)
    python benchmarks/fk.py --json     # the last line of stdout is one JSON object with the figures
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from bodyfit.models.rotations import rotation_angle_between
from bodyfit.models.skeleton.model import Skeleton
from bodyfit.models.skeleton.opensim_reference import OpenSimReference, pose_values
from bodyfit.models.skeleton.rajagopal import rajagopal_osim_path

BATCH = 1024


@dataclass(frozen=True)
class Settings:
    """How much work one run does."""

    n_poses: int
    warmup: int
    repeats: int
    seed: int
    quick: bool


@dataclass(frozen=True)
class Poses:
    """Sampled poses: ``q`` (N, n_dof) in our DOF order, ``root`` (N, 3); float64."""

    q: np.ndarray
    root: np.ndarray


@dataclass(frozen=True)
class Results:
    """The figures one run reports (also the JSON payload)."""

    n_poses: int
    quick: bool
    seed: int
    n_bodies_compared: int
    max_pos_err_m: float
    max_rot_err_rad: float
    opensim_fps: float
    ours_fps_b1: float
    ours_fps_b1024: float
    ratio_b1: float
    ratio_b1024: float
    onnx_fps_b1: float
    ratio_onnx_b1: float
    onnx_parity_max_m: float
    processor: str
    cpu_count: int | None
    torch_threads: int
    torch_version: str


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="200 poses and fewer repeats (CI-sized)")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON object last")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the poses (default 0)")
    return parser.parse_args(argv)


def settings_for(quick: bool, seed: int) -> Settings:
    if quick:
        return Settings(n_poses=200, warmup=1, repeats=3, seed=seed, quick=True)
    return Settings(n_poses=1000, warmup=2, repeats=7, seed=seed, quick=False)


# -- poses --------------------------------------------------------------------------------------------
def rajagopal_dofs(skel: Skeleton) -> list[int]:
    """Indices of the DOFs that Rajagopal2015 has, with the same name and meaning."""
    return [i for i, c in enumerate(skel.spec.coordinates) if c.rajagopal]


def sample_poses(skel: Skeleton, n: int, seed: int) -> Poses:
    """Uniform within range for Rajagopal DOFs, 0 for our extension DOFs, root uniform in [-1, 1]^3."""
    rng = np.random.default_rng(seed)
    q = np.zeros((n, skel.n_dof))
    idx = rajagopal_dofs(skel)
    lo, hi = skel.ranges[idx, 0], skel.ranges[idx, 1]
    q[:, idx] = rng.uniform(lo, hi, size=(n, len(idx)))
    root = rng.uniform(-1.0, 1.0, size=(n, 3))
    return Poses(q, root)


# -- OpenSim --------------------------------------------------------------------------------------------
def load_reference() -> OpenSimReference:
    """Rajagopal2015 in OpenSim, with its logger quietened (missing-geometry warnings go to stdout)."""
    import opensim

    opensim.Logger.setLevelString("error")
    return OpenSimReference(rajagopal_osim_path())


def shared_bodies(skel: Skeleton, ref: OpenSimReference) -> list[str]:
    """Our bodies that Rajagopal2015 also has (all but our extension bodies), in our order."""
    body_set = ref.model.getBodySet()
    return [name for name in skel.body_names if body_set.contains(name)]


def opensim_pose_dicts(skel: Skeleton, poses: Poses) -> list[dict[str, float]]:
    """Per pose, name -> value of every Rajagopal coordinate (extension DOFs are not in OpenSim)."""
    idx = rajagopal_dofs(skel)
    names = [skel.dof_names[i] for i in idx]
    root_names = [c.name for c in skel.spec.root_coordinates]
    return [pose_values(names, q[idx], root_names, r) for q, r in zip(poses.q, poses.root, strict=True)]


def opensim_frames(ref: OpenSimReference, values: list[dict[str, float]], bodies: list[str]) -> np.ndarray:
    """The OpenSim loop: set coordinates, realize position, read the body transforms. (N, n_b, 4, 4)."""
    out = np.empty((len(values), len(bodies), 4, 4))
    for k, pose in enumerate(values):
        ref.set_coordinates(pose)
        out[k] = ref.body_frames(bodies)
    return out


def opensim_loop(
    ref: OpenSimReference, values: list[dict[str, float]], bodies: list[str]
) -> Callable[[], None]:
    """A closure running the OpenSim loop once over all poses."""

    def run() -> None:
        opensim_frames(ref, values, bodies)

    return run


# -- ours -----------------------------------------------------------------------------------------------
def our_frames(skel: Skeleton, poses: Poses, dtype: torch.dtype) -> torch.Tensor:
    """Our FK of all poses in one batch: (N, n_body, 4, 4)."""
    fk = skel.kinematics(dtype)
    with torch.inference_mode():
        q = torch.as_tensor(poses.q, dtype=dtype)
        root = torch.as_tensor(poses.root, dtype=dtype)
        return fk(q, root).frames


def single_pose_loop(skel: Skeleton, poses: Poses) -> Callable[[], None]:
    """A closure running our float32 FK once per pose, B=1 (inputs converted beforehand)."""
    fk = skel.kinematics(torch.float32)
    qs = torch.as_tensor(poses.q, dtype=torch.float32).split(1)
    roots = torch.as_tensor(poses.root, dtype=torch.float32).split(1)

    def run() -> None:
        with torch.inference_mode():
            for q, root in zip(qs, roots, strict=True):
                fk(q, root)

    return run


def batched_call(skel: Skeleton, poses: Poses, batch: int) -> Callable[[], None]:
    """A closure running our float32 FK once on ``batch`` poses (the sampled poses, cycled)."""
    fk = skel.kinematics(torch.float32)
    rows = np.arange(batch) % len(poses.q)
    q = torch.as_tensor(poses.q[rows], dtype=torch.float32)
    root = torch.as_tensor(poses.root[rows], dtype=torch.float32)

    def run() -> None:
        with torch.inference_mode():
            fk(q, root)

    return run


def onnx_single_pose_loop(skel: Skeleton, poses: Poses) -> tuple[Callable[[], None], float]:
    """A closure running the exported FK in ONNX Runtime once per pose (B=1, float32), and the largest
    position difference (m) between ONNX Runtime and torch over all poses in one batch."""
    import onnxruntime as ort

    from bodyfit.models.skeleton.onnx_export import export_fk_onnx

    fk = skel.kinematics(torch.float32)
    options = ort.SessionOptions()
    options.log_severity_level = 3
    sess = ort.InferenceSession(export_fk_onnx(fk), options, providers=["CPUExecutionProvider"])
    q = poses.q.astype(np.float32)
    root = poses.root.astype(np.float32)
    ones = np.ones((len(q), len(skel.segments), 3), np.float32)
    frames, _ = sess.run(None, {"coordinates": q, "root": root, "scales": ones})
    with torch.inference_mode():
        ref = fk(torch.as_tensor(q), torch.as_tensor(root)).frames.numpy()
    parity = float(np.abs(frames[..., :3, 3] - ref[..., :3, 3]).max())
    feeds = [
        {"coordinates": q[i : i + 1], "root": root[i : i + 1], "scales": ones[i : i + 1]}
        for i in range(len(q))
    ]

    def run() -> None:
        for feed in feeds:
            sess.run(None, feed)

    return run, parity


# -- measurement ----------------------------------------------------------------------------------------
def accuracy(ours: torch.Tensor, reference: np.ndarray) -> tuple[float, float]:
    """Largest position error (m) and geodesic rotation error (rad) between two (N, n_b, 4, 4) stacks."""
    ref = torch.as_tensor(reference, dtype=ours.dtype)
    pos = torch.linalg.vector_norm(ours[..., :3, 3] - ref[..., :3, 3], dim=-1)
    rot = rotation_angle_between(ours[..., :3, :3], ref[..., :3, :3])
    return float(pos.max()), float(rot.max())


def rate(fn: Callable[[], None], items: int, warmup: int, repeats: int) -> float:
    """Items per second of ``fn``: the median over ``repeats`` timed calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return items / statistics.median(times)


def run_benchmark(cfg: Settings) -> Results:
    skel = Skeleton.load()
    ref = load_reference()
    bodies = shared_bodies(skel, ref)
    body_idx = [skel.body_names.index(b) for b in bodies]
    poses = sample_poses(skel, cfg.n_poses, cfg.seed)
    values = opensim_pose_dicts(skel, poses)

    reference = opensim_frames(ref, values, bodies)
    pos_err, rot_err = accuracy(our_frames(skel, poses, torch.float64)[:, body_idx], reference)

    n = cfg.n_poses
    opensim_fps = rate(opensim_loop(ref, values, bodies), n, cfg.warmup, cfg.repeats)
    ours_b1 = rate(single_pose_loop(skel, poses), n, cfg.warmup, cfg.repeats)
    ours_batch = rate(batched_call(skel, poses, BATCH), BATCH, cfg.warmup + 3, cfg.repeats * 5)
    onnx_loop, onnx_parity = onnx_single_pose_loop(skel, poses)
    onnx_b1 = rate(onnx_loop, n, cfg.warmup, cfg.repeats)
    return Results(
        n_poses=n,
        quick=cfg.quick,
        seed=cfg.seed,
        n_bodies_compared=len(bodies),
        max_pos_err_m=pos_err,
        max_rot_err_rad=rot_err,
        opensim_fps=opensim_fps,
        ours_fps_b1=ours_b1,
        ours_fps_b1024=ours_batch,
        ratio_b1=ours_b1 / opensim_fps,
        ratio_b1024=ours_batch / opensim_fps,
        onnx_fps_b1=onnx_b1,
        ratio_onnx_b1=onnx_b1 / opensim_fps,
        onnx_parity_max_m=onnx_parity,
        processor=platform.processor() or platform.machine(),
        cpu_count=os.cpu_count(),
        torch_threads=torch.get_num_threads(),
        torch_version=torch.__version__,
    )


# -- report ---------------------------------------------------------------------------------------------
def table(r: Results) -> str:
    rows = [
        ("OpenSim 4.6 (set + realizePosition + read)", f"{r.opensim_fps:14,.0f}", "1.00x"),
        ("ours, torch float32, B=1 loop", f"{r.ours_fps_b1:14,.0f}", f"{r.ratio_b1:.2f}x"),
        (f"ours, torch float32, B={BATCH}", f"{r.ours_fps_b1024:14,.0f}", f"{r.ratio_b1024:.2f}x"),
        ("ours, ONNX Runtime float32, B=1 loop", f"{r.onnx_fps_b1:14,.0f}", f"{r.ratio_onnx_b1:.2f}x"),
    ]
    width = max(len(name) for name, _, _ in rows)
    lines = [
        f"Forward kinematics, Rajagopal2015 poses ({r.n_poses} poses, seed {r.seed}, "
        f"{'quick' if r.quick else 'full'} run)",
        f"machine: {r.processor}, {r.cpu_count} CPUs, torch {r.torch_version} with {r.torch_threads} threads",
        "",
        f"{'':<{width}}  {'frames/s':>14}  {'vs OpenSim':>10}",
        *(f"{name:<{width}}  {fps}  {ratio:>10}" for name, fps, ratio in rows),
        "",
        f"accuracy vs OpenSim (float64, {r.n_bodies_compared} bodies x {r.n_poses} poses):",
        f"  max position error  {r.max_pos_err_m:.3e} m",
        f"  max rotation error  {r.max_rot_err_rad:.3e} rad",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    results = run_benchmark(settings_for(args.quick, args.seed))
    print(table(results), flush=True)
    if args.json:
        payload: dict[str, Any] = asdict(results)
        print(json.dumps(payload), flush=True)


if __name__ == "__main__":
    main()
