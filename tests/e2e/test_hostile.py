"""End to end: the hostile corpus (``benchmarks/hostile.py``: zip bombs, lying headers, pickles, truncated
and garbage files in every format, huge declared counts, NaN / inf, degenerate geometry, wrong units, keys
and types) sent to a real server over REST and gRPC. Every case is refused with a client error whose
message is not an internal one, the server's peak memory grows by less than 200 MB for any case, and the
server is still ready after each. (How long each refusal takes is ``benchmarks/reliability.py``'s job.)"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import grpc
import httpx
import pytest

from benchmarks.hostile import Answer, Case, corpus, send_grpc, send_rest
from benchmarks.server_process import ServerProcess, start_server
from bodyfit.api import bodyfit_pb2_grpc as pb_grpc

# Caps lowered so that the zip bombs can stay small to make: 512 MB of zeros against a 256 MB cap.
CASES = corpus(bomb_mb=512)
MAX_GROWTH_MB = 200.0


@pytest.fixture(scope="module")
def server() -> Iterator[ServerProcess]:
    env = {"BODYFIT_MAX_DECOMPRESSED_MB": "256", "BODYFIT_SCAN_PROCESSES": "1", "BODYFIT_QUEUE_SECONDS": "60"}
    process = start_server(env)
    yield process
    process.stop()


@pytest.fixture(scope="module")
def http(server: ServerProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=60) as client:
        yield client


@pytest.fixture(scope="module")
def stub(server: ServerProcess) -> Iterator[Any]:
    channel = grpc.insecure_channel(server.target, options=[("grpc.max_send_message_length", 64 * 2**20)])
    yield pb_grpc.BodyfitStub(channel)
    channel.close()


def _check(server: ServerProcess, answer: Answer, growth_mb: float) -> None:
    assert answer.code != "timeout", f"{answer.case}: no answer in time"
    assert answer.refused, f"{answer.case} over {answer.transport}: {answer.code} {answer.detail}"
    assert "Internal error" not in answer.detail and "Traceback" not in answer.detail, answer.detail
    assert growth_mb < MAX_GROWTH_MB, f"{answer.case}: the server's peak memory grew {growth_mb:.0f} MB"
    assert server.ready(), f"the server is not ready after {answer.case}"


def test_the_corpus_is_large_and_covers_every_endpoint() -> None:
    assert len(CASES) >= 100
    assert {c.endpoint for c in CASES} == {"scan", "sequence", "upgrade", "synthesize"}
    assert {c.filename.rsplit(".", 1)[-1] for c in CASES if c.endpoint == "scan"} >= {
        "ply",
        "obj",
        "stl",
        "pcd",
        "npz",
    }
    assert sum(c.grpc for c in CASES) >= 100


@pytest.mark.parametrize("case", [c for c in CASES if c.data], ids=lambda c: c.name)
def test_rest_refuses(server: ServerProcess, http: httpx.Client, case: Case) -> None:
    _check(server, *server.peak_growth(lambda: send_rest(http, case)))


@pytest.mark.parametrize("case", [c for c in CASES if c.grpc], ids=lambda c: c.name)
def test_grpc_refuses(server: ServerProcess, stub: Any, case: Case) -> None:
    _check(server, *server.peak_growth(lambda: send_grpc(stub, case, timeout_s=60.0)))
