"""Our file readers, rotation helpers and retry policy against the maintained libraries, on the same files
and the same machine: the evidence behind ``docs/readers.md``.

What is measured
----------------
* Readers (C3D vs ezc3d, TRC vs OpenSim's ``TimeSeriesTableVec3``, PCD vs pypcd4, BVH vs bvhio): on every
  vendor file of ``tests/data/vendors`` (and the Kinect scan and CMU clip in ``tests/data``), whether each
  reader reads it (``*_files_ours`` / ``*_files_<lib>``: files read out of ``*_files``), whether both give
  the same values where both read it (``*_agree``: files whose arrays agree to 1e-3 in file units), and
  the time to read all the files both read (the fastest of the repeats, milliseconds) with the ratio
  ours / library (below 1: ours is faster). BVH times parse and forward kinematics of every frame to world
  positions. TRC compares millimetres (ours returns metres).
* Rotations (CPU, a batch of ``ROT_BATCH``): Rodrigues axis-angle to matrix, the geodesic angle between
  rotations (torch, float32), XYZ body-fixed Euler angles to matrices and weighted Kabsch alignment (ours
  in numpy float64, as the fitting calls them; roma in torch), ours vs roma's equivalents; and the ONNX
  export of the decoder's rotation stage (``CHAIN_JOINTS`` joints of three axes, a batch of 1,000) written
  with each, through the exporter the project uses (dynamo, opset 18): whether it exports, its node
  count, its agreement with torch and the ONNX Runtime time per batch.
* Retry policy: the cost of a call that succeeds at once, ours vs stamina and tenacity (microseconds).

A library that is not installed is skipped (its keys are absent). ezc3d, pypcd4, bvhio, stamina and
tenacity are not in the lock: install them into a separate virtual environment and name its
site-packages folder in ``BODYFIT_READER_LIBS``; it is searched after the project's own packages. OpenSim
and roma come with the ``build`` extra.

Usage::

    BODYFIT_READER_LIBS=build/readers-venv/lib/python3.11/site-packages \\
        python benchmarks/readers.py [--quick] [--json]
"""

from __future__ import annotations

import importlib
import io
import os
import platform
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
VENDORS = ROOT / "tests" / "data" / "vendors"
ROT_BATCH = 100_000
CHAIN_JOINTS = 40  # joints with three rotation axes, about our skeleton's count


def _library(name: str) -> ModuleType | None:
    """The module when it can be imported (from the environment or ``BODYFIT_READER_LIBS``), else None."""
    extra = os.environ.get("BODYFIT_READER_LIBS")
    if extra and extra not in sys.path:
        sys.path.append(extra)
    try:
        return importlib.import_module(name)
    except Exception:  # a missing or broken optional library is skipped, whatever it raises
        return None


def _best_ms(fn: Callable[[], Any], repeats: int) -> float:
    """The fastest of ``repeats`` runs, in milliseconds: on a shared machine the fastest run is the one
    least disturbed by other work, so it is the steadiest estimate of the code's own cost."""
    fn()  # warm-up: imports, allocator, torch's first-call dispatch
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times) * 1e3


def _try(fn: Callable[[], np.ndarray]) -> np.ndarray | None:
    try:
        return fn()
    except Exception:  # any refusal counts as "does not read this file"
        return None


def _agree(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None or a.shape != b.shape:
        return False
    return bool(np.allclose(a, b, atol=1e-3, equal_nan=True))


def compare(
    prefix: str,
    lib: str,
    files: list[Path],
    ours: Callable[[Path], np.ndarray],
    theirs: Callable[[Path], np.ndarray] | None,
    repeats: int,
) -> dict[str, Any]:
    """Files read by each reader, agreement and the time over the files both read. ``ours`` and
    ``theirs`` return the same array (file units and axes) for a path, or raise."""
    out: dict[str, Any] = {f"{prefix}_files": len(files)}
    mine = {f: _try(partial(ours, f)) for f in files}
    out[f"{prefix}_files_ours"] = sum(v is not None for v in mine.values())
    if theirs is None:
        return out
    ref = {f: _try(partial(theirs, f)) for f in files}
    both = [f for f in files if mine[f] is not None and ref[f] is not None]
    out[f"{prefix}_files_{lib}"] = sum(v is not None for v in ref.values())
    out[f"{prefix}_agree"] = sum(1 for f in both if _agree(mine[f], ref[f]))
    ours_ms = sum(_best_ms(partial(ours, f), repeats) for f in both)
    theirs_ms = sum(_best_ms(partial(theirs, f), repeats) for f in both)
    out[f"{prefix}_ours_ms"] = round(ours_ms, 2)
    out[f"{prefix}_{lib}_ms"] = round(theirs_ms, 2)
    out[f"{prefix}_ratio"] = round(ours_ms / theirs_ms, 3) if theirs_ms else None
    return out


def c3d_part(repeats: int) -> dict[str, Any]:
    from bodyfit.io.c3d import parse_c3d_points

    def ours(p: Path) -> np.ndarray:
        return parse_c3d_points(p.read_bytes())[1]

    ezc3d = _library("ezc3d")

    def theirs(p: Path) -> np.ndarray:
        assert ezc3d is not None
        points = ezc3d.c3d(str(p))["data"]["points"]
        if points.shape[1] == 0:
            raise ValueError("no points")
        return np.transpose(points[:3], (2, 1, 0))

    files = sorted(VENDORS.glob("c3d/*.c3d"))
    return compare("c3d", "ezc3d", files, ours, theirs if ezc3d else None, repeats)


def trc_part(repeats: int) -> dict[str, Any]:
    from bodyfit.io.mocap import UNITS, parse_trc

    def ours(p: Path) -> np.ndarray:  # millimetres, to compare with the tolerance of the other readers
        return parse_trc(p.read_text(), zeros_missing=False).positions * 1e3

    osim = _library("opensim")

    def theirs(p: Path) -> np.ndarray:
        assert osim is not None
        table = osim.TimeSeriesTableVec3(str(p))
        n, m = table.getNumRows(), table.getNumColumns()
        values = np.array([[table.getRowAtIndex(i)[j].to_numpy() for j in range(m)] for i in range(n)])
        return values * UNITS[table.getTableMetaDataAsString("Units").strip().lower()] * 1e3

    files = sorted(VENDORS.glob("trc/*.trc")) + sorted((ROOT / "tests/data/opensim_gait").glob("*.trc"))
    return compare("trc", "opensim", files, ours, theirs if osim else None, repeats)


def pcd_part(repeats: int) -> dict[str, Any]:
    from bodyfit.io.pcd import read_pcd

    def ours(p: Path) -> np.ndarray:
        return read_pcd(p.read_bytes())[0]

    pypcd4 = _library("pypcd4")

    def theirs(p: Path) -> np.ndarray:
        assert pypcd4 is not None
        return np.asarray(pypcd4.PointCloud.from_path(p).numpy(("x", "y", "z")), np.float64)

    files = [*sorted(VENDORS.glob("pcd/*.pcd")), ROOT / "tests/data/scans/pcl_template_alignment_person.pcd"]
    return compare("pcd", "pypcd4", files, ours, theirs if pypcd4 else None, repeats)


def bvh_part(repeats: int) -> dict[str, Any]:
    from bodyfit.io.bvh import read_bvh

    def ours(p: Path) -> np.ndarray:
        return read_bvh(p, units=1.0, rotation=np.eye(3)).world()[0]

    bvhio = _library("bvhio")

    def theirs(p: Path) -> np.ndarray:
        assert bvhio is not None
        root = bvhio.readAsHierarchy(str(p))
        layout = root.layout()
        frames = []
        for frame in range(bvhio.readAsBvh(str(p)).FrameCount):
            root.loadPose(frame)
            frames.append([list(joint.PositionWorld) for joint, _, _ in layout])
        return np.array(frames)

    files = [*sorted(VENDORS.glob("bvh/*.bvh")), ROOT / "tests/data/cmu_bvh/cmu_131_01_clip.bvh"]
    return compare("bvh", "bvhio", files, ours, theirs if bvhio else None, repeats)


def _rotation_inputs(n: int) -> dict[str, Any]:
    import torch

    gen = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
    angle = torch.rand(n, generator=gen) * 3.0
    source = np.random.default_rng(0).normal(size=(12, 3))
    target = np.random.default_rng(1).normal(size=(n // 100, 12, 3))
    return {
        "axis": axis,
        "angle": angle,
        "euler": np.random.default_rng(2).uniform(-1, 1, (n, 3)),
        "source": source,
        "target": target,
        "weights": np.ones(12),
    }


def rotation_part(repeats: int) -> dict[str, Any]:
    """Ours vs roma on the rotation operations the fitting uses (see the module docstring)."""
    import torch

    from bodyfit.models import rotations as ours

    roma = _library("roma")
    x = _rotation_inputs(ROT_BATCH)
    Ra = ours.axis_angle_matrix(x["axis"], x["angle"])
    Rb = ours.axis_angle_matrix(x["axis"], x["angle"] * 0.5)
    cases: dict[str, tuple[Callable[[], Any], Callable[[], Any] | None]] = {
        "rot_rodrigues": (
            lambda: ours.axis_angle_matrix(x["axis"], x["angle"]),
            (lambda: roma.rotvec_to_rotmat(x["axis"] * x["angle"][:, None])) if roma else None,
        ),
        "rot_geodesic": (
            lambda: ours.rotation_angle_between(Ra, Rb),
            (lambda: roma.rotmat_geodesic_distance(Ra, Rb)) if roma else None,
        ),
        "rot_euler_xyz": (
            lambda: ours.euler_xyz_body_fixed(x["euler"]),
            (lambda: roma.euler_to_rotmat("XYZ", torch.from_numpy(x["euler"]))) if roma else None,
        ),
        "rot_kabsch": (
            lambda: ours.kabsch(x["source"], x["target"], x["weights"]),
            (lambda: _roma_kabsch(roma, x)) if roma else None,
        ),
    }
    out: dict[str, Any] = {}
    with torch.no_grad():
        for key, (mine, theirs) in cases.items():
            out[f"{key}_ours_ms"] = round(_best_ms(mine, repeats), 3)
            if theirs is not None:
                out[f"{key}_roma_ms"] = round(_best_ms(theirs, repeats), 3)
                out[f"{key}_ratio"] = round(out[f"{key}_ours_ms"] / out[f"{key}_roma_ms"], 3)
        out["rot_rodrigues_max_diff"] = _rodrigues_diff(roma, x) if roma else None
    out.update(export_part(roma, repeats))
    return out


def _roma_kabsch(roma: Any, x: dict[str, Any]) -> Any:
    import torch

    source = torch.from_numpy(x["source"]).expand(len(x["target"]), -1, -1)
    return roma.rigid_points_registration(
        source, torch.from_numpy(x["target"]), torch.from_numpy(x["weights"])
    )


def _rodrigues_diff(roma: Any, x: dict[str, Any]) -> float:
    from bodyfit.models.rotations import axis_angle_matrix

    mine = axis_angle_matrix(x["axis"], x["angle"])
    theirs = roma.rotvec_to_rotmat(x["axis"] * x["angle"][:, None])
    return float((mine - theirs).abs().max())


def _chain_module(kind: str, roma: Any) -> Any:
    """The exported decoder's rotation stage: every joint (``CHAIN_JOINTS``) rotates about its three
    fixed unit axes in turn, angles ``q`` (B, J, 3) -> (B, J, 3, 3). Ours: Rodrigues from precomputed
    tables and products in the component-major layout, as ``SkeletonKinematics`` does; roma: its
    ``rotvec_to_rotmat`` per axis and batched matrix products."""
    import torch

    from bodyfit.models.rotations import cm_matmul
    from bodyfit.models.skeleton.kinematics import rodrigues_tables

    axes = np.random.default_rng(3).normal(size=(CHAIN_JOINTS, 3, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    outer, perp, cross = (torch.tensor(t, dtype=torch.float32) for t in rodrigues_tables(axes))
    axes_t = torch.tensor(axes, dtype=torch.float32)  # (J, axis, 3)

    class Chain(torch.nn.Module):
        def forward(self, q: torch.Tensor) -> torch.Tensor:
            if kind == "ours":
                theta = q.permute(2, 1, 0)[:, None, None]  # (axis, 1, 1, J, B)
                Rk = outer + perp * torch.cos(theta) + cross * torch.sin(theta)
                return cm_matmul(cm_matmul(Rk[0], Rk[1]), Rk[2]).permute(3, 2, 0, 1)
            Rr = [roma.rotvec_to_rotmat(axes_t[:, k] * q[..., k : k + 1]) for k in range(3)]
            return Rr[0] @ Rr[1] @ Rr[2]

    return Chain()


def export_part(roma: Any, repeats: int) -> dict[str, Any]:
    """Whether each chain exports to ONNX, its node count, and ONNX Runtime's time per batch."""
    import contextlib

    import onnx
    import onnxruntime as ort
    import torch

    from bodyfit.models.skeleton.onnx_export import export_module

    out: dict[str, Any] = {}
    q = torch.rand(ROT_BATCH // 100, CHAIN_JOINTS, 3) * 2.0 - 1.0
    for kind in ("ours", "roma") if roma else ("ours",):
        module = _chain_module(kind, roma)
        try:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                data = export_module(module, (q[:2],), ("q",), ("frame",))
        except Exception as exc:  # an export failure is the measurement
            out[f"onnx_chain_{kind}"] = f"fails: {type(exc).__name__}"
            continue
        session = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
        got = session.run(None, {"q": q.numpy()})[0]
        out[f"onnx_chain_{kind}"] = "exports"
        out[f"onnx_chain_{kind}_nodes"] = len(onnx.load_from_string(data).graph.node)
        out[f"onnx_chain_{kind}_max_diff"] = float(np.abs(got - module(q).detach().numpy()).max())
        out[f"onnx_chain_{kind}_ms"] = round(
            _best_ms(partial(session.run, None, {"q": q.numpy()}), repeats), 3
        )
    return out


def retry_part(repeats: int) -> dict[str, Any]:
    """Microseconds for a call that succeeds at once, through each retry machinery."""
    from bodyfit.clients.core.retry import RetryPolicy

    policy = RetryPolicy()
    calls = 2000

    def ours() -> None:
        for _ in range(calls):
            policy.start(idempotent=True)
            int("1")

    out: dict[str, Any] = {"retry_ours_us": round(_best_ms(ours, repeats) * 1e3 / calls, 3)}
    stamina, tenacity = _library("stamina"), _library("tenacity")
    if stamina is not None:
        wrapped = stamina.retry(on=ConnectionError, attempts=20, timeout=20.0)(lambda: int("1"))
        out["retry_stamina_us"] = round(
            _best_ms(lambda: [wrapped() for _ in range(calls)], repeats) * 1e3 / calls, 3
        )
    if tenacity is not None:
        retrying = tenacity.retry(
            stop=tenacity.stop_after_delay(20), wait=tenacity.wait_random_exponential(0.5, 5)
        )
        wrapped_t = retrying(lambda: int("1"))
        out["retry_tenacity_us"] = round(
            _best_ms(lambda: [wrapped_t() for _ in range(calls)], repeats) * 1e3 / calls, 3
        )
    return out


def run(quick: bool) -> dict[str, Any]:
    start = time.perf_counter()
    repeats = 3 if quick else 15
    out: dict[str, Any] = {
        "machine": {"cpu_count": os.cpu_count(), "python": platform.python_version(), "quick": quick},
    }
    for part in (c3d_part, trc_part, pcd_part, bvh_part, rotation_part, retry_part):
        out.update(part(repeats))
    out["seconds"] = round(time.perf_counter() - start, 1)
    return out


def main(argv: list[str] | None = None) -> None:
    from bench_cli import bench_main  # benchmarks/ is on sys.path when this runs as a script

    bench_main(
        run, "readers, rotations and retries: ours against the maintained libraries", "3 repeats", argv
    )


if __name__ == "__main__":
    main()
