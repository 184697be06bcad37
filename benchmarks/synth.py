"""Body model forward pass benchmark: our body model against anny, on CPU in float32, in one run.

What is measured
----------------
* Inputs: random valid parameter sets (fixed seed), prepared before timing. Ours: shape coefficients
  ~ N(0, 1), every coordinate uniform within its range (``skeleton.ranges``), root translation ~ N(0, 0.1 m).
  anny: every phenotype in ``phenotype_labels`` uniform in [0, 1]; pose parameters are per-bone rigid
  deltas (B, n_bones, 4, 4) in anny's default "local-ref" parameterization: identity translations and
  small random rotations (``matrix_exp`` of skew matrices, 0.2 rad std per axis).
* Ours, torch: ``BodyModel.decoder(torch.float32)`` (vertices, joints, frames, scales) under
  ``torch.inference_mode`` with torch's default thread count.
* Ours, ONNX Runtime: the shipped ``body.onnx`` (vertices, joints) in a CPUExecutionProvider session with
  ``intra_op_num_threads = os.cpu_count()`` and ``ORT_ENABLE_ALL`` graph optimisations.
* anny: ``anny.Anny()`` (0.6.x, full body, float32) forward under ``torch.inference_mode``; its first
  calls compile or load warp kernels, so every path gets warm-up calls before it is timed.
* Speed: median wall time (ms) of one call, over timed repeats after warm-up, at B=1 and B=64. The three
  paths take turns in rounds of a few calls (the first of each round untimed), so a slow spell of the
  machine falls on all of them alike.
* Ratios: anny ms / ours ONNX ms at B=1 (latency) and at B=64 (throughput: how many times more bodies
  per second ours delivers); above 1 means ours is faster.
* Parity: the largest absolute difference (m) between ONNX Runtime (float32) and our torch forward in
  float64 (``BodyModel.forward``), over all vertex and joint coordinates of 1,000 random parameter sets,
  in batches of 100.
* Targets: ONNX B=1 at most 1.5 ms, and both ratios at least 5.

Usage::

    python benchmarks/synth.py                 # full timing repeats (a few minutes at most)
    python benchmarks/synth.py --quick         # fewer repeats (well under a minute on 2 cores)
    python benchmarks/synth.py --json          # the last line of stdout is one JSON object with the figures
    python benchmarks/synth.py --assets DIR    # load body.npz / body.onnx from DIR instead of assets/
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
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bodyfit.models.assets import verified_asset
from bodyfit.models.body.model import BodyModel
from bodyfit.models.body.onnx_export import BODY_ONNX

REPO = Path(__file__).resolve().parents[1]
BATCHES = (1, 64)
PARITY_BATCH = 100
ROOT_STD_M = 0.1
ANNY_ROTATION_STD_RAD = 0.2
TARGET_ONNX_MS_B1 = 1.5
TARGET_RATIO = 5.0


@dataclass(frozen=True)
class Settings:
    """How much work one run does."""

    warmup: int
    repeats_b1: int
    repeats_b64: int
    n_parity: int
    seed: int
    quick: bool
    assets: Path | None


@dataclass(frozen=True)
class BodyInputs:
    """Our parameters, float64 numpy: ``shape`` (N, n_shape), ``q`` (N, n_dof), ``root`` (N, 3)."""

    shape: np.ndarray
    q: np.ndarray
    root: np.ndarray

    def rows(self, start: int, stop: int) -> BodyInputs:
        return BodyInputs(self.shape[start:stop], self.q[start:stop], self.root[start:stop])

    def feed(self) -> dict[str, np.ndarray]:
        """ONNX Runtime inputs (float32, contiguous)."""
        return {
            name: np.ascontiguousarray(a, np.float32)
            for name, a in (("shape", self.shape), ("coordinates", self.q), ("root", self.root))
        }


@dataclass(frozen=True)
class Results:
    """The figures one run reports (also the JSON payload)."""

    quick: bool
    seed: int
    assets: str
    n_vertices_ours: int
    n_joints_ours: int
    n_vertices_anny: int
    n_bones_anny: int
    torch_ms_b1: float
    torch_ms_b64: float
    onnx_ms_b1: float
    onnx_ms_b64: float
    anny_ms_b1: float
    anny_ms_b64: float
    ratio_b1: float
    ratio_b64: float
    onnx_parity_max_m: float
    n_parity: int
    targets_met: bool
    machine: str
    cpu_model: str
    cpu_count: int | None
    load_avg_1min: float
    torch_threads: int
    onnx_threads: int
    torch_version: str
    onnxruntime_version: str
    anny_version: str


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="fewer timing repeats (CI-sized)")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON object last")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the inputs (default 0)")
    parser.add_argument(
        "--assets", type=Path, default=None, metavar="DIR", help="asset folder (default: the built-in assets)"
    )
    return parser.parse_args(argv)


def settings_for(args: argparse.Namespace) -> Settings:
    warmup, repeats_b1, repeats_b64 = (3, 50, 15) if args.quick else (5, 200, 40)
    return Settings(warmup, repeats_b1, repeats_b64, 1000, args.seed, args.quick, args.assets)


# -- machine --------------------------------------------------------------------------------------------
def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo, else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load_average() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


# -- inputs ---------------------------------------------------------------------------------------------
def sample_body_inputs(model: BodyModel, n: int, rng: np.random.Generator) -> BodyInputs:
    """Shape ~ N(0, 1), coordinates uniform within range, root ~ N(0, ROOT_STD_M)."""
    lo, hi = model.skeleton.ranges[:, 0], model.skeleton.ranges[:, 1]
    return BodyInputs(
        shape=rng.standard_normal((n, model.n_shape)),
        q=rng.uniform(lo, hi, size=(n, model.skeleton.n_dof)),
        root=rng.normal(0.0, ROOT_STD_M, size=(n, 3)),
    )


def random_rigid_deltas(batch: int, n_bones: int, rng: np.random.Generator) -> torch.Tensor:
    """(B, n_bones, 4, 4) float32 rigid transforms: small random rotations, no translation."""
    w = torch.as_tensor(rng.normal(0.0, ANNY_ROTATION_STD_RAD, size=(batch, n_bones, 3)))
    zero = torch.zeros_like(w[..., 0])
    x, y, z = w.unbind(-1)
    skew = torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2
    )
    deltas = torch.eye(4, dtype=torch.float64).repeat(batch, n_bones, 1, 1)
    deltas[..., :3, :3] = torch.linalg.matrix_exp(skew)
    return deltas.to(torch.float32)


def random_phenotypes(labels: list[str], batch: int, rng: np.random.Generator) -> dict[str, torch.Tensor]:
    """Every phenotype uniform in [0, 1]: label -> (B,) float32."""
    values = torch.as_tensor(rng.uniform(0.0, 1.0, size=(len(labels), batch)), dtype=torch.float32)
    return dict(zip(labels, values.unbind(0), strict=True))


# -- models ---------------------------------------------------------------------------------------------
def load_anny() -> tuple[Any, str]:
    """anny's full-body model in float32 (kernel caches under build/cache/), and anny's version."""
    os.environ.setdefault("ANNY_CACHE_DIR", str(REPO / "build" / "cache" / "anny"))
    os.environ.setdefault("WARP_CACHE_PATH", str(REPO / "build" / "cache" / "warp"))
    import warp

    warp.config.log_level = warp.LOG_WARNING  # keep warp's start-up and kernel-cache banners off stdout
    import anny

    return anny.Anny().to(torch.float32), str(anny.__version__)


def onnx_session(folder: Path | None) -> Any:
    """ONNX Runtime session on the shipped body.onnx: CPU, all cores, all graph optimisations."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = os.cpu_count() or 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    path = verified_asset(BODY_ONNX, folder)
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


# -- calls ----------------------------------------------------------------------------------------------
def torch_call(model: BodyModel, inputs: BodyInputs) -> Callable[[], None]:
    """A closure running our float32 torch decoder once on ``inputs`` (converted beforehand)."""
    decoder = model.decoder(torch.float32)
    shape, q, root = (torch.as_tensor(a, dtype=torch.float32) for a in (inputs.shape, inputs.q, inputs.root))

    def run() -> None:
        with torch.inference_mode():
            decoder(shape, q, root)

    return run


def onnx_call(session: Any, inputs: BodyInputs) -> Callable[[], None]:
    """A closure running body.onnx once on ``inputs`` (converted beforehand)."""
    feed = inputs.feed()

    def run() -> None:
        session.run(None, feed)

    return run


def anny_call(model: Any, batch: int, rng: np.random.Generator) -> Callable[[], None]:
    """A closure running anny's forward once on ``batch`` random bodies (inputs built beforehand)."""
    pose = random_rigid_deltas(batch, len(model.bone_labels), rng)
    phenotypes = random_phenotypes(list(model.phenotype_labels), batch, rng)

    def run() -> None:
        with torch.inference_mode():
            model(pose_parameters=pose, phenotype_kwargs=phenotypes)

    return run


# -- measurement ----------------------------------------------------------------------------------------
def interleaved_medians(
    fns: dict[str, Callable[[], None]], warmup: int, repeats: int, burst: int = 5
) -> dict[str, float]:
    """Median wall time (ms) of one call of each function, over ``repeats`` timed calls each.

    After ``warmup`` calls each, the functions take turns in rounds: per round each runs one untimed call
    (its caches were just used by the others) and then up to ``burst`` timed calls. A slow spell of a
    shared machine then falls on every path alike and the ratios stay fair.
    """
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    while any(len(t) < repeats for t in times.values()):
        for name, fn in fns.items():
            fn()
            for _ in range(min(burst, repeats - len(times[name]))):
                start = time.perf_counter()
                fn()
                times[name].append(time.perf_counter() - start)
    return {name: 1000.0 * statistics.median(t) for name, t in times.items()}


def onnx_parity(model: BodyModel, session: Any, inputs: BodyInputs) -> float:
    """Largest |ONNX float32 - torch float64| (m) over vertices and joints, in batches of PARITY_BATCH."""
    worst = 0.0
    n = len(inputs.shape)
    for start in range(0, n, PARITY_BATCH):
        batch = inputs.rows(start, min(start + PARITY_BATCH, n))
        vertices, joints = session.run(["vertices", "joints"], batch.feed())
        with torch.inference_mode():
            ref = model.forward(batch.shape, batch.q, batch.root, dtype=torch.float64)
        worst = max(
            worst,
            float(np.abs(vertices - ref.vertices.numpy()).max()),
            float(np.abs(joints - ref.joints.numpy()).max()),
        )
    return worst


def run_benchmark(cfg: Settings) -> Results:
    import onnxruntime as ort

    load = load_average()
    rng = np.random.default_rng(cfg.seed)
    model = BodyModel.load(cfg.assets)
    session = onnx_session(cfg.assets)
    anny_model, anny_version = load_anny()

    ms: dict[str, float] = {}
    for batch in BATCHES:
        repeats = cfg.repeats_b1 if batch == 1 else cfg.repeats_b64
        inputs = sample_body_inputs(model, batch, rng)
        calls = {
            f"torch_ms_b{batch}": torch_call(model, inputs),
            f"onnx_ms_b{batch}": onnx_call(session, inputs),
            f"anny_ms_b{batch}": anny_call(anny_model, batch, rng),
        }
        ms.update(interleaved_medians(calls, cfg.warmup, repeats))
    parity = onnx_parity(model, session, sample_body_inputs(model, cfg.n_parity, rng))

    ratio_b1 = ms["anny_ms_b1"] / ms["onnx_ms_b1"]
    ratio_b64 = ms["anny_ms_b64"] / ms["onnx_ms_b64"]
    cpu, cores = cpu_model(), os.cpu_count()
    return Results(
        quick=cfg.quick,
        seed=cfg.seed,
        assets=str(cfg.assets) if cfg.assets else "built-in",
        n_vertices_ours=model.n_vertices,
        n_joints_ours=len(model.joint_names),
        n_vertices_anny=int(anny_model.template_vertices.shape[0]),
        n_bones_anny=len(anny_model.bone_labels),
        torch_ms_b1=ms["torch_ms_b1"],
        torch_ms_b64=ms["torch_ms_b64"],
        onnx_ms_b1=ms["onnx_ms_b1"],
        onnx_ms_b64=ms["onnx_ms_b64"],
        anny_ms_b1=ms["anny_ms_b1"],
        anny_ms_b64=ms["anny_ms_b64"],
        ratio_b1=ratio_b1,
        ratio_b64=ratio_b64,
        onnx_parity_max_m=parity,
        n_parity=cfg.n_parity,
        targets_met=bool(
            ms["onnx_ms_b1"] <= TARGET_ONNX_MS_B1 and ratio_b1 >= TARGET_RATIO and ratio_b64 >= TARGET_RATIO
        ),
        machine=f"{cpu}, {cores} cores",
        cpu_model=cpu,
        cpu_count=cores,
        load_avg_1min=load,
        torch_threads=torch.get_num_threads(),
        onnx_threads=cores or 1,
        torch_version=torch.__version__,
        onnxruntime_version=ort.__version__,
        anny_version=anny_version,
    )


# -- report ---------------------------------------------------------------------------------------------
def table(r: Results) -> str:
    rows = [
        ("ours, torch float32", r.torch_ms_b1, r.torch_ms_b64),
        ("ours, ONNX Runtime float32", r.onnx_ms_b1, r.onnx_ms_b64),
        (f"anny {r.anny_version}, float32", r.anny_ms_b1, r.anny_ms_b64),
    ]
    width = max(len(name) for name, _, _ in rows)
    verdict = "met" if r.targets_met else "NOT met"
    lines = [
        f"Body model forward pass, CPU float32: ours vs anny "
        f"(seed {r.seed}, {'quick' if r.quick else 'full'} run, assets: {r.assets})",
        f"machine: {r.machine}; load average {r.load_avg_1min:.2f} at start",
        f"torch {r.torch_version} with {r.torch_threads} threads; "
        f"onnxruntime {r.onnxruntime_version} with {r.onnx_threads} intra-op threads",
        f"ours: {r.n_vertices_ours} vertices + {r.n_joints_ours} joints; "
        f"anny: {r.n_vertices_anny} vertices, {r.n_bones_anny} bones",
        "",
        f"{'':<{width}}  {'B=1 ms':>10}  {'B=64 ms':>10}  {'B=64 bodies/s':>14}",
        *(f"{name:<{width}}  {b1:10.3f}  {b64:10.3f}  {64_000.0 / b64:14,.0f}" for name, b1, b64 in rows),
        "",
        f"anny / ours ONNX:  B=1 latency {r.ratio_b1:.2f}x   B=64 throughput {r.ratio_b64:.2f}x",
        f"ONNX parity vs torch float64 ({r.n_parity} parameter sets, vertices and joints): "
        f"max |diff| {r.onnx_parity_max_m:.3e} m",
        f"targets (ONNX B=1 <= {TARGET_ONNX_MS_B1} ms, both ratios >= {TARGET_RATIO:g}x): {verdict}",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    results = run_benchmark(settings_for(args))
    print(table(results), flush=True)
    if args.json:
        payload: dict[str, Any] = asdict(results)
        print(json.dumps(payload), flush=True)


if __name__ == "__main__":
    main()
