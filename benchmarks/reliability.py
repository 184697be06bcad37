"""Reliability benchmark: a real server on 127.0.0.1 under hostile input and a mixed soak, and whether
this environment is the lock's.

What is measured
----------------
* ``fresh_lock_matches``: every package pinned in requirements/lock.txt is installed at exactly the pinned
  version (``lock_mismatches`` lists the others).
* ``startup_s``: from starting ``bodyfit serve`` (default settings: the scan helper process included) to
  /readyz answering 200.
* Hostile corpus (``benchmarks/hostile.py``, more than 100 generated files and requests: zip bombs, lying
  .npy headers, pickles, truncated and garbage files in every scan format, huge declared counts, NaN / inf,
  degenerate geometry, wrong units, keys and types) sent one at a time over REST, and the file cases also
  over gRPC. Per case: the answer (``hostile_4xx``: a client error; ``hostile_5xx``: anything else that
  answered; ``hostile_hangs``: no answer in 30 s), its time, and the growth of the server's peak resident
  memory over its resident memory before the case (the peak is reset before each case). After every case
  the server must still answer /readyz.
* Soak: a warm-up that sends every well-formed request below once, then ``soak_requests`` mixed requests,
  one at a time: synthesis in every format and batch size (some
  with the skeleton), registered-mesh fits, short sequence fits and upgrades, model info, 10% hostile cases
  and some NDJSON fits and upgrades whose connection is closed after the first event (cancelled). The
  server's resident memory after the warm-up against its value at the end, each read 2 s after the last
  request (the server trims freed memory about once a second):
  ``soak_rss_growth_pct``; ``soak_errors_5xx`` counts 5xx answers to the well-formed requests.
* Targets: hostile_5xx = 0, hostile_hangs = 0, hostile_cases >= 100, hostile_max_s <= 1,
  hostile_max_rss_growth_mb <= 200, soak_rss_growth_pct <= 10, fresh_lock_matches.

Usage::

    python benchmarks/reliability.py [--quick] [--json]
"""

from __future__ import annotations

import platform
import random
import re
import time
from collections.abc import Callable
from functools import partial
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from benchmarks.bench_cli import bench_main
from benchmarks.hostile import Answer, Case, amass, corpus, npz, send_grpc, send_rest
from benchmarks.server_process import ROOT, ServerProcess, start_server

LOCK = ROOT / "requirements" / "lock.txt"


def lock_mismatches(lock: Path = LOCK) -> list[str]:
    """``name: installed X, locked Y`` for every pinned package not installed at its pinned version."""
    wrong = []
    for name, pinned in re.findall(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)", lock.read_text(), re.M):
        try:
            have = version(name)
        except PackageNotFoundError:
            have = "missing"
        if have != pinned:
            wrong.append(f"{name}: installed {have}, locked {pinned}")
    return wrong


def run_hostile(server: ServerProcess, cases: list[Case]) -> tuple[list[Answer], list[float]]:
    """Send every case over REST (and gRPC where it has a gRPC form); return the answers and each case's
    peak memory growth (MiB). Raises RuntimeError when the server stops answering /readyz."""
    import grpc

    from bodyfit.api import bodyfit_pb2_grpc as pb_grpc

    answers: list[Answer] = []
    growth: list[float] = []
    channel = grpc.insecure_channel(server.target, options=[("grpc.max_send_message_length", 512 * 2**20)])
    stub = pb_grpc.BodyfitStub(channel)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        for case in cases:
            sends: list[tuple[str, Callable[[], Answer]]] = []
            if case.data or case.grpc_request is None:
                sends.append(("rest", partial(send_rest, http, case)))
            if case.grpc:
                sends.append(("grpc", partial(send_grpc, stub, case)))
            for transport, send in sends:
                answer, grown = server.peak_growth(send)
                growth.append(grown)
                answers.append(answer)
                if not server.ready():
                    raise RuntimeError(f"the server stopped being ready after {case.name} over {transport}")
    channel.close()
    return answers, growth


def _legit_requests(n_vertices: int, rng: np.random.Generator) -> list[tuple[str, dict[str, Any]]]:
    """Well-formed requests of every kind (kind, httpx.post keyword arguments)."""
    from bodyfit.models.body.model import BodyModel

    model = BodyModel.load()
    q = np.zeros((4, model.skeleton.n_dof))
    q[:, model.skeleton.dof_index("knee_angle_r")] = [0.2, 0.5, 0.8, 1.1]
    with_root = np.tile([0.0, 0.95, 0.0], (4, 1))
    frames = model.forward(np.zeros((4, model.n_shape)), q, with_root).vertices.detach().numpy()
    assert frames.shape[1] == n_vertices
    out: list[tuple[str, dict[str, Any]]] = []
    for fmt in ("npz", "ply", "obj", "glb", "json"):
        out.append(("synthesize", {"json": {"coordinates": {"knee_angle_r": 0.7}, "format": fmt}}))
    for batch in (1, 16, 64, 256):
        out.append(("synthesize", {"json": {"batch": batch, "skeleton": batch <= 16, "format": "npz"}}))
    out.append(("synthesize-glb-256", {"json": {"batch": 256, "skeleton": True, "format": "glb"}}))
    out.append(("fit-registered", {"files": {"file": ("mesh.npz", npz(points=frames[0]))}}))
    out.append(("fit-sequence", {"files": {"file": ("seq.npz", npz(frames=frames.astype(np.float32)))}}))
    out.append(("upgrade", {"files": {"file": ("motion.npz", npz(**amass(frames=8)))}}))
    out.append(("model", {}))
    return out


PATHS = {
    "synthesize": "/v1/synthesize",
    "synthesize-glb-256": "/v1/synthesize",
    "fit-registered": "/v1/fit/scan",
    "fit-sequence": "/v1/fit/sequence",
    "upgrade": "/v1/upgrade",
}
SETTLE_S = 2.0  # before reading memory: the server trims freed memory about once a second


def _send(http: httpx.Client, kind: str, kwargs: dict[str, Any], cancel: bool) -> int:
    """One well-formed request; with ``cancel``, an NDJSON one whose connection is closed after its first
    event. Returns the HTTP status."""
    if kind == "model":
        return int(http.get("/v1/model").status_code)
    if not cancel:
        return int(http.post(PATHS[kind], **kwargs).status_code)
    with http.stream("POST", PATHS[kind], headers={"accept": "application/x-ndjson"}, **kwargs) as r:
        next(r.iter_lines(), None)
        return int(r.status_code)


def soak(server: ServerProcess, n: int, hostile: list[Case], seed: int = 0) -> dict[str, Any]:
    """A warm-up (every well-formed request once), then ``n`` mixed requests one at a time (see the module
    docstring); the server's memory after each, once it has settled."""
    pick = random.Random(seed)
    legit = _legit_requests(13_348, np.random.default_rng(seed))
    streamed = [r for r in legit if r[0] in ("fit-sequence", "upgrade")]
    errors_5xx = cancelled = hostile_sent = 0
    began = time.perf_counter()
    with httpx.Client(base_url=server.url, timeout=120) as http:
        for kind, kwargs in legit:
            errors_5xx += _send(http, kind, kwargs, False) >= 500
        time.sleep(SETTLE_S)
        rss_warm = server.rss_mb()
        for _ in range(n):
            roll = pick.random()
            if roll < 0.10:
                send_rest(http, pick.choice(hostile))
                hostile_sent += 1
                continue
            cancel = roll < 0.13
            kind, kwargs = pick.choice(streamed if cancel else legit)
            cancelled += cancel
            errors_5xx += _send(http, kind, kwargs, cancel) >= 500
        time.sleep(SETTLE_S)
        rss_end = server.rss_mb()
    return {
        "soak_requests": n,
        "soak_hostile": hostile_sent,
        "soak_cancelled": cancelled,
        "soak_errors_5xx": errors_5xx,
        "soak_rss_warm_mb": round(rss_warm, 1),
        "soak_rss_end_mb": round(rss_end, 1),
        "soak_rss_growth_pct": round(100.0 * (rss_end - rss_warm) / rss_warm, 2),
        "soak_s": round(time.perf_counter() - began, 1),
    }


def run(quick: bool) -> dict[str, Any]:
    wrong = lock_mismatches()
    cases = corpus(bomb_mb=1200 if quick else 2048)
    server = start_server()
    try:
        result: dict[str, Any] = {
            "machine": f"{platform.processor() or platform.machine()}, {__import__('os').cpu_count()} CPUs",
            "fresh_lock_matches": not wrong,
            "lock_mismatches": wrong,
            "startup_s": round(server.startup_s, 2),
        }
        answers, growth = run_hostile(server, cases)
        bad = [a for a in answers if not a.refused]
        result.update(
            {
                "hostile_cases": len(answers),
                "hostile_4xx": sum(a.refused for a in answers),
                "hostile_5xx": sum(not a.refused and a.code != "timeout" for a in answers),
                "hostile_hangs": sum(a.code == "timeout" for a in answers),
                "hostile_max_s": round(max(a.seconds for a in answers), 3),
                "hostile_slowest": max(answers, key=lambda a: a.seconds).case,
                "hostile_max_rss_growth_mb": round(max(growth), 1),
                "hostile_not_refused": [f"{a.transport} {a.case}: {a.code} {a.detail[:120]}" for a in bad],
            }
        )
        result.update(soak(server, 200 if quick else 1000, cases))
    finally:
        server.stop()
    result["targets_met"] = bool(
        result["hostile_5xx"] == 0
        and result["hostile_hangs"] == 0
        and result["hostile_cases"] >= 100
        and result["hostile_max_s"] <= 1.0
        and result["hostile_max_rss_growth_mb"] <= 200
        and result["soak_rss_growth_pct"] <= 10
        and result["fresh_lock_matches"]
    )
    return result


def _show(result: dict[str, Any]) -> None:
    for key, value in result.items():
        if isinstance(value, list):
            print(f"{key:>28}: {len(value)}")
            for line in value:
                print(f"{'':>30}{line}")
        else:
            print(f"{key:>28}: {value}")


def main(argv: list[str] | None = None) -> None:
    bench_main(
        run,
        "Hostile inputs, a mixed soak and the lock, against a real server on 127.0.0.1.",
        "200 soak requests and smaller zip bombs (about 2 minutes)",
        argv,
        show=_show,
    )


if __name__ == "__main__":
    main()
