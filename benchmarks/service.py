"""Service benchmark: synthesize latency and throughput over REST and gRPC on loopback, plus error
handling and memory under bad input, against the same synthesis called in process.

What is measured
----------------
* A real server (``bodyfit serve`` in a subprocess, REST + gRPC on 127.0.0.1, ``--threads 1``, upload
  limit 4 MiB) is started and waited for (``/readyz``).
* The load generators run in this process, on the same 2 cores as the server, so whatever CPU they
  spend is taken from the server and shows in its latency.
* Load: C concurrent clients each send ``synthesize`` requests for one body (16 fixed random poses and
  shapes, npz response without faces) until the level's request count or time budget is spent; C = 1, 8
  and 32. REST: C asyncio tasks, each writing prebuilt HTTP/1.1 requests on its own keep-alive
  connection (a lean load generator, as wrk or hey: about 0.1 ms of client CPU per request); for
  comparison the same load from one ``httpx.AsyncClient`` at C = 8 (``rest_httpx_*``: httpx costs about
  1 ms of CPU per request, and on 2 shared cores that shows in the tail) and the SDK's ``Client`` at
  C = 1 (``rest_sdk_*``). gRPC: C threads with one ``GrpcClient`` each.
  Reported per level and transport: p50 / p99 latency (ms), throughput (requests/s), errors.
* In-process baseline: ``BodyService.synthesize`` + npz encoding, one thread, median ms: what the wire,
  the framework and the concurrency add to is ``rest_p50_ms_c1 / inproc_ms``.
* Bad input: a bounded corpus of malformed requests (garbage JSON, unknown DOFs, NaN, out-of-range values,
  truncated uploads, 5 MiB uploads over the limit) sent repeatedly after the load; every one must get a
  4xx (counted otherwise in ``errors``); the server's resident memory (from /metrics) before and after
  the barrage is reported (``rss_growth_mb``: flat means no leak on refused input).
* The client threads share the machine's cores with the server, as on any loopback test.
* Target: p99 <= 20 ms at 8 clients for one mesh on 2 cores; zero errors.

Usage::

    python benchmarks/service.py [--quick] [--json]
"""

from __future__ import annotations

import os
import platform
import re
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from benchmarks.server_process import start_server

ROOT = Path(__file__).resolve().parents[1]
LEVELS = (1, 8, 32)


def requests_for(n_dof: int, ranges: np.ndarray, n_shape: int) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(0)
    return [
        {
            "shape": rng.normal(size=(1, n_shape)),
            "coordinates": rng.uniform(ranges[:, 0] * 0.5, ranges[:, 1] * 0.5, (1, n_dof)),
        }
        for _ in range(16)
    ]


def load(
    make_call: Callable[[], Callable[[dict[str, np.ndarray]], Any]],
    params: list[dict[str, np.ndarray]],
    clients: int,
    count: int,
    seconds: float,
) -> dict[str, float]:
    """``clients`` threads, each with its own call from ``make_call()``, send ``count // clients``
    requests at most, within ``seconds``."""
    latencies: list[float] = []
    errors = [0]
    lock = threading.Lock()
    per_client = max(1, count // clients)
    stop = time.monotonic() + seconds

    def worker(k: int) -> None:
        call = make_call()
        call(params[k % len(params)])  # connection set-up, not timed
        mine = []
        for i in range(per_client):
            if time.monotonic() > stop:
                break
            t = time.perf_counter()
            try:
                call(params[(k + i) % len(params)])
            except Exception as exc:
                with lock:
                    errors[0] += 1
                    if errors[0] <= 3:
                        print(f"request failed: {type(exc).__name__}: {exc}", file=sys.stderr)
                continue
            mine.append(time.perf_counter() - t)
        with lock:
            latencies.extend(mine)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(clients)]
    began = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return summary(latencies, time.perf_counter() - began, errors[0])


def rest_load(
    url: str, params: list[dict[str, np.ndarray]], clients: int, count: int, seconds: float
) -> dict[str, float]:
    """REST load from ``clients`` asyncio tasks, each on its own keep-alive connection, writing prebuilt
    HTTP/1.1 requests and reading the ``Content-Length`` answer (what wrk or hey do: the generator's CPU
    stays small next to the server's on the shared cores). Anything but a 200 counts as an error."""
    import asyncio

    host, port = url.removeprefix("http://").rsplit(":", 1)
    requests = [
        b"POST /v1/synthesize HTTP/1.1\r\nHost: %s\r\nContent-Type: application/json\r\n"
        b"Content-Length: %d\r\n\r\n" % (host.encode(), len(body)) + body
        for body in _json_bodies(params)
    ]
    latencies: list[float] = []
    errors = 0

    async def exchange(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, request: bytes) -> bool:
        writer.write(request)
        await writer.drain()
        head = await reader.readuntil(b"\r\n\r\n")
        length = re.search(rb"(?im)^content-length:\s*(\d+)", head)
        await reader.readexactly(int(length.group(1)) if length else 0)
        return head.startswith(b"HTTP/1.1 200 ")

    async def worker(k: int) -> None:
        nonlocal errors
        reader, writer = await asyncio.open_connection(host, int(port))
        try:
            await exchange(reader, writer, requests[k % len(requests)])  # connection set-up, not timed
            stop = time.monotonic() + seconds
            for i in range(max(1, count // clients)):
                if time.monotonic() > stop:
                    break
                t = time.perf_counter()
                try:
                    ok = await exchange(reader, writer, requests[(k + i) % len(requests)])
                except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                    errors += 1
                    return
                if ok:
                    latencies.append(time.perf_counter() - t)
                else:
                    errors += 1
        finally:
            writer.close()

    async def main() -> float:
        began = time.perf_counter()
        await asyncio.gather(*(worker(k) for k in range(clients)))
        return time.perf_counter() - began

    wall = asyncio.run(main())
    return summary(latencies, wall, errors)


def httpx_load(
    url: str, params: list[dict[str, np.ndarray]], clients: int, count: int, seconds: float
) -> dict[str, float]:
    """The same load from asyncio tasks sharing one ``httpx.AsyncClient`` pool: what a Python caller sees
    with httpx on the same cores (its own CPU included)."""
    import asyncio

    bodies = _json_bodies(params)
    headers = {"content-type": "application/json"}
    latencies: list[float] = []
    errors = 0

    async def main() -> float:
        nonlocal errors
        limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
        async with httpx.AsyncClient(base_url=url, limits=limits, timeout=30) as http:
            stop = time.monotonic() + seconds

            async def worker(k: int) -> None:
                nonlocal errors
                await http.post("/v1/synthesize", content=bodies[k % len(bodies)], headers=headers)
                for i in range(max(1, count // clients)):
                    if time.monotonic() > stop:
                        break
                    t = time.perf_counter()
                    try:
                        r = await http.post(
                            "/v1/synthesize", content=bodies[(k + i) % len(bodies)], headers=headers
                        )
                        ok = r.status_code == 200
                    except httpx.HTTPError:
                        ok = False
                    if ok:
                        latencies.append(time.perf_counter() - t)
                    else:
                        errors += 1

            began = time.perf_counter()
            await asyncio.gather(*(worker(k) for k in range(clients)))
            return time.perf_counter() - began

    wall = asyncio.run(main())
    return summary(latencies, wall, errors)


def _json_bodies(params: list[dict[str, np.ndarray]]) -> list[bytes]:
    """The synthesize request bodies the SDK would send, encoded once."""
    import json

    from bodyfit.clients.rest_client import synth_body

    return [
        json.dumps(synth_body(p["shape"], p["coordinates"], None, False, "npz", False, None)).encode()
        for p in params
    ]


def summary(latencies: list[float], wall: float, errors: int) -> dict[str, float]:
    ms = np.array(latencies) * 1000.0
    return {
        "p50_ms": float(np.percentile(ms, 50)) if len(ms) else float("nan"),
        "p99_ms": float(np.percentile(ms, 99)) if len(ms) else float("nan"),
        "rps": len(ms) / wall,
        "requests": len(ms),
        "errors": errors,
    }


def rest_call(url: str) -> Callable[[], Callable[[dict[str, np.ndarray]], Any]]:
    from bodyfit.clients.rest_client import Client

    def make() -> Callable[[dict[str, np.ndarray]], Any]:
        client = Client(url, retries=0)
        return lambda p: client.synthesize(shape=p["shape"], coordinates=p["coordinates"])

    return make


def grpc_call(target: str) -> Callable[[], Callable[[dict[str, np.ndarray]], Any]]:
    from bodyfit.clients.grpc_client import GrpcClient

    def make() -> Callable[[dict[str, np.ndarray]], Any]:
        client = GrpcClient(target)
        return lambda p: client.synthesize(shape=p["shape"], coordinates=p["coordinates"])

    return make


def resident_mb(url: str) -> float:
    text = httpx.get(f"{url}/metrics", timeout=5).text
    match = re.search(r"^process_resident_memory_bytes ([0-9.e+]+)$", text, re.M)
    return float(match.group(1)) / 2**20 if match else float("nan")


def bad_inputs(url: str, rounds: int) -> dict[str, float]:
    """Send the malformed corpus ``rounds`` times; count answers that are not 4xx problem documents."""
    truncated = b"ply\nformat binary_little_endian 1.0\nelement vertex 100000\nproperty float x\nend_header\n"
    corpus: list[dict[str, Any]] = [
        {"json": {"coordinates": {"knee_angel_r": 1.0}}},
        {"json": {"coordinates": {"knee_angle_r": 9.0}}},
        {"json": {"shape": [[0.0] * 3]}},
        {"json": {"unknown": 1}},
        {"content": b"{garbage", "headers": {"content-type": "application/json"}},
        {"content": b'{"root": [[NaN, 0, 0]]}', "headers": {"content-type": "application/json"}},
    ]
    uploads: list[dict[str, Any]] = [
        {"files": {"file": ("scan.ply", truncated)}},
        {"files": {"file": ("scan.ply", os.urandom(5 * 2**20))}},
        {"files": {"file": ("scan.npz", b"PK\x03\x04" + os.urandom(1000))}},
    ]
    wrong = 0
    sent = 0
    with httpx.Client(base_url=url, timeout=30) as http:
        for _ in range(rounds):
            for kwargs in corpus:
                r = http.post("/v1/synthesize", **kwargs)
                wrong += not (
                    400 <= r.status_code < 500 and r.headers["content-type"].startswith("application/problem")
                )
                sent += 1
            for kwargs in uploads:
                r = http.post("/v1/fit/scan", **kwargs)
                wrong += not (400 <= r.status_code < 500)
                sent += 1
    return {"bad_requests": sent, "bad_not_4xx": wrong}


def in_process_ms(params: list[dict[str, np.ndarray]], repeats: int) -> float:
    from bodyfit.service.core import BodyService, SynthRequest
    from bodyfit.service.formats import encode_bodies

    service = BodyService.load(threads=1, fitters=False)
    times = []
    for i in range(repeats):
        p = params[i % len(params)]
        t = time.perf_counter()
        encode_bodies(service.synthesize(SynthRequest(p["shape"], p["coordinates"])), "npz")
        times.append(time.perf_counter() - t)
    return float(np.median(times[5:]) * 1000.0)


def run(quick: bool) -> dict[str, Any]:
    from bodyfit.clients.rest_client import Client

    server = start_server({"BODYFIT_MAX_UPLOAD_MB": "4", "BODYFIT_THREADS": "1"})
    url, target = server.url, server.target
    try:
        info = Client(url).model_info()
        params = requests_for(len(info.dof_names), info.dof_ranges, info.n_shape)
        count, seconds = (400, 10.0) if quick else (3000, 60.0)
        result: dict[str, Any] = {
            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
        }
        result["inproc_ms"] = in_process_ms(params, 60 if quick else 300)
        errors = 0
        runs: list[tuple[str, int, Callable[[int], dict[str, float]]]] = [
            ("rest_sdk", 1, lambda c: load(rest_call(url), params, c, count // 4, seconds)),
            *(("rest", c, lambda c: rest_load(url, params, c, count, seconds)) for c in LEVELS),
            ("rest_httpx", 8, lambda c: httpx_load(url, params, c, count, seconds)),
            *(("grpc", c, lambda c: load(grpc_call(target), params, c, count, seconds)) for c in LEVELS),
        ]
        for name, c, measure in runs:
            stats = measure(c)
            errors += int(stats["errors"])
            for key in ("p50_ms", "p99_ms", "rps"):
                result[f"{name}_{key}_c{c}"] = round(stats[key], 3)
        bad_inputs(url, 1)  # warm-up: first-use allocations are not growth
        mem_before = resident_mb(url)
        bad = bad_inputs(url, 5 if quick else 40)
        mem_after = resident_mb(url)
        result.update(bad)
        result["errors"] = errors + bad["bad_not_4xx"]
        result["rss_mb_before"], result["rss_mb_after"] = round(mem_before, 1), round(mem_after, 1)
        result["rss_growth_mb"] = round(mem_after - mem_before, 1)
        result["rest_overhead_ratio_c1"] = round(result["rest_p50_ms_c1"] / result["inproc_ms"], 2)
        result["target_p99_ms_c8"] = 20.0
        result["met"] = bool(
            result["rest_p99_ms_c8"] <= 20.0 and result["grpc_p99_ms_c8"] <= 20.0 and result["errors"] == 0
        )
        return result
    finally:
        server.stop()


def main(argv: list[str] | None = None) -> None:
    from benchmarks.bench_cli import bench_main

    bench_main(
        run, "Service latency, throughput and bad-input handling (REST and gRPC).", "fewer requests", argv
    )


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
